"""Simulation helpers: a scripted robosuite Lift expert and a robomimic-layout collector.

Import `configure_headless` (or any submodule, which calls it) before robosuite or mujoco is
imported: MuJoCo reads MUJOCO_GL once, when its GL backend is first loaded.
"""

from __future__ import annotations

import os
import sys


def configure_headless() -> str | None:
    """Pick a GL backend for machines without a screen; returns the MUJOCO_GL in effect.

    A user's own MUJOCO_GL always wins. On Linux without DISPLAY we choose EGL: it renders
    offscreen without an X server (checked on the dev machine; osmesa was not usable there).
    Low-dim collection never renders, so the choice only matters with cameras.
    """
    if "MUJOCO_GL" not in os.environ and sys.platform.startswith("linux") \
            and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "egl"
    return os.environ.get("MUJOCO_GL")


configure_headless()
