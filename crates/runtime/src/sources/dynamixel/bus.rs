//! One Dynamixel serial bus: its port (opened, lost, reopened with
//! exponential backoff), one read cycle of Present Position for its motors
//! (one USB2AX SYNC_READ, or one rustypot READ_DATA per motor), and the
//! counting and once-per-kind logging of every fault.
//!
//! Enters: the bus's [`BusConfig`] and joints. Leaves: raw positions
//! converted to radians into the caller's model-order slice, each with its
//! stamp (the clock just before the request that gave it: the bus's sync
//! read, the retry of the motors lost in it, or the motor's READ_DATA), and
//! counters in the bus's [`BusStats`].

use std::collections::HashSet;
use std::io;
use std::time::{Duration, Instant};

use rustypot::{CommunicationErrorKind, DynamixelProtocolHandler};
use serialport::SerialPort;
use tracing::{debug, info, warn};

use super::protocol::{self, Scanned, PRESENT_POSITION, USB2AX_ID};
use super::stats::{BusStats, ServoErrorKind};
use super::BusConfig;
use crate::robot::Joint;

/// Consecutive silent sync reads (not one byte back) on a freshly opened port
/// after which the adapter is taken not to speak the USB2AX 0x84.
const SILENT_SYNC_READS_BEFORE_FALLBACK: u32 = 3;
/// Stale bytes drained at most per drain (a port spewing bytes still lets the
/// cycle go on).
const MAX_DRAIN_BYTES: usize = 4096;

/// A motor of this bus and where its angle goes in model order.
#[derive(Debug, Clone)]
pub(crate) struct BusMotor {
    pub index: usize,
    pub joint: Joint,
}

/// How a transaction failed.
#[derive(Debug)]
enum Failure {
    /// No whole answer in time; `received` bytes did arrive.
    Timeout { received: usize },
    /// The answer's checksum was wrong.
    BadChecksum,
    /// The answer was framed but wrong inside.
    BadPacket(String),
    /// The port failed: close it and reopen.
    Lost(String),
}

/// Fault kinds, each logged at warn the first time it happens on a bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum FaultKind {
    Timeout,
    BadChecksum,
    BadPacket,
    Garbage,
    ServoError(ServoErrorKind),
    Missing(u8),
    OpenFailed,
}

/// Read cycles without any answer after which the port is closed and
/// reopened (0.5 s at the default 50 Hz).
const SILENT_CYCLES_BEFORE_REOPEN: u32 = 25;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ReadMode {
    Sync,
    PerMotor,
}

pub(crate) struct BusReader {
    name: String,
    config: BusConfig,
    motors: Vec<BusMotor>,
    request: Vec<u8>,
    port: Option<Box<dyn SerialPort>>,
    opened_once: bool,
    next_open_at: Instant,
    backoff: Duration,
    open_failing: bool,
    mode: ReadMode,
    sync_ok_since_open: bool,
    silent_sync_reads: u32,
    /// Consecutive per-motor cycles in which no motor answered.
    silent_cycles: u32,
    warned: HashSet<FaultKind>,
    handler: DynamixelProtocolHandler,
    buf: Vec<u8>,
}

impl BusReader {
    /// `motors` in model order; `config` already validated (ids 1..=31 when
    /// sync read is on).
    pub(crate) fn new(name: &str, config: BusConfig, motors: Vec<BusMotor>) -> BusReader {
        let ids: Vec<u8> = motors.iter().map(|m| m.joint.id).collect();
        // Validated by the caller: 1 to 31 ids.
        let request =
            protocol::sync_read_request(PRESENT_POSITION.addr, PRESENT_POSITION.len, &ids)
                .unwrap_or_default();
        let mode = if config.sync_read && !request.is_empty() {
            ReadMode::Sync
        } else {
            ReadMode::PerMotor
        };
        BusReader {
            name: name.to_string(),
            backoff: config.reopen_backoff(),
            config,
            motors,
            request,
            port: None,
            opened_once: false,
            next_open_at: Instant::now(),
            open_failing: false,
            mode,
            sync_ok_since_open: false,
            silent_sync_reads: 0,
            silent_cycles: 0,
            warned: HashSet::new(),
            handler: DynamixelProtocolHandler::v1(),
            buf: Vec::with_capacity(128),
        }
    }

    pub(crate) fn motors(&self) -> &[BusMotor] {
        &self.motors
    }

    /// Read every motor of the bus once; write radians into `out` and the
    /// stamp of each position into `read_ns` (both model order: `clock`
    /// read just before the request that gave it) and leave `None` where a
    /// motor gave nothing. `stop` is polled between per-motor reads.
    pub(crate) fn read_cycle(
        &mut self,
        stats: &BusStats,
        out: &mut [Option<f32>],
        read_ns: &mut [Option<i64>],
        clock: &dyn Fn() -> i64,
        stop: &dyn Fn() -> bool,
    ) {
        // Per motor (bus order): (raw position, stamp of its request).
        let mut raw: Vec<Option<(u16, i64)>> = vec![None; self.motors.len()];
        if self.port.is_none() {
            self.try_open(stats);
        }
        if self.port.is_some() {
            match self.mode {
                ReadMode::Sync => self.cycle_sync(stats, &mut raw, clock),
                ReadMode::PerMotor => self.cycle_per_motor(stats, &mut raw, clock, stop),
            }
            // A pulled USB adapter does not always show as an I/O error:
            // writes to a hung-up tty can fail as timeouts and reads see
            // nothing. A bus on which no motor answers for a while is reopened.
            if raw.iter().all(Option::is_none) {
                self.silent_cycles += 1;
                if self.silent_cycles >= SILENT_CYCLES_BEFORE_REOPEN && self.port.is_some() {
                    self.silent_cycles = 0;
                    let reason =
                        format!("no motor answered for {SILENT_CYCLES_BEFORE_REOPEN} cycles");
                    self.lose_port(stats, &reason);
                }
            } else {
                self.silent_cycles = 0;
            }
        }
        let mut missing = Vec::new();
        for (motor, value) in self.motors.iter().zip(&raw) {
            match value {
                Some((value, stamp_ns)) => {
                    out[motor.index] = Some(motor.joint.raw_to_rad(*value) as f32);
                    read_ns[motor.index] = Some(*stamp_ns);
                }
                None => missing.push(motor.joint.id),
            }
        }
        if self.port.is_some() {
            for &id in &missing {
                let name = self
                    .motors
                    .iter()
                    .find(|m| m.joint.id == id)
                    .map_or("?", |m| m.joint.name.as_str());
                let message = format!("motor {id} ({name}) gave no position");
                self.note(stats, FaultKind::Missing(id), &message);
            }
        }
        let stamps: Vec<Option<i64>> = raw.iter().map(|r| r.map(|(_, t)| t)).collect();
        stats.end_cycle(missing, &stamps);
    }

    fn try_open(&mut self, stats: &BusStats) {
        let now = Instant::now();
        if now < self.next_open_at {
            return;
        }
        let opened = serialport::new(&self.config.port, self.config.baud)
            .timeout(self.config.timeout())
            .open();
        match opened {
            Ok(port) => {
                self.port = Some(port);
                stats.set_connected(true);
                if self.opened_once {
                    BusStats::add(&stats.reopens, 1);
                    info!(bus = %self.name, port = %self.config.port, "servo bus reopened");
                } else {
                    info!(bus = %self.name, port = %self.config.port, baud = self.config.baud,
                          sync_read = self.config.sync_read, "servo bus opened");
                }
                self.opened_once = true;
                self.open_failing = false;
                self.backoff = self.config.reopen_backoff();
                self.sync_ok_since_open = false;
                self.silent_sync_reads = 0;
                self.mode = if self.config.sync_read && !self.request.is_empty() {
                    ReadMode::Sync
                } else {
                    ReadMode::PerMotor
                };
                stats.set_sync_read_active(self.mode == ReadMode::Sync);
            }
            Err(err) => {
                BusStats::add(&stats.open_failures, 1);
                stats.set_last_error(&format!("cannot open {}: {err}", self.config.port));
                if !self.open_failing {
                    warn!(bus = %self.name, port = %self.config.port, error = %err,
                          "cannot open servo bus; retrying with backoff from {} ms to {} ms",
                          self.config.reopen_backoff_ms, self.config.reopen_backoff_max_ms);
                    self.warned.insert(FaultKind::OpenFailed);
                } else {
                    debug!(bus = %self.name, port = %self.config.port, error = %err,
                           backoff_ms = self.backoff.as_millis() as u64, "servo bus still cannot be opened");
                }
                self.open_failing = true;
                self.next_open_at = now + self.backoff;
                self.backoff = (self.backoff * 2).min(self.config.reopen_backoff_max());
            }
        }
    }

    fn lose_port(&mut self, stats: &BusStats, reason: &str) {
        BusStats::add(&stats.io_errors, 1);
        stats.set_last_error(&format!("port lost: {reason}"));
        stats.set_connected(false);
        self.port = None;
        self.backoff = self.config.reopen_backoff();
        self.next_open_at = Instant::now() + self.backoff;
        warn!(bus = %self.name, port = %self.config.port, reason,
              "servo bus lost; reopening in {} ms", self.backoff.as_millis());
        self.backoff = (self.backoff * 2).min(self.config.reopen_backoff_max());
    }

    fn note(&mut self, stats: &BusStats, kind: FaultKind, message: &str) {
        stats.set_last_error(message);
        if self.warned.insert(kind) {
            warn!(bus = %self.name, "{message} (logged once; counted in diagnostics)");
        } else {
            debug!(bus = %self.name, "{message}");
        }
    }

    fn garbage(&mut self, stats: &BusStats, bytes: usize) {
        if bytes > 0 {
            BusStats::add(&stats.garbage_bytes, bytes as u64);
            self.note(
                stats,
                FaultKind::Garbage,
                &format!("skipped {bytes} garbage byte(s)"),
            );
        }
    }

    fn fail(&mut self, stats: &BusStats, failure: Failure, what: &str) {
        match failure {
            Failure::Timeout { received } => {
                BusStats::add(&stats.timeouts, 1);
                let message = format!(
                    "{what}: no whole answer within {} ms ({received} byte(s) received)",
                    self.config.timeout_ms
                );
                self.note(stats, FaultKind::Timeout, &message);
            }
            Failure::BadChecksum => {
                BusStats::add(&stats.bad_checksums, 1);
                self.note(
                    stats,
                    FaultKind::BadChecksum,
                    &format!("{what}: answer with a bad checksum"),
                );
            }
            Failure::BadPacket(reason) => {
                BusStats::add(&stats.bad_packets, 1);
                self.note(
                    stats,
                    FaultKind::BadPacket,
                    &format!("{what}: bad answer: {reason}"),
                );
            }
            Failure::Lost(reason) => self.lose_port(stats, &format!("{what}: {reason}")),
        }
    }

    /// Check a raw position against the servo's register range.
    fn checked(&mut self, stats: &BusStats, i: usize, value: u16) -> Option<u16> {
        let joint = &self.motors[i].joint;
        if value <= joint.model.raw_max() {
            return Some(value);
        }
        let message = format!(
            "motor {} ({}) reported position {value}, above {} for an {}",
            joint.id,
            joint.name,
            joint.model.raw_max(),
            joint.model.name()
        );
        BusStats::add(&stats.bad_packets, 1);
        self.note(stats, FaultKind::BadPacket, &message);
        None
    }

    /// One sync read of `request` (`n_ids` motors) on the open port, the
    /// garbage bytes skipped counted; `None` while the port is closed.
    fn sync_read_once(
        &mut self,
        stats: &BusStats,
        request: &[u8],
        n_ids: usize,
        clock: &dyn Fn() -> i64,
    ) -> Option<Result<(i64, Vec<u8>), Failure>> {
        let port = self.port.as_mut()?;
        // The stale bytes drained first count as garbage; the data is
        // stamped with `clock` read just before the request is sent.
        let mut garbage = 0;
        let result = match drain(port.as_mut()) {
            Err(e) => Err(e),
            Ok(drained) => {
                garbage += drained;
                let stamp_ns = clock();
                let timeout = self.config.timeout();
                sync_read(
                    port.as_mut(),
                    request,
                    n_ids,
                    timeout,
                    &mut self.buf,
                    &mut garbage,
                )
                .map(|data| (stamp_ns, data))
            }
        };
        self.garbage(stats, garbage);
        Some(result)
    }

    fn cycle_sync(
        &mut self,
        stats: &BusStats,
        raw: &mut [Option<(u16, i64)>],
        clock: &dyn Fn() -> i64,
    ) {
        // The request is the bus's own, lent for the read.
        let request = std::mem::take(&mut self.request);
        let result = self.sync_read_once(stats, &request, self.motors.len(), clock);
        self.request = request;
        let Some(result) = result else {
            return;
        };
        match result {
            Ok((stamp_ns, data)) => {
                self.sync_ok_since_open = true;
                self.silent_sync_reads = 0;
                let mut lost = Vec::new();
                for i in 0..self.motors.len() {
                    let value = u16::from_le_bytes([data[2 * i], data[2 * i + 1]]);
                    // 0xFFFF: the adapter got no (good) answer from that motor.
                    raw[i] = if value == 0xFFFF {
                        lost.push(i);
                        None
                    } else {
                        self.checked(stats, i, value).map(|v| (v, stamp_ns))
                    };
                }
                if !lost.is_empty() {
                    BusStats::add(&stats.lost_replies, lost.len() as u64);
                    self.retry_sync(stats, raw, &lost, clock);
                }
            }
            Err(failure) => {
                let silent = matches!(failure, Failure::Timeout { received: 0 });
                self.fail(stats, failure, "sync read");
                if silent && !self.sync_ok_since_open {
                    BusStats::add(&stats.sync_probe_timeouts, 1);
                    self.silent_sync_reads += 1;
                    if self.silent_sync_reads >= SILENT_SYNC_READS_BEFORE_FALLBACK {
                        warn!(bus = %self.name, port = %self.config.port,
                              "adapter never answered the USB2AX SYNC_READ (0x84); reading each motor with READ_DATA until the port is reopened");
                        self.mode = ReadMode::PerMotor;
                        stats.set_sync_read_active(false);
                    }
                }
            }
        }
    }

    /// Asks the adapter once more, in the same cycle, for the motors whose
    /// answer it did not get (`FF` bytes): one SYNC_READ of just those ids.
    /// On a noisy bus a lost reply is then a lost cycle only when it is lost
    /// twice. A failure here is counted as any other; the motors stay
    /// without a position for this cycle. A position it gets is stamped
    /// with its own request's time, not the first sync read's.
    fn retry_sync(
        &mut self,
        stats: &BusStats,
        raw: &mut [Option<(u16, i64)>],
        lost: &[usize],
        clock: &dyn Fn() -> i64,
    ) {
        let ids: Vec<u8> = lost.iter().map(|&i| self.motors[i].joint.id).collect();
        let Ok(request) =
            protocol::sync_read_request(PRESENT_POSITION.addr, PRESENT_POSITION.len, &ids)
        else {
            return;
        };
        let Some(result) = self.sync_read_once(stats, &request, ids.len(), clock) else {
            return;
        };
        match result {
            Ok((stamp_ns, data)) => {
                for (k, &i) in lost.iter().enumerate() {
                    let value = u16::from_le_bytes([data[2 * k], data[2 * k + 1]]);
                    if value == 0xFFFF {
                        BusStats::add(&stats.lost_replies, 1);
                    } else {
                        raw[i] = self.checked(stats, i, value).map(|v| (v, stamp_ns));
                    }
                }
            }
            Err(failure) => self.fail(stats, failure, "sync read (again, for the motors lost)"),
        }
    }

    fn cycle_per_motor(
        &mut self,
        stats: &BusStats,
        raw: &mut [Option<(u16, i64)>],
        clock: &dyn Fn() -> i64,
        stop: &dyn Fn() -> bool,
    ) {
        for (i, slot) in raw.iter_mut().enumerate() {
            if stop() {
                return;
            }
            let id = self.motors[i].joint.id;
            let Some(port) = self.port.as_mut() else {
                return;
            };
            let stale = match drain(port.as_mut()) {
                Ok(stale) => stale,
                Err(failure) => {
                    self.fail(stats, failure, "drain");
                    return;
                }
            };
            let timeout = self.config.timeout();
            let stamp_ns = clock();
            let answer = port
                .set_timeout(timeout)
                .map_err(|e| Failure::Lost(e.to_string()))
                .and_then(|()| {
                    self.handler
                        .read_with_error(
                            port.as_mut(),
                            id,
                            PRESENT_POSITION.addr,
                            PRESENT_POSITION.len,
                        )
                        .map_err(classify)
                });
            self.garbage(stats, stale);
            let what = format!("READ_DATA of motor {id}");
            match answer {
                Ok((params, status)) => {
                    if !status.is_ok() {
                        stats.count_servo_errors(status.byte());
                        for kind in ServoErrorKind::from_byte(status.byte()) {
                            self.note(
                                stats,
                                FaultKind::ServoError(kind),
                                &format!("motor {id} reports servo error '{}'", kind.name()),
                            );
                        }
                    }
                    if params.len() == usize::from(PRESENT_POSITION.len) {
                        let value = u16::from_le_bytes([params[0], params[1]]);
                        *slot = self.checked(stats, i, value).map(|v| (v, stamp_ns));
                    } else {
                        let reason = format!("{} data byte(s) instead of 2", params.len());
                        self.fail(stats, Failure::BadPacket(reason), &what);
                    }
                }
                Err(failure) => {
                    let lost = matches!(failure, Failure::Lost(_));
                    self.fail(stats, failure, &what);
                    if lost {
                        return;
                    }
                }
            }
        }
    }
}

/// Map a rustypot error onto a [`Failure`].
fn classify(err: Box<dyn std::error::Error>) -> Failure {
    if let Some(io_err) = err.downcast_ref::<io::Error>() {
        return if io_err.kind() == io::ErrorKind::TimedOut {
            Failure::Timeout { received: 0 }
        } else {
            Failure::Lost(io_err.to_string())
        };
    }
    if let Some(serial_err) = err.downcast_ref::<serialport::Error>() {
        return Failure::Lost(serial_err.to_string());
    }
    match err.downcast_ref::<CommunicationErrorKind>() {
        Some(CommunicationErrorKind::ChecksumError) => Failure::BadChecksum,
        // rustypot reports a failed write as a timeout too; the next drain
        // finds out whether the port is gone.
        Some(CommunicationErrorKind::TimeoutError) => Failure::Timeout { received: 0 },
        Some(other) => Failure::BadPacket(other.to_string()),
        None => Failure::BadPacket(err.to_string()),
    }
}

/// Read and drop whatever already waits in the input buffer (stale answers,
/// noise); also the liveness probe: a hung-up port fails here.
fn drain(port: &mut dyn SerialPort) -> Result<usize, Failure> {
    port.set_timeout(Duration::ZERO)
        .map_err(|e| Failure::Lost(e.to_string()))?;
    let mut chunk = [0u8; 256];
    let mut total = 0;
    while total < MAX_DRAIN_BYTES {
        match port.read(&mut chunk) {
            Ok(0) => return Err(Failure::Lost("end of file".into())),
            Ok(n) => total += n,
            Err(e) if e.kind() == io::ErrorKind::TimedOut => break,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(Failure::Lost(e.to_string())),
        }
    }
    Ok(total)
}

/// One USB2AX SYNC_READ of 2 bytes from `n_ids` motors: send `request`,
/// return the `2 * n_ids` data bytes of the adapter's reply. Bytes skipped
/// while resynchronising are added to `garbage`.
fn sync_read(
    port: &mut dyn SerialPort,
    request: &[u8],
    n_ids: usize,
    timeout: Duration,
    buf: &mut Vec<u8>,
    garbage: &mut usize,
) -> Result<Vec<u8>, Failure> {
    port.write_all(request)
        .map_err(|e| Failure::Lost(format!("write: {e}")))?;
    let deadline = Instant::now() + timeout;
    let data_len = n_ids * usize::from(PRESENT_POSITION.len);
    let expected_len = (data_len + 2) as u8;
    buf.clear();
    let mut received = 0;
    let mut chunk = [0u8; 256];
    loop {
        match protocol::scan(buf) {
            Scanned::Packet {
                garbage: skipped,
                end,
                packet,
            } => {
                *garbage += skipped;
                if packet.id == USB2AX_ID && packet.params.len() == data_len {
                    *garbage += buf.len() - end;
                    if packet.byte4 != 0 {
                        return Err(Failure::BadPacket(format!(
                            "adapter reply carries error byte 0x{:02X}",
                            packet.byte4
                        )));
                    }
                    return Ok(packet.params);
                }
                // A whole packet that is not the adapter's reply (a late
                // status packet, say): skip it.
                *garbage += end - skipped;
                buf.drain(..end);
                continue;
            }
            Scanned::BadChecksum {
                garbage: skipped,
                end,
                id,
                len,
            } => {
                if id == USB2AX_ID && len == expected_len {
                    *garbage += skipped + (buf.len() - end);
                    return Err(Failure::BadChecksum);
                }
                // FF FF inside garbage: skip past its first byte.
                *garbage += skipped + 1;
                buf.drain(..skipped + 1);
                continue;
            }
            Scanned::Incomplete { garbage: skipped } => {
                *garbage += skipped;
                buf.drain(..skipped);
            }
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(Failure::Timeout { received });
        }
        port.set_timeout(left)
            .map_err(|e| Failure::Lost(e.to_string()))?;
        match port.read(&mut chunk) {
            Ok(0) => return Err(Failure::Lost("end of file".into())),
            Ok(n) => {
                received += n;
                buf.extend_from_slice(&chunk[..n]);
            }
            Err(e) if e.kind() == io::ErrorKind::TimedOut => {
                return Err(Failure::Timeout { received });
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(Failure::Lost(format!("read: {e}"))),
        }
    }
}
