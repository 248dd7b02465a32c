"""The densification statistics of one render (what :class:`~ssgwarp.reconstruction.strategy.DefaultStrategy`
observes after each backward): per Gaussian, the sum of its screen-space positional gradient norms in NDC
units, the number of views it was visible in, its largest screen radius. One Warp kernel for the layout
the Trainer renders (``kernels/stats.py``: one launch, no host synchronisation), torch ops for the others
(gsplat's packed layout). :func:`observe_across`: a strategy's statistics of a step whose views are rendered
by several processes (:mod:`ssgwarp.services.distributed`).
"""
from __future__ import annotations

import functools

import torch


def observe_across(strategy, gaussians, meta: dict, group) -> None:
    """``strategy.observe(gaussians, meta)`` of a step whose views ``group``'s processes share: each process
    observes its own views into zeroed statistics, which are combined across processes (the strategy's
    ``stat_ops``: ``"sum"`` or ``"max"``, :meth:`ssgwarp.services.distributed.Group.reduce_stats`) and added
    to the running ones (or their maximum taken), so every process refines identically. Alone (or without
    statistics): ``strategy.observe`` itself."""
    if not group.active or not gaussians.stats:
        strategy.observe(gaussians, meta)
        return
    kept = gaussians.stats
    gaussians.stats = {k: torch.zeros_like(v) for k, v in kept.items()}
    strategy.observe(gaussians, meta)
    ops = strategy.stat_ops
    group.reduce_stats(gaussians.stats, ops)
    gaussians.stats = {k: (torch.maximum(kept[k], v) if ops.get(k, "sum") == "max" else kept[k] + v)
                       for k, v in gaussians.stats.items()}


@torch.no_grad()
def accumulate_grad2d(stats: dict[str, torch.Tensor], meta: dict) -> None:
    """Add one render's view-space gradient norms (NDC units) and visibility counts to ``stats``.

    ``meta`` is a gsplat-compatible rasterization's: ``means2d`` with its ``.grad``
    (``[C, N, 2]``, or ``[nnz, 2]`` with ``gaussian_ids`` in packed mode), ``radii``
    (``[C, N, 2]`` / ``[C, N]`` / ``[nnz, 2]``, > 0 where visible), ``width``, ``height``,
    ``n_cameras``. Pixel gradients are scaled by ``(W/2, H/2)`` (pixels -> NDC) and by the
    number of cameras (the loss is their mean). ``stats["max_radii"]``, when present, keeps
    the largest radius as a fraction of ``max(W, H)``.

    The ``[C, N]`` layout with per-axis int32 radii and statistics of the gradient's dtype (what
    the Trainer keeps) runs as one Warp kernel (``kernels/stats.py``: one launch, no host
    synchronisation; the same sums to float rounding); other layouts in torch.
    """
    g = meta["means2d"].grad
    if g is None:
        return
    w, h = float(meta["width"]), float(meta["height"])
    c = int(meta.get("n_cameras", g.shape[0] if g.ndim == 3 else 1))
    radii = meta["radii"]
    if _accumulate_warp(stats, g, radii, w, h, c):
        return
    if radii.ndim == g.ndim:  # per-axis radii [..., 2]
        vis, r = (radii > 0).all(dim=-1), radii.max(dim=-1).values
    else:
        vis, r = radii > 0, radii
    # (the scale goes to the device without a blocking copy, which would synchronise every step)
    scale = torch.tensor([w / 2.0 * c, h / 2.0 * c], dtype=g.dtype).to(g.device, non_blocking=True)
    norms = (g * scale).norm(dim=-1) * vis
    r = (r * vis).to(torch.float32) / max(w, h)
    ids = meta.get("gaussian_ids")
    if g.ndim == 2:  # packed: one row per (camera, visible Gaussian), ``gaussian_ids`` says which
        stats["grad2d"].index_add_(0, ids, norms.to(stats["grad2d"].dtype))
        stats["count"].index_add_(0, ids, vis.to(stats["count"].dtype))
        if "max_radii" in stats:
            stats["max_radii"].scatter_reduce_(0, ids, r.to(stats["max_radii"].dtype), "amax")
        return
    stats["grad2d"] += norms.sum(dim=0).to(stats["grad2d"].dtype)
    stats["count"] += vis.sum(dim=0).to(stats["count"].dtype)
    if "max_radii" in stats:
        stats["max_radii"] = torch.maximum(stats["max_radii"], r.max(dim=0).values.to(stats["max_radii"].dtype))


def _accumulate_warp(stats: dict[str, torch.Tensor], g: torch.Tensor, radii: torch.Tensor, w: float, h: float,
                     c: int) -> bool:
    """:func:`accumulate_grad2d` of the ``[C, N]`` layout in one Warp kernel; False (nothing done)
    where it does not apply: another layout, radii that are not per-axis int32, statistics of
    another dtype or device, no Warp."""
    names = ("grad2d", "count") + (("max_radii",) if "max_radii" in stats else ())
    if (g.ndim != 3 or radii.ndim != 3 or radii.dtype != torch.int32 or g.dtype not in (torch.float32, torch.float64)
            or g.device.type not in ("cpu", "cuda") or radii.device != g.device
            or any(stats[k].dtype != g.dtype or stats[k].device != g.device or not stats[k].is_contiguous()
                   for k in names)):
        return False
    try:
        from ..raster import launch as L
        from ..kernels import stats as kernels
    except ImportError:  # pragma: no cover - no warp-lang: the torch ops
        return False
    C, N = g.shape[0], g.shape[1]
    if N == 0:
        return True
    g, radii = L.dense(g), L.dense(radii)  # (kept alive until the launch is queued)
    L.launch(kernels.grad2d_kernel(L.scalar_of(g.dtype)), N,
             [*L.arr(g, 2), *L.arr(radii, 2), C, N, w / 2.0 * c, h / 2.0 * c, _reciprocal(max(w, h), g.dtype),
              *L.arr(stats["grad2d"]), *L.arr(stats["count"]),
              *(L.arr(stats["max_radii"]) if "max_radii" in stats else L.NULL)], L.target(g))
    return True


@functools.lru_cache(maxsize=64)
def _reciprocal(x: float, dtype: torch.dtype) -> float:
    """``1 / x`` rounded to ``dtype`` (torch's CUDA division by a number multiplies by it)."""
    return float(torch.tensor(1.0, dtype=dtype) / x)
