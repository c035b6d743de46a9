//! Memory of a loaded dataset: the peak heap while loading and drawing a batch stays within
//! twice the decoded image bytes (measured by a counting global allocator, so this file is
//! its own test binary).
#![cfg(feature = "data")]

use candle_core::{DType, Device};
use neural_fields::data::{load, LoadConfig, RaySampler, Split};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, layout: Layout) {
        unsafe { System.dealloc(p, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

#[test]
fn loading_the_committed_dataset_peaks_below_twice_its_image_bytes() {
    // Warm up rayon's pool and the decoders' one-time state outside the measurement.
    let warm = LoadConfig {
        split: Split::Val,
        ..LoadConfig::default()
    };
    drop(load(Path::new("examples/data/wuson"), &warm).unwrap());
    let base = LIVE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let config = LoadConfig {
        split: Split::All,
        ..LoadConfig::default()
    };
    let data = load(Path::new("examples/data/wuson"), &config).unwrap();
    let mut sampler = RaySampler::new(&data, 0, &Device::Cpu, DType::F32).unwrap();
    let batch = sampler.pixels(4096).unwrap();
    let peak = PEAK.load(Ordering::Relaxed) - base;
    let held = LIVE.load(Ordering::Relaxed) - base;
    let images: usize = data
        .views()
        .iter()
        .map(|v| {
            // A mask file holds one byte per pixel; an alpha channel is in the image.
            let (w, h, c) = v.image().size();
            let mask_file = c == 3 && v.mask(&Device::Cpu, DType::F32).unwrap().is_some();
            v.image().data().len() + if mask_file { w * h } else { 0 }
        })
        .sum();
    assert_eq!(images, 80 * 100 * 100 * 4);
    eprintln!(
        "image bytes {images}, held {held}, peak {peak} ({:.2}×)",
        peak as f64 / images as f64
    );
    assert!(
        peak < 2 * images,
        "peak {peak} bytes for {images} image bytes"
    );
    drop(batch);
}
