"""The CLI reliability matrix: every row drives ``ssgwarp.cli.main([...])``.

Bad input (missing or corrupt images, poses, PLY, masks, style image, weights) must end with exit
code 2 and one line on stderr (no traceback) and leave nothing half-written; a NaN during
optimisation is reported with its step and the last good checkpoint is kept; Ctrl-C keeps a
checkpoint and ``--resume`` reaches the same scene as an uninterrupted seeded run; outputs are never
overwritten without ``--force``; ``--help`` works everywhere and shows examples.
"""
from __future__ import annotations

import hashlib
import json
import re
import shutil
import signal
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ssgwarp import procedural as P
from ssgwarp.cli import COMMANDS, main

# ----------------------------------------------------------------------------- fixtures
FAST = ["--device", "cpu", "--seed", "3"]


@pytest.fixture(autouse=True)
def _no_weights(monkeypatch):
    for var in ("SSGWARP_WEIGHTS", "SSGWARP_SD15", "SSGWARP_CONTROLNET_DEPTH", "SSGWARP_IP_ADAPTER",
                "SSGWARP_IMAGE_ENCODER", "SSGWARP_VGG16", "SSGWARP_RAFT", "SSGWARP_LPIPS"):
        monkeypatch.delenv(var, raising=False)


def _write_colmap(root: Path, gt: P.ProceduralScene, cams, images: torch.Tensor, n_points: int = 200) -> None:
    """The procedural views as a COLMAP text model (PINHOLE) with a sparse cloud drawn from the true Gaussians."""
    from ssgwarp.formats.colmap import ColmapCamera, ColmapImage, ColmapPoints, rotmat_to_qvec, write_model_text
    from ssgwarp.core.fileio import write_image

    K = cams.Ks[0].double()
    ccams = {1: ColmapCamera(1, "PINHOLE", cams.width, cams.height,
                             np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dtype=np.float64))}
    ims = {}
    for i, name in enumerate(cams.names):
        V = cams.viewmats[i].double().numpy()
        ims[i + 1] = ColmapImage(i + 1, rotmat_to_qvec(V[:3, :3]), V[:3, 3], 1, f"{name}.png")
        write_image(root / "images" / f"{name}.png", images[i])
    g = torch.Generator().manual_seed(0)
    pick = torch.randperm(len(gt), generator=g)[:n_points]
    xyz = gt.scene.means[pick].double().numpy()
    rgb = (gt.scene.base_colors[pick].clamp(0, 1) * 255).round().byte().numpy()
    write_model_text(root / "sparse" / "0", ccams, ims,
                     ColmapPoints(np.arange(n_points), xyz, rgb, np.zeros(n_points), np.zeros(n_points, np.int64)))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A COLMAP capture, a NeRF capture, a style image, a reconstructed run and a grouped copy."""
    root = tmp_path_factory.mktemp("cli")
    gt = P.build_scene(0.25)
    cams = P.ring_cameras(6, 32, 24)
    images, _ = P.render_views(gt, cams)
    _write_colmap(root / "cap", gt, cams, images)
    P.write_transforms_dataset(root / "nerf", images, cams)
    from ssgwarp.core.fileio import write_image

    write_image(root / "style.png", P.style_image(32, 32))
    run = root / "run"
    with pytest.MonkeyPatch.context() as mp:
        for var in ("SSGWARP_WEIGHTS", "SSGWARP_VGG16", "SSGWARP_LPIPS", "SSGWARP_RAFT"):
            mp.delenv(var, raising=False)
        assert main(["reconstruct", str(root / "cap"), "--out", str(run), "--iters", "12", "--sh-degree", "0",
                     "--split-every", "3", "--no-progress", *FAST]) == 0
        grouped = root / "grouped"
        shutil.copytree(run, grouped)
        assert main(["group", str(grouped), "--masks", "none", "--iters", "6", "--quiet", *FAST]) == 0
    return SimpleNamespace(root=root, cap=root / "cap", nerf=root / "nerf", style=root / "style.png", run=run,
                           grouped=grouped, names=list(cams.names))


def digest(folder: Path) -> dict[str, str]:
    """File path -> content hash of everything under ``folder`` (to prove nothing changed)."""
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def fails(capsys, argv, *fragments: str) -> str:
    """Run the CLI; assert exit code 2 and that stderr ends with one line ``ssgwarp: error: ...`` holding
    ``fragments`` (progress bars may come before it), with no traceback."""
    capsys.readouterr()
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    assert "Traceback" not in err, err
    segments = [s.strip() for s in re.split(r"[\r\n]", err) if s.strip()]
    errors = [s for s in segments if "ssgwarp: error: " in s]
    assert len(errors) == 1 and segments[-1] == errors[0], err[-2000:]   # one line, and the last
    msg = errors[0][errors[0].index("ssgwarp: error: "):]
    for f in fragments:
        assert f in msg, (f, msg)
    return msg


def copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# ----------------------------------------------------------------------------- images and poses


@pytest.mark.parametrize("damage, message", [
    ("missing", "missing"),
    ("corrupt", "cannot read image"),
    pytest.param("truncated", "r_002.png"),
    pytest.param("truncated jpeg", "Premature end of JPEG"),
])
def test_bad_image(world, tmp_path, capsys, damage, message):
    cap = copy(world.cap, tmp_path / "cap")
    img = cap / "images" / "r_002.png"
    if damage == "missing":
        img.unlink()
    elif damage == "corrupt":
        img.write_bytes(b"this is not a png")
    elif damage == "truncated jpeg":        # libjpeg decodes the missing part as grey and only warns
        _truncated_jpeg(img, np.random.default_rng(2).random((24, 32, 3)).astype(np.float32))
    else:
        img.write_bytes(img.read_bytes()[:60])
    fails(capsys, ["reconstruct", cap, "--out", tmp_path / "run", "--iters", "3", *FAST], message, "r_002.png")
    assert not (tmp_path / "run").exists()


def _truncated_jpeg(path: Path, img: np.ndarray, keep: float = 0.6) -> None:
    """``img`` written as a JPEG, then cut to ``keep`` of its bytes, under ``path`` (whatever its suffix)."""
    from ssgwarp.core.fileio import write_image

    full = write_image(path.with_name(path.stem + "_full.jpg"), img)
    data = full.read_bytes()
    full.unlink()
    path.write_bytes(data[: int(len(data) * keep)])


def _nerf_meta(path: Path) -> dict:
    return json.loads((path / "transforms.json").read_text())


@pytest.mark.parametrize("damage, message", [
    ("colmap: no images.txt", "no capture found"),
    ("colmap: corrupt images.txt", "cannot parse"),
    ("colmap: corrupt cameras.txt", "cannot parse"),
    ("transforms: not JSON", "not valid JSON"),
    ("transforms: NaN pose", "NaN/inf"),
    ("transforms: 2x2 pose", "wrong shape"),
    pytest.param("transforms: no intrinsics", "no intrinsics"),
])
def test_bad_poses(world, tmp_path, capsys, damage, message):
    if damage.startswith("colmap"):
        cap = copy(world.cap, tmp_path / "cap")
        sparse = cap / "sparse" / "0"
        if "no images" in damage:
            (sparse / "images.txt").unlink()
        elif "images" in damage:
            (sparse / "images.txt").write_text("1 0.5 0.5 nan-ish 0.5 0 0 4 1\n\n")
        else:
            (sparse / "cameras.txt").write_text("1 PINHOLE 32 24 40.0\n")
    else:
        cap = copy(world.nerf, tmp_path / "cap")
        meta = _nerf_meta(cap)
        if "not JSON" in damage:
            (cap / "transforms.json").write_text('{"frames": [')
        else:
            if "NaN" in damage:
                meta["frames"][3]["transform_matrix"][0][3] = float("nan")
            elif "2x2" in damage:
                meta["frames"][3]["transform_matrix"] = [[1, 0], [0, 1]]
            else:
                for k in ("camera_angle_x", "fl_x", "fl_y"):
                    meta.pop(k)
            (cap / "transforms.json").write_text(json.dumps(meta))
    fails(capsys, ["reconstruct", cap, "--out", tmp_path / "run", "--iters", "3", *FAST], message)
    assert not (tmp_path / "run").exists()


# ----------------------------------------------------------------------------- PLY
PLY_COMMANDS = {
    "render": lambda run, out, w: ["render", run, "--out", out, "--no-progress"],
    "group": lambda run, out, w: ["group", run, "--masks", "none", "--iters", "2", "--quiet", "--force"],
    "masks": lambda run, out, w: ["masks", run, "--view-masks", out, "--quiet", "--force"],
    "keyviews": lambda run, out, w: ["keyviews", run, "--out", out, "--max-side", "32"],
    "stylize": lambda run, out, w: ["stylize", run, "--style", w.style, "--out", out, "--iters", "2",
                                    "--path-frames", "0", "--max-side", "32"],
    "evaluate": lambda run, out, w: ["evaluate", run, "--table", out / "table.md"],
}


@pytest.mark.parametrize("damage, message", [
    ("missing", "scene.ply"),
    ("truncated", "corrupt or truncated PLY"),
    ("nan", "NaN/inf"),
    ("not a ply", "corrupt or truncated PLY"),
])
def test_bad_ply(world, tmp_path, capsys, damage, message):
    run = copy(world.grouped, tmp_path / "run")
    ply = run / "scene.ply"
    if damage == "missing":
        ply.unlink()
    elif damage == "truncated":
        ply.write_bytes(ply.read_bytes()[: ply.stat().st_size // 2])
    elif damage == "not a ply":
        ply.write_text("hello\n")
    else:
        from ssgwarp.formats.ply import read_ply, write_ply

        s = read_ply(ply)
        m = s.means.clone()
        m[5, 1] = float("nan")
        write_ply(ply, s.replace(means=m))
    before = digest(run)
    for name, argv in PLY_COMMANDS.items():
        out = tmp_path / f"out_{name}"
        fails(capsys, [*argv(run, out, world), *FAST], message)
        assert not out.exists(), name
        assert digest(run) == before, name


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc (a folder nobody can create files in)")
def test_an_unwritable_out_is_named_as_given(world, tmp_path, capsys):
    """(issue 60: the error named the hidden temporary file, '/proc/.x.idg420nf.spz.tmp'.)"""
    msg = fails(capsys, ["export", world.run, "--out", "/proc/x.spz", "--check-views", "0"], "/proc/x.spz",
                "cannot write")
    assert ".tmp" not in msg and "/proc/.x" not in msg
    from ssgwarp.core.fileio import write_json
    from ssgwarp.errors import InputError

    with pytest.raises(InputError, match=r"^/proc/nope/a\.json: cannot write there"):
        write_json("/proc/nope/a.json", {})


# ----------------------------------------------------------------------------- masks
def _write_masks(folder: Path, names, n: int, h: int = 24, w: int = 32) -> None:
    from ssgwarp.core.fileio import write_image

    for name in names[:n]:
        ids = np.zeros((h, w, 1), np.float32)
        ids[:, w // 2:] = 1.0 / 255.0      # ids 0 and 1 in an 8-bit PNG
        write_image(folder / f"{name}.png", ids)


@pytest.mark.parametrize("damage, message", [
    ("folder missing", "folder not found"),
    ("mask missing", "no mask for image"),
    ("corrupt mask", "cannot read mask image"),
    ("truncated mask", "cannot decode mask image"),
    ("colour mask", "single-channel"),
    ("wrong aspect", "aspect"),
])
def test_bad_masks(world, tmp_path, capsys, damage, message):
    from ssgwarp.core.fileio import write_image

    run = copy(world.run, tmp_path / "run")
    masks = tmp_path / "masks"
    if damage != "folder missing":
        _write_masks(masks, world.names, 6)
    target = masks / f"{world.names[1]}.png"           # a training view (split every 3: views 1, 2, 4, 5)
    if damage == "mask missing":
        target.unlink()
    elif damage == "corrupt mask":
        target.write_bytes(b"\x89PNG garbage")
    elif damage == "truncated mask":
        target.write_bytes(target.read_bytes()[:-30])
    elif damage == "colour mask":
        write_image(target, np.random.default_rng(0).random((24, 32, 3)).astype(np.float32))
    elif damage == "wrong aspect":
        write_image(target, np.zeros((32, 32, 1), np.float32))
    before = digest(run)
    fails(capsys, ["group", run, "--masks", masks, "--quiet", *FAST], message)
    assert digest(run) == before and not (run / "groups").exists()


# ----------------------------------------------------------------------------- style image
@pytest.mark.parametrize("damage, message", [("missing", "image not found"), ("corrupt", "cannot read image"),
                                             ("truncated jpeg", "truncated or corrupt")])
def test_bad_style_image(world, tmp_path, capsys, damage, message):
    """(issue 60: the first 3 KB of a JPEG style image used to stylize toward grey, exit 0.)"""
    style = tmp_path / "style.png"
    if damage == "corrupt":
        style.write_bytes(b"GIF89a-not-really")
    elif damage == "truncated jpeg":
        style = tmp_path / "style.jpg"
        _truncated_jpeg(style, np.asarray(P.style_image(64, 64)))
    out = tmp_path / "styled"
    fails(capsys, ["stylize", world.grouped, "--style", style, "--out", out, "--iters", "2", *FAST], message,
          style.name)
    assert not out.exists()


# ----------------------------------------------------------------------------- weights


def _corrupt_weights(tmp_path: Path) -> Path:
    p = tmp_path / "vgg16.pth"
    p.write_bytes(b"not a torch file")
    return p


@pytest.mark.parametrize("row", [
    pytest.param("evaluate --vgg missing", id="evaluate-vgg-missing"),
    pytest.param("evaluate --raft missing", id="evaluate-raft-missing"),
    pytest.param("evaluate --lpips missing", id="evaluate-lpips-missing"),
    pytest.param("evaluate --vgg corrupt", id="evaluate-vgg-corrupt"),
    pytest.param("stylize --vgg16 missing", id="stylize-vgg16-missing"),
    pytest.param("stylize --vgg16 corrupt", id="stylize-vgg16-corrupt"),
    pytest.param("stylize --extractor vgg16", id="stylize-extractor-vgg16"),
    pytest.param("stylize --sd15 missing", id="stylize-sd15-missing"),
])
def test_bad_weights(world, tmp_path, capsys, row):
    run = copy(world.grouped, tmp_path / "run")
    before = digest(run)
    out = tmp_path / "styled"
    missing = "/nonexistent/weights.pth"
    if row.startswith("evaluate"):
        flag = row.split()[1]
        path = _corrupt_weights(tmp_path) if row.endswith("corrupt") else missing
        msg = "cannot load VGG16" if row.endswith("corrupt") else "does not exist"
        fails(capsys, ["evaluate", run, flag, path, "--table", out / "t.md", *FAST], msg)
    else:
        base = ["stylize", run, "--style", world.style, "--out", out, "--iters", "2", "--path-frames", "0",
                "--max-side", "32", *FAST]
        if row == "stylize --vgg16 missing":
            fails(capsys, base + ["--vgg16", missing], "does not exist", "vgg16")
        elif row == "stylize --vgg16 corrupt":
            fails(capsys, base + ["--vgg16", _corrupt_weights(tmp_path)], "cannot load VGG16")
        elif row == "stylize --extractor vgg16":
            fails(capsys, base + ["--extractor", "vgg16"], "no local vgg16 weights",
                  "ssgwarp weights --download vgg16")
        else:
            fails(capsys, base + ["--sd15", missing], "sd15")
    assert digest(run) == before
    assert not out.exists()


# ----------------------------------------------------------------------------- NaN during optimisation
def test_nan_in_reconstruct_is_reported_with_the_step_and_keeps_the_checkpoint(world, tmp_path, capsys,
                                                                                 monkeypatch, fail_on_call):
    import ssgwarp.services.losses as L

    orig = fail_on_call(L, "photometric_warp", 13, "nan")  # (the loss: fused by default)
    out = tmp_path / "run"
    argv = ["reconstruct", world.cap, "--out", out, "--iters", "20", "--sh-degree", "0", "--checkpoint-every", "5",
            "--no-progress", *FAST]
    fails(capsys, argv, "diverged at step 13", "last good checkpoint (step 10)", "--resume")
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]          # no scene.ply or metrics
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ck["step"] == 10 and all(bool(torch.isfinite(v).all()) for v in ck["params"].values())
    monkeypatch.setattr(L, "photometric_warp", orig)
    assert main([str(a) for a in argv + ["--resume"]]) == 0                  # continues from step 10
    assert json.loads((out / "metrics.json").read_text())["iters"] == 20


def test_nan_in_stylize_is_reported_with_the_step_and_keeps_the_checkpoint(world, tmp_path, capsys, fail_on_call):
    import ssgwarp.stylization.stylize as st

    fail_on_call(st.ViewLoss, "__call__", 8, "nan")
    out = tmp_path / "styled"
    fails(capsys, ["stylize", world.grouped, "--style", world.style, "--out", out, "--iters", "12",
                   "--checkpoint-every", "3", "--path-frames", "0", "--max-side", "32", *FAST],
          "loss became nan at step 7", "last good checkpoint kept")
    assert torch.load(out / "stage2.ckpt", weights_only=False)["step"] == 7   # the state after the last good step, saved by ssgwarp.services.loop
    assert not (out / "scene.ply").exists() and not (out / "metrics.json").exists()


def test_nan_in_grouping_is_reported_with_the_step(world, tmp_path, capsys, fail_on_call):
    import ssgwarp.grouping.train as G  # (the training loop calls mask_loss there)

    fail_on_call(G, "mask_loss", 5, "nan")
    run = copy(world.run, tmp_path / "run")
    before = digest(run)
    fails(capsys, ["group", run, "--masks", "none", "--iters", "10", "--quiet", *FAST], "step 5")
    after = digest(run)
    # the run is untouched but for a checkpoint of the last good state (4 steps), for --resume
    ckpt = after.pop("groups/checkpoint.pt", None)
    assert after == before
    assert ckpt is not None and torch.load(run / "groups" / "checkpoint.pt", weights_only=False)["step"] == 4


# ----------------------------------------------------------------------------- Ctrl-C and --resume
def _interrupted(capsys, argv) -> None:
    capsys.readouterr()
    assert main([str(a) for a in argv]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "--resume" in err and "Traceback" not in err


def _same_scene(a: Path, b: Path) -> None:
    from ssgwarp.formats.ply import read_ply

    sa, sb = read_ply(a), read_ply(b)
    assert sa.tensors().keys() == sb.tensors().keys()
    for k, v in sa.tensors().items():
        assert torch.equal(v, sb.tensors()[k]), k


def test_ctrl_c_in_reconstruct_then_resume_matches_an_uninterrupted_run(world, tmp_path, capsys, monkeypatch):
    from ssgwarp.reconstruction.trainer import Trainer

    def argv(out):
        return ["reconstruct", world.cap, "--out", out, "--iters", "24", "--sh-degree", "1",
                "--checkpoint-every", "100", "--no-progress", *FAST]

    assert main([str(a) for a in argv(tmp_path / "a")]) == 0
    orig = Trainer.train_step

    def step(self):
        if self.step == 9:          # a real Ctrl-C (SIGINT) arrives during step 10
            signal.raise_signal(signal.SIGINT)
        return orig(self)

    monkeypatch.setattr(Trainer, "train_step", step)
    _interrupted(capsys, argv(tmp_path / "b"))
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["checkpoint.pt"]
    # the step in flight finished, then the run checkpointed and stopped
    assert torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)["step"] == 10
    monkeypatch.setattr(Trainer, "train_step", orig)
    assert main([str(a) for a in argv(tmp_path / "b") + ["--resume"]]) == 0
    _same_scene(tmp_path / "a" / "scene.ply", tmp_path / "b" / "scene.ply")


def _resume_base(out):
    return ["reconstruct", "CAP", "--out", out, "--sh-degree", "1", "--split-every", "3", "--no-progress",
            "--device", "cpu"]


@pytest.fixture(scope="module")
def checkpointed(world, tmp_path_factory):
    """A 4-step reconstruction at --width 24, seed 3, with its checkpoint (copied by each test)."""
    out = tmp_path_factory.mktemp("ckpt") / "run"
    argv = [str(a).replace("CAP", str(world.cap)) for a in _resume_base(out)]
    assert main(argv + ["--iters", "4", "--width", "24", "--seed", "3"]) == 0
    return out


@pytest.mark.parametrize("change, named", [
    (["--width", "16"], ["--width 24 -> 16", "resolution [24, 18] -> [16, 12]"]),
    ([], ["--width 24 -> none", "resolution [24, 18] -> [32, 24]"]),      # (issue 60: --quick resumed without it)
    (["--width", "24", "--seed", "4"], ["--seed 3 -> 4"]),
    (["--width", "24", "--sh-degree", "0"], ["--sh-degree 1 -> 0"]),
    (["--width", "24", "--max-gaussians", "999"], ["--max-gaussians 1000000 -> 999"]),
    (["--width", "24", "--strategy", "mcmc"], ["--strategy default -> mcmc"]),
    (["--width", "24", "--split-every", "2"], ["--split-every 3 -> 2"]),
    (["--width", "24", "--coarse-to-fine", "2"], ["--coarse-to-fine 1.0 -> 2.0"]),
])
def test_resume_refuses_options_that_change_what_the_checkpoint_means(world, checkpointed, tmp_path, capsys, change,
                                                                       named):
    """A reconstruction checkpoint resumed with another resolution, seed, SH degree, budget, strategy or split is
    one line naming each option and both values, the checkpoint untouched."""
    out = copy(checkpointed, tmp_path / "run")
    base = [str(a).replace("CAP", str(world.cap)) for a in _resume_base(out)]
    seed = ["--seed", "3"] if "--seed" not in change else []
    ck = digest(out)
    msg = fails(capsys, base + ["--iters", "6", "--resume", *seed, *change], "--resume with other options",
                "checkpoint.pt", *named)
    assert "--iters" not in msg and digest(out) == ck


def test_resume_with_more_steps_continues(world, checkpointed, tmp_path):
    """Options that only change the future (more steps, the checkpoint interval) are allowed."""
    out = copy(checkpointed, tmp_path / "run")
    base = [str(a).replace("CAP", str(world.cap)) for a in _resume_base(out)]
    assert main(base + ["--iters", "6", "--width", "24", "--seed", "3", "--checkpoint-every", "2", "--resume"]) == 0
    assert json.loads((out / "metrics.json").read_text())["iters"] == 6


# the flat ``recipe`` of a reconstruction's resume record as versions before the strategies' own dataclasses wrote
# it (every knob of both strategies in one dict; the default Recipe(): what `ssgwarp reconstruct` records)
FLAT_RECIPE_RECORD = {
    "lr_means": 0.00016, "lr_means_final": 1.6e-06, "lr_sh_dc": 0.0025, "lr_sh_rest": 0.000125, "lr_opacity": 0.05,
    "lr_scales": 0.005, "lr_quats": 0.001, "lr_identities": 0.0025, "adam_eps": 1e-15, "lambda_dssim": 0.2,
    "dssim_scale": 1.0, "sh_interval": None, "refine_start": None, "refine_stop": None, "refine_every": None,
    "reset_every": None, "grad_threshold": 0.0002, "percent_dense": 0.01, "split_factor": 1.6, "prune_opacity": 0.005,
    "reset_opacity": 0.01, "prune_world": 0.1, "prune_screen": 0.0, "mcmc_growth": 0.05, "noise_lr": 500000.0,
    "opacity_reg": None, "scale_reg": None, "init_opacity": None, "init_scale": None, "init_max_points": None,
    "identity_init_std": 0.1, "sh_start": None, "res_until": None, "stop_every": None, "stop_patience": 3,
    "stop_tol": 0.1, "stop_views": 4, "stop_tail": 0.2}


def test_a_checkpoint_with_the_flat_recipe_record_of_earlier_versions_resumes(world, checkpointed, tmp_path, capsys):
    """A run folder whose checkpoint holds the resume record of earlier versions (one flat ``recipe``, no
    ``strategy``) resumes with the same options, and is refused with another strategy or budget, naming the
    option as before."""
    out = copy(checkpointed, tmp_path / "run")
    st = torch.load(out / "checkpoint.pt", weights_only=False)
    opts = dict(st["options"])
    assert set(opts["strategy"]) == {"refine_start", "refine_stop", "refine_every", "reset_every", "grad_threshold",
                                     "percent_dense", "split_factor", "prune_opacity", "reset_opacity",
                                     "prune_world", "prune_screen", "prune_contribution", "prune_budget",
                                     "far_split_px"}        # (today's: the strategy's own knobs)
    del opts["strategy"]
    opts["recipe"] = dict(FLAT_RECIPE_RECORD)
    st["options"] = opts
    torch.save(st, out / "checkpoint.pt")
    base = [str(a).replace("CAP", str(world.cap)) for a in _resume_base(out)] + ["--width", "24", "--seed", "3"]
    fails(capsys, base + ["--iters", "6", "--resume", "--strategy", "mcmc"], "--strategy default -> mcmc")
    msg = fails(capsys, base + ["--iters", "6", "--resume", "--max-gaussians", "999"],
                "--max-gaussians 1000000 -> 999")
    assert "recipe." not in msg and "strategy." not in msg       # (only the option that changed)
    assert main(base + ["--iters", "6", "--resume"]) == 0
    assert json.loads((out / "metrics.json").read_text())["iters"] == 6


def test_quick_never_raises_a_captures_resolution(world, tmp_path):
    """(issue 60: --quick set --width 252 always, so a 200x200 capture trained and scored at 252x252.) A capture
    narrower than the preset's 252 px keeps its size; an explicit --width is taken as given."""
    out = tmp_path / "q"
    assert main([str(a) for a in ["reconstruct", world.cap, "--out", out, "--quick", "--iters", "2", "--no-progress",
                                  "--split-every", "3", *FAST]]) == 0
    assert json.loads((out / "metrics.json").read_text())["resolution"] == [32, 24]
    assert json.loads((out / "cameras.json").read_text())["width"] == 32
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.core.presets import AtMost

    assert load_dataset(world.cap, width=AtMost(16), init="random", num_random_points=10).width == 16   # (narrower: resized)


def test_ctrl_c_in_grouping_then_resume_matches_an_uninterrupted_run(world, tmp_path, capsys, monkeypatch,
                                                                     fail_on_call):
    import ssgwarp.grouping.train as G  # (the training loop calls mask_loss there)

    a, b = copy(world.run, tmp_path / "a"), copy(world.run, tmp_path / "b")
    args = ["--masks", "none", "--iters", "14", "--quiet", *FAST]
    assert main(["group", str(a), *args]) == 0
    orig = fail_on_call(G, "mask_loss", 6, "interrupt")
    _interrupted(capsys, ["group", b, *args])
    assert (b / "groups" / "checkpoint.pt").is_file() and not (b / "groups" / "groups.json").exists()
    monkeypatch.setattr(G, "mask_loss", orig)
    ck = digest(b)       # another seed, dimension or K is refused, naming it; more steps would not be
    args3 = [a if a != "3" else "4" for a in args]
    fails(capsys, ["group", b, *args3, "--resume"], "checkpoint.pt", "--resume with other options", "--seed 3 -> 4")
    fails(capsys, ["group", b, *args, "--dim", "5", "--resume"], "--dim 16 -> 5")
    assert digest(b) == ck
    assert main(["group", str(b), *args, "--resume"]) == 0
    _same_scene(a / "scene.ply", b / "scene.ply")
    ca = torch.load(a / "groups" / "classifier.pt", weights_only=True)["state_dict"]
    cb = torch.load(b / "groups" / "classifier.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(ca[k], cb[k]) for k in ca)


def test_ctrl_c_in_stylize_then_resume_matches_an_uninterrupted_run(world, tmp_path, capsys, monkeypatch,
                                                                     fail_on_call):
    import ssgwarp.stylization.stage2 as st   # where optimise calls it

    def argv(out):
        return ["stylize", world.grouped, "--style", world.style, "--out", out, "--iters", "10",
                "--checkpoint-every", "4", "--path-frames", "0", "--max-side", "32", *FAST]

    assert main([str(a) for a in argv(tmp_path / "a")]) == 0
    orig = fail_on_call(st, "backward_views", 7, "interrupt")
    _interrupted(capsys, argv(tmp_path / "b"))
    assert torch.load(tmp_path / "b" / "stage2.ckpt", weights_only=False)["step"] == 6
    assert not (tmp_path / "b" / "scene.ply").exists()
    monkeypatch.setattr(st, "backward_views", orig)
    assert main([str(a) for a in argv(tmp_path / "b") + ["--resume"]]) == 0
    _same_scene(tmp_path / "a" / "scene.ply", tmp_path / "b" / "scene.ply")


# ----------------------------------------------------------------------------- --force


@pytest.mark.parametrize("command", [
    "reconstruct", "group", "stylize",
    pytest.param("render"),
    pytest.param("keyviews"),
    pytest.param("evaluate"),
])
def test_outputs_are_never_overwritten_without_force(world, tmp_path, capsys, command):
    run = copy(world.grouped, tmp_path / "run")
    out = tmp_path / "out"
    argv = {
        "reconstruct": ["reconstruct", world.cap, "--out", run, "--iters", "3", "--no-progress"],
        "group": ["group", run, "--masks", "none", "--iters", "2", "--quiet"],
        "stylize": ["stylize", run, "--style", world.style, "--out", out, "--iters", "2", "--path-frames", "0",
                    "--max-side", "32"],
        "render": ["render", run, "--out", out, "--no-progress"],
        "keyviews": ["keyviews", run, "--out", out, "--max-side", "32"],
        "evaluate": ["evaluate", run, "--max-pairs", "1", "--path-frames", "3", "--save-pairs", "1"],
    }[command]
    if command in ("stylize", "render", "keyviews", "evaluate"):
        capsys.readouterr()
        assert main([str(a) for a in argv + FAST]) == 0          # the first run writes OUT
    before_run, before_out = digest(run), (digest(out) if out.exists() else None)
    fails(capsys, [*argv, "--seed", "4", "--device", "cpu"], "--force")    # another seed: other content
    assert digest(run) == before_run
    assert (digest(out) if out.exists() else None) == before_out


def test_evaluate_quiet_prints_no_progress_bars(world, tmp_path, capsys, monkeypatch):
    import ssgwarp.core.progress as progress

    monkeypatch.setattr(progress, "on_terminal", lambda: True)     # (bars are drawn on a terminal only)
    run = copy(world.grouped, tmp_path / "run")
    argv = [str(a) for a in ["evaluate", run, "--max-pairs", "1", "--path-frames", "3", "--save-pairs", "0", *FAST]]
    capsys.readouterr()
    assert main(argv) == 0
    assert "view/s]" in capsys.readouterr().err                    # the renders' bars, by default
    assert main([*argv, "--force", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "%|" not in captured.err and "metrics written to" in captured.out


def test_force_overwrites(world, tmp_path, capsys):
    run = copy(world.run, tmp_path / "run")
    before = (run / "scene.ply").read_bytes()
    assert main(["reconstruct", str(world.cap), "--out", str(run), "--iters", "4", "--sh-degree", "0",
                 "--no-progress", "--force", *FAST]) == 0
    assert (run / "scene.ply").read_bytes() != before
    assert json.loads((run / "metrics.json").read_text())["iters"] == 4


# ----------------------------------------------------------------------------- help, common flags
def test_top_level_help_lists_every_command_with_an_example(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "examples:" in out
    for name in COMMANDS:
        assert f"ssgwarp {name}" in out, name
    assert main([]) == 0 and "COMMAND" in capsys.readouterr().out       # no command: the help, exit 0


@pytest.mark.parametrize("command", ["demo", "reconstruct", "masks", "group", "stylize", "render"])
def test_long_running_commands_take_quiet(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    assert re.search(r"^  --quiet\b", capsys.readouterr().out, re.M), command


@pytest.mark.parametrize("command", list(COMMANDS))
def test_command_help_shows_options_and_an_example(command, capsys):
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert f"usage: ssgwarp {command}" in out
    assert "example:" in out and f"  ssgwarp {command} " in out
    for flag in ("--device", "--seed", "--config", "--debug"):
        assert flag in out, flag


def test_common_flags(world, tmp_path, capsys):
    out = tmp_path / "r"
    if not torch.cuda.is_available():
        fails(capsys, ["render", world.run, "--out", out, "--device", "cuda"], "CUDA is not available")
    fails(capsys, ["render", world.run, "--out", out, "--config", tmp_path / "nope.json"], "--config", "not found")
    (tmp_path / "bad.json").write_text("{iters: 3")
    fails(capsys, ["render", world.run, "--out", out, "--config", tmp_path / "bad.json"], "not valid JSON")
    assert not out.exists()
    # --config supplies option defaults; the command line still wins
    (tmp_path / "cfg.json").write_text(json.dumps({"iters": 3, "sh-degree": 0, "no_progress": True}))
    assert main(["reconstruct", str(world.cap), "--out", str(tmp_path / "c"), "--config",
                 str(tmp_path / "cfg.json"), *FAST]) == 0
    m = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert m["iters"] == 3 and m["sh_degree"] == 0
    # a key that is no option of the command is an error naming it (not silently ignored)
    (tmp_path / "typo.json").write_text(json.dumps({"iter": 3}))
    fails(capsys, ["reconstruct", world.cap, "--out", tmp_path / "t", "--config", tmp_path / "typo.json"],
          "'iter' is not an option of 'ssgwarp reconstruct'", "did you mean 'iters'")
    assert not (tmp_path / "t").exists()
    # --debug shows the traceback of a user error
    capsys.readouterr()
    assert main(["render", str(tmp_path / "nowhere"), "--out", str(out), "--debug", "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().splitlines()[-1].startswith("ssgwarp: error:")


def test_view_screenshot_is_not_overwritten_without_force(world, tmp_path, capsys):
    shot = tmp_path / "shot.png"
    shot.write_bytes(b"an earlier screenshot")
    fails(capsys, ["view", world.run / "scene.ply", "--screenshot", shot, "--device", "cpu"], str(shot), "--force")
    assert shot.read_bytes() == b"an earlier screenshot"


# ----------------------------------------------------------------------------- other libraries' stderr
def test_libpng_lines_are_folded_into_our_one_line_error(world, tmp_path, capfd):
    """A truncated PNG: libpng prints on the process's stderr (descriptor 2, under OpenImageIO); its words go into
    our one error line instead, and nothing else is left on stderr."""
    cap = copy(world.cap, tmp_path / "cap")
    img = cap / "images" / "r_002.png"
    img.write_bytes(img.read_bytes()[:len(img.read_bytes()) // 2])
    capfd.readouterr()
    assert main(["reconstruct", str(cap), "--out", str(tmp_path / "run"), "--iters", "3", "--quiet", *FAST]) == 2
    err = [s.strip() for s in re.split(r"[\r\n]", capfd.readouterr().err) if s.strip()]
    assert not any(s.startswith("libpng") for s in err), err
    assert err[-1].startswith("ssgwarp: error: ") and "r_002.png" in err[-1] and "libpng error" in err[-1]


def test_no_warp_cuda_driver_warning_on_a_cpu_command(world, tmp_path):
    """Warp's native library prints "Could not find or load the NVIDIA CUDA driver" when it initialises on a
    machine without one; a CPU command initialises Warp (rendering) and its stderr holds no such line."""
    import os
    import subprocess
    import sys

    code = ("import sys; from ssgwarp.cli import main; rc = main(sys.argv[1:]); "
            "from ssgwarp.raster import launch; print('warp initialised:', launch._INIT); sys.exit(rc)")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, "-c", code, "render", str(world.run), "--out", str(tmp_path / "r"),
                        "--quiet", "--device", "cpu"], capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "warp initialised: True" in p.stdout
    assert "CUDA driver" not in p.stderr and "Warp CUDA warning" not in p.stderr, p.stderr[-2000:]


# ----------------------------------------------------------------------------- --quick, CPU expectations
@pytest.mark.parametrize("command, positional", [("reconstruct", ["data", "--out", "o"]), ("group", ["run"]),
                                                 ("stylize", ["run", "--style", "s.png", "--out", "o"])])
def test_quick_presets_are_cpu_sized_and_explicit_options_win(command, positional, capsys):
    import importlib

    from ssgwarp.cli import build_parser

    with pytest.raises(SystemExit):
        main([command, "--help"])
    help_ = " ".join(capsys.readouterr().out.split())
    assert "--quick CPU-sized preset:" in help_ and "min on 2 CPU cores" in help_ and "? min" not in help_
    assert "quick run" not in help_
    module = importlib.import_module(COMMANDS[command][0])
    _, subs = build_parser()
    module.add_arguments(subs[command])
    parse = lambda *a: subs[command].parse_args([*positional, *a])  # noqa: E731
    plain, quick = parse(), parse("--quick")
    for dest, value in module.QUICK.items():
        assert getattr(quick, dest) == value and getattr(plain, dest) != value, dest
    assert parse("--iters", "77", "--quick").iters == 77 and parse("--quick", "--iters", "77").iters == 77


def test_stylize_paint_preset_sets_the_painting_configuration_and_explicit_options_win(tmp_path, capsys):
    from test_stylize import _write_run

    from ssgwarp.cli import build_parser
    from ssgwarp.commands import stylize as stylize_cli

    with pytest.raises(SystemExit):
        main(["stylize", "--help"])
    help_ = " ".join(capsys.readouterr().out.split())
    assert "--paint the weight-free configuration" in help_ and "--mode global, --extractor patches" in help_
    assert "-69 %" in help_ and "1.16x" in help_
    _, subs = build_parser()
    stylize_cli.add_arguments(subs["stylize"])
    parse = lambda *a: subs["stylize"].parse_args(["run", "--style", "s.png", "--out", "o", *a])  # noqa: E731
    plain, paint = parse(), parse("--paint")
    for dest, value in stylize_cli.PAINT.items():
        assert getattr(paint, dest) == value and getattr(plain, dest) != value, dest
    assert parse("--tv-weight", "0.3", "--paint").tv_weight == 0.3
    assert parse("--paint", "--consistency-budget", "3").consistency_budget == 3
    assert parse("--paint", "--quick").iters == stylize_cli.QUICK["iters"]
    # in a --config file the preset sets its options too, below the file's own keys and the command line's
    (tmp_path / "paint.json").write_text(json.dumps({"paint": True, "tv_weight": 0.3}))
    from ssgwarp.cli import _apply_config
    _apply_config(subs["stylize"], ["--config", str(tmp_path / "paint.json")])
    cfg = parse()
    assert cfg.mode == "global" and cfg.consistency_budget == 1.6 and cfg.tv_weight == 0.3
    assert parse("--mode", "ist").mode == "ist"
    _, subs = build_parser()
    stylize_cli.add_arguments(subs["stylize"])
    # end to end: the run records the configuration it ran with
    run, style = _write_run(tmp_path)
    out = tmp_path / "painted"
    assert main(["stylize", str(run), "--style", str(style), "--out", str(out), "--iters", "3", "--paint",
                 "--path-frames", "0", "--device", "cpu", "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["mode"] == "global" and m["extractor"].startswith("patches:")
    for dest in ("tv_weight", "blend_weight", "content_weight", "consistency_weight", "consistency_budget"):
        assert m["config"][dest] == stylize_cli.PAINT[dest], dest


def test_stylize_on_cpu_prints_one_hint_with_the_quick_preset(world, tmp_path, capsys):
    argv = ["stylize", str(world.grouped), "--style", str(world.style), "--iters", "2", "--path-frames", "0",
            "--max-side", "32", "--device", "cpu"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    hints = [ln for ln in capsys.readouterr().out.splitlines() if "--quick (" in ln]
    assert len(hints) == 1 and "on a CPU" in hints[0] and "--iters 150" in hints[0] and "min" in hints[0]
    assert main([*argv, "--out", str(tmp_path / "b"), "--quick", "--iters", "2"]) == 0
    assert "--quick (" not in capsys.readouterr().out
