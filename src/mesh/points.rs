//! Host points `[N][3]` (`f64`): their validation, shared by [`Mesh`](super::Mesh) and
//! [`PointCloud`](super::PointCloud), and their conversion to and from candle tensors.

use crate::error::{Error, Result};
use candle_core::{DType, Device, Tensor};

/// Checks positions and their optional normals and colours, naming `arg` and each
/// element `noun i`: every coordinate and normal component finite, one normal and one
/// colour per position, colour components in `[0, 1]`.
pub(crate) fn check_points(
    arg: &'static str,
    [noun, nouns]: [&str; 2],
    points: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    colors: Option<&[[f64; 3]]>,
) -> Result<()> {
    let n = points.len();
    if let Some(i) = points.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
        return Err(Error::invalid(
            arg,
            format!("finite {noun} coordinates"),
            format!("{noun} {i} = {:?} (NaN or infinite)", points[i]),
        ));
    }
    if let Some(nr) = normals {
        if nr.len() != n {
            return Err(Error::invalid(
                arg,
                format!("one normal per {noun}"),
                format!("{} normals for {n} {nouns}", nr.len()),
            ));
        }
        if let Some(i) = nr.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
            return Err(Error::invalid(
                arg,
                "finite normals",
                format!("normal {i} = {:?}", nr[i]),
            ));
        }
    }
    if let Some(col) = colors {
        if col.len() != n {
            return Err(Error::invalid(
                arg,
                format!("one entry of colors per {noun}"),
                format!("{} colors for {n} {nouns}", col.len()),
            ));
        }
        let in_unit = |c: &f64| (0.0..=1.0).contains(c); // false for NaN
        if let Some(i) = col.iter().position(|v| !v.iter().all(in_unit)) {
            return Err(Error::invalid(
                arg,
                "colors with finite components in [0, 1]",
                format!("colors[{i}] = {:?}", col[i]),
            ));
        }
    }
    Ok(())
}

/// Host points `points: [N][3]` as a `[N, 3]` tensor of `dtype` on `device`: each
/// coordinate rounded to `dtype` (f64 exactly; f32 to nearest). The tensor is a leaf:
/// host points carry no gradient. The inverse is [`points_from_tensor`].
///
/// ```
/// use candle_core::{DType, Device};
/// use neural_fields::mesh::{points_from_tensor, points_to_tensor};
///
/// let points = [[0.5, -1.0, 2.0], [0.0, 0.25, 1e3]];
/// let t = points_to_tensor(&points, &Device::Cpu, DType::F32)?;
/// assert_eq!(t.dims(), &[2, 3]);
/// assert_eq!(points_from_tensor(&t)?, points.to_vec()); // exact in f32
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// A coordinate that is not finite in `dtype` (1e300 overflows f32 to infinity), naming
/// `points` and the point; candle's (an unsupported dtype).
pub fn points_to_tensor(points: &[[f64; 3]], device: &Device, dtype: DType) -> Result<Tensor> {
    let flat: Vec<f64> = points.iter().flatten().copied().collect();
    let t = Tensor::from_vec(flat, (points.len(), 3), &Device::Cpu)?.to_dtype(dtype)?;
    if !points.is_empty() {
        let back: Vec<f64> = t.to_dtype(DType::F64)?.flatten_all()?.to_vec1()?;
        if let Some(i) = back.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "points",
                format!("coordinates that are finite in {dtype:?}"),
                format!("point {} = {:?}", i / 3, points[i / 3]),
            ));
        }
    }
    Ok(t.to_device(device)?)
}

/// A tensor `points: [N, 3]` (f32 or f64, any device) back to host points `[N][3]`, each
/// coordinate widened to `f64` exactly. Not differentiable: the values leave the graph.
/// The inverse of [`points_to_tensor`].
///
/// # Errors
/// [`Error::InvalidArgument`] naming `points` unless it is a float tensor of shape
/// `[N, 3]`; candle's.
pub fn points_from_tensor(points: &Tensor) -> Result<Vec<[f64; 3]>> {
    crate::error::check_points(points, "points")?;
    let v = points
        .to_dtype(DType::F64)?
        .to_device(&Device::Cpu)?
        .to_vec2::<f64>()?;
    Ok(v.into_iter().map(|r| [r[0], r[1], r[2]]).collect())
}
