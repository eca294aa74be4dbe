"""The calibration method of Xu, Wang, Su, Zhu (2016), with standard errors.

- Gyro, eq. 3-11: ``w = K_g G + w0``. The difference of a +rate and a -rate step about the
  same axis removes the bias (eq. 5); K_g from all multirate pairs by least squares (eq. 6-8);
  w0 = -K_g mean(G(0)) from the stationary steps (eq. 10-11).
- Accelerometer, eq. 12-16: ``f = K_a A + f0`` from all multiposition steps.
- The "traditional" inverse model, ``G = S w + b`` so ``w = S^-1 (G - b)``, fitted on the
  same steps, for the comparison of the paper's Table 3.

Standard errors come from the residuals and the design. The step-level noise that the +/-
differences reveal (white noise averaged over the step plus step-to-step bias instability) is
also the noise of each stationary step, which is what makes an honest standard error of w0
possible from only three stationary steps.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import pandas as pd

from calib_core.errors import DesignError
from calib_core.linalg import solve_lstsq
from calib_core.results import Param, matrix_params, vector_params
from calib_core.tables import CodedStrings, ColumnTable
from calib_core.steps import StepMeans

AXES = "xyz"
MAX_CONDITION = 1e6  # beyond this the design cannot separate the parameters


def _axis_names(prefix: str) -> list[str]:
    return [f"{prefix}_{a}" for a in AXES]


def _check_determined(sm: StepMeans, excitation: np.ndarray, what: str, needed: str) -> None:
    """Name the axes the design never excites (rank deficiency with a physical reason)."""
    peak = np.abs(excitation).max(axis=0, initial=0.0)  # per axis, one reduction
    missing = [AXES[i] for i in range(3) if peak[i] < 1e-9]
    if missing:
        raise DesignError(
            "E_UNDETERMINED",
            f"{what}: no {needed} about/along {', '.join(missing)}; "
            f"cannot determine the column(s) of K for axis {', '.join(missing)}",
            undetermined=tuple(f"{what} axis {m}" for m in missing),
        )


# --------------------------------------------------------------------------- gyro
def multirate_pairs(sm: StepMeans) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pair each +rate step with its -rate step about the same axis.

    Returns (dG (n,3) raw, dW (n,3) deg/s, index pairs (n,2) into ``sm``). A step whose
    partner is missing (saturated, too short) is left out: the difference needs both.
    """
    multirate = sm.test == "multirate"
    # the pairing depends on the protocol only (tests, rates, reference rates), the same for
    # every session of a fleet: found once per protocol, not once per session
    pairs_arr = _pairs_of_protocol(multirate.tobytes(), sm.rate_dps.astype(float).tobytes(),
                                   np.ascontiguousarray(sm.w_ref, dtype=float).tobytes())
    dG = sm.gyro[pairs_arr[:, 0]] - sm.gyro[pairs_arr[:, 1]]
    dW = sm.w_ref[pairs_arr[:, 0]] - sm.w_ref[pairs_arr[:, 1]]
    return dG, dW, pairs_arr.copy()


@lru_cache(maxsize=64)
def _pairs_of_protocol(multirate: bytes, rate_dps: bytes, w_ref: bytes) -> np.ndarray:
    """(n,2) index pairs (+rate step, -rate step) of a protocol, read-only (it is shared)."""
    rate = np.frombuffer(rate_dps, dtype=float)
    w_ref_arr = np.frombuffer(w_ref, dtype=float).reshape(-1, 3)
    idx = np.flatnonzero(np.frombuffer(multirate, dtype=bool))
    groups: dict[tuple, dict[int, list[int]]] = {}
    for i in idx:  # one pass over the protocol's steps, once per protocol
        r = rate[i]
        if r == 0:
            continue
        direction = np.round(w_ref_arr[i] / r, 6) + 0.0  # rotation axis, sign-free
        key = (round(abs(r), 6), tuple(direction))
        groups.setdefault(key, {1: [], -1: []})[int(np.sign(r))].append(i)
    pairs = []
    for sides in groups.values():
        for p, m in zip(sides[1], sides[-1]):
            pairs.append((p, m))
    pairs_arr = np.array(sorted(pairs), dtype=int).reshape(-1, 2)
    pairs_arr.setflags(write=False)
    return pairs_arr


@dataclass(frozen=True)
class GyroMultirateFit:
    """K_g and w0 of xu2016 eq. 1 with their standard errors."""

    K: np.ndarray  # (3,3) deg/s per raw unit
    w0: np.ndarray  # (3,) deg/s
    K_stderr: np.ndarray
    w0_stderr: np.ndarray
    step_sigma: np.ndarray  # (3,) deg/s, noise of one step mean (white + instability)
    residual_rms: np.ndarray  # (3,) deg/s, of the +/- difference equations
    condition_number: float
    n_pairs: int
    n_stationary: int
    w0_source: str  # "stationary" (eq. 10-11) or "pair_midpoints" when no stationary step
    raw_unit: str = "deg/s"
    model: str = "gyro"

    def compensate(self, G: np.ndarray) -> np.ndarray:
        """Eq. 1: calibrated rate (deg/s) from raw outputs, no matrix inverse."""
        return np.atleast_2d(G) @ self.K.T + self.w0

    def parameters(self) -> list[Param]:
        return (matrix_params(self.model, "k_g", self.K, self.K_stderr, f"deg/s per {self.raw_unit}")
                + vector_params(self.model, _axis_names("w0"), self.w0, self.w0_stderr, "deg/s"))

    def to_dict(self) -> dict[str, Any]:
        return {
            "K_g": self.K.tolist(), "w0": self.w0.tolist(),
            "stderr": {"K_g": self.K_stderr.tolist(), "w0": self.w0_stderr.tolist()},
            "condition_number": self.condition_number, "n_pairs": self.n_pairs,
            "n_stationary": self.n_stationary, "w0_source": self.w0_source,
            "step_sigma_dps": self.step_sigma.tolist(),
            "units": {"K_g": f"deg/s per {self.raw_unit}", "w0": "deg/s"},
        }


def fit_gyro_multirate(sm: StepMeans) -> GyroMultirateFit:
    """xu2016 eq. 5-11 on one session's step means."""
    dG, dW, pairs = multirate_pairs(sm)
    if len(pairs) < 4:
        raise DesignError("E_UNDETERMINED",
                          f"gyro: {len(pairs)} complete +/- multirate pairs, at least 4 needed "
                          "to determine the 9 elements of K_g with a residual")
    _check_determined(sm, dW, "gyro", "multirate rotation")
    # eq. 6-8 for all three rows at once: dW (n,3) = dG (n,3) K^T
    ls = solve_lstsq(dG, dW)
    if ls.rank < 3 or ls.condition_number > MAX_CONDITION:
        raise DesignError("E_UNDETERMINED",
                          f"gyro: multirate design is singular (condition number "
                          f"{ls.condition_number:.3g}): the rotation axes do not span 3-D")
    K = ls.coef.T
    K_se = ls.stderr.T
    # A difference holds the noise of two steps: step-level variance is half the residual's.
    step_sigma = np.sqrt(ls.sigma2 / 2.0)
    stat = np.flatnonzero(sm.test == "stationary")
    if len(stat):
        G0 = sm.gyro[stat].mean(axis=0)
        n0, source = len(stat), "stationary"
    else:  # a linear sensor's +/- midpoint is its zero-rate output
        G0 = 0.5 * (sm.gyro[pairs[:, 0]] + sm.gyro[pairs[:, 1]]).mean(axis=0)
        n0, source = 2 * len(pairs), "pair_midpoints"
    w0 = -K @ G0  # eq. 10-11
    # var(w0_i) = step noise / n0  +  G0^T cov(K_i) G0   (independent steps)
    var_k = np.array([G0 @ (ls.cov_unscaled * ls.sigma2[i]) @ G0 for i in range(3)])
    w0_se = np.sqrt(step_sigma ** 2 / n0 + var_k)
    return GyroMultirateFit(
        K=K, w0=w0, K_stderr=K_se, w0_stderr=w0_se, step_sigma=step_sigma,
        residual_rms=np.sqrt((ls.residuals ** 2).mean(axis=0)),
        condition_number=ls.condition_number, n_pairs=len(pairs), n_stationary=len(stat),
        w0_source=source, raw_unit=sm.gyro_unit,
    )


# --------------------------------------------------------------------------- accel
@dataclass(frozen=True)
class AccelMultipositionFit:
    """K_a and f0 of xu2016 eq. 2 with their standard errors."""

    K: np.ndarray  # (3,3) g per raw unit
    f0: np.ndarray  # (3,) g
    K_stderr: np.ndarray
    f0_stderr: np.ndarray
    residual_rms: np.ndarray  # (3,) g
    condition_number: float
    n_steps: int
    raw_unit: str = "g"
    model: str = "accel"

    def compensate(self, A: np.ndarray) -> np.ndarray:
        return np.atleast_2d(A) @ self.K.T + self.f0

    def parameters(self) -> list[Param]:
        return (matrix_params(self.model, "k_a", self.K, self.K_stderr, f"g per {self.raw_unit}")
                + vector_params(self.model, _axis_names("f0"), self.f0, self.f0_stderr, "g"))

    def to_dict(self) -> dict[str, Any]:
        return {
            "K_a": self.K.tolist(), "f0": self.f0.tolist(),
            "stderr": {"K_a": self.K_stderr.tolist(), "f0": self.f0_stderr.tolist()},
            "condition_number": self.condition_number, "n_steps": self.n_steps,
            "units": {"K_a": f"g per {self.raw_unit}", "f0": "g"},
        }


def _static_steps(sm: StepMeans) -> StepMeans:
    return sm.of_test("multiposition")


def fit_accel_multiposition(sm: StepMeans) -> AccelMultipositionFit:
    """xu2016 eq. 12-16: F = K_a A + f0 over all multiposition steps."""
    st = _static_steps(sm)
    if len(st) < 5:
        raise DesignError("E_UNDETERMINED",
                          f"accel: {len(st)} multiposition steps, at least 5 needed for the "
                          "12 parameters of K_a and f0 with a residual")
    _check_determined(st, st.f_ref, "accel", "multiposition specific force")
    X = np.hstack([st.accel, np.ones((len(st), 1))])
    ls = solve_lstsq(X, st.f_ref)
    if ls.rank < 4 or ls.condition_number > MAX_CONDITION:
        raise DesignError("E_UNDETERMINED",
                          f"accel: multiposition design is singular (condition number "
                          f"{ls.condition_number:.3g}): orientations do not span 3-D")
    return AccelMultipositionFit(
        K=ls.coef[:3].T, f0=ls.coef[3], K_stderr=ls.stderr[:3].T, f0_stderr=ls.stderr[3],
        residual_rms=np.sqrt((ls.residuals ** 2).mean(axis=0)),
        condition_number=ls.condition_number, n_steps=len(st), raw_unit=sm.accel_unit,
    )


# --------------------------------------------------------------------------- traditional
@dataclass(frozen=True)
class TraditionalFit:
    """Inverse model raw = S x + b (x: deg/s or g); compensation x = S^-1 (raw - b)."""

    model: str  # "gyro_traditional" or "accel_traditional"
    S: np.ndarray  # (3,3) raw unit per physical unit
    b: np.ndarray  # (3,) raw unit
    S_stderr: np.ndarray
    b_stderr: np.ndarray
    condition_number: float
    n_steps: int
    raw_unit: str
    physical_unit: str

    def compensate(self, raw: np.ndarray) -> np.ndarray:
        """The traditional compensation needs the inverse of S (what xu2016 avoids)."""
        return np.linalg.solve(self.S, (np.atleast_2d(raw) - self.b).T).T

    def as_affine(self) -> tuple[np.ndarray, np.ndarray]:
        """Equivalent (K, x0) of the proposed form: K = S^-1, x0 = -S^-1 b."""
        K = np.linalg.inv(self.S)
        return K, -K @ self.b

    def parameters(self) -> list[Param]:
        prefix = "s_g" if self.model.startswith("gyro") else "s_a"
        bname = "b_g" if self.model.startswith("gyro") else "b_a"
        return (matrix_params(self.model, prefix, self.S, self.S_stderr,
                              f"{self.raw_unit} per {self.physical_unit}")
                + vector_params(self.model, _axis_names(bname), self.b, self.b_stderr, self.raw_unit))

    def to_dict(self) -> dict[str, Any]:
        return {"S": self.S.tolist(), "b": self.b.tolist(),
                "stderr": {"S": self.S_stderr.tolist(), "b": self.b_stderr.tolist()},
                "condition_number": self.condition_number, "n_steps": self.n_steps,
                "units": {"S": f"{self.raw_unit} per {self.physical_unit}", "b": self.raw_unit}}


def _fit_traditional(model, ref, raw, raw_unit, phys_unit) -> TraditionalFit:
    X = np.hstack([ref, np.ones((len(ref), 1))])
    ls = solve_lstsq(X, raw, reuse_design=True)  # [references, 1]: the protocol's
    if ls.rank < 4 or ls.condition_number > MAX_CONDITION:
        raise DesignError("E_UNDETERMINED", f"{model}: design is singular "
                          f"(condition number {ls.condition_number:.3g})")
    return TraditionalFit(model=model, S=ls.coef[:3].T, b=ls.coef[3], S_stderr=ls.stderr[:3].T,
                          b_stderr=ls.stderr[3], condition_number=ls.condition_number,
                          n_steps=len(ref), raw_unit=raw_unit, physical_unit=phys_unit)


def fit_gyro_traditional(sm: StepMeans) -> TraditionalFit:
    """G = S w + b over the same multirate and stationary steps as the proposed fit."""
    st = sm.of_test("multirate", "stationary")
    _check_determined(st, st.w_ref, "gyro_traditional", "multirate rotation")
    return _fit_traditional("gyro_traditional", st.w_ref, st.gyro, sm.gyro_unit, "deg/s")


def fit_accel_traditional(sm: StepMeans) -> TraditionalFit:
    """A = S f + b over the same multiposition steps as the proposed fit."""
    st = _static_steps(sm)
    _check_determined(st, st.f_ref, "accel_traditional", "multiposition specific force")
    return _fit_traditional("accel_traditional", st.f_ref, st.accel, sm.accel_unit, "g")


# --------------------------------------------------------------------------- Table 3
def input_axis_of(w_ref: np.ndarray) -> np.ndarray:
    """Body axis a rotation step excites most ('x', 'y', 'z')."""
    return np.array(list(AXES))[np.argmax(np.abs(w_ref), axis=1)]


COMPENSATION_COLUMNS = ["input_axis", "output_axis", "method", "err_min", "err_max",
                        "unit_of_measure", "source", "n_steps"]


def compensation_errors(sm: StepMeans, proposed: GyroMultirateFit,
                        traditional: TraditionalFit | None = None,
                        tests: tuple[str, ...] = ("verification",)) -> pd.DataFrame:
    """xu2016 Table 3: range (min, max) of output error per input axis and output axis,
    uncompensated / proposed / traditional, on rotation steps of the given tests.

    Uncompensated errors are only meaningful when the raw unit is deg/s (else NaN)."""
    table = compensation_error_table(sm, proposed, traditional, tests)
    if len(table) == 0:
        return pd.DataFrame(columns=COMPENSATION_COLUMNS)
    return table.to_frame()


def compensation_error_table(sm: StepMeans, proposed: GyroMultirateFit,
                             traditional: TraditionalFit | None = None,
                             tests: tuple[str, ...] = ("verification",)) -> ColumnTable:
    """The rows of :func:`compensation_errors` as numpy columns (no DataFrame)."""
    rows = _rotation_groups(tests, np.isin(sm.test, tests).tobytes(),
                            sm.rate_dps.astype(float).tobytes(),
                            np.ascontiguousarray(sm.w_ref, dtype=float).tobytes())
    if rows is None:
        return ColumnTable({c: np.empty(0) for c in COMPENSATION_COLUMNS}, 0)
    idx, starts, present, n_steps = rows  # steps ordered by input axis, group starts
    G, w_ref = sm.gyro[idx], sm.w_ref[idx]
    outputs = [G if sm.gyro_unit == "deg/s" else np.full_like(G, np.nan),
               proposed.compensate(G)]
    methods = ["uncompensated", "proposed"]  # row order of xu2016 Table 3
    if traditional is not None:
        outputs.append(traditional.compensate(G))
        methods.append("traditional")
    err = np.stack(outputs) - w_ref  # (methods, steps, 3)
    lo = np.minimum.reduceat(err, starts, axis=1)  # (methods, input axes, 3)
    hi = np.maximum.reduceat(err, starts, axis=1)
    n_rows = len(methods) * len(present) * 3
    return ColumnTable({
        "input_axis": CodedStrings(present, np.tile(
            np.repeat(np.arange(len(present)), 3), len(methods))),
        "output_axis": CodedStrings(np.array(list(AXES)), np.tile(
            np.arange(3), len(methods) * len(present))),
        "method": CodedStrings(np.array(methods), np.repeat(
            np.arange(len(methods)), len(present) * 3)),
        "err_min": lo.ravel(), "err_max": hi.ravel(),
        "unit_of_measure": "deg/s", "source": "+".join(tests),
        "n_steps": np.tile(np.repeat(n_steps, 3), len(methods)),
    }, n_rows)


@lru_cache(maxsize=64)
def _rotation_groups(tests: tuple[str, ...], in_tests: bytes, rate_dps: bytes, w_ref: bytes):
    """Rotation steps of the given tests grouped by input axis, for a protocol (the same for
    every session of a fleet): (step indices ordered by input axis, start of each group,
    the input axes present, steps per group), or None when there is no such step."""
    mask = np.frombuffer(in_tests, dtype=bool) & (np.frombuffer(rate_dps, dtype=float) != 0)
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return None
    axis = np.argmax(np.abs(np.frombuffer(w_ref, dtype=float).reshape(-1, 3)[idx]), axis=1)
    order = np.argsort(axis, kind="stable")  # within a group, steps keep their order
    present, starts, n_steps = np.unique(axis[order], return_index=True, return_counts=True)
    out = (idx[order], starts, np.array(list(AXES))[present], n_steps.astype(np.int64))
    for a in out:
        a.setflags(write=False)
    return out
