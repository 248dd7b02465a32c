"""Loaders: COLMAP (text, written here; binary, shared data), LLFF and transforms.json.

Checks the camera conventions against hand-built poses, intrinsics scaling to the
loaded resolution, RGBA compositing (lens undistortion: test_lens.py), the every-8th split, errors that name what is missing, and -- on the shared real
captures -- that the sparse points land on pixels of their own colour."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from ssgwarp.formats.colmap import ColmapCamera, ColmapImage, ColmapPoints, rotmat_to_qvec, write_model_text
from ssgwarp.capture.datasets import SceneData, detect_layout, load_dataset
from ssgwarp.errors import InputError
from ssgwarp.core.fileio import write_image

from conftest import SHARED_DATA as DATA
needs = lambda name: pytest.mark.skipif(not (DATA / name).is_dir(), reason="shared data not present")  # noqa: E731


def _look(eye, target, up=(0.0, 1.0, 0.0)):
    """OpenCV world-to-camera [4,4] (float64 numpy)."""
    from ssgwarp.core.cameras import look_at

    return look_at(torch.tensor([eye], dtype=torch.float64), torch.tensor([target], dtype=torch.float64), up)[0].numpy()


# ----------------------------------------------------------------------------- COLMAP text
def _colmap_scene(root: Path, n=9, w=32, h=24, full=(64, 48), folder="images", ext=".png", model="PINHOLE"):
    rng = np.random.default_rng(0)
    cams = {1: ColmapCamera(1, model, full[0], full[1],
                            np.array({"PINHOLE": [60.0, 62.0, 32.0, 24.0],
                                      "SIMPLE_PINHOLE": [60.0, 32.0, 24.0]}[model]))}
    images, views = {}, []
    for i in range(n):
        a = 2 * np.pi * i / n
        V = _look([3 * np.cos(a), 0.5, 3 * np.sin(a)], [0, 0, 0])
        views.append(V)
        images[i + 1] = ColmapImage(i + 1, rotmat_to_qvec(V[:3, :3]), V[:3, 3], 1, f"view_{(n - i):02d}.jpg")
        write_image(root / folder / f"view_{(n - i):02d}{ext}", rng.uniform(0, 1, (h, w, 3)).astype(np.float32))
    pts = ColmapPoints(np.arange(5), rng.normal(size=(5, 3)) * 0.3, rng.integers(0, 255, (5, 3)).astype(np.uint8),
                       np.zeros(5), np.zeros(5, np.int64))
    write_model_text(root / "sparse" / "0", cams, images, pts)
    return cams, images, views, pts


def test_colmap_text_capture(tmp_path):
    cams, images, views, pts = _colmap_scene(tmp_path)
    assert detect_layout(tmp_path) == "colmap"
    d = load_dataset(tmp_path, split_every=4)
    assert isinstance(d, SceneData) and d.format == "colmap" and not d.undistorted
    # sorted by name; files found under another extension (.png for a .jpg name)
    assert d.names == sorted(f"view_{i:02d}.png" for i in range(1, 10))
    assert d.images.shape == (9, 24, 32, 3) and d.images.dtype == torch.float32
    assert d.test_ids == [0, 4, 8] and d.train_ids == [1, 2, 3, 5, 6, 7]
    # intrinsics scaled from the 64x48 model to the 32x24 images
    assert torch.allclose(d.cameras.Ks[0], torch.tensor([[30.0, 0, 16.0], [0, 31.0, 12.0], [0, 0, 1]]))
    by_name = {im.name.replace(".jpg", ".png"): i for i, im in enumerate(images.values())}
    for j, name in enumerate(d.names):
        assert np.allclose(d.cameras.viewmats[j].double().numpy(), views[by_name[name]], atol=1e-6)
    assert d.points_source == "colmap"
    assert torch.allclose(d.points[0], torch.from_numpy(pts.xyz).float())
    assert torch.allclose(d.points[1] * 255, torch.from_numpy(pts.rgb).float())
    assert 2.0 < d.near < d.far < 4.5  # depth range of the points from the cameras
    # max_images keeps an evenly spaced subset, resize keeps the aspect ratio
    d2 = load_dataset(tmp_path, max_images=3, width=16)
    assert d2.names == [d.names[0], d.names[4], d.names[8]] and (d2.width, d2.height) == (16, 12)
    assert torch.allclose(d2.cameras.Ks[0, 0, 0], torch.tensor(15.0))


def test_colmap_images_n_folder_and_missing_images(tmp_path):
    _colmap_scene(tmp_path, folder="images_2", w=32, h=24, full=(64, 48))
    with pytest.raises(InputError, match=r"image folder not found; available: images_2 \(pass --images images_2\)"):
        load_dataset(tmp_path)
    d = load_dataset(tmp_path, images="images_2")
    assert d.width == 32 and d.image_dir == "images_2"
    (tmp_path / "images_2" / "view_03.png").unlink()
    (tmp_path / "images_2" / "view_07.png").unlink()
    with pytest.raises(InputError, match=r"2 image\(s\) referenced by .* are missing .*view_03\.jpg, view_07\.jpg"):
        load_dataset(tmp_path, images="images_2")


# ----------------------------------------------------------------------------- LLFF
def _llff_scene(root: Path, n=6, w=40, h=30, full=(400, 300), focal=350.0, points=False):
    rng = np.random.default_rng(1)
    rows, views = [], []
    for i in range(n):
        V = _look([0.3 * i - 0.75, 0.1 * i, -4.0], [0, 0, 0])
        views.append(V)
        c2w = np.linalg.inv(V)
        x, y, z, t = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3]
        pose = np.stack([y, x, -z, t, [full[1], full[0], focal]], axis=1)  # [down, right, back, t, hwf]
        rows.append(np.concatenate([pose.ravel(), [2.0, 6.0]]))
        write_image(root / "images_10" / f"IMG_{i:03d}.png", rng.uniform(0, 1, (h, w, 3)).astype(np.float32))
    np.save(root / "poses_bounds.npy", np.array(rows))
    return views


def test_llff_capture(tmp_path):
    views = _llff_scene(tmp_path)
    assert detect_layout(tmp_path) == "llff"
    d = load_dataset(tmp_path, images="images_10", num_random_points=500, init="random")
    assert d.format == "llff" and len(d) == 6 and (d.width, d.height) == (40, 30)
    for j in range(6):
        assert np.allclose(d.cameras.viewmats[j].double().numpy(), views[j], atol=1e-5)
    # focal given at 400 px wide, images loaded 40 px wide
    assert torch.allclose(d.cameras.Ks[0], torch.tensor([[35.0, 0, 20.0], [0, 35.0, 15.0], [0, 0, 1]]))
    assert (d.near, d.far) == (2.0, 6.0)
    assert d.test_ids == [0] and d.train_ids == [1, 2, 3, 4, 5]
    # no sparse model: random points inside the views' near/far bounds, coloured from the images
    assert d.points_source == "random"
    xyz, rgb = d.points
    assert xyz.shape == (500, 3) and rgb.shape == (500, 3)
    pc = torch.einsum("cij,pj->cpi", d.cameras.viewmats[:, :3, :3], xyz) + d.cameras.viewmats[:, None, :3, 3]
    uv = pc[..., :2] / pc[..., 2:] * 35.0 + torch.tensor([20.0, 15.0])
    inside = ((pc[..., 2] >= 2.0 - 1e-4) & (pc[..., 2] <= 6.0 + 1e-4) & (uv[..., 0] >= 0) & (uv[..., 0] <= 40)
              & (uv[..., 1] >= 0) & (uv[..., 1] <= 30))
    assert bool(inside.any(dim=0).all())
    # seeded: the same points every time
    assert torch.equal(load_dataset(tmp_path, images="images_10", num_random_points=500, init="random").points[0], xyz)


def test_llff_errors(tmp_path):
    _llff_scene(tmp_path)
    np.save(tmp_path / "poses_bounds.npy", np.zeros((6, 15)))
    with pytest.raises(InputError, match=r"poses of the wrong shape \(6, 15\)"):
        load_dataset(tmp_path, images="images_10")
    _llff_scene(tmp_path)
    (tmp_path / "images_10" / "IMG_002.png").unlink()
    with pytest.raises(InputError, match="has 6 poses but .*images_10 has 5 images"):
        load_dataset(tmp_path, images="images_10")
    (tmp_path / "poses_bounds.npy").write_bytes(b"garbage")
    with pytest.raises(InputError, match="poses_bounds.npy: cannot read"):
        load_dataset(tmp_path, images="images_10")


# ----------------------------------------------------------------------------- transforms.json
def _transforms_scene(root: Path, n=4, w=12, h=8, rgba=True, name="transforms.json", intr=None):
    frames = []
    rng = np.random.default_rng(2)
    colors = []
    for i in range(n):
        a = 2 * np.pi * i / n
        V = _look([4 * np.cos(a), 4 * np.sin(a), 1.0], [0, 0, 0], up=(0, 0, 1))
        c2w_gl = np.linalg.inv(V) @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w_gl.tolist()})
        c = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
        a_ = np.ones((h, w, 1), np.float32)
        a_[0, 0] = 0.0
        a_[1, 1] = 0.5
        colors.append((c, a_))
        img = np.concatenate([c * a_, a_], axis=2) if rgba else c
        write_image(root / "train" / f"r_{i}.png", img)
    meta = {"camera_angle_x": 2 * np.arctan(0.5 * w / 10.0), "frames": frames}
    if intr:
        meta = {**intr, "frames": frames}
    (root / name).write_text(json.dumps(meta))
    return colors


def test_transforms_capture_and_rgba_compositing(tmp_path):
    colors = _transforms_scene(tmp_path)
    assert detect_layout(tmp_path) == "transforms"
    d = load_dataset(tmp_path, background=(0.0, 1.0, 0.0), num_random_points=100, init="random")
    assert d.names == [f"train/r_{i}.png" for i in range(4)]
    assert torch.allclose(d.cameras.Ks[0], torch.tensor([[10.0, 0, 6.0], [0, 10.0, 4.0], [0, 0, 1]]), atol=1e-5)
    # OpenGL c2w -> OpenCV w2c: every camera sees the origin straight ahead at depth ~4.12
    o = d.cameras.viewmats[:, :3, 3]
    assert torch.allclose(o[:, :2], torch.zeros(4, 2), atol=1e-5)
    assert torch.allclose(o[:, 2], torch.full((4,), float(np.sqrt(17.0))), atol=1e-4)
    # world up (+z) points up in the image (camera -y)
    up_cam = d.cameras.viewmats[:, :3, :3] @ torch.tensor([0.0, 0.0, 1.0])
    assert bool((up_cam[:, 1] < 0).all())
    c, a = colors[0]
    img = d.images[0].numpy()
    assert np.allclose(img[0, 0], [0, 1, 0], atol=1e-6)  # transparent -> background
    assert np.allclose(img[1, 1], c[1, 1] * 0.5 + 0.5 * np.array([0, 1, 0]), atol=0.01)
    assert np.allclose(img[3, 3], c[3, 3], atol=0.003)
    # no point cloud: random points around the point the cameras look at
    assert d.points_source == "random" and d.points[0].abs().max() <= np.sqrt(17.0) / 3 + 1e-4
    assert d.options["background"] == [0.0, 1.0, 0.0]


def test_transforms_explicit_intrinsics_test_split_and_errors(tmp_path):
    _transforms_scene(tmp_path, name="transforms_train.json", rgba=False,
                      intr={"fl_x": 20.0, "fl_y": 22.0, "cx": 5.5, "cy": 4.5, "w": 24, "h": 16})
    d = load_dataset(tmp_path, num_random_points=10)
    # the JSON's intrinsics are for 24x16, the images are 12x8
    assert torch.allclose(d.cameras.Ks[0], torch.tensor([[10.0, 0, 2.75], [0, 11.0, 2.25], [0, 0, 1]]))
    assert d.test_ids == [0]
    (tmp_path / "test").mkdir()
    for i in range(2):
        write_image(tmp_path / "test" / f"t_{i}.png", np.zeros((8, 12, 3), np.float32))
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    meta["frames"] = [{**f, "file_path": f"test/t_{i}.png"} for i, f in enumerate(meta["frames"][:2])]
    (tmp_path / "transforms_test.json").write_text(json.dumps(meta))
    d = load_dataset(tmp_path, num_random_points=10)
    assert len(d) == 6 and [d.names[i] for i in d.test_ids] == ["test/t_0.png", "test/t_1.png"]
    (tmp_path / "train" / "r_2.png").unlink()
    with pytest.raises(InputError, match=r"1 image\(s\) referenced by transforms_test.json, transforms_train.json "
                                         r"are missing .*train/r_2"):
        load_dataset(tmp_path)
    (tmp_path / "transforms_train.json").write_text('{"frames": [{"file_path": "x"}]}')
    with pytest.raises(InputError, match="frame 0 needs 'file_path' and 'transform_matrix'"):
        load_dataset(tmp_path)
    (tmp_path / "transforms_train.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_dataset(tmp_path)


def test_missing_or_unknown_folders(tmp_path):
    with pytest.raises(InputError, match="data folder not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(InputError, match="no capture found"):
        load_dataset(tmp_path)


# ----------------------------------------------------------------------------- real captures
def _color_agreement(d: SceneData, views) -> tuple[float, float]:
    """Median |pixel - point colour| at the points' projections, and the same with the points shuffled."""
    xyz, rgb = d.points
    g = torch.Generator().manual_seed(0)
    errs, base = [], []
    for i in views:
        V, K = d.cameras.viewmats[i], d.cameras.Ks[i]
        pc = xyz @ V[:3, :3].T + V[:3, 3]
        uv = pc[:, :2] / pc[:, 2:3] @ K[:2, :2].T + K[:2, 2]
        m = (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < d.width) & (uv[:, 1] >= 0) & (uv[:, 1] < d.height)
        pix = d.images[i, uv[m, 1].long(), uv[m, 0].long()]
        errs.append((pix - rgb[m]).abs().mean(1).median())
        base.append((pix[torch.randperm(int(m.sum()), generator=g)] - rgb[m]).abs().mean(1).median())
    return float(torch.stack(errs).mean()), float(torch.stack(base).mean())


@needs("llff_fern")
def test_llff_fern():
    d = load_dataset(DATA / "llff_fern", images="images_8", width=252)
    # sparse/0/cameras.bin is SIMPLE_RADIAL with the poses' focal: the 504x378 images become a 498x372
    # pinhole crop (focal kept), then resized to 252 wide
    assert d.format == "llff" and len(d) == 20 and (d.width, d.height) == (252, 188)
    assert d.test_ids == [0, 8, 16] and len(d.train_ids) == 17
    assert d.undistorted and d.undistortion["size"] == [498, 372] and d.undistortion["resized_to"] == [252, 188]
    assert abs(float(d.cameras.Ks[0, 0, 0]) - 3260.526 * 504 / 4032 * 252 / 498) < 1e-2
    assert d.points_source == "colmap" and len(d.points[0]) == 10091
    err, base = _color_agreement(d, range(0, 20, 4))
    assert err < 0.6 * base, (err, base)


@needs("colmap_cup")
def test_colmap_cup_points_match_image_colours():
    d = load_dataset(DATA / "colmap_cup", max_images=8, width=200)
    assert d.format == "colmap" and len(d) == 8 and (d.width, d.height) == (200, 150)
    assert not d.undistorted and d.points_source == "colmap"
    err, base = _color_agreement(d, range(8))
    assert err < 0.75 * base, (err, base)
    assert 0 < d.near < d.far


@needs("lego_200")
def test_lego_transforms():
    d = load_dataset(DATA / "lego_200", num_random_points=1000, max_images=25, init="capture")
    assert d.format == "transforms" and len(d) == 25 and (d.width, d.height) == (200, 200)
    assert abs(float(d.cameras.Ks[0, 0, 0]) - 100.0 / np.tan(0.5 * 0.6911112070083618)) < 1e-3
    # cameras on a sphere of radius ~4 looking at the origin
    c, f = d.cameras.centers, d.cameras.forwards
    assert torch.allclose(c.norm(dim=1), torch.full((25,), 4.03), atol=0.05)
    assert bool(((f * -torch.nn.functional.normalize(c, dim=1)).sum(1) > 0.95).all())
    # white background around the object
    assert torch.allclose(d.images[:, 0, 0], torch.ones(25, 3))
    assert d.images.mean() > 0.6


# ----------------------------------------------------------------------------- helpers, unit by unit
def test_evenly_spaced_subsets_and_the_split():
    from ssgwarp.capture.loaders import _evenly
    from ssgwarp.capture.datasets import _split

    assert _evenly(10, None) == list(range(10)) and _evenly(10, 10) == list(range(10)) and _evenly(3, 7) == [0, 1, 2]
    assert _evenly(10, 4) == [0, 3, 6, 9] and _evenly(10, 1) == [0] and _evenly(9, 3) == [0, 4, 8]
    for k in (0, -2):
        with pytest.raises(InputError, match=f"max_images must be positive, got {k}"):
            _evenly(10, k)
    assert _split(10, 4) == ([1, 2, 3, 5, 6, 7, 9], [0, 4, 8])
    assert _split(5, 0) == ([0, 1, 2, 3, 4], []) and _split(5, -1) == ([0, 1, 2, 3, 4], [])
    assert _split(4, 8, [False, True, False, True]) == ([0, 2], [1, 3])  # the dataset's own split wins
    assert _split(1, 8) == ([0], [])  # a single image: trained on, nothing held out
    assert _split(2, 1) == ([0, 1], [])  # every image held out would leave nothing to train on


def test_resize_images_by_hand():
    from ssgwarp.capture.loaders import resize_images

    # shrinking 4 -> 2 is antialiased (PIL-style triangle filter twice as wide): output 0 sits between inputs
    # 0 and 1 (weights 3/4 each) and reaches input 2 (1/4; input -1 is outside): (0 + 0 + 1/4) / (7/4) = 1/7
    row = torch.tensor([0.0, 0.0, 1.0, 1.0]).view(1, 1, 4, 1).expand(1, 2, 4, 3).contiguous()
    got = resize_images(row, 1, 2)
    assert got.shape == (1, 1, 2, 3) and torch.allclose(got[0, 0, :, 0], torch.tensor([1 / 7, 6 / 7]), atol=1e-6)
    # enlarging 2 -> 4 is plain bilinear with pixel centres at +0.5: samples at -0.25, 0.25, 0.75, 1.25 (clamped)
    two = torch.tensor([0.0, 1.0]).view(1, 1, 2, 1).expand(1, 1, 2, 3).contiguous()
    big = resize_images(two, 2, 4)
    assert torch.allclose(big[0, :, :, 1], torch.tensor([0.0, 0.25, 0.75, 1.0]).expand(2, 4), atol=1e-6)
    assert big.is_contiguous() and resize_images(row, 2, 4).equal(row)  # same size: unchanged
    # one side kept, the other shrunk: antialiased along the shrunk side (either side)
    assert torch.allclose(resize_images(row, 2, 2)[0, :, :, 0], torch.tensor([1 / 7, 6 / 7]).expand(2, 2), atol=1e-6)
    col = row[:, :1].transpose(1, 2).expand(1, 4, 4, 3).contiguous()   # [0, 0, 1, 1] down each column, 4 wide
    assert torch.allclose(resize_images(col, 2, 4)[0, :, 1, 2], torch.tensor([1 / 7, 6 / 7]), atol=1e-6)
    # one side grown, the other shrunk: plain bilinear (4 -> 2 samples at 0.5 and 2.5: [0, 1])
    mixed = resize_images(row, 3, 2)
    assert mixed.shape == (1, 3, 2, 3) and torch.allclose(mixed[0, :, :, 0], torch.tensor([0.0, 1.0]).expand(3, 2))


def test_viewmats_from_c2w_and_the_focus_point():
    from ssgwarp.core.cameras import Cameras, intrinsics
    from ssgwarp.capture.loaders import _viewmats_from_c2w, focus_point

    eyes = [[3.0, 0.0, 0.5], [0.0, 2.0, -1.0], [-1.0, -2.0, 2.0]]
    V = np.stack([_look(e, [0.2, -0.1, 0.3]) for e in eyes])
    back = _viewmats_from_c2w(np.linalg.inv(V)[:, :3, :4])
    assert back.dtype == torch.float64 and torch.allclose(back, torch.from_numpy(V), atol=1e-12)
    bad = np.linalg.inv(V)[:, :3, :4].copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(InputError, match="^camera poses contain NaN/inf values$"):
        _viewmats_from_c2w(bad)
    cams = Cameras(torch.from_numpy(V).float(), intrinsics(10.0, 10.0, 5.0, 5.0, 3), 10, 10)
    assert torch.allclose(focus_point(cams), torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64), atol=1e-5)
    # parallel optical axes meet nowhere: the centres' mean
    Vp = np.stack([np.eye(4)] * 3)
    Vp[:, :3, 3] = -np.array(eyes)
    par = Cameras(torch.from_numpy(Vp).float(), intrinsics(10.0, 10.0, 5.0, 5.0, 3), 10, 10)
    assert torch.allclose(focus_point(par), torch.tensor(eyes, dtype=torch.float64).mean(0), atol=1e-6)


def test_depth_range_percentiles_of_points_in_front():
    from ssgwarp.capture.loaders import _depth_range

    V = np.eye(4)[None]
    z = np.arange(1.0, 1001.0)
    xyz = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    behind = np.array([[0.0, 0.0, -5.0], [0.0, 0.0, -2000.0], [1.0, 0.0, 0.0]])  # the last in the camera's plane
    # numpy's linear percentiles of 1..1000: 0.1% -> 1 + 0.001 * 999, 99.9% -> 1 + 0.999 * 999
    near, far = _depth_range(np.concatenate([xyz, behind]), V)
    assert near == pytest.approx(1.999) and far == pytest.approx(999.001)
    V2 = np.eye(4)[None].copy()
    V2[0, 2, 3] = 10.0  # the camera 10 units behind the origin along its axis: depths grow by 10
    assert _depth_range(xyz, V2) == (pytest.approx(11.999), pytest.approx(1009.001))
    assert _depth_range(behind, V) == (None, None) and _depth_range(np.zeros((0, 3)), V) == (None, None)
    assert _depth_range(None, V) == (None, None)
    assert _depth_range(np.array([[0.1, 0.0, 3.0]]), V) == (pytest.approx(3.0), pytest.approx(3.0))  # one point
    # more than 20000 points: a seeded sample of them, still close
    many = np.stack([np.zeros(30000), np.zeros(30000), np.linspace(1.0, 2.0, 30000)], axis=1)
    n, f = _depth_range(many, V)
    assert 1.0 < n < 1.01 and 1.99 < f < 2.0 and (n, f) == _depth_range(many, V)


def test_random_points_lie_in_their_pixels_frustum_with_the_pixels_colour():
    """Each camera's image encodes (camera, column, row) in its colour, so a point's colour says which pixel
    it was drawn from: the point must project into that pixel at a depth within that view's near/far."""
    from ssgwarp.core.cameras import Cameras, intrinsics
    from ssgwarp.capture.loaders import random_points_in_frusta

    W, H = 8, 6
    V = np.stack([_look([0.5 * i, 0.2, -3.0], [0.0, 0.0, 0.0]) for i in range(3)])
    K = intrinsics(9.0, 10.0, 4.2, 2.9, 3)
    cams = Cameras(torch.from_numpy(V).float(), K, W, H)
    u, v = torch.meshgrid(torch.arange(W), torch.arange(H), indexing="xy")
    imgs = torch.stack([torch.stack([torch.full((H, W), c / 4), (u + 0.5) / W, (v + 0.5) / H], -1) for c in range(3)])
    near, far = np.array([1.0, 2.0, 1.5]), np.array([4.0, 3.0, 6.0])
    xyz, rgb = random_points_in_frusta(cams, imgs, near, far, 400, seed=5)
    assert xyz.shape == rgb.shape == (400, 3) and xyz.dtype == rgb.dtype == torch.float32
    cam = (rgb[:, 0] * 4).round().long()
    col, row = (rgb[:, 1] * W - 0.5).round().long(), (rgb[:, 2] * H - 0.5).round().long()
    assert set(cam.tolist()) == {0, 1, 2}
    Vt, Kt = cams.viewmats.double()[cam], K.double()[cam]
    pc = (Vt[:, :3, :3] @ xyz.double()[:, :, None])[..., 0] + Vt[:, :3, 3]
    pu = pc[:, 0] / pc[:, 2] * Kt[:, 0, 0] + Kt[:, 0, 2]
    pv = pc[:, 1] / pc[:, 2] * Kt[:, 1, 1] + Kt[:, 1, 2]
    assert bool(((pu >= col - 1e-3) & (pu <= col + 1 + 1e-3) & (pv >= row - 1e-3) & (pv <= row + 1 + 1e-3)).all())
    lo, hi = torch.from_numpy(near)[cam], torch.from_numpy(far)[cam]
    assert bool(((pc[:, 2] >= lo - 1e-4) & (pc[:, 2] <= hi + 1e-4)).all())
    # uniform in disparity: the median disparity is the mean of the bounds' disparities (to sampling noise)
    s = (1 / pc[:, 2] - 1 / hi) / (1 / lo - 1 / hi)
    assert abs(float(s.median()) - 0.5) < 0.1 and float(s.min()) < 0.1 and float(s.max()) > 0.9
    assert torch.equal(random_points_in_frusta(cams, imgs, near, far, 400, seed=5)[0], xyz)


def test_transforms_intrinsics_variants_and_errors():
    from ssgwarp.capture.loaders import _intrinsics_from

    assert _intrinsics_from({"fl_x": 20.0}, 40, 30, "w") == (20.0, 20.0, 20.0, 15.0)
    assert _intrinsics_from({"fl_y": 22.0, "cx": 3.0, "cy": 4.0}, 40, 30, "w") == (22.0, 22.0, 3.0, 4.0)
    fx, fy, cx, cy = _intrinsics_from({"camera_angle_x": 2 * np.arctan(0.5), "camera_angle_y": 2 * np.arctan(0.25)},
                                      40, 30, "w")
    assert (fx, fy, cx, cy) == (pytest.approx(40.0), pytest.approx(60.0), 20.0, 15.0)
    assert _intrinsics_from({"camera_angle_x": 2 * np.arctan(0.5)}, 40, 30, "w")[1] == pytest.approx(40.0)
    with pytest.raises(InputError, match=r"^where: no intrinsics \(need camera_angle_x or fl_x/fl_y\)$"):
        _intrinsics_from({"camera_angle_y": 1.0}, 40, 30, "where")
    with pytest.raises(InputError, match="^where: intrinsics are not numbers$"):
        _intrinsics_from({"fl_x": "wide"}, 40, 30, "where")
    with pytest.raises(InputError, match="^where: intrinsics are not numbers$"):
        _intrinsics_from({"fl_x": 20.0, "cx": [1]}, 40, 30, "where")
    assert _intrinsics_from({"fl_x": 0.5, "fl_y": 0.25}, 40, 30, "w")[:2] == (0.5, 0.25)  # any positive focal
    for bad in ({"fl_x": 0.0}, {"fl_x": 0.0, "fl_y": 10.0}, {"fl_x": 10.0, "fl_y": 0.0}, {"fl_x": 10.0, "fl_y": -1.0},
                {"fl_x": float("inf")}, {"fl_x": 10.0, "cy": float("nan")}):
        with pytest.raises(InputError, match="^where: invalid intrinsics fx="):
            _intrinsics_from(bad, 40, 30, "where")


def test_transforms_lens_variants_and_errors():
    from ssgwarp.capture.loaders import _transforms_lens
    from ssgwarp.capture.lens import Lens

    assert _transforms_lens({}, "w") == Lens("OPENCV", (0.0, 0.0, 0.0, 0.0))
    assert _transforms_lens({"k1": 0.1, "p2": 0.02, "camera_model": "opencv"}, "w") == Lens("OPENCV", (0.1, 0, 0, 0.02))
    assert _transforms_lens({"k1": 0.1, "k3": 0.01, "p1": 0.03}, "w") == Lens("FULL_OPENCV", (0.1, 0, 0.03, 0, 0.01, 0, 0, 0))
    fish = Lens("OPENCV_FISHEYE", (0.1, 0.0, 0.0, 0.02))
    for flag in (True, 1, "true", " True ", "1"):
        assert _transforms_lens({"k1": 0.1, "k4": 0.02, "is_fisheye": flag}, "w") == fish, flag
    for flag in (False, 0, "false", "no", ""):
        assert _transforms_lens({"k1": 0.1, "is_fisheye": flag}, "w").model == "OPENCV", flag
    assert _transforms_lens({"k1": 0.1, "k4": 0.02, "camera_model": "OPENCV_FISHEYE"}, "w") == fish
    assert _transforms_lens({"camera_model": "PINHOLE"}, "w").is_pinhole
    with pytest.raises(InputError, match=r"^w: distortion coefficients are not numbers$"):
        _transforms_lens({"k2": "big"}, "w")
    assert _transforms_lens({"k1": 0.1, "camera_model": "SIMPLE_RADIAL"}, "w") == Lens("OPENCV", (0.1, 0, 0, 0))
    assert _transforms_lens({"k1": 0.1, "k2": 0.2, "camera_model": "RADIAL"}, "w") == Lens("OPENCV", (0.1, 0.2, 0, 0))
    with pytest.raises(InputError, match=r"^w: camera_model fisheye is not supported \(supported: OPENCV, "
                                         r"OPENCV_FISHEYE, PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL\)"):
        _transforms_lens({"camera_model": "fisheye"}, "w")
    with pytest.raises(InputError, match=r"w: a fisheye camera .* not p1 p2 \(got p1=0 p2=0.5\)"):
        _transforms_lens({"is_fisheye": True, "p2": 0.5}, "w")


def test_scene_data_validation_split_background_and_device():
    from ssgwarp.core.cameras import Cameras, intrinsics

    V = torch.from_numpy(np.stack([_look([0.0, 0.0, -3.0 - i], [0, 0, 0]) for i in range(3)])).float()
    cams = Cameras(V, intrinsics(10.0, 10.0, 4.0, 3.0, 3), 8, 6)
    imgs = torch.rand(3, 6, 8, 3, generator=torch.Generator().manual_seed(0))
    d = SceneData(cams, imgs, ["a", "b", "c"], [0, 2], [1], background=(0.1, 0.2, 0.3))
    assert d.split("train") == [0, 2] and d.split("test") == [1] and d.split("all") == [0, 1, 2] and len(d) == 3
    with pytest.raises(InputError, match=r"unknown split 'val' \(train, test or all\)"):
        d.split("val")
    assert torch.equal(d.background_tensor(), torch.tensor([0.1, 0.2, 0.3]))
    assert torch.equal(d.background_tensor(5), torch.tensor([0.1, 0.2, 0.3, 0.0, 0.0]))
    moved = d.to("cpu")
    assert moved.names == d.names and torch.equal(moved.images, imgs) and moved.points is None
    with_pts = SceneData(cams, imgs, ["a", "b", "c"], [0], [], points=(torch.zeros(2, 3), torch.ones(2, 3))).to("cpu")
    assert torch.equal(with_pts.points[1], torch.ones(2, 3)) and torch.equal(with_pts.points[0], torch.zeros(2, 3))
    with pytest.raises(InputError, match=r"SceneData: images \(3, 6, 7, 3\) do not match 3 cameras of 8x6"):
        SceneData(cams, imgs[:, :, :7], ["a", "b", "c"], [0], [])
    with pytest.raises(InputError, match="SceneData: 2 names for 3 cameras"):
        SceneData(cams, imgs, ["a", "b"], [0], [])


def test_loader_option_errors(tmp_path):
    _llff_scene(tmp_path)
    with pytest.raises(InputError, match="width must be positive, got 0"):
        load_dataset(tmp_path, images="images_10", width=0)
    with pytest.raises(InputError, match="split_every must be >= 0, got -1"):
        load_dataset(tmp_path, images="images_10", split_every=-1)
    with pytest.raises(InputError, match=r"background must be 3 numbers \(RGB\), got \(1.0, 1.0\)"):
        load_dataset(tmp_path, images="images_10", background=(1.0, 1.0))
    with pytest.raises(InputError, match="unknown data format 'ply' \\(colmap, llff or transforms\\)"):
        load_dataset(tmp_path, images="images_10", format="ply")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        load_dataset(tmp_path / "file")


# ----------------------------------------------------------------------------- nerfstudio (ns-process-data)
def _nerfstudio_from_colmap(root: Path, cams, images, pts, camera_model="OPENCV", masks=False):
    """The nerfstudio layout ns-process-data makes of the COLMAP capture in ``root``: OpenGL c2w with the world's
    y and z swapped and z negated (``applied_transform``), intrinsics per frame, points in ``sparse_pc.ply`` in the
    frames' world. Returns the applied transform (4x4)."""
    from plyfile import PlyData, PlyElement

    A = np.eye(4)
    A[:3] = np.eye(4)[:3][[0, 2, 1]]
    A[2] *= -1
    cam = cams[1]
    frames = []
    for im in sorted(images.values(), key=lambda im: im.name):  # (ns-process-data sorts by name too)
        V = np.eye(4)
        from ssgwarp.formats.colmap import qvec_to_rotmat
        V[:3, :3], V[:3, 3] = qvec_to_rotmat(im.qvec), im.tvec
        c2w = np.linalg.inv(V)
        c2w[0:3, 1:3] *= -1
        c2w = c2w[[0, 2, 1, 3]]
        c2w[2] *= -1
        fr = {"file_path": f"images/{Path(im.name).stem}.png", "transform_matrix": c2w.tolist(),
              "fl_x": float(cam.params[0]), "fl_y": float(cam.params[1]), "cx": float(cam.params[2]),
              "cy": float(cam.params[3]), "w": cam.width, "h": cam.height}
        if masks:
            fr["mask_path"] = f"masks/{Path(im.name).stem}.png"
        frames.append(fr)
    xyz = pts.xyz @ A[:3, :3].T + A[:3, 3]
    v = np.array([tuple(p) + tuple(c) for p, c in zip(xyz, pts.rgb)],
                 dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    PlyData([PlyElement.describe(v, "vertex")], text=True).write(str(root / "sparse_pc.ply"))
    meta = {"camera_model": camera_model, "frames": frames, "applied_transform": A[:3].tolist(),
            "ply_file_path": "sparse_pc.ply"}
    (root / "transforms.json").write_text(json.dumps(meta))
    return A


def test_nerfstudio_layout_loads_to_the_colmap_capture_it_came_from(tmp_path):
    """ns-process-data's transforms.json (per-frame intrinsics, applied_transform, sparse_pc.ply) gives the COLMAP
    capture's cameras and points, in the frames' world (the COLMAP world through applied_transform)."""
    cams, images, views, pts = _colmap_scene(tmp_path)
    ref = load_dataset(tmp_path, format="colmap", split_every=0)
    A = _nerfstudio_from_colmap(tmp_path, cams, images, pts)
    import shutil
    shutil.rmtree(tmp_path / "sparse")
    d = load_dataset(tmp_path, split_every=0)
    assert d.format == "transforms" and d.points_source == "ply" and d.applied_transform == A[:3].tolist()
    assert [Path(n).stem for n in d.names] == [Path(n).stem for n in ref.names]
    assert torch.allclose(d.cameras.Ks, ref.cameras.Ks, atol=1e-5)
    # the same cameras: world-to-camera of the frames' world = the COLMAP one after undoing applied_transform
    want = ref.cameras.viewmats.double() @ torch.from_numpy(np.linalg.inv(A))
    assert torch.allclose(d.cameras.viewmats.double(), want, atol=1e-5)
    assert torch.allclose(d.images, ref.images)
    # the same points, seen at the same pixels
    xyz = ref.points[0].double() @ torch.from_numpy(A[:3, :3]).T + torch.from_numpy(A[:3, 3])
    assert torch.allclose(d.points[0].double(), xyz, atol=1e-5)
    assert torch.allclose(d.points[1], ref.points[1], atol=1e-6)
    pc = torch.cat([d.points[0].double(), torch.ones(len(xyz), 1, dtype=torch.float64)], 1)
    pr = torch.cat([ref.points[0].double(), torch.ones(len(xyz), 1, dtype=torch.float64)], 1)
    assert torch.allclose(pc @ d.cameras.viewmats[0].double().T, pr @ ref.cameras.viewmats[0].double().T, atol=1e-5)
    from ssgwarp.services.runs import data_json
    assert data_json(d)["applied_transform"] == A[:3].tolist() and data_json(d)["points_source"] == "ply"


def test_nerfstudio_per_frame_intrinsics_and_distortion_override_the_top_level(tmp_path):
    cams, images, views, pts = _colmap_scene(tmp_path)
    _nerfstudio_from_colmap(tmp_path, cams, images, pts, camera_model="SIMPLE_RADIAL")
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta.update({"fl_x": 999.0, "fl_y": 999.0, "cx": 1.0, "cy": 1.0, "w": 64, "h": 48, "k1": 0.3})
    meta["frames"][0]["k1"] = 0.0      # frame 0 is a pinhole, the others take the top level's k1
    meta["frames"][1]["fl_x"] = 70.0   # frame 1 has its own focal
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    import shutil
    shutil.rmtree(tmp_path / "sparse")
    d = load_dataset(tmp_path, split_every=0)
    lenses = {c["lens"]["model"] if c.get("lens") else None for c in d.undistortion["cameras"]}
    assert "OPENCV" in str(d.undistortion) and len(d.undistortion["cameras"]) >= 2, lenses
    # after the crop every camera keeps its focal (x 32/64 for the 32x24 images): 60 -> 30, frame 1's 70 -> 35
    assert abs(float(d.cameras.Ks[0, 0, 0]) - 30.0) < 1e-4 and abs(float(d.cameras.Ks[1, 0, 0]) - 35.0) < 1e-4
    assert abs(float(d.cameras.Ks[2, 1, 1]) - 31.0) < 1e-4


@pytest.mark.parametrize("model, msg", [
    ("EQUIRECTANGULAR", r"camera_model EQUIRECTANGULAR \(a panorama\) is not supported: .* perspective views first$"),
    ("FISHEYE624", r"camera_model FISHEYE624 is not supported \(supported: OPENCV, OPENCV_FISHEYE, PINHOLE, "
                   r"SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL\); convert the capture to pinhole images first$")])
def test_nerfstudio_unsupported_camera_models_are_one_line_errors(tmp_path, model, msg):
    cams, images, views, pts = _colmap_scene(tmp_path)
    _nerfstudio_from_colmap(tmp_path, cams, images, pts, camera_model=model)
    with pytest.raises(InputError, match=msg) as e:
        load_dataset(tmp_path, format="transforms")
    assert "\n" not in str(e.value)


def test_nerfstudio_bad_ply_applied_transform_and_partial_masks(tmp_path):
    cams, images, views, pts = _colmap_scene(tmp_path)
    _nerfstudio_from_colmap(tmp_path, cams, images, pts)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "nope.ply"}))
    with pytest.raises(InputError, match=r"nope.ply: PLY file not found$"):
        load_dataset(tmp_path, format="transforms")
    (tmp_path / "bad.ply").write_text("not a ply")
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "bad.ply"}))
    with pytest.raises(InputError, match=r"bad.ply: corrupt or truncated PLY"):
        load_dataset(tmp_path, format="transforms")
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "applied_transform": [[1, 0], [0, 1]]}))
    with pytest.raises(InputError, match=r"applied_transform must be a 3x4 matrix of numbers$"):
        load_dataset(tmp_path, format="transforms")
    meta["frames"][0]["mask_path"] = "masks/x.png"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"mask_path is given for 1 of 9 frames; give it for every frame or none$"):
        load_dataset(tmp_path, format="transforms")


def test_nerfstudio_masks_are_loaded_undistorted_and_resized_with_their_images(tmp_path):
    cams, images, views, pts = _colmap_scene(tmp_path)
    _nerfstudio_from_colmap(tmp_path, cams, images, pts, masks=True)
    for im in images.values():  # the right half of every image is masked out
        m = np.ones((24, 32, 1), np.float32)
        m[:, 16:] = 0.0
        write_image(tmp_path / "masks" / f"{Path(im.name).stem}.png", m)
    d = load_dataset(tmp_path, format="transforms", width=16)
    assert d.masks.shape == (9, 12, 16) and d.images.shape == (9, 12, 16, 3)
    assert bool((d.masks[:, :, :8] == 1).all()) and bool((d.masks[:, :, 8:] == 0).all())
    assert d.to("cpu").masks is not None
    from ssgwarp.services.runs import data_json
    assert data_json(d)["masks"] is True
    write_image(tmp_path / "masks" / f"{Path(images[1].name).stem}.png", np.ones((5, 5, 1), np.float32))
    with pytest.raises(InputError, match=r"mask size 5x5 differs from its image's \(32x24\)$"):
        load_dataset(tmp_path, format="transforms")


def test_no_image_loading_bar_without_progress(tmp_path, capsys, monkeypatch):
    """`load_dataset(progress=False)` (what `reconstruct --quiet` passes) shows no image-loading bar; with
    progress a capture of 16 or more images shows one (on a terminal: in a log, a sub-step writes nothing)."""
    import ssgwarp.core.progress as progress

    monkeypatch.setattr(progress, "on_terminal", lambda: True)
    from ssgwarp.procedural import ring_cameras, write_transforms_dataset

    cams = ring_cameras(16, 12, 9)
    g = torch.Generator().manual_seed(0)
    write_transforms_dataset(tmp_path / "cap", torch.rand(16, 9, 12, 3, generator=g), cams)
    capsys.readouterr()
    load_dataset(tmp_path / "cap", init="random", num_random_points=10, progress=False)
    assert "loading images" not in capsys.readouterr().err
    load_dataset(tmp_path / "cap", init="random", num_random_points=10, progress=True)
    assert "loading images" in capsys.readouterr().err
