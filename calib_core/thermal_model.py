"""The applied calibration as a function of the sensor's temperature (a chamber calibration).

Each parameter of the affine form (K_g, w0, K_a, f0; xu2016 eq. 1-2) is a polynomial in the
sensor temperature ``T`` (degC) about ``t_ref_c``::

    p(T) = c0 + c1 (T - t_ref) + c2 (T - t_ref)^2 + c3 (T - t_ref)^3

with its own order (0..3). The model is valid over ``[t_min_c, t_max_c]``, the sensor
temperatures of the calibrated setpoints; :meth:`ThermalModel.outside` names the samples
beyond it (the applying code refuses them unless told to extrapolate). The fit that produces
it is :mod:`calib_core.models.thermal`; this module is pure and small so that
:class:`calib_core.calibration.Calibration` can carry it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

_MAT = [f"{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
GYRO_NAMES = tuple(f"k_g{m}" for m in _MAT) + tuple(f"w0_{a}" for a in "xyz")
ACCEL_NAMES = tuple(f"k_a{m}" for m in _MAT) + tuple(f"f0_{a}" for a in "xyz")
PARAM_NAMES = GYRO_NAMES + ACCEL_NAMES
# the tolerance past the calibrated range within which a sample is still in range (degC):
# the recorded temperature has noise of a few hundredths of a degree
RANGE_TOLERANCE_C = 0.5


def coefficient_name(param: str, power: int) -> str:
    """``w0_x``, 1 -> ``w0_tc_x``; ``w0_x``, 3 -> ``w0_tc3_x``; ``k_g11``, 2 -> ``k_g11_tc2``;
    power 0 is the parameter itself (its value at ``t_ref_c``)."""
    if power == 0:
        return param
    tag = "tc" if power == 1 else f"tc{power}"
    if param[-2] == "_" and param[-1] in "xyz":
        return f"{param[:-2]}_{tag}_{param[-1]}"
    return f"{param}_{tag}"


def coefficient_unit(param_unit: str, power: int) -> str:
    """``deg/s``, 1 -> ``deg/s/degC``; a dimensionless unit, 2 -> ``1/degC^2``."""
    if power == 0:
        return param_unit
    per = "degC" if power == 1 else f"degC^{power}"
    dimensionless = param_unit in ("", "1") or (
        " per " in param_unit and len(set(param_unit.split(" per "))) == 1
    )
    return f"1/{per}" if dimensionless else f"{param_unit}/{per}"


@dataclass(frozen=True)
class ThermalModel:
    """Polynomial coefficients of every affine parameter (``coefs[name]``: c0..c_order, in
    the parameter's unit per degC^k) about ``t_ref_c``, valid over ``[t_min_c, t_max_c]``."""

    t_ref_c: float
    t_min_c: float
    t_max_c: float
    coefs: dict[str, np.ndarray]
    hysteresis: dict[str, float] = field(default_factory=dict)  # heating minus cooling, named only

    def value(self, name: str, temp_c: np.ndarray) -> np.ndarray:
        c = np.asarray(self.coefs[name], float)
        dt = np.asarray(temp_c, float) - self.t_ref_c
        return np.polynomial.polynomial.polyval(dt, c)

    def matrices(self, temp_c) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """K_g (n, 3, 3), w0 (n, 3), K_a (n, 3, 3), f0 (n, 3) at each temperature."""
        t = np.atleast_1d(np.asarray(temp_c, float))
        K_g = np.stack([self.value(f"k_g{m}", t) for m in _MAT], axis=-1).reshape(len(t), 3, 3)
        w0 = np.stack([self.value(f"w0_{a}", t) for a in "xyz"], axis=-1)
        K_a = np.stack([self.value(f"k_a{m}", t) for m in _MAT], axis=-1).reshape(len(t), 3, 3)
        f0 = np.stack([self.value(f"f0_{a}", t) for a in "xyz"], axis=-1)
        return K_g, w0, K_a, f0

    def apply(self, G: np.ndarray, A: np.ndarray, temp_c) -> tuple[np.ndarray, np.ndarray]:
        """Each raw sample with the parameters at its own temperature."""
        K_g, w0, K_a, f0 = self.matrices(temp_c)
        w = np.einsum("nij,nj->ni", K_g, np.atleast_2d(G)) + w0
        f = np.einsum("nij,nj->ni", K_a, np.atleast_2d(A)) + f0
        return w, f

    def outside(self, temp_c, tolerance_c: float = RANGE_TOLERANCE_C) -> np.ndarray:
        """Boolean mask of the temperatures outside the calibrated range (NaN counts)."""
        t = np.asarray(temp_c, float)
        return ~((t >= self.t_min_c - tolerance_c) & (t <= self.t_max_c + tolerance_c))

    def orders(self) -> dict[str, int]:
        return {k: len(v) - 1 for k, v in self.coefs.items()}

    def to_dict(self) -> dict[str, Any]:
        return {
            "form": "p(T) = sum_k c_k (T - t_ref_c)^k, T the sensor temperature temp_c in degC",
            "t_ref_c": self.t_ref_c,
            "range_c": [self.t_min_c, self.t_max_c],
            "coefficients": {k: np.asarray(v, float).tolist() for k, v in self.coefs.items()},
            "hysteresis": dict(self.hysteresis),
        }

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> ThermalModel:
        coefs = {k: np.asarray(v, float) for k, v in doc["coefficients"].items()}
        missing = [n for n in PARAM_NAMES if n not in coefs]
        if missing:
            raise ValueError(f"thermal model lacks {', '.join(missing)}")
        bad = [n for n, c in coefs.items() if c.ndim != 1 or not 1 <= len(c) <= 4 or not np.isfinite(c).all()]
        if bad:
            raise ValueError(f"thermal coefficients of {', '.join(bad)} must be 1 to 4 finite numbers")
        lo, hi = (float(x) for x in doc["range_c"])
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ValueError(f"thermal range_c {doc['range_c']!r} is not [min, max]")
        return cls(
            float(doc["t_ref_c"]),
            lo,
            hi,
            coefs,
            {k: float(v) for k, v in (doc.get("hysteresis") or {}).items()},
        )
