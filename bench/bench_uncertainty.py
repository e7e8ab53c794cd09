"""How well the pose covariance covers the twin's true pose (issue 10, section 2).

For each case, several independent calibrations of the twin (seeds 1.., calibrated 211 s apart
on the room's temperature course, so that each sees another draw of every systematic error) run
a scenario; the pipeline's poses and covariances are compared with the twin's true pose (not its
reference instrument, which has noise of its own), each sample's time counted from its
calibration's, as a log of the twin states them (the readings' drift since then). Printed per
case: predicted / observed sigma per axis (x y z roll pitch yaw; observed = RMS of the error,
the twin's pose is absolute), the share of samples in the 95 % ellipsoid (Mahalanobis distance^2
<= chi^2_6(0.95)) pooled and per run, and in the budget's own 95 % region (the same ellipsoid
sized by its sources' forms, :func:`~mmd_ros.core.uncertainty.region_quantile`), their 95 %
intervals over the runs (the runs drawn again with replacement: a run's samples share one draw
of its calibration's constant error, so with 24 realistic runs a coverage near 95 % is known to
about +-4 %), each run's mean bar-length error along the bars' common mode over the sigma
claimed along it (what a zeroed reference cannot see): a check one way only, beyond +-2 or so a
constant the claim lacks; the claim's per-sample parts (quantisation, read noise) average out of
a run's mean, so a true claim gives less than 1 in RMS, by how much they weigh), and a JSON
line.

Usage: ``python bench/bench_uncertainty.py [--cases ideal,noeffect,realistic,realistic_sagspread]
[--scenario random|iso_y|rotary|thermal] [--runs 6] [--seconds 8] [--after] [--datum none|offset]
[--approaches 2] [--no-stated-sag] [--session] [--later-h 0] [--build 0]``. ``--build N`` instead
times the construction of a realistic calibration's budget N times each way, its interpolation fit made
anew (the kept fits cleared) and kept from the first (every pipeline and every trial budget of
an analysis builds one): medians and their ratio, measured in the same run. ``--after`` first runs
``mmd analyze`` (full pose reference, absolute, or zeroed with ``--datum offset``), started from
the bars' stated gravity sag unless ``--no-stated-sag``, on a 60 s random run of each twin and
judges that twin's extended model on a new run of it, also apart where every bar lies inside
the lengths the fit saw and where one does not, and apart those inside with a bar where its
fitted lengths end inside a CDF segment (``LengthBudget.flank``), each of those with every
run's coverage there (a pooled figure hides one twin's miss among others' surplus).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from scipy.stats import chi2

from mmd_ros.core.accuracy import pose_error
from mmd_ros.core.device import find_config, load_device
from mmd_ros.core.model import Model
from mmd_ros.core.pipeline import Pipeline
from mmd_ros.core.uncertainty import region_quantile
from mmd_ros.core.validity import Validity
from mmd_ros.twin import Effects, TwinDevice, make_scenario
from mmd_ros.twin.recording import EPOCH_S, ambient_profile, run_log

LIMIT = chi2.ppf(0.95, 6)
BOOTSTRAP = 2000       # resamples of the runs for the intervals
CASES = {
    'ideal': ('ideal', (), 'section_4_1'),
    'noeffect': ('ideal', ('read_noise_m=0',), 'constant:20'),
    'realistic': ('realistic', (), 'section_4_1'),
    'realistic_noskew': ('realistic', ('sampling_skew_s=0',), 'section_4_1'),
    'realistic_nosag': ('realistic', ('gravity_sag_m=0',), 'section_4_1'),
    # each twin's bars one sag drawn about the figure its description states, +- 15 %
    'realistic_sagspread': ('realistic', ('gravity_sag_spread=0.15',), 'section_4_1'),
}
SCENARIOS = {   # name: (scenario, parameters, sample rate)
    'random': ('random_motion', ('duration_s={seconds}', 'seed={k}'), None),
    'iso_y': ('iso_linear', ('axis=y', 'n_targets=6', 'n_cycles=2'), None),
    'rotary': ('iso_rotary', ('axis=psi', 'n_targets=6', 'n_cycles=2'), None),
    'thermal': ('random_motion', ('duration_s=7200', 'dwell_s=2', 'seed={k}'), 1.0),
}


def judge(errors: list[np.ndarray], covs: list[np.ndarray], tails: list[np.ndarray | None]
          ) -> dict:
    """Ratios and coverage pooled over the runs, and their 95 % intervals over the runs: the
    runs drawn again with replacement (a run's samples share its calibration's constant error,
    so the runs, not the samples, are the independent draws). Coverage of the ellipsoid a
    Gaussian's chi^2 sizes, and of the region the budget's sources size (``region``:
    :func:`region_quantile` of the pipeline's ``tails``)."""
    n = np.array([e.shape[0] for e in errors], dtype=np.float64)
    pred2 = np.array([np.sum(np.diagonal(c, axis1=1, axis2=2), axis=0) for c in covs])
    obs2 = np.array([np.sum(e * e, axis=0) for e in errors])

    d2 = [np.einsum('ni,ni->n', e, np.linalg.solve(c, e[:, :, None])[:, :, 0])
          for e, c in zip(errors, covs)]
    hits = np.array([np.sum(d <= LIMIT) for d in d2], dtype=np.float64)
    region = (hits if tails[0] is None else   # (the bars' lengths: no region of their own)
              np.array([np.sum(d <= region_quantile(c, t)) for d, c, t in zip(d2, covs, tails)],
                       dtype=np.float64))
    pick = np.random.default_rng(0).integers(0, len(n), (BOOTSTRAP, len(n)))
    counts = np.stack([np.bincount(row, minlength=len(n)) for row in pick]).astype(np.float64)
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio_b = np.sqrt((counts @ pred2) / (counts @ obs2))
    cover_b = (counts @ hits) / (counts @ n)
    region_b = (counts @ region) / (counts @ n)

    def interval(v: np.ndarray) -> list:
        return np.round(np.nanpercentile(v, [2.5, 97.5], axis=0), 3).T.tolist()

    return {'ratio': np.round(np.sqrt(pred2.sum(0) / obs2.sum(0)), 3).tolist(),
            'coverage': round(float(hits.sum() / n.sum()), 4),
            'ratio_interval': interval(ratio_b), 'coverage_interval': interval(cover_b),
            'region': round(float(region.sum() / n.sum()), 4),
            'region_interval': interval(region_b),
            'coverage_per_run': [round(float(h / k), 4) for h, k in zip(hits, n)],
            'observed_um_urad': np.round(np.sqrt(obs2.sum(0) / n.sum()) * 1e6, 4).tolist(),
            'predicted_um_urad': np.round(np.sqrt(pred2.sum(0) / n.sum()) * 1e6, 4).tolist(),
            'samples': int(n.sum())}


def run_case(device, name: str, scenario: str, runs: int, seconds: float, after: bool,
             approaches: int = 2, datum: str = 'none', stated_sag: bool = True,
             lengths: bool = False, clock: str = 'shared', session: bool = False,
             later_h: float = 0.0, recalibrate_at: float | None = None) -> dict:
    preset, effect_params, ambient = CASES[name]
    kind, params, rate = SCENARIOS[scenario]
    room = ambient_profile(ambient)
    errors, covs, tails, notes, inside, flank = [], [], [], [], [], []
    common = []     # per run: the bars' mean error along their common mode, and its claim
    model = Model()
    for k in range(runs):
        twin = TwinDevice(device, Effects.preset(preset).with_assignments(effect_params), seed=k + 1)
        calibration = twin.calibrate(-211.0 * k, room, approaches=approaches, epoch_s=EPOCH_S)
        start = 600.0
        if after:
            # each twin's own extended model, judged on new motion of that twin
            model, found, start = (fit_session(twin, room, calibration, k, datum) if session
                                   else fit(twin, room, calibration, k, datum, stated_sag, clock))
            notes.append(found)
            if recalibrate_at is not None:
                # the device calibrated again after the fit: the model's calibration is another
                calibration = twin.calibrate(recalibrate_at, room, approaches=approaches,
                                             epoch_s=EPOCH_S)
                start = recalibrate_at + 600.0
        p = [v.format(seconds=seconds, k=k) for v in params]
        start += 3600.0 * later_h        # (the judged run hours after the fit or calibration)
        run = twin.simulate(make_scenario(kind, p), room, start_s=start, reference='pose6',
                            sample_rate_hz=rate)
        pipeline = Pipeline(twin.documented_device, calibration, model)
        res = pipeline.process(run.times_s, run.counts, with_covariance=True, tails_every=1,
                               with_length_covariance=True, epoch_s=EPOCH_S + start)
        ok = res.valid & np.all(np.isfinite(run.true_poses), axis=1)
        length_error = (res.compensated.lengths_m - run.true_lengths)[ok]
        common.append(common_mode(length_error, res.length_covariance[ok]))
        if lengths:   # the bars' lengths and their covariance against the twin's true ones
            errors.append(length_error)
            covs.append(res.length_covariance[ok])
            tails.append(None)
        else:
            errors.append(pose_error(res.poses, run.true_poses)[ok])
            covs.append(res.covariance[ok])
            tails.append(res.tails[ok])
        validity = Validity.from_model(model)
        cdf = res.compensated.cdf_lengths_m[ok]
        inside.append(np.ones(cdf.shape[0], dtype=bool) if validity is None else np.all(
            (cdf >= validity.bar_range_m[:, 0]) & (cdf <= validity.bar_range_m[:, 1]), axis=1))
        flank.append(inside[-1] & np.any(pipeline.budget.flank(cdf), axis=1))
    out = {'case': name, 'scenario': scenario, 'runs': runs, 'after_analysis': after,
           'calibration_approaches': approaches, 'judged': 'lengths' if lengths else 'pose',
           'later_h': later_h,
           **judge(errors, covs, tails),
           'common_mode_nm': [[round(m * 1e9, 1), round(c * 1e9, 1)] for m, c in common]}
    if notes:
        out['analysis'] = '; '.join(notes)
        out['datum'] = datum
        out['stated_sag'] = stated_sag
        out['reference_clock'] = clock
        out['session'] = session
        # every bar inside the lengths its model's fit saw, and the rest (judged apart); and of
        # the first, those with a bar where its fitted lengths end inside a CDF segment
        groups = (('inside_fit_range', inside, True), ('outside_fit_range', inside, False),
                  ('in_a_segment_s_flank', flank, True))
        for key, masks, want in groups:
            parts = [(k, (e[m == want], c[m == want], None if t is None else t[m == want]))
                     for k, (e, c, t, m) in enumerate(zip(errors, covs, tails, masks))]
            parts = [(k, p) for k, p in parts if p[0].shape[0]]
            if parts:
                r = judge(*(list(z) for z in zip(*(p for _, p in parts))))
                out[key] = {k: r[k] for k in ('ratio', 'coverage', 'ratio_interval',
                                              'coverage_interval', 'region', 'region_interval',
                                              'samples')}
                # (each run's coverage there and its samples, by the run's number)
                out[key]['runs'] = {str(k + 1): [c, p[0].shape[0]] for (k, p), c
                                    in zip(parts, r['coverage_per_run'])}
    return out


def common_mode(error: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """A run's mean bar-length error along the bars' common mode u = (1, ..., 1)/sqrt(6) (what
    a zeroed reference cannot see: temperature, the reference bar, a drift alike on all bars)
    and the sigma Sigma_d claims along it, RMS over the samples [m]."""
    u = np.full(6, 1.0 / np.sqrt(6.0))
    return float(np.mean(error @ u)), float(np.sqrt(np.mean(np.einsum('i,nij,j->n', u, cov, u))))


def fit(twin, room, calibration, k, datum: str = 'none', stated_sag: bool = True,
        clock: str = 'shared'):
    """mmd analyze on a 60 s random run with the full pose reference, absolute (``datum``
    'none') or zeroed (an offset per component removed, 'offset'),
    started from the bars' stated gravity sag unless ``stated_sag`` is False; the log saying
    that its reference runs on the MMD's clock (``clock`` 'shared', the twin's) or its own."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    run = twin.simulate(make_scenario('random_motion', ['duration_s=60', f'seed={100 + k}']), room,
                        start_s=600.0, reference='pose6')
    run.metadata['reference_clock'] = clock
    options = AnalysisOptions(datum=datum, stated_sag=stated_sag)
    result = analyze(run_log(twin, calibration, run, 600.0), options=options)
    found = '+'.join(f.effect for f in result.found) or 'nothing'
    return result.model or Model(), found, 700.0


#: A session of each twin for ``--session``: (name, scenario, parameters, reference); 200 Hz
SESSION = [('x', 'iso_linear', ['n_cycles=5', 'axis=x'], None),
           ('y', 'iso_linear', ['n_cycles=5', 'axis=y'], None),
           ('c', 'iso_rotary', ['n_cycles=5', 'axis=psi'], None),
           ('pose', 'random_motion', ['duration_s=60', 'seed={seed}'], 'pose6')]


def fit_session(twin, room, calibration, k, datum: str = 'none'):
    """mmd analyze on a session of the twin as ``make demo`` records one (x and y lasers, a C
    rotary calibrator, 60 s of 6-DOF motion, each on its own reference; leave-one-run-out),
    the references absolute (``datum`` 'none') or zeroed ('offset')."""
    from mmd_ros.analysis.identify import AnalysisOptions, analyze
    logs, start = [], 600.0
    for name, kind, params, reference in SESSION:
        run = twin.simulate(make_scenario(kind, [p.format(seed=100 + k) for p in params]), room,
                            start_s=start, reference=reference, sample_rate_hz=200.0)
        logs.append(run_log(twin, calibration, run, start, name=f'{name}.mcap'))
        start += 400.0
    result = analyze(logs, options=AnalysisOptions(datum=datum))
    found = '+'.join(f.effect for f in result.found) or 'nothing'
    return result.model or Model(), found, start


def spread(r: dict, what: str) -> str:
    """The 95 % intervals of a judgement's ratios and coverage, one line."""
    ratios = ' '.join(f'{a:.2f}-{b:.2f}' for a, b in r['ratio_interval'])
    lo, hi = r['coverage_interval']
    rlo, rhi = r['region_interval']
    return (f'    95 % intervals{" " + what if what else ""}: ratio {ratios}   ellipsoid '
            f'{100 * lo:.1f}-{100 * hi:.1f} %\n    the budget\'s own 95 % region '
            f'{100 * r["region"]:.1f} % ({100 * rlo:.1f}-{100 * rhi:.1f} %)')


def build_times(device, rounds: int) -> dict:
    """Median seconds to build a realistic calibration's LengthBudget with its interpolation
    fit made anew and kept, alternating, and their ratio."""
    from mmd_ros.core import uncertainty
    from mmd_ros.core.budget import LengthBudget
    twin = TwinDevice(device, Effects.preset('realistic'), seed=1)
    calibration = twin.calibrate(0.0, ambient_profile('section_4_1'), approaches=2)
    fresh, kept = [], []
    for _ in range(rounds):
        uncertainty._INTERPOLATION_FITS.clear()
        for out in (fresh, kept):
            t0 = time.perf_counter()
            LengthBudget(twin.documented_device, calibration, Model())
            out.append(time.perf_counter() - t0)
    f, k = float(np.median(fresh)), float(np.median(kept))
    return {'rounds': rounds, 'fit_anew_ms': round(f * 1e3, 2), 'fit_kept_ms': round(k * 1e3, 2),
            'ratio': round(f / k, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--cases', default='ideal,noeffect,realistic,realistic_noskew')
    parser.add_argument('--scenario', default='random', choices=sorted(SCENARIOS))
    parser.add_argument('--runs', type=int, default=6)
    parser.add_argument('--seconds', type=float, default=8.0)
    parser.add_argument('--after', action='store_true')
    parser.add_argument('--datum', default='none', choices=('none', 'offset'),
                        help='with --after: the fit\'s reference absolute (none, default) or zeroed '
                        '(offset, a laser or tracker zeroed at its start)')
    parser.add_argument('--approaches', type=int, default=2, choices=(1, 2),
                        help='the twin\'s calibration: 2 two-sided with the drift read (default), 1 '
                        'the paper\'s routine')
    parser.add_argument('--no-stated-sag', action='store_true', dest='no_stated_sag',
                        help='with --after: the analysis starts from the model as given, not from '
                        'the bars\' stated gravity sag')
    parser.add_argument('--reference-clock', default='shared', choices=('shared', 'own'),
                        dest='clock', help='with --after: the fitted log says its reference runs '
                        'on the MMD\'s clock (shared, the twin\'s) or its own (a lag is then '
                        'fitted beside the effects, and the skew\'s common delay is not)')
    parser.add_argument('--lengths', action='store_true',
                        help='judge the six bars\' length covariance against their true lengths '
                        '(what a log with reference bar lengths reports) instead of the pose')
    parser.add_argument('--session', action='store_true',
                        help='with --after: each twin\'s model fitted on a session as make demo '
                        'records one (x, y lasers, a C rotary run, 60 s of 6-DOF motion; '
                        'leave-one-run-out) instead of one 60 s 6-DOF run')
    parser.add_argument('--later-h', type=float, default=0.0, dest='later_h', metavar='H',
                        help='judge each twin on a run H hours later than by default (after its '
                        'calibration, or after the run --after fits): the room\'s course and the '
                        'readings\' drift in between')
    parser.add_argument('--recalibrate-at', type=float, default=None, dest='recalibrate_at',
                        metavar='S', help='with --after: calibrate each twin again at S s of the '
                        'room\'s day after its fit (the same routine) and judge it on a run '
                        '600 s later with its model, which names the first calibration')
    parser.add_argument('--build', type=int, default=0, metavar='N',
                        help='time a budget\'s construction N times, its interpolation fit anew '
                        'and kept (instead of the coverage cases)')
    args = parser.parse_args()
    device = load_device(find_config('mmd_prototype.yaml'))
    if args.build:
        r = build_times(device, args.build)
        print(f'budget construction, medians of {r["rounds"]}: interpolation fitted anew '
              f'{r["fit_anew_ms"]:.1f} ms, kept {r["fit_kept_ms"]:.1f} ms ({r["ratio"]:.1f} x)')
        print(json.dumps({'benchmark': 'uncertainty_budget_build', **r}))
        return
    results = []
    for name in args.cases.split(','):
        t0 = time.perf_counter()
        r = run_case(device, name, args.scenario, args.runs, args.seconds, args.after, args.approaches,
                     args.datum, not args.no_stated_sag, args.lengths, args.clock, args.session,
                     args.later_h, args.recalibrate_at)
        r['seconds'] = round(time.perf_counter() - t0, 1)
        results.append(r)
        print(f'{name:17s} {args.scenario:8s} ratio ' + ' '.join(f'{v:.2f}' for v in r['ratio'])
              + f'   ellipsoid {100 * r["coverage"]:.1f} % (runs '
              + ' '.join(f'{100 * v:.0f}' for v in r['coverage_per_run']) + ')'
              + (f'   [{r["analysis"]}]' if 'analysis' in r else ''), flush=True)
        print(spread(r, 'over the runs'))
        z = [m / c for m, c in r['common_mode_nm'] if c > 0]
        print('    the bars\' common mode, each run\'s mean error over its claimed sigma: '
              + ' '.join(f'{v:+.2f}' for v in z)
              + (f' (RMS {np.sqrt(np.mean(np.square(z))):.2f})' if z else ''))
        for key in ('inside_fit_range', 'outside_fit_range', 'in_a_segment_s_flank'):
            if key in r:
                part = r[key]
                runs = ' '.join(f'{k}: {100 * c:.0f} % of {n}'
                                for k, (c, n) in part['runs'].items())
                print(f'  {key:17s} ratio ' + ' '.join(f'{v:.2f}' for v in part['ratio'])
                      + f'   ellipsoid {100 * part["coverage"]:.1f} % ({part["samples"]} samples;'
                      f' runs {runs})')
                print(spread(r[key], ''))
    print(json.dumps({'benchmark': 'uncertainty', 'results': results}))


if __name__ == '__main__':
    main()
