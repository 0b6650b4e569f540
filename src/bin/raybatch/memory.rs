//! How the command takes memory from the system. Page faults are a large share of a job
//! (a full-HD job of a million-triangle mesh touches about 200 MB), so freed memory is
//! kept for reuse.
//!
//! Pages stay the kernel's default size. Asking for transparent huge pages on large blocks
//! (`madvise(MADV_HUGEPAGE)`, tried in fedd46c) halved the faults, but on a virtual
//! machine that hands freed memory back to its host, a huge page touched first after a
//! pause costs the host a fresh 2 MB: the full-HD torus job took 0.58 instead of 0.49 s
//! when started a second after the previous process, for at most a per cent in
//! back-to-back runs (DEVELOPERS.md, "Pages of the default size").

/// Asks glibc's allocator to serve every block from its heaps and keep what is freed,
/// instead of mapping fresh pages for each large block and returning them at once: a
/// job's phases (a mesh's read buffers, the tree build's temporaries, the image) and the
/// jobs of a batch then reuse memory rather than fault it in anew. Measured: a full-HD job
/// of a 124k-triangle mesh went from 19.7k to 12.3k faults (build 45 -> 35 ms, load 23 ->
/// 18 ms) with large blocks on the heap, and the million-triangle torus's build in
/// `raybatch bench` from 0.25 to 0.17 s once no block was mapped on its own
/// (BENCHMARKS.md).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn keep_freed_memory() {
    // SAFETY: `mallopt` only sets allocator parameters; no other thread exists yet. A
    // refused setting (return value 0) leaves glibc's default, which is also correct.
    // Without mappings of its own a block too large for a thread's heap is served by the
    // main heap, and glibc still maps memory when that heap cannot grow.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, libc::c_int::MAX);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn keep_freed_memory() {}
