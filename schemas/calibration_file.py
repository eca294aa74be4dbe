"""Calibration files: the JSON a firmware engineer loads, with a format version.

One format for every calibration type (turntable, Ferraris, field): the affine form
``w = K_g G + w0``, ``f = K_a A + f0`` (deg/s, g), the raw units it expects, optional
extension terms, and provenance. Written atomically (temp file + rename).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from calib_core.calibration import Calibration, TermValue
from calib_core.effects import get_effect
from calib_core.results import to_jsonable
from calib_core.thermal_model import ThermalModel

FORMAT = "mimucal-calibration"
# 1.1 adds ``thermal`` (a chamber calibration: each parameter a polynomial in the sensor
# temperature, docs/thermal.md); a calibration without it is written as 1.0, the same
# document as before, so tools that read 1.0 keep reading every file they can apply
FORMAT_VERSION = "1.0"
THERMAL_FORMAT_VERSION = "1.1"
SUPPORTED_VERSIONS = ("1.0", "1.1")


class CalibrationFileError(ValueError):
    """A calibration file that cannot be used, with the file and the reason."""


def calibration_to_dict(cal: Calibration, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": cal.kind,
        "model": "w = K_g G + w0 - sum(terms); f = K_a A + f0 - sum(terms)",
        "raw_units": {"gyro": cal.gyro_unit, "accel": cal.accel_unit},
        "units": {
            "K_g": f"deg/s per {cal.gyro_unit}",
            "w0": "deg/s",
            "K_a": f"g per {cal.accel_unit}",
            "f0": "g",
            "g_local": "m/s^2",
        },
        "K_g": np.asarray(cal.K_g).tolist(),
        "w0": np.asarray(cal.w0).tolist(),
        "K_a": np.asarray(cal.K_a).tolist(),
        "f0": np.asarray(cal.f0).tolist(),
        "g_local": cal.g_local,
        "terms": [tv.to_dict() for tv in cal.terms],
        "metadata": cal.metadata,
    }
    if cal.thermal is not None:
        doc["format_version"] = THERMAL_FORMAT_VERSION
        doc["model"] = "as 1.0 with K_g, w0, K_a, f0 = thermal polynomials at each sample's temp_c"
        doc["thermal"] = cal.thermal.to_dict()
    if extra:
        doc.update(extra)
    return doc


def calibration_from_dict(doc: dict[str, Any], source: str = "<dict>") -> Calibration:
    if doc.get("format") != FORMAT:
        raise CalibrationFileError(f"{source}: not a mimucal calibration file (format={doc.get('format')!r})")
    if doc.get("format_version") not in SUPPORTED_VERSIONS:
        raise CalibrationFileError(
            f"{source}: format_version {doc.get('format_version')!r} not supported "
            f"(supported: {', '.join(SUPPORTED_VERSIONS)})"
        )
    try:
        terms = []
        for t in doc.get("terms", []):
            term = get_effect(t["name"])
            undetermined = dict(t.get("undetermined") or {})
            # null: an undetermined parameter (the fit fixed it at 0, its reason in
            # "undetermined") is applied as 0; any other null reads back as NaN
            params = np.array(
                [
                    (0.0 if n in undetermined else np.nan) if t["params"][n] is None else t["params"][n]
                    for n in term.param_names
                ],
                dtype=float,
            )
            stderr = None
            if t.get("stderr"):
                stderr = np.array(
                    [np.nan if t["stderr"][n] is None else t["stderr"][n] for n in term.param_names],
                    dtype=float,
                )
            terms.append(TermValue(t["name"], params, stderr, undetermined))
        cal = Calibration(
            K_g=np.array(doc["K_g"], dtype=float),
            w0=np.array(doc["w0"], dtype=float),
            K_a=np.array(doc["K_a"], dtype=float),
            f0=np.array(doc["f0"], dtype=float),
            gyro_unit=doc["raw_units"]["gyro"],
            accel_unit=doc["raw_units"]["accel"],
            terms=tuple(terms),
            g_local=float(doc.get("g_local", 9.80665)),
            kind=doc.get("kind", "turntable"),
            metadata=doc.get("metadata", {}),
            thermal=ThermalModel.from_dict(doc["thermal"]) if doc.get("thermal") is not None else None,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationFileError(f"{source}: malformed calibration ({exc})") from exc
    for name, shape in (("K_g", (3, 3)), ("K_a", (3, 3)), ("w0", (3,)), ("f0", (3,))):
        if getattr(cal, name).shape != shape or not np.isfinite(getattr(cal, name)).all():
            raise CalibrationFileError(f"{source}: {name} must be finite with shape {shape}")
    return cal


# --- JSON text ---------------------------------------------------------------------------------
# Layout of every JSON file mimucal writes: objects one key per line (indent 2), lists that hold
# no object on one line (a 3x3 matrix is one line ``[[...], [...], [...]]``), lists of objects
# one element per line. ``json.dump(indent=2)`` gives the same documents (equal after
# ``json.load``) but goes through json's pure-Python encoder (any ``indent`` disables the C
# one), a large share of storing a unit (docs/benchmarks.md). Here only the
# objects are walked in Python; every one-line value is one call of an encoder without
# ``indent``, which json runs in C.
_INDENT = "  "
_SEPARATORS = (", ", ": ")
_encode_str = json.JSONEncoder(ensure_ascii=True).encode  # a str: straight to the C escaper


def _one_line_encoder(allow_nan: bool, hook):
    """``value -> str`` on one line."""
    return json.JSONEncoder(
        ensure_ascii=True, allow_nan=allow_nan, separators=_SEPARATORS, default=hook
    ).encode


def _plain(o: Any, default) -> Any:
    """numpy values as Python ones (what ``calib_core.results.to_jsonable`` gives), else
    ``default(o)``; TypeError when there is no way to write it."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if default is not None:
        out = default(o)
        if out is not o:
            return out
    raise TypeError(f"Object of type {type(o).__name__} is not JSON serializable")


def _numpy_hook(o: Any) -> Any:
    return _plain(o, None)


_LINE = _one_line_encoder(True, _numpy_hook)
_LINE_STRICT = _one_line_encoder(False, _numpy_hook)
_STRICT = _one_line_encoder(False, None)


def _holds_object(v: Any) -> bool:
    """Whether a list holds a dict (at any depth)."""
    for x in v:
        t = type(x)
        if t is float or t is int or t is str:
            continue
        if isinstance(x, dict):
            return True
        if isinstance(x, (list, tuple)) and _holds_object(x):
            return True
    return False


def _key(k: Any, null: bool) -> str:
    if isinstance(k, str):
        return _encode_str(k)
    if null:  # to_jsonable: str(k)
        return _encode_str(str(k))
    # json.dump's conversions of non-string keys
    if k is True or k is False or k is None:
        return _encode_str(json.dumps(k))
    if isinstance(k, (int, float)):
        return _encode_str(_STRICT(k))
    raise TypeError(f"keys must be str, int, float, bool or None, not {type(k).__name__}")


def _line(v: Any, null: bool, default) -> str:
    """One value without objects, on one line (C encoder)."""
    if default is None:
        text = _LINE(v)
    else:
        text = _one_line_encoder(True, lambda o: _plain(o, default))(v)
    if "NaN" in text or "Infinity" in text:  # a non-finite number (or that text in a string)
        if null:
            text = _STRICT(to_jsonable(v, default or (lambda x: x)))
        elif default is None:  # raises ValueError on a non-finite number, as json.dump does
            text = _LINE_STRICT(v)
        else:
            text = _one_line_encoder(False, lambda o: _plain(o, default))(v)
    return text


def _layout(v: Any, level: int, out: list[str], null: bool, default) -> None:
    t = type(v)
    if t is str:  # the common scalars without a call into the encoder
        out.append(_encode_str(v))
        return
    if t is float and math.isfinite(v):
        out.append(float.__repr__(v))
        return
    if t is int:
        out.append(int.__repr__(v))
        return
    if isinstance(v, dict):
        items = v.items()
    elif isinstance(v, (list, tuple)) and v and _holds_object(v):
        items = None
    else:
        out.append(_line(v, null, default))
        return
    if not v:
        out.append("{}" if items is not None else "[]")
        return
    pad = "\n" + _INDENT * (level + 1)
    out.append("{" if items is not None else "[")
    for i, kv in enumerate(items if items is not None else v):
        out.append(pad if i == 0 else "," + pad)
        if items is not None:
            out.append(_key(kv[0], null) + ": ")
            kv = kv[1]
        _layout(kv, level + 1, out, null, default)
    out.append("\n" + _INDENT * level + ("}" if items is not None else "]"))


def dumps_json(
    doc: Any, nonfinite: str = "error", default=None, null_keys: frozenset[str] | set[str] = frozenset()
) -> str:
    """``doc`` as JSON text in mimucal's layout (see above), ending with a newline.

    ``nonfinite``: ``"error"`` (ValueError, as ``json.dump(allow_nan=False)``) or ``"null"``
    (NaN and infinities written as null, as ``calib_core.results.to_jsonable`` does).
    numpy arrays and scalars are written as lists and numbers; ``default`` converts anything
    else (datetimes, paths) or returns it unchanged (then TypeError). ``null_keys``: top-level
    keys of ``doc`` whose values are written with ``nonfinite="null"`` (the rest as
    ``nonfinite``)."""
    if nonfinite not in ("error", "null"):
        raise ValueError("nonfinite must be 'error' or 'null'")
    null = nonfinite == "null"
    if not null_keys or not isinstance(doc, dict) or not doc:
        out: list[str] = []
        _layout(doc, 0, out, null, default)
        return "".join(out) + "\n"
    out = ["{"]
    for i, (k, x) in enumerate(doc.items()):
        out.append(("\n" if i == 0 else ",\n") + _INDENT + _key(k, null) + ": ")
        _layout(x, 1, out, null or k in null_keys, default)
    out.append("\n}\n")
    return "".join(out)


_FORMAT_LINE = f'  "format": "{FORMAT}",'


def write_json_atomic(
    path: Path,
    doc: dict[str, Any],
    nonfinite: str = "error",
    default=None,
    null_keys: frozenset[str] | set[str] = frozenset(),
) -> None:
    """Write JSON (:func:`dumps_json`) to ``path`` via a temp file in the same directory and an
    atomic rename."""
    _write_text_atomic(Path(path), dumps_json(doc, nonfinite, default, null_keys))


def _write_text_atomic(path: Path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
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


def save_calibration(
    cal: Calibration,
    path: Path,
    extra: dict[str, Any] | None = None,
    extra_nonfinite: str = "null",
    default=None,
) -> Path:
    """Write the calibration file. ``extra`` (top-level keys added to the document) may hold
    numpy values. Non-finite numbers (the standard errors, or values, of components a
    protocol cannot observe) are written as JSON null, in the terms as in ``extra``, and read
    back as NaN; the affine part (K_g, w0, K_a, f0) must be finite (ValueError otherwise, no
    file written). ``extra_nonfinite="error"`` refuses non-finite values in ``extra``."""
    for name in ("K_g", "w0", "K_a", "f0"):
        if not np.isfinite(np.asarray(getattr(cal, name), dtype=float)).all():
            raise ValueError(f"calibration {name} is not finite; no calibration file written")
    doc = calibration_to_dict(cal, extra)
    null_keys = set(doc) - (set(extra or ()) if extra_nonfinite == "error" else set())
    write_json_atomic(Path(path), doc, default=default, null_keys=frozenset(null_keys))
    return Path(path)


def load_calibration(path: Path) -> Calibration:
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: no such calibration file") from None
    except json.JSONDecodeError as exc:
        raise CalibrationFileError(f"{path}: not valid JSON ({exc})") from exc
    except (UnicodeDecodeError, RecursionError):
        raise CalibrationFileError(f"{path}: not a JSON text (damaged or overwritten)") from None
    except OSError as exc:
        raise CalibrationFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return calibration_from_dict(doc, source=str(path))


# --- QA status --------------------------------------------------------------------------------
# A calibration file produced by a fleet run carries ``qa``: the status its unit was judged
# with in its lot (``pass``, ``flagged`` with every reason, ``limits`` with the failed limits)
# and the lot context (lot, reference the robust z used, thresholds, configuration, date).
# A later re-flag that changes the status rewrites the file atomically; the statuses it had
# before are kept, oldest first, in ``qa_history``. A file without ``qa`` was not judged
# (written by ``mimucal calibrate``, or by a fleet run that did not reach its flags).
QA_STATUSES = ("pass", "flagged", "limits")


def read_calibration_document(path: Path) -> dict[str, Any]:
    """The JSON document of a calibration file (CalibrationFileError when unreadable)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: no such calibration file") from None
    except json.JSONDecodeError as exc:
        raise CalibrationFileError(f"{path}: not valid JSON ({exc})") from exc
    except (UnicodeDecodeError, RecursionError):
        raise CalibrationFileError(f"{path}: not a JSON text (damaged or overwritten)") from None
    except OSError as exc:
        raise CalibrationFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not isinstance(doc, dict):
        raise CalibrationFileError(f"{path}: not a mimucal calibration file")
    return doc


def qa_of(doc: dict[str, Any]) -> dict[str, Any] | None:
    """The ``qa`` block of a calibration document, None when it was never judged."""
    qa = doc.get("qa")
    return qa if isinstance(qa, dict) and qa.get("status") in QA_STATUSES else None


def set_qa_status(path: Path, qa: dict[str, Any]) -> bool:
    """Set the file's QA status (atomic rewrite); the previous one goes to ``qa_history``.
    Returns False (file untouched) when the status and reasons are already these."""
    if qa.get("status") not in QA_STATUSES:
        raise ValueError(f"QA status must be one of {QA_STATUSES}, got {qa.get('status')!r}")
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: no such calibration file") from None
    if '"qa"' not in text and text.endswith("\n}\n") and _FORMAT_LINE in text[:200]:
        # a file never judged (every file a fleet run writes, once): the block is appended
        # as the last key, without parsing and re-encoding the whole document (the first
        # re-flag of a fleet judges every file); the same document as the rewrite below
        out: list[str] = []
        _layout(qa, 1, out, True, None)
        _write_text_atomic(path, text[:-3] + ',\n  "qa": ' + "".join(out) + "\n}\n")
        return True
    doc = read_calibration_document(path)
    if doc.get("format") != FORMAT:
        raise CalibrationFileError(f"{path}: not a mimucal calibration file (format={doc.get('format')!r})")
    old = qa_of(doc)
    if old is not None and old.get("status") == qa["status"] and old.get("reasons") == qa.get("reasons"):
        return False
    if old is not None:
        doc["qa_history"] = [*(doc.get("qa_history") or []), old]
    doc["qa"] = qa
    write_json_atomic(Path(path), doc, nonfinite="null")
    return True
