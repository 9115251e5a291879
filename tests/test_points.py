"""No stale result: a sweep point is re-used only when its full fingerprint matches (spread.experiments.points,
spread.runtime.fingerprint), its folder carries the short fingerprint, and the reason of a redo is recorded.
Fake checkpoint and data files (bytes only): the fingerprint reads files, never loads them."""

from __future__ import annotations

import json
import re

import pytest

from spread.experiments.points import POINT, check_point, finish_point, start_point
from spread.runtime.fingerprint import changed_keys, point_fingerprint, run_tags, short

from helpers import compose


@pytest.fixture
def point(tmp_path):
    ckpt = tmp_path / "m.ckpt"
    ckpt.write_bytes(b"weights-1")
    data = tmp_path / "data"
    (data / "test").mkdir(parents=True)
    (data / "test" / "a.npz").write_bytes(b"scene-a")
    (data / "stats.json").write_text("{}")
    out = tmp_path / "out"
    base = [f"ckpt={ckpt}", f"data.root={data}", f"out_dir={out}", "evaluate=true", "guidance=refine"]
    return {"ckpt": ckpt, "data": data, "out": out, "cfg": lambda *more: compose("sample", *base, *more)}


def finish(out, decision):
    start_point(out, decision)
    (out / "metrics.json").write_text(json.dumps({"col_mesh": 0.1}))
    finish_point(out, 1.5)


def test_a_point_is_reused_only_when_every_input_matches(point):
    out, cfg = point["out"], point["cfg"]
    out.mkdir()
    first = check_point(cfg(), out)
    assert (first.reuse, first.fresh, first.reason) == (False, False, None)
    finish(out, first)
    assert check_point(cfg(), out).reuse
    record = json.loads((out / POINT).read_text())
    assert record["status"] == "finished" and record["short"] == short(first.fingerprint)
    assert set(record["tags"]) >= {"job_id", "world_size", "node_list", "git_sha"}
    # every input a number depends on is part of the fingerprint
    for override, key in [("guidance.iterations=7", "guidance.iterations"), ("seed=3", "sampling.seed"),
                          ("sampler.steps=9", "sampling.sampler.steps"), ("guidance.collision=0.5", "guidance.collision"),
                          ("evaluation.protocol.stability_runs=1", "evaluation.protocol.stability_runs"),
                          ("evaluation.fid.enabled=false", "evaluation.fid.enabled"), ("use_ema=false", "sampling.use_ema")]:
        decision = check_point(cfg(override), out)
        assert not decision.reuse and decision.fresh and key in decision.reason, (override, decision.reason)
    # the same settings, other files: another checkpoint's bytes, another scene in the split
    point["ckpt"].write_bytes(b"weights-2")
    assert "ckpt_sha256" in check_point(cfg(), out).reason
    point["ckpt"].write_bytes(b"weights-1")
    assert check_point(cfg(), out).reuse
    (point["data"] / "test" / "a.npz").write_bytes(b"scene-a, changed")
    assert check_point(cfg(), out).reason == "changed: data, evaluation.reference"  # the split is the reference too


def test_a_redo_clears_the_stale_result_and_records_why(point):
    out, cfg = point["out"], point["cfg"]
    out.mkdir()
    finish(out, check_point(cfg(), out))
    decision = check_point(cfg("guidance.iterations=7"), out)
    start_point(out, decision)
    assert not (out / "metrics.json").exists()  # killed now: the next launch cannot take the old numbers
    record = json.loads((out / POINT).read_text())
    assert record["status"] == "running" and record["redone_because"] == "changed: guidance.iterations"
    assert not check_point(cfg("guidance.iterations=7"), out).reuse  # same settings, not finished: resumed
    assert check_point(cfg("guidance.iterations=7"), out).fresh is False


def test_a_run_killed_between_its_metrics_and_its_record_is_reused_and_its_record_completed(point):
    out, cfg = point["out"], point["cfg"]
    out.mkdir()
    start_point(out, check_point(cfg(), out))
    (out / "metrics.json").write_text(json.dumps({"col_mesh": 0.1}))  # killed before finish_point
    assert json.loads((out / POINT).read_text())["status"] == "running"
    decision = check_point(cfg(), out)
    assert decision.reuse and not decision.fresh
    assert json.loads((out / POINT).read_text())["status"] == "finished"
    assert not check_point(cfg("guidance.iterations=7"), out).reuse  # another fingerprint is still redone


def test_results_made_before_fingerprints_are_redone(point):
    out, cfg = point["out"], point["cfg"]
    out.mkdir()
    (out / "metrics.json").write_text(json.dumps({"col_mesh": 0.1}))
    decision = check_point(cfg(), out)
    assert not decision.reuse and decision.fresh and "no fingerprint" in decision.reason
    assert check_point(cfg(), out, resume=False).fresh


def test_unguided_physcene_and_a_stronger_box_iou_have_three_fingerprints(point):
    """The bug of issue 30: "guided" was decided from collision, gravity and relation only, so an unguided run,
    guidance=physcene (box_iou 0.15, SPREAD's terms off) and box_iou 0.5 hashed the same."""
    cfg = point["cfg"]
    unguided, physcene = point_fingerprint(cfg("guidance=none")), point_fingerprint(cfg("guidance=physcene"))
    stronger = point_fingerprint(cfg("guidance=physcene", "guidance.terms.box_iou=0.5"))
    assert len({short(f) for f in (unguided, physcene, stronger)}) == 3
    assert unguided["guidance"] is None and physcene["guidance"]["box_iou"] == 0.15
    assert changed_keys(physcene, stronger) == ["guidance.box_iou"]


def test_every_registered_terms_weight_is_part_of_the_fingerprint(point):
    """Any one registered term's weight changed (built-in, PhyScene's; `terms.<name>` and the built-ins' own keys
    alike) is a changed fingerprint naming that term, so the work is redone."""
    from spread.guidance.terms import term_names

    cfg = point["cfg"]
    base = point_fingerprint(cfg("guidance=paper"))
    for name in term_names():
        changed = point_fingerprint(cfg("guidance=paper", f"+guidance.terms.{name}=0.25"))
        assert changed_keys(base, changed) == [f"guidance.{name}"], name
    alias = point_fingerprint(cfg("guidance=paper", "guidance.collision=0.25"))
    assert alias == point_fingerprint(cfg("guidance=paper", "+guidance.terms.collision=0.25"))  # one setting


def test_unguided_fingerprint_ignores_weights_and_guided_one_keeps_them(point):
    cfg = point["cfg"]
    assert point_fingerprint(cfg("guidance=none", "guidance.collision=0.3")) == point_fingerprint(cfg("guidance=none"))
    assert changed_keys(point_fingerprint(cfg()), point_fingerprint(cfg("guidance.gravity=0.3"))) == ["guidance.gravity"]


def test_sweep_point_folders_carry_the_short_fingerprint(point):
    from test_ablate_report import compose_hydra

    base = ["+sweep=guidance_grid", f"ckpt={point['ckpt']}", f"data.root={point['data']}"]
    a = compose_hydra("sample", *base)
    again = compose_hydra("sample", *base)
    other = compose_hydra("sample", *base, "guidance.iterations=3")
    assert a.out_dir == again.out_dir and a.out_dir != other.out_dir
    fp = short(point_fingerprint(compose("sample", *base, f"out_dir={a.out_dir}")))
    assert a.out_dir.endswith(f"_{fp}") and re.search(r"/c0.0075_g0.001_r0.001_[0-9a-f]{8}$", a.out_dir)
    # each launch keeps its own Hydra records (multirun.yaml, logs)
    assert "/.launches/" in str(a.hydra.sweep.dir)


def test_run_tags_name_the_slurm_job(monkeypatch):
    monkeypatch.setenv("SLURM_JOB_ID", "4242")
    monkeypatch.setenv("SLURM_NTASKS", "8")
    monkeypatch.setenv("SLURM_JOB_NODELIST", "node[01-02]")
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    monkeypatch.delenv("SLURM_ARRAY_TASK_ID", raising=False)
    tags = run_tags()
    assert (tags["job_id"], tags["world_size"], tags["node_list"]) == ("4242", 8, "node[01-02]")
    assert tags["git_sha"] is None or re.fullmatch(r"[0-9a-f]{40}", tags["git_sha"])


def test_a_point_spelled_by_another_sweep_is_found_by_its_fingerprint_not_its_name(point):
    """``points/iterations1_<short>`` made by a sweep over the iterations is the point a later sweep names
    ``floor_<short>`` when it keeps the iterations to one value: found by the fingerprint its point.json records;
    a folder with the same short name but another recorded fingerprint is not taken."""
    from spread.experiments.points import point_folder

    points = point["out"].parent / "points"
    fingerprint = point_fingerprint(point["cfg"]())
    tag = short(fingerprint)
    wanted = points / f"floor_{tag}"
    assert point_folder(wanted, fingerprint) == wanted  # no points folder yet
    impostor = points / f"a_{tag}"
    impostor.mkdir(parents=True)
    start_point(impostor, check_point(point["cfg"]("seed=5"), impostor))
    assert point_folder(wanted, fingerprint) == wanted  # same short name, another fingerprint
    made = points / f"iterations1_{tag}"
    made.mkdir()
    finish(made, check_point(point["cfg"](), made))
    assert point_folder(wanted, fingerprint) == made
    assert point_folder(impostor, fingerprint) == impostor  # a folder that exists is its own point


def test_one_setting_spelled_two_ways_is_one_identity_and_an_earlier_records_spelling_is_read_as_meant(point,
                                                                                                      monkeypatch):
    """The device is the kind the samplers run on (``auto`` resolved as they resolve it, ``cuda:N`` as ``cuda``); a
    disabled FID's other settings change nothing; a point recorded by an earlier version (``device: auto``, a
    disabled FID with its backbone, metrics in another order) is the same point, and another device is a change."""
    from spread.evaluation.protocol import FIDConfig
    from spread.runtime.fingerprint import done_check, upgraded
    from spread.sampling import SamplingConfig

    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # a machine without a GPU, whatever this one has
    cfg = point["cfg"]
    assert point_fingerprint(cfg("device=auto")) == point_fingerprint(cfg("device=cpu"))
    assert point_fingerprint(cfg("device=cpu"))["sampling"]["device"] == "cpu"
    typed = dict(ckpt="m.ckpt", out_dir="o")
    assert SamplingConfig(**typed, device="cuda:1").sampling_device() == "cuda"
    on_ray = SamplingConfig(**typed, device="auto", workers=2)
    assert on_ray.sampling_device() == "cpu"  # Ray hides every GPU from a worker that asks for none
    on_ray.ray.num_gpus_per_worker = 1
    assert on_ray.sampling_device() == "cuda"
    assert FIDConfig(enabled=False, feature_model="clip_vit_b_32").fingerprint() == FIDConfig(enabled=False).fingerprint()
    assert FIDConfig(feature_model="clip_vit_b_32").fingerprint() != FIDConfig().fingerprint()
    off = ["evaluation.fid.enabled=false"]
    assert point_fingerprint(cfg(*off, "evaluation.fid.feature_model=clip_vit_b_32")) == point_fingerprint(cfg(*off))

    now = point_fingerprint(cfg(*off))
    earlier = json.loads(json.dumps(now))
    earlier["sampling"]["device"] = "auto"
    earlier["evaluation"]["fid"] = {"enabled": False, "feature_model": "inception_v3", "weights_path": None,
                                    "extractor": None}
    assert upgraded(earlier) == {**now, "sampling": {**now["sampling"], "device": "auto"}}  # as written: a report
    assert done_check(earlier, now, present=True, finished=True).reuse
    earlier["sampling"]["device"] = "cuda:0"
    assert done_check(earlier, now, present=True).reason == "changed: sampling.device"
    earlier["sampling"]["device"] = "auto"
    # on a GPU machine an old auto run sampled on CUDA in the process, or on Ray's workers on the CPU (they see no
    # GPU): the record does not say which, so it matches what this run records (it was redone, its scenes deleted)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert done_check(earlier, now, present=True, finished=True).reuse
    assert done_check(earlier, {**now, "sampling": {**now["sampling"], "device": "cuda"}}, present=True,
                      finished=True).reuse
    # an evaluation recorded its metrics in the order given: the same set
    earlier["evaluation"]["protocol"]["metrics"] = list(reversed(now["evaluation"]["protocol"]["metrics"]))
    assert len(now["evaluation"]["protocol"]["metrics"]) > 1 and done_check(earlier, now, present=True,
                                                                            finished=True).reuse
    earlier["evaluation"]["fid"]["enabled"] = True
    assert done_check(earlier, now, present=True).fresh  # an enabled FID is compared field by field


def test_a_point_keeps_its_folder_when_its_dataset_moves_and_one_named_by_the_earlier_short_name_is_found(point):
    """Where the data lies is not part of a point's short name; a folder named by an earlier version (whose short
    name held ``data_root``) is found by its values and the fingerprint its point.json records."""
    import shutil

    from spread.experiments.points import point_folder
    from spread.runtime.fingerprint import digest

    (point["data"] / "assets").mkdir()
    (point["data"] / "assets" / "index.json").write_text("{}")
    fingerprint = point_fingerprint(point["cfg"]())
    moved = point["data"].parent / "moved"
    shutil.copytree(point["data"], moved)
    elsewhere = point_fingerprint(point["cfg"](f"data.root={moved}"))
    assert elsewhere["data_root"] != fingerprint["data_root"] and short(elsewhere) == short(fingerprint)
    points = point["out"].parent / "points"
    earlier = points / f"c0.1_{digest(fingerprint)[:8]}"  # the earlier short name: data_root included
    assert earlier.name != f"c0.1_{short(fingerprint)}"
    earlier.mkdir(parents=True)
    finish(earlier, check_point(point["cfg"](), earlier))
    assert point_folder(points / f"c0.1_{short(elsewhere)}", elsewhere) == earlier
    assert check_point(point["cfg"](f"data.root={moved}"), earlier).reuse
    other = point_fingerprint(point["cfg"]("seed=4"))  # the same values, another setting: not that folder
    assert point_folder(points / f"c0.1_{short(other)}", other) == points / f"c0.1_{short(other)}"


def test_a_hydra_sweeps_point_folder_named_by_an_earlier_short_name_is_found_by_its_record(point):
    """``spread-sample -m +sweep=guidance_grid``: ``${point_dir:...}`` names a point's folder as ``spread-sweep`` does."""
    from pathlib import Path

    from test_ablate_report import compose_hydra

    sweep = point["out"].parent / "grid"
    base = ["+sweep=guidance_grid", f"ckpt={point['ckpt']}", f"data.root={point['data']}", f"sweep_dir={sweep}"]
    fresh = Path(compose_hydra("sample", *base).out_dir)
    assert fresh.parent == sweep and fresh.name.startswith("c0.0075_g0.001_r0.001_")
    earlier = fresh.with_name("c0.0075_g0.001_r0.001_0123abcd")
    earlier.mkdir(parents=True)
    finish(earlier, check_point(compose("sample", *base, f"out_dir={earlier}"), earlier))
    assert compose_hydra("sample", *base).out_dir == str(earlier)
    other = Path(compose_hydra("sample", *base, "seed=3").out_dir)
    assert other != earlier and other.name.startswith("c0.0075_g0.001_r0.001_")


def test_a_point_whose_folder_was_sampled_or_evaluated_into_by_another_command_is_redone_and_reported_as_measured(
        point):
    """A plain ``spread-sample`` (other sampler) or ``spread-evaluate`` (other protocol) run into a finished point's
    folder does not write ``point.json``: the relaunched point is redone, not re-used under its old record, and a
    report names what ``metrics.json`` measured with (it named the point's record)."""
    from spread.reporting.runs import recorded_identity

    out, cfg = point["out"], point["cfg"]
    out.mkdir()
    decision = check_point(cfg(), out)
    fingerprint = decision.fingerprint
    sampling = {k: v for k, v in fingerprint.items() if k not in ("samples_per_graph", "evaluation")}
    finish(out, decision)
    (out / "sampling.json").write_text(json.dumps({"fingerprint": sampling, "samples_per_graph": 1}))
    measured = {"col_mesh": 0.1, "sampled_with": {**sampling, "samples_per_graph": fingerprint["samples_per_graph"]},
                "evaluated_with": fingerprint["evaluation"]}
    (out / "metrics.json").write_text(json.dumps(measured))
    assert check_point(cfg(), out).reuse  # every record agrees: re-used
    other = json.loads(json.dumps(sampling))
    other["sampling"]["sampler"]["steps"] = 2
    (out / "sampling.json").write_text(json.dumps({"fingerprint": other}))  # re-sampled, not evaluated yet
    again = check_point(cfg(), out)
    assert not again.reuse and again.fresh and "sampling.json was sampled with other settings" in again.reason
    assert "sampling.sampler.steps" in again.reason
    (out / "sampling.json").write_text(json.dumps({"fingerprint": sampling}))
    protocol = json.loads(json.dumps(fingerprint["evaluation"]))
    protocol["protocol"]["stability_runs"] = 7
    (out / "metrics.json").write_text(json.dumps({**measured, "evaluated_with": protocol}))  # evaluated otherwise
    again = check_point(cfg(), out)
    assert again.fresh and "evaluation.protocol.stability_runs" in again.reason, again.reason
    assert recorded_identity(out, json.loads((out / "metrics.json").read_text()))["evaluation"] == protocol
    (out / "metrics.json").write_text("{not json")
    assert not check_point(cfg(), out).reuse  # a damaged result is not a finished one
    (out / "metrics.json").write_text(json.dumps(measured))
    (out / "sampling.json").write_text("[1, 2")
    assert "its sampling.json does not read" in check_point(cfg(), out).reason


def test_a_sweep_point_is_named_by_the_device_its_trial_samples_on_not_the_drivers(point, monkeypatch, tmp_path):
    """A trial that asks for no GPU samples on the CPU (Ray hides the GPUs from it) while the driver of a GPU machine
    sees one: the driver named its points by ``cuda``, found none finished and sent each back to a trial."""
    import torch

    from spread.experiments.sweep import sample_point

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # the driver of a GPU machine
    fixed = [f"ckpt={point['ckpt']}", f"data.root={point['data']}", "evaluate=true", "guidance=refine", "workers=0"]
    plan = {"fixed": fixed, "points": str(tmp_path / "points"), "name": "s", "trial_gpus": 0.0}
    folder, cfg, overrides = sample_point({"guidance.collision": 0.5}, plan)
    assert point_fingerprint(cfg)["sampling"]["device"] == "cpu" and "device=cpu" in overrides
    _, on_gpu, overrides = sample_point({"guidance.collision": 0.5}, {**plan, "trial_gpus": 1.0})
    assert point_fingerprint(on_gpu)["sampling"]["device"] == "cuda" and "device=cpu" not in overrides
    _, given, _ = sample_point({"guidance.collision": 0.5}, {**plan, "fixed": [*fixed, "device=cuda"]})
    assert str(given.device) == "cuda"  # a device the user gave is kept


def test_a_sweep_point_whose_fid_backbone_cannot_load_is_refused_before_its_sampling(point):
    """``spread-sample evaluate=true`` loaded the FID backbone only after sampling every scene (a sweep's every point
    sampled, then failed); ablations and comparisons check their evaluate list before any stage
    (``StageEngine.check_lists``)."""
    from spread.commands.sample import sample

    out = point["out"]
    cfg = point["cfg"]("logger=none", "+evaluation.fid.extractor=nosuch_mod:make")
    with pytest.raises(ValueError, match=r"fid.extractor=nosuch_mod:make: cannot be loaded"):
        sample(cfg, log=False)
    assert not (out / "scenes").exists() and not (out / POINT).exists() and not (out / "sampling.json").exists()


def test_a_spread_sweep_of_the_hydra_grid_preset_logs_its_trials_in_the_sweeps_experiment(point, tmp_path):
    """``spread-sweep +sweep=guidance_grid``: the preset's ``sweep_dir`` named the trials' experiment
    ``<name>/guidance_grid`` (MLflow, wandb group) while the sweep's parent run sat in ``<name>``."""
    from spread.commands.sample import experiment_of
    from spread.configs import to_object
    from spread.experiments.sweep import sample_point

    fixed = ["+sweep=guidance_grid", f"ckpt={point['ckpt']}", f"data.root={point['data']}", "workers=0"]
    plan = {"fixed": fixed, "points": str(tmp_path / "points"), "name": "tune", "trial_gpus": 0.0}
    _, cfg, _ = sample_point({"guidance.collision": 0.5}, plan)
    assert experiment_of(to_object(cfg)) == "tune"
