//! A field that answers NaN cannot say where its surface is: `dvr::march` and
//! `dvr::sphere_trace` used to report every ray of a field that is NaN everywhere as a
//! clean miss. They now return an error naming the field.

use candle_core::{DType, Device, Result as CResult, Tensor};
use neural_fields::camera::{Intersection, Rays};
use neural_fields::dvr::{march, sphere_trace, MarchConfig, SphereTraceConfig};
use neural_fields::field::{ImplicitSurface, Inside};
use neural_fields::Result;

/// NaN everywhere, or only where `z > 0.5` (a field that breaks part of the way along).
struct NanField {
    everywhere: bool,
}

impl ImplicitSurface for NanField {
    fn value(&self, p: &Tensor) -> Result<Tensor> {
        let z = p.narrow(1, 2, 1)?.squeeze(1)?;
        let nan = Tensor::full(f64::NAN, z.shape(), z.device())?.to_dtype(z.dtype())?;
        if self.everywhere {
            return Ok(nan);
        }
        let far = (z.ones_like()? * 10.0)?; // an SDF far from any surface
        Ok(z.gt(0.5)?.where_cond(&nan, &far)?)
    }
    fn value_and_grad(&self, p: &Tensor) -> Result<(Tensor, Tensor)> {
        Ok((self.value(p)?, p.zeros_like()?))
    }
    fn inside(&self) -> Inside {
        Inside::Negative
    }
}

fn rays() -> CResult<(Rays, Intersection)> {
    let dev = Device::Cpu;
    let rays = Rays::new(
        Tensor::new(&[[0.0f64, 0.0, 0.0], [0.3, 0.0, 0.0]], &dev)?,
        Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.0, 1.0]], &dev)?,
    )
    .unwrap();
    let range = Intersection::new(
        Tensor::new(&[0.0f64, 0.0], &dev)?,
        Tensor::zeros(2, DType::F64, &dev)?.affine(0.0, 1.0)?,
    )
    .unwrap();
    Ok((rays, range))
}

#[test]
fn march_reports_a_nan_field_as_a_field_error() {
    let (rays, range) = rays().unwrap();
    for everywhere in [true, false] {
        let e = march(
            &NanField { everywhere },
            &rays,
            &range,
            &MarchConfig::default(),
        );
        let e = e.expect_err("a NaN field is not a miss").to_string();
        assert!(e.starts_with("field: ") && e.contains("NaN"), "{e}");
    }
}

#[test]
fn sphere_trace_reports_a_nan_field_as_a_field_error() {
    let (rays, range) = rays().unwrap();
    let e = sphere_trace(
        &NanField { everywhere: true },
        &rays,
        &range,
        &SphereTraceConfig::default(),
    );
    let e = e.expect_err("a NaN field is not a miss").to_string();
    assert!(e.starts_with("field: ") && e.contains("NaN"), "{e}");
}
