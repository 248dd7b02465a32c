"""Stage 2 of ``stylize`` over batches of views and processes (``--batch-size B``, ``torchrun``).

* one process: a step of B views draws them in the one-view order, its loss is the mean of the
  B one-view losses, its gradient their mean gradient, and Adam is adapted (lr x sqrt(B), betas ** B);
* the main process alone writes (another rank leaves OUT untouched);
* ``torchrun`` with two gloo processes of one view each stylizes the scene one process does with
  a batch of two (metrics.json records both), and one process resumes their checkpoint.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

import ssgwarp.stylization.stage2 as st
from ssgwarp.stylization.batches import view_order
from ssgwarp.errors import InputError
from ssgwarp.services.distributed import Group
from ssgwarp.evaluation.features import RandomMultiScale

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from test_distributed import _env, _torchrun  # noqa: E402
from test_stylize import _style_setup, _write_run  # noqa: E402

# Two processes with one view each against one process with both: the same sums in another
# order (one render of two cameras accumulating each Gaussian's gradient over both, against two
# renders whose gradients the all-reduce adds and halves), float32 roundoff ~1e-7 relative per
# step. Adam's normalised steps carry it into the colours at most as lr x that relative difference,
# and the final colour transfer (a linear map of gain <= 1.3 fitted on renders) and the float32 PLY
# keep it that size. Measured on the CPU (gloo) over 3 + 2 steps: bit-identical (halving is exact in
# binary and a sum of two terms has one order); other devices or larger worlds sum in other orders. The bound
# 1e-4 is ~300x below one Adam step of a batch of two (lr 0.02 x sqrt(2)): a view rendered twice or
# left out, a gradient summed instead of averaged, or another view order moves colours by whole steps.
ATOL = 1e-4


def _loss(ext, scene, cams, labels, keys, key_ids, cfg):
    targets = st.build_targets(ext, keys, labels[key_ids], cfg)
    return st.ViewLoss(ext, targets, cfg, view_labels=labels, originals=st.render_rgb(scene, cams))


def test_a_batch_is_the_mean_of_its_views_with_adam_adapted(tmp_path):
    scene, obj, cams, labels, keys, key_ids = _style_setup(n_views=5)
    ext = RandomMultiScale(seed=0).freeze()
    # views: consecutive runs of the one-view order
    order = [view_order(s, 5, 3) for s in range(8)]
    assert [v for s in range(4) for v in st.batch_views(s, 2, 5, 3)] == order

    # one step of a batch of two (no Adam scaling): the mean loss, the mean gradient, one Adam step
    cfg = st.Stage2Config(mode="global", iters=1, lr=0.05, sh_rest="keep", batch_size=2, batch_scaling="none",
                          style_loss="nnfm", seed=3)
    loss = _loss(ext, scene, cams, labels, keys, key_ids, cfg)
    res = st.optimise(scene, cams, cfg, loss=loss, progress=False)
    v0, v1 = st.batch_views(0, 2, 5, 3)
    assert v0 != v1 and res.last["views"] == [v0, v1]
    dc = scene.sh_dc.clone().requires_grad_(True)
    render = lambda c: st.render_rgb(scene.replace(sh_dc=dc), c)  # noqa: E731
    singles = []
    for v in (v0, v1):
        singles.append(float(st.deferred_backward(render, cams[v], lambda img, v=v: loss(img, v, 0))))
    assert res.last["total"] == pytest.approx(sum(singles) / 2, rel=1e-6)
    mean_grad = dc.grad / 2
    ref = scene.sh_dc.clone().requires_grad_(True)
    opt = torch.optim.Adam([ref], lr=0.05, eps=1e-15)
    ref.grad = mean_grad
    opt.step()
    assert (res.scene.sh_dc - scene.sh_dc).abs().max() > 0.01
    torch.testing.assert_close(res.scene.sh_dc, ref.detach(), rtol=0, atol=1e-6)

    # the default scaling: lr x sqrt(B), betas ** B, in the checkpoint and the result's record
    cfg4 = st.Stage2Config(mode="global", iters=1, lr=0.05, batch_size=4, style_loss="nnfm")
    res4 = st.optimise(scene, cams, cfg4, loss=_loss(ext, scene, cams, labels, keys, key_ids, cfg4),
                       progress=False, checkpoint=tmp_path / "s2.ckpt")
    group = torch.load(tmp_path / "s2.ckpt", weights_only=False)["optimizer"]["param_groups"][0]
    assert group["lr"] == pytest.approx(0.05 * 2) and group["betas"] == pytest.approx((0.9 ** 4, 0.999 ** 4))
    assert res4.batch == {"batch_size": 4, "world_size": 1, "scaling": "sqrt", "lr_factor": 2.0,
                          "betas": pytest.approx([0.9 ** 4, 0.999 ** 4])}
    assert len(res4.last["views"]) == 4
    # a checkpoint of batch 4 is not continued with another batch size
    with pytest.raises(InputError, match="--batch-size 4"):
        st.optimise(scene, cams, st.Stage2Config(mode="global", iters=2, lr=0.05, batch_size=2, style_loss="nnfm"),
                    loss=loss, progress=False, checkpoint=tmp_path / "s2.ckpt", resume=True)
    with pytest.raises(InputError, match="--batch-size"):
        st.Stage2Config(batch_size=0).validate()


class _Rank1(Group):
    """Rank 1 of 2 whose collectives do nothing (its partner's contributions are zero)."""

    def average_grads(self, params, flags=()):
        return [float(f) for f in flags]

    def barrier(self):
        pass

    def broadcast(self, obj):
        return obj


def test_only_the_main_process_writes(tmp_path, monkeypatch):
    from ssgwarp.stylization.stylize import StylizeOptions, stylize_run

    monkeypatch.setenv("SSGWARP_OFFLINE", "1")
    run, style = _write_run(tmp_path)
    out = tmp_path / "styled"
    opts = StylizeOptions(extractor="random", path_frames=0)
    m = stylize_run(run, style, out, stage2=st.Stage2Config(mode="global", iters=2, checkpoint_every=1),
                    opts=opts, progress=False, group=_Rank1(rank=1, world_size=2))
    assert m == {} and not out.exists()   # no folder, run.json, checkpoints or temporary files from rank 1
    with pytest.raises(InputError, match="multiple of 2"):
        stylize_run(run, style, out, stage2=st.Stage2Config(mode="global", iters=2, batch_size=3), opts=opts,
                    progress=False, group=_Rank1(rank=1, world_size=2))


def _cli(run, style, out, *extra):
    return ["stylize", str(run), "--style", str(style), "--out", str(out), "--keyviews", "2", "--max-side", "48",
            "--path-frames", "0", "--extractor", "random", "--checkpoint-every", "2", "--device", "cpu",
            "--offline", "--quiet", *extra]


def _colours(path: Path) -> torch.Tensor:
    from ssgwarp.formats.ply import read_ply

    return read_ply(path).sh_dc


def _assert_same_ply(a: Path, b: Path):
    from ssgwarp.formats.ply import read_ply

    sa, sb = read_ply(a).tensors(), read_ply(b).tensors()
    assert set(sa) == set(sb)
    for k in sa:
        diff = (sa[k] - sb[k]).abs().max().item()
        assert diff <= ATOL, (k, diff)


def test_two_processes_stylize_the_scene_of_one_with_a_batch_of_two_and_one_resumes(tmp_path, monkeypatch):
    """Steps 1-3 by ``torchrun -m ssgwarp stylize`` with two processes (one view each), then 4-5 by
    one process resuming: after 3 and after 5 steps the scene of one process with batches of two."""
    from ssgwarp import cli

    env = _env()
    for var in ("SSGWARP_SD15", "SSGWARP_CONTROLNET_DEPTH", "SSGWARP_IP_ADAPTER", "SSGWARP_IMAGE_ENCODER"):
        env.pop(var, None)
        monkeypatch.delenv(var, raising=False)
    monkeypatch.delenv("SSGWARP_WEIGHTS", raising=False)
    monkeypatch.delenv("SSGWARP_VGG16", raising=False)
    run, style = _write_run(tmp_path)
    split, three, five = tmp_path / "split", tmp_path / "three", tmp_path / "five"
    r = _torchrun(["-m", "ssgwarp"] + _cli(run, style, split, "--iters", "3"), env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((split / "metrics.json").read_text())
    assert (m["world_size"], m["batch_size"], m["images_seen"]) == (2, 2, 6)
    assert m["batch_scaling"]["lr_factor"] == pytest.approx(2 ** 0.5)
    assert m["stage1"]["ran"] is False and m["keyviews"]["ids"]   # key views chosen once, handed to rank 1
    assert cli.main(_cli(run, style, three, "--iters", "3", "--batch-size", "2")) == 0
    m3 = json.loads((three / "metrics.json").read_text())
    assert (m3["world_size"], m3["batch_size"]) == (1, 2) and m3["keyviews"] == m["keyviews"]
    assert sorted(p.name for p in split.iterdir()) == sorted(p.name for p in three.iterdir())
    _assert_same_ply(split / "scene.ply", three / "scene.ply")
    assert m["final_losses"]["views"] == m3["final_losses"]["views"]
    assert m["final_losses"]["total"] == pytest.approx(m3["final_losses"]["total"], rel=1e-4)
    after3 = _colours(split / "scene.ply")
    # one process continues the two processes' run (the batch size comes from the checkpoint)
    assert cli.main(_cli(run, style, split, "--iters", "5", "--resume")) == 0
    assert cli.main(_cli(run, style, five, "--iters", "5", "--batch-size", "2")) == 0
    assert json.loads((split / "metrics.json").read_text())["world_size"] == 1
    _assert_same_ply(split / "scene.ply", five / "scene.ply")
    assert (_colours(five / "scene.ply") - after3).abs().max() > 100 * ATOL   # (two steps move colours)
    assert cli.main(_cli(run, style, split, "--iters", "6", "--resume", "--batch-size", "4")) == 2
