"""Hostile inputs and features that meet, round 5 (docs/robustness.md): a re-run with other settings never reports,
keeps or mixes what was made with the first ones, and never loses it to a setting it then refuses.

* ``spread-sample``: a setting the model cannot sample with (a non-finite scale, a geometry scale for a model without
  geometry features, an unknown precision) is refused before the finished folder is touched; fewer samples per graph
  leave exactly the planned scenes;
* ``spread-evaluate`` / ``spread-report``: an evaluation keeps the sampling identity of the scenes it measured;
* ``spread-train ckpt_path=last`` with other settings than the checkpoint was trained with is refused by name;
* ``spread-generate`` into a folder of rooms made otherwise (or more of them) is refused by name;
* MLflow takes any room type as part of a metric name; an asset index cannot point outside its library.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, sample_in_process, train_in_process, user_error


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("r5data"))


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory) -> Path:
    """A base model's run folder after 2 training steps (checkpoints/last.ckpt)."""
    out = tmp_path_factory.mktemp("r5run") / "run"
    train_in_process(out, "experiment=quick", "model.variant=base", f"data.root={dataset}", "trainer.max_time=null",
                     "trainer.max_steps=2", *SMALL_MODEL, *FAST_TRAIN)
    return out


def folder_state(out: Path) -> dict:
    """The results of a sampling folder by name, with their bytes: the scenes, renders and ``sampling.json``."""
    files = [out / "sampling.json", *(out / "scenes").glob("*"), *(out / "renders").glob("*")]
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(files) if p.is_file()}


def test_a_scale_or_precision_the_model_cannot_sample_with_is_refused_before_the_finished_folder_is_touched(
        dataset, run, tmp_path):
    ckpt = run / "checkpoints" / "last.ckpt"
    out = tmp_path / "s"
    sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0")
    before = folder_state(out)
    assert sum(name.startswith("scenes/") for name in before) == 3
    line, _ = user_error("spread-sample", f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "workers=0",
                         "graph_scale=inf", "logger=none")
    assert "graph_scale=inf: a finite number" in line
    with pytest.raises(ValueError, match=r"geometry_scale=2.0: this model \(.*base.*\) has no geometry features"):
        sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0", "geometry_scale=2")
    with pytest.raises(ValueError, match="geometry_scale=nan: a finite number"):
        sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0", "geometry_scale=nan")
    with pytest.raises(ValueError, match="precision must be one of"):
        sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0", "precision=fp8")
    assert folder_state(out) == before  # sampling.json too: not pinned to the refused settings


def test_fewer_samples_per_graph_leave_exactly_the_planned_scenes_and_their_renders(dataset, run, tmp_path):
    ckpt = run / "checkpoints" / "last.ckpt"
    out = tmp_path / "s"
    two = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "samples_per_graph=2",
                            "renders=6")
    assert len(list((out / "scenes").glob("*.npz"))) == 6 and len(list((out / "renders").glob("*_k1.png"))) == 3
    first = {p.name: p.read_bytes() for p in two.files}
    kept = {name: data for name, data in first.items() if name.endswith("_k0.npz")}
    one = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "samples_per_graph=1",
                            "renders=6")
    assert sorted(p.name for p in (out / "scenes").glob("*.npz")) == sorted(kept)
    assert {p.name: p.read_bytes() for p in one.files} == kept  # the planned scenes resumed, not sampled again
    assert not list((out / "renders").glob("*_k1*.png"))
    assert one.manifest["set_aside_unplanned"] == 3 and one.manifest["samples"] == 3
    assert one.manifest["written_this_run"] == 0
    # nothing sampled is lost: the k1 scenes and their renders wait in unplanned/ for a run that plans them
    assert len(list((out / "unplanned" / "scenes").glob("*_k1.npz"))) == 3
    assert len(list((out / "unplanned" / "renders").glob("*_k1.png"))) == 3
    again = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "samples_per_graph=2",
                              "renders=6")
    assert again.manifest["taken_back"] == 3 and again.manifest["written_this_run"] == 0
    assert {p.name: p.read_bytes() for p in again.files} == first
    assert not list((out / "unplanned" / "scenes").glob("*.npz"))
    assert len(list((out / "renders").glob("*_k1.png"))) == 3
    # scenes set aside by a run of other settings never come back under new ones, even with scenes/ emptied by hand
    sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "samples_per_graph=1", "renders=0")
    for scene in (out / "scenes").glob("*.npz"):
        scene.unlink()
    other = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "samples_per_graph=2",
                              "renders=0", "seed=1")
    assert other.manifest["taken_back"] == 0 and other.manifest["redone_because"] == "changed: sampling.seed"
    assert all(p.read_bytes() != first[p.name] for p in other.files)


def test_a_report_gives_an_evaluation_the_sampling_settings_it_measured_after_its_folder_is_sampled_again(
        dataset, run, tmp_path):
    from spread.commands.evaluate import evaluate
    from spread.reporting.runs import folder_identity

    from helpers import compose

    ckpt = run / "checkpoints" / "last.ckpt"
    out = tmp_path / "s"
    sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0", "seed=0")
    measured = evaluate(compose("evaluate", f"scenes={out / 'scenes'}", f"reference={dataset}",
                                f"out_dir={tmp_path / 'e'}", "logger=none", "metrics=[grecall]", "fid.enabled=false",
                                "ray.num_cpus=1", "progress=false", "renders=0")).metrics
    assert measured["sampled_with"]["sampling"]["seed"] == 0
    assert measured["sampled_with"]["samples_per_graph"] == 1  # what was scored, though a run may grow
    again = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0", "seed=5")
    assert again.manifest["redone_because"] == "changed: sampling.seed"
    metrics = json.loads((tmp_path / "e" / "metrics.json").read_text())
    assert folder_identity(tmp_path / "e", metrics)["sampling"]["seed"] == 0
    del metrics["sampled_with"]  # an evaluation written before the record: the folder as it is now (the old way)
    assert folder_identity(tmp_path / "e", metrics)["sampling"]["seed"] == 5


def test_resuming_a_checkpoint_with_other_training_settings_is_refused_by_name(dataset, run, tmp_path):
    folder = tmp_path / "run"
    shutil.copytree(run, folder)
    common = ["experiment=quick", "model.variant=base", f"data.root={dataset}", "trainer.max_time=null",
              *SMALL_MODEL, *FAST_TRAIN, "ckpt_path=last"]
    held = (folder / "checkpoints" / "last.ckpt").read_bytes()
    with pytest.raises(ValueError, match=r"trained with other settings than this run's \(model.lr: 0.0005 -> 0.01; "
                                         r"model.seed: 0 -> 3; data.batch_size: 4 -> 2; data.seed: 0 -> 3\).*"
                                         r"model.init_from="):
        train_in_process(folder, *common, "trainer.max_steps=4", "model.lr=0.01", "seed=3", "data.batch_size=2")
    assert (folder / "checkpoints" / "last.ckpt").read_bytes() == held
    # the clipping changes every update: it was resumed, and the run's recorded config rewritten
    for clip, says in (("trainer.gradient_clip_val=0.0", "trainer.gradient_clip_val: 1.0 -> None"),
                       ("+trainer.gradient_clip_algorithm=value", "trainer.gradient_clip_algorithm: 'norm' -> 'value'")):
        with pytest.raises(ValueError, match=re.escape(says)):
            train_in_process(folder, *common, "trainer.max_steps=4", clip)
    assert (folder / "checkpoints" / "last.ckpt").read_bytes() == held
    # what changes none of the trained numbers resumes: more steps, loader processes, validation sampling
    summary = train_in_process(folder, *common, "trainer.max_steps=3", "data.num_workers=1",
                               "model.sample_every_n_epochs=0")
    assert summary["global_step"] == 3 and summary["resumed_from"]


def test_spread_generate_refuses_a_folder_of_rooms_made_otherwise_or_more_of_them(tmp_path):
    from spread.procgen.dataset import AssetSource, DatasetConfig, generate_dataset
    from spread.procgen.room_types import RoomConfig

    data = make_dataset(tmp_path)  # 12 rooms, seed 7, at most 8 objects, 20 % val, 30 % test
    rooms = sorted(p.relative_to(data) for p in data.rglob("*.npz"))
    base = ["renders=0", "processes=1", "rooms=12", "seed=7", "val_fraction=0.2", "test_fraction=0.3"]
    line, _ = user_error("spread-generate", f"out_dir={data}", *base, "room.max_objects=10")
    assert "holds rooms generated with other settings (changed: room.max_objects: 8 -> 10)" in line
    config = DatasetConfig(rooms=12, seed=7, processes=1, renders=0, val_fraction=0.2, test_fraction=0.3,
                           assets=AssetSource(copy_from=str(tmp_path / "assets")), room=RoomConfig(max_objects=8))
    with pytest.raises(ValueError, match=r"changed: seed: 7 -> 8"):
        generate_dataset(data, DatasetConfig(**{**config.__dict__, "seed": 8}), progress=False)
    with pytest.raises(ValueError, match=r"holds 2 room\(s\) this run would not make .*give rooms=12 or more"):
        generate_dataset(data, DatasetConfig(**{**config.__dict__, "rooms": 10}), progress=False)
    (data / "generation.json").unlink()  # a folder made before the pin: its manifest's config says the same
    with pytest.raises(ValueError, match=r"changed: room.max_objects: 8 -> 10"):
        generate_dataset(data, DatasetConfig(**{**config.__dict__, "room": RoomConfig(max_objects=10)}),
                         progress=False)
    manifest = generate_dataset(data, config, progress=False)  # the same settings: complete (nothing to do)
    assert manifest["this_run"]["rooms_generated"] == 0 and sum(manifest["counts"].values()) == 12
    assert sorted(p.relative_to(data) for p in data.rglob("*.npz")) == rooms
    assert json.loads((data / "generation.json").read_text())["status"] == "done"
    # a run that failed before its first room left only its pin: the next run, with other settings, goes ahead
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "generation.json").write_text(json.dumps({"fingerprint": {"seed": 99}, "status": "running"}))
    from spread.procgen.dataset import check_folder

    check_folder(empty, config)
    assert json.loads((empty / "generation.json").read_text())["fingerprint"]["seed"] == 7
    # rooms of an earlier version's run stopped before its manifest (no record): continued when this run makes them
    shutil.copytree(data / "train", empty / "train")
    (empty / "generation.json").unlink()
    check_folder(empty, config)
    (empty / "generation.json").unlink()
    with pytest.raises(ValueError, match=r"without a record of the settings"):  # not rooms seed 8 would make
        check_folder(empty, DatasetConfig(**{**config.__dict__, "seed": 8}))


def test_mlflow_takes_any_room_type_as_part_of_a_metric_name_and_two_types_never_share_one():
    from mlflow.utils.validation import _validate_metric_name

    from spread.tracking.mlflow_store import scalar_metrics

    types = ["bedroom", "Küche (groß)", "kitchen: open-plan", "kitchen/open", "kitchen_open", "../x", ""]
    metrics = {"grecall": 0.5, "per_room_type": {t: {"grecall": float(i), "n_scenes": 1} for i, t in enumerate(types)}}
    keys = scalar_metrics(metrics)
    for key in keys:
        _validate_metric_name(key)
    assert keys["room/bedroom/grecall"] == 0.0  # a plain name is kept as it is
    assert sorted(v for k, v in keys.items() if k.endswith("/grecall") and k.startswith("room/")) == [
        float(i) for i in range(len(types))]  # one key per type
    assert all(k.count("/") == 2 for k in keys if k.startswith("room/"))


@pytest.mark.parametrize("mesh_file", ["../../elsewhere.glb", "/etc/passwd", "meshes/../../x.glb", "a\\..\\b", ""])
def test_an_asset_index_pointing_outside_its_library_is_refused_by_key_and_value(tmp_path, mesh_file):
    from spread.assets.library import AssetLibrary

    from helpers import asset_library

    lib = tmp_path / "assets"
    asset_library(lib, categories=["mug"])
    index = json.loads((lib / "index.json").read_text())
    first = next(iter(index["assets"]))
    index["assets"][first]["mesh_file"] = mesh_file
    (lib / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match=rf"asset '{first}' has a bad record .*mesh_file="):
        AssetLibrary.load(lib)


def test_an_evaluation_refuses_an_index_pointing_outside_its_library_before_any_worker_or_record(dataset, tmp_path):
    """The index was read first by the Ray workers: every scene failed there and the run ended after them."""
    import shutil

    import ray

    from spread.evaluation import EvaluationConfig, run_evaluation

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    index = json.loads((data / "assets" / "index.json").read_text())
    first = next(iter(index["assets"]))
    index["assets"][first]["parts_file"] = "../../outside.npz"
    (data / "assets" / "index.json").write_text(json.dumps(index))
    out = tmp_path / "eval"
    with pytest.raises(ValueError, match=rf"asset '{first}' has a bad record .*parts_file='../../outside.npz'"):
        run_evaluation(EvaluationConfig(scenes=str(data / "test"), reference=str(data), out_dir=str(out),
                                        renders=0, progress=False))
    assert not ray.is_initialized() and not (out / "per_scene.jsonl").exists() and not (out / "metrics.json").exists()


# ---- round 5, second review: sweeps, ablations, exports -------------------------------------------------------

def test_an_object_limit_that_leaves_out_other_graphs_is_another_sampling_run_and_a_table_names_it(dataset, run,
                                                                                                   tmp_path):
    from spread.runtime.fingerprint import settings

    ckpt = run / "checkpoints" / "last.ckpt"
    out = tmp_path / "s"
    first = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0")
    assert first.manifest["samples"] == 3 and "graphs_over_limit" not in first.manifest["fingerprint"]["sampling"]
    same = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0", "max_objects=8")
    assert same.manifest["redone_because"] is None and same.manifest["written_this_run"] == 0  # leaves none out
    fewer = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0", "max_objects=6")
    assert fewer.manifest["redone_because"] == "changed: sampling.graphs_over_limit"
    assert fewer.manifest["samples"] == 2 and sorted(p.stem for p in (out / "scenes").glob("*.npz")) == [
        "s7_000007_k0", "s7_000008_k0"]
    assert settings(fewer.manifest["fingerprint"])["graphs_over_limit"] == "s7_000009"
    assert settings(first.manifest["fingerprint"])["graphs_over_limit"] == "none"


def test_spread_sweep_refuses_one_value_twice_a_sweep_of_its_own_settings_and_a_misspelled_key_in_one_line(
        dataset, run):
    from spread.experiments.sweep import parse_arguments

    with pytest.raises(ValueError, match=r"guidance.collision=0.0,0,0.0075: 0.0 and 0 are one setting"):
        parse_arguments(["guidance.collision=0.0,0,0.0075", "out_dir=x"])
    with pytest.raises(ValueError, match=r"model.lr=1e-3,0.001: 0.001 is listed twice"):
        parse_arguments(["command=train", "model.lr=1e-3,0.001", "out_dir=x"])
    with pytest.raises(ValueError, match=r"seeds=1,2: 'seeds' is a setting of the sweep itself"):
        parse_arguments(["seeds=1,2", "guidance.collision=0.0,0.1", "out_dir=x"])
    with pytest.raises(ValueError, match=r"name=\['a', 'b'\]: one text value"):
        parse_arguments(["name=[a,b]", "guidance.collision=0.0,0.1", "out_dir=x"])
    assert parse_arguments(["name=2024", "guidance.collision=0.0,0.1", "out_dir=x"]).settings.name == "2024"
    assert parse_arguments(["guidance.collision=0.0,0.1", "out_dir=2024"]).settings.out_dir == "2024"  # a folder
    with pytest.raises(ValueError, match=r"max_concurrent=2.7: a whole number of trials"):  # before: 2, silently
        parse_arguments(["max_concurrent=2.7", "guidance.collision=0.0,0.1", "out_dir=x"])
    from spread.cli.sweep import main  # the console script's main, in this process (no process start)

    with pytest.raises(SystemExit) as refused:
        main([f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}", "guidance=refine",
              "guidance.colision=0.1", "guidance.gravity=0.0,0.001", "out_dir=unused"])
    line = str(refused.value.code)
    assert line.startswith("spread-sweep: ") and "\n" not in line and "Traceback" not in line
    assert "Could not override 'guidance.colision'" in line and "Key 'colision' not in 'GuidanceConfig'" in line


def test_spread_ablate_refuses_a_seed_twice_and_a_stage_list_that_does_not_compose_before_any_stage(dataset, run,
                                                                                                    tmp_path):
    from spread.commands.ablate import ablate

    from helpers import compose

    common = ["variants=[base]", f"train.ckpt.base={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}",
              "logger=none", "figures=false", f"out_dir={tmp_path / 'a'}"]
    with pytest.raises(ValueError, match=r"^seeds=\[0, 0\]: 0 is listed twice in \[0, 0\]; give each training seed once$"):
        ablate(compose("ablate", *common, "seeds=[0,0]"))
    with pytest.raises(ValueError, match=r"seeds=\[0, 1.5\]: a seed is a whole number ≥ 0"):  # it ran seed 1
        ablate(compose("ablate", *common, "seeds=[0,1.5]"))
    with pytest.raises(ValueError, match=r"^sample/base: its overrides .*guidance.colision"):
        ablate(compose("ablate", *common, 'sample.extra=["sampler.steps=5","guidance.colision=0.1"]'))
    with pytest.raises(ValueError, match=r"evaluate: .*protocol.stability_runs=x.*could not be converted to Integer"):
        ablate(compose("ablate", *common, 'evaluate.extra=["protocol.stability_runs=x"]'))
    with pytest.raises(ValueError, match=r"evaluate: .*fid.extractor=nosuch_mod:make: cannot be loaded"):
        ablate(compose("ablate", *common, 'evaluate.extra=["fid.enabled=true","+fid.extractor=nosuch_mod:make"]'))
    assert not (tmp_path / "a" / "samples").exists() and not (tmp_path / "a" / "eval").exists()


def test_spread_export_never_lets_one_scene_overwrite_another_or_its_own_report(dataset, tmp_path):
    from spread.export import export_folder
    from spread.scene import read_scene, write_scene

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    source = read_scene(sorted((dataset / "test").glob("*.npz"))[0])
    for file, scene_id in [("0first", "X__b"), ("a", "X"), ("b", "X"), ("c", "export.json"), ("d", "export.log")]:
        write_scene(source.with_poses(source.translation, source.rotation, scene_id=scene_id), scenes / f"{file}.npz")
    report = export_folder(scenes, dataset.parent / "assets", tmp_path / "out", "sceneeval")
    assert not report.failed and len(report.written) == 5
    assert len({Path(p).name for p in report.written.values()}) == 5  # five outputs, none over another
    assert set(report.written) == {"X__b", "X", "X__b_2", "export.json__c", "export.log__d"}
    assert (tmp_path / "out" / "export.json").is_file()
    assert json.loads((tmp_path / "out" / "export.json").read_text())["written"] == report.written


def test_a_3d_front_splits_file_that_puts_one_room_in_two_splits_is_refused_by_line(tmp_path):
    from spread.importers.threed_front import read_splits

    splits = tmp_path / "splits.csv"
    splits.write_text("RoomId,split\nBedroom-1,train\nLivingRoom-2,test\nBedroom-1,train\n")
    assert read_splits(splits) == {"Bedroom-1": "train", "LivingRoom-2": "test"}  # the same line twice: one room
    splits.write_text("RoomId,split\nBedroom-1,train\nLivingRoom-2,test\nBedroom-1,test\n")
    with pytest.raises(ValueError, match=r"splits.csv: line 4: room 'Bedroom-1' is listed in 'train' and 'test'"):
        read_splits(splits)


# ---- round 5, third review: one identity, one unit -------------------------------------------------------------

def test_the_same_metrics_in_another_order_are_one_protocol():
    from spread.evaluation.protocol import EvalProtocol

    given = EvalProtocol(metrics=["stability", "grecall", "asd", "col_mesh"])
    assert given.metrics == EvalProtocol().metrics == ["col_mesh", "grecall", "asd", "stability"]
    assert given.fingerprint() == EvalProtocol().fingerprint()
    assert EvalProtocol(metrics=["grecall"]).fingerprint() != EvalProtocol().fingerprint()


def test_trackers_log_asd_in_mm_keyed_so_and_the_readers_take_it_back_in_metres(tmp_path):
    from spread.metrics.registry import in_stored_units
    from spread.reporting.runs import read_wandb_run
    from spread.tracking.mlflow_store import log_table, scalar_metrics

    metrics = {"asd": 0.0123, "asd_lo": 0.01, "asd_hi": 0.02, "grecall": 0.9, "col_mesh": 0.2, "n_scenes": 3,
               "per_room_type": {"bedroom": {"asd": 0.004, "n_scenes": 1}}}
    logged = scalar_metrics(metrics)
    assert logged["asd_mm"] == pytest.approx(12.3) and logged["asd_mm_lo"] == pytest.approx(10.0)
    assert logged["room/bedroom/asd_mm"] == pytest.approx(4.0) and "asd" not in logged and "room/bedroom/asd" not in logged
    assert logged["grecall"] == 0.9 and logged["n_scenes"] == 3  # a share and a count keep their keys
    back = in_stored_units({k: v for k, v in logged.items() if "/" not in k})
    assert back["asd"] == pytest.approx(0.0123) and back["asd_hi"] == pytest.approx(0.02)

    class Run:
        def __init__(self):
            self.metrics = {}

        def log_metrics(self, values):
            self.metrics |= values

    run = Run()
    log_table(run, [{"variant": "base", "asd": 0.002, "grecall": 0.5}], "variant")
    assert run.metrics == {"base/asd_mm": pytest.approx(2.0), "base/grecall": 0.5}
    # a wandb run as an older wandb wrote it (files/wandb-summary.json): read back in metres, as metrics.json has it
    folder = tmp_path / "wandb" / "offline-run-20261130_000000-abc"
    (folder / "files").mkdir(parents=True)
    (folder / "files" / "wandb-summary.json").write_text(json.dumps(logged))
    (folder / "files" / "config.yaml").write_text("{}\n")
    record = read_wandb_run(folder)
    assert record["asd"] == pytest.approx(0.0123) and record["asd_lo"] == pytest.approx(0.01)


def test_a_row_whose_seeds_ran_with_other_settings_is_not_averaged_and_the_table_says_why():
    from spread.experiments.ablation_seeds import aggregate, differ_note

    def record(variant, seed, value, sampler):
        return {"variant": variant, "status": "ok", "grecall": value, "col_mesh": 0.1,
                "settings": {"ckpt": f"c{seed}{variant}", "seed": seed, "protocol.seed": seed, "sampler": sampler}}

    per_seed = {0: [record("base", 0, 0.5, "ddim-5"), record("geometry", 0, 0.6, "ddim-5")],
                1: [record("base", 1, 0.7, "ddim-10"), record("geometry", 1, 0.8, "ddim-5")]}
    rows = {r["variant"]: r for r in aggregate(per_seed)}
    assert rows["geometry"]["grecall"] == pytest.approx(0.7) and rows["geometry"]["seeds"] == 2  # seeds differ only
    assert rows["base"]["grecall"] is None and rows["base"]["seeds"] == 0
    assert rows["base"]["status"] == "not averaged: its seeds' runs differ in sampler (ddim-10, ddim-5)"
    assert "Ours (base): sampler (ddim-10, ddim-5)" in differ_note(list(rows.values()))


def test_eta_on_a_sampler_that_ignores_it_is_refused_rather_than_made_a_second_identity():
    from spread.model.diffusion import Sampler
    from spread.runtime.fingerprint import settings
    from spread.sampling import SamplingConfig

    for kind in ("ddpm", "dpmsolver++"):
        with pytest.raises(ValueError, match=rf"sampler.eta=0.5: only the ddim sampler reads eta \({re.escape(kind)} "):
            SamplingConfig(ckpt="c", out_dir="o", sampler={"kind": kind, "steps": 10, "eta": 0.5})
        assert Sampler(kind, 10, eta=0.0).label == f"{kind}-10"
    assert SamplingConfig(ckpt="c", out_dir="o", sampler="ddim-10-eta0.5").sampler.label == "ddim-10-eta0.5"
    # a run recorded with one before the refusal still reads back (spread-report, spread.results)
    recorded = {"sampling": {"sampler": {"kind": "ddpm", "steps": 10, "eta": 0.5, "clip_x0": True}}}
    assert settings(recorded)["sampler"] == "ddpm-10-eta0.5"


def test_a_training_stage_is_known_by_the_settings_its_overrides_compose_to_not_by_their_spelling(tmp_path):
    from spread.experiments.stages import Ledger, Stage, StageError, run_stage, typed_training

    folder = tmp_path / "abl" / "train" / "base"
    ledger, runs = Ledger(tmp_path / "abl" / "ledger.json"), []

    def train(resume: bool) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "metrics.json").write_text("{}")
        runs.append(resume)

    def stage(*overrides, data="d1", where=str(tmp_path / "abl")):
        lists = ["experiment=quick", *overrides, f"data.root={where}/data", f"out_dir={where}/train/base",
                 "experiment_name=ablate_x"]
        inputs = {"overrides": lists, **({"data_sha256": data} if data else {})}
        return Stage("train/base", folder, [folder / "metrics.json"], inputs, train, derived=False,
                     typed=typed_training)

    assert run_stage(stage("model.lr=1e-3"), ledger) == "done" and len(runs) == 1
    # the same settings spelled otherwise, the folder named relative to another working directory: re-used
    assert run_stage(stage("model.lr=0.001", where="abl"), ledger) == "skipped"
    assert run_stage(stage("model.lr=1.0e-3", "logger=csv"), ledger) == "skipped"
    with pytest.raises(StageError, match=r"changed: config.model.lr"):
        run_stage(stage("model.lr=0.01"), ledger)
    with pytest.raises(StageError, match=r"changed: data_sha256"):  # other rooms at the same path
        run_stage(stage("model.lr=1e-3", data="d2"), ledger)
    old = Ledger(tmp_path / "abl" / "old_ledger.json")  # a ledger written before stages kept the data's content
    assert run_stage(stage("model.lr=1e-3", data=None), old) == "skipped"
    assert run_stage(stage("model.lr=0.001", data="d1"), old) == "skipped"
    assert len(runs) == 1


def test_a_copy_of_the_dataset_elsewhere_resumes_a_sampling_run_and_the_record_says_where_it_now_lies(dataset, run,
                                                                                                       tmp_path):
    ckpt = run / "checkpoints" / "last.ckpt"
    out = tmp_path / "s"
    sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "renders=0")
    copy = tmp_path / "moved"
    shutil.copytree(dataset.parent, copy)  # the data and its asset library: the same content at another path
    again = sample_in_process(f"ckpt={ckpt}", f"data.root={copy / 'data'}", f"out_dir={out}", "renders=0")
    assert again.manifest["redone_because"] is None and again.manifest["written_this_run"] == 0
    assert again.manifest["fingerprint"]["data_root"] == str((copy / "data").resolve())
    # device=auto resolved as the samplers resolve it: the same run as the device it resolves to here
    from spread.runtime.fingerprint import auto_device

    spelled = sample_in_process(f"ckpt={ckpt}", f"data.root={copy / 'data'}", f"out_dir={out}", "renders=0",
                                f"device={auto_device()}")
    assert spelled.manifest["redone_because"] is None and spelled.manifest["written_this_run"] == 0


@pytest.mark.parametrize("experiment", ["quick", "atiss_quick", "diffuscene_quick"])
def test_a_resume_with_the_checkpoints_own_settings_is_never_refused_whatever_the_model_takes_from_the_data(
        dataset, experiment):
    import hydra

    from spread.training.fit import resumed_changes

    from helpers import compose

    cfg = compose("train", f"experiment={experiment}", f"data.root={dataset}", "data.augment=true")
    model, datamodule = hydra.utils.instantiate(cfg.model), hydra.utils.instantiate(cfg.data)
    # the checkpoint as fitting writes it: what setup() took from the data filled in
    held = {**dict(model.hparams), **model.data_hparams(datamodule)}
    checkpoint = {"hyper_parameters": held, "datamodule_hyper_parameters": dict(datamodule.hparams)}
    assert resumed_changes(checkpoint, model, datamodule) == []
    other = {**checkpoint, "hyper_parameters": {**held, "lr": float(held["lr"]) * 10}}
    assert [c.split(":")[0] for c in resumed_changes(other, model, datamodule)] == ["model.lr"]


def test_an_evaluate_stage_under_another_object_limit_is_not_the_stage_recorded(dataset, tmp_path):
    """An ablation's or comparison's ``evaluate: [max_objects=3]`` left scenes out; relaunched with
    ``max_objects=0`` its stage inputs were the same, so the stage was skipped and the table kept the numbers
    without those scenes. The default (null) is left out of the inputs: stages recorded before keep theirs."""
    from spread.experiments.stages import Ledger, Stage, StageEngine, StagesSpec, run_stage
    from spread.runtime.fingerprint import normalised

    samples = tmp_path / "study" / "samples" / "v"  # the row's sampling stage, finished
    samples.mkdir(parents=True)
    (samples / "sampling.json").write_text('{"fingerprint": {"sampling": {}, "guidance": null}, "samples": 2}')

    def stage(evaluate: list[str]) -> Stage:
        spec = StagesSpec(out_dir=tmp_path / "study", data_root=dataset, split="test", evaluate=evaluate)
        return StageEngine(spec, commands=None, study=None, ledger_name="ablation.json").evaluate_stage("v")

    limited, unlimited, default = stage(["max_objects=3"]), stage(["max_objects=0"]), stage([])
    assert limited.inputs["max_objects"] == 3 and unlimited.inputs["max_objects"] == 0
    assert "max_objects" not in default.inputs and stage(["max_objects=null"]).inputs == default.inputs
    folder = Path(limited.folder)
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text('{"n_evaluated": 2}')
    ledger = Ledger(tmp_path / "study" / "ablation.json")
    ledger.record(limited.name, normalised(limited.inputs), 1.0)
    ran = []
    limited.run = unlimited.run = lambda resume: ran.append(resume)
    assert run_stage(limited, ledger) == "skipped" and ran == []
    assert run_stage(unlimited, ledger) == "done" and ran == [False]  # redone from scratch (resume=false)
    assert ledger.inputs(unlimited.name)["max_objects"] == 0


def test_spread_sample_evaluate_true_evaluates_under_its_own_object_limit_a_negative_one_as_none(tmp_path):
    """``max_objects=-1`` (sampling: no limit) was handed on as -1, which the evaluation refuses: after the whole
    sampling had run, the evaluation failed and the sweep point stayed 'running'."""
    from spread.commands.sample import evaluation_after_sampling
    from spread.configs import compose, to_object

    def limit(value: str):
        command = to_object(compose("sample", ["ckpt=a.ckpt", f"data.root={tmp_path}", f"out_dir={tmp_path / 'o'}",
                                               "evaluate=true", f"max_objects={value}"]))
        return evaluation_after_sampling(command).max_objects

    assert [limit(v) for v in ("-1", "0", "5", "null")] == [0, 0, 5, None]


def test_what_an_object_limit_leaves_out_is_listed_up_to_sixteen_names_and_above_by_count_and_digest():
    """800 scenes over the limit made the evaluation's identity a 22,205-character tag, which MLflow cut to invalid
    JSON (the report of the store then lost the evaluation's identity)."""
    from spread.runtime.fingerprint import NAMES_LISTED, left_out, settings

    few = [f"scene-{i:03d}" for i in range(NAMES_LISTED)]
    assert left_out(reversed(few)) == few
    many = [f"livingroom-big-scene-{i:03d}" for i in range(800)]
    spelled = left_out(many)
    assert isinstance(spelled, str) and spelled.startswith("800 names, sha256 ") and len(spelled) < 40
    assert left_out(reversed(many)) == spelled and left_out(many[:-1]) != spelled
    assert settings({"evaluation": {"scenes_over_limit": spelled}})["scenes_over_limit"] == spelled


def test_spread_generate_refuses_an_out_dir_inside_the_library_it_copies_or_holding_another_commands_run(tmp_path):
    """``out_dir`` inside ``assets.copy_from`` copied the library into itself level upon level (270 levels, then
    Python's recursion limit); into a training run's folder it wrote a dataset beside the checkpoints, and the
    run could no longer be resumed. Both are refused in one line before anything is made."""
    from helpers import user_error

    lib = tmp_path / "lib"
    (lib / "meshes").mkdir(parents=True)
    (lib / "index.json").write_text("{}")
    line, _ = user_error("spread-generate", f"out_dir={lib / 'out'}", "rooms=2", "processes=1", "renders=0",
                         f"assets.copy_from={lib}")
    assert line.startswith(f"spread-generate: assets.copy_from={lib}: out_dir={lib / 'out'} lies inside it, so the "
                           f"copy would hold itself; give an out_dir outside the library"), line
    assert sorted(p.name for p in lib.iterdir()) == ["index.json", "meshes"]
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    line, _ = user_error("spread-generate", f"out_dir={run}", "rooms=2", "processes=1", "renders=0",
                         f"assets.copy_from={lib}")
    assert line.startswith(f"spread-generate: out_dir={run}: holds a training run ({run / 'checkpoints'})"), line
    assert [p.name for p in run.iterdir()] == ["checkpoints"]


def test_a_partial_generation_record_beside_an_intact_manifest_does_not_let_other_settings_mix_in(tmp_path):
    """``generation.json`` cut to ``{"fingerprint": {}}`` (or to one key): the intact manifest was never asked, so a
    relaunch with ``room.max_objects=4`` added its rooms to rooms of up to 8 objects, under a manifest saying 4."""
    data = make_dataset(tmp_path)  # 12 rooms, seed 7, at most 8 objects
    base = ["renders=0", "processes=1", "rooms=14", "seed=7", "val_fraction=0.2", "test_fraction=0.3"]
    rooms = sorted(p.relative_to(data) for p in data.rglob("*.npz"))
    generator = json.loads((data / "generation.json").read_text())["fingerprint"].get("generator")
    for record, says in [({"fingerprint": {}}, "key 'fingerprint' records no setting"),
                         ({"fingerprint": {"generator": generator}}, "changed: room.max_objects: 8 -> 4")]:
        (data / "generation.json").write_text(json.dumps(record))
        line, _ = user_error("spread-generate", f"out_dir={data}", *base, "room.max_objects=4")
        assert says in line, line
        assert sorted(p.relative_to(data) for p in data.rglob("*.npz")) == rooms


@pytest.mark.parametrize("setting, says", [
    ("seed=-1", "seed=-1: expected a whole number ≥ 0"), ("max_attempts=0", "max_attempts=0: expected a whole number ≥ 1"),
    ("settle.rounds=0", "settle.rounds=0: expected a whole number ≥ 1"),
    ("assets.variants=0", "assets.variants=0: expected a whole number ≥ 1"),
    ("settle.max_steps=-5", "settle.max_steps=-5: expected a whole number ≥ 1"),
    ("room.object_density=nan", "room.object_density=nan: expected a finite number ≥ 0"),
    ("settle.verify_dt=nan", "settle.verify_dt=nan: expected a finite number in (0, 1]"),
    ("room.stack_probability=1.5", "room.stack_probability=1.5: expected a finite number in [0, 1]"),
    ("room.max_objects=100000", "room.max_objects=100000: at most 512")])
def test_spread_generate_refuses_a_count_or_measure_out_of_its_range_by_key_before_any_work(tmp_path, setting, says):
    """Each failed after the asset library was built, naming no key ("expected non-negative integer", "compute_stats:
    no scenes given", "lam < 0 or lam is NaN"), or was taken silently (``settle.max_steps=-5``)."""
    from spread.procgen.dataset import DatasetConfig, check_config
    from spread.configs import compose, to_object

    config = to_object(compose("generate", [f"out_dir={tmp_path / 'd'}", "rooms=2", setting]))
    assert isinstance(config, DatasetConfig)
    with pytest.raises(ValueError, match=re.escape(says)):
        check_config(config)


def test_a_dataset_whose_every_room_failed_says_why_and_writes_no_statistics(tmp_path):
    """``room.min_objects=400`` ran 116 s, then ended in "compute_stats: no scenes given": every room kept fewer
    objects than asked. Now the line names the setting, the attempts and what settling removed."""
    from spread.configs import compose, to_object
    from spread.procgen.dataset import write_dataset_files

    config = to_object(compose("generate", [f"out_dir={tmp_path}", "rooms=2", "room.min_objects=400",
                                            "room.max_objects=400", "max_attempts=3"]))
    failed = [{"index": i, "ok": False, "attempts": 3, "removed": {"slid": 2 + i}} for i in range(2)]
    with pytest.raises(ValueError, match=re.escape("no room was made: each of the 2 room(s) kept fewer than "
                                                   "room.min_objects=400 objects in max_attempts=3 attempts "
                                                   "(objects removed in settling: {'slid': 5})")):
        write_dataset_files(tmp_path, config, None, failed, 1.0, 1.0)
    assert not (tmp_path / "stats.json").exists()
