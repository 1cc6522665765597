//! libtorch's CPU thread pools, set explicitly.
//!
//! libtorch keeps two pools per process:
//! - **intra-op** (OpenMP here: the PyPI build links libgomp): splits one operator, e.g. a
//!   128×256 matmul, across threads. Default: one thread per core.
//! - **inter-op**: runs independent tasks concurrently (`at::launch`: TorchScript forks and a
//!   few operators). Default: one thread per core. libtorch lets a process set its size only
//!   *once*, and only before any inter-op work has started.
//!
//! Why the learner's default is 1 + 1 rather than libtorch's: the learner shares its machine
//! with actor processes (on the reference box, 2 cores in all), and libtorch's worker threads
//! do not sleep when idle: OpenMP workers busy-wait (spin) for a while after every parallel
//! region before blocking, so an idle-looking learner with N intra-op threads keeps N cores
//! hot and steals them from the simulators. At the paper's sizes (minibatch 128, 256-wide
//! layers) one thread per pool loses little; raise the counts when the learner has cores of
//! its own (or runs on CUDA, where these pools matter less).

use std::sync::Mutex;

use crate::LearnerError;

/// Default for both pools; see the module docs for why it is 1.
pub const DEFAULT_TORCH_THREADS: usize = 1;

/// Sizes of libtorch's two CPU thread pools.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct TorchThreads {
    /// Threads used inside one operator (`at::set_num_threads`).
    pub intra_op: usize,
    /// Threads running independent operators concurrently (`at::set_num_interop_threads`).
    pub inter_op: usize,
}

impl Default for TorchThreads {
    fn default() -> Self {
        Self { intra_op: DEFAULT_TORCH_THREADS, inter_op: DEFAULT_TORCH_THREADS }
    }
}

/// The inter-op count this process has fixed, if any. libtorch itself would throw on a second
/// `set_num_interop_threads`; remembering the value lets a repeat call with the same count
/// (every test in one test binary, say) succeed.
static INTEROP_FIXED: Mutex<Option<usize>> = Mutex::new(None);

impl TorchThreads {
    /// Applies both counts to this process's libtorch.
    ///
    /// The intra-op count may be changed any number of times. The inter-op count is fixed by
    /// the first successful call; later calls must ask for the same value, otherwise
    /// [`LearnerError::InteropThreadsFixed`]. Call it at start-up, before any tensor work.
    pub fn apply(self) -> Result<(), LearnerError> {
        let intra = to_torch_count("intra-op", self.intra_op)?;
        let inter = to_torch_count("inter-op", self.inter_op)?;

        // A poisoned lock only means another thread panicked while holding it; the Option
        // inside is still meaningful.
        let mut fixed = INTEROP_FIXED.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        match *fixed {
            Some(current) if current == self.inter_op => {}
            Some(current) => {
                return Err(LearnerError::InteropThreadsFixed { requested: self.inter_op, reason: format!("this process already set it to {current}") });
            }
            None => {
                // tch panics (rather than returning an error) when libtorch throws, e.g. because
                // inter-op work already ran; turn that into an error value.
                std::panic::catch_unwind(|| tch::set_num_interop_threads(inter)).map_err(|panic| LearnerError::InteropThreadsFixed { requested: self.inter_op, reason: panic_message(&*panic) })?;
                *fixed = Some(self.inter_op);
            }
        }
        drop(fixed);

        tch::set_num_threads(intra);
        Ok(())
    }
}

fn to_torch_count(pool: &'static str, count: usize) -> Result<i32, LearnerError> {
    match i32::try_from(count) {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(LearnerError::InvalidThreadCount { pool, count }),
    }
}

fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = panic.downcast_ref::<String>() {
        s.clone()
    } else if let Some(s) = panic.downcast_ref::<&str>() {
        (*s).to_owned()
    } else {
        "libtorch refused".to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_one_thread_per_pool() {
        assert_eq!(TorchThreads::default(), TorchThreads { intra_op: 1, inter_op: 1 });
    }

    #[test]
    fn zero_threads_is_rejected_before_reaching_libtorch() {
        let err = TorchThreads { intra_op: 0, inter_op: 1 }.apply().unwrap_err();
        assert!(matches!(err, LearnerError::InvalidThreadCount { pool: "intra-op", count: 0 }));
    }

    #[test]
    fn apply_sets_both_pools_and_repeats_are_idempotent_but_changes_to_inter_op_are_refused() {
        let threads = TorchThreads::default();
        threads.apply().unwrap();
        threads.apply().unwrap();
        assert_eq!(tch::get_num_threads(), 1);
        assert_eq!(tch::get_num_interop_threads(), 1);

        let err = TorchThreads { intra_op: 1, inter_op: 2 }.apply().unwrap_err();
        assert!(matches!(err, LearnerError::InteropThreadsFixed { requested: 2, .. }), "{err}");
        assert_eq!(tch::get_num_interop_threads(), 1);
    }
}
