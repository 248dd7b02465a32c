"""``ssgwarp import``: splats of graphdeco 3DGS, gsplat, nerfstudio and bare PLYs as ssgwarp runs.

Each source layout is written here as the tool writes it (field names and order, activations, SH
layout, camera records, frames) from a small scene with view-dependent colour (SH degree 3), in the
frame the tool trains in; the imported run must re-render the capture's views as the original scene
does (within 1e-4), and a PLY in another frame than the capture's must be refused in one line.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from ssgwarp import procedural as P
from ssgwarp.formats.colmap import ColmapCamera, ColmapImage, ColmapPoints, rotmat_to_qvec, write_model_text
from ssgwarp.formats.ply import read_ply
from ssgwarp.core.frames import Similarity, rotate_sh, sh_rotation, umeyama
from ssgwarp.formats.layouts import gsplat_normalization, parse_cfg_args, transform_scene
from ssgwarp.cli import main
from ssgwarp.core.cameras import Cameras
from ssgwarp.core.fileio import write_image
from ssgwarp.errors import InputError
from ssgwarp.raster.rendering import render_views
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.core.sh import spherical_harmonics
from ssgwarp.reconstruction.importer import ImportConfig, import_splats
from ssgwarp.services.runs import Run

FAST = ["--device", "cpu", "--seed", "0", "--quiet"]
W, H, VIEWS = 40, 30, 8


def _rotation(seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.fixture(scope="module")
def world():
    """The scene (capture frame; random Gaussians of moderate size and SH degree 3: renders free of the
    rasterizer's thresholds flipping under float32 rounding), its cameras, its renders on white and black."""
    g = torch.Generator().manual_seed(0)
    n = 400
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * torch.tensor([1.2, 1.2, 0.6]) + torch.tensor([0.0, 0.0, 0.4])
    scene = GaussianScene(means, torch.log(0.04 + 0.12 * torch.rand(n, 3, generator=g)),
                          torch.nn.functional.normalize(torch.randn(n, 4, generator=g)), 1.5 * torch.randn(n, generator=g),
                          0.8 * torch.randn(n, 3, generator=g), 0.25 * torch.randn(n, 15, 3, generator=g), None, 3)
    cams = P.ring_cameras(VIEWS, W, H, names=[f"view_{i:02d}" for i in range(VIEWS)])
    white = render_views(scene, cams, (1.0, 1.0, 1.0), depth=False).rgb
    black = render_views(scene, cams, (0.0, 0.0, 0.0), depth=False).rgb
    return dict(scene=scene, cams=cams, white=white, black=black)


def _assert_renders(run_dir: Path, world, background="white", tol=1e-4):
    run = Run.reconstruction(run_dir)
    scene = read_ply(run_dir / "scene.ply")
    cams = run.cameras
    order = [cams.names.index(n) for n in world["cams"].names] if cams.names[0] in world["cams"].names else \
        [[Path(c).stem for c in cams.names].index(n) for n in world["cams"].names]
    bg = (1.0, 1.0, 1.0) if background == "white" else (0.0, 0.0, 0.0)
    got = render_views(scene, cams[order], bg, depth=False).rgb
    diff = float((got - world[background]).abs().max())
    assert diff <= tol, f"imported renders differ by {diff:.2e}"
    return json.loads((run_dir / "metrics.json").read_text())


# ----------------------------------------------------------------------------- writers of the tools' files
def _inria_ply(path: Path, scene, normals: bool = True) -> None:
    """The INRIA layout: x y z [nx ny nz] f_dc_0..2 f_rest_* (channel-major) opacity scale_0..2 rot_0..3."""
    n, k = len(scene), scene.sh_rest.shape[1]
    cols = [("x", scene.means[:, 0]), ("y", scene.means[:, 1]), ("z", scene.means[:, 2])]
    if normals:
        cols += [(c, torch.zeros(n)) for c in ("nx", "ny", "nz")]
    cols += [(f"f_dc_{c}", scene.sh_dc[:, c]) for c in range(3)]
    rest = scene.sh_rest.transpose(1, 2).reshape(n, 3 * k)         # [N, K, 3] -> [N, 3, K] -> [N, 3K]
    cols += [(f"f_rest_{i}", rest[:, i]) for i in range(3 * k)]
    cols += [("opacity", scene.logit_opacities)] + [(f"scale_{i}", scene.log_scales[:, i]) for i in range(3)]
    cols += [(f"rot_{i}", scene.quats[:, i]) for i in range(4)]
    arr = np.empty(n, dtype=[(c, "<f4") for c, _ in cols])
    for c, v in cols:
        arr[c] = v.detach().float().numpy()
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))


def _colmap_capture(root: Path, world, background: str = "white", n_points: int = 400) -> Path:
    cams = world["cams"]
    K = cams.Ks[0].double().numpy()
    ccams = {1: ColmapCamera(1, "PINHOLE", W, H, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))}
    ims = {}
    for i, name in enumerate(cams.names):
        vm = cams.viewmats[i].double().numpy()
        ims[i + 1] = ColmapImage(i + 1, rotmat_to_qvec(vm[:3, :3]), vm[:3, 3], 1, f"{name}.png")
        write_image(root / "images" / f"{name}.png", world[background][i])
    xyz = world["scene"].means[:: max(1, len(world["scene"]) // n_points)].double().numpy()
    m = len(xyz)
    write_model_text(root / "sparse" / "0", ccams, ims, ColmapPoints(np.arange(1, m + 1), xyz,
                     np.full((m, 3), 128, np.uint8), np.zeros(m), np.full(m, 2, np.int64)))
    return root


def _graphdeco_output(folder: Path, scene, cams: Cameras, source_path: str, iterations=(7000, 30000),
                      white: bool = False, eval_: bool = True) -> None:
    for it in iterations:                                   # the last iteration holds the scene, earlier ones noise
        s = scene if it == max(iterations) else scene.replace(means=scene.means + 5.0)
        _inria_ply(folder / "point_cloud" / f"iteration_{it}" / "point_cloud.ply", s)
    c2w = cams.camtoworlds.double()
    entries = [{"id": i, "img_name": name, "width": cams.width, "height": cams.height,
                "position": c2w[i, :3, 3].tolist(), "rotation": [r.tolist() for r in c2w[i, :3, :3]],
                "fy": float(cams.Ks[i, 1, 1]), "fx": float(cams.Ks[i, 0, 0])}
               for i, name in enumerate(cams.names)]
    (folder / "cameras.json").write_text(json.dumps(entries))
    (folder / "cfg_args").write_text(
        f"Namespace(data_device='cuda', depths='', eval={eval_}, images='images', model_path='{folder}', "
        f"resolution=-1, sh_degree=3, source_path='{source_path}', train_test_exp=False, "
        f"white_background={white})")


# ----------------------------------------------------------------------------- the maths
def test_sh_rotation_matches_rotating_the_view_direction():
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(50, 16, 3, generator=g, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=1)
    for seed in range(3):
        R = _rotation(seed)
        rest = rotate_sh(coeffs[:, 1:], R, 3)
        new = torch.cat([coeffs[:, :1], rest], 1)
        seen_new = spherical_harmonics(3, dirs @ torch.from_numpy(R).T, new)     # along R d
        seen_old = spherical_harmonics(3, dirs, coeffs)                           # along d
        assert torch.allclose(seen_new, seen_old, atol=1e-10)
    # the band matrices are orthogonal and the identity for R = I
    for B in sh_rotation(_rotation(5), 3):
        assert torch.allclose(B @ B.T, torch.eye(B.shape[0], dtype=B.dtype), atol=1e-10)
    for B in sh_rotation(np.eye(3), 3):
        assert torch.allclose(B, torch.eye(B.shape[0], dtype=B.dtype), atol=1e-12)


def test_transform_scene_renders_the_same_from_moved_cameras(world):
    sim = Similarity(0.37, _rotation(3), np.array([1.0, -2.0, 0.5]))
    moved = transform_scene(world["scene"], sim)
    got = render_views(moved, sim.cameras(world["cams"]), (1.0, 1.0, 1.0), depth=False).rgb
    assert float((got - world["white"]).abs().max()) < 1e-4
    back = transform_scene(moved, sim.inverse())
    assert torch.allclose(back.means, world["scene"].means, atol=1e-5)
    assert torch.allclose(back.log_scales, world["scene"].log_scales, atol=1e-5)
    with pytest.raises(InputError, match="proper rotation"):
        Similarity(1.0, np.diag([1.0, 1.0, -1.0]))


def test_umeyama_recovers_a_similarity():
    x = np.random.default_rng(0).normal(size=(10, 3))
    sim = Similarity(2.5, _rotation(7), np.array([0.3, 4.0, -1.0]))
    fit = umeyama(x, sim.points(x))
    assert np.allclose(fit.matrix, sim.matrix, atol=1e-9)


def test_gsplat_normalization_frames(world):
    c2w = world["cams"].camtoworlds.double().numpy()
    pts = world["scene"].means.double().numpy()
    cands = gsplat_normalization(c2w, pts)
    assert len(cands) == 4 and len({tuple(np.round(s.matrix, 6).ravel()) for _, s in cands}) == 4
    for _, sim in cands:
        p = sim.points(pts.astype(np.float32).astype(np.float64))
        cov = np.cov(p, rowvar=False)
        assert np.allclose(cov - np.diag(np.diag(cov)), 0.0, atol=1e-9)          # principal axes are x, y, z
        assert cov[0, 0] >= cov[1, 1] >= cov[2, 2]                               # largest variance first
    p0 = cands[0][1].points(pts.astype(np.float32).astype(np.float64))
    assert np.median(p0[:, 2]) <= np.mean(p0[:, 2])                               # gsplat's own up-side rule
    # the cameras' scale: the median camera distance to the focus point is 1 before the rigid step
    centres = cands[0][1].points(c2w[:, :3, 3])
    assert 0.2 < np.median(np.linalg.norm(centres - centres.mean(0), axis=1)) < 5.0


# gsplat's own examples/datasets normalize.py (similarity_from_cameras, align_principal_axes, the up-side flip)
# on the colmap_cup capture, computed with gsplat's code: the 3x4 of its Parser.transform
GSPLAT_CUP_TRANSFORM = [[-0.209281085006, 0.070726499876, 0.078485432773, 0.278196181161],
                        [-0.035840754733, -0.211356455707, 0.094892899706, 0.276727871555],
                        [0.099386323217, 0.072711651952, 0.199489718811, -0.961754656069]]


def test_gsplat_normalization_matches_gsplats_parser_on_a_real_capture(shared_data):
    from ssgwarp.formats.colmap import read_model
    model = read_model(shared_data / "colmap_cup" / "sparse" / "0")
    ims = sorted(model.images.values(), key=lambda im: im.name)
    c2w = np.linalg.inv(np.stack([im.viewmat for im in ims]))
    first = gsplat_normalization(c2w, model.points.xyz)[0][1]
    assert np.allclose(first.matrix[:3], GSPLAT_CUP_TRANSFORM, atol=1e-9)


def test_graphdeco_resolution_rule():
    from ssgwarp.reconstruction.importer import _graphdeco_width
    assert _graphdeco_width(-1, 1000) is None and _graphdeco_width(-1, 3200) == 1600      # > 1.6K: to 1600 wide
    assert _graphdeco_width(-1, 1601) == 1599          # (graphdeco truncates 1601 / (1601 / 1600) = 1599.99...)
    assert _graphdeco_width(4, 1001) == 250 and _graphdeco_width(2, 800) == 400
    assert _graphdeco_width(640, 3200) == 640 and _graphdeco_width(None, 500) is None


def test_cfg_args_parse():
    cfg = parse_cfg_args("Namespace(eval=True, images='images_4', resolution=2, source_path='/d/x', "
                         "white_background=False, sh_degree=3)")
    assert cfg == {"eval": True, "images": "images_4", "resolution": 2, "source_path": "/d/x",
                   "white_background": False, "sh_degree": 3}
    with pytest.raises(InputError):
        parse_cfg_args("{'eval': True}")


# ----------------------------------------------------------------------------- the layouts
def test_graphdeco_output_folder(world, tmp_path):
    cap = _colmap_capture(tmp_path / "cap", world, background="black")
    src = tmp_path / "output" / "abc"
    _graphdeco_output(src, world["scene"], world["cams"], str(cap))
    m = import_splats(src, tmp_path / "run", device="cpu", progress=False)
    _assert_renders(tmp_path / "run", world, "black")
    assert m["imported"]["iteration"] == 30000 and m["imported"]["frame"] == "the capture's own frame"
    assert m["test_views"] == 1 and m["psnr"] > 35 and m["train_psnr"] > 35      # graphdeco --eval: every 8th
    data = json.loads((tmp_path / "run" / "data.json").read_text())
    assert data["background"] == [0.0, 0.0, 0.0] and data["split"]["test"] == ["view_00.png"]
    # --iteration picks another one (which here renders nothing like the capture: refused)
    with pytest.raises(InputError, match="do not match"):
        import_splats(src, tmp_path / "run7", ImportConfig(iteration=7000), device="cpu", progress=False)
    assert not (tmp_path / "run7").exists()
    with pytest.raises(InputError, match="no iteration 5"):
        import_splats(src, tmp_path / "run5", ImportConfig(iteration=5), device="cpu", progress=False)


def test_graphdeco_without_its_capture_keeps_the_cameras(world, tmp_path, caplog):
    src = tmp_path / "out"
    _graphdeco_output(src, world["scene"], world["cams"], str(tmp_path / "moved-away"), eval_=False)
    m = import_splats(src, tmp_path / "run", device="cpu", progress=False)
    assert m["psnr"] is None and "no images" in m["note"]
    _assert_renders(tmp_path / "run", world, "black")
    data = json.loads((tmp_path / "run" / "data.json").read_text())
    assert data["data_dir"] is None and data["split"]["test"] == []
    assert main(["render", str(tmp_path / "run"), "--out", str(tmp_path / "renders"), "--no-progress",
                 "--device", "cpu"]) == 0
    assert len(list((tmp_path / "renders").glob("*.png"))) == VIEWS


def test_graphdeco_cameras_of_several_sizes(world, tmp_path):
    src = tmp_path / "out"
    _graphdeco_output(src, world["scene"], world["cams"], "/nowhere")
    cams = json.loads((src / "cameras.json").read_text())
    cams[1]["width"] = 2 * W
    (src / "cameras.json").write_text(json.dumps(cams))
    with pytest.raises(InputError, match="several sizes"):
        import_splats(src, tmp_path / "run", device="cpu", progress=False)
    cap = _colmap_capture(tmp_path / "cap", world, background="black")
    import_splats(src, tmp_path / "run", ImportConfig(data=cap), device="cpu", progress=False)
    _assert_renders(tmp_path / "run", world, "black")


def test_graphdeco_cameras_in_another_frame_are_aligned(world, tmp_path):
    """cameras.json from a capture in another frame than --data's: aligned by the camera centres."""
    cap = _colmap_capture(tmp_path / "cap", world, background="black")
    sim = Similarity(1.7, _rotation(11), np.array([0.5, 0.2, -3.0]))
    src = tmp_path / "out"
    _graphdeco_output(src, transform_scene(world["scene"], sim), sim.cameras(world["cams"]), "/nowhere")
    m = import_splats(src, tmp_path / "run", ImportConfig(data=cap), device="cpu", progress=False)
    assert m["imported"]["frame"].startswith("aligned by cameras.json")
    _assert_renders(tmp_path / "run", world, "black")


@pytest.mark.parametrize("frame", [0, 2])
def test_gsplat_checkpoint_in_its_normalised_world(world, tmp_path, frame):
    cap = _colmap_capture(tmp_path / "cap", world)
    from ssgwarp.formats.colmap import read_model
    model = read_model(cap / "sparse" / "0")
    ims = sorted(model.images.values(), key=lambda im: im.name)
    c2w = np.linalg.inv(np.stack([im.viewmat for im in ims]))
    _, norm = gsplat_normalization(c2w, model.points.xyz)[frame]    # (frame 2: other principal-axis signs)
    s = transform_scene(world["scene"], norm)
    res = tmp_path / "results"
    (res / "ckpts").mkdir(parents=True)
    for step in (999, 29999):
        splats = {"means": s.means + (0 if step == 29999 else 9.0), "scales": s.log_scales, "quats": s.quats,
                  "opacities": s.logit_opacities, "sh0": s.sh_dc[:, None, :], "shN": s.sh_rest}
        torch.save({"step": step, "splats": splats}, res / "ckpts" / f"ckpt_{step}_rank0.pt")
    (res / "cfg.yml").write_text(f"data_dir: {cap}\ndata_factor: 1\nnormalize_world_space: true\n"
                                 f"strategy: !!python/object:gsplat.strategy.DefaultStrategy\n  grow_grad2d: 0.0002\n"
                                 f"test_every: 8\n")
    m = import_splats(res, tmp_path / "run", device="cpu", progress=False)
    assert m["imported"]["step"] == 29999 and m["imported"]["frame"].startswith("gsplat's normalised world")
    _assert_renders(tmp_path / "run", world)
    # its PLY export (no normals) with --data: the same
    ply = tmp_path / "point_cloud_29999.ply"
    _inria_ply(ply, s, normals=False)
    import_splats(ply, tmp_path / "run2", ImportConfig(data=cap, tool="gsplat"), device="cpu", progress=False)
    _assert_renders(tmp_path / "run2", world)


def test_gsplat_checkpoint_needs_its_capture(world, tmp_path):
    s = world["scene"]
    p = tmp_path / "ckpt_10_rank0.pt"
    torch.save({"step": 10, "splats": {"means": s.means, "scales": s.log_scales, "quats": s.quats,
                                       "opacities": s.logit_opacities, "sh0": s.sh_dc[:, None]}}, p)
    with pytest.raises(InputError, match="--data"):
        import_splats(p, tmp_path / "run", device="cpu", progress=False)
    torch.save({"step": 10, "splats": {"means": s.means}}, p)
    with pytest.raises(InputError, match="lack quats"):
        import_splats(p, tmp_path / "run", ImportConfig(data=tmp_path), device="cpu", progress=False)


@pytest.mark.parametrize("applied", [False, True])
def test_nerfstudio_export_with_dataparser_transforms(world, tmp_path, applied):
    cap = tmp_path / "dataset"
    P.write_transforms_dataset(cap, world["white"], world["cams"])
    A = Similarity()
    if applied:        # ns-process-data's applied_transform: the transforms.json frame is A(original)
        meta = json.loads((cap / "transforms.json").read_text())
        meta["applied_transform"] = [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]
        meta["applied_scale"] = 2.0        # (nerfstudio folds it into the saved scale, not into the poses)
        (cap / "transforms.json").write_text(json.dumps(meta))
        A = Similarity.from_matrix(meta["applied_transform"])
    T, scale = Similarity(1.0, _rotation(4), np.array([0.1, -0.4, 0.3])), 0.42
    dp = Similarity(scale) @ T          # transforms.json frame -> splatfacto's (auto-orient and scale of the poses)
    out = tmp_path / "outputs" / "splatfacto" / "2024"
    out.mkdir(parents=True)
    saved = {"transform": (T @ A).matrix[:3].tolist(), "scale": scale * (2.0 if applied else 1.0)}
    (out / "dataparser_transforms.json").write_text(json.dumps(saved, indent=4))
    ply = tmp_path / "exports" / "splat.ply"
    _inria_ply(ply, transform_scene(world["scene"], dp))
    cfg = ImportConfig(data=cap, dataparser_transforms=out / "dataparser_transforms.json")
    m = import_splats(ply, tmp_path / "run", cfg, device="cpu", progress=False)
    assert m["imported"]["tool"] == "nerfstudio"
    _assert_renders(tmp_path / "run", world)
    # beside the PLY, it is found
    (ply.parent / "dataparser_transforms.json").write_text((out / "dataparser_transforms.json").read_text())
    import_splats(ply, tmp_path / "run2", ImportConfig(data=cap), device="cpu", progress=False)
    _assert_renders(tmp_path / "run2", world)


def test_nerfstudio_export_of_a_colmap_dataset(world, tmp_path):
    """nerfstudio's colmap dataparser: its saved transform takes COLMAP's frame to splatfacto's."""
    cap = _colmap_capture(tmp_path / "cap", world)
    A = Similarity.from_matrix([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])
    T, scale = Similarity(1.0, _rotation(8), np.array([0.2, 0.1, -0.3])), 0.3
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": (T @ A).matrix[:3].tolist(),
                                                                     "scale": scale}))
    ply = tmp_path / "splat.ply"
    _inria_ply(ply, transform_scene(world["scene"], Similarity(scale) @ T @ A))
    m = import_splats(ply, tmp_path / "run", ImportConfig(data=cap), device="cpu", progress=False)
    assert m["imported"]["frame"] == "nerfstudio's dataparser frame (COLMAP data)"
    _assert_renders(tmp_path / "run", world)


def test_bare_ply_aligned_and_mismatched(world, tmp_path, capsys):
    cap = tmp_path / "cap"
    P.write_transforms_dataset(cap, world["white"], world["cams"])
    ply = tmp_path / "splats.ply"
    _inria_ply(ply, world["scene"])
    assert main(["import", str(ply), "--data", str(cap), "--out", str(tmp_path / "run"), *FAST]) == 0
    m = _assert_renders(tmp_path / "run", world)
    assert m["psnr"] > 35 and m["imported"]["tool"] == "ply"
    # another frame: refused in one line, exit 2, nothing written
    for i, sim in enumerate([Similarity(1.0, np.eye(3), np.array([40.0, 0.0, 0.0])),     # outside every image
                             Similarity(0.8, _rotation(9), np.array([0.3, 0.0, 0.2]))]):  # renders something else
        bad = tmp_path / f"bad{i}.ply"
        _inria_ply(bad, transform_scene(world["scene"], sim))
        capsys.readouterr()
        assert main(["import", str(bad), "--data", str(cap), "--out", str(tmp_path / f"r{i}"), *FAST]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "do not match the frame" in err, err
        assert not (tmp_path / f"r{i}").exists()
    # no capture: a run with cameras made around the splats (tests/test_bare_splats.py), no PSNR
    assert main(["import", str(ply), "--out", str(tmp_path / "r3"), "--views", "3", "--width", "24", *FAST]) == 0
    assert json.loads((tmp_path / "r3" / "data.json").read_text())["format"] == "orbit"
    assert json.loads((tmp_path / "r3" / "metrics.json").read_text())["psnr"] is None
    # an existing run, a missing source
    assert main(["import", str(ply), "--data", str(cap), "--out", str(tmp_path / "run"), *FAST]) == 2
    assert "--force" in capsys.readouterr().err
    (tmp_path / "run" / "scene.ply").write_bytes(b"stale")
    assert main(["import", str(ply), "--data", str(cap), "--out", str(tmp_path / "run"), "--force", *FAST]) == 0
    _assert_renders(tmp_path / "run", world)
    assert main(["import", str(tmp_path / "nope.ply"), "--data", str(cap), "--out", str(tmp_path / "r4"), *FAST]) == 2


@pytest.mark.parametrize("fmt", ["compressed-ply", "spz"])
def test_other_splat_formats_import_against_their_capture(world, tmp_path, fmt):
    """A compressed PLY or an SPZ of the scene imports with --data as its PLY does (to their quantisation)."""
    from ssgwarp.formats.registry import write_scene

    cap = tmp_path / "cap"
    P.write_transforms_dataset(cap, world["white"], world["cams"])
    f = write_scene(tmp_path / ("splats" + {"compressed-ply": ".compressed.ply", "spz": ".spz"}[fmt]),
                    world["scene"], fmt)
    assert main(["import", str(f), "--data", str(cap), "--out", str(tmp_path / "run"), *FAST]) == 0
    m = _assert_renders(tmp_path / "run", world, tol=0.25)
    assert m["imported"]["tool"] == "ply" and m["imported"]["frame"] == "the capture's own frame"
    assert m["psnr"] > 30 and m["num_gaussians"] == len(world["scene"])


def test_imported_run_works_with_group_and_render(world, tmp_path, capsys):
    cap = _colmap_capture(tmp_path / "cap", world, background="black")
    src = tmp_path / "out"
    _graphdeco_output(src, world["scene"], world["cams"], str(cap))
    run = tmp_path / "run"
    assert main(["import", str(src), "--out", str(run), *FAST]) == 0
    assert "held-out PSNR" in capsys.readouterr().out
    assert main(["render", str(run), "--out", str(tmp_path / "renders"), "--no-progress",
                 "--device", "cpu"]) == 0
    assert len(list((tmp_path / "renders").glob("*.png"))) == VIEWS
    assert main(["group", str(run), "--masks", "none", "--iters", "2", "--groups", "2", *FAST]) == 0
    assert (run / "groups").is_dir() and read_ply(run / "scene.ply").identities is not None
    # the rest of the pipeline takes the imported run as it takes a reconstruction
    style = tmp_path / "style.png"
    write_image(style, torch.rand(24, 24, 3, generator=torch.Generator().manual_seed(0)))
    styled = tmp_path / "styled"
    assert main(["stylize", str(run), "--style", str(style), "--out", str(styled), "--iters", "3",
                 "--keyviews", "2", "--max-side", "32", "--path-frames", "2", "--offline", "--device", "cpu"]) == 0
    assert read_ply(styled / "scene.ply").means.shape == read_ply(run / "scene.ply").means.shape
    assert main(["evaluate", str(styled), "--offline", "--device", "cpu"]) == 0
    assert "evaluation" in json.loads((styled / "metrics.json").read_text())
