"""Summary of a data set directory: fall rate per sigma, onsets, distance, causes, counterfactuals.

Data enters as the ``fall_guard.episode`` metadata of each ``.mcap`` in a
directory; leaves as a JSON summary on stdout (``python -m sim stats DIR``).
With ``--counterfactual N`` it also re-simulates (no camera) up to N of the
directory's perturbation falls with the perturbation knots from
``onset - 1.5 s`` on redrawn, and reports the share of falls that were
averted or moved by more than 15 ticks: the share whose cause lay in the
plan the network is given rather than in hidden state.
"""

from __future__ import annotations

import json
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from .episode import RATE_HZ
from .recording import METADATA_NAME

#: The counterfactual redraws the perturbation from this long before the onset...
COUNTERFACTUAL_LEAD_TICKS = 45
#: ...and counts a fall as moved when its onset shifts by more than this.
COUNTERFACTUAL_MOVE_TICKS = 15


def read_episode_metadata(path: Path) -> dict[str, str]:
    with open(path, "rb") as f:
        for m in make_reader(f).iter_metadata():
            if m.name == METADATA_NAME:
                return dict(m.metadata)
    raise ValueError(f"{path}: no {METADATA_NAME} metadata record")


def _spread(values: list[float], digits: int) -> dict[str, float] | None:
    if not values:
        return None
    v = np.array(values, dtype=float)
    return {"min": round(float(v.min()), digits), "p10": round(float(np.percentile(v, 10)), digits),
            "median": round(float(np.median(v)), digits), "p90": round(float(np.percentile(v, 90)), digits),
            "max": round(float(v.max()), digits), "mean": round(float(v.mean()), digits)}


def plan_of(meta: dict[str, str]) -> dict | None:
    """The kept plan an episode followed, from its metadata (None: generator 2 or older, no plan id)."""
    if not meta.get("plan_id"):
        return None
    return {"params": json.loads(meta["gait"]), "attempts": int(meta["plan_attempts"]),
            "progress_m": float(meta["progress_m"]), "plan_id": meta["plan_id"]}


def _set_sigmas(directory: Path) -> tuple[float, ...]:
    """The sigmas the set's episodes drew from (its manifest), or the generator's default."""
    from .episode import SIGMAS
    try:
        return tuple(json.loads((directory / "manifest.json").read_text())["generator"]["sigmas"])
    except (OSError, ValueError, KeyError, TypeError):
        return SIGMAS


def _set_probabilities(directory: Path) -> dict[str, float]:
    """The ball, push and obstacle probabilities the set was made with (its manifest), or the defaults."""
    from .episode import HAZARD_PROBABILITY, OBSTACLE_PROBABILITY, PUSH_PROBABILITY
    try:
        g = json.loads((directory / "manifest.json").read_text())["generator"]
    except (OSError, ValueError, KeyError, TypeError):
        g = {}
    return {"hazard_probability": float(g.get("hazard_probability", HAZARD_PROBABILITY)),
            "push_probability": float(g.get("push_probability", PUSH_PROBABILITY)),
            "obstacle_probability": float(g.get("obstacle_probability", OBSTACLE_PROBABILITY))}


#: The outside causes, and the simulate_episode switch that takes each out.
CAUSE_SWITCH = {"push": "push", "obstacle": "obstacle", "collision": "hazard"}


def cause_counterfactual(seed: int, sigma: float, duration_s: float, cause: str, plan: dict | None = None,
                         sigmas: tuple[float, ...] | None = None, probabilities: dict | None = None) -> dict:
    """Re-simulate one generated fall with its outside CAUSE and without it (no camera).

    The episode without the push, the obstacle or the ball is the same episode
    (those have random streams of their own, or are drawn whether used or not).
    """
    from .episode import SIGMAS, KeptPlan, simulate_episode
    kw = dict(duration_s=duration_s, render=False, plan=KeptPlan.from_dict(plan) if plan else None,
              sigmas=sigmas or SIGMAS, **(probabilities or {}))
    ep = simulate_episode(seed, **kw)
    if ep.sigma != sigma:
        raise ValueError(f"episode seed {seed}: re-simulated sigma {ep.sigma} is not the recorded {sigma}")
    without = simulate_episode(seed, **kw, **{CAUSE_SWITCH[cause]: False})
    onset, cf = ep.fall_onset_tick, without.fall_onset_tick
    return {"seed": seed, "cause": cause, "reproduced": ep.fall_cause == cause, "onset_tick": onset,
            "without_onset_tick": cf, "averted": onset is not None and cf is None,
            "moved": onset is not None and cf is not None and abs(cf - onset) > COUNTERFACTUAL_MOVE_TICKS}


def counterfactual(seed: int, sigma: float, duration_s: float, draw: int = 1, plan: dict | None = None,
                   sigmas: tuple[float, ...] | None = None, walking: bool = False,
                   probabilities: dict | None = None) -> dict:
    """Re-simulate one generated episode (no camera) and its counterfactual; what happened to the fall.

    ``generate`` lets each episode draw its sigma, so the re-simulation does
    too (passing it would shift the episode's random stream and make another
    episode); SIGMA is the recorded one, checked against the draw. WALKING:
    the knots are redrawn at the episode's background sigma (its event taken
    out from onset - lead on) instead of from their own distribution.
    """
    from .episode import SIGMAS, KeptPlan, simulate_episode
    ep = simulate_episode(seed, duration_s=duration_s, render=False,
                          counterfactual_lead_ticks=COUNTERFACTUAL_LEAD_TICKS, counterfactual_draw=draw,
                          plan=KeptPlan.from_dict(plan) if plan else None, sigmas=sigmas or SIGMAS,
                          counterfactual_walking=walking, **(probabilities or {}))
    if ep.sigma != sigma:
        raise ValueError(f"episode seed {seed}: re-simulated sigma {ep.sigma} is not the recorded {sigma}; "
                         "was it made by `sim generate` with this generator?")
    onset, cf = ep.fall_onset_tick, ep.counterfactual_onset_tick
    return {"seed": seed, "sigma": sigma, "onset_tick": onset, "cause": ep.fall_cause,
            "counterfactual_onset_tick": cf,
            "averted": onset is not None and cf is None,
            "moved": onset is not None and cf is not None and abs(cf - onset) > COUNTERFACTUAL_MOVE_TICKS}


def summarise(directory: Path, counterfactual_n: int = 0, jobs: int = 1) -> dict:
    files = sorted(directory.glob("*.mcap"))
    if not files:
        raise ValueError(f"{directory}: no .mcap recordings")
    rows = []
    for path in files:
        meta = read_episode_metadata(path)
        hazard = json.loads(meta.get("hazard", "null") or "null")
        rows.append({
            "sigma": meta["sigma"], "seed": int(meta["seed"]), "duration_s": float(meta["duration_s"]),
            "onset_s": int(meta["fall_onset_ns"]) / 1e9 if "fall_onset_ns" in meta else None,
            "event_s": int(meta["event_ns"]) / 1e9 if "event_ns" in meta else None,
            "cause": meta.get("fall_cause"),
            "cause_s": int(meta["cause_ns"]) / 1e9 if "cause_ns" in meta else None,
            "push": json.loads(meta.get("push", "null") or "null") is not None,
            "obstacle": (json.loads(meta.get("obstacle", "null") or "null") or {}).get("kind"),
            "hazard": hazard is not None and hazard.get("launched", True),
            "launch_s": (int(hazard["launch_ns"]) / 1e9
                         if hazard is not None and hazard.get("launched", True) and "launch_ns" in hazard else None),
            "distance_m": float(meta.get("distance_m", "nan")),
            "progress_m": float(meta.get("progress_m", "nan")),
            "generator": meta.get("generator", "1"),
            "plan": plan_of(meta),
        })
    per_sigma: dict[str, dict] = {}
    by_sigma = defaultdict(list)
    for r in rows:
        by_sigma[r["sigma"]].append(r)
    for s, rs in sorted(by_sigma.items(), key=lambda kv: float(kv[0])):
        falls = [r for r in rs if r["onset_s"] is not None]
        plain = [r for r in rs if not r["hazard"]]
        per_sigma[s] = {
            "episodes": len(rs), "falling": len(falls), "fall_rate": round(len(falls) / len(rs), 3),
            "episodes_without_ball": len(plain),
            "fall_rate_without_ball": (round(sum(r["onset_s"] is not None for r in plain) / len(plain), 3)
                                       if plain else None),
            "collision_falls": sum(r["cause"] == "collision" for r in falls),
            "onset_s": _spread([r["onset_s"] for r in falls], 2),
            "event_to_onset_s": _spread([r["onset_s"] - r["event_s"] for r in falls
                                         if r["event_s"] is not None and r["cause"] == "perturbation"], 2),
            "perturbation_falls_before_event": sum(r["cause"] == "perturbation" and r["event_s"] is not None
                                                   and r["onset_s"] < r["event_s"] for r in falls),
            "distance_m": _spread([r["distance_m"] for r in rs], 3),
            "distance_m_not_falling": _spread([r["distance_m"] for r in rs if r["onset_s"] is None], 3),
        }
    falls = [r for r in rows if r["onset_s"] is not None]
    causes = {}
    for cause, has in (("perturbation", lambda r: True), ("collision", lambda r: r["hazard"]),
                       ("push", lambda r: r["push"]), ("obstacle", lambda r: r["obstacle"] is not None)):
        mine = [r for r in falls if r["cause"] == cause]
        causes[cause] = {
            "falls": len(mine), "share_of_falls": round(len(mine) / len(falls), 3) if falls else None,
            "episodes_with_it": sum(bool(has(r)) for r in rows),
            "cause_to_onset_s": _spread([r["onset_s"] - r["cause_s"] for r in mine if r["cause_s"] is not None], 2),
        }
    causes["obstacle"]["by_kind"] = {
        k: {"episodes": sum(r["obstacle"] == k for r in rows),
            "obstacle_falls": sum(r["obstacle"] == k and r["cause"] == "obstacle" for r in falls)}
        for k in sorted({r["obstacle"] for r in rows if r["obstacle"]})}
    plain = [r for r in rows if not (r["hazard"] or r["push"] or r["obstacle"])]
    launch_leads = [r["onset_s"] - r["launch_s"] for r in falls
                    if r["cause"] == "collision" and r["launch_s"] is not None]
    summary = {
        "episodes": len(rows),
        "generators": sorted({r["generator"] for r in rows}),
        "falling": len(falls),
        "fall_rate": round(len(falls) / len(rows), 3),
        "collision_share_of_falls": (round(sum(r["cause"] == "collision" for r in falls) / len(falls), 3)
                                     if falls else None),
        "episodes_with_ball": sum(r["hazard"] for r in rows),
        # How long before a collision fall the ball was launched (in the
        # camera's view from then on): what the camera can foresee at most.
        "collision_launch_to_onset_s": _spread(launch_leads, 2),
        "collision_launched_before_onset_share": (
            {f"{t:g}": round(sum(x > t for x in launch_leads) / len(launch_leads), 3) for t in (0.5, 1.0, 1.5, 2.0)}
            if launch_leads else None),
        "per_sigma": per_sigma,
        "onset_s": _spread([r["onset_s"] for r in falls], 2),
        "distance_m": _spread([r["distance_m"] for r in rows], 3),
        "distance_m_not_falling": _spread([r["distance_m"] for r in rows if r["onset_s"] is None], 3),
        "causes": causes,
        "episodes_without_outside_cause": len(plain),
        "distance_m_not_falling_without_outside_cause": _spread(
            [r["distance_m"] for r in plain if r["onset_s"] is None], 3),
        "plan_progress_m": _spread([r["progress_m"] for r in rows], 3),
        "distinct_plans": len({r["plan"]["plan_id"] for r in rows if r["plan"]}),
    }
    if counterfactual_n > 0:
        picks = [r for r in falls if r["cause"] == "perturbation"][:counterfactual_n]
        sigmas = _set_sigmas(directory)
        probabilities = _set_probabilities(directory)
        for cause in CAUSE_SWITCH:
            mine = [r for r in falls if r["cause"] == cause][:counterfactual_n]
            args = [(r["seed"], float(r["sigma"]), r["duration_s"], cause, r["plan"], sigmas, probabilities)
                    for r in mine]
            if jobs > 1 and args:
                with ProcessPoolExecutor(max_workers=jobs) as pool:
                    results = list(pool.map(cause_counterfactual, *zip(*args)))
            else:
                results = [cause_counterfactual(*a) for a in args]
            changed = [r for r in results if r["averted"] or r["moved"]]
            causes[cause]["counterfactual_without_it"] = {
                "falls_tried": len(results), "reproduced": sum(r["reproduced"] for r in results),
                "averted": sum(r["averted"] for r in results), "moved": sum(r["moved"] for r in results),
                "share_averted_or_moved": round(len(changed) / len(results), 3) if results else None,
            }
        for key, walking in (("counterfactual", False), ("counterfactual_walking", True)):
            args = [(r["seed"], float(r["sigma"]), r["duration_s"], 1, r["plan"], sigmas, walking, probabilities)
                    for r in picks]
            if jobs > 1:
                with ProcessPoolExecutor(max_workers=jobs) as pool:
                    results = list(pool.map(counterfactual, *zip(*args)))
            else:
                results = [counterfactual(*a) for a in args]
            changed = [r for r in results if r["averted"] or r["moved"]]
            summary[key] = {
                "lead_s": COUNTERFACTUAL_LEAD_TICKS / RATE_HZ, "move_ticks": COUNTERFACTUAL_MOVE_TICKS,
                "redrawn_from": "the background's sigma" if walking else "the knots' own sigma",
                "perturbation_falls_tried": len(results),
                "reproduced": sum(r["onset_tick"] is not None for r in results),
                "averted": sum(r["averted"] for r in results), "moved": sum(r["moved"] for r in results),
                "share_averted_or_moved": round(len(changed) / len(results), 3) if results else None,
            }
    return summary
