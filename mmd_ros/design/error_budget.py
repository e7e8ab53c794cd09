"""Monte Carlo error budget of the kinematic parameters: section 2.2 of Lei & Chen (2024).

The true device has its ball-joint positions ``a_i``, ``b_i`` and its centre distances ``d_i``
perturbed by random errors (Eqs. 7, 8); the software knows only the nominal joints and reads
a centre distance that is off by ``eps_d,i``. At a setting pose ``p``:

    d_true,i = | R (a_i + eps_ja,i) + t - (b_i + eps_jb,i) |         (Eq. 6 on the true device)
    d_soft,i = d_true,i + eps_d,i                                   (what the software reads)
    p_est    = FK_nominal(d_soft)                                   (Newton, section 2.1)

The position error is ``|t_est - t|`` (2-norm, section 2.2); the rotation error, which the paper
leaves out, is the angle of ``R_est R^T``. Accuracy is mean + 2 standard deviations over N
samples. Eq. (9) is a quadratic surface fitted to the accuracy over a grid of
(||eps_j||_inf, ||eps_d||_inf).

How the errors are drawn for a given bound ``eps`` is a *reading* of the paper's words
"uniformly distributed noises" and "maximal amount of the perturbation"; :data:`READINGS` lists
the ones implemented. ``onesided-max`` reproduces the paper's Eq. (9) (see
``msg_docs/design_tools.md``).

Every error model here is homogeneous of degree one in (eps_j, eps_d) to far below the
Monte Carlo noise (errors of micrometres on 300 mm), so tolerance limits follow from one run per
direction by scaling (:func:`tolerance_frontier`), checked by a final run at the answer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmd_ros.core.kinematics import ForwardKinematics, Geometry, jacobian
from mmd_ros.core.rotation import angle_rate_axes, rotation_angle, rotation_matrix
from mmd_ros.core.units import M_PER_MM, M_PER_UM, arcsec, mm, um
from mmd_ros.design.errors import DesignError

__all__ = [
    'Accuracy', 'DEFAULT_READING', 'ErrorBudget', 'FrontierPoint', 'JACKKNIFE_GROUPS',
    'METHODS', 'PAPER_DESIGN_POINT_M', 'PAPER_EQ9_UM', 'PAPER_POSITIONS_M', 'PARTS',
    'PoseErrors', 'READINGS', 'Study', 'Surface', 'TopEdgeCylinder', 'eq9_design_matrix',
    'eq9_summary', 'fit_eq9', 'format_with_se', 'planned_runs', 'round_to_se', 'run_study',
    'sample_unit_errors', 'se_decimals', 'tolerance_frontier',
]

FloatArray = NDArray[np.float64]

#: The five setting positions of Fig. 2 [m], zero rotation.
PAPER_POSITIONS_M = np.array([
    [100.0, 0.0, 323.0], [50.0, 0.0, 304.25], [0.0, 0.0, 285.5],
    [-50.0, 0.0, 266.75], [-100.0, 0.0, 248.0]]) * M_PER_MM

#: Eq. (9) coefficients of 1, e_j, e_d, e_j^2, e_j e_d, e_d^2 with e in µm and accuracy in µm.
PAPER_EQ9_UM = np.array([0.11, 1.68, 1.21, 0.72, -1.18, 0.59])

#: The design criteria of section 2.2: ||eps_j||_inf = 0.4 µm, ||eps_d||_inf = 0.8 µm [m].
PAPER_DESIGN_POINT_M = (0.4 * M_PER_UM, 0.8 * M_PER_UM)

#: Readings of "perturbed by uniformly distributed noises ... up to eps" (Eqs. 7, 8). Each
#: draws, for a bound eps = 1, the 36 joint-coordinate errors and the 6 centre-distance errors.
READINGS: dict[str, str] = {
    'box': 'every joint coordinate and every centre distance uniform in [-eps, eps]',
    'ball': 'every joint uniform in a ball of radius eps; centre distances uniform in [-eps, eps]',
    'band': 'every joint coordinate and centre distance uniform in [-eps/2, eps/2] '
            '(a tolerance band of total width eps)',
    'onesided': 'every joint coordinate and centre distance uniform in [0, eps]',
    'onesided-max': 'uniform [0, 1] draws scaled so that the largest entry of eps_j (Eq. 7) and '
                    'of eps_d (Eq. 8) equals eps exactly (reproduces the paper)',
}
DEFAULT_READING = 'onesided-max'

#: Ways of computing the estimated pose: full Newton forward kinematics, or the first-order
#: model p_est - p = J^-1 (d_soft - d), J the bar-length Jacobian at the setting pose.
METHODS = ('newton', 'linear')


def sample_unit_errors(reading: str, n: int, rng: np.random.Generator
                       ) -> tuple[FloatArray, FloatArray]:
    """Draw N error sets for a bound of 1 (scale by eps afterwards; every reading is linear in it).

    reading : a key of :data:`READINGS`
    returns : joint errors, ndarray, shape (N, 2, 6, 3) — [k, 0, i] for a_i, [k, 1, i] for b_i;
        centre-distance errors, ndarray, shape (N, 6); both dimensionless (units of eps)
    """
    if reading not in READINGS:
        raise DesignError(f'unknown perturbation reading {reading!r}; '
                          f'use one of {sorted(READINGS)}')
    if reading == 'box':
        return rng.uniform(-1.0, 1.0, (n, 2, 6, 3)), rng.uniform(-1.0, 1.0, (n, 6))
    if reading == 'band':
        return rng.uniform(-0.5, 0.5, (n, 2, 6, 3)), rng.uniform(-0.5, 0.5, (n, 6))
    if reading == 'ball':
        direction = rng.standard_normal((n, 2, 6, 3))
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        radius = rng.uniform(0.0, 1.0, (n, 2, 6, 1)) ** (1.0 / 3.0)
        return direction * radius, rng.uniform(-1.0, 1.0, (n, 6))
    joint = rng.uniform(0.0, 1.0, (n, 2, 6, 3))
    dist = rng.uniform(0.0, 1.0, (n, 6))
    if reading == 'onesided-max':
        joint /= np.max(joint.reshape(n, -1), axis=1)[:, None, None, None]
        dist /= np.max(dist, axis=1)[:, None]
    return joint, dist


@dataclass(frozen=True)
class PoseErrors:
    """Pose errors of N Monte Carlo samples at one setting pose.

    position_m : ndarray, shape (N,) — |t_est - t| [m]
    rotation_rad : ndarray, shape (N,) — angle of R_est R^T [rad]
    """

    position_m: FloatArray
    rotation_rad: FloatArray


#: Groups of a Monte Carlo run for the delete-a-group jackknife of the standard errors.
JACKKNIFE_GROUPS = 20


@dataclass(frozen=True)
class Accuracy:
    """Statistics of one Monte Carlo run (section 2.2: accuracy = mean + 2 std).

    pose : ndarray, shape (6,) — setting pose [m, rad]
    eps_joint_m, eps_dist_m : bounds ||eps_j||_inf, ||eps_d||_inf [m]
    position_groups : ndarray, shape (G, 3) — count, sum [m] and sum of squares [m²] of the
        position errors in each of G consecutive groups of the N samples (the draws are
        independent, so the groups are too); None when N < 4. The jackknife of
        :meth:`position_leave_one_out_m` and :attr:`Surface.coefficients_se_um` uses them.
    """

    pose: FloatArray
    eps_joint_m: float
    eps_dist_m: float
    samples: int
    position_mean_m: float
    position_std_m: float
    rotation_mean_rad: float
    rotation_std_rad: float
    position_groups: FloatArray | None = field(default=None, repr=False, compare=False)

    @property
    def position_m(self) -> float:
        """Position accuracy, mean + 2 std [m]."""
        return self.position_mean_m + 2.0 * self.position_std_m

    @property
    def rotation_rad(self) -> float:
        """Rotation accuracy, mean + 2 std [rad]."""
        return self.rotation_mean_rad + 2.0 * self.rotation_std_rad

    def position_leave_one_out_m(self) -> FloatArray:
        """Position accuracy (mean + 2 std) of the run with each group left out in turn,
        shape (G,) [m] (the jackknife replicates)."""
        if self.position_groups is None:
            raise DesignError(f'a run of {self.samples} samples is too short to estimate its '
                              'Monte Carlo standard error (need at least 4)')
        g = self.position_groups
        n, total, squares = g.sum(axis=0)
        count = n - g[:, 0]
        mean = (total - g[:, 1]) / count
        var = np.maximum((squares - g[:, 2]) / count - mean * mean, 0.0)
        return mean + 2.0 * np.sqrt(var)

    @classmethod
    def of(cls, pose: FloatArray, eps_joint_m: float, eps_dist_m: float,
           errors: PoseErrors) -> Accuracy:
        pos, rot = errors.position_m, errors.rotation_rad
        groups = None
        count = min(JACKKNIFE_GROUPS, pos.size // 2)
        if count >= 2:
            parts = np.array_split(pos, count)
            groups = np.array([[p.size, p.sum(), p @ p] for p in parts])
        return cls(np.array(pose, dtype=np.float64), float(eps_joint_m), float(eps_dist_m),
                   int(pos.size), float(np.mean(pos)), float(np.std(pos)),
                   float(np.mean(rot)), float(np.std(rot)), groups)


class ErrorBudget:
    """Monte Carlo of section 2.2 for one device geometry.

    Parameters
    ----------
    geometry : the nominal joints (the software's); the true device is this one perturbed
    reading : how errors are drawn, a key of :data:`READINGS`
    method : 'newton' (full forward kinematics on every sample) or 'linear' (first order)
    samples : N per run (the paper: 10,000)
    seed : seed of the random generator; runs draw from it in turn, so a sequence of calls is
        reproducible
    on_run : called after every run with the number of samples done (for progress reports)
    """

    def __init__(self, geometry: Geometry, *, reading: str = DEFAULT_READING,
                 method: str = 'newton', samples: int = 10_000, seed: int | None = 0,
                 on_run: Callable[[int], None] | None = None) -> None:
        if reading not in READINGS:
            raise DesignError(f'unknown perturbation reading {reading!r}; '
                              f'use one of {sorted(READINGS)}')
        if method not in METHODS:
            raise DesignError(f'unknown method {method!r}; use one of {list(METHODS)}')
        if samples < 2:
            raise DesignError(f'need at least 2 samples per run, got {samples}')
        self.geometry = geometry
        self.reading = reading
        self.method = method
        self.samples = int(samples)
        self.rng = np.random.default_rng(seed)
        self.on_run = on_run
        self._fk = ForwardKinematics(geometry)
        self._linear: dict[bytes, tuple[FloatArray, FloatArray, FloatArray]] = {}

    # -- one run ---------------------------------------------------------------------------
    def errors(self, pose: ArrayLike, eps_joint_m: float, eps_dist_m: float,
               samples: int | None = None, method: str | None = None) -> PoseErrors:
        """Pose errors of N perturbed devices at one setting pose.

        pose : array_like, shape (6,) or (3,) — setting pose [m, rad]; a position alone means
            zero rotation
        eps_joint_m, eps_dist_m : bounds of the joint and centre-distance errors [m]
        """
        p = _as_pose(pose)
        n = self.samples if samples is None else int(samples)
        method = method or self.method
        unit_joint, unit_dist = sample_unit_errors(self.reading, n, self.rng)
        joint = unit_joint * eps_joint_m
        dist = unit_dist * eps_dist_m
        if method == 'linear':
            result = self._linear_errors(p, joint, dist)
        elif method == 'newton':
            result = self._newton_errors(p, joint, dist)
        else:
            raise DesignError(f'unknown method {method!r}; use one of {list(METHODS)}')
        if self.on_run is not None:
            self.on_run(n)
        return result

    def accuracy(self, pose: ArrayLike, eps_joint_m: float, eps_dist_m: float,
                 samples: int | None = None) -> Accuracy:
        """Mean + 2 std of the position and rotation errors at one setting pose."""
        p = _as_pose(pose)
        return Accuracy.of(p, eps_joint_m, eps_dist_m,
                           self.errors(p, eps_joint_m, eps_dist_m, samples))

    def _newton_errors(self, p: FloatArray, joint: FloatArray, dist: FloatArray) -> PoseErrors:
        rot = rotation_matrix(p[3:])
        upper = self.geometry.upper + joint[:, 0]
        lower = self.geometry.lower + joint[:, 1]
        legs = upper @ rot.T + p[:3] - lower
        d_soft = np.sqrt(np.einsum('nki,nki->nk', legs, legs)) + dist
        # One thread: a run of 10,000 samples is too short for the pool to pay off.
        sol = self._fk.solve_batch(d_soft, guess=p, workers=1)
        if not np.all(sol.converged):
            bad = int(np.count_nonzero(~sol.converged))
            raise DesignError(f'forward kinematics failed on {bad} of {len(d_soft)} samples at '
                              f'pose {p.tolist()}: is the pose reachable and the error bound '
                              'small (micrometres)?')
        est = sol.poses
        position = np.linalg.norm(est[:, :3] - p[:3], axis=1)
        return PoseErrors(position, rotation_angle(rotation_matrix(est[:, 3:]) @ rot.T))

    def _linear_model(self, p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """First-order model at pose p: Delta d_true,i = n_i . (R da_i - db_i) and
        Delta p = J^-1 Delta d_soft. Returns (R a-side map (6, 3), b-side map (6, 3), J^-1)."""
        key = p.tobytes()
        if key not in self._linear:
            rot = rotation_matrix(p[3:])
            legs = self.geometry.upper @ rot.T + p[:3] - self.geometry.lower
            units = legs / np.linalg.norm(legs, axis=1)[:, None]
            jinv = np.linalg.inv(jacobian(self.geometry, p))
            self._linear[key] = (units @ rot, -units, jinv)
        return self._linear[key]

    def _linear_errors(self, p: FloatArray, joint: FloatArray, dist: FloatArray) -> PoseErrors:
        upper_map, lower_map, jinv = self._linear_model(p)
        d_change = (np.einsum('ki,nki->nk', upper_map, joint[:, 0])
                    + np.einsum('ki,nki->nk', lower_map, joint[:, 1]) + dist)
        dp = d_change @ jinv.T
        omega = dp[:, 3:] @ angle_rate_axes(p[3:]).T
        return PoseErrors(np.linalg.norm(dp[:, :3], axis=1), np.linalg.norm(omega, axis=1))

    # -- Fig. 2, 3, 4 ----------------------------------------------------------------------
    def sweep(self, poses: ArrayLike, eps_values_m: Sequence[float], which: str
              ) -> list[list[Accuracy]]:
        """Fig. 2: accuracy against one error bound with the other one zero.

        poses : array_like, shape (P, 3) or (P, 6) [m, rad]
        eps_values_m : the bounds [m]
        which : 'joint' (Fig. 2a) or 'distance' (Fig. 2b)
        returns : [pose][eps] accuracies
        """
        if which not in ('joint', 'distance'):
            raise DesignError(f"which must be 'joint' or 'distance', got {which!r}")
        out = []
        for pose in np.atleast_2d(np.asarray(poses, dtype=np.float64)):
            row = []
            for eps in eps_values_m:
                ej, ed = (eps, 0.0) if which == 'joint' else (0.0, eps)
                row.append(self.accuracy(pose, ej, ed))
            out.append(row)
        return out

    def surface(self, pose: ArrayLike, eps_joint_values_m: Sequence[float],
                eps_dist_values_m: Sequence[float]) -> Surface:
        """Fig. 3: accuracy over a grid of (eps_j, eps_d) at one pose, with the Eq. (9) fit."""
        p = _as_pose(pose)
        ej = np.asarray(eps_joint_values_m, dtype=np.float64)
        ed = np.asarray(eps_dist_values_m, dtype=np.float64)
        grid = [[self.accuracy(p, a, b) for b in ed] for a in ej]
        return Surface.from_grid(p, ej, ed, grid)

    def positions(self, poses: ArrayLike, eps_joint_m: float, eps_dist_m: float
                  ) -> list[Accuracy]:
        """Fig. 4: accuracy at several setting poses for one pair of bounds."""
        return [self.accuracy(pose, eps_joint_m, eps_dist_m)
                for pose in np.atleast_2d(np.asarray(poses, dtype=np.float64))]


def eq9_design_matrix(eps_joint_um: ArrayLike, eps_dist_um: ArrayLike) -> FloatArray:
    """Columns 1, e_j, e_d, e_j^2, e_j e_d, e_d^2 of Eq. (9).

    eps_joint_um, eps_dist_um : array_like, shape (M,) [µm]
    returns : ndarray, shape (M, 6)
    """
    x = np.asarray(eps_joint_um, dtype=np.float64).ravel()
    y = np.asarray(eps_dist_um, dtype=np.float64).ravel()
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)


def fit_eq9(eps_joint_um: ArrayLike, eps_dist_um: ArrayLike, accuracy_um: ArrayLike
            ) -> FloatArray:
    """Least-squares fit of Eq. (9), accuracy = c0 + c1 e_j + c2 e_d + c3 e_j^2 + c4 e_j e_d
    + c5 e_d^2, in the paper's units.

    eps_joint_um, eps_dist_um, accuracy_um : array_like, shape (M,) [µm]
    returns : ndarray, shape (6,) — c0 [µm], c1, c2 [1], c3, c4, c5 [1/µm]
    """
    design = eq9_design_matrix(eps_joint_um, eps_dist_um)
    coef, *_ = np.linalg.lstsq(design, np.asarray(accuracy_um, dtype=np.float64).ravel(),
                               rcond=None)
    return coef


@dataclass(frozen=True)
class Surface:
    """Fig. 3: accuracy over a grid of bounds and the Eq. (9) fit.

    eps_joint_m : ndarray, shape (J,) [m];  eps_dist_m : ndarray, shape (D,) [m]
    position_m, rotation_rad : ndarray, shape (J, D) — mean + 2 std [m], [rad]
    coefficients_um : ndarray, shape (6,) — fitted Eq. (9) in the paper's units (µm)
    coefficients_se_um : ndarray, shape (6,) — their Monte Carlo standard errors, by the
        delete-a-group jackknife: the fit repeated with group g of every run's samples left
        out (g = 1..G), SE = sqrt((G - 1)/G sum_g (c_g - mean c)^2); None for runs too short
    """

    pose: FloatArray
    eps_joint_m: FloatArray
    eps_dist_m: FloatArray
    position_m: FloatArray
    rotation_rad: FloatArray
    coefficients_um: FloatArray
    grid: list[list[Accuracy]] = field(repr=False, compare=False)
    coefficients_se_um: FloatArray | None = None

    @classmethod
    def from_grid(cls, pose: FloatArray, ej: FloatArray, ed: FloatArray,
                  grid: list[list[Accuracy]]) -> Surface:
        pos = np.array([[a.position_m for a in row] for row in grid])
        rot = np.array([[a.rotation_rad for a in row] for row in grid])
        ej_um, ed_um = np.meshgrid(ej / M_PER_UM, ed / M_PER_UM, indexing='ij')
        coef = fit_eq9(ej_um, ed_um, pos / M_PER_UM)
        runs = [a for row in grid for a in row]
        se = None
        if all(a.position_groups is not None for a in runs) and \
                len({len(a.position_groups) for a in runs}) == 1:   # type: ignore[arg-type]
            # replicates (G, J*D): the whole grid with group g left out of every run
            loo = np.stack([a.position_leave_one_out_m() for a in runs], axis=1) / M_PER_UM
            design = eq9_design_matrix(ej_um, ed_um)
            reps, *_ = np.linalg.lstsq(design, loo.T, rcond=None)          # (6, G)
            g = loo.shape[0]
            se = np.sqrt((g - 1) / g * np.sum((reps - reps.mean(axis=1, keepdims=True)) ** 2,
                                              axis=1))
        return cls(pose, ej, ed, pos, rot, coef, grid, se)

    def evaluate_um(self, coefficients_um: ArrayLike) -> FloatArray:
        """An Eq. (9) surface on this grid, shape (J, D) [µm]."""
        ej_um, ed_um = np.meshgrid(self.eps_joint_m / M_PER_UM, self.eps_dist_m / M_PER_UM,
                                   indexing='ij')
        return (eq9_design_matrix(ej_um, ed_um) @ np.asarray(coefficients_um)).reshape(ej_um.shape)

    def rms_um(self, coefficients_um: ArrayLike, against: str = 'fit') -> float:
        """RMS over the grid of an Eq. (9) surface minus the fitted surface ('fit') or minus the
        Monte Carlo points ('points') [µm]."""
        other = (self.evaluate_um(self.coefficients_um) if against == 'fit'
                 else self.position_m / M_PER_UM)
        return float(np.sqrt(np.mean((self.evaluate_um(coefficients_um) - other) ** 2)))

    @property
    def fit_residual_rms_um(self) -> float:
        """RMS of the Monte Carlo points about their own Eq. (9) fit [µm]."""
        return self.rms_um(self.coefficients_um, against='points')


@dataclass(frozen=True)
class TopEdgeCylinder:
    """The cylindrical workspace of Fig. 4: radius [m] and the bottom and top heights [m]."""

    radius_m: float = 100.0 * M_PER_MM
    z_low_m: float = 248.0 * M_PER_MM
    z_high_m: float = 323.0 * M_PER_MM

    def top_edge(self, count: int = 12) -> FloatArray:
        """Fig. 4(a): positions on the top circle, every 360/count degrees from +x,
        shape (count, 3) [m]."""
        ang = np.arange(count) * (2.0 * math.pi / count)
        return np.stack([self.radius_m * np.cos(ang), self.radius_m * np.sin(ang),
                         np.full(count, self.z_high_m)], axis=1)

    def interior(self, count: int = 8) -> FloatArray:
        """Fig. 4(b): positions inside: on the half-radius circle at mid-height every
        360/count degrees, and on the axis at bottom, middle and top, shape (count + 3, 3)."""
        ang = np.arange(count) * (2.0 * math.pi / count)
        mid = 0.5 * (self.z_low_m + self.z_high_m)
        ring = np.stack([0.5 * self.radius_m * np.cos(ang), 0.5 * self.radius_m * np.sin(ang),
                         np.full(count, mid)], axis=1)
        axis = np.array([[0.0, 0.0, self.z_low_m], [0.0, 0.0, mid], [0.0, 0.0, self.z_high_m]])
        return np.vstack([ring, axis])


@dataclass(frozen=True)
class FrontierPoint:
    """The largest bounds along one direction of the (eps_j, eps_d) plane that keep the worst
    accuracy over the setting poses under the target.

    angle_rad : direction, eps_d / eps_j = tan(angle)
    eps_joint_m, eps_dist_m : the largest bounds [m]
    binding : 'position' or 'rotation', the target that limits
    worst_pose : ndarray, shape (6,) — the setting pose with the worst accuracy
    """

    angle_rad: float
    eps_joint_m: float
    eps_dist_m: float
    binding: str
    worst_pose: FloatArray


def tolerance_frontier(budget: ErrorBudget, poses: ArrayLike, target_position_m: float, *,
                       target_rotation_rad: float | None = None,
                       angles_rad: Sequence[float] | None = None) -> list[FrontierPoint]:
    """The inverse question: the largest (eps_j, eps_d) keeping accuracy under a target.

    For each direction (cos a, sin a) in the plane of bounds, one run per pose at a bound of
    1 µm gives accuracy A(a) (worst pose); accuracy is homogeneous of degree one in the
    bounds, so the largest scale is target / A(a).

    poses : array_like, shape (P, 3) or (P, 6) — setting poses [m, rad]
    target_position_m : position accuracy to keep [m]
    target_rotation_rad : optional rotation accuracy to keep as well [rad]
    angles_rad : directions; default 0..90° in 5° steps
    """
    if target_position_m <= 0 or (target_rotation_rad is not None and target_rotation_rad <= 0):
        raise DesignError('targets must be > 0')
    if angles_rad is None:
        angles_rad = np.radians(np.arange(0.0, 90.0 + 1e-9, 5.0))
    unit = M_PER_UM
    poses2 = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    out = []
    for a in angles_rad:
        ej, ed = unit * math.cos(a), unit * math.sin(a)
        # Exactly zero components keep the draw identical in distribution to the one-error case.
        ej = 0.0 if abs(ej) < 1e-12 * unit else ej
        ed = 0.0 if abs(ed) < 1e-12 * unit else ed
        best: tuple[float, str, FloatArray] | None = None
        for pose in poses2:
            acc = budget.accuracy(pose, ej, ed)
            scale = target_position_m / acc.position_m
            binding = 'position'
            if target_rotation_rad is not None and acc.rotation_rad > 0:
                rot_scale = target_rotation_rad / acc.rotation_rad
                if rot_scale < scale:
                    scale, binding = rot_scale, 'rotation'
            if best is None or scale < best[0]:
                best = (scale, binding, acc.pose)
        assert best is not None
        out.append(FrontierPoint(float(a), best[0] * ej, best[0] * ed, best[1], best[2]))
    return out


def _as_pose(pose: ArrayLike) -> FloatArray:
    p = np.asarray(pose, dtype=np.float64).ravel()
    if p.size == 3:
        p = np.concatenate([p, np.zeros(3)])
    if p.size != 6 or not np.all(np.isfinite(p)):
        raise DesignError(f'a setting pose is [x, y, z] or [x, y, z, phi, theta, psi], '
                          f'got {pose!r}')
    return p



# -- the whole study of section 2.2 ------------------------------------------------------------
#: Parts of :func:`run_study`, in order.
PARTS = ('fig2', 'fig3', 'fig4', 'tolerance')


@dataclass(frozen=True)
class Study:
    """Results of :func:`run_study`; a part not asked for is None.

    fig2_eps_m : ndarray, shape (E,) — bounds of Fig. 2 (the non-zero ones of the grid) [m]
    grid_eps_m : ndarray, shape (G,) — bounds of both axes of Fig. 3 [m]
    fig2_joint, fig2_distance : [pose][eps] accuracies (Fig. 2a, 2b)
    surface : Fig. 3 at the first setting pose
    design_point : [pose] accuracies at the design bounds at the setting poses
    fig4_top, fig4_inside : [pose] accuracies at the design bounds (Fig. 4a, 4b)
    frontier : the inverse question, one point per direction; ``ratio_point`` the point on
        the direction of the design bounds and ``ratio_check`` the accuracies of a check run
        there at every pose
    """

    reading: str
    method: str
    samples: int
    poses: FloatArray
    fig2_eps_m: FloatArray
    grid_eps_m: FloatArray
    design_point_m: tuple[float, float]
    target_position_m: float
    target_rotation_rad: float | None
    fig2_joint: list[list[Accuracy]] | None = None
    fig2_distance: list[list[Accuracy]] | None = None
    surface: Surface | None = None
    design_point: list[Accuracy] | None = None
    fig4_top: list[Accuracy] | None = None
    fig4_inside: list[Accuracy] | None = None
    frontier: list[FrontierPoint] | None = None
    ratio_point: FrontierPoint | None = None
    ratio_check: list[Accuracy] | None = None


    def summary(self) -> dict[str, object]:
        """The results in report units (µm, arc-seconds, mm), as plain data for JSON."""
        out: dict[str, object] = {
            'reading': self.reading, 'reading_description': READINGS[self.reading],
            'method': self.method, 'samples': self.samples,
            'setting_positions_mm': [_r(mm(q[:3]), 3) for q in self.poses],
            'design_point_um': [_r(um(v), 4) for v in self.design_point_m],
            'target_um': _r(um(self.target_position_m), 4),
            'target_arcsec': (None if self.target_rotation_rad is None
                              else _r(arcsec(self.target_rotation_rad), 4)),
        }
        for key, table in (('fig2_joint', self.fig2_joint), ('fig2_distance', self.fig2_distance)):
            if table is None:
                continue
            eps_um = um(self.fig2_eps_m)
            acc = np.array([[a.position_m for a in row] for row in table])
            rot = np.array([[a.rotation_rad for a in row] for row in table])
            slope = (acc @ self.fig2_eps_m) / float(self.fig2_eps_m @ self.fig2_eps_m)
            out[key] = {
                'eps_um': _r(eps_um, 4),
                'position_um': _r(um(acc), 4),
                'position_mean_um': _r(um(np.array([[a.position_mean_m for a in row]
                                                    for row in table])), 4),
                'position_std_um': _r(um(np.array([[a.position_std_m for a in row]
                                                   for row in table])), 4),
                'rotation_arcsec': _r(arcsec(rot), 4),
                'slope_um_per_um': _r(slope, 4),
                'eps_for_target_um': _r(um(self.target_position_m / slope), 4),
            }
        if self.surface is not None:
            sf = self.surface
            design = sf.evaluate_um(PAPER_EQ9_UM)
            out['fig3'] = {
                'position_mm': _r(mm(sf.pose[:3]), 3),
                'eps_um': _r(um(sf.eps_joint_m), 4),
                'position_um': _r(um(sf.position_m), 4),
                'rotation_arcsec': _r(arcsec(sf.rotation_rad), 4),
                **eq9_summary(sf),
                'eq9_paper': PAPER_EQ9_UM.tolist(),
                'rms_fit_vs_paper_um': _r(sf.rms_um(PAPER_EQ9_UM), 4),
                'rms_points_vs_paper_um': _r(sf.rms_um(PAPER_EQ9_UM, against='points'), 4),
                'rms_points_vs_fit_um': _r(sf.fit_residual_rms_um, 4),
                'max_abs_points_vs_paper_um': _r(np.max(np.abs(um(sf.position_m) - design)), 4),
            }
        for key, rows in (('design_point', self.design_point), ('fig4_top', self.fig4_top),
                          ('fig4_inside', self.fig4_inside)):
            if rows is None:
                continue
            pos = np.array([a.position_m for a in rows])
            rot = np.array([a.rotation_rad for a in rows])
            out[key] = {
                'positions_mm': [_r(mm(a.pose[:3]), 3) for a in rows],
                'position_um': _r(um(pos), 4),
                'rotation_arcsec': _r(arcsec(rot), 4),
                'max_position_um': _r(um(float(pos.max())), 4),
                'max_rotation_arcsec': _r(arcsec(float(rot.max())), 4),
                'worst_position_mm': _r(mm(rows[int(np.argmax(pos))].pose[:3]), 3),
            }
        if self.frontier is not None and self.ratio_point is not None:
            rp = self.ratio_point
            check = self.ratio_check or []
            out['tolerance'] = {
                'frontier': [{'angle_deg': _r(math.degrees(f.angle_rad), 3),
                              'eps_joint_um': _r(um(f.eps_joint_m), 4),
                              'eps_dist_um': _r(um(f.eps_dist_m), 4),
                              'binding': f.binding,
                              'worst_position_mm': _r(mm(f.worst_pose[:3]), 3)}
                             for f in self.frontier],
                'joint_only_um': _r(um(self.frontier[0].eps_joint_m), 4),
                'dist_only_um': _r(um(self.frontier[-1].eps_dist_m), 4),
                'at_design_ratio': {
                    'eps_joint_um': _r(um(rp.eps_joint_m), 4),
                    'eps_dist_um': _r(um(rp.eps_dist_m), 4),
                    'binding': rp.binding,
                    'worst_position_mm': _r(mm(rp.worst_pose[:3]), 3),
                    'check_max_position_um': _r(um(max(a.position_m for a in check)), 4),
                    'check_max_rotation_arcsec': _r(arcsec(max(a.rotation_rad for a in check)), 4),
                },
            }
        return out


def eq9_summary(surface: Surface) -> dict[str, object]:
    """The fitted Eq. (9) for a report: each coefficient rounded to its Monte Carlo standard
    error (``eq9_fitted``), the standard errors (``eq9_standard_error``), both as text
    (``eq9_text``: "1.667 ± 0.008") and each coefficient's distance from the paper's in standard
    errors (``eq9_paper_deviation_se``). Without standard errors (runs too short) the
    coefficients are given to 4 decimals."""
    coef, se = surface.coefficients_um, surface.coefficients_se_um
    if se is None:
        return {'eq9_fitted': _r(coef, 4), 'eq9_standard_error': None}
    pairs = [round_to_se(c, e) for c, e in zip(coef, se)]
    return {'eq9_fitted': [p[0] for p in pairs],
            'eq9_standard_error': [p[1] for p in pairs],
            'eq9_text': [format_with_se(c, e) for c, e in zip(coef, se)],
            'eq9_paper_deviation_se': _r((coef - PAPER_EQ9_UM) / np.where(se > 0, se, np.nan), 2)}


def planned_runs(parts: Sequence[str], n_poses: int, eps_values_m: ArrayLike,
                 cylinder_counts: tuple[int, int] = (12, 8), n_angles: int = 10) -> int:
    """Number of Monte Carlo runs :func:`run_study` makes with these arguments (for progress
    reports)."""
    eps = np.asarray(eps_values_m, dtype=np.float64)
    runs = 0
    if 'fig2' in parts:
        runs += 2 * n_poses * int(np.count_nonzero(eps > 0))
    if 'fig3' in parts:
        runs += eps.size ** 2
    if 'fig4' in parts:
        runs += n_poses + cylinder_counts[0] + cylinder_counts[1] + 3
    if 'tolerance' in parts:
        worst = n_poses + cylinder_counts[0]
        runs += (n_angles + 2) * worst
    return runs


def run_study(budget: ErrorBudget, poses: ArrayLike, *, parts: Sequence[str] = PARTS,
              eps_values_m: ArrayLike = np.linspace(0.0, 1.0, 11) * M_PER_UM,
              design_point_m: tuple[float, float] = PAPER_DESIGN_POINT_M,
              cylinder: TopEdgeCylinder = TopEdgeCylinder(),
              cylinder_counts: tuple[int, int] = (12, 8),
              target_position_m: float = 2.0 * M_PER_UM,
              target_rotation_rad: float | None = None,
              angles_rad: Sequence[float] = tuple(np.radians(np.arange(0.0, 91.0, 10.0)))
              ) -> Study:
    """Section 2.2 end to end: Fig. 2 (a, b) over ``eps_values_m`` at every setting pose,
    Fig. 3 over the grid ``eps_values_m`` squared at the first setting pose with the Eq. (9)
    fit, Fig. 4 at the design bounds on the top edge and inside the cylinder, and the largest
    bounds keeping the target at the setting poses and the top edge.

    poses : array_like, shape (P, 3) or (P, 6) — setting poses [m, rad]
    """
    unknown = set(parts) - set(PARTS)
    if unknown:
        raise DesignError(f'unknown parts {sorted(unknown)}; use some of {list(PARTS)}')
    p = np.array([_as_pose(q) for q in np.atleast_2d(np.asarray(poses, dtype=np.float64))])
    eps = np.asarray(eps_values_m, dtype=np.float64)
    nonzero = eps[eps > 0]
    out: dict[str, object] = {}
    if 'fig2' in parts:
        out['fig2_joint'] = budget.sweep(p, nonzero, 'joint')
        out['fig2_distance'] = budget.sweep(p, nonzero, 'distance')
    if 'fig3' in parts:
        out['surface'] = budget.surface(p[0], eps, eps)
    top = cylinder.top_edge(cylinder_counts[0])
    if 'fig4' in parts:
        out['design_point'] = budget.positions(p, *design_point_m)
        out['fig4_top'] = budget.positions(top, *design_point_m)
        out['fig4_inside'] = budget.positions(cylinder.interior(cylinder_counts[1]),
                                              *design_point_m)
    if 'tolerance' in parts:
        worst_set = np.vstack([p, np.array([_as_pose(q) for q in top])])
        out['frontier'] = tolerance_frontier(budget, worst_set, target_position_m,
                                             target_rotation_rad=target_rotation_rad,
                                             angles_rad=angles_rad)
        ratio_angle = math.atan2(design_point_m[1], design_point_m[0])
        ratio = tolerance_frontier(budget, worst_set, target_position_m,
                                   target_rotation_rad=target_rotation_rad,
                                   angles_rad=[ratio_angle])[0]
        out['ratio_point'] = ratio
        out['ratio_check'] = budget.positions(worst_set, ratio.eps_joint_m, ratio.eps_dist_m)
    return Study(budget.reading, budget.method, budget.samples, p, nonzero, eps, design_point_m,
                 target_position_m, target_rotation_rad, **out)  # type: ignore[arg-type]


def se_decimals(se: float) -> int:
    """Decimal places a value with standard error ``se`` is stated to: the SE's first
    significant digit, or its second when the first is 1 or 2 (0.008 -> 3, 0.014 -> 3,
    0.04 -> 2; decided on the SE rounded to two digits, so 0.0296 -> 0.03 -> 2). A value
    rounded so gives the same answer again. Non-finite or zero SE: 6 places."""
    if not (math.isfinite(se) and se > 0):
        return 6
    exponent = math.floor(math.log10(se))
    two = round(se / 10.0 ** (exponent - 1))          # the SE's two leading digits, 10..100
    if two >= 100:
        exponent, two = exponent + 1, 10
    return max(0, -exponent + (1 if two < 30 else 0))


def round_to_se(value: float, se: float) -> tuple[float, float]:
    """``value`` and ``se`` rounded to the digits :func:`se_decimals` allows."""
    k = se_decimals(se)
    return round(float(value), k), round(float(se), k)


def format_with_se(value: float, se: float) -> str:
    """``1.667 ± 0.008``: a value with its standard error, rounded to it."""
    k = se_decimals(se)
    return f'{value:.{k}f} ± {se:.{k}f}'


def _r(value: object, digits: int) -> object:
    """Round numbers, arrays and nested lists for a report."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        return round(float(arr), digits)
    return np.round(arr, digits).tolist()
