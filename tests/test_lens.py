"""Lens undistortion into a pinhole crop in which every pixel has a source.

Each test builds a distorted capture on disk in its real format (COLMAP text/binary, transforms.json,
LLFF + sparse/0/cameras.bin): a smooth pattern P(x, y) is fixed on the *undistorted* normalised image
plane and every source pixel centre gets the value of P at its undistorted position (inverted here with
this file's own forward maps, written independently of ``ssgwarp.capture.lens``). Loading must give:

(a) pinhole intrinsics that keep the focal length, one size for all images, the record in
    ``SceneData.undistortion``;
(b) images equal to P seen through the returned pinhole camera, to interpolation accuracy: bilinear
    resampling of a function with |f''| <= ~25 (P's second derivatives, normalised units) at a source
    pixel pitch of 1/60 (1/f; up to ~2.5x that in a fisheye's corners) errs by at most
    h^2/8 * (|f_xx| + |f_yy|) ~ 0.002 (<= 0.012 in the fisheye's corners), plus 8-bit PNG quantisation
    (<= 0.002): we require max |error| <= 0.02 over *every* pixel and mean <= 0.004. P stays in
    [0.2, 0.8], so a zero-filled pixel errs by >= 0.2 and fails;
(c) no pixel without a source: every output pixel centre, pushed through the forward distortion,
    lands inside the source's pixel centres [0.5, W - 0.5] x [0.5, H - 0.5] (so bilinear sampling
    never reads padding or extrapolates), and the crop is tight (widening any side by one pixel
    would take in a pixel without a source);
(d) clear errors for a distortion too strong for a usable crop and for unsupported models;
(e) ``images_N`` levels with consistently scaled intrinsics.
"""
from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from ssgwarp.formats.colmap import MODEL_IDS, ColmapCamera, ColmapImage, ColmapPoints, rotmat_to_qvec, write_model_text
from ssgwarp.capture.datasets import load_dataset
from ssgwarp.services.runs import data_json, load_run
from ssgwarp.errors import InputError
from ssgwarp.core.fileio import write_image

from conftest import SHARED_DATA

DATA = SHARED_DATA if SHARED_DATA.is_dir() else Path("/work/shared/data")  # a worktree's checkout: the shared copy

W0, H0, F = 80, 60, 60.0
FISHEYES = ("OPENCV_FISHEYE", "RADIAL_FISHEYE", "SIMPLE_RADIAL_FISHEYE")
NAMES = {"SIMPLE_RADIAL": ("k1",), "RADIAL": ("k1", "k2"), "OPENCV": ("k1", "k2", "p1", "p2"),
         "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")}
# moderate distortions of every kind: pincushion, barrel, tangential, rational, fisheye
LENSES = {
    "SIMPLE_RADIAL": (0.08,),
    "RADIAL": (-0.12, 0.02),
    "OPENCV": (0.05, -0.01, 0.004, -0.003),
    "FULL_OPENCV": (0.1, 0.01, 0.002, 0.001, -0.005, 0.05, 0.0, 0.001),
    "OPENCV_FISHEYE": (0.05, 0.01, -0.002, 0.0005),
    "RADIAL_FISHEYE": (-0.03, 0.004),
    "SIMPLE_RADIAL_FISHEYE": (0.04,),
}
MAX_ERR, MEAN_ERR = 0.02, 0.004


# ----------------------------------------------------------------------------- independent lens maths
def _forward(model, p, x, y):
    """Distorted normalised coordinates (COLMAP / OpenCV formulas)."""
    if model in FISHEYES:
        k = list(p) + [0.0] * (4 - len(p))
        r = np.sqrt(x * x + y * y)
        th = np.arctan(r)
        thd = th * (1 + k[0] * th ** 2 + k[1] * th ** 4 + k[2] * th ** 6 + k[3] * th ** 8)
        s = np.divide(thd, r, out=np.ones_like(r), where=r > 0)
        return x * s, y * s
    c = dict(zip(NAMES[model], p))
    g = lambda n: c.get(n, 0.0)  # noqa: E731
    r2 = x * x + y * y
    radial = (1 + g("k1") * r2 + g("k2") * r2 ** 2 + g("k3") * r2 ** 3) / (1 + g("k4") * r2 + g("k5") * r2 ** 2
                                                                           + g("k6") * r2 ** 3)
    return (x * radial + 2 * g("p1") * x * y + g("p2") * (r2 + 2 * x * x),
            y * radial + g("p1") * (r2 + 2 * y * y) + 2 * g("p2") * x * y)


def _inverse(model, p, xd, yd):
    """Undistorted coordinates: 1-D Newton on theta for fisheyes, fixed-point iteration otherwise; the
    residual is checked so the captures are exact."""
    if model in FISHEYES:
        k = list(p) + [0.0] * (4 - len(p))
        rd = np.sqrt(xd * xd + yd * yd)
        th = rd.copy()
        for _ in range(50):
            t2 = th * th
            f = th * (1 + k[0] * t2 + k[1] * t2 ** 2 + k[2] * t2 ** 3 + k[3] * t2 ** 4) - rd
            df = 1 + 3 * k[0] * t2 + 5 * k[1] * t2 ** 2 + 7 * k[2] * t2 ** 3 + 9 * k[3] * t2 ** 4
            th = th - f / df
        s = np.divide(np.tan(th), rd, out=np.ones_like(rd), where=rd > 0)
        x, y = xd * s, yd * s
    else:
        x, y = xd.copy(), yd.copy()
        for _ in range(200):
            fx, fy = _forward(model, p, x, y)
            x, y = x + (xd - fx), y + (yd - fy)
    fx, fy = _forward(model, p, x, y)
    assert np.abs(fx - xd).max() < 1e-9 and np.abs(fy - yd).max() < 1e-9
    return x, y


def _pattern(x, y):
    return np.stack([0.5 + 0.2 * np.sin(6 * x + 1) * np.cos(5 * y) + 0.1 * np.cos(4 * x - 7 * y),
                     0.5 + 0.3 * np.cos(5 * x + 3 * y),
                     0.5 + 0.3 * np.sin(7 * y - 2 * x + 0.5)], axis=-1).astype(np.float32)


def _distorted_image(model, p, K, w, h):
    """What a camera ``K`` (w x h) with the lens ``(model, p)`` records of the pattern."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xd, yd = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    if model in ("PINHOLE", "SIMPLE_PINHOLE"):
        return _pattern(xd, yd)
    return _pattern(*_inverse(model, p, xd, yd))


def _check_image(img, K_out, model, p, K_src, w0, h0, check_tight=True):
    """(b) content against the pattern, (c) every pixel has a source and the crop is tight."""
    img = img.double().numpy()
    K_out = K_out.double().numpy()
    h, w = img.shape[:2]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x, y = (u - K_out[0, 2]) / K_out[0, 0], (v - K_out[1, 2]) / K_out[1, 1]
    err = np.abs(img - _pattern(x, y))
    assert err.max() <= MAX_ERR and err.mean() <= MEAN_ERR, (model, err.max(), err.mean())
    assert img.min() >= 0.2 - MAX_ERR  # no zero-filled pixel anywhere

    def source(uu, vv):
        xx, yy = (uu - K_out[0, 2]) / K_out[0, 0], (vv - K_out[1, 2]) / K_out[1, 1]
        if model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            xx, yy = _forward(model, p, xx, yy)
        su, sv = xx * K_src[0, 0] + K_src[0, 2], yy * K_src[1, 1] + K_src[1, 2]
        return (su >= 0.5 - 1e-6) & (su <= w0 - 0.5 + 1e-6) & (sv >= 0.5 - 1e-6) & (sv <= h0 - 0.5 + 1e-6)

    assert source(u, v).all(), model
    if check_tight:  # one more column / row on any side takes in a pixel without a source
        cols, rows = np.arange(w) + 0.5, np.arange(h) + 0.5
        for uu, vv in ((np.full(h, -0.5), rows), (np.full(h, w + 0.5), rows),
                       (cols, np.full(w, -0.5)), (cols, np.full(w, h + 0.5))):
            assert not source(uu, vv).all(), model


# ----------------------------------------------------------------------------- capture writers
def _look(eye):
    from ssgwarp.core.cameras import look_at

    return look_at(torch.tensor([eye], dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64),
                   (0.0, -1.0, 0.0))[0].numpy()


def _cameras_bin(path: Path, cams: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    b = struct.pack("<Q", len(cams))
    for c in cams.values():
        b += struct.pack("<iiQQ", c.id, MODEL_IDS[c.model], c.width, c.height) + c.params.astype("<f8").tobytes()
    path.write_bytes(b)


def _colmap_params(model, p, f=F, cx=W0 / 2, cy=H0 / 2):
    one = model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "FOV")
    return np.array(([f, cx, cy] if one else [f, f * 1.01, cx, cy]) + list(p), dtype=np.float64)


def _colmap_capture(root: Path, cams: dict, n=4, folder="images", render=True, binary=False):
    """COLMAP capture: ``cams`` maps camera id -> (model, params); image i uses camera 1 + i % len(cams)."""
    ccams = {cid: ColmapCamera(cid, m, W0, H0, _colmap_params(m, p)) for cid, (m, p) in cams.items()}
    images = {}
    for i in range(n):
        cid = 1 + i % len(cams)
        V = _look([0.4 * i - 0.6, 0.1, -3.0])
        images[i + 1] = ColmapImage(i + 1, rotmat_to_qvec(V[:3, :3]), V[:3, 3], cid, f"v{i}.png")
        m, p = cams[cid]
        img = _distorted_image(m, p, ccams[cid].K, W0, H0) if render else np.full((H0, W0, 3), 0.5, np.float32)
        write_image(root / folder / f"v{i}.png", img)
    rng = np.random.default_rng(0)
    pts = ColmapPoints(np.arange(30), rng.normal(size=(30, 3)) * 0.4, rng.integers(0, 255, (30, 3)).astype(np.uint8),
                       np.zeros(30), np.zeros(30, np.int64))
    write_model_text(root / "sparse" / "0", ccams, images, pts)
    if binary:
        (root / "sparse" / "0" / "cameras.txt").unlink()
        _cameras_bin(root / "sparse" / "0" / "cameras.bin", ccams)
    return ccams


# ----------------------------------------------------------------------------- COLMAP, every model
@pytest.mark.parametrize("model", list(LENSES))
def test_colmap_models_undistort_into_a_pinhole_crop(tmp_path, model, caplog):
    p = LENSES[model]
    ccams = _colmap_capture(tmp_path, {1: (model, p)}, binary=model == "OPENCV")
    with caplog.at_level(logging.INFO, logger="ssgwarp.capture.datasets"):
        d = load_dataset(tmp_path, split_every=0)
    K_src = ccams[1].K
    assert d.undistorted and f"undistorting 4 images ({model}) into a {d.width}x{d.height} pinhole crop" in caplog.text
    # (a) the focal lengths are kept, the principal point moves with the crop, every view shares K here
    assert torch.allclose(d.cameras.Ks[:, 0, 0].double(), torch.tensor(K_src[0, 0], dtype=torch.float64))
    assert torch.allclose(d.cameras.Ks[:, 1, 1].double(), torch.tensor(K_src[1, 1], dtype=torch.float64))
    rec = d.undistortion
    (cam,) = rec["cameras"]
    assert cam["model"] == model and list(cam["params"].values()) == list(p) and cam["images"] == 4
    assert rec["source_size"] == [W0, H0] and rec["size"] == [d.width, d.height] and rec["resized_to"] is None
    x0, y0, x1, y1 = cam["crop"]
    assert (x1 - x0, y1 - y0) == (d.width, d.height) and rec["area"] >= 0.5
    assert np.allclose(cam["K"], d.cameras.Ks[0].double().numpy(), atol=1e-4)
    assert np.allclose(cam["K_source"], K_src)
    assert np.allclose(cam["K"][0][2], K_src[0, 2] - x0) and np.allclose(cam["K"][1][2], K_src[1, 2] - y0)
    # (b), (c) on every image
    for i in range(len(d)):
        _check_image(d.images[i], d.cameras.Ks[i], model, p, K_src, W0, H0)
    # the record goes into data.json as JSON
    assert json.loads(json.dumps(data_json(d)))["undistortion"]["cameras"][0]["crop"] == [x0, y0, x1, y1]


def test_pincushion_crops_and_barrel_grows():
    """Which way the crop goes: a pincushion lens (k > 0) keeps less than the source frame, a barrel lens
    (k < 0) at least as many pixels (its undistorted frame is larger), with the same focal length."""
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[F, 0, W0 / 2], [0, F, H0 / 2], [0, 0, 1.0]])[None]
    pin = plan_undistortion(K, [Lens("SIMPLE_RADIAL", (0.08,))], W0, H0, ["c"])
    bar = plan_undistortion(K, [Lens("SIMPLE_RADIAL", (-0.08,))], W0, H0, ["c"])
    assert pin.size[0] < W0 and pin.size[1] < H0
    assert bar.size[0] * bar.size[1] > W0 * H0 and min(bar.size[0] - W0, bar.size[1] - H0) >= 0
    assert plan_undistortion(K, [Lens("RADIAL", (0.0, 0.0))], W0, H0, ["c"]) is None  # nothing to do


def test_mixed_cameras_share_one_size(tmp_path):
    """A pinhole camera and a distorted one: one output size; the pinhole images are exact crops."""
    p = LENSES["OPENCV"]
    ccams = _colmap_capture(tmp_path, {1: ("PINHOLE", ()), 2: ("OPENCV", p)}, n=4)
    d = load_dataset(tmp_path, split_every=0)
    rec = d.undistortion
    assert len(rec["cameras"]) == 2 and rec["size"] == [d.width, d.height]
    by_model = {c["model"]: c for c in rec["cameras"]}
    assert set(by_model) == {"PINHOLE", "OPENCV"}
    from ssgwarp.core.fileio import read_image

    for i, name in enumerate(d.names):
        cid = 1 + int(name[1]) % 2
        m, pp = ("PINHOLE", ()) if cid == 1 else ("OPENCV", p)
        _check_image(d.images[i], d.cameras.Ks[i], m, pp, ccams[cid].K, W0, H0, check_tight=False)
        if cid == 1:
            x0, y0, x1, y1 = by_model["PINHOLE"]["crop"]
            src = torch.from_numpy(read_image(tmp_path / "images" / name))
            assert torch.equal(d.images[i], src[y0:y1, x0:x1])


def test_width_resizes_after_undistortion(tmp_path):
    _colmap_capture(tmp_path, {1: ("OPENCV", LENSES["OPENCV"])})
    full = load_dataset(tmp_path)
    d = load_dataset(tmp_path, width=50)
    h = round(full.height * 50 / full.width)
    assert (d.width, d.height) == (50, h) and d.undistortion["resized_to"] == [50, h]
    K = full.cameras.Ks[0].double().clone()
    K[0] *= 50 / full.width
    K[1] *= h / full.height
    assert torch.allclose(d.cameras.Ks[0].double(), K, atol=1e-4)
    assert d.images.min() >= 0.15  # still no zero-filled pixel


# ----------------------------------------------------------------------------- transforms.json
def _transforms_capture(root: Path, meta: dict, per_frame=None, n=4):
    frames = []
    for i in range(n):
        V = _look([0.4 * i - 0.6, 0.1, -3.0])
        c2w_gl = np.linalg.inv(V) @ np.diag([1.0, -1.0, -1.0, 1.0])
        fr = {"file_path": f"images/f{i}.png", "transform_matrix": c2w_gl.tolist(), **((per_frame or {}).get(i, {}))}
        frames.append(fr)
        m = {**meta, **fr}
        s = W0 / m.get("w", W0)
        K = np.array([[m["fl_x"] * s, 0, m["cx"] * s], [0, m["fl_y"] * s, m["cy"] * s], [0, 0, 1.0]])
        if m.get("is_fisheye"):
            model, p = "OPENCV_FISHEYE", tuple(m.get(k, 0.0) for k in ("k1", "k2", "k3", "k4"))
        else:
            model, p = "FULL_OPENCV", tuple(m.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")) + (0.0,) * 3
        write_image(root / "images" / f"f{i}.png", _distorted_image(model, p, K, W0, H0))
    (root / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))


def test_transforms_opencv_k1_k2_k3_p1_p2(tmp_path):
    # intrinsics given for a 2x larger capture (w, h), images at 80x60
    meta = {"fl_x": 2 * F, "fl_y": 2 * F * 1.01, "cx": W0 + 1.0, "cy": H0 - 1.0, "w": 2 * W0, "h": 2 * H0,
            "k1": 0.06, "k2": -0.01, "k3": 0.002, "p1": 0.003, "p2": -0.002}
    _transforms_capture(tmp_path, meta)
    d = load_dataset(tmp_path, split_every=0, num_random_points=10)
    (cam,) = d.undistortion["cameras"]
    assert cam["model"] == "FULL_OPENCV" and cam["params"]["k3"] == 0.002 and cam["params"]["p1"] == 0.003
    K_src = np.array([[F, 0, W0 / 2 + 0.5], [0, F * 1.01, H0 / 2 - 0.5], [0, 0, 1]])
    assert np.allclose(cam["K_source"], K_src)
    p = (0.06, -0.01, 0.003, -0.002, 0.002, 0.0, 0.0, 0.0)
    for i in range(len(d)):
        _check_image(d.images[i], d.cameras.Ks[i], "FULL_OPENCV", p, K_src, W0, H0)


def test_transforms_fisheye_with_per_frame_intrinsics(tmp_path):
    meta = {"fl_x": F, "fl_y": F, "cx": W0 / 2, "cy": H0 / 2, "is_fisheye": True,
            "k1": 0.05, "k2": 0.01, "k3": 0.0, "k4": 0.0}
    per = {1: {"fl_x": F * 1.05, "fl_y": F * 1.05, "cx": W0 / 2 + 2}, 3: {"k1": 0.02}}
    _transforms_capture(tmp_path, meta, per)
    d = load_dataset(tmp_path, split_every=0, num_random_points=10)
    rec = d.undistortion
    assert {c["model"] for c in rec["cameras"]} == {"OPENCV_FISHEYE"} and len(rec["cameras"]) == 3
    assert sum(c["images"] for c in rec["cameras"]) == 4
    for i in range(len(d)):
        m = {**meta, **per.get(i, {})}
        K_src = np.array([[m["fl_x"], 0, m["cx"]], [0, m["fl_y"], m["cy"]], [0, 0, 1]])
        p = tuple(m[k] for k in ("k1", "k2", "k3", "k4"))
        assert np.isclose(float(d.cameras.Ks[i, 0, 0]), m["fl_x"])  # each frame keeps its focal length
        _check_image(d.images[i], d.cameras.Ks[i], "OPENCV_FISHEYE", p, K_src, W0, H0, check_tight=False)
    # nerfstudio's spelling of the same camera
    raw = json.loads((tmp_path / "transforms.json").read_text())
    raw.pop("is_fisheye")
    raw["camera_model"] = "OPENCV_FISHEYE"
    (tmp_path / "transforms.json").write_text(json.dumps(raw))
    d2 = load_dataset(tmp_path, split_every=0, num_random_points=10)
    assert torch.equal(d2.images, d.images) and torch.equal(d2.cameras.Ks, d.cameras.Ks)


def test_transforms_lens_errors(tmp_path):
    meta = {"fl_x": F, "fl_y": F, "cx": W0 / 2, "cy": H0 / 2, "k1": 0.05}
    _transforms_capture(tmp_path, meta, n=2)
    raw = json.loads((tmp_path / "transforms.json").read_text())
    (tmp_path / "transforms.json").write_text(json.dumps({**raw, "camera_model": "EQUIRECTANGULAR"}))
    with pytest.raises(InputError, match=r"camera_model EQUIRECTANGULAR \(a panorama\) is not supported"):
        load_dataset(tmp_path)
    (tmp_path / "transforms.json").write_text(json.dumps({**raw, "k4": 0.01}))
    with pytest.raises(InputError, match="k4=0.01 without is_fisheye"):
        load_dataset(tmp_path)
    (tmp_path / "transforms.json").write_text(json.dumps({**raw, "is_fisheye": True, "p1": 0.01}))
    with pytest.raises(InputError, match="fisheye camera .* takes k1 k2 k3 k4, not p1 p2"):
        load_dataset(tmp_path)


# ----------------------------------------------------------------------------- LLFF, images_N levels
def _llff_capture(root: Path, model, p, full=(320, 240), focal=240.0, levels=(2, 4), n=4):
    rows = []
    for i in range(n):
        c2w = np.linalg.inv(_look([0.3 * i - 0.45, 0.05 * i, -4.0]))
        x, y, z, t = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3]
        pose = np.stack([y, x, -z, t, [full[1], full[0], focal]], axis=1)
        rows.append(np.concatenate([pose.ravel(), [2.0, 6.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    cam = ColmapCamera(1, model, full[0], full[1], _colmap_params(model, p, focal, full[0] / 2, full[1] / 2))
    _cameras_bin(root / "sparse" / "0" / "cameras.bin", {1: cam})
    for s in levels:
        w, h = full[0] // s, full[1] // s
        K = np.array([[focal / s, 0, w / 2], [0, focal / s, h / 2], [0, 0, 1]])
        img = _distorted_image(model, p, K, w, h)
        for i in range(n):
            write_image(root / f"images_{s}" / f"IMG_{i:03d}.png", img)


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "OPENCV_FISHEYE"])
def test_llff_distorted_sparse_camera_at_every_level(tmp_path, model):
    p = LENSES[model]
    _llff_capture(tmp_path, model, p)
    d2 = load_dataset(tmp_path, images="images_2", num_random_points=50, init="random")
    d4 = load_dataset(tmp_path, images="images_4", num_random_points=50, init="random")
    for d, s in ((d2, 2), (d4, 4)):
        assert d.undistortion["cameras"][0]["model"] == model and d.undistortion["source_size"] == [320 // s, 240 // s]
        K_src = np.array([[240.0 / s, 0, 160 / s], [0, 240.0 / s, 120 / s], [0, 0, 1]])
        for i in (0, len(d) - 1):
            _check_image(d.images[i], d.cameras.Ks[i], model, p, K_src, 320 // s, 240 // s)
        # random initial points are drawn in the undistorted cameras' frusta
        assert d.points_source == "random" and torch.isfinite(d.points[0]).all()
    # (e) one lens at two resolutions: the same crop, scaled (to the pixel)
    K2, K4 = d2.cameras.Ks[0].double(), d4.cameras.Ks[0].double()
    assert torch.equal(K2[0, 0], 2 * K4[0, 0]) and torch.equal(K2[1, 1], 2 * K4[1, 1])
    assert abs(float(K2[0, 2] - 2 * K4[0, 2])) <= 1.5 and abs(float(K2[1, 2] - 2 * K4[1, 2])) <= 1.5
    assert abs(d2.width - 2 * d4.width) <= 2 and abs(d2.height - 2 * d4.height) <= 2


def test_llff_sparse_camera_with_another_focal_is_not_used(tmp_path, caplog):
    _llff_capture(tmp_path, "SIMPLE_RADIAL", (0.05,), levels=(4,))
    cam = ColmapCamera(1, "SIMPLE_RADIAL", 320, 240, np.array([300.0, 160, 120, 0.05]))
    _cameras_bin(tmp_path / "sparse" / "0" / "cameras.bin", {1: cam})
    with caplog.at_level(logging.WARNING, logger="ssgwarp.capture.datasets"):
        d = load_dataset(tmp_path, images="images_4", num_random_points=10)
    assert not d.undistorted and (d.width, d.height) == (80, 60) and "its distortion is not removed" in caplog.text


# ----------------------------------------------------------------------------- errors
def test_too_strong_distortion_is_refused_naming_the_camera(tmp_path):
    _colmap_capture(tmp_path / "pin", {1: ("SIMPLE_RADIAL", (2.0,))}, render=False)
    with pytest.raises(InputError, match=r"cameras.txt: camera 1 \(SIMPLE_RADIAL k=2\): lens distortion too "
                                         r"strong for a pinhole crop: .* covers \d+% of the 80x60 image \(at "
                                         r"least 50% needed\); check the calibration"):
        load_dataset(tmp_path / "pin")
    _colmap_capture(tmp_path / "bar", {1: ("RADIAL", (-1.5, 0.0))}, render=False, binary=True)
    with pytest.raises(InputError, match=r"cameras.bin: camera 1 \(RADIAL k1=-1.5 k2=0\): lens distortion too strong"):
        load_dataset(tmp_path / "bar")


@pytest.mark.parametrize("model", ["FOV", "THIN_PRISM_FISHEYE"])
def test_unsupported_models_are_named(tmp_path, model):
    n = {"FOV": 1, "THIN_PRISM_FISHEYE": 8}[model]
    _colmap_capture(tmp_path, {1: ("SIMPLE_RADIAL", (0.0,))}, render=False)
    txt = tmp_path / "sparse" / "0" / "cameras.txt"
    pars = " ".join(["60", "60", "40", "30"] + ["0.01"] * n) if model != "FOV" else "60 60 40 30 0.5"
    txt.write_text(f"1 {model} {W0} {H0} {pars}\n")
    with pytest.raises(InputError, match=f"COLMAP camera 1: model {model} is not supported .*colmap image_undistorter"):
        load_dataset(tmp_path)


# ----------------------------------------------------------------------------- runs
def test_run_files_carry_the_crop_and_load_run_reproduces_it(tmp_path):
    from ssgwarp.core.fileio import write_json
    from ssgwarp.formats.ply import write_ply
    from ssgwarp.raster.scene import GaussianScene

    cap, run = tmp_path / "cap", tmp_path / "run"
    _colmap_capture(cap, {1: ("OPENCV", LENSES["OPENCV"])}, n=5)
    d = load_dataset(cap, split_every=2, width=60)
    write_ply(run / "scene.ply", GaussianScene.from_points(d.points[0], d.points[1], sh_degree=0))
    d.cameras.save(run / "cameras.json")
    write_json(run / "data.json", data_json(d))
    meta = json.loads((run / "data.json").read_text())
    assert meta["undistorted"] and meta["undistortion"]["cameras"][0]["model"] == "OPENCV"
    assert meta["undistortion"]["resized_to"] == [d.width, d.height] and (meta["width"], meta["height"]) == (60, d.height)
    _, back = load_run(run)
    assert torch.equal(back.images, d.images) and torch.equal(back.cameras.Ks, d.cameras.Ks)
    assert back.undistortion == meta["undistortion"] and back.metric_frame == d.metric_frame
    _, cams_only = load_run(run, load_images=False)
    assert cams_only.undistorted and (cams_only.width, cams_only.height) == (d.width, d.height)
    # a run whose cameras are not what the capture loads as (e.g. made before the crop): refused
    cj = json.loads((run / "cameras.json").read_text())
    for c in cj["cameras"]:
        c["K"][0][2] += 3.0
    (run / "cameras.json").write_text(json.dumps(cj))
    with pytest.raises(InputError, match="now loads as .* with other intrinsics than the run's .*cameras.json"):
        load_run(run)


def test_reconstruct_metrics_say_which_frame(tmp_path, monkeypatch):
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.reconstruct import ReconstructConfig, reconstruct

    for var in ("SSGWARP_LPIPS", "SSGWARP_VGG16", "SSGWARP_WEIGHTS"):
        monkeypatch.delenv(var, raising=False)
    _colmap_capture(tmp_path / "cap", {1: ("SIMPLE_RADIAL", LENSES["SIMPLE_RADIAL"])}, n=4)
    m = reconstruct(tmp_path / "cap", tmp_path / "run", ReconstructConfig(iters=2, recipe=Recipe(sh_degree=0),
                    split_every=2, checkpoint_every=0), device="cpu", progress=False)
    meta = json.loads((tmp_path / "run" / "data.json").read_text())
    on_disk = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["metric_frame"] == on_disk["metric_frame"] == "undistorted-crop"
    assert on_disk["metric_size"] == [meta["width"], meta["height"]] == on_disk["resolution"]
    assert on_disk["metric_crop"]["crops"] == [meta["undistortion"]["cameras"][0]["crop"]]
    _colmap_capture(tmp_path / "pin", {1: ("PINHOLE", ())}, n=4)
    m = reconstruct(tmp_path / "pin", tmp_path / "run2", ReconstructConfig(iters=1, recipe=Recipe(sh_degree=0),
                    split_every=2, checkpoint_every=0), device="cpu", progress=False)
    assert m["metric_frame"] == "as-captured" and "metric_crop" not in m


# ----------------------------------------------------------------------------- the real capture
@pytest.mark.skipif(not (DATA / "llff_fern").is_dir(), reason="shared data not present")
def test_fern_every_pixel_is_an_interpolation_of_real_pixels():
    """fern (SIMPLE_RADIAL, k = 0.0197): each loaded pixel is the bilinear interpolation of the source
    image at its distorted position (recomputed here), and that position is inside the source."""
    from ssgwarp.formats.colmap import read_cameras
    from ssgwarp.core.fileio import read_image

    (cam,) = read_cameras(DATA / "llff_fern" / "sparse" / "0" / "cameras.bin").values()
    d = load_dataset(DATA / "llff_fern", images="images_8", max_images=3, split_every=0)
    assert (d.width, d.height) == (498, 372) and d.undistortion["cameras"][0]["crop"] == [3, 3, 501, 375]
    src = read_image(DATA / "llff_fern" / "images_8" / d.names[1]).astype(np.float64)
    h0, w0 = src.shape[:2]
    f = cam.params[0] * w0 / cam.width
    K = d.cameras.Ks[1].double().numpy()
    assert np.isclose(K[0, 0], f, rtol=1e-6)
    v, u = np.mgrid[0:d.height, 0:d.width] + 0.5
    x, y = _forward("SIMPLE_RADIAL", (cam.params[3],), (u - K[0, 2]) / f, (v - K[1, 2]) / f)
    su, sv = x * f + w0 / 2 - 0.5, y * f + h0 / 2 - 0.5  # in pixel-index units
    assert su.min() >= 0 and sv.min() >= 0 and su.max() <= w0 - 1 and sv.max() <= h0 - 1
    i0, j0 = np.minimum(np.floor(su).astype(int), w0 - 2), np.minimum(np.floor(sv).astype(int), h0 - 2)
    a, b = (su - i0)[..., None], (sv - j0)[..., None]
    want = ((1 - a) * (1 - b) * src[j0, i0] + a * (1 - b) * src[j0, i0 + 1] + (1 - a) * b * src[j0 + 1, i0]
            + a * b * src[j0 + 1, i0 + 1])
    assert np.abs(d.images[1].numpy() - want).max() < 1e-4


# ----------------------------------------------------------------------------- masks drawn on the source images
def _coordinate_images(root: Path, n: int) -> None:
    """Overwrite the capture's images with their own pixel coordinates: R = x / W0, G = y / H0 (centres)."""
    x = (np.arange(W0) + 0.5) / W0
    y = (np.arange(H0) + 0.5) / H0
    img = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.zeros((H0, W0))), axis=-1).astype(np.float32)
    for i in range(n):
        write_image(root / "images" / f"v{i}.png", img)


@pytest.mark.parametrize("width", [None, 50])
def test_source_frame_labels_follow_their_images_into_the_crop(tmp_path, width):
    """A label image of the distorted source (each pixel labelled with its own index) undistorted by
    ``undistort_labels`` names, at every output pixel, the source pixel the image's colour came from
    (within half a pixel plus the 8-bit rounding), for two cameras with different lenses and at a
    mask resolution half the image's."""
    from ssgwarp.capture.lens import undistort_labels

    _colmap_capture(tmp_path, {1: ("OPENCV", LENSES["OPENCV"]), 2: ("RADIAL", LENSES["RADIAL"])}, n=4)
    _coordinate_images(tmp_path, 4)
    d = load_dataset(tmp_path, split_every=0, width=width)
    rec = d.undistortion
    assert [c["image_ids"] for c in rec["cameras"]] == [[0, 2], [1, 3]]
    labels = (np.arange(H0)[:, None] * W0 + np.arange(W0)[None, :]).astype(np.int64)
    half = labels[::2, ::2] // W0 // 2 * (W0 // 2) + labels[::2, ::2] % W0 // 2  # the same at half size
    for i in range(4):
        out = undistort_labels(rec, i, labels)
        assert out.shape == (d.height, d.width)
        img = d.images[i].numpy()
        # half a pixel (after a resize: one) + the 8-bit rounding of the coordinate colours (W0 / 510 = 0.16 px)
        tol = (1.0 if width else 0.5) + 0.4
        assert np.abs((out % W0 + 0.5) - img[..., 0] * W0).max() <= tol
        assert np.abs((out // W0 + 0.5) - img[..., 1] * H0).max() <= tol
        small = undistort_labels(rec, i, half)
        assert np.abs((small % (W0 // 2) + 0.5) * 2 - img[..., 0] * W0).max() <= 2 * tol
    with pytest.raises(InputError, match="aspect"):
        undistort_labels(rec, 0, labels[:, :40])


def test_group_masks_of_the_source_frame_are_undistorted(tmp_path):
    """``load_masks`` with the run's undistortion record: a mask at the source size (one id per source
    column band) comes out in the crop's frame, equal to ``undistort_labels`` of it; a mask already at
    the crop's size is taken as it is."""
    from ssgwarp.grouping.mask_files import load_masks
    from ssgwarp.capture.lens import undistort_labels

    _colmap_capture(tmp_path, {1: ("SIMPLE_RADIAL", (0.08,))}, n=2)
    d = load_dataset(tmp_path, split_every=0)
    rec = d.undistortion
    bands = np.broadcast_to((np.arange(W0) // 20)[None, :], (H0, W0)).astype(np.uint8)  # ids 0..3
    masks = tmp_path / "object_mask"
    write_image(masks / "v0.png", bands[..., None].astype(np.float32) / 255.0)
    crop_mask = np.broadcast_to((np.arange(d.width) * 4 // d.width)[None, :], (d.height, d.width)).astype(np.uint8)
    write_image(masks / "v1.png", crop_mask[..., None].astype(np.float32) / 255.0)
    ms = load_masks(masks, ["v0.png", "v1.png"], d.width, d.height, undistortion=rec)
    assert ms.ids == [0, 1, 2, 3]
    assert torch.equal(ms.targets[0], torch.from_numpy(undistort_labels(rec, 0, bands.astype(np.int64))))
    assert torch.equal(ms.targets[1], torch.from_numpy(crop_mask.astype(np.int64)))
    # the crop of a pincushion lens is smaller than the source: band edges move inwards, not copied
    assert not torch.equal(ms.targets[0], torch.from_numpy((np.arange(d.width) // 20)[None, :].repeat(d.height, 0)))

# ----------------------------------------------------------------------------- the lens maths, unit by unit
def _grid_points():
    g = np.random.default_rng(7)
    x, y = g.uniform(-0.6, 0.6, 200), g.uniform(-0.45, 0.45, 200)
    return np.concatenate([[0.0, 0.3, 0.0], x]), np.concatenate([[0.0, 0.0, -0.2], y])  # the centre and the axes


@pytest.mark.parametrize("model", list(LENSES))
def test_lens_distort_matches_the_formulas(model):
    from ssgwarp.capture.lens import Lens

    x, y = _grid_points()
    got = Lens(model, LENSES[model]).distort(x, y)
    want = _forward(model, LENSES[model], x, y)
    assert np.abs(got[0] - want[0]).max() < 1e-13 and np.abs(got[1] - want[1]).max() < 1e-13
    assert got[0][0] == 0.0 and got[1][0] == 0.0  # the principal point stays (the fisheye's r = 0 case too)


def test_rational_model_is_undefined_where_its_denominator_is_not_positive():
    from ssgwarp.capture.lens import Lens

    # FULL_OPENCV denominator 1 + k4 r^2: zero at r = 1 for k4 = -1, negative beyond
    lens = Lens("FULL_OPENCV", (0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0))
    xd, yd = lens.distort(np.array([1.0, 0.0, 1.2, 0.5]), np.array([0.0, 1.0, 0.0, 0.0]))
    assert np.isnan(xd[:3]).all() and np.isnan(yd[:3]).all()
    assert xd[3] == pytest.approx(0.5 / (1 - 0.25)) and yd[3] == 0.0


@pytest.mark.parametrize("model, p", [("SIMPLE_RADIAL", (0.3,)), ("RADIAL", (-0.2, 0.05)),
                                      ("OPENCV_FISHEYE", (0.05, 0.01, -0.002, 0.0005))])
def test_jacobian_determinant_of_radial_maps(model, p):
    """A radial map p -> p rho(r) / r has Jacobian determinant (rho / r) rho'(r)."""
    from ssgwarp.capture.lens import Lens

    x, y = _grid_points()
    x, y = x[3:], y[3:]
    r = np.hypot(x, y)
    if model in FISHEYES:
        k = list(p)
        th = np.arctan(r)
        rho = th * (1 + k[0] * th ** 2 + k[1] * th ** 4 + k[2] * th ** 6 + k[3] * th ** 8)
        drho = (1 + 3 * k[0] * th ** 2 + 5 * k[1] * th ** 4 + 7 * k[2] * th ** 6 + 9 * k[3] * th ** 8) / (1 + r * r)
    else:
        k1, k2 = (list(p) + [0.0])[:2]
        rho = r * (1 + k1 * r ** 2 + k2 * r ** 4)
        drho = 1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4
    want = rho / r * drho
    got = Lens(model, p).jacobian_det(x, y)
    assert np.abs(got - want).max() < 1e-6


def test_undistort_inverts_distort_before_the_fold_and_is_nan_beyond_reach():
    from ssgwarp.capture.lens import Lens

    x, y = _grid_points()
    for model, p in LENSES.items():
        lens = Lens(model, p)
        bx, by = lens.undistort(*lens.distort(x, y))
        assert np.abs(bx - x).max() < 1e-9 and np.abs(by - y).max() < 1e-9, model
    # barrel k = -0.5: rho = r - r^3 / 2 folds at r^2 = 2/3 (largest rho ~0.544); rho = 0.5 has two preimages,
    # r = (sqrt(5) - 1) / 2 before the fold and 1 beyond it; 0.7 has none
    lens = Lens("SIMPLE_RADIAL", (-0.5,))
    t = np.linspace(0.05, 0.75, 15) / 2 ** 0.5  # up the diagonal, to r = 0.75 (near the fold at 0.816)
    bx, by = lens.undistort(*lens.distort(t, t))
    assert np.abs(bx - t).max() < 1e-9 and np.abs(by - t).max() < 1e-9
    ux, uy = lens.undistort(np.array([0.5, 0.0, 0.7, 0.0]), np.array([0.0, -0.5, 0.0, 0.56]))
    assert ux[0] == pytest.approx((5 ** 0.5 - 1) / 2, abs=1e-9) and uy[0] == 0.0
    assert uy[1] == pytest.approx(-(5 ** 0.5 - 1) / 2, abs=1e-9) and ux[1] == 0.0
    assert np.isnan(ux[2:]).all() and np.isnan(uy[2:]).all()


def test_lens_validation_and_description():
    from ssgwarp.capture.lens import Lens

    with pytest.raises(InputError, match=r"lens model FOV is not supported \(supported: SIMPLE_RADIAL, RADIAL, "):
        Lens("FOV", (0.1,))
    with pytest.raises(InputError, match=r"lens model RADIAL takes 2 coefficients \(k1 k2\), got 3"):
        Lens("RADIAL", (0.1, 0.2, 0.3))
    with pytest.raises(InputError, match=r"lens model OPENCV: non-finite coefficients \[0.1, nan, 0.0, 0.0\]"):
        Lens("OPENCV", (0.1, float("nan"), 0, 0))
    lens = Lens("OPENCV", (0.1, -0.02, 1, 0))
    assert lens.params == (0.1, -0.02, 1.0, 0.0) and all(type(v) is float for v in lens.params)
    assert lens.describe() == "OPENCV k1=0.1 k2=-0.02 p1=1 p2=0"
    assert lens.to_json() == {"model": "OPENCV", "params": {"k1": 0.1, "k2": -0.02, "p1": 1.0, "p2": 0.0}}
    assert Lens("RADIAL", (0.0, 0.0)).is_pinhole and not Lens("RADIAL", (0.0, 1e-9)).is_pinhole
    assert not Lens("SIMPLE_RADIAL_FISHEYE", (0.0,)).is_pinhole  # an equidistant fisheye is no pinhole


def test_widest_rectangle_of_row_runs():
    from ssgwarp.capture.lens import _widest

    L, R = np.array([2, 1, 0, 3]), np.array([5, 6, 8, 4])
    # h = 1: row 2 (8 wide); h = 2: rows 1-2 (min R 6 - max L 1); h = 3: rows 0-2 (5 - 2); h = 4: 4 - 3
    assert _widest(L, R).tolist() == [8, 5, 3, 1]


def test_crop_is_centred_on_the_principal_point_and_records_itself():
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[F, 0, W0 / 2], [0, F, H0 / 2], [0, 0, 1.0]])
    plan = plan_undistortion(K[None], [Lens("SIMPLE_RADIAL", (0.08,))], W0, H0, ["cam"])
    (W, H), (x0, y0) = plan.size, plan.cameras[0].crop
    assert (x0 + W / 2, y0 + H / 2) == (W0 / 2, H0 / 2)
    assert np.allclose(plan.Ks[0], [[F, 0, W0 / 2 - x0], [0, F, H0 / 2 - y0], [0, 0, 1]])
    rec = plan.record()
    assert rec["source_size"] == [W0, H0] and rec["size"] == [W, H] and rec["area"] == round(W * H / (W0 * H0), 4)
    assert rec["cameras"][0]["crop"] == [x0, y0, x0 + W, y0 + H] and rec["cameras"][0]["camera"] == "cam"
    # an image of another size is refused
    with pytest.raises(InputError, match=rf"image 0: size 40x30, expected {W0}x{H0}"):
        plan(0, torch.zeros(30, 40, 3))
    # a constant image stays constant: every output pixel interpolates real pixels (none reads padding)
    out = plan(0, torch.full((H0, W0, 3), 0.25))
    assert out.shape == (H, W, 3) and torch.allclose(out, torch.full_like(out, 0.25))
    # the grid follows the image to its device (the meta device stands in for a GPU)
    assert plan(0, torch.zeros(H0, W0, 3, device="meta")).device.type == "meta"


def test_bad_principal_points_are_refused():
    from ssgwarp.capture.lens import Lens, plan_undistortion

    barrel = Lens("SIMPLE_RADIAL", (-0.3,))
    K = np.array([[F, 0, -5.0], [0, F, H0 / 2], [0, 0, 1.0]])
    with pytest.raises(InputError, match=r"cam: the principal point \(-5.0, 30.0\) is outside the 80x60 image; "
                                         r"check the intrinsics"):
        plan_undistortion(K[None], [Lens("SIMPLE_RADIAL", (0.08,))], W0, H0, ["cam"])
    K = np.array([[F, 0, 0.3], [0, F, H0 / 2], [0, 0, 1.0]])  # its pixel maps left of the first pixel centre
    with pytest.raises(InputError, match=r"cam: the principal point does not map inside the 80x60 image through "
                                         r"the lens \(SIMPLE_RADIAL k=-0.3\)"):
        plan_undistortion(K[None], [barrel], W0, H0, ["cam"])


def test_blockwise_scans_give_what_one_block_gives(monkeypatch):
    """The valid-region scan and the sampling grid work in blocks of rows (bounded memory on large images):
    blocks of a few rows, not dividing the image height, give the same crop and grid as one block."""
    import ssgwarp.capture.lens as lens_mod
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[F, 0, W0 / 2 + 1.3], [0, F, H0 / 2 - 0.7], [0, 0, 1.0]])[None]
    lens = Lens("OPENCV_FISHEYE", LENSES["OPENCV_FISHEYE"])
    one = plan_undistortion(K, [lens], W0, H0, ["c"])
    grid = one.grid(0).clone()
    assert one.size[1] > 7 and grid.shape == (1, one.size[1], one.size[0], 2)
    monkeypatch.setattr(lens_mod, "_CHUNK", 7 * W0 + 3)   # 5 to 7 rows a block
    few = plan_undistortion(K, [lens], W0, H0, ["c"])
    assert few.size == one.size and np.array_equal(few.Ks, one.Ks) and few.cameras[0].crop == one.cameras[0].crop
    assert torch.equal(few.grid(0), grid)


def test_a_smaller_common_window_is_placed_nearest_each_principal_point():
    """With one size for all cameras, a camera whose region is larger than the window has room to place it:
    the window goes where its centre is nearest the principal point, clamped to the region (here pinhole
    cameras, whose region is the whole 80x60 image, beside a pincushion camera whose crop is 72x54)."""
    from ssgwarp.capture.lens import Lens, plan_undistortion

    pp = [(40.0, 30.0), (41.7, 28.2), (20.0, 50.0), (70.0, 3.0)]
    Ks = np.stack([np.array([[F, 0, cx], [0, F, cy], [0, 0, 1]]) for cx, cy in pp])
    plan = plan_undistortion(Ks, [Lens("SIMPLE_RADIAL", (0.2,)), None, None, None], W0, H0, list("abcd"))
    assert plan.size == (72, 54)
    # x0 = round(cx - 36) and y0 = round(cy - 27), each clamped to [0, 80 - 72] x [0, 60 - 54]
    assert [c.crop for c in plan.cameras] == [(4, 3), (6, 1), (0, 6), (8, 0)]
    assert np.allclose(plan.Ks[:, :2, 2], [[36.0, 27.0], [35.7, 27.2], [20.0, 44.0], [62.0, 3.0]])
    img = torch.arange(H0 * W0, dtype=torch.float32).reshape(H0, W0, 1)
    assert torch.equal(plan(2, img), img[6:60, 0:72])  # a pinhole image is a plain crop
    rec = plan.record()
    assert rec["method"].startswith("pinhole crop: every pixel has a source")
    assert [(c["model"], c["params"], c["crop"]) for c in rec["cameras"][1:]] == [
        ("PINHOLE", {}, [6, 1, 78, 55]), ("PINHOLE", {}, [0, 6, 72, 60]), ("PINHOLE", {}, [8, 0, 80, 54])]


def _assert_valid_and_tight(plan, i, model, p, K_src, tight=True):
    """(c) on a plan alone: every pixel centre of image ``i``'s crop maps (this file's forward map) inside the
    source's pixel centres, and (``tight``) one more column or row on any side would not."""
    (W, H), K = plan.size, plan.Ks[i]

    def inside(u, v):
        x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
        if model is not None:
            x, y = _forward(model, p, x, y)
        su, sv = x * K_src[0, 0] + K_src[0, 2], y * K_src[1, 1] + K_src[1, 2]
        return (su >= 0.5 - 1e-9) & (su <= W0 - 0.5 + 1e-9) & (sv >= 0.5 - 1e-9) & (sv <= H0 - 0.5 + 1e-9)

    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    assert inside(u, v).all(), (model, K_src)
    if not tight:
        return
    cols, rows = np.arange(W) + 0.5, np.arange(H) + 0.5
    for uu, vv in ((np.full(H, -0.5), rows), (np.full(H, W + 0.5), rows), (cols, np.full(W, -0.5)),
                   (cols, np.full(W, H + 0.5))):
        assert not inside(uu, vv).all(), (model, K_src)


WIDE, NARROW = (26.0, 23.0, 38.3, 33.1), (120.0, 130.0, 41.0, 27.0)


@pytest.mark.parametrize("model, p, intr", [
    ("SIMPLE_RADIAL", (0.02,), WIDE), ("RADIAL", (-0.03, 0.002), WIDE), ("OPENCV", (0.01, 0.0, 0.002, -0.001), WIDE),
    ("SIMPLE_RADIAL", (0.3,), NARROW), ("RADIAL", (-0.5, 0.1), NARROW), ("OPENCV", (0.2, 0.0, 0.004, -0.003), NARROW),
    ("OPENCV_FISHEYE", (0.4, 0.0, 0.0, 0.0), NARROW),
])
def test_crop_is_valid_and_tight_for_wide_and_narrow_non_square_cameras(model, p, intr):
    """Wide (focal below the principal point's coordinates) and narrow cameras, non-square pixels and an
    off-centre principal point: the crop keeps its focal lengths and is valid and tight. (A wide fisheye's
    region reaches the 2x search limit, COLMAP's max_scale, so its crop is not tight: left out.)"""
    from ssgwarp.capture.lens import Lens, plan_undistortion

    fx, fy, cx, cy = intr
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    plan = plan_undistortion(K[None], [Lens(model, p)], W0, H0, ["c"], min_area=0.3)
    assert plan.Ks[0, 0, 0] == fx and plan.Ks[0, 1, 1] == fy
    _assert_valid_and_tight(plan, 0, model, p, K)


def test_pinhole_beside_a_barrel_lens_keeps_its_whole_image():
    """A barrel lens's region is larger than its source: beside a pinhole camera the common size is the
    pinhole camera's whole image (its first and last pixel centres are valid sources), placed at (0, 0)."""
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[F, 0, W0 / 2], [0, F, H0 / 2], [0, 0, 1.0]])
    barrel = Lens("SIMPLE_RADIAL", (-0.08,))
    plan = plan_undistortion(np.stack([K, K]), [None, barrel], W0, H0, ["pin", "bar"])
    assert plan.size == (W0, H0) and plan.cameras[0].crop == (0, 0)
    _assert_valid_and_tight(plan, 0, None, (), K)
    _assert_valid_and_tight(plan, 1, "SIMPLE_RADIAL", (-0.08,), K, tight=False)


def test_principal_point_on_the_first_pixel_column():
    """The valid runs are counted from the principal point's column: with the principal point inside the first
    pixel column (cx = 1.0), the region starts at that column and the crop is still valid and tight."""
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[F, 0, 1.0], [0, F, H0 / 2], [0, 0, 1.0]])
    plan = plan_undistortion(K[None], [Lens("SIMPLE_RADIAL", (0.05,))], W0, H0, ["c"], min_area=0.3)
    assert plan.cameras[0].crop[0] == 1 and plan.Ks[0, 0, 2] == 0.0
    _assert_valid_and_tight(plan, 0, "SIMPLE_RADIAL", (0.05,), K)


def test_a_wide_fisheye_is_cut_at_twice_the_source_size():
    """A fisheye of focal 20 px on an 80x60 image sees past 90 degrees in the corners: its undistorted frame
    is unbounded, and the search stops at the source size beyond each side of the principal point (COLMAP's
    max_scale 2): the crop is that whole 160x120 frame, every pixel still with a source."""
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[20.0, 0, 40.0], [0, 20.0, 30.0], [0, 0, 1.0]])
    plan = plan_undistortion(K[None], [Lens("OPENCV_FISHEYE", (0.02, 0.0, 0.0, 0.0))], W0, H0, ["c"])
    assert plan.size == (2 * W0, 2 * H0) and plan.cameras[0].crop == (-W0 // 2, -H0 // 2)
    _assert_valid_and_tight(plan, 0, "OPENCV_FISHEYE", (0.02, 0.0, 0.0, 0.0), K, tight=False)


def test_min_area_is_inclusive_and_the_refusal_names_the_covered_share():
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[F, 0, W0 / 2], [0, F, H0 / 2], [0, 0, 1.0]])[None]
    lens = Lens("SIMPLE_RADIAL", (0.4,))
    plan = plan_undistortion(K, [lens], W0, H0, ["c"], min_area=0.1)
    share = plan.size[0] * plan.size[1] / (W0 * H0)
    assert plan_undistortion(K, [lens], W0, H0, ["c"], min_area=share).size == plan.size  # exactly enough
    assert 0.5 < share < 0.9
    with pytest.raises(InputError, match=rf"c \(SIMPLE_RADIAL k=0.4\): .* covers {share:.0%} of the 80x60 image "
                                         rf"\(at least 95% needed\)"):
        plan_undistortion(K, [lens], W0, H0, ["c"], min_area=0.95)


def test_cameras_a_fraction_of_a_pixel_apart_stay_apart():
    from ssgwarp.capture.lens import Lens, plan_undistortion

    K = np.array([[F, 0, W0 / 2], [0, F, H0 / 2], [0, 0, 1.0]])
    K2 = K.copy()
    K2[0, 2] += 0.3
    lens = Lens("SIMPLE_RADIAL", (0.08,))
    plan = plan_undistortion(np.stack([K, K2, K]), [lens, lens, lens], W0, H0, ["a", "b", "a"])
    assert len(plan.cameras) == 2 and [c.images for c in plan.cameras] == [[0, 2], [1]]
    assert plan.Ks[1, 0, 2] == pytest.approx(W0 / 2 + 0.3 - plan.cameras[1].crop[0])
