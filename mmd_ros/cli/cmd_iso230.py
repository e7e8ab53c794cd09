"""``mmd iso230-2 LOG.mcap|TABLE.csv``: ISO 230-2 evaluation of a linear or rotary axis from a
log, or from a table of laser or rotary-calibrator readings (told apart by content)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.iso230 import figure_table, target_table
from mmd_ros.analysis.iso230_csv import iso230_of_csv, source_kind
from mmd_ros.analysis.iso230_report import INSTRUMENTS, Iso230Report, iso230_of_run, parse_targets
from mmd_ros.cli.log_args import (add_device_argument, add_segment_argument, log_device,
                                  print_read_notes)
from mmd_ros.core import jsonio, validate
from mmd_ros.core.model import Model, load_model
from mmd_ros.core.progress import Progress
from mmd_ros.logs.layout import metadata_note, read_run
from mmd_ros.logs.outputs import check_output_folder

__all__ = ['register']

#: Options that only mean something for a log of raw counts (argparse dests).
MCAP_ONLY = ('model', 'after', 'calibration', 'instrument', 'segment')
#: What ``--out`` receives (checked against the inputs before anything is read).
OUTPUT_FILES = ('iso230.md', 'iso230.json', 'iso230_*.png')
#: Longest dwell asked for [s].
MAX_DWELL_S = 3600.0


def _report_of_log(args: argparse.Namespace) -> Iso230Report:
    run = read_run(args.log, segment=args.segment, device=log_device(args))
    for problem in (run.problem, metadata_note(run)):
        if problem:
            print(f'warning: {problem}', file=sys.stderr)
    print_read_notes(run)
    models: dict[str, Model] = {}
    models['MMD' if not args.after else 'MMD before'] = load_model(args.model) if args.model else (run.model or Model())
    if args.after:
        models['MMD after'] = load_model(args.after)
    axis = args.axis or (run.metadata.get('iso_targets') or {}).get('axis')
    if not axis:
        raise AnalysisError(f'{args.log} does not say which axis was tested; pass --axis')
    instruments = tuple(args.instrument) if args.instrument else INSTRUMENTS
    progress = Progress('processing', 1.0, enabled=not (args.quiet or args.json))
    report = iso230_of_run(run, axis, models, instruments=instruments,
                           targets=parse_targets(args.targets, axis), min_dwell_s=args.min_dwell,
                           calibration_path=args.calibration, progress=progress.update)
    progress.close()
    return report


def run_command(args: argparse.Namespace) -> int:
    check_output_folder('--out', args.out, [args.log, args.model, args.after, args.calibration],
                        OUTPUT_FILES)
    if source_kind(args.log) == 'csv':
        given = [f'--{o}' for o in MCAP_ONLY if getattr(args, o)]
        if given:
            raise AnalysisError(f'{" and ".join(given)} apply to an MCAP log; {args.log} is a table '
                                'of readings')
        report = iso230_of_csv(args.log, axis=args.axis, targets=args.targets,
                               min_dwell_s=args.min_dwell)
    else:
        report = _report_of_log(args)
    figures: dict[str, str] = {}
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        from mmd_ros.analysis.plots import iso230_figure
        for name, r in report.results.items():
            fname = 'iso230_' + ''.join(c if c.isalnum() else '_' for c in name.lower()).strip('_') + '.png'
            iso230_figure(r, out / fname)
            figures[name] = fname
        (out / 'iso230.md').write_text(report.markdown(figures), encoding='utf-8')
        (out / 'iso230.json').write_text(jsonio.dumps(report.as_dict()), encoding='utf-8')
    if args.json:
        jsonio.dump(report.as_dict(), sys.stdout)
        return 0
    print(f'ISO 230-2, axis {report.axis}, {"log" if report.source == "mcap" else report.source} '
          f'{args.log}')
    if report.sample_note():
        print(report.sample_note())
    for tag, text in report.models.items():
        print(f'  {tag}: {text}')
    print(figure_table(report.rows(), report.unit))
    if args.verbose:
        for name, r in report.results.items():
            print(f'\n{name} (n = {r.n}):')
            print(target_table(r))
    if args.out:
        print(f'wrote {Path(args.out) / "iso230.md"}, iso230.json and {len(figures)} figure(s)')
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'iso230-2', help='ISO 230-2 evaluation of a linear or rotary axis run (log or CSV)',
        description='Evaluate an ISO 230-2 positioning run (targets found from the dwells, or '
        'given) as the paper did in sections 5.2–5.3: per target the mean unidirectional '
        'deviations, reversal and standard uncertainties; for the axis A, A↑, A↓, B, B̄, E, E↑, '
        'E↓, M, R, R↑, R↓. Evaluates the MMD (under one or two models), the reference '
        'instrument and their difference, in the layout of Tables 3–4. A CSV table of laser or '
        'rotary-calibrator readings is evaluated the same way: one row per approach (target, '
        'direction, deviation [, run, instrument]), one row per target (target, +1 … +n, '
        '-1 … -n), or a time series (time, position…).',
        epilog='See msg_docs/analysis.md for the definitions, the table layouts and units.')
    p.add_argument('log', help='MCAP log of the run (raw counts, and the reference if any), or '
                   'a CSV table of readings')
    p.add_argument('--axis', help='axis moved: x, y, z, phi (A), theta (B), psi (C); default '
                   'from the log\'s iso_targets metadata; for a table default x (linear, mm '
                   'and µm), required for a rotary one')
    p.add_argument('--model', help='model file for the MMD (default: the log\'s, else CDF + thermal)')
    p.add_argument('--after', help='a second model file (e.g. from mmd analyze): adds the MMD '
                   '"after" rows, as Table 4\'s before/after error compensation')
    p.add_argument('--calibration', help='calibration file to use instead of the one in the log')
    add_device_argument(p)
    p.add_argument('--instrument', action='append', choices=INSTRUMENTS,
                   help='what to evaluate (repeatable): mmd, reference, error (MMD - reference at '
                   'every sample); default all three')
    p.add_argument('--targets', help='target positions, comma separated, in mm or degrees; '
                   'default the log\'s, else clustered from the dwells (a time-series table: '
                   'in its position unit)')
    p.add_argument('--min-dwell', type=validate.arg_number(low=0.0, low_open=True, high=MAX_DWELL_S),
                   default=0.15, dest='min_dwell',
                   help='shortest stationary stretch taken as a dwell at a target [s] (default 0.15)')
    p.add_argument('--out', help='folder for iso230.md, iso230.json and the plots')
    p.add_argument('--json', action='store_true', help='print the numbers as JSON on stdout')
    p.add_argument('--verbose', action='store_true', help='also print the per-target table')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    add_segment_argument(p)
    p.set_defaults(func=run_command)
