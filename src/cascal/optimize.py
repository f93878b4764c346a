"""Seeded multi-start maximisation of a log marginal likelihood in log-hyperparameter space.

Candidates are drawn by Latin hypercube sampling inside finite log bounds and ranked by the
cheap objective (no gradient); a local optimiser then starts from the best ``n_restarts``
distinct ones (and from a given initial point, if any). A caller with better starts (the
surrogate of :mod:`cascal.surrogate`) passes them instead of the screening, and may pass
probes: points around the best optimum whose higher value starts another run. The local
optimiser is a bounded Newton method with the exact Hessian and a trust region when the
objective provides one (quadratic convergence in a handful of steps), else L-BFGS-B with
the analytic gradient.
The best optimum wins; every start is reported.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .errors import NumericalError

__all__ = ["OptimResult", "Start", "latin_hypercube", "maximize", "newton_maximize"]

#: Starts are at least this far apart in the unit box of the log bounds.
_RADIUS = 0.2
#: An optimum this close to a bound (log units) is at it: :meth:`OptimResult.at_bounds`.
BOUND_TOL = 1e-3
#: First trust radius of a Newton run, log units.
_RADIUS0 = 2.0
#: A run this close (log units, every parameter) to an optimum already found stops there.
_KNOWN = 0.01


@dataclass(frozen=True, slots=True)
class Start:
    """One local optimiser run (Newton or L-BFGS-B): where it began and ended, in log space."""

    theta0: np.ndarray
    theta: np.ndarray
    value: float
    n_evals: int
    converged: bool


@dataclass(frozen=True, slots=True)
class OptimResult:
    """Best log-hyperparameters found and the diagnostics of every start."""

    theta: np.ndarray
    value: float
    starts: tuple[Start, ...]
    n_candidates: int
    n_probes: int = 0
    bounds: np.ndarray | None = None
    names: tuple[str, ...] = ()

    def at_bounds(self, tol: float = BOUND_TOL) -> list[tuple[str, str]]:
        """``(name, "lower" | "upper")`` for every parameter of ``theta`` within ``tol`` (log
        units) of its bound: the likelihood would go on rising past it, so the bound, not
        the data, set that value. Empty when the bounds are unknown (a model file of cascal
        before 0.4.2)."""
        if self.bounds is None:
            return []
        names = self.names or tuple(f"theta[{i}]" for i in range(self.theta.size))
        out = []
        for name, t, (lo, hi) in zip(names, self.theta, self.bounds, strict=True):
            if t - lo <= tol:
                out.append((name, "lower"))
            elif hi - t <= tol:
                out.append((name, "upper"))
        return out

    @property
    def n_evals(self) -> int:
        """Objective evaluations: candidates, probes and every local optimiser evaluation."""
        return self.n_candidates + self.n_probes + sum(s.n_evals for s in self.starts)


def newton_maximize(
    value_grad_hess: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]],
    theta0: np.ndarray,
    bounds: np.ndarray,
    *,
    max_iter: int = 100,
    gtol: float = 1e-7,
    known: list[Start] | None = None,
) -> Start:
    """Maximise inside the box ``bounds`` (p, 2) by trust-region Newton steps from ``theta0``.

    Variables at a bound whose gradient points outward are held there. Where the Hessian
    is not negative definite, the step uses its eigenvalues' magnitudes (an ascent
    direction); the trust radius (log units) shrinks on failure and grows on success.
    Converges when the free gradient is below ``gtol``, the Newton decrement promises less
    than 1e-10 relative gain (or will after one more full step, which is then taken and
    checked by its value alone), or the steps stop changing the value. A run that comes within
    0.01 (log units) of an optimum in ``known`` stops there: it is converging to that optimum.
    The few parameters live in Python floats: the loop's cost is the objective's.
    ``value_grad_hess`` returns ``(f, g, H)``, or ``(f, derivatives)`` with ``derivatives()``
    giving ``(g, H)``: then a rejected step costs only the value.
    """
    lo, hi = bounds[:, 0].tolist(), bounds[:, 1].tolist()
    p = len(lo)
    theta = [
        min(max(t, a), b)
        for t, a, b in zip(np.asarray(theta0, float).tolist(), lo, hi, strict=True)
    ]
    start = np.asarray(theta0)
    try:
        f, rest = _stage(value_grad_hess, theta)
        g, H = rest()
    except NumericalError:
        return Start(start, np.array(theta), -np.inf, 1, False)
    evals, radius, converged = 1, _RADIUS0, False
    if not math.isfinite(f):
        return Start(start, np.array(theta), -np.inf, evals, False)
    others = [k.theta.tolist() for k in known or ()]
    for _ in range(max_iter):
        free = [
            i
            for i in range(p)
            if not ((theta[i] <= lo[i] and g[i] < 0) or (theta[i] >= hi[i] and g[i] > 0))
        ]
        if not free or max(abs(g[i]) for i in free) < gtol:
            converged = True
            break
        gf = [g[i] for i in free]
        sf, decrement = _ascent_step([[H[i][j] for j in free] for i in free], gf)
        tol = 2e-10 * max(1.0, abs(f))
        if decrement is not None and decrement < tol:
            converged = True  # Newton decrement: the remaining gain is round-off
            break
        # Near the top a full step squares the decrement (lambda_k+1 <= lambda_k^2 for
        # self-concordant functions; typically 0.15 lambda_k^2 on likelihoods, but up to
        # 100 lambda_k^2 on a flat stage-A ridge): a decrement whose square is below a thousandth
        # of the tolerance ends the run at its point, without the derivatives, if the value
        # rises by at least half the predicted gain.
        last = decrement is not None and decrement * decrement < 1e-3 * tol
        if any(max(abs(a - b) for a, b in zip(theta, o, strict=True)) < _KNOWN for o in others):
            converged = True
            break
        step = [0.0] * p
        for i, si in zip(free, sf, strict=True):
            step[i] = si
        norm = math.sqrt(sum(x * x for x in step))
        if norm > radius:
            step = [x * (radius / norm) for x in step]
        full = norm <= radius and all(
            a <= t + x <= b for t, x, a, b in zip(theta, step, lo, hi, strict=True)
        )
        trial = [min(max(t + x, a), b) for t, x, a, b in zip(theta, step, lo, hi, strict=True)]
        d = [a - b for a, b in zip(trial, theta, strict=True)]
        Hd = [sum(hij * dj for hij, dj in zip(row, d, strict=True)) for row in H]
        pred = sum(gi * di + 0.5 * di * hdi for gi, di, hdi in zip(g, d, Hd, strict=True))
        try:
            ft, rest = _stage(value_grad_hess, trial)
        except NumericalError:  # not factorisable there: treat as a failed step
            ft = -math.inf
        evals += 1
        gain = ft - f if math.isfinite(ft) else -math.inf
        dn = math.sqrt(sum(x * x for x in d))
        take = gain > 0 or (gain == 0 and dn == 0)
        if take and last and full and gain >= 0.25 * decrement:
            theta, f, converged = trial, ft, True
            break
        if take:
            try:
                gt, Ht = rest()  # derivatives only where the step is taken
            except NumericalError:
                take = False
        if take:
            if gain > 0.75 * pred and dn > 0.9 * radius:
                radius = min(4.0 * radius, 20.0)
            small = gain <= 1e-13 * max(1.0, abs(f))
            theta, f, g, H = trial, ft, gt, Ht
            if small and dn < 1e-7:
                converged = True
                break
        else:
            radius = 0.25 * max(dn, 1e-12)
            if radius < 1e-10:
                converged = True  # no ascent possible at this resolution
                break
    return Start(start, np.array(theta), float(f), evals, converged)


def _stage(vgh: Callable, theta: list[float]) -> tuple[float, Callable[[], tuple[list, list]]]:
    """The value at ``theta`` and a function giving (gradient, Hessian) as Python lists;
    ``vgh`` returns ``(f, g, H)``, or ``(f, derivatives)`` to defer the derivatives."""
    out = vgh(np.array(theta))
    if len(out) == 3:
        f, g, H = out
        derivatives = lambda: (g, H)  # noqa: E731
    else:
        f, derivatives = out

    def rest() -> tuple[list, list]:
        g, H = derivatives()
        return np.asarray(g, dtype=float).tolist(), np.asarray(H, dtype=float).tolist()

    return float(f), rest


def _ascent_step(H: list[list[float]], g: list[float]) -> tuple[list[float], float | None]:
    """Step ``(-H)^-1 g`` and the Newton decrement ``g^T (-H)^-1 g`` where ``H`` is clearly
    negative definite (a Cholesky factor of ``-H`` in floats); otherwise the step of the
    eigenvalues' magnitudes (floored at 1e-8 of the largest) and no decrement."""
    p = len(g)
    top = max(abs(H[i][i]) for i in range(p))
    C = [[0.0] * p for _ in range(p)]
    ok = top > 0.0
    for j in range(p):
        if not ok:
            break
        s = -H[j][j] - sum(C[j][k] * C[j][k] for k in range(j))
        if not s > 1e-8 * top:
            ok = False
            break
        C[j][j] = math.sqrt(s)
        for i in range(j + 1, p):
            C[i][j] = (-H[i][j] - sum(C[i][k] * C[j][k] for k in range(j))) / C[j][j]
    if ok:
        z = [0.0] * p
        for i in range(p):
            z[i] = (g[i] - sum(C[i][k] * z[k] for k in range(i))) / C[i][i]
        x = [0.0] * p
        for i in reversed(range(p)):
            x[i] = (z[i] - sum(C[k][i] * x[k] for k in range(i + 1, p))) / C[i][i]
        return x, sum(zi * zi for zi in z)
    lam, V = np.linalg.eigh(np.array(H))
    mag = np.maximum(np.abs(lam), 1e-8 * max(float(np.max(np.abs(lam))), 1e-300))
    proj = V.T @ np.array(g)
    return (V @ (proj / mag)).tolist(), None


def latin_hypercube(bounds: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` stratified points inside ``bounds`` (p, 2): shape (n, p)."""
    p = len(bounds)
    u = (rng.permuted(np.tile(np.arange(n), (p, 1)), axis=1).T + rng.random((n, p))) / n
    return bounds[:, 0] + u * (bounds[:, 1] - bounds[:, 0])


def maximize(
    value: Callable[[np.ndarray], float],
    value_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
    bounds: np.ndarray,
    *,
    n_restarts: int = 5,
    rng: np.random.Generator | None,
    initial: np.ndarray | None = None,
    n_candidates: int | None = None,
    value_grad_hess: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]] | None = None,
    starts: list[np.ndarray] | None = None,
    probes: list[np.ndarray] | None = None,
    names: tuple[str, ...] = (),
    fill: bool = False,
    known: tuple[Start, ...] = (),
) -> OptimResult:
    """Maximise ``value`` over the box ``bounds`` from several seeded starts.

    Args:
        value: Objective, theta (p,) -> float (non-finite means infeasible).
        value_and_grad: Objective and its gradient (p,).
        bounds: Lower and upper bounds, shape (p, 2), finite.
        n_restarts: Number of local optimiser runs (at least 1).
        rng: Source of the candidate points (None only with ``starts``).
        initial: Optional extra start, shape (p,), tried first.
        n_candidates: Screened candidates; default ``6 * n_restarts`` (at least 16).
        value_grad_hess: Objective, gradient and Hessian (p, p), or the objective and a
            function giving the other two (see :func:`newton_maximize`): enables Newton.
        starts: Start points (p,) to use instead of screened candidates (none screened);
            an empty list or None screens as usual.
        fill: With ``starts``, also screen candidates and run from the best of them up
            to ``n_restarts`` runs in all (``rng`` needed).
        probes: Offsets (p,) from the best Newton optimum (Newton only): where the
            objective is higher there, another Newton run starts there (a nearby maximum
            that approximate starts merged with the one found). One value each.
        names: Names of the parameters, kept in the result (:meth:`OptimResult.at_bounds`).
        known: Optima of runs made before (Newton only): a run that reaches one stops
            there (see :func:`newton_maximize`); they are not part of the result.

    Returns:
        The best optimum and one :class:`Start` per run.
    """
    bounds = np.asarray(bounds, dtype=float)
    n_restarts = max(int(n_restarts), 1)
    lo, width = bounds[:, 0], bounds[:, 1] - bounds[:, 0]
    width = np.where(width > 0, width, 1.0)
    hi = lo + width

    def inside(t) -> np.ndarray:
        return np.minimum(np.maximum(np.asarray(t, dtype=float), lo), hi)  # np.clip, faster

    picks = ([] if initial is None else [inside(initial)]) + [inside(t) for t in starts or ()]
    m = 0
    if not starts or fill:
        m = n_candidates if n_candidates is not None else max(6 * n_restarts, 16)
        cands = latin_hypercube(bounds, m, rng)
        scores = np.array([_safe(value, c) for c in cands])
        picks += _diverse(cands, scores, (cands - lo) / width, n_restarts - len(picks))
    if not picks:
        raise NumericalError(
            "the log marginal likelihood could not be evaluated at any candidate "
            "hyperparameters; check the data for near-duplicates and the bounds"
        )

    def neg(u: np.ndarray) -> tuple[float, np.ndarray]:
        # L-BFGS-B works on the unit box: the log-bounds of every parameter map to [0, 1].
        try:
            v, g = value_and_grad(lo + u * width)
        except NumericalError:
            v, g = -np.inf, np.zeros_like(u)
        if not np.isfinite(v):
            return 1e300, np.zeros_like(u)
        return -v, -g * width

    if value_grad_hess is not None:
        starts: list[Start] = []
        for t0 in picks:
            starts.append(newton_maximize(value_grad_hess, t0, bounds, known=[*known, *starts]))
        best = _best(starts)
        for offset in probes or ():
            t0 = inside(best.theta + offset)
            if _safe(value, t0) > best.value:
                starts.append(newton_maximize(value_grad_hess, t0, bounds, known=[*known, *starts]))
                best = _best(starts)
        return OptimResult(
            best.theta, best.value, tuple(starts), m, len(probes or ()), bounds, names
        )
    from scipy.optimize import minimize  # here: importing it costs 0.2 s at every CLI start

    unit = np.column_stack([np.zeros(len(lo)), np.ones(len(lo))])
    starts = []
    for theta0 in picks:
        res = minimize(neg, (theta0 - lo) / width, jac=True, method="L-BFGS-B", bounds=unit)
        starts.append(
            Start(
                theta0=np.asarray(theta0),
                theta=lo + np.asarray(res.x) * width,
                value=float(-res.fun),
                n_evals=int(res.nfev),
                converged=bool(res.success),
            )
        )
    best = _best(starts)
    return OptimResult(best.theta, best.value, tuple(starts), m, bounds=bounds, names=names)


def _best(starts: list[Start]) -> Start:
    best = max(starts, key=lambda s: s.value)
    if not np.isfinite(best.value):
        raise NumericalError(
            "no optimiser start reached a finite log marginal likelihood; check the data "
            "for near-duplicate positions and the hyperparameter bounds"
        )
    return best


def _diverse(cands: np.ndarray, scores: np.ndarray, unit: np.ndarray, k: int) -> list:
    """Best-scoring candidates, skipping any closer than 0.2 (unit box) to one already taken."""
    order = [i for i in np.argsort(-scores, kind="stable") if np.isfinite(scores[i])]
    taken: list[int] = []
    for i in order:
        if len(taken) == k:
            break
        if all(np.linalg.norm(unit[i] - unit[j]) > _RADIUS for j in taken):
            taken.append(i)
    for i in order:  # too few distinct regions: fill with the next best
        if len(taken) >= k:
            break
        if i not in taken:
            taken.append(i)
    return [cands[i] for i in taken]


def _safe(f: Callable[[np.ndarray], float], theta: np.ndarray) -> float:
    try:
        v = float(f(theta))
    except NumericalError:
        return -np.inf
    return v if np.isfinite(v) else -np.inf
