"""The plan of a run: which units to calibrate and why, over both kinds of reference a unit
can have (turntable sessions, :class:`schemas.dataset.SessionRef`; field recordings,
:class:`schemas.field_dataset.FieldRecordingRef`).

A reference declares its ``kind`` (the unit pipeline that calibrates it) and its
``content_fingerprint``; a unit is calibrated when it is new, when a reference's fingerprint
changed, appeared or disappeared against the store's, or when forced, and skipped otherwise;
a stored fingerprint of an earlier digest scheme recalibrates its unit once, with a reason
that says so (:data:`SCHEME_CHANGED`).
A unit is calibrated one way: when it has turntable sessions, its field recordings are left
out (a path error says so); a unit of field recordings found in two lots is refused."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Protocol

from calib_core.steps import SessionKey
from schemas.dataset import SessionRef
from schemas.errors import E_BAD_PATH, SessionError
from schemas.field_dataset import FieldRecordingRef, find_field_recordings
from schemas.hive import DIGEST_SCHEME, fingerprint_scheme

TURNTABLE, FIELD = SessionRef.kind, FieldRecordingRef.kind
# what one reference of each kind is called in a job's reason
_REFERENCE_NOUN = {TURNTABLE: "rep", FIELD: "recording"}


class UnitReference(Protocol):
    """What the plan needs of a reference (a turntable session or a field recording)."""

    key: SessionKey
    path: Path
    kind: ClassVar[str]

    def content_fingerprint(self, cache=None) -> str: ...


def _calibrated_one_way(r: UnitReference) -> SessionError:
    return SessionError(
        E_BAD_PATH,
        str(r.key),
        r.path.name,
        f"unit {r.key.unit!r} has turntable sessions (rep=N) and field recordings; "
        "a unit is calibrated one way: the field recordings are not used",
    )


@dataclass
class UnitJob:
    """One unit to calibrate: its references (all of one kind) and why it is (re)calibrated
    (new, changed, forced, rerun). ``kind`` names the unit pipeline that runs it."""

    lot: str
    unit: str
    refs: list
    reason: str
    kind: str = TURNTABLE
    follow_symlinks: bool = False  # its noise recordings may be symbolic links (schemas.noise_dataset)


# the reason of a unit whose stored fingerprints are of an earlier digest scheme
# (schemas.hive.fingerprint_scheme): its references are read and calibrated once more
SCHEME_CHANGED = "content fingerprint scheme changed: recalibrated once"


def _older_scheme(stored: str | None, now: str) -> bool:
    """Whether ``stored`` is a fingerprint of an earlier scheme than ``now``'s."""
    was = fingerprint_scheme(stored)
    return was is not None and fingerprint_scheme(now) == DIGEST_SCHEME and was != DIGEST_SCHEME


def plan_unit_jobs(
    refs: list[UnitReference],
    previous: dict[tuple[str, str, int], str],
    force: bool = False,
    cache=None,
) -> tuple[list[UnitJob], list[tuple[str, str]], list[SessionError]]:
    """(units to calibrate, sorted by lot and unit; units skipped because every reference's
    fingerprint is unchanged and none appeared or disappeared; the references refused).
    ``previous``: the store's fingerprints, (lot, unit, rep) -> fingerprint. ``cache``: a
    schemas.dataset.DigestCache for the turntable sessions' digests."""
    errors: list[SessionError] = []
    turntable_units = {r.key.unit for r in refs if r.kind == TURNTABLE}
    by_unit: dict[tuple[str, str, str], list[UnitReference]] = {}
    for r in refs:
        if r.kind != TURNTABLE and r.key.unit in turntable_units:
            errors.append(_calibrated_one_way(r))
            continue
        by_unit.setdefault((r.key.lot, r.key.unit, r.kind), []).append(r)
    lots_of: dict[tuple[str, str], set[str]] = {}
    for lot, u, kind in by_unit:
        lots_of.setdefault((u, kind), set()).add(lot)
    prev_reps: dict[tuple[str, str], set[int]] = {}
    for lot, unit, rep in previous:
        prev_reps.setdefault((lot, unit), set()).add(rep)
    jobs, skipped = [], []
    for (lot, unit, kind), rs in sorted(by_unit.items()):
        lots = lots_of[(unit, kind)]
        if kind == FIELD and len(lots) > 1:
            errors.append(
                SessionError(
                    E_BAD_PATH,
                    f"{lot}/{unit}",
                    "field",
                    f"unit {unit!r} appears in lots {', '.join(sorted(lots))}; a unit belongs to one lot",
                )
            )
            continue
        rs = sorted(rs, key=lambda r: r.key.rep)
        if force:
            jobs.append(UnitJob(lot, unit, rs, "forced", kind))
            continue
        before = prev_reps.get((lot, unit))
        if before is None:
            jobs.append(UnitJob(lot, unit, rs, "new", kind))
            continue
        reps_now = {r.key.rep for r in rs}
        changed, rescheme = [], False
        for r in rs:
            stored, now = previous.get((lot, unit, r.key.rep)), r.content_fingerprint(cache)
            if stored == now:
                continue
            if _older_scheme(stored, now):  # no telling whether its bytes changed too
                rescheme = True
            else:
                changed.append(r.key.rep)
        if changed or rescheme or reps_now != before:
            noun = _REFERENCE_NOUN.get(kind, "rep")
            why = []
            if rescheme:
                why.append(SCHEME_CHANGED)
            if changed:
                why.append(f"changed {noun} " + ",".join(map(str, changed)))
            if reps_now - before:
                why.append(f"new {noun} " + ",".join(map(str, sorted(reps_now - before))))
            if before - reps_now:
                why.append(f"removed {noun} " + ",".join(map(str, sorted(before - reps_now))))
            jobs.append(UnitJob(lot, unit, rs, "; ".join(why), kind))
        else:
            skipped.append((lot, unit))
    return jobs, skipped, errors


def plan_units(
    refs: list[SessionRef], previous: dict[tuple[str, str, int], str], force: bool = False, cache=None
) -> tuple[list[UnitJob], list[tuple[str, str]]]:
    """:func:`plan_unit_jobs` of turntable sessions: (units to calibrate, units skipped)."""
    jobs, skipped, _ = plan_unit_jobs(refs, previous, force, cache)
    return jobs, skipped


def plan_field_units(
    dataset: str | Path,
    previous: dict[tuple[str, str, int], str],
    force: bool = False,
    turntable_units: set[str] | frozenset[str] = frozenset(),
    unit: str | None = None,
    follow_symlinks: bool = False,
) -> tuple[list[UnitJob], list[tuple[str, str]], list]:
    """The field recordings of ``dataset`` found and planned (:func:`plan_unit_jobs`): units
    to calibrate, units skipped, path errors; a unit in ``turntable_units`` is calibrated from
    its turntable sessions, its field recordings are refused."""
    refs, errors = find_field_recordings(dataset, unit=unit, follow_symlinks=follow_symlinks)
    kept = []
    for r in refs:
        if r.key.unit in turntable_units:
            errors.append(_calibrated_one_way(r))
        else:
            kept.append(r)
    jobs, skipped, refused = plan_unit_jobs(kept, previous, force)
    return jobs, skipped, [*errors, *refused]


def make_batches(jobs: list, batch_size: int) -> list[list]:
    """``jobs`` in order, cut into the fewest batches of at most ``batch_size``, their sizes
    differing by at most one: 45 units in batches of 8 are 8, 8, 8, 7, 7, 7 (23 and 22 units
    for two workers) rather than five of 8 and one of 5 (24 and 21)."""
    batch_size = max(1, int(batch_size))
    n_batches = -(-len(jobs) // batch_size)
    if n_batches == 0:
        return []
    size, extra = divmod(len(jobs), n_batches)
    out, start = [], 0
    for i in range(n_batches):
        end = start + size + (i < extra)
        out.append(jobs[start:end])
        start = end
    return out
