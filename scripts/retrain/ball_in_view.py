#!/usr/bin/env python3
"""How long the head camera sees the ball before a collision fall.

    ball_in_view.py SET [SPLIT...]     (default: validation test)

For every fall of those splits caused by the ball (`fall_cause` "collision" with the ball
launched and, where the recording lists what the robot touched, `contacts_ns`, the ball among
it: generator 6's collisions are with furniture too), counts the frames from the ball's launch
to the fall onset in which it is seen: at least MIN_PIXELS pixels
of the ball's colour (its `hazard.rgb`, compared as chromaticity so that shading does not
matter, and at least 60% of its brightness) more than in the frame 10 ticks before the launch.
Prints one line per fall (launch, first contact and onset ticks, frames seen, the first and
last, frames seen at or before the 1 s stop line onset - 30) and the medians. Run with
sim/.venv/bin/python.
"""

from __future__ import annotations

import io
import json
import statistics
import sys
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from sim.episode import RATE_HZ  # noqa: E402
from sim.stats import read_episode_metadata  # noqa: E402
from sim.strip import camera_frames  # noqa: E402

MIN_PIXELS = 4


def decoded(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"), dtype=np.float32) / 255


def ball_pixels(img: np.ndarray, rgb: np.ndarray) -> int:
    chroma = img / np.maximum(img.sum(-1, keepdims=True), 1e-3)
    close = np.abs(chroma - rgb / rgb.sum()).sum(-1) < 0.04
    return int((close & (img.sum(-1) > 0.6 * rgb.sum())).sum())


def ball_fall(meta: dict) -> bool:
    """Whether the recording's fall was caused by the ball (not by furniture, nor another cause)."""
    if meta.get("fall_cause") != "collision":
        return False
    hazard = json.loads(meta.get("hazard") or "null")
    if not hazard or not hazard.get("launched", True):
        return False
    contacts = json.loads(meta.get("contacts_ns") or "null")
    return contacts is None or "ball" in contacts


def seen_frames(path: Path, meta: dict) -> dict:
    hazard = json.loads(meta["hazard"])
    launch = int(hazard["launch_tick"])
    onset = round(int(meta["fall_onset_ns"]) * RATE_HZ / 1e9)
    # The ball's first touch (the first contact of any kind in recordings that list none apart).
    contacts = json.loads(meta.get("contacts_ns") or "null") or {}
    contact = round(int(contacts.get("ball", meta["first_contact_ns"])) * RATE_HZ / 1e9)
    with open(path, "rb") as f:
        frames = camera_frames(make_reader(f, decoder_factories=[DecoderFactory()]))
    rgb = np.array(hazard["rgb"], dtype=np.float32)
    # Only the frames from the baseline to the onset are decoded.
    base = ball_pixels(decoded(frames[max(0, launch - 10)]), rgb)
    seen = [t for t in range(launch, min(onset, len(frames)))
            if ball_pixels(decoded(frames[t]), rgb) - base >= MIN_PIXELS]
    return {"launch": launch, "contact": contact, "onset": onset, "seen": seen,
            "seen_by_1s_stop_line": [t for t in seen if t <= onset - RATE_HZ]}


def main() -> int:
    if len(sys.argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    root = Path(sys.argv[1])
    splits = sys.argv[2:] or ["validation", "test"]
    manifest = json.loads((root / "manifest.json").read_text())
    rows = []
    for split in splits:
        for name in manifest[split]:
            meta = read_episode_metadata(root / name)
            if not ball_fall(meta):
                continue
            r = seen_frames(root / name, meta)
            rows.append(r)
            span = f"{r['seen'][0]}-{r['seen'][-1]}" if r["seen"] else "-"
            print(f"{name}: launch {r['launch']}, contact {r['contact']}, onset {r['onset']}: "
                  f"{len(r['seen'])} frames ({span}), {len(r['seen_by_1s_stop_line'])} by the 1 s stop line")
    if not rows:
        print("no falls caused by the ball in these splits")
        return 0
    seen = [len(r["seen"]) for r in rows]
    by_stop = [len(r["seen_by_1s_stop_line"]) for r in rows]
    print(f"{len(rows)} falls caused by the ball: the ball seen in a median {statistics.median(seen):g} frames "
          f"before the onset, {statistics.median(by_stop):g} by the 1 s stop line; never by it in {by_stop.count(0)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
