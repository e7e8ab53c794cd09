"""Error of measured poses or bar lengths against a reference, in report units (µm, arc-seconds).

A reference may give only some components (a laser along one axis, a rotary calibrator's
angle): unknown components are NaN and are left out of the statistics.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from mmd_ros.core.uncertainty import region_quantile
from mmd_ros.core.units import arcsec, um

__all__ = [
    'ABSOLUTE_WITHIN_SIGMAS', 'GROSS_ERROR', 'ComponentStats', 'CoverageAccumulator',
    'DatumReading', 'ErrorAccumulator', 'ReferenceNoise', 'ReferenceScale', 'coverage',
    'error_stats', 'format_coverage', 'format_stats', 'length_error', 'pose_error', 'read_datum',
    'robust_std', 'smoothing_departures', 'white_noise',
]

FloatArray = NDArray[np.float64]
POSE_NAMES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw']


#: Savitzky-Golay smoothing weights, 5 samples, quadratic; the centre's own weight 17/35.
_SMOOTH5 = np.array([-3.0, 12.0, 17.0, 12.0, -3.0]) / 35.0


def smoothing_departures(values: FloatArray, idx: NDArray[np.int64]) -> FloatArray:
    """Each sample's departure from the quadratic through it and its two neighbours either
    side (a Savitzky-Golay fit: motion up to a constant acceleration leaves nothing), at the
    samples of ``idx`` whose four neighbours are in ``idx`` too, (m, k) for ``values`` (N, k);
    rows with a non-finite value left out."""
    idx = np.asarray(idx, dtype=np.int64)
    centre = idx[2:-2][(idx[4:] - idx[:-4]) == 4] if idx.size > 4 else idx[:0]
    window = centre[:, None] + np.arange(-2, 3)[None, :]
    dev = values[centre] - np.einsum('w,nwk->nk', _SMOOTH5, values[window])
    return dev[np.all(np.isfinite(dev), axis=1)]


def robust_std(values: FloatArray) -> FloatArray:
    """Standard deviation of ``values`` along the first axis from their median absolute
    deviation (1.4826 MAD: a Gaussian's sigma, unmoved by a few outliers)."""
    return 1.4826 * np.median(np.abs(values - np.median(values, axis=0)), axis=0)


#: Departures further than this many robust standard deviations from their median are outliers.
OUTLIER_SIGMAS = 5.0


def _white_scale(departures: FloatArray, width: int) -> FloatArray:
    """White noise from :func:`smoothing_departures`: the standard deviation of those within
    :data:`OUTLIER_SIGMAS` robust standard deviations of their median (a spike dropped, a
    Gaussian's kept) over sqrt(1 - 17/35), what the fit takes of a white sample; zeros below
    10 rows. Not the robust one itself: its scatter is that of a standard deviation of 37 %
    of the samples, and a reference's noise is read as the difference of two such (the
    error's and the MMD's own), whose relative error is the MMD's excess's many times over
    (a 0.1″ reference beside 0.05″ of the MMD's own white noise, read 6 % high, took a
    third of the MMD's roll: new motion's roll claimed 0.76 times its error, 1.02 now)."""
    d = np.asarray(departures, dtype=np.float64)
    if d.shape[0] < 10:
        return np.zeros(width)
    spread = robust_std(d)
    keep = np.abs(d - np.median(d, axis=0)) <= OUTLIER_SIGMAS * spread
    keep |= spread <= 0.0                  # (no spread: counts that rarely change, every row)
    n = keep.sum(axis=0)
    mean = np.sum(np.where(keep, d, 0.0), axis=0) / n
    var = np.sum(np.where(keep, (d - mean) ** 2, 0.0), axis=0) / np.maximum(n - 1, 1)
    return np.sqrt(var) / np.sqrt(1.0 - _SMOOTH5[2])


def white_noise(values: FloatArray, idx: NDArray[np.int64]) -> FloatArray:
    """White noise of ``values`` (N, k) over the samples ``idx``, (k,): the robust spread of
    :func:`smoothing_departures`, which follows motion (zero with fewer than 10 of them)."""
    return _white_scale(smoothing_departures(values, idx), values.shape[1])


class ReferenceNoise:
    """The reference's own white noise per pose component, read from a run given block by
    block: what the white noise of the error (MMD - reference) holds beyond the MMD's own in the
    same component, read from its own poses at the same samples (the two are independent). The
    departures are kept in bounded memory (every one up to ``max_samples``, then a stride that
    doubles). For a log that does not state its reference's uncertainty; motion left in the
    MMD's departures makes the estimate smaller, never larger."""

    MAX_SAMPLES = 200_000

    def __init__(self, max_samples: int = MAX_SAMPLES) -> None:
        self.max_samples = max_samples
        self._error: list[FloatArray] = []
        self._own: list[FloatArray] = []
        self._kept = 0

    def add(self, errors: FloatArray, poses: FloatArray, valid: NDArray[np.bool_]) -> None:
        """errors, poses (N, 6) [m, rad] of one block; valid (N,): the measurements"""
        e, p = np.asarray(errors, dtype=np.float64), np.asarray(poses, dtype=np.float64)
        known = np.isfinite(e).mean(axis=0) >= 0.5
        if not known.any():
            return
        idx = np.flatnonzero(np.asarray(valid, dtype=bool) & np.all(np.isfinite(p), axis=1)
                             & np.all(np.isfinite(e[:, known]), axis=1))
        both = smoothing_departures(np.concatenate([e[:, known], p], axis=1), idx)
        error = np.full((both.shape[0], 6), np.nan)
        error[:, known] = both[:, :int(known.sum())]
        self._error.append(error)
        self._own.append(both[:, int(known.sum()):])
        self._kept += both.shape[0]
        while self._kept > self.max_samples:
            self._error = [np.concatenate(self._error)[::2]]
            self._own = [np.concatenate(self._own)[::2]]
            self._kept = self._error[0].shape[0]

    def sigma(self) -> FloatArray:
        """(6,) [m, rad], NaN for a component the reference does not give."""
        if not self._kept:
            return np.full(6, np.nan)
        e, p = np.concatenate(self._error), np.concatenate(self._own)
        known = np.all(np.isfinite(e), axis=0)     # (a component some block lacked: not known)
        out = np.full(6, np.nan)
        ref = _white_scale(np.nan_to_num(e), 6) ** 2 - _white_scale(p, 6) ** 2
        out[known] = np.sqrt(np.maximum(ref[known], 0.0))
        return out


#: A reference pose that does not say whether it is absolute in {L} (a log's metadata
#: ``reference_absolute``) reads as absolute when every component's median offset from the MMD
#: lies within this many times what the MMD claims for its error there (with the reference's
#: own sigma): a zeroed reference is off by the pose at its zero as well (millimetres, unless
#: zeroed exactly at the origin of {L}, where the two are one)
ABSOLUTE_WITHIN_SIGMAS = 5.0
#: Beyond that, a reference that does not read zero where the log starts (it was not zeroed
#: there) still reads as absolute within these offsets [m, rad]: an MMD with an error its
#: budget does not claim (what an analysis is for) is off by micrometres and arc-seconds, a
#: pose a reference was zeroed at by the MMD's mounting, a tenth of a millimetre or more
GROSS_ERROR = (20e-6, 20.0 * math.pi / (180.0 * 3600.0))


#: How far a component must move over a run for :class:`ReferenceScale` to read the
#: reference's scale in it (standard deviation of the MMD's reading) [m, rad]
SCALE_MOTION = (10e-6, 50e-6)
#: The two readings must follow each other this closely (correlation) to tell a scale ...
SCALE_CORRELATION = 0.99
#: ... and a slope within this fraction of one of :data:`SCALE_BLUNDERS` names it
SCALE_TOLERANCE = 0.03
#: What a slope of -1 says (a position or an angle alike)
REVERSED = 'to have the opposite sign (an axis mounted or read reversed)'
#: Slopes of the reference against the MMD that name a blunder, per kind of component
SCALE_BLUNDERS = {
    'position': ((1e3, 'to be in millimetres, not metres'),
                 (1e6, 'to be in micrometres, not metres'), (-1.0, REVERSED)),
    'angle': ((180.0 / math.pi, 'to be in degrees, not radians'),
              (180.0 / math.pi * 3600.0, 'to be in arc-seconds, not radians'), (-1.0, REVERSED)),
}


class ReferenceScale:
    """Per pose component, the slope and correlation of the reference's reading against the
    MMD's over a run given block by block: a reference in millimetres or degrees, or read with
    the opposite sign, follows the MMD's motion exactly but 1000 or 57.3 times larger, or
    reversed, and its 'error' is the motion itself. Sums of the centred products are kept
    (the first valid sample of each component is the shift)."""

    def __init__(self) -> None:
        self._n = np.zeros(6)
        self._shift = np.zeros((2, 6))    # per component: the MMD's, the reference's
        self._set = np.zeros(6, dtype=bool)
        self._sums = np.zeros((5, 6))     # m, r, m m, r r, m r (shifted)

    def add(self, poses: FloatArray, reference: FloatArray, valid: NDArray[np.bool_]) -> None:
        """poses, reference (N, 6) [m, rad] of one block; valid (N,): the measurements"""
        m = np.asarray(poses, dtype=np.float64)
        r = np.asarray(reference, dtype=np.float64)
        ok = np.asarray(valid, dtype=bool)[:, None] & np.isfinite(m) & np.isfinite(r)
        if not ok.any():
            return
        for j in np.flatnonzero(ok.any(axis=0) & ~self._set):
            first = int(np.argmax(ok[:, j]))
            self._shift[:, j] = m[first, j], r[first, j]
            self._set[j] = True
        dm = np.where(ok, m - self._shift[0], 0.0)
        dr = np.where(ok, r - self._shift[1], 0.0)
        self._n += ok.sum(axis=0)
        self._sums += np.stack([dm.sum(0), dr.sum(0), (dm * dm).sum(0), (dr * dr).sum(0),
                                (dm * dr).sum(0)])

    def slopes(self) -> tuple[FloatArray, FloatArray]:
        """(6,) slope of the reference on the MMD and (6,) their correlation; NaN where a
        component did not move enough (:data:`SCALE_MOTION`) or has no reference."""
        n = np.maximum(self._n, 1.0)
        sm, sr, smm, srr, smr = self._sums / n
        var_m, var_r, cov = smm - sm * sm, srr - sr * sr, smr - sm * sr
        moved = (self._n >= 10) & (np.sqrt(np.maximum(var_m, 0.0))
                                   >= np.repeat(SCALE_MOTION, 3))
        with np.errstate(invalid='ignore', divide='ignore'):
            slope = np.where(moved, cov / var_m, np.nan)
            corr = np.where(moved, cov / np.sqrt(var_m * var_r), np.nan)
        return slope, corr

    def notes(self) -> list[str]:
        """Per component whose reference reads a blunder's slope of the MMD, what it reads."""
        slope, corr = self.slopes()
        out = []
        for j in range(6):
            if not np.isfinite(slope[j]) or abs(corr[j]) < SCALE_CORRELATION:
                continue
            kind = 'position' if j < 3 else 'angle'
            for factor, what in SCALE_BLUNDERS[kind]:
                if abs(slope[j] / factor - 1.0) <= SCALE_TOLERANCE:
                    out.append(f'{POSE_NAMES[j]} reads {slope[j]:.4g} times the MMD\'s '
                               f'(correlation {corr[j]:.4f}): it looks {what}')
                    break
        return out

    def text(self) -> str:
        """The notes as one sentence, or '' when there are none."""
        notes = self.notes()
        if not notes:
            return ''
        return ('the reference\'s ' + '; '.join(notes) + ' (a reference pose is in metres and '
                'radians, in the MMD\'s axes: msg_docs/topics.md)')


@dataclass(frozen=True)
class DatumReading:
    """What the offsets of a reference pose from the MMD say of its zero
    (:func:`read_datum`): ``absolute``; ``within`` (k,) the bound each offset was held to
    [m, rad]; ``starts_at_zero``: the reference reads zero (within it) in every component
    where the log starts."""

    absolute: bool
    within: FloatArray
    starts_at_zero: bool


def read_datum(offsets: FloatArray, sigma: FloatArray, start: FloatArray,
               components: list[int]) -> DatumReading:
    """Whether a reference pose that does not say so reads as absolute in {L}: its median
    offsets from the MMD (reference - MMD) ``offsets`` (k,) of pose components ``components``
    (0..5), ``sigma`` (k,) the MMD's claimed standard uncertainty there with the reference's
    own, ``start`` (k,) the reference where the log starts [m, rad]. Absolute when every offset
    is within :data:`ABSOLUTE_WITHIN_SIGMAS` sigma; beyond it, when the reference does not read
    zero where it starts and no offset exceeds :data:`GROSS_ERROR`."""
    off = np.abs(np.asarray(offsets, dtype=np.float64))
    within = ABSOLUTE_WITHIN_SIGMAS * np.asarray(sigma, dtype=np.float64)
    at_zero = bool(np.all(np.abs(np.asarray(start, dtype=np.float64)) <= within))
    gross = np.array([GROSS_ERROR[0] if c < 3 else GROSS_ERROR[1] for c in components])
    absolute = bool(np.all(off <= within) or (not at_zero and np.all(off <= gross)))
    return DatumReading(absolute, within, at_zero)


@dataclass(frozen=True)
class ComponentStats:
    """Statistics of one error component, in ``unit`` (µm or arcsec)."""

    name: str
    unit: str
    n: int
    mean: float
    std: float
    rms: float
    max_abs: float

    def as_dict(self) -> dict[str, float | int | str]:
        return asdict(self)


def pose_error(poses: FloatArray, reference: FloatArray) -> FloatArray:
    """Measured minus reference, shape (N, 6) [m, rad]; angles wrapped to (-pi, pi]; NaN where
    the reference does not know a component."""
    err = np.asarray(poses, dtype=np.float64) - np.asarray(reference, dtype=np.float64)
    err[:, 3:] = (err[:, 3:] + np.pi) % (2 * np.pi) - np.pi
    return err


def length_error(lengths: FloatArray, reference: FloatArray) -> FloatArray:
    """Measured minus reference bar lengths, shape (N, 6) [m]."""
    return np.asarray(lengths, dtype=np.float64) - np.asarray(reference, dtype=np.float64)


def _stats(name: str, unit: str, values: FloatArray) -> ComponentStats:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return ComponentStats(name, unit, 0, np.nan, np.nan, np.nan, np.nan)
    return ComponentStats(name, unit, int(v.size), float(v.mean()), float(v.std()),
                          float(np.sqrt(np.mean(v * v))), float(np.max(np.abs(v))))


def error_stats(errors: FloatArray, valid: NDArray[np.bool_] | None = None, *,
                kind: str = 'pose') -> list[ComponentStats]:
    """Per-component statistics of pose errors (µm, arcsec) or bar-length errors (µm).

    errors : ndarray, shape (N, 6) — from :func:`pose_error` or :func:`length_error`
    valid : ndarray, shape (N,), optional — samples to include
    kind : 'pose' adds the 3-D position error norm where x, y and z are all known
    """
    e = np.asarray(errors, dtype=np.float64)
    if valid is not None:
        e = e[np.asarray(valid, dtype=bool)]
    if kind == 'lengths':
        return [_stats(f'bar{i + 1}', 'um', um(e[:, i])) for i in range(e.shape[1])]
    out = [_stats(POSE_NAMES[i], 'um', um(e[:, i])) for i in range(3)]
    out += [_stats(POSE_NAMES[i], 'arcsec', arcsec(e[:, i])) for i in range(3, 6)]
    out.append(_stats('position', 'um', um(np.linalg.norm(e[:, :3], axis=1))))
    return [s for s in out if s.n > 0]


class ErrorAccumulator:
    """:func:`error_stats` of a run given block by block (a log too long to hold in memory):
    count, shifted sums and largest magnitude per component, so that mean, std, rms and max|e|
    come out as for the whole run at once (to rounding).

    kind : as for :func:`error_stats`
    """

    def __init__(self, kind: str = 'pose') -> None:
        self.kind = kind
        self._parts: list[tuple[str, str]] | None = None
        self._n = self._shift = self._s1 = self._s2 = self._max = None

    def _columns(self, e: FloatArray) -> tuple[list[tuple[str, str]], FloatArray]:
        if self.kind == 'lengths':
            return [(f'bar{i + 1}', 'um') for i in range(e.shape[1])], um(e)
        cols = np.column_stack([um(e[:, :3]), arcsec(e[:, 3:6]),
                                um(np.linalg.norm(e[:, :3], axis=1))])
        names = [(POSE_NAMES[i], 'um') for i in range(3)] + \
            [(POSE_NAMES[i], 'arcsec') for i in range(3, 6)] + [('position', 'um')]
        return names, cols

    def add(self, errors: FloatArray, valid: NDArray[np.bool_] | None = None) -> None:
        """errors : ndarray, shape (N, 6) [m, rad]; valid : ndarray, shape (N,), optional"""
        e = np.asarray(errors, dtype=np.float64)
        if valid is not None:
            e = e[np.asarray(valid, dtype=bool)]
        names, v = self._columns(e)
        if self._parts is None:
            k = len(names)
            self._parts = names
            self._n = np.zeros(k, dtype=np.int64)
            self._shift = np.full(k, np.nan)
            self._s1, self._s2, self._max = np.zeros(k), np.zeros(k), np.zeros(k)
        ok = np.isfinite(v)
        for j in range(v.shape[1]):
            x = v[ok[:, j], j]
            if x.size == 0:
                continue
            if np.isnan(self._shift[j]):
                self._shift[j] = x[0]   # sums of x - x0 keep their digits when |mean| >> std
            d = x - self._shift[j]
            self._n[j] += x.size
            self._s1[j] += d.sum()
            self._s2[j] += (d * d).sum()
            self._max[j] = max(self._max[j], float(np.max(np.abs(x))))

    def stats(self) -> list[ComponentStats]:
        """Per-component statistics of everything added (components never known left out)."""
        if self._parts is None:
            return []
        out = []
        for j, (name, unit) in enumerate(self._parts):
            n = int(self._n[j])
            if n == 0:
                continue
            m1 = self._s1[j] / n
            var = max(self._s2[j] / n - m1 * m1, 0.0)
            mean = self._shift[j] + m1
            out.append(ComponentStats(name, unit, n, float(mean), float(np.sqrt(var)),
                                      float(np.sqrt(var + mean * mean)), float(self._max[j])))
        return out


def format_stats(stats: list[ComponentStats], title: str) -> str:
    """A fixed-width table of the statistics."""
    lines = [title, f'  {"component":<10} {"unit":>7} {"n":>9} {"mean":>10} {"std":>10} {"rms":>10} {"max|e|":>10}']
    for s in stats:
        lines.append(f'  {s.name:<10} {s.unit:>7} {s.n:>9d} {s.mean:>10.4f} {s.std:>10.4f} '
                     f'{s.rms:>10.4f} {s.max_abs:>10.4f}')
    return '\n'.join(lines)


def coverage(errors: FloatArray, covariance: FloatArray, valid: NDArray[np.bool_], *,
             absolute: bool, reference_sigma: FloatArray | None = None,
             level: float = 0.95, tails: FloatArray | None = None,
             kind: str = 'pose') -> dict[str, object] | None:
    """Does the pose covariance cover the error against a reference? (msg_docs/frames.md)

    Over the samples that are measurements and where the reference knows the components:

    - observed sigma of a component: the RMS of its error (``absolute`` reference), or its
      standard deviation (a reference zeroed at the start: its offset is unknown and removed);
    - predicted sigma: sqrt of the mean of the covariance's diagonal, plus the reference's own
      variance (``reference_sigma``: as the log states it, or :class:`ReferenceNoise`);
    - coverage: the share of samples whose error lies in the ``level`` ellipsoid of the
      marginal covariance of the known components (Mahalanobis distance^2 <= chi^2_m(level),
      m known components), and per component in +-z sigma (z of ``level``, two-sided);
    - with ``tails``: the share in the ``level`` region of the budget's own distribution, the
      same ellipsoid sized by :func:`~mmd_ros.core.uncertainty.region_quantile` (its sources'
      forms: a quantisation, a sine, a known error are bounded, and a Gaussian's chi^2 region
      holds more than ``level`` of them).

    errors : (N, 6) MMD - reference [m, rad], NaN where unknown
    covariance : (N, 6, 6) [m, rad]^2
    reference_sigma : (6,) the reference's standard uncertainty [m, rad], NaN or None unknown
    tails : (N, 6, K) the covariance's light-tailed directions (``ProcessResult.tails``), or None
    kind : 'pose', or 'lengths': the six measuring bars' lengths [m] and their covariance
        Sigma_d (``ProcessResult.length_covariance``), against reference bar lengths
    returns : a JSON-ready mapping, or None when no sample has a known component
    """
    if kind == 'lengths':
        names, in_um = [f'bar{k + 1}' for k in range(6)], [True] * 6
    else:
        names, in_um = list(POSE_NAMES), [k < 3 for k in range(6)]
    e = np.asarray(errors, dtype=np.float64)
    known = [k for k in range(6) if np.isfinite(e[:, k]).mean() >= 0.5]
    if not known:
        return None
    use = np.asarray(valid, dtype=bool) & np.all(np.isfinite(e[:, known]), axis=1) \
        & np.all(np.isfinite(covariance[:, known][:, :, known].reshape(len(e), -1)), axis=1)
    if not use.any():
        return None
    err = e[use][:, known]
    if not absolute:
        err = err - err.mean(axis=0)
    cov = covariance[use][:, known][:, :, known].astype(np.float64)
    ref = np.zeros(len(known))
    if reference_sigma is not None:
        ref = np.nan_to_num(np.asarray(reference_sigma, dtype=np.float64)[known]) ** 2
        cov = cov + np.diag(ref)
    predicted = np.sqrt(np.mean(np.diagonal(cov, axis1=1, axis2=2), axis=0))
    observed = np.sqrt(np.mean(err * err, axis=0))
    d2 = np.einsum('ni,ni->n', err, np.linalg.solve(cov, err[:, :, None])[:, :, 0])
    z = float(chi2.ppf(level, 1) ** 0.5)
    per = np.mean(np.abs(err) <= z * np.sqrt(np.diagonal(cov, axis1=1, axis2=2)), axis=0)
    rows = []
    for j, k in enumerate(known):
        to = um if in_um[k] else arcsec
        rows.append({'name': names[k], 'unit': 'um' if in_um[k] else 'arcsec',
                     'predicted_sigma': float(to(predicted[j])),
                     'observed_sigma': float(to(observed[j])),
                     'ratio': float(predicted[j] / observed[j]) if observed[j] > 0 else None,
                     'reference_sigma': float(to(np.sqrt(ref[j]))),
                     'within_interval': float(per[j])})
    out = {'kind': kind, 'samples': int(use.sum()), 'components': [names[k] for k in known],
           'offset_removed': not absolute, 'level': level,
           'ellipsoid_coverage': float(np.mean(d2 <= chi2.ppf(level, len(known)))),
           'ellipsoid_quantile': float(chi2.ppf(level, len(known))),
           'per_component': rows}
    cols = None if tails is None else np.asarray(tails, dtype=np.float64)[use][:, known]
    has = None if cols is None else np.all(np.isfinite(cols.reshape(len(cols), -1)), axis=1)
    if has is not None and has.any():   # (the samples whose tails were computed)
        q = region_quantile(cov[has], cols[has], level)
        out['region_coverage'] = float(np.mean(d2[has] <= q))
        out['region_samples'] = int(has.sum())
        out['region_quantile'] = [float(v) for v in np.percentile(q, [5, 50, 95])]
    return out


class CoverageAccumulator:
    """:func:`coverage` of a run given block by block, in bounded memory: the errors and
    covariances of the measurements are kept, every sample up to ``max_samples``, then every
    second, fourth... kept sample (a stride that doubles), so a long run is judged on samples
    spread evenly over all of it. The report says the stride (``every``).
    """

    #: samples kept at most by default
    MAX_SAMPLES = 100_000

    def __init__(self, max_samples: int = MAX_SAMPLES) -> None:
        self.max_samples = max_samples
        self.every = 1
        self._seen = 0          # measurements offered so far (the stride counts from the first)
        self._errors: list[FloatArray] = []
        self._cov: list[FloatArray] = []
        self._tails: list[FloatArray] = []
        self._kept = 0

    def add(self, errors: FloatArray, covariance: FloatArray, valid: NDArray[np.bool_],
            tails: FloatArray | None = None) -> None:
        """errors (N, 6) [m, rad]; covariance (N, 6, 6); valid (N,): the measurements; tails
        (N, 6, K) the covariance's light-tailed directions, or None (then for every block)"""
        c = np.asarray(covariance)
        v = np.asarray(valid, dtype=bool) & np.isfinite(c[:, 0, 0])   # (rows not computed: NaN)
        e, c = np.asarray(errors, dtype=np.float64)[v], c[v]
        index = self._seen + np.arange(e.shape[0])
        self._seen += e.shape[0]
        keep = index % self.every == 0
        self._errors.append(e[keep])
        self._cov.append(c[keep])
        if tails is not None:
            self._tails.append(np.asarray(tails)[v][keep])
        self._kept += int(keep.sum())
        while self._kept > self.max_samples:
            self._errors = [np.concatenate(self._errors)[::2]]
            self._cov = [np.concatenate(self._cov)[::2]]
            if self._tails:
                self._tails = [np.concatenate(self._tails)[::2]]
            self.every *= 2
            self._kept = self._errors[0].shape[0]

    def offsets(self) -> tuple[list[int], FloatArray, FloatArray] | None:
        """The known components, the median of their errors (MMD - reference) over the kept
        samples and the RMS of their predicted sigma [m, rad], or None when nothing is kept."""
        if not self._kept:
            return None
        e, c = np.concatenate(self._errors), np.concatenate(self._cov)
        known = [k for k in range(6) if np.isfinite(e[:, k]).mean() >= 0.5]
        use = np.all(np.isfinite(e[:, known]), axis=1)
        if not known or not use.any():
            return None
        var = np.diagonal(c[use][:, known][:, :, known], axis1=1, axis2=2)
        return known, np.median(e[use][:, known], axis=0), np.sqrt(np.mean(var, axis=0))

    def report(self, *, absolute: bool, reference_sigma: FloatArray | None = None,
               level: float = 0.95, kind: str = 'pose') -> dict[str, object] | None:
        """What :func:`coverage` says of the kept samples (``kind`` as there), with
        ``every``."""
        if not self._kept:
            return None
        e, c = np.concatenate(self._errors), np.concatenate(self._cov)
        tails = np.concatenate(self._tails) if self._tails else None
        out = coverage(e, c, np.ones(e.shape[0], dtype=bool), absolute=absolute,
                       reference_sigma=reference_sigma, level=level,
                       tails=tails if tails is not None and len(tails) == len(e) else None,
                       kind=kind)
        if out is not None:
            out['every'] = self.every
        return out


def format_coverage(report: dict[str, object]) -> str:
    """A fixed-width table of :func:`coverage`."""
    level = 100 * float(report['level'])  # type: ignore[arg-type]
    what = 'bar length' if report.get('kind') == 'lengths' else 'pose'
    lines = [f'{what} uncertainty against the reference ({report["samples"]} samples'
             + (', offset removed' if report['offset_removed'] else '') + '):',
             f'  {"component":<10} {"unit":>7} {"predicted":>10} {"observed":>10} {"ratio":>7} '
             f'{"in ±" + format(level, ".0f") + "%":>9}']
    for r in report['per_component']:  # type: ignore[attr-defined]
        ratio = f'{r["ratio"]:.2f}' if r['ratio'] is not None else '–'
        lines.append(f'  {r["name"]:<10} {r["unit"]:>7} {r["predicted_sigma"]:>10.4f} '
                     f'{r["observed_sigma"]:>10.4f} {ratio:>7} {100 * r["within_interval"]:>8.1f}%')
    read = report.get('reference_sigma_estimated') or []
    if read:
        lines.append('  the reference\'s own noise, which the log does not state, read from the data '
                     '(added to the predicted): ' + ', '.join(
                         f'{r["name"]} {r["reference_sigma"]:.2g} {r["unit"]}'
                         for r in report['per_component'] if r['name'] in read))  # type: ignore[attr-defined]
    share = float(report['ellipsoid_coverage'])  # type: ignore[arg-type]
    size = float(report['ellipsoid_quantile'])  # type: ignore[arg-type]
    lines.append(f'  {level:.0f} % ellipsoid of the known components covers {100 * share:.1f} % of '
                 f'the samples (Mahalanobis d² <= {size:.2f}, a Gaussian\'s)')
    if 'region_coverage' in report:
        q = report['region_quantile']
        lines.append(f'  the budget\'s own {level:.0f} % region, sized by its sources\' forms '
                     f'(d² <= {q[1]:.2f}; {q[0]:.2f}-{q[2]:.2f}), covers '  # type: ignore[index]
                     f'{100 * float(report["region_coverage"]):.1f} %')  # type: ignore[arg-type]
    return '\n'.join(lines)
