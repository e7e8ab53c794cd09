"""A simulated run written as an MCAP log in our layout: the twin calibrated on its reference
plate, a scenario, the raw counts and the reference instrument (``mmd simulate``, the demo,
the tests and benchmarks)."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mmd_ros.core.calibration import Calibration, TerminalBinding, channel_roles
from mmd_ros.core.device import DeviceDescription, find_config, load_device
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.progress import Progress
from mmd_ros.core.yamlio import read_yaml
from mmd_ros.logs.layout import (
    BAR_NAMES, FRAME_LOWER, REFERENCE_POSE_NAMES, RUN_METADATA, TOPIC_CALIBRATION, TOPIC_DEVICE,
    TOPIC_MACHINE_JOINTS, TOPIC_RAW, TOPIC_REF_LENGTHS, TOPIC_REF_POSE, RunLog,
)
from mmd_ros.logs.outputs import replacing
from mmd_ros.logs.writer import LogWriter
from mmd_ros.twin.effects import PRESET_AMBIENT, Effects
from mmd_ros.twin.errors import TwinError, TwinParameterError
from mmd_ros.twin.scenarios import make_scenario
from mmd_ros.twin.thermal import AmbientProfile, check_room
from mmd_ros.twin.twin import TwinDevice, simulated_serial

__all__ = ['EPOCH_S', 'SimulationSpec', 'ambient_profile', 'run_log', 'simulate_to_log',
           'simulated_terminal', 'spec_inputs']

#: Default time stamp of the twin's clock zero: 2024-01-01T00:00:00Z [s since the epoch].
EPOCH_S = 1_704_067_200
#: Samples written per chunk of simulation.
CHUNK = 50_000


@dataclass
class SimulationSpec:
    """Everything that defines a simulated log (all of it is written into the log)."""

    scenario: str = 'iso_linear'
    scenario_params: tuple[str, ...] = ()
    effects: str = 'realistic'
    effect_params: tuple[str, ...] = ()
    seed: int = 1
    device: str = 'mmd_prototype.yaml'
    ambient: str | None = None          # None: the preset's room (PRESET_AMBIENT)
    calibrate_at_s: float = 0.0
    start_s: float = 600.0
    reference: str | None = None
    sample_rate_hz: float | None = None
    epoch_s: int = EPOCH_S
    #: 1: the paper's calibration routine; 2: every pair seated from both sides and the
    #: routine's drift read (TwinDevice.calibrate): what the uncertainty budget can size
    calibration_approaches: int = 1

    def __post_init__(self) -> None:
        if self.ambient is None:
            if self.effects not in PRESET_AMBIENT:
                raise TwinError(f'unknown effects preset {self.effects!r}; choose one of '
                                f'{sorted(PRESET_AMBIENT)}')
            self.ambient = PRESET_AMBIENT[self.effects]


def ambient_profile(spec: str) -> AmbientProfile:
    """``section_4_1`` (the 20 h test of section 4.1), ``constant:T`` [°C], or a YAML file
    holding an :class:`AmbientProfile` (``initial_c`` and a list of ``ramps`` with
    ``duration_s``, ``end_c``, ``time_constant_s``)."""
    if spec == 'section_4_1':
        return AmbientProfile.section_4_1()
    if spec.startswith('constant:'):
        try:
            temp_c = float(spec.split(':', 1)[1])
        except ValueError:
            temp_c = None
        if temp_c is not None:
            try:
                check_room('T', temp_c)       # what the calibration the twin makes may state
            except TwinError as exc:
                raise ConfigError('--ambient', spec, str(exc)) from None
            return AmbientProfile.constant(temp_c)
    elif spec.endswith(('.yaml', '.yml')):
        try:
            return AmbientProfile.from_dict(read_yaml(spec))
        except TwinParameterError as exc:
            raise ConfigError(spec, exc.key, exc.problem) from None
        except TwinError as exc:
            raise ConfigError(spec, '(file)', f'is not an ambient profile: {exc}') from None
    raise ConfigError('--ambient', spec, 'must be section_4_1, constant:T or a profile .yaml')


def spec_inputs(spec: SimulationSpec) -> list[Path]:
    """The files a simulation reads (its device description, its ambient profile file)."""
    files = []
    try:
        files.append(find_config(spec.device))
    except FileNotFoundError:
        pass  # reported when the device is loaded
    if spec.ambient.endswith(('.yaml', '.yml')):
        files.append(Path(spec.ambient))
    return files


def run_log(twin: TwinDevice, calibration: Calibration, run: Any, start_s: float,
            counts: np.ndarray | None = None, name: str = 'twin', epoch_s: int = EPOCH_S
            ) -> RunLog:
    """A run of ``twin`` (:meth:`TwinDevice.simulate`, begun at ``start_s`` [s]) as the log
    :func:`mmd_ros.logs.layout.read_run` would give, in memory, with the documented device and
    ``calibration``; ``counts`` (N, channels) in place of the run's (an effect added to them).
    Stamped as :func:`simulate_to_log` stamps, from the Unix time ``epoch_s`` of the twin's
    clock 0 (the ``epoch_s`` a calibration of it states its time on)."""
    return RunLog(Path(name), twin.documented_device, calibration, None,
                  int(epoch_s) * 1_000_000_000
                  + np.round((start_s + run.times_s) * 1e9).astype(np.int64),
                  np.asarray(run.counts if counts is None else counts, dtype=np.float64),
                  twin.device.channel_names, run.reference, metadata=run.metadata)


def simulated_terminal(device: DeviceDescription, seed: int) -> TerminalBinding:
    """The terminal a twin's calibration names: simulated, its serial the twin's
    (:func:`~mmd_ros.twin.twin.simulated_serial`, ``MMD-SIM-<seed>``, as the nodes' simulated
    terminal of that seed reports): the twins of two seeds are two devices, and a log, a
    calibration or a model of one is refused for the other as another terminal's would be."""
    return TerminalBinding(simulated_serial(seed), True, channel_roles(device.channels))


def simulate_to_log(spec: SimulationSpec, out: Path, *, progress: bool = True
                    ) -> tuple[DeviceDescription, Calibration, dict[str, Any]]:
    """Calibrate the twin on its reference plate, run the scenario, write the log (under a
    temporary name, renamed to ``out`` once complete: a failed run leaves nothing).

    Returns the device, the calibration and a summary of the run.
    """
    device = load_device(find_config(spec.device))
    effects = Effects.preset(spec.effects).with_assignments(spec.effect_params)
    twin = TwinDevice(device, effects, seed=spec.seed)
    device = twin.documented_device      # what the log says of the device, its terminal included
    room = ambient_profile(spec.ambient)
    calibration = replace(
        twin.calibrate(spec.calibrate_at_s, room, approaches=spec.calibration_approaches,
                       epoch_s=spec.epoch_s),
        terminal=simulated_terminal(device, spec.seed))
    scenario = make_scenario(spec.scenario, spec.scenario_params)
    chunks = twin.stream(scenario, room, start_s=spec.start_s, reference=spec.reference,
                         sample_rate_hz=spec.sample_rate_hz, chunk_samples=CHUNK)
    rate = spec.sample_rate_hz or device.sample_rate_hz
    epoch_ns = int(spec.epoch_s) * 1_000_000_000
    total = 0
    bar = None
    first = None
    with replacing(out) as tmp, LogWriter(tmp) as log:
        for chunk in chunks:
            if first is None:
                first = chunk
                t0 = epoch_ns + int(round(spec.start_s * 1e9))
                log.write_string(TOPIC_DEVICE, t0, device.to_yaml())
                log.write_string(TOPIC_CALIBRATION, t0, calibration.to_yaml())
                meta = dict(chunk.metadata)
                meta['simulation'] = {k: list(v) if isinstance(v, tuple) else v
                                      for k, v in spec.__dict__.items()}
                if chunk.targets is not None:
                    meta['iso_targets'] = {'axis': chunk.targets.axis,
                                           'positions': chunk.targets.positions.tolist()}
                log.write_metadata(RUN_METADATA, {k: json.dumps(v) for k, v in meta.items()})
                n_expected = _expected_samples(chunk)
                bar = Progress('simulating', n_expected, enabled=progress)
            stamps = epoch_ns + np.round((spec.start_s + chunk.times_s) * 1e9).astype(np.int64)
            streams = [(TOPIC_RAW, 'sensor_msgs/msg/JointState',
                        log.joint_state_rows(device.channel_names, stamps, chunk.counts.astype(np.float64)))]
            if chunk.reference_kind == 'bar_lengths':
                streams.append((TOPIC_REF_LENGTHS, 'sensor_msgs/msg/JointState',
                                log.joint_state_rows(BAR_NAMES, stamps, chunk.reference)))
            else:
                streams.append((TOPIC_REF_POSE, 'sensor_msgs/msg/JointState',
                                log.joint_state_rows(REFERENCE_POSE_NAMES, stamps, chunk.reference,
                                                     FRAME_LOWER)))
            if chunk.machine_joints is not None:
                streams.append((TOPIC_MACHINE_JOINTS, 'sensor_msgs/msg/JointState',
                                log.joint_state_rows(chunk.machine_joint_names, stamps,
                                                     chunk.machine_joints)))
            log.write_rows(streams, stamps)
            total += chunk.n_samples
            if bar:
                bar.update(total)
    if bar:
        bar.close()
    assert first is not None
    summary = {
        # from the first sample to the last, as mmd process counts it
        'log': str(out), 'samples': total, 'duration_s': (total - 1) / rate, 'sample_rate_hz': rate,
        'scenario': scenario.to_dict(), 'effects': effects.to_dict(), 'seed': spec.seed,
        'reference': first.reference_kind, 'ambient': spec.ambient,
        'ambient_at_calibration_c': calibration.ambient_c,
    }
    return device, calibration, summary


def _expected_samples(chunk: Any) -> float:
    n = chunk.metadata.get('n_samples')
    return float(n) if isinstance(n, (int, float)) else float(CHUNK)
