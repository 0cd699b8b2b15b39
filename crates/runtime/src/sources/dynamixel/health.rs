//! The servo buses' health and readings as the joint stream has them:
//! each reading becomes one `Sample::Joints` ([`joints_sample`]), and
//! every 500 ms the bus counters become a [`DeviceDiagnostics`] per bus
//! ([`ServoHealth`]) and the stream's key-values ([`servo_details`]).
//!
//! A reading in which some motors did not answer becomes a sample too,
//! with NaN for those joints: `/joint_states` then carries the joints that
//! were read, and the tick keeps each missing joint's last value while it
//! is younger than `[streams].joints_stale_ms` (`pipeline/tick.rs`). Each
//! position goes with its own read stamp, so its age is its bus's.
//!
//! A bus status names: port, adapter mode, read rate, missing ids and
//! joints, per motor the age of its last position and its share of missed
//! reads, error rates over the last [`ERROR_WINDOW_S`] seconds, reopens,
//! the last error. A motor missing in more than
//! `[dynamixel].warn_missed_share` of the window's cycles is named at WARN.
//! The level is judged on the window, so it returns to OK once the fault is
//! gone; a plain (non-USB2AX) adapter is a mode, not a fault.

use super::{BusStatsSnapshot, JointReading, ServoStatsSnapshot};
use crate::streams::sample::Sample;
use crate::streams::{CounterWindow, DeviceDiagnostics, DiagnosticLevel, ERROR_WINDOW_S};

/// Bus counters as the joints stream's key-values, and their error total
/// (faults only: the probe that finds a plain adapter is not one).
pub fn servo_details(snapshot: &ServoStatsSnapshot) -> (u64, Vec<(String, String)>) {
    let mut details = vec![
        ("cycles".to_string(), snapshot.cycles.to_string()),
        (
            "complete_cycles".to_string(),
            snapshot.complete_cycles.to_string(),
        ),
    ];
    let mut errors = 0;
    for bus in &snapshot.buses {
        let servo_errors: u64 = bus.servo_errors.iter().map(|(_, n)| n).sum();
        // Every skipped garbage byte counts as one error.
        errors += bus.fault_errors() + bus.garbage_bytes;
        let b = &bus.name;
        details.extend([
            (format!("{b}.port"), bus.port.clone()),
            (format!("{b}.connected"), bus.connected.to_string()),
            (format!("{b}.sync_read"), bus.sync_read_active.to_string()),
            (format!("{b}.timeouts"), bus.timeouts.to_string()),
            (format!("{b}.bad_checksums"), bus.bad_checksums.to_string()),
            (format!("{b}.bad_packets"), bus.bad_packets.to_string()),
            (format!("{b}.garbage_bytes"), bus.garbage_bytes.to_string()),
            (format!("{b}.lost_replies"), bus.lost_replies.to_string()),
            (format!("{b}.servo_errors"), servo_errors.to_string()),
            (format!("{b}.missing_ids"), format!("{:?}", bus.missing_ids)),
            (format!("{b}.reopens"), bus.reopens.to_string()),
        ]);
    }
    (errors, details)
}

/// How a bus status is judged besides its counters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BusJudgement {
    /// The clock now (the readings' clock), ns: the age of each motor's
    /// last position is taken from it.
    pub now_ns: i64,
    /// `[dynamixel].warn_missed_share`.
    pub warn_missed_share: f64,
}

/// Per motor of `now`: its share of the cycles in the window in which it
/// gave no position (`None` when the window holds no cycle).
fn missed_shares(now: &BusStatsSnapshot, base: Option<&BusStatsSnapshot>) -> Vec<Option<f64>> {
    let cycles = now.cycles.saturating_sub(base.map_or(0, |b| b.cycles));
    (0..now.motors.len())
        .map(|i| {
            let missed = now.motor_missed.get(i).copied().unwrap_or(0);
            let before = base
                .and_then(|b| b.motor_missed.get(i).copied())
                .unwrap_or(0);
            (cycles > 0).then(|| missed.saturating_sub(before) as f64 / cycles as f64)
        })
        .collect()
}

/// The status of one bus from its counters now and at the start of the
/// window (`base`, `None`: the reader's start, all zeros), `window_s`
/// seconds apart.
pub fn bus_status(
    now: &BusStatsSnapshot,
    base: Option<&BusStatsSnapshot>,
    window_s: f64,
    judgement: BusJudgement,
) -> DeviceDiagnostics {
    let delta = |f: fn(&BusStatsSnapshot) -> u64| f(now).saturating_sub(base.map_or(0, f));
    let per_s = |n: u64| {
        if window_s > 0.0 {
            format!("{:.2}", n as f64 / window_s)
        } else {
            "none".to_string()
        }
    };
    let timeouts = delta(|b| b.timeouts.saturating_sub(b.sync_probe_timeouts));
    let checksums = delta(|b| b.bad_checksums);
    let packets = delta(|b| b.bad_packets);
    let garbage = delta(|b| b.garbage_bytes);
    let lost = delta(|b| b.lost_replies);
    let servo = delta(|b| b.servo_errors.iter().map(|(_, n)| n).sum());
    let io = delta(|b| b.io_errors);
    let reopens = delta(|b| b.reopens);
    let open_failures = delta(|b| b.open_failures);
    let cycles = delta(|b| b.cycles);
    let ok_cycles = delta(|b| b.ok_cycles);
    let read_rate = if window_s > 0.0 {
        cycles as f64 / window_s
    } else {
        0.0
    };
    let missing_joints = now.missing_joints();
    let missing_named: Vec<String> = now
        .missing_ids
        .iter()
        .zip(&missing_joints)
        .map(|(id, name)| format!("{id} ({name})"))
        .collect();
    let last_error = now.last_error.clone().unwrap_or_default();
    let window = ERROR_WINDOW_S;
    let shares = missed_shares(now, base);
    // Motors whose reads fail persistently: named even while the forecast
    // holds their last values and stays valid.
    let failing: Vec<(String, f64)> = now
        .motors
        .iter()
        .zip(&shares)
        .filter_map(|((id, name), share)| {
            share
                .filter(|&s| s > judgement.warn_missed_share)
                .map(|s| (format!("{id} ({name})"), s))
        })
        .collect();
    let mut faults: Vec<String> = [
        (timeouts, "timeouts"),
        (checksums, "bad checksums"),
        (packets, "bad packets"),
        (garbage, "garbage bytes"),
        (lost, "lost replies (asked again)"),
        (servo, "servo error bits"),
        (io, "port errors"),
        (reopens, "reopens"),
    ]
    .iter()
    .filter(|(n, _)| *n > 0)
    .map(|(n, what)| format!("{n} {what}"))
    .collect();
    if open_failures > 0 && now.connected {
        faults.push(format!("{open_failures} failed opens"));
    }
    let (level, message) = if !now.connected {
        let why = if last_error.is_empty() {
            "not opened yet".to_string()
        } else {
            last_error.clone()
        };
        (
            DiagnosticLevel::Error,
            format!("port {} not open: {why}", now.port),
        )
    } else if !now.motors.is_empty() && now.missing_ids.len() == now.motors.len() {
        (
            DiagnosticLevel::Error,
            format!("no motor answers ({} configured)", now.motors.len()),
        )
    } else if !failing.is_empty() || !missing_named.is_empty() || !faults.is_empty() {
        let mut parts = Vec::new();
        if !failing.is_empty() {
            parts.push(format!(
                "reads failing persistently (more than {:.0}% of the cycles of the last {window} s missed): {}",
                judgement.warn_missed_share * 100.0,
                failing
                    .iter()
                    .map(|(m, share)| format!("{m} {:.0}%", share * 100.0))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        if !missing_named.is_empty() {
            parts.push(format!(
                "{} of {} motors not answering: {}",
                missing_named.len(),
                now.motors.len(),
                missing_named.join(", ")
            ));
        }
        if !faults.is_empty() {
            parts.push(format!("in the last {window} s: {}", faults.join(", ")));
        }
        (DiagnosticLevel::Warn, parts.join("; "))
    } else {
        (
            DiagnosticLevel::Ok,
            format!(
                "ok: {} motors at {read_rate:.1} Hz ({})",
                now.motors.len(),
                now.adapter_mode()
            ),
        )
    };
    let servo_total: u64 = now.servo_errors.iter().map(|(_, n)| n).sum();
    let values = vec![
        ("port", now.port.clone()),
        ("adapter_mode", now.adapter_mode().to_string()),
        ("connected", now.connected.to_string()),
        (
            "ids",
            format!("{:?}", now.motors.iter().map(|m| m.0).collect::<Vec<_>>()),
        ),
        ("read_rate_hz", format!("{read_rate:.1}")),
        (
            "complete_rate_hz",
            if window_s > 0.0 {
                format!("{:.1}", ok_cycles as f64 / window_s)
            } else {
                "none".to_string()
            },
        ),
        ("missing_ids", format!("{:?}", now.missing_ids)),
        ("missing_joints", missing_joints.join(",")),
        ("error_window_s", window.to_string()),
        ("timeouts_per_s", per_s(timeouts)),
        ("checksum_errors_per_s", per_s(checksums)),
        ("bad_packets_per_s", per_s(packets)),
        ("garbage_bytes_per_s", per_s(garbage)),
        ("lost_replies_per_s", per_s(lost)),
        ("servo_errors_per_s", per_s(servo)),
        ("reopens_in_window", reopens.to_string()),
        ("timeouts", now.timeouts.to_string()),
        ("bad_checksums", now.bad_checksums.to_string()),
        ("bad_packets", now.bad_packets.to_string()),
        ("garbage_bytes", now.garbage_bytes.to_string()),
        ("lost_replies", now.lost_replies.to_string()),
        ("servo_errors", servo_total.to_string()),
        ("reopens", now.reopens.to_string()),
        ("open_failures", now.open_failures.to_string()),
        ("last_error", last_error),
        (
            "warn_missed_share",
            format!("{}", judgement.warn_missed_share),
        ),
        (
            "failing_motors",
            failing
                .iter()
                .map(|(m, _)| m.as_str())
                .collect::<Vec<_>>()
                .join(", "),
        ),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect::<Vec<(String, String)>>();
    // Per motor: the age of its last position and its share of missed reads
    // over the window.
    let mut values = values;
    for (i, (_, name)) in now.motors.iter().enumerate() {
        let age = now
            .motor_last_read_ns
            .get(i)
            .copied()
            .flatten()
            .map_or_else(
                || "never".to_string(),
                |t| format!("{:.0}", (judgement.now_ns - t).max(0) as f64 / 1e6),
            );
        let share = shares[i].map_or_else(|| "none".to_string(), |s| format!("{s:.3}"));
        values.push((format!("age_ms.{name}"), age));
        values.push((format!("missed_share.{name}"), share));
    }
    DeviceDiagnostics {
        name: format!("servo bus {}", now.name),
        hardware_id: now.port.clone(),
        level,
        message,
        values,
    }
}

/// Bus statuses judged over a sliding window of counter snapshots.
#[derive(Debug)]
pub struct ServoHealth {
    /// (seconds since the reader started, counters), oldest first; the
    /// first entry is the newest one at or before the window's start.
    history: CounterWindow<f64, ServoStatsSnapshot>,
    /// `[dynamixel].warn_missed_share`.
    warn_missed_share: f64,
}

impl ServoHealth {
    /// Bus statuses that name a motor missing in more than
    /// `warn_missed_share` of the window's cycles.
    pub fn new(warn_missed_share: f64) -> ServoHealth {
        ServoHealth {
            history: CounterWindow::default(),
            warn_missed_share,
        }
    }

    /// Add the counters at `t_s` seconds after the reader started (non-
    /// decreasing), the readings' clock being at `now_ns`, and return one
    /// status per bus.
    pub fn update(
        &mut self,
        t_s: f64,
        now_ns: i64,
        snapshot: ServoStatsSnapshot,
    ) -> Vec<DeviceDiagnostics> {
        let judgement = BusJudgement {
            now_ns,
            warn_missed_share: self.warn_missed_share,
        };
        let window = ERROR_WINDOW_S as f64;
        self.history.push(t_s, window, snapshot);
        let (base_t, base) = match self.history.window_start(t_s, window) {
            Some((t, s)) => (*t, Some(s)),
            // Less than a window since the start: count from the start.
            None => (0.0, None),
        };
        let Some(now) = self.history.latest() else {
            return Vec::new();
        };
        now.buses
            .iter()
            .enumerate()
            .map(|(i, bus)| {
                bus_status(
                    bus,
                    base.and_then(|b| b.buses.get(i)),
                    (t_s - base_t).max(0.0),
                    judgement,
                )
            })
            .collect()
    }
}

/// A reading as the joints stream's sample: NaN for a joint not read this
/// cycle (the tick names it once its held value is too old), and each
/// position's own stamp (`read_ns`: its bus's sync read, or the retry that
/// got it), so that a joint's age at a tick is the age of its value, not
/// of the cycle's start; the sample's stamp is the reading's, its newest.
pub fn joints_sample(reading: &JointReading) -> Sample {
    let positions_rad = reading
        .positions_rad
        .iter()
        .map(|p| p.unwrap_or(f32::NAN))
        .collect();
    let read_ns = reading
        .read_ns
        .iter()
        .map(|t| t.unwrap_or(reading.stamp_ns))
        .collect();
    Sample::Joints {
        stamp_ns: reading.stamp_ns,
        positions_rad,
        read_ns: Some(read_ns),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const JUDGE: BusJudgement = BusJudgement {
        now_ns: 0,
        warn_missed_share: 0.2,
    };

    fn bus(connected: bool) -> BusStatsSnapshot {
        BusStatsSnapshot {
            name: "upper".into(),
            port: "/dev/ttyACM1".into(),
            connected,
            sync_read_active: true,
            cycles: 0,
            ok_cycles: 0,
            timeouts: 0,
            bad_checksums: 0,
            bad_packets: 0,
            garbage_bytes: 0,
            lost_replies: 0,
            servo_errors: Vec::new(),
            missing_motor_reads: 0,
            missing_ids: Vec::new(),
            io_errors: 0,
            reopens: 0,
            open_failures: 0,
            sync_probe_timeouts: 0,
            last_ok_ns: None,
            motors: vec![(36, "head_z".into()), (37, "head_y".into())],
            motor_missed: vec![0, 0],
            motor_last_read_ns: vec![None, None],
            sync_read_configured: true,
            last_error: None,
        }
    }

    fn value<'a>(d: &'a DeviceDiagnostics, key: &str) -> &'a str {
        d.values
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
            .unwrap_or_else(|| panic!("no {key} in {:?}", d.values))
    }

    fn snapshot(b: BusStatsSnapshot) -> ServoStatsSnapshot {
        ServoStatsSnapshot {
            running: true,
            cycles: b.cycles,
            complete_cycles: b.ok_cycles,
            last_complete_ns: None,
            buses: vec![b],
        }
    }

    #[test]
    fn a_reading_becomes_one_sample_with_each_position_s_own_stamp() {
        let reading = JointReading {
            stamp_ns: 1_012,
            positions_rad: vec![Some(0.5), None, Some(-0.25)],
            read_ns: vec![Some(1_000), None, Some(1_012)],
        };
        let Sample::Joints {
            stamp_ns,
            positions_rad,
            read_ns,
        } = joints_sample(&reading)
        else {
            panic!("not a joints sample");
        };
        assert_eq!(stamp_ns, 1_012);
        assert_eq!(positions_rad[0], 0.5);
        assert!(positions_rad[1].is_nan());
        assert_eq!(positions_rad[2], -0.25);
        // The joint not read: its entry is the sample's stamp (it means
        // nothing: the NaN is not taken).
        assert_eq!(read_ns, Some(vec![1_000, 1_012, 1_012]));
    }

    #[test]
    fn a_healthy_bus_is_ok_with_its_rate_and_mode() {
        let mut b = bus(true);
        b.cycles = 500;
        b.ok_cycles = 500;
        let d = bus_status(&b, None, 10.0, JUDGE);
        assert_eq!(d.level, DiagnosticLevel::Ok, "{}", d.message);
        assert_eq!(d.name, "servo bus upper");
        assert_eq!(d.hardware_id, "/dev/ttyACM1");
        assert_eq!(value(&d, "read_rate_hz"), "50.0");
        assert_eq!(value(&d, "adapter_mode"), "usb2ax_sync_read");
        assert_eq!(value(&d, "missing_ids"), "[]");
    }

    #[test]
    fn a_missing_motor_is_named() {
        let mut b = bus(true);
        b.cycles = 500;
        b.missing_ids = vec![36];
        b.last_error = Some("motor 36 (head_z) gave no position".into());
        let d = bus_status(&b, None, 10.0, JUDGE);
        assert_eq!(d.level, DiagnosticLevel::Warn);
        assert!(d.message.contains("36 (head_z)"), "{}", d.message);
        assert_eq!(value(&d, "missing_joints"), "head_z");
        assert_eq!(
            value(&d, "last_error"),
            "motor 36 (head_z) gave no position"
        );
        b.missing_ids = vec![36, 37];
        assert_eq!(
            bus_status(&b, None, 10.0, JUDGE).level,
            DiagnosticLevel::Error
        );
    }

    #[test]
    fn a_closed_port_is_an_error_that_says_why() {
        let mut b = bus(false);
        b.last_error = Some("cannot open /dev/ttyACM1: No such file".into());
        let d = bus_status(&b, None, 10.0, JUDGE);
        assert_eq!(d.level, DiagnosticLevel::Error);
        assert!(d.message.contains("No such file"), "{}", d.message);
    }

    #[test]
    fn a_plain_adapter_is_a_mode_not_a_warning() {
        let mut b = bus(true);
        b.sync_read_active = false;
        b.timeouts = 3;
        b.sync_probe_timeouts = 3;
        b.cycles = 500;
        b.ok_cycles = 497;
        let d = bus_status(&b, None, 10.0, JUDGE);
        assert_eq!(d.level, DiagnosticLevel::Ok, "{}", d.message);
        assert_eq!(value(&d, "adapter_mode"), "read_data_fallback");
        assert_eq!(value(&d, "timeouts_per_s"), "0.00");
        b.sync_read_configured = false;
        assert_eq!(
            bus_status(&b, None, 10.0, JUDGE).message,
            "ok: 2 motors at 50.0 Hz (read_data)"
        );
    }

    #[test]
    fn errors_warn_while_in_the_window_and_the_level_returns_to_ok() {
        let mut health = ServoHealth::new(0.2);
        let mut b = bus(true);
        let mut levels = Vec::new();
        // 1 Hz snapshots, 50 cycles a second; bad checksums during seconds 3..5.
        for t in 0..=20 {
            b.cycles = 50 * t;
            b.ok_cycles = b.cycles;
            if (3..5).contains(&t) {
                b.bad_checksums += 5;
            }
            let d = health.update(t as f64, 0, snapshot(b.clone())).remove(0);
            if t == 4 {
                assert!(d.message.contains("10 bad checksums"), "{}", d.message);
                assert_eq!(value(&d, "checksum_errors_per_s"), "2.50");
            }
            levels.push(d.level);
        }
        let warn: Vec<usize> = (0..levels.len())
            .filter(|&t| levels[t] == DiagnosticLevel::Warn)
            .collect();
        // WARN from the first bad checksum until it left the 10 s window.
        assert_eq!(warn, (3..=13).collect::<Vec<_>>(), "{levels:?}");
        assert_eq!(levels[20], DiagnosticLevel::Ok);
    }

    #[test]
    fn lost_replies_asked_again_warn_while_in_the_window() {
        let mut b = bus(true);
        b.cycles = 500;
        b.ok_cycles = 500;
        let base = b.clone();
        b.lost_replies = 12;
        let d = bus_status(&b, Some(&base), 10.0, JUDGE);
        assert_eq!(d.level, DiagnosticLevel::Warn, "{}", d.message);
        assert!(
            d.message.contains("12 lost replies (asked again)"),
            "{}",
            d.message
        );
        assert_eq!(value(&d, "lost_replies_per_s"), "1.20");
        assert_eq!(value(&d, "lost_replies"), "12");
        // Out of the window: OK again, the total kept.
        let d = bus_status(&b, Some(&b), 10.0, JUDGE);
        assert_eq!(d.level, DiagnosticLevel::Ok, "{}", d.message);
        assert_eq!(value(&d, "lost_replies"), "12");
    }

    #[test]
    fn each_motor_reports_its_age_and_missed_share_and_a_failing_one_is_named() {
        let mut health = ServoHealth::new(0.2);
        let mut b = bus(true);
        let at = |health: &mut ServoHealth, t: u64, b: &BusStatsSnapshot| {
            health
                .update(t as f64, t as i64 * 1_000_000_000, snapshot(b.clone()))
                .remove(0)
        };
        // 50 cycles a second; head_y misses 10% of its reads (held, the
        // forecast stays valid), head_z 30%.
        for t in 0..=10u64 {
            b.cycles = 50 * t;
            b.motor_missed = vec![15 * t, 5 * t];
            b.missing_motor_reads = 20 * t;
            b.motor_last_read_ns = vec![
                Some(t as i64 * 1_000_000_000 - 60_000_000),
                Some(t as i64 * 1_000_000_000 - 20_000_000),
            ];
            let d = at(&mut health, t, &b);
            if t == 10 {
                assert_eq!(value(&d, "missed_share.head_z"), "0.300");
                assert_eq!(value(&d, "missed_share.head_y"), "0.100");
                assert_eq!(value(&d, "age_ms.head_z"), "60");
                assert_eq!(value(&d, "age_ms.head_y"), "20");
                assert_eq!(value(&d, "failing_motors"), "36 (head_z)");
                assert_eq!(value(&d, "warn_missed_share"), "0.2");
                assert_eq!(d.level, DiagnosticLevel::Warn, "{}", d.message);
                assert!(
                    d.message.contains("reads failing persistently")
                        && d.message.contains("36 (head_z) 30%")
                        && !d.message.contains("head_y"),
                    "{}",
                    d.message
                );
            }
        }
        // head_z answers every read again: below the share once enough of
        // the window is clean (OK: nothing else is wrong).
        for t in 11..=30u64 {
            b.cycles = 50 * t;
            b.motor_missed[1] += 5;
            b.motor_last_read_ns = vec![Some(t as i64 * 1_000_000_000); 2];
            let d = at(&mut health, t, &b);
            if t == 30 {
                assert_eq!(value(&d, "failing_motors"), "");
                assert_eq!(value(&d, "missed_share.head_z"), "0.000");
                assert_eq!(d.level, DiagnosticLevel::Ok, "{}", d.message);
            }
        }
        // A stricter share names head_y too; a motor never read says so.
        let strict = BusJudgement {
            now_ns: 0,
            warn_missed_share: 0.05,
        };
        b.motor_last_read_ns[0] = None;
        let d = bus_status(&b, None, 30.0, strict);
        assert_eq!(value(&d, "failing_motors"), "36 (head_z), 37 (head_y)");
        assert_eq!(value(&d, "age_ms.head_z"), "never");
        assert_eq!(
            bus_status(&bus(true), None, 0.0, JUDGE)
                .values
                .iter()
                .find(|(k, _)| k == "missed_share.head_z")
                .map(|(_, v)| v.as_str()),
            Some("none")
        );
    }
}
