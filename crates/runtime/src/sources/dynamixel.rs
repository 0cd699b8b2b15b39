//! The Dynamixel servo source: joint angles read straight off the Poppy
//! Humanoid's serial buses.
//!
//! Data enters as Present Position registers (address 36, 2 bytes) read over
//! Dynamixel protocol 1.0, one port per bus (Poppy: `lower` and `upper`, a
//! USB2AX adapter each, 1 Mbaud): one USB2AX SYNC_READ (0x84) per bus and
//! cycle, or one rustypot READ_DATA per motor when sync read is off or the
//! adapter never answers 0x84. It leaves as a [`JointReading`] per cycle
//! (radians in pypot's convention, model order, `None` for a motor that gave
//! nothing; each position stamped with the clock just before the request
//! that gave it, so a bus read later in the cycle, or a motor read by the
//! retry, carries its own time), offered straight into the joints stream's
//! feed as a `Sample::Joints` (`health.rs`, [`joints_sample`]), and as
//! counters in [`ServoStats`], which become the stream's bus statuses on
//! `/diagnostics` ([`ServoHealth`]).
//!
//! Faults never stop the reader: a timeout, a bad checksum, garbage bytes
//! (skipped up to the next `FF FF`), a servo error bit or a position out of
//! range is counted, logged at warn the first time per kind and bus, and that
//! motor (or bus) is left out of the cycle. The motors a sync read's reply
//! gives no position for (`FF` bytes: the adapter did not get their reply)
//! are asked for once more in the same cycle, with a sync read of just
//! those ids. A port that fails (adapter
//! unplugged) is closed and reopened with exponential backoff
//! (`reopen_backoff_ms`, doubling up to `reopen_backoff_max_ms`) while the
//! other bus keeps being read.
//!
//! Use [`DynamixelSource::spawn`] in the daemon (a blocking thread of its
//! own), or [`ServoReader`] to run cycles yourself (tests, benchmarks).
//!
//! Config (TOML, unknown keys rejected): `[dynamixel]`, read into
//! [`DynamixelConfig`] (`config/sources.rs`):
//!
//! ```toml
//! rate_hz = 50                      # read cycles per second (default 50, as pypot)
//! warn_missed_share = 0.2           # a motor missing in more of the last 10 s's cycles: WARN
//! [buses.lower]
//! port = "/dev/serial/by-id/usb-Xevel_USB2AX_..."   # required
//! baud = 1000000                    # default 1000000
//! # ids = [11, 12, 13]              # default: the joint table's motors on bus "lower"
//! sync_read = true                  # default true (USB2AX 0x84)
//! timeout_ms = 20                   # default 20, per transaction
//! reopen_backoff_ms = 100           # default 100, first reopen delay
//! reopen_backoff_max_ms = 5000      # default 5000, backoff ceiling
//! [buses.upper]
//! port = "/dev/serial/by-id/usb-Xevel_USB2AX_..."
//! ```

mod bus;
mod health;
pub mod protocol;
mod stats;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use thiserror::Error;
use tokio::sync::watch;
use tracing::{info, warn};

pub use crate::config::sources::{BusConfig, DynamixelConfig};
use crate::robot::JointTable;
use crate::streams::sample::Sample;
use crate::streams::StreamFeed;
use bus::{BusMotor, BusReader};
pub use health::{bus_status, joints_sample, servo_details, BusJudgement, ServoHealth};
pub use stats::{BusStats, BusStatsSnapshot, ServoErrorKind, ServoStats, ServoStatsSnapshot};

/// A config the servo source cannot run with. `key` is the path inside the
/// servo source's section (`buses.lower.ids`).
#[derive(Debug, Error)]
pub enum DynamixelError {
    /// A bad config value.
    #[error("{key}: {message}")]
    Config {
        /// Key path inside the section.
        key: String,
        /// What is wrong and what to do.
        message: String,
    },
    /// The reader thread could not be started.
    #[error("cannot start the servo reader thread: {0}")]
    Thread(#[from] std::io::Error),
}

fn config_error(key: impl Into<String>, message: impl Into<String>) -> DynamixelError {
    DynamixelError::Config {
        key: key.into(),
        message: message.into(),
    }
}

/// One read cycle of all buses.
///
/// The buses are read one after the other, and a motor whose reply was
/// lost is asked again later in the cycle, so the positions of one cycle
/// are not all read at one time: each carries its own stamp (`read_ns`),
/// and the reading's `stamp_ns` is the newest of them (no position in it
/// was asked for later).
#[derive(Debug, Clone, PartialEq)]
pub struct JointReading {
    /// The newest of `read_ns`, ns; the clock at the start of the cycle
    /// when no motor answered. The clock is [`system_clock_ns`] unless
    /// given to [`DynamixelSource::spawn_with_clock`].
    pub stamp_ns: i64,
    /// Joint angles in radians (pypot convention), model order
    /// ([`JointTable::names`]); `None`: not read this cycle.
    pub positions_rad: Vec<Option<f32>>,
    /// Per joint, model order: the clock just before the request that gave
    /// its position (its bus's sync read, the retry of the motors lost in
    /// it, or its own READ_DATA), ns; `None` where `positions_rad` is.
    pub read_ns: Vec<Option<i64>>,
}

impl JointReading {
    /// Whether every joint has a position.
    pub fn is_complete(&self) -> bool {
        self.positions_rad.iter().all(Option::is_some)
    }
}

/// The clock that stamps readings, in ns.
pub type Clock = Arc<dyn Fn() -> i64 + Send + Sync>;

/// Nanoseconds since the UNIX epoch (the stamp ROS 2 messages carry): the
/// daemon's one clock, [`crate::clock::unix_now_ns`].
pub fn system_clock_ns() -> i64 {
    crate::clock::unix_now_ns()
}

/// Reads all buses, one cycle per call, on the caller's thread.
pub struct ServoReader {
    buses: Vec<BusReader>,
    stats: Arc<ServoStats>,
    n_joints: usize,
    n_configured: usize,
}

impl ServoReader {
    /// Check `config` against `table` and prepare the buses (ports are
    /// opened on the first cycle, so a missing adapter is not an error here).
    pub fn new(
        config: &DynamixelConfig,
        table: &JointTable,
    ) -> Result<ServoReader, DynamixelError> {
        if !(config.rate_hz.is_finite() && config.rate_hz > 0.0 && config.rate_hz <= 1000.0) {
            return Err(config_error(
                "rate_hz",
                format!("{} is not a rate in (0, 1000] Hz", config.rate_hz),
            ));
        }
        if !(0.0..=1.0).contains(&config.warn_missed_share) {
            return Err(config_error(
                "warn_missed_share",
                format!("{} is not a share in 0..1", config.warn_missed_share),
            ));
        }
        if config.buses.is_empty() {
            return Err(config_error(
                "buses",
                "no bus configured; add [buses.<name>] with a port",
            ));
        }
        let mut seen: BTreeMap<u8, String> = BTreeMap::new();
        let mut buses = Vec::new();
        let mut bus_stats = Vec::new();
        for (name, bus) in &config.buses {
            let key = |field: &str| format!("buses.{name}.{field}");
            if bus.port.trim().is_empty() {
                return Err(config_error(key("port"), "empty serial port path"));
            }
            if bus.baud == 0 {
                return Err(config_error(key("baud"), "baud rate must be positive"));
            }
            if bus.timeout_ms == 0 || bus.timeout_ms > 10_000 {
                return Err(config_error(
                    key("timeout_ms"),
                    format!("{} is not in 1..=10000", bus.timeout_ms),
                ));
            }
            if bus.reopen_backoff_ms == 0 {
                return Err(config_error(key("reopen_backoff_ms"), "must be at least 1"));
            }
            if bus.reopen_backoff_max_ms < bus.reopen_backoff_ms {
                return Err(config_error(
                    key("reopen_backoff_max_ms"),
                    format!(
                        "{} is below reopen_backoff_ms ({})",
                        bus.reopen_backoff_max_ms, bus.reopen_backoff_ms
                    ),
                ));
            }
            let ids = match &bus.ids {
                Some(ids) => ids.clone(),
                None => {
                    let ids = table.ids_on_bus(name);
                    if ids.is_empty() {
                        return Err(config_error(
                            key("ids"),
                            format!(
                                "the joint table has no bus named '{name}' (it has {:?}); set ids or rename the bus",
                                table.bus_names()
                            ),
                        ));
                    }
                    ids
                }
            };
            if ids.is_empty() {
                return Err(config_error(key("ids"), "empty id list"));
            }
            if bus.sync_read && ids.len() > protocol::USB2AX_MAX_SYNC_IDS {
                return Err(config_error(
                    key("ids"),
                    format!(
                        "{} ids, but a USB2AX sync read covers {} at most; split the bus or set sync_read = false",
                        ids.len(),
                        protocol::USB2AX_MAX_SYNC_IDS
                    ),
                ));
            }
            let mut motors = Vec::new();
            for &id in &ids {
                let Some(index) = table.index_of_id(id) else {
                    return Err(config_error(
                        key("ids"),
                        format!("id {id} is not a joint of the robot's joint table"),
                    ));
                };
                if let Some(other) = seen.insert(id, name.clone()) {
                    return Err(config_error(
                        key("ids"),
                        format!("id {id} is also on bus '{other}'"),
                    ));
                }
                let joint = table.joints()[index].clone();
                motors.push(BusMotor { index, joint });
            }
            let names = motors
                .iter()
                .map(|m| (m.joint.id, m.joint.name.clone()))
                .collect();
            bus_stats.push(BusStats::new(name, &bus.port, bus.sync_read, names));
            buses.push(BusReader::new(name, bus.clone(), motors));
        }
        let unread: Vec<String> = table
            .joints()
            .iter()
            .filter(|j| !seen.contains_key(&j.id))
            .map(|j| j.name.clone())
            .collect();
        if !unread.is_empty() {
            warn!(joints = ?unread, "these joints are on no configured servo bus and will always be missing");
        }
        Ok(ServoReader {
            buses,
            stats: Arc::new(ServoStats::new(bus_stats)),
            n_joints: table.len(),
            n_configured: seen.len(),
        })
    }

    /// The shared counters.
    pub fn stats(&self) -> Arc<ServoStats> {
        Arc::clone(&self.stats)
    }

    /// Read every bus once (sequentially, in config order) and return what
    /// came back, every position stamped `stamp_ns` (a clock that stands
    /// still: tests and benchmarks). Never fails: faults are counted.
    pub fn read_cycle(&mut self, stamp_ns: i64) -> JointReading {
        self.read_cycle_with(&|| stamp_ns)
    }

    /// Read every bus once (sequentially, in config order) and return what
    /// came back, each position stamped with `clock` read just before the
    /// request that gave it. Never fails: faults are counted.
    pub fn read_cycle_with(&mut self, clock: &dyn Fn() -> i64) -> JointReading {
        self.read_cycle_until(clock, &|| false)
    }

    fn read_cycle_until(
        &mut self,
        clock: &dyn Fn() -> i64,
        stop: &dyn Fn() -> bool,
    ) -> JointReading {
        let start_ns = clock();
        let mut positions_rad = vec![None; self.n_joints];
        let mut read_ns = vec![None; self.n_joints];
        for (i, bus) in self.buses.iter_mut().enumerate() {
            bus.read_cycle(
                self.stats.bus(i),
                &mut positions_rad,
                &mut read_ns,
                clock,
                stop,
            );
        }
        let read = positions_rad.iter().filter(|p| p.is_some()).count();
        let stamp_ns = read_ns.iter().flatten().copied().max().unwrap_or(start_ns);
        self.stats.end_cycle(read == self.n_configured, stamp_ns);
        JointReading {
            stamp_ns,
            positions_rad,
            read_ns,
        }
    }

    /// Model-order indices of the joints this reader covers.
    pub fn joint_indices(&self) -> Vec<usize> {
        let mut indices: Vec<usize> = self
            .buses
            .iter()
            .flat_map(|b| b.motors().iter().map(|m| m.index))
            .collect();
        indices.sort_unstable();
        indices
    }
}

/// How often the bus counters become the joint stream's diagnostics.
const HEALTH_PERIOD: Duration = Duration::from_millis(500);

/// The running servo source: a blocking thread that reads all buses at
/// `rate_hz` and offers each cycle that read at least one motor into the
/// joints [`StreamFeed`] (as [`joints_sample`]: NaN for a motor that did
/// not answer, counted as the stream's `incomplete read` error), and every
/// 500 ms sets the stream's bus counters and one [`DeviceDiagnostics`](crate::streams::DeviceDiagnostics) per
/// bus ([`ServoHealth`]).
///
/// ```no_run
/// # use fall_guard_runtime::robot::JointTable;
/// # use fall_guard_runtime::sources::dynamixel::{DynamixelConfig, DynamixelSource};
/// # use fall_guard_runtime::streams::{stream, StreamKind, input::InputLimits};
/// # use fall_guard_runtime::streams::sample::Sample;
/// let (shutdown_tx, shutdown_rx) = tokio::sync::watch::channel(false);
/// let config = DynamixelConfig::poppy("/dev/ttyACM0", "/dev/ttyACM1");
/// let (feed, tap) = stream::<Sample>(StreamKind::Joints, InputLimits::shapes(25, 0));
/// let source = DynamixelSource::spawn(&config, &JointTable::poppy_humanoid(), feed, shutdown_rx)?;
/// let latest = tap.latest();                    // or await tap.changed() in a task
/// let stats = source.stats.snapshot();          // the raw bus counters
/// shutdown_tx.send(true).ok();
/// source.join();
/// # Ok::<(), fall_guard_runtime::sources::dynamixel::DynamixelError>(())
/// ```
pub struct DynamixelSource {
    /// Counters of the buses (the stream's diagnostics are made from them).
    pub stats: Arc<ServoStats>,
    thread: JoinHandle<()>,
}

impl DynamixelSource {
    /// Validate `config` against `table` and start the reader thread,
    /// stamping readings with [`system_clock_ns`]. The thread stops when
    /// `shutdown` becomes true or its sender is dropped.
    pub fn spawn(
        config: &DynamixelConfig,
        table: &JointTable,
        feed: StreamFeed<Sample>,
        shutdown: watch::Receiver<bool>,
    ) -> Result<DynamixelSource, DynamixelError> {
        Self::spawn_with_clock(config, table, feed, shutdown, Arc::new(system_clock_ns))
    }

    /// [`DynamixelSource::spawn`] with the daemon's own clock (the
    /// readings' stamps and the input boundary's time).
    pub fn spawn_with_clock(
        config: &DynamixelConfig,
        table: &JointTable,
        feed: StreamFeed<Sample>,
        shutdown: watch::Receiver<bool>,
        clock: Clock,
    ) -> Result<DynamixelSource, DynamixelError> {
        let mut reader = ServoReader::new(config, table)?;
        let stats = reader.stats();
        let period = Duration::from_secs_f64(1.0 / config.rate_hz);
        let thread_stats = Arc::clone(&stats);
        let mut health = ServoHealth::new(config.warn_missed_share);
        let thread = std::thread::Builder::new()
            .name("servo-reader".into())
            .spawn(move || {
                info!(
                    period_ms = period.as_secs_f64() * 1e3,
                    "servo reader started"
                );
                let started = Instant::now();
                let mut reported: Option<Instant> = None;
                let mut report_health = || {
                    if reported.is_some_and(|t| t.elapsed() < HEALTH_PERIOD) {
                        return;
                    }
                    reported = Some(Instant::now());
                    let snapshot = thread_stats.snapshot();
                    let (errors, details) = servo_details(&snapshot);
                    feed.stats().set_external(errors, details);
                    let buses = health.update(started.elapsed().as_secs_f64(), clock(), snapshot);
                    feed.stats().set_devices(buses);
                };
                // Err: the shutdown sender is gone, which means stop too.
                let stop = || shutdown.has_changed().is_err() || *shutdown.borrow();
                let mut next = Instant::now();
                while !stop() {
                    report_health();
                    let reading = reader.read_cycle_until(&*clock, &stop);
                    if reading.positions_rad.iter().any(Option::is_some) {
                        if !reading.is_complete() {
                            let missing =
                                reading.positions_rad.iter().filter(|p| p.is_none()).count();
                            feed.error(
                                "incomplete read",
                                &format_args!("{missing} joints not read this cycle"),
                            );
                        }
                        let _ =
                            feed.offer_at(clock(), reading.stamp_ns, Ok(joints_sample(&reading)));
                    }
                    next += period;
                    let now = Instant::now();
                    if next <= now {
                        // Overran (timeouts): start the next cycle now, do not
                        // try to catch up.
                        next = now;
                        continue;
                    }
                    while !stop() {
                        let left = next.saturating_duration_since(Instant::now());
                        if left.is_zero() {
                            break;
                        }
                        std::thread::sleep(left.min(Duration::from_millis(20)));
                    }
                }
                thread_stats.set_stopped();
                info!("servo reader stopped");
            })?;
        Ok(DynamixelSource { stats, thread })
    }

    /// Wait for the reader thread to end (after shutdown). Ports are closed
    /// when it returns.
    pub fn join(self) {
        if self.thread.join().is_err() {
            warn!("servo reader thread panicked");
        }
    }

    /// Whether the reader thread has ended.
    pub fn is_finished(&self) -> bool {
        self.thread.is_finished()
    }

    /// The reader thread, to be joined by the caller after shutdown.
    pub fn into_thread(self) -> JoinHandle<()> {
        self.thread
    }
}
