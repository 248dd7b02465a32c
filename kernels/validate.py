"""Input value checks, in two forms.

:func:`inputs_check_func`, called by the projection kernel on the values it loads anyway (the
rasterizer's path: no pass of its own), answers only whether a check failed; the projection then
marks the Gaussian's intersection count (``projection.CHECK_FAILED``), so that the one value the
rasterizer reads back per call, the intersection total, also says whether every check passed.
:func:`check_kernel`, one thread per element index with every input read flat, sets one flag per
kind of failure (a plain store of 1: threads that find the same problem write the same value);
it runs where nothing is projected (no Gaussians) and, once a call's total has come back marked,
to name the failed check in the error (``ssgwarp.raster.settings.raise_for_flags``).
Finiteness is tested on the bit pattern (:func:`finite`), so it holds in kernels compiled with
fast maths too.
"""

import functools
from typing import Any

import warp as wp

from .types import types_for

# flag slots: 0..7 NaN/Inf in the input of that position in INPUTS, then the range checks
INPUTS = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "backgrounds")
ZERO_QUAT = wp.constant(8)
NEGATIVE_SCALE = wp.constant(9)
OPACITY_RANGE = wp.constant(10)
FOCAL = wp.constant(11)
N_FLAGS = 12


_FINITE32 = """
#if defined(__CUDA_ARCH__)
return (__float_as_uint(x) & 0x7f800000u) != 0x7f800000u;
#else
union { float f; unsigned int u; } v;
v.f = x;
return (v.u & 0x7f800000u) != 0x7f800000u;
#endif
"""
_FINITE64 = """
#if defined(__CUDA_ARCH__)
return (__double_as_longlong(x) & 0x7ff0000000000000ll) != 0x7ff0000000000000ll;
#else
union { double f; unsigned long long u; } v;
v.f = x;
return (v.u & 0x7ff0000000000000ull) != 0x7ff0000000000000ull;
#endif
"""


@wp.func_native(_FINITE32)
def finite(x: wp.float32) -> bool:
    """Neither NaN nor infinite (from the exponent bits: fast maths cannot assume it away)."""
    ...


@wp.func_native(_FINITE64)
def finite(x: wp.float64) -> bool:  # noqa: F811 (the float64 overload)
    """Neither NaN nor infinite (from the exponent bits)."""
    ...


@functools.lru_cache(maxsize=None)
def inputs_check_func(scalar):
    """``check_inputs(c, n, i, mean, quat, scale, opacity, viewmat, K, colors, row, per_camera,
    backgrounds, bg_row) -> bool``: whether a value check fails for Gaussian ``n`` seen from
    camera ``c`` (flat index ``i``), from values the projection has loaded: the Gaussian's own
    inputs once (camera 0), its colour row (``row`` values of the flat ``colors``, per camera or
    shared), and camera ``c``'s view matrix, intrinsics and background row once (Gaussian 0).
    Which check failed is not kept: a call that fails runs :func:`check_kernel` for the message."""
    t = types_for(scalar)
    vec3, vec4, mat33, mat44 = t.vec3, t.vec4, t.mat33, t.mat44

    @wp.func
    def colour_row_finite(colors: wp.array(dtype=scalar), base: int, row: int) -> bool:
        for j in range(row):
            if not finite(colors[base + j]):
                return False
        return True

    @wp.func
    def check_inputs(c: int, n: int, i: int, m: vec3, q: vec4, s: vec3, o: scalar, V: mat44, K: mat33,
                     colors: wp.array(dtype=scalar), row: int, per_camera: int,
                     backgrounds: wp.array(dtype=scalar), bg_row: int) -> bool:
        zero = scalar(0.0)
        if c == 0:
            for j in range(3):
                if not finite(m[j]) or not finite(s[j]) or s[j] < zero:
                    return True
            for j in range(4):
                if not finite(q[j]):
                    return True
            if q[0] == zero and q[1] == zero and q[2] == zero and q[3] == zero:
                return True
            if not finite(o) or o < zero or o > scalar(1.0):
                return True
        if c == 0 or per_camera != 0:
            base = n * row
            if per_camera != 0:
                base = i * row
            if not colour_row_finite(colors, base, row):
                return True
        if n == 0:
            for r in range(4):
                for col in range(4):
                    if not finite(V[r, col]):
                        return True
            for r in range(3):
                for col in range(3):
                    if not finite(K[r, col]):
                        return True
            if K[0, 0] <= zero or K[1, 1] <= zero:
                return True
            if not colour_row_finite(backgrounds, c * bg_row, bg_row):
                return True
        return False

    return check_inputs


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
