"""The package layout (DESIGN §2): one package per stage, and imports only go down the floors.

Every module's imports are read from its source (function-level imports included, so a lazy import that
climbs is caught too); a module may import its own package and any package on a lower floor, never a
sibling on its floor or anything above.
"""

from __future__ import annotations

import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import spread

ROOT = Path(spread.__file__).parent

#: Top to bottom. A package imports only from floors below its own (and from itself).
FLOORS = (
    ("cli",),
    ("commands",),  # one module per command body; studies and sweeps get the commands they run injected
    ("experiments",),  # multi-run studies: the stage engine, ablation, comparison, sweep
    ("results",),  # results as a DataFrame (runs, sweeps, studies, an MLflow store) and the questions asked of it
    ("reporting",),  # the one table writer, plots, intervals, run folders read back, spread-report
    ("configs",),
    ("importers",),  # a dataset from another layout: uses procgen's dataset statistics and renders
    ("procgen", "training", "sampling", "evaluation"),
    ("tracking",),  # wandb, MLflow, CSV: which logger, and what each command logs there
    ("runtime",),
    ("guidance", "metrics", "methods", "export"),  # methods: the registry, every method and its checkpoint loading
    ("model",),
    ("data",),
    ("render",),
    ("physics", "relations", "box_geometry"),
    ("readonce",),  # per-process memo of checkpoints, libraries, scene files, hashes (read once)
    ("scene",),
    ("assets",),
    ("safe_load",),  # loaders that run no code: check their files with io's bounded-read helper
    ("io", "registry", "lazy", "checks"),  # lazy: a package's names imported on first access; checks: whole numbers
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
    bad.write_text("def f():\n    from spread.cli.train import main\n    import spread.experiments.ablation\n")
    assert [t for _, t in spread_imports(bad)] == ["cli", "experiments"]


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def module_graph() -> dict[str, set[str]]:
    """spread module → the spread modules it imports (function-level imports included); ``from p import x``
    counts as an import of ``p.x`` when that is a module, else of ``p``."""
    paths = {module_name(p): p for p in ROOT.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and node.module.startswith("spread"):
                subs = [f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in paths]
                targets = subs or [node.module]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names if a.name.startswith("spread")]
            edges |= {t for t in targets if t in paths and t != name}
        graph[name] = edges
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    import sys

    sys.setrecursionlimit(10_000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle_between_modules_function_level_imports_included():
    """No module imports (at any depth, inside functions too) a module that imports it back; a package's
    ``__init__`` re-exporting its modules counts only where one of them imports the package itself back."""
    graph = module_graph()
    # a module importing its own package's __init__ (which re-exports it) is a circle too: none is allowed
    found = circles(graph)
    assert not found, "import circles:\n" + "\n".join(" ↔ ".join(c) for c in found)


def test_the_circle_finder_finds_a_planted_circle_and_the_old_physics_one():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    graph = module_graph()
    graph["spread.physics.mjcf"].add("spread.physics.mujoco_world")  # the function-level import issue 22 found
    assert ["spread.physics.mjcf", "spread.physics.mujoco_world"] in circles(graph) or \
        any({"spread.physics.mjcf", "spread.physics.mujoco_world"} <= set(c) for c in circles(graph))


def test_a_packages_names_load_on_first_access_and_settings_load_without_the_heavy_libraries():
    """``spread.model``, ``spread.metrics`` and ``spread.evaluation`` import their public names when first asked
    (:mod:`spread.lazy`): the settings (the model's config, the evaluation protocol and its numbers, the sampler)
    load without diffusers or torchmetrics; every listed name resolves to its module's object, a submodule asked for
    as an attribute is imported (as the eager ``__init__`` did); an unknown name is an AttributeError naming it."""
    code = ("import sys; import spread.model.config, spread.evaluation.protocol, spread.metrics.constants, "
            "spread.model.diffusion; print(sorted(m for m in ('diffusers', 'torchmetrics', 'lightning') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
    for package in ("spread.model", "spread.metrics", "spread.evaluation"):
        module = importlib.import_module(package)
        for source, names in module._EXPORTS.items():
            for name in names:
                assert getattr(module, name) is getattr(importlib.import_module(source), name), (package, name)
                assert name in dir(module)
        with pytest.raises(AttributeError, match=rf"module '{package}' has no attribute 'no_such_name'"):
            getattr(module, "no_such_name")
    code = "import spread.metrics, spread.model; print(spread.metrics.support_distance.__name__, spread.model.ema.EMA)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.split()[0] == "spread.metrics.support_distance", out.stderr[-2000:]


@pytest.mark.parametrize("command,args,refusal", [
    ("train", ["nosuchkey=1"], "Could not override 'nosuchkey'"),
    ("sample", ["ckpt=a.ckpt", "data.root=d", "out_dir=o", "sampler.kind=nope"], "unknown sampler 'nope'"),
    ("sample", ["ckpt=a.ckpt", "data.root=d", "out_dir=o", "sampler.eta=2"], "sampler.eta=2.0: expected a number"),
    ("evaluate", ["nosuchkey=1"], "Could not override 'nosuchkey'"),
    ("ablate", ["nosuchkey=1"], "Could not override 'nosuchkey'"),
    ("compare", ["nosuchkey=1"], "Could not override 'nosuchkey'"),
    ("train", ["experiment=quick", "data.root=nodata"], "data.root=nodata: no scene files in nodata/train"),
    ("train_ray", ["experiment=quick", "data.root=nodata"], "data.root=nodata: no scene files in nodata/train"),
])
def test_a_command_refuses_a_bad_setting_before_torch_loads(tmp_path, command, args, refusal):
    """The settings a command composes and checks (its schema, the sampler, the evaluation config) are torch-free
    (:mod:`spread.model.sampler`), and a training command asks its data folder for scenes without torch
    (:mod:`spread.data.splits`), so a refused setting is refused in well under a second instead of after torch's
    ~3–10 s import; the refusal names the setting, exits 1 and writes nothing."""
    code = (f"import sys; sys.argv = ['spread-{command}', *{args!r}]\n"
            f"from spread.cli.{command} import main\n"
            "try:\n    main()\nexcept SystemExit as e:  # sys.exit(message): exit status 1, the message on stderr\n"
            "    code = 1 if isinstance(e.code, str) else e.code\n"
            "    print(e.code if isinstance(e.code, str) else '', file=sys.stderr)\n"
            "print('EXIT', code, 'torch' in sys.modules, 'diffusers' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}  # the one-line refusal a user sees
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         env=env)
    assert out.stdout.strip().splitlines()[-1:] == ["EXIT 1 False False"], out.stdout + out.stderr[-2000:]
    assert refusal in out.stderr, out.stderr[-2000:]
    assert not any(tmp_path.iterdir())
