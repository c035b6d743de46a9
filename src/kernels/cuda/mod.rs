//! The CUDA side of the fused ops (feature `cuda`): CUDA C sources compiled at run time by
//! NVRTC for the device's own compute capability, once per process, module and dtype,
//! and launched through candle's `CustomOpN::cuda_fwd`, so a user keeps one call per
//! operation on either device.
//!
//! Why NVRTC at run time rather than PTX built by `nvcc` in a build script: candle
//! already links NVRTC (its cudarc dependency has the `nvrtc` feature), so the crate
//! needs no CUDA compiler of its own at build time; the kernels are compiled for the
//! architecture they run on (no PTX-version or fat-binary mismatch between build and run
//! machines); and the same source serves f32 and f64 through one `#define`. The cost is
//! one compilation per module and dtype at the first call (tens of milliseconds).
//!
//! A kernel type implements `CudaKernel<N>` (the dispatch module's) beside its
//! `CpuKernel<N>`; the `cpu_op!(Type, N, "name", cuda)` form of the dispatch macro then
//! writes `cuda_fwd` and a `bwd` that runs the CUDA backward for CUDA inputs. Every
//! kernel is tested against the CPU kernel and the candle-op reference path in
//! `tests/cuda.rs`.

use candle_core::backend::BackendStorage;
use candle_core::cuda::cudarc::driver::{
    CudaFunction, CudaSlice, CudaStream, CudaView, DeviceRepr, LaunchArgs, LaunchConfig,
    PushKernelArg, ValidAsZeroBits,
};
use candle_core::cuda::cudarc::nvrtc::{compile_ptx_with_opts, CompileOptions};
use candle_core::cuda::{CudaDType, WrapErr};
use candle_core::{CudaDevice, CudaStorage, Layout, Shape, WithDType};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

pub(crate) mod sources;

/// The element types of the CUDA kernels: f32 and f64.
pub(crate) trait GpuReal: WithDType + CudaDType + DeviceRepr + ValidAsZeroBits {
    /// The dtype's name in module names and the `real` typedef of the sources.
    const C_TYPE: &'static str;
}

impl GpuReal for f32 {
    const C_TYPE: &'static str = "float";
}

impl GpuReal for f64 {
    const C_TYPE: &'static str = "double";
}

/// Helpers every source sees: `real`, the index type and the launch-size helpers.
const PRELUDE: &str = r#"
typedef unsigned long long u64;
typedef long long i64;
#define NF_GRID_STRIDE(i, n) for (u64 i = (u64)blockIdx.x * blockDim.x + threadIdx.x; i < (u64)(n); i += (u64)blockDim.x * gridDim.x)
"#;

/// PTX of every (module, dtype, architecture) compiled so far.
fn ptx_cache() -> &'static Mutex<HashMap<String, String>> {
    static CACHE: OnceLock<Mutex<HashMap<String, String>>> = OnceLock::new();
    CACHE.get_or_init(|| Mutex::new(HashMap::new()))
}

/// A loaded kernel function and the stream of the device it runs on.
#[derive(Clone)]
pub(crate) struct Kernel {
    func: CudaFunction,
    stream: Arc<CudaStream>,
}

impl Kernel {
    /// A launch of this kernel on its device's stream; push the arguments, then
    /// [`launch`].
    pub(crate) fn builder(&self) -> LaunchArgs<'_> {
        self.stream.launch_builder(&self.func)
    }
}

/// The device's compute capability, asked of the driver once per device and process
/// (every kernel load needs it for its module's key).
fn compute_capability(dev: &CudaDevice) -> candle_core::Result<(i32, i32)> {
    static ARCH: OnceLock<Mutex<HashMap<candle_core::cuda::DeviceId, (i32, i32)>>> =
        OnceLock::new();
    let poisoned = || candle_core::Error::Msg("CUDA architecture cache poisoned".into());
    let cache = ARCH.get_or_init(|| Mutex::new(HashMap::new()));
    if let Some(cc) = cache.lock().map_err(|_| poisoned())?.get(&dev.id()) {
        return Ok(*cc);
    }
    let cc = dev.cuda_stream().context().compute_capability().w()?;
    cache.lock().map_err(|_| poisoned())?.insert(dev.id(), cc);
    Ok(cc)
}

/// The kernel functions loaded so far, by device, module, dtype and function name: a
/// launch after the first looks its function up here without touching the PTX.
type FunctionCache =
    HashMap<(candle_core::cuda::DeviceId, &'static str, &'static str), HashMap<String, Kernel>>;

fn function_cache() -> &'static Mutex<FunctionCache> {
    static CACHE: OnceLock<Mutex<FunctionCache>> = OnceLock::new();
    CACHE.get_or_init(|| Mutex::new(HashMap::new()))
}

/// A kernel function of a source module: `source` is compiled for `T` and the device's
/// architecture at the first call; later calls take the loaded function from a cache.
pub(crate) fn function<T: GpuReal>(
    dev: &CudaDevice,
    module: &'static str,
    source: &'static str,
    name: &str,
) -> candle_core::Result<Kernel> {
    let poisoned = || candle_core::Error::Msg("CUDA function cache poisoned".into());
    let slot = (dev.id(), module, T::C_TYPE);
    if let Some(k) = function_cache()
        .lock()
        .map_err(|_| poisoned())?
        .get(&slot)
        .and_then(|m| m.get(name))
    {
        return Ok(k.clone());
    }
    let k = load::<T>(dev, module, source, name)?;
    function_cache()
        .lock()
        .map_err(|_| poisoned())?
        .entry(slot)
        .or_default()
        .insert(name.to_owned(), k.clone());
    Ok(k)
}

/// Compiles (once per module, dtype and architecture) and loads a kernel function.
fn load<T: GpuReal>(
    dev: &CudaDevice,
    module: &'static str,
    source: &'static str,
    name: &str,
) -> candle_core::Result<Kernel> {
    let (major, minor) = compute_capability(dev)?;
    let key = format!("nf_{module}_{}_sm{major}{minor}", T::C_TYPE);
    let ptx = {
        let mut cache = ptx_cache()
            .lock()
            .map_err(|_| candle_core::Error::Msg("CUDA module cache poisoned".into()))?;
        match cache.get(&key) {
            Some(p) => p.clone(),
            None => {
                let src = format!("typedef {} real;\n{PRELUDE}\n{source}", T::C_TYPE);
                let opts = CompileOptions {
                    options: vec![
                        format!("--gpu-architecture=compute_{major}{minor}"),
                        "--std=c++17".into(),
                    ],
                    name: Some(format!("{module}.cu")),
                    ..Default::default()
                };
                let ptx = compile_ptx_with_opts(src, opts)
                    .map_err(|e| candle_core::Error::Msg(format!("NVRTC ({module}): {e:?}")))?
                    .to_src();
                cache.insert(key.clone(), ptx.clone());
                ptx
            }
        }
    };
    Ok(Kernel {
        func: dev
            .get_or_load_custom_func(name, &key, &ptx)?
            .into_cuda_function(),
        stream: dev.cuda_stream(),
    })
}

/// A one-dimensional launch of `n` threads (at least one block), 256 per block.
pub(crate) fn launch_1d(n: usize) -> LaunchConfig {
    let blocks = n.div_ceil(256).clamp(1, 65_535 * 16) as u32;
    LaunchConfig {
        grid_dim: (blocks, 1, 1),
        block_dim: (256, 1, 1),
        shared_mem_bytes: 0,
    }
}

/// Launches the kernel whose arguments `b` holds on `cfg`.
pub(crate) fn launch(mut b: LaunchArgs<'_>, cfg: LaunchConfig) -> candle_core::Result<()> {
    // SAFETY: every kernel of `sources` reads and writes only the element ranges its
    // arguments describe; the callers pass views and sizes of the same tensors.
    unsafe { b.launch(cfg) }.w()?;
    Ok(())
}

/// The contiguous elements of a CUDA storage of type `T`; errors name the op and input.
pub(crate) fn view<'a, T: GpuReal>(
    s: &'a CudaStorage,
    l: &Layout,
    op: &str,
    what: &str,
) -> candle_core::Result<CudaView<'a, T>> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(s.as_cuda_slice::<T>()?.slice(a..b)),
        None => candle_core::bail!("{op}: {what} must be contiguous"),
    }
}

/// Copies host values to a new device buffer (small per-call tables: segment offsets,
/// level geometry).
pub(crate) fn upload<T: DeviceRepr + 'static>(
    dev: &CudaDevice,
    v: &[T],
) -> candle_core::Result<CudaSlice<T>> {
    dev.clone_htod(v)
}

/// A zeroed device buffer of `n` elements.
pub(crate) fn zeros<T: GpuReal>(dev: &CudaDevice, n: usize) -> candle_core::Result<CudaSlice<T>> {
    dev.alloc_zeros::<T>(n.max(1))
}

/// A device buffer of `n` elements (at least one) whose values are not set: for outputs
/// that a kernel or a product with `β = 0` writes in full before anything reads them
/// (skips the memset of [`zeros`]).
pub(crate) fn uninit<T: GpuReal>(dev: &CudaDevice, n: usize) -> candle_core::Result<CudaSlice<T>> {
    // SAFETY: `T` is f32 or f64, for which every bit pattern is a value; the callers
    // write every element before reading it (see each call).
    unsafe { dev.alloc::<T>(n.max(1)) }
}

/// Whether the CUDA kernels run for CUDA tensors: yes unless the environment variable
/// `NEURAL_FIELDS_CUDA_KERNELS` is `0`, which sends every op down its candle-op reference
/// path (to compare the two, or to measure what the kernels gain). Read once per process.
pub(crate) fn enabled() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| std::env::var("NEURAL_FIELDS_CUDA_KERNELS").map_or(true, |v| v != "0"))
}

/// An elementwise kernel `name(x, y, n[, p])` of [`sources::ACTIVATION`] over a
/// contiguous f32/f64 CUDA storage, with the scalar parameter `p` when given.
pub(crate) fn map(
    name: &str,
    s: &CudaStorage,
    l: &Layout,
    p: Option<f64>,
) -> candle_core::Result<(CudaStorage, Shape)> {
    fn run<T: GpuReal>(
        name: &str,
        s: &CudaStorage,
        l: &Layout,
        p: Option<f64>,
    ) -> candle_core::Result<(CudaStorage, Shape)> {
        let dev = s.device().clone();
        let x = view::<T>(s, l, name, "x")?;
        let n = x.len();
        let mut y = zeros::<T>(&dev, n)?;
        let f = function::<T>(&dev, "activation", sources::ACTIVATION, name)?;
        let n64 = n as u64;
        let p = p.map(T::from_f64);
        let mut b = f.builder();
        b.arg(&x).arg(&mut y).arg(&n64);
        if let Some(p) = &p {
            b.arg(p);
        }
        launch(b, launch_1d(n))?;
        Ok((CudaStorage::wrap_cuda_slice(y, dev), l.shape().clone()))
    }
    match s.dtype() {
        candle_core::DType::F32 => run::<f32>(name, s, l, p),
        candle_core::DType::F64 => run::<f64>(name, s, l, p),
        d => candle_core::bail!("{name}: x must be f32 or f64, got {d:?}"),
    }
}
