"""How well group maps agree across views, and the grouping stage's plot.

:func:`reprojection_agreement` lifts each covered pixel of a view with its rendered expected
depth, projects it into a neighbouring view (:func:`neighbour_pairs`) and compares the labels
there, counting only pixels that pass an occlusion test. :func:`plot_training` draws
``groups/groups.png``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..core.cameras import Cameras
from ..core.fileio import atomic_path
from ..core.geometry import project, unproject
from ..raster.scene import GaussianScene

Tensor = torch.Tensor


def neighbour_pairs(cameras: Cameras, ids: Optional[Sequence[int]] = None) -> list[tuple[int, int]]:
    """Each camera of ``ids`` paired with its nearest other camera (centre distance + viewing angle)."""
    ids = list(range(len(cameras))) if ids is None else list(ids)
    if len(ids) < 2:
        return []
    c = cameras.centers.double()[ids]
    f = cameras.forwards.double()[ids]
    d = torch.cdist(c, c)
    scale = d[d > 0].median() if bool((d > 0).any()) else torch.tensor(1.0, dtype=d.dtype)
    cost = d / scale + (1.0 - f @ f.T)
    cost.fill_diagonal_(float("inf"))
    j = cost.argmin(dim=1).tolist()
    return [(ids[a], ids[b]) for a, b in enumerate(j)]


def reprojection_agreement(scene: GaussianScene, cameras: Cameras, labels: Tensor,
                           pairs: Optional[Sequence[tuple[int, int]]] = None, *, alpha_min: float = 0.5,
                           depth_tol: float = 0.05) -> dict:
    """How often group maps agree across views, by reprojecting pixels with the rendered depth.

    Each pixel of view a (alpha >= ``alpha_min``) is lifted with its expected
    depth, projected into view b and compared with b's label there; only
    pixels that land inside b, on a covered pixel whose depth agrees within
    ``depth_tol`` (relative; occlusion test) count.

    Args:
        labels: ``[C, H, W]`` group maps of ``cameras``. pairs: ``(a, b)`` camera
        indices, default :func:`neighbour_pairs`.
    Returns:
        ``{"mean": fraction over all counted pixels, "pairs": [{"a", "b", "agreement", "pixels"}]}``.
    """
    pairs = neighbour_pairs(cameras) if pairs is None else list(pairs)
    dev, dt = scene.device, scene.dtype
    cams = cameras.to(dev, dt)
    need = sorted({i for p in pairs for i in p})
    depth, alpha = {}, {}
    with torch.no_grad():
        for i in need:
            d, a, _ = scene.render(cams[i], render_mode="ED")
            depth[i], alpha[i] = d[0, ..., 0], a[0, ..., 0]
    H, W = cams.height, cams.width
    out, tot_agree, tot = [], 0, 0
    for a, b in pairs:
        uv, zb = project(unproject(depth[a], cams.Ks[a], cams.viewmats[a]), cams.viewmats[b], cams.Ks[b])
        ub, vb = uv[..., 0], uv[..., 1]
        ok = (alpha[a] >= alpha_min) & (zb > 1e-6) & (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
        ui = ub.floor().long().clamp(0, W - 1)
        vi = vb.floor().long().clamp(0, H - 1)
        db = depth[b][vi, ui]
        ok = ok & (alpha[b][vi, ui] >= alpha_min) & ((db - zb).abs() <= depth_tol * zb.abs())
        same = (labels[a].to(dev) == labels[b].to(dev)[vi, ui]) & ok
        n_ok, n_same = int(ok.sum()), int(same.sum())
        out.append({"a": int(a), "b": int(b), "agreement": (n_same / n_ok) if n_ok else None, "pixels": n_ok})
        tot_agree += n_same
        tot += n_ok
    return {"mean": (tot_agree / tot) if tot else None, "pixels": tot, "pairs": out}


def plot_training(path: Path, criterion: Optional[dict], history: list[dict], title: str) -> None:
    """``groups.png``: the training losses over the steps and, mask-free, the K criterion."""
    # matplotlib is imported here, not at the top: it costs ~0.3 s at start-up and only this plot needs it;
    # a bare Figure draws with the Agg canvas, without choosing a process-wide backend
    from matplotlib.figure import Figure

    has_crit = bool(criterion and criterion.get("values"))
    fig = Figure(figsize=(10 if has_crit else 5, 3.6))
    axes = fig.subplots(1, 2 if has_crit else 1)
    axes = np.atleast_1d(axes)
    ax = axes[0]
    if history:
        st = [h["step"] for h in history]
        ax.plot(st, [h["ce"] for h in history], label="cross entropy / log K")
        regs = [(h["step"], h["reg"]) for h in history if h.get("reg")]
        if regs:
            ax.plot(*zip(*regs), label="3D KL / K")
        ax.set_yscale("log")
        ax.legend()
    ax.set_xlabel("step")
    ax.set_title("training loss")
    if has_crit:
        ks = sorted(int(k) for k in criterion["values"])
        vals = [criterion["values"][k] if k in criterion["values"] else criterion["values"][str(k)] for k in ks]
        ax2 = axes[1]
        ax2.plot(ks, vals, "o-")
        ax2.axvline(criterion.get("chosen_k", ks[0]), color="gray", ls="--", label=f"chosen K={criterion.get('chosen_k')}")
        ax2.set_xlabel("K")
        ax2.set_ylabel(criterion.get("measure", "log-eigengap"))
        ax2.set_title(f"K criterion (final K={criterion.get('final_k')})")
        ax2.legend()
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
