//! Large arrays in memory the kernel is asked to back with 2 MiB pages: the BVHs' nodes and
//! triangles ([`Pages`]) and the intersection list's crossings ([`reserve_in_huge_pages`]).
//!
//! A walk of a BVH reads nodes and triangles scattered over megabytes: with 4 KiB pages the
//! addresses of a 200,000-triangle mesh (10 MB of nodes, 8 MB of triangles) span about 4,500
//! pages, more than the processor's translation cache holds, and a read that misses it waits
//! for a walk of the page tables before it can even go to memory. Embree asks for huge pages
//! for its BVHs the same way (`madvise(MADV_HUGEPAGE)`, which transparent huge pages honour in
//! their default `madvise` mode). The allocation starts on a 2 MiB boundary so that every
//! whole 2 MiB of it can be one page; where the kernel declines, the memory is ordinary pages
//! and nothing else changes.

use std::alloc::{Layout, alloc, dealloc, handle_alloc_error};
use std::ops::Deref;
use std::ptr::NonNull;

/// The size of a huge page on x86-64 and most of aarch64's Linux kernels.
const HUGE_PAGE: usize = 2 << 20;

/// An immutable array of `T`, in huge pages when it is large enough to fill one.
pub struct Pages<T: Copy> {
    start: NonNull<T>,
    len: usize,
    /// `None` when nothing was allocated (no items, or items of no size).
    layout: Option<Layout>,
}

// SAFETY: `Pages` owns its items like a `Box<[T]>` and only ever hands out shared references.
unsafe impl<T: Copy + Send> Send for Pages<T> {}
// SAFETY: as above; it is never written after it is made.
unsafe impl<T: Copy + Sync> Sync for Pages<T> {}

impl<T: Copy> Pages<T> {
    /// A copy of `items`.
    #[must_use]
    pub fn new(items: &[T]) -> Self {
        let bytes = size_of_val(items);
        if bytes == 0 {
            return Self {
                start: NonNull::dangling(),
                len: items.len(),
                layout: None,
            };
        }
        let huge = bytes >= HUGE_PAGE;
        let (size, align) = if huge {
            (bytes.next_multiple_of(HUGE_PAGE), HUGE_PAGE)
        } else {
            (bytes, align_of::<T>())
        };
        let layout = Layout::from_size_align(size, align).expect("an array that fits in memory");
        // SAFETY: the layout's size is not zero.
        let raw = unsafe { alloc(layout) };
        let Some(start) = NonNull::new(raw.cast::<T>()) else {
            handle_alloc_error(layout)
        };
        if huge {
            advise_huge_pages(raw, size);
        }
        // SAFETY: the allocation holds `items.len()` values of `T`, suitably aligned (2 MiB is a
        // multiple of any type's alignment), and does not overlap `items`; `T: Copy`.
        unsafe { std::ptr::copy_nonoverlapping(items.as_ptr(), start.as_ptr(), items.len()) };
        Self {
            start,
            len: items.len(),
            layout: Some(layout),
        }
    }
}

/// Reserves room for `additional` more items in `items`, and asks for every whole huge page of
/// the room not yet used to be backed by one: for arrays filled once and read many times, as
/// the intersection list's, whose tens of megabytes then take a page fault per 2 MiB rather
/// than per 4 KiB.
pub fn reserve_in_huge_pages<T>(items: &mut Vec<T>, additional: usize) {
    items.reserve(additional);
    let spare = items.spare_capacity_mut();
    let (from, to) = (
        spare.as_mut_ptr() as usize,
        spare.as_mut_ptr() as usize + size_of_val(spare),
    );
    let (first, last) = (from.next_multiple_of(HUGE_PAGE), to / HUGE_PAGE * HUGE_PAGE);
    if first < last {
        advise_huge_pages(first as *mut u8, last - first);
    }
}

/// Asks the kernel to back `size` bytes from `start` (a multiple of the page size, and within
/// memory this process owns) with huge pages: a hint, ignored where it is not supported.
#[allow(unused_variables)]
fn advise_huge_pages(start: *mut u8, size: usize) {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: the range is within an allocation of this process, 2 MiB aligned (so page
    // aligned); the advice changes how it is backed, never its contents. A failure (a kernel
    // without transparent huge pages) leaves ordinary pages, so its result is not needed.
    unsafe {
        libc::madvise(start.cast(), size, libc::MADV_HUGEPAGE);
    }
}

impl<T: Copy> Deref for Pages<T> {
    type Target = [T];

    fn deref(&self) -> &[T] {
        // SAFETY: `start` holds `len` initialised values (or is dangling for no bytes), owned
        // by `self` and never written after `new`.
        unsafe { std::slice::from_raw_parts(self.start.as_ptr(), self.len) }
    }
}

impl<T: Copy> Drop for Pages<T> {
    fn drop(&mut self) {
        if let Some(layout) = self.layout {
            // SAFETY: allocated in `new` with this layout; `T: Copy` has nothing to drop.
            unsafe { dealloc(self.start.as_ptr().cast(), layout) };
        }
    }
}

impl<T: Copy> From<Vec<T>> for Pages<T> {
    fn from(items: Vec<T>) -> Self {
        Self::new(&items)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn holds_a_copy_of_its_items_at_every_size() {
        for len in [
            0,
            1,
            7,
            HUGE_PAGE / 8 - 1,
            HUGE_PAGE / 8,
            3 * HUGE_PAGE / 8 + 5,
        ] {
            let items: Vec<u64> = (0..len as u64)
                .map(|i| i.wrapping_mul(0x9E37_79B9))
                .collect();
            let pages = Pages::new(&items);
            assert_eq!(&pages[..], &items[..], "{len} items");
            if size_of_val(&items[..]) >= HUGE_PAGE {
                assert_eq!(pages.as_ptr() as usize % HUGE_PAGE, 0, "{len} items");
            }
        }
        let empty: Pages<()> = Pages::new(&[(); 5]);
        assert_eq!(empty.len(), 5);
    }
}
