"""The rasterizer's launch layer (ssgwarp/raster/launch.py) and the op paths it serves: replayed launches equal
to Warp's own, per-camera inputs, partial gradients, and (on CUDA) torch's current stream."""
import pytest
import torch
import warp as wp

import ssgwarp.raster.launch as L
import ssgwarp.raster.private_api as P
from ssgwarp import RasterSettings, rasterization

from conftest import CUDA_ONLY
from test_rasterizer import assert_match, make_cameras, make_scene, run_both

WARP_LAYOUT = pytest.mark.skipif(not L.FAST, reason="Warp's internal array/launch layout differs: launches use wp.launch")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA_ONLY)]


def CUDA(test):
    """A test that needs a CUDA device: in ``pytest -m cuda``'s selection, skipped without one."""
    for mark in CUDA_ONLY:
        test = mark(test)
    return test


def _render_and_grads(params, vm, K, w, h, **kw):
    leaves = [p.clone().requires_grad_(True) for p in params]
    img, alpha, meta = rasterization(*leaves, vm, K, w, h, **kw)
    g = torch.Generator(device=img.device).manual_seed(3)
    ((img * torch.rand(img.shape, generator=g, device=img.device, dtype=img.dtype)).sum()
     + (alpha * torch.rand(alpha.shape, generator=g, device=img.device, dtype=img.dtype)).sum()).backward()
    return [img.detach(), alpha.detach(), meta["flatten_ids"]] + [p.grad for p in leaves]


@pytest.mark.parametrize("device", DEVICES)
def test_replayed_launches_equal_warp_launch(device, monkeypatch):
    """Every kernel launched by replaying its recorded launch gives bit for bit what ``wp.launch``
    gives (the fall-back path, used when Warp's internals differ), forward and backward, with SH
    colours, two cameras and a background."""
    params = [t.to(device) for t in make_scene(80, dtype=torch.float32, seed=2)]
    g = torch.Generator().manual_seed(5)
    params[4] = (torch.randn(80, 16, 3, generator=g) * 0.3).to(device)
    vm, K = (t.to(device) for t in make_cameras(2, 30, 22, dtype=torch.float32))
    kw = dict(sh_degree=3, backgrounds=torch.rand(2, 3, generator=g).to(device), deterministic=True)
    monkeypatch.setattr(L._LOCAL, "plans", {}, raising=False)
    fast = _render_and_grads(params, vm, K, 30, 22, **kw)
    assert L.FAST and all(p.fast is not None for p in L._LOCAL.plans.values())   # (the self-test passed here)
    monkeypatch.setattr(L, "FAST", False)
    monkeypatch.setattr(L._LOCAL, "plans", {}, raising=False)
    slow = _render_and_grads(params, vm, K, 30, 22, **kw)
    assert all(not p.fast for p in L._LOCAL.plans.values())
    for a, b in zip(fast, slow):
        assert torch.equal(a, b)


@WARP_LAYOUT
def test_array_descriptors_follow_the_tensor_layout():
    t = torch.zeros(5, 7, 3)
    assert L.arr(t, 3) == (t.data_ptr(), 0, 35, 0, 0, 0, 12, 0, 0, 0, 1, 0)
    # a column block of a wider matrix: rows spaced by the full row
    assert L.rows(t.view(35, 3)[:, 1:3], 2)[2:7] == (35, 0, 0, 0, 12)
    # a camera-stride-0 grid: every camera reads the same Gaussian
    assert L.grid(t.view(35, 3), 4, 35, 3, False)[2:8] == (4, 35, 0, 0, 0, 12)
    assert L.cams(t, 5, 9, 21)[2:8] == (5, 9, 0, 0, 84, 0)
    assert L.NULL == (0,) * 12
    v = L.grid3(t, 2, 5, 7, 3, True)
    d = P.array_t(v[0], v[1], v[10], v[2:2 + v[10]], v[6:6 + v[10]], v[11])
    assert (d.ndim, tuple(d.shape[:3]), tuple(d.strides[:3])) == (3, (2, 5, 7), (420, 84, 12))


@WARP_LAYOUT
def test_struct_layout_matches_ctypes():
    """The packed parameter block is laid out byte for byte as Warp's ctypes structures."""
    import ctypes
    import struct

    array_t = P.array_t
    fmt = P.layout(array_t)
    assert struct.calcsize("=" + fmt) == ctypes.sizeof(array_t)
    a = array_t(123456789, 0, 2, (3, 4), (16, 4), 0)
    assert struct.pack("=" + fmt, 123456789, 0, 3, 4, 0, 0, 16, 4, 0, 0, 2, 0) == bytes(a)

    class Mixed(ctypes.Structure):
        _fields_ = [("a", ctypes.c_int32), ("b", array_t), ("c", ctypes.c_float), ("d", ctypes.c_double)]

    m = Mixed(7, a, 1.5, 2.25)
    fmt = P.layout(Mixed)
    assert struct.pack("=" + fmt, 7, 123456789, 0, 3, 4, 0, 0, 16, 4, 0, 0, 2, 0, 1.5, 2.25) == bytes(m)


def test_per_camera_colours_and_sh_match_reference():
    """Colours and SH coefficients given per camera ([C, N, ...]), more coefficients than the degree
    uses, and a view-matrix gradient with one camera and with three."""
    means, quats, scales, opac, _ = make_scene(90, seed=12)
    g = torch.Generator().manual_seed(13)
    for c in (1, 3):
        vm, K = make_cameras(c, 33, 27)
        cols = torch.rand(c, 90, 5, generator=g, dtype=torch.float64)
        out = run_both([means, quats, scales, opac, cols], vm, K, 33, 27)
        for d in out.values():
            d[2].append(torch.zeros(1))
        assert_match(out, 1e-10, 1e-9)
        sh = torch.randn(c, 90, 16, 3, generator=g, dtype=torch.float64) * 0.3
        out = run_both([means, quats, scales, opac, sh], vm, K, 33, 27, sh_degree=2)
        for d in out.values():
            d[2].append(torch.zeros(1))
        assert_match(out, 1e-10, 1e-9)


@pytest.mark.parametrize("loss", ["image", "alpha"])
def test_gradients_of_one_output_and_of_some_inputs(loss):
    """A loss on the image only or the alpha only (the other output has no gradient), with a
    background, and inputs of which only some require gradients."""
    means, quats, scales, opac, colors = make_scene(70, seed=21)
    vm, K = make_cameras(2, 26, 20)
    bg = torch.rand(2, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = {}
    for backend in ("torch", "warp"):
        m, o, c, b = (t.clone().requires_grad_(True) for t in (means, opac, colors, bg))
        img, alpha, _ = rasterization(m, quats, scales, o, c, vm, K, 26, 20, backgrounds=b, backend=backend)
        (img.square().sum() if loss == "image" else alpha.square().sum()).backward()
        grads[backend] = [m.grad, o.grad, c.grad, b.grad]
    for a, b in zip(grads["warp"], grads["torch"]):
        if b is None:
            assert a is None or not a.any()
            continue
        assert torch.allclose(a, b, atol=1e-10 * max(1.0, b.abs().max().item()), rtol=0)


def test_tile_counts_and_ids_are_consistent():
    """The projection's tile counts (tiles_per_gauss), the intersection list and the per-tile
    offsets agree with each other for every tile size, including ones that do not divide the image."""
    params = make_scene(150, dtype=torch.float32, seed=4)
    vm, K = make_cameras(2, 37, 29, dtype=torch.float32)
    for ts in (3, 8, 16, 21):
        _, _, meta = rasterization(*params, vm, K, 37, 29, tile_size=ts)
        counts = meta["tiles_per_gauss"].reshape(-1).long()
        ids = meta["flatten_ids"].long()
        assert int(counts.sum()) == ids.numel()
        assert torch.equal(torch.bincount(ids, minlength=counts.numel()), counts)
        offs = torch.cat([meta["isect_offsets"].reshape(-1).long(), torch.tensor([ids.numel()])])
        assert offs[0] == 0 and offs[-1] == ids.numel() and bool((offs[1:] >= offs[:-1]).all())
        # each tile's range holds intersections of that tile only, sorted by depth
        tiles = meta["isect_ids"] >> 32
        assert torch.equal(tiles, torch.sort(tiles).values)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size", [32, 40])
def test_the_sort_covers_every_key_bit_in_use(device, size):
    """The keys (camera-tile range, depth) come out fully sorted, also where the number of ranges is a
    power of two (2 cameras x 16 tiles: the sort stops at the largest range index's top bit) and where
    it is not."""
    params = [t.to(device) for t in make_scene(400, dtype=torch.float32, seed=11, spread=0.9)]
    vm, K = (t.to(device) for t in make_cameras(2, size, size, dtype=torch.float32))
    _, _, meta = rasterization(*params, vm, K, size, size, tile_size=8)
    keys = meta["isect_ids"]
    assert keys.numel() > 1000 and int((keys >> 32).max()) >= 16  # (both cameras' last tiles in use)
    assert torch.equal(keys, torch.sort(keys).values)


def test_sort_bits_cover_the_ranges_in_even_passes_on_cuda():
    """The sort covers every bit of the largest range index above the 32 depth bits; on CUDA in an
    even number of 8-bit passes (never past 64 bits), on the CPU no more than needed."""
    from ssgwarp.raster.ops import sort_bits
    for n in (1, 2, 3, 255, 256, 257, 4096, 8160, 65536, 65537, 2 ** 24, 2 ** 31 - 1):
        need = 32 + max(1, (n - 1).bit_length())
        cuda = sort_bits(n, cpu=False)
        assert need <= cuda <= 64 and cuda % 16 == 0 and cuda - need < 16
        assert sort_bits(n, cpu=True) == need
    assert sort_bits(256, cpu=False) == 48 and sort_bits(8160, cpu=False) == 48
    assert sort_bits(2 ** 24 + 1, cpu=False) == 64


@CUDA
def test_cuda_launches_follow_torchs_current_stream():
    """On a side stream the rasterizer's launches (and the sort) run on that stream: the result
    equals the default stream's without any synchronisation beyond torch's own."""
    params = [t.cuda() for t in make_scene(3000, dtype=torch.float32, seed=6, spread=0.3)]
    vm, K = (t.cuda() for t in make_cameras(1, 96, 80, dtype=torch.float32))
    ref = _render_and_grads(params, vm, K, 96, 80, deterministic=True)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        # a long kernel queued first on the side stream: work launched elsewhere would overtake it
        big = torch.randn(4096, 4096, device="cuda")
        for _ in range(5):
            big = big @ big / 64.0
        out = _render_and_grads(params, vm, K, 96, 80, deterministic=True)
    torch.cuda.current_stream().wait_stream(side)
    torch.cuda.synchronize()
    for a, b in zip(ref, out):
        assert torch.equal(a, b)
    assert wp.get_device("cuda:0").stream.cuda_stream != side.cuda_stream  # Warp's own stream is restored


@CUDA
@pytest.mark.parametrize("sh", [None, 3])
def test_cuda_float64_matches_reference(sh):
    """float64 on CUDA (exact rules) against the torch reference on CUDA: image and every gradient,
    two cameras, colours or SH."""
    params = [t.cuda() for t in make_scene(200, seed=9)]
    if sh is not None:
        params[4] = torch.randn(200, 16, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64).cuda()
    vm, K = (t.cuda() for t in make_cameras(2, 40, 30))
    res = {}
    for backend in ("torch", "warp"):
        leaves = [p.clone().requires_grad_(True) for p in params]
        img, alpha, _ = rasterization(*leaves, vm, K, 40, 30, sh_degree=sh, settings=RasterSettings.exact(),
                                      backend=backend)
        w = torch.linspace(-1, 1, img.numel(), dtype=img.dtype, device="cuda").reshape(img.shape)
        ((img * w).sum() + alpha.sum()).backward()
        res[backend] = [img.detach()] + [p.grad for p in leaves]
    for a, b in zip(res["warp"], res["torch"]):
        assert (a - b).abs().max().item() <= 1e-9 * max(1.0, b.abs().max().item())


def test_tile_size_default_per_device():
    """Without ``tile_size`` the CPU uses 8 (measured faster than gsplat's 16 there), CUDA keeps 16;
    under the default rules the image is the same at both."""
    from ssgwarp.raster.settings import DEFAULT_TILE_SIZE

    assert DEFAULT_TILE_SIZE == {"cuda": 16, "cpu": 8}
    params = make_scene(120, dtype=torch.float32, seed=7)
    vm, K = make_cameras(1, 40, 30, dtype=torch.float32)
    img, alpha, meta = rasterization(*params, vm, K, 40, 30)
    assert meta["tile_size"] == 8 and meta["tile_width"] == 5 and meta["isect_offsets"].shape == (1, 4, 5)
    img16, alpha16, meta16 = rasterization(*params, vm, K, 40, 30, tile_size=16)
    assert meta16["tile_size"] == 16
    assert torch.equal(img, img16) and torch.equal(alpha, alpha16)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("per_camera", [False, True])
def test_value_checks_in_the_projection(device, per_camera):
    """The value checks run inside the projection kernel (compiled with fast maths on CUDA): each
    failure is caught, in the last Gaussian, the last camera, per-camera colours and backgrounds."""
    dtype = torch.float32
    g = torch.Generator().manual_seed(0)
    n, c = 9, 3
    means = (torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0, 0, 3.0])).to(device)
    quats, scales = torch.randn(n, 4, generator=g).to(device), (torch.rand(n, 3, generator=g) * 0.1).to(device)
    opac = torch.rand(n, generator=g).to(device)
    colors = torch.rand(*((c,) if per_camera else ()), n, 4, generator=g).to(device)
    vm, K = (t.to(device=device, dtype=dtype) for t in make_cameras(c, 16, 16, dtype=dtype))
    bg = torch.rand(c, 4, generator=g).to(device)
    good = dict(means=means, quats=quats, scales=scales, opacities=opac, colors=colors, viewmats=vm, Ks=K)

    def last(t, v):
        t = t.clone()
        t.view(-1)[-1] = v
        return t

    rasterization(**good, width=16, height=16, backgrounds=bg)
    cases = [(dict(means=last(means, float("nan"))), "means has NaN/Inf"),
             (dict(quats=last(quats, float("inf"))), "quats has NaN/Inf"),
             (dict(scales=last(scales, float("-inf"))), "scales has NaN/Inf"),
             (dict(opacities=last(opac, float("nan"))), "opacities has NaN/Inf"),
             (dict(colors=last(colors, float("nan"))), "colors has NaN/Inf"),
             (dict(viewmats=last(vm, float("inf"))), "viewmats has NaN/Inf"),
             (dict(Ks=last(K, float("nan"))), "Ks has NaN/Inf"),
             (dict(quats=quats.index_fill(0, torch.tensor([n - 1], device=device), 0.0)), "zero quaternions"),
             (dict(scales=last(scales, -1e-30)), "scales has negative"),
             (dict(opacities=last(opac, 1.0 + 1e-6)), r"opacities must lie in \[0, 1\]"),
             (dict(Ks=K.index_fill(0, torch.tensor([c - 1], device=device), 0.0)), "non-positive focal")]
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            rasterization(**{**good, **change}, width=16, height=16, backgrounds=bg)
    with pytest.raises(ValueError, match="backgrounds has NaN/Inf"):
        rasterization(**good, width=16, height=16, backgrounds=last(bg, float("nan")))
    # no Gaussians to project: the checks still run on the cameras
    empty = [t[:0] for t in (means, quats, scales, opac)] + [colors[..., :0, :]]
    with pytest.raises(ValueError, match="Ks has NaN/Inf"):
        rasterization(*empty, vm, last(K, float("nan")), 16, 16)


def test_no_autograd_node_where_no_backward_can_follow(monkeypatch):
    """Gradients off, or on with no input requiring one: the ops' forwards run without an autograd
    node (``launch.apply``), giving the same image as a call that records one; with an input that
    requires a gradient the node is there and the backward runs."""
    means, quats, scales, opac, colors = make_scene(40, seed=5)
    vm, K = make_cameras(1, 24, 18)
    entered = []
    assert P.function_apply(P._Probe) is not None   # (its self-test run before counting)
    monkeypatch.setattr(P, "_BASE_APPLY", _counting(P._BASE_APPLY, entered))
    with torch.no_grad():
        img0, alpha0, _ = rasterization(means, quats, scales, opac, colors, vm, K, 24, 18)
    img1, alpha1, meta1 = rasterization(means, quats, scales, opac, colors, vm, K, 24, 18)
    assert entered == [] and img1.grad_fn is None and meta1["means2d"].grad_fn is None
    m = means.clone().requires_grad_(True)
    img2, alpha2, meta2 = rasterization(m, quats, scales, opac, colors, vm, K, 24, 18)
    assert len(entered) == 2 and img2.grad_fn is not None and meta2["means2d"].grad_fn is not None
    img2.sum().backward()
    assert m.grad is not None and m.grad.abs().sum() > 0
    for a, b in ((img0, img1), (img1, img2.detach()), (alpha0, alpha2.detach())):
        assert torch.equal(a, b)


def _counting(base, calls):
    """A stand-in for Function.apply's entry point that records each call, then calls it."""
    class Counting:
        def __get__(self, obj, cls):
            bound = base.__get__(obj, cls)

            def call(*args):
                calls.append(cls.__name__)
                return bound(*args)
            return call
    return Counting()


@pytest.mark.parametrize("device", DEVICES)
def test_blend_outputs_are_made_while_the_count_comes_back(device, monkeypatch):
    """The call's one read-back is split: the blending's outputs are made after the copy is queued
    and before the wait (host work that would otherwise wait for the GPU), and are the very tensors
    the call returns; a call without gradients makes no transmittance / last-index buffers. Images
    equal those of a call whose outputs the blending makes itself (the chunked path, which bypasses
    the early outputs, gives the same per channel block too)."""
    import ssgwarp.raster.blend_ops as B
    params = [t.to(device) for t in make_scene(60, seed=8)]
    vm, K = (t.to(device) for t in make_cameras(1, 40, 28))
    events, made = [], []
    start, finish, outputs = L.start_read_int64, L.finish_read_int64, B.blend_outputs

    def rec_start(*a):
        events.append("start")
        return start(*a)

    def rec_finish(*a):
        events.append("finish")
        return finish(*a)

    def rec_outputs(*a):
        events.append("outputs")
        made.append(outputs(*a))
        return made[-1]

    monkeypatch.setattr(L, "start_read_int64", rec_start)
    monkeypatch.setattr(L, "finish_read_int64", rec_finish)
    monkeypatch.setattr(B, "blend_outputs", rec_outputs)
    leaves = [p.clone().requires_grad_(True) for p in params]
    img, alpha, _ = rasterization(*leaves, vm, K, 40, 28)
    assert events == ["start", "outputs", "finish"]
    out, a, T, last, rows = made[0]
    assert img.data_ptr() == out.data_ptr() and alpha.data_ptr() == a.data_ptr()
    assert T is not None and last is not None and rows is not None
    (img.sum() + alpha.sum()).backward()
    assert all(p.grad is not None for p in leaves)
    events.clear()
    with torch.no_grad():
        img0, alpha0, _ = rasterization(*params, vm, K, 40, 28)
    assert events == ["start", "outputs", "finish"] and all(t is None for t in made[1][2:])
    assert torch.equal(img0, img.detach()) and torch.equal(alpha0, alpha.detach())
    # outputs made for a call without a backward, handed to one with: refused
    from ssgwarp.raster import ops
    _, _, meta = rasterization(*params, vm, K, 40, 28, tile_size=16)
    tiles = ops.bin_tiles(meta["means2d"], meta["radii"], meta["depths"], 16, meta["tile_width"],
                          meta["tile_height"])
    colors = params[4].clone().requires_grad_(True)
    with pytest.raises(ValueError, match="outputs made for another case"):
        B.blend_warp(meta["means2d"], meta["conics"], colors, meta["opacities"], None, tiles, 40, 28, 16,
                     RasterSettings(), outputs=made[1])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("sh", [None, 2])
@pytest.mark.parametrize("which", ["means", "quats", "scales", "opacities", "colors", "viewmats"])
def test_one_input_requiring_a_gradient_gets_it(device, sh, which):
    """A call where only one input requires a gradient (a frozen scene whose camera poses are refined,
    colours fine-tuned on frozen geometry) makes the autograd nodes and gives that input the
    gradient it gets when every input requires one."""
    names = ["means", "quats", "scales", "opacities", "colors"]
    params = [t.to(device) for t in make_scene(50, dtype=torch.float64, seed=9)]
    if sh is not None:
        g = torch.Generator().manual_seed(4)
        params[4] = (torch.randn(50, (sh + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.3).to(device)
    vm, K = (t.to(device) for t in make_cameras(2, 28, 20, dtype=torch.float64))
    inputs = dict(zip(names, params), viewmats=vm)

    def grad_of(trainable):
        leaves = {k: v.clone().requires_grad_(k in trainable) for k, v in inputs.items()}
        img, alpha, _ = rasterization(*(leaves[k] for k in names), leaves["viewmats"], K, 28, 20, sh_degree=sh)
        (img.square().sum() + alpha.sum()).backward()
        return leaves[which].grad

    alone, together = grad_of({which}), grad_of(set(inputs))
    assert alone is not None and alone.abs().sum() > 0
    torch.testing.assert_close(alone, together, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("threads", [1, 3])
def test_key_writes_clear_the_buffer_handed_back_during_the_wait(device, threads):
    """A buffer that ``bin_tiles``' ``during_wait`` returns is zeroed by the key-writing kernel, every
    value of it (a whole number per camera and Gaussian; filled with NaN first), also over several
    CPU runs, and the binning is the same as without it."""
    from ssgwarp.raster import ops
    params = [t.to(device) for t in make_scene(70, seed=4)]
    vm, K = (t.to(device) for t in make_cameras(2, 40, 28))
    _, _, meta = rasterization(*params, vm, K, 40, 28, tile_size=8)
    C, N = meta["depths"].shape
    buf = torch.full((C * N * 9,), float("nan"), dtype=meta["means2d"].dtype, device=device)
    args = (meta["means2d"], meta["radii"], meta["depths"], 8, meta["tile_width"], meta["tile_height"])
    cleared = ops.bin_tiles(*args, threads=threads, during_wait=lambda: buf)
    plain = ops.bin_tiles(*args, threads=threads)
    assert torch.equal(buf, torch.zeros_like(buf))
    assert torch.equal(cleared["isect_ids"], plain["isect_ids"]) and torch.equal(cleared["flatten_ids"],
                                                                                  plain["flatten_ids"])
    with pytest.raises(ValueError, match="buffer to clear must be"):  # (the kernel would address another type)
        ops.bin_tiles(*args, threads=threads, during_wait=lambda: buf.float() if buf.dtype != torch.float32
                      else buf.double())


@pytest.mark.parametrize("device", DEVICES)
def test_blending_backward_adds_into_the_rows_the_forward_made(device, monkeypatch):
    """Where a backward can follow, the call makes the blending backward's gradient rows with its
    outputs (zeroed by the key writes), and the backward adds into them instead of clearing a buffer
    of its own: the same gradients as a call without them; a second backward through the same graph
    (retain_graph) clears rows of its own again (reusing the first's would add onto its gradients);
    the deterministic backward, whose rows are per intersection, makes none."""
    import ssgwarp.raster.blend_ops as B
    params = [t.to(device) for t in make_scene(90, seed=6)]
    vm, K = (t.to(device) for t in make_cameras(1, 40, 28))
    cleared = []
    zeros = L.zeros

    def rec_zeros(*a):
        cleared.append(a[0])
        return zeros(*a)
    monkeypatch.setattr(L, "zeros", rec_zeros)

    def grads(retain=False, **kw):
        leaves = [p.clone().requires_grad_(True) for p in params]
        img, alpha, _ = rasterization(*leaves, vm, K, 40, 28, **kw)
        loss = (img * torch.linspace(0, 1, img.numel(), device=device).view(img.shape)).sum() + alpha.sum()
        loss.backward(retain_graph=retain)
        first = [p.grad.clone() for p in leaves]
        if not retain:
            return first, None
        for p in leaves:
            p.grad = None
        loss.backward()
        return first, [p.grad for p in leaves]

    made, again = grads(retain=True)
    assert cleared == [(90 * 9,)] or cleared == [(1, 90, 9)]  # (the second backward's, not the first's)
    cleared.clear()
    monkeypatch.setattr(B, "gradient_rows_size", lambda *a: 0)  # (calls that make no rows)
    own, _ = grads()
    assert len(cleared) == 1
    for a, b, c in zip(made, again, own):
        torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(b, c, rtol=1e-5, atol=1e-6)
    monkeypatch.undo()
    seen = []
    outputs = B.blend_outputs
    monkeypatch.setattr(B, "blend_outputs", lambda *a: seen.append(a[-1]) or outputs(*a))
    grads(deterministic=True)
    assert seen == [0]
