//! # neural-fields
//!
//! Differentiable neural-field primitives on [candle]: fields and implicit surfaces,
//! encodings, cameras, reference networks with trainable normals — and, behind Cargo
//! features, occupancy networks, surface rendering with implicit gradients (DVR) and
//! NeRF volume rendering. You keep your own training loop (a
//! candle-nn `VarMap` and optimiser); this crate gives you the pieces whose gradients
//! are hard to get right, each proven against finite differences by property tests.
//!
//! ## Ten-minute tour
//!
//! **1. Fields.** A [`field::Field`] maps points `[N, 3]` to features `[N, C]`; an
//! [`field::ImplicitSurface`] is a scalar field with a level and an inside sign, and
//! returns its value *and spatial gradient* in one pass. Analytic shapes are fields too
//! and serve as ground truth:
//!
//! ```
//! use candle_core::{DType, Device, Tensor};
//! use neural_fields::field::{ImplicitSurface, SignedDistance, Torus};
//!
//! let torus = Torus::new([0.0; 3], 0.25, 0.125, &Device::Cpu, DType::F32)?.sdf();
//! let p = Tensor::new(&[[0.25f32, 0.0, 0.0], [0.0, 0.0, 0.0]], &Device::Cpu)?;
//! let (d, n) = torus.value_and_grad(&p)?; // distances [2], normals [2, 3]
//! assert_eq!(d.to_vec1::<f32>()?, vec![-0.125, 0.125]);
//! assert_eq!(n.dims(), &[2, 3]);
//! # Ok::<(), neural_fields::Error>(())
//! ```
//!
//! **2. Networks with trainable normals.** [`nn::Mlp`] computes `∇ₓf` by forward-mode
//! tangents made of candle ops, so a loss on the normal (eikonal, normal consistency,
//! DVR's implicit step) back-propagates into the weights — which a gradient obtained
//! from candle's `backward()` cannot, since candle returns it detached:
//!
//! ```
//! use candle_core::{DType, Device, Tensor};
//! use candle_nn::VarMap;
//! use neural_fields::field::ImplicitSurface;
//! use neural_fields::nn::{build_seeded, mlp, MlpConfig};
//!
//! let varmap = VarMap::new();
//! let config = MlpConfig { hidden: 32, depth: 3, ..MlpConfig::sdf(0.5) }; // IDR init
//! let net = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| mlp(&config, vb))?;
//! let p = Tensor::new(&[[0.0f32, 0.0, 0.7]], &Device::Cpu)?;
//! let (_, grad) = net.value_and_grad(&p)?;
//! let eikonal = (grad.sqr()?.sum(1)?.sqrt()? - 1.0)?.sqr()?.mean_all()?;
//! let grads = eikonal.backward()?;            // reaches the weights
//! let vars = varmap.data().lock().map_err(|e| candle_core::Error::Msg(e.to_string()))?;
//! let w0 = vars["layer0.weight"].clone();
//! assert!(grads.get(&w0).is_some());
//! # Ok::<(), neural_fields::Error>(())
//! ```
//!
//! **3. Encodings.** [`encoding::FrequencyEncoding`] (NeRF), [`encoding::FourierFeatures`]
//! (Tancik et al.) and [`encoding::integrated_pe`] (mip-NeRF), accurate in f32 at every
//! frequency thanks to exact argument reduction ([`numerics::sin_cos_pi`]), and
//! [`encoding::HashGrid`] (instant-NGP), whose learned tables train in a fused CPU op
//! with a deterministic gradient.
//!
//! **4. Cameras.** [`camera::Camera`] (pinhole, OpenCV or OpenGL axes) makes
//! [`camera::Rays`] (validated once, taken by every function that traces rays);
//! [`camera::ray_aabb`] and [`camera::ray_sphere`] clip them; [`camera::PoseParam`] is a
//! learnable pose whose rays carry gradients. Poses are [`glam`] types, re-exported.
//!
//! ```
//! use candle_core::{DType, Device};
//! use neural_fields::camera::{ray_sphere, Camera, Convention, Intrinsics};
//! use neural_fields::glam::DVec3;
//!
//! let k = Intrinsics::from_fov_y(64, 48, 0.8)?;
//! let cam = Camera::look_at(k, DVec3::new(0.0, 0.0, 3.0), DVec3::ZERO, DVec3::Y, Convention::OpenGl)?;
//! let rays = cam.rays(&Device::Cpu, DType::F32)?;                 // 3072 rays
//! let hits = ray_sphere(&rays, [0.0; 3], 1.0)?;
//! assert_eq!(hits.near.dims(), &[64 * 48]);
//! # Ok::<(), neural_fields::Error>(())
//! ```
//!
//! **5. Volume rendering (NeRF).** Samplers return [`volume::Intervals`] along the rays;
//! evaluate your field at their positions and [`volume::composite()`] them into pixels
//! (the fused CPU kernel on the CPU, candle ops elsewhere; either the batched `[R, S]`
//! or the packed layout of the [`volume::OccupancyGrid`], which skips empty space):
//!
//! ```
//! use candle_core::{DType, Device};
//! use neural_fields::camera::{ray_aabb, Camera, Convention, Intrinsics};
//! use neural_fields::glam::DVec3;
//! use neural_fields::numerics::trunc_exp;
//! use neural_fields::volume::{composite, stratified, CompositeConfig, Jitter};
//!
//! let dev = Device::Cpu;
//! let k = Intrinsics::from_fov_y(16, 16, 0.8)?;
//! let cam = Camera::look_at(k, DVec3::new(0.0, 0.0, 3.0), DVec3::ZERO, DVec3::Y, Convention::OpenGl)?;
//! let rays = cam.rays(&dev, DType::F32)?;                          // 256 rays
//! let bounds = ray_aabb(&rays, [-1.0; 3], [1.0; 3])?;              // near, far per ray
//! let intervals = stratified(&bounds.near, &bounds.far, 48, Jitter::PerSample, 0)?;
//! let points = intervals.positions(&rays)?;                        // [256, 48, 3]
//! // Your field here: density and colour at the points (a fuzzy ball for the example).
//! let r2 = points.sqr()?.sum(2)?;                                  // [256, 48]
//! let sigmas = trunc_exp(&((r2 * -8.0)? + 3.0)?)?;
//! let colors = points.affine(0.5, 0.5)?.clamp(0.0, 1.0)?;         // [256, 48, 3]
//! let out = composite(&sigmas, &colors, &intervals, Some(&rays), &CompositeConfig::default())?;
//! assert_eq!(out.color.dims(), &[256, 3]);                         // one RGB per pixel
//! # Ok::<(), neural_fields::Error>(())
//! ```
//!
//! To train, sample through the [`volume::OccupancyGrid`] with the field's density as
//! [`volume::OccupancyGrid::sample`]'s density function (only the samples that are
//! visible and not empty come out), minimise `Nerf::color_loss` (one fused CPU op) and
//! render whole views with [`volume::render_image`]: `examples/nerf_tour.rs` is that
//! trainer on the committed scene, with Adam, every test view and its PSNR, in under
//! 60 lines (`cargo run --release --example nerf_tour`).
//!
//! **6. Training.** The usual candle loop; losses use the defended numerics of
//! [`numerics`] (e.g. [`numerics::bce_with_logits`], finite for logits of ±10⁴). See
//! `examples/quickstart.rs`, which fits an occupancy network to a torus in seconds.
//!
//! **7. Meshes.** [`mesh::Mesh`] reads and writes PLY, OBJ, STL and OFF (every reader's
//! work bounded by the file's size, concave polygons ear-clipped), [`mesh::PointCloud`]
//! holds scans (points with normals and colours), and [`mesh::points_to_tensor`] moves
//! host points to any device and dtype; the `mesh` module is always built. With the
//! `occupancy` feature, [`occupancy::mise`] extracts the surface of any implicit field
//! (evaluating it only near the surface) with watertight [`occupancy::marching_cubes`],
//! and [`occupancy::iou`] and [`occupancy::mesh_metrics`] compute ONet's IoU,
//! Chamfer-L1, normal consistency and F-score. See `examples/fit_occupancy.rs`.
//!
//! **8. Texture fields** (feature `texture`). A [`texture::TextureField`] colours surface
//! points from whatever it reads of a [`texture::TextureInput`] (normals, view directions,
//! geometry features, codes): the Texture Fields decoder, IDR's rendering network and
//! DVR's joint decoder are in [`texture`], built on [`nn`]'s blocks. With DVR's surface points the photometric loss
//! reaches the shape; `examples/dvr_multiview/` reconstructs shape and colour from
//! masked images.
//!
//! **9. Motion** (feature `flow`). [`flow::odeint`] integrates `dy/dt = f(t, y)` with RK4
//! or Dormand–Prince and backpropagates through the steps; [`flow::VelocityField`] and
//! [`flow::OccupancyFlow`] give occupancy at any time from a time-0 decoder and dense
//! correspondences. `examples/occupancy_flow.rs` learns a twisting, moving torus.
//!
//! ## Conventions
//! * Shapes are written `[N, 3]`; every function follows the device and dtype (f32 or
//!   f64) of its inputs, so the same code runs on CUDA with the `cuda` feature.
//! * Bad input returns [`Error::InvalidArgument`], whose message names the argument and
//!   what was expected: `points: expected shape [N, 3], got shape [4096, 2]`.
//! * Randomness takes a `u64` seed ([`rng::SplitMix64`]); candle's CPU generator cannot
//!   be seeded, so [`nn::build_seeded`] makes initialisation reproducible too.
//!
//! ## Features
//! | feature | default | module |
//! |---|---|---|
//! | `occupancy` | yes | occupancy networks: losses, samplers, marching cubes, MISE, metrics |
//! | `dvr` | yes | surface rendering with implicit gradients: ray marching + secant, sphere tracing, implicit surface points, DVR/IDR losses |
//! | `volume` | yes | NeRF samplers, compositing (reference and fused CPU kernel), occupancy grid, regularisers |
//! | `texture` | yes | texture fields: the `TextureField` trait, the Texture Fields decoder, IDR's rendering network, DVR's joint decoder, the image-gradient loss, vertex colours for meshes |
//! | `data` | yes | datasets (Blender, nerfstudio, IDR/DTU layouts), seeded ray and patch batches, PSNR/SSIM, PNG output, a Blender-layout writer |
//! | `flow` | yes | motion: ODE integration with gradients (RK4, Dormand–Prince), velocity fields, Occupancy Flow |
//! | `cuda` | no | candle's CUDA backend (needs nvcc) |
//!
//! The derivations behind every gradient are in `docs/math.md`.
//!
//! [candle]: https://github.com/huggingface/candle
#![deny(missing_docs)]

pub mod camera;
#[cfg(feature = "data")]
pub mod data;
#[cfg(feature = "dvr")]
pub mod dvr;
pub mod encoding;
pub mod error;
pub mod field;
#[cfg(feature = "flow")]
pub mod flow;
pub(crate) mod kernels;
mod limits;
pub mod mesh;
mod narrow;
pub mod nn;
pub mod numerics;
#[cfg(feature = "occupancy")]
pub mod occupancy;
pub mod rng;
#[cfg(feature = "texture")]
pub mod texture;
#[cfg(feature = "volume")]
pub mod volume;

pub use error::{Error, Result};

/// Test helpers shared with the integration tests (`tests/common/host.rs`), whose
/// `super::SplitMix64` is this crate's generator.
#[cfg(test)]
#[path = "../tests/common/host.rs"]
#[allow(dead_code)] // `extreme_inputs` serves the `volume` tests only.
mod test_host;
/// glam, whose types ([`glam::DAffine3`], [`glam::DVec3`]) poses and cameras take:
/// re-exported so that users need not pin the same version by hand.
pub use glam;
#[cfg(test)]
use rng::SplitMix64;

/// The README's code blocks, compiled and run as doc tests.
#[doc = include_str!("../README.md")]
#[cfg(doctest)]
pub struct ReadmeDoctests;
