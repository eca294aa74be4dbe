"""A new PREFECT_HOME gets a copy of the template database (flows.runtime.seed_prefect_home),
never over a database it has, and nothing when the template is absent or switched off. The
template's worth is measured in benchmarks/prefect_startup.py, not here (building a real one
migrates a database: ~7 s CPU)."""

from __future__ import annotations

from flows import runtime


def test_a_new_home_gets_the_template_and_an_existing_database_is_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("MIMUCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MIMUCAL_PREFECT_TEMPLATE", raising=False)
    template = runtime.prefect_db_template()
    assert template is not None and template.parent == tmp_path / "cache"
    assert template.name.startswith("prefect-") and template.suffix == ".db"
    new = tmp_path / "new"
    new.mkdir()
    assert not runtime.seed_prefect_home(new)  # no template yet, none built: left to the server
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


def test_a_failed_template_build_leaves_the_home_to_the_server(tmp_path, monkeypatch):
    monkeypatch.setenv("MIMUCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MIMUCAL_PREFECT_TEMPLATE", raising=False)
    monkeypatch.setattr(runtime, "_BUILD_TEMPLATE", "raise SystemExit(3)")
    home = tmp_path / "home"
    home.mkdir()
    assert not runtime.seed_prefect_home(home, build=True)
    assert not any(home.iterdir()) and not runtime.prefect_db_template().exists()
