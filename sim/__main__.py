"""Command line of the simulator: ``python -m sim {generate,fixtures,stats,coverage,strip,build-model,poppy-muffin}``.

Run from the repository root with the venv's Python (see sim/README.md).
Arguments are checked before any work starts; a bad one ends with a message
naming it and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from .cluster import ClusterError
from .dataset import DatasetError, generate
from .gait import GAIT_FAMILIES

REPO_ROOT = Path(__file__).resolve().parent.parent
FIXTURES_DIR = REPO_ROOT / "tests" / "fixtures"


def _sigmas(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of numbers: {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    g = sub.add_parser("generate", help="make a data set of simulated episodes (resumable)")
    g.add_argument("--out", type=Path, required=True, help="data set directory (created if missing)")
    g.add_argument("--episodes", type=int, required=True, help="number of episodes")
    g.add_argument("--seed", type=int, default=1, help="base seed (episode i uses seed*100000+i)")
    g.add_argument("--jobs", type=int, default=1, help="parallel worker processes")
    g.add_argument("--duration", type=float, default=10.0, help="episode length in seconds")
    g.add_argument("--sigmas", type=_sigmas, default=None,
                   help="comma-separated perturbation sigmas to draw from (default 0.005,0.01,0.035,0.04)")
    g.add_argument("--ball-probability", type=float, default=None,
                   help="share of episodes with a ball rolled at the robot (default 0.2)")
    g.add_argument("--gait", choices=GAIT_FAMILIES, default="dynamic",
                   help="the gait family of the set's plans: dynamic (walks through the balance feedback) "
                        "or hardware (the real Poppy walk's step, randomised; sim/README.md)")
    g.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run each plan group as a task on the Ray cluster at ADDRESS (host:port or auto; "
                        "without ADDRESS: $RAY_ADDRESS, else a local one); the files are the same")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    f = sub.add_parser("fixtures", help="regenerate the committed test fixtures in tests/fixtures/")
    f.add_argument("--out", type=Path, default=FIXTURES_DIR)
    f.add_argument("--jobs", type=int, default=2)
    s = sub.add_parser("strip", help="write a PNG strip of head-camera frames of one recording")
    s.add_argument("recording", type=Path)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--frames", type=int, default=10)
    st = sub.add_parser("stats", help="fall rate per sigma, onsets, distance, collision share, counterfactuals")
    st.add_argument("directory", type=Path)
    st.add_argument("--counterfactual", type=int, default=0, metavar="N",
                    help="also re-simulate up to N perturbation falls with the knots from onset - 1.5 s redrawn")
    st.add_argument("--jobs", type=int, default=1, help="parallel worker processes for --counterfactual")
    m = sub.add_parser("build-model", help="rebuild sim/model/poppy_humanoid.urdf from the reference files")
    m.add_argument("--reference", type=Path, default=None)
    cv = sub.add_parser("coverage", help="per joint: does the set's 0.1-99.9 percentile range hold a real walk")
    cv.add_argument("directory", type=Path)
    cv.add_argument("--real", type=Path, default=FIXTURES_DIR / "real" / "poppy_muffin_walk.mcap",
                    help="the real recording (default tests/fixtures/real/poppy_muffin_walk.mcap)")
    cv.add_argument("--max-episodes", type=int, default=None, help="read an even sample of this many episodes")
    cv.add_argument("--markdown", action="store_true", help="print the table as Markdown instead of JSON")
    pm = sub.add_parser("poppy-muffin",
                        help="convert poppy-muffin's real-robot walk buffer to a recording (docs/real-recordings.md)")
    pm.add_argument("--buffers", type=Path, required=True, help="scripts/scratchbuf.real.pkl of poppy-muffin")
    pm.add_argument("--out", type=Path, default=None, help="recording to write")
    pm.add_argument("--commit", default=None, help="poppy-muffin commit the buffers come from (metadata)")
    pm.add_argument("--tracking", action="store_true",
                    help="print the real servos' tracking and the simulator's on the same commanded path")
    hs = sub.add_parser("hardware-step",
                        help="write the hardware gait's step (sim/model/poppy_muffin_step.json) from a real walk")
    hs.add_argument("--real", type=Path, default=FIXTURES_DIR / "real" / "poppy_muffin_walk.mcap",
                    help="the converted real walk (default tests/fixtures/real/poppy_muffin_walk.mcap)")
    hs.add_argument("--out", type=Path, default=None, help="default: sim/model/poppy_muffin_step.json")
    args = parser.parse_args(argv)

    try:
        if args.command == "generate":
            from .dataset import cpu_seconds
            from .episode import HAZARD_PROBABILITY, SIGMAS
            t0, cpu0 = time.perf_counter(), cpu_seconds()
            stats = generate(args.out, args.episodes, args.seed, args.jobs, args.duration,
                             progress=not args.quiet, sigmas=args.sigmas or SIGMAS,
                             hazard_probability=(HAZARD_PROBABILITY if args.ball_probability is None
                                                 else args.ball_probability),
                             use_ray=args.ray is not None, ray_address=args.ray or None, gait=args.gait)
            cpu = cpu_seconds() - cpu0
            made = len(stats)
            falls = sum(s["fall_onset_tick"] is not None for s in stats)
            wall = time.perf_counter() - t0
            per_episode = round(sum(s["seconds"] for s in stats) / made, 2) if made else None
            # On Ray the work runs in the cluster's worker processes, not in this one's children:
            # only the workers' wall time per episode is known here.
            on_ray = args.ray is not None
            print(json.dumps({"out": str(args.out), "made": made, "already_there": args.episodes - made,
                              "falling": falls, "wall_s": round(wall, 1),
                              "cpu_s": None if on_ray else round(cpu, 1),
                              "cpu_s_per_episode": round(cpu / made, 2) if made and not on_ray else None,
                              "worker_wall_s_per_episode": per_episode}))
        elif args.command == "fixtures":
            if args.jobs < 1:
                raise DatasetError(f"--jobs must be at least 1 (got {args.jobs})")
            from .fixtures import make_fixtures
            for row in make_fixtures(args.out, args.jobs):
                print(json.dumps(row))
        elif args.command == "strip":
            from .strip import write_strip
            write_strip(args.recording, args.out, args.frames)
            print(args.out)
        elif args.command == "stats":
            from .stats import summarise
            if args.counterfactual < 0:
                raise DatasetError(f"--counterfactual must be >= 0 (got {args.counterfactual})")
            if args.jobs < 1:
                raise DatasetError(f"--jobs must be at least 1 (got {args.jobs})")
            print(json.dumps(summarise(args.directory, args.counterfactual, args.jobs), indent=2))
        elif args.command == "coverage":
            from .coverage import coverage, markdown
            if args.max_episodes is not None and args.max_episodes < 1:
                raise DatasetError(f"--max-episodes must be at least 1 (got {args.max_episodes})")
            report = coverage(args.directory, args.real, args.max_episodes)
            print(markdown(report) if args.markdown else json.dumps(report, indent=2))
        elif args.command == "poppy-muffin":
            from . import poppy_muffin as pmf
            if args.out is None and not args.tracking:
                raise DatasetError("poppy-muffin: give --out, --tracking or both")
            if args.out is not None:
                print(json.dumps(pmf.convert(args.buffers, args.out, args.commit or pmf.SOURCE_COMMIT)))
            if args.tracking:
                print(json.dumps(pmf.tracking_report(pmf.load_scratchbuf(args.buffers)), indent=2))
        elif args.command == "hardware-step":
            from .gait import STEP_KNOTS_PATH
            from .poppy_muffin import step_knots
            out = args.out or STEP_KNOTS_PATH
            step = step_knots(args.real)
            tmp = out.with_name(out.name + ".partial")
            tmp.write_text(json.dumps(step) + "\n")
            os.replace(tmp, out)
            print(json.dumps({"out": str(out), "knots": len(step["time_s"]), "step_s": step["time_s"][-1]}))
        elif args.command == "build-model":
            from .build_model import build
            if args.reference is None:
                raise DatasetError("--reference DIR is required: the directory of the reference "
                                   "poppy_humanoid.pybullet.urdf and its meshes/ (see sim/README.md)")
            print(build(args.reference))
    except (DatasetError, ClusterError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
