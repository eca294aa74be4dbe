"""Units of the noise coefficients: the channel's own unit inside, IEEE Std 952 (gyros) and
1293 (accelerometers) units for people, Kalibr's continuous-time SI for tools.

Inside, a coefficient is in the channel unit ``U`` times a power of seconds (see
:mod:`calib_core.noise.processes`): quantization ``U s``, white ``U sqrt(s)`` (= U/sqrt(Hz)),
bias instability ``U``, random walk ``U/sqrt(s)``, ramp ``U/s``, Gauss-Markov sigma ``U``.
Channel units: gyro ``deg/s`` or ``rad/s``; accelerometer ``g`` (9.80665 m/s^2) or ``m/s^2``.

IEEE units (what a datasheet prints):

====================  ================  ==================
process               gyro              accelerometer
====================  ================  ==================
quantization          deg               m/s
white (ARW / VRW)     deg/sqrt(h)       m/s/sqrt(h)
bias_instability      deg/h             mg
random_walk (RRW/AA)  deg/h/sqrt(h)     m/s/h/sqrt(h)
ramp                  deg/h^2           m/s/h^2
gauss_markov sigma    deg/h             mg
====================  ================  ==================

Kalibr's ``imu.yaml`` takes continuous-time densities in SI: ``gyroscope_noise_density``
[rad/s/sqrt(Hz)], ``gyroscope_random_walk`` [rad/s^2/sqrt(Hz)], ``accelerometer_noise_density``
[m/s^2/sqrt(Hz)], ``accelerometer_random_walk`` [m/s^3/sqrt(Hz)]. The discrete-time standard
deviation of one sample is the continuous density times sqrt(rate); Kalibr wants the
continuous one.
"""

from __future__ import annotations

import math

G0 = 9.80665  # m/s^2 per g (standard gravity: the definition of mg in IEEE 1293 figures)
GYRO_UNITS = {"deg/s": 1.0, "rad/s": 180.0 / math.pi}  # -> deg/s
ACCEL_UNITS = {"g": G0, "m/s^2": 1.0, "m/s2": 1.0}  # -> m/s^2
SECONDS_POWER = {
    "quantization": 1.0,
    "white": 0.5,
    "bias_instability": 0.0,
    "random_walk": -0.5,
    "ramp": -1.0,
    "gauss_markov": 0.0,
}
IEEE_UNITS = {
    "gyro": {
        "quantization": ("deg", 1.0),
        "white": ("deg/sqrt(h)", 60.0),
        "bias_instability": ("deg/h", 3600.0),
        "random_walk": ("deg/h/sqrt(h)", 3600.0 * 60.0),
        "ramp": ("deg/h^2", 3600.0**2),
        "gauss_markov": ("deg/h", 3600.0),
    },
    "accel": {
        "quantization": ("m/s", 1.0),
        "white": ("m/s/sqrt(h)", 60.0),
        "bias_instability": ("mg", 1000.0 / G0),
        "random_walk": ("m/s/h/sqrt(h)", 3600.0 * 60.0),
        "ramp": ("m/s/h^2", 3600.0**2),
        "gauss_markov": ("mg", 1000.0 / G0),
    },
}  # (unit, factor from the base unit deg/s or m/s^2 times seconds^power)
NATIVE_SUFFIX = {1.0: "*s", 0.5: "/sqrt(Hz)", 0.0: "", -0.5: "/sqrt(s)", -1.0: "/s"}


def channel_kind(unit: str) -> str:
    """``gyro`` or ``accel`` from a channel unit; ValueError for anything else."""
    if unit in GYRO_UNITS:
        return "gyro"
    if unit in ACCEL_UNITS:
        return "accel"
    raise ValueError(
        f"noise coefficients need a physical channel unit (deg/s, rad/s, g or m/s^2), not {unit!r}"
    )


def _to_base(unit: str) -> float:
    return GYRO_UNITS.get(unit) or ACCEL_UNITS[unit]


def native_unit(process: str, channel_unit: str) -> str:
    """The inside unit of a coefficient, e.g. ``deg/s/sqrt(Hz)`` for a gyro's white noise."""
    return channel_unit + NATIVE_SUFFIX[SECONDS_POWER[process]]


def ieee_unit(process: str, channel_unit: str) -> str:
    return IEEE_UNITS[channel_kind(channel_unit)][process][0]


def to_ieee(process: str, value: float, channel_unit: str) -> float:
    """A coefficient in the channel's inside unit -> its IEEE 952/1293 unit."""
    kind = channel_kind(channel_unit)
    return float(value) * _to_base(channel_unit) * IEEE_UNITS[kind][process][1]


def from_unit(process: str, value: float, unit: str, channel_unit: str) -> float:
    """A coefficient written in ``unit`` (its IEEE unit or its inside unit) -> inside unit."""
    if unit == native_unit(process, channel_unit):
        return float(value)
    kind = channel_kind(channel_unit)
    ieee, factor = IEEE_UNITS[kind][process]
    if unit != ieee:
        raise ValueError(
            f"{process} of a {channel_unit} channel is in {ieee} or "
            f"{native_unit(process, channel_unit)}, not {unit!r}"
        )
    return float(value) / factor / _to_base(channel_unit)


def kalibr_density(process: str, value: float, channel_unit: str) -> float:
    """White (noise density) or random walk coefficient -> Kalibr's continuous-time SI
    (gyro rad/s/sqrt(Hz), rad/s^2/sqrt(Hz); accel m/s^2/sqrt(Hz), m/s^3/sqrt(Hz))."""
    if process not in ("white", "random_walk"):
        raise ValueError("Kalibr takes the white and random-walk densities only")
    base = float(value) * _to_base(channel_unit)
    return base * math.pi / 180.0 if channel_kind(channel_unit) == "gyro" else base


KALIBR_UNITS = {
    ("gyro", "white"): ("gyroscope_noise_density", "rad/s/sqrt(Hz)"),
    ("gyro", "random_walk"): ("gyroscope_random_walk", "rad/s^2/sqrt(Hz)"),
    ("accel", "white"): ("accelerometer_noise_density", "m/s^2/sqrt(Hz)"),
    ("accel", "random_walk"): ("accelerometer_random_walk", "m/s^3/sqrt(Hz)"),
}
