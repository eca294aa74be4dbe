"""Errors and warnings about one session, with stable machine-readable codes.

A :class:`SessionError` rejects the whole session (a session is calibrated as a whole or
not at all); a :class:`SessionWarning` names something that was left out (a saturated or
too-short step) while the session is still used. Both name the session (``lot=L/unit=U/rep=R``,
or the directory path when the name does not parse), and errors also name the file, the
column or step when there is one, and the reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# --- error codes (stable: tests, reports and the nightly log key on them) -----------------
E_MISSING_FILE = "E_MISSING_FILE"  # steps.parquet or samples.parquet absent
E_UNREADABLE_FILE = "E_UNREADABLE_FILE"  # zero-byte, truncated or corrupt Parquet
E_MISSING_COLUMN = "E_MISSING_COLUMN"  # a required column is absent
E_WRONG_TYPE = "E_WRONG_TYPE"  # a column has a type the contract does not allow
E_BAD_METADATA = "E_BAD_METADATA"  # missing or unparseable key-value metadata
E_UNKNOWN_UNIT = "E_UNKNOWN_UNIT"  # gyro_unit / accel_unit not one of the allowed strings
E_BAD_PATH = "E_BAD_PATH"  # lot=/unit=/rep= directory name that does not parse
E_DUPLICATE_STEP = "E_DUPLICATE_STEP"  # a step id twice in steps.parquet
E_UNKNOWN_STEP = "E_UNKNOWN_STEP"  # samples.step not in steps.parquet (and not -1)
E_BAD_STEP_DEFINITION = "E_BAD_STEP_DEFINITION"  # unknown test/up_axis, NaN reference, ...
E_NONINCREASING_TIME = "E_NONINCREASING_TIME"  # samples.t not strictly increasing
E_NONFINITE_VALUE = "E_NONFINITE_VALUE"  # NaN, infinite or null sensor value or time
E_EMPTY_SESSION = "E_EMPTY_SESSION"  # no rows, or no usable step left
E_UNDETERMINED = "E_UNDETERMINED"  # the usable steps cannot determine the model
E_STEP_NOT_CONTIGUOUS = "E_STEP_NOT_CONTIGUOUS"  # a step id reappears after another step's
E_TOO_MANY_STEPS_LOST = "E_TOO_MANY_STEPS_LOST"  # more than the allowed share left out
E_CHECKSUM = "E_CHECKSUM"  # a Parquet page's CRC does not match its bytes
E_MIXED_UNITS = "E_MIXED_UNITS"  # a field recording in other raw units than its unit's first
E_BAD_OPTION = "E_BAD_OPTION"  # a field options file: not a bounded JSON object, or a value out of range
E_IMPLAUSIBLE = "E_IMPLAUSIBLE"  # estimates that are not those of a working sensor

ERROR_CODES = (
    E_MISSING_FILE,
    E_UNREADABLE_FILE,
    E_MISSING_COLUMN,
    E_WRONG_TYPE,
    E_BAD_METADATA,
    E_UNKNOWN_UNIT,
    E_BAD_PATH,
    E_DUPLICATE_STEP,
    E_UNKNOWN_STEP,
    E_BAD_STEP_DEFINITION,
    E_NONINCREASING_TIME,
    E_NONFINITE_VALUE,
    E_EMPTY_SESSION,
    E_UNDETERMINED,
    E_STEP_NOT_CONTIGUOUS,
    E_TOO_MANY_STEPS_LOST,
    E_CHECKSUM,
    E_MIXED_UNITS,
    E_BAD_OPTION,
    E_IMPLAUSIBLE,
)

# --- warning codes ------------------------------------------------------------------------
W_SATURATED = "W_SATURATED"  # a sample of the step (after settling) reached full scale
W_TOO_SHORT = "W_TOO_SHORT"  # fewer than min_samples samples left after settling
W_EMPTY_STEP = "W_EMPTY_STEP"  # a step of steps.parquet has no samples at all
W_INCONSISTENT_STEP = "W_INCONSISTENT_STEP"  # the step contradicts the unit's other repetitions
W_NUMERIC = "W_NUMERIC"  # NumPy met overflow / invalid values / division by zero on the session

WARNING_CODES = (W_SATURATED, W_TOO_SHORT, W_EMPTY_STEP, W_INCONSISTENT_STEP, W_NUMERIC)


class SessionError(Exception):
    """One session cannot be used. ``str(err)`` is the message a user sees."""

    def __init__(
        self,
        code: str,
        session: str,
        file: str,
        reason: str,
        column: str | None = None,
        step: int | None = None,
    ):
        self.code = code
        self.session = str(session)
        self.file = file
        self.reason = reason
        self.column = column
        self.step = None if step is None else int(step)
        super().__init__(self._message())

    def _message(self) -> str:
        where = [f"session {self.session}", f"file {self.file}"]
        if self.column is not None:
            where.append(f"column {self.column}")
        if self.step is not None:
            where.append(f"step {self.step}")
        return f"[{self.code}] {', '.join(where)}: {self.reason}"

    def __reduce__(self):  # picklable across process pools (Prefect/Dask task runners)
        return (SessionError, (self.code, self.session, self.file, self.reason, self.column, self.step))

    def to_dict(self) -> dict[str, Any]:
        return {
            "code": self.code,
            "session": self.session,
            "file": self.file,
            "reason": self.reason,
            "column": self.column,
            "step": self.step,
            "message": str(self),
        }


@dataclass(frozen=True)
class SessionWarning:
    """Something left out of a usable session (the session itself is still calibrated)."""

    code: str
    message: str
    step: int | None = None
    column: str | None = None

    def __str__(self) -> str:
        return f"[{self.code}] {self.message}"

    def to_dict(self) -> dict[str, Any]:
        return {"code": self.code, "message": self.message, "step": self.step, "column": self.column}


def from_design_error(exc: Exception, session: str, file: str = "steps.parquet") -> SessionError:
    """Attach the session to a :class:`calib_core.errors.DesignError` (the usable steps cannot
    determine the model): code ``E_UNDETERMINED``, the estimator's reason and what cannot be
    determined. The estimator's own code is kept in the reason for diagnosis."""
    reason = getattr(exc, "reason", None) or str(exc)
    inner = getattr(exc, "code", None)
    undetermined = tuple(getattr(exc, "undetermined", ()) or ())
    parts = [f"the usable steps cannot determine the model: {reason}"]
    if undetermined:
        parts.append(f"undetermined: {', '.join(undetermined)}")
    if inner and inner != E_UNDETERMINED:
        parts.append(f"estimator code {inner}")
    err = SessionError(E_UNDETERMINED, session, file, "; ".join(parts))
    err.__cause__ = exc
    return err
