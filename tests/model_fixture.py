"""A recorded SPREAD network: what the model computed before its GPU rewrite (issue 29), kept as numbers.

``python tests/model_fixture.py`` (run once, on the code before the rewrite: commit 35871fd) wrote ``tests/data/model_outputs.json``:
for each variant, the names and shapes of the network's parameters as they were then, and, for weights drawn from
a seed in that order, the network's ε̂ on a fixed batch at three timesteps and the states of a DDIM-10 sampling run.
``tests/test_gpu_paths.py`` draws the same weights into today's network (old checkpoints load through the layout
conversion) and compares.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

FIXTURE = Path(__file__).parent / "data" / "model_outputs.json"
BOUNDS = [-3.0, 0.0, -3.0, 3.0, 2.5, 3.0]
CONFIG = {"depth": 2, "dim": 64, "heads": 4, "dim_head": 16, "edge_dim": 32, "cond_dim": 32, "ff_mult": 2,
          "dropout": 0.1, "state_bands": 4, "index_dim": 16, "shape_tokens": 4, "shape_dim": 16, "tokenizer_width": 32,
          "tokenizer_heads": 2, "tokenizer_points": 40, "num_latents": 8, "perceiver_depth": 2,
          "perceiver_self_per_cross": 2, "perceiver_cross_heads": 1, "perceiver_cross_dim_head": 16,
          "point_bands": 4, "num_points": 40}


def batch(seed: int = 0) -> dict:
    """Three scenes of 6, 4 and 1 objects (padded to 6), 40 points each, in a 6 m room."""
    from spread.data import matrix_to_rot6d, rot6d_to_matrix

    g = torch.Generator().manual_seed(seed)
    sizes, N, M = (6, 4, 1), 6, 40
    B = len(sizes)
    mask = torch.arange(N)[None, :] < torch.tensor(sizes)[:, None]
    pair = mask[:, :, None] & mask[:, None, :]
    R = rot6d_to_matrix(torch.randn(B, N, 6, generator=g))
    x = torch.cat([torch.rand(B, N, 3, generator=g) * 1.2 - 0.6, matrix_to_rot6d(R)], -1) * mask[..., None]
    points = (torch.rand(B, N, M, 3, generator=g) - 0.5) * 0.8 * mask[..., None, None]
    normals = torch.nn.functional.normalize(torch.randn(B, N, M, 3, generator=g), dim=-1) * mask[..., None, None]
    return dict(x=x, mask=mask, spatial=torch.randint(0, 7, (B, N, N), generator=g).masked_fill(~pair, 7),
                physical=torch.randint(0, 3, (B, N, N), generator=g).masked_fill(~pair, 3),
                points=points, normals=normals, mount=torch.zeros(B, N, dtype=torch.long))


def seeded_state(names_shapes, seed: int = 1) -> dict:
    """Weights drawn in the recorded order (N(0, 0.05²); LayerNorm-like 1-d weights around 1)."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for name, shape in names_shapes:
        value = torch.randn(shape, generator=g) * 0.05
        if name.endswith("norm.weight") or ".norm_" in name and name.endswith("weight") and len(shape) == 1:
            value = value + 1.0
        state[name] = value
    return state


def network(variant: str):
    from spread.model import ModelConfig, SceneDenoiser

    return SceneDenoiser(ModelConfig(**CONFIG), variant, BOUNDS).eval()


def outputs(net, variant_record: dict | None = None) -> dict:
    """ε̂ at t = 10, 500, 990 and the DDIM-10 states (one generator per scene, seeds 0–2)."""
    from spread.model import Sampler
    from spread.model.diffusion import reverse_process

    b = batch()
    cond = net.condition(b)
    out = {}
    with torch.no_grad():
        for t in (10, 500, 990):
            out[f"eps_{t}"] = net(b["x"], torch.full((3,), t), cond).tolist()
        gens = [torch.Generator().manual_seed(s) for s in range(3)]
        out["ddim10"] = reverse_process(Sampler("ddim", 10), lambda x, t: net(x, t, cond), b["mask"],
                                        generator=gens).tolist()
    return out


def record() -> dict:
    torch.manual_seed(0)
    data = {}
    for variant in ("base", "geometry"):
        net = network(variant)
        names = [(k, list(v.shape)) for k, v in net.state_dict().items() if k != "bounds"]
        net.load_state_dict({**seeded_state(names), "bounds": net.bounds}, strict=True)
        data[variant] = {"parameters": names, **outputs(net)}
    return data


if __name__ == "__main__":
    FIXTURE.write_text(json.dumps(record()))
    print(f"wrote {FIXTURE}")
