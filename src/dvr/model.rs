//! A ready-made surface model for multi-view reconstruction from masked images: DVR's
//! occupancy network and texture field, DVR's joint decoder, or IDR's SDF network and
//! rendering network; the loss of one training step on a batch of rays, and the shading
//! of rays for evaluation.

use super::implicit::{implicit_surface, ImplicitConfig};
use super::losses::{
    eikonal_loss, idr_mask_loss, most_inside_along_rays, normal_smoothness_loss, photometric_loss,
    AlphaSchedule, Photometric,
};
use super::marching::{march, sphere_trace, Hits, MarchConfig, SphereTraceConfig};
use crate::camera::{ray_aabb, Intersection, Rays};
use crate::encoding::{hash_grid, CoarseToFine, FrequencyEncoding, HashGridConfig, PointEncoding};
use crate::error::{check_float, check_same, check_shape, Dim, Error, Result};
use crate::field::{ImplicitSurface, Inside};
use crate::nn::{mlp, Mlp, MlpConfig};
use crate::numerics::bce_with_logits;
use crate::rng::SplitMix64;
use crate::texture::{
    image_gradient_loss, joint_decoder, rendering_net, texture_decoder, JointDecoder, RenderingNet,
    RenderingNetConfig, TextureDecoder, TextureDecoderConfig, TextureField, TextureInput,
};
use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;
use std::cell::RefCell;

/// log₂ of the rows of each hash-grid level ([`SurfaceEncoding::HashGrid`]).
const HASH_LOG2: u32 = 15;
/// Channels of IDR's geometry feature (the SDF network's outputs after the distance).
const IDR_FEATURES: usize = 32;
/// Samples per ray of the freespace, occupancy and IDR mask terms.
const RAY_SAMPLES: usize = 64;

/// The networks of a [`SurfaceModel`] ([`SurfaceModelConfig::kind`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SurfaceKind {
    /// DVR (Niemeyer et al. 2020): an occupancy network (logits, inside positive; 5 × 128
    /// with a skip at layer 3 on frequencies, 2 × 64 on a hash grid) and a Texture Fields
    /// decoder for the colour ([`TextureDecoder`]) on the surface point alone: one
    /// colour per point whatever the view (Lambertian, as in DVR), so a specular
    /// highlight is out of its reach ([`SurfaceKind::Idr`]'s rendering network reads the
    /// view direction). Variables under `geometry` and `texture`.
    #[default]
    Dvr,
    /// DVR's joint decoder ([`JointDecoder`]): one trunk (as [`SurfaceKind::Dvr`]'s
    /// occupancy network) for the occupancy logit and the colour. Variables under
    /// `decoder`.
    DvrJoint,
    /// IDR (Yariv et al. 2020): an SDF network (5 × 128, a skip at layer 3, softplus,
    /// inside negative, geometrically initialised to a sphere of radius 0.5) whose 32
    /// outputs after the distance are a feature, and IDR's rendering network
    /// ([`RenderingNet`], 3 × 64) on the point, the view direction, the normal and the
    /// feature. Variables under `geometry` and `render`.
    Idr,
}

/// The position encoding of a [`SurfaceModel`]'s networks.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum SurfaceEncoding {
    /// Frequency encodings: 4 octaves for the occupancy network, 8 for the texture
    /// decoder; IDR's SDF 6 octaves and its rendering network the raw point.
    #[default]
    Frequency,
    /// instant-NGP's hash grid over [`SurfaceModelConfig::scene_box`]
    /// ([`HashGridConfig::default`] with 2¹⁵ rows per level, resolutions 16 to
    /// `finest_resolution`) under the DVR models' networks (the occupancy trunk then 2 ×
    /// 64) and under IDR's rendering network; IDR's SDF keeps its 6 octaves, which its
    /// geometric initialisation needs. Each grid's table is a variable `grid` beside its
    /// network's.
    HashGrid {
        /// The finest level's resolution, ≥ 16 (e.g. five cells per pixel of the images'
        /// larger side: the `data` feature's `Dataset::hash_finest`).
        finest_resolution: f64,
    },
}

/// What IDR's rendering network reads besides the point and the feature (read by
/// [`SurfaceKind::Idr`] only).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RenderInputs {
    /// The view direction (4 octaves) and the normal (IDR).
    #[default]
    Full,
    /// The normal, no view direction (IDR's `no_view_dir` ablation).
    NoView,
    /// The view direction, no normal (IDR's `no_normal` ablation).
    NoNormal,
}

/// Settings of [`surface_model`].
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceModelConfig {
    /// The networks. Default [`SurfaceKind::Dvr`].
    pub kind: SurfaceKind,
    /// Their position encoding. Default [`SurfaceEncoding::Frequency`].
    pub encoding: SurfaceEncoding,
    /// IDR's rendering-network inputs. Default [`RenderInputs::Full`].
    pub render_inputs: RenderInputs,
    /// The scene box `[x₀, y₀, z₀, x₁, y₁, z₁]`: rays are marched inside it, hash grids
    /// span it and IDR's eikonal points are drawn from the cube `[min xᵢ, max xᵢ]³`.
    /// Default `[-1, -1, -1, 1, 1, 1]`.
    pub scene_box: [f64; 6],
    /// Put every position encoding under BARF's coarse-to-fine window
    /// ([`CoarseToFine`], listed in [`SurfaceModel::windows`] for the training loop to
    /// open). Default `false`.
    pub coarse_to_fine: bool,
    /// The side `k` of the square patches the rays of a batch come in (consecutive runs
    /// of `k²` rays, as `RaySampler::patches(count, k)` of the `data` feature draws
    /// them): DVR's image-gradient loss compares the colour differences inside each. 1:
    /// single rays, no image-gradient term. Default 2.
    pub patch: usize,
}

impl Default for SurfaceModelConfig {
    fn default() -> Self {
        Self {
            kind: SurfaceKind::Dvr,
            encoding: SurfaceEncoding::Frequency,
            render_inputs: RenderInputs::Full,
            scene_box: [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0],
            coarse_to_fine: false,
            patch: 2,
        }
    }
}

/// The networks of one [`SurfaceKind`] (one per model, so the variants' sizes do not
/// matter).
#[derive(Clone, Debug)]
#[allow(clippy::large_enum_variant)]
enum Net {
    Dvr {
        geometry: Mlp,
        texture: TextureDecoder,
    },
    Joint(JointDecoder),
    Idr {
        geometry: Mlp,
        render: RenderingNet,
    },
}

/// A surface model: an implicit surface and its colour, trained from masked images by
/// surface rendering with implicit gradients ([`SurfaceModel::loss`]) and rendered by
/// [`SurfaceModel::shade`]; build it with [`surface_model`].
///
/// It is the model's [`ImplicitSurface`] (the occupancy logit or the signed distance:
/// for [`crate::dvr::march`], mesh extraction, or fitting an initial shape) and its
/// [`TextureField`] (the colour at `points` seen along `view_dirs`, which IDR's
/// rendering network reads unless [`RenderInputs::NoView`]; normals and features come
/// from the geometry network). Both are differentiable w.r.t. the parameters and the
/// points.
#[derive(Clone, Debug)]
pub struct SurfaceModel {
    net: Net,
    scene_box: [f64; 6],
    patch: usize,
    /// The coarse-to-fine windows of every position encoding (empty unless
    /// [`SurfaceModelConfig::coarse_to_fine`]; they start closed, α = 0). Open them
    /// during training with [`CoarseToFine::set_alpha`]; clones share their state with
    /// the networks.
    pub windows: Vec<CoarseToFine>,
}

/// The terms of one training step ([`SurfaceModel::loss`]).
#[derive(Clone, Debug)]
pub struct SurfaceLoss {
    /// The weighted sum of every term: a scalar with graph, to backpropagate.
    pub total: Tensor,
    /// The mean L1 colour error of the rays that hit the surface inside the mask: a
    /// scalar with graph (0 when there are none), for logging.
    pub photometric: Tensor,
}

/// What [`SurfaceModel::shade`] sees along `N` rays, without graph, in the rays' dtype.
#[derive(Clone, Debug)]
pub struct SurfaceShading {
    /// The colour on a white background, `[N, 3]`.
    pub rgb: Tensor,
    /// The depth (ray parameter) of the first surface point, `[N]`: for rays without
    /// one, as [`Hits::depth`].
    pub depth: Tensor,
    /// 1 where the ray has a surface point, else 0, `[N]`.
    pub coverage: Tensor,
    /// Outward unit normals (towards decreasing occupancy or increasing distance),
    /// `[N, 3]`; 0 where nothing is hit.
    pub normals: Tensor,
}

/// Builds the [`SurfaceModel`] of `config` from `vb` (f32 or f64, any device; the
/// variables are named in [`SurfaceKind`]'s variants, so weights saved from a `VarMap`
/// load back into the same configuration). Pass it to [`crate::nn::build_seeded`] for a
/// reproducible initialisation.
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::camera::Rays;
/// use neural_fields::dvr::{surface_model, SurfaceModelConfig};
/// use neural_fields::nn::build_seeded;
///
/// let (dev, varmap) = (Device::Cpu, VarMap::new());
/// let config = SurfaceModelConfig::default(); // DVR, frequencies, the box ±1, 2 × 2 patches
/// let model = build_seeded(&varmap, DType::F32, &dev, 0, |vb| surface_model(&config, vb))?;
/// // One 2 × 2 patch of rays along +z, its colours and its mask.
/// let o: Vec<f32> = [-0.1f32, 0.0, 0.1, 0.2].iter().flat_map(|&x| [x, 0.0, -2.0]).collect();
/// let rays = Rays::new(Tensor::from_vec(o, (4, 3), &dev)?, Tensor::new(&[[0f32, 0.0, 1.0]; 4], &dev)?)?;
/// let colors = Tensor::full(0.5f32, (4, 3), &dev)?;
/// let mask = Tensor::new(&[1f32, 1.0, 0.0, 0.0], &dev)?;
/// let loss = model.loss(&rays, &colors, &mask, 0.0, 7)?;
/// let grads = loss.total.backward()?;                        // w.r.t. every weight
/// assert_eq!(loss.total.rank(), 0);
/// let seen = model.shade(&rays)?;                            // without graph
/// assert_eq!((seen.rgb.dims(), seen.coverage.dims()), (&[4, 3][..], &[4][..]));
/// # let _ = grads;
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `config.scene_box` unless finite with `x₀ < x₁`,
/// `y₀ < y₁`, `z₀ < z₁`; `config.patch` when 0; `config.encoding` for a hash grid's
/// finest resolution below 16 or not finite; `vb` unless its dtype is f32 or f64;
/// errors of `vb`.
pub fn surface_model(config: &SurfaceModelConfig, vb: VarBuilder) -> Result<SurfaceModel> {
    let b = config.scene_box;
    if b.iter().any(|x| !x.is_finite()) || (0..3).any(|i| b[i] >= b[i + 3]) {
        return Err(Error::invalid(
            "config.scene_box",
            "finite [x₀, y₀, z₀, x₁, y₁, z₁] with x₀ < x₁, y₀ < y₁, z₀ < z₁",
            format!("{b:?}"),
        ));
    }
    if config.patch == 0 {
        return Err(Error::invalid("config.patch", "a side of at least 1", "0"));
    }
    if let SurfaceEncoding::HashGrid { finest_resolution } = config.encoding {
        if !(finest_resolution.is_finite() && finest_resolution >= 16.0) {
            return Err(Error::invalid(
                "config.encoding",
                "a hash grid's finest resolution ≥ 16 (its coarsest) and finite",
                finest_resolution.to_string(),
            ));
        }
    }
    if !matches!(vb.dtype(), DType::F32 | DType::F64) {
        return Err(Error::invalid(
            "vb",
            "a VarBuilder of dtype f32 or f64",
            format!("{:?}", vb.dtype()),
        ));
    }
    let windows = RefCell::new(Vec::new());
    let window = |encoding: PointEncoding| -> Result<PointEncoding> {
        if !config.coarse_to_fine {
            return Ok(encoding);
        }
        let c = CoarseToFine::new(encoding)?;
        windows.borrow_mut().push(c.clone());
        Ok(PointEncoding::CoarseToFine(c))
    };
    // The encoding of 3-D points: `frequencies` octaves, or the hash grid in `vb.pp("grid")`.
    let encode = |frequencies: usize, vb: &VarBuilder| -> Result<PointEncoding> {
        window(match config.encoding {
            SurfaceEncoding::Frequency => {
                PointEncoding::Frequency(FrequencyEncoding::new(3, frequencies)?)
            }
            SurfaceEncoding::HashGrid { finest_resolution } => {
                let grid = HashGridConfig {
                    lo: b[..3].to_vec(),
                    hi: b[3..].to_vec(),
                    log2_table_size: HASH_LOG2,
                    finest_resolution,
                    ..HashGridConfig::default()
                };
                PointEncoding::HashGrid(hash_grid(&grid, vb.pp("grid"))?)
            }
        })
    };
    // The occupancy network: PE(L = 4) on 5 × 128 with a skip, or a hash grid on 2 × 64.
    let shape = |vb: &VarBuilder| -> Result<MlpConfig> {
        let encoding = encode(4, vb)?;
        Ok(match config.encoding {
            SurfaceEncoding::Frequency => MlpConfig {
                hidden: 128,
                depth: 5,
                skips: vec![3],
                encoding,
                ..MlpConfig::default()
            },
            SurfaceEncoding::HashGrid { .. } => MlpConfig {
                hidden: 64,
                depth: 2,
                encoding,
                ..MlpConfig::default()
            },
        })
    };
    let net = match config.kind {
        SurfaceKind::DvrJoint => {
            let vb = vb.pp("decoder");
            Net::Joint(joint_decoder(&shape(&vb)?, vb)?)
        }
        SurfaceKind::Dvr => {
            let g = vb.pp("geometry");
            let geometry = mlp(&shape(&g)?, g)?;
            let t = vb.pp("texture");
            let texture_config = TextureDecoderConfig {
                encoding: encode(8, &t)?,
                ..TextureDecoderConfig::default()
            };
            let texture = texture_decoder(&texture_config, t)?;
            Net::Dvr { geometry, texture }
        }
        SurfaceKind::Idr => {
            let sdf = MlpConfig {
                hidden: 128,
                depth: 5,
                skips: vec![3],
                out_dim: 1 + IDR_FEATURES,
                // IDR's 6 frequencies: the SDF's geometric initialisation keeps the
                // higher ones at zero, where an occupancy network with them grows floaters.
                encoding: window(PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?))?,
                ..MlpConfig::sdf(0.5)
            };
            let geometry = mlp(&sdf, vb.pp("geometry"))?;
            let r = vb.pp("render");
            let idr = RenderingNetConfig::default();
            let inputs = match config.render_inputs {
                RenderInputs::Full => idr,
                RenderInputs::NoView => RenderingNetConfig {
                    view_frequencies: None,
                    ..idr
                },
                RenderInputs::NoNormal => RenderingNetConfig {
                    use_normals: false,
                    ..idr
                },
            };
            let render_config = RenderingNetConfig {
                feature_dim: IDR_FEATURES,
                hidden: 64,
                depth: 3,
                point_encoding: match config.encoding {
                    SurfaceEncoding::Frequency => PointEncoding::Identity,
                    SurfaceEncoding::HashGrid { .. } => encode(0, &r)?,
                },
                ..inputs
            };
            let render = rendering_net(&render_config, r)?;
            Net::Idr { geometry, render }
        }
    };
    Ok(SurfaceModel {
        net,
        scene_box: b,
        patch: config.patch,
        windows: windows.into_inner(),
    })
}

/// Rows `idx` of `t`.
fn rows(t: &Tensor, idx: &[u32]) -> Result<Tensor> {
    Ok(t.index_select(&Tensor::from_slice(idx, idx.len(), t.device())?, 0)?)
}

/// Rays `idx` of `rays` and their range on each.
fn select(rays: &Rays, range: &Intersection, idx: &[u32]) -> Result<(Rays, Intersection)> {
    let picked = Rays::new(rows(rays.origins(), idx)?, rows(rays.directions(), idx)?)?;
    let range = Intersection {
        near: rows(&range.near, idx)?,
        far: rows(&range.far, idx)?,
        hit: rows(&range.hit, idx)?,
    };
    Ok((picked, range))
}

/// `t` on the host as f64.
fn host(t: &Tensor) -> Result<Vec<f64>> {
    Ok(t.to_dtype(DType::F64)?.to_vec1::<f64>()?)
}

impl SurfaceModel {
    /// The implicit surface (channel 0 of the geometry network).
    fn surface(&self) -> &dyn ImplicitSurface {
        match &self.net {
            Net::Joint(net) => net,
            Net::Dvr { geometry, .. } | Net::Idr { geometry, .. } => geometry,
        }
    }

    /// The range of `rays` in the scene box.
    fn range(&self, rays: &Rays) -> Result<Intersection> {
        let b = self.scene_box;
        ray_aabb(rays, [b[0], b[1], b[2]], [b[3], b[4], b[5]])
    }

    /// The first surface point on each ray, detached: 64 steps and 8 secant steps (DVR),
    /// sphere tracing with that march as the fallback (IDR).
    fn find_surface(&self, rays: &Rays, range: &Intersection) -> Result<Hits> {
        let config = MarchConfig {
            steps: 64,
            secant_steps: 8,
            ..MarchConfig::default()
        };
        match &self.net {
            Net::Joint(_) | Net::Dvr { .. } => march(self.surface(), rays, range, &config),
            Net::Idr { geometry, .. } => sphere_trace(
                geometry,
                rays,
                range,
                &SphereTraceConfig {
                    fallback: config,
                    ..SphereTraceConfig::default()
                },
            ),
        }
    }

    /// The colour at `points: [H, 3]` seen along `dirs: [H, 3]`, and (IDR) the SDF's
    /// gradient there.
    fn shade_points(
        &self,
        points: &Tensor,
        dirs: Option<&Tensor>,
    ) -> Result<(Tensor, Option<Tensor>)> {
        let input = TextureInput {
            view_dirs: dirs,
            ..TextureInput::new(points)
        };
        match &self.net {
            Net::Joint(net) => Ok((net.rgb(&input)?, None)),
            Net::Dvr { texture, .. } => Ok((texture.rgb(&input)?, None)),
            Net::Idr { geometry, render } => {
                let (y, jac) = geometry.forward_with_jacobian(points, None)?;
                let normal = jac.narrow(2, 0, 1)?.squeeze(2)?;
                let feature = y.narrow(1, 1, IDR_FEATURES)?;
                let input = TextureInput {
                    normals: Some(&normal),
                    features: Some(&feature),
                    ..input
                };
                Ok((render.rgb(&input)?, Some(normal)))
            }
        }
    }

    /// The loss of one training step on `N` rays with their colours and mask.
    ///
    /// The rays are marched through the scene box (sphere-traced for IDR), detached;
    /// [`implicit_surface`] makes the hit points `p̂` differentiable. With `S` the rays
    /// that hit inside the mask, each term is a sum over its rays divided by `N` (DVR's
    /// normalisation: a term over few rays does not outweigh the others per ray):
    ///
    /// ```text
    /// total = |S|/N · (L1(c(p̂), C) over S + image_gradient(c, C) over the patches)
    ///   DVR:  + |F|/N · BCE(max_k s(x_k), 0) + |M|/N · BCE(max_k s(x_k), 1)
    ///         + 0.05 · |H|/N · normal_smoothness(p̂)
    ///   IDR:  + 100 · idr_mask(α(progress)) over the rays outside S
    ///         + 0.1 · eikonal(∇f at N/2 points of the box and at p̂)
    /// ```
    ///
    /// where `F` are the rays outside the mask and `M` the mask rays without a surface
    /// point (each in the box), `max_k s(x_k)` the most-inside of 64 samples on a ray
    /// ([`most_inside_along_rays`]: a background ray pushes it out, which removes every
    /// floater on the ray), `H` the rays with a surface point, and IDR's α doubling over
    /// the run ([`AlphaSchedule::default`] at step `2000 · progress`). `seed` draws the
    /// smoothness and eikonal points.
    ///
    /// * `rays`: `N ≥ 1` rays (f32 or f64), a multiple of `patch²` rays in patches when
    ///   [`SurfaceModelConfig::patch`] `≥ 2`;
    /// * `colors: [N, 3]` the target colours, the rays' dtype and device;
    /// * `mask: [N]` float on the rays' device: a ray is inside the object where `≥ ½`;
    /// * `progress ∈ [0, 1]`: the fraction of training done.
    ///
    /// Differentiable w.r.t. the parameters and the rays' origins and directions
    /// (through `p̂` and the samples), so learnable camera poses
    /// ([`crate::camera::pose_rays`]) train with it.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `rays` when there are none or not a multiple of
    /// `patch²`; `colors` unless `[N, 3]` of the rays' dtype and device; `mask` unless a
    /// float `[N]` on their device; `progress` outside `[0, 1]`; errors of the marchers
    /// (naming `directions` for rays whose parameter overflows).
    pub fn loss(
        &self,
        rays: &Rays,
        colors: &Tensor,
        mask: &Tensor,
        progress: f64,
        seed: u64,
    ) -> Result<SurfaceLoss> {
        let n = rays.len();
        let per_patch = if self.patch >= 2 {
            self.patch * self.patch
        } else {
            1
        };
        if n == 0 || !n.is_multiple_of(per_patch) {
            return Err(Error::invalid(
                "rays",
                format!("a positive multiple of {per_patch} rays (whole patches)"),
                n.to_string(),
            ));
        }
        let like = rays.origins();
        check_same(colors, "colors", like, "rays")?;
        check_shape(colors, "colors", &[Dim::Is(n), Dim::Is(3)])?;
        check_float(mask, "mask")?;
        check_shape(mask, "mask", &[Dim::Is(n)])?;
        if !mask.device().same_device(like.device()) {
            return Err(Error::invalid(
                "mask",
                "the rays' device",
                format!("{:?}", mask.device()),
            ));
        }
        if !(0.0..=1.0).contains(&progress) {
            return Err(Error::invalid(
                "progress",
                "a fraction of training in [0, 1]",
                progress.to_string(),
            ));
        }
        let (device, dtype) = (like.device().clone(), like.dtype());
        let mask: Vec<bool> = host(mask)?.iter().map(|&m| m >= 0.5).collect();
        let range = self.range(rays)?;
        let in_box: Vec<bool> = {
            let (near, far) = (host(&range.near)?, host(&range.far)?);
            let hit = range.hit.to_vec1::<u8>()?;
            (0..n).map(|i| hit[i] != 0 && far[i] > near[i]).collect()
        };
        let hits = self.find_surface(rays, &range)?;
        let surf = implicit_surface(self.surface(), rays, &hits, &ImplicitConfig::default())?;
        let hit_rays = surf.indices.to_vec1::<u32>()?;
        let dirs = rays.directions().index_select(&surf.indices, 0)?;
        let (rgb, sdf_gradient) = self.shade_points(&surf.points, Some(&dirs))?;
        // Photometric: rays that hit inside the mask.
        let on: Vec<u32> = hit_rays
            .iter()
            .enumerate()
            .filter(|(_, &r)| mask[r as usize])
            .map(|(k, _)| k as u32)
            .collect();
        let mut photo = Tensor::zeros((), dtype, &device)?;
        if !on.is_empty() {
            let on_rays: Vec<u32> = on.iter().map(|&k| hit_rays[k as usize]).collect();
            photo = photometric_loss(
                &rows(&rgb, &on)?,
                &rows(colors, &on_rays)?,
                None,
                Photometric::L1,
            )?;
        }
        let share = |count: usize| count as f64 / n as f64;
        let photo_scale = share(on.len());
        let mut loss = (&photo * photo_scale)?;
        // DVR's image-gradient loss on the patches that hit inside the mask.
        if !hit_rays.is_empty() && self.patch >= 2 {
            let full = Tensor::zeros((n, 3), dtype, &device)?.index_add(&surf.indices, &rgb, 0)?;
            let mut valid = vec![0u8; n];
            for &r in &hit_rays {
                valid[r as usize] = u8::from(mask[r as usize]);
            }
            let valid = Tensor::from_vec(valid, n, &device)?;
            let gradient = image_gradient_loss(&full, colors, Some(&valid), self.patch)?;
            loss = (loss + (gradient * photo_scale)?)?;
        }
        let surface_hit: Vec<bool> = hits.status.iter().map(|s| s.has_surface()).collect();
        match &self.net {
            Net::Joint(_) | Net::Dvr { .. } => {
                let decoder = self.surface();
                let (mut free, mut missed) = (Vec::new(), Vec::new());
                for r in 0..n {
                    match (mask[r], surface_hit[r]) {
                        (false, _) if in_box[r] => free.push(r as u32),
                        (true, false) if in_box[r] => missed.push(r as u32),
                        _ => {}
                    }
                }
                for (which, target) in [(&free, 0.0), (&missed, 1.0)] {
                    if which.is_empty() {
                        continue;
                    }
                    let (sub, sub_range) = select(rays, &range, which)?;
                    let logits = most_inside_along_rays(decoder, &sub, &sub_range, RAY_SAMPLES)?;
                    let y = Tensor::full(target, which.len(), &device)?.to_dtype(dtype)?;
                    let bce = bce_with_logits(&logits, &y)?.mean_all()?;
                    loss = (loss + (bce * share(which.len()))?)?;
                }
                if !hit_rays.is_empty() {
                    let smooth =
                        normal_smoothness_loss(decoder, &surf.points.detach(), 1e-3, seed ^ 2)?;
                    loss = (loss + (smooth * (0.05 * share(hit_rays.len())))?)?;
                }
            }
            Net::Idr { geometry, .. } => {
                // Mask loss on the rays outside hit ∧ mask.
                let outside: Vec<u32> = (0..n)
                    .filter(|&r| in_box[r] && !(surface_hit[r] && mask[r]))
                    .map(|r| r as u32)
                    .collect();
                if !outside.is_empty() {
                    let (sub, sub_range) = select(rays, &range, &outside)?;
                    let values = most_inside_along_rays(geometry, &sub, &sub_range, RAY_SAMPLES)?;
                    let target: Vec<f64> = outside
                        .iter()
                        .map(|&r| f64::from(u8::from(mask[r as usize])))
                        .collect();
                    let target =
                        Tensor::from_vec(target, outside.len(), &device)?.to_dtype(dtype)?;
                    let alpha = AlphaSchedule::default().alpha_at((progress * 2000.0) as usize);
                    let m = idr_mask_loss(&values, &target, geometry.inside(), alpha, n)?;
                    loss = (loss + (m * 100.0)?)?;
                }
                // Eikonal at random points of the box and at the surface points.
                let b = self.scene_box;
                let mut rng = SplitMix64::new(seed ^ 3);
                let (lo, hi) = (b[0].min(b[1]).min(b[2]), b[3].max(b[4]).max(b[5]));
                let p = rng.uniform_tensor(&[(n / 2).max(1), 3], lo, hi, dtype, &device)?;
                let (_, g) = geometry.value_and_grad(&p)?;
                let mut grads = vec![g];
                grads.extend(sdf_gradient);
                let eik = eikonal_loss(&Tensor::cat(&grads, 0)?)?;
                loss = (loss + (eik * 0.1)?)?;
            }
        }
        Ok(SurfaceLoss {
            total: loss,
            photometric: photo,
        })
    }

    /// The scene along `N` rays (f32 or f64), without graph: the first surface point in
    /// the scene box (marched as in [`SurfaceModel::loss`]), its colour seen along the
    /// ray, on white where nothing is hit, and its outward normal. For evaluation:
    /// whole images through `volume::render_image` (feature `volume`), or the renderer
    /// of [`crate::camera::register_poses`].
    ///
    /// # Errors
    /// Errors of the marchers: [`Error::InvalidArgument`] naming `directions` for rays
    /// whose parameter overflows.
    pub fn shade(&self, rays: &Rays) -> Result<SurfaceShading> {
        let (n, dtype) = (rays.len(), rays.origins().dtype());
        let device = rays.origins().device();
        let hits = self.find_surface(rays, &self.range(rays)?)?;
        let hit_rays = hits.surface_indices();
        let coverage = hits.mask.to_dtype(dtype)?;
        let mut rgb = Tensor::ones((n, 3), dtype, device)?;
        let mut normals = Tensor::zeros((n, 3), dtype, device)?;
        if !hit_rays.is_empty() {
            let idx = Tensor::from_vec(hit_rays.clone(), hit_rays.len(), device)?;
            let points = hits.points.index_select(&idx, 0)?;
            let dirs = rays.directions().index_select(&idx, 0)?;
            let (colour, gradient) = self.shade_points(&points, Some(&dirs))?;
            // IDR's shading has already formed the SDF's gradient; DVR's has not.
            let g = match gradient {
                Some(g) => g,
                None => self.surface().value_and_grad(&points)?.1,
            }
            .detach();
            let length = g
                .sqr()?
                .sum_keepdim(1)?
                .sqrt()?
                .clamp(1e-12, f64::INFINITY)?;
            // Outward normals: towards decreasing occupancy, increasing distance.
            let unit = (g.broadcast_div(&length)? * -self.surface().inside().sign())?;
            let on_white = rgb.zeros_like()?.index_add(&idx, &colour.detach(), 0)?;
            let covered = coverage.unsqueeze(1)?.broadcast_as((n, 3))?.ne(0.0)?;
            rgb = covered.where_cond(&on_white, &rgb)?;
            normals = normals.index_add(&idx, &unit, 0)?;
        }
        Ok(SurfaceShading {
            rgb,
            depth: hits.depth,
            coverage,
            normals,
        })
    }
}

impl ImplicitSurface for SurfaceModel {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        self.surface().value(points)
    }

    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        self.surface().value_and_grad(points)
    }

    fn inside(&self) -> Inside {
        self.surface().inside()
    }
}

impl TextureField for SurfaceModel {
    /// The colour `[N, 3]` at `input.points` seen along `input.view_dirs` (read by IDR's
    /// rendering network unless [`RenderInputs::NoView`]), the normal and feature from
    /// the geometry network; other inputs are not read.
    fn rgb(&self, input: &TextureInput) -> Result<Tensor> {
        Ok(self.shade_points(input.points, input.view_dirs)?.0)
    }
}
