//! Which device the learner's tensors live on, as written in configs and on the command line.
//!
//! Two steps, so that configs can be validated on any machine:
//! - [`str::parse`] (`FromStr`) checks syntax only and never touches libtorch;
//! - [`Device::parse`] also checks that libtorch can actually use the device, so asking for
//!   `cuda` on a machine without one is a clear [`LearnerError::CudaUnavailable`] at start-up,
//!   not a panic deep inside the first tensor operation.

use std::fmt;
use std::str::FromStr;

use crate::LearnerError;

/// A device the learner can run on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Device {
    /// The host CPU (`cpu`).
    Cpu,
    /// CUDA device by ordinal (`cuda` is `cuda:0`).
    Cuda(usize),
}

impl Device {
    /// Parses `cpu`, `cuda` or `cuda:N` (case-insensitive, surrounding spaces ignored) and
    /// checks that libtorch can use the device.
    pub fn parse(spec: &str) -> Result<Self, LearnerError> {
        let device: Self = spec.parse()?;
        device.ensure_available(spec)?;
        Ok(device)
    }

    /// Checks that libtorch sees this device. `spec` is the string to quote in the error.
    fn ensure_available(self, spec: &str) -> Result<(), LearnerError> {
        match self {
            Self::Cpu => Ok(()),
            Self::Cuda(index) => {
                if !tch::Cuda::is_available() {
                    return Err(LearnerError::CudaUnavailable { spec: spec.trim().to_owned() });
                }
                // device_count is an i64 in tch; a negative count would be a libtorch bug and
                // reads as "none".
                let count = usize::try_from(tch::Cuda::device_count()).unwrap_or(0);
                if index >= count {
                    return Err(LearnerError::CudaDeviceOutOfRange { index, count });
                }
                Ok(())
            }
        }
    }

    /// The tch device for tensors and `VarStore`s.
    pub fn to_tch(self) -> tch::Device {
        match self {
            Self::Cpu => tch::Device::Cpu,
            Self::Cuda(index) => tch::Device::Cuda(index),
        }
    }
}

impl FromStr for Device {
    type Err = LearnerError;

    /// Syntax only: does not ask libtorch whether the device exists.
    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let invalid = |reason: &str| LearnerError::InvalidDevice { spec: spec.to_owned(), reason: reason.to_owned() };
        let lower = spec.trim().to_ascii_lowercase();
        match lower.as_str() {
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda(0)),
            other => match other.strip_prefix("cuda:") {
                Some(ordinal) => ordinal.parse::<usize>().map(Self::Cuda).map_err(|_| invalid("the CUDA ordinal must be a non-negative integer")),
                None => Err(invalid("unknown device")),
            },
        }
    }
}

impl fmt::Display for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Cpu => f.write_str("cpu"),
            Self::Cuda(index) => write!(f, "cuda:{index}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn syntax_accepts_cpu_cuda_and_ordinals() {
        assert_eq!("cpu".parse::<Device>().unwrap(), Device::Cpu);
        assert_eq!(" CPU ".parse::<Device>().unwrap(), Device::Cpu);
        assert_eq!("cuda".parse::<Device>().unwrap(), Device::Cuda(0));
        assert_eq!("cuda:3".parse::<Device>().unwrap(), Device::Cuda(3));
    }

    #[test]
    fn syntax_rejects_unknown_devices_and_bad_ordinals_with_the_accepted_forms() {
        for bad in ["", "gpu", "mps", "cuda:", "cuda:-1", "cuda:x", "cuda:1:2", "cpu:0"] {
            let err = bad.parse::<Device>().unwrap_err();
            assert!(matches!(err, LearnerError::InvalidDevice { .. }), "{bad:?} gave {err:?}");
            assert!(err.to_string().contains("expected `cpu`, `cuda` or `cuda:N`"), "{err}");
        }
    }

    #[test]
    fn display_round_trips_through_parse() {
        for device in [Device::Cpu, Device::Cuda(0), Device::Cuda(7)] {
            assert_eq!(device.to_string().parse::<Device>().unwrap(), device);
        }
    }

    #[test]
    fn cpu_is_always_available() {
        assert_eq!(Device::parse("cpu").unwrap().to_tch(), tch::Device::Cpu);
    }
}
