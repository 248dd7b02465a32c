"""The rasterizer against hand-derived values, independent of ``ssgwarp/raster/reference.py``.

Every expectation here is computed in the test from the formulas of 3D Gaussian splatting (numpy,
float64): one Gaussian's image, its 2D covariance ``J Sigma J^T + eps2d I`` (sigma = f s / z on the
optical axis), pixel centres at +0.5, wxyz quaternions, the antialiasing opacity factor, SH colour
+0.5 clamped at 0, depth and expected depth, the camera centre of a moved camera, the alpha clamp,
the 1/255 alpha threshold and the transmittance cut-off. Both backends run each case (the Warp
kernels and the dense torch reference), so a rule shared by both (validation, SH offset, depth
division, camera centres) is checked too. The CUDA cases run the default GPU path (float32, fast
maths) and are marked ``cuda``.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ssgwarp import RasterSettings, rasterization

from conftest import CUDA_ONLY

W, H, F = 33, 29, 30.0
CX, CY = 16.5, 14.5        # the optical axis meets the image at the centre of pixel (x=16, y=14)
PX, PY = 16, 14
ALPHA_MIN = 1.0 / 255.0
SH_C0 = 0.5 / math.sqrt(math.pi)             # Y_0^0 = 1 / (2 sqrt(pi))
SH_C1 = math.sqrt(3.0 / (4.0 * math.pi))     # |Y_1^m| = sqrt(3 / 4pi) times a coordinate

CASES = [
    pytest.param(("warp", "cpu", torch.float64), id="warp-cpu-f64"),
    pytest.param(("torch", "cpu", torch.float64), id="torch-cpu-f64"),
    pytest.param(("warp", "cuda", torch.float32), id="warp-cuda-f32", marks=CUDA_ONLY),
    pytest.param(("torch", "cuda", torch.float32), id="torch-cuda-f32", marks=CUDA_ONLY),
]


def tol(case) -> float:
    """Absolute tolerance on values of order 1: float64 rounding, or float32 with fast maths."""
    return 1e-12 if case[2] == torch.float64 else 2e-6


def K_of(fx=F, fy=None, cx=CX, cy=CY) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, F if fy is None else fy, cy], [0.0, 0.0, 1.0]])


def render(case, means, quats, scales, opacities, colors, viewmats=None, Ks=None, **kw):
    """``rasterization`` of numpy/list inputs with the case's backend, device and dtype; numpy out."""
    backend, device, dtype = case
    t = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
    means = np.atleast_2d(means)
    viewmats = np.eye(4)[None] if viewmats is None else np.asarray(viewmats).reshape(-1, 4, 4)
    Ks = np.repeat(K_of()[None], len(viewmats), 0) if Ks is None else np.asarray(Ks).reshape(-1, 3, 3)
    bg = kw.pop("backgrounds", None)
    img, alpha, meta = rasterization(t(means), t(np.atleast_2d(quats)), t(np.atleast_2d(scales)),
                                     t(np.atleast_1d(opacities)), t(colors), t(viewmats), t(Ks), W, H,
                                     backgrounds=None if bg is None else t(bg), backend=backend, **kw)
    meta = {k: (v.detach().double().cpu().numpy() if isinstance(v, torch.Tensor) else v) for k, v in meta.items()}
    return img.double().cpu().numpy(), alpha.double().cpu().numpy()[..., 0], meta


def pixel_centres() -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    return xs + 0.5, ys + 0.5


def splat_alpha(mean2d, cov2d, opacity, alpha_max=0.999, alpha_min=ALPHA_MIN) -> np.ndarray:
    """``[H, W]`` alpha of one projected Gaussian: ``min(alpha_max, o exp(-d^T cov^-1 d / 2))`` at the
    pixel centres, 0 below ``alpha_min``."""
    xs, ys = pixel_centres()
    d = np.stack([xs - mean2d[0], ys - mean2d[1]], -1)
    q = np.einsum("...i,ij,...j->...", d, np.linalg.inv(cov2d), d)
    a = np.minimum(alpha_max, opacity * np.exp(-0.5 * q))
    return np.where(a >= alpha_min, a, 0.0)


def jacobian(p_cam, fx=F, fy=F) -> np.ndarray:
    x, y, z = p_cam
    return np.array([[fx / z, 0.0, -fx * x / z ** 2], [0.0, fy / z, -fy * y / z ** 2]])


def rotation_axis_angle(axis, angle) -> np.ndarray:
    """Rodrigues' formula (independent of any quaternion formula)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    A = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) * math.cos(angle) + math.sin(angle) * A + (1.0 - math.cos(angle)) * np.outer(a, a)


def quat_wxyz(axis, angle, norm=1.0) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    return norm * np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * a])


def conic_of(cov2d) -> np.ndarray:
    inv = np.linalg.inv(cov2d)
    return np.array([inv[0, 0], inv[0, 1], inv[1, 1]])


# ------------------------------------------------------------------------------------------------
# one Gaussian: image, peak, pixel centres, 2D covariance
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", CASES)
def test_one_gaussian_renders_the_analytic_image(case):
    """An isotropic Gaussian off the optical axis: the whole image and alpha equal
    ``colour * min(0.999, o exp(-d^T (J s^2 J^T + 0.3 I)^-1 d / 2))`` at the pixel centres where that
    alpha is >= 1/255, and exactly 0 elsewhere; meta holds its screen mean, depth, conic and radii."""
    p, s, o, col = np.array([0.3, -0.2, 4.0]), 0.2, 0.8, np.array([0.2, 0.6, 1.0])
    img, alpha, meta = render(case, p, [1, 0, 0, 0], [s, s, s], o, col[None])
    mean2d = np.array([F * p[0] / p[2] + CX, F * p[1] / p[2] + CY])   # (18.75, 13.0)
    J = jacobian(p)
    cov2d = s * s * J @ J.T + 0.3 * np.eye(2)
    a = splat_alpha(mean2d, cov2d, o)
    assert (a > 0).sum() > 30 and (a == 0).sum() > 100          # the test sees both sides of the threshold
    np.testing.assert_allclose(alpha[0], a, rtol=0, atol=tol(case))
    np.testing.assert_allclose(img[0], a[..., None] * col, rtol=0, atol=tol(case))
    np.testing.assert_allclose(meta["means2d"][0, 0], mean2d, rtol=0, atol=50 * tol(case))
    np.testing.assert_allclose(meta["depths"][0, 0], p[2], rtol=0, atol=tol(case))
    np.testing.assert_allclose(meta["conics"][0, 0], conic_of(cov2d), rtol=1e-5 if case[2] == torch.float32 else 1e-11)
    ext = min(3.33, math.sqrt(2.0 * math.log(o / ALPHA_MIN)))         # where o exp(-ext^2 / 2) = 1/255
    radii = np.ceil(ext * np.sqrt(np.diag(cov2d)))
    np.testing.assert_array_equal(meta["radii"][0, 0], radii)


@pytest.mark.parametrize("case", CASES)
def test_pixel_centres_are_at_half_integers(case):
    """A Gaussian whose mean is a pixel centre peaks there with exactly its opacity and renders
    symmetric about that pixel; one whose mean is a pixel corner renders four equal pixels around it."""
    o, col = 0.7, np.array([[1.0, 0.5, 0.25]])
    img, alpha, _ = render(case, [0.0, 0.0, 4.0], [1, 0, 0, 0], [0.15] * 3, o, col)
    a = alpha[0]
    assert np.unravel_index(np.argmax(a), a.shape) == (PY, PX)
    assert abs(a[PY, PX] - o) <= tol(case)
    np.testing.assert_allclose(img[0, PY, PX], o * col[0], rtol=0, atol=tol(case))
    for k in range(1, 5):
        assert 0 < a[PY, PX + k] < a[PY, PX + k - 1]
        np.testing.assert_allclose([a[PY, PX - k], a[PY - k, PX], a[PY + k, PX]], a[PY, PX + k], rtol=0,
                                   atol=tol(case))
    # the principal point on a pixel corner (x = 16, y = 14): pixels 15/16 and 13/14 tie
    K = K_of(cx=16.0, cy=14.0)
    _, alpha, _ = render(case, [0.0, 0.0, 4.0], [1, 0, 0, 0], [0.15] * 3, o, col, Ks=K[None])
    a = alpha[0]
    block = a[13:15, 15:17]
    np.testing.assert_allclose(block, np.full((2, 2), block[0, 0]), rtol=0, atol=tol(case))
    assert block[0, 0] < o - 0.05 and block.min() >= a.max() - tol(case)
    np.testing.assert_allclose(a[:, 15::-1][:, :12], a[:, 16:28], rtol=0, atol=tol(case))   # mirror about x = 16


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("eps2d", [None, 0.0, 1.0])
@pytest.mark.parametrize("depth", [4.0, 8.0])
def test_2d_sigma_is_focal_times_scale_over_depth_plus_eps2d(case, eps2d, depth):
    """Measured from the rendered profile through the peak: ``sigma_x^2 = (fx s / z)^2 + eps2d`` and
    ``sigma_y^2 = (fy s / z)^2 + eps2d``, with gsplat's default ``eps2d = 0.3`` when none is given."""
    fx, fy, s, o = 30.0, 24.0, 0.3, 0.9
    kw = {} if eps2d is None else {"eps2d": eps2d}
    _, alpha, _ = render(case, [0.0, 0.0, depth], [1, 0, 0, 0], [s] * 3, o, [[1.0]], Ks=K_of(fx, fy)[None], **kw)
    a = alpha[0]
    e = 0.3 if eps2d is None else eps2d
    for axis, f in ((0, fx), (1, fy)):
        expect = (f * s / depth) ** 2 + e
        for k in (1, 2):
            ak = a[PY, PX + k] if axis == 0 else a[PY + k, PX]
            measured = k * k / (2.0 * math.log(a[PY, PX] / ak))
            assert measured == pytest.approx(expect, rel=1e-4 if case[2] == torch.float32 else 1e-10), (axis, k)


@pytest.mark.parametrize("case", CASES)
def test_quaternion_is_wxyz_and_rotates_the_ellipse(case):
    """A long Gaussian turned 30 degrees about the optical axis by ``q = (cos 15, 0, 0, sin 15)`` (wxyz,
    any norm) lies along (cos 30, sin 30) in the image (x right, y down): measured from the image's
    second moments, and its conic equals the inverse of ``(f/z)^2 R diag(sx^2, sy^2) R^T + 0.3 I``.
    A general rotation's conic is checked against Rodrigues' rotation matrix."""
    z, sc = 4.0, np.array([0.4, 0.08, 0.08])
    theta = math.radians(30.0)
    img, alpha, meta = render(case, [0.0, 0.0, z], quat_wxyz([0, 0, 1], theta, norm=2.5), sc, 0.9, [[1.0]])
    R2 = rotation_axis_angle([0, 0, 1], theta)[:2, :2]
    cov2d = (F / z) ** 2 * R2 @ np.diag(sc[:2] ** 2) @ R2.T + 0.3 * np.eye(2)
    rtol = 1e-5 if case[2] == torch.float32 else 1e-11
    np.testing.assert_allclose(meta["conics"][0, 0], conic_of(cov2d), rtol=rtol, atol=1e-12)
    xs, ys = pixel_centres()
    a = alpha[0]
    dx, dy = xs - CX, ys - CY
    m20, m02, m11 = (a * dx * dx).sum(), (a * dy * dy).sum(), (a * dx * dy).sum()
    angle = 0.5 * math.degrees(math.atan2(2 * m11, m20 - m02))
    assert angle == pytest.approx(30.0, abs=1.0)
    # a general rotation (axis (1, 2, 3), 50 degrees) off the optical axis: the full EWA covariance
    p = np.array([0.25, 0.1, 5.0])
    axis, ang = [1.0, 2.0, 3.0], math.radians(50.0)
    sc = np.array([0.3, 0.1, 0.05])
    _, _, meta = render(case, p, quat_wxyz(axis, ang, norm=0.4), sc, 0.9, [[1.0]])
    R = rotation_axis_angle(axis, ang)
    J = jacobian(p)
    cov2d = J @ R @ np.diag(sc ** 2) @ R.T @ J.T + 0.3 * np.eye(2)
    np.testing.assert_allclose(meta["conics"][0, 0], conic_of(cov2d), rtol=rtol, atol=1e-12)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("eps2d", [0.3, 0.7])
def test_antialiased_mode_scales_opacity_by_the_blur_compensation(case, eps2d):
    """Antialiased: opacity times ``sqrt(det(Sigma) / det(Sigma + eps2d I))`` (meta and the peak pixel);
    classic: the opacity itself."""
    z, sc, o, col = 4.0, np.array([0.2, 0.1, 0.1]), 0.8, np.array([[0.5, 1.0, 0.25]])
    vx, vy = (F * sc[0] / z) ** 2, (F * sc[1] / z) ** 2
    factor = math.sqrt(vx * vy / ((vx + eps2d) * (vy + eps2d)))
    assert factor < 0.8                               # a real reduction, far from rounding
    for mode, expect in (("antialiased", o * factor), ("classic", o)):
        img, alpha, meta = render(case, [0.0, 0.0, z], [1, 0, 0, 0], sc, o, col, eps2d=eps2d, rasterize_mode=mode)
        assert meta["opacities"][0, 0] == pytest.approx(expect, abs=tol(case))
        assert alpha[0, PY, PX] == pytest.approx(expect, abs=tol(case))
        np.testing.assert_allclose(img[0, PY, PX], expect * col[0], rtol=0, atol=tol(case))


# ------------------------------------------------------------------------------------------------
# colour: SH offset and clamp, view direction from the camera centre
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", CASES)
def test_sh_degree0_adds_half_and_clamps_at_zero(case):
    """Degree 0: colour = ``max(0, Y00 k + 0.5)`` with ``Y00 = 1 / (2 sqrt(pi))``; higher bands are
    ignored at degree 0."""
    o = 0.8
    sh = np.zeros((1, 4, 3))
    sh[0, 0] = [1.0, -3.0, 0.0]          # 0.782..., clamped to 0 (0.5 - 0.846), exactly 0.5
    sh[0, 1:] = 5.0                      # degree-1 bands: unused at degree 0
    img, _, _ = render(case, [0.0, 0.0, 4.0], [1, 0, 0, 0], [0.15] * 3, o, sh, sh_degree=0)
    expect = o * np.array([SH_C0 + 0.5, 0.0, 0.5])
    np.testing.assert_allclose(img[0, PY, PX], expect, rtol=0, atol=tol(case))


def camera_looking_along(centre, forward) -> tuple[np.ndarray, np.ndarray]:
    """``(viewmat, R)`` of a camera at ``centre`` whose optical axis (camera z) is ``forward`` in world."""
    zc = np.asarray(forward, dtype=np.float64)
    zc = zc / np.linalg.norm(zc)
    xc = np.cross([0.0, 1.0, 0.0], zc)
    xc = xc / np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    R = np.stack([xc, yc, zc])                       # rows: camera axes in world coordinates
    vm = np.eye(4)
    vm[:3, :3], vm[:3, 3] = R, -R @ np.asarray(centre, dtype=np.float64)
    return vm, R


@pytest.mark.parametrize("case", CASES)
def test_sh_view_direction_is_from_the_camera_centre(case):
    """Degrees 1 and 2 seen by a moved, turned camera: the direction is the Gaussian's mean minus the
    camera centre ``-R^T t`` (here the camera's optical axis (1, 2, 2)/3), and the colour at the peak
    is the SH sum + 0.5 with the real SH constants written out here."""
    centre, d = np.array([1.0, -2.0, 3.0]), np.array([1.0, 2.0, 2.0]) / 3.0
    vm, _ = camera_looking_along(centre, d)
    mean = centre + 4.0 * d                           # on the optical axis, 4 in front
    g = np.random.default_rng(0)
    sh = g.normal(size=(1, 9, 3)) * 0.3
    x, y, zz = d
    c2a, c2b, c2c = 0.5 * math.sqrt(15 / math.pi), 0.25 * math.sqrt(5 / math.pi), 0.25 * math.sqrt(15 / math.pi)
    basis = np.array([SH_C0, -SH_C1 * y, SH_C1 * zz, -SH_C1 * x,
                      c2a * x * y, -c2a * y * zz, c2b * (2 * zz * zz - x * x - y * y), -c2a * x * zz,
                      c2c * (x * x - y * y)])
    o = 0.9
    for degree in (1, 2):
        k = (degree + 1) ** 2
        img, _, meta = render(case, mean, [1, 0, 0, 0], [0.15] * 3, o, sh, viewmats=vm, sh_degree=degree)
        colour = np.maximum(basis[:k] @ sh[0, :k] + 0.5, 0.0)
        atol = 1e-9 if case[2] == torch.float64 else 1e-4
        np.testing.assert_allclose(meta["means2d"][0, 0], [CX, CY], rtol=0, atol=atol)
        np.testing.assert_allclose(img[0, PY, PX], o * colour, rtol=0, atol=10 * tol(case))


@pytest.mark.parametrize("case", CASES)
def test_moved_cameras_project_through_their_viewmats(case):
    """Two cameras in one call, each at its own centre and orientation: a Gaussian at
    ``c + R^T (0.5, -0.25, 4)`` lands at ``(cx + f 0.5/4, cy - f 0.25/4)`` with depth 4 in each."""
    cams = [camera_looking_along([1.0, -2.0, 3.0], [1.0, 2.0, 2.0]), camera_looking_along([-2.0, 0.5, 0.0], [0, 0, 1])]
    local = np.array([0.5, -0.25, 4.0])
    expect2d = [CX + F * 0.125, CY - F * 0.0625]
    for c, (vm, R) in enumerate(cams):
        centre = -R.T @ vm[:3, 3]
        mean = centre + R.T @ local
        vms = np.stack([cams[0][0], cams[1][0]])
        _, alpha, meta = render(case, mean, [1, 0, 0, 0], [0.1] * 3, 0.9, [[1.0]], viewmats=vms)
        atol = 1e-9 if case[2] == torch.float64 else 2e-4
        np.testing.assert_allclose(meta["means2d"][c, 0], expect2d, rtol=0, atol=atol)
        np.testing.assert_allclose(meta["depths"][c, 0], 4.0, rtol=0, atol=atol)
        assert alpha[c].max() > 0.5                     # and it is drawn there
        assert np.unravel_index(np.argmax(alpha[c]), alpha[c].shape) == (int(expect2d[1]), int(expect2d[0]))


# ------------------------------------------------------------------------------------------------
# depth modes
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", CASES)
def test_depth_and_expected_depth_by_hand(case):
    """Two Gaussians on the optical axis at depths 2 and 4 (same size on screen), opacity 0.5 each:
    at the centre pixel alpha = 0.5 + 0.5 * 0.5 = 0.75, D = 0.5 * 2 + 0.25 * 4 = 2, ED = D / alpha
    = 8/3; colours blend as 0.5 c1 + 0.25 c2 (+ 0.25 bg); depth channels take no background. ED is
    D / alpha at every pixel and 0 where nothing is drawn."""
    means = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0]])
    scales = np.array([[0.06] * 3, [0.12] * 3])
    cols = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    bg = np.array([[0.1, 0.2, 0.3]])
    quats = np.array([[1.0, 0, 0, 0]] * 2)
    out = {}
    for mode in ("RGB", "D", "ED", "RGB+D", "RGB+ED"):
        out[mode] = render(case, means, quats, scales, [0.5, 0.5], cols, render_mode=mode, backgrounds=bg)
    t = tol(case)
    rgb = 0.5 * cols[0] + 0.25 * cols[1] + 0.25 * bg[0]
    np.testing.assert_allclose(out["RGB"][0][0, PY, PX], rgb, rtol=0, atol=t)
    assert out["D"][0].shape[-1] == 1 and out["D"][0][0, PY, PX, 0] == pytest.approx(2.0, abs=4 * t)
    assert out["ED"][0][0, PY, PX, 0] == pytest.approx(8.0 / 3.0, abs=4 * t)
    np.testing.assert_allclose(out["RGB+D"][0][0, PY, PX], [*rgb, 2.0], rtol=0, atol=4 * t)
    np.testing.assert_allclose(out["RGB+ED"][0][0, PY, PX], [*rgb, 8.0 / 3.0], rtol=0, atol=4 * t)
    for mode in out:
        assert out[mode][1][0, PY, PX] == pytest.approx(0.75, abs=t)
    D, ED, alpha = out["D"][0][0, ..., 0], out["ED"][0][0, ..., 0], out["D"][1][0]
    drawn = alpha > 0
    assert drawn.sum() > 20 and (~drawn).sum() > 100
    np.testing.assert_allclose(ED[drawn], D[drawn] / alpha[drawn], rtol=1e-5 if case[2] == torch.float32 else 1e-12)
    assert (ED[~drawn] == 0).all() and (D[~drawn] == 0).all()
    assert ((ED[drawn] >= 2.0 - 1e-5) & (ED[drawn] <= 4.0 + 1e-5)).all()   # a weighted mean of the two depths
    np.testing.assert_allclose(out["RGB+ED"][0][0, ..., 3], ED, rtol=0, atol=4 * t)
    np.testing.assert_allclose(out["RGB+D"][0][0, ..., :3], out["RGB"][0][0], rtol=0, atol=t)


# ------------------------------------------------------------------------------------------------
# gating: alpha clamp, alpha threshold, transmittance cut-off
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", CASES)
def test_alpha_clamp(case):
    """Alpha is clamped at 0.999 (gsplat's value, the default ``RasterSettings.alpha_max``): an opaque
    Gaussian's centre has alpha 0.999 while its neighbours keep ``o exp(-sigma)``; the knob moves it."""
    assert RasterSettings().alpha_max == 0.999
    col = np.array([[0.3, 0.6, 0.9]])
    img, alpha, _ = render(case, [0.0, 0.0, 4.0], [1, 0, 0, 0], [0.4] * 3, 1.0, col)
    assert alpha[0, PY, PX] == pytest.approx(0.999, abs=tol(case))
    np.testing.assert_allclose(img[0, PY, PX], 0.999 * col[0], rtol=0, atol=tol(case))
    v = (F * 0.4 / 4.0) ** 2 + 0.3
    assert alpha[0, PY, PX + 1] == pytest.approx(math.exp(-0.5 / v), abs=tol(case))   # 0.956 < 0.999: not clamped
    _, alpha, _ = render(case, [0.0, 0.0, 4.0], [1, 0, 0, 0], [0.4] * 3, 1.0, col,
                         settings=RasterSettings(alpha_max=0.5))
    np.testing.assert_allclose(alpha[0, PY, PX:PX + 2], 0.5, rtol=0, atol=tol(case))


@pytest.mark.parametrize("case", CASES)
def test_alpha_threshold_1_over_255(case):
    """Contributions below alpha 1/255 are skipped: a faint Gaussian (opacity 1.5/255) covers exactly
    the pixels where ``o exp(-sigma) >= 1/255``; one with opacity 0.99/255 is culled (radii 0, nothing
    drawn)."""
    o = 1.5 / 255.0
    _, alpha, meta = render(case, [0.05, 0.0, 4.0], [1, 0, 0, 0], [0.3] * 3, o, [[1.0]])
    J = jacobian([0.05, 0.0, 4.0])
    cov2d = 0.3 ** 2 * J @ J.T + 0.3 * np.eye(2)
    mean2d = (CX + F * 0.05 / 4.0, CY)
    free = splat_alpha(mean2d, cov2d, o, alpha_min=0.0)
    assert np.abs(free - ALPHA_MIN).min() > 1e-6          # no pixel sits on the threshold itself
    expect = np.where(free >= ALPHA_MIN, free, 0.0)
    assert 5 < (expect > 0).sum() < (free > 0.5 * ALPHA_MIN).sum()
    np.testing.assert_allclose(alpha[0], expect, rtol=0, atol=tol(case) * 1e-2)
    _, alpha, meta = render(case, [0.05, 0.0, 4.0], [1, 0, 0, 0], [0.3] * 3, 0.99 / 255.0, [[1.0]])
    assert (meta["radii"] == 0).all() and (alpha == 0).all()


@pytest.mark.parametrize("case", CASES)
def test_transmittance_cut_off(case):
    """Five layers of alpha 0.85 on one pixel: T falls 0.15, 0.0225, 3.4e-3, 5.1e-4, and the fifth
    would bring it to 7.6e-5 <= t_min = 1e-4, so it ends the pixel unblended; the pixel's channels are
    the first four weights 0.85 * 0.15^k and its alpha 1 - 0.15^4. With ``t_min = 0`` all five blend."""
    n = 5
    z = np.arange(2.0, 2.0 + n)
    means = np.stack([np.zeros(n), np.zeros(n), z], -1)
    scales = np.repeat((0.05 * z)[:, None], 3, 1)                 # same size on screen
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    cols = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    w = 0.85 * 0.15 ** np.arange(n)
    t = 10 * tol(case)
    img, alpha, _ = render(case, means, quats, scales, np.full(n, 0.85), cols)
    np.testing.assert_allclose(img[0, PY, PX], w[:4], rtol=0, atol=t)
    assert alpha[0, PY, PX] == pytest.approx(1.0 - 0.15 ** 4, abs=t)
    img, alpha, _ = render(case, means, quats, scales, np.full(n, 0.85), cols, settings=RasterSettings(t_min=0.0))
    np.testing.assert_allclose(img[0, PY, PX], w[:4] + w[4], rtol=0, atol=t)
    assert alpha[0, PY, PX] == pytest.approx(1.0 - 0.15 ** 5, abs=t)


def test_every_projection_entry_point_defaults_to_gsplats_eps2d():
    """The public call and both projection functions default to gsplat's ``eps2d = 0.3`` (the public
    call's default is measured from images above; the others must not drift from it)."""
    import inspect

    from ssgwarp.raster.ops import project_warp
    from ssgwarp.raster.reference import project_reference

    for fn in (rasterization, project_reference, project_warp):
        assert inspect.signature(fn).parameters["eps2d"].default == 0.3, fn.__qualname__
