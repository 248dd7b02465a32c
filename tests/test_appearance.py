"""Per-image appearance (ssgwarp.reconstruction.appearance, ``reconstruct --appearance``) and its test capture
(ssgwarp.procedural.vary_exposures)."""
from __future__ import annotations

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


def test_the_transforms_keep_their_mean_at_the_identity():
    """Three photos at gains 0.5, 1, 1.2 of a render that is twice too dark: the loss's transforms are fitted per view and composed with the inverse of their mean, so the render
    is pulled toward the photos' mean exposure, not toward any one photo."""
    c = _photo(seed=3)
    a = torch.ones(*c.shape[:2], 1)
    app = ap.Appearance(3, [0, 1, 2], "cpu", ridge=0.0)
    gains = [0.5, 1.0, 1.2]
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
    assert s["fitted_views"] == 3 and abs(s["gain_max"] - 2.4) < 1e-3


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
    assert 0.03 <= ap.MIN_SPREAD <= 0.15


def _points_capture(gains, n_points=600, size=64, seed=0):
    """Points on a sphere seen by a ring of cameras; each image shows every point's colour (times the
    image's ``gains[i]``) at its pixel, on grey."""
    from ssgwarp.core.geometry import project
    from ssgwarp.procedural import ring_cameras

    g = torch.Generator().manual_seed(seed)
    xyz = torch.nn.functional.normalize(torch.randn(n_points, 3, generator=g), dim=1) * 0.8
    rgb = 0.15 + 0.7 * torch.rand(n_points, 3, generator=g)
    cams = ring_cameras(len(gains), size, size)
    images = torch.full((len(gains), size, size, 3), 0.5)
    for i in range(len(gains)):
        uv, z = project(xyz, cams.viewmats[i], cams.Ks[i])
        u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
        ok = (z > 0) & (u >= 0) & (u < size) & (v >= 0) & (v < size)
        images[i, v[ok], u[ok]] = (rgb[ok] * gains[i]).clamp(0, 1)
    return SimpleNamespace(cameras=cams, images=images, train_ids=list(range(len(gains)))), xyz


def test_the_points_probe_finds_differing_exposures_before_training():
    """The capture's points seen in several photos: their colours differ by the photos' gains (on) or not (off),
    with occlusions (a point behind the sphere shows another point's colour) as outliers."""
    rng = np.random.default_rng(1)
    varied = torch.tensor(rng.uniform(0.6, 1.4, (10, 1)) * (1 + rng.uniform(-0.1, 0.1, (10, 3))), dtype=torch.float32)
    data, xyz = _points_capture(varied)
    on = ap.points_probe(data, xyz)
    assert on["use"] and on["probe"] == "points" and on["exposure_spread"] > 0.15, on
    data, xyz = _points_capture(torch.ones(10, 3))
    off = ap.points_probe(data, xyz)
    assert not off["use"] and off["exposure_spread"] < 0.01, off
    assert ap.points_probe(data, xyz[:50]) is None   # too few points: the render probe decides


def test_a_run_with_appearance_fits_each_photo_resumes_and_scores_held_out_halves(tmp_path):
    """auto on a capture whose photos differ (decided before training from its points); the transforms start at
    their step, are fitted for the views visited, go through a checkpoint, and held-out views are scored on
    their right half (``eval_protocol``); ``off`` scores whole images."""
    from ssgwarp.capture.datasets import SceneData
    from ssgwarp.reconstruction.trainer import Trainer

    rng = np.random.default_rng(2)
    gains = torch.tensor(rng.uniform(0.6, 1.4, (10, 1)).repeat(3, 1), dtype=torch.float32)
    cap, xyz = _points_capture(gains, size=32)
    rgb = torch.full((len(xyz), 3), 0.5)
    data = SceneData(cap.cameras, cap.images, [f"v{i}" for i in range(10)], list(range(1, 10)), [0],
                     points=(xyz, rgb), points_source="colmap", background=(0.5, 0.5, 0.5))
    kw = dict(iters=60, sh_degree=0, progress=False, device="cpu", checkpoint_path=tmp_path / "c.pt", backdrop="off")
    t = Trainer(data, **kw)
    assert t.appearance_record["use"] and t.appearance_record["probe"] == "points" and t.appearance_start == 50
    t.train()
    assert int(t.appearance.fitted.sum()) >= 5 and not bool(t.appearance.fitted[0])
    assert t.eval_protocol == ap.HALF_PROTOCOL and t.evaluate()["views"] == 1
    t.save_checkpoint()
    u = Trainer(data, **kw)
    u.load_checkpoint()
    assert torch.equal(u.appearance.table, t.appearance.table) and u.appearance_record == t.appearance_record
    off = Trainer(data, **{**kw, "appearance": "off", "iters": 2, "checkpoint_path": None})
    assert off.appearance is None and off.eval_protocol == ap.FULL_PROTOCOL
    assert off.appearance_record == {"mode": "off", "use": False, "why": "--appearance off", "start_step": 50}
