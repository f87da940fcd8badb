//! The binaries' allocator: mimalloc, told to keep the pages it frees.
//!
//! A pipeline sample allocates tens of megabytes (clouds, kernel maps, images) and frees
//! them a few milliseconds later, and a training step does the same with hundreds of
//! megabytes of tensors; the next one wants the same again. By default mimalloc (and
//! glibc's malloc for blocks over its mmap threshold) hands freed pages back to the
//! kernel, and the next sample or step faults them in again, each fault zeroing a page
//! (2 MiB with transparent huge pages). With purging off, the process keeps its
//! high-water mark of memory and reuses it (the figures: pipeline/docs/FIELD_NOTES.md,
//! "mimalloc: keeping freed pages").
//!
//! The binaries declare `#[global_allocator] static A: Allocator = Allocator;` and call
//! [`keep_freed_pages`] first thing in `main`; the pipeline also calls
//! [`small_pages_only`].

/// The global allocator of superflow's binaries and benches.
pub use mimalloc::MiMalloc as Allocator;

/// `mi_option_purge_delay` in mimalloc 3's `mi_option_e` (libmimalloc-sys exports no
/// constant for it; `purge_delay_option_is_the_one_we_mean` checks the index).
const PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Tells mimalloc never to return freed pages to the kernel (purge delay −1).
pub fn keep_freed_pages() {
    #[allow(unsafe_code)]
    // SAFETY: `mi_option_set` stores an integer option; it has no preconditions and is
    // thread-safe. The option index is checked by a test against the linked mimalloc.
    unsafe {
        libmimalloc_sys::mi_option_set(PURGE_DELAY, -1);
    }
}

/// Turns transparent huge pages off for this process (`PR_SET_THP_DISABLE`); returns
/// whether the kernel agreed.
///
/// mimalloc advises huge pages for its arenas. With them, a big table's place in the
/// cache follows its virtual address (a 2 MiB page is contiguous in physical memory),
/// and where mimalloc put a sample's neighbour and down-sampling tables decides, for the
/// whole life of the process since freed pages are kept, whether they evict each other:
/// the same build ran 25 % slower in voxels and maps one run in four, and a fault on a
/// fresh huge page zeroes 2 MiB. With 4 KiB pages the kernel scatters physical pages, and
/// every process runs alike at the same mean speed (pipeline/docs/FIELD_NOTES.md,
/// "Transparent huge pages").
pub fn small_pages_only() -> bool {
    #[cfg(target_os = "linux")]
    {
        #[allow(unsafe_code)]
        // SAFETY: `prctl(PR_SET_THP_DISABLE, 1, 0, 0, 0)` sets a flag on this process's
        // memory map; it reads no pointer and has no other effect.
        let rc = unsafe { libc::prctl(libc::PR_SET_THP_DISABLE, 1, 0, 0, 0) };
        rc == 0
    }
    #[cfg(not(target_os = "linux"))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[allow(unsafe_code)]
    fn purge_delay_option_is_the_one_we_mean() {
        // SAFETY: reading an option has no preconditions.
        let default = unsafe { libmimalloc_sys::mi_option_get(PURGE_DELAY) };
        // 1000 ms is the purge delay's default in the linked mimalloc 3 (`options.c`;
        // unless the environment set MIMALLOC_PURGE_DELAY); the next option's is 0.
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
            assert_eq!(default, 1000);
            // SAFETY: as above.
            let numa = unsafe { libmimalloc_sys::mi_option_get(PURGE_DELAY + 1) };
            assert_eq!(numa, 0, "use_numa_nodes follows purge_delay");
        }
        keep_freed_pages();
        // SAFETY: as above.
        assert_eq!(unsafe { libmimalloc_sys::mi_option_get(PURGE_DELAY) }, -1);
    }

    #[test]
    #[cfg(target_os = "linux")]
    #[allow(unsafe_code)]
    fn small_pages_only_turns_huge_pages_off() {
        assert!(small_pages_only());
        // SAFETY: reading the flag has no preconditions.
        let disabled = unsafe { libc::prctl(libc::PR_GET_THP_DISABLE, 0, 0, 0, 0) };
        assert_eq!(disabled, 1);
    }
}
