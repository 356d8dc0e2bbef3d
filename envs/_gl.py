"""Pick MuJoCo's offscreen OpenGL backend before dm_control is imported.

Headless machines render through EGL (Mesa or a GPU driver). ``MUJOCO_GL=egl`` is set only when the
user has not chosen a backend and an EGL library is present; otherwise dm_control's own choice
stands, and rendering fails later with a clear message rather than at import.
"""

from __future__ import annotations

import ctypes.util
import os


def select_gl_backend() -> str | None:
    """Set ``MUJOCO_GL=egl`` where possible and return the backend in force (None: automatic)."""
    if "MUJOCO_GL" not in os.environ and ctypes.util.find_library("EGL"):
        os.environ["MUJOCO_GL"] = "egl"
    return os.environ.get("MUJOCO_GL")


select_gl_backend()
