"""A unit's noise model in the nightly (docs/noise.md): measured by
:func:`schemas.unit_noise.measure_unit_noise` on its recordings or static steps, kept on
the unit's outcome (``outcome.noise``) for the store's ``noise`` tables and the calibration
file. Orchestration only; never raises on bad data: a bad recording becomes a note naming
it, and the unit keeps its calibration."""

from __future__ import annotations

from pathlib import Path

from calib_core.noise_fleet import UnitNoise


def apply_noise(unit_out, unit_dir: Path | None, follow_symlinks: bool = False) -> str | None:
    """Set ``unit_out.noise`` (a calibrated unit's measured noise); returns a note (problems,
    recordings refused) or None."""
    from schemas.unit_noise import measure_unit_noise

    if unit_out.applied is None or unit_dir is None:
        return None
    good = [(s.key, s.path) for s in unit_out.sessions if s.succeeded]
    # the static steps the unit pipeline kept from its read of each session (no second read)
    kept = {s.key: s.static_steps for s in unit_out.sessions if s.succeeded and s.static_steps is not None}
    noise, notes = measure_unit_noise(
        unit_dir, unit_out.lot, unit_out.unit, unit_out.applied, good, follow_symlinks, static=kept
    )
    unit_out.noise = noise
    return "; ".join(notes) or None


def unit_noise_of(ur) -> UnitNoise | None:
    """The measured noise of a unit's result (None: not measured)."""
    return getattr(getattr(ur, "outcome", None), "noise", None)
