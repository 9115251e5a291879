"""experiment=cpu_hour (issue 15's CPU recipe): it composes to the levers its file names, builds the module they
describe, its `sampling` block composes with spread-sample to DDIM-50 + refine with its weights, and the
commands that use it (make demo, spread-ablate +preset=quick) take it."""

import pytest

from spread.configs import compose, to_object

SAMPLE = ["ckpt=/c.ckpt", "data.root=/d", "out_dir=/o"]


def recipe(*overrides):
    return compose("train", ["experiment=cpu_hour", "data.root=/d", *overrides])


def test_cpu_hour_trains_the_tiny_base_model_with_its_levers_within_an_hour():
    cfg = recipe()
    assert cfg.experiment_name == "cpu_hour" and cfg.model.variant == "base" and cfg.model.config.name == "tiny"
    assert (cfg.model.prediction, cfg.model.loss_weighting, cfg.model.lr_schedule) == ("v_prediction", "min_snr",
                                                                                        "cosine")
    assert cfg.model.lr_warmup_steps < cfg.trainer.max_steps
    assert cfg.data.augment is True and cfg.data.batch_size == 16
    days, hours, minutes, seconds = map(int, cfg.trainer.max_time.split(":"))
    assert days * 86400 + hours * 3600 + minutes * 60 + seconds <= 3600
    assert cfg.checkpoint.save_top_k == -1  # every periodic checkpoint kept for the learning curve
    assert cfg.model.sample_every_n_epochs > 0  # validation sampling stays on (val/grecall)
    assert 0 < cfg.model.graph_dropout < 1  # trains the graph-free branch of classifier-free guidance


def test_cpu_hour_builds_a_module_with_its_prediction_schedule_and_pose_terms():
    import hydra

    model = hydra.utils.instantiate(recipe().model, bounds=[-3, 0, -3, 3, 3, 3])
    assert model.hparams.prediction == "v_prediction" and model.hparams.lr_schedule == "cosine"
    assert model.variant == "base" and model.config.dim == 128
    # the penetration-aware and relation-aware terms on the decoded poses; the support term off
    assert model.term_weights() == pytest.approx({"penetration": 0.3, "spatial": 0.1})


def test_cpu_hour_samples_with_ddim50_graph_guidance_and_refine_at_four_times_the_papers_collision_settle_and_home():
    sampling = recipe().sampling
    cfg = to_object(compose("sample", [*SAMPLE, *sampling.sampler, *sampling.guidance]))
    assert (cfg.sampler.kind, cfg.sampler.num_steps) == ("ddim", 50)
    assert cfg.graph_scale == 1.5  # classifier-free guidance on the graphs, the scale chosen on val
    assert cfg.guidance.mode == "refine" and cfg.guidance.active
    assert cfg.guidance.weights(nonzero=True) == pytest.approx({"collision": 3e-2, "relation": 1e-3,
                                                               "settle": 0.3, "home": 0.01})  # settle for G_H
    assert cfg.guidance.settle_reach == 0.15
    assert cfg.guidance.denoise_every == 0  # guidance steps only, no network projection between them


def test_quick_preset_trains_both_variants_by_the_recipe_with_a_shorter_schedule():
    from spread.commands.ablate import ablation_spec

    spec = ablation_spec(compose("ablate", ["+preset=quick"]))
    for variant in ("base", "geometry"):
        cfg = compose("train", [*spec.train_variant[variant], "experiment=cpu_hour", "data.root=/d"])
        assert cfg.model.variant == variant
    quick = compose("ablate", ["+preset=quick"])
    assert "experiment=cpu_hour" in quick.train.overrides and "trainer.max_steps=1200" in quick.train.overrides
    sample = to_object(compose("sample", [*SAMPLE, *spec.sample]))
    assert sample.graph_scale == 2.0  # the recipe trains with graph dropout, so its rows sample as the recipe does
    # +Geometry's rows (geometry, guidance) with guidance on its geometry features, base's rows without
    assert sample.geometry_scale == 1.0 and "base" not in spec.sample_variant
    geometry = to_object(compose("sample", [*SAMPLE, *spec.sample, *spec.sample_variant["geometry"]]))
    assert geometry.geometry_scale == 2.0 and geometry.graph_scale == 2.0


def test_quick_preset_scores_both_rows_on_hundreds_of_graphs_with_the_self_conditioned_geometry_row():
    """The quick ablation's +Geometry row is the design that read lower than base on the 1,320-graph runs (`parts`
    features + summary at x̂_0), trained on the same 240 rooms as base and scored on 480 test graphs; base at
    +Geometry's wall time is one of its rows; the paper preset's row keeps the release's feature at x_t."""
    from collections import Counter

    from spread.commands.ablate import ablation_spec
    from spread.procgen.dataset import split_of

    spec = ablation_spec(compose("ablate", ["+preset=quick"]))
    assert {"base", "base_time", "geometry", "guidance"} <= set(spec.variants)
    geometry = compose("train", [*spec.train, *spec.train_variant["geometry"], "data.root=/d"]).model.config
    assert (geometry.geometry_at, geometry.geometry_distance, geometry.geometry_summary) == ("x0_hat", "parts", True)
    generate = to_object(compose("generate", [*spec.generate, "out_dir=/o"]))
    splits = Counter(split_of(i, generate) for i in range(generate.rooms))
    assert splits["train"] == 240 and splits["test"] >= 400 and splits["val"] > 0
    paper = ablation_spec(compose("ablate", ["+preset=paper"]))
    assert compose("train", [*paper.train, *paper.train_variant["geometry"], "data.root=/d"]).model.config.geometry_at \
        == "x_t"
