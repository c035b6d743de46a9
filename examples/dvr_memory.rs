//! Peak heap memory of one DVR step — march (detached, chunked) + implicit step +
//! backward — for 16 384 rays with a 4×64 Mlp, at several step counts. The march keeps
//! nothing per sample, so the peak should not grow with the number of steps.
//!
//! ```text
//! cargo run --release --example dvr_memory
//! ```
//!
//! Memory is measured by a counting global allocator (bytes live on the heap; candle's
//! CPU tensors live there). Exits with an error if 256 steps need more than 1.2× the
//! peak of 16 steps.

use candle_core::{DType, Device};
use candle_nn::VarMap;
use clap::Parser;
use glam::DVec3;
use neural_fields::camera::{ray_sphere, Camera, Convention, Intrinsics};
use neural_fields::dvr::{implicit_surface, march, ImplicitConfig, MarchConfig};
use neural_fields::nn::{build_seeded, mlp, Activation, MlpConfig};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

struct Counting;
static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grew(by: usize) {
    let now = CURRENT.fetch_add(by, Ordering::Relaxed) + by;
    PEAK.fetch_max(now, Ordering::Relaxed);
}

// SAFETY: forwards to the system allocator and only counts sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = System.alloc(layout);
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = System.alloc_zeroed(layout);
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = System.realloc(ptr, layout, new_size);
        if !p.is_null() {
            CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
            grew(new_size);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

fn mib(b: usize) -> f64 {
    b as f64 / (1024.0 * 1024.0)
}

/// Peak heap memory of one DVR step (march, implicit step, backward) for 16 384 rays at
/// 16, 64 and 256 march steps; fails if 256 steps need more than 1.2× the peak of 16.
#[derive(Parser, Debug)]
struct Args {}

fn main() -> neural_fields::Result<()> {
    Args::parse();
    let dev = Device::Cpu;
    let varmap = VarMap::new();
    // ReLU with IDR's geometric initialisation: an approximate sphere SDF of radius 0.5.
    let cfg = MlpConfig {
        hidden: 64,
        depth: 4,
        activation: Activation::Relu,
        ..MlpConfig::sdf(0.5)
    };
    let net = build_seeded(&varmap, DType::F32, &dev, 0, |vb| mlp(&cfg, vb))?;
    let k = Intrinsics::from_fov_y(128, 128, 0.6)?;
    let cam = Camera::look_at(
        k,
        DVec3::new(0.0, 0.0, 2.5),
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenGl,
    )?;
    let rays = cam.rays(&dev, DType::F32)?; // 16 384 rays
    let bounds = ray_sphere(&rays, [0.0; 3], 1.0)?;
    println!("| steps | secant | rays | hits | field evaluations | march peak (MiB) | implicit + backward peak (MiB) | step peak (MiB) | peak / peak(16) | time (s) |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut first = None;
    let mut ratio_256 = 0.0;
    for steps in [16usize, 64, 256] {
        let config = MarchConfig {
            steps,
            secant_steps: 8,
            ..MarchConfig::default()
        };
        let base = CURRENT.load(Ordering::Relaxed);
        PEAK.store(base, Ordering::Relaxed);
        let start = Instant::now();
        let (n_hits, evals, march_peak, implicit_peak) = {
            let hits = march(&net, &rays, &bounds, &config)?;
            let march_peak = PEAK.load(Ordering::Relaxed) - base;
            let mid = CURRENT.load(Ordering::Relaxed);
            PEAK.store(mid, Ordering::Relaxed);
            let surf = implicit_surface(&net, &rays, &hits, &ImplicitConfig::default())?;
            let loss = surf.depth.sum_all()?;
            let grads = loss.backward()?;
            drop(grads);
            let implicit_peak = PEAK.load(Ordering::Relaxed) - base;
            (
                surf.indices.dim(0)?,
                hits.evaluations,
                march_peak,
                implicit_peak,
            )
        };
        let secs = start.elapsed().as_secs_f64();
        let peak = march_peak.max(implicit_peak);
        let f = *first.get_or_insert(peak);
        let ratio = peak as f64 / f as f64;
        if steps == 256 {
            ratio_256 = ratio;
        }
        println!(
            "| {steps} | 8 | {} | {n_hits} | {evals} | {:.1} | {:.1} | {:.1} | {ratio:.3} | {secs:.2} |",
            rays.len(),
            mib(march_peak),
            mib(implicit_peak),
            mib(peak)
        );
    }
    if ratio_256 > 1.2 {
        eprintln!("peak memory at 256 steps is {ratio_256:.3}× that at 16 steps (> 1.2)");
        std::process::exit(1);
    }
    Ok(())
}
