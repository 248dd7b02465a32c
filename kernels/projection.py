"""Projection stage: world Gaussians → screen-space ellipses, one thread per (camera, Gaussian).

EWA splatting as in gsplat 1.5.3: covariance ``R S S R^T`` from the (normalised)
quaternion and scales, rotated into the camera, projected with the Jacobian of
the perspective map whose x/y are clamped at 1.3x the field of view. Two ways to
form the 2D covariance (``RasterSettings.covariance``):

- ``"gsplat"`` (default): ``J (R_cam Sigma R_cam^T) J^T`` with ``Sigma = M M^T``,
  ``M = R_q S``, its determinant as ``ad - bc``: gsplat's arithmetic operation for
  operation (every matrix product summed in index order, zero terms included,
  reciprocal square root for the quaternion norm), so that with the same
  floating-point contraction and fast maths the projected Gaussians are the
  same numbers as gsplat's, and so are the images. It loses the 2D covariance
  of very anisotropic Gaussians in float32 (cancellation; docs/numerics.md).
- ``"factor"``: from the factor ``A = J R_cam R_q S`` as ``A A^T``, its
  determinant as ``|A_0 x A_1|^2`` (Binet-Cauchy): the same values in exact
  arithmetic, no cancellation (anisotropy 1e6 in float32: 4e-6 instead of 1).

``eps2d`` is added to the 2D covariance; in antialiased mode the opacity is multiplied
by ``sqrt(det(cov) / det(cov + eps2d I))``. A Gaussian is culled (radii 0,
other outputs 0) when its depth is outside [near, far], the blurred
determinant is <= 0, its opacity is below ``alpha_min``, both radii are <=
``radius_clip``, or its extent box is off-screen.

The rasterizer's backward is the hand-written :mod:`.projection_backward`; this kernel
is also differentiable by Warp's generated adjoint (the tests hold the hand kernel to it),
whose slots are laid out the same way. Per-Gaussian inputs
and the view matrices are read through 2-D ``[camera, Gaussian]`` arrays (camera
stride 0 for the Gaussians' inputs, Gaussian stride 0 for the view matrices:
no copies), so the adjoint writes each (camera, Gaussian) pair into its own slot
of a ``[C, N]`` buffer: one writer per slot, bit-identical gradients (with one
camera the buffer is the gradient itself).

With ``check`` set the kernel also runs the input value checks on the values it
loads (:func:`.validate.inputs_check_func`; colour rows and backgrounds are read for
them) and writes :data:`CHECK_FAILED` into ``ends`` for a Gaussian that fails one, so
that the intersection total the binning reads back also reports the checks. Culling
is written to hold for NaN too (each test passes only on values in range), so without
a failed check every count written is a number of tiles.

With ``tile_size > 0`` it writes each Gaussian's number of intersected tiles (the
binning's first step, :func:`.binning.tile_box_func`; also as int64 into ``ends``,
which the binning scans in place), and given a ``splats`` array, each visible
Gaussian's screen mean, conic and opacity packed together (what the blending
gathers per intersection: one load instead of three).
Culled Gaussians get zeros in every output, so no output needs clearing first.

``first``: the Gaussian of this launch's first thread (0 for all of them in one launch; on the CPU a
launch may cover a run of Gaussians in every camera, so that several launches, and their adjoints,
run side by side on the CPU's cores: ``ssgwarp.raster.cpu_threads``). Every output and adjoint slot
belongs to one (camera, Gaussian) pair, so the runs never share one.
"""

import functools
from types import SimpleNamespace

import warp as wp

from .binning import tile_box_func
from .fmath import add_rn, fma, rsqrt
from .types import types_for
from .validate import inputs_check_func

# what a Gaussian that fails an input check adds to the intersection total instead of its count:
# larger than any sum of real counts the binning accepts (it refuses totals above 2^30), and
# summed over fewer than 2^30 (camera, Gaussian) pairs it cannot overflow int64
CHECK_FAILED = wp.constant(wp.int64(2**32))
CHECK_MAX_PAIRS = 2**30  # (more pairs per call: the checks run as a pass of their own)
RADIUS_LIMIT = 1073741824.0  # radii saturate here (2^30 px) so the int32 cast never overflows


@functools.lru_cache(maxsize=None)
def matrix_funcs(scalar, native_rsqrt: bool = False):
    """The projection's small linear algebra for one precision, rounded operation for operation as
    nvcc compiles gsplat's (glm's) versions (explicit fused multiply-adds, :mod:`.fmath`; measured
    bit-identical on an H100): ``dot3``, ``mul33`` (``A B``), ``mul33_t``
    (``A B^T``), ``quat_to_rotmat`` (normalised with ``rsqrt`` when ``native_rsqrt``) and
    ``cov2d(J, Sigma_c)`` -> ``vec4(c00, c10, c01, c11)`` of ``(J Sigma_c) J^T`` with J's zero
    entries multiplied out."""
    t = types_for(scalar)
    vec4, mat33, mat23 = t.vec4, t.mat33, t.mat23

    @wp.func
    def dot3(a0: scalar, a1: scalar, a2: scalar, b0: scalar, b1: scalar, b2: scalar):
        # a0 b0 + a1 b1 + a2 b2 rounded as nvcc contracts it in gsplat's matrix products
        return fma(a2, b2, fma(a0, b0, a1 * b1))

    @wp.func
    def mul33(A: mat33, B: mat33):
        """``A B``, every entry summed in index order."""
        return mat33(
            dot3(A[0, 0], A[0, 1], A[0, 2], B[0, 0], B[1, 0], B[2, 0]),
            dot3(A[0, 0], A[0, 1], A[0, 2], B[0, 1], B[1, 1], B[2, 1]),
            dot3(A[0, 0], A[0, 1], A[0, 2], B[0, 2], B[1, 2], B[2, 2]),
            dot3(A[1, 0], A[1, 1], A[1, 2], B[0, 0], B[1, 0], B[2, 0]),
            dot3(A[1, 0], A[1, 1], A[1, 2], B[0, 1], B[1, 1], B[2, 1]),
            dot3(A[1, 0], A[1, 1], A[1, 2], B[0, 2], B[1, 2], B[2, 2]),
            dot3(A[2, 0], A[2, 1], A[2, 2], B[0, 0], B[1, 0], B[2, 0]),
            dot3(A[2, 0], A[2, 1], A[2, 2], B[0, 1], B[1, 1], B[2, 1]),
            dot3(A[2, 0], A[2, 1], A[2, 2], B[0, 2], B[1, 2], B[2, 2]),
        )

    @wp.func
    def mul33_t(A: mat33, B: mat33):
        """``A B^T`` (the transpose moves no bits)."""
        return mul33(A, wp.transpose(B))

    @wp.func
    def inv_norm4(w: scalar, x: scalar, y: scalar, z: scalar):
        n2 = fma(w, w, fma(z, z, fma(x, x, y * y)))
        if wp.static(native_rsqrt):
            return rsqrt(n2)
        else:
            return scalar(1.0) / wp.sqrt(n2)

    @wp.func
    def quat_to_rotmat(q: vec4):
        s = inv_norm4(q[0], q[1], q[2], q[3])
        w = q[0] * s
        x = q[1] * s
        y = q[2] * s
        z = q[3] * s
        y2 = y * y
        z2 = z * z
        wx = w * x
        wy = w * y
        wz = w * z
        one = scalar(1.0)
        two = scalar(2.0)
        # (2 s is exact, so 1 - 2 s rounds once however it is contracted)
        return mat33(
            one - two * add_rn(y2, z2), two * fma(x, y, -wz), two * fma(x, z, wy),
            two * fma(x, y, wz), one - two * fma(x, x, z2), two * fma(y, z, -wx),
            two * fma(x, z, -wy), two * fma(y, z, wx), one - two * fma(x, x, y2),
        )

    @wp.func
    def cov2d(J: mat23, Sc: mat33):
        T2 = mat23(
            dot3(J[0, 0], J[0, 1], J[0, 2], Sc[0, 0], Sc[1, 0], Sc[2, 0]),
            dot3(J[0, 0], J[0, 1], J[0, 2], Sc[0, 1], Sc[1, 1], Sc[2, 1]),
            dot3(J[0, 0], J[0, 1], J[0, 2], Sc[0, 2], Sc[1, 2], Sc[2, 2]),
            dot3(J[1, 0], J[1, 1], J[1, 2], Sc[0, 0], Sc[1, 0], Sc[2, 0]),
            dot3(J[1, 0], J[1, 1], J[1, 2], Sc[0, 1], Sc[1, 1], Sc[2, 1]),
            dot3(J[1, 0], J[1, 1], J[1, 2], Sc[0, 2], Sc[1, 2], Sc[2, 2]))
        return vec4(dot3(T2[0, 0], T2[0, 1], T2[0, 2], J[0, 0], J[0, 1], J[0, 2]),
                    dot3(T2[1, 0], T2[1, 1], T2[1, 2], J[0, 0], J[0, 1], J[0, 2]),
                    dot3(T2[0, 0], T2[0, 1], T2[0, 2], J[1, 0], J[1, 1], J[1, 2]),
                    dot3(T2[1, 0], T2[1, 1], T2[1, 2], J[1, 0], J[1, 1], J[1, 2]))

    return SimpleNamespace(dot3=dot3, mul33=mul33, mul33_t=mul33_t, quat_to_rotmat=quat_to_rotmat, cov2d=cov2d)


@functools.lru_cache(maxsize=None)
def activation_funcs(scalar, activations: bool):
    """How the projection's kernels load scales and opacities, three ``wp.func``s: ``load(s, o) -> (scales,
    opacity)``, and the gradients back through it, ``through_exp(v_scales, scales)`` and
    ``through_sigmoid(v_opacity, opacity)``. With ``activations`` the stored values are log-scales and
    logits: ``exp`` of each log-scale and the sigmoid ``1 / (1 + exp(-logit))`` (what ``GaussianScene.scales``
    and ``.opacities`` compute in torch), their gradients times the scale and times ``(1 - o) o`` (as torch's
    ``ExpBackward`` and ``SigmoidBackward`` take them); without, the values as they are."""
    vec3 = types_for(scalar).vec3
    one = 1.0

    @wp.func
    def load(s: vec3, o: scalar):
        if wp.static(activations):
            return (vec3(wp.exp(s[0]), wp.exp(s[1]), wp.exp(s[2])), scalar(one) / (scalar(one) + wp.exp(-o)))
        return s, o

    @wp.func
    def through_exp(g: vec3, s: vec3):
        if wp.static(activations):
            return vec3(g[0] * s[0], g[1] * s[1], g[2] * s[2])
        return g

    @wp.func
    def through_sigmoid(g: scalar, o: scalar):
        if wp.static(activations):
            return g * (scalar(one) - o) * o
        return g

    return load, through_exp, through_sigmoid


# the fields of the projection's parameter block, in order, with their types (``scalar``: the
# kernel's precision); ``ssgwarp.raster.ops.ProjectionParams`` holds the same names for the host side
PARAM_FIELDS = (("width", int), ("height", int), ("near_plane", "scalar"), ("far_plane", "scalar"),
                ("eps2d", "scalar"), ("radius_clip", "scalar"), ("alpha_min", "scalar"), ("sigma_max", "scalar"),
                ("opacity_extent", int), ("antialiased", int), ("tile_size", int), ("tile_width", int),
                ("tile_height", int))


@functools.lru_cache(maxsize=None)
def projection_params(scalar):
    """The projection's parameter block for one precision (a ``wp.struct``): image size, depth
    range, ``eps2d``, ``radius_clip``, the culling rules (``alpha_min``, ``sigma_max``,
    ``opacity_extent`` 0/1), ``antialiased`` 0/1, and the tile grid (``tile_size`` 0: no tile
    counts)."""
    cls = type(f"ProjectionParams_{scalar.__name__}", (), {
        "__annotations__": {name: scalar if t == "scalar" else t for name, t in PARAM_FIELDS},
        "__module__": __name__})
    return wp.struct(cls)


@functools.lru_cache(maxsize=None)
def covariance_funcs(scalar, native_rsqrt: bool = False):
    """The 2D covariance's two forms for one precision (``wp.func``s), whole and in pieces (the
    hand-written backward recomputes the forward with the pieces): ``cov_gsplat`` /
    ``cov_factor(J, R, M, eps2d)`` -> ``(a, b, c, det_orig, det)`` (the blurred 2D covariance
    ``[[a, b], [b, c]]``, its determinant before and after the blur); ``cov_camera(R, M)`` and
    ``blur_gsplat(cov2d(J, Sc), eps2d)``; ``factor_rows(J, R, M)`` and ``blur_factor(r0, r1, eps2d)``."""
    t = types_for(scalar)
    vec3, vec4, mat33, mat23 = t.vec3, t.vec4, t.mat33, t.mat23
    mf = matrix_funcs(scalar, native_rsqrt)
    mul33, mul33_t, cov2d = mf.mul33, mf.mul33_t, mf.cov2d

    @wp.func
    def cov_camera(R: mat33, M: mat33):
        # gsplat's order: Sigma = M M^T, Sigma_c = (R Sigma) R^T
        return mul33_t(mul33(R, mul33_t(M, M)), R)

    @wp.func
    def blur_gsplat(cv: vec4, eps2d: scalar):
        # cv = (c00, c10, c01, c11) of (J Sigma_c) J^T; eps2d on the diagonal, determinants a d - b c
        c00 = cv[0]
        c10 = cv[1]
        c01 = cv[2]
        c11 = cv[3]
        det_orig = fma(c00, c11, -(c10 * c01))
        a = add_rn(c00, eps2d)
        cc = add_rn(c11, eps2d)
        det = fma(a, cc, -(c10 * c01))
        return a, c10, cc, det_orig, det

    @wp.func
    def cov_gsplat(J: mat23, R: mat33, M: mat33, eps2d: scalar):
        # cov = (J Sigma_c) J^T with J's zero entries multiplied out
        a, b, cc, det_orig, det = blur_gsplat(cov2d(J, cov_camera(R, M)), eps2d)
        return a, b, cc, det_orig, det

    @wp.func
    def factor_rows(J: mat23, R: mat33, M: mat33):
        # the rows of the 2D covariance's 2x3 factor A = J R M
        A = J @ R @ M
        return vec3(A[0, 0], A[0, 1], A[0, 2]), vec3(A[1, 0], A[1, 1], A[1, 2])

    @wp.func
    def blur_factor(r0: vec3, r1: vec3, eps2d: scalar):
        # sums of squares, and the determinant as the squared cross product of the rows
        # (Binet-Cauchy), free of cancellation
        a = wp.dot(r0, r0)
        b = wp.dot(r0, r1)
        cc = wp.dot(r1, r1)
        cr = wp.cross(r0, r1)
        det_orig = wp.dot(cr, cr)
        det = det_orig + eps2d * (a + cc) + eps2d * eps2d
        return a + eps2d, b, cc + eps2d, det_orig, det

    @wp.func
    def cov_factor(J: mat23, R: mat33, M: mat33, eps2d: scalar):
        r0, r1 = factor_rows(J, R, M)
        a, b, cc, det_orig, det = blur_factor(r0, r1, eps2d)
        return a, b, cc, det_orig, det

    return SimpleNamespace(cov_camera=cov_camera, blur_gsplat=blur_gsplat, factor_rows=factor_rows,
                           blur_factor=blur_factor, cov_gsplat=cov_gsplat, cov_factor=cov_factor)


@functools.lru_cache(maxsize=None)
def projection_funcs(scalar, native_rsqrt: bool = False):
    """The projection kernel's maths in pieces for one precision (each a ``wp.func``; the
    hand-written backward recomputes the forward with the same ones, so its intermediate values
    are the forward's to the bit): ``camera_point(V, m)`` (``R m + t``), ``camera_rotation(V)``,
    ``scale_columns(A, s)`` (``A diag(s)``), ``scaled_rotation(q, s)`` (``M = R_q S``), ``fov_limits(fx, fy, cx, cy, w, h)`` (where the Jacobian's x/z and y/z clamp,
    at 1.3x the field of view), ``jacobian(fx, fy, cx, cy, w, h, p, z, rz)``, ``cov_gsplat`` /
    ``cov_factor`` (:func:`covariance_funcs`), ``pixel_radii(op, a, c, alpha_min, sigma_max,
    opacity_extent)`` -> ``(rx, ry)`` and ``cull(i, outputs...)``."""
    t = types_for(scalar)
    vec2, vec3, vec4, mat33, mat44, mat23 = t.vec2, t.vec3, t.vec4, t.mat33, t.mat44, t.mat23
    mf = matrix_funcs(scalar, native_rsqrt)
    dot3, quat_to_rotmat = mf.dot3, mf.quat_to_rotmat

    @wp.func
    def camera_point(V: mat44, m: vec3):
        # world to camera: R m + t, products summed in index order
        return vec3(dot3(V[0, 0], V[0, 1], V[0, 2], m[0], m[1], m[2]) + V[0, 3],
                    dot3(V[1, 0], V[1, 1], V[1, 2], m[0], m[1], m[2]) + V[1, 3],
                    dot3(V[2, 0], V[2, 1], V[2, 2], m[0], m[1], m[2]) + V[2, 3])

    @wp.func
    def scale_columns(A: mat33, s: vec3):
        # A diag(s)
        return mat33(A[0, 0] * s[0], A[0, 1] * s[1], A[0, 2] * s[2],
                     A[1, 0] * s[0], A[1, 1] * s[1], A[1, 2] * s[2],
                     A[2, 0] * s[0], A[2, 1] * s[1], A[2, 2] * s[2])

    @wp.func
    def scaled_rotation(q: vec4, s: vec3):
        return scale_columns(quat_to_rotmat(q), s)

    @wp.func
    def camera_rotation(V: mat44):
        # the rotation block of a world-to-camera matrix
        return mat33(V[0, 0], V[0, 1], V[0, 2], V[1, 0], V[1, 1], V[1, 2], V[2, 0], V[2, 1], V[2, 2])

    @wp.func
    def fov_limits(fx: scalar, fy: scalar, cx: scalar, cy: scalar, w: scalar, h: scalar):
        # how far x/z and y/z may go before the Jacobian clamps them: (x+, x-, y+, y-), 1.3x the
        # field of view
        tan_fovx = scalar(0.5) * w / fx
        tan_fovy = scalar(0.5) * h / fy
        return vec4((w - cx) / fx + scalar(0.3) * tan_fovx, cx / fx + scalar(0.3) * tan_fovx,
                    (h - cy) / fy + scalar(0.3) * tan_fovy, cy / fy + scalar(0.3) * tan_fovy)

    @wp.func
    def jacobian(fx: scalar, fy: scalar, cx: scalar, cy: scalar, w: scalar, h: scalar, p: vec3, z: scalar,
                 rz: scalar):
        lim = fov_limits(fx, fy, cx, cy, w, h)
        rz2 = rz * rz
        tx = z * wp.min(lim[0], wp.max(-lim[1], p[0] * rz))
        ty = z * wp.min(lim[2], wp.max(-lim[3], p[1] * rz))
        zero = scalar(0.0)
        return mat23(fx * rz, zero, -fx * tx * rz2,
                     zero, fy * rz, -fy * ty * rz2)

    @wp.func
    def pixel_radii(op: scalar, a: scalar, cc: scalar, alpha_min: scalar, sigma_max: scalar, opacity_extent: int):
        # the extent in standard deviations (gsplat's opacity rule or sigma_max), then per axis in pixels
        ext = sigma_max
        if opacity_extent != 0 and alpha_min > scalar(0.0):
            ext = wp.min(sigma_max, wp.sqrt(scalar(2.0) * wp.log(wp.max(op / alpha_min, scalar(1.0)))))
        rx = wp.min(wp.ceil(ext * wp.sqrt(a)), scalar(RADIUS_LIMIT))
        ry = wp.min(wp.ceil(ext * wp.sqrt(cc)), scalar(RADIUS_LIMIT))
        return rx, ry

    @wp.func
    def cull(i: int, means2d: wp.array(dtype=vec2), depths: wp.array(dtype=scalar), conics: wp.array(dtype=vec3),
             opac_out: wp.array(dtype=scalar), radii: wp.array(dtype=wp.vec2i), counts: wp.array(dtype=wp.int32),
             ends: wp.array(dtype=wp.int64)):
        """Zeros in every output of a culled Gaussian."""
        means2d[i] = vec2()
        depths[i] = scalar(0.0)
        conics[i] = vec3()
        opac_out[i] = scalar(0.0)
        radii[i] = wp.vec2i(0, 0)
        if counts.shape[0] > 0:
            counts[i] = 0
        if ends.shape[0] > 0:
            ends[i] = wp.int64(0)

    cf = covariance_funcs(scalar, native_rsqrt)
    return SimpleNamespace(camera_point=camera_point, scale_columns=scale_columns, scaled_rotation=scaled_rotation,
                           camera_rotation=camera_rotation, fov_limits=fov_limits,
                           jacobian=jacobian, cov_gsplat=cf.cov_gsplat, cov_factor=cf.cov_factor,
                           pixel_radii=pixel_radii, cull=cull)


@functools.lru_cache(maxsize=None)
def projection_kernel(scalar, covariance: str = "gsplat", fast_math: bool = False, adjoint: bool = False,
                      activations: bool = False):
    """The projection kernel for one precision, launched over ``(C, N)``. ``covariance``:
    ``"gsplat"`` or ``"factor"`` (see the module docstring); ``fast_math``: approximate division,
    square roots and logarithm (float32 on CUDA, as gsplat compiles its kernels; then the
    quaternion norm uses ``rsqrtf``); ``adjoint``: built with Warp's generated adjoint too (the
    hand-written backward's yardstick; without it the module compiles in about 30 % less time);
    ``activations``: ``scales`` holds log-scales and ``opacities`` logits, activated as loaded
    (:func:`activation_funcs`), before the input checks (which then see what the projection uses)."""
    t = types_for(scalar)
    vec2, vec3, vec4, mat33, mat44, splat = t.vec2, t.vec3, t.vec4, t.mat33, t.mat44, t.splat
    fns = projection_funcs(scalar, fast_math and scalar == wp.float32)
    camera_point, camera_rotation, scaled_rotation, jacobian, pixel_radii, cull = (
        fns.camera_point, fns.camera_rotation, fns.scaled_rotation, fns.jacobian, fns.pixel_radii, fns.cull)
    covariance_2d = fns.cov_gsplat if covariance == "gsplat" else fns.cov_factor
    tile_box = tile_box_func(scalar)
    check_inputs = inputs_check_func(scalar)
    Params = projection_params(scalar)
    load_activated = activation_funcs(scalar, activations)[0]

    @wp.kernel(module="unique", module_options={"fast_math": fast_math, "enable_backward": bool(adjoint)})
    def project(
        means: wp.array2d(dtype=vec3),
        quats: wp.array2d(dtype=vec4),
        scales: wp.array2d(dtype=vec3),
        opacities: wp.array2d(dtype=scalar),
        viewmats: wp.array2d(dtype=mat44),
        Ks: wp.array(dtype=mat33),
        params: Params,
        colors: wp.array(dtype=scalar),
        color_row: int,
        colors_per_camera: int,
        backgrounds: wp.array(dtype=scalar),
        background_row: int,
        check: int,
        means2d: wp.array(dtype=vec2),
        depths: wp.array(dtype=scalar),
        conics: wp.array(dtype=vec3),
        opac_out: wp.array(dtype=scalar),
        radii: wp.array(dtype=wp.vec2i),
        counts: wp.array(dtype=wp.int32),
        ends: wp.array(dtype=wp.int64),
        splats: wp.array(dtype=splat),
        first: int,
    ):
        c, t = wp.tid()
        n = t + first
        i = c * means.shape[1] + n
        near_plane = params.near_plane
        far_plane = params.far_plane
        eps2d = params.eps2d
        alpha_min = params.alpha_min
        sigma_max = params.sigma_max
        V = viewmats[c, n]
        m = means[c, n]
        sc, op = load_activated(scales[c, n], opacities[c, n])
        if check != 0:  # the input value checks, on the values loaded here
            if check_inputs(c, n, i, m, quats[c, n], sc, op, V, Ks[c], colors, color_row,
                            colors_per_camera, backgrounds, background_row):
                cull(i, means2d, depths, conics, opac_out, radii, counts, ends)
                if ends.shape[0] > 0:
                    ends[i] = CHECK_FAILED
                return
        p = camera_point(V, m)
        z = p[2]
        if not (z >= near_plane and z <= far_plane):
            cull(i, means2d, depths, conics, opac_out, radii, counts, ends)
            return
        R = camera_rotation(V)
        M = scaled_rotation(quats[c, n], sc)
        K = Ks[c]
        fx = K[0, 0]
        fy = K[1, 1]
        cx = K[0, 2]
        cy = K[1, 2]
        w = scalar(params.width)
        h = scalar(params.height)
        rz = scalar(1.0) / z
        J = jacobian(fx, fy, cx, cy, w, h, p, z, rz)
        a, b, cc, det_orig, det = covariance_2d(J, R, M, eps2d)
        if det <= scalar(0.0):
            cull(i, means2d, depths, conics, opac_out, radii, counts, ends)
            return
        if params.antialiased != 0:
            op = op * wp.sqrt(wp.max(scalar(0.0), det_orig / det))
        if op < alpha_min:
            cull(i, means2d, depths, conics, opac_out, radii, counts, ends)
            return
        rx, ry = pixel_radii(op, a, cc, alpha_min, sigma_max, params.opacity_extent)
        if rx <= params.radius_clip and ry <= params.radius_clip:
            cull(i, means2d, depths, conics, opac_out, radii, counts, ends)
            return
        mx = fx * p[0] * rz + cx
        my = fy * p[1] * rz + cy
        if not (mx + rx > scalar(0.0) and mx - rx < w and my + ry > scalar(0.0) and my - ry < h):
            cull(i, means2d, depths, conics, opac_out, radii, counts, ends)
            return
        means2d[i] = vec2(mx, my)
        depths[i] = z
        inv_det = scalar(1.0) / det
        conic = vec3(cc * inv_det, -b * inv_det, a * inv_det)
        conics[i] = conic
        opac_out[i] = op
        if splats.shape[0] > 0:  # the same, packed for the blending's gather (visible Gaussians only)
            splats[i] = splat(mx, my, conic[0], conic[1], conic[2], op)
        r = wp.vec2i(int(rx), int(ry))
        radii[i] = r
        if counts.shape[0] > 0:
            box = tile_box(vec2(mx, my), r, params.tile_size, params.tile_width, params.tile_height)
            cnt = (box[2] - box[0]) * (box[3] - box[1])
            counts[i] = cnt
            if ends.shape[0] > 0:  # (int64, scanned in place into the intersection ends)
                ends[i] = wp.int64(cnt)

    return project
