"""The last part of ``make demo``: close the loop on the demo's simulated session.

``mmd_ros.demo`` simulates a session of the realistic twin (an x-axis laser run, a C-axis rotary
run, a 6-DOF run) and a second x-axis run kept aside; this analyses the session jointly (the
residual against each reference, the effects found, what is written and what each reference
cannot check), prints each run predicted by the model fitted on the others (leave-one-run-out),
writes the report and the extended model, and evaluates the x axis by ISO 230-2 before and
after, as Table 4 of the paper, on the run kept aside. Run it alone on any logs:

    python -m mmd_ros.analysis.demo out/demo/x_axis.mcap out/demo/c_axis.mcap --out out/demo/analysis
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mmd_ros.analysis.identify import Analysis, analyze
from mmd_ros.analysis.iso230 import figure_table
from mmd_ros.analysis.report import in_range_text, write_report
from mmd_ros.core.progress import heading
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import read_run

__all__ = ['close_the_loop', 'main']

_UNIT = {'um': 'µm', 'arcsec': '″'}


def close_the_loop(logs: list[str | Path], out_dir: str | Path, *,
                   check: str | Path | None = None) -> Analysis:
    """Analyse ``logs`` jointly, write the report into ``out_dir`` and print what was found;
    with ``check``, ISO 230-2 of that run's axis before and after."""
    out = Path(out_dir)
    heading('3. analyze: residual -> effect the model lacks -> extended model, on the session')
    t0 = time.perf_counter()
    runs = [read_run(log) for log in logs]
    result = analyze(runs)
    written = write_report(result, out)
    print(f'validation: {result.validation}')
    for text in result.stated:
        print(f'started from {text}: "before" includes it (the model as given is shown where '
              'that differs)')
    for r in result.runs:
        print(f'{Path(r.name).name} ({r.reference}), noise floor '
              + ', '.join(f'{n} {v:.2g} {_UNIT[u]}' for (n, v), u in zip(r.floor.items(), r.units)))
        if r.given is not None and _line(r.given) != _line(r.before):
            print(f'  held-out blocks, the model as given: {_line(r.given)}')
        print(f'  held-out blocks: {_line(r.before)}  ->  {_line(r.after) if r.after else "unchanged"}')
        if r.loro_before is not None:
            print(f'  predicted by the model fitted on the other runs: {_line(r.loro_before)}  ->  '
                  f'{_line(r.loro_after)}' + (f' ({r.loro_note})' if r.loro_note else '')
                  + in_range_text(r))
    if not result.found:
        print('nothing written: the model is unchanged')
    for f in result.found:
        print(f'written: {f.title} [{f.effect}' + (f', {f.hyper_label}' if f.hyper_label else '') + ']')
        for line in f.interpretation:
            print(f'  {line}')
    for f in result.unchecked:
        print(f'found but not written: {f.title}: {f.reason}')
    for f in result.not_claimed:
        print(f'not claimed: {f.title}: {f.reason}')
    print('remaining: ' + ('at the noise floor' if result.at_floor else
                           'above the noise floor, following ' + ', '.join(
                               f'{n} (R² {r:.2f})' for n, r in result.structure_after[:3])))
    print(f'wrote {written["report"]}' + (f' and {written["model"]}' if 'model' in written else '')
          + f' in {time.perf_counter() - t0:.1f} s')
    if result.model is not None and check is not None:
        from mmd_ros.analysis.iso230_report import iso230_of_run
        run = read_run(check)
        axis = (run.metadata.get('iso_targets') or {}).get('axis')
        if axis:
            heading(f'4. ISO 230-2 of axis {axis} on {Path(check).name}, before and after (as Table 4)')
            report = iso230_of_run(run, None, {'MMD before': run.model or Model(),
                                              'MMD after': result.model})
            print(report.sample_note() or f'{Path(check).name} was not used to fit the model.')
            print(figure_table(report.rows(), report.unit))
    return result


def _line(stats) -> str:
    return ', '.join(f'{s.name} {s.rms:.3g} {_UNIT[s.unit]}' for s in stats if not s.name.startswith('overall'))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('logs', nargs='+', help='logs of one device with references')
    parser.add_argument('--out', default='out/demo/analysis', help='folder for the report')
    parser.add_argument('--check', help='a run not in the session: ISO 230-2 before and after')
    args = parser.parse_args(argv)
    close_the_loop(args.logs, args.out, check=args.check)
    return 0


if __name__ == '__main__':
    sys.exit(main())
