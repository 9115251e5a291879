"""InstructScene's layout stage (Lin & Mu, ICLR 2024): a graph transformer that denoises boxes given a graph.

Facts from the paper and its public code and configs (chenguolin/InstructScene ``src/models/sg2sc_diffusion.py``,
``src/models/networks/transformer.py``, ``configs/*_sg2sc_diffusion_objfeat.yaml``; written anew here):

* Diffused: each object's box [centre (3), size (3), cos θ, sin θ] in [−1, 1]; DDPM, 1,000 steps, linear β
  1e-4 … 0.02, ε-prediction, x̂₀ clipped to [−1, 1]. Loss: the squared error of the centre, size and angle
  parts, each summed over channels and divided by the number of objects, added.
* Conditions: the object classes (embedding → GELU → Linear, concatenated with the noisy box → Linear to
  512, plus a sinusoidal instance code) and the relation graph, 10 spatial predicates + "none"
  (:mod:`spread.methods.predicates`, computed from our scenes by InstructScene's rules; embedding of 128
  → GELU → Linear; the diagonal zeroed). No shape features here (``use_objfeat`` false).
* 5 graph-transformer blocks, width 512, 8 heads, edges 128, GEGLU feed-forwards, dropout 0.1, AdaLN on
  the timestep (sinusoid 128 → MLP). Graph attention: per channel, the query–key product q_i ⊙ k_j is
  modulated by the edge, (1 + E_mul(e_ij)) ⊙ (q_i ⊙ k_j)/√d + E_add(e_ij), and becomes the edge's update;
  softmax over j per channel weights the values. Output: LayerNorm → Linear → ε̂ (8).
* Classifier-free guidance: 20% of training scenes lose their graph (InstructScene zeroes the edge
  embeddings; here every edge gets the padding code :data:`~spread.methods.predicates.PAD`, as
  SceneDiffusion's graph dropout does); at sampling ε̂ = ε̂_∅ + s(ε̂_G − ε̂_∅) with s = ``graph_scale``
  (InstructScene's ``cfg_scale``, default 1).
* AdamW, lr 1e-4, weight decay 0.02; EMA 0.9999.

On the platform: the class and the size are given (the size channels are imputed at every sampling step,
as DiffuScene's are), the centre and heading are generated with the platform's sampler (same budget and
seeds as SPREAD). This is SPREAD's graph denoiser without shape tokens, geometry or the physical graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from spread.methods.base import BaselineConfig, BaselineModule
from spread.methods.boxes import normalize_size, objects_of, poses
from spread.methods.diffuscene import BOX, LINEAR_SCHEDULE
from spread.methods.predicates import PAD, VOCAB, drop_edges, instruct_predicates
from spread.model.diffusion import NOISE_ROWS, Denoising, denoise, training_scheduler
from spread.model.encodings import TimestepEmbedding, sinusoidal_embedding
from spread.model.poses import denormalize


@dataclass(frozen=True)
class InstructSceneConfig(BaselineConfig):
    name: str = "custom"
    dim: int = 512
    edge_dim: int = 128
    time_dim: int = 128
    layers: int = 5
    heads: int = 8
    dropout: float = 0.1
    ff_mult: int = 4
    num_points: int = 1  # surface samples the data module loads per object (InstructScene needs none)

    @classmethod
    def paper(cls, **overrides) -> "InstructSceneConfig":
        """5 layers, width 512, 8 heads, edges 128, timestep 128, dropout 0.1 (sg2sc)."""
        return cls(name="paper", **overrides)

    @classmethod
    def tiny(cls, **overrides) -> "InstructSceneConfig":
        """2 layers, width 64, 4 heads, edges 32: minutes on a CPU."""
        return cls(**{**dict(name="tiny", dim=64, edge_dim=32, time_dim=64, layers=2, heads=4, dropout=0.0,
                             ff_mult=2), **overrides})


class AdaNorm(nn.Module):
    """LayerNorm (no affine) · (1 + scale(t)) + shift(t), t (B, T); x (B, ...)."""

    def __init__(self, dim: int, time_dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim, elementwise_affine=False)
        self.proj = nn.Sequential(nn.GELU(), nn.Linear(time_dim, 2 * dim))

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        scale, shift = self.proj(t).chunk(2, dim=-1)
        shape = (t.shape[0],) + (1,) * (x.dim() - 2) + (x.shape[-1],)
        return self.norm(x) * (1 + scale.view(shape)) + shift.view(shape)


class GEGLUFeedForward(nn.Module):
    def __init__(self, dim: int, mult: int, dropout: float):
        super().__init__()
        self.proj = nn.Linear(dim, 2 * dim * mult)
        self.out = nn.Sequential(nn.Dropout(dropout), nn.Linear(dim * mult, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, gate = self.proj(x).chunk(2, dim=-1)
        return self.out(a * F.gelu(gate))


class EdgeGraphAttention(nn.Module):
    """InstructScene's graph attention (module docstring): nodes x (B, N, D), edges e (B, N, N, E), mask
    (B, N) → node update (B, N, D), edge update (B, N, N, E). Padded nodes are never keys."""

    def __init__(self, dim: int, edge_dim: int, heads: int, dropout: float):
        super().__init__()
        self.heads, self.scale = heads, (dim // heads) ** -0.5
        self.to_q, self.to_k, self.to_v = (nn.Linear(dim, dim, bias=False) for _ in range(3))
        self.e_mul, self.e_add = nn.Linear(edge_dim, dim, bias=False), nn.Linear(edge_dim, dim, bias=False)
        self.x_out = nn.Sequential(nn.Linear(dim, dim), nn.Dropout(dropout))
        self.e_out = nn.Sequential(nn.Linear(dim, edge_dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, e: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        node = mask[..., None].to(x.dtype)
        pair = (mask[:, :, None] & mask[:, None, :])[..., None].to(x.dtype)
        h = self.heads
        q, k, v = (rearrange(f(x) * node, "b n (h d) -> b h n d", h=h) for f in (self.to_q, self.to_k, self.to_v))
        sim = q[:, :, :, None, :] * k[:, :, None, :, :] * self.scale  # (B, h, N, N, d)
        e_mul = rearrange(self.e_mul(e) * pair, "b i j (h d) -> b h i j d", h=h)
        e_add = rearrange(self.e_add(e) * pair, "b i j (h d) -> b h i j d", h=h)
        sim = (1 + e_mul) * sim + e_add
        e_new = self.e_out(rearrange(sim, "b h i j d -> b i j (h d)")) * pair
        keys = mask[:, None, None, :, None].bool()
        attn = sim.masked_fill(~keys, float("-inf")).softmax(dim=3)
        out = (attn * v[:, :, None, :, :]).sum(3)
        return self.x_out(rearrange(out, "b h n d -> b n (h d)")) * node, e_new


class GraphBlock(nn.Module):
    def __init__(self, cfg: InstructSceneConfig):
        super().__init__()
        D, E, T = cfg.dim, cfg.edge_dim, cfg.time_dim
        self.norm_x, self.norm_e = AdaNorm(D, T), AdaNorm(E, T)
        self.attn = EdgeGraphAttention(D, E, cfg.heads, cfg.dropout)
        self.norm_ffx, self.norm_ffe = AdaNorm(D, T), AdaNorm(E, T)
        self.ff_x, self.ff_e = GEGLUFeedForward(D, cfg.ff_mult, cfg.dropout), GEGLUFeedForward(E, cfg.ff_mult, cfg.dropout)

    def forward(self, x, e, t, mask):
        dx, de = self.attn(self.norm_x(x, t), self.norm_e(e, t), mask)
        x, e = x + dx, e + de
        return x + self.ff_x(self.norm_ffx(x, t)), e + self.ff_e(self.norm_ffe(e, t))


class GraphBoxDenoiser(nn.Module):
    """ε̂(boxes_t, t | classes, predicate graph) (B, N, 8), zero at padding."""

    def __init__(self, cfg: InstructSceneConfig, num_classes: int):
        super().__init__()
        D = cfg.dim
        self.cfg = cfg
        self.node_embed = nn.Sequential(nn.Embedding(num_classes + 1, D), nn.GELU(), nn.Linear(D, D))
        self.node_in = nn.Linear(D + BOX, D)
        self.edge_embed = nn.Sequential(nn.Embedding(VOCAB, cfg.edge_dim), nn.GELU(), nn.Linear(cfg.edge_dim, cfg.edge_dim))
        self.time = TimestepEmbedding(cfg.time_dim)
        self.blocks = nn.ModuleList(GraphBlock(cfg) for _ in range(cfg.layers))
        self.out = nn.Sequential(nn.LayerNorm(D), nn.Linear(D, BOX))

    def edge_features(self, edges: torch.Tensor) -> torch.Tensor:
        """(B, N, N) predicate codes → (B, N, N, edge_dim), the diagonal zeroed (InstructScene)."""
        N = edges.shape[-1]
        eye = torch.eye(N, dtype=torch.bool, device=edges.device)[None, :, :, None]
        return self.edge_embed(edges).masked_fill(eye, 0.0)

    def forward(self, boxes_t, t, category, edge_features, mask):
        N = boxes_t.shape[1]
        x = self.node_in(torch.cat([self.node_embed(category), boxes_t], dim=-1))
        x = x + sinusoidal_embedding(torch.arange(N, device=x.device), self.cfg.dim).to(x.dtype)[None]
        temb = self.time(t)
        e = edge_features
        for block in self.blocks:
            x, e = block(x, e, temb, mask)
        return self.out(x) * mask[..., None].to(x.dtype)


class InstructScene(BaselineModule):
    method = "instructscene"
    #: its step reads nothing on the host (counted in tests): recorded as a CUDA graph by default (sampling.cuda_graph)
    cuda_graph_capturable = True
    config_class = InstructSceneConfig

    def __init__(self, config="tiny", bounds=None, categories=None, size_bounds=None, lr: float = 1e-4,
                 weight_decay: float = 0.02, optimizer: str = "adamw", ema_decay: float = 0.9999, seed: int = 0,
                 graph_dropout: float = 0.2, method: str = "instructscene"):
        if not 0.0 <= graph_dropout <= 1.0:
            raise ValueError(f"InstructScene: graph_dropout must be in [0, 1], got {graph_dropout}")
        super().__init__(config, bounds, categories, size_bounds, lr, weight_decay, optimizer, ema_decay, seed,
                         method=method, graph_dropout=float(graph_dropout))
        self.noise_schedule = training_scheduler(**LINEAR_SCHEDULE)

    def make_network(self) -> nn.Module:
        return GraphBoxDenoiser(self.config, self.num_classes)

    def is_lamp(self, category: torch.Tensor) -> torch.Tensor:
        """(B, N) bool: the object's category name contains "lamp" (InstructScene's rule)."""
        lamps = torch.tensor(["lamp" in c for c in self.hparams.categories], device=category.device)
        return lamps[category]

    def boxes_and_graph(self, batch: dict):
        """Boxes x₀ (B, N, 8) in [−1, 1], the predicate graph (B, N, N), the objects."""
        obj = objects_of(batch)
        size = normalize_size(obj.size, self.hparams.size_bounds)
        x0 = torch.cat([obj.translation.to(size.dtype), size, torch.cos(obj.yaw)[..., None],
                        torch.sin(obj.yaw)[..., None]], dim=-1) * obj.mask[..., None]
        centre = denormalize(obj.translation, self.bounds.to(obj.translation))
        edges = instruct_predicates(centre, obj.size, obj.yaw, self.is_lamp(obj.category), obj.mask)
        return x0, edges, obj

    def condition_edges(self, edges: torch.Tensor, drop: torch.Tensor | None) -> torch.Tensor:
        """The graphs the network sees: the scenes in ``drop`` (B,) get the null graph (all PAD)."""
        return edges if drop is None else drop_edges(edges, drop)

    def loss(self, batch: dict, network: nn.Module, generator: torch.Generator | None = None) -> dict:
        x0, edges, obj = self.boxes_and_graph(batch)
        B, N, _ = x0.shape
        keep = obj.mask[..., None].to(x0.dtype)
        noise = torch.randn((B, max(N, NOISE_ROWS), BOX), generator=generator)[:, :N].to(x0) * keep
        t = torch.randint(0, self.noise_schedule.config.num_train_timesteps, (B,), generator=generator).to(x0.device)
        x_t = self.noise_schedule.add_noise(x0, noise, t) * keep
        drop = None
        if network.training and self.hparams.graph_dropout > 0:
            drop = torch.rand((B,), generator=generator).to(x0.device) < self.hparams.graph_dropout
        features = network.edge_features(self.condition_edges(edges, drop))
        eps = network(x_t, t, obj.category, features, obj.mask)
        count = obj.mask.sum().clamp(min=1).to(x0.dtype)
        sq = (eps - noise) ** 2 * keep
        parts = {"pos_mse": sq[..., :3].sum() / count, "size_mse": sq[..., 3:6].sum() / count,
                 "angle_mse": sq[..., 6:8].sum() / count}
        return {"loss": sum(parts.values()), **parts}

    def denoising(self, batch: dict, use_ema: bool = True, graph_scale: float = 1.0) -> Denoising:
        """The batch's :class:`~spread.model.diffusion.Denoising`: ε̂ over boxes (B, N, 8) given the classes and the
        predicate graph (``graph_scale`` ≠ 1: classifier-free guidance on the graph), on the linear schedule, the
        known size channels imputed into x̂₀ at every step, states decoded to poses (centre and heading)."""
        network = self.sampling_network(use_ema)
        batch = {k: v.to(self.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
        known, edges, obj = self.boxes_and_graph(batch)
        cond = network.edge_features(edges)
        null = network.edge_features(torch.full_like(edges, PAD)) if graph_scale != 1.0 else None

        def eps_fn(x_t, t):
            eps = network(x_t, t, obj.category, cond, obj.mask)
            if null is None:
                return eps
            eps_null = network(x_t, t, obj.category, null, obj.mask)
            return eps_null + graph_scale * (eps - eps_null)

        def decode(x):
            return poses(x[..., :3], torch.atan2(x[..., 7], x[..., 6]), obj.tilt, obj.mask, self.bounds)

        fixed = torch.zeros(BOX, dtype=torch.bool, device=self.device)
        fixed[3:6] = True
        return Denoising(eps_fn, obj.mask, decode, BOX, LINEAR_SCHEDULE,
                         x0_hook=lambda x0, ctx: torch.where(fixed, known, x0))

    def sample(self, batch: dict, sampler=None, generator=None, use_ema: bool = True, graph_scale: float = 1.0,
               callbacks=(), **kw):
        """Poses for the batch's object sets given their graphs (module docstring), through the one loop
        (:func:`~spread.model.diffusion.denoise`) with ``callbacks`` (guidance); ``graph_scale``: the
        classifier-free guidance scale on the graph."""
        network = self.sampling_network(use_ema)
        was = network.training
        network.eval()
        try:
            problem = self.denoising(batch, use_ema, graph_scale)
            return problem.decode(denoise(problem, sampler, generator, callbacks))
        finally:
            network.train(was)
