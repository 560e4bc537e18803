//! Process-wide tuning of the C allocator for tensor workloads (glibc on Linux; a no-op
//! elsewhere).
//!
//! candle allocates a new buffer for every op's result, many of them megabytes. glibc serves
//! large requests with fresh `mmap`s and gives freed memory back to the kernel, so every op
//! paid page faults to map and zero its output, copy-on-write faults with TLB-flush
//! interrupts to the other core, and `munmap`s: measured on a 2-core machine, a quarter of the
//! NeRF stage's wall time was spent in the kernel (see docs/BENCHMARKS.md, "Allocator"). Here
//! requests up to 32 MiB come from the heap, and freed memory is kept for reuse instead of
//! being trimmed; [`release_free_memory`] hands it back when a long-lived process (the
//! worker) finishes a task.
//!
//! A process that runs stages also keeps every thread on that one heap
//! ([`one_arena_for_all_threads`]). By default glibc gives other threads arenas of their own,
//! made of 64 MiB heaps, and tensors allocated off the main thread (the views a stage renders
//! two at a time) paid the page faults again: rendering fox's views spent 33 s in the kernel
//! instead of 3. A coordinator keeps glibc's per-thread arenas: its many request threads
//! allocate small buffers all the time, and one shared arena cut its GetJob throughput by a
//! quarter to a half.

/// Largest request served from the heap (glibc's maximum for this setting).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD: libc::c_int = 32 << 20;

/// Set to `off` to keep glibc's defaults (for comparisons, or a machine short of memory).
const SWITCH_ENV: &str = "STYLENERF_MALLOC_TUNING";

/// Call once, early in `main`. Does nothing when [`SWITCH_ENV`] is `off`.
pub fn keep_freed_memory() {
    if std::env::var(SWITCH_ENV).is_ok_and(|v| v == "off") {
        return;
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters (under the allocator's own locks); no
    // memory is touched.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        libc::mallopt(libc::M_TRIM_THRESHOLD, libc::c_int::MAX);
        libc::mallopt(libc::M_TOP_PAD, 256 << 20);
    }
}

/// Every thread allocates from the main heap (after [`keep_freed_memory`]). Call once, early
/// in `main`, in processes that run stages. Does nothing when [`SWITCH_ENV`] is `off`.
pub fn one_arena_for_all_threads() {
    if std::env::var(SWITCH_ENV).is_ok_and(|v| v == "off") {
        return;
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: as in `keep_freed_memory`.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

/// Returns the memory freed since the last call to the kernel (after a stage, so an idle
/// worker does not hold a stage's peak).
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases free memory.
    unsafe {
        libc::malloc_trim(0);
    }
}
