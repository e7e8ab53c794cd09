"""What the model file of ``mmd analyze`` must carry about its own uncertainty.

A fit changes what the bar lengths' uncertainty budget (:mod:`mmd_ros.core.budget`) should
claim in two ways (``msg_docs/frames.md``):

- **fitted terms**: their parameters theta have a covariance Sigma_theta, and a term changes
  the lengths by S theta (its signature S, the same ``features`` the pipeline applies), so each
  sample gains S Sigma_theta S^T. Sigma_theta = V Lambda V^T; each principal direction
  sqrt(lambda_k) v_k is written as the model term(s) that apply it (their correction is
  c_k = S sqrt(lambda_k) v_k), and the pipeline adds sum_k c_k c_k^T per sample. The
  directions that carry least (at most 1 % of the mean trace together) are left out of the
  per-sample sum and enter, with all others, as their mean over the fit's samples
  (``mean_terms_nm2``, for a stage without counts). Parameters that belong to the fitted run
  (a drift's offset and rate, ``Effect.scope == 'run'``) are not among the model's terms, and
  on any other run the same drift would be an error no data checked: less what the model's
  terms, fitted again without it, took over of it (they apply that on every run), the bars'
  correction together is one more direction, and each bar's own, as far as it drifted apart
  from the others (:func:`_apart`), one more, its variance over the fitted run entering that
  bar's residual (another run may drift of its own); after a zeroed fit, which does not see
  where the bars' common drift started, the residual also holds that common mode as large as
  the drift's mean change over the fitted run;
- **the residual**: with a reference that determines every bar (a full pose, or bar lengths)
  the bar-length residual, J dp, has a covariance R, the reference's own variance (the log's
  ``reference_sigma``) taken out. With several logs it is each log's error under the model
  fitted on the others (leave-one-run-out): data the fit never saw; with one log, its
  held-out blocks. The budget keeps its per-sample sources (quantisation, read noise,
  reference bar, thermal, latch skew, fitted terms); what R holds beyond their mean over the
  same samples is the residual source (PSD part), and it replaces the calibration-derived
  systematic sources it measured (:data:`~mmd_ros.core.model.FIT_REPLACEABLE`) over the
  lengths the fit saw: the budget brings them back for a bar outside the model's
  ``validity.bar_range_mm``. Where a bar's residual depended on its length (a local defect of
  its scale), the part the references showed beyond the per-sample sources is claimed where
  along the bar it lay (:func:`_length_profile`). When the fit removed an offset per
  component (a zeroed reference: a log that says so, ``--datum offset``) the residual
  lacks the constant part of the error; what the runs leave unknown of a constant error per
  bar is claimed with it:
  a posterior whose prior is those sources (scaled by k, ``systematic_scale``, never below 1,
  so that they claim per observed component as much as the terms with free constants,
  ``Effect.free_mean``, corrected over the log: an error the calibration may not know of,
  whose mean over a log the reference does not see), with their length-shaped part (the
  points' errors, the interpolation between them: functions of a bar's length) conditioned
  on how each bar's residual varied with its length
  (:func:`_shape_constants`; the estimated mean shrunk by its noise, which the runs' halves
  show, :func:`_shape_noise`), and whose information is how the constant moves the pose as
  J^-1 varies over the runs, none for the common mode of the six bars
  (:func:`_unseen_constants`). A reference that sees only some pose components cannot
  tell the bars apart: the calibration-derived sources stay, scaled by the factor k that
  makes the observed components' predicted variance match what was observed, never below 1
  (what the reference did not see is not claimed better than before); when none of them sees
  the six bars' common mode (which moves z), it is claimed as large as the whole excess
  (:func:`_common_mode_visibility`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.polynomial import legendre
from numpy.typing import NDArray
from scipy.linalg import block_diag
from scipy.optimize import minimize_scalar
from scipy.stats import chi2

from mmd_ros.analysis.data import FitContext, Observation, Processed
from mmd_ros.core.budget import LengthBudget, Observed
from mmd_ros.core.kinematics import jacobian
from mmd_ros.core.model import (FIT_REPLACEABLE, PROFILE_POINTS, FitUncertainty, LengthProfile,
                                Model, ModelTerm, ModelUncertainty)
from mmd_ros.core.terms import limited_to_seen
from mmd_ros.core.uncertainty import hat_weights, pose_covariance
from mmd_ros.core.validity import Validity

__all__ = ['CLAIM_LEVEL', 'FittedEffect', 'MAX_DIRECTIONS', 'ResidualRun', 'base_budget',
           'beyond_claim', 'claimed_sigma', 'fit_uncertainty', 'fitted_effects',
           'measured_read_noise', 'with_fit_uncertainty']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Most principal directions of the fitted parameters evaluated per sample.
MAX_DIRECTIONS = 8
#: Share of the fitted terms' mean variance the per-sample directions must carry.
DIRECTION_SHARE = 0.99
#: Fewest samples of a bar in the flank of its fitted lengths to measure what is left there.
FLANK_SAMPLES = 50
#: The calibration's length-shaped sources: functions of each bar's length, zero-mean between
#: its points (the points' own errors, the interpolation between them, and the sub-divisional
#: error: the points' own, carried between them, and the live count's, whose period of
#: micrometres no run's mean keeps).
LENGTH_SHAPED = ('calibration_points', 'interpolation', 'subdivision')
#: Lengths per bar and run at which the shaped sources' mean is conditioned on its variation,
#: and at most over all runs (the conditional costs the cube of their sum).
SHAPE_POINTS = 200
SHAPE_POINTS_TOTAL = 1200
#: Samples each half of a run needs for the noise in the shape's estimated mean.
HALF_SAMPLES = 200
#: Consecutive blocks of a run whose means of the residual show how a run's mean moves.
DWELL_BLOCKS = 8


@dataclass
class FittedEffect:
    """One effect the written model applies, as :func:`fit_uncertainty` needs it: the effect,
    its setting, the covariance (P, P) of the parameters the model applies and their values
    (P,) [SI]."""

    effect: Any
    hyper: Any
    covariance: FloatArray
    theta: FloatArray | None = None
    #: a continuous setting one sigma away and the parameters that go with it (or None)
    shifted: tuple[Any, FloatArray] | None = None
    #: forms of the effect the data could not rule out (settings, with the same parameters)
    alternatives: list[Any] = field(default_factory=list)
    #: the parameters as fitted together with the run's own effects (a drift), where the
    #: model's were fitted again without them (None: the same)
    joint: FloatArray | None = None


@dataclass
class ResidualRun:
    """A log's residual after the fit: its context, the pipeline over it (the model it is
    judged with), the residual in its observation space (N, k) [m, rad] (NaN where not usable)
    and the samples to judge on."""

    ctx: FitContext
    after: Processed
    residual: FloatArray
    idx: IntArray


def _term_directions(ctx: FitContext, found: list[FittedEffect], idx: IntArray,
                     seen_m: FloatArray | None = None,
                     not_carried: list[tuple[FittedEffect, FloatArray, FloatArray]] | None = None
                     ) -> tuple[list[list[ModelTerm]], FloatArray, FloatArray, FloatArray]:
    """Principal directions of the fitted parameters as model terms (held beyond the lengths
    ``seen_m`` as the model's own terms are), the mean over the samples ``idx`` of
    S Sigma_theta S^T of all of them, (6, 6) [m^2], what another run may hold of the
    effects whose parameters belong to one run (``not_carried``, :func:`_not_carried` at
    ``idx``), (6, 6) [m^2] (below), and the mean of those
    directions that are not kept, (6, 6) [m^2]: a stage evaluates at most MAX_DIRECTIONS per
    sample, and what the others carry is claimed as their mean (the largest eight of 42 CDF
    point offsets carried 73 % of a C-axis fit's variance; which eight, among nearly equal
    ones, changed with a rounding, and so did the coverage of new motion, 92-94 %)."""
    candidates: list[tuple[float, list[ModelTerm], FloatArray]] = []
    mean_total = np.zeros((6, 6))
    for f in found:
        cov = f.covariance
        if cov is None or not np.any(cov):
            continue
        if f.effect.scope == 'run' and f.theta is not None:
            # the model does not apply a run's own terms (a drift): what another run holds of
            # them is claimed below, from their values; their covariance with the terms fitted
            # beside them is the terms' own, fitted again without them (a twin warmed 5 °C:
            # its drift's offsets, taken over by the CDF points, claimed 31 nm per bar again,
            # the rotations of new motion 1.6-1.8 times their error)
            continue
        w, v = np.linalg.eigh(0.5 * (cov + cov.T))
        keep = w > max(float(w.max()), 0.0) * 1e-12
        if not keep.any():
            continue
        dirs = v[:, keep] * np.sqrt(w[keep])                      # (P, r): one sigma each
        sig = f.effect.signature(ctx, f.hyper, idx)               # (n, 6, P)
        cols = sig @ dirs                                          # (n, 6, r)
        outer = np.einsum('nir,njr->rij', cols, cols) / max(idx.size, 1)   # each mean c c^T
        mean_total += outer.sum(axis=0)
        size = np.mean(np.sum(cols * cols, axis=1), axis=0)       # mean |c_k|^2
        for k in range(dirs.shape[1]):
            candidates.append((float(size[k]), limited_to_seen(
                f.effect.make_terms(ctx, f.hyper, dirs[:, k]), seen_m), outer[k]))
    candidates.sort(key=lambda c: -c[0])
    total = sum(c[0] for c in candidates)
    chosen: list[list[ModelTerm]] = []
    for f in found:
        if f.shifted is None or f.theta is None:
            continue
        # the setting one sigma away, with the parameters that go with it: one more direction,
        # always kept (not linear in the setting: as terms, the shifted ones minus these)
        terms, mean = _change_to(ctx, f, *f.shifted, idx, seen_m)
        chosen.append(terms)
        mean_total += mean
    run_own = np.zeros((6, 6))
    for f, sig, left in not_carried or []:
        # parameters that belong to the fitted run (a drift: an offset at its start and a rate)
        # are not in the model's terms; on any other run such a drift is an error no data
        # checked: each bar's correction is claimed as uncertain as it is large, bar by bar (a
        # reading that settled over each run's first seconds, fitted as a drift on one run,
        # left 7.7 % of another run's samples in the ellipsoid), as far as it drifted apart
        # from the other bars (what they drifted together is claimed together, below: bar by
        # bar as well, a settling of nearly the same size on every bar was claimed 4.8-7.1
        # times its error in x, y and the rotations on new motion), less what the model's
        # terms took over of it (:func:`_not_carried`)
        touches = np.any(sig != 0.0, axis=0)                                   # (6, P)
        own = _own_parameters(touches)
        apart = _apart(left, own)
        for bar, mine in enumerate(own):
            theta = np.where(mine, apart, 0.0)
            if not np.any(theta):
                continue
            own = sig @ theta                                                  # (n, 6)
            mean_total += own.T @ own / max(idx.size, 1)
            chosen.append(limited_to_seen(f.effect.make_terms(ctx, f.hyper, theta), seen_m))
            # and another run may have a drift of its own, as large as this one varied
            run_own[bar, bar] += float(np.var(own[:, bar]))
        # and the bars together, as they drifted: a reading that settles alike on every bar
        # after handling moves the common mode, which bar by bar claims sqrt(6) times too
        # little of (z on new motion 0.42 times its error; the drift, applied, had cancelled
        # the new run's own until it was left out of the model's terms)
        whole = sig @ left
        mean_total += whole.T @ whole / max(idx.size, 1)
        chosen.append(limited_to_seen(f.effect.make_terms(ctx, f.hyper, left), seen_m))
        if ctx.obs.datum:
            # a zeroed reference does not see the bars' common offset, so not where their
            # drift started: another run may start as far from where it ends as this one
            # drifted over its course (a settling alike on every bar, fitted zeroed: 55 % of
            # new motion in the ellipsoid, z claimed 0.6 times its error)
            ends = f.effect.signature(ctx, f.hyper, np.array([0, ctx.times_s.size - 1]))
            common = float(np.mean((ends[1] - ends[0]) @ f.theta)) * np.ones(6)
            run_own += np.outer(common, common)
    forced = len(chosen)
    carried = 0.0
    rest = np.zeros((6, 6))
    for size, terms, outer in candidates:
        if len(chosen) - forced >= MAX_DIRECTIONS or (total > 0 and carried >= DIRECTION_SHARE * total):
            rest += outer
            continue
        chosen.append(terms)
        carried += size
    return chosen, mean_total, run_own, rest


def _not_carried(ctx: FitContext, found: list[FittedEffect], idx: IntArray
                 ) -> list[tuple[FittedEffect, FloatArray, FloatArray]]:
    """Each fitted effect whose parameters belong to the run (a drift), with its signature
    (n, 6, P) at the samples ``idx`` and what of its parameters the model's terms do not carry
    (P,): its parameters less what the terms, fitted again without it, took over of its
    correction. Those apply it on every run and their own uncertainty claims it (a settling
    of a few nm whose offsets, 0.14-0.85 µm, stood in for the CDF points' constants: the
    points refitted without it took them, and new motion was claimed 7.8-17.4 times its error
    while they were claimed again)."""
    taken = np.zeros((idx.size, 6))
    for f in found:
        if f.joint is not None and f.theta is not None:
            taken += f.effect.signature(ctx, f.hyper, idx) @ (f.theta - f.joint)
    out = []
    for f in found:
        if f.effect.scope != 'run' or f.theta is None or not np.any(f.theta):
            continue
        sig = f.effect.signature(ctx, f.hyper, idx)                            # (n, 6, P)
        held = np.linalg.lstsq(sig.reshape(-1, sig.shape[2]), taken.reshape(-1), rcond=None)[0]
        out.append((f, sig, f.theta - held))
    return out


def _constants_carried(not_carried: list[tuple[FittedEffect, FloatArray, FloatArray]]) -> bool:
    """Whether the model's terms carry the constants the run's own effects took: of each such
    effect (a drift; ``not_carried``, :func:`_not_carried`), what they do not carry moves no
    bar's mean over its samples by more than twice its own standard deviation there. Then the
    terms hold each bar's error as it was over the fitted runs, the thermal mismatch of their
    temperature among it (:func:`_thermal_state`)."""
    for f, sig, left in not_carried:
        mean = sig.mean(axis=0)                                                # (6, P)
        var = np.einsum('ip,pq,iq->i', mean, f.covariance, mean)
        if np.any(np.abs(mean @ left) > 2.0 * np.sqrt(np.maximum(var, 0.0))):
            return False
    return True


def _own_parameters(touches: NDArray[np.bool_]) -> list[NDArray[np.bool_]]:
    """Per bar, which parameters touch that bar alone, (P,) each (``touches``: (6, P), which
    parameters' columns are non-zero on each bar)."""
    return [touches[bar] & ~np.any(np.delete(touches, bar, axis=0), axis=0)
            for bar in range(touches.shape[0])]


def _apart(theta: FloatArray, own: list[NDArray[np.bool_]]) -> FloatArray:
    """``theta`` less, at each bar's own parameters (:func:`_own_parameters`), their mean over
    the bars (each bar's k-th own parameter with the others' k-th): what each bar did apart
    from the others. ``theta`` as it is when the bars' own parameters do not line up (not as
    many each)."""
    index = [np.flatnonzero(mine) for mine in own]
    if len({i.size for i in index}) != 1 or index[0].size == 0:
        return theta
    rows = np.array(index)                                                 # (6, k)
    out = theta.copy()
    out[rows] = theta[rows] - theta[rows].mean(axis=0)
    return out


def _change_to(ctx: FitContext, f: FittedEffect, hyper: Any, theta: FloatArray, idx: IntArray,
               seen_m: FloatArray | None) -> tuple[list[ModelTerm], FloatArray]:
    """The change from the fitted effect to the state (``hyper``, ``theta``), as terms (the
    state's minus the fitted ones) and its mean c c^T over the samples ``idx``, (6, 6) [m^2]."""
    cols = f.effect.signature(ctx, hyper, idx) @ theta - f.effect.signature(ctx, f.hyper, idx) @ f.theta
    terms = limited_to_seen(f.effect.make_terms(ctx, hyper, theta)
                            + f.effect.make_terms(ctx, f.hyper, -f.theta), seen_m)
    return terms, cols.T @ cols / max(idx.size, 1)


def _psd(matrix: FloatArray) -> FloatArray:
    w, v = np.linalg.eigh(0.5 * (matrix + matrix.T))
    return (v * np.maximum(w, 0.0)) @ v.T


#: Samples at most over which the budget's predicted mean covariance is taken (evenly spread
#: over a run: the mean of a smooth function of the device's state, not a statistic of noise).
PREDICTED_SAMPLES = 50_000


def _spread(idx: IntArray, most: int = PREDICTED_SAMPLES) -> IntArray:
    """At most ``most`` of the sample indexes ``idx``, evenly spread over them."""
    return idx[::max(1, -(-idx.size // most))]


def _trial(model: Model, fit: FitUncertainty, validity: bool = False) -> Model:
    """``model`` with the uncertainty section ``fit`` (and its validity record, or none)."""
    previous = model.uncertainty
    return Model(model.thermal_mode, model.plate_expansion, None, list(model.terms),
                 dict(model.extra) if validity else {}, model.source,
                 ModelUncertainty(previous.thermal_mismatch_fraction, previous.read_noise_m, fit))


def _predicted(run: ResidualRun, model: Model, fit: FitUncertainty, idx: IntArray
               ) -> tuple[FloatArray, FloatArray]:
    """The budget's sources at ``idx`` of a run under the fitted model, (n, 6, 6) each: those
    it keeps after a fit and those a measured residual may replace."""
    return _sources(run.ctx, run.after, _trial(model, fit), idx)


def _flank_excess(parts: list[tuple[ResidualRun, IntArray, FloatArray, FloatArray]],
                  model: Model, fit: FitUncertainty) -> FloatArray:
    """Per bar, the mean square of the bar-length residual where the bar lay within the lengths
    the fit saw but in a CDF segment whose middle it did not see (``LengthBudget.flank``),
    beyond what the written model claims there (its residual included), (6,) [m^2]; 0 for a
    bar with fewer than :data:`FLANK_SAMPLES` such samples. ``parts``: each run, its samples,
    their bar-length residual J dp (n, 6) [m] and the reference's own variance in it (n, 6).

    The end of what a bar's fit saw is where its length term is least determined (a bar there
    always arrives from one side, and its friction state and scale error cannot be told
    apart); a residual averaged over every length does not show what is left there."""
    trial = _trial(model, fit, validity=True)
    total, count = np.zeros(6), np.zeros(6)
    for run, idx, dd, ref_var in parts:
        budget, observed = _observing(run.ctx, run.after, trial)
        flank = budget.flank(run.after.cdf_lengths_m[idx])
        if not flank.any():
            continue
        sub = _spread(np.flatnonzero(flank.any(axis=1)))
        a, at = run.after, idx[sub]
        claim = np.diagonal(budget.covariance(a.lengths_m[at], a.reference_error_m[at],
                                              a.temp_change_c[at], a.bar_error_m[at], None,
                                              observed[at]), axis1=1, axis2=2)
        for b in range(6):
            if not flank[sub, b].any():
                continue
            n = int(np.sum(flank[:, b]))
            seen = np.mean(dd[flank[:, b], b] ** 2 - ref_var[flank[:, b], b])
            total[b] += n * (seen - float(np.mean(claim[flank[sub, b], b])))
            count[b] += n
    return np.where(count >= FLANK_SAMPLES, np.maximum(total / np.maximum(count, 1.0), 0.0), 0.0)


def _observing(ctx: FitContext, processed: Processed, model: Model) -> tuple[LengthBudget, Observed]:
    """``model``'s budget for a log and what it observes over a pipeline pass of it (read
    noise, motion); for the model the fit starts from and its own pass, made once per log."""
    def make() -> tuple[LengthBudget, Observed]:
        budget = LengthBudget(ctx.device, ctx.calibration, model)
        observed = budget.observe(processed.cdf_lengths_m, processed.reference_error_m,
                                  ctx.times_s, processed.poses, ctx.epoch_s)
        if ctx.obs.lag is not None:
            # a residual with the reference's lag taken out holds nothing of a common delay
            # of the bars' channels (one direction with it): the latch skew's claim, which
            # follows the bars' velocity, is not compared with it (with it, a fit against a
            # reference on its own clock measured no residual at all, and 12 realistic twins
            # were covered 76.6 %, one 61 %)
            observed = replace(observed, velocity_m_s=None)
        return budget, observed
    if processed is ctx.base and model is ctx.model:
        return ctx.cached('base_budget', make)
    return make()


def base_budget(ctx: FitContext) -> LengthBudget:
    """The budget of the model the fit starts from, for a log (made once per log)."""
    return _observing(ctx, ctx.base, ctx.model)[0]


def _sources(ctx: FitContext, processed: Processed, model: Model, idx: IntArray,
             apart: tuple[str, ...] = FIT_REPLACEABLE) -> tuple[FloatArray, FloatArray]:
    """The sources of ``model``'s budget at ``idx`` of a pipeline pass over a log, (n, 6, 6)
    each: all but the sources ``apart``, and those (by default: those kept after a fit, and
    those a measured residual may replace)."""
    budget, observed = _observing(ctx, processed, model)
    a = processed
    cov, bias = budget.sources(a.lengths_m[idx], a.reference_error_m[idx], a.temp_change_c[idx],
                               a.bar_error_m[idx], None, observed[idx])
    zero = np.zeros((idx.size, 6, 6))
    kept = sum((np.asarray(c) for name, c in cov.items() if name not in apart), zero)
    replaceable = sum((np.asarray(c) for name, c in cov.items() if name in apart), zero)
    for into_kept, names in ((True, [k for k in bias if k not in apart]),
                             (False, [k for k in bias if k in apart])):
        if names:
            b = sum(bias[k] for k in names)
            if into_kept:
                kept = kept + b[:, :, None] * b[:, None, :]
            else:
                replaceable = replaceable + b[:, :, None] * b[:, None, :]
    return kept, replaceable


def _component_var(ctx: FitContext, processed: Processed, cov: FloatArray, sub: IntArray) -> FloatArray:
    """The mean over the samples ``sub`` of a bar-length covariance (n, 6, 6) [m^2] in each
    observed component of a log, (k,) [m^2, rad^2]."""
    if ctx.obs.kind == 'pose':
        jinv = np.linalg.inv(jacobian(ctx.device.geometry, processed.poses[sub]))
        cov = pose_covariance(jinv, cov, processed.plate_scale[sub])
    return np.mean(np.diagonal(cov, axis1=1, axis2=2)[:, list(ctx.obs.components)], axis=0)


def _common_mode_visibility(ctx: FitContext, processed: Processed, sub: IntArray) -> float:
    """How well a log's observed components see an error common to the six bars: the largest,
    over the components, of the variance a unit error along the common mode gives it over the
    variance a unit error spread evenly over all six bar directions gives it (1: as well as an
    average direction; z of a full pose about 6, x and a rotation about the axis near 0)."""
    shape = (sub.size, 6, 6)     # (read-only views: the propagation divides them anew)
    along = _component_var(ctx, processed, np.broadcast_to(np.full((6, 6), 1.0 / 6.0), shape), sub)
    spread = _component_var(ctx, processed, np.broadcast_to(np.eye(6) / 6.0, shape), sub)
    return float(np.max(along / np.maximum(spread, 1e-300)))


def _scale_terms(ctx: FitContext, processed: Processed, kept: FloatArray, replaceable: FloatArray,
                 residual: FloatArray, sub: IntArray) -> tuple[float, float]:
    """The two sums of the least-squares factor k on the replaceable sources that makes the
    observed components' predicted variance match the residual's: sum (seen - kept) repl and
    sum repl^2 over the components (``residual`` at ``sub``, (n, k) [m, rad])."""
    kept_p = _component_var(ctx, processed, kept, sub)
    repl_p = _component_var(ctx, processed, replaceable, sub)
    seen_var = np.mean(residual ** 2, axis=0)
    if ctx.obs.sigma is not None:
        seen_var = seen_var - ctx.obs.sigma ** 2
    return float(np.sum((seen_var - kept_p) * repl_p)), float(np.sum(repl_p * repl_p))


def _free_mean_scale(ctx: FitContext, free: list[FittedEffect]) -> float:
    """The factor k on the calibration-derived sources' variance that makes them claim, per
    observed component, the variance over the log of what the terms with free constants
    correct (least squares over the components): 0 without such terms."""
    free = [f for f in free if f.theta is not None]
    if not free or ctx.train_idx is None or ctx.train_idx.size < 10:
        return 0.0
    sub = _spread(ctx.train_idx, 2000)
    corr = sum(f.effect.signature(ctx, f.hyper, sub) @ f.theta for f in free)     # (n, 6)
    _, replaceable = _sources(ctx, ctx.base, ctx.model, sub)
    if ctx.obs.kind == 'pose':
        jinv = np.linalg.inv(jacobian(ctx.device.geometry, ctx.base.poses[sub]))
        corr = np.einsum('nij,nj->ni', jinv, corr)
        corr[:, :3] *= ctx.base.plate_scale[sub, None]
        replaceable = pose_covariance(jinv, replaceable, ctx.base.plate_scale[sub])
    comp = list(ctx.obs.components)
    varied = np.var(corr[:, comp], axis=0)
    repl = np.mean(np.diagonal(replaceable, axis1=1, axis2=2)[:, comp], axis=0)
    den = float(np.sum(repl * repl))
    return float(np.sum(varied * repl)) / den if den > 0 else 0.0


def measured_read_noise(ctxs: list[FitContext]) -> FloatArray | None:
    """The read noise of each channel (six measuring bars, then the reference bars) that the
    budget's stream estimate found where the bars of the logs stood still, the largest over the
    logs, (6 + k,) [m]: 0 where no log stood still long enough, None where none did at all."""
    found = [_observing(c, c.base, c.model)[0].noise.sigma_m() for c in ctxs]
    if not found or not all(f.size == found[0].size for f in found):
        return None
    stacked = np.stack(found)
    if not np.isfinite(stacked).any():
        return None
    return np.nan_to_num(np.nanmax(np.where(np.isfinite(stacked), stacked, -np.inf), axis=0),
                         neginf=0.0)


#: The budget's sources that one calibration draws once and a run carries throughout, the same
#: for every length of a bar (the routine's drift, the plate's distances, the reference bar's
#: zero); its points' own errors are constants too, carried between the points by Eq. (10).
RUN_CONSTANT = ('calibration_drift', 'reference_distances', 'reference_bar')


def calibration_constants(ctx: FitContext, idx: IntArray) -> tuple[FloatArray, FloatArray]:
    """The errors one calibration draws once, as bar-length columns at the samples ``idx`` and
    their covariance by the budget of the model a fit starts from: a constant per bar
    (:data:`RUN_CONSTANT`, their mean over the samples) and each calibration point's own error
    (its variance at the point), carried by the hat functions of Eq. (10) at each sample's CDF
    length. Returns (n, 6, Q) [1] and (Q, Q) [m^2], Q = 6 + the points of all bars."""
    budget, _ = _observing(ctx, ctx.base, ctx.model)
    b = ctx.base
    constant = np.mean(_sources(ctx, b, ctx.model, _spread(idx, 2000), RUN_CONSTANT)[1], axis=0)
    knots = budget.knots_m                                           # (6, K)
    k = knots.shape[1]
    at = np.arange(k) % b.lengths_m.shape[0]
    points = budget.sources(knots.T, b.reference_error_m[at], b.temp_change_c[at],
                            None, None, None)[0].get('calibration_points')
    point_var = (np.zeros(6 * k) if points is None
                 else np.diagonal(points, axis1=1, axis2=2).T.reshape(-1))     # bar-major
    cols = np.zeros((idx.size, 6, 6 + 6 * k))
    cols[:, np.arange(6), np.arange(6)] = 1.0
    for i in range(6):
        cols[:, i, 6 + i * k:6 + (i + 1) * k] = hat_weights(b.cdf_lengths_m[idx, i], knots[i])
    q = np.zeros((6 + 6 * k, 6 + 6 * k))
    q[:6, :6] = constant
    q[np.arange(6, 6 + 6 * k), np.arange(6, 6 + 6 * k)] = point_var
    return cols, q


def claimed_sigma(ctx: FitContext, idx: IntArray) -> FloatArray:
    """What the budget of the model a fit starts from claims for each observed component of a
    log, the RMS over the samples ``idx`` of its predicted sigma, (k,) [m, rad].

    A zeroed reference (an offset per component removed) cannot see how a fit moves the mean of
    a component; this is how far the fit may move it (:mod:`mmd_ros.analysis.identify`): what
    the budget claims for it before the fit."""
    budget, observed = _observing(ctx, ctx.base, ctx.model)
    b = ctx.base
    sub = _spread(idx, 2000)
    sigma_d = budget.covariance(b.lengths_m[sub], b.reference_error_m[sub], b.temp_change_c[sub],
                                b.bar_error_m[sub], None, observed[sub])
    return np.sqrt(_component_var(ctx, b, sigma_d, sub))


#: The budget's sources drawn anew at every sample; the others (the calibration's points and
#: interpolation, the thermal compensation, the reference bar's zero, friction) are drawn once
#: per calibration or per run.
PER_SAMPLE = ('quantisation', 'read_noise')
#: Degrees of freedom with which one log shows the sources not drawn per sample: smooth
#: functions of the six bars' lengths and temperatures, about one per bar in a component.
SYSTEMATIC_DOF = 6
#: Level at which a residual above the budget's claim is taken as more than chance, over all
#: the components compared at once (each at 1 - (1 - level) / their number: Bonferroni).
CLAIM_LEVEL = 0.99


#: Width of the bins of a bar's length over which its residual's mean is taken out before its
#: independent samples are counted along it [m]
OFF_LENGTH_BIN_M = 1e-3


def _off_length(residual: FloatArray, lengths: FloatArray) -> FloatArray:
    """A bar's residual (n,) in time order less its mean in bins of its length (n,) [m] of
    :data:`OFF_LENGTH_BIN_M`: what of it is not a function of the length, whose correlation
    in time says how many independent looks at each length the run took. A residual that
    follows the length (a bump of the scale, a point the fit could not reach) is correlated
    in time only because the bar moves smoothly; counted on the residual itself, a bar whose
    fit left +90 to +180 nm over 12 mm (held-out samples, 4287) was 11 independent samples,
    and what it left there, 4 to 16 times the bar's mean excess, was not claimed."""
    finite = np.isfinite(lengths) & np.isfinite(residual)
    out = np.where(finite, residual, 0.0)
    if not finite.any():
        return out
    at = np.floor((lengths[finite] - np.min(lengths[finite])) / OFF_LENGTH_BIN_M).astype(np.intp)
    mean = np.bincount(at, residual[finite]) / np.maximum(np.bincount(at), 1)
    out[finite] = residual[finite] - mean[at]
    return out


def _between_bars_along_lengths(dd: FloatArray, lengths: FloatArray,
                                off: FloatArray | None = None) -> FloatArray:
    """What a run's residual ``dd`` (n, 6) [m] holds between the bars, sum over its samples
    (6, 6) [m^2], through its parts that follow each bar's own CDF length ``lengths`` (n, 6)
    [m] (its mean in bins of that length: ``off`` is the rest, each bar's :func:`_off_length`, made
    here when not given), beyond the product of their means; 0 on the diagonal. Those parts are
    errors of each bar's scale along its length (a point's friction step, the interpolation
    between points, a bump), functions of that bar's length alone: between two bars they go
    together only as the run's motion took the two lengths together, and another run's motion
    takes them otherwise. Of independent functions of lengths that move independently, what
    stays between the bars is the product of their means, which this keeps. On four twins'
    sessions (one-sided routines, each model judged on another 60 s 6-DOF run) one twin's new
    run was covered 83 % while the residual's covariance between the bars was claimed as the
    fitted runs showed it: its bars ran constants of alternating sign (a twist; yaw 0.9″ off,
    as traced on 2026-11-28) that the fitted runs' motion had tied otherwise (99 % now)."""
    if off is None:
        off = np.column_stack([_off_length(dd[:, b], lengths[:, b])
                               for b in range(dd.shape[1])])
    off = np.where(np.isfinite(lengths), off, dd)     # (no length read: nothing follows it)
    along = dd.T @ dd - off.T @ off
    mean = np.mean(dd - off, axis=0)
    along -= dd.shape[0] * np.outer(mean, mean)
    np.fill_diagonal(along, 0.0)
    return along


def _independent_samples(series: FloatArray) -> float:
    """Effective number of independent samples of a series in time order: n over its
    integrated autocorrelation time 1 + 2 sum rho_k, summed up to the first lag where rho
    falls below zero (a slow structure under fast noise keeps rho up for many lags, which the
    lag-1 figure misses: an ISO run's dwells)."""
    c = series - series.mean()
    n = c.size
    spectrum = np.fft.rfft(c, 1 << int(math.ceil(math.log2(2 * n))))
    acf = np.fft.irfft(np.abs(spectrum) ** 2)[:n]
    if acf[0] <= 0:
        return float(n)
    rho = acf / acf[0]
    below = np.flatnonzero(rho < 0)
    last = int(below[0]) if below.size else n
    return float(max(n / (1.0 + 2.0 * np.sum(rho[1:last])), 1.0))


def beyond_claim(ctx: FitContext, residual: FloatArray, idx: IntArray,
                 level: float = CLAIM_LEVEL) -> tuple[FloatArray, FloatArray]:
    """How many times what the budget of the model a fit starts from claims each observed
    component's residual is, and how many times it could be by chance, (k,) each.

    The ratio is the residual's RMS over the samples ``idx`` (the reference's own noise taken
    out) over the RMS sigma the budget predicts there. Above 1 the budget claims too little,
    but most of its sources are one draw per calibration or run, which one log shows with
    about :data:`SYSTEMATIC_DOF` degrees of freedom, and only :data:`PER_SAMPLE` sources with
    the residual's effective sample count: the limit is the ratio that the claim reaches at
    ``level`` of chi-square with those degrees of freedom. Beyond it an error the budget does
    not know of (an interference, an effect outside the catalogue) is in the data."""
    k = len(ctx.obs.components)
    r = residual[idx]
    ok = np.all(np.isfinite(r), axis=1)
    if ok.sum() < 10:
        return np.zeros(k), np.full(k, np.inf)
    r, idx = r[ok], idx[ok]
    seen = np.mean(r ** 2, axis=0)
    if ctx.obs.sigma is not None:
        seen = seen - ctx.obs.sigma ** 2
    sub = _spread(idx, 2000)
    once, each = (_component_var(ctx, ctx.base, c, sub)
                  for c in _sources(ctx, ctx.base, ctx.model, sub, PER_SAMPLE))
    claimed = once + each

    def quantile(dof: FloatArray | float) -> FloatArray:
        return chi2.ppf(level, dof) / dof

    n_eff = np.array([_independent_samples(r[:, j]) for j in range(k)])
    limit = np.sqrt((each * quantile(n_eff) + once * quantile(SYSTEMATIC_DOF)) / claimed)
    return np.sqrt(np.maximum(seen, 0.0) / claimed), limit


def fit_uncertainty(ctx: FitContext, found: list[FittedEffect], runs: list[ResidualRun],
                    model: Model, *, unseen: bool = False,
                    growing: list[ModelTerm] | None = None) -> FitUncertainty:
    """The ``uncertainty.fit`` section of the model a fit writes (see the module docstring).

    ctx : the context of the log whose parameters the model applies (signatures, terms)
    found : the effects the model applies, with their parameters' covariance
    runs : the logs the residual is measured on
    model : the extended model (its terms; its uncertainty section is not used)
    unseen : the residuals come from data the fit never saw (leave-one-run-out: each log
        predicted by the model fitted on the others), else from held-out blocks of the fitted
        logs (recorded in ``from``). Either replaces the calibration-derived sources where
        every bar is seen, over the lengths the fit saw (the budget restores them outside)
    """
    # (the samples of the log whose context the signatures are read on: another log's
    # indices fell outside a shorter one, or on other instants of a longer one)
    ref = next((run for run in runs if run.ctx is ctx), None)
    idx0 = (ref.idx if ref is not None
            else np.flatnonzero(ctx.obs.usable & ctx.base.measured(ctx.obs.kind)))
    validity = Validity.from_model(model)
    sample, seen_m = idx0[:4000], None if validity is None else validity.bar_range_m
    own = _not_carried(ctx, found, sample)
    directions, mean_terms, run_own, rest = _term_directions(ctx, found, sample, seen_m, own)
    previous = model.uncertainty.fit
    if not found and previous is not None:
        # nothing fitted now (the residual written as an uncertainty only): the directions of
        # the terms an earlier analysis fitted stay with those terms
        directions, mean_terms = list(previous.directions), previous.mean_terms_m2
        rest = previous.rest_terms_m2
    fit = FitUncertainty(run_own, (), 1.0, directions, mean_terms,
                         {'residual_from': ('logs the fit did not see (leave-one-run-out)' if unseen
                                            else 'held-out blocks of the fitted logs')},
                         measured_read_noise([run.ctx for run in runs]), rest_terms_m2=rest,
                         measured_unix_s=_measured_at(runs))
    _sized_from(fit, ctx, found, runs, model, unseen, growing,
                carried=_constants_carried(own))
    # a form of an effect the logs could not rule out (a cyclic error the calibration read,
    # fitted from one component): the change to it is claimed too, after the residual and the
    # scale were measured (it is not in these logs' residual: counted there, it lowered the
    # scale of the calibration's sources, and a C-axis fit's coverage fell from 93 % to 72 %)
    for f in found:
        for hyper in f.alternatives if f.theta is not None else []:
            terms, mean = _change_to(ctx, f, hyper, f.theta, sample, seen_m)
            fit.directions.append(terms)
            fit.mean_terms_m2 = fit.mean_terms_m2 + mean
    return fit


def _thermal_state(full: list[tuple[ResidualRun, IntArray]]) -> FloatArray | None:
    """The bars' thermal corrections (Eq. 13), then the reference bars' errors (Eq. 11), over
    the samples of the runs whose absolute references saw every bar, (6 + k,) [m], or None
    (no reference bar). Each bar's thermal mismatch there was measured: the fitted terms of
    free constants took up the constant it was over those runs, or their residual holds it;
    what a later run has of it is the mismatch of the change since (the thermal_mismatch
    source, msg_docs/frames.md; Eq. (13)'s approximation and the plates' scale likewise, from
    the mean temperature change, ``thermal_state_c``). Claimed from zero, a session's model,
    its CDF points fitted at the runs' temperature, claimed 58 nm in x inside the fitted
    lengths of four twins' new runs, 77 nm in all, where 58 nm was observed in all: between
    the fitted 6-DOF run and a new one the bars' mismatch changed by 9 nm RMS, where 40 nm per
    bar was claimed. Not recorded when a run's own drift took constants the model's terms do
    not carry (:func:`_sized_from`)."""
    total, count = None, 0
    for run, idx in full:
        a = run.after
        if a.reference_error_m.ndim != 2 or a.reference_error_m.shape[1] == 0:
            return None
        values = np.concatenate([a.bar_error_m[idx], a.reference_error_m[idx]], axis=1)
        values = values[np.all(np.isfinite(values), axis=1)]
        total = values.sum(axis=0) if total is None else total + values.sum(axis=0)
        count += values.shape[0]
    return None if total is None or count == 0 else total / count


def _measured_at(runs: list[ResidualRun]) -> float | None:
    """The mean Unix time of the samples the residual is measured on [s], or None when a
    log's time is not known."""
    if not runs or any(run.ctx.epoch_s is None for run in runs):
        return None
    total = sum(run.idx.size for run in runs)
    if not total:
        return None
    return sum(run.ctx.epoch_s * run.idx.size + float(np.sum(run.ctx.times_s[run.idx]))
               for run in runs) / total


def _sized_from(fit: FitUncertainty, ctx: FitContext, found: list[FittedEffect],
                runs: list[ResidualRun], model: Model, unseen: bool = False,
                growing: list[ModelTerm] | None = None, carried: bool = True) -> None:
    """The residual, the sources it replaces and the scale of the kept ones, measured on
    ``runs`` with the claims ``fit`` makes so far (:func:`fit_uncertainty`; ``unseen``: the
    runs' residuals are from models fitted without them; ``carried``: the model's terms carry
    the constants the runs' own effects took, :func:`_constants_carried`)."""
    full, partial = [], []
    for run in runs:
        obs: Observation = run.ctx.obs
        ok = np.all(np.isfinite(run.residual[run.idx]), axis=1) & run.after.measured(obs.kind)[run.idx]
        idx = run.idx[ok]
        if idx.size < 10:
            continue
        (full if obs.kind == 'lengths' or len(obs.components) == 6 else partial).append((run, idx))
    if full:
        observed_cov = np.zeros((6, 6))
        predicted = np.zeros((6, 6))
        seen = np.zeros(6, dtype=bool)
        for run, _ in full:      # what the references see of the bars
            seen[slice(None) if run.ctx.obs.kind == 'pose' else run.ctx.obs.components] = True
        # a residual of every bar stands for the calibration-derived sources over the lengths
        # the fit saw (the budget restores them outside: the model's validity record); when an
        # offset per component was removed, the constant part of the error it lacks is claimed
        # as what the runs leave unknown of a constant error per bar (_unseen_constants)
        replacing = bool(seen.all())
        zeroed = any(run.ctx.obs.datum for run, _ in full)
        # the thermal state at which the references measured the thermal errors; not when a
        # run's own drift took constants the model's terms do not carry: its offsets are not
        # written, and a twin warmed 5 °C whose fit found one (no CDF points among the terms)
        # was covered 61 % with the state, 99 % without (inside the fitted lengths)
        if replacing and not zeroed and carried:
            fit.thermal_state_m = _thermal_state(full)
            # the plates' scale moves the pose, not the bars: only a pose reference measured
            # it (a thermal_gain fitted on a soak against bar lengths claimed x and y 0.6
            # times their error 7 h later with the plates' scale counted from the soak's)
            pose = [(run, idx) for run, idx in full if run.ctx.obs.kind == 'pose']
            if fit.thermal_state_m is not None and pose:
                fit.thermal_state_c = float(np.mean(np.concatenate(
                    [run.after.temp_change_c[idx] for run, idx in pose])))
        if zeroed:
            # a zeroed reference: the mean of each component over a log, which those sources
            # stand for, is not seen. An effect of one physical law carries the mean its law
            # gives; a term with free constants was held to move it no further than the budget
            # claims (identify._Rows), but what such terms corrected is an error the
            # calibration's sources may not know of, and its mean over a log is unchecked by
            # about as much as it varied: the sources are scaled to claim that much
            estimate = _free_mean_scale(ctx, [f for f in found if f.effect.free_mean])
            fit.systematic_scale = max(estimate, 1.0)
            fit.record['scale_estimate'] = round(estimate, 4)
        n = 0
        parts, bars_along = [], []
        prior, shaped = np.zeros((6, 6)), np.zeros((6, 6))
        for run, idx in full:
            obs = run.ctx.obs
            r = run.residual[idx]
            ref_var = np.zeros((idx.size, 6))
            if obs.kind == 'pose':
                jac = jacobian(run.ctx.device.geometry, run.after.poses[idx])
                dd = np.einsum('nij,nj->ni', jac, r)
                if obs.sigma is not None:    # the reference's own noise is not the MMD's error
                    observed_cov -= np.einsum('nik,k,njk->ij', jac, obs.sigma ** 2, jac)
                    ref_var = np.einsum('nik,k,nik->ni', jac, obs.sigma ** 2, jac)
            else:
                dd = np.zeros((idx.size, 6))
                dd[:, obs.components] = r
            parts.append((run, idx, dd, ref_var))
            # (what follows each bar's own length is claimed independent between the bars;
            # what does not, counts its independent samples along it below)
            lengths = run.after.cdf_lengths_m[idx]
            off = np.column_stack([_off_length(dd[:, b], lengths[:, b]) for b in range(6)])
            observed_cov -= _between_bars_along_lengths(dd, lengths, off)
            sub = _spread(idx)
            kept, replaceable = _predicted(run, model, fit, sub)
            observed_cov += dd.T @ dd
            prior += np.mean(replaceable, axis=0) * idx.size
            if replacing and zeroed:      # (a mean over the samples: fewer of them do)
                few = _spread(idx, 2000)
                shaped += np.mean(_sources(run.ctx, run.after, _trial(model, fit), few,
                                           LENGTH_SHAPED)[1], axis=0) * idx.size
            predicted += (np.sum(kept if replacing else kept + replaceable, axis=0)
                          * (idx.size / sub.size))
            n += idx.size
            # (the residual along each bar's length, at a few of the samples)
            step = max(1, -(-idx.size // PREDICTED_SAMPLES))      # (sub's, :func:`_spread`)
            few = _spread(np.arange(sub.size), PROFILE_SAMPLES)
            claim = np.diagonal(kept if replacing else kept + replaceable, axis1=1, axis2=2)[few]
            bars_along.append(_AlongBars(run.after.cdf_lengths_m[sub[few]], dd[few * step],
                                    ref_var[few * step] + claim,
                                    np.array([_independent_samples(off[:, b]) / idx.size
                                              for b in range(6)])))
        excess = _psd(observed_cov / n - predicted / n)
        excess[~seen, :] = 0.0
        excess[:, ~seen] = 0.0
        fit.profile, widths = _length_profile(bars_along, excess)
        if fit.profile is not None:
            fit.record['residual_profile_width_mm'] = widths
        if replacing and zeroed:
            # (the replaceable sources were predicted with the scale k already on them). Their
            # length-shaped part is what the variation each bar showed leaves unknown of its
            # mean, in the common mode as between the bars: each bar's shape ties its own mean
            # (the common mode keeping the calibration's whole claim of it claimed z 3.3 times
            # its error on twins without a gravity sag, which that claim had stood for)
            budget = _observing(full[0][0].ctx, full[0][0].after, _trial(model, fit))[0]
            # (a fitted run's residual lacks the variation its terms of free constants took, and
            # their mean is held: the shape is read with their correction taken back out)
            free = [] if unseen else [f for f in found if f.effect.free_mean
                                      and f.effect.scope != 'run' and f.theta is not None]
            shape_var, shape_mean, moves, factor = _shape_constants(
                parts, budget, fit.systematic_scale, free)
            # the square of a noisy estimate overstates what it estimates by its noise: each
            # bar's estimated mean shrunk by the noise its runs' halves disagree by
            noise = _shape_noise(parts, budget, fit.systematic_scale, free)
            shrink = np.clip(1.0 - noise / np.maximum(shape_mean * shape_mean, 1e-40), 0.0, 1.0)
            start = (prior - shaped + np.diag(shape_var * n)) / n
            unseen, estimate = _unseen_constants(parts, start, shape_mean * np.sqrt(shrink))
            fit.record['shape_noise_nm'] = [round(math.sqrt(v) * 1e9, 1) for v in noise]
            # and how far a run's mean moves with where it dwells, per bar
            dwell = np.maximum(_dwell_means(parts), moves)
            unseen = unseen + np.diag(dwell)
            excess = excess + unseen
            fit.record['run_mean_nm'] = [round(math.sqrt(v) * 1e9, 1) for v in dwell]
            fit.record['shape_constant_nm'] = [round(math.sqrt(v) * 1e9, 1) for v in shape_var]
            fit.record['shape_estimate_nm'] = [round(float(v) * 1e9, 1) for v in shape_mean]
            fit.record['shape_factor'] = [round(float(v), 2) for v in factor]
            fit.record['unseen_constant_nm'] = [round(math.sqrt(v) * 1e9, 1) for v in np.diag(unseen)]
            fit.record['constant_estimate_nm'] = [round(float(v) * 1e9, 1) for v in estimate]
            common = np.full(6, 1.0 / math.sqrt(6.0))
            along = float(common @ unseen @ common)
            between = float(np.trace(unseen)) - along          # the five other directions
            fit.record['unseen_common_mode_nm'] = round(math.sqrt(max(along, 0.0)) * 1e9, 1)
            fit.record['unseen_differential_nm'] = round(math.sqrt(max(between, 0.0) / 5.0) * 1e9, 1)
        fit.residual_m2 = excess + fit.residual_m2     # (what another run may drift: run_own)
        fit.replaces = tuple(FIT_REPLACEABLE) if replacing else ()
        if replacing:
            fit.flank_m2 = np.where(seen, _flank_excess(parts, model, fit), 0.0)
        fit.record['samples'] = int(n)
        fit.record['residual_rms_nm'] = [round(float(math.sqrt(max(v, 0.0) / n)) * 1e9, 3)
                                         for v in np.diag(observed_cov)]
        return
    if partial:
        # some pose components: scale what the reference cannot attribute to bars
        num = den = 0.0
        mean_repl, total, sees_common = np.zeros((6, 6)), 0, 0.0
        for run, idx in partial:
            sub = _spread(idx)
            kept, replaceable = _predicted(run, model, fit, sub)
            a, b = _scale_terms(run.ctx, run.after, kept, replaceable, run.residual[sub], sub)
            num, den = num + a, den + b
            mean_repl += np.mean(replaceable, axis=0) * idx.size
            total += idx.size
            sees_common = max(sees_common, _common_mode_visibility(run.ctx, run.after, sub))
        estimate = num / den if den > 0 else 1.0
        fit.systematic_scale = max(estimate, 1.0)
        fit.record['scale_estimate'] = round(estimate, 4)
        fit.record['common_mode_visibility'] = round(sees_common, 3)
        excess = max(estimate - 1.0, 0.0) * mean_repl / max(total, 1)
        if estimate > 1.0 and sees_common < 1.0:
            # what those components showed is of the bars' differences; how much of it the
            # six bars share (an error of their scale, their temperature, the reference bar's),
            # which moves z and none of them, they cannot show: the common mode is claimed as
            # large as the whole excess they showed (scaled alone, a bow of every bar's scale
            # seen by an x-axis laser left z claimed 0.48 times its error, and 86 % of new
            # 6-DOF motion within the lengths the fit saw in the 95 % ellipsoid; measured 95 %)
            common = np.full(6, 1.0 / math.sqrt(6.0))
            whole = float(np.trace(excess))
            fit.residual_m2 = fit.residual_m2 + whole * np.outer(common, common)
            fit.record['common_mode_nm'] = round(math.sqrt(max(whole, 0.0)) * 1e9, 1)
            excess = excess + whole * np.outer(common, common)
        # (an error of the bars' lengths found in it: beyond the lengths seen, it may grow)
        fit.profile, share = _growth_profile(
            [run.after.cdf_lengths_m[idx] for run, idx in partial], excess, growing or [],
            base_budget(ctx))
        if fit.profile is not None:
            fit.record['growing_share'] = [round(float(v), 3) for v in share]
        return
    fit.record['note'] = 'no usable residual: the calibration-derived sources stay as they are'


#: Degree of the polynomial an error of a bar's length is taken to be beyond the lengths a
#: fit saw (a bar's scale error: offset, scale, bow).
GROWTH_DEGREE = 2


def _growth_profile(lengths: list[FloatArray], excess: FloatArray, terms: list[ModelTerm],
                    budget: LengthBudget) -> tuple[LengthProfile | None, FloatArray]:
    """Where along each bar an excess a partial reference showed is claimed, when a term of the
    bars' lengths was found in it and not written (``terms``): as large as seen, and as large
    as a smooth error of that mean square reaches beyond the lengths seen.

    A reference that sees some pose components (a laser along x, a rotary encoder) cannot tell
    which bar an error of the bars' lengths came from, and the term that follows it is not
    written (its effect on the other components is not determined). Its excess is claimed
    flat over the lengths the fit saw (``lengths``, per run (n, 6) [m]); beyond them no data
    say what the error does, and a smooth one grows (a bow of each bar's scale seen by an
    x-axis laser: 12.2 % of new motion's samples with a bar beyond those lengths in the 95 %
    ellipsoid, its error there 2-3 times the claim). Taken as a polynomial of degree
    :data:`GROWTH_DEGREE` in the bar's length u (-1 to 1 over the lengths seen), its
    coefficients on the Legendre polynomials orthonormal there independent and alike, its
    expected square at u is K(u) / (degree + 1) of its mean square, K(u) = sum (2 n + 1)
    P_n(u)^2 (0.75 in the middle, 3 at the ends, 12.2 at u = 1.4). Only the share of a bar's
    error that is smooth grows: of the term's correction over the lengths seen, the share of
    its variance beyond the calibration points' own errors (independent from point to point,
    :meth:`LengthBudget.smooth_share`; a cyclic error the calibration read at its points
    left a points term riding along that does not grow). Bar b's factor is
    max(1, 1 + s_b (K(u) / (degree + 1) - 1)), s_b that share, on a grid 200 mm either side
    of the lengths seen (None where no bar's share is above 0), and the shares (6,)."""
    if not terms or not np.any(np.diag(excess) > 0):
        return None, np.zeros(6)
    x = np.concatenate(lengths)
    finite = np.isfinite(x)
    lo = np.min(np.where(finite, x, np.inf), axis=0)
    hi = np.max(np.where(finite, x, -np.inf), axis=0)
    _, ok, corrections = budget.length_corrections(terms, np.column_stack([lo, hi]))
    share = np.where(ok, budget.smooth_share(np.var(sum(corrections), axis=0)), 0.0)
    if not np.any(share > 0):
        return None, share
    grids, factors = [], []
    for b in range(6):
        if not (ok[b] and share[b] > 0):      # (a bar seen nowhere, or whose error does not grow)
            grids.append(np.zeros(0))
            factors.append(np.zeros(0))
            continue
        mid, half = 0.5 * (lo[b] + hi[b]), max(0.5 * (hi[b] - lo[b]), 1e-3)
        grid = np.linspace(lo[b] - 0.2, hi[b] + 0.2, PROFILE_POINTS)
        u = (grid - mid) / half
        k = sum((2 * j + 1) * legendre.legval(u, np.eye(GROWTH_DEGREE + 1)[j]) ** 2
                for j in range(GROWTH_DEGREE + 1))
        grids.append(grid)
        factors.append(np.clip(1.0 + share[b] * (k / (GROWTH_DEGREE + 1) - 1.0), 1.0, 1e6))
    return LengthProfile(excess.copy(), grids, factors), share


#: Samples per run at most at which the residual's profile along each bar is read.
PROFILE_SAMPLES = 5000
#: Widths [m] of the kernel over a bar's length tried for the residual's profile along it.
PROFILE_WIDTHS_M = (0.5e-3, 1e-3, 2e-3, 4e-3, 8e-3, 16e-3)
#: Consecutive blocks of each run, taken alternately into the two halves that predict each
#: other (a bar may pass a length in a few seconds of a run only).
PROFILE_BLOCKS = 16
#: Least factor of the profile: where a bar's residual was smallest it is still claimed.
PROFILE_FLOOR = 0.1
#: Log-likelihood [nats] by which a profile must predict the other half of the runs better
#: than the flat claim (the best of several widths gains by chance: up to 1.6 where the
#: residual did not depend on length, 3.5-46 for a bump of 3 mm on each bar).
PROFILE_MARGIN = 2.0
#: Where no profile predicts the other half better, a length's excess is still claimed there
#: when it stands this many of its own standard deviations (sqrt(2 / its independent
#: samples), a variance's) above the mean.
PROFILE_SIGMAS = 3.0
#: Independent samples' worth of the mean excess with which each length's estimate starts.
PROFILE_PRIOR_SAMPLES = 1.0


@dataclass
class _AlongBars:
    """A run's residual along the bars at some samples: CDF lengths (n, 6) [m], the bar-length
    residual (n, 6) [m], what the budget already claims of it per sample (n, 6) [m^2] and the
    share of the samples that are independent, per bar (6,)."""

    lengths: FloatArray
    residual: FloatArray
    claimed: FloatArray
    independent: FloatArray


def _length_profile(along: list[_AlongBars], excess: FloatArray
                    ) -> tuple[LengthProfile | None, list[float | None]]:
    """Where along each bar's length the residual beyond the budget's per-sample claim lay
    (:class:`~mmd_ros.core.model.LengthProfile`), and the width of the kernel read per bar
    [mm] (None: alike at every length); None where no bar's residual depended on its length.

    An error of a bar that is a function of its length (a local defect of the scale, a dent in
    a ball's seat, dirt on the grating) shows in the residual at the lengths it lies at and not
    elsewhere: claimed alike at every length, its variance is spread over lengths where it is
    not, and where it is the ellipsoid misses it (a bump of 3 mm, 0.3 µm high on each bar:
    new motion's samples 88.6 % covered, the angles' sigma 1.2-3.5 times their error). Per bar,
    the mean over nearby lengths of the residual's square less the claim (a Gaussian kernel of
    width h, starting from the mean excess with :data:`PROFILE_PRIOR_SAMPLES` independent
    samples' weight), not below :data:`PROFILE_FLOOR` of that mean, divided by its mean over
    the samples. The width, or none, is the one under which each half of every run's samples
    (alternate blocks of it, :data:`PROFILE_BLOCKS`) predicts the other's residual best (a
    Gaussian likelihood, each half's sum of log densities weighted by its share of
    independent samples), by more than :data:`PROFILE_MARGIN`: a residual alike at every
    length keeps the flat claim. Where none does (a bar that crossed its defect a few times:
    one half may not hold it), what was seen where it was seen is claimed there all the same
    where it stands out of the mean by more than chance allows (:data:`PROFILE_SIGMAS`), the
    largest over the widths, and the flat claim elsewhere (a factor of 1): a 4 mm bump of
    0.4 µm that the fitted run crossed for 1 % of its samples and a new run dwelt on for 40 %
    left that run 60.5 % covered, 79 % with this. Where a profile does, the same is claimed
    wherever it exceeds the profile: the profile's estimate starts from the mean and a
    length few independent samples saw stays near it (a bump of -391 nm crossed twice, 5
    independent samples, was claimed 97 nm where the fit left 321 nm; a new run that dwelt
    on it 79 % covered, 99.8 % with this)."""
    if not along or not np.any(np.diag(excess) > 0):
        return None, [None] * 6
    lengths: list[FloatArray] = [np.zeros(0)] * 6
    factor: list[FloatArray] = [np.zeros(0)] * 6
    widths: list[float | None] = [None] * 6
    for b in range(6):
        e = float(excess[b, b])
        if e <= 0:
            continue
        x = [a.lengths[:, b] for a in along]
        y = [a.residual[:, b] ** 2 - a.claimed[:, b] for a in along]
        base = [np.maximum(a.claimed[:, b], 1e-30) for a in along]
        r2 = [a.residual[:, b] ** 2 for a in along]
        weight = [np.full(a.lengths.shape[0], a.independent[b]) for a in along]
        ok = [np.isfinite(v) & np.isfinite(c) for v, c in zip(x, y)]
        x, y, base, r2, weight = ([v[k] for v, k in zip(arrays, ok)]
                                  for arrays in (x, y, base, r2, weight))
        halves = [[(np.arange(v.size) * PROFILE_BLOCKS // max(v.size, 1)) % 2 == 0 for v in x]]
        halves.append([~h for h in halves[0]])
        if sum(v.size for v in x) < 20 or any(not np.any(h) for half in halves for h in half):
            continue

        def local(h: float, pick: list[NDArray[np.bool_]]) -> tuple[FloatArray, ...]:
            """The samples ``pick``'s lengths and weights, a grid of lengths (3 h beyond them
            either side), the residual's local excess there and the budget's local claim, each
            over the mean excess, and the independent samples they rest on."""
            xs = np.concatenate([v[p] for v, p in zip(x, pick)])
            ys = np.concatenate([v[p] for v, p in zip(y, pick)])
            cs = np.concatenate([v[p] for v, p in zip(base, pick)])
            ws = np.concatenate([v[p] for v, p in zip(weight, pick)])
            lo, hi = float(xs.min()), float(xs.max())
            grid = np.linspace(lo - 3.0 * h, hi + 3.0 * h, int(min(
                (hi - lo) / (0.5 * h) + 13, PROFILE_POINTS)))
            # (the samples summed in bins a quarter of the kernel wide first)
            at = ((xs - lo) / (0.25 * h)).astype(np.intp)
            w_bin = np.bincount(at, ws)
            used = w_bin > 0
            centre = np.bincount(at, ws * xs)[used] / w_bin[used]
            k = np.exp(-0.5 * ((grid[:, None] - centre[None, :]) / h) ** 2) * w_bin[None, used]
            count = k.sum(axis=1)
            per = np.maximum(count, 1e-300) * e
            return (xs, ws, grid, k @ (np.bincount(at, ws * ys)[used] / w_bin[used]) / per,
                    k @ (np.bincount(at, ws * cs)[used] / w_bin[used]) / per, count)

        def profile(h: float, pick: list[NDArray[np.bool_]]) -> tuple[FloatArray, FloatArray]:
            xs, ws, grid, ratio, _, count = local(h, pick)
            # (starting from the mean with a weight of its own: where few samples lay, near it)
            ratio = (count * ratio + PROFILE_PRIOR_SAMPLES) / (count + PROFILE_PRIOR_SAMPLES)
            f = np.maximum(ratio, PROFILE_FLOOR)
            return grid, f / float(np.sum(ws * np.interp(xs, grid, f)) / np.sum(ws))

        def score(h: float | None) -> float:
            total = 0.0
            for train, test in ((halves[0], halves[1]), (halves[1], halves[0])):
                grid, g = profile(h, train) if h is not None else (None, None)
                for v, c, q, w, t in zip(x, base, r2, weight, test):
                    f = (np.interp(v[t], grid, g, left=1.0, right=1.0) if g is not None
                         else np.ones(int(t.sum())))
                    var = c[t] + e * f
                    total -= 0.5 * float(np.sum(w[t] * (np.log(var) + q[t] / var)))
            return total

        flat = score(None)
        best, best_score = None, flat
        for h in PROFILE_WIDTHS_M:
            got = score(h)
            if got > best_score:
                best, best_score = h, got
        every = [np.ones(v.size, dtype=bool) for v in x]
        if best is not None and best_score - flat > PROFILE_MARGIN:
            lengths[b], factor[b] = profile(best, every)
            widths[b] = round(best * 1e3, 3)
        # shown to hold along the bar or not, what was seen where it was seen is claimed there
        # (the profile shrinks it toward the mean where few samples lay, the flat claim is the
        # mean), where it stands out of the mean by more than chance allows (the mean
        # square of k independent samples of a Gaussian of variance v scatters by v sqrt(2/k),
        # v the claim and the excess together): the largest over the widths, on the finest
        # grid that holds any
        for h in PROFILE_WIDTHS_M:
            _, _, grid, ratio, claim, count = local(h, every)
            beyond = ratio > 1.0 + PROFILE_SIGMAS * (1.0 + claim) * np.sqrt(
                2.0 / np.maximum(count, 1e-9))
            if not beyond.any():
                continue
            if widths[b] is None:
                lengths[b], factor[b] = grid, np.ones(grid.size)
                widths[b] = round(h * 1e3, 3)
            factor[b] = np.maximum(factor[b], np.interp(lengths[b], grid,
                                                        np.where(beyond, ratio, 0.0)))
    if all(w is None for w in widths):
        return None, widths
    return LengthProfile(excess.copy(), lengths, factor), widths


def _unseen_constants(parts: list[tuple[ResidualRun, IntArray, FloatArray, FloatArray]],
                      prior: FloatArray, prior_mean: FloatArray | None = None
                      ) -> tuple[FloatArray, FloatArray]:
    """What the runs leave unknown of a constant error of each bar when a reference removed an
    offset per component, (6, 6) [m^2], and the runs' estimate of that error (in the sign of
    their residual), (6,) [m].

    A constant bar error c moves the pose by J^-1(t) c; a zeroed reference sees only the part
    of it that varies over a log, A(t) c with A = J^-1 minus its mean over the log (for an
    absolute reference A = J^-1; bar lengths: their rows of the identity, nothing when zeroed).
    Prior: ``prior`` (mean ``prior_mean``, else zero), what the calibration-derived sources
    claim of that error (:func:`_sized_from`). Information: sum_t A^T W A, W the inverse of
    each component's residual variance over its effective samples (a smooth residual is
    fewer independent samples than it has). Claimed: the second moment of c given the data,
    the posterior (P^-1 + I)^-1 and the estimate's square (an error the fit held back from a
    mean it could not see, or one whose shape its terms lack, is left in the runs as a
    constant: without it a bow across the bars, fitted zeroed on 4 twins, was covered 89 %
    where the fit saw the bars). An error common to all six bars (temperature, gravity, the
    reference bar's zero, the plates' scale) changes with the pose as the bars' directions
    do, and a zeroed reference reads it as offsets: the common mode is given no information
    and keeps its prior (on the twin, a gravity sag the calibration read flat left -37 to
    -120 nm on every bar of new runs, while the constants the pose variation determined
    differed between bars by 7 to 21 nm: the bars' stated sag, a source of the prior, claims
    it; ``mmd analyze`` now starts from the stated sag, and the prior keeps the rest)."""
    info, score = np.zeros((6, 6)), np.zeros(6)
    for run, idx, _dd, _ref in parts:
        obs = run.ctx.obs
        comp = list(obs.components)
        r = run.residual[idx]
        var = np.mean(r * r, axis=0)
        n_eff = np.array([_independent_samples(r[:, j]) for j in range(len(comp))])
        w = np.where(var > 0, n_eff / idx.size / np.where(var > 0, var, 1.0), 0.0)
        # the sums over the run, from evenly spread samples (a long 1 kHz log has millions)
        pick = _spread(np.arange(idx.size))
        a = obs.length_map(run.ctx.device, run.after.poses[idx[pick]])
        if obs.datum:
            a = a - a.mean(axis=0)
        share = idx.size / pick.size
        info += share * np.einsum('nki,k,nkj->ij', a, w, a)
        score += share * np.einsum('nki,k,nk->i', a, w, r[pick])
    common = np.eye(6) - 1.0 / 6.0                    # the common mode gets no information
    info, score = common @ info @ common, common @ score
    ev, v = np.linalg.eigh(0.5 * (prior + prior.T))
    half = v * np.sqrt(np.maximum(ev, 0.0))           # P = H H^T, P may be singular
    posterior = half @ np.linalg.solve(np.eye(6) + half.T @ info @ half, half.T)
    start = np.zeros(6) if prior_mean is None else prior_mean
    estimate = start + posterior @ (score - info @ start)
    return _psd(posterior) + np.outer(estimate, estimate), estimate


def _shape_constants(parts: list[tuple[ResidualRun, IntArray, FloatArray, FloatArray]],
                     budget: LengthBudget, scale: float, free: list[FittedEffect],
                     target: list[tuple[FloatArray, FloatArray]] | None = None
                     ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per bar, what the runs leave unknown of the mean over their samples of the calibration's
    length-shaped errors (:data:`LENGTH_SHAPED`) after the model, (6,) [m^2], and its estimate
    from how the bar's error varied with its length, (6,) [m]. ``free``: the model's terms of
    free constants fitted on these runs (none where the residuals come from models fitted
    without them): the error before them is the residual less the change they made to the
    lengths, and what is left of the mean is the estimate from that error plus their mean
    change (a fit that took a shape's variation and held back its mean left a residual that no
    longer shows it).

    Those errors are functions of the bar's length (Gaussian, the covariance the budget claims:
    each point's own error, friction state and sub-divisional error carried linearly between
    the points, and a smooth error between them that is zero at the points; times ``scale``),
    and the runs see each bar's residual at the lengths it passed through, less its mean over
    a zeroed run. A function known where it
    varies is known in its mean as far as its covariance ties the two: an error zero at the
    points is pinned by a run that passed through them. The Gaussian conditional of the mean
    on the variation (each run's residual less its own mean at SHAPE_POINTS of its samples)
    gives both. What the function does not explain is noise: per point, a variance s^2 times
    the run's points over its residual's effective samples (a slow residual is fewer
    independent points), s^2 the one that makes the residual most likely (the marginal
    likelihood), not below the quantisation's; its own mean over a run, which no variation
    shows, is claimed too (:func:`_unexplained_mean`).

    Third, per bar, how far the mean of what the model leaves of that shape moves with where
    a run dwells, (6,) [m^2]. The calibration's description ties the function's mean to its
    variation, and so to any run's; a bar whose error has more of that shape than the
    description allows (the factor a > 1) holds an error no description ties, the share
    1 - 1/a of its variance, and a new run's mean of what the model leaves of it is where that
    run dwells: claimed as that share of its spread over the lengths the runs passed (the
    conditional mean, plus the model's change). On 24 realistic twins a = 1 (142 of 144 bars),
    and the whole spread claimed besides the bars' constants made roll and pitch 1.31 and
    1.26 times the error; a session whose length terms were not written left its one-sided
    calibration's points' friction states, 7-12 times the description in sigma while the
    budget did not claim them, and its new run was covered 89 % without this. Fourth, the
    factor a per bar. With ``target`` (per bar, lengths and their weights), the estimate is of
    the function's weighted mean at those lengths instead (:func:`_shape_noise`)."""
    var, mean, moves, factor = np.zeros(6), np.zeros(6), np.zeros(6), np.ones(6)
    ie, knots = budget.interpolation, budget.knots_m
    total = sum(idx.size for _run, idx, _dd, _ref in parts)
    picks = _shape_picks(parts)
    applied = [sum((f.effect.signature(part[0].ctx, f.hyper, part[1][pick]) @ f.theta
                    for f in free), np.zeros((pick.size, 6))) for part, pick in zip(parts, picks)]
    change = sum(np.mean(took, axis=0) * part[1].size for part, took in zip(parts, applied)) / total
    for b in range(6):
        x, w = _shape_points(parts, picks, b)
        d, blocks, spread, change_at = [], [], [], []
        for (run, idx, dd, _ref), took, pick in zip(parts, applied, picks):
            change_at.append(took[:, b])
            d.append(dd[pick, b] - took[:, b])
            independent = max(_independent_samples(dd[:, b]), 1.0)
            spread.append(np.full(pick.size, max(pick.size / independent, 1.0)))
            centre = np.eye(pick.size)
            if run.ctx.obs.datum:
                centre -= 1.0 / pick.size
            blocks.append(centre)
        xs, ws = np.concatenate(x), np.concatenate(w)
        hat = hat_weights(xs, knots[b])
        points = (budget.point_var_m2 + float(budget.point_friction_m2[b])      # per point
                  + float(budget.subdivision_left_m2[b]))
        cov = scale * (ie.covariance(xs, xs, knots[b]) + points * (hat @ hat.T))
        if target is None:
            tied_to = cov @ ws
        else:       # (the covariance of the data's function with its mean at the target)
            xt, wt = target[b]
            tied_to = scale * (ie.covariance(xs, xt, knots[b])
                               + points * (hat @ hat_weights(xt, knots[b]).T)) @ wt
        c = block_diag(*blocks)
        g = 1.0 / np.sqrt(np.concatenate(spread))          # noise whitened: s^2 I
        lam, u = np.linalg.eigh(g[:, None] * (c @ cov @ c.T) * g[None, :])
        lam = np.maximum(lam, 0.0)
        seen = c @ np.concatenate(d)
        z = u.T @ (g * seen)
        tied = u.T @ (g * (c @ tied_to))
        floor = budget.resolution_m ** 2 / 12.0 * float(np.min(g * g))
        a, s2 = _most_likely(lam, z, floor, max(float(np.mean(z * z)), floor * 10.0))
        t = a * lam + s2
        shape = a * (cov @ c.T @ (g * (u @ (z / t))))      # the function's conditional mean
        rest = np.split(seen - c @ shape, np.cumsum([v.size for v in x])[:-1])
        var[b] = (max(a * float(ws @ cov @ ws) - a * a * float(np.sum(tied * tied / t)), 0.0)
                  + _unexplained_mean(rest, x, w))
        mean[b] = a * float(np.sum(tied * z / t)) + change[b]
        left = shape + np.concatenate(change_at)
        moves[b] = (1.0 - 1.0 / a) * float(ws @ (left - ws @ left) ** 2)
        factor[b] = a
    return var, mean, moves, factor


def _shape_picks(parts: list[tuple[ResidualRun, IntArray, FloatArray, FloatArray]]
                 ) -> list[IntArray]:
    """The samples of each run at which :func:`_shape_constants` reads the shape: at most
    :data:`SHAPE_POINTS` per run and :data:`SHAPE_POINTS_TOTAL` over all, evenly spread."""
    most = max(min(SHAPE_POINTS, SHAPE_POINTS_TOTAL // len(parts)), 20)    # per run
    return [_spread(np.arange(idx.size), most) for _run, idx, _dd, _ref in parts]


def _shape_points(parts: list[tuple[ResidualRun, IntArray, FloatArray, FloatArray]],
                  picks: list[IntArray], b: int) -> tuple[list[FloatArray], list[FloatArray]]:
    """Per run, bar ``b``'s CDF lengths at the samples ``picks`` and their weights in the mean
    over all the runs' samples (a run's share of them, spread evenly over its picks)."""
    total = sum(idx.size for _run, idx, _dd, _ref in parts)
    return ([run.after.cdf_lengths_m[idx[pick], b] for (run, idx, _dd, _ref), pick
             in zip(parts, picks)],
            [np.full(pick.size, idx.size / (total * pick.size))
             for (_run, idx, _dd, _ref), pick in zip(parts, picks)])


def _shape_noise(parts: list[tuple[ResidualRun, IntArray, FloatArray, FloatArray]],
                 budget: LengthBudget, scale: float, free: list[FittedEffect]) -> FloatArray:
    """Per bar, the variance of the noise in the mean :func:`_shape_constants` estimates,
    (6,) [m^2]: a quarter of the square of the difference between its estimates of the same
    mean (over all the runs' samples) from the first and from the second half of every run's
    samples (two estimates from half the data each differ by twice the noise of one, which is
    twice the whole's). 0 when a half of a run holds fewer than :data:`HALF_SAMPLES`."""
    if any(idx.size < 2 * HALF_SAMPLES for _run, idx, _dd, _ref in parts):
        return np.zeros(6)
    picks = _shape_picks(parts)
    target = [tuple(np.concatenate(v) for v in _shape_points(parts, picks, b)) for b in range(6)]
    means = []
    for half in (0, 1):
        cut = []
        for run, idx, dd, ref in parts:
            k = idx.size // 2
            keep = slice(None, k) if half == 0 else slice(k, None)
            cut.append((run, idx[keep], dd[keep], ref[keep]))
        means.append(_shape_constants(cut, budget, scale, free, target)[1])
    return 0.25 * (means[0] - means[1]) ** 2


def _most_likely(lam: FloatArray, z: FloatArray, floor: float, top: float) -> tuple[float, float]:
    """The factor a >= 1 on a Gaussian function's covariance and the noise variance s^2 in
    [floor, top] that make the data most likely, data and covariance in the covariance's
    eigenbasis (``z``, eigenvalues ``lam``): a residual with more of the function's shape
    than its prior allows (an error the calibration did not describe) widens it."""
    def minus_log_likelihood(log_s2: float, a: float) -> float:
        t = a * lam + math.exp(log_s2)
        return float(np.sum(np.log(t)) + np.sum(z * z / t))

    best = (math.inf, 1.0, floor)
    for a in np.geomspace(1.0, 1e4, 25):
        got = minimize_scalar(minus_log_likelihood, args=(float(a),), method='bounded',
                              bounds=(math.log(floor), math.log(top)), options={'xatol': 1e-3})
        if float(got.fun) < best[0]:
            best = (float(got.fun), float(a), math.exp(float(got.x)))
    return best[1], best[2]


def _dwell_means(parts: list[tuple[ResidualRun, IntArray, FloatArray, FloatArray]]) -> FloatArray:
    """Per bar, how far the mean of its error over a run moves with where the run dwelt,
    (6,) [m^2]: the variance of the bar-length residual's means over DWELL_BLOCKS consecutive
    blocks of each run, averaged over the runs by their samples. A constant error is the same
    in every block; an error of the lengths a run passed (a bump one run crossed often and
    another seldom) is not, and no variation within a run shows how much of it the next run's
    mean holds: claimed for a run as long as a block."""
    total, count = np.zeros(6), 0
    for _run, idx, dd, _ref in parts:
        if idx.size < 10 * DWELL_BLOCKS:
            continue
        means = np.array([b.mean(axis=0) for b in np.array_split(dd, DWELL_BLOCKS)])
        total += np.var(means, axis=0, ddof=1) * idx.size
        count += idx.size
    return total / count if count else np.zeros(6)


def _unexplained_mean(rest: list[FloatArray], lengths: list[FloatArray], weights: list[FloatArray]
                      ) -> float:
    """The variance of the mean over the runs of what a length-shaped function did not explain
    of a bar's residual, ``rest`` per run at the ``lengths`` with the ``weights`` of the mean:
    no variation shows it. Each run's mean square over its effective samples taken in the
    order of length (a residual of another shape, a bump, is one draw however often the bar
    passed it), its weight squared."""
    out = 0.0
    for r, x, wr in zip(rest, lengths, weights):
        order = np.argsort(x)
        out += float(np.sum(wr)) ** 2 * float(np.mean(r * r)) / max(_independent_samples(r[order]), 1.0)
    return out


def fitted_effects(sel: Any, chosen: list[tuple[Any, FloatArray]], found: list[Any],
                   run: Any, joint: list[FloatArray] | None = None) -> list[FittedEffect]:
    """The effects a model written for ``run`` applies, with the covariance of their
    parameters for its group (a selector of :mod:`mmd_ros.analysis.identify`); ``joint``:
    the parameters as fitted together with the run's own effects, where ``chosen``'s were
    fitted again without them."""
    out = []
    for k, ((a, theta), f) in enumerate(zip(chosen, found)):
        g = sel.group_index(a.effect, run)
        cov = getattr(f, 'covariance', None)
        if g is None or cov is None:
            continue
        n_p = theta.size // sel.n_groups(a.effect)
        part = slice(g * n_p, (g + 1) * n_p)
        shift = getattr(f, 'setting_shift', None)
        mine = np.asarray(theta)[part]
        both = None if joint is None else np.asarray(joint[k])[part]
        out.append(FittedEffect(a.effect, a.hyper, cov[part, part], mine,
                                None if shift is None else (shift[0], np.asarray(shift[1])[part]),
                                list(getattr(f, 'alternatives', [])),
                                None if both is None or np.array_equal(both, mine) else both))
    return out


def with_fit_uncertainty(model: Model, ctx: FitContext, found: list[FittedEffect],
                         runs: list[ResidualRun], *, unseen: bool = False,
                         growing: list[ModelTerm] | None = None,
                         residual_from: str | None = None) -> Model:
    """``model`` with its ``uncertainty.fit`` section measured by the fit (the overrides of the
    model it started from are kept); see :func:`fit_uncertainty`. ``residual_from`` replaces
    the record of where the residual comes from."""
    previous = model.uncertainty
    fit = fit_uncertainty(ctx, found, runs, model, unseen=unseen, growing=growing)
    if residual_from is not None:
        fit.record['residual_from'] = residual_from
    model.uncertainty = ModelUncertainty(previous.thermal_mismatch_fraction, previous.read_noise_m, fit)
    return model
