"""The platform's commands as library functions on composed configs: what ``spread-generate``, ``-train``,
``-sample`` and ``-evaluate`` do, callable in-process (by the console scripts in :mod:`spread.cli`, by the
ablation's stages, by notebooks).

Each takes the composed ``conf/<command>.yaml`` (:func:`spread.configs.compose`, or the ``DictConfig`` a
Hydra app receives), turns it into the library record its schema describes (:func:`spread.configs.to_object`:
:class:`~spread.procgen.dataset.DatasetConfig`, :class:`~spread.sampling.SamplingConfig`,
:class:`~spread.evaluation.EvaluationConfig`), runs the stage and logs it (:mod:`spread.runtime.tracking`).
``spread-sample evaluate=true`` joins two stages here: sample, then evaluate the scenes into the same run
folder (one wandb run holds both). The ``print_*`` functions are the commands' console summaries.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from spread.configs import to_object


@contextlib.contextmanager
def failed_on_error(wandb_run):
    """The body of a command's wandb run (None: no run): if it raises, the run is finished as failed (exit code 1)
    before the error goes on."""
    try:
        yield
    except BaseException:
        if wandb_run is not None:
            wandb_run.finish(exit_code=1)
        raise


def save_config(cfg: DictConfig, folder: Path, overrides: list[str]) -> None:
    """``folder/.hydra/config.yaml`` and ``overrides.yaml``, as the command's own Hydra run would leave them."""
    from spread.io import write_text_atomic

    write_text_atomic(folder / ".hydra" / "config.yaml", OmegaConf.to_yaml(cfg))
    write_text_atomic(folder / ".hydra" / "overrides.yaml", OmegaConf.to_yaml(OmegaConf.create(list(overrides))))


def hydra_overrides() -> list[str]:
    """The command line's overrides inside a running Hydra app (``[]`` outside one)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def record_config(cfg: DictConfig, folder, overrides: list[str] | None = None):
    """A callback that writes the run's config into ``folder/.hydra`` (run by a stage once its checks passed)."""
    return lambda: save_config(cfg, Path(folder), hydra_overrides() if overrides is None else overrides)


def record_in_log_folder(cfg: DictConfig) -> None:
    """Record the config in Hydra's log folder (commands whose ``out_dir`` is a dataset folder, which stays
    the dataset); nothing outside a running Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        record_config(cfg, HydraConfig.get().runtime.output_dir)()


def plain(cfg: DictConfig) -> dict:
    """The composed config as plain data (what wandb records as the run's config)."""
    return OmegaConf.to_container(cfg, resolve=True)


# ---- generate ------------------------------------------------------------------------------------------------

def generate(cfg: DictConfig) -> dict:
    """``spread-generate``: the dataset folder ``cfg.out_dir``; returns its manifest."""
    from spread.io import run_lock
    from spread.procgen.dataset import generate_dataset

    command = to_object(cfg)
    with run_lock(command.out_dir, "spread-generate"):  # a second run on the folder is refused, never mixed
        record_in_log_folder(cfg)
        return generate_dataset(command.out_dir, command, progress=command.progress)


def print_dataset_summary(manifest: dict, out_dir: str) -> None:
    from rich.console import Console
    from rich.table import Table

    stats = manifest["statistics"]
    run = manifest["this_run"]
    table = Table(title=f"dataset {out_dir}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for split, n in manifest["counts"].items():
        table.add_row(f"rooms ({split})", str(n))
    opr = stats["objects_per_room"]
    table.add_row("objects per room min / mean / max", f"{opr['min']} / {opr['mean']:.1f} / {opr['max']}")
    table.add_row("support pairs per room (mean)", f"{stats['support_pairs_per_room']['mean']:.1f}")
    table.add_row("share of supported objects that are stacked", f"{stats['share_stacked']:.3f}")
    table.add_row("categories in use / in library", f"{len(stats['categories'])} / {len(manifest['categories'])}")
    table.add_row("asset library (s)", f"{run['seconds_assets']:.1f}")
    table.add_row("rooms generated this run", str(run["rooms_generated"]))
    table.add_row("room generation (s)", f"{run['seconds_rooms']:.1f}")
    if run["rooms_per_second"]:
        table.add_row("rooms per second", f"{run['rooms_per_second']:.2f}")
    table.add_row("failed rooms", str(len(manifest["failed_rooms"])))
    Console().print(table)
    top = sorted(stats["categories"].items(), key=lambda kv: -kv[1])[:12]
    Console().print("most frequent categories: " + ", ".join(f"{k} {v}" for k, v in top))
    for message in manifest.get("warnings") or []:
        Console().print(f"[yellow]warning: {message}[/yellow]")


# ---- import --------------------------------------------------------------------------------------------------

def import_data(cfg: DictConfig) -> dict:
    """``spread-import``: another layout converted into the dataset folder ``cfg.out_dir``; returns its
    manifest. A missing split file or a bad option raises ``SystemExit`` with one line naming it."""
    from spread.importers.run import import_dataset

    command = to_object(cfg)
    record_in_log_folder(cfg)
    try:
        return import_dataset(command)
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f"spread-import: {exc}") from exc


def print_import_summary(manifest: dict, out_dir: str) -> None:
    from rich.console import Console
    from rich.table import Table

    run = manifest["this_run"]
    table = Table(title=f"imported {manifest['source']['source']} → {out_dir}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for split, n in manifest["counts"].items():
        table.add_row(f"rooms ({split})", str(n))
    for room_type, n in manifest["room_types"].items():
        table.add_row(f"rooms of type {room_type}", str(n))
    table.add_row("assets (closed / open meshes / boxes)",
                  f"{manifest['assets']} ({manifest['meshes']['closed']} / {manifest['meshes']['open']} / "
                  f"{manifest['meshes']['boxes']})")
    table.add_row("failed rooms / assets", f"{manifest['failed_rooms']} / {manifest['failed_assets']}")
    agree = manifest["relations_agreement"]
    if agree["spatial_agreement"] is not None:
        table.add_row("file vs platform: spatial codes equal", f"{agree['spatial_agreement']:.3f}")
    if agree["file_support_recall"] is not None:
        table.add_row("file support pairs the platform finds", f"{agree['file_support_recall']:.3f}")
    if manifest["decomposition"]["hausdorff_m"]:
        h = manifest["decomposition"]["hausdorff_m"]
        table.add_row(f"{manifest['decomposition']['method']} Hausdorff median / max (mm)",
                      f"{1000 * h['median']:.1f} / {1000 * h['max']:.1f}")
    table.add_row("assets built this run", str(run["assets_built"]))
    table.add_row("rooms written this run", str(run["rooms_written"]))
    for key in ("assets_per_second", "rooms_per_second"):
        if run.get(key):
            table.add_row(key.replace("_", " "), f"{run[key]:.3f}")
    console = Console()
    console.print(table)
    for err in manifest["errors"]["rooms"][:10]:
        console.print(f"room {err['tag']}: {err['error']}")
    for err in manifest["errors"]["assets"][:10]:
        console.print(f"asset {err.get('asset_id')}: {err['error']}")
    for warning in manifest.get("warnings", []):
        console.print(f"[yellow]warning:[/yellow] {warning}")


# ---- export --------------------------------------------------------------------------------------------------

def export(cfg: DictConfig):
    """``spread-export``: every scene of ``cfg.scenes`` as simulation-ready files in ``cfg.out_dir``; returns the
    :class:`~spread.export.ExportReport`. Bad options raise ``SystemExit`` with one line naming them."""
    from spread.export import FORMATS, assets_of, export_folder

    command = to_object(cfg)
    if command.format not in FORMATS:
        raise SystemExit(f"spread-export: format={command.format}: unknown (known: {', '.join(FORMATS)})")
    if not Path(command.scenes).is_dir():
        raise SystemExit(f"spread-export: scenes={command.scenes}: not a folder")
    try:
        assets = assets_of(command.scenes, command.assets)
    except FileNotFoundError as exc:
        raise SystemExit(f"spread-export: {exc}") from exc
    record_config(cfg, command.out_dir)()
    return export_folder(command.scenes, assets, command.out_dir, command.format, floor=command.floor,
                         progress=command.progress)


def print_export_summary(report) -> None:
    print(f"spread-export: {len(report.written)} scenes written as {report.format} to {report.out_dir}, "
          f"{len(report.failed)} failed (see export.json)")
    for scene_id, error in list(report.failed.items())[:10]:
        print(f"  failed {scene_id}: {error}")
    for file, note in list(getattr(report, "duplicates", {}).items())[:10]:
        print(f"  duplicate id in {file}: {note}")


# ---- train ---------------------------------------------------------------------------------------------------

def train(cfg: DictConfig, run_dir: Path | None = None, overrides: list[str] | None = None) -> dict:
    """``spread-train``: fit into ``run_dir`` (default: Hydra's output folder, else ``cfg.out_dir``). The launching
    process holds the folder's run lock (:func:`spread.io.run_lock`; the other ranks of DDP, torchrun, SLURM or MPI,
    which have a non-zero rank variable, do not take it), so a second training run into the same folder is refused."""
    import contextlib
    import os

    from spread.io import run_lock
    from spread.training.fit import run_folder
    from spread.training.fit import train as fit

    run_dir = Path(run_dir) if run_dir is not None else run_folder(cfg)
    ranks = ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_PROCID", "OMPI_COMM_WORLD_RANK", "PMI_RANK")
    launcher = all(os.environ.get(v, "0") in ("", "0") for v in ranks)  # rank 0 of every launcher we know
    with run_lock(run_dir, "spread-train") if launcher else contextlib.nullcontext():
        record_config(cfg, run_dir, overrides)()
        return fit(cfg, run_dir=run_dir)


# ---- evaluate ------------------------------------------------------------------------------------------------

def evaluate(cfg: DictConfig, overrides: list[str] | None = None):
    """``spread-evaluate``: evaluate ``cfg.scenes``; logs to wandb with ``logger=wandb``; returns the
    :class:`~spread.evaluation.EvaluationResult`. The config is recorded in ``out_dir/.hydra`` once the
    protocol check passed."""
    from spread.evaluation import run_evaluation
    from spread.evaluation.wandb_log import log_evaluation
    from spread.runtime import mlflow_log

    command = to_object(cfg)
    tags = {"spread.seed": command.seed, "spread.scenes": str(command.scenes),
            "spread.dataset_fingerprint": mlflow_log.dataset_fingerprint(command.reference)}
    lineage = scenes_lineage(command.scenes)
    wandb_run = None
    if command.logger.wandb:
        from spread.runtime.tracking import init_run

        Path(command.out_dir).mkdir(parents=True, exist_ok=True)
        wandb_run = init_run(command.logger, "evaluate", command.out_dir, plain(cfg) | {"lineage": lineage},
                             group=command.experiment_name, name=Path(command.out_dir).name)
    with failed_on_error(wandb_run):
        with mlflow_log.tracked(command.logger, "evaluate", command.out_dir, plain(cfg), command.experiment_name,
                                tags=tags | lineage) as run:
            result = run_evaluation(command, before_work=record_config(cfg, command.out_dir, overrides))
            if run is not None:
                mlflow_log.log_evaluation(run, result.metrics, result.out_dir, result.renders)
    log_evaluation(result, command.logger, group=command.experiment_name, config=plain(cfg), run=wandb_run)
    return result


def evaluated_specs(metrics: dict) -> list:
    """The registered metrics a ``metrics.json`` holds (its protocol's selection), in table order."""
    from spread.metrics.registry import METRICS, ordered

    names = (metrics.get("protocol") or {}).get("metrics") or [n for n in METRICS.names() if n in metrics]
    return ordered(METRICS.get(n) for n in names if n in METRICS)


def scenes_lineage(scenes) -> dict:
    """Lineage tags of an evaluation of ``scenes``: a sampling run's ``scenes/`` folder names the sampling
    run (its :data:`~spread.runtime.mlflow_log.RUN_FILE`) and, through its recorded checkpoint, the training run."""
    from spread.io import read_json

    from spread.runtime.mlflow_log import RUN_FILE, training_lineage

    folder = Path(scenes).parent
    tags = {}
    if (folder / RUN_FILE).exists():
        tags["spread.sampling_run_id"] = read_json(folder / RUN_FILE).get("run_id")
    manifest = folder / "sampling.json"
    if manifest.exists():
        tags |= training_lineage(read_json(manifest).get("ckpt"))
    return tags


def print_evaluation_summary(metrics: dict, out_dir) -> None:
    """The evaluation's console table: each value of the evaluated metrics in its display unit (the table writer's
    columns, :func:`spread.experiments.tables.metric_column`), its 95 % bootstrap interval over scenes where it has
    one."""
    from rich.console import Console
    from rich.table import Table

    from spread.evaluation.bootstrap import interval_note
    from spread.experiments.tables import metric_column, set_columns

    def fmt(v, digits=4):
        return "null" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))

    def interval(column, row):
        lo, hi = row.get(f"{column.key}_lo"), row.get(f"{column.key}_hi")
        return "" if lo is None or hi is None else f"[{column.format(lo)}, {column.format(hi)}]"

    level = (metrics.get("bootstrap") or {}).get("level")
    table = Table(title=f"evaluation {out_dir}")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column(f"{level * 100:g} % interval" if level else "interval", justify="right")
    specs = evaluated_specs(metrics)
    values = [v for spec in specs for v in spec.values if v.name in metrics]
    for value in values:
        column = metric_column(value)
        arrow = "↑" if value.higher_is_better else "↓"
        table.add_row(f"{value.label} ({value.description or value.name}, {arrow})",
                      column.format(metrics.get(value.name)), interval(column, metrics))
    fid, kid = set_columns()
    table.add_row(f"{fid.label} ({metrics.get('fid_feature_model')}, ↓)", fid.format(metrics.get("fid")))
    table.add_row(f"{kid.label} (↓)", kid.format(metrics.get("kid")))
    table.add_row("scenes / evaluated / failed",
                  f"{metrics['n_scenes']} / {metrics['n_evaluated']} / {metrics['n_failed']}")
    table.add_row("objects", str(metrics["n_objects"]))
    table.add_row("seconds", fmt(metrics["run"]["seconds"], 1))
    console = Console()
    console.print(table)
    if metrics.get("per_room_type"):
        by_type = Table(title="per room type")
        columns = [metric_column(v) for v in values]
        for col in ("room type", "scenes", *[c.label for c in columns]):
            by_type.add_column(col, justify="left" if col == "room type" else "right")
        for name, m in metrics["per_room_type"].items():
            by_type.add_row(name, str(m["n_evaluated"]), *[c.format(m.get(c.key)) for c in columns])
        console.print(by_type)
    note = interval_note(metrics.get("bootstrap"))
    if note:
        console.print(note.replace("± is half the width of the", "interval: the"), soft_wrap=True)
    console.print(f"fid_status: {metrics['fid_status']}")
    for f in metrics["failed"][:10]:
        console.print(f"failed {f['scene_id']}: {f['error']}", markup=False)
    failures = {k: v for k, v in (metrics.get("metric_failures") or {}).items() if v}
    if failures:
        console.print("metric failures (those scenes are left out of that metric only): "
                      + ", ".join(f"{k} on {v} scene(s)" for k, v in failures.items()), markup=False)
        for f in (metrics.get("failed_metrics") or [])[:10]:
            console.print(f"  {f['metric']} failed on {f['scene_id']}: {f['error']}", markup=False)
    for name, why in (metrics.get("invalid_values") or {}).items():
        console.print(f"{name}: no value ({why})", markup=False)


# ---- sample --------------------------------------------------------------------------------------------------

def evaluation_after_sampling(command):
    """The :class:`~spread.evaluation.EvaluationConfig` of ``spread-sample evaluate=true``: the run's scenes
    against the dataset's ``evaluation.reference_split``, results beside them in ``out_dir``."""
    from spread.evaluation import EvaluationConfig

    ev = command.evaluation
    return EvaluationConfig(
        scenes=str(Path(command.out_dir) / "scenes"), reference=command.data.root, out_dir=command.out_dir,
        reference_split=ev.reference_split, chunk_size=ev.chunk_size, resume=command.resume,
        retry_failed=ev.retry_failed, renders=ev.renders, progress=command.progress, protocol=ev.protocol,
        fid=ev.fid, ray=command.ray)


def experiment_of(command) -> str:
    """The experiment (wandb group, MLflow experiment) of a sampling command: ``experiment_name``, and the sweep
    folder's name after it when a sweep's folder is not named so (two launches of one sweep file into
    different folders are two experiments)."""
    name = str(command.experiment_name)
    folder = Path(str(command.sweep_dir)).name if command.sweep_dir else None
    return name if not folder or folder == name else f"{name}/{folder}"


def sample(cfg: DictConfig, log: bool = True, overrides: list[str] | None = None):
    """``spread-sample``: sample (then, with ``evaluate=true``, evaluate) into ``cfg.out_dir``; returns
    (:class:`~spread.sampling.SamplingResult`, :class:`~spread.evaluation.EvaluationResult` or None). A
    finished sweep point (``evaluate=true``, ``resume=true``, ``metrics.json`` there) is left as it is
    and (None, None) returned when its fingerprint matches, else redone (:mod:`spread.experiments.points`).
    ``log=False``: no wandb or MLflow run (the ablation logs its table instead)."""
    from spread.runtime import mlflow_log
    from spread.sampling import run_sampling
    from spread.sampling.mlflow_log import sampling_run_tags
    from spread.sampling.wandb_log import log_sampling, open_sampling_run

    command = to_object(cfg)
    before_work = record_config(cfg, command.out_dir, overrides)
    if command.evaluate:  # a sweep point: re-used only when its fingerprint matches (experiments.points)
        from spread.experiments.points import check_point, finish_point, start_point

        point = check_point(command, command.out_dir, command.resume)
        if point.reuse:
            print(f"{command.out_dir}: finished earlier with the same fingerprint, re-used")
            return None, None
        if point.reason:  # sampling and evaluation then keep what their own fingerprints still match
            print(f"{command.out_dir}: redone ({point.reason})")
        record = before_work

        def before_work():
            record()
            start_point(command.out_dir, point)
    started = time.perf_counter()
    experiment = experiment_of(command)
    wandb_run = open_sampling_run(command, plain(cfg), experiment) if log and command.logger.wandb else None
    with failed_on_error(wandb_run):
        with mlflow_log.tracked(command.logger if log else None, "sample", command.out_dir, plain(cfg), experiment,
                                tags=lambda: sampling_run_tags(command)) as run:
            result = run_sampling(command, before_work=before_work)
            if run is not None:
                mlflow_log.log_sampling(run, result.manifest)
            evaluation = None
            if command.evaluate:
                from spread.evaluation import run_evaluation

                evaluation = run_evaluation(evaluation_after_sampling(command))
                finish_point(command.out_dir, round(time.perf_counter() - started, 3))
                if run is not None:
                    mlflow_log.log_evaluation(run, evaluation.metrics, evaluation.out_dir, evaluation.renders)
    more = None
    if evaluation is not None:
        from spread.evaluation.wandb_log import log_metrics

        renders = list(result.manifest.get("renders") or []) + list(result.manifest.get("figures") or [])

        def more(run):
            log_metrics(run, evaluation.metrics, evaluation.records, renders)
    if wandb_run is not None:
        log_sampling(result.manifest, command.out_dir, plain(cfg), command.logger, group=experiment, more=more,
                     run=wandb_run)
    return result, evaluation


def print_sampling_summary(result) -> None:
    m = result.manifest
    per_batch = "" if m["seconds_per_batch"] is None else f", {m['seconds_per_batch']:.2f} s per batch"
    print(f"{result.out_dir / 'scenes'}: {m['samples']} scenes of {m['graphs']} graphs "
          f"({m['written_this_run']} written now, {m['resumed']} already there; {m['seconds']:.1f} s{per_batch}; "
          f"{m['runner']['mode']}, {m['runner']['workers']} worker(s))")


# ---- the commands as one object (the ablation's stages) ---------------------------------------------------------

class InProcessCommands:
    """:class:`~spread.experiments.stages.Commands` backed by the functions above: each stage composes its
    command's config from the stage's overrides and runs it (which records the config in its folder)."""

    def generate(self, overrides: list[str]) -> None:
        from spread.configs import compose

        generate(compose("generate", overrides))

    def train(self, overrides: list[str], run_dir: Path) -> None:
        from spread.configs import compose

        train(compose("train", overrides), run_dir=run_dir, overrides=overrides)

    def sample(self, overrides: list[str]) -> None:
        from spread.configs import compose

        sample(compose("sample", overrides), log=False, overrides=overrides)

    def evaluate(self, overrides: list[str]) -> dict:
        from spread.configs import compose

        return evaluate(compose("evaluate", overrides), overrides=overrides).metrics
