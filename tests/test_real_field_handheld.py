"""Hand-held field calibration (calib_core.models.field.joint): known truth and standard errors on
simulated sessions (Monte Carlo), pose detection, and the comparison with the published
references on the real recordings, with figures of merit computed here, independently of
the code under test (own pose means, own per-sample rotation products with scipy, own
application of each calibration's formula)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calib_core.models.field.joint import Priors, fit_field, group_redundancies, tangent_bases
from calib_core.models.field.static_detection import detect_poses
from calib_core.sim.hand_held import mpu6050_like_truth, simulate_hand_held
from schemas.importers import read_imutk_pair, read_table_recording

REAL = Path(__file__).parents[2] / "shared" / "data" / "real"
MPU_DIR = REAL / "mpu6050_tedaldi"
MPU = MPU_DIR / "example_data_calibration.csv"
XSENS_ACC, XSENS_GYRO = REAL / "imu_tk" / "xsens_acc.txt", REAL / "imu_tk" / "xsens_gyro.txt"
G0 = 9.80665
MPU_ACC_SCALE, MPU_GYRO_SCALE = 2 * G0 / 32768, np.radians(250 / 32768)


# --- independent reference code ---------------------------------------------------------------
def tri(yz, zy, zx):
    return np.array([[1, -yz, zy], [0, 1, -zx], [0, 0, 1.0]])


def full_mis(yz, zy, zx, xz, xy, yx):
    return np.array([[1, -yz, zy], [xz, 1, -zx], [-xy, yx, 1.0]])


def ours_as_functions(fit, t, A):
    """Our fit's parameters applied with the model's formula written out here:
    f = T_a K_a (A - b_a) [m/s^2], w = T_g K_g (G - b - d t - S f/g) [rad/s]."""
    p = fit.params()
    Ma = tri(p["a_yz"], p["a_zy"], p["a_zx"]) @ np.diag([p["s_ax"], p["s_ay"], p["s_az"]])
    ba = np.array([p["b_ax"], p["b_ay"], p["b_az"]])
    Mg = full_mis(*(p[k] for k in ("g_yz", "g_zy", "g_zx", "g_xz", "g_xy", "g_yx"))) @ np.diag(
        [p["s_gx"], p["s_gy"], p["s_gz"]]
    )
    bg = np.array([p["b_gx"], p["b_gy"], p["b_gz"]])
    d = np.array([p.get(f"d_g{c}", 0.0) for c in "xyz"])
    S = np.array([[p.get(f"S_{r}{c}", 0.0) for c in "xyz"] for r in "xyz"])

    def accel(X):
        return (np.atleast_2d(X) - ba) @ Ma.T

    def gyro(G, idx):
        f_g = accel(A[idx]) / fit.calibration.g_local
        return (G[idx] - bg - t[idx, None] * d - f_g @ S.T) @ Mg.T

    return accel, gyro


def pose_norm_err_mg(accel, A, intervals, g):
    return np.array([1e3 * (np.linalg.norm(accel(A[a:b].mean(axis=0))[0]) / g - 1) for a, b in intervals])


def move_angles_deg(gyro, accel, t, G, A, intervals, moves):
    """Angle between the gravity direction at pose j+1 and the one at pose j carried by the
    gyro (product of exp(w_k dt_k) from the middle of pose j to the middle of pose j+1)."""
    u = np.array([accel(A[a:b].mean(axis=0))[0] for a, b in intervals])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    mids = [(a + b) // 2 for a, b in intervals]
    out = []
    for j in moves:
        idx = np.arange(mids[j], mids[j + 1])
        w = gyro(G, idx)
        dt = t[idx + 1] - t[idx]
        R = Rotation.identity()
        for r in Rotation.from_rotvec(w * dt[:, None]):
            R = R * r
        pred = R.inv().apply(u[j])
        out.append(np.degrees(np.arccos(np.clip(pred @ u[j + 1], -1, 1))))
    return np.array(out)


def quat_exp(rv):
    """Hamilton (w, x, y, z) quaternion of rotation vectors (..., 3)."""
    ang = np.linalg.norm(rv, axis=-1)
    k = np.where(ang > 0, np.sin(ang / 2) / np.where(ang > 0, ang, 1), 0.5)
    return np.concatenate([np.cos(ang / 2)[..., None], rv * k[..., None]], axis=-1)


def quat_mul(a, b):
    """Hamilton product a b of quaternions (..., 4)."""
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def ordered_product(q):
    """q[:, 0] q[:, 1] ... q[:, L-1] per row of quaternions (n, L, 4): neighbours multiplied
    pairwise, order kept (the product is associative), identity appended to odd lengths."""
    while q.shape[1] > 1:
        if q.shape[1] % 2:
            q = np.concatenate([q, np.broadcast_to([1.0, 0, 0, 0], (len(q), 1, 4))], axis=1)
        q = quat_mul(q[:, 0::2], q[:, 1::2])
    return q[:, 0]


def rotate_by_conjugate(q, v):
    """R(q)^T v: scipy's rotation of v by the inverse (scalar-last order for scipy)."""
    return Rotation.from_quat(np.column_stack([q[:, 1:], q[:, 0]])).inv().apply(v)


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


# --- simulated sessions ------------------------------------------------------------------------
def _truth_vector(tr):
    return np.r_[
        tr.acc_mis, tr.acc_scale, tr.acc_bias, tr.gyro_mis, tr.gyro_scale, tr.gyro_bias, tr.gyro_drift
    ]


def test_move_residual_basis_and_variance_component_redundancies():
    """The two pieces the gyro's standard errors rest on, against what they must be by
    construction: each move's residual is taken in two unit directions perpendicular to the
    measured gravity direction; a group's redundancy is its rows minus the parameters it
    determines (all of them summing to rows - parameters, a group with no information on the
    parameters keeping all its rows), and the variance component it gives is unbiased."""
    rng = np.random.default_rng(3)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    B = tangent_bases(u)
    assert np.allclose(np.einsum("kij,ki->kj", B, u), 0, atol=1e-12)
    assert np.allclose(np.einsum("kij,kil->kjl", B, B), np.eye(2), atol=1e-12)
    J = np.vstack(
        [rng.normal(size=(20, 4)), np.c_[rng.normal(size=(30, 2)), np.zeros((30, 2))], np.zeros((7, 4))]
    )
    red = group_redundancies(J, (20, 30, 7))
    assert sum(red) == pytest.approx(57 - 4)
    assert red[2] == pytest.approx(7)
    # group 0 alone determines the last two parameters: its redundancy is below 20 - 2
    assert red[0] < 18
    # unbiased variance components: noise 1 in group 0, 3 in group 1, sum of squared least
    # squares residuals over the redundancy, averaged over 400 draws
    s2 = []
    for _ in range(400):
        y = np.r_[rng.normal(0, 1, 20), rng.normal(0, 3, 30)]
        Jw = np.vstack([J[:20], J[20:50] / 3])
        yw = np.r_[y[:20], y[20:] / 3]
        r = yw - Jw @ np.linalg.lstsq(Jw, yw, rcond=None)[0]
        red = group_redundancies(Jw, (20, 30))
        s2.append([np.sum(r[:20] ** 2) / red[0], 9 * np.sum(r[20:] ** 2) / red[1]])
    assert np.allclose(np.mean(s2, axis=0), [1, 9], rtol=0.06)


@pytest.fixture(scope="module")
def monte_carlo_fits():
    """24 seeded sessions of 14 poses of one MPU-6050-like truth with a gyro bias drift (new
    motion and noise each time), each fitted with a drift and no prior: (errors = estimate -
    truth, stated standard errors), one row per session. Fitted once for both tests below."""
    truth = mpu6050_like_truth(np.random.default_rng(7), drift=True)
    errs, ses = [], []
    for seed in range(24):
        s = simulate_hand_held(truth, np.random.default_rng(1000 + seed), n_poses=14)
        det = detect_poses(s.t, s.gyro, s.accel, init_s=10)
        fit = fit_field(
            s.t,
            s.gyro,
            s.accel,
            det.poses,
            G0,
            accel_scale=MPU_ACC_SCALE,
            gyro_scale=MPU_GYRO_SCALE,
            drift=True,
            g_sensitivity=False,
            priors=Priors(None),
        )
        assert list(fit.params())[-3:] == ["d_gx", "d_gy", "d_gz"]
        errs.append(np.array(list(fit.params().values())) - _truth_vector(truth))
        ses.append(np.array(list(fit.stderrs().values())))
    return np.array(errs), np.array(ses), _truth_vector(truth)


@pytest.mark.slow
def test_standard_errors_match_monte_carlo_spread(monte_carlo_fits):
    """The first 8 sessions, every parameter. Measured on these seeds: MC RMS error / mean
    stated stderr 0.64-1.82 per parameter, median 1.23, the gyro's 1.11 (the mean stated
    error varies between sessions with the pose geometry; docs/real-data.md: the
    accelerometer's z = error / stated error is Student-t with 5 dof, RMS sqrt(5/3); the
    gyro's z is checked on all 24 sessions below); |mean error| / RMS error <= 0.56 (no
    estimator bias beyond the noise of 8 draws); errors below 3e-3 relative on scale factors
    and 2e-3 rad on misalignments."""
    errs, ses, truth = monte_carlo_fits[0][:8], monte_carlo_fits[1][:8], monte_carlo_fits[2]
    ratio = np.sqrt(np.mean(errs**2, axis=0)) / ses.mean(axis=0)
    assert np.all((ratio > 0.5) & (ratio < 2.5)), ratio
    assert 0.9 < np.median(ratio) < 1.8, ratio
    # no estimator bias: a mean error of 3 standard errors of the mean (RMS / sqrt(8)) or more
    # would show one
    assert np.all(np.abs(errs.mean(axis=0)) < 3 / np.sqrt(8) * np.sqrt(np.mean(errs**2, axis=0)))
    scale_idx = [3, 4, 5, 15, 16, 17]
    assert np.all(np.abs(errs[:, scale_idx] / truth[scale_idx]) < 3e-3)
    assert np.all(np.abs(errs[:, [0, 1, 2, 9, 10, 11, 12, 13, 14]]) < 2e-3)


@pytest.mark.slow
def test_gyro_standard_errors_match_monte_carlo_spread(monte_carlo_fits):
    """The gyro's stated standard errors against the Monte Carlo spread: all 24 sessions,
    z = (estimate - truth) / stated error for the 15 gyro parameters (scale, misalignment,
    bias, drift). With right errors the RMS of z is the t expectation ~1.05 (16-39 residual
    degrees of freedom per group); its sampling band over 24 sessions is about +/-0.07 (the
    spread of 16-session subsets). Measured: 1.05 over these 24 sessions (1.00 over 48); 1.22
    before the moves' residuals were counted with their 2 degrees of freedom and the variance
    components with their redundancy (docs/real-data.md)."""
    errs, ses, _ = monte_carlo_fits
    z = errs[:, 9:] / ses[:, 9:]
    rms_z = float(np.sqrt(np.mean(z**2)))
    assert 0.88 < rms_z < 1.12, rms_z
    # each block on its own (scale and misalignment from the moves, bias and drift mostly
    # from the quiet poses): within 25 % of 1
    for block in (slice(0, 9), slice(9, 12), slice(12, 15)):
        assert 0.75 < np.sqrt(np.mean(z[:, block] ** 2)) < 1.25, (block, np.sqrt(np.mean(z[:, block] ** 2)))


@pytest.mark.slow
def test_detector_on_a_wobbly_hand_session_and_rate_adaptation():
    truth = mpu6050_like_truth(np.random.default_rng(3))
    s = simulate_hand_held(truth, np.random.default_rng(4), n_poses=10, hold_rate_dps=0.5)
    det = detect_poses(s.t, s.gyro, s.accel, init_s=10)
    assert len(det.poses) == 11 and not det.rejected
    in_rest = sum(s.rest[p.start : p.end].sum() for p in det.poses)
    assert in_rest / sum(len(p) for p in det.poses) > 0.99
    # the initial rest is a bias observation; holds wobbling at 0.5 deg/s RMS are not, but for
    # a slow (0.5 Hz) wobble that the 0.25 s window hardly sees (measured: 1 of 10 passes)
    assert det.poses[0].gyro_quiet and sum(p.gyro_quiet for p in det.poses[1:]) <= 1
    # the same session at twice the rate: window and shortest pose scale with it (the same
    # seconds, to the odd sample count nearest)
    s2 = simulate_hand_held(truth, np.random.default_rng(4), n_poses=10, hold_rate_dps=0.5, rate_hz=200.0)
    det2 = detect_poses(s2.t, s2.gyro, s2.accel, init_s=10)
    assert abs(det2.window - 2 * det.window) <= 3 and abs(det2.min_samples - 2 * det.min_samples) <= 2
    assert det.window / det.rate_hz == pytest.approx(0.25, abs=1.01 / det.rate_hz)
    assert len(det2.poses) == 11
    # a hold shorter than the shortest pose is rejected and listed with its reason
    det3 = detect_poses(s.t, s.gyro, s.accel, init_s=10, min_pose_s=3.5)
    assert len(det3.poses) == 1 and len(det3.rejected) == 10
    assert all("too short" in r.reason for r in det3.rejected)


# --- the MPU-6050 session vs the authors' published calibration -----------------------------
need_mpu = pytest.mark.skipif(not MPU.exists(), reason=f"real recordings absent under {REAL}")


def _published_mpu():
    pa = np.loadtxt(MPU_DIR / "published_params_acc.csv")
    pg = np.loadtxt(MPU_DIR / "published_params_gyro.csv")
    Ma = tri(pa[0], pa[1], pa[2]) @ np.diag(pa[3:6])
    m = pg[:6]
    Mg = np.array([[1, -m[0], m[1]], [m[2], 1, -m[3]], [-m[4], m[5], 1]]) @ np.diag(pg[6:9])

    def accel(X):  # calibrated accel = T K (raw + b)  (README of the recording)
        return (np.atleast_2d(X) + pa[6:9]) @ Ma.T

    def gyro(G, idx):  # calibrated rate = T K (raw - b)
        return (G[idx] - pg[9:12]) @ Mg.T

    return accel, gyro


@need_mpu
@pytest.mark.slow
def test_mpu6050_held_out_at_least_as_good_as_the_published_calibration():
    rec = read_table_recording(MPU, None, "LSB", "LSB")
    t, G, A = rec.t, rec.gyro, rec.accel
    det = detect_poses(t, G, A, init_s=36.5)  # the preamble's "Initialization time"
    iv = [(p.start, p.end) for p in det.poses]
    # every static interval the authors kept of >= 0.5 s lies in one of our poses
    pub_iv = np.loadtxt(MPU_DIR / "published_static_intervals.csv", delimiter=",").astype(int)
    for a, b in pub_iv.T:
        if b - a >= 50:
            assert any(s <= (a + b) // 2 < e for s, e in iv), (a, b)
    # moves with a saturated int16 gyro sample cannot be integrated: left out for both
    mids = [(a + b) // 2 for a, b in iv]
    ok = np.array([not (np.abs(G[mids[j] : mids[j + 1]]) >= 32767).any() for j in range(len(iv) - 1)])
    assert 5 <= ok.sum() < len(ok)
    kw = {"accel_scale": MPU_ACC_SCALE, "gyro_scale": MPU_GYRO_SCALE}
    full = fit_field(t, G, A, det.poses, G0, move_use=ok, **kw)
    kw.update(drift=full.gyro.drift, g_sensitivity=full.gyro.g_sensitivity)
    # held out: leave one pose out of the accel fit / one move out of the gyro fit
    norm_ho = []
    for k in range(len(iv)):
        use = np.ones(len(iv), bool)
        use[k] = False
        fit = fit_field(t, G, A, det.poses, G0, pose_use=use, move_use=ok, **kw)
        accel, _ = ours_as_functions(fit, t, A)
        norm_ho.append(pose_norm_err_mg(accel, A, [iv[k]], G0)[0])
    angle_ho = []
    for j in np.flatnonzero(ok):
        use = ok.copy()
        use[j] = False
        fit = fit_field(t, G, A, det.poses, G0, move_use=use, **kw)
        accel, gyro = ours_as_functions(fit, t, A)
        angle_ho.append(move_angles_deg(gyro, accel, t, G, A, iv, [j])[0])
    p_accel, p_gyro = _published_mpu()
    norm_pub = pose_norm_err_mg(p_accel, A, iv, G0)
    angle_pub = move_angles_deg(p_gyro, p_accel, t, G, A, iv, np.flatnonzero(ok))
    # the published figures are in-sample for the authors (fitted on all poses and moves)
    assert rms(norm_ho) <= rms(norm_pub), (rms(norm_ho), rms(norm_pub))
    assert rms(angle_ho) <= rms(angle_pub), (rms(angle_ho), rms(angle_pub))

    # and the calibration is a large gain over the datasheet scales
    def raw_accel(X):
        return np.atleast_2d(X) * MPU_ACC_SCALE

    assert rms(pose_norm_err_mg(raw_accel, A, iv, G0)) > 20 * rms(norm_ho)


# --- the Xsens session vs IMU-TK with its demo settings ----------------------------------------
need_xsens = pytest.mark.skipif(not XSENS_ACC.exists(), reason=f"real recordings absent under {REAL}")
XSENS_G = 9.81744


def imu_tk_demo(t, G, A, intervals, pose_use, move_use):
    """IMU-TK's procedure with its demo settings, written here: accel bias start 32768, fit
    on the 100 central samples of each pose; gyro bias = mean of the first 50 s, scale start
    1/6258 rad/s per count, misalignment and scale fitted on the moves from the end of one
    pose's central samples to the start of the next, with a fixed dt = 0.01 s."""
    central = [((a + b) // 2 - 50, (a + b) // 2 + 50) for a, b in intervals]
    X = np.vstack([A[a:b] for (a, b), u in zip(central, pose_use) if u])

    def r_acc(p):
        return XSENS_G - np.linalg.norm((X - p[6:9]) @ (tri(*p[:3]) @ np.diag(p[3:6])).T, axis=1)

    means = np.array([A[a:b].mean(axis=0) for a, b in central])
    s0 = XSENS_G / np.median(np.linalg.norm(means - 32768, axis=1))
    pa = least_squares(r_acc, np.r_[0, 0, 0, s0, s0, s0, 32768, 32768, 32768], method="lm").x
    Ma = tri(*pa[:3]) @ np.diag(pa[3:6])
    u = np.array([(A[a:b].mean(axis=0) - pa[6:9]) @ Ma.T for a, b in central])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    bg = G[t < t[0] + 50].mean(axis=0)
    moves = [j for j in range(len(central) - 1) if move_use[j]]
    segs = [(central[j][1], central[j + 1][0]) for j in moves]

    # per move, its samples in order (padded with zero rotations): q = prod_k exp(w_k dt)
    k = np.arange(max(b - a for a, b in segs))
    idx = np.array([np.minimum(a + k, b - 1) for a, b in segs])
    live = np.array([a + k < b for a, b in segs])

    def r_gyro(p):
        Mg = full_mis(*p[:6]) @ np.diag(p[6:9])
        rv = ((G[idx] - bg) @ Mg.T * 0.01) * live[..., None]
        q = ordered_product(quat_exp(rv))  # per move, Hamilton (w, x, y, z)
        pred = rotate_by_conjugate(q, u[moves])
        return (pred - u[np.array(moves) + 1]).ravel()

    pg = least_squares(r_gyro, np.r_[np.zeros(6), np.full(3, 1 / 6258)], method="lm").x
    Mg = full_mis(*pg[:6]) @ np.diag(pg[6:9])

    def accel(Y):
        return (np.atleast_2d(Y) - pa[6:9]) @ Ma.T

    def gyro(GG, idx):
        return (GG[idx] - bg) @ Mg.T

    return accel, gyro


@need_xsens
@pytest.mark.slow
def test_xsens_held_out_at_least_as_good_as_imu_tk_demo():
    """5 folds, each leaving out every fifth pose (from the accel fit) and every fifth move
    (from the gyro fit), poses dealt in turn as in docs/real-data.md's table; each fold refits
    both methods once, and each is scored on what its fit left out (the accel fit does not
    see the moves, so one fit serves both). Measured: gravity direction ~0.24 deg (mimucal,
    with g-sensitivity) vs ~1.4 deg (IMU-TK); static |f| 0.1346 vs 0.1352 mg (IMU-TK fits
    the same 9-parameter model: the two are at parity, and which is ahead depends on the
    split, see docs/real-data.md)."""
    rec = read_imutk_pair(XSENS_ACC, XSENS_GYRO)
    t, G, A = rec.t, rec.gyro, rec.accel
    det = detect_poses(t, G, A, init_s=50)
    iv = [(p.start, p.end) for p in det.poses]
    assert len(iv) >= 35 and all(b - a >= 100 for a, b in iv)
    n_m = len(iv) - 1
    kw = {"gyro_scale": 1 / 6258, "accel_bias": 32768, "drift": False, "g_sensitivity": True}
    ours_n, ours_a, ref_n, ref_a = [], [], [], []
    for k in range(5):
        out_p = np.arange(len(iv)) % 5 == k
        out_m = np.arange(n_m) % 5 == k
        held_p = [v for v, o in zip(iv, out_p) if o]
        fit = fit_field(t, G, A, det.poses, XSENS_G, pose_use=~out_p, move_use=~out_m, **kw)
        accel, gyro = ours_as_functions(fit, t, A)
        ours_n += list(pose_norm_err_mg(accel, A, held_p, XSENS_G))
        ours_a += list(move_angles_deg(gyro, accel, t, G, A, iv, np.flatnonzero(out_m)))
        r_accel, r_gyro = imu_tk_demo(t, G, A, iv, ~out_p, ~out_m)
        ref_n += list(pose_norm_err_mg(r_accel, A, held_p, XSENS_G))
        ref_a += list(move_angles_deg(r_gyro, r_accel, t, G, A, iv, np.flatnonzero(out_m)))
    assert rms(ours_a) <= 0.5 * rms(ref_a), (rms(ours_a), rms(ref_a))
    assert rms(ours_n) <= rms(ref_n), (rms(ours_n), rms(ref_n))
