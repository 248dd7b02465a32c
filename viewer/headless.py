"""Off-screen rendering set-up for the viewer (no display, no GPU).

The VTK wheels (9.4 and later) carry both an X11 and an EGL render window and
fall back from X11 to EGL when there is no X server. With Mesa's EGL driver
(Debian packages ``libegl1 libegl-mesa0 libgl1-mesa-dri``) EGL renders on the
CPU (llvmpipe) with no display and no GPU. :func:`prepare_offscreen` asks VTK
for the EGL window directly when no display is set, which skips the failed X
connection (and its warning); :func:`offscreen_available` checks, in a child
process so that a broken GL stack cannot take the caller down, that a small
scene really renders.
"""
from __future__ import annotations

import functools
import os
import re
import subprocess
import sys

_PROBE = r"""
import numpy as np
import pyvista as pv
p = pv.Plotter(off_screen=True, window_size=(32, 32))
p.background_color = "black"
p.add_points(np.zeros((1, 3)), color=(1.0, 1.0, 1.0), point_size=16, lighting=False)
img = p.screenshot(None, return_img=True)
p.close()
assert img.shape[:2] == (32, 32) and img.max() > 0, "rendered image is empty"
print("ok", type(p).__name__)
"""


def has_display() -> bool:
    """True when an X11 or Wayland display is set."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def prepare_offscreen() -> None:
    """Ask VTK for its EGL render window when there is no display (call before the first plotter).

    Honours a ``VTK_DEFAULT_OPENGL_WINDOW`` the user already set (e.g.
    ``vtkOSOpenGLRenderWindow`` with an OSMesa build of VTK).
    """
    if not has_display():
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


@functools.lru_cache(maxsize=1)
def offscreen_status(timeout: float = 60.0) -> tuple[bool, str]:
    """``(ok, reason)``: whether pyvista can render off-screen here (probed once per process)."""
    env = dict(os.environ)
    if not has_display():
        env.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                           timeout=timeout)
    except subprocess.TimeoutExpired:
        return False, f"off-screen render probe timed out after {timeout:.0f} s"
    if r.returncode == 0 and r.stdout.startswith("ok"):
        return True, "ok"
    text = re.sub(r"\x1b\[[0-9;]*m", "", r.stderr or r.stdout).strip()
    tail = text.splitlines()[-1:] or ["no output"]
    return False, (f"pyvista/VTK cannot render off-screen (exit {r.returncode}: {tail[0]}); install Mesa EGL: "
                   "apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri")


def offscreen_available() -> bool:
    return offscreen_status()[0]
