"""`mimucal simulate` / flows.fleet_sim.simulate_fleet: layout, manifest, determinism,
outliers beyond the lot spread, bad sessions with their expected codes."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from flows.cli import main
from flows.fleet_sim import BAD_KINDS, UNIT_SPREAD, simulate_fleet
from schemas.averaging import read_step_means
from schemas.dataset import find_sessions
from schemas.errors import SessionError

from conftest import load_manifest

RATE = 20.0  # small rate: file-based tests stay fast


def short_protocol():
    return protocols.default_session(duration_s=1.0, settle_s=0.2, dynamic=False)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet")
    manifest = simulate_fleet(
        out,
        lots=2,
        units=3,
        reps=2,
        seed=5,
        sample_rate_hz=RATE,
        outliers=2,
        bad_sessions=5,
        protocol=short_protocol(),
    )
    return out, manifest


def test_layout_and_manifest(fleet):
    out, manifest = fleet
    assert load_manifest(out) == json.loads(json.dumps(manifest))
    refs, errors = find_sessions(out)
    assert errors == [] and len(refs) == 12
    assert [u["unit"] for u in manifest["units"]] == [f"U{i:04d}" for i in range(1, 7)]
    assert [u["lot"] for u in manifest["units"]] == ["L01"] * 3 + ["L02"] * 3
    for u in manifest["units"]:
        assert np.asarray(u["truth"]["K_g"]).shape == (3, 3)
        assert len(u["reps"]) == 2 and u["reps"][0]["path"] == f"lot={u['lot']}/unit={u['unit']}/rep=1"
    assert len(manifest["outliers"]) == 2 and len(manifest["bad_sessions"]) == 5


def test_bad_sessions_give_their_expected_code_and_the_rest_read(fleet):
    out, manifest = fleet
    expected = {b["session"]: b["expected_code"] for b in manifest["bad_sessions"]}
    assert {b["kind"] for b in manifest["bad_sessions"]} == set(BAD_KINDS)
    refs, _ = find_sessions(out)
    got, good = {}, 0
    for ref in refs:
        try:
            sm, warnings = read_step_means(ref)
            assert warnings == [] and len(sm) == len(short_protocol())
            good += 1
        except SessionError as exc:
            got[exc.session] = exc.code
    assert got == expected
    assert good == 12 - 5


def test_outliers_stand_out_of_the_lot_spread(fleet):
    _, manifest = fleet
    lots = manifest["lot_truth"]
    for u in manifest["units"]:
        lot = lots[u["lot"]]
        dk = np.asarray(u["truth"]["K_g"]) - np.asarray(lot["K_g"])
        dw = np.asarray(u["truth"]["w0"]) - np.asarray(lot["w0"])
        z = max(np.abs(np.diag(dk)).max() / UNIT_SPREAD["k_diag"], np.abs(dw).max() / UNIT_SPREAD["w0_dps"])
        if u["outlier"] is None:
            assert z < 5, u["unit"]
        else:
            param, shift = u["outlier"]["param"], u["outlier"]["shift"]
            value = {"k_g11": dk[0, 0], "w0_z": dw[2]}.get(param)
            if value is None:  # k_a22
                value = (np.asarray(u["truth"]["K_a"]) - np.asarray(lot["K_a"]))[1, 1]
            assert value == pytest.approx(shift, abs=5 * 0.003 if param != "w0_z" else 0.25)


def test_unit_spread_matches_the_population_model():
    """K_g diagonal sd 0.003 and off-diagonal sd 0.002 around the lot mean, w0 sd 0.05 deg/s."""
    from flows.fleet_sim import unit_truth

    lot_truth = sim.typical_truth(np.random.default_rng(0))
    rng = np.random.default_rng(1)
    units = [unit_truth(lot_truth, rng) for _ in range(400)]
    dk = np.array([u.K_g - lot_truth.K_g for u in units])
    off = ~np.eye(3, dtype=bool)
    assert np.std(dk[:, np.eye(3, dtype=bool)], ddof=1) == pytest.approx(0.003, rel=0.08)
    assert np.std(dk[:, off], ddof=1) == pytest.approx(0.002, rel=0.08)
    dw = np.array([u.w0 - lot_truth.w0 for u in units])
    assert np.std(dw, ddof=1) == pytest.approx(0.05, rel=0.08)
    assert units[0].gyro_bias_repeatability_dps == 0.01


def test_truth_factory_replaces_the_population(tmp_path):
    calls = []

    def factory(rng, lot, unit):
        calls.append((lot, unit))
        return sim.MimuTruth()

    steps = protocols.default_session(duration_s=0.5, settle_s=0.1, dynamic=False).iloc[:4]
    m = simulate_fleet(tmp_path, 2, 2, 1, seed=1, sample_rate_hz=10, protocol=steps, truth_factory=factory)
    assert calls == [("L01", "U0001"), ("L01", "U0002"), ("L02", "U0003"), ("L02", "U0004")]
    assert m["units"][3]["truth"]["K_g"] == np.eye(3).tolist()


def test_deterministic_for_a_seed(tmp_path):
    kw = dict(
        lots=1, units=2, reps=2, sample_rate_hz=RATE, outliers=1, bad_sessions=1, protocol=short_protocol()
    )
    a = simulate_fleet(tmp_path / "a", seed=9, **kw)
    b = simulate_fleet(tmp_path / "b", seed=9, **kw)
    c = simulate_fleet(tmp_path / "c", seed=10, **kw)
    assert a == b and a["units"] != c["units"]
    rel = "lot=L01/unit=U0002/rep=2/samples.parquet"
    bad = {x["session"] for x in a["bad_sessions"]}
    if "lot=L01/unit=U0002/rep=2" not in bad:
        assert pq.read_table(tmp_path / "a" / rel).equals(pq.read_table(tmp_path / "b" / rel))
        assert not pq.read_table(tmp_path / "a" / rel).equals(pq.read_table(tmp_path / "c" / rel))


def test_si_units_fleet_reads_like_deg_s(tmp_path):
    kw = dict(lots=1, units=1, reps=1, seed=4, sample_rate_hz=RATE, protocol=short_protocol())
    simulate_fleet(tmp_path / "deg", **kw)
    simulate_fleet(tmp_path / "si", gyro_unit="rad/s", accel_unit="m/s^2", **kw)
    a, _ = read_step_means(find_sessions(tmp_path / "deg")[0][0])
    b, _ = read_step_means(find_sessions(tmp_path / "si")[0][0])
    np.testing.assert_allclose(b.gyro, a.gyro, rtol=2e-7, atol=1e-6)
    np.testing.assert_allclose(b.accel, a.accel, rtol=2e-7, atol=1e-7)
    md = pq.read_schema(tmp_path / "si/lot=L01/unit=U0001/rep=1/samples.parquet").metadata
    assert md[b"gyro_unit"] == b"rad/s"


def test_cli_simulate(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = main(
        [
            "simulate",
            str(out),
            "--lots",
            "1",
            "--units",
            "2",
            "--reps",
            "1",
            "--seed",
            "3",
            "--rate",
            "10",
            "--outliers",
            "1",
            "--bad-sessions",
            "1",
            "--verification",
        ]
    )
    text = capsys.readouterr().out
    print(text)
    assert rc == 0
    # 118 production steps + the verification sweep: 15 x-rates, 15 y-rates, 17 z-rates
    assert "wrote 2 sessions (1 lot(s) x 2 unit(s) x 1 rep(s), 165 steps at 10 Hz" in text
    assert "outlier: lot=L01/unit=U" in text and "bad session: lot=L01/unit=U" in text
    manifest = load_manifest(out)
    assert manifest["verification"] and manifest["n_steps"] == 118 + 47
    # refuses to write over an existing dataset without --force
    rc = main(["simulate", str(out), "--units", "1", "--reps", "1", "--rate", "10"])
    assert rc == 2 and "already holds a dataset" in capsys.readouterr().err
    # --force replaces the simulated fleet: no stale unit U0002 left behind
    rc = main(["simulate", str(out), "--units", "1", "--reps", "1", "--rate", "10", "--force"])
    assert rc == 0
    assert [str(r.key) for r in find_sessions(out)[0]] == ["lot=L01/unit=U0001/rep=1"]
    # ... but never a dataset it did not simulate
    (out / "fleet.json").unlink()
    rc = main(["simulate", str(out), "--units", "1", "--reps", "1", "--rate", "10", "--force"])
    assert rc == 2 and "was not simulated" in capsys.readouterr().err


def test_cli_rejects_bad_counts(tmp_path, capsys):
    rc = main(["simulate", str(tmp_path / "x"), "--units", "1", "--reps", "1", "--outliers", "5"])
    assert rc == 2 and "outliers=5" in capsys.readouterr().err


def test_a_units_data_do_not_depend_on_the_fleet_size(tmp_path):
    kw = dict(
        lots=1,
        reps=1,
        seed=12,
        sample_rate_hz=10.0,
        protocol=protocols.default_session(duration_s=0.5, settle_s=0.1, dynamic=False),
    )
    small = simulate_fleet(tmp_path / "small", units=1, **kw)
    large = simulate_fleet(tmp_path / "large", units=3, **kw)
    assert small["units"][0] == large["units"][0]
    rel = "lot=L01/unit=U0001/rep=1/samples.parquet"
    assert pq.read_table(tmp_path / "small" / rel).equals(pq.read_table(tmp_path / "large" / rel))


def test_fits_on_the_files_recover_the_manifest_truth(tmp_path):
    """Files in rad/s and m/s^2 -> reader -> xu2016 fits: K_g and K_a equal the manifest's
    truth (inside units) within 5 standard errors."""
    from calib_core.models.xu2016 import fit_accel_multiposition, fit_gyro_multirate

    m = simulate_fleet(
        tmp_path,
        lots=1,
        units=2,
        reps=1,
        seed=8,
        sample_rate_hz=RATE,
        outliers=1,
        gyro_unit="rad/s",
        accel_unit="m/s^2",
        protocol=short_protocol(),
    )
    truth = {u["unit"]: u["truth"] for u in m["units"]}
    for ref in find_sessions(tmp_path)[0]:
        sm, _ = read_step_means(ref)
        g, a = fit_gyro_multirate(sm), fit_accel_multiposition(sm)
        z_g = (g.K - np.asarray(truth[ref.key.unit]["K_g"])) / g.K_stderr
        z_a = (a.K - np.asarray(truth[ref.key.unit]["K_a"])) / a.K_stderr
        assert np.abs(z_g).max() < 5 and np.abs(z_a).max() < 5, ref
