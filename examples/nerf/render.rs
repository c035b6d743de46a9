//! The nerf example's renderer: the network behind one of the three samplers (the
//! occupancy grid, stratified samples, proposal networks), RegNeRF's unseen-view patches,
//! and the evaluation on held-out views.

use super::*;

/// The renderer: the network, its sampler and the scene box.
#[derive(Clone, Copy)]
pub(super) struct Renderer<'a> {
    pub(super) net: &'a Nerf,
    pub(super) grid: Option<&'a OccupancyGrid>,
    pub(super) proposals: &'a [Mlp],
    /// RegNeRF's annealed near/far at this training step (stratified sampler).
    pub(super) anneal: Option<usize>,
    pub(super) aabb: [f64; 6],
    pub(super) step_size: f64,
    /// `--scene unbounded`: the frame in which the field sees contracted space.
    pub(super) unbounded: Option<SceneFrame>,
    pub(super) args: &'a Args,
    /// `--device`: where the networks, rays and renders live.
    pub(super) device: &'a Device,
}

/// Near and far of an unbounded scene's rays, in [`SceneFrame`] units (the cameras lie
/// in the unit ball): sampled linearly to 1, then in disparity ([`Spacing`]).
const UNBOUNDED_NEAR: f64 = 0.05;
const UNBOUNDED_FAR: f64 = 1e6;
/// The occupancy grid's levels in an unbounded scene: level `l` covers the frame's cube
/// `±2^l`, the last `±16` (the content past it is drawn on its outer cells).
pub(super) const UNBOUNDED_GRID_LEVELS: usize = 5;
/// The grid march's cone angle in an unbounded scene: steps of `t/256` once that passes
/// the base step (instant-NGP's value for large scenes).
const UNBOUNDED_CONE_ANGLE: f64 = 1.0 / 256.0;
/// mip-NeRF 360's weight of the distortion loss.
const DISTORTION_WEIGHT: f64 = 0.01;

/// An unbounded scene's frame: `x ↦ (x − centre)·scale` puts every training camera in the
/// unit ball, and the networks see [`contract`] of that (radius < 2).
#[derive(Clone, Copy, Debug)]
pub(super) struct SceneFrame {
    centre: [f64; 3],
    scale: f64,
}

impl SceneFrame {
    /// Centred on the cameras' mean position, scaled so that the farthest is at 1.
    pub(super) fn from_cameras(cameras: &[Camera]) -> Self {
        let n = cameras.len().max(1) as f64;
        let centres: Vec<_> = cameras
            .iter()
            .map(|c| c.cam_to_world().translation)
            .collect();
        let mean = centres.iter().fold(glam::DVec3::ZERO, |a, &c| a + c) / n;
        let radius = centres
            .iter()
            .map(|&c| (c - mean).length())
            .fold(0.0, f64::max);
        SceneFrame {
            centre: mean.to_array(),
            scale: if radius > 0.0 { 1.0 / radius } else { 1.0 },
        }
    }

    /// The rays in the frame: origins `(o − centre)·scale`, directions and cone radii as
    /// they are (the parameter `t` is then in frame units, and so is each cone's radius
    /// per unit `t`).
    fn rays(&self, rays: &Rays) -> Result<Rays> {
        let c = Tensor::new(&[self.centre], rays.origins().device())?
            .to_dtype(rays.origins().dtype())?;
        let o = (rays.origins().broadcast_sub(&c)? * self.scale)?;
        let framed = Rays::new(o, rays.directions().clone())?;
        match rays.radii() {
            Some(r) => framed.with_radii(r.clone()),
            None => Ok(framed),
        }
    }
}

/// What the networks see of frame-space rows `[N, 3]` points or `[N, 6]` Gaussians
/// `[μ, σ²]`: their contraction (mip-NeRF 360), the Gaussians' diagonal covariances
/// pushed through its Jacobian.
fn contracted(rows: &Tensor) -> Result<Tensor> {
    if rows.dim(1)? == 6 {
        let (mean, var) = (rows.narrow(1, 0, 3)?, rows.narrow(1, 3, 3)?);
        let (m, v) = contract(&mean, Some(&var))?;
        let v = v.expect("covariances in, covariances out"); // invariant
        return Ok(Tensor::cat(&[m, v], 1)?);
    }
    Ok(contract(rows, None)?.0)
}

/// The occupancy grid's cells per side.
pub(super) const GRID_RESOLUTION: usize = 64;

impl Renderer<'_> {
    /// What the networks see of points `[N, 3]` or Gaussians `[N, 6]`: the rows
    /// themselves, or in an unbounded scene their contraction ([`contracted`]).
    fn space(&self, rows: &Tensor) -> Result<Tensor> {
        match self.unbounded {
            Some(_) => contracted(rows),
            None => Ok(rows.clone()),
        }
    }

    /// The field's density at points `[N, 3]` (in an unbounded scene, frame points,
    /// contracted first) as the occupancy grid sees it: with the integrated encoding
    /// (`--encoding ipe`), of Gaussians the size of a grid cell of the network's box
    /// (variance `cell²/12` per axis), since a point reads octaves no cone trained.
    pub(super) fn grid_density(&self, p: &Tensor) -> Result<Tensor> {
        let p = self.space(p)?;
        if self.args.encoding() != Encoding::Ipe {
            return self.net.density(&p);
        }
        let var: Vec<f64> = (0..3)
            .map(|a| ((self.aabb[a + 3] - self.aabb[a]) / GRID_RESOLUTION as f64).powi(2) / 12.0)
            .collect();
        let var = Tensor::new(var.as_slice(), p.device())?
            .to_dtype(p.dtype())?
            .unsqueeze(0)?
            .broadcast_as(p.shape())?;
        self.net.density(&Tensor::cat(&[&p, &var], 1)?)
    }
}

impl Renderer<'_> {
    /// The intervals of `rays` (frame space) that are still visible, transmittance
    /// `T ≥ 1e-4` ([`DEFAULT_TERMINATION_EPS`]), under the field's density (no graph) at
    /// the inputs the renderer gives it: the intervals' conical frustums with
    /// `--encoding ipe`.
    fn visible(&self, rays: &Rays, intervals: Intervals) -> Result<Intervals> {
        if intervals.starts.elem_count() == 0 {
            return Ok(intervals);
        }
        let inputs = self.space(&self.net.sample_inputs(rays, &intervals)?)?;
        let sigma = self.net.density(&inputs)?.detach();
        let w = render_weights(&sigma, &intervals, Some(rays), &CompositeConfig::default())?;
        let keep = w.transmittance.ge(DEFAULT_TERMINATION_EPS)?;
        Ok(intervals.retain(&keep)?.0)
    }
}

/// `x` forward, its gradient times `s` backward (`s` broadcastable to `x`'s shape, e.g.
/// `[M, 1]` against colours `[M, 3]`; no gradient reaches `s`): `x·s + x·(1 − s)` with
/// the second term detached.
pub(super) fn scale_gradient(x: &Tensor, s: &Tensor) -> Result<Tensor> {
    let s = s.detach().broadcast_as(x.shape())?;
    let kept = x.mul(&s)?;
    let frozen = x.mul(&s.affine(-1.0, 1.0)?)?.detach();
    Ok((kept + frozen)?)
}

/// What a renderer's sampler gives for a batch of rays ([`Renderer::render`]).
pub(super) struct Samples {
    /// The rays the intervals lie on: the batch's, or in an unbounded scene the same
    /// rays in the scene's frame.
    pub(super) rays: Rays,
    pub(super) intervals: Intervals,
    /// The proposal networks' levels, for the interlevel loss against the field's weights.
    levels: Vec<(Intervals, Tensor)>,
    /// The proposal sampler's near, far and spacing.
    near_far: Option<(Tensor, Tensor, Spacing)>,
    /// The interlevel loss the sampler computed itself (a scalar, zero without one).
    interlevel: Tensor,
}

impl Renderer<'_> {
    /// The intervals the sampler places along `rays` (in an unbounded scene, along the
    /// rays in the scene's frame, which it returns), with the proposal levels, the
    /// proposal sampler's near/far and spacing, and the interlevel loss.
    pub(super) fn samples(&self, rays: &Rays, seed: Option<u64>) -> Result<Samples> {
        let mut levels = Vec::new();
        let mut interlevel = Tensor::zeros((), rays.origins().dtype(), rays.origins().device())?;
        let [x0, y0, z0, x1, y1, z1] = self.aabb;
        let framed;
        let rays = match &self.unbounded {
            Some(frame) => {
                framed = frame.rays(rays)?;
                &framed
            }
            None => rays,
        };
        let mut near_far = None;
        let intervals = match self.grid {
            Some(grid) => {
                // Only the samples in occupied cells that are still visible (T ≥ 1e-4)
                // reach the whole network; training shifts each ray's step lattice.
                // In an unbounded scene the march starts near the camera and its steps
                // grow with the distance (cone stepping) through the grid's levels. (No
                // opacity threshold: at the initial density every short step is below
                // one, and a run that drops them all never trains.)
                let (near, cone_angle) = match self.unbounded {
                    Some(_) => (UNBOUNDED_NEAR, UNBOUNDED_CONE_ANGLE),
                    None => (0.0, 0.0),
                };
                let march = GridMarchConfig {
                    near,
                    step_size: self.step_size,
                    cone_angle,
                    jitter: seed.filter(|_| self.args.march_jitter()),
                    ..GridMarchConfig::default()
                };
                if self.args.encoding() == Encoding::Ipe {
                    // The visibility pass on the rays' own cones: the cell-sized Gaussians
                    // the grid reads blur the surface, and their transmittance dropped
                    // samples of the surface that the cones resolve.
                    let all = grid.sample(rays, &march, None)?.intervals;
                    self.visible(rays, all)?
                } else {
                    let mut density = |p: &Tensor| self.grid_density(p);
                    grid.sample(rays, &march, Some(&mut density))?.intervals
                }
            }
            None if !self.proposals.is_empty() => {
                let (near, far, spacing) = match self.unbounded {
                    Some(_) => {
                        let full = |v: f64| -> Result<Tensor> {
                            Ok(Tensor::full(v, rays.len(), rays.origins().device())?
                                .to_dtype(rays.origins().dtype())?)
                        };
                        (
                            full(UNBOUNDED_NEAR)?,
                            full(UNBOUNDED_FAR)?,
                            Spacing::LinearDisparity,
                        )
                    }
                    None => {
                        let hit = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
                        (hit.near, hit.far, Spacing::Linear)
                    }
                };
                let mut coarse = |p: &Tensor| proposal_density(&self.proposals[0], &self.space(p)?);
                let mut fine = |p: &Tensor| proposal_density(&self.proposals[1], &self.space(p)?);
                let proposal = ProposalConfig {
                    spacing,
                    samples: self.args.proposal_samples.to_vec(),
                    final_samples: self.args.samples,
                    alpha_threshold: self.args.alpha_threshold,
                    ..ProposalConfig::default()
                };
                // With --alpha-threshold > 0 the field's density (no graph) culls the
                // samples and gives the interlevel loss its target weights. An unbounded
                // scene keeps every sample: its distortion loss needs whole rays.
                let mut field = |p: &Tensor| self.net.density(&self.space(p)?);
                let cull = (self.args.alpha_threshold > 0.0 && self.unbounded.is_none())
                    .then_some(&mut field as _);
                let mut proposals: [DensityFn; 2] = [&mut coarse, &mut fine];
                let out =
                    proposal_sample(rays, &near, &far, &mut proposals, &proposal, seed, cull)?;
                match out.interlevel {
                    Some(loss) => interlevel = loss,
                    None => levels = out.levels,
                }
                near_far = Some((near, far, spacing));
                out.intervals
            }
            None => {
                let hit = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
                let jitter = if seed.is_some() {
                    Jitter::PerSample
                } else {
                    Jitter::None
                };
                let (near, far) = match self.anneal {
                    Some(step) => anneal_near_far(
                        &hit.near,
                        &hit.far,
                        step,
                        256,
                        ANNEAL_P_START,
                        ANNEAL_MID_RATIO,
                    )?,
                    None => (hit.near, hit.far),
                };
                stratified(&near, &far, self.args.samples, jitter, seed.unwrap_or(0))?
            }
        };
        Ok(Samples {
            rays: rays.clone(),
            intervals,
            levels,
            near_far,
            interlevel,
        })
    }

    /// Whether training may take [`Nerf::color_loss`] of the sampler's intervals (one
    /// fused op where the device and encodings allow): a bounded scene without proposal
    /// networks, whose loss is the photometric one alone.
    pub(super) fn plain(&self) -> bool {
        self.unbounded.is_none() && self.proposals.is_empty()
    }

    /// Renders `rays` composited on `background: [R, 3]`; also returns the number of
    /// samples that went through the full network and the auxiliary loss (interlevel,
    /// and in an unbounded scene the weighted distortion loss). `seed`: jitter (training)
    /// or none.
    pub(super) fn render(
        &self,
        rays: &Rays,
        background: &Tensor,
        seed: Option<u64>,
    ) -> Result<(Composite, usize, Tensor)> {
        self.render_samples(self.samples(rays, seed)?, background)
    }

    /// [`Renderer::render`] of the intervals `samples` that [`Renderer::samples`] placed.
    pub(super) fn render_samples(
        &self,
        samples: Samples,
        background: &Tensor,
    ) -> Result<(Composite, usize, Tensor)> {
        let config = CompositeConfig {
            background: Some(background.clone()),
            ..CompositeConfig::default()
        };
        let Samples {
            rays,
            intervals,
            levels,
            near_far,
            mut interlevel,
        } = samples;
        let rays = &rays;
        // Midpoints, or (--encoding ipe) the intervals' conical frustums.
        let positions = self.space(&self.net.sample_inputs(rays, &intervals)?)?;
        let dirs = intervals.directions(rays)?.reshape(((), 3))?;
        let n = positions.dim(0)?;
        let (sigma, rgb) = self.net.radiance(&positions, &dirs)?;
        let (sigma, rgb) = match &intervals.layout {
            Layout::Batched => {
                let (r, s) = intervals.starts.dims2()?;
                (sigma.reshape((r, s))?, rgb.reshape((r, s, 3))?)
            }
            Layout::Packed(_) => (sigma, rgb),
        };
        // Unbounded, --gradient-scaling on: each sample's gradients scaled by
        // min(1, t²) (t in frame units), so that density next to a training camera
        // (a floater that explains that one view) learns slower than the scene.
        let (sigma, rgb) = match self.unbounded {
            Some(_) if self.args.gradient_scaling => {
                let t = ((&intervals.starts + &intervals.ends)? * 0.5)?;
                let s = t.sqr()?.minimum(1.0)?;
                let rgb = scale_gradient(&rgb, &s.unsqueeze(s.rank())?)?;
                (scale_gradient(&sigma, &s)?, rgb)
            }
            _ => (sigma, rgb),
        };
        // The proposals learn from the interlevel loss against the field's weights.
        if !levels.is_empty() {
            let weights = render_weights(&sigma, &intervals, Some(rays), &config)?.weights;
            for level in &levels {
                interlevel = (interlevel + interlevel_loss(level, &intervals, &weights)?)?;
            }
            // Unbounded: mip-NeRF 360's distortion loss on the intervals in s-space.
            if let (Some(_), Some((near, far, spacing))) = (&self.unbounded, &near_far) {
                let s = Intervals::new(
                    spacing.normalize(&intervals.starts, near, far)?,
                    spacing.normalize(&intervals.ends, near, far)?,
                    Layout::Batched,
                )?;
                let distortion = distortion_loss(&weights, &s)?.mean_all()?;
                interlevel = (interlevel + (distortion * DISTORTION_WEIGHT)?)?;
            }
        }
        let out = composite(&sigma, &rgb, &intervals, Some(rays), &config)?;
        Ok((out, n, interlevel))
    }

    /// View `v` of `data`, `k × k` rays per pixel through `filter`, rendered on the
    /// renderer's device and returned on the CPU: colour `[H, W, 3]`, depth `[H, W]` (NaN
    /// where the opacity is below 0.5), opacity `[H, W]`.
    pub(super) fn render_view(
        &self,
        data: &Dataset,
        v: usize,
        k: usize,
        filter: PixelFilter,
    ) -> Result<[Tensor; 3]> {
        let bg = data.background().eval_color().map(|c| c as f32);
        let bg = Tensor::new(&bg, self.device)?.unsqueeze(0)?;
        let config = ImageConfig {
            supersample: k,
            filter,
            chunk: CHUNK,
        };
        let cam = data.views()[v].camera();
        let [color, depth, opacity] =
            render_image(cam, &config, self.device, DType::F32, |rays| {
                let background = bg.broadcast_as((rays.len(), 3))?.contiguous()?;
                let (out, _, _) = self.render(rays, &background, None)?;
                let depth = out.normalized_depth(1e-6)?;
                Ok([out.color, depth, out.opacity])
            })?;
        let nan = Tensor::full(f32::NAN, depth.shape(), depth.device())?;
        let depth = opacity.ge(0.5)?.where_cond(&depth, &nan)?;
        // Metrics and pictures are computed on the host.
        let host = |t: Tensor| t.to_device(&Device::Cpu);
        Ok([host(color)?, host(depth)?, host(opacity)?])
    }
}

/// A proposal network: 2 × 32 ReLU on a frequency encoding (L = 6), density
/// `trunc_exp(raw − 1)`.
pub(super) fn proposal_net(vb: VarBuilder) -> Result<Mlp> {
    let encoding = PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?);
    mlp(
        &MlpConfig {
            hidden: 32,
            depth: 2,
            encoding,
            ..MlpConfig::default()
        },
        vb,
    )
}

pub(super) fn proposal_density(net: &Mlp, points: &Tensor) -> Result<Tensor> {
    let raw = neural_fields::field::Field::forward(net, points)?.squeeze(1)?;
    trunc_exp(&(raw - 1.0)?)
}

/// RegNeRF's regulariser: the mean depth smoothness of 16 patches of 8 × 8 pixels, each
/// rendered from a random camera around the training cameras ([`cameras_around`]),
/// weighted by the detached opacity as in RegNeRF's DTU configuration.
pub(super) fn regnerf_depth_smoothness(
    r: &Renderer,
    cameras: &[Camera],
    seed: u64,
) -> Result<Tensor> {
    const PATCHES: usize = 16;
    const K: usize = 8;
    let unseen = cameras_around(cameras, PATCHES, seed)?;
    let rays = patch_rays(&unseen, K, seed, r.device, DType::F32)?;
    let n = PATCHES * K * K;
    let black = Tensor::zeros((n, 3), DType::F32, r.device)?;
    let (out, _, _) = r.render(&rays, &black, Some(seed))?;
    let depth = out.normalized_depth(1e-6)?.reshape((PATCHES, K, K))?;
    // Each pixel weighted by its own opacity, detached: pixels of empty space (whose
    // normalised depth means nothing) do not smooth their neighbours.
    let opacity = out.opacity.detach().reshape((PATCHES, K, K))?;
    Ok(depth_smoothness(&depth, Some(&opacity))?.mean_all()?)
}

/// The mean held-out PSNR of an empty scene over the first `n` views of `eval`: each
/// view's truth against its background colour alone, what a field that has learned
/// nothing visible renders.
pub(super) fn empty_psnr(eval: &Dataset, n: usize) -> Result<f64> {
    let n = n.min(eval.views().len());
    let bg = eval.background().eval_color();
    let color = Tensor::new(&bg.map(|c| c as f32), &Device::Cpu)?;
    let mut p = 0.0;
    for view in &eval.views()[..n] {
        let truth = view.rgb(bg, &Device::Cpu, DType::F32)?;
        p += psnr(&color.broadcast_as(truth.shape())?, &truth, None)?;
    }
    Ok(p / n.max(1) as f64)
}

/// PSNR and SSIM of the first `n` views of `eval` (means), and the renders
/// `[truth, colour, depth, opacity]`.
pub(super) fn evaluate(
    r: &Renderer,
    eval: &Dataset,
    n: usize,
) -> Result<(f64, f64, Vec<[Tensor; 4]>)> {
    let (mut p, mut s, mut renders) = (0.0, 0.0, Vec::new());
    let n = n.min(eval.views().len());
    for v in 0..n {
        // The truth on the host, where `render_view` returns its renders.
        let truth =
            eval.views()[v].rgb(eval.background().eval_color(), &Device::Cpu, DType::F32)?;
        let [color, depth, opacity] =
            r.render_view(eval, v, r.args.eval_supersample, r.args.pixel_filter())?;
        p += psnr(&color, &truth, None)?;
        s += ssim(&color, &truth, None)?;
        renders.push([truth, color, depth, opacity]);
    }
    Ok((p / n as f64, s / n as f64, renders))
}
