"""Everything mimucal fits on one session, and the calibration it applies for one unit.

``calibrate_repetition`` runs the xu2016 fits (required: the session fails without them), the
traditional inverse model, and the zhang2017 static and lever-arm fits where the steps allow;
``calibrate_repetitions`` does the same for a unit's repetitions, fitted together.
``calibration_from_unit`` averages the repetitions into the :class:`Calibration` that is saved
and applied (xu2016 section 3.1 averages the five repetitions the same way).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from calib_core.calibration import Calibration, TermValue
from calib_core.errors import DesignError
from calib_core.guards import check_fits, surely_plausible
from calib_core.models import xu2016
from calib_core.models.applied import applied_fits
from calib_core.results import FitResult, RepetitionCalibration, UnitCalibration
from calib_core.steps import StepMeans, stack_field
from calib_core.tables import CodedStrings, ColumnTable

# The methods fitted on every session besides xu2016's (which the session needs), by the
# model name their results carry: ``fitter(sessions) -> one fit per session`` (the sessions
# share one step layout), each fit a calib_core.results.FitResult. A DesignError (the steps
# cannot determine the method) becomes the session's warning ``W_<NAME>_SKIPPED``; the store,
# the averages over repetitions and the reports take every model's parameters as they come.
# Adding a calibration method is its module in calib_core/models/ and its line here.
OPTIONAL_FITS: tuple[tuple[str, Callable[[list[StepMeans]], list[FitResult]]], ...] = (
    ("gyro_traditional", xu2016.fit_gyro_traditional_stack),
    ("accel_traditional", xu2016.fit_accel_traditional_stack),
)


@dataclass
class SessionFit:
    """The fits of one session plus the tables the results store keeps.

    The tables are numpy columns (a DataFrame per session would cost more than the fits);
    ``compensation`` / ``residuals`` give them as DataFrames on request."""

    calibration: RepetitionCalibration
    compensation_table: ColumnTable  # xu2016 Table 3 rows
    residual_table: ColumnTable  # baseline replay residuals per step and channel

    @property
    def compensation(self) -> pd.DataFrame:
        return self.compensation_table.to_frame()

    @property
    def residuals(self) -> pd.DataFrame:
        return self.residual_table.to_frame()


def calibrate_repetition(sm: StepMeans, cpu_by_stage: dict[str, float] | None = None) -> SessionFit:
    """Fit every applicable model to one session. Raises DesignError when the xu2016 base
    model cannot be determined; optional models that cannot be fitted become warnings.

    ``cpu_by_stage``: when given, the CPU seconds of each stage are added to it (keys
    ``STAGES``: xu2016 fits, zhang2017 static fit, lever arms, result tables), for the
    benchmark's split of the fit phase; the results do not depend on it."""
    return _calibrate_together([sm], cpu_by_stage)[0]


def calibrate_repetitions(sms: list[StepMeans]) -> list[SessionFit | Exception]:
    """:func:`calibrate_repetition` of each session (the repetitions of a unit), item i the
    fit of ``sms[i]`` or the exception it raises, the same as each alone would give.

    Sessions that share a step layout (same steps, tests and references: every session of
    one protocol) are fitted together, one stacked LAPACK / BLAS call per operation instead
    of one per session: the per-call overhead of the small numpy operations is most of the
    fits' cost. When a session of such a group would fail or warn, the group is fitted
    session by session instead, so each error and warning stays its session's own."""
    out: list[SessionFit | Exception | None] = [None] * len(sms)
    for group in _same_layout(sms):
        fits = None
        if len(group) > 1:
            try:
                fits = _calibrate_together([sms[i] for i in group])
            except Exception:  # noqa: BLE001 - some session fails or warns: each alone
                fits = None
        for k, i in enumerate(group):
            if fits is not None:
                out[i] = fits[k]
                continue
            try:
                out[i] = calibrate_repetition(sms[i])
            except Exception as exc:  # noqa: BLE001 - the caller reports it for its session
                out[i] = exc
    return out


def _same_layout(sms: list[StepMeans]) -> list[list[int]]:
    """Indices of the sessions grouped by step layout (first-seen order)."""
    groups: list[list[int]] = []
    for i, sm in enumerate(sms):
        group = next((g for g in groups if _share_layout(sms[g[0]], sm)), None)
        if group is None:
            groups.append([i])
        else:
            group.append(i)
    return groups


def _share_layout(a: StepMeans, b: StepMeans) -> bool:
    """Same units, gravity, steps, tests and references, to the bit."""
    return (a.gyro_unit, a.accel_unit, a.g_local) == (b.gyro_unit, b.accel_unit, b.g_local) and all(
        _identical(getattr(a, name), getattr(b, name))
        for name in ("step", "test", "up_axis", "rate_dps", "angle_deg", "w_ref", "f_ref")
    )


def _identical(x: np.ndarray, y: np.ndarray) -> bool:
    """Same dtype, shape and bytes (a comparison of the bytes is ~50x faster than
    ``np.array_equal`` on these small arrays; stricter, never looser)."""
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


def _calibrate_together(
    sms: list[StepMeans], cpu_by_stage: dict[str, float] | None = None
) -> list[SessionFit]:
    """The fits of sessions that share a step layout, the stacked parts solved together.

    One session: exactly :func:`calibrate_repetition`. Several: whatever one of them would
    fail on or warn about from a stacked fit raises (the caller then fits each alone)."""
    lap = _Lap(cpu_by_stage)
    alone = len(sms) == 1
    fits: list[dict] = [{} for _ in sms]
    warnings: list[list[str]] = [[] for _ in sms]
    for f, gyro, accel in zip(
        fits, xu2016.fit_gyro_multirate_stack(sms), xu2016.fit_accel_multiposition_stack(sms)
    ):
        f["gyro"], f["accel"] = gyro, accel
    for f, sm in _unsure_fits(fits, sms):
        implausible = check_fits(f, sm)
        if implausible:
            raise DesignError(
                "E_IMPLAUSIBLE",
                "estimates are not those of a working sensor: " + "; ".join(str(i) for i in implausible),
                undetermined=tuple(f"{i.model} {i.parameter}" for i in implausible),
            )
    for name, fitter in OPTIONAL_FITS:
        try:
            for f, trad in zip(fits, fitter(sms)):
                f[name] = trad
        except DesignError as exc:
            if not alone:
                raise
            warnings[0].append(f"W_{name.upper()}_SKIPPED: {exc.reason}")
    lap("xu2016")
    derived: list[dict] = [{} for _ in sms]
    notes: list[list[str]] = [[] for _ in sms]
    _fit_zhang2017(sms, fits, warnings, derived, lap, notes)
    sm = sms[0]
    source = ("verification",) if (sm.test == "verification").any() else ("multirate",)
    comps = xu2016.compensation_error_tables(
        sms, [f["gyro"] for f in fits], [f.get("gyro_traditional") for f in fits], tests=source
    )
    residuals = residual_tables(sms, [calibration_from_fits(f, s) for f, s in zip(fits, sms)])
    out = []
    for sm, f, w, d, n, comp, res in zip(sms, fits, warnings, derived, notes, comps, residuals):
        key = sm.key
        rep = RepetitionCalibration(
            lot=key.lot,
            unit=key.unit,
            rep=key.rep,
            fits=f,
            warnings=w,
            provenance=dict(sm.metadata),
            derived=d,
            protocol_notes=n,
        )
        out.append(SessionFit(rep, comp, res))
    lap("tables")
    return out


def _unsure_fits(fits: list[dict], sms: list[StepMeans]) -> list[tuple[dict, StepMeans]]:
    """The (fits, session) pairs whose base model ``check_fits`` has to look at: those
    :func:`calib_core.guards.surely_plausible` does not clear."""
    clear = np.ones(len(sms), bool)
    for model, x0_name, range_name in (("gyro", "w0", "gyro_range_dps"), ("accel", "f0", "accel_range_g")):
        raw_unit = fits[0][model].raw_unit
        full_scales = [getattr(s, range_name) for s in sms]
        if any(f[model].raw_unit != raw_unit for f in fits[1:]) or any(
            np.shape(r) != (3,) for r in full_scales
        ):
            return list(zip(fits, sms))  # check_fits decides for each
        clear &= surely_plausible(
            model,
            np.stack([f[model].K for f in fits]),
            np.stack([getattr(f[model], x0_name) for f in fits]),
            raw_unit,
            np.array(full_scales, float),
        )
    return [(f, s) for f, s, c in zip(fits, sms, clear) if not c]


STAGES = ("xu2016", "zhang2017_static", "lever_arm", "tables")


class _Lap:
    """Adds the CPU time since the previous lap to ``cpu[stage]`` (nothing when cpu is None)."""

    def __init__(self, cpu: dict[str, float] | None):
        self.cpu = cpu
        self.t = time.process_time() if cpu is not None else 0.0

    def __call__(self, stage: str) -> None:
        if self.cpu is not None:
            now = time.process_time()
            self.cpu[stage] = self.cpu.get(stage, 0.0) + (now - self.t)
            self.t = now


def _fit_zhang2017(
    sms: list[StepMeans],
    fits: list[dict],
    warnings: list[list[str]],
    derived: list[dict],
    lap: _Lap | None = None,
    notes: list[list[str]] | None = None,
) -> None:
    """The 15-parameter static model and, with dynamic steps, the lever arms, of sessions
    that share a step layout (as :func:`_calibrate_together`: with several sessions, a
    DesignError raises instead of becoming the sessions' warning). Lever-arm components the
    dynamic steps cannot observe are a fact of the protocol: ``notes`` (each session's
    protocol notes) say so, ``P_LEVER_ARM_UNOBSERVED``."""
    notes = notes if notes is not None else [[] for _ in sms]
    lap = lap if lap is not None else _Lap(None)
    try:
        from calib_core.models import zhang2017
    except ImportError:  # pragma: no cover - module always present in a full install
        return
    alone = len(sms) == 1
    try:
        statics = zhang2017.fit_accel_static_stack(sms)
    except DesignError as exc:
        if not alone:
            raise
        warnings[0].append(f"W_ACCEL_STATIC_SKIPPED: {exc.reason}")
        lap("zhang2017_static")
        return
    for f, static in zip(fits, statics):
        f["accel_static"] = static
    lap("zhang2017_static")
    if (sms[0].test == "dynamic").any():
        try:
            # the paper's model (projection on each accelerometer's sensitive axis) is what
            # is reported and what Calibration.apply subtracts: the catalogue's lever arm
            # acts along each sensor's own direction too (a body-axis fit leaves up to
            # 66 mg at 3600 deg/s with 0.5-degree misaligned accelerometers, this one 35 mg
            # on the same physics-simulator units; discovery's joint fit, when it names the
            # lever arm, replaces it)
            inputs = zhang2017.lever_arm_inputs_stack(
                sms, statics, gyro_Ks=[f["gyro"].K for f in fits], gyro_w0s=[f["gyro"].w0 for f in fits]
            )
            for f, n, lever in zip(fits, notes, zhang2017.fit_lever_arm_from_stack(inputs)):
                f["lever_arm"] = lever
                if lever.undetermined:  # stored as NaN; the protocol's note says why
                    n.append(lever_arm_unobserved_note(lever.undetermined))
            for d, f in zip(derived, fits):
                d["lever_arm_mm"] = f["lever_arm"].lever_arm_mm
        except DesignError as exc:
            if not alone:
                raise
            warnings[0].append(f"W_LEVER_ARM_SKIPPED: {exc.reason}")
        lap("lever_arm")


LEVER_ARM_UNOBSERVED = "P_LEVER_ARM_UNOBSERVED"


def lever_arm_unobserved_note(components) -> str:
    """The protocol note of lever-arm components its dynamic steps cannot observe."""
    return (
        f"{LEVER_ARM_UNOBSERVED}: these dynamic steps do not observe "
        + ", ".join(components)
        + ": add tilted steps"
    )


def calibration_from_fits(fits: dict, sm: StepMeans, terms: tuple[TermValue, ...] = ()) -> Calibration:
    g, a = fits["gyro"], fits["accel"]
    return Calibration(
        K_g=g.K,
        w0=g.w0,
        K_a=a.K,
        f0=a.f0,
        gyro_unit=sm.gyro_unit,
        accel_unit=sm.accel_unit,
        terms=terms,
        g_local=sm.g_local,
    )


def applied_terms(
    reps: list[RepetitionCalibration], already: set[str] = frozenset()
) -> tuple[TermValue, ...]:
    """The terms of the applied methods (:mod:`calib_core.models.applied`, e.g. zhang2017's
    lever arm): per method the mean over repetitions of its parameters, when every
    repetition has its fit and every mean is finite, and its effect is not in ``already``
    (model discovery's terms)."""
    out = []
    for model, fit in applied_fits(reps[0].fits).items():
        if fit.applied_term in already or not all(model in r.fits for r in reps):
            continue
        values = np.mean([np.asarray(r.fits[model].applied_values(), float) for r in reps], axis=0)
        if np.isfinite(values).all():  # only a fully determined term is applied
            out.append(TermValue(fit.applied_term, values.ravel()))
    return tuple(out)


def calibration_from_unit(unit: UnitCalibration, terms: tuple[TermValue, ...] = ()) -> Calibration:
    """Average of the repetitions' K_g, w0, K_a, f0 (+ extension terms, + the terms of the
    applied methods, :func:`applied_terms`): what is applied."""
    reps = unit.reps
    if not reps:
        raise ValueError(f"unit {unit.unit}: no successful repetition to average")
    mean = lambda model, attr: np.mean([getattr(r.fits[model], attr) for r in reps], axis=0)  # noqa: E731
    first = reps[0].fits
    g_local = float(reps[0].provenance.get("g_local", 9.80665)) if reps[0].provenance else 9.80665
    terms = tuple(terms) + applied_terms(reps, {t.name for t in terms})
    return Calibration(
        K_g=mean("gyro", "K"),
        w0=mean("gyro", "w0"),
        K_a=mean("accel", "K"),
        f0=mean("accel", "f0"),
        gyro_unit=first["gyro"].raw_unit,
        accel_unit=first["accel"].raw_unit,
        terms=terms,
        g_local=g_local,
        metadata={"lot": unit.lot, "unit": unit.unit, "reps": [r.rep for r in reps]},
    )


RESIDUAL_COLUMNS = [
    "lot",
    "unit",
    "rep",
    "step",
    "test",
    "up_axis",
    "rate_dps",
    "angle_deg",
    "channel",
    "reference",
    "residual",
    "sigma",
    "model",
]


def baseline_residuals(sm: StepMeans, cal: Calibration, model: str = "baseline") -> pd.DataFrame:
    """Calibrated step mean minus reference, every step and channel (gyro deg/s, accel g).

    ``sigma`` is the white-noise part only (within-step scatter through K); the step-to-step
    part is estimated across repetitions by :mod:`calib_core.discovery.replay`."""
    return residual_table(sm, cal, model).to_frame()


CHANNELS = np.array(["gx", "gy", "gz", "ax", "ay", "az"])


def residual_table(sm: StepMeans, cal: Calibration, model: str = "baseline") -> ColumnTable:
    """The rows of :func:`baseline_residuals` as numpy columns (no DataFrame)."""
    return residual_tables([sm], [cal], model)[0]


def _applied(sms: list[StepMeans], cals: list[Calibration]) -> tuple[np.ndarray, np.ndarray]:
    """Each session's step means through its calibration (``Calibration.apply``), stacked."""
    applied = [cal.apply(s.gyro, s.accel, temp_c=s.temp_c, t=s.t_mid) for s, cal in zip(sms, cals)]
    return np.stack([w for w, _ in applied]), np.stack([f for _, f in applied])


def _applied_affine(sms: list[StepMeans], cals: list[Calibration]) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`_applied` of affine calibrations (no terms, no thermal model: the fits'), the
    sessions' products in one stacked matmul (each matrix the same BLAS call as alone, so
    the same numbers); None for any other calibration, or when ``Calibration.raw_inputs``
    would refuse a session's accelerometer data (then :func:`_applied` raises its error)."""
    if any(c.terms or c.thermal is not None or c.accel_unit != "g" for c in cals):
        return None
    G = stack_field(sms, "gyro").astype(float, copy=False)
    A = stack_field(sms, "accel").astype(float, copy=False)
    if A.shape[1]:  # raw_inputs' check: a median norm of gravity in m/s^2
        g_local = np.array([c.g_local for c in cals])
        norms = np.linalg.norm(A, axis=2)
        if np.isnan(norms).any():
            return None  # raw_inputs' nanmedian decides, session by session
        norm = np.median(norms, axis=1)
        if np.any((0.8 * g_local <= norm) & (norm <= 1.25 * g_local)):
            return None
    K_gT = np.stack([c.K_g.T for c in cals])
    K_aT = np.stack([c.K_a.T for c in cals])
    w0 = np.stack([c.w0 for c in cals])[:, None, :]
    f0 = np.stack([c.f0 for c in cals])[:, None, :]
    return G @ K_gT + w0, A @ K_aT + f0


def residual_tables(
    sms: list[StepMeans], cals: list[Calibration], model: str = "baseline"
) -> list[ColumnTable]:
    """:func:`residual_table` of sessions that share a step layout, each with its own
    calibration, computed together (table r is ``residual_table(sms[r], cals[r])``). The
    columns that come from the layout alone (step, test, references, ...) are built once and
    shared by the tables, read-only."""
    sm = sms[0]
    k = len(sm)
    w, f = _applied_affine(sms, cals) or _applied(sms, cals)
    res = np.concatenate([w - sm.w_ref, f - sm.f_ref], axis=2)
    n = np.sqrt(np.maximum(stack_field(sms, "count"), 1))[:, :, None]
    K_g2 = np.stack([cal.K_g.T for cal in cals]) ** 2
    K_a2 = np.stack([cal.K_a.T for cal in cals]) ** 2
    sg = np.sqrt(stack_field(sms, "gyro_std") ** 2 @ K_g2) / n
    sa = np.sqrt(stack_field(sms, "accel_std") ** 2 @ K_a2) / n
    sig = np.concatenate([sg, sa], axis=2)
    layout = {
        "step": np.repeat(sm.step, 6),
        "test": CodedStrings.of(sm.test).repeat(6),
        "up_axis": CodedStrings.of(sm.up_axis).repeat(6),
        "rate_dps": np.repeat(sm.rate_dps, 6),
        "angle_deg": np.repeat(sm.angle_deg, 6),
        "channel": CodedStrings(CHANNELS, np.tile(np.arange(6), k)),
        "reference": np.hstack([sm.w_ref, sm.f_ref]).ravel(),
    }
    if len(sms) > 1:
        for v in layout.values():
            (v.codes if isinstance(v, CodedStrings) else v).setflags(write=False)
    return [
        ColumnTable(
            {
                "lot": s.key.lot,
                "unit": s.key.unit,
                "rep": s.key.rep,
                **{
                    c: layout[c]
                    for c in ("step", "test", "up_axis", "rate_dps", "angle_deg", "channel", "reference")
                },
                "residual": res[r].ravel(),
                "sigma": sig[r].ravel(),
                "model": model,
            },
            6 * k,
        )
        for r, s in enumerate(sms)
    ]
