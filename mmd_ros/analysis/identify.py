"""Close the loop: find the residual, trace it to an effect the model lacks, add the effect and
measure the error before and after (documented for users in msg_docs/analysis.md).

1. Residual. The current model runs over the whole log (the live pipeline); the residual is MMD
   minus reference in the reference's observation space (:mod:`mmd_ros.analysis.data`).
2. Trace. The usable samples are cut into time blocks; of each pair of blocks one (drawn) is
   held out. Each catalogued effect (:mod:`mmd_ros.analysis.effects`) is linear in its
   parameters: its length signature is mapped into the observation space with the pose
   Jacobian (J^-1, only the known components) and weighted by the noise floor. Its columns are
   projected off what is already in the model (datum offsets, effects added before); directions
   with a singular value below ``rcond`` (unit-norm columns) cannot be separated, directions
   whose estimate is below ``min_t_param`` standard deviations are not determined by the data:
   both are reported, not fitted. Least squares on the training blocks; judged on the held-out
   blocks. Stepwise: an effect passes when it lowers the held-out RMS by at least ``min_gain``
   (and ``min_floor_gain`` of the noise floor), the gain is consistent over the held-out blocks
   (t >= ``min_t``) and the held-out information criterion IC = N_eff ln(MSE) + p ln(N_eff)
   falls by at least ``min_delta_ic`` (N_eff: effective number of independent samples of the
   autocorrelated residual). Of those that pass, the one with the fewest identified parameters
   that removes at least ``parsimony`` of what the best removes is added.
3. Add. The effects found become model terms with the fitted parameters; the extended model is
   validated by running the real pipeline again over the log (the "after" numbers).
4. Claims. An added effect must remove at least 1 - ``claim_ratio`` of the structure along its
   own coordinate (variance explained by bin means of its diagnostic feature, with and without
   it); one that fits only part of a structure is not claimed and not kept. If the held-out
   residual stays above the noise floor, the features it follows are listed.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from mmd_ros.analysis.data import (
    FitContext, Observation, Processed, Split, binned_r2, effective_samples, make_observation,
    make_split, noise_floor, residual_features, run_pipeline,
)
from mmd_ros.analysis.effects import Effect, Parameter, catalogue
from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.uncertainty import with_fit_uncertainty
from mmd_ros.core.calibration import Calibration
from mmd_ros.core.kinematics import jacobian
from mmd_ros.core.model import Model, ModelTerm
from mmd_ros.logs.layout import RunLog

__all__ = ['Analysis', 'AnalysisOptions', 'Candidate', 'ComponentError', 'Found', 'analyze',
           'component_errors']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class AnalysisOptions:
    """Settings of :func:`analyze` (defaults documented in msg_docs/analysis.md)."""

    effects: list[str] | None = None
    exclude: tuple[str, ...] = ()
    n_blocks: int = 40
    max_samples: int = 2500
    min_gain: float = 0.05
    min_floor_gain: float = 0.1
    min_t: float = 3.0
    min_delta_ic: float = 10.0
    max_effects: int = 4
    rcond: float = 1e-3
    min_t_param: float = 2.0
    parsimony: float = 0.9
    floor_factor: float = 1.5
    claim_ratio: float = 0.35
    datum: str = 'auto'
    seed: int = 0
    cyclic_periods_m: tuple[float, ...] | None = None


@dataclass
class Candidate:
    """One effect tested at one step of the selection."""

    effect: str
    title: str
    hyper: Any
    hyper_label: str
    n_params: int
    n_identifiable: int
    unidentifiable: list[str]
    note: str
    rms_ratio: float = math.nan      # held-out RMS with the effect / without (whitened)
    gain: float = math.nan           # 1 - rms_ratio
    delta_ic: float = math.nan
    t_stat: float = math.nan
    n_eff: float = math.nan
    verdict: str = ''
    mse0: float = math.nan           # held-out mean square (whitened) before / with the effect
    mse1: float = math.nan
    basis: FloatArray | None = field(default=None, repr=False)  # (P, r): reduced -> parameters

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items() if k not in ('basis', 'hyper')}
        out['hyper'] = self.hyper
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in out.items()}


@dataclass
class Found:
    """An effect added to the model, with its fitted parameters."""

    effect: str
    title: str
    term_type: str
    hyper: Any
    hyper_label: str
    parameters: list[Parameter]
    value: FloatArray
    sigma: FloatArray
    identifiable: NDArray[np.bool_]
    step_gain: float
    interpretation: list[str]
    explained: float = math.nan
    claimed: bool = True
    reason: str = ''
    covariance: FloatArray | None = None  # (P, P) of the parameters [SI]

    def parameter_rows(self) -> list[dict[str, Any]]:
        rows = []
        for p, v, s, ok in zip(self.parameters, self.value, self.sigma, self.identifiable):
            rows.append({'name': p.name, 'unit': p.unit, 'value': float(v * p.factor),
                         'ci95': float(1.96 * s * abs(p.factor)) if ok else None,
                         'identifiable': bool(ok)})
        return rows

    def as_dict(self) -> dict[str, Any]:
        return {'effect': self.effect, 'title': self.title, 'term': self.term_type,
                'hyper': self.hyper_label, 'parameters': self.parameter_rows(),
                'held_out_gain_at_step': self.step_gain, 'explained': self.explained,
                'claimed': self.claimed, 'reason': self.reason, 'interpretation': self.interpretation}


@dataclass(frozen=True)
class ComponentError:
    """Error statistics of one observed component on some samples, in report units."""

    name: str
    unit: str
    n: int
    rms: float
    max_abs: float
    mean: float
    std: float

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def component_errors(obs: Observation, residual: FloatArray, idx: IntArray) -> list[ComponentError]:
    """Per-component and overall (per unit) statistics of ``residual`` at samples ``idx``."""
    r = residual[idx] * obs.to_report
    out = []
    for k, (name, unit) in enumerate(zip(obs.names, obs.units)):
        v = r[:, k][np.isfinite(r[:, k])]
        if v.size:
            out.append(ComponentError(name, unit, int(v.size), float(np.sqrt(np.mean(v * v))),
                                      float(np.max(np.abs(v))), float(v.mean()), float(v.std())))
    for unit in sorted(set(obs.units)):
        cols = [k for k, u in enumerate(obs.units) if u == unit]
        if len(cols) > 1:
            v = r[:, cols]
            v = v[np.all(np.isfinite(v), axis=1)]
            out.append(ComponentError(f'overall ({unit})', unit, int(v.size),
                                      float(np.sqrt(np.mean(v * v))), float(np.max(np.abs(v))),
                                      float(v.mean()), float(v.std())))
    return out


@dataclass
class Analysis:
    """Everything :func:`analyze` found; :mod:`mmd_ros.analysis.report` writes it out."""

    log: str
    options: AnalysisOptions
    obs: Observation
    split: Split
    times_s: FloatArray
    floor: FloatArray
    before: Processed
    after: Processed | None
    residual_before: FloatArray
    residual_after: FloatArray | None
    steps: list[list[Candidate]]
    found: list[Found]
    not_claimed: list[Found]
    stats_before: list[ComponentError]
    stats_after: list[ComponentError] | None
    stats_predicted: list[ComponentError] | None
    structure_before: list[tuple[str, float]]
    structure_after: list[tuple[str, float]]
    at_floor: bool
    validated: bool
    model: Model | None
    conclusion: str
    features: dict[str, FloatArray] = field(repr=False, default_factory=dict)
    contributions: dict[str, FloatArray] = field(repr=False, default_factory=dict)
    per_bar_before: list[ComponentError] | None = None
    per_bar_after: list[ComponentError] | None = None
    seconds: float = 0.0
    not_applicable: dict[str, str] = field(default_factory=dict)
    log_problem: dict[str, Any] | None = None  # what was lost reading the log (LogProblem.as_dict)

    @property
    def changed(self) -> bool:
        return self.model is not None

    def as_dict(self) -> dict[str, Any]:
        floor = {n: float(f * s) for n, f, s in zip(self.obs.names, self.floor, self.obs.to_report)}
        return {
            'log': self.log,
            'reference': {'kind': self.obs.kind, 'components': self.obs.names,
                          'units': self.obs.units, 'datum_offset_removed': self.obs.datum,
                          'description': self.obs.description},
            'samples': {'total': int(self.times_s.size),
                        'usable': int(self.split.train_idx.size + self.split.test_idx.size),
                        'train': int(self.split.train_idx.size), 'held_out': int(self.split.test_idx.size),
                        'blocks': self.split.n_blocks},
            'noise_floor': floor,
            'before': [s.as_dict() for s in self.stats_before],
            'before_per_bar': [s.as_dict() for s in self.per_bar_before] if self.per_bar_before else None,
            'structure_before': [{'feature': f, 'r2': r} for f, r in self.structure_before],
            'steps': [[c.as_dict() for c in step] for step in self.steps],
            'not_applicable': self.not_applicable,
            'found': [f.as_dict() for f in self.found],
            'not_claimed': [f.as_dict() for f in self.not_claimed],
            'after': [s.as_dict() for s in self.stats_after] if self.stats_after else None,
            'after_per_bar': [s.as_dict() for s in self.per_bar_after] if self.per_bar_after else None,
            'predicted_after': [s.as_dict() for s in self.stats_predicted] if self.stats_predicted else None,
            'validated_with_pipeline': self.validated,
            'remaining': {'at_noise_floor': self.at_floor,
                          'structure': [{'feature': f, 'r2': r} for f, r in self.structure_after]},
            'model_changed': self.changed,
            'conclusion': self.conclusion,
            'seconds': self.seconds,
            'options': {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.options.__dict__.items()},
            'log_problem': self.log_problem,
        }


# -- observation rows --------------------------------------------------------------------------
class _Rows:
    """Weighted observation rows of a set of samples: y (m,), nuisance (m, q), blocks (m,)."""

    def __init__(self, ctx: FitContext, idx: IntArray, residual: FloatArray, weights: FloatArray,
                 block: IntArray) -> None:
        self.ctx, self.idx, self.w = ctx, idx, weights
        obs = ctx.obs
        k = len(obs.components)
        self.k = k
        self.jinv = None
        if obs.kind == 'pose':
            jac = jacobian(ctx.device.geometry, ctx.base.poses[idx])
            self.jinv = np.linalg.inv(jac)[:, obs.components, :]  # (n, k, 6)
        self.y = (-residual[idx] * weights).reshape(-1)
        self.blocks = np.repeat(block[idx], k)
        if obs.datum:
            nuis = np.zeros((idx.size, k, k))
            nuis[:, np.arange(k), np.arange(k)] = weights
            self.nuisance = nuis.reshape(-1, k)
        else:
            self.nuisance = np.zeros((idx.size * k, 0))

    def project(self, cols: FloatArray) -> FloatArray:
        """Length-space columns (n, 6, P) to weighted observation columns (n k, P)."""
        if self.jinv is not None:
            obs = np.einsum('nkj,njp->nkp', self.jinv, cols)
        else:
            obs = cols[:, self.ctx.obs.components, :]
        obs = obs * self.w[None, :, None]
        return obs.reshape(-1, cols.shape[2])


def _orthonormal(b: FloatArray) -> FloatArray:
    """Orthonormal basis of the column space of ``b``: columns scaled to unit norm, then the
    eigenvectors of the (small) Gram matrix; directions with eigenvalue below 1e-12 of the
    largest are dropped. Matrix products only: fast for tall matrices."""
    if b.shape[1] == 0:
        return b
    norms = np.linalg.norm(b, axis=0)
    b = b[:, norms > 0] / norms[norms > 0]
    w, v = np.linalg.eigh(b.T @ b)
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    return (b @ v[:, keep]) / np.sqrt(w[keep])


@dataclass
class _Active:
    effect: Effect
    hyper: Any
    basis: FloatArray  # (P, r)
    step_gain: float
    explained: float = math.nan  # share of the initial held-out mean square it removed


class _Selector:
    """Stepwise selection on the fit subsets of the training and held-out blocks."""

    def __init__(self, ctx: FitContext, split: Split, residual: FloatArray, floor: FloatArray,
                 options: AnalysisOptions) -> None:
        self.ctx, self.options = ctx, options
        w = 1.0 / floor
        self.train = _Rows(ctx, split.fit_train, residual, w, split.block)
        self.test = _Rows(ctx, split.fit_test, residual, w, split.block)
        self.active: list[_Active] = []
        self._sig: dict[tuple[str, Any, str], FloatArray] = {}
        self._base: dict[str, FloatArray] = {}
        self._base_key: dict[str, Any] = {}
        self._base_q: dict[str, FloatArray] = {}
        self._step: dict[str, Any] = {}

    def columns(self, effect: Effect, hyper: Any, part: str) -> FloatArray:
        key = (effect.name, hyper, part)
        if key not in self._sig:
            rows = self.train if part == 'train' else self.test
            self._sig[key] = rows.project(effect.signature(self.ctx, hyper, rows.idx))
        return self._sig[key]

    def base(self, part: str) -> FloatArray:
        key = (part, tuple((a.effect.name, a.hyper, a.basis.shape) for a in self.active))
        if self._base_key.get(part) != key:
            rows = self.train if part == 'train' else self.test
            blocks = [rows.nuisance] + [self.columns(a.effect, a.hyper, part) @ a.basis for a in self.active]
            self._base[part] = np.concatenate(blocks, axis=1)
            self._base_key[part] = key
            self._base_q.pop(part, None)
        return self._base[part]

    def base_q(self) -> FloatArray:
        """Orthonormal basis of the training base columns (cached per active set)."""
        b = self.base('train')
        if 'train' not in self._base_q:
            self._base_q['train'] = _orthonormal(b)
        return self._base_q['train']

    def _fit(self, d: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Coefficients and their covariance (residual variance inflated for the
        autocorrelation of the residual: m / N_eff). Columns are scaled to unit norm (the datum
        columns and the effects' columns differ by orders of magnitude), then QR."""
        m, p = d.shape
        if p == 0:
            return np.zeros(0), np.zeros((0, 0))
        norms = np.linalg.norm(d, axis=0)
        norms[norms == 0] = 1.0
        dn = d / norms
        gram_inv = np.linalg.pinv(dn.T @ dn, rcond=1e-13, hermitian=True)
        coef = gram_inv @ (dn.T @ y) / norms
        e = y - d @ coef
        sigma2 = float(e @ e) / max(m - p, 1)
        inflation = max(m / effective_samples(e.reshape(-1, self.train.k)), 1.0)
        return coef, gram_inv / np.outer(norms, norms) * sigma2 * inflation

    def _step_basis(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Of the current base columns B (training): orthonormal basis Q, T = Q^T B, the
        training target projected off B (y_p) and Q^T y (cached per active set)."""
        q = self.base_q()
        key = self._base_key.get('train')
        if self._step.get('key') != key:
            y = self.train.y
            qy = q.T @ y
            self._step = {'key': key, 'T': q.T @ self.base('train'), 'qy': qy, 'yp': y - q @ qy}
        return q, self._step['T'], self._step['yp'], self._step['qy']

    def baseline(self) -> tuple[FloatArray, FloatArray]:
        q, t, yp, qy = self._step_basis()
        coef_b = np.linalg.lstsq(t, qy, rcond=None)[0] if t.size else np.zeros(0)
        return yp, self.test.y - self.base('test') @ coef_b

    def _reduce(self, effect: Effect, hyper: Any) -> dict[str, Any]:
        """Fit of one candidate at one hyperparameter, in the directions the data identify.

        The candidate's unit-norm columns Cn are projected off the base B (Cp); the SVD
        Cp = U S V^T gives its distinct directions. Directions with s <= rcond are structurally
        unidentifiable; of the others, those whose estimate is below min_t_param standard
        deviations are not determined by the data. Both are reported, not fitted. With
        R = Cn V the coefficients are beta_j = u_j^T y_p / s_j.
        """
        names = [p.name for p in effect.parameters(self.ctx, hyper)]
        avail, note = effect.coverage(self.ctx, hyper, self.train.idx)
        c = self.columns(effect, hyper, 'train')
        norms = np.linalg.norm(c, axis=0)
        usable = avail & (norms > 0)
        lost = [f'{names[j]} (not exercised)' for j in np.flatnonzero(~usable)]
        out: dict[str, Any] = {'names': names, 'lost': lost, 'note': note,
                               'basis': np.zeros((len(names), 0))}
        if not usable.any():
            return out
        q, t, yp, qy = self._step_basis()
        cn = c[:, usable] / norms[usable]
        qtc = q.T @ cn if q.shape[1] else np.zeros((0, cn.shape[1]))
        cp = cn - q @ qtc if q.shape[1] else cn
        # SVD of Cp through its Gram matrix (P x P): Cp = U S V^T with V, S^2 from eigh
        w, vecs = np.linalg.eigh(cp.T @ cp)
        order = np.argsort(w)[::-1]
        w, vecs = np.maximum(w[order], 0.0), vecs[:, order]
        sv = np.sqrt(w)
        keep = sv > self.options.rcond
        vt = vecs.T
        sub = [names[j] for j in np.flatnonzero(usable)]
        dropped = vt[~keep]
        for row in dropped[:3]:
            top = np.argsort(-np.abs(row))[:3]
            lost.append('direction ' + ' '.join(f'{row[k]:+.2f}·{sub[k]}' for k in top))
        if dropped.shape[0] > 3:
            lost.append(f'… and {dropped.shape[0] - 3} more directions')
        sv, vt = sv[keep], vt[keep]
        cpv = cp @ vt.T                      # = U S
        proj = (cpv.T @ yp) / sv              # = U^T y_p
        beta = proj / sv
        e = yp - cpv @ beta
        m = yp.size
        dof = max(m - q.shape[1] - sv.size, 1)
        inflation = max(m / effective_samples(e.reshape(-1, self.train.k)), 1.0)
        sd = np.sqrt(float(e @ e) / dof * inflation) / sv
        weak = np.abs(beta) < self.options.min_t_param * sd
        if weak.any():
            lost.append(f'{int(weak.sum())} directions not determined by the data '
                        f'(|estimate| < {self.options.min_t_param:g} σ)')
        # a direction that needs physically implausible parameter values is not identified
        # either (it would corrupt what the reference does not observe)
        bounds = np.array([p.bound for p in effect.parameters(self.ctx, hyper)])[usable]
        size = np.abs(vt.T * (beta / 1.0)[None, :]) / norms[usable, None]   # (P_usable, r)
        wild = np.any(size > bounds[:, None], axis=0) & ~weak
        if wild.any():
            lost.append(f'{int(wild.sum())} directions that would need implausible values '
                        '(beyond the physical bounds of their parameters)')
        drop = weak | wild
        if drop.any():
            e = e + cpv[:, drop] @ beta[drop]
            sv, vt, beta = sv[~drop], vt[~drop], beta[~drop]
        v = vt.T
        basis = np.zeros((len(names), v.shape[1]))
        basis[usable] = v / norms[usable, None]
        coef_b = (np.linalg.lstsq(t, qy - qtc @ v @ beta, rcond=None)[0] if t.size else np.zeros(0))
        out.update(basis=basis, beta=beta, e_train=e, coef_b=coef_b)
        return out

    def evaluate(self, effect: Effect, e0_test: FloatArray) -> Candidate:
        best: Candidate | None = None
        best_ic = math.inf
        for hyper in effect.hypers(self.ctx):
            fit = self._reduce(effect, hyper)
            basis = fit['basis']
            cand = Candidate(effect.name, effect.title, hyper, effect.hyper_label(hyper),
                             len(fit['names']), basis.shape[1], fit['lost'], fit['note'], basis=basis)
            if basis.shape[1] == 0:
                cand.verdict = 'unidentifiable'
                if best is None:
                    best = cand
                continue
            e_tr = fit['e_train']
            n_tr = effective_samples(e_tr.reshape(-1, self.train.k))
            ic = n_tr * math.log(max(float(np.mean(e_tr ** 2)), 1e-300)) + basis.shape[1] * math.log(n_tr)
            if ic < best_ic:
                pred = self.columns(effect, hyper, 'test') @ (basis @ fit['beta'])
                if fit['coef_b'].size:
                    pred = pred + self.base('test') @ fit['coef_b']
                cand._e_test = self.test.y - pred  # type: ignore[attr-defined]
                best, best_ic = cand, ic
        assert best is not None
        if best.verdict == 'unidentifiable':
            return best
        e1 = best._e_test  # type: ignore[attr-defined]
        mse0, mse1 = float(np.mean(e0_test ** 2)), float(np.mean(e1 ** 2))
        best.mse0, best.mse1 = mse0, mse1
        best.rms_ratio = math.sqrt(mse1 / mse0) if mse0 > 0 else 1.0
        best.gain = 1.0 - best.rms_ratio
        n_eff = effective_samples(e1.reshape(-1, self.test.k))
        best.n_eff = n_eff
        best.delta_ic = n_eff * math.log(max(mse1, 1e-300) / max(mse0, 1e-300)) + best.n_identifiable * math.log(n_eff)
        blocks = self.test.blocks
        ids = np.unique(blocks)
        per = np.array([np.mean(e0_test[blocks == b] ** 2 - e1[blocks == b] ** 2) for b in ids])
        if per.size > 1 and per.std(ddof=1) > 0:
            best.t_stat = float(per.mean() / (per.std(ddof=1) / math.sqrt(per.size)))
        else:
            best.t_stat = math.inf if per.mean() > 0 else 0.0
        o = self.options
        floor_gain = math.sqrt(mse0) - math.sqrt(mse1)
        if best.gain >= o.min_gain and floor_gain >= o.min_floor_gain and best.t_stat >= o.min_t \
                and best.delta_ic <= -o.min_delta_ic:
            best.verdict = 'significant'
        else:
            reasons = []
            if best.gain < o.min_gain:
                reasons.append(f'gain {100 * best.gain:.1f} % < {100 * o.min_gain:g} %')
            elif floor_gain < o.min_floor_gain:
                reasons.append(f'RMS falls by {floor_gain:.2f} < {o.min_floor_gain:g} of the noise floor')
            if best.t_stat < o.min_t:
                reasons.append(f't {best.t_stat:.1f} < {o.min_t:g}')
            if best.delta_ic > -o.min_delta_ic:
                reasons.append(f'ΔIC {best.delta_ic:.0f} > -{o.min_delta_ic:g}')
            best.verdict = 'not significant (' + ', '.join(reasons) + ')'
        return best

    def refine(self) -> None:
        """Re-choose the hyperparameters (and identified directions) of each active effect with
        the others in place: a setting chosen before a later effect was added may no longer be
        the best (backfitting, one pass)."""
        for k in range(len(self.active)):
            a = self.active[k]
            if len(a.effect.hypers(self.ctx)) < 2:
                continue
            others = self.active[:k] + self.active[k + 1:]
            self.active = others
            best, best_ic = None, math.inf
            for hyper in a.effect.hypers(self.ctx):
                fit = self._reduce(a.effect, hyper)
                if fit['basis'].shape[1] == 0:
                    continue
                e_tr = fit['e_train']
                n_tr = effective_samples(e_tr.reshape(-1, self.train.k))
                ic = n_tr * math.log(max(float(np.mean(e_tr ** 2)), 1e-300)) + fit['basis'].shape[1] * math.log(n_tr)
                if ic < best_ic:
                    best, best_ic = (hyper, fit['basis']), ic
            if best is not None:
                a = _Active(a.effect, best[0], best[1], a.step_gain, a.explained)
            self.active = others[:k] + [a] + others[k:]

    def own_structure_ratio(self, active: _Active, theta: FloatArray, e_pred: FloatArray
                            ) -> tuple[float, str]:
        """How much of the structure along the effect's own coordinate is left when it is in
        the model, relative to when it is not: V_with / V_without on the held-out fit samples,
        V the variance explained by bin means of the feature (the effect's diagnostic feature
        that carries most structure without it)."""
        contrib = self.columns(active.effect, active.hyper, 'test') @ theta
        k = self.test.k
        with_e = e_pred.reshape(-1, k)
        without = (e_pred + contrib).reshape(-1, k)
        tot_with = float(np.sum((with_e - with_e.mean(axis=0)) ** 2))
        tot_without = float(np.sum((without - without.mean(axis=0)) ** 2))
        best = (0.0, '', 0.0)
        for name, values in active.effect.diagnostics(self.ctx, active.hyper).items():
            f = values[self.test.idx]
            v_without = binned_r2(without, f) * tot_without
            if v_without > best[0]:
                best = (v_without, name, binned_r2(with_e, f) * tot_with)
        if best[0] <= 0:
            return 0.0, ''
        return best[2] / best[0], best[1]

    def final_fit(self) -> tuple[list[tuple[FloatArray, FloatArray]], FloatArray]:
        """Joint fit of all active effects: (theta, sigma) per effect, and the held-out
        weighted residual predicted by the linearised model."""
        d_tr = self.base('train')
        d_te = self.base('test')
        coef, cov = self._fit(d_tr, self.train.y)
        out = []
        start = self.train.nuisance.shape[1]
        for a in self.active:
            r = a.basis.shape[1]
            beta = coef[start:start + r]
            cb = cov[start:start + r, start:start + r]
            theta = a.basis @ beta
            sig = np.sqrt(np.maximum(np.einsum('pr,rs,ps->p', a.basis, cb, a.basis), 0.0))
            out.append((theta, sig, a.basis @ cb @ a.basis.T))
            start += r
        return out, self.test.y - d_te @ coef


# -- the analysis ------------------------------------------------------------------------------
def _datum_corrected(obs: Observation, residual: FloatArray, valid: NDArray[np.bool_],
                     train_idx: IntArray) -> FloatArray:
    """Residual with NaN where not usable and, for a zeroed reference, its training-part mean
    per component removed."""
    r = residual.copy()
    r[~(valid & obs.usable)] = np.nan
    if obs.datum:
        known = r[train_idx]
        known = known[np.all(np.isfinite(known), axis=1)]
        r = r - (known.mean(axis=0) if known.size else 0.0)
    return r


def _build_model(model: Model, ctx: FitContext, chosen: list[tuple[Effect, Any, FloatArray]],
                 record: dict[str, Any] | None) -> Model:
    terms: list[ModelTerm] = [*model.terms]
    for effect, hyper, theta in chosen:
        terms.extend(effect.make_terms(ctx, hyper, theta))
    extra = dict(model.extra)
    if record is not None:
        history = list(extra.get('analysis') or []) if isinstance(extra.get('analysis'), list) else []
        history.append(record)
        extra['analysis'] = history
    return Model(model.thermal_mode, model.plate_expansion, model.length_sigma_m, terms, extra,
                 '<extended model>')


def analyze(run: RunLog, model: Model | None = None, calibration: Calibration | None = None,
            options: AnalysisOptions | None = None,
            progress: Callable[[str], None] | None = None) -> Analysis:
    """Close the loop on one log (see the module docstring).

    run : a log in our layout with raw counts and a reference (pose components or bar lengths)
    model : the current model; default the log's, else CDF + thermal
    calibration : default the log's
    progress : called with a line of text at each stage (for stderr)
    """
    # Many mid-size matrix products: on shared cores, multi-threaded BLAS waits for cores and
    # runs them 5-10x slower than one thread (measured: 33 s against 264 s for the tests).
    with threadpool_limits(limits=1, user_api='blas'):
        return _analyze(run, model, calibration, options, progress)


def _analyze(run: RunLog, model: Model | None, calibration: Calibration | None,
             options: AnalysisOptions | None, progress: Callable[[str], None] | None) -> Analysis:
    started = time.perf_counter()
    o = options or AnalysisOptions()
    say = progress or (lambda text: None)
    model = model or run.model or Model()
    calibration = calibration or run.calibration
    if calibration is None:
        raise AnalysisError(f'{run.path} carries no calibration; pass --calibration FILE')
    if run.counts.shape[0] == 0:
        raise AnalysisError(f'{run.path} has no samples')
    obs = make_observation(run.reference_pose, run.reference_lengths, o.datum)
    times = run.times_s
    say(f'running the current model over {times.size} samples')
    before = run_pipeline(run.device, calibration, model, times, run.counts)
    usable = obs.usable & before.measured(obs.kind)
    split = make_split(times, usable, o.n_blocks, o.max_samples, o.seed)
    ctx = FitContext(run.device, calibration, model, times, run.counts, before, obs, o)
    raw = obs.residual(before)
    res_before = _datum_corrected(obs, raw, before.measured(obs.kind), split.train_idx)
    floor = noise_floor(obs, run.device, before, np.nan_to_num(res_before), split.train_idx, ctx.thermal_on)
    floor = np.maximum(floor, 1e-12)
    features = residual_features(ctx)
    structure_before = _structure(res_before / floor, split.fit_test, features)

    # -- trace: stepwise selection on the linearised model
    effects = [e for e in catalogue(o.effects) if e.name not in o.exclude]
    not_applicable = {e.name: e.applicable(ctx) for e in effects if e.applicable(ctx)}
    effects = [e for e in effects if e.name not in not_applicable]
    sel = _Selector(ctx, split, np.nan_to_num(raw), floor, o)
    steps: list[list[Candidate]] = []
    while len(sel.active) < o.max_effects:
        remaining = [e for e in effects if e.name not in {a.effect.name for a in sel.active}]
        if not remaining:
            break
        say(f'step {len(steps) + 1}: testing {len(remaining)} effects')
        _, e0 = sel.baseline()
        cands = [sel.evaluate(e, e0) for e in remaining]
        cands.sort(key=lambda c: (c.verdict != 'significant', c.delta_ic if math.isfinite(c.delta_ic) else math.inf))
        steps.append(cands)
        significant = [c for c in cands if c.verdict == 'significant']
        if not significant:
            break
        # parsimony: the effect with the fewest identifiable parameters that removes nearly as
        # much of the held-out mean square as the best one
        most = max(c.mse0 - c.mse1 for c in significant)
        best = min((c for c in significant if c.mse0 - c.mse1 >= o.parsimony * most),
                   key=lambda c: (c.n_identifiable, c.delta_ic))
        cands.remove(best)
        cands.insert(0, best)
        best.verdict = 'added'
        eff = next(e for e in effects if e.name == best.effect)
        initial = steps[0][0].mse0 if steps[0] else math.nan
        sel.active.append(_Active(eff, best.hyper, best.basis, best.gain,
                                  (best.mse0 - best.mse1) / initial if initial > 0 else math.nan))
        if len(sel.active) > 1:
            sel.refine()

    # -- add, validate with the pipeline, check what remains; drop effects not explaining
    found: list[Found] = []
    not_claimed: list[Found] = []
    after = res_after = stats_after = stats_pred = None
    per_bar_after = None
    at_floor = False
    validated = False
    extended: Model | None = None
    structure_after: list[tuple[str, float]] = []
    contributions: dict[str, FloatArray] = {}
    for _ in range(o.max_effects + 1):
        if not sel.active:
            break
        fits, e_pred = sel.final_fit()
        current = []
        for a, (theta, sigma, cov_theta) in zip(sel.active, fits):
            params = a.effect.parameters(ctx, a.hyper)
            ident = np.linalg.norm(a.basis, axis=1) > 0
            current.append(Found(a.effect.name, a.effect.title, a.effect.term_type, a.hyper,
                                 a.effect.hyper_label(a.hyper), params, theta, sigma, ident,
                                 a.step_gain, a.effect.interpret(ctx, a.hyper, theta, sigma),
                                 covariance=cov_theta))
        # an effect must remove most of the structure along its own coordinate; one that fits
        # only part of it follows something else (the worst is dropped, then all are refitted)
        worst_k, worst_ratio, worst_txt = -1, 0.0, ''
        for k, (a, f) in enumerate(zip(sel.active, current)):
            ratio, feature = sel.own_structure_ratio(a, f.value, e_pred)
            f.reason = feature
            if ratio > o.claim_ratio and ratio > worst_ratio:
                worst_k, worst_ratio = k, ratio
                worst_txt = (f'{100 * (1 - ratio):.0f} % of the structure along its own coordinate '
                             f'({feature}) removed, less than {100 * (1 - o.claim_ratio):.0f} %: it '
                             'follows part of something else')
        if worst_k >= 0:
            f = current[worst_k]
            f.claimed, f.reason = False, worst_txt
            not_claimed.append(f)
            del sel.active[worst_k]
            continue
        for f in current:
            f.reason = ''
        say('validating the extended model with the pipeline')
        trial = _build_model(model, ctx, [(a.effect, a.hyper, f.value) for a, f in zip(sel.active, current)], None)
        after = run_pipeline(run.device, calibration, trial, times, run.counts)
        res_after = _datum_corrected(obs, obs.residual(after), after.measured(obs.kind), split.train_idx)
        both = split.test_idx[np.all(np.isfinite(res_after[split.test_idx]), axis=1)
                              & np.all(np.isfinite(res_before[split.test_idx]), axis=1)]
        total_b = float(np.mean((res_before[both] / floor) ** 2)) if both.size else math.nan
        total_a = float(np.mean((res_after[both] / floor) ** 2)) if both.size else math.nan
        validated = bool(both.size and math.sqrt(total_a) <= (1.0 - 0.5 * o.min_gain) * math.sqrt(total_b))
        if not validated:
            for f in current:
                f.claimed = False
                f.reason = ('the pipeline with the term did not confirm the linearised gain '
                            f'(held-out RMS {math.sqrt(total_b):.2f} → {math.sqrt(total_a):.2f} floors)')
            not_claimed += current
            sel.active = []
            after = res_after = None
            break
        found = current
        for a, f in zip(sel.active, found):
            f.explained = a.explained
        extended = trial
        stats_pred = component_errors(obs, _unweight(e_pred, floor, obs, split.fit_test),
                                      np.arange(split.fit_test.size))
        ratio = np.sqrt(np.nanmean((res_after[split.fit_test] / floor) ** 2, axis=0))
        at_floor = bool(np.all(ratio <= o.floor_factor))
        structure_after = [] if at_floor else _structure(res_after / floor, split.fit_test, features)
        break
    if not sel.active:
        after = res_after = None
        ratio = np.sqrt(np.nanmean((res_before[split.fit_test] / floor) ** 2, axis=0))
        at_floor = bool(np.all(ratio <= o.floor_factor))
        structure_after = [] if at_floor else structure_before

    stats_before = component_errors(obs, res_before, split.test_idx)
    per_bar_before = _per_bar(ctx, res_before, split.test_idx)
    if res_after is not None:
        stats_after = component_errors(obs, res_after, split.test_idx)
        per_bar_after = _per_bar(ctx, res_after, split.test_idx)
        for f in found:
            contributions[f.effect] = res_before - res_after if len(found) == 1 else _contribution(
                sel, ctx, f, raw.shape)
    record = None
    if extended is not None:
        record = _ascii({
            'created': datetime.now(timezone.utc).isoformat(timespec='seconds'),
            'log': str(run.path), 'reference': obs.description,
            'added': [{'effect': f.effect, 'term': f.term_type, 'setting': f.hyper_label,
                       'parameters': f.parameter_rows()} for f in found],
            'held_out_rms_before': {s.name: s.rms for s in stats_before},
            'held_out_rms_after': {s.name: s.rms for s in stats_after or []},
            'units': {s.name: s.unit for s in stats_before},
        })
        extended = _build_model(model, ctx, [(_effect(f), f.hyper, f.value) for f in found], record)
        # the model's own uncertainty: its fitted terms' covariance and the residual left
        extended = with_fit_uncertainty(extended, ctx, found, after, res_after, split.test_idx)
    conclusion = _conclusion(obs, found, not_claimed, at_floor, structure_after, stats_before,
                             stats_after, floor)
    return Analysis(str(run.path), o, obs, split, times, floor, before, after, res_before,
                    res_after, steps, found, not_claimed, stats_before, stats_after, stats_pred,
                    structure_before, structure_after, at_floor, validated and bool(found), extended,
                    conclusion, features, contributions, per_bar_before, per_bar_after,
                    time.perf_counter() - started, not_applicable,
                    run.problem.as_dict() if run.problem else None)


def _ascii(value: Any) -> Any:
    """The model file's analysis record in plain ASCII (the YAML writer escapes the rest) and
    numbers to six significant digits."""
    if isinstance(value, str):
        return value.replace('µ', 'u').replace('°', 'deg').replace('″', 'arcsec').replace('…', '...')
    if isinstance(value, float):
        return float(f'{value:.6g}') if math.isfinite(value) else None
    if isinstance(value, dict):
        return {_ascii(k): _ascii(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_ascii(v) for v in value]
    return value


def _effect(f: Found) -> Effect:
    return catalogue([f.effect])[0]


def _contribution(sel: _Selector, ctx: FitContext, f: Found, shape: tuple[int, ...]) -> FloatArray:
    """Linearised contribution of one effect to the residual at the held-out fit samples
    (NaN elsewhere), in observation units."""
    out = np.full(shape, np.nan)
    eff = _effect(f)
    cols = sel.columns(eff, f.hyper, 'test') @ f.value
    k = len(ctx.obs.components)
    out[sel.test.idx] = -(cols.reshape(-1, k) / sel.test.w)
    return out


def _unweight(e: FloatArray, floor: FloatArray, obs: Observation, idx: IntArray) -> FloatArray:
    k = len(obs.components)
    return -e.reshape(-1, k) * floor


def _per_bar(ctx: FitContext, residual: FloatArray, idx: IntArray) -> list[ComponentError] | None:
    """Bar-length view of a full 6-DOF pose residual: J dp per bar (µm)."""
    obs = ctx.obs
    if obs.kind != 'pose' or len(obs.components) != 6:
        return None
    sel = idx[np.all(np.isfinite(residual[idx]), axis=1)]
    jac = jacobian(ctx.device.geometry, ctx.base.poses[sel])
    dd = np.einsum('nij,nj->ni', jac, residual[sel])
    bars = Observation('lengths', list(range(6)), [f'bar{i + 1}' for i in range(6)], ['um'] * 6,
                       np.zeros((sel.size, 6)), np.ones(sel.size, bool), False)
    return component_errors(bars, dd, np.arange(sel.size))


def _structure(weighted: FloatArray, idx: IntArray, features: dict[str, FloatArray]) -> list[tuple[str, float]]:
    """Features sorted by the share of the residual variance their binned means explain."""
    r = weighted[idx]
    ok = np.all(np.isfinite(r), axis=1)
    out = [(name, binned_r2(r[ok], v[idx][ok])) for name, v in features.items()]
    return sorted(out, key=lambda t: -t[1])


def _fmt(stats: list[ComponentError] | None) -> str:
    if not stats:
        return '–'
    return ', '.join(f'{s.name} {s.rms:.3g} {_unit(s.unit)}' for s in stats)


def _unit(unit: str) -> str:
    return 'µm' if unit == 'um' else '″' if unit == 'arcsec' else unit


def _conclusion(obs: Observation, found: list[Found], not_claimed: list[Found], at_floor: bool,
                structure: list[tuple[str, float]], before: list[ComponentError],
                after: list[ComponentError] | None, floor: FloatArray) -> str:
    parts = []
    floor_txt = ', '.join(f'{n} {f * s:.3g} {_unit(u)}' for n, f, s, u in
                          zip(obs.names, floor, obs.to_report, obs.units))
    features = ', '.join(f'{name} (R² {r2:.2f})' for name, r2 in structure[:3] if r2 >= 0.05)
    if found:
        names = ', '.join(f.title for f in found)
        parts.append(f'Found: {names}. Held-out RMS {_fmt(before)} → {_fmt(after)} '
                     '(pipeline re-run with the extended model).')
    if not_claimed:
        parts.append('Not claimed: ' + '; '.join(f'{f.title} ({f.reason})' for f in not_claimed) + '.')
    if at_floor:
        if not found:
            parts.append(f'No significant effect: the held-out residual ({_fmt(before)}) is at the '
                         f'noise floor ({floor_txt}). The model is unchanged.')
        else:
            parts.append(f'What remains is at the noise floor ({floor_txt}).')
    else:
        lead = ('No catalogued effect explains the residual; ' if not found else '')
        parts.append(f'{lead}unexplained structure remains above the noise floor ({floor_txt})'
                     + (f', correlated with {features}' if features else '') + '.'
                     + (' The model is unchanged.' if not found else ''))
    return ' '.join(parts)
