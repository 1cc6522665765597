//! glibc's allocator, told to keep freed memory for reuse (Linux with glibc only).
//!
//! libtorch's CPU allocator hands every tensor's buffer straight to `malloc`/`free`. An update
//! at the paper's sizes allocates and frees a few hundred tensors, many of them above glibc's
//! mmap threshold (128 KiB by default; a `[2, 128, 256]` f32 activation of the twin critics is
//! 256 KiB) or large enough to let `free` trim the heap's top. Each such buffer then comes
//! fresh from the kernel on the next update, and every page of it is a page fault (measured:
//! about 400 faults per SAC update, 10–20 % of its CPU time). [`retain_freed_memory`] raises the
//! mmap threshold to glibc's maximum (32 MiB on 64-bit) and disables trimming, so these
//! buffers are recycled inside the heap: the process keeps its peak heap (tens of MiB for a
//! learner) instead of returning it to the kernel between updates. It changes no value
//! computed. This is what `MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=…` would do,
//! set from inside so that every learner gets it; on other platforms it does nothing.

/// Applies the settings of the module docs, once per process. Further calls do nothing.
pub(crate) fn retain_freed_memory() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(apply);
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn apply() {
    // <malloc.h>
    const M_TRIM_THRESHOLD: i32 = -1;
    const M_MMAP_THRESHOLD: i32 = -3;
    /// glibc's DEFAULT_MMAP_THRESHOLD_MAX on 64-bit targets; larger values are refused.
    const MMAP_THRESHOLD_MAX: i32 = 32 * 1024 * 1024;
    unsafe extern "C" {
        fn mallopt(param: i32, value: i32) -> i32;
    }
    // SAFETY: mallopt only changes allocator tunables; glibc takes its own lock. A refusal
    // (return 0) leaves glibc's defaults, which are correct, only slower.
    unsafe {
        mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX);
        mallopt(M_TRIM_THRESHOLD, i32::MAX);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn apply() {}
