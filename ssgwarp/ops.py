"""Torch autograd ops over the Warp kernels (``ssgwarp.kernels``).

Tensors are shared with Warp zero-copy (``wp.from_torch``); CPU tensors run on
Warp's CPU device, CUDA tensors on the same CUDA device and on torch's current
stream. float32 and float64 use the same kernel source, built per precision.
"""
from __future__ import annotations

import contextlib
import ctypes
import math

import torch
import warp as wp

from .kernels import binning, blend_backward, blend_forward, projection, sh, validate
from .kernels.types import channel_vector, types_for

try:  # the launch descriptor wp.from_torch(..., return_ctype=True) builds; made directly here
    from warp._src.types import array_t as _array_t
except ImportError:  # another Warp layout: go through wp.from_torch
    _array_t = None

Tensor = torch.Tensor
_INIT = False
MAX_CHANNELS = 64


def _init() -> None:
    global _INIT
    if not _INIT:
        # keep Warp's per-module "load ... (compiled)" lines off the terminal; warnings still show
        wp.config.log_level = max(int(wp.config.log_level), int(wp.LOG_WARNING))
        wp.init()
        _INIT = True


def _scalar(dtype: torch.dtype):
    if dtype == torch.float32:
        return wp.float32
    if dtype == torch.float64:
        return wp.float64
    raise ValueError(f"ssgwarp kernels support float32 and float64, got {dtype}")


def _fast(settings, scalar) -> bool:
    """Fast maths (approximate exp, log, division, square roots) in the CUDA kernels: float32 only
    (a CUDA compile option; the CPU build ignores it)."""
    return bool(settings.fast_math) and scalar == wp.float32


def _device(t: Tensor) -> str:
    if t.device.type == "cuda":
        return f"cuda:{t.device.index if t.device.index is not None else torch.cuda.current_device()}"
    if t.device.type == "cpu":
        return "cpu"
    raise ValueError(f"ssgwarp kernels run on CPU or CUDA tensors, got {t.device}")


def _wp(t: Tensor, dtype=None, ndim: int = 1, ctype: bool = True):
    """Zero-copy ``ndim``-D Warp view of a tensor; ``dtype`` groups the trailing axes into vectors/matrices.

    ``ctype=True`` returns the light launch descriptor, built directly from the tensor's pointer,
    shape and strides (the cheapest launch argument); ``ctype=False`` a full ``wp.array`` (needed
    by ``wp.utils``).
    """
    t = t.detach()
    if not t.is_contiguous():
        t = t.contiguous()
    inner = tuple(getattr(dtype, "_shape_", ())) if dtype is not None else ()
    lead = t.shape[: t.ndim - len(inner)]
    keep = tuple(lead[len(lead) - (ndim - 1):]) if ndim > 1 else ()
    t = t.reshape(-1, *keep, *inner)
    if not ctype or _array_t is None:
        return wp.from_torch(t, dtype=dtype, return_ctype=ctype)
    scalar = dtype._type_ if dtype is not None else None
    if scalar is not None and ctypes.sizeof(scalar) != t.element_size():
        raise TypeError(f"internal: a {t.dtype} tensor passed as Warp {dtype}")
    shape = tuple(t.shape[: t.ndim - len(inner)])
    size = t.element_size()
    strides = tuple(st * size for st in t.stride()[: len(shape)])
    if not shape:
        shape, strides = (1,), (size,)
    arr = _array_t(t.data_ptr(), 0, len(shape), shape, strides)
    arr.tensor = t  # a contiguous copy made here must live until the launch has been queued
    return arr


_STREAMS: dict = {}


def _warp_stream(device: torch.device):
    """The Warp stream wrapping torch's current CUDA stream (wrappers cached per stream)."""
    ts = torch.cuda.current_stream(device)
    key = (ts.device_index, ts.cuda_stream)
    ws = _STREAMS.get(key)
    if ws is None:
        ws = _STREAMS[key] = wp.stream_from_torch(ts)
    return ws


class _Launcher:
    """Runs launches on the Warp device/stream matching a torch tensor."""

    def __init__(self, like: Tensor):
        _init()
        self.device = _device(like)
        self.stream = _warp_stream(like.device) if like.device.type == "cuda" else None

    def launch(self, kernel, dim, inputs, outputs=(), adj_inputs=(), adj_outputs=(), adjoint=False,
               block_dim=None):
        if (isinstance(dim, int) and dim == 0) or (not isinstance(dim, int) and math.prod(dim) == 0):
            return
        wp.launch(kernel, dim=dim, inputs=list(inputs), outputs=list(outputs), adj_inputs=list(adj_inputs),
                  adj_outputs=list(adj_outputs), adjoint=adjoint, device=self.device, stream=self.stream,
                  record_tape=False, block_dim=block_dim)


# ---------------------------------------------------------------------------------------------
# input value checks
# ---------------------------------------------------------------------------------------------
def check_values(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds=None) -> Tensor:
    """Flags of the value checks of :mod:`.kernels.validate` (one kernel, no synchronisation):
    an int64 tensor ``[N_FLAGS]`` on the inputs' device, non-zero where a check failed (slot ``i``
    < 8: NaN/Inf in ``validate.INPUTS[i]``; then zero quaternion, negative scale, opacity outside
    [0, 1], non-positive focal length). Shapes must already be consistent."""
    flat = [t.detach().reshape(-1) for t in (means, quats, scales, opacities, colors, viewmats, Ks)]
    flat.append(backgrounds.detach().reshape(-1) if backgrounds is not None else flat[0][:0])
    flags = torch.zeros(validate.N_FLAGS, dtype=torch.int64, device=means.device)
    kern = validate.check_kernel(_scalar(means.dtype))
    _Launcher(means).launch(kern, max(t.numel() for t in flat),
                            [*(_wp(t) for t in flat), means.shape[0], viewmats.shape[0]], [_wp(flags)])
    return flags


# ---------------------------------------------------------------------------------------------
# projection
# ---------------------------------------------------------------------------------------------
class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, params, variant):
        width, height, near, far, eps2d, radius_clip, alpha_min, sigma_max, opacity_extent, antialiased = params
        C, N = viewmats.shape[0], means.shape[0]
        dt, dev = means.dtype, means.device
        s = _scalar(dt)
        T = types_for(s)
        means2d = torch.zeros(C, N, 2, dtype=dt, device=dev)
        depths = torch.zeros(C, N, dtype=dt, device=dev)
        conics = torch.zeros(C, N, 3, dtype=dt, device=dev)
        opac = torch.zeros(C, N, dtype=dt, device=dev)
        radii = torch.zeros(C, N, 2, dtype=torch.int32, device=dev)
        L = _Launcher(means)
        scal = [width, height, near, far, eps2d, radius_clip, alpha_min, sigma_max, opacity_extent, antialiased]
        L.launch(projection.projection_kernel(s, False, *variant), (C, N),
                 [_wp(means, T.vec3), _wp(quats, T.vec4), _wp(scales, T.vec3), _wp(opacities),
                  _wp(viewmats, T.mat44), _wp(Ks, T.mat33), N, *scal],
                 [_wp(means2d, T.vec2), _wp(depths), _wp(conics, T.vec3), _wp(opac), _wp(radii, wp.vec2i)])
        ctx.save_for_backward(means, quats, scales, opacities, viewmats, Ks, means2d, depths, conics, opac, radii)
        ctx.scal, ctx.variant = scal, variant
        ctx.mark_non_differentiable(radii)
        return radii, means2d, depths, conics, opac

    @staticmethod
    def backward(ctx, _g_radii, g_means2d, g_depths, g_conics, g_opac):
        means, quats, scales, opacities, viewmats, Ks, means2d, depths, conics, opac, radii = ctx.saved_tensors
        C, N = viewmats.shape[0], means.shape[0]
        s = _scalar(means.dtype)
        T = types_for(s)
        L = _Launcher(means)
        zeros = lambda t: torch.zeros_like(t)  # noqa: E731
        g = [x if x is not None else zeros(y) for x, y in
             ((g_means2d, means2d), (g_depths, depths), (g_conics, conics), (g_opac, opac))]
        g = [x.contiguous() for x in g]
        # Each thread writes its own adjoint slot: per Gaussian when C == 1, else per
        # (camera, Gaussian) pair ("expanded", summed over cameras by torch). No two threads share
        # an adjoint address, so the result is deterministic and free of atomic contention. The
        # view matrices' adjoint is kept per pair as well, and only when asked for.
        need_vm = ctx.needs_input_grad[4]
        expanded = C > 1 or need_vm
        if expanded:
            ex = lambda t: t[None].expand(C, *t.shape).reshape(C * N, *t.shape[1:]).contiguous()  # noqa: E731
            ins = [ex(means), ex(quats), ex(scales), ex(opacities),
                   viewmats[:, None].expand(C, N, 4, 4).reshape(C * N, 4, 4).contiguous()]
        else:
            ins = [means, quats, scales, opacities, viewmats]
        adj = [torch.zeros_like(t) for t in ins[:4]] + [torch.zeros_like(ins[4]) if need_vm else None]
        kern = projection.projection_kernel(s, expanded, *ctx.variant)
        dtypes = [T.vec3, T.vec4, T.vec3, None, T.mat44]
        ins_wp = [_wp(t, d) for t, d in zip(ins, dtypes)]
        adj_wp = [None if t is None else _wp(t, d) for t, d in zip(adj, dtypes)]
        outs = [_wp(means2d, T.vec2), _wp(depths), _wp(conics, T.vec3), _wp(opac), _wp(radii, wp.vec2i)]
        adj_outs = [_wp(g[0], T.vec2), _wp(g[1]), _wp(g[2], T.vec3), _wp(g[3]), None]
        L.launch(kern, (C, N), [*ins_wp, _wp(Ks, T.mat33), N, *ctx.scal], outs,
                 [*adj_wp, None, 0, *([0] * 2 + [0.0] * 6 + [0] * 2)], adj_outs, adjoint=True)
        if expanded:
            v_means, v_quats, v_scales, v_opac = (a.reshape(C, N, *a.shape[1:]).sum(0) for a in adj[:4])
            v_view = adj[4].reshape(C, N, 4, 4).sum(1) if need_vm else None
        else:
            v_means, v_quats, v_scales, v_opac, v_view = adj
        return v_means, v_quats, v_scales, v_opac, v_view, None, None, None


def project_warp(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane=0.01,
                 far_plane=1e10, radius_clip=0.0, eps2d=0.3, antialiased=False, settings=None):
    """Warp version of :func:`ssgwarp.reference.project_reference` (same outputs)."""
    params = (int(width), int(height), float(near_plane), float(far_plane), float(eps2d), float(radius_clip),
              float(settings.alpha_min), float(settings.sigma_max), int(settings.extent == "opacity"),
              int(bool(antialiased)))
    return _Project.apply(means, quats, scales, opacities, viewmats, Ks, params,
                          (settings.covariance, _fast(settings, _scalar(means.dtype))))


# ---------------------------------------------------------------------------------------------
# spherical harmonics
# ---------------------------------------------------------------------------------------------
class _SH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, degree, dirs, coeffs):
        shape = dirs.shape[:-1]
        K = (degree + 1) ** 2
        d = dirs.reshape(-1, 3).contiguous()
        c = coeffs[..., :K, :].reshape(-1, K, 3).contiguous()
        s = _scalar(dirs.dtype)
        T = types_for(s)
        out = torch.empty_like(d)
        _Launcher(dirs).launch(sh.sh_kernel(s, degree), d.shape[0], [_wp(d, T.vec3), _wp(c, T.vec3, 2)], [_wp(out, T.vec3)])
        ctx.save_for_backward(d, c, out)
        ctx.degree, ctx.shape, ctx.cshape = degree, shape, coeffs.shape
        return out.reshape(*shape, 3)

    @staticmethod
    def backward(ctx, g):
        d, c, out = ctx.saved_tensors
        s = _scalar(d.dtype)
        T = types_for(s)
        vd, vc = torch.zeros_like(d), torch.zeros_like(c)
        g = g.reshape(-1, 3).contiguous()
        _Launcher(d).launch(sh.sh_kernel(s, ctx.degree), d.shape[0], [_wp(d, T.vec3), _wp(c, T.vec3, 2)],
                            [_wp(out, T.vec3)], [_wp(vd, T.vec3), _wp(vc, T.vec3, 2)], [_wp(g, T.vec3)], adjoint=True)
        K = c.shape[1]
        v_coeffs = torch.zeros(ctx.cshape, dtype=d.dtype, device=d.device)
        v_coeffs[..., :K, :] = vc.reshape(*ctx.shape, K, 3)
        return None, vd.reshape(*ctx.shape, 3), v_coeffs


def spherical_harmonics_warp(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Warp version of :func:`ssgwarp.sh.spherical_harmonics`: ``dirs [...,3]``, ``coeffs [...,K,3]`` → ``[...,3]``."""
    return _SH.apply(int(degree), dirs, coeffs)


# ---------------------------------------------------------------------------------------------
# tile binning
# ---------------------------------------------------------------------------------------------
INT32_MAX = 2**31 - 1


def bin_tiles(means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_width: int, tile_height: int,
              pending=None) -> dict:
    """Tile intersections of projected Gaussians, sorted by (camera, tile, depth).

    Returns ``tiles_per_gauss [C,N]``, ``isect_ids [M]`` (int64 keys), ``flatten_ids [M]`` (flat
    camera*N + Gaussian index per sorted intersection), ``isect_offsets [C,th,tw]`` and, for the
    backward, ``offsets [C*th*tw+1]``, ``perm [M]`` (pre-sort slot of each sorted intersection),
    ``isect_ends [C*N]``. ``pending``: ``(flags, check)`` from deferred input validation, read
    back with the intersection count and checked before anything else.
    """
    C, N = depths.shape
    s = _scalar(means2d.dtype)
    T = types_for(s)
    dev = means2d.device
    L = _Launcher(means2d)
    n_ranges = C * tile_width * tile_height
    if n_ranges >= INT32_MAX:
        raise ValueError(f"rasterization: {C} cameras x {tile_width * tile_height} tiles exceed the 2^31 tile "
                         "ranges one call can index; render fewer cameras per call or use a larger tile_size")
    m2 = _wp(means2d.reshape(C * N, 2), T.vec2)
    rd = _wp(radii.reshape(C * N, 2), wp.vec2i)
    counts = torch.zeros(C * N, dtype=torch.int64, device=dev)
    L.launch(binning.count_kernel(s), C * N, [m2, rd, tile_size, tile_width, tile_height], [_wp(counts)])
    ends = torch.cumsum(counts, 0)
    total = ends[-1:] if ends.numel() else torch.zeros(1, dtype=torch.int64, device=dev)
    if pending is not None:
        values, check = pending
        host = torch.cat([total, values]).tolist()
        check(host[1:])
        n_isects = int(host[0])
    else:
        n_isects = int(total)
    if n_isects > INT32_MAX // 2:
        raise ValueError(
            f"rasterization: {n_isects:,} Gaussian-tile intersections exceed the {INT32_MAX // 2:,} one call can "
            "sort; render fewer cameras per call, lower the resolution, raise tile_size, or cull large Gaussians "
            "(radius_clip / RasterSettings.sigma_max)")
    starts = ends - counts
    depth_bits = depths.detach().reshape(-1).to(torch.float32).view(torch.int32).to(torch.int64) & 0xFFFFFFFF
    # every entry below n_isects is written by the kernel; the upper halves are the sort's scratch
    keys = torch.empty(2 * max(n_isects, 1), dtype=torch.int64, device=dev)
    values = torch.empty(2 * max(n_isects, 1), dtype=torch.int32, device=dev)
    gauss = torch.empty(max(n_isects, 1), dtype=torch.int32, device=dev)
    L.launch(binning.write_kernel(s), C * N,
             [m2, rd, _wp(depth_bits), _wp(starts), N, tile_size, tile_width, tile_height],
             [_wp(keys), _wp(values), _wp(gauss)])
    offsets = torch.zeros(n_ranges + 1, dtype=torch.int32, device=dev)
    if n_isects > 0:
        end_bit = 32 + max(1, int(n_ranges).bit_length())
        on_stream = wp.ScopedStream(L.stream) if L.stream is not None else contextlib.nullcontext()
        with wp.ScopedDevice(L.device), on_stream:
            wp.utils.radix_sort_pairs(_wp(keys, ctype=False), _wp(values, ctype=False), n_isects, 0, end_bit)
    flatten_ids = torch.empty(n_isects, dtype=torch.int32, device=dev)
    if n_isects > 0:
        L.launch(binning.offsets_kernel, n_isects, [_wp(keys), _wp(values), _wp(gauss), n_isects, n_ranges],
                 [_wp(offsets), _wp(flatten_ids)])
    keys, perm = keys[:n_isects], values[:n_isects]
    return {
        "tiles_per_gauss": counts.reshape(C, N).to(torch.int32),
        "isect_ids": keys,
        "flatten_ids": flatten_ids,
        "isect_offsets": offsets[:-1].reshape(C, tile_height, tile_width),
        "offsets": offsets,
        "perm": perm,
        "isect_ends": ends,
        "n_isects": n_isects,
    }


# ---------------------------------------------------------------------------------------------
# blending
# ---------------------------------------------------------------------------------------------
def pack_splats(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, flatten_ids: Tensor):
    """Per sorted intersection, contiguous in the order the blending kernels walk them:
    ``splats [M, 6]`` (x, y, conic a, b, c, opacity) and ``colors [M, D]`` (one gather kernel)."""
    M, D = flatten_ids.shape[0], colors.shape[-1]
    dt = means2d.dtype
    s = _scalar(dt)
    T = types_for(s)
    vecD = channel_vector(s, D)
    splats = torch.empty(M, 6, dtype=dt, device=means2d.device)
    cols = torch.empty(M, D, dtype=dt, device=means2d.device)
    _Launcher(means2d).launch(blend_forward.pack_kernel(s, D), M,
                              [_wp(flatten_ids), _wp(means2d, T.vec2), _wp(conics, T.vec3), _wp(opacities),
                               _wp(colors, vecD)], [_wp(splats, T.splat), _wp(cols, vecD)])
    return splats, cols


class _Blend(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds, tiles, width, height, tile_size, settings,
                deterministic):
        C, N, D = colors.shape
        dt, dev = colors.dtype, colors.device
        s = _scalar(dt)
        T = types_for(s)
        vecD = channel_vector(s, D)
        th, tw = tiles["isect_offsets"].shape[1:]
        # the kernel writes every pixel
        out = torch.empty(C, height, width, D, dtype=dt, device=dev)
        out_T = torch.empty(C, height, width, dtype=dt, device=dev)
        out_alpha = torch.empty(C, height, width, 1, dtype=dt, device=dev)
        last = torch.empty((C, height, width), dtype=torch.int32, device=dev)
        bg = backgrounds if backgrounds is not None else torch.zeros(C, D, dtype=dt, device=dev)
        L = _Launcher(colors)
        splats, cols = pack_splats(means2d, conics, opacities, colors, tiles["flatten_ids"])
        L.launch(blend_forward.forward_kernel(s, D, _fast(settings, s)), C * th * tw * tile_size * tile_size,
                 [_wp(splats, T.splat), _wp(cols, vecD), _wp(bg, vecD), _wp(tiles["offsets"]), width, height, tile_size, tw, th,
                  settings.alpha_min, settings.alpha_max, settings.t_min],
                 [_wp(out.reshape(-1, D), vecD), _wp(out_T.reshape(-1)), _wp(out_alpha.reshape(-1)),
                  _wp(last.reshape(-1))])
        ctx.save_for_backward(splats, cols, bg, out_T, last)
        ctx.n_gauss = N
        ctx.tiles, ctx.geom, ctx.settings, ctx.det = tiles, (width, height, tile_size, tw, th), settings, deterministic
        ctx.has_bg = backgrounds is not None
        return out, out_alpha

    @staticmethod
    def backward(ctx, g_colors, g_alphas):
        splats, cols, bg, out_T, last = ctx.saved_tensors
        width, height, tile_size, tw, th = ctx.geom
        tiles, st = ctx.tiles, ctx.settings
        C, N, D = bg.shape[0], ctx.n_gauss, cols.shape[-1]
        dt, dev = cols.dtype, cols.device
        s = _scalar(dt)
        T = types_for(s)
        vecD = channel_vector(s, D)
        g_colors = torch.zeros(C, height, width, D, dtype=dt, device=dev) if g_colors is None else g_colors.contiguous()
        g_alphas = torch.zeros(C, height, width, dtype=dt, device=dev) if g_alphas is None else g_alphas[..., 0].contiguous()
        M = tiles["n_isects"]
        L = _Launcher(cols)
        common = [_wp(splats, T.splat), _wp(cols, vecD), _wp(bg, vecD),
                  _wp(tiles["flatten_ids"]), _wp(tiles["offsets"])]
        geom = [width, height, tile_size, tw, th, st.alpha_min, st.alpha_max]
        state = [_wp(out_T.reshape(-1)), _wp(last.reshape(-1)), _wp(g_colors.reshape(-1, D), vecD),
                 _wp(g_alphas.reshape(-1))]
        n_pix = C * th * tw * tile_size * tile_size
        vecG = channel_vector(s, D + 6)
        # blocks of pixels of one tile walk its Gaussians in lockstep and sum their pixels' gradients
        # before one atomic add per Gaussian: per warp with one block per tile where the tile splits
        # into whole warps (and on CPU, one pixel per block), else per block of one tile row.
        # Deterministic: one block per tile adds into the intersection's own slot (one add per slot
        # on CUDA; blocks in turn on CPU), then the slots are summed per Gaussian in a fixed order.
        det = bool(ctx.det)
        if det and tile_size * tile_size > 256:
            # one block per tile: larger blocks run out of registers on CUDA
            raise ValueError(f"rasterization: deterministic=True needs tile_size <= 16, got {tile_size}")
        per_warp, block = backward_blocks(tile_size, det, L.stream is None)
        packed = torch.zeros(max(M if det else C * N, 1), 6 + D, dtype=dt, device=dev)
        L.launch(blend_backward.reduced_backward_kernel(s, D, det, per_warp, _fast(st, s)), n_pix,
                 [*common, *geom, *state, _wp(tiles["perm"])], [_wp(packed, vecG)], block_dim=block)
        if det:
            slots, packed = packed, torch.zeros(C * N, 6 + D, dtype=dt, device=dev)
            counts = tiles["tiles_per_gauss"].reshape(-1).to(torch.int64)
            L.launch(blend_backward.gather_kernel(s, D), C * N,
                     [_wp(tiles["isect_ends"]), _wp(counts), _wp(slots, vecG)], [_wp(packed, vecG)])
        v = [packed[:, 0:2], packed[:, 2:5], packed[:, 5], packed[:, 6:]]
        v_bg = (g_colors * out_T[..., None]).sum(dim=(1, 2)) if ctx.has_bg else None
        return (v[0].reshape(C, N, 2), v[1].reshape(C, N, 3), v[3].reshape(C, N, D), v[2].reshape(C, N),
                v_bg, None, None, None, None, None, None)


def backward_blocks(tile_size: int, deterministic: bool, cpu: bool) -> tuple[bool, int]:
    """``(per_warp, block_dim)`` of the blending backward launch.

    Deterministic: one block per tile (a fixed-order block sum per intersection). Otherwise on CPU
    one pixel per block; on CUDA, when the tile splits into whole warps (``tile_size^2`` a multiple
    of 32), blocks of up to 256 pixels of one tile (the whole tile at tile_size 16) summed per warp,
    else blocks of one tile row summed per block (a warp would straddle two tiles)."""
    pixels = tile_size * tile_size
    if deterministic:
        return False, pixels
    if cpu:
        return True, 1
    if pixels % 32 == 0:
        # the largest multiple of 32 up to 256 that divides the tile
        return True, max(b for b in range(32, 257, 32) if pixels % b == 0)
    return False, tile_size


def blend_warp(means2d, conics, colors, opacities, backgrounds, tiles, width, height, tile_size, settings,
               deterministic=False):
    """Front-to-back blending in Warp: ``colors [C,N,D]`` → ``(image [C,H,W,D], alpha [C,H,W,1])``."""
    D = colors.shape[-1]
    if D > MAX_CHANNELS:
        chunks = [blend_warp(means2d, conics, colors[..., i:i + MAX_CHANNELS], opacities,
                             None if backgrounds is None else backgrounds[..., i:i + MAX_CHANNELS],
                             tiles, width, height, tile_size, settings, deterministic)
                  for i in range(0, D, MAX_CHANNELS)]
        return torch.cat([c[0] for c in chunks], dim=-1), chunks[0][1]
    return _Blend.apply(means2d, conics, colors, opacities, backgrounds, tiles, width, height, tile_size,
                        settings, deterministic)
