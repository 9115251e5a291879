"""Data: scene files → tensors (normalised poses, graphs, per-asset points), padding, Lightning module.

The public names are imported on first access (:mod:`spread.lazy`), so that ``import spread.data.splits`` (a
training command's check of its data folder) does not pay for torch, and ``import spread.data`` not for Lightning
(it never imports pybullet, ray or wandb).
"""
from spread.lazy import lazy_names

__getattr__, __dir__ = lazy_names(__name__, {
    "spread.data.collate": ("INDEX_PAD", "PHYSICAL_PAD", "SPATIAL_PAD", "collate_scenes"),
    "spread.data.dataset": ("SceneDataset",),
    "spread.data.points": ("DEFAULT_NUM_POINTS", "asset_points", "point_indices"),
    "spread.data.rotation": ("matrix_to_rot6d", "rot6d_to_matrix"),
    "spread.data.stats": ("StatsError", "compute_stats", "denormalize_translation", "load_stats",
                          "normalize_translation", "save_stats"),
    "spread.data.datamodule": ("SceneDataModule",),
})
