"""Floating-point operations with a fixed rounding, for arithmetic that must not depend on the
compiler's contraction choices (native snippets; each has its adjoint, so Warp can differentiate
through them).

- :func:`fma`: ``a b + c`` rounded once.
- :func:`add_rn`: ``a + b``, never fused with a product feeding it.
- :func:`div_rn`: ``a / b`` correctly rounded, also in kernels compiled with fast maths.
- :func:`rsqrt`: the GPU's reciprocal square root (float32; ``1 / sqrt`` on the CPU).

The projection (gsplat form) and the per-pixel rule use them to reproduce, operation for
operation, the roundings nvcc makes in gsplat's kernels (see ``kernels/projection.py``).
"""

import warp as wp

_FMA = """
#if defined(__CUDA_ARCH__)
return {rn}(a, b, c);
#else
return {libm}(a, b, c);
#endif
"""
_FMA_ADJ = """
adj_a += b * adj_ret;
adj_b += a * adj_ret;
adj_c += adj_ret;
"""
_ADD = """
#if defined(__CUDA_ARCH__)
return {rn}(a, b);
#else
return a + b;
#endif
"""
_ADD_ADJ = """
adj_a += adj_ret;
adj_b += adj_ret;
"""


@wp.func_native(_FMA.format(rn="__fmaf_rn", libm="fmaf"), _FMA_ADJ)
def fma(a: wp.float32, b: wp.float32, c: wp.float32) -> wp.float32:
    """``a b + c`` rounded once."""
    ...


@wp.func_native(_FMA.format(rn="__fma_rn", libm="fma"), _FMA_ADJ)
def fma(a: wp.float64, b: wp.float64, c: wp.float64) -> wp.float64:  # noqa: F811 (the float64 overload)
    """``a b + c`` rounded once."""
    ...


@wp.func_native(_ADD.format(rn="__fadd_rn"), _ADD_ADJ)
def add_rn(a: wp.float32, b: wp.float32) -> wp.float32:
    """``a + b`` rounded on its own (not contracted with a product that feeds it)."""
    ...


@wp.func_native(_ADD.format(rn="__dadd_rn"), _ADD_ADJ)
def add_rn(a: wp.float64, b: wp.float64) -> wp.float64:  # noqa: F811 (the float64 overload)
    """``a + b`` rounded on its own (not contracted with a product that feeds it)."""
    ...


_DIV = """
#if defined(__CUDA_ARCH__)
return {rn}(a, b);
#else
return a / b;
#endif
"""
_DIV_ADJ = """
adj_a += adj_ret / b;
adj_b -= adj_ret * a / (b * b);
"""


@wp.func_native(_DIV.format(rn="__fdiv_rn"), _DIV_ADJ)
def div_rn(a: wp.float32, b: wp.float32) -> wp.float32:
    """``a / b`` correctly rounded (IEEE), whatever the kernel's fast-maths option."""
    ...


@wp.func_native(_DIV.format(rn="__ddiv_rn"), _DIV_ADJ)
def div_rn(a: wp.float64, b: wp.float64) -> wp.float64:  # noqa: F811 (the float64 overload)
    """``a / b`` correctly rounded (IEEE)."""
    ...


_RSQRT = """
#if defined(__CUDA_ARCH__)
return rsqrtf(x);
#else
return 1.0f / sqrtf(x);
#endif
"""
_RSQRT_ADJ = """
#if defined(__CUDA_ARCH__)
const float r = rsqrtf(x);
#else
const float r = 1.0f / sqrtf(x);
#endif
adj_x += -0.5f * r * r * r * adj_ret;
"""


@wp.func_native(_RSQRT, _RSQRT_ADJ)
def rsqrt(x: wp.float32) -> wp.float32:
    """``1 / sqrt(x)`` through CUDA's ``rsqrtf`` (the GPU's approximate reciprocal square root, as
    gsplat normalises quaternions), ``1 / sqrtf`` on the CPU."""
    ...
