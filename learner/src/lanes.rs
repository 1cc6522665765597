//! Two lanes for the fused CPU update: the calling thread and one persistent helper thread,
//! each running single-threaded BLAS, so that independent products of one update (the two
//! critics' forward passes, a layer's weight gradient beside its input gradient, the actor on
//! `s` beside the actor on `s′`) run side by side instead of each being split across threads.
//!
//! Why: at the paper's sizes one 128×256×256 product is small; split across OpenMP threads it
//! pays a barrier per product, and on a shared VM a late thread stalls both. Whole products
//! per thread were faster for SAC with two threads in every A/B run (docs/learner.md). The
//! results with two lanes are those of one lane with single-threaded BLAS (libtorch at one
//! intra-op thread): every product and sum is the same (`tests/lanes.rs`).
//!
//! A [`Lanes`] is idle (`join` runs both closures in turn on the caller) unless libtorch has
//! ≥ 2 intra-op threads and its BLAS is MKL, whose thread count can be set per thread.

use std::any::Any;
use std::cell::{Cell, UnsafeCell};
use std::os::raw::c_int;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::thread::{JoinHandle, Thread};
use std::time::{Duration, Instant};

const IDLE: u8 = 0;
const READY: u8 = 1;
const DONE: u8 = 2;
const EXIT: u8 = 3;

/// How long a waiting side spins before it parks: longer than most waits inside an update,
/// short enough that an idle helper leaves the core to the actors.
const SPIN: Duration = Duration::from_micros(1000);

/// Whether a fused update can run on two lanes in this process (libtorch's BLAS is MKL).
pub fn available() -> bool {
    mkl_set_local().is_some()
}

/// MKL's per-thread thread count (`MKL_Set_Num_Threads_Local`), found at run time so that a
/// libtorch built on another BLAS still links (and simply gets no second lane).
fn mkl_set_local() -> Option<unsafe extern "C" fn(c_int) -> c_int> {
    #[cfg(target_os = "linux")]
    {
        use std::sync::OnceLock;
        static F: OnceLock<Option<unsafe extern "C" fn(c_int) -> c_int>> = OnceLock::new();
        *F.get_or_init(|| {
            unsafe extern "C" {
                fn dlsym(handle: *mut std::ffi::c_void, symbol: *const std::os::raw::c_char) -> *mut std::ffi::c_void;
            }
            // SAFETY: RTLD_DEFAULT (null on Linux) searches the loaded objects; the name is a
            // NUL-terminated literal. A non-null result is MKL's documented
            // `int MKL_Set_Num_Threads_Local(int)`.
            let f = unsafe { dlsym(std::ptr::null_mut(), c"MKL_Set_Num_Threads_Local".as_ptr()) };
            (!f.is_null()).then(|| unsafe { std::mem::transmute::<*mut std::ffi::c_void, unsafe extern "C" fn(c_int) -> c_int>(f) })
        })
    }
    #[cfg(not(target_os = "linux"))]
    {
        None
    }
}

/// Sets this thread's BLAS thread count (0: back to the process-wide one); returns the
/// previous local setting.
fn set_local_blas_threads(f: unsafe extern "C" fn(c_int) -> c_int, n: c_int) -> c_int {
    // SAFETY: MKL's thread-local setting; any non-negative value is valid.
    unsafe { f(n) }
}

/// The job slot shared by the caller and the helper. `state` orders every access: the caller
/// writes `job` and `caller` only in IDLE, the helper reads them only after seeing READY and
/// writes `panic` before publishing DONE, and the caller reads `panic` only after seeing DONE.
struct Slot {
    state: AtomicU8,
    job: UnsafeCell<Option<Job>>,
    panic: UnsafeCell<Option<Box<dyn Any + Send>>>,
    caller: UnsafeCell<Option<Thread>>,
}

// SAFETY: the UnsafeCells are accessed only under the state protocol above.
unsafe impl Sync for Slot {}

/// A borrowed closure with its lifetime erased; [`Lanes::join`] does not return (or unwind)
/// before the helper has finished with it.
struct Job(*mut (dyn FnMut() + Send + 'static));

// SAFETY: the closure itself is Send; the pointer is only dereferenced by the helper while the
// caller waits.
unsafe impl Send for Job {}

struct Helper {
    slot: Arc<Slot>,
    thread: Option<JoinHandle<()>>,
}

/// See the module docs.
///
/// Not `Sync`: one thread drives it. A `join` inside a `join` runs in turn on its thread.
#[derive(Default)]
pub(crate) struct Lanes {
    helper: Option<Helper>,
    /// Whether [`Lanes::configure`] has run.
    configured: bool,
    /// A `join` is under way (so a nested one runs in turn).
    busy: Cell<bool>,
}

impl std::fmt::Debug for Lanes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lanes").field("lanes", &self.count()).finish()
    }
}

impl Lanes {
    /// One lane, never a helper. A const on purpose: every use is a fresh value with its own
    /// `busy` cell.
    #[allow(clippy::declare_interior_mutable_const)]
    pub const ONE: Lanes = Lanes { helper: None, configured: true, busy: Cell::new(false) };

    /// Starts the helper the first time, when libtorch has ≥ 2 intra-op threads and MKL is
    /// there; otherwise stays one lane. Later calls do nothing.
    pub fn configure(&mut self) {
        if self.configured {
            return;
        }
        self.configured = true;
        if tch::get_num_threads() >= 2 {
            self.start();
        }
    }

    /// Two lanes regardless of libtorch's thread count (tests), where MKL is there.
    #[cfg(test)]
    pub fn started() -> Self {
        let mut lanes = Lanes::ONE;
        lanes.start();
        lanes
    }

    fn start(&mut self) {
        let Some(set_local) = mkl_set_local() else { return };
        let slot = Arc::new(Slot { state: AtomicU8::new(IDLE), job: UnsafeCell::new(None), panic: UnsafeCell::new(None), caller: UnsafeCell::new(None) });
        let s = Arc::clone(&slot);
        let spawned = std::thread::Builder::new().name("learner-lane".into()).spawn(move || {
            set_local_blas_threads(set_local, 1);
            loop {
                let state = wait_until(&s.state, |s| s == READY || s == EXIT, || std::thread::park_timeout(Duration::from_millis(100)));
                if state == EXIT {
                    return;
                }
                // SAFETY: READY: the caller wrote the job and its thread and waits for DONE.
                let job = unsafe { (*s.job.get()).take() }.expect("a job with READY");
                let caller = unsafe { (*s.caller.get()).clone() }.expect("a caller with READY");
                // SAFETY: the closure outlives this call (the caller waits for DONE).
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| unsafe { (*job.0)() }));
                if let Err(payload) = result {
                    // SAFETY: written before DONE is published; read by the caller after.
                    unsafe { *s.panic.get() = Some(payload) };
                }
                s.state.store(DONE, Ordering::Release);
                caller.unpark();
            }
        });
        if let Ok(thread) = spawned {
            self.helper = Some(Helper { slot, thread: Some(thread) });
        }
    }

    /// 2 with a helper thread, else 1.
    pub fn count(&self) -> usize {
        if self.helper.is_some() { 2 } else { 1 }
    }

    /// Makes this thread's BLAS single-threaded until the guard drops, when there are two
    /// lanes (each lane is one thread); does nothing otherwise.
    pub fn single_threaded_blas(&self) -> BlasGuard {
        match (&self.helper, mkl_set_local()) {
            (Some(_), Some(f)) => BlasGuard(Some((f, set_local_blas_threads(f, 1))), std::marker::PhantomData),
            _ => BlasGuard(None, std::marker::PhantomData),
        }
    }

    /// Runs `a` on this thread and `b` on the helper at the same time (both in turn here when
    /// there is one lane); returns when both are done. A panic in either reaches the caller,
    /// after both have finished.
    pub fn join<RA, RB>(&self, a: impl FnOnce() -> RA, b: impl FnOnce() -> RB + Send) -> (RA, RB)
    where
        RB: Send,
    {
        let helper = match &self.helper {
            Some(h) if !self.busy.get() => h,
            _ => {
                let ra = a();
                return (ra, b());
            }
        };
        let slot = &*helper.slot;
        let mut b = Some(b);
        let mut rb = None;
        let mut job = || rb = Some((b.take().expect("run once"))());
        let job: &mut (dyn FnMut() + Send) = &mut job;
        // SAFETY: only the lifetime is erased; `Wait` below keeps this frame (and so the
        // closure and what it borrows) alive until the helper reports DONE, on unwinding too.
        let job: *mut (dyn FnMut() + Send + 'static) = unsafe { std::mem::transmute(job as *mut (dyn FnMut() + Send)) };
        debug_assert_eq!(slot.state.load(Ordering::Acquire), IDLE);
        // SAFETY: IDLE: the helper does not touch the slot.
        unsafe {
            *slot.job.get() = Some(Job(job));
            *slot.caller.get() = Some(std::thread::current());
        }
        slot.state.store(READY, Ordering::Release);
        if let Some(t) = &helper.thread {
            t.thread().unpark();
        }
        /// Waits for the helper; `armed` until `a` has returned, so a drop while armed is
        /// `a` unwinding.
        struct Wait<'a>(&'a Slot, &'a Cell<bool>, bool);
        impl Drop for Wait<'_> {
            fn drop(&mut self) {
                wait_until(&self.0.state, |s| s == DONE, std::thread::park);
                if self.2 {
                    // `a` is unwinding: its panic wins; leave the slot ready for the next join.
                    // SAFETY: DONE: the helper is done with the slot.
                    drop(unsafe { (*self.0.panic.get()).take() });
                    self.0.state.store(IDLE, Ordering::Release);
                }
                self.1.set(false);
            }
        }
        self.busy.set(true);
        let mut wait = Wait(slot, &self.busy, true);
        let ra = a();
        wait.2 = false;
        drop(wait);
        // SAFETY: DONE: the helper has finished and wrote `panic` before publishing it.
        let panic = unsafe { (*slot.panic.get()).take() };
        slot.state.store(IDLE, Ordering::Release);
        if let Some(payload) = panic {
            std::panic::resume_unwind(payload);
        }
        (ra, rb.expect("the helper ran the job"))
    }
}

/// Spins for [`SPIN`], then calls `block` (a park) until `done(state)`; returns that state
/// (acquired).
fn wait_until(state: &AtomicU8, done: impl Fn(u8) -> bool, block: impl Fn()) -> u8 {
    let start = Instant::now();
    loop {
        let s = state.load(Ordering::Acquire);
        if done(s) {
            return s;
        }
        if start.elapsed() < SPIN {
            // The clock is read between bursts of pauses: on a core's other hyperthread the
            // spinning side should take as little as it can from the working one.
            for _ in 0..64 {
                std::hint::spin_loop();
            }
        } else {
            block();
        }
    }
}

impl Drop for Helper {
    fn drop(&mut self) {
        self.slot.state.store(EXIT, Ordering::Release);
        if let Some(t) = self.thread.take() {
            t.thread().unpark();
            let _ = t.join();
        }
    }
}

/// Restores this thread's BLAS thread count on drop ([`Lanes::single_threaded_blas`]).
/// Not `Send`: the setting it restores is its thread's.
pub(crate) struct BlasGuard(Option<(unsafe extern "C" fn(c_int) -> c_int, c_int)>, std::marker::PhantomData<*const ()>);

impl Drop for BlasGuard {
    fn drop(&mut self) {
        if let Some((f, previous)) = self.0 {
            set_local_blas_threads(f, previous);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_lanes() -> Lanes {
        Lanes::started()
    }

    #[test]
    fn join_runs_both_sides_on_two_threads_and_returns_both_results() {
        let lanes = two_lanes();
        if mkl_set_local().is_none() {
            eprintln!("skipped: this libtorch's BLAS is not MKL, so there is one lane");
            return;
        }
        assert_eq!(lanes.count(), 2);
        let mut left = vec![0u64; 1000];
        let mut right = vec![0u64; 1000];
        for round in 0..200u64 {
            let (a, b) = lanes.join(
                || {
                    left.iter_mut().for_each(|v| *v += round);
                    std::thread::current().id()
                },
                || {
                    right.iter_mut().for_each(|v| *v += 2 * round);
                    std::thread::current().id()
                },
            );
            assert_ne!(a, b, "the second closure runs on the helper");
        }
        let sum: u64 = (0..200).sum();
        assert!(left.iter().all(|&v| v == sum) && right.iter().all(|&v| v == 2 * sum));
    }

    #[test]
    fn a_panic_on_the_helper_reaches_the_caller_and_the_lanes_keep_working() {
        let lanes = two_lanes();
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| lanes.join(|| 1, || -> u32 { panic!("boom on the helper") })));
        let payload = caught.expect_err("the helper's panic comes back");
        assert_eq!(payload.downcast_ref::<&str>(), Some(&"boom on the helper"));
        assert_eq!(lanes.join(|| 2, || 3), (2, 3));
    }

    #[test]
    fn a_panic_on_the_caller_waits_for_the_helper_and_leaves_the_lanes_usable() {
        let lanes = two_lanes();
        if lanes.count() < 2 {
            eprintln!("skipped: this libtorch's BLAS is not MKL, so there is one lane");
            return;
        }
        let finished = std::sync::atomic::AtomicBool::new(false);
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            lanes.join(
                || -> u32 { panic!("boom on the caller") },
                || {
                    std::thread::sleep(Duration::from_millis(20));
                    finished.store(true, Ordering::SeqCst);
                },
            )
        }));
        assert!(caught.is_err());
        assert!(finished.load(Ordering::SeqCst), "join unwound only after the helper finished");
        assert_eq!(lanes.join(|| 4, || 5), (4, 5));
    }

    #[test]
    fn one_lane_runs_both_in_turn_on_the_caller() {
        let lanes = Lanes::default();
        assert_eq!(lanes.count(), 1);
        let me = std::thread::current().id();
        let (a, b) = lanes.join(|| std::thread::current().id(), || std::thread::current().id());
        assert_eq!((a, b), (me, me));
    }
}
