"""``spread-ablate``: the ablation table (DESIGN §3 variants, §6 protocol) as resumable stages.

The ablation is a sequence of the platform's own commands, run in this process through a
:class:`Commands` object (:class:`spread.commands.in_process.InProcessCommands`: ``spread-generate``,
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
interval over scenes (:mod:`spread.reporting.intervals`); the CSV keeps the bounds and the bootstrap's seed.

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
stages run before them, ``train_concurrent`` at a time (Ray tasks of ``train_cpus`` CPUs and ``train_gpus``
GPUs each when > 1, so the ablation trains in the time of its slowest row; 1: one after another in this
process), each in-process or as its own processes through ``train.launcher`` (:mod:`spread.commands.launch`).

**Subsets.** A re-run with some rows (``'variants=[base,guidance]'``) re-runs those and keeps the folder's
other finished rows in the table, each marked as carried over (:mod:`spread.experiments.stages`, *Published
tables only grow*).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from spread.reporting.intervals import ci_columns, row_intervals, table_note
from spread.experiments.stages import (
    Commands, Stage, StageEngine, StageError, StagesResult, StagesSpec, carried_note, sampling_inputs, with_carried)
from spread.reporting.tables import Column, columns_of, write_tables
from spread.guidance.config import GuidanceConfig
from spread.checks import listed_once
from spread.io import read_json

#: What a study returns (:class:`~spread.experiments.stages.StagesResult`).
AblationResult = StagesResult

log = logging.getLogger("spread.ablate")

#: One built-in guidance term at a time (the other built-in weights 0): row name → the term kept.
TERMS = {f"guidance_{term}": term for term in GuidanceConfig.weight_keys()}
#: The registered terms of ours that stand in for a built-in one (the recipe's guidance may use ``settle`` for the
#: vertical gap, ``over`` or ``home`` for the footprint): a one-term row keeps them with their built-in and zeroes
#: them otherwise.
STAND_INS = {"settle": "gravity", "over": "relation", "home": "relation"}
VARIANTS = ("base", "base_time", "geometry", "guidance", *TERMS)
#: Row labels, as in the paper's ablation table.
LABELS = {"base": "Ours (base)", "base_time": "Ours (base), +Geometry's time", "geometry": "+Geometry",
          "guidance": "+Guidance", **{v: f"+Guidance ({t} only)" for v, t in TERMS.items()}}
#: The checkpoint each row samples.
CHECKPOINT_OF = {"base": "base", "base_time": "base_time", "geometry": "geometry", "guidance": "geometry",
                 **{v: "geometry" for v in TERMS}}
#: The trained checkpoints, in training order (``base_time`` last: its steps come from the other two's clocks).
TRAINED = ("base", "geometry", "base_time")
LEDGER = "ablation.json"
TABLE = "ablation"


@dataclass
class AblationSpec(StagesSpec):
    """An ablation (:class:`StagesSpec`, ``conf/ablate.yaml`` documents each list): its rows (``variants``),
    each trained row's own training list, the guidance rows' guidance list, and the row figures."""

    variants: tuple[str, ...] = ("base", "geometry", "guidance")  # conf/ablate.yaml adds the one-term rows
    train_variant: dict[str, list[str]] = field(default_factory=lambda: {v: [f"model.variant={v}"]
                                                                         for v in ("base", "geometry")})
    guidance: list[str] = field(default_factory=list)
    #: each trained checkpoint's own sampling list (base, geometry), added to every row that samples it after the
    #: shared list: ``geometry: [geometry_scale=2.0]`` samples +Geometry and the guidance rows with guidance on its
    #: geometry features, which the base rows have none of
    sample_variant: dict[str, list[str]] = field(default_factory=dict)
    figures: bool = True  # one scene per row in 3D with its relation matrix (ablation_<v>.png)

    def __post_init__(self) -> None:
        super().__post_init__()
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown or not self.variants:
            raise ValueError(f"variants: unknown or none {unknown or list(self.variants)} "
                             f"(choose from {list(VARIANTS)})")
        listed_once(self.variants, "variants")  # one row, shown once: the list asked for what the table does not hold
        self.variants = tuple(v for v in VARIANTS if v in self.variants)
        self.check_given(["base", "geometry"], lambda v: {"method": "spread", "variant": v})
        wrong = [k for k in self.sample_variant if k not in ("base", "geometry")]
        if wrong:
            raise ValueError(f"sample.{wrong[0]}: only the trained checkpoints' rows have their own sampling list "
                             f"(sample.base, sample.geometry)")


class Ablation:
    """The ablation's rows over the stage engine (:class:`~spread.experiments.stages.StageEngine`): which
    checkpoint each row samples, its training and sampling overrides, its table and figures."""

    #: the trained checkpoint each row samples from
    checkpoint_of: dict[str, str] = CHECKPOINT_OF

    def __init__(self, spec: AblationSpec, commands: Commands):
        self.spec = spec
        self.engine = StageEngine(spec, commands, self, LEDGER)
        self.out = spec.out_dir
        self.check_trained_variants()
        self.engine.check_data()
        self.engine.check_lists(list(spec.variants))
        self.engine.check_relaunch(self.trained())

    def check_trained_variants(self) -> None:
        """Each row this ablation trains composes to that row's model (:meth:`StagesSpec.check_trained`):
        ``model.variant`` base for base (and base_time, which trains base's lists), geometry for +Geometry."""
        rows = dict.fromkeys("base" if t == "base_time" else t for t in self.trained())
        self.spec.check_trained({row: [*self.spec.train, *self.spec.train_variant.get(row, [])] for row in rows},
                                lambda v: {"method": "spread", "variant": v}, lambda v: LABELS[v])

    def train_lists(self, trained: str) -> list[str]:
        """The ``spread-train`` overrides of one trained row (the spec's shared list, then the row's own);
        ``base_time``: base's, trained for the steps base makes in +Geometry's training time
        (:meth:`equal_time_steps`)."""
        if trained == "base_time":
            return [*self.spec.train, *self.spec.train_variant.get("base", []),
                    f"trainer.max_steps={self.equal_time_steps()}"]
        return [*self.spec.train, *self.spec.train_variant.get(trained, [])]

    def equal_time_steps(self) -> int:
        """The steps of the ``base_time`` row: +Geometry's training seconds over base's seconds per step, both read
        from the clocks of the two runs trained here (``train/<v>/clock.jsonl``: the training loop's wall seconds at
        the last checkpoint, validation left out; :class:`spread.training.clock.TrainingClock`). The learning-rate
        schedule is sized to these steps as to any ``max_steps``."""
        from spread.training.clock import last_record

        try:
            clocks = {v: last_record(self.engine.train_dir(v)) for v in ("base", "geometry")}
        except ValueError as exc:
            raise StageError(str(exc)) from exc
        missing = [f"train/{v}/clock.jsonl" for v, c in clocks.items() if c is None]
        if missing:
            raise StageError(f"base_time: needs base and +Geometry trained in this ablation (no {missing} under "
                             f"{self.out}; a given checkpoint has no clock)")
        base, geometry = clocks["base"], clocks["geometry"]
        return max(1, round(geometry["seconds"] * base["step"] / base["seconds"]))

    def sample_lists(self, variant: str) -> list[str]:
        """The ``spread-sample`` overrides of one row (the spec's shared list, then its checkpoint's own list
        ``sample_variant``, base's for base_time): the guidance rows add the guidance list; a one-term row then sets
        the other two built-in weights to 0, and every other term the guidance list names but its built-in's
        stand-in (``STAND_INS``)."""
        checkpoint = "base" if self.checkpoint_of[variant] == "base_time" else self.checkpoint_of[variant]
        shared = [*self.spec.sample, *self.spec.sample_variant.get(checkpoint, [])]
        if variant in TERMS:
            kept = TERMS[variant]
            off = [f"guidance.{t}=0.0" for t in TERMS.values() if t != kept]
            off += [f"++guidance.terms.{t}=0.0" for t in self.guidance_terms() if STAND_INS.get(t) != kept]
            return [*shared, *self.spec.guidance, *off]
        return [*shared, *(self.spec.guidance if variant == "guidance" else [])]

    def guidance_terms(self) -> list[str]:
        """The names under ``guidance.terms`` that the guidance rows weigh (λ > 0), asked of the guidance config the
        spec's sample and guidance lists compose to (not read off the override strings)."""
        from omegaconf import OmegaConf

        from spread.configs import compose

        cfg = compose("sample", ["ckpt=unset", "data.root=unset", "out_dir=unset", *self.spec.sample,
                                 *self.spec.guidance])
        guidance = GuidanceConfig.from_config(OmegaConf.to_container(cfg.guidance, resolve=True))
        return [name for name, weight in guidance.weights(nonzero=True).items() if name in guidance.terms]

    def rows(self) -> list[dict]:
        """One record per variant: the metrics of ``eval/<v>/metrics.json`` (None where it failed) and the row's
        settings and identity (:func:`spread.reporting.runs.folder_identity`)."""
        from spread.reporting.runs import folder_identity, identity_fields

        records = []
        for v in self.spec.variants:
            path = self.engine.eval_dir(v) / "metrics.json"
            metrics = read_json(path) if self.engine.status.get(f"evaluate/{v}") in ("done", "skipped") else {}
            row = {"variant": v, "method": LABELS[v],
                   **{c.key: metrics.get(c.key) for c in columns_of([metrics], hidden=True)}}
            row.update({"n_scenes": metrics.get("n_scenes"), "n_objects": metrics.get("n_objects"),
                        "fid_status": metrics.get("fid_status"),
                        "status": "ok" if metrics else self.engine.errors.get(f"evaluate/{v}", "not run")})
            row.update(ci_columns(row_intervals(metrics, self.engine.eval_dir(v)) if metrics else {}))
            if metrics:  # what the row's numbers were made with, as recorded beside them
                row.update(identity_fields(folder_identity(self.engine.eval_dir(v), metrics)))
            records.append(row)
        return records

    def pair_geometry(self, records: list[dict]) -> None:
        """On the ``geometry`` record, ``paired``: row → :func:`spread.results.paired_difference` of per-scene
        Col_mesh, +Geometry − that row, for ``base`` and ``base_time`` where both rows were evaluated in this run's
        folders (the same graphs and sampling seeds: the scenes pair up by id). The difference between rows is
        measured per scene, where each row's own interval also carries the spread between scenes."""
        from spread.results import paired_difference

        rows = {r["variant"]: r for r in records}
        geometry = rows.get("geometry")
        if geometry is None or geometry.get("status") != "ok" or geometry.get("carried_from"):
            return
        paired = {}
        for v in ("base", "base_time"):
            row = rows.get(v)
            if row is None or row.get("status") != "ok" or row.get("carried_from"):
                continue
            try:
                d = paired_difference(self.engine.eval_dir("geometry"), self.engine.eval_dir(v), "col_mesh",
                                      seed=0)
            except (ValueError, OSError) as err:
                log.warning("paired Col_mesh, +Geometry against %s: %s", v, err)
                continue
            paired[v] = {k: d[k] for k in ("diff", "lo", "hi", "n_pairs")}
        if paired:
            geometry["paired"] = paired

    def figure_scene(self) -> str | None:
        """The scene file name the figures show: the first one every sampled row has, and no row's ``sampling.json``
        names implausible (a sample written as the model made it, which no reader draws)."""
        from spread.io import read_json

        sets = []
        for v in self.spec.variants:
            if self.engine.status.get(f"sample/{v}") not in ("done", "skipped"):
                continue
            folder = self.engine.sample_dir(v)
            manifest = read_json(folder / "sampling.json") if (folder / "sampling.json").is_file() else {}
            implausible = manifest.get("implausible") if isinstance(manifest, dict) else None
            absurd = {f"{n}.npz" for n in implausible} if isinstance(implausible, dict) else set()
            sets.append({p.name for p in (folder / "scenes").glob("*.npz")} - absurd)
        common = sorted(set.intersection(*sets)) if sets else []
        return common[0] if common else None

    def figure_paths(self, rows: Sequence[str] = ()) -> dict[str, Path]:
        """row (and ``truth``) → its figure's path (``rows``: default ``truth`` and the spec's rows)."""
        return {v: self.out / f"{TABLE}_{v}.png" for v in (rows or ("truth", *self.spec.variants))}

    def figures_stage(self) -> Stage | None:
        name = self.figure_scene()
        if name is None:
            raise StageError("figures: no scene that every sampled row has, nothing to draw")
        rows = [v for v in self.spec.variants if (self.engine.sample_dir(v) / "scenes" / name).exists()]
        truth = self.spec.dataset / self.spec.split / f"{graph_of(name)}.npz"
        paths = {k: p for k, p in self.figure_paths().items() if k in rows or (k == "truth" and truth.exists())}

        def run(resume: bool) -> None:
            write_row_figures(self.spec.dataset, {v: self.engine.sample_dir(v) / "scenes" / name for v in rows},
                              truth if truth.exists() else None, paths)

        inputs = {"scene": name, "samples": {v: sampling_inputs(self.engine.sample_dir(v)) for v in rows}}
        return Stage("figures", self.out, list(paths.values()), inputs, run)

    def table_stage(self, records: list[dict], log_table: Callable[[list[dict], Path], None] | None) -> Stage:
        stem = self.out / TABLE
        outputs = [stem.with_suffix(s) for s in (".md", ".csv", ".tex", ".png")]
        drawn = self.engine.status.get("figures") in ("done", "skipped")
        carried = {r["variant"] for r in records if r.get("carried_from")}  # their figures from the earlier run
        shown = ("truth", *[v for v in VARIANTS if v in self.spec.variants or v in carried])
        figures = {k: p.name for k, p in self.figure_paths(shown).items() if (drawn or k in carried) and p.exists()}

        def run(resume: bool) -> None:
            write_ablation_table(records, stem, self.spec.title, figures)
            if log_table is not None:
                log_table(records, stem.with_suffix(".png"))

        return Stage("table", self.out, outputs, {"rows": records, "figures": figures}, run)

    def trained(self) -> list[str]:
        """The checkpoints the rows sample, in order (``base_time`` needs base and +Geometry trained too)."""
        needed = {CHECKPOINT_OF[v] for v in self.spec.variants}
        if "base_time" in needed:
            needed |= {"base", "geometry"}
        return [t for t in TRAINED if t in needed]

    def training_phases(self) -> list[list[str]]:
        """:meth:`trained` in phases that train one after the other (each phase's rows ``train_concurrent`` at a
        time): ``base_time`` alone after the others, whose clocks size it."""
        trained = self.trained()
        phases = [[t for t in trained if t != "base_time"], [t for t in trained if t == "base_time"]]
        return [p for p in phases if p]

    def run(self, log_table: Callable[[list[dict], Path], None] | None = None) -> AblationResult:
        started = time.perf_counter()
        self.out.mkdir(parents=True, exist_ok=True)
        for phase in self.training_phases():
            self.engine.run_trained(phase)
        self.engine.run_sample_evaluate(list(self.spec.variants))
        return self.finish(log_table, started)

    def finish(self, log_table: Callable[[list[dict], Path], None] | None, started: float) -> AblationResult:
        """The rows (this run's and the carried ones), the figures and the table, once the rows' stages ran."""
        records = with_carried(self.rows(), self.engine.carried("variant", list(self.spec.variants)), "variant",
                               list(VARIANTS))
        self.pair_geometry(records)
        if self.spec.figures:
            self.engine.attempt("figures", self.figures_stage, [])
        self.engine.attempt("table", lambda: self.table_stage(records, log_table), [])
        stem = self.out / TABLE
        if self.engine.status.get("table") == "skipped" and log_table is not None:  # this launch's run shows it too
            log_table(records, stem.with_suffix(".png"))  # (a relaunch's parent run was left empty)
        return self.engine.result(records, {s: stem.with_suffix(f".{s}") for s in ("md", "csv", "tex", "png")},
                                  started)


def table_columns(records: Sequence[dict] = ()) -> list[Column]:
    return [Column("method", "Method"), *columns_of(records)]


def geometry_reading(records: Sequence[dict]) -> str:
    """The table's sentence on the paper's +Geometry claim: the ``geometry`` row's unguided Col_mesh against the
    ``base`` row's (equal steps) and against the ``base_time`` row's (base trained for +Geometry's wall time), each
    with both 95 % bootstrap intervals, saying whether it is lower and whether the intervals are apart (issue 33,
    item 3); empty unless the rows have Col_mesh and its interval."""
    rows = {r.get("variant"): r for r in records}
    geometry = rows.get("geometry")
    scale = ((geometry or {}).get("settings") or {}).get("geometry_scale", 1.0)
    name = "+Geometry" if float(scale) == 1.0 else \
        f"+Geometry (sampled with geometry_scale={scale}: guidance on its own geometry features, no physics term)"
    said = []
    for v, words in (("base", ""), ("base_time", " at equal training time")):
        sentence = col_mesh_reading(geometry, rows.get(v), words, name)
        said.append(sentence + paired_reading(geometry, v) if sentence else "")
    return " ".join(s for s in said if s)


def paired_reading(geometry: dict | None, against: str) -> str:
    """The sentence on the paired per-scene difference (:meth:`Ablation.pair_geometry`), "" without one."""
    d = ((geometry or {}).get("paired") or {}).get(against)
    if not d:
        return ""
    if d["hi"] < 0:
        verdict = "below zero: lower on the same scenes"
    elif d["lo"] > 0:
        verdict = "above zero: higher on the same scenes"
    else:
        verdict = "it spans zero"
    return (f" Paired on the same {d['n_pairs']} scenes (the mean of per-scene Col_mesh differences), +Geometry − "
            f"{LABELS[against]}: {d['diff']:+.3f} [{d['lo']:+.3f}, {d['hi']:+.3f}], {verdict}.")


def col_mesh_reading(geometry: dict | None, base: dict | None, when: str, name: str = "+Geometry") -> str:
    """One sentence of :func:`geometry_reading`: +Geometry's (``name``) unguided Col_mesh against one base row's."""
    keys = ("col_mesh", "col_mesh_lo", "col_mesh_hi")
    if base is None or geometry is None or any(r.get(k) is None for r in (base, geometry) for k in keys):
        return ""
    b, g = (tuple(float(r[k]) for k in keys) for r in (base, geometry))
    apart = g[2] < b[1] or b[2] < g[1]
    if g[0] < b[0]:
        verdict = ("lower than base's, and the 95 % intervals do not overlap: the geometry perceiver reduces "
                   "collisions here, as the paper reports" if apart else
                   "lower than base's, but the 95 % intervals overlap: not shown apart on these graphs")
    elif g[0] > b[0]:
        verdict = ("higher than base's, and the 95 % intervals do not overlap: against the paper's direction"
                   if apart else "higher than base's, but the 95 % intervals overlap: no difference shown")
    else:
        verdict = "equal to base's"
    counts = f" ({base.get('n_scenes')} / {geometry.get('n_scenes')} scenes)" if base.get("n_scenes") else ""
    return (f"{name} against base{when}, unguided Col_mesh{counts}: {g[0]:.3f} [{g[1]:.3f}, {g[2]:.3f}] "
            f"against {b[0]:.3f} [{b[1]:.3f}, {b[2]:.3f}], {verdict}.")


def ablation_caption(records: list[dict], differ: list[str]) -> str:
    """The table's caption: the rows it holds, and "same test graphs, seeds and protocol" only when no setting
    differs between them (``differ``: :func:`spread.reporting.runs.name_differences`), else the settings that do."""
    rows = ", ".join(str(r.get("method") or r.get("variant")) for r in records)
    if not differ:
        return f"Ablation: {rows} (same test graphs, seeds and protocol)"
    shown = ", ".join(differ[:4]) + (", …" if len(differ) > 4 else "")
    return f"Ablation: {rows} (the rows differ in {shown}: named under the table)"


def write_ablation_table(records: list[dict], stem: Path, title: str = "",
                         figures: dict[str, str] | None = None) -> dict[str, Path]:
    """``stem.md``, ``.csv``, ``.tex`` (booktabs, best value bold, ± the bootstrap interval) and ``.png`` (bars
    per metric); every setting that differs between the rows is named per row (CSV columns, and a line per row
    under the Markdown table); ``figures`` (row or ``truth`` → PNG file name beside the table) are linked under the
    Markdown table."""
    from spread.reporting.plots import ablation_bars
    from spread.reporting.runs import name_differences

    records = [dict(r) for r in records]
    differ = name_differences(records)
    caption = title or ablation_caption(records, differ)
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
                                   "ci_resamples", "ci_seed", "carried_from"],
                         note=" ".join(n for n in (geometry_reading(records), table_note(records), carried_note(records))
                                   if n), md_extra=shown)
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
