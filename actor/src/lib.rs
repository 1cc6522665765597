//! `mapless-actor` — the acting side of the cluster, without libtorch.
//!
//! - [`policy`]: the learner's published policy network ([`mapless_proto::v1::WeightsSnapshot`],
//!   safetensors naming) evaluated in pure Rust for all of a process's vehicles at once;
//! - [`noise`]: exploration noise for the deterministic policies (OU for DDPG, Gaussian for TD3);
//! - [`sink`]: which replay client an actor delivers its transition batches with (iceoryx2 or
//!   gRPC; the exactly-once clients themselves are `mapless_net::insert`);
//! - [`identity`]: which index a process runs as (`--index N`, or `auto`: a slot from the replay);
//! - [`nstep`]: n-step rows (discounted sums of n rewards) when the learner bootstraps n steps ahead;
//! - [`run`]: one actor process's loop (the `mapless-actor` binary).
//!
//! How it reaches the replay, the learner's weights and the stats collector (endpoints,
//! security, the shared-memory writer, the insert, weights and stats clients) is `mapless-net`.

/// The `policy_safetensors` fuzz target's harness (`fuzz/` at the repository root); not an API.
#[doc(hidden)]
pub mod fuzzing;
pub mod identity;
pub mod nstep;
pub mod policy;
pub mod run;
pub mod sink;

pub use mapless_proto::exploration::{ExplorationNoise, NoiseProcess};
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
