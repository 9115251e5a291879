"""Extension points from outside the repository (issue 22): ``examples/spread_plugin_example`` — a separate package
declaring a metric (``spread.metrics``), a guidance term (``spread.guidance``) and a method (``spread.methods``) as
entry points — is installed with pip into a folder of its own and found by the console scripts as users run them,
with nothing in the repository edited. Also: the registries' built-ins, and their errors."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import FAST_SAMPLE, FAST_TRAIN, SCRIPTS, SMALL_MODEL, make_dataset, train_in_process

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "spread_plugin_example"


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory) -> Path:
    """The example package installed by pip (its dist-info carries the entry points) into a fresh folder."""
    site = tmp_path_factory.mktemp("plugin_site")
    build = tmp_path_factory.mktemp("plugin_src")
    shutil.copytree(EXAMPLE, build / "pkg")  # pip builds in the source tree: keep the repository clean
    proc = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                           "--target", str(site), str(build / "pkg")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    eps = next(site.glob("spread_plugin_example-*.dist-info")) / "entry_points.txt"
    assert "below_floor" in eps.read_text()
    return site


def hydra_list(key: str, *items: str) -> str:
    """``key=["a=1","b=2"]``: a Hydra list of override strings, quoted as Hydra's grammar needs."""
    return f"{key}=[" + ",".join(f'"{i}"' for i in items) + "]"


def run_with_plugins(site: Path, name: str, *args: str, ok: bool = True,
                     wandb: str = "disabled") -> subprocess.CompletedProcess:
    env = {**os.environ, "WANDB_MODE": wandb, "PYTHONPATH": str(site), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([str(SCRIPTS / name), *args], env=env, capture_output=True, text=True, timeout=900)
    if ok:
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    return proc


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("plugdata"), rooms=10, seed=5, max_objects=6)


def sunk_scenes(dataset: Path, out: Path) -> Path:
    """The test scenes with their first object lowered 10 cm into the floor (known answer: 1 object each)."""
    from spread.scene import list_scene_files, read_scene, write_scene

    out.mkdir(parents=True)
    for path in list_scene_files(dataset / "test"):
        scene = read_scene(path)
        t = scene.translation.copy()
        t[0, 1] -= 0.10 + float(t[0, 1])  # centre 10 cm below y = 0: its hull is surely below the floor
        write_scene(scene.with_poses(t, scene.rotation), out / path.name)
    return out


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_a_plugin_metric_is_selected_by_name_in_spread_evaluate(plugin_site, dataset, tmp_path):
    scenes = sunk_scenes(dataset, tmp_path / "scenes")
    out = tmp_path / "eval"
    proc = run_with_plugins(plugin_site, "spread-evaluate", f"scenes={scenes}", f"reference={dataset}", f"out_dir={out}",
                            "metrics=[grecall,below_floor]", "logger=none", "fid.enabled=false", "renders=0",
                            "progress=false", "ray.num_cpus=1")
    metrics = json.loads((out / "metrics.json").read_text())
    n_objects = metrics["n_objects"]
    n = metrics["n_evaluated"]
    assert metrics["below_floor"] == pytest.approx(n / n_objects)  # one sunk object per scene
    assert metrics["below_floor_lo"] <= metrics["below_floor"] <= metrics["below_floor_hi"]
    assert "col_mesh" not in metrics and metrics["protocol"]["metrics"] == ["grecall", "below_floor"]
    lines = [json.loads(x) for x in (out / "per_scene.jsonl").read_text().splitlines()]
    assert all(r["below_floor"] == pytest.approx(1 / r["num_objects"]) for r in lines)
    assert "Below floor" in proc.stdout  # the console table shows it under its column name
    # a plugin engine by name: nothing moves in it, so even the sunk scenes keep every relation
    still = tmp_path / "static"
    run_with_plugins(plugin_site, "spread-evaluate", f"scenes={scenes}", f"reference={dataset}", f"out_dir={still}",
                     "metrics=[stability]", "protocol.physics=static", "protocol.stability_runs=2", "logger=none",
                     "fid.enabled=false", "renders=0", "progress=false", "ray.num_cpus=1")
    static = json.loads((still / "metrics.json").read_text())
    assert static["stability"] == 1.0 and static["still_fraction"] == 1.0
    assert static["protocol"]["physics"] == "static"
    # without the plugin installed, the name is refused in one line that lists the known metrics
    bad = subprocess.run([str(SCRIPTS / "spread-evaluate"), f"scenes={scenes}", f"reference={dataset}",
                          f"out_dir={tmp_path / 'x'}", "metrics=[grecall,below_floor]", "logger=none"],
                         env={**os.environ, "WANDB_MODE": "disabled"}, capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "unknown metric 'below_floor'" in bad.stderr and "oob" in bad.stderr


@pytest.fixture(scope="module")
def checkpoint(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("plugrun") / "run"
    train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null", "trainer.max_steps=2",
                     *SMALL_MODEL, *FAST_TRAIN)
    return out / "checkpoints" / "last.ckpt"


def scene_files(folder: Path) -> dict:
    from spread.scene import list_scene_files, read_scene

    return {p.name: read_scene(p) for p in list_scene_files(folder)}


@pytest.mark.slow  # long (≈ 35 s on 2 cores: two spread-sample processes): make test-slow runs it; the fast guard
# is test_every_entry_point_group_finds_the_example_and_its_term_is_one_more_setting
def test_a_plugin_guidance_term_is_switched_on_by_name_in_spread_sample(plugin_site, dataset, checkpoint, tmp_path):
    common = [f"ckpt={checkpoint}", f"data.root={dataset}", *FAST_SAMPLE, "seed=1"]
    run_with_plugins(plugin_site, "spread-sample", *common, f"out_dir={tmp_path / 'plain'}")
    run_with_plugins(plugin_site, "spread-sample", *common, f"out_dir={tmp_path / 'pushed'}", "guidance=paper",
                     "guidance.collision=0", "guidance.gravity=0", "guidance.relation=0", "+guidance.terms.floor_push=0.5")
    plain, pushed = scene_files(tmp_path / "plain" / "scenes"), scene_files(tmp_path / "pushed" / "scenes")
    assert plain.keys() == pushed.keys() and plain
    moved = [not np.allclose(plain[k].translation, pushed[k].translation) for k in plain]
    assert any(moved)  # only the plugin term has a weight: it is what moved the objects
    record = json.loads((tmp_path / "pushed" / "sampling.json").read_text())
    assert record["guidance"]["floor_push"] == 0.5 and record["guidance_label"] == "paper(floor_push=0.5)"


def test_every_entry_point_group_finds_the_example_and_its_term_is_one_more_setting(plugin_site, tmp_path):
    """The fast guard of the slow command-line tests below (make test-slow runs those): in a process that sees the
    installed example, each of the four groups lists its entry with the entry point as its origin, and the plugin
    term's weight is part of a ``spread-sample`` setting as the built-ins' are: its fingerprint (a changed weight
    names it), its label, and the sampling run's wandb and MLflow tags."""
    code = """
import json, sys
from pathlib import Path
from spread.configs import compose
from spread.metrics.registry import METRICS
from spread.guidance.terms import TERMS_REGISTRY
from spread.methods.registry import METHODS, method_names
from spread.physics.engines import ENGINES
from spread.runtime.fingerprint import changed_keys, point_fingerprint, typed_command
from spread.tracking.sampling_mlflow import sampling_run_tags
from spread.tracking.sampling_wandb import sampling_tags
root = Path(sys.argv[1])
origins = {r.kind: r.origin(n) for r, n in ((METRICS, "below_floor"), (TERMS_REGISTRY, "floor_push"),
                                             (METHODS, "jitter_truth"), (ENGINES, "static"))}
base = [f"ckpt={root / 'm.ckpt'}", f"data.root={root / 'data'}", f"out_dir={root / 'out'}", "guidance=refine",
        "guidance.collision=0", "guidance.gravity=0", "guidance.relation=0", "guidance.iterations=1"]
half, more = (compose("sample", [*base, f"+guidance.terms.floor_push={w}"]) for w in (0.5, 0.7))
command = typed_command(half)
mlflow_tags = {k: v for k, v in sampling_run_tags(command).items() if k.startswith("spread.guidance")}
print(json.dumps({"origins": origins, "methods": method_names(), "label": METHODS.get("jitter_truth").label,
                  "wandb_tags": sampling_tags(command.ckpt, command.sampler, command.guidance),
                  "mlflow_tags": mlflow_tags,
                  "fingerprint": point_fingerprint(half)["guidance"],
                  "changed": changed_keys(point_fingerprint(half), point_fingerprint(more))}))
"""
    torch.save({"hyper_parameters": {"variant": "geometry", "method": "spread"}, "state_dict": {}}, tmp_path / "m.ckpt")
    (tmp_path / "data" / "test").mkdir(parents=True)
    (tmp_path / "data" / "stats.json").write_text("{}")
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(plugin_site), "WANDB_MODE": "disabled"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    assert seen["origins"] == {
        "metric": "entry point 'below_floor = spread_plugin_example:BelowFloorRate' (spread-plugin-example)",
        "guidance term": "entry point 'floor_push = spread_plugin_example:FLOOR_PUSH' (spread-plugin-example)",
        "method": "entry point 'jitter_truth = spread_plugin_example:JITTER_TRUTH' (spread-plugin-example)",
        "physics engine": "entry point 'static = spread_plugin_example:STATIC_ENGINE' (spread-plugin-example)"}
    assert seen["methods"][-1] == "jitter_truth" and seen["label"] == "Jittered ground truth"
    assert seen["wandb_tags"] == ["geometry", "ddim-50", "guidance", "guidance=refine", "floor_push=0.5"]
    assert seen["mlflow_tags"] == {"spread.guidance": "refine", "spread.guidance.floor_push": "0.5",
                                   "spread.guidance_label": "refine(floor_push=0.5,iterations=1)"}
    assert seen["fingerprint"]["floor_push"] == 0.5 and seen["fingerprint"]["iterations"] == 1
    assert seen["changed"] == ["guidance.floor_push"]


# ---- a plugin's term is one more setting: tags, fingerprints, re-launches, tables, reports -----------------------

#: A guided run whose only acting term is the plugin's, cheap to evaluate (GRecall only, no FID).
PUSHED = ["guidance=refine", "guidance.collision=0", "guidance.gravity=0", "guidance.relation=0",
          "guidance.iterations=1"]
CHEAP_EVALUATION = ["evaluation.metrics=[grecall]", "evaluation.fid.enabled=false", "ray.num_cpus=1"]


def wandb_tags(out: Path) -> list[str]:
    """The tags of the wandb offline run under ``out/wandb`` (its ``.wandb`` log, decoded with wandb's protobuf)."""
    from wandb.proto import wandb_internal_pb2 as pb

    from spread.reporting.runs import wandb_records

    (log,) = out.glob("wandb/offline-run-*/run-*.wandb")
    for raw in wandb_records(log):
        record = pb.Record()
        record.ParseFromString(raw)
        if record.WhichOneof("record_type") == "run":
            return list(record.run.tags)
    raise AssertionError(f"{log}: no run record")


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_a_plugin_term_is_named_in_tags_and_fingerprints_and_a_changed_weight_redoes_the_run(plugin_site, dataset,
                                                                                               checkpoint, tmp_path):
    from mlflow import MlflowClient

    from spread.runtime.fingerprint import short

    out, uri = tmp_path / "pushed", f"sqlite:///{tmp_path / 'mlflow.db'}"
    common = [f"ckpt={checkpoint}", f"data.root={dataset}", *FAST_SAMPLE, "seed=1", *PUSHED, "evaluate=true",
              *CHEAP_EVALUATION, f"out_dir={out}"]
    run_with_plugins(plugin_site, "spread-sample", *common, "+guidance.terms.floor_push=0.5",
                     "logger=mlflow", "logger.name=wandb+mlflow", f"logger.tracking_uri={uri}", wandb="offline")
    assert {"guidance", "guidance=refine", "floor_push=0.5"} <= set(wandb_tags(out))
    run_id = json.loads((out / "mlflow_run.json").read_text())["run_id"]
    tags = MlflowClient(tracking_uri=uri).get_run(run_id).data.tags
    assert tags["spread.guidance.floor_push"] == "0.5" and "spread.guidance.collision" not in tags
    assert tags["spread.guidance_label"] == "refine(floor_push=0.5,iterations=1)"
    sampled, point = (json.loads((out / f).read_text()) for f in ("sampling.json", "point.json"))
    assert sampled["fingerprint"]["guidance"]["floor_push"] == 0.5 == point["fingerprint"]["guidance"]["floor_push"]
    first = point["short"]
    # the plugin term's weight changed: sampled and evaluated again, and the records say why
    changed = run_with_plugins(plugin_site, "spread-sample", *common, "+guidance.terms.floor_push=0.7", "logger=none")
    assert "redone (changed: guidance.floor_push)" in changed.stdout
    sampled, point = (json.loads((out / f).read_text()) for f in ("sampling.json", "point.json"))
    assert sampled["redone_because"] == "changed: guidance.floor_push"
    assert point["redone_because"] == "changed: guidance.floor_push" and point["status"] == "finished"
    assert point["short"] != first and point["short"] == short(point["fingerprint"])


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_a_plugin_term_and_the_refinement_iterations_are_rows_of_the_sweep_and_the_report(plugin_site, dataset,
                                                                                          checkpoint, tmp_path):
    from spread.experiments.sweep import read_results_csv
    from spread.reporting.tables import read_csv

    sweep = tmp_path / "sweep"
    args = [f"ckpt={checkpoint}", f"data.root={dataset}", "sampler.steps=4", "batch_size=2", "renders=0", "logger=none",
            *PUSHED[:-1], *CHEAP_EVALUATION, "num_cpus=2", "max_concurrent=2", f"out_dir={sweep}"]
    run_with_plugins(plugin_site, "spread-sweep", *args, "+guidance.terms.floor_push=0.3,0.6",
                     "guidance.iterations=1,2")
    rows = read_results_csv(sweep / "results.csv")
    assert sorted((r["guidance.floor_push"], r["guidance.iterations"]) for r in rows) == [
        (0.3, 1.0), (0.3, 2.0), (0.6, 1.0), (0.6, 2.0)]  # four identities, four rows
    assert all(r["status"] == "ok" and r["reused"] == "False" for r in rows)
    md = (sweep / "results.md").read_text()
    assert "| guidance.floor_push | guidance.iterations |" in md and "sampler=ddim-4" in md  # as in spread-report
    points = {p.name: json.loads((p / "point.json").read_text()) for p in (sweep / "points").iterdir()}
    assert sorted((v["fingerprint"]["guidance"]["floor_push"], v["fingerprint"]["guidance"]["iterations"])
                  for v in points.values()) == [(0.3, 1), (0.3, 2), (0.6, 1), (0.6, 2)]
    # re-launched with one weight changed and the iterations kept to one value: the changed weight's point is new
    # work; the other is the same setting spelled without its iterations dimension, re-used from its folder
    run_with_plugins(plugin_site, "spread-sweep", *args, "+guidance.terms.floor_push=0.3,0.9",
                     "guidance.iterations=1")
    reused = {r["guidance.floor_push"]: r["reused"] for r in read_results_csv(sweep / "results.csv")}
    assert reused == {0.3: "True", 0.9: "False"} and len(list((sweep / "points").iterdir())) == 5
    # spread-report over the sweep: one row per run, each naming its plugin weight and its iterations
    report = tmp_path / "report"
    run_with_plugins(plugin_site, "spread-report", f"runs={sweep / 'points'}", f"out_dir={report}")
    table = read_csv(report / "report.csv")
    assert sorted((r["guidance.floor_push"], r["guidance.iterations"]) for r in table) == [
        (0.3, 1), (0.3, 2), (0.6, 1), (0.6, 2), (0.9, 1)]
    assert len({r["identity"] for r in table}) == 5
    md = (report / "report.md").read_text()
    assert "| guidance.floor_push | guidance.iterations |" in md and "guidance.mode=refine" in md
    plots = sorted(p.name for p in (report / "plots").iterdir())
    assert "grecall_vs_floor_push.png" in plots and "grecall_vs_iterations.png" in plots


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_spread_ablate_redoes_the_guidance_row_when_a_plugin_terms_weight_changes(plugin_site, dataset, checkpoint,
                                                                                 tmp_path):
    out = tmp_path / "ablate"

    def ablate(weight: float):
        run_with_plugins(plugin_site, "spread-ablate", f"data.root={dataset}", f"out_dir={out}", "variants=[guidance]",
                         f"train.ckpt.geometry={checkpoint}", "recipe=null", "figures=false", "logger=none",
                         "stages.max_concurrent=1",
                         hydra_list("sample.overrides", "seed=0", *FAST_SAMPLE),
                         hydra_list("sample.guidance", *PUSHED, f"+guidance.terms.floor_push={weight}"),
                         hydra_list("evaluate.overrides", "seed=0", "logger=none", "metrics=[grecall]",
                                    "fid.enabled=false", "renders=0", "ray.num_cpus=1", "progress=false"))
        return json.loads((out / "ablation.json").read_text())["stages"]

    first = ablate(0.5)
    assert "redone_because" not in first["sample/guidance"]
    assert first["sample/guidance"]["inputs"]["guidance"]["floor_push"] == 0.5
    changed = ablate(0.7)
    assert changed["sample/guidance"]["redone_because"] == "changed: guidance.floor_push"
    assert changed["evaluate/guidance"]["redone_because"].startswith("changed: samples.fingerprint.guidance.floor_push")
    sampled = json.loads((out / "samples" / "guidance" / "sampling.json").read_text())
    assert sampled["fingerprint"]["guidance"]["floor_push"] == 0.7


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_a_plugin_method_is_a_row_of_spread_compare(plugin_site, dataset, tmp_path):
    from spread.data.stats import load_stats

    bounds = list(load_stats(dataset / "stats.json")["bounds_translations"])
    ckpt = tmp_path / "jitter.ckpt"
    torch.save({"hyper_parameters": {"method": "jitter_truth", "bounds": [float(b) for b in bounds], "sigma": 0.02},
                "state_dict": {"bounds": torch.tensor([float(b) for b in bounds])},
                "datamodule_hyper_parameters": {"num_points": 32, "seed": 0}}, ckpt)
    out = tmp_path / "compare"
    run_with_plugins(plugin_site, "spread-compare", f"data.root={dataset}", f"out_dir={out}", "methods=[jitter_truth]",
                     f"+train.ckpt.jitter_truth={ckpt}", "logger=none",
                     hydra_list("sample.overrides", "sampler=ddim50", "seed=0", "samples_per_graph=1", "workers=0",
                                "renders=0", "progress=false"),
                     hydra_list("evaluate.overrides", "seed=0", "logger=none", "protocol.stability_runs=1",
                                "fid.enabled=false", "renders=0", "ray.num_cpus=1", "progress=false"))
    from spread.reporting.tables import read_csv

    rows = read_csv(out / "table1.csv")
    assert [r["method_key"] for r in rows] == ["jitter_truth"] and rows[0]["status"] == "ok"
    assert rows[0]["method"] == "Jittered ground truth" and 0.5 < rows[0]["grecall"] <= 1.0


def test_the_metrics_order_is_the_same_whichever_metric_module_a_process_imports_first():
    """The default selection is part of an evaluation's fingerprint: Col_mesh, GRecall, ASD, Stability (then OOB),
    also in a process that imported Stability's and OOB's modules before any other."""
    code = ("import spread.metrics.out_of_bounds, spread.metrics.stability; "
            "from spread.metrics.registry import METRICS, default_metric_names; "
            "print(default_metric_names(), METRICS.names()[:5])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip() == ("['col_mesh', 'grecall', 'asd', 'stability'] "
                                  "['col_mesh', 'grecall', 'asd', 'stability', 'oob']")


def test_registries_list_the_built_ins_and_name_unknown_entries():
    from spread.methods.registry import method_names
    from spread.guidance.terms import term_names
    from spread.metrics.registry import METRICS, default_metric_names, selected_metrics
    from spread.registry import RegistryError

    assert default_metric_names() == ["col_mesh", "grecall", "asd", "stability"]
    assert {"col_mesh", "grecall", "asd", "stability", "oob"} <= set(METRICS.names())
    assert METRICS.get("asd").unit == "mm" and METRICS.get("asd").scale == 1000.0
    names = term_names()
    assert [n for n in names if n in ("collision", "gravity", "relation")] == ["collision", "gravity", "relation"]
    assert "box_iou" in names  # PhyScene's term, a built-in like SPREAD's three
    assert method_names()[:5] == ["atiss", "diffuscene", "physcene", "instructscene", "spread"]
    with pytest.raises(RegistryError, match="unknown metric 'nope'.*col_mesh"):
        selected_metrics(["nope"])
    with pytest.raises(RegistryError, match="named twice"):
        selected_metrics(["grecall", "grecall"])
    from spread.registry import resolve

    assert resolve("spread.metrics.out_of_bounds:OutOfBoundsRate") is METRICS.get("oob").metric
    assert resolve(len) is len
    with pytest.raises(RegistryError, match="'spread.metrics'"):
        resolve("spread.metrics")
