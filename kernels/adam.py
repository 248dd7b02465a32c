"""Adam over every parameter group in one launch (``ssgwarp/raster/adam_ops.py``: :class:`WarpAdam`).

One thread per chunk of elements of all groups' parameters, laid end to end (a chunk is one element on CUDA).
A small table describes the groups: per group ``ROW`` int64 values, the addresses of its parameter, gradient,
first and second moments, the running end of its chunks and its element count; and, in the same memory read as
float32, the step's constants. A thread finds its group by a scan over the ends (a handful of groups), then
updates its elements with the
maths of ``torch.optim.Adam`` (L2 weight decay added to the gradient, bias corrections computed on the
host for the group's step count)::

    g = grad + wd p;  m = m + (1 - beta1) (g - m);  v = beta2 v + (1 - beta2) g^2
    p = p - step_size m / (sqrt(v) / bc2_sqrt + eps),  step_size = lr / (1 - beta1^t), bc2_sqrt = sqrt(1 - beta2^t)

``skip`` (one float, or empty): a step whose value is not 0 is skipped (a NaN/inf loss, as torch's fused
Adam's ``found_inf``).
"""

import functools

import warp as wp

ROW = 10         # int64 values per group: param, grad, exp_avg, exp_avg_sq addresses, the running end (in chunks),
END = 4          # the element count, then float32s
COUNT = 5
CONSTANTS = 12   # where the step's float32 constants start in the row read as 2 x ROW float32: step_size,
                 # 1 / bc2_sqrt, 1 - beta1, beta2, 1 - beta2, eps, weight decay


@wp.func
def group_of(ints: wp.array(dtype=wp.int64), groups: int, i: wp.int64):
    k = int(0)
    while k < groups - 1 and i >= ints[k * ROW + END]:
        k += 1
    return k


@wp.func
def adam_element(p: float, g: float, m: float, v: float, step_size: float, inv_bc2_sqrt: float, one_minus_beta1: float,
                 beta2: float, one_minus_beta2: float, eps: float):
    m_new = m + one_minus_beta1 * (g - m)
    v_new = v * beta2 + one_minus_beta2 * g * g
    denom = wp.sqrt(v_new) * inv_bc2_sqrt + eps
    return wp.vec3(p - step_size * (m_new / denom), m_new, v_new)


@functools.lru_cache(maxsize=None)
def adam_kernel():
    """``adam_groups(ints [G * ROW], floats [2 * G * ROW], groups, per_thread, skip [0 or 1])``, launched over
    the groups' chunks of ``per_thread`` elements (the ends in the table count chunks; a chunk never spans two
    groups): 1 on CUDA (neighbouring threads, neighbouring elements), hundreds on the CPU (the group's lookup
    and arrays made once per chunk)."""

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def adam_groups(ints: wp.array(dtype=wp.int64), floats: wp.array(dtype=wp.float32), groups: int,
                    per_thread: int, skip: wp.array(dtype=wp.float32)):
        i = wp.int64(wp.tid())
        if skip.shape[0] > 0:
            if skip[0] != 0.0:
                return
        k = group_of(ints, groups, i)
        start = wp.int64(0)
        if k > 0:
            start = ints[(k - 1) * ROW + END]
        row = k * ROW
        c = 2 * row + CONSTANTS
        n = int(ints[row + COUNT])
        j0 = int(i - start) * per_thread
        j1 = wp.min(j0 + per_thread, n)
        p = wp.array(ptr=wp.uint64(ints[row]), shape=(n,), dtype=wp.float32)
        gr = wp.array(ptr=wp.uint64(ints[row + 1]), shape=(n,), dtype=wp.float32)
        m = wp.array(ptr=wp.uint64(ints[row + 2]), shape=(n,), dtype=wp.float32)
        v = wp.array(ptr=wp.uint64(ints[row + 3]), shape=(n,), dtype=wp.float32)
        step_size, inv_bc2_sqrt, one_minus_beta1 = floats[c], floats[c + 1], floats[c + 2]
        beta2, one_minus_beta2, eps, wd = floats[c + 3], floats[c + 4], floats[c + 5], floats[c + 6]
        for j in range(j0, j1):
            g = gr[j]
            if wd != 0.0:
                g = g + wd * p[j]
            out = adam_element(p[j], g, m[j], v[j], step_size, inv_bc2_sqrt, one_minus_beta1, beta2,
                               one_minus_beta2, eps)
            p[j] = out[0]
            m[j] = out[1]
            v[j] = out[2]

    return adam_groups
