"""Gaussian-process regression of one calibration stage with known (dense) and learned noise.

The target covariance is ``K(theta) + N + noise_variance * I`` with ``N`` a known noise
(:mod:`cascal.noise`, dense for stage B of a cascade) and ``noise_variance`` learned or fixed.
:func:`fit_gp` maximises the log marginal likelihood (GPML eq. 2.30) over the
log-hyperparameters and returns a frozen :class:`FittedGP` whose predictions use stored
weights: O(M N) for the mean, O(M N^2) only when uncertainty is asked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack, solve_triangular

from . import linalg
from .errors import InputError
from .kernels import Kernel, Periodic, _Scaled, make_kernel
from .means import Mean, make_mean
from .noise import Noise, as_noise
from .optimize import OptimResult, maximize
from .validation import as_positions, check_pair

__all__ = ["FittedGP", "Objective", "Posterior", "fit_gp", "log_marginal_likelihood"]

_LOG2PI = np.log(2.0 * np.pi)
_CHUNK = 32768
_BLAS: list = []


def single_threaded_blas():
    """Context limiting BLAS to one thread: small GP matrices run faster and bit-reproducibly."""
    if not _BLAS:
        from threadpoolctl import ThreadpoolController

        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


@dataclass(frozen=True, slots=True)
class Posterior:
    """Posterior of the latent map at some positions: mean (m,) and covariance (m, m)."""

    mean: np.ndarray
    cov: np.ndarray

    @property
    def std(self) -> np.ndarray:
        """Standard deviations, shape (m,)."""
        return np.sqrt(np.clip(np.diagonal(self.cov), 0.0, None))


class Objective:
    """Log marginal likelihood of one data set as a function of log-hyperparameters.

    ``theta`` is ``[kernel.theta, log noise_variance]`` (the last only when the noise
    variance is learned). With ``profile=True`` (a scaled kernel and no known noise) the
    kernel variance is maximised out in closed form and ``theta`` is
    ``[log length_scale, log(noise_variance / variance)]``; :meth:`full_theta` maps back.
    """

    def __init__(
        self,
        x: np.ndarray,
        r: np.ndarray,
        kernel: Kernel,
        known: Noise | None,
        learn_noise: bool,
        profile: bool = False,
    ) -> None:
        self.x, self.r, self.kernel = x, r, kernel
        self.n = len(x)
        self.d = np.subtract.outer(x, x)
        self.learn_noise = learn_noise
        self.known = known
        self.known_matrix = None if known is None else known.dense(self.n)
        self.profile = bool(profile)
        if self.profile and not (isinstance(kernel, _Scaled) and known is None and learn_noise):
            raise ValueError("profiling needs a scaled kernel, no known noise, learned noise")

    @property
    def dim(self) -> int:
        if self.profile:
            return 2
        return self.kernel.n_params + int(self.learn_noise)

    def _factor(self, Kt: np.ndarray) -> np.ndarray:
        L, info = lapack.dpotrf(Kt, lower=1, clean=1)
        if info != 0:
            L, _ = linalg.cholesky(Kt)
        return L

    def matrix(self, theta: np.ndarray, grad: bool = False):
        """Target covariance (n, n) and, with ``grad``, its derivatives (p, n, n)."""
        theta = np.asarray(theta, dtype=float)
        if self.profile:
            raise ValueError("a profiled objective has no full matrix; use full_theta first")
        p = self.kernel.n_params
        K, dK = self.kernel.with_theta(theta[:p])._eval(self.d, grad)
        if self.known_matrix is not None:
            K = K + self.known_matrix
        if self.learn_noise:
            sn2 = np.exp(theta[p])
            K = K.copy() if self.known_matrix is None else K
            K.flat[:: self.n + 1] += sn2
        return K, dK

    def value(self, theta: np.ndarray) -> float:
        """Log marginal likelihood at ``theta`` (profiled, if so built)."""
        return self.value_and_grad(theta, grad=False)[0]

    def value_and_grad(self, theta: np.ndarray, grad: bool = True) -> tuple[float, np.ndarray]:
        """Log marginal likelihood and its gradient with respect to ``theta``."""
        if self.profile:
            return self._profiled(np.asarray(theta, dtype=float), grad)
        n, r = self.n, self.r
        Kt, dK = self.matrix(theta, grad)
        L = self._factor(Kt)
        alpha = linalg.cho_solve(L, r)
        lml = -0.5 * float(r @ alpha) - 0.5 * linalg.logdet(L) - 0.5 * n * _LOG2PI
        if not grad:
            return lml, np.empty(0)
        # GPML eq. 5.9: d lml / d theta_j = 1/2 tr((alpha alpha^T - Kt^-1) dKt/dtheta_j)
        W = np.outer(alpha, alpha) - linalg.inverse_from_cholesky(L)
        g = [0.5 * float(np.vdot(W, dKj)) for dKj in dK]
        if self.learn_noise:
            g.append(0.5 * np.exp(theta[-1]) * float(np.trace(W)))
        return lml, np.asarray(g)

    def _profiled(self, theta: np.ndarray, grad: bool) -> tuple[float, np.ndarray]:
        # Kt = s2 (R + g I); s2 maximised out: s2 = r^T A^-1 r / n with A = R + g I.
        n, r = self.n, self.r
        k = self.kernel.unit(float(np.exp(theta[0])))  # type: ignore[attr-defined]
        rho, drho = k.correlation(self.d, grad)
        g = np.exp(theta[1])
        A = rho  # freshly computed: safe to add the diagonal in place
        A.flat[:: n + 1] += g
        L = self._factor(A)
        alpha = linalg.cho_solve(L, r)
        q = float(r @ alpha)
        lml = -0.5 * n * (np.log(q / n) + 1.0 + _LOG2PI) - 0.5 * linalg.logdet(L)
        if not grad:
            return lml, np.empty(0)
        Ainv = linalg.inverse_from_cholesky(L)
        c = 0.5 * n / q
        gl = c * float(alpha @ drho @ alpha) - 0.5 * float(np.vdot(Ainv, drho))
        gg = g * (c * float(alpha @ alpha) - 0.5 * float(np.trace(Ainv)))
        return lml, np.array([gl, gg])

    def full_theta(self, theta: np.ndarray) -> np.ndarray:
        """``[kernel.theta, log noise_variance]`` from a (possibly profiled) ``theta``."""
        theta = np.asarray(theta, dtype=float)
        if not self.profile:
            return theta
        n = self.n
        k = self.kernel.with_theta(np.array([theta[0], 0.0]))
        A = k(self.x)
        A.flat[:: n + 1] += np.exp(theta[1])
        L = self._factor(A)
        s2 = float(self.r @ linalg.cho_solve(L, self.r)) / n
        return np.array([theta[0], np.log(s2), theta[1] + np.log(s2)])

    def bounds(self, user: dict[str, tuple[float, float]] | None = None) -> np.ndarray:
        """Finite log-space bounds (dim, 2) scaled to the data; ``user`` overrides by name."""
        x, r = self.x, self.r
        span = float(np.ptp(x)) or 1.0
        gaps = np.diff(np.unique(x))
        gap = float(gaps.min()) if gaps.size else span
        v = float(np.var(r)) or float(np.mean(r**2)) or 1.0
        if self.known_matrix is not None:
            v = max(v, float(np.mean(np.diagonal(self.known_matrix))))
        rows: dict[str, tuple[float, float]] = {}
        for name in self.kernel.names:
            base = name.split("_", 1)[1] if name.startswith(("k1_", "k2_")) else name
            if base == "length_scale":
                periodic = isinstance(self.kernel, Periodic)
                rows[name] = (1e-2, 1e2) if periodic else (max(0.5 * gap, 1e-4 * span), 1e2 * span)
            elif base == "variance":
                rows[name] = (1e-6 * v, 1e4 * v)
            else:
                rows[name] = (1e-6 * v, 1e4 * v)
        rows["noise_variance"] = (1e-10 * v, 10.0 * v)
        for name, lohi in (user or {}).items():
            if name not in rows:
                raise InputError(f"bounds: unknown hyperparameter {name!r}; known: {list(rows)}")
            rows[name] = lohi
        if self.profile:
            (l_lo, l_hi) = rows["length_scale"]
            out = [(l_lo, l_hi), (1e-10, 10.0)]
        else:
            out = [rows[name] for name in self.kernel.names]
            if self.learn_noise:
                out.append(rows["noise_variance"])
        b = np.log(np.asarray(out, dtype=float))
        if not np.all(np.isfinite(b)) or np.any(b[:, 0] > b[:, 1]):
            raise InputError(f"bounds: expected 0 < lower <= upper, got {out}")
        return b


def log_marginal_likelihood(
    x: object,
    y: object,
    *,
    kernel: Kernel,
    mean: str | float | Mean = "identity",
    noise: float | np.ndarray | Noise | None = None,
    noise_variance: float = 0.0,
    eval_gradient: bool = False,
) -> float | tuple[float, np.ndarray]:
    """log p(y | x) of a GP (GPML eq. 2.30 with the target covariance in place of s^2 I).

    Args:
        x: Positions, shape (n,).
        y: Targets, shape (n,), same unit.
        kernel: Kernel with its hyperparameters.
        mean: Prior mean (see :func:`cascal.means.make_mean`).
        noise: Known noise: number, (n,), (n, n) or a :class:`~cascal.noise.Noise`.
        noise_variance: Learned white-noise variance added on top.
        eval_gradient: Also return d lml / d [kernel.theta, log noise_variance], shape (p+1,).
    """
    xa, ya = check_pair(x, y)
    m = make_mean(mean, ya)
    obj = Objective(xa, ya - m(xa), kernel, as_noise(noise, len(xa)), learn_noise=True)
    theta = np.r_[kernel.theta, np.log(max(noise_variance, 1e-300))]
    if noise_variance == 0.0:
        obj.learn_noise = False
        theta = kernel.theta
    v, g = obj.value_and_grad(theta, grad=eval_gradient)
    return (v, g) if eval_gradient else v


@dataclass(frozen=True, slots=True)
class FittedGP:
    """A fitted stage: training data, hyperparameters and the stored Cholesky factor.

    Attributes:
        x: Training positions, shape (n,).
        y: Training targets, shape (n,).
        kernel: Kernel at the fitted hyperparameters.
        mean: Prior mean.
        noise: Known noise (or None).
        noise_variance: Learned (or fixed) white-noise variance, target unit squared.
        L: Lower Cholesky factor of the target covariance, shape (n, n).
        alpha: Weights ``Kt^-1 (y - m(x))``, shape (n,).
        jitter: Jitter added to the target covariance's diagonal (0.0 if none).
        log_marginal_likelihood: At the fitted hyperparameters.
        optimization: Per-start diagnostics, or None when hyperparameters were given.
    """

    x: np.ndarray
    y: np.ndarray
    kernel: Kernel
    mean: Mean
    noise: Noise | None
    noise_variance: float
    L: np.ndarray
    alpha: np.ndarray
    jitter: float
    log_marginal_likelihood: float
    optimization: OptimResult | None = None

    @property
    def hyperparameters(self) -> dict[str, float]:
        """Kernel hyperparameters by name plus ``noise_variance``, natural units."""
        hp = dict(self.kernel.params)
        if isinstance(self.kernel, Periodic):
            hp["period"] = self.kernel.period
        hp["noise_variance"] = self.noise_variance
        return hp

    def predict(
        self, x: object, return_std: bool = False, return_cov: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior of the latent map at ``x`` (m,) (GPML Alg. 2.1, lines 4-6).

        Returns:
            mean (m,); with ``return_std`` also the standard deviation (m,); with
            ``return_cov`` the covariance (m, m) instead. Same unit as the targets.
        """
        if return_std and return_cov:
            raise ValueError("ask for return_std or return_cov, not both")
        xs = as_positions(x, "x")
        if return_cov:
            Ks = self.kernel(xs, self.x)
            V = solve_triangular(self.L, Ks.T, lower=True, check_finite=False)
            cov = self.kernel(xs) - V.T @ V
            return self.mean(xs) + Ks @ self.alpha, 0.5 * (cov + cov.T)
        mean = np.empty(xs.shape)
        std = np.empty(xs.shape) if return_std else None
        for s in range(0, xs.size, _CHUNK):
            part = xs[s : s + _CHUNK]
            Ks = self.kernel(part, self.x)
            mean[s : s + _CHUNK] = self.mean(part) + Ks @ self.alpha
            if std is not None:
                V = solve_triangular(self.L, Ks.T, lower=True, check_finite=False)
                var = self.kernel.diag(part) - np.einsum("ij,ij->j", V, V)
                std[s : s + _CHUNK] = np.sqrt(np.clip(var, 0.0, None))
        return (mean, std) if std is not None else mean

    def posterior(self, x: object) -> Posterior:
        """Posterior mean (m,) and full covariance (m, m) of the latent map at ``x``."""
        mean, cov = self.predict(x, return_cov=True)
        return Posterior(mean, cov)


def fit_gp(
    x: object,
    y: object,
    *,
    kernel: str | Kernel = "se",
    mean: str | float | Mean = "identity",
    noise: float | np.ndarray | Noise | None = None,
    learn_noise: bool | None = None,
    hyperparameters: dict[str, float] | None = None,
    n_restarts: int = 5,
    seed: int | np.random.Generator | None = 0,
    period: float | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
    names: tuple[str, str] = ("x", "y"),
) -> FittedGP:
    """Fit a GP to one stage: readings ``x`` (n,) mapped to more accurate readings ``y`` (n,).

    Args:
        x: Readings of the sensor being calibrated, shape (n,).
        y: Readings of the more accurate sensor, shape (n,), same unit.
        kernel: ``"se"``, ``"matern32"``, ``"matern52"``, ``"periodic"`` or a Kernel.
        mean: ``"identity"`` (default), ``"zero"``, ``"constant"`` or a number.
        noise: None (learn a scalar variance), a number or (n,) vector (known variances),
            an (n, n) covariance (known, plus a learned scalar), or a Noise.
        learn_noise: Learn a white-noise variance on top of ``noise``; default: learn it
            unless ``noise`` is a number or a vector.
        hyperparameters: Given values by name (``length_scale``, ``variance``,
            ``noise_variance``, ...); nothing is optimised.
        n_restarts: Number of L-BFGS-B starts (after screening seeded candidates).
        seed: Seed or Generator for the starts.
        period: Period of the ``"periodic"`` kernel, in the unit of ``x``.
        bounds: Optimisation bounds by hyperparameter name, natural units.
        names: Names of ``x`` and ``y`` in error messages.
    """
    with single_threaded_blas():
        return _fit_gp(
            x,
            y,
            kernel,
            mean,
            noise,
            learn_noise,
            hyperparameters,
            n_restarts,
            seed,
            period,
            bounds,
            names,
        )


def _fit_gp(
    x, y, kernel, mean, noise, learn_noise, hyperparameters, n_restarts, seed, period, bounds, names
) -> FittedGP:
    xa, ya = check_pair(x, y, names)
    n = xa.size
    kern = make_kernel(kernel, period=period)
    m = make_mean(mean, ya)
    known = as_noise(noise, n)
    if learn_noise is None:
        learn_noise = known is None or not known.is_diagonal
    if known is None and not learn_noise:
        raise InputError("noise: with learn_noise=False a known noise must be given")
    r = ya - m(xa)
    optimization = None
    if hyperparameters is not None:
        kern, sn2 = _from_dict(kern, hyperparameters, learn_noise)
    else:
        rng = np.random.default_rng(seed)
        profile = isinstance(kern, _Scaled) and known is None and learn_noise
        obj = Objective(xa, r, kern, known, learn_noise, profile=profile)
        b = obj.bounds(bounds)
        optimization = maximize(obj.value, obj.value_and_grad, b, n_restarts=n_restarts, rng=rng)
        theta = obj.full_theta(optimization.theta)
        p = kern.n_params
        kern = kern.with_theta(theta[:p])
        sn2 = float(np.exp(theta[p])) if learn_noise else 0.0
    return _condition(xa, ya, kern, m, known, sn2, optimization)


def _from_dict(kern: Kernel, hp: dict[str, float], learn_noise: bool) -> tuple[Kernel, float]:
    missing = [k for k in kern.names if k not in hp]
    if learn_noise and "noise_variance" not in hp:
        missing.append("noise_variance")
    if missing:
        raise InputError(f"hyperparameters: missing {missing}; expected {list(kern.names)}")
    vals = np.array([float(hp[k]) for k in kern.names])
    if np.any(~np.isfinite(vals)) or np.any(vals <= 0):
        raise InputError(f"hyperparameters: expected positive finite values, got {hp}")
    sn2 = float(hp.get("noise_variance", 0.0)) if learn_noise else 0.0
    if learn_noise and not (np.isfinite(sn2) and sn2 >= 0):
        raise InputError(f"hyperparameters: noise_variance must be >= 0, got {sn2}")
    return kern.with_theta(np.log(vals)), sn2


def _condition(x, y, kern, m, known, sn2, optimization) -> FittedGP:
    n = x.size
    Kt = kern(x)
    if known is not None:
        Kt = known.add_to(Kt)
    Kt.flat[:: n + 1] += sn2
    L, jitter = linalg.cholesky(Kt, what="target covariance")
    r = y - m(x)
    alpha = linalg.cho_solve(L, r)
    lml = -0.5 * float(r @ alpha) - 0.5 * linalg.logdet(L) - 0.5 * n * _LOG2PI
    return FittedGP(x, y, kern, m, known, sn2, L, alpha, jitter, lml, optimization)
