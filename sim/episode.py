"""One simulated episode (generator 6): plan search, perturbation, hazards, physics, camera, labels.

Data enters as an episode seed (everything else is drawn from it) and leaves as
an ``Episode``: per 30 Hz tick the measured joint angles (rad, pypot convention,
model order), a JPEG head-camera frame, the head height and the sticky fallen
label, plus the perturbed plan (one waypoint per tick, including 2.5 s before
the start and 3 s past the end) and the metadata. ``recording.write_episode``
turns it into an MCAP file.

Time: physics runs at 240 Hz (8 steps per tick). Waypoint k applies at tick k;
between waypoints the command is interpolated linearly at each physics step,
and the balance feedback (``balance.py``) corrects it there from the pelvis's
measured pitch and roll: the published plan stays the planner's, the joints
carry the corrections.

Why falls happen, and what shows them coming:

- **An event in the plan.** The perturbation lives on sparse plan knots, one
  every ``KNOT_TICKS`` = 10 ticks (1/3 s), interpolated smoothly (C1
  smoothstep) between knots. Knot j of every joint but the head gets
  ``PERTURBATION_SCALE * eta``, ``eta ~ N(0, s_j^2)``, independent across
  knots and joints. Every knot has the episode's *background* sigma (0.005
  or 0.01: walking). An episode whose sigma is above ``BACKGROUND_SIGMA_MAX``
  also has an *event*: ``EVENT_KNOTS`` consecutive knots at ``EVENT_GAIN``
  x sigma, the first drawn within ``EVENT_START_S``. Until its event such an
  episode is a walking one (same background, same joints' statistics), so
  nothing in the joints foretells the fall; the event is in the published
  plan (one message a second, reaching 3 s ahead) 2-3 s before it acts, and
  the fall follows it by ~1.6 s (median).
- **Plans that walk at low sigma.** A kept plan walks ``MIN_PROGRESS_M`` in
  10 s unperturbed and stays up under ``VALIDATION_DRAWS`` knot
  perturbations: a background at ``VALIDATION_BACKGROUND_SIGMA`` (the largest
  an episode has) from the start plus ``VALIDATION_SIGMA`` with the paper's
  ramp (eq. 1, up to 1.5x that after 4 s), so that falls without an event
  are rare. The
  search runs once per plan, on a bare floor (``search_plan``), and a kept
  plan serves several episodes (``sim.dataset``), each with its own room,
  start pose, ball and perturbation draw.
- **A ball rolled at the robot** in ``HAZARD_PROBABILITY`` of the episodes:
  launched from 1.4-2.0 m ahead inside the head camera's view, it reaches
  the robot about 1 s later. The camera sees it coming; the plan and the
  joints do not.
- **A push on the trunk** in ``PUSH_PROBABILITY`` of the episodes: a force on
  the chest for ``PUSH_DURATION_S`` at a random time, from a random
  direction, of a random impulse. Nothing foretells it.
- **An obstacle in the walking path** in ``OBSTACLE_PROBABILITY`` of the
  episodes: a panel, a box or a low step placed ahead on the robot's start
  heading, which the plan does not know of (the plan search ran on a bare
  floor) and the camera sees as the robot walks to it.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field

import numpy as np
import pybullet as pb
from PIL import Image

from .balance import KH, KHD, KR, KRD, LIMIT_RAD, Balance
from .gait import FAMILIES, GaitParams, HardwareGaitParams, params_from_dict, plan_waypoints, standing_pose
from .robot import FALL_FRACTION, JOINT_NAMES, PHYSICS_HZ, ROBOT_NAME, Robot
from .scene import FLOOR_FRICTION, build_room
from .sensors import (FRAME_DROP_PROBABILITY, FREEZE_START_PROBABILITY, MISS_PROBABILITY, READ_HZ,
                      RETRY_PROBABILITY, camera_summary, draw_camera, draw_reads)

RATE_HZ = 30
STEPS_PER_TICK = PHYSICS_HZ // RATE_HZ
DURATION_S = 10.0
FRAME_PX = 64
PLAN_PERIOD_TICKS = RATE_HZ           # a plan message every 1 s
PLAN_PAST_TICKS = 75                   # each plan covers [now - 2.5 s, now + 3 s]
PLAN_FUTURE_TICKS = 90
SETTLE_STEPS = 60                      # physics steps holding the first pose before tick 0
SIGMAS = (0.005, 0.010, 0.035, 0.040)
#: sigma above this: the episode has an event; at or below: background only (walking).
BACKGROUND_SIGMA_MAX = 0.010
#: An event episode's background sigma is drawn from these (as a walking episode's).
BACKGROUND_SIGMAS = (0.005, 0.010)
#: The event: EVENT_KNOTS consecutive knots at EVENT_GAIN x sigma, starting at a knot
#: drawn within EVENT_START_S (s) of the episode.
EVENT_KNOTS = 3
EVENT_GAIN = 3.0
EVENT_START_S = (3.0, 7.5)
#: The paper's ramp (eq. 1), used by the plan search's validation draws.
RAMP_A = 90.0
RAMP_B = 0.125
GENERATOR_VERSION = 6
#: One perturbation knot every this many ticks (1/3 s); rho counts physics steps.
KNOT_TICKS = 10
#: Radians of knot deviation per unit of eta (chosen by measurement, see sim/README.md).
PERTURBATION_SCALE = 0.5
#: Joints the plan perturbation leaves alone: the head carries the camera.
UNPERTURBED_JOINTS = ("head_z", "head_y")
#: A kept plan survives this many knot perturbations at VALIDATION_SIGMA.
VALIDATION_DRAWS = 6
VALIDATION_SIGMA = 0.015
#: ...on top of a background at this sigma from the start (the largest background an episode has),
#: so that a kept plan walks at low sigma from its first step.
VALIDATION_BACKGROUND_SIGMA = 0.010
#: Validation draws leave the knots up to this tick (the start pose) unperturbed.
VALIDATION_FROM_TICK = 0
HAZARD_PROBABILITY = 0.2
HAZARD_LAUNCH_S = (2.0, 7.5)
HAZARD_DISTANCE_M = (1.4, 2.0)
HAZARD_SPEED_M_S = (1.6, 2.4)
HAZARD_RADIUS_M = (0.12, 0.18)
HAZARD_MASS_KG = (2.0, 4.0)
HAZARD_PARK_XY = (10.0, 10.0)          # outside the room until launched
#: A fall is caused by a collision when it follows the first contact within this.
COLLISION_FALL_WINDOW_TICKS = 2 * RATE_HZ
MAX_PLAN_ATTEMPTS = 400
#: Random stream of the plan search of an episode simulated alone (not in a data set).
PLAN_STREAM = 31
MIN_PROGRESS_M = 0.25                  # a kept 10 s plan walks at least this far along its heading
#: Pushes on the trunk: share of episodes, when (s), impulse (N s), how long the force lasts.
PUSH_PROBABILITY = 0.15
PUSH_START_S = (2.0, 8.0)
PUSH_IMPULSE_NS = (0.3, 1.5)
PUSH_DURATION_S = 0.1
PUSH_LINK = "chest"
#: Obstacles in the walking path: share of episodes, and per kind the distance of its nearest
#: corner ahead of the pelvis (m): a sill (a low bar across the path, which trips the feet), a
#: box (shin to thigh high), a panel (a wall-like board taller than the camera's view line) and
#: a table (its top at chest height: the legs walk under it, the chest and arms hit its edge).
OBSTACLE_PROBABILITY = 0.15
OBSTACLE_KINDS = ("sill", "box", "panel", "table")
OBSTACLE_DIST_M = {"sill": (0.1, 0.35), "box": (0.2, 0.45), "panel": (0.25, 0.5), "table": (0.12, 0.3)}
#: A table's top and legs are this thick (m).
TABLE_BOARD_M = 0.03
#: Random streams of the push and the obstacle (apart from the episode's own, so that
#: forcing either leaves the rest of the episode as it was).
PUSH_STREAM = 41
OBSTACLE_STREAM = 43
#: A fall is caused by a push or a contact when it follows it within this.
CAUSE_WINDOW_TICKS = 2 * RATE_HZ
CAMERA_FOV_DEG = 60.0
CAMERA_PITCH_DOWN_DEG = 10.0           # camera axis below the head's forward direction
JPEG_QUALITY = 90


@dataclass(frozen=True)
class KeptPlan:
    """A walking plan the search kept: the gait, what the search cost, how far it walks.

    PLAN_ID names it in the data set (``"<base seed>:<plan group>"``);
    episodes that share a plan share this record.
    """
    params: GaitParams | HardwareGaitParams
    attempts: int
    progress_m: float
    plan_id: str = ""

    def as_dict(self) -> dict:
        return {"params": self.params.as_dict(), "attempts": self.attempts,
                "progress_m": self.progress_m, "plan_id": self.plan_id}

    @staticmethod
    def from_dict(d: dict) -> "KeptPlan":
        return KeptPlan(params_from_dict(d["params"]), int(d["attempts"]), float(d["progress_m"]),
                        str(d.get("plan_id", "")))


def outside_cause_probabilities(hazard_probability: float) -> dict[str, float]:
    """The push and obstacle probabilities of a set made with HAZARD_PROBABILITY (the ball's):
    PUSH_PROBABILITY and OBSTACLE_PROBABILITY, or none when the ball is off (the walking set,
    ``--ball-probability 0``, has no outside cause)."""
    on = hazard_probability > 0
    return {"push_probability": PUSH_PROBABILITY if on else 0.0,
            "obstacle_probability": OBSTACLE_PROBABILITY if on else 0.0}


def stamp_ns(tick: int) -> int:
    """Episode time of TICK in ns (floor of tick / 30 s); tick 0 is 0 ns."""
    return tick * 1_000_000_000 // RATE_HZ


def knot_ticks(n_plan: int) -> np.ndarray:
    """Ticks of the perturbation knots covering N_PLAN waypoints (0, 10, 20, ...)."""
    return np.arange(n_plan // KNOT_TICKS + 2) * KNOT_TICKS


def knot_deviation(knot_eta: np.ndarray, sigma: float, n_plan: int) -> np.ndarray:
    """Plan deviation [n_plan, 25] (rad) from per-knot eta [n_knots, 25] with the paper's ramp
    (eq. 1 per knot, ``perturbation_factor``), smoothstep between knots: the plan search's
    validation draws."""
    rho = knot_ticks(n_plan) * STEPS_PER_TICK
    return smooth_knots(PERTURBATION_SCALE * perturbation_factor(sigma, rho)[:, None] * knot_eta, n_plan)


def smooth_knots(knot_dev: np.ndarray, n_plan: int) -> np.ndarray:
    """Plan deviation [n_plan, 25] (rad) from per-knot deviations [n_knots, 25] (rad): the head
    joints left alone, a C1 smoothstep from each knot to the next."""
    dev = knot_dev.copy()
    dev[:, [JOINT_NAMES.index(n) for n in UNPERTURBED_JOINTS]] = 0.0
    t = np.arange(n_plan)
    i, f = t // KNOT_TICKS, (t % KNOT_TICKS) / KNOT_TICKS
    s = f * f * (3 - 2 * f)
    return (1 - s)[:, None] * dev[i] + s[:, None] * dev[i + 1]


def knot_sigmas(sigma: float, background_sigma: float, event_knot: int | None, n_knots: int) -> np.ndarray:
    """Per-knot standard deviation of eta [n_knots]: BACKGROUND_SIGMA on every knot, and
    EVENT_GAIN x SIGMA on the EVENT_KNOTS knots from EVENT_KNOT on (None: no event)."""
    amp = np.full(n_knots, background_sigma, dtype=float)
    if event_knot is not None:
        amp[event_knot:event_knot + EVENT_KNOTS] = EVENT_GAIN * sigma
    return amp


def event_knot_range(n_plan: int, n_ticks: int) -> np.ndarray:
    """The knots an event may start at: ticks within EVENT_START_S of the episode (an
    episode too short for that window: any knot from its second on, inside the episode)."""
    ticks = knot_ticks(n_plan)
    lo, hi = (s * RATE_HZ for s in EVENT_START_S)
    knots = np.flatnonzero((ticks >= lo) & (ticks <= min(hi, n_ticks - 1)))
    return knots if knots.size else np.flatnonzero((ticks >= KNOT_TICKS) & (ticks < n_ticks))


def perturbation_factor(sigma: float, rho_steps: np.ndarray) -> np.ndarray:
    """The paper's amplifier: 1 for sigma <= 0.01, else 1.5 / (1 + exp(a - b * rho)).

    RHO_STEPS counts 240 Hz physics steps since tick 0 (8 per tick), so the ramp
    is centred at rho = a / b = 720 steps = 3 s and reaches 1.5 by ~4 s.
    """
    if sigma <= 0.01:
        return np.ones_like(rho_steps, dtype=float)
    return 1.5 / (1.0 + np.exp(RAMP_A - RAMP_B * rho_steps))


class World:
    """A pybullet DIRECT client with gravity and the physics rate set."""

    def __init__(self):
        self.client = pb.connect(pb.DIRECT)
        pb.setGravity(0, 0, -9.81, physicsClientId=self.client)
        pb.setTimeStep(1.0 / PHYSICS_HZ, physicsClientId=self.client)

    def close(self):
        pb.disconnect(self.client)

    def add_floor(self) -> int:
        """A bare floor with the room's friction (plan search, tracking runs)."""
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=self.client)
        floor = pb.createMultiBody(0, plane, physicsClientId=self.client)
        pb.changeDynamics(floor, -1, lateralFriction=FLOOR_FRICTION, physicsClientId=self.client)
        return floor


_STANDING_HEAD_HEIGHT_M: float | None = None


def standing_head_height_m() -> float:
    """Head link height (m) of the model standing still in the zero pose (measured once)."""
    global _STANDING_HEAD_HEIGHT_M
    if _STANDING_HEAD_HEIGHT_M is None:
        world = World()
        try:
            plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=world.client)
            pb.createMultiBody(0, plane, physicsClientId=world.client)
            robot = Robot(world.client)
            robot.place(standing_pose(), (0, 0), 0.0)
            for _ in range(PHYSICS_HZ):
                robot.command(standing_pose())
                pb.stepSimulation(physicsClientId=world.client)
            _STANDING_HEAD_HEIGHT_M = round(robot.head_height_m(), 4)
        finally:
            world.close()
    return _STANDING_HEAD_HEIGHT_M


@dataclass
class Hazard:
    """A ball rolled at the robot: launched at LAUNCH_TICK from DISTANCE_M ahead."""
    launch_tick: int
    distance_m: float
    bearing_rad: float        # from the robot's facing at launch, within the camera's view
    speed_m_s: float
    aim_offset_m: float       # lateral miss distance aimed at (0 = the pelvis)
    radius_m: float
    mass_kg: float
    rgb: tuple[float, float, float]
    #: Where it was launched from (set at launch; None: every path was blocked, not launched).
    start_xy: tuple[float, float] | None = None

    @staticmethod
    def sample(rng: np.random.Generator, n_ticks: int) -> "Hazard":
        lo, hi = (int(s * RATE_HZ) for s in HAZARD_LAUNCH_S)
        return Hazard(launch_tick=int(rng.integers(lo, min(hi, max(lo + 1, n_ticks - RATE_HZ)))),
                      distance_m=float(rng.uniform(*HAZARD_DISTANCE_M)),
                      bearing_rad=float(rng.uniform(-0.17, 0.17)),
                      speed_m_s=float(rng.uniform(*HAZARD_SPEED_M_S)),
                      aim_offset_m=float(rng.uniform(-0.05, 0.05)),
                      radius_m=float(rng.uniform(*HAZARD_RADIUS_M)),
                      mass_kg=float(rng.uniform(*HAZARD_MASS_KG)),
                      rgb=tuple(float(c) for c in rng.uniform(0.2, 1.0, 3)))

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["launch_ns"] = stamp_ns(self.launch_tick)
        d["launched"] = self.start_xy is not None
        return d


@dataclass
class Push:
    """A push on the trunk: a horizontal force on the chest from TICK for PUSH_DURATION_S."""
    tick: int
    direction_rad: float      # where it pushes to, from the robot's facing at the push (0: forward, +: left)
    impulse_ns: float         # N s (force x PUSH_DURATION_S)

    @staticmethod
    def sample(rng: np.random.Generator, n_ticks: int) -> "Push":
        lo, hi = (int(s * RATE_HZ) for s in PUSH_START_S)
        return Push(tick=int(rng.integers(lo, min(hi, max(lo + 1, n_ticks - RATE_HZ)))),
                    direction_rad=float(rng.uniform(-math.pi, math.pi)),
                    impulse_ns=float(rng.uniform(*PUSH_IMPULSE_NS)))

    def as_dict(self) -> dict:
        return {"tick": self.tick, "ns": stamp_ns(self.tick), "direction_rad": round(self.direction_rad, 6),
                "impulse_ns": round(self.impulse_ns, 6), "duration_s": PUSH_DURATION_S, "link": PUSH_LINK}


@dataclass
class Obstacle:
    """An obstacle the plan does not know of, DISTANCE_M ahead on the start heading."""
    kind: str                 # "sill" (a low bar across the path), "box" (a crate), "panel" (a wall-like
                              # board), "table" (size: width, depth, height of the top)
    distance_m: float
    lateral_m: float
    size_m: tuple[float, float, float]   # width (across the path), depth, height
    yaw_rad: float            # from square to the path
    rgb: tuple[float, float, float]

    @staticmethod
    def sample(rng: np.random.Generator) -> "Obstacle":
        kind = str(rng.choice(OBSTACLE_KINDS))
        size = {"sill": (rng.uniform(0.6, 1.0), rng.uniform(0.02, 0.06), rng.uniform(0.02, 0.07)),
                "box": (rng.uniform(0.2, 0.45), rng.uniform(0.15, 0.35), rng.uniform(0.08, 0.35)),
                "panel": (rng.uniform(0.5, 1.2), rng.uniform(0.03, 0.08), rng.uniform(0.5, 1.0)),
                "table": (rng.uniform(0.6, 1.0), rng.uniform(0.4, 0.7), rng.uniform(0.4, 0.62))}[kind]
        return Obstacle(kind=kind, distance_m=float(rng.uniform(*OBSTACLE_DIST_M[kind])),
                        lateral_m=float(rng.uniform(-0.06, 0.06)), size_m=tuple(float(x) for x in size),
                        yaw_rad=float(rng.uniform(-0.4, 0.4)),
                        rgb=tuple(float(c) for c in rng.uniform(0.15, 0.95, 3)))

    def as_dict(self) -> dict:
        return dict(self.__dict__)

    def add(self, client: int, start_xy, direction) -> int:
        """Build it: its nearest corner DISTANCE_M ahead of START_XY along DIRECTION (unit xy)."""
        w, d, h = self.size_m
        fwd = np.asarray(direction, dtype=float)
        side = np.array([-fwd[1], fwd[0]])
        reach = w / 2 * abs(math.sin(self.yaw_rad)) + d / 2 * abs(math.cos(self.yaw_rad))
        xy = np.asarray(start_xy) + (self.distance_m + reach) * fwd + self.lateral_m * side
        yaw = math.atan2(fwd[1], fwd[0]) + math.pi / 2 + self.yaw_rad
        if self.kind == "table":
            # A top at height h and four legs at its corners, in the body's frame (centre on the floor).
            t = TABLE_BOARD_M
            parts = [((w / 2, d / 2, t / 2), (0.0, 0.0, h - t / 2))]
            parts += [((t / 2, t / 2, (h - t) / 2), (sx * (w / 2 - t / 2), sy * (d / 2 - t / 2), (h - t) / 2))
                      for sx in (-1, 1) for sy in (-1, 1)]
        else:
            parts = [((w / 2, d / 2, h / 2), (0.0, 0.0, h / 2))]
        col = pb.createCollisionShapeArray([pb.GEOM_BOX] * len(parts), halfExtents=[p[0] for p in parts],
                                           collisionFramePositions=[p[1] for p in parts], physicsClientId=client)
        vis = pb.createVisualShapeArray([pb.GEOM_BOX] * len(parts), halfExtents=[p[0] for p in parts],
                                        visualFramePositions=[p[1] for p in parts],
                                        rgbaColors=[[*self.rgb, 1.0]] * len(parts), physicsClientId=client)
        body = pb.createMultiBody(0, col, vis, basePosition=(xy[0], xy[1], 0.0),
                                  baseOrientation=pb.getQuaternionFromEuler((0, 0, yaw)), physicsClientId=client)
        pb.changeDynamics(body, -1, lateralFriction=0.9, physicsClientId=client)
        # Points on its surface (corners, edge middles, face centres), for the camera's view test.
        # (A table's: its top's.)
        z0, hz = (h - TABLE_BOARD_M / 2, TABLE_BOARD_M / 2) if self.kind == "table" else (h / 2, h / 2)
        g = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)
                      if (x, y, z) != (0, 0, 0)], dtype=float) * np.array([w / 2, d / 2, hz])
        r = np.array(pb.getMatrixFromQuaternion(pb.getQuaternionFromEuler((0, 0, yaw)))).reshape(3, 3)
        self.surface = g @ r.T + np.array([xy[0], xy[1], z0])
        return body


@dataclass
class Episode:
    seed: int
    sigma: float
    params: GaitParams | HardwareGaitParams | None
    n_ticks: int
    joints_rad: np.ndarray           # [n_ticks, 25]
    plan_rad: np.ndarray             # [PLAN_PAST_TICKS + n_ticks + PLAN_FUTURE_TICKS + 1, 25]
    head_height_m: np.ndarray        # [n_ticks]
    fallen: np.ndarray               # [n_ticks] bool, sticky
    jpeg_frames: list[bytes]
    standing_head_height_m: float
    scene: dict = field(default_factory=dict)
    plan_attempts: int = 0
    progress_m: float = 0.0
    plan_period_ticks: int = PLAN_PERIOD_TICKS
    hazard: Hazard | None = None
    #: First tick at which the robot touched anything but the floor, and what.
    first_contact_tick: int | None = None
    contact_with: str | None = None
    #: Distance walked: pelvis displacement (m) from the start to 1 s before the fall onset, or to the end.
    distance_m: float = 0.0
    #: With ``counterfactual_lead_ticks``: the onset when the knots from
    #: onset - lead on are redrawn (None: the fall was averted).
    counterfactual_onset_tick: int | None = None
    counterfactual_from_tick: int | None = None
    #: The kept plan's name in its data set ("" when searched for this episode alone).
    plan_id: str = ""
    #: The sigma of every knot outside the event (the episode's sigma when it has no event).
    background_sigma: float = 0.0
    #: The tick at which the plan leaves its background for the event (the knot before the
    #: event's first); None: no event (sigma <= BACKGROUND_SIGMA_MAX).
    event_tick: int | None = None
    push: Push | None = None
    obstacle: Obstacle | None = None
    #: First tick of contact with each thing touched but the floor ({name: tick}).
    contacts: dict = field(default_factory=dict)
    #: At the fall onset, the last tick of contact with each thing touched until then.
    touching_at_onset: dict = field(default_factory=dict)
    #: What the daemon would read (``sensors``): /joint_states messages (stamp ns, positions) at
    #: the buses' cycle, and per tick the camera frame sent (-1: dropped); None: one per tick.
    joint_messages: list | None = None
    camera_sent: list | None = None
    sensors: dict | None = None
    #: Per tick, whether the obstacle was in the camera's view (None: no obstacle, or no camera).
    obstacle_in_view: list | None = None

    def obstacle_record(self) -> dict | None:
        """The obstacle's parameters and when the camera first had it in view (ns; None: never)."""
        if self.obstacle is None:
            return None
        d = {k: v for k, v in self.obstacle.as_dict().items() if k != "surface"}
        if self.obstacle_in_view is not None:
            seen = [k for k, v in enumerate(self.obstacle_in_view) if v]
            d["first_in_view_ns"] = stamp_ns(seen[0]) if seen else None
            d["ticks_in_view"] = len(seen)
        return d

    def cause_events(self) -> list[tuple[int, str]]:
        """(tick, cause) of every outside cause: a push, a touch of the ball or furniture
        ("collision"), of the obstacle ("obstacle"). A touch counts at its last tick before the
        onset (a robot held by an obstacle for seconds falls because of it), named by its first."""
        out = [(t, "obstacle" if name == "obstacle" else "collision") for name, t in self.contacts.items()]
        out += [(t, "obstacle" if name == "obstacle" else "collision")
                 for name, t in self.touching_at_onset.items() if t != self.contacts.get(name)]
        if self.push is not None:
            out.append((self.push.tick, "push"))
        return sorted(out)

    @property
    def fall_threshold_m(self) -> float:
        return round(FALL_FRACTION * self.standing_head_height_m, 4)

    @property
    def fall_onset_tick(self) -> int | None:
        idx = np.flatnonzero(self.fallen)
        return int(idx[0]) if idx.size else None

    @property
    def fall_cause(self) -> str | None:
        """The cause of the fall: the last outside cause ("push", "obstacle" or "collision": the
        ball or furniture) within 2 s before the onset, else "perturbation"; None if no fall."""
        onset = self.fall_onset_tick
        if onset is None:
            return None
        near = [(t, c) for t, c in self.cause_events() if 0 <= onset - t <= CAUSE_WINDOW_TICKS]
        return near[-1][1] if near else "perturbation"

    @property
    def fall_cause_tick(self) -> int | None:
        """When the fall's outside cause began (a push, the first touch of what it touched; None:
        no fall, or a perturbation fall)."""
        onset = self.fall_onset_tick
        if onset is None:
            return None
        near = [(t, c) for t, c in self.cause_events() if 0 <= onset - t <= CAUSE_WINDOW_TICKS]
        if not near:
            return None
        cause = near[-1][1]
        if cause == "push":
            return self.push.tick
        names = [n for n in self.contacts if ("obstacle" if n == "obstacle" else "collision") == cause
                 and 0 <= onset - self.touching_at_onset.get(n, self.contacts[n]) <= CAUSE_WINDOW_TICKS]
        return min(self.contacts[n] for n in names) if names else near[-1][0]

    def plan_message_points(self, tick: int) -> tuple[int, np.ndarray]:
        """(first tick, waypoints) of the plan published at TICK: ticks tick-75 .. tick+90."""
        first = tick - PLAN_PAST_TICKS
        lo = first + PLAN_PAST_TICKS
        return first, self.plan_rad[lo:lo + PLAN_PAST_TICKS + PLAN_FUTURE_TICKS + 1]

    def metadata(self) -> dict[str, str]:
        meta = {
            "source": "sim",
            "generator": str(GENERATOR_VERSION),
            "robot": ROBOT_NAME,
            "rate_hz": str(RATE_HZ),
            "seed": str(self.seed),
            "sigma": f"{self.sigma:g}",
            "standing_head_height_m": f"{self.standing_head_height_m:.4f}",
            "fall_threshold_m": f"{self.fall_threshold_m:.4f}",
            "duration_s": f"{self.n_ticks / RATE_HZ:g}",
            "physics_hz": str(PHYSICS_HZ),
            "perturbation": (f"plan knots every {KNOT_TICKS} ticks, smoothstep between; knot deviation "
                             f"{PERTURBATION_SCALE:g}*eta rad per joint (not the head), eta~N(0,s^2) with "
                             f"s=background_sigma on every knot, and s={EVENT_GAIN:g}*sigma on the "
                             f"{EVENT_KNOTS} knots of the event (sigma>{BACKGROUND_SIGMA_MAX:g} only), whose "
                             f"first knot is drawn within {EVENT_START_S[0]:g}-{EVENT_START_S[1]:g} s"),
            "background_sigma": f"{self.background_sigma:g}",
            "gait": json.dumps(self.params.as_dict() if self.params else None, sort_keys=True),
            "plan_attempts": str(self.plan_attempts),
            "plan_id": self.plan_id,
            "progress_m": f"{self.progress_m:.3f}",
            "distance_m": f"{self.distance_m:.3f}",
            "hazard": json.dumps(self.hazard.as_dict() if self.hazard else None, sort_keys=True),
            "push": json.dumps(self.push.as_dict() if self.push else None, sort_keys=True),
            "obstacle": json.dumps(self.obstacle_record(), sort_keys=True),
            "contacts_ns": json.dumps({k: stamp_ns(t) for k, t in self.contacts.items()}, sort_keys=True),
            "sensors": json.dumps(self.sensors, sort_keys=True),
            "balance": (f"pelvis pitch/roll feedback: hip_y += {KH:g}*pitch + {KHD:g}*pitch_rate (stance legs), "
                        f"hip_x += {KR:g}*roll + {KRD:g}*roll_rate, each within +-{LIMIT_RAD:g} rad"),
            "scene": json.dumps(self.scene, sort_keys=True),
        }
        if self.event_tick is not None:
            meta["event_ns"] = str(stamp_ns(self.event_tick))
        onset = self.fall_onset_tick
        if onset is not None:
            meta["fall_onset_ns"] = str(stamp_ns(onset))
            meta["fall_cause"] = self.fall_cause
            if self.fall_cause_tick is not None:
                meta["cause_ns"] = str(stamp_ns(self.fall_cause_tick))
        if self.first_contact_tick is not None:
            meta["first_contact_ns"] = str(stamp_ns(self.first_contact_tick))
            meta["contact_with"] = self.contact_with or ""
        return meta


class HeadCamera:
    """64x64 RGB camera on the head link, looking where the face looks."""

    def __init__(self, robot: Robot):
        # Head frame axes at the zero pose facing -y give the camera axes in the head frame.
        robot.place(standing_pose(), (0, 0), 0.0)
        _, quat = robot.head_pose()
        r0 = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        pitch = math.radians(CAMERA_PITCH_DOWN_DEG)
        fwd = np.array([0.0, -math.cos(pitch), -math.sin(pitch)])
        up = np.array([0.0, -math.sin(pitch), math.cos(pitch)])
        self.fwd_local = r0.T @ fwd
        self.up_local = r0.T @ up
        # The lens sits in front of the face: 4 cm above and 7 cm ahead of the neck pivot.
        self.eye_local = r0.T @ np.array([0.0, -0.07, 0.04])
        self.projection = pb.computeProjectionMatrixFOV(CAMERA_FOV_DEG, 1.0, 0.02, 12.0)
        self.robot = robot

    def frame(self) -> np.ndarray:
        pos, quat = self.robot.head_pose()
        r = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
        eye = pos + r @ self.eye_local
        # A face-down head would put the lens under the floor; a real lens stays above it.
        eye[2] = max(eye[2], 0.015)
        self.axes = (eye, r @ self.fwd_local, r @ self.up_local)
        view = pb.computeViewMatrix(eye.tolist(), (eye + r @ self.fwd_local).tolist(), (r @ self.up_local).tolist())
        _, _, rgba, _, _ = pb.getCameraImage(
            FRAME_PX, FRAME_PX, view, self.projection, renderer=pb.ER_TINY_RENDERER, shadow=0,
            lightDirection=[0.4, -0.6, 1.0], flags=pb.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self.robot.client)
        return np.asarray(rgba, dtype=np.uint8).reshape(FRAME_PX, FRAME_PX, 4)[:, :, :3]


    def sees(self, points: np.ndarray) -> bool:
        """Whether any of POINTS [n, 3] (world) lies in the last frame's field of view (occlusion
        not considered: nothing stands between the robot and an obstacle in its path)."""
        eye, fwd, up = self.axes
        right = np.cross(fwd, up)
        d = points - eye
        z = d @ fwd
        ok = z > 0.02
        half = math.tan(math.radians(CAMERA_FOV_DEG / 2))
        x, y = (d @ right)[ok] / z[ok], (d @ up)[ok] / z[ok]
        return bool(((np.abs(x) <= half) & (np.abs(y) <= half)).any())


def encode_jpeg(rgb: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=JPEG_QUALITY)
    return buf.getvalue()


class _Run:
    """What one rollout measured."""

    def __init__(self):
        self.joints: list[np.ndarray] = []
        self.heights: list[float] = []
        self.frames: list[bytes] = []
        self.first_contact_tick: int | None = None
        self.contact_with: str | None = None
        #: First and (so far) last tick of contact with each thing but the floor.
        self.contacts: dict[str, int] = {}
        self.last_contact: dict[str, int] = {}
        #: At the onset, the last tick of contact with each thing touched until then.
        self.touching_at_onset: dict[str, int] = {}
        #: Per tick, whether the camera had the watched points in view.
        self.in_view: list[bool] = []
        #: Joint angles at the physics steps asked for (``read_steps``), by step (240 Hz from tick 0).
        self.step_angles: dict[int, np.ndarray] = {}
        self.end_xy: np.ndarray | None = None
        #: First tick with the head below the fall threshold (None: stayed up).
        self.onset_tick: int | None = None
        #: The physics state kept at ``save_at`` (None: not asked, or not reached).
        self.saved: int | None = None


def _facing_xy(robot: Robot, r0: np.ndarray, start_dir: np.ndarray) -> np.ndarray:
    """The robot's walking direction now (unit xy), from the pelvis rotation since the start."""
    _, quat = pb.getBasePositionAndOrientation(robot.body, physicsClientId=robot.client)
    r = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
    fwd = (r @ r0.T @ np.array([start_dir[0], start_dir[1], 0.0]))[:2]
    n = float(np.linalg.norm(fwd))
    return fwd / n if n > 1e-6 else start_dir


def _launch(ball: int, robot: Robot, hazard: Hazard, r0: np.ndarray, start_dir: np.ndarray,
            bodies: dict[int, str]) -> None:
    """Put the ball ahead of the robot (within the camera's view) rolling at it.

    It starts DISTANCE_M away at BEARING_RAD from the robot's facing, or, when
    furniture stands in between, at the first of a fixed list of nearer
    distances and other bearings from which the path to the robot is clear
    (the ball swept along it in 5 cm steps touches nothing).
    """
    fwd = _facing_xy(robot, r0, start_dir)
    base = robot.base_xy()
    target = base + hazard.aim_offset_m * np.array([-fwd[1], fwd[0]])
    z = hazard.radius_m
    candidates = [(hazard.distance_m * f, b) for f in (1.0, 0.8, 0.6, 0.45)
                  for b in (hazard.bearing_rad, -hazard.bearing_rad, 0.0, 0.3, -0.3, 0.45, -0.45)]
    starts = []
    for dist, bearing in candidates:
        c, s = math.cos(bearing), math.sin(bearing)
        towards = np.array([c * fwd[0] - s * fwd[1], s * fwd[0] + c * fwd[1]])
        starts.append(base + dist * towards)
    obstacles = [b for b, name in bodies.items() if name != "floor"]

    def free(p: np.ndarray) -> bool:  # nothing but the floor within 3 cm of the ball at P
        pb.resetBasePositionAndOrientation(ball, (p[0], p[1], z), (0, 0, 0, 1), physicsClientId=robot.client)
        return not any(pb.getClosestPoints(ball, b, 0.03, physicsClientId=robot.client) for b in obstacles)

    def path_clear(p: np.ndarray) -> bool:  # the ball rolls from P to the robot touching nothing else
        n = int(np.linalg.norm(target - p) / 0.05)
        return all(free(p + (target - p) * i / n) for i in range(n))

    start = next((p for p in starts if path_clear(p)), None)
    if start is None:  # furniture blocks every path: the ball stays parked, and the episode says so
        pb.resetBasePositionAndOrientation(ball, (*HAZARD_PARK_XY, z), (0, 0, 0, 1), physicsClientId=robot.client)
        return
    hazard.start_xy = (float(start[0]), float(start[1]))
    v = target - start
    v = hazard.speed_m_s * v / np.linalg.norm(v)
    pb.resetBasePositionAndOrientation(ball, (start[0], start[1], z), (0, 0, 0, 1),
                                       physicsClientId=robot.client)
    # Rolling without slipping: omega = z x v / r.
    pb.resetBaseVelocity(ball, (v[0], v[1], 0.0), (-v[1] / hazard.radius_m, v[0] / hazard.radius_m, 0.0),
                         physicsClientId=robot.client)


def _rollout(world: World, robot: Robot, plan: np.ndarray, n_ticks: int, threshold_m: float,
             stop_on_fall: bool, camera: HeadCamera | None, bodies: dict[int, str] | None = None,
             hazard: Hazard | None = None, ball: int | None = None, save_at: int | None = None,
             resume: tuple[int, int] | None = None, push: Push | None = None, balance: bool = True,
             read_steps: set[int] | None = None, watch: np.ndarray | None = None) -> _Run:
    """Run PLAN (waypoints from tick 0) for N_TICKS; returns per-tick measurements.

    BODIES names the room's bodies (contacts with anything but the floor are
    recorded); HAZARD launches BALL at its tick. SAVE_AT: keep the physics
    state at the start of that tick (``_Run.saved``, a ``pb.saveState`` id,
    contacts included); RESUME (state id, tick) starts from such a state at
    that tick instead of from the start pose: the same as running from tick 0
    when PLAN equals the saved run's plan up to that tick. Measurements then
    start at that tick. PUSH pushes the chest at its tick. BALANCE: the
    commands go through the balance feedback (``balance.Balance``).
    READ_STEPS: keep the joint angles at these physics steps (``_Run.step_angles``;
    step m is the state m / 240 s after tick 0), for the servo buses' reads.
    WATCH: points [n, 3] whose view by the camera is recorded per tick (``_Run.in_view``).
    """
    k0 = 0
    if resume is None:
        robot.place(plan[0], robot.start_xy, robot.start_yaw)
        for _ in range(SETTLE_STEPS):
            robot.command(plan[0])
            pb.stepSimulation(physicsClientId=world.client)
        _, quat = pb.getBasePositionAndOrientation(robot.body, physicsClientId=world.client)
        # The pelvis's rotation standing at the start: the balance feedback's upright.
        robot.upright_r0 = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
    else:
        pb.restoreState(resume[0], physicsClientId=world.client)
        k0 = resume[1]
    _, quat = pb.getBasePositionAndOrientation(robot.body, physicsClientId=world.client)
    r0 = np.array(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
    feedback = None
    if balance:
        feedback = Balance(plan)
        feedback.start(robot.body, world.client, robot.upright_r0, robot.start_dir)
    push_steps: dict[int, tuple] = {}
    run = _Run()
    walked_xy: list[np.ndarray] = []
    for k in range(k0, n_ticks):
        if k == save_at:
            run.saved = pb.saveState(physicsClientId=world.client)
        if hazard is not None and ball is not None and k == hazard.launch_tick:
            _launch(ball, robot, hazard, r0, robot.start_dir, bodies or {})
        if push is not None and k == push.tick:
            fwd = _facing_xy(robot, r0, robot.start_dir)
            c, s = math.cos(push.direction_rad), math.sin(push.direction_rad)
            towards = np.array([c * fwd[0] - s * fwd[1], s * fwd[0] + c * fwd[1]])
            force = (push.impulse_ns / PUSH_DURATION_S) * towards
            n_push = int(round(PUSH_DURATION_S * PHYSICS_HZ))
            push_steps = {k * STEPS_PER_TICK + i: (float(force[0]), float(force[1]), 0.0) for i in range(n_push)}
        walked_xy.append(robot.base_xy())
        run.joints.append(robot.joint_angles())
        if read_steps is not None and k * STEPS_PER_TICK in read_steps:
            run.step_angles[k * STEPS_PER_TICK] = run.joints[-1]
        h = robot.head_height_m()
        run.heights.append(h)
        if h < threshold_m and run.onset_tick is None:
            run.onset_tick = k
            run.touching_at_onset = dict(run.last_contact)
            run.end_xy = walked_xy[max(0, k - k0 - RATE_HZ)]
        if bodies is not None:
            for contact in pb.getContactPoints(bodyA=robot.body, physicsClientId=world.client):
                other = bodies.get(contact[2], "ball" if contact[2] == ball else "body")
                if other == "floor":
                    continue
                if other not in run.contacts:
                    run.contacts[other] = k
                    if run.first_contact_tick is None:
                        run.first_contact_tick, run.contact_with = k, other
                run.last_contact[other] = k
        if camera is not None:
            run.frames.append(encode_jpeg(camera.frame()))
            if watch is not None:
                run.in_view.append(camera.sees(watch))
        if stop_on_fall and run.onset_tick is not None:
            break
        step = (plan[k + 1] - plan[k]) / STEPS_PER_TICK
        for s in range(1, STEPS_PER_TICK + 1):
            target = plan[k] + s * step
            robot.command(target if feedback is None else np.clip(feedback.correct(k, target), robot.lo, robot.hi))
            force = push_steps.get(k * STEPS_PER_TICK + s - 1)
            if force is not None:
                pb.applyExternalForce(robot.body, robot.link_by_name[PUSH_LINK], force,
                                      pb.getLinkState(robot.body, robot.link_by_name[PUSH_LINK],
                                                      physicsClientId=world.client)[0],
                                      pb.WORLD_FRAME, physicsClientId=world.client)
            pb.stepSimulation(physicsClientId=world.client)
            if read_steps is not None and s < STEPS_PER_TICK and k * STEPS_PER_TICK + s in read_steps:
                run.step_angles[k * STEPS_PER_TICK + s] = robot.joint_angles()
    if run.end_xy is None:
        run.end_xy = robot.base_xy()
    return run


def joint_limits(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    info = [pb.getJointInfo(robot.body, j, physicsClientId=robot.client) for j in robot.joint_indices]
    return np.array([i[8] for i in info]), np.array([i[9] for i in info])


def _add_ball(client: int, hazard: Hazard) -> int:
    col = pb.createCollisionShape(pb.GEOM_SPHERE, radius=hazard.radius_m, physicsClientId=client)
    vis = pb.createVisualShape(pb.GEOM_SPHERE, radius=hazard.radius_m, rgbaColor=[*hazard.rgb, 1.0],
                               physicsClientId=client)
    return pb.createMultiBody(hazard.mass_kg, col, vis,
                              basePosition=(*HAZARD_PARK_XY, hazard.radius_m), physicsClientId=client)


def search_plan(rng: np.random.Generator, duration_s: float = DURATION_S, plan_id: str = "",
                family: str = "dynamic") -> KeptPlan:
    """Search a walking plan on a bare floor: the first proposed gait that stays up
    and walks unperturbed and survives VALIDATION_DRAWS knot perturbations at
    VALIDATION_SIGMA (each validation run stops at its first fall, and the
    candidate at its first failed run).

    FAMILY ``"dynamic"`` proposes ``GaitParams``; ``"hardware"`` proposes
    ``HardwareGaitParams`` (the real walk's step), run without the feedback
    and kept without a distance to walk (the real step is quasi-static).

    Every run goes through the balance feedback, as the episodes do. A kept
    plan walks MIN_PROGRESS_M or more in 10 s (the farthest ~0.6 m; the
    furniture stands 1 m or more ahead). The floor is the room's (same
    friction), so a plan kept here walks in any room and from any start pose:
    one search serves several episodes. The validation draws add a
    background of VALIDATION_BACKGROUND_SIGMA from the start to the paper's
    ramp at VALIDATION_SIGMA, so that the plan walks at low sigma from its
    first step.
    """
    n_ticks = int(round(duration_s * RATE_HZ))
    n_plan = n_ticks + PLAN_FUTURE_TICKS + 1
    n_knots = len(knot_ticks(n_plan))
    threshold = round(FALL_FRACTION * standing_head_height_m(), 4)
    min_progress_m = MIN_PROGRESS_M * min(1.0, max(0.0, duration_s - 2.0) / 8.0)
    world = World()
    try:
        world.add_floor()
        robot = Robot(world.client)
        robot.start_xy, robot.start_yaw = np.zeros(2), 0.0
        robot.start_dir = direction = np.array([0.0, -1.0])  # yaw 0 faces -y
        lo, hi = joint_limits(robot)
        initial_state = pb.saveState(physicsClientId=world.client)

        # The validation draws perturb the knots after VALIDATION_FROM_TICK only
        # (the start pose), so each draw starts from the unperturbed run's state
        # at that tick: the same simulation, without settling again.
        from_tick = min(VALIDATION_FROM_TICK, n_ticks - 1)
        still = knot_ticks(n_plan) <= from_tick

        def stays_up(candidate: np.ndarray, resume: tuple[int, int] | None = None,
                     save_at: int | None = None) -> tuple[bool, float, int | None]:
            if resume is None:
                pb.restoreState(initial_state, physicsClientId=world.client)
            run = _rollout(world, robot, candidate, n_ticks, threshold, True, None, save_at=save_at,
                           resume=resume, balance=feedback)
            return run.onset_tick is None, float(robot.base_xy() @ direction), run.saved

        params_class = FAMILIES[family]
        feedback = params_class.feedback
        if not params_class.walks:
            min_progress_m = -math.inf
        for attempts in range(1, MAX_PLAN_ATTEMPTS + 1):
            cand = params_class.propose(rng)
            cand_plan = plan_waypoints(cand, n_plan, RATE_HZ)
            ok, moved, saved = stays_up(cand_plan, save_at=from_tick)
            ok = ok and moved >= min_progress_m and saved is not None
            for _ in range(VALIDATION_DRAWS if ok else 0):
                eta = rng.normal(0.0, VALIDATION_SIGMA, (n_knots, len(JOINT_NAMES)))
                eta[still] = 0.0
                background = rng.normal(0.0, VALIDATION_BACKGROUND_SIGMA, (n_knots, len(JOINT_NAMES)))
                background[still] = 0.0
                plan = np.clip(cand_plan + knot_deviation(eta, VALIDATION_SIGMA, n_plan)
                               + smooth_knots(PERTURBATION_SCALE * background, n_plan), lo, hi)
                if not stays_up(plan, resume=(saved, from_tick))[0]:
                    ok = False
                    break
            if saved is not None:
                pb.removeState(saved, physicsClientId=world.client)
            if ok:
                return KeptPlan(cand, attempts, round(moved, 6), plan_id)
    finally:
        world.close()
    raise RuntimeError(f"plan {plan_id or '(unnamed)'}: no walking plan kept in {MAX_PLAN_ATTEMPTS} attempts")


def simulate_episode(seed: int, sigma: float | None = None, duration_s: float = DURATION_S,
                     render: bool = True, gait: bool = True, hazard: bool | None = None,
                     counterfactual_lead_ticks: int | None = None, counterfactual_draw: int = 1,
                     plan: KeptPlan | None = None, hazard_probability: float = HAZARD_PROBABILITY,
                     sigmas: tuple[float, ...] = SIGMAS, counterfactual_walking: bool = False,
                     push_probability: float | None = None, obstacle_probability: float | None = None,
                     push: bool | Push | None = None, obstacle: bool | Obstacle | None = None,
                     daemon_view: bool = True) -> Episode:
    """Simulate the episode of SEED. SIGMA None draws it from SIGMAS; 0 means unperturbed.

    A given SIGMA skips that draw, so the rest of the episode differs from the
    one SEED makes with its sigma drawn (as ``generate`` does): re-simulate a
    generated episode with SIGMA None (``stats.counterfactual``).

    PLAN is the kept walking plan the episode follows (``search_plan``; a data
    set shares one among several episodes); None searches one for this
    episode alone, from the episode's seed. GAIT False keeps the standing pose
    (for the standing test). HAZARD None draws whether a ball is rolled at the
    robot (HAZARD_PROBABILITY); True or False forces it.
    PUSH and OBSTACLE: None draws each (PUSH_PROBABILITY and OBSTACLE_PROBABILITY
    unless given, both 0 when HAZARD_PROBABILITY is 0: ``outside_cause_probabilities``;
    from random streams of their own, so forcing either changes nothing else);
    True or False forces it; a ``Push`` or an ``Obstacle`` forces that one.
    DAEMON_VIEW: record the joints as the servo buses deliver them and the camera
    with its drops and freezes (``sensors``); False: every tick's joints and frame.
    COUNTERFACTUAL_LEAD_TICKS: when the episode falls, run it again with the
    perturbation knots from onset - lead on redrawn (draw COUNTERFACTUAL_DRAW)
    and record that run's onset. The knots are redrawn from their own
    distribution (an event's knots at the event's sigma), or with
    COUNTERFACTUAL_WALKING from the background's (the event taken out there).
    """
    rng = np.random.default_rng(seed)
    if sigma is None:
        sigma = float(sigmas[rng.integers(len(sigmas))])
    n_ticks = int(round(duration_s * RATE_HZ))
    n_plan = n_ticks + PLAN_FUTURE_TICKS + 1
    n_knots = len(knot_ticks(n_plan))
    standing = standing_head_height_m()
    threshold = round(FALL_FRACTION * standing, 4)
    # Drawn before anything else, so that forcing it leaves the rest of the episode as it was.
    hazard_drawn = bool(rng.uniform() < hazard_probability)
    with_hazard = hazard_drawn if hazard is None else hazard
    defaults = outside_cause_probabilities(hazard_probability)
    push_probability = defaults["push_probability"] if push_probability is None else push_probability
    obstacle_probability = (defaults["obstacle_probability"] if obstacle_probability is None
                            else obstacle_probability)
    push_rng = np.random.default_rng([seed, PUSH_STREAM])
    push_drawn = bool(push_rng.uniform() < push_probability)
    the_push = Push.sample(push_rng, n_ticks) if (push_drawn if push is None else push) else None
    if isinstance(push, Push):
        the_push = push
    obstacle_rng = np.random.default_rng([seed, OBSTACLE_STREAM])
    obstacle_drawn = bool(obstacle_rng.uniform() < obstacle_probability)
    the_obstacle = Obstacle.sample(obstacle_rng) if (obstacle_drawn if obstacle is None else obstacle) else None
    if isinstance(obstacle, Obstacle):
        the_obstacle = obstacle
    if gait and plan is None:
        plan = search_plan(np.random.default_rng([seed, PLAN_STREAM]), duration_s)
    if plan is not None and gait:
        params, attempts, progress = plan.params, plan.attempts, plan.progress_m
        base_plan = plan_waypoints(params, n_plan, RATE_HZ)
    else:
        params, attempts, progress = None, 0, 0.0
        base_plan = np.tile(standing_pose(), (n_plan, 1))
    world = World()
    try:
        yaw = float(rng.uniform(-math.pi, math.pi))
        start_xy = rng.uniform(-0.6, 0.6, 2)
        heading = yaw - math.pi / 2  # yaw 0 faces -y
        scene, bodies = build_room(world.client, rng, start_xy, heading)
        # Always drawn, so that HAZARD True or False changes nothing else in the episode.
        haz_drawn = Hazard.sample(rng, n_ticks)
        haz = haz_drawn if with_hazard else None
        ball = _add_ball(world.client, haz) if haz is not None else None
        robot = Robot(world.client)
        direction = np.array([math.cos(heading), math.sin(heading)])
        robot.start_xy, robot.start_yaw, robot.start_dir = start_xy, yaw, direction
        camera = HeadCamera(robot) if render else None
        lo, hi = joint_limits(robot)
        if the_obstacle is not None:
            bodies[the_obstacle.add(world.client, start_xy, direction)] = "obstacle"
        initial_state = pb.saveState(physicsClientId=world.client)

        def perturbed(eta: np.ndarray) -> np.ndarray:
            return np.clip(base_plan + smooth_knots(PERTURBATION_SCALE * eta, n_plan), lo, hi)

        unit_eta = rng.normal(0.0, 1.0, (n_knots, len(JOINT_NAMES)))
        if sigma > BACKGROUND_SIGMA_MAX:
            background = float(BACKGROUND_SIGMAS[rng.integers(len(BACKGROUND_SIGMAS))])
            event_knot = int(rng.choice(event_knot_range(n_plan, n_ticks)))
        else:
            background, event_knot = sigma, None
        amp = knot_sigmas(sigma, background, event_knot, n_knots)
        knot_eta = unit_eta * amp[:, None]
        final = perturbed(knot_eta)
        full_plan = np.vstack([np.tile(final[0], (PLAN_PAST_TICKS, 1)), final])
        event_tick = int(knot_ticks(n_plan)[event_knot - 1]) if event_knot is not None else None

        reads = draw_reads(seed, n_ticks, RATE_HZ) if daemon_view else None
        pb.restoreState(initial_state, physicsClientId=world.client)
        feedback = params.feedback if params is not None else True
        run = _rollout(world, robot, final, n_ticks, threshold, False, camera, bodies, haz, ball, push=the_push,
                       balance=feedback,
                       read_steps=reads.physics_steps() if reads is not None else None,
                       watch=the_obstacle.surface if the_obstacle is not None else None)
        if sigma == 0:
            progress = float((robot.base_xy() - start_xy) @ direction)
        distance = float(np.linalg.norm(run.end_xy - start_xy))
        onset = run.onset_tick
        cf_onset, cf_from = None, None
        if counterfactual_lead_ticks is not None and onset is not None:
            cf_from = max(0, onset - counterfactual_lead_ticks)
            redraw = knot_ticks(n_plan) >= cf_from
            cf_eta = knot_eta.copy()
            cf_rng = np.random.default_rng([seed, 2, counterfactual_draw])
            cf_eta[redraw] = cf_rng.normal(0.0, 1.0, (int(redraw.sum()), len(JOINT_NAMES))) * (background if counterfactual_walking else amp[redraw, None])
            pb.restoreState(initial_state, physicsClientId=world.client)
            cf_run = _rollout(world, robot, perturbed(cf_eta), n_ticks, threshold, True, None,
                              bodies, haz, ball, push=the_push, balance=feedback)
            cf_onset = cf_run.onset_tick
    finally:
        world.close()
    heights = np.array(run.heights)
    fallen = np.maximum.accumulate(heights < threshold)
    joint_messages = camera_sent = sensors = None
    if daemon_view:
        joint_messages = reads.messages(run.step_angles, run.joints[0])
        camera_sent = draw_camera(seed, n_ticks) if render else None
        sensors = {"joint_read_hz": READ_HZ, "miss_probability": MISS_PROBABILITY,
                   "retry_probability": RETRY_PROBABILITY, **reads.summary()}
        if camera_sent is not None:
            sensors.update({"frame_drop_probability": FRAME_DROP_PROBABILITY,
                            "freeze_start_probability": FREEZE_START_PROBABILITY, **camera_summary(camera_sent)})
    return Episode(seed=seed, sigma=sigma, params=params, n_ticks=n_ticks, joints_rad=np.array(run.joints),
                   plan_rad=full_plan, head_height_m=heights, fallen=fallen, jpeg_frames=run.frames,
                   standing_head_height_m=standing, scene=scene, plan_attempts=attempts,
                   progress_m=progress, hazard=haz, first_contact_tick=run.first_contact_tick,
                   contact_with=run.contact_with, distance_m=distance,
                   counterfactual_onset_tick=cf_onset, counterfactual_from_tick=cf_from,
                   plan_id=plan.plan_id if plan is not None else "", background_sigma=background,
                   event_tick=event_tick, push=the_push, obstacle=the_obstacle, contacts=dict(run.contacts),
                   touching_at_onset=dict(run.touching_at_onset),
                   joint_messages=joint_messages, camera_sent=camera_sent, sensors=sensors,
                   obstacle_in_view=run.in_view if the_obstacle is not None and render else None)


__all__ = ["Episode", "Hazard", "Push", "Obstacle", "KeptPlan", "search_plan", "simulate_episode", "stamp_ns", "perturbation_factor",
           "knot_deviation", "smooth_knots", "knot_sigmas", "SIGMAS", "RATE_HZ", "JOINT_NAMES", "GENERATOR_VERSION"]
