//! Counters of the servo reader, written by its thread and read by the
//! daemon for `/diagnostics`.
//!
//! The reader thread bumps lock-free counters ([`ServoStats`], one
//! [`BusStats`] per bus); anyone holding the `Arc<ServoStats>` takes a
//! consistent-enough copy with [`ServoStats::snapshot`].

use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::sync::Mutex;

use serde::Serialize;

/// The error bits of a protocol 1.0 status packet, bit 0 to bit 6.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum ServoErrorKind {
    /// Bit 0: input voltage out of the configured range.
    InputVoltage,
    /// Bit 1: goal position outside the angle limits.
    AngleLimit,
    /// Bit 2: temperature above the limit.
    Overheating,
    /// Bit 3: an instruction parameter out of range.
    Range,
    /// Bit 4: the servo received a packet with a bad checksum.
    Checksum,
    /// Bit 5: the load exceeds the maximum torque.
    Overload,
    /// Bit 6: an undefined instruction (or an action without a reg_write).
    Instruction,
}

impl ServoErrorKind {
    /// All kinds, in bit order.
    pub const ALL: [ServoErrorKind; 7] = [
        ServoErrorKind::InputVoltage,
        ServoErrorKind::AngleLimit,
        ServoErrorKind::Overheating,
        ServoErrorKind::Range,
        ServoErrorKind::Checksum,
        ServoErrorKind::Overload,
        ServoErrorKind::Instruction,
    ];

    /// The kind's bit in the error byte.
    pub fn bit(self) -> u8 {
        1 << (self as u8)
    }

    /// A short name for logs and diagnostics (`"overheating"`).
    pub fn name(self) -> &'static str {
        match self {
            ServoErrorKind::InputVoltage => "input_voltage",
            ServoErrorKind::AngleLimit => "angle_limit",
            ServoErrorKind::Overheating => "overheating",
            ServoErrorKind::Range => "range",
            ServoErrorKind::Checksum => "checksum",
            ServoErrorKind::Overload => "overload",
            ServoErrorKind::Instruction => "instruction",
        }
    }

    /// The kinds set in an error byte (bit 7 is unused on protocol 1.0).
    pub fn from_byte(error: u8) -> Vec<ServoErrorKind> {
        ServoErrorKind::ALL
            .into_iter()
            .filter(|kind| error & kind.bit() != 0)
            .collect()
    }
}

/// Live counters of one bus. Monotonic except the `connected`,
/// `sync_read_active`, `missing_ids` and `last_ok_ns` state.
#[derive(Debug)]
pub struct BusStats {
    name: String,
    port: String,
    connected: AtomicBool,
    sync_read_active: AtomicBool,
    pub(crate) cycles: AtomicU64,
    pub(crate) ok_cycles: AtomicU64,
    pub(crate) timeouts: AtomicU64,
    pub(crate) bad_checksums: AtomicU64,
    pub(crate) bad_packets: AtomicU64,
    pub(crate) garbage_bytes: AtomicU64,
    pub(crate) lost_replies: AtomicU64,
    pub(crate) servo_errors: [AtomicU64; 7],
    pub(crate) missing_motor_reads: AtomicU64,
    pub(crate) io_errors: AtomicU64,
    pub(crate) reopens: AtomicU64,
    pub(crate) open_failures: AtomicU64,
    pub(crate) sync_probe_timeouts: AtomicU64,
    last_ok_ns: AtomicI64,
    missing_ids: Mutex<Vec<u8>>,
    /// (id, joint name) of every motor of the bus, in read order.
    motors: Vec<(u8, String)>,
    /// Per motor (read order): cycles in which it gave no position.
    motor_missed: Vec<AtomicU64>,
    /// Per motor: stamp of its latest position (see the snapshot's field).
    motor_last_read_ns: Vec<AtomicI64>,
    sync_read_configured: bool,
    last_error: Mutex<Option<String>>,
}

const NEVER: i64 = i64::MIN;

impl BusStats {
    pub(crate) fn new(
        name: &str,
        port: &str,
        sync_read: bool,
        motors: Vec<(u8, String)>,
    ) -> BusStats {
        BusStats {
            name: name.to_string(),
            port: port.to_string(),
            connected: AtomicBool::new(false),
            sync_read_active: AtomicBool::new(sync_read),
            cycles: AtomicU64::new(0),
            ok_cycles: AtomicU64::new(0),
            timeouts: AtomicU64::new(0),
            bad_checksums: AtomicU64::new(0),
            bad_packets: AtomicU64::new(0),
            garbage_bytes: AtomicU64::new(0),
            lost_replies: AtomicU64::new(0),
            servo_errors: Default::default(),
            missing_motor_reads: AtomicU64::new(0),
            io_errors: AtomicU64::new(0),
            reopens: AtomicU64::new(0),
            open_failures: AtomicU64::new(0),
            sync_probe_timeouts: AtomicU64::new(0),
            last_ok_ns: AtomicI64::new(NEVER),
            missing_ids: Mutex::new(Vec::new()),
            motor_missed: motors.iter().map(|_| AtomicU64::new(0)).collect(),
            motor_last_read_ns: motors.iter().map(|_| AtomicI64::new(NEVER)).collect(),
            motors,
            sync_read_configured: sync_read,
            last_error: Mutex::new(None),
        }
    }

    /// Remember the latest fault (one line, for `/diagnostics`).
    pub(crate) fn set_last_error(&self, message: &str) {
        if let Ok(mut last) = self.last_error.lock() {
            if last.as_deref() != Some(message) {
                *last = Some(message.to_string());
            }
        }
    }

    pub(crate) fn add(counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::Relaxed);
    }

    pub(crate) fn set_connected(&self, connected: bool) {
        self.connected.store(connected, Ordering::Relaxed);
    }

    pub(crate) fn set_sync_read_active(&self, active: bool) {
        self.sync_read_active.store(active, Ordering::Relaxed);
    }

    pub(crate) fn count_servo_errors(&self, error: u8) {
        for kind in ServoErrorKind::from_byte(error) {
            Self::add(&self.servo_errors[kind as usize], 1);
        }
    }

    /// One cycle of the bus done: `read_ns` per motor (the order of
    /// `motors`), the stamp of the request that gave its position (`None`:
    /// it gave none, and is in `missing_ids`).
    pub(crate) fn end_cycle(&self, missing_ids: Vec<u8>, read_ns: &[Option<i64>]) {
        Self::add(&self.cycles, 1);
        Self::add(&self.missing_motor_reads, missing_ids.len() as u64);
        for (i, (id, _)) in self.motors.iter().enumerate() {
            match read_ns.get(i).copied().flatten() {
                Some(stamp_ns) if !missing_ids.contains(id) => {
                    self.motor_last_read_ns[i].store(stamp_ns, Ordering::Relaxed);
                }
                _ => Self::add(&self.motor_missed[i], 1),
            }
        }
        if missing_ids.is_empty() {
            Self::add(&self.ok_cycles, 1);
            // The oldest read of the cycle: every position is at least this recent.
            if let Some(oldest) = read_ns.iter().flatten().min() {
                self.last_ok_ns.store(*oldest, Ordering::Relaxed);
            }
        }
        if let Ok(mut ids) = self.missing_ids.lock() {
            *ids = missing_ids;
        }
    }

    /// A copy of the counters.
    pub fn snapshot(&self) -> BusStatsSnapshot {
        let load = |c: &AtomicU64| c.load(Ordering::Relaxed);
        let last_ok = self.last_ok_ns.load(Ordering::Relaxed);
        let mut servo_errors = Vec::new();
        for kind in ServoErrorKind::ALL {
            let n = load(&self.servo_errors[kind as usize]);
            if n > 0 {
                servo_errors.push((kind, n));
            }
        }
        BusStatsSnapshot {
            name: self.name.clone(),
            port: self.port.clone(),
            connected: self.connected.load(Ordering::Relaxed),
            sync_read_active: self.sync_read_active.load(Ordering::Relaxed),
            cycles: load(&self.cycles),
            ok_cycles: load(&self.ok_cycles),
            timeouts: load(&self.timeouts),
            bad_checksums: load(&self.bad_checksums),
            bad_packets: load(&self.bad_packets),
            garbage_bytes: load(&self.garbage_bytes),
            lost_replies: load(&self.lost_replies),
            servo_errors,
            missing_motor_reads: load(&self.missing_motor_reads),
            missing_ids: self
                .missing_ids
                .lock()
                .map(|v| v.clone())
                .unwrap_or_default(),
            io_errors: load(&self.io_errors),
            reopens: load(&self.reopens),
            open_failures: load(&self.open_failures),
            sync_probe_timeouts: load(&self.sync_probe_timeouts),
            last_ok_ns: (last_ok != NEVER).then_some(last_ok),
            motors: self.motors.clone(),
            motor_missed: self.motor_missed.iter().map(load).collect(),
            motor_last_read_ns: self
                .motor_last_read_ns
                .iter()
                .map(|t| Some(t.load(Ordering::Relaxed)).filter(|&t| t != NEVER))
                .collect(),
            sync_read_configured: self.sync_read_configured,
            last_error: self.last_error.lock().ok().and_then(|l| l.clone()),
        }
    }
}

/// A copy of one bus's counters at one moment.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct BusStatsSnapshot {
    /// Bus name from the config (`"lower"`).
    pub name: String,
    /// Serial port path from the config.
    pub port: String,
    /// Whether the port is open now.
    pub connected: bool,
    /// Whether cycles use the USB2AX sync read now (false: configured off, or
    /// fallen back to one READ_DATA per motor because the adapter never
    /// answered 0x84).
    pub sync_read_active: bool,
    /// Read cycles on this bus (one per reader cycle, open or not).
    pub cycles: u64,
    /// Cycles in which every motor of the bus gave a position.
    pub ok_cycles: u64,
    /// Transactions with no (whole) answer within `timeout_ms`.
    pub timeouts: u64,
    /// Answers whose checksum was wrong.
    pub bad_checksums: u64,
    /// Answers framed correctly but wrong inside (wrong id or length,
    /// position out of the register's range, an error reply without data).
    pub bad_packets: u64,
    /// Bytes skipped while resynchronising on `FF FF` or drained as stale.
    pub garbage_bytes: u64,
    /// Motor replies the USB2AX adapter marked lost (`0xFFFF` in its sync
    /// read answer: no good reply from that motor), each asked again in
    /// the same cycle; a reply lost again counts again.
    pub lost_replies: u64,
    /// Servo error bits seen (kind, count), kinds never seen left out. Only
    /// per-motor reads carry them: the USB2AX sync read drops them.
    pub servo_errors: Vec<(ServoErrorKind, u64)>,
    /// Motor-cycles without a position (missing motor, 0xFFFF, any failure).
    pub missing_motor_reads: u64,
    /// Ids without a position in the latest cycle.
    pub missing_ids: Vec<u8>,
    /// Read/write errors that closed the port.
    pub io_errors: u64,
    /// Successful reopens after the port was lost.
    pub reopens: u64,
    /// Failed attempts to open the port.
    pub open_failures: u64,
    /// Silent USB2AX sync reads on a freshly opened port (the probe that
    /// finds a plain adapter, also counted in `timeouts`).
    pub sync_probe_timeouts: u64,
    /// Stamp of the latest cycle in which every motor answered (its
    /// oldest read).
    pub last_ok_ns: Option<i64>,
    /// (id, joint name) of every motor of the bus.
    pub motors: Vec<(u8, String)>,
    /// Per motor (the order of `motors`): cycles in which it gave no
    /// position (missing, `0xFFFF` in a sync read, any failure).
    pub motor_missed: Vec<u64>,
    /// Per motor: stamp of its latest position, taken just before the
    /// request that gave it (the bus's sync read, the retry of the motors
    /// lost in it, or the motor's READ_DATA; `None`: never).
    pub motor_last_read_ns: Vec<Option<i64>>,
    /// Whether the config asked for the USB2AX sync read.
    pub sync_read_configured: bool,
    /// The latest fault seen on this bus, one line (None: none yet).
    pub last_error: Option<String>,
}

impl BusStatsSnapshot {
    /// Joint names of `missing_ids`, same order.
    pub fn missing_joints(&self) -> Vec<String> {
        self.missing_ids
            .iter()
            .map(|id| {
                self.motors
                    .iter()
                    .find(|(m, _)| m == id)
                    .map_or_else(|| format!("id {id}"), |(_, n)| n.clone())
            })
            .collect()
    }

    /// How the bus is read: `usb2ax_sync_read`, `read_data` (configured),
    /// or `read_data_fallback` (the adapter never answered the sync read:
    /// a plain USB-serial adapter, which is a mode, not a fault).
    pub fn adapter_mode(&self) -> &'static str {
        if self.sync_read_active {
            "usb2ax_sync_read"
        } else if self.sync_read_configured {
            "read_data_fallback"
        } else {
            "read_data"
        }
    }

    /// Transaction errors that are faults (the plain-adapter probe left
    /// out): timeouts, bad checksums, bad packets, I/O errors, servo error
    /// bits.
    pub fn fault_errors(&self) -> u64 {
        self.timeouts.saturating_sub(self.sync_probe_timeouts)
            + self.bad_checksums
            + self.bad_packets
            + self.io_errors
            + self.servo_errors.iter().map(|(_, n)| n).sum::<u64>()
    }
}

/// Counters of the whole servo source, one [`BusStats`] per bus, shared
/// between the reader thread and the daemon (`Arc<ServoStats>`).
#[derive(Debug)]
pub struct ServoStats {
    buses: Vec<BusStats>,
    cycles: AtomicU64,
    complete_cycles: AtomicU64,
    last_complete_ns: AtomicI64,
    running: AtomicBool,
}

impl ServoStats {
    pub(crate) fn new(buses: Vec<BusStats>) -> ServoStats {
        ServoStats {
            buses,
            cycles: AtomicU64::new(0),
            complete_cycles: AtomicU64::new(0),
            last_complete_ns: AtomicI64::new(NEVER),
            running: AtomicBool::new(true),
        }
    }

    pub(crate) fn bus(&self, index: usize) -> &BusStats {
        &self.buses[index]
    }

    pub(crate) fn end_cycle(&self, complete: bool, stamp_ns: i64) {
        self.cycles.fetch_add(1, Ordering::Relaxed);
        if complete {
            self.complete_cycles.fetch_add(1, Ordering::Relaxed);
            self.last_complete_ns.store(stamp_ns, Ordering::Relaxed);
        }
    }

    pub(crate) fn set_stopped(&self) {
        self.running.store(false, Ordering::Relaxed);
    }

    /// A copy of all counters.
    pub fn snapshot(&self) -> ServoStatsSnapshot {
        let last = self.last_complete_ns.load(Ordering::Relaxed);
        ServoStatsSnapshot {
            running: self.running.load(Ordering::Relaxed),
            cycles: self.cycles.load(Ordering::Relaxed),
            complete_cycles: self.complete_cycles.load(Ordering::Relaxed),
            last_complete_ns: (last != NEVER).then_some(last),
            buses: self.buses.iter().map(BusStats::snapshot).collect(),
        }
    }
}

/// A copy of the servo source's counters at one moment.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ServoStatsSnapshot {
    /// False once the reader thread has stopped.
    pub running: bool,
    /// Reader cycles (all buses read once).
    pub cycles: u64,
    /// Cycles in which every configured motor gave a position.
    pub complete_cycles: u64,
    /// Stamp of the latest complete cycle (its reading's `stamp_ns`: the
    /// newest read of it).
    pub last_complete_ns: Option<i64>,
    /// Per bus, in config order.
    pub buses: Vec<BusStatsSnapshot>,
}

impl ServoStatsSnapshot {
    /// Sum of one counter over the buses (`|b| b.timeouts`).
    pub fn total(&self, counter: impl Fn(&BusStatsSnapshot) -> u64) -> u64 {
        self.buses.iter().map(counter).sum()
    }

    /// Count of one servo error kind over all buses.
    pub fn servo_errors(&self, kind: ServoErrorKind) -> u64 {
        self.buses
            .iter()
            .flat_map(|b| b.servo_errors.iter())
            .filter(|(k, _)| *k == kind)
            .map(|(_, n)| n)
            .sum()
    }
}
