"""The 3DGS photometric loss fused: L1 + D-SSIM of two image batches and its gradient.

Images are ``[V, H, W, C]`` arrays (any strides: read in place), the SSIM window a normalised 1-D
Gaussian of ``2 R + 1`` taps applied separably with reflected borders (the convention of
``ssgwarp.services.losses.ssim_map`` and kornia: index ``-1`` reads ``1``, ``n`` reads ``n - 2``;
images narrower than the window reflect again and again, as numpy's ``pad(mode="reflect")``).

Forward, two passes over the ``N = V H W C`` pixel-channels, each thread one of them:

- :func:`rows_kernel`: the five moments ``x', y', x'^2, y'^2, x' y'`` blurred along the rows, of
  ``x' = x - SHIFT``, ``y' = y - SHIFT`` (:data:`SHIFT`: why).
- :func:`cols_kernel`: blurred along the columns, the per-pixel SSIM and its partial derivatives
  (:func:`ssim_funcs`, written once), and the loss: the sum over pixels of
  ``w_l1 |x - y| + w_ssim S`` (weights already divided by ``N``) plus ``w_0`` (added by pixel 0),
  accumulated in float64 (a block sum and one atomic add per block on CUDA, a plain sum per launch
  on the CPU). Where a backward follows, the partials are stored per pixel-channel:
  ``(dS/dmu'_x, dS/ds'_xx, dS/ds'_xy[, dS/dmu'_y])`` (``dS/ds'_yy = dS/ds'_xx``).

Backward: the loss reaches pixel ``q`` of ``x`` through the blurred moments of every pixel whose
window covers it, so with ``G^T`` the adjoint of the blur (:func:`cols_adjoint_kernel` along the
columns, then :func:`rows_adjoint_kernel` along the rows, the latter also finishing)::

    dL/dx(q) = g [ (G^T dS/dmu'_x)(q) + 2 x'(q) (G^T dS/ds'_xx)(q) + y'(q) (G^T dS/ds'_xy)(q) ]
               + g_l1 sign(x(q) - y(q))

(``y``: the same with the roles swapped), ``g`` and ``g_l1`` the loss's weights times the
incoming gradient, read on the device. The adjoint of the reflected blur gathers, for pixel
``q``, every padded position ``j`` that reads ``q`` (``j = +-q`` modulo the reflection's period
``2 (n - 1)``, within ``[-R, n - 1 + R]``) and the taps of the outputs around it: no atomics.

``first``: the pixel-channel of a launch's first thread (0 for all of them in one launch; on the
CPU a launch may cover a run of them so that several run side by side:
``ssgwarp.raster.cpu_threads``).
"""

import functools

import warp as wp

from .types import types_for

C1 = 0.01 ** 2  # SSIM's stabilisers for images in [0, 1] (K1 = 0.01, K2 = 0.03)
C2 = 0.03 ** 2
EPS = 1e-12     # added to the denominator (as kornia and ssgwarp.services.losses.ssim_map add it)
# the moments are those of x - SHIFT and y - SHIFT (variances and covariance do not change): for images
# in [0, 1] their squares are at most 1/4 instead of 1, so the variances' cancellation (a raw second
# moment minus a squared mean, exact 0 for a flat region) keeps more of float32's bits
SHIFT = 0.5
BLOCK = 256     # CUDA threads per block of the loss kernel (the block sum needs whole blocks)


@wp.func
def reflect(j: int, n: int) -> int:
    """The pixel that padded index ``j`` of a row of ``n`` reads (reflected borders, repeated for
    rows shorter than the padding)."""
    if j >= 0 and j < n:
        return j
    if n == 1:
        return 0
    period = 2 * (n - 1)
    r = j % period
    if r < 0:
        r = r + period
    if r >= n:
        r = period - r
    return r


_BLOCK_SUM_ADD = r"""
#if defined(__CUDA_ARCH__)
{
    __shared__ double ssg_block_part[32];
    double s = v;
    for (int o = 16; o > 0; o >>= 1)
        s += __shfl_xor_sync(0xffffffffu, s, o);
    const int lane = (int)(threadIdx.x & 31u);
    const int wid = (int)(threadIdx.x >> 5);
    if (lane == 0)
        ssg_block_part[wid] = s;
    __syncthreads();
    if (wid == 0) {
        const int nw = (int)((blockDim.x + 31u) >> 5);
        s = lane < nw ? ssg_block_part[lane] : 0.0;
        for (int o = 16; o > 0; o >>= 1)
            s += __shfl_xor_sync(0xffffffffu, s, o);
        if (lane == 0)
            atomicAdd(wp::address(out, 0), s);
    }
    __syncthreads();
}
#else
*wp::address(out, 0) += v;
#endif
"""


@wp.func_native(_BLOCK_SUM_ADD)
def block_sum_add(v: wp.float64, out: wp.array(dtype=wp.float64)):
    """``out[0] += sum of v`` over the CUDA block (a barrier: every thread of the block calls it,
    launched over whole blocks; one atomic add per block); on the CPU ``out[0] += v``."""
    ...


@functools.lru_cache(maxsize=None)
def ssim_funcs(scalar):
    """``ssim_pixel(m) -> (S, partials)`` for the five blurred moments ``m`` of ``x - SHIFT`` and
    ``y - SHIFT`` (first and raw second: ``m = (mu'_x, mu'_y, s'_xx, s'_yy, s'_xy)``): means
    ``mu = mu' + SHIFT``, variances ``s'_xx - mu'_x^2`` (shift-free), ``S = (2 mu_x mu_y + C1)(2 cov +
    C2) / ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2) + EPS)``, and ``partials = (dS/dmu'_x,
    dS/ds'_xx, dS/ds'_xy, dS/dmu'_y)`` (``dS/ds'_yy = dS/ds'_xx``). The forward's loss and the
    backward's gradient both come from it."""
    vec4 = types_for(scalar).vec4
    vec5 = wp.types.vector(5, scalar)

    @wp.func
    def ssim_pixel(m: vec5):
        mu_x = m[0] + scalar(SHIFT)
        mu_y = m[1] + scalar(SHIFT)
        two = scalar(2.0)
        a1 = two * mu_x * mu_y + scalar(C1)
        a2 = two * (m[4] - m[0] * m[1]) + scalar(C2)
        b1 = mu_x * mu_x + mu_y * mu_y + scalar(C1)
        b2 = (m[2] - m[0] * m[0]) + (m[3] - m[1] * m[1]) + scalar(C2)
        den = b1 * b2 + scalar(EPS)
        s = a1 * a2 / den
        inv = scalar(1.0) / den
        # S = a1 a2 / den; mu'_x reaches it through mu_x (a1, b1) and through var_x (b2) and cov (a2)
        sb1 = s * b1
        partials = vec4(two * (mu_y * a2 - s * mu_x * b2 + m[0] * sb1 - m[1] * a1) * inv, -(sb1 * inv),
                        two * a1 * inv, two * (mu_x * a2 - s * mu_y * b2 + m[1] * sb1 - m[0] * a1) * inv)
        return s, partials

    return ssim_pixel


@wp.func
def unflatten(i: int, H: int, W: int, C: int):
    """``(v, y, x, c)`` of flat pixel-channel ``i`` of a ``[V, H, W, C]`` image batch."""
    c = i % C
    t = i // C
    x = t % W
    r = t // W
    return r // H, r % H, x, c


@functools.lru_cache(maxsize=None)
def rows_kernel(scalar, radius: int):
    """``ssim_rows(a, b, window, moments, first)``: ``moments[i]`` = the five moments of pixel-channel
    ``i`` blurred along its row (``window``: the ``2 radius + 1`` taps)."""
    vec5 = wp.types.vector(5, scalar)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def ssim_rows(a: wp.array4d(dtype=scalar), b: wp.array4d(dtype=scalar), window: wp.array(dtype=scalar),
                  moments: wp.array(dtype=vec5), first: int):
        i = wp.tid() + first
        v, y, x, c = unflatten(i, a.shape[1], a.shape[2], a.shape[3])
        W = a.shape[2]
        acc = vec5()
        for k in range(wp.static(2 * radius + 1)):
            xx = reflect(x + k - radius, W)
            p = a[v, y, xx, c] - scalar(SHIFT)
            q = b[v, y, xx, c] - scalar(SHIFT)
            acc = acc + window[k] * vec5(p, q, p * p, q * q, p * q)
        moments[i] = acc

    return ssim_rows


@functools.lru_cache(maxsize=None)
def cols_kernel(scalar, radius: int, both: bool):
    """``ssim_cols(moments, a, b, window, partials, loss, n, w_l1, w_ssim, w_0, first)``: the row-blurred
    moments blurred along the columns, the SSIM per pixel-channel, ``loss[0] +=`` the sum of
    ``w_l1 |a - b| + w_ssim S`` over this launch's pixel-channels (``+ w_0`` at pixel-channel 0);
    ``partials[i]`` (where not a null array): the SSIM's partial derivatives, 3 (``both`` False:
    enough for the gradient of ``a``) or 4. Launched over whole CUDA blocks of :data:`BLOCK`
    threads: threads ``>= n`` add nothing."""
    vec5 = wp.types.vector(5, scalar)
    vecK = wp.types.vector(4 if both else 3, scalar)
    ssim_pixel = ssim_funcs(scalar)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def ssim_cols(moments: wp.array(dtype=vec5), a: wp.array4d(dtype=scalar), b: wp.array4d(dtype=scalar),
                  window: wp.array(dtype=scalar), partials: wp.array(dtype=vecK), loss: wp.array(dtype=wp.float64),
                  n: int, w_l1: wp.float64, w_ssim: wp.float64, w_0: wp.float64, first: int):
        i = wp.tid() + first
        e = wp.float64(0.0)
        if i < n:
            H = a.shape[1]
            W = a.shape[2]
            C = a.shape[3]
            v, y, x, c = unflatten(i, H, W, C)
            stride = W * C
            base = i - y * stride
            m = vec5()
            for k in range(wp.static(2 * radius + 1)):
                m = m + window[k] * moments[base + reflect(y + k - radius, H) * stride]
            s, d = ssim_pixel(m)
            if partials.shape[0] > 0:
                if wp.static(both):
                    partials[i] = d
                else:
                    partials[i] = vecK(d[0], d[1], d[2])
            e = w_l1 * wp.float64(wp.abs(a[v, y, x, c] - b[v, y, x, c])) + w_ssim * wp.float64(s)
            if i == 0:
                e = e + w_0
        block_sum_add(e, loss)

    return ssim_cols


@functools.lru_cache(maxsize=None)
def adjoint_funcs(scalar, radius: int, K: int):
    """``adjoint_gather(f, window, base, stride, q, n) -> vecK``: the adjoint of the reflected blur
    along one axis at pixel ``q`` of a line of ``n`` (element ``p`` of the line at ``f[base + p
    stride]``): the sum over padded positions ``j`` that read ``q`` of ``sum_p f[p] window[j - p +
    radius]`` over the outputs ``p`` whose window holds ``j``."""
    vecK = wp.types.vector(K, scalar)

    @wp.func
    def taps(f: wp.array(dtype=vecK), window: wp.array(dtype=scalar), base: int, stride: int, j: int, n: int):
        out = vecK()
        for p in range(wp.max(0, j - radius), wp.min(n - 1, j + radius) + 1):
            out = out + window[j - p + radius] * f[base + p * stride]
        return out

    @wp.func
    def adjoint_gather(f: wp.array(dtype=vecK), window: wp.array(dtype=scalar), base: int, stride: int, q: int,
                       n: int):
        out = vecK()
        if q > radius and q < n - 1 - radius:  # inside: only j = q reads q, and every output around it is there
            for k in range(wp.static(2 * radius + 1)):
                out = out + window[k] * f[base + (q + radius - k) * stride]
            return out
        if n == 1:  # every padded position reads the one pixel
            for j in range(-radius, radius + 1):
                out = out + taps(f, window, base, stride, j, n)
            return out
        period = 2 * (n - 1)
        reach = (n + 2 * radius) // period + 1
        for m in range(-reach, reach + 1):
            j = q + m * period
            if j >= -radius and j <= n - 1 + radius:
                out = out + taps(f, window, base, stride, j, n)
            if q != 0 and q != n - 1:  # (at the two ends, -q is the same class as q)
                j = m * period - q
                if j >= -radius and j <= n - 1 + radius:
                    out = out + taps(f, window, base, stride, j, n)
        return out

    return adjoint_gather


@functools.lru_cache(maxsize=None)
def cols_adjoint_kernel(scalar, radius: int, both: bool):
    """``ssim_cols_adjoint(partials, window, out, H, W, C, first)``: the per-pixel partials through the
    adjoint of the column blur."""
    K = 4 if both else 3
    vecK = wp.types.vector(K, scalar)
    adjoint_gather = adjoint_funcs(scalar, radius, K)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def ssim_cols_adjoint(partials: wp.array(dtype=vecK), window: wp.array(dtype=scalar), out: wp.array(dtype=vecK),
                          H: int, W: int, C: int, first: int):
        i = wp.tid() + first
        v, y, x, c = unflatten(i, H, W, C)
        stride = W * C
        out[i] = adjoint_gather(partials, window, i - y * stride, stride, y, H)

    return ssim_cols_adjoint


@functools.lru_cache(maxsize=None)
def rows_adjoint_kernel(scalar, radius: int, both: bool):
    """``ssim_rows_adjoint(t, window, a, b, grad_out, grad_a, grad_b, g_ssim, g_l1, first)``: the
    column-adjoint partials through the adjoint of the row blur, then the gradients (module
    docstring): ``grad_a[i]`` and, with ``both``, ``grad_b[i]`` (flat, contiguous; a null array is
    skipped), times ``grad_out[0]``."""
    K = 4 if both else 3
    vecK = wp.types.vector(K, scalar)
    adjoint_gather = adjoint_funcs(scalar, radius, K)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def ssim_rows_adjoint(t: wp.array(dtype=vecK), window: wp.array(dtype=scalar), a: wp.array4d(dtype=scalar),
                          b: wp.array4d(dtype=scalar), grad_out: wp.array(dtype=scalar),
                          grad_a: wp.array(dtype=scalar), grad_b: wp.array(dtype=scalar), g_ssim: scalar,
                          g_l1: scalar, first: int):
        i = wp.tid() + first
        W = a.shape[2]
        C = a.shape[3]
        v, y, x, c = unflatten(i, a.shape[1], W, C)
        T = adjoint_gather(t, window, i - x * C, C, x, W)
        p = a[v, y, x, c] - scalar(SHIFT)
        q = b[v, y, x, c] - scalar(SHIFT)
        zero = scalar(0.0)
        sign = wp.where(p > q, scalar(1.0), wp.where(p < q, scalar(-1.0), zero))  # (torch's: 0 at 0)
        go = grad_out[0]
        two = scalar(2.0)
        if grad_a.shape[0] > 0:
            grad_a[i] = go * (g_ssim * (T[0] + two * p * T[1] + q * T[2]) + g_l1 * sign)
        if wp.static(both):
            if grad_b.shape[0] > 0:
                grad_b[i] = go * (g_ssim * (T[3] + two * q * T[1] + p * T[2]) - g_l1 * sign)

    return ssim_rows_adjoint
