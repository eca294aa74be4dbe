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

from calib_core.linalg import solve_normal_stack
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


def surely_plausible(
    model: str, K: np.ndarray, x0: np.ndarray, raw_unit: str, full_scale: np.ndarray
) -> np.ndarray:
    """(R,) True for the sessions r of a stack (K (R, 3, 3), x0 (R, 3), one raw unit, each
    session's full scale (R, 3)) in which :func:`check_affine` certainly finds nothing: its comparisons on
    the whole stack at once. False leaves the session to :func:`check_affine` (a NaN, in a
    parameter or the full scale, included), so the checks' outcome is theirs."""
    ok = np.isfinite(K).all(axis=(1, 2)) & np.isfinite(x0).all(axis=1)
    if raw_unit == PHYSICAL_UNITS[model]:
        diag = np.diagonal(K, axis1=1, axis2=2)
        ok &= ((SCALE_LIMITS[0] <= diag) & (diag <= SCALE_LIMITS[1])).all(axis=1)
        ok &= (np.abs(np.where(np.eye(3, dtype=bool), 0.0, K)) <= CROSS_AXIS_LIMIT).all(axis=(1, 2))
    return ok & (np.abs(x0) <= full_scale).all(axis=1)


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


# --- field (hand-held) calibrations ------------------------------------------------------------
# A field fit on real MPU-6050 data ends at 0.12 mg |f| RMS and 0.11 deg gravity direction RMS
# (docs/real-data.md); a fit that ends 400x worse, or a gyro bias beyond any MEMS full scale, is
# wrong options (g_local, a scale, a column mapping), not a sensor.
FIELD_NORM_RMS_LIMIT_MG = 50.0
FIELD_ANGLE_RMS_LIMIT_DEG = 10.0
FIELD_GYRO_BIAS_LIMIT_DPS = 2000.0  # the largest MEMS gyro full scale is 2000-4000 deg/s
FIELD_ACCEL_BIAS_LIMIT_G = 32.0


def check_field_fit(
    norm_rms_mg: float, angle_rms_deg: float, K_g: np.ndarray, w0: np.ndarray, K_a: np.ndarray, f0: np.ndarray
) -> list[Implausible]:
    """Checks on a field calibration (affine form: deg/s and g): every value finite, the
    static |f| and gravity-direction RMS after the fit within the limits above, the biases
    within a sensor's reach."""
    out: list[Implausible] = []
    for model, name, arr in (
        ("gyro", "K", K_g),
        ("gyro", "w0", w0),
        ("accel", "K", K_a),
        ("accel", "f0", f0),
    ):
        if not np.isfinite(np.asarray(arr, float)).all():
            out.append(Implausible(model, name, float("nan"), "finite values"))
    if out:
        return out
    if not (np.isfinite(norm_rms_mg) and norm_rms_mg <= FIELD_NORM_RMS_LIMIT_MG):
        out.append(
            Implausible("field_fit", "norm_rms_mg", float(norm_rms_mg), f"{FIELD_NORM_RMS_LIMIT_MG:g} mg")
        )
    if np.isfinite(angle_rms_deg) and angle_rms_deg > FIELD_ANGLE_RMS_LIMIT_DEG:
        out.append(
            Implausible(
                "field_fit", "angle_rms_deg", float(angle_rms_deg), f"{FIELD_ANGLE_RMS_LIMIT_DEG:g} deg"
            )
        )
    for model, prefix, x0, lim, unit in (
        ("gyro", "w0", w0, FIELD_GYRO_BIAS_LIMIT_DPS, "deg/s"),
        ("accel", "f0", f0, FIELD_ACCEL_BIAS_LIMIT_G, "g"),
    ):
        for i, axis in enumerate("xyz"):
            if abs(float(x0[i])) > lim:
                out.append(Implausible(model, f"{prefix}_{axis}", float(x0[i]), f"+/-{lim:g} {unit}"))
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
# robust z beyond which a step is left out: 1.4x the largest of any clean unit measured on
# both simulators (docs/hardening.md)
CONSISTENCY_Z_LIMIT = 15.0
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


_LAYOUT_FIELDS = ("step", "test", "up_axis", "rate_dps", "w_ref", "f_ref")
_BISQUARE_C = 4.685
_IRLS_ITERATIONS = 8
# a robust scale below this fraction of a problem's largest |value| is rounding
_COLLAPSED_SCALE = 1e-8


# the shared scale temperature coefficient is estimated from the (step, repetition) pairs
# whose input is at least this share of the channel's largest and whose temperature differs
# from the step's median repetition by at least _THERMAL_MIN_DT_C
_THERMAL_MIN_INPUT = 0.25
_THERMAL_MIN_DT_C = 0.5
_THERMAL_MIN_PAIRS = 8


def _without_shared_thermal_scale(
    values: np.ndarray, temp: np.ndarray, w_ref: np.ndarray, f_ref: np.ndarray, shared: np.ndarray
) -> np.ndarray:
    """``values`` (R, S, 6) with each channel's scale temperature coefficient, shared by the
    repetitions, taken out: value - c * input * (T - the step's median T over repetitions).

    Why: repetitions at different temperatures (run back to back on one warm-up) see a scale
    with a temperature coefficient move between and *within* them; the per-repetition
    alignment takes one scale per repetition, so the fastest steps would look damaged. A
    coefficient is a property of the unit: one number per channel, the median of the
    (deviation from the step's median) / (input x temperature difference) over the pairs
    where both are large (a Theil-Sen-like estimate a few damaged steps cannot move; the
    turn-on bias differences cancel between a rate and its negative). Sessions without
    temperature, or whose repetitions share one temperature history: unchanged."""
    if not np.all(np.isfinite(temp[:, shared])):
        return values
    with np.errstate(invalid="ignore"):
        dT = temp - np.nanmedian(np.where(shared[None], temp, np.nan), axis=0)
    if not np.any(np.abs(dT[:, shared]) >= _THERMAL_MIN_DT_C):
        return values
    out = values.copy()
    med = np.nanmedian(values, axis=0)  # (S, 6)
    for c in range(6):
        u = (w_ref[:, c] if c < 3 else f_ref[:, c - 3]).astype(float)  # the nominal input
        big = shared & (np.abs(u) >= _THERMAL_MIN_INPUT * max(np.abs(u).max(initial=0.0), 1e-300))
        pairs = big[None] & (np.abs(dT) >= _THERMAL_MIN_DT_C) & np.isfinite(values[..., c])
        if np.count_nonzero(pairs) < _THERMAL_MIN_PAIRS or not np.any(u):
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = (values[..., c] - med[None, :, c]) / (u[None] * dT)
        coef = float(np.median(ratio[pairs]))
        out[..., c] = values[..., c] - coef * u[None] * np.nan_to_num(dT)
    return out


def _same_layout(a: StepMeans, b: StepMeans) -> bool:
    return all(
        getattr(a, f).dtype == getattr(b, f).dtype
        and getattr(a, f).shape == getattr(b, f).shape
        and getattr(a, f).tobytes() == getattr(b, f).tobytes()
        for f in _LAYOUT_FIELDS
    )


def _step_columns(sms: list[StepMeans]) -> tuple[list[np.ndarray], StepMeans | None, list[tuple]]:
    """Column of every row of every session in a table of the unit's distinct steps (same id,
    test, pose, rate and references), and the steps' keys. The usual unit (every repetition
    with the same steps) takes the first session's rows as the columns."""
    if all(_same_layout(sms[0], sm) for sm in sms[1:]):
        cols = np.arange(len(sms[0]))
        return [cols] * len(sms), sms[0], []
    columns: dict[tuple, int] = {}
    out = []
    for sm in sms:
        keys = zip(
            sm.step.tolist(),
            sm.test.tolist(),
            sm.up_axis.tolist(),
            sm.rate_dps.tolist(),
            map(bytes, sm.w_ref),
            map(bytes, sm.f_ref),
        )
        out.append(np.array([columns.setdefault(k, len(columns)) for k in keys], np.intp))
    return out, None, list(columns)


def _nanmedian_rows(a: np.ndarray, n: np.ndarray | None = None) -> np.ndarray:
    """Median of the finite values of each row of ``a`` (P, S), as (P, 1); NaN for a row
    without any. What ``np.nanmedian(a, axis=1, keepdims=True)`` gives, without its masked
    arrays (which cost most of this check's time on rows of ~100 values). ``n``: the count
    of values each row's median is taken over (default: its finite values); the rows are
    sorted NaN last, so the count of non-NaN values makes it ``np.nanmedian``'s, infinities
    included."""
    if n is None:
        n = np.count_nonzero(np.isfinite(a), axis=1)
    return _RowMedians(n, a.shape[1])(a)


class _RowMedians:
    """:func:`_nanmedian_rows` of arrays (P, ``width``) whose rows count ``n`` values each
    (the IRLS takes two medians per iteration over the same counts): the positions of each
    row's middle values in the sorted array found once."""

    def __init__(self, n: np.ndarray, width: int):
        self.n, self.width = n, width
        base = np.arange(len(n)) * width
        self.lo = base + np.maximum((n - 1) // 2, 0)
        self.hi = base + n // 2
        self.empty = None if n.all() else n == 0

    def __call__(self, a: np.ndarray) -> np.ndarray:
        if self.width == 0:
            return np.full((len(a), 1), np.nan)
        srt = np.sort(a, axis=1).ravel()  # NaN last
        mid = 0.5 * (srt[self.lo] + srt[self.hi])
        if self.empty is not None:
            mid[self.empty] = np.nan
        return mid[:, None]


def _nanmedian_first_axis(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=0)`` of ``a`` (R, ...), the same figures (the median of each
    position's non-NaN values; NaN where it has none), by one sort."""
    flat = a.reshape(len(a), -1).T
    n = np.count_nonzero(~np.isnan(flat), axis=1)
    return _nanmedian_rows(flat, n)[:, 0].reshape(a.shape[1:])


def _robust_affine_residuals(d: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Residuals of the problems ``d`` (P, S) (NaN: no value) on ``X`` (P, S, p), each by
    iteratively reweighted least squares with Tukey's bisquare (c = 4.685) starting from the
    median, all problems at once (normal equations, :func:`calib_core.linalg.solve_normal_stack`):
    a few damaged steps do not move the fit.

    A problem whose robust scale falls to rounding (an exact fit of more than half its
    steps: of the zeros of a repetition that is the median on most steps, quantised data)
    has weights set by the rounding of its residuals, which no two ways of solving share:
    such problems are solved with the normal matrices' pseudo-inverse throughout, whose
    rounding the check's figures are kept on. They are foreseen (half or more of the values
    0) and, should another one's scale fall, it is solved again that way."""
    out = np.full(d.shape, np.nan)
    enough = np.isfinite(d).sum(axis=1) >= X.shape[2] + 2  # else no residual (NaN)
    if not enough.any():
        return out
    d, X = d[enough], X[enough]
    zeros = np.count_nonzero(d == 0, axis=1)
    foreseen = 2 * zeros >= np.count_nonzero(np.isfinite(d), axis=1)
    e, collapsed = _irls_residuals(d, X, foreseen)
    again = collapsed & ~foreseen
    if again.any():
        e[again] = _irls_residuals(d[again], X[again], True)[0]
    out[enough] = e
    return out


def _irls_residuals(
    d: np.ndarray, X: np.ndarray, pseudo_inverse: bool | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_robust_affine_residuals`' iterations on problems with enough values, the
    ``pseudo_inverse`` ones (a mask, or all) by the pseudo-inverse; also which problems'
    scale of fitted residuals fell below ``_COLLAPSED_SCALE`` times their largest |value|."""
    valid = np.isfinite(d)
    d0 = np.where(valid, d, 0.0)
    X = np.where(valid[..., None], X, 0.0)
    floor = _COLLAPSED_SCALE * np.abs(d0).max(axis=1)
    collapsed = np.zeros(len(d), bool)
    e = d - _nanmedian_rows(d)
    median = None
    for i in range(_IRLS_ITERATIONS):
        # both medians are taken over the finite residuals (their count rarely changes)
        n = np.count_nonzero(np.isfinite(e), axis=1)
        if median is None or (n != median.n).any():
            median = _RowMedians(n, e.shape[1])
        centre = median(e)
        s = _MAD_TO_SD * median(np.abs(e - centre))
        if i:  # the first scale is of the values themselves
            collapsed |= s[:, 0] < floor
        u = e / (_BISQUARE_C * np.where(s > 0, s, np.inf))
        w = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)  # e NaN (no value): weight 0
        Xw = X * w[..., None]
        XwT = Xw.transpose(0, 2, 1)
        beta = solve_normal_stack(XwT @ X, XwT @ d0[..., None], pseudo_inverse)
        e = np.where(valid, d0 - (X @ beta)[..., 0], np.nan)
    return e, collapsed


def _pooled_scales(absdev: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(L, 6) robust scale of ``absdev`` (R, S, 6), |deviations| (NaN where not counted),
    pooled over the repetitions and the steps of each of the L labels of ``labels`` (S,)
    (0 .. L - 1); NaN for a label and channel with fewer than ``CONSISTENCY_MIN_GROUP``
    values. One sort: each label's values in a row of its own, padded with NaN (a median
    does not depend on the order of its values)."""
    n_rep, n_col, n_ch = absdev.shape
    n_lab = int(labels.max()) + 1
    counts = np.bincount(labels, minlength=n_lab)
    order = np.argsort(labels, kind="stable")
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    slot = np.arange(n_col) - starts[labels[order]]
    padded = np.full((n_lab, counts.max(), n_rep, n_ch), np.nan)
    padded[labels[order], slot] = absdev[:, order].transpose(1, 0, 2)
    rows = padded.transpose(0, 3, 1, 2).reshape(n_lab * n_ch, -1)
    n = np.count_nonzero(np.isfinite(rows), axis=1)
    med = _nanmedian_rows(rows, n)[:, 0]
    return np.where(n >= CONSISTENCY_MIN_GROUP, _MAD_TO_SD * med, np.nan).reshape(n_lab, n_ch)


def _group_scales(
    dev: np.ndarray, group_of: np.ndarray, test_of: np.ndarray, floor: np.ndarray
) -> np.ndarray:
    """(S, 6) robust scale of the deviations ``dev`` (R, S, 6) (NaN where not counted) per
    step and channel: pooled over the steps of the step's group (``group_of`` (S,), labels
    0 .. G - 1: test and |rate|) and every repetition; a group with too few deviations takes
    its test's scale (``test_of``, labels), a test with too few the channel's."""
    absdev = np.abs(dev)
    s = _pooled_scales(absdev, group_of)[group_of]
    for labels in (test_of, np.zeros(len(group_of), np.intp)):
        missing = np.isnan(s)
        if not missing.any():
            break
        s = np.where(missing, _pooled_scales(absdev, labels)[labels], s)
    return np.maximum(s, floor)  # NaN (no scale anywhere) stays NaN


def _standardised_times(t: np.ndarray) -> np.ndarray:
    """Each row of ``t`` (R, S) (NaN: no step) less its mean, over its standard deviation;
    0 where that is not a number (a session without times). A row without NaN takes the
    arithmetic ``np.nanmean`` / ``np.nanstd`` do, without their masks."""
    with np.errstate(invalid="ignore", divide="ignore"):
        if np.isnan(t).any():
            mean = np.nanmean(t, axis=1, keepdims=True)
            sd = np.nanstd(t, axis=1, keepdims=True)
        else:
            mean = t.sum(axis=1, keepdims=True) / t.shape[1]
            dev = t - mean
            sd = np.sqrt((dev * dev).sum(axis=1, keepdims=True) / t.shape[1])
        return np.nan_to_num((t - mean) / sd)


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
    cols_of, layout, keys = _step_columns(sms)
    if layout is not None:
        step_id, test = layout.step, layout.test
        rate, w_ref, f_ref = np.abs(layout.rate_dps), layout.w_ref, layout.f_ref
    else:
        step_id = np.array([k[0] for k in keys])
        test = np.array([k[1] for k in keys])
        rate = np.abs(np.array([k[3] for k in keys], float))
        w_ref = np.array([np.frombuffer(k[4]) for k in keys])
        f_ref = np.array([np.frombuffer(k[5]) for k in keys])
    n_col = len(step_id)
    values = np.full((n_rep, n_col, 6), np.nan)
    t_mid = np.full((n_rep, n_col), np.nan)
    temp = np.full((n_rep, n_col), np.nan)
    if layout is not None:  # every repetition's rows are the columns
        values[..., :3] = [sm.gyro for sm in sms]
        values[..., 3:] = [sm.accel for sm in sms]
        t_mid[...] = [sm.t_mid for sm in sms]
        temp[...] = [sm.temp_c for sm in sms]
    else:
        for r, (sm, cols) in enumerate(zip(sms, cols_of)):
            values[r, cols, :3] = sm.gyro
            values[r, cols, 3:] = sm.accel
            t_mid[r, cols] = sm.t_mid
            temp[r, cols] = sm.temp_c
    present = np.isfinite(values[..., 0])
    shared = present.sum(axis=0) >= 2  # a step seen in one repetition has nothing to compare
    if np.count_nonzero(shared) < 8:
        return []
    values[:, ~shared] = np.nan
    values = _without_shared_thermal_scale(values, temp, w_ref, f_ref, shared)
    median = np.full((n_col, 6), np.nan)  # over the repetitions that have the step
    median[shared] = _nanmedian_first_axis(values[:, shared])
    # the problems: each repetition (two: the first only, the second is its mirror) and channel
    fitted = 1 if n_rep == 2 else n_rep
    d = (values[:fitted] - median[None]).transpose(0, 2, 1)  # (fitted, 6, S)
    t = _standardised_times(t_mid[:fitted])
    # the designs: [1, the references (w_ref for the gyro channels, f_ref for the
    # accelerometers), t, t^2], t the repetition's own
    X = np.empty((fitted, 6, n_col, 6))
    X[..., 0] = 1.0
    X[:, :3, :, 1:4] = w_ref
    X[:, 3:, :, 1:4] = f_ref
    X[..., 4] = t[:, None]
    X[..., 5] = t[:, None] ** 2
    dev = np.full((n_rep, n_col, 6), np.nan)
    dev[:fitted] = (
        _robust_affine_residuals(d.reshape(-1, n_col), X.reshape(-1, n_col, 6))
        .reshape(fitted, 6, n_col)
        .transpose(0, 2, 1)
    )
    if n_rep == 2:  # each the other's reference: both deviations are +/- the difference
        dev[1] = -dev[0]
    # the scale leaves out the median repetition of each step (its deviation from itself
    # is zero before the affine fit: counting it would shrink the scale by a third with
    # three repetitions) and, with two repetitions, the second's (the same numbers); the
    # floor, a millionth of full scale, gives noise-free data one
    counted = np.where(values == median[None], np.nan, dev)
    if n_rep == 2:
        counted[1] = np.nan
    full_scale = np.concatenate(
        [np.asarray(sms[0].gyro_range_dps, float), np.asarray(sms[0].accel_range_g, float)]
    )
    _, test_of = np.unique(test.astype(str), return_inverse=True)
    _, rate_of = np.unique(rate, return_inverse=True)  # NaN rates are one rate
    _, group_of = np.unique(test_of * len(rate) + rate_of, return_inverse=True)  # test and |rate|
    scale = _group_scales(counted, group_of, test_of, 1e-6 * full_scale)
    with np.errstate(invalid="ignore"):
        z = dev / scale[None]
    beyond = np.abs(np.nan_to_num(z)) > z_limit
    out = []
    for r, col in zip(*np.nonzero(beyond.any(axis=2))):
        c = int(np.argmax(np.where(beyond[r, col], np.abs(z[r, col]), -1.0)))  # its worst channel
        out.append(
            StepDisagreement(
                int(r),
                int(step_id[col]),
                CHANNEL_NAMES[c],
                float(z[r, col, c]),
                float(dev[r, col, c]),
                n_rep == 2,
            )
        )
    return sorted(out, key=lambda s: (s.index, s.step))


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
