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
}
