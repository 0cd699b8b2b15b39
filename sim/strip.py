"""A PNG strip of head-camera frames from one recording (for the README).

Data enters as an ``.mcap`` recording; leaves as one PNG: frames side by side,
each scaled 2x, taken evenly from 2 s before the fall onset to 1 s after it
(or across the whole episode when it does not fall).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image

from .episode import RATE_HZ
from .recording import METADATA_NAME, TOPIC_CAMERA


def camera_frames(reader) -> list[bytes]:
    """The head camera's frames (JPEG bytes) in recording order, from an MCAP reader made with
    the ROS 2 decoder."""
    return [bytes(msg.data) for _, _, _, msg in reader.iter_decoded_messages(topics=[TOPIC_CAMERA])]


def write_strip(recording: Path, out: Path, n_frames: int = 10) -> None:
    with open(recording, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        meta = {}
        for m in reader.iter_metadata():
            if m.name == METADATA_NAME:
                meta = dict(m.metadata)
        frames = camera_frames(reader)
    if not frames:
        raise ValueError(f"{recording}: no {TOPIC_CAMERA} messages")
    if "fall_onset_ns" in meta:
        onset = int(round(int(meta["fall_onset_ns"]) * RATE_HZ / 1e9))
        lo, hi = max(0, onset - 2 * RATE_HZ), min(len(frames) - 1, onset + RATE_HZ)
    else:
        lo, hi = 0, len(frames) - 1
    picks = np.linspace(lo, hi, n_frames).round().astype(int)
    tiles = [np.asarray(Image.open(io.BytesIO(frames[k])).convert("RGB").resize((128, 128), Image.NEAREST))
             for k in picks]
    gap = np.full((128, 4, 3), 255, np.uint8)
    row = np.hstack([x for t in tiles for x in (t, gap)][:-1])
    Image.fromarray(row).save(out, format="PNG")
