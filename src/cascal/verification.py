"""Verification of a calibration against independent check points.

After a calibration, the device is read at positions the reference measures too, points
the fit never saw. Each check point's error is ``corrected - reference``. Its standard
uncertainty combines, as independent terms, the calibration's own ``u`` at the reading,
the repeatability of one device reading and the reference's uncertainty; the normalised
error ``En = |error| / (k u)`` is at most 1 at about 95 % of the points where the model's
uncertainty is right (fewer can occur by chance: neighbouring points share the calibration
error). Against a maximum permissible error (MPE), a point conforms when
``|error| + k u_reference <= MPE``: the error, enlarged by the expanded uncertainty of the
check itself, stays within the limit (the rule of ISO 14253-1 for proving conformance).
A recalibration is compared with the calibration before it (:func:`compare`) on a grid of
readings: the change of the correction, its standard uncertainty ``u`` were the device
unchanged (from the change's covariance, see :func:`cascal.workflow.change_covariance`),
pointwise ``En = |change| / (k u)``, and a simultaneous band: the factor ``k_band`` within
which an unchanged device's ``|change| / u`` stays over the whole grid with 95 %
probability. Judging every reading by ``k = 2`` would call a third of unchanged devices
changed somewhere along the range; the band keeps that at 5 %.
Pure numerics: no files, no printing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = [
    "BAND_LEVEL",
    "COVERAGE_FACTOR",
    "Comparison",
    "LimitVerdict",
    "Verification",
    "band_factor",
    "compare",
    "expected_within",
    "verify",
]

#: Coverage factor of the expanded uncertainty U = k u (about 95 % for a normal law, GUM).
COVERAGE_FACTOR = 2.0


def expected_within(k: float = COVERAGE_FACTOR) -> float:
    """Probability that a normal error lies within k standard deviations (0.9545 for 2)."""
    return math.erf(k / math.sqrt(2.0))


#: Units in the last place of the readings (and the MPE) within which a point at the MPE
#: conforms: the round-off of the readings' decimals (the subtraction of two close ones is
#: exact) and of the sum with ``k u``.
LIMIT_ULPS = 4
#: The most of the MPE by which that allowance may widen it: where the readings resolve the
#: MPE less finely than this, a point at the limit is decided by round-off.
LIMIT_SHARE = 1e-9


@dataclass(frozen=True, slots=True)
class Verification:
    """Check points against the corrected readings; statistics count inside points only.

    Attributes:
        reading: Device readings of the check points, shape (m,).
        reference: Reference values at them, shape (m,), same unit.
        corrected: Corrected readings, shape (m,).
        error: ``corrected - reference``, shape (m,) (for a rotary model the shortest way
            round, within half a period).
        error_before: ``reading - reference`` likewise: the error without correction.
        u_calibration: Standard uncertainty of the correction at each reading, shape (m,);
            NaN for a lookup-table model, which has none.
        u_reading: Standard uncertainty of one device reading (its repeatability).
        u_reference: Standard uncertainty of one reference value.
        inside: True where the reading lies in the calibrated range, shape (m,).
        mpe: Maximum permissible error, or None.
        k: Coverage factor of the expanded uncertainties.
        period: A rotary model's period, or None.
    """

    reading: np.ndarray
    reference: np.ndarray
    corrected: np.ndarray
    error: np.ndarray
    error_before: np.ndarray
    u_calibration: np.ndarray
    u_reading: float
    u_reference: float
    inside: np.ndarray
    mpe: float | None = None
    k: float = COVERAGE_FACTOR
    period: float | None = None

    @property
    def u(self) -> np.ndarray:
        """Standard uncertainty of each error: the three terms combined, shape (m,)."""
        return np.sqrt(self.u_calibration**2 + self.u_reading**2 + self.u_reference**2)

    @property
    def en(self) -> np.ndarray:
        """Normalised error ``|error| / (k u)``, shape (m,) (0 where the error is 0); NaN
        without a calibration u."""
        return _ratio(self.error, self.k * self.u)

    @property
    def acceptance(self) -> float | None:
        """``mpe - k u_reference``: the largest |error| that conforms (ISO 14253-1); None
        without MPE."""
        return None if self.mpe is None else self.mpe - self.k * self.u_reference

    @property
    def conforms(self) -> np.ndarray | None:
        """``|error| + k u_reference <= mpe`` at each point, shape (m,); None without MPE.

        A point on the limit in decimals conforms (ISO 14253-1's zones hold their limits)
        whatever the binary round-off of its readings: the comparison allows
        :data:`LIMIT_ULPS` units in the last place of the readings and the MPE, at most
        :data:`LIMIT_SHARE` of the MPE (a review: of five points exactly on the limit, two
        had failed; a second: readings of 1e6 against an MPE of 1e-9 must not widen it)."""
        if self.mpe is None:
            return None
        scale = np.maximum(np.abs(self.corrected), np.abs(self.reference))
        slack = LIMIT_ULPS * np.finfo(float).eps * np.maximum(scale, self.mpe)
        slack = np.minimum(slack, LIMIT_SHARE * self.mpe)
        return np.abs(self.error) + self.k * self.u_reference <= self.mpe + slack

    @property
    def has_u(self) -> bool:
        """Whether the model gives the calibration's uncertainty (not a lookup table)."""
        return not np.all(np.isnan(self.u_calibration))

    def summary(self) -> dict[str, float | int | None]:
        """Statistics over the inside points: their count, RMS and largest error before and
        after correction, how many have ``En <= 1``, the RMS of ``error / u`` and how many
        conform to the MPE (None where they do not apply)."""
        m = self.inside
        e, before = self.error[m], self.error_before[m]
        n = int(e.size)
        out: dict[str, float | int | None] = {
            "points": n,
            "outside_range": int(self.inside.size - n),
            "rms_before": _rms(before),
            "rms_after": _rms(e),
            "max_before": float(np.max(np.abs(before))) if n else math.nan,
            "max_after": float(np.max(np.abs(e))) if n else math.nan,
            "within_U": None,
            "rms_normalised": None,
            "conforming": None,
        }
        if self.has_u and n:
            out["within_U"] = int(np.count_nonzero(self.en[m] <= 1.0))
            out["rms_normalised"] = _rms(self.en[m] * self.k)
        conforms = self.conforms
        if conforms is not None:
            out["conforming"] = int(np.count_nonzero(conforms[m]))
        return out


def verify(
    reading: np.ndarray,
    reference: np.ndarray,
    corrected: np.ndarray,
    u_calibration: np.ndarray,
    *,
    inside: np.ndarray | None = None,
    u_reading: float = 0.0,
    u_reference: float = 0.0,
    period: float | None = None,
    mpe: float | None = None,
    k: float = COVERAGE_FACTOR,
) -> Verification:
    """Compare corrected readings (m,) with reference values (m,) at check points.

    Args:
        reading, reference, corrected, u_calibration: Shape (m,) each, one unit.
        inside: Points that count in the statistics, shape (m,); default all.
        u_reading, u_reference: Standard uncertainties of one device reading and of one
            reference value, >= 0.
        period: For a rotary model, errors are taken the shortest way round.
        mpe: Maximum permissible error (> 0), or None.
        k: Coverage factor (> 0).
    """
    names = ("reading", "reference", "corrected", "u_calibration")
    try:
        arrays = [
            np.asarray(a, dtype=float) for a in (reading, reference, corrected, u_calibration)
        ]
    except (TypeError, ValueError):  # (a review: a bare ValueError)
        raise InputError(f"verify: expected numbers for {', '.join(names)}") from None
    m = arrays[0].shape
    if any(a.ndim != 1 or a.shape != m for a in arrays):
        shapes = ", ".join(str(a.shape) for a in arrays)
        raise InputError(
            "verify: expected reading, reference, corrected and u_calibration of one shape "
            f"(m,), got {shapes}"
        )
    inside = np.ones(m, bool) if inside is None else np.asarray(inside, bool)
    if inside.shape != m:
        raise InputError(f"verify: inside has shape {inside.shape}, expected {m}")
    for name, a in zip(names[:3], arrays[:3], strict=True):
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:  # (a review: NaN statistics came back)
            raise InputError(f"verify: {name} must be finite, got {a[bad[0]]} at index {bad[0]}")
    bad = np.flatnonzero((arrays[3] < 0.0) | np.isinf(arrays[3]))  # (NaN: none, a table's)
    if bad.size:
        raise InputError(
            f"verify: u_calibration must be finite and >= 0 (or NaN for none), got "
            f"{arrays[3][bad[0]]} "
            f"at index {bad[0]}"
        )
    u_reading, u_reference, k = (_number(v, n) for v, n in ((u_reading, "u_reading"),
                                 (u_reference, "u_reference"), (k, "k")))  # fmt: skip
    mpe = None if mpe is None else _number(mpe, "mpe")
    for name, v in (("u_reading", u_reading), ("u_reference", u_reference)):
        if not (0.0 <= v < math.inf):
            raise InputError(f"verify: {name} must be a finite number >= 0, got {v!r}")
    if mpe is not None and not (0.0 < mpe < math.inf):
        raise InputError(f"verify: mpe must be a finite number > 0, got {mpe!r}")
    if not (0.0 < k < math.inf):
        raise InputError(f"verify: k must be a finite number > 0, got {k!r}")
    r, ref, c, u = arrays
    return Verification(
        r,
        ref,
        c,
        _difference(c, ref, period),
        _difference(r, ref, period),
        u,
        float(u_reading),
        float(u_reference),
        inside,
        None if mpe is None else float(mpe),
        float(k),
        None if period is None else float(period),
    )


#: Probability that an unchanged device's change stays within the simultaneous band.
BAND_LEVEL = 0.95
#: Draws that set the simultaneous band's factor (its 95 % quantile to about 0.01 in k).
BAND_DRAWS = 20_000


@dataclass(frozen=True, slots=True)
class Comparison:
    """Two calibrations' corrections on one grid of device readings.

    Attributes:
        reading: Device readings, increasing, shape (n,).
        old, new: Corrected readings of the earlier and the later calibration, shape (n,).
        change: ``new - old`` (for a rotary model the shortest way round), shape (n,).
        u_old, u_new: Their standard uncertainties, shape (n,); NaN for lookup tables.
        u: Standard uncertainty of the change were the device unchanged, shape (n,).
        k_band: Factor of the simultaneous band ``±k_band u`` (NaN without u).
        shared: Whether ``u`` counts an upstream calibration both share.
        k: Coverage factor of the pointwise En.
        period: A rotary model's period, or None.
    """

    reading: np.ndarray
    old: np.ndarray
    new: np.ndarray
    change: np.ndarray
    u_old: np.ndarray
    u_new: np.ndarray
    u: np.ndarray
    k_band: float = math.nan
    shared: bool = False
    k: float = COVERAGE_FACTOR
    period: float | None = None

    @property
    def z(self) -> np.ndarray:
        """``|change| / u``, shape (n,) (0 where the change is 0); NaN without u."""
        return _ratio(self.change, self.u)

    @property
    def en(self) -> np.ndarray:
        """Pointwise ``|change| / (k u)``, shape (n,); NaN without u."""
        return self.z / self.k

    @property
    def has_u(self) -> bool:
        """Whether the change has an uncertainty (neither model is a lookup table)."""
        return not np.any(np.isnan(self.u))

    @property
    def changed(self) -> bool | None:
        """Whether the change leaves the simultaneous band somewhere; None without u."""
        return bool(np.max(self.z) > self.k_band) if self.has_u else None

    def against(self, limit: float) -> LimitVerdict:
        """The change judged against a largest allowed change ``limit`` (> 0, the readings'
        unit) with its uncertainty, as ISO 14253-1 judges a tolerance: shown beyond it
        where ``|change| - k_band u > limit``, shown within it where ``|change| + k_band u
        <= limit`` at every reading; the simultaneous band, so that each holds over the
        whole range with 95 % probability. Without u (lookup tables), the change alone."""
        if not (0.0 < limit < math.inf):
            raise InputError(f"limit: expected a finite number > 0, got {limit!r}")
        a = np.abs(self.change)
        if not self.has_u:
            out = a > limit
            verdict = "beyond" if np.any(out) else "within"
            return LimitVerdict(
                float(limit), verdict, float(np.mean(out)), 0.0, float(np.mean(out))
            )
        # (a review: u 0 everywhere leaves no band, k_band NaN, and a NaN margin had passed
        # any change: where u is 0 the change is exact)
        margin = np.where(self.u > 0, self.k_band * self.u, 0.0)
        if not np.all(np.isfinite(margin)):
            raise InputError("against: the change's uncertainty has no finite band")
        beyond, not_within = a - margin > limit, a + margin > limit
        verdict = "beyond" if np.any(beyond) else "undecided" if np.any(not_within) else "within"
        return LimitVerdict(
            float(limit),
            verdict,
            float(np.mean(beyond)),
            float(np.mean(margin >= limit)),
            float(np.mean(not_within)),
        )

    def summary(self) -> dict[str, float | None]:
        """RMS and largest |change| and the reading of the largest; the largest
        ``|change| / u`` and its reading, and the share of the grid beyond the band and
        beyond ``k u`` (None without u)."""
        i = int(np.argmax(np.abs(self.change)))
        out: dict[str, float | None] = {
            "rms_change": _rms(self.change),
            "max_change": float(abs(self.change[i])),
            "at": float(self.reading[i]),
            "max_z": None,
            "max_z_at": None,
            "share_beyond_band": None,
            "share_beyond_U": None,
        }
        if self.has_u:
            z = self.z
            j = int(np.argmax(z))
            out["max_z"], out["max_z_at"] = float(z[j]), float(self.reading[j])
            out["share_beyond_band"] = float(np.mean(z > self.k_band))
            out["share_beyond_U"] = float(np.mean(z > self.k))
        return out


@dataclass(frozen=True, slots=True)
class LimitVerdict:
    """A comparison judged against a largest allowed change (:meth:`Comparison.against`).

    Attributes:
        limit: The largest change allowed, the readings' unit.
        verdict: ``"within"`` (shown within it at every reading), ``"beyond"`` (shown
            beyond it somewhere) or ``"undecided"`` (neither: the change's uncertainty
            leaves it open); without u, ``"within"`` or ``"beyond"`` by the change alone.
        share_beyond: Share of the readings where the change is shown beyond the limit.
        share_unresolved: Share where the band alone reaches the limit (``k_band u >=
            limit``): there not even an unchanged device is shown within it.
        share_not_within: Share where the change is not shown within the limit.
    """

    limit: float
    verdict: str
    share_beyond: float
    share_unresolved: float
    share_not_within: float


def band_factor(
    cov: np.ndarray, *, level: float = BAND_LEVEL, draws: int = BAND_DRAWS, seed: int = 0
) -> float:
    """Factor k with ``P(max_i |Z_i| / sd_i <= k) = level`` for ``Z ~ N(0, cov)`` (n, n):
    the quantile of the largest standardised value, from ``draws`` draws of a fixed seed
    (the same factor every time): for one point or fully correlated ones close to 1.96, for
    independent ones to the Sidak factor, within the estimate's scatter (about 0.01 with
    the default draws; a review measured 1.948 for one point with seed 0)."""
    cov = np.asarray(cov, dtype=float)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    keep = sd > 0.0
    if not np.any(keep):
        return math.nan
    corr = cov[np.ix_(keep, keep)] / np.outer(sd[keep], sd[keep])
    w, V = np.linalg.eigh(0.5 * (corr + corr.T))
    big = w > w[-1] * 1e-12
    factor = V[:, big] * np.sqrt(w[big])
    rng = np.random.default_rng(seed)
    top = np.empty(draws)
    for s in range(0, draws, 2000):  # blocks: (n, 2000) at a time
        z = factor @ rng.standard_normal((factor.shape[1], min(2000, draws - s)))
        top[s : s + z.shape[1]] = np.max(np.abs(z), axis=0)
    return float(np.quantile(top, level))


def compare(
    reading: np.ndarray,
    old: np.ndarray,
    u_old: np.ndarray,
    new: np.ndarray,
    u_new: np.ndarray,
    *,
    change_cov: np.ndarray | None = None,
    shared: bool = False,
    period: float | None = None,
    k: float = COVERAGE_FACTOR,
) -> Comparison:
    """Compare two calibrations' corrected readings (n,) and their standard uncertainties
    (n,) at the same device readings (n,). ``change_cov``: covariance (n, n) of the change
    were the device unchanged, by default that of two independent errors at independent
    readings (``diag(u_old^2 + u_new^2)``); ``shared``: whether it counts a shared upstream
    calibration; ``period``: changes are taken the shortest way round."""
    arrays = [np.asarray(a, dtype=float) for a in (reading, old, u_old, new, u_new)]
    n = arrays[0].shape
    if any(a.ndim != 1 or a.shape != n for a in arrays) or not n[0]:
        shapes = ", ".join(str(a.shape) for a in arrays)
        raise InputError(
            "compare: expected reading, old, u_old, new and u_new of one non-empty shape "
            f"(n,), got {shapes}"
        )
    if not (0.0 < k < math.inf):
        raise InputError(f"compare: k must be a finite number > 0, got {k!r}")
    r, a, ua, b, ub = arrays
    cov = np.diag(ua**2 + ub**2) if change_cov is None else np.asarray(change_cov, float)
    if cov.shape != n * 2:
        raise InputError(f"compare: change_cov has shape {cov.shape}, expected {n * 2}")
    u = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    band = band_factor(cov) if np.all(np.isfinite(cov)) else math.nan
    p = None if period is None else float(period)
    return Comparison(r, a, b, _difference(b, a, p), ua, ub, u, band, bool(shared), float(k), p)


def breaks(reading: np.ndarray) -> np.ndarray:
    """Where increasing, nearly equally spaced ``reading`` (n,) jump (a step over three
    times the median: two stretches of a turn, :func:`cascal.workflow.compare_models`): the
    indices that start a new stretch, shape (k,)."""
    step = np.diff(reading)
    if step.size < 2:
        return np.zeros(0, dtype=int)
    return np.flatnonzero(step > 3.0 * np.median(step)) + 1


def _ratio(e: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``|e| / s`` elementwise; 0 where ``e`` is 0 (NaN there only where ``s`` is NaN)."""
    a = np.abs(e)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(a == 0.0, 0.0 * s, a / s)


def _difference(a: np.ndarray, b: np.ndarray, period: float | None) -> np.ndarray:
    d = a - b
    if period is not None:
        d = d - period * np.round(d / period)
    return d


def _rms(v: np.ndarray) -> float:
    if not v.size:
        return math.nan
    top = float(np.max(np.abs(v)))
    if not 0.0 < top < math.inf:
        return top
    return top * float(np.sqrt(np.mean((v / top) ** 2)))  # no overflow of v * v


def _number(v: object, name: str) -> float:
    """``v`` as a float; InputError naming ``name`` where it is not a number."""
    if isinstance(v, str | bytes):
        raise InputError(f"verify: {name} must be a number, got {v!r}")
    try:
        return float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"verify: {name} must be a number, got {v!r}") from None
