//! What `/diagnostics` says, decided from the figures the tick loop
//! gathers (`pipeline/tick.rs`, `TickLoop::diagnostics`): each stream's
//! level, message and key-values ([`stream_diagnostics`]), the model's
//! level and message ([`model_level`]), and the out-of-range guard's
//! status ([`inputs_diagnostics`]). Everything here is a pure function of
//! plain values, tested without a daemon.

use crate::streams::StreamStatsSnapshot;

use super::{DiagnosticLevel, InputsDiagnostics, StreamDiagnostics, ERROR_WINDOW_S};

/// One stream's figures at a snapshot.
#[derive(Debug, Clone)]
pub struct StreamFigures<'a> {
    /// "joints", "camera" or "plan".
    pub stream: &'static str,
    pub source: String,
    pub configured: bool,
    /// Its staleness bound, ns.
    pub stale_ns: i64,
    pub stats: &'a StreamStatsSnapshot,
    /// Admitted samples per second over the period.
    pub rate_hz: f64,
    /// Age of the latest tick's value, ns (none: never had one).
    pub age_ns: Option<i64>,
    /// Errors and rejections in the last [`ERROR_WINDOW_S`] seconds.
    pub recent_errors: u64,
    pub recent_rejected: u64,
    /// Joints only: never read; older than the bound (name, age ns).
    pub unread: Vec<String>,
    pub stale: Vec<(String, i64)>,
    pub n_joints: usize,
    /// Joints only: their gaps.
    pub gaps: Option<JointGapFigures>,
}

/// The joints' gaps: how many were bridged on held values, how many waited
/// out, the ticks of the window that were not fresh (bridged ones while the
/// forecast is valid), the last stale tick and its joints.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct JointGapFigures {
    pub stale_ticks_in_window: usize,
    pub max_held_ticks: usize,
    pub bridged: u64,
    pub refilled: u64,
    pub last_stale: String,
}

/// A stream's status.
pub fn stream_diagnostics(f: StreamFigures<'_>) -> StreamDiagnostics {
    // Why samples were refused, appended to a STALE message: a
    // stream that is stale because every sample is rejected says so.
    let rejected_note = if f.recent_rejected > 0 {
        format!(
            "; {} samples rejected in the last {ERROR_WINDOW_S} s (last: {})",
            f.recent_rejected, f.stats.last_rejection
        )
    } else {
        String::new()
    };
    let n_joints = f.n_joints;
    let (level, message) = if !f.configured {
        (DiagnosticLevel::Ok, "not configured".to_string())
    } else {
        match f.age_ns {
            None => (
                DiagnosticLevel::Stale,
                format!("no sample yet{rejected_note}"),
            ),
            // Some joints older than the bound, the others read.
            Some(_) if !f.stale.is_empty() && f.stale.len() < n_joints => (
                DiagnosticLevel::Stale,
                format!(
                    "stale: {} of {n_joints} joints older than {} ms: {}",
                    f.stale.len(),
                    f.stale_ns / 1_000_000,
                    stale_joints_text(&f.stale, n_joints)
                ),
            ),
            Some(age) if age > f.stale_ns => (
                DiagnosticLevel::Stale,
                format!(
                    "stale: last sample {} ms old (limit {} ms){rejected_note}",
                    age / 1_000_000,
                    f.stale_ns / 1_000_000
                ),
            ),
            Some(_) if !f.unread.is_empty() => (
                DiagnosticLevel::Warn,
                format!(
                    "{} of {n_joints} joints not read: {}",
                    f.unread.len(),
                    f.unread.join(", ")
                ),
            ),
            Some(_) if f.recent_rejected > 0 => (
                DiagnosticLevel::Warn,
                format!(
                    "{} samples rejected in the last {ERROR_WINDOW_S} s (last: {})",
                    f.recent_rejected, f.stats.last_rejection
                ),
            ),
            Some(_) if f.recent_errors > 0 => (
                DiagnosticLevel::Warn,
                format!("{} errors in the last {ERROR_WINDOW_S} s", f.recent_errors),
            ),
            Some(_) => (DiagnosticLevel::Ok, "ok".to_string()),
        }
    };
    let mut details: Vec<(String, String)> = f
        .stats
        .error_kinds
        .iter()
        .map(|(k, n)| (format!("errors.{k}"), n.to_string()))
        .collect();
    details.extend(rejection_details(f.stats, f.recent_rejected));
    details.extend(f.stats.details.iter().cloned());
    if !f.stats.state.is_empty() {
        details.push(("state".to_string(), f.stats.state.clone()));
    }
    if let Some(gaps) = &f.gaps {
        details.push(("joints_not_read".to_string(), f.unread.join(",")));
        let stale: Vec<&str> = f.stale.iter().map(|(n, _)| n.as_str()).collect();
        details.push(("joints_stale".to_string(), stale.join(",")));
        details.extend([
            (
                "stale_ticks_in_window".to_string(),
                gaps.stale_ticks_in_window.to_string(),
            ),
            (
                "max_held_ticks".to_string(),
                gaps.max_held_ticks.to_string(),
            ),
            ("gaps_bridged".to_string(), gaps.bridged.to_string()),
            ("gaps_refilled".to_string(), gaps.refilled.to_string()),
            ("last_stale".to_string(), gaps.last_stale.clone()),
        ]);
    }
    StreamDiagnostics {
        stream: f.stream,
        source: f.source,
        level,
        message,
        rate_hz: f.rate_hz,
        last_sample_age_ms: f.age_ns.map(|a| a as f64 / 1e6),
        errors: f.stats.errors,
        recent_errors: f.recent_errors,
        details,
    }
}

/// What decides the model status.
#[derive(Debug, Clone)]
pub struct ModelFigures<'a> {
    /// Inference errors since the last snapshot.
    pub errors: u64,
    /// The latest tick's validity as the tick loop judged it, and why not.
    pub valid: bool,
    pub reason: String,
    /// The out-of-range guard after the latest forecast.
    pub guard: &'a GuardState,
    /// The network running; the best one the configured streams allow.
    pub active: &'static str,
    pub expected: Option<&'static str>,
    /// The overload policy: networks set aside, its last decision, ticks
    /// within budget before the next retry.
    pub set_aside: Vec<&'static str>,
    pub overload_last: Option<String>,
    pub retry_in_ticks: Option<usize>,
    /// The configured streams, for a message (`joints, plan`).
    pub configured_streams: String,
}

/// The model status's level and message, and the validity it reports (the
/// guard under `hold` makes a forecast the tick loop judged valid not
/// valid, on the inference thread).
pub fn model_level(m: &ModelFigures<'_>) -> (DiagnosticLevel, String, bool, String) {
    let held = m.valid && m.guard.holds && !m.guard.out_of_range.is_empty();
    let (last_valid, last_reason) = if held {
        (false, m.guard.sentence())
    } else {
        (m.valid, m.reason.clone())
    };
    let errors = m.errors;
    let (level, message) = if errors > 0 && !last_valid {
        (
            DiagnosticLevel::Error,
            format!("{errors} inference errors; {last_reason}"),
        )
    } else if !last_valid {
        (
            DiagnosticLevel::Warn,
            format!("forecast not valid: {last_reason}"),
        )
    } else if !m.set_aside.is_empty() {
        (
            DiagnosticLevel::Warn,
            format!(
                "overloaded: running {} ({} set aside: inference missed its budget of one tick persistently; {}); tried again after {} ticks within budget",
                m.active,
                m.set_aside.join(", "),
                m.overload_last.clone().unwrap_or_default(),
                m.retry_in_ticks.unwrap_or(0)
            ),
        )
    } else if Some(m.active) != m.expected {
        (
            DiagnosticLevel::Warn,
            format!(
                "degraded: running {} ({} needs a stream that is lost)",
                m.active,
                m.expected.unwrap_or("?")
            ),
        )
    } else if m.active != "EMP" {
        // What the config asked for (camera = "none", plan = "none").
        (
            DiagnosticLevel::Ok,
            format!(
                "ok: running {} (the configured streams: {})",
                m.active, m.configured_streams
            ),
        )
    } else {
        (DiagnosticLevel::Ok, "ok".to_string())
    };
    (level, message, last_valid, last_reason)
}

/// Names at most this many inputs in a message before "and N more".
const NAMED: usize = 3;

/// One input outside its range now.
#[derive(Debug, Clone, PartialEq)]
pub struct OutOfRangeInput {
    /// Its name: a joint, `plan of <joint>`, `camera brightness`, `camera contrast`.
    pub input: String,
    /// `"bust_x 36.2 deg, 31.4 deg above its trained range -4.1..4.8 deg"`.
    pub detail: String,
    /// Tick time its excursion began, ns.
    pub since_ns: i64,
}

/// The out-of-range guard's state (`pipeline/guard.rs`), for `/diagnostics`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GuardState {
    /// The inputs outside their ranges in the latest forecast window,
    /// largest excursion first.
    pub out_of_range: Vec<OutOfRangeInput>,
    /// Forecast windows with an input outside its range, since start.
    pub windows_out_of_range: u64,
    /// Forecast windows judged, since start.
    pub windows: u64,
    /// Where the ranges come from (the active network's).
    pub bounds: String,
    /// `[model].out_of_range = "hold"`: such a window is not valid.
    pub holds: bool,
}

impl GuardState {
    /// `[model].out_of_range`'s value.
    pub fn policy(&self) -> &'static str {
        if self.holds {
            "hold"
        } else {
            "forecast"
        }
    }

    /// `"inputs outside the training range: bust_x 36.2 deg, 31.4 deg
    /// above its trained range -4.1..4.8 deg (since t=2.000 s); ... and 3
    /// more"`.
    pub fn sentence(&self) -> String {
        let out = &self.out_of_range;
        let mut parts: Vec<String> = out
            .iter()
            .take(NAMED)
            .map(|o| format!("{} (since t={:.3} s)", o.detail, o.since_ns as f64 / 1e9))
            .collect();
        if out.len() > NAMED {
            parts.push(format!("and {} more", out.len() - NAMED));
        }
        format!("inputs outside the training range: {}", parts.join("; "))
    }
}

/// `fall_guard: inputs`: OK while the window lies inside the ranges the
/// network was trained on, WARN naming each input outside them.
pub fn inputs_diagnostics(guard: &GuardState) -> InputsDiagnostics {
    let since = guard.out_of_range.iter().map(|o| o.since_ns).min();
    let values = vec![
        (
            "out_of_range".to_string(),
            guard
                .out_of_range
                .iter()
                .map(|o| o.input.as_str())
                .collect::<Vec<_>>()
                .join(","),
        ),
        (
            "since_s".to_string(),
            since.map_or_else(String::new, |s| format!("{:.3}", s as f64 / 1e9)),
        ),
        (
            "windows_out_of_range".to_string(),
            guard.windows_out_of_range.to_string(),
        ),
        ("windows".to_string(), guard.windows.to_string()),
        ("policy".to_string(), guard.policy().to_string()),
        ("bounds".to_string(), guard.bounds.clone()),
    ];
    let (level, message) = if guard.windows == 0 {
        (DiagnosticLevel::Ok, "no forecast window yet".to_string())
    } else if guard.out_of_range.is_empty() {
        (
            DiagnosticLevel::Ok,
            "inside the ranges the network was trained on".to_string(),
        )
    } else {
        let action = if guard.holds {
            "forecasts not valid, fall_imminent asserted ([model].out_of_range = \"hold\")"
        } else {
            "forecasting on the inputs held to their bounds ([model].out_of_range = \"forecast\")"
        };
        (
            DiagnosticLevel::Warn,
            format!("{}; {action}", guard.sentence()),
        )
    };
    InputsDiagnostics {
        level,
        message,
        values,
    }
}

/// The joints of [`stale_joints`] for a message: `head_z 140 ms, abs_x 120
/// ms`, or `all 25 joints` when every joint is.
pub fn stale_joints_text(stale: &[(String, i64)], n_joints: usize) -> String {
    if stale.len() == n_joints {
        return format!("all {n_joints} joints");
    }
    stale
        .iter()
        .map(|(n, age)| format!("{n} {} ms", age / 1_000_000))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The boundary's rejections of one stream as diagnostic key-values:
/// `rejected` (total), `rejected_in_window`, `rejected_per_s` (over the
/// window), `rejected_<reason>` (total per reason seen) and
/// `last_rejection` (empty before the first).
pub fn rejection_details(stats: &StreamStatsSnapshot, recent: u64) -> Vec<(String, String)> {
    let mut out = vec![
        ("rejected".to_string(), stats.rejected.to_string()),
        ("rejected_in_window".to_string(), recent.to_string()),
        (
            "rejected_per_s".to_string(),
            format!("{:.2}", recent as f64 / ERROR_WINDOW_S as f64),
        ),
    ];
    out.extend(
        stats
            .rejections
            .iter()
            .map(|(k, n)| (format!("rejected_{k}"), n.to_string())),
    );
    out.push(("last_rejection".to_string(), stats.last_rejection.clone()));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn guard(holds: bool, out: bool) -> GuardState {
        GuardState {
            out_of_range: if out {
                vec![OutOfRangeInput {
                    input: "abs_x".into(),
                    detail: "abs_x 36.4 deg, 24.5 deg above its trained range -8.9..11.9 deg"
                        .into(),
                    since_ns: 3_967_000_000,
                }]
            } else {
                Vec::new()
            },
            windows_out_of_range: u64::from(out),
            windows: 10,
            bounds: "measured on the train split of simv6".into(),
            holds,
        }
    }

    fn model(guard: &GuardState) -> ModelFigures<'_> {
        ModelFigures {
            errors: 0,
            valid: true,
            reason: String::new(),
            guard,
            active: "EMP",
            expected: Some("EMP"),
            set_aside: Vec::new(),
            overload_last: None,
            retry_in_ticks: None,
            configured_streams: "joints, camera, plan".into(),
        }
    }

    #[test]
    fn the_model_status_says_what_holds_the_forecast() {
        let calm = guard(true, false);
        assert_eq!(model_level(&model(&calm)).0, DiagnosticLevel::Ok);
        let out = guard(true, true);
        let (level, message, valid, reason) = model_level(&model(&out));
        assert_eq!(level, DiagnosticLevel::Warn);
        assert!(!valid);
        assert!(
            message.starts_with("forecast not valid: inputs outside the training range: abs_x"),
            "{message}"
        );
        assert!(reason.ends_with("(since t=3.967 s)"), "{reason}");
        // Forecasting anyway: valid, the model status OK.
        let anyway = guard(false, true);
        let (level, _, valid, _) = model_level(&model(&anyway));
        assert_eq!((level, valid), (DiagnosticLevel::Ok, true));
        let inputs = inputs_diagnostics(&anyway);
        assert_eq!(inputs.level, DiagnosticLevel::Warn);
        assert!(
            inputs.message.contains("\"forecast\""),
            "{}",
            inputs.message
        );
        // Overload: a lighter network, and why.
        let mut m = model(&calm);
        m.active = "MP";
        m.set_aside = vec!["EMP"];
        m.retry_in_ticks = Some(120);
        let (level, message, _, _) = model_level(&m);
        assert_eq!(level, DiagnosticLevel::Warn);
        assert!(
            message.starts_with("overloaded: running MP (EMP set aside"),
            "{message}"
        );
        assert!(
            message.ends_with("tried again after 120 ticks within budget"),
            "{message}"
        );
    }

    #[test]
    fn a_stale_joint_is_named_with_its_age() {
        let stats = StreamStatsSnapshot::default();
        let s = stream_diagnostics(StreamFigures {
            stream: "joints",
            source: "replay".into(),
            configured: true,
            stale_ns: 150_000_000,
            stats: &stats,
            rate_hz: 50.0,
            age_ns: Some(160_000_000),
            recent_errors: 0,
            recent_rejected: 0,
            unread: Vec::new(),
            stale: vec![("head_z".into(), 160_000_000)],
            n_joints: 25,
            gaps: Some(JointGapFigures::default()),
        });
        assert_eq!(s.level, DiagnosticLevel::Stale);
        assert_eq!(
            s.message,
            "stale: 1 of 25 joints older than 150 ms: head_z 160 ms"
        );
        assert!(s
            .details
            .contains(&("joints_stale".into(), "head_z".into())));
    }
}
