"""Colour spaces and the view-consistent colour transfer of Stage 2.

**CIE Lab.** :func:`rgb_to_lab` converts sRGB in [0, 1] (D65 white) to CIE
L*a*b* (``L`` in [0, 100]); the weight-free style distances of
:mod:`ssgwarp.evaluation.metrics` compare colours there, where Euclidean distance follows
perceived colour difference better than in RGB.

**Colour transfer** (ARF, Zhang et al. 2022, §3.3): a linear map of colours
``x -> A x + b`` that gives a source colour distribution the mean and
covariance of a target one. With source mean/covariance ``(mu_s, S)`` and
target ``(mu_t, T)``::

    A = S^{-1/2} (S^{1/2} T S^{1/2})^{1/2} S^{-1/2},     b = mu_t - A mu_s

(symmetric matrix square roots by eigen-decomposition). ``A S A^T = T``
exactly, and among all linear maps doing so this ``A`` moves colours the
least (it is the optimal-transport map between Gaussians; Pitié & Kokaram
2007, "The linear Monge-Kantorovitch linear colour mapping"), so hues are
not rotated gratuitously. ``S`` is regularised by ``eps`` times its mean
eigenvalue (a flat-coloured source would otherwise have its noise amplified
without bound) and the gain of ``A`` is capped (``max_gain``).

Because the map is linear and a Gaussian scene's colour is linear in its SH
coefficients (``c(d) = C0 dc + 0.5 + sum_k B_k(d) rest_k``), applying it to
the coefficients (:func:`transform_sh`) recolours every view identically —
the transfer is view-consistent by construction: ``dc' = A dc + (A 0.5 + b
- 0.5) / C0`` and ``rest_k' = A rest_k``. On opaque pixels the render of the
recoloured scene is exactly ``A render + b`` (up to the rasterizer's clamp of
negative colours).

Per group (:func:`fit_group_transforms`): each group's transform maps that
group's pixels in the source views to its pixels in the target views; a
group with too few target pixels (absent from the key views) falls back to
the global transform, as group matching does.

**Texture** (``keep_detail``): matching the covariance scales every
lightness difference of the scene by one factor, its texture with its
layout. When a capture's lightness varies mostly at large scale (dark
background, bright leaves) and the style's mostly at small scale (pencil
hatching), the map flattens the scene's texture below both its own and the
style's (measured on fern: docs/stylize.md). With ``keep_detail`` the map's
lightness output is then stretched about each group's target mean, chroma
untouched, until the mapped renders' finest texture band
(:func:`texture_bands`: band-passes of L* at 1, 2 and 4 px; in L* because
brightening a scene also flattens its texture as seen) reaches the smaller
of the style's and the capture's own — it never adds texture the capture
did not have, nor more than the style has — and no coarser band ends above
the style's there (a style of thin lines on flat fields does not get the
scene's coarse contrast stretched). After Stage 2 the bound is the capture's
texture, not the optimised scene's (``capture`` of :func:`transfer_colors`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from ..errors import InputError
from ..core.imaging import blur5, pyramid_down, rgb_to_lab  # noqa: F401  (rgb_to_lab re-exported)
from ..core.cameras import Cameras
from ..raster.scene import SH_C0, GaussianScene

Tensor = torch.Tensor

# ----------------------------------------------------------------------------- statistics
class ColorStats:
    """Streaming mean and covariance of colours (float64 sums; add pixels in any number of batches)."""

    def __init__(self, channels: int = 3, device=None) -> None:
        self.n = 0.0
        self.s1 = torch.zeros(channels, dtype=torch.float64, device=device)
        self.s2 = torch.zeros(channels, channels, dtype=torch.float64, device=device)

    def add(self, colors: Tensor) -> "ColorStats":
        """Add colours ``[..., C]`` (flattened)."""
        x = colors.reshape(-1, colors.shape[-1]).to(self.s1.device, torch.float64)
        self.n += float(x.shape[0])
        self.s1 += x.sum(0)
        self.s2 += x.T @ x
        return self

    @property
    def mean(self) -> Tensor:
        return self.s1 / max(self.n, 1.0)

    @property
    def cov(self) -> Tensor:
        mu = self.mean
        c = self.s2 / max(self.n, 1.0) - torch.outer(mu, mu)
        return (c + c.T) / 2


def _sym_pow(m: Tensor, p: float, floor: float = 0.0) -> Tensor:
    """``m^p`` of a symmetric PSD matrix (eigenvalues clamped below at ``floor``)."""
    w, v = torch.linalg.eigh((m + m.T) / 2)
    w = w.clamp_min(floor)
    if p < 0:
        w = w.clamp_min(max(floor, 1e-300))
    return (v * w ** p) @ v.T


@dataclass
class ColorTransform:
    """``x -> A x + b`` on colour vectors (``A [3, 3]``, ``b [3]``, float64)."""

    A: Tensor
    b: Tensor

    @staticmethod
    def identity(device=None) -> "ColorTransform":
        return ColorTransform(torch.eye(3, dtype=torch.float64, device=device),
                              torch.zeros(3, dtype=torch.float64, device=device))

    def __call__(self, x: Tensor) -> Tensor:
        """Apply to colours ``[..., 3]`` (in their dtype)."""
        return x @ self.A.T.to(x) + self.b.to(x)

    def then(self, other: "ColorTransform") -> "ColorTransform":
        """The composition ``other(self(x))``."""
        return ColorTransform(other.A @ self.A, other.A @ self.b + other.b)

    def stretch_lightness(self, k: float, center: Tensor) -> "ColorTransform":
        """This map followed by a stretch of its output's luminance (:data:`LUMA`) by ``k`` about ``center``
        (a grey shift per pixel: ``y -> y + (k - 1) Y(y - center) (1, 1, 1)``; chroma unchanged)."""
        w = torch.tensor(LUMA, dtype=self.A.dtype, device=self.A.device)
        M = torch.eye(3, dtype=self.A.dtype, device=self.A.device) + (k - 1.0) * torch.ones_like(w)[:, None] * w[None]
        c = center.to(self.A)
        return ColorTransform(M @ self.A, M @ self.b + c - M @ c)

    def to_list(self) -> dict:
        return {"A": [[round(float(v), 6) for v in row] for row in self.A], "b": [round(float(v), 6) for v in self.b]}


def fit_transform(source: ColorStats, target: ColorStats, eps: float = 1e-3, max_gain: float = 4.0) -> ColorTransform:
    """The linear colour map giving ``source``'s mean and covariance those of ``target`` (see module docs).

    ``eps``: the source covariance gets ``eps * mean eigenvalue`` (+1e-12) added to its diagonal;
    ``max_gain``: eigenvalues of ``A`` are capped at this (a map that would stretch some colour
    direction more than that — a near-flat source — is limited).
    """
    if source.n < 2 or target.n < 1:
        raise InputError("colour transfer: not enough pixels to estimate colour statistics")
    S, T = source.cov, target.cov
    reg = eps * float(torch.trace(S)) / S.shape[0] + 1e-12
    S = S + reg * torch.eye(S.shape[0], dtype=S.dtype, device=S.device)
    Sh = _sym_pow(S, 0.5)
    Sih = _sym_pow(S, -0.5)
    A = Sih @ _sym_pow(Sh @ T @ Sh, 0.5) @ Sih
    A = (A + A.T) / 2
    w, v = torch.linalg.eigh(A)
    A = (v * w.clamp(0.0, max_gain)) @ v.T
    return ColorTransform(A, target.mean - A @ source.mean)


def transform_sh(scene: GaussianScene, transforms: Sequence[ColorTransform],
                 assign: Optional[Tensor] = None) -> GaussianScene:
    """Recolour a scene by colour transforms applied to its SH coefficients (see module docs).

    Args:
        scene: the scene (not modified).
        transforms: one transform (every Gaussian) or one per group.
        assign: ``[N]`` index into ``transforms`` per Gaussian (required for more than one).
    Returns: the scene with new ``sh_dc`` and ``sh_rest`` (other tensors are the same objects).
    """
    if len(transforms) == 0:
        raise InputError("transform_sh: no colour transforms")
    if len(transforms) > 1 and assign is None:
        raise InputError("transform_sh: several transforms need a per-Gaussian assignment")
    dt, dev = scene.dtype, scene.device
    A = torch.stack([t.A for t in transforms]).to(dev, dt)                 # [G, 3, 3]
    b = torch.stack([t.b for t in transforms]).to(dev, dt)                 # [G, 3]
    idx = torch.zeros(len(scene), dtype=torch.long, device=dev) if assign is None else assign.to(dev).long()
    if idx.numel() != len(scene) or (idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= len(transforms))):
        raise InputError(f"transform_sh: assignment must be [N={len(scene)}] indices < {len(transforms)}")
    Ag, bg = A[idx], b[idx]                                                # [N, 3, 3], [N, 3]
    half = torch.full((3,), 0.5, dtype=dt, device=dev)
    offset = (Ag @ half + bg - half) / SH_C0                                # [N, 3]
    dc = (Ag @ scene.sh_dc[..., None])[..., 0] + offset
    rest = None
    if scene.sh_rest is not None:
        rest = torch.einsum("nij,nkj->nki", Ag, scene.sh_rest)
    return scene.replace(sh_dc=dc, sh_rest=rest) if rest is not None else scene.replace(sh_dc=dc)


# ----------------------------------------------------------------------------- texture kept through the map
LUMA = (0.2126, 0.7152, 0.0722)   # Rec. 709 luminance weights (they sum to 1: a grey shift moves Y by its size)


DETAIL_LEVELS = 3       # texture bands of ``keep_detail``: 1, 2 and 4 px
DETAIL_MAX_GAIN = 3.0   # the lightness stretch of ``keep_detail`` is at most this
DETAIL_VIEWS = 24       # ... measured on at most this many views (:func:`detail_views`)


def texture_bands(images: Tensor, alphas: Optional[Tensor] = None, levels: int = DETAIL_LEVELS,
                  alpha_min: float = 0.5, chunk: int = 4) -> list[float]:
    """Lightness texture per scale of ``images [V, H, W, 3]`` (sRGB, clamped to [0, 1] as renders are):
    for level ``k`` of a Gaussian pyramid of CIE L* (blurred, sigma 1 px, and halved ``k`` times: scale
    ``2^k`` px), the RMS of the level minus its own blur — a band-pass of the lightness, 0 on flat or
    linearly shaded regions. With ``alphas [V, H, W]`` only pixels whose whole 5x5 neighbourhood is kept
    (alpha >= ``alpha_min``) count, so a scene's outline against the background is not texture; 0 for a
    level with no such pixel or smaller than 5 px. ``chunk`` views at a time (float64 work arrays).

    In L*, not RGB: L* compresses differences in bright regions, so brightening a scene flattens its
    texture as seen even when its RGB differences stay.
    """
    total, count = [0.0] * levels, [0] * levels
    for v in range(0, images.shape[0], max(1, int(chunk))):
        y = rgb_to_lab(images[v:v + chunk].to(torch.float64).clamp(0.0, 1.0))[..., 0][:, None]
        m = torch.ones_like(y) if alphas is None else \
            (alphas[v:v + chunk].reshape(y.shape).to(y.device) >= alpha_min).to(y.dtype)
        for k in range(levels):
            if k:
                y, m = pyramid_down(y), pyramid_down(m)
            if min(y.shape[-2:]) < 5:
                break
            band = (y - blur5(y))[blur5(m) >= 0.999]
            total[k] += float(band.pow(2).sum())
            count[k] += band.numel()
    return [(t / n) ** 0.5 if n else 0.0 for t, n in zip(total, count)]


def detail_views(n: int, most: int = DETAIL_VIEWS) -> list[int]:
    """Indices of the views ``keep_detail`` measures texture on: all ``n`` when ``n <= most``, else
    ``most`` evenly spaced ones (texture statistics need a sample of views, not all of a large capture)."""
    if n <= most:
        return list(range(n))
    return sorted({round(i * (n - 1) / (most - 1)) for i in range(most)})


def _mapped(images: Tensor, transforms: Sequence["ColorTransform"], labels: Optional[Tensor]) -> Tensor:
    """``images [V, H, W, 3]`` under one transform, or per pixel under its group's (``labels [V, H, W]``)."""
    if labels is None:
        return transforms[0](images)
    out = torch.empty_like(images)
    lab = labels.to(images.device).long()
    for g, t in enumerate(transforms):
        m = lab == g
        if bool(m.any()):
            out[m] = t(images[m])
    return out


def detail_gain(renders: Tensor, alphas: Tensor, target: Tensor, transforms: Sequence["ColorTransform"],
                centers: Sequence[Tensor], labels: Optional[Tensor] = None, reference: Optional[Sequence[float]] = None,
                tol: float = 0.01, max_gain: float = DETAIL_MAX_GAIN) -> dict:
    """The lightness stretch that keeps texture through the colour maps (see module docs).

    ``renders [V, H, W, 3]`` (surface colours, ``alphas [V, H, W]``) are what ``transforms`` apply to
    (per group with ``labels``), ``target [T, H', W', 3]`` what they match; ``centers``: each map's
    target mean (the stretch's fixed point); ``reference``: the capture's :func:`texture_bands` (default:
    the renders' own — pass the capture's when the renders are of an already stylized scene). The
    stretch ``k`` (:meth:`ColorTransform.stretch_lightness`) is found in two steps on the
    :func:`texture_bands` of the mapped renders: fixed-point steps ``k <- k * want / band0(k)`` (L* is not
    linear in ``k``) until the finest band is within ``tol`` of ``want = min(style, reference)`` there (1
    when it is there already; at most ``max_gain``); then ``k`` is lowered until no band ends above
    ``max(style, plain map)`` at that scale — a style whose texture is fine lines on flat fields does not
    get the scene's coarser contrast stretched beyond its own. Returns ``{"style", "scene", "reference",
    "mapped", "kept", "gain"}``: the bands of the target, of the renders, the reference, of the
    plain-mapped and of the stretched renders, and ``k``.
    """
    style, scene = texture_bands(target), texture_bands(renders, alphas)
    ref = list(scene if reference is None else reference)

    def bands_at(k: float) -> list[float]:
        ts = transforms if k == 1.0 else [t.stretch_lightness(k, c) for t, c in zip(transforms, centers)]
        return texture_bands(_mapped(renders, ts, labels), alphas)

    mapped = kept = bands_at(1.0)
    want = min(style[0], ref[0])
    k = 1.0
    for _ in range(12):
        if kept[0] <= 0 or kept[0] >= want * (1 - tol) or k >= max_gain:
            break
        k = min(max_gain, k * want / kept[0])
        kept = bands_at(k)
    for _ in range(12):
        over = max((b / max(s, m) for b, s, m in zip(kept, style, mapped) if max(s, m) > 0), default=1.0)
        if over <= 1 + tol or k <= 1.0:
            break
        k = max(1.0, k / over)
        kept = bands_at(k)
    return {"style": style, "scene": scene, "reference": ref, "mapped": mapped, "kept": kept, "gain": k}


# ----------------------------------------------------------------------------- fitting from images
def pixel_stats(images: Tensor, alphas: Optional[Tensor] = None, labels: Optional[Tensor] = None,
                num_groups: Optional[int] = None, alpha_min: float = 0.5
                ) -> tuple[ColorStats, dict[int, ColorStats]]:
    """Colour statistics of ``images [V, H, W, 3]``: all kept pixels and, with ``labels [V, H, W]``, per group.

    Pixels with ``alphas [V, H, W]`` below ``alpha_min`` (background) are left out when alphas are given.
    """
    keep = torch.ones(images.shape[:3], dtype=torch.bool, device=images.device)
    if alphas is not None:
        keep = alphas.reshape(images.shape[:3]).to(images.device) >= alpha_min
    total = ColorStats(device=images.device)
    groups: dict[int, ColorStats] = {}
    for v in range(images.shape[0]):
        px = images[v][keep[v]]
        total.add(px)
        if labels is not None:
            lab = labels[v].to(images.device)[keep[v]].long()
            for g in torch.unique(lab).tolist():
                groups.setdefault(int(g), ColorStats(device=images.device)).add(px[lab == g])
    return total, groups


REGION_SPREAD = 0.5   # share of the whole target's covariance in a region's colour target (region_target)


def region_target(region: ColorStats, whole: ColorStats, spread: float = REGION_SPREAD) -> ColorStats:
    """A group's colour target when it takes one region of the style: the region's mean with the covariance
    ``(1 - spread) cov(region) + spread cov(whole)``. A region of nearly one colour would otherwise map the
    group onto that colour and erase its shading (and all Stage 2 did to it: the map after the optimisation
    would flatten it again); with half the style's spread the object keeps its structure."""
    out = ColorStats(len(region.s1), region.s1.device)
    out.n = region.n
    mu = region.mean
    cov = (1 - spread) * region.cov + spread * whole.cov.to(mu)
    out.s1 = mu * region.n
    out.s2 = (cov + torch.outer(mu, mu)) * region.n
    return out


def fit_group_transforms(source: tuple[ColorStats, dict[int, ColorStats]],
                         target: tuple[ColorStats, dict[int, ColorStats]], num_groups: int,
                         min_pixels: int = 64, **kw) -> tuple[list[ColorTransform], list[str]]:
    """One transform per group ``0..num_groups-1`` and how each was obtained (``"group"`` / ``"global"``).

    A group is matched on its own when it has at least ``min_pixels`` pixels in both the source and
    the target views; otherwise it gets the global transform (all source pixels -> all target pixels):
    the same fallback as group matching (:class:`ssgwarp.stylization.matching.MatchTargets`).
    """
    glob = fit_transform(source[0], target[0], **kw)
    out, how = [], []
    for g in range(num_groups):
        s, t = source[1].get(g), target[1].get(g)
        if s is not None and t is not None and s.n >= min_pixels and t.n >= min_pixels:
            out.append(fit_transform(s, t, **kw))
            how.append("group")
        else:
            out.append(glob)
            how.append("global")
    return out, how


__all__ = ["ColorStats", "ColorTransform", "fit_transform", "transform_sh", "pixel_stats", "LUMA",
           "texture_bands", "detail_views", "detail_gain", "surface_renders", "fit_group_transforms",
           "region_target", "transfer_colors", "transfer_background", "describe_transfer"]


# ----------------------------------------------------------------------------- colour transfer
@torch.no_grad()
def surface_renders(scene: GaussianScene, cameras: Cameras) -> tuple[Tensor, Tensor]:
    """``(colours [C, H, W, 3], alphas [C, H, W])`` of ``scene`` from ``cameras``, rendered without
    background and un-premultiplied: the surface colour, which a colour map of the scene maps exactly."""
    renders, alphas = [], []
    for c in range(len(cameras)):
        col, alpha, _ = scene.render(cameras[[c]].to(scene.device))
        renders.append(col[..., :3] / alpha.clamp_min(1e-6))
        alphas.append(alpha[..., 0])
    return torch.cat(renders), torch.cat(alphas)


@torch.no_grad()
def transfer_colors(scene: GaussianScene, cameras: Cameras, target: torch.Tensor, *,
                    labels: Optional[torch.Tensor] = None,
                    target_labels: Optional[torch.Tensor] = None, assign: Optional[torch.Tensor] = None,
                    num_groups: Optional[int] = None, min_pixels: int = 64, max_gain: float = 1.3,
                    keep_detail: bool = False, capture: Optional[GaussianScene] = None,
                    target_groups: Optional[Sequence[int]] = None) -> tuple[GaussianScene, dict]:
    """ARF's colour transfer of ``scene``: its renders from ``cameras`` get the colour mean and
    covariance of ``target [V, H, W, 3]`` (the style image or the stylized key views), by one linear
    map of the SH coefficients (the functions above; view-consistent by construction).

    Per group when ``labels [C, H, W]`` (group maps of the renders), ``target_labels [V, H, W]``,
    ``assign [N]`` (each Gaussian's group) and ``num_groups`` are given: group ``g``'s Gaussians get
    the map from group ``g``'s rendered pixels to group ``g``'s target pixels, or — when ``g`` has
    fewer than ``min_pixels`` pixels on either side (absent from the key views) — the global map
    (all rendered pixels -> all target pixels). The source colours are the renders' surface colours
    (rendered without background and divided by alpha, so that the map is exact on them); pixels with
    alpha < 0.5 (background) are left out. ``target_groups [num_groups]``: group ``g`` takes the target
    pixels labelled ``target_groups[g]`` instead of ``g`` (the style image's regions assigned to the groups,
    :mod:`ssgwarp.stylization.regions`; several groups may share one; :func:`region_target`; a negative entry: the
    group's own pixels mapped to the whole target, a region that was a poor match). ``keep_detail``: stretch the maps'
    lightness so that the
    scene's fine texture is not flattened below the style's nor the capture's (:func:`detail_gain`; module
    docs); ``capture``: the unstylized scene whose texture bounds the stretch (default: ``scene`` itself;
    pass it when recolouring an optimised scene); texture is measured on at most :data:`DETAIL_VIEWS`
    evenly spaced views (:func:`detail_views`). The record's ``detail`` says by how much. Returns the
    recoloured scene and a record of what was done.
    """
    if max_gain is None or not max_gain > 0:
        raise InputError(f"transfer_colors: max_gain must be a number > 0, got {max_gain!r} (Stage 2 leaves "
                         "None to the features: ssgwarp.stylization.stage2.resolve_for makes it concrete)")
    renders, alphas = surface_renders(scene, cameras)
    grouped = labels is not None and target_labels is not None and assign is not None and num_groups
    src = pixel_stats(renders, alphas, labels if grouped else None)
    tgt = pixel_stats(target.to(scene.device), None, target_labels if grouped else None)
    if grouped and target_groups is not None:
        tgt = (tgt[0], {g: tgt[0] if int(t) < 0 else region_target(tgt[1][int(t)], tgt[0])
                        for g, t in enumerate(target_groups) if int(t) < 0 or int(t) in tgt[1]})
    glob = fit_transform(src[0], tgt[0], max_gain=max_gain)
    if grouped:
        transforms, how = fit_group_transforms(src, tgt, int(num_groups), min_pixels, max_gain=max_gain)
        centers = [tgt[1][g].mean if h == "group" else tgt[0].mean for g, h in enumerate(how)]
    else:
        transforms, how, centers = [glob], [], [tgt[0].mean]
    detail = None
    if keep_detail:
        idx = detail_views(len(cameras))
        reference = None if capture is None or capture is scene else \
            texture_bands(*surface_renders(capture, cameras[idx]))
        detail = detail_gain(renders[idx], alphas[idx], target.to(scene.device), transforms, centers,
                             labels[idx] if grouped else None, reference=reference)
        if detail["gain"] > 1.0:
            transforms = [t.stretch_lightness(detail["gain"], c) for t, c in zip(transforms, centers)]
            glob = glob.stretch_lightness(detail["gain"], tgt[0].mean) if grouped else transforms[0]
    if grouped:
        out = transform_sh(scene, transforms, assign)
        info = {"per_group": True, "groups_matched": how.count("group"), "groups_global": how.count("global"),
                "how": how, "global": glob.to_list()}
    else:
        out = transform_sh(scene, transforms)
        info = {"per_group": False, "transform": glob.to_list()}
    if detail is not None:
        info["detail"] = {k: round(v, 6) if k == "gain" else [round(x, 4) for x in v] for k, v in detail.items()}
    return out, info


def describe_transfer(info: dict, against: str) -> str:
    """One line saying what a :func:`transfer_colors` record ``info`` did, against ``against``."""
    d = info.get("detail")
    b = lambda v: "/".join(f"{x:.2f}" for x in v)   # noqa: E731
    kept = "" if d is None else (
        f"; texture (L* bands 1/2/4 px) {b(d['mapped'])} -> {b(d['kept'])} (lightness x{d['gain']:.2f}; capture "
        f"{b(d['reference'])}, style {b(d['style'])})" if d["gain"] > 1
        else f"; texture kept ({b(d['mapped'])} L*, style {b(d['style'])})")
    if info.get("per_group"):
        return (f"per group against {against}: {info['groups_matched']} groups matched on their own, "
                f"{info['groups_global']} by the global map (absent from the key views)" + kept)
    return f"one global linear map against {against}" + kept


def transfer_background(background: Sequence[float], info: dict) -> list[float]:
    """The background colour under the global map of a :func:`transfer_colors` record ``info``
    (``A bg + b``, clamped to [0, 1]): with it, the render of the recoloured scene is the colour map
    of the original render on every pixel, background included (compositing is affine in colour; up to
    the clamp and, per group, where the group maps differ from the global one)."""
    t = info.get("transform") or info["global"]
    A = torch.tensor(t["A"], dtype=torch.float64)
    b = torch.tensor(t["b"], dtype=torch.float64)
    bg = torch.tensor([float(v) for v in background[:3]], dtype=torch.float64)
    return [float(v) for v in (A @ bg + b).clamp(0.0, 1.0)]
