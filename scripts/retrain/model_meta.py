#!/usr/bin/env python3
"""Print a field of a fall-guard model file's metadata (models/README.md "File format").

    model_meta.py MODEL.bpk val_loss     the best epoch's validation loss
    model_meta.py MODEL.bpk json         the whole ModelMeta JSON
    model_meta.py MODEL.bpk KEY          a top-level key (ablation, seed, best_epoch, ...)

Standard library only: the pipeline (scripts/retrain/retrain.sh) selects networks with it.
"""

from __future__ import annotations

import json
import struct
import sys

# Version 2: the same layout, for a file whose calibration is beta calibration.
MAGICS = (b"FGEMP\0v1", b"FGEMP\0v2")


def read_meta(path: str) -> dict:
    with open(path, "rb") as f:
        if f.read(8) not in MAGICS:
            raise SystemExit(f"{path}: not a fall-guard model file (no FGEMP v1 or v2 header)")
        (n,) = struct.unpack("<Q", f.read(8))
        return json.loads(f.read(n))


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    meta = read_meta(sys.argv[1])
    key = sys.argv[2]
    if key == "json":
        print(json.dumps(meta, indent=2))
    elif key == "val_loss":
        best = meta["best_epoch"]
        print(meta["history"][best - 1]["val_loss"])
    else:
        print(json.dumps(meta[key]) if not isinstance(meta[key], str) else meta[key])
    return 0


if __name__ == "__main__":
    sys.exit(main())
