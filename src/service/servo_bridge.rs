//! The servo buses as the daemon's joint stream: starts the servo
//! engineer's [`DynamixelSource`] (its blocking reader thread) with the
//! `[dynamixel]` section, and forwards each complete reading to the joints
//! [`StreamFeed`]; its bus counters (timeouts, bad checksums, garbage bytes,
//! servo error bits, reopens) are copied into the stream's diagnostics.

use std::time::Duration;

use crate::config::Config;
use crate::robot::JointTable;
use crate::service::{ServiceError, SourceHandle};
use crate::shutdown::Shutdown;
use crate::sources::dynamixel::{DynamixelSource, ServoStatsSnapshot};
use crate::sources::StreamFeed;

/// Bus counters as diagnostic key-values, and their error total.
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
        let bus_errors = bus.timeouts
            + bus.bad_checksums
            + bus.bad_packets
            + bus.io_errors
            + bus.garbage_bytes
            + servo_errors;
        errors += bus_errors;
        let b = &bus.name;
        details.extend([
            (format!("{b}.port"), bus.port.clone()),
            (format!("{b}.connected"), bus.connected.to_string()),
            (format!("{b}.sync_read"), bus.sync_read_active.to_string()),
            (format!("{b}.timeouts"), bus.timeouts.to_string()),
            (format!("{b}.bad_checksums"), bus.bad_checksums.to_string()),
            (format!("{b}.bad_packets"), bus.bad_packets.to_string()),
            (format!("{b}.garbage_bytes"), bus.garbage_bytes.to_string()),
            (format!("{b}.servo_errors"), servo_errors.to_string()),
            (format!("{b}.missing_ids"), format!("{:?}", bus.missing_ids)),
            (format!("{b}.reopens"), bus.reopens.to_string()),
        ]);
    }
    (errors, details)
}

/// Start the servo reader; its readings feed `feed` until `shutdown`.
pub fn start(
    config: &Config,
    feed: StreamFeed<Vec<f32>>,
    mut shutdown: Shutdown,
) -> Result<SourceHandle, ServiceError> {
    let section = config
        .dynamixel
        .as_ref()
        .ok_or_else(|| ServiceError::Usage(format!("{}: [dynamixel] missing", config.origin)))?;
    let source = DynamixelSource::spawn(section, &JointTable::poppy_humanoid(), shutdown.watch())
        .map_err(|e| ServiceError::Usage(format!("{}: [dynamixel].{e}", config.origin)))?;
    let task = tokio::spawn(async move {
        let mut readings = source.readings.clone();
        let mut refresh = tokio::time::interval(Duration::from_millis(500));
        loop {
            tokio::select! {
                changed = readings.changed() => {
                    if changed.is_err() { break; }
                    let reading = readings.borrow_and_update().clone();
                    let Some(reading) = reading else { continue };
                    if reading.is_complete() {
                        let positions: Vec<f32> = reading.positions_rad.iter().map(|p| p.unwrap_or(f32::NAN)).collect();
                        feed.send(reading.stamp_ns, positions);
                    } else {
                        let missing = reading.positions_rad.iter().filter(|p| p.is_none()).count();
                        feed.error("incomplete read", &format_args!("{missing} joints not read this cycle"));
                    }
                }
                _ = refresh.tick() => {
                    let (errors, details) = servo_details(&source.stats.snapshot());
                    feed.stats().set_external(errors, details);
                }
                () = shutdown.recv() => break,
            }
        }
        let _ = tokio::task::spawn_blocking(move || source.join()).await;
    });
    Ok(SourceHandle::Task(task))
}
