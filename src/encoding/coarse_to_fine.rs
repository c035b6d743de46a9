//! BARF's coarse-to-fine window over an encoding's frequency bands ([`CoarseToFine`]).

use super::{Encoding, FrequencyEncoding, PointEncoding};
use crate::error::{Error, Result};
use candle_core::Tensor;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// BARF's band weights `w_k(α) = (1 − cos(π·clamp(α − k, 0, 1)))/2` for `k < bands`.
///
/// Each weight is in `[0, 1]`, non-decreasing in `α`, `0` for `α ≤ k`, `1` for
/// `α ≥ k + 1`, `1/2` at `α = k + 1/2`, and continuously differentiable in `α`.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `alpha` if it is NaN (±∞ are allowed: all bands off
/// or on).
pub(crate) fn coarse_to_fine_weights(alpha: f64, bands: usize) -> Result<Vec<f64>> {
    if alpha.is_nan() {
        return Err(Error::invalid("alpha", "a number", "NaN"));
    }
    Ok((0..bands)
        .map(|k| {
            let u = (alpha - k as f64).clamp(0.0, 1.0);
            0.5 * (1.0 - (std::f64::consts::PI * u).cos())
        })
        .collect())
}

/// An encoding whose bands fade in under BARF's coarse-to-fine window (Lin et al. 2021,
/// "BARF: Bundle-Adjusting Neural Radiance Fields"), for fields trained jointly with
/// their cameras.
///
/// The band `k` of an encoding is scaled by
///
/// ```text
/// w_k(α) = (1 − cos(π · clamp(α − k, 0, 1))) / 2,     k = 0, …, B − 1,
/// ```
///
/// so at `α = 0` only the always-on columns reach the network, band `k` fades in while
/// `α` runs from `k` to `k + 1`, and at `α ≥ B` the encoding is the plain one. High
/// frequencies make the photometric loss a function of the camera pose with many local
/// minima; holding them back while the poses move leaves a smooth loss, whose gradient
/// points the poses towards their truth (BARF §3.3).
///
/// The bands of each encoding:
///
/// | encoding | always on | band `k` |
/// |---|---|---|
/// | [`FrequencyEncoding`] | the raw input (if included) | the sines and cosines of frequency `2ᵏ` |
/// | [`HashGrid`](super::HashGrid) | the coarsest level | the features of level `k + 1` |
///
/// The window is a handle shared by every clone of the [`CoarseToFine`] encoding: a
/// network built with one keeps a clone in its configuration, and the training loop moves
/// the window of that network with [`CoarseToFine::set_alpha`] on its own clone.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::encoding::{CoarseToFine, FrequencyEncoding, PointEncoding};
///
/// let window = CoarseToFine::new(PointEncoding::Frequency(FrequencyEncoding::new(3, 4)?))?;
/// let encoding = PointEncoding::CoarseToFine(window.clone()); // give this to a network
/// let x = Tensor::new(&[[0.1f64, -0.2, 0.3]], &Device::Cpu)?;
/// window.set_alpha(0.0)?; // only the raw input reaches the network
/// let y = encoding.forward(&x)?.to_vec2::<f64>()?;
/// assert_eq!(&y[0][..3], &[0.1, -0.2, 0.3]);
/// assert!(y[0][3..].iter().all(|&v| v == 0.0));
/// window.set_alpha(4.0)?; // every band: the plain encoding
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// `γ_α(x) = γ(x) ⊙ w(α)`: the wrapped encoding's output with each column scaled by the
/// weight of its band (1 for the always-on columns). Same shapes and dtypes as the
/// wrapped encoding, differentiable w.r.t. `x` and the wrapped encoding's parameters
/// (`α` is a constant of each call). Once `α` reaches the number of bands the wrapped
/// encoding's output is returned as is, at no cost.
///
/// Clones share `α`.
#[derive(Clone, Debug)]
pub struct CoarseToFine {
    inner: Box<PointEncoding>,
    /// `α` as f64 bits, shared by the clones.
    alpha: Arc<AtomicU64>,
}

impl CoarseToFine {
    /// Wraps `inner` with the window at `α = 0` (only the always-on columns).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `inner` for an encoding without ordered bands
    /// (the identity, random Fourier features) or one already windowed.
    pub fn new(inner: PointEncoding) -> Result<Self> {
        match inner {
            PointEncoding::Frequency(_) | PointEncoding::HashGrid(_) => Ok(Self {
                inner: Box::new(inner),
                alpha: Arc::new(AtomicU64::new(0f64.to_bits())),
            }),
            _ => Err(Error::invalid(
                "inner",
                "a frequency encoding or a hash grid (an encoding with ordered bands)",
                "an encoding without bands",
            )),
        }
    }

    /// The wrapped encoding.
    pub(crate) fn inner(&self) -> &PointEncoding {
        &self.inner
    }

    /// The number of bands `B`: `L` for a frequency encoding of `L` frequencies, the
    /// number of levels less one for a hash grid.
    #[must_use]
    pub fn bands(&self) -> usize {
        match &*self.inner {
            PointEncoding::Frequency(e) => e.n_freqs(),
            PointEncoding::HashGrid(g) => g.config().levels.saturating_sub(1),
            // invariant: `new` admits only the two encodings above.
            _ => 0,
        }
    }

    /// The current `α`.
    #[must_use]
    pub(crate) fn alpha(&self) -> f64 {
        f64::from_bits(self.alpha.load(Ordering::Relaxed))
    }

    /// Sets `α` for this encoding and every clone of it (BARF: `α` rises linearly from 0
    /// to [`CoarseToFine::bands`] over part of the training).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `alpha` if it is NaN.
    pub fn set_alpha(&self, alpha: f64) -> Result<()> {
        if alpha.is_nan() {
            return Err(Error::invalid("alpha", "a number", "NaN"));
        }
        self.alpha.store(alpha.to_bits(), Ordering::Relaxed);
        Ok(())
    }

    /// The weight of each output column at the current `α`: `[E]` values in `[0, 1]`,
    /// laid out as the wrapped encoding's columns.
    #[must_use]
    pub(crate) fn column_weights(&self) -> Vec<f64> {
        let bands = self.bands();
        // invariant: set_alpha refuses NaN, so the weights exist.
        let w = coarse_to_fine_weights(self.alpha(), bands).unwrap_or_else(|_| vec![1.0; bands]);
        match &*self.inner {
            PointEncoding::Frequency(e) => frequency_columns(e, &w),
            PointEncoding::HashGrid(g) => {
                let f = g.config().features;
                std::iter::repeat_n(1.0, f)
                    .chain(w.iter().flat_map(|&wk| std::iter::repeat_n(wk, f)))
                    .collect()
            }
            _ => Vec::new(),
        }
    }

    /// `None` once every band is fully on, else the weights as a `[1, E]` tensor like `y`.
    fn weights_like(&self, y: &Tensor) -> Result<Option<Tensor>> {
        if self.alpha() >= self.bands() as f64 {
            return Ok(None);
        }
        let w = self.column_weights();
        let e = w.len();
        Ok(Some(
            Tensor::from_vec(w, (1, e), y.device())?.to_dtype(y.dtype())?,
        ))
    }
}

impl Encoding for CoarseToFine {
    /// The input dimension `D` of the wrapped encoding.
    fn in_dim(&self) -> usize {
        // invariant: both admitted encodings have a fixed input dimension.
        self.inner.in_dim().unwrap_or(0)
    }

    /// The output dimension `E` of the wrapped encoding.
    fn out_dim(&self) -> usize {
        self.inner.out_dim_for(self.in_dim())
    }

    /// `γ(x) ⊙ w(α)`: `x: [N, D]` → `[N, E]`, differentiable w.r.t. `x` and the wrapped
    /// encoding's parameters.
    ///
    /// # Errors
    /// Those of the wrapped encoding's forward pass.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = self.inner.forward(x)?;
        match self.weights_like(&y)? {
            None => Ok(y),
            Some(w) => Ok(y.broadcast_mul(&w)?),
        }
    }

    /// `γ_α(x)` and its tangents `J_γ(x)·dxₖ ⊙ w(α)`: `x: [N, D]`, `dx: [N, K, D]` →
    /// (`[N, E]`, `[N, K, E]`), differentiable w.r.t. `x` and `dx`.
    ///
    /// # Errors
    /// Those of the wrapped encoding's forward-mode pass.
    fn forward_jvp(&self, x: &Tensor, dx: &Tensor) -> Result<(Tensor, Tensor)> {
        let (y, dy) = self.inner.forward_jvp(x, dx)?;
        match self.weights_like(&y)? {
            None => Ok((y, dy)),
            Some(w) => Ok((y.broadcast_mul(&w)?, dy.broadcast_mul(&w.unsqueeze(0)?)?)),
        }
    }
}

/// The column weights of a frequency encoding from its band weights `w: [L]`: 1 for the
/// input columns, then for each band its `D` sines and `D` cosines at `w_k`.
fn frequency_columns(e: &FrequencyEncoding, w: &[f64]) -> Vec<f64> {
    let d = e.in_dim();
    let head = if e.include_input { d } else { 0 };
    std::iter::repeat_n(1.0, head)
        .chain(w.iter().flat_map(|&wk| std::iter::repeat_n(wk, 2 * d)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frequency(l: usize) -> CoarseToFine {
        CoarseToFine::new(PointEncoding::Frequency(
            FrequencyEncoding::new(3, l).unwrap(),
        ))
        .unwrap()
    }

    #[test]
    fn band_weights_have_their_closed_forms() {
        let w = coarse_to_fine_weights(2.5, 4).unwrap();
        assert_eq!(w[0], 1.0);
        assert_eq!(w[1], 1.0);
        assert!((w[2] - 0.5).abs() < 1e-15);
        assert_eq!(w[3], 0.0);
        assert_eq!(coarse_to_fine_weights(0.0, 3).unwrap(), vec![0.0; 3]);
        assert_eq!(coarse_to_fine_weights(3.0, 3).unwrap(), vec![1.0; 3]);
        assert_eq!(
            coarse_to_fine_weights(f64::INFINITY, 2).unwrap(),
            vec![1.0; 2]
        );
        assert_eq!(
            coarse_to_fine_weights(f64::NEG_INFINITY, 2).unwrap(),
            vec![0.0; 2]
        );
        assert!(coarse_to_fine_weights(0.0, 0).unwrap().is_empty());
        // Non-decreasing in α and in [0, 1].
        let mut last = vec![0.0; 5];
        for i in 0..=600 {
            let w = coarse_to_fine_weights(i as f64 / 100.0 - 0.5, 5).unwrap();
            for (a, b) in w.iter().zip(&last) {
                assert!((0.0..=1.0).contains(a) && a >= b);
            }
            last = w;
        }
    }

    #[test]
    fn nan_alpha_is_refused_naming_alpha() {
        let e = coarse_to_fine_weights(f64::NAN, 3).unwrap_err();
        assert!(e.to_string().contains("alpha"), "{e}");
        let c = frequency(3);
        let e = c.set_alpha(f64::NAN).unwrap_err();
        assert!(e.to_string().contains("alpha"), "{e}");
        assert_eq!(c.alpha(), 0.0, "a refused α leaves the window where it was");
    }

    #[test]
    fn clones_share_the_window() {
        let c = frequency(3);
        let in_config = PointEncoding::CoarseToFine(c.clone());
        c.set_alpha(1.25).unwrap();
        match in_config {
            PointEncoding::CoarseToFine(inner) => assert_eq!(inner.alpha(), 1.25),
            _ => unreachable!(),
        }
    }
}
