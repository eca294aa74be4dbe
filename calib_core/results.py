"""Result types shared by every estimator: named parameters with units and standard errors,
per-repetition calibrations and their aggregate over repetitions (xu2016 Tables 1 and 2)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

FORMAT_VERSION = "1.0"


def to_jsonable(v: Any, default=lambda x: x) -> Any:
    """JSON-safe copy: numpy scalars and arrays to Python, non-finite floats to None;
    ``default`` converts anything else (e.g. datetimes, paths)."""
    kind = type(v)  # the common leaves first, by exact type (subclasses take the checks below)
    if kind is float:
        return v if math.isfinite(v) else None
    if kind is str:
        return default(v)
    if kind is int or kind is bool:
        return v
    if kind is np.float64:  # as the np.floating branch below, without the checks before it
        return float(v) if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): to_jsonable(x, default) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [to_jsonable(x, default) for x in v]
    if isinstance(v, np.ndarray):
        return to_jsonable(v.tolist(), default)
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    return default(v)


@dataclass(frozen=True)
class Param:
    """One estimated scalar: model it belongs to, name, value, standard error, unit."""

    model: str
    name: str
    value: float
    stderr: float
    unit: str


@runtime_checkable
class FitResult(Protocol):
    """What every estimator returns: it can list its parameters and serialise itself."""

    model: str

    def parameters(self) -> list[Param]: ...

    def to_dict(self) -> dict[str, Any]: ...


def param_list(
    model: str, names: Iterable[str], values: Iterable[float], stderrs: Iterable[float], unit: str
) -> list[Param]:
    """Params of one model and unit, built without the frozen dataclass's per-field
    ``object.__setattr__`` (a session lists ~70 parameters; the objects are identical)."""
    new = object.__new__  # the frozen dataclass without its __init__: ~350 Params a unit
    out = []
    for name, v, e in zip(names, values, stderrs):
        p = new(Param)
        p.__dict__.update(model=model, name=name, value=v, stderr=e, unit=unit)
        out.append(p)
    return out


def matrix_names(prefix: str) -> tuple[str, ...]:
    """``prefix11 .. prefix33``: the names of a 3x3 matrix's entries, row-major."""
    return tuple(f"{prefix}{suffix}" for suffix in _MATRIX_SUFFIXES)


_MATRIX_SUFFIXES = tuple(f"{i + 1}{j + 1}" for i in range(3) for j in range(3))


# A fit's parameters as blocks (model, names, values, stderrs, unit): ``names`` a tuple,
# ``values`` / ``stderrs`` arrays (raveled in row-major order) of one name each. A fit with
# a ``param_blocks()`` method lists its parameters from them (``params_of_blocks``).
ParamBlock = tuple[str, tuple[str, ...], Any, Any, str]


def params_of_blocks(blocks: Iterable[ParamBlock]) -> list[Param]:
    """The Params of parameter blocks, in order (the fits' ``parameters()``)."""
    out: list[Param] = []
    for model, names, values, stderrs, unit in blocks:
        # tolist() converts to Python floats in one call (float(M[i, j]) is one numpy scalar
        # each)
        out += param_list(
            model,
            names,
            np.asarray(values, dtype=float).ravel().tolist(),
            np.asarray(stderrs, dtype=float).ravel().tolist(),
            unit,
        )
    return out


def _is_frozen(obj: Any) -> bool:
    params = getattr(type(obj), "__dataclass_params__", None)
    return bool(params is not None and params.frozen)


@dataclass
class RepetitionCalibration:
    """All fits of one session (lot/unit/rep), keyed by model name."""

    lot: str
    unit: str
    rep: int
    fits: dict[str, FitResult] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    provenance: dict[str, Any] = field(default_factory=dict)
    # values needed to apply the calibration that are not reported parameters (e.g. the
    # lever arms re-fitted in the body-axis projection that Calibration.apply subtracts)
    derived: dict[str, Any] = field(default_factory=dict)
    # facts about the protocol (its steps), not about this session: the same for every
    # session of the protocol, said once per lot ("P_<CODE>: ..."); they do not warn a session
    protocol_notes: list[str] = field(default_factory=list)

    def parameters(self) -> list[Param]:
        # listed again by the results store and the unit document: kept while
        # the same (immutable) fit objects are in ``fits``
        current = tuple(self.fits.items())
        cached = self.__dict__.get("_parameters")
        if (
            cached is not None
            and len(cached[0]) == len(current)
            and all(a == c and f is g for (a, f), (c, g) in zip(cached[0], current))
        ):
            return list(cached[1])
        params = [p for fit in self.fits.values() for p in fit.parameters()]
        if all(_is_frozen(f) for f in self.fits.values()):
            self.__dict__["_parameters"] = (current, params)
        return list(params)

    def __getstate__(self) -> dict:  # the parameter list is a cache: not pickled
        state = dict(self.__dict__)
        state.pop("_parameters", None)
        return state


@dataclass(frozen=True)
class ParamSummary:
    """A parameter across repetitions: the 'Average' column of xu2016 Tables 1-2 and spread."""

    model: str
    name: str
    unit: str
    mean: float
    std: float
    min: float
    max: float
    n_reps: int
    values: tuple[float, ...]  # per repetition, in rep order (the 'Number 1..5' columns)
    mean_stderr: float  # mean of the per-repetition standard errors (one repetition's typical)
    # standard error of ``mean`` from the repetitions' own standard errors, the repetitions
    # independent: sqrt(sum se_i^2) / n over those with a finite one
    stderr_of_mean: float = float("nan")


def stderr_of_mean(stderrs: np.ndarray) -> np.ndarray:
    """The standard error of the mean over independent repetitions, per column of
    ``stderrs`` (repetitions x parameters): sqrt(sum se_i^2) / n over the repetitions with a
    finite standard error; NaN where none has one. The summary's ``stderr_of_mean``."""
    s = np.atleast_2d(np.asarray(stderrs, float))
    finite = np.isfinite(s)
    n = finite.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(np.where(finite, s * s, 0.0).sum(axis=0)) / n
    out[n == 0] = np.nan
    return out


def _param_blocks(rep: RepetitionCalibration) -> list[ParamBlock]:
    """The repetition's parameters as blocks, in ``parameters()`` order: each fit's
    ``param_blocks()``, or a block per listed Param of a fit without them."""
    blocks: list[ParamBlock] = []
    for fit in rep.fits.values():
        of_fit = getattr(fit, "param_blocks", None)
        if of_fit is not None:
            blocks += of_fit()
        else:
            blocks += [(p.model, (p.name,), (p.value,), (p.stderr,), p.unit) for p in fit.parameters()]
    return blocks


def summarise(reps: list[RepetitionCalibration]) -> list[ParamSummary]:
    """Every parameter over the repetitions (xu2016 Tables 1-2): mean, sample std (ddof=1),
    min, max, the values in rep order, the mean of the standard errors and the standard
    error of the mean (both NaN when no repetition has a finite one), in the order the
    parameters first appear.

    A parameter some repetitions lack (a model they could not fit) is summarised over those
    that have it; each repetition lists a parameter at most once."""
    reps = sorted(reps, key=lambda r: r.rep)
    if not reps:
        return []
    # the repetitions x parameters table: value, stderr, and whether the repetition has it,
    # filled a parameter block at a time (no Param per parameter and repetition)
    column: dict[tuple[str, str], int] = {}
    units: list[str] = []
    listed = []
    for rep in reps:
        cols: list[int] = []
        values, stderrs = [], []
        for model, names, vals, ses, unit in _param_blocks(rep):
            for name in names:
                c = column.setdefault((model, name), len(column))
                if c == len(units):
                    units.append(unit)
                cols.append(c)
            values.append(np.asarray(vals, dtype=float).ravel())
            stderrs.append(np.asarray(ses, dtype=float).ravel())
        if len(set(cols)) != len(cols):
            raise ValueError(f"repetition {rep.rep} lists a parameter twice")
        listed.append((cols, values, stderrs))
    v = np.full((len(reps), len(units)), np.nan)
    s = np.full_like(v, np.nan)
    has = np.zeros(v.shape, dtype=bool)
    for row, (cols, values, stderrs) in enumerate(listed):
        if cols:
            at = np.array(cols, dtype=np.intp)
            has[row, at] = True
            v[row, at] = np.concatenate(values)
            s[row, at] = np.concatenate(stderrs)
    n = has.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(has, v, 0.0).sum(axis=0) / n
        deviation = np.where(has, v - mean, 0.0)
        std = np.sqrt((deviation * deviation).sum(axis=0) / (n - 1))  # NaN for one value
        se_known = has & ~np.isnan(s)
        mean_se = np.where(se_known, s, 0.0).sum(axis=0) / se_known.sum(axis=0)
    mean_se[~(has & np.isfinite(s)).any(axis=0)] = np.nan
    se_of_mean = stderr_of_mean(np.where(has, s, np.nan))
    vmin = np.where(has, v, np.inf).min(axis=0)
    vmax = np.where(has, v, -np.inf).max(axis=0)
    if has.all():  # every repetition has every parameter (the usual case)
        values = [tuple(col) for col in v.T.tolist()]
    else:
        values = [
            tuple(x for x, h in zip(col, col_has) if h) for col, col_has in zip(v.T.tolist(), has.T.tolist())
        ]
    # each frozen ParamSummary without its per-field object.__setattr__ (the objects are equal)
    new = object.__new__
    out = []
    for (model, name), unit, m, sd, lo, hi, k, vals, se, se_m in zip(
        column,
        units,
        mean.tolist(),
        std.tolist(),
        vmin.tolist(),
        vmax.tolist(),
        n.tolist(),
        values,
        mean_se.tolist(),
        se_of_mean.tolist(),
    ):
        summary = new(ParamSummary)
        summary.__dict__.update(
            model=model,
            name=name,
            unit=unit,
            mean=m,
            std=sd,
            min=lo,
            max=hi,
            n_reps=k,
            values=vals,
            mean_stderr=se,
            stderr_of_mean=se_m,
        )
        out.append(summary)
    return out


@dataclass
class UnitCalibration:
    """A unit's repetitions and their aggregate."""

    lot: str
    unit: str
    reps: list[RepetitionCalibration]
    summary: list[ParamSummary] = field(default_factory=list)

    @classmethod
    def from_reps(cls, lot: str, unit: str, reps: list[RepetitionCalibration]) -> UnitCalibration:
        reps = sorted(reps, key=lambda r: r.rep)
        return cls(lot=lot, unit=unit, reps=reps, summary=summarise(reps))
