"""Colour transfer (ssgwarp.stylization.color and stylize.transfer_colors): hand cases, SH linearity, per-group path and its fallback."""
from __future__ import annotations

import pytest
import torch

from ssgwarp.stylization.color import ColorStats, ColorTransform, fit_group_transforms, fit_transform, pixel_stats, transform_sh
from ssgwarp.stylization.color import transfer_colors
from ssgwarp.core.imaging import rgb_to_lab
from ssgwarp.raster.scene import GaussianScene, sh_dc_to_rgb


def _cloud(n: int, mean, L, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 3, generator=g, dtype=torch.float64) @ torch.tensor(L, dtype=torch.float64).T \
        + torch.tensor(mean, dtype=torch.float64)


def test_rgb_to_lab_reference_values():
    # white, black, the sRGB primaries (CIE values for D65; e.g. red = L 53.24, a 80.09, b 67.20)
    rgb = torch.tensor([[1.0, 1, 1], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0.5]], dtype=torch.float64)
    ref = torch.tensor([[100.0, 0, 0], [0, 0, 0], [53.24, 80.09, 67.20], [87.73, -86.18, 83.18],
                        [32.30, 79.19, -107.86], [53.39, 0, 0]], dtype=torch.float64)
    torch.testing.assert_close(rgb_to_lab(rgb), ref, atol=0.02, rtol=0)


def test_fit_transform_maps_mean_and_covariance_to_the_target():
    """Hand case: a source cloud with known mean/covariance goes to the target's, exactly."""
    src = _cloud(4000, [0.3, 0.5, 0.2], [[0.1, 0, 0], [0.05, 0.08, 0], [0.0, 0.02, 0.03]], 0)
    tgt = _cloud(3000, [0.7, 0.2, 0.6], [[0.02, 0.0, 0], [0.0, 0.15, 0], [0.04, 0.0, 0.05]], 1)
    t = fit_transform(ColorStats().add(src), ColorStats().add(tgt), eps=0.0)
    mapped = ColorStats().add(t(src))
    target = ColorStats().add(tgt)
    torch.testing.assert_close(mapped.mean, target.mean, atol=1e-10, rtol=0)
    torch.testing.assert_close(mapped.cov, target.cov, atol=1e-10, rtol=0)
    # the map is the symmetric (optimal-transport) one: A symmetric positive definite
    torch.testing.assert_close(t.A, t.A.T)
    assert bool((torch.linalg.eigvalsh(t.A) > 0).all())
    # 1-D hand case inside 3-D: isotropic source std 0.1 -> target std 0.2 gives A = 2 I, b = mu_t - 2 mu_s
    s = ColorStats().add(_cloud(20000, [0.5, 0.5, 0.5], [[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], 2))
    s_cov, s_mean = s.cov, s.mean
    tt = ColorStats()
    tt.n, tt.s1 = s.n, s.s1 * 0 + s.n * torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    tt.s2 = s.n * (4 * s_cov + torch.outer(tt.mean, tt.mean))
    t2 = fit_transform(s, tt, eps=0.0)
    torch.testing.assert_close(t2.A, 2 * torch.eye(3, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(t2.b, torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64) - 2 * s_mean)


def test_flat_source_gain_is_capped():
    src = torch.full((100, 3), 0.4, dtype=torch.float64) + 1e-6 * torch.randn(100, 3, dtype=torch.float64)
    tgt = _cloud(500, [0.5, 0.5, 0.5], [[0.2, 0, 0], [0, 0.2, 0], [0, 0, 0.2]], 3)
    t = fit_transform(ColorStats().add(src), ColorStats().add(tgt), max_gain=4.0)
    assert float(torch.linalg.eigvalsh(t.A).max()) <= 4.0 + 1e-9
    torch.testing.assert_close(t(src).mean(0), ColorStats().add(tgt).mean, atol=1e-3, rtol=0)


def test_transform_sh_is_the_colour_map_of_every_view():
    """Applied to the SH coefficients, the map recolours the view-dependent colour of every direction."""
    from ssgwarp.core.sh import spherical_harmonics

    g = torch.Generator().manual_seed(0)
    n = 50
    scene = GaussianScene.from_points(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                      torch.rand(n, 3, generator=g, dtype=torch.float64), sh_degree=2)
    scene = scene.replace(sh_rest=0.1 * torch.randn(scene.sh_rest.shape, generator=g, dtype=torch.float64))
    t = ColorTransform(torch.tensor([[0.8, 0.1, 0.0], [0.1, 1.2, 0.05], [0.0, 0.05, 0.6]], dtype=torch.float64),
                       torch.tensor([0.1, -0.05, 0.2], dtype=torch.float64))
    out = transform_sh(scene, [t])
    dirs = torch.randn(n, 3, generator=g, dtype=torch.float64)
    before = spherical_harmonics(2, dirs, scene.sh_coeffs) + 0.5
    after = spherical_harmonics(2, dirs, out.sh_coeffs) + 0.5
    torch.testing.assert_close(after, t(before), atol=1e-12, rtol=0)
    assert out.means is scene.means and out.logit_opacities is scene.logit_opacities


def test_per_group_transforms_and_the_global_fallback():
    """Group 0 and 1 are matched on their own; group 2 is absent from the target -> the global map."""
    src0 = _cloud(800, [0.2, 0.2, 0.8], [[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], 10)
    src1 = _cloud(800, [0.8, 0.2, 0.2], [[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], 11)
    src2 = _cloud(800, [0.5, 0.5, 0.5], [[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], 12)
    tgt0 = _cloud(600, [0.9, 0.1, 0.1], [[0.02, 0, 0], [0, 0.02, 0], [0, 0, 0.02]], 13)
    tgt1 = _cloud(600, [0.1, 0.1, 0.9], [[0.03, 0, 0], [0, 0.03, 0], [0, 0, 0.03]], 14)
    # images [1, H, W, 3] with group maps: source has groups 0, 1, 2; target only 0 and 1
    src_img = torch.cat([src0, src1, src2]).reshape(1, 40, 60, 3)
    src_lab = torch.cat([torch.full((800,), k) for k in range(3)]).reshape(1, 40, 60)
    tgt_img = torch.cat([tgt0, tgt1]).reshape(1, 30, 40, 3)
    tgt_lab = torch.cat([torch.full((600,), k) for k in range(2)]).reshape(1, 30, 40)
    src, tgt = pixel_stats(src_img, labels=src_lab), pixel_stats(tgt_img, labels=tgt_lab)
    transforms, how = fit_group_transforms(src, tgt, 3, eps=0.0)
    assert how == ["group", "group", "global"]
    for k, (s, t) in enumerate([(src0, tgt0), (src1, tgt1)]):
        torch.testing.assert_close(transforms[k](s).mean(0), t.mean(0), atol=1e-9, rtol=0)
    glob = fit_transform(src[0], tgt[0], eps=0.0)
    torch.testing.assert_close(transforms[2].A, glob.A)
    torch.testing.assert_close(transforms[2].b, glob.b)
    # on a scene: each Gaussian gets its group's map
    scene = GaussianScene.from_points(torch.zeros(3, 3, dtype=torch.float64),
                                      torch.tensor([[0.2, 0.2, 0.8], [0.8, 0.2, 0.2], [0.5, 0.5, 0.5]],
                                                   dtype=torch.float64))
    out = transform_sh(scene, transforms, torch.tensor([0, 1, 2]))
    for k in range(3):
        torch.testing.assert_close(out.base_colors[k], transforms[k](scene.base_colors[k]), atol=1e-12, rtol=0)
    with pytest.raises(Exception, match="assignment"):
        transform_sh(scene, transforms)


def test_transfer_colors_on_a_rendered_scene_per_group_and_global():
    """stylize.transfer_colors: renders of the recoloured scene carry the target's colour statistics;
    per group, a group absent from the target views gets the global map (the fallback)."""
    from test_stylize import object_labels, ring, two_objects

    from ssgwarp.stylization import stylize as st

    scene, obj = two_objects(n=80, dtype=torch.float64)
    cams = ring(n=3, dtype=torch.float64)
    labels = object_labels(scene, obj, cams)                 # 0, 1 objects, 2 background
    # global: against a style image of warm colours (no colour is pushed below 0, where renders clamp)
    style = _cloud(400, [0.6, 0.5, 0.4], [[0.04, 0, 0], [0.02, 0.03, 0], [0.0, 0.01, 0.03]], 5).reshape(1, 20, 20, 3)
    out, info = transfer_colors(scene, cams, style, max_gain=4.0)     # a cap that this map stays under
    assert float(sh_dc_to_rgb(out.sh_dc).min()) > 0
    assert info["per_group"] is False
    col, alpha, _ = out.render(cams)
    surface = (col[..., :3] / alpha)[alpha[..., 0] >= 0.5]     # the pixels the statistics are taken on
    stats, target_stats = ColorStats().add(surface), ColorStats().add(style)
    torch.testing.assert_close(stats.mean, target_stats.mean, atol=1e-6, rtol=0)
    # covariance: up to the eps regularisation of the (nearly rank-2) source covariance
    torch.testing.assert_close(stats.cov, target_stats.cov, atol=0.05 * float(target_stats.cov.diagonal().max()), rtol=0.05)

    # the default cap (Stage 2's --color-max-gain 1.3) limits the stretch of every colour direction
    _, info_d = transfer_colors(scene, cams, style)
    gains = torch.linalg.eigvalsh(torch.tensor(info_d["transform"]["A"], dtype=torch.float64))
    assert float(gains.max()) == pytest.approx(1.3, abs=1e-5), gains      # this map wants more: capped

    # per group: object 0 -> red, object 1 is absent from the target views -> the global map
    target = torch.zeros(1, *labels.shape[1:], 3, dtype=torch.float64)
    tlab = torch.full(labels.shape[1:], 2)[None]
    target[0, :, :] = torch.tensor([0.9, 0.1, 0.1], dtype=torch.float64)
    tlab[0, labels[0] == 0] = 0                               # target view 0 shows object 0 only (as red)
    out_g, info_g = transfer_colors(scene, cams[[0]], target, labels=labels[[0]], target_labels=tlab,
                                       assign=obj, num_groups=2, max_gain=4.0)
    assert info_g["per_group"] and info_g["how"] == ["group", "global"]
    c0 = out_g.base_colors[obj == 0].mean(0)
    assert c0[0] > 0.7 and c0[1] < 0.25 and c0[2] < 0.25, c0
    # object 1 got exactly the global map of the same views
    col, alpha, _ = scene.render(cams[[0]])
    src = pixel_stats(col[..., :3] / alpha, alpha[..., 0])
    glob = fit_transform(src[0], pixel_stats(target)[0])
    torch.testing.assert_close(out_g.sh_dc[obj == 1], transform_sh(scene, [glob]).sh_dc[obj == 1])


def test_transfer_background_makes_the_colour_map_exact_on_every_pixel():
    """The background under the same map: the render of the recoloured scene over the mapped
    background is ``A render + b`` on every pixel, background and outline included (compositing is
    affine in colour); over the capture's background the outline and the background are not."""
    from test_stylize import object_labels, ring, two_objects

    from ssgwarp.stylization.color import transfer_background
    from ssgwarp.stylization import stylize as st

    scene, obj = two_objects(n=80, dtype=torch.float64)
    cams = ring(n=3, dtype=torch.float64)
    white = torch.ones(3, dtype=torch.float64)
    # a dark style with little colour spread, no stretch: white maps inside [0, 1] (no clamp)
    style = _cloud(400, [0.25, 0.2, 0.3], [[0.05, 0, 0], [0.02, 0.04, 0], [0.0, 0.01, 0.05]], 6).reshape(1, 20, 20, 3)
    out, info = transfer_colors(scene, cams, style, max_gain=1.0)
    bg = transfer_background([1.0, 1.0, 1.0], info)
    t = ColorTransform(torch.tensor(info["transform"]["A"], dtype=torch.float64),
                       torch.tensor(info["transform"]["b"], dtype=torch.float64))
    torch.testing.assert_close(torch.tensor(bg, dtype=torch.float64), t(white), atol=1e-12, rtol=0)
    assert max(bg) < 0.85                                       # white became a darker colour of the style
    before, alpha, _ = scene.render(cams, backgrounds=white[None].expand(3, 3))
    after, _, _ = out.render(cams, backgrounds=torch.tensor(bg, dtype=torch.float64)[None].expand(3, 3))
    partial = (alpha[..., 0] < 0.99)
    assert int(partial.sum()) > 100                              # the views show background and outlines
    # exact up to the record's rounding of A and b (6 decimals)
    torch.testing.assert_close(after[..., :3], t(before[..., :3]), atol=2e-6, rtol=0)
    kept, _, _ = out.render(cams, backgrounds=white[None].expand(3, 3))
    assert float((kept[..., :3] - t(before[..., :3])).abs()[partial].max()) > 0.15

    # a map taking white above 1 is clamped into [0, 1]; per group, the global map of the record is used
    light = _cloud(400, [0.9, 0.85, 0.8], [[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], 7).reshape(1, 20, 20, 3)
    _, info_l = transfer_colors(scene, cams, light, max_gain=4.0)
    glob = ColorTransform(torch.tensor(info_l["transform"]["A"], dtype=torch.float64),
                          torch.tensor(info_l["transform"]["b"], dtype=torch.float64))
    assert float(glob(white).max()) > 1.0
    assert transfer_background([1.0, 1.0, 1.0], info_l) == [min(1.0, float(v)) for v in glob(white)]
    labels = object_labels(scene, obj, cams)
    _, info_g = transfer_colors(scene, cams, style, labels=labels, target_labels=torch.zeros(1, 20, 20).long(),
                                   assign=obj, num_groups=2, max_gain=1.0)
    assert info_g["per_group"] and "transform" not in info_g
    assert transfer_background([1.0, 1.0, 1.0], info_g) == pytest.approx(bg, abs=1e-9)   # the same global map


# ----------------------------------------------------------------------------- texture kept through the map
def test_texture_bands_hand_cases():
    """Band-passes of L* (level minus its sigma-1 blur) on a Gaussian pyramid: 1-px black/white stripes
    have a closed form at the finest band and almost nothing at the coarser ones."""
    import math

    from ssgwarp.stylization.color import texture_bands

    img = torch.zeros(1, 24, 24, 3, dtype=torch.float64)
    img[:, :, 1::2] = 1.0                                       # columns alternate black (L* 0) and white (100)
    frame = torch.zeros(1, 24, 24, dtype=torch.float64)
    frame[:, 2:-2, 2:-2] = 1.0                                  # counted: pixels >= 2 px inside the kept part
    e1, e2 = math.exp(-0.5), math.exp(-2.0)
    g1 = e1 / (1 + 2 * e1 + 2 * e2)                             # the blur's weight at +-1 px
    # at every counted pixel: white minus its blur = 100 (1 - g0 - 2 g2) = 2 g1 100, black = -2 g1 100
    b = texture_bands(img, frame)
    assert b[0] == pytest.approx(200 * g1, rel=1e-6)             # (L* of white: 100 to 1e-7)
    assert b[1] < 0.05 * b[0] and b[2] < 0.05 * b[0], b        # blurred away before the coarser bands
    assert texture_bands(torch.full((2, 16, 16, 3), 0.3, dtype=torch.float64)) == [0.0, 0.0, 0.0]   # flat
    assert texture_bands(img, torch.zeros_like(frame)) == [0.0, 0.0, 0.0]                     # nothing kept
    assert texture_bands(img[:, :8, :8], levels=3)[2] == 0.0   # a level under 5 px has no band
    # values outside [0, 1] count as the clamped colour a render shows
    assert texture_bands(img * 3 - 1, frame) == pytest.approx(texture_bands(img, frame), rel=1e-12)
    # a coarse pattern (8-px stripes) has its texture in the coarser bands, not the finest
    coarse = torch.zeros(1, 64, 64, 3, dtype=torch.float64)
    coarse[:, :, (torch.arange(64) // 8) % 2 == 1] = 1.0
    c = texture_bands(coarse)
    assert c[2] > c[0], c


def test_texture_bands_by_chunks_and_the_view_sample():
    """Views taken a few at a time give the bands of all at once (the RMS of every counted pixel);
    ``detail_views`` keeps every view of a small capture and an even spread of a large one."""
    from ssgwarp.stylization.color import DETAIL_VIEWS, detail_views, texture_bands

    g = torch.Generator().manual_seed(7)
    imgs = torch.rand(7, 20, 24, 3, generator=g, dtype=torch.float64)
    alphas = (torch.rand(7, 20, 24, generator=g, dtype=torch.float64) > 0.1).double()
    whole = texture_bands(imgs, alphas, chunk=7)
    assert texture_bands(imgs, alphas, chunk=3) == pytest.approx(whole, rel=1e-12)
    assert texture_bands(imgs, alphas, chunk=1) == pytest.approx(whole, rel=1e-12)
    assert detail_views(5) == [0, 1, 2, 3, 4] and detail_views(DETAIL_VIEWS) == list(range(DETAIL_VIEWS))
    big = detail_views(100, most=24)
    assert len(big) == 24 and big[0] == 0 and big[-1] == 99 and big == sorted(set(big))
    gaps = [b - a for a, b in zip(big, big[1:])]
    assert max(gaps) - min(gaps) <= 1, gaps                     # evenly spaced


def test_stretch_lightness_scales_luminance_about_the_center_and_keeps_chroma():
    from ssgwarp.stylization.color import LUMA

    g = torch.Generator().manual_seed(1)
    A = torch.randn(3, 3, generator=g, dtype=torch.float64) * 0.3 + torch.eye(3, dtype=torch.float64)
    t = ColorTransform(A, torch.tensor([0.1, -0.05, 0.2], dtype=torch.float64))
    c = torch.tensor([0.4, 0.5, 0.6], dtype=torch.float64)
    s = t.stretch_lightness(1.7, c)
    x = torch.rand(50, 3, generator=g, dtype=torch.float64)
    w = torch.tensor(LUMA, dtype=torch.float64)
    torch.testing.assert_close((s(x) - c) @ w, 1.7 * ((t(x) - c) @ w))      # luminance about c: x 1.7
    d = s(x) - t(x)                                                      # the change is a grey shift
    torch.testing.assert_close(d[:, 0], d[:, 1])
    torch.testing.assert_close(d[:, 1], d[:, 2])
    torch.testing.assert_close(s(c[None]) - t(c[None]), (t(c[None]) - c) @ w * 0.7 * torch.ones(1, 3, dtype=torch.float64))
    torch.testing.assert_close(t.stretch_lightness(1.0, c)(x), t(x))


def _textured(v: int, h: int, w: int, seed: int, mean: float, layout: float, grain: float) -> torch.Tensor:
    """Grey images: a left-right ramp of amplitude ``layout`` plus pixel noise of std ``grain``."""
    g = torch.Generator().manual_seed(seed)
    ramp = torch.linspace(-layout, layout, w, dtype=torch.float64).expand(v, h, w)
    y = mean + ramp + grain * torch.randn(v, h, w, generator=g, dtype=torch.float64)
    return y[..., None].expand(-1, -1, -1, 3).clone()


def test_detail_gain_restores_texture_the_plain_map_flattens():
    """A scene whose lightness varies mostly at large scale, a style with more grain but less variance:
    the plain map shrinks the scene's grain below both; the stretch brings the finest band to
    min(style, scene), or to the reference's when one is given."""
    from ssgwarp.stylization.color import detail_gain, texture_bands

    renders = _textured(2, 32, 32, 0, 0.5, 0.15, 0.02)        # strong layout, fine grain
    alphas = torch.ones(2, 32, 32, dtype=torch.float64)
    style = _textured(1, 32, 32, 1, 0.6, 0.0, 0.05)           # no layout, more grain, smaller variance
    g = torch.Generator().manual_seed(2)                        # ... and blotches: texture at every scale
    blotch = torch.nn.functional.interpolate(torch.randn(1, 1, 8, 8, generator=g, dtype=torch.float64),
                                             size=(32, 32), mode="bilinear", align_corners=False)[0, 0]
    style = style + 0.025 * blotch[None, :, :, None]
    t = fit_transform(pixel_stats(renders, alphas)[0], pixel_stats(style)[0])
    center = pixel_stats(style)[0].mean
    plain = texture_bands(t(renders), alphas)
    d = detail_gain(renders, alphas, style, [t], [center])
    assert d["mapped"] == pytest.approx(plain, rel=1e-12) and d["reference"] == d["scene"]
    assert plain[0] < 0.6 * min(d["style"][0], d["scene"][0]), d   # the plain map flattened the grain
    assert d["gain"] > 1.5 and d["kept"][0] == pytest.approx(min(d["style"][0], d["scene"][0]), rel=0.011), d
    assert texture_bands(t.stretch_lightness(d["gain"], center)(renders), alphas) == pytest.approx(d["kept"], rel=1e-9)
    # a reference (the capture's texture, when the renders are of a stylized scene) bounds it instead
    low = [0.8 * x for x in d["scene"]]
    r = detail_gain(renders, alphas, style, [t], [center], reference=low)
    assert r["reference"] == low and 1.0 < r["gain"] < d["gain"]
    assert r["kept"][0] == pytest.approx(low[0], rel=0.011), r
    # a flat style asks for no texture: nothing is stretched
    flat = torch.full((1, 16, 16, 3), 0.6, dtype=torch.float64)
    assert detail_gain(renders, alphas, flat, [t], [center])["gain"] == 1.0
    # a map that keeps the texture already: no stretch
    assert detail_gain(renders, alphas, style, [ColorTransform.identity()], [center])["gain"] == 1.0


def test_detail_gain_stops_where_a_coarser_band_would_pass_the_style():
    """A style of thin lines on flat fields (much fine texture, little coarse) and a scene with a large
    layout and texture at every scale, which the plain map flattens: stretching up to the fine target
    would push the coarse bands past the style's, so the stretch stops where the first band reaches the
    style's there."""
    from ssgwarp.stylization.color import detail_gain, texture_bands

    g = torch.Generator().manual_seed(5)
    base = torch.randn(2, 1, 16, 16, generator=g, dtype=torch.float64)
    coarse = torch.nn.functional.interpolate(base, scale_factor=4, mode="bilinear", align_corners=False)[:, 0]
    fine = torch.randn(2, 64, 64, generator=g, dtype=torch.float64)
    ramp = torch.linspace(-0.25, 0.25, 64, dtype=torch.float64).expand(2, 64, 64)   # a layout: the map shrinks it
    renders = (0.5 + ramp + 0.03 * coarse + 0.03 * fine).clamp(0, 1)[..., None].expand(-1, -1, -1, 3).clone()
    alphas = torch.ones(2, 64, 64, dtype=torch.float64)
    style = torch.full((1, 64, 64, 3), 0.5, dtype=torch.float64)
    style[:, 3::8] = 0.62                                       # 1-px light lines every 8 rows
    style[:, :, 5::8] = 0.4                                     # and dark ones every 8 columns
    t = fit_transform(pixel_stats(renders, alphas)[0], pixel_stats(style)[0])
    center = pixel_stats(style)[0].mean
    d = detail_gain(renders, alphas, style, [t], [center])
    s, m, kept = d["style"], d["mapped"], d["kept"]
    assert s[0] > 1.5 * s[2] and m[0] < min(s[0], d["scene"][0]), d     # fine lines; the map flattened
    assert 1.0 < d["gain"], d
    assert all(k <= max(a, b) * 1.011 for k, a, b in zip(kept, s, m)), d  # no band above the style's
    assert max(k / max(a, b) for k, a, b in zip(kept, s, m)) > 0.98, d     # ... and one band at it
    assert kept[0] < 0.98 * min(s[0], d["scene"][0]), d                     # short of the fine target
    assert texture_bands(t.stretch_lightness(d["gain"], center)(renders), alphas) == pytest.approx(kept, rel=1e-9)


def test_transfer_colors_keep_detail_on_a_rendered_scene():
    """stylize.transfer_colors(keep_detail=True): the recoloured scene's renders hold the texture the
    record says (min of style and scene, within the tolerance), their mean colour stays the target's,
    and the record and its description say what was done; without it nothing is stretched."""
    from test_stylize import ring, two_objects

    from ssgwarp.stylization.color import describe_transfer, texture_bands
    from ssgwarp.stylization import stylize as st

    from ssgwarp.raster.scene import rgb_to_sh_dc

    scene, obj = two_objects(n=80, dtype=torch.float64)       # recoloured: a darker and a lighter grey object
    g = torch.Generator().manual_seed(3)
    grey = torch.where(obj == 0, 0.35, 0.65).double() + 0.1 * torch.randn(len(obj), generator=g, dtype=torch.float64)
    scene = scene.replace(sh_dc=rgb_to_sh_dc(grey[:, None].expand(-1, 3).clamp(0.02, 0.98)).reshape(scene.sh_dc.shape))
    cams = ring(n=3, dtype=torch.float64)
    style = _textured(1, 32, 48, 2, 0.55, 0.0, 0.08)            # one grey with a grain: less variance, more grain,
    g = torch.Generator().manual_seed(4)                        # ... and blotches: more texture at every scale
    blotch = torch.nn.functional.interpolate(torch.randn(1, 1, 8, 12, generator=g, dtype=torch.float64),
                                             size=(32, 48), mode="bilinear", align_corners=False)[0, 0]
    style = style + 0.12 * blotch[None, :, :, None]
    plain, info_p = transfer_colors(scene, cams, style, max_gain=4.0)
    kept, info_k = transfer_colors(scene, cams, style, max_gain=4.0, keep_detail=True)
    assert "detail" not in info_p and "texture" not in describe_transfer(info_p, "the style")
    d = info_k["detail"]
    assert d["gain"] > 1.0 and "texture" in describe_transfer(info_k, "the style")

    def surface(sc):
        col, alpha, _ = sc.render(cams)
        return col[..., :3] / alpha.clamp_min(1e-9), alpha[..., 0]

    s_p, a = surface(plain)
    s_k, _ = surface(kept)
    assert texture_bands(s_p, a) == pytest.approx(d["mapped"], rel=1e-3, abs=1e-3)
    assert texture_bands(s_k, a) == pytest.approx(d["kept"], rel=1e-3, abs=1e-3)
    assert d["kept"][0] == pytest.approx(min(d["style"][0], d["scene"][0]), rel=0.011)
    keep = a >= 0.5
    torch.testing.assert_close(s_k[keep].mean(0), s_p[keep].mean(0), atol=2e-3, rtol=0)   # about the target mean
    # recolouring a scene that is already flatter than the capture (Stage 2's output, the `post` transfer):
    # with `capture`, the stretch is bounded by the capture's texture, not by the flattened scene's own
    again, info_c = transfer_colors(plain, cams, style, max_gain=4.0, keep_detail=True, capture=scene)
    own, info_o = transfer_colors(plain, cams, style, max_gain=4.0, keep_detail=True)
    c, o = info_c["detail"], info_o["detail"]
    assert c["reference"] == pytest.approx(d["scene"], rel=1e-3)         # the capture's bands
    assert o["reference"] == o["scene"] and o["scene"][0] < 0.9 * c["reference"][0]
    assert c["gain"] > o["gain"] and c["kept"][0] > o["kept"][0]


def test_transfer_colors_measures_texture_on_the_view_sample(monkeypatch):
    """With more cameras than the sample, the record's bands are those of the sampled views only (the
    scene's and the capture's alike)."""
    from test_stylize import ring, two_objects

    import ssgwarp.stylization.color as color

    scene, _ = two_objects(n=60, dtype=torch.float64)
    cams = ring(n=3, dtype=torch.float64)
    style = _textured(1, 32, 48, 2, 0.55, 0.0, 0.08)
    orig = color.detail_views
    monkeypatch.setattr(color, "detail_views", lambda n: orig(n, most=2))
    _, info = color.transfer_colors(scene, cams, style, max_gain=4.0, keep_detail=True,
                                    capture=scene.replace(sh_dc=scene.sh_dc * 0.5))
    sample = cams[[0, 2]]
    assert info["detail"]["scene"] == pytest.approx(color.texture_bands(*color.surface_renders(scene, sample)), abs=1e-4)
    half = scene.replace(sh_dc=scene.sh_dc * 0.5)
    assert info["detail"]["reference"] == pytest.approx(color.texture_bands(*color.surface_renders(half, sample)),
                                                        abs=1e-4)
    assert info["detail"]["scene"] != pytest.approx(color.texture_bands(*color.surface_renders(scene, cams)), abs=1e-4)


def test_transfer_colors_target_groups_give_each_group_the_region_assigned_to_it():
    """target_groups (the style image's regions assigned to the groups, issue 39): group g takes the
    statistics of the target pixels labelled target_groups[g]; without it, of those labelled g."""
    from test_stylize import object_labels, ring, two_objects

    from ssgwarp.stylization import stylize as st

    scene, obj = two_objects(n=60, dtype=torch.float64)
    cams = ring(n=2, dtype=torch.float64)
    labels = object_labels(scene, obj, cams)
    target = torch.zeros(1, 20, 20, 3, dtype=torch.float64)
    tlab = torch.zeros(1, 20, 20, dtype=torch.long)
    target[0, :, :10] = torch.tensor([0.85, 0.15, 0.1], dtype=torch.float64)    # region 0: red
    target[0, :, 10:] = torch.tensor([0.1, 0.2, 0.85], dtype=torch.float64)     # region 1: blue
    tlab[0, :, 10:] = 1
    kw = dict(labels=labels, target_labels=tlab, assign=obj, num_groups=2, max_gain=4.0)
    swapped, info = transfer_colors(scene, cams, target, target_groups=[1, 0], **kw)
    straight, _ = transfer_colors(scene, cams, target, **kw)
    shared, _ = transfer_colors(scene, cams, target, target_groups=[1, 1], **kw)
    blue = lambda sc, k: float(sc.base_colors[obj == k].mean(0)[2] - sc.base_colors[obj == k].mean(0)[0])  # noqa: E731
    assert info["how"] == ["group", "group"]
    assert blue(swapped, 0) > 0.5 and blue(swapped, 1) < -0.5           # object 0 -> region 1 (blue), 1 -> red
    assert blue(straight, 0) < -0.5 and blue(straight, 1) > 0.5
    assert blue(shared, 0) > 0.5 and blue(shared, 1) > 0.5               # one region may serve several groups
    # a group whose region was a poor match (-1, issue 62) maps its own pixels to the whole target: half red, half
    # blue on average, whatever the other group takes
    back, info = transfer_colors(scene, cams, target, target_groups=[-1, 1], **kw)
    assert info["how"] == ["group", "group"] and abs(blue(back, 0)) < 0.25 and blue(back, 1) > 0.5


def test_region_target_keeps_half_the_styles_spread_around_the_regions_mean():
    """A group that takes a flat region of the style keeps its shading: the region's mean, half the
    whole style's covariance (a flat region alone would map every Gaussian of the group onto one colour)."""
    from ssgwarp.stylization.color import region_target

    whole = ColorStats().add(_cloud(500, [0.5, 0.4, 0.3], [[0.1, 0, 0], [0.02, 0.08, 0], [0, 0.01, 0.05]], 3))
    flat = ColorStats().add(torch.tensor([[0.2, 0.6, 0.9]], dtype=torch.float64).expand(50, 3))
    t = region_target(flat, whole)
    torch.testing.assert_close(t.mean, flat.mean)
    torch.testing.assert_close(t.cov, 0.5 * whole.cov)
    assert t.n == flat.n
    torch.testing.assert_close(region_target(flat, whole, spread=0.0).cov, flat.cov, atol=1e-12, rtol=0)
