"""Mask-free grouping: multi-view-consistent pseudo-masks from the reconstructed scene itself.

No pretrained segmentation model is used. The Gaussians are partitioned in 3D
by spectral clustering of a k-nearest-neighbour graph built on their position,
colour and shape. The colour is the training images' colour lifted onto each
Gaussian through its blending weights (:func:`lift_colours`), not the
Gaussian's own colour: a reconstruction's colours are noisy where Gaussians
overlap and compensate for each other, the images are not. The number of
groups K is chosen per scene by the largest
(log-)eigengap of the graph Laplacian over K = 2..cap (a graph in pieces: each
connected component is a group, further splits by the eigengap of the pooled
component spectra), and groups too small to matter are merged into their
nearest neighbour. The hard per-Gaussian labels
are then rendered into every training view through the rasterizer (one
channel per label, argmax), so every view is labelled from the same 3D
partition and the masks agree across views by construction. Pixels the scene
barely covers, or where no label dominates, are marked ``IGNORE``.

Public API:
    ClusterConfig, ClusterResult
    lift_colours(scene, cameras, images)          -> (weight [N], colour [N, 3]) of the images under each Gaussian
    gaussian_features(scene, weights, colours=)   -> [N, 9] clustering features
    significant_gaussians(scene, cameras)         -> [N] bool (opaque enough and seen)
    kmeans(x, k, generator=...)                   -> (centroids, labels, inertia)
    affinity_graph(x), spectral_embedding(w, n)   -> the graph and its Laplacian spectrum
    connected_components(w)                       -> [m] component of each node of the graph
    cluster_gaussians(scene, cameras, images=)    -> ClusterResult (labels per Gaussian, K, criterion)
    render_label_masks(scene, cameras, labels, k) -> [C, H, W] long masks (IGNORE = -1)
    pseudo_masks(scene, cameras, images=...)      -> (masks, ClusterResult)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import torch

from ..core.cameras import Cameras
from ..errors import InputError
from ..core.geometry import knn_indices
from ..raster.rendering import gaussian_sums
from ..raster.scene import GaussianScene

Tensor = torch.Tensor
IGNORE = -1


@dataclass(frozen=True)
class ClusterConfig:
    """Knobs of the mask-free path (defaults documented in docs/grouping.md).

    weights: feature weights (position, colour, shape).
    colour: "images": the colour feature is the training images' colour lifted onto the
        Gaussians (when images are given; Gaussians no view sees keep their own);
        "gaussians": the Gaussians' own degree-0 colour.
    max_groups, min_groups: the range of K the eigengap criterion considers.
    gap_floor: eigenvalues below ``gap_floor`` times the (cap+1)-th one count as
        zero in the log-eigengap.
    min_fraction: a cluster holding less than this share of the significant
        Gaussians is merged into its nearest cluster.
    min_opacity: Gaussians below this opacity do not shape the clusters (they
        still get a label by the vote).
    samples: at most this many Gaussians build the graph (dense eigensolver, O(samples^3)).
    graph_k, sigma_rank: neighbours per node and the neighbour whose distance
        sets the node's bandwidth.
    vote_k: every Gaussian takes the majority label of this many nearest sampled Gaussians.
    restarts, kmeans_iters: k-means++ restarts and Lloyd iterations on the embedding.
    alpha_min: pixels whose rendered alpha is below it are ignored.
    share_min: pixels whose dominant label holds less than this share of the
        rendered alpha are ignored (boundaries, mixtures).
    """

    weights: tuple[float, float, float] = (0.25, 1.0, 0.1)
    colour: str = "images"
    max_groups: int = 8
    min_groups: int = 2
    gap_floor: float = 0.01
    min_fraction: float = 0.02
    min_opacity: float = 0.05
    samples: int = 1500
    graph_k: int = 20
    vote_k: int = 10
    sigma_rank: int = 7
    restarts: int = 3
    kmeans_iters: int = 50
    alpha_min: float = 0.5
    share_min: float = 0.5


@dataclass
class ClusterResult:
    """What clustering decided.

    labels: ``[N]`` long, cluster id per Gaussian in ``0..num_groups-1``
        (largest cluster first).
    num_groups: the K kept.
    criterion: ``{"name": "eigengap", "eigenvalues": [...], "values": {K: log-gap},
        "chosen_k": ..., "merged": [...], "final_k": ...}``.
    """

    labels: Tensor
    num_groups: int
    criterion: dict = field(default_factory=dict)


# -- lifting image signals onto the Gaussians ---------------------------------------

def lift_colours(scene: GaussianScene, cameras: Cameras, images: Tensor, *,
                 progress: bool = False) -> tuple[Tensor, Tensor]:
    """The captured colour under each Gaussian: ``(weight [N], colour [N, 3])``.

    ``weight`` is the Gaussian's blending weight summed over all pixels of all views (0 for a
    Gaussian no view sees); ``colour`` the weight-averaged colour of ``images [C, H, W, 3]`` there
    (the Gaussian's own degree-0 colour where the weight is 0).
    """
    from ..core.progress import tqdm

    if images.shape[:3] != (len(cameras), cameras.height, cameras.width):
        raise InputError(f"lift_colours: images {tuple(images.shape)} for {len(cameras)} cameras of "
                         f"{cameras.width}x{cameras.height}")
    acc = torch.zeros(len(scene), 4, dtype=torch.float64, device=scene.device)
    for c in tqdm(range(len(cameras)), desc="lift colours", unit="view", leave=False, disable=not progress):
        img = images[c, ..., :3].to(scene.device, scene.dtype)
        acc += gaussian_sums(scene, cameras[c], torch.cat([torch.ones_like(img[..., :1]), img], -1)).double()
    w = acc[:, 0]
    seen = w > 1e-9
    col = torch.where(seen[:, None], acc[:, 1:] / w.clamp_min(1e-9)[:, None], scene.base_colors.detach().double())
    return w.to(scene.dtype), col.to(scene.dtype)


# -- features -------------------------------------------------------------------

def _rgb_to_lab(rgb: Tensor) -> Tensor:
    """``[N, 3]`` sRGB in [0, 1] → CIE Lab (kornia), L in [0, 100]."""
    import kornia

    lab = kornia.color.rgb_to_lab(rgb.clamp(0.0, 1.0).T.reshape(1, 3, -1, 1).float())
    return lab.reshape(3, -1).T.to(rgb.dtype)


def gaussian_features(scene: GaussianScene, weights: Sequence[float] = (0.25, 1.0, 0.1),
                      reference: Optional[Tensor] = None, colours: Optional[Tensor] = None) -> Tensor:
    """``[N, 9]`` features for clustering: position (3), colour (3), shape (3).

    - position: centred on the median and divided by the mean 5-95 percentile
      span of the ``reference`` Gaussians (bool ``[N]``, default all), clamped
      to [-1, 1] so far-away outliers cannot dominate;
    - colour: CIE Lab of ``colours [N, 3]`` (default the degree-0 colour), divided by 100;
    - shape: the sorted log-scales minus their median over the reference set
      (size and anisotropy).

    Each block is multiplied by its weight. All blocks are in fixed physical
    units (no per-scene whitening), so a block without structure (a
    single-coloured scene) contributes only its small real spread.
    """
    w_pos, w_col, w_shape = (float(v) for v in weights)
    ref = torch.ones(len(scene), dtype=torch.bool, device=scene.device) if reference is None else reference
    if int(ref.sum()) == 0:
        ref = torch.ones_like(ref)
    xyz = scene.means.detach()
    rx = xyz[ref]
    if rx.shape[0] > 1_000_000:   # torch.quantile's input limit; an even subsample is plenty
        rx = rx[:: math.ceil(rx.shape[0] / 1_000_000)]
    med = rx.median(dim=0).values
    if rx.shape[0] >= 2:
        q = torch.quantile(rx.float(), torch.tensor([0.05, 0.95], device=rx.device), dim=0)
        span = (q[1] - q[0]).mean().to(xyz.dtype)
    else:
        span = torch.ones((), dtype=xyz.dtype, device=xyz.device)
    span = span if float(span) > 0 else torch.ones_like(span)
    pos = ((xyz - med) / span).clamp(-1.0, 1.0)
    col = _rgb_to_lab(scene.base_colors.detach() if colours is None else colours.to(xyz)) / 100.0
    ls = scene.log_scales.detach().sort(dim=1, descending=True).values
    shape = ls - ls[ref].median(dim=0).values
    return torch.cat([w_pos * pos, w_col * col, w_shape * shape], dim=1)


def significant_gaussians(scene: GaussianScene, cameras: Optional[Cameras] = None,
                          min_opacity: float = 0.05) -> Tensor:
    """``[N]`` bool: opacity >= ``min_opacity`` and centre inside at least one camera's image."""
    keep = scene.opacities.detach() >= min_opacity
    if cameras is not None and len(cameras) > 0:
        seen = torch.zeros_like(keep)
        vm = cameras.viewmats.to(scene.device, scene.dtype)
        Ks = cameras.Ks.to(scene.device, scene.dtype)
        m = scene.means.detach()
        for c in range(len(cameras)):
            pc = m @ vm[c, :3, :3].T + vm[c, :3, 3]
            z = pc[:, 2]
            zs = z.clamp_min(1e-9)
            u = Ks[c, 0, 0] * pc[:, 0] / zs + Ks[c, 0, 2]
            v = Ks[c, 1, 1] * pc[:, 1] / zs + Ks[c, 1, 2]
            seen |= (z > 0.01) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
        keep &= seen
    if int(keep.sum()) < 2:
        # nothing passes (e.g. a freshly initialised cloud): let everything count
        keep = torch.ones_like(keep)
    return keep


# -- k-means and the graph --------------------------------------------------------

def _nearest(x: Tensor, centroids: Tensor, chunk: int = 8192) -> tuple[Tensor, Tensor]:
    """Index ``[n]`` and squared distance ``[n]`` of each row's nearest centroid."""
    idx, dist = [], []
    for s in range(0, x.shape[0], chunk):
        d = torch.cdist(x[s:s + chunk], centroids) ** 2
        v, i = d.min(dim=1)
        idx.append(i)
        dist.append(v)
    return torch.cat(idx), torch.cat(dist)


def _knn_vote(x: Tensor, ref: Tensor, ref_labels: Tensor, num_labels: int, k: int) -> Tensor:
    """``[n]`` majority label among each row's ``k`` nearest rows of ``ref`` (ties: the nearer label wins)."""
    k = max(1, min(k, ref.shape[0]))
    lab = ref_labels[knn_indices(x, ref, k)]                   # [n, k], nearest first
    votes = torch.zeros(lab.shape[0], num_labels, dtype=torch.float64, device=x.device)
    # weight 1 per vote plus a tiny rank bonus so ties go to the nearer neighbour
    w = 1.0 + 1e-3 * (k - torch.arange(k, device=x.device, dtype=torch.float64)) / k
    votes.scatter_add_(1, lab, w[None].expand_as(lab).contiguous())
    return votes.argmax(dim=1)


def kmeans(x: Tensor, k: int, *, generator: torch.Generator, iters: int = 50, restarts: int = 3,
           weights: Optional[Tensor] = None) -> tuple[Tensor, Tensor, float]:
    """Weighted k-means (k-means++ seeding, Lloyd iterations, best of ``restarts``).

    Args:
        x: ``[n, d]`` points. k: clusters (<= n). generator: a CPU generator (the
        only randomness). weights: ``[n]`` non-negative, default 1.
    Returns:
        ``(centroids [k, d], labels [n] long, inertia)`` (weighted sum of squared distances).
    """
    n = x.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"kmeans: k={k} with {n} points")
    w = torch.ones(n, dtype=x.dtype, device=x.device) if weights is None else weights.to(x.dtype)
    best = None
    for _ in range(max(1, restarts)):
        first = int(torch.multinomial(w.cpu().double(), 1, generator=generator))
        cent = x[first:first + 1].clone()
        d2 = _nearest(x, cent)[1]
        for _j in range(1, k):
            p = (w * d2).cpu().double()
            if float(p.sum()) <= 0:
                p = w.cpu().double()
            nxt = int(torch.multinomial(p, 1, generator=generator))
            cent = torch.cat([cent, x[nxt:nxt + 1]], dim=0)
            d2 = torch.minimum(d2, _nearest(x, cent[-1:])[1])
        labels = None
        for _it in range(iters):
            new_labels, d2 = _nearest(x, cent)
            if labels is not None and torch.equal(new_labels, labels):
                break
            labels = new_labels
            sums = torch.zeros_like(cent).index_add_(0, labels, x * w[:, None])
            mass = torch.zeros(k, dtype=x.dtype, device=x.device).index_add_(0, labels, w)
            empty = mass <= 0
            cent = torch.where(empty[:, None], cent, sums / mass.clamp_min(1e-12)[:, None])
            if bool(empty.any()):
                # re-seed an empty cluster at the point currently worst served
                for e in torch.nonzero(empty).flatten().tolist():
                    far = int(torch.argmax(w * d2))
                    cent[e] = x[far]
                    d2[far] = 0
        labels, d2 = _nearest(x, cent)
        inertia = float((w * d2).sum())
        if best is None or inertia < best[2]:
            best = (cent, labels, inertia)
    return best


# -- clustering the scene ---------------------------------------------------------------

def _subsample(idx: Tensor, n: int, generator: torch.Generator) -> Tensor:
    if idx.numel() <= n:
        return idx
    perm = torch.randperm(idx.numel(), generator=generator)[:n].to(idx.device)
    return idx[perm.sort().values]


def affinity_graph(x: Tensor, k: int = 10, sigma_rank: int = 7) -> Tensor:
    """``[m, m]`` symmetric kNN affinity with self-tuning bandwidths (Zelnik-Manor and Perona).

    ``W_ij = exp(-d_ij^2 / (s_i s_j))`` for j among i's ``k`` nearest points (or
    i among j's), 0 otherwise; ``s_i`` is i's distance to its ``sigma_rank``-th
    nearest point.
    """
    m = x.shape[0]
    d = torch.cdist(x, x)
    k = min(k, m - 1)
    r = min(sigma_rank, m - 1)
    srt = d.sort(dim=1).values
    sig = srt[:, r].clamp_min(1e-12)
    knn = d.topk(k + 1, dim=1, largest=False).indices[:, 1:]
    mask = torch.zeros_like(d, dtype=torch.bool)
    mask.scatter_(1, knn, True)
    mask = mask | mask.T
    w = torch.exp(-(d * d) / (sig[:, None] * sig[None, :]))
    return torch.where(mask, w, torch.zeros_like(w))


def spectral_embedding(w: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Eigenvalues ``[m]`` (ascending) of the normalised Laplacian ``I - D^-1/2 W D^-1/2`` and its first ``n`` eigenvectors ``[m, n]``."""
    deg = w.sum(dim=1).clamp_min(1e-12)
    dis = deg.rsqrt()
    lap = torch.eye(w.shape[0], dtype=w.dtype, device=w.device) - dis[:, None] * w * dis[None, :]
    evals, evecs = torch.linalg.eigh(lap)
    return evals, evecs[:, :n]


def connected_components(w: Tensor) -> Tensor:
    """``[m]`` long: the connected component of each node of the graph ``w [m, m]`` (an edge where
    ``w > 0``), numbered in the order of their smallest node index (deterministic)."""
    m = w.shape[0]
    adj = (w > 0) | (w.T > 0)
    lab = torch.arange(m, device=w.device)
    big = torch.full_like(lab, m)
    while True:
        # each node takes its neighbours' smallest label, then labels jump to their label's label
        nxt = torch.minimum(lab, torch.where(adj, lab[None, :], big[None, :]).min(dim=1).values)
        while True:
            jumped = nxt[nxt]
            if torch.equal(jumped, nxt):
                break
            nxt = jumped
        if torch.equal(nxt, lab):
            break
        lab = nxt
    return torch.unique(lab, sorted=True, return_inverse=True)[1]


def _log_gaps(evals: Tensor, lo: int, cap: int, gap_floor: float) -> dict[int, float]:
    """``{K: log((lambda_{K+1} + eps) / (lambda_K + eps))}`` for K = lo..cap (1-based eigenvalues ascending;
    eps = ``gap_floor`` times the (cap+1)-th eigenvalue)."""
    top = evals[: cap + 1].clamp_min(0.0)
    eps = max(float(top[-1]) * gap_floor, 1e-12)
    return {kk: float(torch.log((top[kk] + eps) / (top[kk - 1] + eps)))
            for kk in range(max(1, lo), cap + 1) if kk < top.numel()}


def _best(gaps: dict[int, float], default: int) -> int:
    """The K of the largest gap; ties (and all-zero gaps) go to the smaller K."""
    return max(gaps, key=lambda kk: (gaps[kk], -kk)) if gaps else default


def _row_kmeans(vecs: Tensor, k: int, config: "ClusterConfig", gen: torch.Generator) -> Tensor:
    """k-means labels of the row-normalised spectral embedding ``vecs [n, >= k]`` (0 for k == 1)."""
    if k <= 1:
        return torch.zeros(vecs.shape[0], dtype=torch.long, device=vecs.device)
    emb = vecs[:, :k]
    emb = emb / emb.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return kmeans(emb, k, generator=gen, iters=config.kmeans_iters, restarts=config.restarts)[1]


def _spectral_labels(xs: Tensor, w: Tensor, num_groups: Optional[int], cap: int, config: "ClusterConfig",
                     gen: torch.Generator, criterion: dict) -> tuple[int, Tensor]:
    """K and the labels ``[m]`` of the sampled Gaussians ``xs [m, D]`` from their graph ``w`` (records into
    ``criterion``).

    A connected graph: K by the largest log-eigengap over ``config.min_groups..cap``, k-means on the first K
    eigenvectors. A graph in several pieces (its Laplacian has one exact zero eigenvalue per piece, and the
    log-gap after an exact zero is decided by the floor alone): pieces too small to be a group (under
    ``config.min_fraction`` of the sample) take their label from the rest by a vote in feature space; each
    remaining component is a group, and K = components + j further splits, j by the largest (absolute)
    eigengap of the components' pooled spectra, the zeros included (``j = 0``: the components are the
    groups). Each split goes to the component that owns the eigenvalue, which is clustered on its own.
    """
    m = w.shape[0]
    comp = connected_components(w)
    sizes = torch.bincount(comp)
    small = sizes < max(2.0, config.min_fraction * m)
    if bool(small.all()):
        small = sizes < int(sizes.max())                  # nothing large: keep the largest piece(s)
    parts = [int(c) for c in torch.argsort(-sizes, stable=True) if not bool(small[c])]
    criterion["components"] = [int(sizes[c]) for c in parts]
    main = ~small[comp]
    frag = torch.nonzero(~main).flatten()
    criterion["fragments"] = int(frag.numel())
    if len(parts) == 1 and frag.numel() == 0:
        # connected: the log-eigengap over K = min_groups..cap
        evals, evecs = spectral_embedding(w, min(m, cap + 1))
        gaps = _log_gaps(evals, config.min_groups, cap, config.gap_floor)
        criterion.update(measure="log-eigengap", eigenvalues=[float(v) for v in evals[: cap + 1].clamp_min(0.0)],
                         values=gaps)
        k = int(num_groups) if num_groups is not None else _best(gaps, 1)
        vecs = evecs if k <= evecs.shape[1] else spectral_embedding(w, k)[1]
        return k, _row_kmeans(vecs, k, config, gen)
    nodes = [torch.nonzero(comp == c).flatten() for c in parts]
    spectra = [spectral_embedding(w[idx][:, idx], idx.numel()) for idx in nodes]
    c = len(parts)
    if c == 1:
        # one component after the fragments: the connected rule on it
        evals, evecs = spectra[0]
        capc = max(1, min(cap, nodes[0].numel() - 1))
        gaps = _log_gaps(evals, config.min_groups, capc, config.gap_floor)
        criterion.update(measure="log-eigengap", eigenvalues=[float(v) for v in evals[: capc + 1].clamp_min(0.0)],
                         values=gaps)
        k = int(num_groups) if num_groups is not None else _best(gaps, 1)
        per = [min(k, nodes[0].numel())]
    else:
        # the pooled spectrum without each component's own zero, ascending (ties by component)
        pooled = sorted((max(float(v), 0.0), i) for i, (ev, _) in enumerate(spectra) for v in ev[1: cap + 1])
        zeros_then = [0.0] + [v for v, _ in pooled]
        gaps = {c + j: zeros_then[j + 1] - zeros_then[j] for j in range(0, cap - c + 1) if j + 1 < len(zeros_then)}
        criterion.update(measure="eigengap (components pooled)",
                         eigenvalues=([0.0] * c + [v for v, _ in pooled])[: max(cap, c) + 1], values=gaps)
        k = int(num_groups) if num_groups is not None else _best(gaps, c)
        # k < c (a given K, or more components than the cap): one group per component, merged later
        per = [1] * c
        for _, i in pooled[: max(0, k - c)]:
            per[i] += 1
    lab_s = torch.full((m,), -1, dtype=torch.long, device=w.device)
    base = 0
    for idx, (_, vecs), ki in zip(nodes, spectra, per):
        lab_s[idx] = base + _row_kmeans(vecs, ki, config, gen)
        base += ki
    if frag.numel():
        ref = torch.nonzero(main).flatten()
        lab_s[frag] = _knn_vote(xs[frag], xs[ref], lab_s[ref], base, config.vote_k)
        criterion["fragments_merged"] = [{"share": float(frag.numel()) / m, "fragment": True}]
    return base, lab_s


def cluster_gaussians(scene: GaussianScene, cameras: Optional[Cameras] = None, *,
                      num_groups: Optional[int] = None, config: ClusterConfig = ClusterConfig(),
                      seed: int = 0, images: Optional[Tensor] = None, progress: bool = False) -> ClusterResult:
    """Partition the Gaussians into groups by spectral clustering (see docs/grouping.md).

    1. Draw at most ``config.samples`` significant Gaussians (opaque enough and
       seen by a camera) and build a kNN affinity graph on their features
       (:func:`gaussian_features`, :func:`affinity_graph`); with ``images`` (``[C, H, W, 3]``
       of ``cameras``) and ``config.colour == "images"`` the colour feature is the images'
       colour lifted onto the Gaussians (:func:`lift_colours`).
    2. K: given (``num_groups``), or the largest log-eigengap of the normalised graph
       Laplacian over ``K = config.min_groups..config.max_groups``; a graph in pieces: each
       connected component is a group and further splits are chosen by the eigengap of the
       components' pooled spectra (:func:`_spectral_labels`).
    3. k-means on the row-normalised first K eigenvectors (of each component) labels the sample;
       every Gaussian takes the majority label of its ``config.vote_k`` nearest
       sampled Gaussians in feature space.
    4. Unless K was given, clusters holding less than ``config.min_fraction`` of
       the significant Gaussians are merged into the nearest cluster (feature
       centroids), repeatedly.

    Labels are numbered largest cluster first. Deterministic for a seed.
    """
    n = len(scene)
    if n == 0:
        raise InputError("mask-free grouping: the scene has no Gaussians")
    gen = torch.Generator().manual_seed(int(seed))
    if config.colour not in ("images", "gaussians"):
        raise InputError(f"ClusterConfig.colour must be 'images' or 'gaussians', got {config.colour!r}")
    sig = significant_gaussians(scene, cameras, config.min_opacity)
    lifted = config.colour == "images" and images is not None and cameras is not None
    colours = lift_colours(scene, cameras, images, progress=progress)[1] if lifted else None
    feats = gaussian_features(scene, config.weights, reference=sig, colours=colours).double()
    sig_idx = torch.nonzero(sig).flatten()
    samp = _subsample(sig_idx, config.samples, gen)
    xs = feats[samp]
    m = xs.shape[0]
    criterion: dict = {"name": "eigengap", "method": "spectral clustering of a kNN graph on position, colour, shape",
                       "features": {"position": config.weights[0], "colour": config.weights[1],
                                    "shape": config.weights[2]},
                       "colour": ("the training images' colour under each Gaussian (lifted through its blending "
                                  "weights)" if lifted else "the Gaussians' own colour"),
                       "significant_gaussians": int(sig.sum()), "sampled": int(m)}
    if num_groups is not None:
        if int(num_groups) < 1:
            raise InputError(f"--groups must be >= 1, got {num_groups}")
        if int(num_groups) > m:
            raise InputError(f"--groups {num_groups}: the scene has only {m} significant Gaussians to cluster")
    cap = max(1, min(int(config.max_groups), m - 1))
    if m < 3:
        # too few Gaussians for a graph: one group each (or one group)
        k = int(num_groups) if num_groups is not None else 1
        lab_s = torch.zeros(m, dtype=torch.long, device=xs.device) if k == 1 else torch.arange(m, device=xs.device) % k
    else:
        w = affinity_graph(xs, config.graph_k, config.sigma_rank)
        k, lab_s = _spectral_labels(xs, w, num_groups, cap, config, gen, criterion)
    criterion["chosen_k"] = int(k)
    criterion["given"] = num_groups is not None
    # every Gaussian takes the majority label of its nearest sampled Gaussians in feature space
    labels = _knn_vote(feats, xs, lab_s, k, config.vote_k)
    # centroids of the clusters in feature space (for merging)
    cent = torch.zeros(k, feats.shape[1], dtype=feats.dtype, device=feats.device).index_add_(0, lab_s, xs)
    cent = cent / torch.bincount(lab_s, minlength=k).clamp_min(1)[:, None].to(cent.dtype)
    merged = list(criterion.pop("fragments_merged", []))
    # at most this many groups: the cap, or the K given (components of the graph can outnumber either)
    limit = int(num_groups) if num_groups is not None else max(1, int(config.max_groups))
    if num_groups is None or cent.shape[0] > limit:
        while cent.shape[0] > 1:
            counts = torch.bincount(labels[sig_idx], minlength=cent.shape[0]).double()
            share = counts / counts.sum().clamp_min(1)
            small = int(torch.argmin(share))
            if cent.shape[0] <= limit and (num_groups is not None or float(share[small]) >= config.min_fraction):
                break
            d = torch.cdist(cent[small:small + 1], cent)[0]
            d[small] = float("inf")
            into = int(torch.argmin(d))
            merged.append({"share": float(share[small])})
            keep = [i for i in range(cent.shape[0]) if i != small]
            remap = torch.full((cent.shape[0],), -1, dtype=torch.long, device=labels.device)
            remap[torch.tensor(keep, device=labels.device)] = torch.arange(len(keep), device=labels.device)
            remap[small] = remap[into]
            labels = remap[labels]
            lab_s = remap[lab_s]
            cent = cent[keep]
            tgt = int(remap[into])
            cent[tgt] = xs[lab_s == tgt].mean(dim=0)
    # relabel: largest (by significant Gaussians) first, ties by index
    k_final = cent.shape[0]
    counts = torch.bincount(labels[sig_idx], minlength=k_final)
    order = sorted(range(k_final), key=lambda i: (-int(counts[i]), i))
    remap = torch.empty(k_final, dtype=torch.long, device=labels.device)
    remap[torch.tensor(order, device=labels.device)] = torch.arange(k_final, device=labels.device)
    labels = remap[labels]
    criterion["merged"] = merged
    criterion["final_k"] = int(k_final)
    return ClusterResult(labels=labels, num_groups=int(k_final), criterion=criterion)


# -- rendering the labels --------------------------------------------------------------

def render_label_masks(scene: GaussianScene, cameras: Cameras, labels: Tensor, num_groups: int, *,
                       alpha_min: float = 0.5, share_min: float = 0.5, progress: bool = False) -> Tensor:
    """Render hard per-Gaussian labels into each view.

    Args:
        labels: ``[N]`` long in ``0..num_groups-1``.
    Returns:
        ``[C, H, W]`` long, on the CPU: the label whose one-hot channel dominates the
        blended colour, or ``IGNORE`` where alpha < ``alpha_min`` or the
        dominant label holds less than ``share_min`` of the alpha.
    """
    from ..core.progress import tqdm

    onehot = torch.nn.functional.one_hot(labels.to(scene.device), num_groups).to(scene.dtype)
    out = []
    with torch.no_grad():
        for c in tqdm(range(len(cameras)), desc="pseudo-masks", unit="view", disable=not progress, leave=False):
            img, alpha, _ = scene.render(cameras[c].to(scene.device), rgb=False, extra=onehot)
            top, lab = img[0].max(dim=-1)
            a = alpha[0, ..., 0]
            bad = (a < alpha_min) | (top < share_min * a.clamp_min(1e-12))
            out.append(torch.where(bad, torch.full_like(lab, IGNORE), lab).cpu())
    return torch.stack(out)


def pseudo_masks(scene: GaussianScene, cameras: Cameras, *, num_groups: Optional[int] = None,
                 config: ClusterConfig = ClusterConfig(), seed: int = 0, images: Optional[Tensor] = None,
                 progress: bool = False) -> tuple[Tensor, ClusterResult]:
    """Cluster the scene and render the labels into ``cameras``: ``(masks [C,H,W] long, ClusterResult)``.

    ``images [C, H, W, 3]``: the captured views of ``cameras`` (their colour is lifted onto the Gaussians)."""
    res = cluster_gaussians(scene, cameras, num_groups=num_groups, config=config, seed=seed, images=images,
                            progress=progress)
    masks = render_label_masks(scene, cameras, res.labels, res.num_groups, alpha_min=config.alpha_min,
                               share_min=config.share_min, progress=progress)
    valid = masks >= 0
    cover = torch.bincount(masks[valid].flatten(), minlength=res.num_groups).double()
    res.criterion["mask_pixels_labelled"] = float(valid.double().mean())
    res.criterion["mask_coverage"] = (cover / cover.sum().clamp_min(1)).tolist()
    return masks, res
