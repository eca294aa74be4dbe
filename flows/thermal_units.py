"""A unit calibrated over temperature in the nightly: its sessions carry the samples metadata
``chamber_setpoint_c`` (docs/data-contract.md); with three or more setpoints the unit's
calibration is thermal (:mod:`calib_core.models.thermal`).

Every session is first calibrated as any other (the unit pipeline: xu2016 fits, tables,
discovery); this module then groups the successful sessions by setpoint, names those not
soaked (``W_NOT_SOAKED`` on the session, left out of the fit), fits the polynomials from the
sessions' own fits and replaces the unit's applied calibration by the thermal one (kind
``thermal``, file format 1.1; K_g, w0, K_a, f0 at 25 degC). The thermal coefficients go to
the store as the model ``thermal`` (parameters ``w0_tc_x``, ``k_g11_tc2``, ...), so
``[limits.thermal]`` in the QA configuration judges them like any other limit
(``w0_tc_x = {max = "0.01 deg/s/degC"}``). Never raises: a unit whose thermal fit cannot be
made keeps its single-temperature calibration and a note says why.
"""

from __future__ import annotations

import math
from dataclasses import replace

from calib_core.errors import DesignError
from calib_core.models.thermal import ThermalFit, chamber_point, fit_thermal, infer_sweeps, soak_of
from calib_core.thermal_model import PARAM_NAMES

SETPOINT_KEY = "chamber_setpoint_c"
SWEEP_KEY = "chamber_sweep"  # optional: heating | cooling (else inferred from the order)


def setpoint_of(metadata: dict) -> float | None:
    v = (metadata or {}).get(SETPOINT_KEY)
    if v is None or str(v).strip() == "":
        return None
    try:
        x = float(v)
    except ValueError:
        return None
    return x if math.isfinite(x) else None


def is_chamber_unit(outcomes) -> bool:
    """Whether any successful session of the unit carries ``chamber_setpoint_c``."""
    return any(
        o.succeeded and o.step_means is not None and setpoint_of(o.step_means.metadata) is not None
        for o in outcomes
    )


def thermal_fit_of(outcomes) -> tuple[ThermalFit | None, str | None]:
    """The unit's thermal fit from its sessions' outcomes (step means kept), or None and why.
    Sessions not soaked get ``W_NOT_SOAKED`` in their warnings."""
    good = [
        o
        for o in outcomes
        if o.succeeded
        and o.step_means is not None
        and o.calibration is not None
        and setpoint_of(o.step_means.metadata) is not None
    ]
    bad_meta = [
        str(o.key)
        for o in outcomes
        if o.succeeded
        and o.step_means is not None
        and SETPOINT_KEY in (o.step_means.metadata or {})
        and setpoint_of(o.step_means.metadata) is None
    ]
    warnings = [f"W_BAD_SETPOINT: {k}: {SETPOINT_KEY} is not a number; left out" for k in bad_meta]
    setpoints = [setpoint_of(o.step_means.metadata) for o in good]
    starts = [str(o.step_means.metadata.get("session_start") or "") for o in good]
    order = sorted(range(len(good)), key=lambda i: (starts[i], good[i].key.rep))
    rank = [0] * len(good)
    for r, i in enumerate(order):
        rank[i] = r
    inferred = infer_sweeps(setpoints, rank) if good else []
    points, soaks = [], []
    for o, sp, guess in zip(good, setpoints, inferred):
        declared = str(o.step_means.metadata.get(SWEEP_KEY, "")).strip().lower()
        sweep = {"heating": 1, "cooling": -1}.get(declared, guess)
        try:
            soak = soak_of(o.step_means, sp)
        except DesignError as exc:  # past the limit: the session fails (not a chamber soak)
            warnings.append(f"{exc.code}: {exc.reason}")
            o.status, o.code = "failed", exc.code
            o.message = f"[{exc.code}] session {o.key}, file samples.parquet: {exc.reason}"
            continue
        soaks.append(soak)
        if not soak.soaked:
            warnings.append(soak.warning)
            o.warnings.append(soak.warning)
            if o.status == "ok":
                o.status = "warned"
            continue
        points.append(chamber_point(str(o.key), sp, soak.mean_c, sweep, o.calibration.fits))
    try:
        return fit_thermal(points, soaks, warnings), None
    except DesignError as exc:
        return None, f"{exc.code}: {exc.reason}"
    except Exception as exc:  # noqa: BLE001 - the unit keeps its single-temperature calibration
        return None, f"E_THERMAL_FIT: {type(exc).__name__}: {exc}"


def apply_thermal(unit_out, outcomes) -> str | None:
    """Replace ``unit_out``'s applied calibration by the thermal one when its sessions make
    one; returns a note (why not, or the thermal fit's warnings) or None."""
    if unit_out.applied is None or not is_chamber_unit(outcomes):
        return None
    fit, why = thermal_fit_of(outcomes)
    failed = {(o.key.lot, o.key.unit, o.key.rep) for o in outcomes if not o.succeeded}
    c = unit_out.calibration
    if c is not None and any((r.lot, r.unit, r.rep) in failed for r in c.reps):
        # sessions failed here (E_NOT_SOAKED) leave the unit's repetitions
        kept = [r for r in c.reps if (r.lot, r.unit, r.rep) not in failed]
        unit_out.calibration = type(c).from_reps(c.lot, c.unit, kept) if kept else None
        if not kept:
            unit_out.applied = None
            return f"unit {unit_out.unit}: no session left; no calibration produced"
        if fit is None:
            from calib_core.models.pipeline import calibration_from_unit

            unit_out.applied = calibration_from_unit(unit_out.calibration)
    if fit is None:
        return f"thermal calibration not made: {why}; the unit keeps its single-temperature calibration"
    ref = fit.at_reference()
    applied = unit_out.applied
    unit_out.applied = replace(
        applied,
        K_g=ref["K_g"],
        w0=ref["w0"],
        K_a=ref["K_a"],
        f0=ref["f0"],
        terms=(),  # discovery's terms were fitted at one temperature
        kind="thermal",
        thermal=fit.thermal_model(),
        metadata={**applied.metadata, "model": "thermal (chamber setpoints)", "thermal_fit": fit.to_dict()},
    )
    # the coefficients go to the store as the model "thermal" of the first session fitted
    first = next(o for o in outcomes if str(o.key) == fit.points[0].key)
    first.calibration.fits["thermal"] = fit
    if unit_out.calibration is not None:
        for r in unit_out.calibration.reps:
            if (r.lot, r.unit, r.rep) == (first.key.lot, first.key.unit, first.key.rep):
                r.fits["thermal"] = fit
        c = unit_out.calibration
        unit_out.calibration = type(c).from_reps(c.lot, c.unit, c.reps)  # the summary with them
    return "; ".join(fit.warnings) or None


THERMAL_PARAMETERS = PARAM_NAMES
