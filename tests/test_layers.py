"""The import rules of docs/DESIGN.md's tree hold: every import statement of the shipped
packages (top-level, inside functions, under TYPE_CHECKING) goes where its room may import.

calib_core: the shared top-level modules import each other and the effect catalogue; the
catalogue nothing else; models the shared modules and the catalogue; sim also models (the
forms its truths are written in), its physics simulator nothing of calib_core; discovery also
sim; paper anything in calib_core. Nothing in calib_core imports schemas, flows or reports;
schemas imports only calib_core; reports only schemas and calib_core."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("calib_core", "schemas", "flows", "reports")

# room -> the rooms it may import (itself always; calib_core.sim covers calib_core.sim.physics;
# "calib_core.*": every room of calib_core)
ALLOWED = {
    "calib_core": {"calib_core.effects"},
    "calib_core.effects": set(),
    "calib_core.models": {"calib_core", "calib_core.effects"},
    "calib_core.sim": {"calib_core", "calib_core.effects", "calib_core.models"},
    "calib_core.sim.physics": set(),
    "calib_core.discovery": {"calib_core", "calib_core.effects", "calib_core.models", "calib_core.sim"},
    "calib_core.paper": {
        "calib_core",
        "calib_core.effects",
        "calib_core.models",
        "calib_core.sim",
        "calib_core.discovery",
    },
    "schemas": {"calib_core.*"},
    "reports": {"calib_core.*", "schemas"},
    "flows": {"calib_core.*", "schemas", "reports"},
}
SUBROOMS = (
    "calib_core.effects",
    "calib_core.models",
    "calib_core.sim",
    "calib_core.discovery",
    "calib_core.paper",
)


def may_import(own: str, other: str) -> bool:
    if other == own or (own, other) == ("calib_core.sim", "calib_core.sim.physics"):
        return True  # (the chamber runs of calib_core.sim.chamber are the physics simulator's)
    for allowed in ALLOWED[own]:
        if allowed == "calib_core.*" and other.split(".")[0] == "calib_core":
            return True
        if other == allowed or (allowed, other) == ("calib_core.sim", "calib_core.sim.physics"):
            return True
    return False


def room(module: str) -> str | None:
    """The room of a dotted module path (None: not one of the project's packages)."""
    if module == "calib_core.sim.physics":
        return module
    for sub in SUBROOMS:
        if module == sub or module.startswith(sub + "."):
            return sub
    top = module.split(".")[0]
    if top == "calib_core":
        return "calib_core"
    return top if top in PACKAGES else None


def imports_of(path: Path, module: str) -> list[tuple[int, str]]:
    """(line, imported module) of every import statement; ``from pkg import name`` counts as
    ``pkg.name`` when that is a module, else ``pkg``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against this module's package
                base = module.rsplit(".", node.level)[0]
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            for a in node.names:
                sub = f"{target}.{a.name}"
                is_module = (REPO / (sub.replace(".", "/") + ".py")).exists() or (
                    REPO / sub.replace(".", "/")
                ).is_dir()
                out.append((node.lineno, sub if is_module else target))
    return out


def violations(repo: Path = REPO) -> list[str]:
    found = []
    for pkg in PACKAGES:
        for path in sorted((repo / pkg).rglob("*.py")):
            rel = path.relative_to(repo).with_suffix("")
            module = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
            own = room(module)
            for line, target in imports_of(path, module):
                other = room(target)
                if other is None or may_import(own, other):
                    continue
                found.append(f"{path.relative_to(repo)}:{line} ({own}) imports {target} ({other})")
    return found


def test_every_import_goes_where_its_room_may_import():
    bad = violations()
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(
    "module, expected",
    [
        ("calib_core.steps", "calib_core"),
        ("calib_core.models.zhang2017.lever_arm", "calib_core.models"),
        ("calib_core.sim.physics", "calib_core.sim.physics"),
        ("calib_core.sim.simulator", "calib_core.sim"),
        ("calib_core.discovery", "calib_core.discovery"),
        ("flows.commands.plan", "flows"),
        ("numpy", None),
    ],
)
def test_rooms(module, expected):
    assert room(module) == expected


def test_a_forbidden_import_is_named(tmp_path):
    for d in ("calib_core/models", "calib_core/sim", "schemas", "flows", "reports"):
        (tmp_path / d).mkdir(parents=True)
        (tmp_path / d / "__init__.py").write_text("")
    (tmp_path / "calib_core" / "__init__.py").write_text("")
    (tmp_path / "calib_core" / "models" / "fit.py").write_text(
        "from calib_core.sim import simulator\n\ndef f():\n    import schemas.api\n"
    )
    bad = violations(tmp_path)
    assert [b.split(" (")[0] for b in bad] == ["calib_core/models/fit.py:1", "calib_core/models/fit.py:4"], (
        bad
    )
