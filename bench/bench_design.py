"""Design-tool benchmarks: the default ``mmd error-budget`` study (section 2.2; N = 10,000 per
run, Figs. 2-4 and the tolerance frontier), Newton against the first-order model, and the
default ``mmd workspace`` study (Fig. 8 and the paper's statements).

Prints the figures and a final JSON line. Target (issue): the default error-budget run in
under a minute on this machine. Never fails on timing.
"""

from __future__ import annotations

import json
import time

import numpy as np

from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.units import M_PER_UM
from mmd_ros.design.error_budget import (
    PAPER_EQ9_UM, PAPER_POSITIONS_M, PARTS, ErrorBudget, eq9_summary, planned_runs, run_study)
from mmd_ros.design.workspace import WorkspaceLimits, run_workspace_study


def main() -> None:
    device = load_device(find_config('mmd_prototype.yaml'))
    geometry = device.design_geometry
    grid = np.linspace(0.0, 1.0, 11) * M_PER_UM
    runs = planned_runs(PARTS, len(PAPER_POSITIONS_M), grid)

    timings = {}
    fits = {}
    for method in ('newton', 'linear'):
        budget = ErrorBudget(geometry, method=method, samples=10_000, seed=0)
        t0 = time.perf_counter()
        study = run_study(budget, PAPER_POSITIONS_M, eps_values_m=grid)
        timings[method] = time.perf_counter() - t0
        assert study.surface is not None
        fits[method] = study.surface
        print(f'error-budget default study, {method:6s}: {timings[method]:6.1f} s for {runs} runs '
              f'of N = 10,000 ({runs * 10_000 / timings[method]:,.0f} samples/s)')
    newton = fits['newton']
    eq9 = eq9_summary(newton)
    print('Eq. (9) fitted (newton): ' + ', '.join(eq9['eq9_text'])
          + '   paper: ' + ', '.join(f'{c:.2f}' for c in PAPER_EQ9_UM))
    print(f'surface RMS fitted vs paper: {newton.rms_um(PAPER_EQ9_UM):.4f} µm')

    t0 = time.perf_counter()
    ws = run_workspace_study(geometry, WorkspaceLimits.from_device(device))
    t_ws = time.perf_counter() - t0
    print(f'workspace default study: {t_ws:6.1f} s')

    result = {
        'benchmark': 'design',
        'error_budget_default_s': timings['newton'],
        'error_budget_linear_s': timings['linear'],
        'error_budget_runs': runs,
        'error_budget_samples_per_run': 10_000,
        'under_a_minute': timings['newton'] < 60.0,
        'eq9_fitted': eq9['eq9_fitted'],
        'eq9_standard_error': eq9['eq9_standard_error'],
        'eq9_rms_vs_paper_um': round(newton.rms_um(PAPER_EQ9_UM), 4),
        'workspace_default_s': t_ws,
        'workspace_statements_hold': [s['holds'] for s in ws.summary()['statements']],
    }
    print(json.dumps(result))


if __name__ == '__main__':
    main()
