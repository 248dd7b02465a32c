"""Spherical-harmonics colour (degrees 0..3, the 3DGS real basis).

``sh_eval`` sums ``basis_k(normalize(dir)) * coeffs[k]`` (one ``@wp.func``, used by both
kernels): :func:`sh_kernel` evaluates it for given directions; :func:`colour_kernel` is the
rasterizer's colour step, one thread per (camera, Gaussian): the direction from the camera
centre to the Gaussian, the SH sum, ``+ 0.5`` clamped at 0, and 0 for Gaussians the projection
culled (gsplat's rule). :func:`sh_kernel` is differentiated by Warp's generated adjoint;
:func:`colour_kernel` by it too, except for coefficients shared by several cameras: the
hand-written :func:`colour_backward_kernel` (one thread per Gaussian over the cameras, no
per-camera copies of the coefficients' gradient). Inputs are read through 2-D
``[camera, Gaussian]`` arrays (stride 0 over what is shared). :func:`centres_kernel` gives the
camera centres the directions start from.
"""

import functools

import warp as wp

from .types import types_for

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C20, C21, C22, C23, C24 = 1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396
C30, C31, C32, C33, C34, C35, C36 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                                     -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def n_coeffs(degree: int) -> int:
    """Coefficients per channel of an SH expansion of ``degree``: ``(degree + 1)^2``."""
    return (degree + 1) ** 2


@functools.lru_cache(maxsize=None)
def sh_basis_funcs(scalar, degree: int):
    """``(sh_basis, sh_basis_vjp)``: the real SH basis at a unit direction ``u`` as a vector of
    :func:`n_coeffs` values, and ``sum_k w_k d basis_k / d u`` for weights ``w`` (what the colour's
    gradient gives the direction). Written once: the forward's sum and the hand-written backward
    both use them."""
    vec3 = types_for(scalar).vec3
    K = n_coeffs(degree)
    vecK = wp.types.vector(K, scalar)

    @wp.func
    def sh_basis(u: vec3):
        x = u[0]
        y = u[1]
        z = u[2]
        b = vecK()
        b[0] = scalar(C0)
        if wp.static(degree >= 1):
            b[1] = -(scalar(C1) * y)
            b[2] = scalar(C1) * z
            b[3] = -(scalar(C1) * x)
        if wp.static(degree >= 2):
            xx = x * x
            yy = y * y
            zz = z * z
            b[4] = scalar(C20) * x * y
            b[5] = scalar(C21) * y * z
            b[6] = scalar(C22) * (scalar(2.0) * zz - xx - yy)
            b[7] = scalar(C23) * x * z
            b[8] = scalar(C24) * (xx - yy)
            if wp.static(degree >= 3):
                b[9] = scalar(C30) * y * (scalar(3.0) * xx - yy)
                b[10] = scalar(C31) * x * y * z
                b[11] = scalar(C32) * y * (scalar(4.0) * zz - xx - yy)
                b[12] = scalar(C33) * z * (scalar(2.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy)
                b[13] = scalar(C34) * x * (scalar(4.0) * zz - xx - yy)
                b[14] = scalar(C35) * z * (xx - yy)
                b[15] = scalar(C36) * x * (xx - scalar(3.0) * yy)
        return b

    # the derivatives' constant factors (Python floats: Warp reads them as constants of the precision)
    C22x2 = 2.0 * C22
    C24x2 = 2.0 * C24
    C32x2 = 2.0 * C32
    C34x2 = 2.0 * C34
    C35x2 = 2.0 * C35
    C30x3 = 3.0 * C30
    C33x3 = 3.0 * C33
    C36x3 = 3.0 * C36
    C22x4 = 4.0 * C22
    C30x6 = 6.0 * C30
    C33x6 = 6.0 * C33
    C36x6 = 6.0 * C36
    C32x8 = 8.0 * C32
    C34x8 = 8.0 * C34

    @wp.func
    def sh_basis_vjp(u: vec3, w: vecK):
        x = u[0]
        y = u[1]
        z = u[2]
        gx = scalar(0.0)
        gy = scalar(0.0)
        gz = scalar(0.0)
        if wp.static(degree >= 1):
            gx = gx - scalar(C1) * w[3]
            gy = gy - scalar(C1) * w[1]
            gz = gz + scalar(C1) * w[2]
        if wp.static(degree >= 2):
            gx = gx + scalar(C20) * y * w[4] - scalar(C22x2) * x * w[6] + scalar(C23) * z * w[7] \
                + scalar(C24x2) * x * w[8]
            gy = gy + scalar(C20) * x * w[4] + scalar(C21) * z * w[5] - scalar(C22x2) * y * w[6] \
                - scalar(C24x2) * y * w[8]
            gz = gz + scalar(C21) * y * w[5] + scalar(C22x4) * z * w[6] + scalar(C23) * x * w[7]
            if wp.static(degree >= 3):
                xx = x * x
                yy = y * y
                zz = z * z
                gx = (gx + scalar(C30x6) * x * y * w[9] + scalar(C31) * y * z * w[10]
                      - scalar(C32x2) * x * y * w[11] - scalar(C33x6) * x * z * w[12]
                      + scalar(C34) * (scalar(4.0) * zz - scalar(3.0) * xx - yy) * w[13]
                      + scalar(C35x2) * x * z * w[14] + scalar(C36x3) * (xx - yy) * w[15])
                gy = (gy + scalar(C30x3) * (xx - yy) * w[9] + scalar(C31) * x * z * w[10]
                      + scalar(C32) * (scalar(4.0) * zz - xx - scalar(3.0) * yy) * w[11]
                      - scalar(C33x6) * y * z * w[12] - scalar(C34x2) * x * y * w[13]
                      - scalar(C35x2) * y * z * w[14] - scalar(C36x6) * x * y * w[15])
                gz = (gz + scalar(C31) * x * y * w[10] + scalar(C32x8) * y * z * w[11]
                      + scalar(C33x3) * (scalar(2.0) * zz - xx - yy) * w[12]
                      + scalar(C34x8) * x * z * w[13] + scalar(C35) * (xx - yy) * w[14])
        return vec3(gx, gy, gz)

    return sh_basis, sh_basis_vjp


@functools.lru_cache(maxsize=None)
def sh_eval_func(scalar, degree: int):
    """``sh_eval(d, coeffs, c, n)``: the SH colour for direction ``d`` (any length) from the
    coefficients ``coeffs[c, n, :]`` of a ``[C, N, K]`` array (the basis of :func:`sh_basis_funcs`,
    summed from the lowest band up)."""
    vec3 = types_for(scalar).vec3
    sh_basis, _ = sh_basis_funcs(scalar, degree)
    sh_sum = sh_sum_func(scalar, degree)

    @wp.func
    def sh_eval(d: vec3, coeffs: wp.array3d(dtype=vec3), c: int, n: int):
        u = d / wp.max(wp.length(d), scalar(1e-30))
        return sh_sum(sh_basis(u), coeffs, c, n)

    return sh_eval


@functools.lru_cache(maxsize=None)
def sh_sum_func(scalar, degree: int):
    """``sh_sum(b, coeffs, c, n)``: ``sum_k b_k coeffs[c, n, k]`` from the lowest band up (the
    colour before the ``+ 0.5``; the forward and the hand-written backward round it alike)."""
    vec3 = types_for(scalar).vec3
    K = n_coeffs(degree)
    vecK = wp.types.vector(K, scalar)

    @wp.func
    def sh_sum(b: vecK, coeffs: wp.array3d(dtype=vec3), c: int, n: int):
        out = b[0] * coeffs[c, n, 0]
        for k in range(1, wp.static(K)):
            out = out + b[k] * coeffs[c, n, k]
        return out

    return sh_sum


@functools.lru_cache(maxsize=None)
def sh_kernel(scalar, degree: int):
    """``eval_sh(dirs [1, M], coeffs [1, M, K], colors [M])``: plain SH evaluation."""
    vec3 = types_for(scalar).vec3
    sh_eval = sh_eval_func(scalar, degree)

    @wp.kernel(module="unique")
    def eval_sh(dirs: wp.array2d(dtype=vec3), coeffs: wp.array3d(dtype=vec3), colors: wp.array(dtype=vec3)):
        c, n = wp.tid()
        colors[n] = sh_eval(dirs[c, n], coeffs, c, n)

    return eval_sh


@functools.lru_cache(maxsize=None)
def colour_kernel(scalar, degree: int):
    """``sh_colour(means [C, N], campos [C, N], coeffs [C, N, K], radii [C*N], colors [C*N])``,
    launched over ``(C, N)``: ``max(sh(means - campos) + 0.5, 0)``, 0 where culled (radii 0).
    ``first``: the Gaussian of the launch's first thread (as the projection's: runs of Gaussians
    side by side on the CPU's cores; 0 for one launch over all)."""
    vec3 = types_for(scalar).vec3
    sh_eval = sh_eval_func(scalar, degree)

    @wp.kernel(module="unique")
    def sh_colour(means: wp.array2d(dtype=vec3), campos: wp.array2d(dtype=vec3), coeffs: wp.array3d(dtype=vec3),
                  radii: wp.array(dtype=wp.vec2i), colors: wp.array(dtype=vec3), first: int):
        c, t = wp.tid()
        n = t + first
        i = c * means.shape[1] + n
        r = radii[i]
        if r[0] <= 0 or r[1] <= 0:
            colors[i] = vec3()
            return
        v = sh_eval(means[c, n] - campos[c, n], coeffs, c, n) + vec3(scalar(0.5), scalar(0.5), scalar(0.5))
        zero = scalar(0.0)
        # the clamp as torch's clamp_min(0) differentiates it: the gradient passes where v >= 0
        colors[i] = vec3(wp.where(v[0] >= zero, v[0], zero), wp.where(v[1] >= zero, v[1], zero),
                         wp.where(v[2] >= zero, v[2], zero))

    return sh_colour


@functools.lru_cache(maxsize=None)
def colour_backward_kernel(scalar, degree: int):
    """A hand-written backward of :func:`colour_kernel` for coefficients shared by several cameras:
    one thread per Gaussian looping over the cameras, the coefficients' gradient summed there in a
    fixed order and stored once (``v_coeffs[0, n]``; Warp's generated adjoint needs a per-camera
    copy, zero-filled, and a sum after it: 0.38 against 1.06 ms for 300,000 Gaussians in 4 cameras
    on an H100; with one camera the adjoint is the faster, 0.21 against 0.22 ms at 200,000,
    docs/notes/benchmarks-history.md). Also ``v_means [C, N]`` (added to: the projection's backward adds its
    own terms to the same slots) and ``v_campos [C, N]`` (stored). The gradient passes the clamp
    where the colour before it is ``>= 0`` (as the forward's ``where`` passes it) and is 0 for
    culled Gaussians; absent outputs come as null arrays. ``first``: as in :func:`colour_kernel`.
    Only the first :func:`n_coeffs` coefficients are written."""
    t = types_for(scalar)
    vec3 = t.vec3
    K = n_coeffs(degree)
    vecK = wp.types.vector(K, scalar)
    matK3 = wp.types.matrix(shape=(K, 3), dtype=scalar)
    sh_basis, sh_basis_vjp = sh_basis_funcs(scalar, degree)
    sh_sum = sh_sum_func(scalar, degree)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def sh_colour_backward(means: wp.array2d(dtype=vec3), campos: wp.array2d(dtype=vec3),
                           coeffs: wp.array3d(dtype=vec3), radii: wp.array(dtype=wp.vec2i),
                           v_colors: wp.array(dtype=vec3), v_means: wp.array2d(dtype=vec3),
                           v_campos: wp.array2d(dtype=vec3), v_coeffs: wp.array3d(dtype=vec3), first: int):
        n = wp.tid() + first
        C = means.shape[0]
        N = means.shape[1]
        zero = scalar(0.0)
        acc = matK3()
        for c in range(C):
            i = c * N + n
            r = radii[i]
            if r[0] <= 0 or r[1] <= 0:  # culled: no colour, no gradient
                if v_campos.shape[0] > 0:
                    v_campos[c, n] = vec3()
                continue
            d = means[c, n] - campos[c, n]
            length = wp.length(d)
            u = d / wp.max(length, scalar(1e-30))  # (as the forward rounds it)
            inv = scalar(1.0) / wp.max(length, scalar(1e-30))
            b = sh_basis(u)
            v = sh_sum(b, coeffs, c, n)
            g = v_colors[i]
            half = scalar(0.5)
            g = vec3(wp.where(v[0] + half >= zero, g[0], zero), wp.where(v[1] + half >= zero, g[1], zero),
                     wp.where(v[2] + half >= zero, g[2], zero))
            if v_coeffs.shape[0] > 0:
                for k in range(wp.static(K)):
                    acc[k] = acc[k] + b[k] * g
            if v_means.shape[0] > 0 or v_campos.shape[0] > 0:
                w = vecK()
                for k in range(wp.static(K)):
                    w[k] = wp.dot(coeffs[c, n, k], g)
                v_u = sh_basis_vjp(u, w)
                # through u = d / max(|d|, 1e-30): the part of v_u across u, over the length
                v_d = v_u * inv
                if length > scalar(1e-30):
                    v_d = (v_u - u * wp.dot(u, v_u)) * inv
                if v_means.shape[0] > 0:
                    v_means[c, n] = v_means[c, n] + v_d
                if v_campos.shape[0] > 0:
                    v_campos[c, n] = -v_d
        if v_coeffs.shape[0] > 0:
            for k in range(wp.static(K)):
                v_coeffs[0, n, k] = acc[k]

    return sh_colour_backward


@functools.lru_cache(maxsize=None)
def centres_kernel(scalar):
    """``camera_centres(viewmats [C], centres [C])``: each camera's centre in world space, the
    translation column of the inverse world-to-camera matrix (one thread per camera; not
    differentiated: a caller that needs gradients with respect to the view matrices inverts them
    in torch)."""
    t = types_for(scalar)
    vec3, mat44 = t.vec3, t.mat44

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def camera_centres(viewmats: wp.array(dtype=mat44), centres: wp.array(dtype=vec3)):
        c = wp.tid()
        inv = wp.inverse(viewmats[c])
        centres[c] = vec3(inv[0, 3], inv[1, 3], inv[2, 3])

    return camera_centres
