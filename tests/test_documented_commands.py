"""Every command line the documentation shows parses: README.md, docs/*.md and the comments of conf/**/*.yaml.

Each ``spread-<command> ...`` line (backslash continuations joined, a trailing ``# comment`` cut, ``...``
and ``<placeholders>`` dropped) is parsed with Hydra's override grammar and composed against its command's
config (a sweep's comma list composes with its first value); ``spread-sweep`` lines go through its own parser.
For ``spread-ablate``, every element of the ``*.extra`` lists must itself be a valid override (the lists are
handed to the sub-commands). Nothing runs.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

from spread.configs import conf_dir

ROOT = Path(conf_dir()).parent
CONFIG = {"generate": "generate", "import": "import", "export": "export", "train": "train", "train-ray": "train",
          "sample": "sample", "evaluate": "evaluate", "ablate": "ablate", "compare": "compare", "report": "report"}
LINE = re.compile(r"(?:\.venv/bin/|\$\{program\} )?spread-([a-z-]+)((?:\s+\S.*)?)$")


def documented() -> list[tuple[str, str, str]]:
    """(where, command, arguments) of every documented command line."""
    found = []
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted(Path(conf_dir()).rglob("*.yaml"))]
    for path in files:
        text = path.read_text()
        lines = text.splitlines()
        if path.suffix == ".yaml":  # examples are indented comment lines ("#   spread-sample ..."), prose is not
            lines = [line.split("#", 1)[1] if re.match(r"\s*#\s{2,}", line) else "" for line in lines]
        else:  # the fenced code blocks of a Markdown file
            fenced, inside = [], False
            for line in lines:
                if line.lstrip().startswith("```"):
                    inside = not inside
                    line = ""
                fenced.append(line if inside else "")
            lines = fenced
        joined, buffer = [], ""
        for line in lines:
            if line.rstrip().endswith("\\"):
                buffer += line.rstrip()[:-1] + " "
                continue
            joined.append(buffer + line)
            buffer = ""
        for number, line in enumerate(joined, 1):
            line = re.split(r"\s{2,}#|\s#\s|&&|\|\s", line.strip().lstrip("$ "))[0].strip().strip("`")
            match = LINE.match(line)
            prose = re.search("[─│◄►▼]", line) or (match and match.group(2).strip() and "=" not in match.group(2))
            if match and match.group(1) in (*CONFIG, "sweep") and not prose:
                found.append((f"{path.relative_to(ROOT)}:{number}", match.group(1), match.group(2)))
    return found


COMMANDS = documented()


def arguments(raw: str) -> list[str]:
    raw = re.sub(r"<[^>\s]*>", "x", raw.replace("...", " ").replace("…", " "))
    raw = raw.replace("CKPT", "c.ckpt").replace("DIR", "/d").replace("A.ckpt", "a.ckpt").replace("B.ckpt", "b.ckpt")
    return [a for a in shlex.split(raw) if not a.startswith("-") and a not in ("job",)]


def test_the_docs_show_many_command_lines():
    commands = {c for _, c, _ in COMMANDS}
    assert len(COMMANDS) > 40 and {"sample", "ablate", "train", "sweep", "evaluate"} <= commands


def check_line(command: str, raw: str, compose) -> None:
    """Parse and compose one documented line (module docstring); raises on a line that does not parse."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    args = arguments(raw)
    if command == "train-ray":  # spread-train-ray adds its trainer (spread.cli.train_ray.with_default_trainer)
        args = ["trainer=ray", *args]
    if command == "sweep":
        from spread.experiments.sweep import parse_arguments

        parse_arguments(args)
        return
    parser = OverridesParser.create()
    overrides = parser.parse_overrides(args)  # the grammar: a bad line fails here, naming the input
    first = []
    for o in overrides:
        if o.is_sweep_override():
            value = next(iter(o.sweep_string_iterator())) if not o.is_interval_sweep() else o.value().start
            first.append(f"{o.get_key_element()}={value}")
        else:
            first.append(o.input_line)
    cfg = compose(config_name=CONFIG[command], overrides=first, return_hydra_config=True)
    if command == "ablate":
        from omegaconf import OmegaConf

        for key in ("train.extra", "sample.extra", "evaluate.extra", "data.extra"):
            parser.parse_overrides([str(x) for x in OmegaConf.select(cfg, key) or []])


def test_every_documented_command_line_parses():
    from hydra import compose, initialize_config_dir

    from spread.configs import register

    register()
    failures = []
    with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
        for where, command, raw in COMMANDS:
            launcher = re.search(r"hydra/launcher=(\w+)", raw)
            if launcher and not plugin(launcher.group(1)):
                continue  # an optional extra (pip install -e '.[launchers]')
            try:
                check_line(command, raw, compose)
            except Exception as exc:  # noqa: BLE001 - every failing line is listed
                failures.append(f"{where}: spread-{command}{raw}\n    {type(exc).__name__}: {str(exc).splitlines()[0]}")
    assert not failures, "\n".join(failures)


def plugin(name: str) -> bool:
    """Whether the Hydra launcher plugin behind conf/hydra/launcher/<name>.yaml is installed."""
    import importlib.util

    name = {"parallel": "joblib", "slurm": "submitit"}.get(name, name)
    try:
        return importlib.util.find_spec(f"hydra_plugins.hydra_{name}_launcher") is not None
    except ModuleNotFoundError:
        return False
