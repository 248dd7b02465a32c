"""3DGS training: held-out PSNR rises on a real capture, densification is generic over every
scene tensor (identities included), Ctrl-C checkpoints and --resume continue bit-exactly,
NaNs stop the run with the step, and the CLI writes the run contract (or refuses cleanly)."""
from __future__ import annotations

import json
import math
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

from ssgwarp.cameras import Cameras, intrinsics, look_at
from ssgwarp.datasets import SceneData, load_dataset, load_run
from ssgwarp.errors import SsgwarpError
from ssgwarp.reconstruct import Recipe, Trainer
from ssgwarp.scene import GaussianScene

from conftest import SHARED_DATA as DATA
needs_fern = pytest.mark.skipif(not (DATA / "llff_fern").is_dir(), reason="shared data not present")


@pytest.fixture(scope="module")
def fern():
    if not (DATA / "llff_fern").is_dir():
        pytest.skip("shared data not present")
    return load_dataset(DATA / "llff_fern", images="images_8", width=32)


@needs_fern
def test_training_raises_heldout_psnr(fern):
    """fern at 32x24, 200 COLMAP points, 60 steps: held-out PSNR up by >= 5 dB (seen: ~11.5 -> ~19.7)."""
    rec = Recipe(init_max_points=200, refine_start=20, refine_every=20, reset_every=10**6)
    t = Trainer(fern, iters=60, sh_degree=1, max_gaussians=300, recipe=rec, progress=False, device="cpu")
    before = t.evaluate()
    t.train()
    after = t.evaluate()
    assert before["views"] == after["views"] == 3
    assert after["psnr"] >= before["psnr"] + 5.0, (before["psnr"], after["psnr"])
    assert after["ssim"] > before["ssim"] + 0.2
    assert 200 < t.num_gaussians <= 300  # densified, within the cap
    assert t.active_sh_degree == 1 and t.final_scene().sh_rest.shape == (t.num_gaussians, 3, 3)


class IdentityHook:
    """Pushes the rendered identity channels towards a fixed colour-derived target; can raise Ctrl-C."""

    def __init__(self, dim: int, interrupt_at=None, nan_at=None):
        g = torch.Generator().manual_seed(5)
        self.head = torch.nn.Linear(dim, 2)
        with torch.no_grad():
            self.head.weight.copy_(torch.randn(2, dim, generator=g))
            self.head.bias.zero_()
        self.interrupt_at, self.nan_at = interrupt_at, nan_at
        self.calls = []
        self.scene_fn = None

    def parameters(self):
        return [{"params": list(self.head.parameters()), "lr": 1e-2, "name": "head"}]

    def loss(self, step, view_index, identity_render):
        self.calls.append((step, view_index, tuple(identity_render.shape)))
        if step == self.interrupt_at:
            signal.raise_signal(signal.SIGINT)
        out = self.head(identity_render)
        loss = ((out - 0.5) ** 2).mean()
        if step == self.nan_at:
            loss = loss * float("nan")
        return loss


def _resume_kwargs(fern, tmp_path, name):
    rec = Recipe(init_max_points=120, refine_start=8, refine_every=8, reset_every=20, sh_interval=10,
                 prune_screen_px=0)
    return dict(iters=30, sh_degree=1, max_gaussians=400, recipe=rec, progress=False, device="cpu", seed=3,
                identity_dim=4, checkpoint_path=tmp_path / name, checkpoint_every=100)


@needs_fern
def test_ctrl_c_checkpoint_and_resume_match_an_uninterrupted_run(fern, tmp_path):
    small = load_dataset(DATA / "llff_fern", images="images_8", width=28, max_images=8)
    ha = IdentityHook(4)
    a = Trainer(small, hooks=[ha], **_resume_kwargs(small, tmp_path, "a.pt"))
    n0 = a.num_gaussians
    sa = a.train()
    # the hook saw [H, W, E] identity renders of training views, and the scene through scene_fn
    assert ha.calls and all(c[2] == (small.height, small.width, 4) for c in ha.calls)
    assert {c[1] for c in ha.calls} <= set(small.train_ids)
    assert ha.scene_fn is not None and len(ha.scene_fn()) == len(sa)
    # densification carried the identities along (other N than at the start, same N everywhere)
    assert len(sa) != n0 and sa.identities.shape == (len(sa), 4)

    hb = IdentityHook(4, interrupt_at=13)
    b = Trainer(small, hooks=[hb], **_resume_kwargs(small, tmp_path, "b.pt"))
    with pytest.raises(KeyboardInterrupt):
        b.train()
    assert b.step == 14 and (tmp_path / "b.pt").is_file()  # the step in flight finished, then checkpointed
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handler restored

    hc = IdentityHook(4)
    c = Trainer(small, hooks=[hc], **_resume_kwargs(small, tmp_path, "b.pt"))
    c.load_checkpoint()
    assert c.step == 14
    sc = c.train()
    for k, v in sa.tensors().items():
        assert torch.equal(v, sc.tensors()[k]), k
    for p, q in zip(ha.head.parameters(), hc.head.parameters()):
        assert torch.equal(p, q)
    assert not torch.equal(ha.head.weight, IdentityHook(4).head.weight)  # the hook's parameters were trained


def _toy_data(n_cams=2, size=8):
    V = look_at(torch.tensor([[0.0, 0.0, -3.0], [0.5, 0.0, -3.0]])[:n_cams], torch.zeros(n_cams, 3),
                up=(0.0, -1.0, 0.0)).float()
    cams = Cameras(V, intrinsics(8.0, 8.0, size / 2, size / 2, n_cams), size, size)
    g = torch.Generator().manual_seed(0)
    return SceneData(cams, torch.rand(n_cams, size, size, 3, generator=g), [f"v{i}" for i in range(n_cams)],
                     list(range(n_cams)), [], points=None)


def _toy_scene(n=12):
    g = torch.Generator().manual_seed(1)
    s = GaussianScene.from_points(torch.randn(n, 3, generator=g) * 0.3, torch.rand(n, 3, generator=g), sh_degree=1,
                                  opacity=0.5, scale=torch.full((n,), 0.001))
    s = s.replace(sh_rest=torch.randn(n, 3, 3, generator=g), identities=torch.randn(n, 5, generator=g))
    ls = s.log_scales.clone()
    ls[4:8] = math.log(0.5)  # large: split
    lo = s.logit_opacities.clone()
    lo[8] = -8.0  # nearly transparent: pruned
    return s.replace(log_scales=ls, logit_opacities=lo)


def test_densification_is_generic_and_respects_the_cap():
    data = _toy_data()
    s0 = _toy_scene()
    t = Trainer(data, scene=s0, iters=100, sh_degree=1, recipe=Recipe(sh_interval=1), progress=False, device="cpu")
    assert math.isclose(t.extent, 1.1 * 0.25, rel_tol=1e-5)
    t.step = 1
    t.train_step()  # creates Adam state for the tensors that get gradients (identities: only with a hook)
    before = {k: v.detach().clone() for k, v in t.params.items()}
    t.grad2d[:] = 0.0
    t.grad2d[0:8] = 1.0
    t.count[:] = 1.0
    t.step = 200  # before the first reset: no size pruning
    info = t._refine()
    assert info == {"clone": 4, "split": 4, "prune": 1}
    n = t.num_gaussians
    assert n == 12 + 4 + 4 - 1
    with_state = set()
    for k, p in t.params.items():
        assert p.shape[0] == n
        if p in t.opt.state:
            st = t.opt.state[p]
            assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape, k
            with_state.add(k)
    assert with_state == {"means", "log_scales", "quats", "logit_opacities", "sh_dc", "sh_rest"}
    # survivors first (minus the split and pruned ones), then clones, then split children
    keep = [0, 1, 2, 3, 9, 10, 11]
    assert torch.equal(t.params["identities"][:7], before["identities"][keep])
    assert torch.equal(t.params["identities"][7:11], before["identities"][0:4])  # clones: exact copies
    assert torch.equal(t.params["sh_rest"][7:11], before["sh_rest"][0:4])
    children = t.params["identities"][11:]
    assert torch.equal(children, before["identities"][4:8].repeat(2, 1))
    assert torch.allclose(t.params["log_scales"][11:], (before["log_scales"][4:8] - math.log(1.6)).repeat(2, 1))
    d = (t.params["means"][11:] - before["means"][4:8].repeat(2, 1)).norm(dim=1)
    assert bool((d > 0).all()) and bool((d < 0.5 * 6).all())
    assert t.grad2d.shape == (n,) and float(t.grad2d.abs().sum()) == 0.0  # statistics reset

    # the cap: only the highest-gradient candidates grow
    t2 = Trainer(data, scene=s0, iters=100, sh_degree=1, max_gaussians=14, progress=False, device="cpu")
    t2.grad2d[:] = 0.0
    t2.grad2d[0:8] = torch.arange(1.0, 9.0)
    t2.count[:] = 1.0
    info = t2._refine()
    assert info["clone"] + info["split"] == 2 and info["split"] == 2  # gaussians 6, 7 have the top gradients
    assert t2.num_gaussians <= 14

    # opacity reset: capped at 0.01 and the Adam moments of the opacities cleared
    t.train_step()
    t._reset_opacity()
    assert float(torch.sigmoid(t.params["logit_opacities"].detach()).max()) <= 0.01 + 1e-6
    assert float(t.opt.state[t.params["logit_opacities"]]["exp_avg"].abs().sum()) == 0.0


def test_nan_stops_with_the_step_and_keeps_the_last_checkpoint(tmp_path):
    data = _toy_data()
    hook = IdentityHook(3, nan_at=12)
    t = Trainer(data, scene=_toy_scene().replace(identities=None), iters=50, sh_degree=1, hooks=[hook],
                identity_dim=3, checkpoint_path=tmp_path / "ck.pt", checkpoint_every=5, progress=False, device="cpu")
    with pytest.raises(SsgwarpError, match=r"diverged at step 13 .*last good checkpoint \(step 10\)"):
        t.train()
    t2 = Trainer(data, scene=_toy_scene().replace(identities=None), iters=50, sh_degree=1, hooks=[IdentityHook(3)],
                 identity_dim=3, checkpoint_path=tmp_path / "ck.pt", progress=False, device="cpu")
    t2.load_checkpoint()
    assert t2.step == 10 and all(bool(torch.isfinite(p).all()) for p in t2.params.values())


def _write_tiny_colmap(root: Path):
    from ssgwarp.colmap import ColmapCamera, ColmapImage, ColmapPoints, rotmat_to_qvec, write_model_text
    from ssgwarp.fileio import write_image

    rng = np.random.default_rng(0)
    cams = {1: ColmapCamera(1, "SIMPLE_PINHOLE", 24, 18, np.array([20.0, 12.0, 9.0]))}
    images = {}
    for i in range(6):
        a = 0.3 * i
        V = look_at(torch.tensor([[3 * math.sin(a), 0.2, -3 * math.cos(a)]]), torch.zeros(1, 3),
                    up=(0.0, -1.0, 0.0))[0].numpy()
        images[i + 1] = ColmapImage(i + 1, rotmat_to_qvec(V[:3, :3]), V[:3, 3], 1, f"{i}.png")
        yy, xx = np.mgrid[0:18, 0:24] / 24.0
        img = np.stack([xx, yy, 0.5 + 0 * xx], -1) + 0.1 * np.sin(i)
        write_image(root / "images" / f"{i}.png", np.clip(img, 0, 1).astype(np.float32))
    xyz = rng.normal(size=(60, 3)) * 0.5
    pts = ColmapPoints(np.arange(60), xyz, rng.integers(0, 255, (60, 3)).astype(np.uint8), np.zeros(60),
                       np.zeros(60, np.int64))
    write_model_text(root / "sparse" / "0", cams, images, pts)


def test_cli_reconstruct_writes_the_run_contract_and_refuses_to_overwrite(tmp_path, monkeypatch, capsys):
    from ssgwarp import cli
    from ssgwarp.ply import read_ply

    for var in ("SSGWARP_LPIPS", "SSGWARP_VGG16", "SSGWARP_WEIGHTS"):
        monkeypatch.delenv(var, raising=False)
    data_dir, out = tmp_path / "cap", tmp_path / "run"
    _write_tiny_colmap(data_dir)
    args = ["reconstruct", str(data_dir), "--out", str(out), "--iters", "6", "--sh-degree", "0",
            "--split-every", "3", "--no-progress", "--device", "cpu", "--checkpoint-every", "4"]
    assert cli.main(args) == 0
    assert {p.name for p in out.iterdir()} == {"scene.ply", "cameras.json", "data.json", "metrics.json",
                                               "checkpoint.pt"}
    m = json.loads((out / "metrics.json").read_text())
    assert m["test_views"] == 2 and m["psnr"] > 0 and 0 < m["ssim"] <= 1 and m["iters"] == 6
    assert m["lpips"] is None and "skipped" in m["lpips_note"]
    assert m["num_gaussians"] == 60 and m["sh_degree"] == 0 and m["train_seconds"] >= 0
    meta = json.loads((out / "data.json").read_text())
    assert meta["split"] == {"train": ["1.png", "2.png", "4.png", "5.png"], "test": ["0.png", "3.png"]}
    assert meta["data_dir"] == str(data_dir.resolve()) and meta["format"] == "colmap"
    scene = read_ply(out / "scene.ply")
    assert scene.sh_rest is None and scene.identities is None  # degree 0: no higher bands

    # the run reads back through the contract
    s2, d2 = load_run(out, "cpu")
    assert torch.equal(s2.means, scene.means)
    assert d2.names == [f"{i}.png" for i in range(6)] and d2.train_ids == [1, 2, 4, 5] and d2.test_ids == [0, 3]
    assert torch.equal(d2.images, load_dataset(data_dir).images)

    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "already holds a reconstruction" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # --resume of a finished run rewrites the same scene without training
    assert cli.main(args + ["--resume"]) == 0
    assert (out / "scene.ply").read_bytes() == before["scene.ply"]

    # bad input: one line, exit 2, nothing created
    assert cli.main(["reconstruct", str(tmp_path / "nope"), "--out", str(tmp_path / "run2"), "--device", "cpu"]) == 2
    assert "data folder not found" in capsys.readouterr().err and not (tmp_path / "run2").exists()
    (data_dir / "images" / "4.png").unlink()
    assert cli.main(["reconstruct", str(data_dir), "--out", str(tmp_path / "run3"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "missing" in err and "4.png" in err and not (tmp_path / "run3").exists()

    # render along the cameras and along a smooth path
    assert cli.main(["render", str(out), "--out", str(tmp_path / "r"), "--split", "test", "--device", "cpu",
                     "--no-progress"]) == 0
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["0.png", "3.png"]
    assert cli.main(["render", str(out), "--out", str(tmp_path / "p"), "--path", "5", "--device", "cpu",
                     "--no-progress"]) == 0
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == [f"frame_{i:04d}.png" for i in range(5)] + [
        "path_cameras.json"]


def test_smooth_path_through_cameras():
    from ssgwarp.render import smooth_path

    n = 10
    ang = torch.linspace(0, 2 * math.pi, n + 1)[:-1]
    perm = torch.tensor([3, 7, 0, 9, 5, 1, 8, 2, 6, 4])  # given out of order
    eyes = torch.stack([3 * torch.cos(ang), torch.zeros(n), 3 * torch.sin(ang)], 1)[perm]
    V = look_at(eyes, torch.zeros(n, 3), up=(0.0, -1.0, 0.0)).float()
    cams = Cameras(V, intrinsics(20.0, 20.0, 16.0, 12.0, n), 32, 24)
    path = smooth_path(cams, 60)
    assert len(path) == 60 and path.names[0] == "frame_0000" and (path.width, path.height) == (32, 24)
    c = path.centers.double()
    assert torch.allclose(c.norm(dim=1), torch.full((60,), 3.0, dtype=torch.float64), atol=0.05)  # stays on the circle
    steps = (torch.roll(c, -1, 0) - c).norm(dim=1)  # a loop: the last frame leads back to the first
    assert float(steps.max() / steps.min()) < 1.2  # even speed
    # passes (nearly) through every camera, still looking at the centre
    assert float(torch.cdist(eyes.double(), c).min(dim=1).values.max()) < 0.5 * float(steps.mean())
    f = path.forwards.double()
    assert bool(((f * -torch.nn.functional.normalize(c, dim=1)).sum(1) > 0.99).all())
    R = path.viewmats[:, :3, :3].double()
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(60, 3, 3), atol=1e-5)
    # open path: starts at a camera and ends at another
    op = smooth_path(cams, 7, closed=False)
    assert float(torch.cdist(op.centers[[0, -1]].double(), eyes.double()).min(dim=1).values.max()) < 1e-4
