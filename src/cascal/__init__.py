"""cascal: cascaded calibration of position sensors with Gaussian processes."""

from __future__ import annotations

from . import kernels, noise, planning, screening, simulation
from ._version import __version__
from .baselines import OffsetTable, fit_table
from .cascade import Cascade, FittedCascade, Stage
from .errors import CascalError, InputError, ModelFileError, NumericalError
from .gp import FittedGP, Posterior, fit_gp, log_marginal_likelihood
from .io.modelfile import CalibrationModel, load_model, save_model
from .kernels import Constant, Matern32, Matern52, Periodic, SquaredExp
from .means import Mean
from .noise import Dense, Diagonal
from .study import run_study
from .validation import aggregate_repeats

__all__ = [
    "CalibrationModel",
    "Cascade",
    "CascalError",
    "Constant",
    "Dense",
    "Diagonal",
    "FittedCascade",
    "FittedGP",
    "InputError",
    "Matern32",
    "Matern52",
    "Mean",
    "ModelFileError",
    "NumericalError",
    "OffsetTable",
    "Periodic",
    "Posterior",
    "SquaredExp",
    "Stage",
    "__version__",
    "aggregate_repeats",
    "fit_gp",
    "fit_table",
    "kernels",
    "load_model",
    "log_marginal_likelihood",
    "noise",
    "planning",
    "run_study",
    "save_model",
    "screening",
    "simulation",
]
