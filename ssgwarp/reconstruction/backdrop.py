"""Far content and sky: initial Gaussians for what lies beyond a capture's initial points.

A capture's initial points (COLMAP's, triangulated, or random in a cube around the point the cameras look
at) cover what several views see up close. The room behind an object, a city around a rooftop, the sky, are
often not among them, and 3DGS cannot carry Gaussians there during training: densification only clones and
splits Gaussians that already render into those pixels. :func:`plan_backdrop` decides, from the geometry,
whether a capture needs more, and :func:`backdrop_points` makes it:

* **rays**: points along the training views' rays beyond the initial points, at depths uniform in inverse
  depth from the view's median point depth to the far radius, coloured by their pixel;
* **shell**: a Fibonacci sphere at the far radius around the cameras (the sky and anything at infinity),
  each point coloured by the training view that sees it closest to its optical axis (points no view sees
  are dropped).

The decision (:func:`plan_backdrop`) uses the camera layout and how much of the training images the
initial points cover: the fraction of an 8 x 8 grid of cells of each view hit by a point in front of it or
showing nothing but the background colour (median over views). A capture gets a backdrop when its cameras
look outward (``inside-out``: the optical axes do not meet in front of the cameras), when its points are the
random cube of a transforms.json capture without points and its images are not an object on a plain
ground (less than 30% background-colour pixels), when a forward-facing capture's points were triangulated
(they hold the textured foreground, not what lies beyond it), or when the coverage is below
:data:`MIN_COVERAGE` and the photos show far content where the points leave the images uncovered
(:func:`far_evidence`: a plane sweep of the uncovered cells against neighbouring views finds at least
:data:`MIN_FAR` of the cells beyond twice the depth of the points; uncovered cells alone are no evidence:
sparse COLMAP points leave walls and tables uncovered). A forward-facing capture with COLMAP points or an
object capture whose points fill the images or whose uncovered cells are near or textureless keeps its points
alone.

With a backdrop (and for any inside-out capture) the densification rules measure sizes against the
distance from the cameras beyond the initial points' radius (:class:`ssgwarp.reconstruction.strategy.DefaultStrategy`: ``scene_radius``), so a
distant Gaussian as wide as a few pixels is neither split as "large" nor pruned as too big for the scene.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from ..capture.loaders import focus_point, random_points_in_frusta
from ..core.geometry import project
from ..errors import InputError

log = logging.getLogger("ssgwarp.reconstruction.reconstruct")

MODES = ("auto", "on", "off")
MIN_COVERAGE = 0.9       # median fraction of image cells the initial points must hit to go without a backdrop
GRID = 8                 # cells per image side for the coverage
PLAIN_TOL = 0.02         # a cell whose pixels are all this close to the background colour is empty
PLAIN_FRACTION = 0.3     # images with at least this fraction of background-colour pixels: an object on a plain ground
FAR_FACTOR = 50.0        # far radius = this x the larger of the cameras' radius and the points' median distance
RAY_FRACTION = 0.7       # of the backdrop points: along rays (the rest on the far shell)
# the far-background evidence (far_evidence: a plane sweep of the cells no point falls in)
MIN_FAR = 0.05           # mean fraction of image cells showing far content that earns a backdrop
SWEEP_VIEWS = 16         # views swept (evenly spaced training views)
SWEEP_SIZE = 160         # their long side (pixels)
SWEEP_PLANES = 32        # depth planes, uniform in inverse depth from half the nearest points' depth to infinity
SWEEP_WINDOW = 7         # NCC window (pixels)
SWEEP_MAX_ANGLE = 30.0   # neighbours look within this angle (degrees) of the view's direction
SWEEP_BASELINE = 0.1     # neighbours' preferred baseline, as a fraction of the view's median point depth
TEXTURE_STD = 0.02       # windowed grey standard deviation of a textured pixel
TEXTURED_CELL = 0.25     # fraction of a cell's pixels that must be textured (and matched) to carry evidence
FAR_NCC = 0.5            # the far plane's NCC must reach this
FAR_MARGIN = 0.1         # and beat every plane at or in front of the points by this


@dataclass
class BackdropPlan:
    """What :func:`plan_backdrop` found: ``layout`` ("forward-facing", "object-centred", "inside-out"),
    ``coverage`` (median fraction of image cells hit by the initial points), ``use`` (whether a backdrop is
    added), ``why`` (one line), ``evidence`` (:func:`far_evidence`'s, where it was measured), and, once made,
    the backdrop's ``points`` count, ``far_radius`` and the initial points' ``scene_radius`` around ``center``."""

    layout: str
    coverage: float
    use: bool
    why: str
    mode: str = "auto"
    points: int = 0
    far_radius: Optional[float] = None
    scene_radius: Optional[float] = None
    center: Optional[list] = field(default=None)
    evidence: Optional[dict] = None

    def record(self) -> dict:
        """For ``metrics.json`` / ``data.json``."""
        return {"mode": self.mode, "used": self.use, "why": self.why, "layout": self.layout,
                "coverage": round(self.coverage, 4), "points": self.points,
                "far_radius": None if self.far_radius is None else round(self.far_radius, 6),
                "scene_radius": None if self.scene_radius is None else round(self.scene_radius, 6),
                "far_cells": None if self.evidence is None else round(self.evidence["far"], 4)}


def camera_layout(cameras) -> str:
    """``"forward-facing"`` (optical axes within 35 degrees of their mean), ``"inside-out"`` (the point
    nearest to all optical axes lies behind or beside most cameras: they look outward) or
    ``"object-centred"`` (they look at a common point in front of them)."""
    fwd = torch.nn.functional.normalize(cameras.forwards.double().cpu(), dim=1)
    mean = torch.nn.functional.normalize(fwd.mean(0), dim=0) if float(fwd.mean(0).norm()) > 1e-6 else None
    if mean is not None and float((fwd @ mean).min()) >= math.cos(math.radians(35.0)):
        return "forward-facing"
    to_focus = focus_point(cameras).double() - cameras.centers.double().cpu()
    cos = (torch.nn.functional.normalize(to_focus, dim=1) * fwd).sum(1)
    # a common point in front, within the view cone (about 30 degrees off axis) of most cameras
    return "object-centred" if float((cos > math.cos(math.radians(30.0))).double().mean()) >= 0.75 else "inside-out"


def _plain_cells(images: torch.Tensor, background, grid: int) -> torch.Tensor:
    """``[C, grid, grid]`` bool: cells of ``images [C, H, W, 3]`` whose every pixel is the background colour."""
    bg = torch.as_tensor(background, dtype=images.dtype)
    off = ((images - bg).abs().amax(dim=-1) > PLAIN_TOL).float()[:, None]        # [C, 1, H, W]
    return torch.nn.functional.adaptive_max_pool2d(off, grid)[:, 0] == 0


def image_coverage(cameras, xyz: torch.Tensor, ids, grid: int = GRID, max_points: int = 200_000,
                   images: Optional[torch.Tensor] = None, background=(1.0, 1.0, 1.0)) -> float:
    """Median over the views ``ids`` of the fraction of a ``grid x grid`` partition of the image with at least
    one of the points ``xyz [P, 3]`` in front of the camera (with ``images``, cells showing nothing but the
    ``background`` colour count as covered)."""
    if xyz is None or len(xyz) == 0 or not len(ids):
        return 0.0
    plain = None if images is None else _plain_cells(images[list(ids)].cpu(), background, grid)
    xyz = xyz.double().cpu()
    if len(xyz) > max_points:
        xyz = xyz[torch.randperm(len(xyz), generator=torch.Generator().manual_seed(0))[:max_points]]
    fr = []
    for j, i in enumerate(ids):
        uv, z = project(xyz, cameras.viewmats[i].double().cpu(), cameras.Ks[i].double().cpu())
        u, v = uv[z > 1e-9].unbind(-1)
        ok = (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
        cu = (u[ok] / cameras.width * grid).long().clamp(0, grid - 1)
        cv = (v[ok] / cameras.height * grid).long().clamp(0, grid - 1)
        hit = torch.zeros(grid * grid, dtype=torch.bool)
        hit[cv * grid + cu] = True
        if plain is not None:
            hit |= plain[j].reshape(-1)
        fr.append(float(hit.double().mean()))
    return float(torch.tensor(fr).median())


def _grey(images: torch.Tensor, size: int) -> torch.Tensor:
    """``[C, h, w]`` grey images area-averaged so that the long side is at most ``size``."""
    g = (images.float() @ torch.tensor([0.299, 0.587, 0.114]))[:, None]
    H, W = g.shape[-2:]
    f = max(1, math.ceil(max(H, W) / size))
    return torch.nn.functional.avg_pool2d(g, f, ceil_mode=True)[:, 0] if f > 1 else g[:, 0]


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    """Sums over ``(2r+1) x (2r+1)`` windows of ``x [..., H, W]`` (zeros beyond the edges), same shape."""
    k = 2 * r + 1
    c = torch.nn.functional.pad(x, (r + 1, r, r + 1, r)).cumsum(-1).cumsum(-2)
    return c[..., k:, k:] - c[..., :-k, k:] - c[..., k:, :-k] + c[..., :-k, :-k]


def _ncc(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor, r: int) -> torch.Tensor:
    """Windowed normalised cross-correlation of ``a`` and ``b`` (``[..., H, W]``) over the pixels where
    ``valid``; NaN where a window has an invalid pixel."""
    m = valid.to(a.dtype)
    a, b = a * m, b * m
    n = _box(m, r).clamp(min=1)
    ma, mb = _box(a, r) / n, _box(b, r) / n
    va = (_box(a * a, r) / n - ma * ma).clamp(min=0)
    vb = (_box(b * b, r) / n - mb * mb).clamp(min=0)
    ncc = (_box(a * b, r) / n - ma * mb) / (va * vb + 1e-8).sqrt()
    return ncc.masked_fill(_box(1 - m, r) > 0.5, float("nan"))


def _sweep_neighbours(cams, i: int, candidates, depth: float, count: int = 2) -> list[int]:
    """The ``count`` views of ``candidates`` best placed for a plane sweep from view ``i``: looking within
    :data:`SWEEP_MAX_ANGLE` degrees of its direction, baseline nearest :data:`SWEEP_BASELINE` x ``depth``."""
    fwd = torch.nn.functional.normalize(cams.forwards.double().cpu(), dim=1)
    c = cams.centers.double().cpu()
    score = []
    for j in candidates:
        if j == i or float(fwd[i] @ fwd[j]) < math.cos(math.radians(SWEEP_MAX_ANGLE)):
            continue
        b = float((c[j] - c[i]).norm()) / max(depth, 1e-12)
        if b > 1e-3:
            score.append((abs(math.log(b / SWEEP_BASELINE)), j))
    return [j for _, j in sorted(score)[:count]]


@torch.no_grad()
def far_evidence(cameras, images: torch.Tensor, xyz: torch.Tensor, ids, candidates=None, grid: int = GRID,
                 views: int = SWEEP_VIEWS, size: int = SWEEP_SIZE, planes: int = SWEEP_PLANES,
                 background=None) -> dict:
    """How much of the views ``ids`` shows a far background: textured image cells no point of ``xyz`` falls in
    whose content two neighbouring views (among ``candidates``, default ``ids``) place beyond twice the depth of
    the farthest points (95th percentile) that view sees, and not at or in front of it.

    A plane sweep per view (at most ``views`` of them, images at most ``size`` pixels on their long side):
    the neighbours' grey images are warped onto fronto-parallel planes at ``planes`` depths uniform in inverse
    depth from half the nearest points' depth to infinity, and compared with the view by windowed normalised
    cross-correlation (NCC). A cell is **far** when the best plane of its textured pixels' mean NCC lies beyond
    twice that depth, scores at least :data:`FAR_NCC`, and beats every plane at or in front of the points by
    :data:`FAR_MARGIN` (the points cannot explain it). Textureless cells (a wall, a plain sky, the background
    colour) carry no evidence either way.

    Returns ``far`` (mean over the swept views of their fraction of far cells), ``uncovered`` (mean fraction of
    cells no point falls in), ``textured`` (mean fraction of uncovered cells with texture) and ``views``.
    """
    ids = list(ids)
    candidates = ids if candidates is None else list(candidates)
    if xyz is None or len(xyz) < 8 or len(candidates) < 2:
        return {"far": 0.0, "uncovered": 1.0, "textured": 0.0, "views": 0}
    pick = [ids[int(k)] for k in torch.linspace(0, len(ids) - 1, min(views, len(ids))).round().long().unique()]
    xyz = xyz.double().cpu()
    if len(xyz) > 50_000:
        xyz = xyz[torch.randperm(len(xyz), generator=torch.Generator().manual_seed(0))[:50_000]]
    H, W = cameras.height, cameras.width
    plain = None if background is None else _plain_cells(images[pick].cpu(), background, grid)
    far_fr, unc_fr, tex_fr, n = [], [], [], 0
    for k, i in enumerate(pick):
        V = cameras.viewmats[i].double().cpu()
        K = cameras.Ks[i].double().cpu()
        uv, z = project(xyz, V, K)
        front = z > 1e-9
        u, v = uv[front].unbind(-1)
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        if int(ok.sum()) < 8:
            continue
        zs = z[front][ok]
        d_lo, d_hi = float(torch.quantile(zs, 0.05)), float(torch.quantile(zs, 0.95))
        cells = torch.zeros(grid * grid, dtype=torch.bool)
        cells[(v[ok] / H * grid).long().clamp(0, grid - 1) * grid + (u[ok] / W * grid).long().clamp(0, grid - 1)] = True
        if plain is not None:
            cells |= plain[k].reshape(-1)
        nb = _sweep_neighbours(cameras, i, candidates, float(zs.median()))
        if not nb:
            continue
        grey = _grey(images[[i] + nb].cpu(), size).double()
        h, w = grey.shape[-2:]
        sx, sy = w / W, h / H
        r = SWEEP_WINDOW // 2
        std = (_box(grey[0] ** 2, r) / _box(torch.ones_like(grey[0]), r)
               - (_box(grey[0], r) / _box(torch.ones_like(grey[0]), r)) ** 2).clamp(min=0).sqrt()
        # the cells no point falls in whose pixels are textured; each as a block of ch x cw pixels plus a
        # margin of half a window (so its windows see their whole neighbourhood)
        ch, cw = -(-h // grid), -(-w // grid)
        cy = (torch.arange(h) * grid // h).clamp(max=grid - 1)
        cx = (torch.arange(w) * grid // w).clamp(max=grid - 1)
        tex_frac = torch.zeros(grid * grid, dtype=torch.float64).index_add_(
            0, (cy[:, None] * grid + cx[None, :]).reshape(-1), (std > TEXTURE_STD).double().reshape(-1))
        tex_frac /= torch.bincount((cy[:, None] * grid + cx[None, :]).reshape(-1), minlength=grid * grid)
        todo = ((~cells) & (tex_frac >= TEXTURED_CELL)).nonzero()[:, 0]
        far = torch.zeros(grid * grid, dtype=torch.bool)
        if len(todo):
            y0 = (todo // grid) * h // grid - r
            x0 = (todo % grid) * w // grid - r
            by = y0[:, None] + torch.arange(ch + 2 * r)                                    # [N, bh]
            bx = x0[:, None] + torch.arange(cw + 2 * r)                                    # [N, bw]
            inside = ((by >= 0) & (by < h))[:, :, None] & ((bx >= 0) & (bx < w))[:, None, :]
            Y = by.clamp(0, h - 1)[:, :, None].expand(-1, -1, bx.shape[1])
            X = bx.clamp(0, w - 1)[:, None, :].expand(-1, by.shape[1], -1)
            ref = grey[0][Y, X]                                                            # [N, bh, bw]
            tex = std[Y, X] > TEXTURE_STD
            rays = torch.stack([((X + 0.5) / sx - K[0, 2]) / K[0, 0], ((Y + 0.5) / sy - K[1, 2]) / K[1, 1],
                                torch.ones(X.shape, dtype=torch.float64)], -1)            # [N, bh, bw, 3], z = 1
            inv = torch.linspace(2.0 / d_lo, 0.0, planes, dtype=torch.float64)            # inverse depths
            c2w = torch.linalg.inv(V)
            score = torch.zeros(planes, len(todo), dtype=torch.float64)
            count = torch.zeros(planes, len(todo), dtype=torch.float64)
            core = (slice(None), slice(None), slice(r, r + ch), slice(r, r + cw))
            for m, j in enumerate(nb):
                rel = cameras.viewmats[j].double().cpu() @ c2w                          # view i -> view j
                Kj = cameras.Ks[j].double().cpu()
                p = (rays @ rel[:3, :3].T)[None] + inv[:, None, None, None, None] * rel[:3, 3]  # [P, N, bh, bw, 3]
                zj = p[..., 2]
                uj = (Kj[0, 0] * p[..., 0] / zj.clamp(min=1e-12) + Kj[0, 2]) * sx
                vj = (Kj[1, 1] * p[..., 1] / zj.clamp(min=1e-12) + Kj[1, 2]) * sy
                gxy = torch.stack([uj / w * 2 - 1, vj / h * 2 - 1], -1)
                warped = torch.nn.functional.grid_sample(
                    grey[1 + m][None, None].expand(planes, 1, h, w), gxy.reshape(planes, -1, gxy.shape[-2], 2),
                    mode="bilinear", padding_mode="zeros", align_corners=False)[:, 0].reshape(zj.shape)
                valid = (zj > 0) & (gxy.abs() <= 1).all(-1) & inside[None]
                ncc = _ncc(ref[None].expand_as(warped), warped, valid, r)[core]
                good = torch.isfinite(ncc) & tex[None][core]
                score += torch.where(good, ncc, torch.zeros_like(ncc)).sum((2, 3))
                count += good.double().sum((2, 3))
            curve = (score / count.clamp(min=1)).masked_fill(count < TEXTURED_CELL * ch * cw, -1.0)   # [P, N]
            best, arg = curve.max(0)
            near = curve[inv >= 1.0 / d_hi].amax(0)
            far[todo] = (inv[arg] <= 0.5 / d_hi) & (best >= FAR_NCC) & (best - near >= FAR_MARGIN)
        textured_cells = len(todo)
        far_fr.append(float(far.double().mean()))
        unc_fr.append(float((~cells).double().mean()))
        tex_fr.append(textured_cells / max(1, int((~cells).sum())))
        n += 1
    if not n:
        return {"far": 0.0, "uncovered": 1.0, "textured": 0.0, "views": 0}
    mean = lambda x: sum(x) / len(x)
    return {"far": mean(far_fr), "uncovered": mean(unc_fr), "textured": mean(tex_fr), "views": n}


def plan_backdrop(data, xyz: Optional[torch.Tensor], mode: str = "auto") -> BackdropPlan:
    """Whether the capture ``data`` (:class:`~ssgwarp.capture.datasets.SceneData`) starting from the points
    ``xyz`` needs a backdrop (``mode`` "auto"), or is given one regardless ("on") or not ("off")."""
    if mode not in MODES:
        raise InputError(f"backdrop mode {mode!r}: choose one of {', '.join(MODES)}")
    ids = list(data.train_ids)
    layout = camera_layout(data.cameras[ids]) if len(ids) > 1 else "forward-facing"
    cov = image_coverage(data.cameras, xyz, ids, images=data.images, background=data.background)
    if mode != "auto":
        return BackdropPlan(layout, cov, mode == "on", f"--backdrop {mode}", mode)
    if layout == "inside-out":
        return BackdropPlan(layout, cov, True, "the cameras look outward (inside-out)", mode)
    if data.points_source == "random":
        # measured (7k steps, H200): random points with a backdrop / without: colmap_cup 21.45 / 18.65 dB,
        # fern images_8 27.52 / 27.32 dB; the living room's random cube 29.38 / 17.18 dB
        bg = torch.as_tensor(data.background, dtype=data.images.dtype, device=data.images.device)
        plain = float(((data.images[ids] - bg).abs().amax(dim=-1) <= PLAIN_TOL).double().mean())
        if plain < PLAIN_FRACTION:
            return BackdropPlan(layout, cov, True, "random initial points stand for no surface in particular, and "
                                "the images show more than an object on a plain ground", mode)
    if layout == "forward-facing" and data.points_source == "triangulated":
        # measured (fern images_8, 7k steps, H200): triangulated points alone 26.07 dB, with a backdrop 27.55 dB
        # (COLMAP's points 27.33); orbit captures were better without one (cup 29.66 / 28.72, room 29.40 / 23.63)
        return BackdropPlan(layout, cov, True, "a forward-facing capture's triangulated points hold its textured "
                            "foreground, not what lies beyond it", mode)
    if cov < MIN_COVERAGE:
        # cells the points leave uncovered are not enough (a phone capture's 4.4k COLMAP points covered 78% of
        # an object-centred capture and the backdrop cost 1.9 dB): the views must show far content there
        ev = far_evidence(data.cameras, data.images, xyz, ids, background=data.background)
        if ev["far"] >= MIN_FAR:
            return BackdropPlan(layout, cov, True, f"the initial points cover {cov:.0%} of the image cells and "
                                f"{ev['far']:.0%} of the cells show content beyond twice their depth "
                                f"(>= {MIN_FAR:.0%})", mode, evidence=ev)
        return BackdropPlan(layout, cov, False, f"the initial points cover {cov:.0%} of the image cells; "
                            f"{ev['far']:.0%} of the cells show content beyond twice their depth "
                            f"(< {MIN_FAR:.0%})", mode, evidence=ev)
    return BackdropPlan(layout, cov, False, f"the initial points cover {cov:.0%} of the image cells", mode)


def with_backdrop(data, xyz: torch.Tensor, rgb: torch.Tensor, mode: str = "auto", budget: Optional[int] = None,
                  seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, BackdropPlan]:
    """The initial points ``(xyz, rgb)`` of ``data`` with a backdrop appended when :func:`plan_backdrop` says so,
    and the plan. ``budget``: the most points in all (a budgeted strategy's): the backdrop takes at most a third
    and the initial points are subsampled (seeded) to leave it room. An inside-out capture without a backdrop
    still gets its far field (``plan.scene_radius``)."""
    plan = plan_backdrop(data, xyz, mode)
    if plan.use:
        n_far = backdrop_count(len(xyz), pixels=len(data.train_ids) * data.height * data.width)
        if budget is not None and len(xyz) + n_far > budget:
            n_far = min(n_far, budget // 3)
            keep = torch.randperm(len(xyz), generator=torch.Generator().manual_seed(seed + 4))
            keep = keep[:budget - n_far].sort().values
            xyz, rgb = xyz[keep], rgb[keep]
        bx, bc = backdrop_points(data, xyz, n_far, plan, seed)
        xyz, rgb = torch.cat([xyz, bx.to(xyz)]), torch.cat([rgb, bc.to(rgb)])
        log.info("backdrop: %d far points (%s; layout %s), far radius %.3g", plan.points, plan.why, plan.layout,
                 plan.far_radius)
    elif plan.layout == "inside-out":  # no backdrop, but what the views show is far all the same
        far_field_radius(data, xyz, plan)
    return xyz, rgb, plan


def backdrop_count(n_initial: int, pixels: int = 0) -> int:
    """How many backdrop points a cloud of ``n_initial`` points gets: half as many, but at least one per 32
    training pixels (a sparse triangulated cloud of a few hundred points still gets a backdrop that can cover
    the images), 2,000 to 100,000."""
    return int(min(100_000, max(2_000, n_initial // 2, pixels // 32)))


@torch.no_grad()
def backdrop_points(data, xyz: torch.Tensor, n: int, plan: BackdropPlan, seed: int = 0
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` backdrop points for ``data`` beyond the initial points ``xyz``: ``(xyz [M, 3], rgb [M, 3])``,
    ``M <= n`` (shell points no training view sees are dropped). Fills ``plan``'s radii and count."""
    ids = list(data.train_ids)
    cams = data.cameras[ids].to("cpu")
    images = data.images[ids].cpu()
    center, cam_radius, median = far_field_radius(data, xyz, plan)
    far = FAR_FACTOR * max(cam_radius, median, 1e-6)
    # per view: rays from the median depth of the points it sees (or the cameras' radius) to the far radius
    # (a view that sees no point: rays from the cameras' radius, uniform in log depth, not in inverse depth,
    # which would put most of them within a few radii of the camera: floaters, docs/reconstruction.md)
    near = torch.empty(len(ids), dtype=torch.float64)
    blind = np.zeros(len(ids), dtype=bool)
    for j in range(len(ids)):
        V = cams.viewmats[j].double()
        z = (xyz.double().cpu() @ V[2, :3] + V[2, 3])
        z = z[z > 0]
        near[j] = float(z.median()) if len(z) else max(cam_radius, 1e-3 * far)
        blind[j] = len(z) == 0
    near = near.clamp(min=1e-3 * far, max=0.5 * far)
    n_rays = int(round(RAY_FRACTION * n))
    rx, rc = random_points_in_frusta(cams, images, near.numpy(), torch.full((len(ids),), far).numpy(), n_rays,
                                     seed + 11, log_depth=blind)
    sx, sc = _shell(cams, images, center, far, n - n_rays)
    plan.points = len(rx) + len(sx)
    plan.far_radius = far
    return torch.cat([rx, sx]).float(), torch.cat([rc, sc]).float()


def far_field_radius(data, xyz: torch.Tensor, plan: BackdropPlan) -> tuple[torch.Tensor, float, float]:
    """Set ``plan.center`` (the training cameras' centroid) and ``plan.scene_radius`` (the 99th percentile of
    the points' distance from it, at least the cameras' radius): beyond it the densification rules measure
    sizes against the distance. Returns ``(center [3] float64, cameras' radius, median point distance)``."""
    centers = data.cameras.centers[list(data.train_ids)].double().cpu()
    center = centers.mean(0)
    cam_radius = float((centers - center).norm(dim=1).max()) if len(centers) > 1 else 0.0
    d = (xyz.double().cpu() - center).norm(dim=1)
    scene_radius = float(torch.quantile(d[:100_000], 0.99)) if len(d) else cam_radius
    median = float(d.median()) if len(d) else cam_radius
    plan.center, plan.scene_radius = center.tolist(), max(scene_radius, cam_radius)
    return center, cam_radius, median


def _shell(cams, images: torch.Tensor, center: torch.Tensor, radius: float, n: int
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Fibonacci points on the sphere ``(center, radius)``, each with the colour of the view that sees it
    nearest its optical axis; points no view sees are dropped."""
    if n <= 0:
        return torch.zeros(0, 3), torch.zeros(0, 3)
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.arccos(1 - 2 * i / n)
    theta = math.pi * (1 + 5 ** 0.5) * i
    dirs = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], 1)
    pts = center + radius * dirs
    best = torch.full((n,), -2.0, dtype=torch.float64)
    rgb = torch.zeros(n, 3)
    centres = cams.centers.double()
    for j in range(len(cams)):
        uv, z = project(pts, cams.viewmats[j].double(), cams.Ks[j].double())
        u, v = uv.unbind(-1)
        cos = z / (pts - centres[j]).norm(dim=1)
        ok = (z > 0) & (u >= 0) & (u < cams.width) & (v >= 0) & (v < cams.height) & (cos > best)
        if bool(ok.any()):
            best[ok] = cos[ok]
            rgb[ok] = images[j, v[ok].long().clamp(max=cams.height - 1), u[ok].long().clamp(max=cams.width - 1)]
    seen = best > -2.0
    return pts[seen].float(), rgb[seen]
