"""Schedules that fit the capture (ssgwarp.reconstruction.schedules): coarse-to-fine levels and their cameras
(a render at a level is the full render downsampled, densification statistics keep their scale), the stop rule
on synthetic curves, --iters auto in the trainer and the run files, and resuming mid-schedule bit-exactly."""
from __future__ import annotations

import json
import math

import pytest
import torch

from ssgwarp.capture.datasets import SceneData
from ssgwarp.procedural import build_scene, render_views, ring_cameras, write_transforms_dataset
from ssgwarp.raster.rendering import render
from ssgwarp.reconstruction.recipe import Recipe
from ssgwarp.reconstruction.strategy import DefaultStrategy
from ssgwarp.reconstruction.schedules import (AUTO_MAX_ITERS, Pyramid, StopMonitor, check_views,
                                              level_size, plateaued, resolution_factor, resolution_levels, tail_lr)
from ssgwarp.reconstruction.statistics import accumulate_grad2d
from ssgwarp.reconstruction.trainer import Trainer
from ssgwarp.services.losses import photometric, psnr


@pytest.fixture(scope="module")
def gt():
    return build_scene(0.4)


@pytest.fixture(scope="module")
def toy(gt):
    """8 ring views of the procedural scene at 48x36, 6 trained, initial points: the true centres, jittered."""
    cams = ring_cameras(8, 48, 36)
    images, _ = render_views(gt, cams)
    g = torch.Generator().manual_seed(0)
    idx = torch.randperm(len(gt.scene), generator=g)[:300]
    pts = gt.scene.means[idx] + 0.05 * torch.randn(300, 3, generator=g)
    rgb = torch.full((300, 3), 0.5)
    return SceneData(cams, images, [f"v{i}" for i in range(8)], [0, 1, 2, 4, 5, 6], [3, 7], points=(pts, rgb),
                     points_source="ply")


def test_resolution_levels_fall_to_full_resolution_by_the_given_step():
    assert resolution_levels(1.0) == [] and resolution_levels(0.5) == []
    assert [round(f, 2) for f in resolution_levels(4.0)] == [4.0, 2.83, 2.0, 1.41]
    assert [round(f, 2) for f in resolution_levels(2.0)] == [2.0, 1.41]
    assert [round(f, 2) for f in resolution_levels(3.0)] == [3.0, 2.28, 1.73, 1.32]  # ceil(2 log2 3) levels
    fs = [resolution_factor(s, 4.0, 100) for s in range(120)]
    assert fs[0] == 4.0 and fs[24] == 4.0 and round(fs[25], 2) == 2.83 and round(fs[99], 2) == 1.41
    assert all(f == 1.0 for f in fs[100:]) and all(a >= b for a, b in zip(fs, fs[1:]))  # never back up
    assert all(resolution_factor(s, 1.0, 100) == 1.0 for s in (0, 50))               # off
    assert level_size(1008, 756, 4.0) == (252, 189) and level_size(1008, 756, 1.0) == (1008, 756)
    assert level_size(5, 3, 8.0) == (1, 1)


def test_a_render_at_a_level_is_the_full_render_downsampled(gt):
    cams = ring_cameras(2, 128, 96)
    full, _ = render_views(gt, cams)
    masks = (full.mean(-1) < 0.99).float()
    pyr = Pyramid(cams, full, masks)
    c1, i1, m1 = pyr.level(1.0)
    assert c1 is cams and i1 is full and m1 is masks                       # full resolution: the data itself
    cams2, im2, m2 = pyr.level(2.0)
    assert (cams2.width, cams2.height) == (64, 48) and im2.shape == (2, 48, 64, 3) and m2.shape == (2, 48, 64)
    assert torch.allclose(cams2.Ks[:, :2], cams.Ks[:, :2] / 2) and torch.equal(cams2.viewmats, cams.viewmats)
    assert torch.allclose(im2[0, 0, 0], full[0, :2, :2].mean(dim=(0, 1)))  # area average
    assert torch.allclose(m2[0, 0, 0], masks[0, :2, :2].mean())
    assert pyr.level(2.0)[1] is im2                                          # cached
    # the render at the level's cameras matches the downsampled images (seen 31.7 dB; 37.6 dB at 192x144, the
    # rest is the Gaussians that get narrower than a pixel); half a pixel off it would be 3 dB worse
    low, _ = render_views(gt, cams2)
    off = cams2.rescaled(64, 48)
    off.Ks[:, 0, 2] += 0.5
    shifted, _ = render_views(gt, off)
    assert float(psnr(low, im2)) > 30.0 and float(psnr(low, im2)) > float(psnr(shifted, im2)) + 2.0
    # a level that rounds to the full size is the full data
    assert Pyramid(cams, full).level(1.001)[1] is full


def test_densification_gradients_keep_their_scale_at_low_resolution(gt):
    """grad2d is in NDC units: the mean over visible Gaussians at half resolution is within -20%..+50% of full
    resolution's (seen: +21%; +11% at factor 2 and +18% at 4 at 192x144), so the threshold neither starves nor
    floods growth."""
    cams = ring_cameras(2, 96, 72)
    full, _ = render_views(gt, cams)
    g = torch.Generator().manual_seed(0)
    noisy = gt.scene.replace(means=torch.nn.Parameter(gt.scene.means + 0.03 * torch.randn(gt.scene.means.shape,
                                                                                           generator=g)))
    means = []
    for f in (1.0, 2.0):
        cams_f, target, _ = Pyramid(cams, full).level(f)
        out, _, meta = render(noisy, cams_f, sh_degree=0, backgrounds=torch.ones(2, 3))
        meta["means2d"].retain_grad()
        photometric(out[..., :3], target, 0.2, 1.0).backward()
        st = {"grad2d": torch.zeros(len(noisy)), "count": torch.zeros(len(noisy))}
        accumulate_grad2d(st, meta)
        vis = st["count"] > 0
        means.append(float((st["grad2d"][vis] / st["count"][vis]).mean()))
    assert 0.8 < means[1] / means[0] < 1.5, means


def test_the_stop_rule_on_synthetic_curves():
    # rising by 0.5 dB a check: never a plateau
    assert not any(plateaued([20 + 0.5 * i for i in range(k)], 3, 0.1) for k in range(12))
    # a saturating curve: stops once three checks add < 0.1 dB, not before
    curve = [30 - 8 * math.exp(-i / 3) for i in range(40)]
    first = next(k for k in range(1, 41) if plateaued(curve[:k], 3, 0.1))
    assert curve[first - 1] - curve[first - 4] < 0.1 and curve[first - 2] - curve[first - 5] >= 0.1
    # noise around a flat line stops after patience checks of no new best beyond tol
    assert plateaued([25.0, 25.05, 24.98, 25.02], 3, 0.1) and not plateaued([25.0, 25.05, 24.98], 3, 0.1)
    # a dip then a recovery past the old best: not a plateau
    assert not plateaued([25.0, 24.0, 24.5, 25.3], 3, 0.1)

    def run(values):
        m = StopMonitor(first=1000, every=500, patience=2, tol=0.1, tail=0.2, horizon=5000)
        due = [s for s in range(0, 6000, 100) if m.due(s)][:len(values)]
        for s, v in zip(due, values):
            if m.add(s, v):
                break
        return m
    m = run([20.0, 21.0, 21.05, 21.08, 22.0])
    assert m.history[0][0] == 1000 and not StopMonitor(first=1000, every=500, patience=2, tol=0.1, tail=0.2,
                                                      horizon=5000).due(500)   # no check before the first
    assert m.decided == 2500 and m.stop_at == 3000 and m.end == 3000           # tail: 20% of 2500
    assert not m.due(3000) and "plateau" in m.reason(3000) and m.reason(2999) == "not finished"
    assert run([20.0, 21.0, 21.05, 21.08, 22.0]).state_dict() == m.state_dict()   # deterministic
    long = run([20.0 + i for i in range(9)])
    assert long.decided is None and long.end == 5000 and "no plateau" in long.reason(5000)
    late = StopMonitor(first=1000, every=500, patience=1, tol=0.1, tail=0.5, horizon=4600)
    late.add(4000, 1.0), late.add(4500, 1.0)
    assert late.stop_at == 4600                                                   # the tail ends at the horizon
    assert check_views(list(range(10)), 4) == [1, 3, 6, 8] and check_views([2, 5], 4) == [2, 5]
    assert tail_lr(10, 10, 20, 1.0, 0.01) == 1.0 and math.isclose(tail_lr(15, 10, 20, 1.0, 0.01), 0.1)
    assert math.isclose(tail_lr(25, 10, 20, 1.0, 0.01), 0.01)


def _auto_recipe(**kw):
    return Recipe(**{"sh_degree": 1, **kw}, sh_interval=5, stop_every=10, stop_patience=2, stop_tol=100.0)


AUTO_STRATEGY = DefaultStrategy(refine_start=10, refine_stop=20, refine_every=10, reset_every=0)


def test_auto_trains_until_the_plateau_and_a_tail_with_the_learning_rate_annealed(toy):
    t = Trainer(toy, iters="auto", recipe=_auto_recipe(), strategy=AUTO_STRATEGY, progress=False, device="cpu",
                backdrop="off")
    assert t.iters == AUTO_MAX_ITERS and t.schedules.end == AUTO_MAX_ITERS and t.schedules.check_ids == [0, 2, 4, 6]
    lrs = []
    while not t.finished:
        t._set_lrs()
        lrs.append(t.gaussians.groups["means"]["lr"])
        t.train_step()
    # checks at 20, 30, 40 (tol 100 dB: a plateau at the third), then a tail of max(10, 20% of 40) steps
    rec = t.schedules.record(t.step)
    assert t.step == 50 and rec["steps"] == 50 and rec["iters"] == "auto" and "plateau" in rec["stopped"]
    assert [c[0] for c in rec["stop_rule"]["checks"]] == [20, 30, 40] and rec["stop_rule"]["decided_at"] == 40
    assert rec["stop_rule"]["views"] == ["v0", "v2", "v4", "v6"]
    final = t.recipe.lr_means_final * t.extent
    at_plateau = (t.recipe.lr_means * t.extent) ** (1 - 40 / 30000) * final ** (40 / 30000)
    assert all(a > b for a, b in zip(lrs[40:], lrs[41:]))        # step 49 (the last): 9/10 of the way to the end
    assert math.isclose(lrs[40], at_plateau, rel_tol=1e-9) and math.isclose(lrs[-1], at_plateau ** 0.1 * final ** 0.9,
                                                                             rel_tol=1e-9)
    assert lrs[39] / lrs[40] < 1.001                                               # continuous into the tail
    # train() stops there too (the loop's end follows the stop rule)
    t2 = Trainer(toy, iters="auto", recipe=_auto_recipe(), strategy=AUTO_STRATEGY, progress=False, device="cpu",
                backdrop="off")
    t2.train()
    assert t2.step == 50 and torch.equal(t2.final_scene().means, t.final_scene().means)
    with pytest.raises(Exception, match="iters"):
        Trainer(toy, iters="soon", progress=False, device="cpu")


def test_auto_decides_on_the_main_processs_psnr(toy):
    """Under torchrun every process must stop at the same step: the checks take rank 0's PSNR (broadcast)."""
    from ssgwarp.services.distributed import Group

    class Rank0Says(Group):
        def broadcast(self, obj):
            return 99.0 if isinstance(obj, float) else obj

    t = Trainer(toy, iters="auto", recipe=_auto_recipe(), strategy=AUTO_STRATEGY, progress=False, device="cpu",
                backdrop="off",
                group=Rank0Says())
    t.train()
    checks = t.schedules.record(t.step)["stop_rule"]["checks"]
    assert t.step == 50 and [c[1] for c in checks] == [99.0, 99.0, 99.0]


@pytest.mark.parametrize("stop_at", [15, 35])
def test_resume_mid_schedule_is_bit_exact(toy, tmp_path, stop_at):
    """Coarse-to-fine from 4x until step 30, SH from step 25, --iters auto: interrupted at 15 (mid
    resolution schedule) or 35 (between two checks of the stop rule) and resumed = uninterrupted."""
    def trainer(name):
        return Trainer(toy, iters="auto", recipe=_auto_recipe(res_start=4.0, res_until=30, sh_start=25),
                       strategy=AUTO_STRATEGY,
                       progress=False, device="cpu", backdrop="off", checkpoint_path=tmp_path / name,
                       checkpoint_every=1000, seed=2)
    a = trainer("a.pt")
    assert a.schedules.monitor.first == 30                                  # checks start at full resolution
    sizes = []
    while not a.finished:
        sizes.append(a.schedules.views(a.step)[0].width)
        a.train_step()
    assert sizes[0] == 12 and sizes[29] == 34 and sizes[30] == 48 and a.active_sh_degree == 1
    b = trainer("b.pt")
    b.train(until=stop_at)
    b.save_checkpoint()
    c = trainer("b.pt")
    c.load_checkpoint()
    c.train()
    assert c.step == a.step == 60 and c.schedules.record(c.step) == a.schedules.record(a.step)
    for k, v in a.final_scene().tensors().items():
        assert torch.equal(v, c.final_scene().tensors()[k]), k


def test_sh_start_delays_the_first_degree_and_the_default_keeps_the_old_schedule(toy):
    t = Trainer(toy, iters=100, recipe=Recipe(sh_degree=3, sh_interval=10), progress=False, device="cpu",
                backdrop="off")
    degrees = []
    for s in (0, 9, 10, 19, 20, 30, 99):
        t.step = s
        degrees.append(t.active_sh_degree)
    assert degrees == [min(3, s // 10) for s in (0, 9, 10, 19, 20, 30, 99)]
    t = Trainer(toy, iters=100, recipe=Recipe(sh_degree=3, sh_interval=10, sh_start=50), progress=False, device="cpu",
                backdrop="off")
    degrees = []
    for s in (0, 49, 50, 59, 60, 70, 99):
        t.step = s
        degrees.append(t.active_sh_degree)
    assert degrees == [0, 0, 1, 1, 2, 3, 3]


def test_reconstruct_auto_records_the_steps_and_why_it_stopped(toy, tmp_path, monkeypatch, capsys):
    from ssgwarp import cli
    from ssgwarp.reconstruction.reconstruct import ReconstructConfig, reconstruct

    for var in ("SSGWARP_LPIPS", "SSGWARP_VGG16", "SSGWARP_WEIGHTS"):
        monkeypatch.delenv(var, raising=False)
    data_dir = tmp_path / "cap"
    write_transforms_dataset(data_dir, toy.images, toy.cameras)
    m = reconstruct(data_dir, tmp_path / "run", ReconstructConfig(
        iters="auto", recipe=_auto_recipe(sh_degree=0, res_start=2.0), strategy=AUTO_STRATEGY, backdrop="off",
        split_every=4, init="random",
        num_random_points=300), device="cpu", progress=False)
    assert m["iters"] == 50 and m["schedule"]["iters"] == "auto" and m["schedule"]["steps"] == 50
    assert m["schedule"]["coarse_to_fine"] == {"start": 2.0, "until": 20}
    written = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert written["schedule"]["stop_rule"]["decided_at"] == 40
    dj = json.loads((tmp_path / "run" / "data.json").read_text())
    assert dj["schedule"]["steps"] == 50 and "plateau" in dj["schedule"]["stopped"] and "stop_rule" not in dj["schedule"]
    # a fixed length says so; bad values of the options are one line, exit 2, nothing written
    args = ["reconstruct", str(data_dir), "--out", str(tmp_path / "fixed"), "--iters", "3", "--sh-degree", "0",
            "--no-progress", "--device", "cpu", "--coarse-to-fine", "2", "--init", "random", "--random-points", "300"]
    assert cli.main(args) == 0
    fixed = json.loads((tmp_path / "fixed" / "metrics.json").read_text())["schedule"]
    assert fixed["stopped"] == "fixed length (3 steps)" and fixed["coarse_to_fine"]["start"] == 2.0
    for opt, bad in (("--iters", "soon"), ("--iters", "0"), ("--coarse-to-fine", "0.5")):
        with pytest.raises(SystemExit) as e:
            cli.main(["reconstruct", str(data_dir), "--out", str(tmp_path / "bad"), opt, bad, "--device", "cpu"])
        assert e.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert repr(bad) in err[-1] and "expected" in err[-1] and not (tmp_path / "bad").exists()
