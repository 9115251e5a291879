"""Configuration (DESIGN §5): every config composes, a default lives once, the paper's recipe is one file.

* Every group option that extends a registered schema (``defaults: [base, ...]``) only overrides: no key it
  sets restates the schema's default.
* ``experiment=paper_base`` / ``paper_geometry`` compose to the supplement's "Implementation details",
  value by value, and their ``sampling`` block samples as the paper and the release do.
* The command schemas turn a composed config into the library record (no field copied by hand), and a
  typo in a key is refused with its name.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from spread.configs import compose, conf_dir, to_object

CONF = Path(conf_dir())

#: The supplement's training recipe (spread_paper.tex, "Implementation details"), as composed config keys.
SUPPLEMENT_TRAINING = {
    "trainer.max_epochs": 2000,                # "trained for 2,000 epochs
    "data.batch_size": 16,                     #  with a batch size of 16"
    "model.lr": 1e-4,                          # "AdamW ... learning rate of 1 × 10^-4
    "model.weight_decay": 1e-4,                #  and a weight decay of 1 × 10^-4"
    "model.beta_schedule": "squaredcos_cap_v2",  # "squaredcos_cap_v2 noise schedule,
    "model.diffusion_steps": 1000,             #  ... a total of 1,000 denoising timesteps"
    "model.config.num_points": 2000,           # "we empirically set M to be 2,000"
    "data.num_points": 2000,                   # the data module loads what the model was built for
}
#: The network of the release (reference notes §2.1): width 512, 6 blocks of 8 heads, 128-d edges.
RELEASE_NETWORK = {"dim": 512, "depth": 6, "heads": 8, "edge_dim": 128, "dim_head": 64, "shape_dim": 64}
#: The guidance weights of the supplement and the release's 100 refinement iterations.
SUPPLEMENT_GUIDANCE = {"mode": "refine", "iterations": 100, "collision": 7.5e-3, "relation": 1e-3, "gravity": 1e-3}

COMMANDS = {"generate": ["out_dir=/o"], "import": ["source=spread_release", "src=/s", "out_dir=/o"], "export": ["scenes=/s", "out_dir=/o"], "train": ["data.root=/d"], "sample": ["ckpt=c", "data.root=/d", "out_dir=/o"],
            "evaluate": ["scenes=/s", "reference=/d", "out_dir=/o"], "ablate": [], "compare": [], "report": ["runs=/r"]}


def group_options():
    for path in sorted(CONF.glob("*/*.yaml")):
        data = yaml.safe_load(path.read_text()) or {}
        if "base" in (data.get("defaults") or []):
            yield path


@pytest.mark.parametrize("path", list(group_options()), ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_group_options_only_override_their_schema(path):
    from hydra.core.config_store import ConfigStore

    from spread.configs import register

    register()
    group = path.parent.name
    own = {k: v for k, v in yaml.safe_load(path.read_text()).items() if k != "defaults"}
    schema = ConfigStore.instance().load(f"{group}/base.yaml").node
    for key, value in own.items():
        assert key in schema, f"{path.name}: '{key}' is not a key of the {group} schema"
        if isinstance(value, dict) or (isinstance(value, str) and value.startswith("${")):
            continue
        assert schema[key] != value, f"{path.name}: '{key}: {value}' restates the schema's default"


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_composes(name):
    cfg = compose(name, COMMANDS[name])
    assert cfg is not None
    if name in ("generate", "sample", "evaluate"):
        record = to_object(cfg)
        assert type(record).__name__.lower().startswith(name)


def test_command_schemas_give_the_library_records():
    from spread.evaluation import EvalProtocol, EvaluationConfig, FIDConfig
    from spread.guidance import GuidanceConfig
    from spread.procgen.dataset import DatasetConfig
    from spread.sampling import SamplingConfig

    sample = to_object(compose("sample", [*COMMANDS["sample"], "guidance=refine", "guidance.collision=0.015"]))
    assert isinstance(sample, SamplingConfig) and isinstance(sample.guidance, GuidanceConfig)
    assert sample.guidance.mode == "refine" and sample.guidance.collision == 0.015 and sample.guidance.gravity == 1e-3
    evaluate = to_object(compose("evaluate", [*COMMANDS["evaluate"], "seed=4", "fid=clip", "fid.enabled=false"]))
    assert isinstance(evaluate, EvaluationConfig) and isinstance(evaluate.protocol, EvalProtocol)
    assert evaluate.protocol.seed == 4 and isinstance(evaluate.fid, FIDConfig)
    assert evaluate.fid.feature_model == "clip_vit_b_32" and evaluate.fid.enabled is False
    generate = to_object(compose("generate", ["out_dir=/o", "room.max_objects=9", "assets.copy_from=/lib"]))
    assert isinstance(generate, DatasetConfig) and generate.room.max_objects == 9 and generate.assets.copy_from == "/lib"


def test_a_misspelt_key_is_refused_with_its_name():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="colision"):
        compose("sample", [*COMMANDS["sample"], "guidance.colision=1"])
    with pytest.raises(Exception, match="stability_runs"):
        to_object(compose("evaluate", [*COMMANDS["evaluate"], "protocol.stability_runs=many"]))


@pytest.mark.parametrize("experiment", ["paper_base", "paper_geometry"])
def test_paper_experiments_compose_to_the_supplements_recipe(experiment):
    cfg = compose("train", [f"experiment={experiment}", "data.root=/d"])
    for key, expected in SUPPLEMENT_TRAINING.items():
        assert OmegaConf.select(cfg, key) == expected, key
    assert {k: cfg.model.config[k] for k in RELEASE_NETWORK} == RELEASE_NETWORK
    assert cfg.model.variant == ("geometry" if experiment == "paper_geometry" else "base")
    assert cfg.experiment_name == experiment


def test_paper_sampling_is_ddpm_1000_and_refine_guidance_with_the_supplements_weights():
    sampling = compose("train", ["experiment=paper_geometry", "data.root=/d"]).sampling
    cfg = to_object(compose("sample", [*COMMANDS["sample"], *sampling.sampler, *sampling.guidance]))
    assert (cfg.sampler.kind, cfg.sampler.num_steps) == ("ddpm", 1000)
    assert {k: getattr(cfg.guidance, k) for k in SUPPLEMENT_GUIDANCE} == SUPPLEMENT_GUIDANCE
    base = compose("train", ["experiment=paper_base", "data.root=/d"]).sampling
    assert to_object(compose("sample", [*COMMANDS["sample"], *base.guidance])).guidance.active is False


def test_the_paper_preset_only_names_the_experiments():
    from spread.commands.ablate import ablation_spec

    spec = ablation_spec(compose("ablate", ["+preset=paper"]))
    assert spec.train_variant == {"base": ["experiment=paper_base"], "geometry": ["experiment=paper_geometry"]}
    assert "sampler=ddpm" in spec.sample and "guidance=refine" in spec.guidance
    preset = (CONF / "preset" / "paper.yaml").read_text()
    for number in ("2000", "1.0e-4", "7.5e-3", "squaredcos"):
        assert number not in preset, f"preset/paper.yaml restates {number}: it belongs to the experiment files"


def test_every_command_shares_the_run_folder_policy():
    for name in COMMANDS:
        defaults = yaml.safe_load((CONF / f"{name}.yaml").read_text())["defaults"]
        assert {"hydra": "default"} in defaults and {"paths": "default"} in defaults, name


def test_runs_started_by_a_wandb_agent_log_online_and_wandb_mode_wins(monkeypatch):
    """``wandb agent`` sets WANDB_SWEEP_ID for the runs it starts: they log online so the sweep's controller sees
    their metrics; WANDB_MODE, when set, decides; otherwise runs stay offline."""
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.delenv("WANDB_SWEEP_ID", raising=False)
    assert compose("sample", ["ckpt=x"]).logger.mode == "offline"
    monkeypatch.setenv("WANDB_SWEEP_ID", "abc123")
    assert compose("sample", ["ckpt=x"]).logger.mode == "online"
    assert compose("train", ["logger=mlflow"]).logger.mode == "online"
    monkeypatch.setenv("WANDB_MODE", "disabled")
    assert compose("sample", ["ckpt=x"]).logger.mode == "disabled"


def test_the_parallel_and_slurm_hydra_launchers_are_installed_and_compose():
    """``hydra/launcher=parallel`` (joblib) and ``=slurm`` (submitit) resolve: `make` installs the launchers extra."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from spread.configs import conf_dir, register

    register("sample")
    with initialize_config_dir(config_dir=str(conf_dir()), version_base="1.3"):
        for launcher, target in (("parallel", "JoblibLauncher"), ("slurm", "SlurmLauncher")):
            cfg = hydra_compose("sample", ["hydra/launcher=" + launcher, "ckpt=c", "data.root=d"],
                                return_hydra_config=True)
            assert cfg.hydra.launcher._target_.endswith(target)


def test_a_composed_config_is_kept_and_each_caller_gets_its_own_copy(tmp_path, monkeypatch):
    """compose() keeps what it composed (planning a study composes each stage's config several times): the same
    arguments give an equal config, a change to one copy is not seen by the next caller, and a config file
    edited in this process (or another config folder) composes anew."""
    import shutil

    import spread.configs as configs

    args = ["ckpt=c", "data.root=/d", "out_dir=/o"]
    first = compose("sample", args)
    first.seed = 123  # the caller's copy
    again = compose("sample", args)
    assert again.seed == 0 and again is not first and OmegaConf.is_struct(again)
    assert OmegaConf.get_type(again) is OmegaConf.get_type(first)
    with pytest.raises(Exception, match="colision"):  # a misspelt key is still refused, every time
        compose("sample", [*args, "guidance.colision=1"])
    copied = tmp_path / "conf"
    shutil.copytree(CONF, copied)
    monkeypatch.setenv("SPREAD_CONF_DIR", str(copied))
    assert compose("sample", args).max_objects is None
    text = (copied / "sample.yaml").read_text()
    assert "\nmax_objects: null " in text, "the test edits sample.yaml's max_objects line"
    (copied / "sample.yaml").write_text(text.replace("\nmax_objects: null ", "\nmax_objects: 7 "))
    assert compose("sample", args).max_objects == 7  # the edited file, not the kept config
    assert len([k for k in configs._COMPOSED if k[0] == "sample" and k[1] == tuple(args)]) == 3
