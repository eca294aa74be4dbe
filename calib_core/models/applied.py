"""What makes a calibration method *applied*: its fit declares the catalogue effect whose
parameters it estimates, and :func:`calib_core.models.pipeline.calibration_from_unit` puts
the repetitions' mean of those parameters into the unit's :class:`Calibration` as a term
(``Calibration.apply`` subtracts it). A method that is only reported declares none of this.

An applied fit (a ``calib_core.results.FitResult`` with, as class attributes):

- ``applied_term``: the catalogue name of the effect (``calib_core.effects``);
- ``document_key``, ``document_unit``: its key and unit in the calibration file's
  ``repetitions`` and ``averaged`` sections (``schemas.unit_document``);
- ``applied_values()`` / ``applied_stderr()``: the effect's parameters in the catalogue's
  units, in the shape the calibration file shows them (raveled, the catalogue's order; NaN
  where the steps could not determine one), and their standard errors.

A term is applied only when every repetition has the fit and every parameter of the mean is
finite, and not when model discovery's joint fit already applies the same effect."""

from __future__ import annotations

from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class AppliedFit(Protocol):
    model: ClassVar[str]
    applied_term: ClassVar[str]
    document_key: ClassVar[str]
    document_unit: ClassVar[str]

    def applied_values(self) -> np.ndarray: ...

    def applied_stderr(self) -> np.ndarray: ...


def is_applied(fit: Any) -> bool:
    """Whether ``fit`` is the result of an applied method (it declares ``applied_term``)."""
    return isinstance(getattr(type(fit), "applied_term", None), str) and isinstance(fit, AppliedFit)


def applied_fits(fits: dict[str, Any]) -> dict[str, AppliedFit]:
    """The applied fits of one repetition, model name -> fit, in the fits' order."""
    return {m: f for m, f in fits.items() if is_applied(f)}
