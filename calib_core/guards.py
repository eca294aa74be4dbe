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


# --- steps whose content contradicts the unit's other repetitions -----------------------------
# A step mean damaged into the sensor's range (bytes that still decode, no page checksum) is
# invisible to the session's own fit: the structured model error the fit leaves out (lever
# arm, nonlinearity) reaches a robust z of ~3,500 on clean high-rate steps. The same step in
# the unit's other repetitions carries the same structured error, so the step is compared with
# the median of its repetitions; what differs between clean repetitions (turn-on bias, a
# scale or drift that moved) is taken out per repetition by a robust affine fit on the
# references and the step's time, and what is left is noise, scaled per group of steps of
# one test and rate (a scale pooled over the group's steps and repetitions).
CONSISTENCY_Z_LIMIT = 15.0  # robust z beyond which a step is left out: twice the largest of clean units (docs/hardening.md)
CONSISTENCY_MIN_GROUP = 30  # deviations needed for a group's own scale (else its test's, then all)
CHANNEL_NAMES = ("gx", "gy", "gz", "ax", "ay", "az")
_MAD_TO_SD = 1.4826


@dataclass(frozen=True)
class StepDisagreement:
    """Step ``step`` of repetition ``index`` (position in the list given) disagrees with the
    same step in the unit's other repetitions: channel, robust z and the difference in the
    channel's raw unit (after the repetition's own offset is taken out)."""

    index: int
    step: int
    channel: str
    z: float
    deviation: float
    ambiguous: bool  # two repetitions: which one is wrong cannot be told; both are named


def _step_key(sm: StepMeans, i: int) -> tuple:
    return (
        int(sm.step[i]),
        str(sm.test[i]),
        str(sm.up_axis[i]),
        float(sm.rate_dps[i]),
        sm.w_ref[i].tobytes(),
        sm.f_ref[i].tobytes(),
    )


def _robust_affine_residual(d: np.ndarray, X: np.ndarray, iterations: int = 8) -> np.ndarray:
    """Residual of ``d`` (m,) on ``X`` (m, p) by iteratively reweighted least squares with
    Tukey's bisquare (c = 4.685), starting from the median: a few damaged steps do not move it."""
    e = d - np.median(d)
    w = np.ones(len(d))
    for _ in range(iterations):
        s = _MAD_TO_SD * np.median(np.abs(e - np.median(e)))
        if not s > 0:
            break
        u = e / (4.685 * s)
        w = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        if np.count_nonzero(w) <= X.shape[1]:
            break
        sw = np.sqrt(w)
        beta = np.linalg.lstsq(X * sw[:, None], d * sw, rcond=None)[0]
        e = d - X @ beta
    return e


def _group_scales(
    dev: np.ndarray, groups: np.ndarray, tests: np.ndarray, floor: float
) -> np.ndarray:
    """(S,) robust scale of the deviations ``dev`` (R, S) per step: pooled over the steps of
    the step's group (test and |rate|) and every repetition (NaN where not counted); a group
    with too few deviations takes its test's scale, a test with too few the channel's."""

    def scale(values: np.ndarray) -> float | None:
        v = values[np.isfinite(values)]
        if len(v) < CONSISTENCY_MIN_GROUP:
            return None
        return _MAD_TO_SD * float(np.median(np.abs(v)))

    everything = scale(dev.ravel())
    out = np.full(dev.shape[1], np.nan)
    for g in np.unique(groups):
        cols = groups == g
        s = scale(dev[:, cols].ravel())
        if s is None:
            s = scale(dev[:, tests == tests[cols][0]].ravel())
        if s is None:
            s = everything
        out[cols] = np.nan if s is None else max(s, floor)
    return out


def inconsistent_steps(sms: list[StepMeans], z_limit: float = CONSISTENCY_Z_LIMIT) -> list[StepDisagreement]:
    """Steps of the repetitions ``sms`` (one unit) whose mean disagrees with the same step
    (same id, test, pose, rate and references) in the other repetitions by more than
    ``z_limit`` robust standard deviations, on any channel; at most one entry per
    repetition and step (its worst channel).

    With three or more repetitions the reference of a step is the median over repetitions,
    which one damaged repetition cannot move. With two, each is the other's reference: a
    step beyond the limit is named in both, ``ambiguous``. One repetition: nothing to compare
    with (an empty list)."""
    n_rep = len(sms)
    if n_rep < 2:
        return []
    columns: dict[tuple, int] = {}
    where: list[tuple[np.ndarray, np.ndarray]] = []
    for sm in sms:
        cols = np.array([columns.setdefault(_step_key(sm, i), len(columns)) for i in range(len(sm))], np.intp)
        where.append((np.arange(len(sm)), cols))
    n_col = len(columns)
    keys = list(columns)
    step_id = np.array([k[0] for k in keys])
    test = np.array([k[1] for k in keys])
    rate = np.array([abs(k[3]) for k in keys])
    group = np.array([f"{t}|{r:g}" for t, r in zip(test, rate)])
    w_ref = np.array([np.frombuffer(k[4]) for k in keys])
    f_ref = np.array([np.frombuffer(k[5]) for k in keys])
    values = np.full((n_rep, n_col, 6), np.nan)
    t_mid = np.full((n_rep, n_col), np.nan)
    for r, (sm, (rows, cols)) in enumerate(zip(sms, where)):
        values[r, cols, :3] = sm.gyro[rows]
        values[r, cols, 3:] = sm.accel[rows]
        t_mid[r, cols] = sm.t_mid[rows]
    present = np.isfinite(values[..., 0])
    shared = present.sum(axis=0) >= 2  # a step seen in one repetition has nothing to compare
    full_scale = np.concatenate([np.asarray(sms[0].gyro_range_dps, float), np.asarray(sms[0].accel_range_g, float)])
    worst: dict[tuple[int, int], StepDisagreement] = {}
    median = np.full((n_col, 6), np.nan)  # over the repetitions that have the step
    median[shared] = np.nanmedian(values[:, shared], axis=0)
    for c in range(6):
        ref = w_ref if c < 3 else f_ref
        dev = np.full((n_rep, n_col), np.nan)
        for r in range(1 if n_rep == 2 else n_rep):
            ok = present[r] & shared
            d = values[r, ok, c] - median[ok, c]
            if np.count_nonzero(ok) < 8:
                continue
            t = t_mid[r, ok]
            t = (t - np.nanmean(t)) / (np.nanstd(t) or 1.0)
            X = np.column_stack([np.ones(len(d)), ref[ok], np.nan_to_num(t), np.nan_to_num(t) ** 2])
            dev[r, ok] = _robust_affine_residual(d, X)
        if n_rep == 2:  # each the other's reference: both deviations are +/- the difference
            dev[1] = -dev[0]
        # the scale leaves out the median repetition of each step (its deviation from itself
        # is zero before the affine fit: counting it would shrink the scale by a third with
        # three repetitions); the floor, a millionth of full scale, gives noise-free data one
        # (two repetitions: only the first's, the second's are the same numbers)
        at_median = values[..., c] == median[None, :, c]
        counted = np.where(at_median, np.nan, dev)
        if n_rep == 2:
            counted[1] = np.nan
        scale = _group_scales(counted, group, test, 1e-6 * float(full_scale[c]))
        z = dev / scale[None, :]
        for r, col in zip(*np.nonzero(np.abs(np.nan_to_num(z)) > z_limit)):
            found = StepDisagreement(
                int(r), int(step_id[col]), CHANNEL_NAMES[c], float(z[r, col]), float(dev[r, col]), n_rep == 2
            )
            prev = worst.get((int(r), int(col)))
            if prev is None or abs(found.z) > abs(prev.z):
                worst[(int(r), int(col))] = found
    return sorted(worst.values(), key=lambda s: (s.index, s.step))


# --- NumPy floating-point errors: recorded and named, not printed -------------------------------
class NumericEvents:
    """Floating-point errors NumPy meets inside a ``with`` block (overflow, invalid value,
    division by zero), counted instead of printed as ``RuntimeWarning``s, so that the caller
    can name them (``W_NUMERIC``, with the session) where they happen. ``np.errstate`` is a
    context variable: each thread (a Prefect task) records its own; code that deliberately
    ignores an error (``np.errstate(invalid="ignore")`` around a NaN comparison) still does."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self._state = np.errstate(over="call", invalid="call", divide="call", call=self._record)

    def _record(self, kind: str, flag: int) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1

    def __enter__(self) -> NumericEvents:
        self._state.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._state.__exit__(*exc)

    def __bool__(self) -> bool:
        return bool(self.counts)

    def __str__(self) -> str:
        """e.g. ``overflow (2 operations), invalid value (1 operation)``."""
        return ", ".join(
            f"{kind} ({n} operation{'s' if n != 1 else ''})" for kind, n in sorted(self.counts.items())
        )
