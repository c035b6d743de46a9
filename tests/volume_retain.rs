//! `Intervals::retain` with `visible_mask`: early termination changes the composite by at
//! most the termination threshold, in both layouts, and keeps rays and order.
#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor};
use common::v64;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{composite, stratified, visible_mask, CompositeConfig, Jitter, Layout};

#[test]
fn early_termination_by_retain_changes_the_composite_by_less_than_eps() {
    let dev = Device::Cpu;
    let mut rng = SplitMix64::new(9);
    let (r, s) = (64, 48);
    let near = Tensor::zeros(r, DType::F64, &dev).unwrap();
    let far = Tensor::full(4.0f64, r, &dev).unwrap();
    let iv = stratified(&near, &far, s, Jitter::PerSample, 3).unwrap();
    // Dense walls somewhere along most rays.
    let sigmas = rng
        .uniform_tensor(&[r, s], 0.0, 40.0, DType::F64, &dev)
        .unwrap();
    let colors = rng
        .uniform_tensor(&[r, s, 3], 0.0, 1.0, DType::F64, &dev)
        .unwrap();
    let full = composite(&sigmas, &colors, &iv, None, &CompositeConfig::default()).unwrap();
    let eps = 1e-4;
    let mask = visible_mask(&sigmas, &iv, None, eps).unwrap();
    let (kept, idx) = iv.retain(&mask).unwrap();
    let m = idx.dim(0).unwrap();
    assert!(
        m < r * s / 2,
        "most samples are hidden: kept {m} of {}",
        r * s
    );
    assert_eq!(kept.n_rays(), r);
    let pick = |t: &Tensor, c: usize| {
        t.reshape((r * s, c))
            .unwrap()
            .index_select(&idx, 0)
            .unwrap()
    };
    let early = composite(
        &pick(&sigmas, 1).squeeze(1).unwrap(),
        &pick(&colors, 3),
        &kept,
        None,
        &CompositeConfig::default(),
    )
    .unwrap();
    for (a, b) in v64(&full.color).iter().zip(v64(&early.color)) {
        assert!((a - b).abs() <= eps, "{a} vs {b}");
    }
    // Retaining from packed intervals: keep every other sample of the retained set.
    let every_other: Vec<u8> = (0..m).map(|i| (i % 2 == 0) as u8).collect();
    let (again, idx2) = kept
        .retain(&Tensor::from_vec(every_other, m, &dev).unwrap())
        .unwrap();
    assert_eq!(
        idx2.to_vec1::<u32>().unwrap(),
        (0..m as u32).step_by(2).collect::<Vec<_>>()
    );
    match (&kept.layout, &again.layout) {
        (Layout::Packed(a), Layout::Packed(b)) => {
            assert_eq!(a.n_rays, b.n_rays);
            assert_eq!(b.n_samples(), m.div_ceil(2));
        }
        _ => panic!("retain returns the packed layout"),
    }
    // A mask of another shape or dtype is refused.
    assert!(iv
        .retain(&Tensor::zeros((r, s - 1), DType::U8, &dev).unwrap())
        .is_err());
    assert!(iv
        .retain(&Tensor::zeros((r, s), DType::F32, &dev).unwrap())
        .is_err());
}
