"""Walking plans: waypoint trajectories of the 25 joints, and their search.

A plan is an array ``[T, 25]`` of joint targets in radians (pypot convention,
model joint order), one waypoint per 30 Hz tick, starting at the episode's tick 0.
Plans come from a periodic dynamic gait family (lateral sway on the hips,
alternating leg lift, stride, turning, crouch, forward lean, arm swing) with
the real robot's posture (generator 6): the trunk swaying on ``abs_x`` with
``bust_x`` opposite and the arms held out on ``shoulder_x``, as the Poppy
hardware walk does (and the authors' keyframe walk: shoulders 20-45 deg out,
``abs_x`` 10 deg), and a head posture. Its parameters are sampled; the
planner keeps a sample only if the robot, simulated without perturbation and
with the balance feedback of ``balance.py``, stays up and walks forward (see
``episode.search_plan``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .robot import JOINT_NAMES, index_of

J = {name: index_of(name) for name in JOINT_NAMES}

#: Sampling ranges of the gait parameters (uniform).
PARAM_RANGES: dict[str, tuple[float, float]] = {
    "period_s": (1.1, 2.4),        # one full step cycle (left + right step)
    "sway_rad": (0.15, 0.25),      # hip_x amplitude: shifts the weight over the stance foot
    "lift_rad": (0.12, 0.28),      # extra knee flexion of the swing leg
    "stride_rad": (0.02, 0.12),    # hip_y amplitude: fore-aft swing of each leg
    "crouch_rad": (0.05, 0.22),    # standing knee flexion / 2
    "turn_rad": (-0.05, 0.05),     # hip_z amplitude, signed: heading change per step
    "lean_rad": (-0.02, 0.15),     # abs_y forward lean
    "arm_swing_rad": (0.0, 0.15),   # shoulder_y amplitude
    "lift_lag": (0.3, 0.8),        # phase lag of lift behind sway (rad)
    "ramp_s": (1.0, 2.0),          # time over which the gait grows from standing
    "trunk_sway_rad": (0.0, 0.5),  # abs_x amplitude, bust_x opposite (the real robot's trunk sway)
    "arm_out_rad": (0.0, 0.8),     # shoulder_x held out, both sides (the real robot's arms out)
    "head_y_rad": (-0.15, 0.3),    # head posture: pitch (down +) and yaw held through the walk
    "head_z_rad": (-0.25, 0.25),
}


#: The plan search's proposal (uniform). Generator 5's (hip sway, knee lift and
#: lift lag narrowed to where its kept gaits lay) with what walks under the
#: balance feedback (sim/README.md, "A walk with feedback"): a longer stride
#: and a shorter period walk farther with the feedback and fall without it;
#: a lift above 0.2 rad or a trunk sway above ~0.4 rad falls in most draws
#: (trunk sway 0.45-0.7 rad: 0 of 10 gaits stayed up), a deeper crouch (up to
#: 0.22 rad: knees to 37 deg with the lift) walks (6 of 10 at 0.15-0.25).
PROPOSAL_RANGES: dict[str, tuple[float, float]] = {
    **PARAM_RANGES,
    "period_s": (1.1, 2.4),
    "sway_rad": (0.15, 0.18),
    "lift_rad": (0.12, 0.2),
    "stride_rad": (0.04, 0.09),
    "turn_rad": (-0.04, 0.04),
    "lean_rad": (0.0, 0.12),
    "arm_swing_rad": (0.0, 0.12),
    "lift_lag": (0.3, 0.65),
    "trunk_sway_rad": (0.0, 0.4),
    "arm_out_rad": (0.0, 0.75),
}

@dataclass(frozen=True)
class GaitParams:
    period_s: float
    sway_rad: float
    lift_rad: float
    stride_rad: float
    crouch_rad: float
    turn_rad: float
    lean_rad: float
    arm_swing_rad: float
    lift_lag: float
    ramp_s: float
    trunk_sway_rad: float = 0.0
    arm_out_rad: float = 0.0
    head_y_rad: float = 0.0
    head_z_rad: float = 0.0

    @staticmethod
    def sample(rng: np.random.Generator) -> "GaitParams":
        return GaitParams(**{k: float(rng.uniform(lo, hi)) for k, (lo, hi) in PARAM_RANGES.items()})

    @staticmethod
    def propose(rng: np.random.Generator) -> "GaitParams":
        """A candidate of the plan search, from PROPOSAL_RANGES."""
        return GaitParams(**{k: float(rng.uniform(lo, hi)) for k, (lo, hi) in PROPOSAL_RANGES.items()})

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def standing_pose() -> np.ndarray:
    """All joints at 0 rad: upright, arms down (pypot's zero, offsets applied)."""
    return np.zeros(len(JOINT_NAMES))


def gait_waypoints(p: GaitParams, n_ticks: int, rate_hz: float) -> np.ndarray:
    """Waypoints [n_ticks, 25] (rad) of gait P sampled at RATE_HZ from t = 0."""
    t = np.arange(n_ticks) / rate_hz
    # Amplitude grows smoothly from 0 (standing) to 1 over ramp_s.
    ramp = np.clip(t / p.ramp_s, 0.0, 1.0)
    ramp = ramp * ramp * (3 - 2 * ramp)
    phase = 2 * np.pi * t / p.period_s
    sway = p.sway_rad * np.sin(phase)
    lift_phase = np.sin(phase - p.lift_lag)
    lift_l = p.lift_rad * np.clip(lift_phase, 0, None)
    lift_r = p.lift_rad * np.clip(-lift_phase, 0, None)
    # Stance leg pushes back while the other leg is lifted (found by search:
    # this phase walks forward, the opposite one falls backward).
    stride = -p.stride_rad * np.cos(phase - p.lift_lag)
    w = np.zeros((n_ticks, len(JOINT_NAMES)))
    crouch = p.crouch_rad * ramp
    for side, lift, sgn in (("l", lift_l, 1.0), ("r", lift_r, -1.0)):
        hip_y = -crouch - ramp * (lift / 2) + ramp * sgn * stride
        knee = 2 * crouch + ramp * lift
        w[:, J[f"{side}_hip_y"]] = hip_y
        w[:, J[f"{side}_knee_y"]] = knee
        w[:, J[f"{side}_ankle_y"]] = -(hip_y + knee)
        w[:, J[f"{side}_hip_x"]] = ramp * sway
        w[:, J[f"{side}_hip_z"]] = ramp * p.turn_rad * sgn * np.cos(phase - p.lift_lag)
    w[:, J["abs_y"]] = ramp * p.lean_rad
    w[:, J["abs_x"]] = -0.5 * ramp * sway + ramp * p.trunk_sway_rad * np.sin(phase)
    w[:, J["bust_x"]] = -ramp * p.trunk_sway_rad * np.sin(phase)
    w[:, J["l_shoulder_x"]] = ramp * p.arm_out_rad
    w[:, J["r_shoulder_x"]] = -ramp * p.arm_out_rad
    w[:, J["head_y"]] = ramp * p.head_y_rad
    w[:, J["head_z"]] = ramp * p.head_z_rad
    w[:, J["l_shoulder_y"]] = -ramp * p.arm_swing_rad * np.cos(phase - p.lift_lag)
    w[:, J["r_shoulder_y"]] = ramp * p.arm_swing_rad * np.cos(phase - p.lift_lag)
    return w
