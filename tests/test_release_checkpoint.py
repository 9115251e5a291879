"""The release-compatible network (spread.methods.release_network) against the release's own code.

tests/data/release_network_fixture.npz was written by running the SPREAD release's network code
(``Sg2ScTransformerDiffusionWrapper`` and its perceiver, from github.com/L-avenir/SPREAD, outside this
repository) on CPU at reduced sizes (width 32, 2 blocks of 4 heads, an 8-latent perceiver of depth 1,
8 Fourier bands; the rest as the release: 140-d box input with the 128-d index code, 256 × 64 shape latents,
edge width = width / 4): its random weights in the release's key layout and order, its inputs
(one scene of 4 entries, the last padded), and its outputs ε̂ at t = 0, 437, 999. Data only.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from spread.methods.release_network import (
    ReleaseCheckpointError, ReleaseNetwork, ReleaseNetworkConfig, load_release_checkpoint,
)

FIXTURE = Path(__file__).parent / "data" / "release_network_fixture.npz"


@pytest.fixture(scope="module")
def fixture():
    return network_fixture()


def network_fixture():
    """(config, weights, key order, all arrays) of the network fixture."""
    with np.load(FIXTURE, allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    cfg = json.loads(str(data["config"]))
    w, p = cfg["wrapper"], cfg["perceiver"]
    config = ReleaseNetworkConfig(
        attn_dim=w["attn_dim"], t_dim=w["t_dim"], n_heads=w["n_heads"], n_layers=w["n_layers"],
        context_dim=w["context_dim"], num_freq_bands=p["num_freq_bands"], perceiver_depth=p["depth"],
        num_latents=p["num_latents"], cross_heads=p["cross_heads"], cross_dim_head=p["cross_dim_head"],
        latent_heads=p["latent_heads"], latent_dim_head=p["latent_dim_head"], num_classes=p["num_classes"],
        self_per_cross=p["self_per_cross_attn"])
    weights = {k: torch.from_numpy(data[f"w/{k}"]) for k in cfg["key_order"]}
    return config, weights, cfg["key_order"], data


def outputs(net, data) -> dict[int, np.ndarray]:
    x = {k: torch.from_numpy(data[f"in/{k}"]) for k in ("box", "pc_feat", "miche_feat", "edges", "regions", "mask",
                                                       "condition")}
    with torch.no_grad():
        return {int(t): net(x["box"], x["pc_feat"], x["miche_feat"], x["edges"], x["regions"], torch.tensor([int(t)]),
                            condition=x["condition"], mask=x["mask"]).numpy() for t in data["in/timesteps"]}


def test_the_network_has_the_releases_keys_in_the_releases_order(fixture):
    config, _, keys, _ = fixture
    assert list(ReleaseNetwork(config).state_dict()) == keys


def test_the_network_reproduces_the_releases_outputs(fixture):
    config, weights, _, data = fixture
    net = ReleaseNetwork(config).eval()
    net.load_state_dict(weights, strict=True)
    for t, eps in outputs(net, data).items():
        assert np.abs(eps - data[f"out/eps_t{t}"]).max() <= 1e-4, f"t = {t}"
        assert (eps[0, -1] == 0).all()  # the padded entry


def release_ckpt(path: Path, weights: dict, keys: list, noise: float = 1.0) -> Path:
    """A ckpt.pth in the release's format: the diffusion module's weights (random here) under
    ``_orig_mod.network.`` (a torch.compile'd module), AdamW state, and diffusers-EMA states whose shadow
    parameters are the fixture weights."""
    g = torch.Generator().manual_seed(5)
    model = {f"_orig_mod.network.{k}": weights[k] + noise * torch.randn(weights[k].shape, generator=g) for k in keys}
    optimizer = {"state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.zeros(2)}},
                 "param_groups": [{"lr": 1e-4, "weight_decay": 1e-4, "params": list(range(len(keys)))}]}
    ema = {"decay": 0.9999, "min_decay": 0.0, "optimization_step": 3, "update_after_step": 0, "use_ema_warmup": True,
           "inv_gamma": 1.0, "power": 0.75, "shadow_params": [weights[k].clone() for k in keys]}
    torch.save({"model": model, "optimizer": optimizer, "ema_states": ema}, path)
    return path


def test_a_release_ckpt_loads_its_ema_weights_by_default_with_no_missing_or_unexpected_keys(fixture, tmp_path):
    config, weights, keys, data = fixture
    path = release_ckpt(tmp_path / "ckpt.pth", weights, keys)
    net = load_release_checkpoint(path, config)  # strict: raises on any missing or unexpected key
    assert not net.training
    for t, eps in outputs(net, data).items():
        assert np.abs(eps - data[f"out/eps_t{t}"]).max() <= 1e-4
    raw = load_release_checkpoint(path, config, use_ema=False)
    assert np.abs(outputs(raw, data)[437] - data["out/eps_t437"]).max() > 1e-2  # the raw (here: noisy) weights


def test_a_ckpt_that_does_not_fit_is_refused_naming_the_keys(fixture, tmp_path):
    config, weights, keys, _ = fixture
    partial = {k: v for k, v in weights.items() if k != "proj_out.1.bias"}
    path = release_ckpt(tmp_path / "ckpt.pth", partial, [k for k in keys if k != "proj_out.1.bias"])
    with pytest.raises(ReleaseCheckpointError, match=r"missing \['proj_out.1.bias'\]"):
        load_release_checkpoint(path, config)
    torch.save({"state_dict": {}}, tmp_path / "lightning.pth")
    with pytest.raises(ReleaseCheckpointError, match="expected a dict with key 'model'"):
        load_release_checkpoint(tmp_path / "lightning.pth", config)


def test_the_default_config_is_the_releases_network():
    net = ReleaseNetwork()
    sd = net.state_dict()
    assert sd["box_proj.weight"].shape == (512, 140) and sd["miche_proj.weight"].shape == (512, 64)
    assert sd["pc_preceiver.latents"].shape == (256, 512)
    assert sd["pc_preceiver.layers.0.0.fn.to_kv.weight"].shape == (128, 4 + 128 + 129)  # 1 head × 64, k and v
    assert sd["edge_proj_in.weight"].shape == (128, 256) and sd["region_embed.0.weight"].shape == (8, 128)
    assert sd["transformer_blocks.0.graph_layer.cross_attn.to_k.weight"].shape == (512, 768)
    assert len(net.transformer_blocks) == 6 and "transformer_blocks.6.norm1.weight" not in sd
    assert sd["proj_out.1.weight"].shape == (12, 512)


def test_the_command_refuses_a_ckpt_of_another_size_naming_the_keys(fixture, tmp_path):
    from helpers import run_script

    _, weights, keys, _ = fixture
    path = release_ckpt(tmp_path / "ckpt.pth", weights, keys)  # width 32: not the release's 512
    proc = run_script("spread-release-ckpt", f"ckpt={path}", ok=False)
    assert proc.returncode != 0 and "other shapes than the release network" in proc.stderr
    assert "miche_proj.weight (32, 64) (network: (512, 64))" in proc.stderr
    proc = run_script("spread-release-ckpt", "ckpt=/nonexistent/ckpt.pth", ok=False)
    assert proc.returncode != 0 and "no such checkpoint file" in proc.stderr


@pytest.mark.slow
def test_the_command_loads_a_full_size_release_ckpt(tmp_path):
    """A ckpt.pth of the release's full size (98 M parameters, ~400 MB): loads with no missing or unexpected keys."""
    from helpers import run_script

    net = ReleaseNetwork()
    sd = {f"_orig_mod.network.{k}": v for k, v in net.state_dict().items()}
    torch.save({"model": sd, "optimizer": {}, "ema_states": {"shadow_params": list(sd.values())}}, tmp_path / "ckpt.pth")
    proc = run_script("spread-release-ckpt", f"ckpt={tmp_path / 'ckpt.pth'}")
    assert "no missing or unexpected keys" in proc.stdout and "98,285,724 parameters" in proc.stdout
