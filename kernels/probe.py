"""A small kernel the launch layer's self-test runs both ways (``ssgwarp/raster/private_api.py``): replayed
through the fast path and through ``wp.launch``, forward and adjoint, before any of the rasterizer's kernels is
replayed on a device. Its parameters have the kinds the rasterizer's kernels have: arrays of vectors, a 2-D
array whose first stride is 0 (every row reads the same elements), a ``wp.struct`` of scalars and a scalar."""

import functools

import warp as wp


@wp.struct
class ProbeParams:
    scale: wp.float32
    shift: wp.int32


@functools.lru_cache(maxsize=None)
def probe_kernel():
    """``probe(x [n] vec3, p, k, w [2, n], y [n])``, launched over n: ``y[i] = (x0 + 2 x1 - x2) * p.scale +
    (p.shift + k i) + w[i % 2, i]`` (its adjoint: the gradients to ``x`` and ``w``)."""

    @wp.kernel(module="unique")
    def probe(x: wp.array(dtype=wp.vec3), p: ProbeParams, k: int, w: wp.array2d(dtype=wp.float32),
              y: wp.array(dtype=wp.float32)):
        i = wp.tid()
        v = x[i]
        y[i] = (v[0] + 2.0 * v[1] - v[2]) * p.scale + float(p.shift + k * i) + w[i % 2, i]

    return probe
