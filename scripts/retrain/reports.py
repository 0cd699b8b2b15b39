#!/usr/bin/env python3
"""The retrain's small questions about its reports and model files, one subcommand each.

    reports.py current REPORT MODEL HORIZON_MS HOLD_MS DATA_ROOT
        exit 0 when the warnings REPORT is of MODEL at HORIZON_MS with HOLD_MS
        (its model named relative to DATA_ROOT, or absolute as older reports
        name it), else 1
    reports.py shipped-run MODEL_FILE TRAINED_ON
        prints "SAME ABLATION SEED TRAJECTORY SUFFIX": whether the file was
        trained on TRAINED_ON by a run that ran its course (True/False;
        `ran_its_course`), its ablation in lower case, seed,
        trajectory input, and "-pp" when trained under the paper protocol
    reports.py chosen-pair THRESHOLDS_JSON
        prints "TRIGGER RELEASE": the pair chosen, or when none kept within
        the budget, the grid's highest trigger
    reports.py warned-ahead THRESHOLDS_JSON
        prints how many falls that pair (as chosen-pair) warned at least
        0.5 s ahead
    reports.py causes BYCAUSE_DIR
        prints the test split's fall causes that subset_by_cause.py found
        (BYCAUSE_DIR/causes.json), most falls first, on one line: the
        subsets BYCAUSE_DIR/CAUSE/ it wrote

Standard library only (with model_meta.py beside it).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from model_meta import read_meta  # noqa: E402


def is_current(report: str, model: str, horizon_ms: int, hold_ms: int, data_root: str) -> bool:
    r = json.loads(Path(report).read_text())
    named = os.path.realpath(os.path.join(data_root, r.get("model") or ""))
    return (named == os.path.realpath(model) and r.get("horizon_ms") == horizon_ms
            and r.get("release_hold_ms") == hold_ms)


#: The plan's training: at most this many epochs, stopped after this many without a better one.
PLAN_EPOCHS, PLAN_PATIENCE = 10, 3


def ran_its_course(meta: dict) -> bool:
    """The run behind a model file ended as the plan's runs end: early stopped (PLAN_PATIENCE
    epochs after its best) or at PLAN_EPOCHS. A file written part-way (`--epochs 3` while the
    validation loss still fell) is not the plan's run: its run resumes instead of being restored."""
    epochs = len(meta.get("history", []))
    return epochs >= PLAN_EPOCHS or epochs - int(meta.get("best_epoch", 0)) >= PLAN_PATIENCE


def shipped_run(model_file: str, trained_on: str) -> str:
    m = read_meta(model_file)
    same = m["trained_on"] == trained_on and ran_its_course(m)
    return " ".join(map(str, (same, m["ablation"].lower(), m["seed"],
                              m["config"].get("trajectory", "planned"),
                              "-pp" if m.get("protocol") == "paper" else "")))


def chosen(thresholds: str) -> dict:
    r = json.loads(Path(thresholds).read_text())
    return r["chosen"] or max(r["grid"], key=lambda s: s["trigger"])


def chosen_pair(thresholds: str) -> str:
    c = chosen(thresholds)
    return f"{c['trigger']} {c['release']}"


def causes(bycause: str) -> str:
    return " ".join(json.loads((Path(bycause) / "causes.json").read_text())["causes"])


def main(argv: list[str]) -> int:
    usage = "usage: reports.py current|shipped-run|chosen-pair|warned-ahead|causes ARGS... (see the module's docstring)"
    if not argv:
        print(usage, file=sys.stderr)
        return 2
    command, args = argv[0], argv[1:]
    if command == "current" and len(args) == 5:
        return 0 if is_current(args[0], args[1], int(args[2]), int(args[3]), args[4]) else 1
    if command == "shipped-run" and len(args) == 2:
        print(shipped_run(*args))
        return 0
    if command == "chosen-pair" and len(args) == 1:
        print(chosen_pair(args[0]))
        return 0
    if command == "warned-ahead" and len(args) == 1:
        print(chosen(args[0])["warned_by_0_5s"])
        return 0
    if command == "causes" and len(args) == 1:
        print(causes(args[0]))
        return 0
    print(usage, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
