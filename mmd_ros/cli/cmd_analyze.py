"""``mmd analyze LOG.mcap [LOG.mcap ...] --out DIR``: close the loop with measured data
(residual → effect → extended model → error before and after), on one log or a session of logs
of one device."""

from __future__ import annotations

import argparse
import sys
import time

from mmd_ros.analysis.effects import CATALOGUE
from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.identify import AnalysisOptions, analyze
from mmd_ros.analysis.report import format_summary, write_report
from mmd_ros.cli.log_args import (add_device_argument, add_segment_argument, log_device,
                                  print_read_notes)
from mmd_ros.core import jsonio, validate
from mmd_ros.core.calibration import load_calibration
from mmd_ros.core.model import Model, load_model
from mmd_ros.core.units import M_PER_UM
from mmd_ros.logs.layout import metadata_note, read_run
from mmd_ros.logs.outputs import check_output_folder

__all__ = ['register']

#: What ``--out`` receives (checked against the inputs before anything is read).
OUTPUT_FILES = ('report.md', 'analysis.json', 'model.yaml', '*.png')
#: Bounds of the options (argparse prints them with the error).
MAX_BLOCKS = 10_000
MAX_SAMPLES = 10_000_000
MAX_PERIOD_UM = 10_000.0
MAX_LOG_SAMPLES = 1_000_000_000


def _names(text: str | None) -> list[str] | None:
    if not text:
        return None
    names = [n.strip() for n in text.split(',') if n.strip()]
    unknown = [n for n in names if n not in CATALOGUE]
    if unknown:
        raise AnalysisError(f'unknown effects {unknown}; the catalogue has {list(CATALOGUE)}')
    return names


def run_command(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    quiet = args.json or args.quiet
    check_output_folder('--out', args.out, [*args.logs, args.model, args.calibration], OUTPUT_FILES)

    def say(text: str) -> None:
        if not quiet:
            print(f'[{time.perf_counter() - started:6.1f} s] {text}', file=sys.stderr, flush=True)

    runs = []
    flagged_samples = {}
    device = log_device(args)
    for path in args.logs:
        say(f'reading {path}')
        run = read_run(path, segment=args.segment, device=device)
        if run.problem:
            print(f'warning: {path}: {run.problem}', file=sys.stderr)
        if metadata_note(run):
            print(f'warning: {metadata_note(run)}', file=sys.stderr)
        print_read_notes(run)
        unreadable = int(run.unreadable.sum())
        run, flagged = run.without_flagged()
        flagged_samples[str(path)] = flagged
        if flagged - unreadable:
            print(f'warning: {path}: {flagged - unreadable} sample(s) the terminal flagged '
                  '(encoder signal lost) are not measurements: left out of the analysis',
                  file=sys.stderr)
        if unreadable:
            print(f'warning: {path}: {unreadable} sample(s) with a count that is not a number '
                  'are not measurements: left out of the analysis', file=sys.stderr)
        runs.append(run)
    model = load_model(args.model) if args.model else (runs[0].model or Model())
    calibration = load_calibration(args.calibration) if args.calibration else None
    periods = tuple(v * M_PER_UM for v in args.cyclic_period_um) if args.cyclic_period_um else None
    options = AnalysisOptions(
        effects=_names(args.effects), exclude=tuple(_names(args.exclude) or ()),
        n_blocks=args.blocks, max_samples=args.max_samples, min_gain=args.min_gain,
        max_effects=args.max_effects, datum=args.datum,
        seed=args.seed, cyclic_periods_m=periods, accept_unchecked=args.accept_unchecked,
        axis_motion=not args.no_axis_motion, stated_sag=not args.no_stated_sag,
        reference_clock=args.reference_clock, max_log_samples=args.max_log_samples)
    result = analyze(runs, model, calibration, options, progress=say)
    written = {}
    if args.out:
        say(f'writing the report to {args.out}')
        written = write_report(result, args.out, figures=not args.no_figures)
    if args.json:
        data = result.as_dict()
        data['model_file'] = str(written['model']) if 'model' in written else None
        data['flagged_samples_left_out'] = flagged_samples
        jsonio.dump(data, sys.stdout)
        return 0
    print(format_summary(result))
    if written:
        print(f'wrote {written["report"]}' + (f', {written["model"]}' if 'model' in written else '')
              + f' and {written["json"]}')
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'analyze', help='find the residual, trace it to a missing effect, extend the model',
        description='Run the current model over a log with a reference, compute the residual at '
        'the level the reference allows (pose components or bar lengths), test a catalogue of '
        'physical effects the model may lack on held-out time blocks, add those that explain the '
        'residual significantly, write the extended model and report the error before and after '
        '(the pipeline re-run with the extended model).',
        epilog=f'Catalogue: {", ".join(CATALOGUE)}. See msg_docs/analysis.md.')
    p.add_argument('logs', nargs='+', metavar='LOG',
                   help='MCAP logs of one device with raw counts and a reference (pose components or '
                   'bar lengths): one run, or the session of runs (x, y, z, C...) analysed jointly')
    p.add_argument('--model', help='current model file (default: the log\'s, else CDF + thermal)')
    p.add_argument('--calibration', help='calibration file to use instead of the one in the log')
    add_device_argument(p)
    p.add_argument('--out', help='folder for report.md, analysis.json, the figures and model.yaml')
    p.add_argument('--json', action='store_true', help='print the numbers as JSON on stdout')
    p.add_argument('--effects', help='comma-separated effects to test (default: the whole catalogue)')
    p.add_argument('--exclude', help='comma-separated effects not to test')
    p.add_argument('--blocks', type=validate.arg_number(low=2, high=MAX_BLOCKS, integer=True),
                   default=40, help='time blocks of the split (default 40)')
    p.add_argument('--max-samples', type=validate.arg_number(low=10, high=MAX_SAMPLES, integer=True),
                   default=2500, dest='max_samples', help='samples per part used for fitting (default 2500)')
    p.add_argument('--min-gain', type=validate.arg_number(low=0.0, high=1.0, high_open=True),
                   default=0.05, dest='min_gain',
                   help='smallest relative fall of the held-out RMS for an effect, in [0, 1) '
                   '(default 0.05)')
    held = AnalysisOptions.max_log_samples
    p.add_argument('--max-log-samples', dest='max_log_samples', default=held,
                   type=validate.arg_number(low=1000, high=MAX_LOG_SAMPLES, integer=True),
                   help='the most samples the analysis holds over all its logs (about 2.7 kB '
                   'each): longer logs are analysed at every k-th sample, k the smallest that '
                   f'fits (default {held}: 20 minutes at 1 kHz, about 3.2 GB)')
    p.add_argument('--max-effects', type=validate.arg_number(low=0, high=len(CATALOGUE), integer=True),
                   default=6, dest='max_effects', help='most effects added (default 6)')
    p.add_argument('--cyclic-period-um', dest='cyclic_period_um',
                   type=validate.arg_numbers(low=0.0, low_open=True, high=MAX_PERIOD_UM),
                   help='signal period(s) of the scales in µm, comma separated (default: estimated '
                   'from the residual\'s spectrum against each bar\'s scale position)')
    p.add_argument('--accept-unchecked', action='store_true', dest='accept_unchecked',
                   help='also write effects whose consequence on pose components no reference saw '
                   'is not determined by the data (default: reported, not written)')
    p.add_argument('--no-axis-motion', action='store_true', dest='no_axis_motion',
                   help='read a one-axis run (one reference component) in that component only '
                   '(default: the MMD\'s other five components are read as the machine\'s motion '
                   'along the axis, a function of its position and direction, which determines '
                   'what moves with speed)')
    p.add_argument('--no-stated-sag', action='store_true', dest='no_stated_sag',
                   help='start from the model as given (default: also from the bars\' gravity sag '
                   'the device description states, bars.gravity_sag_nm, when the model has none; '
                   'a zeroed reference does not see the common mode it moves)')
    datum = p.add_mutually_exclusive_group()
    datum.add_argument('--absolute-reference', action='store_const', const='none', dest='datum',
                       default='auto',
                       help='every reference pose is absolute in {L}, over what the logs say '
                       '(default: as a log says, metadata reference_absolute; a log that does '
                       'not say is read from its offsets from the MMD: msg_docs/analysis.md, '
                       'Absolute or zeroed)')
    datum.add_argument('--zeroed-reference', action='store_const', const='offset', dest='datum',
                       help='every reference was zeroed somewhere: a constant offset per '
                       'component is removed, over what the logs say')
    p.add_argument('--reference-clock', choices=('shared', 'own'), dest='reference_clock',
                   help='whose clock the references ran on, over what the logs say (metadata '
                   'reference_clock): shared, the MMD\'s (a common delay is the channels\'), '
                   'or own (its lag is fitted per log; msg_docs/analysis.md)')
    p.add_argument('--seed', type=validate.arg_number(low=0, integer=True), default=0,
                   help='draws the held-out blocks (default 0)')
    add_segment_argument(p)
    p.add_argument('--no-figures', action='store_true', dest='no_figures', help='skip the PNG figures')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')
    p.set_defaults(func=run_command)
