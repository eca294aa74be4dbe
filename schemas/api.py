"""mimucal's Python API: load a calibration, apply it to a DataFrame, calibrate a unit from a
dataset, run model discovery. Plain functions over the data contract (:mod:`schemas`) and the
numerics (:mod:`calib_core`); no Prefect, no results store needed except to read one.

A tiny simulated dataset (one unit, two repetitions at 10 Hz) makes the examples runnable:

>>> import tempfile, pathlib
>>> from schemas.api import simulate_unit_dataset
>>> root = pathlib.Path(tempfile.mkdtemp())
>>> truth = simulate_unit_dataset(root / "data", unit="U0001", reps=2, seed=3, rate_hz=10)
>>> sorted(p.name for p in (root / "data" / "lot=L01" / "unit=U0001").iterdir())
['rep=1', 'rep=2']

Calibrate it (every repetition, their average, model discovery), save the calibration file
(the format of the results store and of ``mimucal calibrate --json``) and load it again:

>>> from schemas.api import calibrate_unit, load_calibration_for, apply_to_frame, read_samples
>>> result = calibrate_unit(root / "data", "U0001")
>>> result.n_reps, result.failed
(2, [])
>>> bool(abs(result.calibration.K_g[0, 0] - truth.K_g[0, 0]) < 1e-3)  # truth known: simulated
True
>>> result.summary_frame().query("parameter == 'k_g11'")[["model", "unit"]].values.tolist()
[['gyro', 'deg/s per deg/s']]
>>> path = result.save(root / "U0001.json")
>>> cal = load_calibration_for(path, unit="U0001")
>>> cal.metadata["unit"]
'U0001'

Apply it to raw samples in a DataFrame whose raw units are named (here read from a session
file, whose metadata names them in ``df.attrs``); a unit or raw-unit mismatch is refused:

>>> raw = read_samples(root / "data" / "lot=L01" / "unit=U0001" / "rep=1" / "samples.parquet")
>>> raw.attrs["gyro_unit"], raw.attrs["accel_unit"], raw.attrs["unit"]
('deg/s', 'g', 'U0001')
>>> out = apply_to_frame(cal, raw)
>>> list(out.columns[-6:])
['w_x', 'w_y', 'w_z', 'f_x', 'f_y', 'f_z']
>>> at_rest = out[raw["step"] == 0]  # step 0: at rest, +x up: f is (1, 0, 0) g
>>> bool(abs(at_rest["f_x"].mean() - 1) < 2e-3 and abs(at_rest["f_z"].mean()) < 2e-3)
True
>>> apply_to_frame(cal, raw, unit="U0002")
Traceback (most recent call last):
...
schemas.api.CalibrationMismatch: the samples are of unit U0002, the calibration of unit U0001
>>> apply_to_frame(cal, raw, gyro_unit="LSB")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
schemas.api.CalibrationMismatch: raw units gyro='LSB' (LSB after conversion), accel='g' do not match ...
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from calib_core.calibration import Calibration
from calib_core.results import RepetitionCalibration, UnitCalibration
from schemas.errors import SessionError
from schemas.importers import convert_accel, convert_gyro

__all__ = [
    "CalibrationMismatch",
    "FlaggedCalibration",
    "UnitCalibrationResult",
    "apply_to_frame",
    "calibrate_unit",
    "discover_unit",
    "load_calibration_for",
    "read_samples",
    "simulate_unit_dataset",
]

GYRO_COLUMNS = ("gx", "gy", "gz")
ACCEL_COLUMNS = ("ax", "ay", "az")


class CalibrationMismatch(ValueError):
    """The data are not what the calibration was made for (another unit, other raw units)."""


# --- loading -------------------------------------------------------------------------------------
def load_calibration_for(
    source: str | Path,
    unit: str | None = None,
    at: str | datetime | None = None,
    mode: str = "before",
    allow_flagged: bool = False,
) -> Calibration:
    """The calibration of ``unit`` valid at ``at`` from a results folder, or the one in a
    calibration file.

    ``source``: a results store directory (then ``unit`` is required; ``at`` is an ISO 8601
    date or date-time or a datetime, default now; ``mode`` ``before`` takes the latest
    calibration made at or before ``at``, ``after`` the earliest at or after, ``closest`` the
    nearest) or a calibration file (``mimucal calibrate --json``, the store's files, Ferraris
    and field calibrations), whose unit must be ``unit`` when both are known. Times are when
    the unit's sessions were acquired (``session_start``; the production time for files
    without it). A calibration whose QA status is ``flagged`` or ``limits`` raises
    :class:`FlaggedCalibration` (with the reasons) unless ``allow_flagged``, as
    ``mimucal calibration`` refuses it.

    Raises ``LookupError`` (no calibration of the unit at that date, with the calibrations
    there are), :class:`CalibrationMismatch` (a file of another unit) or
    ``schemas.calibration_file.CalibrationFileError`` (a file that is not a calibration).

    >>> load_calibration_for("/nonexistent/results", unit="U0001")
    Traceback (most recent call last):
    ...
    LookupError: /nonexistent/results is neither a calibration file nor a results folder
    """
    from schemas.calibration_file import load_calibration
    from schemas.results_store import find_calibration, parse_when

    source = Path(source)
    if source.is_file():
        cal = load_calibration(source)
        have = cal.metadata.get("unit")
        if unit is not None and have is not None and str(have) != str(unit):
            raise CalibrationMismatch(f"{source} is the calibration of unit {have}, not {unit}")
        return cal
    if not source.is_dir():
        raise LookupError(f"{source} is neither a calibration file nor a results folder")
    if unit is None:
        raise ValueError("a results folder holds many units: give unit=")
    when = parse_when(at) if isinstance(at, str) else at
    path = find_calibration(source, unit, when, mode)
    check_qa(path, allow_flagged)
    return load_calibration(path)


class FlaggedCalibration(LookupError):
    """The calibration found was judged an outlier or outside limits in its lot."""


def check_qa(path: str | Path, allow_flagged: bool = False) -> None:
    """Raise :class:`FlaggedCalibration` when the calibration file's QA status is ``flagged``
    or ``limits`` (unless ``allow_flagged``); a file never judged passes."""
    from schemas.calibration_file import qa_of, read_calibration_document

    qa = qa_of(read_calibration_document(Path(path)))
    if qa is not None and qa["status"] != "pass" and not allow_flagged:
        raise FlaggedCalibration(
            f"{path}: QA status {qa['status']!r} in lot {qa.get('lot')}: "
            + "; ".join(qa.get("reasons") or [])
            + " (allow_flagged=True to use it anyway)"
        )


def read_samples(path: str | Path) -> pd.DataFrame:
    """A contract ``samples.parquet`` as a DataFrame; its metadata (``gyro_unit``,
    ``accel_unit``, ``unit``, ``lot``, ``g_local``...) in ``df.attrs``, the form
    :func:`apply_to_frame` reads the raw units and the unit id from."""
    import pyarrow.parquet as pq

    from schemas.contract import decode_metadata

    table = pq.read_table(path)
    df = table.to_pandas()
    df.attrs.update(decode_metadata(table.schema.metadata))
    return df


# --- applying ------------------------------------------------------------------------------------
class TemperatureOutOfRange(ValueError):
    """Samples a thermal calibration cannot take: no temperature, or one outside its range."""


def check_temperatures(cal: Calibration, temp_c: np.ndarray | None, extrapolate: bool = False) -> None:
    """One-line refusal of samples a thermal calibration was not made for (module text)."""
    th = cal.thermal
    if temp_c is None:
        raise TemperatureOutOfRange("the calibration is thermal and the samples have no temp_c column")
    temp_c = np.asarray(temp_c, float)
    if not np.isfinite(temp_c).all():
        raise TemperatureOutOfRange(f"{int((~np.isfinite(temp_c)).sum())} sample(s) have no finite temp_c")
    out = th.outside(temp_c)
    if out.any() and not extrapolate:
        raise TemperatureOutOfRange(
            f"{int(out.sum())} of {len(temp_c)} samples have temp_c outside the calibrated range "
            f"{th.t_min_c:.1f}..{th.t_max_c:.1f} degC (samples {np.nanmin(temp_c):.1f}.."
            f"{np.nanmax(temp_c):.1f} degC); pass --extrapolate (extrapolate=True) to apply the "
            "polynomials beyond it"
        )


def apply_to_frame(
    cal: Calibration,
    df: pd.DataFrame,
    gyro_unit: str | None = None,
    accel_unit: str | None = None,
    unit: str | None = None,
    extrapolate: bool = False,
) -> pd.DataFrame:
    """Calibrated rates and specific forces of the raw samples in ``df``.

    A thermal calibration (format 1.1, ``cal.thermal``) takes each sample's parameters at its
    own ``temp_c``: it needs the column, and refuses (:class:`TemperatureOutOfRange`)
    temperatures outside its calibrated range unless ``extrapolate``.

    ``df`` has the contract's columns ``gx, gy, gz`` and ``ax, ay, az`` (raw outputs) and
    optionally ``t`` [s], ``step``, ``temp_c``. The raw units are named: ``gyro_unit`` /
    ``accel_unit`` (deg/s, rad/s, LSB, V / g, m/s^2, LSB, V), else ``df.attrs`` (as
    :func:`read_samples` fills it); rad/s and m/s^2 are converted first (m/s^2 with
    ``df.attrs["g_local"]`` or the calibration's). The unit id, ``unit`` or
    ``df.attrs["unit"]``, must be the calibration's when both are known.

    Returns a DataFrame with ``df``'s index: ``t``, ``step``, ``temp_c`` when present, then
    ``w_x, w_y, w_z`` [deg/s] and ``f_x, f_y, f_z`` [g]; its ``attrs`` name those units.
    Raises :class:`CalibrationMismatch` on another unit or other raw units, ``ValueError``
    on missing columns or unnamed raw units.
    """
    attrs = dict(df.attrs)
    gyro_unit = gyro_unit or attrs.get("gyro_unit")
    accel_unit = accel_unit or attrs.get("accel_unit")
    if not gyro_unit or not accel_unit:
        raise ValueError("name the raw units: gyro_unit= and accel_unit= (or df.attrs)")
    missing = [c for c in GYRO_COLUMNS + ACCEL_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(
            f"missing column(s) {', '.join(missing)} (need {', '.join(GYRO_COLUMNS + ACCEL_COLUMNS)})"
        )
    unit = unit or attrs.get("unit")
    cal_unit = cal.metadata.get("unit")
    if unit is not None and cal_unit is not None and str(unit) != str(cal_unit):
        raise CalibrationMismatch(f"the samples are of unit {unit}, the calibration of unit {cal_unit}")
    g_local = float(attrs.get("g_local", cal.g_local))
    try:  # the importers' boundary conversion (rad/s -> deg/s, m/s^2 and mg -> g)
        G, gu = convert_gyro(df[list(GYRO_COLUMNS)].to_numpy(float), gyro_unit)
        A, au = convert_accel(df[list(ACCEL_COLUMNS)].to_numpy(float), accel_unit, g_local)
    except SessionError as exc:
        raise CalibrationMismatch(
            f"{exc.reason}; the calibration's raw_units are gyro={cal.gyro_unit!r}, accel={cal.accel_unit!r}"
        ) from None
    if gu != cal.gyro_unit or au != cal.accel_unit:
        raise CalibrationMismatch(
            f"raw units gyro={gyro_unit!r} ({gu} after conversion), accel={accel_unit!r} do not "
            f"match the calibration's raw_units gyro={cal.gyro_unit!r}, "
            f"accel={cal.accel_unit!r} (unit {cal_unit})"
        )
    t = df["t"].to_numpy(float) if "t" in df else None
    temp = df["temp_c"].to_numpy(float) if "temp_c" in df else None
    if cal.thermal is not None:
        check_temperatures(cal, temp, extrapolate)
    w, f = cal.apply_recording(G, A, t=t, temp_c=temp)
    out = pd.DataFrame({c: df[c] for c in ("t", "step", "temp_c") if c in df}, index=df.index)
    for i, ax in enumerate("xyz"):
        out[f"w_{ax}"] = w[:, i]
    for i, ax in enumerate("xyz"):
        out[f"f_{ax}"] = f[:, i]
    out.attrs = {"gyro_unit": "deg/s", "accel_unit": "g", "unit": cal_unit, "calibrated": True}
    return out


# --- calibrating ---------------------------------------------------------------------------------
@dataclass
class UnitCalibrationResult:
    """One unit calibrated from a dataset: the calibration to apply, every repetition's fits
    and their summary, the sessions that failed, model discovery's diagnosis."""

    lot: str
    unit: str
    calibration: Calibration  # what apply uses (discovery's terms when it kept any)
    unit_calibration: UnitCalibration  # repetitions and their mean/std per parameter
    failed: list[dict[str, Any]] = field(default_factory=list)  # {"rep", "code", "message"}
    diagnosis: Any = None  # calib_core.discovery.Diagnosis, None when not run
    sessions: list[dict[str, Any]] = field(default_factory=list)  # the sessions used
    # the measured noise (calib_core.noise_fleet.UnitNoise, docs/noise.md), None when none
    noise: Any = None

    @property
    def n_reps(self) -> int:
        return len(self.unit_calibration.reps)

    def summary_frame(self) -> pd.DataFrame:
        """One row per parameter: model, parameter, mean, std (over repetitions), unit."""
        return pd.DataFrame(
            [
                {
                    "model": s.model,
                    "parameter": s.name,
                    "mean": s.mean,
                    "std": s.std,
                    "n_reps": s.n_reps,
                    "unit": s.unit,
                }
                for s in self.unit_calibration.summary
            ]
        )

    def save(self, path: str | Path) -> Path:
        """Write the calibration file (the results store's format, which ``mimucal apply``
        and :func:`load_calibration_for` read) atomically; return its path."""
        from schemas.calibration_file import save_calibration
        from schemas.unit_document import calibration_file_sections

        diag = None if self.diagnosis is None else self.diagnosis.to_dict()
        extra = calibration_file_sections(
            self.lot,
            self.unit,
            self.unit_calibration.reps,
            self.failed,
            self.sessions,
            [t.name for t in self.calibration.terms],
            diag,
            {"run_id": None, "command": "schemas.api.calibrate_unit"},
        )
        if self.noise is not None:
            extra["noise"] = self.noise.to_dict()
        return save_calibration(self.calibration, Path(path), extra, extra_nonfinite="null", default=str)


def _read_unit(dataset: str | Path, unit: str):
    """The unit's sessions read and averaged, the steps that contradict the unit's other
    repetitions left out (as the nightly does): (lot, [(ref, step means, warnings)], failed)."""
    from schemas.averaging import leave_out_inconsistent_steps, read_step_means
    from schemas.dataset import find_sessions
    from schemas.errors import SessionError

    refs, _ = find_sessions(dataset, unit=unit)
    if not refs:
        units = sorted({p.name.split("=", 1)[1] for p in Path(dataset).glob("lot=*/unit=*")})
        raise LookupError(
            f"no session of unit {unit!r} under {dataset} (units: {', '.join(units) or 'none'})"
        )
    read, failed = [], []
    for ref in sorted(refs, key=lambda r: r.key.rep):
        try:
            sm, warns = read_step_means(ref)
        except (SessionError, ValueError) as exc:  # names the session, file and reason
            failed.append({"rep": ref.key.rep, "code": getattr(exc, "code", "E_INPUT"), "message": str(exc)})
            continue
        read.append((ref, sm, warns))
    checked = leave_out_inconsistent_steps([(sm, warns) for _, sm, warns in read])
    kept = []
    for (ref, _, _), item in zip(read, checked):
        if isinstance(item, SessionError):  # E_TOO_MANY_STEPS_LOST
            failed.append({"rep": ref.key.rep, "code": item.code, "message": str(item)})
        else:
            kept.append((ref, *item))
    return refs[0].key.lot, kept, failed


def calibrate_unit(dataset: str | Path, unit: str, discover: bool = True) -> UnitCalibrationResult:
    """Calibrate every session (repetition) of ``unit`` in a hive dataset
    (``lot=*/unit=*/rep=*``): the xu2016 and zhang2017 fits of each repetition, their
    average, and (``discover``, with two or more good repetitions) model discovery, whose
    extended calibration is the one applied when it keeps a term.

    A bad session is a failed entry (its session, file and reason), never an exception;
    ``LookupError`` when the dataset has no session of the unit (it names the units there
    are), ``ValueError`` when every session failed.

    >>> calibrate_unit("/nonexistent", "U0001")
    Traceback (most recent call last):
    ...
    LookupError: no session of unit 'U0001' under /nonexistent (units: none)
    """
    from calib_core.models.pipeline import calibrate_repetitions, calibration_from_unit
    from schemas.errors import SessionError

    lot, read, failed = _read_unit(dataset, unit)
    fits = calibrate_repetitions([sm for _, sm, _ in read])
    reps: list[RepetitionCalibration] = []
    good_sm, sessions = [], []
    for (ref, sm, warns), fit in zip(read, fits):
        if isinstance(fit, Exception):
            code = getattr(fit, "code", "E_INTERNAL")
            msg = str(fit) if isinstance(fit, SessionError) else f"[{code}] session {ref.key}: {fit}"
            failed.append({"rep": ref.key.rep, "code": code, "message": msg})
            continue
        reps.append(fit.calibration)
        good_sm.append(sm)
        sessions.append(
            {
                "rep": ref.key.rep,
                "path": str(ref.path),
                "status": "warned" if warns else "ok",
                "warnings": [str(w) for w in warns],
                "session_start": fit.calibration.provenance.get("session_start"),
            }
        )
    failed.sort(key=lambda f: f["rep"])
    if not reps:
        raise ValueError(f"unit {unit}: every session failed: " + "; ".join(f["message"] for f in failed))
    uc = UnitCalibration.from_reps(lot, unit, reps)
    cal = calibration_from_unit(uc)
    diagnosis = None
    from schemas.unit_noise import measure_unit_noise, recording_noise

    good = [(ref.key, ref.path) for ref, _, _ in read if ref.key.rep in {s["rep"] for s in sessions}]
    unit_dir = Path(good[0][1]).parent
    # a noise recording's model is discovery's null (the static steps' is not: same data)
    noise, _ = recording_noise(unit_dir, lot, unit, cal) if discover and len(good_sm) >= 2 else (None, [])
    if discover and len(good_sm) >= 2:
        from dataclasses import replace

        from calib_core.discovery import diagnose_unit
        from calib_core.discovery.measured_noise import MeasuredNoise

        measured = None if noise is None else MeasuredNoise.from_document(noise.model, noise.source)
        diagnosis = diagnose_unit(good_sm, tables=False, measured_noise=measured)
        if diagnosis.terms:
            cal = replace(diagnosis.calibration, metadata={**cal.metadata, "model": "discovery (joint fit)"})
            noise = None  # measured again through the extended calibration
    if noise is None:
        noise, _ = measure_unit_noise(unit_dir, lot, unit, cal, good)
    return UnitCalibrationResult(lot, unit, cal, uc, failed, diagnosis, sessions, noise)


def discover_unit(dataset: str | Path, unit: str, alpha: float | None = None):
    """Model discovery on ``unit``'s repetitions (two or more readable sessions): the
    misfit test, the catalogue effects found with their estimates and held-out gains, what
    stays unexplained (``calib_core.discovery.Diagnosis``; ``.to_dict()`` for JSON)."""
    from calib_core.discovery import DEFAULT_ALPHA, diagnose_unit

    _, read, failed = _read_unit(dataset, unit)
    if len(read) < 2:
        raise ValueError(
            f"unit {unit}: model discovery needs two readable repetitions, "
            f"{len(read)} read" + (f" ({failed[0]['message']})" if failed else "")
        )
    return diagnose_unit([sm for _, sm, _ in read], DEFAULT_ALPHA if alpha is None else alpha)


# --- a small dataset to try things on ------------------------------------------------------------
def simulate_unit_dataset(
    root: str | Path,
    unit: str = "U0001",
    lot: str = "L01",
    reps: int = 2,
    seed: int = 0,
    rate_hz: float = 10.0,
):
    """Write ``reps`` simulated turntable sessions of one unit (the default xu2016 +
    zhang2017 protocol, a typical MEMS unit) under ``root/lot=<lot>/unit=<unit>/`` and
    return its truth (``calib_core.sim.simulator.MimuTruth``). For examples and tests."""
    from calib_core.sim.protocols import default_session
    from calib_core.sim.simulator import (
        draw_repetition_truth,
        session_metadata,
        simulate_session,
        typical_truth,
    )
    from calib_core.steps import SessionKey
    from schemas.writer import write_session

    rng = np.random.default_rng(seed)
    truth = typical_truth(rng)
    steps = default_session()
    for rep in range(1, reps + 1):
        rep_truth = draw_repetition_truth(truth, rng)
        samples = simulate_session(rep_truth, steps, rng, rate_hz)
        md = session_metadata(
            rep_truth,
            rate_hz,
            session_start=f"2026-11-20T02:{rep - 1:02d}:00Z",
            lot=lot,
            unit=unit,
            rep=str(rep),
        )
        write_session(root, SessionKey(lot, unit, rep), steps, samples, md)
    return truth
