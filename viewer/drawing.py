"""The viewer's drawing: the cloud (discs or ellipsoid glyphs), the camera frustums (key views and
the selected camera highlighted), the overlays (status text, group legend), the start view and the
splat-image panel. A mixin of :class:`ssgwarp.viewer.app.Viewer`, which holds the state these read
(``plotter``, ``pv``, the scene arrays, the colouring, the cameras and the selection); the keys,
the state changes and the command stay in :mod:`ssgwarp.viewer.app`."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import geometry
from .data import as_numpy

CAMERA_COLOR = (0.70, 0.70, 0.70)
KEYVIEW_COLOR = (1.00, 0.55, 0.00)
SELECTED_COLOR = (0.20, 0.60, 1.00)
FRAME_ZOOM = 0.85  # a margin around the robust box (discs and the cloud's edges reach beyond it)

# Fragment code for vtkPointGaussianMapper: flat, opaque discs of radius = the point's scale value.
_DISC_SHADER = ("//VTK::Color::Impl\n"
                "float dist2 = dot(offsetVCVSOutput.xy, offsetVCVSOutput.xy);\n"
                "if (dist2 > 1.0) { discard; }\n")


def label_name(name: str) -> str:
    """A camera's label in the view: its image name without folders and extension."""
    return Path(name).stem or name


class Drawing:
    """Drawing methods of the viewer (see the module docs)."""

    def _auto_frustum_size(self) -> float:
        if self.cameras is None or len(self.cameras) == 0:
            return 0.1 * self.extent
        c = as_numpy(self.cameras.centers)
        if len(c) > 1:
            d = np.linalg.norm(c[:, None] - c[None], axis=-1)
            np.fill_diagonal(d, np.inf)
            spacing = float(np.median(d.min(axis=1)))
        else:
            spacing = np.inf
        return float(min(0.6 * spacing, 0.1 * max(self.extent, 1e-6)))

    def _draw_cloud(self) -> None:
        pv, pl = self.pv, self.plotter
        for name in ("gaussians", "glyphs"):
            pl.remove_actor(name, render=False)
        if "opacity" in pl.scalar_bars:
            pl.remove_scalar_bar("opacity", render=False)
        vis = np.nonzero(self.visible)[0]
        self.cloud_actor, self.glyph_count = None, 0
        if len(vis) == 0:
            return
        scalars = {"scalars": "opacity", "cmap": "viridis", "clim": (0.0, 1.0), "show_scalar_bar": self.hud,
                   "scalar_bar_args": {"title": "opacity", "vertical": True, "position_x": 0.9,
                                       "position_y": 0.3, "width": 0.04, "height": 0.4, "n_labels": 3,
                                       "title_font_size": 12, "label_font_size": 10, "fmt": "%.1f"}} \
            if self.color == "opacity" else {"scalars": "colors", "rgb": True}
        if self.glyphs:
            chosen = np.sort(vis[np.argsort(self._glyph_rank[vis])[: self.max_glyphs]])
            pts, faces, owner = geometry.ellipsoid_glyphs(self.xyz[chosen], self.quats[chosen],
                                                          self.scales[chosen], self.sigma)
            mesh = pv.PolyData(pts, faces=faces)
            mesh.point_data["colors"] = self.colors()[chosen][owner]
            mesh.point_data["opacity"] = self.opacity[chosen][owner]
            mesh.point_data["gaussian"] = self.index[chosen][owner]
            self.cloud_actor = pl.add_mesh(mesh, name="glyphs", smooth_shading=True, reset_camera=False,
                                           pickable=True, **scalars)
            self.glyph_count = len(chosen)
            return
        cloud = pv.PolyData(self.xyz[vis])
        cloud.point_data["colors"] = self.colors()[vis]
        cloud.point_data["opacity"] = self.opacity[vis]
        cloud.point_data["radius"] = self.radii[vis]
        cloud.point_data["gaussian"] = self.index[vis]
        actor = pl.add_mesh(cloud, name="gaussians", style="points_gaussian", emissive=False, lighting=False,
                            reset_camera=False, pickable=True, **scalars)
        actor.mapper.scale_array = "radius"
        actor.mapper.SetSplatShaderCode(_DISC_SHADER)
        actor.prop.opacity = 1.0
        self.cloud_actor = actor

    def _draw_cameras(self) -> None:
        if self.cameras is None or len(self.cameras) == 0:
            return
        pv, pl, cams = self.pv, self.plotter, self.cameras
        vm, Ks = as_numpy(cams.viewmats), as_numpy(cams.Ks)
        key = set(self.keyviews)
        groups = [("frustums", [i for i in range(len(cams)) if i not in key], CAMERA_COLOR, 1.5),
                  ("keyview_frustums", sorted(key), KEYVIEW_COLOR, 3.0)]
        for name, ids, color, width in groups:
            pl.remove_actor(name, render=False)
            if not ids:
                continue
            pts, lines = geometry.frustum_lines(vm[ids], Ks[ids], cams.width, cams.height, self.frustum_size)
            pl.add_mesh(pv.PolyData(pts, lines=lines), name=name, color=color, line_width=width,
                        lighting=False, pickable=False, reset_camera=False)
        if key and self.hud:
            # at the centre of each frustum's far face (nearer the cloud than the apex, so in the
            # start view, which frames the cloud, more often than the camera centre)
            c2w = as_numpy(cams.camtoworlds)[sorted(key)]
            cen = c2w[:, :3, 3] + c2w[:, :3, 2] * self.frustum_size
            # short names (the file stem) on a dark box: readable over frustum lines and the cloud
            pl.add_point_labels(cen, [label_name(cams.names[i]) for i in sorted(key)], name="keyview_names",
                                font_size=14, text_color=KEYVIEW_COLOR, shape="rounded_rect",
                                shape_color=(0.06, 0.06, 0.08), shape_opacity=0.8, margin=2, show_points=False,
                                always_visible=True, pickable=False, reset_camera=False)
        self._draw_selected()

    def _draw_selected(self) -> None:
        pl = self.plotter
        pl.remove_actor("selected_frustum", render=False)
        if self.selected is None:
            return
        cams, i = self.cameras, self.selected
        pts, lines = geometry.frustum_lines(as_numpy(cams.viewmats[i:i + 1]), as_numpy(cams.Ks[i:i + 1]),
                                            cams.width, cams.height, self.frustum_size * 1.02)
        pl.add_mesh(self.pv.PolyData(pts, lines=lines), name="selected_frustum", color=SELECTED_COLOR,
                    line_width=4.0, lighting=False, pickable=False, reset_camera=False)

    def _draw_overlays(self) -> None:
        pl = self.plotter
        if self.hud:
            pl.add_text(self.status_text(), position="upper_left", font_size=9, color="white", name="status",
                        shadow=True)
        if self.legend and self.color == "group" and self.groups is not None:
            rows = self.legend_entries()
            size = (0.18, min(0.9, (0.035 if len(rows) <= 8 else 0.027) * len(rows) + 0.02))
            legend = pl.add_legend(labels=[list(r) for r in rows], bcolor=(0.12, 0.12, 0.14), border=False,
                                   size=size, loc="upper right", face="rectangle", name="legend")
            # in the upper right corner (pyvista 0.49 places a legend taller than wide further left)
            legend.SetPosition(1.0 - size[0] - 0.02, 1.0 - size[1] - 0.05)
        elif getattr(pl, "legend", None) is not None:
            pl.remove_legend(render=False)

    def _set_start_view(self) -> None:
        pl = self.plotter
        if self.cameras is not None and len(self.cameras):
            c2w = as_numpy(self.cameras.camtoworlds)
            up = -c2w[:, :3, 1].mean(axis=0)           # OpenCV: camera y points down
            up = up / (np.linalg.norm(up) or 1.0)
            # an oblique overview from above the cameras: their ring/arc and the cloud both show
            back = c2w[:, :3, 3].mean(axis=0) - self.center
            back = back - up * (back @ up)
            if np.linalg.norm(back) < 1e-9:
                back = c2w[0, :3, 3] - self.center
                back = back - up * (back @ up)
            direction = 0.6 * back / (np.linalg.norm(back) or 1.0) + up
            pl.camera.focal_point = tuple(self.center)
            pl.camera.position = tuple(self.center + direction * self.extent)
            pl.camera.up = tuple(up)
        else:
            pl.view_isometric(render=False)
            pl.camera_set = True  # (else the first render frames every actor's bounds again)
        # frame the cloud's robust box (percentiles), not every actor's bounds: far floaters and the
        # camera frustums would leave the cloud small in the middle
        lo, hi = self.frame_box
        pl.renderer.ComputeAspect()  # (the viewport may have changed: the splat panel beside it)
        pl.reset_camera(render=False, bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        pl.camera.zoom(FRAME_ZOOM)
        pl.reset_camera_clipping_range()

    def _show_panel(self, img: np.ndarray, title: str) -> None:
        from vtkmodules.vtkRenderingCore import vtkImageActor, vtkRenderer, vtkTextActor

        pl, split = self.plotter, 0.62
        if self._panel is None:
            ren = vtkRenderer()
            ren.SetViewport(split, 0.0, 1.0, 1.0)
            ren.SetBackground(0.0, 0.0, 0.0)
            ren.SetInteractive(False)
            actor, text = vtkImageActor(), vtkTextActor()
            text.GetTextProperty().SetFontSize(12)
            text.GetTextProperty().SetColor(1.0, 1.0, 1.0)
            text.GetPositionCoordinate().SetCoordinateSystemToNormalizedViewport()
            text.GetPositionCoordinate().SetValue(0.03, 0.03)
            actor.InterpolateOff()  # show the rasterizer's pixels as they are
            ren.AddActor(actor)
            ren.AddViewProp(text)
            pl.render_window.AddRenderer(ren)
            pl.renderer.viewport = (0.0, 0.0, split, 1.0)
            self._panel = (ren, actor, text)
        ren, actor, text = self._panel
        h, w = img.shape[:2]
        data = self.pv.ImageData(dimensions=(w, h, 1))
        data.point_data["rgb"] = (np.clip(img[::-1], 0, 1) * 255 + 0.5).astype(np.uint8).reshape(-1, 3)
        actor.GetMapper().SetInputData(data)
        text.SetInput(title)
        cam = ren.GetActiveCamera()
        cam.ParallelProjectionOn()
        cam.SetFocalPoint((w - 1) / 2, (h - 1) / 2, 0.0)
        cam.SetPosition((w - 1) / 2, (h - 1) / 2, 10.0 * max(w, h))
        cam.SetViewUp(0.0, 1.0, 0.0)
        win_w, win_h = pl.window_size
        aspect = (1.0 - split) * win_w / max(win_h, 1)
        cam.SetParallelScale(max(h / 2, w / 2 / aspect) * 1.02)
        ren.ResetCameraClippingRange()
        pl.render()
