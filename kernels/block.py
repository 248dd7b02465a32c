"""Block and warp votes and sums for the blending backward (native CUDA snippets).

On CUDA a block of the blending kernels is a group of pixels of one tile that
walks the tile's Gaussians in lockstep; a vote lets the whole block (or warp)
skip work none of its pixels needs, and a warp-wide sum turns 32 pixels'
gradients for one Gaussian into one atomic add per component. On the CPU a block
is one thread: the vote is the thread's own flag and the sum its own value.
"""

from typing import Any

import warp as wp


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
return __syncthreads_or(flag);
#else
return flag;
#endif
"""
)
def block_any(flag: int) -> int:
    """Non-zero when ``flag`` is non-zero in any thread of the block (a barrier: every thread of
    the block must call it)."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
return __syncthreads_and(flag);
#else
return flag;
#endif
"""
)
def block_all(flag: int) -> int:
    """Non-zero when ``flag`` is non-zero in every thread of the block (a barrier: every thread of
    the block must call it); on the CPU (one thread per block) the thread's own flag."""
    ...


_WARP_SUM_ADD = r"""
const int n = (int)(sizeof(v.c) / sizeof(v.c[0]));
#if defined(__CUDA_ARCH__)
{
    typedef decltype(v.c[0] + v.c[0]) T;
    // P: n rounded up to a power of two; each halving step below keeps half of the P values
    constexpr int P = n <= 1 ? 1 : n <= 2 ? 2 : n <= 4 ? 4 : n <= 8 ? 8 : n <= 16 ? 16 : n <= 32 ? 32
                    : n <= 64 ? 64 : 128;
    const int lane = (int)(threadIdx.x & 31u);
    T buf[P];
#pragma unroll
    for (int i = 0; i < P; ++i)
        buf[i] = i < n ? v.c[i] : T(0);
    // one step per lane bit, high to low: while a lane holds more than one value, the lane with
    // the bit set keeps the upper half of its values and receives its partner's upper half (the
    // other the lower halves: a reduce-scatter); once one value is left, plain butterfly steps.
    // Every loop bound is a compile-time constant, so buf stays in registers.
#define SSG_WARP_STEP(O, H)                                                   \
    if ((H) >= 1) {                                                           \
        const bool up = (lane & (O)) != 0;                                    \
        _Pragma("unroll") for (int j = 0; j < (H); ++j) {                     \
            const T send = up ? buf[j] : buf[j + (H)];                        \
            const T keep = up ? buf[j + (H)] : buf[j];                        \
            buf[j] = keep + __shfl_xor_sync(0xffffffffu, send, (O));          \
        }                                                                     \
    } else {                                                                  \
        buf[0] += __shfl_xor_sync(0xffffffffu, buf[0], (O));                  \
    }
    SSG_WARP_STEP(16, P / 2)
    SSG_WARP_STEP(8, P / 4)
    SSG_WARP_STEP(4, P / 8)
    SSG_WARP_STEP(2, P / 16)
    SSG_WARP_STEP(1, P / 32)
#undef SSG_WARP_STEP
    auto* dst_c = &(wp::address(out, ((const int*)ids.data)[k])->c[0]);
    if (P >= 32) {
        // every lane holds the totals of P/32 consecutive components
#pragma unroll
        for (int j = 0; j < P / 32; ++j)
            if (lane * (P / 32) + j < n)
                atomicAdd(dst_c + lane * (P / 32) + j, buf[j]);
    } else {
        // groups of 32/P lanes hold the total of one component; the first lane of each adds it
        const int g = P >= 32 ? 1 : 32 / P;
        if (lane % g == 0 && lane / g < n)
            atomicAdd(dst_c + lane / g, buf[0]);
    }
}
#else
{
    auto* dst_c = &(wp::address(out, ((const int*)ids.data)[k])->c[0]);
    for (int i = 0; i < n; ++i)
        dst_c[i] += v.c[i];
}
#endif
"""


@wp.func_native(_WARP_SUM_ADD)
def warp_sum_add(v: Any, out: wp.array(dtype=Any), ids: wp.array(dtype=wp.int32), k: int):
    """``out[ids[k]] += sum of v`` over the 32 threads of a CUDA warp (all of which call it with the
    same ``k``; see :func:`warp_any` to skip it). The sum is a reduce-scatter butterfly: each
    shuffle step halves the values a lane holds, so ``n`` components cost about ``n`` shuffles
    (not ``5 n``) and end one per lane (or group of lanes), whose lanes then add them with one
    atomic instruction. ``ids`` must be contiguous. On the CPU (one thread per block) it is
    ``out[ids[k]] += v``. Needs full warps: launch with a block
    size that is a multiple of 32."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
return __any_sync(0xffffffffu, flag);
#else
return flag;
#endif
"""
)
def warp_any(flag: int) -> int:
    """Non-zero when ``flag`` is non-zero in any of the 32 threads of a CUDA warp (all of which
    call it); on the CPU (one thread per block) the thread's own flag."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
int m = v;
for (int o = 16; o > 0; o >>= 1)
    m = max(m, __shfl_xor_sync(0xffffffffu, m, o));
return m;
#else
return v;
#endif
"""
)
def warp_max(v: int) -> int:
    """The largest ``v`` of the 32 threads of a CUDA warp (all of which call it); on the CPU (one
    thread per block) ``v`` itself."""
    ...
