"""Pure-torch dense reference of the rasterizer: the spec the Warp kernels are held to.

Every rule of the Warp kernels is written here once more in plain torch, densely
(every Gaussian against every pixel, O(C*N*H*W) memory in pixel chunks), and
differentiated by torch autograd. It is slow and meant for tests and small
images; :func:`rasterization_reference` has the signature of
:func:`ssgwarp.rasterization`.

Rules (gsplat 1.5.3 classic mode, with :class:`~ssgwarp.RasterSettings` knobs):
- EWA projection, Jacobian clamped at 1.3x the field of view; the 2D covariance
  is ``J (R M M^T R^T) J^T`` (``M = R_q S``) with determinant ``ad - bc``
  (``covariance="gsplat"``), or formed from its 2x3 factor ``A = J R M`` as
  ``A A^T`` with the determinant as the squared cross product of A's rows (no
  cancellation; ``covariance="factor"``);
- ``eps2d`` added to the 2D covariance (antialiased: opacity times
  ``sqrt(det(cov) / det(cov + eps2d I))``);
- culled (radii 0, outputs 0): depth outside [near, far], blurred
  determinant <= 0, opacity < alpha_min, radius <= radius_clip on both axes,
  or the extent box entirely off-screen;
- per-axis radius ``ceil(e * sqrt(cov_ii))`` with ``e = min(sigma_max,
  sqrt(2 ln(opacity / alpha_min)))`` (extent "opacity") or ``sigma_max``;
- a Gaussian touches a pixel only if the pixel's tile lies in its tile box;
- front to back by depth (ties: lower index first); ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``
  with pixel centres at +0.5; ``alpha = min(alpha_max, opacity exp(-sigma))``;
  skipped if ``sigma < 0`` or ``alpha < alpha_min``; the Gaussian that would
  bring T to ``<= t_min`` ends the pixel and is not blended; the pixel's alpha
  is the sum of the blending weights (``1 - T`` in exact arithmetic).
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from ..core.geometry import quat_to_rotmat
from .settings import INPUTS, RasterSettings, check_shapes, raise_for_flags, resolve_arguments
from ..core.sh import spherical_harmonics

Tensor = torch.Tensor
RADIUS_LIMIT = 1073741824.0  # radii saturate at 2^30 px (as kernels/projection.py)


def extent_sigmas(opacities: Tensor, settings: RasterSettings) -> Tensor:
    """Extent in standard deviations per Gaussian (the opacity-aware rule or the fixed one)."""
    full = torch.full_like(opacities, settings.sigma_max)
    if settings.extent == "fixed" or settings.alpha_min <= 0.0:
        return full
    ratio = (opacities / settings.alpha_min).clamp_min(1.0)
    return torch.minimum(full, torch.sqrt(2.0 * torch.log(ratio)))


def project_reference(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      viewmats: Tensor, Ks: Tensor, width: int, height: int, *,
                      near_plane: float = 0.01, far_plane: float = 1e10, radius_clip: float = 0.0,
                      eps2d: float = 0.3, antialiased: bool = False,
                      settings: RasterSettings = RasterSettings()):
    """EWA projection of N Gaussians into C cameras.

    Returns ``radii [C,N,2] int32, means2d [C,N,2], depths [C,N], conics [C,N,3],
    opacities [C,N]`` (times the antialiasing compensation when ``antialiased``);
    culled Gaussians have radii 0 and zeros elsewhere.
    """
    C, N = viewmats.shape[0], means.shape[0]
    R = viewmats[:, None, :3, :3]                       # [C,1,3,3]
    t = viewmats[:, None, :3, 3]                        # [C,1,3]
    mean_c = (R @ means[None, :, :, None])[..., 0] + t  # [C,N,3]
    x, y, z = mean_c.unbind(-1)
    valid = (z >= near_plane) & (z <= far_plane)
    zs = torch.where(valid, z, torch.ones_like(z))       # safe z (no inf/nan on culled paths)

    Rq = quat_to_rotmat(quats)                           # [N,3,3]
    M = Rq * scales[:, None, :]                          # covariance = M M^T

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    tx = zs * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x / zs))
    ty = zs * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y / zs))
    zero = torch.zeros_like(zs)
    J = torch.stack([
        fx / zs, zero, -fx * tx / (zs * zs),
        zero, fy / zs, -fy * ty / (zs * zs),
    ], dim=-1).reshape(C, N, 2, 3)
    mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)
    if settings.covariance == "gsplat":
        # J (R Sigma R^T) J^T with Sigma = M M^T, determinant a d - b c (gsplat's formula)
        cov_c = R @ (M @ M.transpose(-1, -2))[None] @ R.transpose(-1, -2)
        cov = J @ cov_c @ J.transpose(-1, -2)                # [C,N,2,2]
        a, b, c = cov[..., 0, 0], cov[..., 1, 0], cov[..., 1, 1]
        det_orig = a * c - b * cov[..., 0, 1]
        a, c = a + eps2d, c + eps2d
        det = a * c - b * cov[..., 0, 1]
    else:
        # 2D covariance J R M (J R M)^T from its 2x3 factor: sums of squares, and the determinant as
        # the squared cross product of the rows (Binet-Cauchy), free of cancellation
        A = J @ R @ M[None]                                  # [C,N,2,3]
        r0, r1 = A[..., 0, :], A[..., 1, :]
        a, b, c = (r0 * r0).sum(-1), (r0 * r1).sum(-1), (r1 * r1).sum(-1)
        det_orig = (torch.linalg.cross(r0, r1) ** 2).sum(-1)
        det = det_orig + eps2d * (a + c) + eps2d * eps2d     # det of the covariance + eps2d I
        a, c = a + eps2d, c + eps2d
    valid = valid & (det > 0)
    dets = torch.where(valid, det, torch.ones_like(det))
    conic = torch.stack([c / dets, -b / dets, a / dets], dim=-1)
    opac = opacities[None].expand(C, N)
    if antialiased:
        opac = opac * torch.sqrt(torch.clamp_min(det_orig / dets, 0.0))
    if settings.alpha_min > 0:
        valid = valid & (opac >= settings.alpha_min)
    ext = extent_sigmas(opac.detach(), settings)
    with torch.no_grad():
        rx = torch.ceil(ext * torch.sqrt(torch.where(valid, a, torch.ones_like(a)))).clamp_max(RADIUS_LIMIT)
        ry = torch.ceil(ext * torch.sqrt(torch.where(valid, c, torch.ones_like(c)))).clamp_max(RADIUS_LIMIT)
        valid = valid & ~((rx <= radius_clip) & (ry <= radius_clip))
        mx, my = mean2d[..., 0], mean2d[..., 1]
        valid = valid & ~((mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height))
        radii = torch.stack([rx, ry], dim=-1).where(valid[..., None], torch.zeros_like(mean2d)).to(torch.int32)
    v = valid[..., None]
    return (radii, torch.where(v, mean2d, 0.0), torch.where(valid, z, 0.0),
            torch.where(v, conic, 0.0), torch.where(valid, opac, 0.0))


def tile_boxes(means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int, tile_height: int) -> Tensor:
    """``[..., 4]`` (x0, y0, x1, y1) half-open tile box of each Gaussian (empty when culled)."""
    r = radii.to(means2d.dtype)
    tx, ty = means2d[..., 0] / tile_size, means2d[..., 1] / tile_size
    rx, ry = r[..., 0] / tile_size, r[..., 1] / tile_size
    x0 = torch.floor(tx - rx).clamp(0, tile_width)
    y0 = torch.floor(ty - ry).clamp(0, tile_height)
    x1 = torch.ceil(tx + rx).clamp(0, tile_width)
    y1 = torch.ceil(ty + ry).clamp(0, tile_height)
    box = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.int64)
    culled = (radii[..., 0] <= 0) | (radii[..., 1] <= 0)
    return torch.where(culled[..., None], torch.zeros_like(box), box)


def blend_reference(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, radii: Tensor,
                    depths: Tensor, width: int, height: int, tile_size: int = 16,
                    backgrounds: Optional[Tensor] = None, settings: RasterSettings = RasterSettings(),
                    max_chunk: int = 1 << 22, absgrad=None):
    """Dense front-to-back blending: ``colors [C,N,D]`` → ``(image [C,H,W,D], alpha [C,H,W,1])``.
    ``absgrad``: None, or a function that the backward calls with ``(camera, gaussian ids [n],
    values [n, 2])``: the sums over pixels of the absolute per-pixel gradients of those Gaussians'
    2D means (each pixel's own copy of the means is differentiated, so autograd's sum over pixels
    is taken apart)."""
    C, N, D = colors.shape
    dev, dt = colors.device, colors.dtype
    tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
    boxes = tile_boxes(means2d.detach(), radii, tile_size, tw, th)
    out_img, out_alpha, kept = [], [], {}
    for ci in range(C):
        order = torch.sort(depths[ci].detach(), stable=True).indices
        m2, cn, col, op, bx = means2d[ci][order], conics[ci][order], colors[ci][order], opacities[ci][order], boxes[ci][order]
        keep = (bx[:, 2] > bx[:, 0]) & (bx[:, 3] > bx[:, 1])
        kept[ci] = order[keep]
        m2, cn, col, op, bx = m2[keep], cn[keep], col[keep], op[keep], bx[keep]
        n = m2.shape[0]
        rows_per_chunk = max(1, min(height, max_chunk // max(1, n * width)))
        img_rows, alpha_rows = [], []
        for y0 in range(0, height, rows_per_chunk):
            ys = torch.arange(y0, min(height, y0 + rows_per_chunk), device=dev)
            xs = torch.arange(width, device=dev)
            py, px = torch.meshgrid(ys, xs, indexing="ij")
            px, py = px.reshape(-1), py.reshape(-1)
            txp, typ = px // tile_size, py // tile_size
            inside = ((txp[:, None] >= bx[None, :, 0]) & (txp[:, None] < bx[None, :, 2])
                      & (typ[:, None] >= bx[None, :, 1]) & (typ[:, None] < bx[None, :, 3]))  # [P,n]
            mp = m2[None]
            if absgrad is not None and m2.requires_grad and torch.is_grad_enabled():
                mp = m2[None].expand(px.shape[0], -1, -1)            # [P,n,2]: one copy per pixel
                ids = kept[ci]
                mp.register_hook(lambda g, ci=ci, ids=ids: absgrad(ci, ids, g.abs().sum(0)))
            dx = mp[..., 0] - (px.to(dt)[:, None] + 0.5)
            dy = mp[..., 1] - (py.to(dt)[:, None] + 0.5)
            sigma = 0.5 * (cn[None, :, 0] * dx * dx + cn[None, :, 2] * dy * dy) + cn[None, :, 1] * dx * dy
            alpha = torch.clamp_max(op[None, :] * torch.exp(-sigma), settings.alpha_max)
            use = inside & (sigma >= 0) & (alpha >= settings.alpha_min)
            alpha = torch.where(use, alpha, torch.zeros_like(alpha))
            one_minus = 1.0 - alpha
            T_next = torch.cumprod(one_minus, dim=1)
            blended = (T_next > settings.t_min) & use
            alpha = torch.where(blended, alpha, torch.zeros_like(alpha))
            T_incl = torch.cumprod(1.0 - alpha, dim=1)
            T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
            w = alpha * T_excl                                   # [P,n]
            T_final = T_incl[:, -1:] if n > 0 else torch.ones(px.shape[0], 1, dtype=dt, device=dev)
            pix = w @ col if n > 0 else torch.zeros(px.shape[0], D, dtype=dt, device=dev)
            if backgrounds is not None:
                pix = pix + T_final * backgrounds[ci][None, :]
            img_rows.append(pix.reshape(len(ys), width, D))
            alpha_rows.append(w.sum(dim=1, keepdim=True).reshape(len(ys), width, 1))
        out_img.append(torch.cat(img_rows, 0))
        out_alpha.append(torch.cat(alpha_rows, 0))
    return torch.stack(out_img), torch.stack(out_alpha)


def add_absgrad(target: Tensor, values: Tensor) -> None:
    """Add ``values`` to ``target.absgrad`` (set by the first backward; later ones add to it, as
    ``.grad`` sums over backward passes)."""
    prev = getattr(target, "absgrad", None)
    target.absgrad = values if prev is None else prev + values


def pack_visible(radii: Tensor, means2d: Tensor, depths: Tensor, conics: Tensor, opacities: Tensor):
    """gsplat's packed layout of the projection's ``[C, N, ...]`` outputs: ``(meta, means2d_dense,
    visible)``. ``meta``: ``camera_ids``, ``gaussian_ids`` (int64 ``[nnz]``, the (camera, Gaussian)
    pairs with both radii > 0, camera-major and by Gaussian index, gsplat's order), ``radii [nnz, 2]``,
    ``means2d [nnz, 2]``, ``depths [nnz]``, ``conics [nnz, 3]``, ``opacities [nnz]`` (differentiable
    gathers of the dense ones). ``means2d_dense``: ``[C, N, 2]`` made back from the packed means2d,
    the same values as ``means2d`` where visible (0 elsewhere, never read), for the blending to
    read, so that the packed ``means2d`` lies on the loss's path and its ``.grad`` (and
    ``absgrad``) are the blending's, as in gsplat. ``visible``: ``[C, N]`` bool."""
    visible = (radii > 0).all(dim=-1)
    cid, gid = visible.nonzero(as_tuple=True)
    m2 = means2d[cid, gid]
    dense = means2d.new_zeros(means2d.shape).index_put((cid, gid), m2)
    meta = {"camera_ids": cid, "gaussian_ids": gid, "radii": radii[cid, gid], "means2d": m2,
            "depths": depths[cid, gid], "conics": conics[cid, gid], "opacities": opacities[cid, gid]}
    return meta, dense, visible


def pack_tiles(tiles_per_gauss: Tensor, flatten_ids: Tensor, visible: Tensor) -> tuple[Tensor, Tensor]:
    """The binning's ``tiles_per_gauss [C, N]`` and ``flatten_ids [M]`` (indices into ``C * N``) in
    the packed layout: ``[nnz]`` and indices into the ``nnz`` packed rows (int32, as gsplat's)."""
    flat = visible.reshape(-1)
    pos = flat.to(torch.int32).cumsum(0, dtype=torch.int32) - 1
    return tiles_per_gauss.reshape(-1)[flat], pos[flatten_ids.long()]


def check_values_reference(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds=None) -> list:
    """The input value checks of ``kernels/validate.py`` in torch: a list of ``N_FLAGS`` ints in
    the slots of :mod:`ssgwarp.raster.settings` (NaN/Inf per input of ``INPUTS``, then zero quaternion,
    negative scale, opacity outside [0, 1], non-positive focal length), for
    :func:`ssgwarp.raster.settings.raise_for_flags`. Shapes must already be consistent."""
    inputs = (means, quats, scales, opacities, colors, viewmats, Ks, backgrounds)
    checks = [torch.zeros((), dtype=torch.bool, device=means.device) if t is None else ~torch.isfinite(t).all()
              for t in inputs]
    assert len(checks) == len(INPUTS)
    checks += [(quats == 0).all(dim=-1).any(), (scales < 0).any(), ((opacities < 0) | (opacities > 1)).any(),
               ((Ks[:, 0, 0] <= 0) | (Ks[:, 1, 1] <= 0)).any()]
    return [int(v) for v in torch.stack(checks).tolist()]


def mode_channels(colors, depths, backgrounds, render_mode, C):
    """The blended channels of a render mode: colours, depth, or colours then depth (and the
    background of each)."""
    if render_mode in ("RGB+D", "RGB+ED"):
        if colors.ndim == 2:
            colors = colors[None].expand(C, -1, -1)
        colors = torch.cat([colors, depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, torch.zeros_like(backgrounds[:, :1])], dim=-1)
    elif render_mode in ("D", "ED"):
        colors = depths[..., None]
        if backgrounds is not None:
            backgrounds = torch.zeros_like(backgrounds[:, :1])
    return colors, backgrounds


def expected_depth(render_colors, render_alphas, render_mode):
    """The expected-depth modes: the blended depth channel divided by the alpha."""
    if render_mode in ("ED", "RGB+ED"):
        render_colors = torch.cat(
            [render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)], dim=-1)
    return render_colors


def render_reference(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
                     radius_clip, eps2d, sh_degree, tile_size, backgrounds, render_mode, rasterize_mode, settings,
                     validate, packed=False, absgrad=False):
    """:func:`ssgwarp.rasterization` with ``backend="torch"``, its arguments resolved (``settings``
    for the dtype, ``tile_size`` an int): the checks in torch, projection, SH colours and blending
    by this module. No Warp kernel runs. ``packed``: meta in gsplat's packed layout
    (:func:`pack_visible`); ``absgrad``: ``meta["means2d"].absgrad`` after a backward."""
    if validate:
        check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                     render_mode, rasterize_mode, tile_size, near_plane)
        raise_for_flags(check_values_reference(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds))
    C = viewmats.shape[0]
    antialiased = rasterize_mode == "antialiased"
    radii, means2d, depths, conics, opacs = project_reference(
        means, quats, scales, opacities, viewmats, Ks, width, height, near_plane=near_plane, far_plane=far_plane,
        radius_clip=radius_clip, eps2d=eps2d, antialiased=antialiased, settings=settings)
    if sh_degree is not None:
        # inv_ex: no singularity check, so no device synchronisation per call
        campos = torch.linalg.inv_ex(viewmats).inverse[:, :3, 3]
        dirs = means[None] - campos[:, None]
        shs = colors if colors.ndim == 4 else colors[None].expand(C, -1, -1, -1)
        visible = (radii > 0).all(dim=-1)
        cols = spherical_harmonics(sh_degree, dirs, shs)
        colors = torch.where(visible[..., None], torch.clamp_min(cols + 0.5, 0.0), 0.0)
    elif colors.ndim == 2:
        colors = colors[None].expand(C, -1, -1)
    colors, backgrounds = mode_channels(colors, depths, backgrounds, render_mode, C)
    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    meta = {
        "radii": radii, "means2d": means2d, "depths": depths, "conics": conics, "opacities": opacs,
        "tile_width": tile_width, "tile_height": tile_height, "width": width, "height": height,
        "tile_size": tile_size, "n_cameras": C, "settings": settings, "backend": "torch",
    }
    sink = None
    if packed:
        pmeta, means2d, visible = pack_visible(radii, means2d, depths, conics, opacs)
        meta.update(pmeta)
        cid, gid = pmeta["camera_ids"], pmeta["gaussian_ids"]
        if absgrad:
            sink = lambda v: add_absgrad(pmeta["means2d"], v[cid, gid])  # noqa: E731
    elif absgrad:
        sink = lambda v: add_absgrad(meta["means2d"], v)  # noqa: E731
    to_dense = None
    if sink is not None:
        def to_dense(ci, ids, vals):
            dense = torch.zeros(C, means2d.shape[1], 2, dtype=vals.dtype, device=vals.device)
            dense[ci].index_add_(0, ids, vals)
            sink(dense)
    render_colors, render_alphas = blend_reference(
        means2d, conics, colors, opacs, radii, depths, width, height, tile_size, backgrounds, settings,
        absgrad=to_dense)
    return expected_depth(render_colors, render_alphas, render_mode), render_alphas, meta


def rasterization_reference(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=0.01,
                            far_plane=1e10, radius_clip=0.0, eps2d=0.3, sh_degree=None, packed=None, tile_size=None,
                            backgrounds=None, render_mode="RGB", sparse_grad=False, absgrad=False,
                            rasterize_mode="classic", channel_chunk=32, *, settings=None, deterministic=False,
                            validate=True, camera_model="pinhole"):
    """:func:`ssgwarp.rasterization` computed by this module (the same as ``backend="torch"``;
    ``packed=None``/``False``: the ``[C, N]`` layout, ``True``: gsplat's packed one)."""
    settings, tile_size = resolve_arguments(means, settings, tile_size, camera_model)
    return render_reference(means, quats, scales, opacities, colors, viewmats, Ks, int(width), int(height),
                            near_plane, far_plane, radius_clip, eps2d, sh_degree, tile_size, backgrounds,
                            render_mode, rasterize_mode, settings, validate, packed is True, absgrad)
