"""Splats without their capture (issue 61): any splat file into ``render``, ``stylize``, ``import``, ``view``;
cameras made around the splats (:mod:`ssgwarp.capture.orbit`); ``render --video``; ``ssgwarp --version``."""
from __future__ import annotations

import json
import math
import shutil
from importlib.metadata import version as package_version
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from ssgwarp import procedural as P
from ssgwarp.capture.orbit import fit_splats, orbit_cameras, parse_up
from ssgwarp.formats.ply import read_ply, write_ply
from ssgwarp.formats.registry import write_scene
from ssgwarp.formats.registry import is_splat_file, read_splat_file
from ssgwarp.cli import main
from ssgwarp.core.fileio import read_image, write_image
from ssgwarp.core.geometry import project
from ssgwarp.core.imaging import mp4_writer_missing, write_video
from ssgwarp.errors import InputError
from ssgwarp.raster.scene import GaussianScene

FAST = ["--device", "cpu", "--seed", "0"]


@pytest.fixture(scope="module")
def demo():
    """The demo's procedural scene at a small density (z up, objects standing on a ground disc)."""
    return P.build_scene(0.25).scene


def _rotation(axis, deg: float) -> torch.Tensor:
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    k = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    t = math.radians(deg)
    return torch.eye(3, dtype=torch.float64) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def _moved(scene: GaussianScene, R: torch.Tensor, t) -> GaussianScene:
    from ssgwarp.core.geometry import quat_to_rotmat, rotmat_to_quat

    means = (scene.means.double() @ R.T + torch.tensor(t, dtype=torch.float64)).float()
    quats = rotmat_to_quat(R[None] @ quat_to_rotmat(scene.quats.double())).float()
    return scene.replace(means=means, quats=quats)


def _with_outliers(scene: GaussianScene, n: int, radius: float, opacity: float, seed: int = 0) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1) * radius
    extra = GaussianScene(d, torch.full((n, 3), -2.0), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                          torch.full((n,), math.log(opacity / (1 - opacity))), torch.zeros(n, 3))
    cat = lambda a, b: torch.cat([a, b])  # noqa: E731
    return GaussianScene(cat(scene.means, extra.means), cat(scene.log_scales, extra.log_scales),
                         cat(scene.quats, extra.quats), cat(scene.logit_opacities, extra.logit_opacities),
                         cat(scene.sh_dc, extra.sh_dc))


# ----------------------------------------------------------------------------- the fit
def test_fit_finds_up_centre_and_extent_despite_outliers(demo):
    """A tilted, shifted ground-plane scene with 3 % far floaters (opaque) and 20 % faint splats: up is the
    ground's normal on the side the objects stand, the centre and extent are the scene's, not the floaters'."""
    R = _rotation((1.0, 2.0, 0.5), 37.0)
    t = (3.0, -1.0, 2.0)
    n = len(demo)
    noisy = _with_outliers(_with_outliers(demo, int(0.03 * n), 60.0, 0.9), int(0.2 * n), 30.0, 0.01, seed=1)
    fit = fit_splats(_moved(noisy, R, t))
    true_up = R @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    assert float(torch.from_numpy(fit.up) @ true_up) > math.cos(math.radians(6)), fit.record()
    assert "plane holding" in fit.up_rule and "stand out" in fit.up_rule
    clean = fit_splats(_moved(demo, R, t))
    assert np.linalg.norm(fit.centre - clean.centre) < 0.1           # the floaters do not pull the centre
    assert np.allclose(fit.half_extent[:2], clean.half_extent[:2], rtol=0.1)
    assert 1.7 < fit.half_extent[0] < 2.4 and fit.half_extent[2] < 0.6   # the ground disc: radius 2.2
    assert fit.kept < fit.total * 0.97 and fit.record()["inliers"] == fit.kept
    # an up within a few degrees of a file axis is that axis
    snapped = fit_splats(demo)
    assert np.allclose(snapped.up, [0, 0, 1]) and "snapped" in snapped.up_rule


def test_up_upside_down_scene_and_the_file_convention(demo):
    flipped = fit_splats(_moved(demo, _rotation((1.0, 0.0, 0.0), 180.0), (0, 0, 0)))
    assert np.allclose(flipped.up, [0, 0, -1])                       # the objects still stand "up"
    # the same scene in the OpenCV / COLMAP convention (its up along -y): the ground faces y, its -y side is up
    cv = fit_splats(_moved(demo, _rotation((1.0, 0.0, 0.0), 90.0), (0, 0, 0)))
    assert np.allclose(cv.up, [0, -1, 0]) and "-y side" in cv.up_rule
    # a wall beside the ground holding fewer splats does not change which plane is the ground
    wall = _moved(demo, _rotation((0.0, 1.0, 0.0), 90.0), (2.5, 0.0, 2.2))   # standing on the ground
    keep = wall.means[:, 0] > 2.45                                    # the turned ground disc only: a wall at x=2.5
    w = GaussianScene(wall.means[keep][::2], wall.log_scales[keep][::2], wall.quats[keep][::2],
                      wall.logit_opacities[keep][::2], wall.sh_dc[keep][::2])
    both = GaussianScene(*(torch.cat([a, b]) for a, b in zip(
        (demo.means, demo.log_scales, demo.quats, demo.logit_opacities, demo.sh_dc),
        (w.means, w.log_scales, w.quats, w.logit_opacities, w.sh_dc))))
    assert np.allclose(fit_splats(both).up, [0, 0, 1])
    # a ball (no layer): the file's -y, the OpenCV / COLMAP convention
    g = torch.Generator().manual_seed(0)
    ball = GaussianScene(torch.randn(500, 3, generator=g), torch.full((500, 3), -3.0),
                         torch.tensor([[1.0, 0, 0, 0]]).repeat(500, 1), torch.full((500,), 3.0), torch.zeros(500, 3))
    fit = fit_splats(ball)
    assert np.allclose(fit.up, [0, -1, 0]) and "-y" in fit.up_rule
    assert np.allclose(fit_splats(ball, up=parse_up("+x")).up, [1, 0, 0])


def test_parse_up():
    assert np.allclose(parse_up("-z"), [0, 0, -1]) and np.allclose(parse_up("y"), [0, 1, 0])
    assert np.allclose(parse_up("0,3,4"), [0, 0.6, 0.8]) and parse_up("auto") is None and parse_up(None) is None
    for bad in ("up", "1,2", "0,0,0", "+w"):
        with pytest.raises(InputError, match="--up"):
            parse_up(bad)


def test_orbit_cameras_look_at_the_splats_and_fill_the_frame(demo):
    fit = fit_splats(_moved(demo, _rotation((0.3, 1.0, 0.2), 50.0), (1.0, 2.0, 3.0)))
    cams, rec = orbit_cameras(fit, 12, max_width=400)
    assert len(cams) == 12 and cams.width == rec["width"] and cams.width % 2 == 0 and cams.height % 2 == 0
    # the width: at most the splats' own resolution (the median splat one pixel across), below the cap
    assert cams.width <= min(400, rec["native_width"]) + 1 and 1.0 <= rec["aspect"] <= 16 / 9
    centres = cams.camtoworlds[:, :3, 3].double()
    dist = (centres - torch.from_numpy(fit.centre)).norm(dim=1)
    assert torch.allclose(dist, torch.full_like(dist, rec["distance"]), rtol=1e-5)     # one distance
    pts = torch.from_numpy(fit.points)
    filled = []
    for i in range(len(cams)):
        uv, z = project(pts, cams.viewmats[i].double(), cams.Ks[i].double())
        assert bool((z > 0).all())
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < cams.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cams.height)
        assert float(inside.double().mean()) > 0.99
        c, _ = project(torch.from_numpy(fit.centre)[None], cams.viewmats[i].double(), cams.Ks[i].double())
        assert torch.allclose(c[0], torch.tensor([cams.width / 2, cams.height / 2], dtype=torch.float64), atol=1e-3)
        half = torch.tensor([cams.width / 2, cams.height / 2], dtype=torch.float64)
        reach = ((uv - half).abs() / half).max(dim=1).values          # 1: at the frame's edge
        filled.append(float(torch.quantile(reach, 0.995)))
    # the splats fill the frame: the farthest of them reach the 0.9 of the frame the orbit leaves them
    assert max(filled) == pytest.approx(0.9, abs=0.05) and min(filled) > 0.5, filled
    # up is up in every view: the objects above the ground project above its centre
    up_pt = torch.from_numpy(fit.centre + fit.up)[None]
    for i in range(len(cams)):
        a, _ = project(up_pt, cams.viewmats[i].double(), cams.Ks[i].double())
        assert float(a[0, 1]) < cams.height / 2
    with pytest.raises(InputError):
        orbit_cameras(fit, 0)


# ----------------------------------------------------------------------------- any splat file in
FORMATS = {"ply": "s.ply", "compressed-ply": "s.compressed.ply", "spz": "s.spz", "splat": "s.splat"}


@pytest.fixture(scope="module")
def files(demo, tmp_path_factory):
    d = tmp_path_factory.mktemp("splat_files")
    return {fmt: write_scene(d / name, demo, fmt) for fmt, name in FORMATS.items()}


def test_every_format_reads_through_one_helper(files, demo, tmp_path):
    for fmt, path in files.items():
        assert is_splat_file(path), fmt
        scene = read_splat_file(path)
        assert len(scene) == len(demo)
        # (compressed PLY reorders the splats): every splat read back lies where one was written
        assert float(torch.cdist(scene.means, demo.means).min(dim=1).values.max()) < 0.01, fmt
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a splat file")
    assert not is_splat_file(bad) and not is_splat_file(tmp_path)
    with pytest.raises(InputError, match="bad.ply"):
        read_splat_file(bad)
    with pytest.raises(InputError, match="not found"):
        read_splat_file(tmp_path / "missing.spz")


def test_render_a_splat_file_along_its_orbit_with_a_video(files, tmp_path, capsys):
    for fmt in ("spz", "compressed-ply"):
        out = tmp_path / fmt
        assert main(["render", str(files[fmt]), "--out", str(out), "--path", "5", "--width", "48", "--video",
                     "--quiet", *FAST]) == 0, capsys.readouterr().err
        said = capsys.readouterr().out
        assert "orbit made around the splats" in said and "path.gif" in said
        frames = sorted(out.glob("frame_*.png"))
        assert len(frames) == 5
        img = read_image(frames[0], 3)
        # the scene is in the frame: its centre is covered, its corners are the white background
        h, w = img.shape[:2]
        assert img[h // 2 - 2:h // 2 + 2, w // 2 - 2:w // 2 + 2].mean() < 0.9
        assert img[0, 0].min() > 0.99 and img[-1, -1].min() > 0.99
        with Image.open(out / "path.gif") as gif:
            assert gif.n_frames == 5 and gif.size == (w, h)
        orbit = json.loads((out / "orbit.json").read_text())
        assert orbit["cameras"]["views"] == 5 and orbit["fit"]["splats"] == len(read_splat_file(files[fmt]))
        assert (out / "path_cameras.json").is_file()
    # without --path: --views cameras named after the orbit
    out = tmp_path / "views"
    assert main(["render", str(files["splat"]), "--out", str(out), "--views", "3", "--width", "32", "--quiet",
                 *FAST]) == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["orbit_000.png", "orbit_001.png", "orbit_002.png"]


def test_render_video_options_fail_in_one_line(files, tmp_path, capsys):
    assert main(["render", str(files["ply"]), "--out", str(tmp_path / "a"), "--video", "clip.avi", *FAST]) == 2
    assert ".gif or .mp4" in capsys.readouterr().err and not (tmp_path / "a").exists()
    if mp4_writer_missing():
        assert main(["render", str(files["ply"]), "--out", str(tmp_path / "b"), "--video", "c.mp4", *FAST]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "imageio-ffmpeg" in err and not (tmp_path / "b").exists()
    assert main(["render", str(files["ply"]), "--out", str(tmp_path / "c"), "--up", "sideways", *FAST]) == 2
    assert "--up sideways" in capsys.readouterr().err


def test_write_video_gif_and_mp4(tmp_path):
    frames = [np.full((10, 14, 3), 40 * i, np.uint8) for i in range(4)]
    with Image.open(write_video(tmp_path / "v.gif", frames, fps=10)) as im:
        assert im.n_frames == 4 and im.size == (14, 10) and im.info["duration"] == 100
    if mp4_writer_missing():
        with pytest.raises(InputError, match="imageio-ffmpeg"):
            write_video(tmp_path / "v.mp4", frames)
        assert not (tmp_path / "v.mp4").exists()
    else:
        assert write_video(tmp_path / "v.mp4", frames).stat().st_size > 0
    with pytest.raises(InputError, match=".gif or .mp4"):
        write_video(tmp_path / "v.avi", frames)


def test_view_reads_any_splat_file(files, demo):
    from ssgwarp.viewer.data import load_scene

    for fmt in ("spz", "splat", "compressed-ply"):
        assert len(load_scene(files[fmt])) == len(demo)


def test_import_a_splat_file_without_its_capture(files, demo, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["import", str(files["spz"]), "--out", str(run), "--views", "6", "--width", "40", "--quiet",
                 *FAST]) == 0
    assert "no capture" in json.loads((run / "metrics.json").read_text())["note"]
    data = json.loads((run / "data.json").read_text())
    assert data["format"] == "orbit" and len(data["split"]["train"]) == 6 and data["split"]["test"] == []
    assert data["orbit"]["source"] == str(files["spz"].resolve()) and data["orbit"]["cameras"]["width"] == 40
    assert len(read_ply(run / "scene.ply")) == len(demo)
    assert main(["render", str(run), "--out", str(tmp_path / "r"), "--quiet", *FAST]) == 0
    assert len(list((tmp_path / "r").glob("orbit_*.png"))) == 6
    # a run folder's smooth path as a video too
    assert main(["render", str(run), "--out", str(tmp_path / "p"), "--path", "3", "--video", "loop.gif", "--quiet",
                 *FAST]) == 0
    with Image.open(tmp_path / "p" / "loop.gif") as gif:
        assert gif.n_frames == 3


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"ssgwarp {package_version('ssgwarp')}"


@pytest.mark.slow
def test_a_scene_ply_alone_in_an_empty_folder_stylizes(demo, tmp_path, monkeypatch, capsys):
    """The issue's target: a scene's scene.ply copied alone into an empty folder stylizes with --quick, its
    renders written; the groups (mask-free), Stage 1 (skipped: no weights) and Stage 2 run on the made views."""
    src = tmp_path / "somewhere" / "scene.ply"
    write_ply(src, demo)
    folder = tmp_path / "empty"
    folder.mkdir()
    shutil.copy(src, folder / "scene.ply")
    write_image(tmp_path / "style.png", torch.from_numpy(P.style_image(32, 32)))
    monkeypatch.chdir(folder)
    args = ["stylize", "scene.ply", "--style", str(tmp_path / "style.png"), "--out", "out", "--quick",
            "--views", "4", "--width", "40", "--iters", "2", "--group-iters", "5", "--path-frames", "3",
            "--keyviews", "2", "--max-side", "40", "--offline", "--quiet", *FAST]
    assert main(args) == 0, capsys.readouterr().err
    out = folder / "out"
    assert sorted(p.name for p in (out / "renders" / "train").glob("*.png")) == [f"orbit_{i:03d}.png"
                                                                               for i in range(4)]
    assert len(list((out / "renders" / "path").glob("*.png"))) == 3 and (out / "path.gif").is_file()
    m = json.loads((out / "metrics.json").read_text())
    assert m["splat_file"] == str((folder / "scene.ply").resolve()) and m["orbit"]["cameras"]["views"] == 4
    assert m["groups"] and m["groups"] >= 1 and m["stage1"]["ran"] is False
    assert (out / "source" / "groups" / "groups.json").is_file()
    assert json.loads((out / "source" / "groups" / "groups.json").read_text())["kind"] == "mask-free clusters"
    assert len(read_ply(out / "scene.ply")) == len(demo)
    assert read_image(out / "renders" / "train" / "orbit_000.png", 3).min() < 0.9      # the scene is in view
    assert sorted(p.name for p in folder.iterdir()) == ["out", "scene.ply"]
    # an existing output is refused, --resume keeps the made run
    assert main(args) == 2 and "--force" in capsys.readouterr().err
    assert main([*args, "--resume"]) == 0
    # the stylized run renders as any stylize output
    assert main(["render", "out", "--out", "r", "--quiet", *FAST]) == 0
    assert len(list((folder / "r").glob("*.png"))) == 4
