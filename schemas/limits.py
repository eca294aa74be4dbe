"""The QA configuration engineers write: outlier options and acceptance limits, as TOML, with
the unit written next to every dimensional number::

    [outliers]                 # all optional
    z_threshold = 3.5
    family_alpha = 0.01
    history_units = 60         # small lots: judged against the last N good units of earlier lots
    history_below = 20         # ... when the lot has fewer units than this
    history_location = "lot"   # "lot": own median, history's spread; "history": both from it

    [limits]                   # parameter names are unique across models
    f0_y  = {min = "-7 mg", max = "7 mg"}
    w0_z  = {max = "0.5 deg/s"}
    k_g11 = {min = 0.995, max = 1.005}   # dimensionless: a plain number or "5000 ppm"

    [limits.lever_arm]         # the model may be named too
    r1x = {min = "-20 mm", max = "20 mm"}

The numbers are converted to the unit the store keeps (g, deg/s, deg, mm, dimensionless) with
a small explicit table (:data:`UNITS`): no units library is installed in the venv and the
quantities are few and linear (a library like pint would add a dependency for seven lines of
factors, and its own spellings of "deg/h" and "g", the latter being gram). Unknown
parameters, unknown units and a unit of the wrong kind are errors listing what is valid.
m/s^2 converts with standard gravity (9.80665): the store keeps g of each session's
``g_local``, which differs by < 0.1 %.

The numerics of judging are :mod:`calib_core.outliers`; this module only parses.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from calib_core.outliers import Limit, OutlierConfig, OutlierConfigError
from calib_core.thermal_model import coefficient_name

if TYPE_CHECKING:  # the store module imports more than a configuration needs
    from schemas.results_store import ResultsStore

STANDARD_GRAVITY = 9.80665
_SQRT_H = 60.0  # sqrt(3600 s)
_RAD = 180.0 / math.pi
NOISE_COEFFICIENTS = ("quantization", "white", "bias_instability", "random_walk", "ramp", "gauss_markov")
# noise coefficient kinds -> {unit: factor to the unit the noise table holds (the first)}
NOISE_UNITS: dict[str, dict[str, float]] = {
    "gyro quantization": {"deg": 1.0, "arcsec": 1.0 / 3600.0, "rad": _RAD, "urad": _RAD * 1e-6},
    "gyro white": {
        "deg/sqrt(h)": 1.0,
        "deg/s/sqrt(Hz)": _SQRT_H,
        "deg/h/sqrt(Hz)": _SQRT_H / 3600.0,
        "mdeg/s/sqrt(Hz)": _SQRT_H * 1e-3,
        "rad/s/sqrt(Hz)": _SQRT_H * _RAD,
    },
    "gyro bias_instability": {"deg/h": 1.0, "deg/s": 3600.0, "rad/s": 3600.0 * _RAD},
    "gyro random_walk": {
        "deg/h/sqrt(h)": 1.0,
        "deg/s/sqrt(s)": 3600.0 * _SQRT_H,
        "rad/s^2/sqrt(Hz)": 3600.0 * _SQRT_H * _RAD,
    },
    "gyro ramp": {"deg/h^2": 1.0, "deg/h/h": 1.0, "deg/s^2": 3600.0**2},
    "gyro gauss_markov": {"deg/h": 1.0, "deg/s": 3600.0, "rad/s": 3600.0 * _RAD},
    "accel quantization": {"m/s": 1.0, "mm/s": 1e-3},
    "accel white": {
        "m/s/sqrt(h)": 1.0,
        "m/s^2/sqrt(Hz)": _SQRT_H,
        "mg/sqrt(Hz)": _SQRT_H * STANDARD_GRAVITY * 1e-3,
        "ug/sqrt(Hz)": _SQRT_H * STANDARD_GRAVITY * 1e-6,
    },
    "accel bias_instability": {"mg": 1.0, "g": 1e3, "ug": 1e-3, "m/s^2": 1e3 / STANDARD_GRAVITY},
    "accel random_walk": {
        "m/s/h/sqrt(h)": 1.0,
        "m/s^2/sqrt(s)": 3600.0 * _SQRT_H,
        "m/s^3/sqrt(Hz)": 3600.0 * _SQRT_H,
    },
    "accel ramp": {"m/s/h^2": 1.0, "m/s/h/h": 1.0, "m/s^3": 3600.0**2},
    "accel gauss_markov": {"mg": 1.0, "g": 1e3, "ug": 1e-3, "m/s^2": 1e3 / STANDARD_GRAVITY},
}
_MAT = [f"{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
_AX = "xyz"

# kind of quantity -> {unit as written: factor to the stored unit}; the stored unit first
UNITS: dict[str, dict[str, float]] = {
    "dimensionless": {"": 1.0, "1": 1.0, "%": 1e-2, "ppm": 1e-6},
    "acceleration": {
        "g": 1.0,
        "mg": 1e-3,
        "ug": 1e-6,
        "µg": 1e-6,
        "m/s^2": 1.0 / STANDARD_GRAVITY,
        "m/s2": 1.0 / STANDARD_GRAVITY,
    },
    "angular rate": {
        "deg/s": 1.0,
        "mdeg/s": 1e-3,
        "deg/h": 1.0 / 3600.0,
        "rad/s": 180.0 / math.pi,
        "mrad/s": 0.18 / math.pi,
    },
    "angle": {
        "deg": 1.0,
        "mdeg": 1e-3,
        "arcmin": 1.0 / 60.0,
        "arcsec": 1.0 / 3600.0,
        "rad": 180.0 / math.pi,
        "mrad": 0.18 / math.pi,
    },
    "length": {"mm": 1.0, "um": 1e-3, "cm": 10.0, "m": 1000.0},
    # thermal coefficients (model "thermal", docs/thermal.md): per degC^k of the parameter
    **{
        f"{kind} per degC{sup}": {f"{u}/degC{sup}": f for u, f in units.items()}
        for sup in ("", "^2", "^3")
        for kind, units in (
            ("angular rate", {"deg/s": 1.0, "mdeg/s": 1e-3, "deg/h": 1.0 / 3600.0}),
            ("acceleration", {"g": 1.0, "mg": 1e-3, "ug": 1e-6}),
            ("dimensionless", {"1": 1.0, "ppm": 1e-6}),
        )
    },
    # noise coefficients (model "noise", docs/noise.md): the IEEE 952 / 1293 units the noise
    # table holds first; the continuous-time densities (Kalibr's) convert to them
    **NOISE_UNITS,
}
STORED_UNIT = {
    "dimensionless": "",
    "acceleration": "g",
    "angular rate": "deg/s",
    "angle": "deg",
    "length": "mm",
    **{
        f"{kind} per degC{sup}": f"{u}/degC{sup}"
        for sup in ("", "^2", "^3")
        for kind, u in (("angular rate", "deg/s"), ("acceleration", "g"), ("dimensionless", "1"))
    },
    **{kind: next(iter(units)) for kind, units in NOISE_UNITS.items()},
}

# model -> parameter -> kind of quantity (the stored units when the raw units are deg/s and g;
# a unit fitted on LSB keeps "deg/s per LSB" etc., which a limit may name literally)
PARAMETERS: dict[str, dict[str, str]] = {
    "gyro": {**{f"k_g{m}": "dimensionless" for m in _MAT}, **{f"w0_{a}": "angular rate" for a in _AX}},
    "accel": {**{f"k_a{m}": "dimensionless" for m in _MAT}, **{f"f0_{a}": "acceleration" for a in _AX}},
    "gyro_traditional": {
        **{f"s_g{m}": "dimensionless" for m in _MAT},
        **{f"b_g_{a}": "angular rate" for a in _AX},
    },
    "accel_traditional": {
        **{f"s_a{m}": "dimensionless" for m in _MAT},
        **{f"b_a_{a}": "acceleration" for a in _AX},
    },
    "accel_static": {
        **{f"k_{a}": "dimensionless" for a in _AX},
        **{f"u0_{a}": "acceleration" for a in _AX},
        **{f"theta_{a}{b}": "angle" for a in _AX for b in _AX},
    },
    "lever_arm": {f"r{i}{a}": "length" for i in (1, 2, 3) for a in _AX},
    # the thermal coefficients (flows.thermal_units): w0_tc_x, k_g11_tc2, f0_tc3_z, ...
    "thermal": {
        coefficient_name(p, k): f"{kind} per degC{sup}"
        for k, sup in ((1, ""), (2, "^2"), (3, "^3"))
        for p, kind in [(f"k_g{m}", "dimensionless") for m in _MAT]
        + [(f"w0_{a}", "angular rate") for a in _AX]
        + [(f"k_a{m}", "dimensionless") for m in _MAT]
        + [(f"f0_{a}", "acceleration") for a in _AX]
    },
    # the noise coefficients (calib_core.noise_fleet): gyro_white applies to gx, gy and gz
    "noise": {f"{sensor}_{c}": f"{sensor} {c}" for sensor in ("gyro", "accel") for c in NOISE_COEFFICIENTS},
}
MODEL_OF = {name: model for model, names in PARAMETERS.items() for name in names}

_NUMBER = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")


class LimitsError(OutlierConfigError):
    """A QA configuration that cannot be used, naming the file, the entry and the reason."""


def parse_quantity(value: Any, kind: str, where: str) -> tuple[float, str]:
    """(value in the stored unit, the stored unit) of ``"-7 mg"`` / ``0.995`` for a parameter
    of ``kind``. A bare number is only accepted for dimensionless parameters."""
    if isinstance(value, bool):
        raise LimitsError(f"{where}: {value!r} is not a quantity")
    if isinstance(value, (int, float)):
        if kind != "dimensionless":
            raise LimitsError(
                f"{where}: {value!r} has no unit; write it with one, e.g. "
                f'"{value} {next(iter(UNITS[kind]))}" (units for {kind}: '
                f"{', '.join(UNITS[kind])})"
            )
        if not math.isfinite(value):
            raise LimitsError(f"{where}: {value!r} is not a finite number")
        return float(value), ""
    if not isinstance(value, str):
        raise LimitsError(f"{where}: {value!r} is not a number with a unit")
    m = _NUMBER.match(value)
    if not m:
        raise LimitsError(f"{where}: {value!r} is not a number followed by a unit")
    number, unit = float(m.group(1)), m.group(2)
    if not math.isfinite(number):  # "1e999 mg"
        raise LimitsError(f"{where}: {value!r} is not a finite number")
    factors = UNITS[kind]
    if unit in factors:
        return number * factors[unit], STORED_UNIT[kind]
    if " per " in unit:  # a unit fitted on raw LSB/V: "deg/s per LSB", kept as written
        return number, unit
    other = next((k for k, f in UNITS.items() if unit in f), None)
    why = f"a unit of {other}, not {kind}" if other else "an unknown unit"
    raise LimitsError(
        f"{where}: {unit!r} is {why}; valid units for {kind}: "
        f"{', '.join(repr(u) for u in factors if u) or 'none'}"
        + (" or a plain number" if kind == "dimensionless" else "")
    )


def _limit(model: str, name: str, spec: Any, source: str) -> Limit:
    where = f"{source}: limit of {model}.{name}"
    if not isinstance(spec, dict) or not spec or not set(spec) <= {"min", "max"}:
        raise LimitsError(f"{where} must be {{min = ..., max = ...}} (either or both), got {spec!r}")
    kind = PARAMETERS[model][name]
    lo = hi = None
    units = set()
    if "min" in spec:
        lo, u = parse_quantity(spec["min"], kind, f"{where}, min")
        units.add(u)
    if "max" in spec:
        hi, u = parse_quantity(spec["max"], kind, f"{where}, max")
        units.add(u)
    if len(units) > 1:
        raise LimitsError(f"{where}: min and max in units of different kinds {sorted(units)}")
    if lo is not None and hi is not None and lo > hi:
        raise LimitsError(f"{where}: min {spec['min']!r} > max {spec['max']!r}")
    return Limit(
        model,
        name,
        lo,
        hi,
        unit=units.pop(),
        written=" .. ".join(str(spec.get(k, "")) for k in ("min", "max")),
    )


def _unknown_parameter(name: str, model: str | None, source: str) -> LimitsError:
    if model is not None:
        return LimitsError(
            f"{source}: unknown parameter {name!r} of model {model!r}; valid: {', '.join(PARAMETERS[model])}"
        )
    return LimitsError(
        f"{source}: unknown parameter or model {name!r} in [limits]; models: "
        f"{', '.join(PARAMETERS)}; parameters: "
        + "; ".join(f"{m}: {', '.join(p)}" for m, p in PARAMETERS.items())
    )


def parse_limits(doc: Any, source: str) -> tuple[Limit, ...]:
    if not isinstance(doc, dict):
        raise LimitsError(f"{source}: [limits] must be a table")
    out: list[Limit] = []
    for key, value in doc.items():
        if key in PARAMETERS:
            if not isinstance(value, dict):
                raise LimitsError(
                    f"{source}: [limits.{key}] must hold <parameter> = {{min = ..., max = ...}}"
                )
            for name, spec in value.items():
                if name not in PARAMETERS[key]:
                    raise _unknown_parameter(name, key, source)
                out.append(_limit(key, name, spec, source))
        elif key in MODEL_OF:
            out.append(_limit(MODEL_OF[key], key, value, source))
        else:
            raise _unknown_parameter(key, None, source)
    seen = set()
    for lim in out:
        if (lim.model, lim.parameter) in seen:
            raise LimitsError(f"{source}: two limits for {lim.model}.{lim.parameter}")
        seen.add((lim.model, lim.parameter))
    return tuple(out)


# models whose parameters the store's summary holds (robust_models names some of them)
ROBUST_MODELS = (*PARAMETERS, "field_fit")

OUTLIER_KEYS = {
    "z_threshold": float,
    "family_alpha": float,
    "spread_factor": float,
    "min_units": int,
    "robust_models": list,
    "scale_pool": str,
    "history_units": int,
    "history_below": int,
    "history_location": str,
}


def config_from_toml(text: str, source: str = "<config>") -> OutlierConfig:
    """The :class:`calib_core.outliers.OutlierConfig` of a TOML text (module docstring)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise LimitsError(f"{source}: not valid TOML ({exc})") from exc
    unknown = set(doc) - {"outliers", "limits"}
    if unknown:
        raise LimitsError(f"{source}: unknown section(s) {sorted(unknown)}; expected [outliers] and [limits]")
    opts = doc.get("outliers", {})
    if not isinstance(opts, dict) or set(opts) - set(OUTLIER_KEYS):
        bad = sorted(set(opts) - set(OUTLIER_KEYS)) if isinstance(opts, dict) else opts
        raise LimitsError(
            f"{source}: unknown key(s) {bad} in [outliers]; allowed: {', '.join(sorted(OUTLIER_KEYS))}"
        )
    kwargs: dict[str, Any] = {}
    for key, value in opts.items():
        want = OUTLIER_KEYS[key]
        try:
            if want is list:
                if not isinstance(value, list):
                    raise TypeError
                unknown_models = [m for m in value if m not in ROBUST_MODELS]
                if unknown_models or not value:
                    raise LimitsError(
                        f"{source}: [outliers] {key} = {value!r}: "
                        + (f"unknown model(s) {unknown_models}" if unknown_models else "no model")
                        + f"; known: {', '.join(ROBUST_MODELS)}"
                    )
                kwargs[key] = tuple(str(m) for m in value)
            elif want is str:
                kwargs[key] = str(value)
            elif isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError
            elif not math.isfinite(value):
                raise LimitsError(f"{source}: [outliers] {key} = {value!r} is not a finite number")
            else:
                kwargs[key] = want(value)
        except LimitsError:
            raise
        except (TypeError, ValueError):
            raise LimitsError(f"{source}: [outliers] {key} = {value!r} is not a {want.__name__}") from None
    kwargs["limits"] = parse_limits(doc.get("limits", {}), source)
    try:
        return OutlierConfig(**kwargs)
    except OutlierConfigError as exc:
        raise LimitsError(f"{source}: {exc}") from None


# --- a run's configuration: --config FILE, --config none, or the one the store keeps ----------------
CLEAR_CONFIG = "none"  # ``--config none``: forget the stored configuration, use the defaults


def load_config(path: str | Path | None) -> OutlierConfig:
    if not path or str(path) == CLEAR_CONFIG:
        return OutlierConfig()
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise FileNotFoundError(f"outlier configuration {p}: {exc.strerror}") from None
    return config_from_toml(text, source=str(p))


def resolve_config(store: ResultsStore, path: str | Path | None) -> tuple[OutlierConfig, str | None | bool]:
    """The QA configuration of a run and what to store under the lock: ``--config FILE``
    sets it for this and every later run (returned text), ``--config none`` clears it
    (None), no ``--config`` keeps the one stored (False: nothing to store). A stored text
    that no longer parses is an error naming the file."""
    if path is None:
        text = store.read_qa_config()
        if text is None:
            return OutlierConfig(), False
        return config_from_toml(text, source=str(store.qa_config_path)), False
    if str(path) == CLEAR_CONFIG:
        return OutlierConfig(), None
    cfg = load_config(path)
    return cfg, Path(path).read_text()


def save_config(store: ResultsStore, text: str | None | bool) -> None:
    """Store what :func:`resolve_config` returned (under the run's lock)."""
    if text is not False:
        store.write_qa_config(text)  # type: ignore[arg-type]
