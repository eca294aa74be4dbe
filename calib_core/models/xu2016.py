"""The calibration method of Xu, Wang, Su, Zhu (2016), with standard errors.

- Gyro, eq. 1 ``w = K_g G + w0`` (G raw output, w rate in deg/s), section 2.3.1:
  eq. 3-4 the model at +rate and -rate about one axis; eq. 5 their difference
  ``dw = K_g dG`` has no bias; eq. 6-8 K_g from all pairs by least squares; eq. 9-11
  ``w0 = -K_g G(0)``, G(0) the mean output of the stationary steps.
- Accelerometer, eq. 2 ``f = K_a A + f0``, section 2.3.2: eq. 12-13 the model of one
  position as linear in the 12 parameters; eq. 14-16 all multiposition steps, least squares.
- The "traditional" inverse model, ``G = S w + b`` so ``w = S^-1 (G - b)``, fitted on the
  same steps, for the comparison of the paper's Table 3.

The paper writes each least squares as one stacked system (eq. 7, 15: a block-diagonal
design with one block per row of K). The blocks share their design, so each fit below solves
the three rows at once: ``dW = dG K_g^T`` (eq. 6) and ``F = [A 1] [K_a f0]^T`` (eq. 14), the
same estimates. Every fit works on a leading repetition axis: ``fit_*`` of one session is the
``fit_*_stack`` of a list of one, and the stack of a unit's repetitions (same step layout)
runs each operation once for all of them.

Standard errors come from the residuals and the design. The step-level noise that the +/-
differences reveal (white noise averaged over the step plus step-to-step bias instability) is
also the noise of each stationary step, which is what makes an honest standard error of w0
possible from only three stationary steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from calib_core.errors import DesignError
from calib_core.linalg import solve_lstsq_stack
from calib_core.models.display import MATRIX, ModelDisplay, matrix_symbols, register_display, vector_symbols
from calib_core.results import Param, ParamBlock, matrix_names, params_of_blocks
from calib_core.steps import StepMeans, stack_field
from calib_core.tables import CodedStrings, ColumnTable

AXES = "xyz"
MAX_CONDITION = 1e6  # beyond this the design cannot separate the parameters


def _axis_names(prefix: str) -> tuple[str, ...]:
    return tuple(f"{prefix}_{a}" for a in AXES)


# parameter names (the paper's): K_g, w0 (eq. 1), K_a, f0 (eq. 2), the traditional S, b
K_G_NAMES, W0_NAMES = matrix_names("k_g"), _axis_names("w0")
K_A_NAMES, F0_NAMES = matrix_names("k_a"), _axis_names("f0")
S_G_NAMES, B_G_NAMES = matrix_names("s_g"), _axis_names("b_g")
S_A_NAMES, B_A_NAMES = matrix_names("s_a"), _axis_names("b_a")


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
    pairs = _pair_indices(sm)
    dG = sm.gyro[pairs[:, 0]] - sm.gyro[pairs[:, 1]]
    dW = sm.w_ref[pairs[:, 0]] - sm.w_ref[pairs[:, 1]]
    return dG, dW, pairs


def _pair_indices(sm: StepMeans) -> np.ndarray:
    """(n,2) index pairs (+rate step, -rate step) of the multirate steps: same rotation axis,
    same |rate|, opposite signs; matched in step order, sorted."""
    idx = np.flatnonzero((sm.test == "multirate") & (sm.rate_dps != 0))
    rate = sm.rate_dps[idx].astype(float)
    # a step's key: |rate| and rotation axis (w_ref / rate: the same for + and -), rounded
    key = np.round(np.column_stack([np.abs(rate), sm.w_ref[idx] / rate[:, None]]), 6) + 0.0
    sides: dict[tuple, tuple[list[int], list[int]]] = {}
    for i, k, minus in zip(idx.tolist(), map(tuple, key.tolist()), (rate < 0).tolist()):
        sides.setdefault(k, ([], []))[minus].append(i)
    pairs = sorted(p for plus, minus in sides.values() for p in zip(plus, minus))
    return np.array(pairs, dtype=int).reshape(-1, 2)


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
        return params_of_blocks(self.param_blocks())

    def param_blocks(self) -> list[ParamBlock]:
        return [
            (self.model, K_G_NAMES, self.K, self.K_stderr, f"deg/s per {self.raw_unit}"),
            (self.model, W0_NAMES, self.w0, self.w0_stderr, "deg/s"),
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "K_g": self.K.tolist(),
            "w0": self.w0.tolist(),
            "stderr": {"K_g": self.K_stderr.tolist(), "w0": self.w0_stderr.tolist()},
            "condition_number": self.condition_number,
            "n_pairs": self.n_pairs,
            "n_stationary": self.n_stationary,
            "w0_source": self.w0_source,
            "step_sigma_dps": self.step_sigma.tolist(),
            "units": {"K_g": f"deg/s per {self.raw_unit}", "w0": "deg/s"},
        }


def fit_gyro_multirate(sm: StepMeans) -> GyroMultirateFit:
    """xu2016 eq. 3-11 on one session's step means (see :func:`fit_gyro_multirate_stack`)."""
    return fit_gyro_multirate_stack([sm])[0]


def fit_gyro_multirate_stack(sms: Sequence[StepMeans]) -> list[GyroMultirateFit]:
    """K_g and w0 of each session of one step layout (the repetitions of a unit: same steps,
    tests and references); item r is ``fit_gyro_multirate(sms[r])``, bit for bit. Raises the
    DesignError of the first session that has one."""
    sm = sms[0]  # the layout every session shares
    pairs = _pair_indices(sm)
    if len(pairs) < 4:
        raise DesignError(
            "E_UNDETERMINED",
            f"gyro: {len(pairs)} complete +/- multirate pairs, at least 4 needed "
            "to determine the 9 elements of K_g with a residual",
        )
    plus, minus = pairs[:, 0], pairs[:, 1]
    G = stack_field(sms, "gyro")  # (R, n, 3) raw outputs, one row per step

    # eq. 3-5: w+(i) - w-(i) = K_g (G+(i) - G-(i)), the bias w0 cancels
    dW = sm.w_ref[plus] - sm.w_ref[minus]  # (pairs, 3): the rows of dOmega
    dG = G[:, plus] - G[:, minus]  # (R, pairs, 3): the rows of dG
    _check_determined(sm, dW, "gyro", "multirate rotation")

    # eq. 6-8: K_G = (dG^T dG)^-1 dG^T dOmega over all pairs, the three rows of K_g at once
    # (dW = dG K_g^T); by SVD, never forming dG^T dG
    ls = solve_lstsq_stack(dG, dW)
    singular = (ls.rank < 3) | (ls.condition_number > MAX_CONDITION)
    if singular.any():
        cond = float(ls.condition_number[np.argmax(singular)])
        raise DesignError(
            "E_UNDETERMINED",
            f"gyro: multirate design is singular (condition number "
            f"{cond:.3g}): the rotation axes do not span 3-D",
        )
    K = np.swapaxes(ls.coef, 1, 2)
    K_se = np.swapaxes(ls.stderr, 1, 2)
    # a difference holds the noise of two steps: the step-level variance is half the residual's
    step_sigma = np.sqrt(ls.sigma2 / 2.0)

    # eq. 9-11: w0 = -K_g G(0), G(0) the mean output of the stationary steps
    stat = np.flatnonzero(sm.test == "stationary")
    if len(stat):
        G0 = G[:, stat].mean(axis=1)
        n0, source = len(stat), "stationary"
    else:  # without stationary steps: a linear sensor's +/- midpoint is its zero-rate output
        G0 = 0.5 * (G[:, plus] + G[:, minus]).mean(axis=1)
        n0, source = 2 * len(pairs), "pair_midpoints"
    w0 = (-K @ G0[:, :, None])[:, :, 0]
    # var(w0_i) = step noise / n0  +  G0^T cov(K_i) G0   (independent steps)
    # (R, 3): G0^T (cov * sigma2_i) G0 of each session and row, as stacked vector-matrix
    # and vector-vector products (the same as one at a time)
    cov_rows = ls.cov_unscaled[:, None] * ls.sigma2[:, :, None, None]  # (R, 3, 3, 3)
    var_k = (G0[:, None, None, :] @ cov_rows @ G0[:, None, :, None])[..., 0, 0]
    w0_se = np.sqrt(step_sigma**2 / n0 + var_k)
    residual_rms = np.sqrt((ls.residuals**2).mean(axis=1))
    return [
        GyroMultirateFit(
            K=K[r],
            w0=w0[r],
            K_stderr=K_se[r],
            w0_stderr=w0_se[r],
            step_sigma=step_sigma[r],
            residual_rms=residual_rms[r],
            condition_number=float(ls.condition_number[r]),
            n_pairs=len(pairs),
            n_stationary=len(stat),
            w0_source=source,
            raw_unit=sm.gyro_unit,
        )
        for r in range(len(sms))
    ]


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
        return params_of_blocks(self.param_blocks())

    def param_blocks(self) -> list[ParamBlock]:
        return [
            (self.model, K_A_NAMES, self.K, self.K_stderr, f"g per {self.raw_unit}"),
            (self.model, F0_NAMES, self.f0, self.f0_stderr, "g"),
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "K_a": self.K.tolist(),
            "f0": self.f0.tolist(),
            "stderr": {"K_a": self.K_stderr.tolist(), "f0": self.f0_stderr.tolist()},
            "condition_number": self.condition_number,
            "n_steps": self.n_steps,
            "units": {"K_a": f"g per {self.raw_unit}", "f0": "g"},
        }


def fit_accel_multiposition(sm: StepMeans) -> AccelMultipositionFit:
    """xu2016 eq. 12-16 on one session's step means (see
    :func:`fit_accel_multiposition_stack`)."""
    return fit_accel_multiposition_stack([sm])[0]


def fit_accel_multiposition_stack(sms: Sequence[StepMeans]) -> list[AccelMultipositionFit]:
    """K_a and f0 of each session of one step layout, as :func:`fit_gyro_multirate_stack`."""
    sm = sms[0]
    rows = sm.rows_of_test("multiposition")
    n = len(rows)
    if n < 5:
        raise DesignError(
            "E_UNDETERMINED",
            f"accel: {n} multiposition steps, at least 5 needed for the "
            "12 parameters of K_a and f0 with a residual",
        )
    # eq. 12-13: at one position, f = K_a A + f0 is linear in (K_a, f0): f_i = [A 1] . row i
    F = sm.f_ref[rows]  # (n, 3) the known specific force of each position
    _check_determined(sm, F, "accel", "multiposition specific force")
    A1 = np.concatenate(
        [stack_field(sms, "accel")[:, rows], np.ones((len(sms), n, 1))], axis=2
    )  # (R, n, 4): [A 1]

    # eq. 14-16: K_A = (A^T A)^-1 A^T F over all positions, the three rows at once
    ls = solve_lstsq_stack(A1, F)
    singular = (ls.rank < 4) | (ls.condition_number > MAX_CONDITION)
    if singular.any():
        cond = float(ls.condition_number[np.argmax(singular)])
        raise DesignError(
            "E_UNDETERMINED",
            f"accel: multiposition design is singular (condition number "
            f"{cond:.3g}): orientations do not span 3-D",
        )
    K = np.swapaxes(ls.coef[:, :3], 1, 2)
    K_se = np.swapaxes(ls.stderr[:, :3], 1, 2)
    residual_rms = np.sqrt((ls.residuals**2).mean(axis=1))
    return [
        AccelMultipositionFit(
            K=K[r],
            f0=ls.coef[r, 3],
            K_stderr=K_se[r],
            f0_stderr=ls.stderr[r, 3],
            residual_rms=residual_rms[r],
            condition_number=float(ls.condition_number[r]),
            n_steps=n,
            raw_unit=sm.accel_unit,
        )
        for r in range(len(sms))
    ]


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
        return params_of_blocks(self.param_blocks())

    def param_blocks(self) -> list[ParamBlock]:
        s_names, b_names = (S_G_NAMES, B_G_NAMES) if self.model.startswith("gyro") else (S_A_NAMES, B_A_NAMES)
        return [
            (self.model, s_names, self.S, self.S_stderr, f"{self.raw_unit} per {self.physical_unit}"),
            (self.model, b_names, self.b, self.b_stderr, self.raw_unit),
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "S": self.S.tolist(),
            "b": self.b.tolist(),
            "stderr": {"S": self.S_stderr.tolist(), "b": self.b_stderr.tolist()},
            "condition_number": self.condition_number,
            "n_steps": self.n_steps,
            "units": {"S": f"{self.raw_unit} per {self.physical_unit}", "b": self.raw_unit},
        }


def _fit_traditional(model, ref, raw, raw_unit, phys_unit) -> list[TraditionalFit]:
    """raw (R, n, 3) of R sessions on the references ref (n, 3) they share."""
    X = np.hstack([ref, np.ones((len(ref), 1))])
    ls = solve_lstsq_stack(X, raw)  # one design [references, 1], shared by the sessions
    rank, cond = int(ls.rank[0]), float(ls.condition_number[0])
    if rank < 4 or cond > MAX_CONDITION:
        raise DesignError("E_UNDETERMINED", f"{model}: design is singular (condition number {cond:.3g})")
    S = np.swapaxes(ls.coef[:, :3], 1, 2)
    S_se = np.swapaxes(ls.stderr[:, :3], 1, 2)
    return [
        TraditionalFit(
            model=model,
            S=S[r],
            b=ls.coef[r, 3],
            S_stderr=S_se[r],
            b_stderr=ls.stderr[r, 3],
            condition_number=cond,
            n_steps=len(ref),
            raw_unit=raw_unit,
            physical_unit=phys_unit,
        )
        for r in range(len(raw))
    ]


def fit_gyro_traditional(sm: StepMeans) -> TraditionalFit:
    """G = S w + b over the same multirate and stationary steps as the proposed fit."""
    return fit_gyro_traditional_stack([sm])[0]


def fit_gyro_traditional_stack(sms: Sequence[StepMeans]) -> list[TraditionalFit]:
    """:func:`fit_gyro_traditional` of sessions that share one step layout, together."""
    sm = sms[0]
    rows = sm.rows_of_test("multirate", "stationary")
    w_ref = sm.w_ref[rows]
    _check_determined(sm, w_ref, "gyro_traditional", "multirate rotation")
    return _fit_traditional(
        "gyro_traditional", w_ref, stack_field(sms, "gyro")[:, rows], sm.gyro_unit, "deg/s"
    )


def fit_accel_traditional(sm: StepMeans) -> TraditionalFit:
    """A = S f + b over the same multiposition steps as the proposed fit."""
    return fit_accel_traditional_stack([sm])[0]


def fit_accel_traditional_stack(sms: Sequence[StepMeans]) -> list[TraditionalFit]:
    """:func:`fit_accel_traditional` of sessions that share one step layout, together."""
    sm = sms[0]
    rows = sm.rows_of_test("multiposition")
    f_ref = sm.f_ref[rows]
    _check_determined(sm, f_ref, "accel_traditional", "multiposition specific force")
    return _fit_traditional(
        "accel_traditional", f_ref, stack_field(sms, "accel")[:, rows], sm.accel_unit, "g"
    )


# --------------------------------------------------------------------------- Table 3
COMPENSATION_COLUMNS = [
    "input_axis",
    "output_axis",
    "method",
    "err_min",
    "err_max",
    "unit_of_measure",
    "source",
    "n_steps",
]


def compensation_errors(
    sm: StepMeans,
    proposed: GyroMultirateFit,
    traditional: TraditionalFit | None = None,
    tests: tuple[str, ...] = ("verification",),
) -> pd.DataFrame:
    """xu2016 Table 3: range (min, max) of output error per input axis and output axis,
    uncompensated / proposed / traditional, on rotation steps of the given tests.

    Uncompensated errors are only meaningful when the raw unit is deg/s (else NaN)."""
    table = compensation_error_table(sm, proposed, traditional, tests)
    if len(table) == 0:
        return pd.DataFrame(columns=COMPENSATION_COLUMNS)
    return table.to_frame()


def compensation_error_table(
    sm: StepMeans,
    proposed: GyroMultirateFit,
    traditional: TraditionalFit | None = None,
    tests: tuple[str, ...] = ("verification",),
) -> ColumnTable:
    """The rows of :func:`compensation_errors` as numpy columns (no DataFrame)."""
    return compensation_error_tables([sm], [proposed], [traditional], tests)[0]


def compensation_error_tables(
    sms: Sequence[StepMeans],
    proposed: Sequence[GyroMultirateFit],
    traditional: Sequence[TraditionalFit | None],
    tests: tuple[str, ...] = ("verification",),
) -> list[ColumnTable]:
    """:func:`compensation_error_table` of sessions that share a step layout, each with its
    own fits, computed together (table r is ``compensation_error_table(sms[r], ...[r])``).
    The columns that come from the layout alone are built once and shared, read-only."""
    if len({t is None for t in traditional}) > 1:  # not one set of methods: each alone
        return [compensation_error_table(sm, p, t, tests) for sm, p, t in zip(sms, proposed, traditional)]
    sm = sms[0]
    rows = _rotation_groups(sm, tests)
    if rows is None:
        return [ColumnTable({c: np.empty(0) for c in COMPENSATION_COLUMNS}, 0) for _ in sms]
    idx, starts, present, n_steps = rows  # steps ordered by input axis, group starts
    G, w_ref = stack_field(sms, "gyro")[:, idx], sm.w_ref[idx]  # (R, steps, 3)
    # GyroMultirateFit.compensate and TraditionalFit.compensate of every session at once
    w0 = np.stack([p.w0 for p in proposed])[:, None]
    outputs = [
        G if sm.gyro_unit == "deg/s" else np.full_like(G, np.nan),
        G @ np.stack([p.K.T for p in proposed]) + w0,
    ]
    methods = ["uncompensated", "proposed"]  # row order of xu2016 Table 3
    if traditional[0] is not None:
        b = np.stack([t.b for t in traditional])[:, None]
        outputs.append(
            np.swapaxes(np.linalg.solve(np.stack([t.S for t in traditional]), np.swapaxes(G - b, 1, 2)), 1, 2)
        )
        methods.append("traditional")
    err = np.stack(outputs, axis=1) - w_ref  # (R, methods, steps, 3)
    lo = np.minimum.reduceat(err, starts, axis=2)  # (R, methods, input axes, 3)
    hi = np.maximum.reduceat(err, starts, axis=2)
    n_rows = len(methods) * len(present) * 3
    layout = {
        "input_axis": CodedStrings(present, np.tile(np.repeat(np.arange(len(present)), 3), len(methods))),
        "output_axis": CodedStrings(np.array(list(AXES)), np.tile(np.arange(3), len(methods) * len(present))),
        "method": CodedStrings(np.array(methods), np.repeat(np.arange(len(methods)), len(present) * 3)),
        "n_steps": np.tile(np.repeat(n_steps, 3), len(methods)),
    }
    if len(sms) > 1:
        for v in layout.values():
            (v.codes if isinstance(v, CodedStrings) else v).setflags(write=False)
    return [
        ColumnTable(
            {
                "input_axis": layout["input_axis"],
                "output_axis": layout["output_axis"],
                "method": layout["method"],
                "err_min": lo[r].ravel(),
                "err_max": hi[r].ravel(),
                "unit_of_measure": "deg/s",
                "source": "+".join(tests),
                "n_steps": layout["n_steps"],
            },
            n_rows,
        )
        for r in range(len(sms))
    ]


def _rotation_groups(sm: StepMeans, tests: tuple[str, ...]):
    """Rotation steps of the given tests grouped by input axis (the body axis the step
    excites most): (step indices ordered by input axis, start of each group, the input axes
    present, steps per group), or None when there is no such step."""
    idx = np.flatnonzero(np.isin(sm.test, tests) & (sm.rate_dps != 0))
    if len(idx) == 0:
        return None
    axis = np.argmax(np.abs(sm.w_ref[idx]), axis=1)
    order = np.argsort(axis, kind="stable")  # within a group, steps keep their order
    present, starts, n_steps = np.unique(axis[order], return_index=True, return_counts=True)
    return idx[order], starts, np.array(list(AXES))[present], n_steps.astype(np.int64)


# How the reports show the four models of this module (calib_core.models.display).
register_display(
    ModelDisplay(
        "gyro",
        "Table 1 · gyroscope output model (multirate)",
        tuple(f"k_g{m}" for m in MATRIX) + ("w0_x", "w0_y", "w0_z"),
        rank=0,
        key_title="Gyroscope K<sub>g</sub>, ω<sub>0</sub> (ω = K<sub>g</sub> G + ω<sub>0</sub>: "
        "turntable multirate or field poses)",
        symbols={**matrix_symbols("k_g"), **vector_symbols("w0_", "ω", "0")},
    )
)
register_display(
    ModelDisplay(
        "accel",
        "Table 2 · accelerometer output model (multiposition)",
        tuple(f"k_a{m}" for m in MATRIX) + ("f0_x", "f0_y", "f0_z"),
        rank=1,
        key_title="Accelerometer K<sub>a</sub>, f<sub>0</sub> (f = K<sub>a</sub> A + f<sub>0</sub>: "
        "turntable multiposition or field poses)",
        symbols={**matrix_symbols("k_a"), **vector_symbols("f0_", "f", "0")},
    )
)
register_display(
    ModelDisplay(
        "gyro_traditional",
        "Gyroscope, traditional inverse model",
        tuple(f"s_g{m}" for m in MATRIX) + tuple(f"b_g_{a}" for a in "xyz"),
        rank=10,
        symbols=matrix_symbols("s_g"),
    )
)
register_display(
    ModelDisplay(
        "accel_traditional",
        "Accelerometer, traditional inverse model",
        tuple(f"s_a{m}" for m in MATRIX) + tuple(f"b_a_{a}" for a in "xyz"),
        rank=11,
        symbols=matrix_symbols("s_a"),
    )
)
