"""The reports' structure: one builder signature for every section, unique section ids, and
no cache kept by hand (LotContext's views are functools.cached_property)."""

from __future__ import annotations

import inspect
from pathlib import Path

from reports.sections import LOT_SECTIONS, UNIT_SECTIONS

REPORTS = Path(__file__).resolve().parents[1] / "reports"


def test_every_section_builder_takes_ctx_page_unit():
    for s in [*LOT_SECTIONS, *UNIT_SECTIONS]:
        params = list(inspect.signature(s.build).parameters)
        assert params == ["ctx", "page", "unit"], (s.id, params)


def test_section_ids_are_unique_in_each_list():
    for sections in (LOT_SECTIONS, UNIT_SECTIONS):
        ids = [s.id for s in sections]
        assert len(ids) == len(set(ids)), ids


def test_no_module_of_reports_keeps_a_cache_in_an_instance_dict():
    found = [
        f"{p.relative_to(REPORTS)}:{i}"
        for p in sorted(REPORTS.rglob("*.py"))
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if "__dict__" in line
    ]
    assert len(list(REPORTS.rglob("*.py"))) > 10
    assert not found, found
