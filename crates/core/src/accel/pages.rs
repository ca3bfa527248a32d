//! Large BVH arrays on transparent huge pages.
//!
//! Incoherent rays touch BVH nodes and triangles all over arrays of many
//! megabytes, and with 4 KiB pages most of those touches also miss the
//! processor's TLB (1,536 entries reach 6 MiB; the room's triangles alone
//! are 11.7 MiB). Asking the kernel for 2 MiB pages over such an array
//! (`madvise(MADV_HUGEPAGE)`, which Linux honours when
//! `/sys/kernel/mm/transparent_hugepage/enabled` is `always` or `madvise`,
//! its usual default) before the array is first written lets one TLB
//! entry cover 512 times as much. Only 2 MiB extents that lie wholly
//! inside the array become huge pages, so no memory is spent beyond the
//! array itself. Elsewhere, or if the kernel declines, nothing changes.

/// Arrays smaller than one huge page hold no whole 2 MiB extent.
const HUGE_PAGE: usize = 2 << 20;

/// A vector of `len` elements from `items`, its memory advised to huge
/// pages before it is written.
pub(super) fn collect<T>(len: usize, items: impl IntoIterator<Item = T>) -> Vec<T> {
    let mut v = Vec::with_capacity(len);
    advise(v.as_mut_ptr() as *mut u8, len * size_of::<T>());
    v.extend(items);
    v
}

fn advise(ptr: *mut u8, bytes: usize) {
    #[cfg(target_os = "linux")]
    if bytes >= HUGE_PAGE {
        // madvise wants a page-aligned start: the range is shrunk to the
        // whole 4 KiB pages inside the allocation.
        const PAGE: usize = 4096;
        let start = (ptr as usize).next_multiple_of(PAGE);
        let end = (ptr as usize + bytes) & !(PAGE - 1);
        if end > start {
            // SAFETY: the range lies inside one live allocation of ours;
            // MADV_HUGEPAGE changes how it is backed, never its contents.
            // A refusal (an old kernel, THP off) is harmless and ignored.
            unsafe {
                libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (ptr, bytes);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contents_are_kept_whatever_the_size() {
        for n in [0usize, 1, 1000, (3 << 20) / 4 + 7] {
            let src: Vec<u32> = (0..n as u32)
                .map(|i| i.wrapping_mul(2_654_435_761))
                .collect();
            assert_eq!(collect(n, src.iter().copied()), src);
        }
    }
}
