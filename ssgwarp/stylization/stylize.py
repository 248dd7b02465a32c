"""The end-to-end ``ssgwarp stylize`` command: key views, Stage 1 and Stage 2 on a (grouped) run.

:func:`stylize_run` runs one step after the other (each a function of its own, resumable
through ``run.json``): load the run, the style and the feature extractor
(:func:`_open`); key views and Stage 1 (:func:`_keyviews_and_stage1`, :mod:`ssgwarp.stylization.keyviews`,
:mod:`ssgwarp.stylization.diffusion`); Stage 2 (:func:`_stage2`, :mod:`ssgwarp.stylization.stage2`); renders along
the training cameras and a smooth path (:func:`_renders`); metrics, the contact sheet and
``metrics.json`` (:func:`_metrics`). The steps read one frozen :class:`Inputs`, add to the run's
:class:`Record` and hand their results on (:class:`Stage2Output`, :class:`ssgwarp.stylization.targets.Targets`). The
command line (options, ``--quick``, the CPU hint) is :mod:`ssgwarp.commands.stylize`.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import torch

from ..core.cameras import Cameras
from ..errors import InputError, WeightsNotFound
from ..core.imaging import contact_sheet, fit_style, plot_losses, write_video
from ..raster.scene import GaussianScene
from ..services.runs import resume_record
from .targets import Targets, color_transfer, densify_run, group_maps, targets_for
from .stage2 import Stage2Config, ViewLoss, build_targets, optimise, render_alphas, render_batched, render_rgb, trainable_names
from .feature_defaults import style_loss_kind, tv_weight_for, resolve_for

# ----------------------------------------------------------------------------- end to end
@dataclass
class StylizeOptions:
    """Options of :func:`stylize_run` besides Stage 1 and Stage 2 (CLI flags of the same names).

    keyviews / ids / max_side: key-view choice and diffusion resolution (:mod:`ssgwarp.stylization.keyviews`);
    extractor / vgg16 / layers: the feature extractor (:func:`ssgwarp.evaluation.features.load_extractor`);
    path_frames: frames of the smooth camera path (0: none); sheet_views: rows of the contact sheet;
    weights: the config file's ``weights`` mapping.
    """

    keyviews: int = 4
    ids: Optional[list[int]] = None
    max_side: int = 512
    extractor: str = "auto"
    vgg16: Optional[str] = None
    layers: Optional[list[str]] = None
    path_frames: int = 60
    sheet_views: int = 3
    weights: Optional[dict] = None


OUTPUTS = ("run.json", "keyviews", "stage2.ckpt", "scene.ply", "renders", "contact_sheet.png", "loss.png",
           "metrics.json", "path.gif", "densify.pt")


def _say(msg: str, progress: bool) -> None:
    if progress:
        print(f"ssgwarp stylize: {msg}", flush=True)


def _signature(style: Path, scene_dir: Path, s2: Stage2Config, opts: StylizeOptions, s1) -> dict:
    """What must not change between a run and its ``--resume``."""
    # (the batch size is checked by Stage 2's checkpoint, which names the fix)
    cfg = {k: v for k, v in asdict(s2).items() if k not in ("iters", "checkpoint_every", "batch_size")}
    s1d = None
    if s1 is not None:
        s1d = {k: v for k, v in asdict(s1).items() if k not in ("progress", "weights")}
    sig = {"scene_dir": str(scene_dir.resolve()), "style": str(style.resolve()), "stage2": cfg,
           "keyviews": opts.keyviews, "ids": opts.ids, "max_side": opts.max_side, "extractor": opts.extractor,
           "vgg16": opts.vgg16, "layers": opts.layers, "stage1": s1d}
    return resume_record(**sig)      # (the resume record: as it reads back from run.json)


def _prepare_out(out: Path, scene_dir: Path, signature: dict, resume: bool, force: bool, group) -> dict:
    """Claim ``out`` (:func:`ssgwarp.services.runs.claim`: the policy every stage shares) and return the run's
    record: on ``--resume`` the finished stages of the earlier run, which must have had the same options.
    Every process checks; only the main one changes ``out``, after all have looked."""
    from ..services.runs import claim, resumed_stages

    if out.resolve() == scene_dir.resolve():
        raise InputError(f"--out {out}: must differ from the scene folder (it would overwrite its scene.ply)")
    claimed = claim(out, OUTPUTS, force=force, resume=resume, what="a stylize output")
    state: dict = {"signature": signature,
                   "stages": resumed_stages(claimed, "run.json", "signature", signature, "the earlier run",
                                            kind="a stylize record")}
    group.barrier()
    if group.is_main:
        claimed.clear()
        out.mkdir(parents=True, exist_ok=True)
    return state


def _check_explicit_stage1_paths(stage1) -> None:
    """A Stage 1 weight path the user gave explicitly must exist (absent defaults just skip Stage 1)."""
    from ..services import weights as W
    from .diffusion_models import WEIGHT_KEYS

    for key in WEIGHT_KEYS:
        explicit = getattr(stage1, key, None)
        if explicit and W.find(key, explicit) is None:
            raise WeightsNotFound(W.message(key, explicit))

@dataclass(frozen=True)
class Inputs:
    """What the steps of :func:`stylize_run` read and none changes (:func:`_open` makes it): the options, the
    loaded run (scene, cameras, background), the style, the feature extractor and the scene's groups."""

    scene_dir: Path
    style_path: Path
    out: Path
    stage2: Stage2Config
    stage1: object
    opts: StylizeOptions
    device: torch.device
    resume: bool
    progress: bool
    stage1_models: object
    scene: GaussianScene
    data: object
    extractor: object
    style_np: object
    style: torch.Tensor
    cams: Cameras
    train_ids: tuple
    bg: torch.Tensor
    group: object = None
    classifier: object = None
    num_groups: Optional[int] = None

    @property
    def train_cams(self) -> Cameras:
        return self.cams[list(self.train_ids)]

    @functools.cached_property
    def style_scale(self) -> tuple[float, Optional[float]]:
        """``(the style scale used, the style's stroke period in view pixels at scale 1 when measured)``:
        ``--style-scale``, or with ``auto`` :func:`ssgwarp.stylization.scale.auto_style_scale`."""
        if self.stage2.style_scale != "auto":
            return float(self.stage2.style_scale), None
        from .scale import auto_style_scale

        return auto_style_scale(self.style.float().cpu(), self.cams.height, self.cams.width)

    @property
    def style_at_views(self) -> torch.Tensor:
        """The style ``[1, H, W, 3]`` as the style loss and the colour transfer take it (:func:`fit_style`,
        ``--style-scale``)."""
        return fit_style(self.style.to(self.scene.dtype), self.cams.height, self.cams.width,
                         self.style_scale[0]).permute(0, 2, 3, 1)

    def say(self, msg: str) -> None:
        _say(msg, self.progress)


@dataclass
class Record:
    """The run's progress record: ``OUT/run.json`` (the finished steps, for ``--resume``) and the seconds of each
    step, the one thing the steps add to."""

    out: Path
    state: dict
    times: dict = dataclasses.field(default_factory=dict)

    def mark(self, stage: str, **info) -> None:
        from ..core.fileio import write_json

        self.state["stages"][stage] = {"done": True, **info}
        write_json(self.out / "run.json", self.state)


@dataclass(frozen=True)
class Stage2Output:
    """What :func:`_stage2` hands to the renders and the metrics."""

    scene: GaussianScene
    result: object
    originals: torch.Tensor
    matching: str
    transfer: dict
    densify: Optional[dict]
    background: torch.Tensor     # the stylized scene's background (Stage2Config.background)
    sh: dict                     # metrics.json's ``sh``: the SH degree written and why (:func:`_sh_record`)
    strength: Optional[dict] = None   # metrics.json's ``strength``: the painting strength and its probe (--paint-strength)


def _open(scene_dir: Path, style_path: Path, out: Path, stage2: Stage2Config, stage1, opts: StylizeOptions,
          device: torch.device, resume: bool, force: bool, progress: bool, stage1_models, group) -> tuple:
    """Read the inputs and the weights (a missing or corrupt one fails before anything is written to OUT),
    then claim OUT: ``(Inputs, Record)``."""
    from ..services.runs import load_run
    from ..evaluation.features import load_extractor
    from ..core.fileio import read_image, write_json

    from ..services.runs import claim

    style_np = read_image(style_path, 3)                       # InputError when missing / corrupt
    scene, data = load_run(scene_dir, device, load_images=False)
    claim(out, OUTPUTS, force=force, resume=resume, what="a stylize output")   # a taken OUT refuses before any download
    extractor = load_extractor(opts.vgg16, device, opts.layers, kind=opts.extractor, seed=stage2.seed,
                               config=opts.weights, fallback="random-edges")
    stage2 = resolve_for(stage2, extractor)      # the options left to the extractor, made concrete
    if stage1 is not None and stage2.mode != "global" and stage1_models is None:
        _check_explicit_stage1_paths(stage1)
    state = _prepare_out(out, scene_dir, _signature(style_path, scene_dir, stage2, opts,
                                                    stage1 if stage2.mode != "global" else None), resume, force,
                         group)
    if group.is_main:
        write_json(out / "run.json", state)
    cams = data.cameras.to(device)
    classifier, num_groups = None, None
    if (scene_dir / "groups").is_dir():
        if scene.identities is None:
            _say(f"{scene_dir}/groups exists but scene.ply has no identity fields: using one group", progress)
        else:
            from ..raster.groups import load_groups
            gm = load_groups(scene_dir, device)
            classifier, num_groups = gm.classifier, gm.num_groups
    r = Inputs(scene_dir, style_path, out, stage2, stage1, opts, device, resume, progress, stage1_models,
               scene, data, extractor, style_np, torch.from_numpy(style_np).to(device), cams,
               tuple(data.train_ids) or tuple(range(len(cams))),
               torch.tensor(data.background[:3], dtype=scene.dtype, device=device), group, classifier, num_groups)
    r.say(f"{len(scene)} Gaussians, {len(r.train_ids)} training views {cams.width}x{cams.height}, "
          f"{'%d groups' % r.num_groups if r.num_groups else 'no groups (one group)'}, features {extractor.name}, "
          f"device {device}")
    return r, Record(out, state)


def _missing_models(stage1) -> list[str]:
    """The Stage 1 models not (completely) on this machine, by name."""
    from ..services import weights as W
    from ..services.weight_specs import SPECS
    from .diffusion_models import WEIGHT_KEYS

    out = []
    for key in WEIGHT_KEYS:
        found = W.find(key, getattr(stage1, key, None), getattr(stage1, "weights", None))
        if found is None or any(not (found / f).exists() for f in SPECS[key].required):
            out.append(key)
    return out


def _stage1_skipped(names: list[str]) -> str:
    """The one line saying that Stage 1 is skipped: which models are missing and what fetching them costs."""
    from ..services.weight_specs import SPECS

    if not names:
        return "Stage 1 skipped: its models are incomplete (`ssgwarp weights` shows what is missing)"
    size = sum(SPECS[k].size for k in names)
    return (f"Stage 1 skipped: no local {', '.join(names)} (~{size / 1e9:.1f} GB; `ssgwarp weights --download "
            f"stage1` fetches them, `ssgwarp weights` shows where they are looked for)")


def groups_unused(num_groups: Optional[int], mode: str) -> Optional[str]:
    """The line saying that the scene's groups went unused because Stage 1 did not run (None when they are used
    or there are none): IST then matches the style image globally, as the groups only split the stylized key
    views."""
    if not num_groups or mode == "global":
        return None
    return (f"the scene's {num_groups} groups are not used: without Stage 1's stylized key views Stage 2 matches "
            f"the style image globally (groups select which key-view region styles which object; Stage 1 "
            f"weights, `ssgwarp weights --download stage1`, make them count)")


def _keyviews(r: Inputs, rec: Record, for_stage1: bool = True):
    """Select, render and save the key views (or load them on ``--resume``); ``(keyviews, stylized or None)``.
    ``for_stage1`` False: Stage 1 will not run, and the line says that the key views are for inspection only."""
    from . import keyviews as K

    kv_dir, t0 = r.out / "keyviews", time.perf_counter()
    if r.resume and (kv_dir / "keyviews.json").is_file() and rec.state["stages"].get("keyviews", {}).get("done"):
        kv, stylized = K.load_keyviews(kv_dir, r.device)
        rec.times["keyviews"] = rec.state["stages"]["keyviews"].get("seconds", 0.0)
        r.say(f"key views {kv.ids} loaded from {kv_dir}")
        return kv, stylized
    ids = K.select_keyviews(r.cams, r.opts.keyviews, r.opts.ids, candidates=list(r.train_ids))
    size = K.diffusion_size(r.cams.width, r.cams.height, r.opts.max_side)
    kv = K.render_keyviews(r.scene, r.cams, ids, size, r.classifier, background=r.data.background)
    K.save_keyviews(kv, kv_dir)
    rec.times["keyviews"] = time.perf_counter() - t0
    rec.mark("keyviews", seconds=rec.times["keyviews"], ids=list(kv.ids))
    what = (f"at {size[0]}x{size[1]} (Stage 1's size)" if for_stage1 else
            f"saved at {size[0]}x{size[1]} for inspection only (Stage 1 will not run, and Stage 2 does not use them "
            f"without it)")
    r.say(f"key views {kv.ids} ({', '.join(kv.cameras.names)}) {what} -> {kv_dir}")
    return kv, None


def _keyviews_and_stage1(r: Inputs, rec: Record):
    """Key views and Stage 1: ``(keyviews or None, stylized key views or None, the Stage 1 record)``."""
    if r.stage2.mode == "global":
        return None, None, {"ran": False, "reason": "global mode matches against the style image (no key views)"}
    from . import keyviews as K
    from .diffusion import stylize_keyviews
    from .diffusion_models import missing_weights

    stage1 = r.stage1
    # check the weights before anything imports diffusers (seconds of import for nothing)
    missing = [] if r.stage1_models is not None else missing_weights(stage1)
    kv, stylized = _keyviews(r, rec, for_stage1=not missing)
    t0 = time.perf_counter()
    if stylized is not None:
        rec.times["stage1"] = rec.state["stages"].get("stage1", {}).get("seconds", 0.0)
        return kv, stylized, {"ran": True, "cvsa": bool(stage1.cvsa), "resumed": True}
    if missing:
        r.say(_stage1_skipped(_missing_models(stage1)))
    else:
        r.say(f"Stage 1: diffusion on {len(kv)} key views (CVSA {'on' if stage1.cvsa else 'off'})")
        stylized = stylize_keyviews(kv, r.style_np, stage1, r.device, models=r.stage1_models)
        missing = [] if stylized is not None else missing_weights(stage1)
    rec.times["stage1"] = time.perf_counter() - t0
    if stylized is None:
        info = {"ran": False, "reason": "no local diffusion weights: " + " | ".join(missing),
                "cvsa": bool(stage1.cvsa)}
    else:
        info = {"ran": True, "cvsa": bool(stage1.cvsa), "steps": stage1.steps,
                "guidance": stage1.guidance, "ip_adapter_scale": stage1.ip_adapter_scale}
        K.save_keyviews(kv, r.out / "keyviews", stylized.to(kv.rgb.device), extra={"stage1": info})
    rec.mark("stage1", seconds=rec.times["stage1"], **info)
    return kv, stylized, info


def _stage2_loss(r: Inputs, t: Targets, kv, content_ref: torch.Tensor, alphas: torch.Tensor):
    """``(ViewLoss or None, finetune images, finetune cameras, the matching's description)``."""
    stage2 = r.stage2
    ref = {"originals": content_ref, "alphas": alphas}
    if t.use_keys and stage2.mode == "finetune":
        return None, t.key_images, t.key_cams, "none (fine-tuned on the stylized key views)"
    if t.use_keys:
        view_labels = None if r.classifier is None else group_maps(r.scene, r.train_cams, r.classifier, r.progress)
        targets = build_targets(r.extractor, t.key_images, t.key_labels, stage2)
        matching = (f"per group ({r.num_groups} groups) against {len(kv)} stylized key views"
                    if r.classifier is not None else f"global against {len(kv)} stylized key views (no groups)")
        if stage2.style_scale != 1:
            unused = (f"--style-scale {stage2.style_scale} not used: the stylized key views are views already "
                      "(--mode global matches the style image)")
            r.say(unused)
            matching += f" ({unused})"
        return ViewLoss(r.extractor, targets, stage2, view_labels=view_labels, **ref), \
            None, None, matching
    if t.regions is not None:
        targets = build_targets(r.extractor, r.style_at_views, t.key_labels, stage2).for_regions(t.regions["region"])
        used = len(set(t.regions["region"].tolist()) - {-1})
        back = (t.regions.get("fallback") or {}).get("fell_back", [])
        matching = (f"per group ({r.num_groups} groups) against {t.regions['regions']} regions of the style image "
                    f"({used} used; Stage 1 did not run)" + (f"; groups {', '.join(map(str, sorted(back)))} against "
                    "the whole style image (their regions were poor matches)" if back else ""))
        r.say(f"Stage 1 did not run: Stage 2 matches each of the {r.num_groups} groups against its own region "
              f"of the style image")
        return ViewLoss(r.extractor, targets, stage2, view_labels=t.view_labels, **ref), \
            None, None, matching
    targets = build_targets(r.extractor, r.style_at_views, None, stage2)
    matching = "global against the style image"
    if stage2.mode != "global":
        matching += f" (Stage 1 did not run: requested mode '{stage2.mode}' fell back)"
        r.say(groups_unused(r.num_groups, stage2.mode) or
              "Stage 1 did not run: Stage 2 matches against the style image globally")
    return ViewLoss(r.extractor, targets, stage2, **ref), None, None, matching


def _stage2(r: Inputs, rec: Record, kv, stylized) -> Optional[Stage2Output]:
    """Colour transfer, the optimisation and colour transfer again; writes ``scene.ply`` and ``loss.png``."""
    from ..formats.ply import write_ply

    t0 = time.perf_counter()
    r, strength = _strength(r)
    stage2 = r.stage2
    originals = render_batched(r.scene, r.train_cams, r.bg, desc="original renders" if r.progress else None)
    t = targets_for(r, kv, stylized, originals)
    transfer: dict = {"setting": stage2.color_transfer,
                      "against": "the stylized key views" if t.use_keys else
                      "the style image's regions" if t.regions is not None else "the style image"}
    work, bg = r.scene, r.bg
    if stage2.color_transfer in ("pre", "both"):
        work, transfer["pre"], bg = color_transfer(r, t, r.scene, "pre", transfer["against"], bg)
    content_ref = originals if work is r.scene else render_batched(work, r.train_cams, bg)
    alphas = render_alphas(r.scene, r.train_cams)
    loss, ft_images, ft_cams, matching = _stage2_loss(r, t, kv, content_ref, alphas)
    if stage2.style_scale == "auto" and not t.use_keys:
        matching += (f"; style scale auto: {r.style_scale[0]:.2f} (the style's stroke period is "
                     f"{r.style_scale[1]:.1f} view pixels at scale 1)")
    densified = None
    if stage2.densify > 0 and loss is not None:
        work, densified, t = densify_run(r, t, work, loss, bg)
    if stage2.consistency_weight > 0 and loss is not None:   # the geometry is final: its depths once
        from .spread import ViewPairs

        loss.pairs = ViewPairs.build(work, r.train_cams, stage2.consistency_neighbours, bg,
                                     stage2.consistency_budget, stage2.seed)
    run_cfg = stage2
    if stage2.mode == "finetune" and ft_images is None:   # no stylized key views to fit: global fallback
        run_cfg = dataclasses.replace(stage2, mode="global")
    r.say(f"Stage 2 ({stage2.mode}): {stage2.iters} steps, matching {matching}")
    res = optimise(work, r.train_cams, run_cfg, loss=loss, finetune_images=ft_images, finetune_cameras=ft_cams,
                   background=bg, checkpoint=r.out / "stage2.ckpt", resume=r.resume, progress=r.progress,
                   group=r.group)
    if not r.group.is_main:   # the others only helped with the optimisation
        return None
    styled = res.scene
    if stage2.color_transfer in ("post", "both"):
        styled, transfer["post"], bg = color_transfer(r, t, styled, "post", transfer["against"], bg)
    rec.times["stage2"] = time.perf_counter() - t0
    rec.times["stage2_optimisation"] = res.seconds
    sh_source = styled.sh_degree
    styled = written_degree(styled)
    write_ply(r.out / "scene.ply", styled)
    rec.mark("stage2", seconds=rec.times["stage2"], iters=stage2.iters)
    plot_losses(r.out / "loss.png", res.history, f"Stage 2 ({stage2.mode}, {r.extractor.name})")
    return Stage2Output(styled, res, originals, matching, transfer, densified, bg,
                        _sh_record(styled, sh_source, stage2.sh_rest), strength)


def _strength(r: Inputs) -> tuple[Inputs, Optional[dict]]:
    """``--paint-strength``: the inputs with the smoothing weights divided by the painting strength, and its record
    (:func:`ssgwarp.stylization.spread.paint_strength`)."""
    from .spread import paint_strength

    stage2, rec = paint_strength(r.stage2, tv_weight_for(r.stage2, r.extractor), r.scene, r.train_cams, r.bg, r.say)
    return dataclasses.replace(r, stage2=stage2), rec


def _renders(r: Inputs, rec: Record, styled: GaussianScene, bg: torch.Tensor) -> torch.Tensor:
    """``renders/train/*.png``, ``renders/path/frame_*.png`` and ``path.gif``; returns the training renders.
    The files are encoded and written on background threads (:class:`ssgwarp.core.fileio.ImageWriter`) while
    the next views render; all are on disk (or the first error raised) when this returns."""
    from ..core.fileio import ImageWriter
    from ..core.progress import tqdm

    t0, train_cams = time.perf_counter(), r.train_cams
    with ImageWriter() as writer:
        renders = render_batched(styled, train_cams, bg, desc="train renders" if r.progress else None)
        for i, img in enumerate(renders):
            writer.image(r.out / "renders" / "train" / f"{Path(train_cams.names[i]).stem}.png", img.clamp(0, 1))
        if r.opts.path_frames > 0:
            from ..evaluation.render import smooth_path

            path = smooth_path(train_cams, r.opts.path_frames).to(r.device)
            frames = []
            for s in tqdm(range(len(path)), desc="path renders", disable=not r.progress, leave=False):
                with torch.no_grad():
                    frame = render_rgb(styled, path[[s]], bg)[0].clamp(0, 1).float().cpu()   # (read back once)
                writer.image(r.out / "renders" / "path" / f"frame_{s:04d}.png", frame)
                frames.append((frame.numpy() * 255 + 0.5).astype("uint8"))
            writer.call(write_video, r.out / "path.gif", frames)
        t_wait = time.perf_counter()
    # (the phase; the wait for the last writes after the last render; the CPU time of the writes, off this thread)
    rec.times["renders"] = time.perf_counter() - t0
    rec.times["renders_write_wait"] = time.perf_counter() - t_wait
    rec.times["renders_write_cpu"] = writer.cpu
    return renders


def _scores(r: Inputs, rec: Record, styled: GaussianScene, renders: torch.Tensor, originals: torch.Tensor) -> dict:
    """Gram style and content losses and style distances, before and after, on the training views
    (:func:`ssgwarp.evaluation.metrics.style_scores`: ``ssgwarp evaluate --views train`` gives the same numbers)."""
    from ..evaluation.metrics import style_scores

    t0 = time.perf_counter()
    with torch.no_grad():
        alphas = render_alphas(r.scene, r.train_cams)
        changed = r.stage2.free_opacity or len(styled) != len(r.scene)    # opacities freed or Gaussians split
        alphas_after = render_alphas(styled, r.train_cams) if changed else alphas
        sc = style_scores(r.extractor, renders, r.style, originals, alphas=alphas_after, original_alphas=alphas)
    rec.times["metrics"] = time.perf_counter() - t0
    dist = lambda suffix: {k: sc.get(f"style_distance_{k}{suffix}") for k in ("color", "texture")}  # noqa: E731
    return {"gram_style_loss": sc["gram_style_loss"], "gram_style_loss_original": sc["gram_style_loss_original"],
            "style_distance": dist(""), "style_distance_original": dist("_original"),
            "content_loss": sc["content_loss"],
            "empty_regions": ({"share": sc["empty_share"], "spread": sc["empty_spread"],
                               "spread_original": sc["empty_spread_original"]} if "empty_spread" in sc else None)}


def written_degree(scene: GaussianScene) -> GaussianScene:
    """The stylized scene as it is written: when its higher SH bands are all zero (Stage 2's default
    ``--sh-rest zero`` makes its colour view-independent), at SH degree 0, the degree it really has: the
    same renders, a file about 4x smaller, and exports whose size and round trip are a degree-0 scene's."""
    if scene.sh_degree > 0 and scene.sh_rest is not None and not bool(scene.sh_rest.detach().any()):
        return scene.with_sh_degree(0)
    return scene


def _sh_record(styled: GaussianScene, source_degree: int, sh_rest: str) -> dict:
    """metrics.json's ``sh``: the degree written and why."""
    if styled.sh_degree == source_degree:
        why = (f"the source's view-dependent colour (SH degree {source_degree}) kept (--sh-rest {sh_rest})"
               if source_degree > 0 else "the source scene has SH degree 0")
    else:
        why = (f"view-independent colour: the source's SH bands 1-{source_degree} were zeroed (--sh-rest {sh_rest}), "
               f"so the scene is written at degree 0")
    return {"degree": styled.sh_degree, "source_degree": source_degree, "note": why}


def _metrics(r: Inputs, rec: Record, s2: Stage2Output, renders: torch.Tensor, kv, stage1_info: dict, t_start: float) -> dict:
    """Scores, the contact sheet and ``metrics.json``; returns the metrics dict."""
    from ..core.fileio import write_json
    from .batches import batch_record

    stage2, styled, originals, train_ids, device = r.stage2, s2.scene, s2.originals, r.train_ids, r.device
    scores = _scores(r, rec, styled, renders, originals)
    rows = sorted({round(i * (len(train_ids) - 1) / max(1, r.opts.sheet_views - 1))
                   for i in range(min(r.opts.sheet_views, len(train_ids)))})
    contact_sheet(r.out / "contact_sheet.png", originals[rows], renders[rows], r.style,
                  [Path(r.train_cams.names[i]).stem for i in rows],
                  title=f"{stage2.mode}: {s2.matching}; features {r.extractor.name}")
    rec.times["total"] = time.perf_counter() - t_start
    metrics = {
        "source_scene": str(r.scene_dir.resolve()), "style": str(r.style_path.resolve()), "mode": stage2.mode,
        "matching": s2.matching, "stage1": stage1_info, "extractor": r.extractor.name,
        "style_loss": style_loss_kind(stage2, r.extractor), "tv_weight": tv_weight_for(stage2, r.extractor),
        "gram_style_loss": scores["gram_style_loss"], "gram_style_loss_original": scores["gram_style_loss_original"],
        "style_distance": scores["style_distance"], "style_distance_original": scores["style_distance_original"],
        "empty_regions": scores["empty_regions"],
        "metric_views": f"the {len(train_ids)} training views at {r.cams.width}x{r.cams.height} "
                        f"(`ssgwarp evaluate --views train` scores the same; its default is novel path views)",
        "groups_used": bool(r.num_groups) and "per group" in s2.matching,
        "content_loss": scores["content_loss"], "color_transfer": s2.transfer, "final_losses": s2.result.last,
        "keyviews": None if kv is None else {"ids": list(kv.ids), "names": list(kv.cameras.names),
                                              "size": list(kv.size)},
        "background": [float(v) for v in s2.background],
        "groups": r.num_groups, "gaussians": len(styled), "densify": s2.densify, "views": len(train_ids),
        "resolution": [r.cams.width, r.cams.height], "optimised": trainable_names(stage2, r.scene),
        "sh": s2.sh, "strength": s2.strength,
        "config": asdict(stage2),
        **batch_record(s2.result),
        "seconds": rec.times,
        "device": str(device) if device.type != "cuda" else f"cuda ({torch.cuda.get_device_name(device)})",
        "outputs": {"scene": "scene.ply", "renders": "renders/train", "path": "renders/path",
                    **({"path_video": "path.gif"} if r.opts.path_frames > 0 else {}),
                    "contact_sheet": "contact_sheet.png", "loss_plot": "loss.png", "keyviews": "keyviews"},
    }
    write_json(r.out / "metrics.json", metrics)
    rec.mark("done", seconds=rec.times["total"])
    return metrics


def _summary(metrics: dict, out: Path) -> str:
    d0, d1 = metrics["style_distance_original"], metrics["style_distance"]
    g = lambda x: "n/a" if x is None else f"{x:.3g}"  # noqa: E731
    return (f"done in {metrics['seconds']['total']:.1f}s; on the {metrics['views']} training views "
            f"({metrics['extractor']}): style distance colour {g(d0['color'])} -> "
            f"{g(d1['color'])}, texture {g(d0['texture'])} -> {g(d1['texture'])}; Gram style loss "
            f"{metrics['gram_style_loss_original']:.4g} -> {metrics['gram_style_loss']:.4g}, content "
            f"{metrics['content_loss']:.4g}; contact sheet {out / 'contact_sheet.png'}")


def stylize_run(scene_dir: str | Path, style_path: str | Path, out: str | Path, *,
                stage2: Optional[Stage2Config] = None, stage1=None, opts: Optional[StylizeOptions] = None,
                device: torch.device | str = "cpu", resume: bool = False, force: bool = False,
                progress: bool = True, stage1_models=None, group=None) -> dict:
    """``ssgwarp stylize``: key views, Stage 1 and Stage 2 on a (grouped) run; returns the metrics dict.

    Writes into ``out``: ``keyviews/`` (key views, stylized key views, sheet),
    ``stage2.ckpt``, ``scene.ply`` (the stylized scene), ``renders/train/*.png``
    and ``renders/path/frame_*.png``, ``contact_sheet.png``, ``loss.png``,
    ``metrics.json`` and ``run.json`` (options and finished stages, for ``resume``).
    ``stage1`` is a :class:`ssgwarp.stylization.diffusion.Stage1Config` (default: its
    defaults); ``stage1_models`` preloaded Stage 1 models (tests). ``group``: a ``torchrun`` launch's
    :class:`ssgwarp.services.distributed.Group` (:mod:`ssgwarp.stylization.batches`; the others return ``{}``).
    """
    from ..services.distributed import SINGLE
    from .batches import on_main_for_all, resumed_batch_size

    t_start = time.perf_counter()
    group = group if group is not None else SINGLE
    progress = progress and group.is_main
    stage2 = (stage2 or Stage2Config()).validate()
    if stage2.batch_size is None:
        b = resumed_batch_size(Path(out) / "stage2.ckpt", resume) or group.world_size
        stage2 = dataclasses.replace(stage2, batch_size=b)
    opts = opts or StylizeOptions()
    if stage1 is None and stage2.mode != "global":
        from .diffusion_models import Stage1Config
        stage1 = Stage1Config(weights=opts.weights)
    if opts.path_frames < 0 or opts.sheet_views < 1:
        raise InputError("--path-frames must be >= 0 and the contact sheet needs >= 1 view")
    r, rec = _open(Path(scene_dir), Path(style_path), Path(out), stage2, stage1, opts, torch.device(device),
                   resume, force, progress, stage1_models, group)
    kv, stylized, stage1_info = on_main_for_all(group, lambda: _keyviews_and_stage1(r, rec), r.device)  # Stage 1 once
    s2 = _stage2(r, rec, kv, stylized)
    if s2 is None:     # (under torchrun, a process other than the main one)
        return {}
    renders = _renders(r, rec, s2.scene, s2.background)
    metrics = _metrics(r, rec, s2, renders, kv, stage1_info, t_start)
    r.say(_summary(metrics, r.out))
    return metrics
