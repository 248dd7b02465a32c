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
deterministic option on both devices. Its variants:

* ``per_warp=False``: the sum runs over the whole block (a tile reduction), after a block vote that
  skips Gaussians none of the block's pixels blended. ``per_warp=True`` (CUDA blocks whose size is a
  multiple of 32, e.g. one block per tile): each warp sums its 32 pixels with shuffles and adds,
  skipping Gaussians none of its pixels blended, and starts at its own pixels' last Gaussian (not the
  block's); the warps of a tile share the tile's data in the SM's cache.
* ``to_slots=True`` (the deterministic option) adds each block sum to the intersection's own slot
  ``slots[k]`` instead of the Gaussian's: on CUDA (``per_warp=False``, one block per tile) exactly one
  block writes a slot and the block reduction has a fixed order; on the CPU (``per_warp=True``, one
  pixel per block) the pixels of a tile add to its slots one after the other in pixel order, and
  launches over disjoint runs of tiles write disjoint slots; so with :func:`gather_kernel` summing the
  slots in a fixed order the gradients are bit-identical from run to run (and on the CPU for any
  number of launches side by side).
* ``colour_only=True``: the colours' gradients alone, ``[colour(D)]`` (:func:`layer_colour_grad_func`).
* ``through_ids=False``: per-intersection data is read in sorted order from the forward's gather
  (``splats[k]``, ``colors[k]``); ``True``: ``splats`` and ``colors`` are the projection's
  per-(camera, Gaussian) arrays, read through the sorted ids as the forward's
  :func:`.blend_forward.batched_forward_kernel` reads them (``color_shift`` as there).
* ``absgrad=True`` (with the geometry, not with ``split_colours``): each row ends in two more
  values, the sum over pixels of ``|d loss / d xy|`` per pixel (gsplat's ``means2d.absgrad``),
  summed and added like the others: ``[xy(2), conic(3), opacity(1), colour(D), |xy|(2)]``.
* ``split_colours=True`` (with the geometry, not with ``to_slots``): the colours' gradients go to rows
  of their own, ``v_colours [C*N, D]``, and ``v_packed`` holds ``[xy(2), conic(3), opacity(1)]``: the
  colours' gradient is then a contiguous tensor autograd keeps as it is (no copy); two atomic adds
  per Gaussian instead of one (slower at millions of intersections).
"""

import functools

import warp as wp

from .block import block_any, warp_any, warp_max, warp_sum_add
from .pixel import pixel_funcs, tile_pixel
from .types import channel_vector, element_at, splat_at, types_for


@functools.lru_cache(maxsize=None)
def layer_grad_func(scalar, channels: int, absgrad: bool = False):
    """``layer_grad(...)``: one layer of the reverse traversal of one pixel, without branches.

    Takes the gating's result for this pixel (``used``: whether the forward pass blended the
    Gaussian here; ``alpha``, 0 where not used, so nothing changes; ``g = exp(-sigma)``; ``dx``,
    ``dy``), the packed projected Gaussian, its colour and the pixel's state after it (``T_next``:
    transmittance behind it, ``S``: colour accumulated behind it). Returns ``(T, S', grad)`` with ``grad`` packed as
    ``[xy(2), conic(3), opacity(1), colour(D)]`` (zero where not used). Branch-free, so a
    block's pixels run it in lockstep with no merging of per-pixel results afterwards.
    ``absgrad``: two more values, ``|xy|`` of this pixel's own gradient (summed over the pixels
    they give gsplat's ``means2d.absgrad``), packed as ``[..., colour(D), |xy|(2)]``.
    """
    t = types_for(scalar)
    splat = t.splat
    vecD = channel_vector(scalar, channels)
    vecG = channel_vector(scalar, channels + (8 if absgrad else 6))

    @wp.func
    def layer_grad(sp: splat, c: vecD, used: bool, alpha: scalar, g: scalar, dx: scalar, dy: scalar,
                   alpha_max: scalar, T_next: scalar, S: vecD, v_col: vecD, v_alpha_out: scalar, T_final: scalar,
                   bg_term: scalar):
        inv = scalar(1.0) / (scalar(1.0) - alpha)
        T = T_next * inv
        w = alpha * T
        v_a = T * wp.dot(c, v_col) - (wp.dot(S, v_col) + bg_term - v_alpha_out * T_final) * inv
        # no gradient through alpha where the clamp alpha_max was active (nor where not used)
        open_ = used and sp[5] * g <= alpha_max
        v_sigma = wp.where(open_, -v_a * alpha, scalar(0.0))
        v_op = wp.where(open_, v_a * g, scalar(0.0))
        grad = vecG()
        grad[0] = v_sigma * (sp[2] * dx + sp[3] * dy)
        grad[1] = v_sigma * (sp[3] * dx + sp[4] * dy)
        grad[2] = scalar(0.5) * dx * dx * v_sigma
        grad[3] = dx * dy * v_sigma
        grad[4] = scalar(0.5) * dy * dy * v_sigma
        grad[5] = v_op
        for d in range(wp.static(channels)):
            grad[6 + d] = v_col[d] * w
        if wp.static(absgrad):
            grad[6 + channels] = wp.abs(grad[0])
            grad[7 + channels] = wp.abs(grad[1])
        return T, S + c * w, grad

    return layer_grad


@functools.lru_cache(maxsize=None)
def layer_colour_grad_func(scalar, channels: int):
    """:func:`layer_grad_func`'s layer when only the colours want a gradient (the geometry is
    frozen), with the same arguments: the same ``T`` and colour gradient ``v_col * alpha T``,
    rounded the same way, returned alone as ``grad [colour(D)]`` (``S`` passed through); the
    alpha and geometry terms are not computed."""
    t = types_for(scalar)
    splat = t.splat
    vecD = channel_vector(scalar, channels)

    @wp.func
    def layer_colour_grad(sp: splat, c: vecD, used: bool, alpha: scalar, g: scalar, dx: scalar, dy: scalar,
                          alpha_max: scalar, T_next: scalar, S: vecD, v_col: vecD, v_alpha_out: scalar,
                          T_final: scalar, bg_term: scalar):
        T = T_next * (scalar(1.0) / (scalar(1.0) - alpha))
        return T, S, v_col * (alpha * T)

    return layer_colour_grad


@functools.lru_cache(maxsize=None)
def split_funcs(scalar, channels: int):
    """``(geometry_of, colour_of)``: the ``[xy(2), conic(3), opacity(1)]`` and ``[colour(D)]`` parts of
    a gradient packed as :func:`layer_grad_func` returns it."""
    vecG = channel_vector(scalar, channels + 6)
    vec6 = channel_vector(scalar, 6)
    vecD = channel_vector(scalar, channels)

    @wp.func
    def geometry_of(pk: vecG) -> vec6:
        out = vec6()
        for i in range(6):
            out[i] = pk[i]
        return out

    @wp.func
    def colour_of(pk: vecG) -> vecD:
        out = vecD()
        for d in range(wp.static(channels)):
            out[d] = pk[6 + d]
        return out

    return geometry_of, colour_of


@functools.lru_cache(maxsize=None)
def gather_kernel(scalar, width: int):
    """Sum each Gaussian's per-intersection gradient slots (``width`` values each: ``6 + D``, or
    ``D`` for colour-only gradients) in a fixed order (deterministic)."""
    vecG = channel_vector(scalar, width)

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
                            fast_math: bool = False, colour_only: bool = False, through_ids: bool = False,
                            split_colours: bool = False, absgrad: bool = False):
    """Backward by blocks of pixels of one tile (the variants: the module's docstring): the block walks
    the tile's Gaussians in lockstep (from the largest last index of its pixels), sums the pixels'
    gradients for each Gaussian and adds the sum with one atomic per Gaussian. Gradients land packed
    as ``[xy(2), conic(3), opacity(1), colour(D)]``; the images' gradients are read in place through
    their strides (``[pixels, D]``, ``[pixels]``). Launch with a ``block_dim`` that divides ``tile_size^2``
    (on CPU the block width is 1: the per-pixel walk); ``first``: as in :mod:`.blend_forward`."""
    splat = types_for(scalar).splat
    IDS = bool(through_ids)
    ABS = bool(absgrad) and not colour_only
    SPLIT = bool(split_colours) and not colour_only and not to_slots and not ABS
    vecD = channel_vector(scalar, channels)
    # the packed rows: the colours alone, the geometry alone, or both (with absgrad: then |xy|)
    vecG = channel_vector(scalar, channels if colour_only else 6 if SPLIT else channels + (8 if ABS else 6))
    layer_grad = layer_colour_grad_func(scalar, channels) if colour_only else layer_grad_func(scalar, channels, ABS)
    splat_alpha, _ = pixel_funcs(scalar)
    colour_at = element_at(vecD)
    # CUDA float32: at most 256 threads per block (true of every launch in ops.py) and registers
    # capped for 5 blocks per SM (measured: 6% faster than the compiler's 4 at 1M Gaussians)
    bounds = (256, 5) if scalar == wp.float32 else None
    geometry_of, colour_of = split_funcs(scalar, channels)

    # no FMA contraction: the gating in pixel.py must decide as in the forward pass
    @wp.kernel(module="unique", module_options={"fuse_fp": False, "enable_backward": False, "fast_math": fast_math},
               launch_bounds=bounds)
    def blend_backward_reduced(
        splats: wp.array(dtype=splat),
        colors: wp.array(dtype=vecD),
        backgrounds: wp.array(dtype=vecD),
        flatten_ids: wp.array(dtype=wp.int32),
        color_shift: int,
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
        v_out_colors: wp.array2d(dtype=scalar),
        v_out_alphas: wp.array(dtype=scalar),
        slots: wp.array(dtype=wp.int32),
        v_packed: wp.array(dtype=vecG),
        v_colours: wp.array(dtype=vecD),
        first: int,
    ):
        p = tile_pixel(wp.tid() + first, tile_size, tile_width, tile_height)
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
            # (an image without a gradient comes as a null array: zeros)
            if v_out_colors.shape[0] > 0:
                for d in range(wp.static(channels)):
                    v_col[d] = v_out_colors[pix, d]
            if v_out_alphas.shape[0] > 0:
                v_alpha_out = v_out_alphas[pix]
        bg_term = scalar(0.0)
        if backgrounds.shape[0] > 0:  # (an absent background: a null array)
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
        shift = cam * color_shift
        while k >= start:
            at = k  # (where this intersection's splat and colour are read: the gather, or through the ids)
            if wp.static(IDS):
                at = int(flatten_ids[k])
            sp = splat_at(splats, at)
            a, g, dx, dy, keep = splat_alpha(sp, px, py, alpha_min, alpha_max)
            # not used: this pixel did not blend this Gaussian (skipped, or behind its last one)
            used = k <= last and keep
            alpha = wp.where(used, a, scalar(0.0))
            hit = int(used)
            # the vote's result is the same in every thread of the warp (block): the sums below
            # are reached by all of them or by none
            if wp.static(per_warp):
                if warp_any(hit) != 0:
                    T_next, S, pk = layer_grad(sp, colour_at(colors, at - shift), used, alpha, g, dx, dy, alpha_max,
                                               T_next, S, v_col, v_alpha_out, T_final, bg_term)
                    if wp.static(to_slots):  # (the CPU's deterministic walk: one pixel per block)
                        warp_sum_add(pk, v_packed, slots, k)
                    elif wp.static(SPLIT):
                        warp_sum_add(geometry_of(pk), v_packed, flatten_ids, k)
                        warp_sum_add(colour_of(pk), v_colours, flatten_ids, k)
                    else:
                        warp_sum_add(pk, v_packed, flatten_ids, k)
            elif block_any(hit) != 0:
                T_next, S, pk = layer_grad(sp, colour_at(colors, at - shift), used, alpha, g, dx, dy, alpha_max,
                                           T_next, S, v_col, v_alpha_out, T_final, bg_term)
                dst = int(flatten_ids[k])
                if wp.static(to_slots):
                    dst = int(slots[k])
                if wp.static(SPLIT):
                    wp.tile_atomic_add(v_packed, wp.tile_sum(wp.tile(geometry_of(pk), preserve_type=True)), offset=(dst,))
                    wp.tile_atomic_add(v_colours, wp.tile_sum(wp.tile(colour_of(pk), preserve_type=True)), offset=(dst,))
                else:
                    wp.tile_atomic_add(v_packed, wp.tile_sum(wp.tile(pk, preserve_type=True)), offset=(dst,))
            k -= 1

    return blend_backward_reduced
