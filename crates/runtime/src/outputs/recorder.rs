//! Records the live streams in the recording format (`fall-guard record`),
//! so that a user can build a real-robot data set and label it afterwards
//! (`fall-guard label`).
//!
//! Joints and plans enter in model form, as the tick sees them (joints in
//! model order, plans); camera frames enter as the camera's own
//! `CompressedImage` ([`Recorder::record_image`]: the ROS message as
//! received, or the V4L2 camera's MJPEG buffer, or one full-size JPEG of a
//! raw frame), never the network's S x S input, so a recording outlives the
//! model it was made with (readers decode and resize any JPEG/PNG size).
//! They leave as the messages of `docs/contracts.md` ("Recording
//! conventions") through the data plane's [`RecordingWriter`]:
//! `/joint_states` (`JointState`, radians),
//! `/head_camera/image_raw/compressed` (unchanged: format, header and bytes)
//! and `/planned_trajectory` (`JointTrajectory`, every point of the plan),
//! with the sample's stamp as log time (and `header.stamp` of the joints
//! and plans). The episode metadata (`source = robot`, `rate_hz` of the
//! config, no fall onset until labelled) is written at the end.

use std::path::{Path, PathBuf};

use crate::frame::{encode_jpeg, Frame};
use crate::msgs::{
    CompressedImage, Duration, Header, JointState, JointTrajectory, JointTrajectoryPoint, Time,
};
use crate::recording::{topics, EpisodeMeta, RecordingError, RecordingWriter};
use crate::streams::sample::{Plan, Sample};
use crate::streams::PerStream;

/// JPEG quality of recorded frames.
const JPEG_QUALITY: u8 = 90;

/// An MCAP file being written from live samples.
pub struct Recorder {
    path: PathBuf,
    writer: RecordingWriter,
    joint_names: Vec<String>,
    robot: String,
    rate_hz: f64,
    first_ns: Option<i64>,
    last_ns: Option<i64>,
    counts: PerStream<u64>,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("path", &self.path)
            .field("counts", &self.counts)
            .finish_non_exhaustive()
    }
}

/// What was recorded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordSummary {
    /// Messages per stream.
    pub counts: PerStream<u64>,
    pub duration_ns: i64,
}

impl Recorder {
    pub fn create(
        path: &Path,
        joint_names: Vec<String>,
        robot: &str,
        rate_hz: f64,
    ) -> Result<Recorder, RecordingError> {
        let mut writer = RecordingWriter::create(path)?;
        writer.add_topic::<JointState>(topics::JOINT_STATES)?;
        writer.add_topic::<CompressedImage>(topics::HEAD_CAMERA)?;
        writer.add_topic::<JointTrajectory>(topics::PLANNED_TRAJECTORY)?;
        tracing::info!(path = %path.display(), "recording started");
        Ok(Recorder {
            path: path.to_path_buf(),
            writer,
            joint_names,
            robot: robot.to_string(),
            rate_hz,
            first_ns: None,
            last_ns: None,
            counts: PerStream::default(),
        })
    }

    /// Write one camera message unchanged, logged at `stamp_ns`.
    pub fn record_image(
        &mut self,
        stamp_ns: i64,
        msg: &CompressedImage,
    ) -> Result<(), RecordingError> {
        self.writer.write(topics::HEAD_CAMERA, stamp_ns, msg)?;
        self.counts.camera += 1;
        self.stamped(stamp_ns);
        Ok(())
    }

    fn stamped(&mut self, stamp_ns: i64) {
        self.first_ns.get_or_insert(stamp_ns);
        self.last_ns = Some(self.last_ns.map_or(stamp_ns, |t| t.max(stamp_ns)));
    }

    /// Write one sample as its message (a model-form frame as a JPEG of
    /// its S x S pixels).
    pub fn record(&mut self, sample: &Sample) -> Result<(), RecordingError> {
        let stamp_ns = sample.stamp_ns();
        let header = Header {
            stamp: Time::from_ns(stamp_ns),
            frame_id: String::new(),
        };
        match sample {
            Sample::Joints { positions_rad, .. } => {
                let msg = JointState {
                    header,
                    name: self.joint_names.clone(),
                    position: positions_rad.iter().map(|&p| f64::from(p)).collect(),
                    velocity: Vec::new(),
                    effort: Vec::new(),
                };
                self.writer.write(topics::JOINT_STATES, stamp_ns, &msg)?;
                self.counts.joints += 1;
            }
            Sample::Frame { frame, .. } => {
                let msg = frame_message(header, frame).map_err(|reason| RecordingError::Write {
                    path: self.path.clone(),
                    reason,
                })?;
                self.writer.write(topics::HEAD_CAMERA, stamp_ns, &msg)?;
                self.counts.camera += 1;
            }
            Sample::Plan { plan, .. } => {
                let msg = plan_message(plan, &self.joint_names);
                self.writer
                    .write(topics::PLANNED_TRAJECTORY, stamp_ns, &msg)?;
                self.counts.plan += 1;
            }
        }
        self.stamped(stamp_ns);
        Ok(())
    }

    /// Write the episode metadata and close the file.
    pub fn finish(mut self) -> Result<RecordSummary, RecordingError> {
        let duration_ns = match (self.first_ns, self.last_ns) {
            (Some(a), Some(b)) => b - a,
            _ => 0,
        };
        let mut other = std::collections::BTreeMap::new();
        other.insert(
            "duration_s".to_string(),
            format!("{:.3}", duration_ns as f64 / 1e9),
        );
        self.writer.write_episode(&EpisodeMeta {
            source: "robot".into(),
            robot: self.robot.clone(),
            rate_hz: self.rate_hz,
            fall_onset_ns: None,
            seed: None,
            sigma: None,
            other,
        })?;
        self.writer.finish()?;
        tracing::info!(path = %self.path.display(), joints = self.counts.joints, frames = self.counts.camera,
            plans = self.counts.plan, "recording finished");
        Ok(RecordSummary {
            counts: self.counts,
            duration_ns,
        })
    }
}

fn frame_message(header: Header, frame: &Frame) -> Result<CompressedImage, String> {
    Ok(CompressedImage {
        header,
        format: "jpeg".into(),
        data: encode_jpeg(frame, JPEG_QUALITY).map_err(|e| e.to_string())?,
    })
}

/// A plan back as the `JointTrajectory` it came from (model joint order).
pub fn plan_message(plan: &Plan, joint_names: &[String]) -> JointTrajectory {
    let c = plan.n_joints;
    JointTrajectory {
        header: Header {
            stamp: Time::from_ns(plan.stamp_ns),
            frame_id: String::new(),
        },
        joint_names: joint_names.to_vec(),
        points: plan
            .times_ns
            .iter()
            .enumerate()
            .map(|(i, &t)| JointTrajectoryPoint {
                positions: plan.positions_rad[i * c..(i + 1) * c].to_vec(),
                velocities: Vec::new(),
                accelerations: Vec::new(),
                effort: Vec::new(),
                time_from_start: Duration::from_ns(t - plan.stamp_ns),
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::recording::Recording;
    use crate::window::{samples_from_recording, WindowSpec};

    fn names() -> Vec<String> {
        vec!["a".into(), "b".into()]
    }

    #[test]
    fn recorded_samples_read_back_as_the_same_samples() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("live.mcap");
        let mut recorder =
            Recorder::create(&path, names(), "poppy_humanoid", 30.0).expect("create");
        let plan = Arc::new(Plan {
            stamp_ns: 1_000,
            times_ns: vec![1_000, 34_334_334, 67_667_667],
            positions_rad: vec![0.1, -0.2, 0.15, -0.25, 0.2, -0.3],
            n_joints: 2,
        });
        let frame = Arc::new(Frame::solid(8, 8, [200, 40, 10]));
        let input = vec![
            Sample::Plan {
                stamp_ns: 1_000,
                plan: Arc::clone(&plan),
            },
            Sample::Joints {
                stamp_ns: 2_000,
                positions_rad: vec![0.5, -0.125],
                read_ns: None,
            },
            Sample::Frame {
                stamp_ns: 3_000,
                frame: Arc::clone(&frame),
            },
            Sample::Joints {
                stamp_ns: 33_336_000,
                positions_rad: vec![0.25, 1.5],
                read_ns: None,
            },
        ];
        for s in &input {
            recorder.record(s).expect("record");
        }
        // A camera message as received: kept byte for byte.
        let big = Frame::solid(320, 240, [10, 200, 40]);
        let received = CompressedImage {
            header: Header {
                stamp: Time::from_ns(33_000_000),
                frame_id: "head_camera".into(),
            },
            format: "rgb8; jpeg compressed bgr8".into(),
            data: encode_jpeg(&big, 80).expect("jpeg"),
        };
        recorder
            .record_image(33_337_000, &received)
            .expect("record image");
        let summary = recorder.finish().expect("finish");
        assert_eq!(
            summary.counts,
            PerStream {
                joints: 2,
                camera: 2,
                plan: 1
            }
        );
        assert_eq!(summary.duration_ns, 33_336_000);

        let rec = Recording::open(&path).expect("read back");
        let meta = rec.episode().expect("episode metadata");
        assert_eq!(
            (
                meta.source.as_str(),
                meta.robot.as_str(),
                meta.rate_hz,
                meta.fall_onset_ns
            ),
            ("robot", "poppy_humanoid", 30.0, None)
        );
        let spec = WindowSpec {
            n_ticks: 2,
            max_horizon_ticks: 1,
            rate_hz: 30.0,
            joint_names: names(),
            frame_size: 8,
        };
        assert_eq!(rec.images[1].msg, received);
        assert_eq!(rec.images[1].log_time_ns, 33_337_000);
        let back = samples_from_recording(&rec, &spec).expect("samples");
        assert_eq!(back.len(), input.len() + 1);
        let Sample::Frame { frame, .. } = &back[4] else {
            panic!("the image last: {:?}", back[4]);
        };
        assert_eq!((frame.width, frame.height), (8, 8), "resized to the model");
        for (a, b) in input.iter().zip(&back) {
            assert_eq!(a.stamp_ns(), b.stamp_ns());
            match (a, b) {
                (
                    Sample::Joints {
                        positions_rad: x, ..
                    },
                    Sample::Joints {
                        positions_rad: y, ..
                    },
                ) => assert_eq!(x, y),
                (Sample::Plan { plan: x, .. }, Sample::Plan { plan: y, .. }) => assert_eq!(x, y),
                (Sample::Frame { frame: x, .. }, Sample::Frame { frame: y, .. }) => {
                    assert_eq!((x.width, x.height), (y.width, y.height));
                    let worst = x
                        .rgb
                        .iter()
                        .zip(&y.rgb)
                        .map(|(&p, &q)| (i32::from(p) - i32::from(q)).abs())
                        .max();
                    assert!(worst.unwrap_or(0) <= 6, "JPEG error {worst:?}");
                }
                _ => panic!("sample kinds differ: {a:?} vs {b:?}"),
            }
        }
    }
}
