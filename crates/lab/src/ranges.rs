//! The input ranges a network was trained on, measured on its training
//! split ([`measure`]), written into the model file by `train` and by
//! `fall-guard-lab ranges` (the weights untouched), read by the daemon's
//! out-of-range guard (`fall_guard_runtime::model::ranges`).
//!
//! Over every tick a training window can hold (every tick of a non-falling
//! episode, the ticks before the onset of a falling one, as the deployment
//! protocol draws its windows): per joint the smallest and largest angle;
//! per joint the same of the planned trajectory over every row a window
//! cuts from each plan message (the past and future rows of every tick the
//! message was the newest); for the camera, each frame's mean brightness and
//! contrast.

use std::borrow::Cow;
use std::sync::Arc;

use fall_guard_runtime::clock::TickGrid;
use fall_guard_runtime::model::ranges::{InputRanges, RangeMeter};
use fall_guard_runtime::model::{ModelMeta, TrajectoryInput};
use fall_guard_runtime::window::{EpisodeTicks, TickFrame};

use crate::error::TrainError;

/// What [`measure`] went through.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Measured {
    pub episodes: usize,
    pub ticks: usize,
    pub plans: usize,
    pub frames: usize,
}

/// The ranges of `episodes`, the `split` split of data set `set` (read
/// with the streams `meta`'s network needs), named by [`describe`].
pub fn measure(
    episodes: &[EpisodeTicks],
    meta: &ModelMeta,
    set: &str,
    split: &str,
) -> Result<(InputRanges, Measured), TrainError> {
    let cfg = &meta.config;
    let c = cfg.n_joints;
    let grid = TickGrid::new(meta.rate_hz).map_err(|e| TrainError::Data(e.to_string()))?;
    let (n, rows_ahead) = (cfg.n_ticks as i64, cfg.max_horizon_ticks() as i64);
    let mut meter = RangeMeter::new(c);
    let mut count = Measured {
        episodes: episodes.len(),
        ..Measured::default()
    };
    let s = cfg.frame_size;
    let mut chw = vec![0f32; 3 * s * s];
    for ep in episodes {
        let usable = ep
            .ticks
            .iter()
            .take_while(|t| ep.fall_onset_tick.is_none_or(|onset| t.tick < onset));
        // Per plan message, the ticks it was the newest at.
        let mut plan_span: Option<(Arc<_>, i64, i64)> = None;
        let mut last_frame: Option<&TickFrame> = None;
        let plan_rows = |plan: &fall_guard_runtime::streams::sample::Plan,
                         first: i64,
                         last: i64,
                         meter: &mut RangeMeter| {
            let mut row = vec![0f32; c];
            for t in (first - n + 1)..=(last + rows_ahead) {
                plan.sample_into(grid.stamp_ns(t), &mut row);
                meter.plan(&row);
            }
        };
        for t in usable {
            count.ticks += 1;
            if let Some(j) = &t.joints_rad {
                meter.joints(j);
            }
            if let Some(p) = &t.plan {
                match &mut plan_span {
                    Some((held, _, last)) if Arc::ptr_eq(held, p) => *last = t.tick,
                    _ => {
                        if let Some((held, first, last)) = plan_span.take() {
                            plan_rows(&held, first, last, &mut meter);
                            count.plans += 1;
                        }
                        plan_span = Some((Arc::clone(p), t.tick, t.tick));
                    }
                }
            }
            if let Some(f) = &t.frame {
                if !last_frame.is_some_and(|l| l.same_as(f)) {
                    let decoded: Cow<'_, _> = f.decoded().map_err(|e| {
                        TrainError::Data(format!("{}: tick {}: {e}", ep.path.display(), t.tick))
                    })?;
                    if decoded.width as usize == s && decoded.height as usize == s {
                        decoded.write_chw(&mut chw, s * s);
                        meter.frame(&chw);
                        count.frames += 1;
                    }
                    last_frame = Some(f);
                }
            }
        }
        if let Some((held, first, last)) = plan_span.take() {
            plan_rows(&held, first, last, &mut meter);
            count.plans += 1;
        }
    }
    let measured_on = describe(set, split, &count);
    let mut ranges = meter.finish(measured_on.clone()).ok_or_else(|| {
        TrainError::Data(format!(
            "{measured_on}: no tick with joint angles to measure the input ranges on"
        ))
    })?;
    // A real-position trajectory input is the measured joints.
    if cfg.trajectory == TrajectoryInput::RealPosition {
        ranges.plan = ranges.joints.clone();
    }
    Ok((ranges, count))
}

/// `"the train split of simv6 (1600 episodes, 412345 ticks)"`.
pub fn describe(set: &str, split: &str, m: &Measured) -> String {
    format!(
        "the {split} split of {set} ({} episodes, {} ticks before any fall)",
        m.episodes, m.ticks
    )
}

/// `fall-guard-lab ranges`.
#[derive(Debug, Clone)]
pub struct RangesOptions {
    /// Model file to give ranges.
    pub model: std::path::PathBuf,
    /// Data set whose split the network was trained on.
    pub data: std::path::PathBuf,
    pub split: crate::dataset::Split,
    /// Where to write (none: over `model`).
    pub out: Option<std::path::PathBuf>,
}

/// Measures the ranges of `model`'s inputs on a split of `data` and writes
/// them into the model file's metadata (weights byte for byte); returns the
/// sentence it logs.
pub fn run_ranges(args: &RangesOptions) -> crate::error::CommandResult<String> {
    use crate::error::Doing;
    let (mut meta, _) = fall_guard_runtime::model::file::load_emp(
        &args.model,
        &fall_guard_runtime::model::cpu_device(),
    )
    .doing(|| format!("reading {}", args.model.display()))?;
    let dataset = crate::dataset::Dataset::open(&args.data)
        .doing(|| format!("opening data set {}", args.data.display()))?;
    let spec = meta.window_spec();
    let needs = fall_guard_runtime::window::Streams {
        joints: true,
        camera: meta.ablation.uses_vision(),
        plan: meta.ablation.uses_plan(),
    };
    let episodes = dataset.load_split(args.split, &spec, needs).doing(|| {
        format!(
            "reading the {} split of {}",
            args.split,
            args.data.display()
        )
    })?;
    let set = crate::dataset::data_name(&dataset.dir);
    let (ranges, measured) = measure(&episodes, &meta, &set, args.split.name())?;
    let on = ranges.measured_on.clone();
    meta.input_ranges = Some(ranges);
    let out = args.out.as_ref().unwrap_or(&args.model);
    fall_guard_runtime::model::file::rewrite_meta(&args.model, out, &meta)
        .doing(|| format!("writing {}", out.display()))?;
    Ok(format!(
        "{}: input ranges measured on {on} ({} plan messages, {} frames)",
        out.display(),
        measured.plans,
        measured.frames
    ))
}
