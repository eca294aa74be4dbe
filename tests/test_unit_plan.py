"""One plan over both kinds of reference (schemas.unit_plan): new, changed, appeared,
removed and unchanged units alike for turntable sessions and field recordings; a unit with
both kinds is calibrated from its turntable sessions; a field unit in two lots is refused;
the batches units are calibrated in."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
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


def _blake2b_fingerprint(path: Path) -> str:
    """A session's fingerprint as the earlier scheme made it (blake2b of each file, the
    names, sizes and digests under a SHA-256 cut to 32 hex digits): what an older store holds."""
    import hashlib

    h = hashlib.sha256()
    for name in ("steps.parquet", "samples.parquet"):
        data = (path / name).read_bytes()
        h.update(f"{name}:{len(data)}:{hashlib.blake2b(data, digest_size=16).hexdigest()};".encode())
    return h.hexdigest()[:32]


def test_a_store_of_the_earlier_fingerprint_scheme_recalibrates_each_unit_once_and_says_why(tmp_path):
    from calib_core.sim import protocols
    from calib_core.sim import simulator as sim
    from schemas.dataset import DigestCache, find_sessions
    from schemas.results_store import ResultsStore
    from schemas.unit_plan import SCHEME_CHANGED
    from schemas.writer import write_session

    rng = np.random.default_rng(5)
    truth = sim.typical_truth(rng)
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2)
    md = sim.session_metadata(truth, 20.0)
    for unit in ("U1", "U2", "U3"):
        for rep in (1, 2):
            samples = sim.simulate_session(truth, steps, rng, 20.0)
            write_session(tmp_path / "data", SessionKey("L1", unit, rep), steps, samples, md)
    refs, _ = find_sessions(tmp_path / "data")
    # U1 and U2 stored by the earlier code (U2's rep 2 rewritten since), U3 by this code
    by_key = {(r.key.unit, r.key.rep): r for r in refs}
    old = {k: _blake2b_fingerprint(r.path) for k, r in by_key.items()}
    stored = {k: old[k] for k in old if k[0] != "U3"}
    stored |= {k: by_key[k].content_fingerprint() for k in by_key if k[0] == "U3"}
    stored[("U2", 2)] = "0" * 32  # of the earlier scheme and of other bytes: no telling
    store = ResultsStore(tmp_path / "results")
    store.write("sessions", _sessions_table(stored))
    # the digest cache of the earlier code: five items per file, a blake2b digest
    files = [str(r.path / n) for r in refs for n in ("steps.parquet", "samples.parquet")]
    cache = DigestCache({f: [*_stat_key(f), "0" * 32] for f in files})
    jobs, skipped, _ = plan_unit_jobs(refs, store.fingerprints(), cache=cache)
    assert [(j.unit, j.reason) for j in jobs] == [("U1", SCHEME_CHANGED), ("U2", SCHEME_CHANGED)]
    assert skipped == [("L1", "U3")] and cache.read == 12  # every old entry computed again
    # once the units are stored with this scheme's fingerprints, nothing is left to do
    store.write("sessions", _sessions_table({k: r.content_fingerprint() for k, r in by_key.items()}))
    jobs, skipped, _ = plan_unit_jobs(refs, store.fingerprints(), cache=cache)
    assert jobs == [] and len(skipped) == 3 and cache.read == 12


def _sessions_table(fingerprints: dict):
    import pandas as pd

    rows = [(u, rep, fp) for (u, rep), fp in fingerprints.items()]
    return pd.DataFrame(rows, columns=["unit", "rep", "fingerprint"]).assign(lot="L1", status="ok")


def _stat_key(path: str) -> list[int]:
    st = os.stat(path)
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
