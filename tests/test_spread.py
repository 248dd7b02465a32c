"""The blend-spread term of Stage 2 (ssgwarp.stylization.spread): its value by hand, and what it does."""
from __future__ import annotations

import pytest
import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.stylization import stylize as st
from ssgwarp.stylization.spread import SPREAD_CHANNELS, blend_spread, render_with_spread

from test_stylize import _Identity, ring, two_objects


def _front_camera(W: int = 24, H: int = 24, dtype=torch.float64) -> Cameras:
    vm = look_at(torch.tensor([[0.0, 0.0, -3.0]]), torch.zeros(1, 3), up=(0.0, -1.0, 0.0)).to(dtype)
    return Cameras(vm, intrinsics(30.0, 30.0, W / 2, H / 2, 1, dtype), W, H)


def _pair(c_front, c_back, keep=slice(None), dtype=torch.float64) -> GaussianScene:
    """Two Gaussians on the camera's axis, the front one (z = -0.5) in front of the back one (z = 0.5);
    ``keep`` selects some of them."""
    xyz = torch.tensor([[0.0, 0.0, -0.5], [0.05, 0.0, 0.5]], dtype=dtype)[keep]
    rgb = torch.tensor([c_front, c_back], dtype=dtype)[keep]
    return GaussianScene.from_points(xyz, rgb, opacity=0.6, scale=torch.tensor([0.3, 0.35], dtype=dtype)[keep])


def test_spread_of_two_gaussians_is_their_weighted_colour_variance():
    """Per pixel, with blend weights w1 (front), w2 (back): alpha Var = w1 w2 / (w1 + w2) |c1 - c2|^2.
    w1 is the front Gaussian's alpha rendered alone (it is first on every ray), w2 the pair's alpha minus w1."""
    cam = _front_camera()
    red, blue = (0.9, 0.1, 0.1), (0.1, 0.2, 0.9)
    scene = _pair(red, blue)
    with torch.no_grad():
        ch = render_with_spread(scene, cam)[0]
        w1 = _pair(red, blue, keep=slice(0, 1)).render(cam)[1][0, ..., 0]
    w2 = ch[..., 9] - w1
    assert float(w1.min()) >= 0 and float(w2.max()) > 0.05 and float(w1.max()) > 0.05
    d2 = sum((a - b) ** 2 for a, b in zip(red, blue))
    expected = torch.where(w1 + w2 > 1e-4, w1 * w2 / (w1 + w2).clamp_min(1e-12) * d2, torch.zeros_like(w1))
    assert float(blend_spread(ch)) == pytest.approx(float(expected.mean()), rel=1e-9, abs=1e-12)
    # the same colour front and back: no spread, whatever the geometry
    assert float(blend_spread(render_with_spread(_pair(red, red), cam)[0])) == pytest.approx(0.0, abs=1e-12)


def test_rgb_channels_are_stage2s_render_and_uniform_colour_has_no_spread():
    scene, _ = two_objects(60, dtype=torch.float64)
    cams = ring(32, 24, 3, dtype=torch.float64)
    bg = torch.tensor([0.2, 0.7, 0.4], dtype=torch.float64)
    with torch.no_grad():
        ch = render_with_spread(scene, cams, bg)
        rgb = st.render_rgb(scene, cams, bg)
    assert ch.shape == (3, 24, 32, SPREAD_CHANNELS)
    assert torch.allclose(ch[..., :3], rgb, atol=1e-10)
    assert float(blend_spread(ch)) > 1e-5                        # the scene's colours vary along rays
    flat = scene.replace(sh_dc=torch.full_like(scene.sh_dc, 0.3))
    with torch.no_grad():
        assert float(blend_spread(render_with_spread(flat, cams, bg))) == pytest.approx(0.0, abs=1e-12)


def _optimise_pair(blend_weight: float, steps: int = 30) -> tuple[float, float]:
    """Stage 2 on the pair with the style term off (style weight 0, no content, no TV): returns the colour
    distance between the two Gaussians before and after."""
    scene = _pair((0.9, 0.1, 0.1), (0.1, 0.2, 0.9))
    cam = _front_camera()
    ext = _Identity()
    cfg = st.Stage2Config(mode="global", iters=steps, lr=0.05, style_weight=0.0, content_weight=0.0, tv_weight=0.0,
                          blend_weight=blend_weight, style_loss="nnfm", color_transfer="off")
    keys = torch.rand(1, 4, 4, 3, dtype=torch.float64)
    loss = st.ViewLoss(ext, st.build_targets(ext, keys, None, cfg), cfg)
    out = st.optimise(scene, cam, cfg, loss=loss, progress=False).scene
    gap = lambda s: float((s.sh_dc[0] - s.sh_dc[1]).norm())  # noqa: E731
    return gap(scene), gap(out)


def test_blend_weight_pulls_the_colours_a_ray_mixes_together():
    before, after = _optimise_pair(blend_weight=5.0)
    assert after < 0.5 * before
    before0, after0 = _optimise_pair(blend_weight=0.0)   # no term: no gradient, the colours stay
    assert after0 == pytest.approx(before0, abs=1e-12)


def test_loss_with_blend_weight_refuses_an_image_without_the_spread_channels():
    """A loss built with blend_weight > 0 given a plain RGB render says so (it used to drop the term
    silently); given the spread channels it adds the term."""
    scene = _pair((0.9, 0.1, 0.1), (0.1, 0.2, 0.9))
    cam = _front_camera()
    ext = _Identity()
    cfg = st.Stage2Config(mode="global", style_weight=0.0, content_weight=0.0, tv_weight=0.0, blend_weight=1.0,
                          style_loss="nnfm", color_transfer="off")
    loss = st.ViewLoss(ext, st.build_targets(ext, torch.rand(1, 4, 4, 3, dtype=torch.float64), None, cfg), cfg)
    with torch.no_grad():
        rgb = st.render_rgb(scene, cam)[0]
        channels = render_with_spread(scene, cam)[0]
    with pytest.raises(ValueError, match="blend spread"):
        loss(rgb, 0)
    assert float(loss(channels, 0)) == pytest.approx(float(blend_spread(channels)), rel=1e-9)


def test_blend_weight_must_be_a_finite_non_negative_number():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="blend-weight"):
            st.Stage2Config(blend_weight=bad).validate()


def test_cli_flags_reach_every_stage2_field(monkeypatch):
    """``ssgwarp stylize --blend-weight 0.3 ...`` builds the Stage 2 options from the flags, field by field."""
    import dataclasses

    from ssgwarp.cli import main

    seen = {}

    def fake_run(scene_dir, style, out, *, stage2, **kw):
        seen["cfg"] = stage2
        return {}

    monkeypatch.setattr(st, "stylize_run", fake_run)
    assert main(["stylize", "run", "--style", "s.png", "--out", "o", "--blend-weight", "0.3", "--tv-weight", "0.1",
                 "--sh-bands", "--direct", "--device", "cpu"]) == 0
    cfg = seen["cfg"]
    assert cfg.blend_weight == 0.3 and cfg.tv_weight == 0.1 and cfg.sh_rest == "optimise" and cfg.deferred is False
    default = {f.name: getattr(st.Stage2Config(), f.name) for f in dataclasses.fields(st.Stage2Config)}
    changed = {k for k, v in dataclasses.asdict(cfg).items() if v != default[k]}
    assert changed == {"blend_weight", "tv_weight", "sh_rest", "deferred"}


# ----------------------------------------------------------------------------- the view-pair term
def _pairs_setup(dtype=torch.float64):
    from ssgwarp.stylization.spread import ViewPairs

    scene, _ = two_objects(80, dtype=dtype)
    cams = ring(32, 24, 5, dtype=dtype)
    return ViewPairs, scene, cams


def test_view_pairs_pair_each_camera_with_its_nearest_and_measure_what_evaluate_measures():
    """nearest(): the ring's cameras are ordered by angle, so camera 0's nearest are 1 then 2 and camera 2's
    are 1 and 3; error() is the masked mean squared difference against reprojection_warp's warped image."""
    from ssgwarp.evaluation.metrics import View, reprojection_warp

    ViewPairs, scene, cams = _pairs_setup()
    near = ViewPairs.nearest(cams, 2)
    assert near[0] == [1, 2] and sorted(near[2]) == [1, 3] and near[4] == [3, 2]
    assert [len(n) for n in ViewPairs.nearest(cams, 10)] == [4] * 5          # at most the other cameras
    pairs = ViewPairs.build(scene, cams, 2)
    assert pairs.depths.shape == pairs.alphas.shape == (5, 24, 32)
    assert set(pairs.reference) == {(v, u) for v in range(5) for u in near[v]}
    assert all(e > 0 for e in pairs.reference.values())
    noisy = scene.replace(sh_dc=scene.sh_dc + 0.5 * torch.randn(scene.sh_dc.shape, generator=torch.Generator()
                                                              .manual_seed(1), dtype=scene.sh_dc.dtype))
    with torch.no_grad():
        img = st.render_rgb(noisy, cams)
    image = img[1].clone().requires_grad_(True)
    e = pairs.error(image, 1, img[0], 0)
    res = reprojection_warp(View(img[0], pairs.depths[0], pairs.alphas[0], cams.viewmats[0], cams.Ks[0]),
                            View(img[1], pairs.depths[1], pairs.alphas[1], cams.viewmats[1], cams.Ks[1]))
    assert res.mask.sum() > 50
    by_hand = ((img[1] - res.warped) ** 2)[res.mask].mean()
    assert float(e.detach()) == pytest.approx(float(by_hand), rel=1e-9)
    e.backward()
    assert float(image.grad[~res.mask].abs().max()) == 0.0 and float(image.grad[res.mask].abs().max()) > 0
    # the hinge: relative to the pair's own reference, less the budget, never below 0
    pairs.budget = 0.0
    assert float(pairs.loss(img[1], 1, img[0], 0)) == pytest.approx(float(e.detach()) / pairs.reference[(1, 0)], rel=1e-9)
    pairs.budget = 1e6
    assert float(pairs.loss(img[1], 1, img[0], 0)) == 0.0
    assert float(pairs.loss(img[1], 1, img[4], 4)) == 0.0                    # 4 is not one of 1's neighbours


def test_neighbour_choice_is_a_function_of_seed_step_and_view():
    ViewPairs, scene, cams = _pairs_setup()
    pairs = ViewPairs.build(scene, cams, 3, seed=5)
    picks = [pairs.neighbour(2, s) for s in range(40)]
    assert picks == [pairs.neighbour(2, s) for s in range(40)]
    assert set(picks) == set(pairs.neighbours[2]) and len(set(picks)) == 3
    assert ViewPairs(cams[[0]], pairs.depths[:1], pairs.alphas[:1], [[]]).neighbour(0, 0) is None


def _pair_error(pairs, scene, cams) -> float:
    with torch.no_grad():
        img = st.render_rgb(scene, cams)
        return sum(float(pairs.error(img[v], v, img[u], u)) for v in range(len(cams)) for u in pairs.neighbours[v])


def test_consistency_weight_lowers_the_pair_error_and_needs_its_pairs():
    """Colours painted per Gaussian at random (inconsistent blends); Stage 2 with the view-pair term alone
    (no style, content or TV) lowers the summed pair error; without the term nothing changes."""
    ViewPairs, scene, cams = _pairs_setup()
    g = torch.Generator().manual_seed(3)
    noisy = scene.replace(sh_dc=scene.sh_dc + 0.8 * torch.randn(scene.sh_dc.shape, generator=g, dtype=scene.sh_dc.dtype))
    ext = _Identity()

    def run(weight: float):
        cfg = st.Stage2Config(mode="global", iters=40, lr=0.1, style_weight=0.0, content_weight=0.0, tv_weight=0.0,
                              blend_weight=0.0, style_loss="nnfm", color_transfer="off", consistency_weight=weight,
                              consistency_budget=0.0, consistency_neighbours=2)
        loss = st.ViewLoss(ext, st.build_targets(ext, torch.rand(1, 4, 4, 3, dtype=torch.float64), None, cfg), cfg,
                           pairs=ViewPairs.build(scene, cams, 2))
        return st.optimise(noisy, cams, cfg, loss=loss, progress=False).scene, loss

    pairs = ViewPairs.build(scene, cams, 2)
    before = _pair_error(pairs, noisy, cams)
    out, loss = run(1.0)
    assert _pair_error(pairs, out, cams) < 0.7 * before and loss.last["pair"] >= 0
    out0, _ = run(0.0)
    assert torch.equal(out0.sh_dc, noisy.sh_dc)
    cfg = st.Stage2Config(mode="global", iters=2, style_loss="nnfm", color_transfer="off", consistency_weight=1.0)
    bare = st.ViewLoss(ext, st.build_targets(ext, torch.rand(1, 4, 4, 3, dtype=torch.float64), None, cfg), cfg)
    with pytest.raises(InputError, match="consistency_weight needs the view pairs"):
        st.optimise(noisy, cams, cfg, loss=bare, progress=False)


def test_consistency_options_are_checked():
    for field, bad, flag in (("consistency_weight", -1.0, "consistency-weight"),
                             ("consistency_weight", float("nan"), "consistency-weight"),
                             ("consistency_budget", -0.5, "consistency-budget"),
                             ("consistency_budget", float("inf"), "consistency-budget"),
                             ("consistency_neighbours", 0, "consistency-neighbours")):
        with pytest.raises(InputError, match=flag):
            st.Stage2Config(**{field: bad}).validate()
