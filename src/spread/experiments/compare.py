"""``spread-compare``: the paper's Table 1 — every method trained, sampled and evaluated on one dataset.

The stages are the ablation's (:mod:`spread.experiments.ablation`: the same :class:`Stage`, ledger, resume
rules and in-process :class:`~spread.experiments.stages.Commands`), over methods instead of variants:

| stage | command | folder under ``out_dir`` | finished when |
|---|---|---|---|
| ``data`` (only when ``data.root`` is not given or does not exist) | spread-generate | ``data/`` | ``manifest.json`` |
| ``train/<m>``, m = atiss, diffuscene, instructscene, spread (unless given) | spread-train | ``train/<m>/`` | ``metrics.json``, ``last.ckpt`` |
| ``sample/<m>`` | spread-sample | ``samples/<m>/`` | ``sampling.json``, all scenes |
| ``evaluate/<m>`` | spread-evaluate | ``eval/<m>/`` | ``metrics.json`` |
| ``table`` | — | ``table1.{md,csv,tex}`` (+ wandb Table) | the three files |

``physcene`` is DiffuScene's checkpoint sampled with PhyScene's guidance (``guidance=physcene``: the registered
guidance term ``box_iou``; its registered sampling overrides; no second training, no second checkpoint);
``spread`` is the platform's own SceneDiffusion (by default the ``geometry`` model sampled with guidance).
Every method samples the split's graphs with one shared override list (``sample.overrides``: sampler, seed,
samples per graph) plus its own (``sample.<m>``); every evaluation shares ``evaluate.overrides``. The ledger is
``out_dir/compare.json``; ``out_dir/compare_times.json`` keeps each stage's CPU seconds (this process).

Table layouts (``layout``): ``procthor`` — GRecall, Col_mesh, ASD, Stability, FID, KID; ``threedfront`` —
Col_mesh per room type (the test graphs' ``room_type``) and FID, KID; ``auto`` picks ``threedfront`` when the
dataset's ``manifest.json`` names 3D-FRONT as its source, else ``procthor``. Both add the sampling time per
scene (the paper's Table 3) and the CSV holds every value (per-room-type Col_mesh included). GRecall is "—"
for the methods that do not see the graph (ATISS, DiffuScene, PhyScene-style); the value measured anyway is
in the CSV as ``grecall_measured``. The caption states each method's budget: its training run (size, steps
taken) and its sampler.

A re-run with some methods (``'methods=[atiss]'``) re-runs those and keeps the folder's other finished rows
in Table 1, each marked as carried over (:mod:`spread.experiments.stages`, *Published tables only grow*);
training stages run ``stages.train_concurrent`` at a time as the ablation's do.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from spread.reporting.intervals import (
    ci_columns, folder_records, grouped_intervals, protocol_seed, row_intervals, table_note,
)
from spread.experiments.stages import (
    Commands, Stage, StageEngine, StagesResult, StagesSpec, carried_note, with_carried)
from spread.reporting.tables import Column, columns_of, display_rows, set_columns, value_column, write_tables
from spread.checks import listed_once
from spread.io import read_json, read_text_checked, write_json_atomic

log = logging.getLogger("spread.compare")

#: The paper's Table 1 rows (the default ``methods``); every registered method can be a row
#: (:mod:`spread.methods.registry`: labels, notes, graph conditioning, which checkpoint a method samples).
METHODS = ("atiss", "diffuscene", "physcene", "instructscene", "spread")


def registered() -> list[str]:
    """Every registered method (plugins too), in Table 1's row order."""
    from spread.methods.registry import method_names

    return method_names()


def spec_of(method: str):
    from spread.methods.registry import method_spec

    return method_spec(method)


def label(method: str) -> str:
    return spec_of(method).row_label


def trained_from(method: str) -> str:
    """The trained method whose checkpoint ``method`` samples (physcene: diffuscene's)."""
    return spec_of(method).trained_from


def checkpoint_methods() -> list[str]:
    """The registered methods that sample a checkpoint of their own (trained here, or given: ``train.ckpt.<m>``)."""
    return [m for m in registered() if spec_of(m).checkpoint is None]


def trained_methods() -> list[str]:
    """The registered methods trained here (a checkpoint of their own and a training recipe)."""
    return [m for m in checkpoint_methods() if spec_of(m).trainable]
LEDGER = "compare.json"
TIMES = "compare_times.json"
TABLE = "table1"
LAYOUTS = ("auto", "procthor", "threedfront")


@dataclass
class CompareSpec(StagesSpec):
    """A comparison (:class:`~spread.experiments.stages.StagesSpec`; ``conf/compare.yaml`` documents each
    list): its rows (``methods``), each trained method's own training list and each method's own sampling list
    (default: the method's registered ``sample``, physcene's ``guidance=physcene``); ``layout``."""

    methods: tuple[str, ...] = METHODS
    train_method: dict[str, list[str]] = field(default_factory=dict)
    sample_method: dict[str, list[str]] = field(default_factory=dict)
    layout: str = "auto"

    def __post_init__(self) -> None:
        super().__post_init__()
        known = registered()
        unknown = [m for m in self.methods if m not in known]
        if unknown or not self.methods:
            raise ValueError(f"methods: unknown or none {unknown or list(self.methods)} (choose from {known})")
        listed_once(self.methods, "methods")  # one row, shown once: the list asked for what the table does not hold
        self.methods = tuple(m for m in known if m in self.methods)
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout: {self.layout!r}, choose from {LAYOUTS}")
        for method in self.methods:
            source = trained_from(method)
            if not spec_of(source).trainable and not self.ckpt.get(source):
                raise ValueError(f"methods: '{method}' is not trained here; give its checkpoint with "
                                 f"+train.ckpt.{source}=<file> (e.g. spread-release-ckpt ckpt=ckpt.pth out=<file>)")
        self.check_given(checkpoint_methods(), lambda m: {"method": m}, " (physcene samples diffuscene's)")

    def trained(self) -> list[str]:
        """The checkpoints the chosen methods need, in order."""
        need = {trained_from(m) for m in self.methods}
        return [t for t in checkpoint_methods() if t in need]


@dataclass
class CompareResult(StagesResult):
    """:class:`~spread.experiments.stages.StagesResult` and the table's ``layout``."""

    layout: str = "procthor"


class Comparison:
    """Table 1's rows (the registered methods) over the stage engine
    (:class:`~spread.experiments.stages.StageEngine`): which checkpoint each method samples, its own training and
    sampling overrides, the CPU seconds of its stages, its budget columns and the table."""

    def __init__(self, spec: CompareSpec, commands: Commands):
        self.spec = spec
        self.engine = StageEngine(spec, commands, self, LEDGER)
        self.out = spec.out_dir
        self.times_path = self.out / TIMES
        self.times: dict = read_json(self.times_path) if self.times_path.exists() else {}
        # each method trained here composes that method's model (a +train.<m> list replaces its recipe)
        spec.check_trained({m: self.train_lists(m) for m in spec.trained()}, lambda m: {"method": m}, label)
        self.engine.check_data()
        self.engine.check_lists(list(spec.methods))
        self.engine.check_relaunch(spec.trained())

    @property
    def checkpoint_of(self) -> dict[str, str]:
        """method → the trained method whose checkpoint it samples (its own; physcene: diffuscene's)."""
        return {m: trained_from(m) for m in self.spec.methods}

    def timed(self, name: str, run: Callable[[bool], None]) -> Callable[[bool], None]:
        """``run`` with this process's CPU seconds recorded under ``name`` in ``compare_times.json``."""
        def wrapper(resume: bool) -> None:
            started = time.process_time()
            run(resume)
            self.times[name] = round(self.times.get(name, 0.0) * resume + time.process_time() - started, 3)
            write_json_atomic(self.times_path, self.times)
        return wrapper

    def worker_state(self, names: list[str]) -> dict:
        return {"times": {k: self.times[k] for k in names if k in self.times}}

    def merge_worker_state(self, state: dict) -> None:
        """A chain task's CPU seconds (its worker process's) into ``compare_times.json``."""
        times = state.get("times") or {}
        if times:
            self.times.update(times)
            write_json_atomic(self.times_path, self.times)

    # ---- stages ----
    def train_lists(self, method: str) -> list[str]:
        return [*self.spec.train, *self.spec.train_method.get(method, [])]

    def sample_lists(self, method: str) -> list[str]:
        """The shared sampling overrides, then the method's own (default: its registered ``sample``, e.g.
        physcene's ``guidance=physcene``)."""
        own = self.spec.sample_method.get(method)
        return [*self.spec.sample, *(list(spec_of(method).sample) if own is None else own)]

    # ---- the table ----
    def layout(self) -> str:
        if self.spec.layout != "auto":
            return self.spec.layout
        manifest = self.spec.dataset / "manifest.json"
        try:
            source = str(read_json(manifest).get("source", ""))
        except (OSError, ValueError):
            source = ""
        return "threedfront" if re.search(r"3d-?front", source, re.IGNORECASE) else "procthor"

    def room_types(self) -> dict[str, str]:
        """Test graph scene id → its ``room_type`` (graphs without one are left out)."""
        from spread.scene import list_scene_files, read_scene

        folder = self.spec.dataset / self.spec.split
        out = {}
        for path in list_scene_files(folder) if folder.is_dir() else []:
            scene = read_scene(path, validate=False)
            if "room_type" in scene.extras:
                out[scene.scene_id] = str(scene.extras["room_type"])
        return out

    def rows(self) -> list[dict]:
        from spread.methods import graph_conditioned
        from spread.reporting.runs import folder_identity, identity_fields

        GRAPH_CONDITIONED = graph_conditioned()
        rooms = self.room_types()
        suffix = re.compile(r"_k\d+$")  # generated scene <graph>_k<k> (spread.sampling.plan.SAMPLE_NAME) → graph
        records = []
        for m in self.spec.methods:
            ok = self.engine.status.get(f"evaluate/{m}") in ("done", "skipped")
            metrics = read_json(self.engine.eval_dir(m) / "metrics.json") if ok else {}
            row = {"method_key": m, "method": label(m)}
            measured = metrics.get("grecall")
            row["grecall"] = measured if m in GRAPH_CONDITIONED else None
            row["grecall_measured"] = measured
            for key in (*[c.key for c in columns_of([metrics], hidden=True) if c.key != "grecall"],
                        "n_scenes", "n_objects", "fid_status"):
                row[key] = metrics.get(key)
            if ok:
                row.update(ci_columns(row_intervals(metrics, self.engine.eval_dir(m))))
                if m not in GRAPH_CONDITIONED:  # no GRecall cell, so no interval beside it
                    row["grecall_lo"] = row["grecall_hi"] = None
                row.update(grouped_intervals(folder_records(self.engine.eval_dir(m)) or [],
                                             lambda sid: rooms.get(suffix.sub("", sid)), ["col_mesh"],
                                             seed=protocol_seed(metrics)))
            row.update(self.budget(m))
            if ok:  # what the row's numbers were made with, as recorded beside them
                row.update(identity_fields(folder_identity(self.engine.eval_dir(m), metrics)))
            row["status"] = "ok" if metrics else self.failure(m)
            records.append(row)
        return records

    def failure(self, method: str) -> str:
        """The first error on the method's way to its row (training, derivation, sampling, evaluation)."""
        trained = trained_from(method)
        chain = ["data", f"train/{trained}", f"sample/{method}", f"evaluate/{method}"]
        for name in chain:
            if self.engine.status.get(name) == "failed":
                return self.engine.errors[name]
        return self.engine.errors.get(f"evaluate/{method}", "not run")

    def budget(self, method: str) -> dict:
        """Training steps and size, sampler, sampling seconds per scene, CPU seconds of this process."""
        out: dict = {}
        trained = trained_from(method)
        summary = self.engine.train_dir(trained) / "metrics.json"
        if summary.exists():
            out["train_steps"] = read_json(summary).get("global_step")
        config = self.engine.train_dir(trained) / ".hydra" / "config.yaml"
        if config.exists():
            import yaml

            cfg = yaml.safe_load(read_text_checked(config)) or {}
            out["model_size"] = ((cfg.get("model") or {}).get("config") or {}).get("name")
        manifest = self.engine.sample_dir(method) / "sampling.json"
        if manifest.exists():
            data = read_json(manifest)
            guidance = data.get("guidance_label") or "none"
            out["sampler"] = str(data.get("sampler"))  # what ran: an own sampler's label (ATISS's), as recorded
            out["sampler"] += "" if guidance == "none" else f" + guidance {guidance}"
            per_batch, batches, written = data.get("seconds_per_batch"), data.get("batches_run"), data.get("written_this_run")
            if per_batch is not None and written:
                out["seconds_per_scene"] = per_batch * batches / written
        for stage in ("train", "sample"):
            key = f"{stage}/{trained if stage == 'train' else method}"
            if key in self.times:
                out[f"{stage}_cpu_s"] = self.times[key]
        return out

    def columns(self, layout: str, records: list[dict]) -> list[Column]:
        from dataclasses import replace

        time_col = Column("seconds_per_scene", "s / scene", 3, "min", r"s / scene$\downarrow$")
        if layout == "threedfront":
            rooms = sorted({k.split("/", 1)[1] for r in records for k in r if k.startswith("col_mesh/")})
            col_mesh = value_column("col_mesh")
            latex = (col_mesh.latex or col_mesh.label).replace(r"\downarrow$", "$")
            per_room = [replace(col_mesh, key=f"col_mesh/{room}", label=f"{col_mesh.label} {room}",
                                latex=rf"{latex} {room}$\downarrow$") for room in rooms]
            return [Column("method", "Method"), *per_room, *set_columns(), time_col]
        return [Column("method", "Method"), *columns_of(records), time_col]

    def caption(self, records: list[dict]) -> str:
        parts = []
        for r in records:
            steps = r.get("train_steps")
            size = r.get("model_size") or "?"
            trained = f"{size} model, {steps} training steps" if steps is not None else "given checkpoint"
            parts.append(f"{r['method']}: {trained}; {r.get('sampler', '?')} ({spec_of(r['method_key']).note or 'plugin'})")
        title = self.spec.title or f"Table 1 on {self.spec.dataset.name} ({self.spec.split} graphs, same seeds)"
        return title + ". Budget: " + "; ".join(parts) + ". GRecall is not reported for methods that do not see the graph."

    def table_stage(self, records: list[dict], log_table) -> Stage:
        stem = self.out / TABLE
        outputs = [stem.with_suffix(s) for s in (".md", ".csv", ".tex")]
        layout = self.layout()

        def run(resume: bool) -> None:
            from spread.reporting.runs import name_differences

            rows = [dict(r) for r in records]
            differ = name_differences(rows)  # every setting that differs between the rows, per row in the CSV
            columns = self.columns(layout, rows)
            keys = ["method_key", "method", *differ, "grecall", "grecall_measured",
                    *[c.key for c in columns_of(records, hidden=True) if c.key != "grecall"], "seconds_per_scene"]
            keys += sorted({k for r in records for k in r if k.startswith("col_mesh/")})
            keys += ["train_steps", "model_size", "sampler", "train_cpu_s", "sample_cpu_s", "n_scenes", "n_objects",
                     "fid_status", "status", "identity", "carried_from"]
            note = " ".join(n for n in (measured_otherwise(rows, differ), table_note(rows), carried_note(rows)) if n)
            write_tables(rows, columns, stem, caption=self.caption(rows), label="tab:table1", csv_keys=keys,
                         note=note)
            if log_table is not None:
                log_table(rows, columns)

        return Stage("table", self.out, outputs, {"rows": records, "layout": layout}, run)

    # ---- running ----
    def run(self, log_table=None) -> CompareResult:
        started = time.perf_counter()
        self.out.mkdir(parents=True, exist_ok=True)
        self.engine.run_trained(self.spec.trained())
        self.engine.run_sample_evaluate(list(self.spec.methods))
        records = with_carried(self.rows(), self.engine.carried("method_key", list(self.spec.methods)), "method_key",
                               registered())
        self.engine.attempt("table", lambda: self.table_stage(records, log_table), [])
        stem = self.out / TABLE
        if self.engine.status.get("table") == "skipped" and log_table is not None:  # this launch's run shows it too
            rows = [dict(r) for r in records]  # (a relaunch's parent run was left empty)
            log_table(rows, self.columns(self.layout(), rows))
        done = self.engine.result(records, {s: stem.with_suffix(f".{s}") for s in ("md", "csv", "tex")}, started)
        return CompareResult(**vars(done), layout=self.layout())


#: Settings in which Table 1's rows differ by design (each method's own weights, sampler and guidance, which the
#: caption names); any other that differs (the evaluation protocol, FID's settings, the reference, the seed, …)
#: measured one row otherwise than another, and is named under the table.
METHOD_OWN = ("ckpt", "sampler", "guidance.")


def measured_otherwise(rows: list[dict], differ: list[str]) -> str:
    """The line under Table 1 naming, row by row, the settings other than :data:`METHOD_OWN` in which its rows
    differ (``differ``: :func:`spread.reporting.runs.name_differences`, whose values the rows hold), or ""; e.g. a
    row carried over from a run under another evaluation protocol."""
    keys = [k for k in differ if not k.startswith(METHOD_OWN)]
    if not keys:
        return ""
    per_row = "; ".join(f"{r.get('method')}: " + ", ".join(f"{k}={r.get(k)}" for k in keys) for r in rows)
    return f"The rows were not measured alike: they differ in {', '.join(keys)} ({per_row})."


def run_comparison(spec: CompareSpec, commands: Commands, log_table=None) -> CompareResult:
    """Run (or resume) every stage of ``spec`` (module docstring) and write Table 1."""
    return Comparison(spec, commands).run(log_table)


def log_table1(records: list[dict], columns: list[Column], out_dir: str | Path, logger, name: str | None = None,
               config: dict | None = None, group: str | None = None) -> str | None:
    """Table 1 as a ``wandb.Table`` (the table's columns plus budget fields) and per-method summary values
    (``<method>/<metric>``), with ``logger`` (a :class:`~spread.tracking.loggers.LoggerConfig`,
    ``job_type=compare``). Returns the wandb run folder (None when disabled)."""
    import wandb

    from spread.tracking.loggers import as_logger_config, init_run, run_folder

    keys = ["method_key", *[c.key for c in columns], "grecall_measured", "train_steps", "sampler", "status"]
    run = init_run(as_logger_config(logger), "compare", out_dir, config or {}, group=group, name=name)
    try:
        header, rows = display_rows(records, keys, columns)  # display units, headed as in the CSV (asd_mm)
        table = wandb.Table(columns=header)
        for row in rows:
            table.add_data(*row)
        run.log({"table1": table})
        from spread.metrics.registry import in_display_units

        run.summary.update({f"{r['method_key']}/{key}": value for r in records for key, value in in_display_units(
            {c.key: r.get(c.key) for c in columns if c.key != "method"}).items()})  # display units (asd_mm)
        return run_folder(run)
    finally:
        run.finish()
