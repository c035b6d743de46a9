//! The CUDA path of [`FusedNerfLoss`] (`sources::NERF_LOSS`): the encodings and the
//! per-ray compositing and loss as kernels, both networks' matrix products (forward,
//! weight gradients, input gradients) through cuBLAS on candle's stream, and the bias
//! gradients as products with a column of ones. Like the CPU op, the forward pass
//! computes the loss and the parameter gradient and keeps the gradient for the backward
//! pass; the loss and the opacity statistics are read back once per call.

use super::{FusedNerfLoss, RowEncode};
use crate::kernels::activation::Act;
use crate::kernels::cuda::{
    function, launch, launch_1d, sources, uninit, upload, view, zeros, GpuReal,
};
use crate::kernels::mlp::FusedMlp;
use crate::kernels::nerf_loss::Density;
use candle_core::backend::BackendStorage;
use candle_core::cuda::cudarc::cublas::sys::cublasOperation_t;
use candle_core::cuda::cudarc::cublas::{CudaBlas, Gemm, GemmConfig};
use candle_core::cuda::cudarc::driver::{
    CudaSlice, CudaView, DevicePtr, DevicePtrMut, LaunchConfig, PushKernelArg,
};
use candle_core::{CudaDevice, CudaStorage, Layout, Shape};

/// `C = α·op(A)·op(B) + β·C` in cuBLAS's column-major terms (`ta`/`tb`: transpose).
#[allow(clippy::too_many_arguments)]
fn gemm<T: GpuReal, A: DevicePtr<T>, B: DevicePtr<T>, C: DevicePtrMut<T>>(
    blas: &CudaBlas,
    (ta, tb): (bool, bool),
    (m, n, k): (usize, usize, usize),
    alpha: f64,
    (a, lda): (&A, usize),
    (b, ldb): (&B, usize),
    beta: f64,
    (c, ldc): (&mut C, usize),
) -> candle_core::Result<()>
where
    CudaBlas: Gemm<T>,
{
    let op = |t: bool| {
        if t {
            cublasOperation_t::CUBLAS_OP_T
        } else {
            cublasOperation_t::CUBLAS_OP_N
        }
    };
    let int = |v: usize| {
        i32::try_from(v).map_err(|_| {
            candle_core::Error::Msg(format!("fused NeRF loss: {v} exceeds cuBLAS's sizes"))
        })
    };
    let cfg = GemmConfig {
        transa: op(ta),
        transb: op(tb),
        m: int(m)?,
        n: int(n)?,
        k: int(k)?,
        alpha: T::from_f64(alpha),
        lda: int(lda)?,
        ldb: int(ldb)?,
        beta: T::from_f64(beta),
        ldc: int(ldc)?,
    };
    // SAFETY: every operand is a view of at least the extent its (m, n, k, ld) describe:
    // the callers pass the layers' weight blocks of the flat parameters and the
    // activation buffers of `m` rows allocated for those widths.
    unsafe { blas.gemm(cfg, a, b, c) }
        .map_err(|e| candle_core::Error::Msg(format!("fused NeRF loss: cuBLAS: {e:?}")))
}

/// The kernels' activation code and softplus slope.
fn act_code(act: Act) -> (i32, f64) {
    match act {
        Act::Relu => (0, 1.0),
        Act::Softplus(beta) => (1, beta),
    }
}

/// One network's forward activations: each layer's pre-activation `z` (the last one is
/// the output) and each hidden layer's activation.
struct Activations<T> {
    z: Vec<CudaSlice<T>>,
    a: Vec<CudaSlice<T>>,
}

/// What every launch of one call shares.
struct Ctx<'a> {
    dev: &'a CudaDevice,
    blas: &'a CudaBlas,
    m: usize,
}

fn forward<T: GpuReal>(
    cx: &Ctx<'_>,
    net: &FusedMlp,
    a0: &CudaSlice<T>,
    params: &CudaView<'_, T>,
) -> candle_core::Result<Activations<T>>
where
    CudaBlas: Gemm<T>,
{
    let m = cx.m;
    let (act, beta) = act_code(net.act);
    let last = net.layers.len() - 1;
    let mut acts = Activations {
        z: Vec::with_capacity(net.layers.len()),
        a: Vec::with_capacity(last),
    };
    let f = function::<T>(cx.dev, "nerf_loss", sources::NERF_LOSS, "nf_nl_bias_act")?;
    for (l, layer) in net.layers.iter().enumerate() {
        let (w, b) = net.offsets[l];
        // Written in full by the product (β = 0).
        let mut z = uninit::<T>(cx.dev, m * layer.out)?;
        let op = (true, false);
        if l == 0 {
            let wv = params.slice(w..);
            gemm::<T, _, _, _>(
                cx.blas,
                op,
                (layer.out, m, net.a0),
                1.0,
                (&wv, layer.input),
                (a0, net.a0),
                0.0,
                (&mut z, layer.out),
            )?;
        } else {
            let p_w = net.layers[l - 1].out;
            let scale = if layer.skip {
                std::f64::consts::FRAC_1_SQRT_2
            } else {
                1.0
            };
            let wv = params.slice(w..);
            gemm::<T, _, _, _>(
                cx.blas,
                op,
                (layer.out, m, p_w),
                scale,
                (&wv, layer.input),
                (&acts.a[l - 1], p_w),
                0.0,
                (&mut z, layer.out),
            )?;
            if layer.skip {
                let wv = params.slice(w + p_w..);
                gemm::<T, _, _, _>(
                    cx.blas,
                    op,
                    (layer.out, m, net.a0),
                    scale,
                    (&wv, layer.input),
                    (a0, net.a0),
                    1.0,
                    (&mut z, layer.out),
                )?;
            }
        }
        let hidden = l < last;
        // Written in full by the bias pass (not read after the last layer).
        let mut a = uninit::<T>(cx.dev, if hidden { m * layer.out } else { 1 })?;
        let bias = params.slice(b..b + layer.out);
        let (m64, out64, is_last) = (m as u64, layer.out as u64, i32::from(!hidden));
        let mut bld = f.builder();
        bld.arg(&mut z).arg(&mut a).arg(&bias).arg(&m64).arg(&out64);
        bld.arg(&act).arg(&beta).arg(&is_last);
        launch(bld, launch_1d(m * layer.out))?;
        acts.z.push(z);
        if hidden {
            acts.a.push(a);
        }
    }
    Ok(acts)
}

/// The backward pass of one network: `dz` is the output's gradient `[m, out]`; writes
/// the parameter gradient into `gp` (this network's block of the flat gradient) and, when
/// given, adds `∂L/∂a₀` into `ga0`.
#[allow(clippy::too_many_arguments)]
fn backward<T: GpuReal>(
    cx: &Ctx<'_>,
    net: &FusedMlp,
    a0: &CudaSlice<T>,
    acts: &Activations<T>,
    params: &CudaView<'_, T>,
    mut dz: CudaSlice<T>,
    gp: &mut CudaSlice<T>,
    gp_start: usize,
    mut ga0: Option<&mut CudaSlice<T>>,
    ones: &CudaSlice<T>,
) -> candle_core::Result<()>
where
    CudaBlas: Gemm<T>,
{
    let m = cx.m;
    let (act, beta) = act_code(net.act);
    let f = function::<T>(cx.dev, "nerf_loss", sources::NERF_LOSS, "nf_nl_act_bwd")?;
    for (l, layer) in net.layers.iter().enumerate().rev() {
        let (w, b) = net.offsets[l];
        let (w, b) = (gp_start + w, gp_start + b);
        let p_w = if l == 0 {
            net.a0
        } else {
            net.layers[l - 1].out
        };
        let scale = if l > 0 && layer.skip {
            std::f64::consts::FRAC_1_SQRT_2
        } else {
            1.0
        };
        // ∂L/∂W = dzᵀ·[a_prev, a₀] (row-major [out, in]), ∂L/∂b = dzᵀ·1.
        {
            let mut gw = gp.slice_mut(w..);
            if l == 0 {
                gemm::<T, _, _, _>(
                    cx.blas,
                    (false, true),
                    (p_w, layer.out, m),
                    1.0,
                    (a0, net.a0),
                    (&dz, layer.out),
                    0.0,
                    (&mut gw, layer.input),
                )?;
            } else {
                gemm::<T, _, _, _>(
                    cx.blas,
                    (false, true),
                    (p_w, layer.out, m),
                    scale,
                    (&acts.a[l - 1], p_w),
                    (&dz, layer.out),
                    0.0,
                    (&mut gw, layer.input),
                )?;
            }
        }
        if l > 0 && layer.skip {
            let mut gw = gp.slice_mut(w + p_w..);
            gemm::<T, _, _, _>(
                cx.blas,
                (false, true),
                (net.a0, layer.out, m),
                scale,
                (a0, net.a0),
                (&dz, layer.out),
                0.0,
                (&mut gw, layer.input),
            )?;
        }
        {
            let mut gb = gp.slice_mut(b..b + layer.out);
            gemm::<T, _, _, _>(
                cx.blas,
                (false, false),
                (layer.out, 1, m),
                1.0,
                (&dz, layer.out),
                (ones, m),
                0.0,
                (&mut gb, layer.out),
            )?;
        }
        // ∂L/∂a₀ of a skip layer and of layer 0 (accumulated), ∂L/∂a_prev.
        let wv_skip = params.slice(w - gp_start + p_w..);
        if l > 0 && layer.skip {
            if let Some(g) = ga0.as_deref_mut() {
                gemm::<T, _, _, _>(
                    cx.blas,
                    (false, false),
                    (net.a0, m, layer.out),
                    scale,
                    (&wv_skip, layer.input),
                    (&dz, layer.out),
                    1.0,
                    (g, net.a0),
                )?;
            }
        }
        let wv = params.slice(w - gp_start..);
        if l == 0 {
            if let Some(g) = ga0.as_deref_mut() {
                gemm::<T, _, _, _>(
                    cx.blas,
                    (false, false),
                    (net.a0, m, layer.out),
                    1.0,
                    (&wv, layer.input),
                    (&dz, layer.out),
                    1.0,
                    (g, net.a0),
                )?;
            }
            break;
        }
        // Written in full by the product (β = 0).
        let mut da = uninit::<T>(cx.dev, m * p_w)?;
        gemm::<T, _, _, _>(
            cx.blas,
            (false, false),
            (p_w, m, layer.out),
            scale,
            (&wv, layer.input),
            (&dz, layer.out),
            0.0,
            (&mut da, p_w),
        )?;
        let n64 = (m * p_w) as u64;
        let mut bld = f.builder();
        bld.arg(&mut da)
            .arg(&acts.z[l - 1])
            .arg(&n64)
            .arg(&act)
            .arg(&beta);
        launch(bld, launch_1d(m * p_w))?;
        dz = da;
    }
    Ok(())
}

impl<E: RowEncode> FusedNerfLoss<E> {
    /// `CustomOp3::cuda_fwd`: the loss `[]`; the parameter gradient is kept for the
    /// backward pass.
    pub(super) fn cuda_loss(
        &self,
        inputs: [(&CudaStorage, &Layout); 3],
    ) -> candle_core::Result<(CudaStorage, Shape)> {
        match inputs[0].0.dtype() {
            candle_core::DType::F32 => self.cuda_run::<f32>(inputs),
            candle_core::DType::F64 => self.cuda_run::<f64>(inputs),
            d => candle_core::bail!("fused NeRF loss: f32 or f64 inputs, got {d:?}"),
        }
    }

    fn cuda_run<T: GpuReal>(
        &self,
        [(s1, l1), (s2, l2), (s3, l3)]: [(&CudaStorage, &Layout); 3],
    ) -> candle_core::Result<(CudaStorage, Shape)>
    where
        CudaBlas: Gemm<T>,
    {
        let name = "fused NeRF loss";
        let dev = s1.device().clone();
        let samples = view::<T>(s1, l1, name, "samples")?;
        let rays = view::<T>(s2, l2, name, "rays")?;
        let params = view::<T>(s3, l3, name, "parameters")?;
        self.check(samples.len(), rays.len(), params.len())?;
        let (trunk, head) = (&self.nets.trunk, &self.nets.head);
        let (wd, t_out, h_in) = self.nets.widths();
        let (pl, pinc) = self.position.frequency_spec();
        let (dl, dinc) = self.direction.frequency_spec();
        let width = |l: usize, inc: bool| 3 * (2 * l + usize::from(inc));
        if width(pl, pinc) != trunk.a0 || width(dl, dinc) != wd || head.out_dim() != 3 {
            candle_core::bail!("{name}: encodings of 3-vectors and a colour head expected");
        }
        let (m, r) = (self.offsets.last().copied().unwrap_or(0), self.n_rays());
        let blas = dev.cublas_handle();
        let cx = Ctx {
            dev: &dev,
            blas: &blas,
            m,
        };
        let kernel = |n: &str| function::<T>(&dev, "nerf_loss", sources::NERF_LOSS, n);
        let offsets: Vec<u64> = self.offsets.iter().map(|&o| o as u64).collect();
        let offsets = upload(&dev, &offsets)?;
        let (m64, r64) = (m as u64, r as u64);

        // Encodings.
        // Every encoding buffer is written in full by its kernel.
        let mut ep = uninit::<T>(&dev, m * trunk.a0)?;
        let (pl64, pinc32, wp64) = (pl as u64, i32::from(pinc), trunk.a0 as u64);
        let f = kernel("nf_nl_encode_positions")?;
        let mut b = f.builder();
        b.arg(&samples)
            .arg(&mut ep)
            .arg(&m64)
            .arg(&pl64)
            .arg(&pinc32)
            .arg(&wp64);
        launch(b, launch_1d(3 * m))?;
        let mut ed = uninit::<T>(&dev, r * wd)?;
        let (dl64, dinc32, wd64) = (dl as u64, i32::from(dinc), wd as u64);
        let f = kernel("nf_nl_encode_directions")?;
        let mut b = f.builder();
        b.arg(&rays)
            .arg(&mut ed)
            .arg(&r64)
            .arg(&dl64)
            .arg(&dinc32)
            .arg(&wd64);
        launch(b, launch_1d(3 * r))?;

        // Both networks forward.
        let (pt, ph) = (
            params.slice(..trunk.n_params),
            params.slice(trunk.n_params..),
        );
        let at = forward(&cx, trunk, &ep, &pt)?;
        let yt =
            at.z.last()
                .ok_or_else(|| candle_core::Error::Msg("empty trunk".into()))?;
        // Every row of every ray's segment is written by the kernel.
        let mut ha0 = uninit::<T>(&dev, m * h_in)?;
        let f64_ = (t_out - 1) as u64;
        let f = kernel("nf_nl_head_input")?;
        let mut b = f.builder();
        b.arg(&ed)
            .arg(yt)
            .arg(&offsets)
            .arg(&wd64)
            .arg(&f64_)
            .arg(&mut ha0);
        launch(
            b,
            LaunchConfig {
                grid_dim: (r.max(1) as u32, 1, 1),
                block_dim: (128, 1, 1),
                shared_mem_bytes: 0,
            },
        )?;
        let ah = forward(&cx, head, &ha0, &ph)?;
        let yh =
            ah.z.last()
                .ok_or_else(|| candle_core::Error::Msg("empty head".into()))?;

        // Compositing, the loss, the raw outputs' gradients.
        let mut gyt = zeros::<T>(&dev, m * t_out)?;
        let mut gyh = zeros::<T>(&dev, m * 3)?;
        // The loss sum, the opacity sum and maximum, and a non-finite flag.
        let mut stats = dev.alloc_zeros::<f64>(4)?;
        let (density, shift) = match self.density {
            Density::TruncExp(s) => (0i32, s),
            Density::Softplus(s) => (1i32, s),
        };
        let (t_out64, opaque) = (t_out as u64, i32::from(self.opaque_last));
        let inv = 1.0 / (3 * r).max(1) as f64;
        let f = kernel("nf_nl_rays")?;
        let mut b = f.builder();
        b.arg(yt)
            .arg(&t_out64)
            .arg(yh)
            .arg(&samples)
            .arg(&rays)
            .arg(&offsets);
        b.arg(&r64).arg(&density).arg(&shift).arg(&opaque).arg(&inv);
        b.arg(&mut gyt).arg(&mut gyh).arg(&mut stats);
        launch(
            b,
            LaunchConfig {
                grid_dim: ((r as u32).div_ceil(64).max(1), 1, 1),
                block_dim: (64, 1, 1),
                shared_mem_bytes: 0,
            },
        )?;

        // Both networks backward, head first (its input's feature columns feed the trunk).
        let mut ones = uninit::<T>(&dev, m)?;
        let f = kernel("nf_nl_ones")?;
        let mut b = f.builder();
        b.arg(&mut ones).arg(&m64);
        launch(b, launch_1d(m))?;
        // Zeroed: with no samples (m = 0) no product writes it.
        let mut gp = zeros::<T>(&dev, params.len())?;
        let mut gha0 = zeros::<T>(&dev, m * h_in)?;
        let gp_head = trunk.n_params;
        backward(
            &cx,
            head,
            &ha0,
            &ah,
            &ph,
            gyh,
            &mut gp,
            gp_head,
            Some(&mut gha0),
            &ones,
        )?;
        let f = kernel("nf_nl_feature_grad")?;
        let mut b = f.builder();
        b.arg(&gha0).arg(&mut gyt).arg(&m64).arg(&wd64).arg(&f64_);
        launch(b, launch_1d(m * (t_out - 1)))?;
        backward(&cx, trunk, &ep, &at, &pt, gyt, &mut gp, 0, None, &ones)?;

        // Read back the loss and the statistics (one synchronisation).
        let st = dev.clone_dtoh(&stats)?;
        if st.len() != 4 || st[3] != 0.0 {
            candle_core::bail!(
                "fused NeRF loss: the network's raw output is not finite (NaN or infinite parameters?)"
            )
        }
        let opacity = [st[1] / r.max(1) as f64, st[2]];
        *self
            .opacity
            .lock()
            .map_err(|_| candle_core::Error::Msg("fused NeRF loss: poisoned".into()))? =
            Some(opacity);
        *self
            .grad_cuda
            .lock()
            .map_err(|_| candle_core::Error::Msg("fused NeRF loss: poisoned".into()))? =
            Some(CudaStorage::wrap_cuda_slice(gp, dev.clone()));
        let loss = upload(&dev, &[T::from_f64(st[0] * inv)])?;
        Ok((CudaStorage::wrap_cuda_slice(loss, dev), Shape::from(())))
    }
}
