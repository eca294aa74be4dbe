"""The nightly flow stores lot by lot (flows.nightly._run_batches), without Prefect: the task
is replaced by a thread pool, so what is checked is the bookkeeping: each lot is handed over
once, whole and sorted, as soon as its last unit is done; no more than ``max_in_flight``
batches are ever submitted and not consumed; a stored lot's results are not kept."""

from __future__ import annotations

import gc
import random
import threading
import time
import weakref
from concurrent.futures import ThreadPoolExecutor, as_completed

import pytest

from flows import runtime

runtime.ensure_environment()

from flows import nightly  # noqa: E402
from flows.unit_pipeline import UnitJob  # noqa: E402


class FakeResult:
    """Stands for a UnitResult (weak-referenceable, to see when it is freed)."""

    def __init__(self, lot: str, unit: str):
        self.lot, self.unit = lot, unit
        self.n_failed = 0
        self.payload = bytearray(10_000)


class FakeTask:
    """``calibrate_units_task`` on a thread pool; counts batches submitted and not consumed."""

    def __init__(self, pool: ThreadPoolExecutor, seed: int):
        self.pool = pool
        self.rng = random.Random(seed)
        self.lock = threading.Lock()
        self.outstanding = 0
        self.max_outstanding = 0

    def submit(self, jobs, run_discovery):
        delay = self.rng.uniform(0, 0.01)  # completions out of submission order
        with self.lock:
            self.outstanding += 1
            self.max_outstanding = max(self.max_outstanding, self.outstanding)
        fut = self.pool.submit(lambda: (time.sleep(delay), [FakeResult(j.lot, j.unit) for j in jobs])[1])
        original = fut.result

        def result(timeout=None):
            out = original(timeout)
            with self.lock:
                self.outstanding -= 1
            return out

        fut.result = result
        return fut


@pytest.mark.parametrize("batch_size,max_in_flight,seed", [(3, 4, 1), (1, 2, 2), (8, 1, 3)])
def test_lots_are_handed_over_whole_once_done_and_then_freed(monkeypatch, batch_size, max_in_flight, seed):
    per_lot = {"L01": 7, "L02": 5, "L03": 1, "L04": 9}
    jobs = [UnitJob(lot, f"U{lot[-1]}{i:02d}", [], "new") for lot, n in per_lot.items() for i in range(n)]
    with ThreadPoolExecutor(max_workers=2) as pool:
        fake = FakeTask(pool, seed)
        monkeypatch.setattr(nightly, "calibrate_units_task", fake)
        monkeypatch.setattr(nightly, "as_completed", as_completed)
        handed: list[tuple[str, list[str]]] = []
        progress: list[int] = []
        refs: dict[str, list[weakref.ref]] = {}
        units_done = []

        def on_progress(batch):
            progress.append(len(batch))
            units_done.extend(r.unit for r in batch)

        def on_lot(lot, results):
            # every unit of the lot is done; a lot is never handed over before its last unit
            assert {r.unit for r in results} == {j.unit for j in jobs if j.lot == lot}
            assert set(units_done) >= {r.unit for r in results}
            handed.append((lot, [r.unit for r in results]))
            refs[lot] = [weakref.ref(r) for r in results]

        nightly._run_batches(jobs, batch_size, False, on_progress, on_lot, max_in_flight)
    assert sorted(lot for lot, _ in handed) == sorted(per_lot)  # each lot once
    for lot, units in handed:
        assert units == sorted(j.unit for j in jobs if j.lot == lot)
    assert sum(progress) == len(jobs)
    assert fake.max_outstanding <= max_in_flight
    gc.collect()
    assert all(r() is None for rs in refs.values() for r in rs), "stored results still held"


def test_a_lot_is_stored_before_later_lots_finish_calibrating(monkeypatch):
    """With one batch in flight the lots are stored in order, each before the next lot's
    first batch completes: what bounds memory to one lot."""
    per_lot = {"L01": 4, "L02": 4, "L03": 4}
    jobs = [UnitJob(lot, f"U{lot[-1]}{i}", [], "new") for lot, n in per_lot.items() for i in range(n)]
    events = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        monkeypatch.setattr(nightly, "calibrate_units_task", FakeTask(pool, 0))
        monkeypatch.setattr(nightly, "as_completed", as_completed)
        nightly._run_batches(
            jobs,
            2,
            False,
            lambda b: events.append(("batch", b[0].lot)),
            lambda lot, rs: events.append(("store", lot)),
            max_in_flight=1,
        )
    assert events == [
        ("batch", "L01"),
        ("batch", "L01"),
        ("store", "L01"),
        ("batch", "L02"),
        ("batch", "L02"),
        ("store", "L02"),
        ("batch", "L03"),
        ("batch", "L03"),
        ("store", "L03"),
    ]
