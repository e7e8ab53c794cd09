"""``make demo``: the main job on the simulated device, printed for a person to read.

1. The digital twin of the paper's prototype is calibrated on its reference plate (section 3.2)
   and records a session, as the paper measured its axes: ISO 230-2 x- and y-axis tests with a
   laser (11 targets over 200 mm, 5 bidirectional cycles), a C-axis test with a rotary
   calibrator, and two minutes of random 6-DOF motion against a 6-DOF reference; later, a
   second x-axis test kept aside. The room is at 22 °C. Raw counts and references go into MCAP logs (250 Hz).
2. ``mmd process`` turns the counts into poses and prints the error against the laser.
3. ``mmd analyze`` closes the loop on the session: the effects the model lacks, identified
   jointly; what each run's reference cannot check is reported, not written; each run predicted
   by the model fitted on the others (leave-one-run-out); ISO 230-2 of the x axis before and
   after on the run kept aside (not used to fit the model).
4. Live: ``pose_node`` on the simulated terminal; the guided calibration through
   ``/mmd/calibrate_bar``; 10 s of the live pose stream while it is recorded; the recorded log
   processed and compared with the twin's reference.
5. Machine tool (``mmd machine``): the MMD in a five-axis XYZAC machine with known errors: a
   short session of the ISO runs of X, Y, Z, C and A with the controller's joint states, the
   machine's error table, report, figures and LinuxCNC compensation files.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mmd_ros.analysis.demo import close_the_loop
from mmd_ros.logs.processing import process_run, summarize, write_processed
from mmd_ros.twin.recording import SimulationSpec, simulate_to_log
from mmd_ros.core.progress import heading
from mmd_ros.core.accuracy import ComponentStats, format_stats
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import read_run

__all__ = ['main']


def show_calibration(calibration: Calibration) -> None:
    print(f'calibrated {len(calibration.bars)} bars on the 7 reference pairs at '
          f'{calibration.ambient_c:.1f} °C:')
    for name, bar in calibration.bars.items():
        counts = bar.counts
        span_mm = (bar.distances_m[-1] - bar.distances_m[0]) * 1e3
        scale_nm = span_mm * 1e6 / (counts[-1] - counts[0])
        print(f'  {name:5s} counts {counts[0]:>13.1f} … {counts[-1]:>13.1f}  '
              f'({span_mm:.4f} mm, {scale_nm:.4f} nm/count)')


#: The demo's session: (log name, scenario, parameters, start on the twin's clock [s]).
SESSION = [
    ('x_axis', 'iso_linear', ('axis=x',), 600.0),
    ('y_axis', 'iso_linear', ('axis=y',), 800.0),
    ('c_axis', 'iso_rotary', ('axis=psi', 'n_cycles=3'), 1000.0),
    ('motion', 'random_motion', ('duration_s=120', 'seed=7'), 1300.0),
]
CHECK = ('x_check', 'iso_linear', ('axis=x',), 1500.0)
RATE_HZ = 250.0


def simulate_session(out_dir: Path) -> list[Path]:
    """The session and the run kept aside; prints the calibration. Returns the logs."""
    heading('1. simulate: a session of the digital twin (x, y laser, C rotary, 6-DOF) and a check run')
    logs = []
    calibration = None
    t0 = time.perf_counter()
    for name, scenario, params, start in [*SESSION, CHECK]:
        spec = SimulationSpec(scenario=scenario, scenario_params=params, effects='realistic', seed=1,
                              ambient='constant:22', calibrate_at_s=0.0, start_s=start,
                              sample_rate_hz=RATE_HZ)
        log = out_dir / f'{name}.mcap'
        _, calibration, summary = simulate_to_log(spec, log, progress=False)
        print(f'wrote {log}: {summary["samples"]} samples = {summary["duration_s"]:.0f} s of '
              f'{scenario} {" ".join(params)}, reference {summary["reference"]}')
        logs.append(log)
    print(f'in {time.perf_counter() - t0:.1f} s')
    assert calibration is not None
    show_calibration(calibration)
    return logs


def process_x(log: Path, out_dir: Path) -> None:
    heading('2. process: counts -> CDF (Eq. 10) -> thermal (Eq. 13) -> forward kinematics')
    run = read_run(log)
    t0 = time.perf_counter()
    model = Model()
    result = process_run(run, model)
    out = out_dir / f'{log.stem}.processed.mcap'
    write_processed(out, run, model, result, run.calibration.to_yaml())
    elapsed = time.perf_counter() - t0
    info = summarize(run, result)
    print(f'{info["samples"]} samples -> {info["valid"]} valid poses '
          f'({info["not_converged"]} not converged, {info["out_of_range"]} out of range) '
          f'in {elapsed:.2f} s = {info["samples"] / elapsed:,.0f} samples/s; wrote {out}')
    print(f'thermal: the reference bar saw {result.reference_error_m[-1, 0] * 1e6:+.3f} µm '
          f'= {result.temp_change_c[-1]:+.2f} °C since calibration')
    print(format_stats([ComponentStats(**s) for s in info['pose_error']],
                       'error of the MMD against the laser along x (MMD - laser):'))


def machine_step(out_dir: Path) -> None:
    """Step 5: a five-axis machine's geometric errors from one MMD session."""
    import math

    from mmd_ros.core.machine import load_machine
    from mmd_ros.machine import IdentifyOptions, SessionOptions, analyze_session, error_table, write_outputs
    from mmd_ros.twin.scenarios import make_scenario

    heading('5. machine tool: a five-axis XYZAC machine\'s errors from one MMD session')
    params = ('machine_file=machine_xyzac.yaml', 'n_linear_targets=6', 'n_rotary_targets=5',
              'n_cycles=3', 'dwell_s=0.4', 'lead_s=0.5')
    spec = SimulationSpec(scenario='machine_session', scenario_params=params, effects='realistic',
                          seed=1, ambient='section_4_1', sample_rate_hz=200.0)
    log = out_dir / 'machine_session.mcap'
    t0 = time.perf_counter()
    _, _, summary = simulate_to_log(spec, log, progress=True)
    print(f'wrote {log}: the ISO runs of X, Y, Z, C (±60°) and A (±15°, Y and Z following) with '
          f'the machine\'s joint states, {summary["duration_s"]:.0f} s at 200 Hz, in '
          f'{time.perf_counter() - t0:.1f} s')
    machine = load_machine('machine_xyzac.yaml')
    t0 = time.perf_counter()
    result = analyze_session([log], machine, SessionOptions(identify=IdentifyOptions(draws=100)))
    print(f'analysed in {time.perf_counter() - t0:.1f} s (mmd machine analyze {log.name} '
          f'--machine machine_xyzac.yaml --out ...)')
    print(error_table(result))
    for line in result.not_determined():
        print(f'  not determined: {line}')
    twin = make_scenario('machine_session', params).machine()
    truth = dict(twin.truth.squareness)
    for name, t in twin.truth.rotary.items():
        for j, c in enumerate('XYZ'):
            truth[f'E{c}0{name}'] = t.position[j]
            truth[f'E{"ABC"[j]}0{name}'] = t.orientation[j]
    print('the twin\'s truth beside them:')
    for v in result.values():
        scale, unit = (1e6, 'µm') if v.unit == 'm' else (180 / math.pi * 3600, '″')
        print(f'  {v.name:<6} identified {v.value * scale:7.2f} ± {v.expanded * scale:5.2f} {unit:<3}'
              f'  truth {truth[v.name] * scale:7.2f}')
    written = write_outputs(result, out_dir / 'machine', SessionOptions())
    print(f'wrote {written["report"]}, {len(written["figures"])} figures, LinuxCNC compensation '
          f'files in {out_dir / "machine" / "compensation"}')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--out', default='out/demo', help='folder for the logs and reports')
    parser.add_argument('--no-live', action='store_true', dest='no_live',
                        help='skip the live ROS 2 step (pose_node, calibration service, recording)')
    parser.add_argument('--live-seconds', type=float, default=10.0, dest='live_seconds',
                        help='length of the live pose stream [s] (default 10)')
    args = parser.parse_args(argv)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    logs = simulate_session(out_dir)
    process_x(logs[0], out_dir)
    close_the_loop(logs[:-1], out_dir / 'analysis', check=logs[-1])
    print(f'(steps 1-3 took {time.perf_counter() - started:.0f} s)')
    if not args.no_live:
        heading('4. live: pose_node on the simulated terminal, through ROS 2')
        from mmd_ros.nodes.live_demo import live_step
        if live_step(out_dir, stream_s=args.live_seconds, heading=heading):
            return 1
    machine_step(out_dir)
    return 0


if __name__ == '__main__':
    sys.exit(main())
