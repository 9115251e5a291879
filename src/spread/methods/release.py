"""``ReleaseDiffusion``: the SPREAD release's network (:mod:`spread.methods.release_network`) behind the platform's
sampling interface, so ``spread-sample`` samples the authors' weights and ``spread-evaluate`` scores them.

A platform checkpoint of this module is made from the release's ``ckpt.pth`` by
``spread-release-ckpt ckpt=ckpt.pth out=release.ckpt`` (``experiment=release`` sizes; EMA weights by default).
It is sampling-only: the release ships no training code, and ``spread-train experiment=release`` stops at
``setup`` saying so.

Inputs, as the release builds them (reference_implementation.md §1.3–1.5, §2.2), for a scene of N objects
plus the release's placeholder at index 0 (mask 1, zero point features):

* box state (12): normalised translation (the release's ``dataset_stats`` bounds, ``bounds`` here, metres),
  size (unused by the release: it never places meshes by it) and rot6d (first two columns of R);
* shape tokens: the scene's ``shape_tokens`` extra (the file's ``miche_feature``, 256 × 64 per object; zeros
  when the scene has none, and for the placeholder, whose tokens the importer does not keep);
* points: the scene's ``surface_points`` / ``surface_normals`` (the file's ``xyz`` / ``normal``, first
  ``num_points`` of them), else the asset library's canonical points moved into the file's frame;
  their 4-channel feature [local xyz, signed nearest distance to the other objects' posed points] is
  recomputed from x_t at every step;
* graphs: physical edges from the file's triples (``release_relations``: Empty and root ones included;
  3 where there is none), else from the platform's physical matrix (codes 1, 2; 3 elsewhere); spatial codes
  from the file's ``regions_bbox`` (``release_regions``: root row and column included), else the platform's
  codes with 7 (padding) for the placeholder's row and column;
* the image cross-attention fed zeros, as the release does (``use_image: false``).

Sampling: through the platform's one loop (:func:`spread.model.diffusion.denoise`) like every diffusion method:
:meth:`ReleaseDiffusion.denoising` gives the batch's :class:`~spread.model.diffusion.Denoising` — the network's
ε-function over states (B, 1 + N, 12) whose index 0 is the placeholder (``lead=1``: denoised with the objects, dropped
by ``decode``, never moved by guidance), the release's schedule (1000 cosine steps, ε-prediction, x̂_0 clipped to
±1, fixed-small variance: ``sampler=ddpm`` is the release's 1000 ancestral steps). Decoded poses are the platform's:
translation = T + R · (canonical offset − file bbox centre), so the file's frame and the library's canonical frame
agree (see :mod:`spread.importers.spread_release`); guidance terms act on them, for the real objects only.

Guidance: ``guidance=paper`` runs what the authors run after the sampler — their 100 refinement iterations at t = 0
with their own terms, gravity in the later half (``guidance.mode=release``, :mod:`spread.guidance.release`,
:meth:`ReleaseDiffusion.resolve_guidance`): ``spread-sample ckpt=release.ckpt sampler=ddpm guidance=paper`` is the
authors' pipeline. The other modes (``refine``, ``sample``, ``release``) run as asked, with the platform's terms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F

from spread.model.diffusion import Denoising, denoise, training_scheduler
from spread.model.module import Poses
from spread.methods.release_network import ReleaseNetwork, ReleaseNetworkConfig

#: The release's translation bounds (its dataset_stats.txt: min xyz, max xyz; metres).
RELEASE_BOUNDS = [-10.743414729014988, -0.004465443312673229, -8.645766256492678,
                  10.834109617906746, 3.083343120690726, 10.285219198353952]
#: The release's diffusion schedule (diffusers DDPMScheduler: squaredcos_cap_v2, 1000 steps, ε).
RELEASE_SCHEDULE = {"num_train_timesteps": 1000, "beta_schedule": "squaredcos_cap_v2", "prediction_type": "epsilon"}
EDGE_NONE, REGION_PAD, REGION_SELF = 3, 7, 6


def release_rotation(rot6d: torch.Tensor) -> torch.Tensor:
    """(..., 6) → (..., 3, 3) by Gram–Schmidt as the release computes it (norms without an added epsilon)."""
    b1 = F.normalize(rot6d[..., :3], dim=-1)
    a2 = rot6d[..., 3:6]
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    return torch.stack([b1, b2, torch.linalg.cross(b1, b2, dim=-1)], dim=-1)


@dataclass
class ReleaseData:
    """What the sampling pipeline reads from the module: surface points per object (the release's 1000)."""

    num_points: int = 1000


class ReleaseDiffusion(L.LightningModule):
    """The release's network with the platform's ``sample`` (module docstring). ``config``: fields of
    :class:`~spread.methods.release_network.ReleaseNetworkConfig`; ``bounds``: the translation bounds its boxes were
    normalised with; ``weights``: "ema" or "raw" (which of the file's weights were converted)."""

    method = "release"
    #: its point features loop over each scene's real objects on the host: no CUDA-graph capture (sampling.cuda_graph)
    cuda_graph_capturable = False

    def __init__(self, config: dict | None = None, bounds: Sequence[float] = tuple(RELEASE_BOUNDS),
                 num_points: int = 1000, weights: str = "ema", source: str | None = None, method: str = "release"):
        super().__init__()
        if method != self.method:
            raise ValueError(f"ReleaseDiffusion: hyperparameters are for method '{method}', not 'release'")
        config = dict(config or {})
        num_points = int(config.pop("num_points", num_points))  # conf/model/release.yaml keeps it in config
        net_config = ReleaseNetworkConfig(**config)
        bounds = [float(b) for b in bounds]
        if len(bounds) != 6 or not all(hi > lo for lo, hi in zip(bounds[:3], bounds[3:])):
            raise ValueError(f"ReleaseDiffusion: bounds must be [min x, y, z, max x, y, z], got {bounds}")
        self.save_hyperparameters({"method": self.method, "config": net_config.to_dict(), "bounds": bounds,
                                   "num_points": int(num_points), "weights": str(weights), "source": source})
        self.config = ReleaseData(int(num_points))
        self.network = ReleaseNetwork(net_config)
        self.noise_schedule = training_scheduler(**RELEASE_SCHEDULE)

    @property
    def bounds(self) -> torch.Tensor:
        """(6,) the translation bounds [min xyz, max xyz] the release's boxes are normalised by, metres."""
        return torch.tensor(self.hparams.bounds, dtype=torch.float32, device=self.device)

    @classmethod
    def resolve_guidance(cls, config):
        """The guidance this method runs for ``config`` (a GuidanceConfig): the paper's guidance is, for the authors'
        network, the authors' refinement (mode ``release``, same weights and schedule); other modes as asked. Declared
        once, by the method's registry entry (:attr:`~spread.methods.registry.MethodSpec.guidance_modes`), which the
        run's identity and tags ask too."""
        from spread.methods.registry import method_spec

        return method_spec(cls.method).guidance_run(config)

    def setup(self, stage: str | None = None) -> None:
        if stage == "fit":
            raise RuntimeError("experiment=release: the SPREAD release ships no training code; this model only "
                               "samples the authors' weights (spread-release-ckpt ckpt=ckpt.pth out=release.ckpt, "
                               "then spread-sample ckpt=release.ckpt)")

    def describe(self) -> str:
        c = self.network.config
        return f"release network (width {c.attn_dim}, {c.n_layers} blocks, {self.hparams.weights} weights)"

    # ---- inputs -----------------------------------------------------------------------------------------
    def scene_inputs(self, sources: Sequence, library) -> dict:
        """``{"release": {...}}``: per-scene arrays of the source scenes (padded to the batch's N) that the
        batch encoding lacks: shape tokens, the file's points, graphs and frame shift (module docstring)."""
        B, N = len(sources), max(s.num_objects for s in sources)
        D = int(self.network.config.miche_dim)
        given = [np.asarray(s.extras["shape_tokens"]).shape for s in sources if "shape_tokens" in s.extras]
        L_ = given[0][1] if given else 256  # the release's 256 tokens per object (zeros when the scenes have none)
        tokens = torch.zeros(B, N, L_, D)
        shift = torch.zeros(B, N, 3)
        edges = torch.full((B, N + 1, N + 1), EDGE_NONE, dtype=torch.long)
        regions = torch.full((B, N + 1, N + 1), REGION_PAD, dtype=torch.long)
        P = int(self.config.num_points)
        have_points = all("surface_points" in s.extras and "surface_normals" in s.extras
                          and np.asarray(s.extras["surface_points"]).shape[1] >= P for s in sources)
        points = torch.zeros(B, N, P, 3) if have_points else None
        normals = torch.zeros(B, N, P, 3) if have_points else None
        for b, s in enumerate(sources):
            n, ex = s.num_objects, s.extras
            if "shape_tokens" in ex:
                t = torch.as_tensor(np.asarray(ex["shape_tokens"], np.float32))
                if t.shape[1:] != tokens.shape[2:]:
                    raise ValueError(f"scene '{s.scene_id}': shape_tokens {tuple(t.shape)}, expected (N, {L_}, {D}) "
                                     f"(the batch's first scene's token count, the network's token width)")
                tokens[b, :n] = t
            offsets = np.array([library[str(a)].source.get("canonical_offset", [0.0] * 3) for a in s.asset_id], np.float64)
            centres = np.asarray(ex.get("reference_bbox_center", offsets), np.float64)
            shift[b, :n] = torch.from_numpy(offsets - centres).float()
            if "release_relations" in ex:
                for si, p, o in np.asarray(ex["release_relations"]).reshape(-1, 3):
                    edges[b, int(si), int(o)] = int(p)
            else:
                phys = torch.as_tensor(np.asarray(s.physical, np.int64))
                edges[b, 1:n + 1, 1:n + 1] = torch.where((phys == 1) | (phys == 2), phys, EDGE_NONE)
            if "release_regions" in ex and np.asarray(ex["release_regions"]).shape == (n + 1, n + 1):
                regions[b, :n + 1, :n + 1] = torch.as_tensor(np.asarray(ex["release_regions"], np.int64))
            else:
                regions[b, 1:n + 1, 1:n + 1] = torch.as_tensor(np.asarray(s.spatial, np.int64))
                regions[b, 0, 0] = REGION_SELF
            if have_points:
                points[b, :n] = torch.as_tensor(np.asarray(ex["surface_points"], np.float32)[:, :P])
                normals[b, :n] = torch.as_tensor(np.asarray(ex["surface_normals"], np.float32)[:, :P])
        return {"release": {"shape_tokens": tokens, "shift": shift, "edges": edges, "regions": regions,
                            "points": points, "normals": normals}}

    def point_features(self, x: torch.Tensor, points: torch.Tensor, normals: torch.Tensor,
                       mask: torch.Tensor) -> torch.Tensor:
        """(B, N+1, P, 4): [local xyz, signed distance of each posed point to the nearest posed point of the
        other objects, sign from that point's normal] (release §2.2); zeros at the placeholder and padding.
        x (B, N+1, 12) normalised boxes; points/normals (B, N, P, 3) in the file's object frames."""
        B, N, P, _ = points.shape
        T = self.denormalise(x[:, 1:, :3])
        R = release_rotation(x[:, 1:, 6:12])
        world = torch.einsum("bnij,bnpj->bnpi", R, points) + T[:, :, None]
        wn = torch.einsum("bnij,bnpj->bnpi", R, normals)
        sd = torch.zeros(B, N, P, dtype=x.dtype, device=x.device)
        for b in range(B):
            real = torch.nonzero(mask[b]).flatten().tolist()
            for i in real:
                others = [j for j in real if j != i]
                if not others:
                    continue
                q, qn = world[b, others].reshape(-1, 3), wn[b, others].reshape(-1, 3)
                d, k = torch.cdist(world[b, i], q).min(dim=1)
                sd[b, i] = torch.sign(((world[b, i] - q[k]) * qn[k]).sum(-1)) * d
        feats = torch.cat([points, sd[..., None]], dim=-1) * mask[:, :, None, None]
        return torch.cat([torch.zeros_like(feats[:, :1]), feats], dim=1)

    def denormalise(self, t: torch.Tensor) -> torch.Tensor:
        bounds = torch.tensor(self.hparams.bounds, dtype=t.dtype, device=t.device)
        return (t + 1.0) / 2.0 * (bounds[3:] - bounds[:3]) + bounds[:3]

    # ---- sampling -----------------------------------------------------------------------------------------
    def denoising(self, batch: dict, use_ema: bool = True, graph_scale: float = 1.0) -> Denoising:
        """The batch's :class:`~spread.model.diffusion.Denoising` (module docstring): states (B, 1 + N, 12) with the
        placeholder at index 0 (``lead=1``), decoded to the real objects' poses. ``batch`` needs the ``release``
        inputs of :meth:`scene_inputs` (the sampling pipeline adds them); ``use_ema`` is fixed at conversion
        (``hparams.weights``); the release has no classifier-free graph guidance (``graph_scale`` must be 1)."""
        if "release" not in batch:
            raise ValueError("ReleaseDiffusion: the batch has no 'release' inputs (scene_inputs)")
        if float(graph_scale) != 1.0:
            raise ValueError(f"ReleaseDiffusion: graph_scale={graph_scale}: the release has no classifier-free graph "
                             f"guidance (its cfg_scale path does not run); sample with graph_scale=1")
        r = {k: (v.to(self.device) if isinstance(v, torch.Tensor) else v) for k, v in batch["release"].items()}
        mask = batch["mask"].to(self.device).bool()
        B, N = mask.shape
        mask1 = torch.cat([torch.ones(B, 1, dtype=torch.bool, device=self.device), mask], dim=1)
        if r["points"] is not None:
            points, normals = r["points"], r["normals"]
        else:  # library points (canonical frame) moved into the file's frame
            points = batch["points"].to(self.device) + r["shift"][:, :, None]
            normals = batch["normals"].to(self.device)
        tokens = torch.cat([torch.zeros_like(r["shape_tokens"][:, :1]), r["shape_tokens"]], dim=1)
        net = self.network.eval()
        dtype = next(net.parameters()).dtype

        def eps_fn(x, t):  # in the network's precision (guidance may keep float64 states)
            xn = x.to(dtype)
            pc = self.point_features(xn, points.to(dtype), normals.to(dtype), mask.to(dtype))
            return net(xn, pc, tokens.to(dtype), r["edges"], r["regions"], t, None, mask1.to(dtype)).to(x.dtype)

        def decode(x):  # the placeholder (index 0) dropped
            R = release_rotation(x[:, 1:, 6:12])
            T = self.denormalise(x[:, 1:, :3]) + torch.einsum("bnij,bnj->bni", R, r["shift"].to(x.dtype))
            eye = torch.eye(3, device=x.device, dtype=R.dtype).expand(B, N, 3, 3)
            keep = mask[..., None]
            return Poses(torch.where(keep, T, 0.0), torch.where(keep[..., None], R, eye))

        return Denoising(eps_fn, mask1, decode, 12, RELEASE_SCHEDULE, lead=1)

    def sample(self, batch: dict, sampler=None, generator=None, use_ema: bool = True, **kw) -> Poses:
        """Unguided poses (translation (B, N, 3) metres, rotation (B, N, 3, 3)) of the batch's scenes through the one
        loop (default sampler: the release's 1000 DDPM steps); guided sampling goes through the pipeline."""
        problem = self.denoising(batch, use_ema)
        return problem.decode(denoise(problem, sampler or "ddpm", generator))
