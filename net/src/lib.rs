//! `mapless-net` — how the cluster's processes reach each other, shared by the actors, the
//! replay, the learner and the supervisor; no libtorch, no simulator, no table.
//!
//! ```text
//!   actor ──ShmWriter (iceoryx2, same host) / Insert (gRPC)──► replay ──Sample (gRPC)──► learner
//!     ▲                                                                                   │
//!     └───────────────────── weights::subscribe / follow (gRPC stream) ◄──────────────────┘
//!   actor ──stats::report──► supervisor (stats::serve_collector)
//!   (insert: ShmInsertClient / InsertClient; sample: SampleClient)
//! ```
//!
//! - [`endpoint`]: where a service is and how to reach it (URI, TLS CA, bearer token), the
//!   client-side [`ClientSecurity`] settings, and [`NetError`];
//! - [`serve`]: the server side of the same rules — TLS files, bearer-token and role checks, and
//!   [`serve::serve_secured`], the one way every gRPC service of the cluster is served;
//! - [`shm`]: the shared-memory ingest's settings, wire types and the actors' [`shm::ShmWriter`];
//! - [`insert`]: the actors' exactly-once delivery of transition batches — [`insert::InsertClient`]
//!   (gRPC `Insert`) and [`insert::ShmInsertClient`] (over the writer);
//! - [`register`]: an actor's slot from the replay (`RegisterActor`, for `--index auto`);
//! - [`sample`]: the learner's prefetching `Sample` client with asynchronous priority updates,
//!   [`sample::SampleClient`];
//! - [`weights`]: the checked weights-stream client and a reconnecting follower;
//! - [`stats`]: episode statistics, reported by actors and collected by the supervisor;
//! - [`logging`]: every process's log set-up with its identity on every line;
//! - [`metrics`]: the Prometheus `/metrics` exporter of every process, and the one line per
//!   figure that every `mapless bench` prints;
//! - [`health`]: whether a process can do its job — the gRPC health protocol beside every
//!   service, `/healthz` beside every `/metrics`, and the probes a container runs;
//! - [`signals`]: the SIGINT/SIGTERM every service stops on.

pub mod endpoint;
pub mod health;
pub mod insert;
pub mod logging;
pub mod metrics;
pub mod register;
pub mod sample;
pub mod serve;
pub mod shm;
pub mod stats;
pub mod weights;

pub use endpoint::{ClientSecurity, GrpcEndpoint, NetError, error_chain};
pub use serve::{AuthRefusals, BearerAuth, Role, RoleTokenFiles, RoleTokens, Security, TlsFiles, TlsPem};
pub mod signals;
