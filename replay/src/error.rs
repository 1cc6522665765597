//! The replay library's one error type, with its gRPC status.

use mapless_proto::ProtoError;

#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// A batch, request or update that breaks the wire contract (wrong dims, NaN, …).
    #[error(transparent)]
    Invalid(#[from] ProtoError),
    /// A request that names something that does not exist or is out of range.
    #[error("{0}")]
    BadRequest(String),
    /// The rate limiter did not allow the call before its deadline.
    #[error("{op} blocked by the rate limiter for {waited_ms} ms (deadline reached): {state}")]
    DeadlineExceeded { op: &'static str, waited_ms: u64, state: String },
    /// The table is shutting down.
    #[error("table `{0}` is closed")]
    Closed(String),
    #[error("invalid config: {0}")]
    InvalidConfig(String),
    /// `RegisterActor` for a new name while every slot the server allows is held.
    #[error("all {max} actor slots are taken by other names (max_actor_slots in the replay's config); reuse a name or raise the limit")]
    SlotsExhausted { max: u32 },
    /// Disk trouble in the log or snapshots; names the file.
    #[error("storage {path}: {problem}")]
    Storage { path: std::path::PathBuf, problem: String },
    /// The file system holding the log or a snapshot is full (ENOSPC, EDQUOT): the change was
    /// not stored; the same call succeeds once space is freed, without a restart.
    #[error("disk full: {path}: {problem}; inserts are refused until space is freed there (sampling goes on)")]
    DiskFull { path: std::path::PathBuf, problem: String },
}

impl From<mapless_net::shm::ShmError> for ReplayError {
    fn from(e: mapless_net::shm::ShmError) -> Self {
        use mapless_net::shm::ShmError;
        match e {
            ShmError::BadRequest(m) => ReplayError::BadRequest(m),
            ShmError::DeadlineExceeded { op, waited_ms, state } => ReplayError::DeadlineExceeded { op, waited_ms, state },
            ShmError::Closed(m) => ReplayError::Closed(m),
            ShmError::InvalidConfig(m) => ReplayError::InvalidConfig(m),
        }
    }
}

impl ReplayError {
    /// `what` on `path` failed with `e`: [`ReplayError::DiskFull`] when the file system is out
    /// of space or quota, [`ReplayError::Storage`] otherwise.
    pub(crate) fn io(path: &std::path::Path, what: impl std::fmt::Display, e: &std::io::Error) -> ReplayError {
        let problem = format!("{what}: {e}");
        let path = path.to_path_buf();
        if is_disk_full(e) { ReplayError::DiskFull { path, problem } } else { ReplayError::Storage { path, problem } }
    }

    /// The gRPC status a client sees.
    pub fn to_status(&self) -> tonic_status::Status {
        use tonic_status::{Code, Status};
        match self {
            ReplayError::Invalid(e) => e.to_status(),
            ReplayError::BadRequest(m) => Status::new(Code::InvalidArgument, m.clone()),
            ReplayError::DeadlineExceeded { .. } => Status::new(Code::DeadlineExceeded, self.to_string()),
            ReplayError::Closed(_) => Status::new(Code::Unavailable, self.to_string()),
            ReplayError::InvalidConfig(_) => Status::new(Code::FailedPrecondition, self.to_string()),
            ReplayError::SlotsExhausted { .. } => Status::new(Code::ResourceExhausted, self.to_string()),
            ReplayError::Storage { .. } => Status::new(Code::Internal, self.to_string()),
            // gRPC's code for "the entire file system is out of space".
            ReplayError::DiskFull { .. } => Status::new(Code::ResourceExhausted, self.to_string()),
        }
    }
}

/// Whether `e` says the file system is out of space (ENOSPC) or out of quota (EDQUOT).
pub(crate) fn is_disk_full(e: &std::io::Error) -> bool {
    matches!(e.kind(), std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded)
}

/// tonic's status types, re-exported so callers need not name tonic's version.
pub mod tonic_status {
    pub use tonic::{Code, Status};
}
