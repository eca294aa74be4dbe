"""Hive layout discovery (good and bad directory names), fingerprints, and the writer's
round trip."""

from __future__ import annotations

import os

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey
from schemas.contract import SAMPLES_SCHEMA, STEPS_SCHEMA
from schemas.dataset import find_sessions, fingerprint
from schemas.errors import E_BAD_PATH
from schemas.reader import read_session
from schemas.writer import write_session

RATE = 20.0


def _session(seed=0, temperature=False):
    rng = np.random.default_rng(seed)
    truth = sim.typical_truth(rng, temperature=sim.TemperatureProfile() if temperature else None)
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2)
    samples = sim.simulate_session(truth, steps, rng, RATE)
    return steps, samples, sim.session_metadata(truth, RATE, operator="jd", turntable="T-7")


def _mkdirs(root, *paths):
    for p in paths:
        (root / p).mkdir(parents=True)


def test_find_sessions_good_and_bad_names(tmp_path):
    _mkdirs(
        tmp_path,
        "lot=L1/unit=U001/rep=1",
        "lot=L1/unit=U001/rep=2",
        "lot=L1/unit=U002/rep=10",
        "lot=L2/unit=U003/rep=1",
        "lot=L2/unit=U003/rep=0",  # rep must be >= 1
        "lot=L2/unit=U003/rep=01",  # leading zero would alias rep=1
        "lot=L2/unit=U003/rep=x",
        "lot=L2/unit=U 4/rep=1",  # space not allowed in an id
        "lot=L2/units=U005/rep=1",  # wrong key
        "batch=7/unit=U006/rep=1",
        "lot=L1/unit=U001/.rep=3.tmp",  # hidden: ignored
        "_staging/unit=U009/rep=1",
    )  # underscore: ignored
    (tmp_path / "fleet.json").write_text("{}")  # plain files are ignored
    refs, errors = find_sessions(tmp_path)
    assert [str(r.key) for r in refs] == [
        "lot=L1/unit=U001/rep=1",
        "lot=L1/unit=U001/rep=2",
        "lot=L1/unit=U002/rep=10",
        "lot=L2/unit=U003/rep=1",
    ]
    assert refs[2].path == tmp_path / "lot=L1/unit=U002/rep=10"
    assert all(e.code == E_BAD_PATH for e in errors)
    bad = {e.file: e for e in errors}
    assert set(bad) == {"rep=0", "rep=01", "rep=x", "unit=U 4", "units=U005", "batch=7"}
    assert "rep must be an integer >= 1" in str(bad["rep=0"])
    assert str(tmp_path / "lot=L2/unit=U003/rep=0") in str(bad["rep=0"])
    assert "must match [A-Za-z0-9][A-Za-z0-9_.-]*" in str(bad["unit=U 4"])
    assert "expected 'lot=<id>'" in str(bad["batch=7"])
    for e in errors:
        print(e)


def test_filters(tmp_path):
    _mkdirs(
        tmp_path,
        "lot=L1/unit=U001/rep=1",
        "lot=L1/unit=U002/rep=1",
        "lot=L2/unit=U003/rep=1",
        "lot=L2/unit=U003/rep=2",
    )
    refs, errors = find_sessions(tmp_path, unit="U003")
    assert [r.key for r in refs] == [SessionKey("L2", "U003", 1), SessionKey("L2", "U003", 2)]
    refs, _ = find_sessions(tmp_path, lot="L1")
    assert [r.key.unit for r in refs] == ["U001", "U002"]
    refs, errors = find_sessions(tmp_path, lot="L9")
    assert refs == [] and errors == []


def test_unit_in_two_lots_is_rejected(tmp_path):
    _mkdirs(tmp_path, "lot=L1/unit=U001/rep=1", "lot=L2/unit=U001/rep=1", "lot=L2/unit=U002/rep=1")
    refs, errors = find_sessions(tmp_path)
    assert [str(r.key) for r in refs] == ["lot=L2/unit=U002/rep=1"]
    assert len(errors) == 2 and all(e.code == E_BAD_PATH for e in errors)
    assert "unit 'U001' appears in lots L1, L2" in str(errors[0])
    # also when only one of the lots is asked for
    refs, errors = find_sessions(tmp_path, lot="L1")
    assert refs == [] and "appears in lots L1, L2" in str(errors[0])
    print(errors[0])


def test_missing_root(tmp_path):
    refs, errors = find_sessions(tmp_path / "nope")
    assert refs == [] and errors[0].code == E_BAD_PATH and "not a directory" in str(errors[0])


def test_fingerprint_is_content_touch_and_copy_keep_it_a_changed_value_does_not(tmp_path):
    import shutil

    steps, samples, md = _session()
    key = SessionKey("L1", "U001", 1)
    path = write_session(tmp_path / "a", key, steps, samples, md)
    before = fingerprint(path)
    refs, _ = find_sessions(tmp_path / "a")
    read_session(refs[0])
    assert fingerprint(path) == before
    st = os.stat(path / "samples.parquet")
    os.utime(path / "samples.parquet", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert fingerprint(path) == before  # touch: same content
    copy = tmp_path / "b" / path.relative_to(tmp_path / "a")
    shutil.copytree(path, copy)  # new inode and mtime, same bytes
    assert fingerprint(copy) == before
    changed = samples.copy()
    changed.loc[len(changed) // 2, "gx"] += 1e-3  # one value of one column
    other = write_session(tmp_path / "c", key, steps, changed, md)
    assert fingerprint(other) != before
    (path / "steps.parquet").unlink()
    assert fingerprint(path) != before


def test_write_read_round_trip(tmp_path):
    steps, samples, md = _session(seed=1, temperature=True)
    key = SessionKey("L7", "U123", 3)
    path = write_session(tmp_path, key, steps, samples, md)
    assert path == tmp_path / "lot=L7/unit=U123/rep=3"
    assert sorted(p.name for p in path.iterdir()) == ["samples.parquet", "steps.parquet"]  # no temp
    # the files are the contract's schemas (+ the optional columns)
    st = pq.read_schema(path / "steps.parquet")
    sa = pq.read_schema(path / "samples.parquet")
    assert st.names == STEPS_SCHEMA.names + ["duration_s"]
    for f in STEPS_SCHEMA:
        assert st.field(f.name).type == f.type
    assert sa.names == SAMPLES_SCHEMA.names + ["temp_c"]
    for f in SAMPLES_SCHEMA:
        assert sa.field(f.name).type == f.type
    assert sa.field("temp_c").type == pa.float32()
    assert {k.decode(): v.decode() for k, v in sa.metadata.items()} == md
    meta = pq.ParquetFile(path / "samples.parquet").metadata
    for i in range(meta.num_columns):
        col = meta.row_group(0).column(i)
        assert col.compression == "ZSTD" and not col.has_dictionary_page
    # and the reader gets the same data back
    data = read_session(next(iter(find_sessions(tmp_path)[0])))
    np.testing.assert_array_equal(data.step, samples["step"].to_numpy())
    np.testing.assert_array_equal(data.t, samples["t"].to_numpy())
    np.testing.assert_array_equal(data.gyro, samples[["gx", "gy", "gz"]].to_numpy(np.float64))
    np.testing.assert_array_equal(data.accel, samples[["ax", "ay", "az"]].to_numpy(np.float64))
    np.testing.assert_array_equal(data.temp_c, samples["temp_c"].to_numpy(np.float64))
    for c in STEPS_SCHEMA.names + ["duration_s"]:
        np.testing.assert_array_equal(data.steps[c].to_numpy(), steps[c].to_numpy())
    assert data.meta.provenance["operator"] == "jd"


def test_rewrite_replaces_atomically(tmp_path):
    steps, samples, md = _session(seed=2)
    key = SessionKey("L1", "U001", 1)
    write_session(tmp_path, key, steps, samples, md)
    path = write_session(tmp_path, key, steps, samples.iloc[:100], md)
    assert pq.read_metadata(path / "samples.parquet").num_rows == 100
    assert sorted(p.name for p in path.iterdir()) == ["samples.parquet", "steps.parquet"]


def test_writer_refuses_unknown_conversion(tmp_path):
    steps, samples, md = _session(seed=3)
    with pytest.raises(ValueError, match="cannot convert"):
        write_session(tmp_path, SessionKey("L1", "U1", 1), steps, samples, md, gyro_unit="LSB")
    assert not (tmp_path / "lot=L1").exists()


def _files_and_fingerprint_agree(path):
    from schemas.dataset import read_session_files

    files = read_session_files(path)
    assert files.fingerprint == fingerprint(path) and files.fingerprint.startswith("xxh3:")
    return files


def test_one_read_gives_the_fingerprint_of_the_bytes_it_hands_the_reader(tmp_path):
    from schemas.dataset import read_session_files

    steps, samples, md = _session(3)
    key = SessionKey("L1", "U001", 1)
    path = write_session(tmp_path, key, steps, samples, md)
    files = _files_and_fingerprint_agree(path)
    assert files.steps == (path / "steps.parquet").read_bytes()
    assert files.samples == (path / "samples.parquet").read_bytes()
    ref = find_sessions(tmp_path)[0][0]
    plain = read_session(ref)
    # the file rewritten after the read: the session calibrated is the bytes fingerprinted
    changed = samples.copy()
    changed["gx"] += 1.0
    write_session(tmp_path, key, steps, changed, md)
    assert fingerprint(path) != files.fingerprint
    from_bytes = read_session(ref, files)
    np.testing.assert_array_equal(from_bytes.channels, plain.channels)
    np.testing.assert_array_equal(from_bytes.t, plain.t)
    assert not np.array_equal(read_session(ref, read_session_files(path)).gyro, plain.gyro)
    # a missing, an empty and an unreadable file: not held, the same fingerprint both ways
    (path / "samples.parquet").write_bytes(b"")
    files = _files_and_fingerprint_agree(path)
    assert files.samples is None and files.steps is not None
    (path / "samples.parquet").unlink()
    files = _files_and_fingerprint_agree(path)
    assert files.samples is None
    (path / "samples.parquet").mkdir()
    assert _files_and_fingerprint_agree(path).samples is None


def test_a_file_too_large_to_hold_is_hashed_in_chunks_and_read_by_its_path(tmp_path, monkeypatch):
    from schemas import dataset

    steps, samples, md = _session(4)
    path = write_session(tmp_path, SessionKey("L1", "U001", 1), steps, samples, md)
    held = _files_and_fingerprint_agree(path)
    size = (path / "samples.parquet").stat().st_size
    assert (path / "steps.parquet").stat().st_size < size // 2
    monkeypatch.setattr(dataset, "MAX_HELD_BYTES", size // 2)
    files = _files_and_fingerprint_agree(path)
    assert files.samples is None and files.steps is not None
    assert files.fingerprint == held.fingerprint  # the same digest, streamed
    ref = find_sessions(tmp_path)[0][0]
    np.testing.assert_array_equal(read_session(ref, files).channels, read_session(ref, held).channels)


def test_digest_cache_recomputes_entries_of_the_earlier_scheme(tmp_path):
    from schemas.dataset import DigestCache
    from schemas.hive import DIGEST_SCHEME, file_digest

    p = tmp_path / "f.parquet"
    p.write_bytes(b"abc" * 1000)
    st = os.stat(p)
    key = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
    old = DigestCache({str(p): key + ["0" * 32]})  # a blake2b entry of the earlier code
    assert old.digest(str(p)) == file_digest(str(p)) != "0" * 32 and old.read == 1
    assert old.entries[str(p)] == key + [file_digest(str(p)), DIGEST_SCHEME]
    again = DigestCache(old.entries)
    assert again.digest(str(p)) == file_digest(str(p)) and again.read == 0
