"""Projection stage: world Gaussians → screen-space ellipses, one thread per (camera, Gaussian).

EWA splatting as in gsplat 1.5.3: covariance ``R S S R^T`` from the (normalised)
quaternion and scales, rotated into the camera, projected with the Jacobian of
the perspective map whose x/y are clamped at 1.3x the field of view. The 2D
covariance is formed from its factor ``A = J R_cam R_q S`` as ``A A^T``, its
determinant as ``|A_0 x A_1|^2``: the same values as gsplat's ``J Sigma J^T`` in
exact arithmetic, without its cancellation for very anisotropic Gaussians in
float32 (docs/numerics.md). ``eps2d``
is added to the 2D covariance; in antialiased mode the opacity is multiplied
by ``sqrt(det(cov) / det(cov + eps2d I))``. A Gaussian is culled (radii 0,
other outputs 0) when its depth is outside [near, far], the blurred
determinant is <= 0, its opacity is below ``alpha_min``, both radii are <=
``radius_clip``, or its extent box is off-screen.

The kernel is differentiable by Warp's generated adjoint. With
``expanded=True`` every per-Gaussian input and the view matrix are read at the
flat (camera, Gaussian) index, so the adjoint writes each (camera, Gaussian)
pair to its own slot: no atomics, bit-identical gradients.
"""

import functools

import warp as wp

from .types import types_for

RADIUS_LIMIT = 1073741824.0  # radii saturate here (2^30 px) so the int32 cast never overflows


@functools.lru_cache(maxsize=None)
def projection_kernel(scalar, expanded: bool = False):
    t = types_for(scalar)
    vec2, vec3, vec4, mat33, mat44, mat23 = t.vec2, t.vec3, t.vec4, t.mat33, t.mat44, t.mat23

    @wp.func
    def quat_to_rotmat(q: vec4):
        qn = q / wp.length(q)
        w = qn[0]
        x = qn[1]
        y = qn[2]
        z = qn[3]
        one = scalar(1.0)
        two = scalar(2.0)
        return mat33(
            one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
            two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
            two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
        )

    @wp.kernel(module="unique")
    def project(
        means: wp.array(dtype=vec3),
        quats: wp.array(dtype=vec4),
        scales: wp.array(dtype=vec3),
        opacities: wp.array(dtype=scalar),
        viewmats: wp.array(dtype=mat44),
        Ks: wp.array(dtype=mat33),
        n_gauss: int,
        width: int,
        height: int,
        near_plane: scalar,
        far_plane: scalar,
        eps2d: scalar,
        radius_clip: scalar,
        alpha_min: scalar,
        sigma_max: scalar,
        opacity_extent: int,
        antialiased: int,
        means2d: wp.array(dtype=vec2),
        depths: wp.array(dtype=scalar),
        conics: wp.array(dtype=vec3),
        opac_out: wp.array(dtype=scalar),
        radii: wp.array(dtype=wp.vec2i),
    ):
        c, n = wp.tid()
        i = c * n_gauss + n
        gi = n
        vi = c
        if wp.static(expanded):
            gi = i
            vi = i
        V = viewmats[vi]
        R = mat33(V[0, 0], V[0, 1], V[0, 2], V[1, 0], V[1, 1], V[1, 2], V[2, 0], V[2, 1], V[2, 2])
        tr = vec3(V[0, 3], V[1, 3], V[2, 3])
        p = R @ means[gi] + tr
        z = p[2]
        if z < near_plane or z > far_plane:
            return

        Rq = quat_to_rotmat(quats[gi])
        s = scales[gi]
        M = Rq @ wp.diag(s)

        K = Ks[c]
        fx = K[0, 0]
        fy = K[1, 1]
        cx = K[0, 2]
        cy = K[1, 2]
        w = scalar(width)
        h = scalar(height)
        tan_fovx = scalar(0.5) * w / fx
        tan_fovy = scalar(0.5) * h / fy
        lim_x_pos = (w - cx) / fx + scalar(0.3) * tan_fovx
        lim_x_neg = cx / fx + scalar(0.3) * tan_fovx
        lim_y_pos = (h - cy) / fy + scalar(0.3) * tan_fovy
        lim_y_neg = cy / fy + scalar(0.3) * tan_fovy
        rz = scalar(1.0) / z
        tx = z * wp.min(lim_x_pos, wp.max(-lim_x_neg, p[0] * rz))
        ty = z * wp.min(lim_y_pos, wp.max(-lim_y_neg, p[1] * rz))
        J = mat23(fx * rz, scalar(0.0), -fx * tx * rz * rz,
                  scalar(0.0), fy * rz, -fy * ty * rz * rz)
        # the 2D covariance from its 2x3 factor A = J R M: sums of squares, and its determinant as
        # the squared cross product of A's rows (Binet-Cauchy), free of cancellation
        A = J @ R @ M
        r0 = vec3(A[0, 0], A[0, 1], A[0, 2])
        r1 = vec3(A[1, 0], A[1, 1], A[1, 2])
        a = wp.dot(r0, r0)
        b = wp.dot(r0, r1)
        cc = wp.dot(r1, r1)
        cr = wp.cross(r0, r1)
        det_orig = wp.dot(cr, cr)
        det = det_orig + eps2d * (a + cc) + eps2d * eps2d
        a = a + eps2d
        cc = cc + eps2d
        if det <= scalar(0.0):
            return
        op = opacities[gi]
        if antialiased != 0:
            op = op * wp.sqrt(wp.max(scalar(0.0), det_orig / det))
        if op < alpha_min:
            return
        ext = sigma_max
        if opacity_extent != 0 and alpha_min > scalar(0.0):
            ext = wp.min(sigma_max, wp.sqrt(scalar(2.0) * wp.log(wp.max(op / alpha_min, scalar(1.0)))))
        rx = wp.min(wp.ceil(ext * wp.sqrt(a)), scalar(RADIUS_LIMIT))
        ry = wp.min(wp.ceil(ext * wp.sqrt(cc)), scalar(RADIUS_LIMIT))
        if rx <= radius_clip and ry <= radius_clip:
            return
        mx = fx * p[0] * rz + cx
        my = fy * p[1] * rz + cy
        if mx + rx <= scalar(0.0) or mx - rx >= w or my + ry <= scalar(0.0) or my - ry >= h:
            return
        means2d[i] = vec2(mx, my)
        depths[i] = z
        conics[i] = vec3(cc / det, -b / det, a / det)
        opac_out[i] = op
        radii[i] = wp.vec2i(int(rx), int(ry))

    return project
