"""Scene FID (DESIGN §6): Fréchet distance between feature statistics of top-down renders.

Renders: :func:`fid_render` = :func:`spread.render.render_topdown` with :data:`FID_RENDER_SETTINGS`
(256 × 256, white background, the fixed per-category palette, objects painted bottom-up by height,
no outline; window = the scene's room rectangle, else its objects' bounds, plus the margin). The
settings go into the result so a number can be traced to the images behind it.

Features: clean-fid's ``clip_vit_b_32`` (the paper's) or ``inception_v3``, loaded from local files only
(:mod:`spread.metrics.extractors`); any callable ``images (B, H, W, 3) uint8 → (B, D)`` can be injected
instead (tests, other backbones). When the clean-fid weights are not on disk — the normal case offline —
``compute()`` reports ``fid = None`` with a ``fid_status`` saying why; never a stand-in number.

States, per set (generated / reference): Σf (D,), Σffᵀ (D, D) in float64 and the count, all summed
across processes. Mean and covariance follow exactly (μ = Σf / n, Σ = (Σffᵀ − n μμᵀ) / (n − 1), the
unbiased covariance of ``np.cov`` that ``cleanfid.fid.fid_from_feats`` uses) and the distance is
``cleanfid.fid.frechet_distance``. So sharded and merged states give the FID of the whole set.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from spread.metrics.base import SceneMetric, check_scene
from spread.metrics.extractors import FEATURE_DIMS, ExtractorStatus, load_extractor
from spread.render import TopDownRenderSettings, render_topdown
from spread.scene import Scene

#: The protocol's render settings (DESIGN §6).
FID_RENDER_SETTINGS = TopDownRenderSettings(image_size=256, background=(255, 255, 255), outline=False)
#: The paper's feature model.
DEFAULT_FEATURE_MODEL = "clip_vit_b_32"
SETS = ("generated", "reference")


def fid_render(scene: Scene, library, settings: TopDownRenderSettings = FID_RENDER_SETTINGS) -> np.ndarray:
    """(H, W, 3) uint8 top-down render of one scene for FID; raises on a scene that cannot be measured."""
    check_scene(scene, library)
    return render_topdown(scene, library, settings)


def scene_features(scenes: Sequence[Scene], library, extractor: Callable,
                   settings: TopDownRenderSettings = FID_RENDER_SETTINGS) -> np.ndarray:
    """(B, D) float64 features of the FID renders of ``scenes`` (what a worker ships to the driver)."""
    images = np.stack([fid_render(s, library, settings) for s in scenes])
    return np.asarray(extractor(images), np.float64)


def feature_statistics(total: np.ndarray, outer: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and unbiased covariance (D, D) from Σf, Σffᵀ and n ≥ 2."""
    mu = total / count
    sigma = (outer - count * np.outer(mu, mu)) / (count - 1)
    return mu, 0.5 * (sigma + sigma.T)


class SceneFID(SceneMetric):
    """FID between generated and reference scenes' top-down renders (lower is better).

    Args:
        feature_model: ``"clip_vit_b_32"`` (default, the paper's) or ``"inception_v3"``; the name of the
            injected extractor's features otherwise.
        extractor: a callable images (B, H, W, 3) uint8 → (B, D) features; overrides loading clean-fid's.
        feature_dim: D; defaults to ``extractor.feature_dim``, the clean-fid model's, or one probe call.
        weights_path: local clean-fid weights file (defaults: clean-fid's and CLIP's caches).
        render_settings: :data:`FID_RENDER_SETTINGS` unless a study changes them (recorded in the result).

    ``update(scenes, library, real=False)`` renders and embeds scenes (``real=True`` for the reference
    set); ``update(images=..., real=...)`` or ``update(features=..., real=...)`` take renders or
    features made elsewhere. ``compute()`` → dict: ``fid`` (float or None), ``fid_status``,
    ``feature_model``, ``num_generated``, ``num_reference``, ``render_settings``.
    """

    higher_is_better = False

    def __init__(self, feature_model: str = DEFAULT_FEATURE_MODEL, extractor: Callable | None = None,
                 feature_dim: int | None = None, weights_path: str | Path | None = None,
                 render_settings: TopDownRenderSettings = FID_RENDER_SETTINGS, device: str = "cpu", **kwargs):
        super().__init__(**kwargs)
        if extractor is None:
            loaded = load_extractor(feature_model, weights_path, device)
        else:
            loaded = ExtractorStatus(feature_model, extractor, 0, f"ok: injected extractor '{feature_model}'")
        dim = feature_dim or getattr(loaded.extractor, "feature_dim", None) or FEATURE_DIMS.get(feature_model)
        if dim is None:  # an injected extractor that does not say: ask it once
            dim = np.asarray(loaded.extractor(np.full((1, 8, 8, 3), 255, np.uint8))).shape[-1]
        self.feature_model, self.feature_dim, self.fid_status = feature_model, int(dim), loaded.status
        self.render_settings = render_settings
        object.__setattr__(self, "_extractor", loaded.extractor)  # not registered as a submodule / state
        for s in SETS:
            self._add_sum_state(f"{s}_sum", (self.feature_dim,))
            self._add_sum_state(f"{s}_outer", (self.feature_dim, self.feature_dim))
            self._add_sum_state(f"{s}_count", dtype=torch.int64)

    @property
    def available(self) -> bool:
        return self._extractor is not None

    def update(self, scenes: Sequence[Scene] | Scene = (), library=None, real: bool = False,
               images: np.ndarray | None = None, features: np.ndarray | None = None) -> None:
        """Add scenes (rendered with ``library``), images (B, H, W, 3) uint8, or features (B, D) to one set."""
        which = "reference" if real else "generated"
        if features is None and images is None:
            scenes = [scenes] if isinstance(scenes, Scene) else list(scenes)
            if not self.available:  # nothing to embed with: count the scenes, skip rendering
                for s in scenes:
                    check_scene(s, library)
                self._add(f"{which}_count", len(scenes))
                return
            if library is None and scenes:
                raise ValueError("SceneFID.update: scenes need the asset library (update(scenes, library))")
            images = [fid_render(s, library, self.render_settings) for s in scenes]
        if features is None:
            if not self.available:
                self._add(f"{which}_count", len(images))
                return
            features = self._extractor(np.stack(images)) if len(images) else np.zeros((0, self.feature_dim))
        f = torch.as_tensor(np.asarray(features, np.float64), device=self.device)
        if f.ndim != 2 or f.shape[1] != self.feature_dim:
            raise ValueError(f"SceneFID: features of shape {tuple(f.shape)}, expected (B, {self.feature_dim})")
        self._add(f"{which}_sum", f.sum(0))
        self._add(f"{which}_outer", f.T @ f)
        self._add(f"{which}_count", f.shape[0])

    def statistics(self, which: str) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of the ``"generated"`` or ``"reference"`` features (needs ≥ 2)."""
        return feature_statistics(getattr(self, f"{which}_sum").cpu().numpy(),
                                  getattr(self, f"{which}_outer").cpu().numpy(),
                                  int(getattr(self, f"{which}_count")))

    def compute(self) -> dict:
        n_gen, n_ref = int(self.generated_count), int(self.reference_count)
        out = {"fid": None, "fid_status": self.fid_status, "feature_model": self.feature_model,
               "num_generated": n_gen, "num_reference": n_ref, "render_settings": self.render_settings.to_dict()}
        if not self.available:
            return out
        if min(n_gen, n_ref) < 2:
            out["fid_status"] = (f"unavailable: FID needs at least 2 scenes per set "
                                 f"(generated {n_gen}, reference {n_ref})")
            return out
        from cleanfid.fid import frechet_distance

        try:
            out["fid"] = float(frechet_distance(*self.statistics("generated"), *self.statistics("reference")))
        except ValueError as exc:  # clean-fid refuses a covariance square root with a large imaginary part
            out["fid_status"] = f"unavailable: Fréchet distance failed ({exc})"
        return out
