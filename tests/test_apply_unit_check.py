"""``mimucal apply`` refuses another unit's raw file, whether its hive path (``unit=<id>``, the
dataset's key) or its metadata names the other unit, in one line (exit 2), unless ``--force``."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest

from flows.cli import main as cli_main
from flows.fleet_sim import simulate_fleet
from schemas.hive import hive_keys

RATE_HZ = 20.0


@pytest.fixture(scope="module")
def unit_a(tmp_path_factory):
    """Two simulated units; unit U0001's calibration file."""
    base = tmp_path_factory.mktemp("apply")
    simulate_fleet(base / "d", 1, 2, 1, seed=4, sample_rate_hz=RATE_HZ)
    cal = base / "U0001.json"
    assert (
        cli_main(["calibrate", str(base / "d"), "--unit", "U0001", "--no-discovery", "--json", str(cal)]) == 0
    )
    return base, cal


def apply(cal: Path, raw: Path, out: Path, *extra: str) -> int:
    return cli_main(["apply", str(cal), str(raw), str(out), *extra])


def test_hive_keys_read_the_layout_directories():
    assert hive_keys("/x/lot=L01/unit=U0002/rep=1/samples.parquet") == {
        "lot": "L01",
        "unit": "U0002",
        "rep": "1",
    }
    assert hive_keys("/x/unit=../samples.parquet") == {}  # not a valid id: no claim
    assert hive_keys("recording.csv") == {}


def test_another_units_file_is_refused_by_its_path_and_its_metadata(unit_a, tmp_path, capsys):
    base, cal = unit_a
    own = base / "d" / "lot=L01" / "unit=U0001" / "rep=1" / "samples.parquet"
    other = base / "d" / "lot=L01" / "unit=U0002" / "rep=1" / "samples.parquet"
    assert pq.read_schema(other).metadata[b"unit"] == b"U0002"

    assert apply(cal, own, tmp_path / "ok.parquet") == 0
    assert (tmp_path / "ok.parquet").exists()
    capsys.readouterr()

    # path and metadata both name U0002
    assert apply(cal, other, tmp_path / "b.parquet") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "hive path and metadata name unit 'U0002'" in err and "--force" in err
    assert not (tmp_path / "b.parquet").exists()

    # unit A's own samples copied under unit=U0002: the metadata says U0001, the path U0002
    moved = tmp_path / "lot=L01" / "unit=U0002" / "rep=1" / "samples.parquet"
    moved.parent.mkdir(parents=True)
    shutil.copy(own, moved)
    assert apply(cal, moved, tmp_path / "c.parquet") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "hive path names unit 'U0002'" in err and "'U0001'" in err

    # a CSV under another unit's directory: its path alone names the unit
    csv = moved.with_name("recording.csv")
    df = pd.read_parquet(own)
    names = {"gx": "gyr_x", "gy": "gyr_y", "gz": "gyr_z", "ax": "acc_x", "ay": "acc_y", "az": "acc_z"}
    df.rename(columns=names)[["t", *names.values()]].to_csv(csv, index=False)
    assert apply(cal, csv, tmp_path / "c.csv", "--accel-unit", "g") == 2
    assert "hive path names unit 'U0002'" in capsys.readouterr().err

    # --force: applied, with the warning
    assert apply(cal, moved, tmp_path / "f.parquet", "--force") == 0
    assert "warning" in capsys.readouterr().err and (tmp_path / "f.parquet").exists()
