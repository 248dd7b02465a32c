"""``ssgwarp.rasterization``: the differentiable 3DGS renderer, gsplat 1.5.3-compatible.

A gsplat user swaps the import and keeps the call. The work runs in Warp
kernels (``backend="warp"``, CPU tensors on Warp's CPU device, CUDA tensors on
CUDA, zero-copy on torch's current stream) or in the dense torch reference
(``backend="torch"``, :mod:`ssgwarp.reference`, the spec).

Pipeline (one module each): projection + SH (``kernels/projection.py``,
``kernels/sh.py``) → tile binning and sort (``kernels/binning.py``) → blending
(``kernels/blend_forward.py``, ``kernels/blend_backward.py``), the per-pixel
rule shared by both in ``kernels/pixel.py``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal, Optional

import torch

Tensor = torch.Tensor


@dataclass(frozen=True)
class RasterSettings:
    """Speed/accuracy knobs of the rasterizer (defaults = gsplat classic mode).

    alpha_min: contributions with alpha below it are skipped, and Gaussians
        whose opacity is below it are culled (gsplat: 1/255).
    t_min: transmittance cut-off: the Gaussian that would bring T to
        ``<= t_min`` ends the pixel and is not blended (gsplat: 1e-4).
    alpha_max: alpha clamp (gsplat: 0.999).
    extent: ``"opacity"``: per-axis radius of ``min(sigma_max, sqrt(2 ln(opacity /
        alpha_min)))`` standard deviations (gsplat); ``"fixed"``: ``sigma_max``.
    sigma_max: the extent cap in standard deviations (gsplat: 3.33).
    fast_math: CUDA float32 kernels use the GPU's approximate ``exp``, ``log``, division and
        square roots (relative error ~1e-6; see docs/tradeoffs.md), as gsplat compiles its
        kernels; ``False``: IEEE maths. No effect on the CPU or in float64. The forward and
        backward passes always share one rule, so the gating decisions match either way.
    covariance: how the projection forms the 2D covariance. ``"gsplat"``: ``J Sigma J^T``
        with gsplat's order of operations, so float32 CUDA images equal gsplat's; loses very
        anisotropic Gaussians (ratio of scales beyond ~1e3) in float32 to cancellation.
        ``"factor"``: from its 2x3 factor with a cancellation-free determinant (accurate at
        anisotropy 1e6 in float32; docs/numerics.md). Same values in exact arithmetic.
    """

    alpha_min: float = 1.0 / 255.0
    t_min: float = 1e-4
    alpha_max: float = 0.999
    extent: Literal["opacity", "fixed"] = "opacity"
    sigma_max: float = 3.33
    fast_math: bool = True
    covariance: Literal["gsplat", "factor"] = "gsplat"

    def __post_init__(self) -> None:
        if not 0.0 <= self.alpha_min < 1.0:
            raise ValueError(f"RasterSettings.alpha_min must be in [0, 1), got {self.alpha_min}")
        if not 0.0 <= self.t_min < 1.0:
            raise ValueError(f"RasterSettings.t_min must be in [0, 1), got {self.t_min}")
        if not 0.0 < self.alpha_max <= 1.0:
            raise ValueError(f"RasterSettings.alpha_max must be in (0, 1], got {self.alpha_max}")
        if self.extent not in ("opacity", "fixed"):
            raise ValueError(f"RasterSettings.extent must be 'opacity' or 'fixed', got {self.extent!r}")
        if self.covariance not in ("gsplat", "factor"):
            raise ValueError(f"RasterSettings.covariance must be 'gsplat' or 'factor', got {self.covariance!r}")
        if not self.sigma_max > 0.0:
            raise ValueError(f"RasterSettings.sigma_max must be > 0, got {self.sigma_max}")

    def for_dtype(self, dtype: torch.dtype) -> "RasterSettings":
        """These settings with ``t_min`` raised to the precision's floor (see ``T_MIN_FLOOR``)."""
        floor = T_MIN_FLOOR.get(dtype, 0.0)
        if self.t_min >= floor:
            return self
        return dataclasses.replace(self, t_min=floor)

    @classmethod
    def exact(cls, sigma_max: float = 3.33) -> "RasterSettings":
        """No alpha threshold, no transmittance cut-off, no alpha clamp, IEEE maths and the
        cancellation-free covariance (gradient checks, extreme scenes)."""
        return cls(alpha_min=0.0, t_min=0.0, alpha_max=1.0, extent="fixed", sigma_max=sigma_max, fast_math=False,
                   covariance="factor")


RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
_DEFAULT_SETTINGS = RasterSettings()

# tile size when the caller gives none, per device type: gsplat's 16 on CUDA (its layout, and the
# fastest forward+backward there); 8 on the CPU, where a pixel walks its whole tile's list one
# Gaussian at a time, so shorter lists win (measured 1.6-3x faster than 16; benchmarks/tile_size.py,
# docs/tradeoffs.md). Under the default rules the image does not depend on the tile size.
DEFAULT_TILE_SIZE = {"cuda": 16, "cpu": 8}

# Pixels always end once the transmittance would fall to this floor, also with t_min = 0: layers
# behind it add less than the precision resolves, and the backward pass rebuilds each layer's
# transmittance from the final one by division, which needs the final one well inside the normal
# range of the type (float32 denormals start at 1.2e-38).
T_MIN_FLOOR = {torch.float32: 1e-20, torch.float64: 1e-200}


def validate_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                    sh_degree, backgrounds, render_mode, rasterize_mode, tile_size, near_plane=0.01,
                    defer_values: bool = False, flags=None):
    """One cheap pass over the inputs; raises ValueError naming the bad argument.

    Shapes, devices and dtypes are checked at once (:func:`check_shapes`). The value checks
    (NaN/Inf, zero quaternions, negative scales, opacities outside [0, 1], focal lengths) run as
    one kernel over all inputs on their device (:func:`ssgwarp.ops.check_values`), whose flags are
    read back with one synchronisation; with ``defer_values=True`` that read is left to the
    caller, which gets ``(flags, check)``: an int64 device tensor and the function that raises on
    its host copy (``check(flags.tolist())``, :func:`raise_for_flags`), so the read can share a
    synchronisation the caller makes anyway; ``flags``: a zeroed int64 tensor ``[N_FLAGS]`` for
    the kernel to write into (else one is made).
    """
    check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                 render_mode, rasterize_mode, tile_size, near_plane)
    from .ops import check_values

    values = check_values(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds, flags)
    if defer_values:
        return values, raise_for_flags
    raise_for_flags(values.tolist())
    return None


def raise_for_flags(flags: list) -> None:
    """Raise the ValueError of the first failed value check (``flags``: the host copy of the
    flags of :func:`ssgwarp.ops.check_values`)."""
    from .kernels.validate import FOCAL, INPUTS, NEGATIVE_SCALE, OPACITY_RANGE, ZERO_QUAT

    if not any(flags):
        return
    for slot, n in enumerate(INPUTS):
        if flags[slot]:
            raise ValueError(f"rasterization: {n} has NaN/Inf values")
    if flags[ZERO_QUAT]:
        raise ValueError("rasterization: quats has zero quaternions (rotation undefined)")
    if flags[NEGATIVE_SCALE]:
        raise ValueError("rasterization: scales has negative values (scales are linear, >= 0)")
    if flags[OPACITY_RANGE]:
        raise ValueError("rasterization: opacities must lie in [0, 1] (apply a sigmoid to logits)")
    if flags[FOCAL]:
        raise ValueError("rasterization: Ks has non-positive focal lengths")


def check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                 render_mode, rasterize_mode, tile_size, near_plane=0.01) -> None:
    """The shape, device, dtype and argument checks of :func:`validate_inputs` (host only)."""
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities,
             "colors": colors, "viewmats": viewmats, "Ks": Ks}
    if backgrounds is not None:
        named["backgrounds"] = backgrounds
    for name, t in named.items():
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"rasterization: {name} must be a torch.Tensor, got {type(t).__name__}")
    dev, dt = means.device, means.dtype
    if dt not in (torch.float32, torch.float64):
        raise ValueError(f"rasterization: means must be float32 or float64, got {dt}")
    for name, t in named.items():
        if t.device != dev:
            raise ValueError(f"rasterization: {name} is on {t.device} but means is on {dev}")
        if t.dtype != dt:
            raise ValueError(f"rasterization: {name} is {t.dtype} but means is {dt} (use one dtype)")
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterization: means must be [N, 3], got {tuple(means.shape)}")
    N = means.shape[0]
    if quats.shape != (N, 4):
        raise ValueError(f"rasterization: quats must be [N={N}, 4], got {tuple(quats.shape)}")
    if scales.shape != (N, 3):
        raise ValueError(f"rasterization: scales must be [N={N}, 3], got {tuple(scales.shape)}")
    if opacities.shape != (N,):
        raise ValueError(f"rasterization: opacities must be [N={N}], got {tuple(opacities.shape)}")
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"rasterization: viewmats must be [C, 4, 4], got {tuple(viewmats.shape)}")
    C = viewmats.shape[0]
    if Ks.shape != (C, 3, 3):
        raise ValueError(f"rasterization: Ks must be [C={C}, 3, 3], got {tuple(Ks.shape)}")
    if sh_degree is None:
        if not ((colors.ndim == 2 and colors.shape[0] == N) or (colors.ndim == 3 and colors.shape[:2] == (C, N))):
            raise ValueError(f"rasterization: colors must be [N={N}, D] or [C={C}, N, D], got {tuple(colors.shape)}")
        if colors.shape[-1] < 1:
            raise ValueError("rasterization: colors has zero channels")
    else:
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"rasterization: sh_degree must be 0..3, got {sh_degree}")
        ok = (colors.ndim == 3 and colors.shape[0] == N) or (colors.ndim == 4 and colors.shape[:2] == (C, N))
        if not ok or colors.shape[-1] != 3 or colors.shape[-2] < (sh_degree + 1) ** 2:
            raise ValueError(f"rasterization: with sh_degree={sh_degree} colors must be [N={N}, K>={(sh_degree + 1) ** 2}, 3]"
                             f" (or [C, N, K, 3]), got {tuple(colors.shape)}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"rasterization: width and height must be positive, got {width}x{height}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"rasterization: render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterization: rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")
    if not near_plane > 0:
        raise ValueError(f"rasterization: near_plane must be > 0, got {near_plane}")
    if int(tile_size) <= 0 or int(tile_size) > 64:
        raise ValueError(f"rasterization: tile_size must be in 1..64, got {tile_size}")


def rasterization(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: Optional[int] = None,
    backgrounds: Optional[Tensor] = None,
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    channel_chunk: int = 32,
    *,
    settings: Optional[RasterSettings] = None,
    deterministic: bool = False,
    validate: bool = True,
    backend: str = "auto",
):
    """Render N Gaussians into C cameras (gsplat 1.5.3 ``rasterization`` semantics, classic mode).

    Args (gsplat's): ``means [N,3]``, ``quats [N,4]`` (wxyz, any norm), ``scales [N,3]`` (linear),
        ``opacities [N]`` in [0,1], ``colors [N,D]`` / ``[C,N,D]`` or SH ``[N,K,3]`` / ``[C,N,K,3]``
        with ``sh_degree``, ``viewmats [C,4,4]`` (world-to-camera), ``Ks [C,3,3]``, ``width``,
        ``height``, ``near_plane``, ``far_plane``, ``radius_clip``, ``eps2d``, ``backgrounds [C,D]``,
        ``render_mode`` (RGB, D, ED, RGB+D, RGB+ED), ``rasterize_mode`` (classic, antialiased),
        ``tile_size`` (default: per device, :data:`DEFAULT_TILE_SIZE`: gsplat's 16 on CUDA, 8 on the
        CPU, where shorter per-tile lists are about 1.8x faster; docs/tradeoffs.md). ``packed``,
        ``sparse_grad`` and ``channel_chunk`` are accepted for compatibility; the layout is always the
        non-packed one ([C, N] per-camera arrays).
    Extra (keyword only):
        settings: :class:`RasterSettings` speed/accuracy knobs (default: gsplat's rules).
        deterministic: bit-identical gradients from run to run on CUDA (slower backward; needs
            ``tile_size <= 16``).
        validate: check inputs for NaN/Inf, bad shapes, devices, dtypes, quaternions, scales,
            opacities (one cheap pass); ``False`` skips it.
        backend: ``"warp"`` (kernels), ``"torch"`` (dense reference) or ``"auto"`` (warp).

    Returns:
        ``render_colors [C,H,W,D']``, ``render_alphas [C,H,W,1]``, ``meta`` with ``radii [C,N,2]``,
        ``means2d [C,N,2]`` (after backward its ``.grad`` is the screen-space positional gradient
        used by densification; call ``meta["means2d"].retain_grad()`` first), ``depths [C,N]``,
        ``conics [C,N,3]``, ``opacities [C,N]``, ``tiles_per_gauss``, ``isect_ids``,
        ``flatten_ids``, ``isect_offsets [C,th,tw]``, ``tile_width``, ``tile_height``,
        ``width``, ``height``, ``tile_size``, ``n_cameras``, ``settings``.
    """
    settings = (settings or _DEFAULT_SETTINGS).for_dtype(means.dtype)
    if absgrad:
        raise ValueError("rasterization: absgrad=True is not supported (use means2d.grad)")
    if tile_size is None:
        tile_size = DEFAULT_TILE_SIZE.get(means.device.type, 16)
    width, height, tile_size = int(width), int(height), int(tile_size)
    if backend == "auto":
        backend = "warp" if _warp_available() else "torch"
    if backend not in ("warp", "torch"):
        raise ValueError(f"rasterization: backend must be 'warp', 'torch' or 'auto', got {backend!r}")
    if backend == "warp":
        return _rasterize_warp(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                               far_plane, radius_clip, eps2d, sh_degree, tile_size, backgrounds, render_mode,
                               rasterize_mode, settings, deterministic, validate)
    if validate:
        validate_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                        backgrounds, render_mode, rasterize_mode, tile_size, near_plane)
    C = viewmats.shape[0]
    antialiased = rasterize_mode == "antialiased"
    from .reference import blend_reference, project_reference

    radii, means2d, depths, conics, opacs = project_reference(
        means, quats, scales, opacities, viewmats, Ks, width, height, near_plane=near_plane, far_plane=far_plane,
        radius_clip=radius_clip, eps2d=eps2d, antialiased=antialiased, settings=settings)
    if sh_degree is not None:
        from .sh import spherical_harmonics

        # inv_ex: no singularity check, so no device synchronisation per call
        campos = torch.linalg.inv_ex(viewmats).inverse[:, :3, 3]
        dirs = means[None] - campos[:, None]
        shs = colors if colors.ndim == 4 else colors[None].expand(C, -1, -1, -1)
        visible = (radii > 0).all(dim=-1)
        cols = spherical_harmonics(sh_degree, dirs, shs)
        colors = torch.where(visible[..., None], torch.clamp_min(cols + 0.5, 0.0), 0.0)
    elif colors.ndim == 2:
        colors = colors[None].expand(C, -1, -1)
    colors, backgrounds = _mode_channels(colors, depths, backgrounds, render_mode, C)
    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    meta = {
        "radii": radii, "means2d": means2d, "depths": depths, "conics": conics, "opacities": opacs,
        "tile_width": tile_width, "tile_height": tile_height, "width": width, "height": height,
        "tile_size": tile_size, "n_cameras": C, "settings": settings, "backend": backend,
    }
    render_colors, render_alphas = blend_reference(
        means2d, conics, colors, opacs, radii, depths, width, height, tile_size, backgrounds, settings)
    return _expected_depth(render_colors, render_alphas, render_mode), render_alphas, meta


def _mode_channels(colors, depths, backgrounds, render_mode, C):
    """The blended channels of a render mode: colours, depth, or colours then depth (and the
    background of each)."""
    if render_mode in ("RGB+D", "RGB+ED"):
        if colors.ndim == 2:
            colors = colors[None].expand(C, -1, -1)
        colors = torch.cat([colors, depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, torch.zeros_like(backgrounds[:, :1])], dim=-1)
    elif render_mode in ("D", "ED"):
        colors = depths[..., None]
        if backgrounds is not None:
            backgrounds = torch.zeros_like(backgrounds[:, :1])
    return colors, backgrounds


def _expected_depth(render_colors, render_alphas, render_mode):
    if render_mode in ("ED", "RGB+ED"):
        render_colors = torch.cat(
            [render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)], dim=-1)
    return render_colors


def _rasterize_warp(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
                    radius_clip, eps2d, sh_degree, tile_size, backgrounds, render_mode, rasterize_mode, settings,
                    deterministic, validate):
    """The Warp path: value checks, projection (+ tile counts, + SH colours), binning with the one
    read-back, blending (:mod:`ssgwarp.ops`)."""
    from . import ops
    from .kernels.validate import N_FLAGS

    pending = None
    if validate:
        check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                     render_mode, rasterize_mode, tile_size, near_plane)
    C, N = viewmats.shape[0], means.shape[0]
    CN = C * N
    tile_width, tile_height = -(-width // tile_size), -(-height // tile_size)
    # the projection writes each Gaussian's tile count into the head of ``scan`` (scanned there in
    # place into the intersection ends) and the value checks their flags into its tail, so the
    # intersection count and the flags come back in one read: one synchronisation per call, and
    # nothing is allocated from the inputs' values before it
    scan = torch.empty(CN + (N_FLAGS if validate else 0), dtype=torch.int64, device=means.device)
    extra = {"ends": scan[:CN]}
    if validate:
        flags = scan[CN:]
        flags.zero_()
        if CN:  # the projection runs the checks on the values it loads
            extra.update(flags=flags, colors=colors, backgrounds=backgrounds, sh=sh_degree is not None)
        else:  # nothing to project: the checks on their own
            ops.check_values(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds, flags)
        pending = (flags, raise_for_flags)
    cfg = ops._project_cfg(means.dtype, width, height, near_plane, far_plane, radius_clip, eps2d,
                           rasterize_mode == "antialiased", settings, tile_size, tile_width, tile_height, sh_degree)
    coeffs = campos = None
    if sh_degree is not None:
        # inv_ex: no singularity check, so no device synchronisation per call
        campos = torch.linalg.inv_ex(viewmats).inverse[:, :3, 3]
        coeffs = colors
    radii, means2d, depths, conics, opacs, sh_colors, counts, packed = ops._Project.apply(
        means, quats, scales, opacities, viewmats, Ks, coeffs, campos, cfg, extra)
    if sh_colors is not None:
        colors = sh_colors
    colors, backgrounds = _mode_channels(colors, depths, backgrounds, render_mode, C)
    meta = {
        "radii": radii, "means2d": means2d, "depths": depths, "conics": conics, "opacities": opacs,
        "tile_width": tile_width, "tile_height": tile_height, "width": width, "height": height,
        "tile_size": tile_size, "n_cameras": C, "settings": settings, "backend": "warp",
    }
    tiles = ops.bin_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, pending=pending, counts=counts,
                          scan=scan, keep_perm=deterministic, counts_in_scan=True)
    meta.update(tiles)
    render_colors, render_alphas = ops.blend_warp(means2d, conics, colors, opacs, backgrounds, tiles, width, height,
                                                  tile_size, settings, deterministic=deterministic, packed=packed)
    return _expected_depth(render_colors, render_alphas, render_mode), render_alphas, meta
def _warp_available() -> bool:
    try:
        from . import ops  # noqa: F401
    except ImportError:
        return False
    return True
