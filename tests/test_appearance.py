"""Per-image appearance (ssgwarp.reconstruction.appearance, ``reconstruct --appearance``) and its test capture
(ssgwarp.procedural.vary_exposures)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ssgwarp.core.fileio import read_image, write_image
from ssgwarp.errors import InputError
from ssgwarp.reconstruction import appearance as ap
from ssgwarp.services.losses import psnr


def _photo(h=24, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(h // 4, w // 4, 3, generator=g)
    return base.repeat_interleave(4, 0).repeat_interleave(4, 1) * 0.7 + 0.1


def test_fit_affine_recovers_a_colour_transform_and_the_ridge_pulls_toward_identity():
    c = _photo()
    a = torch.ones(*c.shape[:2], 1)
    W = torch.tensor([[1.3, 0.05, 0.0, 0.02], [0.0, 0.9, 0.1, -0.03], [0.02, 0.0, 0.7, 0.05]])
    y = ap.apply_affine(W, c, a)
    assert torch.allclose(ap.fit_affine(torch.cat([c, a], -1), y, ridge=0.0), W, atol=1e-4)
    strong = ap.fit_affine(torch.cat([c, a], -1), y, ridge=100.0)
    assert (strong - torch.eye(3, 4)).abs().max() < 0.05


def test_the_half_protocol_fits_on_the_left_and_scores_the_right_half():
    """A held-out photo that is the render under an unknown exposure scores (nearly) perfectly; the right half
    only (the fit never sees it); the background of an RGBA capture stays untransformed."""
    c = _photo(seed=1)
    a = torch.ones(*c.shape[:2], 1)
    a[:, :3] = 0.0  # uncovered columns: the background shows
    c = c * a
    bg = torch.tensor([1.0, 1.0, 1.0])
    gt = c * torch.tensor([0.6, 0.65, 0.55]) + (1 - a) * bg
    pred, right, mask = ap.score_half(c, a, gt, bg)
    assert pred.shape == right.shape == (24, 16, 3) and mask is None
    assert torch.equal(right, gt[:, 16:])
    assert float(psnr(pred, right)) > 50.0
    raw = (c + (1 - a) * bg)[:, 16:]
    assert float(psnr(raw, right)) < 20.0


class _Capture(SimpleNamespace):
    def background_tensor(self, channels=3):
        return torch.zeros(channels)


def _probe_case(gains, noise=0.02, views=12, seed=0):
    """Renders of views of a scene (a slightly wrong render: ``noise`` per region) and photos that are
    the true scene under ``gains[i]`` (per channel)."""
    g = torch.Generator().manual_seed(seed)
    truth = [_photo(seed=10 + i) for i in range(views)]
    renders = [t * (1 + noise * torch.randn(6, 8, 3, generator=g).repeat_interleave(4, 0).repeat_interleave(4, 1))
               for t in truth]
    images = torch.stack([t * gains[i] for i, t in enumerate(truth)])
    data = _Capture(images=images, masks=None)
    alpha = torch.ones(24, 32, 1)
    return ap.probe(lambda i: (renders[i], alpha), data, list(range(views)))


def test_auto_turns_on_for_photos_whose_exposures_differ_and_stays_off_otherwise():
    rng = np.random.default_rng(0)
    varied = torch.tensor(rng.uniform(0.6, 1.4, (12, 1)) * (1 + rng.uniform(-0.1, 0.1, (12, 3))), dtype=torch.float32)
    on = _probe_case(varied)
    assert on["use"] and on["exposure_spread"] > 0.15 and on["probe_views"] == 12, on
    off = _probe_case(torch.ones(12, 3))
    assert not off["use"] and off["exposure_spread"] < ap.MIN_SPREAD, off
    # a render whose error is large, but not the same in both halves of a view: still off
    noisy = _probe_case(torch.ones(12, 3), noise=0.15)
    assert not noisy["use"], noisy
    slight = _probe_case(torch.tensor(rng.uniform(0.99, 1.01, (12, 1)), dtype=torch.float32).repeat(1, 3))
    assert not slight["use"], slight
    assert "why" in on and "exposures differ" in on["why"] and "agree" in off["why"]


def test_the_transforms_keep_their_mean_at_the_identity():
    """Three photos at gains 0.5, 1, 2 (mean 7/6) of a render that is twice too dark: the loss's transforms are fitted per view and composed with the inverse of their mean, so the render
    is pulled toward the photos' mean exposure, not toward any one photo."""
    c = _photo(seed=3)
    a = torch.ones(*c.shape[:2], 1)
    app = ap.Appearance(3, [0, 1, 2], "cpu", ridge=0.0)
    gains = [0.5, 1.0, 2.0]
    render = 0.5 * c
    gt = torch.stack([g * c for g in gains])
    args = (render.expand(3, -1, -1, -1), a.expand(3, -1, -1, -1), gt, torch.zeros(3, 3))
    first = app([0, 1, 2], *args)   # nothing fitted before: the fits themselves
    assert torch.allclose(first[2], gt[2], atol=1e-4)
    out = app([0, 1, 2], *args)     # now the mean of the fits is known
    mean_gain = sum(g / 0.5 for g in gains) / 3
    # each view's transform is its gain over the render's; the loss uses it over the mean of them
    for j, g in enumerate(gains):
        assert torch.allclose(out[j], render * (g / 0.5) / mean_gain, atol=1e-4)
    s = app.summary()
    assert s["fitted_views"] == 3 and abs(s["gain_max"] - 4.0) < 1e-3


def test_vary_exposures_writes_a_seeded_copy(tmp_path):
    src = tmp_path / "cap"
    (src / "images").mkdir(parents=True)
    img = np.concatenate([np.full((4, 5, 3), 0.5, np.float32), np.full((4, 5, 1), 0.8, np.float32)], -1)
    for n in ("a.png", "b.png", "c.png"):
        write_image(src / "images" / n, img)
    (src / "transforms.json").write_text("{}")
    f = ap_vary(src, tmp_path / "v1", seed=3)
    assert sorted(f) == ["images/a.png", "images/b.png", "images/c.png"]
    assert (tmp_path / "v1" / "transforms.json").read_text() == "{}"
    for n, fac in f.items():
        g = np.asarray(fac)
        assert 0.6 * 0.9 - 1e-6 <= g.min() and g.max() <= 1.4 * 1.1 + 1e-6
        out = read_image(tmp_path / "v1" / n)
        assert np.allclose(out[0, 0, :3], np.clip(128 / 255 * g, 0, 1), atol=0.6 / 255)
        assert abs(out[0, 0, 3] - 0.8) < 1 / 255   # alpha unchanged
    assert ap_vary(src, tmp_path / "v2", seed=3) == f
    only = ap_vary(src, tmp_path / "v3", seed=3, names=["images/b.png"])
    assert only == {"images/b.png": f["images/b.png"]}
    assert np.allclose(read_image(tmp_path / "v3" / "images" / "a.png"), read_image(src / "images" / "a.png"))
    with pytest.raises(InputError):
        ap_vary(src, tmp_path / "v1")


def ap_vary(*a, **k):
    from ssgwarp.procedural import vary_exposures

    return vary_exposures(*a, **k)


def test_check_mode_and_start_step():
    assert ap.check_mode("auto") == "auto"
    with pytest.raises(InputError, match="--appearance"):
        ap.check_mode("maybe")
    assert ap.start_step(600) == 100 and ap.start_step(60) == 50 and ap.start_step(30000) == 500
    assert math.isclose(ap.MIN_SPREAD, 0.03)
