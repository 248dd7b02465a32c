"""Tile binning: which tiles each projected Gaussian touches, sorted per tile by depth.

1. :func:`count_kernel`: per (camera, Gaussian), the half-open tile box
   ``[floor((m - r) / ts), ceil((m + r) / ts))`` per axis clamped to the grid,
   and its tile count (0 when culled).
2. (host) 64-bit exclusive scan of the counts.
3. :func:`write_kernel`: one intersection per (Gaussian, tile) with the 64-bit
   key ``(camera * n_tiles + tile) << 32 | depth bits`` (the depth's float32
   bit pattern orders positive depths; camera-major like gsplat's keys),
   value = the intersection's own position (so the sort also yields the
   permutation).
4. (host) Warp's stable radix sort of (key, value) pairs.
5. :func:`offsets_kernel`: the start of each (camera, tile) range in the sorted
   list, ``offsets[C * n_tiles] = n_isects``.
"""

import functools

import warp as wp

from .types import types_for


@functools.lru_cache(maxsize=None)
def tile_box_func(scalar):
    vec2 = types_for(scalar).vec2

    @wp.func
    def tile_box(xy: vec2, r: wp.vec2i, tile_size: int, tile_width: int, tile_height: int):
        ts = scalar(tile_size)
        tx = xy[0] / ts
        ty = xy[1] / ts
        rx = scalar(r[0]) / ts
        ry = scalar(r[1]) / ts
        x0 = wp.clamp(int(wp.floor(tx - rx)), 0, tile_width)
        y0 = wp.clamp(int(wp.floor(ty - ry)), 0, tile_height)
        x1 = wp.clamp(int(wp.ceil(tx + rx)), 0, tile_width)
        y1 = wp.clamp(int(wp.ceil(ty + ry)), 0, tile_height)
        if r[0] <= 0 or r[1] <= 0:
            x0 = 0
            x1 = 0
        return wp.vec4i(x0, y0, x1, y1)

    return tile_box


@functools.lru_cache(maxsize=None)
def count_kernel(scalar):
    vec2 = types_for(scalar).vec2
    tile_box = tile_box_func(scalar)

    @wp.kernel(module="unique")
    def count_tiles(means2d: wp.array(dtype=vec2), radii: wp.array(dtype=wp.vec2i), tile_size: int,
                    tile_width: int, tile_height: int, counts: wp.array(dtype=wp.int64)):
        i = wp.tid()
        b = tile_box(means2d[i], radii[i], tile_size, tile_width, tile_height)
        counts[i] = wp.int64((b[2] - b[0]) * (b[3] - b[1]))

    return count_tiles


@functools.lru_cache(maxsize=None)
def write_kernel(scalar):
    vec2 = types_for(scalar).vec2
    tile_box = tile_box_func(scalar)

    @wp.kernel(module="unique")
    def write_isects(means2d: wp.array(dtype=vec2), radii: wp.array(dtype=wp.vec2i),
                     depth_bits: wp.array(dtype=wp.int64), offsets: wp.array(dtype=wp.int64),
                     n_gauss: int, tile_size: int, tile_width: int, tile_height: int,
                     keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32),
                     gauss_of_isect: wp.array(dtype=wp.int32)):
        i = wp.tid()
        b = tile_box(means2d[i], radii[i], tile_size, tile_width, tile_height)
        first_range = wp.int64(i // n_gauss) * wp.int64(tile_width * tile_height)
        k = offsets[i]
        for ty in range(b[1], b[3]):
            for tx in range(b[0], b[2]):
                r = first_range + wp.int64(ty * tile_width + tx)
                keys[k] = (r << wp.int64(32)) | depth_bits[i]
                values[k] = wp.int32(k)
                gauss_of_isect[k] = wp.int32(i)
                k += wp.int64(1)

    return write_isects


@wp.kernel
def offsets_kernel(keys: wp.array(dtype=wp.int64), perm: wp.array(dtype=wp.int32),
                   gauss_of_isect: wp.array(dtype=wp.int32), n_isects: int, n_ranges: int,
                   offsets: wp.array(dtype=wp.int32), flatten_ids: wp.array(dtype=wp.int32)):
    """Per sorted intersection ``k``: ``flatten_ids[k]``, its Gaussian (``perm[k]`` is its slot
    before the sort), and ``offsets[r]`` = first sorted position of range r (= camera * n_tiles +
    tile)."""
    k = wp.tid()
    flatten_ids[k] = gauss_of_isect[perm[k]]
    cur = wp.int32(keys[k] >> wp.int64(32))
    prev = wp.int32(-1)
    if k > 0:
        prev = wp.int32(keys[k - 1] >> wp.int64(32))
    for r in range(prev + 1, cur + 1):
        offsets[r] = wp.int32(k)
    if k == n_isects - 1:
        for r in range(cur + 1, n_ranges + 1):
            offsets[r] = wp.int32(n_isects)
