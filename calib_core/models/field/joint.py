"""Field calibration of a hand-held multi-pose recording: accelerometer from the static poses,
gyro (scale, misalignment, bias and bias drift) jointly from the moves and the quiet poses,
with standard errors and held-out figures of merit.

Models (IMU-TK's ``x' = T K (x - b)``, as in :mod:`calib_core.models.field.imu_tk`):

* accel, 9 parameters ``a_yz a_zy a_zx s_ax s_ay s_az b_ax b_ay b_az``: triangular ``T_a``
  (the body frame is the accelerometer's), fitted on the **mean of each static pose**:
  residual ``|T_a K_a (mean A_k - b_a)| - g`` per pose, every pose weighted alike (a 36 s rest
  and a 1 s hold count once each: the error that matters is the orientation-dependent one).
* gyro, 12 or 15 parameters ``g_yz g_zy g_zx g_xz g_xy g_yx s_gx s_gy s_gz b_gx b_gy b_gz
  [d_gx d_gy d_gz]``: ``w = T_g K_g (G - b_g - d_g t)``. The six off-diagonal terms of ``T_g``
  are the gyro's non-orthogonality together with the gyro-to-accelerometer misalignment
  (``w`` is expressed in the accelerometer frame, where the gravity directions live). Two
  kinds of residual, fitted together:

  - each move between consecutive poses ``j -> j+1``: ``dR^T u_j - u_{j+1}`` in the two
    directions across ``u_{j+1}`` (:func:`tangent_bases`; along it the difference of two
    unit vectors is second order), with ``u`` the
    unit gravity direction of each pose (calibrated accel mean) and ``dR`` the product of
    ``exp(w_k (t_{k+1} - t_k))`` over the samples from the middle of pose ``j`` to the middle
    of pose ``j+1``, on the recorded sample times. Integrating from pose middle to pose
    middle makes the mean direction of a pose that turns slowly in the hand (residual
    motion) the direction at its middle sample, to first order;
  - each **gyro-quiet** pose (initial rest included): the mean raw rate minus the bias,
    divided by the mean's standard error (within-pose std over sqrt(count / 0.25 s of
    samples)): the bias comes from every quiet interval, not the initial rest alone, each
    weighted by how still it was.

  The bias drift ``d_g`` (counts per s) is fitted and kept when the data show it (any axis
  at more than 3 standard errors, see :func:`fit_gyro_joint`). The two residual groups are
  weighted by their own variance components (sum of squares over the group's redundancy,
  :func:`group_redundancies`, re-estimated twice), so neither unit (rad vs rad/s) dominates
  by convention.

Standard errors: ``(J^T J)^-1`` at the solution with the weighted residuals' variance, as a
sandwich for the gyro noise a quiet pose's mean shares with the two moves integrated through
it (:func:`_shared_hold_correlation`); the gyro's include the accelerometer's, propagated
through the gravity directions to first order. Checked against Monte Carlo on the hand-held
simulator (docs/real-data.md, tests/test_real_field_handheld.py).

Figures of merit (:func:`field_figures`): per pose the static |f| error (|mean f| - 1 g, mg),
per move the angle between the gravity direction the gyro predicts and the one measured
(deg). :func:`held_out_figures` recomputes them on poses/moves left out of the fit
(k-fold over poses for the accelerometer, over moves for the gyro).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from calib_core.calibration import Calibration, TermValue
from calib_core.errors import DesignError
from calib_core.models.field.imu_tk import (
    ACCEL_PARAM_NAMES,
    GYRO_PARAM_NAMES,
    SegmentIntegrator,
    _rotate_by_conjugate,
    accel_matrix,
    gyro_matrix,
)
from calib_core.models.field.static_detection import Pose, odd_window

GYRO_BIAS_NAMES = ("b_gx", "b_gy", "b_gz")
GYRO_DRIFT_NAMES = ("d_gx", "d_gy", "d_gz")
GYRO_G_SENS_NAMES = tuple(f"S_{r}{c}" for r in "xyz" for c in "xyz")  # raw gyro per g
MIN_ACCEL_POSES = 10  # 9 parameters + 1 degree of freedom for the residual variance
MIN_ACCEL_POSES_WITH_PRIOR = 7  # the prior determines the 3 misalignments: 6 + 1
CORR_WINDOW_S = 0.25  # samples closer than this are not independent in a pose's gyro mean
ACCEL_BATCH_S = 0.5  # block length of the batch-means standard error of a pose's accel mean
MIN_TAU_DOF = 10  # residual degrees of freedom needed to estimate tau / drop the prior
MIN_MOVES = 5  # 2 direction constraints each: 10 >= 9 gyro parameters (bias from quiet poses)


# --- pose summaries -----------------------------------------------------------------------
@dataclass(frozen=True)
class PoseMeans:
    """Per pose: raw means, mean time, middle sample, count, gyro-quiet flag."""

    accel: np.ndarray  # (k, 3)
    gyro: np.ndarray  # (k, 3)
    t_mean: np.ndarray  # (k,)
    mid: np.ndarray  # (k,) sample index
    start: np.ndarray  # (k,) first sample
    end: np.ndarray  # (k,) one past the last sample
    count: np.ndarray  # (k,)
    gyro_quiet: np.ndarray  # (k,) bool
    gyro_se: np.ndarray  # (k, 3) standard error of the gyro mean, raw units (see pose_means)
    accel_se: np.ndarray  # (k, 3) same for the accel mean
    accel_se_batch: np.ndarray | None = None  # (k, 3) the accel mean's, by batch means

    def __len__(self) -> int:
        return len(self.count)


def pose_means(
    t, G, A, poses: tuple[Pose, ...] | list[Pose], corr_samples: int = 1, batch_samples: int | None = None
) -> PoseMeans:
    """``gyro_se``: within-pose std / sqrt(count / corr_samples): a hand's wobble is slow, so
    samples closer than ``corr_samples`` (the detector's window) are not counted as
    independent; a long rest gets a small error, a wobbly hold a large one.

    ``accel_se``: as ``gyro_se``. ``accel_se_batch`` (with ``batch_samples``): by batch
    means, the std of the means of consecutive blocks of that many samples over sqrt(number
    of blocks): the white noise's std / sqrt(count) for a still unit, larger with a slow
    wobble, without assuming its correlation time, but from few blocks (a 3 s pose has 6 of
    0.5 s: a ~30 % error); poses of fewer than 3 blocks get ``accel_se``."""
    t, G, A = (np.asarray(x, float) for x in (t, G, A))

    def se_of(X):
        return np.array(
            [X[p.start : p.end].std(axis=0, ddof=1) / np.sqrt(max(len(p) / corr_samples, 1.0)) for p in poses]
        ).reshape(-1, 3)

    def batch_se(X, p):
        n_b = len(p) // batch_samples if batch_samples else 0
        if n_b < 3:
            return X[p.start : p.end].std(axis=0, ddof=1) / np.sqrt(max(len(p) / corr_samples, 1.0))
        blocks = X[p.start : p.start + n_b * batch_samples].reshape(n_b, batch_samples, 3).mean(axis=1)
        return blocks.std(axis=0, ddof=1) / np.sqrt(n_b)

    se = se_of(G)
    accel_se_batch = np.array([batch_se(A, p) for p in poses]).reshape(-1, 3) if batch_samples else None
    return PoseMeans(
        accel=np.array([A[p.start : p.end].mean(axis=0) for p in poses]).reshape(-1, 3),
        gyro=np.array([G[p.start : p.end].mean(axis=0) for p in poses]).reshape(-1, 3),
        t_mean=np.array([t[p.start : p.end].mean() for p in poses]),
        mid=np.array([p.mid for p in poses], int),
        start=np.array([p.start for p in poses], int),
        end=np.array([p.end for p in poses], int),
        count=np.array([len(p) for p in poses], int),
        gyro_quiet=np.array([p.gyro_quiet for p in poses], bool),
        gyro_se=np.maximum(se, 1e-12),
        accel_se=np.maximum(se_of(A), 1e-12),
        accel_se_batch=None if accel_se_batch is None else np.maximum(accel_se_batch, 1e-12),
    )


def _covariance(sol, n_params: int, cross: np.ndarray | None = None) -> np.ndarray:
    """``(J^T J)^-1`` times the residual variance (NaN when not determined). ``cross``: the
    weighted residuals' correlation matrix where it is not the identity (leading rows, the
    rest independent), giving the sandwich ``B J^T C J B`` with ``B = (J^T J)^-1``."""
    m = sol.fun.size
    if m <= n_params:
        return np.full((n_params, n_params), np.nan)
    s2 = float(np.sum(sol.fun**2)) / (m - n_params)
    try:
        B = np.linalg.inv(sol.jac.T @ sol.jac)
    except np.linalg.LinAlgError:
        return np.full((n_params, n_params), np.nan)
    if cross is None:
        return B * s2
    J = sol.jac[: len(cross)]
    meat = sol.jac.T @ sol.jac + J.T @ (cross - np.eye(len(cross))) @ J
    return B @ meat @ B * s2


# --- accelerometer ------------------------------------------------------------------------
@dataclass(frozen=True)
class AccelPoseFit:
    params: np.ndarray  # ACCEL_PARAM_NAMES, output m/s^2 (with g_local)
    stderr: np.ndarray
    x0: np.ndarray  # starting point
    residual_mg: np.ndarray  # per fitted pose, |f| - g in mg
    cov: np.ndarray | None = None
    pose_noise_mg: float = 0.0  # tau: the pose-to-pose |f| noise beyond the poses' own
    prior_used: tuple[bool, ...] = (False, False, False)  # a_yz a_zy a_zx kept the prior


def initial_accel_params(
    accel_means: np.ndarray, g_local: float, scale: float | None = None, bias=None
) -> np.ndarray:
    """Starting point: no misalignment; bias the centre of the poses' range per axis (or
    given); scale given (m/s^2 per count, e.g. from the full-scale range) or from the median
    radius of the poses around that centre."""
    b = (
        0.5 * (accel_means.max(axis=0) + accel_means.min(axis=0))
        if bias is None
        else np.broadcast_to(np.asarray(bias, float), (3,)).copy()
    )
    if scale is None:
        scale = g_local / np.median(np.linalg.norm(accel_means - b, axis=1))
    return np.concatenate([np.zeros(3), np.full(3, float(scale)), b])


@dataclass(frozen=True)
class Priors:
    """Datasheet tolerance as a Gaussian prior (MAP), for sessions with few poses or moves
    where 9 parameters per sensor are barely determined: every misalignment ~ N(0,
    misalignment^2) rad. The default is half the cross-axis sensitivity limit of consumer
    MEMS parts (MPU-6050: +/-2 %), i.e. the limit taken as 2 sigma. ``None`` switches it
    off. With tens of poses the data outweigh it (a 0.054 rad misalignment on the Xsens
    recording moves by < 1 %)."""

    misalignment: float | None = 0.01


def _pose_norm_se_mg(accel_se: np.ndarray, scale_g_per_unit: float) -> np.ndarray:
    """Standard error of each pose's |mean f| in mg (isotropic approximation) from the
    per-axis errors of its accel mean (raw units)."""
    return 1e3 * np.linalg.norm(accel_se, axis=1) / np.sqrt(3) * scale_g_per_unit


def fit_accel_poses(
    pm: PoseMeans, g_local: float, x0: np.ndarray, use=None, priors: Priors = Priors()
) -> AccelPoseFit:
    """9 accel parameters from the poses' |mean f|, each residual divided by its standard
    error (mg), plus the misalignment prior in the same normalised units; standard errors
    scaled by the residual variance.

    A pose's |f| error is the noise of its mean plus a pose-to-pose part ``tau`` the noise
    does not show (placement on an uneven support, a hand's residual acceleration,
    hysteresis). When the fit leaves at least ``MIN_TAU_DOF`` degrees of freedom, ``tau`` is
    estimated from the residuals (variance components, method of moments) with the means'
    batch-means errors (``accel_se_batch``: the within-pose std over sqrt(count / 0.25 s)
    overstates a still unit's white noise ~5x and would hide ``tau``), and each pose is
    weighted by ``1/sqrt(se^2 + tau^2)``, so that a very still pose does not outweigh the
    others by a noise that is not its error. With fewer poses the weights are
    ``1/accel_se`` (from all of a pose's samples: steadier than a few block means).

    The prior acts on the misalignments the data do not determine: with ``MIN_TAU_DOF``
    degrees of freedom, a misalignment whose standard error without the prior is below the
    prior's sigma is left to the data (``prior_used`` says which ones kept it)."""
    use = np.ones(len(pm), bool) if use is None else np.asarray(use, bool)
    X = pm.accel[use]
    need = MIN_ACCEL_POSES_WITH_PRIOR if priors.misalignment else MIN_ACCEL_POSES
    if len(X) < need:
        raise DesignError(
            "E_FIELD_TOO_FEW_POSES",
            f"{len(X)} static poses: the accelerometer's 9 parameters need at least {need}",
            undetermined=ACCEL_PARAM_NAMES,
        )
    dof = len(X) - 9
    estimate_tau = dof >= MIN_TAU_DOF and pm.accel_se_batch is not None
    se_per_axis = pm.accel_se_batch if estimate_tau else pm.accel_se
    se = np.maximum(_pose_norm_se_mg(se_per_axis, float(np.mean(x0[3:6])) / g_local)[use], 1e-6)
    mis_sig = priors.misalignment

    def norm_err_mg(p):
        M, b = accel_matrix(p)
        return 1e3 * (np.linalg.norm((X - b) @ M.T, axis=1) / g_local - 1)

    def solve(start, sigma, prior_on):
        def resid(p):
            r = norm_err_mg(p) / sigma
            return np.concatenate([r, p[:3][prior_on] / mis_sig]) if prior_on.any() else r

        return least_squares(resid, np.asarray(start, float), method="lm", x_scale="jac")

    prior_on = np.full(3, bool(mis_sig))
    if mis_sig and estimate_tau:
        free = solve(x0, se, np.zeros(3, bool))
        free_se = np.sqrt(np.clip(np.diag(_covariance(free, 9)), 0, None))[:3]
        prior_on = ~(free_se < mis_sig)  # NaN (undetermined): the prior stays
    sol = solve(x0, se, prior_on)
    tau = 0.0
    if estimate_tau:
        for _ in range(3):  # tau moves the solution a little: re-estimated on it
            r = norm_err_mg(sol.x)
            tau = float(np.sqrt(max(0.0, float(np.sum(r**2)) / dof - float(np.mean(se**2)))))
            sol = solve(sol.x, np.sqrt(se**2 + tau**2), prior_on)
    cov = _covariance(sol, 9)
    return AccelPoseFit(
        sol.x,
        np.sqrt(np.clip(np.diag(cov), 0, None)),
        np.asarray(x0, float),
        norm_err_mg(sol.x),
        cov,
        tau,
        tuple(bool(v) for v in prior_on),
    )


def gravity_directions(accel_params: np.ndarray, accel_means: np.ndarray) -> np.ndarray:
    M, b = accel_matrix(accel_params)
    u = (np.asarray(accel_means) - b) @ M.T
    return u / np.linalg.norm(u, axis=1, keepdims=True)


# --- gyroscope ------------------------------------------------------------------------------
@dataclass(frozen=True)
class GyroJointFit:
    params: np.ndarray  # names: T_g, K_g (rad/s per raw unit), bias [, drift][, g-sensitivity]
    stderr: np.ndarray
    names: tuple[str, ...]
    drift: bool
    g_sensitivity: bool
    x0: np.ndarray
    sigma_move_rad: float  # RMS of the move residuals (variance component)
    sigma_quiet: float  # RMS of the quiet-pose residuals (in standard errors of the pose mean)
    n_moves: int
    n_quiet: int
    cov: np.ndarray | None = None  # covariance of params, accel parameters taken as known
    jac: np.ndarray | None = field(default=None, repr=False)  # weighted rows (data, then prior)
    weighted: object = field(default=None, repr=False, compare=False)  # (p, u, F) -> data rows
    wald: dict = field(default_factory=dict)  # block -> (statistic, threshold) when "auto" tested

    @property
    def matrix(self) -> np.ndarray:
        return gyro_matrix(self.params[:9])

    @property
    def bias(self) -> np.ndarray:
        return self.params[9:12]

    @property
    def drift_per_s(self) -> np.ndarray:
        return self.params[12:15] if self.drift else np.zeros(3)

    @property
    def g_sensitivity_raw(self) -> np.ndarray:
        """(3, 3) raw gyro units per g of calibrated specific force (zeros when not fitted)."""
        if not self.g_sensitivity:
            return np.zeros((3, 3))
        k = 15 if self.drift else 12
        return self.params[k : k + 9].reshape(3, 3)


def moves_of(mid: np.ndarray) -> list[tuple[int, int]]:
    """Sample ranges integrated for each move: middle of pose j to middle of pose j+1."""
    return [(int(mid[j]), int(mid[j + 1])) for j in range(len(mid) - 1)]


def tangent_bases(u: np.ndarray) -> np.ndarray:
    """(k, 3, 2): two orthonormal vectors perpendicular to each unit vector ``u_k``. A move's
    residual is the difference of two unit vectors, whose component along ``u_{j+1}`` is
    second order (``cos(angle) - 1``): its two components across ``u_{j+1}`` are the
    residual's degrees of freedom, and counting a third would understate the move noise by
    sqrt(2/3) in the variance components."""
    u = np.asarray(u, float)
    helper = np.eye(3)[np.argmin(np.abs(u), axis=1)]  # the axis least aligned with u
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return np.stack([e1, e2], axis=2)


def _gyro_residual_fn(t, G, F, integ, u, move_use, pm: PoseMeans, quiet_use, drift: bool, g_sens: bool):
    """Residual groups (moves, quiet poses) of the gyro model; ``F`` calibrated specific
    force (g) per sample, used by the g-sensitivity block. ``parts(p, u, F)`` takes other
    gravity directions / specific forces (the accelerometer's uncertainty propagation)."""
    samples = integ.samples  # only the samples the moves integrate
    G_s, t_s, F_s = G[samples], t[samples], F[samples]
    Gq, tq, se_q = pm.gyro[quiet_use], pm.t_mean[quiet_use], pm.gyro_se[quiet_use]
    j0, j1 = np.flatnonzero(move_use), np.flatnonzero(move_use) + 1
    k_s = 15 if drift else 12
    starts, ends = pm.start[quiet_use], pm.end[quiet_use]
    tangent = tangent_bases(u)

    def pose_means(F_):
        if not g_sens:
            return np.zeros((len(Gq), 3))
        return np.array([F_[a:b].mean(axis=0) for a, b in zip(starts, ends)]).reshape(-1, 3)

    Fq_of_F = pose_means(F)  # F is fixed but in the accelerometer's uncertainty propagation

    def parts(p, u_=u, F_=F):
        M = gyro_matrix(p[:9])
        b0 = p[9:12]
        b1 = p[12:15] if drift else np.zeros(3)
        S = p[k_s : k_s + 9].reshape(3, 3) if g_sens else np.zeros((3, 3))
        same_F = F_ is F
        corr = ((F_s if same_F else F_[samples]) @ S.T) if g_sens else 0.0
        q = integ.rotations_at_samples((G_s - b0 - t_s[:, None] * b1 - corr) @ M.T)
        r_move = np.einsum("mki,mk->mi", tangent[j1], _rotate_by_conjugate(q[j0], u_[j0]) - u_[j1]).ravel()
        Fq = Fq_of_F if same_F else pose_means(F_)
        r_quiet = ((Gq - b0 - tq[:, None] * b1 - Fq @ S.T) / se_q).ravel()
        return r_move, r_quiet

    return parts


def _shared_hold_correlation(
    parts_of, t, G, p, pm: PoseMeans, quiet_use, move_use, sig_m: float, sig_q: float
) -> np.ndarray:
    """Correlation matrix of the weighted residuals (moves, then quiet poses) from the gyro
    samples they share: a move integrates from the middle of one pose to the middle of the
    next, so the noise of each half of a quiet pose is in a move *and* in that pose's mean
    (its bias residual). Taken as independent, the two would count that noise twice and
    the bias and drift errors would be stated ~1.15x too small.

    Per half of a quiet pose and per axis, ``D``: the weighted residual of the move through
    that half, its change per raw unit of a constant offset on the half's samples (finite
    difference; ``parts_of(G, integrator)`` gives the residual function, here with only that
    move integrated). A half's mean noise carries the pose mean's variance (two independent
    halves, each twice the mean's variance, half of it shared), so its covariance with the
    weighted quiet row is ``D * se * sig_q`` (that row's noise is ``mean noise / (se
    sig_q)``, variance 1)."""
    moves = moves_of(pm.mid)
    row = np.cumsum(move_use) - 1  # each used move's first residual row / 2
    n_m, n_q = 2 * int(move_use.sum()), 3 * int(quiet_use.sum())
    X = np.zeros((n_m, n_q))
    h = max(float(np.median(pm.gyro_se)), 1e-9)
    for col, j in enumerate(np.flatnonzero(quiet_use)):
        for m, lo, hi in ((j - 1, pm.start[j], pm.mid[j]), (j, pm.mid[j], pm.end[j])):
            if not (0 <= m < len(moves) and move_use[m]) or hi <= lo:
                continue
            only_m = SegmentIntegrator(t, [mv if k == m else (mv[0], mv[0]) for k, mv in enumerate(moves)])
            rows = slice(2 * row[m], 2 * row[m] + 2)
            r0 = parts_of(G, only_m)(p)[0][rows]
            for a in range(3):
                Gp = G.copy()
                Gp[lo:hi, a] += h
                D = (parts_of(Gp, only_m)(p)[0][rows] - r0) / (h * sig_m)
                X[rows, 3 * col + a] += D * pm.gyro_se[j, a] * sig_q
    C = np.eye(n_m + n_q)
    C[:n_m, n_m:] = X
    C[n_m:, :n_m] = X.T
    return C


def group_redundancies(jac: np.ndarray, sizes: tuple[int, ...]) -> list[float]:
    """Redundancy of each consecutive group of rows: its row count minus its share of the
    hat matrix' trace (the parameters it determines), at least 0.5. Dividing a group's sum
    of squares by it (rather than by its row count) is the unbiased variance component: a
    group that determines most parameters would otherwise look quieter than it is."""
    try:
        h = np.sum(jac * np.linalg.solve(jac.T @ jac, jac.T).T, axis=1)
    except np.linalg.LinAlgError:
        h = np.zeros(len(jac))
    out, k = [], 0
    for n in sizes:
        out.append(max(n - float(np.sum(h[k : k + n])), 0.5))
        k += n
    return out


WALD_P = 1e-3  # an optional block is kept when its Wald test rejects "zero" at this level


def fit_gyro_joint(
    t,
    G,
    pm: PoseMeans,
    u: np.ndarray,
    move_use=None,
    drift: bool | str = "auto",
    init_scale: float | None = None,
    init_bias=None,
    priors: Priors = Priors(),
    g_sensitivity: bool | str = False,
    F: np.ndarray | None = None,
) -> GyroJointFit:
    """Joint fit of the gyro (see the module docstring). ``move_use`` selects the moves
    fitted (default all). Optional blocks, each True/False or ``"auto"`` (fitted, then kept
    only if its Wald statistic ``x^T Cov^-1 x`` exceeds the chi-square quantile at
    ``WALD_P``; a drift is only tried with three or more quiet poses at different times):
    ``drift`` (bias linear in time, counts per s) and ``g_sensitivity`` (bias
    linear in the calibrated specific force ``F``, (n, 3) in g, raw units per g).
    ``init_scale`` rad/s per raw unit (e.g. from the full-scale range); without it an
    isotropic scale is found on a coarse log grid."""
    from scipy.stats import chi2

    t, G = np.asarray(t, float), np.asarray(G, float)
    moves = moves_of(pm.mid)
    move_use = np.ones(len(moves), bool) if move_use is None else np.asarray(move_use, bool)
    if move_use.sum() < MIN_MOVES:
        raise DesignError(
            "E_FIELD_TOO_FEW_POSES",
            f"{int(move_use.sum())} moves between static poses: the gyro needs at least {MIN_MOVES}",
            undetermined=GYRO_PARAM_NAMES,
        )
    quiet_use = pm.gyro_quiet.copy()
    if not quiet_use.any():
        raise DesignError(
            "E_FIELD_NO_QUIET_POSE",
            "no pose where the gyro is at rest: the gyro bias is not determined",
            undetermined=GYRO_BIAS_NAMES,
        )
    if init_bias is None:
        init_bias = np.average(pm.gyro[quiet_use], axis=0, weights=pm.count[quiet_use])
    b0 = np.broadcast_to(np.asarray(init_bias, float), (3,)).copy()
    n_quiet_times = len(np.unique(np.round(pm.t_mean[quiet_use], 3)))
    if "auto" in (drift, g_sensitivity):
        # "auto" needs a third quiet pose: through two, a line fits exactly and a hand's
        # wobble in one of them would pass for a drift
        try_drift = drift == "auto" and n_quiet_times >= 3 or drift is True
        try_gs = g_sensitivity == "auto" and quiet_use.sum() >= 5 or g_sensitivity is True
        full = fit_gyro_joint(t, G, pm, u, move_use, try_drift, init_scale, b0, priors, try_gs, F)
        wald = {}
        keep_drift, keep_gs = bool(drift is True), bool(g_sensitivity is True)
        blocks = []
        if drift == "auto" and try_drift:
            blocks.append(("drift", slice(12, 15)))
        if g_sensitivity == "auto" and try_gs:
            k = 15 if try_drift else 12
            blocks.append(("g_sensitivity", slice(k, k + 9)))
        for name, sl in blocks:
            x, cov = full.params[sl], full.cov[sl, sl]
            try:
                stat = float(x @ np.linalg.solve(cov, x))
            except np.linalg.LinAlgError:
                stat = 0.0
            thr = float(chi2.ppf(1 - WALD_P, len(x)))
            wald[name] = (stat, thr)
            if name == "drift":
                keep_drift = stat > thr
            else:
                keep_gs = stat > thr
        if keep_drift == try_drift and keep_gs == try_gs:
            return GyroJointFit(**{**full.__dict__, "wald": wald})
        fit = fit_gyro_joint(t, G, pm, u, move_use, keep_drift, init_scale, b0, priors, keep_gs, F)
        return GyroJointFit(**{**fit.__dict__, "wald": wald})
    drift, g_sensitivity = bool(drift), bool(g_sensitivity)
    if drift and n_quiet_times < 2:
        raise DesignError(
            "E_FIELD_DRIFT", "a bias drift needs at least two gyro-quiet poses", undetermined=GYRO_DRIFT_NAMES
        )
    if g_sensitivity and F is None:
        raise ValueError("g_sensitivity needs the calibrated specific force F")
    F = np.zeros((len(G), 3)) if F is None else np.asarray(F, float)
    integ = SegmentIntegrator(t, moves)
    parts = _gyro_residual_fn(t, G, F, integ, u, move_use, pm, quiet_use, drift, g_sensitivity)
    extra = np.zeros((3 if drift else 0) + (9 if g_sensitivity else 0))
    if init_scale is None:  # isotropic scale from a coarse log grid (no datasheet value given)
        grid = np.logspace(-8, 1, 73)  # 8 per decade: steps of x1.33
        costs = [np.sum(parts(np.r_[np.zeros(6), s, s, s, b0, extra])[0] ** 2) for s in grid]
        init_scale = grid[int(np.argmin(costs))]
    x0 = np.r_[np.zeros(6), np.full(3, float(init_scale)), b0, extra]
    sig_m, sig_q = 1e-3, 1.0
    x = x0
    mis_sig = priors.misalignment
    for _ in range(3):  # variance components: weight each group by its own RMS

        def resid(p, sm=sig_m, sq=sig_q):
            rm, rq = parts(p)
            r = [rm / sm, rq / sq]
            if mis_sig:
                r.append(p[:6] / mis_sig)
            return np.concatenate(r)

        sol = least_squares(resid, x, method="lm", x_scale="jac")
        sig_m_used, sig_q_used = sig_m, sig_q
        x = sol.x
        rm, rq = parts(x)
        red_m, red_q = group_redundancies(sol.jac, (rm.size, rq.size))
        sig_m = max(float(np.sqrt(np.sum(rm**2) / red_m)), 1e-9)
        sig_q = max(float(np.sqrt(np.sum(rq**2) / red_q)), 1e-12)
    names = (
        GYRO_PARAM_NAMES
        + GYRO_BIAS_NAMES
        + (GYRO_DRIFT_NAMES if drift else ())
        + (GYRO_G_SENS_NAMES if g_sensitivity else ())
    )
    sm_final, sq_final = sig_m_used, sig_q_used
    cross = _shared_hold_correlation(
        lambda G_, integ_: _gyro_residual_fn(
            t, G_, F, integ_, u, move_use, pm, quiet_use, drift, g_sensitivity
        ),
        t,
        G,
        sol.x,
        pm,
        quiet_use,
        move_use,
        sm_final,
        sq_final,
    )
    cov = _covariance(sol, len(x0), cross)

    def weighted(p, u_, F_):
        rm, rq = parts(p, u_, F_)
        return np.concatenate([rm / sm_final, rq / sq_final])

    return GyroJointFit(
        sol.x,
        np.sqrt(np.clip(np.diag(cov), 0, None)),
        names,
        drift,
        g_sensitivity,
        x0,
        sig_m,
        sig_q,
        int(move_use.sum()),
        int(quiet_use.sum()),
        cov=cov,
        jac=sol.jac,
        weighted=weighted,
    )


def _with_accel_uncertainty(
    gyr: GyroJointFit, acc: AccelPoseFit, A, pm: PoseMeans, g_local: float
) -> GyroJointFit:
    """Gyro covariance including the accelerometer's: the gravity directions (and the
    specific force of the g-sensitivity) come from the accel parameters, so to first order
    ``dx_g = D dx_a`` with ``D = -(J_g^T J_g)^-1 J_g^T J_a`` (``J_a`` by central differences
    of the gyro's weighted residuals in the accel parameters) and
    ``Cov_g = Cov_g|a + D Cov_a D^T``."""
    cov_a = _covariance_from_stderr(acc)
    if gyr.jac is None or not np.all(np.isfinite(cov_a)):
        return gyr
    pa = acc.params
    cols = []
    for i in range(9):
        h = max(float(acc.stderr[i]), 1e-9 * max(abs(pa[i]), 1.0))
        r = []
        for sign in (1, -1):
            q = pa.copy()
            q[i] += sign * h
            M, b = accel_matrix(q)
            r.append(gyr.weighted(gyr.params, gravity_directions(q, pm.accel), (A - b) @ (M / g_local).T))
        cols.append((r[0] - r[1]) / (2 * h))
    J_g = gyr.jac
    J_a = np.zeros((len(J_g), 9))  # prior rows do not depend on the accel
    J_a[: len(cols[0])] = np.column_stack(cols)
    try:
        D = -np.linalg.solve(J_g.T @ J_g, J_g.T @ J_a)
    except np.linalg.LinAlgError:
        return gyr
    cov = gyr.cov + D @ cov_a @ D.T
    return GyroJointFit(**{**gyr.__dict__, "cov": cov, "stderr": np.sqrt(np.clip(np.diag(cov), 0, None))})


def _covariance_from_stderr(acc: AccelPoseFit) -> np.ndarray:
    return acc.cov if acc.cov is not None else np.diag(acc.stderr**2)


# --- the calibration -----------------------------------------------------------------------
def to_calibration(
    accel_params,
    gyro_matrix_rad,
    bias,
    drift_per_s,
    g_local: float,
    gyro_unit: str,
    accel_unit: str,
    metadata: dict | None = None,
    g_sensitivity_raw=None,
) -> Calibration:
    """IMU-TK parameters -> the affine form (deg/s, g) with the drift as the catalogue term
    ``thermal_bias_drift`` (time form: deg/s per hour, ``t`` in s since the first sample) and
    the g-sensitivity as ``gyro_g_sensitivity`` (deg/s per g)."""
    M_a, b_a = accel_matrix(np.asarray(accel_params, float))
    K_a = M_a / g_local
    K_g = np.degrees(np.asarray(gyro_matrix_rad, float))
    terms = []
    if np.any(np.asarray(drift_per_s) != 0):
        d = np.r_[K_g @ np.asarray(drift_per_s, float) * 3600.0, np.zeros(3)]
        terms.append(TermValue("thermal_bias_drift", d))
    if g_sensitivity_raw is not None and np.any(np.asarray(g_sensitivity_raw) != 0):
        terms.append(TermValue("gyro_g_sensitivity", (K_g @ np.asarray(g_sensitivity_raw)).reshape(-1)))
    terms = tuple(terms)
    return Calibration(
        K_g=K_g,
        w0=-K_g @ np.asarray(bias, float),
        K_a=K_a,
        f0=-K_a @ b_a,
        gyro_unit=gyro_unit,
        accel_unit=accel_unit,
        g_local=g_local,
        kind="field",
        terms=terms,
        metadata=dict(metadata or {}),
    )


@dataclass(frozen=True)
class FieldJointFit:
    calibration: Calibration
    start: Calibration  # the starting point (nominal scale, pose-centre bias, rest-mean gyro bias)
    accel: AccelPoseFit
    gyro: GyroJointFit
    pose_means: PoseMeans
    pose_use: np.ndarray
    move_use: np.ndarray

    def params(self) -> dict[str, float]:
        out = {n: float(v) for n, v in zip(ACCEL_PARAM_NAMES, self.accel.params)}
        out.update({n: float(v) for n, v in zip(self.gyro.names, self.gyro.params)})
        return out

    def stderrs(self) -> dict[str, float]:
        out = {n: float(v) for n, v in zip(ACCEL_PARAM_NAMES, self.accel.stderr)}
        out.update({n: float(v) for n, v in zip(self.gyro.names, self.gyro.stderr)})
        return out


def fit_field(
    t,
    G,
    A,
    poses,
    g_local: float,
    accel_scale: float | None = None,
    gyro_scale: float | None = None,
    accel_bias=None,
    drift: bool | str = "auto",
    pose_use=None,
    move_use=None,
    gyro_unit: str = "LSB",
    accel_unit: str = "LSB",
    priors: Priors = Priors(),
    g_sensitivity: bool | str = "auto",
    metadata: dict | None = None,
) -> FieldJointFit:
    """Field calibration: the accel on the |f| of the poses in ``pose_use`` (default all),
    then the gyro on the moves in ``move_use`` (default all) and the quiet poses with the
    accel's gravity directions, deciding the bias drift and the gyro g-sensitivity
    (``"auto"``: kept when the data show them, see :func:`fit_gyro_joint`). ``accel_scale`` m/s^2 and
    ``gyro_scale`` rad/s per raw unit are starting values (full-scale range / 32768);
    ``accel_bias`` a starting bias (default: centre of the poses)."""
    t, G, A = (np.asarray(x, float) for x in (t, G, A))
    rate = 1.0 / np.median(np.diff(t))
    pm = pose_means(t, G, A, poses, odd_window(rate, CORR_WINDOW_S), max(int(round(ACCEL_BATCH_S * rate)), 1))
    pose_use = np.ones(len(pm), bool) if pose_use is None else np.asarray(pose_use, bool)
    move_use = np.ones(max(len(pm) - 1, 0), bool) if move_use is None else np.asarray(move_use, bool)
    x0 = initial_accel_params(pm.accel[pose_use], g_local, accel_scale, accel_bias)
    acc = fit_accel_poses(pm, g_local, x0, pose_use, priors)
    u = gravity_directions(acc.params, pm.accel)
    M_a, b_a = accel_matrix(acc.params)
    F = (A - b_a) @ (M_a / g_local).T  # calibrated specific force, g
    gyr = fit_gyro_joint(
        t, G, pm, u, move_use, drift, gyro_scale, priors=priors, g_sensitivity=g_sensitivity, F=F
    )
    gyr = _with_accel_uncertainty(gyr, acc, A, pm, g_local)
    meta = {
        "method": "hand-held poses: accel |f| per pose mean; gyro scale, misalignment, bias "
        "(and drift) jointly over the moves and the quiet poses",
        "n_poses": int(pose_use.sum()),
        "n_moves": int(move_use.sum()),
        "n_quiet_poses": gyr.n_quiet,
        "gyro_bias_drift": gyr.drift,
        "gyro_g_sensitivity": gyr.g_sensitivity,
        "misalignment_prior_rad": priors.misalignment,
        "misalignment_prior_applied": dict(zip(ACCEL_PARAM_NAMES[:3], acc.prior_used)),
        "accel_pose_noise_mg": acc.pose_noise_mg,
        **(metadata or {}),
    }
    cal = to_calibration(
        acc.params,
        gyr.matrix,
        gyr.bias,
        gyr.drift_per_s,
        g_local,
        gyro_unit,
        accel_unit,
        meta,
        gyr.g_sensitivity_raw,
    )
    start = to_calibration(
        acc.x0,
        gyro_matrix(gyr.x0[:9]),
        gyr.x0[9:12],
        np.zeros(3),
        g_local,
        gyro_unit,
        accel_unit,
        {"method": "starting point"},
    )
    return FieldJointFit(cal, start, acc, gyr, pm, pose_use, move_use)


# --- figures of merit ---------------------------------------------------------------------
@dataclass(frozen=True)
class FieldFigures:
    norm_err_mg: np.ndarray  # per pose: |mean calibrated f| - 1 g
    angle_deg: np.ndarray  # per move: gravity direction predicted by the gyro vs measured

    def summary(self, prefix: str = "", move_ok=None) -> dict[str, float]:
        e, a = self.norm_err_mg, self.angle_deg
        if move_ok is not None:
            a = a[np.asarray(move_ok, bool)]
        return {
            f"{prefix}norm_rms_mg": float(np.sqrt(np.mean(e**2))) if e.size else float("nan"),
            f"{prefix}norm_std_mg": float(np.std(e)) if e.size else float("nan"),
            f"{prefix}angle_rms_deg": float(np.sqrt(np.mean(a**2))) if a.size else float("nan"),
            f"{prefix}angle_max_deg": float(np.max(a)) if a.size else float("nan"),
            f"{prefix}n_poses": int(e.size),
            f"{prefix}n_moves": int(a.size),
        }


def field_figures(cal: Calibration, t, G, A, poses) -> FieldFigures:
    """|f| error per pose and gravity-direction angle per move (pose middle to pose middle,
    on the sample times) of any calibration in the affine form."""
    t, G, A = (np.asarray(x, float) for x in (t, G, A))
    pm = pose_means(t, G, A, poses)
    moves = moves_of(pm.mid)
    span = slice(min(a for a, _ in moves), max(b for _, b in moves) + 1) if moves else slice(0, 0)
    w = np.zeros((len(t), 3))
    if moves:
        w[span], _ = cal.apply(G[span], A[span], t=t[span])
    # pose-mean specific force: affine on the mean equals the mean of the affine per sample
    _, f = cal.apply(pm.gyro, pm.accel, t=pm.t_mean)
    norm_err = 1e3 * (np.linalg.norm(f, axis=1) - 1.0)
    if not moves:
        return FieldFigures(norm_err, np.zeros(0))
    u = f / np.linalg.norm(f, axis=1, keepdims=True)
    q = SegmentIntegrator(t, moves).rotations(np.radians(w))
    pred = _rotate_by_conjugate(q, u[:-1])
    c = np.clip(np.sum(pred * u[1:], axis=1) / np.linalg.norm(pred, axis=1), -1, 1)
    return FieldFigures(norm_err, np.degrees(np.arccos(c)))


def usable_moves(G: np.ndarray, poses, clipped: np.ndarray | None = None) -> np.ndarray:
    """Moves (pose middle to next pose middle) with no clipped gyro sample: a saturated
    output loses rotation, so such a move is neither fitted nor used as a figure of merit."""
    n_m = max(len(poses) - 1, 0)
    if clipped is None:
        return np.ones(n_m, bool)
    c = np.concatenate([[0], np.cumsum(np.asarray(clipped, bool))])
    mids = [p.mid for p in poses]
    return np.array([c[mids[j + 1]] - c[mids[j]] == 0 for j in range(n_m)], bool)


@dataclass(frozen=True)
class HeldOut:
    """Figures on data left out of the fit. Poses are dealt to folds in turn and each fold
    refitted without the |f| of its poses, then evaluated on them (``norm_err_mg``); the
    usable moves likewise, refitted without the fold's moves and evaluated on them
    (``angle_deg``, NaN for unusable moves). Each pose and each move is held out once. NaN
    where a fold could not be fitted (listed in ``notes``)."""

    norm_err_mg: np.ndarray
    angle_deg: np.ndarray
    pose_folds: int
    move_folds: int
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        e, a = self.norm_err_mg[np.isfinite(self.norm_err_mg)], self.angle_deg[np.isfinite(self.angle_deg)]
        return {
            **FieldFigures(e, a).summary("held_out_"),
            "held_out_pose_folds": self.pose_folds,
            "held_out_move_folds": self.move_folds,
        }


def default_folds(n: int) -> int:
    """Leave-one-out up to 15 items (each fold keeps as much as possible for 9 parameters),
    5 folds beyond."""
    return n if n <= 15 else 5


def held_out_figures(
    t, G, A, poses, g_local: float, move_ok=None, n_folds: int | None = None, **fit_kwargs
) -> HeldOut:
    """k-fold held-out figures of :func:`fit_field` (see :class:`HeldOut`); ``move_ok`` the
    usable moves (:func:`usable_moves`). Optional gyro blocks left on ``"auto"`` are decided
    on all data first and then fixed in every fold."""
    t, G, A = (np.asarray(x, float) for x in (t, G, A))
    n_p = len(poses)
    move_ok = np.ones(max(n_p - 1, 0), bool) if move_ok is None else np.asarray(move_ok, bool)
    ok_idx = np.flatnonzero(move_ok)
    if "auto" in (fit_kwargs.get("drift", "auto"), fit_kwargs.get("g_sensitivity", "auto")):
        # the optional gyro blocks are chosen once, on all data, and kept in every fold
        full = fit_field(t, G, A, poses, g_local, move_use=move_ok, **fit_kwargs)
        fit_kwargs = {**fit_kwargs, "drift": full.gyro.drift, "g_sensitivity": full.gyro.g_sensitivity}
    pf = default_folds(n_p) if n_folds is None else int(n_folds)
    mf = default_folds(len(ok_idx)) if n_folds is None else int(n_folds)
    norm_err, angle = np.full(n_p, np.nan), np.full(len(move_ok), np.nan)
    notes: list[str] = []
    fold_p = np.arange(n_p) % pf
    for k in range(pf):
        out = fold_p == k
        try:
            fit = fit_field(t, G, A, poses, g_local, pose_use=~out, move_use=move_ok, **fit_kwargs)
        except DesignError as exc:
            notes.append(f"pose fold {k}: {exc.reason}")
            continue
        norm_err[out] = field_figures(fit.calibration, t, G, A, poses).norm_err_mg[out]
    fold_m = np.arange(len(ok_idx)) % max(mf, 1)
    for k in range(mf):
        out = np.zeros(len(move_ok), bool)
        out[ok_idx[fold_m == k]] = True
        try:
            fit = fit_field(t, G, A, poses, g_local, move_use=move_ok & ~out, **fit_kwargs)
        except DesignError as exc:
            notes.append(f"move fold {k}: {exc.reason}")
            continue
        angle[out] = field_figures(fit.calibration, t, G, A, poses).angle_deg[out]
    return HeldOut(norm_err, angle, pf, mf, notes)
