//! `mapless-replay` — the experience store every actor writes to and the learner samples from.
//!
//! ```text
//!   actors ──gRPC Insert / iceoryx2──► Table (ring columns + sum tree + rate limiter)
//!                                        │            ▲ UpdatePriorities
//!                                        ▼            │
//!                                   Sample stream ──► learner
//! ```
//!
//! Anchored on DeepMind Reverb (tables, selectors, a rate limiter), with exactly-once inserts
//! on (actor id, sequence). The table (`table.rs`) lives in memory; [`DurableTable`]
//! (`persist/`) makes it survive restarts with a write-ahead log and snapshots, and depends on
//! the table, never the reverse. [`ActorRegistry`] (`registry.rs`) gives actor processes their
//! slots (`RegisterActor`), kept beside the table's files. This crate never links libtorch.

pub mod actors;
pub mod bench;
mod clock;
pub mod config;
pub mod error;
/// The fuzz targets' harnesses (`fuzz/` at the repository root); not an API.
#[doc(hidden)]
pub mod fuzzing;
pub mod grpc;
pub mod metrics;
pub mod persist;
pub mod rate_limiter;
pub mod registry;
pub mod server;
pub mod shm;
mod snapshot;
pub mod sum_tree;
pub mod table;
mod wal;

pub use actors::ActorStats;
pub use config::{FsyncPolicy, PersistenceConfig, RateLimiterConfig, SamplerConfig, TableConfig};
pub use error::ReplayError;
pub use persist::{DurableTable, RecoveryReport, SnapshotInfo};
pub use registry::{ActorRegistry, Registration};
pub use table::{CheckpointMark, Journal, StorageRefusal, Table, TableCheckpoint};
pub use wal::StorageFault;
