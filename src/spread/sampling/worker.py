"""One sampling worker: a checkpoint's :class:`~spread.sampling.pipeline.ScenePipeline`, turning batches into files.

A worker holds one pipeline (model with EMA weights by default, encoder, sampler, guidance) for its whole
life, so a Ray actor — or the driver itself when ``workers=0`` — pays for loading it once; it is built from
the run's :class:`~spread.sampling.SamplingConfig` as it is (a new sampling option is read here, nowhere
else). The model, the encoder, the asset library and the graphs are read once per process
(:mod:`spread.readonce`), so a second run in the same process (the next trial of a sweep) loads nothing. Conditioning
graphs are encoded exactly as in training: the asset points are sampled with the ``num_points`` and
``seed`` of the data module the checkpoint was trained with (Lightning stores its hyperparameters in the
checkpoint).

A generated scene keeps the source's objects (asset ids, categories, order), both graphs and ``room``,
takes the sampled poses, and records where it came from in two extra arrays (DESIGN §4):
``source`` = ``"ckpt=… sampler=… seed=… graph=<scene_id> k=<i>"`` and ``conditioned_on`` = the source
scene id; the source's ``room_type`` array, when it has one, is kept too. Each file is validated and written atomically (:func:`spread.scene.write_scene`).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from spread.sampling.pipeline import ScenePipeline, sampling_kind
from spread.sampling.plan import BatchPlan, SampleItem, missing_items
from spread.scene import Scene


def resolve_device(device: str) -> str:
    """``auto``: ``cuda`` when a GPU is visible, else ``cpu``; any other a torch device that this process can use
    (checked where the model is loaded: a Ray worker on a GPU node may see a GPU its driver does not)."""
    import torch

    from spread.runtime.fingerprint import auto_device

    if device == "auto":
        return auto_device()
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"device={device!r} is not a torch device (auto, cpu, cuda, cuda:N): {exc}") from None
    if parsed.type not in ("cpu", "cuda"):  # mps, xpu, meta, …: not a device the samplers are made for
        raise ValueError(f"device={device!r}: the samplers run on auto, cpu, cuda or cuda:N")
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"device={device!r}: this process sees no CUDA device (torch.cuda.is_available() is "
                             f"False); use device=auto or device=cpu")
        if parsed.index is not None and parsed.index >= count:
            raise ValueError(f"device={device!r}: this process sees {count} CUDA device(s) (cuda:0..cuda:{count - 1})")
    return device


def warn_graph_guidance(guided, model, ckpt) -> None:
    """A warning when relation (support-graph) guidance steers a method that was not trained with the graphs (the
    registry's ``graph_conditioned``): the guidance then pulls towards supports the network never saw."""
    if guided is None or not guided.active or guided.weight("relation") <= 0:
        return
    from spread.methods.registry import METHODS

    method = str((getattr(model, "hparams", None) or {}).get("method") or "spread")
    if method in METHODS and not METHODS.get(method).graph_conditioned:
        import warnings

        warnings.warn(f"guidance.relation={guided.weight('relation'):g}: relation guidance pulls the objects towards "
                      f"the support graph, but {ckpt} is a '{method}' checkpoint, not trained with the graphs "
                      f"(set guidance.relation=0 to steer it by collision and gravity only)", UserWarning, stacklevel=2)


def checkpoint_data_settings(ckpt: dict, model) -> dict:
    """``num_points`` and point ``seed`` the checkpoint was trained with (its data module's hyperparameters;
    the model's ``num_points`` and seed 0 when it was trained without one), and the model's ``geometry_distance``
    (what its batches must carry)."""
    hp = ckpt.get("datamodule_hyper_parameters") or {}
    points = hp["num_points"] if "num_points" in hp else model.config.num_points
    return {"num_points": int(points), "seed": int(hp.get("seed", 0)),
            "geometry_distance": str(getattr(getattr(model, "config", None), "geometry_distance", "chamfer"))}


def cached_model(ckpt: str, device: str):
    """The model of a ``spread-train`` checkpoint (SceneDiffusion or a baseline) in eval mode on ``device``,
    built once per process from the one read of the file (:mod:`spread.readonce`): a second worker or a
    second sweep trial in this process re-uses it (sampling never changes its weights)."""
    from spread import readonce
    from spread.methods import module_from_checkpoint

    device = resolve_device(device)
    return readonce.memo("model", (readonce.file_key(ckpt), device), lambda: module_from_checkpoint(
        readonce.checkpoint(ckpt), map_location=device, source=str(ckpt)).eval())


def cached_dataset(data_root: str, split: str, num_points: int, seed: int, geometry_distance: str = "chamfer"):
    """The :class:`~spread.data.SceneDataset` encoding a split's graphs (its library and scene files read
    through :mod:`spread.readonce`), once per process and settings."""
    from spread import readonce
    from spread.data import SceneDataset

    root = Path(data_root).resolve()
    library = readonce.asset_library(root / "assets")
    parts = [root / split, root / "stats.json", root / "manifest.json"]  # the files, bounds, category order
    key = (str(root), split, int(num_points), int(seed), str(geometry_distance), readonce.library_key(library),
           *[readonce.file_key(p) if p.exists() else str(p) for p in parts])
    return readonce.memo("dataset", key, lambda: SceneDataset(root, split, library=library, num_points=num_points,
                                                               seed=seed, reader=readonce.scene,
                                                               geometry_distance=geometry_distance))


def load_pipeline(cfg) -> ScenePipeline:
    """The pipeline of a :class:`~spread.sampling.SamplingConfig`: its checkpoint's model (SceneDiffusion or a
    baseline, in eval mode on ``cfg.device``), an encoder of ``cfg.data``'s split with the checkpoint's point
    settings, ``cfg.sampler``, ``cfg.guidance``, ``cfg.use_ema``, ``cfg.graph_scale``, ``cfg.geometry_scale``. The model and the
    encoder are built once per process (:func:`cached_model`, :func:`cached_dataset`)."""
    from spread import readonce

    model = cached_model(cfg.ckpt, cfg.device)
    check_sampling_kind(cfg, model)
    warn_graph_guidance(cfg.guidance, model, cfg.ckpt)
    data = checkpoint_data_settings(readonce.checkpoint(cfg.ckpt), model)
    dataset = cached_dataset(cfg.data.root, cfg.data.split, data["num_points"], data["seed"], data["geometry_distance"])
    return pipeline_of(cfg, model, dataset)


def pipeline_of(cfg, model, dataset) -> ScenePipeline:
    """The :class:`~spread.sampling.pipeline.ScenePipeline` of a config's settings around ``model`` and ``dataset``."""
    return ScenePipeline(model, dataset, cfg.sampler, cfg.guidance, cfg.use_ema, cfg.graph_scale,
                         cuda_graph=cfg.cuda_graph, precision=cfg.precision, geometry_scale=cfg.geometry_scale)


def check_settings(cfg, model) -> None:
    """The config's sampling settings against the model they would sample, refused in one line (``ValueError``) where
    they cannot run: guidance on a method that samples its own way, and every check of the pipeline's (precision,
    the guidance scales, ``cuda_graph=true`` on a model whose step cannot be recorded). The driver runs it on the
    checkpoint's model built on the ``meta`` device before anything in the output folder is touched
    (:func:`spread.sampling.run.check_checkpoint`); a worker's :func:`load_pipeline` makes the same checks on its
    real model as it builds the pipeline."""
    check_sampling_kind(cfg, model)
    pipeline_of(cfg, model, None)


def check_sampling_kind(cfg, model) -> None:
    """``ValueError`` for guidance on a method that samples its own way (not through the pipeline's loop)."""
    if cfg.guidance.active and sampling_kind(model) != "pipeline":
        raise ValueError(f"guidance={cfg.guidance.mode}: guidance steers the methods that sample through the pipeline's "
                         f"loop; {cfg.ckpt} is a '{model.hparams.method}' checkpoint, which samples its own way "
                         f"(sample it with guidance=none)")


def generated_scene(source: Scene, translation: np.ndarray, rotation: np.ndarray, item: SampleItem,
                    provenance: str, trajectory=None) -> Scene:
    """The source's objects, graphs and room with new poses and the provenance extras (module docstring)."""
    scene = source.with_poses(translation, rotation, scene_id=item.name)
    scene.extras = {"source": np.asarray(f"{provenance} graph={item.graph.scene_id} k={item.k}"),
                    "conditioned_on": np.asarray(source.scene_id)}
    if "room_type" in source.extras:  # evaluation reports per room type (imported 3D-FRONT rooms)
        scene.extras["room_type"] = np.asarray(source.extras["room_type"])
    if "mount" in source.extras:  # wall and ceiling mounts stay welded when the sample is simulated
        scene.extras["mount"] = np.asarray(source.extras["mount"])
    if trajectory is not None:  # the guidance timeline (guidance.record_every), for spread-view
        scene.extras["trajectory_translation"] = np.asarray(trajectory[0], np.float32)
        scene.extras["trajectory_rotation"] = np.asarray(trajectory[1], np.float32)
    return scene


class SampleWorker:
    """Builds the pipeline of ``cfg`` (a :class:`~spread.sampling.SamplingConfig`, as it is: Ray pickles the
    dataclass) once; :meth:`run` samples a batch and writes its missing scene files to ``scenes_dir``.

    ``cfg.threads``: torch intra-op threads (None: leave as is); the rest as in :func:`load_pipeline`.
    """

    def __init__(self, cfg, scenes_dir: str | Path):
        import torch

        if cfg.threads:
            torch.set_num_threads(int(cfg.threads))
        from spread.runtime.fingerprint import sampler_label

        self.scenes_dir = Path(scenes_dir)
        self.pipeline = load_pipeline(cfg)
        guided = self.pipeline.guidance
        self.provenance = (f"ckpt={cfg.ckpt} sampler={sampler_label(cfg.ckpt, self.pipeline.sampler)} seed={int(cfg.seed)}"
                           + (f" guidance={guided.label}" if guided else ""))
        self.repaired = 0  # degenerate rotations replaced so far (repair_rotations)

    def source(self, item: SampleItem) -> Scene:
        """The validated source scene of an item (read once per process: :func:`spread.readonce.scene`)."""
        from spread import readonce

        return readonce.scene(item.graph.path, self.pipeline.dataset.library)

    def reads(self) -> dict:
        """This process's reads and hits per kind (:func:`spread.readonce.counts`): what a Ray actor read."""
        from spread import readonce

        return readonce.counts()

    def sample(self, batch: BatchPlan) -> list[Scene]:
        """The generated scenes of every item of ``batch``, in order (nothing written)."""
        import torch

        sources = [self.source(item) for item in batch.items]
        # one CPU generator per sample, seeded by (seed, graph, k): its noise is the same on any device and in
        # any batch (so batch_size and workers change a sample only by float rounding, not by its noise)
        generators = [torch.Generator().manual_seed(item.seed) for item in batch.items]
        poses = self.pipeline(sources, generators, [item.graph.path for item in batch.items])
        scenes = []
        for src, item, p in zip(sources, batch.items, poses):
            self.repaired += p.repaired
            scenes.append(generated_scene(src, p.translation, p.rotation, item, self.provenance, p.trajectory))
        return scenes

    def run(self, batch: BatchPlan) -> dict:
        """Sample ``batch`` and write its scene files that are missing; returns ``{"index", "written",
        "skipped", "implausible", "repaired_rotations", "seconds", "pid"}`` (nothing is sampled when no file is
        missing). A sample the model made physically implausible (an object beyond the
        :class:`~spread.scene.Plausibility` bounds) is written as made, unvalidated, and named in ``implausible``
        with why: it is a result (every reader refuses it; ``spread-evaluate`` counts it apart, ``n_implausible``),
        not a reason to end the run, and sampling it again gives the same."""
        from spread.scene import ImplausibleSceneError, write_scene

        started = time.perf_counter()
        repaired_before = self.repaired
        wanted = {item.name for item in missing_items(batch, self.scenes_dir)}
        written, implausible = [], {}
        if wanted:
            for scene in self.sample(batch):
                if scene.scene_id in wanted:
                    path = self.scenes_dir / f"{scene.scene_id}.npz"
                    try:
                        write_scene(scene, path)
                    except ImplausibleSceneError as exc:
                        write_scene(scene, path, validate=False)
                        implausible[scene.scene_id] = exc.problem
                    written.append(scene.scene_id)
        return {"index": batch.index, "written": written, "implausible": implausible,
                "skipped": [n for n in batch.names() if n not in wanted],
                "repaired_rotations": self.repaired - repaired_before, "seconds": time.perf_counter() - started,
                "guidance": self.pipeline.guidance_stats if wanted else {}, "pid": os.getpid()}
