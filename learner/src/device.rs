//! Which device the learner's tensors live on. The [`Device`] value and its syntax live in
//! `mapless-learner-config` (configs are checked without libtorch); here, two steps more:
//! [`available`] checks that libtorch can actually use the device, so asking for `cuda` on a
//! machine without one is a clear [`LearnerError::CudaUnavailable`] at start-up, not a panic
//! deep inside the first tensor operation, and [`ToTch`] names it for tch.

pub use mapless_learner_config::Device;

use crate::LearnerError;

/// Parses `cpu`, `cuda` or `cuda:N` (case-insensitive, surrounding spaces ignored) and checks
/// that libtorch can use the device.
pub fn available(spec: &str) -> Result<Device, LearnerError> {
    let device: Device = spec.parse()?;
    ensure_available(device, spec)?;
    Ok(device)
}

/// Checks that libtorch sees `device`. `spec` is the string to quote in the error.
fn ensure_available(device: Device, spec: &str) -> Result<(), LearnerError> {
    match device {
        Device::Cpu => Ok(()),
        Device::Cuda(index) => {
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
pub trait ToTch {
    fn to_tch(self) -> tch::Device;
}

impl ToTch for Device {
    fn to_tch(self) -> tch::Device {
        match self {
            Device::Cpu => tch::Device::Cpu,
            Device::Cuda(index) => tch::Device::Cuda(index),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_is_always_available() {
        assert_eq!(available("cpu").unwrap().to_tch(), tch::Device::Cpu);
    }
}
