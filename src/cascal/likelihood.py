"""The log marginal likelihood of one stage as a function of log-hyperparameters.

:class:`Objective` evaluates GPML eq. 2.30 with the target covariance
``K(theta) + N + noise_variance * I`` (``N`` a known, possibly dense noise), its gradient
(GPML eq. 5.9) and, for the scaled kernels, its exact Hessian for Newton steps. With the
kernel variance profiled out in closed form the search has one dimension less.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.linalg import lapack

from . import linalg
from .errors import InputError
from .kernels import Kernel, Periodic, Product, _Scaled
from .noise import Noise

__all__ = ["Objective", "noiseless"]

_LOG2PI = np.log(2.0 * np.pi)
#: Upper bound of the noise ratio (noise variance / variance) where the variance is profiled:
#: as in the box without profiling (noise up to 10, variance down to 1e-6 of the
#: corrections' variance). Readings whose noise exceeds a smooth error of theirs have their
#: optimum at ratios over 10 (32 in a review's case of 100 readings, where a cap at 10
#: left a length scale below the spacing that fitted the noise as signal).
RATIO_MAX = 1e7


def noiseless(known: Noise | None, n: int, white: float) -> bool:
    """Whether a target covariance of n points with the known noise ``known`` and a white
    noise of variance ``white`` may hold no noise in some direction: no white noise and a
    known noise whose smallest eigenvalue may be 0 (:meth:`cascal.noise.Noise.floor`):
    none at some point of its diagonal (a kernel matrix alone there), or a singular dense
    noise (a shared offset of rank 1, whatever its diagonal). Its Cholesky factor is then
    checked for pivots of round-off (:func:`cascal.linalg.pivots_ok`)."""
    return white == 0.0 and (known is None or known.floor(n) <= 0.0)


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
        self._exact = True
        self.jitter = 0.0  # added to the diagonal in the latest factorisation
        # no noise on the diagonal (a kernel matrix alone): round-off pivots count as failed
        self._noiseless = noiseless(known, self.n, 1.0 if learn_noise else 0.0)
        self._last: tuple | None = None  # (theta bytes, L, Kt^-1 r, r^T A^-1 r or None)
        if self.profile and not (isinstance(kernel, _Scaled) and known is None and learn_noise):
            raise ValueError("profiling needs a scaled kernel, no known noise, learned noise")

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the entries of ``theta`` (``noise_ratio``: noise_variance / variance)."""
        return theta_names(self.kernel, self.learn_noise, self.profile)

    @property
    def dim(self) -> int:
        if self.profile:
            return 2
        return self.kernel.n_params + int(self.learn_noise)

    def _factor(self, Kt: np.ndarray) -> np.ndarray:
        L, info = lapack.dpotrf(Kt, lower=1, clean=1)
        self._exact = info == 0 and (not self._noiseless or linalg.pivots_ok(L, Kt))
        self.jitter = 0.0
        if not self._exact:
            L, self.jitter = linalg.cholesky(Kt, noiseless=self._noiseless)
        return L

    def factor_at(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Lower Cholesky factor (n, n) of the target covariance and the weights
        ``Kt^-1 r`` (n,) at ``theta`` (as optimised: profiled or not), if the latest
        staged evaluation (:meth:`value_and_derivatives`) was there and needed no jitter;
        else None. A fit's optimum is usually its latest evaluation: this saves the
        final factorisation."""
        last = self._last_at(theta)
        if last is None:
            return None
        _, L, a, q = last
        if not self.profile:
            return L, a
        s2 = q / self.n  # Kt = s2 A: its factor sqrt(s2) L_A, its weights A^-1 r / s2
        return L * math.sqrt(s2), a / s2

    def _last_at(self, theta: np.ndarray) -> tuple | None:
        """The latest staged evaluation's record if it was at ``theta``, else None."""
        last = self._last
        if last is None or last[0] != np.asarray(theta, dtype=float).tobytes():
            return None
        return last

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
        if not q > 0.0:  # targets equal to the prior mean: no scale to profile
            return -np.inf, np.zeros(2)
        lml = -0.5 * n * (np.log(q / n) + 1.0 + _LOG2PI) - 0.5 * linalg.logdet(L)
        if not grad:
            return lml, np.empty(0)
        Ainv = linalg.inverse_from_cholesky(L)
        c = 0.5 * n / q
        gl = c * float(alpha @ drho @ alpha) - 0.5 * float(np.vdot(Ainv, drho))
        gg = g * (c * float(alpha @ alpha) - 0.5 * float(np.trace(Ainv)))
        return lml, np.array([gl, gg])

    @property
    def has_hessian(self) -> bool:
        """True when :meth:`value_grad_hess` is available (scaled kernels)."""
        return isinstance(self.kernel, _Scaled)

    def value_grad_hess(self, theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """Log marginal likelihood, gradient (p,) and exact Hessian (p, p) at ``theta``.

        Uses d^2 lml / d theta_i d theta_j = 1/2 a^T K_ij a - a^T K_i Kt^-1 K_j a
        + 1/2 tr(Kt^-1 K_i Kt^-1 K_j) - 1/2 tr(Kt^-1 K_ij), a = Kt^-1 r (K_i = dKt/dtheta_i).
        """
        lml, derivatives = self.value_and_derivatives(theta)
        return (lml, *derivatives())

    def value_and_derivatives(
        self, theta: np.ndarray
    ) -> tuple[float, Callable[[], tuple[np.ndarray, np.ndarray]]]:
        """Log marginal likelihood at ``theta`` and a function giving its gradient and
        Hessian from the same factorisation (:meth:`value_grad_hess` in two stages): an
        optimiser that rejects the point pays only for the Cholesky factor."""
        theta = np.asarray(theta, dtype=float)
        if self.profile:
            return self._profiled_staged(theta)
        n, r = self.n, self.r
        k = self.kernel.unit(math.exp(theta[0]))  # type: ignore[attr-defined]
        rho, r1, r2 = k.correlation2(self.d)
        sf2 = math.exp(theta[1])
        Kt = sf2 * rho
        if self.known_matrix is not None:
            Kt += self.known_matrix
        sn2 = math.exp(theta[2]) if self.learn_noise else 0.0
        Kt.flat[:: n + 1] += sn2
        L = self._factor(Kt)
        a = linalg.cho_solve(L, r)
        self._last = (theta.tobytes(), L, a, None) if self._exact else None
        lml = -0.5 * float(r @ a) - 0.5 * linalg.logdet(L) - 0.5 * n * _LOG2PI
        return lml, lambda: self._derivatives(L, a, rho, r1, r2, sf2, sn2)

    def _derivatives(self, L, a, rho, r1, r2, sf2: float, sn2: float) -> tuple[np.ndarray, ...]:
        n = self.n
        Kinv = linalg.inverse_from_cholesky(L)
        # dKt/dtheta: sf2 r1, sf2 rho, sn2 I; second: K_ll = sf2 r2, K_ls = sf2 r1,
        # K_ss = sf2 rho, K_nn = sn2 I, others 0. Q_i = Kt^-1 rho_i, so M_i = sf2 Q_i.
        Q1, Q2 = Kinv @ r1, Kinv @ rho
        p = 3 if self.learn_noise else 2
        V = np.empty((p, n))
        np.matmul(r1, a, out=V[0])
        np.matmul(rho, a, out=V[1])
        V[:2] *= sf2
        if p == 3:
            np.multiply(a, sn2, out=V[2])
        VKV = (V @ Kinv) @ V.T
        VKV += VKV.T
        VKV *= 0.5
        av = V @ a
        s2 = sf2 * sf2
        t1, t2 = sf2 * float(np.trace(Q1)), sf2 * float(np.trace(Q2))
        T = np.empty((p, p))
        T[0, 0] = s2 * float(np.vdot(Q1, Q1.T))
        T[0, 1] = s2 * float(np.vdot(Q1, Q2.T))
        T[1, 1] = s2 * float(np.vdot(Q2, Q2.T))
        tr = [t1, t2]
        if p == 3:
            tr.append(sn2 * float(np.trace(Kinv)))
            T[0, 2] = sf2 * sn2 * float(np.vdot(Q1, Kinv))
            T[1, 2] = sf2 * sn2 * float(np.vdot(Q2, Kinv))
            T[2, 2] = sn2 * sn2 * float(np.vdot(Kinv, Kinv))
        g = 0.5 * av - 0.5 * np.asarray(tr)
        T[1, 0] = T[0, 1]
        if p == 3:
            T[2, 0], T[2, 1] = T[0, 2], T[1, 2]
        H = 0.5 * T - VKV
        # second-derivative terms: 1/2 a^T K_ij a - 1/2 tr(Kt^-1 K_ij)
        H[0, 0] += 0.5 * sf2 * (float(a @ (r2 @ a)) - float(np.vdot(Kinv, r2)))
        H[0, 1] += g[0]
        H[1, 0] += g[0]
        H[1, 1] += g[1]
        if p == 3:
            H[2, 2] += g[2]
        return g, H

    def _profiled_staged(self, theta: np.ndarray) -> tuple[float, Callable]:
        # P = -n/2 log q - 1/2 log|A| + c, q = r^T A^-1 r, A = rho + g I, a_i = alpha^T A_i alpha.
        n, r = self.n, self.r
        k = self.kernel.unit(math.exp(theta[0]))  # type: ignore[attr-defined]
        rho, r1, r2 = k.correlation2(self.d)
        gn = math.exp(theta[1])
        A = rho
        A.flat[:: n + 1] += gn
        L = self._factor(A)
        al = linalg.cho_solve(L, r)
        q = float(r @ al)
        if not q > 0.0:
            return -math.inf, lambda: (np.zeros(2), np.zeros((2, 2)))
        self._last = (theta.tobytes(), L, al, q) if self._exact else None
        lml = -0.5 * n * (math.log(q / n) + 1.0 + _LOG2PI) - 0.5 * linalg.logdet(L)
        return lml, lambda: self._profiled_derivatives(L, al, q, r1, r2, gn)

    def _profiled_derivatives(self, L, al, q: float, r1, r2, gn: float):
        n = self.n
        Ainv = linalg.inverse_from_cholesky(L)
        M1 = Ainv @ r1
        v1 = r1 @ al
        w1, wa = Ainv @ v1, Ainv @ al
        a1, a2 = float(al @ v1), gn * float(al @ al)
        t1, t2 = float(np.trace(M1)), gn * float(np.trace(Ainv))
        c = 0.5 * n / q
        g = np.array([c * a1 - 0.5 * t1, c * a2 - 0.5 * t2])
        # d a_i / d theta_j = alpha^T A_ij alpha - 2 alpha^T A_i A^-1 A_j alpha
        v1w1, v1wa, awa = float(v1 @ w1), float(v1 @ wa), float(al @ wa)
        da11 = float(al @ (r2 @ al)) - 2.0 * v1w1
        da12 = -2.0 * gn * v1wa
        da22 = a2 - 2.0 * gn * gn * awa
        tr11 = float(np.vdot(M1, M1.T)) - float(np.vdot(Ainv, r2))
        tr12 = gn * float(np.vdot(M1, Ainv))
        tr22 = gn * gn * float(np.vdot(Ainv, Ainv)) - t2
        h12 = c * (da12 + a1 * a2 / q) + 0.5 * tr12
        H = np.array(
            [
                [c * (da11 + a1 * a1 / q) + 0.5 * tr11, h12],
                [h12, c * (da22 + a2 * a2 / q) + 0.5 * tr22],
            ]
        )
        return g, H

    def full_theta(self, theta: np.ndarray) -> np.ndarray:
        """``[kernel.theta, log noise_variance]`` from a (possibly profiled) ``theta``."""
        theta = np.asarray(theta, dtype=float)
        if not self.profile:
            return theta
        n = self.n
        last = self._last_at(theta)
        if last is not None:  # s2 = r^T A^-1 r / n from the latest evaluation
            s2 = last[3] / n
            return np.array([theta[0], np.log(s2), theta[1] + np.log(s2)])
        k = self.kernel.with_theta(np.array([theta[0], 0.0]))
        A = k(self.x)
        A.flat[:: n + 1] += np.exp(theta[1])
        L = self._factor(A)
        s2 = float(self.r @ linalg.cho_solve(L, self.r)) / n
        return np.array([theta[0], np.log(s2), theta[1] + np.log(s2)])

    def bounds(self, user: dict[str, tuple[float, float]] | None = None) -> np.ndarray:
        """Finite log-space bounds (dim, 2) scaled to the data; ``user`` overrides by name."""
        return search_bounds(
            self.x, self.r, self.kernel, self.known, self.learn_noise, self.profile, user
        )


def theta_names(kernel: Kernel, learn_noise: bool, profile: bool) -> tuple[str, ...]:
    """Names of the entries of :class:`Objective`'s ``theta``."""
    if profile:
        return ("length_scale", "noise_ratio")
    return tuple(kernel.names) + (("noise_variance",) if learn_noise else ())


def search_bounds(
    x: np.ndarray,
    r: np.ndarray,
    kernel: Kernel,
    known: Noise | None,
    learn_noise: bool,
    profile: bool,
    user: dict[str, tuple[float, float]] | None = None,
) -> np.ndarray:
    """Finite log-space bounds (dim, 2) of :class:`Objective`'s ``theta`` for readings ``x``
    (n,) and residuals ``r`` (n,), scaled to the data; ``user`` overrides by name."""
    add = np.add.reduce  # (as np.sort, .min(), .mean() and .sum(), without their wrappers)
    xs = np.array(x, dtype=float)
    xs.sort()
    span = float(xs[-1] - xs[0]) or 1.0
    gaps = xs[1:] - xs[:-1]
    gaps = gaps[gaps > 0]  # the distinct positions' gaps
    gap = float(np.minimum.reduce(gaps)) if gaps.size else span
    n = r.size  # the variance (as np.var), else the mean square, at least the known noise's
    v = float(add(np.square(r - add(r) / n))) / n or float(add(np.square(r))) / n
    if known is not None:
        v = max(v, float(add(known.diagonal(n))) / n)
    v = v or 1.0  # no scale in the data at all (every correction 0, no known noise)
    rows: dict[str, tuple[float, float]] = {}
    for name, (leaf, unit) in zip(kernel.names, _leaves(kernel), strict=True):
        if name.rsplit("_", 2)[-2:] == ["length", "scale"]:
            periodic = isinstance(leaf, Periodic)  # its length scale is dimensionless
            rows[name] = (1e-2, 1e2) if periodic else (max(0.5 * gap, 1e-4 * span), 1e2 * span)
        else:  # variances and constants: in the target unit squared, or factors of 1
            scale = v if unit else 1.0
            rows[name] = (1e-6 * scale, 1e4 * scale)
    rows["noise_variance"] = (1e-10 * v, 10.0 * v)
    if user is not None and not isinstance(user, dict):
        raise InputError(
            f"bounds: expected a dict of name: (lower, upper), e.g. "
            f"{{'length_scale': (0.01, 1.0)}}, got {user!r}"
        )
    for name, lohi in (user or {}).items():
        if name not in rows:
            raise InputError(f"bounds: unknown hyperparameter {name!r}; known: {list(rows)}")
        try:
            lo, hi = (float(v) for v in lohi)
        except (TypeError, ValueError):
            raise InputError(f"bounds: {name}: expected (lower, upper), got {lohi!r}") from None
        if not 0.0 < lo <= hi < math.inf:  # (a review: the message had shown every row)
            raise InputError(f"bounds: {name}: expected 0 < lower <= upper, got ({lo!r}, {hi!r})")
        rows[name] = (lo, hi)
    if profile:
        (l_lo, l_hi) = rows["length_scale"]
        out = [(l_lo, l_hi), (1e-10, RATIO_MAX)]
    else:
        out = [rows[name] for name in kernel.names]
        if learn_noise:
            out.append(rows["noise_variance"])
    if not all(0.0 < lo <= hi < math.inf for lo, hi in out):
        raise InputError(f"bounds: expected 0 < lower <= upper, got {out}")
    return np.log(np.asarray(out, dtype=float))


def _leaves(kernel: Kernel, unit: bool = True) -> list[tuple[Kernel, bool]]:
    """The leaf kernel owning each hyperparameter, in the order of ``kernel.names``, and
    whether its variance carries the target's unit: in a product, the first factor's
    does, the others' are numbers (their product spans the target's scale: with every
    variance bounded by the data's, a product of two could not reach data of variance
    below 1e-8, micrometres in metres)."""
    left = getattr(kernel, "left", None)
    if left is None:
        return [(kernel, unit)] * kernel.n_params
    right = kernel.right  # type: ignore[attr-defined]
    return _leaves(left, unit) + _leaves(right, unit and not isinstance(kernel, Product))
