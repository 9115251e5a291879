"""What one sampling run generates: the conditioning graphs, one item per (graph, k), items in batches.

Determinism (DESIGN §3 "same seed, same files"):

* Each item's seed is derived from ``(seed, scene_id, k)`` by SHA-256 (:func:`sample_seed`), so it does
  not depend on the order of the graphs, on the worker that runs it or on how many there are.
* The batches are fixed by the graph list alone: graphs are ordered by (object count, scene id) — scenes
  of similar size share a batch, so little compute goes to padding — and, for each k separately, cut into
  runs of ``batch_size``. Asking for more samples per graph later adds batches and leaves those of the
  smaller k unchanged.
* Each item's noise comes from its own ``torch.Generator`` seeded with the item's seed (the sampler takes
  one generator per scene), so a sample does not depend on its batch-mates: with the deterministic samplers
  (DDIM, DPM-Solver++) another ``batch_size`` gives the same samples up to float rounding; DDPM's step
  noise is drawn at the batch's padded size, so there the batching still matters. Re-running
  a batch — after a crash, on another worker — gives the same files bit for bit on the same device and
  software. (:func:`batch_seed` names a batch's seed set; it no longer seeds noise.)
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

#: File name of a generated scene: ``<source scene id>_k<sample index>.npz`` (made a
#: :func:`spread.io.safe_name`, so that no scene id can lead a file outside ``out_dir``).
SAMPLE_NAME = "{graph}_k{k}"


def _hash_int(text: str) -> int:
    """A 63-bit integer from SHA-256 of ``text`` (a valid ``torch.Generator.manual_seed`` value)."""
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little") & (2 ** 63 - 1)


def sample_seed(seed: int, scene_id: str, k: int) -> int:
    """The seed of sample ``k`` of graph ``scene_id`` in a run with ``seed``."""
    return _hash_int(f"spread-sample/{int(seed)}/{scene_id}/{int(k)}")


@dataclass(frozen=True)
class Graph:
    """A conditioning graph: the source scene's id, file and object count."""

    scene_id: str
    path: str
    num_objects: int


@dataclass(frozen=True)
class SampleItem:
    """Sample ``k`` of ``graph``; ``seed`` = :func:`sample_seed` (seed, graph.scene_id, k)."""

    graph: Graph
    k: int
    seed: int

    @property
    def name(self) -> str:
        """The generated scene's id and file stem: one safe path component whatever the graph's id
        (``../../x`` or ``/abs/x`` or ``sub/dir`` become hashed names inside the scenes folder)."""
        from spread.io import safe_name

        return safe_name(SAMPLE_NAME.format(graph=self.graph.scene_id, k=self.k))


@dataclass(frozen=True)
class BatchPlan:
    """Items sampled together in one forward batch (one Ray task)."""

    index: int
    items: tuple[SampleItem, ...]

    @property
    def seed(self) -> int:
        return batch_seed(self.items)

    def names(self) -> list[str]:
        return [item.name for item in self.items]


def batch_seed(items) -> int:
    """The batch generator's seed: a hash of its items' seeds (so of seed, scene ids and ks)."""
    return _hash_int("spread-batch/" + ",".join(str(item.seed) for item in items))


def plan_batches(graphs: list[Graph], samples_per_graph: int, batch_size: int, seed: int) -> list[BatchPlan]:
    """Every item of the run in batches (module docstring for the order)."""
    if samples_per_graph < 1 or batch_size < 1:
        raise ValueError(f"samples_per_graph and batch_size must be ≥ 1, got {samples_per_graph}, {batch_size}")
    seen: dict[str, Graph] = {}
    for g in graphs:
        if g.scene_id in seen:
            raise ValueError(f"two conditioning graphs share the scene id '{g.scene_id}': {seen[g.scene_id].path} "
                             f"and {g.path} (sampled files are named after it)")
        seen[g.scene_id] = g
    ordered = sorted(graphs, key=lambda g: (g.num_objects, g.scene_id))
    batches: list[BatchPlan] = []
    for k in range(samples_per_graph):
        for start in range(0, len(ordered), batch_size):
            items = tuple(SampleItem(g, k, sample_seed(seed, g.scene_id, k)) for g in ordered[start:start + batch_size])
            batches.append(BatchPlan(len(batches), items))
    return batches


def missing_items(batch: BatchPlan, scenes_dir: str | Path) -> list[SampleItem]:
    """Items of ``batch`` whose scene file is not in ``scenes_dir`` yet (files are written atomically, and
    :func:`remove_unreadable` has removed damaged ones, so an existing file is complete)."""
    scenes_dir = Path(scenes_dir)
    return [item for item in batch.items if not (scenes_dir / f"{item.name}.npz").exists()]


def remove_unreadable(batches: list[BatchPlan], scenes_dir: str | Path,
                      implausible: dict[str, str] | None = None) -> list[str]:
    """Delete the plan's existing scene files that do not read back as valid scenes (cut short or damaged by
    something other than this platform's atomic writes), so a resumed run samples them again; returns their
    names. A file that reads back is kept as it is, and so is one that reads back whole but physically implausible
    (:class:`~spread.scene.ImplausibleSceneError`: a sample the model pushed kilometres away, written as made by
    :meth:`~spread.sampling.worker.SampleWorker.run`; sampled again it would be the same): its name and why go into
    ``implausible`` when given."""
    removed = []
    for item in (item for batch in batches for item in batch.items):
        path = Path(scenes_dir) / f"{item.name}.npz"
        if not path.exists():
            continue
        whole, problem = read_back(path)
        if not whole:  # any other reason it does not read back: sample it again
            path.unlink()
            removed.append(item.name)
        elif problem is not None and implausible is not None:
            implausible[item.name] = problem
    return removed


def read_back(path: Path) -> tuple[bool, str | None]:
    """(whether a written scene file reads back whole, why it is physically implausible or None)."""
    from spread.scene import ImplausibleSceneError, read_scene

    try:
        read_scene(path)
    except ImplausibleSceneError as exc:
        return True, exc.problem
    except Exception:  # noqa: BLE001 - cut short, damaged, not a scene
        return False, None
    return True, None
