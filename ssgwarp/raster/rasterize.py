"""``ssgwarp.rasterization``: the differentiable 3DGS renderer, gsplat 1.5.3-compatible.

A gsplat user swaps the import and keeps the call. The work runs in Warp
kernels (``backend="warp"``, CPU tensors on Warp's CPU device, CUDA tensors on
CUDA, zero-copy on torch's current stream) or in the dense torch reference
(``backend="torch"``, :mod:`ssgwarp.raster.reference`, the spec).

Pipeline (one module each): projection + SH (``kernels/projection.py``,
``kernels/sh.py``) → tile binning and sort (``kernels/binning.py``) → blending
(``kernels/blend_forward.py``, ``kernels/blend_backward.py``), the per-pixel
rule shared by both in ``kernels/pixel.py``.
"""
from __future__ import annotations

import warnings
from functools import partial
from typing import Optional

import torch

from . import reference
from .settings import RasterSettings, check_shapes, raise_for_flags, resolve_arguments

try:  # the Warp path; without warp-lang (or ssgwarp.kernels) only backend="torch" is available
    from . import blend_ops, ops, sh_ops
    KERNELS_ERROR: Optional[str] = None
except ImportError as _e:  # pragma: no cover - warp-lang or ssgwarp.kernels missing
    blend_ops = ops = sh_ops = None
    KERNELS_ERROR = f"{type(_e).__name__}: {_e}"

# backend="auto" without the kernels: above this many (camera, Gaussian, pixel) triples the dense
# torch reference it would fall back to (O(N x pixels) time, memory in chunks) is refused with an
# error instead of a warning (a 256x256 image of 60k Gaussians is 2^32)
AUTO_FALLBACK_MAX = 1 << 30
_warned_fallback = False

Tensor = torch.Tensor
# the binning outputs that ``meta`` carries (gsplat's names)
PUBLIC_TILE_KEYS = ("tiles_per_gauss", "isect_ids", "flatten_ids", "isect_offsets")


def validate_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                    sh_degree, backgrounds, render_mode, rasterize_mode, tile_size, near_plane=0.01,
                    defer_values: bool = False, flags=None, backend: str = "warp"):
    """One cheap pass over the inputs; raises ValueError naming the bad argument.

    Shapes, devices and dtypes are checked at once (:func:`check_shapes`). The value checks
    (NaN/Inf, zero quaternions, negative scales, opacities outside [0, 1], focal lengths) run,
    with ``backend="warp"``, as one kernel over all inputs on their device
    (:func:`ssgwarp.raster.ops.check_values`), whose flags are read back with one synchronisation; with
    ``defer_values=True`` that read is left to the caller, which gets ``(flags, check)``: an int64
    device tensor and the function that raises on its host copy (``check(flags.tolist())``,
    :func:`raise_for_flags`), so the read can share a synchronisation the caller makes anyway;
    ``flags``: a zeroed int64 tensor ``[N_FLAGS]`` for the kernel to write into (else one is
    made). With ``backend="torch"`` the same checks run in torch
    (:func:`ssgwarp.raster.reference.check_values_reference`; no Warp kernel, nothing deferred).
    """
    check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                 render_mode, rasterize_mode, tile_size, near_plane)
    if backend == "torch":
        raise_for_flags(reference.check_values_reference(means, quats, scales, opacities, colors, viewmats, Ks,
                                                         backgrounds))
        return None
    values = ops.check_values(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds, flags)
    if defer_values:
        return values, raise_for_flags
    raise_for_flags(values.tolist())
    return None


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
    packed: Optional[bool] = None,
    tile_size: Optional[int] = None,
    backgrounds: Optional[Tensor] = None,
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    channel_chunk: int = 32,
    *,
    camera_model: str = "pinhole",
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
        CPU, where shorter per-tile lists are about 1.8x faster; docs/tradeoffs.md).
        ``packed``: ``True`` returns gsplat's packed meta (below); ``None`` (the default) or
        ``False`` the ``[C, N]`` layout. Unlike gsplat, whose default is ``packed=True``, the
        default is the ``[C, N]`` layout (the images are the same either way; the packed meta costs
        one device synchronisation and a few gathers). The blending itself always runs on the
        ``[C, N]`` arrays (no memory saving from ``packed``).
        ``absgrad``: after a backward, ``meta["means2d"].absgrad`` (the shape of
        ``meta["means2d"]``) holds per Gaussian and camera the sum over pixels of the absolute
        value of each pixel's gradient of the 2D mean (AbsGS; ``.grad`` is the sum of the signed
        ones, so ``absgrad >= |grad|`` entrywise, equal where every pixel pulls the same way).
        Further backward passes through the same call add to it, as to ``.grad``; with more than
        64 channels it is summed per block of 64. Off (the default): no extra work.
        ``camera_model`` (keyword): ``"pinhole"`` only; gsplat's ``"ortho"``, ``"fisheye"`` and
        ``"ftheta"`` raise a ValueError saying what to do instead. ``sparse_grad`` and
        ``channel_chunk`` are accepted for compatibility and have no effect (gradients are dense;
        the blending takes up to 64 channels per pass).
    Extra (keyword only):
        settings: :class:`RasterSettings` speed/accuracy knobs (default: gsplat's rules).
        deterministic: bit-identical gradients from run to run on CUDA (slower backward; needs
            ``tile_size <= 16``).
        validate: check inputs for NaN/Inf, bad shapes, devices, dtypes, quaternions, scales,
            opacities (one cheap pass); ``False`` skips it.
        backend: ``"warp"`` (kernels), ``"torch"`` (dense reference) or ``"auto"``: the kernels;
            where ``ssgwarp.kernels`` (or warp-lang) cannot be imported, the torch reference with a
            RuntimeWarning (once per process) for calls up to :data:`AUTO_FALLBACK_MAX` (camera,
            Gaussian, pixel) triples, and an ImportError naming the cause above it.

    Returns:
        ``render_colors [C,H,W,D']``, ``render_alphas [C,H,W,1]``, ``meta`` with ``radii [C,N,2]``,
        ``means2d [C,N,2]`` (after backward its ``.grad`` is the screen-space positional gradient
        used by densification; call ``meta["means2d"].retain_grad()`` first), ``depths [C,N]``,
        ``conics [C,N,3]``, ``opacities [C,N]``, ``tiles_per_gauss``, ``isect_ids``,
        ``flatten_ids``, ``isect_offsets [C,th,tw]``, ``tile_width``, ``tile_height``,
        ``width``, ``height``, ``tile_size``, ``n_cameras``, ``settings``.
        With ``packed=True`` (gsplat's packed layout): ``camera_ids [nnz]``, ``gaussian_ids [nnz]``
        (int64: the (camera, Gaussian) pairs with both radii > 0, camera-major, by Gaussian index),
        ``radii [nnz,2]``, ``means2d [nnz,2]`` (its ``.grad`` and ``.absgrad`` per pair),
        ``depths [nnz]``, ``conics [nnz,3]``, ``opacities [nnz]``, ``tiles_per_gauss [nnz]`` and
        ``flatten_ids`` indexing the ``nnz`` rows; ``isect_ids`` and ``isect_offsets`` as unpacked.
        Not gsplat's: no batch dimensions (no ``batch_ids``), ``sparse_grad`` has no effect.
    """
    return _rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
                          radius_clip, eps2d, sh_degree, packed, tile_size, backgrounds, render_mode, sparse_grad, absgrad,
                          rasterize_mode, channel_chunk, camera_model=camera_model, settings=settings,
                          deterministic=deterministic, validate=validate, backend=backend)


def rasterization_from_parameters(means: Tensor, quats: Tensor, log_scales: Tensor, logit_opacities: Tensor,
                                  colors: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int, **kwargs):
    """:func:`rasterization` of ``(means, quats, exp(log_scales), sigmoid(logit_opacities), ...)``: a
    scene's stored parameters, which the Warp kernels activate as they load them (and whose
    gradients they carry back through ``exp`` and the sigmoid): four torch ops and their backward
    nodes fewer per call than activating them first. The same images and gradients to float
    rounding. Keyword arguments as :func:`rasterization`'s; without the kernels (or with
    ``backend="torch"``) the activations run in torch and the call goes to :func:`rasterization`.
    Internal (the training loop's); ``rasterization`` stays gsplat's signature."""
    if ops is None or kwargs.get("backend", "auto") == "torch":
        return rasterization(means, quats, torch.exp(log_scales), torch.sigmoid(logit_opacities), colors, viewmats,
                             Ks, width, height, **kwargs)
    return _rasterization(means, quats, log_scales, logit_opacities, colors, viewmats, Ks, width, height,
                          activations=True, **kwargs)


def _rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=0.01,
                   far_plane=1e10, radius_clip=0.0, eps2d=0.3, sh_degree=None, packed=None, tile_size=None,
                   backgrounds=None, render_mode="RGB", sparse_grad=False, absgrad=False, rasterize_mode="classic",
                   channel_chunk=32, *, camera_model="pinhole", settings=None, deterministic=False, validate=True,
                   backend="auto", activations=False):
    """:func:`rasterization`'s work; ``activations``: ``scales`` and ``opacities`` are log-scales and
    logits, activated in the kernels (:func:`rasterization_from_parameters`; the Warp backend only)."""
    settings, tile_size = resolve_arguments(means, settings, tile_size, camera_model)
    width, height = int(width), int(height)
    if backend == "auto":
        backend = "warp" if ops is not None else _fallback(viewmats.shape[0] * means.shape[0] * width * height)
    if backend not in ("warp", "torch"):
        raise ValueError(f"rasterization: backend must be 'warp', 'torch' or 'auto', got {backend!r}")
    if backend == "warp":
        return _rasterize_warp(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                               far_plane, radius_clip, eps2d, sh_degree, tile_size, backgrounds, render_mode,
                               rasterize_mode, settings, deterministic, validate, packed is True, absgrad, activations)
    if activations:  # (not reached through rasterization_from_parameters)
        raise ValueError("rasterization: activations in the kernels need backend='warp'")
    return reference.render_reference(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane, radius_clip,
        eps2d, sh_degree, tile_size, backgrounds, render_mode, rasterize_mode, settings, validate, packed is True,
        absgrad)


def _fallback(triples: int) -> str:
    """``backend="auto"`` without the kernels: ``"torch"`` with a RuntimeWarning (once per process),
    or an ImportError naming the cause where the call has more than :data:`AUTO_FALLBACK_MAX`
    (camera, Gaussian, pixel) triples."""
    global _warned_fallback
    why = f"ssgwarp.kernels cannot be imported ({KERNELS_ERROR})"
    if triples > AUTO_FALLBACK_MAX:
        raise ImportError(f"rasterization: {why}; backend='auto' would fall back to the dense torch reference, "
                          f"{triples:,} (camera, Gaussian, pixel) pairs for this call: fix the install "
                          f"(pip install -e . installs warp-lang and ssgwarp.kernels), or pass backend='torch' "
                          f"to accept the slow path")
    if not _warned_fallback:
        _warned_fallback = True
        warnings.warn(f"rasterization: {why}; backend='auto' renders with the dense torch reference "
                      f"(O(N x pixels) time; calls above {AUTO_FALLBACK_MAX:,} pairs are refused). Fix the install "
                      f"or pass backend='torch' to silence this", RuntimeWarning, stacklevel=3)
    return "torch"


def _recheck(inputs, activations: bool = False) -> None:
    """The value checks as a pass of their own (:func:`ssgwarp.raster.ops.check_values`, one
    synchronisation): raises the first failed check's error, returns when all pass. ``activations``:
    the scales and opacities are log-scales and logits (checked as the scales and opacities they make)."""
    if activations:
        means, quats, scales, opacities, *rest = inputs
        inputs = (means, quats, torch.exp(scales.detach()), torch.sigmoid(opacities.detach()), *rest)
    raise_for_flags(ops.check_values(*inputs).tolist())


def _rasterize_warp(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
                    radius_clip, eps2d, sh_degree, tile_size, backgrounds, render_mode, rasterize_mode, settings,
                    deterministic, validate, packed_meta=False, absgrad=False, activations=False):
    """The Warp path: value checks, projection (+ tile counts, + SH colours), binning with the one
    read-back, blending (:mod:`ssgwarp.raster.ops`); ``packed_meta``: gsplat's packed meta
    (:func:`ssgwarp.raster.reference.pack_visible`), ``absgrad``: ``meta["means2d"].absgrad``;
    ``activations``: log-scales and logits in (:func:`rasterization_from_parameters`)."""
    if ops is None:
        raise ImportError("rasterization: backend='warp' needs warp-lang (pip install warp-lang), "
                          "or use backend='torch'")
    if validate:
        check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                     render_mode, rasterize_mode, tile_size, near_plane)
    C, N = viewmats.shape[0], means.shape[0]
    CN = C * N
    tile_width, tile_height = -(-width // tile_size), -(-height // tile_size)
    # the projection writes each Gaussian's tile count into ``scan`` (scanned there in place into
    # the intersection ends) and runs the value checks on what it loads: a Gaussian that fails one
    # marks its count, so the intersection total, read back once, also says whether all passed
    # (then a pass of the checks names the failure); nothing is allocated from the inputs' values
    # before that one synchronisation
    scan = torch.empty(CN, dtype=torch.int64, device=means.device)
    extra = {"ends": scan}
    recheck = None
    if validate:
        recheck = partial(_recheck, (means, quats, scales, opacities, colors, viewmats, Ks, backgrounds), activations)
        if 0 < CN < ops.CHECK_MAX_PAIRS:  # the projection runs the checks on the values it loads
            extra.update(check=True, colors=colors, backgrounds=backgrounds, sh=sh_degree is not None)
        else:  # nothing to project (or more pairs than the mark can count): the checks on their own
            recheck()
    cfg = ops._project_cfg(means.dtype, width, height, near_plane, far_plane, radius_clip, eps2d,
                           rasterize_mode == "antialiased", settings, tile_size, tile_width, tile_height, sh_degree,
                           activations)
    coeffs = campos = None
    if sh_degree is not None:
        if viewmats.requires_grad and torch.is_grad_enabled():
            # differentiable (camera pose gradients); inv_ex: no singularity check, so no device
            # synchronisation per call
            campos = torch.linalg.inv_ex(viewmats).inverse[:, :3, 3]
        else:  # one small kernel (torch's batched inverse costs ~0.4 ms of host time on CUDA)
            campos = sh_ops.camera_centres(viewmats)
        coeffs = colors
    means2d, depths, conics, opacs, sh_colors = ops.apply(
        ops._Project, means, quats, scales, opacities, viewmats, Ks, coeffs, campos, cfg, extra)
    radii, counts, packed = extra["radii"], extra["counts"], extra["splats"]  # (no gradient: beside the op)
    if sh_colors is not None:
        colors = sh_colors
    colors, backgrounds = reference.mode_channels(colors, depths, backgrounds, render_mode, C)
    meta = {
        "radii": radii, "means2d": means2d, "depths": depths, "conics": conics, "opacities": opacs,
        "tile_width": tile_width, "tile_height": tile_height, "width": width, "height": height,
        "tile_size": tile_size, "n_cameras": C, "settings": settings, "backend": "warp",
    }
    # the blending's outputs are made while the intersection total is on its way back (host work
    # that would otherwise wait for the GPU), and where a backward can follow, its gradient rows,
    # which the binning's key writes zero (the backward then makes and clears none)
    made = []
    D = colors.shape[-1]
    if D <= blend_ops.MAX_CHANNELS:
        def make_outputs():
            gather = blend_ops.backward_may_follow(means2d, conics, colors, opacs, backgrounds)
            rows = blend_ops.gradient_rows_size(C, N, D, means2d.requires_grad or conics.requires_grad
                                                or opacs.requires_grad, deterministic) if gather else 0
            made.append(blend_ops.blend_outputs(C, height, width, D, colors.dtype, colors.device, gather, rows))
            return made[0][4]
    else:
        make_outputs = None
    tiles = ops.bin_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, recheck=recheck, counts=counts,
                          scan=scan, keep_perm=deterministic, counts_in_scan=True,
                          threads=settings.cpu_threads, during_wait=make_outputs, tg=extra["tg"])
    # gsplat's binning outputs; the backward's internal arrays (offsets, perm, isect_ends) stay in ``tiles``
    meta.update({k: tiles[k] for k in PUBLIC_TILE_KEYS})
    sink = None
    if packed_meta:  # (gsplat's packed layout: the blending reads the means back from the packed ones)
        pmeta, means2d, visible = reference.pack_visible(radii, means2d, depths, conics, opacs)
        meta.update(pmeta)
        meta["tiles_per_gauss"], meta["flatten_ids"] = reference.pack_tiles(tiles["tiles_per_gauss"],
                                                                            tiles["flatten_ids"], visible)
        if absgrad:
            cid, gid = pmeta["camera_ids"], pmeta["gaussian_ids"]
            sink = lambda v: reference.add_absgrad(pmeta["means2d"], v[cid, gid])  # noqa: E731
    elif absgrad:
        sink = partial(reference.add_absgrad, means2d)
    render_colors, render_alphas = blend_ops.blend_warp(means2d, conics, colors, opacs, backgrounds, tiles, width, height,
                                                        tile_size, settings, deterministic=deterministic, packed=packed,
                                                        outputs=made[0] if made else None, absgrad=sink)
    return reference.expected_depth(render_colors, render_alphas, render_mode), render_alphas, meta
