"""The calibration a firmware engineer loads: raw outputs -> deg/s and g.

    w = K_g G + w0 - e_gyro(w, f, ...)        f = K_a A + f0 - e_accel(w, f, ...)

The affine part is xu2016 eq. 1-2 (no matrix inverse at run time); ``terms`` are optional
catalogue effects (:mod:`calib_core.effects`) whose estimated error is subtracted, acting
through the sensing geometry of the calibration's own gains. Every
calibration type mimucal produces (turntable, Ferraris, reference-free field calibration) is
expressed in this one form, so one ``apply`` serves them all. Serialisation lives in
``schemas.calibration_file``; this module is pure.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib_core.effects import MotionContext, SensingGeometry, get_effect
from calib_core.thermal_model import ThermalModel


@dataclass(frozen=True)
class TermValue:
    """An extension term with its estimated parameters.

    A parameter the steps could not determine (``undetermined``: name -> reason) is applied
    as 0 and written as ``null`` with its reason, never as a number."""

    name: str  # catalogue name
    params: np.ndarray
    stderr: np.ndarray | None = None
    undetermined: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        term = get_effect(self.name)

        def number(n: str, v: float) -> float | None:
            return None if n in self.undetermined or not np.isfinite(v) else float(v)

        out = {
            "name": self.name,
            "params": {n: number(n, v) for n, v in zip(term.param_names, self.params)},
            "stderr": None
            if self.stderr is None
            else {n: number(n, v) for n, v in zip(term.param_names, self.stderr)},
            "units": dict(zip(term.param_names, term.param_units)),
        }
        if self.undetermined:
            out["undetermined"] = dict(self.undetermined)
        return out


class RawUnitError(ValueError):
    """Raw data in units a calibration cannot take."""


@dataclass(frozen=True)
class Calibration:
    """Affine calibration of both sensors plus optional extension terms."""

    K_g: np.ndarray  # deg/s per raw gyro unit
    w0: np.ndarray  # deg/s
    K_a: np.ndarray  # g per raw accel unit
    f0: np.ndarray  # g
    gyro_unit: str = "deg/s"  # raw unit the matrices expect (after boundary conversion)
    accel_unit: str = "g"
    terms: tuple[TermValue, ...] = ()
    g_local: float = 9.80665
    kind: str = "turntable"  # turntable | ferraris | field | thermal
    metadata: dict[str, Any] = field(default_factory=dict)
    # a chamber calibration: the affine parameters as polynomials in the sensor temperature
    # (K_g, w0, K_a, f0 above are their values at thermal.t_ref_c); applied per sample when
    # the temperature is given, the fields above when it is not
    thermal: ThermalModel | None = None

    @property
    def geometry(self) -> SensingGeometry:
        """Sensing directions of the six sensors implied by the gains: what the terms act
        through."""
        return SensingGeometry.from_gains(self.K_g, self.K_a)

    def apply_affine(
        self, G: np.ndarray, A: np.ndarray, temp_c: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        G = np.atleast_2d(G)
        A = np.atleast_2d(A)
        if self.thermal is not None and temp_c is not None:
            return self.thermal.apply(G, A, np.broadcast_to(np.asarray(temp_c, float), (len(G),)))
        return G @ self.K_g.T + self.w0, A @ self.K_a.T + self.f0

    def raw_inputs(
        self, G: np.ndarray, A: np.ndarray, gyro_unit: str | None = None, accel_unit: str | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``G``, ``A`` in the raw units this calibration expects (:class:`RawUnitError`
        when they cannot be). ``gyro_unit`` / ``accel_unit``: the units of the data;
        rad/s -> deg/s and m/s^2 -> g (this calibration's ``g_local``) are converted when the
        calibration expects deg/s and g; any other difference is refused. Without
        ``accel_unit``, accelerometer data whose median norm is that of gravity in m/s^2
        (7.8-12.3) given to a calibration in g are refused (the mistake that otherwise
        returns |f| ~ 9.8 "g")."""
        G = np.atleast_2d(np.asarray(G, float))
        A = np.atleast_2d(np.asarray(A, float))
        if gyro_unit is not None and gyro_unit != self.gyro_unit:
            if gyro_unit == "rad/s" and self.gyro_unit == "deg/s":
                G = G * (180.0 / np.pi)
            else:
                raise RawUnitError(f"gyro data in {gyro_unit!r}, calibration expects {self.gyro_unit!r}")
        if accel_unit is not None and accel_unit != self.accel_unit:
            if accel_unit == "m/s^2" and self.accel_unit == "g":
                A = A / self.g_local
            else:
                raise RawUnitError(
                    f"accelerometer data in {accel_unit!r}, calibration expects {self.accel_unit!r}"
                )
        elif accel_unit is None and self.accel_unit == "g" and A.size:
            norm = float(np.nanmedian(np.linalg.norm(A, axis=1)))
            if 0.8 * self.g_local <= norm <= 1.25 * self.g_local:
                raise RawUnitError(
                    f"accelerometer data have a median norm of {norm:.3g}: that is gravity "
                    f"in m/s^2, and this calibration expects g; pass accel_unit='m/s^2' (or "
                    f"'g' if the data really are in g)"
                )
        return G, A

    def apply_recording(
        self,
        G: np.ndarray,
        A: np.ndarray,
        t: np.ndarray | None = None,
        temp_c: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`apply` to the samples of a recording (raw units already the calibration's):
        the angular acceleration that terms of it need is the time derivative of the affine
        rates (``t`` [s], at least 3 samples; without them the terms see none)."""
        dwdt = None
        if self.terms and t is not None and len(t) > 2:
            w_affine, _ = self.apply_affine(G, A, temp_c)
            dwdt = np.gradient(w_affine, t, axis=0)
        return self.apply(G, A, dwdt=dwdt, temp_c=temp_c, t=t)

    def apply(
        self,
        G: np.ndarray,
        A: np.ndarray,
        dwdt: np.ndarray | None = None,
        temp_c: np.ndarray | None = None,
        t: np.ndarray | None = None,
        iterations: int = 2,
        gyro_unit: str | None = None,
        accel_unit: str | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Calibrated rate (deg/s) and specific force (g), rows of raw samples or step means.

        ``gyro_unit`` / ``accel_unit``: the units of ``G`` and ``A``, checked against the
        calibration's and converted where that is exact (:meth:`raw_inputs`).
        Extension terms depend on the true motion, which is estimated by the affine part and
        refined by a fixed-point iteration (terms are small: two iterations reach noise)."""
        G, A = self.raw_inputs(G, A, gyro_unit, accel_unit)
        w, f = self.apply_affine(G, A, temp_c)
        if not self.terms:
            return w, f
        w_aff, f_aff = w, f
        geometry = self.geometry
        for _ in range(iterations):
            ctx = MotionContext.from_refs(w, f, temp_c=temp_c, t=t, dwdt=dwdt, g_local=self.g_local)
            err = np.zeros((len(w), 6))
            for tv in self.terms:
                term = get_effect(tv.name)
                if term.sensor_effect:  # the Earth's rotation is signal once off the table
                    err += term.error(ctx, tv.params, geometry)
            w, f = w_aff - err[:, :3], f_aff - err[:, 3:]
        return w, f

    def predict_raw(
        self, w: np.ndarray, f: np.ndarray, dwdt=None, temp_c=None, t=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The calibration run as a simulation: raw outputs it expects for a motion."""
        w = np.atleast_2d(w)
        f = np.atleast_2d(f)
        sensed = np.hstack([w, f])
        if self.terms:
            ctx = MotionContext.from_refs(w, f, temp_c=temp_c, t=t, dwdt=dwdt, g_local=self.g_local)
            for tv in self.terms:
                sensed = sensed + get_effect(tv.name).error(ctx, tv.params, self.geometry)
        G = np.linalg.solve(self.K_g, (sensed[:, :3] - self.w0).T).T
        A = np.linalg.solve(self.K_a, (sensed[:, 3:] - self.f0).T).T
        return G, A
