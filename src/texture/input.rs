//! The inputs of a texture field and the trait every texture field implements.

use crate::error::{check_points, check_same, check_shape, Dim, Error, Result};
use candle_core::Tensor;

/// The inputs of a [`TextureField`] at `N` points; start from [`TextureInput::new`] and
/// set what the field reads, e.g. `TextureInput { normals: Some(&n), ..TextureInput::new(&p) }`.
///
/// Every tensor shares the points' dtype (f32 or f64) and device and has `N` rows.
#[derive(Clone, Copy, Debug)]
pub struct TextureInput<'a> {
    /// Surface points `[N, 3]`.
    pub points: &'a Tensor,
    /// Surface normals `[N, 3]` (any length: fields that read them normalise or not as
    /// they document), e.g. the spatial gradient of an SDF at the points.
    pub normals: Option<&'a Tensor>,
    /// Viewing directions `[N, 3]`: the directions of the rays that reached the points
    /// (from the camera towards the surface).
    pub view_dirs: Option<&'a Tensor>,
    /// Feature vectors `[N, F]` from the geometry network (IDR's global feature).
    pub features: Option<&'a Tensor>,
    /// Shape codes `[N, C]` (Texture Fields' `c`).
    pub shape_code: Option<&'a Tensor>,
    /// Image codes `[N, Z]` (Texture Fields' `z`).
    pub image_code: Option<&'a Tensor>,
}

impl<'a> TextureInput<'a> {
    /// Inputs with only the points `[N, 3]`.
    #[must_use]
    pub fn new(points: &'a Tensor) -> Self {
        Self {
            points,
            normals: None,
            view_dirs: None,
            features: None,
            shape_code: None,
            image_code: None,
        }
    }

    /// Checks the points: f32/f64 `[N, 3]`; returns `N`.
    ///
    /// # Errors
    /// Naming `points`.
    pub(crate) fn check_points(&self) -> Result<usize> {
        check_points(self.points, "points")
    }

    /// The optional input `which` (named `arg`), required with `cols` columns (any
    /// number for `None`) and `n` rows, in the points' dtype and device.
    ///
    /// # Errors
    /// Naming `arg` when it is missing or of another shape, dtype or device.
    pub(crate) fn required(
        &self,
        which: Option<&'a Tensor>,
        arg: &'static str,
        cols: Option<usize>,
        reader: &str,
    ) -> Result<&'a Tensor> {
        let n = self.check_points()?;
        let t = which.ok_or_else(|| {
            Error::invalid(
                arg,
                format!(
                    "[N, {}] (read by {reader})",
                    cols.map_or("K".into(), |c| c.to_string())
                ),
                "none",
            )
        })?;
        check_same(t, arg, self.points, "points")?;
        let col = match cols {
            Some(c) => Dim::Is(c),
            None => Dim::Any("K"),
        };
        check_shape(t, arg, &[Dim::Is(n), col])?;
        Ok(t)
    }
}

/// A colour field over surface points: [`TextureInput`] → RGB `[N, 3]` in `[0, 1]`.
///
/// Implementations document which inputs they read, and return an error naming an input
/// they read but did not get. The output is differentiable w.r.t. the field's parameters
/// and every input it reads (so a photometric loss reaches the surface points, normals,
/// features and codes).
pub trait TextureField {
    /// RGB `[N, 3]` in `[0, 1]` at `input.points`, in their dtype and device.
    ///
    /// # Errors
    /// Missing or mis-shaped inputs (naming them); errors of the computation.
    fn rgb(&self, input: &TextureInput) -> Result<Tensor>;
}
