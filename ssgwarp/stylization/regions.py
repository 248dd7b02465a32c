"""Groups without Stage 1: the style image cut into regions, and each scene group given one of them.

Without the diffusion weights there are no stylized key views whose pixels carry group ids, so per-group
matching has nothing to match a group against. Here the style image itself is segmented
(:func:`segment_style`: k-means on smoothed Lab colour and local lightness contrast, seeded, so the
same image always gives the same regions), and the scene's groups are mapped onto the regions by
optimal transport on their statistics (:func:`assign_groups`): each group and each region is described
by its mean lightness, chroma and local contrast, standardized within its own set (so the *order* of
the scene's groups — the darkest, the most textured — is what is matched, not absolute colours, which
the colour transfer changes anyway), weighted by its share of pixels, and an entropic transport plan
(Sinkhorn) between the two sets gives each group the region that receives most of its mass. Large groups
spread their mass over the regions in proportion to the regions' sizes, so the style's main parts are
all used. Stage 2 then matches group ``g``'s features (and colours) against region ``region[g]``
only (:meth:`ssgwarp.stylization.matching.SlicedTargets.for_regions`, :func:`ssgwarp.stylization.color.transfer_colors`'s
``target_groups``): each instance takes its own part of the style and group boundaries stay crisp.

A region can be a poor match for its group: a large group given a small or atypical region makes the whole view
look like that part of the painting, farther from the style than the unstylized scene (measured: issue 62). So the
assignment can be checked before it is used (``--region-check``; :func:`fall_back_poor_matches`): the view it would give is predicted as
the mixture of the regions' pixels in proportion to their groups' shares of the views, and scored against the whole
style with the weight-free colour and texture distances (:class:`ssgwarp.evaluation.style_distance.StyleDistance`'s
measures; a region's colours as the colour transfer gives them: its mean with part of the whole style's spread).
While that mixture is farther from the style than half of the style image is from the whole (a render
that were a piece of the painting), the group whose switch to the whole style brings the mixture closest falls
back to global matching (region ``-1``: Stage 2 and the colour transfer then match it against the whole style).
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from ..core.imaging import rgb_to_lab
from ..errors import InputError
from ..evaluation.style_distance import filter_responses, sliced_wasserstein, texture_levels
from .color import REGION_SPREAD

MAX_REGIONS = 6        # a style image rarely has more parts than this that read as distinct
KMEANS_ITERS = 25
SINKHORN_EPS = 0.05
SINKHORN_ITERS = 300


def _blur(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Box blur of ``x [C, H, W]`` (replicate edges)."""
    k = 2 * radius + 1
    return F.avg_pool2d(F.pad(x[None], (radius,) * 4, mode="replicate"), k, stride=1)[0]


def pixel_descriptors(image: torch.Tensor, radius: Optional[int] = None) -> torch.Tensor:
    """``[H, W, 5]`` per-pixel descriptors of ``image [H, W, 3]`` in [0, 1]: Lab colour blurred over a
    ``2 radius + 1`` window (a, b halved: lightness separates parts of a painting more than hue does)
    and the local standard deviation of L (contrast: strokes, patterns), and its blurred gradient
    magnitude. ``radius`` defaults to 1/40 of the shorter side (at least 1)."""
    if image.ndim != 3 or image.shape[-1] != 3:
        raise InputError(f"pixel_descriptors: expected an image [H, W, 3], got {tuple(image.shape)}")
    H, W = image.shape[:2]
    r = max(1, min(H, W) // 40) if radius is None else int(radius)
    lab = rgb_to_lab(image.float().clamp(0, 1)).permute(2, 0, 1)          # [3, H, W]
    mean = _blur(lab, r)
    std = (_blur(lab[:1] ** 2, r) - mean[:1] ** 2).clamp_min(0).sqrt()
    gy, gx = torch.gradient(lab[0])
    grad = _blur(torch.sqrt(gx ** 2 + gy ** 2)[None], r)
    return torch.cat([mean[:1], mean[1:] * 0.5, std, grad]).permute(1, 2, 0)


def kmeans(x: torch.Tensor, k: int, seed: int = 0, iters: int = KMEANS_ITERS) -> tuple[torch.Tensor, torch.Tensor]:
    """k-means of the rows of ``x [N, D]`` (k-means++ seeding from a seeded CPU generator): ``(labels [N], centers
    [k, D])``. Deterministic for a seed; fewer distinct rows than ``k`` give duplicate (empty) centres."""
    if x.ndim != 2 or x.shape[0] == 0 or k < 1:
        raise InputError(f"kmeans: expected points [N, D] with N >= 1 and k >= 1, got {tuple(x.shape)}, k={k}")
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    x = x.float()
    centers = x[torch.randint(x.shape[0], (1,), generator=g)]
    for _ in range(1, k):
        d = torch.cdist(x, centers).min(1).values ** 2
        p = d / d.sum() if float(d.sum()) > 0 else torch.full_like(d, 1.0 / len(d))
        centers = torch.cat([centers, x[torch.multinomial(p.cpu(), 1, generator=g).to(x.device)]])
    labels = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
    for _ in range(iters):
        labels = torch.cdist(x, centers).argmin(1)
        new = torch.zeros_like(centers).index_add_(0, labels, x)
        counts = torch.bincount(labels, minlength=k).to(x.dtype)[:, None]
        new = torch.where(counts > 0, new / counts.clamp_min(1), centers)
        if torch.allclose(new, centers):
            break
        centers = new
    return labels, centers


def segment_style(style: torch.Tensor, regions: int, seed: int = 0, max_pixels: int = 65536) -> torch.Tensor:
    """``[H, W]`` region ids ``0..regions-1`` of the style image ``style [H, W, 3]``: k-means of
    :func:`pixel_descriptors` (each standardized), fitted on at most ``max_pixels`` evenly strided pixels
    and applied to all; ids ordered by region size, largest first (empty ones are dropped, so fewer
    ids may come back)."""
    if regions < 1:
        raise InputError(f"segment_style: regions must be >= 1, got {regions}")
    d = pixel_descriptors(style)
    H, W, D = d.shape
    flat = d.reshape(-1, D)
    flat = (flat - flat.mean(0)) / flat.std(0).clamp_min(1e-6)
    step = max(1, flat.shape[0] // max_pixels)
    _, centers = kmeans(flat[::step], regions, seed)
    lab = torch.cdist(flat, centers).argmin(1)
    counts = torch.bincount(lab, minlength=len(centers))
    order = [int(i) for i in torch.argsort(counts, descending=True, stable=True) if counts[i] > 0]
    remap = torch.full((len(centers),), -1, dtype=torch.long, device=lab.device)
    remap[torch.tensor(order, device=lab.device)] = torch.arange(len(order), device=lab.device)
    return remap[lab].reshape(H, W)


def label_stats(images: torch.Tensor, labels: torch.Tensor, count: int,
                keep: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per label ``0..count-1``: ``(stats [count, 3], mass [count])`` of ``images [V, H, W, 3]`` with
    ``labels [V, H, W]`` (pixels with ``keep`` False left out): mean lightness, mean chroma and mean local
    contrast (:func:`pixel_descriptors`), and the label's share of the kept pixels."""
    stats = torch.zeros(count, 3, dtype=torch.float64)
    mass = torch.zeros(count, dtype=torch.float64)
    for v in range(images.shape[0]):
        d = pixel_descriptors(images[v]).double().cpu()
        desc = torch.stack([d[..., 0], d[..., 1:3].norm(dim=-1), d[..., 3]], -1).reshape(-1, 3)
        lab = labels[v].reshape(-1).long().cpu()
        ok = (lab >= 0) & (lab < count)
        if keep is not None:
            ok &= keep[v].reshape(-1).cpu().bool()
        stats.index_add_(0, lab[ok], desc[ok])
        mass += torch.bincount(lab[ok], minlength=count).double()
    stats = stats / mass.clamp_min(1)[:, None]
    return stats, mass / mass.sum().clamp_min(1)


def _standardize(stats: torch.Tensor, mass: torch.Tensor) -> torch.Tensor:
    w = mass / mass.sum().clamp_min(1e-12)
    mu = (stats * w[:, None]).sum(0)
    sd = ((stats - mu) ** 2 * w[:, None]).sum(0).sqrt().clamp_min(1e-6)
    return (stats - mu) / sd


def sinkhorn(cost: torch.Tensor, a: torch.Tensor, b: torch.Tensor, eps: float = SINKHORN_EPS,
             iters: int = SINKHORN_ITERS) -> torch.Tensor:
    """Entropic optimal transport plan ``[n, m]`` between the weights ``a [n]`` and ``b [m]`` (each summing
    to 1) for ``cost [n, m]`` (log-domain Sinkhorn, ``eps`` relative to the cost's mean)."""
    cost = cost.double()
    e = eps * float(cost.mean().clamp_min(1e-12))
    la, lb = a.double().clamp_min(1e-300).log(), b.double().clamp_min(1e-300).log()
    f = torch.zeros_like(la)
    g = torch.zeros_like(lb)
    for _ in range(iters):
        f = e * (la - torch.logsumexp((g[None, :] - cost) / e, dim=1))
        g = e * (lb - torch.logsumexp((f[:, None] - cost) / e, dim=0))
    return torch.exp((f[:, None] + g[None, :] - cost) / e)


def assign_groups(group_stats: torch.Tensor, group_mass: torch.Tensor, region_stats: torch.Tensor,
                  region_mass: torch.Tensor, weights: tuple[float, ...] = (2.0, 1.0, 1.0)) -> torch.Tensor:
    """``[G]`` the region of each group: the arg-max of the group's row of the transport plan between the
    groups (``group_mass``, stats standardized) and the regions (``region_mass``), cost the weighted squared
    difference of the standardized statistics (lightness weighted ``weights[0]``). Groups without pixels
    (mass 0) get the largest region."""
    if group_stats.shape[1] != region_stats.shape[1] or group_stats.shape[1] != len(weights):
        raise InputError(f"assign_groups: statistics of different sizes {tuple(group_stats.shape)}, "
                         f"{tuple(region_stats.shape)}, weights {len(weights)}")
    present = group_mass > 0
    out = torch.full((group_stats.shape[0],), int(torch.argmax(region_mass)), dtype=torch.long)
    if not bool(present.any()):
        return out
    gs = _standardize(group_stats[present].double(), group_mass[present].double())
    rs = _standardize(region_stats.double(), region_mass.double())
    w = torch.tensor(weights, dtype=torch.float64)
    cost = (((gs[:, None, :] - rs[None, :, :]) ** 2) * w).sum(-1)
    a = group_mass[present].double() / group_mass[present].sum()
    b = region_mass.double() / region_mass.sum()
    plan = sinkhorn(cost, a, b)
    out[present] = plan.argmax(1)
    return out


MIXTURE_SAMPLES = 4096   # pixels drawn for the predicted view (fall_back_poor_matches)
GLOBAL = -1              # the region of a group that falls back to the whole style


def _region_features(style: torch.Tensor, labels: torch.Tensor, count: int) -> tuple[list, list]:
    """Per label ``0..count-1`` and last the whole image (index ``count``): Lab colours ``[n, 3]`` and texture
    responses per pyramid level (as :class:`~ssgwarp.evaluation.style_distance.StyleDistance` takes them)."""
    lab = rgb_to_lab(style.float().clamp(0, 1)).double()
    levels = texture_levels(*style.shape[:2])
    cols, tex = [], []
    for r in list(range(count)) + [None]:
        mask = None if r is None else labels == r
        cols.append(lab.reshape(-1, 3) if mask is None else lab[mask])
        tex.append(filter_responses(lab[..., 0], levels, mask=mask))
    return cols, tex


def _draw(x: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    """``n`` rows of ``x`` spread evenly over a seeded permutation (with repeats when ``n`` > rows)."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    perm = torch.randperm(len(x), generator=g).to(x.device)
    return x[perm[(torch.arange(n, device=x.device) * len(x)) // max(n, 1) % len(x)]]


def _counts(weights: list[float], n: int) -> list[int]:
    """``n`` split in proportion to ``weights`` (largest remainders: the counts sum to ``n``)."""
    raw = [w * n / sum(weights) for w in weights]
    out = [int(x) for x in raw]
    for i in sorted(range(len(raw)), key=lambda i: out[i] - raw[i])[: n - sum(out)]:
        out[i] += 1
    return out


def _distance(parts: list[tuple[torch.Tensor, int]], whole: torch.Tensor, projections: int, seed: int) -> float:
    """Sliced Wasserstein distance between ``MIXTURE_SAMPLES`` rows drawn from ``parts`` (rows, count) and as many
    drawn from ``whole`` (equal sizes: the exact sorted-sample comparison)."""
    mix = torch.cat([_draw(x, n, seed) for x, n in parts if n > 0])
    return float(sliced_wasserstein(mix, _draw(whole, len(mix), seed + 1), projections))


def mixture_distance(cols: list, tex: list, region: list[int], mass: list[float], seed: int = 0) -> tuple[float, float]:
    """``(colour, texture)`` distance to the whole style (the last entry of ``cols`` / ``tex``) of the view
    predicted for groups of shares ``mass`` taking the regions ``region`` (:data:`GLOBAL`: the whole style)."""
    pick = [(len(cols) - 1 if r == GLOBAL else r, m) for r, m in zip(region, mass) if m > 0]
    n = _counts([m for _, m in pick], MIXTURE_SAMPLES)
    # a region's colours as the colour transfer gives them (region_target): its mean, and a REGION_SPREAD share of
    # the whole style's spread around it (the whole style's pixels moved to the region's mean)
    whole = cols[-1]
    parts = [p for (r, _), k in zip(pick, n) for p in (
        [(cols[r], k)] if r == len(cols) - 1 else
        [(cols[r], k - round(k * REGION_SPREAD)), (whole - whole.mean(0) + cols[r].mean(0), round(k * REGION_SPREAD))])]
    c = _distance(parts, whole, 64, seed)
    per = [_distance([(tex[r][k], c_) for (r, _), c_ in zip(pick, n) if len(tex[r]) > k], tex[-1][k], 32, seed)
           for k in range(len(tex[-1]))]
    return c, (sum(per) / len(per) if per else 0.0)


def halves_distance(cols: list, tex: list, style_shape: tuple, seed: int = 0) -> tuple[float, float]:
    """``(colour, texture)``: the mean distance of the style's two halves (across its longer side) to the whole,
    in :func:`mixture_distance`'s terms (as :meth:`StyleDistance.halves`)."""
    H, W = style_shape[:2]
    idx = torch.arange(H * W).reshape(H, W)
    halves = [idx[:, : W // 2], idx[:, W // 2:]] if W >= H else [idx[: H // 2], idx[H // 2:]]
    c = [_distance([(cols[-1][h.reshape(-1).to(cols[-1].device)], MIXTURE_SAMPLES)], cols[-1], 64, seed)
         for h in halves]
    # texture: the halves' responses at each level, the level's grid split the same way
    t = []
    for h in (0, 1):
        per = []
        for k, resp in enumerate(tex[-1]):
            hk, wk = (H + 2 ** k - 1) // 2 ** k, (W + 2 ** k - 1) // 2 ** k
            if hk * wk != len(resp):
                break
            grid = resp.reshape(hk, wk, -1)
            part = (grid[:, : wk // 2] if h == 0 else grid[:, wk // 2:]) if W >= H else \
                (grid[: hk // 2] if h == 0 else grid[hk // 2:])
            per.append(_distance([(part.reshape(-1, resp.shape[1]), MIXTURE_SAMPLES)], resp, 32, seed))
        t.append(sum(per) / len(per) if per else 0.0)
    return sum(c) / 2, sum(t) / 2


def fall_back_poor_matches(style: torch.Tensor, labels: torch.Tensor, region: torch.Tensor,
                           group_mass: torch.Tensor, seed: int = 0) -> tuple[torch.Tensor, dict]:
    """``(region with poor matches set to GLOBAL, record)`` (module docs): groups fall back to the whole style,
    one at a time, the one that brings the predicted view closest first, while the predicted view is farther
    from the style than its halves (colour or texture). The record holds the predicted distances before and
    after, the halves' and the groups that fell back."""
    count = int(labels.max()) + 1
    cols, tex = _region_features(style, labels, count)
    ref = halves_distance(cols, tex, tuple(style.shape), seed)
    mass = [float(m) for m in group_mass]
    out = [int(r) for r in region]

    def score(d: tuple[float, float]) -> float:
        return d[0] / max(ref[0], 1e-6) + d[1] / max(ref[1], 1e-6)

    now = mixture_distance(cols, tex, out, mass, seed)
    record = {"predicted_before": list(now), "halves": list(ref), "fell_back": []}
    while now[0] > ref[0] or now[1] > ref[1]:
        tries = {g: mixture_distance(cols, tex, out[:g] + [GLOBAL] + out[g + 1:], mass, seed)
                 for g, r in enumerate(out) if r != GLOBAL and mass[g] > 0}
        if not tries:
            break
        g = min(tries, key=lambda k: score(tries[k]))
        if score(tries[g]) >= score(now):
            break
        out[g], now = GLOBAL, tries[g]
        record["fell_back"].append(g)
    record["predicted_after"] = list(now)
    return torch.tensor(out, dtype=torch.long), record


def style_regions(style: torch.Tensor, renders: torch.Tensor, view_labels: torch.Tensor, num_groups: int,
                  alphas: Optional[torch.Tensor] = None, regions: Optional[int] = None,
                  seed: int = 0, check: bool = False) -> dict:
    """Segment ``style [H, W, 3]`` and assign the scene's groups to its regions.

    ``renders [V, H', W', 3]`` / ``view_labels [V, H', W']``: the scene's renders and group maps (training
    views), ``alphas [V, H', W']``: scene pixels (>= 0.5) only. ``regions``: how many (default
    ``min(num_groups, MAX_REGIONS)``, at least 2 when there are 2 groups or more). Returns ``{"labels":
    [H, W] region ids, "region": [num_groups] region of each group (:data:`GLOBAL` for a group whose region is
    a poor match, :func:`fall_back_poor_matches`, when ``check``), "regions": count, "group_mass", "region_mass",
    "fallback": the check's record (None without ``check``)}``."""
    if num_groups < 1:
        raise InputError("style_regions: no groups")
    k = max(1, min(num_groups, MAX_REGIONS)) if regions is None else int(regions)
    labels = segment_style(style, k, seed)
    count = int(labels.max()) + 1
    r_stats, r_mass = label_stats(style[None], labels[None], count)
    keep = None if alphas is None else alphas >= 0.5
    g_stats, g_mass = label_stats(renders, view_labels, num_groups, keep)
    region = assign_groups(g_stats, g_mass, r_stats, r_mass)
    region, record = fall_back_poor_matches(style, labels, region, g_mass, seed) if check else (region, None)
    return {"labels": labels, "region": region, "regions": count, "group_mass": g_mass, "region_mass": r_mass,
            "fallback": record}
