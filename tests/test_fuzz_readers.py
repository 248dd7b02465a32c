"""Fuzzing the camera, config and image readers (issue 60): every damaged file is a clean one-line error or a
correct read, never a traceback, a hang or an allocation far beyond the file's size.

Each test damages one small valid file with :mod:`fuzzing`'s strategies (truncated, bit-flipped, wrongly
counted, huge counts, NaN/inf) and reads it with the reader a command uses. Seeded and small by default
(a few seconds in all); ``SSGWARP_FUZZ_EXAMPLES=20000`` is the nightly setting (docs/testing.md,
"Fuzzing the readers").
"""
from __future__ import annotations

import argparse
import json
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, strategies as st

from fuzzing import binary_damage, check_reader, fuzz_dir, fuzz_settings, text_damage
from ssgwarp.formats import colmap
from ssgwarp.capture.loaders import read_poses_bounds, read_transforms
from ssgwarp.errors import InputError, SsgwarpError


@pytest.fixture(scope="module")
def tmp_dir(tmp_path_factory):
    yield from fuzz_dir(tmp_path_factory)


# ----------------------------------------------------------------------------- COLMAP
def _model():
    rng = np.random.default_rng(0)
    cams = {1: colmap.ColmapCamera(1, "PINHOLE", 64, 48, np.array([50.0, 52.0, 31.5, 24.25])),
            2: colmap.ColmapCamera(2, "OPENCV", 64, 48, np.array([50.0, 51.0, 32.0, 24.0, 0.05, -0.01, 1e-3, -2e-3]))}
    images = {}
    for i in range(1, 4):
        q = rng.normal(size=4)
        images[i] = colmap.ColmapImage(i, q / np.linalg.norm(q), rng.normal(size=3), 1 + i % 2, f"img{i}.png",
                                       rng.uniform(0, 60, size=(2, 2)), np.array([7, -1], dtype=np.int64))
    pts = colmap.ColmapPoints(np.array([7, 9], np.int64), rng.normal(size=(2, 3)),
                              np.array([[255, 0, 10], [1, 2, 3]], np.uint8), np.array([0.5, 1.25]),
                              np.array([1, 0], np.int64))
    return cams, images, pts


def _binary(cams, images, pts) -> dict[str, bytes]:
    b = struct.pack("<Q", len(cams))
    for c in cams.values():
        b += struct.pack("<iiQQ", c.id, colmap.MODEL_IDS[c.model], c.width, c.height) + c.params.astype("<f8").tobytes()
    out = {"cameras.bin": b}
    b = struct.pack("<Q", len(images))
    for im in images.values():
        b += struct.pack("<i4d3di", im.id, *im.qvec, *im.tvec, im.camera_id) + im.name.encode() + b"\0"
        b += struct.pack("<Q", len(im.xys)) + b"".join(struct.pack("<ddq", x, y, p)
                                                      for (x, y), p in zip(im.xys, im.point3d_ids))
    out["images.bin"] = b
    b = struct.pack("<Q", len(pts))
    for i in range(len(pts)):
        b += struct.pack("<Q3d3Bd", pts.ids[i], *pts.xyz[i], *pts.rgb[i], pts.error[i])
        b += struct.pack("<Q", pts.track_lengths[i]) + struct.pack("<ii", 1, 0) * int(pts.track_lengths[i])
    out["points3D.bin"] = b
    return out


def _text(tmp_path_factory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("colmap_text")
    colmap.write_model_text(folder, *_model())
    return {p.name: p.read_bytes() for p in folder.iterdir()}


GOOD_BIN = _binary(*_model())
BIN_READERS = {"cameras.bin": colmap.read_cameras_binary, "images.bin": colmap.read_images_binary,
               "points3D.bin": colmap.read_points3d_binary}
TEXT_READERS = {"cameras.txt": colmap.read_cameras_text, "images.txt": colmap.read_images_text,
                "points3D.txt": colmap.read_points3d_text}


def _check_colmap_result(name: str, result) -> None:
    """A read that succeeded holds what the checks promise: finite poses and points, known models, sizes > 0."""
    if isinstance(result, SsgwarpError):
        return
    if name.startswith("cameras"):
        for c in result.values():
            assert c.width > 0 and c.height > 0 and np.isfinite(c.params).all()
    elif name.startswith("images"):
        for im in result.values():
            assert np.isfinite(im.qvec).all() and np.isfinite(im.tvec).all() and im.name
            assert np.isfinite(im.R).all()
    else:
        assert np.isfinite(result.xyz).all() and len(result.ids) == len(result.xyz)


@pytest.mark.parametrize("name", list(BIN_READERS))
def test_fuzz_colmap_binary(name, tmp_dir):
    read = BIN_READERS[name]
    assert len(read(_write(tmp_dir / name, GOOD_BIN[name]))) > 0       # the undamaged file reads

    @fuzz_settings(200)
    @given(data=binary_damage(GOOD_BIN[name]))
    def run(data):
        _check_colmap_result(name, check_reader(read, tmp_dir / name, data, name=f"COLMAP {name}"))

    run()


@pytest.mark.parametrize("name", list(TEXT_READERS))
def test_fuzz_colmap_text(name, tmp_dir, tmp_path_factory):
    good = _text(tmp_path_factory)[name]
    read = TEXT_READERS[name]
    assert len(read(_write(tmp_dir / name, good))) > 0

    @fuzz_settings(150)
    @given(data=text_damage(good.decode()))
    def run(data):
        _check_colmap_result(name, check_reader(read, tmp_dir / name, data, name=f"COLMAP {name}"))

    run()


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# ----------------------------------------------------------------------------- LLFF poses_bounds.npy
def _good_poses_bounds(tmp_dir) -> bytes:
    rng = np.random.default_rng(1)
    pb = np.zeros((3, 17))
    for i in range(3):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        pose = np.concatenate([q, rng.normal(size=(3, 1)), np.array([[378.0], [504.0], [400.0]])], axis=1)
        pb[i, :15] = pose.reshape(-1)
        pb[i, 15:] = (1.5, 20.0)
    p = tmp_dir / "good_pb.npy"
    np.save(p, pb)
    return p.read_bytes()


def test_fuzz_poses_bounds(tmp_dir):
    good = _good_poses_bounds(tmp_dir)
    assert read_poses_bounds(_write(tmp_dir / "poses_bounds.npy", good)).shape == (3, 17)

    @fuzz_settings(200)
    @given(data=binary_damage(good))
    def run(data):
        out = check_reader(read_poses_bounds, tmp_dir / "poses_bounds.npy", data, name="LLFF poses_bounds.npy")
        if not isinstance(out, SsgwarpError):
            assert out.dtype == np.float64 and out.shape[1] == 17 and np.isfinite(out).all()

    run()


# ----------------------------------------------------------------------------- transforms.json
def _good_transforms() -> str:
    rng = np.random.default_rng(2)
    frames = []
    for i in range(3):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = q, rng.normal(size=3)
        frames.append({"file_path": f"images/r_{i}.png", "transform_matrix": m.round(6).tolist(),
                       **({"fl_x": 40.0, "fl_y": 41.0, "w": 64, "h": 48} if i == 1 else {})})
    meta = {"camera_angle_x": 0.69, "k1": 0.01, "p1": 0.001, "cx": 32, "cy": 24, "w": 64, "h": 48,
            "camera_model": "OPENCV", "applied_transform": np.eye(4)[:3].tolist(), "frames": frames}
    # one token per line element: the text damages replace numbers, keys and brackets alike
    return json.dumps(meta, indent=1).replace(",", " , ").replace(":", " : ")


JSON_TOKENS = ("NaN", "Infinity", "-Infinity", "1e400", "-1", "0", "null", "true", "[]", "{}", '"x"', '""',
               "[[1]]", "99999999999999999999", "1.5", '"\\u0000"', "[", "}")


def test_fuzz_transforms(tmp_dir):
    root = tmp_dir / "nerf"
    root.mkdir(exist_ok=True)
    good = _good_transforms()
    assert len(read_transforms(_write(root / "transforms.json", good.encode()).parent)) == 3

    @fuzz_settings(200)
    @given(data=text_damage(good, tokens=JSON_TOKENS))
    def run(data):
        out = check_reader(lambda p: read_transforms(p.parent), root / "transforms.json", data,
                           name="transforms.json")
        if not isinstance(out, SsgwarpError):
            for fr in out:
                assert np.isfinite(fr["c2w"]).all() and fr["c2w"].shape == (3, 4)

    run()


# ----------------------------------------------------------------------------- --config
_PARSERS: dict = {}


def _parser(command: str) -> argparse.ArgumentParser:
    """The command's parser as ``ssgwarp`` builds it, built once; its defaults restored on every call (each
    case's ``--config`` sets them)."""
    import importlib

    from ssgwarp.cli import COMMANDS, add_common, build_parser

    if command not in _PARSERS:
        _, subs = build_parser()
        importlib.import_module(COMMANDS[command][0]).add_arguments(subs[command])
        add_common(subs[command])
        p = subs[command]
        _PARSERS[command] = (p, {a.dest: a.default for a in p._actions}, dict(p._defaults))
    p, defaults, extra = _PARSERS[command]
    for a in p._actions:
        a.default = defaults[a.dest]
    p._defaults = dict(extra)
    return p


CONFIG_COMMANDS = {"reconstruct": ["DATA", "--out", "RUN"], "stylize": ["RUN", "--style", "S.png", "--out", "O"],
                   "render": ["RUN", "--out", "O"]}
_JSON = st.recursive(st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=True)
                     | st.text(max_size=8), lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=4), c,
                                                                                               max_size=3), max_leaves=6)


def _apply_and_parse(command: str, path: Path):
    from ssgwarp.cli import _apply_config

    parser = _parser(command)
    argv = [command, *CONFIG_COMMANDS[command], "--config", str(path)]
    _apply_config(parser, argv)
    return parser, parser.parse_args(argv[1:])


@pytest.mark.parametrize("command", list(CONFIG_COMMANDS))
def test_fuzz_config_values(command, tmp_dir):
    """Any JSON value under any option's name: refused in one line, or parsed to what the option takes."""
    parser = _parser(command)
    dests = sorted({a.dest for a in parser._actions if a.dest not in ("help", "config")} - {"_module"})
    types = {a.dest: a for a in parser._actions}
    path = tmp_dir / f"{command}.json"

    @fuzz_settings(60)
    @given(cfg=st.dictionaries(st.sampled_from(dests), _JSON, min_size=1, max_size=4))
    def run(cfg):
        data = json.dumps(cfg).encode()
        out = check_reader(lambda p: _apply_and_parse(command, p), path, data, name=f"--config ({command})")
        if isinstance(out, SsgwarpError):
            return
        args = out[1]
        for k in cfg:
            act, v = types[k], getattr(args, k)
            if act.nargs == 0:
                assert isinstance(v, bool), (k, v)
            elif v is not None and act.type in (int, float) and not isinstance(v, list):
                assert isinstance(v, act.type), (k, v)
            if act.choices is not None and v is not None and not isinstance(v, list):
                assert v in act.choices, (k, v)

    run()


def test_fuzz_config_bytes(tmp_dir):
    good = json.dumps({"iters": 3000, "sh_degree": 2, "quick": True, "width": 252, "strategy": "mcmc"})

    @fuzz_settings(100)
    @given(data=text_damage(good.replace(",", " , ").replace(":", " : "), tokens=JSON_TOKENS))
    def run(data):
        check_reader(lambda p: _apply_and_parse("reconstruct", p), tmp_dir / "cfg.json", data, name="--config (bytes)")

    run()


# ----------------------------------------------------------------------------- images
def _good_image(tmp_dir, ext: str, channels: int = 3) -> bytes:
    from ssgwarp.core.fileio import write_image

    img = np.random.default_rng(3).random((20, 24, channels)).astype(np.float32)
    return write_image(tmp_dir / f"good.{ext}", img).read_bytes()


@pytest.mark.parametrize("ext", ["png", "jpg"])
def test_fuzz_images(ext, tmp_dir):
    from ssgwarp.core.fileio import read_image

    good = _good_image(tmp_dir, ext)

    @fuzz_settings(100)
    @given(data=binary_damage(good))
    def run(data):
        out = check_reader(lambda p: read_image(p, 3), tmp_dir / f"img.{ext}", data, name=f"image (.{ext})",
                           alloc_factor=64)
        if not isinstance(out, SsgwarpError):
            assert out.ndim == 3 and out.shape[2] == 3 and out.dtype == np.float32

    run()


def test_fuzz_mask_images(tmp_dir):
    from ssgwarp.core.fileio import write_image
    from ssgwarp.grouping.mask_files import read_id_image

    ids = np.zeros((20, 24, 1), np.float32)
    ids[:, 12:] = 3 / 255
    good = write_image(tmp_dir / "good_mask.png", ids).read_bytes()

    @fuzz_settings(100)
    @given(data=binary_damage(good))
    def run(data):
        out = check_reader(read_id_image, tmp_dir / "mask.png", data, name="mask image (.png)", alloc_factor=64)
        if not isinstance(out, SsgwarpError):
            assert out.ndim == 2 and out.dtype == np.int64

    run()


def test_fuzz_check_reader_catches_what_it_should(tmp_dir):
    """The helper itself: a reader that raises a non-user error, or allocates far beyond the file, fails."""
    p = tmp_dir / "x.bin"
    with pytest.raises(IndexError):
        check_reader(lambda path: [][0], p, b"abc")
    with pytest.raises(AssertionError, match="allocated"):
        check_reader(lambda path: np.ones(10_000_000), p, b"abc", alloc_slack=1 << 20)
    assert isinstance(check_reader(lambda path: (_ for _ in ()).throw(InputError(f"{path}: bad")), p, b"a"),
                      InputError)
