"""The blend-spread term of Stage 2: colours that differ along a ray are colours that differ between views.

A pixel's colour is the blend ``sum_i w_i c_i`` of the Gaussians its ray crosses, with weights
``w_i = alpha_i T_i`` that change with the viewpoint. When those Gaussians carry the same colour the
pixel is the same from every view; when Stage 2 paints texture by giving overlapping Gaussians
different colours (the front one red, the one behind it blue), one view sees red and the next one
purple: the stylized scene flickers even though every colour is view-independent. The spread of the
colours along a ray, weighted as the blend weighs them,

    spread = sum_i w_i c_i^2 - (sum_i w_i c_i)^2 / alpha        (alpha = sum_i w_i, per channel)

is ``alpha`` times the weighted variance of the colours the pixel mixes: 0 when they agree, whatever
their colour, so the term leaves the texture *between* surfaces free and penalises only texture that
exists in one view's blend. It is rendered in the same rasterizer pass as the image, as extra
channels (``c``, ``c^2`` and a constant 1, with no background: :func:`render_with_spread`), and
:func:`blend_spread` turns those channels into the mean spread over the pixels. :func:`empty_loss` is Stage 2's
other per-pixel term: empty pixels keep the unstylized render (``--hold-empty``). :class:`ViewPairs`
compares a view with its neighbours warped into it (``--consistency-weight``).
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch

from ..core.cameras import Cameras
from ..errors import InputError
from ..raster import rendering

SPREAD_CHANNELS = 10    # composited RGB (3), sum w c (3), sum w c^2 (3), alpha (1)


def render_with_spread(scene, cams: Cameras, background: Optional[torch.Tensor] = None, **kwargs) -> torch.Tensor:
    """``[C, H, W, 10]``: the RGB render composited over ``background`` (as Stage 2's plain render),
    then ``sum w c``, ``sum w c^2`` and ``alpha``, from one differentiable rasterizer call of 7
    channels (the colours as :func:`ssgwarp.raster.rendering.gaussian_colors` gives them)."""
    cams = cams.to(scene.device)
    colors = rendering.gaussian_colors(scene, cams)                              # [C, N, 3]
    rows = torch.cat([colors, colors * colors, torch.ones_like(colors[..., :1])], dim=-1)
    out, _, _ = rendering.render(scene, cams, rgb=False, extra=rows, **kwargs)   # no background
    rgb = out[..., :3]
    if background is not None:   # composited as the rasterizer composites: + (1 - alpha) background
        rgb = rgb + (1.0 - out[..., 6:7]) * background.to(out.device, out.dtype).reshape(1, 1, 1, 3)
    return torch.cat([rgb, out[..., :7]], dim=-1)


def blend_spread(channels: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    """Mean over pixels of ``sum_ch (sum w c^2 - (sum w c)^2 / alpha)`` from the channels of
    :func:`render_with_spread` (``[..., 10]``); pixels with ``alpha < eps`` count as 0."""
    c, c2, alpha = channels[..., 3:6], channels[..., 6:9], channels[..., 9:10]
    spread = c2 - c * c / alpha.clamp_min(eps)
    spread = torch.where(alpha > eps, spread, torch.zeros_like(spread))
    return spread.sum(-1).mean()


def empty_loss(image: torch.Tensor, original: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Stage 2's empty-region term (``--hold-empty``): ``mean((1 - a) |I - I0|^2) / max(mean(1 - a), 0.01)`` for
    ``image``/``original [H, W, 3]`` and the original's accumulated opacity ``alpha [H, W]``: the pixels the
    unstylized scene leaves (nearly) empty keep its render, so low-opacity Gaussians over the background do not
    become coloured floaters; ~0 on a capture that fills the frame."""
    empty = 1 - alpha.to(image).clamp(0, 1)
    return (empty[..., None] * (image - original.to(image)) ** 2).mean() / empty.mean().clamp_min(0.01)


def check_pair_options(budget: float, neighbours: int) -> None:
    """The view-pair term's options: a finite budget >= 0, at least one neighbour."""
    if not (math.isfinite(budget) and budget >= 0):
        raise InputError(f"--consistency-budget {budget}: must be a finite number >= 0")
    if neighbours < 1:
        raise InputError(f"--consistency-neighbours {neighbours}: must be >= 1")


class ViewPairs:
    """Stage 2's view-pair term (``--consistency-weight``): a training view's render against its neighbours'.

    Stage 2 changes colours only, so the geometry of every training view (expected depth, opacity) is fixed:
    it is rendered once (:meth:`build`). At a step on view ``v`` a neighbour ``u`` (one of the ``neighbours``
    training cameras nearest to ``v``'s centre, chosen by the step) is rendered with the current colours
    and without gradient, warped into ``v`` by exact reprojection through the depths
    (:func:`ssgwarp.evaluation.metrics.reprojection_warp`: the pixels both views see, opaque, not occluded;
    the warp ``ssgwarp evaluate`` scores consistency with), and

        pair = max(0, mean_mask |I_v - warp(I_u)|^2 / e0(v, u) - budget)

    with ``e0`` the same error of the scene Stage 2 starts from: the pair's squared error may grow to
    ``budget`` times the scene's own (``budget`` 2: an RMSE ratio of about 1.4) before the term pulls ``v``'s
    pixels towards what ``u`` shows of the same surface. Measured (docs/notes/stylize-history.md): it trades
    texture for consistency at the same rate as the blend spread; the two are alternatives.
    """

    def __init__(self, cameras: Cameras, depths: torch.Tensor, alphas: torch.Tensor, neighbours: list[list[int]],
                 reference: Optional[dict] = None, budget: float = 0.0, seed: int = 0) -> None:
        self.cameras, self.depths, self.alphas = cameras, depths, alphas
        self.neighbours, self.seed, self.budget = neighbours, int(seed), float(budget)
        self.reference: dict[tuple[int, int], float] = dict(reference or {})
        self.render: Optional[Callable[[int], torch.Tensor]] = None   # view -> its current render [H, W, 3]

    @staticmethod
    def nearest(cameras: Cameras, k: int) -> list[list[int]]:
        """For each camera the ``k`` other cameras whose centres are nearest (fewer when there are fewer)."""
        c = cameras.centers.double()
        d = torch.cdist(c, c)
        d.fill_diagonal_(float("inf"))
        k = min(int(k), len(cameras) - 1)
        return [d[i].argsort()[:k].tolist() for i in range(len(cameras))] if k > 0 else [[] for _ in range(len(cameras))]

    @classmethod
    @torch.no_grad()
    def build(cls, scene, cameras: Cameras, neighbours: int = 4, background: Optional[torch.Tensor] = None,
              budget: float = 0.0, seed: int = 0) -> "ViewPairs":
        """Render the depths and opacities of ``cameras`` once; each pair's reference error is ``scene``'s own
        (at least a quarter of the mean over the pairs, so a pair the scene happens to match exactly does not
        forbid every change)."""
        from ..raster.rendering import render_views

        bg = None if background is None else [float(x) for x in background.reshape(-1)[:3]]
        views = render_views(scene, cameras, bg)
        pairs = cls(cameras, views.depth, views.alpha, cls.nearest(cameras, neighbours), None, budget, seed)
        errs = {(v, u): pairs.error(views.rgb[v], v, views.rgb[u], u) for v in range(len(cameras))
                for u in pairs.neighbours[v]}
        errs = {k: float(e) for k, e in errs.items() if e is not None}
        floor = max(sum(errs.values()) / len(errs), 1e-12) * 0.25 if errs else 1e-12
        pairs.reference = {k: max(e, floor) for k, e in errs.items()}
        return pairs

    def neighbour(self, view: int, step: int) -> Optional[int]:
        """The neighbour of ``view`` at ``step`` (a pure function of seed, step and view), None if it has none."""
        near = self.neighbours[view]
        if not near:
            return None
        g = torch.Generator(device="cpu").manual_seed(self.seed * 1_000_003 + int(step) * 7919 + int(view))
        return near[int(torch.randint(len(near), (1,), generator=g))]

    def error(self, image: torch.Tensor, view: int, other: torch.Tensor, other_view: int) -> Optional[torch.Tensor]:
        """``mean_mask |image - warp(other)|^2`` (differentiable in ``image [H, W, 3]``; ``other`` is held);
        None when the two views share no pixel."""
        from ..evaluation.metrics import View, reprojection_warp

        cam = self.cameras
        a = View(other.detach()[..., :3], self.depths[other_view], self.alphas[other_view], cam.viewmats[other_view],
                 cam.Ks[other_view])
        b = View(image.detach()[..., :3], self.depths[view], self.alphas[view], cam.viewmats[view], cam.Ks[view])
        res = reprojection_warp(a, b)
        if not bool(res.mask.any()):
            return None
        m = res.mask.to(image.dtype)[..., None]
        return (m * (image[..., :3] - res.warped.to(image)) ** 2).sum() / (3 * m.sum())

    def term(self, image: torch.Tensor, view: int, step: int) -> torch.Tensor:
        """:meth:`loss` of ``view``'s ``image`` against the neighbour of ``step``, rendered by :attr:`render`."""
        other = self.neighbour(view, step)
        return image.new_zeros(()) if other is None else self.loss(image, view, self.render(other), other)

    def loss(self, image: torch.Tensor, view: int, other: torch.Tensor, other_view: int) -> torch.Tensor:
        """:meth:`error` relative to the starting scene's error of the pair, less ``budget`` (not below 0);
        0 when the views share nothing."""
        ref = self.reference.get((view, other_view))
        e = None if ref is None else self.error(image, view, other, other_view)
        return image.new_zeros(()) if e is None else torch.relu(e / ref - self.budget)


# ----------------------------------------------------------------------------- the consistency probe (--paint-strength auto)
PROBE_PERIOD = 4.0        # view pixels at the scene's median depth
PROBE_AMPLITUDE = 0.3     # standard deviation of the probe's grey pattern (colour 0..1)
STRENGTH_TARGET = 1.2     # the RMSE ratio to the unpainted scene that painted texture may cost (issue 62's target)
STRENGTH_RANGE = (0.5, 2.0)


def pixel_size(scene, cameras: Cameras) -> float:
    """World size of one pixel at the scene's median depth in the first camera."""
    xyz = scene.means.detach().double().cpu()
    X = torch.cat([xyz, torch.ones(len(xyz), 1, dtype=xyz.dtype)], 1) @ cameras.viewmats[0].double().cpu().T
    z = X[:, 2][X[:, 2] > 0]
    return float(z.median() if len(z) else 1.0) / float(cameras.Ks[0, 0, 0])


def probe_scene(scene, period_px: float, amplitude: float, pixel: float, seed: int = 0):
    """``scene`` with ``amplitude`` x a unit-variance sum of six seeded 3-D sinusoids of ``period_px`` pixels (of
    world size ``pixel`` each) added to its base colour (grey) and its SH bands above 0 zeroed: texture that is
    consistent between views by construction."""
    from ..raster.scene import SH_C0

    g = torch.Generator().manual_seed(seed)
    xyz = scene.means.detach().double().cpu()
    k = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=torch.float64), dim=1)
    k = k * (2 * math.pi / (period_px * pixel))
    phase = torch.rand(6, generator=g, dtype=torch.float64) * 2 * math.pi
    pattern = (torch.sin(xyz @ k.T + phase).sum(1) / math.sqrt(3)).to(scene.sh_dc)
    rest = None if scene.sh_rest is None else torch.zeros_like(scene.sh_rest)
    return scene.replace(sh_dc=scene.sh_dc + (amplitude * pattern / SH_C0)[:, None], sh_rest=rest)


@torch.no_grad()
def consistency_probe(scene, cameras: Cameras, background: Optional[torch.Tensor] = None, neighbours: int = 4,
                      period_px: float = PROBE_PERIOD, amplitude: float = PROBE_AMPLITUDE, seed: int = 0) -> float:
    """The view-pair RMSE ratio that texture fixed in 3-D (:func:`probe_scene`) costs on ``scene``'s geometry:
    ``sqrt(sum of the pairs' squared errors painted / unpainted)`` over each training view and its ``neighbours``
    nearest (:class:`ViewPairs`' warp). 1: texture of that contrast and period costs no consistency; a scene whose
    Gaussians blend several depths pays more."""
    from ..raster.rendering import render_views

    bg = None if background is None else [float(x) for x in background.reshape(-1)[:3]]
    plain = scene.replace(sh_rest=None if scene.sh_rest is None else torch.zeros_like(scene.sh_rest))
    base = render_views(plain, cameras, bg)
    pairs = ViewPairs(cameras, base.depth, base.alpha, ViewPairs.nearest(cameras, neighbours))
    painted = render_views(probe_scene(plain, period_px, amplitude, pixel_size(scene, cameras), seed), cameras, bg).rgb
    e0 = e1 = 0.0
    for v in range(len(cameras)):
        for u in pairs.neighbours[v]:
            a, b = pairs.error(base.rgb[v], v, base.rgb[u], u), pairs.error(painted[v], v, painted[u], u)
            if a is not None and b is not None:
                e0, e1 = e0 + float(a), e1 + float(b)
    return math.sqrt(e1 / e0) if e0 > 0 else 1.0


def strength_for(ratio: float, target: float = STRENGTH_TARGET) -> float:
    """The painting strength for a scene whose probe costs ``ratio``: the share of the probe's contrast that
    keeps the ratio at ``target`` when painted error adds to the scene's own (``r(s)^2 = 1 + s^2 (ratio^2 - 1)``),
    ``sqrt((target^2 - 1) / (ratio^2 - 1))``, within :data:`STRENGTH_RANGE` (its top when painting costs nothing)."""
    if ratio <= 1.0:
        return STRENGTH_RANGE[1]
    return min(max(math.sqrt((target ** 2 - 1) / (ratio ** 2 - 1)), STRENGTH_RANGE[0]), STRENGTH_RANGE[1])


def paint_strength(stage2, tv_weight: float, scene, cams: Cameras, bg: torch.Tensor,
                   say: Callable[[str], None]):
    """``(stage2 with the smoothing weights divided by the painting strength, its record or None)`` for
    ``--paint-strength`` S or ``auto`` (S from :func:`consistency_probe` of ``scene`` on ``cams``, through
    :func:`strength_for`); ``tv_weight``: the TV weight the run would use at strength 1."""
    import dataclasses

    if stage2.paint_strength == 1 or stage2.mode == "finetune":
        return stage2, None
    rec: dict = {"setting": stage2.paint_strength}
    if stage2.paint_strength == "auto":
        ratio = consistency_probe(scene, cams, bg, stage2.consistency_neighbours, seed=stage2.seed)
        rec.update(probe_ratio=ratio, probe_period_px=PROBE_PERIOD, probe_amplitude=PROBE_AMPLITUDE,
                   target=STRENGTH_TARGET)
        s = strength_for(ratio)
    else:
        s = float(stage2.paint_strength)
    tv = tv_weight / s
    rec.update(strength=s, tv_weight=tv, blend_weight=stage2.blend_weight / s)
    say(f"painting strength {s:.2f}" + (f" (the consistency probe costs {rec['probe_ratio']:.2f}x on this scene)"
                                        if "probe_ratio" in rec else "") + f": TV {tv:.3g}, blend spread "
        f"{rec['blend_weight']:.3g}")
    return dataclasses.replace(stage2, tv_weight=tv, blend_weight=rec["blend_weight"]), rec
