"""Tables and the Markdown report of a machine session (µm, arc-seconds, mm, degrees)."""

from __future__ import annotations

import math
from typing import Any

from mmd_ros.machine.results import COVERAGE_K, AxisResult, MachineResult, Value, report_scale

__all__ = ['error_rows', 'error_table', 'markdown_report']


def error_rows(result: MachineResult) -> list[dict[str, Any]]:
    """One row per reported error: squareness, location errors, and each error motion's figure
    (straightness error, angular deviation, positioning E, rotary error motion ranges)."""
    rows = []

    def add(v: Value, axis: str, kind: str) -> None:
        scale, unit = report_scale(v.unit)
        rows.append({'error': v.name.replace(' figure', ''), 'axis': axis, 'kind': kind,
                     'value': v.value * scale if math.isfinite(v.value) else None,
                     'U': v.expanded * scale if math.isfinite(v.u) else None,
                     'U_mmd': COVERAGE_K * v.u_mmd * scale if math.isfinite(v.u_mmd) else None,
                     'k': v.k,
                     'unit': unit, 'determined': v.determined, 'note': v.note})

    for v in result.squareness:
        add(v, '-', 'squareness')
    for name, a in result.axes.items():
        for v in a.location:
            add(v, name, 'location')
    for name, a in result.axes.items():
        for m in a.motions:
            kind = {'positioning': 'positioning E', 'straightness': 'straightness',
                    'angular': 'angular deviation', 'radial': 'radial motion', 'axial': 'axial motion',
                    'tilt': 'tilt motion'}[m.kind]
            if a.rotary and m.kind == 'positioning':
                kind = 'angular positioning E'
            add(m.figure, name, kind)
    return rows


def _fmt(v: float | None, digits: int = 2) -> str:
    return '–' if v is None or not math.isfinite(v) else f'{v:.{digits}f}'


def error_table(result: MachineResult, *, markdown: bool = False) -> str:
    """The machine's error table: value, expanded uncertainty U (95 %) and the MMD's part
    (2 u_mmd)."""
    rows = error_rows(result)
    head = ['error', 'axis', 'what', 'value', 'U (95%)', 'MMD part', 'unit', '']
    lines = []
    if markdown:
        lines.append('| ' + ' | '.join(head) + ' |')
        lines.append('|' + '---|' * len(head))
    else:
        lines.append(f'{head[0]:<8}{head[1]:>5}  {head[2]:<22}{head[3]:>9}{head[4]:>11}{head[5]:>10}  {head[6]}')
    for r in rows:
        flag = '' if r['determined'] else 'not determined'
        cells = [r['error'], r['axis'], r['kind'], _fmt(r['value']), _fmt(r['U']), _fmt(r['U_mmd']),
                 r['unit'], flag]
        if markdown:
            lines.append('| ' + ' | '.join(cells) + ' |')
        else:
            lines.append(f'{cells[0]:<8}{cells[1]:>5}  {cells[2]:<22}{cells[3]:>9}{cells[4]:>11}'
                         f'{cells[5]:>10}  {cells[6]:<3} {cells[7]}')
    return '\n'.join(lines)


def _target_table(a: AxisResult) -> str:
    ps, punit = a.position_scale
    head = [f'{a.axis} [{punit}]']
    for m in a.motions:
        _, unit = report_scale(m.unit)
        head += [f'{m.name} ↑ [{unit}]', f'{m.name} ↓', 'U']
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for i, q in enumerate(a.targets):
        cells = [f'{q * ps:.4g}']
        for m in a.motions:
            scale, _ = report_scale(m.unit)
            cells += [_fmt(m.up[i] * scale), _fmt(m.down[i] * scale), _fmt(m.U_mean[i] * scale)]
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def _location_parts(a: AxisResult, plate_u: float) -> list[str]:
    """What each location error's standard uncertainty is made of (report lines)."""
    span = math.degrees(a.targets[-1] - a.targets[0])
    lines = [f'Standard uncertainty of the location errors and its main parts (the run turned '
             f'over {span:.0f}°):', '',
             '| error | u | the MMD | upper plate position | component errors over this span | unit |',
             '|---|---|---|---|---|---|']
    for v in a.location:
        scale, unit = report_scale(v.unit)
        plate = plate_u if v.unit == 'm' else 0.0
        lines.append(f'| {v.name} | {_fmt(v.u * scale)} | {_fmt(v.u_mmd * scale)} | {_fmt(plate * scale)} | '
                     f'{_fmt(v.u_turn * scale)} | {unit} |')
    lines += ['', 'The upper plate\'s position relative to the controlled tool point (`mmd.'
              'upper_offset_uncertainty_um`) moves the measured axis line with it; component '
              'errors of the size stated (`--rotary-components`) can pass for location errors over '
              'a partial turn. A longer turn, a better-known plate position or a better-known '
              'table shrinks these parts; a better MMD model only the MMD\'s.']
    return lines


def markdown_report(result: MachineResult, figures: dict[str, str], files: list[str],
                    separation: str, volumetric: dict[str, dict[str, float]] | None = None) -> str:
    """The whole report: errors, what was not determined, how the MMD's own errors were kept
    apart, per axis per-target tables and figures, and the files written."""
    m = result.machine
    lines = [f'# Machine geometric errors: {m.name}', '',
             f'Machine description: `{m.source}` ({m.description}). Instrument: {result.instrument}. '
             f'Logs: {", ".join(f"`{p}`" for p in result.logs)}.', '',
             'Every error is of the tool relative to the workpiece in machine coordinates '
             '(ISO 230-1, ISO 230-7; signs in `msg_docs/machine.md`). U is the expanded '
             f'uncertainty for about 95 % (k from the degrees of freedom, at least 2; '
             f'{result.draws} Monte Carlo draws), "MMD part" 2 u of the MMD\'s own pose '
             'uncertainty alone.', '',
             '## Errors', '', error_table(result, markdown=True), '']
    nd = result.not_determined()
    lines += ['## Not determined by this session', '']
    lines += [f'- {t}' for t in nd] if nd else ['Everything listed above is determined.']
    lines += ['', '## How the machine\'s errors are kept apart from the MMD\'s', '', separation, '',
              f'Machine frame: {result.frame_source}.', '']
    if result.play:
        lines += ['The other table axes\' play (ISO 230-2 reversal B) during the rotary runs:', '']
        lines += [f'- {t}' for t in result.play] + ['']
    for name, a in result.axes.items():
        lines += [f'## Axis {name}', '',
                  f'Log `{a.log}` (axis values from {a.source}); {a.targets.size} targets, '
                  f'{a.n_cycles} bidirectional cycles'
                  + (f'; linear axes following: {", ".join(a.following)}' if a.following else '') + '.', '']
        if a.rotary:
            lines += [f'Location fit: residual {math.sqrt(max(a.fit_ratio, 0)):.2g}× what the inputs '
                      'explain (above 1: component errors the partial turn cannot separate from '
                      'location; the location uncertainty includes them).', '']
            lines += _location_parts(a, result.machine.upper_offset_uncertainty) + ['']
        lines += [_target_table(a), '']
        for caption, fname in figures.items():
            if caption.startswith(f'{name} axis'):
                lines += [f'![{caption}]({fname})', '']
    vol = {k: v for k, v in figures.items() if k.startswith('Volumetric')}
    if vol or volumetric:
        lines += ['## Volumetric error', '',
                  'The tool tip (the functional point) against the workpiece, predicted by the '
                  'kinematic model with every identified error over the measured ranges '
                  '(`mmd machine volumetric` for another tool length):', '']
        for key, s in (volumetric or {}).items():
            lines.append(f'- {key}: {s["points"]} points, max {s["max_um"]:.2f} µm, RMS {s["rms_um"]:.2f} µm')
        lines.append('')
        for caption, fname in vol.items():
            lines += [f'![{caption}]({fname})', '']
    if files:
        lines += ['## Files', ''] + [f'- `{f}`' for f in files] + ['']
    return '\n'.join(lines)
