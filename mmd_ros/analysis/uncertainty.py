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
  (``mean_terms_nm2``, for a stage without counts);
- **the residual**: with a reference that determines every bar (a full pose, or bar lengths)
  the bar-length residual the fit left, J dp, has a covariance R over the held-out samples. The
  budget keeps its per-sample sources (quantisation, read noise, reference bar, thermal,
  fitted terms); what R holds beyond their mean over the same samples is the residual source
  (PSD part), and it replaces the calibration-derived systematic sources it measured
  (:data:`~mmd_ros.core.model.FIT_REPLACEABLE`). A reference that sees only some pose
  components cannot tell the bars apart: the calibration-derived sources stay, scaled by the
  factor k that makes the observed components' predicted variance match what was observed,
  never below 1 (what the reference did not see is not claimed better than before).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmd_ros.analysis.data import FitContext, Observation, Processed
from mmd_ros.core.budget import LengthBudget
from mmd_ros.core.kinematics import jacobian
from mmd_ros.core.model import FIT_REPLACEABLE, FitUncertainty, Model, ModelTerm, ModelUncertainty
from mmd_ros.core.uncertainty import pose_covariance

__all__ = ['MAX_DIRECTIONS', 'fit_uncertainty', 'with_fit_uncertainty']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Most principal directions of the fitted parameters evaluated per sample.
MAX_DIRECTIONS = 8
#: Share of the fitted terms' mean variance the per-sample directions must carry.
DIRECTION_SHARE = 0.99


def _term_directions(ctx: FitContext, found: list[Any], idx: IntArray
                     ) -> tuple[list[list[ModelTerm]], FloatArray]:
    """Principal directions of the fitted parameters as model terms, and the mean over the
    samples ``idx`` of S Sigma_theta S^T of all of them, (6, 6) [m^2]."""
    from mmd_ros.analysis.effects import catalogue

    candidates: list[tuple[float, list[ModelTerm]]] = []
    mean_total = np.zeros((6, 6))
    for f in found:
        cov = getattr(f, 'covariance', None)
        if cov is None or not np.any(cov):
            continue
        effect = catalogue([f.effect])[0]
        w, v = np.linalg.eigh(0.5 * (cov + cov.T))
        keep = w > max(float(w.max()), 0.0) * 1e-12
        if not keep.any():
            continue
        dirs = v[:, keep] * np.sqrt(w[keep])                      # (P, r): one sigma each
        sig = effect.signature(ctx, f.hyper, idx)                 # (n, 6, P)
        cols = sig @ dirs                                          # (n, 6, r)
        mean_total += np.einsum('nir,njr->ij', cols, cols) / max(idx.size, 1)
        size = np.mean(np.sum(cols * cols, axis=1), axis=0)       # mean |c_k|^2
        for k in range(dirs.shape[1]):
            candidates.append((float(size[k]), effect.make_terms(ctx, f.hyper, dirs[:, k])))
    candidates.sort(key=lambda c: -c[0])
    total = sum(c[0] for c in candidates)
    chosen: list[list[ModelTerm]] = []
    carried = 0.0
    for size, terms in candidates:
        if len(chosen) >= MAX_DIRECTIONS or (total > 0 and carried >= DIRECTION_SHARE * total):
            break
        chosen.append(terms)
        carried += size
    return chosen, mean_total


def _psd(matrix: FloatArray) -> FloatArray:
    w, v = np.linalg.eigh(0.5 * (matrix + matrix.T))
    return (v * np.maximum(w, 0.0)) @ v.T


def fit_uncertainty(ctx: FitContext, found: list[Any], after: Processed, residual: FloatArray,
                    idx: IntArray, model: Model, *, unseen: bool = False) -> FitUncertainty:
    """The ``uncertainty.fit`` section of the model a fit writes (see the module docstring).

    ctx : the fit's context (device, calibration, run)
    found : the effects added, each with ``covariance`` (P, P) of its parameters [SI]
    after : the pipeline with the extended model over the whole run
    residual : (N, k) the residual after the fit in the observation space [m, rad] (NaN where
        not usable; a zeroed reference's offsets removed)
    idx : samples to judge on (the held-out ones)
    model : the extended model (its terms; its uncertainty section is not used)
    unseen : the residual comes from data the fit never saw (other runs: leave-one-run-out).
        Only then may it replace the calibration-derived sources: blocks of the fitted run
        interleave with the training blocks and show how well the model fits that run, not
        how it does on another motion, so otherwise the calibration-derived sources stay and
        the residual adds only what exceeds them
    """
    obs: Observation = ctx.obs
    idx = idx[np.all(np.isfinite(residual[idx]), axis=1) & after.measured(obs.kind)[idx]]
    directions, mean_terms = _term_directions(ctx, found, idx)
    fit = FitUncertainty(np.zeros((6, 6)), (), 1.0, directions, mean_terms,
                         {'samples': int(idx.size), 'reference': obs.description})
    if idx.size < 10:
        fit.record['note'] = 'too few usable samples to measure the residual'
        return fit
    # the budget of the extended model with the fitted terms' uncertainty and no residual yet
    trial = Model(model.thermal_mode, model.plate_expansion, None, list(model.terms), {},
                  model.source, ModelUncertainty(fit=fit))
    budget = LengthBudget(ctx.device, ctx.calibration, trial)
    observed = budget.observe(after.cdf_lengths_m, after.reference_error_m)
    cov, bias = budget.sources(after.lengths_m[idx], after.reference_error_m[idx],
                               after.temp_change_c[idx], after.bar_error_m[idx], None, observed[idx])
    zero = np.zeros((idx.size, 6, 6))
    kept = sum((np.asarray(c) for name, c in cov.items() if name not in FIT_REPLACEABLE), zero)
    replaceable = sum((np.asarray(c) for name, c in cov.items() if name in FIT_REPLACEABLE), zero)
    for group, names in ((True, [k for k in bias if k not in FIT_REPLACEABLE]),
                         (False, [k for k in bias if k in FIT_REPLACEABLE])):
        if names:
            b = sum(bias[k] for k in names)
            if group:
                kept = kept + b[:, :, None] * b[:, None, :]
            else:
                replaceable = replaceable + b[:, :, None] * b[:, None, :]
    r = residual[idx]
    if obs.kind == 'lengths' or len(obs.components) == 6:
        if obs.kind == 'pose':
            jac = jacobian(ctx.device.geometry, after.poses[idx])
            dd = np.einsum('nij,nj->ni', jac, r)
        else:
            dd = np.zeros((idx.size, 6))
            dd[:, obs.components] = r
        observed_cov = dd.T @ dd / idx.size
        predicted = np.mean(kept if unseen else kept + replaceable, axis=0)
        excess = _psd(observed_cov - predicted)
        if obs.kind == 'lengths' and len(obs.components) < 6:
            unseen = [i for i in range(6) if i not in obs.components]
            excess[unseen, :] = 0.0
            excess[:, unseen] = 0.0
            fit.residual_m2 = excess
            fit.record['note'] = ('bars without a reference keep the calibration-derived sources')
            return fit
        fit.residual_m2 = excess
        fit.replaces = tuple(FIT_REPLACEABLE) if unseen else ()
        fit.record['residual_from'] = 'runs the fit did not see' if unseen else 'held-out blocks of the fitted run'
        fit.record['residual_rms_nm'] = [round(float(math.sqrt(max(v, 0.0))) * 1e9, 3)
                                         for v in np.diag(observed_cov)]
        return fit
    # some pose components: scale what the reference cannot attribute to bars
    jinv = np.linalg.inv(jacobian(ctx.device.geometry, after.poses[idx]))
    comp = obs.components
    kept_p = np.mean(np.diagonal(pose_covariance(jinv, kept, after.plate_scale[idx]), axis1=1,
                                 axis2=2)[:, comp], axis=0)
    repl_p = np.mean(np.diagonal(pose_covariance(jinv, replaceable, after.plate_scale[idx]),
                                 axis1=1, axis2=2)[:, comp], axis=0)
    seen = np.mean(r * r, axis=0)
    scale = float(np.sum((seen - kept_p) * repl_p) / np.sum(repl_p * repl_p)) if np.any(repl_p > 0) else 1.0
    fit.systematic_scale = max(scale, 1.0)
    fit.record['observed_components'] = list(obs.names)
    fit.record['scale_estimate'] = round(scale, 4)
    return fit


def with_fit_uncertainty(model: Model, ctx: FitContext, found: list[Any], after: Processed,
                         residual: FloatArray, idx: IntArray, *, unseen: bool = False) -> Model:
    """``model`` with its ``uncertainty.fit`` section measured by the fit (the overrides of the
    model it started from are kept); ``unseen`` as :func:`fit_uncertainty`."""
    previous = ctx.model.uncertainty
    model.uncertainty = ModelUncertainty(
        previous.thermal_mismatch_fraction, previous.read_noise_m,
        fit_uncertainty(ctx, found, after, residual, idx, model, unseen=unseen))
    return model
