"""Group matching and the nearest-neighbour feature matching (NNFM) style loss of Stage 2.

Instance-level style transfer (IST) restricts each feature of a rendered
training view to style features of *the same group* in the stylized key views:

    group i of the training view  ->  key-view pixels of group i,   if group i appears in the key views
                                  ->  all key-view pixels,          otherwise (global fallback)

Matching runs at feature-map resolution: group maps are downsampled to the
feature grid (:func:`downsample_labels`, by majority vote or nearest
neighbour). The style loss is then, for every feature ``f_p`` of the rendered
view,

    L_style = mean_p  min_{q in M(p)}  (1 - cos(f_p, k_q))

where ``M(p)`` is the matched key-feature set of ``p``'s group. The
nearest-neighbour search is chunked so that at most ``chunk`` similarity
entries exist at once (memory-bounded at any resolution); it runs without
gradient, and the loss is differentiated with the neighbours held fixed
(the gradient of the min is the gradient at the arg-min, so value and
gradient are exact).

``global`` mode (ARF) is the special case of a single group: every position
matches against all features of the style image.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from ..errors import InputError

DEFAULT_CHUNK = 1 << 26  # similarity entries per block (256 MiB in float32)
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


def search_dtype(precision: str, device, dtype: torch.dtype = torch.float32) -> torch.dtype:
    """dtype of the nearest-neighbour search: ``auto`` = bf16 on CUDA (tensor cores), else the features' dtype."""
    if precision == "auto":
        return torch.bfloat16 if torch.device(device).type == "cuda" else dtype
    if precision not in PRECISIONS:
        raise InputError(f"nearest-neighbour precision '{precision}': use auto, fp32, bf16 or fp16")
    return PRECISIONS[precision]


def downsample_labels(labels: torch.Tensor, size: tuple[int, int], mode: str = "majority",
                      num_groups: Optional[int] = None) -> torch.Tensor:
    """Group maps at feature resolution.

    Args:
        labels: ``[B, H, W]`` integer group ids (>= 0).
        size: ``(h, w)`` of the feature grid.
        mode: ``"majority"`` (most frequent id among the pixels each cell
            covers, adaptive-pooling cells; ties go to the lower id) or
            ``"nearest"`` (the id at the cell's nearest pixel).
        num_groups: ids are < this (default ``labels.max() + 1``).
    Returns: ``[B, h, w]`` long.
    """
    if labels.ndim != 3:
        raise InputError(f"downsample_labels: expected [B,H,W] labels, got {tuple(labels.shape)}")
    labels = labels.long()
    if tuple(labels.shape[-2:]) == tuple(size):
        return labels
    if mode == "nearest":
        return F.interpolate(labels[:, None].float(), size=size, mode="nearest")[:, 0].round().long()
    if mode != "majority":
        raise InputError(f"downsample_labels: mode '{mode}' (use majority or nearest)")
    if labels.numel() and int(labels.min()) < 0:
        raise InputError("downsample_labels: negative group ids")
    k = int(labels.max()) + 1 if num_groups is None else int(num_groups)
    out = torch.empty((labels.shape[0],) + tuple(size), dtype=torch.long, device=labels.device)
    for b in range(labels.shape[0]):  # one view at a time: K x H x W counts, not B x K x H x W
        onehot = F.one_hot(labels[b], k).permute(2, 0, 1)[None].float()  # [1,K,H,W]
        counts = F.adaptive_avg_pool2d(onehot, size)[0]                  # [K,h,w]
        out[b] = counts.argmax(0)
    return out


def match_mask(view_labels: torch.Tensor, key_labels: torch.Tensor) -> torch.Tensor:
    """The dense matching relation (for inspection and tests; O(P*Q) memory).

    Args:
        view_labels: ``[P]`` (or any shape, flattened) group ids of the view's feature positions.
        key_labels: ``[Q]`` (or any shape, flattened) group ids of all key-view feature positions.
    Returns: ``[P, Q]`` bool, ``M[p, q] = key[q] == view[p]`` if ``view[p]`` occurs in the key
    views, else True for every ``q``.
    """
    v = view_labels.reshape(-1).long()
    k = key_labels.reshape(-1).long()
    present = torch.isin(v, k)
    same = v[:, None] == k[None, :]
    return torch.where(present[:, None], same, torch.ones_like(same))


@torch.no_grad()
def nearest_neighbors(queries: torch.Tensor, keys: torch.Tensor, chunk: int = DEFAULT_CHUNK
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Maximum inner product search, chunked over queries and keys.

    Args:
        queries: ``[P, C]``; keys: ``[Q, C]`` (L2-normalised rows give cosine similarity).
        chunk: at most this many ``P x Q`` similarity entries exist at once.
    Returns: ``(index [P] long, similarity [P])`` of each query's best key (lowest index on ties).
    """
    P, Q = queries.shape[0], keys.shape[0]
    if Q == 0:
        raise InputError("nearest_neighbors: no key features to match against")
    best = torch.full((P,), -float("inf"), dtype=queries.dtype, device=queries.device)
    idx = torch.zeros(P, dtype=torch.long, device=queries.device)
    kc = min(Q, max(1, chunk))
    qc = max(1, chunk // kc)
    for q0 in range(0, P, qc):
        q = queries[q0:q0 + qc]
        for k0 in range(0, Q, kc):
            sim = q @ keys[k0:k0 + kc].T                           # [qc, kc]
            val, arg = sim.max(dim=1)
            better = val > best[q0:q0 + qc]
            best[q0:q0 + qc] = torch.where(better, val, best[q0:q0 + qc])
            idx[q0:q0 + qc] = torch.where(better, arg + k0, idx[q0:q0 + qc])
    return idx, best


def _group_index(feats: torch.Tensor, labels: Optional[torch.Tensor]) -> tuple[Optional[torch.Tensor], dict]:
    """Flattened key labels ``[Q]`` and, per group present, the key positions ``{g: [Q_g]}`` (None, {} without labels)."""
    if feats.ndim != 4:
        raise InputError(f"style targets: expected key features [V,C,h,w], got {tuple(feats.shape)}")
    if labels is None:
        return None, {}
    V, _, h, w = feats.shape
    if tuple(labels.shape) != (V, h, w):
        raise InputError(f"style targets: labels {tuple(labels.shape)} do not match features {(V, h, w)}")
    flat = labels.reshape(-1).long().to(feats.device)
    return flat, {int(g): torch.nonzero(flat == g)[:, 0] for g in torch.unique(flat)}


class _GroupedTargets:
    """Key features with group ids and the group -> key positions rule shared by the style losses."""

    labels: Optional[torch.Tensor]
    groups: dict
    keys: torch.Tensor

    def for_regions(self, region) -> "_GroupedTargets":
        """These targets with group ``g`` matched against the key positions labelled ``region[g]`` (the
        key labels being regions of the style image, :mod:`ssgwarp.stylization.regions`; several groups may
        share a region). A group whose region has no key position falls back to all of them. In place;
        returns ``self``."""
        if self.labels is None:
            raise InputError("for_regions: the targets have no labels (regions) to assign groups to")
        regions = self.groups
        self.groups = {g: regions[int(r)] for g, r in enumerate(region) if int(r) in regions}
        return self

    def key_index(self, group: int) -> Optional[torch.Tensor]:
        """Key positions group ``group`` matches against: its own, or None (= all: global fallback)."""
        return self.groups.get(int(group)) if self.labels is not None else None

    def _check_view(self, feats: torch.Tensor, view_labels: Optional[torch.Tensor], who: str) -> torch.Tensor:
        if feats.ndim == 4:
            if feats.shape[0] != 1:
                raise InputError(f"{who}: one view at a time")
            feats = feats[0]
        C, h, w = feats.shape
        if C != self.keys.shape[1]:
            raise InputError(f"{who}: {C} feature channels, key features have {self.keys.shape[1]}")
        if view_labels is not None and tuple(view_labels.shape[-2:]) != (h, w):
            raise InputError(f"{who}: view labels {tuple(view_labels.shape)} vs features {(h, w)}")
        return feats


class MatchTargets(_GroupedTargets):
    """Style features of the stylized key views (or of the style image), with their group ids.

    Args:
        feats: ``[V, C, h, w]`` key-view features (any resolution; detached inside).
        labels: ``[V, h, w]`` group ids at that feature resolution, or None (one group:
            every position matches everything, i.e. global NNFM).
        chunk: similarity entries per block of the nearest-neighbour search.
        precision: dtype of the search (``auto``: bf16 on CUDA, else the features' dtype). The loss
            itself is always computed in the features' dtype, at the neighbour found; a
            low-precision search may pick a neighbour whose similarity is a rounding
            error below the best one.
    """

    def __init__(self, feats: torch.Tensor, labels: Optional[torch.Tensor] = None,
                 chunk: int = DEFAULT_CHUNK, precision: str = "auto") -> None:
        _group_index(feats, None)                     # shape check
        C = feats.shape[1]
        self.keys = F.normalize(feats.detach().permute(0, 2, 3, 1).reshape(-1, C), dim=1)  # [Q, C]
        self.labels, self.groups = _group_index(feats, labels)
        self.chunk = chunk
        self.search_dtype = search_dtype(precision, feats.device, self.keys.dtype)
        self._search_keys = self.keys if self.search_dtype == self.keys.dtype else self.keys.to(self.search_dtype)

    @torch.no_grad()
    def nearest(self, queries: torch.Tensor, view_labels: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``[P]`` index (into :attr:`keys`) of each query's nearest matched key feature.

        queries: ``[P, C]`` L2-normalised; view_labels: ``[P]`` group ids, or None (global).
        """
        queries = queries.to(self.search_dtype)
        keys = self._search_keys
        if view_labels is None or self.labels is None:
            return nearest_neighbors(queries, keys, self.chunk)[0]
        view_labels = view_labels.reshape(-1).to(queries.device)
        out = torch.empty(queries.shape[0], dtype=torch.long, device=queries.device)
        for g in torch.unique(view_labels).tolist():
            sel = torch.nonzero(view_labels == g)[:, 0]
            kidx = self.key_index(g)
            if kidx is None:
                out[sel] = nearest_neighbors(queries[sel], keys, self.chunk)[0]
            else:
                out[sel] = kidx[nearest_neighbors(queries[sel], keys[kidx], self.chunk)[0]]
        return out

    def loss(self, feats: torch.Tensor, view_labels: Optional[torch.Tensor] = None) -> torch.Tensor:
        """The NNFM style loss of one view (differentiable w.r.t. ``feats``).

        Args:
            feats: ``[C, h, w]`` (or ``[1, C, h, w]``) features of the rendered view.
            view_labels: ``[h, w]`` group ids at the same resolution, or None (global).
        Returns: scalar ``mean_p min_{q in M(p)} (1 - cos(f_p, k_q))``.
        """
        feats = self._check_view(feats, view_labels, "MatchTargets.loss")
        C = feats.shape[0]
        q = F.normalize(feats.permute(1, 2, 0).reshape(-1, C), dim=1)
        idx = self.nearest(q.detach(), view_labels)
        return (1.0 - (q * self.keys[idx]).sum(dim=1)).mean()


class SlicedTargets(_GroupedTargets):
    """Style features to match *as distributions*: the sliced Wasserstein feature loss, per group.

    For one view with features ``f_p`` and group map ``g(p)``, each group ``i`` present is compared
    with its matched key features ``K_i`` (its own key-view features, or all of them when group
    ``i`` is absent from the key views — the same fallback as NNFM matching)::

        L_i = mean_theta mean_p ( sort(<f_p, theta>)_p - Q_i(theta, p) )^2 / mean_theta mean(<K_i, theta>^2)

    where ``theta`` runs over ``projections`` random unit directions drawn afresh at every step (seeded
    by ``seed`` and the step, so a resumed run draws the same ones) and ``Q_i`` are the sorted key
    projections at the view's quantile levels ``(p + 0.5) / n_i`` (nearest order statistic). The loss
    is the pixel-weighted mean of ``L_i`` over the groups (one group: the global loss). Unlike NNFM,
    which sends every feature to its nearest style feature and so collapses a view onto the style's
    dominant mode (measured in docs/stylize.md), this matches the whole distribution of the style's
    features along every sampled direction (Heitz et al. 2021, "A Sliced Wasserstein Loss for Neural
    Texture Synthesis"). The gradient flows through the sort (exact almost everywhere).
    """

    def __init__(self, feats: torch.Tensor, labels: Optional[torch.Tensor] = None, projections: int = 64,
                 seed: int = 0) -> None:
        self.labels, self.groups = _group_index(feats, labels)
        C = feats.shape[1]
        self.keys = feats.detach().permute(0, 2, 3, 1).reshape(-1, C)         # [Q, C], not normalised
        self.projections, self.seed = int(projections), int(seed)
        if self.projections < 1:
            raise InputError("SlicedTargets: projections must be >= 1")

    def directions(self, step: int, channels: int, device, dtype) -> torch.Tensor:
        """``[C, P]`` unit directions of ``step`` (a pure function of seed and step)."""
        g = torch.Generator(device="cpu").manual_seed(self.seed * 1_000_003 + int(step))
        d = torch.randn(channels, self.projections, generator=g, dtype=torch.float64)
        return F.normalize(d, dim=0).to(device=device, dtype=dtype)

    @staticmethod
    def sliced_term(queries: torch.Tensor, keys: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """``mean (sort(q d) - quantiles of sort(k d))^2 / mean((k d)^2)`` for ``queries [n, C]``, ``keys [m, C]``."""
        pq = (queries @ d).sort(dim=0).values                                   # [n, P]
        pk = (keys @ d).sort(dim=0).values                                      # [m, P]
        n, m = pq.shape[0], pk.shape[0]
        idx = ((torch.arange(n, device=pq.device, dtype=torch.float64) + 0.5) * m / n).long().clamp_max(m - 1)
        return ((pq - pk[idx]) ** 2).mean() / (pk ** 2).mean().clamp_min(1e-12)

    def loss(self, feats: torch.Tensor, view_labels: Optional[torch.Tensor] = None, step: int = 0) -> torch.Tensor:
        """The sliced Wasserstein style loss of one view (``feats [C, h, w]``; labels as :meth:`MatchTargets.loss`)."""
        feats = self._check_view(feats, view_labels, "SlicedTargets.loss")
        C = feats.shape[0]
        q = feats.permute(1, 2, 0).reshape(-1, C)
        keys = self.keys.to(q)
        d = self.directions(step, C, q.device, q.dtype)
        if view_labels is None or self.labels is None:
            return self.sliced_term(q, keys, d)
        lab = view_labels.reshape(-1).to(q.device)
        total = q.new_zeros(())
        for g in torch.unique(lab).tolist():
            sel = torch.nonzero(lab == g)[:, 0]
            kidx = self.key_index(g)
            k = keys if kidx is None else keys[kidx]
            total = total + self.sliced_term(q[sel], k, d) * (len(sel) / q.shape[0])
        return total


def nnfm_loss(feats: torch.Tensor, key_feats: torch.Tensor, view_labels: Optional[torch.Tensor] = None,
              key_labels: Optional[torch.Tensor] = None, chunk: int = DEFAULT_CHUNK,
              precision: str = "auto") -> torch.Tensor:
    """Functional form of :meth:`MatchTargets.loss`.

    feats ``[C,h,w]``, key_feats ``[V,C,hk,wk]``, view_labels ``[h,w]`` / key_labels
    ``[V,hk,wk]`` (both or neither) -> scalar.
    """
    return MatchTargets(key_feats, key_labels, chunk, precision).loss(feats, view_labels)
