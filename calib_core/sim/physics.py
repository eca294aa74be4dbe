"""A MIMU on a turntable, written from the sensor physics and nothing else.

Why a second simulator: model discovery must be checked on data it did not shape. The older
:mod:`calib_core.sim.simulator` adds each effect with the very term functions the estimator fits,
so it can only show that the code agrees with itself. This module is a forward model in the
*sensor* frame, written from first principles, and it imports nothing from the effect
catalogue, the estimators or the calibration forms.

The unit is six sensors, each with

- its own sensing direction ``axis`` (a unit vector in the body frame, misaligned from the
  nominal body axis by a fraction of a degree) and scale factor (raw units per deg/s or g);
- a polynomial in *its own* input ``u = axis . q`` (q the rate, or the specific force at the
  sensor's position): ``u + k2 u^2 + k3 u^3 + asym/2 |u|`` (asymmetry = scale(+) - scale(-));
- a scale factor that drifts with temperature (``scale_tc_ppm`` per degC from 25 degC);
- a bias, a bias temperature coefficient (``bias_tc`` per degC from 25 degC), a bias trend in
  time (``bias_per_h``, per hour since power-on), a turn-on bias
  drawn per repetition, a bias instability (first-order Gauss-Markov) and an in-run random walk;
- white noise given as a density (per sqrt(Hz)), so the per-sample noise follows the rate;
- gyros only: g-sensitivity (``g_sens``, deg/s per g of body specific force), and two errors
  that are in no catalogue on purpose: an error periodic in the input
  (``periodic_amp``, ``periodic_period_dps``) and rate-squared cross-coupling from the other
  axes (``cross_quad``: error += sum_j cross_quad[j] w_j^2);
- accelerometers only: a 3-D ``position_mm`` from the table's rotation centre; the sensor
  senses ``axis . (f + w x (w x r) + dw/dt x r)``.

The turntable (:class:`Turntable`) turns about an axis that may be tilted from the vertical
(``axis_tilt_deg``, rotating steps only: the unit sits on the table face, so it turns about
its nominal axis while gravity is off that axis and turns around it), at a rate that may be off by
``rate_scale_error``;
Earth rotation (15.04 deg/h) is added at ``latitude_deg`` (``None``: no Earth rate).

Orientation convention (what the Earth rate's horizontal part depends on): in each step the
body's *heading reference* is the body axis least aligned with the step's up direction,
projected on the horizontal plane; at the start of the step it points at azimuth
``table.heading_deg + steps.heading_deg`` (optional steps column, default 0; degrees east of
true north). A rotating step turns the body about its rotation axis from there (positive rate
= counter-clockwise seen from above when the axis points up), starting at the commanded rate
after a linear ramp over the first half of the settling time (the ramp's angular acceleration
is physical: the accelerometers see dw/dt x r there).

Temperature: ``ChamberSoak`` holds the sensor near a thermal chamber's setpoint (the
bias and the scale factor follow cubic polynomials in temperature, ``bias_tc``..``bias_tc3``,
``scale_tc_ppm``..``scale_tc3_ppm``, and the bias keeps ``bias_hyst`` of the direction the
temperature came from: heating or cooling); ``WarmUp`` from ``start_c`` towards
``start_c + rise_c`` with time constant
``tau_s`` after power-on; the recorded ``temp_c`` adds sensor noise. A session starts
``power_on_s`` after power-on: 0 for a cold start (one repetition a day), the time already
run for repetitions run back to back (the unit stays warm; a new turn-on bias is still
drawn, as after a power cycle). The bias trend counts from power-on too.

Outputs: the contract's samples columns (raw units ``deg/s``/``g``, or ``LSB`` with
quantisation) and key-value metadata. Physical outputs saturate at the declared ranges.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from scipy.signal import lfilter

DEG = np.pi / 180.0
EARTH_RATE_DPS = 7.2921150e-5 / DEG  # sidereal rotation, 0.0041781 deg/s = 15.041 deg/h
REF_TEMP_C = 25.0
_AXES = np.eye(3)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


@dataclass(frozen=True)
class WarmUp:
    """Sensor temperature after power-on: start + rise (1 - exp(-t/tau)); recorded with noise."""

    start_c: float = 25.0
    rise_c: float = 10.0
    tau_s: float = 600.0
    noise_c: float = 0.02

    def at(self, t: np.ndarray) -> np.ndarray:
        return self.start_c + self.rise_c * (1.0 - np.exp(-np.asarray(t, float) / self.tau_s))


@dataclass(frozen=True)
class ChamberSoak:
    """Sensor temperature in a thermal chamber held at ``setpoint_c``: the sensor runs
    ``self_heating_c`` above the chamber air and approaches it from ``from_c`` (the previous
    setpoint) with time constant ``tau_s``; the session starts ``soak_s`` after the setpoint
    was reached by the air. A long soak (several tau) gives a settled temperature; a short
    one a session still drifting. ``approach``: +1 heating, -1 cooling (what hysteresis
    depends on)."""

    setpoint_c: float = 25.0
    from_c: float = 25.0
    soak_s: float = 3600.0
    tau_s: float = 300.0
    self_heating_c: float = 3.0
    noise_c: float = 0.02

    @property
    def approach(self) -> float:
        return float(np.sign(self.setpoint_c - self.from_c))

    def at(self, t: np.ndarray) -> np.ndarray:
        lag = (self.from_c - self.setpoint_c) * np.exp(-(np.asarray(t, float) + self.soak_s) / self.tau_s)
        return self.setpoint_c + self.self_heating_c + lag


@dataclass(frozen=True)
class _Sensor:
    """What gyros and accelerometers share. Physical unit: deg/s (gyro) or g (accel)."""

    axis: tuple[float, float, float]
    scale: float = 1.0  # raw units per physical unit
    bias: float = 0.0
    k2: float = 0.0  # per physical unit: output += k2 u^2
    k3: float = 0.0  # per physical unit^2: output += k3 u^3
    asym: float = 0.0  # scale(+) - scale(-), fraction
    bias_tc: float = 0.0  # bias per degC from REF_TEMP_C
    scale_tc_ppm: float = 0.0  # scale factor, ppm per degC from REF_TEMP_C
    white_density: float = 0.0  # per sqrt(Hz)
    instability: float = 0.0  # Gauss-Markov sd
    instability_tau_s: float = 20.0
    turn_on: float = 0.0  # sd of the bias drawn at each power-on (repetition)
    random_walk: float = 0.0  # per sqrt(s)
    bias_per_h: float = 0.0  # bias trend, per hour since power-on
    # chamber calibration: higher orders of the temperature dependence and a hysteresis
    bias_tc2: float = 0.0  # bias per degC^2 from REF_TEMP_C
    bias_tc3: float = 0.0  # bias per degC^3
    scale_tc2_ppm: float = 0.0  # scale factor, ppm per degC^2
    scale_tc3_ppm: float = 0.0  # scale factor, ppm per degC^3
    bias_hyst: float = 0.0  # bias reached by heating minus bias reached by cooling

    def transfer(self, u: np.ndarray, temp_c: np.ndarray, approach: float = 0.0) -> np.ndarray:
        """Deterministic response to the input along the sensor's own axis. ``approach``:
        +1 when the sensor reached its temperature by heating, -1 by cooling, 0 unknown
        (half the hysteresis each way)."""
        dt = temp_c - REF_TEMP_C
        shaped = u + self.k2 * u**2 + self.k3 * u**3 + 0.5 * self.asym * np.abs(u)
        scale = 1.0 + 1e-6 * (
            self.scale_tc_ppm * dt + self.scale_tc2_ppm * dt**2 + self.scale_tc3_ppm * dt**3
        )
        bias = self.bias + self.bias_tc * dt + self.bias_tc2 * dt**2 + self.bias_tc3 * dt**3
        return shaped * scale + bias + 0.5 * approach * self.bias_hyst

    def noise(self, t: np.ndarray, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
        """White + Gauss-Markov instability + random walk + turn-on bias, one session."""
        n = len(t)
        out = np.full(n, rng.normal(0.0, self.turn_on) if self.turn_on else 0.0)
        if self.white_density:
            out += rng.normal(0.0, self.white_density * np.sqrt(rate_hz), n)
        dt = 1.0 / rate_hz
        if self.instability:
            a = np.exp(-dt / self.instability_tau_s)
            drive = rng.normal(0.0, self.instability * np.sqrt(1.0 - a * a), n)
            drive[0] = rng.normal(0.0, self.instability)  # stationary from the start
            out += lfilter([1.0], [1.0, -a], drive)
        if self.random_walk:
            out += np.cumsum(rng.normal(0.0, self.random_walk * np.sqrt(dt), n))
        return out


@dataclass(frozen=True)
class GyroSensor(_Sensor):
    """One gyro: physical unit deg/s."""

    g_sens: tuple[float, float, float] = (0.0, 0.0, 0.0)  # deg/s per g of body specific force
    periodic_amp: float = 0.0  # deg/s, error periodic in the own input
    periodic_period_dps: float = 130.0
    cross_quad: tuple[float, float, float] = (0.0, 0.0, 0.0)  # deg/s per (deg/s)^2 of w_j


@dataclass(frozen=True)
class AccelSensor(_Sensor):
    """One accelerometer: physical unit g."""

    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # from the rotation centre


@dataclass(frozen=True)
class PhysicsUnit:
    gyros: tuple[GyroSensor, GyroSensor, GyroSensor]
    accels: tuple[AccelSensor, AccelSensor, AccelSensor]
    gyro_unit: str = "deg/s"  # deg/s or LSB (LSB: outputs rounded to integers)
    accel_unit: str = "g"  # g or LSB
    gyro_range_dps: tuple[float, float, float] = (350.0, 350.0, 4000.0)
    accel_range_g: tuple[float, float, float] = (50.0, 50.0, 50.0)
    temperature: WarmUp | ChamberSoak | None = field(default_factory=WarmUp)
    g_local: float = 9.80665

    def replace_gyro(self, i: int, **changes) -> PhysicsUnit:
        gyros = list(self.gyros)
        gyros[i] = replace(gyros[i], **changes)
        return replace(self, gyros=tuple(gyros))

    def replace_accel(self, i: int, **changes) -> PhysicsUnit:
        accels = list(self.accels)
        accels[i] = replace(accels[i], **changes)
        return replace(self, accels=tuple(accels))


@dataclass(frozen=True)
class Turntable:
    """The table and where it stands. ``latitude_deg=None``: no Earth rate in the outputs.
    ``declare_location``: write ``latitude_deg``/``table_heading_deg`` into the metadata."""

    rate_scale_error: float = 0.0
    axis_tilt_deg: float = 0.0
    tilt_azimuth_deg: float = 0.0  # direction of the tilt, in the plane normal to the axis
    latitude_deg: float | None = None
    heading_deg: float = 0.0
    declare_location: bool = False


def misaligned_axis(nominal: np.ndarray, angle_rad: float, rng: np.random.Generator) -> np.ndarray:
    """``nominal`` tilted by ``angle_rad`` in a random direction."""
    nominal = _unit(nominal)
    perp = _unit(np.cross(nominal, rng.normal(size=3)))
    return nominal * np.cos(angle_rad) + perp * np.sin(angle_rad)


def typical_physics_unit(
    rng: np.random.Generator,
    misalignment_deg: float = 0.5,
    scale_error: float = 0.01,
    gyro_bias_dps: float = 0.5,
    accel_bias_g: float = 5e-3,
    temperature: WarmUp | None = WarmUp(),
    **unit_kw,
) -> PhysicsUnit:
    """A clean, realistic unit: each sensing axis off its nominal body axis by
    ``misalignment_deg`` (each sensor its own direction), scale errors and biases of the
    given size, MEMS-grade noise, a warm-up ramp; no effect beyond the linear model.

    Noise (densities): gyro 0.007 deg/s/sqrt(Hz) (0.05 deg/s per sample at 50 Hz), bias
    instability 0.01 deg/s (tau 20 s), turn-on 0.05 deg/s; accelerometer 0.14 mg/sqrt(Hz)
    (1 mg per sample at 50 Hz), instability 0.1 mg, turn-on 1 mg.
    """
    mis = misalignment_deg * DEG
    gyros = tuple(
        GyroSensor(
            axis=tuple(misaligned_axis(_AXES[i], mis, rng)),
            scale=1.0 + rng.normal(0.0, scale_error),
            bias=rng.normal(0.0, gyro_bias_dps),
            white_density=0.05 / np.sqrt(50.0),
            instability=0.01,
            turn_on=0.05,
        )
        for i in range(3)
    )
    accels = tuple(
        AccelSensor(
            axis=tuple(misaligned_axis(_AXES[i], mis, rng)),
            scale=1.0 + rng.normal(0.0, scale_error),
            bias=rng.normal(0.0, accel_bias_g),
            white_density=1e-3 / np.sqrt(50.0),
            instability=1e-4,
            turn_on=1e-3,
        )
        for i in range(3)
    )
    return PhysicsUnit(gyros=gyros, accels=accels, temperature=temperature, **unit_kw)


# -- kinematics -------------------------------------------------------------------------
def _rotate(v: np.ndarray, k: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: rows of v (n, 3) turned right-handedly about unit rows k (n, 3) by angle (n,)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + np.cross(k, v) * s + k * np.sum(k * v, axis=1, keepdims=True) * (1.0 - c)


def _heading_reference(up: np.ndarray) -> np.ndarray:
    """The body axis least aligned with ``up``, projected on the plane normal to it."""
    e = _AXES[int(np.argmin(np.abs(up)))]
    return _unit(e - np.dot(e, up) * up)


@dataclass(frozen=True)
class _StepGeometry:
    up0: np.ndarray  # (3,) body direction of the world vertical at the step's start
    north0: np.ndarray  # (3,) body direction of true north at the step's start
    axis: np.ndarray  # (3,) body rotation axis (unit); zeros for a static step
    rate: float  # true table rate, deg/s (signed about ``axis``)


def _step_geometry(
    w_ref: np.ndarray, f_ref: np.ndarray, heading_deg: float, table: Turntable
) -> _StepGeometry:
    rate_nominal = float(np.linalg.norm(w_ref))
    if np.linalg.norm(f_ref) > 1e-9:
        up0 = _unit(f_ref)
    else:
        up0 = _unit(w_ref) if rate_nominal else np.array([0.0, 0.0, 1.0])
    if rate_nominal:
        axis = _unit(w_ref)
        if table.axis_tilt_deg:  # the unit sits on the table face; the table axis is off
            side = _heading_reference(axis)  # the vertical, so gravity is off the axis too
            side = _rotate(side[None], axis[None], np.array([table.tilt_azimuth_deg * DEG]))[0]
            up0 = _rotate(
                up0[None], _unit(np.cross(axis, side))[None], np.array([table.axis_tilt_deg * DEG])
            )[0]
        rate = rate_nominal * (1.0 + table.rate_scale_error)
    else:
        axis, rate = np.zeros(3), 0.0
    href = _heading_reference(up0)
    # href points at azimuth psi (clockwise from north); north is href turned by +psi about up
    psi = (table.heading_deg + heading_deg) * DEG
    north0 = _rotate(href[None], up0[None], np.array([psi]))[0]
    return _StepGeometry(up0, north0, axis, rate)


def _timeline(steps: pd.DataFrame, rate_hz: float, gap_s: float):
    dur = steps["duration_s"].to_numpy(float) if "duration_s" in steps else np.full(len(steps), 3.0)
    n = np.maximum(np.round(dur * rate_hz).astype(int), 1)
    n_gap = max(int(round(gap_s * rate_hz)), 1)
    starts = np.concatenate([[0], np.cumsum(n + n_gap)[:-1]]) + n_gap
    return starts, n


def _motion(steps: pd.DataFrame, rate_hz: float, gap_s: float, table: Turntable):
    """Per sample: step id, time, body rate (deg/s), angular acceleration (deg/s^2), body
    direction of up (specific force at the centre, g) and of north."""
    starts, n = _timeline(steps, rate_hz, gap_s)
    total = int(starts[-1] + n[-1])
    t = np.arange(total) / rate_hz
    step_of = np.full(total, -1, dtype=np.int32)
    axis = np.zeros((total, 3))
    rate = np.zeros(total)
    dwdt = np.zeros(total)
    angle = np.zeros(total)
    up0 = np.zeros((total, 3))
    north0 = np.zeros((total, 3))
    w_ref = steps[["w_ref_x", "w_ref_y", "w_ref_z"]].to_numpy(float)
    f_ref = steps[["f_ref_x", "f_ref_y", "f_ref_z"]].to_numpy(float)
    settle = steps["settle_s"].to_numpy(float)
    heading = steps["heading_deg"].to_numpy(float) if "heading_deg" in steps else np.zeros(len(steps))
    ids = steps["step"].to_numpy(np.int32)
    prev = None
    for k in range(len(steps)):  # per step (a hundred), not per sample
        geo = _step_geometry(w_ref[k], f_ref[k], heading[k], table)
        s0, m = int(starts[k]), int(n[k])
        # the gap before the step holds the previous step's state (ignored samples, step -1)
        g0 = int(starts[k - 1] + n[k - 1]) if k else 0
        sl = slice(g0, s0)
        if prev is not None:
            axis[sl], rate[sl], up0[sl], north0[sl] = prev.axis, prev.rate, prev.up0, prev.north0
            angle[sl] = angle[g0 - 1] + prev.rate * DEG * (t[sl] - t[g0 - 1])
        else:  # before the first step the unit rests in the first step's position
            up0[sl], north0[sl] = geo.up0, geo.north0
        sl = slice(s0, s0 + m)
        step_of[sl] = ids[k]
        axis[sl], up0[sl], north0[sl] = geo.axis, geo.up0, geo.north0
        tau = t[sl] - t[s0]
        ramp = max(0.5 * settle[k], 1.0 / rate_hz)
        r = geo.rate * np.minimum(tau / ramp, 1.0)
        rate[sl] = r
        dwdt[sl] = np.where(tau < ramp, geo.rate / ramp, 0.0)
        # angle turned: integral of the ramp then of the constant rate
        angle[sl] = DEG * np.where(
            tau < ramp, 0.5 * geo.rate * tau**2 / ramp, geo.rate * (0.5 * ramp + (tau - ramp))
        )
        prev = geo
    w_table = axis * rate[:, None]
    # world vectors seen from the body turn backwards about the rotation axis
    has_axis = np.linalg.norm(axis, axis=1) > 0
    up = up0.copy()
    north = north0.copy()
    if has_axis.any():
        up[has_axis] = _rotate(up0[has_axis], axis[has_axis], -angle[has_axis])
        north[has_axis] = _rotate(north0[has_axis], axis[has_axis], -angle[has_axis])
    return step_of, t, w_table, axis * dwdt[:, None], up, north


def earth_rate_body(up: np.ndarray, north: np.ndarray, latitude_deg: float) -> np.ndarray:
    """Earth rotation in the body frame (deg/s), from the body directions of up and north."""
    lat = latitude_deg * DEG
    return EARTH_RATE_DPS * (np.cos(lat) * north + np.sin(lat) * up)


# -- the session ------------------------------------------------------------------------
def simulate_physics_session(
    unit: PhysicsUnit,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    rate_hz: float = 50.0,
    table: Turntable = Turntable(),
    gap_s: float = 0.2,
    session_start: str = "2026-11-20T02:00:00Z",
    dtype=np.float32,
    power_on_s: float = 0.0,
) -> tuple[pd.DataFrame, dict[str, str]]:
    """Raw samples (the contract's columns) and metadata of one repetition that starts
    ``power_on_s`` after power-on (0: a cold start)."""
    step_of, t, w_table, dwdt, up, north = _motion(steps, rate_hz, gap_s, table)
    w = w_table.copy()
    if table.latitude_deg is not None:
        w += earth_rate_body(up, north, table.latitude_deg)
    t_on = t + power_on_s  # time since power-on: what warms the sensor and ages its bias
    temp = unit.temperature.at(t_on) if unit.temperature is not None else np.full(len(t), REF_TEMP_C)
    approach = float(getattr(unit.temperature, "approach", 0.0))
    f_centre = up  # specific force at rest is the up direction, 1 g
    w_rad, a_rad = w * DEG, dwdt * DEG
    raw = {}
    for i, (name, g) in enumerate(zip(("gx", "gy", "gz"), unit.gyros)):
        u = w @ np.asarray(g.axis)
        out = g.transfer(u, temp, approach) + f_centre @ np.asarray(g.g_sens) + g.bias_per_h * t_on / 3600.0
        if g.periodic_amp:
            out += g.periodic_amp * np.sin(2.0 * np.pi * u / g.periodic_period_dps)
        out += (w**2) @ np.asarray(g.cross_quad)
        out += g.noise(t, rate_hz, rng)
        lim = unit.gyro_range_dps[i]
        raw[name] = g.scale * np.clip(out, -lim, lim)
    for i, (name, a) in enumerate(zip(("ax", "ay", "az"), unit.accels)):
        r = np.asarray(a.position_mm) * 1e-3
        centripetal = np.cross(w_rad, np.cross(w_rad, np.broadcast_to(r, w.shape)))
        tangential = np.cross(a_rad, np.broadcast_to(r, w.shape))
        f = f_centre + (centripetal + tangential) / unit.g_local
        out = a.transfer(f @ np.asarray(a.axis), temp, approach) + a.bias_per_h * t_on / 3600.0
        out += a.noise(t, rate_hz, rng)
        lim = unit.accel_range_g[i]
        raw[name] = a.scale * np.clip(out, -lim, lim)
    for names, quant in (
        (("gx", "gy", "gz"), unit.gyro_unit == "LSB"),
        (("ax", "ay", "az"), unit.accel_unit == "LSB"),
    ):
        if quant:
            for nm in names:
                raw[nm] = np.round(raw[nm])
    samples = pd.DataFrame({"step": step_of, "t": t, **{k: v.astype(dtype) for k, v in raw.items()}})
    if unit.temperature is not None:
        samples["temp_c"] = (temp + rng.normal(0.0, unit.temperature.noise_c, len(t))).astype(np.float32)
    return samples, physics_metadata(unit, rate_hz, table, session_start)


def physics_metadata(
    unit: PhysicsUnit, rate_hz: float, table: Turntable, session_start: str
) -> dict[str, str]:
    """Key-value metadata of samples.parquet. Ranges are declared in the physical units."""
    md = {
        "gyro_unit": unit.gyro_unit,
        "accel_unit": unit.accel_unit,
        "sample_rate_hz": f"{rate_hz:g}",
        "gyro_range_dps": ",".join(f"{v:g}" for v in unit.gyro_range_dps),
        "accel_range_g": ",".join(f"{v:g}" for v in unit.accel_range_g),
        "g_local": f"{unit.g_local:.5f}",
        "session_start": session_start,
        "source": "mimucal physics simulator",
    }
    if table.declare_location and table.latitude_deg is not None:
        md["latitude_deg"] = f"{table.latitude_deg:g}"
        md["table_heading_deg"] = f"{table.heading_deg:g}"
    return md
