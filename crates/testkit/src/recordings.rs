//! Synthetic recordings and data sets, for tests and for trying the
//! pipeline without the simulator.
//!
//! An episode is given per tick ([`SyntheticEpisode`]: measured joints,
//! planned pose, frame, fall onset) and written in exactly the recording
//! format of `docs/contracts.md`: `/joint_states`, `/head_camera/...`
//! (JPEG) and `/ground_truth/fallen` every tick, `/planned_trajectory` every
//! `plan_period_ticks` covering 2.5 s back and 3 s ahead, and the
//! `fall_guard.episode` metadata. [`write_dataset`] adds `manifest.json`.
//! [`learnable_episode`] makes episodes whose falls are predictable from
//! the inputs (joints drift from the plan and the picture reddens during the
//! two seconds before the fall), so that a model test can learn them.

use std::path::Path;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use fall_guard_runtime::clock::TickGrid;
use fall_guard_runtime::frame::{encode_jpeg, Frame};
use fall_guard_runtime::msgs::{
    Bool, CompressedImage, Duration, Header, JointState, JointTrajectory, JointTrajectoryPoint,
    Time,
};
use fall_guard_runtime::recording::{topics, EpisodeMeta, RecordingError, RecordingWriter};

/// What the camera shows at one tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SyntheticFrame {
    Solid([u8; 3]),
    /// Vertical stripes of `a` and `b`, `period_px` wide, shifted by `phase_px`.
    Stripes {
        a: [u8; 3],
        b: [u8; 3],
        period_px: u32,
        phase_px: u32,
    },
}

impl SyntheticFrame {
    pub fn render(&self, size: u32) -> Frame {
        match *self {
            SyntheticFrame::Solid(rgb) => Frame::solid(size, size, rgb),
            SyntheticFrame::Stripes {
                a,
                b,
                period_px,
                phase_px,
            } => {
                let period = period_px.max(2);
                let mut rgb = Vec::with_capacity((size * size * 3) as usize);
                for _y in 0..size {
                    for x in 0..size {
                        let c = if ((x + phase_px) % period) < period / 2 {
                            a
                        } else {
                            b
                        };
                        rgb.extend_from_slice(&c);
                    }
                }
                Frame {
                    width: size,
                    height: size,
                    rgb,
                }
            }
        }
    }
}

/// One episode, given per tick (tick `k` is written at `TickGrid::stamp_ns(k)`).
#[derive(Debug, Clone)]
pub struct SyntheticEpisode {
    pub rate_hz: f64,
    pub joint_names: Vec<String>,
    /// Measured joint angles per tick, radians, `joint_names` order.
    pub joints_rad: Vec<Vec<f32>>,
    /// Planned pose per tick, radians (same length as `joints_rad`).
    pub plan_rad: Vec<Vec<f32>>,
    /// Frame per tick (same length).
    pub frames: Vec<SyntheticFrame>,
    pub frame_size: u32,
    /// First fallen tick (`None`: no fall).
    pub fall_onset_tick: Option<usize>,
    /// A new plan message every this many ticks (the simulator: once a second).
    pub plan_period_ticks: usize,
    pub seed: u64,
    pub sigma: f64,
}

impl SyntheticEpisode {
    pub fn n_ticks(&self) -> usize {
        self.joints_rad.len()
    }

    /// Writes the episode as one MCAP recording.
    pub fn write(&self, path: &Path) -> Result<(), RecordingError> {
        let bad = |reason: String| RecordingError::Write {
            path: path.to_path_buf(),
            reason,
        };
        let n = self.n_ticks();
        if n == 0 || self.plan_rad.len() != n || self.frames.len() != n {
            return Err(bad(format!(
                "per-tick arrays differ in length: joints {}, plan {}, frames {}",
                n,
                self.plan_rad.len(),
                self.frames.len()
            )));
        }
        let grid = TickGrid::new(self.rate_hz).map_err(|e| bad(e.to_string()))?;
        let c = self.joint_names.len();
        if let Some(k) =
            (0..n).find(|&k| self.joints_rad[k].len() != c || self.plan_rad[k].len() != c)
        {
            return Err(bad(format!("tick {k}: joint vectors must have {c} values")));
        }
        let back_ticks = (2.5 * self.rate_hz).ceil() as i64;
        let ahead_ticks = (3.0 * self.rate_hz).ceil() as i64;
        let plan_period = self.plan_period_ticks.max(1);

        let mut w = RecordingWriter::create(path)?;
        let mut meta = EpisodeMeta {
            source: "sim".into(),
            robot: "poppy_humanoid".into(),
            rate_hz: self.rate_hz,
            fall_onset_ns: self.fall_onset_tick.map(|k| grid.stamp_ns(k as i64)),
            seed: Some(self.seed),
            sigma: Some(self.sigma),
            other: Default::default(),
        };
        meta.other
            .insert("generator".into(), "fall_guard_testkit::recordings".into());
        meta.other.insert(
            "duration_s".into(),
            format!("{}", grid.stamp_ns(n as i64 - 1) as f64 / 1e9),
        );
        w.write_episode(&meta)?;
        for k in 0..n {
            let stamp_ns = grid.stamp_ns(k as i64);
            let header = Header {
                stamp: Time::from_ns(stamp_ns),
                frame_id: String::new(),
            };
            if k % plan_period == 0 {
                let first = k as i64 - back_ticks;
                let plan_stamp = grid.stamp_ns(first);
                let points = (first..=k as i64 + ahead_ticks)
                    .map(|t| {
                        let idx = t.clamp(0, n as i64 - 1) as usize;
                        JointTrajectoryPoint {
                            positions: self.plan_rad[idx].iter().map(|&v| f64::from(v)).collect(),
                            time_from_start: Duration::from_ns(grid.stamp_ns(t) - plan_stamp),
                            ..Default::default()
                        }
                    })
                    .collect();
                let plan = JointTrajectory {
                    header: Header {
                        stamp: Time::from_ns(plan_stamp),
                        frame_id: String::new(),
                    },
                    joint_names: self.joint_names.clone(),
                    points,
                };
                w.write(topics::PLANNED_TRAJECTORY, stamp_ns, &plan)?;
            }
            let joints = JointState {
                header: header.clone(),
                name: self.joint_names.clone(),
                position: self.joints_rad[k].iter().map(|&v| f64::from(v)).collect(),
                velocity: Vec::new(),
                effort: Vec::new(),
            };
            w.write(topics::JOINT_STATES, stamp_ns, &joints)?;
            let jpeg = encode_jpeg(&self.frames[k].render(self.frame_size), 90)
                .map_err(|e| bad(e.to_string()))?;
            let image = CompressedImage {
                header,
                format: "jpeg".into(),
                data: jpeg,
            };
            w.write(topics::HEAD_CAMERA, stamp_ns, &image)?;
            let fallen = self.fall_onset_tick.is_some_and(|o| k >= o);
            w.write(
                topics::GROUND_TRUTH_FALLEN,
                stamp_ns,
                &Bool { data: fallen },
            )?;
        }
        w.finish()?;
        Ok(())
    }
}

/// Writes `episode_NNNN.mcap` files and `manifest.json` into `dir`
/// (created if needed). Episode names are numbered across the three splits.
pub fn write_dataset(
    dir: &Path,
    train: &[SyntheticEpisode],
    validation: &[SyntheticEpisode],
    test: &[SyntheticEpisode],
) -> Result<(), RecordingError> {
    std::fs::create_dir_all(dir).map_err(|source| RecordingError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut index = 0usize;
    let mut names = |episodes: &[SyntheticEpisode]| -> Result<Vec<String>, RecordingError> {
        let mut out = Vec::new();
        for e in episodes {
            let name = format!("episode_{index:04}.mcap");
            index += 1;
            e.write(&dir.join(&name))?;
            out.push(name);
        }
        Ok(out)
    };
    let train_names = names(train)?;
    let validation_names = names(validation)?;
    let test_names = names(test)?;
    let any = train.first().or(validation.first()).or(test.first());
    let manifest = serde_json::json!({
        "train": train_names,
        "validation": validation_names,
        "test": test_names,
        "generator": {
            "kind": "fall_guard_testkit::recordings",
            "robot": "poppy_humanoid",
            "rate_hz": any.map(|e| e.rate_hz),
            "seeds": train.iter().chain(validation).chain(test).map(|e| e.seed).collect::<Vec<_>>(),
        },
    });
    let path = dir.join("manifest.json");
    let text = serde_json::to_string_pretty(&manifest).map_err(|e| RecordingError::Write {
        path: path.clone(),
        reason: e.to_string(),
    })?;
    std::fs::write(&path, text).map_err(|source| RecordingError::Io { path, source })
}

/// An episode whose fall is predictable: joints follow a smooth plan (held
/// inside each Poppy joint's limits, as the daemon checks plans) with a
/// little noise; when `falls`, the onset is drawn in the last 40% of the
/// episode and, during the `2 * rate_hz` ticks before it, the joints drift
/// away from the plan (up to 0.6 rad) and the frame turns from blue-grey to
/// red; from the onset on the joints stay collapsed and the frame is dark.
pub fn learnable_episode(
    seed: u64,
    falls: bool,
    n_ticks: usize,
    joint_names: &[String],
    rate_hz: f64,
    frame_size: u32,
) -> SyntheticEpisode {
    let mut rng = StdRng::seed_from_u64(seed);
    let c = joint_names.len();
    let phase: f32 = rng.random_range(0.0..std::f32::consts::TAU);
    let precursor = (2.0 * rate_hz).round() as usize;
    let onset = falls.then(|| {
        let lo = (n_ticks as f64 * 0.6) as usize;
        let hi = (n_ticks as f64 * 0.9) as usize;
        rng.random_range(lo.max(precursor + 1)..hi.max(lo.max(precursor + 1) + 1))
    });
    let mut joints_rad = Vec::with_capacity(n_ticks);
    let mut plan_rad = Vec::with_capacity(n_ticks);
    let mut frames = Vec::with_capacity(n_ticks);
    // A plan the daemon accepts: inside each Poppy joint's limits.
    let range =
        fall_guard_runtime::robot::JointTable::poppy_humanoid().ranges_rad(joint_names, 0.0);
    for k in 0..n_ticks {
        let t = k as f32 / rate_hz as f32;
        let plan: Vec<f32> = (0..c)
            .map(|j| {
                let p = 0.3 * (std::f32::consts::TAU * 0.5 * t + phase + j as f32 * 0.3).sin();
                p.clamp(range[j].0 as f32, range[j].1 as f32)
            })
            .collect();
        // 0 before the precursor, rising to 1 at the onset, 1 after
        let drift = match onset {
            Some(o) if k + precursor >= o => {
                ((k + precursor - o) as f32 / precursor as f32).min(1.0)
            }
            _ => 0.0,
        };
        let joints: Vec<f32> = plan
            .iter()
            .enumerate()
            .map(|(j, &p)| {
                let noise: f32 = rng.random_range(-0.01..0.01);
                let sign = if j % 2 == 0 { 1.0 } else { -1.0 };
                p + noise + sign * 0.6 * drift
            })
            .collect();
        let fallen = onset.is_some_and(|o| k >= o);
        let frame = if fallen {
            SyntheticFrame::Solid([20, 20, 20])
        } else {
            let red = (90.0 + 160.0 * drift) as u8;
            SyntheticFrame::Stripes {
                a: [red, 120, (200.0 - 150.0 * drift) as u8],
                b: [red / 2, 90, 140],
                period_px: 8,
                phase_px: (k % 8) as u32,
            }
        };
        joints_rad.push(joints);
        plan_rad.push(plan);
        frames.push(frame);
    }
    SyntheticEpisode {
        rate_hz,
        joint_names: joint_names.to_vec(),
        joints_rad,
        plan_rad,
        frames,
        frame_size,
        fall_onset_tick: onset,
        plan_period_ticks: rate_hz.round().max(1.0) as usize,
        seed,
        sigma: if falls { 0.04 } else { 0.0 },
    }
}

/// Joint names `j00, j01, ...` for tests that do not need the robot's.
pub fn joint_names(c: usize) -> Vec<String> {
    (0..c).map(|j| format!("j{j:02}")).collect()
}
