"""One simulated episode: plan search, perturbation, physics, camera and labels.

Data enters as an episode seed (everything else is drawn from it) and leaves as
an ``Episode``: per 30 Hz tick the measured joint angles (rad, pypot convention,
model order), a JPEG head-camera frame, the head height and the sticky fallen
label, plus the perturbed plan (one waypoint per tick, including 2.5 s before
the start and 3 s past the end) and the metadata. ``recording.write_episode``
turns it into an MCAP file.

Time: physics runs at 240 Hz (8 steps per tick). Waypoint k applies at tick k;
between waypoints the command is interpolated linearly at each physics step.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field

import numpy as np
import pybullet as pb
from PIL import Image

from .gait import GaitParams, gait_waypoints, standing_pose
from .robot import FALL_FRACTION, JOINT_NAMES, PHYSICS_HZ, ROBOT_NAME, Robot
from .scene import build_room

RATE_HZ = 30
STEPS_PER_TICK = PHYSICS_HZ // RATE_HZ
DURATION_S = 10.0
FRAME_PX = 64
PLAN_PERIOD_TICKS = RATE_HZ           # a plan message every 1 s
PLAN_PAST_TICKS = 75                   # each plan covers [now - 2.5 s, now + 3 s]
PLAN_FUTURE_TICKS = 90
SETTLE_STEPS = 60                      # physics steps holding the first pose before tick 0
SIGMAS = (0.005, 0.010, 0.035, 0.040)
RAMP_A = 90.0
RAMP_B = 0.125
MAX_PLAN_ATTEMPTS = 60
MIN_PROGRESS_M = 0.04                  # a kept 10 s plan walks at least this far along its heading
CAMERA_FOV_DEG = 60.0
CAMERA_PITCH_DOWN_DEG = 10.0           # camera axis below the head's forward direction
JPEG_QUALITY = 90


def stamp_ns(tick: int) -> int:
    """Episode time of TICK in ns (floor of tick / 30 s); tick 0 is 0 ns."""
    return tick * 1_000_000_000 // RATE_HZ


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
class Episode:
    seed: int
    sigma: float
    params: GaitParams | None
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

    @property
    def fall_threshold_m(self) -> float:
        return round(FALL_FRACTION * self.standing_head_height_m, 4)

    @property
    def fall_onset_tick(self) -> int | None:
        idx = np.flatnonzero(self.fallen)
        return int(idx[0]) if idx.size else None

    def plan_message_points(self, tick: int) -> tuple[int, np.ndarray]:
        """(first tick, waypoints) of the plan published at TICK: ticks tick-75 .. tick+90."""
        first = tick - PLAN_PAST_TICKS
        lo = first + PLAN_PAST_TICKS
        return first, self.plan_rad[lo:lo + PLAN_PAST_TICKS + PLAN_FUTURE_TICKS + 1]

    def metadata(self) -> dict[str, str]:
        meta = {
            "source": "sim",
            "robot": ROBOT_NAME,
            "rate_hz": str(RATE_HZ),
            "seed": str(self.seed),
            "sigma": f"{self.sigma:g}",
            "standing_head_height_m": f"{self.standing_head_height_m:.4f}",
            "fall_threshold_m": f"{self.fall_threshold_m:.4f}",
            "duration_s": f"{self.n_ticks / RATE_HZ:g}",
            "physics_hz": str(PHYSICS_HZ),
            "perturbation": (f"factor*eta per waypoint and joint, eta~N(0,sigma^2); factor=1 if sigma<=0.01 "
                             f"else 1.5/(1+exp({RAMP_A:g}-{RAMP_B:g}*rho)), rho=240 Hz physics steps since tick 0"),
            "gait": json.dumps(self.params.as_dict() if self.params else None, sort_keys=True),
            "plan_attempts": str(self.plan_attempts),
            "progress_m": f"{self.progress_m:.3f}",
            "scene": json.dumps(self.scene, sort_keys=True),
        }
        onset = self.fall_onset_tick
        if onset is not None:
            meta["fall_onset_ns"] = str(stamp_ns(onset))
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
        view = pb.computeViewMatrix(eye.tolist(), (eye + r @ self.fwd_local).tolist(), (r @ self.up_local).tolist())
        _, _, rgba, _, _ = pb.getCameraImage(
            FRAME_PX, FRAME_PX, view, self.projection, renderer=pb.ER_TINY_RENDERER, shadow=0,
            lightDirection=[0.4, -0.6, 1.0], flags=pb.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self.robot.client)
        return np.asarray(rgba, dtype=np.uint8).reshape(FRAME_PX, FRAME_PX, 4)[:, :, :3]


def encode_jpeg(rgb: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=JPEG_QUALITY)
    return buf.getvalue()


def _rollout(world: World, robot: Robot, plan: np.ndarray, n_ticks: int, threshold_m: float,
             stop_on_fall: bool, camera: HeadCamera | None):
    """Run PLAN (waypoints from tick 0) for N_TICKS; returns per-tick measurements."""
    robot.place(plan[0], robot.start_xy, robot.start_yaw)
    for _ in range(SETTLE_STEPS):
        robot.command(plan[0])
        pb.stepSimulation(physicsClientId=world.client)
    joints, heights, frames = [], [], []
    for k in range(n_ticks):
        joints.append(robot.joint_angles())
        h = robot.head_height_m()
        heights.append(h)
        if camera is not None:
            frames.append(encode_jpeg(camera.frame()))
        if stop_on_fall and h < threshold_m:
            break
        for s in range(1, STEPS_PER_TICK + 1):
            a = s / STEPS_PER_TICK
            robot.command((1 - a) * plan[k] + a * plan[k + 1])
            pb.stepSimulation(physicsClientId=world.client)
    return np.array(joints), np.array(heights), frames


def joint_limits(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    info = [pb.getJointInfo(robot.body, j, physicsClientId=robot.client) for j in robot.joint_indices]
    return np.array([i[8] for i in info]), np.array([i[9] for i in info])


def simulate_episode(seed: int, sigma: float | None = None, duration_s: float = DURATION_S,
                     render: bool = True, gait: bool = True) -> Episode:
    """Simulate the episode of SEED. SIGMA None draws it from SIGMAS; 0 means unperturbed.

    GAIT False keeps the standing pose (for the standing test).
    """
    rng = np.random.default_rng(seed)
    if sigma is None:
        sigma = float(SIGMAS[rng.integers(len(SIGMAS))])
    n_ticks = int(round(duration_s * RATE_HZ))
    n_plan = n_ticks + PLAN_FUTURE_TICKS + 1
    standing = standing_head_height_m()
    threshold = round(FALL_FRACTION * standing, 4)
    world = World()
    try:
        yaw = float(rng.uniform(-math.pi, math.pi))
        start_xy = rng.uniform(-0.6, 0.6, 2)
        heading = yaw - math.pi / 2  # yaw 0 faces -y
        scene = build_room(world.client, rng, start_xy, heading)
        robot = Robot(world.client)
        robot.start_xy, robot.start_yaw = start_xy, yaw
        camera = HeadCamera(robot) if render else None
        lo, hi = joint_limits(robot)
        initial_state = pb.saveState(physicsClientId=world.client)
        direction = np.array([math.cos(heading), math.sin(heading)])
        # Progress asked of a kept plan: MIN_PROGRESS_M over 10 s, pro rata after the 2 s start-up.
        min_progress_m = MIN_PROGRESS_M * min(1.0, max(0.0, duration_s - 2.0) / 8.0)

        # Plan search: sample gait parameters, keep the first plan that, run
        # without perturbation in this very room, stays up and walks forward.
        params, plan, attempts, progress = None, np.tile(standing_pose(), (n_plan, 1)), 0, 0.0
        if gait:
            for attempts in range(1, MAX_PLAN_ATTEMPTS + 1):  # noqa: B007 (read after the loop)
                cand = GaitParams.sample(rng)
                cand_plan = gait_waypoints(cand, n_plan, RATE_HZ)
                pb.restoreState(initial_state, physicsClientId=world.client)
                _, heights, _ = _rollout(world, robot, cand_plan, n_ticks, threshold, True, None)
                moved = float((robot.base_xy() - start_xy) @ direction)
                if len(heights) == n_ticks and heights.min() >= threshold and moved >= min_progress_m:
                    params, plan, progress = cand, cand_plan, moved
                    break
            else:
                raise RuntimeError(f"episode seed {seed}: no walking plan kept in {MAX_PLAN_ATTEMPTS} attempts")

        # Perturbation per waypoint and joint (i.i.d., not cumulative).
        rho = np.arange(n_plan) * STEPS_PER_TICK
        eta = rng.normal(0.0, 1.0, plan.shape) * sigma
        perturbed = np.clip(plan + perturbation_factor(sigma, rho)[:, None] * eta, lo, hi)
        full_plan = np.vstack([np.tile(perturbed[0], (PLAN_PAST_TICKS, 1)), perturbed])

        pb.restoreState(initial_state, physicsClientId=world.client)
        joints, heights, frames = _rollout(world, robot, perturbed, n_ticks, threshold, False, camera)
        if sigma == 0:
            progress = float((robot.base_xy() - start_xy) @ direction)
    finally:
        world.close()
    fallen = np.maximum.accumulate(heights < threshold)
    return Episode(seed=seed, sigma=sigma, params=params, n_ticks=n_ticks, joints_rad=joints,
                   plan_rad=full_plan, head_height_m=heights, fallen=fallen, jpeg_frames=frames,
                   standing_head_height_m=standing, scene=scene, plan_attempts=attempts,
                   progress_m=progress)


__all__ = ["Episode", "simulate_episode", "stamp_ns", "perturbation_factor", "SIGMAS", "RATE_HZ",
           "JOINT_NAMES"]
