//! How the command takes memory from the system. Page faults are a large share of a job
//! (a full-HD job of a million-triangle mesh touches about 220 MB), so freed memory is
//! kept for reuse and large blocks are backed by huge pages where the kernel offers them.

use std::alloc::{GlobalAlloc, Layout, System};

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

/// The system allocator, which asks the kernel (`madvise(MADV_HUGEPAGE)`) to back the
/// whole 2 MB pages inside each block of [`HUGE_BLOCK`] bytes or more with huge pages
/// (transparent huge pages, where enabled): one fault then maps 2 MB instead of 4 kB, and
/// the process exits sooner, with fewer pages to unmap. Pages already touched keep their
/// size; the advice is only a hint, and a refusal changes nothing. Measured: the
/// full-HD torus job faults 17.7k pages instead of 60.7k, and its whole process took 0.246
/// instead of 0.280 s (median of 11 alternating runs; BENCHMARKS.md).
pub struct HugePages;

/// Blocks from this size on are advised (smaller ones hold few whole huge pages).
const HUGE_BLOCK: usize = 4 << 20;
/// The size of a huge page on x86-64.
const HUGE_PAGE: usize = 2 << 20;

#[global_allocator]
static ALLOCATOR: HugePages = HugePages;

impl HugePages {
    fn advise(block: *mut u8, size: usize) {
        #[cfg(target_os = "linux")]
        if let Some((start, end)) = whole_huge_pages(block as usize, size) {
            // SAFETY: the range lies within a block this allocator just handed out;
            // `MADV_HUGEPAGE` changes no contents.
            unsafe { libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE) };
        }
    }
}

/// The whole huge pages inside the block of `size` bytes at address `block`, as a range of
/// addresses; `None` for a block under [`HUGE_BLOCK`] or at address 0 (a failed
/// allocation).
#[cfg_attr(not(target_os = "linux"), allow(dead_code))]
fn whole_huge_pages(block: usize, size: usize) -> Option<(usize, usize)> {
    if size < HUGE_BLOCK || block == 0 {
        return None;
    }
    let start = block.next_multiple_of(HUGE_PAGE);
    let end = (block + size) / HUGE_PAGE * HUGE_PAGE;
    Some((start, end))
}

// SAFETY: every call is the system allocator's, with the same arguments; `advise` only
// gives the kernel a hint about pages of the block returned.
unsafe impl GlobalAlloc for HugePages {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as required of the caller.
        let block = unsafe { System.alloc(layout) };
        Self::advise(block, layout.size());
        block
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as required of the caller.
        let block = unsafe { System.alloc_zeroed(layout) };
        Self::advise(block, layout.size());
        block
    }

    unsafe fn realloc(&self, block: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as required of the caller.
        let block = unsafe { System.realloc(block, layout, new_size) };
        Self::advise(block, new_size);
        block
    }

    unsafe fn dealloc(&self, block: *mut u8, layout: Layout) {
        // SAFETY: as required of the caller.
        unsafe { System.dealloc(block, layout) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_whole_huge_pages_inside_a_large_block_are_advised() {
        const MB: usize = 1 << 20;
        // (address, size) -> expected range.
        let cases = [
            ((0, 64 * MB), None),                                  // failed allocation
            ((6 * MB, HUGE_BLOCK - 1), None),                      // too small
            ((6 * MB, HUGE_BLOCK), Some((6 * MB, 10 * MB))),       // aligned both ends
            ((6 * MB + 16, HUGE_BLOCK), Some((8 * MB, 10 * MB))),  // one page inside
            ((5 * MB, 5 * MB), Some((6 * MB, 10 * MB))),           // starts mid-page
            ((6 * MB + 16, 6 * MB - 32), Some((8 * MB, 10 * MB))), // ends mid-page
        ];
        for ((block, size), expected) in cases {
            let range = whole_huge_pages(block, size);
            assert_eq!(range, expected, "block at {block:#x} of {size} bytes");
            if let Some((start, end)) = range {
                assert!(block <= start && end <= block + size && start < end);
                assert!(start % HUGE_PAGE == 0 && end % HUGE_PAGE == 0);
            }
        }
    }
}
