"""cascal: cascaded calibration of position sensors with Gaussian processes."""

from __future__ import annotations

from .errors import CascalError, InputError, ModelFileError, NumericalError
from .gp import FittedGP, Posterior, fit_gp, log_marginal_likelihood
from .kernels import Constant, Matern32, Matern52, Periodic, SquaredExp
from .means import Mean
from .noise import Dense, Diagonal

__version__ = "0.1.0"

__all__ = [
    "CascalError",
    "Constant",
    "Dense",
    "Diagonal",
    "FittedGP",
    "InputError",
    "Matern32",
    "Matern52",
    "Mean",
    "ModelFileError",
    "NumericalError",
    "Periodic",
    "Posterior",
    "SquaredExp",
    "__version__",
    "fit_gp",
    "log_marginal_likelihood",
]
