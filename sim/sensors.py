"""What the daemon reads on the robot, simulated: the servo buses' joint reads and the camera's hiccups.

Data enters as an episode seed and length (everything is drawn from the
random stream ``[seed, SENSOR_STREAM]``, apart from the episode's own, so the
physics does not change with it) and the joint angles the physics had at the
240 Hz steps the reads fall on; it leaves as the ``/joint_states`` messages
and the camera frames the recording holds, in the recording format already
used (docs/contracts.md), as the daemon would see them on the robot
(docs/daemon.md, "Validity"):

- **Joints at the buses' 50 Hz cycle**, not at the 30 Hz tick. A cycle
  starts every 20 ms (plus up to 2 ms late); the lower bus (the legs) is
  read at its start and the upper bus (trunk, head, arms) 5-9 ms later, so
  the joints of one message were not read at one time; a motor whose reply
  was faulted and asked again (``RETRY_PROBABILITY``) is read 2-6 ms after
  its bus. Each joint's value is the simulated angle at the physics step of
  its own read. One message per cycle, all 25 joints, stamped with its newest
  read (no value in it was read later).
- **A reply missed now and then** (``MISS_PROBABILITY`` per motor and cycle,
  after the retry): the joint keeps the value of its last read, as the
  daemon holds a motor that did not answer (a JointState in a recording
  carries every joint, so the held value is written).
- **Camera frames dropped or frozen now and then**: a tick's frame is not
  published (``FRAME_DROP_PROBABILITY``), or the camera freezes
  (``FREEZE_START_PROBABILITY`` a tick) and sends its last image again for
  3-15 ticks with new stamps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .robot import JOINT_NAMES, PHYSICS_HZ

SENSOR_STREAM = 47
READ_HZ = 50
CYCLE_NS = 1_000_000_000 // READ_HZ
CYCLE_LATE_NS = (0, 2_000_000)
#: The lower bus: the legs (Dynamixel ids 11-25); the upper: the rest.
LOWER_BUS = tuple(range(10))
UPPER_BUS = tuple(range(10, len(JOINT_NAMES)))
UPPER_AFTER_NS = (5_000_000, 9_000_000)
RETRY_PROBABILITY = 0.1
RETRY_AFTER_NS = (2_000_000, 6_000_000)
MISS_PROBABILITY = 0.015
FRAME_DROP_PROBABILITY = 0.01
FREEZE_START_PROBABILITY = 0.003
FREEZE_TICKS = (3, 15)


@dataclass
class Reads:
    """The joint reads of one episode: per cycle, each joint's read time (ns) or a miss."""
    read_ns: np.ndarray       # [cycles, 25] int64; -1 where the reply was missed
    retried: np.ndarray       # [cycles, 25] bool

    @property
    def missed(self) -> np.ndarray:
        return self.read_ns < 0

    def physics_steps(self) -> set[int]:
        """The 240 Hz steps whose state the reads take (the last step at or before each read)."""
        ns = self.read_ns[self.read_ns >= 0]
        return set((ns * PHYSICS_HZ // 1_000_000_000).tolist())

    def messages(self, angles_at_step: dict[int, np.ndarray], start: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """(stamp ns, positions [25] rad) of every cycle: each joint at its read, or held when missed
        (before its first read: START, the pose at tick 0)."""
        held = np.array(start, dtype=float)
        out = []
        for c in range(self.read_ns.shape[0]):
            ns = self.read_ns[c]
            for j in np.flatnonzero(ns >= 0):
                held[j] = angles_at_step[int(ns[j]) * PHYSICS_HZ // 1_000_000_000][j]
            out.append((int(ns.max()) if (ns >= 0).any() else int(c * CYCLE_NS), held.copy()))
        return out

    def summary(self) -> dict:
        return {"cycles": int(self.read_ns.shape[0]), "missed": int(self.missed.sum()),
                "retried": int(self.retried.sum())}


def draw_reads(seed: int, n_ticks: int, rate_hz: int) -> Reads:
    """The reads of an episode of N_TICKS at RATE_HZ: cycles from 0 to the last tick's time."""
    rng = np.random.default_rng([seed, SENSOR_STREAM, 1])
    end_ns = (n_ticks - 1) * 1_000_000_000 // rate_hz
    n = len(JOINT_NAMES)
    starts = np.arange(0, end_ns + 1, CYCLE_NS, dtype=np.int64)
    starts = starts + rng.integers(*CYCLE_LATE_NS, size=len(starts))
    upper = starts + rng.integers(*UPPER_AFTER_NS, size=len(starts))
    read = np.empty((len(starts), n), dtype=np.int64)
    read[:, list(LOWER_BUS)] = starts[:, None]
    read[:, list(UPPER_BUS)] = upper[:, None]
    retried = rng.uniform(size=read.shape) < RETRY_PROBABILITY
    read = read + np.where(retried, rng.integers(*RETRY_AFTER_NS, size=read.shape), 0)
    missed = rng.uniform(size=read.shape) < MISS_PROBABILITY
    read = np.minimum(read, end_ns)
    read[missed] = -1
    # Keep the cycles whose reads lie inside the episode (the first one always: tick 0's pose).
    return Reads(read_ns=read, retried=retried & ~missed)


def draw_camera(seed: int, n_ticks: int) -> list[int]:
    """Per tick, the frame the camera sends: its own index, an earlier one (frozen), or -1 (dropped)."""
    rng = np.random.default_rng([seed, SENSOR_STREAM, 2])
    sent: list[int] = []
    frozen_until, frozen_at = -1, -1
    for k in range(n_ticks):
        drop, freeze, length = rng.uniform(), rng.uniform(), int(rng.integers(FREEZE_TICKS[0], FREEZE_TICKS[1] + 1))
        if k <= frozen_until:
            sent.append(frozen_at)
            continue
        if k > 0 and freeze < FREEZE_START_PROBABILITY:
            frozen_at = next((f for f in reversed(sent) if f >= 0), 0)
            frozen_until = k + length - 1
            sent.append(frozen_at)
            continue
        sent.append(-1 if drop < FRAME_DROP_PROBABILITY else k)
    return sent


def camera_summary(sent: list[int]) -> dict:
    return {"frames_dropped": sum(s < 0 for s in sent),
            "frames_frozen": sum(0 <= s != k for k, s in enumerate(sent))}
