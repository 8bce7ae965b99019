//! How the `dnm` process asks glibc's allocator to behave over weeks of running.
//!
//! With glibc's defaults, a DNM that records grows by a few MB an hour without holding more
//! data (its live heap stays flat under a heap profiler): glibc raises its mmap threshold each
//! time a large block is freed, up to 32 MiB, so the recorder's large buffers (zstd contexts,
//! chunks of closed files) come to live inside the heaps among small blocks that stay, and
//! are never given back whole; and with ~60 threads glibc opens up to eight arenas per core,
//! each keeping its own free pages. A fixed threshold of 64 KiB (large blocks mapped and
//! unmapped on their own) and two arenas bound it (BENCHMARKS.md, "Beetle-One for an hour").
//! Whoever sets `glibc.malloc.*` tunables in `GLIBC_TUNABLES` keeps them: nothing is changed.
//!
//! Only a process that records asks for it (`dnm up` and `dnm demo` unless `--no-record`): one
//! that does not stays flat with the defaults, and with a fixed threshold a large sample
//! crossing DNMs cost about 20 % more CPU in the link benchmark (225 KiB: most likely Zenoh's
//! 64 KiB fragment buffers, each a fresh mapping and its page faults).

/// Blocks of this size or more are mapped on their own and given back when freed.
pub const MMAP_THRESHOLD: i32 = 64 * 1024;
/// Arenas glibc may open, whatever the number of threads.
pub const ARENAS: i32 = 2;

/// Applies [`MMAP_THRESHOLD`] and [`ARENAS`], unless `GLIBC_TUNABLES` already sets the
/// allocator's. Call it first thing in `main`, before any thread starts. Returns whether it
/// did.
pub fn bound_for_long_runs() -> bool {
    let tuned_from_outside = std::env::var("GLIBC_TUNABLES")
        .map(|t| t.contains("glibc.malloc."))
        .unwrap_or(false);
    if tuned_from_outside {
        return false;
    }
    // SAFETY: mallopt(3) only changes the allocator's parameters; called before any other
    // thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
            && libc::mallopt(libc::M_ARENA_MAX, ARENAS) == 1
    }
}
