"""The per-repetition and averaged sections of a unit's calibration file.

A unit's calibration file (``schemas.calibration_file``: the store's
``calibrations/<unit>/<time>.json``, ``mimucal calibrate --json``, ``schemas.api``) is the
applied calibration plus the sections :func:`calibration_file_sections` builds from
:func:`unit_document`::

    "provenance": {"lot", "unit", run context..., "sessions_used", "sessions_failed",
                   "extension_terms", "model_discovery"},
    "averaged": {"mean", "std", "units"},
    "repetitions": [{"rep", "K_g", "w0", "K_a", "f0", "stderr": {same keys}, "warnings",
                     "accel_static"?, "lever_arm_mm"? (each applied method's key), "condition_numbers"}]

K matrices are 3x3 row-major lists (w = K_g G + w0, f = K_a A + f0); w0 in deg/s and f0 in g
whatever the raw units (the boundary converts rad/s and m/s^2). Keys are only ever added.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calib_core.models.applied import applied_fits
from calib_core.results import FORMAT_VERSION, RepetitionCalibration

BASE_KEYS = ("K_g", "w0", "K_a", "f0")


def _rep_values(rep: RepetitionCalibration) -> dict[str, Any]:
    g, a = rep.fits["gyro"], rep.fits["accel"]
    vals = {"K_g": g.K, "w0": g.w0, "K_a": a.K, "f0": a.f0}
    errs = {"K_g": g.K_stderr, "w0": g.w0_stderr, "K_a": a.K_stderr, "f0": a.f0_stderr}
    if "accel_static" in rep.fits:
        st = rep.fits["accel_static"].to_dict()
        vals["accel_static"] = {k: np.asarray(st[k]) for k in ("scale", "bias", "angles_deg")}
        errs["accel_static"] = {k: np.asarray(st["stderr"][k]) for k in ("scale", "bias", "angles_deg")}
    for fit in applied_fits(rep.fits).values():  # e.g. the lever arm (calib_core.models.applied)
        vals[fit.document_key] = np.asarray(fit.applied_values(), dtype=float)
        errs[fit.document_key] = np.asarray(fit.applied_stderr(), dtype=float)
    return {"values": vals, "stderr": errs}


def _tolist(v):
    if isinstance(v, dict):
        return {k: _tolist(x) for k, x in v.items()}
    arr = np.asarray(v, dtype=float)
    return (
        [None if not np.isfinite(x) else float(x) for x in arr.ravel()]
        if arr.ndim == 1
        else [
            [None if not np.isfinite(x) else float(x) for x in row] for row in arr.reshape(arr.shape[0], -1)
        ]
    )


def _stack(reps: list[dict], key: str, fn):
    present = [r["values"][key] for r in reps if key in r["values"]]
    if not present:
        return None
    if isinstance(present[0], dict):
        return {k: fn(np.array([p[k] for p in present], dtype=float)) for k in present[0]}
    return fn(np.array(present, dtype=float))


def _mean_over_reps(a: np.ndarray) -> np.ndarray:
    """Mean over repetitions (axis 0) of the finite values; NaN where none is finite (a lever
    arm component no repetition could observe, named by the protocol note P_LEVER_ARM_UNOBSERVED), computed
    without NumPy's empty-slice warning."""
    finite = np.isfinite(a)
    n = finite.sum(axis=0)
    total = np.where(finite, a, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _std_over_reps(a: np.ndarray) -> np.ndarray:
    """Sample standard deviation (ddof 1) over repetitions of the finite values; NaN where
    fewer than two are finite."""
    finite = np.isfinite(a)
    n = finite.sum(axis=0)
    dev = np.where(finite, a - _mean_over_reps(a), 0.0)
    var = (dev * dev).sum(axis=0) / np.maximum(n - 1, 1)
    return np.where(n > 1, np.sqrt(var), np.nan)


def unit_document(
    lot: str, unit: str, reps: list[RepetitionCalibration], failed: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    reps = sorted(reps, key=lambda r: r.rep)
    per = [_rep_values(r) for r in reps]
    doc_reps = []
    for r, p in zip(reps, per):
        entry: dict[str, Any] = {"rep": r.rep}
        entry.update({k: _tolist(v) for k, v in p["values"].items()})
        entry["stderr"] = {k: _tolist(v) for k, v in p["stderr"].items()}
        entry["warnings"] = list(r.warnings)
        entry["condition_numbers"] = {
            m: float(f.condition_number) for m, f in r.fits.items() if hasattr(f, "condition_number")
        }
        doc_reps.append(entry)
    applied = {f.document_key: f.document_unit for r in reps for f in applied_fits(r.fits).values()}
    keys = list(BASE_KEYS) + [k for k in ("accel_static", *applied) if any(k in p["values"] for p in per)]
    mean = {k: _tolist(_stack(per, k, _mean_over_reps)) for k in keys}
    std = {k: _tolist(_stack(per, k, _std_over_reps)) for k in keys}
    g, a = (reps[0].fits["gyro"], reps[0].fits["accel"]) if reps else (None, None)
    units = {
        "K_g": f"deg/s per {g.raw_unit}" if g else None,
        "w0": "deg/s",
        "K_a": f"g per {a.raw_unit}" if a else None,
        "f0": "g",
    }
    if "accel_static" in keys:
        units["accel_static"] = {"scale": f"{a.raw_unit} per g", "bias": a.raw_unit, "angles_deg": "deg"}
    units.update({k: u for k, u in applied.items() if k in keys})
    return {
        "lot": lot,
        "unit": unit,
        "format_version": FORMAT_VERSION,
        "reps": doc_reps,
        "mean": mean,
        "std": std,
        "units": units,
        "failed": list(failed or []),
    }


def calibration_file_sections(
    lot: str,
    unit: str,
    reps: list[RepetitionCalibration],
    failed: list[dict[str, Any]],
    sessions_used: list[dict[str, Any]],
    extension_terms: list[str],
    model_discovery: dict | None,
    context: dict[str, Any],
) -> dict[str, Any]:
    """The sections a unit's calibration file holds beside the applied calibration (one
    format for the results store, ``mimucal calibrate --json`` and ``schemas.api``):
    ``provenance`` (``context``: run id, code version, time...; the sessions used and failed,
    the extension terms, model discovery's verdict), ``averaged`` (mean, std and units over
    the repetitions) and ``repetitions`` (each repetition's fits with standard errors)."""
    doc = unit_document(lot, unit, reps, failed)
    provenance = {
        "lot": lot,
        "unit": unit,
        **context,
        "sessions_used": sessions_used,
        "sessions_failed": list(failed),
        "extension_terms": list(extension_terms),
        "model_discovery": None
        if model_discovery is None
        else {k: model_discovery.get(k) for k in ("misfit", "unexplained", "effects")},
    }
    return {
        "provenance": provenance,
        "averaged": {k: doc[k] for k in ("mean", "std", "units")},
        "repetitions": doc["reps"],
    }
