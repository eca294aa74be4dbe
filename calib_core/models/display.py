"""How a calibration method's results are shown, declared by the method itself.

Each method module declares a :class:`ModelDisplay` per model name its fits carry and
registers it with :func:`register_display`: the heading of its per-unit table, its heading in
the lot's key-parameter table and strip plots (key models only), the order of its parameters,
and the symbol of each parameter (``k_g11`` is k with subscript g11). The unit of each
parameter is the one its :class:`calib_core.results.Param` carries (the store's
``unit_of_measure``). The reports read these declarations and nothing else about a model; a
model without one is shown under its name, its parameters sorted.

Titles are display text that may hold ``<sub>`` markup (the reports write them as given).
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable
from dataclasses import dataclass, field

MATRIX = tuple(f"{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))  # the nine elements of a 3x3


@dataclass(frozen=True)
class ModelDisplay:
    """The display facts of one model (the ``model`` name its fits carry).

    ``rank`` orders the models in a unit's tables and in the key-parameter table (lower
    first; equal ranks by name). ``key_title``: its heading in the lot's key-parameter table
    and strip plots, or None when the model is not a key model. ``symbols``: parameter name
    -> (letter, subscript), e.g. ``"w0_x": ("ω", "0x")``; a parameter without one is shown by
    its name."""

    model: str
    title: str
    param_order: tuple[str, ...]
    rank: int = 100
    key_title: str | None = None
    symbols: dict[str, tuple[str, str]] = field(default_factory=dict)


_DISPLAYS: dict[str, ModelDisplay] = {}  # in display order
_LOADED: list[bool] = []  # the declaring modules imported

# The modules that declare the shipped methods' displays (imported on first use, so that a
# report needs no import of the fitting code beyond these). A new method's module registers
# itself when calib_core.models.pipeline imports it (its OPTIONAL_FITS line).
_DECLARING_MODULES = (
    "calib_core.models.xu2016",
    "calib_core.models.zhang2017",
    "calib_core.models.pipeline",
)


def register_display(display: ModelDisplay) -> ModelDisplay:
    """Declare how ``display.model`` is shown (a second declaration of a model replaces the
    first)."""
    _DISPLAYS[display.model] = display
    ordered = sorted(_DISPLAYS.values(), key=lambda d: (d.rank, d.model))
    _DISPLAYS.clear()
    _DISPLAYS.update((d.model, d) for d in ordered)
    return display


def displays() -> dict[str, ModelDisplay]:
    """Every declared model display, in the order of :func:`ordered_models`."""
    if not _LOADED:
        for name in _DECLARING_MODULES:
            importlib.import_module(name)
        _LOADED.append(True)
    return _DISPLAYS


def display_of(model: str) -> ModelDisplay | None:
    return displays().get(str(model))


def model_title(model: str) -> str:
    """The heading of a model's per-unit table (its name when it declares none)."""
    d = display_of(model)
    return d.title if d is not None else str(model)


def key_models() -> list[tuple[str, str]]:
    """(model, heading) of the models in the lot's key-parameter table, in order."""
    return [(m, d.key_title) for m, d in displays().items() if d.key_title is not None]


def param_orders() -> dict[str, list[str]]:
    """Model -> its parameters in display order."""
    return {m: list(d.param_order) for m, d in displays().items()}


def ordered_params(model: str, names: Iterable[str]) -> list[str]:
    """``names`` in the model's declared order, the undeclared ones after, sorted."""
    names = list(dict.fromkeys(str(n) for n in names))
    d = display_of(model)
    order = list(d.param_order) if d is not None else []
    known = [n for n in order if n in names]
    return known + sorted(n for n in names if n not in order)


def ordered_models(models: Iterable[str]) -> list[str]:
    """``models`` in the declared ranks, the undeclared ones after, sorted."""
    models = list(dict.fromkeys(str(m) for m in models))
    first = list(displays())
    return [m for m in first if m in models] + sorted(m for m in models if m not in first)


def param_symbol(name: str) -> tuple[str, str] | None:
    """(letter, subscript) of a parameter name as any model declares it, None when none
    does (the same name means the same symbol in every model)."""
    n = str(name)
    for d in displays().values():
        if n in d.symbols:
            return d.symbols[n]
    return None


def matrix_symbols(prefix: str) -> dict[str, tuple[str, str]]:
    """``k_g11`` -> ("k", "g11") for the nine elements of a matrix named ``prefix`` (k_g)."""
    letter, sub = prefix.split("_", 1)
    return {f"{prefix}{m}": (letter, f"{sub}{m}") for m in MATRIX}


def vector_symbols(prefix: str, letter: str, sub: str) -> dict[str, tuple[str, str]]:
    """``w0_x`` -> ("ω", "0x") for the three components of a vector named ``prefix`` (w0_)."""
    return {f"{prefix}{a}": (letter, f"{sub}{a}") for a in "xyz"}
