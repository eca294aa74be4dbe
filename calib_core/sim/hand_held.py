"""Simulated hand-held calibration sessions with known truth (for the field estimator's tests
and Monte Carlo), written independently of the fit code in :mod:`calib_core.models.field.joint`.

The unit rests, then is turned by hand through ``n_poses`` rotations about random body axes
(raised-cosine angle profile) and held still after each. A hand does not hold perfectly
still: ``hold_rate_dps`` adds a wobble during the holds (a rotation rate oscillating at
0.5-1.5 Hz about a random axis, that RMS), which the gyro sees and the accelerometer barely
does, as in real recordings. Sample times carry a jitter, so an
estimator that assumes a nominal rate is visibly wrong.

Sensor model (IMU-TK's ``x' = T K (x - b)`` inverted to produce raw outputs):

* accel: ``A = (T_a K_a)^-1 f + b_a + noise`` with ``f`` in m/s^2, ``T_a`` triangular;
* gyro: ``G = (T_g K_g)^-1 w + b_g(t) + noise`` with ``w`` in rad/s, full ``T_g`` (gyro axes
  relative to the accelerometer frame), ``b_g(t) = b_g0 + b_g1 t`` (bias drift).

Orientation is propagated on a fine time grid (``oversample`` sub-steps per sample, exact
exponential of the piecewise constant rate), so the truth does not share the estimator's
per-sample integration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


def imutk_misalignment(yz=0.0, zy=0.0, zx=0.0, xz=0.0, xy=0.0, yx=0.0) -> np.ndarray:
    """IMU-TK's misalignment matrix (written out here, not imported from the fit code)."""
    return np.array([[1.0, -yz, zy], [xz, 1.0, -zx], [-xy, yx, 1.0]])


@dataclass(frozen=True)
class HandHeldTruth:
    acc_mis: np.ndarray  # a_yz, a_zy, a_zx (rad)
    acc_scale: np.ndarray  # m/s^2 per count
    acc_bias: np.ndarray  # counts
    gyro_mis: np.ndarray  # g_yz, g_zy, g_zx, g_xz, g_xy, g_yx (rad)
    gyro_scale: np.ndarray  # rad/s per count
    gyro_bias: np.ndarray  # counts at t = 0
    gyro_drift: np.ndarray  # counts per s
    g_local: float = 9.80665

    @property
    def accel_matrix(self) -> np.ndarray:
        return imutk_misalignment(*self.acc_mis) @ np.diag(self.acc_scale)

    @property
    def gyro_matrix(self) -> np.ndarray:
        return imutk_misalignment(*self.gyro_mis) @ np.diag(self.gyro_scale)


def mpu6050_like_truth(rng: np.random.Generator, drift: bool = False) -> HandHeldTruth:
    """A truth like an MPU-6050 at +/-2 g, +/-250 deg/s (16384 counts/g, 131 counts per deg/s)
    with percent-level scale errors, 1e-2 rad misalignments and the offsets such parts show."""
    return HandHeldTruth(
        acc_mis=rng.normal(0, 0.01, 3),
        acc_scale=(9.80665 / 16384) * (1 + rng.normal(0, 0.02, 3)),
        acc_bias=rng.normal(0, 800, 3),
        gyro_mis=rng.normal(0, 0.01, 6),
        gyro_scale=np.radians(1 / 131.072) * (1 + rng.normal(0, 0.02, 3)),
        gyro_bias=rng.normal(0, 300, 3),
        gyro_drift=rng.normal(0, 0.05, 3) if drift else np.zeros(3),
    )


@dataclass(frozen=True)
class HandHeldSession:
    t: np.ndarray  # s, jittered
    gyro: np.ndarray  # counts
    accel: np.ndarray  # counts
    rest: np.ndarray  # bool: the accelerometer is at rest (hold or initial rest)
    truth: HandHeldTruth


def simulate_hand_held(
    truth: HandHeldTruth,
    rng: np.random.Generator,
    n_poses: int = 20,
    rate_hz: float = 100.0,
    init_s: float = 10.0,
    hold_s: float = 3.0,
    move_s: float = 1.5,
    hold_rate_dps: float = 0.0,
    acc_noise: float = 60.0,
    gyro_noise: float = 12.0,
    jitter: float = 0.05,
    oversample: int = 4,
) -> HandHeldSession:
    """A hand-held session of ``truth``. Noise in counts (white), ``jitter`` the relative
    spread of the sample intervals (uniform), ``hold_rate_dps`` the RMS rate of the hand's
    wobble during the holds (not during the initial rest)."""
    dt_nom = 1.0 / rate_hz
    segments = []  # (n samples, rate function of local time, rest?)
    segments.append((int(init_s * rate_hz), None, True))
    for _ in range(n_poses):
        axis = rng.normal(0, 1, 3)
        axis /= np.linalg.norm(axis)
        total = np.radians(rng.uniform(60, 150)) * rng.choice([-1, 1])
        segments.append((int(move_s * rate_hz), (axis, total), False))
        wobble_axis = rng.normal(0, 1, 3)
        wobble_axis *= np.radians(hold_rate_dps) * np.sqrt(2) / np.linalg.norm(wobble_axis)
        segments.append(
            (
                int(hold_s * rate_hz),
                ("hold", wobble_axis, rng.uniform(0.5, 1.5), rng.uniform(0, 2 * np.pi)),
                True,
            )
        )
    n = sum(s[0] for s in segments)
    dt = dt_nom * (1 + rng.uniform(-jitter, jitter, n))
    t = np.concatenate([[0.0], np.cumsum(dt)[:-1]])
    # true rate at fine sub-steps; sample k holds the rate over [t_k, t_k+1)
    w = np.zeros((n, oversample, 3))
    rest = np.zeros(n, bool)
    k = 0
    for count, spec, is_rest in segments:
        sl = slice(k, k + count)
        rest[sl] = is_rest
        if spec is not None and spec[0] is not None and not isinstance(spec[0], str):
            axis, total = spec
            tau0 = t[sl] - t[k]
            T = t[k + count] - t[k] if k + count < n else tau0[-1] + dt[-1]
            for j in range(oversample):
                tau = tau0 + (j + 0.5) / oversample * dt[sl]
                w[sl, j] = (total * np.pi / (2 * T) * np.sin(np.pi * np.clip(tau / T, 0, 1)))[:, None] * axis
        elif spec is not None:
            _, axis, freq, phase = spec
            tau0 = t[sl] - t[k]
            for j in range(oversample):
                tau = tau0 + (j + 0.5) / oversample * dt[sl]
                w[sl, j] = np.sin(2 * np.pi * freq * tau + phase)[:, None] * axis
        k += count
    # orientation body->world at each sample time; specific force f = R^T [0, 0, g]
    # R_i = R_0 exp(w_00 dt_0/m) ... exp(w_(i-1)(m-1) dt_(i-1)/m): the running products of the
    # sub-step rotations by a Hillis-Steele scan (log2 passes, order kept: the product is
    # associative, not commutative)
    R0 = Rotation.from_rotvec(rng.normal(0, 1, 3))
    P = Rotation.from_rotvec((w * (dt / oversample)[:, None, None]).reshape(-1, 3))
    d = 1
    while d < len(P):
        P = Rotation.concatenate([P[:d], P[:-d] * P[d:]])
        d *= 2
    R = Rotation.concatenate([R0, R0 * P[oversample * np.arange(1, n) - 1]])
    f = R.inv().apply([0.0, 0.0, truth.g_local])
    w_sample = w.mean(axis=1)  # what a rate gyro averages over its sample interval
    A = np.linalg.solve(truth.accel_matrix, f.T).T + truth.acc_bias + rng.normal(0, acc_noise, f.shape)
    b_g = truth.gyro_bias + truth.gyro_drift * t[:, None]
    G = np.linalg.solve(truth.gyro_matrix, w_sample.T).T + b_g + rng.normal(0, gyro_noise, w_sample.shape)
    return HandHeldSession(t, G, A, rest, truth)
