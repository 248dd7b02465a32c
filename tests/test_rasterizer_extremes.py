"""Gradient checks, numerical extremes, knobs, determinism and input validation of the rasterizer."""
import dataclasses

import pytest
import torch

from ssgwarp import RasterSettings, rasterization
from ssgwarp.core.cameras import intrinsics

from conftest import assert_close_elementwise
from test_rasterizer import GRAD_NAMES, assert_match, make_cameras, make_scene, run_both

EXACT = RasterSettings.exact()


def _front_camera(w, h, dtype=torch.float64, f=None, c=1):
    f = f or 0.9 * max(w, h)
    vm = torch.eye(4, dtype=dtype)[None].repeat(c, 1, 1)
    return vm, intrinsics(f, f, w / 2, h / 2, c, dtype=dtype)


@pytest.mark.parametrize("covariance", ["factor", "gsplat"])
def test_gradcheck_exact_float64(covariance):
    """torch.autograd.gradcheck on every differentiable input, exact gating, Warp backend, with
    both ways of forming the 2D covariance."""
    settings = dataclasses.replace(EXACT, covariance=covariance)
    g = torch.Generator().manual_seed(0)
    n = 4
    means = torch.tensor([[0.1, -0.05, 3.0], [-0.2, 0.1, 3.5], [0.05, 0.15, 4.0], [0.0, 0.0, 4.5]], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.3 + 0.4  # large: boxes cover the one tile
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.8 + 0.1
    colors = torch.rand(n, 2, generator=g, dtype=torch.float64)
    vm, K = _front_camera(12, 12, f=10.0)
    vm = vm.clone()
    vm[0, :3, 3] = torch.tensor([0.02, -0.01, 0.05], dtype=torch.float64)
    bg = torch.tensor([[0.3, 0.7]], dtype=torch.float64)

    def f(means, quats, scales, opac, colors, vm, bg):
        img, alpha, _ = rasterization(means, quats, scales, opac, colors, vm, K, 12, 12, settings=settings,
                                      backgrounds=bg, render_mode="RGB+D", backend="warp")
        return img, alpha

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors, vm, bg)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_deterministic_backward():
    g = torch.Generator().manual_seed(1)
    means = torch.tensor([[0.1, -0.05, 3.0], [-0.2, 0.1, 3.5], [0.05, 0.15, 4.0]], dtype=torch.float64)
    quats = torch.randn(3, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(3, 3, generator=g, dtype=torch.float64) * 0.3 + 0.4
    opac = torch.rand(3, generator=g, dtype=torch.float64) * 0.8 + 0.1
    colors = torch.rand(3, 3, generator=g, dtype=torch.float64)
    vm, K = _front_camera(12, 12, f=10.0, c=2)

    def f(means, opac, colors):
        return rasterization(means, quats, scales, opac, colors, vm, K, 12, 12, settings=EXACT,
                             deterministic=True)[0]

    assert torch.autograd.gradcheck(f, [t.clone().requires_grad_(True) for t in (means, opac, colors)],
                                    eps=1e-6, atol=1e-6, rtol=1e-4)


def test_deterministic_and_default_backward_match_reference():
    """Both backward variants (per-warp sums, and the deterministic per-intersection slots summed in a
    fixed order) give the reference's gradients entry by entry. (Run-to-run bit identity is a CUDA
    property, where atomics reorder sums: test_deterministic_bit_identical_cuda; on the CPU every run
    is serial, so repeating a CPU run proves nothing.)"""
    params = make_scene(200, dtype=torch.float32, seed=2)
    vm, K = make_cameras(2, 40, 32, dtype=torch.float32)
    grads = {}
    variants = (("reference", dict(backend="torch")), ("default", {}), ("deterministic", dict(deterministic=True)))
    for name, kw in variants:
        leaves = [p.clone().requires_grad_(True) for p in params]
        img, alpha, _ = rasterization(*leaves, vm, K, 40, 32, **kw)
        (img.sum() + 0.5 * alpha.sum()).backward()
        grads[name] = [p.grad for p in leaves]
    for variant in ("default", "deterministic"):
        for pname, a, b in zip(GRAD_NAMES, grads[variant], grads["reference"]):
            assert_close_elementwise(a, b, 2e-4, 1e-6, f"{variant} gradient of {pname}", ulps=16)


def test_deterministic_needs_small_tiles():
    params = make_scene(20, dtype=torch.float32, seed=2)
    vm, K = make_cameras(1, 40, 32, dtype=torch.float32)
    leaves = [p.clone().requires_grad_(True) for p in params]
    img, alpha, _ = rasterization(*leaves, vm, K, 40, 32, tile_size=32, deterministic=True)
    with pytest.raises(ValueError, match="tile_size <= 16"):
        img.sum().backward()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="fast_math is a CUDA compile option")
def test_fast_math_cuda_close_to_ieee():
    params = [p.cuda() for p in make_scene(3000, dtype=torch.float32, seed=5, spread=0.3)]
    vm, K = [t.cuda() for t in make_cameras(1, 128, 96, dtype=torch.float32)]
    out = {}
    for fast in (False, True):
        leaves = [p.clone().requires_grad_(True) for p in params]
        img, alpha, _ = rasterization(*leaves, vm, K, 128, 96, settings=RasterSettings(fast_math=fast))
        img.sum().backward()
        out[fast] = (img.detach(), leaves[0].grad)
    diff = (out[True][0] - out[False][0]).abs().max().item()
    # approximate exp/division: the same image within 1e-4 (whether any bit differs depends on the
    # GPU and the compiler, so it is not asserted)
    assert diff < 1e-4
    assert torch.allclose(out[True][1], out[False][1], rtol=1e-3, atol=1e-4)


def test_fast_math_is_a_setting_and_exact_turns_it_off():
    assert RasterSettings().fast_math is True
    assert RasterSettings.exact().fast_math is False
    assert RasterSettings(t_min=0.0).for_dtype(torch.float32).fast_math is True


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="bit-identity across runs matters on CUDA (atomics)")
def test_deterministic_bit_identical_cuda():
    params = [p.cuda() for p in make_scene(5000, dtype=torch.float32, seed=3, spread=0.3)]
    vm, K = make_cameras(2, 128, 96, dtype=torch.float32)
    vm, K = vm.cuda(), K.cuda()
    runs = []
    for _ in range(3):
        leaves = [p.clone().requires_grad_(True) for p in params]
        img, _, _ = rasterization(*leaves, vm, K, 128, 96, deterministic=True)
        img.sum().backward()
        runs.append([p.grad.clone() for p in leaves])
    for a, b in zip(runs[0], runs[2]):
        assert torch.equal(a, b)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="the warp-level gradient sums run on CUDA only")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_warp_sums_every_channel_count(dtype):
    """The CUDA backward sums each warp's gradients with a reduce-scatter whose layout depends on the
    packed gradient length (6 + D rounded up to 8, 16, 32, 64 or 128): every layout against the
    torch reference on the GPU, with two cameras and a tile that is not 16."""
    for D in (1, 3, 19, 32, 64):
        means, quats, scales, opac, _ = make_scene(300, dtype=dtype, seed=D)
        colors = torch.rand(300, D, generator=torch.Generator().manual_seed(D), dtype=dtype)
        params = [t.cuda() for t in (means, quats, scales, opac, colors)]
        vm, K = [t.cuda() for t in make_cameras(2, 53, 41, dtype=dtype)]
        grads, imgs = {}, {}
        for backend in ("torch", "warp"):
            leaves = [p.clone().requires_grad_(True) for p in params]
            img, alpha, _ = rasterization(*leaves, vm, K, 53, 41, tile_size=8, backend=backend, settings=EXACT)
            w = torch.linspace(-1, 1, img.numel(), dtype=dtype, device="cuda").reshape(img.shape)
            ((img * w).sum() + alpha.sum()).backward()
            imgs[backend], grads[backend] = img.detach(), [p.grad for p in leaves]
        tol = 1e-12 if dtype == torch.float64 else 1e-4
        assert_close_elementwise(imgs["warp"], imgs["torch"], 0.0, tol, f"image D={D}")
        # per entry: float32 sums in another order (warp shuffles, atomics) differ by ~eps * the sum
        # of the terms' magnitudes, which atol covers for entries near 0
        rtol, atol = (1e-11, 0.0) if dtype == torch.float64 else (2e-4, 0.0)
        for name, a, b in zip(GRAD_NAMES, grads["warp"], grads["torch"]):
            assert_close_elementwise(a, b, rtol, atol, f"gradient of {name}, D={D}", ulps=64)


# ------------------------------------------------------------------------------------------------
# extremes: all outputs finite and equal to the reference
# ------------------------------------------------------------------------------------------------
def _extreme_case(kind):
    means, quats, scales, opac, colors = make_scene(40, seed=11, spread=0.4, scale=0.1)
    means = means.clone()
    means[:, 2] += 3.0
    scales, opac = scales.clone(), opac.clone()
    if kind == "behind_and_near":
        means[:10, 2] = -2.0                 # behind the camera
        means[10:15, 2] = 0.01               # exactly at the near plane
        means[15:20, 2] = 0.0                # in the camera plane
    elif kind == "far":
        means[:20] *= 1e5
        means[:20, 2] = 1e6                  # depth 1e6
    elif kind == "tiny_huge_scales":
        scales[:10] = 1e-8
        scales[10:12] = 1e4
    elif kind == "anisotropy":
        scales[:20, 0] = 1e-3
        scales[:20, 1] = 1e3                 # 1e6 anisotropy
    elif kind == "opacity_extremes":
        opac[:20] = 1e-6
        opac[20:] = 1 - 1e-7
    elif kind == "offscreen":
        means[:, 0] += 100.0
    return means, quats, scales, opac, colors


@pytest.mark.parametrize("kind", ["behind_and_near", "far", "tiny_huge_scales", "anisotropy",
                                  "opacity_extremes", "offscreen"])
@pytest.mark.parametrize("settings", [RasterSettings(), EXACT], ids=["default", "exact"])
def test_extremes_match_reference(kind, settings):
    if kind == "anisotropy":
        # gsplat's J Sigma J^T cancels at anisotropy 1e6 (1e-8 relative even in float64, order 1 in
        # float32: docs/numerics.md); the cancellation-free form is the one for such scenes
        settings = dataclasses.replace(settings, covariance="factor")
    params = _extreme_case(kind)
    vm, K = _front_camera(40, 30)
    out = run_both(params, vm, K, 40, 30, settings=settings, render_mode="RGB+ED",
                   backgrounds=torch.tensor([[0.1, 0.2, 0.3, 0.0]], dtype=torch.float64)[:, :3])
    for img, alpha, grads, _ in out.values():
        assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
        assert all(torch.isfinite(g).all() for g in grads if g is not None)
    # docs/numerics.md lists the errors observed for each case (benchmarks/numerics.py)
    assert_match(out, 1e-9, 1e-8)
    if kind == "offscreen":
        assert out["warp"][3]["flatten_ids"].numel() == 0
        assert torch.all(out["warp"][1] == 0)


def test_covariance_forms_agree_and_factor_survives_anisotropy():
    """Both ways of forming the 2D covariance give the same image on an ordinary scene; at
    anisotropy 1e6 in float32 only the factor form stays close to the float64 render."""
    params = make_scene(120, seed=4)
    vm, K = make_cameras(2, 40, 32)
    imgs = {cov: rasterization(*params, vm, K, 40, 32, settings=RasterSettings(covariance=cov))[0]
            for cov in ("gsplat", "factor")}
    assert (imgs["gsplat"] - imgs["factor"]).abs().max().item() < 1e-12
    means, quats, scales, opac, colors = _extreme_case("anisotropy")
    vm1, K1 = _front_camera(40, 30)
    errs = {}
    for cov in ("gsplat", "factor"):
        st = RasterSettings(covariance=cov)
        ref = rasterization(means, quats, scales, opac, colors, vm1, K1, 40, 30, settings=st)[0]
        p32 = [t.float() for t in (means, quats, scales, opac, colors)]
        img = rasterization(*p32, vm1.float(), K1.float(), 40, 30, settings=st)[0]
        errs[cov] = (img.double() - ref).abs().max().item()
    assert errs["factor"] < 1e-4 < errs["gsplat"]


def test_covariance_setting_is_checked():
    with pytest.raises(ValueError, match="covariance"):
        RasterSettings(covariance="exact")
    assert RasterSettings().covariance == "gsplat" and RasterSettings.exact().covariance == "factor"


def test_thousands_of_layers_on_one_pixel():
    n = 5000
    g = torch.Generator().manual_seed(5)
    means = torch.zeros(n, 3, dtype=torch.float64)
    means[:, 2] = torch.linspace(2.0, 6.0, n, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.full((n, 3), 0.002, dtype=torch.float64)
    opac = torch.full((n,), 0.01, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    vm, K = _front_camera(8, 8, f=8.0)
    for settings in (RasterSettings(), EXACT):
        out = run_both([means, quats, scales, opac, colors], vm, K, 8, 8, settings=settings)
        for d in out.values():
            d[2].append(torch.zeros(1))
        assert_match(out, 1e-10, 1e-8)
    # float32: same thing, looser (T is rebuilt by division through thousands of layers: the
    # backward's rounding error grows with the layer count, measured ~700 roundoffs of the largest
    # entry on the viewmats gradient, a sum over all 5000 layers)
    p32 = [t.float() for t in (means, quats, scales, opac, colors)]
    out = run_both(p32, vm.float(), K.float(), 8, 8)
    for d in out.values():
        d[2].append(torch.zeros(1))
    assert_match(out, 1e-5, 1e-3, atol_grad=1e-6, ulps=2048)


def test_empty_and_many_cameras():
    vm, K = make_cameras(8, 20, 16)
    empty = [torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 4, dtype=torch.float64),
             torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, dtype=torch.float64),
             torch.zeros(0, 3, dtype=torch.float64)]
    img, alpha, meta = rasterization(*empty, vm, K, 20, 16, backgrounds=torch.ones(8, 3, dtype=torch.float64))
    assert img.shape == (8, 16, 20, 3) and torch.all(img == 1) and torch.all(alpha == 0)
    params = make_scene(60, seed=8)
    out = run_both(params, vm, K, 20, 16)
    for d in out.values():
        d[2].append(torch.zeros(1))
    assert_match(out, 1e-10, 1e-9)


# ------------------------------------------------------------------------------------------------
# knobs: each has its documented effect
# ------------------------------------------------------------------------------------------------
def test_knob_effects():
    params = make_scene(300, dtype=torch.float64, seed=9, spread=0.3, scale=0.2)
    vm, K = make_cameras(1, 32, 32)

    def render(**kw):
        img, alpha, meta = rasterization(*params, vm, K, 32, 32, **kw)
        return img, alpha, meta

    base, a_base, m_base = render()
    exact, a_exact, m_exact = render(settings=EXACT)
    ref_exact = rasterization(*params, vm, K, 32, 32, settings=EXACT, backend="torch")[0]
    assert torch.allclose(exact, ref_exact, atol=1e-10)
    # the fixed extent touches at least as many tiles as the opacity-aware one
    fixed = render(settings=RasterSettings(extent="fixed"))[2]
    assert int(fixed["tiles_per_gauss"].sum()) >= int(m_base["tiles_per_gauss"].sum())
    assert (fixed["radii"] >= m_base["radii"]).all()
    # a harder transmittance cut-off stops pixels earlier: less alpha, still close
    cut = render(settings=RasterSettings(t_min=0.3))[1]
    assert (cut <= a_base + 1e-12).all() and (cut < a_base - 1e-6).any()
    # alpha clamp: a single opaque Gaussian's alpha is capped at alpha_max
    one = [t[:1].clone() for t in params]
    one[0][0] = torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)
    one[3][0] = 0.99
    a_free = rasterization(*one, vm, K, 32, 32)[1].max().item()
    a_cap = rasterization(*one, vm, K, 32, 32, settings=RasterSettings(alpha_max=0.5))[1].max().item()
    assert a_free > 0.6 and a_cap == pytest.approx(0.5, abs=1e-12)
    # the threshold matters only slightly; errors of the default against exact are small
    assert (base - exact).abs().max() < 0.05
    assert (base - exact).abs().max() > 0
    # tile size changes only which far tails are cut: images agree closely
    for ts in (8, 32):
        img = render(tile_size=ts)[0]
        assert (img - base).abs().max() < 0.02


# ------------------------------------------------------------------------------------------------
# input validation
# ------------------------------------------------------------------------------------------------
def _good():
    params = list(make_scene(10, dtype=torch.float32))
    vm, K = make_cameras(1, 16, 16, dtype=torch.float32)
    return params, vm, K


@pytest.mark.parametrize("arg,mutate,word", [
    (0, lambda t: t.index_fill(0, torch.tensor([0]), float("nan")), "means"),
    (1, lambda t: t.index_fill(0, torch.tensor([2]), 0.0), "quats"),
    (2, lambda t: -t, "scales"),
    (3, lambda t: t + 2.0, "opacities"),
    (4, lambda t: t.index_fill(0, torch.tensor([1]), float("inf")), "colors"),
    (4, lambda t: t[:5], "colors"),
    (1, lambda t: t[:, :3], "quats"),
    (0, lambda t: t.double(), "float64"),
])
def test_bad_input_names_argument(arg, mutate, word):
    params, vm, K = _good()
    params[arg] = mutate(params[arg])
    with pytest.raises(ValueError, match=word):
        rasterization(*params, vm, K, 16, 16)


def _set_last(t, value):
    t = t.clone()
    t.view(-1)[-1] = value
    return t


@pytest.mark.parametrize("backend", ["warp", "torch"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_value_checks_each_message(backend, dtype):
    """Every value check fires with its own message, including for the very last element of the
    largest input (SH coefficients), and exact boundary values (opacity 0 and 1, scale 0) pass."""
    g = torch.Generator().manual_seed(0)
    n = 7
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3 + torch.tensor([0, 0, 3.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.1
    opac = torch.rand(n, generator=g, dtype=dtype)
    sh = torch.rand(n, 16, 3, generator=g, dtype=dtype)
    vm, K = make_cameras(2, 16, 16, dtype=dtype)
    bg = torch.rand(2, 3, generator=g, dtype=dtype)
    good = dict(means=means, quats=quats, scales=scales, opacities=opac, colors=sh, viewmats=vm, Ks=K)

    def run(**change):
        args = {**good, **{k: v for k, v in change.items() if k != "backgrounds"}}
        return rasterization(**args, width=16, height=16, sh_degree=3,
                             backgrounds=change.get("backgrounds", bg), backend=backend)

    edge_opac = opac.clone()
    edge_opac[0], edge_opac[1] = 0.0, 1.0
    edge_scales = scales.clone()
    edge_scales[0] = 0.0
    run(opacities=edge_opac, scales=edge_scales)  # boundary values are valid
    cases = [
        (dict(means=_set_last(means, float("nan"))), "means has NaN/Inf"),
        (dict(quats=_set_last(quats, float("inf"))), "quats has NaN/Inf"),
        (dict(scales=_set_last(scales, float("-inf"))), "scales has NaN/Inf"),
        (dict(opacities=_set_last(opac, float("nan"))), "opacities has NaN/Inf"),
        (dict(colors=_set_last(sh, float("nan"))), "colors has NaN/Inf"),
        (dict(viewmats=_set_last(vm, float("inf"))), "viewmats has NaN/Inf"),
        (dict(Ks=_set_last(K, float("nan"))), "Ks has NaN/Inf"),
        (dict(backgrounds=_set_last(bg, float("nan"))), "backgrounds has NaN/Inf"),
        (dict(quats=quats.index_fill(0, torch.tensor([n - 1]), 0.0)), "zero quaternions"),
        (dict(scales=_set_last(scales, -1e-30)), "scales has negative"),
        (dict(opacities=_set_last(opac, 1.0 + 1e-6)), r"opacities must lie in \[0, 1\]"),
        (dict(opacities=_set_last(opac, -1e-30)), r"opacities must lie in \[0, 1\]"),
        (dict(Ks=K.index_fill(0, torch.tensor([1]), 0.0)), "non-positive focal"),
    ]
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            run(**change)


def test_failed_check_marks_the_intersection_total():
    """The projection runs the value checks on what it loads: a Gaussian that fails one writes
    CHECK_FAILED into its slot of the scan instead of its tile count (camera 0 checks the Gaussian's
    own inputs, Gaussian 0 its camera's), the others their counts; without checks nothing is marked."""
    from ssgwarp.raster import ops

    params, vm, K = _good()
    vm = torch.cat([vm, vm])
    K = torch.cat([K, K])
    means, quats, scales, opac, colors = params
    scales = scales.clone()
    scales[4, 1] = -0.5  # Gaussian 4: a negative scale
    cfg = ops._project_cfg(torch.float32, 16, 16, 0.01, 1e10, 0.0, 0.3, False, RasterSettings(), 16, 1, 1)

    def ends(check):
        e = torch.full((2 * 10,), -7, dtype=torch.int64)
        extra = {"ends": e, "check": check, "colors": colors, "backgrounds": None, "sh": False}
        ops.apply(ops._Project, means, quats, scales, opac, vm, K, None, None, cfg, extra)
        return e, extra["counts"].view(-1)

    e, counts = ends(True)
    assert e[4] == ops.CHECK_FAILED and counts[4] == 0
    others = [i for i in range(20) if i != 4]
    assert torch.equal(e[others], counts[others].long()) and counts[others].sum() > 0
    e, counts = ends(False)
    assert (e < ops.CHECK_FAILED).all() and torch.equal(e, counts.long())


def test_non_finite_gaussians_are_culled_without_checks():
    """With validate=False a NaN mean or a NaN view matrix culls what it touches (radii and tile counts
    0: no garbage intersection counts), and the other Gaussians and cameras render as without them."""
    params, vm, K = _good()
    vm = torch.cat([vm, vm])
    K = torch.cat([K, K])
    bad = [t.clone() for t in params]
    bad[0][3] = float("nan")
    bad_vm = vm.clone()
    bad_vm[1, 0, 3] = float("nan")
    img, _, meta = rasterization(*bad, bad_vm, K, 16, 16, validate=False)
    assert (meta["radii"][:, 3] == 0).all() and (meta["tiles_per_gauss"][:, 3] == 0).all()
    assert (meta["radii"][1] == 0).all() and (meta["tiles_per_gauss"][1] == 0).all()
    keep = [i for i in range(10) if i != 3]
    ref, _, _ = rasterization(*[t[keep] for t in params], vm[:1], K[:1], 16, 16)
    assert torch.equal(img[0], ref[0]) and img[0].abs().max() > 0


def test_checks_on_their_own_and_false_alarms(monkeypatch):
    """Above CHECK_MAX_PAIRS (camera, Gaussian) pairs the checks run as a pass of their own (bad input
    still named, good input renders the same); a total that reaches CHECK_FAILED without a failed check
    (here: the mark lowered to 1) re-runs the checks, which pass, and the call goes on."""
    from ssgwarp.raster import ops

    params, vm, K = _good()
    ref = rasterization(*params, vm, K, 16, 16)[0]
    monkeypatch.setattr(ops, "CHECK_MAX_PAIRS", 5)
    assert torch.equal(rasterization(*params, vm, K, 16, 16)[0], ref)
    bad = list(params)
    bad[3] = bad[3] + 2.0
    with pytest.raises(ValueError, match="opacities"):
        rasterization(*bad, vm, K, 16, 16)
    monkeypatch.undo()
    calls = []
    check_values = ops.check_values
    monkeypatch.setattr(ops, "CHECK_FAILED", 1)
    monkeypatch.setattr(ops, "check_values", lambda *a, **k: calls.append(1) or check_values(*a, **k))
    assert torch.equal(rasterization(*params, vm, K, 16, 16)[0], ref)
    assert calls == [1]


def test_bad_cameras_and_modes():
    params, vm, K = _good()
    with pytest.raises(ValueError, match="Ks"):
        rasterization(*params, vm, K[:, :2], 16, 16)
    with pytest.raises(ValueError, match="viewmats"):
        rasterization(*params, vm.index_fill(1, torch.tensor([0]), float("nan")), K, 16, 16)
    with pytest.raises(ValueError, match="render_mode"):
        rasterization(*params, vm, K, 16, 16, render_mode="XYZ")
    with pytest.raises(ValueError, match="sh_degree"):
        rasterization(*params, vm, K, 16, 16, sh_degree=2)
    # validation can be switched off (garbage in, no error raised here)
    bad = list(params)
    bad[3] = bad[3] + 2.0
    rasterization(*bad, vm, K, 16, 16, validate=False)


def test_intersection_overflow_is_a_clear_error(monkeypatch):
    import ssgwarp.raster.ops as ops

    params, vm, K = _good()
    monkeypatch.setattr(ops, "INT32_MAX", 8)
    with pytest.raises(ValueError, match="intersections"):
        rasterization(*params, vm, K, 16, 16, backend="warp")
