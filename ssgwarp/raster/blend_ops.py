"""Blending as a torch autograd op over the Warp kernels of ``kernels/blend_forward.py`` and
``kernels/blend_backward.py``: front-to-back compositing of any number of channels over the tile
ranges :func:`ssgwarp.raster.ops.bin_tiles` sorted, and its hand-written backward.

On CUDA the forward runs one block per tile (:func:`batched`): reading the projection's packed splats
through the sorted ids where no backward can follow or where there are few intersections
(:data:`IDS_BACKWARD_MAX`; the backward then reads through them too), else the per-intersection
gather (:func:`pack_splats`) that the backward walks; on the CPU each pixel walks the gathered
arrays, on several threads (:mod:`.cpu_threads`).
"""
from __future__ import annotations

from functools import lru_cache, partial

import torch

from . import cpu_threads
from . import launch as L
from ..kernels import blend_backward, blend_forward
from .launch import NULL, apply, arr

Tensor = torch.Tensor
MAX_CHANNELS = 64


def pack_splats(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, flatten_ids: Tensor,
                packed: Tensor | None = None, threads: int = 1, tg=None):
    """Per sorted intersection, contiguous in the order the blending kernels walk them:
    ``splats [M, 6]`` (x, y, conic a, b, c, opacity) and ``colors [M, D]`` (one gather kernel;
    ``colors`` is ``[C, N, D]`` or, the same for every camera, ``[N, D]``; ``packed [C, N, 6]``:
    the projection's packed splats, read instead of the three arrays). ``threads`` (CPU): launches over
    equal runs of the intersections side by side (:mod:`.cpu_threads`). ``tg``: the launch target
    (:func:`ssgwarp.raster.launch.target` of ``means2d`` when not given)."""
    M, D = flatten_ids.shape[0], colors.shape[-1]
    dt = means2d.dtype
    s = L.scalar_of(dt)
    splats = torch.empty(M, 6, dtype=dt, device=means2d.device)
    cols = torch.empty(M, D, dtype=dt, device=means2d.device)
    if packed is None:
        gauss = [*arr(L.dense(means2d), 2), *arr(L.dense(conics), 3), *arr(L.dense(opacities))]
    else:  # (the three arrays are not read)
        gauss = [*NULL, *NULL, *NULL]
    ids, cs = L.dense(flatten_ids), L.dense(colors)
    kern = blend_forward.pack_kernel(s, D)
    head = [*arr(ids), *(NULL if packed is None else arr(packed, 6)), *gauss, *arr(cs, D), *arr(splats, 6),
            *arr(cols, D)]
    tg = tg or L.target(means2d)
    cpu_threads.launch_runs(kern, (), cpu_threads.element_runs(tg, threads, M, 1), head, tg)
    return splats, cols


class _Blend(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds, tiles, width, height, tile_size, settings,
                deterministic, packed, gather, outputs, absgrad=None):
        C, N = means2d.shape[:2]
        D = colors.shape[-1]
        dt, dev = colors.dtype, colors.device
        s = L.scalar_of(dt)
        th, tw = tiles["isect_offsets"].shape[1:]
        tg = tiles.get("target") or L.target(colors)
        ctx.set_materialize_grads(False)
        out, out_alpha, out_T, last, rows = outputs or blend_outputs(C, height, width, D, dt, dev, gather)
        a_T, a_last = (arr(out_T), arr(last)) if gather else (NULL, NULL)
        bg = L.dense(backgrounds) if backgrounds is not None else None
        # on the CPU, runs of whole tiles on several threads (cpu_threads.py); else one launch
        parts = _tile_parts(tg, settings, tiles, C * th * tw, tile_size)
        a_bg, a_offsets = NULL if bg is None else arr(bg, D), arr(tiles["offsets"])
        ids = tiles["flatten_ids"]
        tp = tile_size * tile_size
        # on CUDA one block per tile (kernels/blend_forward.py): where a backward may follow over
        # many intersections, the per-intersection gather it walks is made here and read
        # contiguously; else the kernel (and its backward) reads the projection's packed splats
        # through the ids and nothing is gathered
        block = batched(tg, packed, tile_size)
        through_ids = block and (not gather or tiles["n_isects"] <= IDS_BACKWARD_MAX)
        if through_ids:
            cs = L.dense(colors)
            shift = N if cs.ndim == 2 else 0  # (colours shared by the cameras)
            splats, cols = packed, cs
        else:
            splats, cols = pack_splats(means2d, conics, opacities, colors, ids, packed, len(parts), tg)
            shift = 0
        head = [*arr(splats, 6), *arr(cols, D)]
        if block:
            head += [*arr(ids), shift]
            kern = blend_forward.batched_forward_kernel(s, D, L.fast_math(settings, s), tp, through_ids)
        else:
            kern = blend_forward.forward_kernel(s, D, L.fast_math(settings, s))
        head += [*a_bg, *a_offsets, width, height, tile_size, tw, th, settings.alpha_min, settings.alpha_max,
                 settings.t_min, *arr(out, D), *a_T, *arr(out_alpha), *a_last]
        if block:
            L.launch(kern, C * th * tw * tp, head, tg, None, tp)
        else:
            cpu_threads.launch_runs(kern, (), [(a * tp, b * tp) for a, b in parts], head, tg)
        ctx.save_for_backward(splats, cols, bg, out_T, last)
        # the backward launch's arguments after the splats and colours: the same tensors (kept by ctx)
        ctx.args = [*a_bg, *arr(ids), shift, *a_offsets, width, height, tile_size, tw, th, settings.alpha_min,
                    settings.alpha_max, *a_T, *a_last]
        ctx.through_ids = through_ids
        ctx.n_gauss, ctx.cshape = N, colors.shape
        ctx.tiles, ctx.geom, ctx.settings, ctx.det = tiles, (width, height, tile_size, tw, th), settings, deterministic
        ctx.parts, ctx.tg = parts, tg  # (a backward runs on its forward's stream)
        ctx.rows = rows  # (zeroed gradient rows made with the outputs, for the first backward; else None)
        ctx.absgrad = absgrad  # (None, or what receives the absolute gradients [C, N, 2] of the means)
        return out, out_alpha

    @staticmethod
    def backward(ctx, g_colors, g_alphas):
        splats, cols, bg, out_T, last = ctx.saved_tensors
        width, height, tile_size, tw, th = ctx.geom
        tiles, st = ctx.tiles, ctx.settings
        N, D = ctx.n_gauss, cols.shape[-1]
        C = out_T.shape[0]
        dt, dev = cols.dtype, cols.device
        s = L.scalar_of(dt)
        tg = ctx.tg
        # the images' gradients read in place where their strides allow (an image without a
        # gradient is passed as a null array, read as zeros)
        a_gc, g_colors_kept = L.pixel_rows(g_colors, D)
        a_ga, g_alphas_kept = L.pixel_rows(g_alphas, 1)
        M = tiles["n_isects"]
        # blocks of pixels of one tile walk its Gaussians in lockstep and sum their pixels' gradients
        # before one atomic add per Gaussian: per warp with one block per tile where the tile splits
        # into whole warps (and on CPU, one pixel per block), else per block of one tile row.
        # Deterministic: one block per tile adds into the intersection's own slot (one add per slot
        # on CUDA; on CPU the tile's pixels in turn), then the slots are summed per Gaussian in a
        # fixed order. On CPU, launches over runs of whole tiles on several threads (cpu_threads.py).
        det = bool(ctx.det)
        if det and tile_size * tile_size > 256:
            # one block per tile: larger blocks run out of registers on CUDA
            raise ValueError(f"rasterization: deterministic=True needs tile_size <= 16, got {tile_size}")
        per_warp, block = backward_blocks(tile_size, det, tg.cpu)
        # nothing upstream of the splats wants a gradient (a frozen scene's colours or identities
        # trained): the colour gradients alone, the same values, without the geometry terms
        need = ctx.needs_input_grad
        geometry = need[0] or need[1] or need[3]
        # absgrad: two more values per row after the colours, the sums of |per-pixel gradient| of the means
        absgrad = ctx.absgrad is not None and need[0]
        lead = 6 if geometry else 0
        W = lead + D + (2 if absgrad else 0)
        rows = max(M if det else C * N, 1)
        parts = ctx.parts
        if not det and len(parts) > 1:  # (each thread adds into its own rows: within a memory cap)
            parts = cpu_threads.merge(parts, cpu_threads.extra_buffers(len(parts), W * cols.element_size(), rows))
        # with few intersections (the forward read through the ids) the colours' gradients get rows of
        # their own after the geometry's, in the same buffer: a contiguous gradient autograd keeps as
        # it is, where a column block of the packed rows is copied for the colours' .grad
        split = ctx.through_ids and geometry and not det and len(parts) == 1 and C * N > 0 and not absgrad
        # the rows made with the forward's outputs and zeroed by the binning's key writes (a first
        # backward's, of the default kind), else cleared here (CUDA: one memset on the stream); the
        # default backward's rows as [C, N, W] from the start
        made, ctx.rows = ctx.rows, None
        if made is not None and C * N and made.numel() == gradient_rows_size(C, N, D, geometry, det) and not absgrad:
            packed = made if split else made.view(C, N, W)
        else:
            packed = L.zeros((C * N * W,) if split else (C, N, W) if not det and C * N else (rows, W), dt, tg)
        # the default backward's other threads: their own rows, added to the first thread's below
        extra = torch.zeros(len(parts) - 1, rows, W, dtype=dt, device=dev) if len(parts) > 1 and not det else None
        kern = blend_backward.reduced_backward_kernel(s, D, det, per_warp, L.fast_math(st, s), not geometry,
                                                      ctx.through_ids, split, absgrad)
        head = [*arr(splats, 6), *arr(cols, D), *ctx.args, *a_gc, *a_ga, *(arr(tiles["perm"]) if det else NULL)]
        tp = tile_size * tile_size
        if split:
            es, ptr = packed.element_size(), packed.data_ptr()
            rows_args = [*L.at(ptr, C * N, 6 * es), *L.at(ptr + C * N * 6 * es, C * N, D * es)]
            (a, b), = parts
            L.launch(kern, (b - a) * tp, head + rows_args + [a * tp], tg, None, block)
        else:
            cpu_threads.run([partial(L.launch, kern, (b - a) * tp,
                                     head + [*arr(packed if (i == 0 or det) else extra[i - 1], W), *NULL, a * tp],
                                     tg, None, block)
                             for i, (a, b) in enumerate(parts)])
        del g_colors_kept, g_alphas_kept  # (kept alive until the launches were queued)
        if extra is not None:
            packed.view(rows, W).add_(extra.sum(0) if extra.shape[0] > 1 else extra[0])
        if det:
            slots = packed
            packed = torch.empty(C * N, W, dtype=dt, device=dev)
            L.launch(blend_backward.gather_kernel(s, W), C * N,
                     [*arr(tiles["isect_ends"]), *arr(tiles["tiles_per_gauss"]), *arr(slots, W), *arr(packed, W)],
                     tg)
        # (the gradients as views of the packed rows, in as few torch calls as may be)
        v_m2d = v_conics = v_opac = None
        shared = len(ctx.cshape) == 2  # (colours shared by the cameras)
        if split:
            geom, v_colors = packed.split_with_sizes((C * N * 6, C * N * D))
            v_m2d, v_conics, v_opac = geom.view(C, N, 6).split_with_sizes((2, 3, 1), -1)
            v_opac = v_opac.squeeze(-1)
            v_colors = v_colors.view(N, D) if shared and C == 1 else v_colors.view(C, N, D)
        elif absgrad:
            v_m2d, v_conics, v_opac, v_colors, v_abs = _rows(packed, C, N, W).split_with_sizes((2, 3, 1, D, 2), -1)
            v_opac = v_opac.squeeze(-1)
            ctx.absgrad(v_abs.contiguous())
        elif geometry:
            v_m2d, v_conics, v_opac, v_colors = _rows(packed, C, N, W).split_with_sizes((2, 3, 1, D), -1)
            v_opac = v_opac.squeeze(-1)
        else:
            v_colors = _rows(packed, C, N, D)
        if shared and v_colors.dim() == 3:
            v_colors = v_colors[0] if C == 1 else v_colors.sum(0)
        v_bg = None
        if bg is not None and need[4]:  # (a constant background, as training passes: no gradient to form)
            v_bg = (g_colors * out_T[..., None]).sum(dim=(1, 2)) if g_colors is not None else torch.zeros_like(bg)
        return v_m2d, v_conics, v_colors, v_opac, v_bg, None, None, None, None, None, None, None, None, None, None


def blend_outputs(C: int, height: int, width: int, D: int, dtype, device, gather: bool,
                  grad_rows: int = 0) -> tuple:
    """``(image [C,H,W,D], alpha [C,H,W,1], T [C,H,W], last [C,H,W], rows)``: what the blending
    forward writes (every pixel), made before it runs (also ahead of the binning's read-back, where
    the host would wait); the final transmittance and last blended Gaussian per pixel only where a
    backward can follow (``gather``), else None. ``rows``: with ``grad_rows > 0`` (and ``gather``), a
    flat buffer of that many values for the backward's per-Gaussian gradient rows (:func:`gradient_rows_size`),
    which the caller has zeroed before the backward runs (the binning's key writes do it), else None."""
    out = torch.empty(C, height, width, D, dtype=dtype, device=device)
    alpha = torch.empty(C, height, width, 1, dtype=dtype, device=device)
    if not gather:
        return out, alpha, None, None, None
    return (out, alpha, torch.empty(C, height, width, dtype=dtype, device=device),
            torch.empty(C, height, width, dtype=torch.int32, device=device),
            torch.empty(grad_rows, dtype=dtype, device=device) if grad_rows > 0 else None)


def gradient_rows_size(C: int, N: int, D: int, geometry: bool, deterministic: bool) -> int:
    """How many values the blending backward's gradient rows hold for ``C`` cameras, ``N`` Gaussians
    and ``D`` channels: ``C * N`` rows of the splat's 6 (where ``geometry``: the means, conics or
    opacities want a gradient) and the ``D`` colour values; 0 for the deterministic backward, whose
    rows are per intersection (their number is known only after the binning)."""
    return 0 if deterministic else C * N * ((6 if geometry else 0) + D)


def backward_may_follow(means2d, conics, colors, opacities, backgrounds) -> bool:
    """Whether a backward can follow the blending of these tensors (gradients on, one of them
    requiring one): the forward then keeps what the backward reads."""
    return torch.is_grad_enabled() and (means2d.requires_grad or conics.requires_grad or colors.requires_grad
                                        or opacities.requires_grad
                                        or (backgrounds is not None and backgrounds.requires_grad))


def _rows(packed: Tensor, C: int, N: int, W: int) -> Tensor:
    """The per-Gaussian gradient rows as ``[C, N, W]`` (a view unless they are already)."""
    return packed if packed.dim() == 3 else packed.view(C, N, W)


# the blending forward on CUDA with one block per tile (False: the per-intersection gather and the
# per-pixel walk, as on the CPU)
BATCHED = True
# up to this many intersections, a forward on CUDA that a backward may follow makes no
# per-intersection gather: both passes read the projection's splats and the colours through the
# sorted ids (one launch, two buffers and the colour gradient's copy fewer per call: 10k Gaussians
# at 256x256, 15k intersections, forward+backward 3-14 % faster; at 0.3M a wash). Above it the
# backward's contiguous reads of the gather win (2.5-3M intersections: 6-8 % slower through the
# ids). Measured on H100s, docs/notes/benchmarks-history.md (the retired benchmarks/blend_ids.py)
IDS_BACKWARD_MAX = 1 << 19


def batched(tg, packed, tile_size: int) -> bool:
    """Whether the blending forward runs :func:`ssgwarp.kernels.blend_forward.batched_forward_kernel`:
    on CUDA, with the projection's packed splats, for tiles of at most 1024 pixels (one block)."""
    return BATCHED and not tg.cpu and packed is not None and tile_size * tile_size <= 1024


def _tile_parts(tg, settings, tiles, n_ranges: int, tile_size: int) -> list[tuple[int, int]]:
    """The runs of tile ranges the blending launches cover: on the CPU one per thread
    (:mod:`.cpu_threads`), on CUDA the whole image in one launch."""
    if not tg.cpu:
        return [(0, n_ranges)]
    n = cpu_threads.count(settings.cpu_threads, n_ranges, tiles["n_isects"], tile_size * tile_size)
    return cpu_threads.split(tiles["offsets"], n_ranges, n)


@lru_cache(maxsize=None)
def backward_blocks(tile_size: int, deterministic: bool, cpu: bool) -> tuple[bool, int]:
    """``(per_warp, block_dim)`` of the blending backward launch.

    On the CPU one pixel per block (the pixels of a tile walk in turn, in pixel order; the
    deterministic option adds into per-intersection slots the same way, so threads over disjoint
    tiles never share a slot). On CUDA: deterministic, one block per tile (a fixed-order block sum
    per intersection); else, when the tile splits into whole warps (``tile_size^2`` a multiple of
    32), blocks of up to 256 pixels of one tile (the whole tile at tile_size 16) summed per warp,
    else blocks of one tile row summed per block (a warp would straddle two tiles)."""
    pixels = tile_size * tile_size
    if cpu:
        return True, 1
    if deterministic:
        return False, pixels
    if pixels % 32 == 0:
        # the largest multiple of 32 up to 256 that divides the tile
        return True, max(b for b in range(32, 257, 32) if pixels % b == 0)
    return False, tile_size


def blend_warp(means2d, conics, colors, opacities, backgrounds, tiles, width, height, tile_size, settings,
               deterministic=False, packed=None, outputs=None, absgrad=None):
    """Front-to-back blending in Warp: ``colors [C,N,D]`` (or ``[N,D]``, the same for every
    camera) → ``(image [C,H,W,D], alpha [C,H,W,1])``. ``packed``: the projection's packed splats
    (the same values as means2d, conics and opacities; read instead of them). ``outputs``: what
    :func:`blend_outputs` made for this call (``D <= MAX_CHANNELS``), else made here. ``absgrad``:
    None, or a function the backward calls with ``[C, N, 2]``: per Gaussian and camera the sum over
    pixels of the absolute per-pixel gradient of its 2D mean (gsplat's ``absgrad``; with more than
    ``MAX_CHANNELS`` channels, once per block of channels)."""
    D = colors.shape[-1]
    if D > MAX_CHANNELS:
        chunks = [blend_warp(means2d, conics, colors[..., i:i + MAX_CHANNELS], opacities,
                             None if backgrounds is None else backgrounds[..., i:i + MAX_CHANNELS],
                             tiles, width, height, tile_size, settings, deterministic, packed, None, absgrad)
                  for i in range(0, D, MAX_CHANNELS)]
        return torch.cat([c[0] for c in chunks], dim=-1), chunks[0][1]
    # whether a backward can follow (the forward keeps what it reads)
    gather = backward_may_follow(means2d, conics, colors, opacities, backgrounds)
    if outputs is not None and (outputs[2] is not None) != gather:
        raise ValueError("blend_warp: outputs made for another case (blend_outputs(..., gather) must say whether a "
                         "backward can follow, as backward_may_follow does)")
    return apply(_Blend, means2d, conics, colors, opacities, backgrounds, tiles, width, height, tile_size,
                 settings, deterministic, packed, gather, outputs, absgrad, needs_grad=gather)
