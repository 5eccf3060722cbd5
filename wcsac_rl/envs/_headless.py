"""Pick MuJoCo's EGL backend on headless Linux unless the user chose one.

MuJoCo reads ``MUJOCO_GL`` once, when ``mujoco`` is first imported; its default
(GLFW) needs a display. On Linux without ``DISPLAY`` and without an explicit
``MUJOCO_GL``, this sets ``MUJOCO_GL=egl`` so ``render_mode="rgb_array"`` works on
servers. It has no effect if ``mujoco`` was imported before ``wcsac_rl.envs``.
"""

from __future__ import annotations

import os
import sys

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")
