"""Result types shared by every estimator: named parameters with units and standard errors,
per-repetition calibrations and their aggregate over repetitions (xu2016 Tables 1 and 2)."""
from __future__ import annotations

import math
from functools import lru_cache
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


@lru_cache(maxsize=None)
def matrix_names(prefix: str) -> tuple[str, ...]:
    """``prefix11 .. prefix33``: the names of a 3x3 matrix's entries, row-major."""
    return tuple(f"{prefix}{suffix}" for suffix in _MATRIX_SUFFIXES)


_MATRIX_SUFFIXES = tuple(f"{i + 1}{j + 1}" for i in range(3) for j in range(3))


# A fit's parameters as blocks (model, names, values, stderrs, unit): ``names`` a tuple,
# ``values`` / ``stderrs`` arrays (raveled in row-major order) of one name each. A fit with
# a ``param_blocks()`` method lists its parameters from them (``params_of_blocks``), and
# ``summarise`` reads the repetitions' values from them as arrays, without a Param each.
ParamBlock = tuple[str, tuple[str, ...], Any, Any, str]


def params_of_blocks(blocks: Iterable[ParamBlock]) -> list[Param]:
    """The Params of parameter blocks, in order (the fits' ``parameters()``)."""
    out: list[Param] = []
    for model, names, values, stderrs, unit in blocks:
        # tolist() converts to Python floats in one call (float(M[i, j]) is one numpy scalar
        # each)
        out += param_list(model, names, np.asarray(values, dtype=float).ravel().tolist(),
                          np.asarray(stderrs, dtype=float).ravel().tolist(), unit)
    return out


@lru_cache(maxsize=256)
def _block_layout(heads: tuple[tuple[str, tuple[str, ...], str], ...]
                  ) -> tuple[tuple[tuple[str, str], ...], tuple[str, ...], bool]:
    """(model, name) of every parameter of blocks with these (model, names, unit) heads,
    their units, and whether the (model, name) pairs are distinct. The same few heads come
    back for every repetition of every unit: worked out once each."""
    keys = tuple((model, name) for model, names, _ in heads for name in names)
    units = tuple(unit for _, names, unit in heads for _ in names)
    return keys, units, len(set(keys)) == len(keys)


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

    def param_blocks(self) -> list[ParamBlock] | None:
        """Every fit's parameter blocks in ``parameters()`` order, or None when a fit has no
        ``param_blocks`` method (then only ``parameters()`` lists them)."""
        blocks: list[ParamBlock] = []
        for fit in self.fits.values():
            of_fit = getattr(fit, "param_blocks", None)
            if of_fit is None:
                return None
            blocks += of_fit()
        return blocks


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
    reps = sorted(reps, key=lambda r: r.rep)
    if not reps:
        return []
    # the values as arrays straight from the fits' parameter blocks (a Param per parameter
    # and repetition would cost more than the statistics); Params only for other fits
    blocks = [rep.param_blocks() for rep in reps]
    if any(b is None for b in blocks):
        return _summarise_params([rep.parameters() for rep in reps])
    layouts = [_block_layout(tuple((model, names, unit) for model, names, _, _, unit in b))
               for b in blocks]
    keys, units, distinct = layouts[0]
    if not distinct or any(lay[0] != keys for lay in layouts[1:]):
        return _summarise_by_key([rep.parameters() for rep in reps])
    n = len(reps)
    v = np.concatenate([np.asarray(x, dtype=float).ravel()
                        for b in blocks for _, _, x, _, _ in b]).reshape(n, len(keys))
    s = np.concatenate([np.asarray(x, dtype=float).ravel()
                        for b in blocks for _, _, _, x, _ in b]).reshape(n, len(keys))
    return _summary_rows(keys, units, v, s)


def _summarise_params(params: list[list[Param]]) -> list[ParamSummary]:
    """summarise() of the repetitions' parameter lists."""
    keys = [(p.model, p.name) for p in params[0]]
    if len(set(keys)) != len(keys) or any(
            [(p.model, p.name) for p in ps] != keys for ps in params[1:]):
        return _summarise_by_key(params)
    v = np.array([[p.value for p in ps] for ps in params], dtype=float)
    s = np.array([[p.stderr for p in ps] for ps in params], dtype=float)
    return _summary_rows(keys, [p.unit for p in params[0]], v, s)


def _summary_rows(keys, units, v: np.ndarray, s: np.ndarray) -> list[ParamSummary]:
    """The summaries when every repetition has the same parameters in the same order (the
    usual case): v and s (reps, parameters) values and standard errors, every statistic a
    reduction over the first axis."""
    n = v.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = v.mean(axis=0)
        std = v.std(axis=0, ddof=1) if n > 1 else np.full(v.shape[1], np.nan)
        has_se = np.isfinite(s).any(axis=0)
        s_sum = np.where(np.isnan(s), 0.0, s).sum(axis=0)  # nanmean, same arithmetic
        mean_se = np.where(has_se, s_sum / (~np.isnan(s)).sum(axis=0), np.nan)
    vmin, vmax = v.min(axis=0), v.max(axis=0)
    out = []
    for (model, name), unit, m, sd, lo, hi, col, se in zip(
            keys, units, mean.tolist(), std.tolist(), vmin.tolist(), vmax.tolist(),
            v.T.tolist(), mean_se.tolist()):
        summary = _new(ParamSummary)  # as ParamSummary(...), minus the frozen __setattr__s
        summary.__dict__.update(model=model, name=name, unit=unit, mean=m, std=sd, min=lo,
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
