"""Key view selection, the resize/pad rule and key view rendering/saving (ssgwarp.stylization.keyviews)."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError
from ssgwarp.stylization.keyviews import (content_size, diffusion_cameras, diffusion_size, from_diffusion, load_keyviews,
                              parse_ids, render_keyviews, save_keyviews, select_keyviews, to_diffusion)
from ssgwarp.raster.scene import GaussianScene


def ring_cameras(n: int, radius: float = 3.0, w: int = 50, h: int = 30) -> Cameras:
    ang = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    eyes = torch.stack([radius * torch.cos(ang), radius * torch.sin(ang), torch.zeros(n, dtype=torch.float64)], -1)
    vm = look_at(eyes, torch.zeros(n, 3)).float()
    return Cameras(vm, intrinsics(40.0, 40.0, w / 2, h / 2, n), w, h)


def _features(cams: Cameras) -> torch.Tensor:
    c = cams.centers.double()
    rel = c - c.mean(0)
    s = rel.pow(2).sum(-1).mean().sqrt()
    return torch.cat([rel / s, cams.forwards.double()], -1)


def _min_pairwise(feat: torch.Tensor, ids) -> float:
    return min(float((feat[a] - feat[b]).norm()) for a, b in itertools.combinations(ids, 2))


def test_select_ring_is_evenly_spread_in_farthest_point_order():
    """On a ring every camera is equally far from the rig's mean, so the lowest index starts; then the
    opposite camera (farthest in position and in direction), then the first of the two tied quarter points
    (ties go to the lowest index), then the other."""
    cams = ring_cameras(16)
    assert select_keyviews(cams, 4) == [0, 8, 4, 12]
    assert select_keyviews(cams, 2) == [0, 8]
    # the same ring numbered from camera 3: the same views, in the new numbering
    order = [(i + 3) % 16 for i in range(16)]
    assert [order[i] for i in select_keyviews(cams[order], 4)] == [3, 11, 7, 15]


def test_select_spread_close_to_optimal_on_random_rig():
    g = torch.Generator().manual_seed(3)
    n = 14
    eyes = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 1.0, 0.3], dtype=torch.float64)
    eyes[:, 1] += 4.0
    cams = Cameras(look_at(eyes, torch.zeros(n, 3)).float(), intrinsics(40, 40, 25, 15, n), 50, 30)
    feat = _features(cams)
    k = 4
    ids = select_keyviews(cams, k)
    assert len(set(ids)) == k
    best = max(_min_pairwise(feat, c) for c in itertools.combinations(range(n), k))
    got = _min_pairwise(feat, ids)
    print(f"min pairwise distance: farthest-point {got:.3f}, optimum {best:.3f}")
    assert got >= 0.5 * best  # farthest-point sampling is a 2-approximation of the max-min spread
    # and better than the first k cameras
    assert got > _min_pairwise(feat, range(k)) or got >= 0.99 * best


def test_select_user_ids_candidates_and_errors():
    cams = ring_cameras(10)
    assert select_keyviews(cams, 4, ids=[9, 2, 5]) == [9, 2, 5]
    assert parse_ids("0, 5,9") == [0, 5, 9] and parse_ids("") is None
    with pytest.raises(InputError, match="out of range"):
        select_keyviews(cams, ids=[0, 10])
    with pytest.raises(InputError, match="duplicates"):
        select_keyviews(cams, ids=[1, 1])
    with pytest.raises(InputError, match="comma-separated"):
        parse_ids("1;2")
    with pytest.raises(InputError):
        select_keyviews(cams, 0)
    cand = [1, 3, 5, 7]
    got = select_keyviews(cams, 2, candidates=cand)
    assert set(got) <= set(cand) and len(got) == 2
    assert select_keyviews(cams, 8, candidates=cand) == cand  # k >= candidates: all of them
    # all centres equal (a rotating tripod): directions alone decide
    vm = ring_cameras(8).viewmats.clone()
    vm[:, :3, 3] = 0.0
    tripod = Cameras(vm, intrinsics(40, 40, 25, 15, 8), 50, 30)
    ids = select_keyviews(tripod, 2)
    f = tripod.forwards
    assert float((f[ids[0]] * f[ids[1]]).sum()) < -0.99  # opposite directions


@pytest.mark.parametrize("w,h,side,expect", [(504, 378, 512, (512, 384)), (200, 200, 512, (512, 512)),
                                             (800, 600, 512, (512, 384)), (50, 30, 64, (64, 40)),
                                             (378, 504, 512, (384, 512)), (1000, 10, 64, (64, 8))])
def test_diffusion_size(w, h, side, expect):
    W, H = diffusion_size(w, h, side)
    assert (W, H) == expect and W % 8 == 0 and H % 8 == 0
    rw, rh = content_size(w, h, side)
    assert max(rw, rh) == side and rw <= W < rw + 8 and rh <= H < rh + 8
    assert abs(rw / rh - w / h) <= (w / h) * (1.0 / min(rh, rw))  # aspect kept up to rounding


def test_diffusion_size_rejects_bad_max_side():
    with pytest.raises(InputError, match="multiple of 8"):
        diffusion_size(100, 100, 500)


def test_resize_pad_round_trip():
    # no scaling: exact identity, numpy in numpy out
    img = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    d = to_diffusion(img, 64)
    assert isinstance(d, np.ndarray) and d.shape == (48, 64, 3)
    np.testing.assert_array_equal(from_diffusion(d, 64, 48), img)
    # smooth image, scaled and padded (50x30 -> content 64x38, padded to 64x40)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 30), torch.linspace(0, 1, 50), indexing="ij")
    smooth = torch.stack([torch.sin(3 * xx), torch.cos(2 * yy), xx * yy], -1)
    d = to_diffusion(smooth, 64)
    assert d.shape == (40, 64, 3)
    np.testing.assert_allclose(d[38:].numpy(), d[37:38].expand(2, -1, -1).numpy())  # edge padding
    back = from_diffusion(d, 50, 30)
    assert back.shape == smooth.shape
    err = float((back - smooth).abs().max())
    print(f"resize/pad round trip max error (smooth 50x30 via 64x40): {err:.4f}")
    assert err < 0.03
    with pytest.raises(InputError, match="not the diffusion size"):
        from_diffusion(d[:32], 50, 30)


def test_diffusion_cameras_follow_the_rule():
    cams = ring_cameras(3, w=50, h=30)
    dc = diffusion_cameras(cams, (64, 40))
    assert (dc.width, dc.height) == (64, 40)
    # a world point projects to pixel coordinates scaled by (rw/w, rh/h)
    p = torch.tensor([0.3, -0.2, 0.1, 1.0])
    def proj(c):
        x = (c.viewmats[0] @ p)[:3]
        uv = c.Ks[0] @ x
        return uv[:2] / uv[2]
    rw, rh = content_size(50, 30, 64)
    torch.testing.assert_close(proj(dc), proj(cams) * torch.tensor([rw / 50, rh / 30]))
    with pytest.raises(InputError, match="resize/pad rule"):
        diffusion_cameras(cams, (64, 48))


def _two_blob_scene():
    # two opaque clusters at different depths along the x axis, identities one-hot per cluster
    g = torch.Generator().manual_seed(0)
    a = torch.randn(20, 3, generator=g) * 0.05 + torch.tensor([0.0, -0.5, 0.0])
    b = torch.randn(20, 3, generator=g) * 0.05 + torch.tensor([-1.0, 0.5, 0.0])
    xyz = torch.cat([a, b])
    rgb = torch.cat([torch.tensor([[1.0, 0.0, 0.0]]).expand(20, 3), torch.tensor([[0.0, 0.0, 1.0]]).expand(20, 3)])
    scene = GaussianScene.from_points(xyz, rgb, opacity=0.9, scale=torch.full((40,), 0.12))
    ident = torch.zeros(40, 2)
    ident[:20, 0] = 1.0
    ident[20:, 1] = 1.0
    return scene.replace(identities=ident)


def test_render_keyviews_rgb_depth_groups():
    scene = _two_blob_scene()
    eye = torch.tensor([[3.0, 0.0, 0.0]])
    cams = Cameras(look_at(eye, torch.zeros(1, 3)).float(), intrinsics(30, 30, 25, 15, 1), 50, 30)
    clf = torch.nn.Linear(2, 3, bias=False)
    with torch.no_grad():
        clf.weight.copy_(torch.tensor([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]]))  # cluster a -> 1, cluster b -> 2
    kv = render_keyviews(scene, cams, [0], (64, 40), clf, background=(1.0, 1.0, 1.0))
    assert kv.rgb.shape == (1, 40, 64, 3) and kv.depth.shape == (1, 40, 64) and kv.groups.shape == (1, 40, 64)
    assert kv.groups.dtype == torch.long and kv.num_groups == 3 and kv.ids == [0]
    red = (kv.rgb[0, ..., 0] > 0.7) & (kv.rgb[0, ..., 2] < 0.3) & (kv.alpha[0] > 0.9)
    blue = (kv.rgb[0, ..., 2] > 0.7) & (kv.rgb[0, ..., 0] < 0.3) & (kv.alpha[0] > 0.9)
    assert red.sum() > 10 and blue.sum() > 10
    assert (kv.groups[0][red] == 1).all() and (kv.groups[0][blue] == 2).all()
    # expected depth: cluster a at distance ~3, cluster b at ~4
    assert abs(float(kv.depth[0][red].median()) - 3.0) < 0.2
    assert abs(float(kv.depth[0][blue].median()) - 4.0) < 0.2
    assert (kv.depth[0][kv.alpha[0] == 0] == 0).all()
    # without classifier: no group maps
    kv2 = render_keyviews(scene, cams, [0], (64, 40))
    assert kv2.groups is None and kv2.num_groups is None
    torch.testing.assert_close(kv2.depth, kv.depth, atol=1e-5, rtol=1e-5)


def test_save_and_load_keyviews(tmp_path):
    from ssgwarp.core.fileio import read_json

    scene = _two_blob_scene()
    cams = ring_cameras(4)
    clf = torch.nn.Linear(2, 3)
    kv = render_keyviews(scene, cams, [0, 2], (64, 40), clf)
    stylized = kv.rgb.flip(-1)
    path = save_keyviews(kv, tmp_path / "kv", stylized=stylized)
    meta = read_json(path)
    assert meta["ids"] == [0, 2] and meta["names"] == [cams.names[0], cams.names[2]]
    assert (meta["width"], meta["height"], meta["source_width"], meta["source_height"]) == (64, 40, 50, 30)
    for f in meta["files"]:
        for key in ("rgb", "depth", "alpha", "groups", "groups_color", "stylized"):
            assert (tmp_path / "kv" / f[key]).is_file()
    assert (tmp_path / "kv" / "sheet.png").is_file()
    kv2, st2 = load_keyviews(tmp_path / "kv")
    assert torch.equal(kv2.groups, kv.groups) and kv2.ids == kv.ids
    torch.testing.assert_close(kv2.depth, kv.depth)
    assert float((kv2.rgb - kv.rgb).abs().max()) <= 0.5 / 255 + 1e-6
    assert float((st2 - stylized).abs().max()) <= 0.5 / 255 + 1e-6
    torch.testing.assert_close(kv2.cameras.Ks, kv.cameras.Ks)


def test_cli_keyviews_on_a_run_directory(tmp_path):
    from ssgwarp.cli import main
    from ssgwarp.core.fileio import read_json, write_json
    from ssgwarp.formats.ply import write_ply

    run = tmp_path / "run"
    run.mkdir()
    scene = _two_blob_scene()
    write_ply(run / "scene.ply", scene)
    cams = ring_cameras(6)
    cams.save(run / "cameras.json")
    write_json(run / "data.json", {"split": {"train": cams.names[:5], "test": cams.names[5:]},
                                   "background": [1.0, 1.0, 1.0]})
    clf = torch.nn.Linear(2, 3)
    (run / "groups").mkdir()
    torch.save({"dim": 2, "num_groups": 3, "state_dict": clf.state_dict()}, run / "groups" / "classifier.pt")
    out = tmp_path / "kv"
    rc = main(["keyviews", str(run), "--keyviews", "2", "--out", str(out), "--max-side", "64", "--device", "cpu"])
    assert rc == 0
    meta = read_json(out / "keyviews.json")
    assert len(meta["ids"]) == 2 and all(i < 5 for i in meta["ids"])  # chosen among the training views
    assert meta["num_groups"] == 3 and (meta["width"], meta["height"]) == (64, 40)
    assert main(["keyviews", str(run), "--ids", "5,0", "--out", str(out), "--max-side", "64",
                 "--device", "cpu"]) == 2                      # an existing output needs --force
    assert main(["keyviews", str(run), "--ids", "5,0", "--out", str(out), "--max-side", "64",
                 "--device", "cpu", "--force"]) == 0
    assert read_json(out / "keyviews.json")["ids"] == [5, 0]
    assert main(["keyviews", str(run), "--ids", "9", "--out", str(out), "--device", "cpu"]) == 2
