//! The per-tick parts of the EMP lite forecast, one at a time, on one core:
//! a vision time slice per layer (inside the window and at its end, where
//! the kernel reads the "same" padding), the trajectory encoder's fused
//! Inception convolution folded at several periods, and the classifier's
//! input projection. Random weights: the cost does not depend on them.
//!
//! `cargo bench -p fall-guard-runtime --bench model_parts`; medians in
//! `target/criterion/<group>/<name>/new/estimates.json`. `fall-guard bench`
//! gives the whole tick; this says where it goes.

use std::time::Duration;

use burn::prelude::*;
use burn::tensor::Distribution;
use criterion::{criterion_group, criterion_main, Criterion};
use fall_guard_runtime::model::cpu_device;
use fall_guard_runtime::model::host_conv::HostConv;
use fall_guard_runtime::model::host_linear::HostLinear;
use fall_guard_runtime::model::inception::{Inception2d, Inception3d};
use fall_guard_runtime::model::ModelConfig;

fn noise(len: usize, seed: u64) -> Vec<f32> {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..len)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) - 0.5
        })
        .collect()
}

fn vision_slices(c: &mut Criterion) {
    let device = cpu_device();
    let cfg = ModelConfig::lite(60, 25, vec![15, 30, 45, 60], 64);
    let mut group = c.benchmark_group("vision_slice");
    group.measurement_time(Duration::from_secs(2));
    let (mut c_in, mut hw) = (3usize, cfg.lowpassed_size());
    for (li, &c_out) in cfg.vision_channels.iter().enumerate() {
        let conv = HostConv::from_fused(&Inception3d::new(c_in, c_out, &device).fuse());
        let input = noise(c_in * hw * hw, li as u64);
        let terms = conv.slice_terms(&input, &[0, 1, 2], hw, &mut Vec::new());
        let terms: Vec<&[f32]> = terms.iter().map(Vec::as_slice).collect();
        let name = format!("layer{li}_{c_in}x{hw}x{hw}_to_{c_out}");
        group.bench_function(format!("{name}/3_terms"), |b| {
            b.iter(|| {
                std::hint::black_box(conv.slice_terms(&input, &[0, 1, 2], hw, &mut Vec::new()))
            })
        });
        group.bench_function(format!("{name}/pool_of_3_terms"), |b| {
            b.iter(|| std::hint::black_box(conv.pooled_of_terms(&terms, hw)))
        });
        c_in = c_out;
        hw /= 2;
    }
    group.finish();
}

fn trajectory_grid(c: &mut Criterion) {
    let device = cpu_device();
    let cfg = ModelConfig::lite(60, 25, vec![15, 30, 45, 60], 64);
    let l = cfg.plan_len();
    let mut group = c.benchmark_group("trajectory_grid");
    group.measurement_time(Duration::from_secs(2));
    let conv_in = HostConv::from_fused(
        &Inception2d::new(cfg.plan_d, cfg.inc_dim, cfg.num_kernels, &device).fuse(),
    );
    let conv_out = HostConv::from_fused(
        &Inception2d::new(cfg.inc_dim, cfg.plan_d, cfg.num_kernels, &device).fuse(),
    );
    let x = noise(l * cfg.plan_d, 7);
    for p in [2usize, 3, 4, 5, 6, 7, 8, 10, 12, 16, 20, 40, 60] {
        let rows = l.div_ceil(p);
        group.bench_function(format!("in_out_p{p}"), |b| {
            b.iter(|| {
                let h = conv_in.forward_grid(&x, rows, p, rows * p);
                std::hint::black_box(conv_out.forward_grid(&h, rows, p, l))
            })
        });
    }
    group.finish();
    // A block's first convolution at three periods: folded at each, or the
    // tap products made once and summed per period (`grid_taps` chooses).
    let conv_in = conv_in.with_tap_products();
    let mut group = c.benchmark_group("trajectory_conv_in_3_periods");
    group.measurement_time(Duration::from_secs(2));
    group.bench_function("tap_products_only", |b| {
        b.iter(|| std::hint::black_box(conv_in.tap_products(&x)))
    });
    for periods in [
        [2usize, 3, 4],
        [3, 5, 8],
        [5, 7, 10],
        [8, 12, 20],
        [12, 20, 40],
    ] {
        let name = format!("{}_{}_{}", periods[0], periods[1], periods[2]);
        group.bench_function(format!("folded/{name}"), |b| {
            b.iter(|| {
                for &p in &periods {
                    let rows = l.div_ceil(p);
                    std::hint::black_box(conv_in.forward_grid(&x, rows, p, rows * p));
                }
            })
        });
        group.bench_function(format!("tap_products/{name}"), |b| {
            b.iter(|| {
                let y = conv_in.tap_products(&x);
                for &p in &periods {
                    let rows = l.div_ceil(p);
                    std::hint::black_box(conv_in.forward_grid_from_taps(&y, rows, p, rows * p));
                }
            })
        });
    }
    group.finish();
}

fn projection(c: &mut Criterion) {
    let device = cpu_device();
    let (d_in, d_out) = (7260usize, 1024usize);
    // f16-exact weights, as the shipped files hold.
    let w: Vec<f32> = noise(d_in * d_out, 3)
        .into_iter()
        .map(|v| half::f16::from_f32(v * 0.02).to_f32())
        .collect();
    let linear = HostLinear::new(w, vec![0.0; d_out], d_in, d_out);
    assert!(linear.is_half());
    let x = Tensor::<2>::random([1, d_in], Distribution::Normal(0.0, 1.0), &device);
    let mut group = c.benchmark_group("projection");
    group.measurement_time(Duration::from_secs(2));
    group.bench_function(format!("{d_in}x{d_out}_f16"), |b| {
        b.iter(|| std::hint::black_box(linear.forward(x.clone())))
    });
    let int8 = linear.to_int8();
    group.bench_function(format!("{d_in}x{d_out}_int8"), |b| {
        b.iter(|| std::hint::black_box(int8.forward(x.clone())))
    });
    group.finish();
}

criterion_group!(benches, vision_slices, trajectory_grid, projection);
criterion_main!(benches);
