"""The guided calibration on the reference plate (section 3.2), ROS-free.

An operator puts each ball bar on the reference plate's socket pairs one after the other; at
every placement the bar's encoder count, averaged over a settling window, and the pair's
reference distance d_r^j make one calibration point (q_i^j, d_r^j). Seven points make the bar's
centre distance function (Eq. 10). :class:`CalibrationRoutine` is the state machine behind
``/mmd/calibrate_bar``:

- **which placement comes next** (:meth:`CalibrationRoutine.next_step`): first the reference
  bar read on its resting pair (the temperature before the routine), then the measuring bars
  in bar order on dr1..dr7, then each reference bar on the other pairs and last on its resting
  pair, where it stays (as :meth:`mmd_ros.twin.TwinDevice.calibration_schedule`); the operator
  may select another bar or override the pair;
- **whether a capture is acceptable** (:meth:`CalibrationRoutine.capture`): the bar has settled
  (the counts' standard deviation and linear drift over the window are small) and the reading
  is plausible for that pair (its count differences to the bar's other points match the
  distance differences at the encoder resolution, or it matches the current calibration);
- **building the CDF** after a bar's seventh point, with quality figures (scale against the
  nominal resolution, nonlinearity, noise), merged into the calibration to be persisted;
- **the thermal zero** (Eq. 11): a reference bar's last placement is on its resting pair, and
  the offset f_ref(q_ref) - d_r read there becomes ``thermal_zero_m``;
- **quick re-reference** after a terminal counter reset (power loss): one placement on one
  pair re-establishes a bar's count offset and keeps the CDF shape. Reference bars go first
  (their thermal error is then zero at that moment); a measuring bar re-referenced on pair P
  is shifted so that its thermally compensated length equals d_P.

Nothing here knows about ROS, files or time: the caller passes the samples of the window, the
current time as text, and persists the :class:`Calibration` that a capture returns.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core.calibration import BarCalibration, Calibration, unix_seconds
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import CalibrationError
from mmd_ros.core.thermal import ReferenceBar, ThermalCompensation, thermal_sensitivity
from mmd_ros.core.uncertainty import (
    CalibrationUncertainty, capture_var, read_noise_from_dither, two_sided_figures,
)
from mmd_ros.core.units import M_PER_MM, M_PER_UM, PPM

__all__ = [
    'APPROACHES', 'CalibrationRoutine', 'CaptureResult', 'CaptureStats', 'RoutineSettings', 'Step',
    'Window', 'bar_quality', 'capture_uncertainty',
]

FloatArray = NDArray[np.float64]

KINDS = ('calibrate', 'thermal_zero', 're_reference', 'drift')
MODES = ('auto', 'full', 're_reference')
#: Largest change of a reference bar's reading on its resting pair over a routine taken for a
#: temperature change [m] (100 °C of the prototype's; a bar not on that pair at one end, in its
#: case or on another pair 16 mm away, reads millimetres off).
DRIFT_READING_LIMIT_M = 0.1e-3
#: How a bar is seated on a pair: from shorter (its guide lengthens into the sockets: friction
#: state +1) or from longer (-1); '' when the routine does not say.
APPROACHES = {'short': 1.0, 'long': -1.0}


@dataclass(frozen=True)
class CaptureStats:
    """One capture of the calibration routine, as its uncertainty needs it.

    channel, pair : the bar and the pair it sat on; approach : 'short', 'long' or ''
    mean_counts : the averaged count; var_counts2 : the counts' variance in the window
    samples : samples averaged
    time_s : middle of the window on any clock of the routine [s], NaN when unknown
    kind : 'point' (a calibration point or a thermal zero) or 'drift' (a reference bar on its
        resting pair before the measuring bars, to see the temperature change over the routine)
    """

    channel: str
    pair: str
    approach: str
    mean_counts: float
    var_counts2: float
    samples: int
    time_s: float = math.nan
    kind: str = 'point'


def capture_uncertainty(device: DeviceDescription, captures: list[CaptureStats],
                        cdfs: dict[str, Callable[[NDArray[np.float64]], Any]]
                        ) -> CalibrationUncertainty:
    """What a calibration's captures say about its own points (``msg_docs/frames.md``).

    - read noise: the captures' mean variance is g(sigma) of a still, quantised reading over
      its unknown position within a count (:func:`~mmd_ros.core.uncertainty.dither_var`),
      solved for sigma;
    - with two captures per pair, from shorter and from longer: each bar's friction hysteresis
      h (half their mean difference, as CDF lengths) and the seating repeatability (their
      scatter about h, pooled over bars);
    - with ``drift`` captures of a reference bar on its resting pair before the measuring bars
      (as it rests, or from short and from long with two approaches) and its captures there
      at the end (its thermal zero the last): the temperature change over the routine dT (the
      change of its reading over its sensitivity, Fig. 10, at the rate the two sides' mean
      times give; none when the reading moved more than :data:`DRIFT_READING_LIMIT_M`), and
      the thermal error every point carries from its capture time,
      -S(d_j) dT (t_ij - t_zero) / (t_zero - t_drift).

    cdfs : per bar, what reads its counts as lengths: its new CDF (the points are the captures'
        means) or anything that returns (lengths, ...) for an array of counts
    """
    resolution_m = device.encoder_resolution_m
    drifts = [c for c in captures if c.kind == 'drift']
    captures = [c for c in captures if c.kind != 'drift']
    if not captures:
        return CalibrationUncertainty()
    var = float(np.mean([c.var_counts2 for c in captures])) * resolution_m ** 2
    noise = read_noise_from_dither(resolution_m, var)
    samples = int(np.median([c.samples for c in captures]))
    by_bar: dict[str, dict[str, dict[str, float]]] = {}
    for c in captures:
        if c.approach in APPROACHES:
            by_bar.setdefault(c.channel, {}).setdefault(c.pair, {})[c.approach] = c.mean_counts
    short, long, names = [], [], []
    for name, pairs in by_bar.items():
        both = [p for p, v in pairs.items() if len(v) == 2]
        if len(both) < 2 or name not in cdfs:
            continue
        f = cdfs[name]
        short.append(f(np.array([pairs[p]['short'] for p in both]))[0])
        long.append(f(np.array([pairs[p]['long'] for p in both]))[0])
        names.append(name)
    bias = capture_var(resolution_m, noise, samples)
    if names:
        h, seating, dof = two_sided_figures(short, long, bias)
        hyst = dict(zip(names, (float(v) for v in h)))
        seating_m = None if not math.isfinite(seating) else seating
    else:
        hyst, seating_m, dof = {}, None, 0
    one = bias + (seating_m or 0.0) ** 2
    temp, drift, temp_sigma = _routine_drift(device, captures, drifts, cdfs, one)
    figures = CalibrationUncertainty(noise, samples, 2 if names else 1, hyst, seating_m, dof, temp,
                                     drift, temp_sigma)
    # at the precision the calibration file keeps, so that a saved calibration reads back equal
    return CalibrationUncertainty.from_dict(figures.to_dict(), '<calibration>')


def _routine_drift(device: DeviceDescription, points: list[CaptureStats], drifts: list[CaptureStats],
                   cdfs: dict[str, Callable[[NDArray[np.float64]], Any]], capture_var_m2: float
                   ) -> tuple[float | None, dict[str, list[float]], float | None]:
    """The temperature change over the routine, each point's thermal error (see
    :func:`capture_uncertainty`) and the change's standard uncertainty, from the first
    reference bar with a drift capture.

    A bar's reading on a pair depends on the friction state it was seated in, so the start and
    the end are compared in the same states: the approaches both have (a drift capture from
    each side against the two captures of the resting pair's point: each side's mean, the
    friction cancelled and each end an average of two seatings); with none in common (a capture
    taken as it came), the start against the last capture on the pair, the bar's resting
    placement. Its variance is ``capture_var_m2`` times each side's sum over its approaches of
    1 / (captures G^2), G the approaches, over the sensitivity squared: seating a bar anew
    scatters its reading (30 nm on the realistic twin, 0.07 °C of this change on the
    prototype's reference bar with one capture at each end)."""
    for channel in dict.fromkeys(c.channel for c in drifts):
        starts = [c for c in drifts if c.channel == channel and math.isfinite(c.time_s)]
        pair = starts[0].pair if starts else ''
        ends = [c for c in points if c.channel == channel and c.pair == pair
                and math.isfinite(c.time_s)]
        if not starts or not ends or channel not in cdfs:
            continue
        zero_s = max(c.time_s for c in ends)           # the last: the bar's resting placement
        ways = sorted({c.approach for c in starts} & {c.approach for c in ends} - {''})
        if ways:
            starts = [c for c in starts if c.approach in ways]
            ends = [c for c in ends if c.approach in ways]
        else:
            ends = [max(ends, key=lambda c: c.time_s)]
        f = cdfs[channel]

        def side(captures: list[CaptureStats]) -> tuple[float, float, float]:
            """The mean reading [m] and time [s] of captures, each approach weighing alike,
            and the reading's variance in units of one capture's."""
            groups = [[c for c in captures if c.approach == w or not ways] for w in ways or ['']]
            read = [float(np.mean(f(np.array([c.mean_counts for c in g]))[0])) for g in groups]
            return (float(np.mean(read)), float(np.mean([np.mean([c.time_s for c in g])
                                                         for g in groups])),
                    sum(1.0 / len(g) for g in groups) / len(groups) ** 2)

        (first, t0, v0), (last, t1, v1) = side(starts), side(ends)
        span = t1 - t0
        if not span > 0 or abs(last - first) > DRIFT_READING_LIMIT_M:
            continue    # (not on that pair at one end: no temperature moves it a millimetre)
        at_ref = thermal_sensitivity(device, device.pair(pair).distance_m)
        rate = (last - first) / at_ref / span               # [°C/s]
        times: dict[str, dict[str, list[float]]] = {}
        for c in points:
            if math.isfinite(c.time_s):
                times.setdefault(c.channel, {}).setdefault(c.pair, []).append(c.time_s)
        drift = {}
        for name, by_pair in times.items():
            pairs = [p for p in device.pairs if p.name in by_pair]
            drift[name] = [float(-thermal_sensitivity(device, p.distance_m) * rate
                                 * (np.mean(by_pair[p.name]) - zero_s)) for p in pairs]
        var = capture_var_m2 * (v0 + v1)
        return rate * (zero_s - t0), drift, math.sqrt(var) / abs(at_ref) * (zero_s - t0) / span
    return None, {}, None


@dataclass(frozen=True)
class RoutineSettings:
    """Acceptance limits of a capture.

    settle_std_m : largest standard deviation of the bar's reading over the window [m]
    settle_drift_m : largest linear drift of the reading across the window [m]
    min_samples : fewest samples a window must hold
    plausibility_m : largest disagreement between a reading and what the bar's other points
        (or the current calibration) predict for that pair [m]; a bar on the wrong pair is
        off by at least the 16 mm between two pairs
    thermal_mode : the model's thermal mode, used to re-reference measuring bars
    re_reference_pair : pair on which measuring bars are re-referenced; None: the middle one
    approaches : 1 — each bar once on each pair (the paper's routine); 2 — each bar on each
        pair twice, seated from shorter and from longer (the point is the mean: the friction
        state cancels, and half the difference and its scatter measure the bar's friction
        hysteresis and the seating repeatability). Either way a reference bar is read first
        on its resting pair (where the last routine left it; from both sides with 2): against
        its placement there at the end, the temperature drift over the routine
    """

    settle_std_m: float = 0.25e-6
    settle_drift_m: float = 0.25e-6
    min_samples: int = 20
    plausibility_m: float = 0.2e-3
    thermal_mode: str = 'auto'
    re_reference_pair: str | None = None
    approaches: int = 1

    def __post_init__(self) -> None:
        for name in ('settle_std_m', 'settle_drift_m', 'plausibility_m'):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise CalibrationError(f'{name} must be > 0, got {value}')
        if self.min_samples < 2:
            raise CalibrationError(f'min_samples must be >= 2, got {self.min_samples}')
        if self.approaches not in (1, 2):
            raise CalibrationError(f'approaches must be 1 or 2, got {self.approaches!r}')


@dataclass(frozen=True)
class Step:
    """One placement: put ``channel`` (a bar) on reference ``pair``.

    kind : 'calibrate' (a calibration point), 'thermal_zero' (a reference bar back on its
        resting pair to set Eq. 11's zero), 're_reference' (one point restores the count offset)
        or 'drift' (a reference bar on its resting pair before the measuring bars)
    approach : 'short' (seat it from shorter: the bar lengthens into the sockets), 'long' (from
        longer) or '' (as it comes)
    """

    kind: str
    channel: str
    pair: str
    approach: str = ''

    def describe(self, device: DeviceDescription) -> str:
        p = device.pair(self.pair)
        what = {'calibrate': '', 'thermal_zero': ' to set the thermal zero (Eq. 11)',
                're_reference': ' to re-reference it',
                'drift': ' to read the temperature before the measuring bars (it comes off '
                         'again)'}[self.kind]
        how = {'': '', 'short': ' from short (push it in, let it lengthen into the sockets)',
               'long': ' from long (pull it out, let it shorten into the sockets)'}[self.approach]
        return (f'place {self.channel} on {self.pair} (sockets {p.sockets[0]}-{p.sockets[1]}, '
                f'{p.distance_m / M_PER_MM:.4f} mm){how}{what}')


@dataclass(frozen=True)
class Window:
    """The samples a capture averages.

    counts : ndarray, shape (N, 8) — unwrapped counts of all channels, in time order
    duration_s : time the window spans [s]
    counter_reset : the terminal's counters were reset inside the window
    """

    counts: NDArray[np.float64]
    duration_s: float
    counter_reset: bool = False

    @classmethod
    def of(cls, counts: ArrayLike, duration_s: float, counter_reset: bool = False) -> Window:
        return cls(np.asarray(counts, dtype=np.float64).reshape(-1, 8), float(duration_s),
                   bool(counter_reset))


@dataclass(frozen=True)
class CaptureResult:
    """What a capture did.

    accepted : the point was taken; otherwise ``message`` says why not
    message : for the operator: what was captured or why not, and what to place next
    calibration : a new calibration to persist and publish, or None when it did not change
    completed : the bar whose CDF was just built, or None
    quality : that bar's quality figures (see :func:`bar_quality`)
    next_step : the placement that comes next, or None when the routine is complete
    """

    accepted: bool
    message: str
    step: Step | None
    calibration: Calibration | None = None
    completed: str | None = None
    quality: dict[str, Any] | None = None
    next_step: Step | None = None


@dataclass
class _Point:
    """A pair's capture(s) of one bar: per approach ('' , 'short', 'long') the mean count, the
    counts' standard deviation [m], the samples and the time [s] (NaN unknown)."""

    captures: dict[str, tuple[float, float, int, float]]

    @property
    def count(self) -> float:
        return float(np.mean([c[0] for c in self.captures.values()]))

    @property
    def std_m(self) -> float:
        return max(c[1] for c in self.captures.values())


def bar_quality(bar: BarCalibration, resolution_m: float, noise_m: float | None = None
                ) -> dict[str, float]:
    """Quality of a bar's CDF: a straight line through its points.

    scale_nm_per_count : slope of that line; scale_ppm : its deviation from the nominal
    encoder resolution; nonlinearity_um : the largest distance of a point from the line
    (what the CDF corrects, section 3.2); noise_um : the largest standard deviation of a
    capture (when known)
    """
    q = np.asarray(bar.counts, dtype=np.float64)
    d = np.asarray(bar.distances_m, dtype=np.float64)
    slope, intercept = np.polyfit(q - q.mean(), d, 1)
    residual = d - (intercept + slope * (q - q.mean()))
    out = {
        'scale_nm_per_count': round(float(abs(slope)) * 1e9, 6),
        'scale_ppm': round(float((abs(slope) - resolution_m) / resolution_m / PPM), 2),
        'nonlinearity_um': round(float(np.max(np.abs(residual))) / M_PER_UM, 4),
    }
    if noise_m is not None:
        out['noise_um'] = round(noise_m / M_PER_UM, 4)
    return out


def _seconds(when: str) -> float:
    """An ISO 8601 time as seconds since the epoch, NaN when it is not one."""
    stamp = unix_seconds(when)
    return math.nan if stamp is None else stamp


class CalibrationRoutine:
    """The calibration routine of one device (see the module docstring).

    device : the device description (channels, reference pairs, encoder resolution)
    calibration : the current calibration, or None
    settings : acceptance limits
    """

    def __init__(self, device: DeviceDescription, calibration: Calibration | None = None,
                 settings: RoutineSettings | None = None) -> None:
        self.device = device
        self.settings = settings or RoutineSettings()
        names = device.channel_names
        self._index = {n: k for k, n in enumerate(names)}
        self.measuring = [names[k] for k in device.measuring_channels]
        self.references = [c.name for c in device.reference_channels]
        self._resting = {c.name: c.pair for c in device.reference_channels}
        self.pair_names = [p.name for p in device.pairs]
        middle = self.pair_names[len(self.pair_names) // 2]
        rr = self.settings.re_reference_pair or middle
        if rr not in self.pair_names:
            raise CalibrationError(f're_reference_pair must be one of {self.pair_names}, got {rr!r}')
        self._re_reference_pair = rr
        self._points: dict[str, dict[str, _Point]] = {}
        self._order: dict[str, list[str]] = {}
        self._completed: set[str] = set()
        self._needs_zero: set[str] = set()
        self._captures: list[CaptureStats] = []
        self._drifts: dict[str, CaptureStats] = {}     # by approach
        self._last_approach: dict[str, str] = {}
        self.calibration: Calibration | None = None
        self.pending: list[str] = []
        self.set_calibration(calibration)

    # -- state ---------------------------------------------------------------------------------
    @property
    def bar_channels(self) -> list[str]:
        """Every channel with a bar: measuring bars in bar order, then reference bars."""
        return self.measuring + self.references

    def set_calibration(self, calibration: Calibration | None) -> None:
        """Use ``calibration`` (loaded or reloaded from its file). The session's points stay."""
        self.calibration = calibration
        self.pending = []
        if calibration is not None and not calibration.valid:
            listed = calibration.quality.get('pending_re_reference') if calibration.quality else None
            if isinstance(listed, list) and listed:
                self.pending = [str(c) for c in listed if str(c) in calibration.bars]
            else:
                self.pending = [c for c in self.bar_channels if c in calibration.bars]

    def reset_session(self) -> None:
        """Forget the points captured in this session (the calibration itself is unchanged)."""
        self._points.clear()
        self._order.clear()
        self._completed.clear()
        self._needs_zero.clear()
        self._captures.clear()
        self._drifts = {}

    def session_points(self, channel: str) -> dict[str, float]:
        """Counts captured in this session for ``channel``, by pair."""
        return {p: v.count for p, v in self._points.get(channel, {}).items()}

    def missing_bars(self) -> list[str]:
        """Bars the current calibration has no CDF for."""
        have = self.calibration.bars if self.calibration is not None else {}
        return [c for c in self.bar_channels if c not in have]

    def invalidate(self, reason: str, when: str) -> Calibration | None:
        """The terminal's counters were reset: every bar's count offset is lost.

        Returns the calibration marked invalid (to persist and publish), listing every bar as
        waiting for a re-reference, or None when there is no calibration.
        """
        cal = self.calibration
        if cal is None:
            return None
        pending = [c for c in self.bar_channels if c in cal.bars]
        quality = dict(cal.quality)
        quality['pending_re_reference'] = pending
        quality['invalidated'] = {'reason': reason, 'at': when}
        new = replace(cal, valid=False, quality=quality)
        self.set_calibration(new)
        # points captured before the reset have lost their zero as well
        self.reset_session()
        return new

    def align(self, counts: ArrayLike, counter_bits: int | None = None) -> Calibration | None:
        """Move each bar's calibration counts by whole multiples of the counter range 2^bits to
        the counts a driver session reports now (``counts``, shape (8,)).

        The terminal's counters wrap; a driver unwraps them from the first frame it sees, so two
        sessions agree modulo 2^bits only (``msg_docs/usb_protocol.md``). A bar spans about
        2.5 million counts, far less than 2^31, so the window of 2^bits around its calibrated
        span is unambiguous. Returns the moved calibration (same CDFs, exact shift), or None
        when nothing had to move.
        """
        cal = self.calibration
        if cal is None:
            return None
        period = float(1 << int(counter_bits or self.device.counter_bits))
        q = np.asarray(counts, dtype=np.float64).ravel()
        bars = dict(cal.bars)
        moved = []
        for name, bar in cal.bars.items():
            k = self._index.get(name)
            if k is None or not math.isfinite(q[k]):
                continue
            centre = 0.5 * (min(bar.counts) + max(bar.counts))
            turns = round((q[k] - centre) / period)
            if turns:
                bars[name] = BarCalibration(name, bar.pairs, tuple(c + turns * period for c in bar.counts),
                                            bar.distances_m)
                moved.append(name)
        if not moved:
            return None
        quality = dict(cal.quality)
        quality['aligned_to_session'] = moved
        new = replace(cal, bars=bars, quality=quality)
        self.set_calibration(new)
        return new

    # -- what next -----------------------------------------------------------------------------
    def _pairs_of(self, channel: str) -> list[str]:
        if channel in self._resting:
            rest = self._resting[channel]
            return [p for p in self.pair_names if p != rest] + [rest]
        return list(self.pair_names)

    def _check_names(self, bar: str, pair: str) -> None:
        if bar and bar not in self.bar_channels:
            raise CalibrationError(f'bar must be one of {self.bar_channels} (or empty for the '
                                   f'routine\'s order), got {bar!r}')
        if pair and pair not in self.pair_names:
            raise CalibrationError(f'pair must be one of {self.pair_names} (or empty for the '
                                   f'routine\'s order), got {pair!r}')

    def effective_mode(self, mode: str = 'auto') -> str:
        """'re_reference' or 'full': what ``mode`` means now."""
        if mode not in MODES:
            raise CalibrationError(f'mode must be one of {list(MODES)}, got {mode!r}')
        if mode == 'auto':
            return 're_reference' if self.pending else 'full'
        return mode

    def next_step(self, bar: str = '', pair: str = '', mode: str = 'auto') -> Step | None:
        """The placement that comes next, or None when there is nothing left to do.

        bar : select a bar ('' follows the routine's order)
        pair : override the pair of the next capture ('' follows the routine's order)
        mode : 'auto' (re-reference after a counter reset, else calibrate), 'full' or
            're_reference'
        """
        self._check_names(bar, pair)
        if self.effective_mode(mode) == 're_reference':
            return self._next_re_reference(bar, pair)
        ways = tuple(APPROACHES) if self.settings.approaches == 2 else ('',)   # (each capture)
        if bar:
            channel = bar
        else:
            zero = next((c for c in self.references if c in self._needs_zero), None)
            if zero is not None:
                return Step('thermal_zero', zero, pair or self._resting[zero])
            channel = next((c for c in self.bar_channels if c not in self._completed), None)
            if channel is None:
                return None
            way = next((w for w in ways if w not in self._drifts), None)
            if way is not None and self.references and not self._completed and not self._points:
                ref = self.references[0]
                return Step('drift', ref, self._resting[ref], way)
        if channel in self._needs_zero and not pair:
            return Step('thermal_zero', channel, self._resting[channel])
        done = self._points.get(channel, {})

        def missing(p: str) -> str | None:
            have = done[p].captures if p in done else {}
            return next((w for w in ways if w not in have), None)

        if pair:
            return Step('calibrate', channel, pair, missing(pair) or ways[0])
        remaining = [p for p in self._pairs_of(channel) if missing(p) is not None]
        return Step('calibrate', channel, remaining[0], missing(remaining[0]) or '') if remaining else None

    def _next_re_reference(self, bar: str, pair: str) -> Step | None:
        if bar:
            channel = bar
        else:
            order = [c for c in self.references if c in self.pending] + \
                    [c for c in self.measuring if c in self.pending]
            if not order:
                return None
            channel = order[0]
        default = self._resting.get(channel, self._re_reference_pair)
        return Step('re_reference', channel, pair or default)

    # -- capture -------------------------------------------------------------------------------
    def _refuse(self, step: Step, why: str, bar: str, pair: str, mode: str) -> CaptureResult:
        nxt = self.next_step(bar, pair, mode)
        tail = f' Next: {nxt.describe(self.device)}.' if nxt else ''
        return CaptureResult(False, f'refused: {why}.{tail}', step, next_step=nxt)

    def _settled(self, channel: str, window: Window) -> tuple[float, float, float] | str:
        """(mean count, std [m], drift [m]) of the channel over the window, or why not."""
        s = self.settings
        n = window.counts.shape[0]
        if window.counter_reset:
            return ('the terminal\'s counters were reset during the settling window; '
                    'wait for a full window and call again')
        if n < s.min_samples:
            return (f'only {n} samples in the settling window (need {s.min_samples}): is the '
                    'terminal streaming?')
        q = window.counts[:, self._index[channel]]
        res = self.device.encoder_resolution_m
        std_m = float(np.std(q)) * res
        t = np.linspace(0.0, 1.0, n)
        slope = float(np.polyfit(t, q, 1)[0]) if n > 2 else float(q[-1] - q[0])
        drift_m = abs(slope) * res
        if std_m > s.settle_std_m or drift_m > s.settle_drift_m:
            return (f'{channel} is still moving: over the {window.duration_s:.2f} s window its reading '
                    f'varies by {std_m / M_PER_UM:.3f} µm (std, limit {s.settle_std_m / M_PER_UM:.3f}) and '
                    f'drifts by {drift_m / M_PER_UM:.3f} µm (limit {s.settle_drift_m / M_PER_UM:.3f}); '
                    'let it settle in its sockets and call again')
        return float(np.mean(q)), std_m, drift_m

    def _plausible(self, channel: str, pair: str, q: float) -> str | None:
        """Why the reading ``q`` on ``pair`` is implausible, or None."""
        res = self.device.encoder_resolution_m
        tol = self.settings.plausibility_m
        d = self.device.pair(pair).distance_m
        points = {p: v.count for p, v in self._points.get(channel, {}).items() if p != pair}
        if points:
            ds = np.array([self.device.pair(p).distance_m for p in points])
            qs = np.array(list(points.values()))
            sign = 0.0
            if len(points) >= 2:
                k = np.argsort(ds)
                sign = float(np.sign((qs[k][-1] - qs[k][0]) / (ds[k][-1] - ds[k][0])))
            signs = [sign] if sign else [1.0, -1.0]
            for sg in signs:
                predicted = qs + sg * (d - ds) / res
                allowed = (tol + 1e-3 * np.abs(d - ds)) / res
                if np.all(np.abs(q - predicted) <= allowed):
                    return None
            j = int(np.argmin(np.abs(d - ds)))
            guess = (q - qs[j]) * res * (signs[0] or 1.0) + ds[j]
            nearest = min(self.device.pairs, key=lambda p: abs(p.distance_m - guess))
            hint = (f'; it reads like {nearest.name} ({nearest.distance_m / M_PER_MM:.3f} mm)'
                    if abs(nearest.distance_m - guess) < 5 * tol and nearest.name != pair else '')
            doubt = ''
            if len(points) == 1:
                first = next(iter(points))
                doubt = (f'; if it does, its point on {first} was taken elsewhere: capture that one '
                         f'again (pair:={first}) or start over (calibration/reset_session)')
            return (f'{channel} reads {q:.1f} counts, which does not fit {pair} '
                    f'({d / M_PER_MM:.4f} mm) given its points on {", ".join(points)}: that reading '
                    f'means about {guess / M_PER_MM:.3f} mm (tolerance {tol / M_PER_MM:.3f} mm){hint}; '
                    f'check that the bar sits in sockets {"-".join(self.device.pair(pair).sockets)}'
                    + doubt)
        cal = self.calibration
        if cal is not None and cal.valid and channel in cal.bars:
            cdf = cal.bars[channel].cdf()
            predicted = float(cdf.inverse(d))
            if abs(q - predicted) * res > tol:
                reads = float(cdf(q)[0][()])
                return (f'{channel} reads {q:.1f} counts; its current calibration expects '
                        f'{predicted:.1f} on {pair} ({d / M_PER_MM:.4f} mm) and reads this as '
                        f'{reads / M_PER_MM:.3f} mm (tolerance {tol / M_PER_MM:.3f} mm): check that '
                        f'the bar sits in sockets {"-".join(self.device.pair(pair).sockets)}')
        return None

    def capture(self, step: Step, window: Window, when: str, *, ambient_c: float | None = None,
                bar: str = '', pair: str = '', mode: str = 'auto') -> CaptureResult:
        """Take one point of ``step`` from the samples of ``window``.

        when : the current time as ISO 8601 text (stored in the calibration)
        ambient_c : room temperature to record with a thermal zero [°C], or None
        bar, pair, mode : the selection in force (to say what comes next)
        """
        if step.kind not in KINDS:
            raise CalibrationError(f'step kind must be one of {KINDS}, got {step.kind!r}')
        self._check_names(step.channel, step.pair)
        settled = self._settled(step.channel, window)
        if isinstance(settled, str):
            return self._refuse(step, settled, bar, pair, mode)
        q, std_m, _ = settled
        if step.kind == 're_reference':
            return self._re_reference(step, q, window, when, bar, pair, mode)
        if step.kind == 'thermal_zero':
            return self._thermal_zero(step, q, when, ambient_c, bar, pair, mode)
        n = int(window.counts.shape[0])
        res = self.device.encoder_resolution_m
        if step.kind == 'drift':
            if step.channel not in self._resting or step.pair != self._resting[step.channel]:
                return self._refuse(step, 'the drift reading is taken with a reference bar on its '
                                    'resting pair', bar, pair, mode)
            why = self._plausible(step.channel, step.pair, q)
            if why:
                return self._refuse(step, why, bar, pair, mode)
            self._drifts[step.approach] = CaptureStats(step.channel, step.pair, step.approach, q,
                                                       (std_m / res) ** 2, n, _seconds(when),
                                                       'drift')
            nxt = self.next_step(bar, '', mode)
            way = f' from {step.approach}' if step.approach else ''
            return CaptureResult(True, f'read {step.channel} on {step.pair}{way} before the '
                                 f'measuring bars: {q:.1f} counts (the routine\'s temperature '
                                 'drift is its change until its placements there at the end).'
                                 + (f' Next: {nxt.describe(self.device)}.' if nxt else ''),
                                 step, next_step=nxt)
        why = self._plausible(step.channel, step.pair, q)
        if why:
            return self._refuse(step, why, bar, pair, mode)
        points = self._points.setdefault(step.channel, {})
        point = points.setdefault(step.pair, _Point({}))
        point.captures[step.approach] = (q, std_m, n, _seconds(when))
        self._last_approach[step.channel] = step.approach
        self._order.setdefault(step.channel, [])
        if step.pair in self._order[step.channel]:
            self._order[step.channel].remove(step.pair)
        self._order[step.channel].append(step.pair)
        d = self.device.pair(step.pair)
        ways = 2 if self.settings.approaches == 2 else 1
        full = sum(len(v.captures) >= ways for v in points.values())
        head = (f'captured {step.channel} on {step.pair}'
                + (f' from {step.approach}' if step.approach else '')
                + f' ({d.distance_m / M_PER_MM:.4f} mm): '
                f'{q:.1f} counts, noise {std_m / M_PER_UM:.3f} µm over {window.duration_s:.2f} s '
                f'({full} of {len(self.pair_names)} points)')
        if full < len(self.pair_names):
            nxt = self.next_step(bar, '', mode)
            tail = f' Next: {nxt.describe(self.device)}.' if nxt else ''
            return CaptureResult(True, head + '.' + tail, step, next_step=nxt)
        return self._complete(step, head, when, ambient_c, bar, mode)

    def _complete(self, step: Step, head: str, when: str, ambient_c: float | None, bar: str,
                  mode: str) -> CaptureResult:
        channel = step.channel
        points = self._points[channel]
        pairs = [p for p in self.device.pairs if p.name in points]
        new_bar = BarCalibration(channel, tuple(p.name for p in pairs),
                                 tuple(points[p.name].count for p in pairs),
                                 tuple(p.distance_m for p in pairs))
        try:
            new_bar.cdf()
        except CalibrationError as exc:
            del self._points[channel]
            self._order.pop(channel, None)
            nxt = self.next_step(bar, '', mode)
            tail = f' Next: {nxt.describe(self.device)}.' if nxt else ''
            return CaptureResult(False, f'refused: {channel}\'s seven points do not make a CDF '
                                 f'({exc}); its points of this session were discarded: calibrate '
                                 f'it again.{tail}', step, next_step=nxt)
        noise = max(v.std_m for v in points.values())
        quality = bar_quality(new_bar, self.device.encoder_resolution_m, noise)
        quality['captured'] = when
        cal = self._merged(channel, new_bar, when, quality)
        # what the session's captures measured about their own points (read noise, from the
        # dither of the still readings): msg_docs/frames.md
        res = self.device.encoder_resolution_m
        self._captures += [CaptureStats(channel, p, way, c[0], (c[1] / res) ** 2 * c[2]
                                        / max(c[2] - 1, 1), c[2], c[3])
                           for p, v in points.items() for way, c in v.captures.items() if c[2] > 1]
        drift = list(self._drifts.values())
        cal = replace(cal, uncertainty=capture_uncertainty(
            self.device, self._captures + drift, {c: b.cdf() for c, b in cal.bars.items()}))
        last_pair = self._order[channel][-1]
        zero_text = ''
        if channel in self._resting:
            if last_pair == self._resting[channel]:
                # the bar stays as it was seated last: its zero is that capture's reading
                last = points[last_pair].captures[self._last_approach.get(channel, '')]
                cal = self._with_zero(cal, channel, last[0], when, ambient_c)
                self._needs_zero.discard(channel)
                zero_text = (f' It rests on {last_pair}: thermal zero set there (Eq. 11), '
                             f'{cal.thermal_zero_m[channel] / M_PER_UM:+.3f} µm.')
            else:
                self._needs_zero.add(channel)
                zero_text = (f' Put it back on its resting pair {self._resting[channel]} to set '
                             'the thermal zero.')
        self._completed.add(channel)
        del self._points[channel]
        self._order.pop(channel, None)
        self.set_calibration(cal)
        msg = (f'{head}. {channel} calibrated: CDF from {len(pairs)} points, scale '
               f'{quality["scale_nm_per_count"]:.4f} nm/count ({quality["scale_ppm"]:+.1f} ppm '
               f'against the nominal {self.device.encoder_resolution_m / 1e-9:g} nm), nonlinearity '
               f'{quality["nonlinearity_um"]:.3f} µm, noise {quality["noise_um"]:.3f} µm.{zero_text}')
        if bar == channel:
            msg += (f' (Parameter bar is still {bar!r}: the next call calibrates it again; set it '
                    'to \'\' to follow the routine.)')
        missing = self.missing_bars()
        if missing:
            msg += f' Bars without a CDF: {", ".join(missing)}.'
        nxt = self.next_step(bar, '', mode)
        if nxt is not None:
            msg += f' Next: {nxt.describe(self.device)}.'
        elif not missing and cal.valid:
            msg += ' Calibration complete. Next: mount the measuring bars between the plates.'
        return CaptureResult(True, msg, step, cal, channel, quality, nxt)

    def _merged(self, channel: str, new_bar: BarCalibration, when: str,
                quality: dict[str, Any]) -> Calibration:
        old = self.calibration
        bars = dict(old.bars) if old is not None else {}
        bars[channel] = new_bar
        q = dict(old.quality) if old is not None else {}
        per_bar = dict(q.get('bars') or {})
        per_bar[channel] = quality
        q['bars'] = per_bar
        pending = [c for c in self.pending if c != channel]
        if pending:
            q['pending_re_reference'] = pending
        else:
            q.pop('pending_re_reference', None)
            q.pop('invalidated', None)
        zero = dict(old.thermal_zero_m) if old is not None else {}
        return Calibration(device=self.device.name, bars=bars, thermal_zero_m=zero,
                           ambient_c=old.ambient_c if old is not None else None, created=when,
                           valid=not pending, quality=q,
                           uncertainty=old.uncertainty if old is not None else CalibrationUncertainty())

    def _with_zero(self, cal: Calibration, channel: str, q: float, when: str,
                   ambient_c: float | None) -> Calibration:
        """Eq. (11)'s zero of reference bar ``channel`` from its reading ``q`` on its pair."""
        d = self.device.pair(self._resting[channel]).distance_m
        reading = float(cal.bars[channel].cdf()(q)[0][()])
        zero = dict(cal.thermal_zero_m)
        zero[channel] = reading - d
        quality = dict(cal.quality)
        quality['thermal_zero_set'] = when
        return replace(cal, thermal_zero_m=zero, created=when, quality=quality,
                       ambient_c=ambient_c if ambient_c is not None else cal.ambient_c)

    def _thermal_zero(self, step: Step, q: float, when: str, ambient_c: float | None,
                      bar: str, pair: str, mode: str) -> CaptureResult:
        channel = step.channel
        cal = self.calibration
        if channel not in self._resting:
            return self._refuse(step, f'{channel} is not a reference bar', bar, pair, mode)
        if step.pair != self._resting[channel]:
            return self._refuse(step, f'the thermal zero of {channel} is set on its resting pair '
                                f'{self._resting[channel]}, not {step.pair}', bar, pair, mode)
        if cal is None or channel not in cal.bars:
            return self._refuse(step, f'{channel} has no CDF yet: calibrate it first', bar, pair, mode)
        why = self._plausible(channel, step.pair, q)
        if why:
            return self._refuse(step, why, bar, pair, mode)
        new = self._with_zero(cal, channel, q, when, ambient_c)
        self._needs_zero.discard(channel)
        self.set_calibration(new)
        nxt = self.next_step(bar, '', mode)
        msg = (f'thermal zero of {channel} set on {step.pair}: '
               f'{new.thermal_zero_m[channel] / M_PER_UM:+.3f} µm (Eq. 11).')
        msg += f' Next: {nxt.describe(self.device)}.' if nxt else \
            ' Calibration complete. Next: mount the measuring bars between the plates.'
        return CaptureResult(True, msg, step, new, None, None, nxt)

    def _re_reference(self, step: Step, q: float, window: Window, when: str, bar: str,
                      pair: str, mode: str) -> CaptureResult:
        channel = step.channel
        cal = self.calibration
        if cal is None or channel not in cal.bars:
            return self._refuse(step, f'{channel} has no CDF to re-reference: run the full '
                                'calibration (parameter mode:=full)', bar, pair, mode)
        old = cal.bars[channel]
        cdf = old.cdf()
        d = self.device.pair(step.pair).distance_m
        if channel in self._resting:
            target = d + cal.thermal_zero_m.get(channel, 0.0)
            what = 'its thermal error is zero from now on (Eq. 11)'
        else:
            waiting = [c for c in self.references if c in self.pending]
            if waiting and self.settings.thermal_mode != 'off':
                return self._refuse(step, f're-reference the reference bar {waiting[0]} first: '
                                    f'measuring bars are re-referenced against its thermal error',
                                    bar, pair, mode)
            error = self._thermal_error(cal, window, d, channel)
            target = d + error
            what = f'its compensated length reads {d / M_PER_MM:.4f} mm (thermal error {error / M_PER_UM:+.3f} µm)'
        shift = q - float(cdf.inverse(target))
        moved = BarCalibration(channel, old.pairs, tuple(c + shift for c in old.counts), old.distances_m)
        bars = dict(cal.bars)
        bars[channel] = moved
        pending = [c for c in self.pending if c != channel]
        quality = dict(cal.quality)
        per_bar = dict(quality.get('bars') or {})
        entry = dict(per_bar.get(channel) or {})
        entry['re_referenced'] = when
        entry['re_reference_pair'] = step.pair
        entry['offset_shift_counts'] = round(shift, 3)
        per_bar[channel] = entry
        quality['bars'] = per_bar
        if pending:
            quality['pending_re_reference'] = pending
        else:
            quality.pop('pending_re_reference', None)
            quality.pop('invalidated', None)
        new = replace(cal, bars=bars, valid=not pending, created=when, quality=quality)
        self.set_calibration(new)
        slope = abs((old.distances_m[-1] - old.distances_m[0]) / (old.counts[-1] - old.counts[0]))
        msg = (f're-referenced {channel} on {step.pair}: count offset shifted by {shift:+.1f} counts '
               f'({shift * slope / M_PER_UM:+.3f} µm), CDF shape kept; {what}.')
        if pending:
            msg += f' Still to re-reference: {", ".join(pending)}.'
        else:
            msg += ' Every bar is re-referenced: the calibration is valid again.'
        # once every bar is back, the routine is done (a full calibration is not implied)
        nxt = self.next_step(bar if bar != channel else '', '', mode) if pending else None
        if nxt is not None:
            msg += f' Next: {nxt.describe(self.device)}.'
        elif not pending:
            msg += ' Next: mount the measuring bars between the plates.'
        return CaptureResult(True, msg, step, new, None, None, nxt)

    def _thermal_error(self, cal: Calibration, window: Window, d: float, channel: str) -> float:
        """Thermal error of a bar of length ``d`` now, from the reference bars in the window."""
        if self.settings.thermal_mode == 'off' or not self.references:
            return 0.0
        refs = [ReferenceBar(self._index[name], self.device.pair(self._resting[name]).distance_m,
                             cal.bars[name].cdf(), cal.thermal_zero_m.get(name, 0.0))
                for name in self.references if name in cal.bars]
        if not refs:
            return 0.0
        thermal = ThermalCompensation(self.device, refs, mode=self.settings.thermal_mode,
                                      plate_expansion=False)
        counts = window.counts.mean(axis=0, keepdims=True)
        state = thermal.state(counts, np.full((1, 6), d))
        return float(state.bar_error_m[0, self.measuring.index(channel)])
