//! The size check every caller-chosen allocation runs first (crate-private).
//!
//! A count, resolution or table size that a caller passes becomes a buffer length
//! somewhere: before anything of that length is allocated, [`check_bytes`] multiplies the
//! dimensions with checked arithmetic and refuses a request past [`MAX_ALLOC_BYTES`] with
//! an [`Error::InvalidArgument`] naming the argument, the figure and the limit. Without
//! it, a sample count above 2⁶³ panics on overflow and one of 2⁴⁰ aborts the process in
//! the allocator, neither of which a caller can catch.

use crate::error::{Error, Result};

/// The most bytes one caller-sized request may ask for: 2³³ (8 GiB).
pub(crate) const MAX_ALLOC_BYTES: u64 = 1 << 33;

/// Checks that a buffer of `dims` elements of `elem_bytes` bytes each stays within
/// [`MAX_ALLOC_BYTES`]; returns the number of elements (the product of `dims`).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg`, with the dimensions, the bytes (or "overflows
/// 64 bits") and the limit.
pub(crate) fn check_bytes(arg: &'static str, dims: &[usize], elem_bytes: usize) -> Result<usize> {
    let elems = dims
        .iter()
        .try_fold(1u64, |acc, &d| acc.checked_mul(d as u64));
    let bytes = elems.and_then(|e| e.checked_mul(elem_bytes as u64));
    match (elems, bytes) {
        (Some(e), Some(b)) if b <= MAX_ALLOC_BYTES && usize::try_from(e).is_ok() => Ok(e as usize),
        _ => Err(Error::invalid(
            arg,
            format!("a size within the allocation limit of {MAX_ALLOC_BYTES} bytes (8 GiB)"),
            match bytes {
                Some(b) => format!("{dims:?} × {elem_bytes} B = {b} bytes"),
                None => format!("{dims:?} × {elem_bytes} B, which overflows 64 bits"),
            },
        )),
    }
}

/// Checks a network of `count` layers of `params` parameters each (and a layer's
/// bookkeeping, counted as 64 more) of `elem_bytes` bytes against [`MAX_ALLOC_BYTES`]
/// before its layers are built, naming `arg` (the layer or block count).
///
/// # Errors
/// Those of [`check_bytes`].
pub(crate) fn check_layers(
    arg: &'static str,
    count: usize,
    params: usize,
    elem_bytes: usize,
) -> Result<()> {
    check_bytes(arg, &[count, params.saturating_add(64)], elem_bytes).map(|_| ())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn products_past_the_limit_or_overflowing_are_refused_with_the_figures() {
        assert_eq!(check_bytes("n", &[1 << 20, 3], 8).unwrap(), 3 << 20);
        assert_eq!(check_bytes("n", &[0, usize::MAX], 8).unwrap(), 0);
        assert_eq!(check_bytes("n", &[1 << 30], 8).unwrap(), 1 << 30);
        let e = check_bytes("n", &[(1 << 30) + 1], 8)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("n: ") && e.contains("8589934600 bytes"),
            "{e}"
        );
        assert!(e.contains("8589934592"), "{e}");
        let e = check_bytes("n", &[usize::MAX, 2], 1)
            .unwrap_err()
            .to_string();
        assert!(e.contains("overflows"), "{e}");
    }
}
