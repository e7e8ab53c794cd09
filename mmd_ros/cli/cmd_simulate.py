"""``mmd simulate``: run the digital twin and write an MCAP log in our layout."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mmd_ros.core import jsonio, validate
from mmd_ros.hardware.protocol import MAX_SAMPLE_RATE_HZ
from mmd_ros.logs.outputs import check_outputs
from mmd_ros.twin import SCENARIOS
from mmd_ros.twin.effects import PRESETS
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log, spec_inputs
from mmd_ros.twin.twin import MAX_CLOCK_S, MAX_SEED

__all__ = ['register']


def run_command(args: argparse.Namespace) -> int:
    spec = SimulationSpec(
        scenario=args.scenario, scenario_params=tuple(args.param), effects=args.effects,
        effect_params=tuple(args.effect), seed=args.seed, device=args.device, ambient=args.ambient,
        calibrate_at_s=args.calibrate_at, start_s=args.start, reference=args.reference,
        sample_rate_hz=args.rate, calibration_approaches=2 if args.two_sided else 1)
    out = Path(args.out)
    check_outputs([('--out', out)], spec_inputs(spec), force=args.force)
    started = time.perf_counter()
    _, _, summary = simulate_to_log(spec, out, progress=not (args.json or args.quiet))
    summary['seconds'] = time.perf_counter() - started
    if args.json:
        jsonio.dump(summary, sys.stdout)
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
        'see msg_docs/simulation.md for the lists. A run lasts at most a week and has at most '
        '10^9 samples.')
    p.add_argument('--scenario', default='iso_linear', choices=sorted(SCENARIOS),
                   help='what the machine does (default: iso_linear, an ISO 230-2 x-axis run)')
    p.add_argument('--param', action='append', default=[], metavar='NAME=VALUE',
                   help='scenario parameter, e.g. axis=y, n_cycles=5, dwell_s=1.0 (repeatable)')
    p.add_argument('--effects', default='realistic', choices=PRESETS,
                   help='physical effects preset (default: realistic): none (no error source '
                   'at all, room held at 20 °C), ideal (only what the default model '
                   'compensates), realistic (everything on)')
    p.add_argument('--effect', action='append', default=[], metavar='NAME=VALUE',
                   help='change one effect parameter, e.g. hysteresis_m=0.5e-6 (repeatable)')
    p.add_argument('--seed', type=validate.arg_number(low=0, high=MAX_SEED, integer=True),
                   default=1,
                   help='random seed, an integer in [0, 2^64 - 1] (default: 1)')
    p.add_argument('--device', default='mmd_prototype.yaml', help='device description file')
    p.add_argument('--ambient', default=None,
                   help='room temperature: section_4_1 (the 20 h test), constant:T in °C, or a '
                   'profile .yaml (see msg_docs/simulation.md); default constant:20 with '
                   '--effects none, else section_4_1')
    clock = validate.arg_number(low=-MAX_CLOCK_S, high=MAX_CLOCK_S)
    p.add_argument('--calibrate-at', type=clock, default=0.0, dest='calibrate_at',
                   help='time of the calibration on the twin\'s clock [s], within a year of its '
                   'zero (default: 0)')
    p.add_argument('--start', type=clock, default=600.0,
                   help='start of the run on the twin\'s clock [s], within a year of its zero '
                   '(default: 600)')
    p.add_argument('--reference', default=None,
                   help='reference instrument (pose6, laser_x/y/z, rotary_phi/theta/psi, '
                   'bar_lengths); default: the scenario\'s own')
    p.add_argument('--rate', type=validate.arg_number(low=0.0, low_open=True, high=MAX_SAMPLE_RATE_HZ),
                   default=None,
                   help='sample rate of the log [Hz], at most the terminal\'s maximum '
                   f'({MAX_SAMPLE_RATE_HZ} Hz); default the device\'s (1 kHz); a lower rate keeps '
                   'every k-th sample (for hours-long thermal soaks)')
    p.add_argument('--two-sided-calibration', action='store_true', dest='two_sided',
                   help='calibrate every bar on every pair from shorter and from longer and read '
                   'the routine\'s temperature drift (what the pose uncertainty budget can then '
                   'size: hysteresis, seating, drift; msg_docs/frames.md); default the paper\'s '
                   'routine, one placement per pair')
    p.add_argument('--out', required=True, help='MCAP file to write')
    p.add_argument('--force', action='store_true', help='allow --out to replace an existing raw log')
    p.add_argument('--json', action='store_true', help='print a machine-readable summary on stdout')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    p.set_defaults(func=run_command)
