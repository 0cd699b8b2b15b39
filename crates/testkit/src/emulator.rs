//! A Dynamixel bus behind a USB2AX, emulated on a real pseudo-terminal, for
//! tests and benchmarks of the servo reader.
//!
//! [`BusEmulator::start`] opens a pty pair (serialport's `TTYPort::pair`),
//! points a symlink of the caller's choosing at the slave side (as udev's
//! `/dev/serial/by-id` links do), and answers on the master side, on its own
//! thread, as the USB2AX and its servos would on protocol 1.0:
//!
//! - PING, READ_DATA and WRITE_DATA addressed to a present motor, with a
//!   control table laid out by rustypot's MX/AX register maps (writing Goal
//!   Position moves Present Position there at once); an unknown instruction
//!   gets the instruction error bit; broadcasts get no answer.
//! - The USB2AX SYNC_READ (0x84, to id FE or FD): one status packet from id
//!   FD with `L` bytes per requested id, `FF` bytes for a missing motor;
//!   servo error bits do not come through, as on the adapter. The official
//!   0x82 is ignored, as the servos and the adapter ignore it.
//!
//! Test hooks: positions ([`BusEmulator::set_raw_position`]), missing
//! motors, servo error bits, reply faults applied to every reply ([`Fault`]:
//! no reply, bad checksum, garbage before the reply), seeded random faults
//! of each motor's reply on its own ([`ReplyNoise`]), an adapter without
//! 0x84 ([`BusEmulator::set_sync_read_supported`]), unplugging (the pty is
//! closed and the link removed) and replugging (a new pty behind the same
//! link), and an optional 1 Mbaud wire-time delay.
//!
//! Inside a sync read, a motor's reply is the adapter's exchange with that
//! servo, not bytes the host sees. The USB2AX firmware (`AX.c`,
//! `axReadPacket`) reads a fixed-length status packet (`L + 6` bytes) from
//! the servo's first byte within its receive timeout and checks its
//! checksum, with no search for the `FF FF` header; whatever fails (no
//! reply, a bad checksum, garbage bytes before the packet, which shift it)
//! gives `FF` bytes for that id in an otherwise well-formed reply. The
//! emulator does the same with a [`ReplyNoise`] fault of a motor's reply in
//! a sync read.

use std::collections::BTreeMap;
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use rustypot::servo::dynamixel::{ax, mx};
use serialport::{SerialPort, TTYPort};
use thiserror::Error;

use fall_guard_runtime::robot::{JointTable, ServoModel};
use fall_guard_runtime::sources::dynamixel::protocol::{
    self, instruction, Packet, Scanned, BROADCAST_ID, USB2AX_ID,
};
use fall_guard_runtime::sources::dynamixel::DynamixelConfig;

/// Error bit 6 (instruction) of a protocol 1.0 status packet.
const ERROR_INSTRUCTION: u8 = 1 << 6;
/// Error bit 3 (range).
const ERROR_RANGE: u8 = 1 << 3;

/// What the emulator cannot do.
#[derive(Debug, Error)]
pub enum EmulatorError {
    /// The pty pair could not be created.
    #[error("cannot create a pseudo-terminal pair: {0}")]
    Pty(#[from] serialport::Error),
    /// The symlink to the slave could not be made.
    #[error("cannot link {link} to the pseudo-terminal: {source}")]
    Link {
        /// The link path.
        link: PathBuf,
        /// Why.
        source: io::Error,
    },
    /// The emulator thread could not be started.
    #[error("cannot start the emulator thread: {0}")]
    Thread(io::Error),
    /// An id with no emulated motor.
    #[error("no emulated motor with id {0}")]
    NoMotor(u8),
    /// The emulator thread did not act in time.
    #[error("the emulator thread did not {0} within 2 s")]
    Stalled(&'static str),
}

/// A fault applied to every reply while set.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fault {
    /// Requests are read but never answered.
    NoReply,
    /// Each reply's checksum byte is corrupted.
    BadChecksum,
    /// These bytes are sent before each reply.
    Garbage(Vec<u8>),
}

/// Seeded random faults of each motor's reply, drawn per reply (a motor's
/// status packet to a PING, READ_DATA or WRITE_DATA, or its part of a USB2AX
/// sync read): dropped with probability `p_drop`, else its checksum
/// corrupted with `p_corrupt`, else 1 to 4 garbage bytes (never `FF`) sent
/// before it with `p_garbage`. The same seed and the same requests give the
/// same faults.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReplyNoise {
    /// Seed of the draws.
    pub seed: u64,
    /// Probability that a reply is lost.
    pub p_drop: f64,
    /// Probability that a reply's checksum is corrupted.
    pub p_corrupt: f64,
    /// Probability that garbage bytes come before a reply.
    pub p_garbage: f64,
}

/// What [`ReplyNoise`] did to one reply.
#[derive(Debug, Clone, PartialEq, Eq)]
enum ReplyFate {
    Clean,
    Dropped,
    Corrupted,
    Garbage(Vec<u8>),
}

/// The draws of a [`ReplyNoise`]: SplitMix64, so that a seed gives the
/// same faults on every platform and version.
#[derive(Debug, Clone)]
struct Noise {
    config: ReplyNoise,
    state: u64,
    /// Replies faulted so far: (dropped, corrupted, garbage).
    counts: NoiseCounts,
}

/// How many replies a [`ReplyNoise`] faulted, by kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NoiseCounts {
    /// Motor replies drawn for (faulted or not).
    pub replies: u64,
    /// Dropped.
    pub dropped: u64,
    /// Checksum corrupted.
    pub corrupted: u64,
    /// Garbage bytes before them.
    pub garbage: u64,
}

impl Noise {
    fn new(config: ReplyNoise) -> Noise {
        Noise {
            config,
            state: config.seed,
            counts: NoiseCounts::default(),
        }
    }

    fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// The fate of the next motor reply.
    fn draw(&mut self) -> ReplyFate {
        self.counts.replies += 1;
        let c = self.config;
        if self.unit() < c.p_drop {
            self.counts.dropped += 1;
            ReplyFate::Dropped
        } else if self.unit() < c.p_corrupt {
            self.counts.corrupted += 1;
            ReplyFate::Corrupted
        } else if self.unit() < c.p_garbage {
            self.counts.garbage += 1;
            let n = 1 + (self.next_u64() % 4) as usize;
            ReplyFate::Garbage((0..n).map(|_| (self.next_u64() % 0xFF) as u8).collect())
        } else {
            ReplyFate::Clean
        }
    }
}

/// How many requests the emulator received, by kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RequestCounts {
    /// PING.
    pub pings: u64,
    /// READ_DATA.
    pub reads: u64,
    /// WRITE_DATA.
    pub writes: u64,
    /// USB2AX SYNC_READ (0x84).
    pub sync_reads: u64,
    /// Anything else (including 0x82, broadcasts, unknown ids).
    pub other: u64,
    /// Instruction packets with a bad checksum (ignored).
    pub bad_checksums: u64,
}

#[derive(Debug, Clone)]
struct EmulatedMotor {
    model: ServoModel,
    registers: Vec<u8>,
    present: bool,
    error_bits: u8,
}

impl EmulatedMotor {
    fn new(id: u8, model: ServoModel) -> EmulatedMotor {
        let size = match model {
            ServoModel::Mx28 | ServoModel::Mx64 => 74,
            ServoModel::Ax12 => 50,
        };
        let mut motor = EmulatedMotor {
            model,
            registers: vec![0; size],
            present: true,
            error_bits: 0,
        };
        let centre = model.raw_max() / 2 + 1;
        for (name, value) in [
            ("model_number", model.model_number()),
            ("firmware_version", 36),
            ("id", u16::from(id)),
            ("baudrate", 1),
            ("return_delay_time", 0),
            ("cw_angle_limit", 0),
            ("ccw_angle_limit", model.raw_max()),
            ("temperature_limit", 80),
            ("min_voltage_limit", 60),
            ("max_voltage_limit", 160),
            ("max_torque", 1023),
            ("status_return_level", 2),
            ("torque_limit", 1023),
            ("goal_position", centre),
            ("present_position", centre),
            ("present_voltage", 120),
            ("present_temperature", 35),
        ] {
            motor.set_register(name, value);
        }
        motor
    }

    /// Write a register by its rustypot name (little endian, its own size).
    fn set_register(&mut self, name: &str, value: u16) {
        let info = match self.model {
            ServoModel::Mx28 | ServoModel::Mx64 => mx::register(name),
            ServoModel::Ax12 => ax::register(name),
        };
        let Some(info) = info else { return };
        let addr = usize::from(info.addr);
        let bytes = value.to_le_bytes();
        for (i, byte) in bytes.iter().take(usize::from(info.size)).enumerate() {
            if let Some(slot) = self.registers.get_mut(addr + i) {
                *slot = *byte;
            }
        }
    }

    fn read(&self, addr: u8, len: u8) -> Option<&[u8]> {
        let start = usize::from(addr);
        let end = start + usize::from(len);
        (len > 0 && end <= self.registers.len()).then(|| &self.registers[start..end])
    }
}

struct State {
    motors: BTreeMap<u8, EmulatedMotor>,
    fault: Option<Fault>,
    noise: Option<Noise>,
    sync_read_supported: bool,
    plugged: bool,
    pty_open: bool,
    wire_baud: Option<u32>,
    requests: RequestCounts,
}

/// A USB2AX and its servos on a pseudo-terminal. Dropping it stops the thread,
/// closes the pty and removes the link.
pub struct BusEmulator {
    state: Arc<Mutex<State>>,
    link: PathBuf,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

fn lock(state: &Mutex<State>) -> MutexGuard<'_, State> {
    // A panic while holding the lock leaves plain data behind: keep going.
    state
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl BusEmulator {
    /// Emulate `motors` (id, model) behind a USB2AX reachable at `link`
    /// (a symlink created, or replaced, there).
    pub fn start(
        motors: &[(u8, ServoModel)],
        link: impl Into<PathBuf>,
    ) -> Result<BusEmulator, EmulatorError> {
        let link = link.into();
        let master = open_pty(&link)?;
        let state = Arc::new(Mutex::new(State {
            motors: motors
                .iter()
                .map(|&(id, model)| (id, EmulatedMotor::new(id, model)))
                .collect(),
            fault: None,
            noise: None,
            sync_read_supported: true,
            plugged: true,
            pty_open: true,
            wire_baud: None,
            requests: RequestCounts::default(),
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let state = Arc::clone(&state);
            let stop = Arc::clone(&stop);
            let link = link.clone();
            std::thread::Builder::new()
                .name("bus-emulator".into())
                .spawn(move || serve(master, &state, &stop, &link))
                .map_err(EmulatorError::Thread)?
        };
        Ok(BusEmulator {
            state,
            link,
            stop,
            thread: Some(thread),
        })
    }

    /// Emulate the motors of `table` on bus `bus` (`"lower"`, `"upper"`).
    pub fn for_bus(
        table: &JointTable,
        bus: &str,
        link: impl Into<PathBuf>,
    ) -> Result<BusEmulator, EmulatorError> {
        let motors: Vec<(u8, ServoModel)> = table
            .joints()
            .iter()
            .filter(|j| j.bus == bus)
            .map(|j| (j.id, j.model))
            .collect();
        BusEmulator::start(&motors, link)
    }

    /// The path to open: the symlink to the pty's slave side.
    pub fn port_path(&self) -> &Path {
        &self.link
    }

    fn with_motor<T>(
        &self,
        id: u8,
        f: impl FnOnce(&mut EmulatedMotor) -> T,
    ) -> Result<T, EmulatorError> {
        let mut state = lock(&self.state);
        state
            .motors
            .get_mut(&id)
            .map(f)
            .ok_or(EmulatorError::NoMotor(id))
    }

    /// Set a motor's Present Position (and Goal Position) register.
    pub fn set_raw_position(&self, id: u8, raw: u16) -> Result<(), EmulatorError> {
        self.with_motor(id, |m| {
            m.set_register("present_position", raw);
            m.set_register("goal_position", raw);
        })
    }

    /// A motor's Present Position register.
    pub fn raw_position(&self, id: u8) -> Result<u16, EmulatorError> {
        self.with_motor(id, |m| {
            let bytes = m
                .read(
                    protocol::PRESENT_POSITION.addr,
                    protocol::PRESENT_POSITION.len,
                )
                .unwrap_or(&[0, 0]);
            u16::from_le_bytes([bytes[0], bytes[1]])
        })
    }

    /// Make a motor answer (true) or stay silent as if unplugged from the
    /// daisy chain (false: FF FF in sync reads, no status packet otherwise).
    pub fn set_present(&self, id: u8, present: bool) -> Result<(), EmulatorError> {
        self.with_motor(id, |m| m.present = present)
    }

    /// Error bits a motor puts in its status packets (0: none).
    pub fn set_error_bits(&self, id: u8, error_bits: u8) -> Result<(), EmulatorError> {
        self.with_motor(id, |m| m.error_bits = error_bits & 0x7F)
    }

    /// Apply `fault` to every reply from now on (`None`: answer normally).
    pub fn set_fault(&self, fault: Option<Fault>) {
        lock(&self.state).fault = fault;
    }

    /// Fault each motor's reply at random from now on, as `noise` says
    /// (`None`: no random faults). The draws start again from the seed.
    pub fn set_noise(&self, noise: Option<ReplyNoise>) {
        lock(&self.state).noise = noise.map(Noise::new);
    }

    /// Replies the current [`ReplyNoise`] drew for and faulted (zeros
    /// without one).
    pub fn noise_counts(&self) -> NoiseCounts {
        lock(&self.state)
            .noise
            .as_ref()
            .map_or_else(NoiseCounts::default, |n| n.counts)
    }

    /// false: behave like an adapter without the USB2AX firmware (0x84 is
    /// forwarded to servos that ignore it: no answer).
    pub fn set_sync_read_supported(&self, supported: bool) {
        lock(&self.state).sync_read_supported = supported;
    }

    /// Delay each reply by the time its bytes (and, for a sync read, the
    /// adapter's exchanges with each servo) take on the wire at `baud`.
    /// `None` (the default) answers at once.
    pub fn set_wire_baud(&self, baud: Option<u32>) {
        lock(&self.state).wire_baud = baud.filter(|b| *b > 0);
    }

    /// Requests received so far.
    pub fn requests(&self) -> RequestCounts {
        lock(&self.state).requests
    }

    /// Unplug the adapter: close the pty and remove the link. Returns once
    /// the pty is closed.
    pub fn unplug(&self) -> Result<(), EmulatorError> {
        lock(&self.state).plugged = false;
        self.wait_pty(false, "close the pty")
    }

    /// Plug it back: a new pty behind the same link. Returns once it answers.
    pub fn replug(&self) -> Result<(), EmulatorError> {
        lock(&self.state).plugged = true;
        self.wait_pty(true, "open a new pty")
    }

    fn wait_pty(&self, open: bool, what: &'static str) -> Result<(), EmulatorError> {
        let deadline = Instant::now() + Duration::from_secs(2);
        while Instant::now() < deadline {
            if lock(&self.state).pty_open == open {
                return Ok(());
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        Err(EmulatorError::Stalled(what))
    }
}

impl Drop for BusEmulator {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        let _ = std::fs::remove_file(&self.link);
    }
}

/// Open a pty pair, point `link` at its slave, and keep only the master (the
/// reader opens the slave by path).
fn open_pty(link: &Path) -> Result<TTYPort, EmulatorError> {
    let (master, slave) = TTYPort::pair()?;
    let slave_path = slave.name().unwrap_or_default();
    drop(slave);
    let tmp = link.with_extension("emulator-new");
    let _ = std::fs::remove_file(&tmp);
    std::os::unix::fs::symlink(&slave_path, &tmp)
        .and_then(|()| std::fs::rename(&tmp, link))
        .map_err(|source| EmulatorError::Link {
            link: link.to_path_buf(),
            source,
        })?;
    Ok(master)
}

/// The emulator thread: read requests off the master, answer them.
fn serve(master: TTYPort, state: &Mutex<State>, stop: &AtomicBool, link: &Path) {
    let mut master = Some(master);
    let mut buf: Vec<u8> = Vec::with_capacity(256);
    let mut chunk = [0u8; 256];
    while !stop.load(Ordering::Relaxed) {
        let plugged = lock(state).plugged;
        if !plugged && master.is_some() {
            master = None;
            let _ = std::fs::remove_file(link);
            buf.clear();
            lock(state).pty_open = false;
        } else if plugged && master.is_none() {
            match open_pty(link) {
                Ok(port) => {
                    master = Some(port);
                    lock(state).pty_open = true;
                }
                Err(_) => std::thread::sleep(Duration::from_millis(5)),
            }
        }
        let Some(port) = master.as_mut() else {
            std::thread::sleep(Duration::from_millis(1));
            continue;
        };
        if port.set_timeout(Duration::from_millis(5)).is_err() {
            continue;
        }
        match port.read(&mut chunk) {
            Ok(n) if n > 0 => buf.extend_from_slice(&chunk[..n]),
            Ok(_) => {}
            Err(e) if e.kind() == io::ErrorKind::TimedOut => continue,
            // No slave side open (the reader is between opens): wait.
            Err(_) => {
                std::thread::sleep(Duration::from_millis(1));
                continue;
            }
        }
        loop {
            match protocol::scan(&buf) {
                Scanned::Packet { end, packet, .. } => {
                    buf.drain(..end);
                    let reply = answer(&mut lock(state), &packet);
                    if let Some((reply, delay)) = reply {
                        if !delay.is_zero() {
                            spin_sleep(delay);
                        }
                        let _ = port.write_all(&reply);
                    }
                }
                Scanned::BadChecksum { end, .. } => {
                    lock(state).requests.bad_checksums += 1;
                    buf.drain(..end);
                }
                Scanned::Incomplete { garbage } => {
                    buf.drain(..garbage);
                    break;
                }
            }
        }
    }
}

/// Sleep precisely enough for wire times of a few hundred microseconds.
fn spin_sleep(delay: Duration) {
    let until = Instant::now() + delay;
    if delay > Duration::from_micros(200) {
        std::thread::sleep(delay - Duration::from_micros(100));
    }
    while Instant::now() < until {
        std::hint::spin_loop();
    }
}

fn bits_time(bytes: usize, baud: Option<u32>) -> Duration {
    match baud {
        Some(baud) => Duration::from_nanos((bytes as u64) * 10 * 1_000_000_000 / u64::from(baud)),
        None => Duration::ZERO,
    }
}

/// The reply to one request (bytes, wire delay), or `None` for silence.
fn answer(state: &mut State, request: &Packet) -> Option<(Vec<u8>, Duration)> {
    let request_len = request.params.len() + 6;
    let (reply, wire_bytes) = match (request.id, request.byte4) {
        (BROADCAST_ID | USB2AX_ID, instruction::USB2AX_SYNC_READ) => {
            state.requests.sync_reads += 1;
            if !state.sync_read_supported || request.params.len() < 3 {
                return None;
            }
            let (addr, len) = (request.params[0], request.params[1]);
            let mut data = Vec::new();
            for id in &request.params[2..] {
                let read = state
                    .motors
                    .get(id)
                    .filter(|m| m.present)
                    .and_then(|m| m.read(addr, len))
                    .map(<[u8]>::to_vec);
                // A motor that answers, and whose answer the adapter takes:
                // any fault of it gives FF bytes (see the module doc).
                let taken = read.filter(|_| {
                    state
                        .noise
                        .as_mut()
                        .is_none_or(|n| n.draw() == ReplyFate::Clean)
                });
                match taken {
                    Some(bytes) => data.extend_from_slice(&bytes),
                    None => data.extend(std::iter::repeat_n(0xFF, usize::from(len))),
                }
            }
            // The adapter's own exchange with each servo: 8 bytes out, 6 + L back.
            let n_ids = request.params.len() - 2;
            let inner = n_ids * (8 + 6 + usize::from(len));
            let reply = protocol::packet(USB2AX_ID, 0, &data).ok()?;
            let wire = inner + request_len + reply.len();
            (reply, wire)
        }
        (BROADCAST_ID, _) | (USB2AX_ID, _) => {
            state.requests.other += 1;
            return None;
        }
        (id, inst) => {
            match inst {
                instruction::PING => state.requests.pings += 1,
                instruction::READ_DATA => state.requests.reads += 1,
                instruction::WRITE_DATA => state.requests.writes += 1,
                _ => state.requests.other += 1,
            }
            let motor = state.motors.get_mut(&id).filter(|m| m.present)?;
            let error_bits = motor.error_bits;
            let (error, params): (u8, Vec<u8>) = match inst {
                instruction::PING => (error_bits, Vec::new()),
                instruction::READ_DATA if request.params.len() == 2 => {
                    match motor.read(request.params[0], request.params[1]) {
                        Some(bytes) => (error_bits, bytes.to_vec()),
                        None => (error_bits | ERROR_RANGE, Vec::new()),
                    }
                }
                instruction::WRITE_DATA if request.params.len() >= 2 => {
                    let addr = usize::from(request.params[0]);
                    let data = &request.params[1..];
                    if addr + data.len() <= motor.registers.len() {
                        motor.registers[addr..addr + data.len()].copy_from_slice(data);
                        // The servo "arrives" at its goal at once.
                        let goal =
                            usize::from(mx::register("goal_position").map_or(30, |r| r.addr));
                        if addr <= goal + 1 && goal < addr + data.len() {
                            let position = usize::from(protocol::PRESENT_POSITION.addr);
                            let (lo, hi) = (motor.registers[goal], motor.registers[goal + 1]);
                            motor.registers[position] = lo;
                            motor.registers[position + 1] = hi;
                        }
                        (error_bits, Vec::new())
                    } else {
                        (error_bits | ERROR_RANGE, Vec::new())
                    }
                }
                _ => (error_bits | ERROR_INSTRUCTION, Vec::new()),
            };
            let reply = protocol::packet(id, error, &params).ok()?;
            let wire = request_len + reply.len();
            let mut reply = reply;
            match state.noise.as_mut().map(Noise::draw) {
                None | Some(ReplyFate::Clean) => {}
                Some(ReplyFate::Dropped) => return None,
                Some(ReplyFate::Corrupted) => {
                    if let Some(last) = reply.last_mut() {
                        *last ^= 0x5A;
                    }
                }
                Some(ReplyFate::Garbage(garbage)) => {
                    reply.splice(0..0, garbage);
                }
            }
            (reply, wire)
        }
    };
    let delay = bits_time(wire_bytes, state.wire_baud);
    match &state.fault {
        None => Some((reply, delay)),
        Some(Fault::NoReply) => None,
        Some(Fault::BadChecksum) => {
            let mut reply = reply;
            if let Some(last) = reply.last_mut() {
                *last ^= 0x5A;
            }
            Some((reply, delay))
        }
        Some(Fault::Garbage(garbage)) => {
            let mut bytes = garbage.clone();
            bytes.extend_from_slice(&reply);
            Some((bytes, delay))
        }
    }
}

/// Both Poppy Humanoid buses emulated, reachable at `dir/lower` and
/// `dir/upper`.
pub struct PoppyBuses {
    /// Motors 11-25.
    pub lower: BusEmulator,
    /// Motors 31-54.
    pub upper: BusEmulator,
}

impl PoppyBuses {
    /// Start both buses of `table` (its `lower` and `upper` motors), links in `dir`.
    pub fn start(table: &JointTable, dir: &Path) -> Result<PoppyBuses, EmulatorError> {
        Ok(PoppyBuses {
            lower: BusEmulator::for_bus(table, "lower", dir.join("lower"))?,
            upper: BusEmulator::for_bus(table, "upper", dir.join("upper"))?,
        })
    }

    /// A reader config for both buses, every key at its default.
    pub fn config(&self) -> DynamixelConfig {
        DynamixelConfig::poppy(
            self.lower.port_path().to_string_lossy(),
            self.upper.port_path().to_string_lossy(),
        )
    }

    /// The bus that holds motor `id`.
    pub fn bus_of(&self, id: u8) -> &BusEmulator {
        if lock(&self.lower.state).motors.contains_key(&id) {
            &self.lower
        } else {
            &self.upper
        }
    }

    /// Set motor `id`'s Present Position on whichever bus holds it.
    pub fn set_raw_position(&self, id: u8, raw: u16) -> Result<(), EmulatorError> {
        self.bus_of(id).set_raw_position(id, raw)
    }

    /// Every motor of `table` at the standing pose: each joint at 0 in the
    /// robot's convention (upright, arms down), where a real Poppy stands
    /// and inside the shipped networks' training ranges. The motors start
    /// at their raw centre, which puts the shoulders at +-90 deg.
    pub fn stand(&self, table: &JointTable) -> Result<(), EmulatorError> {
        for joint in table.joints() {
            self.set_raw_position(joint.id, joint.rad_to_raw(0.0))?;
        }
        Ok(())
    }
}
