"""``ssgwarp view``: a pyvista inspection viewer for Gaussian scenes, their groups and cameras.

The cloud is drawn as flat discs sized by each Gaussian's scale (radius =
``sigma`` x the geometric mean of its three standard deviations) or, for a
subsample, as oriented ellipsoids (semi-axes ``sigma`` x scales). Colouring is
the degree-0 SH colour, the group label (the palette of
:mod:`ssgwarp.core.palette`, shared with the group-map renders, with a legend of
group ids and Gaussian counts) or the opacity. Camera frustums are drawn with
the key views highlighted; the splat image of the selected camera, rendered by
our rasterizer, can be shown beside the cloud.

Keys (interactive window):
    c  cycle colouring (rgb → group → opacity)     g  toggle ellipsoid glyphs / discs
    n  select the next camera (N: previous)        k  select the next key view
    l  look through the selected camera            i  render the selected camera's splat image beside the cloud
    h  show/hide this help                         right click  pick a Gaussian (group id and parameters)
A slider sets the opacity threshold (Gaussians below it are hidden).

Python API: :func:`build_viewer` / :class:`Viewer` (``build_plotter`` returns
the pyvista plotter) and :func:`screenshot`; the command is :mod:`ssgwarp.commands.view`.
pyvista is imported only when a viewer is built. The drawing is :mod:`ssgwarp.viewer.drawing`'s.
"""
from __future__ import annotations

import sys
import weakref
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ssgwarp.core.cameras import Cameras
from ssgwarp.errors import InputError, SsgwarpError
from ssgwarp.core.fileio import write_image
from ssgwarp.core.palette import palette
from ssgwarp.raster.scene import GaussianScene

from . import geometry
from .data import (GroupInfo, as_numpy, camera_index, finite_mask, load_cameras, resolve_groups, resolve_keyviews, run_folders)
from .drawing import Drawing
from .headless import has_display, prepare_offscreen

COLOR_MODES = ("rgb", "group", "opacity")
MAX_LEGEND_ROWS = 24
RADIUS_CAP = 0.02  # discs are at most this fraction of the cloud's (1st-99th percentile) diagonal
FRAME_PERCENT = 2.0  # the start view frames the cloud's 2nd-98th percentile box (floaters may fall outside)

HELP = ("keys:  c colouring   g glyphs/discs   n/N next/previous camera   k next key view\n"
        "       l look through camera   i render splat image   h help   right click: pick a Gaussian")

def _fmt(n: int) -> str:
    return f"{n:,}"


class Viewer(Drawing):
    """An inspection viewer of one Gaussian scene (see the module docstring for what it draws).

    Args:
        scene: the Gaussians (any device; the viewer keeps numpy copies, the
            splat render uses ``scene`` on ``device``).
        groups: per-Gaussian labels (:func:`ssgwarp.viewer.data.resolve_groups`), or None.
        cameras: frustums to draw, or None. keyviews: indices of the key-view cameras.
        color: ``rgb``, ``group`` or ``opacity``.
        max_points: point budget; above it a seeded random subsample is drawn (and the status line says so).
        glyphs: start with ellipsoid glyphs instead of discs; ``max_glyphs`` of the drawn Gaussians get one.
        sigma: discs have radius ``sigma`` x the geometric-mean scale, ellipsoids semi-axes ``sigma`` x scales.
        opacity_threshold: Gaussians with opacity below it are hidden.
        frustum_size: frustum depth in world units (default: from camera spacing and scene size).
        off_screen: render without a window (screenshots, tests).
        legend / hud / widgets: draw the group legend / status text / opacity slider
            (``widgets`` defaults to ``not off_screen``).
        render_width: width of the splat image rendered from a camera (aspect kept, never above the camera's).
        device: where the splat image is rendered.
        name: shown in the status line.
    """

    def __init__(self, scene: GaussianScene, *, groups: Optional[GroupInfo] = None,
                 cameras: Optional[Cameras] = None, keyviews: Sequence[int] = (), color: str = "rgb",
                 max_points: Optional[int] = 300_000, glyphs: bool = False, max_glyphs: int = 3000,
                 sigma: float = 1.0, opacity_threshold: float = 0.0, frustum_size: Optional[float] = None,
                 off_screen: bool = False, window_size: tuple[int, int] = (1280, 800), legend: bool = True,
                 hud: bool = True, widgets: Optional[bool] = None, render_width: int = 320,
                 device: torch.device | str = "cpu", background=(0.08, 0.08, 0.10), seed: int = 0,
                 name: str = "scene", log=None):
        if color not in COLOR_MODES:
            raise InputError(f"colour mode must be one of {', '.join(COLOR_MODES)}, got '{color}'")
        if color == "group" and groups is None:
            raise InputError("--color group: the scene has no groups (run `ssgwarp group` first, or pass --labels)")
        if not 0.0 <= opacity_threshold <= 1.0:
            raise InputError(f"opacity threshold must be in [0, 1], got {opacity_threshold}")
        if sigma <= 0:
            raise InputError(f"--sigma must be positive, got {sigma}")
        if max_glyphs <= 0:
            raise InputError(f"--max-glyphs must be positive, got {max_glyphs}")
        self.log = log if log is not None else (lambda msg: print(msg, file=sys.stderr))
        self.scene, self.device, self.name = scene, torch.device(device), name
        self.groups, self.cameras = groups, cameras
        self.keyviews = list(keyviews)
        self.color, self.glyphs, self.sigma = color, glyphs, float(sigma)
        self.max_glyphs, self.threshold, self.seed = int(max_glyphs), float(opacity_threshold), seed
        self.legend, self.hud, self.render_width = legend, hud, int(render_width)
        self.widgets = (not off_screen) if widgets is None else widgets
        self.selected: Optional[int] = (self.keyviews[0] if self.keyviews else 0) if cameras is not None else None
        self.notes: list[str] = []
        self.last_pick: Optional[dict] = None
        self.splat_image: Optional[np.ndarray] = None
        self._panel = None
        self.glyph_count = 0
        self._help_shown = False

        # -- what is drawn: finite Gaussians, within the point budget --------
        n = len(scene)
        ok = finite_mask(scene)
        if not ok.all():
            self.notes.append(f"{_fmt(int((~ok).sum()))} Gaussians with non-finite values are not drawn")
        finite_idx = np.nonzero(ok)[0]
        pick = geometry.subsample_indices(len(finite_idx), max_points, seed)
        self.index = finite_idx[pick]                      # [M] scene indices drawn
        if len(pick) < len(finite_idx):
            self.notes.append(f"showing a random {_fmt(len(pick))} of {_fmt(len(finite_idx))} Gaussians "
                              f"(point budget --max-points {_fmt(int(max_points))})")
        for note in self.notes:
            self.log(f"ssgwarp view: {note}")
        idx_t = torch.as_tensor(self.index, dtype=torch.long, device=scene.means.device)
        sub = scene.subset(idx_t) if len(self.index) < n else scene
        self.xyz = as_numpy(sub.means)
        self.scales = as_numpy(sub.scales)
        self.quats = as_numpy(sub.quats)
        self.opacity = as_numpy(sub.opacities)
        self.rgb = np.clip(as_numpy(sub.base_colors), 0.0, 1.0)
        self.labels = groups.labels[self.index] if groups is not None else None
        lo, hi = (np.percentile(self.xyz, [1, 99], axis=0) if len(self.xyz) else (np.zeros(3), np.ones(3)))
        self.extent = float(np.linalg.norm(hi - lo)) or 1.0
        # the box the start view frames: the 2nd-98th percentiles (far floaters left out)
        self.frame_box = (np.percentile(self.xyz, [FRAME_PERCENT, 100 - FRAME_PERCENT], axis=0)
                          if len(self.xyz) else (np.zeros(3), np.ones(3)))
        self.center = np.median(self.xyz, axis=0) if len(self.xyz) else np.zeros(3)
        self.radii = geometry.point_radii(self.scales, self.sigma, cap=RADIUS_CAP * self.extent)
        rng = np.random.default_rng(seed + 1)
        self._glyph_rank = rng.permutation(len(self.index))  # glyphs: the visible ones of lowest rank
        self.frustum_size = frustum_size if frustum_size is not None else self._auto_frustum_size()

        # -- the plotter -----------------------------------------------------
        if off_screen:
            prepare_offscreen()
        elif not has_display():
            raise SsgwarpError("no display for the interactive viewer (DISPLAY is not set): use "
                               "--screenshot out.png to render off-screen, or run under xvfb-run")
        import pyvista as pv

        self.pv = pv
        self.plotter = pv.Plotter(off_screen=off_screen, window_size=tuple(int(v) for v in window_size),
                                  title=f"ssgwarp view: {name}")
        self.plotter.background_color = background
        if not off_screen:
            self.plotter.enable_anti_aliasing("msaa")
        self._draw_cloud()
        self._draw_cameras()
        self._draw_overlays()
        self._set_start_view()
        self._bind_keys()
        if self.widgets:
            self.plotter.add_slider_widget(self.set_opacity_threshold, rng=[0.0, 1.0], value=self.threshold,
                                           title="min opacity", pointa=(0.04, 0.16), pointb=(0.34, 0.16),
                                           style="modern", interaction_event="end", fmt="%.2f")
            self.plotter.enable_point_picking(callback=self.pick, picker="point", show_message=False,
                                              show_point=True, color="white", point_size=12)

    # -- state -----------------------------------------------------------------
    @property
    def visible(self) -> np.ndarray:
        """``[M]`` bool over the drawn Gaussians: opacity at or above the threshold."""
        return self.opacity >= self.threshold

    @property
    def num_visible(self) -> int:
        return int(self.visible.sum())

    def colors(self, mode: Optional[str] = None) -> np.ndarray:
        """``[M, 3]`` uint8 colours of the drawn Gaussians for ``mode`` (rgb or group)."""
        mode = mode or self.color
        if mode == "group":
            if self.labels is None:
                raise InputError("group colouring: the scene has no groups")
            pal = palette(max(self.groups.num_groups, 1))
            c = np.zeros((len(self.labels), 3), dtype=np.float32)
            ok = (self.labels >= 0) & (self.labels < len(pal))
            c[ok] = pal[self.labels[ok]]
        elif mode == "rgb":
            c = self.rgb
        else:
            import matplotlib

            c = matplotlib.colormaps["viridis"](self.opacity)[:, :3]
        return (np.clip(c, 0, 1) * 255 + 0.5).astype(np.uint8)

    def legend_entries(self) -> list[tuple[str, tuple[float, float, float]]]:
        """``[(text, rgb)]``: one row per group present (id and Gaussian count over the whole scene)."""
        if self.groups is None:
            return []
        counts = self.groups.counts()
        pal = palette(max(self.groups.num_groups, 1))
        present = [g for g in range(self.groups.num_groups) if counts[g] > 0]
        rows = [(f"group {g}: {_fmt(int(counts[g]))}", tuple(float(v) for v in pal[g]))
                for g in present[:MAX_LEGEND_ROWS]]
        if len(present) > MAX_LEGEND_ROWS:
            rest = int(sum(counts[g] for g in present[MAX_LEGEND_ROWS:]))
            rows.append((f"+{len(present) - MAX_LEGEND_ROWS} groups: {_fmt(rest)}", (0.5, 0.5, 0.5)))
        return rows

    def status_text(self) -> str:
        mode = {"rgb": "SH-DC colour", "group": "group", "opacity": "opacity"}[self.color]
        lines = [f"{self.name}: {_fmt(len(self.scene))} Gaussians, SH degree {self.scene.sh_degree}",
                 f"colour: {mode}   shown: {_fmt(self.num_visible)} (opacity >= {self.threshold:.2f})   "
                 + (f"{_fmt(self.glyph_count)} ellipsoids (--max-glyphs)" if self.glyphs else "discs")
                 + f" at {self.sigma:g} sigma"]
        if self.groups is not None:
            lines.append(f"{self.groups.num_groups} groups ({self.groups.source})")
        if self.cameras is not None:
            sel = "" if self.selected is None else f", selected {self.cameras.names[self.selected]}"
            lines.append(f"{len(self.cameras)} cameras, {len(self.keyviews)} key views{sel}")
        return "\n".join(lines + self.notes)

    def _bind_keys(self) -> None:
        pl = self.plotter
        actions = {"c": self.cycle_color, "g": self.toggle_glyphs, "n": lambda: self.next_camera(+1),
                   "N": lambda: self.next_camera(-1), "k": self.next_keyview, "l": self.look_through,
                   "i": self.show_splat, "h": self.toggle_help}
        for key, fn in actions.items():
            pl.add_key_event(key, lambda fn=fn: self._safe(fn))

    def _safe(self, fn) -> None:
        """Run a key action; a failure shows in the window instead of killing it."""
        try:
            fn()
        except (SsgwarpError, RuntimeError, MemoryError) as e:
            self.plotter.add_text(f"error: {e}", position="lower_left", font_size=9, color="red", name="help")
            self.plotter.render()

    def refresh(self) -> None:
        """Redraw the cloud and overlays after a state change."""
        self._draw_cloud()
        self._draw_overlays()
        self.plotter.render()

    # -- actions (also bound to keys) --------------------------------------------
    def set_color(self, mode: str) -> None:
        if mode not in COLOR_MODES:
            raise InputError(f"colour mode must be one of {', '.join(COLOR_MODES)}, got '{mode}'")
        if mode == "group" and self.groups is None:
            raise InputError("group colouring: the scene has no groups")
        self.color = mode
        self.refresh()

    def cycle_color(self) -> None:
        modes = [m for m in COLOR_MODES if m != "group" or self.groups is not None]
        self.set_color(modes[(modes.index(self.color) + 1) % len(modes)])

    def toggle_glyphs(self) -> None:
        self.glyphs = not self.glyphs
        self.refresh()

    def set_opacity_threshold(self, value: float) -> None:
        """Hide Gaussians whose opacity is below ``value``."""
        self.threshold = float(min(max(value, 0.0), 1.0))
        self.refresh()

    def select_camera(self, item) -> int:
        """Select a camera by index or name; returns its index."""
        self.selected = camera_index(item, self.cameras)
        self._draw_selected()
        self._draw_overlays()
        self.plotter.render()
        return self.selected

    def next_camera(self, step: int = 1) -> None:
        if self.cameras is not None:
            self.select_camera(((self.selected or 0) + step) % len(self.cameras))

    def next_keyview(self) -> None:
        if self.keyviews:
            pos = self.keyviews.index(self.selected) + 1 if self.selected in self.keyviews else 0
            self.select_camera(self.keyviews[pos % len(self.keyviews)])

    def look_through(self, item=None) -> None:
        """Set the 3D view to camera ``item`` (default: the selected one)."""
        i = self.selected if item is None else camera_index(item, self.cameras)
        if i is None:
            raise InputError("look through: no camera selected (no cameras loaded)")
        c2w = as_numpy(self.cameras.camtoworlds[i])
        fy = float(self.cameras.Ks[i, 1, 1])
        cam = self.plotter.camera
        cam.position = tuple(c2w[:3, 3])
        cam.focal_point = tuple(c2w[:3, 3] + c2w[:3, 2] * max(self.extent, 1e-6))
        cam.up = tuple(-c2w[:3, 1])
        cam.view_angle = float(np.degrees(2 * np.arctan(self.cameras.height / (2 * fy))))
        self.plotter.reset_camera_clipping_range()
        self.plotter.render()

    def toggle_help(self) -> None:
        self._help_shown = not self._help_shown
        self.plotter.add_text(HELP if self._help_shown else "", position="lower_left", font_size=9,
                              color="white", name="help")
        self.plotter.render()

    def describe(self, i: int) -> dict:
        """Parameters of scene Gaussian ``i`` (group id, position, scales, rotation, opacity, colour)."""
        s = self.scene
        q = as_numpy(s.quats[i])
        info = {
            "index": int(i),
            "group": None if self.groups is None else int(self.groups.labels[i]),
            "group_prob": None if self.groups is None or self.groups.prob is None else float(self.groups.prob[i]),
            "position": as_numpy(s.means[i]).tolist(),
            "scales": as_numpy(s.scales[i]).tolist(),
            "rotation_wxyz": (q / (np.linalg.norm(q) or 1.0)).tolist(),
            "opacity": float(s.opacities[i]),
            "rgb": np.clip(as_numpy(s.base_colors[i]), 0, 1).tolist(),
        }
        if s.identities is not None:
            info["identity_norm"] = float(s.identities[i].norm())
        return info

    def pick(self, point) -> Optional[dict]:
        """The visible Gaussian nearest to world point ``point [3]``; shown in the window and returned."""
        vis = np.nonzero(self.visible)[0]
        if point is None or len(vis) == 0:
            return None
        d = np.linalg.norm(self.xyz[vis] - np.asarray(point, dtype=np.float64)[None], axis=1)
        info = self.describe(int(self.index[vis[int(np.argmin(d))]]))
        self.last_pick = info
        grp = "-" if info["group"] is None else str(info["group"])
        if info["group_prob"] is not None:
            grp += f" (p={info['group_prob']:.2f})"
        text = (f"Gaussian {info['index']}   group {grp}\n"
                f"xyz    {np.array2string(np.array(info['position']), precision=3)}\n"
                f"scales {np.array2string(np.array(info['scales']), precision=4)}\n"
                f"quat   {np.array2string(np.array(info['rotation_wxyz']), precision=3)}\n"
                f"opacity {info['opacity']:.3f}   rgb {np.array2string(np.array(info['rgb']), precision=2)}")
        self.plotter.add_text(text, position="lower_right", font_size=9, color="white", name="pick_info")
        self.plotter.render()
        return info

    def render_splat(self, item=None) -> np.ndarray:
        """The splat image ``[H, W, 3]`` float in [0, 1] of camera ``item`` (default: selected), by our rasterizer.

        Rendered at ``render_width`` pixels wide (aspect kept) from the full scene, on ``device``.
        """
        i = self.selected if item is None else camera_index(item, self.cameras)
        if i is None:
            raise InputError("render: no camera selected (no cameras loaded)")
        cam = self.cameras[i]
        w = min(self.render_width, cam.width)
        h = max(1, round(cam.height * w / cam.width))
        cam = cam.rescaled(w, h).to(self.device)
        scene = self.scene.to(self.device)
        with torch.no_grad():
            colors, _, _ = scene.render(cam)
        return colors[0, ..., :3].clamp(0, 1).cpu().float().numpy()

    def show_splat(self, item=None) -> np.ndarray:
        """Render camera ``item`` (default: selected) and show the image in a panel beside the cloud."""
        img = self.render_splat(item)
        i = self.selected if item is None else camera_index(item, self.cameras)
        self.splat_image = img
        self._show_panel(img, f"splat render: {self.cameras.names[i]} ({img.shape[1]}x{img.shape[0]})")
        return img

    # -- output ------------------------------------------------------------------
    def screenshot(self, path: str | Path | None = None) -> np.ndarray:
        """The current image ``[H, W, 3]`` uint8; written (atomically, via OpenImageIO) when ``path`` is given."""
        img = self.plotter.screenshot(None, return_img=True)
        if path is not None:
            write_image(path, img.astype(np.float32) / 255.0)
        return img

    def show(self) -> None:
        self.plotter.show()

    def close(self) -> None:
        self.plotter.close()


def build_viewer(scene: GaussianScene, *, labels=None, scene_dir: str | Path | None = None,
                 cameras: Cameras | str | Path | None = None, keyviews: Sequence = (),
                 device: torch.device | str = "cpu", **kwargs) -> Viewer:
    """A :class:`Viewer` of ``scene``.

    ``labels`` (``[N]`` ints or a ``.npy`` path) override the groups found for
    ``scene_dir`` (its ``groups/classifier.pt``, a stylized run's source's) or the identity channels.
    ``cameras`` is a :class:`Cameras` or a ``cameras.json`` path (default: the run's
    cameras, :func:`ssgwarp.viewer.data.run_folders`); ``keyviews`` are camera indices,
    names, or key-view JSON files/directories. Other keyword arguments go to
    :class:`Viewer`.
    """
    found = run_folders(scene_dir)
    groups = resolve_groups(scene, labels=labels, scene_dir=found.groups, device=device)
    if not isinstance(cameras, Cameras):
        cameras = load_cameras(cameras, found.cameras)
    keys = resolve_keyviews(keyviews, cameras)
    return Viewer(scene, groups=groups, cameras=cameras, keyviews=keys, device=device, **kwargs)


_VIEWERS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def build_plotter(scene: GaussianScene, **kwargs):
    """The ``pyvista.Plotter`` of :func:`build_viewer`; :func:`viewer_of` gives its :class:`Viewer` back."""
    viewer = build_viewer(scene, **kwargs)
    # a weak value too: a strong one would keep the key (its own plotter) alive forever; the
    # viewer lives as long as the plotter through the key and picking callbacks it installed
    _VIEWERS[viewer.plotter] = weakref.ref(viewer)
    return viewer.plotter


def viewer_of(plotter) -> Viewer:
    """The :class:`Viewer` that :func:`build_plotter` made ``plotter`` for."""
    ref = _VIEWERS.get(plotter)
    viewer = ref() if ref is not None else None
    if viewer is None:
        raise ValueError("this plotter was not made by ssgwarp.viewer.build_plotter")
    return viewer


def screenshot(scene: GaussianScene, path: str | Path | None = None, *, render_view=None, view=None,
               **kwargs) -> np.ndarray:
    """Render ``scene`` off-screen and return the image ``[H, W, 3]`` uint8 (also written to ``path``).

    ``view`` looks through that camera (index or name); ``render_view`` shows
    that camera's splat image beside the cloud. Other arguments as :func:`build_viewer`.
    """
    kwargs.setdefault("off_screen", True)
    v = build_viewer(scene, **kwargs)
    try:
        if view is not None:
            v.look_through(view)
        if render_view is not None:
            v.select_camera(render_view)
            v.show_splat()
            if view is None:
                v._set_start_view()
        return v.screenshot(path)
    finally:
        v.close()
