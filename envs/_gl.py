"""Pick MuJoCo's offscreen OpenGL backend before dm_control is imported.

Headless machines render through EGL (Mesa or a GPU driver). ``MUJOCO_GL=egl`` is set only when
the user has not chosen a backend, an EGL library is present, and MuJoCo and dm_control import
with it (tried once, in a child process); otherwise dm_control's own choice stands, and
rendering fails later with a clear message rather than at import. The try matters: both load
their EGL backend when imported, so an EGL library that PyOpenGL cannot use (seen on a GPU
machine, where PyOpenGL found no EGL functions in it, and with ``PYOPENGL_PLATFORM`` set to
another platform) would make every import of this package fail.
"""

from __future__ import annotations

import ctypes.util
import os

#: What loads the EGL backend at import: MuJoCo (whose own import lets an ImportError of its
#: renderer pass, not other errors) and dm_control's renderer (which lets none pass).
_PROBE = "import mujoco\nfrom dm_control import _render"


def egl_imports() -> bool:
    """Whether MuJoCo and dm_control import with ``MUJOCO_GL=egl`` here, tried in a child
    process (a failed import would leave PyOpenGL half set up in this one)."""
    from rcvae_torchrl.processes import try_in_a_child

    try:
        return try_in_a_child(_PROBE, timeout=120, env={"MUJOCO_GL": "egl"}).problem is None
    except OSError:
        return False


def select_gl_backend() -> str | None:
    """Set ``MUJOCO_GL=egl`` where it works and return the backend in force (None: automatic)."""
    if "MUJOCO_GL" not in os.environ and ctypes.util.find_library("EGL") and egl_imports():
        os.environ["MUJOCO_GL"] = "egl"
    return os.environ.get("MUJOCO_GL")


select_gl_backend()
