"""A step whose content contradicts its reference although it decodes (issue 19, item 1):
compared with the same step in the unit's other repetitions, left out with
``W_INCONSISTENT_STEP``, counted toward ``E_TOO_MANY_STEPS_LOST``; and the damaged-bytes
corpus on a samples file written without page checksums."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from calib_core.guards import CONSISTENCY_Z_LIMIT, inconsistent_steps
from calib_core.models.pipeline import calibrate_repetition
from calib_core.sim import protocols
from calib_core.sim.physics import Turntable, typical_physics_unit
from calib_core.sim.simulator import REALISTIC_NOISE, simulate_unit, typical_truth
from flows import unit_pipeline
from flows.fleet_sim import simulate_fleet
from schemas import errors as E
from schemas.averaging import leave_out_inconsistent_steps
from schemas.dataset import find_sessions
from schemas.errors import SessionError
from schemas.physics_sessions import physics_unit_step_means

STEPS = protocols.default_session()


def _project_unit(seed: int, reps: int):
    rng = np.random.default_rng(seed)
    return simulate_unit(replace(typical_truth(rng), **REALISTIC_NOISE), STEPS, rng, n_reps=reps)[0]


def _physics_unit(seed: int, reps: int):
    """A clean physics-simulator unit with what the xu2016 model leaves out: lever arms up to
    12 mm, accelerometer and gyro nonlinearity, g-sensitivity, a tilted table axis."""
    rng = np.random.default_rng(seed)
    unit = typical_physics_unit(rng)
    unit = replace(
        unit,
        accels=tuple(
            replace(a, position_mm=tuple(rng.uniform(-12, 12, 3)), k2=rng.normal(0, 1e-4))
            for a in unit.accels
        ),
        gyros=tuple(
            replace(g, k3=rng.normal(0, 1e-10), g_sens=tuple(rng.normal(0, 0.01, 3)), random_walk=0.002)
            for g in unit.gyros
        ),
    )
    table = Turntable(axis_tilt_deg=float(rng.uniform(0, 1)), rate_scale_error=float(rng.normal(0, 1e-4)))
    return physics_unit_step_means(unit, STEPS, rng, n_reps=reps, rate_hz=50.0, table=table)


@pytest.mark.parametrize("reps", [2, 3, 5])
def test_clean_units_lose_no_step(reps):
    """No clean unit of either simulator loses a step (measured on 1,000 project-simulator
    and 300 physics-simulator units per repetition count: largest robust z 10.8, limit 15,
    tools/step_consistency_figures.py; here a sample of them)."""
    for seed in range(12):
        assert inconsistent_steps(_project_unit(seed, reps)) == []
    for seed in range(2):
        assert inconsistent_steps(_physics_unit(100 + seed, reps)) == []


def _damage(sm, step: int, channel: int, delta: float):
    """A copy of ``sm`` whose step ``step`` mean is moved by ``delta`` on ``channel`` (0-5)."""
    i = int(np.flatnonzero(sm.step == step)[0])
    gyro, accel = sm.gyro.copy(), sm.accel.copy()
    (gyro if channel < 3 else accel)[i, channel % 3] += delta
    return replace(sm, gyro=gyro, accel=accel)


def test_a_damaged_step_is_left_out_and_the_fit_redone_without_it():
    sms = _physics_unit(7, 3)  # lever arms: the session's own fit residuals are large here
    step = int(sms[1].step[np.flatnonzero(sms[1].test == "multiposition")[3]])
    bad = _damage(sms[1], step, 4, 0.005)  # ay + 5 mg: inside the range, ~25x the step noise
    out = leave_out_inconsistent_steps([(sms[0], []), (bad, []), (sms[2], [])])
    assert out[0][1] == [] and out[2][1] == []  # the clean repetitions keep every step
    kept, warns = out[1]
    assert [(w.code, w.step, w.column) for w in warns] == [(E.W_INCONSISTENT_STEP, step, "ay")]
    assert f"lot=PHYS/unit=U000/rep=2: step {step} (multiposition" in warns[0].message
    assert "ay differs from the same step in the unit's other repetitions by +0.005" in warns[0].message
    assert step not in kept.step and len(kept) == len(bad) - 1
    # the fit without the step is the clean session's fit without it, and the damage mattered
    clean_without = calibrate_repetition(sms[1].select(sms[1].step != step)).calibration.fits["accel"]
    redone = calibrate_repetition(kept).calibration.fits["accel"]
    with_damage = calibrate_repetition(bad).calibration.fits["accel"]
    clean = calibrate_repetition(sms[1]).calibration.fits["accel"]
    np.testing.assert_array_equal(redone.K, clean_without.K)
    np.testing.assert_array_equal(redone.f0, clean_without.f0)
    assert np.abs(with_damage.f0 - clean.f0).max() > 5 * np.abs(redone.f0 - clean.f0).max()


def test_a_high_rate_gyro_step_damaged_by_one_percent_is_caught():
    sms = _physics_unit(8, 5)
    i = int(np.argmax(np.abs(sms[0].rate_dps)))
    step, rate = int(sms[0].step[i]), float(abs(sms[0].rate_dps[i]))
    axis = int(np.argmax(np.abs(sms[0].w_ref[i])))
    found = inconsistent_steps([sms[0], sms[1], sms[2], _damage(sms[3], step, axis, 0.01 * rate), sms[4]])
    assert [(d.index, d.step, d.channel) for d in found] == [(3, step, ("gx", "gy", "gz")[axis])]
    assert abs(found[0].z) > CONSISTENCY_Z_LIMIT


def test_two_repetitions_cannot_tell_which_is_wrong_so_both_lose_the_step():
    sms = _project_unit(3, 2)
    step = int(sms[0].step[5])
    out = leave_out_inconsistent_steps([(sms[0], []), (_damage(sms[1], step, 0, 5.0), [])])
    for sm, warns in out:
        assert [(w.code, w.step) for w in warns] == [(E.W_INCONSISTENT_STEP, step)]
        assert "two repetitions cannot tell which is wrong" in warns[0].message
        assert step not in sm.step


def test_one_repetition_has_nothing_to_compare_with():
    sm = _project_unit(4, 1)[0]
    assert inconsistent_steps([_damage(sm, int(sm.step[5]), 0, 5.0)]) == []


def test_inconsistent_steps_count_toward_too_many_steps_lost():
    sms = _project_unit(5, 3)
    n = len(sms[0])
    bad = sms[2]
    for step in sms[2].step[:7]:  # 7 of 118 = 5.9 %, more than the 5 % allowed
        bad = _damage(bad, int(step), 3, 0.05)
    out = leave_out_inconsistent_steps([(sms[0], []), (sms[1], []), (bad, [])])
    assert isinstance(out[2], SessionError) and out[2].code == E.E_TOO_MANY_STEPS_LOST
    assert f"7 of {n} steps left out (7 W_INCONSISTENT_STEP), more than the 5% allowed" in str(out[2])
    # 5 of 118 (4.2 %) are allowed: the session is used without them
    bad = sms[2]
    for step in sms[2].step[:5]:
        bad = _damage(bad, int(step), 3, 0.05)
    sm, warns = leave_out_inconsistent_steps([(sms[0], []), (sms[1], []), (bad, [])])[2]
    assert len(warns) == 5 and len(sm) == n - 5


# --- damaged bytes in a file without page checksums -----------------------------------------------
def _chunks(path: Path) -> list[tuple[str, int, int]]:
    md = pq.ParquetFile(path).metadata
    return [
        (
            md.row_group(g).column(c).path_in_schema,
            md.row_group(g).column(c).data_page_offset,
            md.row_group(g).column(c).total_compressed_size,
        )
        for g in range(md.num_row_groups)
        for c in range(md.num_columns)
    ]


def _damaged(original: bytes, start: int, size: int, how: str, where: float) -> bytes:
    b = bytearray(original)
    if how == "flip":  # 4 bytes XORed: the page usually still decompresses and decodes
        for p in start + int(size * where) + np.arange(4):
            b[p] ^= 0x5A
    else:  # 16 zero bytes
        at = start + int(size * where * 2 / 3)
        b[at : at + 16] = bytes(16)
    return bytes(b)


@pytest.mark.slow
def test_damaged_sensor_bytes_without_checksums_never_enter_the_unit_unflagged(tmp_path):
    """Each of the six sensor column chunks of repetition 1 (of 3), damaged at three places in
    two ways (36 files, written without page checksums): the session fails, or it is warned
    with the damaged steps named and left out, and what it then gives the unit's mean is
    within the fit's noise (measured: at most 2.2 standard errors from the clean session's
    fit, the loss of the left-out steps included). The other repetitions stay ``ok``."""
    simulate_fleet(tmp_path / "d", 1, 1, 3, seed=11, sample_rate_hz=20.0)
    refs = sorted(find_sessions(tmp_path / "d")[0], key=lambda r: r.key.rep)
    victim = refs[0]
    table = pq.read_table(victim.samples_path)
    pq.write_table(table, victim.samples_path, compression="zstd", use_dictionary=False)
    original = victim.samples_path.read_bytes()
    clean = unit_pipeline.calibrate_sessions(refs)
    assert [o.status for o in clean] == ["ok"] * 3
    ref = {(p.model, p.name): p for p in clean[0].calibration.parameters() if p.model in ("gyro", "accel")}
    outcomes = {}
    for name, start, size in _chunks(victim.samples_path)[2:]:
        for how in ("flip", "zero"):
            for where in (0.25, 0.5, 0.75):
                victim.samples_path.write_bytes(_damaged(original, start, size, how, where))
                out = unit_pipeline.calibrate_sessions(refs)
                assert [o.status for o in out[1:]] == ["ok", "ok"]
                o = out[0]
                outcomes[(name, how, where)] = o.code or "+".join(
                    sorted({w[1:].split("]")[0] for w in o.warnings})
                )
                if o.status == "failed":
                    continue
                assert o.status == "warned" and o.warnings, (name, how, where)
                shift = max(
                    abs(p.value - ref[(p.model, p.name)].value) / ref[(p.model, p.name)].stderr
                    for p in o.calibration.parameters()
                    if (p.model, p.name) in ref
                )
                assert shift < 3.0, (name, how, where, shift, o.warnings)
    codes = set(outcomes.values())
    assert "W_INCONSISTENT_STEP" in codes  # values damaged inside the range are caught
    assert codes & {E.E_NONFINITE_VALUE, E.E_TOO_MANY_STEPS_LOST}


# --- NumPy floating-point errors ------------------------------------------------------------------
def test_numeric_events_are_recorded_per_thread_and_deliberate_ignores_stay_ignored():
    import threading
    import warnings

    from calib_core.guards import NumericEvents

    seen: dict[str, NumericEvents] = {}

    def work(name: str, overflow: bool) -> None:
        with NumericEvents() as events:
            if overflow:
                np.array([1e200]) * np.array([1e200])
            with np.errstate(invalid="ignore"):  # a NaN comparison the code means
                np.array([np.inf]) - np.array([np.inf])
        seen[name] = events

    threads = [threading.Thread(target=work, args=(n, n == "a")) for n in ("a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen["a"].counts == {"overflow": 1} and str(seen["a"]) == "overflow (1 operation)"
    assert not seen["b"]
    with warnings.catch_warnings():  # outside the block NumPy's own setting is back
        warnings.simplefilter("error")
        with pytest.raises(RuntimeWarning):
            np.array([1e200]) * np.array([1e200])
