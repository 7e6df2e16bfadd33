"""Simulation helpers: a scripted robosuite Lift expert and a robomimic-layout collector.

Import `configure_headless` (or any submodule, which calls it) before robosuite or mujoco is
imported: MuJoCo reads MUJOCO_GL once, when its GL backend is first loaded, and robosuite logs
its start-up notes as it is imported (`quiet_robosuite`).
"""

from __future__ import annotations

import logging
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


class RobosuiteNotes(logging.Filter):
    """robosuite's logger below ERROR: at import it warns about its own installation (no private
    macro file, no robosuite_models, no mink IK for the GR1 robot) and at every env creation it
    names the controller file it loads; none of it concerns a sefa run, which builds Lift with
    its default Panda and OSC controller (sefa_sim/collect.py). Its errors still show."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.ERROR


def quiet_robosuite() -> None:
    """Installed before robosuite is imported: its logger is created then, and would print
    those notes to every command that simulates Lift."""
    logger = logging.getLogger("robosuite_logs")  # robosuite.utils.log_utils' logger name
    if not any(isinstance(f, RobosuiteNotes) for f in logger.filters):
        logger.addFilter(RobosuiteNotes())


configure_headless()
quiet_robosuite()
