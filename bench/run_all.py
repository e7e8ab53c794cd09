"""Run every benchmark in bench/ (``make bench``) and collect their JSON lines.

Each benchmark prints its figures and ends with one JSON line; this runner prints them as it
goes and writes all JSON lines to ``out/bench.jsonl``. Benchmarks never fail on timing.
Pass ``--quick`` to give it to the benchmarks that have a quick mode.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
QUICK = {'bench_machine.py', 'bench_process.py', 'bench_ros.py'}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--quick', action='store_true')
    args = parser.parse_args()
    results = []
    failed = []
    for script in sorted(HERE.glob('bench_*.py')):
        cmd = [sys.executable, str(script)] + (['--quick'] if args.quick and script.name in QUICK else [])
        print(f'\n### {script.name}', flush=True)
        run = subprocess.run(cmd, capture_output=True, text=True)
        sys.stdout.write(run.stdout)
        if run.returncode != 0:
            failed.append(script.name)
            sys.stdout.write(run.stderr[-2000:])
            continue
        lines = [line for line in run.stdout.splitlines() if line.startswith('{')]
        if lines:
            results.append(json.loads(lines[-1]))
    out = Path('out')
    out.mkdir(exist_ok=True)
    (out / 'bench.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in results))
    print(f'\n{len(results)} benchmarks, JSON lines in out/bench.jsonl'
          + (f'; failed to run: {failed}' if failed else ''))
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
