"""The per-pixel rule, written once and used by the blending forward and backward kernels.

For a Gaussian with screen mean ``xy``, conic ``(a, b, c)`` and opacity ``o``,
seen from pixel centre ``(px, py)``::

    dx, dy = xy - (px, py)
    sigma  = 0.5 (a dx^2 + c dy^2) + b dx dy      (one fused multiply-add, see below)
    alpha  = min(alpha_max, o exp(-sigma))

The contribution is skipped when ``sigma < 0`` or ``alpha < alpha_min``.
The transmittance cut-off (the Gaussian that would bring T to <= t_min ends
the pixel unblended) is :func:`ends_pixel`.

The blending kernels are compiled without floating-point contraction, so every
rounding here is the one written: ``a dx^2 + c dy^2`` is the single fused
multiply-add ``fma(a dx, dx, c dy dy)``, the contraction nvcc makes of gsplat's
same expression, so a Gaussian at the alpha threshold is decided as gsplat
decides it, and identically in the forward and backward passes.
"""

import functools

import warp as wp

from .fmath import fma
from .types import types_for


@wp.func
def tile_pixel(tid: int, tile_size: int, tile_width: int, tile_height: int):
    """``vec4i(range, camera, x, y)`` of blending thread ``tid``: threads run tile by tile (the
    ``tile_size^2`` threads of a tile are consecutive), ``range = camera * n_tiles + tile``."""
    tile_pixels = tile_size * tile_size
    rng = tid // tile_pixels
    local = tid - rng * tile_pixels
    n_tiles = tile_width * tile_height
    cam = rng // n_tiles
    tile = rng - cam * n_tiles
    tyi = tile // tile_width
    x = (tile - tyi * tile_width) * tile_size + local % tile_size
    y = tyi * tile_size + local // tile_size
    return wp.vec4i(rng, cam, x, y)


@functools.lru_cache(maxsize=None)
def pixel_funcs(scalar):
    """``(splat_alpha, ends_pixel)`` for one precision.

    ``splat_alpha(splat, px, py, alpha_min, alpha_max) -> (alpha, g, dx, dy, keep)`` for a packed
    projected Gaussian ``splat = (x, y, a, b, c, opacity)``, with ``g = exp(-sigma)``; ``keep`` is
    False when the contribution is skipped (``sigma < 0`` or ``alpha < alpha_min``, or a NaN alpha).
    The exponent is formed as ``-0.5 q - b dx dy`` (the same bits as ``-sigma``: negation is exact
    and round-to-nearest is symmetric), and the callers branch on ``keep`` itself: no negation
    and no sentinel value in the loops that run this once per (pixel, Gaussian).
    """
    t = types_for(scalar)
    splat = t.splat

    @wp.func
    def splat_alpha(sp: splat, px: scalar, py: scalar, alpha_min: scalar, alpha_max: scalar):
        dx = sp[0] - px
        dy = sp[1] - py
        nsigma = scalar(-0.5) * fma(sp[2] * dx, dx, sp[4] * dy * dy) - sp[3] * dx * dy
        g = wp.exp(nsigma)
        alpha = wp.min(alpha_max, sp[5] * g)
        keep = alpha >= alpha_min and not (nsigma > scalar(0.0))
        return alpha, g, dx, dy, keep

    @wp.func
    def ends_pixel(T: scalar, alpha: scalar, t_min: scalar):
        return T * (scalar(1.0) - alpha) <= t_min

    return splat_alpha, ends_pixel
