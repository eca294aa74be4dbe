"""A new PREFECT_HOME gets a copy of the template database (flows.runtime.seed_prefect_home),
never over a database it has, and nothing when the template is absent or switched off; the
template is a consistent copy of the first new home's database once its server migrated it
(flows.runtime.save_prefect_template), made once. The template's worth is measured in
benchmarks/prefect_startup.py, not here; the whole path (a command's own server, the
template made, the runs recorded) is tests/test_prefect_command_server.py."""

from __future__ import annotations

import sqlite3

from flows import runtime


def test_a_new_home_gets_the_template_and_an_existing_database_is_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("MIMUCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MIMUCAL_PREFECT_TEMPLATE", raising=False)
    template = runtime.prefect_db_template()
    assert template is not None and template.parent == tmp_path / "cache"
    assert template.name.startswith("prefect-") and template.suffix == ".db"
    new = tmp_path / "new"
    new.mkdir()
    assert not runtime.seed_prefect_home(new)  # no template yet: left to the server
    assert not (new / runtime.PREFECT_DB).exists()
    template.parent.mkdir()
    template.write_bytes(b"migrated database")
    assert runtime.seed_prefect_home(new)
    assert (new / runtime.PREFECT_DB).read_bytes() == b"migrated database"
    assert [p.name for p in new.iterdir()] == [runtime.PREFECT_DB]  # no temp file left
    (new / runtime.PREFECT_DB).write_bytes(b"this home's runs")
    assert not runtime.seed_prefect_home(new)
    assert (new / runtime.PREFECT_DB).read_bytes() == b"this home's runs"
    off = tmp_path / "off"
    off.mkdir()
    monkeypatch.setenv("MIMUCAL_PREFECT_TEMPLATE", "off")
    assert not runtime.seed_prefect_home(off) and not any(off.iterdir())


def _live_wal_database(path):
    """A WAL-mode database with committed rows still in its write-ahead log and a writer
    holding it open, as the API server leaves its database."""
    con = sqlite3.connect(path)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA wal_autocheckpoint=0")  # the rows stay in the -wal file
    con.execute("CREATE TABLE alembic_version (version_num TEXT)")
    con.execute("INSERT INTO alembic_version VALUES ('head')")
    con.executemany("INSERT INTO alembic_version VALUES (?)", [(f"r{i}",) for i in range(50)])
    con.commit()
    return con


def test_the_template_is_a_consistent_copy_of_a_live_database_made_once(tmp_path):
    db = tmp_path / "home" / runtime.PREFECT_DB
    db.parent.mkdir()
    writer = _live_wal_database(db)
    try:
        assert (db.parent / (db.name + "-wal")).stat().st_size > 0
        template = tmp_path / "cache" / "prefect-x.db"
        assert runtime.save_prefect_template(db, template)
        copy = sqlite3.connect(template)
        assert copy.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        assert copy.execute("SELECT count(*) FROM alembic_version").fetchone() == (51,)
        copy.close()
        writer.execute("INSERT INTO alembic_version VALUES ('a flow run')")
        writer.commit()
        assert not runtime.save_prefect_template(db, template)  # the first template is kept
        copy = sqlite3.connect(template)
        assert copy.execute("SELECT count(*) FROM alembic_version").fetchone() == (51,)
        copy.close()
    finally:
        writer.close()
    assert [p.name for p in template.parent.iterdir()] == [template.name]  # no temp file left


def test_a_failed_template_copy_leaves_no_template(tmp_path):
    template = tmp_path / "cache" / "prefect-x.db"
    assert not runtime.save_prefect_template(tmp_path / "no-such.db", template)
    assert not template.parent.exists() or not any(template.parent.iterdir())
    not_sqlite = tmp_path / "home" / runtime.PREFECT_DB
    not_sqlite.parent.mkdir()
    not_sqlite.write_bytes(b"not a database" * 100)
    assert not runtime.save_prefect_template(not_sqlite, template)
    assert not any(template.parent.iterdir())


def test_only_a_new_home_without_template_is_kept_for_the_template(tmp_path, monkeypatch):
    monkeypatch.setenv("MIMUCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MIMUCAL_PREFECT_TEMPLATE", raising=False)
    monkeypatch.setattr(runtime, "_home_for_template", None)
    home = tmp_path / "home"
    home.mkdir()
    runtime._want_template(home)
    assert runtime._home_for_template == home
    monkeypatch.setattr(runtime, "_home_for_template", None)
    monkeypatch.setenv("MIMUCAL_PREFECT_TEMPLATE", "off")
    runtime._want_template(home)
    assert runtime._home_for_template is None
