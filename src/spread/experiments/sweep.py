"""``spread-sweep``: a sweep as Ray Tune trials, ``max_concurrent`` at a time, here or on a Ray cluster.

A **trial** is one point: ``spread-sample evaluate=true`` (``command=sample``: sampling + evaluation) or one
``spread-train`` run (``command=train``), given the sweep's fixed overrides plus the trial's values. The
command line is ``spread-sample``'s (or ``spread-train``'s) plus the keys of ``conf/sweep_run.yaml``:

* fixed overrides (``ckpt=... data.root=...``) go to every trial;
* Hydra's sweep syntax makes the search space: a comma list or ``choice(a,b)`` / ``range(0,10,2)`` → a grid
  (``search=grid``, every combination) or a categorical dimension (``search=random`` / ``optuna`` / any other
  search by registered name or ``module:Class``, :mod:`spread.experiments.tuning`); ``interval(a,b)`` → a
  uniform dimension (searches that draw only), ``int(interval(a,b))`` → whole numbers from a to b (for a count:
  ``data.batch_size``, ``trainer.max_steps``), ``tag(log,…)`` → log-uniform; a preset's ``hydra.sweeper.params``
  (``+sweep=guidance_grid``) count as if written on the command line, unless the key is given there.

Each trial's run folder is ``out_dir/points/<values>_<short fingerprint>`` and it is re-used only when its
fingerprint matches (:mod:`spread.experiments.points`), so a re-launched sweep re-uses every finished point,
resumes a killed one and redoes only what changed; ``results.csv`` / ``results.md`` are rebuilt from the
points every time, so an interrupted and re-run sweep ends with the same table as an uninterrupted one.

**Resources.** One Ray session for the whole sweep (``address=null``: a local one with ``num_cpus``;
``auto`` or ``HOST:PORT``: a cluster). A trial reserves a placement group: an empty head bundle (its GPUs
with ``trial_gpus``) for the trial process, which samples in-process (``workers=0``), and a bundle of
``trial_cpus`` CPUs that its evaluation tasks (and sampling actors, with ``workers>0``) use
(:func:`spread.runtime.ray.scheduling_strategy`). Trial processes are re-used across trials
(``reuse_actors``): imports, the trial process's model, asset library and graphs (:mod:`spread.readonce`:
a second trial in the process reads none of them again) and each Ray worker's per-process caches (the asset
library, convex parts, physics worlds, FID reference features) stay warm. A row's ``startup_seconds`` is its
sampling's time to the first batch, ``trial_pid`` the trial process.

**Training sweeps** (``command=train``): each trial trains into its point folder; with a trial scheduler
(``scheduler=asha``, or another by name, :mod:`spread.experiments.tuning`) a Lightning callback reports every
validation to Tune and the scheduler stops the worst trials early.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

log = logging.getLogger("spread.sweep")

COMMANDS = ("sample", "train")
#: prepended to every sampling trial (the command line may override them)
SAMPLE_DEFAULTS = ["workers=0", "progress=false", "figures=0", "evaluate=true"]
TRAIN_DEFAULTS = ["trainer.enable_progress_bar=false"]
#: a grid's remaining points go to Tune as one grid over whole points (trial config ``{POINT_KEY: {...}}``)
POINT_KEY = "point"


@dataclass
class SweepSettings:
    """The sweep's own keys (``conf/sweep_run.yaml`` documents each)."""

    out_dir: str = "???"
    command: str = "sample"
    name: str = "sweep"
    max_concurrent: int = 1
    search: str = "grid"
    num_samples: int = 8
    search_seed: int = 0
    metric: str = "grecall"
    mode: str = "max"
    address: str | None = None
    num_cpus: int | None = None
    trial_cpus: float = 1.0
    trial_gpus: float = 0.0
    scheduler: str | None = None
    asha: dict = field(default_factory=lambda: {"grace_period": 1, "reduction_factor": 2})
    seeds: int = 1

    def __post_init__(self) -> None:
        if self.out_dir in ("???", None, ""):
            raise ValueError("spread-sweep: out_dir is required (the sweep folder)")
        for key in ("name", "out_dir"):  # name=2024, out_dir=2024: a name and a folder all the same
            value = getattr(self, key)
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                setattr(self, key, str(value))
        for key in ("out_dir", "command", "name", "search", "metric", "mode"):
            if not isinstance(getattr(self, key), str):
                raise ValueError(f"spread-sweep: {key}={getattr(self, key)!r}: one text value")
        if self.command not in COMMANDS:
            raise ValueError(f"spread-sweep: command={self.command}: choose from {COMMANDS}")
        from spread.experiments.tuning import search_spec, trial_scheduler_spec

        try:
            search_spec(self.search)  # a registered name or "module:Class"; else an error naming the known ones
        except ValueError as exc:
            raise ValueError(f"spread-sweep: search={self.search}: {exc}") from exc
        try:
            if self.scheduler is not None:
                trial_scheduler_spec(self.scheduler)
        except ValueError as exc:
            raise ValueError(f"spread-sweep: scheduler={self.scheduler}: {exc}") from exc
        if self.mode not in ("min", "max"):
            raise ValueError(f"spread-sweep: mode={self.mode}: min or max")
        if isinstance(self.max_concurrent, bool) or not isinstance(self.max_concurrent, int) or self.max_concurrent < 1:
            raise ValueError(f"spread-sweep: max_concurrent={self.max_concurrent}: a whole number of trials, at least 1")
        if isinstance(self.num_samples, bool) or not isinstance(self.num_samples, int) or self.num_samples < 1:
            raise ValueError(f"spread-sweep: num_samples={self.num_samples}: a whole number ≥ 1 (Ray Tune reads -1 "
                             f"as 'for ever')")
        for key, low in (("trial_cpus", 0.0), ("trial_gpus", 0.0)):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < low or (key == "trial_cpus" and value <= 0):
                raise ValueError(f"spread-sweep: {key}={value}: expected a number "
                                 f"{'> 0' if key == 'trial_cpus' else '≥ 0'}")
        if self.num_cpus is not None and (isinstance(self.num_cpus, bool) or not isinstance(self.num_cpus, int)
                                          or self.num_cpus < 1):
            raise ValueError(f"spread-sweep: num_cpus={self.num_cpus}: null or a whole number ≥ 1")
        if not str(self.name).strip():
            raise ValueError("spread-sweep: name is empty")
        if isinstance(self.seeds, bool) or not isinstance(self.seeds, int) or self.seeds < 1:
            raise ValueError(f"spread-sweep: seeds={self.seeds}: a whole number ≥ 1 (sampling seeds per point)")
        if self.seeds > 1 and self.command != "sample":
            raise ValueError(f"spread-sweep: seeds={self.seeds} is for command=sample (each point sampled with that "
                             f"many seeds); a training sweep sweeps its seed as a setting: 'seed=0,1'")

    @property
    def grid(self) -> bool:
        """The search runs every combination once (:mod:`spread.experiments.tuning`)."""
        from spread.experiments.tuning import search_spec

        return search_spec(self.search).grid

    @property
    def folder_name(self) -> str:
        """:attr:`name` as one safe path component (:func:`spread.io.safe_name`): Ray Tune's records go to
        ``out_dir/tune/<folder_name>``, inside ``out_dir`` whatever the name (``../../x`` included)."""
        from spread.io import safe_name

        return safe_name(str(self.name))


@dataclass
class Dimension:
    """One swept key: ``key`` (as written, with a ``+`` prefix if any), ``values`` (override strings) or an
    interval ``low``/``high`` (``log`` tag: log-uniform; ``integer``: Hydra's ``int(interval(a,b))``, whole numbers
    from ``a`` to ``b`` inclusive, for settings that take one: ``trainer.max_steps``, ``batch_size``)."""

    key: str
    values: list[str] | None = None
    low: float | None = None
    high: float | None = None
    log: bool = False
    integer: bool = False


@dataclass
class SweepPlan:
    settings: SweepSettings
    fixed: list[str]
    dimensions: list[Dimension]


def settings_keys() -> set[str]:
    return set(SweepSettings.__dataclass_fields__)


def default_settings() -> dict:
    """``conf/sweep_run.yaml``'s values."""
    from spread.configs import conf_dir

    from spread.io import read_text_checked

    return OmegaConf.to_container(OmegaConf.create(read_text_checked(Path(conf_dir()) / "sweep_run.yaml")),
                                  resolve=False)


def parse_arguments(argv: list[str]) -> SweepPlan:
    """Split a ``spread-sweep`` command line (module docstring) into settings, fixed overrides and dimensions."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    own = settings_keys()
    settings = default_settings()
    fixed, swept = [], {}
    for override in parser.parse_overrides([a for a in argv if a.strip()]):
        key = override.key_or_group
        if key in own and override.is_sweep_override():
            raise ValueError(f"spread-sweep: {override.input_line}: '{key}' is a setting of the sweep itself and takes "
                             f"one value, not a sweep over values")
        if key in own:
            settings[key] = None if override.value() is None else override.value()
        elif override.is_sweep_override():
            swept[override.get_key_element()] = dimension(override)
        else:
            fixed.append(override.input_line)
    sweep_settings = SweepSettings(**settings)
    defaults = SAMPLE_DEFAULTS if sweep_settings.command == "sample" else TRAIN_DEFAULTS
    fixed = [*defaults, *fixed]
    given = {o.split("=", 1)[0].lstrip("+~") for o in fixed}
    for key, values in preset_params(sweep_settings.command, fixed).items():
        if key.lstrip("+~") not in given and key not in swept:
            swept[key] = dimension(parser.parse_overrides([f"{key}={values}"])[0])
    dims = list(swept.values())
    check_dimensions(dims)
    if sweep_settings.grid and any(d.values is None for d in dims):
        bad = [d.key for d in dims if d.values is None]
        raise ValueError(f"spread-sweep: interval() on {bad} needs search=random, search=optuna or another search "
                         f"that draws")
    return SweepPlan(sweep_settings, fixed, dims)


def check_dimensions(dims: list[Dimension]) -> None:
    """``ValueError`` naming the first dimension with no value (``range(0,0)``) or an empty or inverted interval
    (``interval(1,0)``; a log interval needs low > 0)."""
    for d in dims:
        if d.values is not None and not d.values:
            raise ValueError(f"spread-sweep: {d.key}: the sweep over it has no value (e.g. range(0,0)); give at least "
                             f"one")
        if d.values is None:
            ordered = d.low <= d.high if d.integer else d.low < d.high  # int(interval(3,3)): the one value 3
            if not (math.isfinite(d.low) and math.isfinite(d.high)) or not ordered:
                raise ValueError(f"spread-sweep: {d.key}=interval({d.low:g},{d.high:g}): expected finite low "
                                 f"{'≤' if d.integer else '<'} high")
            if d.log and d.low <= 0:
                raise ValueError(f"spread-sweep: {d.key}: a log interval needs low > 0, got {d.low:g}")


def check_whole_ends(line: str) -> None:
    """``ValueError`` for ``int(interval(a,b))`` whose ends as written are not whole: Hydra truncates them
    (``int(interval(1.5,3.5))`` drew from 1 to 3, below what was written)."""
    import re

    found = re.search(r"interval\(\s*([^,()]+?)\s*,\s*([^,()]+?)\s*\)", line)
    if found is None:
        return
    for end in found.groups():
        try:
            whole = float(end).is_integer()
        except ValueError:
            continue
        if not whole:
            raise ValueError(f"spread-sweep: {line}: int() of an interval with the end {end} draws from its truncated "
                             f"ends (Hydra casts them); give whole ends, e.g. int(interval(2,4))")


def dimension(override) -> Dimension:
    """The swept key of one override; ``ValueError`` naming two of its listed values that are one setting (``0.0``
    and ``0``, ``1e-3`` and ``0.001``: the same point twice, and with ``seeds`` its runs counted as more seeds)."""
    key = override.get_key_element()
    if override.is_interval_sweep():
        value = override.value()
        integer = all(isinstance(v, int) and not isinstance(v, bool) for v in (value.start, value.end))
        if integer:
            check_whole_ends(override.input_line)
        return Dimension(key, low=value.start if integer else float(value.start),
                         high=value.end if integer else float(value.end), log="log" in (value.tags or set()),
                         integer=integer)
    from spread.runtime.fingerprint import canonical

    values = [str(v) for v in override.sweep_string_iterator()]
    seen: dict = {}
    for text, typed in zip(values, override.sweep_iterator()):
        same = float(typed) if isinstance(typed, (int, float)) and not isinstance(typed, bool) else canonical(typed)
        if same in seen:
            twice = f"{seen[same]} and {text} are one setting" if seen[same] != text else f"{text} is listed twice"
            raise ValueError(f"spread-sweep: {override.input_line}: {twice} (the same point twice); give each value "
                             f"once")
        seen[same] = text
    return Dimension(key, values=values)


def preset_params(command: str, fixed: list[str]) -> dict:
    """``hydra.sweeper.params`` of the composed command config (a ``+sweep=...`` preset's grid)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from spread.configs import conf_dir, register

    register(command)
    if GlobalHydra.instance().is_initialized():
        cfg = hydra_compose(config_name=command, overrides=fixed, return_hydra_config=True)
    else:
        with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
            cfg = hydra_compose(config_name=command, overrides=fixed, return_hydra_config=True)
    params = OmegaConf.select(cfg, "hydra.sweeper.params")
    if params is None:
        return {}
    return {str(k): str(v) for k, v in OmegaConf.to_container(params, resolve=False).items()}


def search_space(plan: SweepPlan) -> dict:
    """Ray Tune's param space: one entry per dimension, keyed by the override key."""
    from ray import tune

    space = {}
    for d in plan.dimensions:
        if d.values is not None:
            space[d.key] = tune.grid_search(d.values) if plan.settings.grid else tune.choice(d.values)
        elif d.integer:  # Ray Tune's upper end is exclusive, Hydra's int(interval(a,b)) holds b
            space[d.key] = (tune.lograndint if d.log else tune.randint)(d.low, d.high + 1)
        else:
            space[d.key] = (tune.loguniform if d.log else tune.uniform)(d.low, d.high)
    return space


#: significant digits a drawn value keeps (an interval's draw from random or Optuna search): the value the trial
#: runs, names its folder by and shows in the table
SIGNIFICANT = 4


def drawn(config: dict) -> dict:
    """The trial's values as it runs them: a float a search drew from an interval rounded to :data:`SIGNIFICANT`
    significant digits (``0.012345678901234567`` → ``0.01235``), so folder names, table cells and the point's
    identity carry no 17-digit floats and two draws that round alike are one point; listed values (strings from
    the command line) are kept as written."""
    return {k: float(f"{v:.{SIGNIFICANT}g}") if isinstance(v, float) and math.isfinite(v) else v
            for k, v in config.items()}


def trial_overrides(config: dict) -> list[str]:
    return [f"{k}={format_value(v)}" for k, v in sorted(drawn(config).items())]


def format_value(v) -> str:
    return repr(float(f"{v:.{SIGNIFICANT}g}")) if isinstance(v, float) else str(v)


def point_name(config: dict) -> str:
    """A folder-name part for the trial's values: ``collision0.0075_gravity0.001`` (last key component)."""
    from spread.io import safe_name

    parts = [f"{k.lstrip('+~').split('.')[-1]}{format_value(v)}" for k, v in sorted(config.items())]
    return safe_name("_".join(parts) or "point")[:120]


# ---- trials (run in Ray Tune's trial processes) ----------------------------------------------------------------

def read_metrics(folder: Path) -> dict:
    """Every registered value of an evaluation folder (FID, KID too) with its interval, the point's seconds and
    fingerprint (its short name)."""
    from spread.reporting.intervals import ci_columns, row_intervals
    from spread.experiments.points import read_point
    from spread.reporting.runs import record_metrics
    from spread.io import read_json_object

    metrics = read_json_object(folder / "metrics.json")
    intervals = ci_columns(row_intervals(metrics, folder))
    row = {}
    for name in (n for n in record_metrics() if n in metrics and not n.startswith("n_") and n != "fid_status"):
        row[name] = metrics.get(name)
        for bound in ("lo", "hi"):
            if f"{name}_{bound}" in intervals:
                row[f"{name}_{bound}"] = intervals[f"{name}_{bound}"]
    row.update({k: intervals.get(k) for k in ("ci_level", "ci_resamples", "ci_seed")})
    point = read_point(folder) or {}
    row.update(n_scenes=metrics.get("n_scenes"), n_failed=metrics.get("n_failed"), seconds=point.get("seconds"),
               fingerprint=point.get("short"))
    return row


def sample_trial(config: dict, plan: dict, commands) -> None:
    """One sampling + evaluation point (module docstring) through ``commands`` (the sweep command's
    :class:`~spread.commands.in_process.InProcessCommands`); reports its metrics to Tune."""
    from ray import tune

    from spread.experiments.points import point_lock

    started = time.perf_counter()
    in_launch_folder(plan)
    config = drawn(config.get(POINT_KEY, config))
    runs = []
    for seed in point_seeds(config, plan):
        folder, cfg, overrides = sample_point(config, plan, seed)
        with point_lock(folder):  # a trial of the same point running now: wait for it, then re-use its result
            result, _ = commands.sample_config(cfg, overrides)
        runs.append({"seed": seed, "point": folder.name, "reused": result is None, "trial_pid": os.getpid(),
                     "startup_seconds": None if result is None else result.manifest.get("startup_seconds")})
    rows = [{**read_metrics(Path(plan["points"]) / run["point"]), **run} for run in runs]
    tune.report({**seed_mean(rows, plan["metric"]), "runs": json.dumps(runs), "node": node_id(),
                 "trial_seconds": round(time.perf_counter() - started, 3)})


def in_launch_folder(plan: dict) -> None:
    """Run the trial in the folder ``spread-sweep`` was launched from (where it exists: on the driver's machine),
    not in Ray Tune's trial folder, so relative paths on the command line (``ckpt=runs/x/last.ckpt``,
    ``data.root=data``) mean what they meant to the user."""
    if plan.get("cwd") and Path(plan["cwd"]).is_dir():
        os.chdir(plan["cwd"])


def seed_mean(rows: list[dict], metric: str) -> dict:
    """One report for the searcher from a point's runs (one per seed): the first run's fields, ``metric`` the mean
    over the seeds whose value is a number."""
    values = [r[metric] for r in rows if isinstance(r.get(metric), (int, float)) and math.isfinite(r[metric])]
    return {**rows[0], metric: sum(values) / len(values) if values else None}


def point_seeds(config: dict, plan: dict) -> list[int | None]:
    """The sampling seeds of a point: ``[None]`` (the command's own seed, no seed in the folder name) for
    ``seeds=1``; else ``seeds`` consecutive seeds from the point's ``seed`` setting."""
    from spread.configs import compose

    if int(plan.get("seeds") or 1) == 1:
        return [None]
    first = int(compose("sample", [*plan["fixed"], *trial_overrides(config), "out_dir=unset"]).seed)
    return [first + i for i in range(int(plan["seeds"]))]


def sample_point(config: dict, plan: dict, seed: int | None = None):
    """(run folder, composed config, overrides) of a sampling point: ``points/<values>_<short fingerprint>``
    (``<values>_seed<seed>_<short fingerprint>`` for one of several seeds)."""
    from spread.configs import compose
    from spread.experiments.points import point_folder
    from spread.runtime.fingerprint import point_fingerprint, short

    name = point_name(config) + ("" if seed is None else f"_seed{seed}")
    overrides = [*plan["fixed"], *trial_overrides(config), *([] if seed is None else [f"seed={seed}"]),
                 f"experiment_name={plan['name']}", f"logger.run_name={plan['name']}/{name}",
                 "sweep_dir=null"]  # a Hydra grid preset's folder (+sweep=guidance_grid): this sweep is out_dir
    cfg = compose("sample", [*overrides, "out_dir=unset"])
    if not plan.get("trial_gpus") and str(cfg.device) == "auto" and int(cfg.workers) == 0:
        # the trial samples in its own process, which Ray gives no GPU when it asks for none: auto is the CPU
        # there, and so here (the driver may see a GPU: it found no finished point and sent each back to a trial)
        overrides.append("device=cpu")
        cfg.device = "cpu"
    fingerprint = point_fingerprint(cfg)
    folder = point_folder(Path(plan["points"]) / f"{name}_{short(fingerprint)}", fingerprint)
    cfg.out_dir = str(folder)
    return folder, cfg, [*overrides, f"out_dir={folder}"]


def finished_point(config: dict, plan: dict) -> list[dict] | None:
    """The rows (one per seed) of a sampling point whose folders are all finished with the same fingerprint (no
    trial needed); None when one is not."""
    from spread.experiments.points import check_point

    rows = []
    for seed in point_seeds(config, plan):
        folder, cfg, _ = sample_point(config, plan, seed)
        if not check_point(cfg, folder).reuse:
            return None
        rows.append({**{k: parse_number(v) for k, v in config.items()}, **read_metrics(folder), "point": folder.name,
                     "seed": seed, "reused": True, "trial_seconds": 0.0, "node": None, "status": "ok"})
    return rows


def node_id() -> str:
    import ray

    return ray.get_runtime_context().get_node_id()


class TuneReport:
    """Lightning callback: every validation's logged values to Ray Tune (what ASHA compares), with the training
    step and the point's folder name (so a trial the scheduler stops is listed with the step it stopped at)."""

    def __new__(cls, metric: str, point: str | None = None):
        import lightning as L

        class _Report(L.Callback):
            def on_validation_end(self, trainer, module):
                from ray import tune

                if trainer.sanity_checking:
                    return
                logged = {k: float(v) for k, v in trainer.callback_metrics.items() if getattr(v, "numel", lambda: 1)() == 1}
                if metric in logged:
                    tune.report({**logged, "step": int(trainer.global_step), "point": point, "status": "running"})

        return _Report()


def train_trial(config: dict, plan: dict, commands) -> None:
    """One training run into its point folder, done or not by the platform's done-check (its identity: the
    composed config and the data's content, recorded in the folder's ``point.json``)."""
    from ray import tune

    from spread.experiments.points import point_lock
    from spread.io import read_json_object

    started = time.perf_counter()
    in_launch_folder(plan)
    config = drawn(config.get(POINT_KEY, config))
    folder, identity, overrides = train_point(config, plan)
    with point_lock(folder):  # a trial of the same point running now: wait for it, then re-use its run
        reused = train_point_run(folder, identity, overrides, plan, commands)
    summary = read_json_object(folder / "metrics.json")
    logged = {k: v for k, v in (summary.get("metrics") or {}).items() if isinstance(v, (int, float))}
    tune.report({**logged, "point": folder.name, "reused": reused, "status": "ok",
                 "seconds": round(time.perf_counter() - started, 3),
                 "trial_seconds": round(time.perf_counter() - started, 3), "node": node_id()})


#: settings of ``conf/train.yaml`` left out of a training point's identity: its folder, the run folders' root and
#: the tracking (``logger=mlflow`` pins ``paths.runs_dir`` and the store to absolute paths in the driver, which must
#: not make a point depend on the folder the sweep is launched from)
UNTRAINED_KEYS = ("out_dir", "paths", "logger")


def train_point(config: dict, plan: dict) -> tuple[Path, dict, list[str]]:
    """(folder, identity, overrides) of a training point: ``points/<values>_<short identity>``; the identity is
    the composed config (less :data:`UNTRAINED_KEYS`), the data's content and the numbers version."""
    from spread.configs import compose
    from spread.experiments.points import point_folder
    from spread.runtime.fingerprint import (NUMBERS_VERSION, dataset_digest, init_weights_digest, normalised, short,
                                            training_config_identity)

    name = point_name(config)
    overrides = [*plan["fixed"], *trial_overrides(config), f"experiment_name={plan['name']}"]
    cfg = compose("train", [*overrides, "out_dir=unset"])
    plain = OmegaConf.to_container(cfg, resolve=True)
    for key in UNTRAINED_KEYS:  # where the run is written and logged changes none of its numbers
        plain.pop(key, None)
    root = OmegaConf.select(cfg, "data.root")
    weights = init_weights_digest(plain)  # what model.init_from holds now, recorded with the point
    identity = normalised({"config": training_config_identity(plain),
                           "data": dataset_digest(root, ["train", "val"]) if root else None,
                           "numbers_version": NUMBERS_VERSION, **({"init_from_sha256": weights} if weights else {})})
    return point_folder(Path(plan["points"]) / f"{name}_{short(identity)}", identity), identity, overrides


def train_point_run(folder: Path, identity: dict, overrides: list[str], plan: dict, commands) -> bool:
    """Train the point into ``folder`` unless it is finished with ``identity`` (the platform's done-check);
    True when re-used."""
    from spread.configs import compose
    from spread.experiments.points import PointDecision, finish_point, read_point, start_point
    from spread.runtime.fingerprint import done_check
    from spread.training.fit import train as fit

    started = time.perf_counter()
    record, finished = read_point(folder), (folder / "metrics.json").exists()
    # a folder without a record carries this identity in its name (made before point.json): the same inputs
    before = record.get("fingerprint") if record is not None else identity if folder.exists() else None
    decision = done_check(before, identity, present=folder.exists(), finished=finished)
    last = folder / "checkpoints" / "last.ckpt"
    if not decision.reuse:
        resume = last.exists() and not decision.fresh
        run = [*overrides, f"out_dir={folder}", f"ckpt_path={last}" if resume else "ckpt_path=null"]
        cfg = compose("train", run)
        start_point(folder, PointDecision(False, decision.fresh, decision.reason, identity))
        commands.record_config(cfg, folder, run)
        callbacks = [TuneReport(plan["metric"], folder.name)] if plan.get("scheduler") else []
        fit(cfg, run_dir=folder, extra_callbacks=callbacks)
        finish_point(folder, round(time.perf_counter() - started, 3))
    return decision.reuse


# ---- the sweep ------------------------------------------------------------------------------------------------

@dataclass
class SweepResult:
    """rows: one per trial (per seed of a point with ``seeds`` > 1), as in results.csv; points: one per point (the
    rows themselves, or their means over seeds), as in results.md; best: the best point."""

    rows: list[dict]
    best: dict | None
    csv: Path
    md: Path
    seconds: float
    points: list[dict] = field(default_factory=list)


def checked_sweep(plan: SweepPlan) -> dict:
    """What every trial of ``plan`` shares, once the sweep's checks passed (inert dimensions, a started
    cluster's resources, the first point's inputs): run before anything is written, Ray starts or a tracker
    opens (the sweep command checks before its parent run opens); ``ValueError`` naming the setting."""
    s = plan.settings
    out = Path(s.out_dir).resolve()
    shared = {"fixed": plan.fixed, "points": str(out / "points"), "name": s.name, "metric": s.metric,
              "scheduler": s.scheduler, "seeds": s.seeds, "cwd": os.getcwd(), "trial_gpus": float(s.trial_gpus or 0)}
    from spread.io import check_folder_kind
    from spread.reporting.runs import record_metrics

    check_folder_kind(out, "spread-sweep", {"sweep"})  # a dataset's or another command's folder: refused
    if s.seeds > 1 and any(d.key == "seed" for d in plan.dimensions):  # the points' seeds overlapped: a wrong table
        raise ValueError(f"spread-sweep: seed is swept and seeds={s.seeds}: a point samples the seeds from its seed "
                         f"on, so points of neighbouring seeds share runs; sweep seed with seeds=1, or give seeds="
                         f"{s.seeds} alone")
    known = [n for n in record_metrics() if not n.startswith("n_") and n != "fid_status"]
    if s.command == "sample" and s.metric not in known:  # a typo marked no point best, or failed Optuna's trials
        raise ValueError(f"spread-sweep: metric={s.metric}: no point reports it (a sampling sweep's points report "
                         f"{', '.join(known)})")
    check_point_records(out / "points")
    check_inert_dimensions(plan, shared)
    check_started_cluster(s)
    check_first_point(plan, shared)
    return shared


def check_point_records(points: Path) -> None:
    """Every record a point folder holds (``point.json``, ``metrics.json``, ``sampling.json``) is a file, else a
    ``ValueError`` naming it before any trial: a folder there (a hand edit) failed its trial in Ray's tracebacks
    when the point was cleared for a redo. A record that is a file but does not read is the point's own business
    (it is redone)."""
    if not points.is_dir():
        return
    for record in ("point.json", "metrics.json", "sampling.json"):
        for path in sorted(points.glob(f"*/{record}")):
            if not path.is_file() and not path.is_symlink():
                raise ValueError(f"spread-sweep: {path}: not a file (a point's record); remove it, and the point is "
                                 f"made again")


def run_sweep(plan: SweepPlan, commands, shared: dict | None = None) -> SweepResult:
    """Run every trial of ``plan`` on Ray Tune and write ``results.csv`` / ``results.md`` (module docstring);
    ``commands``: what a trial runs (:class:`~spread.commands.in_process.InProcessCommands`: ``sample_config``,
    ``record_config``), handed to each trial by the sweep command; ``shared``: :func:`checked_sweep`'s answer when
    the caller checked already."""
    from ray import tune

    from spread.experiments.tuning import limited, search_spec, trial_scheduler_spec
    from spread.tracking.parent import nested_trial

    s = plan.settings
    out = Path(s.out_dir).resolve()
    started = time.perf_counter()
    trial = sample_trial if s.command == "sample" else train_trial
    trial = nested_trial(trial)  # its runs nest under the sweep's parent run (spread.tracking.parent)
    shared = checked_sweep(plan) if shared is None else shared
    (out / "points").mkdir(parents=True, exist_ok=True)
    head = {"GPU": float(s.trial_gpus)} if s.trial_gpus else {}
    resources = tune.PlacementGroupFactory([head, {"CPU": float(s.trial_cpus)}])
    trainable = tune.with_resources(tune.with_parameters(trial, plan=shared, commands=commands), resources)
    search = search_spec(s.search)
    searcher = limited(search.build(s) if search.build is not None else None, s.max_concurrent)  # every search
    scheduler = trial_scheduler_spec(s.scheduler).build(s) if s.scheduler is not None else None
    samples = 1 if search.grid else int(s.num_samples)
    space, rows = search_space(plan), []
    if search.grid and s.command == "sample":  # finished points are read on the driver, no trial
        todo = []
        for config in grid_points(plan):
            done = finished_point(config, shared)
            rows.extend(done) if done is not None else todo.append(config)
        space = {POINT_KEY: tune.grid_search(todo)} if todo else None
    if space is not None:
        rows += tune_rows(s, trainable, space, searcher, scheduler, samples, plan, out, shared)
    rows.sort(key=lambda r: (values_of(r, plan), r.get("seed") or 0))
    point_settings(rows, out / "points")
    points = seed_means(rows, plan) if s.seeds > 1 else rows
    best = mark_best(points, s.metric, s.mode)
    for r in rows:  # a point's every seed row is marked with it
        r["best"] = best is not None and values_of(r, plan) == values_of(best, plan)
    csv_path, md_path = write_results(rows, out, plan, best, points)
    return SweepResult(rows, best, csv_path, md_path, round(time.perf_counter() - started, 3), points)


def values_of(row: dict, plan: SweepPlan) -> tuple:
    """A row's swept values (what names its point, less the seed)."""
    return tuple(str(row.get(d.key)) for d in plan.dimensions)


#: level of the interval over a point's sampling seeds (``seeds=K``)
SEED_LEVEL = 0.95


def seed_means(rows: list[dict], plan: SweepPlan) -> list[dict]:
    """One row per point (what :func:`spread.results.over_seeds` gives for a frame) from its rows of ``seeds=K``
    sampling seeds: each metric the mean over the seeds, ``<metric>_sd`` their sample sd and ``<metric>_lo`` / ``_hi`` the Student-t interval at :data:`SEED_LEVEL` over
    the seeds (not over scenes); ``seeds`` the seeds, ``status`` ok when every seed's is. Rows of one run (the same
    point folder and seed: a drawing search repeating a point) count once."""
    from spread.reporting.tables import columns_of
    from spread.results.stats import t_interval

    metrics = [c.key for c in columns_of(rows)]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(values_of(r, plan), []).append(r)
    points = []
    for rows_of_point in groups.values():
        runs: dict[tuple, dict] = {}  # a run drawn twice (a search repeating a point) is one run of its seed
        for r in rows_of_point:
            runs.setdefault((r.get("point"), r.get("seed")), r)
        mine = list(runs.values())
        ok = [r for r in mine if r.get("status") == "ok"]
        first = mine[0]
        row = {**{d.key: first.get(d.key) for d in plan.dimensions}, "seeds": [r.get("seed") for r in mine],
               "n_seeds": len(ok), "status": "ok" if len(ok) == len(mine) else f"{len(mine) - len(ok)} of "
                                                                                  f"{len(mine)} seeds failed",
               "point": str(first.get("point", "")).split("_seed")[0],
               "seconds": sum(float(r.get("seconds") or 0.0) for r in mine),
               "settings": {k: v for k, v in (first.get("settings") or {}).items() if k != "seed"}}
        for key in metrics:
            stats = t_interval([r[key] for r in ok if isinstance(r.get(key), (int, float))], SEED_LEVEL)
            row.update(zip((key, f"{key}_sd", f"{key}_lo", f"{key}_hi"),
                           (None if math.isnan(v) else v for v in stats)))
        points.append(row)
    return points


#: Most points composed to find a swept key that changes nothing (beyond: each key is probed at the others' first
#: values only).
PROBE_POINTS = 64


def probe_values(d: Dimension) -> list:
    """Values of ``d`` that :func:`check_inert_dimensions` composes: every listed value (at most 4: the first, the
    last and two between), or an interval's two ends."""
    if d.values is None:
        return [d.low, d.high]
    values = list(d.values)
    return values if len(values) <= 4 else [values[0], values[len(values) // 3], values[2 * len(values) // 3],
                                            values[-1]]


def check_inert_dimensions(plan: SweepPlan, shared: dict) -> None:
    """Before any trial of a sampling sweep: ``ValueError`` naming a swept key none of whose values changes a
    point's fingerprint (:func:`spread.runtime.fingerprint.point_fingerprint`, what a sampled-and-evaluated result
    depends on) whatever the other keys' values: every value would repeat the same run, and the table would star
    one of identical rows. A guidance weight while guidance is off is the usual case."""
    import itertools

    from spread.runtime.fingerprint import point_fingerprint, short

    dims = plan.dimensions
    if plan.settings.command != "sample" or not any(len(probe_values(d)) > 1 for d in dims):
        return
    probes = [probe_values(d) for d in dims]
    if math.prod(len(v) for v in probes) <= PROBE_POINTS:
        combos = list(itertools.product(*probes))
    else:  # each key alone, the others at their first values
        base = tuple(v[0] for v in probes)
        combos = [base[:i] + (v,) + base[i + 1:] for i, values in enumerate(probes) for v in values]
    guided, prints = set(), {}
    for combo in combos:
        config = {d.key: v for d, v in zip(dims, combo)}
        fingerprint = point_fingerprint(sample_point(config, shared)[1])
        prints[combo] = short(fingerprint)
        guided.add(fingerprint.get("guidance") is not None)
    for i, d in enumerate(dims):
        if len(probes[i]) < 2:
            continue
        groups: dict[tuple, set] = {}
        for combo, fp in prints.items():
            groups.setdefault(combo[:i] + combo[i + 1:], set()).add((combo[i], fp))
        varied = [g for g in groups.values() if len({v for v, _ in g}) > 1]
        if varied and all(len({fp for _, fp in g}) == 1 for g in varied):
            hint = (" (guidance is off in every point — guidance.mode none or every weight 0 — so its settings are "
                    "not used: switch it on, e.g. guidance=refine)" if guided == {False} else "")
            shown = [format_value(v) for v in probes[i]]
            raise ValueError(f"spread-sweep: {d.key}: its values {shown} give every point the same fingerprint (what "
                             f"a sampled and evaluated result depends on){hint}; every value would repeat the same "
                             f"run — remove the key from the sweep or sweep something that changes the result")


def check_first_point(plan: SweepPlan, shared: dict) -> None:
    """Before Ray starts and anything is written: the sweep's first point passes the checks its command makes of its
    inputs (a sampling point: the device, the checkpoint and the split's graphs,
    :func:`spread.sampling.run.check_inputs`; a training point: the ``trainer.*`` values and the dataset's splits),
    so a checkpoint or data folder that is not there is refused in one line, not a failed trial per point with
    Ray's tracebacks and a table of empty rows."""
    try:
        _check_first_point(plan, shared)
    except ValueError as exc:
        said = str(exc)
        drawn_floats = [d for d in plan.dimensions if d.values is None and not d.integer
                        and f"{d.key.lstrip('+')}={format_value(float(probe_values(d)[0]))}" in said]
        if not drawn_floats:
            raise
        d = drawn_floats[0]
        raise ValueError(f"{said} (interval({d.low:g},{d.high:g}) draws real numbers: {whole_way(d)})") from None


def whole_way(d: Dimension) -> str:
    """How to sweep the whole numbers of the real interval ``d`` (the hint of :func:`check_first_point`)."""
    low, high = math.ceil(d.low), math.floor(d.high)
    if low > high:
        return "it holds no whole number; give a whole value"
    if low == high:
        return f"its one whole number is {low}: write {d.key.lstrip('+')}={low}"
    drawn = f"int(interval({low},{high}))"
    return f"write {d.key}='{f'tag(log,{drawn})' if d.log else drawn}' to draw whole numbers"


def _check_first_point(plan: SweepPlan, shared: dict) -> None:
    from spread.configs import compose, to_object

    config = {d.key: probe_values(d)[0] for d in plan.dimensions}
    if plan.settings.command == "sample":
        from spread.sampling.run import check_inputs

        check_inputs(to_object(sample_point(config, shared)[1]))
        return
    import hydra

    from spread.training.fit import trainer_validates
    from spread.training.trainer_settings import built, check_training_settings

    cfg = compose("train", [*shared["fixed"], *trial_overrides(config), "out_dir=unset"])
    check_training_settings(cfg)
    built(lambda: hydra.utils.instantiate(cfg.data), "data").check_fit(trainer_validates(cfg.trainer))


def grid_points(plan: SweepPlan) -> list[dict]:
    """Every combination of the dimensions' values (a grid)."""
    import itertools

    keys = [d.key for d in plan.dimensions]
    return [dict(zip(keys, combo)) for combo in itertools.product(*[d.values for d in plan.dimensions])]


def tune_rows(s: SweepSettings, trainable, space, searcher, scheduler, samples: int, plan: SweepPlan,
              out: Path, shared: dict | None = None) -> list[dict]:
    """Run the trials on Ray Tune (one Ray session) and return their rows; ``shared``: the trials' plan (what the
    search's identity reads its inputs through, :func:`search_inputs`)."""
    from ray import tune

    from spread.runtime.ray import RaySettings, ray_session

    settings = RaySettings(address=s.address, num_cpus=s.num_cpus, log_to_driver=False)
    storage = out / "tune"
    if not (storage / s.folder_name).resolve().is_relative_to(out.resolve()):  # safe_name makes this impossible
        raise ValueError(f"spread-sweep: name={s.name}: Ray Tune's folder would leave out_dir={out}")
    with ray_session(settings, owner=out):
        check_resources(s)
        if resumable(plan, out, shared):  # the same search, same inputs: its searcher and trials where they stopped
            log.info("spread-sweep: resuming the search recorded in %s", storage / s.folder_name)
            tuner = tune.Tuner.restore(str(storage / s.folder_name), trainable=trainable, resume_unfinished=True,
                                       resume_errored=True, param_space=space)
        else:
            tuner = tune.Tuner(
                trainable, param_space=space,
                tune_config=tune.TuneConfig(num_samples=samples,  # max_concurrent: the searcher's (tuning.limited)
                                            search_alg=searcher, scheduler=scheduler, reuse_actors=True),
                run_config=tune.RunConfig(storage_path=str(storage), name=s.folder_name, verbose=0,
                                          failure_config=tune.FailureConfig(max_failures=1)))
        with tune_leaves_ctrl_c():
            grid = tuner.fit()
        return [row for r in grid for row in result_rows(r, plan, out)]


@contextlib.contextmanager
def tune_leaves_ctrl_c():
    """Ray Tune without its own SIGINT handler while it runs the trials: with it, Ctrl-C ended ``tuner.fit()``
    normally, and the sweep wrote a table of the points finished so far as if it were whole (exit 0). Without it,
    Ctrl-C is a ``KeyboardInterrupt`` as in every other command (``interrupted (Ctrl-C)``, exit 130, no table); a
    relaunch goes on from the points recorded."""
    before = os.environ.get("TUNE_DISABLE_SIGINT_HANDLER")
    os.environ["TUNE_DISABLE_SIGINT_HANDLER"] = "1"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("TUNE_DISABLE_SIGINT_HANDLER", None)
        else:
            os.environ["TUNE_DISABLE_SIGINT_HANDLER"] = before


#: the search a sweep folder's Ray Tune state belongs to (:func:`resumable`)
SEARCH_RECORD = "search.json"


def search_identity(plan: SweepPlan, shared: dict | None = None) -> dict:
    """What a drawing search's suggestions and its trials' results depend on: the fixed overrides, the dimensions, the
    search, its seed, trial count, metric, mode, trial scheduler and seeds, and (with ``shared``, the trials' plan)
    the content those overrides point to (:func:`search_inputs`)."""
    s = plan.settings
    return {"fixed": list(plan.fixed), "dimensions": [vars(d) for d in plan.dimensions], "search": s.search,
            "search_seed": s.search_seed, "num_samples": s.num_samples, "metric": s.metric, "mode": s.mode,
            "scheduler": s.scheduler, "asha": dict(s.asha or {}), "seeds": s.seeds, "command": s.command,
            **({"inputs": search_inputs(plan, shared)} if shared is not None else {})}


def search_inputs(plan: SweepPlan, shared: dict) -> dict:
    """The content the sweep's fixed settings point to, the same for every point: a sampling sweep's checkpoint,
    data and reference (a point's fingerprint at the dimensions' first values, those parts), a training sweep's data.
    New weights or rooms at the same paths are another search (a resumed one would report the old trials)."""
    from spread.runtime.fingerprint import point_fingerprint

    first = {d.key: probe_values(d)[0] for d in plan.dimensions}
    if plan.settings.command != "sample":
        return {"data": train_point(first, shared)[1].get("data")}
    fingerprint = point_fingerprint(sample_point(first, shared)[1])
    evaluation = fingerprint.get("evaluation") or {}
    return {"ckpt_sha256": fingerprint.get("ckpt_sha256"), "data": fingerprint.get("data"),
            "reference": evaluation.get("reference"), "assets_sha256": evaluation.get("assets_sha256")}


def resumable(plan: SweepPlan, out: Path, shared: dict | None = None) -> bool:
    """Whether this launch resumes the Ray Tune experiment in ``out`` (a drawing search — random, Optuna, … — killed
    or finished before, with the same :func:`search_identity`): Tune restores the searcher's state (Optuna's study
    and sampler, the random generator) and the trials where they stopped, so the resumed sweep makes the same
    suggestions as an uninterrupted one. Otherwise the folder's old Tune state is moved aside
    (``tune/<name>.<time>``) and this launch's search recorded. A grid needs none of this (every point is known;
    finished ones are re-used by their fingerprints)."""
    from ray import tune

    from spread.io import read_json, write_json_atomic
    from spread.runtime.fingerprint import normalised

    s = plan.settings
    state, record = out / "tune" / s.folder_name, out / SEARCH_RECORD
    if s.grid:
        return False
    identity = normalised(search_identity(plan, shared))
    try:
        before = read_json(record) if record.exists() else None
    except (OSError, ValueError):
        before = None
    if before == identity and tune.Tuner.can_restore(str(state)):
        return True
    if state.exists():
        state.rename(state.with_name(f"{state.name}.{time.strftime('%Y%m%d-%H%M%S')}"))
    write_json_atomic(record, identity)
    return False


def check_started_cluster(s: SweepSettings) -> None:
    """A cluster this sweep starts has its ``num_cpus``: a trial it cannot hold is refused before Ray starts."""
    from spread.runtime.ray import RaySettings

    if RaySettings(address=s.address, num_cpus=s.num_cpus).starts_cluster and s.num_cpus:
        check_resources(s, [{"CPU": float(s.num_cpus)}], keys=("trial_cpus",))


def check_resources(s: SweepSettings, nodes: list[dict] | None = None,
                    keys: tuple[str, ...] = ("trial_cpus", "trial_gpus")) -> None:
    """``ValueError`` when no live node holds a trial's bundle (``trial_cpus`` CPUs; ``trial_gpus`` GPUs), which
    Ray Tune would wait for for ever. ``nodes``: each node's resources (default: the live nodes of this process's
    Ray session); ``keys``: the settings checked."""
    if nodes is None:
        import ray

        nodes = [n.get("Resources") or {} for n in ray.nodes() if n.get("Alive")]
    for key, resource in (("trial_cpus", "CPU"), ("trial_gpus", "GPU")):
        if key not in keys:
            continue
        wanted = float(getattr(s, key))
        largest = max((float(n.get(resource, 0)) for n in nodes), default=0.0)
        if wanted > largest:
            raise ValueError(f"spread-sweep: {key}={wanted:g}: no node of the Ray cluster has that many {resource}s "
                             f"(the largest has {largest:g}, over {len(nodes)} node(s)); a trial would never start — "
                             f"lower {key} or add nodes")


def result_rows(result, plan: SweepPlan, out: Path) -> list[dict]:
    """A trial's rows: one, or one per seed of a sampling point (its report's ``runs``: each seed's folder, read
    back here)."""
    row = result_row(result, plan)
    runs = row.pop("runs", None)
    if not runs:
        return [row]
    return [{**row, **read_metrics(out / "points" / run["point"]), **run} for run in json.loads(runs)]


def result_row(result, plan: SweepPlan) -> dict:
    given = result.config.get(POINT_KEY, result.config)
    config = drawn({d.key: given.get(d.key) for d in plan.dimensions})
    row = {k: parse_number(v) for k, v in config.items()}
    metrics = dict(result.metrics or {})
    for key in list(metrics):
        if key in ("config", "trial_id", "date", "timestamp", "pid", "hostname", "node_ip", "time_this_iter_s",
                   "time_total_s", "time_since_restore", "iterations_since_restore", "training_iteration", "done",
                   "checkpoint_dir_name", "should_checkpoint", "experiment_tag"):
            metrics.pop(key)
    row.update(metrics)
    # a training trial's last report is a validation's ("running") when a trial scheduler stopped it there
    stopped = not result.error and metrics.get("status") == "running"
    row["status"] = "error" if result.error else "stopped" if stopped else "ok"
    if stopped:
        row["stopped_at_step"] = metrics.get("step")
    if result.error:
        row["error"] = error_line(result.error)
    return row


def error_line(error) -> str:
    """A trial's error in one readable line: the exception's own last line (Ray wraps it in a traceback headed by
    the worker's colour-coded name), at most 300 characters."""
    import re

    lines = [re.sub(r"\x1b\[[0-9;]*m", "", line).strip() for line in str(error).splitlines()]
    lines = [line for line in lines if line]
    return (lines[-1] if lines else type(error).__name__)[:300]


def parse_number(v):
    try:
        return float(v) if isinstance(v, str) and any(c.isdigit() for c in v) else v
    except ValueError:
        return v


def mark_best(rows: list[dict], metric: str, mode: str) -> dict | None:
    """The best row by ``metric`` (marked ``best``); only a finished trial's valid value competes (finite, inside
    the metric's bounds: :meth:`spread.reporting.tables.Column.valid`; not a trial a scheduler stopped)."""
    from spread.reporting.tables import Column, metric_column
    from spread.metrics.registry import display_spec

    spec = display_spec(metric)
    column = metric_column(spec) if spec is not None else Column(metric, metric, 4, mode)
    scored = [r for r in rows if r.get("status", "ok") == "ok" and column.valid(r.get(metric)) is not None]
    best = (max if mode == "max" else min)(scored, key=lambda r: r[metric]) if scored else None
    for r in rows:
        r["best"] = r is best
    return best


def setting_of(key: str) -> str:
    """The settings key (:func:`spread.runtime.fingerprint.settings`) a swept override key names."""
    return key.lstrip("+~").replace("guidance.terms.", "guidance.")


def point_settings(rows: list[dict], points: Path) -> None:
    """Each row's ``settings`` and ``identity``: its point's recorded identity (``point.json``), read here."""
    from spread.experiments.points import read_point
    from spread.reporting.runs import identity_fields

    for r in rows:
        record = read_point(points / str(r.get("point"))) if r.get("point") else None
        if record and isinstance(record.get("fingerprint"), dict):
            r.update(identity_fields(record["fingerprint"]))


def write_results(rows: list[dict], out: Path, plan: SweepPlan, best: dict | None,
                  points: list[dict] | None = None) -> tuple[Path, Path]:
    """``results.csv`` (every field of every row: one per trial, one per seed with ``seeds`` > 1) and
    ``results.md`` (one line per point — ``points``, the rows' means over seeds when there are several —: the swept
    settings — named as settings: ``+guidance.terms.floor_push`` is ``guidance.floor_push`` —, every other setting
    that differs between the points, each metric in its display unit with ± half-width of its interval (over
    scenes; over seeds with several seeds), best marked), through the one table writer
    (:func:`spread.reporting.tables.write_tables`); the settings every point shares under the table."""
    from spread.reporting.runs import name_differences
    from spread.reporting.tables import Column, columns_of, metric_columns, write_tables

    points = rows if points is None else points
    keys = [setting_of(d.key) for d in plan.dimensions]  # a swept key named as the setting it is
    for r in [*rows, *([] if points is rows else points)]:
        for d in plan.dimensions:
            if d.key != setting_of(d.key) and d.key in r:
                r[setting_of(d.key)] = r.pop(d.key)
        r["mark"] = "★" if r.get("best") else ""
    seeded = points is not rows
    csv_keys = list(dict.fromkeys([*keys, "seed", "best", "point", "status",
                                   *name_differences(rows, exclude={*keys, "seed"}),
                                   *[k for r in rows for k in r if k not in ("settings", "mark")]]))
    csv_keys = [k for k in csv_keys if k != "seed" or any(r.get("seed") is not None for r in rows)]
    if seeded:  # units from the metric registry (no columns given)
        rows_csv = write_tables(rows, [], out / "results", formats=("csv",), csv_keys=csv_keys)["csv"]
        rows = points
    settings = [r.get("settings") or {} for r in rows]
    differ = name_differences(rows, exclude={*keys, "seed"})
    metric = plan.settings.metric
    metrics = [c for c in columns_of(rows) if any(r.get(c.key) is not None for r in rows)] or \
        (metric_columns([metric]) if metric in metric_names() else [Column(metric, metric, 4, plan.settings.mode)])
    columns = [Column("mark", ""), *[Column(k, k) for k in [*keys, *differ]], *metrics,
               *([Column("n_seeds", "seeds")] if seeded else []), Column("seconds", "seconds", 1),
               Column("point", "point")]
    shared = {k: v for k, v in (settings[0] if settings else {}).items()
              if k not in differ and k not in keys and all(s.get(k) == v for s in settings)}
    shown = next((c for c in metrics if c.key == metric), Column(metric, metric, 4))
    notes = [f"Best: {best.get('point')} ({shown.label} = {shown.format(best[metric])})." if best is not None else "",
             "Every point: " + ", ".join(f"{k}={v}" for k, v in shared.items()) + "." if shared else ""]
    if seeded:
        seeds = rows[0].get("seeds") if rows else []
        note = (f"Each cell: the mean over the point's {len(seeds)} sampling seeds {seeds} ± half the width of the "
                f"{SEED_LEVEL:.0%} Student-t interval over those seeds; results.csv has one row per seed, each with "
                f"its interval over scenes.")
    else:
        note = table_note(rows)
    paths = write_tables(rows, columns, out / "results", formats=("md",) if seeded else ("md", "csv"),
                         csv_keys=csv_keys,
                         caption=f"# sweep {plan.settings.name}: {len(rows)} points, best by {plan.settings.metric} "
                                 f"({plan.settings.mode}) marked ★",
                         note=note, md_extra="\n\n".join(n for n in notes if n))
    return (rows_csv if seeded else paths["csv"]), paths["md"]


def metric_names() -> list[str]:
    from spread.metrics.registry import METRICS

    return METRICS.names()


def table_note(rows: list[dict]) -> str:
    from spread.reporting.intervals import table_note as note

    return note(rows)


def read_results_csv(path) -> list[dict]:
    """``results.csv`` back as rows (numbers as floats, empty cells as None)."""
    from spread.io import read_text_checked

    rows = []
    for r in csv.DictReader(io.StringIO(read_text_checked(path), newline="")):
        rows.append({k: (None if v == "" else parse_number(v)) for k, v in r.items()})
    return rows
