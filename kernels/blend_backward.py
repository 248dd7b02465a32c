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

One kernel, :func:`reduced_backward_kernel`: blocks of pixels of one tile walk
the tile's Gaussians in lockstep and sum their gradients (per 32-pixel warp, or
per block) before one atomic add per Gaussian; a vote skips the sum and the add
for Gaussians none of the pixels blended (on CPU the block width is 1: the plain
per-pixel walk). With per-intersection slots plus :func:`gather_kernel` it is the
deterministic option on both devices.
"""

import functools

import warp as wp

from .block import block_any, warp_max, warp_sum_add
from .pixel import pixel_funcs, tile_pixel
from .types import channel_vector, types_for


@functools.lru_cache(maxsize=None)
def layer_grad_func(scalar, channels: int):
    """``layer_grad(...)``: one layer of the reverse traversal of one pixel.

    Given the packed projected Gaussian and the pixel's state after it (``T_next``:
    transmittance behind it, ``S``: colour accumulated behind it), returns
    ``(used, T, S', v_xy, v_conic, v_opacity, v_color)``; ``used`` is 0 when the
    forward pass skipped this Gaussian at this pixel (then nothing changes).
    """
    t = types_for(scalar)
    vec2, vec3, splat = t.vec2, t.vec3, t.splat
    vecD = channel_vector(scalar, channels)
    splat_alpha, _ = pixel_funcs(scalar)

    @wp.func
    def layer_grad(sp: splat, c: vecD, px: scalar, py: scalar, alpha_min: scalar,
                   alpha_max: scalar, T_next: scalar, S: vecD, v_col: vecD, v_alpha_out: scalar,
                   T_final: scalar, bg_term: scalar):
        r = splat_alpha(sp, px, py, alpha_min, alpha_max)
        alpha = r[0]
        used = int(0)
        T = T_next
        S_out = S
        v_xy = vec2()
        v_cn = vec3()
        v_op = scalar(0.0)
        v_c = vecD()
        if alpha >= scalar(0.0):
            used = 1
            inv = scalar(1.0) / (scalar(1.0) - alpha)
            T = T_next * inv
            w = alpha * T
            v_a = T * wp.dot(c, v_col) - (wp.dot(S, v_col) + bg_term - v_alpha_out * T_final) * inv
            S_out = S + c * w
            v_c = v_col * w
            vis = r[1]
            dx = r[2]
            dy = r[3]
            if sp[5] * vis <= alpha_max:
                v_sigma = -v_a * alpha
                v_op = v_a * vis
                v_cn = vec3(scalar(0.5) * dx * dx * v_sigma, dx * dy * v_sigma, scalar(0.5) * dy * dy * v_sigma)
                v_xy = vec2(v_sigma * (sp[2] * dx + sp[3] * dy), v_sigma * (sp[3] * dx + sp[4] * dy))
        return used, T, S_out, v_xy, v_cn, v_op, v_c

    return layer_grad


@functools.lru_cache(maxsize=None)
def gather_kernel(scalar, channels: int):
    """Sum each Gaussian's per-intersection gradient slots in a fixed order (deterministic)."""
    vecG = channel_vector(scalar, channels + 6)

    @wp.kernel(module="unique")
    def gather(ends: wp.array(dtype=wp.int64), counts: wp.array(dtype=wp.int64),
               slots: wp.array(dtype=vecG), out: wp.array(dtype=vecG)):
        i = wp.tid()
        end = ends[i]
        acc = vecG()
        for k in range(int(end - counts[i]), int(end)):
            acc = acc + slots[k]
        out[i] = acc

    return gather


@functools.lru_cache(maxsize=None)
def reduced_backward_kernel(scalar, channels: int, to_slots: bool = False, per_warp: bool = False,
                            fast_math: bool = False):
    """Backward by blocks of pixels of one tile: the block walks the tile's Gaussians in lockstep
    (from the largest last index of its pixels), sums the pixels' gradients for each Gaussian and
    adds the sum with one atomic per Gaussian (instead of one per pixel). Gradients land packed as
    ``[xy(2), conic(3), opacity(1), colour(D)]``; per-intersection data is read in sorted order
    (``splats[k]``, ``colors[k]``). Launch with a ``block_dim`` that divides ``tile_size^2``
    (blocks never straddle tiles); on CPU the block width is 1 and this is the per-pixel walk.

    ``per_warp=False``: the sum runs over the whole block (a tile reduction), after a block vote
    that skips Gaussians none of the block's pixels blended. ``per_warp=True`` (CUDA blocks whose
    size is a multiple of 32, e.g. one block per tile): each warp sums its 32 pixels with shuffles
    and adds, skipping Gaussians none of its pixels blended, and starts at its own pixels' last
    Gaussian (not the block's); the warps of a tile share the tile's data in the SM's cache.

    ``to_slots=True`` (the deterministic option) adds each block sum to the intersection's own slot
    ``slots[k]`` instead of the Gaussian's: on CUDA exactly one block writes a slot and the block
    reduction has a fixed order, on CPU blocks run in turn, so with :func:`gather_kernel` summing
    the slots in a fixed order the gradients are bit-identical from run to run.
    """
    t = types_for(scalar)
    splat = t.splat
    vecD = channel_vector(scalar, channels)
    vecG = channel_vector(scalar, channels + 6)
    layer_grad = layer_grad_func(scalar, channels)
    # CUDA float32: at most 256 threads per block (true of every launch in ops.py) and registers
    # capped for 5 blocks per SM (measured: 6% faster than the compiler's 4 at 1M Gaussians)
    bounds = (256, 5) if scalar == wp.float32 else None

    # no FMA contraction: the gating in pixel.py must decide as in the forward pass
    @wp.kernel(module="unique", module_options={"fuse_fp": False, "enable_backward": False, "fast_math": fast_math},
               launch_bounds=bounds)
    def blend_backward_reduced(
        splats: wp.array(dtype=splat),
        colors: wp.array(dtype=vecD),
        backgrounds: wp.array(dtype=vecD),
        flatten_ids: wp.array(dtype=wp.int32),
        offsets: wp.array(dtype=wp.int32),
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
        slots: wp.array(dtype=wp.int32),
        v_packed: wp.array(dtype=vecG),
    ):
        p = tile_pixel(wp.tid(), tile_size, tile_width, tile_height)
        rng = p[0]
        cam = p[1]
        x = p[2]
        y = p[3]
        last = int(-1)
        T_final = scalar(1.0)
        v_col = vecD()
        v_alpha_out = scalar(0.0)
        if x < width and y < height:
            pix = (cam * height + y) * width + x
            last = int(last_ids[pix])
            T_final = out_T[pix]
            v_col = v_out_colors[pix]
            v_alpha_out = v_out_alphas[pix]
        bg_term = T_final * wp.dot(backgrounds[cam], v_col)
        px = scalar(x) + scalar(0.5)
        py = scalar(y) + scalar(0.5)
        k = int(0)
        if wp.static(per_warp):
            k = warp_max(last)  # each warp starts at its own pixels' last Gaussian
        else:
            k = wp.tile_extract(wp.tile_max(wp.tile(last)), 0)
        start = offsets[rng]
        T_next = T_final
        S = vecD()
        while k >= start:
            pk = vecG()
            hit = int(0)
            if k <= last:
                used, T, S2, v_xy, v_cn, v_op, v_c = layer_grad(
                    splats[k], colors[k], px, py, alpha_min, alpha_max,
                    T_next, S, v_col, v_alpha_out, T_final, bg_term)
                if used != 0:
                    hit = 1
                    T_next = T
                    S = S2
                    pk[0] = v_xy[0]
                    pk[1] = v_xy[1]
                    pk[2] = v_cn[0]
                    pk[3] = v_cn[1]
                    pk[4] = v_cn[2]
                    pk[5] = v_op
                    for d in range(wp.static(channels)):
                        pk[6 + d] = v_c[d]
            if wp.static(per_warp):
                warp_sum_add(pk, hit, v_packed, int(flatten_ids[k]))
            # the vote's result is the same in every thread of the block: the tile operations
            # below are reached by all of them or by none
            elif block_any(hit) != 0:
                total = wp.tile_sum(wp.tile(pk, preserve_type=True))
                dst = int(flatten_ids[k])
                if wp.static(to_slots):
                    dst = int(slots[k])
                wp.tile_atomic_add(v_packed, total, offset=(dst,))
            k -= 1

    return blend_backward_reduced
