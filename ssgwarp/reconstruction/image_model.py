"""What a training image is made of besides the splats, as a part of :class:`~ssgwarp.reconstruction.trainer.Trainer`:
the sky behind them (``--sky``, :mod:`ssgwarp.reconstruction.sky`) and each photo's exposure and white balance
(``--appearance``, :mod:`ssgwarp.reconstruction.appearance`): their decisions, the training image, their part of
the checkpoint, and the trainer's renders and held-out evaluation (the whole image, or the half protocol)."""
from __future__ import annotations

import logging
from typing import Optional, Sequence

import torch

from ..core.optim import adam
from ..errors import InputError
from ..raster.rendering import render
from ..evaluation.held_out import score_views
from ..services.loop import to_cpu
from . import appearance as appearance_mod
from . import sky as sky_mod

log = logging.getLogger("ssgwarp.reconstruction.reconstruct")


class ImageModel:
    """The :class:`Trainer`'s sky and per-image appearance (a mixin: it uses the trainer's data, scene, step)."""

    def _init_image_model(self, appearance: str, sky: str) -> None:
        self._init_appearance(appearance_mod.check_mode(appearance))
        self.sky_mode, self.sky_record, self.environment = sky_mod.check_mode(sky), None, None
        self.env_opt = None

    def _decide_image_model(self) -> None:
        """Once the initial scene (and its backdrop plan) is made."""
        self._init_sky()
        if self.appearance_mode == "auto":
            self._set_appearance(self._appearance_probe())
            log.info("appearance auto: %s", self.appearance_record["why"])
        elif self.appearance is not None:   # on: the probe's gains to start from, where the capture has points
            gains = self._appearance_probe().get("_gains")
            if gains is not None:
                self.appearance.start_from(gains)
                self.appearance_record["from_probe"] = True

    # -- per-image appearance (ssgwarp.reconstruction.appearance) ---------------------------------
    def _init_appearance(self, mode: str) -> None:
        self.appearance_mode = mode
        self.appearance_start = appearance_mod.start_step(self.iters)
        self.appearance: Optional[appearance_mod.Appearance] = None
        self.appearance_record: Optional[dict] = None   # (auto: set once the initial scene is made)
        if mode != "auto":
            self._set_appearance({"mode": mode, "use": mode == "on", "why": f"--appearance {mode}"})

    def _set_appearance(self, record: dict) -> None:
        gains = record.pop("_gains", None)
        self.appearance_record = {**record, "start_step": self.appearance_start}
        if record["use"] and self.appearance is None:
            self.appearance = appearance_mod.Appearance(len(self.data.names), self.data.train_ids, self.device)
            if gains is not None:   # the probe's gains from the first step (refitted from start_step on)
                self.appearance.start_from(gains)
                self.appearance_record["from_probe"] = True

    def _render_premultiplied(self, i: int, sh_degree: Optional[int] = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(colour [H, W, 3] on a zero background, alpha [H, W, 1])`` of view ``i`` (no gradient)."""
        with torch.no_grad():
            img, alpha, _ = render(self.scene.detach(), self.data.cameras[i],
                                   sh_degree=self.sh_degree if sh_degree is None else sh_degree,
                                   backgrounds=torch.zeros(1, 3, device=self.device), rasterize=self.rasterize,
                                   **self.raster_kwargs)
            if self.environment is not None:  # the sky: part of the picture, opaque
                img = self.environment.composite(img[..., :3], alpha, self.data.cameras[i])
                alpha = torch.ones_like(alpha)
        return img[0, ..., :3], alpha[0]

    def _appearance_probe(self) -> dict:
        """``auto``: the decision from the capture's own points (:func:`appearance.points_probe`)."""
        none = {"mode": "auto", "use": False, "probe": None}
        if self.data.points is None or self.data.points_source == "random":
            return {**none, "why": "no points of the capture's own (random initial points): no evidence, off "
                                   "(--appearance on turns it on)"}
        rec = appearance_mod.points_probe(self.data, self.data.points[0], seed=self.seed)
        return rec if rec is not None else {**none, "why": "fewer than 200 of the capture's points are seen by "
                                                           "3 training views: no evidence, off"}

    def _appearance_step(self):
        """The transforms this step trains with (None: off, or before their start step and no probe's gains)."""
        if self.appearance is None or (self.step < self.appearance_start and
                                       not self.appearance_record.get("from_probe")):
            return None
        return self.appearance

    # -- the sky behind the splats (ssgwarp.reconstruction.sky) -------------------------------------
    def _init_sky(self) -> None:
        layout = None if self.backdrop is None else self.backdrop.layout
        self.sky_record = sky_mod.decide(self.data, self.sky_mode, layout,
                                         self.backdrop is not None and bool(self.backdrop.use))
        if self.sky_record["use"]:
            self.environment = sky_mod.initial(self.data, self.device)
            self.env_opt = adam([{"params": [self.environment.grid], "lr": sky_mod.LR * self.lr_factor,
                                  "name": "environment"}], betas=self.betas)

    def _composite(self, color: torch.Tensor, alpha: torch.Tensor, cameras, bg: torch.Tensor):
        """The render on its background: the sky where there is one (then fully opaque), else ``bg``.
        Returns ``(colour, alpha)`` (alpha: what the appearance transform's offset scales)."""
        if self.environment is None:
            return color + (1.0 - alpha) * bg[:, None, None, :3], alpha
        return self.environment.composite(color, alpha, cameras), torch.ones_like(alpha)

    @property
    def eval_protocol(self) -> str:
        """How held-out views are scored: the whole image, or (appearance on) the half protocol."""
        return appearance_mod.HALF_PROTOCOL if self.appearance is not None else appearance_mod.FULL_PROTOCOL

    def _env_params(self) -> list[torch.Tensor]:
        return [] if self.environment is None else [self.environment.grid]

    def _picture(self, app, views, img, alphas, cam, gt, bg, masks) -> torch.Tensor:
        """The training image from the render on black: the sky (or ``bg``) behind it, then each photo's
        transform (``app``: the :class:`appearance.Appearance` of this step, or None)."""
        if app is None:
            return self._composite(img, alphas, cam, bg)[0]
        if self.environment is not None:
            img, alphas = self._composite(img, alphas, cam, bg)
        return app(views, img, alphas, gt, bg, masks, fit=self.step >= self.appearance_start)

    def _half_view(self, i: int, gt: torch.Tensor, mask: Optional[torch.Tensor]):
        """``(prediction, ground truth, mask)`` of held-out view ``i`` under the half protocol."""
        c, a = self._render_premultiplied(i)
        pred, gt, m = appearance_mod.score_half(c, a, gt[0], self.data.background_tensor(3),
                                                None if mask is None else mask[0])
        return pred[None], gt[None], None if m is None else m[None]

    def image_model_state(self) -> dict:
        """The sky's and the appearance's part of the checkpoint (:class:`~ssgwarp.reconstruction.checkpoint.TrainState`)."""
        return {"sky": {"record": self.sky_record,
                        "grid": None if self.environment is None else self.environment.grid.detach().cpu(),
                        "optimizer": None if self.env_opt is None else to_cpu(self.env_opt.state_dict())},
                "appearance": {"record": self.appearance_record,
                               "state": None if self.appearance is None else self.appearance.state_dict()}}

    def load_image_model(self, st: dict) -> None:
        """Restore :meth:`image_model_state`'s part of a checkpoint ``st``; a sky where the run has none (or none
        where it has one) is one line naming the flag."""
        sky = st.get("sky")
        if (sky is not None and sky.get("grid") is not None) != (self.environment is not None):
            raise InputError(f"the checkpoint was trained {'with' if self.environment is None else 'without'} "
                             f"a sky (--sky); pass --sky {'on' if self.environment is None else 'off'} to resume it")
        if self.environment is not None:
            with torch.no_grad():
                self.environment.grid.copy_(sky["grid"].to(self.device))
            if sky.get("optimizer") is not None:
                self.env_opt.load_state_dict(sky["optimizer"])
        app = st.get("appearance")
        if app is not None and app.get("record") is not None:
            self.appearance = None
            self._set_appearance(app["record"])
            if self.appearance is not None and app.get("state") is not None:
                self.appearance.load_state_dict(app["state"])

    # -- evaluation -----------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, ids: Sequence[int]) -> torch.Tensor:
        """``[len(ids), H, W, 3]`` renders of the data's views ``ids`` at the final SH degree."""
        scene = self.scene.detach()
        out = []
        bg = self.data.background_tensor(3)[None]
        for i in ids:
            if self.environment is not None:
                img = self._render_premultiplied(i)[0][None]
            else:
                img, _, _ = render(scene, self.data.cameras[i], sh_degree=self.sh_degree, backgrounds=bg,
                                   rasterize=self.rasterize, **self.raster_kwargs)
            out.append(img[0, ..., :3].clamp(0.0, 1.0))
        return torch.stack(out) if out else torch.zeros(0, self.data.height, self.data.width, 3)

    @torch.no_grad()
    def evaluate(self, ids: Optional[Sequence[int]] = None, lpips=None) -> dict:
        """PSNR / SSIM (and LPIPS when a model is given) over the views ``ids`` (default: test views), scored by
        :func:`ssgwarp.evaluation.held_out.score_views` (appearance on: the half protocol, :meth:`_half_view`)."""
        ids = list(self.data.test_ids if ids is None else ids)
        return score_views((self._scored_view(i) for i in ids), lpips=lpips)

    @torch.no_grad()
    def _scored_view(self, i: int):
        """``(name, prediction, target, mask)`` of view ``i`` as it is scored."""
        gt = self.data.images[i][None]
        mask = None if self.data.masks is None else self.data.masks[i][None]
        if self.appearance is not None:
            pred, gt, mask = self._half_view(i, gt, mask)
            return self.data.names[i], pred, gt, mask
        return self.data.names[i], self.render([i]), gt, mask
