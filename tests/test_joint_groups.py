"""`ssgwarp reconstruct --groups`: Gaussian Grouping trained in the reconstruction's own loop.

A small procedural capture (ssgwarp.procedural: ground disc and four objects, 8 views 48x36, object ids
known per pixel) is reconstructed with the groups; the run must hold what `ssgwarp group` writes, readable
by `stylize`, with groups that follow the objects (given masks from step 0; mask-free from the scene once
densification stops), bad input refused in one line before anything is written, and an interrupted run
resumed to the same result.
"""
from __future__ import annotations

import json
import signal

import numpy as np
import pytest
import torch

from ssgwarp import procedural as P
from ssgwarp.cli import main as _main


def main(argv):
    return _main([str(a) for a in argv])

FAST = ["--device", "cpu", "--sh-degree", "0", "--init", "random", "--random-points", "600",
        "--max-gaussians", "2500", "--quiet"]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The capture folder, the true object ids of every view ``[C, H, W]`` (-1 background) and object count."""
    root = tmp_path_factory.mktemp("joint")
    gt = P.build_scene(0.5, seed=0)
    cams = P.ring_cameras(8, 48, 36)
    images, objects = P.render_views(gt, cams)
    P.write_transforms_dataset(root / "cap", images, cams)
    return root / "cap", objects, len(gt.names)


def _with_masks(tmp_path, capture):
    """A copy of the capture with ``object_mask/`` (id = object + 1, 0 = background)."""
    import shutil

    from PIL import Image

    cap, objects, _ = capture
    dst = tmp_path / "cap"
    shutil.copytree(cap, dst)
    (dst / "object_mask").mkdir()
    for i, obj in enumerate(objects):
        Image.fromarray((obj + 1).to(torch.uint8).numpy()).save(dst / "object_mask" / f"r_{i:03d}.png")
    return dst


def _agreement(run, objects, num_objects):
    from ssgwarp.formats.ply import read_ply
    from ssgwarp.demo import group_agreement
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.raster.groups import render_group_maps
    from ssgwarp.services.runs import Run

    r = Run.open(run)
    labels, _ = render_group_maps(read_ply(run / "scene.ply"), r.cameras, load_groups(run).classifier)
    return group_agreement(labels, objects, num_objects)


def test_given_masks_train_from_step_0_and_the_groups_follow_the_objects(tmp_path, capture):
    cap = _with_masks(tmp_path, capture)
    run = tmp_path / "run"
    assert main(["reconstruct", cap, "--out", run, "--iters", "60", "--groups", "--group-dim", "8", *FAST]) == 0
    info = json.loads((run / "groups" / "groups.json").read_text())
    assert info["trained_with"] == "reconstruct --groups" and info["start_step"] == 0
    assert info["kind"] == "given masks" and info["num_groups"] == 6            # 5 objects + background
    assert info["train_mask_accuracy"] > 0.9 and info["test_mask_accuracy"] > 0.85
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["groups"]["num_groups"] == 6 and metrics["identity_dim"] == 8
    agree = _agreement(run, capture[1], capture[2])
    assert agree["separated"] == capture[2] and agree["purity"] > 0.9


def test_mask_free_groups_come_from_the_scene_and_stylize_reads_them(tmp_path, capture):
    from ssgwarp.core.fileio import write_image
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.stylization.stylize import StylizeOptions, stylize_run
    from ssgwarp.stylization.stage2 import Stage2Config

    cap, objects, n_obj = capture
    run = tmp_path / "run"
    assert main(["reconstruct", cap, "--out", run, "--iters", "150", "--groups", "--group-dim", "8", *FAST]) == 0
    info = json.loads((run / "groups" / "groups.json").read_text())
    assert info["kind"] == "mask-free clusters" and info["dim"] == 8
    assert 0 < info["start_step"] < 150 and info["num_groups"] >= 2
    assert {"classifier", "group_maps", "scene"} <= set(info["outputs"])
    assert len(list((run / "groups" / "group_maps").iterdir())) == 8
    assert load_groups(run).num_groups == info["num_groups"]
    # the group maps reproduce the pseudo-masks, and split the objects better than one group would (a short run
    # of a random start: the clusters of a settled scene are the demo's test)
    assert info["train_mask_accuracy"] > 0.9
    counts = torch.bincount(objects[objects >= 0].flatten())
    assert _agreement(run, objects, n_obj)["purity"] > float(counts.max() / counts.sum()) + 0.1
    write_image(tmp_path / "style.png", P.style_image(32, 32, seed=0))
    sm = stylize_run(run, tmp_path / "style.png", tmp_path / "styled", stage2=Stage2Config(iters=2),
                     opts=StylizeOptions(keyviews=2, max_side=32, path_frames=0, sheet_views=1), device="cpu",
                     progress=False)
    assert "per group" in sm["matching"] or "group" in sm["matching"]
    assert (tmp_path / "styled" / "scene.ply").is_file()


@pytest.mark.parametrize("extra, message", [
    (["--groups", "1"], "--groups 1: at least 2 groups"),
    (["--groups", "many"], "--groups 'many': give a number of groups K >= 2, or auto"),
    (["--groups", "--masks", "{tmp}/nowhere"], "nowhere: folder not found"),
    (["--masks", "none"], "--masks: only with --groups"),
    (["--groups", "--group-start", "1.5"], "--group-start 1.5: a share of the run in [0, 1)"),
])
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capture, capsys, extra, message):
    run = tmp_path / "run"
    extra = [e.replace("{tmp}", str(tmp_path)) for e in extra]
    assert main([str(a) for a in ["reconstruct", capture[0], "--out", run, "--iters", "5", *FAST, *extra]]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not run.exists() or not any(run.iterdir())


def test_groups_of_a_finished_run_are_not_overwritten_without_force(tmp_path, capture, capsys):
    cap = _with_masks(tmp_path, capture)
    run = tmp_path / "run"
    argv = ["reconstruct", cap, "--out", run, "--iters", "6", "--groups", *FAST]
    assert main([str(a) for a in argv]) == 0
    assert main([str(a) for a in argv]) == 2
    assert "already holds" in capsys.readouterr().err
    assert main([str(a) for a in argv + ["--force"]]) == 0


def test_interrupted_after_grouping_started_resumes_to_the_same_run(tmp_path, capture, capsys, monkeypatch):
    from ssgwarp.formats.ply import read_ply
    from ssgwarp.reconstruction.trainer import Trainer

    def argv(out, groups=True):
        return [str(a) for a in ["reconstruct", capture[0], "--out", out, "--iters", "40", "--checkpoint-every", "100",
                                 *FAST, *(["--groups", "--group-start", "0.25"] if groups else [])]]

    assert main(argv(tmp_path / "a")) == 0
    orig = Trainer.train_step

    def step(self):
        if self.step == 24:          # a Ctrl-C during step 25, after the groups were attached at step 10
            signal.raise_signal(signal.SIGINT)
        return orig(self)

    monkeypatch.setattr(Trainer, "train_step", step)
    assert main(argv(tmp_path / "b")) == 130
    ck = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    assert ck["step"] == 25 and ck["attached"]["start"] == 10 and "identities" in ck["params"]
    monkeypatch.setattr(Trainer, "train_step", orig)
    # a plain reconstruct cannot resume it (the groups' state would be lost)
    assert main(argv(tmp_path / "b", groups=False) + ["--resume"]) == 2
    assert "reconstruct --groups" in capsys.readouterr().err
    assert main(argv(tmp_path / "b") + ["--resume"]) == 0
    sa, sb = read_ply(tmp_path / "a" / "scene.ply"), read_ply(tmp_path / "b" / "scene.ply")
    for k, v in sa.tensors().items():
        assert torch.equal(v, sb.tensors()[k]), k
    ca = torch.load(tmp_path / "a" / "groups" / "classifier.pt", weights_only=True)["state_dict"]
    cb = torch.load(tmp_path / "b" / "groups" / "classifier.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(ca[k], cb[k]) for k in ca)
    ga = json.loads((tmp_path / "a" / "groups" / "groups.json").read_text())
    gb = json.loads((tmp_path / "b" / "groups" / "groups.json").read_text())
    assert ga["num_groups"] == gb["num_groups"] and np.isclose(ga["train_mask_accuracy"], gb["train_mask_accuracy"])


def test_mask_free_grouping_takes_the_runs_last_steps_and_follows_an_auto_end():
    from ssgwarp.grouping.joint import GroupsDuringReconstruction
    from ssgwarp.grouping.model import GroupConfig

    g = GroupsDuringReconstruction("unused")
    g.refine_stop = 3400                        # densification stopped at 3,400 (fern images_4's sparse rule)
    assert GroupConfig().iters == 1000          # the `group` stage's steps: the last 1,000 of the run
    assert g.start_at(30000) == 29000 and g.start_at(17880) == 16880 and g.start_at(7000) == 6000
    g3 = GroupsDuringReconstruction("unused", config=GroupConfig(iters=3000))
    g3.refine_stop = 3400
    assert g3.start_at(7000) == 4000
    assert g3.start_at(5000) == 3400                                     # never before densification stops
    assert g3.start_at(4000) == 3000                                     # (which counts at most 3/4 of the run)
    g.refine_stop = 10**9                                                # refining until the end: 3/4 of the run
    assert g.start_at(2000) == 1500
    g.refine_stop, g.share = 3400, 0.5                                   # --group-start: a share of the run
    assert g.start_at(17880) == 8940
    g.share, g.with_masks = None, True                                   # masks: from the first step
    assert g.start_at(30000) == 0
    g.with_masks, g.refine_stop = False, 30000
    assert g.start_at(1) == 0                                            # at least one step with the groups


def test_with_iters_auto_mask_free_grouping_starts_when_the_stop_rule_moves_the_end(tmp_path, capture):
    from ssgwarp.grouping.joint import reconstruct_with_groups
    from ssgwarp.reconstruction.reconstruct import ReconstructConfig
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.strategy import DefaultStrategy

    # checks every 10 steps from 20 (densification's end), a plateau at the third check (40), a 10-step tail:
    # the planned 30,000-step run would group from step 29,000, which it never reaches; it groups from 40 to 50
    recipe = Recipe(sh_degree=0, sh_interval=5, stop_every=10, stop_patience=2, stop_tol=100.0)
    strategy = DefaultStrategy(max_gaussians=2500, refine_start=10, refine_stop=20, refine_every=10, reset_every=0)
    cfg = ReconstructConfig(iters="auto", recipe=recipe, strategy=strategy, init="random", num_random_points=600,
                            backdrop="off")
    m = reconstruct_with_groups(capture[0], tmp_path / "run", cfg, device="cpu", progress=False)
    info = json.loads((tmp_path / "run" / "groups" / "groups.json").read_text())
    assert m["iters"] == 50 and info["start_step"] == 40 and m["groups"]["start_step"] == 40
    assert info["kind"] == "mask-free clusters" and info["iters"] == 50
