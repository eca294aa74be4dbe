"""Strapdown navigation of a turntable trajectory: the navigation impact of zhang2017 (its
section 3.3, Figures 6-10).

The unit sits with its origin on the table axis and turns about it, so its true motion is a
pure rotation: true velocity and position stay zero and whatever the strapdown integration
produces is error. The table axis is vertical in the navigation frame (z up, no Earth rate)
and fixed in the body frame (``axis_body``, e.g. a diagonal so that the unit is tilted on the
table as in the paper's semi-physical test). The accelerometers are simulated with their
lever arms; attitude comes from the gyros (ideal plus white noise), integrated by the
rotation-vector (quaternion) update; velocity and position from the compensated specific
force with gravity removed.

Three accelerometer compensations are compared:
- ``none``: per-axis scale and bias only, f_i = (u_i - u0_i)/k_i (installation angles and lever
  arms ignored; the paper's "before compensation"),
- ``static``: the 15-parameter static model,
- ``static+dynamic``: static model minus the lever-arm term (rate and its derivative from the
  gyros).
Pure numerics: the report helper plots the returned time series.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from calib_core.models.zhang2017 import AccelStaticFit, LeverArmFit, compensate_specific_force
from calib_core.sim.accel_unit import AccelUnitTruth

if TYPE_CHECKING:  # pandas is imported where the store's table is built
    import pandas as pd

CASES = ("none", "static", "static+dynamic")


@dataclass(frozen=True)
class TurntableTrajectory:
    """Rotation about a body-fixed axis held vertical: rate(t) = rate + amp sin(2 pi t / T)."""

    axis_body: tuple[float, float, float] = (1.0, 1.0, 1.0)
    rate_dps: float = 100.0
    rate_amplitude_dps: float = 0.0
    rate_period_s: float = 20.0
    duration_s: float = 100.0
    sample_rate_hz: float = 100.0

    def motion(self) -> dict[str, np.ndarray]:
        """t (s), body rate w (deg/s), dw/dt (deg/s^2), true specific force f (g, body) and
        the true body-to-navigation rotation C_nb, (n,3,3)."""
        n = int(round(self.duration_s * self.sample_rate_hz)) + 1
        t = np.arange(n) / self.sample_rate_hz
        u = np.asarray(self.axis_body, float)
        u = u / np.linalg.norm(u)
        om = 2.0 * np.pi / self.rate_period_s
        rate = self.rate_dps + self.rate_amplitude_dps * np.sin(om * t)
        drate = self.rate_amplitude_dps * om * np.cos(om * t)
        phi = np.radians(self.rate_dps * t + self.rate_amplitude_dps / om * (1 - np.cos(om * t)))
        C0 = _align(u)  # C_nb at t = 0: body axis u -> navigation z
        Rz = np.zeros((n, 3, 3))
        Rz[:, 0, 0] = Rz[:, 1, 1] = np.cos(phi)
        Rz[:, 0, 1] = -np.sin(phi)
        Rz[:, 1, 0] = np.sin(phi)
        Rz[:, 2, 2] = 1.0
        C_nb = Rz @ C0
        f_b = np.einsum("nji,j->ni", C_nb, np.array([0.0, 0.0, 1.0]))  # C_bn (0,0,1 g)
        return {"t": t, "w": rate[:, None] * u, "dwdt": drate[:, None] * u, "f": f_b, "C_nb": C_nb}


def _align(u: np.ndarray) -> np.ndarray:
    """A rotation taking unit vector u (body) onto navigation z (Rodrigues)."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    s, c = np.linalg.norm(v), float(u @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = v / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def _quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (scalar first) along the last axis: (4,) or (n, 4)."""
    a1, b1, c1, d1 = np.moveaxis(p, -1, 0)
    a2, b2, c2, d2 = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            a1 * a2 - b1 * b2 - c1 * c2 - d1 * d2,
            a1 * b2 + b1 * a2 + c1 * d2 - d1 * c2,
            a1 * c2 - b1 * d2 + c1 * a2 + d1 * b2,
            a1 * d2 + b1 * c2 - c1 * b2 + d1 * a2,
        ],
        axis=-1,
    )


def _quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """Direction cosine matrix of unit quaternions: (4,) -> (3, 3), (n, 4) -> (n, 3, 3)."""
    a, b, c, d = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)], axis=-1),
            np.stack([2 * (b * c + a * d), a * a - b * b + c * c - d * d, 2 * (c * d - a * b)], axis=-1),
            np.stack([2 * (b * d - a * c), 2 * (c * d + a * b), a * a - b * b - c * c + d * d], axis=-1),
        ],
        axis=-2,
    )


def _dcm_to_quat(C: np.ndarray) -> np.ndarray:
    w = np.sqrt(max(1.0 + np.trace(C), 1e-12)) / 2.0
    return np.array(
        [w, (C[2, 1] - C[1, 2]) / (4 * w), (C[0, 2] - C[2, 0]) / (4 * w), (C[1, 0] - C[0, 1]) / (4 * w)]
    )


def _prefix_products(dq: np.ndarray) -> np.ndarray:
    """``out[k] = dq[0] dq[1] ... dq[k]`` for unit quaternions (n, 4), by a doubling scan
    (Hillis-Steele): log2(n) vectorised products instead of n sequential ones. The product is
    associative, so this is the sequential product up to rounding; each pass renormalises,
    as the sequential update did after every step."""
    out = dq.copy()
    shift = 1
    while shift < len(out):
        out[shift:] = _quat_mul(out[:-shift], out[shift:])
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        shift *= 2
    return out


def integrate_attitude(C0: np.ndarray, w_dps: np.ndarray, dt: float) -> np.ndarray:
    """C_nb over time from gyro rates: rotation-vector update with the trapezoidal increment
    (exact for a fixed axis and a rate linear within the interval). The per-step rotations
    are composed by a prefix scan (no per-sample loop)."""
    n = len(w_dps)
    out = np.empty((n, 3, 3))
    out[0] = C0
    if n < 2:
        return out
    inc = 0.5 * (w_dps[1:] + w_dps[:-1]) * np.radians(dt)
    ang = np.linalg.norm(inc, axis=1)
    dq = np.concatenate([np.cos(ang / 2)[:, None], np.sinc(ang / (2 * np.pi))[:, None] * inc / 2], axis=1)
    q = _quat_mul(_dcm_to_quat(C0), _prefix_products(dq))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    out[1:] = _quat_to_dcm(q)
    return out


def integrate_navigation(
    C_nb: np.ndarray, f_g: np.ndarray, dt: float, g_local: float
) -> tuple[np.ndarray, np.ndarray]:
    """Velocity (m/s) and position (m) in the navigation frame from zero initial state,
    trapezoidal integration of C_nb f - g."""
    a = np.einsum("nij,nj->ni", C_nb, f_g) * g_local
    a[:, 2] -= g_local
    v = np.zeros_like(a)
    v[1:] = np.cumsum(0.5 * (a[1:] + a[:-1]) * dt, axis=0)
    p = np.zeros_like(a)
    p[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * dt, axis=0)
    return v, p


@dataclass(frozen=True)
class NavigationResult:
    """Velocity and position errors (navigation frame) for each compensation case."""

    t: np.ndarray
    velocity_error: dict[str, np.ndarray]  # case -> (n,3) m/s
    position_error: dict[str, np.ndarray]  # case -> (n,3) m
    trajectory: TurntableTrajectory = field(default_factory=TurntableTrajectory)

    def final(self) -> dict[str, dict[str, float]]:
        """|v| and |p| at the end (the 'after 100 s' values)."""
        return {
            c: {
                "velocity_mps": float(np.linalg.norm(self.velocity_error[c][-1])),
                "position_m": float(np.linalg.norm(self.position_error[c][-1])),
            }
            for c in self.velocity_error
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "duration_s": float(self.t[-1]),
            "final": self.final(),
            "trajectory": {
                k: (list(v) if isinstance(v, tuple) else v) for k, v in self.trajectory.__dict__.items()
            },
        }


def simulate_navigation(
    truth: AccelUnitTruth,
    static: AccelStaticFit,
    lever: LeverArmFit | None,
    trajectory: TurntableTrajectory = TurntableTrajectory(),
    rng: np.random.Generator | None = None,
    accel_noise_g: float = 1e-3,
    gyro_noise_dps: float = 0.0,
) -> NavigationResult:
    """Navigation errors of ``truth`` on ``trajectory`` under the three compensations.

    Accelerometer white noise is in g per sample (raw = k x noise); the gyros are the
    calibrated gyros (true rate plus white noise), and dw/dt for compensation is their
    numerical derivative. All three cases use the same samples and the same attitude."""
    rng = np.random.default_rng(0) if rng is None else rng
    m = trajectory.motion()
    dt = 1.0 / trajectory.sample_rate_hz
    u = truth.raw(m["f"], m["w"], m["dwdt"])
    u = u + rng.normal(0.0, accel_noise_g, u.shape) * truth.scale
    w_gyro = m["w"] + rng.normal(0.0, gyro_noise_dps, m["w"].shape)
    dwdt_gyro = np.gradient(w_gyro, dt, axis=0)
    C_nb = integrate_attitude(m["C_nb"][0], w_gyro, dt)
    fs = {
        "none": static.sensed_along_axes(u),
        "static": compensate_specific_force(static, None, u),
    }
    if lever is not None:
        fs["static+dynamic"] = compensate_specific_force(static, lever, u, w_gyro, dwdt_gyro)
    vel, pos = {}, {}
    for case, f in fs.items():
        vel[case], pos[case] = integrate_navigation(C_nb, f, dt, truth.g_local)
    return NavigationResult(t=m["t"], velocity_error=vel, position_error=pos, trajectory=trajectory)


def navigation_impact(
    static: AccelStaticFit,
    lever: LeverArmFit,
    trajectory: TurntableTrajectory = TurntableTrajectory(),
    rng: np.random.Generator | None = None,
    accel_noise_g: float = 0.0,
) -> NavigationResult:
    """The three curves for a calibrated unit's report: its own fitted model (static
    parameters and lever arms, undetermined components as 0) replayed as the truth on
    ``trajectory``. ``none`` and ``static`` then show the error the unit's size effect and
    misalignment would cause; ``static+dynamic`` is ~0 by construction (noise only)."""
    truth = AccelUnitTruth(
        scale=static.scale,
        bias=static.bias,
        C=static.C,
        lever_arm_mm=lever.r_for_compensation,
        unit=static.unit,
        g_local=static.g_local,
    )
    return simulate_navigation(truth, static, lever, trajectory, rng, accel_noise_g=accel_noise_g)


def navigation_table(
    static: AccelStaticFit, lever: LeverArmFit, sample_rate_hz: float = 10.0
) -> pd.DataFrame:
    """The three drift curves of :func:`navigation_impact` as a tidy table for the results
    store: case, t (s), vel_err (|v|, m/s), pos_err (|p|, m). 10 Hz keeps it to ~0.3 s per
    unit; the attitude integrator is the same for the three cases, so their difference is
    the calibration's."""
    import pandas as pd

    res = navigation_impact(static, lever, TurntableTrajectory(sample_rate_hz=sample_rate_hz))
    frames = [
        pd.DataFrame(
            {
                "case": case,
                "t": res.t,
                "vel_err": np.linalg.norm(res.velocity_error[case], axis=1),
                "pos_err": np.linalg.norm(res.position_error[case], axis=1),
            }
        )
        for case in res.velocity_error
    ]
    return pd.concat(frames, ignore_index=True)


def unit_navigation_table(reps) -> pd.DataFrame | None:
    """:func:`navigation_table` of a unit's first repetition (``RepetitionCalibration``, in
    rep order) with a static fit and a fully determined lever arm; None when none has them."""
    for rep in reps:
        static, lever = rep.fits.get("accel_static"), rep.fits.get("lever_arm")
        if static is not None and lever is not None and not lever.undetermined:
            return navigation_table(static, lever)
    return None
