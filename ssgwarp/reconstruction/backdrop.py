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
:data:`MIN_COVERAGE`. A forward-facing capture with COLMAP points or an object capture whose points fill the
images keeps its points alone.

With a backdrop (and for any inside-out capture) the densification rules measure sizes against the
distance from the cameras beyond the initial points' radius (:class:`ssgwarp.reconstruction.strategy.DefaultStrategy`: ``scene_radius``), so a
distant Gaussian as wide as a few pixels is neither split as "large" nor pruned as too big for the scene.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Optional

import torch

from ..capture.datasets import focus_point, random_points_in_frusta
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


@dataclass
class BackdropPlan:
    """What :func:`plan_backdrop` found: ``layout`` ("forward-facing", "object-centred", "inside-out"),
    ``coverage`` (median fraction of image cells hit by the initial points), ``use`` (whether a backdrop is
    added), ``why`` (one line), and, once made, the backdrop's ``points`` count, ``far_radius`` and the
    initial points' ``scene_radius`` around ``center``."""

    layout: str
    coverage: float
    use: bool
    why: str
    mode: str = "auto"
    points: int = 0
    far_radius: Optional[float] = None
    scene_radius: Optional[float] = None
    center: Optional[list] = field(default=None)

    def record(self) -> dict:
        """For ``metrics.json`` / ``data.json``."""
        return {"mode": self.mode, "used": self.use, "why": self.why, "layout": self.layout,
                "coverage": round(self.coverage, 4), "points": self.points,
                "far_radius": None if self.far_radius is None else round(self.far_radius, 6),
                "scene_radius": None if self.scene_radius is None else round(self.scene_radius, 6)}


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
        return BackdropPlan(layout, cov, True, f"the initial points cover {cov:.0%} of the image cells "
                            f"(< {MIN_COVERAGE:.0%})", mode)
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
    near = torch.empty(len(ids), dtype=torch.float64)
    for j in range(len(ids)):
        V = cams.viewmats[j].double()
        z = (xyz.double().cpu() @ V[2, :3] + V[2, 3])
        z = z[z > 0]
        near[j] = float(z.median()) if len(z) else max(cam_radius, 1e-3 * far)
    near = near.clamp(min=1e-3 * far, max=0.5 * far)
    n_rays = int(round(RAY_FRACTION * n))
    rx, rc = random_points_in_frusta(cams, images, near.numpy(), torch.full((len(ids),), far).numpy(), n_rays,
                                     seed + 11)
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
