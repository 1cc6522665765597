//! `mapless-learner-config` — the learner's configuration, without libtorch.
//!
//! The supervisor (`mapless train`) resolves and checks these sections and writes them into
//! the learner's `learner.yaml`; the learner (`mapless-learner`, which links libtorch) runs
//! them. Keeping them here lets every libtorch-free command read, check and show a learner
//! configuration.
//!
//! - [`algorithm`]: which algorithm, its hyperparameters (paper Table I) and the exploration
//!   noise the actors add ([`LearnerConfig`]);
//! - [`device`]: `cpu`, `cuda`, `cuda:N` ([`Device`], syntax only);
//! - [`service`]: the learner process's cadence ([`DriverConfig`]) and settings
//!   ([`LearnerServiceConfig`]).

pub mod algorithm;
pub mod device;
pub mod service;

pub use algorithm::*;
pub use device::Device;
pub use service::{DriverConfig, LearnerEvent, LearnerServiceConfig};

/// Hidden-layer width when none is given ([inferred], SPEC §2).
pub const DEFAULT_HIDDEN_WIDTH: i64 = 256;

/// Checkpoints kept unless told otherwise (`DriverConfig::checkpoint_keep`) [ours: 2, the
/// newest and the one before it, in case the newest is torn].
pub const DEFAULT_CHECKPOINT_KEEP: usize = 2;

/// A configuration value that cannot work; the message names the field.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// A field outside its domain.
    #[error("invalid learner config: `{field}` {reason}")]
    InvalidConfig {
        /// The field, as written in the config file.
        field: &'static str,
        /// What is wrong with it and what would be accepted.
        reason: String,
    },
    /// A device string that is not `cpu`, `cuda` or `cuda:N`.
    #[error("invalid device `{spec}`: {reason}; expected `cpu`, `cuda` or `cuda:N`")]
    InvalidDevice {
        /// The string as given.
        spec: String,
        /// What is wrong with it.
        reason: String,
    },
}
