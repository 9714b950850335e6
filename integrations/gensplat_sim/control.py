"""End-effector control of the Panda: damped least-squares inverse kinematics on the pinch
site (the point between the fingertips) feeding the joint position servos.

The action space shared by the experts, the recorded datasets and the evaluation
environment is ``[x, y, z, yaw, gripper]``: the pinch site's target position (world,
metres), its rotation about world +z (radians; 0 = fingers closing along world y) with the
gripper pointing straight down, and the gripper command in [0, 1] (1 = closed).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

ACTION_NAMES = ("x", "y", "z", "yaw", "gripper")
#: Reachable box for the pinch site (world, metres) and the yaw range (radians).
ACTION_LOW = np.array([0.25, -0.45, 0.01, -math.pi / 2, 0.0])
ACTION_HIGH = np.array([0.80, 0.45, 0.50, math.pi / 2, 1.0])
_GRIPPER_CTRL_MAX = 255.0  # Robotiq 2F-85 actuator range (0 = open)
_N_ARM = 7


def down_rotation(yaw: float) -> np.ndarray:
    """(3, 3) pinch-site orientation pointing down (+z to world -z), rotated by ``yaw`` about world z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])


def yaw_of(R: np.ndarray) -> float:
    """Yaw of a (roughly) downward pinch orientation: the inverse of :func:`down_rotation`."""
    return math.atan2(R[1, 0], R[0, 0])


class ArmController:
    """Turns ``[x, y, z, yaw, gripper]`` actions into actuator controls.

    IK starts from the previous joint target (``data.ctrl[:7]``), so the command is a smooth
    function of the action sequence and does not depend on tracking error.

    Args:
        model: the scene model (:func:`~.scene.build_model`).
        home: (7,) rest posture the null-space term pulls towards.
        iterations: IK iterations per control step.
    """

    def __init__(
        self, model: mujoco.MjModel, home: np.ndarray, iterations: int = 15, damping: float = 0.05
    ) -> None:
        self.model = model
        self.home = np.asarray(home, dtype=np.float64)
        self.iterations, self.damping = iterations, damping
        self._scratch = mujoco.MjData(model)
        self._site = model.site("pinch").id
        self._range = model.jnt_range[:_N_ARM].copy()
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    def inverse_kinematics(self, q0: np.ndarray, pos: np.ndarray, yaw: float) -> np.ndarray:
        """(7,) joint angles placing the pinch site at ``pos`` pointing down with ``yaw``."""
        d = self._scratch
        q = np.array(q0[:_N_ARM], dtype=np.float64)
        R_target = down_rotation(yaw)
        for _ in range(self.iterations):
            d.qpos[:_N_ARM] = q
            mujoco.mj_kinematics(self.model, d)
            mujoco.mj_comPos(self.model, d)
            R = d.site_xmat[self._site].reshape(3, 3)
            err = np.concatenate([pos - d.site_xpos[self._site], 0.5 * np.cross(R, R_target, axis=0).sum(1)])
            if np.linalg.norm(err) < 1e-5:
                break
            mujoco.mj_jacSite(self.model, d, self._jacp, self._jacr, self._site)
            J = np.concatenate([self._jacp[:, :_N_ARM], self._jacr[:, :_N_ARM]])
            JJt = J @ J.T + self.damping**2 * np.eye(6)
            dq = J.T @ np.linalg.solve(JJt, err)
            null = np.eye(_N_ARM) - J.T @ np.linalg.solve(JJt, J)
            q = np.clip(q + dq + 0.1 * null @ (self.home - q), self._range[:, 0], self._range[:, 1])
        return q

    def apply(self, data: mujoco.MjData, action: np.ndarray) -> None:
        """Write the controls for ``action`` (5,) into ``data.ctrl``."""
        a = np.clip(np.asarray(action, dtype=np.float64), ACTION_LOW, ACTION_HIGH)
        data.ctrl[:_N_ARM] = self.inverse_kinematics(data.ctrl[:_N_ARM], a[:3], float(a[3]))
        data.ctrl[_N_ARM] = a[4] * _GRIPPER_CTRL_MAX
