"""cascal: cascaded calibration of position sensors with Gaussian processes.

The public names load on first use (PEP 562), so the ``cascal`` command starts, and
answers Ctrl-C, before NumPy and SciPy are imported.
"""

from importlib import import_module as _import_module
from importlib.util import find_spec as _find_spec
from typing import TYPE_CHECKING as _TYPE_CHECKING

from ._version import __version__
from .errors import (
    CascalError,
    CascalWarning,
    DataWarning,
    InputError,
    JitterWarning,
    ModelFileError,
    NumericalError,
)

if _TYPE_CHECKING:  # pragma: no cover
    from . import kernels, noise, planning, screening, simulation
    from .baselines import OffsetTable, fit_table
    from .cascade import Cascade, FittedCascade, Stage
    from .gp import FittedGP, Posterior, fit_gp, log_marginal_likelihood
    from .io.modelfile import CalibrationModel, load_model, save_model
    from .kernels import Constant, Matern32, Matern52, Periodic, SquaredExp
    from .means import Mean
    from .noise import Dense, Diagonal
    from .study import run_study
    from .validation import aggregate_repeats

#: Public name -> the module that defines it ("" for the submodules themselves).
_WHERE = {
    **dict.fromkeys(("kernels", "noise", "planning", "screening", "simulation"), ""),
    **dict.fromkeys(("OffsetTable", "fit_table"), ".baselines"),
    **dict.fromkeys(("Cascade", "FittedCascade", "Stage"), ".cascade"),
    **dict.fromkeys(("FittedGP", "Posterior", "fit_gp", "log_marginal_likelihood"), ".gp"),
    **dict.fromkeys(("CalibrationModel", "load_model", "save_model"), ".io.modelfile"),
    **dict.fromkeys(("Constant", "Matern32", "Matern52", "Periodic", "SquaredExp"), ".kernels"),
    "Mean": ".means",
    **dict.fromkeys(("Dense", "Diagonal"), ".noise"),
    "run_study": ".study",
    "aggregate_repeats": ".validation",
}


def __getattr__(name: str) -> object:
    """A public name, or any submodule (``cascal.workflow``), imported on first use."""
    where = _WHERE.get(name)
    if where is None and not name.startswith("_") and _find_spec(f"{__name__}.{name}"):
        where = ""  # a submodule that is not public by name: as after a plain import
    if where is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = _import_module(f".{name}" if where == "" else where, __name__)
    if where:
        value = getattr(value, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({n for n in globals() if not n.startswith("_")} | set(_WHERE) | {"__version__"})


__all__ = [
    "CalibrationModel",
    "Cascade",
    "CascalError",
    "CascalWarning",
    "Constant",
    "DataWarning",
    "Dense",
    "Diagonal",
    "FittedCascade",
    "FittedGP",
    "InputError",
    "JitterWarning",
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
