"""The pyvista inspection viewer (``ssgwarp view``), rendered off-screen on a tiny synthetic scene.

Rendering tests need off-screen OpenGL (Mesa EGL on a machine with no display,
see docs/viewer.md); they are skipped, with the reason, only when a probe
render in a child process fails.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError, SsgwarpError
from ssgwarp.core.palette import palette
from ssgwarp.raster.scene import GaussianScene, rgb_to_sh_dc

from ssgwarp import viewer  # (installed from viewer/)
from ssgwarp.viewer import geometry
from ssgwarp.viewer.data import resolve_groups, resolve_keyviews

OK, REASON = viewer.offscreen_status()
needs_gl = pytest.mark.skipif(not OK, reason=REASON)

K = 3
PER = 40
CENTERS = torch.tensor([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.2, 0.0]])
LOW_OPACITY_GROUP = 2
SIZE = (200, 150)


def make_scene(identities: bool = False) -> tuple[GaussianScene, np.ndarray]:
    """Three blobs of 40 Gaussians, group g around CENTERS[g]; group 2 is faint (opacity 0.2)."""
    g = torch.Generator().manual_seed(0)
    xyz = torch.cat([c + 0.2 * torch.randn(PER, 3, generator=g) for c in CENTERS])
    labels = np.repeat(np.arange(K), PER)
    rgb = torch.full((K * PER, 3), 0.5)
    rgb[:, 2] = torch.linspace(0.3, 0.7, K * PER)  # greyish-blue colours, none in the palette
    n = K * PER
    opac = torch.full((n,), 0.9)
    opac[labels == LOW_OPACITY_GROUP] = 0.2
    quats = torch.randn(n, 4, generator=g)
    log_s = torch.log(torch.tensor([0.09, 0.06, 0.03])).repeat(n, 1)
    ident = None
    if identities:
        ident = torch.full((n, K), -2.0)
        ident[torch.arange(n), torch.as_tensor(labels)] = 2.0
    scene = GaussianScene(xyz, log_s, quats, torch.logit(opac), rgb_to_sh_dc(rgb), None, ident, 0)
    return scene, labels


def make_cameras() -> Cameras:
    eyes = torch.tensor([[0.0, -4.0, 1.5], [4.0, 0.0, 1.5], [0.0, 4.0, 1.5], [-4.0, 0.0, 1.5]])
    return Cameras(look_at(eyes, torch.zeros(4, 3)).float(), intrinsics(30.0, 30.0, 16.0, 12.0, 4), 32, 24,
                   ["cam_a", "cam_b", "cam_c", "cam_d"])


def colour_pixels(img: np.ndarray, rgb01, tol: int = 3) -> int:
    target = (np.asarray(rgb01) * 255 + 0.5).astype(int)
    return int((np.abs(img[..., :3].astype(int) - target).max(axis=-1) <= tol).sum())


def press(v, key: str) -> None:
    """Deliver a key press to the viewer's interactor, as a real key event would."""
    v.plotter.iren.interactor.SetKeySym(key)
    v.plotter.iren.key_press_event()


@pytest.fixture(scope="module")
def scene():
    return make_scene()


# -- pure geometry / data (no GL) -------------------------------------------------------
def test_frustum_corners_project_to_image_corners():
    cams = make_cameras()
    depth = 0.5
    pts, lines = geometry.frustum_lines(cams.viewmats.numpy(), cams.Ks.numpy(), cams.width, cams.height, depth)
    assert pts.shape == (6 * len(cams), 3)
    assert len(lines) == 3 * geometry.SEGMENTS_PER_FRUSTUM * len(cams)
    for i in range(len(cams)):
        P = pts[6 * i: 6 * i + 6]
        assert np.allclose(P[0], cams.centers[i].numpy(), atol=1e-5)
        cam = (cams.viewmats[i].double().numpy() @ np.c_[P[1:5], np.ones(4)].T)[:3]
        assert np.allclose(cam[2], depth, atol=1e-5)
        uv = (cams.Ks[i].double().numpy() @ cam)[:2] / cam[2]
        assert np.allclose(uv.T, [[0, 0], [32, 0], [32, 24], [0, 24]], atol=1e-4)


def test_ellipsoid_glyphs_lie_on_the_sigma_surface():
    g = torch.Generator().manual_seed(1)
    means, quats = torch.randn(5, 3, generator=g).numpy(), torch.randn(5, 4, generator=g).numpy()
    scales = (torch.rand(5, 3, generator=g) * 0.5 + 0.1).numpy()
    pts, faces, owner = geometry.ellipsoid_glyphs(means, quats, scales, sigma=2.0, theta_res=8, phi_res=5)
    R = geometry.quat_to_rotmat(quats)
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    local = np.einsum("nji,nj->ni", R[owner], pts - means[owner]) / scales[owner]  # R^T (x - mu) / s
    assert np.allclose(np.linalg.norm(local, axis=1), 2.0, atol=1e-9)
    assert faces.reshape(-1, 4)[:, 0].tolist() == [3] * (len(faces) // 4)
    assert faces.reshape(-1, 4)[:, 1:].max() == len(pts) - 1


def test_subsample_respects_budget_and_seed():
    a = geometry.subsample_indices(1000, 100, seed=3)
    assert len(a) == 100 and len(np.unique(a)) == 100 and np.all(np.diff(a) > 0)
    assert np.array_equal(a, geometry.subsample_indices(1000, 100, seed=3))
    assert not np.array_equal(a, geometry.subsample_indices(1000, 100, seed=4))
    assert np.array_equal(geometry.subsample_indices(50, 100), np.arange(50))


def test_groups_from_classifier_labels_and_identity_fallback(tmp_path):
    sc, labels = make_scene(identities=True)
    # no classifier: argmax of identity channels, and it says so
    info = resolve_groups(sc, scene_dir=tmp_path)
    assert np.array_equal(info.labels, labels) and "argmax" in info.source
    assert info.counts().tolist() == [PER] * K
    # a classifier that permutes channels -> groups: the viewer must use it, not the argmax
    grouping = pytest.importorskip("ssgwarp.grouping.stage")
    perm = [2, 0, 1]
    lin = torch.nn.Linear(K, K)
    with torch.no_grad():
        lin.weight.zero_()
        lin.bias.zero_()
        for j, p in enumerate(perm):
            lin.weight[p, j] = 1.0
    (tmp_path / "groups").mkdir()
    torch.save({"format": getattr(grouping, "FORMAT", 1), "dim": K, "num_groups": K,
                "state_dict": {k: v.detach() for k, v in lin.state_dict().items()}},
               tmp_path / "groups" / "classifier.pt")
    info = resolve_groups(sc, scene_dir=tmp_path)
    assert info.source == "grouping classifier"
    assert np.array_equal(info.labels, np.asarray(perm)[labels])
    # explicit labels win; bad ones are refused
    assert np.array_equal(resolve_groups(sc, labels=labels[::-1].copy()).labels, labels[::-1])
    with pytest.raises(InputError, match="one label per Gaussian"):
        resolve_groups(sc, labels=labels[:-1])
    with pytest.raises(InputError, match="integers"):
        resolve_groups(sc, labels=labels + 0.5)


def test_keyviews_from_ids_names_and_keyviews_json(tmp_path):
    cams = make_cameras()
    assert resolve_keyviews(["1", "cam_d", 1], cams) == [1, 3]
    kv = tmp_path / "keyviews"
    kv.mkdir()
    cams[[0, 2]].save(kv / "cameras.json")
    (kv / "keyviews.json").write_text('{"ids": [2, 0], "names": ["cam_c", "cam_a"], "width": 32}')
    assert resolve_keyviews([str(kv)], cams) == [2, 0]
    assert resolve_keyviews([str(kv / "keyviews.json")], cams) == [2, 0]
    with pytest.raises(InputError, match="out of range"):
        resolve_keyviews(["7"], cams)
    with pytest.raises(InputError, match="neither a camera index nor a camera name"):
        resolve_keyviews(["nope"], cams)


def test_interactive_without_display_is_a_clear_error(scene, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(SsgwarpError, match="--screenshot"):
        viewer.Viewer(scene[0], off_screen=False)


# -- off-screen rendering ---------------------------------------------------------------
@needs_gl
def test_group_colouring_puts_each_palette_colour_into_the_image(scene):
    sc, labels = scene
    cams = make_cameras()
    v = viewer.build_viewer(sc, labels=labels, cameras=cams, color="group", off_screen=True, window_size=SIZE,
                            legend=False, hud=False, sigma=1.5, frustum_size=0.01)
    try:
        v.look_through("cam_a")                         # the 3D view now matches camera 0's pinhole
        img = v.screenshot()
        assert img.shape == (SIZE[1], SIZE[0], 3)
        pal = palette(K)
        scale = SIZE[0] / cams.width
        for g in range(K):
            assert colour_pixels(img, pal[g]) >= 15, f"group {g}'s palette colour missing"
            # ...and it sits where group g's blob projects in camera 0
            cam = cams.viewmats[0].double() @ torch.cat([CENTERS[g].double(), torch.ones(1, dtype=torch.float64)])
            uv = (cams.Ks[0].double() @ cam[:3])[:2] / cam[2] * scale
            target = (np.asarray(pal[g]) * 255 + 0.5).astype(int)
            rows, cols = np.nonzero(np.abs(img.astype(int) - target).max(-1) <= 3)
            assert np.hypot(cols.mean() - uv[0].item(), rows.mean() - uv[1].item()) < 0.08 * SIZE[0], g
        press(v, "c")                                   # key 'c': group -> opacity
        assert v.color == "opacity"
        press(v, "c")                                   # opacity -> rgb
        assert v.color == "rgb"
        img = v.screenshot()
        for g in range(K):
            assert colour_pixels(img, pal[g]) == 0, "palette colours left after switching to SH colour"
        assert colour_pixels(img, (0.5, 0.5, 0.5), tol=40) > 50
    finally:
        v.close()


@needs_gl
def test_legend_lists_group_ids_and_counts(scene):
    sc, labels = scene
    lab = labels.copy()
    lab[:5] = 4                                        # group 3 empty, group 4 has 5 Gaussians
    v = viewer.build_viewer(sc, labels=lab, color="group", off_screen=True, window_size=SIZE)
    try:
        rows = v.legend_entries()
        assert [r[0] for r in rows] == [f"group 0: {PER - 5}", f"group 1: {PER}", f"group 2: {PER}", "group 4: 5"]
        assert np.allclose(rows[3][1], palette(5)[4])
        assert v.plotter.legend is not None
    finally:
        v.close()


@needs_gl
def test_opacity_threshold_removes_points(scene):
    sc, labels = scene
    v = viewer.build_viewer(sc, labels=labels, color="group", off_screen=True, window_size=SIZE, legend=False,
                            hud=False, sigma=1.5, widgets=True)   # slider + picking built off-screen too
    try:
        faint = palette(K)[LOW_OPACITY_GROUP]
        assert v.cloud_actor.mapper.dataset.n_points == K * PER
        assert colour_pixels(v.screenshot(), faint) > 0
        v.set_opacity_threshold(0.5)
        assert v.num_visible == (K - 1) * PER
        assert v.cloud_actor.mapper.dataset.n_points == (K - 1) * PER
        shown = set(v.cloud_actor.mapper.dataset.point_data["gaussian"].tolist())
        assert shown == set(np.nonzero(labels != LOW_OPACITY_GROUP)[0].tolist())
        assert colour_pixels(v.screenshot(), faint) == 0
        v.set_opacity_threshold(0.95)                   # nothing left: no actor, no crash
        assert v.num_visible == 0 and v.cloud_actor is None
        v.screenshot()
    finally:
        v.close()


@needs_gl
def test_camera_frustums_appear_with_key_views_highlighted(scene):
    sc, labels = scene
    cams = make_cameras()
    v = viewer.build_viewer(sc, labels=labels, cameras=cams, keyviews=["cam_b"], off_screen=True,
                            window_size=SIZE, hud=False, legend=False)
    try:
        plain = v.plotter.actors["frustums"].mapper.dataset
        key = v.plotter.actors["keyview_frustums"].mapper.dataset
        assert plain.n_lines == 3 * geometry.SEGMENTS_PER_FRUSTUM
        assert key.n_lines == geometry.SEGMENTS_PER_FRUSTUM
        assert v.selected == 1                          # the first key view starts selected
        # the start view frames the cloud; these cameras stand 2-3x its size away: step back to see them
        v.plotter.camera.zoom(0.4)
        img = v.screenshot()
        from ssgwarp.viewer.drawing import CAMERA_COLOR, KEYVIEW_COLOR, SELECTED_COLOR
        assert colour_pixels(img, CAMERA_COLOR) > 10
        assert colour_pixels(img, SELECTED_COLOR) > 5
        press(v, "n")                                   # select the next camera: the key view shows orange
        assert v.selected == 2
        assert colour_pixels(v.screenshot(), KEYVIEW_COLOR) > 5
    finally:
        v.close()
    v = viewer.build_viewer(sc, off_screen=True, window_size=SIZE)
    try:
        assert "frustums" not in v.plotter.actors and "keyview_frustums" not in v.plotter.actors
    finally:
        v.close()


@needs_gl
def test_glyphs_pick_and_splat_panel(scene):
    sc, labels = scene
    cams = make_cameras()
    v = viewer.build_viewer(sc, labels=labels, cameras=cams, off_screen=True, window_size=SIZE, max_glyphs=25,
                            max_points=90, seed=1)
    try:
        assert len(v.index) == 90 and any("90 of 120" in n for n in v.notes)
        press(v, "g")
        assert v.glyphs and v.glyph_count == 25
        verts = len(geometry.unit_sphere()[0])
        assert v.plotter.actors["glyphs"].mapper.dataset.n_points == 25 * verts
        i = int(v.index[7])
        info = v.pick(sc.means[i].numpy() + 1e-4)
        assert info["index"] == i and info["group"] == labels[i]
        assert info["opacity"] == pytest.approx(float(sc.opacities[i]), abs=1e-6)
        img = v.show_splat("cam_c")
        ref = sc.render(cams[2])[0][0].clamp(0, 1).numpy()
        assert img.shape == ref.shape and np.allclose(img, ref, atol=1e-6)
        shot = v.screenshot()
        panel = shot[:, int(0.65 * SIZE[0]):]
        assert (panel.max(axis=-1) > 20).sum() > 50     # the splat image is drawn in the right panel
    finally:
        v.close()


@needs_gl
def test_screenshot_api_writes_the_file(scene, tmp_path):
    sc, labels = scene
    out = tmp_path / "api.png"
    img = viewer.screenshot(sc, out, labels=labels, cameras=make_cameras(), keyviews=[0], view="cam_a",
                            render_view="cam_b", window_size=SIZE)
    from ssgwarp.core.fileio import read_image

    assert out.is_file() and img.shape == (SIZE[1], SIZE[0], 3)
    assert np.abs(read_image(out, 3) * 255 - img).max() <= 1
    plotter = viewer.build_plotter(sc, off_screen=True, window_size=SIZE)
    try:
        assert viewer.app.viewer_of(plotter).num_visible == K * PER and "gaussians" in plotter.actors
    finally:
        plotter.close()


@needs_gl
def test_cli_screenshot_is_written(tmp_path, capsys):
    ply = pytest.importorskip("ssgwarp.formats.ply")
    from ssgwarp.cli import main
    from ssgwarp.core.fileio import read_image

    sc, labels = make_scene(identities=True)
    run = tmp_path / "run"
    ply.write_ply(run / "scene.ply", sc)
    make_cameras().save(run / "cameras.json")
    np.save(tmp_path / "labels.npy", labels)
    out = tmp_path / "shots" / "view.png"
    rc = main(["view", str(run), "--labels", str(tmp_path / "labels.npy"), "--keyviews", "0", "2",
               "--max-points", "60", "--render-view", "cam_b", "--window-size", "240", "160",
               "--screenshot", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    img = read_image(out, 3)
    assert img.shape == (160, 240, 3) and img.max() > 0
    assert "60 of 120" in captured.err                  # the subsample is announced
    assert not list(out.parent.glob(".*tmp"))           # written atomically


def test_bad_ply_gives_a_clear_error(tmp_path, capsys):
    from ssgwarp.cli import main

    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"this is not a ply file\n")
    assert main(["view", str(bad), "--screenshot", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "bad.ply" in err and "not a PLY" in err and "Traceback" not in err
    assert not (tmp_path / "x.png").exists()

    assert main(["view", str(tmp_path / "missing.ply")]) == 2
    assert "not found" in capsys.readouterr().err

    pytest.importorskip("ssgwarp.formats.ply")
    plain = tmp_path / "points.ply"                    # a valid PLY, but a plain point cloud
    plain.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n0 0 0\n1 1 1\n")
    assert main(["view", str(plain), "--screenshot", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "points.ply" in err and "ssgwarp: error:" in err
    trunc = tmp_path / "trunc.ply"
    trunc.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\0\0")
    assert main(["view", str(trunc)]) == 2
    assert "trunc.ply" in capsys.readouterr().err


def _stylized_run(tmp_path, sc):
    """A reconstruction of ``sc`` (cameras, a classifier of its K identity channels onto 2 groups) and a
    stylized run of it as ``ssgwarp stylize`` writes one: scene.ply, metrics.json naming its
    source_scene, keyviews/keyviews.json. Neither holds the other's files."""
    ply = pytest.importorskip("ssgwarp.formats.ply")
    from ssgwarp.core.fileio import write_json

    rec, sty = tmp_path / "rec", tmp_path / "sty"
    ply.write_ply(rec / "scene.ply", sc)
    cams = make_cameras()
    near = torch.tensor([[0.0, -2.2, 0.8], [2.2, 0.0, 0.8], [0.0, 2.2, 0.8], [-2.2, 0.0, 0.8]])
    # (nearer than make_cameras': inside the start view, which frames the cloud)
    Cameras(look_at(near, torch.zeros(4, 3)).float(), cams.Ks, cams.width, cams.height, cams.names).save(
        rec / "cameras.json")
    lin = torch.nn.Linear(K, 2)
    with torch.no_grad():  # groups 0 and 1 -> group 0, group 2 -> group 1
        lin.weight.copy_(torch.tensor([[1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]]))
        lin.bias.zero_()
    (rec / "groups").mkdir()
    torch.save({"format": 1, "dim": K, "num_groups": 2,
                "state_dict": {k: v.detach() for k, v in lin.state_dict().items()}}, rec / "groups" / "classifier.pt")
    ply.write_ply(sty / "scene.ply", sc)
    write_json(sty / "metrics.json", {"source_scene": str(rec), "style": "style.png", "mode": "ist"})
    (sty / "keyviews").mkdir()
    write_json(sty / "keyviews" / "keyviews.json", {"ids": [1, 3], "names": ["cam_b", "cam_d"]})
    return rec, sty


def test_a_stylized_run_shows_its_sources_groups_and_cameras_and_its_key_views(tmp_path):
    from ssgwarp.viewer.data import load_cameras, run_folders

    sc, labels = make_scene(identities=True)
    rec, sty = _stylized_run(tmp_path, sc)
    found = run_folders(sty)
    assert (found.cameras, found.groups, found.keyviews) == (rec, rec, sty / "keyviews")
    info = resolve_groups(sc, scene_dir=found.groups)
    # the source's classifier (2 groups), not the argmax of the K identity channels
    assert info.source == "grouping classifier" and info.num_groups == 2
    assert np.array_equal(info.labels, (labels == 2).astype(np.int64))
    cams = load_cameras(None, found.cameras)
    assert cams.names == make_cameras().names
    assert resolve_keyviews([str(found.keyviews)], cams) == [1, 3]
    # a folder that is no run: what lies in it
    plain = tmp_path / "plain"
    plain.mkdir()
    make_cameras().save(plain / "cameras.json")
    f = run_folders(plain)
    assert (f.cameras, f.groups, f.keyviews) == (plain, None, None)
    assert run_folders(None).cameras is None


@needs_gl
def test_view_of_a_stylized_run_draws_its_key_views_and_groups(tmp_path, capsys):
    from ssgwarp.cli import main
    from ssgwarp.core.fileio import read_image
    from ssgwarp.viewer.drawing import KEYVIEW_COLOR

    sc, labels = make_scene(identities=True)
    _, sty = _stylized_run(tmp_path, sc)
    out = tmp_path / "view.png"
    rc = main(["view", str(sty), "--window-size", "320", "240", "--screenshot", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "ignoring" not in captured.err
    img = (read_image(out, 3) * 255 + 0.5).astype(np.uint8)
    assert colour_pixels(img, KEYVIEW_COLOR, tol=6) > 10       # the key views' frustums, without --cameras
    pal = palette(2)
    assert colour_pixels(img, pal[0], tol=6) > 50 and colour_pixels(img, pal[1], tol=6) > 10
    v = viewer.build_viewer(sc, scene_dir=sty, off_screen=True, window_size=SIZE)
    try:
        assert v.groups.num_groups == 2 and v.cameras is not None and len(v.cameras) == 4
        assert "2 groups (grouping classifier)" in v.status_text()
    finally:
        v.close()


@needs_gl
def test_far_floaters_do_not_shrink_the_start_view(scene):
    """The start view frames the cloud's robust box: a few Gaussians 50 units away leave the cloud
    (nearly) as large on screen as without them, with or without cameras (floaters: under 2%)."""
    sc, labels = scene
    g = torch.Generator().manual_seed(1)
    far = GaussianScene(torch.randn(2, 3, generator=g) * 5 + torch.tensor([50.0, 40.0, 30.0]),
                        sc.log_scales[:2], sc.quats[:2], sc.logit_opacities[:2], sc.sh_dc[:2], None, None, 0)
    with_floaters = GaussianScene(torch.cat([sc.means, far.means]), torch.cat([sc.log_scales, far.log_scales]),
                                  torch.cat([sc.quats, far.quats]),
                                  torch.cat([sc.logit_opacities, far.logit_opacities]),
                                  torch.cat([sc.sh_dc, far.sh_dc]), None, None, 0)
    bg = np.array([0.08, 0.08, 0.10])

    def cloud_box(s, cameras):
        """Width and height in pixels of what the three blobs cover on screen (the floaters' discs and
        the frustum lines, grey, are not counted: the blobs are coloured)."""
        img = viewer.screenshot(s, cameras=cameras, window_size=SIZE, hud=False, legend=False).astype(int)
        lit = np.abs(img[..., :3] - (bg * 255 + 0.5).astype(int)).max(-1) > 20
        lit &= np.abs(img[..., 2] - img[..., 0]) > 8                    # bluish-grey blobs, not grey lines
        ys, xs = np.nonzero(lit)
        return xs.max() - xs.min() + 1, ys.max() - ys.min() + 1

    for cams in (None, make_cameras()):
        (w0, h0), (w1, h1) = cloud_box(sc, cams), cloud_box(with_floaters, cams)
        assert max(w0 / SIZE[0], h0 / SIZE[1]) > 0.4               # the cloud spans much of the view
        assert w1 > 0.8 * w0 and h1 > 0.8 * h0
