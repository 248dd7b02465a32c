"""Spherical-harmonics colour (degrees 0..3, the 3DGS real basis).

``sh_eval`` sums ``basis_k(normalize(dir)) * coeffs[k]`` (one ``@wp.func``, used by both
kernels): :func:`sh_kernel` evaluates it for given directions; :func:`colour_kernel` is the
rasterizer's colour step, one thread per (camera, Gaussian): the direction from the camera
centre to the Gaussian, the SH sum, ``+ 0.5`` clamped at 0, and 0 for Gaussians the projection
culled (gsplat's rule). Both are differentiable by Warp's generated adjoint (with respect to the
coefficients and the directions, or the means and camera centres). Inputs are read through 2-D
``[camera, Gaussian]`` arrays (stride 0 over what is shared), so the adjoint writes one slot per
pair (see :mod:`.projection`). :func:`centres_kernel` gives the camera centres the directions
start from.
"""

import functools

import warp as wp

from .types import types_for

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C20, C21, C22, C23, C24 = 1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396
C30, C31, C32, C33, C34, C35, C36 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                                     -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


@functools.lru_cache(maxsize=None)
def sh_eval_func(scalar, degree: int):
    """``sh_eval(d, coeffs, c, n)``: the SH colour for direction ``d`` (any length) from the
    coefficients ``coeffs[c, n, :]`` of a ``[C, N, K]`` array."""
    vec3 = types_for(scalar).vec3

    @wp.func
    def sh_eval(d: vec3, coeffs: wp.array3d(dtype=vec3), c: int, n: int):
        u = d / wp.max(wp.length(d), scalar(1e-30))
        x = u[0]
        y = u[1]
        z = u[2]
        out = scalar(C0) * coeffs[c, n, 0]
        if wp.static(degree >= 1):
            out = (out - scalar(C1) * y * coeffs[c, n, 1] + scalar(C1) * z * coeffs[c, n, 2]
                   - scalar(C1) * x * coeffs[c, n, 3])
        if wp.static(degree >= 2):
            xx = x * x
            yy = y * y
            zz = z * z
            out = (out + scalar(C20) * x * y * coeffs[c, n, 4] + scalar(C21) * y * z * coeffs[c, n, 5]
                   + scalar(C22) * (scalar(2.0) * zz - xx - yy) * coeffs[c, n, 6]
                   + scalar(C23) * x * z * coeffs[c, n, 7] + scalar(C24) * (xx - yy) * coeffs[c, n, 8])
            if wp.static(degree >= 3):
                out = (out + scalar(C30) * y * (scalar(3.0) * xx - yy) * coeffs[c, n, 9]
                       + scalar(C31) * x * y * z * coeffs[c, n, 10]
                       + scalar(C32) * y * (scalar(4.0) * zz - xx - yy) * coeffs[c, n, 11]
                       + scalar(C33) * z * (scalar(2.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy) * coeffs[c, n, 12]
                       + scalar(C34) * x * (scalar(4.0) * zz - xx - yy) * coeffs[c, n, 13]
                       + scalar(C35) * z * (xx - yy) * coeffs[c, n, 14]
                       + scalar(C36) * x * (xx - scalar(3.0) * yy) * coeffs[c, n, 15])
        return out

    return sh_eval


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
