//! The networks of one configuration ([`ModelSet`]): EMP and the fallbacks
//! that are configured, each checked at start against the robot and EMP's
//! window, loaded at start or at their first use (`[model].fallbacks`).

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use thiserror::Error;

use crate::config::{Config, ConfigError, FallbackLoading, ModelFacts};
use crate::model::{
    Ablation, Convolutions, LoadedModel, ModelError, ProjectionWeights, StreamingForecaster,
    TrajectoryInput,
};
use crate::window::WindowSpec;

#[derive(Debug, Error)]
pub enum ForecastError {
    #[error("{key}: {file}: {source}")]
    Load {
        key: String,
        file: PathBuf,
        #[source]
        source: ModelError,
    },
    #[error("{key}: {file} holds a {found} network, expected {expected}")]
    WrongAblation {
        key: String,
        file: PathBuf,
        found: Ablation,
        expected: Ablation,
    },
    #[error("{key}: {file} does not fit this robot: {source}")]
    Incompatible {
        key: String,
        file: PathBuf,
        #[source]
        source: ModelError,
    },
    #[error("{key}: {file}: {what} differs from [model].emp ({emp}): the fallbacks must share the window")]
    Mismatch {
        key: String,
        file: PathBuf,
        what: &'static str,
        emp: String,
    },
    #[error("{key}: {file} was trained with the {trajectory} trajectory input (a paper ablation for the model card): the daemon runs networks that read the planned trajectory only; configure a model trained with `fall-guard-lab train --trajectory planned`")]
    Trajectory {
        key: String,
        file: PathBuf,
        trajectory: TrajectoryInput,
    },
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("cannot start the inference thread: {0}")]
    Thread(std::io::Error),
}

/// The name of an ablation as published ("EMP", "MP", ...).
pub fn ablation_name(ablation: Ablation) -> &'static str {
    match ablation {
        Ablation::P => "P",
        Ablation::MP => "MP",
        Ablation::EP => "EP",
        Ablation::EMP => "EMP",
    }
}

/// The networks of one configuration: EMP and the fallbacks that are
/// configured, all on the same window. With `[model].fallbacks =
/// "when_needed"` a fallback is checked at start, released, and loaded again
/// at its first use ([`ModelSet::model`]), then kept.
#[derive(Debug)]
pub struct ModelSet {
    slots: Vec<ModelSlot>,
    spec: WindowSpec,
    horizons_ms: Vec<u32>,
    robot_joints: Vec<String>,
    /// `[model].projection`, applied to every network as it is loaded.
    projection: ProjectionWeights,
    /// `[model].convolutions`, applied to every network as it is loaded.
    convolutions: Convolutions,
}

/// One configured network: its file, and the network while in memory.
#[derive(Debug)]
struct ModelSlot {
    key: &'static str,
    ablation: Ablation,
    path: PathBuf,
    loaded: Mutex<Option<LoadedModel>>,
}

impl ModelSlot {
    fn loaded(&self) -> std::sync::MutexGuard<'_, Option<LoadedModel>> {
        self.loaded.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Loads `path` for `key` and refuses a file that is not the ablation its
/// key names, does not fit the robot's joints, or (for a fallback) does not
/// share EMP's window.
fn load_checked(
    key: &str,
    path: &Path,
    expected: Ablation,
    robot_joints: &[String],
    emp: Option<&LoadedModel>,
) -> Result<LoadedModel, ForecastError> {
    let model = LoadedModel::load(path).map_err(|source| ForecastError::Load {
        key: key.to_string(),
        file: path.to_path_buf(),
        source,
    })?;
    let meta = &model.meta;
    if meta.ablation != expected {
        return Err(ForecastError::WrongAblation {
            key: key.to_string(),
            file: path.to_path_buf(),
            found: meta.ablation,
            expected,
        });
    }
    // The stream freshness and fallback rules below are written for
    // networks whose trajectory encoder reads the plan stream.
    if meta.config.trajectory != TrajectoryInput::Planned {
        return Err(ForecastError::Trajectory {
            key: key.to_string(),
            file: path.to_path_buf(),
            trajectory: meta.config.trajectory,
        });
    }
    meta.check_compatible_with(
        robot_joints,
        meta.rate_hz,
        meta.n_ticks,
        meta.config.max_horizon_ticks(),
        meta.frame_size,
    )
    .map_err(|source| ForecastError::Incompatible {
        key: key.to_string(),
        file: path.to_path_buf(),
        source,
    })?;
    if let Some(emp) = emp {
        let e = &emp.meta;
        let what = if e.n_ticks != meta.n_ticks {
            Some("window length N")
        } else if (e.rate_hz - meta.rate_hz).abs() > 1e-9 {
            Some("tick rate")
        } else if e.horizons_ticks != meta.horizons_ticks {
            Some("horizons")
        } else {
            None
        };
        if let Some(what) = what {
            return Err(ForecastError::Mismatch {
                key: key.to_string(),
                file: path.to_path_buf(),
                what,
                emp: emp.path.display().to_string(),
            });
        }
    }
    Ok(model)
}

impl ModelSet {
    /// A streaming forecaster for each network in memory (the inference
    /// thread's).
    pub(super) fn forecasters(&self) -> Vec<(Ablation, StreamingForecaster)> {
        self.slots
            .iter()
            .filter_map(|s| {
                s.loaded()
                    .as_ref()
                    .map(|m| (s.ablation, StreamingForecaster::new(m)))
            })
            .collect()
    }

    /// Loads `[model].emp` and the configured fallbacks, refusing a file
    /// that is not the ablation its key names, does not fit the robot's
    /// joints, or does not share EMP's window; checks `[model].horizon_ms`.
    /// With `[model].fallbacks = "when_needed"` the fallbacks are released
    /// once checked.
    pub fn load(config: &Config, robot_joints: &[String]) -> Result<ModelSet, ForecastError> {
        let m = &config.model;
        let entries = [
            ("[model].emp", Some(&m.emp), Ablation::EMP),
            ("[model].mp", m.mp.as_ref(), Ablation::MP),
            ("[model].ep", m.ep.as_ref(), Ablation::EP),
            ("[model].p", m.p.as_ref(), Ablation::P),
        ];
        let mut slots: Vec<ModelSlot> = Vec::new();
        let mut emp: Option<LoadedModel> = None;
        for (key, file, expected) in entries {
            let Some(file) = file else { continue };
            let path = config.model_path(file);
            let model = load_checked(key, &path, expected, robot_joints, emp.as_ref())?
                .with_projection(m.projection)
                .with_convolutions(m.convolutions);
            let meta = &model.meta;
            tracing::info!(key, file = %path.display(), ablation = ablation_name(meta.ablation),
                trained_on = %meta.trained_on, best_epoch = meta.best_epoch,
                projection = m.projection.name(),
                projection_mb = format!("{:.1}", model.network.projection_bytes() as f64 / 1e6),
                convolutions = m.convolutions.resolved().name(),
                "network ready");
            if emp.is_none() {
                emp = Some(model.clone());
            }
            let keep = expected == Ablation::EMP || m.fallbacks == FallbackLoading::AtStart;
            if !keep {
                tracing::info!(key, "checked; released until it is first needed ([model].fallbacks = \"when_needed\")");
            }
            slots.push(ModelSlot {
                key,
                ablation: expected,
                path,
                loaded: Mutex::new(keep.then_some(model)),
            });
        }
        let emp = emp.expect("[model].emp is required");
        let horizons_ms = emp.meta.horizons_ms();
        config.check_against_model(
            &ModelFacts {
                horizons_ms: horizons_ms.clone(),
                joint_names: emp.meta.joint_names.clone(),
                rate_hz: emp.meta.rate_hz,
                n_ticks: emp.meta.n_ticks,
            },
            robot_joints,
        )?;
        let spec = emp.meta.window_spec();
        drop(emp);
        release_freed_memory();
        Ok(ModelSet {
            slots,
            spec,
            horizons_ms,
            robot_joints: robot_joints.to_vec(),
            projection: m.projection,
            convolutions: m.convolutions,
        })
    }

    /// Wraps networks already in memory (tests, benches); the first is EMP.
    pub fn from_models(models: Vec<LoadedModel>) -> ModelSet {
        let emp = &models[0].meta;
        let spec = emp.window_spec();
        let horizons_ms = emp.horizons_ms();
        let robot_joints = emp.joint_names.clone();
        ModelSet {
            spec,
            horizons_ms,
            robot_joints,
            projection: ProjectionWeights::AsFile,
            convolutions: Convolutions::F32,
            slots: models
                .into_iter()
                .map(|m| ModelSlot {
                    key: "(in memory)",
                    ablation: m.meta.ablation,
                    path: m.path.clone(),
                    loaded: Mutex::new(Some(m)),
                })
                .collect(),
        }
    }

    pub fn spec(&self) -> &WindowSpec {
        &self.spec
    }

    pub fn horizons_ms(&self) -> &[u32] {
        &self.horizons_ms
    }

    /// Which ablations are configured and were checked at start (in memory
    /// or not).
    pub fn available(&self) -> Vec<Ablation> {
        self.slots.iter().map(|s| s.ablation).collect()
    }

    /// Which ablations are in memory now.
    pub fn in_memory(&self) -> Vec<Ablation> {
        self.slots
            .iter()
            .filter(|s| s.loaded().is_some())
            .map(|s| s.ablation)
            .collect()
    }

    /// The network of `ablation`, loading it (and checking it again against
    /// EMP and the robot) when it is not in memory; `Ok(None)` when it is not
    /// configured. A load here is the first switch to a `"when_needed"`
    /// fallback; its time is logged.
    pub fn model(&self, ablation: Ablation) -> Result<Option<LoadedModel>, ForecastError> {
        let Some(slot) = self.slots.iter().find(|s| s.ablation == ablation) else {
            return Ok(None);
        };
        if let Some(m) = slot.loaded().as_ref() {
            return Ok(Some(m.clone()));
        }
        let emp = self.slots.first().and_then(|s| s.loaded().clone());
        let started = std::time::Instant::now();
        let model = load_checked(
            slot.key,
            &slot.path,
            ablation,
            &self.robot_joints,
            emp.as_ref().filter(|e| e.meta.ablation != ablation),
        )?
        .with_projection(self.projection)
        .with_convolutions(self.convolutions);
        // As at start: hand the load's transient heap back to the system,
        // or the resident memory keeps the load's peak (`docs/performance.md`).
        release_freed_memory();
        tracing::info!(key = slot.key, file = %slot.path.display(),
            load_ms = format!("{:.1}", started.elapsed().as_secs_f64() * 1e3),
            "fallback loaded at its first use");
        *slot.loaded() = Some(model.clone());
        Ok(Some(model))
    }

    /// File of a configured ablation.
    pub fn file(&self, ablation: Ablation) -> Option<&Path> {
        self.slots
            .iter()
            .find(|s| s.ablation == ablation)
            .map(|s| s.path.as_path())
    }
}

/// Loading a network allocates several times its size for a moment (file
/// bytes, the record, the f16 -> f32 cast, the randomly initialised module
/// it replaces); glibc keeps such freed heap mapped. Hand it back to the
/// system once the networks are loaded, so the daemon's resident memory is
/// what it uses.
fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free heap pages to the kernel; it
    // touches no memory that is in use.
    unsafe {
        libc::malloc_trim(0);
    }
}
