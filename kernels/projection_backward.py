"""Projection backward, written by hand: one thread per (camera, Gaussian).

The chain rule of :mod:`.projection`'s forward, from the gradients of its outputs (screen
mean, depth, conic, opacity) to the Gaussian's mean, quaternion, scales and opacity and to the
view matrix. Each thread recomputes what it needs of the forward (camera point, rotation,
Jacobian, 2D covariance), with the forward's own ``wp.func``s, so every intermediate value is
the forward's to the bit, and nothing else: no input checks, tile counts or culling tests (a
Gaussian the forward culled has zero radii and gets no gradient). Warp's generated adjoint of
the forward kernel computes the same derivatives (the tests hold this kernel to it) but replays
the whole forward first and keeps every intermediate: 0.215 against 0.088 ms at 1M Gaussians
on an H100 (gsplat's hand-written one: 0.143; docs/notes/benchmarks-history.md).

The 2D covariance's entries ``c00, c10, c01, c11`` (``c = J Sc J^T``) are blurred into ``a =
c00 + eps2d``, ``cc = c11 + eps2d``, ``det = a cc - c10 c01``, ``conic = (cc, -c10, a) / det``;
each of those steps is differentiated as written (the determinant's cancellation included),
then::

    cov = J Sc J^T:  v_Sc = J^T v_cov J,   v_J = v_cov J Sc^T + v_cov^T J Sc
    Sc = R Sigma R^T: v_Sigma = R^T v_Sc R, v_R += v_Sc R Sigma^T + v_Sc^T R Sigma
    Sigma = M M^T:   v_M = (v_Sigma + v_Sigma^T) M;  M = R_q diag(s): v_s, v_R_q, then the quaternion
    p = R m + t:     v_m = R^T v_p,     v_R += v_p m^T,  v_t = v_p

(the ``"factor"`` covariance form goes through the rows ``r0, r1`` of ``A = J R M``, its
determinant ``|r0 x r1|^2`` differentiated through the cross product, free of cancellation).
The antialiasing factor ``sqrt(det_orig / det)`` adds its terms to both determinants. The
Jacobian's x/y clamp at 1.3x the field of view passes no gradient to the camera point where it
clamps, as in the forward's maths. Every output slot belongs to one (camera, Gaussian) pair and
is added to (the SH colour backward may have written the means' slots already), so the
gradients are deterministic.
"""

import functools

import warp as wp

from .projection import activation_funcs, covariance_funcs, matrix_funcs, projection_funcs, projection_params
from .types import types_for


@functools.lru_cache(maxsize=None)
def quat_backward_func(scalar):
    """``quat_backward(q, G) -> v_q``: the gradient to a (not necessarily unit) quaternion
    ``q = (w, x, y, z)`` of ``G``, the gradient of the rotation matrix of ``q / |q|``
    (``projection.matrix_funcs``' ``quat_to_rotmat``)."""
    t = types_for(scalar)
    vec4, mat33 = t.vec4, t.mat33

    @wp.func
    def quat_backward(q: vec4, G: mat33):
        inv = scalar(1.0) / wp.sqrt(wp.dot(q, q))
        w = q[0] * inv
        x = q[1] * inv
        y = q[2] * inv
        z = q[3] * inv
        two = scalar(2.0)
        vw = two * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
        vx = two * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - two * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
                    + w * G[2, 1] - two * x * G[2, 2])
        vy = two * (-two * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
                    + z * G[2, 1] - two * y * G[2, 2])
        vz = two * (-two * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - two * z * G[1, 1]
                    + y * G[1, 2] + x * G[2, 0] + y * G[2, 1])
        vn = vec4(vw, vx, vy, vz)
        qn = vec4(w, x, y, z)
        # through the normalisation: the part of the gradient along q is lost
        return (vn - qn * wp.dot(qn, vn)) * inv

    return quat_backward


@functools.lru_cache(maxsize=None)
def covariance_backward_func(scalar, covariance: str, native_rsqrt: bool = False):
    """``covariance_backward(J, R, M, eps2d, antialiased, o, g_con, g_op) -> (v_J, v_R, v_M, v_o)``:
    the 2D covariance recomputed with the forward's own functions (``covariance``: ``"gsplat"``,
    ``J (R M M^T R^T) J^T`` with the determinant as ``ad - bc``; ``"factor"``, from ``A = J R M``
    with the determinant by Binet-Cauchy), so every value, rounding included, is the forward's,
    then the gradients of the conic ``(cc, -b, a) / det`` (``g_con``) and of the opacity (``g_op``,
    through the antialiasing factor ``sqrt(det_orig / det)`` when ``antialiased``) back to the
    Jacobian ``J``, the camera rotation ``R``, the scaled rotation ``M`` and the input opacity
    ``o``."""
    t = types_for(scalar)
    vec3, mat22, mat33, mat23 = t.vec3, t.mat22, t.mat33, t.mat23
    FACTOR = covariance == "factor"
    cf = covariance_funcs(scalar, native_rsqrt)
    mf = matrix_funcs(scalar, native_rsqrt)
    cov_camera, blur_gsplat, factor_rows, blur_factor = cf.cov_camera, cf.blur_gsplat, cf.factor_rows, cf.blur_factor
    cov2d, mul33_t = mf.cov2d, mf.mul33_t

    @wp.func
    def covariance_backward(J: mat23, R: mat33, M: mat33, eps2d: scalar, antialiased: int, o: scalar, g_con: vec3,
                            g_op: scalar):
        zero = scalar(0.0)
        one = scalar(1.0)
        two = scalar(2.0)
        r0 = vec3()
        r1 = vec3()
        Sc = mat33()
        c00 = zero
        c10 = zero
        c01 = zero
        c11 = zero
        a = zero
        cc = zero
        det_orig = zero
        det = zero
        if wp.static(FACTOR):
            r0, r1 = factor_rows(J, R, M)
            a, c10, cc, det_orig, det = blur_factor(r0, r1, eps2d)
        else:
            Sc = cov_camera(R, M)
            cv = cov2d(J, Sc)
            a, c10, cc, det_orig, det = blur_gsplat(cv, eps2d)
            c00 = cv[0]
            c01 = cv[2]
            c11 = cv[3]

        # conic = (cc, -b, a) / det
        inv_det = one / det
        v_a = g_con[2] * inv_det
        v_cc = g_con[0] * inv_det
        v_b = -g_con[1] * inv_det
        v_det = -(g_con[0] * cc - g_con[1] * c10 + g_con[2] * a) * inv_det * inv_det
        v_do = zero
        v_o = g_op
        if antialiased != 0:  # op = o sqrt(det_orig / det)
            ratio = det_orig / det
            v_o = zero
            if ratio > zero:
                f = wp.sqrt(ratio)
                v_o = g_op * f
                v_ratio = g_op * o * scalar(0.5) / f
                v_do = v_ratio / det
                v_det -= v_ratio * ratio / det

        v_R = mat33()
        v_M = mat33()
        v_J = mat23()
        if wp.static(FACTOR):
            RM = R @ M
            v_D = v_det + v_do  # det = det_orig + eps2d (c00 + c11) + eps2d^2, det_orig = |r0 x r1|^2
            v_c00 = v_a + v_det * eps2d
            v_c11 = v_cc + v_det * eps2d
            v_cr = two * v_D * wp.cross(r0, r1)
            v_r0 = wp.cross(r1, v_cr) + two * v_c00 * r0 + v_b * r1
            v_r1 = wp.cross(v_cr, r0) + two * v_c11 * r1 + v_b * r0
            v_A = mat23(v_r0[0], v_r0[1], v_r0[2], v_r1[0], v_r1[1], v_r1[2])
            v_J = v_A @ wp.transpose(RM)
            v_RM = wp.transpose(J) @ v_A
            v_R = v_RM @ wp.transpose(M)
            v_M = wp.transpose(R) @ v_RM
        else:
            v_cov = mat22(v_a + v_det * cc + v_do * c11, -(v_det + v_do) * c10,
                          v_b - (v_det + v_do) * c01, v_cc + v_det * a + v_do * c00)
            Sigma = mul33_t(M, M)
            v_Sc = wp.transpose(J) @ v_cov @ J
            v_J = v_cov @ J @ wp.transpose(Sc) + wp.transpose(v_cov) @ J @ Sc
            v_R = v_Sc @ R @ wp.transpose(Sigma) + wp.transpose(v_Sc) @ R @ Sigma
            v_Sigma = wp.transpose(R) @ v_Sc @ R
            v_M = (v_Sigma + wp.transpose(v_Sigma)) @ M
        return v_J, v_R, v_M, v_o

    return covariance_backward


@functools.lru_cache(maxsize=None)
def point_backward_func(scalar, native_rsqrt: bool = False):
    """``point_backward(p, K, w, h, g_xy, g_z, v_J) -> v_p``: the gradient to the camera point ``p``
    of the screen mean (``g_xy``), the depth (``g_z``) and the entries of the forward's Jacobian
    (``v_J``; where its x/y clamp is active, none through the clamped coordinate)."""
    t = types_for(scalar)
    vec2, vec3, mat33, mat23 = t.vec2, t.vec3, t.mat33, t.mat23
    fov_limits = projection_funcs(scalar, native_rsqrt).fov_limits

    @wp.func
    def point_backward(p: vec3, K: mat33, w: scalar, h: scalar, g_xy: vec2, g_z: scalar, v_J: mat23):
        fx = K[0, 0]
        fy = K[1, 1]
        lim = fov_limits(fx, fy, K[0, 2], K[1, 2], w, h)
        z = p[2]
        rz = scalar(1.0) / z
        rz2 = rz * rz
        two = scalar(2.0)
        ux = p[0] * rz
        uy = p[1] * rz
        kx = wp.min(lim[0], wp.max(-lim[1], ux))
        ky = wp.min(lim[2], wp.max(-lim[3], uy))
        tx = z * kx
        ty = z * ky
        # screen mean (fx x / z + cx, fy y / z + cy) and depth z
        v_p = vec3(g_xy[0] * fx * rz, g_xy[1] * fy * rz, g_z)
        v_rz = g_xy[0] * fx * p[0] + g_xy[1] * fy * p[1]
        # J = [[fx rz, 0, -fx tx rz^2], [0, fy rz, -fy ty rz^2]], tx = z clamp(x rz)
        v_rz += fx * v_J[0, 0] + fy * v_J[1, 1] - two * fx * tx * rz * v_J[0, 2] - two * fy * ty * rz * v_J[1, 2]
        v_tx = -fx * rz2 * v_J[0, 2]
        v_ty = -fy * rz2 * v_J[1, 2]
        if ux > -lim[1] and ux < lim[0]:  # (clamped: no gradient to the point through it)
            v_p[0] += v_tx * z * rz
            v_rz += v_tx * z * p[0]
        if uy > -lim[3] and uy < lim[2]:
            v_p[1] += v_ty * z * rz
            v_rz += v_ty * z * p[1]
        v_p[2] += v_tx * kx + v_ty * ky - v_rz * rz2
        return v_p

    return point_backward


@functools.lru_cache(maxsize=None)
def zero_slots_func(scalar):
    """``zero_slots(c, n, v_means, v_quats, v_scales, v_opacities, v_viewmats)``: zeros in the
    (camera, Gaussian) slot of each present gradient (a culled Gaussian's, when nothing cleared them)."""
    t = types_for(scalar)
    vec3, vec4, mat44 = t.vec3, t.vec4, t.mat44

    @wp.func
    def zero_slots(c: int, n: int, v_means: wp.array2d(dtype=vec3), v_quats: wp.array2d(dtype=vec4),
                   v_scales: wp.array2d(dtype=vec3), v_opacities: wp.array2d(dtype=scalar),
                   v_viewmats: wp.array2d(dtype=mat44)):
        if v_means.shape[0] > 0:
            v_means[c, n] = vec3()
        if v_quats.shape[0] > 0:
            v_quats[c, n] = vec4()
        if v_scales.shape[0] > 0:
            v_scales[c, n] = vec3()
        if v_opacities.shape[0] > 0:
            v_opacities[c, n] = scalar(0.0)
        if v_viewmats.shape[0] > 0:
            v_viewmats[c, n] = mat44()

    return zero_slots


@functools.lru_cache(maxsize=None)
def projection_backward_kernel(scalar, covariance: str = "gsplat", fast_math: bool = False,
                               activations: bool = False):
    """The projection backward for one precision, launched over ``(C, N)`` (or a run of
    Gaussians, ``first``). Inputs as the forward kernel reads them (2-D ``[camera, Gaussian]``
    arrays), the forward's ``radii`` (flat ``[C * N]``), the outputs' gradients (flat, null
    arrays where none came). Outputs (each a null array when not wanted): the gradients of
    means, quaternions, scales, opacities and view matrices, one ``[camera, Gaussian]`` slot
    each: added to with ``accumulate`` (another kernel wrote there first: the SH colours'
    backward), else written, zeros for culled Gaussians included (no clearing first).
    ``activations``: as the forward's (``projection.activation_funcs``)."""
    t = types_for(scalar)
    vec2, vec3, vec4, mat33, mat44 = t.vec2, t.vec3, t.vec4, t.mat33, t.mat44
    native_rsqrt = fast_math and scalar == wp.float32
    fns = projection_funcs(scalar, native_rsqrt)
    camera_point, camera_rotation, jacobian, scale_columns = (fns.camera_point, fns.camera_rotation, fns.jacobian,
                                                              fns.scale_columns)
    quat_to_rotmat = matrix_funcs(scalar, native_rsqrt).quat_to_rotmat
    quat_backward = quat_backward_func(scalar)
    covariance_backward = covariance_backward_func(scalar, covariance, native_rsqrt)
    point_backward = point_backward_func(scalar, native_rsqrt)
    zero_slots = zero_slots_func(scalar)
    Params = projection_params(scalar)
    load_activated, through_exp, through_sigmoid = activation_funcs(scalar, activations)

    @wp.kernel(module="unique", module_options={"fast_math": fast_math, "enable_backward": False})
    def project_backward(
        means: wp.array2d(dtype=vec3),
        quats: wp.array2d(dtype=vec4),
        scales: wp.array2d(dtype=vec3),
        opacities: wp.array2d(dtype=scalar),
        viewmats: wp.array2d(dtype=mat44),
        Ks: wp.array(dtype=mat33),
        params: Params,
        radii: wp.array(dtype=wp.vec2i),
        v_means2d: wp.array(dtype=vec2),
        v_depths: wp.array(dtype=scalar),
        v_conics: wp.array(dtype=vec3),
        v_opac: wp.array(dtype=scalar),
        v_means: wp.array2d(dtype=vec3),
        v_quats: wp.array2d(dtype=vec4),
        v_scales: wp.array2d(dtype=vec3),
        v_opacities: wp.array2d(dtype=scalar),
        v_viewmats: wp.array2d(dtype=mat44),
        accumulate: int,
        first: int,
    ):
        c, tt = wp.tid()
        n = tt + first
        i = c * means.shape[1] + n
        r = radii[i]
        if r[0] == 0 and r[1] == 0:  # culled: no gradient
            if accumulate == 0:  # (slots not cleared: their zeros written here)
                zero_slots(c, n, v_means, v_quats, v_scales, v_opacities, v_viewmats)
            return
        zero = scalar(0.0)
        # the outputs' gradients (zero where none came)
        g_xy = vec2()
        if v_means2d.shape[0] > 0:
            g_xy = v_means2d[i]
        g_z = zero
        if v_depths.shape[0] > 0:
            g_z = v_depths[i]
        g_con = vec3()
        if v_conics.shape[0] > 0:
            g_con = v_conics[i]
        g_op = zero
        if v_opac.shape[0] > 0:
            g_op = v_opac[i]

        V = viewmats[c, n]
        m = means[c, n]
        R = camera_rotation(V)
        p = camera_point(V, m)
        K = Ks[c]
        w = scalar(params.width)
        h = scalar(params.height)
        J = jacobian(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, p, p[2], scalar(1.0) / p[2])
        q = quats[c, n]
        s, o = load_activated(scales[c, n], opacities[c, n])
        Rq = quat_to_rotmat(q)
        M = scale_columns(Rq, s)  # (the forward's scaled_rotation(q, s), its rotation kept)
        v_J, v_R, v_M, v_o = covariance_backward(J, R, M, params.eps2d, params.antialiased, o, g_con, g_op)
        v_p = point_backward(p, K, w, h, g_xy, g_z, v_J)

        if v_means.shape[0] > 0:
            gm = wp.transpose(R) @ v_p
            if accumulate != 0:
                gm = v_means[c, n] + gm
            v_means[c, n] = gm
        if v_viewmats.shape[0] > 0:  # p = R m + t
            v_R += wp.outer(v_p, m)
            gv = mat44(
                v_R[0, 0], v_R[0, 1], v_R[0, 2], v_p[0],
                v_R[1, 0], v_R[1, 1], v_R[1, 2], v_p[1],
                v_R[2, 0], v_R[2, 1], v_R[2, 2], v_p[2],
                zero, zero, zero, zero)
            if accumulate != 0:
                gv = v_viewmats[c, n] + gv
            v_viewmats[c, n] = gv
        if v_scales.shape[0] > 0:  # M = Rq diag(s)
            gs = vec3(
                v_M[0, 0] * Rq[0, 0] + v_M[1, 0] * Rq[1, 0] + v_M[2, 0] * Rq[2, 0],
                v_M[0, 1] * Rq[0, 1] + v_M[1, 1] * Rq[1, 1] + v_M[2, 1] * Rq[2, 1],
                v_M[0, 2] * Rq[0, 2] + v_M[1, 2] * Rq[1, 2] + v_M[2, 2] * Rq[2, 2])
            gs = through_exp(gs, s)
            if accumulate != 0:
                gs = v_scales[c, n] + gs
            v_scales[c, n] = gs
        if v_quats.shape[0] > 0:
            gq = quat_backward(q, scale_columns(v_M, s))
            if accumulate != 0:
                gq = v_quats[c, n] + gq
            v_quats[c, n] = gq
        if v_opacities.shape[0] > 0:
            go = through_sigmoid(v_o, o)
            if accumulate != 0:
                go = v_opacities[c, n] + go
            v_opacities[c, n] = go

    return project_backward
