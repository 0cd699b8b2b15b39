//! The error of the training-side commands (`train`, `eval`, `calibrate`,
//! `warnings`, `half`, `bench`): each says what was asked or being done (a
//! flag, a named file, a training step) and why it failed.

use std::fmt::Display;

use crate::device::DeviceError;
use fall_guard_runtime::model::ModelError;

/// Any error kept as the cause of a [`CommandError`].
pub type BoxError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// The result of a training-side command.
pub type CommandResult<T> = Result<T, CommandError>;

#[derive(Debug, thiserror::Error)]
pub enum CommandError {
    /// A request that cannot be carried out as given: the message names
    /// the flag, setting or file and what to pass instead.
    #[error("{0}")]
    Refused(String),
    /// A step that failed: what was being done (reading or writing a named
    /// file, a training step), and the cause.
    #[error("{doing}: {source}")]
    Failed {
        doing: String,
        #[source]
        source: BoxError,
    },
    /// A failure whose own message names its input (a model file, a data
    /// set, a recording, a window).
    #[error(transparent)]
    Cause(BoxError),
}

/// A refused request, its message naming what to change.
pub(crate) fn refused(message: impl Display) -> CommandError {
    CommandError::Refused(message.to_string())
}

/// Says what was being done when a step failed.
pub(crate) trait Doing<T> {
    fn doing<D: Display>(self, what: impl FnOnce() -> D) -> CommandResult<T>;
}

impl<T, E: Into<BoxError>> Doing<T> for Result<T, E> {
    fn doing<D: Display>(self, what: impl FnOnce() -> D) -> CommandResult<T> {
        self.map_err(|e| CommandError::Failed {
            doing: what().to_string(),
            source: e.into(),
        })
    }
}

macro_rules! cause_from {
    ($($t:ty),* $(,)?) => {$(
        impl From<$t> for CommandError {
            fn from(e: $t) -> CommandError {
                CommandError::Cause(Box::new(e))
            }
        }
    )*};
}

cause_from!(
    std::io::Error,
    serde_json::Error,
    ModelError,
    fall_guard_runtime::recording::RecordingError,
    fall_guard_runtime::window::WindowError,
    TrainError,
    crate::dataset::DatasetError,
    DeviceError,
    crate::plots::PlotError,
);

impl From<BoxError> for CommandError {
    fn from(e: BoxError) -> CommandError {
        CommandError::Cause(e)
    }
}

/// Errors of training (the loop, its windows and its checkpoints).
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The model rejected a window.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// The data could not be read or sampled.
    #[error("training data: {0}")]
    Data(String),
    /// The training device is unknown or not compiled in.
    #[error(transparent)]
    Device(#[from] DeviceError),
}
