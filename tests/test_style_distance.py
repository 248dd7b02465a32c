"""Weight-free style distances (ssgwarp.evaluation.metrics): sliced Wasserstein hand cases, the filter bank, StyleDistance."""
from __future__ import annotations

import math

import pytest
import torch

from ssgwarp.evaluation.metrics import empty_spread, style_scores
from ssgwarp.evaluation.style_distance import StyleDistance, filter_responses, projections, sliced_wasserstein, texture_levels, wasserstein_1d_sorted


def _image(seed: int, h: int = 48, w: int = 64) -> torch.Tensor:
    """A smooth colourful test image with some edges."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    a, b = torch.rand(2, generator=g) * 6 + 2
    img = torch.stack([0.5 + 0.4 * torch.sin(a * xx + 1.0), 0.5 + 0.4 * torch.cos(b * yy),
                       ((xx * 4).floor() + (yy * 3).floor()) % 2 * 0.6 + 0.2], -1)
    return img.clamp(0, 1)


def _stripes(h: int = 48, w: int = 64) -> torch.Tensor:
    xx = torch.arange(w)[None, :].expand(h, w)
    yy = torch.arange(h)[:, None].expand(h, w)
    on = ((xx + yy) // 3) % 2 == 0
    return torch.where(on[..., None], torch.tensor([0.9, 0.2, 0.1]), torch.tensor([0.95, 0.9, 0.7]))


def test_one_dimensional_hand_cases():
    x = torch.randn(500, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert float(sliced_wasserstein(x, x)) == 0.0                                  # identical -> 0
    assert float(sliced_wasserstein(x, x + 0.7)) == pytest.approx(0.7, abs=1e-12)  # a shift by c -> |c|
    # different sample sizes, exact: {0, 1} vs {0, 0.5, 1}: W2^2 = 0.25 * (1/6 + 1/6) = 1/12
    a = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    b = torch.tensor([[0.0], [0.5], [1.0]], dtype=torch.float64)
    assert float(sliced_wasserstein(a, b)) == pytest.approx(math.sqrt(1 / 12), abs=1e-12)
    assert float(wasserstein_1d_sorted(a.T, b.T)[0]) == pytest.approx(1 / 12, abs=1e-15)
    # a uniform grid on [0, 1) against a finer one: W2^2 of the step quantile functions, by hand
    u = (torch.arange(4, dtype=torch.float64) / 4)[:, None]
    v = (torch.arange(8, dtype=torch.float64) / 8)[:, None]
    assert float(sliced_wasserstein(u, v)) == pytest.approx(math.sqrt(0.5 * (1 / 8) ** 2), abs=1e-12)


def test_projections_are_seeded_and_include_the_axes():
    d1, d2 = projections(3, 64), projections(3, 64)
    assert torch.equal(d1, d2) and d1.shape == (64, 3)
    assert torch.equal(d1[:3], torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(d1.norm(dim=1), torch.ones(64, dtype=torch.float64))
    assert not torch.equal(projections(3, 64, seed=1), d1)
    # the distance in 3-D: a constant shift by vector c -> sqrt(mean_theta <c, theta>^2)
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    c = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    expect = math.sqrt(float(((d1 @ c) ** 2).mean()))
    assert float(sliced_wasserstein(x, x + c)) == pytest.approx(expect, abs=1e-12)


def test_filter_bank_responds_to_edges_and_not_to_flat_images():
    flat = torch.full((32, 40), 55.0)
    for r in filter_responses(flat):
        assert r.abs().max() < 1e-4
    edge = torch.zeros(32, 40)
    edge[:, 20:] = 50.0                                     # a vertical edge: varies along x only
    r0 = filter_responses(edge, levels=1)[0]                # [pixels, 8]: 4 first-order, then 4 second-order
    strength = r0.abs().amax(0)
    assert strength[0] > 10 and strength[2] < 1e-3          # 0 deg (along x) responds, 90 deg does not
    assert strength[1] > 1 and strength[3] > 1              # the diagonals see part of it
    levels = filter_responses(torch.rand(64, 96), levels=4)
    assert [r.shape for r in levels] == [(64 * 96, 8), (32 * 48, 8), (16 * 24, 8), (8 * 12, 8)]
    # texture scales only: filter scale 2^k px up to 1/16 of the shorter side, at most 4 levels
    assert [texture_levels(n, 2 * n) for n in (20, 32, 63, 64, 127, 128, 1000)] == [1, 2, 2, 3, 3, 4, 4]
    assert StyleDistance(torch.rand(40, 40, 3)).levels_for(72, 96) == 3


def test_style_distance_identical_permutation_and_determinism():
    style = _stripes()
    dist = StyleDistance(style)
    same = dist(style[None])
    assert float(same["color"][0]) < 1e-9 and float(same["texture"][0]) < 1e-9
    img = _image(0)
    d = dist(img[None])
    assert float(d["color"][0]) > 5 and float(d["texture"][0]) > 0.5
    again = StyleDistance(style)(img[None])
    assert torch.equal(d["color"], again["color"]) and torch.equal(d["texture"], again["texture"])
    # the colour term is a distance between colour distributions: any pixel permutation gives the same value
    perm = torch.randperm(img.shape[0] * img.shape[1], generator=torch.Generator().manual_seed(3))
    shuffled = img.reshape(-1, 3)[perm].reshape(img.shape)
    ds = dist(shuffled[None])
    assert float(ds["color"][0]) == pytest.approx(float(d["color"][0]), rel=1e-6)
    assert abs(float(ds["texture"][0]) - float(d["texture"][0])) > 0.5   # while texture sees the spatial structure


@pytest.mark.parametrize("seed", [0, 1])
def test_style_distance_is_monotone_along_a_blend_toward_the_style(seed):
    style = _stripes()
    dist = StyleDistance(style)
    img = _image(seed)
    ts = [0.0, 0.25, 0.5, 0.75, 1.0]
    vals = dist(torch.stack([(1 - t) * img + t * style for t in ts]))
    for k in ("color", "texture"):
        v = vals[k].tolist()
        assert all(b < a for a, b in zip(v, v[1:])), (k, v)
        assert v[-1] < 1e-6 and v[0] > 0


def test_style_distance_compares_the_scene_pixels_only_when_alphas_are_given():
    style = _stripes()
    dist = StyleDistance(style)
    img = style.clone()
    alpha = torch.ones(img.shape[:2])
    alpha[:, 40:] = 0.0
    img[:, 40:] = torch.tensor([0.0, 1.0, 0.0])            # a green background where alpha is 0
    masked, full = dist(img[None], alpha[None]), dist(img[None])
    assert float(masked["color"][0]) < 0.3 * float(full["color"][0])
    assert float(masked["texture"][0]) < float(full["texture"][0])
    none = dist(img[None], torch.zeros(1, *img.shape[:2]))
    assert math.isnan(float(none["color"][0])) and dist.mean(img[None], torch.zeros(1, *img.shape[:2]))["color"] is None


def test_empty_spread_is_zero_on_a_flat_background_and_grows_with_blobs():
    img = torch.full((2, 20, 30, 3), 0.9)                   # a white-ish background ...
    img[:, 5:15, 5:15] = torch.tensor([0.2, 0.4, 0.1])      # ... and an object
    alpha0 = torch.zeros(2, 20, 30)
    alpha0[:, 5:15, 5:15] = 1.0
    empty = alpha0 < 0.05
    assert empty_spread(img, empty) == pytest.approx(0.0, abs=1e-7)
    blob = img.clone()
    blob[0, 0:4, 20:24] = torch.tensor([1.0, 0.0, 0.0])     # a red floater over the background: 16 of 1,000 empty px
    one = empty_spread(blob, empty)
    expected = math.sqrt(16 / (2 * 500) * (0.1 ** 2 + 0.9 ** 2 + 0.9 ** 2))
    assert one == pytest.approx(expected, rel=1e-5)
    blob[1, 0:4, 20:24] = torch.tensor([1.0, 0.0, 0.0])     # twice the floaters: more spread
    assert empty_spread(blob, empty) > one
    assert empty_spread(img, torch.zeros_like(empty)) is None            # a capture that fills the frame
    # style_scores reports it with the original alphas (a stylize output's source), not without
    style = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(0))
    sc = style_scores(None, blob, style, img, alphas=alpha0, original_alphas=alpha0)
    assert sc["empty_share"] == pytest.approx(500 / 600) and sc["empty_spread_original"] == pytest.approx(0.0, abs=1e-7)
    assert sc["empty_spread"] > 0.05
    assert "empty_spread" not in style_scores(None, blob, style, img, alphas=alpha0)


def test_halves_of_a_uniform_style_are_close_and_of_a_split_style_far():
    """StyleDistance.halves: a style that is the same pattern across the canvas scores about 0 against itself
    (its halves are alike); one whose left half is flat and right half striped scores a large texture and
    colour distance (each half misses what the other holds); the value is the mean of the two halves."""
    stripes = _stripes(48, 128)
    uniform = StyleDistance(stripes).halves(48, 128)
    split = stripes.clone()
    split[:, :64] = torch.tensor([0.5, 0.5, 0.5])
    far = StyleDistance(split).halves(48, 128)
    assert uniform["texture"] < 0.1 * far["texture"] and uniform["color"] < 0.05 * far["color"]
    assert far["texture"] > 1.0 and far["color"] > 5.0
    d = StyleDistance(split)
    whole = d(split[:, :64][None])["texture"][0], d(split[:, 64:][None])["texture"][0]
    # the same as scoring each half as an image (same fit of the style, same levels)
    assert far["texture"] == pytest.approx(float(sum(whole)) / 2, rel=1e-9)
