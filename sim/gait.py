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

A second family, the **hardware gait** (``HardwareGaitParams``), is the real
Poppy walk's own commanded step, replayed open loop and randomised around
it: a quasi-static step (the trunk swings to one side, +-36 deg on ``abs_x``
with ``bust_x`` the same way, the arms out, the unloaded leg kicks forward,
the trunk swings back), mirrored every step. Its knots are
``model/poppy_muffin_step.json``, taken from the committed real walk's
published plan (``poppy_muffin.step_knots``). The real robot walks it
slowly and with little progress; it is in the family so that the postures
of the real walk (the trunk's full sway, the knee's 46 deg kick) are in the
training data, not for distance.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

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

    family = "dynamic"
    feedback = True  # walks through the balance feedback
    walks = True     # a kept plan walks MIN_PROGRESS_M or more (``episode.search_plan``)

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


#: One step of the real Poppy walk's commanded path (``poppy_muffin.step_knots``): the
#: knots (s, model order rad) from the initial pose to its mirror image.
STEP_KNOTS_PATH = Path(__file__).parent / "model" / "poppy_muffin_step.json"

#: Joints whose sign flips when the step is mirrored left for right (roll and yaw axes);
#: pitch joints keep their sign. Left and right joints swap.
MIRROR_NEGATED = ("hip_x", "hip_z", "abs_x", "abs_z", "bust_x", "head_z", "shoulder_x", "arm_z")


def mirror_index_and_sign() -> tuple[np.ndarray, np.ndarray]:
    """For each model joint: the joint whose angle it takes in the mirror image, and the sign."""
    index, sign = [], []
    for name in JOINT_NAMES:
        other = ("r_" + name[2:] if name.startswith("l_") else "l_" + name[2:]
                 if name.startswith("r_") else name)
        index.append(J[other])
        sign.append(-1.0 if any(name.endswith(k) for k in MIRROR_NEGATED) else 1.0)
    return np.array(index), np.array(sign)


def mirrored(q: np.ndarray) -> np.ndarray:
    """Angles [..., 25] mirrored left for right."""
    index, sign = mirror_index_and_sign()
    return q[..., index] * sign


def load_step_knots(path: Path = STEP_KNOTS_PATH) -> tuple[np.ndarray, np.ndarray]:
    """The hardware step's knot times (s) and angles [K, 25] (rad)."""
    d = json.loads(path.read_text())
    if list(d["joint_names"]) != list(JOINT_NAMES):
        raise ValueError(f"{path}: joint names are not the model's, in its order")
    return np.asarray(d["time_s"], dtype=float), np.asarray(d["angles_rad"], dtype=float)


#: The hardware gait's proposal ranges (uniform; ``mirrored`` is drawn 0 or 1).
HARDWARE_RANGES: dict[str, tuple[float, float]] = {
    "time_scale": (0.35, 1.0),   # the step's duration x this (1: the real walk's 25.6 s)
    "trunk_scale": (0.8, 1.15),  # abs_x and bust_x (1: +-36 deg)
    "arm_scale": (0.6, 1.2),     # shoulder_x (1: 36 deg out)
    "leg_scale": (0.8, 1.1),     # hip_y, knee_y, ankle_y away from the initial pose (1: the knee's 46 deg)
    "lean_scale": (0.5, 1.3),    # abs_y (1: 11 deg forward at rest)
    "head_y_rad": (-0.15, 0.3),
    "head_z_rad": (-0.25, 0.25),
}

_GROUPS: dict[str, tuple[str, ...]] = {
    "trunk_scale": ("abs_x", "bust_x"),
    "arm_scale": ("l_shoulder_x", "r_shoulder_x"),
    "leg_scale": tuple(f"{s}_{j}" for s in "lr" for j in ("hip_y", "knee_y", "ankle_y")),
    "lean_scale": ("abs_y",),
}


@dataclass(frozen=True)
class HardwareGaitParams:
    time_scale: float
    trunk_scale: float
    arm_scale: float
    leg_scale: float
    lean_scale: float
    mirrored: float
    head_y_rad: float = 0.0
    head_z_rad: float = 0.0

    family = "hardware"
    #: The balance feedback is off: the real walk's step is quasi-static and
    #: stays up open loop; the feedback's hip corrections tip it over.
    feedback = False
    #: Kept without a distance to walk: the real step is quasi-static.
    walks = False

    @staticmethod
    def propose(rng: np.random.Generator) -> "HardwareGaitParams":
        drawn = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in HARDWARE_RANGES.items()}
        return HardwareGaitParams(mirrored=float(rng.integers(2)), **drawn)

    def as_dict(self) -> dict[str, float | str]:
        return {"family": self.family, **asdict(self)}


def hardware_waypoints(p: HardwareGaitParams, n_ticks: int, rate_hz: float,
                       knots: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Waypoints [n_ticks, 25] (rad) of the hardware gait P: the real step, then its mirror
    image, and so on, each step TIME_SCALE x as long as the real one, scaled around its start pose."""
    t_k, q_k = knots if knots is not None else load_step_knots()
    step_s = float(t_k[-1])
    q0 = q_k[0]
    scaled = q_k.copy()
    for key, names in _GROUPS.items():
        cols = [J[n] for n in names]
        scaled[:, cols] = q0[cols] + getattr(p, key) * (q_k[:, cols] - q0[cols])
    t = np.arange(n_ticks) / rate_hz / p.time_scale
    step_no = np.floor(t / step_s).astype(int)
    within = t - step_no * step_s
    w = np.column_stack([np.interp(within, t_k, scaled[:, j]) for j in range(len(JOINT_NAMES))])
    flip = (step_no + int(p.mirrored)) % 2 == 1
    w[flip] = mirrored(w[flip])
    w[:, J["head_y"]] += p.head_y_rad
    w[:, J["head_z"]] += p.head_z_rad
    return w


def plan_waypoints(p: "GaitParams | HardwareGaitParams", n_ticks: int, rate_hz: float) -> np.ndarray:
    """Waypoints of either family's gait."""
    if isinstance(p, HardwareGaitParams):
        return hardware_waypoints(p, n_ticks, rate_hz)
    return gait_waypoints(p, n_ticks, rate_hz)


#: The gait families a data set can be made of (``generate --gait``), by name.
FAMILIES: dict[str, type] = {cls.family: cls for cls in (GaitParams, HardwareGaitParams)}
GAIT_FAMILIES = tuple(FAMILIES)


def params_from_dict(d: dict) -> "GaitParams | HardwareGaitParams":
    """Gait parameters as ``as_dict`` wrote them (no ``family``: the dynamic gait)."""
    d = dict(d)
    family = d.pop("family", "dynamic")
    if family not in FAMILIES:
        raise ValueError(f"unknown gait family {family!r}")
    return FAMILIES[family](**d)
