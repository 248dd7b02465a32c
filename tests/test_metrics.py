"""Evaluation metrics: exact reprojection warp, softmax splatting, Gram/content losses, LPIPS and RAFT layouts."""
from __future__ import annotations

import math

import pytest
import torch

from ssgwarp.evaluation import metrics as M
from ssgwarp.evaluation import networks as N
from ssgwarp.errors import InputError, WeightsNotFound

F_PX, W, H = 40.0, 32, 24


def _K() -> torch.Tensor:
    return torch.tensor([[F_PX, 0.0, W / 2], [0.0, F_PX, H / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _viewmat(tx: float, ty: float) -> torch.Tensor:
    """Camera at world (tx, ty, 0) looking down +z (world axes = camera axes)."""
    v = torch.eye(4, dtype=torch.float64)
    v[0, 3], v[1, 3] = -tx, -ty
    return v


def _texture(X: torch.Tensor, Y: torch.Tensor, red: bool = False) -> torch.Tensor:
    """Colour linear in world (X, Y): bilinear resampling reproduces it exactly."""
    if red:
        return torch.stack([torch.full_like(X, 0.9), 0.1 + 0.01 * X, torch.full_like(X, 0.1)], -1)
    return torch.stack([0.5 + 0.1 * X, 0.5 - 0.05 * Y, 0.3 + 0.02 * (X + Y)], -1)


def _raycast(tx: float, ty: float, patch=None) -> M.View:
    """Analytic render of the plane z = 4 (linear texture), optionally with a red square patch at z = 2.

    ``patch = (x0, x1, y0, y1)`` in world units at z = 2.
    """
    uv = M.pixel_centers(H, W, dtype=torch.float64)
    dx, dy = (uv[..., 0] - W / 2) / F_PX, (uv[..., 1] - H / 2) / F_PX
    depth = torch.full((H, W), 4.0, dtype=torch.float64)
    img = _texture(tx + dx * 4.0, ty + dy * 4.0)
    if patch is not None:
        x0, x1, y0, y1 = patch
        X, Y = tx + dx * 2.0, ty + dy * 2.0
        hit = (X >= x0) & (X <= x1) & (Y >= y0) & (Y <= y1)
        depth = torch.where(hit, torch.full_like(depth, 2.0), depth)
        img = torch.where(hit[..., None], _texture(X, Y, red=True), img)
    return M.View(img, depth, torch.ones(H, W, dtype=torch.float64), _viewmat(tx, ty), _K())


def test_unproject_project_round_trip():
    v = _raycast(0.2, -0.1)
    X = M.unproject(v.depth, v.K, v.viewmat)
    uv, z = M.project(X, v.viewmat, v.K)
    assert torch.allclose(uv, M.pixel_centers(H, W, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(z, v.depth, atol=1e-12)
    assert torch.allclose(X[..., 2], torch.full((H, W), 4.0, dtype=torch.float64))


@pytest.mark.parametrize("shift", [(0.3, 0.1), (0.33, 0.05)])  # (3, 1) px and (3.3, 0.5) px
def test_reprojection_warp_is_exact_on_a_plane(shift):
    a, b = _raycast(0.0, 0.0), _raycast(*shift)
    res = M.reprojection_warp(a, b)
    # B pixel u maps to A pixel u + f * t / z; kept while the bilinear footprint stays inside A
    sx, sy = F_PX * shift[0] / 4.0, F_PX * shift[1] / 4.0
    uv = M.pixel_centers(H, W, dtype=torch.float64)
    expect = (uv[..., 0] + sx <= W - 0.5 + 1e-9) & (uv[..., 1] + sy <= H - 0.5 + 1e-9)
    assert torch.equal(res.mask, expect)
    assert M.masked_rmse(res.warped, b.image, res.mask) < 1e-12
    # a known colour change gives the known RMSE
    assert M.masked_rmse(res.warped, b.image + 0.1, res.mask) == pytest.approx(0.1, abs=1e-12)
    changed = b.image.clone()
    changed[..., 0] += 0.2          # red channel only: RMSE = sqrt(0.2^2 / 3)
    assert M.masked_rmse(res.warped, changed, res.mask) == pytest.approx(0.2 / math.sqrt(3), abs=1e-12)


def test_reprojection_warp_masks_occlusions_and_low_alpha():
    patch = (-0.3, 0.3, -0.3, 0.3)  # seen by both cameras, hides different parts of the plane
    a, b = _raycast(0.0, 0.0, patch), _raycast(0.3, 0.1, patch)
    res = M.reprojection_warp(a, b)
    # ground truth: B pixels on the plane whose plane point A sees behind the patch
    X = M.unproject(b.depth, b.K, b.viewmat)
    uv_a, _ = M.project(X, a.viewmat, a.K)
    ia = uv_a[..., 0].floor().long().clamp(0, W - 1), uv_a[..., 1].floor().long().clamp(0, H - 1)
    inside = (uv_a[..., 0] >= 0.5) & (uv_a[..., 0] <= W - 0.5) & (uv_a[..., 1] >= 0.5) & (uv_a[..., 1] <= H - 0.5)
    occluded = inside & (b.depth == 4.0) & (a.depth[ia[1], ia[0]] == 2.0)
    assert occluded.sum() > 20
    assert not (res.mask & occluded).any()
    assert res.mask.sum() > 0.5 * H * W
    assert M.masked_rmse(res.warped, b.image, res.mask) < 1e-12
    # without the occlusion test those pixels would carry the patch's red: the error is large
    loose = M.reprojection_warp(a, b, rel_tol=0.9)
    assert (loose.mask & occluded).sum() == occluded.sum()
    assert M.masked_rmse(loose.warped, b.image, occluded) > 0.2
    # low alpha in B is excluded
    b.alpha[:, :5] = 0.5
    res2 = M.reprojection_warp(a, b, alpha_min=0.9)
    assert not res2.mask[:, :5].any() and torch.equal(res2.mask[:, 5:], res.mask[:, 5:])


def test_reprojection_warp_on_a_rendered_plane():
    """A perfectly consistent render (flat Gaussians on a plane) warps to ~0 error."""
    from ssgwarp.core.cameras import Cameras
    from ssgwarp.raster.scene import GaussianScene

    g = torch.linspace(-2.2, 2.2, 34)
    gy, gx = torch.meshgrid(g * 0.75, g, indexing="ij")
    xyz = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((gx.numel(),), 4.0)], -1)
    rgb = _texture(xyz[:, 0], xyz[:, 1]).float()
    scene = GaussianScene.from_points(xyz, rgb, opacity=0.99, scale=torch.full((len(xyz),), 0.1))
    scene = scene.replace(log_scales=scene.log_scales.clone().index_fill_(1, torch.tensor([2]), math.log(1e-4)))
    vms = torch.stack([_viewmat(0.0, 0.0), _viewmat(0.3, 0.1)]).float()
    cams = Cameras(vms, _K().float().expand(2, 3, 3).clone(), W, H)
    colors, alphas, _ = scene.render(cams, render_mode="RGB+ED")
    views = [M.View(colors[i, ..., :3], colors[i, ..., 3], alphas[i, ..., 0], vms[i], cams.Ks[i]) for i in range(2)]
    assert torch.allclose(views[0].depth[alphas[0, ..., 0] > 0.9], torch.tensor(4.0), atol=1e-3)
    res = M.reprojection_warp(views[0], views[1])
    assert res.mask.float().mean() > 0.8
    assert M.masked_rmse(res.warped, views[1].image, res.mask) < 1e-4
    assert M.masked_rmse(res.warped, views[1].image + 0.1, res.mask) == pytest.approx(0.1, abs=1e-4)


def test_softmax_splat_integer_and_subpixel_flow():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(6, 7, 3, generator=g, dtype=torch.float64)
    flow = torch.zeros(6, 7, 2, dtype=torch.float64)
    flow[..., 0], flow[..., 1] = 2.0, 1.0
    out, cov = M.softmax_splat(img, flow)
    assert torch.allclose(out[1:, 2:], img[:-1, :-2], atol=1e-12)
    assert torch.equal(cov[1:, 2:], torch.ones(5, 5, dtype=torch.float64))
    assert cov[0].abs().sum() == 0 and cov[:, :2].abs().sum() == 0 and out[0].abs().sum() == 0
    # half a pixel to the right: each target averages its two sources (bilinear weights 1/2)
    flow = torch.zeros(6, 7, 2, dtype=torch.float64)
    flow[..., 0] = 0.5
    out, cov = M.softmax_splat(img, flow)
    assert torch.allclose(out[:, 1:], 0.5 * (img[:, :-1] + img[:, 1:]), atol=1e-12)
    assert torch.allclose(cov[:, 0], torch.full((6,), 0.5, dtype=torch.float64))
    # invalid sources are dropped
    valid = torch.ones(6, 7, dtype=torch.bool)
    valid[:, 3] = False
    out, cov = M.softmax_splat(img, flow, valid=valid)
    assert torch.allclose(out[:, 4], img[:, 4], atol=1e-12) and torch.allclose(cov[:, 4], torch.full((6,), 0.5,
                                                                                                   dtype=torch.float64))


def test_softmax_splat_collision_weights_by_metric():
    img = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)  # [1, 3, 3]
    flow = torch.zeros(1, 3, 2, dtype=torch.float64)
    flow[0, 0, 0] = 2.0            # pixel 0 lands on pixel 2
    metric = torch.tensor([[1000.0, 0.0, 997.0]], dtype=torch.float64)  # huge values: must stay finite
    out, cov = M.softmax_splat(img, flow, metric)
    w0, w2 = math.exp(3.0), 1.0
    expect = (w0 * img[0, 0] + w2 * img[0, 2]) / (w0 + w2)
    assert torch.allclose(out[0, 2], expect, atol=1e-12)
    assert cov[0, 2] == 2.0 and cov[0, 0] == 0.0 and torch.allclose(out[0, 1], img[0, 1])
    # no metric: plain average
    out, _ = M.softmax_splat(img, flow)
    assert torch.allclose(out[0, 2], 0.5 * (img[0, 0] + img[0, 2]))


@pytest.mark.parametrize("shift", [(0.3, 0.1), (0.33, 0.05)])
def test_flow_warp_with_geometric_flow_matches_reprojection(shift):
    a, b = _raycast(0.0, 0.0), _raycast(*shift)
    flow_ab, z = M.reprojection_flow(a, b)
    flow_ba, _ = M.reprojection_flow(b, a)
    # B sits at +x of A: points move left in B
    assert torch.allclose(flow_ab[..., 0], torch.full((H, W), -F_PX * shift[0] / 4, dtype=torch.float64))
    assert torch.allclose(z, torch.full((H, W), 4.0, dtype=torch.float64))
    fb = M.forward_backward_mask(flow_ab, flow_ba)
    assert fb[2:, 4:].all() and not fb[:, :3].any()
    # where a target pixel receives its full bilinear share (coverage 1) the splat of a linear texture is exact
    res = M.flow_warp(a.image, b.image, flow_ab, flow_ba=flow_ba, alpha_a=a.alpha, alpha_b=b.alpha,
                      min_coverage=0.999)
    assert res.mask.float().mean() > 0.7
    assert M.masked_rmse(res.warped, b.image, res.mask) < 1e-10
    # the default keeps half-covered border pixels too (biased towards their one side): still small
    res = M.flow_warp(a.image, b.image, flow_ab, flow_ba=flow_ba, alpha_a=a.alpha, alpha_b=b.alpha)
    assert M.masked_rmse(res.warped, b.image, res.mask) < 0.005
    # a flow that is not undone by the backward flow is masked by the forward-backward check
    bad = flow_ab.clone()
    bad[:8, :8] += 5.0
    assert not M.forward_backward_mask(bad, flow_ba)[:8, :8].any()


def test_masked_rmse_and_pairs():
    a = torch.zeros(4, 4, 3)
    assert math.isnan(M.masked_rmse(a, a, torch.zeros(4, 4, dtype=torch.bool)))
    assert M.consistency_pairs(5, "short") == [(0, 1), (1, 2), (2, 3), (3, 4)]
    assert M.consistency_pairs(5, "long", gap=7) == [(0, 4)]
    assert M.consistency_pairs(20, "long", gap=7, max_pairs=3) == [(0, 7), (6, 13), (12, 19)]
    assert M.consistency_pairs(1, "short") == []
    with pytest.raises(InputError):
        M.consistency_pairs(5, "medium")


class _Identity:
    """A 'feature extractor' returning the image and its 2x average pool (hand-computable)."""

    name = "identity"

    def __call__(self, x):
        return [x, torch.nn.functional.avg_pool2d(x, 2)]


def test_gram_and_content_losses_by_hand():
    c = torch.tensor([0.2, 0.5, 0.8], dtype=torch.float64)
    s = torch.tensor([0.9, 0.1, 0.4], dtype=torch.float64)
    images = c.expand(2, 8, 6, 3).clone()
    style = s.expand(5, 7, 3).clone()
    # constant features: G = c c^T on every layer; loss = mean_ij (c_i c_j - s_i s_j)^2
    expect_style = float(((torch.outer(c, c) - torch.outer(s, s)) ** 2).mean())
    originals = images.clone()
    originals[..., 0] += 0.3           # content: mean over 3 channels of 0.3^2 on each layer
    out = M.style_content_losses(_Identity(), images, style, originals)
    assert torch.allclose(out["style"], torch.full((2,), expect_style, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(out["content"], torch.full((2,), 0.09 / 3, dtype=torch.float64), atol=1e-12)
    # a non-constant example against an explicit sum
    f = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]], [[0.0, 1.0], [1.0, 0.0]]]], dtype=torch.float64)  # [1,2,2,2]
    G = torch.tensor([[30.0 / 4, 5.0 / 4], [5.0 / 4, 2.0 / 4]], dtype=torch.float64)
    S = torch.eye(2, dtype=torch.float64)[None]
    assert M.gram_style_loss([f], [S]).item() == pytest.approx(float(((G - S[0]) ** 2).mean()), abs=1e-12)
    assert M.content_loss([f], [torch.zeros_like(f)]).item() == pytest.approx(32.0 / 8, abs=1e-12)


def test_style_is_resized_keeping_aspect():
    s = torch.rand(40, 80, 3, generator=torch.Generator().manual_seed(0))
    assert M.fit_style(s, 24, 32).shape == (1, 3, 24, 48)


def test_reconstruction_quality():
    g = torch.Generator().manual_seed(1)
    t = torch.rand(2, 16, 16, 3, generator=g)
    # constant images: SSIM = (2ab + C1) / (a^2 + b^2 + C1), C1 = 0.01^2 (no variance terms)
    a, b = torch.full((1, 16, 16, 3), 0.3), torch.full((1, 16, 16, 3), 0.6)
    q = M.reconstruction_quality(a, b)
    assert q["ssim"][0] == pytest.approx((2 * 0.18 + 1e-4) / (0.09 + 0.36 + 1e-4), abs=1e-5)
    assert q["psnr"][0] == pytest.approx(-10 * math.log10(0.09), rel=1e-5)
    q = M.reconstruction_quality((t + 0.1).clamp(0, 1), t)
    mse = float((((t + 0.1).clamp(0, 1) - t) ** 2)[0].mean())
    assert q["psnr"][0] == pytest.approx(-10 * math.log10(mse), rel=1e-4)


def test_lpips_loads_lpips_layout_and_is_a_distance(tmp_path):
    torch.manual_seed(0)
    model = N.LPIPS()
    vgg = {f"features.{k}": v for k, v in model.trunk.features.state_dict().items()}
    lins = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate(N.LPIPS_CHANNELS)}
    torch.save(vgg, tmp_path / "vgg16.pth")
    torch.save(lins, tmp_path / "lpips_vgg.pth")
    lp = N.load_lpips(tmp_path / "lpips_vgg.pth", tmp_path / "vgg16.pth")
    assert torch.equal(lp.lins[3].weight, lins["lin3.model.1.weight"])
    x = torch.rand(2, 3, 32, 32)
    y = (x + 0.2 * torch.randn_like(x)).clamp(0, 1)
    # distance properties, on top of the value against its definition
    # (test_quality_measures.py::test_lpips_value_follows_its_definition)
    with torch.no_grad():
        assert torch.allclose(lp(x, x), torch.zeros(2), atol=1e-6)
        d = lp(x, y)
    assert (d > 0).all() and torch.allclose(d, lp(y, x), rtol=1e-5)
    with pytest.raises(InputError):
        model.load(vgg, {"lin0.model.1.weight": torch.rand(1, 64, 1, 1)})


def test_raft_large_matches_torchvision_layout_and_loads(tmp_path, monkeypatch):
    for var in ("SSGWARP_RAFT", "SSGWARP_WEIGHTS"):
        monkeypatch.delenv(var, raising=False)
    torch.manual_seed(0)
    model = N.RAFTLarge()
    # torchvision documents raft_large as 5,257,536 parameters
    assert sum(p.numel() for p in model.parameters()) == 5_257_536
    sd = model.state_dict()
    assert tuple(sd["update_block.recurrent_block.convgru1.convz.weight"].shape) == (128, 384, 1, 5)
    assert tuple(sd["update_block.motion_encoder.convcorr1.0.weight"].shape) == (256, 324, 1, 1)
    assert tuple(sd["mask_predictor.conv.weight"].shape) == (576, 256, 1, 1)
    assert "context_encoder.layer2.0.downsample.1.running_var" in sd
    assert "feature_encoder.convnormrelu.1.weight" not in sd  # instance norm without affine parameters
    with pytest.raises(WeightsNotFound):
        N.load_raft(None)
    torch.save(sd, tmp_path / "raft_large.pth")
    loaded = N.load_raft(tmp_path / "raft_large.pth")
    a, b = torch.rand(36, 44, 3), torch.rand(36, 44, 3)   # not multiples of 8: padded inside
    f1 = N.estimate_flow(loaded, a, b, iters=2)
    assert f1.shape == (36, 44, 2) and torch.isfinite(f1).all()
    model.eval()
    f2 = N.estimate_flow(model, a, b, iters=2)
    assert torch.allclose(f1, f2, atol=1e-5)
    bad = dict(sd)
    bad.pop("mask_predictor.conv.bias")
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(InputError, match="raft_large"):
        N.load_raft(tmp_path / "bad.pth")
