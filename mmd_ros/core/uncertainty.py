"""The uncertainty of every compensated bar length and of the pose it gives (ROS-free).

Every sample carries a covariance of the six compensated bar lengths, Sigma_d (6 x 6, not
diagonal where a source is shared between bars), built from what is known about this device and
this calibration, and propagated to the pose as Sigma_p = J^-1 Sigma_d J^-T (translation rows and
columns times the plates' scale, as :class:`~mmd_ros.core.pipeline.Pipeline` solves the FK on
d / s). The sources, their formulas and where their numbers come from are documented in
``msg_docs/frames.md``; in short (Delta the encoder resolution, sigma_n a channel's read noise,
h_j(d) the hat functions of Eq. (10) — weights 1 - u and u of the two calibration points around
d):

=========================  ==========================================================  ========
source                     contribution to Sigma_d                                     shared
=========================  ==========================================================  ========
``quantisation``           Delta^2 / 12                                                no
``read_noise``             sigma_n,i^2 (from the stream, else the calibration)         no
``reference_bar``          Delta^2/12 + sigma_n,ref^2 + u_zero^2 - 2 C(eps) (Eq. 13:   all bars
                           every bar minus the same eps) + its cyclic error's change
                           a^2 (1 - cos(2 pi eps / p))
``calibration_points``     u_p^2 ((1 - u)^2 + u^2)                                     no
``calibration_drift``      known error (1 - u) beta_j + u beta_j+1 (the routine's      yes
                           temperature drift, measured by the reference bar)
``reference_distances``    sum_j h_j(d_i) h_j(d_k) u_dr,j^2 (Table 2, CMM)              yes
``interpolation``          V_i(d_i): variance of e - L, e a smooth random scale       no
                           error fitted to the points, L its Eq. (10) interpolant
``subdivision``            a^2 / 2 (1 + (1 - u)^2 + u^2): the encoders' cyclic error   no
                           (datasheet bound a), at the live count and the two points
``thermal_approximation``  known error -alpha_scale (d_i - d_ref) dT (the Eq. 12       yes
                           term Eq. 13 drops)
``thermal_mismatch``       (f eps_i)^2 / 2 per bar, + (f eps_ref)^2 / 2 in every       all bars
                           entry (the reference bar is one of the bars; section 4.1);
                           off with a fitted ``thermal_gain``
``plate_scale``            (a_p |dT| u_rel)^2 w w^T, w_i = n_i . (R a_i - b_i): the     all bars
                           plates' expansion estimated at dT, as uncertain as the
                           bars' sensitivity S (rod CTE's uncertainty, the reference
                           bar's mismatch)
``hysteresis``             known error -h_i s_i(t) (friction, measured by the          yes
                           two-sided calibration); when a model term compensates it,
                           h_i^2 / 3 exp(-2 p_i / travel): the start state it cannot
                           know (rectangular in [-1, 1]), forgotten along the path p_i
``fitted_terms``           sum_k c_k c_k^T, c_k one sigma of the fitted correction     yes
                           along a principal direction
``residual``               what ``mmd analyze`` left, per bar (6 x 6)                  yes
=========================  ==========================================================  ========

The known errors (their size and sign follow from what the device measured, but the paper's
compensation does not correct them) are added up into one vector b, which enters as b b^T.

The quantisation of an *averaged* reading (a calibration point, the thermal zero) is not
Delta^2 / 12 / N: with read noise small against a count the average keeps a bias that depends on
where the true value lies within the count. Over that unknown position its variance is

    b^2(sigma) = sum_k Delta^2 / (2 pi^2 k^2) exp(-4 pi^2 k^2 sigma^2 / Delta^2)

(Delta^2 / 12 without noise, negligible beyond sigma ~ Delta / 2), and the mean variance of the
readings within a capture, over the same unknown position, is
g(sigma) = Delta^2 / 12 + sigma^2 - b^2(sigma): the calibration routine measures g and solves it
for sigma (:func:`read_noise_from_dither`).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq, minimize
from scipy.stats import chi2

from mmd_ros.core import validate
from mmd_ros.core.kinematics import propagate_covariance
from mmd_ros.core.piecewise import segment

__all__ = [
    'CalibrationUncertainty', 'InterpolationError', 'capture_var', 'NoiseEstimator', 'averaged_quantisation_var',
    'dither_var', 'fit_interpolation_error', 'hat_weights', 'hysteresis_claim',
    'pose_covariance',
    'quantisation_cross_cov',
    'quantisation_cross_weights',
    'read_noise_from_dither', 'region_quantile', 'tail_columns', 'two_sided_figures',
]

FloatArray = NDArray[np.float64]

_HARMONICS = np.arange(1, 65, dtype=np.float64)


def _tail(c: float) -> float:
    """sum_{k > K} exp(-c k^2) / (2 pi^2 k^2) for the K harmonics summed (an integral bound,
    exact at c = 0 to 1 / (2 pi^2 K)^2 relative)."""
    k = float(_HARMONICS[-1])
    return math.exp(-c * (k + 0.5) ** 2) / (2.0 * math.pi ** 2 * (k + 0.5))


# -- quantisation of a dithered reading ----------------------------------------------------------
def averaged_quantisation_var(resolution_m: float, noise_m: float) -> float:
    """b^2(sigma) [m^2]: variance, over the unknown position of the true value within a count, of
    the bias of the mean of many quantised readings with Gaussian read noise ``noise_m``."""
    r = float(resolution_m)
    s = max(float(noise_m), 0.0)
    c = 4.0 * math.pi ** 2 * s * s / (r * r)
    terms = r * r / (2.0 * math.pi ** 2 * _HARMONICS ** 2) * np.exp(-c * _HARMONICS ** 2)
    return float(terms.sum()) + r * r * _tail(c)


def quantisation_cross_weights(resolution_m: float, noise_a_m: float, noise_b_m: float) -> FloatArray:
    """The weights of the harmonics k = 1.. of :func:`quantisation_cross_cov` [m^2]."""
    r = float(resolution_m)
    k = _HARMONICS
    return r * r / (2.0 * math.pi ** 2 * k ** 2) * np.exp(
        -2.0 * math.pi ** 2 * k ** 2 * (noise_a_m ** 2 + noise_b_m ** 2) / (r * r))


def quantisation_cross_cov(resolution_m: float, noise_a_m: float, noise_b_m: float,
                           delta_m: FloatArray) -> FloatArray:
    """Covariance, over the unknown position x within a count, of the quantisation biases of
    two (averaged) readings of x and of x + delta with read noise a and b [m^2]:
    sum_k Delta^2 / (2 pi^2 k^2) exp(-2 pi^2 k^2 (a^2 + b^2) / Delta^2) cos(2 pi k delta / Delta).
    With a = b and delta = 0 it is :func:`averaged_quantisation_var`."""
    d = np.asarray(delta_m, dtype=np.float64)
    w = quantisation_cross_weights(resolution_m, noise_a_m, noise_b_m)
    return np.cos(2.0 * math.pi * d[..., None] * _HARMONICS / float(resolution_m)) @ w





def capture_var(resolution_m: float, noise_m: float, samples: int) -> float:
    """Variance of one averaged capture of a still value [m^2]: the quantisation bias b^2 left
    in the mean and the mean's standard error over ``samples`` readings, g(sigma) / N (the
    readings vary by g, dither and noise together)."""
    return averaged_quantisation_var(resolution_m, noise_m) + dither_var(resolution_m, noise_m) / max(
        int(samples), 1)


def dither_var(resolution_m: float, noise_m: float) -> float:
    """g(sigma) [m^2]: mean variance of quantised readings of a still value with read noise
    ``noise_m``, over the unknown position of that value within a count."""
    r = float(resolution_m)
    return r * r / 12.0 + noise_m * noise_m - averaged_quantisation_var(r, noise_m)


def read_noise_from_dither(resolution_m: float, mean_var_m2: float) -> float:
    """The read noise sigma [m] whose :func:`dither_var` is ``mean_var_m2``: g is 0 at sigma = 0
    and increases, so the inverse is unique (0 for a reading that never toggles)."""
    v = float(mean_var_m2)
    if not v > dither_var(resolution_m, 0.0):
        return 0.0
    hi = max(math.sqrt(v), float(resolution_m)) * 4.0
    if dither_var(resolution_m, hi) <= v:
        return math.sqrt(max(v - resolution_m ** 2 / 12.0, 0.0))
    return float(brentq(lambda s: dither_var(resolution_m, s) - v, 0.0, hi, xtol=1e-13))


# -- two-sided calibration ------------------------------------------------------------------------
def two_sided_figures(short_m: list[FloatArray], long_m: list[FloatArray], point_bias_var_m2: float
                      ) -> tuple[FloatArray, float, int]:
    """Friction hysteresis and seating repeatability from bars seated on each pair twice, once
    from shorter (the guide lengthens into the sockets) and once from longer.

    short_m, long_m : per bar, ndarray (n_b,) — its two readings on each of its pairs, as CDF
        lengths (the mean of the two is the calibration point) [m]
    point_bias_var_m2 : b^2 of one averaged capture [m^2]
    returns : h (B,) — half the mean difference long - short per bar [m] (a bar reads long
        when it was last shortened by h); the seating repeatability sigma_s [m], from the scatter
        of the half differences about their bar's mean (var = sigma_s^2 / 2 + b^2 / 2), pooled
        over bars; its degrees of freedom
    """
    halves = [0.5 * (np.asarray(lo, dtype=np.float64) - np.asarray(sh, dtype=np.float64))
              for sh, lo in zip(short_m, long_m)]
    h = np.array([v.mean() if v.size else 0.0 for v in halves])
    dof = int(sum(max(v.size - 1, 0) for v in halves))
    if dof <= 0:
        return h, math.nan, 0
    pooled = float(sum(np.sum((v - v.mean()) ** 2) for v in halves if v.size) / dof)
    return h, math.sqrt(max(2.0 * pooled - point_bias_var_m2, 0.0)), dof


def hysteresis_claim(estimates_m: FloatArray, estimate_var_m2: FloatArray | float) -> FloatArray:
    """Each bar's friction hysteresis as the budget claims it, from a two-sided calibration's
    estimates (:func:`two_sided_figures`), (B,) [m].

    An estimate is the bar's h plus the mean of its pairs' seating differences, of variance
    v = (one placement's variance) / (2 pairs) per bar (``estimate_var_m2``, scalar or (B,)): a
    bar without friction still reads a few tens of nanometres of it where its placements seat
    loosely, and claiming that as live friction over-states every pose. The bars' h are taken as
    drawn from one spread tau^2 = max(mean(estimate^2 - v), 0) (the bars of one type); each
    bar's posterior, its estimate shrunk by tau^2 / (tau^2 + v) with the variance
    tau^2 v / (tau^2 + v), gives the root of its expected square, claimed as h."""
    est = np.asarray(estimates_m, dtype=np.float64)
    v = np.broadcast_to(np.asarray(estimate_var_m2, dtype=np.float64), est.shape)
    if not est.size:
        return est.copy()
    tau2 = max(float(np.mean(est * est - v)), 0.0)
    with np.errstate(invalid='ignore', divide='ignore'):
        w = np.where(tau2 + v > 0.0, tau2 / (tau2 + v), 1.0)
    return np.sqrt((w * est) ** 2 + w * v)


# -- interpolation between calibration points -----------------------------------------------------
def _matern52(r: FloatArray, length_m: float) -> FloatArray:
    a = math.sqrt(5.0) * np.abs(r) / length_m
    return (1.0 + a + a * a / 3.0) * np.exp(-a)


@dataclass(frozen=True)
class InterpolationError:
    """A bar's scale error between calibration points as a smooth random function: zero-mean
    Gaussian, Matérn-5/2 covariance of amplitude ``sigma_m`` and correlation length
    ``length_m`` (any straight-line part is what Eq. 10 removes exactly). The CDF interpolates
    it linearly between the points, so what is left at a length d between points x_j and x_j+1
    (fraction u) has the variance

        V(d) = sigma^2 [1 + (1-u)^2 + u^2 - 2 (1-u) rho(d - x_j) - 2 u rho(x_j+1 - d)
                        + 2 u (1-u) rho(x_j+1 - x_j)]

    zero at the points and largest mid-segment (rho the correlation function)."""

    sigma_m: float
    length_m: float
    dof: int = 0

    def correlation(self, distance_m: FloatArray) -> FloatArray:
        """rho: the correlation of the error at two lengths ``distance_m`` apart (0 where the
        fit found no error)."""
        d = np.asarray(distance_m, dtype=np.float64)
        if self.sigma_m <= 0.0 or self.length_m <= 0.0:
            return np.zeros_like(d)
        return _matern52(d, self.length_m)

    def variance(self, lengths_m: FloatArray, knots_m: FloatArray) -> FloatArray:
        """V at ``lengths_m`` (N, B) for bars with knots ``knots_m`` (B, n), shape (N, B) [m^2].
        Beyond the end points the end segment is extrapolated, as the CDF does."""
        x = np.asarray(lengths_m, dtype=np.float64)
        out = np.empty_like(x)
        if self.sigma_m <= 0.0:
            out[:] = 0.0
            return out
        for b in range(x.shape[1]):
            kn = knots_m[b]
            seg, u = segment(x[:, b], kn)
            x0, x1 = kn[seg], kn[seg + 1]
            rho = self.correlation
            out[:, b] = (1.0 + (1 - u) ** 2 + u ** 2 - 2 * (1 - u) * rho(x[:, b] - x0)
                         - 2 * u * rho(x1 - x[:, b]) + 2 * u * (1 - u) * rho(x1 - x0))
        return np.maximum(out, 0.0) * self.sigma_m ** 2

    def covariance(self, a_m: FloatArray, b_m: FloatArray, knots_m: FloatArray) -> FloatArray:
        """Of one bar with knots ``knots_m`` (n,): the covariance of what is left at the
        lengths ``a_m`` (p,) with what is left at ``b_m`` (q,), (p, q) [m^2] (the error less
        its linear interpolation through the points; :meth:`variance` is its diagonal)."""
        a, b = np.asarray(a_m, dtype=np.float64), np.asarray(b_m, dtype=np.float64)
        if self.sigma_m <= 0.0:
            return np.zeros((a.size, b.size))
        kn = np.asarray(knots_m, dtype=np.float64)
        wa, wb = hat_weights(a, kn), hat_weights(b, kn)
        rho = self.correlation
        out = (rho(a[:, None] - b[None, :]) - rho(a[:, None] - kn[None, :]) @ wb.T
               - wa @ rho(kn[:, None] - b[None, :]) + wa @ rho(kn[:, None] - kn[None, :]) @ wb.T)
        return out * self.sigma_m ** 2

    def as_dict(self) -> dict[str, Any]:
        return {'sigma_um': round(self.sigma_m * 1e6, 6), 'length_mm': round(self.length_m * 1e3, 3),
                'dof': self.dof}


def hat_weights(x_m: FloatArray, knots_m: FloatArray) -> FloatArray:
    """The weights of a bar's points ``knots_m`` (n,) in the piecewise-linear interpolation at
    ``x_m`` (p,), (p, n); the end segments extrapolated, as Eq. (10) does."""
    n = knots_m.size
    seg, u = segment(x_m, knots_m)
    out = np.zeros((x_m.size, n))
    rows = np.arange(x_m.size)
    out[rows, seg] = 1.0 - u
    out[rows, seg + 1] = u
    return out


def fit_interpolation_error(knots_m: FloatArray, deviations_m: FloatArray,
                            point_var_m2: FloatArray) -> InterpolationError:
    """Amplitude and correlation length of the scale error, by restricted maximum likelihood
    over every bar's calibration points, pooled (universal kriging with a straight line per
    bar: the line is what the CDF removes exactly).

    knots_m : ndarray, shape (B, n) — each bar's calibration distances, increasing [m]
    deviations_m : ndarray, shape (B, n) — what each bar's encoder read at its points minus the
        reference distance, at the nominal resolution [m] (any line in it is irrelevant)
    point_var_m2 : ndarray, shape (B, n) — the points' own variance (the nugget) [m^2]

    The fit is kept for the last few calibrations it was made for (every pipeline and every
    trial of an analysis builds a budget of the same calibration; the fit takes 0.25 s).
    """
    knots = np.ascontiguousarray(knots_m, dtype=np.float64)
    dev = np.ascontiguousarray(deviations_m, dtype=np.float64)
    nug = np.ascontiguousarray(np.broadcast_to(point_var_m2, knots.shape), dtype=np.float64)
    key = (knots.shape, knots.tobytes(), dev.tobytes(), nug.tobytes())
    with _INTERPOLATION_LOCK:
        found = _INTERPOLATION_FITS.get(key)
    if found is None:
        found = _fit_interpolation_error(knots, dev, nug)
        with _INTERPOLATION_LOCK:      # (nodes build budgets from several threads)
            _INTERPOLATION_FITS[key] = found
            while len(_INTERPOLATION_FITS) > INTERPOLATION_FITS_KEPT:
                del _INTERPOLATION_FITS[next(iter(_INTERPOLATION_FITS))]
    return found


#: How many interpolation fits :func:`fit_interpolation_error` keeps (oldest dropped first).
INTERPOLATION_FITS_KEPT = 16
_INTERPOLATION_FITS: dict[tuple[Any, ...], InterpolationError] = {}
_INTERPOLATION_LOCK = threading.Lock()


def _fit_interpolation_error(knots: FloatArray, dev: FloatArray, nug: FloatArray
                             ) -> InterpolationError:
    bars = [b for b in range(knots.shape[0]) if knots.shape[1] >= 4]
    if not bars:
        return InterpolationError(0.0, 1.0, 0)
    spans = knots[:, -1] - knots[:, 0]
    gaps = np.diff(knots, axis=1)
    lo_l, hi_l = float(gaps.min()) * 0.5, float(spans.max()) * 4.0
    scale = float(np.std(dev - dev.mean(axis=1, keepdims=True))) or 1e-9
    dof = sum(knots.shape[1] - 2 for _ in bars)

    def nll(params: FloatArray) -> float:
        log_s, log_l = params
        s2 = (scale * math.exp(log_s)) ** 2
        ell = math.exp(log_l)
        total = 0.0
        for b in bars:
            x = knots[b]
            k = s2 * _matern52(x[:, None] - x[None, :], ell) + np.diag(nug[b] + 1e-30)
            f = np.column_stack([np.ones_like(x), (x - x.mean()) / (float(np.ptp(x)) or 1.0)])
            try:
                c = np.linalg.cholesky(k)
            except np.linalg.LinAlgError:
                return 1e30
            ki_f = np.linalg.solve(k, f)
            ki_y = np.linalg.solve(k, dev[b])
            ftkf = f.T @ ki_f
            beta = np.linalg.solve(ftkf, f.T @ ki_y)
            r = dev[b] - f @ beta
            total += (2.0 * np.sum(np.log(np.diag(c))) + np.linalg.slogdet(ftkf)[1]
                      + float(r @ np.linalg.solve(k, r)))
        return 0.5 * total

    best = None
    for log_s in np.linspace(-6.0, 2.0, 9):
        for log_l in np.linspace(math.log(lo_l), math.log(hi_l), 7):
            v = nll(np.array([log_s, log_l]))
            if best is None or v < best[0]:
                best = (v, log_s, log_l)
    assert best is not None
    res = minimize(nll, np.array(best[1:]), method='L-BFGS-B',
                   bounds=[(-12.0, 4.0), (math.log(lo_l), math.log(hi_l))])
    log_s, log_l = (res.x if res.fun <= best[0] else best[1:])
    return InterpolationError(scale * math.exp(log_s), math.exp(log_l), dof)


# -- read noise from the stream -------------------------------------------------------------------
class NoiseEstimator:
    """The read noise of each channel, estimated from the stream itself where it stands still.

    The samples are cut into windows of ``window`` samples (counted from the start of the run);
    a column whose values span at most ``rest_counts`` counts in a window stands still there,
    and the window's variance (about a straight line, which removes a slow thermal creep) is
    one capture of the dither of a still reading. Their mean over all such windows so far is
    g(sigma) of :func:`dither_var`, solved for sigma as the calibration routine does. A column
    needs ``min_windows`` windows before it has an estimate (NaN until then).

    columns : number of columns fed (e.g. six CDF lengths and the reference bars' errors)
    resolution_m : one count [m]
    """

    def __init__(self, columns: int, resolution_m: float, *, window: int = 64,
                 rest_counts: float = 3.0, min_windows: int = 20) -> None:
        self.columns = int(columns)
        self.resolution_m = float(resolution_m)
        self.window = int(window)
        self.rest_m = float(rest_counts) * self.resolution_m
        self.min_windows = int(min_windows)
        # g(sigma) on a grid, for a fast inverse
        r = self.resolution_m
        self._sigma_grid = np.concatenate([[0.0], np.geomspace(1e-3 * r, 20.0 * r, 400)])
        self._g_grid = np.array([dither_var(r, v) for v in self._sigma_grid])
        self.reset()

    def reset(self) -> None:
        self._buffer = np.zeros((self.window, self.columns))   # the window being filled
        self._fill = 0
        self.sum_var = np.zeros(self.columns)
        self.windows = np.zeros(self.columns, dtype=np.int64)
        self._now: FloatArray | None = None

    def _invert(self, mean_var: FloatArray) -> FloatArray:
        v = np.asarray(mean_var, dtype=np.float64)
        out = np.interp(v, self._g_grid, self._sigma_grid)
        big = v > self._g_grid[-1]
        out[big] = np.sqrt(np.maximum(v[big] - self.resolution_m ** 2 / 12.0, 0.0))
        return out

    def _estimate(self, sum_var: FloatArray, windows: FloatArray) -> FloatArray:
        ok = windows >= self.min_windows
        mean = np.where(ok, sum_var / np.maximum(windows, 1), 0.0)
        return np.where(ok, self._invert(mean), np.nan)

    def sigma_m(self) -> FloatArray:
        """Read noise per column after everything fed so far [m], NaN where too few still
        windows were seen."""
        if self._now is None:
            self._now = self._estimate(self.sum_var, self.windows.astype(np.float64))
        return self._now

    def feed(self, values_m: FloatArray) -> FloatArray:
        """Add N consecutive samples, shape (N, columns) [m] (a window with a NaN is skipped).

        returns : ndarray, shape (N, columns) — the estimate in force at each sample: from the
            windows completed up to and including it (so a stream fed piecewise gets what one
            call gives)
        """
        v = np.asarray(values_m, dtype=np.float64).reshape(-1, self.columns)
        offset = self._fill
        w = self.window
        if offset + v.shape[0] < w:   # the common case of a stream: no window completes
            self._buffer[offset:offset + v.shape[0]] = v
            self._fill = offset + v.shape[0]
            return np.broadcast_to(self.sigma_m(), v.shape)
        buf = np.concatenate([self._buffer[:offset], v]) if offset else v
        full = buf.shape[0] // w
        out = np.broadcast_to(self.sigma_m(), v.shape).copy()
        if full:
            blocks = buf[:full * w].reshape(full, w, self.columns)
            finite = np.all(np.isfinite(blocks), axis=1)
            b = np.nan_to_num(blocks)
            still = finite & (np.ptp(b, axis=1) <= self.rest_m)
            t = np.arange(w, dtype=np.float64) - 0.5 * (w - 1)
            centred = b - b.mean(axis=1, keepdims=True)
            slope = np.einsum('t,btc->bc', t, centred) / float(t @ t)
            resid = centred - slope[:, None, :] * t[None, :, None]
            var = np.where(still, np.sum(resid * resid, axis=1) / (w - 2), 0.0)
            cum_var = self.sum_var + np.cumsum(var, axis=0)           # (full, C)
            cum_n = self.windows + np.cumsum(still, axis=0)
            est = self._estimate(cum_var, cum_n.astype(np.float64))
            done = (offset + np.arange(v.shape[0]) + 1) // w           # windows completed
            has = done > 0
            out[has] = est[np.minimum(done[has], full) - 1]
            self.sum_var = cum_var[-1].copy()
            self.windows = cum_n[-1].copy()
            self._now = None
        rest = buf[full * w:]
        self._buffer[:rest.shape[0]] = rest
        self._fill = rest.shape[0]
        return out


# -- the calibration's figures --------------------------------------------------------------------
#: Keys of a calibration file's ``uncertainty`` section.
CALIBRATION_UNCERTAINTY_KEYS = (
    'approaches', 'read_noise_nm', 'capture_samples', 'hysteresis_um', 'seating_repeatability_nm',
    'seating_dof', 'routine_temp_change_c', 'routine_temp_sigma_c', 'drift_nm')
@dataclass(frozen=True)
class CalibrationUncertainty:
    """What the calibration routine measured about its own points (the ``uncertainty`` section
    of a calibration file). Every figure is optional: an old calibration has none.

    read_noise_m : read noise during the captures, from their dither (pooled) [m]
    capture_samples : samples averaged per capture
    approaches : 1 (one placement per pair, the paper's routine) or 2 (seated once from shorter,
        once from longer; the point is their mean)
    hysteresis_m : per bar channel, half the difference between the two approaches [m]
    seating_m : placement repeatability of a bar in a socket pair (1 sigma) [m]
    seating_dof : degrees of freedom behind ``seating_m``
    routine_temp_change_c : temperature change over the routine, from a reference bar read on
        its resting pair before the measuring bars and again at its thermal zero [°C]
    routine_temp_sigma_c : standard uncertainty of that change (two captures) [°C]
    drift_m : per bar channel and point (in the bar's pair order), the thermal error its point
        carries from being captured at another temperature than the thermal zero's (that
        change interpolated linearly in time, Fig. 10's sensitivity) [m]
    """

    read_noise_m: float | None = None
    capture_samples: int | None = None
    approaches: int = 1
    hysteresis_m: dict[str, float] = field(default_factory=dict)
    seating_m: float | None = None
    seating_dof: int = 0
    routine_temp_change_c: float | None = None
    drift_m: dict[str, list[float]] = field(default_factory=dict)
    routine_temp_sigma_c: float | None = None

    def point_var(self, resolution_m: float, stated_seating_m: float | None = None) -> float:
        """Variance of one calibration point [m^2]: the averaged quantisation b^2 and the
        averaging's standard error of the capture(s), and the seating repeatability (the
        routine's, else ``stated_seating_m``); a two-sided point is the mean of two captures."""
        s = self.read_noise_m or 0.0
        n = max(int(self.capture_samples or 1), 1)
        seating = self.seating_m if self.seating_m is not None else stated_seating_m
        one = capture_var(resolution_m, s, n) + (seating or 0.0) ** 2
        return one / max(self.approaches, 1)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {'approaches': self.approaches}
        if self.read_noise_m is not None:
            out['read_noise_nm'] = round(self.read_noise_m * 1e9, 4)
        if self.capture_samples is not None:
            out['capture_samples'] = int(self.capture_samples)
        if self.hysteresis_m:
            out['hysteresis_um'] = {k: round(v * 1e6, 5) for k, v in self.hysteresis_m.items()}
        if self.seating_m is not None:
            out['seating_repeatability_nm'] = round(self.seating_m * 1e9, 3)
            out['seating_dof'] = int(self.seating_dof)
        if self.routine_temp_change_c is not None:
            out['routine_temp_change_c'] = round(self.routine_temp_change_c, 6)
        if self.routine_temp_sigma_c is not None:
            out['routine_temp_sigma_c'] = round(self.routine_temp_sigma_c, 6)
        if self.drift_m:
            out['drift_nm'] = {k: [round(v * 1e9, 3) for v in vals] for k, vals in self.drift_m.items()}
        return out

    @classmethod
    def from_dict(cls, data: Any, source: str) -> CalibrationUncertainty:
        if data is None:
            return cls()
        f = validate.Fields(source)
        path = 'uncertainty'
        data = validate.mapping(data, source, path)
        f.known_keys(data, CALIBRATION_UNCERTAINTY_KEYS, path)

        def number(key: str, high: float, low: float = 0.0) -> float | None:
            return f.number(data, key, path, low=low, high=high) if data.get(key) is not None else None

        approaches = f.choice(data, 'approaches', path, (1, 2), default=1)
        noise = number('read_noise_nm', 1e6)
        samples = (validate.integer(data['capture_samples'], source, f'{path}.capture_samples', low=1)
                   if data.get('capture_samples') is not None else None)
        seating = number('seating_repeatability_nm', 1e6)
        dof = (validate.integer(data['seating_dof'], source, f'{path}.seating_dof', low=0)
               if data.get('seating_dof') is not None else 0)
        temp = number('routine_temp_change_c', 100.0, -100.0)
        temp_sigma = number('routine_temp_sigma_c', 100.0)
        hyst = f.mapping(data, 'hysteresis_um', path, default={}) or {}
        hysteresis = {str(k): validate.number(v, source, f'{path}.hysteresis_um.{k}', low=-1e3,
                                              high=1e3) * 1e-6 for k, v in hyst.items()}
        drift_raw = f.mapping(data, 'drift_nm', path, default={}) or {}
        drift = {str(k): (validate.floats(v, source, f'{path}.drift_nm.{k}', (-1,)) * 1e-9).tolist()
                 for k, v in drift_raw.items()}
        return cls(None if noise is None else noise * 1e-9, samples, int(approaches), hysteresis,
                   None if seating is None else seating * 1e-9, dof, temp, drift, temp_sigma)


def pose_covariance(jinv: FloatArray, length_cov_m2: FloatArray, plate_scale: FloatArray, *,
                    compiled: bool | None = None) -> FloatArray:
    """Sigma_p = J^-1 Sigma_d J^-T, translation rows and columns times the plates' scale s (the
    FK solves d / s with the nominal joints and scales the translation by s).

    jinv : ndarray, shape (N, 6, 6) — inverse Jacobians dd/dp at the solutions on d / s
    length_cov_m2 : ndarray, shape (N, 6, 6) — Sigma_d [m^2]
    plate_scale : ndarray, shape (N,)
    compiled : the compiled propagation (default: when it is in use); False: numpy
    returns : ndarray, shape (N, 6, 6) [m, rad]^2
    """
    scale = np.asarray(plate_scale, dtype=np.float64)
    # J is dd/dp of the lengths d / s, so the lengths' covariance is divided by s^2 first
    return propagate_covariance(jinv, length_cov_m2 / (scale * scale)[:, None, None], scale,
                                compiled=compiled)


def tail_columns(jinv: FloatArray, cumulant_m4: FloatArray, known_m: FloatArray,
                 plate_scale: FloatArray, known_shape: float = -2.0) -> FloatArray:
    """The pose-space directions c_k along which Sigma_p's error is lighter-tailed than a
    Gaussian, scaled so that a region's size can be read from them (:func:`region_quantile`):
    each bar's column of J^-1 times (-kappa_i)^(1/4), kappa_i its sources' fourth cumulant
    (:meth:`~mmd_ros.core.budget.LengthBudget.light_tails`), and J^-1 b times
    (-known_shape)^(1/4), b the known error; mapped as :func:`pose_covariance` maps Sigma_d.

    jinv : (N, 6, 6) inverse Jacobians on d / s; cumulant_m4 : (N, 6) [m^4], <= 0
    known_m : (N, 6) [m]; plate_scale : (N,)
    returns : (N, 6, 7) [m, rad]
    """
    scale = np.asarray(plate_scale, dtype=np.float64)
    bars = np.asarray(jinv) * np.maximum(-np.asarray(cumulant_m4), 0.0)[:, None, :] ** 0.25
    known = np.einsum('nij,nj->ni', jinv, known_m) * (-known_shape) ** 0.25
    cols = np.concatenate([bars, known[:, :, None]], axis=2) / scale[:, None, None]
    cols[:, :3] *= scale[:, None, None]
    return cols


def region_quantile(covariance: FloatArray, columns: FloatArray, level: float = 0.95
                    ) -> FloatArray:
    """The size q of the region d^2 = e^T Sigma^-1 e <= q that holds ``level`` of an error
    whose covariance is Sigma and whose light-tailed parts are ``columns``
    (:func:`tail_columns`), per sample: a Gaussian error gives chi^2_m(level); sources of
    bounded form (a rectangular quantisation, a sine, a known error) make d^2 vary less about its
    mean m, Var(d^2) = 2 m - sum_k (c_k^T Sigma^-1 c_k)^2 (the fourth cumulants of independent
    components), and q is read from the scaled chi^2 of that mean and variance
    (a chi^2_nu, a nu = m, 2 a^2 nu = Var(d^2): Satterthwaite's approximation).

    covariance : (N, m, m); columns : (N, m, K) in the same m components
    returns : (N,)
    """
    cov = np.asarray(covariance, dtype=np.float64)
    m = cov.shape[-1]
    lev = np.einsum('nik,nik->nk', columns, np.linalg.solve(cov, columns))
    var = np.clip(2.0 * m - np.sum(lev * lev, axis=1), 2e-3 * m, 2.0 * m)
    a = var / (2.0 * m)
    return a * chi2.ppf(level, m / a)
