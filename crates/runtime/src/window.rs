//! The tick grid, the resampling of input streams onto it, the ring of the
//! last N ticks and the `Window` arrays the network reads.
//!
//! This is the one place where windows are made. The daemon (live and replay)
//! and training both turn messages into [`Sample`]s with the conversions of
//! `streams::sample`, feed them to a [`Resampler`], which emits one [`TickInput`] per tick, and
//! cut windows with [`Window::from_ticks`] (through [`Ring::window`] live, or
//! [`EpisodeTicks::window_ending_at`] in training). Same samples in, same
//! bytes out.
//!
//! Conventions (fixed here, used everywhere):
//! - **Tick grid**: tick `k` is at `stamp_ns(k) = ceil(k * 1e12 / rate_mHz)`
//!   nanoseconds on the stream clock: the grid is anchored at clock zero,
//!   not at the first sample, so every process that sees the same clock
//!   agrees on tick numbers. (At 30 Hz tick 1 is at 33_333_334 ns; the
//!   rounding up means a sample stamped `k / rate` seconds, however the writer
//!   rounded it to ns, is at or before tick `k`.) The first tick a
//!   [`Resampler`] emits is the first grid tick at or after the first time it
//!   is given (a sample's stamp or an `advance_to` time).
//! - **Resampling**: zero-order hold for every stream: a tick sees the last
//!   sample whose stamp is at or before the tick's stamp. Joints are held
//!   per joint: a joints sample with NaN for a joint (a motor that did not
//!   answer that cycle) leaves that joint's earlier value and stamp, so a
//!   tick's joints age is the age of its oldest joint
//!   ([`TickInput::joint_age_ns`] per joint). A joint's stamp is the time
//!   its value was read: the sample's `read_ns` entry when it has one (the
//!   servo buses, read one after the other), else the sample's stamp. A
//!   joints sample takes effect at its stamp, the newest of its reads.
//!   Joints are not interpolated.
//! - **Plan**: the latest plan message at tick `t` is evaluated at the stamps
//!   of ticks `t-N+1 ..= t+hK` by linear interpolation between its points
//!   (point time = `header.stamp + time_from_start`), holding the first and
//!   last point outside their span; computed in `f64`, stored as `f32`.
//! - **Joints** are reordered by name into the model's order
//!   ([`WindowSpec::joint_names`]); a joint missing from a message is an error.
//! - **Frames** are decoded and resized to S x S once, when they arrive
//!   ([`crate::frame::decode_compressed`]), and enter the window as
//!   `value / 255`. Episodes read for training and evaluation
//!   ([`FrameStorage::Compressed`]) keep them as recorded instead, checked
//!   to decode at load, and decode them (to the same bytes) when a window
//!   is built ([`TickFrame`]).

use std::borrow::Cow;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::clock::{BadRate, TickGrid};
use crate::frame::{CompressedFrame, Frame, FrameError};
use crate::msgs::{CompressedImage, JointState, JointTrajectory};
use crate::recording::{topics, Logged, Recording};
use crate::streams::sample::{Plan, Sample, SampleError};
use crate::streams::{PerStream, StreamKind};

/// A resampler that sees no sample for longer than this restarts its grid at
/// the next sample instead of emitting every tick of the gap.
pub const MAX_GAP_TICKS: i64 = 1_000_000;

/// Why a sample, tick or window could not be made.
#[derive(Debug, thiserror::Error)]
pub enum WindowError {
    #[error(transparent)]
    BadRate(#[from] BadRate),
    #[error("bad window spec: {reason}")]
    BadSpec { reason: String },
    /// A message that does not convert to model form.
    #[error(transparent)]
    Sample(#[from] SampleError),
    #[error("window ending at tick {end_tick} needs {need} consecutive ticks, has {have}")]
    NotFull {
        end_tick: i64,
        have: usize,
        need: usize,
    },
    #[error("window ending at tick {end_tick}: no {stream} sample yet at tick {tick}")]
    MissingStream {
        end_tick: i64,
        stream: &'static str,
        tick: i64,
    },
    #[error("tick {tick} is outside the episode's ticks {first} ..= {last}")]
    TickOutOfRange { tick: i64, first: i64, last: i64 },
    #[error("{}: {topic} message at log time {log_time_ns} ns: {source}", path.display())]
    InRecording {
        path: PathBuf,
        topic: &'static str,
        log_time_ns: i64,
        source: Box<SampleError>,
    },
    #[error("{}: recording has no messages on {topic} (needed)", path.display())]
    NoSamples { path: PathBuf, topic: &'static str },
}

/// What the model's input windows are made of. Comes from the model file
/// (`ModelMeta`) or the training config.
#[derive(Debug, Clone, PartialEq)]
pub struct WindowSpec {
    /// `N`: ticks of past input, ending at the current tick.
    pub n_ticks: usize,
    /// `hK`: the longest horizon; the plan runs this many ticks past `t`.
    pub max_horizon_ticks: usize,
    pub rate_hz: f64,
    /// `C` joint names, in model order.
    pub joint_names: Vec<String>,
    /// `S`: frames are S x S.
    pub frame_size: u32,
}

impl WindowSpec {
    /// Checks the spec and returns its tick grid.
    pub fn grid(&self) -> Result<TickGrid, WindowError> {
        if self.n_ticks == 0 {
            return Err(WindowError::BadSpec {
                reason: "n_ticks must be at least 1".into(),
            });
        }
        if self.joint_names.is_empty() {
            return Err(WindowError::BadSpec {
                reason: "joint_names is empty".into(),
            });
        }
        if self.frame_size == 0 {
            return Err(WindowError::BadSpec {
                reason: "frame_size must be at least 1".into(),
            });
        }
        Ok(TickGrid::new(self.rate_hz)?)
    }

    /// `N + hK`: plan ticks per window.
    pub fn plan_len(&self) -> usize {
        self.n_ticks + self.max_horizon_ticks
    }

    /// `C`.
    pub fn n_joints(&self) -> usize {
        self.joint_names.len()
    }
}

/// Per stream, ns from the last sample to the tick (`None`: no sample yet).
pub type StreamAges = PerStream<Option<i64>>;

/// The frame a tick holds.
#[derive(Debug, Clone, PartialEq)]
pub enum TickFrame {
    /// Decoded and resized to S x S on arrival (the daemon, live and replay).
    Decoded(Arc<Frame>),
    /// As recorded, decoded when a window is built (training and evaluation
    /// episodes, [`FrameStorage::Compressed`]).
    Compressed(Arc<CompressedFrame>),
}

impl TickFrame {
    /// Width and height of the decoded frame.
    pub fn dimensions(&self) -> (u32, u32) {
        match self {
            TickFrame::Decoded(f) => (f.width, f.height),
            TickFrame::Compressed(c) => (c.size(), c.size()),
        }
    }

    /// The decoded frame: borrowed when it is decoded already.
    pub fn decoded(&self) -> Result<Cow<'_, Frame>, FrameError> {
        match self {
            TickFrame::Decoded(f) => Ok(Cow::Borrowed(f)),
            TickFrame::Compressed(c) => c.decode().map(Cow::Owned),
        }
    }

    /// Whether both hold the very same frame (not a copy of it).
    pub fn same_as(&self, other: &TickFrame) -> bool {
        match (self, other) {
            (TickFrame::Decoded(a), TickFrame::Decoded(b)) => Arc::ptr_eq(a, b),
            (TickFrame::Compressed(a), TickFrame::Compressed(b)) => Arc::ptr_eq(a, b),
            _ => false,
        }
    }
}

impl From<Arc<Frame>> for TickFrame {
    fn from(frame: Arc<Frame>) -> TickFrame {
        TickFrame::Decoded(frame)
    }
}

impl From<Frame> for TickFrame {
    fn from(frame: Frame) -> TickFrame {
        TickFrame::Decoded(Arc::new(frame))
    }
}

/// How an episode read from a recording holds its frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FrameStorage {
    /// Decoded once at load, as the daemon holds them (what a tick-by-tick
    /// replay through the streaming forecaster reads fastest).
    #[default]
    Decoded,
    /// As recorded (JPEG or PNG bytes, ~10 times smaller), checked to decode
    /// at load, decoded when a window is built: the splits of a data set.
    Compressed,
}

/// One tick of resampled inputs (zero-order hold: last sample at or before the tick).
#[derive(Debug, Clone, PartialEq)]
pub struct TickInput {
    pub tick: i64,
    pub stamp_ns: i64,
    /// `C` values in model order; `None` until the first sample.
    pub joints_rad: Option<Vec<f32>>,
    /// Latest frame, S x S once decoded.
    pub frame: Option<TickFrame>,
    /// Latest plan.
    pub plan: Option<Arc<Plan>>,
    /// Per stream, ns from the sample held to the tick; for the joints, the
    /// age of the oldest joint value held.
    pub age_ns: StreamAges,
    /// Per joint (model order), the stamp of the value held, when the
    /// joints' values were not all read at once (a servo reading that
    /// missed some motors keeps their earlier values); `None` when every
    /// value is from the latest joints sample (`age_ns.joints`).
    pub joint_stamps_ns: Option<Arc<[Option<i64>]>>,
}

impl TickInput {
    /// Age at this tick of joint `index`'s value, ns (`None`: never read).
    pub fn joint_age_ns(&self, index: usize) -> Option<i64> {
        match &self.joint_stamps_ns {
            Some(stamps) => stamps
                .get(index)
                .copied()
                .flatten()
                .map(|s| self.stamp_ns - s),
            None => self
                .joints_rad
                .as_ref()
                .and_then(|j| j.get(index))
                .filter(|v| v.is_finite())
                .and(self.age_ns.joints),
        }
    }
}

/// Which streams a window must hold (an ablation without vision does not
/// need the camera's frames).
pub type Streams = PerStream<bool>;

impl PerStream<bool> {
    /// Every stream.
    pub const ALL: Streams = Streams {
        joints: true,
        camera: true,
        plan: true,
    };

    /// Whether `tick` has every stream needed here.
    pub fn present_in(&self, tick: &TickInput) -> bool {
        (!self.joints || tick.joints_rad.is_some())
            && (!self.plan || tick.plan.is_some())
            && (!self.camera || tick.frame.is_some())
    }
}

/// The joints a [`Resampler`] holds: each joint's latest finite angle and
/// the stamp it was read at (its own read stamp when the sample has them).
/// A joints sample with NaN for a joint (the servo source: that motor did
/// not answer this cycle) updates the others only.
#[derive(Debug, Clone)]
struct JointHold {
    /// Stamp of the latest joints sample.
    latest_ns: i64,
    values: Vec<f32>,
    /// Per joint, when its value was read (`None`: never).
    stamps: Vec<Option<i64>>,
    /// `stamps` as the ticks share it, when some value is older than the
    /// latest sample; `None` when every joint was read in it.
    shared: Option<Arc<[Option<i64>]>>,
}

impl JointHold {
    fn new(stamp_ns: i64, positions_rad: &[f32], read_ns: Option<&[i64]>) -> JointHold {
        let stamps = vec![None; positions_rad.len()];
        let mut hold = JointHold {
            latest_ns: stamp_ns,
            values: vec![f32::NAN; positions_rad.len()],
            stamps,
            shared: None,
        };
        hold.update(stamp_ns, positions_rad, read_ns);
        hold
    }

    /// Takes the finite values of a sample stamped `stamp_ns`, each read at
    /// its `read_ns` entry (all at `stamp_ns` without them). A value read
    /// before the one held is not taken.
    fn update(&mut self, stamp_ns: i64, positions_rad: &[f32], read_ns: Option<&[i64]>) {
        if positions_rad.len() != self.values.len() {
            // Another joint count: nothing earlier applies.
            self.values = vec![f32::NAN; positions_rad.len()];
            self.stamps = vec![None; positions_rad.len()];
        }
        self.latest_ns = stamp_ns;
        let read_ns = read_ns.filter(|r| r.len() == positions_rad.len());
        for (i, ((value, stamp), &v)) in self
            .values
            .iter_mut()
            .zip(&mut self.stamps)
            .zip(positions_rad)
            .enumerate()
        {
            let read = read_ns.map_or(stamp_ns, |r| r[i].min(stamp_ns));
            if v.is_finite() && stamp.is_none_or(|held| read >= held) {
                *value = v;
                *stamp = Some(read);
            }
        }
        self.shared = (!self.stamps.iter().all(|s| *s == Some(stamp_ns)))
            .then(|| Arc::from(self.stamps.as_slice()));
    }

    /// Age at `stamp_ns` of the oldest value held (`None`: no joint read yet).
    fn age_ns(&self, stamp_ns: i64) -> Option<i64> {
        if self.shared.is_none() {
            return Some(stamp_ns - self.latest_ns);
        }
        self.stamps.iter().flatten().min().map(|s| stamp_ns - s)
    }
}

/// Turns time-ordered samples into one [`TickInput`] per grid tick.
///
/// [`push`](Self::push) a sample: every tick strictly before its stamp is
/// final and is emitted, then the sample becomes its stream's latest value.
/// [`advance_to`](Self::advance_to) a time: every tick at or before it is
/// emitted (the caller promises no sample at or before that time will come).
/// The ticks emitted depend only on the samples and the final time, not on
/// how the calls interleave, provided each sample is pushed before any
/// `advance_to` past its stamp. A sample older than its stream's latest is
/// dropped and counted ([`dropped_out_of_order`](Self::dropped_out_of_order)).
#[derive(Debug, Clone)]
pub struct Resampler {
    grid: TickGrid,
    next_tick: Option<i64>,
    joints: Option<JointHold>,
    frame: Option<(i64, TickFrame)>,
    plan: Option<(i64, Arc<Plan>)>,
    dropped: u64,
}

impl Resampler {
    pub fn new(spec: &WindowSpec) -> Result<Resampler, WindowError> {
        Ok(Resampler {
            grid: spec.grid()?,
            next_tick: None,
            joints: None,
            frame: None,
            plan: None,
            dropped: 0,
        })
    }

    pub fn grid(&self) -> TickGrid {
        self.grid
    }

    /// The next tick that will be emitted (`None` before the first call).
    pub fn next_tick(&self) -> Option<i64> {
        self.next_tick
    }

    /// Samples dropped because they were older than their stream's latest.
    pub fn dropped_out_of_order(&self) -> u64 {
        self.dropped
    }

    /// Feed one sample; ticks that became final are appended to `out`.
    pub fn push(&mut self, sample: Sample, out: &mut Vec<TickInput>) {
        let stamp_ns = sample.stamp_ns();
        self.start_or_jump(stamp_ns);
        // Ticks strictly before this sample can no longer change.
        self.emit_while(out, |stamp| stamp < stamp_ns);
        let newer = |latest: Option<i64>| latest.is_none_or(|t| stamp_ns >= t);
        match sample {
            Sample::Joints {
                stamp_ns,
                positions_rad,
                read_ns,
            } => {
                if !newer(self.joints.as_ref().map(|x| x.latest_ns)) {
                    self.dropped += 1;
                } else if let Some(hold) = self.joints.as_mut() {
                    hold.update(stamp_ns, &positions_rad, read_ns.as_deref());
                } else {
                    self.joints =
                        Some(JointHold::new(stamp_ns, &positions_rad, read_ns.as_deref()));
                }
            }
            Sample::Frame { stamp_ns, frame } => {
                if newer(self.frame.as_ref().map(|x| x.0)) {
                    self.frame = Some((stamp_ns, TickFrame::Decoded(frame)));
                } else {
                    self.dropped += 1;
                }
            }
            Sample::Plan { stamp_ns, plan } => {
                if newer(self.plan.as_ref().map(|x| x.0)) {
                    self.plan = Some((stamp_ns, plan));
                } else {
                    self.dropped += 1;
                }
            }
        }
    }

    /// Feed one frame as [`push`](Self::push) feeds a `Sample::Frame`, held
    /// as it is given (compressed or decoded).
    pub fn push_frame(&mut self, stamp_ns: i64, frame: TickFrame, out: &mut Vec<TickInput>) {
        self.start_or_jump(stamp_ns);
        self.emit_while(out, |stamp| stamp < stamp_ns);
        if self.frame.as_ref().is_none_or(|(t, _)| stamp_ns >= *t) {
            self.frame = Some((stamp_ns, frame));
        } else {
            self.dropped += 1;
        }
    }

    /// Emit every tick whose stamp is at or before `now_ns`.
    pub fn advance_to(&mut self, now_ns: i64, out: &mut Vec<TickInput>) {
        self.start_or_jump(now_ns);
        self.emit_while(out, |stamp| stamp <= now_ns);
    }

    fn start_or_jump(&mut self, t_ns: i64) {
        let first = self.grid.first_tick_at_or_after(t_ns);
        match self.next_tick {
            None => self.next_tick = Some(first),
            Some(next) if first - next > MAX_GAP_TICKS => {
                tracing::warn!(
                    from_tick = next,
                    to_tick = first,
                    "input gap longer than {MAX_GAP_TICKS} ticks: tick grid restarts"
                );
                self.next_tick = Some(first);
            }
            Some(_) => {}
        }
    }

    fn emit_while(&mut self, out: &mut Vec<TickInput>, keep_going: impl Fn(i64) -> bool) {
        let Some(mut tick) = self.next_tick else {
            return;
        };
        loop {
            let stamp_ns = self.grid.stamp_ns(tick);
            if !keep_going(stamp_ns) {
                break;
            }
            out.push(TickInput {
                tick,
                stamp_ns,
                joints_rad: self.joints.as_ref().map(|h| h.values.clone()),
                frame: self.frame.as_ref().map(|(_, f)| f.clone()),
                plan: self.plan.as_ref().map(|(_, p)| Arc::clone(p)),
                age_ns: StreamAges {
                    joints: self.joints.as_ref().and_then(|h| h.age_ns(stamp_ns)),
                    camera: self.frame.as_ref().map(|(t, _)| stamp_ns - t),
                    plan: self.plan.as_ref().map(|(t, _)| stamp_ns - t),
                },
                joint_stamps_ns: self.joints.as_ref().and_then(|h| h.shared.clone()),
            });
            tick += 1;
        }
        self.next_tick = Some(tick);
    }
}

/// The network's input for the window ending at `end_tick` (row-major arrays).
#[derive(Debug, Clone, PartialEq)]
pub struct Window {
    pub end_tick: i64,
    /// `[N, C]` radians (empty when joints were not asked for).
    pub joints: Vec<f32>,
    /// `[N + hK, C]` radians (empty when the plan was not asked for).
    pub plan: Vec<f32>,
    /// `[3, N, S, S]` in `[0, 1]` (empty when frames were not asked for).
    pub frames: Vec<f32>,
}

impl Window {
    /// Builds the window from `N` consecutive ticks, oldest first. The one
    /// function that makes windows; the plan comes from the last tick.
    pub fn from_ticks<'a, I>(
        ticks: I,
        spec: &WindowSpec,
        needs: Streams,
    ) -> Result<Window, WindowError>
    where
        I: IntoIterator<Item = &'a TickInput>,
        I::IntoIter: ExactSizeIterator + Clone,
    {
        let grid = spec.grid()?;
        let ticks = ticks.into_iter();
        let (n, c, s) = (spec.n_ticks, spec.n_joints(), spec.frame_size as usize);
        let Some(last) = ticks.clone().last() else {
            return Err(WindowError::NotFull {
                end_tick: 0,
                have: 0,
                need: n,
            });
        };
        let end_tick = last.tick;
        let consecutive = ticks
            .clone()
            .enumerate()
            .all(|(i, t)| t.tick == end_tick - (ticks.len() - 1 - i) as i64);
        if ticks.len() != n || !consecutive {
            return Err(WindowError::NotFull {
                end_tick,
                have: if consecutive { ticks.len() } else { 0 },
                need: n,
            });
        }
        let missing = |stream, tick| WindowError::MissingStream {
            end_tick,
            stream,
            tick,
        };
        let mut joints = Vec::new();
        if needs.joints {
            joints.reserve_exact(n * c);
            for t in ticks.clone() {
                let j = t
                    .joints_rad
                    .as_ref()
                    .ok_or_else(|| missing("joints", t.tick))?;
                if j.len() != c {
                    return Err(WindowError::BadSpec {
                        reason: format!("tick {} has {} joints, spec has {c}", t.tick, j.len()),
                    });
                }
                joints.extend_from_slice(j);
            }
        }
        let mut plan_out = Vec::new();
        if needs.plan {
            let plan = last
                .plan
                .as_ref()
                .ok_or_else(|| missing("plan", end_tick))?;
            if plan.n_joints != c {
                return Err(WindowError::BadSpec {
                    reason: format!("plan has {} joints, spec has {c}", plan.n_joints),
                });
            }
            let first_tick = end_tick - n as i64 + 1;
            plan_out = vec![0f32; spec.plan_len() * c];
            for (i, row) in plan_out.chunks_exact_mut(c).enumerate() {
                plan.sample_into(grid.stamp_ns(first_tick + i as i64), row);
            }
        }
        let mut frames = Vec::new();
        if needs.camera {
            let plane = s * s;
            frames = vec![0f32; 3 * n * plane];
            // A compressed frame held over several ticks is decoded once.
            let mut last: Option<(&TickFrame, Cow<'_, Frame>)> = None;
            for (i, t) in ticks.clone().enumerate() {
                let held = t.frame.as_ref().ok_or_else(|| missing("frames", t.tick))?;
                let (w, h) = held.dimensions();
                if w as usize != s || h as usize != s {
                    return Err(WindowError::BadSpec {
                        reason: format!("tick {} has a {w}x{h} frame, spec wants {s}x{s}", t.tick),
                    });
                }
                if !last.as_ref().is_some_and(|(f, _)| f.same_as(held)) {
                    let decoded = held.decoded().map_err(|source| SampleError::Frame {
                        topic: topics::HEAD_CAMERA,
                        source,
                    })?;
                    last = Some((held, decoded));
                }
                let f = &last.as_ref().expect("decoded above").1;
                // channel c of tick i starts at (c * N + i) * S * S
                f.write_chw(&mut frames[i * plane..], n * plane);
            }
        }
        Ok(Window {
            end_tick,
            joints,
            plan: plan_out,
            frames,
        })
    }
}

/// The last `N` ticks, as the daemon keeps them.
#[derive(Debug, Clone)]
pub struct Ring {
    capacity: usize,
    ticks: VecDeque<TickInput>,
}

impl Ring {
    pub fn new(n_ticks: usize) -> Ring {
        Ring {
            capacity: n_ticks.max(1),
            ticks: VecDeque::with_capacity(n_ticks.max(1)),
        }
    }

    /// Adds the next tick. A tick that does not follow the previous one
    /// (a gap, or time going back) empties the ring first: a window is
    /// always `N` consecutive ticks.
    pub fn push(&mut self, tick: TickInput) {
        if let Some(last) = self.ticks.back() {
            if tick.tick != last.tick + 1 {
                tracing::debug!(
                    last = last.tick,
                    next = tick.tick,
                    "tick gap: ring restarts"
                );
                self.ticks.clear();
            }
        }
        if self.ticks.len() == self.capacity {
            self.ticks.pop_front();
        }
        self.ticks.push_back(tick);
    }

    pub fn is_full(&self) -> bool {
        self.ticks.len() == self.capacity
    }

    pub fn len(&self) -> usize {
        self.ticks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ticks.is_empty()
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn latest(&self) -> Option<&TickInput> {
        self.ticks.back()
    }

    /// Oldest first.
    pub fn iter(&self) -> impl ExactSizeIterator<Item = &TickInput> + Clone {
        self.ticks.iter()
    }

    pub fn clear(&mut self) {
        self.ticks.clear();
    }

    /// The full window (all streams), or `None` until the ring is full and
    /// every stream has a sample in every tick of it.
    pub fn window(&self, spec: &WindowSpec) -> Option<Window> {
        self.try_window(spec, Streams::ALL).ok()
    }

    /// The window with the streams in `needs`, or why not.
    pub fn try_window(&self, spec: &WindowSpec, needs: Streams) -> Result<Window, WindowError> {
        Window::from_ticks(self.ticks.iter(), spec, needs)
    }
}

/// Every tick of one recording, as the daemon would have seen them replaying it.
#[derive(Debug, Clone)]
pub struct EpisodeTicks {
    pub path: PathBuf,
    pub grid: TickGrid,
    /// Consecutive ticks, `ticks[i].tick == first_tick() + i`.
    pub ticks: Vec<TickInput>,
    /// First tick at or after the recorded fall onset (`None`: no fall).
    pub fall_onset_tick: Option<i64>,
}

impl EpisodeTicks {
    /// Resamples a recording: its messages become samples (in log-time
    /// order, ties in file order) fed to a [`Resampler`], advanced to the
    /// last message's log time. Needs `/joint_states`; the fall onset comes
    /// from the episode metadata (absent metadata = no fall).
    pub fn from_recording(rec: &Recording, spec: &WindowSpec) -> Result<EpisodeTicks, WindowError> {
        Self::from_recording_as(rec, spec, FrameStorage::Decoded)
    }

    /// [`from_recording`](Self::from_recording) with the frames held as
    /// `storage` says: the same ticks, and windows of the same bytes.
    pub fn from_recording_as(
        rec: &Recording,
        spec: &WindowSpec,
        storage: FrameStorage,
    ) -> Result<EpisodeTicks, WindowError> {
        let inputs = match storage {
            FrameStorage::Decoded => samples_from_recording(rec, spec)?
                .into_iter()
                .map(EpisodeInput::Sample)
                .collect(),
            FrameStorage::Compressed => inputs_with_compressed_frames(rec, spec)?,
        };
        let end_ns = rec.end_ns().ok_or_else(|| WindowError::NoSamples {
            path: rec.path.clone(),
            topic: topics::JOINT_STATES,
        })?;
        let onset = rec.episode.as_ref().and_then(|m| m.fall_onset_ns);
        Self::from_inputs(&rec.path, inputs, end_ns, onset, spec)
    }

    /// Resamples time-ordered samples up to `end_ns`.
    pub fn from_samples(
        path: &Path,
        samples: Vec<Sample>,
        end_ns: i64,
        fall_onset_ns: Option<i64>,
        spec: &WindowSpec,
    ) -> Result<EpisodeTicks, WindowError> {
        let inputs = samples.into_iter().map(EpisodeInput::Sample).collect();
        Self::from_inputs(path, inputs, end_ns, fall_onset_ns, spec)
    }

    fn from_inputs(
        path: &Path,
        inputs: Vec<EpisodeInput>,
        end_ns: i64,
        fall_onset_ns: Option<i64>,
        spec: &WindowSpec,
    ) -> Result<EpisodeTicks, WindowError> {
        let mut resampler = Resampler::new(spec)?;
        let mut ticks = Vec::new();
        for input in inputs {
            match input {
                EpisodeInput::Sample(sample) => resampler.push(sample, &mut ticks),
                EpisodeInput::Frame { stamp_ns, frame } => {
                    resampler.push_frame(stamp_ns, frame, &mut ticks)
                }
            }
        }
        resampler.advance_to(end_ns, &mut ticks);
        let grid = resampler.grid();
        // A restarted grid (huge gap) would break tick continuity: keep the last run.
        if let Some(cut) = ticks.windows(2).rposition(|w| w[1].tick != w[0].tick + 1) {
            ticks.drain(..=cut);
        }
        // Held for the whole run (a data set's splits): no spare capacity.
        ticks.shrink_to_fit();
        Ok(EpisodeTicks {
            path: path.to_path_buf(),
            grid,
            ticks,
            fall_onset_tick: fall_onset_ns.map(|t| grid.first_tick_at_or_after(t)),
        })
    }

    pub fn first_tick(&self) -> Option<i64> {
        self.ticks.first().map(|t| t.tick)
    }

    pub fn last_tick(&self) -> Option<i64> {
        self.ticks.last().map(|t| t.tick)
    }

    pub fn get(&self, tick: i64) -> Option<&TickInput> {
        let first = self.first_tick()?;
        usize::try_from(tick - first)
            .ok()
            .and_then(|i| self.ticks.get(i))
    }

    /// Ground truth at `tick` (sticky: fallen from the onset tick on).
    pub fn is_fallen(&self, tick: i64) -> bool {
        self.fall_onset_tick.is_some_and(|onset| tick >= onset)
    }

    /// The first end tick whose window is full and has every stream in `needs`
    /// (streams never disappear once seen: zero-order hold).
    pub fn first_complete_end_tick(&self, n_ticks: usize, needs: Streams) -> Option<i64> {
        let first_present = self.ticks.iter().find(|t| needs.present_in(t))?.tick;
        let end = first_present.max(self.first_tick()?) + n_ticks as i64 - 1;
        (end <= self.last_tick()?).then_some(end)
    }

    /// The window ending at `end_tick`.
    pub fn window_ending_at(
        &self,
        end_tick: i64,
        spec: &WindowSpec,
        needs: Streams,
    ) -> Result<Window, WindowError> {
        let (Some(first), Some(last)) = (self.first_tick(), self.last_tick()) else {
            return Err(WindowError::TickOutOfRange {
                tick: end_tick,
                first: 0,
                last: -1,
            });
        };
        let start = end_tick - spec.n_ticks as i64 + 1;
        if start < first || end_tick > last {
            return Err(WindowError::TickOutOfRange {
                tick: if end_tick > last { end_tick } else { start },
                first,
                last,
            });
        }
        let from = (start - first) as usize;
        Window::from_ticks(&self.ticks[from..from + spec.n_ticks], spec, needs)
    }
}

/// A recording's messages as samples in model form, sorted by log time (ties
/// keep file order). Training uses this: a message that does not convert is
/// an error naming it (a replay rejects it instead, [`recorded_samples`]).
pub fn samples_from_recording(
    rec: &Recording,
    spec: &WindowSpec,
) -> Result<Vec<Sample>, WindowError> {
    require_joint_states(rec)?;
    recorded_samples(rec, spec)
        .into_iter()
        .map(|r| r.sample.map_err(in_recording(rec, r.topic, r.stamp_ns)))
        .collect()
}

/// A recording without joint states has nothing to make a window of.
fn require_joint_states(rec: &Recording) -> Result<(), WindowError> {
    if rec.joint_states.is_empty() {
        return Err(WindowError::NoSamples {
            path: rec.path.clone(),
            topic: topics::JOINT_STATES,
        });
    }
    Ok(())
}

/// What a recording's episode is resampled from: a sample, or a frame held
/// as it is (compressed).
enum EpisodeInput {
    Sample(Sample),
    Frame { stamp_ns: i64, frame: TickFrame },
}

/// [`samples_from_recording`] with the camera's frames kept as recorded
/// (checked to decode, [`CompressedFrame::new`]): the same inputs in the same
/// order, and the same error for a message that does not convert.
fn inputs_with_compressed_frames(
    rec: &Recording,
    spec: &WindowSpec,
) -> Result<Vec<EpisodeInput>, WindowError> {
    require_joint_states(rec)?;
    let converted = convert_messages(
        rec,
        |msg, stamp_ns| {
            Sample::joints_from_msg(msg, &spec.joint_names, stamp_ns).map(EpisodeInput::Sample)
        },
        |msg, stamp_ns| {
            let frame = CompressedFrame::new(&msg.format, msg.data.clone(), spec.frame_size)
                .map_err(|source| SampleError::Frame {
                    topic: topics::HEAD_CAMERA,
                    source,
                })?;
            Ok(EpisodeInput::Frame {
                stamp_ns,
                frame: TickFrame::Compressed(Arc::new(frame)),
            })
        },
        |msg, stamp_ns| {
            Sample::plan_from_msg(msg, &spec.joint_names, stamp_ns).map(EpisodeInput::Sample)
        },
    );
    converted
        .into_iter()
        .map(|c| c.sample.map_err(in_recording(rec, c.topic, c.stamp_ns)))
        .collect()
}

/// Each of `messages`, of stream `kind`, converted, into `out`.
fn convert_stream<M, T>(
    out: &mut Vec<RecordedSample<T>>,
    kind: StreamKind,
    messages: &[Logged<M>],
    convert: impl Fn(&M, i64) -> Result<T, SampleError>,
) {
    out.extend(messages.iter().map(|m| RecordedSample {
        kind,
        topic: topics::of_stream(kind),
        stamp_ns: m.log_time_ns,
        file_order: m.file_order,
        sample: convert(&m.msg, m.log_time_ns),
    }));
}

/// Every message of the input streams of `rec`, each converted by its
/// stream's function (message, log time), in log-time order (ties in file
/// order).
fn convert_messages<T>(
    rec: &Recording,
    joints: impl Fn(&JointState, i64) -> Result<T, SampleError>,
    image: impl Fn(&CompressedImage, i64) -> Result<T, SampleError>,
    plan: impl Fn(&JointTrajectory, i64) -> Result<T, SampleError>,
) -> Vec<RecordedSample<T>> {
    let mut out = Vec::with_capacity(rec.joint_states.len() + rec.images.len() + rec.plans.len());
    convert_stream(&mut out, StreamKind::Joints, &rec.joint_states, joints);
    convert_stream(&mut out, StreamKind::Camera, &rec.images, image);
    convert_stream(&mut out, StreamKind::Plan, &rec.plans, plan);
    out.sort_by_key(|r| (r.stamp_ns, r.file_order));
    out
}

/// A message of `rec` that did not convert, named by its topic and log time.
fn in_recording<'a>(
    rec: &'a Recording,
    topic: &'static str,
    log_time_ns: i64,
) -> impl FnOnce(SampleError) -> WindowError + 'a {
    move |e| WindowError::InRecording {
        path: rec.path.clone(),
        topic,
        log_time_ns,
        source: Box::new(e),
    }
}

/// One recorded message of an input stream in model form (`T`), or why
/// it is not one.
#[derive(Debug)]
pub struct RecordedSample<T = Sample> {
    pub kind: StreamKind,
    pub topic: &'static str,
    /// Its log time, ns.
    pub stamp_ns: i64,
    pub file_order: u64,
    pub sample: Result<T, SampleError>,
}

/// Every message of the input streams of `rec`, converted one by one (as
/// [`samples_from_recording`] does), in log-time order (ties in file
/// order). A replay offers each to its stream's input boundary, which
/// rejects the ones that did not convert.
pub fn recorded_samples(rec: &Recording, spec: &WindowSpec) -> Vec<RecordedSample> {
    convert_messages(
        rec,
        |msg, stamp_ns| Sample::joints_from_msg(msg, &spec.joint_names, stamp_ns),
        |msg, stamp_ns| Sample::frame_from_msg(msg, spec.frame_size, stamp_ns),
        |msg, stamp_ns| Sample::plan_from_msg(msg, &spec.joint_names, stamp_ns),
    )
}
