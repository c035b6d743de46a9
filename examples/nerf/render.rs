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
    pub(super) args: &'a Args,
}

impl Renderer<'_> {
    /// Renders `rays` composited on `background: [R, 3]`; also returns the number of
    /// samples that went through the full network and the interlevel loss. `seed`:
    /// jitter (training) or none.
    pub(super) fn render(
        &self,
        rays: &Rays,
        background: &Tensor,
        seed: Option<u64>,
    ) -> Result<(Composite, usize, Tensor)> {
        let config = CompositeConfig {
            background: Some(background.clone()),
            ..CompositeConfig::default()
        };
        let mut levels = Vec::new();
        let mut interlevel = Tensor::zeros((), rays.origins().dtype(), rays.origins().device())?;
        let [x0, y0, z0, x1, y1, z1] = self.aabb;
        let intervals = match self.grid {
            Some(grid) => {
                // Only the samples in occupied cells that are still visible (T ≥ 1e-4)
                // reach the whole network; training shifts each ray's step lattice.
                let march = GridMarchConfig {
                    step_size: self.step_size,
                    jitter: seed.filter(|_| self.args.march_jitter),
                    ..GridMarchConfig::default()
                };
                let mut density = |p: &Tensor| self.net.density(p);
                grid.sample(rays, &march, Some(&mut density))?.intervals
            }
            None if !self.proposals.is_empty() => {
                let hit = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
                let mut coarse = |p: &Tensor| proposal_density(&self.proposals[0], p);
                let mut fine = |p: &Tensor| proposal_density(&self.proposals[1], p);
                let proposal = ProposalConfig {
                    samples: self.args.proposal_samples.to_vec(),
                    final_samples: self.args.samples,
                    alpha_threshold: self.args.alpha_threshold,
                    ..ProposalConfig::default()
                };
                // With --alpha-threshold > 0 the field's density (no graph) culls the
                // samples and gives the interlevel loss its target weights.
                let mut field = |p: &Tensor| self.net.density(p);
                let cull = (self.args.alpha_threshold > 0.0).then_some(&mut field as _);
                let mut proposals: [DensityFn; 2] = [&mut coarse, &mut fine];
                let out = proposal_sample(
                    rays,
                    &hit.near,
                    &hit.far,
                    &mut proposals,
                    &proposal,
                    seed,
                    cull,
                )?;
                match out.interlevel {
                    Some(loss) => interlevel = loss,
                    None => levels = out.levels,
                }
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
        // Midpoints, or (--encoding ipe) the intervals' conical frustums.
        let positions = self.net.sample_inputs(rays, &intervals)?;
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
        // The proposals learn from the interlevel loss against the field's weights.
        if !levels.is_empty() {
            let weights = render_weights(&sigma, &intervals, Some(rays), &config)?.weights;
            for level in &levels {
                interlevel = (interlevel + interlevel_loss(level, &intervals, &weights)?)?;
            }
        }
        let out = composite(&sigma, &rgb, &intervals, Some(rays), &config)?;
        Ok((out, n, interlevel))
    }

    /// View `v` of `data`, `k × k` rays per pixel through `filter`: colour `[H, W, 3]`,
    /// depth `[H, W]` (NaN where the opacity is below 0.5), opacity `[H, W]`.
    pub(super) fn render_view(
        &self,
        data: &Dataset,
        v: usize,
        k: usize,
        filter: PixelFilter,
    ) -> Result<[Tensor; 3]> {
        let bg = data.background().eval_color().map(|c| c as f32);
        let bg = Tensor::new(&bg, &Device::Cpu)?.unsqueeze(0)?;
        let config = ImageConfig {
            supersample: k,
            filter,
            chunk: CHUNK,
        };
        let cam = data.views()[v].camera();
        let [color, depth, opacity] =
            render_image(cam, &config, &Device::Cpu, DType::F32, |rays| {
                let background = bg.broadcast_as((rays.len(), 3))?.contiguous()?;
                let (out, _, _) = self.render(rays, &background, None)?;
                let depth = out.normalized_depth(1e-6)?;
                Ok([out.color, depth, out.opacity])
            })?;
        let nan = Tensor::full(f32::NAN, depth.shape(), depth.device())?;
        Ok([color, opacity.ge(0.5)?.where_cond(&depth, &nan)?, opacity])
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
    let rays = patch_rays(&unseen, K, seed, &Device::Cpu, DType::F32)?;
    let n = PATCHES * K * K;
    let black = Tensor::zeros((n, 3), DType::F32, &Device::Cpu)?;
    let (out, _, _) = r.render(&rays, &black, Some(seed))?;
    let depth = out.normalized_depth(1e-6)?.reshape((PATCHES, K, K))?;
    // Each pixel weighted by its own opacity, detached: pixels of empty space (whose
    // normalised depth means nothing) do not smooth their neighbours.
    let opacity = out.opacity.detach().reshape((PATCHES, K, K))?;
    Ok(depth_smoothness(&depth, Some(&opacity))?.mean_all()?)
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
