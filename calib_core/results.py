"""Result types shared by every estimator: named parameters with units and standard errors,
per-repetition calibrations and their aggregate over repetitions (xu2016 Tables 1 and 2)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Protocol, runtime_checkable

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


def param_list(model: str, names: Iterable[str], values: Iterable[float],
               stderrs: Iterable[float], unit: str) -> list[Param]:
    """Params of one model and unit, built without the frozen dataclass's per-field
    ``object.__setattr__`` (a session lists ~70 parameters; the objects are identical)."""
    out = []
    for name, v, e in zip(names, values, stderrs):
        p = _new(Param)
        p.__dict__.update(model=model, name=name, value=v, stderr=e, unit=unit)
        out.append(p)
    return out


_new = object.__new__


def matrix_params(model: str, prefix: str, M: np.ndarray, S: np.ndarray, unit: str) -> list[Param]:
    """Params ``prefix11 .. prefix33`` of a 3x3 matrix (paper numbering, row-major)."""
    # tolist() converts to Python floats in one call (float(M[i, j]) is one numpy scalar each)
    return param_list(model, [f"{prefix}{suffix}" for suffix in _MATRIX_SUFFIXES],
                      np.asarray(M, dtype=float).ravel().tolist(),
                      np.asarray(S, dtype=float).ravel().tolist(), unit)


_MATRIX_SUFFIXES = tuple(f"{i + 1}{j + 1}" for i in range(3) for j in range(3))


def vector_params(model: str, names: Iterable[str], v: np.ndarray, s: np.ndarray,
                  unit: str) -> list[Param]:
    return param_list(model, names, np.asarray(v, dtype=float).ravel().tolist(),
                      np.asarray(s, dtype=float).ravel().tolist(), unit)


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

    def parameters(self) -> list[Param]:
        # listed again by summarise, the results store and the unit document: kept while
        # the same (immutable) fit objects are in ``fits``
        current = tuple(self.fits.items())
        cached = self.__dict__.get("_parameters")
        if cached is not None and len(cached[0]) == len(current) and all(
                a == c and f is g for (a, f), (c, g) in zip(cached[0], current)):
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
    mean_stderr: float  # mean of the per-repetition standard errors


def summarise(reps: list[RepetitionCalibration]) -> list[ParamSummary]:
    """Mean, sample std (ddof=1), min, max over repetitions of every parameter."""
    params = [rep.parameters() for rep in sorted(reps, key=lambda r: r.rep)]
    if not params:
        return []
    keys = [(p.model, p.name) for p in params[0]]
    if len(set(keys)) != len(keys) or any(
            [(p.model, p.name) for p in ps] != keys for ps in params[1:]):
        return _summarise_by_key(params)
    # every repetition has the same parameters in the same order (the usual case): one
    # (reps, parameters) matrix, every statistic a reduction over its first axis
    v = np.array([[p.value for p in ps] for ps in params], dtype=float)
    s = np.array([[p.stderr for p in ps] for ps in params], dtype=float)
    n = len(params)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = v.mean(axis=0)
        std = v.std(axis=0, ddof=1) if n > 1 else np.full(v.shape[1], np.nan)
        has_se = np.isfinite(s).any(axis=0)
        s_sum = np.where(np.isnan(s), 0.0, s).sum(axis=0)  # nanmean, same arithmetic
        mean_se = np.where(has_se, s_sum / (~np.isnan(s)).sum(axis=0), np.nan)
    vmin, vmax = v.min(axis=0), v.max(axis=0)
    out = []
    for (model, name), p, m, sd, lo, hi, col, se in zip(
            keys, params[0], mean.tolist(), std.tolist(), vmin.tolist(), vmax.tolist(),
            v.T.tolist(), mean_se.tolist()):
        summary = _new(ParamSummary)  # as ParamSummary(...), minus the frozen __setattr__s
        summary.__dict__.update(model=model, name=name, unit=p.unit, mean=m, std=sd, min=lo,
                                max=hi, n_reps=n, values=tuple(col), mean_stderr=se)
        out.append(summary)
    return out


def _summarise_by_key(params: list[list[Param]]) -> list[ParamSummary]:
    """summarise() when the repetitions do not list the same parameters."""
    by_key: dict[tuple[str, str], list[Param]] = {}
    for ps in params:
        for p in ps:
            by_key.setdefault((p.model, p.name), []).append(p)
    out = []
    for (model, name), ps in by_key.items():
        v = np.array([p.value for p in ps])
        s = np.array([p.stderr for p in ps])
        out.append(ParamSummary(
            model=model, name=name, unit=ps[0].unit, mean=float(v.mean()),
            std=float(v.std(ddof=1)) if len(v) > 1 else float("nan"),
            min=float(v.min()), max=float(v.max()), n_reps=len(v), values=tuple(v.tolist()),
            mean_stderr=float(np.nanmean(s)) if np.isfinite(s).any() else float("nan"),
        ))
    return out


@dataclass
class UnitCalibration:
    """A unit's repetitions and their aggregate."""

    lot: str
    unit: str
    reps: list[RepetitionCalibration]
    summary: list[ParamSummary] = field(default_factory=list)

    @classmethod
    def from_reps(cls, lot: str, unit: str, reps: list[RepetitionCalibration]) -> "UnitCalibration":
        reps = sorted(reps, key=lambda r: r.rep)
        return cls(lot=lot, unit=unit, reps=reps, summary=summarise(reps))

    def summary_of(self, model: str) -> dict[str, ParamSummary]:
        return {s.name: s for s in self.summary if s.model == model}
