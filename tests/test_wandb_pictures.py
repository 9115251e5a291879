"""What a sampling run puts on wandb as pictures: one picture size per key (wandb shows a list of mixed sizes
wrongly, and warns "Images sizes do not match")."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest


class RecordingRun:
    """A wandb run's surface as the platform's loggers use it, recording what is logged."""

    def __init__(self):
        self.logged: list[dict] = []
        self.summary: dict = {}
        self.config = SimpleNamespace(update=lambda *a, **k: None)
        self.settings = SimpleNamespace(mode="disabled")
        self.finished = False

    def log(self, data: dict) -> None:
        self.logged.append(data)

    def finish(self) -> None:
        self.finished = True


def png(path: Path, size: tuple[int, int]) -> str:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, (200, 40, 40)).save(path)
    return str(path)


@pytest.mark.parametrize("evaluated", [False, True], ids=["sampled", "sampled_and_evaluated"])
def test_a_sampling_run_logs_one_picture_size_per_wandb_key(tmp_path, evaluated):
    """``spread-sample figures=1 evaluate=true`` logged its 3D cards and physics figures in the evaluation's list of
    top-down renders (three sizes under ``renders``; wandb warned). Now the renders go with the per-scene table and
    each kind of figure has its own key, whether or not the scenes were evaluated in the same command."""
    import wandb

    from spread.tracking.config import LoggerConfig
    from spread.tracking.sampling_wandb import log_sampling

    renders = [png(tmp_path / "renders" / f"s{i}.png", (524, 264)) for i in range(2)]
    figures = [png(tmp_path / "renders" / "s0_3d.png", (1330, 575)),
               png(tmp_path / "renders" / "s0_physics.png", (1430, 545))]
    manifest = {"samples": 2, "seconds": 1.5, "renders": renders, "figures": figures}
    evaluation = SimpleNamespace(metrics={"col_mesh": 0.1, "fid_status": "disabled", "protocol": {"metrics": []}},
                                 records=[{"scene_id": "s0", "num_objects": 3}, {"scene_id": "s1", "num_objects": 4}])
    run = RecordingRun()
    log_sampling(manifest, tmp_path, {}, LoggerConfig(name="wandb"), evaluation=evaluation if evaluated else None,
                 run=run)
    assert run.finished
    pictures = {key: value for entry in run.logged for key, value in entry.items()
                if isinstance(value, list) and value and all(isinstance(v, wandb.Image) for v in value)}
    assert sorted(pictures) == ["figures/3d", "figures/physics", "renders"]
    for key, images in pictures.items():
        assert len({(i.image.width, i.image.height) for i in images}) == 1, key
    assert [i._caption for i in pictures["renders"]] == ["s0", "s1"]
    tables = [entry["per_scene"] for entry in run.logged if "per_scene" in entry]
    assert len(tables) == (1 if evaluated else 0)
    if evaluated:
        assert [row[0] for row in tables[0].data] == ["s0", "s1"]
        assert all(isinstance(row[1], wandb.Image) for row in tables[0].data)  # the renders beside the table
