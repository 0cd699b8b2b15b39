"""The room the robot walks in: floor, four textured walls, ceiling, furniture.

Data enters as a numpy random generator and the robot's start pose and heading;
it leaves as bodies in a pybullet client. Wallpapers are a fixed bank of 28
generated textures (``wallpaper_bank``), written once as PNG files to a cache
folder (pybullet loads textures from files). Walls and ceiling are UV-mapped
quads (an OBJ written next to the textures). Furniture is built from boxes and
cylinders (table, chair, bookshelf, cabinet, sofa, lamp, plant, crate), six
pieces per episode, placed at random in front of the robot inside the head
camera's field of view.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pybullet as pb
from PIL import Image

N_WALLPAPERS = 28
WALLPAPER_BANK_SEED = 20260328
WALLPAPER_PX = 128
ROOM_HALF_M = 3.0
ROOM_HEIGHT_M = 2.4
N_FURNITURE = 6
#: Furniture bearing from the robot's heading stays within this (camera FOV is 60 deg).
FURNITURE_MAX_BEARING_RAD = math.radians(20)
FURNITURE_DIST_M = (1.0, 2.4)
#: Friction of the floor (and of the bare floor plans are searched on).
FLOOR_FRICTION = 0.9

_ASSET_VERSION = "v1"


def asset_dir() -> Path:
    """Cache folder of generated wallpapers and the quad mesh (FALL_GUARD_SIM_ASSETS overrides)."""
    env = os.environ.get("FALL_GUARD_SIM_ASSETS")
    base = Path(env) if env else Path(tempfile.gettempdir()) / f"fall_guard_sim_assets_{os.getuid()}"
    return base / _ASSET_VERSION


def _wallpaper(i: int) -> np.ndarray:
    """Wallpaper I of the bank: an HxWx3 uint8 pattern (stripes, checks, dots, waves, plain)."""
    rng = np.random.default_rng([WALLPAPER_BANK_SEED, i])
    n = WALLPAPER_PX
    y, x = np.mgrid[0:n, 0:n] / n
    c1 = rng.uniform(0.25, 0.95, 3)
    c2 = np.clip(c1 + rng.uniform(-0.4, 0.4, 3), 0, 1)
    kind = i % 7
    freq = rng.integers(3, 10)
    if kind == 0:
        mask = (np.floor(x * freq) % 2) == 0
    elif kind == 1:
        mask = (np.floor(y * freq) % 2) == 0
    elif kind == 2:
        mask = ((np.floor(x * freq) + np.floor(y * freq)) % 2) == 0
    elif kind == 3:
        mask = ((x * freq % 1 - 0.5) ** 2 + (y * freq % 1 - 0.5) ** 2) < 0.08
    elif kind == 4:
        mask = np.sin(2 * np.pi * (x * freq + 0.3 * np.sin(2 * np.pi * y * 2))) > 0
    elif kind == 5:
        mask = (np.floor((x + y) * freq) % 2) == 0
    else:
        mask = rng.uniform(size=(n, n)) < 0.15
    img = np.where(mask[..., None], c1, c2)
    img *= 1 - 0.08 * rng.uniform(size=(n, n, 1))  # paper grain
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


_QUAD_OBJ = """# unit quad in the x-z plane, facing -y and +y, UV 0..1
v -0.5 0 -0.5
v 0.5 0 -0.5
v 0.5 0 0.5
v -0.5 0 0.5
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 -1 0
vn 0 1 0
f 1/1/1 2/2/1 3/3/1
f 1/1/1 3/3/1 4/4/1
f 3/3/2 2/2/2 1/1/2
f 4/4/2 3/3/2 1/1/2
"""


def ensure_assets() -> Path:
    """Write the wallpaper PNGs and the quad mesh once; return their folder."""
    d = asset_dir()
    done = d / "complete"
    if done.exists():
        return d
    d.mkdir(parents=True, exist_ok=True)
    for i in range(N_WALLPAPERS):
        tmp = d / f"wallpaper_{i:02d}.png.{os.getpid()}"
        Image.fromarray(_wallpaper(i)).save(tmp, format="PNG")
        os.replace(tmp, d / f"wallpaper_{i:02d}.png")
    tmp = d / f"quad.obj.{os.getpid()}"
    tmp.write_text(_QUAD_OBJ)
    os.replace(tmp, d / "quad.obj")
    done.write_text("ok\n")
    return d


def _quad(client: int, assets: Path, centre, yaw_rad: float, width_m: float, height_m: float,
          roll_rad: float = 0.0, texture: int | None = None, rgba=(1, 1, 1, 1)) -> int:
    vis = pb.createVisualShape(pb.GEOM_MESH, fileName=str(assets / "quad.obj"),
                               meshScale=[width_m, 1, height_m], rgbaColor=rgba, physicsClientId=client)
    col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[width_m / 2, 0.01, height_m / 2],
                                  physicsClientId=client)
    body = pb.createMultiBody(0, col, vis, basePosition=centre,
                              baseOrientation=pb.getQuaternionFromEuler((roll_rad, 0, yaw_rad)),
                              physicsClientId=client)
    if texture is not None:
        pb.changeVisualShape(body, -1, textureUniqueId=texture, physicsClientId=client)
    return body


# Furniture: lists of (shape, half extents or (radius, length), centre xyz, colour key).
def _furniture_parts(kind: str, rng: np.random.Generator):
    s = rng.uniform(0.85, 1.15)
    if kind == "table":
        w, d, h = 0.9 * s, 0.6 * s, 0.72 * s
        parts = [("box", (w / 2, d / 2, 0.02), (0, 0, h - 0.02), 0)]
        parts += [("box", (0.025, 0.025, (h - 0.04) / 2), (sx * (w / 2 - 0.05), sy * (d / 2 - 0.05), (h - 0.04) / 2), 1)
                  for sx in (-1, 1) for sy in (-1, 1)]
    elif kind == "chair":
        w, h = 0.45 * s, 0.45 * s
        parts = [("box", (w / 2, w / 2, 0.025), (0, 0, h), 0),
                 ("box", (w / 2, 0.025, 0.22 * s), (0, w / 2, h + 0.22 * s), 0)]
        parts += [("box", (0.02, 0.02, h / 2), (sx * (w / 2 - 0.03), sy * (w / 2 - 0.03), h / 2), 1)
                  for sx in (-1, 1) for sy in (-1, 1)]
    elif kind == "bookshelf":
        w, d, h = 0.8 * s, 0.3, 1.6 * s
        parts = [("box", (0.02, d / 2, h / 2), (sx * w / 2, 0, h / 2), 0) for sx in (-1, 1)]
        parts += [("box", (w / 2, d / 2, 0.015), (0, 0, z), 0) for z in np.linspace(0.02, h, 5)]
        parts += [("box", (w / 2 - 0.03, d / 2 - 0.03, 0.1), (0, 0, z + 0.11), 2) for z in np.linspace(0.02, h, 5)[:-1]]
    elif kind == "cabinet":
        w, d, h = 0.6 * s, 0.45, 0.85 * s
        parts = [("box", (w / 2, d / 2, h / 2), (0, 0, h / 2), 0),
                 ("box", (0.1, 0.01, 0.015), (0, -d / 2 - 0.01, h * 0.8), 1),
                 ("box", (0.1, 0.01, 0.015), (0, -d / 2 - 0.01, h * 0.45), 1)]
    elif kind == "sofa":
        w, d = 1.6 * s, 0.8
        parts = [("box", (w / 2, d / 2, 0.2), (0, 0, 0.2), 0),
                 ("box", (w / 2, 0.1, 0.25), (0, d / 2 - 0.1, 0.6), 0),
                 ("box", (0.1, d / 2, 0.15), (-w / 2 + 0.1, 0, 0.5), 1),
                 ("box", (0.1, d / 2, 0.15), (w / 2 - 0.1, 0, 0.5), 1)]
    elif kind == "lamp":
        h = 1.5 * s
        parts = [("cyl", (0.15, 0.03), (0, 0, 0.015), 1), ("cyl", (0.015, h), (0, 0, h / 2), 1),
                 ("cyl", (0.2, 0.25), (0, 0, h), 0)]
    elif kind == "plant":
        parts = [("cyl", (0.15 * s, 0.35 * s), (0, 0, 0.175 * s), 1),
                 ("sphere", (0.3 * s,), (0, 0, 0.35 * s + 0.25 * s), 3)]
    else:  # crate stack
        parts = [("box", (0.25, 0.25, 0.25), (0, 0, 0.25), 0),
                 ("box", (0.2, 0.2, 0.2), (0.05, 0.02, 0.7), 1)]
    return parts


FURNITURE_KINDS = ("table", "chair", "bookshelf", "cabinet", "sofa", "lamp", "plant", "crate")


def _add_furniture(client: int, kind: str, xy, yaw_rad: float, rng: np.random.Generator) -> int:
    base = rng.uniform(0.15, 0.8, 3)
    colours = [np.append(base, 1), np.append(base * 0.6, 1), np.append(rng.uniform(0.2, 0.9, 3), 1),
               np.array([0.2, 0.6, 0.25, 1])]
    parts = _furniture_parts(kind, rng)
    types, radii, halfs, lengths, frames, rgbas = [], [], [], [], [], []
    for shape, dims, centre, colour in parts:
        # (pybullet type, radius, half extents, length) of each primitive.
        if shape == "box":
            row = (pb.GEOM_BOX, 0, dims, 0)
        elif shape == "cyl":
            row = (pb.GEOM_CYLINDER, dims[0], (0, 0, 0), dims[1])
        else:
            row = (pb.GEOM_SPHERE, dims[0], (0, 0, 0), 0)
        types.append(row[0])
        radii.append(row[1])
        halfs.append(row[2])
        lengths.append(row[3])
        frames.append(centre)
        rgbas.append(colours[colour].tolist())
    vis = pb.createVisualShapeArray(types, radii=radii, halfExtents=halfs, lengths=lengths,
                                    visualFramePositions=frames, rgbaColors=rgbas, physicsClientId=client)
    col = pb.createCollisionShapeArray(types, radii=radii, halfExtents=halfs, lengths=lengths,
                                       collisionFramePositions=frames, physicsClientId=client)
    return pb.createMultiBody(0, col, vis, basePosition=(xy[0], xy[1], 0),
                              baseOrientation=pb.getQuaternionFromEuler((0, 0, yaw_rad)),
                              physicsClientId=client)


def build_room(client: int, rng: np.random.Generator, robot_xy, heading_rad: float) -> tuple[dict, dict[int, str]]:
    """Floor, walls, ceiling and six furniture pieces; returns what was chosen and the body names.

    HEADING_RAD is the robot's walking direction in the world (0 = +x). The
    names ({body id: "floor" | "wall" | "ceiling" | furniture kind}) let a
    rollout say what the robot touched.
    """
    assets = ensure_assets()
    plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=client)
    floor_vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[ROOM_HALF_M, ROOM_HALF_M, 0.001],
                                     rgbaColor=np.append(rng.uniform(0.3, 0.7, 3), 1).tolist(),
                                     physicsClientId=client)
    floor = pb.createMultiBody(0, plane, floor_vis, basePosition=(0, 0, 0), physicsClientId=client)
    pb.changeDynamics(floor, -1, lateralFriction=FLOOR_FRICTION, physicsClientId=client)
    papers = [int(i) for i in rng.integers(0, N_WALLPAPERS, 4)]
    textures = [pb.loadTexture(str(assets / f"wallpaper_{i:02d}.png"), physicsClientId=client) for i in papers]
    r, h = ROOM_HALF_M, ROOM_HEIGHT_M
    walls = [((0, r, h / 2), 0.0), ((0, -r, h / 2), 0.0), ((r, 0, h / 2), math.pi / 2), ((-r, 0, h / 2), math.pi / 2)]
    bodies = {floor: "floor"}
    for (centre, yaw), tex in zip(walls, textures):
        bodies[_quad(client, assets, centre, yaw, 2 * r, h, texture=tex)] = "wall"
    ceiling = _quad(client, assets, (0, 0, h), 0.0, 2 * r, 2 * r, roll_rad=math.pi / 2,
                    rgba=np.append(rng.uniform(0.75, 0.95, 3), 1).tolist())
    bodies[ceiling] = "ceiling"
    kinds = [str(k) for k in rng.choice(FURNITURE_KINDS, N_FURNITURE, replace=True)]
    placed: list[tuple[float, float]] = []
    for kind in kinds:
        for _ in range(50):
            dist = rng.uniform(*FURNITURE_DIST_M)
            bearing = heading_rad + rng.uniform(-FURNITURE_MAX_BEARING_RAD, FURNITURE_MAX_BEARING_RAD)
            xy = (robot_xy[0] + dist * math.cos(bearing), robot_xy[1] + dist * math.sin(bearing))
            inside = max(abs(xy[0]), abs(xy[1])) < r - 0.5
            if inside and all(math.dist(xy, q) > 0.55 for q in placed):
                break
        placed.append(xy)
        # Face the robot (the furniture's front is its -y side).
        face = math.atan2(robot_xy[1] - xy[1], robot_xy[0] - xy[0]) + math.pi / 2
        bodies[_add_furniture(client, kind, xy, face + rng.uniform(-0.4, 0.4), rng)] = kind
    return {"wallpapers": papers, "furniture": kinds, "furniture_xy": placed}, bodies
