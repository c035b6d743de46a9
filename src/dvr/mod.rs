//! Surface rendering of implicit fields with implicit gradients (DVR, IDR).
//!
//! One training step: [`march`] (or [`sphere_trace`] for SDFs) finds the first surface
//! point on each ray, detached and in chunks (memory O(rays)); [`implicit_surface`]
//! evaluates the field once more at those points and returns depths and points whose
//! gradients are the implicit-function ones, w.r.t. the field's parameters, a bound latent
//! code ([`crate::field::Conditioned`], shared `[D]` or one `[R, D]` row per ray), and the
//! ray origins and directions (so a
//! [`crate::camera::PoseParam`] is trained too). The losses are DVR's and IDR's, all finite
//! for any finite input (BCE terms use [`crate::numerics::bce_with_logits`]; norms have a
//! floored square root so their gradients stay finite at 0); logits of an implicit
//! surface are `s = σ·(f − τ)`, inside positive for both occupancy logits and SDFs (see
//! [`march`]).
//!
//! [`SurfaceModel`] ([`surface_model`]) puts these pieces together for multi-view
//! reconstruction from masked images: DVR's or IDR's networks, the loss of one training
//! step on a batch of rays ([`SurfaceModel::loss`]) and the shading of rays for
//! evaluation ([`SurfaceModel::shade`]).
//!
//! ```
//! use candle_core::{DType, Device, Tensor, Var};
//! use neural_fields::camera::{Intersection, Rays};
//! use neural_fields::dvr::{implicit_surface, march, ImplicitConfig, MarchConfig, RayStatus};
//! use neural_fields::field::{SignedDistance, Sphere};
//!
//! let dev = Device::Cpu;
//! let radius = Var::new(0.5f64, &dev)?;                       // a learnable radius
//! let sphere = Sphere { center: Tensor::zeros(3, DType::F64, &dev)?,
//!                       radius: radius.as_tensor().clone() }.sdf();
//! let rays = Rays::new(
//!     Tensor::new(&[[0.0f64, 0.0, -2.0], [0.0, 3.0, -2.0]], &dev)?,  // origins
//!     Tensor::new(&[[0.0f64, 0.0, 1.0], [0.0, 0.0, 1.0]], &dev)?,    // directions
//! )?;
//! let range = Intersection::new(Tensor::new(&[0.0f64, 0.0], &dev)?, Tensor::new(&[4.0f64, 4.0], &dev)?)?;
//! let hits = march(&sphere, &rays, &range, &MarchConfig::default())?;
//! assert_eq!(hits.status, vec![RayStatus::Hit, RayStatus::Miss]);
//! let surf = implicit_surface(&sphere, &rays, &hits, &ImplicitConfig::default())?;
//! let t = surf.depth.to_vec1::<f64>()?;                        // one surface point
//! assert!((t[0] - 1.5).abs() < 1e-12);
//! let g = surf.depth.sum_all()?.backward()?;
//! let no_grad = || candle_core::Error::Msg("no gradient for radius".into());
//! let dt_dr = g.get(&radius).ok_or_else(no_grad)?.to_scalar::<f64>()?; // ∂t/∂r = −1
//! assert!((dt_dr + 1.0).abs() < 1e-12);
//! # Ok::<(), neural_fields::Error>(())
//! ```

mod implicit;
mod losses;
mod marching;
mod model;

pub use implicit::{implicit_surface, ImplicitConfig, SurfacePoints};
pub use losses::{
    depth_loss, eikonal_loss, idr_mask_loss, most_inside_along_rays, normal_smoothness_loss,
    occupancy_bce, photometric_loss, random_points_on_rays, AlphaSchedule, Photometric,
};
pub use marching::{
    march, sphere_trace, Hits, MarchConfig, RayStatus, SecantRule, SphereTraceConfig, StepSchedule,
};
pub use model::{
    surface_model, RenderInputs, SurfaceEncoding, SurfaceKind, SurfaceLoss, SurfaceModel,
    SurfaceModelConfig, SurfaceShading,
};
