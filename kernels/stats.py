"""Densification statistics of one render, accumulated per Gaussian (the default strategy's
``grad2d``, ``count`` and ``max_radii``; ``ssgwarp/reconstruction/strategy.py: accumulate_grad2d``).

One thread per Gaussian walks the cameras in order: where the Gaussian was visible (both radii
> 0) it adds the norm of its screen-space positional gradient scaled to NDC units to ``grad2d``,
1 to ``count``, and keeps the largest screen radius as a fraction of the image's larger side in
``max_radii`` (absent: a null array). The torch version runs a dozen elementwise ops for the
same sums; here one launch, in place, no host synchronisation.
"""

import functools

import warp as wp

from .types import types_for


@functools.lru_cache(maxsize=None)
def grad2d_kernel(scalar):
    """``accumulate_grad2d(grads [C*N], radii [C*N], C, N, sx, sy, inv_side, grad2d [N], count [N],
    max_radii [N])``, launched over N: ``grads`` the screen-space gradients (``vec2`` rows, camera-major),
    ``radii`` their per-axis radii; ``sx``, ``sy`` the pixel-to-NDC scales (``W / 2``, ``H / 2``, times
    the number of cameras the loss averages over); ``inv_side``: ``1 / max(W, H)``. The sums over the
    cameras start at 0 and are added to the statistics once (the order of torch's ``sum(dim=0)``)."""
    vec2 = types_for(scalar).vec2

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def accumulate_grad2d(grads: wp.array(dtype=vec2), radii: wp.array(dtype=wp.vec2i), C: int, N: int,
                          sx: scalar, sy: scalar, inv_side: scalar, grad2d: wp.array(dtype=scalar),
                          count: wp.array(dtype=scalar), max_radii: wp.array(dtype=scalar)):
        n = wp.tid()
        zero = scalar(0.0)
        norms = zero
        seen = zero
        largest = zero
        for c in range(C):
            i = c * N + n
            r = radii[i]
            if r[0] > 0 and r[1] > 0:
                g = grads[i]
                norms = norms + wp.length(vec2(g[0] * sx, g[1] * sy))
                seen = seen + scalar(1.0)
                largest = wp.max(largest, scalar(wp.max(r[0], r[1])) * inv_side)
        grad2d[n] = grad2d[n] + norms
        count[n] = count[n] + seen
        if max_radii.shape[0] > 0:
            max_radii[n] = wp.max(max_radii[n], largest)

    return accumulate_grad2d
