"""Points from known poses (ssgwarp.capture.triangulate) and the initial-points options of load_dataset.

The scenes are ray-cast here: a textured ground square and a textured box on it, so every pixel's surface
point is known exactly and a triangulated point's distance to the true surface can be measured.
"""
from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch

import ssgwarp.capture.triangulate as tri_mod
from ssgwarp.capture.datasets import check_init, load_dataset
from ssgwarp.services.runs import data_json
from ssgwarp.capture.triangulate import select_pairs, triangulate
from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError
from ssgwarp.procedural import write_transforms_dataset

BOX_C = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
BOX_H = 0.5          # half size: the box spans [-0.5, 0.5]^2 x [0, 1]
GROUND = 2.5         # the ground square spans [-2.5, 2.5]^2 at z = 0


def _noise(seed: int, cells: int = 16) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(1, 3, cells, cells, generator=g, dtype=torch.float64)


TEX_GROUND, TEX_BOX = _noise(1), _noise(2)


def _texture(tex: torch.Tensor, a: torch.Tensor, b: torch.Tensor, period: float) -> torch.Tensor:
    """Bilinear value noise at surface coordinates (a, b) (tiled every ``period`` units) -> [N, 3]."""
    grid = torch.stack([(a / period) % 1.0 * 2 - 1, (b / period) % 1.0 * 2 - 1], -1)[None, None]
    return torch.nn.functional.grid_sample(tex, grid, mode="bilinear", align_corners=False)[0, :, 0].T


def _surface_distance(x: torch.Tensor) -> torch.Tensor:
    """Distance of points [N, 3] to the union of the ground square and the box's surface."""
    x = x.double()
    q = (x - BOX_C).abs() - BOX_H
    box = q.clamp_min(0).norm(dim=1) + q.max(dim=1).values.clamp_max(0)
    ground = torch.sqrt(x[:, 2] ** 2 + ((x[:, :2].abs() - GROUND).clamp_min(0) ** 2).sum(1))
    return torch.minimum(box.abs(), ground)


def _render(cams: Cameras) -> torch.Tensor:
    """Ray-cast the box on the ground: [C, H, W, 3] (sky grey where nothing is hit)."""
    C, W, H = len(cams), cams.width, cams.height
    out = []
    c2w = torch.linalg.inv(cams.viewmats.double())
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.ones(H * W, dtype=torch.float64)], 1)
    for i in range(C):
        d = pix @ torch.linalg.inv(cams.Ks[i].double()).T @ c2w[i, :3, :3].T
        o = c2w[i, :3, 3].expand_as(d)
        t_best = torch.full((len(d),), math.inf, dtype=torch.float64)
        col = torch.full((len(d), 3), 0.55, dtype=torch.float64)
        # ground
        tg = -o[:, 2] / d[:, 2]
        pg = o + tg[:, None] * d
        hit = (tg > 0) & (pg[:, :2].abs() <= GROUND).all(1)
        t_best = torch.where(hit, tg, t_best)
        gcol = 0.5 * _texture(TEX_GROUND, pg[:, 0], pg[:, 1], 1.6) + torch.tensor([0.2, 0.35, 0.5], dtype=torch.float64)
        col = torch.where(hit[:, None], gcol, col)
        # box (slab method)
        inv = 1.0 / d
        t1, t2 = (BOX_C - BOX_H - o) * inv, (BOX_C + BOX_H - o) * inv
        tn, tf = torch.minimum(t1, t2).max(1).values, torch.maximum(t1, t2).min(1).values
        hb = (tn <= tf) & (tn > 0) & (tn < t_best)
        pb = o + tn[:, None] * d
        axis = torch.minimum(t1, t2).argmax(1)   # the face hit: its normal axis
        a = torch.where(axis == 0, pb[:, 1], pb[:, 0])
        b = torch.where(axis == 2, pb[:, 1], pb[:, 2])
        bcol = 0.5 * _texture(TEX_BOX, a + axis * 0.37, b, 0.8) + torch.tensor([0.5, 0.3, 0.15], dtype=torch.float64)
        col = torch.where(hb[:, None], bcol, col)
        out.append(col.reshape(H, W, 3))
    return torch.stack(out).float().clamp(0, 1)


def _cameras(n: int = 8, size: int = 160) -> Cameras:
    """``n`` views in rows of 4 (2.4 units wide, rows 0.5 apart) 3.2 units from the box, looking at it."""
    k = torch.arange(n, dtype=torch.float64)
    eyes = torch.stack([torch.full_like(k, 3.2), (k % 4 - 1.5) / 1.5 * 1.2, 1.6 + 0.5 * (k // 4)], 1)
    vm = look_at(eyes, torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64).expand(n, 3))
    f = 0.5 * size / math.tan(math.radians(30))
    return Cameras(vm.float(), intrinsics(f, f, size / 2, size / 2, n), size, size, [f"v{i}" for i in range(n)])


@pytest.fixture(scope="module")
def scene():
    cams = _cameras()
    return cams, _render(cams)


@pytest.fixture(scope="module")
def result(scene):
    cams, imgs = scene
    return triangulate(cams, imgs, progress=False)


def test_points_lie_on_the_true_surface_with_the_surface_colour(result):
    r = result
    assert r.xyz.dtype == torch.float32 and r.xyz.shape == (r.stats["count"], 3) and r.rgb.shape == r.xyz.shape
    assert len(r) >= 250, r.stats
    dist = _surface_distance(r.xyz)
    # the scene is 5 units across; a pixel at 3-4 units is ~0.025 units, the baselines are short
    assert float(dist.median()) < 0.03 and float(dist.quantile(0.9)) < 0.15, (dist.median(), dist.quantile(0.9))
    assert r.stats["median_reprojection_error_px"] < 0.5
    assert r.stats["mean_track_length"] > 2.0 and r.stats["tracks"] >= len(r)
    # points on both surfaces, coloured like them (the box is orange-tinted, the ground blue-tinted)
    on_box = (_surface_distance(r.xyz) < 0.05) & (r.xyz[:, 2] > 0.1)
    on_ground = r.xyz[:, 2].abs() < 0.05
    assert on_box.sum() > 30 and on_ground.sum() > 100
    assert bool((r.rgb[on_box, 0] > r.rgb[on_box, 2]).float().mean() > 0.9)
    assert bool((r.rgb[on_ground, 2] > r.rgb[on_ground, 0]).float().mean() > 0.9)
    assert float(r.rgb.min()) >= 0 and float(r.rgb.max()) <= 1
    assert sum(r.stats["observations_per_view"].values()) == pytest.approx(r.stats["mean_track_length"] * len(r))


def test_deterministic(scene, result):
    cams, imgs = scene
    again = triangulate(cams, imgs, progress=False)
    assert torch.equal(again.xyz, result.xyz) and torch.equal(again.rgb, result.rgb)


def test_pairs_follow_the_overlap():
    cams = _cameras(8)
    pairs = select_pairs(cams, neighbours=2)
    # each view's two best partners are next to it, never at the other end of the row
    assert len(pairs) <= 16 and (0, 1) in pairs and (2, 3) in pairs
    assert not any({i % 4, j % 4} == {0, 3} for i, j in pairs)
    assert len(select_pairs(cams, neighbours=7)) == 28
    # a view looking away from everything is matched with nothing
    vm = cams.viewmats.clone()
    vm[3] = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0])) @ vm[3]   # turned around: faces outwards
    assert all(3 not in p for p in select_pairs(Cameras(vm, cams.Ks, 128, 128), neighbours=3))


def test_a_wrong_pose_is_filtered_out(scene, result):
    cams, imgs = scene
    vm = cams.viewmats.clone().double()
    th = math.radians(3.0)
    # view 2 is turned 3 degrees (~7 px) away from its image, about a diagonal axis (off every epipolar line)
    kx = torch.tensor([[0, 0, 1], [0, 0, -1], [-1, 1, 0]], dtype=torch.float64) / math.sqrt(2)
    rot = torch.eye(3, dtype=torch.float64) + math.sin(th) * kx + (1 - math.cos(th)) * kx @ kx
    vm[2, :3, :3] = rot @ vm[2, :3, :3]
    vm[2, :3, 3] = rot @ vm[2, :3, 3]
    bad = Cameras(vm.float(), cams.Ks, cams.width, cams.height, cams.names)
    r = triangulate(bad, imgs, progress=False)
    per_view = r.stats["observations_per_view"]
    others = np.median([v for k, v in per_view.items() if k != "v2"])
    assert per_view["v2"] < 0.1 * others, per_view
    assert result.stats["observations_per_view"]["v2"] > 0.5 * others   # (with the right pose it is used)
    dist = _surface_distance(r.xyz)
    assert len(r) > 150 and float(dist.median()) < 0.03 and float(dist.quantile(0.9)) < 0.15


def test_wrong_matches_are_rejected(scene, result, monkeypatch):
    """Random wrong matches added to every pair: the epipolar test drops them (as many as the right ones);
    without it the reprojection test does (one in ten)."""
    cams, imgs = scene
    real = tri_mod._match

    frac = {"value": 1.0}

    def noisy(da, db, ratio):
        m = real(da, db, ratio)
        g = torch.Generator().manual_seed(len(da) * 7919 + len(db))
        k = max(2, int(frac["value"] * len(m)))
        wrong = torch.stack([torch.randint(0, len(da), (k,), generator=g), torch.randint(0, len(db), (k,), generator=g)], 1)
        return torch.cat([m, wrong])

    monkeypatch.setattr(tri_mod, "_match", noisy)
    for eps, f, least in ((2.0, 1.0, 150), (math.inf, 0.1, 100)):
        frac["value"] = f
        r = triangulate(cams, imgs, progress=False, max_epipolar_px=eps)
        dist = _surface_distance(r.xyz)
        assert len(r) > least, (eps, r.stats)
        assert float(dist.median()) < 0.03 and float(dist.quantile(0.9)) < 0.15, (eps, dist.quantile(0.9))
        assert r.stats["median_reprojection_error_px"] < 0.6
    assert r.stats["matches"] > 1.05 * result.stats["matches"]   # without the epipolar test they came through


def test_filters_and_small_inputs(scene, result):
    cams, imgs = scene
    strict = triangulate(cams, imgs, progress=False, max_reproj_px=0.3, min_angle_deg=20.0)
    assert 0 < len(strict) < len(result)
    # the largest angle between two rays of every kept point is at least 20 degrees
    centres = cams.centers.double()
    x = strict.xyz.double()
    rays = torch.nn.functional.normalize(x[:, None] - centres[None], dim=-1)
    cos = torch.einsum("pci,pdi->pcd", rays, rays)
    assert bool((cos.flatten(1).min(1).values <= math.cos(math.radians(20.0)) + 1e-6).all())
    one = triangulate(cams[[0]], imgs[:1], progress=False)
    assert len(one) == 0 and one.stats["count"] == 0
    flat = triangulate(cams, torch.full_like(imgs, 0.5), progress=False)
    assert len(flat) == 0 and flat.stats["median_reprojection_error_px"] is None
    with pytest.raises(InputError, match="do not match"):
        triangulate(cams, imgs[:3], progress=False)
    with pytest.raises(InputError, match="64x64"):
        triangulate(cams, imgs[:, :64, :64].contiguous(), progress=False)
    # features on shrunk images: fewer, errors reported in pixels of the given images
    small = triangulate(cams, imgs, progress=False, max_size=96)
    assert small.stats["scale"] == 0.6 and 0 < len(small) < len(result)
    assert float(_surface_distance(small.xyz).median()) < 0.06


# ----------------------------------------------------------------------------- load_dataset(init=...)
@pytest.fixture(scope="module")
def capture(tmp_path_factory, scene):
    cams, imgs = scene
    folder = tmp_path_factory.mktemp("cap")
    write_transforms_dataset(folder, imgs, cams)
    return folder


def test_load_dataset_triangulates_a_capture_without_points(capture, result):
    d = load_dataset(capture, num_random_points=300, progress=False)
    assert d.points_source == "triangulated" and d.options["init"] == "auto"
    # from the training views only: the held-out view 0 is not used
    assert d.test_ids == [0] and set(d.points_stats["observations_per_view"]) == {f"images/v{i}.png" for i in range(1, 8)}
    assert 0.6 * len(result) < len(d.points[0]) < len(result)
    assert float(_surface_distance(d.points[0]).median()) < 0.03
    # near / far now come from the triangulated points, not the guessed cube
    z = torch.einsum("cij,pj->cpi", d.cameras.viewmats[:, :3, :3].double(), d.points[0].double())[..., 2]
    z = z + d.cameras.viewmats[:, None, 2, 3].double()
    assert d.near == pytest.approx(float(z[z > 0].quantile(0.001)), rel=0.05)
    rec = json.loads(json.dumps(data_json(d)))
    assert rec["points_source"] == "triangulated" and rec["points_count"] == len(d.points[0])
    assert rec["points_reprojection_error_px"] == d.points_stats["median_reprojection_error_px"] < 0.5
    assert rec["points_stats"]["pairs"] > 0 and rec["load_options"]["init"] == "auto"


def test_random_and_capture_init_keep_the_old_behaviour(capture):
    for init in ("random", "capture"):
        d = load_dataset(capture, num_random_points=300, init=init)
        assert d.points_source == "random" and len(d.points[0]) == 300 and d.points_stats == {}
        rec = data_json(d)
        assert rec["points_count"] == 300 and rec["points_reprojection_error_px"] is None


def test_ply_init(capture, tmp_path):
    from plyfile import PlyData, PlyElement

    pts = np.zeros(4, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    pts["x"], pts["y"], pts["z"] = [0, 1, 2, 3], [1, 1, 1, 1], [0.5, 0, 0, 0]
    pts["red"], pts["green"], pts["blue"] = [255, 0, 0, 51], [0, 255, 0, 51], [0, 0, 255, 51]
    path = tmp_path / "init.ply"
    PlyData([PlyElement.describe(pts, "vertex")]).write(str(path))
    d = load_dataset(capture, init=str(path))
    assert d.points_source == "ply" and d.points_stats["count"] == 4
    assert torch.equal(d.points[0], torch.tensor([[0, 1, 0.5], [1, 1, 0], [2, 1, 0], [3, 1, 0]]))
    assert torch.allclose(d.points[1][3], torch.full((3,), 0.2)) and torch.equal(d.points[1][0], torch.tensor([1.0, 0, 0]))
    assert data_json(d)["points_source"] == "ply" and data_json(d)["points_count"] == 4
    # a Gaussian scene PLY (f_dc colours) works too; a PLY without positions does not
    g = np.zeros(2, dtype=[(n, "f4") for n in ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2")])
    PlyData([PlyElement.describe(g, "vertex")]).write(str(tmp_path / "g.ply"))
    assert torch.allclose(load_dataset(capture, init=tmp_path / "g.ply").points[1], torch.full((2, 3), 0.5))
    bad = np.zeros(2, dtype=[("a", "f4")])
    PlyData([PlyElement.describe(bad, "vertex")]).write(str(tmp_path / "bad.ply"))
    with pytest.raises(InputError, match="no x/y/z"):
        load_dataset(capture, init=tmp_path / "bad.ply")


def test_bad_init_values():
    for bad, msg in (("bogus", "unknown initial points 'bogus'"), ("missing.ply", "not found")):
        with pytest.raises(InputError, match=msg):
            check_init(bad)
    assert check_init("triangulate") == "triangulate"


def test_too_few_points_fall_back_to_random_in_one_line(tmp_path, scene, caplog):
    cams, imgs = scene
    write_transforms_dataset(tmp_path, torch.full_like(imgs, 0.4), cams)   # nothing to match
    with caplog.at_level(logging.WARNING, logger="ssgwarp.capture.datasets"):
        d = load_dataset(tmp_path, num_random_points=200, progress=False)
    assert d.points_source == "random" and len(d.points[0]) == 200
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(msgs) == 1 and "\n" not in msgs[0]
    assert msgs[0].startswith("triangulation kept 0 points (fewer than 100") and "200 random points" in msgs[0]
    assert d.points_stats["fallback"].startswith("triangulation kept 0 points")


def test_cli_init_option(capture, tmp_path, capsys):
    from ssgwarp.cli import main

    rc = main(["reconstruct", str(capture), "--out", str(tmp_path / "run"), "--init", "nonsense", "--iters", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "unknown initial points 'nonsense'" in err[0]
    assert not (tmp_path / "run").exists()


def test_reconstruct_records_the_initial_points(capture, tmp_path):
    from plyfile import PlyData, PlyElement

    from ssgwarp.cli import main

    base = ["--iters", "2", "--sh-degree", "0", "--no-progress", "--device", "cpu", "--checkpoint-every", "100"]
    pts = np.zeros(300, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    pts["z"] = np.linspace(0.0, 1.0, 300)
    PlyData([PlyElement.describe(pts, "vertex")]).write(str(tmp_path / "p.ply"))
    assert main(["reconstruct", str(capture), "--out", str(tmp_path / "ply"), "--init", str(tmp_path / "p.ply")]
                + base) == 0
    meta = json.loads((tmp_path / "ply" / "data.json").read_text())
    assert meta["points_source"] == "ply" and meta["points_count"] == 300 and meta["points_reprojection_error_px"] is None
    assert meta["load_options"]["init"] == str(tmp_path / "p.ply")


def test_refinement_and_the_angle_filter_on_known_truth():
    """Poses held fixed, noisy observations of known points: Gauss-Newton lowers the error of the linear
    solution, and the triangulation-angle filter keeps the well-conditioned points (their error is smaller)."""
    g = torch.Generator().manual_seed(0)
    C, T_, W = 6, 400, 256
    eyes = torch.stack([torch.linspace(-0.5, 0.5, C, dtype=torch.float64), torch.zeros(C, dtype=torch.float64),
                        torch.zeros(C, dtype=torch.float64)], 1)
    vm = look_at(eyes, eyes + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), up=(0.0, -1.0, 0.0))
    K = intrinsics(200.0, 200.0, W / 2, W / 2, C).double()
    Pn = vm[:, :3, :].double()
    P = K @ Pn
    # points from 2 to 60 units away (uniform in inverse depth), inside every view
    inv = 1 / 60 + (1 / 2 - 1 / 60) * torch.rand(T_, generator=g, dtype=torch.float64)
    z = 1 / inv
    X = torch.stack([(torch.rand(T_, generator=g, dtype=torch.float64) - 0.5) * 0.4 * z,
                     (torch.rand(T_, generator=g, dtype=torch.float64) - 0.5) * 0.4 * z, z], 1)
    cam = torch.arange(C)[None].expand(T_, C)
    x = (P[cam][..., :3] @ X[:, None, :, None])[..., 0] + P[cam][..., 3]
    uv = x[..., :2] / x[..., 2:] + 0.7 * torch.randn(T_, C, 2, generator=g, dtype=torch.float64)
    mask = torch.ones(T_, C, dtype=torch.bool)
    xn = (torch.linalg.inv(K)[cam] @ torch.cat([uv, torch.ones_like(uv[..., :1])], -1)[..., None])[..., :2, 0]
    lin, ok = tri_mod._dlt(Pn[cam], xn, mask)
    ref = tri_mod._gauss_newton(P[cam], lin, uv, mask, 5)
    rms = lambda Y: tri_mod._reproject(P[cam], Y, uv)[0].pow(2).mean(1).sqrt()
    assert bool(ok.all()) and float(rms(ref).mean()) < float(rms(lin).mean())
    rel = lambda Y: (Y - X).norm(dim=1) / X.norm(dim=1)
    assert float(rel(ref).median()) <= float(rel(lin).median())
    imgs = torch.rand(C, W, W, 3, generator=g)
    centres = eyes
    kept = {}
    for angle in (1.0, 2.0, 4.0):
        Xk, _, _, _, _ = tri_mod._keep_points(P, centres, imgs, cam, uv, mask, ref, ok, 3.0, angle)
        idx = torch.cdist(Xk, ref).argmin(1)
        kept[angle] = (len(Xk), float(rel(ref)[idx].median()))
    # the 1 m baseline subtends 2 degrees at about 29 units, 4 degrees at about 14
    assert kept[1.0][0] > kept[2.0][0] > kept[4.0][0] > 0
    assert kept[1.0][1] > kept[2.0][1] > kept[4.0][1]
    assert triangulate.__kwdefaults__["min_angle_deg"] == 1.0   # (2 is closer to COLMAP but costs bird 1.4 dB)
