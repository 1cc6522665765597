//! The mapless wire contract, version 1.
//!
//! ```text
//!  actor --Insert(TransitionBatch*)--> ReplayService --Sample -> SampledBatch*--> learner
//!    ^                                                                              |
//!    +------------- WeightsService.Subscribe -> WeightsSnapshot* -------------------+
//!  actor --StatsService.Report(EpisodeStats*)--> learner (or a collector)
//! ```
//!
//! The `.proto` files under `proto/mapless/v1/` are the API documentation: every message,
//! field and RPC is described there, including the order of messages on every stream. This
//! crate holds
//!
//! - [`v1`]: the Rust generated from them by prost and tonic (messages, servers and clients),
//!   checked in under `src/gen/` so that no dependent crate needs `protoc`
//!   (`tests/codegen.rs` keeps it in sync; see `README.md`);
//! - hand-written helpers on the generated types: validation of everything a peer sends
//!   ([`v1::TransitionBatch::validate`], [`v1::SampledBatch::validate`],
//!   [`v1::SampleRequest::validate`], [`v1::PriorityUpdate::validate`],
//!   [`v1::WeightsSnapshot::validate`], [`v1::EpisodeStats::validate`]), a
//!   [`TransitionBatchBuilder`], row accessors returning [`Transition`] views, column
//!   accessors that read either encoding of the float columns ([`FloatColumn`],
//!   [`FloatEncoding`]), f32 tensor conversion, and the error type [`ProtoError`] with its
//!   mapping to a gRPC status.
//!
//! - [`weights_file`]: the `.safetensors` codec of [`v1::WeightsSnapshot`] (policy files that
//!   actors, `mapless eval` and deployments read without libtorch);
//! - [`atomic_file`]: the workspace's one atomic file write (the lowest crate that the
//!   learner, the replay, the supervisor and the pictures all reach).
//!
//! Apart from [`weights_file`]'s and [`atomic_file`]'s reads and writes, nothing here does
//! I/O or spawns tasks;
//! servers and clients live in `mapless-net` and the crates that use it.

pub mod atomic_file;
mod error;
pub mod exploration;
mod floats;
mod replay;
mod stats;
mod tensor;
mod transition;
pub mod weights_file;

pub use error::ProtoError;
pub use floats::{FloatColumn, FloatEncoding, extend_f32le, f32le_bytes};
pub use replay::check_actor_name;
pub use transition::{Transition, TransitionBatchBuilder};

/// Messages, services and clients of package `mapless.v1`, generated from
/// `proto/mapless/v1/*.proto`.
///
/// Servers implement e.g. [`v1::weights_service_server::WeightsService`] on a plain struct and
/// wrap it in [`v1::weights_service_server::WeightsServiceServer`]; clients use
/// [`v1::weights_service_client::WeightsServiceClient`]. Configure both with
/// [`MAX_MESSAGE_BYTES`] (`max_decoding_message_size` / `max_encoding_message_size`), because
/// tonic's default decoding limit is 4 MiB.
#[allow(missing_docs, clippy::all, clippy::pedantic, rustdoc::broken_intra_doc_links, rustdoc::invalid_html_tags)]
pub mod v1 {
    include!("gen/mapless.v1.rs");
}

/// Version of the wire contract this crate implements; the value of
/// [`v1::ProtocolVersion::V1`]. Requests carrying any other version are rejected with
/// [`ProtoError::UnsupportedProtocolVersion`] (gRPC FAILED_PRECONDITION).
pub const PROTOCOL_VERSION: u32 = 1;

// The constant and the enum must never disagree.
const _: () = assert!(PROTOCOL_VERSION as i32 == v1::ProtocolVersion::V1 as i32);

/// Largest encoded message either side sends or accepts: 16 MiB.
///
/// Sized for a TransitionBatch of about 1,000 rows of a dense 1,080-beam scan
/// (obs_dim = 2,163, so ~17 KiB per row) or ~90,000 rows of the default 7-beam scan, and for
/// a WeightsSnapshot of a few million f32 parameters; the policy networks are far smaller.
/// Bounding every message keeps a misbehaving peer from making a server allocate without
/// limit. tonic rejects a larger message with OUT_OF_RANGE before it reaches mapless code.
pub const MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;

/// Name of the replay table when none is configured (`replay.name`); the shared-memory
/// ingest's default service prefix is derived from it.
pub const DEFAULT_TABLE: &str = "transitions";

/// Longest accepted `actor_id`, in bytes. Ids are keys in the replay server's persistent
/// de-duplication table and appear in every log line, so they stay short.
pub const MAX_ACTOR_ID_BYTES: usize = 128;

/// `WeightsSnapshot.metadata` key of the n a learner bootstraps its TD targets with (absent:
/// 1): actors that sum another number of rewards per row refuse those weights.
pub const META_N_STEP: &str = "n_step";

/// `WeightsSnapshot.metadata` key of the learner's γ, published with [`META_N_STEP`] when n > 1:
/// actors whose rows sum with another γ refuse those weights.
pub const META_GAMMA: &str = "gamma";

/// Largest n of n-step rows and targets (`learner.n_step`).
pub const MAX_N_STEP: usize = 64;

/// Longest accepted `RegisterActorRequest.name`, in bytes: a DNS host name (at most 63 bytes
/// per label) or a container id (64 hex digits) fits, and the actor id derived from the slot
/// stays within [`MAX_ACTOR_ID_BYTES`] whatever the name.
pub const MAX_ACTOR_NAME_BYTES: usize = 128;

/// Checks a message's `protocol_version` field (the raw `i32` prost stores, so that values
/// from a newer contract are seen as what they are, not as the default).
///
/// Servers call this first on every request, e.g.
/// `check_protocol_version(request.protocol_version)?`.
pub fn check_protocol_version(protocol_version: i32) -> Result<(), ProtoError> {
    if protocol_version == v1::ProtocolVersion::V1 as i32 { Ok(()) } else { Err(ProtoError::UnsupportedProtocolVersion { got: protocol_version }) }
}
