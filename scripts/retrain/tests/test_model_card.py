"""scripts/model_card.py: results kept per run, merged over seeds, the statistics and the checks."""

from __future__ import annotations

import json
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import model_card  # noqa: E402


def horizon(ms: float, accs: list[float], eces: list[float], floors=None) -> dict:
    """One horizon of a group report of len(accs) models."""
    per_model = [{"accuracy": a, "f1": a, "precision": a, "recall": a, "ece": e, "roc_auc": a, "count": 10}
                 for a, e in zip(accs, eces)]
    cis = [{"ece": e, "lower": e / 2, "upper": 2 * e, "level": 0.95, "resamples": 1000, "episodes": 5}
           for e in eces]
    for c, f in zip(cis, floors or []):
        c["floor"], c["floor_upper"] = f
    return {"horizon_ticks": round(ms * 0.03), "horizon_ms": ms, "per_model": per_model, "ece_ci95": cis,
            "windows": 10, "positive_rate": 0.5}


def report(models: list[str], accs_by_ms: dict[float, list[float]], eces=None, floors=None) -> dict:
    hs = [horizon(ms, accs, eces or [0.05] * len(accs), floors) for ms, accs in accs_by_ms.items()]
    return {"models": models, "ablation": "EMP", "split": "test",
            "protocols": [{"protocol": "paper", "description": "d", "windows": 40, "horizons": hs}]}


def test_a_group_report_splits_into_runs_and_merges_back_as_mean_and_std():
    r = report(["/d/runs/emp-pp-s1.cal.bpk", "/d/runs/emp-pp-s2.cal.bpk"], {1000.0: [0.8, 0.9]})
    runs = model_card.split_report(r)
    assert sorted(runs) == ["emp-pp-s1", "emp-pp-s2"]
    assert runs["emp-pp-s2"]["protocols"][0]["horizons"][0]["per_model"][0]["accuracy"] == 0.9
    merged = model_card.merge_records(list(runs.values()))
    h = merged["protocols"][0]["horizons"][0]
    assert merged["models"] == ["emp-pp-s1", "emp-pp-s2"]
    assert math.isclose(h["accuracy"]["mean"], 0.85) and math.isclose(h["accuracy"]["std"], 0.05)
    assert len(h["ece_ci95"]) == 2


def write_eval(reports: Path, label: str, r: dict) -> None:
    d = reports / f"eval-{label}-paper"
    d.mkdir(parents=True, exist_ok=True)
    (d / "metrics.json").write_text(json.dumps(r))


def test_seeds_evaluated_apart_add_up_and_the_newest_record_of_a_run_wins(tmp_path):
    reports, keep = tmp_path / "reports", tmp_path / "keep"
    write_eval(reports, "emp-pp", report(["runs/emp-pp-s1.cal.bpk", "runs/emp-pp-s2.cal.bpk"],
                                         {1000.0: [0.80, 0.82]}))
    model_card.keep_results(reports, keep)
    # Another data directory evaluates seed 3, and seed 2 again with another result.
    write_eval(reports, "emp-pp", report(["runs/emp-pp-s2.cal.bpk", "runs/emp-pp-s3.cal.bpk"],
                                         {1000.0: [0.90, 0.84]}))
    model_card.keep_results(reports, keep)
    evals = model_card.kept_evals(keep)
    r = evals[("emp-pp", "paper")]
    assert r["models"] == ["emp-pp-s1", "emp-pp-s2", "emp-pp-s3"]
    assert model_card.per_seed(r["protocols"][0]["horizons"][0], "accuracy") == [0.80, 0.90, 0.84]


def t_sf_by_integration(t: float, df: float) -> float:
    """P(T > t) by Simpson's rule on Student's density over [t, t + 200]."""
    c = math.gamma((df + 1) / 2) / (math.sqrt(df * math.pi) * math.gamma(df / 2))
    f = lambda x: c * (1 + x * x / df) ** (-(df + 1) / 2)  # noqa: E731
    n, a, b = 200_000, t, t + 200.0
    step = (b - a) / n
    s = f(a) + f(b) + sum((4 if i % 2 else 2) * f(a + i * step) for i in range(1, n))
    return s * step / 3


def test_the_t_tail_matches_the_density_integrated():
    for t, df in ((1.9, 3.7), (0.4, 2.0), (3.1, 8.5)):
        assert math.isclose(model_card.t_sf(t, df), t_sf_by_integration(t, df), rel_tol=1e-3, abs_tol=1e-6)
    assert math.isclose(model_card.t_sf(-1.2, 4.0), 1 - model_card.t_sf(1.2, 4.0), rel_tol=1e-9)


def test_welch_is_one_sided_and_needs_two_seeds_a_side():
    a, b = [0.84, 0.85, 0.86], [0.80, 0.81, 0.83]
    t, p = model_card.welch_greater(a, b)
    # t = (mean a - mean b) / sqrt(va / na + vb / nb), sample variances.
    se = math.sqrt(statistics.variance(a) / 3 + statistics.variance(b) / 3)
    assert math.isclose(t, (statistics.mean(a) - statistics.mean(b)) / se, rel_tol=1e-9)
    assert 0 < p < 0.05
    assert math.isclose(model_card.welch_greater(b, a)[1], 1 - p, rel_tol=1e-9)
    assert model_card.welch_greater([0.9], b) is None


def merged(r: dict) -> dict:
    """A group report as the card reads it: merged from its runs' records."""
    return model_card.merge_records(list(model_card.split_report(r).values()))


def test_the_ece_check_says_by_how_much_and_where_the_floor_stands():
    # Seed 1 above its floor's 97.5th percentile, seed 2 within it.
    emp = report(["emp-pp-s1", "emp-pp-s2"], {500.0: [0.95, 0.97]}, eces=[0.08, 0.04],
                 floors=[(0.03, 0.05), (0.035, 0.06)])
    lines = model_card.checks({("emp-pp", "paper"): merged(emp)})
    ece = [x for x in lines if "ECE" in x]
    assert len(ece) == 1
    assert "0.060 (target <= 0.03" in ece[0] and "missed by 0.030" in ece[0]
    assert "would show 0.033" in ece[0] and "1 of 2 seeds stand above" in ece[0]
    acc = [x for x in lines if "accuracy" in x]
    assert "0.960 (target >= 0.96): met" in acc[0]
    # A report from before the floor: the check without it.
    old = report(["emp-pp-s1"], {500.0: [0.9]}, eces=[0.02])
    ece = [x for x in model_card.checks({("emp-pp", "paper"): merged(old)}) if "ECE" in x]
    assert ece[0].endswith("): met")


def test_the_held_out_set_gets_its_own_ece_check_and_table():
    emp = report(["emp-pp-s1", "emp-pp-s2"], {500.0: [0.95, 0.97]}, eces=[0.08, 0.04],
                 floors=[(0.03, 0.05), (0.035, 0.06)])
    held = report(["emp-pp-s1", "emp-pp-s2"], {500.0: [0.93, 0.95]}, eces=[0.02, 0.03],
                  floors=[(0.015, 0.02), (0.017, 0.025)])
    evals = {("emp-pp", "paper"): merged(emp), ("emp-pp-heldout", "paper"): merged(held)}
    ece = [x for x in model_card.checks(evals) if "ECE" in x]
    assert len(ece) == 2
    assert ece[0].startswith("- EMP ECE at 0.5 s: 0.060") and "missed by 0.030" in ece[0]
    assert ece[1].startswith("- EMP ECE on the held-out set at 0.5 s: 0.025") and "): met;" in ece[1]
    assert "would show 0.016" in ece[1] and "1 of 2 seeds stand above" in ece[1]
    # The accuracy checks stay the test split's.
    assert len([x for x in model_card.checks(evals) if "accuracy" in x]) == 1
    rows = model_card.heldout_rows(evals)
    assert rows[0] == "| network | seeds | accuracy 0.5 s | ECE 0.5 s |"
    assert rows[2] == "| EMP | 2 | 0.940 +- 0.010 | 0.025 +- 0.005 (floor 0.016) |"
    assert model_card.heldout_rows({("emp-pp", "paper"): merged(emp)}) == []


def test_each_per_horizon_network_sits_beside_the_all_horizon_emp_at_its_horizon():
    emp = report(["emp-pp-s1", "emp-pp-s2"], {500.0: [0.95, 0.97], 1000.0: [0.84, 0.86]})
    h30 = report(["emp-perh-s1.h30", "emp-perh-s2.h30"], {1000.0: [0.81, 0.83]})
    h15 = report(["emp-perh-s1.h15"], {500.0: [0.93]})
    evals = {("emp-pp", "paper"): merged(emp), ("emp-perh.h30", "paper"): merged(h30),
             ("emp-perh.h15", "paper"): merged(h15)}
    rows = model_card.per_horizon_rows(evals)
    assert "all-horizon EMP (2 seeds)" in rows[2]
    # Shortest horizon first, whatever order the reports came in; each with its own seeds.
    assert rows[4] == "| 0.5 s | 0.930 +- 0.000 (0.930 +- 0.000) (1) | 0.960 +- 0.010 (0.960 +- 0.010) |"
    assert rows[5] == "| 1 s | 0.820 +- 0.010 (0.820 +- 0.010) (2) | 0.850 +- 0.010 (0.850 +- 0.010) |"
    assert model_card.per_horizon_rows({("emp-pp", "paper"): merged(emp)}) == []


def warnings_report(falls: int, early: int, walks: int = 10) -> dict:
    """A `fall-guard-lab warnings` report with fixed thresholds: FALLS falls, EARLY of them
    warned >= 0.5 s ahead."""
    t = {"trigger": 0.7, "release": 0.4, "falling_episodes": falls, "warned": early, "warned_share": early / falls,
         "warned_by_0_5s": early, "warned_by_0_5s_share": early / falls, "lead_median_s": 1.0, "lead_p10_s": 0.6,
         "non_falling_episodes": walks, "non_falling_minutes": walks / 6, "false_alarms": 0,
         "false_alarms_per_min": 0.0}
    return {"model": "runs/x.cal.bpk", "data": "bycause/x", "split": "test", "horizon_ms": 2000,
            "release_hold_ms": 1000, "grid": [t], "chosen": None, "max_false_alarms_per_min": 0.5}


def spread(median: float, p10: float, p90: float) -> dict:
    return {"min": p10, "p10": p10, "median": median, "p90": p90, "max": p90, "mean": median}


#: Generator 6's four causes on a test split of 40 falls (scripts/retrain/subset_by_cause.py's causes.json).
CAUSE_STATS = {"split": "test", "episodes": 70, "falls": 40, "walks": 30, "early_lead_s": 0.5, "causes": {
    "perturbation": {"falls": 20, "share_of_falls": 0.5, "cause_to_onset_s": None,
                     "event_to_onset_s": spread(1.77, 1.2, 2.3), "timed_falls": 12, "caused_0_5s_before_onset": 12},
    "collision": {"falls": 8, "share_of_falls": 0.2, "cause_to_onset_s": spread(0.85, 0.74, 1.35),
                  "event_to_onset_s": None, "timed_falls": 8, "caused_0_5s_before_onset": 8},
    "obstacle": {"falls": 7, "share_of_falls": 0.175, "cause_to_onset_s": spread(2.43, 0.26, 4.48),
                 "event_to_onset_s": None, "timed_falls": 7, "caused_0_5s_before_onset": 5},
    "push": {"falls": 5, "share_of_falls": 0.125, "cause_to_onset_s": spread(0.88, 0.45, 1.52),
             "event_to_onset_s": None, "timed_falls": 5, "caused_0_5s_before_onset": 4}}}

#: Per cause, the falls warned >= 0.5 s ahead by EMP, MP, EP and P.
EARLY = {"perturbation": (20, 20, 19, 15), "collision": (7, 5, 5, 2), "obstacle": (6, 3, 3, 1),
         "push": (1, 1, 1, 1)}
SELECTED = [("emp", "emp-pp-s1"), ("mp", "mp-pp-s1"), ("ep", "ep-pp-s1"), ("p", "p-pp-s1")]


def write_cause_reports(d: Path, with_stats: bool = True) -> None:
    d.mkdir(parents=True, exist_ok=True)
    if with_stats:
        (d / "cause-stats.json").write_text(json.dumps(CAUSE_STATS))
    for cause, early in EARLY.items():
        for (abl, _), n in zip(SELECTED, early):
            falls = CAUSE_STATS["causes"][cause]["falls"]
            (d / f"warnings-{abl}-{cause}-test.json").write_text(json.dumps(warnings_report(falls, n)))
    # The reports on the whole test split and the walking set are no causes.
    for target in ("set-test", "walk-train", "walk-test"):
        (d / f"warnings-emp-{target}.json").write_text(json.dumps(warnings_report(40, 34)))


def test_the_card_gives_every_cause_its_share_time_to_onset_and_each_networks_early_warnings(tmp_path):
    write_cause_reports(tmp_path)
    assert model_card.cause_names(tmp_path, SELECTED) == ["perturbation", "collision", "obstacle", "push"]
    rows = model_card.cause_warning_rows(tmp_path, SELECTED)
    assert rows[0] == ("| cause | test falls (share) | cause to onset, median (p10-p90) | "
                       "cause >= 0.5 s before onset | EMP warned >= 0.5 s ahead | MP warned >= 0.5 s ahead | "
                       "EP warned >= 0.5 s ahead | P warned >= 0.5 s ahead | EMP - MP |")
    assert rows[1] == "| " + " | ".join(["---"] * 9) + " |"
    assert rows[2:] == [
        "| perturbation | 20 (50%) | 1.77 s (1.20-2.30) from the event | 12/12 | 20/20 (100%) | 20/20 (100%) | "
        "19/20 (95%) | 15/20 (75%) | +0 points (+0 falls) |",
        "| collision | 8 (20%) | 0.85 s (0.74-1.35) | 8/8 | 7/8 (88%) | 5/8 (62%) | 5/8 (62%) | 2/8 (25%) | "
        "+25 points (+2 falls) |",
        "| obstacle | 7 (18%) | 2.43 s (0.26-4.48) | 5/7 | 6/7 (86%) | 3/7 (43%) | 3/7 (43%) | 1/7 (14%) | "
        "+43 points (+3 falls) |",
        "| push | 5 (12%) | 0.88 s (0.45-1.52) | 4/5 | 1/5 (20%) | 1/5 (20%) | 1/5 (20%) | 1/5 (20%) | "
        "+0 points (+0 falls) |",
    ]
    # The detailed table has every cause and network too.
    detail = model_card.cause_lead_rows(tmp_path, SELECTED)
    assert len(detail) == 2 + 4 * 4 and detail[2].startswith("| perturbation | EMP | 20/20 (100%) |")


def test_without_the_cause_statistics_the_causes_come_from_the_warnings(tmp_path):
    # Kept reports from before cause-stats.json: the causes by name, their share from the warnings' falls.
    write_cause_reports(tmp_path, with_stats=False)
    assert model_card.cause_names(tmp_path, SELECTED) == ["collision", "obstacle", "perturbation", "push"]
    rows = model_card.cause_warning_rows(tmp_path, SELECTED)
    assert rows[2].startswith("| collision | 8 (20%) | - | - | 7/8 (88%) |")
    assert rows[5].startswith("| push | 5 (12%) | - | - | 1/5 (20%) |")
    # A network without a report for a cause leaves its cell empty and the difference unsaid.
    (tmp_path / "warnings-mp-push-test.json").unlink()
    rows = model_card.cause_warning_rows(tmp_path, SELECTED)
    assert rows[5] == "| push | 5 (12%) | - | - | 1/5 (20%) | - | 1/5 (20%) | 1/5 (20%) | - |"
    assert model_card.cause_warning_rows(tmp_path / "none", SELECTED) == []


def test_the_set_statistics_give_its_falls_by_cause():
    stats = {"episodes": 100, "falling": 50, "fall_rate": 0.5, "distinct_plans": 10,
             "collision_share_of_falls": 0.24, "per_sigma": {}, "causes": {
                 "perturbation": {"falls": 23, "share_of_falls": 0.46, "episodes_with_it": 100,
                                  "cause_to_onset_s": None},
                 "collision": {"falls": 12, "share_of_falls": 0.24, "episodes_with_it": 15,
                               "cause_to_onset_s": spread(0.85, 0.74, 1.35),
                               "counterfactual_without_it": {"falls_tried": 10, "averted": 6, "moved": 2}},
                 "push": {"falls": 6, "share_of_falls": 0.12, "episodes_with_it": 11,
                          "cause_to_onset_s": spread(0.88, 0.45, 1.52)},
                 "obstacle": {"falls": 9, "share_of_falls": 0.18, "episodes_with_it": 16,
                              "cause_to_onset_s": spread(2.43, 0.26, 4.48)}}}
    rows = model_card.stats_rows(stats, "Training set")
    assert rows[0].endswith("10 plans, falls by cause below.")
    i = rows.index("| cause | episodes with it | falls | share of falls | cause to onset, median (p10-p90) | "
                   "without it: averted or moved |")
    assert rows[i + 2:i + 6] == ["| perturbation | 100 | 23 | 46% | - | - |",
                                 "| collision | 15 | 12 | 24% | 0.85 s (0.74-1.35) | 8 / 10 |",
                                 "| obstacle | 16 | 9 | 18% | 2.43 s (0.26-4.48) | - |",
                                 "| push | 11 | 6 | 12% | 0.88 s (0.45-1.52) | - |"]
    # Generator 5's statistics name the ball's share only.
    del stats["causes"]
    assert model_card.stats_rows(stats, "Training set")[0].endswith("collision share of falls 0.24.")


def test_the_card_has_every_cause_of_the_data(tmp_path, monkeypatch):
    reports, keep = tmp_path / "reports", tmp_path / "keep"
    write_cause_reports(reports)
    (reports / "selected.txt").write_text("".join(f"{a} {n} 0.1\n" for a, n in SELECTED))
    for cause in EARLY:
        write_eval(reports, f"emp-pp-{cause}", report(["runs/emp-pp-s1.cal.bpk"], {1000.0: [0.9]}))
    out = tmp_path / "tables.md"
    monkeypatch.setattr(sys, "argv", ["model_card.py", "--reports", str(reports), "--keep", str(keep),
                                      "--out", str(out)])
    assert model_card.main() == 0
    card = out.read_text()
    assert (keep / "reports" / "cause-stats.json").is_file()
    for cause in EARLY:
        assert f"| {cause} | EMP (paper-trained) | 0.900 +- 0.000 |" in card
        assert f"| {cause} | {CAUSE_STATS['causes'][cause]['falls']} (" in card
    assert "### What each network warns, by fall cause" in card


def held_report(held: float, minutes: float, out_of_range: float | None = None) -> dict:
    row = {"non_falling_minutes": minutes, "held_minutes": held, "false_alarms": 1}
    if out_of_range is not None:
        row["out_of_range_share"] = out_of_range
    return {"grid": [row]}


def test_time_held_is_given_per_set_and_missing_figures_say_so(tmp_path):
    d = tmp_path
    (d / "warnings-mp-walk-train.json").write_text(json.dumps(held_report(0.5, 10.0)))
    (d / "warnings-mp-walk-test.json").write_text(json.dumps(held_report(0.1, 10.0)))
    (d / "warnings-mp-set-test.json").write_text(json.dumps(held_report(0.2, 4.0, 0.004)))
    (d / "warnings-mp-real-test.json").write_text(json.dumps(held_report(0.56, 0.56, 0.9)))
    # Written before time held existed: no figure, a dash.
    (d / "warnings-p-set-test.json").write_text(json.dumps({"grid": [{"non_falling_minutes": 4.0}]}))
    rows = model_card.time_held_rows(d, [("mp", "mp-pp-s1"), ("p", "p-pp-s1"), ("emp", "emp-pp-s1")])
    mp = next(r for r in rows if r.startswith("| MP"))
    assert "| 3.0% (0.60 of 20.0 min) | 5.0% (0.20 of 4.0 min) | 100.0% (0.56 of 0.6 min) | 0.4% / 90.0% |" in mp
    p = next(r for r in rows if r.startswith("| P"))
    assert p == "| P (p-pp-s1) | - | - | - | - |"
    assert not any(r.startswith("| EMP") for r in rows), "no report, no row"


def test_calibration_is_tabled_under_both_protocols(tmp_path):
    def proto(name: str, ece: float) -> dict:
        return {"protocol": name, "horizons": [
            {"horizon_ms": 500.0, "ece_ci95": [{"ece": ece, "lower": ece - 0.01, "upper": ece + 0.01, "floor": 0.02}]}]}
    runs = tmp_path / "runs"
    runs.mkdir()
    (runs / "emp-pp--emp-pp-s3.json").write_text(json.dumps(
        {"protocols": [proto("paper", 0.035), proto("deployment", 0.231)]}))
    # A run written after part of its epochs is kept under its run's group.
    (runs / "ep-pp--ep5-pp-s1.json").write_text(json.dumps({"protocols": [proto("paper", 0.075)]}))
    # Its record on a subset of the test split is not its calibration.
    (runs / "ep-pp-collision--ep5-pp-s1.json").write_text(json.dumps({"protocols": [proto("paper", 0.5)]}))
    rows = model_card.calibration_rows(tmp_path, [("emp", "emp-pp-s3"), ("mp", "mp-pp-s1"), ("ep", "ep5-pp-s1")])
    assert "| EMP (emp-pp-s3) | paper | 0.035 [0.025, 0.045], floor 0.020 |" in rows
    assert "| EMP (emp-pp-s3) | deployment | 0.231 [0.221, 0.241], floor 0.020 |" in rows
    assert "| EP (ep5-pp-s1) | paper | 0.075 [0.065, 0.085], floor 0.020 |" in rows
    assert not any("MP (mp-pp-s1)" in r for r in rows)


def grid_entry(trigger: float, warned_early: int, alarms_per_min: float, held: float, falls: int = 20) -> dict:
    return {"trigger": trigger, "release": trigger - 0.3, "falling_episodes": falls, "warned_by_0_5s": warned_early,
            "false_alarms_per_min": alarms_per_min, "held_share": held}


def test_the_trade_table_gives_the_cost_of_each_share_of_warned_falls(tmp_path):
    grid = [grid_entry(0.4, 20, 6.0, 0.8), grid_entry(0.6, 19, 2.5, 0.3), grid_entry(0.7, 18, 0.5, 0.05),
            grid_entry(0.8, 16, 0.0, 0.0), grid_entry(0.9, 12, 0.0, 0.0)]
    (tmp_path / "emp-thresholds.json").write_text(json.dumps(
        {"grid": grid, "chosen": grid[3], "max_false_alarms_per_min": 0.1}))
    # A network whose grid never reaches 95%.
    low = [grid_entry(0.4, 18, 7.0, 1.0), grid_entry(0.8, 15, 0.0, 0.0)]
    (tmp_path / "mp-thresholds.json").write_text(json.dumps(
        {"grid": low, "chosen": low[1], "max_false_alarms_per_min": 0.1}))
    rows = model_card.trade_rows(tmp_path, [("emp", "emp-s1"), ("mp", "mp-s1"), ("p", "p-s1")])
    assert rows[2:] == [
        "| EMP | chosen (<= 0.1 / min) | 0.80 / 0.50 | 16/20 (80%) | 0.00 | 0.0% |",
        # 80% is the chosen pair itself; 90% needs the trigger down to 0.7 (the highest that reaches it).
        "| EMP | >= 80% warned | 0.80 / 0.50 | 16/20 (80%) | 0.00 | 0.0% |",
        "| EMP | >= 90% warned | 0.70 / 0.40 | 18/20 (90%) | 0.50 | 5.0% |",
        "| EMP | >= 95% warned | 0.60 / 0.30 | 19/20 (95%) | 2.50 | 30.0% |",
        "| MP | chosen (<= 0.1 / min) | 0.80 / 0.50 | 15/20 (75%) | 0.00 | 0.0% |",
        "| MP | >= 80% warned | 0.40 / 0.10 | 18/20 (90%) | 7.00 | 100.0% |",
        "| MP | >= 90% warned | 0.40 / 0.10 | 18/20 (90%) | 7.00 | 100.0% |",
        "| MP | >= 95% warned | none of the grid | - | - | - |",
    ]
    assert model_card.trade_rows(tmp_path / "none", [("emp", "emp-s1")]) == []
