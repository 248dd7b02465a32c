"""gsplat 1.5.3 arguments of ``ssgwarp.rasterization`` beyond the images: ``absgrad``, ``packed=True``
(gsplat's packed meta), ``camera_model``, and ``backend="auto"`` without the kernels.

gsplat's documented semantics checked here: ``meta["means2d"].absgrad`` is, per Gaussian and camera,
the sum over pixels of the absolute value of each pixel's gradient of the 2D mean (so it is at least
``|means2d.grad|``, equal where all pixels pull the same way); the packed meta holds the visible
(camera, Gaussian) pairs as ``camera_ids`` / ``gaussian_ids [nnz]`` and ``[nnz, ...]`` tensors, with
``flatten_ids`` indexing those rows.
"""
from __future__ import annotations

import warnings

import pytest
import torch

from ssgwarp import RasterSettings, rasterization
from ssgwarp.raster import rasterize
from ssgwarp.raster.reference import rasterization_reference

from conftest import CUDA_ONLY, assert_close_elementwise
from test_rasterizer import make_cameras, make_scene

F64 = torch.float64
W, H = 40, 30


def scene(n=50, dtype=F64, seed=3):
    return list(make_scene(n, dtype=dtype, seed=seed)), *make_cameras(2, W, H, dtype=dtype)


def render_backward(params, vm, K, *, backend="warp", device="cpu", weight_seed=5, **kw):
    """Render, backprop a fixed random weighting of the image (gradients of both signs per pixel);
    returns ``(image, meta, leaves)``."""
    leaves = [p.to(device).clone().requires_grad_(True) for p in params]
    img, alpha, meta = rasterization(*leaves, vm.to(device), K.to(device), W, H, backend=backend, **kw)
    meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(weight_seed)
    wi = torch.randn(img.shape, generator=g, dtype=img.dtype).to(device)
    ((img * wi).sum() + alpha.sum()).backward()
    return img.detach(), meta, leaves


# ------------------------------------------------------------------------------------------ absgrad
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_absgrad_of_the_kernels_equals_the_reference(dtype):
    params, vm, K = scene(dtype=dtype)
    _, mw, _ = render_backward(params, vm, K, backend="warp", absgrad=True)
    _, mt, _ = render_backward(params, vm, K, backend="torch", absgrad=True)
    a, b = mw["means2d"].absgrad, mt["means2d"].absgrad
    assert a.shape == b.shape == mw["means2d"].shape == (2, 50, 2) and a.dtype == dtype
    tol = 1e-10 if dtype == F64 else 2e-4
    assert_close_elementwise(a, b, rtol=tol, atol=tol * float(b.abs().max()), name="absgrad")
    assert float(b.sum()) > 0


def test_absgrad_bounds_the_gradient_and_exceeds_it_where_pixels_disagree():
    params, vm, K = scene()
    _, meta, _ = render_backward(params, vm, K, absgrad=True)
    m = meta["means2d"]
    assert (m.absgrad >= m.grad.abs() - 1e-12).all()
    drawn = (meta["radii"] > 0).all(-1)
    # a random weighting of the pixels: most drawn Gaussians get pulls of both signs
    assert (m.absgrad[drawn] > m.grad.abs()[drawn] * 1.01 + 1e-9).float().mean() > 0.5
    assert (m.absgrad[~drawn] == 0).all()


def test_absgrad_equals_the_gradient_where_every_pixel_pulls_the_same_way():
    """One round Gaussian whose centre lies left of the image: every pixel it covers lies right of
    its centre, and the summed image pulls it the same way everywhere: |grad x| == absgrad x. Its
    y gradient comes from pixels above and below the centre, of both signs: absgrad y > |grad y|."""
    means = torch.tensor([[-0.05, 0.0, 2.0]], dtype=F64)     # x = -0.05 * f / 2 + cx: about 3 px left of the image
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=F64)
    scales = torch.full((1, 3), 0.06, dtype=F64)
    opac = torch.tensor([0.9], dtype=F64)
    colors = torch.tensor([[0.2, 0.5, 0.7]], dtype=F64)
    vm = torch.eye(4, dtype=F64)[None]
    K = torch.tensor([[[40.0, 0, 0.5], [0, 40.0, H / 2], [0, 0, 1]]], dtype=F64)
    for backend in ("warp", "torch"):
        leaves = [p.clone().requires_grad_(True) for p in (means, quats, scales, opac, colors)]
        img, _, meta = rasterization(*leaves, vm, K, W, H, absgrad=True, backend=backend)
        meta["means2d"].retain_grad()
        img.sum().backward()
        m = meta["means2d"]
        assert float(m[0, 0, 0].detach()) < 0 and (meta["radii"] > 0).all()
        gx, ax = float(m.grad[0, 0, 0]), float(m.absgrad[0, 0, 0])
        assert gx != 0 and ax == pytest.approx(abs(gx), rel=1e-12)
        assert float(m.absgrad[0, 0, 1]) > 1.5 * abs(float(m.grad[0, 0, 1]))


def test_absgrad_is_the_same_for_every_backward_variant():
    """Deterministic slots, several CPU threads and the default walk: one absgrad (and the other
    gradients unchanged by absgrad)."""
    params, vm, K = scene(n=80)
    _, base, lb = render_backward(params, vm, K, absgrad=True)
    _, plain, lp = render_backward(params, vm, K)
    assert not hasattr(plain["means2d"], "absgrad")          # off: nothing computed or attached
    for a, b in zip(lb, lp):
        assert_close_elementwise(a.grad, b.grad, rtol=1e-12, atol=1e-14, name="gradient with absgrad")
    for kw in ({"deterministic": True}, {"settings": RasterSettings(cpu_threads=3)}):
        _, m, _ = render_backward(params, vm, K, absgrad=True, **kw)
        assert_close_elementwise(m["means2d"].absgrad, base["means2d"].absgrad, rtol=1e-12, atol=1e-14,
                                 name=f"absgrad {kw}")


def test_absgrad_adds_up_over_backward_passes_and_needs_a_means_gradient():
    params, vm, K = scene()
    leaves = [p.clone().requires_grad_(True) for p in params]
    img, _, meta = rasterization(*leaves, vm, K, W, H, absgrad=True)
    img.sum().backward(retain_graph=True)
    first = meta["means2d"].absgrad.clone()
    img.sum().backward()
    assert torch.allclose(meta["means2d"].absgrad, 2 * first, rtol=1e-12, atol=0)
    # only the colours learn: no gradient reaches the means, no absgrad either (and no error)
    cols = params[4].clone().requires_grad_(True)
    img, _, meta = rasterization(*params[:4], cols, vm, K, W, H, absgrad=True)
    img.sum().backward()
    assert cols.grad is not None and not hasattr(meta["means2d"], "absgrad")


@pytest.mark.parametrize("device", [pytest.param("cuda", marks=CUDA_ONLY)])
def test_absgrad_on_cuda_equals_the_reference(device):
    """The CUDA kernels' absgrad against the torch reference on the same device (the GPU machine compiles
    CUDA kernels only, so the CPU kernels are not the yardstick here)."""
    params, vm, K = scene(n=300, dtype=torch.float32)
    _, mc, _ = render_backward(params, vm, K, device=device, backend="torch", absgrad=True)
    for kw in ({}, {"deterministic": True}):
        _, md, _ = render_backward(params, vm, K, device=device, absgrad=True, **kw)
        assert_close_elementwise(md["means2d"].absgrad.cpu(), mc["means2d"].absgrad.cpu(), rtol=1e-3,
                                 atol=1e-4 * float(mc["means2d"].absgrad.abs().max()), name="absgrad cuda")


# ------------------------------------------------------------------------------------------- packed
@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_packed_meta_is_gsplats_layout_with_the_unpacked_values(backend):
    params, vm, K = scene(n=60)
    params[0] = params[0].clone()
    params[0][::4, 0] += 3.0                                    # some Gaussians out of one camera's view or both
    img_u, mu, lu = render_backward(params, vm, K, backend=backend, absgrad=True)
    img_p, mp, lp = render_backward(params, vm, K, backend=backend, absgrad=True, packed=True)
    _, mf, _ = render_backward(params, vm, K, backend=backend, packed=False)
    assert torch.equal(img_u, img_p)
    assert "camera_ids" not in mu and "camera_ids" not in mf and mf["means2d"].shape == (2, 60, 2)
    cid, gid = mp["camera_ids"], mp["gaussian_ids"]
    visible = (mu["radii"] > 0).all(-1)
    nnz = int(visible.sum())
    assert 0 < nnz < 2 * 60 and cid.dtype == gid.dtype == torch.int64 and cid.shape == gid.shape == (nnz,)
    exp_c, exp_g = visible.nonzero(as_tuple=True)       # camera-major, by Gaussian index
    assert torch.equal(cid, exp_c) and torch.equal(gid, exp_g)
    shapes = {"radii": (nnz, 2), "means2d": (nnz, 2), "depths": (nnz,), "conics": (nnz, 3), "opacities": (nnz,)}
    for k, shape in shapes.items():
        assert mp[k].shape == shape and mp[k].dtype == mu[k].dtype, k
        assert torch.equal(mp[k].detach(), mu[k][cid, gid].detach()), k
    # the gradients: the packed means2d's are the unpacked ones of the visible pairs; the leaves' equal
    assert_close_elementwise(mp["means2d"].grad, mu["means2d"].grad[cid, gid], rtol=1e-12, atol=1e-14, name="grad")
    assert_close_elementwise(mp["means2d"].absgrad, mu["means2d"].absgrad[cid, gid], rtol=1e-12, atol=1e-14,
                             name="absgrad")
    for a, b in zip(lp, lu):
        assert_close_elementwise(a.grad, b.grad, rtol=1e-12, atol=1e-14, name="leaf gradient")
    if backend == "warp":  # the binning's outputs, indexing the packed rows
        N = 60
        assert torch.equal(mp["isect_ids"], mu["isect_ids"]) and torch.equal(mp["isect_offsets"], mu["isect_offsets"])
        assert mp["tiles_per_gauss"].shape == (nnz,) and mp["flatten_ids"].dtype == torch.int32
        assert torch.equal(mp["tiles_per_gauss"], mu["tiles_per_gauss"].reshape(2, N)[cid, gid])
        f = mp["flatten_ids"].long()
        assert torch.equal(cid[f] * N + gid[f], mu["flatten_ids"].long())


def test_packed_with_nothing_visible():
    params, vm, K = scene(n=10)
    params[0] = params[0] + 100.0                               # far outside every camera
    img, alpha, meta = rasterization(*params, vm, K, W, H, packed=True)
    assert meta["camera_ids"].shape == (0,) and meta["means2d"].shape == (0, 2) and meta["flatten_ids"].numel() == 0
    assert float(alpha.abs().max()) == 0


# ------------------------------------------------------------------------------------- camera_model
@pytest.mark.parametrize("fn", [rasterization, rasterization_reference])
def test_camera_model_pinhole_only_with_one_clear_error_per_other_model(fn):
    params, vm, K = scene(n=5)
    img, _, _ = fn(*params, vm, K, W, H, camera_model="pinhole")
    assert torch.equal(img, fn(*params, vm, K, W, H)[0])
    messages = set()
    for model in ("ortho", "fisheye", "ftheta"):
        with pytest.raises(ValueError, match=f"camera_model='{model}' is not supported") as e:
            fn(*params, vm, K, W, H, camera_model=model)
        messages.add(str(e.value))
    assert len(messages) == 3
    with pytest.raises(ValueError, match="camera_model must be 'pinhole'"):
        fn(*params, vm, K, W, H, camera_model="equirect")


# ------------------------------------------------------------------------- backend="auto" fallback
def test_auto_backend_without_kernels_warns_once_or_refuses_large_calls(monkeypatch):
    params, vm, K = scene(n=8)
    monkeypatch.setattr(rasterize, "ops", None)
    monkeypatch.setattr(rasterize, "KERNELS_ERROR", "ImportError: No module named 'warp'")
    monkeypatch.setattr(rasterize, "_warned_fallback", False)
    with pytest.warns(RuntimeWarning, match="ssgwarp.kernels cannot be imported.*No module named 'warp'"):
        img, _, meta = rasterization(*params, vm, K, W, H)
    assert meta["backend"] == "torch"
    assert torch.equal(img, rasterization(*params, vm, K, W, H, backend="torch")[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")                          # once per process
        rasterization(*params, vm, K, W, H)
    monkeypatch.setattr(rasterize, "AUTO_FALLBACK_MAX", 2 * 8 * W * H - 1)
    with pytest.raises(ImportError, match="backend='torch' to accept the slow path"):
        rasterization(*params, vm, K, W, H)
    with pytest.raises(ImportError, match="needs warp-lang"):
        rasterization(*params, vm, K, W, H, backend="warp")
    assert rasterization(*params, vm, K, W, H, backend="torch")[2]["backend"] == "torch"
