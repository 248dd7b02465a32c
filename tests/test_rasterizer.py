"""The Warp rasterizer against the pure-torch reference (the spec), images and every gradient."""
import pytest
import torch

from ssgwarp import rasterization
from ssgwarp.core.cameras import intrinsics, look_at

from conftest import CUDA_ONLY, assert_close_elementwise


def make_scene(n, dtype=torch.float64, seed=0, spread=0.6, scale=0.15):
    g = torch.Generator().manual_seed(seed)
    means = (torch.randn(n, 3, generator=g) * spread).to(dtype)
    quats = torch.randn(n, 4, generator=g).to(dtype)
    scales = (torch.rand(n, 3, generator=g) * scale + 0.01).to(dtype)
    opac = torch.rand(n, generator=g).to(dtype)
    colors = torch.rand(n, 3, generator=g).to(dtype)
    return means, quats, scales, opac, colors


def make_cameras(c, w, h, dtype=torch.float64, dist=4.0):
    ang = torch.linspace(0, 1.2, c)
    eyes = torch.stack([dist * torch.sin(ang), -dist * torch.cos(ang), 0.3 * torch.ones(c)], -1)
    vm = look_at(eyes, torch.zeros(c, 3)).to(dtype)
    f = 0.8 * max(w, h)
    K = intrinsics(f, f * 1.05, w / 2 + 0.3, h / 2 - 0.2, c, dtype=dtype)
    return vm, K


def run_both(params, vm, K, w, h, seed=1, **kw):
    """Render with both backends, backprop the same random cotangents; return per-backend results."""
    out = {}
    for backend in ("torch", "warp"):
        leaves = [p.clone().requires_grad_(True) for p in params]
        vml = vm.clone().requires_grad_(True)
        bg = kw.pop("backgrounds", None)
        bgl = None if bg is None else bg.clone().requires_grad_(True)
        img, alpha, meta = rasterization(*leaves, vml, K, w, h, backend=backend, backgrounds=bgl, **kw)
        kw["backgrounds"] = bg
        meta["means2d"].retain_grad()
        g = torch.Generator().manual_seed(seed)
        wi = torch.randn(img.shape, generator=g, dtype=img.dtype)
        wa = torch.randn(alpha.shape, generator=g, dtype=img.dtype)
        ((img * wi).sum() + (alpha * wa).sum()).backward()
        grads = [p.grad for p in leaves] + [vml.grad, meta["means2d"].grad]
        if bgl is not None:
            grads.append(bgl.grad)
        out[backend] = (img.detach(), alpha.detach(), grads, meta)
    return out


GRAD_NAMES = ["means", "quats", "scales", "opacities", "colors", "viewmats", "means2d", "backgrounds"]


def assert_match(out, atol_img, rtol_grad, atol_grad=1e-12, ulps=16):
    """Same radii; images and alphas within ``atol_img``; every gradient entry within
    ``atol_grad + rtol_grad * |reference entry|`` plus ``ulps`` roundoffs of the gradient's largest
    entry (conftest.assert_close_elementwise)."""
    (ti, ta, tg, tm), (wi, wa, wg, wm) = out["torch"], out["warp"]
    assert torch.equal(tm["radii"], wm["radii"])
    assert_close_elementwise(wi, ti, 0.0, atol_img, "image")
    assert_close_elementwise(wa, ta, 0.0, atol_img, "alpha")
    for name, a, b in zip(GRAD_NAMES, tg, wg):
        if a is None or b is None:  # no path from the input to the outputs (depth-only, all culled)
            other = b if a is None else a
            assert other is None or not other.any(), name
            continue
        assert_close_elementwise(b, a, rtol_grad, atol_grad, f"gradient of {name}", ulps=ulps)


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED", "D"])
def test_float64_matches_reference(mode):
    params = make_scene(150)
    vm, K = make_cameras(2, 45, 37)  # non-square, not multiples of the tile size
    bg = None if mode == "D" else torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]], dtype=torch.float64)
    if bg is not None and mode == "RGB+ED":
        bg = None
    out = run_both(params, vm, K, 45, 37, render_mode=mode, backgrounds=bg)
    if bg is None:
        for d in out.values():
            d[2].append(torch.zeros(1))  # no background gradient to compare
    assert_match(out, 1e-10, 1e-9)


def test_float64_antialiased_sh_and_tiles():
    means, quats, scales, opac, _ = make_scene(120, seed=3)
    g = torch.Generator().manual_seed(4)
    sh = torch.randn(120, 16, 3, generator=g, dtype=torch.float64) * 0.3
    vm, K = make_cameras(3, 40, 40)
    for tile in (8, 16):
        out = run_both([means, quats, scales, opac, sh], vm, K, 40, 40, sh_degree=3, tile_size=tile,
                       rasterize_mode="antialiased")
        for d in out.values():
            d[2].append(torch.zeros(1))
        assert_match(out, 1e-10, 1e-9)


def test_float32_matches_reference():
    params = make_scene(200, dtype=torch.float32, seed=5)
    vm, K = make_cameras(2, 48, 40, dtype=torch.float32)
    out = run_both(params, vm, K, 48, 40, backgrounds=torch.rand(2, 3, generator=torch.Generator().manual_seed(6)))
    assert_match(out, 1e-5, 2e-4, atol_grad=1e-6)


def test_identity_channels_one_pass():
    """RGB + 16 identity channels in one pass equal the two renders done separately."""
    means, quats, scales, opac, colors = make_scene(100, dtype=torch.float32, seed=6)
    ids = torch.randn(100, 16, generator=torch.Generator().manual_seed(6))
    vm, K = make_cameras(2, 32, 32, dtype=torch.float32)
    both, _, _ = rasterization(means, quats, scales, opac, torch.cat([colors, ids], -1), vm, K, 32, 32)
    rgb, _, _ = rasterization(means, quats, scales, opac, colors, vm, K, 32, 32)
    idr, _, _ = rasterization(means, quats, scales, opac, ids, vm, K, 32, 32)
    ref, _, _ = rasterization(means, quats, scales, opac, ids, vm, K, 32, 32, backend="torch")
    assert both.shape == (2, 32, 32, 19)
    assert torch.allclose(both[..., :3], rgb, atol=1e-6)
    assert torch.allclose(both[..., 3:], idr, atol=1e-6)
    assert torch.allclose(idr, ref, atol=1e-5)


def test_many_channels_split_in_chunks():
    means, quats, scales, opac, _ = make_scene(50, dtype=torch.float32, seed=7)
    feats = torch.rand(50, 70, generator=torch.Generator().manual_seed(7))
    vm, K = make_cameras(1, 24, 24, dtype=torch.float32)
    a, _, _ = rasterization(means, quats, scales, opac, feats, vm, K, 24, 24)
    b, _, _ = rasterization(means, quats, scales, opac, feats, vm, K, 24, 24, backend="torch")
    assert torch.allclose(a, b, atol=1e-5)


def test_sh_kernel_matches_torch():
    from ssgwarp.raster.sh_ops import spherical_harmonics_warp
    from ssgwarp.core.sh import spherical_harmonics

    g = torch.Generator().manual_seed(0)
    for deg in range(4):
        dirs = torch.randn(2, 30, 3, generator=g, dtype=torch.float64)
        coeffs = torch.randn(2, 30, 16, 3, generator=g, dtype=torch.float64)
        outs = []
        for f in (spherical_harmonics, spherical_harmonics_warp):
            d, c = dirs.clone().requires_grad_(True), coeffs.clone().requires_grad_(True)
            y = f(deg, d, c)
            (y * torch.arange(3, dtype=torch.float64)).sum().backward()
            dg = torch.zeros_like(d) if d.grad is None else d.grad  # degree 0 ignores the direction
            outs.append((y.detach(), dg, c.grad))
        for a, b in zip(*outs):
            assert torch.allclose(a, b, atol=1e-12, rtol=0)


def test_camera_centres_kernel_and_both_sh_paths():
    """The camera centres the SH directions start from: one Warp kernel when the view matrices need
    no gradient (the inverse's translation: ``-R^T t`` for a rigid camera, any invertible matrix
    too), torch's inverse when they do; both give the same image."""
    from ssgwarp.raster.sh_ops import camera_centres

    eyes = torch.tensor([[3.0, -1.0, 0.5], [-2.0, 2.5, 1.0], [0.1, 0.2, -4.0]])
    vm = look_at(eyes, torch.zeros(3, 3))
    for dt, tol in ((torch.float64, 1e-12), (torch.float32, 2e-6)):
        got = camera_centres(vm.to(dt))
        assert got.dtype == dt and got.shape == (3, 3)
        assert (got - eyes.to(dt)).abs().max() < tol * 4
        assert (got - torch.linalg.inv(vm.to(dt))[:, :3, 3]).abs().max() < tol * 4
    general = torch.randn(4, 4, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert torch.allclose(camera_centres(general), torch.linalg.inv(general)[:, :3, 3], atol=1e-10, rtol=0)
    # the two paths in a render: same image; the differentiable one gives the view matrices a gradient
    means, quats, scales, opac, _ = make_scene(40)
    sh = torch.randn(40, 9, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 0.4
    vm2, K = make_cameras(2, 20, 16)
    img_fast, _, _ = rasterization(means, quats, scales, opac, sh, vm2, K, 20, 16, sh_degree=2)
    vml = vm2.clone().requires_grad_(True)
    img_grad, _, _ = rasterization(means, quats, scales, opac, sh, vml, K, 20, 16, sh_degree=2)
    assert torch.allclose(img_fast, img_grad.detach(), atol=1e-12, rtol=0)
    img_grad.sum().backward()
    assert vml.grad is not None and vml.grad.abs().sum() > 0


def test_densification_gradient_in_meta():
    means, quats, scales, opac, colors = make_scene(60, dtype=torch.float32)
    means.requires_grad_(True)
    vm, K = make_cameras(1, 32, 32, dtype=torch.float32)
    img, _, meta = rasterization(means, quats, scales, opac, colors, vm, K, 32, 32)
    meta["means2d"].retain_grad()
    img.sum().backward()
    g = meta["means2d"].grad
    assert g.shape == (1, 60, 2)
    visible = (meta["radii"] > 0).all(-1)
    assert (g[~visible] == 0).all()
    assert g[visible].abs().sum() > 0
    for key in ("radii", "means2d", "depths", "conics", "opacities", "tiles_per_gauss", "isect_ids",
                "flatten_ids", "isect_offsets", "tile_width", "tile_height"):
        assert key in meta
    assert int(meta["tiles_per_gauss"].sum()) == meta["flatten_ids"].numel()



@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA_ONLY)])
@pytest.mark.parametrize("cams,sh", [(1, False), (2, False), (1, True)])
def test_retained_graph_and_repeated_renders_add_up(cams, sh, device):
    """Two backwards of different losses through one retained graph, and two renders of the same leaves
    in one loss, give the sum of the two losses' gradients: each backward starts from zeroed rows of
    its own and writes gradients autograd does not already hold (the blending's rows, the
    projection's slots, the colours' rows of their own)."""
    means, quats, scales, opac, colors = make_scene(50, seed=3)
    if sh:
        colors = torch.randn(50, 4, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 0.3
    means, quats, scales, opac, colors = (t.to(device) for t in (means, quats, scales, opac, colors))
    vm, K = (t.to(device) for t in make_cameras(cams, 24, 20))
    kw = {"sh_degree": 1} if sh else {}
    losses = (lambda img, alpha: img.sum() + 0.5 * alpha.sum(), lambda img, alpha: (img * img).sum())

    def run(pairs):
        """``pairs``: (render index, loss index) per backward; renders made first, then the backwards."""
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
        outs = [rasterization(*leaves, vm, K, 24, 20, **kw) for _ in range(1 + max(r for r, _ in pairs))]
        for o in outs:
            o[2]["means2d"].retain_grad()
        for i, (r, k) in enumerate(pairs):
            losses[k](*outs[r][:2]).backward(retain_graph=i + 1 < len(pairs))
        return [t.grad for t in leaves], [o[2]["means2d"].grad for o in outs]

    (a, (ma,)), (b, (mb,)) = run([(0, 0)]), run([(0, 1)])
    for grads, screen, expected_screen in ((*run([(0, 0), (0, 1)]), [ma + mb]), (*run([(0, 0), (1, 1)]), [ma, mb])):
        for x, y, g in zip(a, b, grads):
            assert x.abs().sum() > 0 and y.abs().sum() > 0
            assert torch.allclose(x + y, g, atol=1e-12, rtol=1e-10)
        for e, g in zip(expected_screen, screen):
            assert torch.allclose(e, g, atol=1e-12, rtol=1e-10)
