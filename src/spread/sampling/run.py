"""One sampling run (``spread-sample``): a checkpoint + a split's graphs → ``out_dir/scenes/*.npz``.

1. Read the split's scene files (validated against the dataset's asset library): the conditioning graphs.
2. Plan the batches (:mod:`spread.sampling.plan`): per-item seeds from (seed, scene id, k), fixed batches.
3. Resume: a batch whose files all exist is skipped; a batch missing some is sampled again (same seeds,
   same batch, so the same scenes) and only its missing files are written. ``out_dir/sampling.json`` pins
   what the files were made with (:func:`spread.runtime.fingerprint.sampling_identity`: checkpoint hash, the
   split's data content, sampler, seed, batching, every acting guidance term's weight, ...) from before the first
   file is written; a re-launch into a folder made with other settings (or scene files
   without a record) redoes it from scratch and records why (``redone_because: "changed: <keys>"``), so a
   folder never mixes two runs and never passes old scenes off as new ones. ``resume=false`` deletes the
   folder's scene files first and samples everything. Scenes of the same identity this run does not plan (a larger
   ``samples_per_graph`` before) wait in ``out_dir/unplanned/`` for a run that plans them
   (:func:`set_aside_unplanned`): ``scenes/`` holds exactly what ``sampling.json`` counts, and nothing is lost.
4. Fan out: ``workers`` Ray actors (one model each, ``threads`` CPUs and ``num_gpus_per_worker`` GPUs each),
   one batch per task, the next batch to whichever actor finishes first; ``workers=0`` samples in this
   process. Actors that die are restarted and their task retried (``ray.max_retries``).
5. ``out_dir/renders/``: ground truth | generated top-down, side by side, for the first ``renders`` samples;
   for the first ``figures`` samples also a 3D scene card (``<name>_3d.png``: the perspective view with its
   category legend and the relation matrix against the conditioning graph) and the scene before | after one
   Stability run (``<name>_physics.png``), see :mod:`spread.render.figures`;
   ``out_dir/sampling.json``: the settings, counts and timings (``startup_seconds``: from the start to the
   first batch — checks, graph reads, model load, on Ray the actors' start; near 0 in a warm process;
   ``process_reads``: this process's reads and hits per kind so far, :func:`spread.readonce.counts`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from omegaconf import MISSING

from spread import readonce
from spread.data.limit import object_limit
from spread.guidance import GuidanceConfig
from spread.io import check_folder_kind, read_json, write_json_atomic
from spread.runtime.threads import check_threads
from spread.model.sampler import Sampler
from spread.runtime.ray import RaySettings, ray_session
from spread.sampling.plan import BatchPlan, Graph, missing_items, plan_batches, read_back, remove_unreadable

MANIFEST = "sampling.json"
#: The 3D figures ``spread-sample`` can write per sample: file suffix of each.
FIGURE_KINDS = {"card": "_3d", "physics": "_physics"}


@dataclass
class DataSplit:
    """A dataset folder and the split whose scene files are the conditioning graphs."""

    root: str = MISSING
    split: str = "test"


@dataclass
class SamplingConfig:
    """ckpt: Lightning checkpoint; data: dataset folder and split whose graphs condition; out_dir: run
    folder; sampler: a :class:`~spread.model.Sampler` (or its config / short name); samples_per_graph: k;
    seed; batch_size: samples per forward batch (= per task); workers: Ray actors (0: in this process);
    device: cpu, cuda or auto; threads: torch threads per worker; use_ema: the EMA weights; graph_scale:
    classifier-free guidance on the graphs (needs a model trained with graph_dropout); geometry_scale: classifier-free
    guidance on a +Geometry model's geometry features (s: the output with them against the output reading nothing
    near anything; 1: the model as trained; one network pass more per step); resume: skip
    existing files (false: delete and redo all); renders: top-down truth | generated PNGs of the first samples;
    figures: 3D figures of the first samples, of the kinds in ``figure_kinds`` (``card``: 3D view + relation
    matrix, ``physics``: before | after one Stability run); progress: tqdm bar; guidance: a
    :class:`~spread.guidance.GuidanceConfig` (or its mapping / mode name); ray: where the actors run
    (``ray.num_gpus_per_worker``: GPUs per actor); max_objects: largest graph sampled (None: twice the
    dataset's largest scene, ``stats.json``'s ``max_objects``; 0: no limit) — a larger one is skipped and named
    before any work (the geometry model's cost grows with the square of the objects, and a graph far beyond
    what the model was trained on would hold up its batch). ``conf/sample.yaml`` overrides these defaults."""

    ckpt: str = MISSING
    data: DataSplit = field(default_factory=DataSplit)
    out_dir: str = MISSING
    sampler: Sampler = field(default_factory=lambda: Sampler("ddim", 50))
    samples_per_graph: int = 1
    seed: int = 0
    batch_size: int = 16
    workers: int = 2
    device: str = "auto"
    threads: int | None = 1
    use_ema: bool = True
    graph_scale: float = 1.0
    geometry_scale: float = 1.0
    resume: bool = True
    renders: int = 4
    figures: int = 2
    figure_kinds: list[str] = field(default_factory=lambda: list(FIGURE_KINDS))
    progress: bool = True
    guidance: GuidanceConfig = field(default_factory=GuidanceConfig)
    ray: RaySettings = field(default_factory=RaySettings)
    max_objects: int | None = None
    #: CUDA: record each batch's network call once as a CUDA graph and replay it every step (the same kernels, far
    #: fewer launches, the same numbers; spread.model.capture). null (default): on for a model that says its step
    #: reads nothing on the host (``cuda_graph_capturable``: SPREAD's base, +Geometry with the chamfer feature
    #: searched by ``dense``/``auto``, DiffuScene, InstructScene), off for the rest; true: record, or refuse a model
    #: that cannot be; false: never. Ignored on CPU.
    cuda_graph: bool | None = None
    #: The network's arithmetic: "32" (float32) or "bf16" (bfloat16 autocast; geometry features stay float32).
    precision: str = "32"

    def __post_init__(self) -> None:  # Python callers may give a sampler name or a guidance mode
        if not isinstance(self.sampler, Sampler) and self.sampler is not MISSING:
            self.sampler = Sampler.from_config(self.sampler)
        if isinstance(self.sampler, Sampler):
            self.sampler.check_eta()
        if not isinstance(self.guidance, GuidanceConfig):
            self.guidance = GuidanceConfig.from_config(self.guidance)
        from spread.sampling.pipeline import check_values

        check_values(self.graph_scale, self.geometry_scale, self.precision)
        from spread.checks import whole_number

        for key in ("workers", "renders", "figures", "seed"):
            whole_number(getattr(self, key), key)
        for key in ("samples_per_graph", "batch_size"):  # refused at once, not after the checkpoint is read
            whole_number(getattr(self, key), key, 1)
        check_threads(self.threads)
        unknown = [k for k in self.figure_kinds if k not in FIGURE_KINDS]
        if unknown:
            raise ValueError(f"figure_kinds: unknown {unknown} (choose from {list(FIGURE_KINDS)})")


    def sampling_device(self) -> str:
        """The kind of device the samplers run on, ``cpu`` or ``cuda`` (part of the run's identity, as the device
        changes the numbers' rounding): ``auto`` resolved as the samplers resolve it — in this process
        (``workers=0``) ``cuda`` when it sees a GPU; on Ray's workers ``cuda`` only with ``ray.num_gpus_per_worker``
        > 0 (Ray hides every GPU from a worker that asks for none) —, ``cuda:N`` as ``cuda``."""
        from spread.runtime.fingerprint import auto_device

        device = str(self.device)
        if device == "auto":
            if self.workers > 0:
                return "cuda" if self.ray.num_gpus_per_worker > 0 else "cpu"
            return auto_device()
        return device.split(":", 1)[0]

    def graphs_over_limit(self) -> list[str]:
        """The split's graphs (scene file names) this run leaves out for the object limit in effect
        (:func:`object_limit`): part of the run's identity, as they change what it samples."""
        return graphs_over(self.data.root, self.data.split, object_limit(self.data.root, self.max_objects))


@dataclass
class SamplingResult:
    """files: every scene file of the run (in plan order); written: files written by this call."""

    out_dir: Path
    files: list[Path]
    written: list[str]
    manifest: dict


def list_graphs(data_root: str | Path, split: str) -> list[Graph]:
    """The split's scene files as conditioning graphs (each read and validated against the library)."""
    return read_graphs(data_root, split)[0]


def graphs_over(data_root: str | Path, split: str, limit: int | None) -> list[str]:
    """Names of the split's scene files of more than ``limit`` objects (None: no limit), read once per process
    (:mod:`spread.readonce`, as :func:`read_graphs` reads them); a folder or file that does not read gives none (its
    run names it)."""
    if limit is None or not (Path(data_root) / split).is_dir():
        return []
    from spread.scene import SceneFormatError, list_scene_files

    assets = Path(data_root) / "assets"
    library = readonce.asset_library(assets) if (assets / "index.json").is_file() else None
    out = []
    for path in list_scene_files(Path(data_root) / split):
        try:
            scene = readonce.scene(path, library)
        except (SceneFormatError, OSError, ValueError):
            continue
        if scene.num_objects > limit:
            out.append(path.stem)
    return out


def read_graphs(data_root: str | Path, split: str, max_objects: int | None = None) -> tuple[list[Graph], list[dict]]:
    """(the split's usable scene files as conditioning graphs, one ``{"file", "error"}`` per skipped file):
    a damaged or implausible file, or a graph of more than ``max_objects`` objects, is named and skipped,
    the others are sampled; none usable is refused."""
    from spread.scene import SceneFormatError, list_scene_files

    folder = Path(data_root) / split
    files = list_scene_files(folder) if folder.is_dir() else []
    if not files:
        raise FileNotFoundError(f"{folder}: no scene files to condition on")
    library = readonce.asset_library(Path(data_root) / "assets")
    graphs, skipped = [], []
    for path in files:
        try:
            scene = readonce.scene(path, library)
        except SceneFormatError as exc:  # named, counted in sampling.json, and the other graphs are sampled
            skipped.append({"file": str(path), "error": str(exc)})
            continue
        if max_objects is not None and scene.num_objects > max_objects:
            skipped.append({"file": str(path), "error": f"{path}: {scene.num_objects} objects, over the object limit "
                                                        f"{max_objects} (set max_objects=<n> to raise it, 0: no limit)"})
            continue
        graphs.append(Graph(scene.scene_id, str(path), scene.num_objects))
    if skipped:
        import logging

        logging.getLogger("spread.sample").warning("skipped %d of %d graphs: %s", len(skipped), len(files),
                                                   "; ".join(s["error"] for s in skipped[:3]))
    if not graphs:
        raise ValueError(f"{folder}: none of its {len(files)} scene files is a usable graph "
                         f"(first: {skipped[0]['error']})")
    return graphs, skipped


def check_checkpoint(cfg: SamplingConfig) -> dict:
    """The checkpoint (tensors memory-mapped) once it reads safely, its weights fit the network its
    hyperparameters describe (:func:`spread.methods.check_weight_shapes`: nothing is allocated) and the sampling
    settings fit that network (:func:`spread.sampling.worker.check_settings` on it, built on the ``meta`` device:
    a setting it cannot sample with is refused before the output folder is touched). The one read of the file in
    this process (:func:`spread.readonce.checkpoint`): the workers build from it."""
    from spread.methods import check_weight_shapes, checkpoint_method, module_class
    from spread.sampling.worker import check_settings

    checkpoint = readonce.checkpoint(cfg.ckpt)
    check_categories(checkpoint, cfg)
    meta = check_weight_shapes(module_class(checkpoint_method(checkpoint.get("hyper_parameters") or {})), checkpoint,
                               str(cfg.ckpt))
    if meta is not None:
        try:
            check_settings(cfg, meta)
        except ValueError:
            raise
        except Exception:  # noqa: BLE001 - a model whose checks read real tensors: its workers check them
            pass
    return checkpoint


def check_inputs(cfg: SamplingConfig) -> None:
    """What :func:`run_sampling` checks of its inputs before it samples, without touching ``out_dir``, for a caller
    that plans runs before any starts (a sweep's driver, before Ray): the checkpoint (:func:`check_checkpoint`) and
    the split's graphs (:func:`read_graphs`) — not the device, which the process that samples checks (a sweep's
    trials run on GPU nodes its driver may not be)."""
    check_checkpoint(cfg)
    read_graphs(cfg.data.root, cfg.data.split, object_limit(cfg.data.root, cfg.max_objects))


def check_categories(checkpoint: dict, cfg: SamplingConfig) -> None:
    """``ValueError`` when the checkpoint's model was trained on another category list than the dataset's
    (``hyper_parameters.categories`` — a baseline's one-hot columns — against ``manifest.json``'s): its samples would
    be conditioned on the wrong classes under the right names (training refuses the same mismatch)."""
    held = (checkpoint.get("hyper_parameters") or {}).get("categories")
    if not isinstance(held, (list, tuple)) or not held:
        return
    from spread.methods.base import dataset_facts

    now = dataset_facts(cfg.data.root)["categories"]
    if [str(c) for c in held] != [str(c) for c in now]:
        first = next((i for i, (a, b) in enumerate(zip(held, now)) if str(a) != str(b)), min(len(held), len(now)))
        a, b = (names[first] if first < len(names) else None for names in (held, now))
        raise ValueError(f"ckpt={cfg.ckpt}: trained on {len(held)} categories that differ from the "
                         f"{len(now)} of {Path(str(cfg.data.root)) / 'manifest.json'} (first at column {first}: "
                         f"{a!r} vs {b!r}); sample it on the dataset it was trained on")


def check_fingerprint(out: Path, settings: dict, resume: bool,
                      before_clearing: Callable[[], None] | None = None) -> str | None:
    """Resume, or redo from scratch (module docstring, step 3; ``resume=false``: always) by the platform's
    done-check (:func:`spread.runtime.fingerprint.done_check`); returns why the folder is redone (None: a resume
    or a new folder). A redo deletes the folder's scene files and renders, and those set aside (no file of an earlier
    run stays beside the new ones); then (either way) ``sampling.json``
    is pinned to ``settings`` (``status: running``) before any file is written, so a run killed mid-way is
    resumed only by a re-launch with the same settings. ``before_clearing()``: the last check before a redo
    deletes anything (its refusal leaves the folder as it was)."""
    from spread.runtime.fingerprint import done_check

    path, scenes = out / MANIFEST, out / "scenes"
    try:
        before = read_json(path).get("fingerprint")
    except (OSError, ValueError, AttributeError):
        before = None
    present = any(scenes.glob("*.npz")) or any((out / ASIDE / "scenes").glob("*.npz"))  # set aside: theirs too
    decision = done_check(before, settings, present=present, resume=resume,
                          unknown=f"its scenes have no readable {MANIFEST} fingerprint")
    if decision.fresh:
        if before_clearing is not None:
            before_clearing()
        for old in [*scenes.glob("*.npz"), *(out / ASIDE).glob("scenes/*.npz"), *own_renders(out, path)]:
            old.unlink(missing_ok=True)
    write_json_atomic(path, {"fingerprint": settings, "status": "running", "redone_because": decision.reason})
    return decision.reason


def own_renders(out: Path, manifest: Path) -> list[Path]:
    """The pictures an earlier sampling run wrote in ``out``'s ``renders/`` (and those set aside with its scenes):
    those named after its scene files (``<scene>.png``, ``<scene><figure suffix>.png``) and those its ``sampling.json``
    lists — never another file of the folder (a dataset's or a user's picture there stays)."""
    stems = [f.stem for f in [*(out / "scenes").glob("*.npz"), *(out / ASIDE).glob("scenes/*.npz")]]
    names = {f"{stem}{suffix}.png" for stem in stems for suffix in ("", *FIGURE_KINDS.values())}
    found = [folder / name for folder in (out / "renders", out / ASIDE / "renders") for name in sorted(names)]
    try:
        record = read_json(manifest)
        listed = [Path(str(p)) for key in ("renders", "figures") for p in (record.get(key) or [])]
    except (OSError, ValueError, AttributeError, TypeError):
        listed = []
    inside = [p for p in listed if p.suffix == ".png" and p.parent.resolve() == (out / "renders").resolve()]
    return [p for p in dict.fromkeys([*found, *inside]) if p.is_file() and not p.is_symlink()]


#: Where a run keeps the scene files (and renders) of an earlier run of the same identity that it does not plan.
ASIDE = "unplanned"


def move_file(source: Path, target: Path) -> None:
    """``source`` to ``target`` (same file system: an atomic rename); a target already there stays."""
    if source.is_file() and not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        source.replace(target)


def set_aside_unplanned(batches: list[BatchPlan], out: Path) -> tuple[list[str], list[str]]:
    """Keep the folder to exactly this run's plan without losing what was sampled: scene files that are not in the
    plan — samples of a larger ``samples_per_graph``, or of graphs this run does not sample (``max_objects``), left
    by an earlier run of the same identity (neither is part of it: more samples resume) — move with their renders and
    figures to ``out/unplanned/``, and planned ones kept there by an earlier run come back (the same identity, so the
    same scenes: a redo deletes ``unplanned/``). An evaluation of ``scenes/`` thus never scores another run's samples;
    returns (names set aside, names taken back)."""
    planned = {item.name for b in batches for item in b.items}
    aside = out / ASIDE

    def move(name: str, source: Path, target: Path) -> None:  # a sample's scene file, its render and figures
        files = [f"scenes/{name}.npz", *(f"renders/{name}{suffix}.png" for suffix in ("", *FIGURE_KINDS.values()))]
        for file in files:
            move_file(source / file, target / file)

    set_aside = sorted(p.stem for p in (out / "scenes").glob("*.npz") if p.stem not in planned)
    for name in set_aside:
        (aside / "scenes" / f"{name}.npz").unlink(missing_ok=True)  # a stale copy never shadows the newer file
        move(name, out, aside)
    taken_back = sorted(p.stem for p in (aside / "scenes").glob("*.npz")
                        if p.stem in planned and not (out / "scenes" / p.name).exists())
    for name in taken_back:
        move(name, aside, out)
    return set_aside, taken_back


def check_device(cfg: SamplingConfig) -> None:
    """A device the samplers cannot use, refused before anything is written: in this process (``workers=0``) one it
    does not see (:func:`spread.sampling.worker.resolve_device`); on Ray's workers (each checks its own device: a GPU
    node's may differ from the driver's) ``cuda`` without ``ray.num_gpus_per_worker`` — Ray hides every GPU from a
    worker that asks for none (its ``CUDA_VISIBLE_DEVICES`` is empty), so each would fail."""
    from spread.sampling.worker import resolve_device

    if cfg.workers <= 0:
        resolve_device(cfg.device)
        return
    if str(cfg.device) not in ("auto", "cpu") and not str(cfg.device).startswith("cuda"):
        resolve_device(cfg.device)  # mps, …: refused by name here too
    if str(cfg.device).startswith("cuda") and not cfg.ray.num_gpus_per_worker > 0:
        raise ValueError(f"device={cfg.device} with workers={cfg.workers}: Ray gives a worker no GPU unless it asks "
                         f"for one; set ray.num_gpus_per_worker=1 (a fraction shares a GPU between workers) or "
                         f"workers=0")
    if cfg.ray.num_gpus_per_worker > 0 and cfg.ray.starts_cluster:  # the Ray this command starts: this machine's GPUs
        import torch

        if not (torch.cuda.is_available() and torch.cuda.device_count() > 0):
            raise ValueError(f"ray.num_gpus_per_worker={cfg.ray.num_gpus_per_worker} with workers={cfg.workers}: "
                             f"this machine has no GPU for the Ray this command starts (ray.address unset or local); "
                             f"set ray.num_gpus_per_worker=0, or ray.address= a cluster with GPUs")


def run_in_process(todo: list[BatchPlan], cfg: SamplingConfig, scenes_dir: Path, on_result) -> dict:
    """Sample the batches in this process with one model."""
    from spread.sampling.worker import SampleWorker

    worker = SampleWorker(cfg, scenes_dir)
    for batch in todo:
        on_result(worker.run(batch))
    return {"workers": 1, "mode": "in-process"}


def check_joined_cluster(cfg: SamplingConfig) -> None:
    """Before a redo clears the folder: a cluster this run joins (``ray.address``) can hold one sampling actor with
    its ``ray.num_gpus_per_worker`` GPUs (:func:`actor_count` found it only after the folder was cleared). A started
    cluster's GPUs are this machine's, checked by :func:`check_device`; ``workers=0`` uses no Ray."""
    if cfg.workers <= 0 or not cfg.ray.num_gpus_per_worker > 0 or cfg.ray.starts_cluster:
        return
    import ray

    with ray_session(cfg.ray):
        gpus = ray.cluster_resources().get("GPU", 0)
    if gpus < cfg.ray.num_gpus_per_worker:
        raise ValueError(f"ray.num_gpus_per_worker={cfg.ray.num_gpus_per_worker} but the cluster at "
                         f"ray.address={cfg.ray.address} has {gpus:g} GPUs (nothing in {cfg.out_dir} was removed)")


def actor_count(cfg: SamplingConfig, batches: int) -> int:
    """Actors to start: ``workers``, no more than the batches or than the cluster's CPUs/GPUs can hold."""
    import ray

    total = ray.cluster_resources()
    n = min(int(cfg.workers), batches)
    n = min(n, max(1, int(total.get("CPU", 1) // max(1, cfg.threads or 1))))
    gpus = cfg.ray.num_gpus_per_worker
    if gpus > 0:
        n = min(n, int(total.get("GPU", 0) // gpus))
        if n < 1:
            raise ValueError(f"ray.num_gpus_per_worker={gpus} but the cluster has {total.get('GPU', 0)} GPUs")
    return max(1, n)


def run_on_ray(todo: list[BatchPlan], cfg: SamplingConfig, scenes_dir: Path, on_result) -> dict:
    """Sample the batches on Ray actors (module docstring, step 4)."""
    import ray

    from spread.runtime.ray import scheduling_strategy
    from spread.sampling.worker import SampleWorker

    with ray_session(cfg.ray, owner=scenes_dir.parent) as cluster:
        n = actor_count(cfg, len(todo))
        actor = ray.remote(SampleWorker).options(
            num_cpus=max(1, cfg.threads or 1), num_gpus=cfg.ray.num_gpus_per_worker,
            max_restarts=cfg.ray.max_retries, max_task_retries=cfg.ray.max_retries,
            scheduling_strategy=scheduling_strategy(cfg.ray))  # SPREAD: actors over every node
        actors = [actor.remote(cfg, scenes_dir) for _ in range(n)]  # the typed config, pickled as it is
        queue = list(todo)
        running = {}
        for a in actors:
            if queue:
                running[a.run.remote(queue.pop(0))] = a
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            a = running.pop(done[0])
            on_result(ray.get(done[0]))
            if queue:
                running[a.run.remote(queue.pop(0))] = a
            if queue and len(actors) < min(int(cfg.workers), len(todo)):  # nodes that joined since the start
                for _ in range(actor_count(cfg, len(todo)) - len(actors)):
                    if not queue:
                        break
                    actors.append(actor.remote(cfg, scenes_dir))
                    running[actors[-1].run.remote(queue.pop(0))] = actors[-1]
        for a in actors:
            ray.kill(a)
    return {"workers": len(actors), "mode": "ray", **cluster}


def unreported_implausible(names: list[str], scenes_dir: Path) -> dict[str, str]:
    """Of scene files a worker wrote but never reported (it died after writing them; its retry skipped them), those
    that read back physically implausible, with why (:func:`~spread.sampling.plan.read_back`; a damaged one is
    the next launch's to sample again)."""
    out = {}
    for name in names:
        problem = read_back(scenes_dir / f"{name}.npz")[1]
        if problem is not None:
            out[name] = problem
    return out


def drawable(batches: list[BatchPlan], count: int, skip=()) -> list:
    """The first ``count`` planned items, those in ``skip`` (implausible samples: no reader draws them) left out."""
    return [item for b in batches for item in b.items if item.name not in skip][:max(0, count)]


def write_renders(out: Path, batches: list[BatchPlan], data_root: str, count: int, skip=()) -> list[Path]:
    """Ground truth | generated PNGs of the first ``count`` samples (not those in ``skip``),
    ``out/renders/<name>.png``."""
    from spread.render import VIEW_SETTINGS_FLOOR, TopDownRenderSettings, render_before_after, save_png

    items = drawable(batches, count, skip)
    if not items:
        return []
    library = readonce.asset_library(Path(data_root) / "assets")
    settings = TopDownRenderSettings(floor=VIEW_SETTINGS_FLOOR)
    paths = []
    for item in items:
        generated = readonce.scene(out / "scenes" / f"{item.name}.npz", library)
        truth = readonce.scene(item.graph.path, library)
        image = render_before_after(truth, generated, library, settings)
        paths.append(save_png(image, out / "renders" / f"{item.name}.png"))
    return paths


def write_figures(out: Path, batches: list[BatchPlan], data_root: str, count: int, kinds, seed: int = 0,
                  skip=()) -> list[Path]:
    """3D figures of the first ``count`` samples (module docstring, step 5; not those in ``skip``),
    ``out/renders/<name><suffix>.png``."""
    from spread.render import before_after_figure, save_png, scene_card_figure

    items = drawable(batches, count, skip)
    if not items or not kinds:
        return []
    library = readonce.asset_library(Path(data_root) / "assets")
    paths = []
    for item in items:
        generated = readonce.scene(out / "scenes" / f"{item.name}.npz", library)
        title = f"{item.name} (graph of {item.graph.scene_id})"
        for kind in kinds:
            image = scene_card_figure(generated, library, title=title) if kind == "card" \
                else before_after_figure(generated, library, seed=seed, title=item.name)
            paths.append(save_png(image, out / "renders" / f"{item.name}{FIGURE_KINDS[kind]}.png"))
    return paths


def run_sampling(cfg: SamplingConfig, before_work: Callable[[], None] | None = None) -> SamplingResult:
    """Generate ``samples_per_graph`` scenes for every graph of the split (module docstring);
    ``before_work()`` runs once the checks passed (the command records its config there). The run holds
    ``out_dir``'s lock (:func:`spread.io.run_lock`)."""
    from spread.io import run_lock

    with run_lock(cfg.out_dir, "spread-sample"):
        return _run_sampling(cfg, before_work)


def _run_sampling(cfg: SamplingConfig, before_work: Callable[[], None] | None = None) -> SamplingResult:
    from tqdm.auto import tqdm

    started = time.perf_counter()
    out = Path(cfg.out_dir)
    # its own runs, and the evaluation of its scenes (spread-sample evaluate=true) — not an evaluation of others
    check_folder_kind(out, "spread-sample", {"sampling run", "evaluation"} if (out / MANIFEST).exists()
                      else {"sampling run"})
    check_device(cfg)
    scenes_dir = out / "scenes"
    scenes_dir.mkdir(parents=True, exist_ok=True)
    check_checkpoint(cfg)  # missing, damaged, unsafe, self-contradictory or not for these settings: before any work
    limit = object_limit(cfg.data.root, cfg.max_objects)
    graphs, skipped_graphs = read_graphs(cfg.data.root, cfg.data.split, limit)
    batches = plan_batches(graphs, cfg.samples_per_graph, cfg.batch_size, cfg.seed)
    from spread.runtime.fingerprint import guidance_run, normalised, sampler_label, sampling_identity

    settings = normalised(sampling_identity(cfg))  # the checkpoint hashed once per process
    redone_because = check_fingerprint(out, settings, cfg.resume, before_clearing=lambda: check_joined_cluster(cfg))
    unplanned, taken_back = set_aside_unplanned(batches, out)
    if unplanned:
        print(f"{scenes_dir}: set {len(unplanned)} scene file(s) this run does not plan aside in {out / ASIDE} "
              f"(samples_per_graph={cfg.samples_per_graph}, {len(graphs)} graphs), e.g. {unplanned[0]}; a run that "
              f"plans them takes them back", flush=True)
    if taken_back:
        print(f"{scenes_dir}: took {len(taken_back)} planned scene file(s) back from {out / ASIDE}", flush=True)
    if before_work is not None:
        before_work()
    implausible: dict[str, str] = {}  # name → why: the samples the model made physically implausible
    damaged = remove_unreadable(batches, scenes_dir, implausible)
    todo = [b for b in batches if missing_items(b, scenes_dir)]
    total = sum(len(b.items) for b in batches)
    pending = sum(len(missing_items(b, scenes_dir)) for b in todo)
    bar = tqdm(total=total, initial=total - pending, desc="samples", unit="scene", disable=not cfg.progress)
    written: list[str] = []
    batch_seconds: list[float] = []
    repaired = [0]
    guidance_totals: dict[str, float] = {}
    startup: list[float] = []  # seconds from the start to the first batch's start (checks, reads, model load)

    def on_result(result: dict) -> None:
        if not startup:
            startup.append(time.perf_counter() - started - result["seconds"])
        written.extend(result["written"])
        implausible.update(result.get("implausible") or {})
        repaired[0] += result["repaired_rotations"]
        for key, value in (result.get("guidance") or {}).items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                guidance_totals[key] = guidance_totals.get(key, 0) + value
        batch_seconds.append(result["seconds"])
        bar.set_postfix_str(f"batch {len(batch_seconds)}/{len(todo)}", refresh=False)  # progress per batch
        bar.update(len(result["written"]))

    runner = {"workers": 0, "mode": "none"}
    wanted = [item.name for b in todo for item in missing_items(b, scenes_dir)]
    if todo:
        runner = (run_on_ray if cfg.workers > 0 else run_in_process)(todo, cfg, scenes_dir, on_result)
    bar.close()
    # counted on disk: a worker killed after writing some files never reports them, its retry skips them
    reported = set(written)
    written = [name for name in wanted if (scenes_dir / f"{name}.npz").exists()]
    implausible |= unreported_implausible([n for n in written if n not in reported], scenes_dir)
    if implausible:
        first = next(iter(implausible.items()))
        print(f"{scenes_dir}: {len(implausible)} of {total} samples physically implausible, written as made and "
              f"named in {out / MANIFEST} (spread-evaluate counts them apart: n_implausible), e.g. {first[0]}: "
              f"{first[1]}", flush=True)
    renders = write_renders(out, batches, cfg.data.root, cfg.renders, skip=implausible)
    figures = write_figures(out, batches, cfg.data.root, cfg.figures, cfg.figure_kinds, cfg.seed, skip=implausible)
    files = [scenes_dir / f"{item.name}.npz" for b in batches for item in b.items]
    manifest = {
        "fingerprint": settings, "ckpt": str(cfg.ckpt), "samples_per_graph": int(cfg.samples_per_graph),
        "graphs": len(graphs), "samples": total,
        "skipped_graphs": skipped_graphs, "max_objects": limit, "written_this_run": len(written),
        "resumed": total - pending, "redone_unreadable": len(damaged),
        "set_aside_unplanned": len(unplanned), "taken_back": len(taken_back),
        "batches": len(batches),
        "batches_run": len(todo),
        "repaired_rotations": repaired[0],
        "implausible": dict(sorted(implausible.items())),
        "sampler": sampler_label(cfg.ckpt, cfg.sampler), "guidance": settings["guidance"],
        "guidance_label": guidance_run(cfg.ckpt, cfg.guidance).label,
        "guidance_totals": guidance_totals or None,
        "renders": [str(p) for p in renders], "figures": [str(p) for p in figures], "device": cfg.device, "threads": cfg.threads,
        "seconds": round(time.perf_counter() - started, 3),
        "startup_seconds": round(startup[0], 3) if startup else None,
        "seconds_per_batch": round(sum(batch_seconds) / len(batch_seconds), 4) if batch_seconds else None,
        "runner": runner, "redone_because": redone_because,
        "process_reads": readonce.counts(),  # this process's reads and hits so far (a warm process: no new reads)
    }
    write_json_atomic(out / MANIFEST, manifest)
    return SamplingResult(out, files, written, manifest)
