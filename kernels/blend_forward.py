"""Blending forward: front-to-back alpha compositing of any number of channels.

One thread per pixel; the ``tile_size^2`` threads of a tile are consecutive,
so they walk the same depth-sorted Gaussian range together, reading each
intersection's packed projected Gaussian (``splats[k]``: x, y, conic,
opacity, laid out in sorted order) with one contiguous load. Per pixel::

    T = 1
    for each Gaussian of the tile, front to back:
        alpha = splat_alpha(...)            # -1: skipped (pixel.py)
        if ends_pixel(T, alpha): break      # not blended
        out += colors[g] * alpha * T;  T *= 1 - alpha
    out += T * background

The pixel's alpha is the sum of the blending weights (equal to ``1 - T`` in
exact arithmetic, but exact to the last bit for faint pixels where ``1 - T``
cancels). Outputs what the backward needs: the final transmittance and the
position of the last blended Gaussian in the sorted list.

``first``: the thread index of this launch's first thread (0 for a whole image; on the CPU a
launch may cover a run of whole tiles, ``first`` a multiple of ``tile_size^2``, so that several
launches run side by side on the CPU's cores: ``ssgwarp.raster.cpu_threads``).
"""

import functools

import warp as wp

from .fmath import fma
from .pixel import pixel_funcs, tile_pixel
from .types import channel_vector, splat_at, types_for


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
def forward_kernel(scalar, channels: int, fast_math: bool = False):
    t = types_for(scalar)
    splat = t.splat
    vecD = channel_vector(scalar, channels)
    splat_alpha, ends_pixel = pixel_funcs(scalar)

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
            r = splat_alpha(splat_at(splats, k), px, py, alpha_min, alpha_max)
            alpha = r[0]
            if alpha < scalar(0.0):
                continue
            if ends_pixel(T, alpha, t_min):
                break
            w = alpha * T
            c = colors[k]
            for d in range(wp.static(channels)):
                acc[d] = fma(c[d], w, acc[d])  # rounded once per channel, as gsplat's nvcc build
            wsum = wsum + w
            T = T * (scalar(1.0) - alpha)
            last = wp.int32(k)
        pix = (cam * height + y) * width + x
        if backgrounds.shape[0] > 0:  # (an absent background: a null array)
            bg = backgrounds[cam]
            for d in range(wp.static(channels)):
                acc[d] = fma(T, bg[d], acc[d])
        out_colors[pix] = acc
        out_T[pix] = T
        out_alpha[pix] = wsum
        last_ids[pix] = last

    return blend_forward
