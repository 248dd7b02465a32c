"""COLMAP readers: text and binary agree with what was written, corrupt files fail clearly,
and the real colmap_cup model reprojects its points onto its own 2D observations."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from ssgwarp.formats.colmap import (MODEL_IDS, ColmapCamera, ColmapImage, ColmapPoints, find_model, qvec_to_rotmat,
                            read_cameras_binary, read_images_binary, read_model, read_points3d_binary,
                            rotmat_to_qvec, write_model_text)
from ssgwarp.errors import InputError

from conftest import SHARED_DATA as DATA


def _model():
    rng = np.random.default_rng(0)
    cams = {
        1: ColmapCamera(1, "PINHOLE", 64, 48, np.array([50.0, 52.0, 31.5, 24.25])),
        2: ColmapCamera(2, "SIMPLE_PINHOLE", 64, 48, np.array([55.0, 32.0, 24.0])),
        3: ColmapCamera(3, "SIMPLE_RADIAL", 64, 48, np.array([55.0, 32.0, 24.0, 0.05])),
        4: ColmapCamera(4, "RADIAL", 64, 48, np.array([55.0, 32.0, 24.0, 0.05, -0.01])),
        5: ColmapCamera(5, "OPENCV", 64, 48, np.array([50.0, 51.0, 32.0, 24.0, 0.05, -0.01, 0.001, -0.002])),
    }
    images = {}
    for i in range(1, 6):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        xys = rng.uniform(0, 60, size=(3, 2))
        images[10 + i] = ColmapImage(10 + i, q, rng.normal(size=3), i, f"img {i}.png" if i == 2 else f"img{i}.png",
                                     xys, np.array([7, -1, 9], dtype=np.int64))
    pts = ColmapPoints(np.array([7, 9], np.int64), rng.normal(size=(2, 3)), np.array([[255, 0, 10], [1, 2, 3]], np.uint8),
                       np.array([0.5, 1.25]), np.array([0, 0], np.int64))
    return cams, images, pts


def _write_binary(folder: Path, cams, images, pts) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    b = struct.pack("<Q", len(cams))
    for c in cams.values():
        b += struct.pack("<iiQQ", c.id, MODEL_IDS[c.model], c.width, c.height) + c.params.astype("<f8").tobytes()
    (folder / "cameras.bin").write_bytes(b)
    b = struct.pack("<Q", len(images))
    for im in images.values():
        b += struct.pack("<i4d3di", im.id, *im.qvec, *im.tvec, im.camera_id) + im.name.encode() + b"\0"
        b += struct.pack("<Q", len(im.xys))
        for (x, y), p in zip(im.xys, im.point3d_ids):
            b += struct.pack("<ddq", x, y, p)
    (folder / "images.bin").write_bytes(b)
    b = struct.pack("<Q", len(pts))
    for i in range(len(pts)):
        b += struct.pack("<Q3d3Bd", pts.ids[i], *pts.xyz[i], *pts.rgb[i], pts.error[i])
        b += struct.pack("<Q", 2) + struct.pack("<iiii", 11, 0, 13, 2)
    (folder / "points3D.bin").write_bytes(b)


def _check_same(model, cams, images, pts):
    assert set(model.cameras) == set(cams)
    for k, c in cams.items():
        m = model.cameras[k]
        assert (m.model, m.width, m.height) == (c.model, c.width, c.height)
        np.testing.assert_array_equal(m.params, c.params)
    assert set(model.images) == set(images)
    for k, im in images.items():
        m = model.images[k]
        assert m.name == im.name and m.camera_id == im.camera_id
        np.testing.assert_array_equal(m.qvec, im.qvec)
        np.testing.assert_array_equal(m.tvec, im.tvec)
        np.testing.assert_array_equal(m.xys, im.xys)
        np.testing.assert_array_equal(m.point3d_ids, im.point3d_ids)
    np.testing.assert_array_equal(model.points.xyz, pts.xyz)
    np.testing.assert_array_equal(model.points.rgb, pts.rgb)
    np.testing.assert_array_equal(model.points.ids, pts.ids)


def test_text_and_binary_round_trip(tmp_path):
    cams, images, pts = _model()
    write_model_text(tmp_path / "txt", cams, images, pts)
    _write_binary(tmp_path / "bin", cams, images, pts)
    mt = read_model(tmp_path / "txt")
    mb = read_model(tmp_path / "bin")
    _check_same(mt, cams, images, pts)
    _check_same(mb, cams, images, pts)
    assert mb.points.track_lengths.tolist() == [2, 2]
    # intrinsics and distortion per model
    assert mt.cameras[1].K.tolist() == [[50.0, 0.0, 31.5], [0.0, 52.0, 24.25], [0.0, 0.0, 1.0]]
    assert not mt.cameras[1].is_distorted and not mt.cameras[2].is_distorted
    assert mt.cameras[1].distortion is None and mt.cameras[2].distortion is None
    assert mt.cameras[3].distortion == ("SIMPLE_RADIAL", (0.05,))
    assert mt.cameras[4].distortion == ("RADIAL", (0.05, -0.01))
    assert mt.cameras[5].distortion == ("OPENCV", (0.05, -0.01, 0.001, -0.002))
    assert mt.cameras[5].K.tolist() == [[50.0, 0.0, 32.0], [0.0, 51.0, 24.0], [0.0, 0.0, 1.0]]
    # the model folder is found from the capture root
    (tmp_path / "cap" / "sparse" / "0").mkdir(parents=True)
    _write_binary(tmp_path / "cap" / "sparse" / "0", cams, images, pts)
    assert find_model(tmp_path / "cap") == tmp_path / "cap" / "sparse" / "0"


def test_quaternion_conversions():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        R = qvec_to_rotmat(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
        np.testing.assert_allclose(rotmat_to_qvec(R), q, atol=1e-10)


def test_truncated_and_corrupt_binary(tmp_path):
    cams, images, pts = _model()
    _write_binary(tmp_path, cams, images, pts)
    for name, reader in (("cameras.bin", read_cameras_binary), ("images.bin", read_images_binary),
                         ("points3D.bin", read_points3d_binary)):
        full = (tmp_path / name).read_bytes()
        for cut in (3, len(full) // 2, len(full) - 1):
            bad = tmp_path / f"cut_{cut}_{name}"
            bad.write_bytes(full[:cut])
            with pytest.raises(InputError, match="truncated|corrupt"):
                reader(bad)
        extra = tmp_path / f"extra_{name}"
        extra.write_bytes(full + b"\0\0\0")
        with pytest.raises(InputError, match="corrupt"):
            reader(extra)
    # a huge count must not allocate or loop: it is rejected before reading
    (tmp_path / "huge.bin").write_bytes(struct.pack("<Q", 2**40) + b"\0" * 64)
    with pytest.raises(InputError, match="does not fit"):
        read_points3d_binary(tmp_path / "huge.bin")
    # unknown camera model id
    (tmp_path / "badmodel.bin").write_bytes(struct.pack("<QiiQQ", 1, 1, 99, 10, 10) + b"\0" * 32)
    with pytest.raises(InputError, match="unknown model id 99"):
        read_cameras_binary(tmp_path / "badmodel.bin")


def test_corrupt_text(tmp_path):
    cams, images, pts = _model()
    write_model_text(tmp_path, cams, images, pts)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32\n")  # one parameter short
    with pytest.raises(InputError, match=r"cameras.txt:1: cannot parse"):
        read_model(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 FISHEYE_MAGIC 64 48 50 50 32 1\n")
    with pytest.raises(InputError, match="cannot parse"):
        read_model(tmp_path)
    write_model_text(tmp_path, {1: cams[1]}, images, pts)  # images refer to cameras 2..5
    with pytest.raises(InputError, match="refers to camera 2"):
        read_model(tmp_path)
    write_model_text(tmp_path, cams, images, pts)
    (tmp_path / "points3D.txt").write_text("7 0.1 0.2 nan-ish 1 2 3 0.5\n")
    with pytest.raises(InputError, match="points3D.txt:1"):
        read_model(tmp_path)
    (tmp_path / "points3D.txt").unlink()
    assert read_model(tmp_path).points is None  # points are optional
    (tmp_path / "images.txt").unlink()
    with pytest.raises(InputError, match="not a COLMAP model folder"):
        read_model(tmp_path)


def test_unsupported_model_is_reported(tmp_path):
    cam = ColmapCamera(1, "FOV", 10, 10, np.ones(5))
    with pytest.raises(InputError, match="FOV is not supported"):
        cam.K
    with pytest.raises(InputError, match="FOV is not supported"):
        cam.distortion
    fish = ColmapCamera(2, "OPENCV_FISHEYE", 10, 10, np.arange(1.0, 9.0))
    assert fish.K.tolist() == [[1.0, 0.0, 3.0], [0.0, 2.0, 4.0], [0.0, 0.0, 1.0]]
    assert fish.distortion == ("OPENCV_FISHEYE", (5.0, 6.0, 7.0, 8.0)) and fish.is_distorted


@pytest.mark.skipif(not (DATA / "colmap_cup").is_dir(), reason="shared data not present")
def test_colmap_cup_points_reproject_onto_their_observations():
    model = read_model(DATA / "colmap_cup" / "sparse" / "0")
    assert len(model.images) == 77 and len(model.points) > 1000
    assert {c.model for c in model.cameras.values()} == {"SIMPLE_PINHOLE"}
    pid_to_row = {int(p): i for i, p in enumerate(model.points.ids)}
    errs = []
    for im in list(model.images.values())[::8]:
        cam = model.cameras[im.camera_id]
        ok = im.point3d_ids >= 0
        xyz = model.points.xyz[[pid_to_row[int(p)] for p in im.point3d_ids[ok]]]
        pc = xyz @ im.R.T + im.tvec
        assert (pc[:, 2] > 0).all()  # every observed point is in front of the camera
        uv = pc[:, :2] / pc[:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
        errs.append(np.linalg.norm(uv - im.xys[ok], axis=1))
    errs = np.concatenate(errs)
    # COLMAP's mean reprojection error is about a pixel; a wrong quaternion order or axis would be far off
    assert np.median(errs) < 1.5, np.median(errs)


@pytest.mark.skipif(not (DATA / "llff_fern").is_dir(), reason="shared data not present")
def test_fern_cameras_and_points_binary():
    from ssgwarp.formats.colmap import read_cameras, read_points3d

    cams = read_cameras(DATA / "llff_fern" / "sparse" / "0" / "cameras.bin")
    (cam,) = cams.values()
    assert (cam.model, cam.width, cam.height) == ("SIMPLE_RADIAL", 4032, 3024)
    assert cam.is_distorted
    pts = read_points3d(DATA / "llff_fern" / "sparse" / "0" / "points3D.bin")
    assert len(pts) == 10091 and np.isfinite(pts.xyz).all()
