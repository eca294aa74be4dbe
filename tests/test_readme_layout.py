"""The README's layout table cannot go stale: every package has a row, every path it names exists.

The table is the ``| path | what |`` table under ``## Layout``. A row's path is a directory
(``calib_core/sim/``) or a file; a package row covers the modules in it, so adding a module
needs no README change, adding a package needs its row. Paths named in a row's text in
backticks (``steps.py``, ``paper/``) are read relative to the row's path, or relative to
the repository when they contain a ``/`` before their end (``flows/cli.py``); each must exist.
Packages are the directories with an ``__init__.py`` under the packages the wheel ships
(``[tool.setuptools.packages.find] include`` in pyproject.toml).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# a backticked token that names a file or directory: ends in .py, .md, .sh, .toml or /
PATH_TOKEN = re.compile(r"`([A-Za-z0-9_./-]+(?:\.py|\.md|\.sh|\.toml|/))`")


def layout_rows(readme: str) -> dict[str, str]:
    """``{path: text}`` of the table under ``## Layout`` (the first table of that section)."""
    section = re.search(r"^## Layout\n(.*?)(?=^## |\Z)", readme, re.M | re.S)
    if section is None:
        raise AssertionError("README.md has no '## Layout' section")
    rows: dict[str, str] = {}
    for line in section.group(1).splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 2 or not line.lstrip().startswith("|"):
            continue
        m = re.fullmatch(r"`([^`]+)`", cells[0])
        if m is None:  # the header and the |---| line
            continue
        if m.group(1) in rows:
            raise AssertionError(f"README layout table: two rows for {m.group(1)}")
        rows[m.group(1)] = "|".join(cells[1:])
    if not rows:
        raise AssertionError("README.md's '## Layout' section has no '| `path` | what |' rows")
    return rows


def shipped_packages(repo: Path) -> list[str]:
    """Every package of the wheel, as ``dir/sub/`` paths relative to the repository."""
    find = tomllib.loads((repo / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    tops = [pattern.rstrip("*") for pattern in find["include"]]
    found = []
    for top in tops:
        for init in sorted((repo / top).rglob("__init__.py")):
            found.append(init.parent.relative_to(repo).as_posix() + "/")
    return found


def named_paths(row_path: str, text: str) -> list[str]:
    """The paths a row's text names, relative to the repository."""
    base = row_path if row_path.endswith("/") else str(Path(row_path).parent) + "/"
    out = []
    for token in PATH_TOKEN.findall(text):
        out.append(token if "/" in token.rstrip("/") else base + token)
    return out


def layout_problems(repo: Path) -> list[str]:
    rows = layout_rows((repo / "README.md").read_text())
    problems = []
    for pkg in shipped_packages(repo):
        if pkg not in rows:
            problems.append(
                f"package {pkg} has no row in README.md's layout table (add '| `{pkg}` | what lives there |')"
            )
    for path, text in rows.items():
        if not (repo / path).exists():
            problems.append(f"README.md's layout table has a row for {path}, which does not exist")
        if not text.strip():
            problems.append(f"README.md's layout row for {path} says nothing")
        for named in named_paths(path, text):
            if not (repo / named).exists():
                problems.append(f"README.md's layout row for {path} names {named}, which does not exist")
    return problems


def test_readme_layout_table_matches_the_tree():
    problems = layout_problems(REPO)
    assert not problems, "\n".join(problems)


# --- the check itself, on a made-up repository -------------------------------------------------
def _tree(tmp_path: Path, layout: str) -> Path:
    (tmp_path / "pyproject.toml").write_text(
        '[tool.setuptools.packages.find]\ninclude = ["core*", "flows*"]\n'
    )
    for pkg in ("core", "core/sim", "flows"):
        (tmp_path / pkg).mkdir(parents=True)
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "core" / "steps.py").write_text("")
    (tmp_path / "flows" / "cli.py").write_text("")
    (tmp_path / "README.md").write_text(
        f"# x\n\n## Layout\n\n| path | what |\n|---|---|\n{layout}\n"
        "\n## Next\n\n| `other/` | not the layout table |\n"
    )
    return tmp_path


GOOD = (
    "| `core/` | numerics: `steps.py`, simulation in `sim/` |\n"
    "| `core/sim/` | simulators |\n"
    "| `flows/` | flows, the CLI (`flows/cli.py`) |"
)


def test_a_complete_table_passes(tmp_path):
    assert layout_problems(_tree(tmp_path, GOOD)) == []


@pytest.mark.parametrize(
    "layout, expected",
    [
        (GOOD.replace("| `core/sim/` | simulators |\n", ""), "package core/sim/ has no row"),
        (GOOD + "\n| `core/old/` | gone |", "row for core/old/, which does not exist"),
        (GOOD.replace("`steps.py`", "`stepz.py`"), "names core/stepz.py, which does not exist"),
        (GOOD.replace("`flows/cli.py`", "`flows/main.py`"), "names flows/main.py, which does not exist"),
        (GOOD.replace("| simulators |", "|  |"), "row for core/sim/ says nothing"),
    ],
)
def test_a_stale_table_is_named(tmp_path, layout, expected):
    problems = layout_problems(_tree(tmp_path, layout))
    assert len(problems) == 1 and expected in problems[0], problems


def test_rows_outside_the_layout_section_are_ignored(tmp_path):
    # the '## Next' section's row for other/ (which does not exist) is not read
    assert "other/" not in layout_rows(_tree(tmp_path, GOOD).joinpath("README.md").read_text())
