"""DiffuScene (Tang et al., CVPR 2024) and PhyScene-style box-IoU guidance on it (Yang et al., CVPR 2024).

DiffuScene — facts from the paper and its public configs (tangjiapeng/DiffuScene ``config/uncond/*``,
written anew here):

* A scene is a fixed set of object slots, each the vector [centre (3), size (3), cos θ, sin θ, class
  one-hot (C)] in [−1, 1] (classes in {0, 1}); ``objfeat_dim = 0`` here (no shape autoencoder).
* DDPM, 1,000 steps, linear β from 1e-4 to 0.02, ε-prediction (the ``*_eps`` configs).
* Denoiser: a 1-D UNet over the slots with kernel-1 convolutions (512 channels, four levels with
  ``dim_mults`` [1, 1, 1, 1], no down-sampling): separate MLP encoders of the box and class channels,
  ResNet blocks (GroupNorm, SiLU, FiLM by the timestep embedding, and by a learnable per-slot instance
  embedding of 128), linear attention across slots at every level, full attention in the middle, separate
  box and class decoders.
* Loss: mean squared error of the box part plus that of the class part, plus 0.1·ᾱ_t × the mean pairwise
  axis-aligned IoU of the predicted x̂₀ boxes (``loss_iou``). Adam, lr 2e-4 halved every 10,000 steps
  (``lr_step``, ``lr_decay``), gradient norm clipped at 10, no weight decay, no EMA.

On the platform: the slots are the batch's objects padded to its largest scene; **the slot mask hides
empty slots from the loss** and from every other slot (masked GroupNorm statistics and masked attention),
where DiffuScene trains an "empty" class on padded slots instead — our object sets are given, so a slot is
never empty by choice. At sampling the class and size channels are the object's own (imputed: x̂₀'s known
channels are replaced at every step, so x_t's known part follows q(x_t | x₀)) and the centre and (cos θ,
sin θ) are generated, with the platform's :class:`~spread.model.diffusion.Sampler` on the linear schedule
(same sampler, budget and seeds as SPREAD). No relation graph: GRecall is not comparable.

PhyScene-style guidance is not part of this module: it is the guidance term ``box_iou``
(:mod:`spread.guidance.box_iou`), which ``guidance=physcene`` switches on for any method that samples through the
pipeline; the ``physcene`` method (:data:`~spread.methods.registry.METHODS`) is DiffuScene's checkpoint sampled
with it. DiffuScene samples through the platform's one loop (:func:`spread.model.diffusion.denoise`):
:meth:`DiffuScene.denoising` gives its ε-function, its state decoder (centre and heading → poses) and the
imputation of the known channels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from spread.methods.base import BaselineConfig, BaselineModule
from spread.box_geometry import axis_aligned_iou, pairwise
from spread.methods.boxes import denormalize_size, normalize_size, objects_of, poses
from spread.model.diffusion import NOISE_ROWS, Denoising, denoise, training_scheduler
from spread.model.encodings import sinusoidal_embedding
from spread.model.poses import denormalize

#: The noise schedule of DiffuScene and InstructScene (DDPM, T = 1000, linear β 1e-4 … 0.02, ε-prediction).
LINEAR_SCHEDULE = {"beta_schedule": "linear", "beta_start": 1e-4, "beta_end": 0.02}
BOX = 8  # centre 3, size 3, cos, sin


@dataclass(frozen=True)
class DiffuSceneConfig(BaselineConfig):
    name: str = "custom"
    dim: int = 512
    levels: int = 4  # dim_mults [1] * levels
    instance_dim: int = 128
    max_slots: int = 64  # learnable instance embeddings (DiffuScene: the dataset's max objects)
    groups: int = 8  # GroupNorm groups
    attn_heads: int = 4
    attn_dim_head: int = 32
    iou_weight: float = 0.1  # loss_iou factor (× ᾱ_t)
    num_points: int = 1  # surface samples the data module loads per object (DiffuScene needs none)

    @classmethod
    def paper(cls, **overrides) -> "DiffuSceneConfig":
        """512 channels, 4 levels, instance embedding 128, attention 4 × 32 (DiffuScene's bedroom config)."""
        return cls(name="paper", **overrides)

    @classmethod
    def tiny(cls, **overrides) -> "DiffuSceneConfig":
        """64 channels, 2 levels, instance embedding 32: minutes on a CPU."""
        return cls(**{**dict(name="tiny", dim=64, levels=2, instance_dim=32, attn_heads=2, attn_dim_head=16),
                      **overrides})


# ---- the 1-D UNet (over slots) --------------------------------------------------------------------------

class MaskedGroupNorm(nn.Module):
    """GroupNorm over (channels of a group × real slots) of x (B, C, N); padded slots never enter the
    statistics (DiffuScene normalises over every slot)."""

    def __init__(self, groups: int, channels: int):
        super().__init__()
        self.groups = groups
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        B, C, N = x.shape
        g = x.view(B, self.groups, C // self.groups, N)
        m = mask[:, None, None, :].to(x.dtype)
        count = (m.sum(-1, keepdim=True) * (C // self.groups)).clamp(min=1)
        mean = (g * m).sum((-1, -2), keepdim=True) / count
        var = (((g - mean) ** 2) * m).sum((-1, -2), keepdim=True) / count
        g = (g - mean) / torch.sqrt(var + 1e-5)
        return g.view(B, C, N) * self.weight[:, None] + self.bias[:, None]


class ChannelNorm(nn.Module):
    """DiffuScene's LayerNorm over the channels of each slot, (B, C, N)."""

    def __init__(self, channels: int):
        super().__init__()
        self.g = nn.Parameter(torch.ones(1, channels, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = x.mean(1, keepdim=True)
        var = x.var(1, unbiased=False, keepdim=True)
        return (x - mean) * (var + 1e-5).rsqrt() * self.g


class ResBlock(nn.Module):
    """Two (1×1 conv → masked GroupNorm → [FiLM] → SiLU) blocks + residual; ``cond`` (B, E) or (B, N, E)."""

    def __init__(self, dim_in: int, dim_out: int, cond_dim: int, groups: int):
        super().__init__()
        self.film = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 2 * dim_out))
        self.conv1, self.norm1 = nn.Conv1d(dim_in, dim_out, 1), MaskedGroupNorm(groups, dim_out)
        self.conv2, self.norm2 = nn.Conv1d(dim_out, dim_out, 1), MaskedGroupNorm(groups, dim_out)
        self.skip = nn.Conv1d(dim_in, dim_out, 1) if dim_in != dim_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        film = self.film(cond)
        film = film[..., None] if film.dim() == 2 else film.transpose(1, 2)  # (B, 2C, 1 or N)
        scale, shift = film.chunk(2, dim=1)
        h = self.norm1(self.conv1(x), mask) * (scale + 1) + shift
        h = F.silu(h)
        h = F.silu(self.norm2(self.conv2(h), mask))
        return (h + self.skip(x)) * mask[:, None, :].to(x.dtype)


class SlotAttention(nn.Module):
    """Pre-norm residual attention across slots (B, C, N); ``linear``: DiffuScene's linear attention (softmax
    of queries over channels, of keys over slots), else softmax attention. Padded slots are never keys."""

    def __init__(self, dim: int, heads: int, dim_head: int, linear: bool):
        super().__init__()
        self.heads, self.scale, self.linear = heads, dim_head ** -0.5, linear
        self.norm = ChannelNorm(dim)
        self.to_qkv = nn.Conv1d(dim, 3 * heads * dim_head, 1, bias=False)
        self.to_out = nn.Sequential(nn.Conv1d(heads * dim_head, dim, 1), ChannelNorm(dim)) if linear else \
            nn.Conv1d(heads * dim_head, dim, 1)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        q, k, v = rearrange(self.to_qkv(self.norm(x)), "b (three h d) n -> three b h d n", three=3, h=self.heads)
        key = mask[:, None, None, :].bool()
        if self.linear:
            q = q.softmax(dim=-2) * self.scale
            k = k.masked_fill(~key, float("-inf")).softmax(dim=-1)
            v = v * key
            context = torch.einsum("bhdn,bhen->bhde", k, v)
            out = torch.einsum("bhde,bhdn->bhen", context, q)
        else:
            sim = torch.einsum("bhdi,bhdj->bhij", q * self.scale, k).masked_fill(~key, float("-inf"))
            out = torch.einsum("bhij,bhdj->bhdi", sim.softmax(dim=-1), v)
        out = self.to_out(rearrange(out, "b h d n -> b (h d) n"))
        return (x + out) * mask[:, None, :].to(x.dtype)


def encoder_mlp(inp: int, dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv1d(inp, dim, 1), nn.GELU(), nn.Conv1d(dim, 2 * dim, 1), nn.GELU(),
                         nn.Conv1d(2 * dim, dim, 1))


def decoder_mlp(dim: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv1d(dim, 2 * dim, 1), nn.GELU(), nn.Conv1d(2 * dim, dim, 1), nn.GELU(),
                         nn.Conv1d(dim, out, 1))


class UNet1D(nn.Module):
    """ε̂(x_t, t) for slot states x_t (B, N, 8 + C), zero at padded slots (module docstring)."""

    def __init__(self, cfg: DiffuSceneConfig, num_classes: int):
        super().__init__()
        D, G, T = cfg.dim, cfg.groups, 4 * cfg.dim
        self.cfg, self.num_classes = cfg, num_classes
        self.box_in, self.class_in = encoder_mlp(BOX, D), encoder_mlp(num_classes, D)
        self.init = nn.Conv1d(D, D, 1)
        self.time = nn.Sequential(nn.Linear(D, T), nn.GELU(), nn.Linear(T, T))
        self.instance = nn.Parameter(torch.randn(cfg.max_slots, cfg.instance_dim))
        I, h, dh = cfg.instance_dim, cfg.attn_heads, cfg.attn_dim_head
        self.downs = nn.ModuleList(nn.ModuleList([
            ResBlock(D, D, I, G), ResBlock(D, D, T, G), ResBlock(D, D, T, G), SlotAttention(D, h, dh, True),
            nn.Conv1d(D, D, 1)]) for _ in range(cfg.levels))
        self.mid = nn.ModuleList([ResBlock(D, D, I, G), ResBlock(D, D, T, G), SlotAttention(D, h, dh, False),
                                  ResBlock(D, D, T, G)])
        self.ups = nn.ModuleList(nn.ModuleList([
            ResBlock(D, D, I, G), ResBlock(2 * D, D, T, G), ResBlock(2 * D, D, T, G), SlotAttention(D, h, dh, True),
            nn.Conv1d(D, D, 1)]) for _ in range(cfg.levels))
        self.final = ResBlock(2 * D, D, T, G)
        self.box_out, self.class_out = decoder_mlp(D, BOX), decoder_mlp(D, num_classes)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        B, N, _ = x_t.shape
        if N > self.cfg.max_slots:
            raise ValueError(f"DiffuScene: {N} objects but max_slots={self.cfg.max_slots}; train with a larger "
                             f"model.config.max_slots")
        mask = mask.bool()
        keep = mask[:, None, :].to(x_t.dtype)
        x = rearrange(x_t, "b n c -> b c n")
        x = (self.box_in(x[:, :BOX]) + self.class_in(x[:, BOX:])) * keep
        x = self.init(x) * keep
        r = x
        temb = self.time(sinusoidal_embedding(t, self.cfg.dim).to(x.dtype))
        inst = self.instance[:N][None].expand(B, -1, -1).to(x.dtype)
        skips = []
        for block0, block1, block2, attn, proj in self.downs:
            x = block1(block0(x, inst, mask), temb, mask)
            skips.append(x)
            x = attn(block2(x, temb, mask), mask)
            skips.append(x)
            x = proj(x) * keep
        b0, b1, attn, b2 = self.mid
        x = b2(attn(b1(b0(x, inst, mask), temb, mask), mask), temb, mask)
        for block0, block1, block2, attn, proj in self.ups:
            x = block0(x, inst, mask)
            x = block1(torch.cat([x, skips.pop()], dim=1), temb, mask)
            x = block2(torch.cat([x, skips.pop()], dim=1), temb, mask)
            x = proj(attn(x, mask)) * keep
        x = self.final(torch.cat([x, r], dim=1), temb, mask)
        out = torch.cat([self.box_out(x), self.class_out(x)], dim=1) * keep
        return rearrange(out, "b c n -> b n c")


# ---- the LightningModule ------------------------------------------------------------------------------

class DiffuScene(BaselineModule):
    """DiffuScene (module docstring). Sampled with ``guidance=physcene`` it is the ``physcene`` row."""

    method = "diffuscene"
    config_class = DiffuSceneConfig
    #: its step reads nothing on the host (counted in tests): recorded as a CUDA graph by default (sampling.cuda_graph)
    cuda_graph_capturable = True

    def __init__(self, config="tiny", bounds=None, categories=None, size_bounds=None, lr: float = 2e-4,
                 weight_decay: float = 0.0, optimizer: str = "adam", ema_decay: float = 0.0, seed: int = 0,
                 lr_step: int = 0, lr_decay: float = 1.0, method: str = "diffuscene", box_guidance=None):
        if method == "physcene" or box_guidance:
            raise ValueError("a 'physcene' checkpoint of an older platform (spread.methods.with_box_guidance): "
                             "PhyScene's guidance is now the guidance term box_iou; sample the DiffuScene "
                             "checkpoint it was derived from with guidance=physcene")
        super().__init__(config, bounds, categories, size_bounds, lr, weight_decay, optimizer, ema_decay, seed,
                         method=method, lr_step=int(lr_step), lr_decay=float(lr_decay))
        self.noise_schedule = training_scheduler(**LINEAR_SCHEDULE)

    def make_network(self) -> nn.Module:
        return UNet1D(self.config, self.num_classes)

    @property
    def state_dim(self) -> int:
        return BOX + self.num_classes

    def state(self, batch: dict) -> tuple[torch.Tensor, torch.Tensor, object]:
        """Slot states x₀ (B, N, 8 + C) in [−1, 1], zero at padding; the mask; the objects."""
        obj = objects_of(batch)
        size = normalize_size(obj.size, self.hparams.size_bounds)
        onehot = F.one_hot(obj.category, self.num_classes).to(size.dtype)
        x0 = torch.cat([obj.translation.to(size.dtype), size, torch.cos(obj.yaw)[..., None],
                        torch.sin(obj.yaw)[..., None], onehot], dim=-1)
        return x0 * obj.mask[..., None], obj.mask, obj

    def boxes(self, x0: torch.Tensor) -> torch.Tensor:
        """(B, N, 7) world boxes [centre, size (metres), θ] of slot states."""
        centre = denormalize(x0[..., :3], self.bounds.to(x0))
        size = denormalize_size(x0[..., 3:6], self.hparams.size_bounds)
        yaw = torch.atan2(x0[..., 7], x0[..., 6])
        return torch.cat([centre, size, yaw[..., None]], dim=-1)

    def loss(self, batch: dict, network: nn.Module, generator: torch.Generator | None = None) -> dict:
        x0, mask, _ = self.state(batch)
        B = x0.shape[0]
        keep = mask[..., None].to(x0.dtype)
        # a fixed-size draw per scene: the real slots' noise does not depend on how far the batch is padded
        rows = max(x0.shape[1], NOISE_ROWS)
        noise = torch.randn((B, rows, x0.shape[2]), generator=generator)[:, :x0.shape[1]].to(x0) * keep
        t = torch.randint(0, self.noise_schedule.config.num_train_timesteps, (B,), generator=generator).to(x0.device)
        x_t = self.noise_schedule.add_noise(x0, noise, t) * keep
        eps = network(x_t, t, mask)
        count = mask.sum(1).clamp(min=1).to(x0.dtype)  # real slots per scene
        sq = (eps - noise) ** 2 * keep
        loss_box = sq[..., :BOX].sum((1, 2)) / (count * BOX)
        loss_class = sq[..., BOX:].sum((1, 2)) / (count * self.num_classes)
        terms = {"loss_box": loss_box.mean(), "loss_class": loss_class.mean()}
        total = loss_box + loss_class
        if self.config.iou_weight > 0:
            a = self.noise_schedule.alphas_cumprod.to(x0.device)[t].to(x0.dtype)
            x0_hat = ((x_t - (1 - a)[:, None, None].sqrt() * eps) / a[:, None, None].sqrt()).clamp(-1, 1)
            iou = pairwise(axis_aligned_iou, self.boxes(x0_hat), mask)
            pairs = (count * (count - 1)).clamp(min=1)
            mean_iou = iou.sum((1, 2)) / pairs
            total = total + self.config.iou_weight * a * mean_iou
            terms["box_iou"] = mean_iou.mean()
        return {"loss": total.mean(), **terms}

    # ---- sampling -------------------------------------------------------------------------------------
    def denoising(self, batch: dict, use_ema: bool = True, graph_scale: float = 1.0) -> Denoising:
        """The batch's :class:`~spread.model.diffusion.Denoising`: the network's ε̂ over slot states (B, N, 8 + C)
        on the linear schedule, the known class and size channels imputed into x̂₀ at every step and into the
        result (module docstring), states decoded to poses (centre and heading; the rest orientation held).
        The network is used as it is (``eval()`` first); no graph: ``graph_scale`` is ignored."""
        network = self.sampling_network(use_ema)
        batch = {k: v.to(self.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
        known, mask, obj = self.state(batch)
        fixed = torch.zeros(self.state_dim, dtype=torch.bool, device=self.device)
        fixed[3:6] = True
        fixed[BOX:] = True

        def decode(x):
            return poses(x[..., :3], torch.atan2(x[..., 7], x[..., 6]), obj.tilt, mask, self.bounds)

        return Denoising(lambda x_t, t: network(x_t, t, mask), mask, decode, self.state_dim, LINEAR_SCHEDULE,
                         x0_hook=lambda x0, ctx: torch.where(fixed, known, x0),
                         finish=lambda x: torch.where(fixed, known, x))

    def sample(self, batch: dict, sampler=None, generator=None, use_ema: bool = True, callbacks=(), **kw):
        """Poses for the batch's object sets (centre and heading sampled, the rest held; module docstring),
        through the one loop (:func:`~spread.model.diffusion.denoise`) with ``callbacks`` (guidance)."""
        network = self.sampling_network(use_ema)
        was = network.training
        network.eval()
        try:
            problem = self.denoising(batch, use_ema)
            return problem.decode(denoise(problem, sampler, generator, callbacks))
        finally:
            network.train(was)
