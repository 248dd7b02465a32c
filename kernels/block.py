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


_WARP_SUM_ADD = """
auto* dst_c = &(wp::address(out, dst)->c[0]);
const int n = (int)(sizeof(v.c) / sizeof(v.c[0]));
#if defined(__CUDA_ARCH__)
if (__any_sync(0xffffffffu, hit)) {
    const int lane = (int)(threadIdx.x & 31u);
    for (int i = 0; i < n; ++i) {
        auto s = v.c[i];
        for (int o = 16; o > 0; o >>= 1)
            s += __shfl_xor_sync(0xffffffffu, s, o);
        if (lane == (i & 31))
            atomicAdd(dst_c + i, s);
    }
}
#else
if (hit) {
    for (int i = 0; i < n; ++i)
        dst_c[i] += v.c[i];
}
#endif
"""


@wp.func_native(_WARP_SUM_ADD)
def warp_sum_add(v: Any, hit: int, out: wp.array(dtype=Any), dst: int):
    """``out[dst] += sum of v`` over the 32 threads of a CUDA warp (all of which call it and share
    ``dst``), skipped when no thread has ``hit``; the sum is a shuffle butterfly per component
    and different lanes add different components in one step. On the CPU (one thread per
    block) it is ``out[dst] += v`` when ``hit``. Needs full warps: launch with a block size that
    is a multiple of 32."""
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
