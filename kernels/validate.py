"""Input value checks in one pass: one thread per element index, every input read flat.

Each check that fails sets its own flag (a plain store of 1: threads that find the same
problem write the same value). The flags are read back once, together with the
intersection count, and turned into errors on the host (``ssgwarp.rasterize``).
"""

import functools
from typing import Any

import warp as wp

# flag slots: 0..7 NaN/Inf in the input of that position in INPUTS, then the range checks
INPUTS = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "backgrounds")
ZERO_QUAT = wp.constant(8)
NEGATIVE_SCALE = wp.constant(9)
OPACITY_RANGE = wp.constant(10)
FOCAL = wp.constant(11)
N_FLAGS = 12


@wp.func
def flag_nonfinite(a: wp.array(dtype=Any), i: int, slot: int, flags: wp.array(dtype=wp.int64)):
    """``flags[slot] = 1`` when ``a[i]`` exists and is NaN or infinite (float32 or float64)."""
    if i < a.shape[0]:
        if not wp.isfinite(a[i]):
            flags[slot] = wp.int64(1)


@functools.lru_cache(maxsize=None)
def check_kernel(scalar):
    """``check(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds, n_gauss,
    n_cams, flags)`` over flat views (``quats`` and ``Ks`` are read flat, 4 and 9 values per
    Gaussian / camera); launch with the largest flat length."""

    # no fast maths: isfinite must see NaN and Inf
    @wp.kernel(module="unique", module_options={"fast_math": False, "enable_backward": False})
    def check(means: wp.array(dtype=scalar), quats: wp.array(dtype=scalar), scales: wp.array(dtype=scalar),
              opacities: wp.array(dtype=scalar), colors: wp.array(dtype=scalar), viewmats: wp.array(dtype=scalar),
              Ks: wp.array(dtype=scalar), backgrounds: wp.array(dtype=scalar), n_gauss: int, n_cams: int,
              flags: wp.array(dtype=wp.int64)):
        i = wp.tid()
        flag_nonfinite(means, i, 0, flags)
        flag_nonfinite(quats, i, 1, flags)
        flag_nonfinite(scales, i, 2, flags)
        flag_nonfinite(opacities, i, 3, flags)
        flag_nonfinite(colors, i, 4, flags)
        flag_nonfinite(viewmats, i, 5, flags)
        flag_nonfinite(Ks, i, 6, flags)
        flag_nonfinite(backgrounds, i, 7, flags)
        if i < n_gauss:
            q = 4 * i
            if quats[q] == scalar(0.0) and quats[q + 1] == scalar(0.0) and quats[q + 2] == scalar(0.0) \
                    and quats[q + 3] == scalar(0.0):
                flags[ZERO_QUAT] = wp.int64(1)
            o = opacities[i]
            if o < scalar(0.0) or o > scalar(1.0):
                flags[OPACITY_RANGE] = wp.int64(1)
        if i < scales.shape[0]:
            if scales[i] < scalar(0.0):
                flags[NEGATIVE_SCALE] = wp.int64(1)
        if i < n_cams:
            if Ks[9 * i] <= scalar(0.0) or Ks[9 * i + 4] <= scalar(0.0):
                flags[FOCAL] = wp.int64(1)

    return check
