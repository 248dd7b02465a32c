"""Weight-free style distances: sliced Wasserstein distances between a render's and the style
image's colours (Lab) and oriented filter-bank responses on a pyramid, on the scene's pixels only.
:mod:`ssgwarp.evaluation.metrics` re-exports them."""
from __future__ import annotations

import functools
import math
from typing import Optional

import torch
import torch.nn.functional as F

from ..errors import InputError
from ..core.imaging import fit_style, pyramid_down, rgb_to_lab

Tensor = torch.Tensor


# ----------------------------------------------------------------------------------------------
# weight-free style distances: sliced Wasserstein of colours (Lab) and of filter-bank responses
# ----------------------------------------------------------------------------------------------
SW_SEED = 0                 # the projections are drawn from this seed: every machine, every run, the same
COLOR_PROJECTIONS = 64      # 3 axes + 61 random directions in Lab
TEXTURE_PROJECTIONS = 32    # per pyramid level: 8 filter axes + 24 random directions
TEXTURE_LEVELS = 4          # at most 4 filter scales: sigma = 1, 2, 4, 8 px of the image ...
TEXTURE_MAX_SCALE = 1 / 16  # ... and at most this fraction of the image's shorter side (texture, not layout)
TEXTURE_ORIENTATIONS = 4    # 0, 45, 90, 135 degrees


def projections(dim: int, count: int, seed: int = SW_SEED, device=None, dtype=torch.float64) -> Tensor:
    """``[count, dim]`` unit directions: the ``dim`` coordinate axes, then seeded Gaussian-random directions."""
    count = max(count, dim)
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    rnd = torch.randn(count - dim, dim, generator=g, dtype=torch.float64)
    d = torch.cat([torch.eye(dim, dtype=torch.float64), F.normalize(rnd, dim=1)])
    return d.to(device=device, dtype=dtype)


@functools.lru_cache(maxsize=16)
def _merged_quantiles(N: int, M: int, device: str) -> tuple[Tensor, Tensor, Tensor]:
    """Indices into sorted samples of sizes N and M, and the widths, of the intervals between the
    merged quantile breakpoints ``i/N`` and ``j/M`` (see :func:`wasserstein_1d_sorted`)."""
    tx = torch.arange(1, N + 1, dtype=torch.float64, device=device) / N
    ty = torch.arange(1, M + 1, dtype=torch.float64, device=device) / M
    t = torch.unique(torch.cat([tx, ty]))                     # sorted breakpoints, 1.0 last
    dt = torch.diff(t, prepend=t.new_zeros(1))
    mid = t - dt / 2
    return (torch.searchsorted(tx, mid).clamp_max(N - 1), torch.searchsorted(ty, mid).clamp_max(M - 1), dt)


def wasserstein_1d_sorted(xs: Tensor, ys: Tensor) -> Tensor:
    """Squared 2-Wasserstein distances ``[P]`` between 1-D empirical distributions, from sorted samples.

    ``xs [P, N]``, ``ys [P, M]`` sorted along the last axis (N and M may differ). Exact:
    ``W2^2 = int_0^1 (F^-1(t) - G^-1(t))^2 dt`` over the merged breakpoints ``i/N``, ``j/M``
    of the two step quantile functions.
    """
    N, M = xs.shape[-1], ys.shape[-1]
    if N == 0 or M == 0:
        raise InputError("sliced Wasserstein: an empty sample")
    if N == M:
        return ((xs.to(torch.float64) - ys.to(torch.float64)) ** 2).mean(-1)
    ix, iy, dt = _merged_quantiles(N, M, str(xs.device))
    d = xs[..., ix].to(torch.float64) - ys[..., iy].to(torch.float64)
    return (d * d * dt).sum(-1)


def sorted_projections(x: Tensor, num_projections: int, seed: int = SW_SEED) -> Tensor:
    """``[P, N]``: the points ``x [N, D]`` projected on the :func:`projections` directions, each row sorted."""
    if x.ndim != 2:
        raise InputError(f"sliced Wasserstein: expected points [N, D], got {tuple(x.shape)}")
    dirs = projections(x.shape[1], num_projections, seed, x.device, x.dtype)
    return (x @ dirs.T).T.sort(dim=-1).values


def sliced_wasserstein(x: Tensor, y: Tensor, num_projections: int = COLOR_PROJECTIONS, seed: int = SW_SEED,
                       y_sorted: Optional[Tensor] = None) -> Tensor:
    """Sliced 2-Wasserstein distance between point sets ``x [N, D]`` and ``y [M, D]`` (any N, M).

    ``SW = sqrt(mean_theta W2^2(<x, theta>, <y, theta>))`` over the directions of :func:`projections`
    (the D axes and seeded random ones), each 1-D distance exact (:func:`wasserstein_1d_sorted`).
    In the data's units; 0 for identical sets; for 1-D data the exact W2 (a shift by ``c`` gives ``|c|``).
    Invariant to the order of the points. ``y_sorted``: ``sorted_projections(y, ...)`` computed once
    for many ``x`` (then ``y`` is not used).
    """
    if x.ndim != 2 or (y_sorted is None and (y.ndim != 2 or x.shape[1] != y.shape[1])):
        raise InputError(f"sliced Wasserstein: expected [N, D] and [M, D], got {tuple(x.shape)}, "
                         f"{tuple(y.shape) if y is not None else None}")
    xs = sorted_projections(x, num_projections, seed)
    ys = sorted_projections(y.to(x), num_projections, seed) if y_sorted is None else y_sorted.to(xs)
    return torch.sqrt(wasserstein_1d_sorted(xs, ys).mean())


def _gaussian_derivative_bank(orientations: int = TEXTURE_ORIENTATIONS, sigma: float = 1.0,
                              dtype=torch.float32, device=None) -> Tensor:
    """``[2 * orientations, 1, k, k]`` scale-normalised first and second derivatives of a Gaussian.

    First order (edges): ``sigma * d/du G``; second order (bars, ridges): ``sigma^2 * d^2/du^2 G``,
    ``u`` the direction at angle ``pi * i / orientations``. Kernel radius ``ceil(4 sigma)``. Each
    first-order kernel sums to 0 and each second-order kernel is made to sum to 0 (a flat image
    responds with 0 exactly).
    """
    r = int(math.ceil(4 * sigma))
    ax = torch.arange(-r, r + 1, dtype=torch.float64)
    yy, xx = torch.meshgrid(ax, ax, indexing="ij")
    g = torch.exp(-(xx ** 2 + yy ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    first, second = [], []
    for i in range(orientations):
        th = math.pi * i / orientations
        u = xx * math.cos(th) + yy * math.sin(th)
        d1 = -(u / sigma ** 2) * g * sigma
        d2 = ((u ** 2 - sigma ** 2) / sigma ** 4) * g * sigma ** 2
        first.append(d1 - d1.mean())
        second.append(d2 - d2.mean())
    return torch.stack(first + second)[:, None].to(device=device, dtype=dtype)


def texture_levels(height: int, width: int, max_levels: int = TEXTURE_LEVELS) -> int:
    """Pyramid levels whose filter scale ``2^k`` px is at most ``TEXTURE_MAX_SCALE`` of the shorter side
    (at least 1, at most ``max_levels``): 4 levels from 128 px up, 3 at 64-127 px, 2 at 32-63 px.

    Coarser filters see the scene's layout (objects against the ground), not its texture: matching
    them to a style would mean moving the scene's structure, which Stage 2 must keep.
    """
    n = 1
    while n < max_levels and 2 ** n <= TEXTURE_MAX_SCALE * min(height, width):
        n += 1
    return n


def filter_responses(lightness: Tensor, levels: int = TEXTURE_LEVELS, orientations: int = TEXTURE_ORIENTATIONS,
                     mask: Optional[Tensor] = None) -> list[Tensor]:
    """Responses of the oriented derivative-of-Gaussian bank on a Gaussian pyramid.

    ``lightness [H, W]`` (Lab L). Level ``k`` is the image blurred (sigma 1, 5 taps) and halved ``k``
    times (filter scale ``2^k`` px of the input); at each level the bank of
    :func:`_gaussian_derivative_bank` (sigma 1 px, reflect padding). Returns per level
    ``[n_k, 2 * orientations]`` (pixels x filters): all ``h_k * w_k`` pixels, or with ``mask [H, W]``
    (bool) those whose pyramid cell is at least half inside the mask. Levels smaller than 8 px on a
    side, or with fewer than 16 masked pixels, are left out.
    """
    x = lightness[None, None]
    m = None if mask is None else mask.to(x.dtype)[None, None]
    bank = _gaussian_derivative_bank(orientations, 1.0, x.dtype, x.device)
    r = bank.shape[-1] // 2

    out = []
    for k in range(levels):
        h, w = x.shape[-2:]
        if min(h, w) < 8:
            break
        mode = "reflect" if min(h, w) > r else "replicate"
        resp = F.conv2d(F.pad(x, (r, r, r, r), mode=mode), bank)[0]          # [F, h, w]
        resp = resp.reshape(resp.shape[0], -1).T
        if m is not None:
            resp = resp[m.reshape(-1) >= 0.5]
            if resp.shape[0] < 16:
                break
        out.append(resp)
        if k + 1 < levels:
            x = pyramid_down(x)
            m = None if m is None else pyramid_down(m)
    return out


class StyleDistance:
    """Weight-free distances of images to one style image: colour and texture (filter bank).

    * ``color``: :func:`sliced_wasserstein` between the images' pixel colours and the style's,
      in CIE Lab (:func:`ssgwarp.core.imaging.rgb_to_lab`; Lab units, about one just-noticeable difference per unit);
    * ``texture``: per pyramid level, the sliced Wasserstein distance between the per-pixel responses
      of a fixed oriented derivative-of-Gaussian filter bank (:func:`filter_responses`, on Lab L;
      4 orientations x first/second derivative), averaged over the levels (filter scales 1, 2, 4, 8 px,
      those up to 1/16 of the shorter image side: :func:`texture_levels`).

    The style image is resized like the Gram loss's (:func:`fit_style`: shorter side = the images'
    shorter side), so filter scales mean the same in both. No learned weights, no randomness beyond
    the seeded projections: the same images give the same numbers on every machine.

    ``StyleDistance(style [Hs, Ws, 3])(images [V, H, W, 3]) -> {"color": [V], "texture": [V]}``.
    """

    def __init__(self, style: Tensor, color_projections: int = COLOR_PROJECTIONS,
                 texture_projections: int = TEXTURE_PROJECTIONS, levels: Optional[int] = None,
                 seed: int = SW_SEED) -> None:
        if style.ndim != 3 or style.shape[-1] != 3:
            raise InputError(f"StyleDistance: expected a style image [H, W, 3], got {tuple(style.shape)}")
        self.style = style.detach().float()
        self.color_projections, self.texture_projections = color_projections, texture_projections
        self.levels, self.seed = levels, seed
        self._cache: dict[tuple[int, str], tuple[Tensor, Tensor, list[Tensor]]] = {}

    def _features(self, image: Tensor, levels: int, mask: Optional[Tensor] = None) -> tuple[Tensor, list[Tensor]]:
        lab = rgb_to_lab(image.float())
        colors = lab.reshape(-1, 3) if mask is None else lab[mask]
        return colors, filter_responses(lab[..., 0], levels, mask=mask)

    def levels_for(self, height: int, width: int) -> int:
        """Pyramid levels used at this image size (``levels``, or :func:`texture_levels` when None)."""
        return self.levels if self.levels is not None else texture_levels(height, width)

    def _style_at(self, height: int, width: int, device) -> tuple[Tensor, Tensor, list[Tensor]]:
        """The style fitted to the images' scale ``[h, w, 3]`` and its sorted projections (colour; texture
        per level), cached."""
        key = (min(height, width), str(device))
        if key not in self._cache:
            s = fit_style(self.style.to(device), height, width)[0].permute(1, 2, 0)
            lab, resp = self._features(s, self.levels_for(height, width))
            self._cache[key] = (s, sorted_projections(lab, self.color_projections, self.seed),
                                [sorted_projections(r, self.texture_projections, self.seed) for r in resp])
        return self._cache[key]

    @torch.no_grad()
    def __call__(self, images: Tensor, alphas: Optional[Tensor] = None, alpha_min: float = 0.5) -> dict[str, Tensor]:
        """Distances of ``images [V, H, W, 3]`` (or one ``[H, W, 3]``) to the style.

        With ``alphas [V, H, W]`` only the scene's pixels (alpha >= ``alpha_min``) are compared: the
        background colour is not part of the scene (a view with fewer than 16 such pixels gives NaN).
        """
        if images.ndim == 3:
            images = images[None]
            alphas = None if alphas is None else alphas.reshape(1, *images.shape[1:3])
        V, H, W, _ = images.shape
        _, s_lab, s_resp = self._style_at(H, W, images.device)
        color, texture = [], []
        for v in range(V):
            mask = None if alphas is None else alphas[v].reshape(H, W).to(images.device) >= alpha_min
            if mask is not None and int(mask.sum()) < 16:
                color.append(float("nan"))
                texture.append(float("nan"))
                continue
            c, t = self._against_style(images[v], self.levels_for(H, W), s_lab, s_resp, mask)
            color.append(c)
            texture.append(t)
        return {"color": torch.tensor(color, dtype=torch.float64), "texture": torch.tensor(texture, dtype=torch.float64)}

    def _against_style(self, image: Tensor, levels: int, s_lab: Tensor, s_resp: list[Tensor],
                       mask: Optional[Tensor] = None) -> tuple[float, float]:
        lab, resp = self._features(image, levels, mask)
        color = float(sliced_wasserstein(lab, None, self.color_projections, self.seed, s_lab))
        per = [float(sliced_wasserstein(a, None, self.texture_projections, self.seed, b)) for a, b in zip(resp, s_resp)]
        return color, (sum(per) / len(per) if per else float("nan"))

    @torch.no_grad()
    def halves(self, height: int, width: int, device=None) -> dict[str, float]:
        """The distances of the style image's own halves to the whole, at the scale of ``height x width``
        images (the style fitted as for them; split across its longer side; the mean of the two halves).

        A reference for the numbers of :meth:`__call__`: a render that is literally half of the painting
        scores this, so it is about as close as a render can be expected to get (a style that is uniform
        across the canvas gives ~0, one whose halves differ gives more).
        """
        device = device if device is not None else self.style.device
        s, s_lab, s_resp = self._style_at(height, width, device)
        h, w = s.shape[:2]
        parts = [s[:, : w // 2], s[:, w // 2:]] if w >= h else [s[: h // 2], s[h // 2:]]
        d = [self._against_style(p, self.levels_for(height, width), s_lab, s_resp) for p in parts]
        return {"color": sum(c for c, _ in d) / 2, "texture": sum(t for _, t in d) / 2}

    def mean(self, images: Tensor, alphas: Optional[Tensor] = None) -> dict[str, Optional[float]]:
        """``{"color", "texture"}`` averaged over the views (views without scene pixels skipped; None if none)."""
        out = {}
        for k, v in self(images, alphas).items():
            v = v[torch.isfinite(v)]
            out[k] = float(v.mean()) if v.numel() else None
        return out


def style_distances(images: Tensor, style: Tensor, alphas: Optional[Tensor] = None) -> dict[str, Tensor]:
    """Per-view weight-free style distances of ``images [V, H, W, 3]`` to ``style [Hs, Ws, 3]``
    (see :class:`StyleDistance`; ``alphas [V, H, W]``: compare the scene's pixels only)."""
    return StyleDistance(style)(images, alphas)
