"""Hostile inputs, round 6: the scene viewer and the release converter (docs/robustness.md).

* ``spread-view``: text from data files (category names, scene ids, file names) reaches the browser as text, never
  as markup (viser sets the legend as inner HTML and renders the caption as markdown with raw HTML);
* ``spread-view``: a run folder whose ``sampling.json`` record is damaged is refused naming the file and the key;
* ``spread-release-ckpt``: an ``out=`` that is the authors' checkpoint (any spelling) or a folder, and a ``model.*``
  setting the network cannot be built with, are refused in one line before anything is written.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from helpers import free_port, scene_of, user_error

HOSTILE_CATEGORY = "<img src=x onerror=alert(1)>"
HOSTILE_ID = "<script>alert(1)</script>"


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> Path:
    """A 2-asset library (book_00, mug_00): what the viewer needs to pose and colour a scene."""
    from spread.assets.build import build_library

    root = tmp_path_factory.mktemp("r6lib") / "assets"
    build_library(root, categories=["mug", "book"], variants=1, processes=1, progress=False, caches=False)
    return root


def write_run(root: Path, library: Path, fingerprint) -> Path:
    """A sampling run folder: ``scenes/g_k0.npz`` (conditioned on graph ``g``), ``sampling.json`` with
    ``fingerprint``, and the dataset it names (``data/test/g.npz``)."""
    from spread.assets import AssetLibrary
    from spread.scene import write_scene

    lib = AssetLibrary.load(library)
    ids = sorted(lib)
    poses = np.array([[0.0, 0.05, 0.0], [0.4, 0.05, 0.0]])
    write_scene(scene_of(ids, poses, library=lib, scene_id="g_k0"), root / "run" / "scenes" / "g_k0.npz")
    write_scene(scene_of(ids, poses, library=lib, scene_id=HOSTILE_ID), root / "data" / "test" / "g.npz")
    (root / "run" / "sampling.json").write_text(json.dumps({"fingerprint": fingerprint}))
    return root / "run"


def test_category_names_scene_ids_and_file_names_reach_the_viewer_panel_as_text_not_markup(library, tmp_path):
    """High: a scene file whose category was ``<img src=x onerror=...>`` ran script in the browser of whoever viewed
    it (the legend is set as inner HTML); the caption took the file name and scene id as markdown. Variants: a
    markdown link and emphasis in the file name, the ground truth's scene id."""
    from spread.assets import AssetLibrary
    from spread.render.viewer import SceneViewer, collect
    from spread.scene import write_scene

    run = write_run(tmp_path, library, {"data_root": str(tmp_path / "data"), "split": "test"})
    lib = AssetLibrary.load(library)
    hostile = scene_of(sorted(lib), np.array([[0.0, 0.05, 0.0], [0.4, 0.05, 0.0]]), library=lib,
                       categories=[HOSTILE_CATEGORY, "dining_table"], scene_id=HOSTILE_ID)
    write_scene(hostile, run / "scenes" / "x<b>_[a](javascript:alert(1))_k0.npz")
    items, root = collect(run, library)
    viewer = SceneViewer(items, root, port=free_port())
    try:
        shown = {}
        for item in items:
            viewer.pick.value = item.name  # shows it
            shown[item.name] = viewer.info.content, viewer.legend.content
    finally:
        viewer.server.stop()
    info, legend = shown["x<b>_[a](javascript:alert(1))_k0"]
    assert "&lt;img src=x onerror=alert(1)&gt;" in legend and "dining_table" in legend
    assert "<img" not in legend and "<script" not in info and "<b>" not in info and "](javascript" not in info
    assert "&lt;script&gt;" in info and "x&lt;b&gt;" in info  # escaped, still shown
    truth_info, truth_legend = shown["g_k0"]
    assert "ground truth beside it: &lt;script&gt;" in truth_info and "<script" not in truth_info
    assert "book" in truth_legend and "mug" in truth_legend


@pytest.mark.parametrize("text", [HOSTILE_CATEGORY, HOSTILE_ID, "**bold** _em_ [a](javascript:alert(1)) `c`",
                                  "# heading", "{alert(1)} $x$ | a | b |", "dining_table & 'chair' \"3\"",
                                  "two\nlines  <b>x</b>", r"back\slash \* \<"])
def test_text_from_a_data_file_renders_in_markdown_as_exactly_that_text(text):
    """The caption's escape, checked with a CommonMark renderer that passes raw HTML (as viser's does): the page
    shows the text itself (white space as one space) inside one paragraph, and no tag, link or emphasis of its own."""
    import html

    markdown_it = pytest.importorskip("markdown_it")
    from spread.render.viewer import markdown_text

    rendered = markdown_it.MarkdownIt("commonmark", {"html": True}).render(f"scene {markdown_text(text)}").strip()
    assert rendered.startswith("<p>") and rendered.endswith("</p>")
    inner = rendered[3:-4]
    assert "<" not in inner and ">" not in inner, rendered  # no element of its own
    assert html.unescape(inner) == "scene " + " ".join(text.split())


@pytest.mark.parametrize("fingerprint, words", [
    ([1], "'fingerprint' holds list"),
    ({"data_root": 5, "split": "test"}, "'fingerprint.data_root' holds int 5"),
    ({"data_root": "/d", "split": 3}, "'fingerprint.split' holds int 3"),
    ({"data_root": "/d", "split": "../../etc"}, "'fingerprint.split' holds '../../etc'"),
])
def test_a_run_folder_whose_sampling_record_is_damaged_is_refused_naming_the_file_and_key(library, tmp_path,
                                                                                          fingerprint, words):
    """Low: ``{"fingerprint": [1]}`` in sampling.json ended spread-view in an AttributeError, ``"data_root": 5`` and
    ``"split": 3`` in a TypeError. Variant: a split that leaves the dataset folder."""
    from spread.render.viewer import collect

    run = write_run(tmp_path, library, fingerprint)
    with pytest.raises(ValueError, match=re.escape(f"{run / 'sampling.json'}: {words}")):
        collect(run, library)


def test_spread_view_refuses_a_damaged_sampling_record_in_one_line_and_shows_a_run_without_one(library, tmp_path):
    from spread.render.viewer import collect

    run = write_run(tmp_path, library, {"data_root": 5})
    line, _ = user_error("spread-view", str(run), f"assets={library}", f"port={free_port()}")
    assert f"{run / 'sampling.json'}: 'fingerprint.data_root' holds int 5" in line
    (run / "sampling.json").write_text(json.dumps({"fingerprint": {"data_root": None, "split": None}}))
    items, _ = collect(run, library)  # a record without a dataset: the scenes, no ground truth
    assert [(i.name, i.ground_truth) for i in items] == [("g_k0", None)]
    (run / "sampling.json").write_text(json.dumps({"fingerprint": {"data_root": str(tmp_path / "data"),
                                                                   "split": "test"}}))
    assert collect(run, library)[0][0].ground_truth == tmp_path / "data" / "test" / "g.npz"


def test_a_runs_scenes_folder_or_one_scene_file_is_shown_with_its_runs_dataset_as_spread_export_finds_it(library,
                                                                                                     tmp_path):
    """``spread-view <run>/scenes`` (or one file there) finds the dataset the run's ``sampling.json`` names: its
    asset library and the ground truth (before: "no asset library … give assets=DIR", where spread-export worked)."""
    import shutil

    from spread.render.viewer import collect

    run = write_run(tmp_path, library, {"data_root": str(tmp_path / "data"), "split": "test"})
    shutil.copytree(library, tmp_path / "data" / "assets")
    for given in (run / "scenes", run / "scenes" / "g_k0.npz"):
        items, found = collect(given)
        assert found == tmp_path / "data" / "assets", given
        assert [(i.name, i.ground_truth) for i in items] == [("g_k0", tmp_path / "data" / "test" / "g.npz")], given


def test_spread_view_leaves_out_a_scene_that_does_not_read_and_a_conditioned_on_that_is_not_a_file_name(
        library, tmp_path):
    """Before: a scene with a NaN pose first in the folder ended spread-view in a 29-line traceback; a 300-character
    ``conditioned_on`` in an OSError (file name too long), and ``../x`` read ground truth outside the split."""
    from spread.render.viewer import collect, ground_truth_id
    from spread.safe_load import load_npz

    run = write_run(tmp_path, library, {"data_root": str(tmp_path / "data"), "split": "test"})
    with load_npz(run / "scenes" / "g_k0.npz") as data:
        arrays = {k: data[k] for k in data.files}
    np.savez(run / "scenes" / "a_bad.npz", **{**arrays, "translation": np.full_like(arrays["translation"], np.nan)})
    np.savez(run / "scenes" / "h_k0.npz", **{**arrays, "conditioned_on": np.asarray("x" * 300)})
    np.savez(run / "scenes" / "u_k0.npz", **{**arrays, "conditioned_on": np.asarray("../test/g")})
    refused: list[str] = []
    items, _ = collect(run, library, refused)
    assert [i.name for i in items] == ["g_k0", "h_k0", "u_k0"] and len(refused) == 1
    assert "a_bad.npz" in refused[0] and "translation" in refused[0]
    assert ground_truth_id(run / "scenes" / "u_k0.npz") == "u"  # not a path: the name's own graph
    assert [i.ground_truth for i in items] == [tmp_path / "data" / "test" / "g.npz", None, None]


# ---- spread-release-ckpt ----------------------------------------------------------------------------------------

@pytest.fixture
def release(tmp_path) -> Path:
    """The authors' ``ckpt.pth`` (the reduced-size fixture weights in the release's format)."""
    from test_release_checkpoint import network_fixture, release_ckpt

    _, weights, keys, _ = network_fixture()
    (tmp_path / "authors").mkdir()
    return release_ckpt(tmp_path / "authors" / "ckpt.pth", weights, keys)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def files_under(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.mark.parametrize("case", ["out_is_ckpt_by_link", "out_is_folder", "unknown_key", "nan_bounds"])
def test_spread_release_ckpt_refuses_an_out_that_is_the_checkpoint_or_a_folder_and_bad_model_settings(
        release, tmp_path, case):
    """High: ``out=`` the checkpoint itself (here through a symbolic link) replaced the authors' weights with the
    converted ones; low: ``out=`` a folder ended in an IsADirectoryError traceback, ``model.config.foo=1`` in 61
    lines of Hydra's, ``model.bounds=[nan,...]`` in a ValueError traceback. One line, nothing written."""
    (tmp_path / "link.pth").symlink_to(release)
    (tmp_path / "folder").mkdir()
    args, words = {
        "out_is_ckpt_by_link": ([f"out={tmp_path / 'link.pth'}"],
                                f"out={tmp_path / 'link.pth'} is the checkpoint being converted (ckpt={release})"),
        "out_is_folder": ([f"out={tmp_path / 'folder'}"], f"out={tmp_path / 'folder'}: is a folder"),
        "unknown_key": ([f"out={tmp_path / 'r.ckpt'}", "model.config.foo=1"],
                        "model.config.foo=1: the release's network has no setting 'foo' (known: attn_dim,"),
        "nan_bounds": ([f"out={tmp_path / 'r.ckpt'}", "model.bounds=[nan,0,0,1,1,1]"],
                       "model.bounds=[nan,0,0,1,1,1]: expected 6 finite numbers"),
    }[case]
    before, listed = digest(release), files_under(tmp_path)
    line, _ = user_error("spread-release-ckpt", f"ckpt={release}", *args)
    assert words in line, line
    assert digest(release) == before and files_under(tmp_path) == listed


def refused(argv: list[str]) -> str:
    """The one-line refusal of ``spread-release-ckpt``'s main for ``argv``, in this process."""
    from spread.cli.release_ckpt import main

    with pytest.raises(SystemExit) as stop:
        main(argv)
    message = str(stop.value.code)
    assert stop.value.code not in (0, None) and "\n" not in message and message.startswith("spread-release-ckpt: ")
    return message


def test_spread_release_ckpt_refuses_every_spelling_of_its_checkpoint_and_each_bad_value_by_key(release, tmp_path,
                                                                                                monkeypatch):
    """Variants in process: ``..`` and a hard link for the checkpoint, a path through a file; ``model.bounds=abc``,
    ``model.config.attn_dim=abc`` (a TypeError traceback), a negative width, a dropout of 2, heads that do not divide
    the width, an unknown top-level key, an override that does not parse. A new out= beside them converts."""
    from test_release_checkpoint import network_fixture

    for name in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG"):  # as a user runs it (tests/conftest.py sets the first)
        monkeypatch.delenv(name, raising=False)
    from test_release_sampling import network_overrides

    config = network_fixture()[0]
    sized = network_overrides(config)
    os.link(release, tmp_path / "hard.pth")
    (tmp_path / "a_file").write_text("x")
    before, listed = digest(release), files_under(tmp_path)
    dotted = f"{release.parent}/../{release.parent.name}/ckpt.pth"
    cases = {
        f"out={dotted}": f"out={dotted} is the checkpoint being converted",
        f"out={tmp_path / 'hard.pth'}": "is the checkpoint being converted",
        f"out={tmp_path / 'a_file' / 'r.ckpt'}": f"{tmp_path / 'a_file'} is not a folder",
        "model.bounds=abc": "model.bounds=abc: expected 6 finite numbers",
        "model.config.attn_dim=abc": "model.config.attn_dim=abc: expected a whole number ≥ 1",
        "model.config.attn_dim=-8": "model.config.attn_dim=-8: expected a whole number ≥ 1",
        "model.config.dropout=2": "model.config.dropout=2: expected a number in [0, 1)",
        "model.config.n_heads=5": "model.config.n_heads=5 does not divide model.config.attn_dim=32",
        "model.colour=1": "model.colour=1: the release's model has no key 'colour'",
        "model.bounds=[1,2": "model.bounds=[1,2: no viable alternative",
    }
    for arg, words in cases.items():
        out = [] if arg.startswith("out=") else [f"out={tmp_path / 'r.ckpt'}"]
        assert words in refused([f"ckpt={release}", *sized, *out, arg]), arg
        if arg in ("model.bounds=abc", "model.config.attn_dim=abc"):  # without out= (only checking the file) too
            assert words in refused([f"ckpt={release}", *sized, arg]), arg
    assert digest(release) == before and files_under(tmp_path) == listed
    from spread.cli.release_ckpt import main

    main([f"ckpt={release}", *sized, f"out={tmp_path / 'new' / 'r.ckpt'}"])  # the same, well set: converted
    assert (tmp_path / "new" / "r.ckpt").is_file() and digest(release) == before


def test_spread_view_help_prints_its_usage():
    """``spread-view --help`` answered "--help: no such file or folder"."""
    import subprocess

    from helpers import SCRIPTS

    for flag in ("--help", "-h"):
        proc = subprocess.run([str(SCRIPTS / "spread-view"), flag], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0 and proc.stdout.startswith("``spread-view PATH [assets=DIR]"), proc.stderr


def test_spread_view_leaves_out_names_and_meshes_it_cannot_show_and_a_timeline_that_is_no_timeline(library, tmp_path):
    """Found by a review: a text-typed trajectory ended the viewer at start-up, one over fewer objects failed its
    slider (and took the scene off the view); a truncated mesh and a damaged ground-truth file ended it in a
    traceback; a file name or category that is not valid UTF-8 closed every browser connection or ended it."""
    import shutil

    from spread.render.viewer import collect, scene_timeline
    from spread.safe_load import load_npz
    from spread.scene import SceneFormatError, read_scene

    run = write_run(tmp_path, library, {"data_root": str(tmp_path / "data"), "split": "test"})
    scenes = run / "scenes"
    with load_npz(scenes / "g_k0.npz") as data:
        arrays = {k: data[k] for k in data.files}
    k, n = 3, len(arrays["asset_id"])
    moves = np.repeat(arrays["translation"][None], k, axis=0)
    turns = np.repeat(arrays["rotation"][None], k, axis=0)
    np.savez(scenes / "t_good.npz", **arrays, trajectory_translation=moves, trajectory_rotation=turns)
    np.savez(scenes / "t_text.npz", **arrays, trajectory_translation=np.full(moves.shape, "x"),
             trajectory_rotation=turns)
    np.savez(scenes / "t_fewer.npz", **arrays, trajectory_translation=moves[:, :1], trajectory_rotation=turns[:, :1])
    np.savez(scenes / "c_surrogate.npz", **{**arrays, "category": np.array(["mug\udcff"] * n)})
    shutil.copy(scenes / "g_k0.npz", scenes / "bad\udcff.npz")
    assert [len(scene_timeline(read_scene(scenes / f"t_{x}.npz"))) for x in ("good", "text", "fewer")] == [k, 0, 0]
    with pytest.raises(SceneFormatError, match="category.*not valid text"):
        read_scene(scenes / "c_surrogate.npz")
    refused: list[str] = []
    items, _ = collect(run, library, refused)
    assert sorted(i.name for i in items) == ["g_k0", "t_fewer", "t_good", "t_text"]
    assert len(refused) == 2, refused
    assert any("c_surrogate.npz" in r and "not valid text" in r for r in refused), refused
    assert any("bad" in r and "its name is not valid text (UTF-8)" in r for r in refused), refused
    assert next(i for i in items if i.name == "g_k0").ground_truth == tmp_path / "data" / "test" / "g.npz"
    (tmp_path / "data" / "test" / "g.npz").write_bytes(b"PK\x03\x04 damaged")  # the ground truth
    items, _ = collect(run, library, [])
    assert next(i for i in items if i.name == "g_k0").ground_truth is None  # shown as not known
    copy = tmp_path / "lib2"
    shutil.copytree(library, copy)
    mesh = next((copy / "meshes").glob("mug*"))
    mesh.write_bytes(mesh.read_bytes()[:-7])
    refused = []
    with pytest.raises(FileNotFoundError, match="no scene here reads as a valid scene"):
        collect(run, copy, refused)  # every scene shows the mug: each named, none shown
    assert sum(f"mesh file of asset 'mug" in r and "does not read as a mesh" in r for r in refused) == 4, refused
