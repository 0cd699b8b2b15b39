//! Where training runs: `--device cpu|cuda[:N]|wgpu` on `fall-guard-lab train`
//! and `fall-guard-lab bench`.
//!
//! The CPU (burn's Flex backend) is always there. The GPU backends are burn's
//! own, compiled in by cargo feature (`cuda`: NVIDIA through CUDA, `wgpu`:
//! Vulkan/Metal/DX12 through wgpu), so a fleet's recordings can be trained
//! on a GPU machine with the same code and the same model file. A device
//! whose feature is not compiled in is refused with the rebuild command.

use std::fmt;
use std::str::FromStr;

use burn::prelude::Device;

use fall_guard_runtime::model::cpu_device;

/// A training device as named on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TrainDevice {
    /// The CPU backend the daemon uses (Flex, one thread).
    #[default]
    Cpu,
    /// CUDA device `N` (feature `cuda`).
    Cuda(usize),
    /// The default wgpu adapter, a high-power GPU first (feature `wgpu`).
    Wgpu,
}

/// A device name that is not understood, or not compiled in.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DeviceError {
    /// Not one of the accepted spellings.
    #[error("unknown device {0:?}: expected cpu, cuda, cuda:N or wgpu")]
    Unknown(String),
    /// The backend's cargo feature was not enabled when building.
    #[error(
        "device {device} needs a fall-guard built with the `{feature}` feature: \
         cargo build --release --features {feature}"
    )]
    NotCompiled {
        /// The device asked for.
        device: String,
        /// The cargo feature that provides it.
        feature: &'static str,
    },
}

impl FromStr for TrainDevice {
    type Err = DeviceError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let t = s.trim().to_ascii_lowercase();
        match t.as_str() {
            "cpu" => return Ok(TrainDevice::Cpu),
            "cuda" => return Ok(TrainDevice::Cuda(0)),
            "wgpu" => return Ok(TrainDevice::Wgpu),
            _ => {}
        }
        t.strip_prefix("cuda:")
            .and_then(|i| i.parse::<usize>().ok())
            .map(TrainDevice::Cuda)
            .ok_or_else(|| DeviceError::Unknown(s.to_string()))
    }
}

impl fmt::Display for TrainDevice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TrainDevice::Cpu => write!(f, "cpu"),
            TrainDevice::Cuda(i) => write!(f, "cuda:{i}"),
            TrainDevice::Wgpu => write!(f, "wgpu"),
        }
    }
}

impl TrainDevice {
    /// The cargo feature the device needs (`None`: always built).
    pub fn feature(&self) -> Option<&'static str> {
        match self {
            TrainDevice::Cpu => None,
            TrainDevice::Cuda(_) => Some("cuda"),
            TrainDevice::Wgpu => Some("wgpu"),
        }
    }

    /// Whether this binary was built with the device's backend.
    pub fn compiled_in(&self) -> bool {
        match self {
            TrainDevice::Cpu => true,
            TrainDevice::Cuda(_) => cfg!(feature = "cuda"),
            TrainDevice::Wgpu => cfg!(feature = "wgpu"),
        }
    }

    /// The burn device (without autodiff), or why there is none.
    pub fn device(&self) -> Result<Device, DeviceError> {
        if !self.compiled_in() {
            return Err(DeviceError::NotCompiled {
                device: self.to_string(),
                feature: self.feature().unwrap_or("flex"),
            });
        }
        Ok(match *self {
            TrainDevice::Cpu => cpu_device(),
            #[cfg(feature = "cuda")]
            TrainDevice::Cuda(i) => Device::cuda(i),
            #[cfg(feature = "wgpu")]
            TrainDevice::Wgpu => Device::wgpu(burn::tensor::DeviceKind::DefaultDevice),
            // Refused above when the feature is off.
            #[allow(unreachable_patterns)]
            _ => unreachable!("compiled_in() checked the feature"),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_names_parse() {
        assert_eq!("cpu".parse(), Ok(TrainDevice::Cpu));
        assert_eq!(" CPU ".parse(), Ok(TrainDevice::Cpu));
        assert_eq!("cuda".parse(), Ok(TrainDevice::Cuda(0)));
        assert_eq!("cuda:3".parse(), Ok(TrainDevice::Cuda(3)));
        assert_eq!("wgpu".parse(), Ok(TrainDevice::Wgpu));
        for bad in ["", "gpu", "cuda:", "cuda:x", "cuda:-1", "cuda3", "wgpu:0"] {
            assert!(
                matches!(bad.parse::<TrainDevice>(), Err(DeviceError::Unknown(_))),
                "{bad:?}"
            );
        }
        for d in [TrainDevice::Cpu, TrainDevice::Cuda(2), TrainDevice::Wgpu] {
            assert_eq!(d.to_string().parse(), Ok(d));
        }
    }

    #[test]
    fn the_cpu_is_always_there() {
        assert!(TrainDevice::Cpu.compiled_in());
        let device = TrainDevice::Cpu.device().expect("cpu");
        assert_eq!(device, cpu_device());
    }

    #[test]
    fn a_backend_not_compiled_in_is_refused_with_the_rebuild_command() {
        for (d, feature, built) in [
            (TrainDevice::Cuda(1), "cuda", cfg!(feature = "cuda")),
            (TrainDevice::Wgpu, "wgpu", cfg!(feature = "wgpu")),
        ] {
            assert_eq!(d.compiled_in(), built);
            if built {
                continue;
            }
            let e = d.device().expect_err("not compiled in");
            assert_eq!(
                e,
                DeviceError::NotCompiled {
                    device: d.to_string(),
                    feature,
                }
            );
            let msg = e.to_string();
            assert!(
                msg.contains(&format!("--features {feature}")) && msg.contains(&d.to_string()),
                "{msg}"
            );
        }
    }
}
