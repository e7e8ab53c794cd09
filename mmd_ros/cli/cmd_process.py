"""``mmd process LOG.mcap``: counts → CDF → thermal → FK for every sample of a log."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mmd_ros.cli.log_args import (add_device_argument, add_segment_argument, log_device,
                                  print_read_notes)
from mmd_ros.core import jsonio
from mmd_ros.core.accuracy import format_stats
from mmd_ros.core.calibration import load_calibration
from mmd_ros.core.lag import MAX_SKEW_S, ReferenceLag
from mmd_ros.core.model import Model, load_model
from mmd_ros.core.progress import Progress
from mmd_ros.logs.errors import StampsNotIncreasing
from mmd_ros.logs.layout import metadata_note, open_run, read_run
from mmd_ros.logs.outputs import check_outputs
from mmd_ros.logs.processing import process_log

__all__ = ['register']

#: What ``mmd process`` does with a reference's lag
LAG_TAKEN_OUT = ('each MMD sample is compared with the reference\'s reading of its instant '
                 '(its reading a whole number of periods away, moved on along the MMD\'s '
                 'motion by the rest)')


def _capital(text: str) -> str:
    return text[:1].upper() + text[1:]


def run_command(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    quiet = args.json or args.quiet
    out = Path(args.out) if args.out else Path(args.log).with_suffix('.processed.mcap')
    check_outputs([('--out', out), ('--csv', args.csv)], [args.log, args.model, args.calibration],
                  force=args.force)
    device = log_device(args)
    if not quiet:
        print(f'reading {args.log}', file=sys.stderr)
    cal = load_calibration(args.calibration) if args.calibration else None
    chosen = load_model(args.model) if args.model else None

    def process(run) -> dict:
        progress = Progress('processing', max(run.n_samples, 1), enabled=not quiet)
        summary = process_log(run, out, chosen or run.model or Model(), calibration=cal,
                              with_covariance=args.covariance,
                              csv=Path(args.csv) if args.csv else None, progress=progress,
                              absolute_reference=args.absolute_reference,
                              coverage=args.coverage, reference_clock=args.reference_clock)
        progress.close()
        return summary

    if args.segment is not None:
        run = read_run(args.log, segment=args.segment, device=device)   # one segment, in memory
        summary = process(run)
    else:
        try:
            with open_run(args.log, device) as run:   # block by block, in bounded memory
                summary = process(run)
        except StampsNotIncreasing:
            run = read_run(args.log, device=device)   # refuses, naming the segments (--segment)
            summary = process(run)
    model = chosen or run.model or Model()
    if summary.get('log_problem'):
        print(f'warning: {summary["log_problem"]["message"]}', file=sys.stderr)
    if metadata_note(run):
        print(f'warning: {metadata_note(run)}', file=sys.stderr)
    print_read_notes(run)
    if summary.get('model_calibration'):
        print(f'warning: {summary["model_calibration"]}', file=sys.stderr)
    if summary.get('reference_scale_note'):
        print(f'warning: {args.log}: {summary["reference_scale_note"]}', file=sys.stderr)
    if getattr(run, 'reference_note', ''):
        summary['reference_note'] = run.reference_note
    elapsed = time.perf_counter() - started
    summary.update(output=str(out), csv=args.csv, seconds=elapsed,
                   samples_per_s=summary['samples'] / elapsed if elapsed > 0 else None,
                   model=model.to_dict())
    if args.json:
        jsonio.dump(summary, sys.stdout)
        return 0
    print(f'{summary["samples"]} samples over {summary["duration_s"]:.1f} s: '
          f'{summary["valid"]} valid poses, {summary["not_converged"]} not converged, '
          f'{summary["out_of_range"]} with a bar out of its calibrated range'
          + (f', {summary["no_signal"]} without encoder signal (flagged by the terminal: no pose)'
             if summary['no_signal'] else ''))
    print(f'wrote {out}' + (f' and {args.csv}' if args.csv else '')
          + f' in {elapsed:.2f} s ({summary["samples_per_s"]:.0f} samples/s)')
    lag = summary.get('reference_lag')
    if lag is not None:
        read = ReferenceLag(lag['delay_s'], lag['sd_s'], lag['clock_stated_own'])
        if lag['taken_out']:
            print(_capital(read.text(LAG_TAKEN_OUT)) + '.')
        elif read.sd_s <= MAX_SKEW_S:
            print(f'the reference reads {read.delay_s * 1e6:+.3g} ± {read.sd_s * 1e6:.2g} µs '
                  'against the MMD: within what its channels can latch, so left in the error '
                  '(the MMD\'s own sampling skew; --reference-clock own says otherwise)')
    if summary.get('pose_error_note'):
        print(f'pose error against the reference: none, {summary["pose_error_note"]}')
    elif 'pose_error' in summary:
        from mmd_ros.core.accuracy import ComponentStats
        print(format_stats([ComponentStats(**s) for s in summary['pose_error']],
                           'pose error against the reference (MMD - reference):'))
    if 'uncertainty_coverage' in summary:
        from mmd_ros.core.accuracy import format_coverage
        print(format_coverage(summary['uncertainty_coverage']))
        for note in summary.get('uncertainty_budget', {}).get('notes', []):
            print(f'  not in the budget: {note}')
    if 'length_error' in summary:
        from mmd_ros.core.accuracy import ComponentStats
        print(format_stats([ComponentStats(**s) for s in summary['length_error']],
                           'bar length error against the reference:'))
    if 'length_uncertainty_coverage' in summary:
        from mmd_ros.core.accuracy import format_coverage
        print(format_coverage(summary['length_uncertainty_coverage']))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser('process', help='compute bar lengths and poses for every sample of a log',
                       description='Run the model over every sample of a log (counts → CDF, Eq. 10 → '
                       'thermal, Eqs. 11–13 → model terms → forward kinematics) and write the bar '
                       'lengths and poses as MCAP (CSV on request). With a reference in the log, '
                       'print the error statistics in µm and arc-seconds.')
    p.add_argument('log', help='MCAP log with raw counts (from mmd simulate, the recorder, a user)')
    p.add_argument('--model', help='model file (YAML); default: the log\'s model, else CDF + thermal')
    p.add_argument('--calibration', help='calibration file to use instead of the one in the log')
    add_device_argument(p)
    p.add_argument('--out', help='output MCAP (default: LOG.processed.mcap)')
    p.add_argument('--csv', help='also write the poses and lengths as CSV to this file')
    p.add_argument('--covariance', action='store_true',
                   help='also write /mmd/pose_with_covariance (the propagated uncertainty, '
                   'msg_docs/frames.md); with a reference pose in the log it is always computed '
                   'and compared with the error')
    datum = p.add_mutually_exclusive_group()
    datum.add_argument('--absolute-reference', action='store_const', const=True,
                       dest='absolute_reference',
                       help='the reference pose is absolute in {L} (default: as the log says, '
                       'metadata reference_absolute; a log that does not say is read from its '
                       'offsets from the MMD: msg_docs/analysis.md, Absolute or zeroed)')
    datum.add_argument('--zeroed-reference', action='store_const', const=False,
                       dest='absolute_reference',
                       help='the reference was zeroed somewhere: a constant offset per component '
                       'is removed, over what the log says')
    p.add_argument('--reference-clock', choices=('shared', 'own'), dest='reference_clock',
                   help='whose clock the reference pose ran on, over what the log says (metadata '
                   'reference_clock): shared, the MMD\'s instants, or own; unless shared, a '
                   'delay between the two beyond what the MMD\'s channels can latch, or any on '
                   'a clock of its own, is taken out of the comparison (msg_docs/analysis.md)')
    p.add_argument('--no-coverage', action='store_false', dest='coverage',
                   help='with a reference pose in the log, do not compute the covariance to report '
                   'how well it covers the error (faster on long logs)')
    add_segment_argument(p)
    p.add_argument('--force', action='store_true',
                   help='allow --out/--csv to replace an existing raw log (never the input)')
    p.add_argument('--json', action='store_true', help='print a machine-readable summary on stdout')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    p.set_defaults(func=run_command)
