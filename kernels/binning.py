"""Tile binning: which tiles each projected Gaussian touches, sorted per tile by depth.

1. per (camera, Gaussian), the half-open tile box ``[floor((m - r) / ts), ceil((m + r) / ts))``
   per axis clamped to the grid, and its tile count (0 when culled): written by the projection
   kernel in the rasterizer (:func:`tile_box_func`), or by :func:`count_kernel` on its own.
2. (host) 64-bit inclusive scan of the counts (``ends``).
3. :func:`write_kernel`: one intersection per (Gaussian, tile) from slot ``ends - count`` on,
   with the 64-bit key ``(camera * n_tiles + tile) << 32 | depth bits`` (the depth's float32
   bit pattern orders positive depths; camera-major like gsplat's keys), value = the Gaussian
   (so the sorted values are the flattened ids), or for the deterministic backward the
   intersection's own position (so the sort also yields the permutation). It also clears, when
   given, a buffer of a fixed number of values per Gaussian (the blending backward's gradient
   rows: one memset call fewer on the host).
4. (host) Warp's stable radix sort of (key, value) pairs.
5. :func:`offsets_kernel`: the start of each (camera, tile) range in the sorted
   list, ``offsets[C * n_tiles] = n_isects`` (and with the permutation, the flattened ids).
"""

import functools

import warp as wp

from .fmath import add_rn, div_rn
from .types import types_for

_DEPTH_BITS = """
union { float f; unsigned int u; } v;
v.f = (float)d;
return (long long)v.u;
"""


@wp.func_native(_DEPTH_BITS)
def depth_bits(d: wp.float32) -> wp.int64:
    """The bit pattern of ``d`` as float32, as a non-negative int64 (orders positive depths)."""
    ...


@wp.func_native(_DEPTH_BITS)
def depth_bits(d: wp.float64) -> wp.int64:  # noqa: F811 (the float64 overload: rounded to float32 first)
    """The bit pattern of ``d`` rounded to float32, as a non-negative int64."""
    ...


@functools.lru_cache(maxsize=None)
def tile_box_func(scalar):
    vec2 = types_for(scalar).vec2

    @wp.func
    def tile_box(xy: vec2, r: wp.vec2i, tile_size: int, tile_width: int, tile_height: int):
        """Every operation correctly rounded, so that kernels compiled with and without fast
        maths (the projection counts, the intersection writes fill) find the same box."""
        ts = scalar(tile_size)
        tx = div_rn(xy[0], ts)
        ty = div_rn(xy[1], ts)
        rx = div_rn(scalar(r[0]), ts)
        ry = div_rn(scalar(r[1]), ts)
        x0 = wp.clamp(int(wp.floor(add_rn(tx, -rx))), 0, tile_width)
        y0 = wp.clamp(int(wp.floor(add_rn(ty, -ry))), 0, tile_height)
        x1 = wp.clamp(int(wp.ceil(add_rn(tx, rx))), 0, tile_width)
        y1 = wp.clamp(int(wp.ceil(add_rn(ty, ry))), 0, tile_height)
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
                    tile_width: int, tile_height: int, counts: wp.array(dtype=wp.int32)):
        i = wp.tid()
        b = tile_box(means2d[i], radii[i], tile_size, tile_width, tile_height)
        counts[i] = (b[2] - b[0]) * (b[3] - b[1])

    return count_tiles


@functools.lru_cache(maxsize=None)
def write_kernel(scalar):
    vec2 = types_for(scalar).vec2
    tile_box = tile_box_func(scalar)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def write_isects(means2d: wp.array(dtype=vec2), radii: wp.array(dtype=wp.vec2i),
                     depths: wp.array(dtype=scalar), ends: wp.array(dtype=wp.int64),
                     counts: wp.array(dtype=wp.int32), n_gauss: int, tile_size: int, tile_width: int,
                     tile_height: int, keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32),
                     gauss_of_isect: wp.array(dtype=wp.int32), clear: wp.array(dtype=scalar), clear_width: int,
                     first: int):
        i = wp.tid() + first
        # ``clear`` (``clear_width`` values per camera and Gaussian, e.g. the rows the blending backward
        # adds its gradients into, which then needs no clearing of its own), when given, zeroed by the
        # threads together: thread i the values i, i + n, i + 2n, ... (coalesced stores)
        if clear.shape[0] > 0:
            n_rows = clear.shape[0] // clear_width
            for j in range(clear_width):
                clear[j * n_rows + i] = scalar(0.0)
        cnt = counts[i]
        if cnt == 0:
            return
        b = tile_box(means2d[i], radii[i], tile_size, tile_width, tile_height)
        first_range = wp.int64(i // n_gauss) * wp.int64(tile_width * tile_height)
        bits = depth_bits(depths[i])
        end = ends[i]
        k = end - wp.int64(cnt)
        # values: the Gaussian itself (sorted, they are the flattened ids), or with gauss_of_isect
        # given, the slot (sorted, the permutation; the Gaussian of each slot goes there)
        slots = gauss_of_isect.shape[0] > 0
        for ty in range(b[1], b[3]):
            for tx in range(b[0], b[2]):
                if k < end:  # never past this Gaussian's slots (the box is the one counted)
                    r = first_range + wp.int64(ty * tile_width + tx)
                    keys[k] = (r << wp.int64(32)) | bits
                    if slots:
                        values[k] = wp.int32(k)
                        gauss_of_isect[k] = wp.int32(i)
                    else:
                        values[k] = wp.int32(i)
                k += wp.int64(1)

    return write_isects


@wp.kernel
def offsets_kernel(keys: wp.array(dtype=wp.int64), perm: wp.array(dtype=wp.int32),
                   gauss_of_isect: wp.array(dtype=wp.int32), n_isects: int, n_ranges: int,
                   offsets: wp.array(dtype=wp.int32), flatten_ids: wp.array(dtype=wp.int32), first: int):
    """Per sorted intersection ``k``: ``offsets[r]`` = first sorted position of range r (= camera *
    n_tiles + tile), and when ``gauss_of_isect`` is given, ``flatten_ids[k]``, its Gaussian
    (``perm[k]`` is its slot before the sort). ``first``: the intersection of the launch's first
    thread (runs side by side on the CPU's cores; each range's offsets are written by the thread of
    the intersection that starts it, or the last one)."""
    k = wp.tid() + first
    if gauss_of_isect.shape[0] > 0:
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
