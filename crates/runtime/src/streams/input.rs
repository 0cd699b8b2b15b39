//! The input boundary: the one place where a sample of any stream is
//! checked, numbered and either admitted or rejected.
//!
//! Every source (servo bus, ROS 2 subscription, V4L2 camera, replay) turns
//! what it read into a model-form value and a stamp, then hands both to a
//! [`Gate`] (live: through [`super::StreamFeed::offer`], which owns one).
//! [`validate`] checks the stamp against the tick clock and the value
//! against the model's shape; an admitted sample gets the next sequence
//! number of its stream (`seq`, from 1), a rejected one is counted per
//! stream and per [`Rejection`] reason in [`StreamStats`] (shown on
//! `/diagnostics` as `rejected_<reason>`, `last_rejection`) and goes no
//! further: it never reaches the ring, never moves the tick clock, and is
//! never republished.
//!
//! Conversion errors of a source (an undecodable JPEG, a `JointState` that
//! lacks a model joint, a trajectory with no points) are typed here too
//! ([`Rejection::from_sample`], [`Rejection::from_frame`]), so that a
//! subscriber and an operator see one vocabulary of reasons whatever the
//! source.
//!
//! Adding a stream (an IMU, say): a [`StreamKind`] variant and its field in
//! [`PerStream`] (`sources/mod.rs`), a [`ValueRef`] variant and its checks
//! in [`validate`] (here), its `[streams].imu_stale_ms` in the config.

use std::fmt;
use std::sync::Arc;
use std::sync::Mutex;

use crate::frame::Frame;
use crate::streams::sample::{Plan, Sample, SampleError};

use super::{StreamKind, StreamStats};

/// What the boundary checks a sample against.
#[derive(Debug, Clone, PartialEq)]
pub struct InputLimits {
    /// A stamp later than the tick clock by more than this is rejected
    /// (`[streams].max_future_ms`).
    pub max_future_ns: i64,
    /// A stamp older than the tick clock by more than this is rejected
    /// (`[streams].max_past_ms`).
    pub max_past_ns: i64,
    /// `C`: joints per reading, in model order.
    pub n_joints: usize,
    /// `S`: frames are S x S.
    pub frame_size: u32,
    /// Each model joint's range for planned positions (radians, model
    /// order): the joint's limits widened by `[streams].plan_limit_margin_deg`.
    /// A plan beyond them is a planner's error, not a motion the robot can
    /// make. `None`: not checked.
    pub plan_range_rad: Option<Arc<[(f64, f64)]>>,
    /// A compressed camera image larger than this is rejected before it is
    /// decoded (`[streams].max_image_bytes`).
    pub max_image_bytes: usize,
}

impl InputLimits {
    /// The size check of a compressed image of `bytes` bytes, before
    /// anything decodes it.
    pub fn image_size(&self, bytes: usize) -> Result<(), Rejection> {
        if bytes > self.max_image_bytes {
            return Err(Rejection::TooLarge {
                bytes,
                max: self.max_image_bytes,
            });
        }
        Ok(())
    }

    /// Limits that check only the shapes (tests, tools).
    pub fn shapes(n_joints: usize, frame_size: u32) -> InputLimits {
        InputLimits {
            max_future_ns: 250_000_000,
            max_past_ns: 10_000_000_000,
            n_joints,
            frame_size,
            plan_range_rad: None,
            max_image_bytes: usize::MAX,
        }
    }
}

/// Why a sample was not admitted. [`Rejection::key`] names it on
/// `/diagnostics` (`rejected_<key>`).
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    /// Stamped later than the tick clock allows.
    FutureStamp { ahead_ms: i64 },
    /// Stamped too long before the tick clock.
    PastStamp { age_ms: i64 },
    /// Stamped before the stream's last admitted sample.
    OutOfOrder { behind_ms: i64 },
    /// A position that is not a number (or infinite).
    NonFinite { what: String },
    /// Joint names or counts that do not fit the model's joints.
    WrongJoints { what: String },
    /// A frame that is not S x S.
    FrameSize {
        width: u32,
        height: u32,
        expected: u32,
    },
    /// Image bytes that do not decode.
    Undecodable { what: String },
    /// A trajectory with no points.
    EmptyPlan,
    /// A planned position beyond its joint's limits.
    OutOfLimits { what: String },
    /// An image larger than `[streams].max_image_bytes`.
    TooLarge { bytes: usize, max: usize },
    /// A trajectory whose point times do not strictly increase.
    PlanTimes { what: String },
    /// Anything else malformed.
    BadMessage { what: String },
}

impl Rejection {
    /// Every key, in diagnostics order.
    pub const KEYS: [&'static str; 12] = [
        "future_stamp",
        "past_stamp",
        "out_of_order",
        "non_finite",
        "wrong_joints",
        "frame_size",
        "undecodable",
        "empty_plan",
        "plan_times",
        "out_of_limits",
        "too_large",
        "bad_message",
    ];

    /// The reason's key (`/diagnostics`: `rejected_<key>`).
    pub fn key(&self) -> &'static str {
        match self {
            Rejection::FutureStamp { .. } => "future_stamp",
            Rejection::PastStamp { .. } => "past_stamp",
            Rejection::OutOfOrder { .. } => "out_of_order",
            Rejection::NonFinite { .. } => "non_finite",
            Rejection::WrongJoints { .. } => "wrong_joints",
            Rejection::FrameSize { .. } => "frame_size",
            Rejection::Undecodable { .. } => "undecodable",
            Rejection::EmptyPlan => "empty_plan",
            Rejection::PlanTimes { .. } => "plan_times",
            Rejection::OutOfLimits { .. } => "out_of_limits",
            Rejection::TooLarge { .. } => "too_large",
            Rejection::BadMessage { .. } => "bad_message",
        }
    }

    /// A conversion error (message to model form, `streams::sample`), typed.
    pub fn from_sample(e: &SampleError) -> Rejection {
        match e {
            SampleError::NonFinite { joint, value, .. } => Rejection::NonFinite {
                what: format!("joint {joint} is {value}"),
            },
            SampleError::MissingJoint { joint, .. } => Rejection::WrongJoints {
                what: format!("joint {joint} missing"),
            },
            SampleError::JointCount { what, .. } => Rejection::WrongJoints { what: what.clone() },
            SampleError::EmptyPlan { .. } => Rejection::EmptyPlan,
            SampleError::PlanTimes { point, .. } => Rejection::PlanTimes {
                what: format!("point {point}: time_from_start does not increase"),
            },
            SampleError::Frame { source, .. } => Rejection::from_frame(source),
        }
    }

    /// A frame decoding error (`FrameError`, the V4L2 camera's), typed.
    pub fn from_frame(e: &dyn fmt::Display) -> Rejection {
        Rejection::Undecodable {
            what: e.to_string(),
        }
    }
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: ", self.key())?;
        match self {
            Rejection::FutureStamp { ahead_ms } => {
                write!(f, "stamp {ahead_ms} ms ahead of the clock")
            }
            Rejection::PastStamp { age_ms } => write!(f, "stamp {age_ms} ms in the past"),
            Rejection::OutOfOrder { behind_ms } => {
                write!(f, "stamp {behind_ms} ms before the last admitted sample")
            }
            Rejection::NonFinite { what }
            | Rejection::WrongJoints { what }
            | Rejection::Undecodable { what }
            | Rejection::PlanTimes { what }
            | Rejection::OutOfLimits { what }
            | Rejection::BadMessage { what } => f.write_str(what),
            Rejection::TooLarge { bytes, max } => {
                write!(f, "an image of {bytes} bytes, more than {max}")
            }
            Rejection::FrameSize {
                width,
                height,
                expected,
            } => write!(f, "{width}x{height} frame, expected {expected}x{expected}"),
            Rejection::EmptyPlan => f.write_str("trajectory has no points"),
        }
    }
}

/// A model-form value of one stream, borrowed for checking.
#[derive(Debug, Clone, Copy)]
pub enum ValueRef<'a> {
    /// Radians, model order; NaN marks a joint the servo bus did not read
    /// this cycle (the tick names it; see `docs/ros.md`, "One absent servo").
    /// With each position's own read stamp when they were not all read at
    /// the sample's stamp (`Sample::Joints::read_ns`).
    Joints(&'a [f32], Option<&'a [i64]>),
    Frame(&'a Frame),
    /// A camera image as the camera compressed it (not decoded here).
    Encoded(&'a [u8]),
    Plan(&'a Plan),
}

impl ValueRef<'_> {
    pub fn kind(&self) -> StreamKind {
        match self {
            ValueRef::Joints(..) => StreamKind::Joints,
            ValueRef::Frame(_) | ValueRef::Encoded(_) => StreamKind::Camera,
            ValueRef::Plan(_) => StreamKind::Plan,
        }
    }
}

/// The value type of one stream.
pub trait StreamValue: Send + Sync + 'static {
    fn value_ref(&self) -> ValueRef<'_>;
}

impl StreamValue for Vec<f32> {
    fn value_ref(&self) -> ValueRef<'_> {
        ValueRef::Joints(self, None)
    }
}

impl StreamValue for Arc<Frame> {
    fn value_ref(&self) -> ValueRef<'_> {
        ValueRef::Frame(self)
    }
}

/// The camera's own compressed message (`record`): stamps are checked,
/// the bytes are kept as they are.
impl StreamValue for Arc<crate::msgs::CompressedImage> {
    fn value_ref(&self) -> ValueRef<'_> {
        ValueRef::Encoded(&self.data)
    }
}

impl StreamValue for Arc<Plan> {
    fn value_ref(&self) -> ValueRef<'_> {
        ValueRef::Plan(self)
    }
}

impl StreamValue for Sample {
    fn value_ref(&self) -> ValueRef<'_> {
        Sample::value_ref(self)
    }
}

impl Sample {
    /// The value of a model-form sample, for [`validate`].
    pub fn value_ref(&self) -> ValueRef<'_> {
        match self {
            Sample::Joints {
                positions_rad,
                read_ns,
                ..
            } => ValueRef::Joints(positions_rad, read_ns.as_deref()),
            Sample::Frame { frame, .. } => ValueRef::Frame(frame),
            Sample::Plan { plan, .. } => ValueRef::Plan(plan),
        }
    }

    pub fn kind(&self) -> StreamKind {
        self.value_ref().kind()
    }
}

/// The one check of a sample: its stamp against the tick clock (`now_ns`)
/// and its stream's last admitted stamp, its value against the model's
/// shapes. `Ok` admits it.
pub fn validate(
    limits: &InputLimits,
    stamp_ns: i64,
    now_ns: i64,
    last_stamp_ns: Option<i64>,
    value: ValueRef<'_>,
) -> Result<(), Rejection> {
    let ms = |ns: i64| ns / 1_000_000;
    if stamp_ns.saturating_sub(now_ns) > limits.max_future_ns {
        return Err(Rejection::FutureStamp {
            ahead_ms: ms(stamp_ns.saturating_sub(now_ns)),
        });
    }
    if now_ns.saturating_sub(stamp_ns) > limits.max_past_ns {
        return Err(Rejection::PastStamp {
            age_ms: ms(now_ns.saturating_sub(stamp_ns)),
        });
    }
    if let Some(last) = last_stamp_ns.filter(|&last| stamp_ns < last) {
        return Err(Rejection::OutOfOrder {
            behind_ms: ms(last - stamp_ns),
        });
    }
    match value {
        ValueRef::Joints(j, read_ns) => {
            if j.len() != limits.n_joints {
                return Err(Rejection::WrongJoints {
                    what: format!("{} joints, the model has {}", j.len(), limits.n_joints),
                });
            }
            // NaN is "not read this cycle" (servo bus); infinity is never a reading.
            if let Some(i) = j.iter().position(|v| v.is_infinite()) {
                return Err(Rejection::NonFinite {
                    what: format!("joint {i} is {}", j[i]),
                });
            }
            if let Some(read_ns) = read_ns {
                if read_ns.len() != j.len() {
                    return Err(Rejection::WrongJoints {
                        what: format!("{} read stamps for {} joints", read_ns.len(), j.len()),
                    });
                }
                // Each position read: at or before the sample's stamp, and
                // within the past the boundary admits.
                let read = read_ns.iter().zip(j).enumerate();
                for (i, (&t, _)) in read.filter(|(_, (_, v))| !v.is_nan()) {
                    if t > stamp_ns {
                        return Err(Rejection::WrongJoints {
                            what: format!(
                                "joint {i} read {} ms after its sample's stamp",
                                ms(t - stamp_ns)
                            ),
                        });
                    }
                    if now_ns.saturating_sub(t) > limits.max_past_ns {
                        return Err(Rejection::PastStamp {
                            age_ms: ms(now_ns.saturating_sub(t)),
                        });
                    }
                }
            }
        }
        ValueRef::Encoded(bytes) => {
            if bytes.is_empty() {
                return Err(Rejection::Undecodable {
                    what: "an image of 0 bytes".to_string(),
                });
            }
            limits.image_size(bytes.len())?;
        }
        ValueRef::Frame(f) => {
            if f.width != limits.frame_size || f.height != limits.frame_size {
                return Err(Rejection::FrameSize {
                    width: f.width,
                    height: f.height,
                    expected: limits.frame_size,
                });
            }
        }
        ValueRef::Plan(p) => {
            if p.times_ns.is_empty() {
                return Err(Rejection::EmptyPlan);
            }
            if let Some(i) = p.times_ns.windows(2).position(|w| w[1] <= w[0]) {
                return Err(Rejection::PlanTimes {
                    what: format!("point {}: time does not increase", i + 1),
                });
            }
            if p.n_joints != limits.n_joints
                || p.positions_rad.len() != p.times_ns.len() * p.n_joints
            {
                return Err(Rejection::WrongJoints {
                    what: format!(
                        "plan of {} joints ({} values for {} points), the model has {}",
                        p.n_joints,
                        p.positions_rad.len(),
                        p.times_ns.len(),
                        limits.n_joints
                    ),
                });
            }
            if let Some(i) = p.positions_rad.iter().position(|v| !v.is_finite()) {
                return Err(Rejection::NonFinite {
                    what: format!("plan value {i} is {}", p.positions_rad[i]),
                });
            }
            if let Some(range) = limits.plan_range_rad.as_deref() {
                let beyond = p.positions_rad.iter().enumerate().find(|&(i, &v)| {
                    range
                        .get(i % p.n_joints)
                        .is_some_and(|&(lo, hi)| !(lo..=hi).contains(&v))
                });
                if let Some((i, &v)) = beyond {
                    let (lo, hi) = range[i % p.n_joints];
                    return Err(Rejection::OutOfLimits {
                        what: format!(
                            "point {} joint {}: {v:.3} rad, outside [{lo:.3}, {hi:.3}]",
                            i / p.n_joints,
                            i % p.n_joints
                        ),
                    });
                }
            }
        }
    }
    Ok(())
}

/// One stream's entrance: its limits, the last admitted stamp and
/// sequence number, its counters. Shared by every clone of the stream's
/// feed; a replay holds its own.
#[derive(Debug)]
pub struct Gate {
    kind: StreamKind,
    limits: InputLimits,
    stats: Arc<StreamStats>,
    /// (last admitted stamp, last sequence number given).
    state: Mutex<(Option<i64>, u64)>,
}

/// An admitted sample's sequence number on its stream (1, 2, ...).
pub type Seq = u64;

impl Gate {
    pub fn new(kind: StreamKind, limits: InputLimits, stats: Arc<StreamStats>) -> Gate {
        Gate {
            kind,
            limits,
            stats,
            state: Mutex::new((None, 0)),
        }
    }

    pub fn kind(&self) -> StreamKind {
        self.kind
    }

    pub fn limits(&self) -> &InputLimits {
        &self.limits
    }

    pub fn stats(&self) -> &Arc<StreamStats> {
        &self.stats
    }

    /// Check a value (or a source's conversion error) stamped `stamp_ns`
    /// at tick-clock time `now_ns`, and then, while still holding the
    /// stream's lock, call `admit` with its sequence number. Counts the
    /// sample or the rejection (logged once per reason).
    pub fn pass<T: StreamValue>(
        &self,
        now_ns: i64,
        stamp_ns: i64,
        value: Result<T, Rejection>,
        admit: impl FnOnce(Seq, T),
    ) -> Result<Seq, Rejection> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let checked = value.and_then(|v| {
            debug_assert_eq!(v.value_ref().kind(), self.kind);
            validate(&self.limits, stamp_ns, now_ns, state.0, v.value_ref()).map(|()| v)
        });
        match checked {
            Ok(v) => {
                state.0 = Some(stamp_ns);
                state.1 += 1;
                let seq = state.1;
                self.stats.record_sample();
                admit(seq, v);
                Ok(seq)
            }
            Err(r) => {
                if self.stats.record_rejection(&r) {
                    tracing::warn!(stream = %self.kind, reason = r.key(), detail = %r,
                        "sample rejected (logged once per reason, counted in /diagnostics)");
                } else {
                    tracing::debug!(stream = %self.kind, detail = %r, "sample rejected");
                }
                Err(r)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NOW: i64 = 1_700_000_000_000_000_000;

    fn limits() -> InputLimits {
        InputLimits {
            max_future_ns: 100_000_000,
            max_past_ns: 1_000_000_000,
            n_joints: 2,
            frame_size: 4,
            plan_range_rad: Some(Arc::from(vec![(-1.0, 1.0), (-2.0, 0.5)])),
            max_image_bytes: 1000,
        }
    }

    fn check(stamp_ns: i64, last: Option<i64>, value: ValueRef<'_>) -> Result<(), Rejection> {
        validate(&limits(), stamp_ns, NOW, last, value)
    }

    fn plan(times_ns: Vec<i64>, n_joints: usize, value: f64) -> Plan {
        Plan {
            stamp_ns: NOW,
            positions_rad: vec![value; times_ns.len() * n_joints],
            times_ns,
            n_joints,
        }
    }

    #[test]
    fn a_good_sample_of_each_stream_is_admitted() {
        let frame = Frame::solid(4, 4, [0; 3]);
        assert_eq!(
            check(NOW, None, ValueRef::Joints(&[0.1, f32::NAN], None)),
            Ok(())
        );
        // Each position with its own read stamp, at or before the sample's;
        // a NaN (not read) joint's stamp means nothing.
        assert_eq!(
            check(
                NOW,
                None,
                ValueRef::Joints(&[0.1, f32::NAN], Some(&[NOW - 12_000_000, NOW + 99]))
            ),
            Ok(())
        );
        assert_eq!(
            check(NOW + 100_000_000, Some(NOW), ValueRef::Frame(&frame)),
            Ok(())
        );
        assert_eq!(
            check(
                NOW - 1_000_000_000,
                None,
                ValueRef::Plan(&plan(vec![1, 2], 2, 0.5))
            ),
            Ok(())
        );
    }

    #[test]
    fn each_reason_is_rejected_with_its_key() {
        let j = [0.1f32, 0.2];
        let cases: Vec<(Result<(), Rejection>, &str)> = vec![
            (
                check(NOW + 100_000_001, None, ValueRef::Joints(&j, None)),
                "future_stamp",
            ),
            (
                check(NOW - 1_000_000_001, None, ValueRef::Joints(&j, None)),
                "past_stamp",
            ),
            (
                check(NOW - 5, Some(NOW), ValueRef::Joints(&j, None)),
                "out_of_order",
            ),
            (
                check(NOW, None, ValueRef::Joints(&[0.1, f32::INFINITY], None)),
                "non_finite",
            ),
            (
                check(NOW, None, ValueRef::Joints(&[0.1], None)),
                "wrong_joints",
            ),
            // Read stamps: one per joint, none after the sample's stamp or
            // further back than the boundary admits.
            (
                check(NOW, None, ValueRef::Joints(&j, Some(&[NOW]))),
                "wrong_joints",
            ),
            (
                check(NOW, None, ValueRef::Joints(&j, Some(&[NOW, NOW + 1]))),
                "wrong_joints",
            ),
            (
                check(
                    NOW,
                    None,
                    ValueRef::Joints(&j, Some(&[NOW - 1_000_000_001, NOW])),
                ),
                "past_stamp",
            ),
            (
                check(NOW, None, ValueRef::Frame(&Frame::solid(4, 3, [0; 3]))),
                "frame_size",
            ),
            (
                check(NOW, None, ValueRef::Plan(&plan(vec![], 2, 0.0))),
                "empty_plan",
            ),
            (
                check(NOW, None, ValueRef::Plan(&plan(vec![5, 5], 2, 0.0))),
                "plan_times",
            ),
            (
                check(NOW, None, ValueRef::Plan(&plan(vec![1, 2], 3, 0.0))),
                "wrong_joints",
            ),
            (
                check(NOW, None, ValueRef::Plan(&plan(vec![1], 2, f64::NAN))),
                "non_finite",
            ),
            // Joint 1's range ends at 0.5 rad.
            (
                check(NOW, None, ValueRef::Plan(&plan(vec![1, 2], 2, 0.75))),
                "out_of_limits",
            ),
            (
                check(NOW, None, ValueRef::Encoded(&[0xFF; 1001])),
                "too_large",
            ),
        ];
        for (i, (got, key)) in cases.into_iter().enumerate() {
            let r = got.expect_err(&format!("case {i} ({key}) admitted"));
            assert_eq!(r.key(), key, "case {i}: {r}");
            assert!(r.to_string().starts_with(key), "{r}");
        }
    }

    #[test]
    fn conversion_errors_are_typed() {
        use crate::msgs::{CompressedImage, JointState, JointTrajectory};
        let names = vec!["a".to_string(), "b".to_string()];
        let js = |name: Vec<&str>, position: Vec<f64>| JointState {
            name: name.into_iter().map(String::from).collect(),
            position,
            ..JointState::default()
        };
        let key = |e: SampleError| Rejection::from_sample(&e).key();
        let joints = |m: JointState| {
            crate::streams::sample::joints_from_msg(&m, &names).expect_err("rejected")
        };
        assert_eq!(
            key(joints(js(vec!["a", "b"], vec![0.0, f64::NAN]))),
            "non_finite"
        );
        assert_eq!(key(joints(js(vec!["a"], vec![0.0]))), "wrong_joints");
        assert_eq!(key(joints(js(vec!["a", "b"], vec![0.0]))), "wrong_joints");
        let empty = JointTrajectory {
            joint_names: names.clone(),
            ..JointTrajectory::default()
        };
        assert_eq!(
            key(Plan::from_msg(&empty, &names).expect_err("empty")),
            "empty_plan"
        );
        let jpeg = CompressedImage {
            format: "jpeg".into(),
            data: vec![1, 2, 3],
            ..CompressedImage::default()
        };
        assert_eq!(
            key(crate::streams::sample::frame_from_msg(&jpeg, 4).expect_err("not a JPEG")),
            "undecodable"
        );
    }

    #[test]
    fn a_gate_numbers_admitted_samples_and_counts_rejections_per_reason() {
        let stats = Arc::new(StreamStats::default());
        let gate = Gate::new(StreamKind::Joints, limits(), Arc::clone(&stats));
        let mut admitted = Vec::new();
        let mut pass = |stamp: i64, v: Result<Vec<f32>, Rejection>| {
            gate.pass(NOW, stamp, v, |seq, v| admitted.push((seq, v)))
        };
        assert_eq!(pass(NOW - 10, Ok(vec![1.0, 2.0])), Ok(1));
        assert!(pass(NOW + 1_000_000_000, Ok(vec![1.0, 2.0])).is_err());
        assert!(pass(NOW, Err(Rejection::EmptyPlan)).is_err());
        assert!(pass(NOW - 20, Ok(vec![1.0, 2.0])).is_err());
        assert_eq!(pass(NOW, Ok(vec![3.0, 4.0])), Ok(2));
        assert_eq!(admitted.iter().map(|a| a.0).collect::<Vec<_>>(), [1, 2]);
        let snap = stats.snapshot();
        assert_eq!((snap.samples, snap.rejected), (2, 3));
        assert_eq!(
            snap.rejections,
            vec![("future_stamp", 1), ("empty_plan", 1), ("out_of_order", 1)]
        );
        assert!(
            snap.last_rejection.starts_with("out_of_order"),
            "{}",
            snap.last_rejection
        );
    }
}
