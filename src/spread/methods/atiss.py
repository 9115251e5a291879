"""ATISS (Paschalidou et al., NeurIPS 2021): an autoregressive set transformer that adds objects one at a time.

Facts from the paper and its public configs (nv-tlabs/ATISS ``config/*_config.yaml``, written anew here):

* Sequence = [floor token, query token, the objects placed so far]; **no positional encoding** on the
  objects, so the model sees an unordered set and the query token's output F is invariant to the order
  of the context (:meth:`ATISS.log_likelihood` is tested for it). Transformer encoder: 4 layers, 8 heads
  of 64 (width 512), feed-forward 1024, GELU.
* Floor token: the room's floor plan as a 64 × 64 mask (rendered from the scene's ``room`` rectangle in
  the dataset's normalised xz frame) through a ResNet-18 (feature 64) and a Linear to 512. (GroupNorm
  instead of BatchNorm, so a scene's sample never depends on its batch-mates.)
* Object token: class (one-hot → Linear 64) and sinusoidal codes (64 each) of the centre (x, y, z), the
  size (x, y, z) and the angle → Linear to 512.
* Output: class logits (with an end class) → centre | class → angle | class, centre → size | class,
  centre, angle; each continuous value a discretised mixture of 10 logistics over 256 bins
  (:mod:`spread.methods.dmll`). Loss: the negative log-likelihood of the next object given a random
  subset of the others (a random permutation cut at a random length; the end class after the last).
* Adam, lr 1e-4, no weight decay, no EMA (ATISS uses none).

On the platform (fair comparison, :mod:`spread.methods.boxes`): the object set is given, so at sampling
the objects are placed in the scene's order with their own class (ATISS's ``add_object`` with a class
label), the centre and the angle are drawn from the model, and the size (and rest orientation) are the
object's own; the class and size heads are trained as in ATISS but not sampled. ATISS sees no relation
graph: its GRecall is not comparable (Table 1 prints "—"). It uses no diffusion sampler: one network pass
per object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from spread.methods import dmll
from spread.methods.base import BaselineConfig, BaselineModule, uniform_draws
from spread.methods.boxes import Objects, normalize_size, objects_of, poses

#: The floor raster covers normalised xz coordinates in [−FLOOR_WINDOW, FLOOR_WINDOW] (rooms reach a little
#: beyond the outermost object centres, which span [−1, 1]).
FLOOR_WINDOW = 1.25


@dataclass(frozen=True)
class ATISSConfig(BaselineConfig):
    name: str = "custom"
    dim: int = 512  # transformer width (heads × 64)
    layers: int = 4
    heads: int = 8
    ff_dim: int = 1024
    dropout: float = 0.1
    pe_dim: int = 64  # sinusoidal code of each scalar (centre x/y/z, size x/y/z, angle)
    class_dim: int = 64
    hidden_dim: int = 512  # width of the output MLPs
    mixtures: int = 10
    bins: int = 256
    floor_encoder: str = "resnet18"  # "resnet18" | "cnn" (three strided convolutions, for the tiny size)
    floor_features: int = 64
    floor_resolution: int = 64
    num_points: int = 1  # surface samples the data module loads per object (ATISS needs none)

    @classmethod
    def paper(cls, **overrides) -> "ATISSConfig":
        """4 layers, 8 heads, width 512, FF 1024, 10 logistics, ResNet-18 floor features (64), 64² floor."""
        return cls(name="paper", **overrides)

    @classmethod
    def tiny(cls, **overrides) -> "ATISSConfig":
        """2 layers, 4 heads, width 64, FF 128, 4 logistics, a small CNN on a 32² floor: minutes on a CPU."""
        base = dict(name="tiny", dim=64, layers=2, heads=4, ff_dim=128, dropout=0.0, pe_dim=16, class_dim=16,
                    hidden_dim=64, mixtures=4, floor_encoder="cnn", floor_features=32, floor_resolution=32)
        return cls(**{**base, **overrides})


def scalar_code(x: torch.Tensor, dim: int) -> torch.Tensor:
    """(...,) scalars → (..., dim) [sin(2π f_k x), cos(2π f_k x)], f_k = 10^(k/dim), k < dim/2 (ATISS's code)."""
    k = torch.arange(dim // 2, device=x.device, dtype=torch.float32)
    freqs = 2 * math.pi * torch.pow(10.0, k / dim)
    angles = x.float()[..., None] * freqs
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


def mlp(inp: int, hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inp, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out))


def floor_masks(room: torch.Tensor | None, bounds: torch.Tensor, resolution: int, batch: int,
                device) -> torch.Tensor:
    """(B, 1, R, R) float floor masks: 1 inside the room's xz rectangle (``room`` (B, 2, 3) metres, NaN = no
    room: everything is floor), in the dataset's normalised frame over ±:data:`FLOOR_WINDOW`."""
    axis = (torch.arange(resolution, device=device, dtype=torch.float32) + 0.5) / resolution * 2 - 1
    axis = axis * FLOOR_WINDOW
    gz, gx = torch.meshgrid(axis, axis, indexing="ij")  # rows z, columns x
    if room is None:
        return torch.ones(batch, 1, resolution, resolution, device=device)
    room = room.to(device=device, dtype=torch.float32)
    lo, hi = bounds[:3].to(room), bounds[3:].to(room)
    norm = 2 * (room - lo) / (hi - lo) - 1  # (B, 2, 3)
    inside = ((gx >= norm[:, 0, 0, None, None]) & (gx <= norm[:, 1, 0, None, None])
              & (gz >= norm[:, 0, 2, None, None]) & (gz <= norm[:, 1, 2, None, None]))
    missing = ~torch.isfinite(room).all(-1).all(-1)
    inside = inside | missing[:, None, None]
    return inside[:, None].float()


def build_floor_encoder(cfg: ATISSConfig) -> nn.Module:
    if cfg.floor_encoder == "resnet18":
        from torchvision.models import resnet18

        net = resnet18(weights=None, num_classes=cfg.floor_features,
                       norm_layer=lambda channels: nn.GroupNorm(min(32, channels // 4), channels))
        net.conv1 = nn.Conv2d(1, 64, kernel_size=7, stride=2, padding=3, bias=False)
        return net
    if cfg.floor_encoder == "cnn":
        r = cfg.floor_resolution // 8
        return nn.Sequential(
            nn.Conv2d(1, 16, 3, stride=2, padding=1), nn.GELU(), nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1), nn.GELU(), nn.Flatten(), nn.Linear(32 * r * r, cfg.floor_features))
    raise ValueError(f"ATISS: unknown floor_encoder '{cfg.floor_encoder}' (resnet18 or cnn)")


class ATISSNetwork(nn.Module):
    """Set transformer + autoregressive DMLL heads (module docstring). ``num_classes`` real classes; class
    index ``num_classes`` is the end symbol."""

    def __init__(self, cfg: ATISSConfig, num_classes: int):
        super().__init__()
        self.cfg, self.num_classes = cfg, num_classes
        vocab = num_classes + 1
        self.floor = build_floor_encoder(cfg)
        self.floor_in = nn.Linear(cfg.floor_features, cfg.dim)
        self.query = nn.Parameter(torch.randn(1, 1, cfg.dim) * 0.02)
        self.class_in = nn.Linear(vocab, cfg.class_dim, bias=False)
        self.object_in = nn.Linear(cfg.class_dim + 7 * cfg.pe_dim, cfg.dim)
        layer = nn.TransformerEncoderLayer(cfg.dim, cfg.heads, cfg.ff_dim, cfg.dropout, activation="gelu",
                                           batch_first=True)
        self.transformer = nn.TransformerEncoder(layer, cfg.layers, enable_nested_tensor=False)
        D, H, K3, P = cfg.dim, cfg.hidden_dim, 3 * cfg.mixtures, cfg.pe_dim
        self.class_head = mlp(D, H, vocab)
        self.class_out = nn.Linear(vocab, cfg.class_dim, bias=False)
        c = D + cfg.class_dim
        self.translation_heads = nn.ModuleList(mlp(c, H, K3) for _ in range(3))
        self.angle_head = mlp(c + 3 * P, H, K3)
        self.size_heads = nn.ModuleList(mlp(c + 4 * P, H, K3) for _ in range(3))

    def one_hot(self, category: torch.Tensor) -> torch.Tensor:
        return F.one_hot(category, self.num_classes + 1).float()

    def object_tokens(self, category, translation, size, angle) -> torch.Tensor:
        """(B, N, dim) tokens of objects: class index, centre (3, normalised), size (3, normalised), angle θ/π."""
        P = self.cfg.pe_dim
        codes = [self.class_in(self.one_hot(category)), scalar_code(translation, P).flatten(-2),
                 scalar_code(size, P).flatten(-2), scalar_code(angle, P)]
        return self.object_in(torch.cat(codes, dim=-1))

    def floor_feature(self, masks: torch.Tensor) -> torch.Tensor:
        return self.floor_in(self.floor(masks))

    def encode(self, floor: torch.Tensor, tokens: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """F (B, dim): the query token's output with the objects of ``context`` (B, N) bool as the set."""
        B = tokens.shape[0]
        x = torch.cat([floor[:, None], self.query.expand(B, -1, -1), tokens], dim=1)
        pad = torch.cat([torch.zeros(B, 2, dtype=torch.bool, device=tokens.device), ~context.bool()], dim=1)
        return self.transformer(x, src_key_padding_mask=pad)[:, 1]

    # ---- heads: each returns DMLL parameters -----------------------------------------------------------
    def class_logits(self, F_: torch.Tensor) -> torch.Tensor:
        return self.class_head(F_)

    def _cond(self, F_, category):
        return torch.cat([F_, self.class_out(self.one_hot(category))], dim=-1)

    def translation_params(self, F_, category) -> torch.Tensor:
        """(B, 3, 3K) parameters of the centre's x, y, z given the class."""
        c = self._cond(F_, category)
        return torch.stack([h(c) for h in self.translation_heads], dim=1)

    def angle_params(self, F_, category, translation) -> torch.Tensor:
        c = torch.cat([self._cond(F_, category), scalar_code(translation, self.cfg.pe_dim).flatten(-2)], dim=-1)
        return self.angle_head(c)

    def size_params(self, F_, category, translation, angle) -> torch.Tensor:
        c = torch.cat([self._cond(F_, category), scalar_code(translation, self.cfg.pe_dim).flatten(-2),
                       scalar_code(angle, self.cfg.pe_dim)], dim=-1)
        return torch.stack([h(c) for h in self.size_heads], dim=1)


def gather_object(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """values (B, N, ...) → (B, ...) at object ``index`` (B,)."""
    idx = index.view(-1, *([1] * (values.dim() - 1))).expand(-1, 1, *values.shape[2:])
    return torch.gather(values, 1, idx)[:, 0]


class ATISS(BaselineModule):
    method = "atiss"
    config_class = ATISSConfig

    def __init__(self, config="tiny", bounds=None, categories=None, size_bounds=None, lr: float = 1e-4,
                 weight_decay: float = 0.0, optimizer: str = "adam", ema_decay: float = 0.0, seed: int = 0,
                 method: str = "atiss"):
        super().__init__(config, bounds, categories, size_bounds, lr, weight_decay, optimizer, ema_decay, seed,
                         method=method)

    def make_network(self) -> nn.Module:
        return ATISSNetwork(self.config, self.num_classes)

    # ---- inputs ---------------------------------------------------------------------------------------
    def inputs(self, batch: dict) -> tuple[Objects, torch.Tensor, torch.Tensor]:
        """Objects, their normalised sizes (B, N, 3) and angles θ/π (B, N)."""
        obj = objects_of(batch)
        return obj, normalize_size(obj.size, self.hparams.size_bounds), obj.yaw / math.pi

    def floor(self, network: ATISSNetwork, batch: dict) -> torch.Tensor:
        masks = floor_masks(batch.get("room"), self.bounds, self.config.floor_resolution, batch["x"].shape[0],
                            batch["x"].device)
        return network.floor_feature(masks)

    # ---- likelihood -----------------------------------------------------------------------------------
    def next_object_nll(self, network: ATISSNetwork, floor: torch.Tensor, obj: Objects, size: torch.Tensor,
                        angle: torch.Tensor, context: torch.Tensor, target: torch.Tensor,
                        end: torch.Tensor) -> dict:
        """Per-scene negative log-likelihoods (B,) of the next object ``target`` (B,) index (or the end class
        where ``end``) given the objects of ``context`` (B, N) bool: class, centre, angle, size terms."""
        tokens = network.object_tokens(obj.category, obj.translation, size, angle)
        F_ = network.encode(floor, tokens, context)
        target = torch.where(end, torch.zeros_like(target), target)
        cls = torch.where(end, torch.full_like(target, self.num_classes), gather_object(obj.category, target))
        nll_class = F.cross_entropy(network.class_logits(F_), cls, reduction="none")
        t, a, s = gather_object(obj.translation, target), gather_object(angle, target), gather_object(size, target)
        bins = self.config.bins
        keep = (~end).float()
        nll_t = -dmll.log_prob(network.translation_params(F_, cls), t, bins).sum(-1) * keep
        nll_a = -dmll.log_prob(network.angle_params(F_, cls, t), a, bins) * keep
        nll_s = -dmll.log_prob(network.size_params(F_, cls, t, a), s, bins).sum(-1) * keep
        return {"class": nll_class, "translation": nll_t, "angle": nll_a, "size": nll_s,
                "total": nll_class + nll_t + nll_a + nll_s}

    def log_likelihood(self, batch: dict, context: torch.Tensor, target: torch.Tensor,
                       use_ema: bool = True) -> torch.Tensor:
        """log p(object ``target`` (B,) | the objects of ``context`` (B, N) bool, the floor) per scene (B,),
        with the network in eval mode."""
        network = self.sampling_network(use_ema)
        was = network.training
        network.eval()
        try:
            with torch.no_grad():
                obj, size, angle = self.inputs(batch)
                end = torch.zeros_like(target, dtype=torch.bool)
                out = self.next_object_nll(network, self.floor(network, batch), obj, size, angle,
                                           context.bool() & obj.mask, target.long(), end)
            return -out["total"]
        finally:
            network.train(was)

    def loss(self, batch: dict, network: nn.Module, generator: torch.Generator | None = None) -> dict:
        obj, size, angle = self.inputs(batch)
        B, N = obj.mask.shape
        device = obj.mask.device
        keys = torch.rand((B, N), generator=generator).to(device)
        keys = torch.where(obj.mask, keys, torch.full_like(keys, 2.0))  # padding sorts last
        rank = keys.argsort(dim=1).argsort(dim=1)
        n = obj.mask.sum(1)
        cut = (torch.rand((B,), generator=generator).to(device) * (n + 1).float()).long().clamp(max=n)
        context = obj.mask & (rank < cut[:, None])
        end = cut >= n
        target = torch.where(end, torch.zeros_like(cut), (rank == cut[:, None]).float().argmax(dim=1))
        out = self.next_object_nll(network, self.floor(network, batch), obj, size, angle, context, target, end)
        return {"loss": out["total"].mean(), **{f"nll_{k}": v.mean() for k, v in out.items() if k != "total"}}

    # ---- sampling -------------------------------------------------------------------------------------
    @torch.no_grad()
    def sample(self, batch: dict, sampler=None, generator=None, use_ema: bool = True, guidance=None, **kw):
        """Place the objects one at a time in the scene's order (module docstring); ``sampler`` is not used
        (ATISS is not a diffusion model); ``guidance`` must be None."""
        if guidance is not None:
            raise ValueError("ATISS: no guidance (it is not a diffusion model)")
        network = self.sampling_network(use_ema)
        was = network.training
        network.eval()
        try:
            batch = {k: v.to(self.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
            obj, size, _ = self.inputs(batch)
            B, N = obj.mask.shape
            u = uniform_draws(generator, (B, N, 8), self.device)
            floor = self.floor(network, batch)
            translation = torch.zeros_like(obj.translation)
            angle = torch.zeros_like(obj.yaw)
            index = torch.arange(N, device=self.device)
            bins = self.config.bins
            for k in range(N):
                context = obj.mask & (index < k)[None, :]
                tokens = network.object_tokens(obj.category, translation, size, angle)
                F_ = network.encode(floor, tokens, context)
                cls = obj.category[:, k]
                t = dmll.sample(network.translation_params(F_, cls), u[:, k, :6].reshape(B, 3, 2))
                a = dmll.sample(network.angle_params(F_, cls, t), u[:, k, 6:8])
                real = obj.mask[:, k]
                translation[:, k] = torch.where(real[:, None], t, 0.0)
                angle[:, k] = torch.where(real, a, 0.0)
            return poses(translation, angle * math.pi, obj.tilt, obj.mask, self.bounds)
        finally:
            network.train(was)
