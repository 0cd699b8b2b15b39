"""Does a data set's joint distribution cover a real walk? Per joint, the set's range against the real readings.

Data enters as a directory of recordings (``sim generate``) and one real
recording (``tests/fixtures/real/poppy_muffin_walk.mcap``, docs/real-recordings.md),
both read from their ``/joint_states`` (names mapped to the model's order);
it leaves as a table per joint: the set's 0.1 and 99.9 percentiles, mean and
standard deviation, the real walk's lowest and highest reading, whether every
real reading lies inside the set's 0.1-99.9 percentile range, and the largest
standardised distance of a real reading from the set's mean (degrees in the
table, as the real robot reports them).

Run: ``python -m sim coverage DIR --real tests/fixtures/real/poppy_muffin_walk.mcap``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from .robot import JOINT_NAMES

TOPIC_JOINTS = "/joint_states"
PERCENTILES = (0.1, 99.9)


def joint_positions(path: Path) -> np.ndarray:
    """Every /joint_states message of PATH as rows [n, 25] (rad, model order; NaN: not in the message)."""
    rows = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages(topics=[TOPIC_JOINTS], log_time_order=True):
            row = np.full(len(JOINT_NAMES), np.nan)
            for name, pos in zip(msg.name, msg.position):
                if name in JOINT_NAMES:
                    row[JOINT_NAMES.index(name)] = pos
            rows.append(row)
    if not rows:
        raise ValueError(f"{path}: no {TOPIC_JOINTS} messages")
    return np.array(rows)


def coverage(directory: Path, real: Path, max_episodes: int | None = None) -> dict:
    files = sorted(directory.glob("*.mcap"))
    if not files:
        raise ValueError(f"{directory}: no .mcap recordings")
    if max_episodes is not None and len(files) > max_episodes:
        # An even sample over the set (its episodes are in plan order).
        files = [files[i] for i in np.linspace(0, len(files) - 1, max_episodes).round().astype(int)]
    sim = np.rad2deg(np.vstack([joint_positions(f) for f in files]))
    walk = np.rad2deg(joint_positions(real))
    table = []
    for j, name in enumerate(JOINT_NAMES):
        s = sim[:, j][np.isfinite(sim[:, j])]
        r = walk[:, j][np.isfinite(walk[:, j])]
        lo, hi = np.percentile(s, PERCENTILES)
        mean, std = float(s.mean()), float(s.std())
        table.append({
            "joint": name, "set_p0.1_deg": round(float(lo), 2), "set_p99.9_deg": round(float(hi), 2),
            "set_mean_deg": round(mean, 2), "set_std_deg": round(std, 2),
            "real_min_deg": round(float(r.min()), 2), "real_max_deg": round(float(r.max()), 2),
            "real_inside": bool(r.min() >= lo and r.max() <= hi),
            "real_share_inside": round(float(((r >= lo) & (r <= hi)).mean()), 3),
            "max_standardised_distance": round(float(np.abs(r - mean).max() / max(std, 1e-9)), 1),
        })
    return {"episodes": len(files), "set_readings": int(sim.shape[0]), "real_readings": int(walk.shape[0]),
            "joints_inside": sum(t["real_inside"] for t in table), "joints": table}


def markdown(report: dict) -> str:
    lines = ["| joint | set p0.1 / p99.9 (deg) | set mean +- std | real min / max | inside | share inside | "
             "max distance (std) |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for t in report["joints"]:
        lines.append(f"| {t['joint']} | {t['set_p0.1_deg']:.1f} / {t['set_p99.9_deg']:.1f} | "
                     f"{t['set_mean_deg']:.1f} +- {t['set_std_deg']:.1f} | {t['real_min_deg']:.1f} / "
                     f"{t['real_max_deg']:.1f} | {'yes' if t['real_inside'] else 'no'} | "
                     f"{t['real_share_inside']:.3f} | {t['max_standardised_distance']:.1f} |")
    return "\n".join(lines)
