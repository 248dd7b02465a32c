"""Far-field densification (ssgwarp.reconstruction.far_field): the footprint it measures is the rasterizer's, a wide
far Gaussian whose gradient cancels over its footprint is split, near Gaussians and captures without a far field keep
the 3DGS rule, and the rule is on for the procedural inside-out capture and off for an object-centred one."""
from __future__ import annotations

import math

import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.raster.rasterize import rasterization
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.reconstruction.far_field import SPLIT_RADIUS_PX, FarField
from ssgwarp.reconstruction.recipe import Recipe, resolve
from ssgwarp.reconstruction.gaussians import GaussianParams
from ssgwarp.reconstruction.strategy import REFERENCE_ITERS, DefaultStrategy


def _params(means: torch.Tensor, scales: torch.Tensor) -> GaussianParams:
    n = len(means)
    s = GaussianScene.from_points(means, torch.full((n, 3), 0.5), sh_degree=0, opacity=0.5, scale=scales)
    params = {k: torch.nn.Parameter(v.detach().clone()) for k, v in s.tensors().items()}
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3, "name": k} for k, p in params.items()])
    return GaussianParams(params, opt)


def test_the_screen_radius_is_the_rasterizers_for_far_gaussians():
    """A camera at the centre looking at Gaussians 5-50 units away: the far field's radius (3 sigma of the largest
    axis x focal / distance) is the rasterizer's integer radius to a pixel (it rounds up and adds a 0.3 px blur)."""
    d = torch.tensor([5.0, 12.0, 30.0, 50.0])
    s = torch.tensor([0.2, 0.5, 0.4, 3.0])
    means = torch.stack([0.3 * d, 0.1 * d, d], 1)   # off axis, in view
    vm = look_at(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), up=(0.0, -1.0, 0.0))
    f = 60.0
    cams = Cameras(vm.float(), intrinsics(f, f, 64.0, 48.0, 1), 128, 96)
    _, _, meta = rasterization(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1), s[:, None].repeat(1, 3),
                               torch.full((4,), 0.5), torch.rand(4, 3), cams.viewmats, cams.Ks, 128, 96)
    ff = FarField(torch.zeros(3), 1.0, f)
    r = ff.screen_radius(means, torch.log(s)[:, None].repeat(1, 3))
    got = meta["radii"][0].amax(-1).float()
    # the depth is z, the rule uses the distance: the rasterizer's radius is a little larger off axis
    assert torch.all((got - r).abs() <= 0.12 * r + 1.5), (got, r)


def test_a_wide_far_gaussian_with_a_cancelling_gradient_is_split_and_a_near_one_is_not():
    """Two Gaussians with the same mean gradient (a third of the threshold): one near (under 5 extents from the centre), one
    at distance 20 that is 30 pixels wide. The far one's statistic is scaled by 30 / 8 and it is split; the near one
    is not; without a focal length (no far field) or with ``far_split_px`` 0 (the default) neither is, as in 3DGS. A far
    one narrower than the split radius keeps its gradient."""
    focal = 100.0
    w = 30.0 * 20.0 / (3.0 * focal)          # 30 px at distance 20
    narrow = 4.0 * 20.0 / (3.0 * focal)      # 4 px
    means = torch.tensor([[0.5, 0.0, 0.0], [20.0, 0.0, 0.0], [0.0, 20.0, 0.0]])
    scales = torch.tensor([w, w, narrow])
    for focal_px, split_px, splits in ((focal, SPLIT_RADIUS_PX, 1), (None, SPLIT_RADIUS_PX, 0), (focal, 0.0, 0)):
        g = _params(means, scales)
        recipe, s = resolve(Recipe(sh_degree=0), DefaultStrategy(far_split_px=split_px, max_gaussians=100),
                            REFERENCE_ITERS)
        s.setup(g, recipe=recipe, extent=1.0, seed=0)
        s.far_field(torch.zeros(3), 2.0, focal_px)
        thr = s.grad_threshold
        g.stats["grad2d"][:] = thr / 3.0
        g.stats["count"][:] = 1.0
        stat = s.far.statistic(g.stats["grad2d"], g.params["means"].data, g.params["log_scales"].data) \
            if s.far is not None else None
        if stat is not None:
            assert math.isclose(float(stat[1]), thr / 3.0 * 30.0 / SPLIT_RADIUS_PX, rel_tol=1e-4)
            assert torch.equal(stat[[0, 2]], g.stats["grad2d"][[0, 2]])
        before = g.params["means"].data.clone()
        info = s.refine(g, step=2000)
        assert info["split"] == splits and info["clone"] == 0, (focal_px, info)
        left = g.params["means"].data
        assert any(torch.equal(left[i], before[0]) for i in range(len(left)))      # the near one stays
        assert any(torch.equal(left[i], before[2]) for i in range(len(left)))      # and the narrow far one
        assert any(torch.equal(left[i], before[1]) for i in range(len(left))) == (splits == 0)


def test_the_rule_is_on_for_the_inside_out_capture_and_off_where_there_is_no_far_field(tmp_path):
    """With the rule asked for (``far_split_px`` > 0; off by default), the trainer gives the strategy the far field
    (with the images' focal length) where the backdrop decision made one: the inside-out rig; an object-centred capture whose points cover its images gets none, and its
    densification is the 3DGS rule's (strategy.far is None)."""
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.procedural import build_inside_out, build_scene, render_views, rig_cameras, ring_cameras
    from ssgwarp.procedural import write_transforms_dataset
    from ssgwarp.reconstruction.trainer import Trainer
    from dataclasses import replace

    gt = build_inside_out(0.1)
    cams = rig_cameras(8, 24, 18)
    write_transforms_dataset(tmp_path / "io", render_views(gt, cams)[0], cams)
    data = load_dataset(tmp_path / "io", num_random_points=300, init="random")
    t = Trainer(data, iters=10, recipe=Recipe(sh_degree=0), progress=False, device="cpu", sky="off")
    assert t.backdrop.layout == "inside-out" and t.strategy.far is None   # (the default: the rule off)
    t = Trainer(data, iters=10, recipe=Recipe(sh_degree=0), strategy=DefaultStrategy(far_split_px=SPLIT_RADIUS_PX),
                progress=False, device="cpu", sky="off")
    assert t.strategy.far is not None
    assert math.isclose(t.strategy.far.focal_px, float(cams.Ks[0, 0, 0]), rel_tol=1e-6)

    obj = build_scene(0.3)
    ring = ring_cameras(8, 24, 18)
    write_transforms_dataset(tmp_path / "obj", render_views(obj, ring)[0], ring)
    data = load_dataset(tmp_path / "obj", num_random_points=300, init="random")
    pts = obj.scene.means[torch.randperm(len(obj.scene), generator=torch.Generator().manual_seed(0))[:2000]]
    data = replace(data, points=(pts, torch.full_like(pts, 0.5)), points_source="colmap")
    t = Trainer(data, iters=10, recipe=Recipe(sh_degree=0), strategy=DefaultStrategy(far_split_px=SPLIT_RADIUS_PX),
                progress=False, device="cpu")
    assert t.backdrop.layout == "object-centred" and not t.backdrop.use
    assert t.strategy.far is None and t.strategy.center is None




def test_surface_points_are_centres_of_the_truths_solid_gaussians():
    """procedural.surface_points (the benchmark's stand-in for SfM points): n seeded centres of the inside-out truth's
    Gaussians, none of the sky, each with its Gaussian's colour."""
    from ssgwarp.procedural import build_inside_out, surface_points
    from ssgwarp.raster.scene import sh_dc_to_rgb

    gt = build_inside_out(0.05, railing=True)
    xyz, rgb = surface_points(gt, 200, seed=3)
    assert xyz.shape == rgb.shape == (200, 3) and torch.equal(xyz, surface_points(gt, 200, seed=3)[0])
    row = torch.cdist(xyz, gt.scene.means).argmin(dim=1)
    assert torch.allclose(gt.scene.means[row], xyz) and bool((gt.object_ids[row] != 2).all())
    assert torch.allclose(sh_dc_to_rgb(gt.scene.sh_dc[row]).clamp(0, 1), rgb, atol=1e-6)
