"""A LeRobot robot without hardware, for the tests of lerobot-rollout and the async robot_client:
LeRobot 0.6.1 ships none (its `mock_robot` type imports `tests.mocks`, which the wheel lacks).

A position-controlled 2-joint arm (`x.pos`, `y.pos`, in Push-T's pixels): each commanded target
becomes the new position, as a servo that reaches it within a control step. Every observation
it returns and action it receives is appended, one JSON line each, to the file named by
SEFA_TEST_ROBOT_LOG, so that a test can replay the observations through the policy and check
the actions it received are the policy's.

Imported by the tools through LeRobot's own plugin hooks: `--robot.discover_packages_path=
sefa_test_robot` (lerobot-rollout), or imported before `lerobot.async_inference.robot_client`
runs (that script's parser has no such hook).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from functools import cached_property

from lerobot.robots.config import RobotConfig
from lerobot.robots.robot import Robot

LOG = "SEFA_TEST_ROBOT_LOG"
JOINTS = ("x.pos", "y.pos")


@RobotConfig.register_subclass("sefa_test_robot")
@dataclass
class SefaTestRobotConfig(RobotConfig):
    start_x: float = 250.0
    start_y: float = 300.0


class SefaTestRobot(Robot):
    config_class = SefaTestRobotConfig
    name = "sefa_test_robot"

    def __init__(self, config: SefaTestRobotConfig):
        super().__init__(config)
        self.position = {"x.pos": config.start_x, "y.pos": config.start_y}
        self.connected = False

    @cached_property
    def observation_features(self) -> dict:
        return {j: float for j in JOINTS}

    @cached_property
    def action_features(self) -> dict:
        return {j: float for j in JOINTS}

    @property
    def is_connected(self) -> bool:
        return self.connected

    def connect(self, calibrate: bool = True) -> None:
        self.connected = True

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_observation(self) -> dict:
        obs = dict(self.position)
        _log({"observation": obs})
        return obs

    def send_action(self, action: dict) -> dict:
        sent = {j: float(action[j]) for j in JOINTS}
        _log({"action": sent})
        self.position = dict(sent)
        return sent

    def disconnect(self) -> None:
        self.connected = False


def _log(entry: dict) -> None:
    path = os.environ.get(LOG)
    if path:
        with open(path, "a") as f:
            f.write(json.dumps(entry) + "\n")
