"""One sampling worker: a checkpoint's model and the dataset's encoder, turning batches into scene files.

A worker holds one model (EMA weights by default) for its whole life, so a Ray actor — or the driver
itself when ``workers=0`` — pays for loading it once. Conditioning graphs are encoded exactly as in
training: the asset points are sampled with the ``num_points`` and ``seed`` of the data module the
checkpoint was trained with (Lightning stores its hyperparameters in the checkpoint).

A generated scene keeps the source's objects (asset ids, categories, order), both graphs and ``room``,
takes the sampled poses, and records where it came from in two extra arrays (DESIGN §4):
``source`` = ``"ckpt=… sampler=… seed=… graph=<scene_id> k=<i>"`` and ``conditioned_on`` = the source
scene id. Each file is validated and written atomically (:func:`spread.scene.write_scene`).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from spread.sampling.plan import BatchPlan, SampleItem, missing_items
from spread.scene import Scene

#: A sampled rotation further than this from orthonormal (max |RᵀR − I|) is replaced by its nearest rotation.
REPAIR_TOLERANCE = 1e-4


def resolve_device(device: str) -> str:
    """``auto``: ``cuda`` when a GPU is visible, else ``cpu``."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def sampler_label(sampler) -> str:
    """Short name of a :class:`~spread.model.Sampler`: ``ddim-50``, ``ddpm-1000``, ``dpmsolver++-20``."""
    return f"{sampler.kind}-{sampler.num_steps}" + (f"-eta{sampler.eta:g}" if sampler.eta else "")


def active_guidance(guidance):
    """The :class:`~spread.guidance.GuidanceConfig` of ``guidance`` (a config, mapping or mode name) when it
    guides; None for ``None``, ``"none"`` or a config with no weight > 0."""
    from spread.guidance import GuidanceConfig

    config = GuidanceConfig.from_config(guidance)
    return config if config.active else None


def guidance_label(config) -> str:
    """Short name of an active guidance config: ``refine(c=0.0075,g=0.001,r=0.001)``."""
    return f"{config.mode}(c={config.collision:g},g={config.gravity:g},r={config.relation:g})"


def checkpoint_data_settings(ckpt: dict, model) -> dict:
    """``num_points`` and point ``seed`` the checkpoint was trained with (its data module's hyperparameters;
    the model's ``num_points`` and seed 0 when it was trained without one)."""
    hp = ckpt.get("datamodule_hyper_parameters") or {}
    return {"num_points": int(hp.get("num_points", model.config.num_points)), "seed": int(hp.get("seed", 0))}


def repair_rotations(rotation: np.ndarray) -> tuple[np.ndarray, int]:
    """(N, 3, 3) rotations with the degenerate ones replaced by the nearest proper rotation (SVD); and how
    many were replaced. Gram–Schmidt of a sampled rot6d whose two columns are (anti)parallel — e.g. both
    clipped to (±1, ±1, ±1) by an undertrained model — leaves a zero column, which no reader accepts."""
    R = rotation.astype(np.float64)
    error = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > REPAIR_TOLERANCE) | (np.linalg.det(R) <= 0))
    if not len(bad):
        return rotation, 0
    U, _, Vt = np.linalg.svd(R[bad])
    D = np.ones((len(bad), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    D[D[:, 2] == 0, 2] = 1.0
    out = rotation.copy()
    out[bad] = ((U * D[:, None, :]) @ Vt).astype(rotation.dtype)
    return out, len(bad)


def generated_scene(source: Scene, translation: np.ndarray, rotation: np.ndarray, item: SampleItem,
                    provenance: str) -> Scene:
    """The source's objects, graphs and room with new poses and the provenance extras (module docstring)."""
    scene = source.with_poses(translation, rotation, scene_id=item.name)
    scene.extras = {"source": np.asarray(f"{provenance} graph={item.graph.scene_id} k={item.k}"),
                    "conditioned_on": np.asarray(source.scene_id)}
    return scene


class SampleWorker:
    """Loads ``ckpt`` once; :meth:`run` samples a batch and writes its missing scene files to ``scenes_dir``.

    ``sampler``: a :class:`~spread.model.Sampler` or its config; ``threads``: torch intra-op threads (None:
    leave as is); ``use_ema`` / ``graph_scale``: as in :meth:`SceneDiffusion.sample`; ``guidance``: a
    :class:`~spread.guidance.GuidanceConfig` or its mapping (None: unguided), applied to every batch with the
    batch's meshes and support graph.
    """

    def __init__(self, ckpt: str, data_root: str, split: str, scenes_dir: str, sampler, seed: int,
                 device: str = "cpu", threads: int | None = 1, use_ema: bool = True, graph_scale: float = 1.0,
                 guidance=None):
        import torch

        from spread.baselines import load_module
        from spread.data import SceneDataset
        from spread.model import Sampler
        from spread.model.module import SceneDiffusion

        if threads:
            torch.set_num_threads(int(threads))
        self.device = resolve_device(device)
        self.sampler = Sampler.from_config(sampler)
        self.use_ema, self.graph_scale = bool(use_ema), float(graph_scale)
        self.scenes_dir = Path(scenes_dir)
        checkpoint = torch.load(ckpt, map_location="cpu", weights_only=False)
        self.model = load_module(ckpt, map_location=self.device).eval()  # SceneDiffusion or a baseline
        data = checkpoint_data_settings(checkpoint, self.model)
        self.dataset = SceneDataset(data_root, split, num_points=data["num_points"], seed=data["seed"])
        self.guidance = active_guidance(guidance)
        if self.guidance is not None and not isinstance(self.model, SceneDiffusion):
            raise ValueError(f"guidance={self.guidance.mode}: SPREAD's guidance needs a SceneDiffusion checkpoint, "
                             f"{ckpt} is a '{self.model.hparams.method}' baseline (sample it with guidance=none)")
        self.provenance = (f"ckpt={ckpt} sampler={sampler_label(self.sampler)} seed={int(seed)}"
                           + (f" guidance={guidance_label(self.guidance)}" if self.guidance else ""))
        self.guidance_stats: dict = {}
        self._sources: dict[str, Scene] = {}
        self.repaired = 0  # degenerate rotations replaced so far (repair_rotations)

    def source(self, item: SampleItem) -> Scene:
        """The validated source scene of an item (memoised: a graph's k samples read it once)."""
        from spread.scene import read_scene

        path = item.graph.path
        if path not in self._sources:
            self._sources[path] = read_scene(path, assets=self.dataset.library)
        return self._sources[path]

    def sample(self, batch: BatchPlan) -> list[Scene]:
        """The generated scenes of every item of ``batch``, in order (nothing written)."""
        import torch

        from spread.data import collate_scenes

        sources = [self.source(item) for item in batch.items]
        encoded = collate_scenes([self.dataset.encode(src, source=item.graph.path)
                                  for src, item in zip(sources, batch.items)])
        # one CPU generator per sample, seeded by (seed, graph, k): its noise is the same on any device and in
        # any batch (so batch_size and workers change a sample only by float rounding, not by its noise)
        generator = [torch.Generator().manual_seed(item.seed) for item in batch.items]
        guidance = None
        if self.guidance is not None:
            from spread.guidance import SceneGuidance

            guidance = SceneGuidance(self.guidance, self.dataset.library, [list(src.asset_id) for src in sources],
                                     encoded["physical"].to(self.model.device), encoded["mask"].to(self.model.device),
                                     self.model.network.bounds)
        poses = self.model.sample(encoded, self.sampler, generator=generator, use_ema=self.use_ema,
                                  graph_scale=self.graph_scale, **({"guidance": guidance} if guidance else {}))
        self.guidance_stats = dict(guidance.stats) if guidance is not None else {}
        translation, rotation = poses.translation.cpu().numpy(), poses.rotation.cpu().numpy()
        scenes = []
        for b, (src, item) in enumerate(zip(sources, batch.items)):
            R, repaired = repair_rotations(rotation[b, :src.num_objects])
            self.repaired += repaired
            scenes.append(generated_scene(src, translation[b, :src.num_objects], R, item, self.provenance))
        return scenes

    def run(self, batch: BatchPlan) -> dict:
        """Sample ``batch`` and write its scene files that are missing; returns ``{"index", "written",
        "skipped", "repaired_rotations", "seconds", "pid"}`` (nothing is sampled when no file is missing)."""
        from spread.scene import write_scene

        started = time.perf_counter()
        repaired_before = self.repaired
        wanted = {item.name for item in missing_items(batch, self.scenes_dir)}
        written = []
        if wanted:
            for scene in self.sample(batch):
                if scene.scene_id in wanted:
                    write_scene(scene, self.scenes_dir / f"{scene.scene_id}.npz")
                    written.append(scene.scene_id)
        return {"index": batch.index, "written": written, "skipped": [n for n in batch.names() if n not in wanted],
                "repaired_rotations": self.repaired - repaired_before, "seconds": time.perf_counter() - started,
                "guidance": self.guidance_stats if wanted else {}, "pid": os.getpid()}
