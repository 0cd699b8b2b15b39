#!/usr/bin/env python3
"""The model card's result tables, from the reports of scripts/retrain/retrain.sh.

    model_card.py --reports DIR --keep models/card --out tables.md

Reads, under DIR (this data directory's reports): eval-GROUP-PROTOCOL/metrics.json
(`fall-guard-lab eval`), warnings-ABL-SET-SPLIT.json (`fall-guard-lab warnings`),
ABL-thresholds.json (chosen on scripts/retrain/choice_set.py's set, which holds the
walking set's validation split: false alarms are counted on its train and
test splits only), selected.txt, set-stats.json and walk-stats.json
(`python -m sim stats`) and cause-stats.json (the test split's falls by cause,
scripts/retrain/subset_by_cause.py).

The results are kept in the repository, under --keep, so that seeds trained
from different data directories add up (the data set and training are
deterministic: a run is the same network wherever it was trained, and eval
draws the same windows): each group report is split into one record per run
and per group (KEEP/runs/GROUP--RUN.json, the run's own metrics); the tables
are computed from every record there, a run's newest record winning. The
small reports (warnings, thresholds, selection, data statistics) are copied
to KEEP/reports/ and read from there.

Writes Markdown: the data, the paper and deployment protocols (seeds as mean
+- std), the checks the card makes (each with its figure, and by how much a
target is missed), by fall cause, and the daemon's warnings. The fall causes
are the data's (cause-stats.json, else those the warnings were replayed on):
per cause, its share of the test falls, the time from the cause to the onset
and, per network, the share of its falls warned >= 0.5 s ahead, EMP against
MP. Standard library only. Welch's t-test is one-sided (the claim "A > B" over seeds).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
from pathlib import Path

GROUPS = [("emp", "EMP"), ("mp", "MP"), ("ep", "EP"), ("p", "P"),
          ("emp-pp", "EMP, trained under the paper protocol"), ("mp-pp", "MP, trained under the paper protocol"),
          ("ep-pp", "EP, trained under the paper protocol"), ("p-pp", "P, trained under the paper protocol"),
          ("emp-hist", "EMP, historical-only plan"), ("emp-real", "EMP, real-position trajectory"),
          ("emp-hist-pp", "EMP, historical-only plan, paper protocol"),
          ("emp-real-pp", "EMP, real-position trajectory, paper protocol"),
          ("emp-vis-pp", "EMP, vision encoder at 1e-4, paper protocol"),
          ("emp-paper-pp", "EMP, `paper` configuration, paper protocol"), ("logreg", "logistic baseline"),
          ("gen1-emp", "EMP trained on generator 1"), ("gen1-mp", "MP trained on generator 1"),
          ("gen1-p", "P trained on generator 1"), ("gen4-emp", "EMP trained on generator 4"),
          ("gen4-mp", "MP trained on generator 4"), ("gen4-p", "P trained on generator 4")]


def load(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


# --- Results kept per run (KEEP/runs/GROUP--RUN.json) ---

METRICS = ("accuracy", "f1", "precision", "recall", "ece", "roc_auc")


def run_name(model_path: str) -> str:
    """The run a model file is: runs/emp-s2.cal.bpk -> emp-s2."""
    base = Path(model_path).name
    for suffix in (".cal.bpk", ".bpk", ".json"):
        if base.endswith(suffix):
            return base[: -len(suffix)]
    return base


def write_json(path: Path, value) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(value, indent=1) + "\n")
    os.replace(tmp, path)


def split_report(report: dict) -> dict[str, dict]:
    """One single-run report per model of a group report."""
    out = {}
    for i, model in enumerate(report["models"]):
        protocols = []
        for p in report.get("protocols", []):
            horizons = []
            for h in p["horizons"]:
                ci = h.get("ece_ci95", [])
                horizons.append({"horizon_ticks": h["horizon_ticks"], "horizon_ms": h["horizon_ms"],
                                 "per_model": [h["per_model"][i]], "ece_ci95": [ci[i]] if i < len(ci) else [],
                                 "windows": h["windows"], "positive_rate": h["positive_rate"]})
            protocols.append({"protocol": p["protocol"], "description": p.get("description", ""),
                              "windows": p["windows"], "horizons": horizons})
        out[run_name(model)] = {"models": [run_name(model)], "ablation": report.get("ablation"),
                                "split": report.get("split"), "protocols": protocols}
    return out


def mean_std(values: list[float]) -> dict:
    """Mean and population standard deviation of the finite values (as `fall-guard-lab eval`)."""
    v = [x for x in values if isinstance(x, (int, float)) and math.isfinite(x)]
    if not v:
        return {"mean": float("nan"), "std": float("nan")}
    m = sum(v) / len(v)
    return {"mean": m, "std": math.sqrt(sum((x - m) ** 2 for x in v) / len(v))}


def merge_records(records: list[dict]) -> dict:
    """One group report from single-run records (runs in name order)."""
    records = sorted(records, key=lambda r: r["models"][0])
    first = records[0]
    protocols = []
    for pi, p in enumerate(first["protocols"]):
        horizons = []
        for hi, h in enumerate(p["horizons"]):
            hs = [r["protocols"][pi]["horizons"][hi] for r in records]
            merged = {"horizon_ticks": h["horizon_ticks"], "horizon_ms": h["horizon_ms"],
                      "per_model": [x["per_model"][0] for x in hs],
                      "ece_ci95": [c for x in hs for c in x.get("ece_ci95", [])],
                      "windows": h["windows"], "positive_rate": h["positive_rate"]}
            for key in METRICS:
                merged[key] = mean_std([m[key] for m in merged["per_model"]])
            horizons.append(merged)
        protocols.append({**{k: p[k] for k in ("protocol", "description", "windows")}, "horizons": horizons})
    return {"models": [r["models"][0] for r in records], "ablation": first.get("ablation"),
            "split": first.get("split"), "protocols": protocols}


def keep_results(reports: Path, keep: Path) -> None:
    """Records this data directory's group reports per run under KEEP/runs and
    copies its small reports to KEEP/reports."""
    (keep / "runs").mkdir(parents=True, exist_ok=True)
    (keep / "reports").mkdir(parents=True, exist_ok=True)
    for d in sorted(reports.glob("eval-*")):
        r = load(d / "metrics.json")
        if r is None:
            continue
        label = d.name[len("eval-"):].rsplit("-", 1)[0]
        for run, record in split_report(r).items():
            write_json(keep / "runs" / f"{label}--{run}.json", record)
    for pattern in ("warnings-*.json", "warn2s-*.json", "*-thresholds.json", "*-stats.json", "selected.txt"):
        for f in reports.glob(pattern):
            if f.name.endswith(".partial"):
                continue
            shutil.copyfile(f, keep / "reports" / (f.name + ".partial"))
            os.replace(keep / "reports" / (f.name + ".partial"), keep / "reports" / f.name)


def kept_evals(keep: Path) -> dict:
    """(GROUP, PROTOCOL) -> the group's report merged from its kept runs."""
    groups: dict[str, list[dict]] = {}
    for f in sorted((keep / "runs").glob("*--*.json")):
        r = load(f)
        if r is not None:
            groups.setdefault(f.name.split("--", 1)[0], []).append(r)
    evals = {}
    for label, records in groups.items():
        r = merge_records(records)
        for p in r["protocols"]:
            evals[(label, p["protocol"])] = r
    return evals


# --- Student's t distribution (regularised incomplete beta, Numerical Recipes' continued fraction) ---

def _betacf(a: float, b: float, x: float) -> float:
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > 1e-300 else 1e-300)
    h = d
    for m in range(1, 300):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > 1e-300 else 1e-300)
        c = 1.0 + aa / c if abs(c) > 1e-300 else 1e300
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > 1e-300 else 1e-300)
        c = 1.0 + aa / c if abs(c) > 1e-300 else 1e300
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-12:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    lbeta = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log(1 - x)
    if x < (a + 1) / (a + b + 2):
        return math.exp(lbeta) * _betacf(a, b, x) / a
    return 1.0 - math.exp(lbeta) * _betacf(b, a, 1 - x) / b


def t_sf(t: float, df: float) -> float:
    """P(T > t) for Student's t with DF degrees of freedom."""
    x = df / (df + t * t)
    tail = 0.5 * betainc(df / 2, 0.5, x)
    return tail if t > 0 else 1.0 - tail


def welch_greater(a: list[float], b: list[float]) -> tuple[float, float] | None:
    """One-sided Welch test of mean(a) > mean(b): (t, p); None with fewer than 2 values a side."""
    if len(a) < 2 or len(b) < 2:
        return None
    ma, mb = sum(a) / len(a), sum(b) / len(b)
    va = sum((x - ma) ** 2 for x in a) / (len(a) - 1)
    vb = sum((x - mb) ** 2 for x in b) / (len(b) - 1)
    se2 = va / len(a) + vb / len(b)
    if se2 == 0:
        return (math.inf if ma > mb else -math.inf, 0.0 if ma > mb else 1.0)
    t = (ma - mb) / math.sqrt(se2)
    df = se2 ** 2 / ((va / len(a)) ** 2 / (len(a) - 1) + (vb / len(b)) ** 2 / (len(b) - 1))
    return t, t_sf(t, df)


# --- reports ---

def protocol(report: dict, name: str) -> dict | None:
    for p in report.get("protocols", []):
        if p["protocol"] == name:
            return p
    return None


def per_seed(h: dict, key: str) -> list[float]:
    return [m[key] for m in h["per_model"]]


def fmt_ms(ms: dict, digits: int = 3) -> str:
    if ms is None or ms.get("mean") is None or (isinstance(ms["mean"], float) and math.isnan(ms["mean"])):
        return "-"
    return f"{ms['mean']:.{digits}f} +- {ms['std']:.{digits}f}"


def horizon(report: dict, proto: str, ms: float) -> dict | None:
    p = protocol(report, proto)
    if p is None:
        return None
    for h in p["horizons"]:
        if abs(h["horizon_ms"] - ms) < 1:
            return h
    return None


def protocol_table(evals: dict, proto: str) -> list[str]:
    rows = []
    horizons = None
    for key, label in GROUPS:
        r = evals.get((key, proto))
        if r is None:
            continue
        p = protocol(r, proto)
        horizons = horizons or [h["horizon_ms"] for h in p["horizons"]]
        cells = [f"{fmt_ms(h['accuracy'])}" for h in p["horizons"]]
        auc = [f"{fmt_ms(h['roc_auc'])}" for h in p["horizons"]]
        rows.append(f"| {label} | {len(r['models'])} | " + " | ".join(cells) + " | " + " | ".join(auc) + " |")
    if not rows:
        return [f"(no {proto}-protocol report yet)"]
    return [*table_head(horizons, "accuracy", "ROC-AUC"), *rows]


def table_head(horizons_ms: list[float], *metrics: str) -> list[str]:
    """The head and rule of a table with a network and seeds column, then one column per metric
    and horizon."""
    hs = [f"{h / 1000:g} s" for h in horizons_ms]
    return ["| network | seeds | " + " | ".join(f"{m} {h}" for m in metrics for h in hs) + " |",
            "| " + " | ".join(["---"] * (2 + len(metrics) * len(hs))) + " |"]


def mean_floor(h: dict) -> float | None:
    """The ECE's noise floor of a horizon (`eval`'s `floor`), mean of its seeds; None for reports
    without it."""
    floors = [c["floor"] for c in h.get("ece_ci95", []) if "floor" in c]
    return sum(floors) / len(floors) if floors else None


def floor_note(h: dict) -> str:
    """What the ECE's noise floor (`eval`'s `floor`, `floor_upper`: the ECE a perfectly calibrated
    network shows on the same windows) says of a horizon's seeds; empty for reports without it."""
    floor = mean_floor(h)
    if floor is None:
        return ""
    cis = [c for c in h["ece_ci95"] if "floor" in c]
    above = sum(1 for c in cis if c["ece"] > c["floor_upper"])
    return (f"; a calibrated network would show {floor:.3f} on these windows (mean of seeds), and "
            f"{above} of {len(cis)} seeds stand above its 97.5th percentile")


def checks(evals: dict) -> list[str]:
    """The bars, on the groups that ship: the paper-trained runs (`ABL-pp`) when there are
    any, else the deployment-trained ones."""
    out = []
    emp, mp, p = (evals.get((f"{k}-pp", "paper")) or evals.get((k, "paper")) for k in ("emp", "mp", "p"))
    hist = evals.get(("emp-hist-pp", "paper")) or evals.get(("emp-hist", "paper"))
    if emp:
        pe = protocol(emp, "paper")
        for h in pe["horizons"]:
            acc = h["accuracy"]["mean"]
            verdict = "met" if acc >= 0.96 else f"missed by {100 * (0.96 - acc):.1f} points"
            out.append(f"- EMP accuracy at {h['horizon_ms'] / 1000:g} s: {acc:.3f} (target >= 0.96): {verdict}")
    for report, where in ((emp, ""), (evals.get(("emp-pp-heldout", "paper")), " on the held-out set")):
        if not report:
            continue
        for h in protocol(report, "paper")["horizons"]:
            ece = h["ece"]["mean"]
            cis = ", ".join(f"[{c['lower']:.3f}, {c['upper']:.3f}]" for c in h.get("ece_ci95", []) if "lower" in c)
            verdict = "met" if ece <= 0.03 else f"missed by {ece - 0.03:.3f}"
            out.append(f"- EMP ECE{where} at {h['horizon_ms'] / 1000:g} s: {ece:.3f} (target <= 0.03; 95% bootstrap "
                       f"per seed {cis or '-'}): {verdict}{floor_note(h)}")
    for a, b, an, bn, gap in ((emp, mp, "EMP", "MP", 0.02), (mp, p, "MP", "P", 0.04)):
        if not (a and b):
            continue
        ha, hb = horizon(a, "paper", 1000), horizon(b, "paper", 1000)
        if not (ha and hb):
            continue
        xa, xb = per_seed(ha, "accuracy"), per_seed(hb, "accuracy")
        diff = sum(xa) / len(xa) - sum(xb) / len(xb)
        w = welch_greater(xa, xb)
        wtxt = f"Welch t = {w[0]:.2f}, one-sided p = {w[1]:.3g}" if w else "Welch test needs 2 seeds a side"
        verdict = ("met" if diff >= gap and w and w[1] < 0.05 else
                   f"missed (gap {100 * diff:.1f} points against {100 * gap:.0f}; {wtxt})")
        out.append(f"- {an} - {bn} at 1 s: {100 * diff:+.1f} points ({len(xa)} vs {len(xb)} seeds; {wtxt}): "
                   f"{verdict}")
    # Trained under the paper protocol: the plan against the joints alone at every horizon.
    mpp, ppp = evals.get(("mp-pp", "paper")), evals.get(("p-pp", "paper"))
    if mpp and ppp:
        for h in protocol(mpp, "paper")["horizons"]:
            hb = horizon(ppp, "paper", h["horizon_ms"])
            if hb is None:
                continue
            xa, xb = per_seed(h, "accuracy"), per_seed(hb, "accuracy")
            diff = sum(xa) / len(xa) - sum(xb) / len(xb)
            w = welch_greater(xa, xb)
            wtxt = f"Welch t = {w[0]:.2f}, one-sided p = {w[1]:.3g}" if w else "Welch test needs 2 seeds a side"
            out.append(f"- MP - P, both trained under the paper protocol, at {h['horizon_ms'] / 1000:g} s: "
                       f"{100 * diff:+.1f} points ({len(xa)} vs {len(xb)} seeds; {wtxt})")
    if emp and hist:
        for h in protocol(emp, "paper")["horizons"]:
            hh = horizon(hist, "paper", h["horizon_ms"])
            if hh is None:
                continue
            diff = h["accuracy"]["mean"] - hh["accuracy"]["mean"]
            verdict = "met" if diff >= 0.05 else f"missed by {100 * (0.05 - diff):.1f} points"
            out.append(f"- full plan - historical-only at {h['horizon_ms'] / 1000:g} s: {100 * diff:+.1f} points "
                       f"(target >= 5): {verdict}")
    return out or ["(no paper-protocol reports yet)"]


def test_and_walking(reports: Path, stem: str) -> tuple[dict, int, float] | None:
    """The test split's latch figures of STEM-set-test.json, with the false alarms and minutes of
    the walking set's train and test splits (STEM-walk-*.json); None without the test report."""
    test = load(reports / f"{stem}-set-test.json")
    if not test:
        return None
    walks = [load(reports / f"{stem}-walk-{s}.json") for s in ("train", "test")]
    alarms = sum(w["grid"][0]["false_alarms"] for w in walks if w)
    minutes = sum(w["grid"][0]["non_falling_minutes"] for w in walks if w)
    return test["grid"][0], alarms, minutes


def warnings_rows(reports: Path, selected: list[tuple[str, str]]) -> list[str]:
    rows = ["| network | latch horizon | trigger / release | test falls warned | warned >= 0.5 s ahead | lead median | "
            "false alarms / min (walking set) | walking minutes |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for abl, name in selected:
        figures = test_and_walking(reports, f"warnings-{abl}")
        if not figures:
            continue
        t, alarms, minutes = figures
        early = t.get("warned_by_0_5s_share")
        early_txt = "-" if early is None else f"{100 * early:.0f}%"
        lead_txt = "-" if t["lead_median_s"] is None else f"{t['lead_median_s']:.2f} s"
        rate = alarms / minutes if minutes else float("nan")
        horizon = load(reports / f"warnings-{abl}-set-test.json").get("horizon_ms", 1000) / 1000
        rows.append(f"| {abl.upper()} ({name}) | {horizon:g} s | {t['trigger']:.2f} / {t['release']:.2f} | "
                    f"{t['warned']}/{t['falling_episodes']} ({100 * t['warned_share']:.0f}%) | {early_txt} | "
                    f"{lead_txt} | {rate:.3f} ({alarms} in {minutes:.1f} min) | {minutes:.1f} |")
    return rows


def held_txt(reports: list[dict | None]) -> str:
    """Time held (fall_imminent asserted) over the non-falling minutes of REPORTS (their first grid row), or
    '-' when none of them has the figure (reports written before it existed)."""
    rows = [r["grid"][0] for r in reports if r and "held_minutes" in r["grid"][0]]
    minutes = sum(g["non_falling_minutes"] for g in rows)
    if not rows or not minutes:
        return "-"
    held = sum(g["held_minutes"] for g in rows)
    return f"{100 * held / minutes:.1f}% ({held:.2f} of {minutes:.1f} min)"


def time_held_rows(reports: Path, selected: list[tuple[str, str]]) -> list[str]:
    """Time held per selected network: on the walking set, on the non-falling test episodes and on the real
    walk (warnings-ABL-real-test.json), each the share of non-falling time with fall_imminent asserted once the
    window is full; with the share of ticks before any fall whose window is outside the training range."""
    rows = []
    for abl, name in selected:
        stem = f"warnings-{abl}"
        walk = [load(reports / f"{stem}-walk-{s}.json") for s in ("train", "test")]
        test = load(reports / f"{stem}-set-test.json")
        real = load(reports / f"{stem}-real-test.json")
        if not any([*walk, test, real]):
            continue
        oor = [r["grid"][0].get("out_of_range_share") for r in (test, real) if r]
        oor_txt = " / ".join("-" if v is None else f"{100 * v:.1f}%" for v in oor) or "-"
        rows.append(f"| {abl.upper()} ({name}) | {held_txt(walk)} | {held_txt([test])} | {held_txt([real])} | "
                    f"{oor_txt} |")
    if not rows:
        return []
    return ["### Time held (`fall-guard-lab warnings`: the share of non-falling time with `fall_imminent` asserted, "
            "once the window is full)", "",
            "| network | walking set | non-falling test episodes | the real walk | windows out of range "
            "(test / real walk) |", "| --- | --- | --- | --- | --- |", *rows, ""]


def calibration_rows(keep: Path, selected: list[tuple[str, str]]) -> list[str]:
    """ECE of each selected network under both protocols (its own run's eval report, kept in KEEP/runs), with
    the floor a calibrated network would show on the same windows."""
    rows = []
    for abl, name in selected:
        # The run's record on the test split: under its own group (the name without
        # its seed), or, for a run written after part of its epochs (emp3-pp-s1),
        # under its ablation's (emp-pp); never a subset's (emp-pp-collision).
        prefix = name.rsplit("-s", 1)[0]
        groups = [prefix, abl + ("-pp" if prefix.endswith("-pp") else "")]
        report = next(filter(None, (load(keep / "runs" / f"{g}--{name}.json") for g in groups)), None)
        if not report:
            continue
        for proto in ("paper", "deployment"):
            p = protocol(report, proto)
            if not p:
                continue
            cells = []
            for h in p["horizons"]:
                ci = (h.get("ece_ci95") or [{}])[0]
                if "ece" not in ci:
                    continue
                floor = f", floor {ci['floor']:.3f}" if "floor" in ci else ""
                cells.append(f"{ci['ece']:.3f} [{ci['lower']:.3f}, {ci['upper']:.3f}]{floor}")
            rows.append(f"| {abl.upper()} ({name}) | {proto} | " + " | ".join(cells) + " |")
    if not rows:
        return []
    return ["### Calibration under both protocols (test split; ECE with its 95% bootstrap interval over episodes and "
            "the floor of a calibrated network on the same windows)", "",
            "| network | protocol | 0.5 s | 1 s | 1.5 s | 2 s |", "| --- | --- | --- | --- | --- | --- |", *rows, ""]


def latch_2s_rows(reports: Path) -> list[str]:
    """The latch on the 2 s output of the paper-trained networks (warn2s-RUN-*.json)."""
    rows = []
    for choose in sorted(reports.glob("warn2s-*-choose.json")):
        name = choose.name[len("warn2s-"):-len("-choose.json")]
        figures = test_and_walking(reports, f"warn2s-{name}")
        if not figures:
            continue
        t, alarms, minutes = figures
        lead = "-" if t["lead_median_s"] is None else f"{t['lead_median_s']:.2f} s"
        p10 = "-" if t.get("lead_p10_s") is None else f"{t['lead_p10_s']:.2f} s"
        early = t.get("warned_by_0_5s")
        rows.append(f"| {name} | {t['trigger']:.2f} / {t['release']:.2f} | {t['warned']}/{t['falling_episodes']} | "
                    f"{early if early is not None else '-'} | {lead} | {p10} | "
                    f"{t['false_alarms']} in {t['non_falling_minutes']:.1f} min | "
                    f"{alarms} in {minutes:.1f} min |")
    if not rows:
        return []
    return ["### The latch on the 2 s output (paper-trained networks; thresholds chosen at 2 s on validation)", "",
            "| run | trigger / release | test falls warned | warned >= 0.5 s ahead | lead median | lead p10 | "
            "alarms on non-falling test episodes | alarms on the walking set |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |", *rows, ""]


def cause_names(reports: Path, selected: list[tuple[str, str]]) -> list[str]:
    """The fall causes the card has figures for: those of the test split's falls
    (cause-stats.json, most falls first), else, by name, those a selected network's warnings
    were replayed on (warnings-ABL-CAUSE-test.json; not the test split, the walking set or the real walk)."""
    stats = load(reports / "cause-stats.json")
    if stats and stats.get("causes"):
        return list(stats["causes"])
    found = set()
    for abl, _ in selected:
        prefix = f"warnings-{abl}-"
        for f in reports.glob(f"{prefix}*-test.json"):
            cause = f.name[len(prefix):-len("-test.json")]
            if cause not in ("set", "walk", "real"):
                found.add(cause)
    return sorted(found)


def spread_txt(spread: dict | None, what: str = "") -> str:
    """A `sim stats` spread in s as "median (p10-p90)"; "-" without one."""
    if not spread:
        return "-"
    return f"{spread['median']:.2f} s ({spread['p10']:.2f}-{spread['p90']:.2f}){what}"


def early_share(t: dict) -> float | None:
    """The share of a warnings grid entry's falls warned >= 0.5 s ahead (None: not in the report)."""
    if t.get("warned_by_0_5s") is None or not t.get("falling_episodes"):
        return None
    return t["warned_by_0_5s"] / t["falling_episodes"]


def cause_warning_rows(reports: Path, selected: list[tuple[str, str]]) -> list[str]:
    """One row per fall cause of the test split: its falls and their share of the test falls, the
    time from the cause to the onset (cause-stats.json; a perturbation fall's from its event) and
    how many of the timed falls had their cause >= 0.5 s before the onset, then per selected
    network the falls warned >= 0.5 s ahead (warnings-ABL-CAUSE-test.json) and EMP's share
    against MP's; nothing without such warnings."""
    causes = cause_names(reports, selected)
    abls = [abl for abl, _ in selected]
    warned = {(c, a): load(reports / f"warnings-{a}-{c}-test.json") for c in causes for a in abls}
    if not any(warned.values()):
        return []
    stats = (load(reports / "cause-stats.json") or {}).get("causes", {})
    falls = {}
    for c in causes:
        counts = [r["grid"][0]["falling_episodes"] for a in abls if (r := warned[(c, a)])]
        falls[c] = stats[c]["falls"] if c in stats else (counts[0] if counts else None)
    total = sum(n for n in falls.values() if n is not None)
    both = "emp" in abls and "mp" in abls
    rows = ["| cause | test falls (share) | cause to onset, median (p10-p90) | cause >= 0.5 s before onset | "
            + " | ".join(f"{a.upper()} warned >= 0.5 s ahead" for a in abls) + (" | EMP - MP |" if both else " |"),
            "| " + " | ".join(["---"] * (4 + len(abls) + both)) + " |"]
    for c in causes:
        s = stats.get(c)
        n = falls[c]
        share = s["share_of_falls"] if s else (n / total if n is not None and total else None)
        head = f"{n} ({100 * share:.0f}%)" if n is not None and share is not None else "-"
        if not s:
            onset = "-"
        elif s.get("cause_to_onset_s"):
            onset = spread_txt(s["cause_to_onset_s"])
        else:
            onset = spread_txt(s.get("event_to_onset_s"), " from the event")
        timed = f"{s['caused_0_5s_before_onset']}/{s['timed_falls']}" if s and s.get("timed_falls") else "-"
        cells = []
        for a in abls:
            r = warned[(c, a)]
            e = early_share(r["grid"][0]) if r else None
            cells.append("-" if e is None else
                         f"{r['grid'][0]['warned_by_0_5s']}/{r['grid'][0]['falling_episodes']} ({100 * e:.0f}%)")
        if both:
            te, tm = (warned[(c, a)]["grid"][0] if warned[(c, a)] else {} for a in ("emp", "mp"))
            ee, em = early_share(te), early_share(tm)
            gap = "-"
            if ee is not None and em is not None and te["falling_episodes"] == tm["falling_episodes"]:
                d = te["warned_by_0_5s"] - tm["warned_by_0_5s"]
                gap = f"{100 * (ee - em):+.0f} points ({d:+d} {'fall' if abs(d) == 1 else 'falls'})"
            cells.append(gap)
        rows.append(f"| {c} | {head} | {onset} | {timed} | " + " | ".join(cells) + " |")
    return rows


def cause_lead_rows(reports: Path, selected: list[tuple[str, str]]) -> list[str]:
    rows = []
    for cause in cause_names(reports, selected):
        for abl, name in selected:
            r = load(reports / f"warnings-{abl}-{cause}-test.json")
            if not r:
                continue
            t = r["grid"][0]
            early = t.get("warned_by_0_5s_share")
            early_txt = "-" if early is None else f"{100 * early:.0f}%"
            lead_txt = "-" if t["lead_median_s"] is None else f"{t['lead_median_s']:.2f} s"
            rows.append(f"| {cause} | {abl.upper()} | {t['warned']}/{t['falling_episodes']} "
                        f"({100 * t['warned_share']:.0f}%) | {early_txt} | {lead_txt} |")
    if not rows:
        return []
    return ["| cause | network | falls warned | warned >= 0.5 s ahead | lead median |",
            "| --- | --- | --- | --- | --- |", *rows]


def warning_checks(reports: Path, selected: list[tuple[str, str]]) -> list[str]:
    """The daemon-path targets, for the shipped EMP: >= 95% of test falls warned >= 0.5 s
    ahead, median lead >= 1.5 s, <= 0.1 false alarms per minute over >= 30 min of walking."""
    name = dict(selected).get("emp")
    test = load(reports / "warnings-emp-set-test.json")
    if not (name and test):
        return []
    t = test["grid"][0]
    walks = [load(reports / f"warnings-emp-walk-{s}.json") for s in ("train", "test")]
    alarms = sum(w["grid"][0]["false_alarms"] for w in walks if w)
    minutes = sum(w["grid"][0]["non_falling_minutes"] for w in walks if w)
    out = []
    early = t.get("warned_by_0_5s_share")
    if early is not None:
        out.append(f"- EMP test falls warned >= 0.5 s ahead: {100 * early:.1f}% (target >= 95%): "
                   + ("met" if early >= 0.95 else f"missed by {100 * (0.95 - early):.1f} points"))
    lead = t["lead_median_s"]
    if lead is not None:
        out.append(f"- EMP median lead: {lead:.2f} s (target >= 1.5 s): "
                   + ("met" if lead >= 1.5 else f"missed by {1.5 - lead:.2f} s"))
    if minutes:
        rate = alarms / minutes
        ok = rate <= 0.1 and minutes >= 30
        out.append(f"- EMP false alarms: {rate:.3f} per minute ({alarms} in {minutes:.1f} min of walking; target "
                   f"<= 0.1 over >= 30 min): " + ("met" if ok else
                                                  f"missed ({'rate' if rate > 0.1 else 'too few minutes'})"))
    return out


TRADE_SHARES = (0.80, 0.90, 0.95)


def trade_cells(g: dict) -> str:
    """A latch grid entry as the trade table's cells: pair, falls warned >= 0.5 s ahead, alarms, held."""
    return (f"{g['trigger']:.2f} / {g['release']:.2f} | {g['warned_by_0_5s']}/{g['falling_episodes']} "
            f"({100 * early_share(g):.0f}%) | {g['false_alarms_per_min']:.2f} | {100 * g['held_share']:.1f}%")


def trade_rows(reports: Path, selected: list[tuple[str, str]]) -> list[str]:
    """What warning more falls costs, per selected network, from its latch's grid on the validation
    falls and walks (ABL-thresholds.json, where the pair was chosen): the chosen pair, then for each
    share in TRADE_SHARES the highest trigger whose latch warns at least that share of the validation
    falls >= 0.5 s ahead, with its false alarms per minute and share of walking held; "none" when no
    pair of the grid reaches it."""
    rows = []
    for abl, _ in selected:
        r = load(reports / f"{abl}-thresholds.json")
        if not r or not r.get("grid") or not r.get("chosen"):
            continue
        rows.append(f"| {abl.upper()} | chosen (<= {r['max_false_alarms_per_min']:g} / min) | "
                    f"{trade_cells(r['chosen'])} |")
        for want in TRADE_SHARES:
            reach = [g for g in r["grid"] if (e := early_share(g)) is not None and e >= want - 1e-9]
            if reach:
                rows.append(f"| {abl.upper()} | >= {100 * want:.0f}% warned | "
                            f"{trade_cells(max(reach, key=lambda g: g['trigger']))} |")
            else:
                rows.append(f"| {abl.upper()} | >= {100 * want:.0f}% warned | none of the grid | - | - | - |")
    if not rows:
        return []
    return ["| network | pair | trigger / release | validation falls warned >= 0.5 s ahead | "
            "false alarms / min (validation walking) | walking held |",
            "| --- | --- | --- | --- | --- | --- |", *rows]


def stats_rows(stats: dict | None, title: str) -> list[str]:
    if not stats:
        return [f"({title}: no stats yet)"]
    causes = stats.get("causes")
    share = ("falls by cause below" if causes else
             f"collision share of falls {stats['collision_share_of_falls']}")
    rows = [f"{title}: {stats['episodes']} episodes, {stats['falling']} falling ({100 * stats['fall_rate']:.1f}%), "
            f"{stats.get('distinct_plans', '-')} plans, {share}.", "",
            "| sigma | episodes | falls | without the ball: falls / episodes | collision falls |",
            "| --- | --- | --- | --- | --- |"]
    for s, r in stats["per_sigma"].items():
        plain = r["episodes_without_ball"]
        fr = r["fall_rate_without_ball"]
        rows.append(f"| {s} | {r['episodes']} | {r['falling']} | "
                    f"{round(fr * plain) if fr is not None else '-'} / {plain} | {r['collision_falls']} |")
    if causes:
        rows += ["", *cause_stats_rows(causes)]
    cf = stats.get("counterfactual")
    if cf:
        rows += ["", f"Counterfactual (knots from onset - {cf['lead_s']} s redrawn, {cf['perturbation_falls_tried']} "
                     f"perturbation falls): {cf['averted']} averted, {cf['moved']} moved by more than "
                     f"{cf['move_ticks']} ticks: {100 * cf['share_averted_or_moved']:.0f}%."]
    lead, share = stats.get("collision_launch_to_onset_s"), stats.get("collision_launched_before_onset_share")
    if lead and share:
        rows += ["", f"The ball, from its launch (in the head camera's view from then on) to the collision fall: "
                     f"median {lead['median']} s (p10 {lead['p10']}, p90 {lead['p90']}); launched more than "
                     + ", ".join(f"{k} s before the onset in {100 * v:.0f}%" for k, v in share.items())
                     + " of the collision falls."]
    return rows


def cause_stats_rows(causes: dict) -> list[str]:
    """The falls of a set by cause (`sim stats`, `causes`), most falls first: the episodes with the
    cause, its falls and share of the falls, the time from the cause to the onset, and when measured,
    the share of its falls averted or moved with the cause taken out."""
    rows = ["| cause | episodes with it | falls | share of falls | cause to onset, median (p10-p90) | "
            "without it: averted or moved |", "| --- | --- | --- | --- | --- | --- |"]
    for cause, c in sorted(causes.items(), key=lambda kv: (-kv[1]["falls"], kv[0])):
        share = "-" if c.get("share_of_falls") is None else f"{100 * c['share_of_falls']:.0f}%"
        cf = c.get("counterfactual_without_it")
        cf_txt = (f"{cf['averted'] + cf['moved']} / {cf['falls_tried']}" if cf and cf.get("falls_tried") else "-")
        rows.append(f"| {cause} | {c['episodes_with_it']} | {c['falls']} | {share} | "
                    f"{spread_txt(c.get('cause_to_onset_s'))} | {cf_txt} |")
    return rows


def accuracy_auc_rows(evals: dict, subset: str, groups) -> list[str]:
    """One row per GROUP evaluated on SUBSET (label GROUP-SUBSET, paper protocol): its
    seeds, then accuracy (ROC-AUC) per horizon."""
    rows = []
    for key, label in groups:
        r = evals.get((f"{key}-{subset}", "paper"))
        if r:
            p = protocol(r, "paper")
            rows.append(f"| {label} | {len(r['models'])} | "
                        + " | ".join(f"{fmt_ms(h['accuracy'])} ({fmt_ms(h['roc_auc'])})" for h in p["horizons"])
                        + " |")
    return rows


def per_horizon_rows(evals: dict) -> list[str]:
    """EMP trained one network per horizon (`emp-perh.hH`: horizon H's networks of every seed,
    paper protocol) against the all-horizon EMP's seeds (`emp-pp`): accuracy (ROC-AUC) per
    horizon, mean +- std over seeds; nothing without them."""
    perh = sorted((k for k in evals if k[0].startswith("emp-perh.h") and k[1] == "paper"),
                  key=lambda k: int(k[0].rsplit(".h", 1)[1]))
    if not perh:
        return []
    all_h = evals.get(("emp-pp", "paper"))
    seeds = len(all_h["models"]) if all_h else 0
    rows = ["### One network per horizon against the all-horizon EMP (paper protocol, both calibrated; "
            "accuracy (ROC-AUC), mean +- std over seeds)", "",
            f"| horizon | per-horizon networks (seeds) | all-horizon EMP ({seeds} seeds) |", "| --- | --- | --- |"]
    for key in perh:
        h = protocol(evals[key], "paper")["horizons"][0]
        full = horizon(all_h, "paper", h["horizon_ms"]) if all_h else None
        rows.append(f"| {h['horizon_ms'] / 1000:g} s | {fmt_ms(h['accuracy'])} ({fmt_ms(h['roc_auc'])}) "
                    f"({len(evals[key]['models'])}) | "
                    + (f"{fmt_ms(full['accuracy'])} ({fmt_ms(full['roc_auc'])})" if full else "-") + " |")
    return rows + [""]


def heldout_rows(evals: dict) -> list[str]:
    """The held-out set (`GROUP-heldout`, paper protocol): per network its seeds, accuracy per
    horizon, then ECE per horizon with its noise floor (mean of seeds)."""
    rows = []
    horizons = None
    for key, label in (("emp-pp", "EMP"), ("mp-pp", "MP"), ("p-pp", "P")):
        r = evals.get((f"{key}-heldout", "paper"))
        if not r:
            continue
        p = protocol(r, "paper")
        horizons = horizons or [h["horizon_ms"] for h in p["horizons"]]

        def ece(h: dict) -> str:
            floor = mean_floor(h)
            return fmt_ms(h["ece"]) + ("" if floor is None else f" (floor {floor:.3f})")

        rows.append(f"| {label} | {len(r['models'])} | " + " | ".join(fmt_ms(h["accuracy"]) for h in p["horizons"])
                    + " | " + " | ".join(ece(h) for h in p["horizons"]) + " |")
    if not rows:
        return []
    return [*table_head(horizons, "accuracy", "ECE"), *rows]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", type=Path, required=True)
    ap.add_argument("--keep", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    keep_results(a.reports, a.keep)
    evals = kept_evals(a.keep)
    kept = a.keep / "reports"
    selected = []
    sel = kept / "selected.txt"
    if sel.exists():
        selected = [tuple(line.split()[:2]) for line in sel.read_text().splitlines() if line.strip()]
    lines = ["<!-- Written by scripts/retrain/model_card.py from the reports of scripts/retrain/retrain.sh. -->", "",
             "### Data (simulated)", "", *stats_rows(load(kept / "set-stats.json"), "Training set"), "",
             *stats_rows(load(kept / "walk-stats.json"), "Walking set (false alarms)"), "",
             "### Paper protocol (test split)", "", *protocol_table(evals, "paper"), "",
             "### Checks", "", *checks(evals), "",
             "### Deployment protocol (test split)", "", *protocol_table(evals, "deployment"), ""]
    cause_rows = []
    for cause in cause_names(kept, selected):
        for key, label in (("emp", "EMP"), ("mp", "MP"), ("emp-pp", "EMP (paper-trained)"),
                           ("mp-pp", "MP (paper-trained)"), ("ep-pp", "EP (paper-trained)"),
                           ("p-pp", "P (paper-trained)"),
                           ("emp-vis-pp", "EMP, vision encoder at 1e-4 (paper-trained)")):
            r = evals.get((f"{key}-{cause}", "paper"))
            if r:
                p = protocol(r, "paper")
                cause_rows.append(f"| {cause} | {label} | " + " | ".join(fmt_ms(h["accuracy"]) for h in p["horizons"])
                                  + " |")
    if cause_rows:
        lines += ["### By fall cause (paper protocol, test falls of that cause with the test walks)", "",
                  "| cause | network | 0.5 s | 1 s | 1.5 s | 2 s |", "| --- | --- | --- | --- | --- | --- |",
                  *cause_rows, ""]
    sigma_rows = accuracy_auc_rows(evals, "highsigma", (
        ("emp", "EMP"), ("mp", "MP"), ("p", "P"), ("emp-pp", "EMP (paper-trained)"),
        ("mp-pp", "MP (paper-trained)"), ("p-pp", "P (paper-trained)")))
    if sigma_rows:
        lines += ["### Within the event episodes (test episodes at sigma >= 0.035; paper protocol, "
                  "accuracy (ROC-AUC))", "",
                  "| network | seeds | 0.5 s | 1 s | 1.5 s | 2 s |",
                  "| --- | --- | --- | --- | --- | --- |", *sigma_rows, ""]
    held = heldout_rows(evals)
    if held:
        lines += ["### The held-out set (a second test set of its own seed and plans; paper protocol, "
                  "ECE with its noise floor)", "", *held, ""]
    camera_rows = accuracy_auc_rows(evals, "valcollision", (
        ("emp-pp", "EMP"), ("emp-vis-pp", "EMP, vision encoder at 1e-4"), ("mp-pp", "MP")))
    if camera_rows:
        lines += ["### The camera's case on validation (validation collision falls with the validation walks; "
                  "paper protocol, accuracy (ROC-AUC))", "",
                  "| network | seeds | 0.5 s | 1 s | 1.5 s | 2 s |", "| --- | --- | --- | --- | --- | --- |",
                  *camera_rows, ""]
    warned_rows = cause_warning_rows(kept, selected)
    if warned_rows:
        lines += ["### What each network warns, by fall cause (`fall-guard-lab warnings` on the test falls of "
                  "that cause; the cause's time to the onset on the test split, a perturbation fall's from its event)",
                  "", *warned_rows, "",
                  "A fall whose cause comes less than 0.5 s before its onset is warned 0.5 s ahead only by a latch "
                  "already asserted before the cause.", ""]
    trade = trade_rows(kept, selected)
    if trade:
        lines += ["### What warning more falls costs (the latch's pairs on the validation falls and walks, where "
                  "each pair was chosen)", "", *trade, ""]
    lead_rows = cause_lead_rows(kept, selected)
    if lead_rows:
        lines += ["### Warnings by fall cause (`fall-guard-lab warnings` on the test falls of that cause)", "",
                  *lead_rows, ""]
    lines += per_horizon_rows(evals)
    lines += ["### The daemon's warnings (`fall-guard-lab warnings`, streaming, thresholds chosen on validation)", "",
              *warnings_rows(kept, selected), "", *warning_checks(kept, selected), "",
              *time_held_rows(kept, selected), *calibration_rows(a.keep, selected),
              *latch_2s_rows(kept)]
    a.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
