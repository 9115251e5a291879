"""The resumable stage engine of the multi-run studies (``spread-ablate``, ``spread-compare``).

A study is a sequence of the platform's own commands, run through a :class:`Commands` object; each
:class:`Stage` is one command with its Hydra overrides (printed as the equivalent command line), finished when
its outputs exist. :class:`StageEngine` owns what every study shares: the folders (``data/``, ``train/<row>/``,
``samples/<row>/``, ``eval/<row>/`` under ``out_dir``), the data, training, sampling and evaluation stages, the
ledger (:class:`Ledger`: each finished stage's inputs, decided by the platform's one done-check
:func:`spread.runtime.fingerprint.done_check`), the outcome of each stage (``status``, ``errors``: a failed stage
blocks only the stages that need it), the concurrent training stages and the rows' concurrent sample → evaluate
chains (:mod:`spread.experiments.stage_pool`), and the rows a re-run carries over.

**Published tables only grow.** A re-run with a subset of the rows (``'variants=[base,guidance]'``,
``'methods=[atiss]'``) re-runs those rows and keeps the others of the folder's table: :meth:`StageEngine.carried`
takes them from the ledger's ``table`` entry (the rows the table was last written with) when the row finished
there (``status`` ok, an ``identity``) and its evaluation is still recorded and on disk. A row of the same name
that this run re-runs always replaces the kept one (its identity may differ: what differs is named under the
table). A kept row carries ``carried_from`` (when its evaluation finished) and :func:`carried_note` says under
the table which rows were carried over.

What differs between studies is asked of the study object the engine serves (:class:`Study`: which checkpoint a
row samples, a row's training and sampling overrides, optionally a wrapper that times a stage body and the state
a Ray task hands back); the ablation (:mod:`spread.experiments.ablation`) and the comparison
(:mod:`spread.experiments.compare`) each hold an engine — neither inherits from the other.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

from spread.experiments.begun import forget_begun, mark_begun, read_begun
from spread.io import read_json, write_json_atomic
from spread.runtime.ray import TERMINATED, RaySettings, terminated

log = logging.getLogger("spread.stages")


class Commands(Protocol):
    """The platform's commands, run in-process; each takes the Hydra overrides of its ``conf/<name>.yaml``."""

    def generate(self, overrides: list[str]) -> None: ...

    def train(self, overrides: list[str], run_dir: Path) -> None: ...

    def sample(self, overrides: list[str]) -> None: ...

    def evaluate(self, overrides: list[str]) -> dict: ...


def check_data_split(spec) -> None:
    """A study's given ``data.root`` without the split its rows are sampled on (``spec``: an ablation's or comparison's
    spec): a ``ValueError`` before its config is recorded or any stage runs (the data stage's refusal came once per
    phase, then Ray started and a table of – was written)."""
    root = spec.dataset
    if spec.data_root and root.exists() and not (root / spec.split).is_dir():
        raise ValueError(f"data.root={root}: no '{spec.split}' split folder (data.split={spec.split})")


class StageError(RuntimeError):
    """A stage that cannot run as configured; the message names its folder."""


@dataclass
class StagesSpec:
    """What an ablation or a comparison shares (:class:`AblationSpec`, :class:`~spread.experiments.compare.CompareSpec`).
    Override lists are Hydra overrides of the sub-commands' configs; ``ckpt``: trained row → a given checkpoint
    (no training); ``data_root``: None → generate into ``out_dir/data``; ``group``: wandb group of every stage's
    run (``experiment_name=<group>``; "" leaves each command's); ``max_concurrent``: rows' sample → evaluate
    chains at a time (Ray tasks when > 1, on ``ray``: None, a local Ray session); ``train_concurrent``: training
    stages at a time (Ray tasks when > 1, each reserving ``train_cpus`` CPUs and ``train_gpus`` GPUs; 1: one
    after another in this process)."""

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
    train_concurrent: int = 1
    train_cpus: float = 1.0
    train_gpus: float = 0.0

    def named(self, overrides: list[str]) -> list[str]:
        """``overrides`` with the wandb group first (so a list can still set its own)."""
        return ([f"experiment_name={self.group}"] if self.group else []) + list(overrides)

    def __post_init__(self) -> None:
        self.out_dir = Path(self.out_dir)
        if int(self.max_concurrent) < 1:
            raise ValueError(f"max_concurrent={self.max_concurrent}: at least 1")
        if int(self.train_concurrent) < 1:
            raise ValueError(f"train_concurrent={self.train_concurrent}: at least 1")
        if float(self.train_cpus) < 0 or float(self.train_gpus) < 0:
            raise ValueError(f"train_cpus={self.train_cpus}, train_gpus={self.train_gpus}: not negative")

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

    def check_trained(self, lists_of: dict[str, list[str]], method_of: Callable[[str], dict],
                      label: Callable[[str], str] = str) -> None:
        """Every row this study trains composes to that row's kind of model — the counterpart of
        :meth:`check_given` for the rows trained here: ``lists_of`` (trained row → its ``spread-train`` overrides)
        composed with ``conf/train.yaml`` and asked :func:`spread.methods.loading.trained_identity` (the ``method``
        and ``variant`` its checkpoint will hold), compared with ``method_of(row)``'s keywords. A ``ValueError``
        naming ``train.<row>`` before any stage runs; a row with a given checkpoint is not trained, so not asked.
        (A list given on the command line replaces the preset's: ``train.geometry`` without
        ``model.variant=geometry`` trained a second base model under +Geometry's name.)"""
        from spread.configs import compose
        from spread.methods.loading import trained_identity

        keys = {"method": "method", "variant": "model.variant"}
        for row, lists in lists_of.items():
            if self.ckpt.get(row):
                continue
            got = trained_identity(compose("train", list(lists)).model)
            wanted = {k: v for k, v in method_of(row).items() if v is not None}
            wrong = {k: v for k, v in wanted.items() if got.get(k) != v}
            if wrong:
                wants = ", ".join(f"{keys.get(k, k)}={v}" for k, v in wrong.items())
                holds = ", ".join(f"{keys.get(k, k)}={got.get(k)}" for k in wrong)
                hint = (f"add model.variant={wrong['variant']} to train.{row}" if list(wrong) == ["variant"]
                        else f"its recipe's model or experiment makes a {wanted.get('method')} model")
                raise ValueError(f"train.{row}: the {label(row)} row trains {wants}, but its training overrides "
                                 f"{list(lists)} compose {holds} ({hint})")

    @property
    def dataset(self) -> Path:
        return Path(self.data_root) if self.data_root else self.out_dir / "data"


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
    #: the typed identity of a recorded ``inputs`` (this run's and the ledger's alike), compared instead of the
    #: record itself: the settings its overrides compose to, not how they were spelled (None: the record itself)
    typed: Callable[[dict], dict] | None = None

    def finished(self) -> bool:
        return all(p.exists() for p in self.outputs) and (self.complete is None or self.complete())


@dataclass
class StagesResult:
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
    """``out_dir/ablation.json``: finished stages with their inputs, seconds and time (atomic writes); and each
    stage's inputs when it begins (:meth:`begin`), so that a driver stopped mid-stage resumes that stage's own work
    instead of redoing it against the older finished record."""

    def __init__(self, path: Path):
        self.path = path
        self.data = read_json(path) if path.exists() else {"stages": {}}

    def inputs(self, name: str) -> dict | None:
        entry = self.data["stages"].get(name)
        return None if entry is None else entry["inputs"]

    def begin(self, name: str, inputs: dict) -> None:
        """Record that the stage ``name`` begins with ``inputs`` (before its command writes anything)."""
        mark_begun(self.path, name, inputs)

    def begun(self, name: str) -> dict | None:
        return read_begun(self.path, name)

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
        forget_begun(self.path, name)


def typed_inputs(stage: Stage, before: dict, now: dict) -> tuple[dict, dict]:
    """(recorded, this run's) inputs as the done-check compares them: through :attr:`Stage.typed` when the stage
    has it (a part only this run's record holds — one added since the ledger was written — is left out of both),
    else as recorded; a record the typed identity cannot read (overrides that no longer compose) as recorded."""
    from spread.runtime.fingerprint import normalised

    if stage.typed is None:
        return before, now
    try:
        held, wanted = normalised(stage.typed(before)), normalised(stage.typed(now))
    except Exception:  # noqa: BLE001 - an old record this version cannot compose: compared as written
        return before, now
    return held, {k: v for k, v in wanted.items() if k in held}


def decide(stage: Stage, ledger: Ledger):
    """The done-check's :class:`~spread.runtime.fingerprint.Decision` for ``stage`` against the ledger (module
    docstring, *Resume*), and the refusal when it must be redone but is not derived (None: it may run)."""
    from spread.runtime.fingerprint import done_check, normalised

    inputs = normalised(stage.inputs)
    # a stage begun and not recorded (its driver stopped): what is on disk was begun with those inputs, not the
    # finished record's — the same inputs now continue it, other ones redo it
    before = ledger.begun(stage.name) or ledger.inputs(stage.name)
    finished = stage.finished()
    # a stage folder deleted since the ledger recorded it (what the refusal below asks for) is simply made anew
    present = stage.derived or Path(stage.folder).exists()
    if before is None:  # outputs the ledger does not know: its command re-uses or redoes them by its own record
        decision = done_check(inputs, inputs, present=present, finished=finished and not stage.derived)
    else:
        decision = done_check(*typed_inputs(stage, before, inputs), present=present, finished=finished)
    refusal = None
    if decision.fresh and not stage.derived:
        refusal = (f"{stage.folder}: made with other settings ({decision.reason}); "
                   f"delete that folder or use another out_dir")
    return decision, refusal


def run_stage(stage: Stage, ledger: Ledger) -> str:
    """Skip, continue, redo or refuse the stage (module docstring, *Resume*) by the platform's done-check
    (:func:`spread.runtime.fingerprint.done_check`); returns "skipped" or "done"."""
    from spread.runtime.fingerprint import normalised

    inputs = normalised(stage.inputs)
    begun = ledger.begun(stage.name)
    decision, refusal = decide(stage, ledger)
    if decision.reuse:
        if begun is None and ledger.inputs(stage.name) is None:
            ledger.record(stage.name, inputs, None)
        log.info("✓ %s: finished earlier (%s), skipped", stage.name, stage.folder)
        return "skipped"
    if refusal:
        raise StageError(refusal)
    if decision.fresh:
        log.info("▶ %s: %s, redoing it from scratch", stage.name, decision.reason)
    elif begun is not None:
        log.info("▶ %s: continuing the run begun with these inputs (%s)", stage.name, stage.folder)
    ledger.begin(stage.name, inputs)
    started, started_at = time.perf_counter(), time.time()
    stage.run(not decision.fresh)
    if not stage.finished():
        missing = [str(p) for p in stage.outputs if not p.exists()] or ["(incomplete outputs)"]
        raise StageError(f"{stage.name}: the command returned but its outputs are missing: {missing}")
    ledger.record(stage.name, inputs, round(time.perf_counter() - started, 3), decision.reason, started_at=started_at)
    return "done"


#: Settings of a composed ``spread-train`` config that change none of its trained numbers: where it is written and
#: logged (the run folder, the runs' root, the tracking, the wandb group) and where the data lies (its content is
#: the stage's ``data_sha256``).
UNTRAINED = ("out_dir", "paths", "logger", "experiment_name", "tags")


def init_weights_input(overrides: list[str]) -> dict:
    """``{"init_from_sha256": …}`` for a training stage whose overrides start from weights (``model.init_from``), taken
    when the stage is planned: the stage's record keeps what the file held then (recomputed from the file at
    comparison time, a replaced file would compare equal to itself). Empty without ``init_from``."""
    from omegaconf import OmegaConf

    from spread.configs import compose
    from spread.runtime.fingerprint import init_weights_digest

    weights = init_weights_digest(OmegaConf.to_container(compose("train", list(overrides)), resolve=True))
    return {"init_from_sha256": weights} if weights else {}


def typed_training(inputs: dict) -> dict:
    """A training stage's identity: the ``spread-train`` config its overrides compose to, less :data:`UNTRAINED`
    and ``data.root``, with the data's content (``data_sha256``, in records made since it was kept) and the content of
    the weights ``model.init_from`` names, as recorded when the stage was planned (``init_from_sha256``:
    :func:`init_weights_input`)."""
    from omegaconf import OmegaConf

    from spread.configs import compose
    from spread.runtime.fingerprint import training_config_identity

    config = OmegaConf.to_container(compose("train", list(inputs["overrides"])), resolve=False)
    for key in UNTRAINED:
        config.pop(key, None)
    (config.get("data") or {}).pop("root", None)
    return {"config": training_config_identity(config), **{k: inputs[k] for k in ("data_sha256", "init_from_sha256")
                                                             if k in inputs}}


def typed_generation(inputs: dict) -> dict:
    """A data stage's identity: what its rooms depend on (:meth:`spread.procgen.dataset.DatasetConfig.fingerprint`)
    and how many, from the ``spread-generate`` config its overrides compose to."""
    from spread.configs import compose, to_object

    command = to_object(compose("generate", list(inputs["overrides"])))
    return {"fingerprint": command.fingerprint(), "rooms": int(command.rooms)}


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


class Study(Protocol):
    """What a study tells the engine (module docstring). Optional: ``timed(name, run)`` (a stage body as it runs),
    ``worker_state(names)`` and ``merge_worker_state(state)`` (a Ray task's own records)."""

    checkpoint_of: dict[str, str]

    def train_lists(self, trained: str) -> list[str]: ...

    def sample_lists(self, row: str) -> list[str]: ...


class StageEngine:
    """Builds and runs the shared stages of a :class:`StagesSpec` with :class:`Commands` for a :class:`Study`."""

    def __init__(self, spec: StagesSpec, commands: Commands, study: Study, ledger_name: str):
        self.spec = spec
        self.commands = commands
        self.study = study
        self.out = spec.out_dir
        self.ledger = Ledger(self.out / ledger_name)
        self.slot = None  # while rows run concurrently: the stage pool's slot for exclusive stages
        self.status: dict[str, str] = {}
        self.errors: dict[str, str] = {}

    def check_data(self) -> None:
        check_data_split(self.spec)

    def check_relaunch(self, trained: list[str]) -> None:
        """Refuse a relaunch whose data or training stage was made with other settings (:func:`decide`) before any
        stage runs or anything is written: found mid-run, the refusal failed that row and the folder's table was
        rewritten with the row blank. Training stages are asked only when the data stays as it is (a dataset that
        is still to be made has no content to compare); a stage that cannot be built yet is left to its run."""
        if not self.ledger.path.exists():
            return
        names = [("data", self.data_stage)]
        names += [(f"train/{t}", lambda t=t: self.train_stage(t)) for t in trained if not self.spec.ckpt.get(t)]
        for name, build in names:
            try:
                stage = build()
            except Exception:  # noqa: BLE001 - the stage's run reports it, where a failed stage is reported
                continue
            if stage is None:
                continue
            decision, refusal = decide(stage, self.ledger)
            if refusal:  # a user's error (the folder and the settings disagree): one line, nothing written
                raise ValueError(f"{name}: {refusal}")
            if name == "data" and not decision.reuse:
                return

    def check_lists(self, rows: list[str]) -> None:
        """Every row's ``spread-sample`` list and the ``spread-evaluate`` list compose to their commands' typed
        configs, before any stage runs: a misspelled key, a value of the wrong type or a refused setting is a
        ``ValueError`` naming the stage and the override (a stage that failed on it turned its finished row of the
        table to –)."""
        from hydra.errors import ConfigCompositionException, OverrideParseException

        from spread.configs import compose, error_message, to_object

        lists = {f"sample/{row}": ("sample", [*self.study.sample_lists(row), "ckpt=unset", "data.root=unset",
                                              "out_dir=unset"]) for row in rows}
        lists["evaluate"] = ("evaluate", [*self.spec.evaluate, "scenes=unset", "reference=unset", "out_dir=unset"])
        from spread.evaluation.run import check_fid

        for name, (command, overrides) in lists.items():
            try:
                typed = to_object(compose(command, self.spec.named(overrides)))
                if command == "evaluate":  # a FID backbone that cannot load: said before training and sampling
                    check_fid(typed.fid)
            except (ValueError, ConfigCompositionException, OverrideParseException) as exc:
                raise ValueError(f"{name}: its overrides {overrides[:-3]} do not make a spread-{command} command: "
                                 f"{error_message(exc)}") from None

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

        return Stage("data", root, [root / "manifest.json"], {"overrides": overrides}, run, derived=False,
                     typed=typed_generation)

    def timed(self, name: str, run: Callable[[bool], None]) -> Callable[[bool], None]:
        """A stage body as it runs: the study's ``timed`` wrapper when it has one (e.g. to record its CPU time)."""
        timed = getattr(self.study, "timed", None)
        return run if timed is None else timed(name, run)

    def train_stage(self, trained: str) -> Stage:
        folder = self.train_dir(trained)
        last = folder / "checkpoints" / "last.ckpt"
        overrides = self.spec.named([*self.study.train_lists(trained), f"data.root={self.spec.dataset}",
                                     f"out_dir={folder}"])
        from spread.runtime.fingerprint import dataset_digest

        inputs = {"overrides": overrides, "data_sha256": dataset_digest(self.spec.dataset, ["train", "val"]),
                  **init_weights_input(overrides)}

        def run(resume: bool) -> None:
            extra = [f"ckpt_path={last}" if last.exists() else "ckpt_path=null"]
            log.info("  ≙ %s", command_line("spread-train", overrides + extra))
            self.commands.train(overrides + extra, folder)

        return Stage(f"train/{trained}", folder, [folder / "metrics.json", last], inputs,
                     self.timed(f"train/{trained}", run), derived=False, typed=typed_training)

    def sample_stage(self, variant: str) -> Stage:
        from spread.configs import compose, to_object
        from spread.runtime.fingerprint import point_identity

        folder, ckpt = self.sample_dir(variant), self.ckpt(self.study.checkpoint_of[variant])
        overrides = self.spec.named([*self.study.sample_lists(variant), f"ckpt={ckpt}", f"data.root={self.spec.dataset}",
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
                  **self.data_inputs(),  # an object limit set leaves scenes out of the numbers (the default: none)
                  **({"max_objects": command.max_objects} if command.max_objects is not None else {})}
        return Stage(f"evaluate/{variant}", folder, [folder / "metrics.json"], inputs, run)

    def data_inputs(self) -> dict:
        """What a sample or evaluate stage depends on besides its overrides: the split's data content and the
        code version of the numbers (:mod:`spread.runtime.fingerprint`)."""
        from spread.runtime.fingerprint import NUMBERS_VERSION, dataset_digest

        return {"data_sha256": dataset_digest(self.spec.dataset, [self.spec.split]), "numbers_version": NUMBERS_VERSION}

    # ---- running ----
    def worker_state(self, names: list[str]) -> dict:
        """What the stages ``names`` run in a Ray task changed besides the ledger (the study's own records)."""
        own = getattr(self.study, "worker_state", None)
        return {} if own is None else own(names)

    def merge_worker_state(self, state: dict) -> None:
        """Take a task's :meth:`worker_state` into the study (the driver's)."""
        own = getattr(self.study, "merge_worker_state", None)
        if own is not None and state:
            own(state)

    def row_pool(self) -> dict:
        """How :func:`~spread.experiments.stage_pool.run_jobs` runs sample → evaluate chains: ``max_concurrent``
        tasks that only drive their commands."""
        return {"max_concurrent": self.spec.max_concurrent, "ray_settings": self.spec.ray, "owner": self.out}

    def train_pool(self) -> dict:
        """How :func:`~spread.experiments.stage_pool.run_jobs` runs training stages: ``train_concurrent`` tasks,
        each reserving ``train_cpus`` CPUs and ``train_gpus`` GPUs."""
        return {"max_concurrent": self.spec.train_concurrent, "ray_settings": self.spec.ray, "owner": self.out,
                "resources": {"num_cpus": self.spec.train_cpus, "num_gpus": self.spec.train_gpus}}

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

        from spread.runtime.fingerprint import normalised

        before = self.ledger.begun(stage.name) or self.ledger.inputs(stage.name)
        return before is not None and done_check(*typed_inputs(stage, before, normalised(stage.inputs)), present=True,
                                                 finished=stage.finished()).reuse

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
            if terminated(exc):  # the command was asked to stop, not the stage failed: no later stage may start
                log.error("■ %s stopped by SIGTERM: the command stops (a relaunch continues this stage)", name)
                raise SystemExit(TERMINATED) from exc
            message = str(exc) if isinstance(exc, SystemExit) else f"{type(exc).__name__}: {exc}"
            self.status[name], self.errors[name] = "failed", f"{name}: {message}"
            log.error("✗ %s failed: %s\n%s", name, message, traceback.format_exc(limit=6))
        return False

    def train_jobs(self, trained: list[str]) -> list[tuple]:
        """``(self, chain)`` per trained row to train (a given checkpoint is ``given``): a chain of one step
        each, independent of one another (:mod:`spread.experiments.stage_pool`)."""
        jobs = []
        for t in trained:
            if self.spec.ckpt.get(t):
                self.status[f"train/{t}"] = "given"
            else:
                jobs.append((self, [(f"train/{t}", "train_stage", t, ["data"])]))
        return jobs

    def row_jobs(self, rows: list[str]) -> list[tuple]:
        """``(self, chain)`` per row: its sample → evaluate chain (after its data and checkpoint)."""
        return [(self, [(f"sample/{r}", "sample_stage", r, ["data", f"train/{self.study.checkpoint_of[r]}"]),
                        (f"evaluate/{r}", "evaluate_stage", r, [f"sample/{r}"])]) for r in rows]

    def run_trained(self, trained: list[str]) -> dict:
        """The data stage, then the trained rows' training stages (``train_concurrent`` at a time)."""
        from spread.experiments.stage_pool import run_jobs

        self.attempt("data", self.data_stage, [])
        return run_jobs(self.train_jobs(trained), **self.train_pool())

    def run_sample_evaluate(self, rows: list[str]) -> dict:
        """Each row's sample → evaluate chain (after its data and checkpoint), ``max_concurrent`` at a time."""
        from spread.experiments.stage_pool import run_jobs

        return run_jobs(self.row_jobs(rows), **self.row_pool())

    # ---- the table ----
    def carried(self, key: str, rerun: list[str]) -> list[dict]:
        """The rows of the folder's last table that this run does not re-run (module docstring, *Published
        tables only grow*); ``key``: the record field that names a row (``variant``, ``method_key``)."""
        before = self.ledger.inputs("table") or {}
        stages = self.ledger.data["stages"]
        kept = []
        for row in before.get("rows") or []:
            name = row.get(key)
            entry = stages.get(f"evaluate/{name}")
            if name in rerun or row.get("status") != "ok" or not row.get("identity") or entry is None \
                    or not (self.eval_dir(name) / "metrics.json").exists():
                continue
            kept.append({**row, "carried_from": row.get("carried_from") or entry.get("finished")})
        return kept

    def result(self, records: list[dict], tables: dict[str, Path], started: float) -> "StagesResult":
        return StagesResult(records, dict(self.status), dict(self.errors), tables,
                            round(time.perf_counter() - started, 3))


def with_carried(records: list[dict], carried: list[dict], key: str, order: list[str]) -> list[dict]:
    """This run's rows and the carried ones (:meth:`StageEngine.carried`) in the table's row order (``order``:
    every row name; a re-run row replaces a carried one of the same name)."""
    fresh = {r[key] for r in records}
    rows = records + [r for r in carried if r[key] not in fresh]
    rank = {name: i for i, name in enumerate(order)}
    return sorted(rows, key=lambda r: rank.get(r[key], len(rank)))


def carried_note(records: list[dict], label: str = "method") -> str:
    """The table's line naming the rows carried over from an earlier run (empty when none)."""
    carried = [f"{r.get(label)} (evaluated {r['carried_from']})" for r in records if r.get("carried_from")]
    if not carried:
        return ""
    return "Rows carried over from an earlier run of this folder, not re-run this time: " + "; ".join(carried) + "."
