"""The report of an analysis: ``report.md`` with PNG figures, ``analysis.json`` with the numbers,
and ``model.yaml`` when the model was extended. Units of the report: µm and arc-seconds."""

from __future__ import annotations

import math
from pathlib import Path

from mmd_ros.analysis.identify import Analysis, ComponentError, Found, RunSummary
from mmd_ros.core import jsonio
from mmd_ros.core.jsonio import finite_json  # noqa: F401  (re-exported for older callers)

__all__ = ['finite_json', 'format_summary', 'write_report']

_UNIT = {'um': 'µm', 'arcsec': '″'}


def _u(unit: str) -> str:
    return _UNIT.get(unit, unit)


def _num(v: float | None, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return '–'
    return f'{v:.{digits}g}'


def _stats_table(before: list[ComponentError], after: list[ComponentError] | None,
                 predicted: list[ComponentError] | None = None) -> list[str]:
    if after is None:
        lines = ['| component | unit | RMS | max | mean |', '|---|---|---|---|---|']
        lines += [f'| {s.name} | {_u(s.unit)} | {_num(s.rms)} | {_num(s.max_abs)} | {_num(s.mean)} |'
                  for s in before]
        return lines
    head = '| component | unit | RMS before | max before | RMS after | max after |'
    sep = '|---|---|---|---|---|---|'
    if predicted:
        head += ' RMS predicted (linear) |'
        sep += '---|'
    lines = [head, sep]
    amap = {s.name: s for s in after}
    pmap = {s.name: s for s in predicted or []}
    for s in before:
        a = amap.get(s.name)
        row = (f'| {s.name} | {_u(s.unit)} | {_num(s.rms)} | {_num(s.max_abs)} | '
               f'{_num(a.rms) if a else "–"} | {_num(a.max_abs) if a else "–"} |')
        if predicted:
            p = pmap.get(s.name)
            row += f' {_num(p.rms) if p else "–"} |'
        lines.append(row)
    return lines


def _param_table(f: Found) -> list[str]:
    lines = ['| parameter | value | 95 % interval (±) | unit |', '|---|---|---|---|']
    rows = f.parameter_rows()
    shown = [r for r in rows if abs(r['value']) > 0 or r['identifiable']]
    if len(shown) > 24:
        shown = sorted(shown, key=lambda r: -abs(r['value']))[:24]
        lines.insert(0, f'(the 24 largest of {len(rows)} parameters; all are in analysis.json)\n')
    for r in shown:
        ci = '–' if r['ci95'] is None else _num(r['ci95'])
        lines.append(f'| {r["name"]} | {_num(r["value"], 4)} | {ci} | {r["unit"]} |')
    return lines


def write_report(a: Analysis, out_dir: str | Path, *, figures: bool = True) -> dict[str, Path]:
    """Write report.md, analysis.json, the figures and (if extended) model.yaml into
    ``out_dir``; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    figs: dict[str, str] = {}
    if figures:
        from mmd_ros.analysis.plots import analysis_figures
        figs = analysis_figures(a, out)
    if a.model is not None:
        written['model'] = a.model.save(out / 'model.yaml')
    data = a.as_dict()
    data['model_file'] = str(written['model']) if 'model' in written else None
    data['figures'] = figs
    (out / 'analysis.json').write_text(jsonio.dumps(data), encoding='utf-8')
    written['json'] = out / 'analysis.json'
    (out / 'report.md').write_text(_markdown(a, figs, written.get('model')), encoding='utf-8')
    written['report'] = out / 'report.md'
    return written


def _uncertainty_section(a: Analysis) -> list[str]:
    """What the written model claims of its own uncertainty (``uncertainty.fit``), per bar."""
    fit = None if a.model is None else a.model.uncertainty.fit
    if fit is None:
        return []
    L = ['## 5. What the model claims of its own uncertainty', '',
         f'Residual measured on {fit.record.get("residual_from", "the analysed logs")}'
         + (f'; it stands for {", ".join(fit.replaces)} where the fit saw the bars'
            if fit.replaces else '; the calibration-derived sources stay'
            + (f', scaled by {fit.systematic_scale:.3g}' if fit.systematic_scale != 1.0 else ''))
         + '. The pose covariance adds these per bar (`msg_docs/frames.md`).', '']
    common = fit.record.get('common_mode_nm')
    if common:
        L += [f'The references see only some pose components, and none of them an error the six '
              f'bars share (its visibility {fit.record.get("common_mode_visibility", 0):.2g} of an '
              f'average direction\'s): the common mode is claimed at {common:.3g} nm, the whole '
              'excess the components showed (a rule, not a measurement).', '']
    unseen = fit.record.get('unseen_constant_nm')
    if unseen is not None:
        L += ['The reference was zeroed: the residual holds, per bar, what the runs left unknown of '
              'a constant error (a zeroed reference reads its mean as an offset), '
              f'{fit.record.get("unseen_common_mode_nm", "?")} nm along the common mode of the six '
              'bars (which the pose\'s variation cannot show: temperature, gravity, the reference '
              f'bar\'s zero) and {fit.record.get("unseen_differential_nm", "?")} nm RMS in the '
              'directions between them.'
              + _shape_text(fit.record.get('shape_constant_nm'), fit.record.get('shape_factor')),
              '']
    L += ['| bar | residual σ [nm] | of it, an unknown constant σ [nm] '
          '| where its fitted lengths end inside a CDF segment, σ [nm] |', '|---|---|---|---|']
    for i in range(6):
        flank = math.sqrt(max(float(fit.flank_m2[i]), 0.0)) * 1e9
        L.append(f'| bar{i + 1} | {math.sqrt(max(float(fit.residual_m2[i, i]), 0.0)) * 1e9:.1f} | '
                 + (f'{float(unseen[i]):.1f} | ' if unseen is not None else '– | ')
                 + (f'{flank:.1f} |' if flank > 0 else '– |'))
    widths = fit.record.get('residual_profile_width_mm')
    if fit.profile is not None and widths:
        read = ', '.join(f'bar{i + 1} {w:g} mm' for i, w in enumerate(widths) if w is not None)
        L += ['', 'The residual depended on where along a bar it was read: its claim follows it '
              f'there (`uncertainty.fit.profile`, read with a kernel of {read}; the other bars '
              'alike at every length).']
    return L + ['']


def _shape_text(shape_nm: list[float] | None, factor: list[float] | None = None) -> str:
    """What the section says of the calibration's length-shaped errors between the bars, and
    of the bars whose error held more of that shape than the calibration describes."""
    if not shape_nm:
        return ''
    rms = math.sqrt(sum(v * v for v in shape_nm) / len(shape_nm))
    text = (' Between the bars, the calibration\'s length-shaped errors (its points\', the '
            'interpolation between them) were read from how each bar\'s residual varied with its '
            f'length: {rms:.1f} nm RMS per bar left unknown of their mean.')
    wide = [(i, a) for i, a in enumerate(factor or []) if a > 1.0]
    if wide:
        text += (' ' + ', '.join(f'bar{i + 1} ({math.sqrt(a):.1f} ×)' for i, a in wide)
                 + ' held more of that shape than the calibration describes (σ times the factor '
                 'given): no description ties its mean to its variation, and the claim adds that '
                 'share of its spread for where a new run dwells (a length term or a new '
                 'calibration would remove it).')
    return text


def _markdown(a: Analysis, figs: dict[str, str], model_path: Path | None) -> str:
    o = a.obs
    L: list[str] = ['# Closing the loop: residual, effect, error before and after', '']
    L += [f'Log: `{a.log}`  ', f'Reference: {o.description}'
          + (' (a constant offset per component removed: the instrument is zeroed)' if o.datum else '') + '  ',
          f'Samples: {a.times_s.size} over {a.times_s[-1]:.1f} s; {a.split.train_idx.size} for fitting, '
          f'{a.split.test_idx.size} held out ({a.split.n_blocks} time blocks, one of each pair '
          'held out)' + (f'; {_thinning(a)}' if a.every > 1 else ''), '']
    for run in a.runs:
        if run.log_problem:
            L += [f'**`{run.name}` was not read whole:** {run.log_problem["message"]}', '']
    L += ['## Conclusion', '', a.conclusion, '']
    L += ['## Validation', '', f'{a.validation[0].upper()}{a.validation[1:]}.', '']
    L += _runs_table(a) + ['']
    if model_path is not None:
        L += [f'Extended model: `{model_path.name}` (`mmd process --model {model_path.name}`, or the '
              'compensation node\'s `model_file` parameter).', '']
    L += ['## 1. Residual of the current model (held-out blocks)', '']
    for text in a.stated:
        L += [f'Started from {text}: the figures below include it (the model as given: '
              f'{_fmt(a.runs[0].given)}).', '']
    floor = ', '.join(f'{n} {f * s:.3g} {_u(u)}' for n, f, s, u in zip(o.names, a.floor, o.to_report, o.units))
    L += [f'Noise floor (encoder quantisation propagated, and the sample-to-sample noise): {floor}.', '']
    L += _stats_table(a.stats_before, None) + ['']
    if a.per_bar_before:
        L += ['Per bar (the pose residual mapped to bar lengths, J · Δp):', '',
              '| bar | RMS [µm] | max [µm] |', '|---|---|---|']
        L += [f'| {s.name} | {_num(s.rms)} | {_num(s.max_abs)} |' for s in a.per_bar_before]
        L += ['']
    L += ['Structure: share of the residual variance that bin means of each feature explain '
          '(R², held-out samples):', '']
    L += [f'- {name}: {r2:.2f}' for name, r2 in a.structure_before[:8]] + ['']
    L += ['## 2. Effects tested', '',
          'Each effect is fitted on the training blocks and judged on the held-out blocks. '
          'Added when the held-out RMS falls by at least '
          f'{100 * a.options.min_gain:g} % and {a.options.min_floor_gain:g} of the noise floor, '
          f'consistently over the held-out blocks (t ≥ {a.options.min_t:g}), and the held-out '
          f'information criterion falls by at least {a.options.min_delta_ic:g}.', '']
    for k, step in enumerate(a.steps):
        L += [f'### Step {k + 1}', '',
              '| effect | setting | identifiable / parameters | held-out RMS ratio | ΔIC | t | verdict |',
              '|---|---|---|---|---|---|---|']
        for c in step:
            L.append(f'| {c.effect} | {c.hyper_label or "–"} | {c.n_identifiable} / {c.n_params} | '
                     f'{_num(c.rms_ratio)} | {_num(c.delta_ic, 4)} | {_num(c.t_stat)} | {c.verdict} |')
        notes = [c for c in step if c.unidentifiable or c.note]
        if notes:
            L += ['', 'Not identifiable from this reference and run (reported, not fitted):', '']
            for c in notes:
                items = ([c.note] if c.note else []) + [x for x in c.unidentifiable if 'not exercised' not in x]
                n_lost = sum('not exercised' in x for x in c.unidentifiable)
                if n_lost:
                    items.insert(0, f'{n_lost} parameter{"s" if n_lost > 1 else ""} not exercised')
                L.append(f'- {c.effect}: ' + '; '.join(items[:6]))
        L.append('')
    if a.not_applicable:
        L += ['Not applicable: ' + '; '.join(f'{k} ({v})' for k, v in a.not_applicable.items()), '']
    L += ['## 3. Effects found', '']
    if not a.found and a.uncertainty_only:
        L += [f'None. But {a.uncertainty_only}: the model written keeps its terms and carries it '
              'as an uncertainty only (`uncertainty.fit`), for the pose covariance to cover it.', '']
    elif not a.found:
        L += ['None: the model is unchanged.', '']
    for f in a.found:
        setting = f', {f.hyper_label}' if f.hyper_label else ''
        L += [f'### {f.title} (`{f.effect}`, model term `{f.term_type}`{setting})', '']
        if math.isfinite(f.explained):
            L.append(f'Explains {100 * f.explained:.0f} % of the held-out residual variance.  ')
        L += [f'- {text}' for text in f.interpretation] + ['']
        L += _param_table(f) + ['']
    for f in a.not_claimed:
        L += [f'Not claimed: {f.title}: {f.reason}.', '']
    if a.unchecked:
        L += ['### Found but not written', '',
              'These explain part of the residual, but what they would do to the pose components '
              'no reference saw is not determined by these runs (or the pipeline with them makes '
              'a component worse). They stay in the fit (so that they do not bend the others) and '
              'are left out of the model; `--accept-unchecked` writes them.', '']
        for f in a.unchecked:
            setting = f', {f.hyper_label}' if f.hyper_label else ''
            L += [f'- **{f.title}** (`{f.effect}`{setting}): {f.reason}.']
            L += [f'  - {u.message()}' for u in f.unchecked[:6]]
        L += ['']
    L += ['## 4. Error before and after (held-out blocks, pipeline re-run with the extended model)', '']
    L += _stats_table(a.stats_before, a.stats_after or [], a.stats_predicted) + ['']
    if a.per_bar_before and a.per_bar_after:
        L += ['| bar | RMS before [µm] | RMS after [µm] |', '|---|---|---|']
        amap = {s.name: s for s in a.per_bar_after}
        L += [f'| {s.name} | {_num(s.rms)} | {_num(amap[s.name].rms)} |' for s in a.per_bar_before]
        L += ['']
    if a.at_floor:
        L += ['What remains is at the noise floor.', '']
    else:
        L += ['What remains is above the noise floor; it follows:', '']
        L += [f'- {name}: R² {r2:.2f}' for name, r2 in a.structure_after[:6]] + ['']
    L += _uncertainty_section(a)
    if figs:
        L += ['## Figures', '']
        for caption, name in figs.items():
            L += [f'### {caption}', '', f'![{caption}]({name})', '']
    L += [f'Analysis took {a.seconds:.1f} s.', '']
    return '\n'.join(L)


def _fmt(stats: list[ComponentError] | None) -> str:
    if not stats:
        return '–'
    return ', '.join(f'{s.name} {s.rms:.3g} {_u(s.unit)}' for s in stats)


def in_range_text(r: RunSummary) -> str:
    """The leave-one-run-out figure on the samples within the bar lengths the other runs
    covered, when some of the run lies outside them ('' otherwise)."""
    share = r.loro_in_range_share
    if share is None or share >= 1.0:
        return ''
    if not r.loro_in_range:
        return '; no sample lies within the bar lengths the other runs covered'
    return (f'; {100 * (1 - share):.0f} % of its samples lie outside the bar lengths the other '
            f'runs covered (where their model is not validated), within them: {_fmt(r.loro_in_range)}')



def _runs_table(a: Analysis) -> list[str]:
    """Per log: reference, noise floor, RMS before and after (held-out blocks, and each log
    predicted by the model fitted on the others)."""
    lines = ['| log | reference | noise floor | held-out blocks: before → after | '
             'leave-one-run-out: before → after |', '|---|---|---|---|---|']
    for r in a.runs:
        floor = ', '.join(f'{n} {v:.2g} {_u(u)}' for (n, v), u in zip(r.floor.items(), r.units))
        loro = (f'{_fmt(r.loro_before)} → {_fmt(r.loro_after)}' if r.loro_before is not None
                else '– (one log)')
        loro += in_range_text(r)
        if r.loro_note:
            loro += f' ({r.loro_note})'
        lines.append(f'| {Path(r.name).name} | {r.reference} | {floor} | {_fmt(r.before)} → '
                     f'{_fmt(r.after)} | {loro} |')
    return lines


def _thinning(a: Analysis) -> str:
    """How many of the logs' samples a long session's analysis read (:attr:`Analysis.every`)."""
    return (f'analysed one sample in {a.every} of the logs\' {a.recorded_samples} (at most '
            f'{a.options.max_log_samples} held: --max-log-samples)')


def format_summary(a: Analysis) -> str:
    """A few lines for the terminal."""
    lines = [f'residual of the current model ({a.obs.description}), held-out RMS: '
             + ', '.join(f'{s.name} {s.rms:.3g} {_u(s.unit)}' for s in a.stats_before)]
    lines.append(f'validation: {a.validation}')
    if a.every > 1:
        lines.append(_thinning(a))
    for text in a.stated:
        lines.append(f'started from {text} (the figures before include it)')
    for r in a.runs:
        if r.loro_before is not None:
            lines.append(f'  {Path(r.name).name}: leave-one-run-out {_fmt(r.loro_before)} → {_fmt(r.loro_after)}'
                         + in_range_text(r))
    for f in a.found:
        lines.append(f'found {f.effect} ({f.title}{", " + f.hyper_label if f.hyper_label else ""}): '
                     + '; '.join(f.interpretation))
    for f in a.not_claimed:
        lines.append(f'not claimed {f.effect}: {f.reason}')
    for f in a.unchecked:
        lines.append(f'not written {f.effect}: {f.reason}')
    if a.stats_after:
        lines.append('after, held-out RMS: ' + ', '.join(f'{s.name} {s.rms:.3g} {_u(s.unit)}' for s in a.stats_after))
    lines.append(a.conclusion)
    return '\n'.join(lines)
