"""Per-image appearance: the exposure and white balance of each training photo (``reconstruct --appearance``).

Photos of one scene often differ in exposure and white balance (phones' auto-exposure, photos from the
web). A scene trained on them averages the exposures: the renders match none of the photos. Here each
training image ``i`` gets an affine colour transform ``T_i`` (a 3x3 matrix and an offset) that maps the
render to that photo's colours before the loss; the scene itself stays one appearance (``scene.ply``,
``ssgwarp render``, the exports: no transform).

The transform acts on the render's premultiplied colour ``c`` and its alpha ``a``:
``out = M_i c + b_i a + (1 - a) background`` (the background of an RGBA capture is a compositing
constant, not part of the photo: it is never transformed).

How the transforms are found (:class:`Appearance`): not by gradient descent (a view is visited a few
times in a short run: 600 steps over 88 views is 7 visits each, too few steps of Adam to reach a gain of
0.6), but in closed form: at each visit, the ridge least-squares fit of the detached render to the photo
(``ridge`` pulls it toward the identity). The transform the loss uses is that fit composed with the
inverse of the mean of all views' latest fits (:meth:`Appearance.gauge`): the scene is pulled toward the
mean exposure of the photos, so the transforms cannot drift together with the scene's colours (mean
pinned to the identity). They start late (:func:`start_step`: after the scene has its coarse colours).

``auto`` decides from evidence, before training, from the capture's own points (:func:`points_probe`): each
of its points (COLMAP's or triangulated) is seen in several training photos (hidden ones left out: the points
as a depth buffer); its log colour there is fitted as the point's log albedo plus the photo's log gain per
channel (alternating medians; observations far from the fit left out), and each photo's gain is measured
twice, from the points in the left and in the right half of the image. An exposure changes the whole photo,
so it shows in both; occlusions, edges, highlights and noise change parts of it. Across photos, the
covariance of the two measurements is the photos' exposure variance, half the variance of their difference
the noise (:func:`_split_half`). On when the exposures spread by at least :data:`MIN_SPREAD` (12 %:
above what the probe reads on captures of one exposure seen all around, where occlusion and shading it does
not model leave 8 %) and the signal is at least :data:`MIN_RATIO` times the noise. A capture without points of its
own (random initial points: triangulation found too few) has no such evidence: ``auto`` is off there
(``--appearance on`` turns it on).

Held-out views (:func:`score_half`, the protocol of the field for per-image appearance, e.g. NeRF-W's and
the "in the wild" benchmarks'): a held-out photo has no trained transform, so one is fitted on the left
half of the image (least squares, the same affine model) and PSNR / SSIM are measured on the right half.
``metrics.json`` says which protocol scored the run (``eval_protocol``).
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

import torch

from ..errors import InputError

MODES = ("auto", "on", "off")
MIN_SPREAD = 0.12   # auto: the photos' exposures must differ by at least this (std of log-gain); the probe
                    # reads 8.0 % on lego_200 (rendered, one exposure) and 8.1 % on colmap_cup, 0.4 % on fern
MIN_RATIO = 2.0     # auto: ... and their variance be this many times the split-half noise
VISIBLE_DEPTH = 0.05  # points probe: a point farther than this fraction behind the nearest one of its cell is hidden
OUTLIER = 0.15      # points probe: log-colour residual beyond which an observation is an outlier (occlusion)
FULL_PROTOCOL = "full image"
HALF_PROTOCOL = ("per-view affine colour transform (3x3 + offset) fitted by least squares on the left half of "
                 "each held-out image, PSNR/SSIM on the right half")


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError(f"--appearance {mode!r}: choose one of {', '.join(MODES)}")
    return mode


def start_step(iters: int) -> int:
    """The step where the transforms start (and ``auto`` probes): a sixth of the run, 50 to 500 steps."""
    return int(min(500, max(50, iters // 6)))


def _features(color: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """``[..., 4]``: the premultiplied colour and the alpha (the affine model's inputs)."""
    return torch.cat([color, alpha], dim=-1)


def fit_affine(x: torch.Tensor, y: torch.Tensor, ridge: float = 1e-2,
               weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``[3, 4]`` affine colour transform ``W`` minimising ``|x W^T - y|^2 + ridge n s |W - [I 0]|^2``
    (``x [..., 4]``: premultiplied colour and alpha; ``y [..., 3]``: the photo less the background's share;
    ``s`` the mean square of ``x``: the ridge is relative). ``weight [...]``: per-pixel weights (masks)."""
    x = x.reshape(-1, 4).double()
    y = y.reshape(-1, 3).double()
    if weight is not None:
        w = weight.reshape(-1, 1).double()
        x, y = x * w, y * w
    n = max(x.shape[0], 1)
    xtx = x.T @ x
    lam = ridge * n * (torch.diagonal(xtx).sum() / (4 * n)).clamp_min(1e-8)
    w0 = torch.eye(3, 4, dtype=torch.float64, device=x.device)
    eye = torch.eye(4, dtype=torch.float64, device=x.device)
    wt = torch.linalg.solve(xtx + lam * eye, x.T @ y + lam * w0.T)
    return wt.T.float()


def apply_affine(W: torch.Tensor, color: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """``M c + b a`` for ``W = [M b]`` (``[3, 4]``) on ``color [..., 3]``, ``alpha [..., 1]``."""
    return color @ W[:, :3].T + alpha * W[:, 3]


def _augment(W: torch.Tensor) -> torch.Tensor:
    A = torch.eye(4, dtype=W.dtype, device=W.device).repeat(*W.shape[:-2], 1, 1)
    A[..., :3, :] = W
    return A


class Appearance:
    """The per-image transforms of one run: ``table [N, 3, 4]`` (one per image of the capture; the identity
    until the view is fitted), fitted in closed form at each visit (module docstring)."""

    def __init__(self, n_images: int, train_ids: Sequence[int], device, ridge: float = 1e-2):
        self.ridge = float(ridge)
        self.train_ids = torch.as_tensor(list(train_ids), dtype=torch.long, device=device)
        self.table = torch.eye(3, 4, device=device).repeat(n_images, 1, 1)
        self.fitted = torch.zeros(n_images, dtype=torch.bool, device=device)

    def start_from(self, log_gains: dict) -> None:
        """Each training photo's transform from the points probe's per-channel log gains (a diagonal), before
        any is fitted: the scene trains against them from the first step."""
        for i, g in log_gains.items():
            self.table[i] = torch.eye(3, 4, device=self.table.device)
            self.table[i, :, :3] = torch.diag(g.exp().to(self.table.device))
            self.fitted[i] = True

    def gauge(self) -> torch.Tensor:
        """``[4, 4]``: the mean of the fitted training views' transforms (augmented; the identity before any)."""
        f = self.fitted[self.train_ids]
        if not bool(f.any()):
            return torch.eye(4, device=self.table.device)
        return _augment(self.table[self.train_ids][f].mean(0))

    def __call__(self, views: Sequence[int], color: torch.Tensor, alpha: torch.Tensor, gt: torch.Tensor,
                 background: torch.Tensor, masks: Optional[torch.Tensor] = None, fit: bool = True) -> torch.Tensor:
        """The training image: each view's fitted transform (gauge-fixed) on ``color [B, H, W, 3]``
        (premultiplied, background 0) and ``alpha [B, H, W, 1]``, composited on ``background [B, 3]``
        (``fit`` False: the stored transforms, not refitted)."""
        inv = torch.linalg.inv(self.gauge())
        out = []
        for j, v in enumerate(views):
            c, a = color[j], alpha[j]
            bg = background[j, :3]
            if fit:
                y = gt[j] - (1.0 - a.detach()) * bg
                W = fit_affine(_features(c.detach(), a.detach()), y, self.ridge,
                               None if masks is None else masks[j])
                self.table[v] = W
                self.fitted[v] = True
            W = self.table[v]
            W_eff = (_augment(W) @ inv)[:3]
            out.append(apply_affine(W_eff, c, a) + (1.0 - a) * bg)
        # a photo clips what its exposure pushes beyond white (or black): so does the transformed render (no
        # gradient there: a clipped pixel does not pull the scene darker)
        return torch.stack(out).clamp(0.0, 1.0)

    def state_dict(self) -> dict:
        return {"table": self.table.detach().cpu(), "fitted": self.fitted.detach().cpu()}

    def load_state_dict(self, st: dict) -> None:
        self.table = st["table"].to(self.table.device)
        self.fitted = st["fitted"].to(self.fitted.device)

    def summary(self) -> dict:
        """The training views' fitted transforms in numbers: gains (mean diagonal), offsets, spread."""
        f = self.fitted[self.train_ids]
        W = self.table[self.train_ids][f]
        if len(W) == 0:
            return {"fitted_views": 0}
        gain = torch.diagonal(W[:, :, :3], dim1=1, dim2=2)  # [V, 3]
        lg = gain.clamp_min(1e-6).log()
        return {"fitted_views": int(len(W)),
                "gain_min": round(float(gain.mean(1).min()), 4), "gain_max": round(float(gain.mean(1).max()), 4),
                "log_gain_std": round(float(lg.mean(1).std()) if len(W) > 1 else 0.0, 4),
                "offset_abs_max": round(float(W[:, :, 3].abs().max()), 4)}


def _split_half(L: torch.Tensor, R: torch.Tensor, rec: dict, what: str) -> dict:
    """The decision from per-view log-gains measured twice independently (``L``, ``R`` ``[V, 3]``): their
    covariance across views is the photos' exposure variance, half their difference's variance the noise."""
    L, R = L.double(), R.double()
    n = len(L)
    Lc, Rc = L - L.mean(0), R - R.mean(0)
    signal = float((Lc * Rc).sum(0).mean() / (n - 1))
    noise = float(((L - R) - (L - R).mean(0)).pow(2).sum(0).mean() / (n - 1) / 2)
    spread = math.sqrt(max(signal, 0.0))
    use = spread >= MIN_SPREAD and signal >= MIN_RATIO * noise
    rec.update({"exposure_spread": round(spread, 4), "signal_variance": round(signal, 6),
                "noise_variance": round(noise, 6), "use": bool(use)})
    rec["why"] = (f"the photos' exposures differ: per-image gains spread {100 * spread:.1f} % (>= {100 * MIN_SPREAD:.0f} %), "
                  f"{what} agree ({signal:.2e} vs noise {noise:.2e})" if use else
                  f"the photos' exposures agree: per-image gain spread {100 * spread:.1f} % "
                  f"(signal {signal:.2e}, noise {noise:.2e}; on needs >= {100 * MIN_SPREAD:.0f} % and "
                  f">= {MIN_RATIO:g}x the noise)")
    return rec


@torch.no_grad()
def points_probe(data, xyz: torch.Tensor, max_points: int = 20_000, seed: int = 0) -> Optional[dict]:
    """The ``auto`` decision before training, from the capture's own points (COLMAP's or triangulated): each
    point's colour in every training view it projects into. ``log colour = log albedo(point) + log gain(view)``
    is fitted robustly (alternating medians, observations far from the fit left out: highlights); a point
    more than :data:`VISIBLE_DEPTH` behind the nearest point of its image cell is hidden (not observed). The view gains are fitted
    twice, from the points seen in the left and in the right half of each image (an exposure changes the
    whole photo; occlusion, edges and highlights change parts of it), and :func:`_split_half` decides. Observations near black or
    white (clipped) are left out. None when fewer than 200 points are seen by 3 views or more (no evidence)."""
    from ..core.geometry import project

    ids = list(data.train_ids)
    if xyz is None or len(xyz) == 0 or len(ids) < 4:
        return None
    g = torch.Generator().manual_seed(seed)
    xyz = xyz.double().cpu()
    if len(xyz) > max_points:
        xyz = xyz[torch.randperm(len(xyz), generator=g)[:max_points]]
    cams = data.cameras
    obs = torch.full((len(xyz), len(ids), 3), float("nan"), dtype=torch.float64)
    left = torch.zeros(len(xyz), len(ids), dtype=torch.bool)   # seen in the left half of the image
    # visibility: the points themselves as a depth buffer of cells holding about 2 points each when all are seen
    cell = max(4.0, math.sqrt(2.0 * cams.width * cams.height / len(xyz)))
    gw, gh = int(math.ceil(cams.width / cell)), int(math.ceil(cams.height / cell))
    for j, i in enumerate(ids):
        uv, z = project(xyz, cams.viewmats[i].double().cpu(), cams.Ks[i].double().cpu())
        u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
        ok = (z > 1e-9) & (u >= 1) & (u < cams.width - 1) & (v >= 1) & (v < cams.height - 1)
        key = (v.clamp(0, cams.height - 1) / cell).long() * gw + (u.clamp(0, cams.width - 1) / cell).long()
        key = torch.where(ok, key, torch.zeros_like(key))
        front = torch.full((gw * gh,), float("inf"), dtype=torch.float64)
        front = front.scatter_reduce(0, key[ok], z[ok], reduce="amin")
        ok &= z <= front[key] * (1.0 + VISIBLE_DEPTH)
        pix = data.images[i].cpu().double()[v[ok], u[ok]]
        good = (pix > 0.03).all(1) & (pix < 0.97).all(1)
        rows = ok.nonzero()[:, 0][good]
        obs[rows, j] = pix[good].log()
        left[:, j] = u < cams.width / 2
    seen = (~obs[..., 0].isnan()).sum(1) >= 3
    obs, left = obs[seen], left[seen]
    rec = {"mode": "auto", "probe": "points", "probe_points": int(len(obs)), "probe_views": len(ids),
           "min_spread": MIN_SPREAD, "min_ratio": MIN_RATIO}
    if len(obs) < 200:
        return None

    def gains(o: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
        gv = torch.nanmedian(o - albedo[:, None], dim=0).values             # [V, 3]
        return torch.nan_to_num(gv - torch.nanmean(gv, dim=0), nan=0.0)

    n0 = int((~obs[..., 0].isnan()).sum())
    gv = torch.zeros(len(ids), 3, dtype=torch.float64)
    for k in range(8):
        albedo = torch.nanmedian(obs - gv[None], dim=1).values             # [P, 3]
        gv = gains(obs, albedo)
        if k >= 3:  # observations far from the fit (occluded: another surface's colour) are left out
            far = (obs - albedo[:, None] - gv[None]).abs().amax(-1) > OUTLIER
            obs = torch.where(far[..., None], torch.full_like(obs, float("nan")), obs)
    rec["inlier_share"] = round(int((~obs[..., 0].isnan()).sum()) / max(n0, 1), 4)
    nan = torch.full_like(obs, float("nan"))
    rec["_gains"] = {int(i): gv[j].float() for j, i in enumerate(ids)}   # (the per-photo log gains: not recorded)
    return _split_half(gains(torch.where(left[..., None], obs, nan), albedo),
                       gains(torch.where(left[..., None], nan, obs), albedo), rec,
                       "the gains of the images' left and right halves")


@torch.no_grad()
def score_half(color: torch.Tensor, alpha: torch.Tensor, gt: torch.Tensor, background: torch.Tensor,
               mask: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, torch.Tensor, Optional[torch.Tensor]]:
    """The held-out protocol with appearance (:data:`HALF_PROTOCOL`): ``(prediction, ground truth, mask)`` of
    the right half of one view, its transform fitted on the left half. ``color [H, W, 3]`` premultiplied,
    ``alpha [H, W, 1]``, ``gt [H, W, 3]``, ``background [3]``, ``mask [H, W]`` (or None)."""
    half = color.shape[1] // 2
    y = gt - (1.0 - alpha) * background
    w = None if mask is None else mask[:, :half]
    W = fit_affine(_features(color[:, :half], alpha[:, :half]), y[:, :half], 1e-3, w)
    right = slice(half, None)
    pred = (apply_affine(W, color[:, right], alpha[:, right]) + (1.0 - alpha[:, right]) * background).clamp(0, 1)
    return pred, gt[:, right], None if mask is None else mask[:, right]
