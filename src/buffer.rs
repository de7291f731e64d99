//! Large sample buffers backed by transparent huge pages where the operating system offers
//! them.
//!
//! A fresh allocation is mapped page by page as it is first written: 4 KiB pages cost one page
//! fault each, and an image stack of 100 MB takes some 25 000 of them (about a tenth of the
//! CPU time of a DiLiGenT run, measured with `perf`). On Linux the buffer is marked
//! `MADV_HUGEPAGE` before it is touched, so that the kernel maps it in 2 MiB pages where it
//! can (with `/sys/kernel/mm/transparent_hugepage/enabled` at `madvise` or `always`; with
//! `never` the advice is ignored). Elsewhere the buffer is an ordinary allocation.

/// Smallest buffer worth advising: below a few huge pages the advice buys nothing.
const MIN_ADVISED_BYTES: usize = 8 << 20;

/// A zeroed `Vec<f32>` of `len` values, mapped with huge pages where possible (see the module
/// documentation). The contents and behaviour are those of `vec![0.0; len]`.
pub(crate) fn zeroed_f32(len: usize) -> Vec<f32> {
    let v = vec![0f32; len];
    advise_huge_pages(&v);
    v
}

/// [`zeroed_f32`] for `f64` (e.g. the values of a sparse factor).
pub(crate) fn zeroed_f64(len: usize) -> Vec<f64> {
    let v = vec![0f64; len];
    advise_huge_pages(&v);
    v
}

#[cfg(target_os = "linux")]
fn advise_huge_pages<T>(v: &[T]) {
    const PAGE: usize = 4096;
    let bytes = std::mem::size_of_val(v);
    if bytes < MIN_ADVISED_BYTES {
        return;
    }
    let start = v.as_ptr() as usize;
    let aligned = start.next_multiple_of(PAGE);
    let end = start + bytes;
    if aligned >= end {
        return;
    }
    // SAFETY: [aligned, end) lies inside the allocation owned by `v`, and MADV_HUGEPAGE only
    // changes how the kernel backs those pages, never their contents. A failure (EINVAL
    // where huge pages are not supported) leaves the buffer as it was, so it is ignored.
    #[allow(unsafe_code)]
    unsafe {
        libc::madvise(
            aligned as *mut libc::c_void,
            end - aligned,
            libc::MADV_HUGEPAGE,
        );
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge_pages<T>(_: &[T]) {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zeroed_buffers_are_zero_and_writable() {
        for len in [0, 1, 1000, (MIN_ADVISED_BYTES / 4) + 12_345] {
            let mut v = zeroed_f32(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|x| *x == 0.0));
            for (i, x) in v.iter_mut().enumerate() {
                *x = i as f32;
            }
            assert!(v.iter().enumerate().all(|(i, x)| *x == i as f32));
            let mut d = zeroed_f64(len);
            assert_eq!(d.len(), len);
            assert!(d.iter().all(|x| *x == 0.0));
            d.iter_mut().for_each(|x| *x = -1.5);
            assert!(d.iter().all(|x| *x == -1.5));
        }
    }
}
