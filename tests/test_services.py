"""The shared services: the run folder (ssgwarp.services.runs), rendering (ssgwarp.raster.rendering) and the
checkpointed loop (ssgwarp.services.loop), each tested on its own policy."""
from __future__ import annotations

import signal

import pytest
import torch

from ssgwarp import rasterization
from ssgwarp.core.cameras import Cameras
from ssgwarp.errors import InputError, SsgwarpError
from ssgwarp.core.fileio import write_json
from ssgwarp.services.loop import Diverged, Loop, check_finite
from ssgwarp.formats.ply import write_ply
from ssgwarp.raster.rendering import gaussian_colors, render, render_views
from ssgwarp.services.runs import Run, claim
from ssgwarp.raster.scene import GaussianScene


def _scene(n=30, degree=1, ids=0, seed=0) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    xyz = torch.randn(n, 3, generator=g) * 0.4
    s = GaussianScene.from_points(xyz, torch.rand(n, 3, generator=g), sh_degree=degree, opacity=0.6,
                                  scale=torch.full((n,), 0.15))
    if degree:
        s = s.replace(sh_rest=torch.randn(s.sh_rest.shape, generator=g) * 0.2)
    if ids:
        s = s.replace(identities=torch.randn(n, ids, generator=g))
    return s


def _cams(c=3, w=20, h=16) -> Cameras:
    vm = torch.eye(4).repeat(c, 1, 1)
    vm[:, 0, 3] = torch.linspace(-0.3, 0.3, c)
    vm[:, 2, 3] = 3.0
    K = torch.tensor([[18.0, 0, w / 2], [0, 18.0, h / 2], [0, 0, 1]]).repeat(c, 1, 1)
    return Cameras(vm, K, w, h, [f"v{i}.png" for i in range(c)])


# ----------------------------------------------------------------------------- rendering
def test_render_matches_the_rasterizer_and_channels_stay_in_one_pass():
    scene, cams = _scene(ids=4), _cams()
    # RGB only: the rasterizer evaluates the SH itself
    img, alpha, _ = render(scene, cams, sh_degree=1)
    ref, ref_a, _ = rasterization(scene.means, scene.quats, scene.scales, scene.opacities, scene.sh_coeffs,
                                  cams.viewmats, cams.Ks, cams.width, cams.height, sh_degree=1)
    assert torch.equal(img, ref) and torch.equal(alpha, ref_a)
    # RGB + identities: colours evaluated here (same maths as the rasterizer's SH), one blending pass
    both, alpha2, _ = render(scene, cams, sh_degree=1, identities=True)
    assert both.shape == (3, 16, 20, 7) and torch.equal(alpha2, alpha)
    assert torch.allclose(both[..., :3], img, atol=1e-5)
    ident, _, _ = render(scene, cams, rgb=False, identities=True)
    assert torch.allclose(both[..., 3:], ident, atol=1e-6)
    cols = gaussian_colors(scene, cams, sh_degree=0, identities=True)
    assert cols.shape == (3, 30, 7) and torch.allclose(cols[0, :, :3], (scene.sh_dc * 0.28209479177387814 + 0.5))
    with pytest.raises(InputError, match="identity"):
        render(_scene(), cams, identities=True)
    # GaussianScene.render is this service
    s_img, _, _ = scene.render(cams, sh_degree=1)
    assert torch.equal(s_img, img)


def test_render_views_composites_over_the_background_one_camera_at_a_time():
    scene, cams = _scene(), _cams()
    v = render_views(scene, cams, (1.0, 0.0, 0.0))
    img, alpha, _ = render(scene, cams, render_mode="RGB+ED")
    a = alpha[..., 0]
    expect = (img[..., :3] + (1 - a)[..., None] * torch.tensor([1.0, 0.0, 0.0])).clamp(0, 1)
    assert torch.allclose(v.rgb, expect, atol=1e-6) and torch.allclose(v.alpha, a)
    assert torch.allclose(v.depth, img[..., 3], atol=1e-5)
    assert render_views(scene, cams, "white", depth=False).depth is None
    with pytest.raises(InputError, match="background 'grey'"):
        render_views(scene, cams, "grey")


# ----------------------------------------------------------------------------- runs
def _recon_run(path, names=("v0.png", "v1.png", "v2.png"), test=("v1.png",)):
    path.mkdir(parents=True)
    write_ply(path / "scene.ply", _scene())
    _cams().save(path / "cameras.json")
    write_json(path / "data.json", {"split": {"train": [n for n in names if n not in test], "test": list(test)},
                                    "data_dir": None, "background": [1, 1, 1]})
    return path


def test_run_folders_are_classified_and_their_split_read_once(tmp_path):
    rec = _recon_run(tmp_path / "rec")
    r = Run.open(rec)
    assert (r.kind, r.train_ids, r.test_ids) == ("reconstruction", [0, 2], [1])
    assert len(r.cameras) == 3 and r.camera_dir == rec
    scene, data = r.load(load_images=False)
    assert len(scene) == 30 and data.train_ids == [0, 2] and data.test_ids == [1]
    sty = tmp_path / "sty"
    sty.mkdir()
    write_ply(sty / "scene.ply", _scene(seed=1))
    write_json(sty / "metrics.json", {"source_scene": str(rec), "style": "style.png", "mode": "ist"})
    s = Run.open(sty)
    assert (s.kind, s.source_dir, s.mode, s.test_ids) == ("stylized", rec, "ist", [1])
    own, data = s.load(load_images=False)       # its own scene, its source's capture
    assert not torch.equal(own.means, scene.means) and data.test_ids == [1]
    with pytest.raises(InputError, match="no scene.ply"):
        Run.open(tmp_path)
    write_json(rec / "data.json", {"split": {"train": ["nope.png"]}})
    with pytest.raises(InputError, match="nope.png"):
        Run.open(rec).train_ids


def test_claim_refuses_overwrites_and_force_clears_only_the_stage_outputs(tmp_path):
    out = tmp_path / "out"
    assert claim(out, ("a.json", "b")).existing == []              # nothing there yet
    out.mkdir()
    (out / "a.json").write_text("{}")
    (out / "b").mkdir()
    (out / "scratch.pt").write_text("x")
    (out / "mine.txt").write_text("user file")
    with pytest.raises(SsgwarpError, match=r"already holds a thing \(a.json, b\); pass --force .* --resume"):
        claim(out, ("a.json", "b"), what="a thing")
    with pytest.raises(InputError, match="exclude each other"):
        claim(out, ("a.json",), force=True, resume=True)
    assert claim(out, ("a.json", "b"), resume=True).existing == ["a.json", "b"]   # the stage continues
    c = claim(out, ("a.json", "b"), force=True, scratch=("scratch.pt",))
    assert (out / "a.json").exists()                                # nothing removed before clear()
    c.clear()
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        claim(tmp_path / "file", ("a",))


# ----------------------------------------------------------------------------- the loop
class _Counter:
    """A stage whose parameters change only at the end of a step; steps may raise or signal."""

    def __init__(self, fail_at=None, how=None):
        self.step, self.saved, self.fail_at, self.how = 0, [], fail_at, how

    def save(self):
        self.saved.append(self.step)

    def step_fn(self):
        if self.step == self.fail_at:
            if self.how == "sigint":
                signal.raise_signal(signal.SIGINT)
            elif self.how == "error":
                raise RuntimeError("boom")
            elif self.how == "nan":
                check_finite(torch.tensor(float("nan")), self.step + 1, "kept")
        self.step += 1


def test_loop_checkpoints_on_schedule_and_at_the_end():
    c = _Counter()
    Loop(lambda: c.step, save=c.save, every=3, progress=False).run(c.step_fn, 10)
    assert c.step == 10 and c.saved == [3, 6, 9, 10]


def test_loop_ctrl_c_finishes_the_step_then_saves_and_restores_the_handler():
    c = _Counter(fail_at=4, how="sigint")
    with pytest.raises(KeyboardInterrupt):
        Loop(lambda: c.step, save=c.save, every=100, progress=False).run(c.step_fn, 10)
    assert c.step == 5 and c.saved == [5]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


@pytest.mark.parametrize("how, exc", [("error", RuntimeError), ("nan", Diverged)])
def test_loop_saves_the_last_completed_step_after_an_error_inside_a_step(how, exc):
    c = _Counter(fail_at=4, how=how)
    last_good = []
    with pytest.raises(exc):
        Loop(lambda: c.step, save=c.save, every=3, save_last_good=lambda: last_good.append(c.step),
             progress=False).run(c.step_fn, 10)
    assert c.saved == [3] and last_good == [4]
    c = _Counter(fail_at=4, how=how)                 # a stage that cannot rewind keeps its last checkpoint
    with pytest.raises(exc):
        Loop(lambda: c.step, save=c.save, every=3, progress=False).run(c.step_fn, 10)
    assert c.saved == [3]


def test_check_finite_names_the_step_and_what_is_kept():
    check_finite(torch.tensor(1.0), 3, "x")
    with pytest.raises(Diverged, match=r"diverged at step 7 \(the loss is NaN/inf\); the checkpoint of step 5"):
        check_finite(torch.tensor([1.0, float("inf")]), 7, "the checkpoint of step 5")


# ----------------------------------------------------------------------------- core.optim.adam
def test_adam_is_fused_on_the_cpu_and_takes_torchs_default_steps():
    from ssgwarp.core.optim import adam

    torch.manual_seed(0)
    a = [torch.nn.Parameter(torch.randn(50, 3)), torch.nn.Parameter(torch.randn(50))]
    b = [torch.nn.Parameter(p.detach().clone()) for p in a]
    start = [p.detach().clone() for p in a]
    fused = adam([{"params": [a[0]], "lr": 0.1}, {"params": [a[1]], "lr": 0.01}], eps=1e-15, betas=(0.81, 0.998))
    plain = torch.optim.Adam([{"params": [b[0]], "lr": 0.1}, {"params": [b[1]], "lr": 0.01}], eps=1e-15,
                             betas=(0.81, 0.998))
    assert fused.defaults["fused"] is True and not plain.defaults["fused"]
    for step in range(5):
        g = [torch.randn_like(p) for p in a]
        for p, q, gi in zip(a, b, g):
            p.grad, q.grad = gi.clone(), gi.clone()
        fused.step()
        plain.step()
    for p, q in zip(a, b):
        assert (p - q).abs().max() < 1e-6
    assert all((p - s0).abs().min() > 1e-4 for p, s0 in zip(a, start))      # every entry moved
    # a state dict of the fused optimiser loads into a plain one and back (checkpoints move between devices)
    plain.load_state_dict(fused.state_dict())
    fused.load_state_dict(plain.state_dict())
    # an explicit choice keeps torch's default
    assert not adam([torch.nn.Parameter(torch.randn(3))], foreach=False).defaults["fused"]
    # which parameter sets are fused: one device type with a fused Adam, float32 / float64 only
    from ssgwarp.core.optim import fusable
    f32, f64, f16 = torch.float32, torch.float64, torch.float16
    assert fusable({("cpu", f32)}) and fusable({("cuda", f32), ("cuda", f64)})
    assert not fusable({("cpu", f32), ("cuda", f32)})                       # mixed devices
    assert not fusable({("cuda", f16)}) and not fusable({("mps", f32)}) and not fusable(set())


def test_png_writes_are_lossless_at_the_fast_zlib_level(tmp_path):
    from ssgwarp.core.fileio import PNG_LEVEL, read_image, write_image

    img = torch.rand(37, 53, 3, generator=torch.Generator().manual_seed(0))
    path = write_image(tmp_path / "a.png", img)
    assert (torch.from_numpy(read_image(path)) - img).abs().max() <= 0.5 / 255 + 1e-6     # 8-bit, nothing else lost
    data = path.read_bytes()
    idat = data.index(b"IDAT") + 4
    # the zlib stream's header says the level class: FLEVEL 0 ("fastest") for PNG_LEVEL 1 (libpng's default 6: 2)
    assert PNG_LEVEL == 1 and data[idat] & 0x0F == 8 and data[idat + 1] >> 6 == 0


def test_adam_takes_torchs_steps_to_the_bit_without_importing_dynamo():
    """core.optim.Adam is torch's Adam whose methods skip the dynamo guard (which imports torch._dynamo and
    sympy, ~1.5 s on 2 cores): the same steps, state dicts and step hooks, and no torch._dynamo afterwards."""
    import subprocess
    import sys

    code = """
import sys, torch
from ssgwarp.core.optim import Adam, adam
from ssgwarp.reconstruction.step import adam_step
torch.manual_seed(0)
a = [torch.nn.Parameter(torch.randn(40, 3)), torch.nn.Parameter(torch.randn(40))]
groups = lambda ps: [{"params": [ps[0]], "lr": 0.1}, {"params": [ps[1]], "lr": 0.01}]
mine = adam(groups(a), eps=1e-15, betas=(0.9, 0.99))
assert type(mine) is Adam and mine.defaults["fused"] is True
calls = []
hook = mine.register_step_post_hook(lambda *args: calls.append(1))
saved = []
for i in range(4):
    for p in a:
        p.grad = torch.randn_like(p)
    saved.append([p.grad.clone() for p in a])
    if i < 2:
        mine.step()
    else:   # (the project's step without torch's: once the hook is gone)
        hook.remove()
        adam_step(mine)
    mine.zero_grad()
assert calls == [1, 1] and all(p.grad is None for p in a)
state = mine.state_dict()
mine.load_state_dict(state)
assert "torch._dynamo" not in sys.modules and "sympy" not in sys.modules, "dynamo imported"
torch.manual_seed(0)
b = [torch.nn.Parameter(torch.randn(40, 3)), torch.nn.Parameter(torch.randn(40))]
ref = torch.optim.Adam(groups(b), eps=1e-15, betas=(0.9, 0.99), fused=True)
for gs in saved:
    for p, g in zip(b, gs):
        p.grad = g.clone()
    ref.step()
for p, q in zip(a, b):
    assert torch.equal(p, q)
ref.load_state_dict(state)                                          # the state dicts are torch's
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
