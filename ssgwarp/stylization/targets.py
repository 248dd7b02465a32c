"""What Stage 2 matches inside ``ssgwarp stylize`` (:mod:`ssgwarp.stylization.stylize`), and the steps that
change the scene before the optimisation.

* :class:`Targets` / :func:`targets_for`: the stylized key views (with their cameras and group maps), or the
  style image; without Stage 1, on a grouped scene in ``ist`` mode, the style image's regions assigned to
  the groups (:func:`style_regions_for`, :mod:`ssgwarp.stylization.regions`);
* :func:`color_transfer`: ARF's colour transfer against them (per group, per region, or global);
* :func:`densify_run`: Gaussians split where the style loss wants detail (:mod:`ssgwarp.stylization.densify`),
  recorded in ``OUT/densify.pt`` and replayed on ``--resume``.

The functions read the command's inputs ``r`` (:class:`ssgwarp.stylization.stylize.Inputs`: scene, cameras,
style, options; frozen) and return what they make: the targets, a recoloured scene and its background, a densified
scene with its groups.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import torch

from ..core.cameras import Cameras
from ..raster.scene import GaussianScene
from .stage2 import render_alphas, render_rgb
from .color import describe_transfer, transfer_background, transfer_colors


def group_maps(scene: GaussianScene, cams: Cameras, classifier, progress: bool) -> torch.Tensor:
    from ..raster.groups import render_group_maps

    labels = []
    for c in range(len(cams)):  # one view at a time: the probabilities are dropped right away
        lab, _ = render_group_maps(scene, cams[c], classifier)
        labels.append(lab)
    return torch.cat(labels)


@dataclass(frozen=True)
class Targets:
    """What Stage 2 matches: the stylized key views (with their cameras and group maps) or the style image."""

    use_keys: bool
    key_images: Optional[torch.Tensor] = None
    key_cams: Optional[Cameras] = None
    key_labels: Optional[torch.Tensor] = None
    assign: Optional[torch.Tensor] = None
    regions: Optional[dict] = None               # without Stage 1, grouped, ist: the style image's regions
    view_labels: Optional[torch.Tensor] = None   # the training views' group maps (when regions are used)


def style_regions_for(r, originals: torch.Tensor) -> Targets:
    """Without Stage 1 (``ist`` on a grouped scene): the style image's regions and each group's region
    (:mod:`ssgwarp.stylization.regions`), so that Stage 2 still matches per group."""
    from ..raster.groups import gaussian_groups
    from .regions import style_regions

    view_labels = group_maps(r.scene, r.train_cams, r.classifier, r.progress)
    alphas = render_alphas(r.scene, r.train_cams)
    regions = style_regions(r.style_at_views[0].float(), originals.float(), view_labels, int(r.num_groups),
                            alphas=alphas, seed=r.stage2.seed, check=r.stage2.region_check)
    return Targets(False, key_labels=regions["labels"][None].to(r.device),
                   assign=gaussian_groups(r.scene, r.classifier)[0], regions=regions, view_labels=view_labels)


def targets_for(r, kv, stylized, originals: Optional[torch.Tensor] = None) -> Targets:
    use_keys = stylized is not None and r.stage2.mode in ("ist", "finetune")
    if not use_keys:
        if r.stage2.mode == "ist" and r.classifier is not None and (r.num_groups or 0) > 1 and originals is not None:
            return style_regions_for(r, originals)
        return Targets(False)
    from .keyviews import from_diffusion

    key_images = from_diffusion(stylized.to(r.device).float(), r.cams.width, r.cams.height).to(r.scene.dtype)
    key_cams = r.cams[list(kv.ids)]
    if r.classifier is None:
        return Targets(True, key_images, key_cams)
    from ..raster.groups import gaussian_groups

    return Targets(True, key_images, key_cams, key_labels=group_maps(r.scene, key_cams, r.classifier, r.progress),
                   assign=gaussian_groups(r.scene, r.classifier)[0])


def color_transfer(r, t: Targets, sc: GaussianScene, when: str, against: str,
                   bg: torch.Tensor) -> tuple[GaussianScene, dict, torch.Tensor]:
    """ARF's colour transfer against the stylized key views (per group when grouped) or the style image:
    ``(scene, what it did, background)``; with ``--background transfer`` the stylized scene's background ``bg``
    goes through its global map (else it comes back as it was)."""
    kw = {"max_gain": r.stage2.color_max_gain, "keep_detail": r.stage2.color_detail == "keep", "capture": r.scene}
    if t.use_keys:
        out, info = transfer_colors(sc, t.key_cams, t.key_images, labels=t.key_labels, target_labels=t.key_labels,
                                    assign=t.assign, num_groups=r.num_groups, **kw)
    elif t.regions is not None:
        out, info = transfer_colors(sc, r.train_cams, r.style_at_views, labels=t.view_labels,
                                    target_labels=t.key_labels, assign=t.assign, num_groups=r.num_groups,
                                    target_groups=t.regions["region"].tolist(), **kw)
    else:
        out, info = transfer_colors(sc, r.train_cams, r.style_at_views, **kw)
    if r.stage2.background == "transfer":
        bg = r.bg.new_tensor(transfer_background(bg.tolist(), info))
    r.say(f"colour transfer ({when}): " + describe_transfer(info, against))
    return out, info, bg


def densify_run(r, t: Targets, work: GaussianScene, loss, bg: torch.Tensor) -> tuple[GaussianScene, dict, Targets]:
    """Split Gaussians where the style loss wants detail (:mod:`ssgwarp.stylization.densify`); on ``--resume``
    the splits recorded in ``OUT/densify.pt`` are replayed (the exact Gaussians the checkpoint holds).
    ``(scene, the record, the targets with the new Gaussians' groups)``; ``bg``: the background renders use."""
    from ..core.fileio import atomic_path
    from .densify import densify_for_style, replay
    from .spread import render_with_spread

    path, stage2, group = r.out / "densify.pt", r.stage2, r.group
    record, parent = None, None
    if group.is_main and r.resume and path.is_file():
        record = torch.load(path, map_location="cpu", weights_only=False)
    elif group.is_main:
        draw = render_with_spread if loss.cfg.blend_weight > 0 else render_rgb

        def image_grad(scene: GaussianScene, view: int) -> torch.Tensor:
            with torch.no_grad():
                image = draw(scene, r.train_cams[[view]], bg)[0]
            image = image.detach().requires_grad_(True)
            return torch.autograd.grad(loss(image, view, 0), image)[0]

        work, parent, record = densify_for_style(
            work, r.train_cams, image_grad, lambda sc, cam: render_rgb(sc, cam, bg), stage2.densify,
            views=stage2.densify_views, progress=lambda m: r.say(m))
        with atomic_path(path) as tmp:
            torch.save(record, tmp)
    record = group.broadcast(record)       # under torchrun every process takes the main one's splits
    if parent is None:
        work, parent = replay(work, record["indices"])
    if t.assign is not None:
        t = replace(t, assign=t.assign[parent.to(t.assign.device)])
    return work, {k: v for k, v in record.items() if k != "indices"}, t
