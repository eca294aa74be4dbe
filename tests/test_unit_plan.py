"""One plan over both kinds of reference (schemas.unit_plan): new, changed, appeared,
removed and unchanged units alike for turntable sessions and field recordings; a unit with
both kinds is calibrated from its turntable sessions; a field unit in two lots is refused;
the batches units are calibrated in."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import pytest

from calib_core.steps import SessionKey
from schemas.unit_plan import FIELD, TURNTABLE, make_batches, plan_unit_jobs


@dataclass
class Session:
    key: SessionKey
    path: Path
    fp: str
    kind: ClassVar[str] = TURNTABLE

    def content_fingerprint(self, cache=None) -> str:
        return self.fp


@dataclass
class Recording(Session):
    kind: ClassVar[str] = FIELD


def refs(cls, lot, unit, fps):
    return [cls(SessionKey(lot, unit, rep), Path(f"{lot}/{unit}/{rep}"), fp) for rep, fp in fps.items()]


def test_both_kinds_are_planned_by_one_rule():
    now = [
        *refs(Session, "L1", "T1", {1: "a", 2: "b"}),  # unchanged
        *refs(Session, "L1", "T2", {1: "a", 2: "x", 3: "c"}),  # rep 2 changed, rep 3 new
        *refs(Recording, "L1", "F1", {1: "a"}),  # recording 2 removed
        *refs(Recording, "L1", "F2", {1: "a", 2: "b"}),  # unchanged
        *refs(Recording, "L2", "F3", {1: "a"}),  # new
    ]
    previous = {
        ("L1", "T1", 1): "a",
        ("L1", "T1", 2): "b",
        ("L1", "T2", 1): "a",
        ("L1", "T2", 2): "b",
        ("L1", "F1", 1): "a",
        ("L1", "F1", 2): "b",
        ("L1", "F2", 1): "a",
        ("L1", "F2", 2): "b",
    }
    jobs, skipped, errors = plan_unit_jobs(now, previous)
    assert [(j.lot, j.unit, j.kind, j.reason) for j in jobs] == [
        ("L1", "F1", FIELD, "removed recording 2"),
        ("L1", "T2", TURNTABLE, "changed rep 2,3; new rep 3"),  # a new rep has no fingerprint yet
        ("L2", "F3", FIELD, "new"),
    ]
    assert skipped == [("L1", "F2"), ("L1", "T1")] and errors == []
    forced, skipped, _ = plan_unit_jobs(now, previous, force=True)
    assert len(forced) == 5 and not skipped and {j.reason for j in forced} == {"forced"}


def test_a_unit_is_calibrated_one_way_and_a_field_unit_belongs_to_one_lot():
    now = [
        *refs(Session, "L1", "U1", {1: "a"}),
        *refs(Recording, "L1", "U1", {1: "b"}),
        *refs(Recording, "L1", "U2", {1: "a"}),
        *refs(Recording, "L2", "U2", {1: "a"}),
    ]
    jobs, _, errors = plan_unit_jobs(now, {})
    assert [(j.unit, j.kind) for j in jobs] == [("U1", TURNTABLE)]
    msgs = [str(e) for e in errors]
    assert len(msgs) == 3  # U1's recording; U2 in L1 and in L2
    assert "turntable sessions (rep=N) and field recordings" in msgs[0]
    assert all("appears in lots L1, L2" in m for m in msgs[1:])


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 45, 50, 1000])
def test_batches_are_the_fewest_of_at_most_the_size_and_even(n):
    jobs = list(range(n))
    batches = make_batches(jobs, 8)
    assert [j for b in batches for j in b] == jobs  # every job once, in order
    assert len(batches) == -(-n // 8)
    sizes = [len(b) for b in batches]
    assert all(0 < s <= 8 for s in sizes) and (not sizes or max(sizes) - min(sizes) <= 1)
