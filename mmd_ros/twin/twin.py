"""The digital twin: a simulated MMD that produces what the encoder terminal would count.

One :class:`TwinDevice` is one physical device after power-on: its bars' count offsets,
nonlinearities, thermal constants and so on are drawn once from its seed. It lives on one
clock (seconds, the same clock as the :class:`~mmd_ros.twin.thermal.AmbientProfile`), on
which it can be calibrated on the reference plate (section 3.2) and then run scenarios.

Physical truth inside the twin: the CMM-measured joints (Table 1) and reference distances
(Table 2), whatever the device description tells the software to use; plates expand from
20 °C; the reference plate lies horizontally. A bar resting on a reference pair (seat 0) sits
with its own seating offset and friction state (fixed per bar and pair). The calibration places
each bar once on each pair as it rests there (the paper's routine), or, with ``approaches=2``,
seats it twice, once from shorter and once from longer (friction state +1 and -1, further
seatings with their own offsets); either way it leaves a reference bar on its resting pair in
its resting placement, so that it simply continues it afterwards.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core.calibration import BarCalibration, Calibration, iso_utc
from mmd_ros.core.calibration_routine import CaptureStats, capture_uncertainty
from mmd_ros.core.device import DeviceDescription
from mmd_ros.core.errors import ConfigError
from mmd_ros.hardware.protocol import MAX_SAMPLE_RATE_HZ
from mmd_ros.twin.effects import Effects
from mmd_ros.twin.errors import TwinError
from mmd_ros.twin.machine import MachineTrajectory
from mmd_ros.twin.mechanism import bar_legs, check_workspace, rotation_matrices
from mmd_ros.twin.physics import HYSTERESIS_SPREAD, RESEATS, BarPhysics, DahlState, dahl
from mmd_ros.twin.reference import POSE_NOISE, reference_names, reference_values
from mmd_ros.twin.scenarios import MAX_DURATION_S, RestingBars, Scenario
from mmd_ros.twin.thermal import REFERENCE_TEMP_C, AmbientProfile

__all__ = ['MAX_CLOCK_S', 'MAX_SAMPLES', 'MAX_SEED', 'IsoTargets', 'Placement', 'SimulatedRun',
           'TwinDevice', 'check_clock', 'simulated_serial']

FloatArray = NDArray[np.float64]

#: Samples simulated at once inside a run (bounds the memory of long runs).
BLOCK = 32768
#: Rate of the workspace check done before a run starts [Hz] (every sample is checked again
#: while simulating).
CHECK_RATE_HZ = 100.0
#: Most samples one run may have: 10^9, about 100 GB of log at the measured ~100 bytes per
#: sample of raw counts and reference (a week at 1 kHz fits; at 10 kHz, a day).
MAX_SAMPLES = 1_000_000_000
#: Largest time on the twin's clock, either side of its zero [s]: a year.
MAX_CLOCK_S = 365 * 24 * 3600.0
#: Largest seed: the twin's random streams are keyed by 64-bit hashes of it.
MAX_SEED = 2**64 - 1


def simulated_serial(seed: int) -> str:
    """The serial number of the twin of ``seed``'s simulated terminal, ``MMD-SIM-<seed>`` (four
    digits at least): what `mmd simulate`'s calibrations name and the nodes' simulated terminal
    reports, so that a model or a calibration of one twin goes with that twin's logs and live
    stream and is refused for another's."""
    return f'MMD-SIM-{int(seed):04d}'


def check_clock(t_s: float, what: str) -> None:
    """A time on the twin's clock: finite and within +-:data:`MAX_CLOCK_S`."""
    if not -MAX_CLOCK_S <= t_s <= MAX_CLOCK_S:  # False for NaN too
        raise TwinError(f'{what} must be within +-{MAX_CLOCK_S:g} s of the twin\'s clock zero (a '
                        f'year), got {t_s}')


@dataclass(frozen=True)
class Placement:
    """A bar on a socket pair during calibration: seated ``settle_s`` before ``start_s``, its
    counts averaged over [start_s, end_s) on the twin's clock [s]; ``approach`` +1 seated from
    shorter (its guide lengthened into the sockets), -1 from longer, None as it rests there
    (its own friction state); ``seat`` 0 its resting placement, 1.. further seatings."""

    channel: int
    pair: str
    start_s: float
    end_s: float
    approach: float | None = None
    seat: int = 0


@dataclass
class IsoTargets:
    """ISO 230-2 targets of a run and where each sample stands in the test cycle.

    axis : str — pose component moved
    positions : ndarray, shape (n,) — commanded target coordinates [m or rad]
    commanded_poses : ndarray, shape (n, 6)
    index : ndarray of int16, shape (N,) — target approached or dwelt at, -1 for none
    direction : ndarray of int8, shape (N,) — +1 / -1 approach direction, 0 for none
    approach : ndarray of int16, shape (N,) — cycle number, -1 for none
    in_dwell : ndarray of bool, shape (N,) — the machine stands at the target
    """

    axis: str
    positions: FloatArray
    commanded_poses: FloatArray
    index: NDArray[np.int16]
    direction: NDArray[np.int8]
    approach: NDArray[np.int16]
    in_dwell: NDArray[np.bool_]


@dataclass
class SimulatedRun:
    """A simulated run, or one chunk of it.

    times_s : ndarray, shape (N,) — time since the run's start [s]
    counts : ndarray of int64, shape (N, 8) — unwrapped counts of the terminal's channels
    true_poses : ndarray, shape (N, 6) — actual pose of {U} in {L} [m, rad]; NaN when the
        bars rest on reference pairs
    true_lengths : ndarray, shape (N, 6) — true centre distances of bars 1..6 [m]
    ambient_c : ndarray, shape (N,) — room temperature [°C]
    bar_temp_c : ndarray, shape (N, 8) — temperature of each channel's bar, NaN if unused [°C]
    plate_temp_c : ndarray, shape (N,) — temperature of the plates [°C]
    reference : ndarray, shape (N, 6) — reference instrument, NaN where it does not measure
    reference_kind, reference_names : what the reference columns are
    channel_names : the terminal's channel names
    metadata : plain, JSON-serialisable description of the run (device, seed, effects, drawn
        bar parameters, scenario, ambient profile, start, rate)
    targets : IsoTargets of an ISO 230-2 run, else None
    start_s : the twin's clock at the run's start [s]
    start_sample : index of the first sample in the whole run
    machine_joints : ndarray, shape (N, n_axes), or None — commanded axis values of the machine
        tool carrying the MMD (a machine session) [m, rad]
    machine_joint_names : their names (X Y Z A C ...)
    """

    times_s: FloatArray
    counts: NDArray[np.int64]
    true_poses: FloatArray
    true_lengths: FloatArray
    ambient_c: FloatArray
    bar_temp_c: FloatArray
    plate_temp_c: FloatArray
    reference: FloatArray
    reference_kind: str
    reference_names: list[str]
    channel_names: list[str]
    metadata: dict[str, Any]
    targets: IsoTargets | None
    start_s: float
    start_sample: int = 0
    machine_joints: FloatArray | None = None
    machine_joint_names: list[str] | None = None

    #: Per-sample fields of a run and of its targets (what chunks concatenate along).
    ARRAY_FIELDS: ClassVar[tuple[str, ...]] = (
        'times_s', 'counts', 'true_poses', 'true_lengths', 'ambient_c', 'bar_temp_c',
        'plate_temp_c', 'reference')
    TARGET_ARRAY_FIELDS: ClassVar[tuple[str, ...]] = ('index', 'direction', 'approach', 'in_dwell')

    @property
    def n_samples(self) -> int:
        return int(self.times_s.size)

    @classmethod
    def concatenate(cls, runs: list[SimulatedRun]) -> SimulatedRun:
        """Join consecutive chunks into one run."""
        if not runs:
            raise TwinError('nothing to concatenate')
        first = runs[0]
        arrays = {name: np.concatenate([getattr(r, name) for r in runs]) for name in cls.ARRAY_FIELDS}
        targets = None
        if first.targets is not None:
            targets = IsoTargets(
                first.targets.axis, first.targets.positions, first.targets.commanded_poses,
                **{name: np.concatenate([getattr(r.targets, name) for r in runs])
                   for name in cls.TARGET_ARRAY_FIELDS})
        joints = None
        if first.machine_joints is not None:
            joints = np.concatenate([r.machine_joints for r in runs])
        return cls(**arrays, reference_kind=first.reference_kind,
                   reference_names=first.reference_names, channel_names=first.channel_names,
                   metadata=first.metadata, targets=targets, start_s=first.start_s,
                   start_sample=first.start_sample, machine_joints=joints,
                   machine_joint_names=first.machine_joint_names)


def _stating(effects: tuple[str, ...], values: Effects, stating: Any, *figures: float
             ) -> DeviceDescription:
    """``stating(*figures)``: the description stating figures of the effects named, or a
    :class:`TwinError` that blames those effects (not the description, which holds none of
    them) when the figures are beyond what a description may state."""
    try:
        return stating(*figures)
    except ConfigError as exc:
        given = ', '.join(f'{name}={getattr(values, name):g}' for name in effects)
        raise TwinError(f'effect {given}: the simulated device cannot state it in its '
                        f'description ({exc.key} {exc.problem}); change the effect') from None


class TwinDevice:
    """A simulated MMD (seeded, deterministic).

    device : the device description (joints, reference plate, bars, channel map)
    effects : error sources; ``Effects.ideal()`` if None
    seed : integer in [0, 2^64 - 1]; the same seed draws the same device
    """

    def __init__(self, device: DeviceDescription, effects: Effects | None = None, seed: int = 0) -> None:
        if not (isinstance(seed, (int, np.integer)) and 0 <= seed <= MAX_SEED):
            raise TwinError(f'seed must be an integer in [0, 2^64 - 1] (it keys 64-bit random '
                            f'streams), got {seed!r}')
        if not 0 < device.sample_rate_hz <= MAX_SAMPLE_RATE_HZ:
            raise TwinError(f'{device.source}: terminal.sample_rate_hz must be in (0, {MAX_SAMPLE_RATE_HZ}] '
                            f'Hz (the terminal\'s maximum), got {device.sample_rate_hz:g}')
        self.device = device
        self.effects = Effects.ideal() if effects is None else effects
        self.seed = int(seed)
        self.physics = BarPhysics(device, self.effects, self.seed)
        self._pair_index = {p.name: j for j, p in enumerate(device.pairs)}

    def __repr__(self) -> str:
        return f'TwinDevice({self.device.name!r}, seed={self.seed})'

    @property
    def documented_device(self) -> DeviceDescription:
        """The device description as the simulated hardware's datasheets complete it: the
        terminal's latch skew (``terminal.latch_skew_us``) is the bound the effects give the
        channels' delays (``sampling_skew_s``), not the channels' own delays, which stay hidden
        (as a real terminal's datasheet states a bound); the encoders' sub-divisional error
        (``bars.subdivision_error_nm``, ``bars.signal_period_um``) is the effects' cyclic
        amplitude and period (each bar's phase stays hidden); the bars' friction hysteresis
        (``bars.friction_hysteresis_nm``) is the RMS of the amplitudes the effects give the bars
        (each bar's own stays hidden, as a characterisation of the bar type states it); the
        reference plate's seating repeatability (``reference_plate.seating_repeatability_nm``) is
        the effects' placement repeatability (each placement's own offset stays hidden); the bars'
        gravity sag (``bars.gravity_sag_nm``) is the effects' figure and its uncertainty
        (``bars.gravity_sag_uncertainty_nm``) their spread times it (0 without a spread: the
        twin's sag is then its figure; with one, this twin's own sag, alike for its bars, stays
        hidden), and the vertical it sags along (``plates.vertical``) the one the twin stands
        in: the description's, else level (+z of {L}); the bound on the bars' reading drift rate
        (``bars.drift_nm_per_h``) the effects' largest (each bar's own rate stays hidden); the
        uncertainty of the bars' effective rod CTE (``bars.rod_cte_uncertainty_ppm_per_c``) how
        far the effects' rod CTE lies from the one the description states (0 when they take
        it; each bar's spread about it is the thermal mismatch's). What a description states,
        it keeps.
        Raises :class:`TwinError` naming the effect whose figure no description may state."""
        device = self.device
        fx = self.effects
        if device.latch_skew_s is None:
            device = _stating(('sampling_skew_s',), fx, device.with_latch_skew, fx.sampling_skew_s)
        if device.subdivision_error_m is None:
            device = _stating(('cyclic_error_m', 'cyclic_period_m'), fx,
                              device.with_subdivision_error, fx.cyclic_error_m, fx.cyclic_period_m)
        if device.friction_hysteresis_m is None:
            lo, hi = HYSTERESIS_SPREAD      # the RMS of a uniform share in [lo, hi]
            device = _stating(('hysteresis_m',), fx, device.with_friction_hysteresis,
                              fx.hysteresis_m * math.sqrt((hi ** 3 - lo ** 3) / (3.0 * (hi - lo))))
        if device.seating_repeatability_m is None:
            device = _stating(('placement_repeatability_m',), fx, device.with_seating_repeatability,
                              fx.placement_repeatability_m)
        if device.gravity_sag_m is None:
            sag = fx.gravity_sag_m
            device = _stating(('gravity_sag_m', 'gravity_sag_spread'), fx, device.with_gravity_sag,
                              sag, sag * fx.gravity_sag_spread)
        if device.vertical is None:
            device = device.with_vertical(device.up)
        if device.drift_m_per_s is None:
            device = _stating(('drift_m_per_s',), fx, device.with_reading_drift,
                              abs(fx.drift_m_per_s))
        if device.rod_cte_sigma_per_c is None:
            device = _stating(('rod_cte_per_c',), fx, device.with_rod_cte_uncertainty,
                              abs(fx.rod_cte(device.rod_cte_per_c) - device.rod_cte_per_c))
        return device

    # -- bars on the reference plate -----------------------------------------------------------
    def _pair(self, pair: str) -> int:
        if pair not in self._pair_index:
            raise TwinError(f'no reference pair {pair!r}; pairs are {list(self._pair_index)}')
        return self._pair_index[pair]

    def _bar_channel(self, channel: int) -> int:
        roles = {c.index: c.role for c in self.device.channels}
        if roles.get(channel) not in ('measuring', 'reference'):
            raise TwinError(f'channel {channel} has no bar (role {roles.get(channel)!r}); '
                            f'bar channels are {[k for k, r in roles.items() if r != "unused"]}')
        return channel

    def _plate_growth(self, plate_temp_c: FloatArray, cte: float) -> FloatArray:
        """1 + alpha dT of a plate, or 1 when plate expansion is off."""
        if not self.effects.plate_expansion:
            return np.ones_like(plate_temp_c)
        return 1.0 + cte * (plate_temp_c - REFERENCE_TEMP_C)

    def _temperatures(self, times_s: FloatArray, ambient: AmbientProfile) -> FloatArray:
        """Bar temperatures of all channels and the plate temperature, shape (N, 9) [°C]."""
        taus = np.append(self.physics.time_constant_s, self.effects.plate_time_constant_s)
        return ambient.lagged(times_s, taus)

    def _on_pairs(self, channels: list[int], pairs: list[str], times_s: FloatArray,
                  sample_index: NDArray[np.int64], bar_temp_c: FloatArray,
                  plate_temp_c: FloatArray, approach: float | None = None,
                  seat: int = 0) -> tuple[FloatArray, FloatArray]:
        """Readings [m] and true lengths [m] of bars lying on reference pairs, (N, M) each
        (``approach``, ``seat``: see :class:`Placement`)."""
        j = [self._pair(p) for p in pairs]
        growth = self._plate_growth(plate_temp_c, self.device.reference_plate_cte_per_c)
        true = growth[:, None] * np.array([self.device.pairs[k].measured_m for k in j])
        seated = true + self.physics.seating(channels, j, seat)
        own = self.physics.pair_state[channels, j]
        state = np.broadcast_to(own if approach is None else np.full(len(j), float(approach)),
                                true.shape)
        reading = self.physics.scale_reading_m(channels, seated, bar_temp_c, state, times_s,
                                               sample_index)
        return reading, seated

    def _sample_index(self, times_s: FloatArray) -> NDArray[np.int64]:
        return np.rint(times_s * self.device.sample_rate_hz).astype(np.int64)

    def counts_on_pair(self, channel: int, pair: str, times_s: ArrayLike,
                       ambient: AmbientProfile, *, approach: float | None = None,
                       seat: int = 0) -> NDArray[np.int64]:
        """Counts of the bar on ``channel`` resting on reference ``pair``.

        times_s : array_like, shape (N,) — on the twin's clock [s]
        approach, seat : how it was seated (:class:`Placement`); default its resting placement
        returns : ndarray of int64, shape (N,)
        """
        ch = self._bar_channel(channel)
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        temps = self._temperatures(t, ambient)
        reading, _ = self._on_pairs([ch], [pair], t, self._sample_index(t), temps[:, [ch]],
                                    temps[:, -1], approach, seat)
        return self.physics.counts([ch], reading)[:, 0]

    def counts_for_lengths(self, channel: int, lengths_m: ArrayLike, times_s: ArrayLike,
                           ambient: AmbientProfile, *, axis_z: ArrayLike | None = None,
                           friction_state: float | None = None) -> NDArray[np.int64]:
        """Counts of the bar on ``channel`` held at given true centre distances, e.g. beside an
        interferometer on a machine tool (section 4.2).

        lengths_m : array_like, shape (N,) — true centre distance at each sample [m]
        times_s : array_like, shape (N,) — on the twin's clock, increasing [s]
        axis_z : array_like, shape (N,), optional — z-component of the bar axis; None: horizontal
        friction_state : Dahl state at the first sample in [-1, 1]; None takes the bar's drawn
            start state
        returns : ndarray of int64, shape (N,)
        """
        ch = self._bar_channel(channel)
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        d = np.asarray(lengths_m, dtype=np.float64).reshape(-1, 1)
        if d.shape[0] != t.size:
            raise TwinError(f'lengths_m and times_s must have equal length, got {d.shape[0]} and {t.size}')
        s0 = self.physics.start_state[ch] if friction_state is None else friction_state
        friction, _ = dahl(d, DahlState.start([s0]), self.effects.hysteresis_travel_m)
        temps = self._temperatures(t, ambient)
        z = None if axis_z is None else np.asarray(axis_z, dtype=np.float64).reshape(-1, 1)
        reading = self.physics.scale_reading_m([ch], d, temps[:, [ch]], friction, t,
                                               self._sample_index(t), z)
        return self.physics.counts([ch], reading)[:, 0]

    # -- calibration (section 3.2) -------------------------------------------------------------
    def calibration_schedule(self, at_s: float, settle_s: float = 3.0,
                             average_s: float = 2.0, approaches: int = 1) -> list[Placement]:
        """The order of the calibration routine starting at ``at_s``: each measuring bar (bar
        order), then each reference bar, on the seven pairs in turn; a reference bar visits
        its resting pair last and stays there. A placement takes ``settle_s`` to seat the bar,
        then counts are averaged for ``average_s``.

        approaches : 1 — one placement per pair, as the bar lies there (the paper's routine),
            and before it each reference bar read where the last routine left it, on its
            resting pair, over the ``average_s`` before ``at_s`` (a seating of its own: the
            routine's temperature drift, seen against its placement there at the end; the
            placements of the routine keep their times);
            2 — two placements per pair, seated once from shorter and once from longer (a
            reference bar's last one on its resting pair is its resting placement), and before
            the measuring bars each reference bar on its resting pair in the same two ways (the
            routine's temperature drift, seen against its two placements there at the end)
        """
        if settle_s < 0 or not average_s > 0:
            raise TwinError(f'need settle_s >= 0 and average_s > 0, got {settle_s} and {average_s}')
        if approaches not in (1, 2):
            raise TwinError(f'approaches must be 1 or 2, got {approaches!r}')
        names = [p.name for p in self.device.pairs]
        resting = {c.index: c.pair for c in self.device.reference_channels}
        visits = [(c, names) for c in self.device.measuring_channels]
        for ref in self.device.reference_channels:
            visits.append((ref.index, [p for p in names if p != ref.pair] + [ref.pair]))
        # (channel, pair, [(approach, seat), ...]) in the routine's order
        plan: list[tuple[int, str, list[tuple[float | None, int]]]] = []
        if approaches == 2:
            # each reference bar first on its resting pair, seated from both sides as at its
            # end there: the routine's temperature drift
            for ref in self.device.reference_channels:
                own = self._pair_state(ref.index, ref.pair)
                plan.append((ref.index, ref.pair, [(-own, RESEATS - 1), (None, RESEATS)]))
        for channel, pairs in visits:
            for pair in pairs:
                if approaches == 1:
                    plan.append((channel, pair, [(None, 0)]))
                elif resting.get(channel) == pair:
                    plan.append((channel, pair, [(-self._pair_state(channel, pair), 1), (None, 0)]))
                else:
                    plan.append((channel, pair, [(1.0, 1), (-1.0, 2)]))
        out, t = [], float(at_s)
        if approaches == 1:
            out += [Placement(ref.index, ref.pair, t - average_s, t, None, RESEATS)
                    for ref in self.device.reference_channels]
        for channel, pair, ways in plan:
            for approach, seat in ways:
                out.append(Placement(channel, pair, t + settle_s, t + settle_s + average_s,
                                     approach, seat))
                t += settle_s + average_s
        return out

    def _pair_state(self, channel: int, pair: str) -> float:
        """The friction state a bar takes seated on a pair as it comes (+1 or -1)."""
        return float(self.physics.pair_state[channel, self._pair(pair)])

    def calibrate(self, at_s: float, ambient: AmbientProfile, settle_s: float = 3.0,
                  average_s: float = 2.0, approaches: int = 1, epoch_s: float | None = None
                  ) -> Calibration:
        """Run the calibration routine of section 3.2 (see :meth:`calibration_schedule`).

        Each calibration point is the mean count over its averaging window (of both
        placements with ``approaches=2``), kept as a float (sub-count resolution from the read
        noise). A reference bar's thermal zero is what its CDF reads at its last placement,
        on its resting pair, minus that pair's distance (0 with one placement per pair): it
        rests there afterwards without being moved. ``ambient_c`` is the room temperature at
        ``at_s``. The ``uncertainty`` section holds what the captures measured (read noise;
        with two approaches the friction hysteresis and the seating repeatability,
        :func:`~mmd_ros.core.calibration_routine.capture_uncertainty`). ``epoch_s``: the Unix
        time [s] of the twin's clock 0 (what a log of the twin stamps its samples from); with
        it ``created`` is when the routine ended on that clock (ISO 8601, UTC), what the
        budget counts the readings' drift from; None leaves it empty. No quality figures are
        invented: ``quality`` is empty.
        """
        check_clock(at_s, 'the calibration time')
        rate = self.device.sample_rate_hz
        counts: dict[int, dict[str, list[float]]] = {}
        captures, last = [], {}
        names = self.device.channel_names
        way = {1.0: 'short', -1.0: 'long'}
        schedule = self.calibration_schedule(at_s, settle_s, average_s, approaches)
        n_drift = approaches * len(self.device.reference_channels)     # (first in the schedule)
        for k, p in enumerate(schedule):
            times = p.start_s + np.arange(max(1, int(round((p.end_s - p.start_s) * rate)))) / rate
            c = self.counts_on_pair(p.channel, p.pair, times, ambient, approach=p.approach,
                                    seat=p.seat).astype(np.float64)
            state = p.approach if p.approach is not None else self._pair_state(p.channel, p.pair)
            captures.append(CaptureStats(
                names[p.channel], p.pair, way[state] if approaches == 2 else '', float(np.mean(c)),
                float(np.var(c, ddof=1)) if c.size > 1 else 0.0, int(c.size),
                float(0.5 * (p.start_s + p.end_s)), 'drift' if k < n_drift else 'point'))
            if k < n_drift:
                continue
            counts.setdefault(p.channel, {}).setdefault(p.pair, []).append(float(np.mean(c)))
            last[p.channel] = (p.pair, float(np.mean(c)))
        bars = {}
        for channel, by_pair in counts.items():
            pairs = [p for p in self.device.pairs if p.name in by_pair]
            bars[names[channel]] = BarCalibration(
                channel=names[channel], pairs=tuple(p.name for p in pairs),
                counts=tuple(float(np.mean(by_pair[p.name])) for p in pairs),
                distances_m=tuple(p.distance_m for p in pairs))
        readers = {name: _linear_reader(b.counts, b.distances_m) for name, b in bars.items()}
        zero = {}
        for c in self.device.reference_channels:
            pair, q = last[c.index]
            reading = float(readers[c.name](np.array([q]))[0][0])
            offset = 0.0 if approaches == 1 else reading - self.device.pair(pair).distance_m
            zero[c.name] = float(offset / 1e-6) * 1e-6   # as the calibration file keeps it
        uncertainty = capture_uncertainty(self.device, captures, readers)
        return Calibration(
            device=self.device.name, bars=bars, thermal_zero_m=zero,
            ambient_c=float(ambient(at_s)),
            created='' if epoch_s is None else iso_utc(float(epoch_s) + schedule[-1].end_s),
            valid=True, quality={},
            uncertainty=uncertainty)

    # -- runs ----------------------------------------------------------------------------------
    def simulate(self, scenario: Scenario, ambient: AmbientProfile, *, start_s: float = 0.0,
                 reference: str | None = None, sample_rate_hz: float | None = None) -> SimulatedRun:
        """Simulate a whole scenario starting at ``start_s`` on the twin's clock.

        reference : reference instrument kind (:mod:`mmd_ros.twin.reference`); None takes the
            scenario's own (laser along an ISO linear axis, rotary calibrator for a rotary axis,
            bar lengths for a thermal soak, pose6 otherwise)
        sample_rate_hz : None samples at the terminal's rate; a lower rate gives every k-th
            sample of the full-rate run (for long soaks)
        """
        plan = _Plan(self, scenario, ambient, start_s, reference, sample_rate_hz)
        return plan.run(0, plan.n_samples, plan.initial_state())[0]

    def stream(self, scenario: Scenario, ambient: AmbientProfile, *, start_s: float = 0.0,
               reference: str | None = None, sample_rate_hz: float | None = None,
               chunk_samples: int = 1000) -> Iterator[SimulatedRun]:
        """The run of :meth:`simulate` in consecutive chunks of ``chunk_samples`` samples, for a
        simulated terminal streaming in real time. The chunks concatenate to exactly the
        one-shot run. The scenario is checked before the first chunk is asked for."""
        if chunk_samples < 1:
            raise TwinError(f'chunk_samples must be >= 1, got {chunk_samples}')
        plan = _Plan(self, scenario, ambient, start_s, reference, sample_rate_hz)

        def chunks() -> Iterator[SimulatedRun]:
            state = plan.initial_state()
            for k0 in range(0, plan.n_samples, chunk_samples):
                run, state = plan.run(k0, min(k0 + chunk_samples, plan.n_samples), state)
                yield run

        return chunks()


def _linear_reader(counts: tuple[float, ...], distances_m: tuple[float, ...]):
    """Counts read as lengths by linear interpolation between a bar's calibration points (the
    routine's own arithmetic, written here so that the twin shares no code with the
    compensation), as (lengths, None)."""
    q = np.asarray(counts, dtype=np.float64)
    d = np.asarray(distances_m, dtype=np.float64)
    order = np.argsort(q)
    q, d = q[order], d[order]

    def read(values: NDArray[np.float64]) -> tuple[NDArray[np.float64], None]:
        v = np.asarray(values, dtype=np.float64)
        k = np.clip(np.searchsorted(q, v, side='right') - 1, 0, q.size - 2)
        return d[k] + (v - q[k]) * (d[k + 1] - d[k]) / (q[k + 1] - q[k]), None

    return read


def _check_times(motion: Any, rate_hz: float) -> Iterator[FloatArray]:
    """The times of the workspace check before a run (a grid at ``rate_hz`` and every knot
    of ``motion``) in increasing blocks of about :data:`BLOCK`: a week at 100 Hz would need
    gigabytes of poses at once."""
    step = 1.0 / rate_hz
    n = math.ceil(motion.duration_s / step)
    knots = motion.knots_s[motion.knots_s <= motion.duration_s]
    for k0 in range(0, max(n, 1), BLOCK):
        k1 = min(k0 + BLOCK, n)
        end = k1 * step if k1 < n else math.inf
        yield np.union1d(np.arange(k0, k1) * step, knots[(knots >= k0 * step) & (knots < end)])


class _Plan:
    """A scenario prepared for simulation on one twin: motion built, workspace checked."""

    def __init__(self, twin: TwinDevice, scenario: Scenario, ambient: AmbientProfile,
                 start_s: float, reference: str | None, sample_rate_hz: float | None) -> None:
        dev = twin.device
        self.twin, self.scenario, self.ambient, self.start_s = twin, scenario, ambient, float(start_s)
        self.rate = float(sample_rate_hz or dev.sample_rate_hz)
        if not 0 < self.rate <= MAX_SAMPLE_RATE_HZ:
            raise TwinError(f'sample_rate_hz must be in (0, {MAX_SAMPLE_RATE_HZ}] Hz (the '
                            f'terminal\'s maximum), got {sample_rate_hz or dev.sample_rate_hz}')
        check_clock(start_s, 'start_s')
        self.reference = reference or scenario.default_reference
        self.measuring = dev.measuring_channels
        self.names = reference_names(self.reference, [dev.channel_names[c] for c in self.measuring])
        self.motion = scenario.build(dev)
        if isinstance(self.motion, RestingBars) and self.reference != 'bar_lengths':
            raise TwinError(f'{scenario.kind}: the bars rest on reference pairs, there is no '
                            f'pose for a {self.reference!r} reference; use bar_lengths')
        if not 0 <= self.motion.duration_s <= MAX_DURATION_S:
            raise TwinError(f'{scenario.kind}: the run lasts {self.motion.duration_s:.6g} s; at most '
                            f'{MAX_DURATION_S:g} s (a week) can be simulated')
        self.n_samples = int(math.floor(self.motion.duration_s * self.rate + 1e-9)) + 1
        if self.n_samples > MAX_SAMPLES:
            raise TwinError(f'{scenario.kind}: {self.n_samples:.3g} samples ({self.motion.duration_s:g} s '
                            f'at {self.rate:g} Hz); at most {MAX_SAMPLES:.0e} can be simulated in one '
                            'run: lower the sample rate')
        if self.n_samples < 2:
            raise TwinError(f'{scenario.kind}: the run lasts {self.motion.duration_s:.6g} s, which '
                            f'at {self.rate:g} Hz is {self.n_samples} sample: raise the sample '
                            f'rate to at least {math.ceil(1e3 / self.motion.duration_s) / 1e3:g} Hz'
                            if self.motion.duration_s > 0 else
                            f'{scenario.kind}: the run lasts 0 s: nothing to simulate')
        if not isinstance(self.motion, RestingBars):
            geo = dev.measured_geometry
            for times in _check_times(self.motion, min(self.rate, CHECK_RATE_HZ)):
                poses = self.motion.pose(times)
                rot = rotation_matrices(poses)
                check_workspace(dev, times, bar_legs(geo.upper, geo.lower, poses, rot), rot,
                                scenario.kind)
        self.metadata = {
            'device': dev.name,
            'seed': twin.seed,
            'effects': twin.effects.to_dict(),
            'bars': twin.physics.summary(),
            'scenario': scenario.to_dict(),
            'ambient': ambient.to_dict(),
            'start_s': self.start_s,
            'sample_rate_hz': self.rate,
            'n_samples': self.n_samples,
            'reference': self.reference,
            # the twin reads the actual pose, not zeroed, with the instrument's noise
            'reference_absolute': True,
            'reference_sigma': None if self.reference == 'bar_lengths' else POSE_NOISE.tolist(),
            # at the MMD's sample instants: a delay between the two is the MMD's
            'reference_clock': 'shared',
        }

    def initial_state(self) -> DahlState:
        return DahlState.start(self.twin.physics.start_state[self.measuring])

    def run(self, k0: int, k1: int, state: DahlState) -> tuple[SimulatedRun, DahlState]:
        """Samples k0..k1-1 given the friction state before k0."""
        parts = []
        for b0 in range(k0, k1, BLOCK):
            part, state = self._block(b0, min(b0 + BLOCK, k1), state)
            parts.append(part)
        arrays = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
        targets = None
        spec = getattr(self.motion, 'targets', None)
        if spec is not None:
            targets = IsoTargets(spec.axis, spec.positions, spec.commanded_poses,
                                 **{k: arrays.pop(k) for k in SimulatedRun.TARGET_ARRAY_FIELDS})
        joint_names = None
        if 'machine_joints' in arrays:
            joint_names = list(self.motion.machine.names)
        run = SimulatedRun(**arrays, reference_kind=self.reference, reference_names=self.names,
                           channel_names=self.twin.device.channel_names, metadata=self.metadata,
                           targets=targets, start_s=self.start_s, start_sample=k0,
                           machine_joint_names=joint_names)
        return run, state

    def _block(self, k0: int, k1: int, state: DahlState) -> tuple[dict[str, NDArray], DahlState]:
        twin, dev, phys = self.twin, self.twin.device, self.twin.physics
        meas = self.measuring
        t = np.arange(k0, k1) / self.rate
        clock = self.start_s + t
        index = twin._sample_index(clock)
        temps = twin._temperatures(clock, self.ambient)
        plate_c = temps[:, -1]
        counts = np.empty((t.size, len(dev.channels)), dtype=np.int64)
        out: dict[str, NDArray] = {}

        if not isinstance(self.motion, RestingBars):
            poses = self.motion.pose(t)
            rot = rotation_matrices(poses)
            geo = dev.measured_geometry
            growth = twin._plate_growth(plate_c, dev.plate_cte_per_c)
            legs = bar_legs(geo.upper, geo.lower, poses, rot, growth, growth)
            lengths = np.linalg.norm(legs, axis=2)
            check_workspace(dev, t, legs, rot, self.scenario.kind)
            # Friction follows the machine's motion, not the plates' thermal growth.
            driver = lengths if not twin.effects.plate_expansion else \
                np.linalg.norm(bar_legs(geo.upper, geo.lower, poses, rot), axis=2)
            friction, state = dahl(driver, state, twin.effects.hysteresis_travel_m)
            read = lengths
            skew = phys.skew_s[meas]
            if np.any(skew > 0):
                # Channel k latches at t + skew_k: interpolate between t and t + the largest skew
                # (error at most largest^2 x acceleration / 8, far below a nanometre).
                largest = float(skew.max())
                later = np.linalg.norm(bar_legs(geo.upper, geo.lower, self.motion.pose(t + largest),
                                                None, growth, growth), axis=2)
                read = lengths + (skew / largest) * (later - lengths)
            # (the bars sag along the vertical the description states: the twin stands so)
            reading = phys.scale_reading_m(meas, read, temps[:, meas], friction, clock, index,
                                           (legs @ dev.up) / lengths)
            if self.motion.targets is not None:
                out.update(self.motion.labels(t))
            if isinstance(self.motion, MachineTrajectory):
                out['machine_joints'] = self.motion.joints(t)
        else:
            poses = np.full((t.size, 6), np.nan)
            reading, lengths = twin._on_pairs(meas, list(self.motion.pairs), clock, index,
                                              temps[:, meas], plate_c)
        counts[:, meas] = phys.counts(meas, reading)

        refs = dev.reference_channels
        ref_idx = [c.index for c in refs]
        ref_reading, _ = twin._on_pairs(ref_idx, [c.pair for c in refs], clock, index,
                                        temps[:, ref_idx], plate_c)
        counts[:, ref_idx] = phys.counts(ref_idx, ref_reading)
        bar_temp = temps[:, :-1].copy()
        for c in dev.channels:
            if c.role == 'unused':
                counts[:, c.index] = phys.offsets_counts[c.index]
                bar_temp[:, c.index] = np.nan

        out.update(
            times_s=t, counts=counts, true_poses=poses, true_lengths=lengths,
            ambient_c=self.ambient(clock), bar_temp_c=bar_temp, plate_temp_c=plate_c,
            reference=reference_values(self.reference, poses, lengths, twin.seed, index))
        return out, state
