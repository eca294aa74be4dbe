"""Reference-free multi-position calibration (Tedaldi, Pretto, Menegatti, ICRA 2014; IMU-TK).

The unit is moved by hand through many static poses. No reference is known except that

* at rest the calibrated specific force has the magnitude of local gravity (accelerometer);
* the gyro, integrated over the motion between two consecutive poses, must rotate the
  gravity direction measured in the first pose onto the one measured in the second (gyro).

Models (IMU-TK's ``CalibratedTriad``: ``x' = T K (x - b)``, ``K`` diagonal scale):

* accel, 9 parameters: ``T_a = [[1, -a_yz, a_zy], [0, 1, -a_zx], [0, 0, 1]]`` (triangular: the
  body frame is defined by the accelerometer axes, so three of the six misalignments are not
  observable and are fixed at 0, as in IMU-TK's ``MultiPosAccResidual``), scale ``s_a``, bias
  ``b_a``; output m/s^2. Residual per static sample: ``g - |T_a K_a (a - b_a)|``.
* gyro, 9 parameters: full misalignment ``T_g = [[1, -g_yz, g_zy], [g_xz, 1, -g_zx],
  [-g_xy, g_yx, 1]]`` and scale ``s_g`` (rad/s per raw unit); the bias is the mean over the
  initial static period and is not refined (IMU-TK's default). Residual per transition:
  ``dR^T u_0 - u_1`` (3 components) with ``dR`` the product of ``exp(w_k dt_k)`` over the
  samples between the two poses and ``u`` the unit gravity direction of each pose.

Static detection (:mod:`calib_core.models.field.static_detection`) uses Tedaldi's data-driven threshold:
``k * noise floor`` with the floor from the initial static period, and, as IMU-TK does,
``k = 2..10`` is scanned and the one whose accelerometer fit has the lowest cost is kept.
Only the central ``interval_samples`` samples of each static interval are used.

The result is expressed in the affine form of :class:`calib_core.calibration.Calibration`:
``K_a = T_a K_a / g_local`` (g per raw unit), ``f0 = -K_a b_a``; ``K_g = (180/pi) T_g K_g``
(deg/s per raw unit), ``w0 = -K_g b_g``. Solved with ``scipy.optimize.least_squares``.
Differences from IMU-TK: rotations are integrated with the exact exponential of each sample's
rate over its own time step (IMU-TK uses Runge-Kutta 4 on quaternions with a fixed dt).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from calib_core.calibration import Calibration, TermValue
from calib_core.effects import SensingGeometry
from calib_core.errors import DesignError
from calib_core.models.field.static_detection import (
    StaticDetection,
    central_samples,
    detect_static,
    runs_of,
    static_pose_means,
)

ACCEL_PARAM_NAMES = ("a_yz", "a_zy", "a_zx", "s_ax", "s_ay", "s_az", "b_ax", "b_ay", "b_az")
GYRO_PARAM_NAMES = ("g_yz", "g_zy", "g_zx", "g_xz", "g_xy", "g_yx", "s_gx", "s_gy", "s_gz")


# --- models ---------------------------------------------------------------------------------
def misalignment(yz=0.0, zy=0.0, zx=0.0, xz=0.0, xy=0.0, yx=0.0) -> np.ndarray:
    """IMU-TK's misalignment matrix T."""
    return np.array([[1.0, -yz, zy], [xz, 1.0, -zx], [-xy, yx, 1.0]])


def accel_matrix(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T_a K_a, b_a) from the 9 accelerometer parameters (output m/s^2 or the g unit used)."""
    return misalignment(p[0], p[1], p[2]) @ np.diag(p[3:6]), np.asarray(p[6:9])


def gyro_matrix(p: np.ndarray) -> np.ndarray:
    """T_g K_g from the 9 gyro parameters (output rad/s)."""
    return misalignment(*p[:6]) @ np.diag(p[6:9])


# --- accelerometer ----------------------------------------------------------------------------
def _samples_of(intervals) -> np.ndarray:
    return np.concatenate([np.arange(a, b) for a, b in intervals]) if intervals else np.zeros(0, int)


def fit_accel_field(A: np.ndarray, intervals, g_local: float, x0: np.ndarray):
    """Least-squares fit of the 9 accelerometer parameters on the samples of ``intervals``.
    Returns (params, cost = 0.5 sum r^2 as Ceres reports it, residuals m/s^2)."""
    X = np.asarray(A, float)[_samples_of(intervals)]

    def resid(p):
        M, b = accel_matrix(p)
        return g_local - np.linalg.norm((X - b) @ M.T, axis=1)

    sol = least_squares(resid, np.asarray(x0, float), method="lm", x_scale="jac")
    return sol.x, float(sol.cost), sol.fun


@dataclass(frozen=True)
class AccelFieldFit:
    params: np.ndarray  # ACCEL_PARAM_NAMES
    cost: float
    multiplier: int  # threshold multiplier kept (lowest cost)
    detection: StaticDetection  # detection with that multiplier (statistic, threshold, intervals)
    extracted: tuple[tuple[int, int], ...]  # central samples actually used, [start, end)
    residual_rms: float  # m/s^2 (|f| - g over the used samples)
    costs: dict[int, float] = field(default_factory=dict)  # per multiplier tried

    @property
    def matrix(self) -> np.ndarray:
        return accel_matrix(self.params)[0]

    @property
    def bias(self) -> np.ndarray:
        return self.params[6:9]


def _initial_accel_guess(A, init_bias, init_scale, g_local, intervals):
    static_means = np.array([A[a:b].mean(axis=0) for a, b in intervals])
    if init_bias is None:  # centre of the poses' range per axis
        init_bias = 0.5 * (static_means.max(axis=0) + static_means.min(axis=0))
    b = np.broadcast_to(np.asarray(init_bias, float), (3,)).copy()
    if init_scale is None:
        init_scale = g_local / np.median(np.linalg.norm(static_means - b, axis=1))
    s = np.broadcast_to(np.asarray(init_scale, float), (3,)).copy()
    return np.concatenate([np.zeros(3), s, b])


def calibrate_accel_field(
    A: np.ndarray,
    g_local: float,
    init_samples: int,
    window: int = 101,
    multipliers=range(2, 11),
    interval_samples: int = 100,
    min_intervals: int = 12,
    init_bias=None,
    init_scale=None,
) -> AccelFieldFit:
    """IMU-TK's ``calibrateAcc``: scan threshold multipliers, keep the lowest-cost fit."""
    A = np.asarray(A, float)
    best = None
    costs: dict[int, float] = {}
    for k in multipliers:
        det = detect_static(A, window=window, multiplier=k, init_samples=init_samples)
        ext = central_samples(det.intervals, interval_samples)
        if len(ext) < min_intervals:
            continue
        x0 = _initial_accel_guess(A, init_bias, init_scale, g_local, ext)
        p, cost, r = fit_accel_field(A, ext, g_local, x0)
        costs[int(k)] = cost
        if best is None or cost < best[1]:
            best = (p, cost, int(k), det, tuple(ext), float(np.sqrt(np.mean(r**2))))
    if best is None:
        raise DesignError(
            "E_FIELD_TOO_FEW_POSES",
            f"fewer than {min_intervals} static poses of >= {interval_samples} samples "
            f"found with threshold multipliers {list(multipliers)}",
            undetermined=ACCEL_PARAM_NAMES,
        )
    return AccelFieldFit(best[0], best[1], best[2], best[3], best[4], best[5], costs)


# --- gyroscope ------------------------------------------------------------------------------
def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(v, axis=-1)
    half_sinc = 0.5 * np.sinc(angle / (2 * np.pi))  # sin(angle/2)/angle, finite at 0
    return np.concatenate([np.cos(angle / 2)[..., None], v * half_sinc[..., None]], axis=-1)


def _rotate_by_conjugate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q)^T v for unit quaternions q (..., 4) and vectors v (..., 3)."""
    w, u = q[..., :1], -q[..., 1:]
    t = 2 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


class SegmentIntegrator:
    """Products of per-sample rotations over many segments at once. Each segment is cut into
    chunks of ``chunk`` samples (padded with identity rotations); chunk products and then the
    per-segment products of chunks are formed by pairwise multiplication (order kept), so one
    evaluation is a few vectorised passes instead of a Python loop over samples."""

    def __init__(self, t: np.ndarray, segments, chunk: int = 64):
        t = np.asarray(t, float)
        dt = np.diff(t, append=t[-1] + np.median(np.diff(t)))
        rows, owner = [], []
        for i, (a, b) in enumerate(segments):
            for c in range(a, max(b, a + 1), chunk):
                r = np.full(chunk, -1)
                stop = min(c + chunk, b)
                r[: max(stop - c, 0)] = np.arange(c, stop)
                rows.append(r)
                owner.append(i)
        self.idx = np.array(rows)
        self.dt = np.where(self.idx >= 0, dt[np.maximum(self.idx, 0)], 0.0)
        # the samples the segments integrate, and each chunk entry's place among them: a
        # residual needs the angular rate at these samples only (rotations_at_samples)
        self.samples = np.unique(self.idx[self.idx >= 0])
        if not len(self.samples):
            self.samples = np.zeros(1, int)
        self._local = np.searchsorted(self.samples, np.maximum(self.idx, 0))
        owner = np.array(owner)
        n_seg = len(segments)
        per_seg = np.bincount(owner, minlength=n_seg)
        width = 1 << int(np.ceil(np.log2(max(per_seg.max(), 1))))
        self.chunk_pos = np.full((n_seg, width), -1)
        for i in range(n_seg):
            self.chunk_pos[i, : per_seg[i]] = np.flatnonzero(owner == i)

    @staticmethod
    def _reduce(q: np.ndarray) -> np.ndarray:
        while q.shape[1] > 1:
            q = _qmul(q[:, 0::2], q[:, 1::2])
        return q[:, 0]

    def rotations(self, w: np.ndarray) -> np.ndarray:
        """Quaternion of dR = prod_k exp(w_k dt_k) per segment; ``w`` (n, 3) in rad/s."""
        return self._product(w[np.maximum(self.idx, 0)] * self.dt[..., None])

    def rotations_at_samples(self, w_samples: np.ndarray) -> np.ndarray:
        """As :meth:`rotations`, ``w_samples`` being the rate at :attr:`samples` only."""
        return self._product(w_samples[self._local] * self.dt[..., None])

    def _product(self, v: np.ndarray) -> np.ndarray:
        chunks = self._reduce(_quat_from_rotvec(v))
        chunks = np.vstack([chunks, [1.0, 0.0, 0.0, 0.0]])  # identity at index -1
        return self._reduce(chunks[self.chunk_pos])


def transition_segments(extracted) -> list[tuple[int, int]]:
    """Samples integrated between consecutive poses: from the end of the central samples of
    one pose to the start of the next (IMU-TK)."""
    return [(extracted[i][1], extracted[i + 1][0]) for i in range(len(extracted) - 1)]


def gravity_directions(A: np.ndarray, accel_params: np.ndarray, extracted) -> np.ndarray:
    M, b = accel_matrix(accel_params)
    u = np.array([(A[a:b_] - b).mean(axis=0) @ M.T for a, b_ in extracted])
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def transition_angles_deg(
    gyro_params: np.ndarray, G_unbiased: np.ndarray, integ: SegmentIntegrator, u: np.ndarray
) -> np.ndarray:
    """Angle between the gravity direction predicted by the gyro and the one measured, per
    transition (deg)."""
    q = integ.rotations_at_samples(G_unbiased[integ.samples] @ gyro_matrix(gyro_params).T)
    pred = _rotate_by_conjugate(q, u[:-1])
    c = np.clip(np.sum(pred * u[1:], axis=1) / np.linalg.norm(pred, axis=1), -1, 1)
    return np.degrees(np.arccos(c))


@dataclass(frozen=True)
class GyroFieldFit:
    params: np.ndarray  # GYRO_PARAM_NAMES (rad/s per raw unit)
    bias: np.ndarray  # raw unit: initial-period mean, or static-pose fit with g-sensitivity
    cost: float
    used: np.ndarray  # (m,) bool: transitions used in the fit
    angles_initial_deg: np.ndarray  # per transition, initial guess
    angles_deg: np.ndarray  # per transition, fitted

    @property
    def matrix(self) -> np.ndarray:
        return gyro_matrix(self.params)


def fit_gyro_field(
    t, G, A, accel_params, extracted, bias, init_scale=None, use: np.ndarray | None = None
) -> GyroFieldFit:
    """Fit the 9 gyro parameters on the transitions selected by ``use`` (default all)."""
    G0 = np.asarray(G, float) - bias
    u = gravity_directions(np.asarray(A, float), accel_params, extracted)
    segs = transition_segments(extracted)
    if len(segs) < 3:
        raise DesignError(
            "E_FIELD_TOO_FEW_POSES",
            f"{len(segs)} transitions: need at least 3",
            undetermined=GYRO_PARAM_NAMES,
        )
    integ = SegmentIntegrator(t, segs)
    use = np.ones(len(segs), bool) if use is None else np.asarray(use, bool)
    if 3 * use.sum() < 9:
        raise DesignError(
            "E_FIELD_TOO_FEW_POSES", "fewer than 3 transitions selected", undetermined=GYRO_PARAM_NAMES
        )

    G0_s = G0[integ.samples]

    def resid(p):
        q = integ.rotations_at_samples(G0_s @ gyro_matrix(p).T)
        return (_rotate_by_conjugate(q, u[:-1]) - u[1:])[use].ravel()

    if init_scale is None:  # isotropic scale from a coarse log grid (no datasheet value given)
        grid = np.logspace(-8, 1, 73)  # 8 per decade: steps of x1.33
        costs = [np.sum(resid(np.r_[np.zeros(6), s, s, s]) ** 2) for s in grid]
        init_scale = grid[int(np.argmin(costs))]
    x0 = np.r_[np.zeros(6), np.broadcast_to(np.asarray(init_scale, float), (3,))]
    sol = least_squares(resid, x0, method="lm", x_scale="jac")
    return GyroFieldFit(
        sol.x,
        np.asarray(bias, float),
        float(sol.cost),
        use,
        transition_angles_deg(x0, G0, integ, u),
        transition_angles_deg(sol.x, G0, integ, u),
    )


# --- the whole calibration ----------------------------------------------------------------
@dataclass(frozen=True)
class FieldCalibrationResult:
    calibration: Calibration  # kind="field"
    accel: AccelFieldFit
    gyro: GyroFieldFit
    pose_means: pd.DataFrame  # raw means of the poses where accel and gyro are both at rest
    stats: dict[str, float]

    def params(self) -> dict[str, float]:
        out = {n: float(v) for n, v in zip(ACCEL_PARAM_NAMES, self.accel.params)}
        out.update({n: float(v) for n, v in zip(GYRO_PARAM_NAMES, self.gyro.params)})
        out.update({f"b_g{c}": float(v) for c, v in zip("xyz", self.gyro.bias)})
        return out


def static_norm_stats(A, accel_M, accel_b, extracted, g_local) -> dict[str, float]:
    """|f| of the static samples used: RMS error vs g (mg) and relative spread (std/mean)."""
    X = np.asarray(A, float)[_samples_of(extracted)]
    n = np.linalg.norm((X - accel_b) @ np.asarray(accel_M).T, axis=1)
    return {
        "norm_rms_err_mg": float(1e3 * np.sqrt(np.mean((n / g_local - 1) ** 2))),
        "norm_rel_std": float(np.std(n) / np.mean(n)),
    }


def field_calibration(
    t,
    G,
    A,
    g_local: float,
    init_static_s: float = 50.0,
    window: int = 101,
    interval_samples: int = 100,
    min_intervals: int = 12,
    multipliers=range(2, 11),
    init_acc_bias=None,
    init_acc_scale=None,
    init_gyro_scale=None,
    gyro_unit: str = "LSB",
    accel_unit: str = "LSB",
    gyro_g_sensitivity: bool = False,
    metadata: dict | None = None,
) -> FieldCalibrationResult:
    """Tedaldi 2014 / IMU-TK calibration of a hand-moved multi-pose recording.

    ``A`` raw accel (any unit; the fit outputs m/s^2 with ``g_local``), ``G`` raw gyro;
    ``init_*`` are the initial guesses (IMU-TK's demo: acc bias 32768, gyro scale 1/6258 rad/s
    per count); ``None`` derives them from the data (acc: centre and radius of the static
    means; gyro: coarse grid over an isotropic scale). The recording must start with
    ``init_static_s`` seconds at rest (noise floor and gyro bias).

    ``gyro_g_sensitivity=True`` extends IMU-TK's model: the raw gyro bias is ``b + S f`` with
    ``f`` the calibrated specific force (g), ``b`` and ``S`` estimated by least squares from the
    static poses' raw gyro means (:func:`fit_static_gyro_g_sensitivity`; only static data,
    never the transitions), removed before the transitions are fitted, and stored as the
    catalogue term ``gyro_g_sensitivity`` (deg/s per g)."""
    t = np.asarray(t, float)
    G = np.asarray(G, float)
    A = np.asarray(A, float)
    init_samples = int(np.searchsorted(t, t[0] + init_static_s))
    if init_samples < window:
        raise DesignError(
            "E_FIELD_INIT_PERIOD",
            f"initial static period of {init_static_s} s has "
            f"{init_samples} samples, fewer than the window ({window})",
        )
    acc = calibrate_accel_field(
        A,
        g_local,
        init_samples,
        window,
        multipliers,
        interval_samples,
        min_intervals,
        init_acc_bias,
        init_acc_scale,
    )
    M_a, b_a = accel_matrix(acc.params)
    K_a = M_a / g_local
    f_all = (A - b_a) @ K_a.T  # calibrated specific force, g, every sample
    S_raw = None
    # where the gyro is quiet too: a slow turn about the vertical leaves the accelerometer
    # static but would put rotation rate into a pose's gyro mean
    gyro_quiet = detect_static(G, window=window, multiplier=acc.multiplier, init_samples=init_samples).mask
    quiet = [(a, b) for a, b in runs_of(acc.detection.mask & gyro_quiet) if b - a >= window]
    if gyro_g_sensitivity:
        bias_g, S_raw = fit_static_gyro_g_sensitivity(G, f_all, quiet)
        G_fit = G - f_all @ S_raw.T
    else:
        bias_g, G_fit = G[:init_samples].mean(axis=0), G
    gyro = fit_gyro_field(t, G_fit, A, acc.params, acc.extracted, bias_g, init_gyro_scale)

    K_g = np.degrees(gyro.matrix)
    # the catalogue's g-sensitivity is per gyro (own sensing direction, rows of A_g): the
    # body-frame rate error K_g S_raw f is A_g^-1 (A_g K_g S_raw) f
    A_g = SensingGeometry.from_gains(K_g, K_a).gyro_axes
    terms = () if S_raw is None else (TermValue("gyro_g_sensitivity", (A_g @ K_g @ S_raw).reshape(-1)),)
    cal = Calibration(
        K_g=K_g,
        w0=-K_g @ bias_g,
        K_a=K_a,
        f0=-K_a @ b_a,
        gyro_unit=gyro_unit,
        accel_unit=accel_unit,
        g_local=g_local,
        kind="field",
        terms=terms,
        metadata={
            "method": "Tedaldi, Pretto, Menegatti 2014 (IMU-TK)",
            "threshold_multiplier": acc.multiplier,
            "n_static_poses": len(acc.extracted),
            "init_static_s": init_static_s,
            "gyro_bias_from": (
                "static poses, with g-sensitivity" if gyro_g_sensitivity else "initial static period"
            ),
            **(metadata or {}),
        },
    )
    # initial-guess reference for the |f| spread: isotropic, no misalignment
    x0 = _initial_accel_guess(A, init_acc_bias, init_acc_scale, g_local, acc.extracted)
    before = static_norm_stats(A, accel_matrix(x0)[0], x0[6:9], acc.extracted, g_local)
    after = static_norm_stats(A, M_a, b_a, acc.extracted, g_local)
    stats = {
        "n_static_poses": len(acc.extracted),
        "threshold_multiplier": acc.multiplier,
        "threshold": acc.detection.threshold,
        "noise_floor": acc.detection.noise_floor,
        "accel_norm_rms_err_mg_initial": before["norm_rms_err_mg"],
        "accel_norm_rms_err_mg": after["norm_rms_err_mg"],
        "accel_norm_rel_std_initial": before["norm_rel_std"],
        "accel_norm_rel_std": after["norm_rel_std"],
        "gyro_angle_median_deg_initial": float(np.median(gyro.angles_initial_deg)),
        "gyro_angle_median_deg": float(np.median(gyro.angles_deg)),
        "gyro_angle_max_deg_initial": float(np.max(gyro.angles_initial_deg)),
        "gyro_angle_max_deg": float(np.max(gyro.angles_deg)),
    }
    # handover for model discovery: poses where both sensors are at rest
    means = static_pose_means(t, G, A, quiet)
    if len(means):
        w_pose, _ = cal.apply(means[["gx", "gy", "gz"]].to_numpy(), means[["ax", "ay", "az"]].to_numpy())
        stats["gyro_static_rate_rms_dps"] = float(np.sqrt(np.mean(w_pose**2)))
    stats["n_quiet_poses"] = int(len(means))
    return FieldCalibrationResult(cal, acc, gyro, means, stats)


def fit_static_gyro_g_sensitivity(G: np.ndarray, f: np.ndarray, intervals) -> tuple[np.ndarray, np.ndarray]:
    """Raw gyro bias ``b`` and g-sensitivity ``S`` (raw gyro per g) from static poses:
    per-pose means ``G_k = b + S f_k`` by least squares (lstsq), ``f`` the calibrated specific
    force in g. Needs at least 5 poses whose gravity directions span 3-D."""
    Gm = np.array([np.asarray(G)[a:b].mean(axis=0) for a, b in intervals])
    fm = np.array([np.asarray(f)[a:b].mean(axis=0) for a, b in intervals])
    X = np.column_stack([np.ones(len(fm)), fm])
    if len(fm) < 5 or np.linalg.matrix_rank(X, tol=1e-3 * np.sqrt(len(fm))) < 4:
        raise DesignError(
            "E_FIELD_G_SENSITIVITY",
            f"{len(fm)} static poses do not determine a "
            "gyro g-sensitivity (need >= 5 with gravity directions spanning 3-D)",
            undetermined=("gyro_g_sensitivity",),
        )
    coef, *_ = np.linalg.lstsq(X, Gm, rcond=None)
    return coef[0], coef[1:].T
