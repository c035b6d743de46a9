//! An AVX-512 f32 matrix product for the fused MLP's tile shapes.
//!
//! `C[m×n] = (acc ? C : 0) + scale · A[m×k] · B[k×n]` with `B` and `C` row-major (unit
//! column stride) and `A` at any strides. The micro-kernel keeps a 6 × 64 block of `C` in
//! 24 zmm registers; each step of the inner product loads one 64-wide row of `B` (masked
//! at the right edge) and broadcasts six entries of `A`, so the loop issues 24 FMAs per 4
//! loads and runs at the FMA units' rate. A panel narrower than 64 columns (the last one
//! of `n = 65`, the 3 colours of a NeRF head, 91 = 64 + 27) runs a kernel with only as
//! many registers per row as it has 16-column groups, so that no FMA is spent on masked
//! lanes: in the NeRF training step such lanes were a sixth of the products' work. Stable Rust has the AVX-512 intrinsics (1.89)
//! but the `gemm` crate enables its AVX-512 kernels only on nightly; on this shape
//! (k ≤ 128 and n ≤ 128) this kernel is about twice as fast as gemm's AVX2 one.

#![allow(unsafe_code)]

use std::arch::x86_64::*;

/// Rows of `C` per micro-kernel call.
const MR: usize = 6;
/// zmm registers per row of `C` (64 f32 columns).
const NR: usize = 4;

/// Whether the CPU runs [`matmul_f32`].
pub(crate) fn available() -> bool {
    use std::sync::OnceLock;
    static HAS: OnceLock<bool> = OnceLock::new();
    *HAS.get_or_init(|| is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("fma"))
}

/// The lane mask of columns `j..min(j + 16, n)`.
#[inline(always)]
fn mask(j: usize, n: usize) -> __mmask16 {
    let left = n.saturating_sub(j).min(16);
    ((1u32 << left) - 1) as __mmask16
}

/// One `R × (≤ 16·Q)` block of `C` at rows `i`, columns `j..j + 16·Q` (masked beyond `n`).
///
/// # Safety
/// AVX-512F and FMA are available; every accessed element lies inside the matrices
/// (`i + R ≤ m`, columns masked at `n`, `k` rows of `B`); `Q ≤ NR`.
#[inline(always)]
// Register blocks are indexed, as in any micro-kernel.
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
unsafe fn block<const R: usize, const Q: usize>(
    (n, k): (usize, usize),
    (i, j): (usize, usize),
    c: *mut f32,
    ldc: usize,
    acc: bool,
    a: *const f32,
    (a_rs, a_cs): (usize, usize),
    b: *const f32,
    ldb: usize,
    scale: f32,
) {
    let mut masks = [0; Q];
    for (q, m) in masks.iter_mut().enumerate() {
        *m = mask(j + 16 * q, n);
    }
    let mut sum = [[_mm512_setzero_ps(); Q]; R];
    for p in 0..k {
        let brow = b.add(p * ldb + j);
        let mut bv = [_mm512_setzero_ps(); Q];
        for q in 0..Q {
            if masks[q] != 0 {
                bv[q] = _mm512_maskz_loadu_ps(masks[q], brow.add(16 * q));
            }
        }
        for r in 0..R {
            let av = _mm512_set1_ps(*a.add((i + r) * a_rs + p * a_cs));
            for q in 0..Q {
                sum[r][q] = _mm512_fmadd_ps(av, bv[q], sum[r][q]);
            }
        }
    }
    let s = _mm512_set1_ps(scale);
    for r in 0..R {
        let crow = c.add((i + r) * ldc + j);
        for q in 0..Q {
            if masks[q] == 0 {
                continue;
            }
            let ptr = crow.add(16 * q);
            let v = if acc {
                _mm512_fmadd_ps(s, sum[r][q], _mm512_maskz_loadu_ps(masks[q], ptr))
            } else {
                _mm512_mul_ps(s, sum[r][q])
            };
            _mm512_mask_storeu_ps(ptr, masks[q], v);
        }
    }
}

/// `C = (acc ? C : 0) + scale · A · B`; see the module documentation.
///
/// # Safety
/// [`available`] returned true; `C` has `m` rows of stride `ldc ≥ n`, `B` has `k` rows of
/// stride `ldb ≥ n`, and `A`'s element `(r, p)` at `r·a_rs + p·a_cs` exists for `r < m`,
/// `p < k`.
#[target_feature(enable = "avx512f,fma")]
#[allow(clippy::too_many_arguments)]
pub(crate) unsafe fn matmul_f32(
    (m, n, k): (usize, usize, usize),
    c: *mut f32,
    ldc: usize,
    acc: bool,
    a: *const f32,
    a_strides: (usize, usize),
    b: *const f32,
    ldb: usize,
    scale: f32,
) {
    for j in (0..n).step_by(16 * NR) {
        // 16-column groups in this panel (1 to NR).
        match (n - j).min(16 * NR).div_ceil(16) {
            1 => panel::<1>((m, n, k), j, c, ldc, acc, a, a_strides, b, ldb, scale),
            2 => panel::<2>((m, n, k), j, c, ldc, acc, a, a_strides, b, ldb, scale),
            3 => panel::<3>((m, n, k), j, c, ldc, acc, a, a_strides, b, ldb, scale),
            _ => panel::<NR>((m, n, k), j, c, ldc, acc, a, a_strides, b, ldb, scale),
        }
    }
}

/// Every row block of the panel of `Q` column groups at column `j`.
///
/// # Safety
/// As [`matmul_f32`]'s, with `j < n`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn panel<const Q: usize>(
    (m, n, k): (usize, usize, usize),
    j: usize,
    c: *mut f32,
    ldc: usize,
    acc: bool,
    a: *const f32,
    a_strides: (usize, usize),
    b: *const f32,
    ldb: usize,
    scale: f32,
) {
    let mut i = 0;
    while i + MR <= m {
        block::<MR, Q>((n, k), (i, j), c, ldc, acc, a, a_strides, b, ldb, scale);
        i += MR;
    }
    match m - i {
        0 => {}
        1 => block::<1, Q>((n, k), (i, j), c, ldc, acc, a, a_strides, b, ldb, scale),
        2 => block::<2, Q>((n, k), (i, j), c, ldc, acc, a, a_strides, b, ldb, scale),
        3 => block::<3, Q>((n, k), (i, j), c, ldc, acc, a, a_strides, b, ldb, scale),
        4 => block::<4, Q>((n, k), (i, j), c, ldc, acc, a, a_strides, b, ldb, scale),
        _ => block::<5, Q>((n, k), (i, j), c, ldc, acc, a, a_strides, b, ldb, scale),
    }
}

#[cfg(test)]
mod tests {
    use super::{available, matmul_f32};

    /// Against a naive triple loop in f64, over shapes with row and column tails, both
    /// `A` layouts, accumulation and scaling.
    #[test]
    fn avx512_matmul_equals_a_naive_product() {
        if !available() {
            return;
        }
        let mut seed = 7u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32 / (1u64 << 24) as f32) - 0.5
        };
        for &(m, n, k) in &[
            (1, 1, 1),
            (6, 64, 64),
            (7, 63, 5),
            (128, 65, 64),
            (13, 3, 91),
            (64, 91, 128),
            (5, 130, 2),
            (9, 17, 33),
            (11, 40, 7),
            (6, 129, 3),
            (31, 5, 17),
        ] {
            for transposed_a in [false, true] {
                for acc in [false, true] {
                    let a: Vec<f32> = (0..m * k).map(|_| next()).collect();
                    let b: Vec<f32> = (0..k * n).map(|_| next()).collect();
                    let c0: Vec<f32> = (0..m * n).map(|_| next()).collect();
                    let strides = if transposed_a { (1, m) } else { (k, 1) };
                    let mut c = c0.clone();
                    // SAFETY: the buffers have exactly the shapes passed.
                    unsafe {
                        matmul_f32(
                            (m, n, k),
                            c.as_mut_ptr(),
                            n,
                            acc,
                            a.as_ptr(),
                            strides,
                            b.as_ptr(),
                            n,
                            0.7,
                        );
                    }
                    for i in 0..m {
                        for j in 0..n {
                            let mut s = 0f64;
                            for p in 0..k {
                                s += f64::from(a[i * strides.0 + p * strides.1])
                                    * f64::from(b[p * n + j]);
                            }
                            let want = if acc { f64::from(c0[i * n + j]) } else { 0.0 } + 0.7 * s;
                            let got = f64::from(c[i * n + j]);
                            assert!(
                                (got - want).abs() <= 1e-5 * (1.0 + want.abs()),
                                "{m}x{n}x{k} ({i},{j}): {got} vs {want}"
                            );
                        }
                    }
                }
            }
        }
    }
}
