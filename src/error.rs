//! The crate's error type, and the (crate-private) argument checks every public function
//! runs first.
//!
//! Every check names the argument it inspected and says what was expected, so that a
//! wrong shape deep inside a training loop reads as `points: expected shape [N, 3], got
//! [4096, 2]` rather than as a candle broadcast error three calls later.

use candle_core::{DType, Tensor};
use std::fmt;

/// Errors returned by this crate. New variants may be added in minor releases, so
/// matches need a wildcard arm.
#[derive(Debug)]
#[non_exhaustive]
pub enum Error {
    /// An argument failed validation: `arg` names it, `expected` says what was wanted and
    /// `got` what was passed.
    InvalidArgument {
        /// The name of the offending argument, as it appears in the function signature.
        arg: &'static str,
        /// What the function expected of it.
        expected: String,
        /// What it received.
        got: String,
    },
    /// An error raised by candle while evaluating an operation.
    Candle(candle_core::Error),
    /// An I/O error, with the path or stream it concerns.
    Io {
        /// The file or stream the error concerns.
        path: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A file's content is not what its format requires: `path` names the file, `field`
    /// the key, element or member that failed (`frames[3].transform_matrix`,
    /// `world_mat_2`), `expected` what the format requires and `got` what the file holds.
    Format {
        /// The file.
        path: String,
        /// The key, element or member of the file that failed.
        field: String,
        /// What the format requires there.
        expected: String,
        /// What the file holds.
        got: String,
    },
}

/// `Result` with this crate's [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// Builds an [`Error::InvalidArgument`].
    #[must_use]
    pub(crate) fn invalid(
        arg: &'static str,
        expected: impl Into<String>,
        got: impl Into<String>,
    ) -> Self {
        Error::InvalidArgument {
            arg,
            expected: expected.into(),
            got: got.into(),
        }
    }

    /// Builds an [`Error::Format`] for the file at `path`.
    #[must_use]
    pub(crate) fn format(
        path: impl AsRef<std::path::Path>,
        field: impl Into<String>,
        expected: impl Into<String>,
        got: impl Into<String>,
    ) -> Self {
        Error::Format {
            path: path.as_ref().display().to_string(),
            field: field.into(),
            expected: expected.into(),
            got: got.into(),
        }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::InvalidArgument { arg, expected, got } => {
                write!(f, "{arg}: expected {expected}, got {got}")
            }
            Error::Candle(e) => write!(f, "candle: {e}"),
            Error::Io { path, source } => write!(f, "{path}: {source}"),
            Error::Format {
                path,
                field,
                expected,
                got,
            } => write!(f, "{path}: {field}: expected {expected}, got {got}"),
        }
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Candle(e) => Some(e),
            Error::Io { source, .. } => Some(source),
            Error::InvalidArgument { .. } | Error::Format { .. } => None,
        }
    }
}

impl From<candle_core::Error> for Error {
    fn from(e: candle_core::Error) -> Self {
        Error::Candle(e)
    }
}

/// One expected dimension in a shape pattern: a fixed size or any size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Dim {
    /// Any size (printed with the given symbol, e.g. `N`).
    Any(&'static str),
    /// Exactly this size.
    Is(usize),
}

fn pattern_string(pattern: &[Dim]) -> String {
    let parts: Vec<String> = pattern
        .iter()
        .map(|d| match d {
            Dim::Any(s) => (*s).to_string(),
            Dim::Is(n) => n.to_string(),
        })
        .collect();
    format!("shape [{}]", parts.join(", "))
}

/// Checks that `t` has the given shape pattern and returns its dims.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` when the rank or a fixed dimension differs.
pub(crate) fn check_shape(t: &Tensor, arg: &'static str, pattern: &[Dim]) -> Result<Vec<usize>> {
    let dims = t.dims();
    let ok = dims.len() == pattern.len()
        && dims.iter().zip(pattern).all(|(&d, p)| match p {
            Dim::Any(_) => true,
            Dim::Is(n) => d == *n,
        });
    if ok {
        Ok(dims.to_vec())
    } else {
        Err(Error::invalid(
            arg,
            pattern_string(pattern),
            format!("shape {dims:?}"),
        ))
    }
}

/// Checks that a requested `dtype` argument is one this crate computes in (f32 or f64).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `dtype` for any other.
pub(crate) fn check_dtype(dtype: DType) -> Result<()> {
    match dtype {
        DType::F32 | DType::F64 => Ok(()),
        other => Err(Error::invalid("dtype", "f32 or f64", format!("{other:?}"))),
    }
}

/// Checks that `t` is a floating-point tensor this crate computes in (f32 or f64).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` for any other dtype.
pub(crate) fn check_float(t: &Tensor, arg: &'static str) -> Result<DType> {
    match t.dtype() {
        DType::F32 | DType::F64 => Ok(t.dtype()),
        other => Err(Error::invalid(
            arg,
            "dtype f32 or f64",
            format!("{other:?}"),
        )),
    }
}

/// Checks that `t` has the same dtype and device as `reference` (named `ref_arg`).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` when either differs.
pub(crate) fn check_same(
    t: &Tensor,
    arg: &'static str,
    reference: &Tensor,
    ref_arg: &str,
) -> Result<()> {
    if t.dtype() != reference.dtype() {
        return Err(Error::invalid(
            arg,
            format!("dtype {:?} (that of {ref_arg})", reference.dtype()),
            format!("{:?}", t.dtype()),
        ));
    }
    if !t.device().same_device(reference.device()) {
        return Err(Error::invalid(
            arg,
            format!("device {:?} (that of {ref_arg})", reference.device()),
            format!("{:?}", t.device()),
        ));
    }
    Ok(())
}

/// Checks that `t` has the same shape as `reference` (named `ref_arg`).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` when the shapes differ.
pub(crate) fn check_same_shape(
    t: &Tensor,
    arg: &'static str,
    reference: &Tensor,
    ref_arg: &str,
) -> Result<()> {
    if t.dims() == reference.dims() {
        Ok(())
    } else {
        Err(Error::invalid(
            arg,
            format!("shape {:?} (that of {ref_arg})", reference.dims()),
            format!("shape {:?}", t.dims()),
        ))
    }
}

/// Whether `t` holds no NaN or ±∞: [`finite_probe`] read back from the device as one
/// scalar. An integer tensor is finite.
pub(crate) fn all_finite(t: &Tensor) -> Result<bool> {
    if !t.dtype().is_float() {
        return Ok(true);
    }
    let probe = finite_probe(t)?.to_dtype(DType::F64)?.to_scalar::<f64>()?;
    Ok(probe.is_finite())
}

/// `Σ 0·x` over a float tensor `t`, a scalar tensor of `t`'s dtype on its device: every
/// term is 0 for a finite `x` whatever its magnitude and NaN for NaN or ±∞, so the sum is
/// exact in any float dtype and finite exactly when `t` is. No copy of `t` in another
/// dtype.
pub(crate) fn finite_probe(t: &Tensor) -> Result<Tensor> {
    Ok(t.detach().affine(0.0, 0.0)?.sum_all()?)
}

/// Checks that every element of `t` is finite (no NaN, no ±∞).
///
/// This reads one scalar back from the device (a reduction), so it synchronises with
/// an accelerator.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` when some element is not finite.
pub(crate) fn check_finite(t: &Tensor, arg: &'static str) -> Result<()> {
    if t.elem_count() == 0 {
        return Ok(());
    }
    if all_finite(t)? {
        Ok(())
    } else {
        Err(Error::invalid(arg, "finite values", "NaN or infinity"))
    }
}

/// Checks a plain scalar argument: finite, and strictly positive if `positive`.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` otherwise.
pub(crate) fn check_scalar(x: f64, arg: &'static str, positive: bool) -> Result<()> {
    if !x.is_finite() {
        return Err(Error::invalid(arg, "a finite number", format!("{x}")));
    }
    if positive && x <= 0.0 {
        return Err(Error::invalid(arg, "a number > 0", format!("{x}")));
    }
    Ok(())
}

/// Checks `[N, 3]` float points: rank 2, three columns and dtype f32 or f64. Returns `N`.
///
/// An empty batch (`N = 0`) is accepted: the `dvr` marchers and losses evaluate fields
/// on the (possibly empty) set of rays that hit, and return empty or zero results for
/// it. Functions that need `N > 0` add [`check_nonempty`].
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` for another rank, column count or dtype.
pub(crate) fn check_points(t: &Tensor, arg: &'static str) -> Result<usize> {
    check_float(t, arg)?;
    let dims = check_shape(t, arg, &[Dim::Any("N"), Dim::Is(3)])?;
    Ok(dims[0])
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn messages_name_the_argument_and_the_expectation() -> Result<()> {
        let t = Tensor::zeros((4, 2), DType::F32, &Device::Cpu)?;
        let e = check_points(&t, "points").unwrap_err().to_string();
        assert_eq!(e, "points: expected shape [N, 3], got shape [4, 2]");
        let t = Tensor::zeros((4, 3), DType::U32, &Device::Cpu)?;
        let e = check_points(&t, "points").unwrap_err().to_string();
        assert!(e.starts_with("points: expected dtype f32 or f64"), "{e}");
        Ok(())
    }

    #[test]
    fn finite_check_catches_nan_and_inf_but_not_large_values() -> Result<()> {
        let d = Device::Cpu;
        let ok = Tensor::new(&[1e38f32, -3.0, 0.0], &d)?;
        assert!(check_finite(&ok, "x").is_ok());
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let t = Tensor::new(&[1.0f32, bad], &d)?;
            assert!(check_finite(&t, "x").is_err());
        }
        Ok(())
    }
}
