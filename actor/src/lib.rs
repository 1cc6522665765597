//! `mapless-actor` — the acting side of the cluster, without libtorch.
//!
//! - [`policy`]: the learner's published policy network ([`mapless_proto::v1::WeightsSnapshot`],
//!   safetensors naming) evaluated in pure Rust for all of a process's vehicles at once;
//! - [`noise`]: exploration noise for the deterministic policies (OU for DDPG, Gaussian for TD3);
//! - [`net`]: reaching gRPC services (URI, TLS, bearer token), shared with the learner;
//! - [`weights`]: the checked weights-stream client and a reconnecting follower;
//! - [`sink`]: delivery of transition batches to the replay (iceoryx2 or gRPC), exactly once;
//! - [`stats`]: episode statistics, reported and collected;
//! - [`run`]: one actor process's loop (the `mapless-actor` binary).

pub mod metrics;
pub mod net;
pub mod noise;
pub mod policy;
pub mod run;
pub mod sink;
pub mod stats;
pub mod weights;

pub use noise::{Noise, NoiseConfig};
pub use policy::{ActMode, Head, Policy};

/// Everything an actor can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    /// Published weights that this actor cannot use (missing tensor, wrong shape, ...).
    #[error("unusable policy weights: {0}")]
    BadWeights(String),
    /// Inputs of the wrong size or with non-finite values.
    #[error("wrong input: {0}")]
    Dimension(String),
}
