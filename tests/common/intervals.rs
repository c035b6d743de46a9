//! Sample intervals from per-sample lengths δ: the 0.1 compositing functions took δ and
//! the depths t directly, 0.2 derives both from `Intervals` (δ = ends − starts for unit
//! directions, t = midpoints).

use candle_core::{DType, Device, Tensor};
use neural_fields::volume::{Intervals, Layout, Packed};

/// Contiguous intervals with the given lengths, ray by ray: ray `r` owns the next
/// `counts[r]` entries of `deltas`, and its intervals start at `t = 0` and follow each
/// other (`startsᵢ₊₁ = endsᵢ`). Summed in f64 on the host; because every end is the next
/// start as the same f64, casting to f32 keeps the intervals sorted (rounding can change
/// a δ that follows a much larger one; only the first δ of a ray is exact in any dtype).
///
/// Panics if `counts` does not add up to `deltas.len()`.
pub fn starts_ends(deltas: &[f64], counts: &[usize]) -> (Vec<f64>, Vec<f64>) {
    assert_eq!(
        counts.iter().sum::<usize>(),
        deltas.len(),
        "counts vs deltas"
    );
    let (mut starts, mut ends) = (Vec::with_capacity(deltas.len()), Vec::new());
    let mut i = 0;
    for &c in counts {
        let mut t = 0.0f64;
        for &d in &deltas[i..i + c] {
            starts.push(t);
            t += d;
            ends.push(t);
        }
        i += c;
    }
    (starts, ends)
}

/// Batched `[R, S]` intervals with lengths `deltas` (`R·S` values, row-major), each ray
/// starting at 0, in `dtype` on `dev`.
pub fn batched_from_deltas(
    deltas: &[f64],
    r: usize,
    s: usize,
    dtype: DType,
    dev: &Device,
) -> Intervals {
    let (st, en) = starts_ends(deltas, &vec![s; r]);
    let mk = |v: Vec<f64>| {
        Tensor::from_vec(v, (r, s), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
            .to_device(dev)
            .unwrap()
    };
    Intervals::new(mk(st), mk(en), Layout::Batched).unwrap()
}

/// Packed `[M]` intervals with lengths `deltas` (`M` values, the samples of `packed`), each
/// ray starting at 0, in `dtype` on `packed`'s device.
pub fn packed_from_deltas(deltas: &[f64], packed: &Packed, dtype: DType) -> Intervals {
    let counts: Vec<usize> = packed
        .offsets
        .to_vec1::<u32>()
        .unwrap()
        .windows(2)
        .map(|w| (w[1] - w[0]) as usize)
        .collect();
    let (st, en) = starts_ends(deltas, &counts);
    let dev = packed.offsets.device().clone();
    let m = st.len();
    let mk = |v: Vec<f64>| {
        Tensor::from_vec(v, m, &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
            .to_device(&dev)
            .unwrap()
    };
    Intervals::new(mk(st), mk(en), Layout::Packed(packed.clone())).unwrap()
}
