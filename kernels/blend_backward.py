"""Blending backward: the hand-written reverse traversal of :mod:`.blend_forward`.

Per pixel, from the last blended Gaussian back to the first, with ``T_f`` the
final transmittance and ``S`` the colour already accumulated behind::

    T_i      = T_{i+1} / (1 - alpha_i)                   (T_{last+1} = T_f)
    dC/dc_i  = alpha_i T_i
    dC/da_i  = T_i c_i - (S_i + T_f bg) / (1 - alpha_i)
    dA/da_i  = T_f / (1 - alpha_i)                        (A = 1 - T_f)

then through ``alpha = opacity exp(-sigma)`` (no gradient where the clamp
``alpha_max`` is active) to opacity, conic and the screen mean. The gating
(skip / end) is the same ``@wp.func`` the forward used (:mod:`.pixel`).

Two variants: :func:`backward_kernel` (one thread per pixel, atomic adds per
Gaussian; fast, summation order varies on CUDA) and
:func:`backward_tile_kernel` (one thread per tile walking its pixels in order,
each intersection's gradient in its own slot; with :func:`gather_kernel`
summing the slots per Gaussian in a fixed order it is bit-identical from run
to run).
"""

import functools

import warp as wp

from .pixel import pixel_funcs
from .types import channel_vector, types_for


@functools.lru_cache(maxsize=None)
def pixel_backward_func(scalar, channels: int):
    """``walk_pixel(...)``: the reverse traversal of one pixel; writes gradients to
    slot ``slot_of(k)`` (the Gaussian's flat index, or the intersection's own slot)."""
    t = types_for(scalar)
    vec2, vec3 = t.vec2, t.vec3
    vecD = channel_vector(scalar, channels)
    splat_alpha, _ = pixel_funcs(scalar)

    @wp.func
    def walk_pixel(
        start: int, last: int, T_final: scalar, v_col: vecD, v_alpha_out: scalar, bg: vecD,
        px: scalar, py: scalar, alpha_min: scalar, alpha_max: scalar,
        means2d: wp.array(dtype=vec2), conics: wp.array(dtype=vec3), opacities: wp.array(dtype=scalar),
        colors: wp.array(dtype=vecD), flatten_ids: wp.array(dtype=wp.int32),
        slots: wp.array(dtype=wp.int32), use_atomics: int,
        v_means2d: wp.array(dtype=vec2), v_conics: wp.array(dtype=vec3),
        v_opacities: wp.array(dtype=scalar), v_colors: wp.array(dtype=vecD),
    ):
        T_next = T_final
        S = vecD()
        bg_term = T_final * wp.dot(bg, v_col)
        k = last
        while k >= start:
            g = flatten_ids[k]
            xy = means2d[g]
            cn = conics[g]
            op = opacities[g]
            r = splat_alpha(xy, cn, op, px, py, alpha_min, alpha_max)
            alpha = r[0]
            if alpha >= scalar(0.0):
                one_m = scalar(1.0) - alpha
                T = T_next / one_m
                c = colors[g]
                w = alpha * T
                v_a = T * wp.dot(c, v_col) - (wp.dot(S, v_col) + bg_term) / one_m + v_alpha_out * T_final / one_m
                S = S + c * w
                vis = r[1]
                dx = r[2]
                dy = r[3]
                v_xy = vec2()
                v_cn = vec3()
                v_op = scalar(0.0)
                if op * vis <= alpha_max:
                    v_sigma = -v_a * alpha
                    v_op = v_a * vis
                    v_cn = vec3(scalar(0.5) * dx * dx * v_sigma, dx * dy * v_sigma, scalar(0.5) * dy * dy * v_sigma)
                    v_xy = vec2(v_sigma * (cn[0] * dx + cn[1] * dy), v_sigma * (cn[1] * dx + cn[2] * dy))
                s = g
                if use_atomics == 0:
                    s = slots[k]
                    v_colors[s] = v_colors[s] + v_col * w
                    v_means2d[s] = v_means2d[s] + v_xy
                    v_conics[s] = v_conics[s] + v_cn
                    v_opacities[s] = v_opacities[s] + v_op
                else:
                    wp.atomic_add(v_colors, s, v_col * w)
                    wp.atomic_add(v_means2d, s, v_xy)
                    wp.atomic_add(v_conics, s, v_cn)
                    wp.atomic_add(v_opacities, s, v_op)
                T_next = T
            k -= 1
        return 0

    return walk_pixel


@functools.lru_cache(maxsize=None)
def backward_kernel(scalar, channels: int, per_tile: bool = False):
    t = types_for(scalar)
    vec2, vec3 = t.vec2, t.vec3
    vecD = channel_vector(scalar, channels)
    walk_pixel = pixel_backward_func(scalar, channels)

    @wp.func
    def pixel_xy(rng: int, local: int, tile_size: int, tile_width: int, tile_height: int):
        n_tiles = tile_width * tile_height
        cam = rng // n_tiles
        tile = rng - cam * n_tiles
        tyi = tile // tile_width
        x = (tile - tyi * tile_width) * tile_size + local % tile_size
        y = tyi * tile_size + local // tile_size
        return wp.vec3i(cam, x, y)

    # no FMA contraction: the gating in pixel.py must decide identically in both passes
    @wp.kernel(module="unique", module_options={"fuse_fp": False})
    def blend_backward(
        means2d: wp.array(dtype=vec2),
        conics: wp.array(dtype=vec3),
        opacities: wp.array(dtype=scalar),
        colors: wp.array(dtype=vecD),
        backgrounds: wp.array(dtype=vecD),
        flatten_ids: wp.array(dtype=wp.int32),
        offsets: wp.array(dtype=wp.int32),
        slots: wp.array(dtype=wp.int32),
        width: int,
        height: int,
        tile_size: int,
        tile_width: int,
        tile_height: int,
        alpha_min: scalar,
        alpha_max: scalar,
        out_T: wp.array(dtype=scalar),
        last_ids: wp.array(dtype=wp.int32),
        v_out_colors: wp.array(dtype=vecD),
        v_out_alphas: wp.array(dtype=scalar),
        v_means2d: wp.array(dtype=vec2),
        v_conics: wp.array(dtype=vec3),
        v_opacities: wp.array(dtype=scalar),
        v_colors: wp.array(dtype=vecD),
    ):
        tid = wp.tid()
        tile_pixels = tile_size * tile_size
        rng = tid
        first = 0
        count = tile_pixels
        if wp.static(not per_tile):
            rng = tid // tile_pixels
            first = tid - rng * tile_pixels
            count = 1
        for local in range(first, first + count):
            cxy = pixel_xy(rng, local, tile_size, tile_width, tile_height)
            cam = cxy[0]
            x = cxy[1]
            y = cxy[2]
            if x < width and y < height:
                pix = (cam * height + y) * width + x
                walk_pixel(offsets[rng], int(last_ids[pix]), out_T[pix], v_out_colors[pix], v_out_alphas[pix],
                           backgrounds[cam], scalar(x) + scalar(0.5), scalar(y) + scalar(0.5), alpha_min, alpha_max,
                           means2d, conics, opacities, colors, flatten_ids, slots,
                           wp.static(0 if per_tile else 1), v_means2d, v_conics, v_opacities, v_colors)

    return blend_backward


@functools.lru_cache(maxsize=None)
def gather_kernel(scalar, channels: int):
    """Sum each Gaussian's per-intersection gradient slots in a fixed order (deterministic)."""
    t = types_for(scalar)
    vec2, vec3 = t.vec2, t.vec3
    vecD = channel_vector(scalar, channels)

    @wp.kernel(module="unique")
    def gather(
        ends: wp.array(dtype=wp.int64), counts: wp.array(dtype=wp.int64),
        s_means2d: wp.array(dtype=vec2), s_conics: wp.array(dtype=vec3),
        s_opacities: wp.array(dtype=scalar), s_colors: wp.array(dtype=vecD),
        v_means2d: wp.array(dtype=vec2), v_conics: wp.array(dtype=vec3),
        v_opacities: wp.array(dtype=scalar), v_colors: wp.array(dtype=vecD),
    ):
        i = wp.tid()
        end = ends[i]
        a = vec2()
        b = vec3()
        o = scalar(0.0)
        c = vecD()
        for k in range(int(end - counts[i]), int(end)):
            a = a + s_means2d[k]
            b = b + s_conics[k]
            o = o + s_opacities[k]
            c = c + s_colors[k]
        v_means2d[i] = a
        v_conics[i] = b
        v_opacities[i] = o
        v_colors[i] = c

    return gather
