//! A data set: a directory of MCAP recordings plus `manifest.json`
//! (`{"train": [...], "validation": [...], "test": [...], "generator": {...}}`,
//! file names relative to the directory, split by episode).
//!
//! [`Dataset::open`] checks the manifest (present, every file there, no
//! episode in two splits); [`Dataset::load_split`] reads a split's
//! recordings into [`EpisodeTicks`] with the same resampling the daemon
//! uses, checking that each has the topics the model needs. A split's
//! frames stay compressed in memory (checked to decode at load, decoded
//! when a window is built): 1.4-1.8 KB a tick (the simulator's 64 x 64
//! JPEGs) instead of 12 KB.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use fall_guard_runtime::recording::{topics, Recording, RecordingError};
use fall_guard_runtime::window::{EpisodeTicks, FrameStorage, Streams, WindowError, WindowSpec};

/// Why a data set could not be opened or loaded.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{}: no manifest.json in this directory (a data set is a directory of .mcap recordings plus manifest.json listing the train/validation/test files)", dir.display())]
    NoManifest { dir: PathBuf },
    #[error("{}: {reason}", path.display())]
    BadManifest { path: PathBuf, reason: String },
    #[error("{}: {split} lists {name:?}, which does not exist", dir.display())]
    MissingFile {
        dir: PathBuf,
        split: Split,
        name: String,
    },
    #[error("{}: {name:?} is listed in both {first} and {second}: splits must not share an episode", dir.display())]
    SharedEpisode {
        dir: PathBuf,
        name: String,
        first: Split,
        second: Split,
    },
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error(transparent)]
    Window(#[from] WindowError),
}

/// One of the three splits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Split {
    Train,
    Validation,
    Test,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Validation, Split::Test];

    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Validation => "validation",
            Split::Test => "test",
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Split {
    type Err = String;
    fn from_str(s: &str) -> Result<Split, String> {
        match s {
            "train" => Ok(Split::Train),
            "validation" | "val" => Ok(Split::Validation),
            "test" => Ok(Split::Test),
            other => Err(format!(
                "unknown split {other:?} (train, validation or test)"
            )),
        }
    }
}

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub train: Vec<String>,
    pub validation: Vec<String>,
    pub test: Vec<String>,
    /// The generator's parameters (seed range, rate, robot ...), kept as written.
    #[serde(default)]
    pub generator: serde_json::Value,
}

impl Manifest {
    pub fn files(&self, split: Split) -> &[String] {
        match split {
            Split::Train => &self.train,
            Split::Validation => &self.validation,
            Split::Test => &self.test,
        }
    }
}

/// An opened, checked data set.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

impl Dataset {
    /// Reads and checks `dir/manifest.json`.
    pub fn open(dir: impl AsRef<Path>) -> Result<Dataset, DatasetError> {
        let dir = dir.as_ref().to_path_buf();
        let path = dir.join("manifest.json");
        if !path.is_file() {
            return Err(DatasetError::NoManifest { dir });
        }
        let text = std::fs::read_to_string(&path).map_err(|e| DatasetError::BadManifest {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        let manifest: Manifest =
            serde_json::from_str(&text).map_err(|e| DatasetError::BadManifest {
                path: path.clone(),
                reason: format!("not a valid manifest: {e}"),
            })?;
        let mut seen: BTreeMap<&str, Split> = BTreeMap::new();
        for split in Split::ALL {
            for name in manifest.files(split) {
                if let Some(&first) = seen.get(name.as_str()) {
                    return Err(DatasetError::SharedEpisode {
                        dir,
                        name: name.clone(),
                        first,
                        second: split,
                    });
                }
                seen.insert(name, split);
                if !dir.join(name).is_file() {
                    return Err(DatasetError::MissingFile {
                        dir,
                        split,
                        name: name.clone(),
                    });
                }
            }
        }
        tracing::info!(
            dir = %dir.display(),
            train = manifest.train.len(),
            validation = manifest.validation.len(),
            test = manifest.test.len(),
            "data set opened"
        );
        Ok(Dataset { dir, manifest })
    }

    /// The recordings of `split`, in manifest order.
    pub fn paths(&self, split: Split) -> Vec<PathBuf> {
        self.manifest
            .files(split)
            .iter()
            .map(|n| self.dir.join(n))
            .collect()
    }

    /// Reads and resamples every recording of `split` (manifest order),
    /// frames kept compressed ([`FrameStorage::Compressed`]).
    pub fn load_split(
        &self,
        split: Split,
        spec: &WindowSpec,
        needs: Streams,
    ) -> Result<Vec<EpisodeTicks>, DatasetError> {
        self.paths(split)
            .iter()
            .map(|p| load_episode_as(p, spec, needs, FrameStorage::Compressed))
            .collect()
    }
}

/// Reads one recording into ticks, frames decoded (what a tick-by-tick
/// replay reads). The recording must carry the `fall_guard.episode`
/// metadata (the fall onset comes from it) and a message on every topic in
/// `needs`.
pub fn load_episode(
    path: &Path,
    spec: &WindowSpec,
    needs: Streams,
) -> Result<EpisodeTicks, DatasetError> {
    load_episode_as(path, spec, needs, FrameStorage::Decoded)
}

/// [`load_episode`] with the frames held as `storage` says.
pub fn load_episode_as(
    path: &Path,
    spec: &WindowSpec,
    needs: Streams,
    storage: FrameStorage,
) -> Result<EpisodeTicks, DatasetError> {
    let rec = Recording::open(path)?;
    let meta = rec.episode()?;
    if (meta.rate_hz - spec.rate_hz).abs() > 1e-6 {
        tracing::warn!(
            path = %path.display(),
            recorded_hz = meta.rate_hz,
            model_hz = spec.rate_hz,
            "recording rate differs from the model's tick rate; resampling"
        );
    }
    rec.require_topic(topics::JOINT_STATES)?;
    if needs.plan {
        rec.require_topic(topics::PLANNED_TRAJECTORY)?;
    }
    if needs.camera {
        rec.require_topic(topics::HEAD_CAMERA)?;
    }
    Ok(EpisodeTicks::from_recording_as(&rec, spec, storage)?)
}

/// The data directory: `$FALL_GUARD_DATA`, else `~/fall-guard-data` (as
/// `scripts/retrain/retrain.sh` has it).
pub fn data_dir() -> Option<PathBuf> {
    std::env::var_os("FALL_GUARD_DATA")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join("fall-guard-data")))
}

/// `path` as a report or a model file names it: relative to the data
/// directory ([`data_dir`]) when it lies there, so that a file made from
/// the data names no machine; else as given.
pub fn data_name(path: &Path) -> String {
    name_under(path, data_dir().as_deref())
}

/// `path` relative to `dir` when it lies there, else as given.
fn name_under(path: &Path, dir: Option<&Path>) -> String {
    let canonical = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    if let Some(dir) = dir {
        if let Ok(rel) = canonical(path).strip_prefix(canonical(dir)) {
            if !rel.as_os_str().is_empty() {
                return rel.display().to_string();
            }
        }
    }
    path.display().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_path_in_the_data_directory_is_named_relative_to_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let data = dir.path().join("data");
        std::fs::create_dir_all(data.join("runs")).expect("mkdir");
        let run = data.join("runs/emp-s1.bpk");
        std::fs::write(&run, b"x").expect("write");
        assert_eq!(name_under(&run, Some(&data)), "runs/emp-s1.bpk");
        // Not yet written: named by its path alone.
        assert_eq!(name_under(&data.join("simv5"), Some(&data)), "simv5");
        // Outside it, or no data directory: as given.
        let elsewhere = dir.path().join("elsewhere.bpk");
        assert_eq!(
            name_under(&elsewhere, Some(&data)),
            elsewhere.display().to_string()
        );
        assert_eq!(
            name_under(Path::new("models/emp.bpk"), None),
            "models/emp.bpk"
        );
        assert_eq!(name_under(&data, Some(&data)), data.display().to_string());
    }
}
