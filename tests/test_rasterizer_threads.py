"""The CPU blending kernels on several threads (ssgwarp/raster/cpu_threads.py, RasterSettings.cpu_threads):
the same images and deterministic gradients as one thread bit for bit, the default backward's gradients within
the rounding of its per-thread sums, the split of the tiles, and the waiting on Ctrl-C and errors."""
import threading
import time

import pytest
import torch

import ssgwarp.raster.cpu_threads as CT
from ssgwarp import RasterSettings, rasterization

from test_rasterizer import make_cameras, make_scene

W, H = 64, 48  # 8 x 6 tiles of 8 pixels per camera


# the blending's split calls: the gather, the forward, the backward (their kernels' Warp keys end so)
BLENDING = ("pack", "blend_forward", "blend_backward_reduced")


@pytest.fixture
def split_calls(monkeypatch):
    """Split whatever the size (no work thresholds); records the number of launches of each split call:
    ``["blending"]`` the blending's, ``["elements"]`` ``(kernel key, launches)`` of the per-element kernels'."""
    monkeypatch.setattr(CT, "MIN_WORK", 1)
    monkeypatch.setattr(CT, "MIN_ITEMS", 1)
    monkeypatch.setattr(CT, "MIN_ITEMS_LIGHT", 1)
    seen = {"blending": [], "elements": []}
    run = CT.run

    def record(key, n):
        if key.endswith(BLENDING):
            seen["blending"].append(n)
        else:
            seen["elements"].append((key, n))

    def counting(calls):
        record(calls[0].args[0].key, len(calls))
        return run(calls)

    launch_runs = CT.launch_runs

    def counting_runs(kern, lead, runs, *rest):  # (one run is launched without CT.run)
        if len(runs) == 1:
            record(kern.key, 1)
        return launch_runs(kern, lead, runs, *rest)

    monkeypatch.setattr(CT, "run", counting)
    monkeypatch.setattr(CT, "launch_runs", counting_runs)
    return seen


@pytest.fixture
def launches(split_calls):
    """The number of launches of each of the blending's split calls."""
    return split_calls["blending"]


def _render_and_grads(params, vm, K, threads, channels=3, geometry=True, **kw):
    leaves = [p.clone().requires_grad_(geometry or i == 4) for i, p in enumerate(params)]
    C = vm.shape[0]
    bg = torch.linspace(0.1, 0.9, C * channels, dtype=params[0].dtype).view(C, channels)
    img, alpha, _ = rasterization(*leaves, vm, K, W, H, backgrounds=bg, settings=RasterSettings(cpu_threads=threads),
                                  **kw)
    g = torch.Generator().manual_seed(3)
    ((img * torch.rand(img.shape, generator=g, dtype=img.dtype)).sum()
     + (alpha * torch.rand(alpha.shape, generator=g, dtype=img.dtype)).sum()).backward()
    return [img.detach(), alpha.detach()] + [p.grad for p in leaves if p.grad is not None]


def _scene(dtype, channels=3):
    params = list(make_scene(300, dtype=dtype, seed=4))
    if channels != 3:
        params[4] = torch.rand(300, channels, generator=torch.Generator().manual_seed(5)).to(dtype)
    vm, K = make_cameras(2, W, H, dtype=dtype)
    return params, vm, K


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_threads_give_the_same_images_and_deterministic_gradients(dtype, launches):
    """Images (forward) and the deterministic backward's gradients equal one thread's bit for bit, at 2, 3
    and more threads than the 96 tiles of the two cameras."""
    params, vm, K = _scene(dtype)
    ref = _render_and_grads(params, vm, K, 1, deterministic=True)
    assert launches == [1, 1, 1]  # the forward's gather and blending, the backward
    for threads in (2, 3, 500):
        launches.clear()
        out = _render_and_grads(params, vm, K, threads, deterministic=True)
        # gather, forward and backward split alike; many threads: as many runs as the work's cuts give (a
        # tile is not cut)
        n = launches[0]
        assert launches == [n] * 3 and (n == threads if threads < 96 else 40 < n <= 96)
        for a, b in zip(out, ref):
            assert b.abs().max() > 0 and torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cameras", [1, 2])
def test_per_element_kernels_on_threads_bit_identical(dtype, cameras, split_calls):
    """The projection (with the input checks, tile counts and packed splats), the SH colours, the binning's
    key writes and range offsets, and the adjoints of the projection and the SH, in runs of Gaussians or
    intersections on several threads: every output, the binning and the gradients of every input, the view
    matrices included (deterministic backward), equal one thread's bit for bit, at 2, 3 and 7 threads and
    at more threads than the 300 Gaussians (one Gaussian per launch); one camera (the gradients written
    straight) and two (per-camera slots)."""
    g = torch.Generator().manual_seed(7)
    n = 300
    means, quats, scales, opac, _ = make_scene(n, dtype=dtype, seed=4)
    coeffs = (torch.randn(n, 16, 3, generator=g) * 0.3).to(dtype)
    vm, K = make_cameras(cameras, W, H, dtype=dtype)

    def run(threads):
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, coeffs, vm)]
        img, alpha, meta = rasterization(*leaves[:5], leaves[5], K, W, H, sh_degree=3, deterministic=True,
                                         settings=RasterSettings(cpu_threads=threads))
        gen = torch.Generator().manual_seed(3)
        ((img * torch.rand(img.shape, generator=gen, dtype=dtype)).sum()
         + (alpha * torch.rand(alpha.shape, generator=gen, dtype=dtype)).sum()).backward()
        keys = ("radii", "means2d", "depths", "conics", "opacities", "tiles_per_gauss", "isect_ids", "flatten_ids",
                "isect_offsets")
        return [img.detach(), alpha.detach()] + [meta[k].detach() for k in keys] + [p.grad for p in leaves]

    ref = run(1)
    assert all(k == 1 for _, k in split_calls["elements"])
    assert all(r.abs().max() > 0 for r in ref[:2] + ref[11:])
    for threads in (2, 3, 7, 500):
        split_calls["elements"].clear()
        out = run(threads)
        runs = {}
        for key, k in split_calls["elements"]:
            runs.setdefault(key.split("__")[-1], []).append(k)
        # forward and backward of the projection (hand-written) and the SH colours (with shared coefficients
        # and several cameras, the SH colours' hand-written backward) over runs of the Gaussians (in every
        # camera); the key writes over (camera, Gaussian) pairs, the offsets over the intersections
        sh_runs = runs["sh_colour"] + runs.get("sh_colour_backward", [])
        assert runs["project"] == [min(threads, n)] and runs["project_backward"] == [min(threads, n)]
        assert sh_runs == [min(threads, n)] * 2
        assert ("sh_colour_backward" in runs) == (cameras > 1)
        assert runs["write_isects"] == [min(threads, cameras * n)] and runs["offsets_kernel"] == [threads]
        for a, b in zip(out, ref):
            assert a.dtype == b.dtype and torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("geometry", [True, False], ids=["full", "colour-only"])
def test_threads_default_backward_within_rounding(dtype, geometry, launches):
    """The default backward adds each Gaussian's gradient from every thread's own rows, summed afterwards:
    the images are bit-identical, the gradients equal one thread's up to the rounding of that reordered
    sum (at most a few units of the precision relative to the gradient's scale: 1e-6 in float32, 1e-14 in
    float64), with 16 channels for the colour-only case; and the same bit for bit from run to run at one
    thread count."""
    params, vm, K = _scene(dtype, 3 if geometry else 16)
    ch = params[4].shape[-1]
    ref = _render_and_grads(params, vm, K, 1, ch, geometry)
    rtol, atol = (1e-5, 1e-6) if dtype == torch.float32 else (1e-12, 1e-14)
    for threads in (2, 5, 500):
        out = _render_and_grads(params, vm, K, threads, ch, geometry)
        assert torch.equal(out[0], ref[0]) and torch.equal(out[1], ref[1])
        assert len(out) == len(ref) == (7 if geometry else 3)
        for a, b in zip(out[2:], ref[2:]):
            torch.testing.assert_close(a, b, rtol=rtol, atol=atol * float(b.abs().max()))
        # the same number of threads cuts the same runs and adds in the same order: the same gradients
        again = _render_and_grads(params, vm, K, threads, ch, geometry)
        assert all(torch.equal(a, b) for a, b in zip(again, out))


def test_default_backward_threads_capped_by_memory(launches, monkeypatch):
    """Each extra thread of the default backward holds a gradient buffer; past the memory cap fewer,
    longer runs of tiles are used (the forward keeps its split) and the result still matches."""
    params, vm, K = _scene(torch.float64)
    ref = _render_and_grads(params, vm, K, 1)
    row_bytes = (6 + 3) * 8
    monkeypatch.setattr(CT, "MAX_EXTRA_BYTES", row_bytes * 2 * 300)  # two cameras x 300 Gaussians: one extra buffer
    launches.clear()
    out = _render_and_grads(params, vm, K, 5)
    assert launches == [5, 5, 2]
    for a, b in zip(out[2:], ref[2:]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14 * float(b.abs().max()))


def test_thread_count_and_split():
    """``count``: the setting (default torch's threads), at most one per tile and per MIN_WORK of work;
    ``split``: consecutive non-empty runs covering every tile, cut at equal work."""
    assert CT.count(4, 100, 10**9, 64) == 4
    assert CT.count(4, 3, 10**9, 64) == 3                        # at most one thread per tile
    assert CT.count(4, 10, 0, 64) == 1                           # too little work: one launch
    assert CT.count(None, 10**4, 10**9, 64) == torch.get_num_threads()
    saved = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        assert CT.count(None, 10**4, 10**9, 64) == 3
    finally:
        torch.set_num_threads(saved)
    # 10 tiles, all intersections in tiles 6 and 7: the work is cut there, not at the middle of the image
    counts = torch.tensor([0, 0, 0, 0, 0, 0, 500, 500, 0, 0])
    offsets = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)]).to(torch.int32)
    parts = CT.split(offsets, 10, 2)
    assert parts == [(0, 7), (7, 10)]
    for n in (1, 2, 3, 7, 10, 40):
        parts = CT.split(offsets, 10, n)
        assert parts[0][0] == 0 and parts[-1][1] == 10 and len(parts) <= min(n, 10)
        assert all(a < b for a, b in parts) and all(p[1] == q[0] for p, q in zip(parts, parts[1:]))
    assert CT.split(torch.zeros(11, dtype=torch.int32), 10, 5) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
    # ``ranges``: equal consecutive runs of elements, one per thread, at most one per MIN_ITEMS elements
    assert CT.ranges(2, 10 * CT.MIN_ITEMS) == [(0, 5 * CT.MIN_ITEMS), (5 * CT.MIN_ITEMS, 10 * CT.MIN_ITEMS)]
    m = 3 * CT.MIN_ITEMS - 1  # two whole MIN_ITEMS only: two runs over all of them
    assert CT.ranges(4, m) == [(0, m // 2), (m // 2, m)]
    assert CT.ranges(8, 100) == [(0, 100)] and CT.ranges(1, 10**9) == [(0, 10**9)]
    assert CT.ranges(5, 3, 1) == [(0, 1), (1, 2), (2, 3)] and CT.ranges(3, 0) == [(0, 0)]


def test_run_waits_for_every_launch_on_error_and_interrupt():
    """``run`` returns (or raises) only once every call has finished: the launches write into tensors
    the caller holds. The first error is raised; Ctrl-C in the calling thread's own call waits too."""
    done = []

    def slow():
        time.sleep(0.2)
        done.append(threading.current_thread().name)

    def fails():
        raise RuntimeError("launch failed")

    def interrupted():
        raise KeyboardInterrupt

    with pytest.raises(RuntimeError, match="launch failed"):
        CT.run([fails, slow, slow])
    assert len(done) == 2 and all(n.startswith("ssgwarp-blend") for n in done)
    done.clear()
    with pytest.raises(KeyboardInterrupt):
        CT.run([interrupted, slow])
    assert len(done) == 1
    with pytest.raises(RuntimeError, match="launch failed"):
        CT.run([slow, fails])


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2"])
def test_cpu_threads_setting_checked(bad):
    with pytest.raises(ValueError, match="cpu_threads"):
        RasterSettings(cpu_threads=bad)
    assert RasterSettings(cpu_threads=3).for_dtype(torch.float64).cpu_threads == 3
