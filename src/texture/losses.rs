//! Losses on rendered colours beyond the per-pixel photometric loss
//! ([`crate::dvr::photometric_loss`]).

use crate::error::{check_float, check_same, check_same_shape, check_shape, Dim, Error, Result};
use candle_core::Tensor;

/// DVR's image-gradient loss on `k × k` patches (DVR's multi-view setting: 2 × 2, weight
/// 1): the first differences of each patch's top-left pixel to its right and lower
/// neighbours, predicted against true,
///
/// ```text
/// Δx(c) = c[0, 0] − c[0, 1],   Δy(c) = c[0, 0] − c[1, 0],
/// ℓₚ = Σ_ch |Δx(pred) − Δx(target)| + |Δy(pred) − Δy(target)|,
/// L = Σₚ mₚ ℓₚ / max(Σₚ mₚ, 1),
/// ```
///
/// where `mₚ = 1` when every pixel of patch `p` is valid. It asks the rendered colours to
/// change across the surface as the image does, which a per-pixel loss does not see at
/// texture edges.
///
/// * `pred, target: [P·k², C]`, f32 or f64, ordered patch by patch and row-major inside a
///   patch (the order of [`crate::data::RaySampler::patches`]: row `p·k² + i·k + j` is
///   pixel `(j, i)` of patch `p`);
/// * `valid: [P·k²]` of any dtype (nonzero = valid: the ray hit the surface and lies in
///   the object mask), or `None` for all valid;
/// * `k ≥ 2`.
///
/// Returns a scalar in `pred`'s dtype, differentiable w.r.t. `pred` and `target`
/// (the absolute value's derivative at 0 is candle's, 0). 0 when no patch is valid.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::texture::image_gradient_loss;
///
/// // One 2×2 grey patch; the prediction is flat where the target has an edge.
/// let target = Tensor::new(&[[1.0f64], [0.0], [1.0], [1.0]], &Device::Cpu)?;
/// let pred = Tensor::new(&[[0.5f64], [0.5], [0.5], [0.5]], &Device::Cpu)?;
/// let loss = image_gradient_loss(&pred, &target, None, 2)?.to_scalar::<f64>()?;
/// assert_eq!(loss, 1.0); // |0 − (1 − 0)| + |0 − (1 − 1)|
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// `pred` not a float `[N, C]`; `target` of another shape, dtype or device; `k < 2` or
/// `N` not a multiple of `k²` (naming `k`); `valid` not `[N]` on the same device.
pub fn image_gradient_loss(
    pred: &Tensor,
    target: &Tensor,
    valid: Option<&Tensor>,
    k: usize,
) -> Result<Tensor> {
    check_float(pred, "pred")?;
    let dims = check_shape(pred, "pred", &[Dim::Any("N"), Dim::Any("C")])?;
    check_same(target, "target", pred, "pred")?;
    check_same_shape(target, "target", pred, "pred")?;
    let (n, c) = (dims[0], dims[1]);
    if k < 2 {
        return Err(Error::invalid(
            "k",
            "a patch side of at least 2",
            format!("{k}"),
        ));
    }
    let kk = k * k;
    if n % kk != 0 {
        return Err(Error::invalid(
            "k",
            format!("patches of {kk} pixels tiling the {n} rows of pred"),
            format!("k = {k}"),
        ));
    }
    let p = n / kk;
    if p == 0 {
        return Ok(Tensor::zeros((), pred.dtype(), pred.device())?);
    }
    let patch_valid = match valid {
        None => Tensor::ones(p, pred.dtype(), pred.device())?,
        Some(m) => {
            check_shape(m, "valid", &[Dim::Is(n)])?;
            if !m.device().same_device(pred.device()) {
                return Err(Error::invalid(
                    "valid",
                    "the device of pred",
                    format!("{:?}", m.device()),
                ));
            }
            // A patch counts when all its k² pixels are valid.
            m.to_dtype(candle_core::DType::F64)?
                .ne(0.0)?
                .to_dtype(pred.dtype())?
                .reshape((p, kk))?
                .min(1)?
        }
    };
    let diffs = |t: &Tensor| -> Result<(Tensor, Tensor)> {
        let t = t.reshape((p, kk, c))?;
        let corner = t.narrow(1, 0, 1)?;
        Ok((
            (&corner - crate::narrow::narrow(&t, 1, 1, 1)?)?.squeeze(1)?,
            (&corner - crate::narrow::narrow(&t, 1, k, 1)?)?.squeeze(1)?,
        ))
    };
    let (dxp, dyp) = diffs(pred)?;
    let (dxt, dyt) = diffs(target)?;
    let per = ((dxp - dxt)?.abs()? + (dyp - dyt)?.abs()?)?.sum(1)?;
    let count = patch_valid.sum_all()?.clamp(1.0, f64::INFINITY)?;
    Ok((per * &patch_valid)?.sum_all()?.div(&count)?)
}
