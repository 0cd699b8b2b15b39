//! The model-form value of a stream ([`Sample`]: joints in radians in the
//! model's joint order, a frame already S x S, a [`Plan`]) and the
//! conversions of ROS 2 messages into it, used at every edge (the ROS 2
//! subscriptions, a replayed recording, training's windows) so that a
//! message converts the same wherever it comes from.

use std::sync::Arc;

use crate::frame::{decode_compressed, Frame, FrameError};
use crate::msgs::{CompressedImage, JointState, JointTrajectory};
use crate::streams::topics;

/// Why a message does not convert to model form: each names its topic and
/// what was wrong (a stream's boundary counts it as a typed rejection).
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    #[error("{topic}: joint {joint:?} (needed by the model) is missing from the message")]
    MissingJoint { topic: &'static str, joint: String },
    #[error("{topic}: {what}")]
    JointCount { topic: &'static str, what: String },
    #[error("{topic}: trajectory has no points")]
    EmptyPlan { topic: &'static str },
    #[error("{topic}: point {point}: time_from_start does not increase")]
    PlanTimes { topic: &'static str, point: usize },
    #[error("{topic}: joint {joint:?} is {value} (not finite)")]
    NonFinite {
        topic: &'static str,
        joint: String,
        value: f64,
    },
    #[error("{topic}: frame: {source}")]
    Frame {
        topic: &'static str,
        source: FrameError,
    },
}

/// A planned trajectory, joints in model order, ready to be evaluated at any time.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// `header.stamp` of the message, ns.
    pub stamp_ns: i64,
    /// Absolute time of each point, ns, strictly increasing.
    pub times_ns: Vec<i64>,
    /// `[P, C]` positions, radians, model joint order.
    pub positions_rad: Vec<f64>,
    /// `C`.
    pub n_joints: usize,
}

impl Plan {
    /// Reorders a `JointTrajectory` into model order and checks it.
    pub fn from_msg(msg: &JointTrajectory, joint_names: &[String]) -> Result<Plan, SampleError> {
        const TOPIC: &str = topics::PLANNED_TRAJECTORY;
        let index = joint_indices(&msg.joint_names, joint_names, TOPIC)?;
        if msg.points.is_empty() {
            return Err(SampleError::EmptyPlan { topic: TOPIC });
        }
        let stamp_ns = msg.header.stamp.to_ns();
        let mut times_ns = Vec::with_capacity(msg.points.len());
        let mut positions_rad = Vec::with_capacity(msg.points.len() * joint_names.len());
        for (p, point) in msg.points.iter().enumerate() {
            if point.positions.len() != msg.joint_names.len() {
                return Err(SampleError::JointCount {
                    topic: TOPIC,
                    what: format!(
                        "point {p} has {} positions for {} joint names",
                        point.positions.len(),
                        msg.joint_names.len()
                    ),
                });
            }
            let t = stamp_ns + point.time_from_start.to_ns();
            if let Some(&prev) = times_ns.last() {
                if t <= prev {
                    return Err(SampleError::PlanTimes {
                        topic: TOPIC,
                        point: p,
                    });
                }
            }
            times_ns.push(t);
            for (j, &i) in index.iter().enumerate() {
                let v = point.positions[i];
                if !v.is_finite() {
                    return Err(SampleError::NonFinite {
                        topic: TOPIC,
                        joint: joint_names[j].clone(),
                        value: v,
                    });
                }
                positions_rad.push(v);
            }
        }
        Ok(Plan {
            stamp_ns,
            times_ns,
            positions_rad,
            n_joints: joint_names.len(),
        })
    }

    /// The planned positions at `t_ns` (linear between points, first/last
    /// point held outside), written as `f32` into `out[..C]`.
    pub fn sample_into(&self, t_ns: i64, out: &mut [f32]) {
        let c = self.n_joints;
        let last = self.times_ns.len() - 1;
        let row = |i: usize| &self.positions_rad[i * c..(i + 1) * c];
        if t_ns <= self.times_ns[0] {
            for (o, &v) in out.iter_mut().zip(row(0)) {
                *o = v as f32;
            }
            return;
        }
        if t_ns >= self.times_ns[last] {
            for (o, &v) in out.iter_mut().zip(row(last)) {
                *o = v as f32;
            }
            return;
        }
        // times[i] <= t < times[i + 1]
        let i = self.times_ns.partition_point(|&x| x <= t_ns) - 1;
        let (t0, t1) = (self.times_ns[i], self.times_ns[i + 1]);
        let w = (t_ns - t0) as f64 / (t1 - t0) as f64;
        for ((o, &a), &b) in out.iter_mut().zip(row(i)).zip(row(i + 1)) {
            *o = (a + (b - a) * w) as f32;
        }
    }
}

/// Joint positions of a `JointState` in model order, radians.
pub fn joints_from_msg(msg: &JointState, joint_names: &[String]) -> Result<Vec<f32>, SampleError> {
    const TOPIC: &str = topics::JOINT_STATES;
    if msg.position.len() != msg.name.len() {
        return Err(SampleError::JointCount {
            topic: TOPIC,
            what: format!(
                "{} positions for {} joint names",
                msg.position.len(),
                msg.name.len()
            ),
        });
    }
    let index = joint_indices(&msg.name, joint_names, TOPIC)?;
    index
        .iter()
        .zip(joint_names)
        .map(|(&i, name)| {
            let v = msg.position[i];
            if v.is_finite() {
                Ok(v as f32)
            } else {
                Err(SampleError::NonFinite {
                    topic: TOPIC,
                    joint: name.clone(),
                    value: v,
                })
            }
        })
        .collect()
}

/// A `CompressedImage` decoded and resized to `size x size`.
pub fn frame_from_msg(msg: &CompressedImage, size: u32) -> Result<Frame, SampleError> {
    decode_compressed(&msg.format, &msg.data, size).map_err(|source| SampleError::Frame {
        topic: topics::HEAD_CAMERA,
        source,
    })
}

/// For each model joint, its index in `names`.
fn joint_indices(
    names: &[String],
    model_names: &[String],
    topic: &'static str,
) -> Result<Vec<usize>, SampleError> {
    model_names
        .iter()
        .map(|joint| {
            names
                .iter()
                .position(|n| n == joint)
                .ok_or_else(|| SampleError::MissingJoint {
                    topic,
                    joint: joint.clone(),
                })
        })
        .collect()
}

/// One timestamped input, already in model form.
#[derive(Debug, Clone)]
pub enum Sample {
    /// Joint positions, radians, model order.
    Joints {
        /// No position in the sample was read later than this.
        stamp_ns: i64,
        positions_rad: Vec<f32>,
        /// Per joint (model order), when its position was read, ns, where
        /// the positions were not all read at one time (the servo buses:
        /// one bus after the other, and a retry for the motors whose reply
        /// was lost); `None`: every position at `stamp_ns` (a `JointState`
        /// message, a recording). The entry of a NaN (not read) joint means
        /// nothing.
        read_ns: Option<Vec<i64>>,
    },
    /// A frame, already S x S.
    Frame { stamp_ns: i64, frame: Arc<Frame> },
    /// A new plan.
    Plan { stamp_ns: i64, plan: Arc<Plan> },
}

impl Sample {
    /// A `JointState` in model order (`joint_names`), stamped `stamp_ns`.
    pub fn joints_from_msg(
        msg: &JointState,
        joint_names: &[String],
        stamp_ns: i64,
    ) -> Result<Sample, SampleError> {
        joints_from_msg(msg, joint_names).map(|positions_rad| Sample::Joints {
            stamp_ns,
            positions_rad,
            read_ns: None,
        })
    }

    /// A `CompressedImage` decoded to a `size x size` frame, stamped `stamp_ns`.
    pub fn frame_from_msg(
        msg: &CompressedImage,
        size: u32,
        stamp_ns: i64,
    ) -> Result<Sample, SampleError> {
        frame_from_msg(msg, size).map(|frame| Sample::Frame {
            stamp_ns,
            frame: Arc::new(frame),
        })
    }

    /// A `JointTrajectory` in model order (`joint_names`), stamped `stamp_ns`.
    pub fn plan_from_msg(
        msg: &JointTrajectory,
        joint_names: &[String],
        stamp_ns: i64,
    ) -> Result<Sample, SampleError> {
        Plan::from_msg(msg, joint_names).map(|plan| Sample::Plan {
            stamp_ns,
            plan: Arc::new(plan),
        })
    }

    pub fn stamp_ns(&self) -> i64 {
        match self {
            Sample::Joints { stamp_ns, .. }
            | Sample::Frame { stamp_ns, .. }
            | Sample::Plan { stamp_ns, .. } => *stamp_ns,
        }
    }
}
