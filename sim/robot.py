"""The simulated Poppy Humanoid: joint table, loading, pose and head height.

Data enters as joint targets in radians (pypot sign convention, model joint order)
and leaves as measured joint angles in the same order and the head link's pose.
The model file is ``sim/model/poppy_humanoid.urdf`` (see ``build_model.py``).
"""

from __future__ import annotations

import numpy as np
import pybullet as pb

from .build_model import MODEL_PATH

#: The 25 motors in model order (Dynamixel ids ascending), as docs/robot.md.
JOINT_NAMES: tuple[str, ...] = (
    "l_hip_x", "l_hip_z", "l_hip_y", "l_knee_y", "l_ankle_y",
    "r_hip_x", "r_hip_z", "r_hip_y", "r_knee_y", "r_ankle_y",
    "abs_y", "abs_x", "abs_z", "bust_y", "bust_x",
    "head_z", "head_y",
    "l_shoulder_y", "l_shoulder_x", "l_arm_z", "l_elbow_y",
    "r_shoulder_y", "r_shoulder_x", "r_arm_z", "r_elbow_y",
)
JOINT_IDS: tuple[int, ...] = (
    11, 12, 13, 14, 15, 21, 22, 23, 24, 25,
    31, 32, 33, 34, 35, 36, 37,
    41, 42, 43, 44, 51, 52, 53, 54,
)
ROBOT_NAME = "poppy_humanoid"
PHYSICS_HZ = 240
#: Fallen when the head link is below this fraction of its standing height.
FALL_FRACTION = 0.8
#: Position-controller gains (pybullet positionGain, velocityGain). 0.07 was chosen by
#: measurement: gaits kept by the search survive small perturbations far more often
#: than at 0.3 (sigma 0.005: 26/26 vs 13/22 runs; sigma 0.01: 20/26 vs 2/22).
POSITION_GAIN = 0.07
VELOCITY_GAIN = 1.0


def index_of(name: str) -> int:
    return JOINT_NAMES.index(name)


class Robot:
    """One Poppy Humanoid body in a pybullet client."""

    def __init__(self, client: int, base_xy=(0.0, 0.0), yaw_rad: float = 0.0):
        self.client = client
        self.body = pb.loadURDF(
            str(MODEL_PATH), basePosition=(base_xy[0], base_xy[1], 0.5),
            baseOrientation=pb.getQuaternionFromEuler((0, 0, yaw_rad)),
            flags=pb.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client)
        by_name = {}
        self.link_by_name = {}
        for i in range(pb.getNumJoints(self.body, physicsClientId=client)):
            info = pb.getJointInfo(self.body, i, physicsClientId=client)
            by_name[info[1].decode()] = i
            self.link_by_name[info[12].decode()] = i
        missing = [n for n in JOINT_NAMES if n not in by_name]
        if missing:
            raise RuntimeError(f"{MODEL_PATH}: joints missing from the model: {missing}")
        self.joint_indices = [by_name[n] for n in JOINT_NAMES]
        self.max_force = np.array([
            pb.getJointInfo(self.body, j, physicsClientId=client)[10] for j in self.joint_indices])
        # The per-step command's constant arguments, made once (the command runs 2,400 times an episode).
        self._forces = self.max_force.tolist()
        #: Joint limits (rad, model order): the balance feedback's corrections stay inside them.
        self.lo = np.array([pb.getJointInfo(self.body, j, physicsClientId=client)[8] for j in self.joint_indices])
        self.hi = np.array([pb.getJointInfo(self.body, j, physicsClientId=client)[9] for j in self.joint_indices])
        self._zero_velocities = [0.0] * len(self.joint_indices)
        self._position_gains = [POSITION_GAIN] * len(self.joint_indices)
        self._velocity_gains = [VELOCITY_GAIN] * len(self.joint_indices)
        self.head_link = self.link_by_name["head"]
        self.foot_links = [self.link_by_name["l_foot"], self.link_by_name["r_foot"]]
        for j in range(pb.getNumJoints(self.body, physicsClientId=client)):
            pb.changeDynamics(self.body, j, lateralFriction=0.9, physicsClientId=client)

    def set_root_frame(self, xyz, yaw_rad: float) -> None:
        """Put the URDF root (pelvis) frame at XYZ with yaw YAW_RAD, upright.

        pybullet's base frame is the pelvis's inertial frame, rotated from the
        URDF frame, so the URDF frame pose is composed with it here.
        """
        info = pb.getDynamicsInfo(self.body, -1, physicsClientId=self.client)
        pos, orn = pb.multiplyTransforms(xyz, pb.getQuaternionFromEuler((0, 0, yaw_rad)), info[3], info[4])
        pb.resetBasePositionAndOrientation(self.body, pos, orn, physicsClientId=self.client)
        pb.resetBaseVelocity(self.body, (0, 0, 0), (0, 0, 0), physicsClientId=self.client)

    def place(self, angles_rad: np.ndarray, base_xy, yaw_rad: float) -> None:
        """Reset to a pose, the robot upright with yaw YAW_RAD (0: facing -y) and
        the lowest foot point on the floor (z = 0)."""
        self.set_root_frame((base_xy[0], base_xy[1], 0.5), yaw_rad)
        for j, a in zip(self.joint_indices, angles_rad):
            pb.resetJointState(self.body, j, float(a), 0.0, physicsClientId=self.client)
        low = min(pb.getAABB(self.body, f, physicsClientId=self.client)[0][2] for f in self.foot_links)
        self.set_root_frame((base_xy[0], base_xy[1], 0.5 - low + 0.0005), yaw_rad)
        self.command(angles_rad)

    def command(self, targets_rad: np.ndarray) -> None:
        pb.setJointMotorControlArray(
            self.body, self.joint_indices, pb.POSITION_CONTROL,
            targetPositions=np.asarray(targets_rad, dtype=float).tolist(),
            targetVelocities=self._zero_velocities,
            forces=self._forces,
            positionGains=self._position_gains,
            velocityGains=self._velocity_gains,
            physicsClientId=self.client)

    def joint_angles(self) -> np.ndarray:
        states = pb.getJointStates(self.body, self.joint_indices, physicsClientId=self.client)
        return np.array([s[0] for s in states])

    def head_pose(self):
        """(position xyz, orientation quaternion xyzw) of the head link frame."""
        st = pb.getLinkState(self.body, self.head_link, computeForwardKinematics=True,
                             physicsClientId=self.client)
        return np.array(st[4]), np.array(st[5])

    def head_height_m(self) -> float:
        return float(self.head_pose()[0][2])

    def base_xy(self) -> np.ndarray:
        return np.array(pb.getBasePositionAndOrientation(self.body, physicsClientId=self.client)[0][:2])
