"""``mmd simulate``: run the digital twin and write an MCAP log in our layout."""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mmd_ros.cli.progress import Progress
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.device import DeviceDescription, find_config, load_device
from mmd_ros.core.errors import ConfigError
from mmd_ros.core.yamlio import read_yaml
from mmd_ros.logs.layout import (
    BAR_NAMES, FRAME_LOWER, REFERENCE_POSE_NAMES, RUN_METADATA, TOPIC_CALIBRATION, TOPIC_DEVICE,
    TOPIC_RAW, TOPIC_REF_LENGTHS, TOPIC_REF_POSE,
)
from mmd_ros.logs.writer import LogWriter
from mmd_ros.twin import SCENARIOS, AmbientProfile, Effects, TwinDevice, TwinError, make_scenario

__all__ = ['SimulationSpec', 'register', 'simulate_to_log']

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
    ambient: str = 'section_4_1'
    calibrate_at_s: float = 0.0
    start_s: float = 600.0
    reference: str | None = None
    sample_rate_hz: float | None = None
    epoch_s: int = EPOCH_S


def ambient_profile(spec: str) -> AmbientProfile:
    """``section_4_1`` (the 20 h test of section 4.1), ``constant:T`` [°C], or a YAML file
    holding an :class:`AmbientProfile` (``initial_c`` and a list of ``ramps`` with
    ``duration_s``, ``end_c``, ``time_constant_s``)."""
    if spec == 'section_4_1':
        return AmbientProfile.section_4_1()
    if spec.startswith('constant:'):
        try:
            return AmbientProfile.constant(float(spec.split(':', 1)[1]))
        except ValueError:
            pass
    elif spec.endswith(('.yaml', '.yml')):
        try:
            return AmbientProfile.from_dict(read_yaml(spec))
        except TwinError as exc:
            raise ConfigError(spec, '(file)', f'is not an ambient profile: {exc}') from None
    raise ConfigError('--ambient', spec, 'must be section_4_1, constant:T or a profile .yaml')


def simulate_to_log(spec: SimulationSpec, out: Path, *, progress: bool = True
                    ) -> tuple[DeviceDescription, Calibration, dict[str, Any]]:
    """Calibrate the twin on its reference plate, run the scenario, write the log.

    Returns the device, the calibration and a summary of the run.
    """
    device = load_device(find_config(spec.device))
    effects = Effects.preset(spec.effects).with_assignments(spec.effect_params)
    twin = TwinDevice(device, effects, seed=spec.seed)
    room = ambient_profile(spec.ambient)
    calibration = twin.calibrate(spec.calibrate_at_s, room)
    scenario = make_scenario(spec.scenario, spec.scenario_params)
    chunks = twin.stream(scenario, room, start_s=spec.start_s, reference=spec.reference,
                         sample_rate_hz=spec.sample_rate_hz, chunk_samples=CHUNK)
    rate = spec.sample_rate_hz or device.sample_rate_hz
    epoch_ns = int(spec.epoch_s) * 1_000_000_000
    total = 0
    bar = None
    first = None
    with LogWriter(out) as log:
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
            log.write_rows(streams, stamps)
            total += chunk.n_samples
            if bar:
                bar.update(total)
    if bar:
        bar.close()
    assert first is not None
    summary = {
        'log': str(out), 'samples': total, 'duration_s': total / rate, 'sample_rate_hz': rate,
        'scenario': scenario.to_dict(), 'effects': effects.to_dict(), 'seed': spec.seed,
        'reference': first.reference_kind, 'ambient': spec.ambient,
        'ambient_at_calibration_c': calibration.ambient_c,
    }
    return device, calibration, summary


def _expected_samples(chunk: Any) -> float:
    n = chunk.metadata.get('n_samples')
    return float(n) if isinstance(n, (int, float)) else float(CHUNK)


def run_command(args: argparse.Namespace) -> int:
    spec = SimulationSpec(
        scenario=args.scenario, scenario_params=tuple(args.param), effects=args.effects,
        effect_params=tuple(args.effect), seed=args.seed, device=args.device, ambient=args.ambient,
        calibrate_at_s=args.calibrate_at, start_s=args.start, reference=args.reference,
        sample_rate_hz=args.rate)
    started = time.perf_counter()
    _, _, summary = simulate_to_log(spec, Path(args.out), progress=not (args.json or args.quiet))
    summary['seconds'] = time.perf_counter() - started
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        sys.stdout.write('\n')
    else:
        print(f'wrote {summary["log"]}: {summary["samples"]} samples ({summary["duration_s"]:.1f} s at '
              f'{summary["sample_rate_hz"]:g} Hz) of {args.scenario}, effects {args.effects}, seed {args.seed}, reference '
              f'{summary["reference"]}, in {summary["seconds"]:.1f} s')
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'simulate', help='run the digital twin and write an MCAP log',
        description='Calibrate the simulated device on its reference plate (section 3.2), run a '
        'scenario and write the raw counts of all eight channels, the device description, the '
        'calibration and the reference instrument into an MCAP log.',
        epilog='Scenario parameters (--param) and effects (--effect) are name=value; '
        'see msg_docs/simulation.md for the lists.')
    p.add_argument('--scenario', default='iso_linear', choices=sorted(SCENARIOS),
                   help='what the machine does (default: iso_linear, an ISO 230-2 x-axis run)')
    p.add_argument('--param', action='append', default=[], metavar='NAME=VALUE',
                   help='scenario parameter, e.g. axis=y, n_cycles=5, dwell_s=1.0 (repeatable)')
    p.add_argument('--effects', default='realistic', choices=['ideal', 'realistic'],
                   help='physical effects preset (default: realistic)')
    p.add_argument('--effect', action='append', default=[], metavar='NAME=VALUE',
                   help='change one effect parameter, e.g. hysteresis_m=0.5e-6 (repeatable)')
    p.add_argument('--seed', type=int, default=1, help='random seed (default: 1)')
    p.add_argument('--device', default='mmd_prototype.yaml', help='device description file')
    p.add_argument('--ambient', default='section_4_1',
                   help='room temperature: section_4_1 (the 20 h test), constant:T in °C, or a '
                   'profile .yaml (see msg_docs/simulation.md)')
    p.add_argument('--calibrate-at', type=float, default=0.0, dest='calibrate_at',
                   help='time of the calibration on the twin\'s clock [s] (default: 0)')
    p.add_argument('--start', type=float, default=600.0,
                   help='start of the run on the twin\'s clock [s] (default: 600)')
    p.add_argument('--reference', default=None,
                   help='reference instrument (pose6, laser_x/y/z, rotary_phi/theta/psi, '
                   'bar_lengths); default: the scenario\'s own')
    p.add_argument('--rate', type=float, default=None,
                   help='sample rate of the log [Hz]; default the terminal\'s (1 kHz); a lower '
                   'rate keeps every k-th sample (for hours-long thermal soaks)')
    p.add_argument('--out', required=True, help='MCAP file to write')
    p.add_argument('--json', action='store_true', help='print a machine-readable summary on stdout')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    p.set_defaults(func=run_command)
