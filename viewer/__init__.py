"""Inspection viewer (``ssgwarp view``): Gaussian clouds, group labels, cameras and key views, with pyvista.

pyvista/VTK are imported only when a viewer is built (:func:`build_viewer`,
:func:`build_plotter`, :func:`screenshot`), so importing this package is cheap.
"""
from .app import COLOR_MODES, Viewer, build_plotter, build_viewer, screenshot, viewer_of
from .headless import offscreen_available, offscreen_status, prepare_offscreen

__all__ = ["Viewer", "build_viewer", "build_plotter", "screenshot", "viewer_of", "COLOR_MODES",
           "offscreen_available", "offscreen_status", "prepare_offscreen"]
