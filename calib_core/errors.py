"""Numerical failures of the estimators. The caller (schemas/flows) attaches the session."""

from __future__ import annotations


class DesignError(ValueError):
    """The steps available cannot determine the model (rank-deficient or too few equations).

    ``code`` is stable and machine-readable; ``undetermined`` names what cannot be estimated.
    """

    def __init__(self, code: str, reason: str, undetermined: tuple[str, ...] = ()):
        super().__init__(reason)
        self.code = code
        self.reason = reason
        self.undetermined = undetermined
