"""Plausibility of a fitted calibration: absurd estimates are refused, not written.

A least-squares fit always returns numbers. Whether they describe a sensor is a separate
question: a scale factor of 0.3 on a deg/s output, a bias beyond the full scale or a
non-finite value means the data or the references are wrong (a unit mounted on the wrong
axis, a rate table in rad/s written as deg/s, ...). These checks name the parameter, its value
and the limit; the pipeline fails the session with ``E_IMPLAUSIBLE`` so the unit's last good
calibration stays in force.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_core.steps import StepMeans

# K diagonal for an output already in deg/s or g: a MEMS scale error beyond +/-25 % is a
# wrong unit or a wrong reference, not a sensor.
SCALE_LIMITS = (0.75, 1.25)
CROSS_AXIS_LIMIT = 0.2  # |off-diagonal K| (about 11 deg of misalignment)
PHYSICAL_UNITS = {"gyro": "deg/s", "accel": "g"}


@dataclass(frozen=True)
class Implausible:
    model: str
    parameter: str
    value: float
    limit: str

    def __str__(self) -> str:
        return f"{self.model} {self.parameter} = {self.value:.6g} outside {self.limit}"


def check_affine(
    model: str, prefix: str, K: np.ndarray, x0: np.ndarray, raw_unit: str, full_scale: np.ndarray
) -> list[Implausible]:
    out: list[Implausible] = []
    for name, arr in (("K", K), ("bias", x0)):
        if not np.isfinite(arr).all():
            out.append(Implausible(model, name, float("nan"), "finite values"))
    if out:
        return out
    if raw_unit == PHYSICAL_UNITS[model]:
        for i in range(3):
            if not SCALE_LIMITS[0] <= K[i, i] <= SCALE_LIMITS[1]:
                out.append(
                    Implausible(
                        model,
                        f"{prefix}{i + 1}{i + 1}",
                        float(K[i, i]),
                        f"[{SCALE_LIMITS[0]}, {SCALE_LIMITS[1]}] for raw {raw_unit}",
                    )
                )
            for j in range(3):
                if i != j and abs(K[i, j]) > CROSS_AXIS_LIMIT:
                    out.append(
                        Implausible(
                            model, f"{prefix}{i + 1}{j + 1}", float(K[i, j]), f"+/-{CROSS_AXIS_LIMIT}"
                        )
                    )
    bias_name = "w0" if model == "gyro" else "f0"
    for i, axis in enumerate("xyz"):
        if abs(x0[i]) > full_scale[i]:
            out.append(
                Implausible(
                    model,
                    f"{bias_name}_{axis}",
                    float(x0[i]),
                    f"the declared full scale +/-{full_scale[i]:g}",
                )
            )
    return out


def check_fits(fits: dict, sm: StepMeans) -> list[Implausible]:
    """Checks on the base model of a session's fits."""
    out: list[Implausible] = []
    if "gyro" in fits:
        g = fits["gyro"]
        out += check_affine("gyro", "k_g", g.K, g.w0, g.raw_unit, np.asarray(sm.gyro_range_dps))
    if "accel" in fits:
        a = fits["accel"]
        out += check_affine("accel", "k_a", a.K, a.f0, a.raw_unit, np.asarray(sm.accel_range_g))
    return out
