"""Stage 2: group matching, NNFM loss, deferred back-propagation, IST vs global, frozen geometry, resume."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ssgwarp.stylization import stylize as st
from ssgwarp.stylization import color as stylize_color, feature_defaults as fd, stage2 as s2
from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError
from ssgwarp.evaluation.features import RandomMultiScale
from ssgwarp.stylization.matching import MatchTargets, downsample_labels, match_mask, nearest_neighbors, nnfm_loss
from ssgwarp.raster.scene import GaussianScene, rgb_to_sh_dc

RED, BLUE = (0.9, 0.1, 0.1), (0.1, 0.1, 0.9)


# ----------------------------------------------------------------------------- synthetic scene
def two_objects(n: int = 120, dtype=torch.float32, identities: bool = False):
    """Two Gaussian blobs left (x<0, bluish grey) and right (x>0, reddish grey); returns (scene, object id [N])."""
    g = torch.Generator().manual_seed(0)
    pts, rgb, obj = [], [], []
    for k, (cx, col) in enumerate([(-0.55, (0.42, 0.42, 0.58)), (0.55, (0.58, 0.42, 0.42))]):
        pts.append(torch.randn(n, 3, generator=g) * torch.tensor([0.22, 0.3, 0.15]) + torch.tensor([cx, 0.0, 0.0]))
        rgb.append(torch.tensor(col).expand(n, 3) + 0.03 * torch.randn(n, 3, generator=g))
        obj.append(torch.full((n,), k))
    pts, rgb, obj = torch.cat(pts), torch.cat(rgb), torch.cat(obj)
    scene = GaussianScene.from_points(pts.to(dtype), rgb.to(dtype), opacity=0.8)
    if identities:
        scene = scene.replace(identities=torch.randn(len(obj), 4, generator=g).to(dtype))
    return scene, obj


def ring(W: int = 48, H: int = 32, n: int = 5, dtype=torch.float32) -> Cameras:
    ang = torch.linspace(-0.35, 0.35, n)
    eyes = torch.stack([3.0 * torch.sin(ang), 0.15 * torch.cos(3 * ang), -3.0 * torch.cos(ang)], 1)
    vm = look_at(eyes, torch.zeros(n, 3), up=(0.0, -1.0, 0.0)).to(dtype)
    return Cameras(vm, intrinsics(40.0, 40.0, W / 2, H / 2, n, dtype), W, H)


def object_labels(scene: GaussianScene, obj: torch.Tensor, cams: Cameras) -> torch.Tensor:
    """Ground-truth group maps [C,H,W]: object 0, object 1, background 2."""
    onehot = F.one_hot(obj, 2).to(scene.dtype)
    out, alpha, _ = scene.render(cams, rgb=False, extra=onehot)
    lab = out.argmax(-1)
    lab[alpha[..., 0] < 0.5] = 2
    return lab


# ----------------------------------------------------------------------------- group matching
def test_downsample_labels_majority_and_nearest():
    lab = torch.tensor([[0, 0, 1, 1],
                        [0, 2, 1, 2],
                        [3, 3, 2, 2],
                        [3, 0, 2, 1]])[None]
    maj = downsample_labels(lab, (2, 2), "majority")
    assert maj.tolist() == [[[0, 1], [3, 2]]]
    near = downsample_labels(lab, (2, 2), "nearest")
    assert near.shape == (1, 2, 2) and near.dtype == torch.long
    assert near.tolist() == [[[lab[0, 0, 0].item(), lab[0, 0, 2].item()], [lab[0, 2, 0].item(), lab[0, 2, 2].item()]]]
    with pytest.raises(InputError):
        downsample_labels(lab, (2, 2), "mode")


def test_group_matching_follows_the_formula():
    # view: groups 0, 1 (both in the key views) and 3 (absent from the key views)
    view = torch.tensor([[0, 1], [3, 1]])
    keys = torch.tensor([[[0, 0], [2, 1]], [[2, 2], [1, 0]]])   # [V=2, 2, 2]: groups 0, 1, 2
    M = match_mask(view, keys)
    kf = keys.reshape(-1).tolist()
    expect = []
    for g in view.reshape(-1).tolist():
        if g in kf:
            expect.append([kq == g for kq in kf])
        else:                                   # absent: global fallback
            expect.append([True] * len(kf))
    assert M.tolist() == expect
    # MatchTargets picks, for every view position, the best key among exactly those
    torch.manual_seed(0)
    kfeat = torch.randn(2, 5, 2, 2)
    vfeat = torch.randn(5, 2, 2)
    t = MatchTargets(kfeat, keys)
    q = F.normalize(vfeat.permute(1, 2, 0).reshape(-1, 5), dim=1)
    idx = t.nearest(q, view.reshape(-1))
    sim = q @ t.keys.T
    for p in range(4):
        assert M[p, idx[p]]
        assert sim[p, idx[p]] == sim[p][M[p]].max()
    assert t.key_index(3) is None and t.key_index(0).tolist() == [0, 1, 7]


def test_nearest_neighbors_chunking_is_exact():
    torch.manual_seed(1)
    q, k = torch.randn(37, 6), torch.randn(53, 6)
    ref = (q @ k.T).max(dim=1)
    for chunk in (1, 5, 64, 10_000):
        idx, val = nearest_neighbors(q, k, chunk)
        assert torch.equal(idx, ref.indices)
        torch.testing.assert_close(val, ref.values)


@pytest.mark.parametrize("grouped", [False, True])
def test_nnfm_loss_equals_brute_force(grouped):
    torch.manual_seed(2)
    C, h, w = 8, 5, 6
    kfeat = torch.randn(3, C, 4, 5)
    feats = torch.randn(C, h, w, requires_grad=True)
    vlab = torch.randint(0, 4, (h, w)) if grouped else None            # group 3 never in the keys
    klab = torch.randint(0, 3, (3, 4, 5)) if grouped else None
    loss = nnfm_loss(feats, kfeat, vlab, klab, chunk=7)
    (g,) = torch.autograd.grad(loss, feats)

    f2 = feats.detach().clone().requires_grad_(True)
    q = F.normalize(f2.permute(1, 2, 0).reshape(-1, C), dim=1)
    k = F.normalize(kfeat.permute(0, 2, 3, 1).reshape(-1, C), dim=1)
    dist = 1.0 - q @ k.T                                                   # [P, Q] cosine distance
    if grouped:
        dist = dist.masked_fill(~match_mask(vlab, klab), float("inf"))
    ref = dist.min(dim=1).values.mean()
    (g_ref,) = torch.autograd.grad(ref, f2)
    torch.testing.assert_close(loss, ref)
    torch.testing.assert_close(g, g_ref)


# ----------------------------------------------------------------------------- deferred back-propagation
def test_deferred_backprop_equals_direct():
    scene, obj = two_objects(n=40, dtype=torch.float64)
    cams = ring(W=40, H=36, n=3, dtype=torch.float64)
    ext = RandomMultiScale(seed=0).double().freeze()
    cfg = st.Stage2Config(content_weight=0.5, tv_weight=0.1, free_opacity=True)
    keys = st.render_rgb(scene.replace(sh_dc=rgb_to_sh_dc(torch.tensor(RED, dtype=torch.float64).expand(80, 3))),
                         cams[[0]])
    labels = object_labels(scene, obj, cams)
    targets = st.build_targets(ext, keys, labels[[0]], cfg)
    loss = st.ViewLoss(ext, targets, cfg, view_labels=labels, originals=st.render_rgb(scene, cams))

    def grads(deferred: bool):
        dc = scene.sh_dc.clone().requires_grad_(True)
        op = scene.logit_opacities.clone().requires_grad_(True)
        means = scene.means.clone().requires_grad_(True)
        render = lambda c: st.render_rgb(scene.replace(sh_dc=dc, logit_opacities=op, means=means), c)  # noqa: E731
        fn = lambda img: loss(img, 1)  # noqa: E731
        value = (s2.deferred_backward if deferred else s2.direct_backward)(render, cams[1], fn)
        return value, dc.grad, op.grad, means.grad

    direct, deferred = grads(False), grads(True)
    assert direct[1].abs().max() > 0 and direct[3].abs().max() > 0
    for a, b in zip(direct, deferred):
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-12)


# ----------------------------------------------------------------------------- IST vs global
def _style_setup(n_views: int = 5):
    scene, obj = two_objects()
    cams = ring(n=n_views)
    labels = object_labels(scene, obj, cams)
    colors = torch.tensor([RED, BLUE])
    g = torch.Generator().manual_seed(1)
    stylized_scene = scene.replace(sh_dc=rgb_to_sh_dc(colors[obj] + 0.05 * torch.randn(len(obj), 3, generator=g)))
    key_ids = [0, n_views - 1]
    keys = st.render_rgb(stylized_scene, cams[key_ids])
    return scene, obj, cams, labels, keys, key_ids


def _redness(scene, obj, k):
    c = scene.base_colors[obj == k].mean(0)
    return float(c[0] - c[2])


@pytest.mark.parametrize("style_loss,margin", [("nnfm", 0.25), ("sw", 0.15)])
def test_ist_gives_each_object_its_matched_colour_while_global_mixes(style_loss, margin):
    """Left object is matched (by group) to red, right to blue; the style image holds both colours.

    The objects start bluish (left) and reddish (right), so plain nearest-neighbour matching
    against the style image (global, ARF) pulls each to the *other* colour, while IST follows
    the groups. Measured: red - blue of each object's mean colour after 40 steps.
    """
    scene, obj, cams, labels, keys, key_ids = _style_setup()
    ext = RandomMultiScale(seed=0).freeze()
    originals = st.render_rgb(scene, cams)
    before = (_redness(scene, obj, 0), _redness(scene, obj, 1))
    assert before[0] < -0.1 and before[1] > 0.1
    out = {}
    for mode in ("ist", "global"):
        cfg = st.Stage2Config(mode=mode, iters=40, lr=0.05, content_weight=0.0, tv_weight=0.0, style_loss=style_loss,
                              color_transfer="off")
        if mode == "ist":
            targets = st.build_targets(ext, keys, labels[key_ids], cfg)
        else:
            style = torch.zeros(32, 48, 3)
            style[:, :24], style[:, 24:] = torch.tensor(RED), torch.tensor(BLUE)
            targets = st.build_targets(ext, style[None], None, cfg)
        loss = st.ViewLoss(ext, targets, cfg, view_labels=labels, originals=originals)
        res = st.optimise(scene, cams, cfg, loss=loss, progress=False)
        out[mode] = (_redness(res.scene, obj, 0), _redness(res.scene, obj, 1))
        assert res.last["style"] < res.history[0]["style"]
    # IST: left clearly red, right clearly blue (margin on a 0..0.8 scale)
    assert out["ist"][0] > margin and out["ist"][1] < -margin, out
    # global: the assignment is not the matched one (each object goes to its nearest style colour)
    assert not (out["global"][0] > 0.0 and out["global"][1] < 0.0), out
    assert out["ist"][0] - out["global"][0] > 0.5 and out["global"][1] - out["ist"][1] > 0.5, out


def test_finetune_mode_fits_key_views():
    scene, obj, cams, labels, keys, key_ids = _style_setup()
    cfg = st.Stage2Config(mode="finetune", iters=20, lr=0.05)
    res = st.optimise(scene, cams, cfg, finetune_images=keys, finetune_cameras=cams[key_ids], progress=False)
    before = (st.render_rgb(scene, cams[key_ids]) - keys).abs().mean()
    after = (st.render_rgb(res.scene, cams[key_ids]) - keys).abs().mean()
    assert after < 0.6 * before, (float(before), float(after))
    assert _redness(res.scene, obj, 0) > 0.0 > _redness(res.scene, obj, 1)


# ----------------------------------------------------------------------------- what is optimised
@pytest.mark.parametrize("free_opacity", [False, True])
def test_colour_only_leaves_geometry_bit_identical(free_opacity):
    scene, obj = two_objects(n=30, identities=True)
    scene = scene.with_sh_degree(1)
    keep = {k: v.clone() for k, v in scene.tensors().items()}
    cams = ring(n=3)
    ext = RandomMultiScale(seed=0).freeze()
    cfg = st.Stage2Config(mode="global", iters=6, lr=0.05, free_opacity=free_opacity, sh_rest="keep")
    targets = st.build_targets(ext, torch.rand(1, 32, 48, 3, generator=torch.Generator().manual_seed(0)), None, cfg)
    res = st.optimise(scene, cams, cfg, loss=st.ViewLoss(ext, targets, cfg), progress=False)
    frozen = ["means", "log_scales", "quats", "identities", "sh_rest"] + ([] if free_opacity else ["logit_opacities"])
    for k in frozen:
        assert torch.equal(getattr(res.scene, k), keep[k]), k
        assert getattr(res.scene, k) is getattr(scene, k), k        # not even copied
    assert not torch.equal(res.scene.sh_dc, keep["sh_dc"])
    assert free_opacity == (not torch.equal(res.scene.logit_opacities, keep["logit_opacities"]))
    for k, v in scene.tensors().items():                             # the input scene is untouched
        assert torch.equal(v, keep[k]), k


def test_resume_reaches_the_uninterrupted_result(tmp_path):
    scene, obj, cams, labels, keys, key_ids = _style_setup(n_views=3)
    ext = RandomMultiScale(seed=0).freeze()

    def run(iters, ckpt=None, resume=False):
        cfg = st.Stage2Config(mode="ist", iters=iters, lr=0.05, checkpoint_every=3)
        targets = st.build_targets(ext, keys, labels[key_ids], cfg)
        loss = st.ViewLoss(ext, targets, cfg, view_labels=labels, originals=st.render_rgb(scene, cams))
        return st.optimise(scene, cams, cfg, loss=loss, checkpoint=ckpt, resume=resume, progress=False)

    full = run(8)
    ckpt = tmp_path / "stage2.ckpt"
    run(4, ckpt)                       # "interrupted" after 4 steps: the checkpoint holds step 4
    assert torch.load(ckpt, weights_only=False)["step"] == 4
    resumed = run(8, ckpt, resume=True)
    assert torch.equal(resumed.scene.sh_dc, full.scene.sh_dc)
    assert [h["step"] for h in resumed.history] == [h["step"] for h in full.history]


def test_bad_options_are_one_line_errors():
    with pytest.raises(InputError, match="--mode"):
        st.Stage2Config(mode="arf").validate()
    with pytest.raises(InputError, match="--lr"):
        st.Stage2Config(lr=float("nan")).validate()
    with pytest.raises(InputError, match="--feature-scale"):
        st.Stage2Config(feature_scale=0).validate()
    with pytest.raises(InputError, match="--color-transfer"):
        st.Stage2Config(color_transfer="sideways").validate()
    with pytest.raises(InputError, match="--sh-rest"):
        st.Stage2Config(sh_rest="drop").validate()
    with pytest.raises(InputError, match="--style-loss"):
        st.Stage2Config(style_loss="gram").validate()
    with pytest.raises(InputError, match="--color-max-gain"):
        st.Stage2Config(color_max_gain=0.0).validate()
    with pytest.raises(InputError, match="--color-detail"):
        st.Stage2Config(color_detail="more").validate()
    for bad in (0.1, 5.0, float("nan")):
        with pytest.raises(InputError, match="--style-scale"):
            st.Stage2Config(style_scale=bad).validate()
    with pytest.raises(InputError, match="--label-mode mean: use one of majority, nearest"):
        st.Stage2Config(label_mode="mean").validate()


# ----------------------------------------------------------------------------- end to end (CLI)
def _write_run(tmp_path, grouped: bool = True):
    """A tiny reconstruction run folder (scene.ply, cameras.json, data.json, groups/) and a style image."""
    import json

    from ssgwarp.core.fileio import write_image
    from ssgwarp.formats.ply import write_ply

    scene, obj = two_objects(n=60)
    run = tmp_path / "run"
    run.mkdir()
    cams = ring(W=48, H=32, n=6)
    cams.names = [f"img{i:02d}.png" for i in range(6)]
    if grouped:   # identities: object one-hot x 4; classifier = identity with a bias for background (group 2)
        ident = torch.zeros(len(obj), 3)
        ident[torch.arange(len(obj)), obj] = 4.0
        scene = scene.replace(identities=ident)
        lin = torch.nn.Linear(3, 3)
        with torch.no_grad():
            lin.weight.copy_(torch.eye(3))
            lin.bias.copy_(torch.tensor([0.0, 0.0, 1.0]))
        (run / "groups").mkdir()
        torch.save({"dim": 3, "num_groups": 3, "state_dict": lin.state_dict()}, run / "groups" / "classifier.pt")
    write_ply(run / "scene.ply", scene)
    cams.save(run / "cameras.json")
    (run / "data.json").write_text(json.dumps({
        "data_dir": None, "images": "images", "background": [0.0, 0.0, 0.0],
        "split": {"train": cams.names[:5], "test": cams.names[5:]}}))
    style = torch.zeros(40, 40, 3)
    style[:, :20], style[:, 20:] = torch.tensor(RED), torch.tensor(BLUE)
    write_image(tmp_path / "style.png", style)
    return run, tmp_path / "style.png"


def test_resume_refusal_names_the_changed_stage2_fields():
    from ssgwarp.services.runs import resume_changes

    old = {"style": "a.png", "stage2": {"lr": 0.02}}
    assert resume_changes(old, {"style": "a.png", "stage2": {"lr": 0.02, "content_weight": 0.01}}) == \
        ["stage2.content_weight (not recorded) -> 0.01"]          # a field added since the earlier run
    assert resume_changes(old, {"style": "b.png", "stage2": {"lr": 0.5}}) == ["stage2.lr 0.02 -> 0.5",
                                                                              "style a.png -> b.png"]
    assert resume_changes(old, dict(old)) == []


def test_cli_stylize_end_to_end_without_stage1_weights(tmp_path, monkeypatch, capsys):
    import json

    from ssgwarp.cli import main
    from ssgwarp.formats.ply import read_ply

    for var in ("SSGWARP_WEIGHTS", "SSGWARP_SD15", "SSGWARP_CONTROLNET_DEPTH", "SSGWARP_IP_ADAPTER",
                "SSGWARP_IMAGE_ENCODER", "SSGWARP_VGG16"):
        monkeypatch.delenv(var, raising=False)
    run, style = _write_run(tmp_path)
    out = tmp_path / "styled"
    argv = [str(run), "--style", str(style), "--out", str(out), "--iters", "6", "--keyviews", "2",
            "--max-side", "48", "--path-frames", "3", "--checkpoint-every", "2", "--device", "cpu"]
    assert main(["stylize", *argv]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["stage1"]["ran"] is False and "no local diffusion weights" in m["stage1"]["reason"]
    # the console says it in one short line (the models' names, how to find and fetch them); the full
    # reasons (where each model was looked for) stay in metrics.json and run.json
    line = next(x for x in capsys.readouterr().out.splitlines() if "Stage 1 skipped" in x)
    assert "sd15" in line and "image_encoder" in line and "ssgwarp weights --download stage1" in line
    assert len(line) < 250 and len(m["stage1"]["reason"]) > len(line)
    assert json.loads((out / "run.json").read_text())["stages"]["stage1"]["reason"] == m["stage1"]["reason"]
    # without Stage 1 the groups still matter: each matches its own region of the style image (issue 39)
    assert m["matching"].startswith("per group (3 groups) against") and "regions of the style image" in m["matching"]
    assert m["extractor"] == "random-multiscale:seed0,c128s2p2-4-8,edges" and m["groups"] == 3 and m["style_loss"] == "sw"
    assert m["gram_style_loss"] > 0 and m["content_loss"] > 0
    for k in ("color", "texture"):
        assert m["style_distance"][k] > 0 and m["style_distance_original"][k] > 0
    er = m["empty_regions"]          # floaters over the pixels the source leaves empty (this scene has some)
    assert 0 < er["share"] < 1 and er["spread_original"] >= 0 and abs(er["spread"] - er["spread_original"]) < 0.05
    ct = m["color_transfer"]
    assert ct["setting"] == "both" and ct["against"] == "the style image's regions"
    assert ct["pre"]["per_group"] is True and ct["post"]["per_group"] is True
    assert set(m["seconds"]) >= {"keyviews", "stage1", "stage2", "renders", "total"}
    for f in ("scene.ply", "contact_sheet.png", "loss.png", "keyviews/keyviews.json", "renders/train/img00.png",
              "path.gif"):
        assert (out / f).is_file(), f
    src, styled = read_ply(run / "scene.ply"), read_ply(out / "scene.ply")
    assert torch.equal(src.means, styled.means) and torch.equal(src.identities, styled.identities)
    assert not torch.equal(src.sh_dc, styled.sh_dc)
    # an existing output is never overwritten silently; --resume continues; --force starts over
    assert main(["stylize", *argv]) == 2
    assert main(["stylize", *argv, "--resume"]) == 0
    assert torch.equal(read_ply(out / "scene.ply").sh_dc, styled.sh_dc)
    capsys.readouterr()
    assert main(["stylize", *argv, "--resume", "--lr", "0.5"]) == 2     # different options: the field is named
    assert "--resume with other options than the earlier run was started with (stage2.lr 0.02 -> 0.5)" in capsys.readouterr().err
    assert main(["stylize", *argv, "--force", "--mode", "global", "--color-transfer", "off", "--style-loss", "nnfm",
                 "--style-scale", "1.5"]) == 0
    m2 = json.loads((out / "metrics.json").read_text())
    assert m2["mode"] == "global" and m2["style_loss"] == "nnfm" and set(m2["color_transfer"]) == {"setting", "against"}
    assert m2["config"]["style_scale"] == 1.5
    assert m2["matching"].startswith("global against the style image")     # --mode global: today's behaviour
    # densify: more Gaussians; a resumed run replays the same splits and continues from the checkpoint
    # (with the view-pair term, built on the densified geometry)
    extra = ["--densify", "0.5", "--hold-empty", "1", "--consistency-weight", "1"]
    assert main(["stylize", *argv, "--force", *extra]) == 0
    m3 = json.loads((out / "metrics.json").read_text())
    d = m3["densify"]
    assert d["gaussians_after"] == m3["gaussians"] > d["gaussians_before"] == len(src.means)
    assert m3["final_losses"]["empty"] >= 0 and m3["final_losses"]["pair"] >= 0
    assert m3["config"]["consistency_weight"] == 1.0
    once = read_ply(out / "scene.ply")
    assert main(["stylize", *argv, "--resume", *extra, "--iters", "8"]) == 0
    again = read_ply(out / "scene.ply")
    assert torch.equal(again.means, once.means) and json.loads((out / "metrics.json").read_text())["gaussians"] == len(once.means)
    # bad input: a missing style image is a one-line error
    assert main(["stylize", str(run), "--style", str(tmp_path / "nope.png"), "--out", str(tmp_path / "o2")]) == 2


def test_stylize_with_tiny_stage1_runs_ist_on_the_stylized_key_views(tmp_path, monkeypatch):
    """Stage 1 on tiny random diffusion models (no weights): IST matches per group against its output,
    CVSA on/off is recorded, and --resume reuses the stylized key views instead of rerunning Stage 1."""
    import json

    pytest.importorskip("diffusers")
    from fakeweights import random_stage1_components
    from ssgwarp.stylization.diffusion_models import Stage1Config, assemble_stage1
    from ssgwarp.stylization.keyviews import load_keyviews

    for var in ("SSGWARP_WEIGHTS", "SSGWARP_SD15"):
        monkeypatch.delenv(var, raising=False)
    run, style = _write_run(tmp_path)
    models = assemble_stage1(random_stage1_components("tiny"), "cpu")
    out = tmp_path / "styled"
    kw = dict(stage2=st.Stage2Config(iters=3), opts=st.StylizeOptions(keyviews=2, max_side=48, path_frames=0),
              progress=False)
    m = st.stylize_run(run, style, out, stage1=Stage1Config(steps=2, cvsa=False, progress=False),
                       stage1_models=models, **kw)
    assert m["stage1"]["ran"] and m["stage1"]["cvsa"] is False
    assert m["matching"] == "per group (3 groups) against 2 stylized key views"
    kv, stylized = load_keyviews(out / "keyviews")
    assert stylized is not None and stylized.shape == (2, 32, 48, 3) and kv.groups is not None
    # resume without models (and without weights): the stylized key views are reloaded, not recomputed
    m2 = st.stylize_run(run, style, out, stage1=Stage1Config(steps=2, cvsa=False, progress=False), resume=True, **kw)
    assert m2["stage1"]["ran"] and m2["stage1"].get("resumed")
    assert json.loads((out / "metrics.json").read_text())["matching"] == m["matching"]
    # a different CVSA setting is a different run
    with pytest.raises(InputError, match="stage1"):
        st.stylize_run(run, style, out, stage1=Stage1Config(steps=2, cvsa=True, progress=False), resume=True, **kw)
    # --style-scale sizes the style image, which Stage 2 does not match here: the run says so
    kw["stage2"] = st.Stage2Config(iters=1, style_scale=2)
    m3 = st.stylize_run(run, style, tmp_path / "scaled", stage1=Stage1Config(steps=2, cvsa=False, progress=False),
                        stage1_models=models, **kw)
    assert m3["matching"] == m["matching"] + " (--style-scale 2 not used: the stylized key views are views already " \
        "(--mode global matches the style image))"


# ----------------------------------------------------------------------------- the Stage 2 objective, by hand
class _Identity(torch.nn.Module):
    """Features = the image itself (stride 1): every loss term becomes hand-computable."""

    name = "identity"
    strides = [1]

    def __init__(self):
        super().__init__()
        self.p = torch.nn.Parameter(torch.zeros(1, dtype=torch.float64), requires_grad=False)

    def forward(self, x):
        return [x.to(self.p.dtype)]


def test_stage2_total_loss_equals_its_equation_by_hand():
    """L = style_weight * L_style + content_weight * L_content + tv_weight * L_TV on a 2x2 image.

    NNFM: pixels (1,0,0) (0,1,0) / (0,0,1) (1,1,0) against keys (1,0,0), (0,1,1): cosine distances to
    the nearest key 0, 1 - 1/sqrt2, 1 - 1/sqrt2, 1 - 1/sqrt2 -> mean 3 (1 - 1/sqrt2) / 4.
    Content against a flat 0.5 render: mean((I - 0.5)^2) / mean(0.5^2) = 0.25 / 0.25 = 1.
    TV: vertical squared differences (1,0,1), (1,0,0) -> 1/2; horizontal (1,1,0), (1,1,1) -> 5/6.
    """
    img = torch.tensor([[[1.0, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 1, 0]]], dtype=torch.float64)
    keys = torch.tensor([[[1.0, 0, 0], [0, 1, 1]]], dtype=torch.float64)          # a 1x2 style image
    original = torch.full((1, 2, 2, 3), 0.5, dtype=torch.float64)
    ext = _Identity()
    nnfm = 3 * (1 - 1 / 2 ** 0.5) / 4
    content, tv = 1.0, 0.5 + 5 / 6
    for sw, cw, tw in [(2.0, 0.5, 0.1), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 3.0)]:
        cfg = st.Stage2Config(style_loss="nnfm", style_weight=sw, content_weight=cw, tv_weight=tw)
        loss = st.ViewLoss(ext, st.build_targets(ext, keys, None, cfg), cfg, originals=original)
        total = loss(img, 0)
        assert float(total) == pytest.approx(sw * nnfm + cw * content + tw * tv, abs=1e-12)
        assert loss.last["style"] == pytest.approx(nnfm, abs=1e-12)
    # the paper's objective (content 0, TV 0) is the style term alone
    cfg = st.Stage2Config(style_loss="nnfm", content_weight=0.0, tv_weight=0.0)
    loss = st.ViewLoss(ext, st.build_targets(ext, keys, None, cfg), cfg, originals=original)
    assert float(loss(img, 0)) == pytest.approx(nnfm, abs=1e-12) and set(loss.last) == {"style", "total"}


def test_sliced_style_loss_by_hand_and_per_group():
    """SW term: a view whose features are the keys permuted -> 0; scaled by 2 -> exactly 1 for any
    directions (sorting commutes with scaling); per group, an absent group uses all keys (fallback)."""
    from ssgwarp.stylization.matching import SlicedTargets

    g = torch.Generator().manual_seed(0)
    keys = torch.randn(1, 6, 4, 5, generator=g, dtype=torch.float64)            # [V, C, h, w]
    flat = keys[0].reshape(6, -1)
    perm = torch.randperm(20, generator=g)
    view = flat[:, perm].reshape(6, 4, 5)
    t = SlicedTargets(keys, None, projections=16, seed=3)
    assert float(t.loss(view, step=0)) < 1e-24
    assert float(t.loss(2 * view, step=5)) == pytest.approx(1.0, abs=1e-12)
    # resumable: the directions are a function of seed and step only
    assert torch.equal(t.directions(7, 6, "cpu", torch.float64), SlicedTargets(keys, None, 16, 3).directions(7, 6, "cpu", torch.float64))
    assert not torch.equal(t.directions(7, 6, "cpu", torch.float64), t.directions(8, 6, "cpu", torch.float64))
    # per group: keys of group 0 (left half) and 1 (right half); the view has groups 0 and 9 (absent)
    klab = torch.zeros(1, 4, 5, dtype=torch.long)
    klab[..., 3:] = 1
    tg = SlicedTargets(keys, klab, projections=16, seed=3)
    vlab = torch.zeros(4, 5, dtype=torch.long)
    vlab[2:] = 9
    k_all = keys[0].permute(1, 2, 0).reshape(-1, 6)
    k_g0 = k_all[klab.reshape(-1) == 0]
    q = view.permute(1, 2, 0).reshape(-1, 6)
    d = tg.directions(0, 6, "cpu", torch.float64)
    m0, m9 = vlab.reshape(-1) == 0, vlab.reshape(-1) == 9
    expect = (SlicedTargets.sliced_term(q[m0], k_g0, d) * m0.sum() + SlicedTargets.sliced_term(q[m9], k_all, d) * m9.sum()) / 20
    assert float(tg.loss(view, vlab, step=0)) == pytest.approx(float(expect), rel=1e-12)
    assert tg.key_index(9) is None and tg.key_index(0).numel() == int((klab == 0).sum())


def test_absent_group_falls_back_to_every_key_view_feature():
    """A group the key views do not show is matched against all key features (never against nothing,
    never against one group only): its nearest neighbour is the global one, here in group 1."""
    kf = torch.zeros(1, 2, 1, 3, dtype=torch.float64)
    kf[0, :, 0, 0] = torch.tensor([1.0, 0.0])    # group 0
    kf[0, :, 0, 1] = torch.tensor([0.0, 1.0])    # group 1
    kf[0, :, 0, 2] = torch.tensor([-1.0, 0.0])   # group 1
    klab = torch.tensor([[[0, 1, 1]]])
    t = MatchTargets(kf, klab)
    q = F.normalize(torch.tensor([[0.1, 1.0], [0.9, 0.1]], dtype=torch.float64), dim=1)
    assert t.nearest(q, torch.tensor([4, 4])).tolist() == [1, 0]        # group 4 absent: best over all keys
    assert t.nearest(q, torch.tensor([1, 1])).tolist() == [1, 1]        # group 1: only its own keys
    assert t.nearest(q, torch.tensor([0, 0])).tolist() == [0, 0]        # group 0: only its own key
    vf = q.T.reshape(2, 1, 2)
    loss_absent = t.loss(vf, torch.tensor([[4, 4]]))
    brute = (1 - (q @ F.normalize(kf[0, :, 0].T, dim=1).T).max(1).values).mean()
    assert float(loss_absent) == pytest.approx(float(brute), abs=1e-12)


def test_weight_free_default_moves_the_scene_toward_its_style(tmp_path):
    """The default weight-free Stage 2 (colour transfer before and after, SW loss on the random
    features), scored by the weight-free distances — not by the extractor it optimised.

    Measured on this scene and the procedural style, 30 steps (2026-11-23, CPU): colour distance
    x0.77, texture x0.93; the previous default (NNFM on the same features, no colour transfer) x0.84,
    x0.96 (re-measured with the TV default 0.5: the same). Asserted with about half of those margins, and
    better than the previous default.
    """
    from ssgwarp.core.fileio import write_image
    from ssgwarp.procedural import style_image

    run, _ = _write_run(tmp_path)
    write_image(tmp_path / "art.png", torch.from_numpy(style_image(96, 96, seed=0)))
    opts = st.StylizeOptions(keyviews=2, max_side=48, path_frames=0, sheet_views=2)
    ratio = {}
    for name, kw in (("default", {}), ("previous", {"color_transfer": "off", "style_loss": "nnfm"})):
        m = st.stylize_run(run, tmp_path / "art.png", tmp_path / name, device="cpu", progress=False, opts=opts,
                           stage2=st.Stage2Config(iters=30, checkpoint_every=1000, **kw))
        b, a = m["style_distance_original"], m["style_distance"]
        ratio[name] = {k: a[k] / b[k] for k in ("color", "texture")}
    assert m["extractor"].startswith("random-multiscale") and m["stage1"]["ran"] is False
    assert ratio["default"]["color"] < 0.88 and ratio["default"]["texture"] < 0.97, ratio
    assert ratio["default"]["color"] < ratio["previous"]["color"] - 0.03, ratio
    assert ratio["default"]["texture"] < ratio["previous"]["texture"], ratio


def test_default_zeroes_the_view_dependent_bands_and_lowers_the_consistency_error():
    """``sh_rest="zero"`` (the default) against ``keep`` on a scene with view-dependent colour (SH
    degree 1, bands ~0.15): the stylized scene's bands are exactly 0, and its reprojection RMSE
    between views is lower. Measured here (2026-11-23, CPU, 6 steps): short 0.0195 vs 0.0291
    (x0.67), long 0.0549 vs 0.0691 (x0.79); colour distance to the style 12.3 (unstylized 17.2).
    Asserted with about half of those margins."""
    from ssgwarp.evaluation.evaluate import EvalOptions, consistency
    from ssgwarp.raster.rendering import render_views
    from ssgwarp.core.imaging import fit_style
    from ssgwarp.evaluation.style_distance import StyleDistance

    assert st.Stage2Config().sh_rest == "zero"
    scene, _ = two_objects(n=50)
    g = torch.Generator().manual_seed(1)
    scene = scene.with_sh_degree(1)
    scene = scene.replace(sh_rest=0.15 * torch.randn(scene.sh_rest.shape, generator=g))
    cams = ring(n=5)
    style = torch.rand(40, 40, 3, generator=g)
    style[:, :20] *= 0.3
    ext = RandomMultiScale(seed=0).freeze()
    dist, opts = StyleDistance(style), EvalOptions(gap=3, max_pairs=8)

    def score(sc):
        rgb, depth, alpha = render_views(sc, cams, [0.0, 0.0, 0.0])
        rep = consistency(rgb, depth, alpha, cams, opts)["reprojection"]
        return rep["short"]["rmse"], rep["long"]["rmse"], float(dist.mean(rgb, alpha)["color"])

    out = {}
    for sh in ("keep", None):
        cfg = st.Stage2Config(mode="global", iters=6, lr=0.05, **({"sh_rest": sh} if sh else {}))
        work, _ = stylize_color.transfer_colors(scene, cams, style[None], max_gain=st.resolve_for(cfg, ext).color_max_gain)
        targets = st.build_targets(ext, fit_style(style, 32, 48).permute(0, 2, 3, 1), None, cfg)
        res = st.optimise(work, cams, cfg, loss=st.ViewLoss(ext, targets, cfg), progress=False)
        out[sh or "default"], _ = stylize_color.transfer_colors(res.scene, cams, style[None], max_gain=st.resolve_for(cfg, ext).color_max_gain)
    assert float(out["default"].sh_rest.abs().max()) == 0.0 and float(out["keep"].sh_rest.abs().max()) > 0.1
    src, keep, default = score(scene), score(out["keep"]), score(out["default"])
    assert default[0] < 0.85 * keep[0] and default[1] < 0.9 * keep[1], (keep, default)
    assert default[2] < 0.85 * src[2], (src, default)           # still clearly closer to the style's colours


def test_fit_style_scales_the_style_to_the_views_shorter_side_keeping_its_aspect():
    """The one rule Stage 2's global targets, the Gram loss and the style distance use
    (``[1, 3, h, w]``; Stage 2 permutes it to ``[1, h, w, 3]``)."""
    from ssgwarp.core.imaging import fit_style

    style = torch.rand(100, 300, 3)
    assert fit_style(style, 24, 32).shape == (1, 3, 24, 72)        # shorter side 24, aspect 3:1 kept
    assert fit_style(style, 600, 800).shape == (1, 3, 600, 1800)   # enlarged too
    same = torch.rand(24, 40, 3)
    assert torch.equal(fit_style(same, 24, 99)[0].permute(1, 2, 0), same)   # already the size: untouched
    small = fit_style(torch.rand(50, 50, 3), 4, 6)
    assert small.shape == (1, 3, 4, 4) and 0.0 <= float(small.min()) and float(small.max()) <= 1.0
    assert fit_style(style, 24, 32, scale=2).shape == (1, 3, 48, 144)      # --style-scale: patterns twice as large
    assert fit_style(style, 24, 32, scale=0.5).shape == (1, 3, 12, 36)


def test_style_scale_sizes_the_style_the_loss_and_the_colour_transfer_see(tmp_path, monkeypatch):
    """``--style-scale 2``: Stage 2's style targets (and the colour transfer) take the style image at twice the
    views' shorter side, so a stripe of the style spans twice as many pixels of a render; the run records it."""
    import ssgwarp.stylization.stylize as stylize_mod
    import ssgwarp.stylization.targets as targets_mod
    from ssgwarp.core.fileio import read_json, write_image
    from ssgwarp.core.imaging import fit_style

    run, _ = _write_run(tmp_path, grouped=False)
    stripes = torch.zeros(64, 96, 3)
    stripes[:, (torch.arange(96) // 8) % 2 == 1] = 1.0             # vertical stripes 8 px wide
    write_image(tmp_path / "stripes.png", stripes)
    seen = {"targets": [], "colour": []}
    real_targets, real_colours = stylize_mod.build_targets, targets_mod.transfer_colors
    monkeypatch.setattr(stylize_mod, "build_targets", lambda ext, images, *a, **kw: seen["targets"].append(images)
                        or real_targets(ext, images, *a, **kw))
    monkeypatch.setattr(targets_mod, "transfer_colors", lambda sc, cams, target, **kw: seen["colour"].append(target)
                        or real_colours(sc, cams, target, **kw))
    cams = Cameras.load(run / "cameras.json")
    for scale in (1.0, 2.0):
        seen["targets"].clear(), seen["colour"].clear()
        st.stylize_run(run, tmp_path / "stripes.png", tmp_path / f"o{scale:g}", device="cpu", progress=False,
                       opts=st.StylizeOptions(path_frames=0, sheet_views=1),
                       stage2=st.Stage2Config(mode="global", iters=2, checkpoint_every=1000, style_scale=scale))
        want = fit_style(stripes, cams.height, cams.width, scale).permute(0, 2, 3, 1)
        assert min(want.shape[1:3]) == round(scale * min(cams.height, cams.width))
        for target in seen["targets"] + seen["colour"]:
            assert target.shape == want.shape
            torch.testing.assert_close(target.float(), want, atol=2e-3, rtol=0)
        assert len(seen["targets"]) == 1 and len(seen["colour"]) == 2
        bright = seen["targets"][0][0, 0, :, 0] > 0.5                # one row of the style as the loss sees it
        edges = bright[1:].ne(bright[:-1]).nonzero()[:, 0]
        assert set(edges.diff().tolist()) == {round(8 * scale * min(cams.height, cams.width) / 64)}   # stripe width
        assert read_json(tmp_path / f"o{scale:g}" / "metrics.json")["config"]["style_scale"] == scale


def test_content_loss_relative_is_the_feature_mse_over_the_references_mean_square():
    """One content loss: absolute for the metric, ``relative=True`` for Stage 2's term (so a weight
    means the same for every extractor): by hand on two layers."""
    from ssgwarp.evaluation.features import content_loss

    f = [torch.full((2, 1, 2, 2), 3.0), torch.full((2, 4, 1, 1), 1.0)]
    r = [torch.full((2, 1, 2, 2), 1.0), torch.full((2, 4, 1, 1), 2.0)]
    torch.testing.assert_close(content_loss(f, r), torch.tensor([2.5, 2.5]))              # (4 + 1) / 2
    torch.testing.assert_close(content_loss(f, r, relative=True), torch.tensor([2.125, 2.125]))  # (4/1 + 1/4) / 2
    x = torch.randn(1, 3, 5, 5)
    assert float(content_loss([x * 7], [x * 7], relative=True)[0]) == 0.0
    assert content_loss([x], [torch.zeros_like(x)], relative=True).isfinite().all()     # zero reference: no 0/0


def test_tv_default_resolves_by_extractor_and_smooths_the_weight_free_renders():
    """``tv_weight=None`` (the default, CLI too) is 0.5 on the weight-free random features and 0.02 on
    VGG16 (the weighted path, unchanged); an explicit weight wins. On the random features it gives
    smoother renders than the previous 0.02 at a similar style distance. Measured here (2026-11-23, CPU,
    300 Gaussians with SH degree 1, 30 steps, lr 0.3): mean TV of the renders 0.00279 vs 0.00291 (x0.957;
    unstylized 0.00170), colour distance 5.35 vs 5.23 (unstylized 15.2), texture 1.697 vs 1.684 (1.893). At this scale the consistency RMSE
    moves by < 1 % either way; on fern (H100, 25 styles) the worst ratio fell from 1.55x/1.63x to
    1.29x/1.36x (docs/notes/stylize-history.md). Asserted: half the TV margin, and still clearly closer to the style."""
    from ssgwarp.core.imaging import fit_style
    from ssgwarp.raster.rendering import render_views
    from ssgwarp.evaluation.style_distance import StyleDistance
    import argparse

    ext = RandomMultiScale(seed=0).freeze()

    class _Vgg:
        name = "vgg16:conv3"

    assert st.Stage2Config().tv_weight is None
    assert st.tv_weight_for(st.Stage2Config(), ext) == fd.TV_WEIGHT_FREE == 0.5
    assert st.tv_weight_for(st.Stage2Config(), _Vgg()) == fd.TV_WEIGHT_VGG == 0.02
    assert st.tv_weight_for(st.Stage2Config(tv_weight=0.0), ext) == 0.0
    from ssgwarp.commands.stylize import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["scene", "--style", "s.png", "--out", "o"])
    assert args.tv_weight is None and args.blend_weight is None and args.color_max_gain is None
    assert args.content_weight is None and st.Stage2Config().content_weight is None
    assert args.color_detail == "auto"
    # the options left to the features: edge features -> spread 0.65, gain 1.0, texture kept; else 0, 1.3, off
    edges = RandomMultiScale(seed=0, edges=True, scales=(2, 4, 8)).freeze()
    r = st.resolve_for(st.Stage2Config(), edges)
    assert (r.blend_weight, r.color_max_gain, r.color_detail) == (fd.BLEND_WEIGHT_EDGES, fd.COLOR_GAIN_EDGES, "keep")
    assert (fd.BLEND_WEIGHT_EDGES, fd.COLOR_GAIN_EDGES) == (0.65, 1.0)
    for other in (ext, _Vgg()):
        r = st.resolve_for(st.Stage2Config(), other)
        assert (r.blend_weight, r.color_max_gain, r.color_detail) == (0.0, fd.COLOR_GAIN_OTHER, "off")
    for any_but_patches in (edges, ext, _Vgg()):
        assert st.resolve_for(st.Stage2Config(), any_but_patches).content_weight == 0.05
    mine = st.Stage2Config(content_weight=0.3, blend_weight=0.1, color_max_gain=2.0, color_detail="off")
    assert st.resolve_for(mine, edges) == mine                   # what is set stays set
    assert st.ViewLoss(edges, None, st.Stage2Config()).cfg.blend_weight == fd.BLEND_WEIGHT_EDGES

    scene, _ = two_objects(n=300)
    g = torch.Generator().manual_seed(1)
    scene = scene.with_sh_degree(1)      # view-dependent colour, zeroed by the default sh_rest
    scene = scene.replace(sh_rest=0.15 * torch.randn(scene.sh_rest.shape, generator=g))
    cams = ring(n=5)
    style = torch.rand(40, 40, 3, generator=g)
    style[:, :20] *= 0.3
    dist = StyleDistance(style)

    def score(sc):
        rgb, _, alpha = render_views(sc, cams, [0.0, 0.0, 0.0])
        d = dist.mean(rgb, alpha)
        return float(sum(s2.tv_loss(x) for x in rgb)) / len(rgb), float(d["color"]), float(d["texture"])

    out = {}
    for tv in (0.02, None):
        cfg = st.Stage2Config(mode="global", iters=30, lr=0.3, tv_weight=tv)
        work, _ = stylize_color.transfer_colors(scene, cams, style[None], max_gain=st.resolve_for(cfg, ext).color_max_gain)
        loss = st.ViewLoss(ext, st.build_targets(ext, fit_style(style, 32, 48).permute(0, 2, 3, 1), None, cfg), cfg)
        assert loss.tv_weight == (0.5 if tv is None else tv)
        res = st.optimise(work, cams, cfg, loss=loss, progress=False)
        out[tv], _ = stylize_color.transfer_colors(res.scene, cams, style[None], max_gain=st.resolve_for(cfg, ext).color_max_gain)
    src, prev, default = score(scene), score(out[0.02]), score(out[None])
    assert default[0] < 0.98 * prev[0], (prev, default)
    assert default[1] < 0.5 * src[1] and default[2] < src[2], (src, default)


def test_background_is_recoloured_with_the_scene_and_evaluated_on(tmp_path):
    """``background="transfer"`` (the default): the capture's background goes through the same colour
    transfer as the scene (pre and post), the run records it, its renders and ``ssgwarp evaluate``
    show the scene on it, while the unstylized source is still scored on the capture's; ``keep``
    leaves it as captured. (Why: on the demo scene a style that darkens the scene otherwise draws a
    hard outline against the white background, which the texture distance counts:
    docs/notes/stylize-history.md, "Why the demo's texture distance does not fall".)"""
    from ssgwarp.core.fileio import read_image, write_image
    from ssgwarp.evaluation.evaluate import EvalOptions, evaluate_run
    from ssgwarp.stylization.color import transfer_background
    from ssgwarp.services.runs import Run

    assert st.Stage2Config().background == "transfer"
    run, _ = _write_run(tmp_path, grouped=False)                 # captured on black
    g = torch.Generator().manual_seed(0)
    write_image(tmp_path / "light.png", 0.75 + 0.05 * torch.rand(32, 32, 3, generator=g))   # a light, flat style
    opts = st.StylizeOptions(path_frames=0, sheet_views=1)
    out = {}
    for bg in ("transfer", "keep"):
        m = st.stylize_run(run, tmp_path / "light.png", tmp_path / bg, device="cpu", progress=False, opts=opts,
                           stage2=st.Stage2Config(mode="global", iters=2, checkpoint_every=1000, background=bg))
        out[bg] = m
    assert out["keep"]["background"] == [0.0, 0.0, 0.0]
    ct = out["transfer"]["color_transfer"]
    expect = transfer_background(transfer_background([0.0, 0.0, 0.0], ct["pre"]), ct["post"])
    assert out["transfer"]["background"] == pytest.approx(expect, abs=1e-6)
    assert sum(expect) / 3 > 0.15 and min(expect) > 0.05        # black became a colour of the light style
    assert Run.open(tmp_path / "transfer").background([0.0, 0.0, 0.0]) == pytest.approx(expect, abs=1e-6)
    # the saved renders show it where there is no scene (the image corners of this ring of cameras)
    img = read_image(next((tmp_path / "transfer" / "renders" / "train").glob("*.png")), 3)
    assert abs(float(img[0, 0].mean()) - sum(expect) / 3) < 0.02
    ev = evaluate_run(tmp_path / "transfer", EvalOptions(path_frames=4, max_pairs=2, save_pairs=0), "cpu", write=False)
    assert ev["background"] == pytest.approx(expect, abs=1e-6)
    ev_keep = evaluate_run(tmp_path / "keep", EvalOptions(path_frames=4, max_pairs=2, save_pairs=0), "cpu", write=False)
    # the source is scored on the capture's background in both: the same "before" distances
    sc, sk = ev["style_content"], ev_keep["style_content"]
    assert sc["style_distance_color_original"] == pytest.approx(sk["style_distance_color_original"], rel=1e-9)
    assert sc["style_distance_texture_original"] == pytest.approx(sk["style_distance_texture_original"], rel=1e-9)


def test_colour_transfer_matches_the_style_as_the_loss_and_the_distance_see_it(tmp_path, monkeypatch):
    """Against the style image, the colour statistics are those of the style resized to the views
    (:func:`fit_style`, as the style loss and the style distance take it), not of the full-size file:
    a style of 1-pixel black and white lines, which at the views' size is a mid grey, must not get the
    scene stretched to black and white (docs/notes/stylize-history.md: the demo's line-art styles)."""
    import ssgwarp.stylization.targets as stylize_mod     # (where stylize's colour transfer is called)
    from ssgwarp.core.fileio import write_image
    from ssgwarp.core.imaging import fit_style

    run, _ = _write_run(tmp_path, grouped=False)
    lines = torch.zeros(256, 256, 3)
    lines[::2] = 1.0                                              # 1-pixel lines: variance 0.25 at full size
    write_image(tmp_path / "lines.png", lines)
    seen = []
    real = stylize_mod.transfer_colors
    monkeypatch.setattr(stylize_mod, "transfer_colors", lambda sc, cams, target, **kw: seen.append(target) or
                        real(sc, cams, target, **kw))
    st.stylize_run(run, tmp_path / "lines.png", tmp_path / "o", device="cpu", progress=False,
                   opts=st.StylizeOptions(path_frames=0, sheet_views=1),
                   stage2=st.Stage2Config(mode="global", iters=2, checkpoint_every=1000))
    assert len(seen) == 2                                         # before and after the optimisation
    cams = Cameras.load(run / "cameras.json")
    want = fit_style(lines, cams.height, cams.width).permute(0, 2, 3, 1)
    for target in seen:
        assert target.shape == want.shape and min(target.shape[1:3]) == min(cams.height, cams.width)
        torch.testing.assert_close(target.float(), want, atol=2e-3, rtol=0)   # (8-bit file)
        assert float(target.var()) < 0.02                         # grey at that size, not 0.25


# ----------------------------------------------------------------------------- issue 39: style, not only colour
def test_random_strokes_features_see_far_and_ignore_flat_colour():
    """random-strokes: seeded (same filters for a seed), one output per branch and dilation, unit mean square
    per layer on noise; the deepest layer of the coarsest branch responds to a change ~40 px away (the
    shallow branches cannot), and a flat colour gives the same response everywhere in the first layer."""
    from ssgwarp.evaluation.features import RandomStrokes, load_extractor, stack_features

    a, b = RandomStrokes(seed=3).freeze(), RandomStrokes(seed=3).freeze()
    assert a.name == "random-strokes:seed3,c48s2p2-4d1-2-4-8" and len(a.strides) == 8
    x = torch.rand(1, 3, 96, 128, generator=torch.Generator().manual_seed(0))
    fa = a(x)
    assert len(fa) == 8 and all(f.shape == (1, 48, 48, 64) for f in fa)
    assert all(torch.equal(u, v) for u, v in zip(fa, b(x)))
    assert not torch.equal(stack_features(fa), stack_features(RandomStrokes(seed=4).freeze()(x)))
    # receptive field: change a 4x4 patch at the left edge; look at the feature 40 px to its right
    y = x.clone()
    y[..., 46:50, 0:4] = 1 - y[..., 46:50, 0:4]
    fy = a(y)
    far = lambda f, g: float((f[0, :, 24, 22] - g[0, :, 24, 22]).abs().max())   # noqa: E731  (44 px right)
    assert far(fa[7], fy[7]) > 1e-3                        # 1/4 branch, dilation 8: sees it
    assert far(fa[0], fy[0]) == 0.0                        # 1/2 branch, first layer (6 px): does not
    shallow = RandomMultiScale(seed=3, edges=True, scales=(2, 4, 8)).freeze()
    assert all(far(f, g) == 0.0 for f, g in list(zip(shallow(x), shallow(y)))[:2])   # 1/2, 1/4 branches: blind
    # the first layer's filters are zero-mean: a flat image gives one value per channel (before pooling)
    flat = a._raw(torch.full((1, 3, 32, 32), 0.3))[0][0]
    assert float((flat - flat.mean(dim=(2, 3), keepdim=True)).abs().max()) < 1e-5
    assert load_extractor(kind="random-strokes").name == a.name.replace("seed3", "seed0")
    with pytest.raises(InputError):
        RandomStrokes(dilations=(0,))


def test_patches_features_are_centred_windows_at_every_level():
    """patches: per level a pixel's feature is the normalised image's 5x5 window there (box-averaged for the
    coarser levels), each colour channel's window mean removed: a flat colour gives exact zeros, an edge
    gives the window's values; every level at full resolution; differentiable; the edge-feature defaults."""
    from ssgwarp.evaluation.features import IMAGENET_MEAN, IMAGENET_STD, PyramidPatches, load_extractor, stack_features
    from ssgwarp.stylization.feature_defaults import resolve_for

    ext = PyramidPatches().freeze()
    assert ext.name == "patches:p5s1-2-4" and load_extractor(kind="patches").name == ext.name
    x = torch.rand(1, 3, 24, 32, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    f = ext.to(torch.float64)(x)
    assert [t.shape for t in f] == [(1, 75, 24, 32)] * 3
    xn = (x - torch.tensor(IMAGENET_MEAN, dtype=x.dtype).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD, dtype=x.dtype).view(1, 3, 1, 1)
    for level, (s, y, c) in enumerate([(1, 10, 13), (2, 10, 13), (4, 9, 21)]):
        xs = F.avg_pool2d(xn, s) if s > 1 else xn
        win = xs[0, :, y // s - 2:y // s + 3, c // s - 2:c // s + 3].reshape(3, 25)
        torch.testing.assert_close(f[level][0, :, y, c], (win - win.mean(1, keepdim=True)).reshape(75))
    flat = ext(torch.full((2, 3, 16, 16), 0.3))
    assert all(float(t.abs().max()) < 1e-6 for t in flat)
    g = x.clone().requires_grad_(True)
    stack_features(ext.to(torch.float64)(g)).pow(2).sum().backward()
    assert g.grad is not None and float(g.grad.abs().sum()) > 0
    cfg = resolve_for(st.Stage2Config(), ext)
    assert (cfg.blend_weight, cfg.color_max_gain, cfg.color_detail) == (0.65, 1.0, "keep")
    assert cfg.content_weight == 0.01          # their content term holds the scene's own patterns: lighter
    assert resolve_for(st.Stage2Config(content_weight=0.05), ext).content_weight == 0.05
    # ... and the loss weighs its content term so: style, TV and spread off, total = 0.01 x content
    view = torch.rand(1, 12, 16, 3, generator=torch.Generator().manual_seed(2))
    quiet = st.Stage2Config(mode="global", style_weight=0.0, tv_weight=0.0, blend_weight=0.0)
    loss = st.ViewLoss(ext, st.build_targets(ext, view, None, quiet), quiet, originals=view.flip(2))
    total = float(loss(view[0], 0))
    assert loss.last["content"] > 0.1 and total == pytest.approx(0.01 * loss.last["content"], rel=1e-6)
    with pytest.raises(InputError):
        st.Stage2Config(content_weight=-1.0).validate()
    with pytest.raises(InputError):
        PyramidPatches(patch=1)
    with pytest.raises(InputError):
        PyramidPatches(scales=(0, 2))


def test_split_gaussians_keeps_each_gaussians_moments_and_the_render():
    from ssgwarp.core.geometry import quat_to_rotmat
    from ssgwarp.stylization.densify import replay, split_gaussians

    scene, _ = two_objects(n=30, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    scene = scene.replace(log_scales=scene.log_scales + torch.rand(len(scene), 3, generator=g, dtype=torch.float64),
                          quats=torch.randn(len(scene), 4, generator=g, dtype=torch.float64))
    idx = torch.tensor([3, 7, 40])
    out, parent = split_gaussians(scene, idx)
    assert len(out) == len(scene) + 3 and parent.tolist()[-6:] == [3, 3, 7, 7, 40, 40]
    keep = parent[:-6]
    assert torch.equal(out.means[:-6], scene.means[keep]) and torch.equal(out.sh_dc[-6:], scene.sh_dc[parent[-6:]])

    def cov(sc, i):
        R = quat_to_rotmat(sc.quats[i:i + 1])[0]
        return R @ torch.diag(sc.log_scales[i].exp() ** 2) @ R.T

    for k, p in enumerate(idx.tolist()):
        c1, c2 = len(out) - 6 + 2 * k, len(out) - 5 + 2 * k
        mean = (out.means[c1] + out.means[c2]) / 2
        d = out.means[c1] - mean
        mix = (cov(out, c1) + cov(out, c2)) / 2 + torch.outer(d, d)       # covariance of the equal mixture
        torch.testing.assert_close(mean, scene.means[p])
        torch.testing.assert_close(mix, cov(scene, p))
        a, a2 = torch.sigmoid(scene.logit_opacities[p]), torch.sigmoid(out.logit_opacities[c1])
        torch.testing.assert_close(1 - (1 - a2) ** 2, a)                   # two overlapping children block as one
    cams = ring(n=3, dtype=torch.float64)
    every, _ = split_gaussians(scene, torch.arange(len(scene)))
    before, after = st.render_rgb(scene, cams), st.render_rgb(every, cams)
    assert float((before - after).abs().mean()) < 0.1 * float(before.abs().mean())
    again, p2 = replay(scene, [idx])
    assert torch.equal(again.means, out.means) and torch.equal(p2, parent)
    with pytest.raises(InputError):
        split_gaussians(scene, torch.tensor([len(scene)]))


def _one_big_gaussian():
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    return GaussianScene(torch.zeros(1, 3, dtype=torch.float64), torch.full((1, 3), -0.7, dtype=torch.float64), q,
                         torch.tensor([3.0], dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64))


def test_detail_demand_is_the_spread_of_the_pixels_wishes():
    """D = sum w |g|^2 - |sum w g|^2 / sum w: zero when every pixel wants the same change, positive when the
    left and right halves of a splat want opposite ones; densify splits only where D > 0, within the budget."""
    from ssgwarp.stylization.densify import densify_for_style, detail_demand

    scene = _one_big_gaussian()
    cams = ring(n=1, dtype=torch.float64)
    render = lambda sc, cam: st.render_rgb(sc, cam)       # noqa: E731
    H, W = cams.height, cams.width
    same = lambda sc, v: torch.ones(H, W, 3, dtype=torch.float64)       # noqa: E731
    halves = torch.ones(H, W, 3, dtype=torch.float64)
    halves[:, : W // 2] = -1
    opposite = lambda sc, v: halves                                       # noqa: E731
    d_same = detail_demand(scene, cams, [0], same, render)
    d_opp = detail_demand(scene, cams, [0], opposite, render)
    assert float(d_same[0]) < 1e-9 * float(d_opp[0]) + 1e-12 and float(d_opp[0]) > 0
    out, parent, rec = densify_for_style(scene, cams, opposite, render, budget=1.0, views=1, rounds=1)
    assert len(out) == 2 and parent.tolist() == [0, 0] and rec["split"] == [1]
    kept, _, rec0 = densify_for_style(scene, cams, same, render, budget=1.0, views=1, rounds=1)
    assert len(kept) == 1 and rec0["split"] == []                      # no demand: nothing split
    big, _ = two_objects(n=20, dtype=torch.float64)
    rnd = lambda sc, v: torch.randn(H, W, 3, generator=torch.Generator().manual_seed(v), dtype=torch.float64)  # noqa: E731
    out, _, rec = densify_for_style(big, ring(n=3, dtype=torch.float64), rnd, render, budget=0.25, views=2)
    assert len(out) - len(big) <= 10 and rec["gaussians_after"] == len(out) and rec["views"] == 2
    with pytest.raises(InputError):
        densify_for_style(big, cams, rnd, render, budget=-1)


def test_style_regions_segment_the_style_and_assign_groups_by_their_statistics():
    """A style image of a dark textured left half and a bright flat right half gives those two regions; a
    dark group takes the dark region and a bright one the bright region (OT on standardized statistics)."""
    from ssgwarp.stylization.regions import assign_groups, kmeans, segment_style, sinkhorn, style_regions

    g = torch.Generator().manual_seed(0)
    style = torch.empty(40, 60, 3)
    style[:, :30] = 0.15 + 0.1 * torch.rand(40, 30, 3, generator=g)
    style[:, 30:] = torch.tensor([0.9, 0.85, 0.6])
    lab = segment_style(style, 2)
    assert lab.shape == (40, 60) and set(lab.unique().tolist()) == {0, 1}
    left, right = lab[:, 2:27], lab[:, 33:58]
    assert left.unique().numel() == 1 and right.unique().numel() == 1 and int(left[0, 0]) != int(right[0, 0])
    # the scene: two objects rendered dark (group 0) and bright (group 1)
    renders = torch.empty(1, 20, 20, 3)
    renders[0, :, :10] = 0.8
    renders[0, :, 10:] = 0.2
    vl = torch.zeros(1, 20, 20, dtype=torch.long)
    vl[0, :, 10:] = 0   # dark half is group 0
    vl[0, :, :10] = 1   # bright half is group 1
    res = style_regions(style, renders, vl, 2, regions=2)
    dark_region = int(lab[0, 0])
    assert res["region"].tolist() == [dark_region, 1 - dark_region]
    assert res["fallback"] is None      # (the region check is --region-check's: off by default)
    checked = style_regions(style, renders, vl, 2, regions=2, check=True)
    assert checked["fallback"] is not None and set(checked["fallback"]) >= {"halves", "fell_back", "predicted_after"}
    # Sinkhorn: the plan's marginals are the weights
    a, b = torch.tensor([0.3, 0.7], dtype=torch.float64), torch.tensor([0.5, 0.25, 0.25], dtype=torch.float64)
    plan = sinkhorn(torch.rand(2, 3, generator=g, dtype=torch.float64), a, b)
    torch.testing.assert_close(plan.sum(1), a, atol=1e-6, rtol=0)
    torch.testing.assert_close(plan.sum(0), b, atol=1e-6, rtol=0)
    # a group without pixels gets the largest region; k-means is deterministic for a seed
    region = assign_groups(torch.rand(3, 3, dtype=torch.float64), torch.tensor([0.5, 0.5, 0.0], dtype=torch.float64),
                           torch.rand(2, 3, dtype=torch.float64), torch.tensor([0.2, 0.8], dtype=torch.float64))
    assert int(region[2]) == 1
    pts = torch.rand(200, 2, generator=g)
    assert torch.equal(kmeans(pts, 3, seed=5)[0], kmeans(pts, 3, seed=5)[0])
    with pytest.raises(InputError):
        segment_style(style, 0)


def test_a_group_whose_region_is_a_poor_match_falls_back_to_the_whole_style():
    """Issue 62: a style of 85 % smooth blue and a 15 % dark noisy strip. A group holding 90 % of the views given
    the strip would make the view look like the strip (farther from the style than its halves): it falls back to
    the whole style (GLOBAL), and Stage 2's targets and colour transfer then match it against everything; the
    same group given the blue region keeps it, as does the small group given the strip."""
    from ssgwarp.stylization.matching import SlicedTargets
    from ssgwarp.stylization.regions import GLOBAL, fall_back_poor_matches

    g = torch.Generator().manual_seed(0)
    style = torch.tensor([0.2, 0.3, 0.8]) + 0.05 * torch.rand(48, 64, 3, generator=g)
    style[:, 54:] = 0.1 + 0.3 * torch.rand(48, 10, 3, generator=g)
    lab = torch.zeros(48, 64, dtype=torch.long)
    lab[:, 54:] = 1
    mass = torch.tensor([0.9, 0.1])
    region, rec = fall_back_poor_matches(style, lab, torch.tensor([1, 0]), mass)
    assert region.tolist() == [GLOBAL, 0] and rec["fell_back"] == [0]
    assert rec["predicted_before"][0] > rec["halves"][0] > rec["predicted_after"][0]
    kept, rec = fall_back_poor_matches(style, lab, torch.tensor([0, 1]), mass)
    assert kept.tolist() == [0, 1] and rec["fell_back"] == [] and rec["predicted_after"] == rec["predicted_before"]
    # a fallen-back group matches every key position (the whole style), the other its region's
    feats = torch.randn(1, 4, 6, 8, generator=g)
    labels = torch.zeros(1, 6, 8, dtype=torch.long)
    labels[..., 6:] = 1
    t = SlicedTargets(feats, labels, projections=8).for_regions(region)
    assert t.key_index(0) is None and len(t.key_index(1)) == 36


def test_sliced_targets_for_regions_match_each_group_against_its_region():
    from ssgwarp.stylization.matching import SlicedTargets

    g = torch.Generator().manual_seed(0)
    feats = torch.randn(1, 4, 6, 8, generator=g)
    regions = torch.zeros(1, 6, 8, dtype=torch.long)
    regions[..., 4:] = 1
    t = SlicedTargets(feats, regions, projections=8).for_regions(torch.tensor([1, 1, 0]))
    assert torch.equal(t.key_index(0), t.key_index(1)) and len(t.key_index(2)) == 24
    assert set(t.key_index(0).tolist()) == {r * 8 + c for r in range(6) for c in range(4, 8)}
    # the loss of a view of group 2 made of region 0's features is ~0, of region 1's is not
    q0 = feats[0, :, :, :4].clone()
    lab = torch.full((6, 4), 2)
    assert float(t.loss(q0, lab)) < 1e-6 and float(t.loss(feats[0, :, :, 4:], lab)) > 1e-3
    with pytest.raises(InputError):
        SlicedTargets(feats, None).for_regions([0])


def test_hold_empty_keeps_the_background_pixels_and_needs_alphas():
    scene, obj = two_objects(n=40)
    cams = ring(n=2)
    originals = st.render_rgb(scene, cams)
    alphas = st.render_alphas(scene, cams)
    ext = RandomMultiScale(seed=0, channels=8).freeze()
    targets = st.build_targets(ext, originals[:1], None, st.Stage2Config(style_loss="sw"))
    cfg = st.Stage2Config(style_loss="sw", hold_empty=1.0, content_weight=0.0, tv_weight=0.0, blend_weight=0.0,
                          style_weight=0.0)
    loss = st.ViewLoss(ext, targets, cfg, originals=originals, alphas=alphas)
    img = originals[0].clone()
    assert float(loss(img, 0)) == 0.0
    empty = alphas[0] < 0.05
    assert bool(empty.any())
    moved = img.clone()
    moved[empty] = moved[empty] * 0 + torch.tensor([1.0, 0.0, 1.0])      # colour the empty pixels
    inside = img.clone()
    full = alphas[0] > 0.99
    inside[full] = inside[full] * 0 + torch.tensor([1.0, 0.0, 1.0])      # colour the scene's pixels
    assert float(loss(moved, 0)) > 100 * float(loss(inside, 0)) and "empty" in loss.last
    with pytest.raises(InputError):
        st.ViewLoss(ext, targets, cfg, originals=originals)


def test_path_video_is_a_looping_gif_of_every_frame(tmp_path):
    from PIL import Image

    from ssgwarp.core.imaging import write_video   # (path.gif's writer; ssgwarp render --video's too)

    frames = [(torch.rand(12, 16, 3, generator=torch.Generator().manual_seed(i)).numpy() * 255).astype("uint8")
              for i in range(5)]
    path = write_video(tmp_path / "path.gif", frames, fps=10)
    with Image.open(path) as im:
        assert im.format == "GIF" and im.n_frames == 5 and im.size == (16, 12) and im.info["loop"] == 0
        assert im.info["duration"] == 100
    big = [np.full((300, 1024, 3), 40 * i, dtype=np.uint8) for i in range(3)]   # shrunk to 512 px, colours kept
    with Image.open(write_video(tmp_path / "big.gif", big)) as im:
        assert im.size == (512, 150) and im.n_frames == 3
        im.seek(2)
        assert np.allclose(np.asarray(im.convert("RGB")), 80, atol=1)
    with pytest.raises(InputError):
        write_video(tmp_path / "none.gif", [])
    assert not (tmp_path / "none.gif").exists()


@pytest.mark.parametrize("period", [4, 9, 24])
def test_a_style_with_a_known_stroke_period_measures_that_period(period):
    """Issue 62: stripes of period p (oblique, on noise-free grey) measure p to within the 1/4-octave bin; the
    auto style scale moves a period below the features' reach up into it and leaves one inside alone."""
    import math

    from ssgwarp.stylization.scale import PERIOD_MAX, PERIOD_MIN, auto_style_scale, stroke_period

    y, x = torch.meshgrid(torch.arange(120.0), torch.arange(160.0), indexing="ij")
    stripes = (0.5 + 0.3 * torch.sin(2 * math.pi * (0.8 * x + 0.6 * y) / period))[..., None].expand(-1, -1, 3)
    assert abs(math.log2(stroke_period(stripes) / period)) <= 0.125 + 1e-9
    # at views of the style's own size the period lands as measured; views half as large halve it
    scale, at_views = auto_style_scale(stripes, 120, 160)
    assert at_views == pytest.approx(stroke_period(stripes))
    if at_views < PERIOD_MIN:
        assert scale * at_views == pytest.approx(PERIOD_MIN)
    elif at_views <= PERIOD_MAX:
        assert scale == 1.0
    half_scale, half = auto_style_scale(stripes, 60, 80)
    assert half == pytest.approx(at_views / 2) and half_scale >= scale
    with pytest.raises(InputError):
        stroke_period(torch.rand(8, 8, 3))


def test_style_scale_takes_auto_or_a_number_in_range():
    import argparse

    from ssgwarp.commands.stylize import style_scale_arg

    assert style_scale_arg("auto") == "auto" and style_scale_arg(" AUTO ") == "auto" and style_scale_arg("2") == 2.0
    with pytest.raises(argparse.ArgumentTypeError):
        style_scale_arg("big")
    st.Stage2Config(style_scale="auto").validate()
    for bad in ("big", 5.0, float("nan")):
        with pytest.raises(InputError, match="--style-scale"):
            st.Stage2Config(style_scale=bad).validate()


def test_the_consistency_probe_picks_a_weaker_strength_for_a_less_consistent_scene():
    """Issue 62: a textured wall seen by five cameras, and the same wall with its Gaussians scattered in depth
    (the colours as smooth, so the unpainted views agree about as well). Texture fixed in 3-D costs the scattered
    scene more consistency, so the probe gives it a lower painting strength; a probe that costs nothing gives
    the top of the range."""
    from ssgwarp.raster.scene import GaussianScene
    from ssgwarp.stylization.spread import STRENGTH_RANGE, consistency_probe, strength_for

    g = torch.Generator().manual_seed(0)
    n = 1200
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([2.4, 1.6])
    rgb = torch.stack([0.5 + 0.3 * torch.sin(2 * xy[:, 0]), 0.5 + 0.3 * torch.cos(3 * xy[:, 1]),
                       0.5 + 0.2 * xy[:, 0]], 1)
    ratio = {}
    for name, depth in (("wall", 0.0), ("scattered", 1.5)):
        z = (torch.rand(n, 1, generator=g) - 0.5) * depth
        scene = GaussianScene.from_points(torch.cat([xy, z], 1), rgb, opacity=0.9, scale=torch.full((n,), 0.04))
        ratio[name] = consistency_probe(scene, ring(W=64, H=48, n=5), torch.ones(3), 2, period_px=8, amplitude=0.05)
    assert 1.0 < ratio["wall"] < ratio["scattered"]
    assert STRENGTH_RANGE[0] < strength_for(ratio["scattered"]) < strength_for(ratio["wall"]) <= STRENGTH_RANGE[1]
    assert strength_for(1.0) == STRENGTH_RANGE[1] and strength_for(100.0) == STRENGTH_RANGE[0]


def test_stylize_records_the_auto_style_scale_and_paint_strength(tmp_path, monkeypatch):
    """``--style-scale auto --paint-strength auto``: the run measures the style's stroke period and probes the
    scene, divides the smoothing by the strength it found, and says both in metrics.json."""
    import json

    from ssgwarp.cli import main

    for var in ("SSGWARP_WEIGHTS", "SSGWARP_SD15", "SSGWARP_CONTROLNET_DEPTH", "SSGWARP_IP_ADAPTER",
                "SSGWARP_IMAGE_ENCODER", "SSGWARP_VGG16"):
        monkeypatch.delenv(var, raising=False)
    run, style = _write_run(tmp_path)
    out = tmp_path / "styled"
    assert main(["stylize", str(run), "--style", str(style), "--out", str(out), "--iters", "2", "--keyviews", "2",
                 "--max-side", "48", "--path-frames", "0", "--sheet-views", "1", "--device", "cpu", "--mode", "global",
                 "--style-scale", "auto", "--paint-strength", "auto", "--tv-weight", "0.2", "--offline"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert "style scale auto:" in m["matching"] and "stroke period" in m["matching"]
    s = m["strength"]
    assert s["setting"] == "auto" and s["probe_ratio"] > 0 and 0.5 <= s["strength"] <= 2.0
    assert s["tv_weight"] == pytest.approx(0.2 / s["strength"])
