"""Batches of views and data-parallel training (``torchrun``, gloo on the CPU).

* batch semantics on one process: B views per step in the one-view order, Adam adapted to the
  batch (lr x sqrt(B), betas ** B), the default schedule counted in images, densification
  statistics per view (a batch of two views gives the sum of the two views' statistics);
* two gloo processes with one view each train the same scene as one process with a batch of
  two (with densification, an identity hook, and the cross-rank checksum on every step), and that
  checksum stops ranks that diverge;
* only the main process writes; ``--resume`` continues a run with another number of processes;
* Ctrl-C on one process stops all at the same step with a checkpoint (slow).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from ssgwarp.services.distributed import Group
from ssgwarp.errors import InputError
from ssgwarp.reconstruction.recipe import Recipe, resolve
from ssgwarp.reconstruction.strategy import DefaultStrategy
from ssgwarp.reconstruction.trainer import Trainer
from ssgwarp.core.optim import batch_factors
from ssgwarp.services.loop import read_checkpoint

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from ddp_worker import make_trainer  # noqa: E402
from test_reconstruct import _write_tiny_colmap  # noqa: E402

# Two processes and one process with the whole batch compute the same sums in another order
# (one render's per-camera adjoint sum against an all-reduce of two renders, the 1/2 before or
# after summing): float32 roundoff of ~1e-7 relative per step, which Adam (normalised steps)
# carries into the parameters at most as lr x (relative gradient difference). Measured over 12
# steps with 4 refinements: max |difference| 3.5e-6 (quaternions), the same Gaussians. The bound,
# 1e-4, is 30x that and 700x below one Adam step at the largest learning rate (opacity,
# 0.05 x sqrt(2)): any real difference (a view rendered twice, a gradient not averaged, a
# statistic not reduced) moves parameters by whole steps and exceeds it.
ATOL = 1e-4


def _env():
    # PYTHONFAULTHANDLER: a worker killed by a signal (SIGABRT, SIGSEGV) prints its Python stacks
    env = dict(os.environ, SSGWARP_OFFLINE="1", OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1")
    for var in ("SSGWARP_LPIPS", "SSGWARP_VGG16", "SSGWARP_WEIGHTS"):
        env.pop(var, None)
    return env


def _launch(args, n=2, env=None) -> subprocess.Popen:
    """``torchrun --standalone --nproc_per_node n ARGS`` in its own session (killed as a whole if stuck)."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(n)] + args
    return subprocess.Popen(cmd, env=env or _env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _finish(p: subprocess.Popen, timeout: float = 180) -> subprocess.CompletedProcess:
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)  # torchrun and its workers
        out, err = p.communicate()
        r = subprocess.CompletedProcess(p.args, p.returncode, out, err)
        raise AssertionError(f"torchrun did not finish in {timeout} s: {_failure(r)}") from None
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def _failure(r: subprocess.CompletedProcess) -> str:
    """What the workers said (their stderr, before torchrun's own report) and torchrun's root cause."""
    err = r.stderr
    cut = err.find("torch/distributed/elastic/")  # torchrun's first line about a failed worker
    workers = err if cut < 0 else err[:err.rfind("\n", 0, cut) + 1]
    root = err[err.find("Root Cause"):][:1500] if "Root Cause" in err else ""
    return (f"torchrun exited {r.returncode}\n--- the workers' stderr (end):\n{workers[-6000:]}\n"
            f"--- stdout (end):\n{r.stdout[-1500:]}\n--- torchrun: {root}")


def _torchrun(args, n=2, env=None) -> subprocess.CompletedProcess:
    return _finish(_launch(args, n, env))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp") / "cap"
    _write_tiny_colmap(root)
    return root


def _toy_data(n_cams: int, size: int = 12):
    """``n_cams`` cameras on an arc looking at the origin, random images, no points."""
    from ssgwarp.core.cameras import Cameras, intrinsics, look_at
    from ssgwarp.capture.datasets import SceneData

    a = torch.linspace(-0.4, 0.4, n_cams, dtype=torch.float64)
    eyes = torch.stack([3 * torch.sin(a), torch.zeros_like(a), -3 * torch.cos(a)], -1)
    V = look_at(eyes, torch.zeros(n_cams, 3), up=(0.0, -1.0, 0.0)).float()
    cams = Cameras(V, intrinsics(1.2 * size, 1.2 * size, size / 2, size / 2, n_cams), size, size)
    g = torch.Generator().manual_seed(0)
    return SceneData(cams, torch.rand(n_cams, size, size, 3, generator=g), [f"v{i}" for i in range(n_cams)],
                     list(range(n_cams)), [], points=None)


def _assert_same_scene(a: dict, b: dict, what: str):
    assert set(a) == set(b)
    for k in a:
        assert a[k].shape == b[k].shape, (what, k, a[k].shape, b[k].shape)
        diff = (a[k].float() - b[k].float()).abs().max().item() if a[k].numel() else 0.0
        assert diff <= ATOL, (what, k, diff)


# ----------------------------------------------------------------------------- one process
def test_batch_draws_views_in_the_one_view_order_and_adapts_adam():
    data = _toy_data(n_cams=5)
    g = torch.Generator().manual_seed(2)
    data.points = (torch.randn(30, 3, generator=g) * 0.4, torch.rand(30, 3, generator=g))
    one = Trainer(data, iters=10, recipe=Recipe(sh_degree=0), progress=False, device="cpu", seed=4)
    two = Trainer(data, iters=10, recipe=Recipe(sh_degree=0), progress=False, device="cpu", seed=4, batch_size=2)
    order = [one.next_batch()[0] for _ in range(8)]
    assert [v for _ in range(4) for v in two.next_batch()] == order
    # Adam for 2 views per step: learning rates x sqrt(2), betas squared (moments forget per image)
    assert two.betas == pytest.approx((0.81, 0.998001))
    for k, g in two.gaussians.groups.items():
        assert g["lr"] == pytest.approx(one.gaussians.groups[k]["lr"] * 2 ** 0.5), k
    assert two.opt.param_groups[0]["betas"] == pytest.approx((0.81, 0.998001))
    assert batch_factors(4, "linear") == (4.0, 4.0) and batch_factors(4, "none") == (1.0, 1.0)
    plain = Trainer(data, iters=10, progress=False, device="cpu", batch_size=3,
                    recipe=Recipe(sh_degree=0, batch_scaling="none"))
    assert plain.betas == (0.9, 0.999) and plain.lr_factor == 1.0
    with pytest.raises(InputError, match="batch_scaling"):
        resolve(Recipe(sh_degree=0, batch_scaling="cube"), "default", 10)
    with pytest.raises(InputError, match="batch_size"):
        Trainer(data, iters=10, progress=False, device="cpu", batch_size=0)


def test_default_schedule_counts_images():
    """3000 steps of 4 views refine, reset and raise the SH degree after the images 12000 one-view steps do."""
    one = resolve(Recipe(), "default", 12000)
    four = resolve(Recipe(), "default", 3000, batch_size=4)
    for i, k in ((1, "refine_start"), (1, "refine_stop"), (1, "refine_every"), (1, "reset_every"), (0, "sh_interval")):
        assert getattr(four[i], k) == round(getattr(one[i], k) / 4), k
    assert (four[1].refine_every, four[1].refine_stop, four[0].sh_interval) == (25, 1500, 250)
    # values given are steps, kept as given
    assert resolve(Recipe(), DefaultStrategy(refine_every=7), 3000, batch_size=4)[1].refine_every == 7


def test_a_batch_step_renders_every_view_once_and_keeps_statistics_per_view():
    """A batch of two views: each rendered once, the loss their mean, and the densification
    statistics the sum of what each view alone gives (gradient norms per view, counts per view)."""
    from ssgwarp.raster.scene import GaussianScene

    data = _toy_data(n_cams=4, size=16)
    g = torch.Generator().manual_seed(2)
    scene = GaussianScene.from_points(torch.randn(40, 3, generator=g) * 0.4, torch.rand(40, 3, generator=g),
                                      sh_degree=0, opacity=0.5, scale=torch.full((40,), 0.05))

    def stats_after_step(batch_size, views):
        t = Trainer(data, scene=scene, iters=100, progress=False, device="cpu", seed=1,
                    batch_size=batch_size, recipe=Recipe(sh_degree=0, batch_scaling="none"))
        t.next_batch = lambda: list(views)  # these views, this step
        t.train_step()
        return {k: v.clone() for k, v in t.gaussians.stats.items()}

    both = stats_after_step(2, [0, 2])
    a, b = stats_after_step(1, [0]), stats_after_step(1, [2])
    assert float(both["count"].sum()) > 0 and float(both["grad2d"].sum()) > 0
    assert torch.equal(both["count"], a["count"] + b["count"])
    torch.testing.assert_close(both["grad2d"], a["grad2d"] + b["grad2d"], rtol=1e-4, atol=1e-9)
    # (without the factor C for the mean over cameras the batch's norms would be half)
    assert not torch.allclose(both["grad2d"], (a["grad2d"] + b["grad2d"]) / 2, rtol=1e-2)


class _Rank1(Group):
    """Rank 1 of 2 whose collectives do nothing (its partner's contributions are zero)."""

    def average_grads(self, params, flags=()):
        return [float(f) for f in flags]

    def reduce_stats(self, stats, ops):
        pass

    def check_identical(self, named, step):
        pass

    def barrier(self):
        pass


def test_only_the_main_process_writes(capture, tmp_path, monkeypatch):
    from ssgwarp.reconstruction.reconstruct import ReconstructConfig, reconstruct

    monkeypatch.setenv("SSGWARP_OFFLINE", "1")
    out = tmp_path / "run"
    m = reconstruct(capture, out, ReconstructConfig(iters=3, recipe=Recipe(sh_degree=0), checkpoint_every=1),
                    device="cpu", progress=False, group=_Rank1(rank=1, world_size=2))
    assert m == {}
    assert not out.exists()  # no folder, outputs, checkpoints or temporary files from rank 1
    with pytest.raises(InputError, match="multiple of 2"):
        reconstruct(capture, out, ReconstructConfig(iters=3, batch_size=3), device="cpu", progress=False,
                    group=_Rank1(rank=1, world_size=2))


# ----------------------------------------------------------------------------- two processes
def test_two_processes_with_one_view_each_train_the_scene_of_one_process_with_two(capture, tmp_path):
    """... and then the debug check catches ranks that diverge: the same two processes start a second
    run in which rank 1 nudges one position; the check stops both with an error naming rank 1 and the
    tensor, and the job fails with nothing written (one launch for both: a launch costs ~10 s of CPU)."""
    env = dict(_env(), SSGWARP_DDP_CHECK="1")  # and the ranks' scenes are compared after every step
    r = _torchrun([str(HERE / "ddp_worker.py"), str(capture), str(tmp_path / "ddp.pt"),
                   "--diverge", str(tmp_path / "x.pt")], env=env)
    assert (tmp_path / "ddp.pt").is_file(), _failure(r)   # the first run finished and was saved
    assert r.returncode != 0
    assert "rank 1's" in r.stderr and "param.means" in r.stderr and "diverged" in r.stderr, _failure(r)
    assert not (tmp_path / "x.pt").exists()
    got = torch.load(tmp_path / "ddp.pt", weights_only=False)
    ref = make_trainer(capture, batch_size=2)
    n0 = ref.num_gaussians
    ref.train()
    st = got["state"]
    assert ref.num_gaussians != n0  # densification happened, and took the same decisions
    assert st["step"] == 12 and st["batch_size"] == 2 and st["world_size"] == 2
    _assert_same_scene(st["params"], {k: v.detach() for k, v in ref.params.items()}, "params")
    _assert_same_scene(st["stats"], ref.gaussians.stats, "stats")
    _assert_same_scene(dict(enumerate(st["hook_params"])), dict(enumerate(ref._hook_params())), "hook")
    # rank 0 rendered the first view of every batch (its hook saw those), rank 1 the second
    assert [v for _, v in got["calls"]] == [v for i, (_, v) in enumerate(ref.hooks[0].calls) if i % 2 == 0]


def _cli(capture, out, *extra):
    return ["reconstruct", str(capture), "--out", str(out), "--sh-degree", "1", "--device", "cpu",
            "--no-progress", "--offline", *extra]


def test_torchrun_resumes_a_one_process_checkpoint_and_records_the_world(capture, tmp_path, monkeypatch):
    """Steps 1-4 in one process (batch 2), 5-8 by ``torchrun -m ssgwarp`` with two: the scene of
    an uninterrupted one-process run; metrics.json says who trained it."""
    from ssgwarp import cli
    from ssgwarp.capture.datasets import load_dataset

    monkeypatch.setenv("SSGWARP_OFFLINE", "1")
    full, split = tmp_path / "full", tmp_path / "split"
    assert cli.main(_cli(capture, full, "--iters", "8", "--batch-size", "2")) == 0
    # the first half as the CLI would run it, stopped at step 4
    torch.manual_seed(0)
    data = load_dataset(capture, seed=0)
    t = Trainer(data, iters=8, recipe=Recipe(sh_degree=1), progress=False, device="cpu", seed=0, batch_size=2,
                checkpoint_path=split / "checkpoint.pt")
    t.train(until=4)
    assert read_checkpoint(split / "checkpoint.pt")["step"] == 4
    r = _torchrun(["-m", "ssgwarp"] + _cli(capture, split, "--iters", "8", "--resume"))
    assert r.returncode == 0, _failure(r)
    assert r.stdout.count("held-out PSNR") == 1  # one summary line, from the main process
    m = json.loads((split / "metrics.json").read_text())
    assert (m["world_size"], m["batch_size"], m["iters"], m["images_seen"]) == (2, 2, 8, 16)
    assert m["batch_scaling"]["lr_factor"] == pytest.approx(2 ** 0.5)
    assert json.loads((full / "metrics.json").read_text())["world_size"] == 1
    assert sorted(p.name for p in split.iterdir()) == sorted(p.name for p in full.iterdir())
    a, b = read_checkpoint(full / "checkpoint.pt"), read_checkpoint(split / "checkpoint.pt")
    assert a["step"] == b["step"] == 8
    _assert_same_scene(a["params"], b["params"], "params")
    # another batch size cannot continue it
    assert cli.main(_cli(capture, split, "--iters", "9", "--resume", "--batch-size", "4")) == 2


def _rank_pid(parent: int, rank: int) -> int:
    """The pid of torchrun ``parent``'s worker whose environment says ``RANK=rank``."""
    for d in Path("/proc").iterdir():
        try:
            if not d.name.isdigit() or f"PPid:\t{parent}\n" not in (d / "status").read_text():
                continue
            if f"RANK={rank}".encode() in (d / "environ").read_bytes().split(b"\0"):
                return int(d.name)
        except OSError:
            continue
    raise AssertionError(f"no worker of rank {rank} under {parent}")


@pytest.mark.slow  # a two-process run interrupted, then resumed in one (~20 s on 2 cores)
def test_ctrl_c_on_one_process_stops_all_with_a_checkpoint(capture, tmp_path, monkeypatch):
    from ssgwarp import cli

    monkeypatch.setenv("SSGWARP_OFFLINE", "1")
    out = tmp_path / "run"
    p = _launch(["-m", "ssgwarp"] + _cli(capture, out, "--iters", "100000", "--checkpoint-every", "5"))
    try:
        deadline = time.time() + 120
        while not (out / "checkpoint.pt").exists() and time.time() < deadline and p.poll() is None:
            time.sleep(0.2)
        assert (out / "checkpoint.pt").exists(), "no checkpoint within 120 s"
        os.kill(_rank_pid(p.pid, 1), signal.SIGINT)
    finally:
        r = _finish(p, timeout=90)
    err = r.stderr
    assert r.returncode != 0
    assert err.count("interrupted at step") == 1  # said once, by the main process
    st = read_checkpoint(out / "checkpoint.pt")
    stopped = st["step"]
    assert stopped > 0 and f"interrupted at step {stopped};" in err
    assert not (out / "metrics.json").exists()
    # one process continues it (the batch size comes from the checkpoint)
    assert cli.main(_cli(capture, out, "--iters", str(stopped + 2), "--resume")) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert (m["world_size"], m["batch_size"], m["iters"]) == (1, 2, stopped + 2)
