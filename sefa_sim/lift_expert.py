"""A scripted expert for robosuite Lift (Panda, OSC_POSE with delta actions).

The action is 7-D: [dx, dy, dz, dax, day, daz, gripper] in [-1, 1]. The controller scales the
position part by its output_max (0.05 m per step by default) and the rotation part by 0.5 rad;
gripper -1 opens and +1 closes.

The expert runs four phases: move above the cube, descend to it, close the gripper and wait,
lift. Each phase ends on reaching its target or on a step budget, so a missed target cannot
stall an episode. Yaw is servoed to the cube's faces (modulo 90 degrees, the cube's symmetry) so
the fingers close on two parallel faces instead of on edges.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

OPEN, CLOSE = -1.0, 1.0


class Phase(Enum):
    APPROACH = "approach"
    DESCEND = "descend"
    GRASP = "grasp"
    LIFT = "lift"


@dataclass(frozen=True)
class LiftExpertConfig:
    hover_height: float = 0.10  # above the cube centre before descending
    grasp_offset: float = -0.005  # the grip site sits a little below the cube centre at grasp
    lift_height: float = 0.20  # above the grasp point; success needs only 0.04
    pos_gain: float = 10.0  # action per metre of error: 0.1 m error saturates the action
    yaw_gain: float = 4.0  # action per radian of yaw error
    approach_tol_xy: float = 0.008
    approach_tol_z: float = 0.02
    approach_tol_yaw: float = 0.05
    descend_tol: float = 0.008
    grasp_steps: int = 12  # the GRIP controller needs several steps to close the fingers
    approach_budget: int = 80
    descend_budget: int = 50
    align_yaw: bool = True
    noise_std: float = 0.0  # on the position and rotation parts only, for diverse demos


class LiftExpert:
    """Stateful scripted policy: call `reset(obs)` at each episode start, then `act(obs)`."""

    def __init__(self, config: LiftExpertConfig | None = None, seed: int | None = None) -> None:
        self.config = config or LiftExpertConfig()
        self._rng = np.random.default_rng(seed)
        self.phase = Phase.APPROACH
        self._phase_steps = 0
        self._grasp_target = np.zeros(3)

    def reset(self, obs: dict[str, np.ndarray], seed: int | None = None) -> None:
        """Start a new episode; a seed here re-seeds the action noise for this episode."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.phase = Phase.APPROACH
        self._phase_steps = 0
        self._grasp_target = np.asarray(obs["cube_pos"], dtype=float).copy()

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        eef = np.asarray(obs["robot0_eef_pos"], dtype=float)
        cube = np.asarray(obs["cube_pos"], dtype=float)
        yaw_err = self._yaw_error(obs) if self.config.align_yaw else 0.0
        self._advance_phase(eef, cube, yaw_err)
        target, gripper, use_yaw = self._phase_target(cube)
        action = np.zeros(7)
        action[:3] = self.config.pos_gain * (target - eef)
        if use_yaw:
            action[5] = self.config.yaw_gain * yaw_err
        if self.config.noise_std > 0:
            action[:6] += self._rng.normal(0.0, self.config.noise_std, 6)
        action[6] = gripper
        self._phase_steps += 1
        return np.clip(action, -1.0, 1.0)

    # ------------------------------------------------------------------ phases

    def _advance_phase(self, eef: np.ndarray, cube: np.ndarray, yaw_err: float) -> None:
        c = self.config
        if self.phase is Phase.APPROACH:
            err = cube + [0.0, 0.0, c.hover_height] - eef
            reached = (np.linalg.norm(err[:2]) < c.approach_tol_xy
                       and abs(err[2]) < c.approach_tol_z and abs(yaw_err) < c.approach_tol_yaw)
            if reached or self._phase_steps >= c.approach_budget:
                self._enter(Phase.DESCEND)
        elif self.phase is Phase.DESCEND:
            err = cube + [0.0, 0.0, c.grasp_offset] - eef
            if np.linalg.norm(err) < c.descend_tol or self._phase_steps >= c.descend_budget:
                # hold where the hand is, not where the cube is: the fingers touching the cube
                # while closing can nudge it, and chasing it would drag the hand sideways
                self._grasp_target = eef.copy()
                self._enter(Phase.GRASP)
        elif self.phase is Phase.GRASP and self._phase_steps >= c.grasp_steps:
            self._enter(Phase.LIFT)

    def _enter(self, phase: Phase) -> None:
        self.phase = phase
        self._phase_steps = 0

    def _phase_target(self, cube: np.ndarray) -> tuple[np.ndarray, float, bool]:
        """(position target, gripper command, whether to servo yaw) for the current phase."""
        c = self.config
        if self.phase is Phase.APPROACH:
            return cube + [0.0, 0.0, c.hover_height], OPEN, True
        if self.phase is Phase.DESCEND:
            return cube + [0.0, 0.0, c.grasp_offset], OPEN, True
        if self.phase is Phase.GRASP:
            return self._grasp_target, CLOSE, False
        return self._grasp_target + [0.0, 0.0, c.lift_height], CLOSE, False

    # ------------------------------------------------------------------ yaw

    def _yaw_error(self, obs: dict[str, np.ndarray]) -> float:
        """Rotation about world z that brings the hand square to the cube, in [-pi/4, pi/4)."""
        diff = _yaw(obs["cube_quat"]) - _yaw(obs["robot0_eef_quat"])
        # the cube looks the same every 90 degrees, so the smallest turn is modulo pi/2
        return float((diff + np.pi / 4) % (np.pi / 2) - np.pi / 4)


def _yaw(quat_xyzw: np.ndarray) -> float:
    """Heading of the body's x axis projected on the world xy plane (robosuite quats are xyzw).

    For the hand, pointing down, this is its rotation about world z; for the cube, resting on
    a face, it is its rotation about z. Either way only the projection is needed.
    """
    x, y, z, w = np.asarray(quat_xyzw, dtype=float)
    # first column of the rotation matrix
    r00 = 1.0 - 2.0 * (y * y + z * z)
    r10 = 2.0 * (x * y + w * z)
    return float(np.arctan2(r10, r00))
