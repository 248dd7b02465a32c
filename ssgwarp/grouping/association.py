"""Cross-view association of per-view instance masks through the reconstruction (``ssgwarp masks``).

A segmenter labels every view on its own: mask 3 of one view and mask 3 of the
next have nothing to do with each other, an object may be split in one view and
whole in the next, two objects may share one mask, and a view may miss an object.
Instead of a video tracker, the masks are associated through the Gaussians that
render them:

1. **Lift** (:func:`lift_masks`): each view's masks are lifted onto the Gaussians.
   The rasterizer blends one channel per mask; the gradient of
   ``sum_p onehot(mask(p)) . image(p)`` with respect to the Gaussians' channel
   values is, per Gaussian and mask, the sum of the Gaussian's blending weights
   ``T alpha`` over the mask's pixels. A Gaussian belongs to the mask holding the
   largest share of its weight in that view (a hard label when the share is at
   least ``label_share``); it is *unlabelled* there when pixels no mask covers
   hold the largest share, and *unseen* when its weights sum to less than
   ``visible_weight`` pixels (occluded, outside, transparent).
2. **Overlaps**: for masks ``a`` (view u) and ``c`` (view w), ``D[a, c]`` counts
   the Gaussians hard-labelled ``a`` in u and ``c`` in w.
3. **View consensus**: view w *observes* mask a when at least
   ``observe_fraction`` of a's Gaussians (and ``min_observed``) are hard-labelled
   in w, and *contains* it in mask c when c holds at least ``contain`` of them.
   Two masks that share Gaussians are the same instance when, among the views
   observing both, more than ``consensus`` of them contain both in one mask.
   A mask split in one view is contained whole in the views that see the object
   whole (the parts join); a mask merging two objects is contained in no single
   mask of the views that separate them (it joins neither by majority).
4. **Instances**: connected components of that graph. Each Gaussian votes, view
   by view, for the instance of the mask it falls in (weighted by its share) or
   for the background (``background_vote``, when it is visible on pixels no mask
   covers); it takes the winning label. Gaussians with no vote take the label of
   their nearest voting neighbours in 3D.
5. **Masks**: the per-Gaussian labels (0 = background, 1..K instances, by size)
   are rendered into every view (one channel per label, as the mask-free
   pseudo-masks are), so the written masks agree across views by construction;
   pixels where no label holds ``share_min`` of the alpha, or with alpha below
   ``alpha_min``, are ``IGNORE``.

Public API:
    AssociationConfig, Association
    compact_masks(label_maps, min_pixels)        -> (compact [V,H,W] long, per-view original ids)
    lift_masks(scene, cameras, compact, ...)      -> (labels [V,N] long, share [V,N])
    associate(scene, cameras, label_maps, ...)    -> Association
    adjusted_rand_index(a, b)                     -> float
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Optional

import numpy as np
import torch

from ..core.cameras import Cameras
from ..errors import InputError
from ..raster.rendering import gaussian_sums
from .pseudomasks import _knn_vote, render_label_masks
from ..raster.scene import GaussianScene

Tensor = torch.Tensor
UNLABELLED = -1   # seen, with most of its weight on pixels no mask covers
UNSEEN = -2       # its blending weights in the view sum to less than ``visible_weight``
BACKGROUND = 0    # the label of Gaussians (and pixels) that belong to no instance


@dataclass(frozen=True)
class AssociationConfig:
    """Knobs of the association (defaults documented in docs/grouping.md).

    min_mask_fraction: masks covering fewer pixels than this share of the view are dropped
        (their pixels count as unlabelled).
    visible_weight: a Gaussian is seen by a view when its blending weights there sum to at
        least this many pixels.
    label_share: a Gaussian is hard-labelled with a mask when the mask's pixels hold at least
        this share of its weight in the view.
    observe_fraction, min_observed: a view observes a mask when at least this share of the
        mask's Gaussians (and at least ``min_observed`` of them) are hard-labelled there.
    contain: a view contains a mask in one of its own masks when that mask holds at least
        this share of the observed Gaussians.
    consensus: two masks are one instance when more than this share of the views observing
        both contain them in one mask.
    background_vote: weight of a view's vote for the background (the Gaussian is seen on
        unlabelled pixels); a view's vote for an instance weighs the Gaussian's share.
    vote_k: Gaussians without any vote take the majority label of this many nearest voters.
    max_instances: at most this many instances are kept (those with the most Gaussians); the
        Gaussians of the others join the background (254: 8-bit masks, Gaussian Grouping's 256 classes).
    alpha_min, share_min: rendering the final masks (see :func:`ssgwarp.grouping.pseudomasks.render_label_masks`).
    masks_per_pass: lifting renders at most this many mask channels per rasterizer pass.
    """

    min_mask_fraction: float = 0.0005
    visible_weight: float = 0.05
    label_share: float = 0.5
    observe_fraction: float = 0.25
    min_observed: int = 3
    contain: float = 0.6
    consensus: float = 0.5
    background_vote: float = 0.25
    vote_k: int = 5
    max_instances: int = 254
    alpha_min: float = 0.5
    share_min: float = 0.5
    masks_per_pass: int = 63

    def validate(self) -> "AssociationConfig":
        for name in ("min_mask_fraction", "label_share", "observe_fraction", "contain", "consensus",
                     "alpha_min", "share_min"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InputError(f"association: {name} must be in [0, 1], got {v}")
        if self.visible_weight < 0 or self.background_vote < 0:
            raise InputError("association: visible_weight and background_vote must be >= 0")
        if min(self.min_observed, self.vote_k, self.masks_per_pass, self.max_instances) < 1:
            raise InputError("association: min_observed, vote_k, masks_per_pass and max_instances must be >= 1")
        return self


@dataclass
class Association:
    """What :func:`associate` found.

    labels: ``[N]`` long, per Gaussian: 0 background, 1..K instances (largest first).
    num_instances: K (the background not counted).
    masks: ``[C, H, W]`` long, the labels rendered into the cameras passed as ``render_cameras``
        (``IGNORE`` = -1 where no label dominates).
    mask_instance: per input view, the instance (1..K, 0 background, -1 dropped as too small)
        of each of its compact masks.
    mask_ids: per input view, the original id of each compact mask.
    stats: counts for the record (masks, dropped, edges, instances, votes).
    """

    labels: Tensor
    num_instances: int
    masks: Tensor
    mask_instance: list[list[int]]
    mask_ids: list[list[int]]
    stats: dict = field(default_factory=dict)


# -- masks ----------------------------------------------------------------------------------------

def compact_masks(label_maps: Tensor, min_pixels: int = 0) -> tuple[Tensor, list[list[int]]]:
    """Per view, ids made compact ``0..M_v-1`` (sorted by original id); negative ids and masks of
    fewer than ``min_pixels`` pixels become -1 (unlabelled).

    Returns ``(compact [V, H, W] long, ids)`` where ``ids[v][m]`` is the original id of compact mask m.
    """
    if label_maps.ndim != 3:
        raise InputError(f"per-view masks must be [V, H, W], got {tuple(label_maps.shape)}")
    out = torch.full(label_maps.shape, -1, dtype=torch.long, device=label_maps.device)
    ids: list[list[int]] = []
    for v in range(label_maps.shape[0]):
        lab = label_maps[v].long()
        vals, inv, counts = torch.unique(lab, return_inverse=True, return_counts=True)
        keep = (vals >= 0) & (counts >= max(1, int(min_pixels)))
        remap = torch.full((vals.numel(),), -1, dtype=torch.long, device=lab.device)
        remap[keep] = torch.arange(int(keep.sum()), device=lab.device)
        out[v] = remap[inv]
        ids.append([int(x) for x in vals[keep].tolist()])
    return out, ids


# -- lifting --------------------------------------------------------------------------------------

def lift_masks(scene: GaussianScene, cameras: Cameras, compact: Tensor, *, visible_weight: float = 0.05,
               masks_per_pass: int = 63, progress: bool = False, **raster_kwargs) -> tuple[Tensor, Tensor]:
    """Lift each view's masks onto the Gaussians through their blending weights.

    Args:
        compact: ``[V, H, W]`` long, ids ``0..M_v-1`` per view, -1 unlabelled (:func:`compact_masks`).
    Returns:
        ``(labels [V, N] long, share [V, N] float)``: per view and Gaussian, the mask holding the
        largest share of the Gaussian's blending weight (``UNLABELLED`` when the unlabelled pixels
        hold it, ``UNSEEN`` when the weights sum to less than ``visible_weight`` pixels) and that share.
    """
    from ..core.progress import tqdm

    V = compact.shape[0]
    if V != len(cameras) or tuple(compact.shape[1:]) != (cameras.height, cameras.width):
        raise InputError(f"lift_masks: masks {tuple(compact.shape)} for {len(cameras)} cameras of "
                         f"{cameras.width}x{cameras.height}")
    geom = scene.detach().replace(identities=None)
    dev, dt = geom.device, geom.dtype
    n = len(geom)
    labels = torch.full((V, n), UNSEEN, dtype=torch.long, device=dev)
    share = torch.zeros((V, n), dtype=dt, device=dev)
    cams = cameras.to(dev)
    step = max(1, int(masks_per_pass))
    for v in tqdm(range(V), desc="lift masks", unit="view", leave=False, disable=not progress):
        lab = compact[v].to(dev)
        m = int(lab.max()) + 1 if lab.numel() else 0
        best_w = torch.zeros(n, dtype=dt, device=dev)
        best_i = torch.full((n,), UNLABELLED, dtype=torch.long, device=dev)
        total = labelled = None
        # channel 0 of the first pass: every pixel (the Gaussian's total weight)
        for s in range(0, max(m, 1), step):
            e = min(m, s + step)
            off = 1 if s == 0 else 0
            sig = torch.zeros(cams.height, cams.width, (e - s) + off, dtype=dt, device=dev)
            if off:
                sig[..., 0] = 1.0
            yy, xx = torch.nonzero((lab >= s) & (lab < e), as_tuple=True)
            sig[yy, xx, lab[yy, xx] - s + off] = 1.0
            w = gaussian_sums(geom, cams[v], sig, **raster_kwargs)
            if off:
                total = w[:, 0]
                labelled = torch.zeros_like(total)
            if e > s:
                wm = w[:, off:]
                labelled = labelled + wm.sum(dim=1)
                top, idx = wm.max(dim=1)
                better = top > best_w
                best_w = torch.where(better, top, best_w)
                best_i = torch.where(better, idx + s, best_i)
        unl = (total - labelled).clamp_min(0.0)
        seen = total >= visible_weight
        on_mask = best_w > unl
        labels[v] = torch.where(seen, torch.where(on_mask, best_i, torch.full_like(best_i, UNLABELLED)),
                                torch.full_like(best_i, UNSEEN))
        tot = total.clamp_min(1e-12)
        share[v] = torch.where(seen, torch.where(on_mask, best_w, unl) / tot, torch.zeros_like(tot))
    return labels, share


# -- the graph -------------------------------------------------------------------------------------

def _overlaps(hard: Tensor, offsets: Tensor, total: int) -> tuple[Tensor, Tensor, Tensor]:
    """Sparse ``D``: triples ``(a, c, count)`` of masks a, c (global ids) sharing ``count`` hard-labelled Gaussians."""
    V = hard.shape[0]
    glob = torch.where(hard >= 0, hard + offsets[:, None], torch.full_like(hard, -1))
    keys, counts = [], []
    for u in range(V):
        gu = glob[u]
        ok_u = gu >= 0
        if not bool(ok_u.any()):
            continue
        gw = glob[:, ok_u]                                   # [V, n_u]
        a = gu[ok_u][None].expand_as(gw)
        ok = gw >= 0
        k, c = torch.unique(a[ok] * total + gw[ok], return_counts=True)
        keys.append(k)
        counts.append(c)
    if not keys:
        e = torch.zeros(0, dtype=torch.long, device=hard.device)
        return e, e, e
    k, c = torch.cat(keys), torch.cat(counts)
    return k // total, k % total, c


def _clusters(total: int, pa: np.ndarray, pc: np.ndarray, order: np.ndarray, cont: np.ndarray,
              observed: np.ndarray, consensus: float) -> tuple[np.ndarray, int]:
    """Merge masks along the edges ``pa[i] - pc[i]`` taken in ``order``, refusing a merge that would put
    two masks in one cluster whose views disagree: among the views observing both, fewer than
    ``consensus`` contain them in one mask. Returns ``([total] cluster ids (compact), merges refused)``."""
    parent = np.arange(total)
    members: dict[int, list[int]] = {i: [i] for i in range(total)}

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    refused = 0
    for e in order:
        ra, rb = find(int(pa[e])), find(int(pc[e]))
        if ra == rb:
            continue
        ma, mb = members[ra], members[rb]
        ca, cb = cont[ma][:, None, :], cont[mb][None, :, :]            # [A, 1, V], [1, B, V]
        both = observed[ma][:, None, :] & observed[mb][None, :, :]
        n_both = both.sum(axis=2)
        n_same = (both & (ca == cb) & (ca >= 0)).sum(axis=2)
        if bool(((n_both > 0) & (n_same < consensus * n_both)).any()):
            refused += 1                                              # a pair the views keep apart
            continue
        if len(ma) < len(mb):
            ra, rb, ma, mb = rb, ra, mb, ma
        parent[rb] = ra
        ma.extend(mb)
        del members[rb]
    roots = np.array([find(i) for i in range(total)], dtype=np.int64)
    return (np.unique(roots, return_inverse=True)[1] if total else roots), refused


def _vote_labels(scene: GaussianScene, labels: Tensor, share: Tensor, comp: Tensor, purity: Tensor, offsets: Tensor,
                 q: int, cfg: AssociationConfig) -> tuple[Tensor, Tensor, int]:
    """Each Gaussian's instance (0: background) by the views' votes: ``(labels [N], voted [N] bool,
    instances dropped over the cap)``. Gaussians without votes take their nearest voted ones'."""
    V, n = labels.shape
    dev = labels.device
    # votes: per Gaussian, per view, for the instance of its mask (its share x the mask's purity) or for
    # the background; kept sparse (at most one vote per Gaussian and view)
    ar = torch.arange(n, device=dev)
    gi, li, wi = [], [], []
    for v in range(V):
        lv = labels[v]
        on = lv >= 0
        g = lv[on] + offsets[v]
        gi += [ar[on], ar[lv == UNLABELLED]]
        li += [comp[g] + 1, torch.zeros(int((lv == UNLABELLED).sum()), dtype=torch.long, device=dev)]
        wi += [share[v][on].double() * purity[g],
               torch.full((int((lv == UNLABELLED).sum()),), float(cfg.background_vote), dtype=torch.float64,
                          device=dev)]
    key_v, inv = torch.unique(torch.cat(gi) * (q + 1) + torch.cat(li), return_inverse=True)
    tot = torch.zeros(key_v.numel(), dtype=torch.float64, device=dev).index_add_(0, inv, torch.cat(wi))
    pos = tot > 0
    vg, vl, tot = key_v[pos] // (q + 1), key_v[pos] % (q + 1), tot[pos]
    top = torch.zeros(n, dtype=torch.float64, device=dev).scatter_reduce_(0, vg, tot, reduce="amax")
    win = tot >= top[vg]
    lab = torch.full((n,), q + 1, dtype=torch.long, device=dev).scatter_reduce_(0, vg[win], vl[win], reduce="amin")
    has = torch.zeros(n, dtype=torch.bool, device=dev)
    has[vg] = True
    lab[~has] = 0
    # at most max_instances instances (the most Gaussians); the rest join the background
    counts = torch.bincount(lab[has], minlength=q + 1)
    counts[0] = 0
    dropped_cap = max(0, int((counts > 0).sum()) - cfg.max_instances)
    if dropped_cap:
        keep = torch.zeros(q + 1, dtype=torch.bool, device=dev)
        keep[torch.argsort(counts, descending=True, stable=True)[:cfg.max_instances]] = True
        keep[0] = True
        lab = torch.where(keep[lab], lab, torch.zeros_like(lab))
    if bool((~has).any()) and bool(has.any()):
        pts = scene.means.detach()
        used, lab_c = torch.unique(lab[has], return_inverse=True)          # vote over the labels in use
        lab[~has] = used[_knn_vote(pts[~has].double(), pts[has].double(), lab_c, used.numel(), cfg.vote_k)]
    return lab, has, dropped_cap


def _number_instances(scene: GaussianScene, rc: Cameras, lab: Tensor, q: int, cfg: AssociationConfig,
                      progress: bool) -> tuple[Tensor, Tensor, int, Tensor]:
    """Instances numbered by their number of Gaussians, largest first: ``(labels [N], remap [q + 1]
    old -> new id, instances, masks [C, H, W] rendered in ``rc``)``."""
    dev = lab.device
    # instances numbered by their number of Gaussians, largest first; those without Gaussians, or that
    # dominate no pixel of any view, vanish (their Gaussians join the background)
    remap = torch.arange(q + 1, device=dev)
    while True:
        counts = torch.bincount(lab, minlength=q + 1)
        order = [i for i in sorted(range(1, q + 1), key=lambda i: (-int(counts[i]), i)) if counts[i] > 0]
        step = torch.zeros(q + 1, dtype=torch.long, device=dev)
        for new, old in enumerate(order, start=1):
            step[old] = new
        lab, remap, q = step[lab], step[remap], len(order)
        masks = render_label_masks(scene, rc, lab, q + 1, alpha_min=cfg.alpha_min, share_min=cfg.share_min,
                                   progress=progress)
        shown = torch.bincount(masks[masks >= 0].flatten(), minlength=q + 1)
        hidden = (shown[1:] == 0).nonzero().flatten() + 1
        if hidden.numel() == 0:
            break
        lab = torch.where(torch.isin(lab, hidden.to(dev)), torch.zeros_like(lab), lab)
    return lab, remap, q, masks


def associate(scene: GaussianScene, cameras: Cameras, label_maps: Tensor, *,
              config: AssociationConfig = AssociationConfig(), render_cameras: Optional[Cameras] = None,
              progress: bool = False, **raster_kwargs) -> Association:
    """Associate per-view instance masks across views through the scene (see the module docstring).

    Args:
        scene: the reconstruction. cameras: the V views the masks belong to.
        label_maps: ``[V, H, W]`` integer ids per view (any values; negative = unlabelled), at the
            cameras' resolution; ids need not agree between views.
        render_cameras: where to render the final masks (default ``cameras``).
    Returns:
        :class:`Association`.
    """
    cfg = config.validate()
    V = len(cameras)
    if label_maps.shape[0] != V:
        raise InputError(f"associate: {label_maps.shape[0]} mask images for {V} cameras")
    dev = scene.device
    min_px = int(round(cfg.min_mask_fraction * cameras.width * cameras.height))
    compact, ids = compact_masks(label_maps.to(dev), min_px)
    raw_counts = [int(torch.unique(label_maps[v][label_maps[v] >= 0]).numel()) for v in range(V)]
    labels, share = lift_masks(scene, cameras, compact, visible_weight=cfg.visible_weight,
                               masks_per_pass=cfg.masks_per_pass, progress=progress, **raster_kwargs)
    n = labels.shape[1]
    per_view = torch.tensor([len(x) for x in ids], dtype=torch.long, device=dev)
    offsets = torch.cumsum(per_view, 0) - per_view
    total = int(per_view.sum())
    view_of = torch.repeat_interleave(torch.arange(V, device=dev), per_view)
    hard = torch.where((labels >= 0) & (share >= cfg.label_share), labels, torch.full_like(labels, -1))

    a, c, cnt = _overlaps(hard, offsets, total)
    size = torch.zeros(total, dtype=torch.long, device=dev)
    same = a == c
    size[a[same]] = cnt[same]
    # per mask and view: Gaussians observed there, and the largest share one mask of the view holds
    key = a * V + view_of[c]
    obs = torch.zeros(total * V, dtype=torch.long, device=dev).index_add_(0, key, cnt)
    best = torch.zeros(total * V, dtype=torch.long, device=dev).scatter_reduce_(0, key, cnt, reduce="amax")
    is_best = cnt == best[key]
    best_c = torch.full((total * V,), total, dtype=torch.long, device=dev)
    best_c.scatter_reduce_(0, key[is_best], c[is_best], reduce="amin")       # ties: the lowest id
    obs, best, best_c = obs.view(total, V), best.view(total, V), best_c.view(total, V)
    need = torch.clamp(torch.ceil(cfg.observe_fraction * size.double()).long(), min=cfg.min_observed)
    observed = obs >= need[:, None]
    contained = observed & (best.double() >= cfg.contain * obs.double())
    # purity of a mask: the share of its Gaussians that the other observing views keep in one mask
    # (about 1 for a mask of one object or part; lower for a mask merging objects the others separate)
    other = observed & (torch.arange(V, device=dev)[None] != view_of[:, None])
    o_sum = torch.where(other, obs, torch.zeros_like(obs)).sum(dim=1).double()
    purity = torch.where(o_sum > 0, torch.where(other, best, torch.zeros_like(best)).sum(dim=1).double()
                         / o_sum.clamp_min(1), torch.ones_like(o_sum))
    cont = torch.where(contained, best_c, torch.full_like(best_c, -1))

    # candidate pairs: masks of different views sharing Gaussians, each pair once
    cand = (view_of[a] != view_of[c]) & (a < c)
    pa, pc = a[cand], c[cand]
    shared = cnt[cand]
    both = observed[pa] & observed[pc]
    support = both & (cont[pa] == cont[pc]) & (cont[pa] >= 0)
    n_both = both.sum(dim=1)
    ratio = support.sum(dim=1).double() / n_both.clamp_min(1).double()
    edge = (n_both > 0) & (ratio > cfg.consensus)
    # strongest evidence first: consensus, then the number of shared Gaussians
    ea, ec, er, es = (t[edge].cpu().numpy() for t in (pa, pc, ratio, shared))
    order = np.lexsort((-es, -er))
    comp_np, refused = _clusters(total, ea, ec, order, cont.cpu().numpy(), observed.cpu().numpy(), cfg.consensus)
    comp = torch.from_numpy(comp_np).to(dev)
    q = int(comp.max()) + 1 if total else 0
    n_clusters = q

    lab, has, dropped_cap = _vote_labels(scene, labels, share, comp, purity, offsets, q, cfg)
    rc = cameras if render_cameras is None else render_cameras
    lab, remap, q, masks = _number_instances(scene, rc, lab, q, cfg, progress)
    k = q
    mask_instance = []
    for v in range(V):
        mi = remap[comp[offsets[v]:offsets[v] + per_view[v]] + 1]
        mask_instance.append([int(x) for x in mi.tolist()])
    seen = (labels != UNSEEN).sum(dim=0)
    stats = {"views": V, "gaussians": n, "masks_given": raw_counts, "masks_kept": [len(x) for x in ids],
             "masks_dropped_small": [r - len(x) for r, x in zip(raw_counts, ids)], "min_mask_pixels": min_px,
             "candidate_pairs": int(cand.sum()), "edges": int(edge.sum()), "merges_refused": refused,
             "clusters": n_clusters,
             "instances": k, "gaussians_per_label": torch.bincount(lab, minlength=k + 1).tolist(),
             "gaussians_unseen": int((seen == 0).sum()), "gaussians_without_votes": int((~has).sum()),
             "instances_over_cap": dropped_cap,
             "config": asdict(cfg)}
    return Association(labels=lab, num_instances=k, masks=masks, mask_instance=mask_instance, mask_ids=ids,
                       stats=stats)


# -- scoring ---------------------------------------------------------------------------------------

def adjusted_rand_index(a: Tensor, b: Tensor) -> float:
    """Adjusted Rand index (Hubert and Arabie) of two labelings of the same items (any integer ids).

    1 for identical partitions (up to renaming), about 0 for independent ones. Two partitions
    that are both a single cluster (or both all singletons) score 1.
    """
    a = torch.as_tensor(a).reshape(-1).long().cpu()
    b = torch.as_tensor(b).reshape(-1).long().cpu()
    if a.shape != b.shape:
        raise ValueError(f"adjusted_rand_index: {a.numel()} and {b.numel()} labels")
    n = a.numel()
    if n < 2:
        return 1.0
    _, ia = torch.unique(a, return_inverse=True)
    _, ib = torch.unique(b, return_inverse=True)
    nb = int(ib.max()) + 1
    table = torch.bincount(ia * nb + ib, minlength=(int(ia.max()) + 1) * nb).double()

    def pairs(x: Tensor) -> float:
        return float((x * (x - 1) / 2).sum())

    sum_ij = pairs(table)
    sum_a = pairs(torch.bincount(ia).double())
    sum_b = pairs(torch.bincount(ib).double())
    expected = sum_a * sum_b / (n * (n - 1) / 2)
    top = (sum_a + sum_b) / 2
    if top == expected:
        return 1.0
    return (sum_ij - expected) / (top - expected)


__all__ = ["AssociationConfig", "Association", "compact_masks", "lift_masks", "associate", "adjusted_rand_index",
           "UNLABELLED", "UNSEEN", "BACKGROUND",]
