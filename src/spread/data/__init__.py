"""Data: scene files → tensors (normalised poses, graphs, per-asset points), padding, Lightning module.

``SceneDataModule`` is imported on first access so that ``import spread.data`` does not pay for
Lightning (and never imports pybullet, ray or wandb).
"""
from spread.data.collate import INDEX_PAD, PHYSICAL_PAD, SPATIAL_PAD, collate_scenes  # noqa: F401
from spread.data.dataset import SceneDataset  # noqa: F401
from spread.data.points import DEFAULT_NUM_POINTS, asset_points, point_indices  # noqa: F401
from spread.data.rotation import matrix_to_rot6d, rot6d_to_matrix  # noqa: F401
from spread.data.stats import (  # noqa: F401
    StatsError, compute_stats, denormalize_translation, load_stats, normalize_translation, save_stats,
)


def __getattr__(name: str):
    if name == "SceneDataModule":
        from spread.data.datamodule import SceneDataModule

        return SceneDataModule
    raise AttributeError(f"module 'spread.data' has no attribute '{name}'")
