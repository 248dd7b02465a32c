"""Blending forward: front-to-back alpha compositing of any number of channels.

One thread per pixel; the ``tile_size^2`` threads of a tile are consecutive,
so they walk the same depth-sorted Gaussian range together, reading each
intersection's packed projected Gaussian (``splats[k]``: x, y, conic,
opacity, laid out in sorted order) with one contiguous load. Per pixel::

    T = 1
    for each Gaussian of the tile, front to back:
        alpha, keep = splat_alpha(...)      # keep False: skipped (pixel.py)
        if ends_pixel(T, alpha): break      # not blended
        out += colors[g] * alpha * T;  T *= 1 - alpha
    out += T * background

The pixel's alpha is the sum of the blending weights (equal to ``1 - T`` in
exact arithmetic, but exact to the last bit for faint pixels where ``1 - T``
cancels). Outputs what the backward needs, where one can follow (else null
arrays): the final transmittance and the position of the last blended Gaussian
in the sorted list.

On CUDA, :func:`batched_forward_kernel` runs the same rule with one block per tile: the block
loads the tile's next Gaussians into shared memory together (one per thread, through the sorted
ids with no gather before it, or from the gathered arrays) and stops once all its pixels have
ended, as gsplat's kernel does; which one runs is ``ssgwarp.raster.blend_ops``'s choice.

``first``: the thread index of this launch's first thread (0 for a whole image; on the CPU a
launch may cover a run of whole tiles, ``first`` a multiple of ``tile_size^2``, so that several
launches run side by side on the CPU's cores: ``ssgwarp.raster.cpu_threads``).
"""

import functools

import warp as wp

from .fmath import fma
from .block import block_all
from .pixel import pixel_funcs, tile_pixel
from .types import channel_vector, element_at, splat_at, types_for


@functools.lru_cache(maxsize=None)
def pack_kernel(scalar, channels: int):
    """``splats[k]``, ``colors_sorted[k]``: the packed projected Gaussian (x, y, conic a, b, c,
    opacity) and colour of sorted intersection ``k``, gathered once so the blending loops read
    each intersection's data contiguously (inputs flat over camera x Gaussian; the splats from
    ``packed`` when the projection packed them, else from means, conics and opacities; colours
    either the same for every camera, ``n_colors = N``, or per camera, ``n_colors = C * N``).
    ``first``: the intersection of this launch's first thread (0 for all of them in one launch)."""
    t = types_for(scalar)
    vec2, vec3, splat = t.vec2, t.vec3, t.splat
    vecD = channel_vector(scalar, channels)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def pack(flatten_ids: wp.array(dtype=wp.int32), packed: wp.array(dtype=splat), means2d: wp.array(dtype=vec2),
             conics: wp.array(dtype=vec3), opacities: wp.array(dtype=scalar), colors: wp.array(dtype=vecD),
             splats: wp.array(dtype=splat), colors_sorted: wp.array(dtype=vecD), first: int):
        k = wp.tid() + first
        g = int(flatten_ids[k])
        if packed.shape[0] > 0:  # the projection packed them already
            splats[k] = packed[g]
        else:
            m = means2d[g]
            c = conics[g]
            splats[k] = splat(m[0], m[1], c[0], c[1], c[2], opacities[g])
        colors_sorted[k] = colors[g % colors.shape[0]]

    return pack


@functools.lru_cache(maxsize=None)
def compositing_funcs(scalar, channels: int):
    """``(blend, finish)``: what both forward kernels do with a pixel, written once.

    ``blend(acc, wsum, T, c, alpha) -> (acc, wsum, T)``: one Gaussian composited front to back,
    ``acc + alpha T c`` rounded once per channel (one fused multiply-add, as gsplat's nvcc build
    rounds it). ``finish(acc, wsum, T, last, cam, pix, backgrounds, out_colors, out_T, out_alpha,
    last_ids)``: the background under the remaining transmittance, and the pixel's outputs (the
    transmittance and last Gaussian only where the backward needs them: null arrays otherwise)."""
    vecD = channel_vector(scalar, channels)

    @wp.func
    def blend(acc: vecD, wsum: scalar, T: scalar, c: vecD, alpha: scalar):
        w = alpha * T
        out = acc
        for d in range(wp.static(channels)):
            out[d] = fma(c[d], w, acc[d])
        return out, wsum + w, T * (scalar(1.0) - alpha)

    @wp.func
    def finish(acc: vecD, wsum: scalar, T: scalar, last: wp.int32, cam: int, pix: int,
               backgrounds: wp.array(dtype=vecD), out_colors: wp.array(dtype=vecD), out_T: wp.array(dtype=scalar),
               out_alpha: wp.array(dtype=scalar), last_ids: wp.array(dtype=wp.int32)):
        out = acc
        if backgrounds.shape[0] > 0:  # (an absent background: a null array)
            bg = backgrounds[cam]
            for d in range(wp.static(channels)):
                out[d] = fma(T, bg[d], acc[d])
        out_colors[pix] = out
        out_alpha[pix] = wsum
        if out_T.shape[0] > 0:
            out_T[pix] = T
            last_ids[pix] = last

    return blend, finish


@functools.lru_cache(maxsize=None)
def forward_kernel(scalar, channels: int, fast_math: bool = False):
    t = types_for(scalar)
    splat = t.splat
    vecD = channel_vector(scalar, channels)
    splat_alpha, ends_pixel = pixel_funcs(scalar)
    blend, finish = compositing_funcs(scalar, channels)
    colour_at = element_at(vecD)

    # no FMA contraction: the gating in pixel.py must decide identically in both passes
    @wp.kernel(module="unique", module_options={"fuse_fp": False, "enable_backward": False, "fast_math": fast_math})
    def blend_forward(
        splats: wp.array(dtype=splat),
        colors: wp.array(dtype=vecD),
        backgrounds: wp.array(dtype=vecD),
        offsets: wp.array(dtype=wp.int32),
        width: int,
        height: int,
        tile_size: int,
        tile_width: int,
        tile_height: int,
        alpha_min: scalar,
        alpha_max: scalar,
        t_min: scalar,
        out_colors: wp.array(dtype=vecD),
        out_T: wp.array(dtype=scalar),
        out_alpha: wp.array(dtype=scalar),
        last_ids: wp.array(dtype=wp.int32),
        first: int,
    ):
        p = tile_pixel(wp.tid() + first, tile_size, tile_width, tile_height)
        rng = p[0]
        cam = p[1]
        x = p[2]
        y = p[3]
        if x >= width or y >= height:
            return
        px = scalar(x) + scalar(0.5)
        py = scalar(y) + scalar(0.5)
        T = scalar(1.0)
        acc = vecD()
        wsum = scalar(0.0)
        last = wp.int32(-1)
        for k in range(offsets[rng], offsets[rng + 1]):
            alpha, g, dx, dy, keep = splat_alpha(splat_at(splats, k), px, py, alpha_min, alpha_max)
            if not keep:
                continue
            if ends_pixel(T, alpha, t_min):
                break
            acc, wsum, T = blend(acc, wsum, T, colour_at(colors, k), alpha)
            last = wp.int32(k)
        finish(acc, wsum, T, last, cam, (cam * height + y) * width + x, backgrounds, out_colors, out_T, out_alpha,
               last_ids)

    return blend_forward


@functools.lru_cache(maxsize=None)
def batched_forward_kernel(scalar, channels: int, fast_math: bool, block: int, through_ids: bool):
    """The blending forward on CUDA with one block per tile (``block = tile_size^2`` threads): the
    block loads the tile's next ``block`` projected Gaussians into shared memory together, one per
    thread, and every pixel walks them from there; the walk ends once every pixel of the tile has
    ended. The same per-pixel rule, order and roundings as :func:`forward_kernel`.

    ``through_ids=False``: ``splats`` and ``colors`` are the gathered per-intersection arrays
    (:func:`pack_kernel`); ``through_ids=True``: ``splats`` are the projection's packed splats
    ``[C * N]``, read through the sorted ids, with no gather before the launch, and ``colors``
    ``[C * N]`` (``color_shift = 0``) or, the same for every camera, ``[N]`` (``color_shift = N``:
    camera ``c``'s ids are ``c * N + g``)."""
    t = types_for(scalar)
    splat = t.splat
    vecD = channel_vector(scalar, channels)
    splat_alpha, ends_pixel = pixel_funcs(scalar)
    blend, finish = compositing_funcs(scalar, channels)
    colour_at = element_at(vecD)
    B = int(block)
    IDS = bool(through_ids)

    @wp.kernel(module="unique", module_options={"fuse_fp": False, "enable_backward": False, "fast_math": fast_math})
    def blend_forward_batched(
        splats: wp.array(dtype=splat),
        colors: wp.array(dtype=vecD),
        flatten_ids: wp.array(dtype=wp.int32),
        color_shift: int,
        backgrounds: wp.array(dtype=vecD),
        offsets: wp.array(dtype=wp.int32),
        width: int,
        height: int,
        tile_size: int,
        tile_width: int,
        tile_height: int,
        alpha_min: scalar,
        alpha_max: scalar,
        t_min: scalar,
        out_colors: wp.array(dtype=vecD),
        out_T: wp.array(dtype=scalar),
        out_alpha: wp.array(dtype=scalar),
        last_ids: wp.array(dtype=wp.int32),
    ):
        p = tile_pixel(wp.tid(), tile_size, tile_width, tile_height)
        rng = p[0]
        cam = p[1]
        x = p[2]
        y = p[3]
        inside = x < width and y < height
        px = scalar(x) + scalar(0.5)
        py = scalar(y) + scalar(0.5)
        T = scalar(1.0)
        acc = vecD()
        wsum = scalar(0.0)
        last = wp.int32(-1)
        done = int(0)
        if not inside:  # (kept to load and to vote: every thread of the block takes part)
            done = 1
        shift = cam * color_shift
        b = offsets[rng]
        end = offsets[rng + 1]
        while b < end:
            if block_all(done) != 0:
                break
            if wp.static(IDS):
                ids = wp.tile_load(flatten_ids, shape=(B,), offset=(b,), storage="shared")
                sps = wp.tile_load_indexed(splats, indices=ids, shape=(B,), offset=(0,), axis=0, storage="shared")
            else:
                sps = wp.tile_load(splats, shape=(B,), offset=(b,), storage="shared")
            if done == 0:
                n = wp.min(B, end - b)
                j = int(0)
                # (a skipped Gaussian continues the loop at once: nothing assigned on its path, so
                # no per-Gaussian selects of the pixel's state)
                while j < n:
                    alpha, g, dx, dy, keep = splat_alpha(sps[j], px, py, alpha_min, alpha_max)
                    j += 1
                    if not keep:
                        continue
                    if ends_pixel(T, alpha, t_min):
                        done = 1
                        break
                    if wp.static(IDS):
                        c = colour_at(colors, ids[j - 1] - shift)
                    else:
                        c = colour_at(colors, b + j - 1)
                    acc, wsum, T = blend(acc, wsum, T, c, alpha)
                    last = wp.int32(b + j - 1)
            b += B
        if inside:
            finish(acc, wsum, T, last, cam, (cam * height + y) * width + x, backgrounds, out_colors, out_T,
                   out_alpha, last_ids)

    return blend_forward_batched
