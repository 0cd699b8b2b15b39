"""The simulated robot's low-level balance feedback (generator 6).

Data enters as the plan being followed (joint targets, rad, model order, one
per 30 Hz tick) and, at every 240 Hz physics step, the pelvis's measured
orientation and angular velocity (what an IMU in the pelvis reads); it leaves
as the joint targets sent to the servos: the plan's, corrected.

The plan stays what the planner published: the feedback acts only between
the plan and the servos, as a walking robot's low-level controller does, so
the measured joints carry the corrections and the plan does not.

- **Pitch** (trunk leaning forward, rad, and its rate, rad/s) moves the hip
  pitch of the stance leg(s): ``hip_y += KH * pitch + KHD * pitch_rate``
  (the hip strategy: the legs are brought under a falling trunk).
- **Roll** (leaning to the robot's left) moves both hips' roll:
  ``hip_x += KR * roll + KRD * roll_rate``.
- Each correction is clipped to +-``LIMIT_RAD``; a leg's share of the pitch
  correction falls to 0 while the plan lifts it (its knee flexed more than
  the other's by ``SWING_KNEE_RAD`` or more).

The gains were chosen by a grid on the bare floor (sim/README.md, "A walk
with feedback"): of the combinations tried, these kept 8 of 8 sampled gaits
of the generator's family up for 10 s with the longest walks.
"""

from __future__ import annotations

import numpy as np
import pybullet as pb

from .robot import JOINT_NAMES

KH = 0.5          # rad of hip_y per rad of pitch
KHD = 0.16        # rad of hip_y per rad/s of pitch rate
KR = -0.3         # rad of hip_x per rad of roll
KRD = -0.1        # rad of hip_x per rad/s of roll rate
LIMIT_RAD = 0.35
SWING_KNEE_RAD = 0.08
#: The pitch-rate term grows with the plan's crouch: full from this much knee flexion of the
#: less flexed knee on, none standing straight (where it tips the robot over backwards).
RATE_FULL_KNEE_RAD = 0.1

_J = {n: i for i, n in enumerate(JOINT_NAMES)}
_HIP_Y = np.array([_J["l_hip_y"], _J["r_hip_y"]])
_HIP_X = np.array([_J["l_hip_x"], _J["r_hip_x"]])


class Balance:
    """Feedback for one rollout of PLAN ([n, 25] rad, one row per tick)."""

    def __init__(self, plan: np.ndarray):
        dk = plan[:, _J["l_knee_y"]] - plan[:, _J["r_knee_y"]]
        # Stance share of each leg per tick (1: on the ground, 0: lifted by the plan).
        self.stance = np.stack([1.0 - np.clip(dk / SWING_KNEE_RAD, 0, 1),
                                1.0 - np.clip(-dk / SWING_KNEE_RAD, 0, 1)], axis=1)
        crouch = np.minimum(plan[:, _J["l_knee_y"]], plan[:, _J["r_knee_y"]])
        self.rate_share = np.clip(crouch / RATE_FULL_KNEE_RAD, 0.0, 1.0)
        self.body = None

    def start(self, body: int, client: int, r0: np.ndarray, start_dir) -> None:
        """Measure from now on relative to the upright pose R0 (the pelvis's rotation at the start)."""
        self.body, self.client, self.r0 = body, client, r0
        self.d0 = np.array([start_dir[0], start_dir[1], 0.0])

    def measure(self) -> tuple[float, float, float, float]:
        """(pitch, pitch rate, roll, roll rate) of the pelvis: forward and leftward lean, rad and rad/s."""
        _, q = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        _, w = pb.getBaseVelocity(self.body, physicsClientId=self.client)
        r = np.array(pb.getMatrixFromQuaternion(q)).reshape(3, 3) @ self.r0.T
        up = r[:, 2]
        f = r @ self.d0
        f[2] = 0.0
        n = float(np.hypot(f[0], f[1]))
        f = f / n if n > 1e-9 else self.d0
        left = np.array([-f[1], f[0], 0.0])
        w = np.asarray(w)
        return float(up @ f), float(w @ left), float(up @ left), float(-(w @ f))

    def correct(self, tick: int, target: np.ndarray) -> np.ndarray:
        """TARGET (the plan's command at this physics step, in the plan's tick TICK), corrected."""
        pitch, pitch_rate, roll, roll_rate = self.measure()
        tick = min(tick, len(self.stance) - 1)
        dh = float(np.clip(KH * pitch + KHD * self.rate_share[tick] * pitch_rate, -LIMIT_RAD, LIMIT_RAD))
        dr = float(np.clip(KR * roll + KRD * roll_rate, -LIMIT_RAD, LIMIT_RAD))
        out = np.array(target, dtype=float)
        out[_HIP_Y] += dh * self.stance[tick]
        out[_HIP_X] += dr
        return out
