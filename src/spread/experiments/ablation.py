"""``spread-ablate``: the ablation table (DESIGN §3 variants, §6 protocol) as resumable stages.

The ablation is a sequence of the platform's own commands, run in this process through a
:class:`Commands` object (:class:`spread.experiments.commands.InProcessCommands`: ``spread-generate``,
``-train``, ``-sample`` and ``-evaluate``'s library functions); each stage is exactly one command with its Hydra overrides, printed as
the equivalent command line. The stages, under ``out_dir``:

| stage | command | folder | finished when |
|---|---|---|---|
| ``data`` (only when ``data.root`` is not given or does not exist) | spread-generate | ``data/`` | ``manifest.json`` |
| ``train/<v>``, v = base, geometry (unless given) | spread-train | ``train/<v>/`` | ``metrics.json``, ``last.ckpt`` |
| ``sample/<v>``, v = base, geometry, guidance, guidance_collision / _gravity / _relation | spread-sample | ``samples/<v>/`` | ``sampling.json``, all scenes |
| ``evaluate/<v>`` | spread-evaluate | ``eval/<v>/`` | ``metrics.json`` |
| ``figures`` (``figures: true``) | — | ``ablation_<v>.png``, ``ablation_truth.png`` | the PNGs |
| ``table`` | — | ``ablation.{md,csv,tex,png}`` (+ wandb table) | the four files |

**Figures**: one scene per row — the first test graph that every row sampled — as the paper shows scenes: a
3D view with its category legend beside the relation matrix against the graph
(:func:`spread.render.scene_card_figure`), and the graph's ground-truth room the same way; ``ablation.md``
links them under the table. **Intervals**: every metric cell is value ± half the width of its 95 % bootstrap
interval over scenes (:mod:`spread.experiments.intervals`); the CSV keeps the bounds and the bootstrap's seed.

``guidance`` samples the ``geometry`` checkpoint with guidance, ``guidance_<term>`` with that one term of it
(the other two weights 0: collision only, gravity only, relation only); all rows sample the same split's
graphs with the same seed and are evaluated with the same protocol (one override list for all).

**Resume.** Every output above is written atomically at the end of its command, so it exists only for a
finished stage. ``out_dir/ablation.json`` (the ledger) records each finished stage's inputs: for a sampling
stage the identity of the run its overrides compose to (:func:`spread.runtime.fingerprint.point_identity`:
checkpoint hash, data content, sampler, seed, every acting guidance term's weight and setting, ...), for an
evaluation stage the protocol's identity and the fingerprint of the scenes it reads, for data and training
stages their overrides, for the table its rows. Whether a stage is done is decided by the platform's one
done-check (:func:`spread.runtime.fingerprint.done_check`). A re-run skips a stage
whose outputs exist and whose inputs are unchanged; a stage with missing outputs runs again and continues
what is there (the commands resume themselves: training from ``last.ckpt``, sampling and evaluation skip
finished scenes); a sampling or evaluation stage whose inputs changed (e.g. a retrained checkpoint) is
redone from scratch; a training or data stage whose settings changed is refused (delete its folder). A
sampling, evaluation, figures or table stage whose outputs exist but that the ledger does not know is never
re-used on existence alone: its command runs and re-uses or redoes the folder by its own fingerprint
(``sampling.json``, ``protocol.json``). A failing stage is reported and blocks only the stages that need it;
the table is still written.

**Concurrency.** The rows' sample → evaluate chains are independent: with ``max_concurrent`` > 1 they run as
Ray tasks, that many at a time (:mod:`spread.experiments.stage_pool`; the ledger entries carry each stage's
``started_at`` / ``ended_at``); ``max_concurrent: 1`` runs them one after another in this process. Training
stages run before them, in this process or as their own processes through ``train.launcher``
(:mod:`spread.experiments.launch`).
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol, Sequence

from spread.experiments.intervals import ci_columns, row_intervals, table_note
from spread.guidance.config import GuidanceConfig
from spread.experiments.tables import Column, columns_of, write_tables
from spread.io import read_json, write_json_atomic
from spread.runtime.ray import RaySettings

log = logging.getLogger("spread.ablate")

#: One built-in guidance term at a time (the other built-in weights 0): row name → the term kept.
TERMS = {f"guidance_{term}": term for term in GuidanceConfig.weight_keys()}
VARIANTS = ("base", "geometry", "guidance", *TERMS)
#: Row labels, as in the paper's ablation table.
LABELS = {"base": "Ours (base)", "geometry": "+Geometry", "guidance": "+Guidance",
          **{v: f"+Guidance ({t} only)" for v, t in TERMS.items()}}
#: The checkpoint each row samples.
CHECKPOINT_OF = {"base": "base", "geometry": "geometry", "guidance": "geometry", **{v: "geometry" for v in TERMS}}
LEDGER = "ablation.json"
TABLE = "ablation"


class Commands(Protocol):
    """The platform's commands, run in-process; each takes the Hydra overrides of its ``conf/<name>.yaml``."""

    def generate(self, overrides: list[str]) -> None: ...

    def train(self, overrides: list[str], run_dir: Path) -> None: ...

    def sample(self, overrides: list[str]) -> None: ...

    def evaluate(self, overrides: list[str]) -> dict: ...


class StageError(RuntimeError):
    """A stage that cannot run as configured; the message names its folder."""


@dataclass
class StagesSpec:
    """What an ablation or a comparison shares (:class:`AblationSpec`, :class:`~spread.experiments.compare.CompareSpec`).
    Override lists are Hydra overrides of the sub-commands' configs; ``ckpt``: trained row → a given checkpoint
    (no training); ``data_root``: None → generate into ``out_dir/data``; ``group``: wandb group of every stage's
    run (``experiment_name=<group>``; "" leaves each command's); ``max_concurrent``: rows' sample → evaluate
    chains at a time (Ray tasks when > 1, on ``ray``: None, a local Ray session)."""

    out_dir: Path
    data_root: Path | None = None
    split: str = "test"
    generate: list[str] = field(default_factory=list)
    train: list[str] = field(default_factory=list)
    ckpt: dict[str, str | None] = field(default_factory=dict)
    sample: list[str] = field(default_factory=list)
    evaluate: list[str] = field(default_factory=list)
    title: str = ""
    group: str = ""
    max_concurrent: int = 1
    ray: RaySettings | None = None

    def named(self, overrides: list[str]) -> list[str]:
        """``overrides`` with the wandb group first (so a list can still set its own)."""
        return ([f"experiment_name={self.group}"] if self.group else []) + list(overrides)

    def __post_init__(self) -> None:
        self.out_dir = Path(self.out_dir)
        if int(self.max_concurrent) < 1:
            raise ValueError(f"max_concurrent={self.max_concurrent}: at least 1")

    def check_given(self, trained: list[str], method_of: Callable[[str], dict], note: str = "") -> None:
        """Every given checkpoint names a trained row (``note`` says more when not), exists, and is that row's
        kind of model (``method_of(row)``: :func:`spread.safe_load.expect_checkpoint`'s keywords) — one line
        before any stage runs."""
        from spread.safe_load import expect_checkpoint

        for row, path in self.ckpt.items():
            if row not in trained:
                raise ValueError(f"train.ckpt.{row}: only {trained} are trained{note}")
            if path and not Path(path).is_file():
                raise FileNotFoundError(f"train.ckpt.{row}={path}: no such checkpoint file")
            if path:
                expect_checkpoint(path, f"train.ckpt.{row}", **method_of(row))

    @property
    def dataset(self) -> Path:
        return Path(self.data_root) if self.data_root else self.out_dir / "data"


@dataclass
class AblationSpec(StagesSpec):
    """An ablation (:class:`StagesSpec`, ``conf/ablate.yaml`` documents each list): its rows (``variants``),
    each trained row's own training list, the guidance rows' guidance list, and the row figures."""

    variants: tuple[str, ...] = ("base", "geometry", "guidance")  # conf/ablate.yaml adds the one-term rows
    train_variant: dict[str, list[str]] = field(default_factory=dict)
    guidance: list[str] = field(default_factory=list)
    figures: bool = True  # one scene per row in 3D with its relation matrix (ablation_<v>.png)

    def __post_init__(self) -> None:
        super().__post_init__()
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown or not self.variants:
            raise ValueError(f"variants: unknown or none {unknown or list(self.variants)} "
                             f"(choose from {list(VARIANTS)})")
        self.variants = tuple(v for v in VARIANTS if v in self.variants)
        self.check_given(["base", "geometry"], lambda v: {"method": "spread", "variant": v})


@dataclass
class Stage:
    """One command run. ``inputs``: what its outputs depend on (compared with the ledger); ``derived``: when
    the inputs changed, redo it from scratch (else refuse); ``complete``: extra check beyond ``outputs``;
    ``exclusive``: it holds Ray actors while it waits for more (sampling with ``workers`` > 0), so concurrent
    rows run such stages one at a time (:mod:`spread.experiments.stage_pool`)."""

    name: str
    folder: Path
    outputs: list[Path]
    inputs: dict
    run: Callable[[bool], object]
    derived: bool = True
    complete: Callable[[], bool] | None = None
    exclusive: bool = False

    def finished(self) -> bool:
        return all(p.exists() for p in self.outputs) and (self.complete is None or self.complete())


@dataclass
class AblationResult:
    """records: the table's rows; stages: name → "skipped" | "done" | "given" (a given dataset or checkpoint)
    | "failed" | "blocked"; errors: name → message; tables: format → path (md, csv, tex, png); seconds: wall."""

    records: list[dict]
    stages: dict[str, str]
    errors: dict[str, str]
    tables: dict[str, Path]
    seconds: float

    @property
    def ok(self) -> bool:
        return not self.errors


class Ledger:
    """``out_dir/ablation.json``: finished stages with their inputs, seconds and time (atomic writes)."""

    def __init__(self, path: Path):
        self.path = path
        self.data = read_json(path) if path.exists() else {"stages": {}}

    def inputs(self, name: str) -> dict | None:
        entry = self.data["stages"].get(name)
        return None if entry is None else entry["inputs"]

    def record(self, name: str, inputs: dict, seconds: float | None, reason: str | None = None,
               started_at: float | None = None, ended_at: float | None = None, tags: dict | None = None) -> None:
        """One finished stage; ``started_at`` / ``ended_at``: Unix seconds of its work (None: nothing ran)."""
        from spread.runtime.fingerprint import run_tags

        self.data["stages"][name] = {"inputs": inputs, "seconds": seconds,
                                     "finished": time.strftime("%Y-%m-%dT%H:%M:%S"), "tags": tags or run_tags(),
                                     **({"started_at": started_at, "ended_at": ended_at or time.time()}
                                        if started_at is not None else {}),
                                     **({"redone_because": reason} if reason else {})}
        write_json_atomic(self.path, self.data)


def run_stage(stage: Stage, ledger: Ledger) -> str:
    """Skip, continue, redo or refuse the stage (module docstring, *Resume*) by the platform's done-check
    (:func:`spread.runtime.fingerprint.done_check`); returns "skipped" or "done"."""
    from spread.runtime.fingerprint import done_check, normalised

    inputs = normalised(stage.inputs)
    before = ledger.inputs(stage.name)
    finished = stage.finished()
    if before is None:  # outputs the ledger does not know: its command re-uses or redoes them by its own record
        decision = done_check(inputs, inputs, present=True, finished=finished and not stage.derived)
    else:
        decision = done_check(before, inputs, present=True, finished=finished)
    if decision.reuse:
        if before is None:
            ledger.record(stage.name, inputs, None)
        log.info("✓ %s: finished earlier (%s), skipped", stage.name, stage.folder)
        return "skipped"
    if decision.fresh and not stage.derived:
        raise StageError(f"{stage.folder}: made with other settings ({decision.reason}); "
                         f"delete that folder or use another out_dir")
    if decision.fresh:
        log.info("▶ %s: %s, redoing it from scratch", stage.name, decision.reason)
    started, started_at = time.perf_counter(), time.time()
    stage.run(not decision.fresh)
    if not stage.finished():
        missing = [str(p) for p in stage.outputs if not p.exists()] or ["(incomplete outputs)"]
        raise StageError(f"{stage.name}: the command returned but its outputs are missing: {missing}")
    ledger.record(stage.name, inputs, round(time.perf_counter() - started, 3), decision.reason, started_at=started_at)
    return "done"


def command_line(command: str, overrides: list[str]) -> str:
    return " ".join([command, *overrides])


def scenes_complete(folder: Path) -> bool:
    """Every scene ``sampling.json`` counts is on disk (a run's pinned ``sampling.json`` counts none until the
    run ends: not complete)."""
    try:
        manifest = read_json(folder / "sampling.json")
    except (OSError, ValueError):
        return False
    if not isinstance(manifest, dict) or "samples" not in manifest:
        return False
    return len(list((folder / "scenes").glob("*.npz"))) >= int(manifest["samples"])


def sampling_inputs(folder: Path) -> dict:
    """What an evaluation of a sampling run's scenes depends on: the fingerprint its ``sampling.json`` recorded
    (:func:`spread.runtime.fingerprint.sampling_identity`) and the number of samples."""
    manifest = read_json(folder / "sampling.json")
    return {"fingerprint": manifest.get("fingerprint"), "samples": manifest.get("samples")}


class Ablation:
    """Builds the stages of an :class:`AblationSpec` and runs them with :class:`Commands`."""

    #: the trained checkpoint each row samples from
    checkpoint_of: dict[str, str] = CHECKPOINT_OF
    #: the ledger's file name under ``out_dir``
    ledger_name: str = LEDGER

    def __init__(self, spec: StagesSpec, commands: Commands):
        self.spec = spec
        self.commands = commands
        self.out = spec.out_dir
        self.ledger = Ledger(self.out / self.ledger_name)
        self.slot = None  # while rows run concurrently: the stage pool's slot for exclusive stages
        self.status: dict[str, str] = {}
        self.errors: dict[str, str] = {}

    # ---- folders ----
    def train_dir(self, variant: str) -> Path:
        return self.out / "train" / variant

    def ckpt(self, trained: str) -> Path:
        given = self.spec.ckpt.get(trained)
        return Path(given) if given else self.train_dir(trained) / "checkpoints" / "last.ckpt"

    def sample_dir(self, variant: str) -> Path:
        return self.out / "samples" / variant

    def eval_dir(self, variant: str) -> Path:
        return self.out / "eval" / variant

    # ---- stages ----
    def data_stage(self) -> Stage | None:
        root = self.spec.dataset
        if self.spec.data_root and root.exists():
            if not (root / self.spec.split).is_dir():
                raise StageError(f"data.root={root}: no '{self.spec.split}' split folder")
            return None
        overrides = [*self.spec.generate, f"out_dir={root}"]

        def run(resume: bool) -> None:  # spread-generate resumes by itself (rooms on disk are kept)
            log.info("  ≙ %s", command_line("spread-generate", overrides))
            self.commands.generate(overrides)

        return Stage("data", root, [root / "manifest.json"], {"overrides": overrides}, run, derived=False)

    def train_lists(self, trained: str) -> list[str]:
        """The ``spread-train`` overrides of one trained row (the spec's shared list, then the row's own)."""
        return [*self.spec.train, *self.spec.train_variant.get(trained, [])]

    def timed(self, name: str, run: Callable[[bool], None]) -> Callable[[bool], None]:
        """A stage body as it runs (a subclass may wrap it, e.g. to record its CPU time)."""
        return run

    def train_stage(self, trained: str) -> Stage:
        folder = self.train_dir(trained)
        last = folder / "checkpoints" / "last.ckpt"
        overrides = self.spec.named([*self.train_lists(trained), f"data.root={self.spec.dataset}",
                                     f"out_dir={folder}"])

        def run(resume: bool) -> None:
            extra = [f"ckpt_path={last}" if last.exists() else "ckpt_path=null"]
            log.info("  ≙ %s", command_line("spread-train", overrides + extra))
            self.commands.train(overrides + extra, folder)

        return Stage(f"train/{trained}", folder, [folder / "metrics.json", last], {"overrides": overrides},
                     self.timed(f"train/{trained}", run), derived=False)

    def sample_lists(self, variant: str) -> list[str]:
        """The ``spread-sample`` overrides of one row (the spec's shared list, then the row's own): the guidance
        rows add the guidance list; a one-term row then sets the other two weights to 0."""
        if variant in TERMS:
            off = [f"guidance.{t}=0.0" for t in TERMS.values() if t != TERMS[variant]]
            return [*self.spec.sample, *self.spec.guidance, *off]
        return [*self.spec.sample, *(self.spec.guidance if variant == "guidance" else [])]

    def sample_stage(self, variant: str) -> Stage:
        from spread.configs import compose, to_object
        from spread.runtime.fingerprint import point_identity

        folder, ckpt = self.sample_dir(variant), self.ckpt(self.checkpoint_of[variant])
        overrides = self.spec.named([*self.sample_lists(variant), f"ckpt={ckpt}", f"data.root={self.spec.dataset}",
                                     f"data.split={self.spec.split}", f"out_dir={folder}"])
        command = to_object(compose("sample", overrides))  # parsed once: the stage's identity and how it samples

        def run(resume: bool) -> None:
            args = overrides + [f"resume={str(resume).lower()}"]
            log.info("  ≙ %s", command_line("spread-sample", args))
            self.commands.sample(args)

        return Stage(f"sample/{variant}", folder, [folder / "sampling.json"], point_identity(command),
                     self.timed(f"sample/{variant}", run),
                     complete=lambda: scenes_complete(folder), exclusive=int(command.workers) > 0)

    def evaluate_stage(self, variant: str) -> Stage:
        from spread.configs import compose, to_object
        from spread.runtime.fingerprint import evaluation_identity

        folder, samples = self.eval_dir(variant), self.sample_dir(variant)
        overrides = self.spec.named([*self.spec.evaluate, f"scenes={samples / 'scenes'}",
                                     f"reference={self.spec.dataset}", f"reference_split={self.spec.split}",
                                     f"out_dir={folder}"])
        command = to_object(compose("evaluate", overrides))

        def run(resume: bool) -> None:
            args = overrides + [f"resume={str(resume).lower()}"]
            log.info("  ≙ %s", command_line("spread-evaluate", args))
            self.commands.evaluate(args)

        inputs = {"evaluation": evaluation_identity(command.protocol, command.fid, Path(command.reference) / "assets"),
                  "reference_split": command.reference_split, "samples": sampling_inputs(samples),
                  **self.data_inputs()}
        return Stage(f"evaluate/{variant}", folder, [folder / "metrics.json"], inputs, run)

    def data_inputs(self) -> dict:
        """What a sample or evaluate stage depends on besides its overrides: the split's data content and the
        code version of the numbers (:mod:`spread.runtime.fingerprint`)."""
        from spread.runtime.fingerprint import NUMBERS_VERSION, dataset_digest

        return {"data_sha256": dataset_digest(self.spec.dataset, [self.spec.split]), "numbers_version": NUMBERS_VERSION}

    # ---- running ----
    def worker_state(self, names: list[str]) -> dict:
        """What the stages ``names`` run in a Ray task changed besides the ledger (a subclass's own records)."""
        return {}

    def merge_worker_state(self, state: dict) -> None:
        """Take a task's :meth:`worker_state` into this (the driver's) runner."""

    def run_rows(self, chains: list[list[tuple]]) -> dict:
        """The rows' independent stage chains (module docstring, *Concurrency*)."""
        from spread.experiments.stage_pool import run_chains

        return run_chains(self, chains, self.spec.max_concurrent, self.spec.ray)

    def finished_already(self, name: str, method: str, key: str, needs: list[str]) -> bool:
        """True when the row step ``(name, method, key, needs)`` would be skipped: the ledger holds it with the
        inputs it has now and its outputs are there (so a re-run of a finished table starts no Ray session)."""
        if any(self.status.get(n) in ("failed", "blocked") for n in needs):
            return False
        try:
            stage = getattr(self, method)(key)
        except Exception:  # noqa: BLE001 - attempt() will report it
            return False
        if stage is None:
            return False
        from spread.runtime.fingerprint import done_check

        before = self.ledger.inputs(stage.name)
        return before is not None and done_check(before, stage.inputs, present=True, finished=stage.finished()).reuse

    def attempt(self, name: str, build: Callable[[], Stage | None], needs: list[str]) -> bool:
        """Build and run one stage unless a stage it needs failed; record the outcome; True when finished."""
        blocked = [n for n in needs if self.status.get(n) in ("failed", "blocked")]
        if blocked:
            self.status[name] = "blocked"
            self.errors.setdefault(name, f"not run: {', '.join(blocked)} did not finish")
            return False
        try:
            stage = build()
            if stage is None:
                self.status[name] = "given"
                return True
            log.info("▶ %s → %s", name, stage.folder)
            from spread.experiments.stage_pool import held

            with held(self.slot if stage.exclusive else None):
                self.status[name] = run_stage(stage, self.ledger)
            return True
        except KeyboardInterrupt:
            raise
        except (Exception, SystemExit) as exc:  # noqa: BLE001 - a failed stage must not lose the other rows
            message = str(exc) if isinstance(exc, SystemExit) else f"{type(exc).__name__}: {exc}"
            self.status[name], self.errors[name] = "failed", f"{name}: {message}"
            log.error("✗ %s failed: %s\n%s", name, message, traceback.format_exc(limit=6))
        return False

    def rows(self) -> list[dict]:
        """One record per variant: the metrics of ``eval/<v>/metrics.json`` (None where it failed) and the row's
        settings and identity (:func:`spread.experiments.runs.folder_identity`)."""
        from spread.experiments.runs import folder_identity, identity_fields

        records = []
        for v in self.spec.variants:
            path = self.eval_dir(v) / "metrics.json"
            metrics = read_json(path) if self.status.get(f"evaluate/{v}") in ("done", "skipped") else {}
            row = {"variant": v, "method": LABELS[v],
                   **{c.key: metrics.get(c.key) for c in columns_of([metrics], hidden=True)}}
            row.update({"n_scenes": metrics.get("n_scenes"), "n_objects": metrics.get("n_objects"),
                        "fid_status": metrics.get("fid_status"),
                        "status": "ok" if metrics else self.errors.get(f"evaluate/{v}", "not run")})
            row.update(ci_columns(row_intervals(metrics, self.eval_dir(v)) if metrics else {}))
            if metrics:  # what the row's numbers were made with, as recorded beside them
                row.update(identity_fields(folder_identity(self.eval_dir(v), metrics)))
            records.append(row)
        return records

    def figure_scene(self) -> str | None:
        """The scene file name the figures show: the first one every sampled row has."""
        sets = [{p.name for p in (self.sample_dir(v) / "scenes").glob("*.npz")} for v in self.spec.variants
                if self.status.get(f"sample/{v}") in ("done", "skipped")]
        common = sorted(set.intersection(*sets)) if sets else []
        return common[0] if common else None

    def figure_paths(self) -> dict[str, Path]:
        """row (and ``truth``) → its figure's path."""
        return {v: self.out / f"{TABLE}_{v}.png" for v in ("truth", *self.spec.variants)}

    def figures_stage(self) -> Stage | None:
        name = self.figure_scene()
        if name is None:
            raise StageError("figures: no scene that every sampled row has, nothing to draw")
        rows = [v for v in self.spec.variants if (self.sample_dir(v) / "scenes" / name).exists()]
        truth = self.spec.dataset / self.spec.split / f"{graph_of(name)}.npz"
        paths = {k: p for k, p in self.figure_paths().items() if k in rows or (k == "truth" and truth.exists())}

        def run(resume: bool) -> None:
            write_row_figures(self.spec.dataset, {v: self.sample_dir(v) / "scenes" / name for v in rows},
                              truth if truth.exists() else None, paths)

        inputs = {"scene": name, "samples": {v: sampling_inputs(self.sample_dir(v)) for v in rows}}
        return Stage("figures", self.out, list(paths.values()), inputs, run)

    def table_stage(self, records: list[dict], log_table: Callable[[list[dict], Path], None] | None) -> Stage:
        stem = self.out / TABLE
        outputs = [stem.with_suffix(s) for s in (".md", ".csv", ".tex", ".png")]
        figures = {k: p.name for k, p in self.figure_paths().items()
                   if self.status.get("figures") in ("done", "skipped") and p.exists()}

        def run(resume: bool) -> None:
            write_ablation_table(records, stem, self.spec.title, figures)
            if log_table is not None:
                log_table(records, stem.with_suffix(".png"))

        return Stage("table", self.out, outputs, {"rows": records, "figures": figures}, run)

    def run(self, log_table: Callable[[list[dict], Path], None] | None = None) -> AblationResult:
        started = time.perf_counter()
        self.out.mkdir(parents=True, exist_ok=True)
        spec = self.spec
        self.attempt("data", self.data_stage, [])
        trained = [t for t in ("base", "geometry") if any(CHECKPOINT_OF[v] == t for v in spec.variants)]
        for t in trained:
            if spec.ckpt.get(t):
                self.status[f"train/{t}"] = "given"
            else:
                self.attempt(f"train/{t}", lambda t=t: self.train_stage(t), ["data"])
        self.run_rows([[(f"sample/{v}", "sample_stage", v, ["data", f"train/{CHECKPOINT_OF[v]}"]),
                        (f"evaluate/{v}", "evaluate_stage", v, [f"sample/{v}"])] for v in spec.variants])
        records = self.rows()
        if spec.figures:
            self.attempt("figures", self.figures_stage, [])
        self.attempt("table", lambda: self.table_stage(records, log_table), [])
        stem = self.out / TABLE
        tables = {s: stem.with_suffix(f".{s}") for s in ("md", "csv", "tex", "png")}
        return AblationResult(records, dict(self.status), dict(self.errors), tables,
                              round(time.perf_counter() - started, 3))


def table_columns(records: Sequence[dict] = ()) -> list[Column]:
    return [Column("method", "Method"), *columns_of(records)]


def write_ablation_table(records: list[dict], stem: Path, title: str = "",
                         figures: dict[str, str] | None = None) -> dict[str, Path]:
    """``stem.md``, ``.csv``, ``.tex`` (booktabs, best value bold, ± the bootstrap interval) and ``.png`` (bars
    per metric); every setting that differs between the rows is named per row (CSV columns, and a line per row
    under the Markdown table); ``figures`` (row or ``truth`` → PNG file name beside the table) are linked under the
    Markdown table."""
    from spread.experiments.plots import ablation_bars
    from spread.experiments.runs import name_differences

    records = [dict(r) for r in records]
    differ = name_differences(records)
    caption = title or "Ablation: base, +geometry perceiver, +guidance (same test graphs, seeds and protocol)"
    shown = "".join(f"\n\n**{r['method']}**: " + ", ".join(f"{k}={r.get(k)}" for k in differ) for r in records
                    if differ)
    shown = f"What differs between the rows:{shown}" if shown else ""
    if figures:
        labels = {"truth": "ground truth", **LABELS}
        shown += ("\n\n" if shown else "") \
            + "One test graph, row by row (3D view | relation matrix against the graph):" \
            + "".join(f"\n\n**{labels[k]}**\n\n![{labels[k]}]({name})" for k, name in figures.items())
    metrics = columns_of(records)
    paths = write_tables(records, table_columns(records), stem, caption=caption, label="tab:ablation",
                         csv_keys=["variant", "method", *differ, *[c.key for c in columns_of(records, hidden=True)],
                                   "n_scenes", "n_objects", "fid_status", "status", "identity", "ci_level",
                                   "ci_resamples", "ci_seed"],
                         note=table_note(records), md_extra=shown)
    ablation_bars(records, metrics, stem.with_suffix(".png"), label_key="method", title=caption)
    return {**paths, "png": stem.with_suffix(".png")}


def graph_of(sample_name: str) -> str:
    """The conditioning graph's scene id of a sample file name ``<graph>_k<i>.npz``."""
    return Path(sample_name).stem.rsplit("_k", 1)[0]


def write_row_figures(dataset: Path, scenes: dict[str, Path], truth: Path | None,
                      paths: dict[str, Path]) -> dict[str, Path]:
    """Scene cards (3D view + relation matrix) of one sampled scene per row and of its graph's ground truth."""
    from spread.assets.library import AssetLibrary
    from spread.render import save_png, scene_card_figure
    from spread.scene import read_scene

    library = AssetLibrary.load(Path(dataset) / "assets")
    written = {}
    for key, path in ([("truth", truth)] if truth is not None else []) + list(scenes.items()):
        scene = read_scene(path, assets=library)
        label = "ground truth" if key == "truth" else LABELS[key]
        written[key] = save_png(scene_card_figure(scene, library, title=f"{label}: {scene.scene_id}"), paths[key])
    return written


def run_ablation(spec: AblationSpec, commands: Commands,
                 log_table: Callable[[list[dict], Path], None] | None = None) -> AblationResult:
    """Run (or resume) every stage of ``spec`` (module docstring) and write the table."""
    return Ablation(spec, commands).run(log_table)
