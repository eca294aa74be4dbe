"""Calibration files: the JSON a firmware engineer loads, with a format version.

One format for every calibration type (turntable, Ferraris, field): the affine form
``w = K_g G + w0``, ``f = K_a A + f0`` (deg/s, g), the raw units it expects, optional
extension terms, and provenance. Written atomically (temp file + rename).
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from calib_core.calibration import Calibration, TermValue
from calib_core.effects import get_effect

FORMAT = "mimucal-calibration"
FORMAT_VERSION = "1.0"
SUPPORTED_VERSIONS = ("1.0",)


class CalibrationFileError(ValueError):
    """A calibration file that cannot be used, with the file and the reason."""


def calibration_to_dict(cal: Calibration, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": cal.kind,
        "model": "w = K_g G + w0 - sum(terms); f = K_a A + f0 - sum(terms)",
        "raw_units": {"gyro": cal.gyro_unit, "accel": cal.accel_unit},
        "units": {"K_g": f"deg/s per {cal.gyro_unit}", "w0": "deg/s",
                  "K_a": f"g per {cal.accel_unit}", "f0": "g", "g_local": "m/s^2"},
        "K_g": np.asarray(cal.K_g).tolist(),
        "w0": np.asarray(cal.w0).tolist(),
        "K_a": np.asarray(cal.K_a).tolist(),
        "f0": np.asarray(cal.f0).tolist(),
        "g_local": cal.g_local,
        "terms": [tv.to_dict() for tv in cal.terms],
        "metadata": cal.metadata,
    }
    if extra:
        doc.update(extra)
    return doc


def calibration_from_dict(doc: dict[str, Any], source: str = "<dict>") -> Calibration:
    if doc.get("format") != FORMAT:
        raise CalibrationFileError(f"{source}: not a mimucal calibration file (format={doc.get('format')!r})")
    if doc.get("format_version") not in SUPPORTED_VERSIONS:
        raise CalibrationFileError(
            f"{source}: format_version {doc.get('format_version')!r} not supported "
            f"(supported: {', '.join(SUPPORTED_VERSIONS)})")
    try:
        terms = []
        for t in doc.get("terms", []):
            term = get_effect(t["name"])
            params = np.array([t["params"][n] for n in term.param_names], dtype=float)
            stderr = None
            if t.get("stderr"):
                stderr = np.array([t["stderr"][n] for n in term.param_names], dtype=float)
            terms.append(TermValue(t["name"], params, stderr))
        cal = Calibration(
            K_g=np.array(doc["K_g"], dtype=float), w0=np.array(doc["w0"], dtype=float),
            K_a=np.array(doc["K_a"], dtype=float), f0=np.array(doc["f0"], dtype=float),
            gyro_unit=doc["raw_units"]["gyro"], accel_unit=doc["raw_units"]["accel"],
            terms=tuple(terms), g_local=float(doc.get("g_local", 9.80665)),
            kind=doc.get("kind", "turntable"), metadata=doc.get("metadata", {}),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationFileError(f"{source}: malformed calibration ({exc})") from exc
    for name, shape in (("K_g", (3, 3)), ("K_a", (3, 3)), ("w0", (3,)), ("f0", (3,))):
        if getattr(cal, name).shape != shape or not np.isfinite(getattr(cal, name)).all():
            raise CalibrationFileError(f"{source}: {name} must be finite with shape {shape}")
    return cal


def write_json_atomic(path: Path, doc: dict[str, Any]) -> None:
    """Write JSON to ``path`` via a temp file in the same directory and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(doc, fh, indent=2, sort_keys=False, allow_nan=False)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates 0600; a calibration is read by other users (firmware tooling)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o644 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_calibration(cal: Calibration, path: Path, extra: dict[str, Any] | None = None) -> Path:
    write_json_atomic(Path(path), calibration_to_dict(cal, extra))
    return Path(path)


def load_calibration(path: Path) -> Calibration:
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: no such calibration file") from None
    except json.JSONDecodeError as exc:
        raise CalibrationFileError(f"{path}: not valid JSON ({exc})") from exc
    return calibration_from_dict(doc, source=str(path))
