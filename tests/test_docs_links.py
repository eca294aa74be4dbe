"""Links between the docs, and the docs pages the code cites, point at files that exist.

A page that is merged or renamed leaves no dangling reference: every relative Markdown link
in README.md, BENCHMARKS.md and docs/*.md, and every ``docs/<page>.md`` named in the
Markdown or Python files of the repository, must resolve.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MD_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
DOCS_PAGE = re.compile(r"(?<![\w/.])docs/[\w.-]+\.md")
SKIP_DIRS = {".git", ".venv", "node_modules", "demo-output", ".pytest_cache"}


def _files(*patterns: str) -> list[Path]:
    out = []
    for pattern in patterns:
        for path in REPO.rglob(pattern):
            if not SKIP_DIRS.intersection(path.relative_to(REPO).parts):
                out.append(path)
    return sorted(out)


def dangling_links(pages: list[Path], repo: Path = REPO) -> list[str]:
    bad = []
    for page in pages:
        for target in MD_LINK.findall(page.read_text()):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:, file:
                continue
            if not (page.parent / target).exists():
                bad.append(f"{page.relative_to(repo)} links to {target}, which does not exist")
    return bad


def dangling_docs_pages(files: list[Path], repo: Path = REPO) -> list[str]:
    bad = []
    for path in files:
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for page in DOCS_PAGE.findall(line):
                if not (repo / page).exists():
                    bad.append(f"{path.relative_to(repo)}:{i} names {page}, which does not exist")
    return bad


def test_markdown_links_resolve():
    pages = [REPO / "README.md", REPO / "BENCHMARKS.md", *sorted((REPO / "docs").glob("*.md"))]
    problems = dangling_links([p for p in pages if p.exists()])
    assert not problems, "\n".join(problems)


def test_docs_pages_named_in_code_and_docs_exist():
    # this file names made-up pages on purpose (the check of the check below)
    files = [f for f in _files("*.py", "*.md") if f != Path(__file__).resolve()]
    problems = dangling_docs_pages(files)
    assert not problems, "\n".join(problems)


def test_a_dangling_link_and_page_name_are_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("[b](b.md) [web](https://x.org/y.md) [self](a.md#top)\n")
    (tmp_path / "code.py").write_text("# see docs/a.md and docs/gone.md\nX = 'mydocs/x.md'\n")
    assert dangling_links([tmp_path / "docs" / "a.md"], tmp_path) == [
        "docs/a.md links to b.md, which does not exist"
    ]
    assert dangling_docs_pages([tmp_path / "code.py"], tmp_path) == [
        "code.py:1 names docs/gone.md, which does not exist"
    ]
