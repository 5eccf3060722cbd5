"""Pick MuJoCo's EGL backend on headless Linux unless the user chose one.

MuJoCo reads ``MUJOCO_GL`` once, when ``mujoco`` is first imported; its default
(GLFW) needs a display. On Linux without ``DISPLAY`` and without an explicit
``MUJOCO_GL``, this sets ``MUJOCO_GL=egl`` so ``render_mode="rgb_array"`` works on
servers. Imported first by ``wcsac_rl`` (so before ``wcsac_rl.envs`` or torchrl can
import ``mujoco``); it has no effect if ``mujoco`` was imported before ``wcsac_rl``.
"""

from __future__ import annotations

import os
import sys

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")
