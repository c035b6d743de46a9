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
    match &kept.layout {
        Layout::Packed(p) => assert_eq!(p.n_rays, r),
        Layout::Batched => panic!("retain returns packed intervals"),
    }
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
            assert_eq!(b.ray_indices.dim(0).unwrap(), m.div_ceil(2));
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

/// `Intervals::directions` gives every sample its own ray's direction in both layouts, in
/// the order of `Intervals::positions`, and retained samples keep theirs.
#[test]
fn sample_directions_follow_their_rays_in_both_layouts() {
    use neural_fields::camera::Rays;
    for dtype in [DType::F32, DType::F64] {
        let dev = Device::Cpu;
        let mut rng = SplitMix64::new(4);
        let (r, s) = (5, 7);
        let origins = rng.uniform_tensor(&[r, 3], -1.0, 1.0, dtype, &dev).unwrap();
        let dirs = rng.uniform_tensor(&[r, 3], -2.0, 2.0, dtype, &dev).unwrap();
        let rays = Rays::new(origins.clone(), dirs.clone()).unwrap();
        let near = Tensor::zeros(r, dtype, &dev).unwrap();
        let far = Tensor::full(3.0, r, &dev).unwrap().to_dtype(dtype).unwrap();
        let iv = stratified(&near, &far, s, Jitter::PerSample, 1).unwrap();
        let d = iv.directions(&rays).unwrap();
        assert_eq!(d.dims(), &[r, s, 3]);
        assert_eq!(d.dtype(), dtype);
        let (d, o, m) = (
            v64(&d.reshape(((), 3)).unwrap()),
            v64(&origins),
            v64(&iv.midpoints().unwrap()),
        );
        let p = v64(&iv.positions(&rays).unwrap().reshape(((), 3)).unwrap());
        let truth = v64(&dirs);
        for (k, (dk, pk)) in d.chunks(3).zip(p.chunks(3)).enumerate() {
            let ray = k / s;
            assert_eq!(dk, &truth[3 * ray..3 * ray + 3], "sample {k}");
            for c in 0..3 {
                let want = o[3 * ray + c] + m[k] * dk[c];
                assert!(
                    (pk[c] - want).abs() <= 1e-6 * (1.0 + want.abs()),
                    "sample {k}"
                );
            }
        }
        // Packed: keep every third sample.
        let keep: Vec<u8> = (0..r * s).map(|i| u8::from(i % 3 == 0)).collect();
        let (kept, idx) = iv
            .retain(&Tensor::from_vec(keep, (r, s), &dev).unwrap())
            .unwrap();
        assert!(matches!(kept.layout, Layout::Packed(_)));
        let packed = v64(&kept.directions(&rays).unwrap());
        let idx = idx.to_vec1::<u32>().unwrap();
        assert_eq!(packed.len(), 3 * idx.len());
        for (dk, &i) in packed.chunks(3).zip(&idx) {
            assert_eq!(dk, &d[3 * i as usize..3 * i as usize + 3]);
        }
        // Another ray count is refused, naming the rays.
        let two = Rays::new(
            origins.narrow(0, 0, 2).unwrap(),
            dirs.narrow(0, 0, 2).unwrap(),
        )
        .unwrap();
        let err = iv.directions(&two).unwrap_err().to_string();
        assert!(err.contains("rays"), "{err}");
    }
}
