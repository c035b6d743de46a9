//! A small seeded random number generator for reproducible sampling.
//!
//! candle's CPU device cannot be seeded, so everything in this crate that draws random
//! numbers (Gaussian Fourier features, pixel subsets, jittered samples) takes a `u64`
//! seed and draws from [`SplitMix64`] on the host, then moves the numbers to the
//! device of the computation. Same seed, same numbers, on every machine.

use candle_core::{DType, Device, Tensor};

/// SplitMix64 (Steele, Lea & Flood 2014): a 64-bit generator with good statistical
/// quality for sampling, one addition and three xor-shift-multiplies per number.
#[derive(Clone, Debug)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// A generator started from `seed`.
    #[must_use]
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A uniform number in `[0, 1)` with 53 random bits.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// A uniform integer in `0..n` (`n > 0`), by Lemire's multiply-shift.
    pub fn below(&mut self, n: u64) -> u64 {
        ((u128::from(self.next_u64()) * u128::from(n)) >> 64) as u64
    }

    /// A standard normal number, by the Box–Muller transform.
    pub fn normal(&mut self) -> f64 {
        // 1 − u ∈ (0, 1], so the logarithm is finite.
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// A tensor of i.i.d. `N(mean, std²)` numbers with the given shape, dtype and device.
    ///
    /// # Errors
    /// A shape whose values (8 bytes each) pass the allocation limit of 2³³ bytes (8 GiB),
    /// refused before anything is allocated; candle's (e.g. an unsupported dtype).
    pub(crate) fn normal_tensor(
        &mut self,
        shape: &[usize],
        mean: f64,
        std: f64,
        dtype: DType,
        device: &Device,
    ) -> candle_core::Result<Tensor> {
        let n = checked_len(shape)?;
        let v: Vec<f64> = (0..n).map(|_| mean + std * self.normal()).collect();
        Tensor::from_vec(v, shape, &Device::Cpu)?
            .to_dtype(dtype)?
            .to_device(device)
    }

    /// A tensor of i.i.d. uniform numbers in `[lo, hi)` with the given shape, dtype and
    /// device.
    ///
    /// # Errors
    /// A shape whose values (8 bytes each) pass the allocation limit of 2³³ bytes (8 GiB),
    /// refused before anything is allocated (a candle error naming `shape`); candle's.
    pub fn uniform_tensor(
        &mut self,
        shape: &[usize],
        lo: f64,
        hi: f64,
        dtype: DType,
        device: &Device,
    ) -> candle_core::Result<Tensor> {
        let n = checked_len(shape)?;
        let v: Vec<f64> = (0..n).map(|_| lo + (hi - lo) * self.uniform()).collect();
        Tensor::from_vec(v, shape, &Device::Cpu)?
            .to_dtype(dtype)?
            .to_device(device)
    }
}

/// The element count of `shape`, checked against the allocation limit (host f64 values).
fn checked_len(shape: &[usize]) -> candle_core::Result<usize> {
    crate::limits::check_bytes("shape", shape, 8)
        .map_err(|e| candle_core::Error::Msg(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_stream_and_sane_moments() {
        let mut a = SplitMix64::new(7);
        let mut b = SplitMix64::new(7);
        assert_eq!(a.next_u64(), b.next_u64());
        let n = 200_000;
        let xs: Vec<f64> = (0..n).map(|_| a.normal()).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(
            mean.abs() < 0.01 && (var - 1.0).abs() < 0.02,
            "{mean} {var}"
        );
        assert!((0..1000).all(|_| a.below(5) < 5));
    }

    /// Normal tensors stay finite for means and deviations from 1e-30 to 1e30, in f32 and
    /// f64, with the shape, dtype and device asked for.
    #[test]
    fn normal_tensors_stay_finite_at_extreme_parameters() -> candle_core::Result<()> {
        for dtype in [DType::F32, DType::F64] {
            for (mean, std) in [(0.0f64, 1e-30f64), (-1e30, 1e30), (1e10, 1e10)] {
                let t = SplitMix64::new(1).normal_tensor(&[64], mean, std, dtype, &Device::Cpu)?;
                assert_eq!((t.dims(), t.dtype()), (&[64][..], dtype));
                let v = t.to_dtype(DType::F64)?.to_vec1::<f64>()?;
                assert!(v.iter().all(|x| x.is_finite()), "{dtype:?}, {mean}, {std}");
            }
        }
        Ok(())
    }
}
