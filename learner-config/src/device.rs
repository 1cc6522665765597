//! Which device the learner's tensors live on, as written in configs and on the command line.
//! Parsing here checks the syntax only; whether libtorch can use the device is checked where
//! the learner starts (`mapless_learner::device::available`).

use std::fmt;
use std::str::FromStr;

use crate::ConfigError;

/// A device the learner can run on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Device {
    /// The host CPU (`cpu`).
    Cpu,
    /// CUDA device by ordinal (`cuda` is `cuda:0`).
    Cuda(usize),
}

impl FromStr for Device {
    type Err = ConfigError;

    /// Syntax only: does not ask libtorch whether the device exists.
    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let invalid = |reason: &str| ConfigError::InvalidDevice { spec: spec.to_owned(), reason: reason.to_owned() };
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
            assert!(matches!(err, ConfigError::InvalidDevice { .. }), "{bad:?} gave {err:?}");
            assert!(err.to_string().contains("expected `cpu`, `cuda` or `cuda:N`"), "{err}");
        }
    }

    #[test]
    fn display_round_trips_through_parse() {
        for device in [Device::Cpu, Device::Cuda(0), Device::Cuda(7)] {
            assert_eq!(device.to_string().parse::<Device>().unwrap(), device);
        }
    }
}
