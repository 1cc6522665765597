//! The learner's one error type.

/// Everything the learner library can fail with. Messages are written for the person who typed
/// the config: they name the offending value and what would be accepted instead.
#[derive(Debug, thiserror::Error)]
pub enum LearnerError {
    /// A device string that is not `cpu`, `cuda` or `cuda:N`.
    #[error("invalid device `{spec}`: {reason}; expected `cpu`, `cuda` or `cuda:N`")]
    InvalidDevice {
        /// The string as given.
        spec: String,
        /// What is wrong with it.
        reason: String,
    },

    /// A CUDA device was asked for, but libtorch sees none (no GPU, no driver, a CPU-only
    /// libtorch, or `CUDA_VISIBLE_DEVICES` hides them all).
    #[error(
        "device `{spec}` requested, but libtorch sees no CUDA device (no GPU or driver, a \
         CPU-only libtorch, or CUDA_VISIBLE_DEVICES hides them); use `cpu` instead"
    )]
    CudaUnavailable {
        /// The string as given.
        spec: String,
    },

    /// `cuda:N` with N at or past the number of visible devices.
    #[error("device `cuda:{index}` requested, but libtorch sees only {count} CUDA device(s)")]
    CudaDeviceOutOfRange {
        /// The requested ordinal.
        index: usize,
        /// How many devices libtorch sees.
        count: usize,
    },

    /// A libtorch thread count of zero or one too large for libtorch's `int`.
    #[error("invalid libtorch {pool} thread count {count}: must be between 1 and {max}", max = i32::MAX)]
    InvalidThreadCount {
        /// `intra-op` or `inter-op`.
        pool: &'static str,
        /// The requested count.
        count: usize,
    },

    /// libtorch fixes the inter-op pool size once per process.
    #[error(
        "libtorch inter-op threads: cannot set {requested}: {reason} (libtorch allows setting \
         it once per process, before any inter-op parallel work)"
    )]
    InteropThreadsFixed {
        /// The requested count.
        requested: usize,
        /// What libtorch or our own bookkeeping said.
        reason: String,
    },

    /// A network whose layer sizes make no sense.
    #[error("invalid network `{name}`: {reason}")]
    InvalidNetwork {
        /// The network's VarStore prefix.
        name: String,
        /// What is wrong with it.
        reason: String,
    },

    /// Anything libtorch itself reported.
    #[error("libtorch: {0}")]
    Torch(#[from] tch::TchError),

    /// A replay source other than the gRPC one (e.g. a table in the same process) refused or
    /// failed a call.
    #[error("replay: {0}")]
    Replay(String),

    /// A gRPC call to a peer (the replay service, the weights service) failed: the peer could
    /// not be reached (`Unavailable`), or it answered with an error status.
    #[error("{service} at {endpoint}: {code:?}: {message}")]
    Grpc {
        /// `replay` or `weights`.
        service: &'static str,
        /// The address dialled.
        endpoint: String,
        /// The gRPC status code (transport failures are `Unavailable`).
        code: tonic::Code,
        /// The peer's status message, or the transport error.
        message: String,
    },

    /// A weights snapshot, or a `.safetensors` file meant to hold one, breaks the contract.
    #[error("invalid weights ({origin}): {reason}")]
    InvalidWeights {
        /// Where the weights came from: a file path, `publish`, a tensor list.
        origin: String,
        /// What is wrong.
        reason: String,
    },

    /// Reading or writing a file failed.
    #[error("{path}: {error}")]
    FileIo {
        /// The file.
        path: std::path::PathBuf,
        /// What the OS said.
        error: std::io::Error,
    },

    /// A replay source configured with values that cannot work (batch size 0, an endpoint
    /// that is not a URI, a token that is not ASCII, ...).
    #[error("invalid replay source config: {reason}")]
    ReplaySourceConfig {
        /// What is wrong, naming the field.
        reason: String,
    },

    /// Priorities handed to a replay source that it cannot send (lengths differ, NaN, < 0).
    #[error("invalid priority update: {reason}")]
    InvalidPriorities {
        /// What is wrong.
        reason: String,
    },

    /// A TensorBoard event file that cannot be written or read back (bad CRC, truncated
    /// record, an empty tag).
    #[error("event file {path}: {reason}")]
    EventFile {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong.
        reason: String,
    },

    /// A replay source stopped for good after an error that retrying cannot fix (wrong
    /// table, wrong token, incompatible dims, ...); every later call returns this again.
    #[error("replay source stopped: {reason}")]
    ReplaySourceStopped {
        /// The error that stopped it.
        reason: String,
    },

    /// A minibatch (or observation) whose shape or values cannot be learned from.
    #[error("invalid batch: {0}")]
    InvalidBatch(String),

    /// A learner config value outside its domain.
    #[error("invalid learner config: `{field}` {reason}")]
    InvalidConfig {
        /// The field, as written in the config file.
        field: &'static str,
        /// What is wrong with it and what would be accepted.
        reason: String,
    },

    /// A loss came out NaN or infinite; the step was not applied.
    #[error("{what} is {value} at update {update}; the step was not applied (diverged, or a learning rate too high?)")]
    NonFiniteLoss {
        /// Which loss (`losses/critic`, ...).
        what: &'static str,
        /// The value.
        value: f64,
        /// The agent's update counter.
        update: u64,
    },

    /// A checkpoint could not be written or read from disk.
    #[error("checkpoint `{path}`: {reason}")]
    CheckpointIo {
        /// The file or directory.
        path: std::path::PathBuf,
        /// The operation and the OS error.
        reason: String,
    },

    /// A checkpoint whose bytes are damaged: a checksum mismatch, a truncated or unparsable file.
    #[error("checkpoint `{path}` is corrupt: {reason}")]
    CheckpointCorrupt {
        /// The file or directory.
        path: std::path::PathBuf,
        /// What is wrong.
        reason: String,
    },

    /// An intact checkpoint that does not fit: another algorithm, other dimensions, another
    /// critic normalisation, another format version, or tensors of other shapes.
    #[error("checkpoint `{path}` does not match: {what} is {found}, expected {expected}")]
    CheckpointMismatch {
        /// The checkpoint directory.
        path: std::path::PathBuf,
        /// Which property differs.
        what: String,
        /// What this learner needs.
        expected: String,
        /// What the checkpoint holds.
        found: String,
    },
}

impl From<mapless_learner_config::ConfigError> for LearnerError {
    fn from(e: mapless_learner_config::ConfigError) -> Self {
        use mapless_learner_config::ConfigError;
        match e {
            ConfigError::InvalidConfig { field, reason } => LearnerError::InvalidConfig { field, reason },
            ConfigError::InvalidDevice { spec, reason } => LearnerError::InvalidDevice { spec, reason },
        }
    }
}

/// A failed atomic write (a policy file, checkpoints' `LATEST`): the path the failed step acted
/// on and what the OS said.
impl From<mapless_proto::atomic_file::AtomicWriteError> for LearnerError {
    fn from(e: mapless_proto::atomic_file::AtomicWriteError) -> Self {
        LearnerError::FileIo { path: e.path, error: e.error }
    }
}

impl From<mapless_proto::weights_file::WeightsFileError> for LearnerError {
    fn from(e: mapless_proto::weights_file::WeightsFileError) -> Self {
        use mapless_proto::weights_file::WeightsFileError;
        match e {
            WeightsFileError::Invalid { origin, reason } => LearnerError::InvalidWeights { origin, reason },
            WeightsFileError::Io { path, error } => LearnerError::FileIo { path, error },
        }
    }
}

impl From<mapless_net::NetError> for LearnerError {
    fn from(e: mapless_net::NetError) -> Self {
        use mapless_net::NetError;
        match e {
            NetError::Grpc { service, endpoint, code, message } => LearnerError::Grpc { service, endpoint, code, message },
            NetError::Config { reason } => LearnerError::ReplaySourceConfig { reason },
            NetError::FileIo { path, error } => LearnerError::FileIo { path, error },
            NetError::Invalid { origin, reason } => LearnerError::InvalidWeights { origin, reason },
            NetError::ClientConfig { reason, .. } => LearnerError::ReplaySourceConfig { reason },
            NetError::Stopped { reason, .. } => LearnerError::ReplaySourceStopped { reason },
        }
    }
}
