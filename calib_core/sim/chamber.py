"""Chamber runs of the physics simulator: units with known thermal coefficients, the setpoint
schedule of a heating and a cooling sweep, and the truth of the calibration form at any
temperature, written from the sensor settings (not from the estimator's code).

A unit's bias and scale factor follow polynomials in its sensor temperature
(:class:`calib_core.sim.physics._Sensor`: ``bias_tc..bias_tc3``, ``scale_tc_ppm..
scale_tc3_ppm``, ``bias_hyst``); a *linear* unit has the first-order terms only, a *cubic*
one second- and third-order terms of the same size at the ends of the range as well.

The schedule: ``reps`` sweeps over the setpoints, heating (-40 -> 85) and cooling
(85 -> -40) alternately; each sweep starts 10 degC beyond its first setpoint (the chamber
pre-conditions the unit), so every session of a heating sweep is reached by heating.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from calib_core.sim import protocols
from calib_core.sim.physics import REF_TEMP_C, ChamberSoak, PhysicsUnit, typical_physics_unit

SETPOINTS_C = (-40.0, -20.0, 0.0, 20.0, 45.0, 65.0, 85.0)
SPAN_C = 60.0  # the size of each term is given by its contribution at 60 degC from 25 degC


def chamber_steps(duration_s: float = 3.0, settle_s: float = 0.5) -> pd.DataFrame:
    """The protocol run at each setpoint: xu2016 multirate + multiposition (74 steps)."""
    return protocols.to_frame(
        protocols.xu2016_multirate(duration_s, settle_s)
        + protocols.xu2016_multiposition(duration_s, settle_s)
    )


def _signed(rng: np.random.Generator, lo: float, hi: float, n: int = 3) -> np.ndarray:
    return rng.uniform(lo, hi, n) * rng.choice((-1.0, 1.0), n)


def thermal_physics_unit(
    rng: np.random.Generator,
    cubic: bool = False,
    hysteresis: bool = False,
    gyro_bias_tc: tuple[float, float] = (0.002, 0.008),
) -> PhysicsUnit:
    """A typical physics unit with thermal coefficients (sizes as contributions at 60 degC):

    - gyro bias: linear 0.002-0.008 deg/s/degC; cubic units add 0.15-0.4 deg/s of each of
      the second and third orders; hysteresis 0.15-0.3 deg/s;
    - accelerometer bias: linear 0.05-0.2 mg/degC; cubic: 3-8 mg each; hysteresis 3-6 mg;
    - scale factors (both): linear 20-60 ppm/degC; cubic: 300-900 ppm each.
    """
    unit = typical_physics_unit(rng, temperature=ChamberSoak())
    s = SPAN_C
    for kind, n in (("gyro", 0), ("accel", 1)):
        if kind == "gyro":
            b1 = _signed(rng, *gyro_bias_tc)
            b23, hy = (0.15, 0.4), (0.15, 0.3)
        else:
            b1 = _signed(rng, 5e-5, 2e-4)
            b23, hy = (3e-3, 8e-3), (3e-3, 6e-3)
        s1 = _signed(rng, 20.0, 60.0)
        b2 = _signed(rng, *b23) / s**2 if cubic else np.zeros(3)
        b3 = _signed(rng, *b23) / s**3 if cubic else np.zeros(3)
        s2 = _signed(rng, 300.0, 900.0) / s**2 if cubic else np.zeros(3)
        s3 = _signed(rng, 300.0, 900.0) / s**3 if cubic else np.zeros(3)
        h = _signed(rng, *hy) if hysteresis else np.zeros(3)
        for i in range(3):
            change = dict(
                bias_tc=b1[i],
                bias_tc2=b2[i],
                bias_tc3=b3[i],
                scale_tc_ppm=s1[i],
                scale_tc2_ppm=s2[i],
                scale_tc3_ppm=s3[i],
                bias_hyst=h[i],
            )
            unit = unit.replace_gyro(i, **change) if n == 0 else unit.replace_accel(i, **change)
    return unit


@dataclass(frozen=True)
class ChamberSession:
    """One session of a chamber run: its repetition, setpoint, sweep and temperature profile."""

    rep: int
    setpoint_c: float
    sweep: str  # heating | cooling
    soak: ChamberSoak
    order: int  # acquisition order


def chamber_schedule(
    setpoints=SETPOINTS_C,
    reps: int = 2,
    soak_s: float = 3600.0,
    tau_s: float = 300.0,
    self_heating_c: float = 3.0,
    unsoaked: tuple[int, ...] = (),
) -> list[ChamberSession]:
    """The sessions of ``reps`` alternating sweeps (heating first). ``unsoaked``: acquisition
    indices of sessions started two time constants after the setpoint was reached (the
    sensor is still on its way from the previous setpoint: a few degC during the session)."""
    out = []
    k = 0
    for r in range(reps):
        heating = r % 2 == 0
        seq = sorted(setpoints) if heating else sorted(setpoints, reverse=True)
        prev = seq[0] - 10.0 if heating else seq[0] + 10.0
        for sp in seq:
            soak = ChamberSoak(
                setpoint_c=float(sp),
                from_c=float(prev),
                soak_s=2.0 * tau_s if k in unsoaked else soak_s,
                tau_s=tau_s,
                self_heating_c=self_heating_c,
            )
            out.append(ChamberSession(r + 1, float(sp), "heating" if heating else "cooling", soak, k))
            prev = sp
            k += 1
    return out


def _affine_truth(sensors, temp_c: float, approach: float, physical_unit_per_raw: bool = True):
    """K (3,3) and offset (3,) of the calibration form for three sensors at one temperature.

    Sensor i outputs raw_i = c_i [ (1 + s_i(T)) a_i . q + b_i(T) + approach h_i / 2 ];
    so q = M^-1 diag(1 / (c_i (1 + s_i))) raw - M^-1 diag(1 / (1 + s_i)) (b_i + ...)."""
    dt = temp_c - REF_TEMP_C
    M = np.array([s.axis for s in sensors], float)
    scale = np.array(
        [
            1.0 + 1e-6 * (s.scale_tc_ppm * dt + s.scale_tc2_ppm * dt**2 + s.scale_tc3_ppm * dt**3)
            for s in sensors
        ]
    )
    bias = np.array(
        [
            s.bias + s.bias_tc * dt + s.bias_tc2 * dt**2 + s.bias_tc3 * dt**3 + 0.5 * approach * s.bias_hyst
            for s in sensors
        ]
    )
    c = np.array([s.scale for s in sensors], float)
    Minv = np.linalg.inv(M)
    K = Minv @ np.diag(1.0 / (c * scale))
    off = -Minv @ (bias / scale)
    return K, off


def true_parameters(unit: PhysicsUnit, temp_c: float, approach: float = 0.0) -> dict[str, float]:
    """The calibration form's K_g, w0, K_a, f0 (by their parameter names) the unit has at a
    sensor temperature, reached by heating (+1), cooling (-1) or the mid-line (0)."""
    K_g, w0 = _affine_truth(unit.gyros, temp_c, approach)
    K_a, f0 = _affine_truth(unit.accels, temp_c, approach)
    out = {}
    for i in range(3):
        for j in range(3):
            out[f"k_g{i + 1}{j + 1}"] = float(K_g[i, j])
            out[f"k_a{i + 1}{j + 1}"] = float(K_a[i, j])
    for i, a in enumerate("xyz"):
        out[f"w0_{a}"] = float(w0[i])
        out[f"f0_{a}"] = float(f0[i])
    return out


def with_soak(unit: PhysicsUnit, soak: ChamberSoak) -> PhysicsUnit:
    return replace(unit, temperature=soak)
