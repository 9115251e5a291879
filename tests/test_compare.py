"""spread-compare (Table 1): stages with fake commands (resume, the physcene row, a failing row), both table
layouts, the presets, and the quick preset's code path end to end with tiny models (one Ray session)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from spread.experiments.compare import METHODS, CompareSpec, run_comparison
from spread.reporting.tables import read_csv
from spread.io import file_sha256
from spread.scene import Scene, write_scene

from helpers import FAST_TRAIN, SMALL_MODEL, compose, make_dataset, user_error

CATEGORIES = ["bed", "nightstand", "sofa", "coffee_table", "armchair", "side_table", "lamp", "book", "cup", "bowl",
              "dining_table", "chair"]
ROOMS = {"g0": "bedroom", "g1": "bedroom", "g2": "livingroom"}


def args(overrides: list[str]) -> dict:
    return dict(o.split("=", 1) for o in overrides)


class FakeCommands:
    """Writes each command's outputs like the real one (checkpoints that torch can load, per-scene records with
    collision states), records the calls; ``fail`` names a method whose sampling raises."""

    def __init__(self, fail: str | None = None, source: str = "procedural"):
        self.calls: list[tuple[str, str, str | None]] = []
        self.fail, self.source = fail, source

    def generate(self, overrides):
        out = Path(args(overrides)["out_dir"])
        for scene_id, room in ROOMS.items():
            write_scene(Scene(scene_id, ["a"], ["c"], np.zeros((1, 3)), np.eye(3)[None], [[6]], [[0]],
                              extras={"room_type": np.asarray(room)}), out / "test" / f"{scene_id}.npz")
        (out / "manifest.json").write_text(json.dumps({"source": self.source}))
        self.calls.append(("generate", str(out), None))

    def train(self, overrides, run_dir):
        a = args(overrides)
        method = {"experiment=quick": "spread"}.get(f"experiment={a['experiment']}", a["experiment"])
        (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
        torch.save({"hyper_parameters": {} if method == "spread" else {"method": method}, "state_dict": {},
                    "run": str(run_dir)}, run_dir / "checkpoints" / "last.ckpt")
        (run_dir / "metrics.json").write_text(json.dumps({"global_step": 7}))
        self.calls.append(("train", run_dir.name, a["ckpt_path"]))

    def sample(self, overrides):
        from spread.io import file_sha256
        from spread.methods.registry import method_spec

        a = args(overrides)
        out = Path(a["out_dir"])
        self.calls.append(("sample", out.name, a["resume"]))
        if out.name == self.fail:
            raise RuntimeError(f"{out.name} exploded")
        (out / "scenes").mkdir(parents=True, exist_ok=True)
        for g in ROOMS:
            (out / "scenes" / f"{g}_k0.npz").write_bytes(b"x")
        guidance = guidance_config(a.get("guidance"))
        (out / "sampling.json").write_text(json.dumps(
            {"samples": 3, "fingerprint": {"ckpt_sha256": file_sha256(a["ckpt"]), "sampling": {"seed": a["seed"]}},
             # as the sampler records it: an own sampler's label (ATISS's), else the sampler's
             "sampler": method_spec(out.name).ignores.get("sampler", "ddim-50"), "guidance": guidance.fingerprint(), "guidance_label": guidance.label,
             "seconds_per_batch": 0.5, "batches_run": 2, "written_this_run": 3}))

    def evaluate(self, overrides):
        a = args(overrides)
        out = Path(a["out_dir"])
        out.mkdir(parents=True, exist_ok=True)
        index = METHODS.index(out.name)
        (out / "metrics.json").write_text(json.dumps(
            {"col_mesh": 0.5 - 0.1 * index, "grecall": 0.9, "asd": 0.01, "stability": 0.8, "fid": None,
             "n_scenes": 3,  # what it measured with, as the real command records it (one setting of it here)
             "evaluated_with": {"protocol": {"collision_threshold": float(a.get("protocol.collision_threshold",
                                                                                 0.01))}}}))
        # g0 (bedroom): 1 of 4 objects colliding; g1 (bedroom): index of 4; g2 (livingroom): 2 of 5
        colliding = {"g0": (1, 4), "g1": (index, 4), "g2": (2, 5)}
        lines = [json.dumps({"scene_id": f"{g}_k0", "error": None,
                             "state": {"col_mesh": {"colliding_objects": c, "objects": n},
                                       "grecall": {"matches": 9, "pairs": 10},
                                       "asd": {"abs_distance_sum": 0.01, "pairs": 1},
                                       "stability": {"unchanged_pairs": 8, "pairs": 10, "still_objects": n,
                                                     "objects": n, "displacement_ok": n, "rotation_ok": n}}})
                 for g, (c, n) in colliding.items()]
        (out / "per_scene.jsonl").write_text("\n".join(lines) + "\n")
        self.calls.append(("evaluate", out.name, a["resume"]))
        return {}


def guidance_config(preset: str | None):
    """The typed guidance of ``guidance=<preset>`` (None: unguided), as spread-sample parses it."""
    from spread.configs import to_object

    return to_object(compose("sample", "ckpt=x", "data.root=x", "out_dir=x", f"guidance={preset or 'none'}")).guidance


def spec(tmp_path: Path, **kw) -> CompareSpec:
    defaults = dict(out_dir=tmp_path / "cmp", train=["seed=0"], generate=["rooms=4"], sample=["seed=0"],
                    evaluate=["seed=0"],
                    train_method={"atiss": ["experiment=atiss"], "diffuscene": ["experiment=diffuscene"],
                                  "instructscene": ["experiment=instructscene"], "spread": ["experiment=quick"]},
                    sample_method={"spread": ["guidance=refine"]})
    return CompareSpec(**{**defaults, **kw})


def test_comparison_runs_every_method_and_resumes_stage_by_stage(tmp_path):
    commands = FakeCommands()
    first = run_comparison(spec(tmp_path), commands)
    assert first.ok, first.errors
    assert [c[0] for c in commands.calls] == ["generate", *["train"] * 4, *["sample"] * 5, *["evaluate"] * 5]
    assert [c[1] for c in commands.calls if c[0] == "train"] == ["atiss", "diffuscene", "instructscene", "spread"]
    out = tmp_path / "cmp"
    # physcene: DiffuScene's checkpoint (no derived file, no training) with its registered guidance preset
    physcene = json.loads((out / "samples" / "physcene" / "sampling.json").read_text())
    assert physcene["fingerprint"]["ckpt_sha256"] == file_sha256(out / "train" / "diffuscene" / "checkpoints" / "last.ckpt")
    assert physcene["guidance"]["box_iou"] == 0.15 and not (out / "train" / "physcene.ckpt").exists()
    assert "collision" not in physcene["guidance"]  # SPREAD's terms do not act: not part of its identity
    rows = {r["method_key"]: r for r in first.records}
    assert list(rows) == list(METHODS) and first.layout == "procthor"
    assert [rows[m]["grecall"] for m in METHODS] == [None, None, None, 0.9, 0.9]  # only graph-conditioned
    assert rows["atiss"]["grecall_measured"] == 0.9 and rows["atiss"]["seconds_per_scene"] == pytest.approx(1 / 3)
    assert rows["spread"]["sampler"] == "ddim-50 + guidance refine(collision=0.0075,gravity=0.001,relation=0.001)"
    assert rows["atiss"]["sampler"] == "one pass per object" and rows["physcene"]["train_steps"] == 7
    assert rows["physcene"]["sampler"] == "ddim-50 + guidance sample(box_iou=0.15,last_steps=10,grad_clip=0.1)"
    csv = {r["method_key"]: r for r in read_csv(out / "table1.csv")}
    assert csv["diffuscene"]["col_mesh"] == pytest.approx(0.4) and csv["diffuscene"]["grecall"] is None
    md = (out / "table1.md").read_text()
    assert "GRecall ↑" in md and "| ATISS | – |" in md and "Budget:" in md and "7 training steps" in md
    # every cell with its bootstrap interval over the three scenes; none for a GRecall the table leaves out
    assert rows["atiss"]["grecall_lo"] is None and rows["spread"]["grecall_lo"] == rows["spread"]["grecall_hi"] == 0.9
    lo, hi = rows["atiss"]["col_mesh_lo"], rows["atiss"]["col_mesh_hi"]  # per scene 1/4, 0/4, 2/5
    assert 0.0 <= lo < 3 / 13 < hi <= 2 / 5 and "±" in md and csv["atiss"]["ci_seed"] == 0

    commands.calls.clear()  # everything finished: nothing runs
    again = run_comparison(spec(tmp_path), commands)
    assert commands.calls == [] and set(again.stages.values()) == {"skipped"}, again.stages

    (out / "train" / "atiss" / "metrics.json").unlink()  # interrupted training: continue from last.ckpt
    commands.calls.clear()
    run_comparison(spec(tmp_path), commands)
    assert commands.calls == [("train", "atiss", str(out / "train" / "atiss" / "checkpoints" / "last.ckpt"))]

    torch.save({"hyper_parameters": {"method": "diffuscene"}, "state_dict": {}, "run": "retrained"},
               out / "train" / "diffuscene" / "checkpoints" / "last.ckpt")
    commands.calls.clear()
    run_comparison(spec(tmp_path), commands)  # new DiffuScene weights: both its rows are redone, nothing else
    assert commands.calls == [("sample", "diffuscene", "false"), ("sample", "physcene", "false"),
                              ("evaluate", "diffuscene", "false"), ("evaluate", "physcene", "false")]

    # relaunched with another training recipe for one method: refused before any stage, Table 1 as it was
    table = (out / "table1.csv").read_bytes()
    commands.calls.clear()
    other = {**spec(tmp_path).train_method, "atiss": ["experiment=atiss", "trainer.max_steps=3"]}
    with pytest.raises(ValueError, match=f"train/atiss: {out / 'train' / 'atiss'}: made with other settings"):
        run_comparison(spec(tmp_path, train_method=other), commands)
    assert commands.calls == [] and (out / "table1.csv").read_bytes() == table


def test_a_rerun_with_some_methods_keeps_the_other_finished_rows_of_table1(tmp_path):
    """Every method, then ``methods=[atiss]`` alone: Table 1 keeps the other four rows (marked carried over, a
    note line names them) in the registry's order, and its numbers."""
    run_comparison(spec(tmp_path), FakeCommands())
    before = read_csv(tmp_path / "cmp" / "table1.csv")
    commands = FakeCommands()
    again = run_comparison(spec(tmp_path, methods=("atiss",)), commands)
    assert again.ok and [c[0] for c in commands.calls] == []  # atiss finished earlier: skipped
    rows = read_csv(tmp_path / "cmp" / "table1.csv")
    assert [r["method_key"] for r in rows] == list(METHODS) == [r["method_key"] for r in again.records]
    assert [r["method_key"] for r in rows if r["carried_from"]] == ["diffuscene", "physcene", "instructscene", "spread"]
    assert [r["col_mesh"] for r in rows] == [r["col_mesh"] for r in before]
    md = (tmp_path / "cmp" / "table1.md").read_text()
    assert "Rows carried over from an earlier run of this folder" in md and "InstructScene" in md
    assert "not measured alike" not in md
    # ATISS re-evaluated under another protocol beside rows carried from the first: named under the table, not
    # only in the CSV
    again = run_comparison(spec(tmp_path, methods=("atiss",), evaluate=["seed=0", "protocol.collision_threshold=0.02"]),
                           commands)
    assert again.ok and commands.calls == [("evaluate", "atiss", "false")]
    md, tex = ((tmp_path / "cmp" / f"table1.{s}").read_text() for s in ("md", "tex"))
    line = ("The rows were not measured alike: they differ in protocol.collision_threshold (ATISS: "
            "protocol.collision_threshold=0.02; DiffuScene: protocol.collision_threshold=0.01;")
    assert line in md and "protocol.collision\\_threshold" in tex, md


def test_a_failing_method_blocks_only_its_row(tmp_path):
    result = run_comparison(spec(tmp_path), FakeCommands(fail="instructscene"))
    assert not result.ok and result.stages["sample/instructscene"] == "failed"
    assert result.stages["evaluate/instructscene"] == "blocked" and result.stages["evaluate/spread"] == "done"
    row = {r["method_key"]: r for r in result.records}["instructscene"]
    assert row["col_mesh"] is None and "exploded" in row["status"] and result.tables["md"].exists()


def test_threedfront_layout_shows_col_mesh_per_room_type(tmp_path):
    result = run_comparison(spec(tmp_path, methods=("atiss", "spread")), FakeCommands(source="3D-FRONT import"))
    assert result.ok and result.layout == "threedfront"
    rows = {r["method_key"]: r for r in result.records}
    assert rows["atiss"]["col_mesh/bedroom"] == pytest.approx(1 / 8)  # atiss is method 0: (1 + 0) / 8
    assert rows["spread"]["col_mesh/bedroom"] == pytest.approx(5 / 8) and rows["spread"]["col_mesh/livingroom"] == 0.4
    header = result.tables["md"].read_text().splitlines()[2]
    assert "Col_mesh bedroom" in header and "Col_mesh livingroom" in header and "GRecall" not in header
    assert "FID" in header and "s / scene" in header
    tex = result.tables["tex"].read_text()
    assert r"Col$_{\text{mesh}}$ bedroom$\downarrow$" in tex and r"\label{tab:table1}" in tex


def test_table_is_logged_to_wandb_offline(tmp_path, monkeypatch):
    from spread.experiments.compare import log_table1
    from spread.tracking.loggers import LoggerConfig

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    logged = []

    def log_table(records, columns):
        logged.append(log_table1(records, columns, tmp_path / "cmp", LoggerConfig(name="wandb", mode="offline"), name="table1/test"))

    result = run_comparison(spec(tmp_path, methods=("atiss", "spread")), FakeCommands(), log_table)
    assert result.ok and len(logged) == 1
    runs = list((tmp_path / "cmp" / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("*.wandb"))
    again = run_comparison(spec(tmp_path, methods=("atiss", "spread")), FakeCommands(), log_table)
    assert again.stages["table"] == "skipped" and len(logged) == 2  # a relaunch's tracker run shows the table too


def test_bad_specs_name_the_key(tmp_path):
    with pytest.raises(ValueError, match="methods: unknown"):
        spec(tmp_path, methods=("atiss", "gaussians"))
    with pytest.raises(ValueError, match="train.ckpt.physcene"):
        spec(tmp_path, ckpt={"physcene": None})
    with pytest.raises(FileNotFoundError, match="train.ckpt.atiss="):
        spec(tmp_path, ckpt={"atiss": str(tmp_path / "missing.ckpt")})
    with pytest.raises(ValueError, match="layout"):
        spec(tmp_path, layout="wide")


def test_presets_compose_with_one_sampler_for_every_method():
    from spread.commands.compare import compare_spec

    for preset in ("quick", "paper"):
        s = compare_spec(compose("compare", f"+table1={preset}", "data.root=/d", "out_dir=/o"))
        assert s.methods == METHODS and set(s.train_method) == {"atiss", "diffuscene", "instructscene", "spread"}
        assert any(o.startswith("sampler=") for o in s.sample)  # one sampler for all, in the shared list
        assert not any(o.startswith("sampler") for m in METHODS for o in s.sample_method.get(m, []))
        assert s.sample_method["spread"][0] == "guidance=refine" and s.sample_method["physcene"] == ["guidance=physcene"]
    quick = compare_spec(compose("compare", "+table1=quick", "data.root=/d", "out_dir=/o"))
    assert quick.train_method["atiss"] == ["experiment=atiss_quick"] and "sampler=ddim50" in quick.sample
    # the recipes live once, in the registry: the presets name none of them (paper's SPREAD adds its epochs)
    from spread.methods.registry import method_spec

    full = compare_spec(compose("compare", "data.root=/d", "out_dir=/o"))
    assert all(full.train_method[m] == list(method_spec(m).train) for m in full.train_method)
    assert all(quick.train_method[m] == list(method_spec(m).train_quick) for m in quick.train_method)
    assert full.sample_method["spread"] == ["guidance=refine"] and quick.sample_method["spread"][0] == "guidance=refine"
    own = compare_spec(compose("compare", "data.root=/d", "out_dir=/o", "+train.atiss=['experiment=atiss_quick']"))
    assert own.train_method["atiss"] == ["experiment=atiss_quick"]


# ---- end to end -----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_comparison(tmp_path_factory):
    """The quick preset's code path on 12 generated rooms (3 test graphs), a few training steps per method,
    every evaluation in one Ray session (spread.runtime.ray uses a caller's Ray as is)."""
    import ray

    from omegaconf import open_dict

    from spread.methods.registry import method_spec
    from spread.commands.compare import compare

    torch.set_num_threads(1)
    data = make_dataset(tmp_path_factory.mktemp("cmpdata"), categories=CATEGORIES)
    out = tmp_path_factory.mktemp("compare") / "quick"
    cfg = compose("compare", "+table1=quick", f"data.root={data}", f"out_dir={out}", "logger=none")
    cfg.train.extra = [*FAST_TRAIN, "trainer.max_steps=3", "trainer.max_time=null"]
    with open_dict(cfg):  # the spread recipe of the quick preset (its registered train_quick), shrunk further
        cfg.train.spread = [*method_spec("spread").recipe("quick"), *SMALL_MODEL]
    cfg.sample.extra = ["sampler.steps=4", "progress=false", "renders=1", "batch_size=2"]
    cfg.sample.spread = [*cfg.sample.spread, "guidance.iterations=4"]
    cfg.evaluate.extra = ["protocol.stability_runs=1", "fid.enabled=false", "renders=0", "progress=false"]
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        started = time.perf_counter()
        result = compare(cfg)
        seconds = time.perf_counter() - started
        again_started = time.perf_counter()
        again = compare(cfg)
        again_seconds = time.perf_counter() - again_started
    finally:
        ray.shutdown()
    return {"result": result, "again": again, "out": out, "seconds": seconds, "again_seconds": again_seconds}


def test_tiny_comparison_end_to_end_and_resume(tiny_comparison):
    result, out = tiny_comparison["result"], tiny_comparison["out"]
    assert result.ok, result.errors
    rows = {r["method_key"]: r for r in result.records}
    assert list(rows) == list(METHODS) and result.layout == "procthor"
    for m, r in rows.items():
        assert r["n_scenes"] == 3 and 0.0 <= r["col_mesh"] <= 1.0 and 0.0 <= r["stability"] <= 1.0, (m, r)
        assert r["seconds_per_scene"] > 0 and r["train_steps"] == 3 and r["sample_cpu_s"] > 0
        assert (r["grecall"] is None) == (m in ("atiss", "diffuscene", "physcene"))
    assert rows["atiss"]["model_size"] == "tiny" and rows["spread"]["sampler"].startswith("ddim-4 + guidance refine(")
    # same graphs and seeds for every method; physcene samples DiffuScene's weights with guidance
    names = [sorted(p.name for p in (out / "samples" / m / "scenes").glob("*.npz")) for m in METHODS]
    assert all(n == names[0] for n in names) and len(names[0]) == 3
    seeds = {json.loads((out / "samples" / m / "sampling.json").read_text())["fingerprint"]["sampling"]["seed"]
             for m in METHODS}
    assert seeds == {0}
    physcene = json.loads((out / "samples" / "physcene" / "sampling.json").read_text())
    assert physcene["fingerprint"]["ckpt_sha256"] == file_sha256(out / "train" / "diffuscene" / "checkpoints" / "last.ckpt")
    assert physcene["guidance"]["mode"] == "sample" and physcene["guidance"]["box_iou"] == 0.15
    assert physcene["guidance_totals"]["steps"] > 0  # PhyScene's term stepped DiffuScene's samples
    table = read_csv(out / "table1.csv")
    assert [r["method_key"] for r in table] == list(METHODS)
    assert "InstructScene (graph-to-layout)" in (out / "table1.md").read_text()
    again = tiny_comparison["again"]  # the second run skips every stage and rewrites nothing
    assert again.stages.pop("data") == "given" and set(again.stages.values()) == {"skipped"}, again.stages
    assert again.records == result.records and tiny_comparison["again_seconds"] < 30


def test_a_method_without_a_training_recipe_needs_its_checkpoint_given(tmp_path):
    from spread.experiments.compare import CompareSpec, trained_methods

    assert "release" not in trained_methods()  # the authors' weights: converted, never trained here
    with pytest.raises(ValueError, match=r"'release' is not trained here.*\+train\.ckpt\.release="):
        CompareSpec(out_dir=tmp_path, methods=("release",))
    import torch

    given = tmp_path / "release.ckpt"
    torch.save({"hyper_parameters": {"method": "release"}, "state_dict": {}}, given)
    assert CompareSpec(out_dir=tmp_path, methods=("release",), ckpt={"release": str(given)}).trained() == ["release"]


@pytest.mark.parametrize("recipe", ["full", "quick"])
def test_every_trained_methods_registered_recipe_composes_a_model_of_that_method(recipe):
    """A test over every method: each registered recipe composes with ``conf/train.yaml`` to its own method's model
    (the checkpoint's ``method``), SPREAD's to +Geometry. (The full recipe named ``experiment=geometry`` after the
    file became ``paper_geometry``: ``spread-compare +table1=paper`` failed at SPREAD's training stage, after the
    baselines had trained.)"""
    from spread.experiments.compare import spec_of, trained_methods
    from spread.methods.loading import trained_identity

    assert {"atiss", "diffuscene", "instructscene", "spread"} <= set(trained_methods())
    for method in trained_methods():
        cfg = compose("train", *spec_of(method).recipe(recipe), "data.root=/d", "out_dir=/o")
        held = trained_identity(cfg.model)
        assert held["method"] == method, (method, recipe, held)
        if method == "spread":
            assert held["variant"] == "geometry"


def test_a_trained_method_whose_list_composes_another_model_is_refused_before_any_stage(tmp_path):
    """``+train.<m>`` replaces a method's recipe; a list that composes another method's model (here SPREAD's quick
    experiment under DiffuScene's name) would train it and fill DiffuScene's row. Refused in one line naming the
    list before anything is generated or trained — the script as users type it, and the library for SPREAD's row
    given DiffuScene's model; a row with a given checkpoint is not asked."""
    from spread.commands.compare import compare_spec
    from spread.experiments.compare import Comparison

    last, _ = user_error("spread-compare", "+table1=quick", f"data.root={tmp_path / 'data'}",
                         f"out_dir={tmp_path / 'cmp'}", "methods=[diffuscene]", "logger=none",
                         '+train.diffuscene=["experiment=quick"]')
    assert last.startswith("spread-compare: train.diffuscene: the DiffuScene row trains method=diffuscene"), last
    assert "compose method=spread" in last
    assert not (tmp_path / "data").exists() and not (tmp_path / "cmp" / "train").exists()
    spec = compare_spec(compose("compare", "+table1=quick", f"data.root={tmp_path / 'data'}",
                                f"out_dir={tmp_path / 'cmp'}", "methods=[spread]", '+train.spread=["model=diffuscene"]'))
    with pytest.raises(ValueError, match=r"^train\.spread: the SPREAD \(ours\) row trains method=spread, but .*"
                                         r"compose method=diffuscene"):
        Comparison(spec, commands=None)
    spec.ckpt["spread"] = str(tmp_path / "given.ckpt")  # a given checkpoint is not trained: its list is not asked
    Comparison(spec, commands=None)
