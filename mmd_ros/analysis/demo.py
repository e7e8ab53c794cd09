"""The last part of ``make demo``: close the loop on the demo's own simulated run.

``mmd_ros.demo`` simulates an ISO 230-2 x-axis run of the realistic twin and processes it; this
analyses that log (the residual against the laser, the effects found, the error before and after
on held-out data), writes the report and the extended model, and evaluates the axis by ISO 230-2
before and after, as Table 4 of the paper. Run it alone on any log:

    python -m mmd_ros.analysis.demo out/demo/x_axis.mcap --out out/demo/analysis
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mmd_ros.analysis.identify import Analysis, analyze
from mmd_ros.analysis.iso230 import figure_table
from mmd_ros.analysis.report import write_report
from mmd_ros.core.progress import heading
from mmd_ros.core.model import Model
from mmd_ros.logs.layout import read_run

__all__ = ['close_the_loop', 'main']

_UNIT = {'um': 'µm', 'arcsec': '″'}


def close_the_loop(log: str | Path, out_dir: str | Path) -> Analysis:
    """Analyse ``log``, write the report into ``out_dir`` and print what was found."""
    out = Path(out_dir)
    heading('3. analyze: residual -> effect the model lacks -> extended model')
    t0 = time.perf_counter()
    run = read_run(log)
    result = analyze(run)
    written = write_report(result, out)
    print(f'residual of the current model against the {result.obs.description} '
          f'(held-out blocks, {result.split.test_idx.size} samples):')
    for s in result.stats_before:
        print(f'  {s.name:<16} RMS {s.rms:8.3f} {_UNIT[s.unit]}   max {s.max_abs:8.3f} {_UNIT[s.unit]}')
    top = ', '.join(f'{name} (R² {r2:.2f})' for name, r2 in result.structure_before[:3])
    print(f'  it follows: {top}')
    if not result.found:
        print('no catalogued effect explains it significantly: the model is unchanged')
    for f in result.found:
        print(f'found: {f.title} [{f.effect}' + (f', {f.hyper_label}' if f.hyper_label else '') + ']')
        for line in f.interpretation:
            print(f'  {line}')
    for f in result.not_claimed:
        print(f'not claimed: {f.title}: {f.reason}')
    if result.stats_after:
        print('error before -> after on the held-out blocks (pipeline re-run with the extended model):')
        after = {s.name: s for s in result.stats_after}
        for s in result.stats_before:
            a = after[s.name]
            print(f'  {s.name:<16} RMS {s.rms:8.3f} -> {a.rms:8.3f} {_UNIT[s.unit]}   '
                  f'max {s.max_abs:8.3f} -> {a.max_abs:8.3f} {_UNIT[s.unit]}')
    print('remaining: ' + ('at the noise floor' if result.at_floor else
                           'above the noise floor, following ' + ', '.join(
                               f'{n} (R² {r:.2f})' for n, r in result.structure_after[:3])))
    print(f'wrote {written["report"]}' + (f' and {written["model"]}' if 'model' in written else '')
          + f' in {time.perf_counter() - t0:.1f} s')
    if result.model is not None and (run.metadata.get('iso_targets') or {}).get('axis'):
        from mmd_ros.analysis.iso230_report import iso230_of_run
        heading('4. ISO 230-2 of the axis, before and after (as Table 4)')
        report = iso230_of_run(run, None, {'MMD before': run.model or Model(), 'MMD after': result.model})
        print(figure_table(report.rows(), report.unit))
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('log', help='a log with a reference (e.g. out/demo/x_axis.mcap)')
    parser.add_argument('--out', default='out/demo/analysis', help='folder for the report')
    args = parser.parse_args(argv)
    close_the_loop(args.log, args.out)
    return 0


if __name__ == '__main__':
    sys.exit(main())
