"""The paper's Monte Carlo study: one trial per index, three methods, cost J, summaries.

A trial's randomness derives from ``(seed, index)`` alone (a :class:`numpy.random.SeedSequence`
with the index as spawn key), so results do not depend on the number of workers or on the
order in which trials finish. Nothing here does I/O; the runner in :mod:`cascal.study`
stores results and drives executors.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from functools import partial
from itertools import combinations

import numpy as np

from .baselines import fit_table
from .cascade import METHODS, Cascade
from .errors import CascalError
from .gp import FittedGP, single_threaded_blas
from .simulation import Trial, cost_j, j_reference, simulate_trial
from .tabulate import chebyshev_mean

__all__ = [
    "StudyConfig",
    "TrialResult",
    "compiled",
    "run_chunk",
    "run_trial",
    "stage_fits",
    "summarize",
    "trial_rng",
]

QUANTILES = (0.10, 0.25, 0.50, 0.75, 0.90)


@dataclass(frozen=True, slots=True)
class StudyConfig:
    """What a study computes; two runs with equal configs give identical numbers.

    Attributes:
        seed: Root seed of the study.
        n_restarts: Local searches per GP stage fit, at most: the best local maxima of
            a likelihood table over the length scale, each refined by Brent's method
            (:mod:`cascal.studyfit`; for other kernels than ``"se"``, and where that fit
            declines, the Newton runs of :func:`cascal.fit_gp`). With three, no fit of
            the benchmark's sample ends below a five-start L-BFGS-B from random starts
            (``make bench`` counts both directions).
        kernel: Kernel of every GP stage.
        methods: Methods compared in every trial.
    """

    seed: int = 0
    n_restarts: int = 3
    kernel: str = "se"
    methods: tuple[str, ...] = METHODS

    def as_dict(self) -> dict:
        d = asdict(self)
        d["methods"] = list(self.methods)
        return d


@dataclass(frozen=True, slots=True)
class TrialResult:
    """One trial: J per method (m), fitted hyperparameters, diagnostics and timings (s).

    ``fits`` maps ``"<method>/<stage>"`` to that stage's hyperparameters, log marginal
    likelihood and jitter; the stage-0 GP is shared by ``bayes`` and ``homoscedastic``.
    """

    index: int
    cost: dict[str, float]
    redraws: int
    fits: dict[str, dict[str, float]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def trial_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of trial ``index`` in a study seeded with ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(index,)))


def _fit_record(gp: FittedGP, library: bool, polished: bool | None = None) -> dict[str, float]:
    rec = {k: float(v) for k, v in gp.hyperparameters.items()}
    rec["library_fit"] = float(library)
    if polished is not None:  # (the bayes stage's compiled fit: see studyfit.noise_stage)
        rec["polished"] = float(polished)
    rec["log_marginal_likelihood"] = float(gp.log_marginal_likelihood)
    rec["jitter"] = float(gp.jitter)
    if gp.noise is not None and hasattr(gp.noise, "n_clipped"):
        rec["clipped_eigenvalues"] = float(gp.noise.n_clipped)
    return rec


def run_trial(config: StudyConfig, index: int) -> TrialResult:
    """Simulate trial ``index`` and score every method of ``config`` on it."""
    with single_threaded_blas():
        try:
            return _run_trial(config, index)
        except CascalError as exc:
            raise type(exc)(f"trial {index} (seed {config.seed}): {exc}") from exc


def stage_fits(
    config: StudyConfig, trial: Trial, seed: int
) -> tuple[FittedGP, dict[str, FittedGP]]:
    """The GP stages of ``trial`` as a study trial fits them, ``seed`` being the trial's
    fit seed: stage A's GP and, per GP method of ``config``, stage B's GP (for checks of
    the study's fits against other optimisers)."""
    fitter = _Fitter(trial, config, seed)
    fitter.stage0()  # (stage B's fits share one search: their order does not matter)
    return fitter.gp0, {m: fitter.stage1(m)[0] for m in config.methods if m != "lut"}


def _run_trial(config: StudyConfig, index: int) -> TrialResult:
    t0 = time.perf_counter()
    rng = trial_rng(config.seed, index)
    trial = simulate_trial(rng)
    fit_seed = int(rng.integers(2**63))
    reference = j_reference(trial)
    seconds = {"simulate": time.perf_counter() - t0}
    cost: dict[str, float] = {}
    fits: dict[str, dict[str, float]] = {}
    fitter = _Fitter(trial, config, fit_seed)
    if any(m != "lut" for m in config.methods):
        t = time.perf_counter()
        fits["stage0"] = fitter.stage0()
        seconds["stage_a"] = time.perf_counter() - t
    # the homoscedastic fit first: its maxima start the bayes fit's search
    for method in sorted(config.methods, key=lambda m: m != "homoscedastic"):
        t = time.perf_counter()
        if method == "lut":
            device = fitter.tables()
        else:
            device, fits[f"{method}/stage1"] = fitter.stage1(method)
        t1 = time.perf_counter()
        cost[method] = cost_j(trial, correct=fitter.correct(device), reference=reference)
        seconds[method if method == "lut" else f"{method}_stage_b"] = t1 - t
        seconds[f"{method}_cost"] = time.perf_counter() - t1
    return TrialResult(index, cost, trial.redraws, fits, seconds)


class _Fitter:
    """A trial's GP stages: the compiled fits of :mod:`cascal.studyfit` for the squared
    exponential, :class:`~cascal.cascade.Cascade` (that is :func:`cascal.fit_gp`) for other
    kernels and wherever the compiled fit declines (a maximum at a bound, say); a record's
    ``library_fit`` is 1 there."""

    def __init__(self, trial: Trial, config: StudyConfig, seed: int) -> None:
        self.trial, self.config, self.seed = trial, config, seed
        self.compiled = config.kernel == "se"
        self._chain: Cascade | None = None
        self.gp0: FittedGP | None = None
        self.posterior = None  # stage A's posterior at stage B's upper readings: (mean, factor)
        self.white = None  # the compiled white-noise fit of stage B: (gp, its search)

    @property
    def chain(self) -> Cascade:
        """The trial's two-stage chain (made where a fit is left to the library)."""
        if self._chain is None:
            self._chain = Cascade([self.trial.d2, self.trial.d1], "bayes", **self._settings())
        return self._chain

    def _settings(self) -> dict:
        c = self.config
        return {"kernel": c.kernel, "n_restarts": c.n_restarts, "seed": self.seed}

    def stage0(self) -> dict[str, float]:
        found = self._white(*self.trial.d2, branches=False)  # (never needed for stage A)
        if found is None:
            # (a stage's seed derives from (seed, stage) alone: the one-stage chain fits
            # stage A exactly as the two-stage one would)
            self.gp0 = Cascade(self.chain.stages[:1], "bayes", **self._settings()).fit().models[0]
        else:
            self.gp0 = found[0]
        return _fit_record(self.gp0, found is None)

    def stage1(self, method: str) -> tuple[FittedGP, dict[str, float]]:
        x, y = self.trial.d1
        if self.compiled and self.white is None:  # (bayes: its search starts from it)
            from .studyfit import posterior_factor

            self.posterior = posterior_factor(self.gp0, y)  # targets and factor
            self.white = self._white(x, self.posterior[0]) or False
        gp, polished = None, None
        if method == "homoscedastic" and self.white:
            gp = self.white[0]
        elif method == "bayes" and self.white:
            from .studyfit import noise_stage

            targets, factor = self.posterior
            n = self.config.n_restarts
            gp, polished = noise_stage(x, targets, factor, self.white, n) or (None, None)
        if gp is None:
            gp = self.chain.with_method(method).fit(first=self.gp0).models[1]
            return gp, _fit_record(gp, True)
        return gp, _fit_record(gp, False, polished)

    def tables(self):
        """The lookup-table method's correction, readings -> true positions: the tables
        of :meth:`Cascade.fit` (:func:`~cascal.baselines.fit_table`'s knots and offsets),
        without its checks where the readings do not repeat."""
        first = _table(*self.trial.d2, "testbed")
        x, y = self.trial.d1
        return _table(x, first(y), "device")

    def correct(self, device):
        """The device's correction as a callable readings -> true positions (J's)."""
        if not isinstance(device, FittedGP):
            return device
        if self.compiled:
            from .studyfit import corrected

            return partial(corrected, device)
        return partial(chebyshev_mean, device)

    def _white(self, x: np.ndarray, y: np.ndarray, branches: bool = True):
        if not self.compiled:
            return None
        from .studyfit import white_stage  # (Numba loads with it: only where the study runs)

        return white_stage(x, y, self.config.n_restarts, branches)


def _table(x: np.ndarray, y: np.ndarray, stage: str):
    """Readings -> ``reading + offset`` interpolated as :class:`OffsetTable` does."""
    order = np.argsort(x, kind="stable")
    knots = x[order]
    if not (knots[1:] > knots[:-1]).all():  # repeated readings: fit_table averages them
        return fit_table(x, y, _names(stage))
    offsets = (y - x)[order]
    return lambda r: r + np.interp(r, knots, offsets)


def _names(stage: str) -> tuple[str, str]:
    return (f"{stage} x", f"{stage} y")


def compiled(config: StudyConfig) -> bool:
    """Whether Numba's cache holds this machine's compiled code of the study's trials as
    ``config`` runs them (the simulator; the fits for the squared exponential) for the
    sources installed. Without it a process compiles that code at its first trial (about
    55 s, then cached). False where the cache cannot be read."""
    from . import simulation

    functions = [simulation._on_grid, simulation._newton]
    if config.kernel == "se" and any(m != "lut" for m in config.methods):
        from . import studyfit

        functions += [studyfit._search_profile, studyfit._search_dense, studyfit._factorise]
    try:  # (Numba's index of a function's cache: keyed by signature, machine, bytecode)
        from numba.core.registry import cpu_target

        codegen = cpu_target.target_context.codegen()
        magic = codegen.magic_tuple()
        return all(
            any(
                key[1] == magic and key[2] == f._cache._index_key(key[0], codegen)[2]
                for key in f._cache._cache_file._load_index()
            )
            for f in functions
        )
    except Exception:  # (another Numba's internals: then compile first, as if not cached)
        return False


def run_chunk(config: StudyConfig, indices: list[int]) -> list[TrialResult]:
    """Run several trials in one task (for executors); order follows ``indices``."""
    return [run_trial(config, i) for i in indices]


def summarize(costs: dict[str, np.ndarray]) -> dict:
    """Statistics of J per method and paired comparisons between methods.

    Args:
        costs: J per method, each of shape (n_trials,), paired by trial.

    Returns:
        ``{"n_trials", "methods": {m: {median, mean, q10, q25, q75, q90}}, "pairs":
        {"a vs b": {fraction_a_better, wilcoxon_p}}}``; the Wilcoxon signed-rank test is
        two-sided on the paired differences.
    """
    from scipy.stats import wilcoxon  # here: importing scipy.stats costs 0.5 s at start-up

    out: dict = {"n_trials": len(next(iter(costs.values()))), "methods": {}, "pairs": {}}
    for m, j in costs.items():
        j = np.asarray(j, dtype=float)
        q = np.quantile(j, QUANTILES)
        out["methods"][m] = {
            "median": float(q[2]),
            "mean": float(np.mean(j)),
            "q10": float(q[0]),
            "q25": float(q[1]),
            "q75": float(q[3]),
            "q90": float(q[4]),
        }
    for a, b in combinations(costs, 2):
        ja, jb = np.asarray(costs[a], float), np.asarray(costs[b], float)
        diff = ja - jb
        p = float(wilcoxon(ja, jb).pvalue) if np.any(diff != 0) else 1.0
        out["pairs"][f"{a} vs {b}"] = {
            "fraction_a_better": float(np.mean(ja < jb)),
            "wilcoxon_p": p,
        }
    return out
