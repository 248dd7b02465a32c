"""Evaluation metrics: multi-view consistency, style / content losses, reconstruction quality.

Consistency (the short-/long-range protocol of the 3D style transfer papers):
a view A is warped into a view B and compared with B on the pixels both see.
Two warps are provided:

* :func:`reprojection_warp` (default, no weights): every pixel of B is lifted
  to 3D with B's rendered expected depth, projected into A and A's colour is
  sampled there (bilinear). The pixel is kept only where both renders are
  opaque (alpha >= ``alpha_min``), the point lands inside A, and the point's
  depth in A agrees with A's rendered depth within ``rel_tol`` (occlusion
  test: the surface B sees is the surface A sees). With exact geometry this is
  exact: a perfectly consistent scene gives 0.
* :func:`flow_warp`: A is forward-warped into B along an optical flow A→B by
  softmax splatting (Niklaus & Liu 2020; importance metric from brightness
  constancy), masking occlusions by a forward-backward flow check. The flow
  comes from RAFT (:class:`ssgwarp.evaluation.networks.RAFTLarge`, torchvision ``raft_large`` state-dict
  layout; weights through :mod:`ssgwarp.services.weights`) to match the published protocol, or from the
  geometry (:func:`reprojection_flow`).

Errors on the mask are :func:`masked_rmse` (images in [0, 1]) and, when LPIPS
weights are configured, masked LPIPS (:class:`ssgwarp.evaluation.networks.LPIPS`, both images multiplied by
the mask). The two networks live in :mod:`ssgwarp.evaluation.networks` (re-exported here); the pixel
geometry (:func:`pixel_centers`, :func:`unproject`, :func:`project`) in :mod:`ssgwarp.core.geometry`.

Quality: Gram-matrix style loss against the style image and feature content
loss against the unstylized renders (:func:`style_content_losses`) with any
:mod:`ssgwarp.evaluation.features` extractor; PSNR / SSIM for reconstructions
(:func:`reconstruction_quality`). :func:`style_scores` is the one definition of the
style / content numbers that ``ssgwarp stylize`` and ``ssgwarp evaluate`` report
(the same views and extractor give the same numbers; :func:`extractor_from_name`
rebuilds the extractor a run recorded).

Images are channels-last ``[H, W, C]`` float in [0, 1]; pixel centres are at
integer + 0.5 (the rasterizer's convention); cameras are world-to-camera
``viewmat [4, 4]`` and intrinsics ``K [3, 3]`` (OpenCV axes).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..errors import InputError
from .features import content_loss, gram_matrix
from ..core.geometry import pixel_centers, project, unproject
from ..core.imaging import fit_style
from ..services.losses import psnr, ssim
from .style_distance import StyleDistance

Tensor = torch.Tensor

__all__ = ["View", "WarpResult", "sample_bilinear", "reprojection_warp", "reprojection_flow", "softmax_splat",
           "flow_warp", "forward_backward_mask", "masked_rmse", "consistency_pairs", "gram_style_loss",
           "style_content_losses", "reconstruction_quality", "style_scores", "extractor_from_name"]


# ----------------------------------------------------------------------------------------------
# geometry
# ----------------------------------------------------------------------------------------------
@dataclass
class View:
    """One rendered view.

    Attributes:
        image: ``[H, W, C]`` colour in [0, 1].
        depth: ``[H, W]`` expected z-depth in camera space (the rasterizer's ``ED``).
        alpha: ``[H, W]`` accumulated opacity.
        viewmat: ``[4, 4]`` world-to-camera.
        K: ``[3, 3]`` intrinsics in pixels.
    """

    image: Tensor
    depth: Tensor
    alpha: Tensor
    viewmat: Tensor
    K: Tensor

    def __post_init__(self) -> None:
        H, W = self.image.shape[:2]
        if self.image.ndim != 3:
            raise InputError(f"View.image: expected [H, W, C], got {tuple(self.image.shape)}")
        for name in ("depth", "alpha"):
            t = getattr(self, name)
            if t.ndim == 3 and t.shape[-1] == 1:
                setattr(self, name, t[..., 0])
                t = getattr(self, name)
            if tuple(t.shape) != (H, W):
                raise InputError(f"View.{name}: expected [{H}, {W}], got {tuple(t.shape)}")


@dataclass
class WarpResult:
    """A view warped into another.

    Attributes:
        warped: ``[H_b, W_b, C]`` A's colours in B's frame (0 where unknown).
        mask: ``[H_b, W_b]`` bool, the pixels the comparison uses.
    """

    warped: Tensor
    mask: Tensor


def sample_bilinear(img: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples ``[..., C]`` of ``img [H, W, C]`` at pixel coordinates ``uv [..., 2]``.

    Pixel centres are at integer + 0.5; outside the image the border is repeated.
    """
    H, W, C = img.shape
    shape = uv.shape[:-1]
    g = uv.reshape(1, 1, -1, 2).to(img.dtype)
    grid = torch.stack([2.0 * g[..., 0] / W - 1.0, 2.0 * g[..., 1] / H - 1.0], dim=-1)
    grid = torch.nan_to_num(grid, nan=-2.0, posinf=2.0, neginf=-2.0)
    out = F.grid_sample(img.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border",
                        align_corners=False)
    return out[0, :, 0].T.reshape(*shape, C)


def _inside(uv: Tensor, height: int, width: int) -> Tensor:
    """Points whose bilinear footprint lies on real pixels (centres span [0.5, size - 0.5])."""
    eps = 1e-4
    return ((uv[..., 0] >= 0.5 - eps) & (uv[..., 0] <= width - 0.5 + eps)
            & (uv[..., 1] >= 0.5 - eps) & (uv[..., 1] <= height - 0.5 + eps))


def reprojection_warp(a: View, b: View, *, rel_tol: float = 0.02, alpha_min: float = 0.9) -> WarpResult:
    """Warp view A into view B by exact reprojection (see module docs).

    For each pixel p of B: ``X = unproject(depth_b[p])``; ``(q, z) = project(X, A)``;
    ``warped[p] = image_a(q)`` (bilinear). ``mask[p]`` holds when ``alpha_b[p] >=
    alpha_min``, ``alpha_a(q) >= alpha_min``, q lies inside A, ``z > 0`` and
    ``|z - depth_a(q)| <= rel_tol * z`` (A sees the same surface: not occluded).
    """
    Hb, Wb = b.depth.shape
    Ha, Wa = a.depth.shape
    dt = torch.float64 if a.image.dtype == torch.float64 else torch.float32
    db = b.depth.to(dt)
    X = unproject(torch.nan_to_num(db, nan=0.0, posinf=0.0, neginf=0.0), b.K, b.viewmat)
    uv, z = project(X, a.viewmat, a.K)
    warped = sample_bilinear(a.image.to(dt), uv)
    da = sample_bilinear(a.depth.to(dt)[..., None], uv)[..., 0]
    aa = sample_bilinear(a.alpha.to(dt)[..., None], uv)[..., 0]
    ok_b = torch.isfinite(db) & (db > 0) & (b.alpha.to(dt) >= alpha_min)
    ok_a = _inside(uv, Ha, Wa) & (z > 0) & (aa >= alpha_min) & torch.isfinite(da) & (da > 0)
    visible = (z - da).abs() <= rel_tol * z.abs()
    mask = ok_b & ok_a & visible
    warped = torch.where(mask[..., None], warped, torch.zeros_like(warped))
    return WarpResult(warped.to(a.image.dtype), mask)


def reprojection_flow(a: View, b: View) -> tuple[Tensor, Tensor]:
    """Exact optical flow A→B from A's depth: ``flow [H_a, W_a, 2]`` (pixels) and B-camera depth ``[H_a, W_a]``.

    ``flow[p] = project(unproject(depth_a[p]), B) - p``; NaN where the depth is unusable.
    """
    Ha, Wa = a.depth.shape
    dt = torch.float64 if a.depth.dtype == torch.float64 else torch.float32
    da = a.depth.to(dt)
    ok = torch.isfinite(da) & (da > 0)
    X = unproject(torch.where(ok, da, torch.ones_like(da)), a.K, a.viewmat)
    uv, z = project(X, b.viewmat, b.K)
    flow = uv - pixel_centers(Ha, Wa, da.device, dt)
    bad = ~ok | (z <= 0)
    flow = torch.where(bad[..., None], torch.full_like(flow, float("nan")), flow)
    return flow, z


# ----------------------------------------------------------------------------------------------
# flow-based warp: softmax splatting
# ----------------------------------------------------------------------------------------------
def softmax_splat(image: Tensor, flow: Tensor, metric: Optional[Tensor] = None,
                  valid: Optional[Tensor] = None, size: Optional[tuple[int, int]] = None) -> tuple[Tensor, Tensor]:
    """Forward-warp ``image [H, W, C]`` along ``flow [H, W, 2]`` by softmax splatting.

    Each source pixel p lands at ``p + flow[p]`` and spreads over the 4 nearest
    target pixels with bilinear weights ``b``. A target q gets
    ``sum_p exp(Z_p) b_pq image_p / sum_p exp(Z_p) b_pq`` (``Z = metric [H, W]``,
    0 when None: average splatting). Sources where ``valid [H, W]`` is False or the
    flow is not finite are dropped. Computed with the per-target maximum of Z
    subtracted, so any metric range is stable.

    Returns ``(out [H_t, W_t, C], coverage [H_t, W_t])`` where coverage is the
    total bilinear weight received (1 for a hole-free one-to-one warp) and
    ``(H_t, W_t) = size`` (default ``(H, W)``).
    """
    H, W, C = image.shape
    Ht, Wt = size if size is not None else (H, W)
    dev = image.device
    dt = torch.float64 if image.dtype == torch.float64 else torch.float32
    img = image.to(dt).reshape(H * W, C)
    fl = flow.to(dt)
    ys, xs = torch.meshgrid(torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt), indexing="ij")
    tx, ty = xs + fl[..., 0], ys + fl[..., 1]
    ok = torch.isfinite(tx) & torch.isfinite(ty)
    if valid is not None:
        ok = ok & valid.to(torch.bool)
    Z = torch.zeros(H, W, dtype=dt, device=dev) if metric is None else metric.to(dt).reshape(H, W)
    ok = ok & torch.isfinite(Z)
    tx = torch.where(ok, tx, torch.zeros_like(tx))
    ty = torch.where(ok, ty, torch.zeros_like(ty))
    x0, y0 = torch.floor(tx), torch.floor(ty)
    fx, fy = tx - x0, ty - y0
    idx_l, w_l, src_l = [], [], []
    src = torch.arange(H * W, device=dev)
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi, yi = x0 + dx, y0 + dy
        keep = (ok & (w > 0) & (xi >= 0) & (xi <= Wt - 1) & (yi >= 0) & (yi <= Ht - 1)).reshape(-1)
        idx_l.append((yi * Wt + xi).reshape(-1)[keep].long())
        w_l.append(w.reshape(-1)[keep])
        src_l.append(src[keep])
    idx, w, s = torch.cat(idx_l), torch.cat(w_l), torch.cat(src_l)
    z = Z.reshape(-1)[s]
    zmax = torch.full((Ht * Wt,), -torch.inf, dtype=dt, device=dev).scatter_reduce(0, idx, z, "amax")
    e = torch.exp(z - zmax[idx]) * w
    num = torch.zeros(Ht * Wt, C, dtype=dt, device=dev).index_add_(0, idx, e[:, None] * img[s])
    den = torch.zeros(Ht * Wt, dtype=dt, device=dev).index_add_(0, idx, e)
    cov = torch.zeros(Ht * Wt, dtype=dt, device=dev).index_add_(0, idx, w)
    out = torch.where(den[:, None] > 0, num / den.clamp_min(torch.finfo(dt).tiny)[:, None], torch.zeros_like(num))
    return out.reshape(Ht, Wt, C).to(image.dtype), cov.reshape(Ht, Wt).to(image.dtype)


def forward_backward_mask(flow_ab: Tensor, flow_ba: Tensor, alpha1: float = 0.01, alpha2: float = 0.5) -> Tensor:
    """``[H, W]`` bool: pixels of A whose flow A→B is undone by the flow B→A (not occluded).

    Criterion of Sundaram et al. (2010): ``|f + g|^2 <= alpha1 (|f|^2 + |g|^2) + alpha2``
    with ``f = flow_ab[p]`` and ``g = flow_ba(p + f)`` (bilinear).
    """
    H, W = flow_ab.shape[:2]
    uv = pixel_centers(H, W, flow_ab.device, flow_ab.dtype) + torch.nan_to_num(flow_ab)
    g = sample_bilinear(torch.nan_to_num(flow_ba), uv)
    s = flow_ab + g
    lhs = (s * s).sum(-1)
    rhs = alpha1 * ((flow_ab * flow_ab).sum(-1) + (g * g).sum(-1)) + alpha2
    Hb, Wb = flow_ba.shape[:2]
    return (lhs <= rhs) & _inside(uv, Hb, Wb) & torch.isfinite(flow_ab).all(-1)


def flow_warp(image_a: Tensor, image_b: Tensor, flow_ab: Tensor, *, flow_ba: Optional[Tensor] = None,
              alpha_a: Optional[Tensor] = None, alpha_b: Optional[Tensor] = None, alpha_min: float = 0.9,
              metric_scale: float = -20.0, min_coverage: float = 0.5) -> WarpResult:
    """Forward-warp A into B along ``flow_ab [H, W, 2]`` by softmax splatting.

    Sources: A's pixels with ``alpha_a >= alpha_min`` (when given) and, when
    ``flow_ba`` is given, passing :func:`forward_backward_mask`. Importance
    metric ``Z = metric_scale * mean_c |image_a - image_b(p + flow_ab)|`` (brightness
    constancy: the better-matching source wins where several land). Mask: B
    pixels that received at least ``min_coverage`` bilinear weight and (when
    given) ``alpha_b >= alpha_min``.
    """
    H, W = image_a.shape[:2]
    valid = torch.isfinite(flow_ab).all(-1)
    if alpha_a is not None:
        valid = valid & (alpha_a.reshape(H, W) >= alpha_min)
    if flow_ba is not None:
        valid = valid & forward_backward_mask(flow_ab, flow_ba)
    uv = pixel_centers(H, W, image_a.device, image_a.dtype) + torch.nan_to_num(flow_ab).to(image_a.dtype)
    back = sample_bilinear(image_b.to(image_a.dtype), uv)
    metric = metric_scale * (image_a - back).abs().mean(-1)
    Hb, Wb = image_b.shape[:2]
    out, cov = softmax_splat(image_a, flow_ab, metric, valid, size=(Hb, Wb))
    mask = cov >= min_coverage
    if alpha_b is not None:
        mask = mask & (alpha_b.reshape(Hb, Wb) >= alpha_min)
    out = torch.where(mask[..., None], out, torch.zeros_like(out))
    return WarpResult(out, mask)


# ----------------------------------------------------------------------------------------------
# errors and pairs
# ----------------------------------------------------------------------------------------------
def masked_rmse(a: Tensor, b: Tensor, mask: Tensor) -> float:
    """Root mean squared error of ``a, b [H, W, C]`` over the pixels of ``mask [H, W]`` (all channels).

    NaN when the mask is empty.
    """
    m = mask.to(torch.bool)
    n = int(m.sum())
    if n == 0:
        return float("nan")
    d = (a.to(torch.float64) - b.to(torch.float64))[m]
    return float(torch.sqrt((d * d).mean()))


def consistency_pairs(num_views: int, kind: str = "short", gap: int = 7,
                      max_pairs: Optional[int] = None) -> list[tuple[int, int]]:
    """View index pairs ``(a, b)`` for the consistency protocol.

    ``short``: adjacent views ``(i, i + 1)``; ``long``: ``(i, i + gap)`` (gap
    clamped to ``num_views - 1``). At most ``max_pairs`` pairs, spread evenly
    over the sequence.
    """
    if kind not in ("short", "long"):
        raise InputError(f"consistency pairs: unknown kind '{kind}' (use short or long)")
    if num_views < 2:
        return []
    step = 1 if kind == "short" else max(1, min(int(gap), num_views - 1))
    pairs = [(i, i + step) for i in range(num_views - step)]
    if max_pairs is not None and 0 < max_pairs < len(pairs):
        picks = torch.linspace(0, len(pairs) - 1, max_pairs).round().long().unique().tolist()
        pairs = [pairs[i] for i in picks]
    return pairs


# ----------------------------------------------------------------------------------------------
# style and content
# ----------------------------------------------------------------------------------------------
def gram_style_loss(feats: Sequence[Tensor], style_grams: Sequence[Tensor]) -> Tensor:
    """``[B]`` Gram style loss: mean over layers of ``mean_ij (G(f)_ij - S_ij)^2``.

    ``feats``: per layer ``[B, C, h, w]``; ``style_grams``: per layer ``[1, C, C]``
    (:func:`ssgwarp.evaluation.features.gram_matrix`, normalised by ``h*w``).
    """
    per = [((gram_matrix(f) - s) ** 2).mean(dim=(1, 2)) for f, s in zip(feats, style_grams)]
    return torch.stack(per, 0).mean(0)




@torch.no_grad()
def style_content_losses(extractor, images: Tensor, style: Optional[Tensor] = None,
                         originals: Optional[Tensor] = None, batch: int = 4) -> dict[str, Tensor]:
    """Per-view Gram style and content losses.

    Args:
        extractor: ``ssgwarp.evaluation.features`` extractor (``__call__([B,3,H,W]) -> list``).
        images: ``[V, H, W, 3]`` stylized renders.
        style: ``[H_s, W_s, 3]`` style image (resized by :func:`fit_style`) or None.
        originals: ``[V, H, W, 3]`` unstylized renders from the same cameras, or None.
    Returns:
        ``{"style": [V], "content": [V]}`` (keys present when computed).
    """
    V, H, W, _ = images.shape
    out: dict[str, list[Tensor]] = {}
    grams = None
    if style is not None:
        grams = [gram_matrix(f) for f in extractor(fit_style(style.to(images), H, W))]
    for s in range(0, V, batch):
        x = images[s:s + batch].permute(0, 3, 1, 2)
        fx = extractor(x)
        if grams is not None:
            out.setdefault("style", []).append(gram_style_loss(fx, grams).cpu())
        if originals is not None:
            fr = extractor(originals[s:s + batch].permute(0, 3, 1, 2).to(x))
            out.setdefault("content", []).append(content_loss(fx, fr).cpu())
    return {k: torch.cat(v) for k, v in out.items()}


@torch.no_grad()
def reconstruction_quality(renders: Tensor, targets: Tensor) -> dict[str, list[float]]:
    """Per-image PSNR (dB) and SSIM of ``renders`` vs ``targets`` (``[V, H, W, 3]`` in [0, 1])."""
    if renders.shape != targets.shape:
        raise InputError(f"quality: renders {tuple(renders.shape)} and targets {tuple(targets.shape)} differ in shape")
    ps, ss = [], []
    for r, t in zip(renders, targets):
        r, t = r.clamp(0, 1)[None].float(), t[None].to(r.device).float()
        ps.append(float(psnr(r, t)))
        ss.append(float(ssim(r, t)))
    return {"psnr": ps, "ssim": ss}


EMPTY_ALPHA = 0.05   # a pixel the unstylized scene leaves (nearly) empty: its render alpha below this


def empty_spread(images: Tensor, empty: Tensor, min_pixels: int = 64) -> Optional[float]:
    """Floaters, as a number: the RMS distance of ``images [V, H, W, 3]``'s colours from their median colour
    over the pixels ``empty [V, H, W]`` (bool; those the unstylized scene leaves empty). 0 when the empty
    regions stay one flat colour (the background); coloured blobs over them raise it. None with fewer than
    ``min_pixels`` empty pixels (a capture that fills the frame)."""
    px = images.float()[empty.to(images.device)]
    if px.shape[0] < min_pixels:
        return None
    med = px.median(dim=0).values
    return float(((px - med) ** 2).sum(-1).mean().sqrt())


@torch.no_grad()
def style_scores(extractor, images: Tensor, style: Optional[Tensor], originals: Optional[Tensor] = None, *,
                 alphas: Optional[Tensor] = None, original_alphas: Optional[Tensor] = None) -> dict[str, float]:
    """The style / content numbers of rendered views: the one definition ``stylize`` and ``evaluate`` share.

    ``images [V, H, W, 3]`` (stylized renders), ``style [Hs, Ws, 3]`` or None, ``originals`` the
    unstylized renders from the same cameras or None, ``alphas`` / ``original_alphas [V, H, W]``
    their render alphas (the style distances compare the scene's pixels, alpha >= 0.5); the images are
    clamped to [0, 1] first, as they are shown and saved (a colour transfer may overshoot). ``extractor``
    None: no Gram / content numbers. Returns the means over the views of ``gram_style_loss``
    (Gram matrices normalised by ``h*w``, :func:`gram_style_loss`), ``content_loss`` (absolute
    feature MSE, :func:`content_loss`), ``style_distance_color`` / ``style_distance_texture``
    (:class:`StyleDistance`) and, with ``originals``, the same of the originals (``..._original``). With
    ``original_alphas`` too: floaters over the pixels the unstylized scene leaves empty (alpha below
    :data:`EMPTY_ALPHA`): ``empty_share`` (their share of the pixels), ``empty_spread`` and
    ``empty_spread_original`` (:func:`empty_spread` of the stylized and the unstylized renders), when there
    are enough such pixels.
    """
    out: dict[str, float] = {}
    images = images.float().clamp(0, 1)              # as the renders are shown and saved
    originals = None if originals is None else originals.float().clamp(0, 1).to(images.device)
    style = None if style is None else style.float().to(images.device)
    if extractor is not None and (style is not None or originals is not None):
        after = style_content_losses(extractor, images, style, originals)
        if "style" in after:
            out["gram_style_loss"] = float(after["style"].mean())
        if "content" in after:
            out["content_loss"] = float(after["content"].mean())
        if style is not None and originals is not None:
            out["gram_style_loss_original"] = float(style_content_losses(extractor, originals, style)["style"].mean())
    if style is not None:
        dist = StyleDistance(style)
        out.update({f"style_distance_{k}": v for k, v in dist.mean(images, alphas).items()})
        if originals is not None:
            out.update({f"style_distance_{k}_original": v
                        for k, v in dist.mean(originals, original_alphas if original_alphas is not None
                                              else alphas).items()})
    if originals is not None and original_alphas is not None:
        empty = original_alphas.to(images.device) < EMPTY_ALPHA
        after, before = empty_spread(images, empty), empty_spread(originals, empty)
        if after is not None:
            out.update({"empty_share": float(empty.float().mean()), "empty_spread": after,
                        "empty_spread_original": before})
    return out


def extractor_from_name(name: str, device="cpu", *, vgg_weights=None, config=None):
    """The feature extractor whose :attr:`~ssgwarp.evaluation.features.FeatureExtractor.name` is ``name``
    (what a run recorded: ``random-multiscale:seed0,c128s2,edges``, ``vgg16:relu3_1+relu3_2``, ...).

    Raises :class:`~ssgwarp.errors.InputError` for a name it does not know, and
    :class:`~ssgwarp.errors.WeightsNotFound` for VGG16 without weights.
    """
    import re

    from .features import PyramidPatches, RandomMultiScale, RandomStrokes, load_extractor

    kind, _, spec = str(name).partition(":")
    if kind == "vgg16":
        layers = [x for x in spec.split("+") if x] or None
        return load_extractor(vgg_weights, device, layers, kind="vgg16", config=config)
    ints = lambda text: tuple(int(x) for x in text.split("-"))  # noqa: E731  ("2-4-8" -> (2, 4, 8))
    if kind == "random-multiscale":
        kw: dict = {"channels": 64, "stride": 4}
        for part in spec.split(","):
            if m := re.fullmatch(r"seed(-?\d+)", part):
                kw["seed"] = int(m.group(1))
            elif m := re.fullmatch(r"c(\d+)s(\d+)(?:p([\d-]+))?", part):
                kw["channels"], kw["stride"] = int(m.group(1)), int(m.group(2))
                if m.group(3):
                    kw["scales"] = ints(m.group(3))
            elif part == "edges":
                kw["edges"] = True
            else:
                raise InputError(f"feature extractor '{name}': unknown part '{part}'")
        ext = RandomMultiScale(**kw)
    elif kind == "patches" and (m := re.fullmatch(r"p(\d+)s([\d-]+)", spec)):
        ext = PyramidPatches(int(m.group(1)), ints(m.group(2)))
    elif kind == "random-strokes" and (m := re.fullmatch(r"seed(-?\d+),c(\d+)s(\d+)p([\d-]+)d([\d-]+)", spec)):
        ext = RandomStrokes(int(m.group(1)), int(m.group(2)), ints(m.group(4)), ints(m.group(5)),
                            stride=int(m.group(3)))
    else:
        raise InputError(f"feature extractor '{name}': not one ssgwarp makes (vgg16:..., random-multiscale:..., "
                         f"random-strokes:..., patches:...)")
    if ext.name != name:
        raise InputError(f"feature extractor '{name}': rebuilt as '{ext.name}'")
    return ext.freeze().to(device)
