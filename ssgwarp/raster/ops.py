"""Torch autograd ops over the Warp kernels (``ssgwarp.kernels``).

Tensors are shared with Warp zero-copy: launch arguments are Warp array descriptors built from
a tensor's pointer (:mod:`ssgwarp.raster.launch`), and launches replay a recorded Warp launch; CPU
tensors run on Warp's CPU device, CUDA tensors on the same CUDA device and on torch's current
stream. float32 and float64 use the same kernel source, built per precision.

:func:`ssgwarp.raster.rasterize.rasterization`'s Warp path: two autograd ops (:class:`_Project`
here: projection, tile counts and SH colours; :class:`ssgwarp.raster.blend_ops._Blend`: blending)
around the tile binning (:func:`bin_tiles`), with one device synchronisation per call (the
intersection total, which also reports the input value checks run in the projection).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import torch

from . import cpu_threads
from . import launch as L
from ..kernels import binning, projection, projection_backward, sh, validate
from .launch import NULL, apply, arr

Tensor = torch.Tensor
INT32_MAX = 2**31 - 1
CHECK_FAILED = int(projection.CHECK_FAILED)  # (what a failed input check adds to the intersection total)
CHECK_MAX_PAIRS = projection.CHECK_MAX_PAIRS  # (more (camera, Gaussian) pairs: the checks run on their own)
# the projection's backward: the hand-written kernel (True) or Warp's generated adjoint of the
# forward kernel (False; slower, kept as the tests' yardstick and for before/after benchmarks)
HAND_BACKWARD = True


# ---------------------------------------------------------------------------------------------
# input value checks
# ---------------------------------------------------------------------------------------------
def check_values(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds=None, flags=None) -> Tensor:
    """Flags of the value checks of :mod:`.kernels.validate` (one kernel, no synchronisation):
    an int64 tensor ``[N_FLAGS]`` on the inputs' device, non-zero where a check failed (slot ``i``
    < 8: NaN/Inf in ``validate.INPUTS[i]``; then zero quaternion, negative scale, opacity outside
    [0, 1], non-positive focal length). Shapes must already be consistent. ``flags``: a zeroed
    int64 tensor ``[N_FLAGS]`` to write into (else one is made)."""
    flat = [L.dense(t) for t in (means, quats, scales, opacities, colors, viewmats, Ks)]
    if backgrounds is not None:
        flat.append(L.dense(backgrounds))
    if flags is None:
        flags = torch.zeros(validate.N_FLAGS, dtype=torch.int64, device=means.device)
    descs = [v for t in flat for v in arr(t)]
    if backgrounds is None:
        descs += NULL
    L.launch(validate.check_kernel(L.scalar_of(means.dtype)), max(t.numel() for t in flat),
             [*descs, means.shape[0], viewmats.shape[0], *arr(flags)], L.target(means))
    return flags


# ---------------------------------------------------------------------------------------------
# projection (+ tile counts, + SH colours)
# ---------------------------------------------------------------------------------------------
class _Project(torch.autograd.Function):
    """``(means2d, depths, conics, opacities, colors)`` of N Gaussians in C cameras; the results
    without a gradient go to ``extra`` (a dict) instead of through the autograd op (each output
    costs it host time): ``radii [C, N, 2]``, and ``counts [C, N]`` (int32 tiles per Gaussian) and
    ``splats [C, N, 6]`` (the blending's packed splats) when ``cfg["tile_size"] > 0``, else None;
    ``tg``, the launch target (:func:`ssgwarp.raster.launch.target`), for the launches that follow.

    ``colors [C, N, 3]`` (SH colour, ``+ 0.5`` clamped, 0 where culled) when ``coeffs`` is given,
    else None. ``extra`` may also hold, on the way in,
    ``ends`` (int64 ``[C*N]``) to receive the tile counts for the binning's in-place scan;
    ``check=True`` to run the input value checks in the projection (a Gaussian that fails one
    marks its count in ``ends``: ``kernels/projection.py: CHECK_FAILED``), with the ``colors``
    and ``backgrounds`` they also cover. Backward: the SH colour's backward then the
    projection's (``kernels/projection_backward.py``), both into per-(camera, Gaussian) slots
    when C > 1 (summed here in a fixed order), straight into the gradients when C = 1."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, coeffs, campos, cfg, extra):
        C, N = viewmats.shape[0], means.shape[0]
        dt, dev = means.dtype, means.device
        s = L.scalar_of(dt)
        tg = L.target(means)
        ctx.set_materialize_grads(False)  # (outputs without a gradient arrive as None: no zero tensors)
        ins = [L.dense(t) for t in (means, quats, scales, opacities, viewmats, Ks)]
        means2d = torch.empty(C, N, 2, dtype=dt, device=dev)
        depths = torch.empty(C, N, dtype=dt, device=dev)
        conics = torch.empty(C, N, 3, dtype=dt, device=dev)
        opac = torch.empty(C, N, dtype=dt, device=dev)
        radii = torch.empty(C, N, 2, dtype=torch.int32, device=dev)
        counts = splats = None
        if cfg["tile_size"] > 0:  # (rendering follows: tile counts and packed splats for the binning and blending)
            counts = torch.empty(C, N, dtype=torch.int32, device=dev)
            splats = torch.empty(C, N, 6, dtype=dt, device=dev)
        outs = [means2d, depths, conics, opac, radii]
        kern = projection.projection_kernel(s, *cfg["variant"], activations=cfg["activations"])
        head = _project_args(ins, C, N) + list(cfg["params"])
        a_radii = arr(radii, 2)
        tail = [*arr(means2d, 2), *arr(depths), *arr(conics, 3), *arr(opac), *a_radii]
        checks, keep = _check_args(extra, C, N)
        ends = extra.get("ends")
        # on the CPU, runs of Gaussians (in every camera) on several threads; else one launch
        runs = cpu_threads.element_runs(tg, cfg["cpu_threads"], N)
        cpu_threads.launch_runs(kern, (C,), runs, head + checks + tail + [*(arr(counts) if counts is not None else NULL),
                                                               *(arr(ends) if ends is not None else NULL),
                                                               *(arr(splats, 6) if splats is not None else NULL)], tg)
        del keep  # (contiguous copies made for the checks: needed until the launch is queued)
        colors = colour_args = None
        if coeffs is not None:
            coeffs, campos = L.dense(coeffs), L.dense(campos)
            colors = torch.empty(C, N, 3, dtype=dt, device=dev)
            colour_args = _colour_args(ins[0], campos, coeffs, radii, C, N)
            cpu_threads.launch_runs(sh.colour_kernel(s, cfg["sh_degree"]), (C,), runs, colour_args + [*arr(colors, 3)], tg)
        # (the hand-written backward reads the radii of the outputs; Warp's adjoint all of them)
        ctx.hand = HAND_BACKWARD
        ctx.save_for_backward(*ins, coeffs, campos, *((radii,) if ctx.hand else outs))
        # the backward launches read the same tensors (kept by ctx): their descriptors are kept too
        # (inputs and parameters, outputs; not the checks' nor the tile counts', which the binning has scanned)
        ctx.cfg, ctx.head, ctx.tail, ctx.a_radii, ctx.colour_args = cfg, head, tail, a_radii, colour_args
        ctx.runs, ctx.tg = runs, tg  # (a backward runs on its forward's stream)
        extra["radii"], extra["counts"], extra["splats"], extra["tg"] = radii, counts, splats, tg
        return means2d, depths, conics, opac, colors

    @staticmethod
    def backward(ctx, g_means2d, g_depths, g_conics, g_opac, g_colors):
        means, quats, scales, opacities, viewmats, Ks, coeffs, campos = ctx.saved_tensors[:8]
        cfg, need, hand = ctx.cfg, ctx.needs_input_grad, ctx.hand
        C, N = viewmats.shape[0], means.shape[0]
        dt, dev = means.dtype, means.device
        s = L.scalar_of(dt)
        tg = ctx.tg
        # one adjoint slot per (camera, Gaussian). Where the projection's backward is the only
        # kernel to write them it writes every slot (no clearing); after the SH colours' backward
        # (which adds into the means' slots) or Warp's adjoint they start from zeros, in one buffer
        lead = (C, N) if C > 1 else (N,)
        sh_back = g_colors is not None and coeffs is not None
        grads = [L.grad_rows(g, k, C * N) for g, k in ((g_means2d, 2), (g_depths, 1), (g_conics, 3), (g_opac, 1))]
        project = any(g[1] is not None for g in grads) and any(need[:5])
        written = project and hand and not sh_back
        if written:
            v_means, v_quats, v_scales, v_opac = (torch.empty(*lead, *((w,) if w > 1 else ()), dtype=dt, device=dev)
                                                  if on else None for w, on in zip((3, 4, 3, 1), need[:4]))
        else:
            v_means, v_quats, v_scales, v_opac = _zeros_split([3, 4, 3, 1], need[:4], lead, dt, tg)
        v_view = None if not need[4] else (torch.empty(C, N, 4, 4, dtype=dt, device=dev) if written
                                           else L.zeros((C, N, 4, 4), dt, tg))
        v_coeffs = v_campos = None
        if sh_back:
            g, g_t = L.grad_rows(g_colors, 3, C * N)
            K, degree = coeffs.shape[-2], cfg["sh_degree"]
            if need[7]:
                v_campos = L.zeros((C, N, 3), dt, tg)
            if coeffs.ndim == 3 and C > 1:
                # the same coefficients for several cameras: summed over them in one hand-written
                # kernel (kernels/sh.py: colour_backward_kernel; every used row written)
                if need[6]:
                    v_coeffs = (torch.empty_like(coeffs) if K == sh.n_coeffs(degree)
                                else L.zeros(tuple(coeffs.shape), dt, tg))
                cpu_threads.launch_runs(sh.colour_backward_kernel(s, degree), (), ctx.runs,
                                        [*ctx.colour_args, *g, *_grid(v_means, C, N, 3), *_grid(v_campos, C, N, 3),
                                         *(NULL if v_coeffs is None else L.grid3(v_coeffs, C, N, K, 3, False))], tg)
            else:  # one row per (camera, Gaussian): Warp's generated adjoint (the faster one there)
                if need[6]:
                    v_coeffs = L.zeros(tuple(coeffs.shape), dt, tg)
                adj = [*_grid(v_means, C, N, 3), *_grid(v_campos, C, N, 3),
                       *(NULL if v_coeffs is None else L.grid3(v_coeffs, C, N, K, 3, True)), *NULL, *g]
                # (array stores are not replayed in Warp's adjoints: the colour output is not needed)
                cpu_threads.launch_runs(sh.colour_kernel(s, degree), (C,), ctx.runs, ctx.colour_args + [*NULL], tg, adj)
            del g_t
        if project:
            outs = [*_grid(v_means, C, N, 3), *_grid(v_quats, C, N, 4), *_grid(v_scales, C, N, 3),
                    *_grid(v_opac, C, N, 1), *_grid(v_view, C, N, 16)]
            if hand:  # kernels/projection_backward.py
                kern = projection_backward.projection_backward_kernel(s, *cfg["variant"], cfg["activations"])
                cpu_threads.launch_runs(kern, (C,), ctx.runs, [*ctx.head, *ctx.a_radii,
                                                               *(v for g in grads for v in g[0]), *outs,
                                                               int(not written)], tg)
            else:  # Warp's generated adjoint of the forward kernel (the hand kernel's yardstick in the tests)
                adj = [*outs, *NULL, *_ADJ_PARAMS, *_NO_CHECKS, *grads[0][0], *grads[1][0],
                       *grads[2][0], *grads[3][0], *NULL, *NULL, *NULL, *NULL]
                args = ctx.head + _NO_CHECKS + ctx.tail + [*NULL, *NULL, *NULL]  # (the forward's, checks off)
                kern = projection.projection_kernel(s, *cfg["variant"], True, cfg["activations"])
                cpu_threads.launch_runs(kern, (C,), ctx.runs, args, tg, adj)
        if C > 1:
            v_means, v_quats, v_scales, v_opac = (None if v is None else v.sum(0)
                                                  for v in (v_means, v_quats, v_scales, v_opac))
        if v_view is not None:
            v_view = v_view.sum(1)
        if v_campos is not None:
            v_campos = v_campos.sum(1)
        return v_means, v_quats, v_scales, v_opac, v_view, None, v_coeffs, v_campos, None, None


class ProjectionParams(NamedTuple):
    """The projection kernel's parameter block (``kernels/projection.py: projection_params``, the
    same fields in the same order), passed to a launch as its fields (``*params``)."""

    width: int
    height: int
    near_plane: float
    far_plane: float
    eps2d: float
    radius_clip: float
    alpha_min: float
    sigma_max: float
    opacity_extent: int
    antialiased: int
    tile_size: int = 0
    tile_width: int = 0
    tile_height: int = 0


assert ProjectionParams._fields == tuple(name for name, _ in projection.PARAM_FIELDS)
# the adjoint of the parameter block (not read: nothing is differentiated with respect to it)
_ADJ_PARAMS = ProjectionParams(0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0)
# the projection's check parameters when it runs no checks: colours, row, per camera, backgrounds, row, check
_NO_CHECKS = [*NULL, 0, 0, *NULL, 0, 0]


def _check_args(extra, C, N):
    """``(flat arguments, tensors to keep alive)`` of the projection's input checks (none without
    ``extra["check"]``): the colours read flat in rows (per camera or shared), the backgrounds."""
    if not extra.get("check"):
        return _NO_CHECKS, ()
    colors, bg = L.dense(extra["colors"]), extra.get("backgrounds")
    per_cam = colors.shape[0] == C and colors.ndim == (4 if extra.get("sh") else 3)
    row = colors.numel() // (C * N if per_cam else N) if N else 0
    bg = L.dense(bg) if bg is not None else None
    args = [*arr(colors), row, int(per_cam), *(arr(bg) if bg is not None else NULL),
            bg.shape[-1] if bg is not None else 0, 1]
    return args, (colors, bg)


def _zeros_split(widths, wanted, lead, dt, tg):
    """Zeroed ``[*lead, w]`` tensors for the wanted widths (None for the others), as contiguous
    views of one buffer (one allocation and one clear, :func:`ssgwarp.raster.launch.zeros`)."""
    n = 1
    for d in lead:
        n *= d
    sizes = [n * w for w, on in zip(widths, wanted) if on]
    if not sizes:
        return [None] * len(widths)
    parts = iter(L.zeros((sum(sizes),), dt, tg).split_with_sizes(sizes))
    return [(next(parts).view(*lead, w) if w > 1 else next(parts).view(*lead)) if on else None
            for w, on in zip(widths, wanted)]


def _grid(t, C, N, inner):
    """Adjoint slots ``[C, N]`` (or ``[N]`` with one camera) as a 2-D descriptor; NULL if absent."""
    return NULL if t is None else L.grid(t, C, N, inner, True)


def _project_args(ins, C, N):
    means, quats, scales, opacities, viewmats, Ks = ins
    return [*L.grid(means, C, N, 3, False), *L.grid(quats, C, N, 4, False), *L.grid(scales, C, N, 3, False),
            *L.grid(opacities, C, N, 1, False), *L.cams(viewmats, C, N, 16), *arr(Ks, 9)]


def _colour_args(means, campos, coeffs, radii, C, N):
    K = coeffs.shape[-2]
    per_cam = coeffs.ndim == 4
    return [*L.grid(means, C, N, 3, False), *L.cams(campos, C, N, 3), *L.grid3(coeffs, C, N, K, 3, per_cam),
            *arr(radii, 2)]


def project_warp(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane=0.01,
                 far_plane=1e10, radius_clip=0.0, eps2d=0.3, antialiased=False, settings=None):
    """Warp version of :func:`ssgwarp.raster.reference.project_reference` (same outputs)."""
    cfg = _project_cfg(means.dtype, width, height, near_plane, far_plane, radius_clip, eps2d, antialiased, settings)
    side: dict = {}
    means2d, depths, conics, opac, _ = apply(_Project, means, quats, scales, opacities, viewmats, Ks, None, None, cfg,
                                             side)
    return side["radii"], means2d, depths, conics, opac


def _project_cfg(*args) -> dict:
    """What :class:`_Project` needs besides tensors: ``params`` (:class:`ProjectionParams`),
    ``variant`` (the kernel's build: covariance form, fast maths), ``tile_size``,
    ``sh_degree`` and ``activations`` (log-scales and logits in: the kernels apply ``exp`` and the
    sigmoid, ``kernels/projection.py: activation_funcs``); arguments as :func:`_build_project_cfg`'s. The
    same arguments give the same dict (cached; read only)."""
    try:
        return _cached_project_cfg(*args)
    except TypeError:  # (an unhashable argument)
        return _build_project_cfg(*args)


def _build_project_cfg(dtype, width, height, near_plane, far_plane, radius_clip, eps2d, antialiased, settings,
                       tile_size=0, tile_width=0, tile_height=0, sh_degree=None, activations=False) -> dict:
    params = ProjectionParams(
        width=int(width), height=int(height), near_plane=float(near_plane), far_plane=float(far_plane),
        eps2d=float(eps2d), radius_clip=float(radius_clip), alpha_min=float(settings.alpha_min),
        sigma_max=float(settings.sigma_max), opacity_extent=int(settings.extent == "opacity"),
        antialiased=int(bool(antialiased)), tile_size=int(tile_size), tile_width=int(tile_width),
        tile_height=int(tile_height))
    return {"params": params, "variant": (settings.covariance, L.fast_math(settings, L.scalar_of(dtype))),
            "tile_size": int(tile_size), "sh_degree": sh_degree, "cpu_threads": settings.cpu_threads,
            "activations": bool(activations)}


_cached_project_cfg = functools.lru_cache(maxsize=256)(_build_project_cfg)


# ---------------------------------------------------------------------------------------------
# tile binning
# ---------------------------------------------------------------------------------------------
def sort_bits(n_ranges: int, cpu: bool) -> int:
    """The key bits the radix sort covers for ``n_ranges`` (camera, tile) ranges: 32 of depth, then as
    many as the largest range index needs; on CUDA rounded up to an even number of 8-bit passes
    (CUB's one-sweep sort of 64-bit keys), after which the sorted keys end in their own half of the
    double buffer: after an odd number Warp's sort copies them back, two copies that cost more host
    time than the extra pass (at 256 tiles, 6 passes against 5 + 2 copies: the sort's host time 8-10
    µs shorter inside a call; H100, docs/notes/benchmarks-history.md). The bits added are zero in every key, so the
    order is the same."""
    bits = 32 + max(1, int(n_ranges - 1).bit_length())
    if cpu:
        return bits
    passes = -(-bits // 8)
    return min(64, 8 * (passes + passes % 2))


def bin_tiles(means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_width: int, tile_height: int,
              recheck=None, counts: Tensor | None = None, scan: Tensor | None = None, keep_perm: bool = True,
              counts_in_scan: bool = False, threads: int | None = None, during_wait=None, tg=None) -> dict:
    """Tile intersections of projected Gaussians, sorted by (camera, tile, depth).

    Returns ``tiles_per_gauss [C,N]`` (int32), ``isect_ids [M]`` (int64 keys), ``flatten_ids [M]``
    (flat camera*N + Gaussian index per sorted intersection), ``isect_offsets [C,th,tw]`` and, for
    the backward, ``offsets [C*th*tw+1]``, ``perm [M]`` (pre-sort slot of each sorted
    intersection; the deterministic backward's slots; None unless ``keep_perm``), ``isect_ends
    [C*N]`` (int64 inclusive scan of the counts).

    ``counts``: the tile counts when already known (the projection writes them), else counted
    here. ``scan``: an int64 tensor ``[C*N]`` to hold the scan, with ``counts_in_scan`` already
    holding the counts (the projection wrote them; scanned in place). The intersection total is
    the one value read back (the one synchronisation); where the projection ran the input checks,
    a Gaussian that failed one added ``kernels/projection.py: CHECK_FAILED`` to it, and then
    ``recheck()`` runs before anything else: it raises the failed check's error (and returns when
    every check passes: the total is then a real, too large, count). Without ``keep_perm`` the
    sort carries the Gaussian ids themselves (as gsplat's does), so the sorted values are the
    flattened ids. ``threads`` (CPU): ``RasterSettings.cpu_threads`` for the key writes and the
    range offsets (:mod:`.cpu_threads`). ``during_wait``: host work (a callable, no read-back of
    its own) run while the total is on its way back, where the host would otherwise wait; it may
    return a contiguous tensor of the means' dtype holding a whole number of values per (camera,
    Gaussian), which the key-writing kernel then zeroes (a clearing call fewer), or None. ``tg``:
    the launch target when the caller has it (:func:`ssgwarp.raster.launch.target` of ``means2d``).
    """
    C, N = depths.shape
    s = L.scalar_of(means2d.dtype)
    dev = means2d.device
    tg = tg or L.target(means2d)
    n_ranges = C * tile_width * tile_height
    if n_ranges >= INT32_MAX:
        raise ValueError(f"rasterization: {C} cameras x {tile_width * tile_height} tiles exceed the 2^31 tile "
                         "ranges one call can index; render fewer cameras per call or use a larger tile_size")
    CN = C * N
    if counts is None:
        counts = torch.empty(C, N, dtype=torch.int32, device=dev)
        L.launch(binning.count_kernel(s), CN, [*arr(L.dense(means2d), 2), *arr(L.dense(radii), 2), tile_size,
                                                tile_width, tile_height, *arr(counts)], tg)
    if scan is None or scan.numel() != CN:
        scan, counts_in_scan = torch.empty(CN, dtype=torch.int64, device=dev), False
    ends = scan
    if CN and counts_in_scan:
        ends.cumsum_(0)
    elif CN:
        torch.cumsum(counts.view(-1), 0, dtype=torch.int64, out=ends)
    pending = L.start_read_int64(ends, CN - 1, tg) if CN else 0
    m2, rd, dp = L.dense(means2d), L.dense(radii), L.dense(depths)
    clear = during_wait() if during_wait is not None else None
    n_isects = L.finish_read_int64(pending, tg) if CN else 0
    if n_isects >= CHECK_FAILED and recheck is not None:
        recheck()
    if n_isects > INT32_MAX // 2:
        raise ValueError(
            f"rasterization: {n_isects:,} Gaussian-tile intersections exceed the {INT32_MAX // 2:,} one call can "
            "sort; render fewer cameras per call, lower the resolution, raise tile_size, or cull large Gaussians "
            "(radius_clip / RasterSettings.sigma_max)")
    M = max(n_isects, 1)
    # every entry below n_isects is written by the kernel; the upper halves are the sort's scratch.
    # One int32 buffer: sort values (2M) | offsets, and with keep_perm also the Gaussian of each
    # pre-sort slot (M) and the flatten ids (M)
    keys = torch.empty(2 * M, dtype=torch.int64, device=dev)
    extra = 2 * M if keep_perm else 0
    ints = torch.empty(2 * M + extra + n_ranges + 1, dtype=torch.int32, device=dev)
    # (the views in one torch call: each costs as much as an allocation in the middle of a call)
    if keep_perm:
        values, gauss, flatten_ids, _, offsets = ints.split_with_sizes((2 * M, M, n_isects, M - n_isects,
                                                                        n_ranges + 1))
        a_gauss, a_flat = arr(gauss), arr(flatten_ids)
    else:
        flatten_ids, _, offsets = ints.split_with_sizes((n_isects, 2 * M - n_isects, n_ranges + 1))
        values, a_gauss, a_flat = None, NULL, NULL
    a_values = L.at(ints.data_ptr(), 2 * M, 4)  # (the sort's values and their scratch: the buffer's head)
    a_clear = (*NULL, 0)
    if clear is not None and CN:
        if clear.dtype != means2d.dtype or not clear.is_contiguous() or clear.numel() % CN:
            raise ValueError(f"bin_tiles: the buffer to clear must be a contiguous {means2d.dtype} tensor of a whole "
                             f"number of values per (camera, Gaussian), got {clear.dtype} {tuple(clear.shape)}")
        a_clear = (*arr(clear), clear.numel() // CN)
    # (on the CPU, runs of Gaussians and of intersections on several threads)
    cpu_threads.launch_runs(binning.write_kernel(s), (), cpu_threads.element_runs(tg, threads, CN),
                 [*arr(m2, 2), *arr(rd, 2), *arr(dp), *arr(ends), *arr(counts), N, tile_size, tile_width, tile_height,
                  *arr(keys), *a_values, *a_gauss, *a_clear], tg)
    if n_isects > 0:
        L.sort_pairs(keys, ints, n_isects, sort_bits(n_ranges, tg.cpu), tg)
        cpu_threads.launch_runs(binning.offsets_kernel, (), cpu_threads.element_runs(tg, threads, n_isects, cpu_threads.MIN_ITEMS_LIGHT),
                     [*arr(keys), *a_values, *a_gauss, n_isects, n_ranges, *arr(offsets), *a_flat], tg)
    else:
        offsets.zero_()
    return {
        "tiles_per_gauss": counts,
        "isect_ids": keys[:n_isects],
        "flatten_ids": flatten_ids,
        "isect_offsets": offsets.as_strided((C, tile_height, tile_width), (tile_height * tile_width, tile_width, 1)),
        "offsets": offsets,
        "perm": values[:n_isects] if keep_perm else None,
        "isect_ends": ends,
        "n_isects": n_isects,
        "target": tg,  # (where the blending launches: the same device and stream)
    }
