"""The package layout (DESIGN §2): one package per stage, and imports only go down the floors.

Every module's imports are read from its source (function-level imports included, so a lazy import that
climbs is caught too); a module may import its own package and any package on a lower floor, never a
sibling on its floor or anything above.
"""

from __future__ import annotations

import ast
from pathlib import Path

import spread

ROOT = Path(spread.__file__).parent

#: Top to bottom. A package imports only from floors below its own (and from itself).
FLOORS = (
    ("cli",),
    ("experiments",),
    ("configs",),
    ("importers",),  # a dataset from another layout: uses procgen's dataset statistics and renders
    ("procgen", "training", "sampling", "evaluation"),
    ("runtime",),
    ("guidance", "metrics", "baselines", "export"),
    ("model",),
    ("data",),
    ("render",),
    ("physics", "relations"),
    ("scene",),
    ("assets",),
    ("safe_load",),  # loaders that run no code: check their files with io's bounded-read helper
    ("io",),
)
FLOOR = {name: i for i, names in enumerate(FLOORS) for name in names}


def top_package(path: Path) -> str:
    rel = path.relative_to(ROOT)
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def spread_imports(path: Path) -> list[tuple[int, str]]:
    """(line, first component below ``spread``) of every ``spread.*`` import in the file."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = []
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names] if node.module == "spread" \
                else [node.module]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] == "spread" and len(parts) > 1 and parts[1] != "__version__":
                out.append((node.lineno, parts[1]))
    return out


def modules():
    return sorted(p for p in ROOT.rglob("*.py") if p.name != "__init__.py" or p.parent != ROOT)


def test_every_package_has_a_floor():
    packages = {top_package(p) for p in modules()}
    assert packages <= set(FLOOR), f"packages without a floor in DESIGN §2: {sorted(packages - set(FLOOR))}"


def test_no_import_climbs_or_crosses_a_floor():
    offences = []
    for path in modules():
        here = top_package(path)
        for line, target in spread_imports(path):
            if target == here:
                continue
            if target not in FLOOR:
                offences.append(f"{path.relative_to(ROOT)}:{line} imports unknown spread.{target}")
            elif FLOOR[target] <= FLOOR[here]:
                offences.append(f"{path.relative_to(ROOT)}:{line} ({here}) imports spread.{target} "
                                f"({'the same floor' if FLOOR[target] == FLOOR[here] else 'a floor above'})")
    assert not offences, "\n".join(offences)


def test_the_checker_sees_a_climbing_import(tmp_path):
    """The check itself: a lazy import inside a function that climbs is found."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from spread.cli.train import main\n    import spread.experiments.commands\n")
    assert [t for _, t in spread_imports(bad)] == ["cli", "experiments"]
