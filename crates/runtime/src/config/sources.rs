//! The sources' own sections of the config file: the servo buses
//! (`[dynamixel]`, read by `sources/dynamixel.rs`), the head camera
//! (`[camera]`, `sources/camera.rs`), and how fast a replay runs
//! (`sources/replay.rs`). They live here, below the sources, so that the
//! config reads them without importing the sources, and each source takes
//! its section from the config.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

use serde::Deserialize;

/// Pixel format asked from a V4L2 camera.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum PixelFormat {
    Mjpeg,
    Yuyv,
}

/// `[camera]`: the head camera when `[streams].camera = "v4l2"`.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// `/dev/videoN`.
    pub device: PathBuf,
    pub format: PixelFormat,
    pub width: u32,
    pub height: u32,
    pub fps: u32,
}

/// How fast recorded time runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pacing {
    /// `x` times real time (1.0: as recorded).
    Speed(f64),
    /// As fast as inference allows; every tick gets a forecast.
    MaxSpeed,
}

fn default_rate_hz() -> f64 {
    50.0
}
fn default_baud() -> u32 {
    1_000_000
}
fn default_true() -> bool {
    true
}
fn default_timeout_ms() -> u64 {
    20
}
fn default_backoff_ms() -> u64 {
    100
}
fn default_backoff_max_ms() -> u64 {
    5_000
}
fn default_warn_missed_share() -> f64 {
    0.2
}

/// The servo source's config section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamixelConfig {
    /// Read cycles per second (all buses once per cycle). Default 50.
    #[serde(default = "default_rate_hz")]
    pub rate_hz: f64,
    /// A motor that gave no position in more than this share of the read
    /// cycles of the last 10 s is named at WARN on its bus's status, even
    /// while the forecast stays valid (the joint's last value is held while
    /// it is young enough). 0 to 1, default 0.2.
    #[serde(default = "default_warn_missed_share")]
    pub warn_missed_share: f64,
    /// The buses by name; a name is also the joint table's bus name used
    /// when `ids` is left out (`lower`, `upper` on Poppy).
    pub buses: BTreeMap<String, BusConfig>,
}

/// One serial bus.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusConfig {
    /// Serial device path (a `/dev/serial/by-id/...` link survives replugging).
    pub port: String,
    /// Baud rate. Default 1000000.
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Motor ids on this bus; default: the joint table's motors whose bus
    /// has this bus's name. Each must be a joint of the table.
    #[serde(default)]
    pub ids: Option<Vec<u8>>,
    /// Use the USB2AX SYNC_READ (0x84). Default true. When the adapter never
    /// answers it, the reader falls back to READ_DATA per motor by itself.
    #[serde(default = "default_true")]
    pub sync_read: bool,
    /// How long one transaction may wait for its answer. Default 20 ms.
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: u64,
    /// First delay before reopening a lost port. Default 100 ms.
    #[serde(default = "default_backoff_ms")]
    pub reopen_backoff_ms: u64,
    /// Ceiling of the doubling reopen delay. Default 5000 ms.
    #[serde(default = "default_backoff_max_ms")]
    pub reopen_backoff_max_ms: u64,
}

impl BusConfig {
    /// A bus on `port` with every default.
    pub fn new(port: impl Into<String>) -> BusConfig {
        BusConfig {
            port: port.into(),
            baud: default_baud(),
            ids: None,
            sync_read: true,
            timeout_ms: default_timeout_ms(),
            reopen_backoff_ms: default_backoff_ms(),
            reopen_backoff_max_ms: default_backoff_max_ms(),
        }
    }

    pub(crate) fn timeout(&self) -> Duration {
        Duration::from_millis(self.timeout_ms)
    }

    pub(crate) fn reopen_backoff(&self) -> Duration {
        Duration::from_millis(self.reopen_backoff_ms)
    }

    pub(crate) fn reopen_backoff_max(&self) -> Duration {
        Duration::from_millis(self.reopen_backoff_max_ms)
    }
}

impl DynamixelConfig {
    /// Both Poppy buses on the given ports, every other key at its default.
    pub fn poppy(lower_port: impl Into<String>, upper_port: impl Into<String>) -> DynamixelConfig {
        let mut buses = BTreeMap::new();
        buses.insert("lower".to_string(), BusConfig::new(lower_port));
        buses.insert("upper".to_string(), BusConfig::new(upper_port));
        DynamixelConfig {
            rate_hz: default_rate_hz(),
            warn_missed_share: default_warn_missed_share(),
            buses,
        }
    }
}
