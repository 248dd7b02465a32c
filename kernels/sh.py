"""Spherical-harmonics colour (degrees 0..3, the 3DGS real basis), one thread per (camera, Gaussian).

``colors[i] = sum_k basis_k(normalize(dirs[i])) * coeffs[i, k]``; the caller
adds 0.5 and clamps at 0. Differentiable by Warp's generated adjoint (with
respect to the coefficients and the directions).
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
def sh_kernel(scalar, degree: int):
    t = types_for(scalar)
    vec3 = t.vec3

    @wp.kernel(module="unique")
    def eval_sh(dirs: wp.array(dtype=vec3), coeffs: wp.array2d(dtype=vec3), colors: wp.array(dtype=vec3)):
        i = wp.tid()
        d = dirs[i]
        d = d / wp.max(wp.length(d), scalar(1e-30))
        x = d[0]
        y = d[1]
        z = d[2]
        out = scalar(C0) * coeffs[i, 0]
        if wp.static(degree >= 1):
            out = out - scalar(C1) * y * coeffs[i, 1] + scalar(C1) * z * coeffs[i, 2] - scalar(C1) * x * coeffs[i, 3]
        if wp.static(degree >= 2):
            xx = x * x
            yy = y * y
            zz = z * z
            out = (out + scalar(C20) * x * y * coeffs[i, 4] + scalar(C21) * y * z * coeffs[i, 5]
                   + scalar(C22) * (scalar(2.0) * zz - xx - yy) * coeffs[i, 6]
                   + scalar(C23) * x * z * coeffs[i, 7] + scalar(C24) * (xx - yy) * coeffs[i, 8])
            if wp.static(degree >= 3):
                out = (out + scalar(C30) * y * (scalar(3.0) * xx - yy) * coeffs[i, 9]
                       + scalar(C31) * x * y * z * coeffs[i, 10]
                       + scalar(C32) * y * (scalar(4.0) * zz - xx - yy) * coeffs[i, 11]
                       + scalar(C33) * z * (scalar(2.0) * zz - scalar(3.0) * xx - scalar(3.0) * yy) * coeffs[i, 12]
                       + scalar(C34) * x * (scalar(4.0) * zz - xx - yy) * coeffs[i, 13]
                       + scalar(C35) * z * (xx - yy) * coeffs[i, 14]
                       + scalar(C36) * x * (xx - scalar(3.0) * yy) * coeffs[i, 15])
        colors[i] = out

    return eval_sh
