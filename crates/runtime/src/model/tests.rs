//! Tests of the network, the model file and the streaming forecaster.

use super::*;
use burn::prelude::*;

use super::bench::noise;

fn joint_names(c: usize) -> Vec<String> {
    (0..c).map(|i| format!("joint_{i}")).collect()
}

/// A small but complete configuration (reference sizes make tests slow in debug).
fn small_config() -> ModelConfig {
    let mut cfg = ModelConfig::lite(12, 5, vec![3, 6, 9, 12], 32);
    cfg.d_model = 64;
    cfg.inc_dim = 8;
    cfg.plan_d = 8;
    cfg
}

struct Windows {
    joints: Vec<f32>,
    plan: Vec<f32>,
    frames: Vec<f32>,
}

fn window(cfg: &ModelConfig, seed: u64) -> Windows {
    let (n, c, s) = (cfg.n_ticks, cfg.n_joints, cfg.frame_size);
    Windows {
        joints: noise(n * c, seed).iter().map(|v| v * 2.0 - 1.0).collect(),
        plan: noise(cfg.plan_len() * c, seed + 1)
            .iter()
            .map(|v| v * 2.0 - 1.0)
            .collect(),
        frames: noise(3 * n * s * s, seed + 2),
    }
}

fn model(cfg: &ModelConfig, ablation: Ablation) -> (ModelMeta, Emp) {
    let device = cpu_device();
    let meta = ModelMeta::new(cfg.clone(), ablation, 30.0, joint_names(cfg.n_joints));
    (meta, Emp::new(cfg, ablation, &device))
}

#[test]
fn every_ablation_has_the_right_shapes_and_monotone_output() {
    let cfg = small_config();
    let device = cpu_device();
    for ablation in Ablation::ALL {
        let (meta, emp) = model(&cfg, ablation);
        let w: Vec<Windows> = (0..3).map(|i| window(&cfg, 10 + i)).collect();
        let input = file::build_input(
            &meta,
            &w.iter().map(|w| w.joints.as_slice()).collect::<Vec<_>>(),
            &w.iter().map(|w| w.plan.as_slice()).collect::<Vec<_>>(),
            &w.iter().map(|w| w.frames.as_slice()).collect::<Vec<_>>(),
            &device,
        )
        .expect("valid input");
        let logits = emp.forward(input);
        assert_eq!(logits.dims(), [3, 4], "{ablation}");
        let z: Vec<f32> = logits.into_data().try_to_vec::<f32>().unwrap();
        for row in z.chunks(4) {
            assert!(
                row.windows(2).all(|p| p[0] <= p[1]),
                "{ablation}: logits not monotone: {row:?}"
            );
        }
    }
}

#[test]
fn reference_config_shapes() {
    let cfg = ModelConfig::lite(60, 25, vec![15, 30, 45, 60], 64);
    cfg.validate().unwrap();
    assert_eq!(cfg.vision_out_shape(), [32, 15, 2, 2]);
    assert_eq!(vision::VisionEncoder::out_features(&cfg), 1920);
    assert_eq!(plan::PlanEncoder::out_features(&cfg), 120 * 32);
    let device = cpu_device();
    let v = vision::VisionEncoder::new(&cfg, &device);
    let x = Tensor::<5>::zeros([1, 3, 60, 32, 32], &device);
    assert_eq!(v.forward(x).dims(), [1, 1920]);
}

#[test]
fn monotone_map_is_cumulative_softplus() {
    let device = cpu_device();
    let a = Tensor::<2>::from_data(
        TensorData::new(vec![0.5f32, -3.0, 2.0, -20.0], [1, 4]),
        &device,
    );
    let z: Vec<f32> = emp::monotone_logits(a)
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();
    let sp = |x: f32| (1.0 + x.exp()).ln();
    let want = [
        0.5,
        0.5 + sp(-3.0),
        0.5 + sp(-3.0) + sp(2.0),
        0.5 + sp(-3.0) + sp(2.0) + sp(-20.0),
    ];
    for (g, w) in z.iter().zip(want) {
        assert!((g - w).abs() < 1e-5, "{z:?} vs {want:?}");
    }
}

#[test]
fn probabilities_never_decrease_with_horizon_for_random_inputs() {
    let cfg = small_config();
    let (meta, emp) = model(&cfg, Ablation::EMP);
    let loaded = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
    for seed in 0..5 {
        let w = window(&cfg, 100 + seed);
        let p = loaded
            .forecast_arrays(&w.joints, &w.plan, &w.frames)
            .unwrap();
        assert_eq!(p.len(), 4);
        assert!(p.windows(2).all(|q| q[0] <= q[1]), "{p:?}");
        assert!(p.iter().all(|v| (0.0..=1.0).contains(v)));
    }
}

#[test]
fn fused_inception_equals_branches() {
    // The block's branches and its fused kernel on `x`, element by element
    // (the 2-D and 3-D blocks are different types).
    macro_rules! assert_fused_equals_branches {
        ($block:expr, $x:expr) => {
            let a: Vec<f32> = $block
                .forward_branches($x.clone())
                .into_data()
                .try_to_vec::<f32>()
                .unwrap();
            let b: Vec<f32> = $block
                .fuse()
                .forward($x)
                .into_data()
                .try_to_vec::<f32>()
                .unwrap();
            assert!(a.iter().zip(&b).all(|(p, q)| (p - q).abs() < 1e-5));
        };
    }
    let device = cpu_device();
    let inc = inception::Inception2d::new(4, 6, 3, &device);
    let x = Tensor::<4>::from_data(
        TensorData::new(noise(2 * 4 * 5 * 7, 3), [2, 4, 5, 7]),
        &device,
    );
    assert_fused_equals_branches!(inc, x);
    let inc3 = inception::Inception3d::new(3, 5, &device);
    let x = Tensor::<5>::from_data(
        TensorData::new(noise(3 * 6 * 8 * 8, 4), [1, 3, 6, 8, 8]),
        &device,
    );
    assert_fused_equals_branches!(inc3, x);
}

/// Training runs the fused kernel built from the branch parameters with
/// tensor ops: the same outputs as the branches, and the same gradients
/// reach every branch's weight and bias (2-D and 3-D blocks).
#[test]
fn training_fusion_has_the_branches_outputs_and_gradients() {
    fn close(a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
        assert!(
            a.iter().zip(b).all(|(p, q)| (p - q).abs() <= 1e-5 * scale),
            "{a:?} vs {b:?}"
        );
    }
    fn vec_of<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_to_vec::<f32>().unwrap()
    }
    let device = cpu_device().autodiff();
    let inc = inception::Inception2d::new(3, 4, 3, &device);
    let x = Tensor::<4>::from_data(
        TensorData::new(noise(2 * 3 * 5 * 6, 7), [2, 3, 5, 6]),
        &device,
    );
    let target = Tensor::<4>::from_data(
        TensorData::new(noise(2 * 4 * 5 * 6, 8), [2, 4, 5, 6]),
        &device,
    );
    // Outputs equal; the gradients `params` reads off `y * target` equal.
    fn same_outputs_and_gradients<const D: usize>(
        fused: Tensor<D>,
        branches: Tensor<D>,
        target: Tensor<D>,
        params: impl Fn(&burn::tensor::Gradients) -> Vec<Vec<f32>>,
    ) -> usize {
        close(&vec_of(fused.clone()), &vec_of(branches.clone()));
        let grads = |y: Tensor<D>| params(&(y * target.clone()).sum().backward());
        let (ga, gb) = (grads(fused), grads(branches));
        for (a, b) in ga.iter().zip(&gb) {
            close(a, b);
        }
        ga.len()
    }
    // Each branch's weight and bias gradients (the 2-D and 3-D blocks'
    // branches are different types).
    macro_rules! branch_gradients {
        ($block:expr, $g:expr) => {
            $block
                .branches()
                .iter()
                .flat_map(|c| {
                    let bias = c.bias.as_ref().expect("bias").val();
                    [
                        vec_of(c.weight.val().grad($g).expect("weight gradient")),
                        vec_of(bias.grad($g).expect("bias gradient")),
                    ]
                })
                .collect()
        };
    }
    let params = inc.branches().len();
    let checked = same_outputs_and_gradients(
        inc.forward(x.clone()),
        inc.forward_branches(x),
        target,
        |g| branch_gradients!(inc, g),
    );
    assert_eq!(checked, 2 * params);
    assert_eq!(params, 3);

    let inc3 = inception::Inception3d::new(2, 3, &device);
    let x = Tensor::<5>::from_data(
        TensorData::new(noise(2 * 4 * 5 * 5, 9), [1, 2, 4, 5, 5]),
        &device,
    );
    let target = Tensor::<5>::from_data(
        TensorData::new(noise(3 * 4 * 5 * 5, 10), [1, 3, 4, 5, 5]),
        &device,
    );
    let checked = same_outputs_and_gradients(
        inc3.forward(x.clone()),
        inc3.forward_branches(x),
        target,
        |g| branch_gradients!(inc3, g),
    );
    assert_eq!(checked, 4);
}

/// The conv3d reference and [`inception::conv3d_channel_major`] (channel-major
/// in and out) of the same `x` `[B, C, T, H, W]`, kernel and bias.
fn conv3d_both_ways(x: Tensor<5>, w: Tensor<5>, bias: Tensor<1>) -> (Tensor<5>, Tensor<5>) {
    let k = w.dims()[2];
    let want = burn::tensor::module::conv3d(
        x.clone(),
        w.clone(),
        Some(bias.clone()),
        burn::tensor::ops::ConvOptions::new([1, 1, 1], [k / 2; 3], [1, 1, 1], 1),
    );
    let got = inception::conv3d_channel_major(x.permute([1, 0, 2, 3, 4]), w, bias)
        .permute([1, 0, 2, 3, 4]);
    (want, got)
}

#[test]
fn conv3d_channel_major_is_a_3d_convolution() {
    let device = cpu_device();
    for (k, t) in [(3, 5), (1, 4), (5, 7), (3, 1)] {
        let x = Tensor::<5>::from_data(
            TensorData::new(noise(2 * 3 * t * 6 * 5, 11), [2, 3, t, 6, 5]),
            &device,
        );
        let w = Tensor::<5>::from_data(
            TensorData::new(noise(4 * 3 * k * k * k, 12), [4, 3, k, k, k]),
            &device,
        )
        .sub_scalar(0.5);
        let bias = Tensor::<1>::from_data(TensorData::new(noise(4, 13), [4]), &device);
        let (want, got) = conv3d_both_ways(x, w, bias);
        assert_eq!(got.dims(), [2, 4, t, 6, 5]);
        let want: Vec<f32> = want.into_data().try_to_vec::<f32>().unwrap();
        let got: Vec<f32> = got.into_data().try_to_vec::<f32>().unwrap();
        assert!(
            got.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-4),
            "k {k}, t {t}"
        );
    }
}

/// The gather + matmul form trains like `conv3d`: the same gradients reach
/// the input, the weight and the bias (a vision layer past the first, whose
/// input is itself trained, needs all three).
#[test]
fn conv3d_channel_major_has_the_convolution_gradients() {
    fn vec_of<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_to_vec::<f32>().unwrap()
    }
    let device = cpu_device().autodiff();
    for (k, t) in [(3, 5), (3, 1), (1, 3)] {
        let x = Tensor::<5>::from_data(
            TensorData::new(noise(2 * 3 * t * 6 * 5, 21), [2, 3, t, 6, 5]),
            &device,
        );
        let w = Tensor::<5>::from_data(
            TensorData::new(noise(4 * 3 * k * k * k, 22), [4, 3, k, k, k]),
            &device,
        )
        .sub_scalar(0.5);
        let bias = Tensor::<1>::from_data(TensorData::new(noise(4, 23), [4]), &device);
        let target = Tensor::<5>::from_data(
            TensorData::new(noise(2 * 4 * t * 6 * 5, 24), [2, 4, t, 6, 5]),
            &device,
        );
        let grads = |use_slices: bool| -> Vec<Vec<f32>> {
            let (x, w, bias) = (
                x.clone().require_grad(),
                w.clone().require_grad(),
                bias.clone().require_grad(),
            );
            let (want, got) = conv3d_both_ways(x.clone(), w.clone(), bias.clone());
            let y = if use_slices { got } else { want };
            let g = (y * target.clone()).sum().backward();
            vec![
                vec_of(x.grad(&g).expect("input gradient")),
                vec_of(w.grad(&g).expect("weight gradient")),
                vec_of(bias.grad(&g).expect("bias gradient")),
            ]
        };
        for (a, b) in grads(true).iter().zip(&grads(false)) {
            assert_eq!(a.len(), b.len());
            let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
            assert!(
                a.iter().zip(b).all(|(p, q)| (p - q).abs() <= 1e-5 * scale),
                "k {k}, t {t}: {a:?} vs {b:?}"
            );
        }
    }
}

#[test]
fn fused_network_equals_training_network() {
    let cfg = small_config();
    let (meta, emp) = model(&cfg, Ablation::EMP);
    let device = cpu_device();
    let w = window(&cfg, 5);
    let input = file::build_input(&meta, &[&w.joints], &[&w.plan], &[&w.frames], &device).unwrap();
    let a: Vec<f32> = emp
        .forward(input.clone())
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();
    let b: Vec<f32> = emp
        .to_inference()
        .forward(input)
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();
    assert!(
        a.iter().zip(&b).all(|(p, q)| (p - q).abs() < 1e-5),
        "{a:?} vs {b:?}"
    );
}

#[test]
fn save_then_load_gives_identical_outputs() {
    let cfg = small_config();
    let dir = tempfile::tempdir().unwrap();
    for ablation in [Ablation::P, Ablation::EMP] {
        let (mut meta, emp) = model(&cfg, ablation);
        meta.joint_mean = vec![0.1; cfg.n_joints];
        meta.trained_on = "simulated".into();
        let path = dir.path().join(format!("{ablation}.bpk"));
        save_model(&path, &meta, &emp).unwrap();
        let before = LoadedModel::from_parts(meta.clone(), &emp, cpu_device(), path.clone());
        let after = LoadedModel::load(&path).unwrap();
        assert_eq!(after.meta, meta);
        let w = window(&cfg, 9);
        let a = before
            .forecast_arrays(&w.joints, &w.plan, &w.frames)
            .unwrap();
        let b = after
            .forecast_arrays(&w.joints, &w.plan, &w.frames)
            .unwrap();
        assert_eq!(a, b, "{ablation}");
    }
}

#[test]
fn half_precision_file_is_smaller_and_forecasts_alike() {
    let cfg = small_config();
    let dir = tempfile::tempdir().unwrap();
    let (meta, emp) = model(&cfg, Ablation::EMP);
    let full = dir.path().join("full.bpk");
    let half = dir.path().join("half.bpk");
    save_model(&full, &meta, &emp).unwrap();
    save_model_as(&half, &meta, &emp, WeightPrecision::Half).unwrap();
    let size = |p: &std::path::Path| std::fs::metadata(p).unwrap().len() as f64;
    assert!(
        size(&half) < 0.6 * size(&full),
        "half {} bytes vs full {} bytes",
        size(&half),
        size(&full)
    );
    let w = window(&cfg, 11);
    let a = LoadedModel::load(&full)
        .unwrap()
        .forecast_arrays(&w.joints, &w.plan, &w.frames)
        .unwrap();
    let b = LoadedModel::load(&half)
        .unwrap()
        .forecast_arrays(&w.joints, &w.plan, &w.frames)
        .unwrap();
    assert_ne!(a, b, "the weights were not rounded");
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() < 5e-3, "full {a:?} vs half {b:?}");
    }
}

#[test]
fn load_errors_name_the_file() {
    let cfg = small_config();
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.bpk");
    let e = LoadedModel::load(&missing).unwrap_err().to_string();
    assert!(e.contains("nope.bpk"), "{e}");

    let (meta, emp) = model(&cfg, Ablation::MP);
    let good = dir.path().join("good.bpk");
    save_model(&good, &meta, &emp).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    for cut in [4usize, 12, 40, bytes.len() - 10] {
        let p = dir.path().join(format!("cut{cut}.bpk"));
        std::fs::write(&p, &bytes[..cut]).unwrap();
        let e = LoadedModel::load(&p).unwrap_err();
        assert!(
            matches!(e, ModelError::Truncated { .. }),
            "cut at {cut}: {e}"
        );
        assert!(e.to_string().contains(&format!("cut{cut}.bpk")));
    }
    let bad = dir.path().join("bad.bpk");
    std::fs::write(&bad, b"PK\x03\x04 definitely not a model").unwrap();
    let e = LoadedModel::load(&bad).unwrap_err();
    assert!(
        matches!(e, ModelError::BadMagic { .. }) && e.to_string().contains("bad.bpk"),
        "{e}"
    );
}

#[test]
fn mismatched_inputs_are_refused_with_what_differs() {
    let cfg = small_config();
    let meta = ModelMeta::new(cfg.clone(), Ablation::EMP, 30.0, joint_names(5));
    meta.check_compatible_with(&joint_names(5), 30.0, 12, 12, 32)
        .unwrap();
    let mut other = joint_names(5);
    other.swap(1, 2);
    let e = meta
        .check_compatible_with(&other, 30.0, 12, 12, 32)
        .unwrap_err()
        .to_string();
    assert!(e.contains("joint list") && e.contains("index 1"), "{e}");
    let e = meta
        .check_compatible_with(&joint_names(5), 10.0, 12, 12, 32)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("tick rate") && e.contains("30") && e.contains("10"),
        "{e}"
    );
    let e = meta
        .check_compatible_with(&joint_names(5), 30.0, 24, 12, 32)
        .unwrap_err()
        .to_string();
    assert!(e.contains("window length"), "{e}");
}

#[test]
fn nan_input_is_an_error_naming_tick_and_joint() {
    let cfg = small_config();
    let (meta, emp) = model(&cfg, Ablation::P);
    let loaded = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
    let mut w = window(&cfg, 1);
    w.joints[3 * 5 + 2] = f32::NAN;
    let e = loaded
        .forecast_arrays(&w.joints, &[], &[])
        .unwrap_err()
        .to_string();
    assert!(e.contains("tick 3") && e.contains("joint_2"), "{e}");
}

/// The whole-window arrays for the window ending at `end` of a long stream.
fn stream_window(
    cfg: &ModelConfig,
    stream_joints: &[f32],
    stream_frames: &[Vec<f32>],
    end: usize,
) -> (Vec<f32>, Vec<f32>) {
    let (n, c, s) = (cfg.n_ticks, cfg.n_joints, cfg.frame_size);
    let start = end + 1 - n;
    let joints = stream_joints[start * c..(end + 1) * c].to_vec();
    let mut frames = vec![0.0f32; 3 * n * s * s];
    for t in 0..n {
        let f = &stream_frames[start + t];
        for ch in 0..3 {
            frames[(ch * n + t) * s * s..(ch * n + t + 1) * s * s]
                .copy_from_slice(&f[ch * s * s..(ch + 1) * s * s]);
        }
    }
    (joints, frames)
}

#[test]
fn streaming_equals_whole_window() {
    for cfg in [
        small_config(),
        ModelConfig::lite(24, 25, vec![6, 12, 18, 24], 64),
    ] {
        let (meta, emp) = model(&cfg, Ablation::EMP);
        let loaded = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
        let mut stream = StreamingForecaster::new(&loaded);
        let (c, s, l) = (cfg.n_joints, cfg.frame_size, cfg.plan_len());
        let total = cfg.n_ticks + 7;
        let joints = noise(total * c, 77);
        let frames: Vec<Vec<f32>> = (0..total)
            .map(|t| noise(3 * s * s, 1000 + t as u64))
            .collect();
        for t in 0..total {
            let plan = noise(l * c, 5000 + t as u64);
            stream
                .push_parts(
                    100 + t as i64,
                    &joints[t * c..(t + 1) * c],
                    Some(&frames[t]),
                    Some(&plan),
                )
                .unwrap();
            if t + 1 < cfg.n_ticks {
                assert!(
                    stream.forecast().is_err(),
                    "forecast before the window is full"
                );
                continue;
            }
            let got = stream.forecast().unwrap();
            let (wj, wf) = stream_window(&cfg, &joints, &frames, t);
            let want = loaded.forecast_arrays(&wj, &plan, &wf).unwrap();
            for (g, w) in got.iter().zip(&want) {
                assert!(
                    (g - w).abs() < 1e-5,
                    "tick {t}: streaming {got:?} vs window {want:?}"
                );
            }
        }
    }
}

/// `[model].convolutions = "int8"`: the streaming forecasts of a lite EMP
/// with its trajectory and vision convolutions in integers stay within
/// 0.01 of the f32 ones on every tick and horizon (noise inputs, random
/// weights), and are not the same (the integer path ran).
#[test]
fn int8_convolutions_stream_close_to_f32() {
    let cfg = ModelConfig::lite(24, 25, vec![6, 12, 18, 24], 64);
    let (meta, emp) = model(&cfg, Ablation::EMP);
    let f32_model = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
    let int8_model = f32_model.clone().with_convolutions(Convolutions::Int8);
    let (c, s, l) = (cfg.n_joints, cfg.frame_size, cfg.plan_len());
    let total = cfg.n_ticks + 5;
    let mut streams = [
        StreamingForecaster::new(&f32_model),
        StreamingForecaster::new(&int8_model),
    ];
    let (mut worst, mut moved) = (0.0f32, 0usize);
    for t in 0..total {
        let joints = noise(c, 300 + t as u64);
        let frame = noise(3 * s * s, 3000 + t as u64);
        let plan = noise(l * c, 6000 + t as u64);
        let mut out = Vec::new();
        for stream in &mut streams {
            stream
                .push_parts(100 + t as i64, &joints, Some(&frame), Some(&plan))
                .unwrap();
            if t + 1 >= cfg.n_ticks {
                out.push(stream.forecast().unwrap());
            }
        }
        if let [a, b] = &out[..] {
            for (x, y) in a.iter().zip(b) {
                assert!(y.is_finite(), "tick {t}: {b:?}");
                worst = worst.max((x - y).abs());
                moved += usize::from(x != y);
            }
        }
    }
    assert!(worst < 0.01, "int8 moved a forecast by {worst}");
    assert!(moved > 0, "int8 changed nothing: not applied");
}

/// Vision slices prepared while the window fills: the first forecast of the
/// full window equals the whole-window forward and computes no more slices
/// than a steady tick (without `prepare` it computes every slice).
#[test]
fn prepared_fill_makes_the_first_forecast_a_normal_tick() {
    let cfg = ModelConfig::lite(24, 25, vec![6, 12, 18, 24], 64);
    let (meta, emp) = model(&cfg, Ablation::EMP);
    let loaded = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
    let (n, c, s, l) = (cfg.n_ticks, cfg.n_joints, cfg.frame_size, cfg.plan_len());
    let total = n + 3;
    let joints = noise(total * c, 78);
    let frames: Vec<Vec<f32>> = (0..total)
        .map(|t| noise(3 * s * s, 2000 + t as u64))
        .collect();
    let mut costs = Vec::new();
    for prepared in [true, false] {
        let mut stream = StreamingForecaster::new(&loaded);
        let mut per_forecast = Vec::new();
        for t in 0..total {
            let plan = noise(l * c, 6000 + t as u64);
            let j = &joints[t * c..(t + 1) * c];
            stream
                .push_parts(t as i64, j, Some(&frames[t]), Some(&plan))
                .unwrap();
            if t + 1 < n {
                if prepared {
                    stream.prepare().unwrap();
                }
                continue;
            }
            let before = stream.slices_computed();
            let got = stream.forecast().unwrap();
            per_forecast.push(stream.slices_computed() - before);
            let (wj, wf) = stream_window(&cfg, &joints, &frames, t);
            let want = loaded.forecast_arrays(&wj, &plan, &wf).unwrap();
            for (g, w) in got.iter().zip(&want) {
                assert!(
                    (g - w).abs() < 1e-5,
                    "prepared {prepared}, tick {t}: streaming {got:?} vs window {want:?}"
                );
            }
        }
        costs.push(per_forecast);
    }
    let (with, without) = (&costs[0], &costs[1]);
    let steady = *with[1..].iter().max().unwrap();
    assert!(
        with[0] <= steady,
        "first forecast {} slices, steady {steady}",
        with[0]
    );
    assert!(
        without[0] >= n as u64,
        "unprepared first forecast {}",
        without[0]
    );
}

/// Steady ticks with the plan window sliding over one plan, as between two
/// plan messages: the forecasts equal the whole-window forward, the vision
/// sums terms kept from the tick before, and the trajectory encoder's first
/// block multiplies one new row a tick once it holds the products of the
/// tick before. (The first forecast may fold each period on its own when
/// its periods make that cheaper, keeping no products; the tick after it
/// then makes all the rows once. Which it does depends on the periods
/// alone, and it has varied between runs of this test: the periods come
/// from DFT amplitudes computed by burn's matrix product.)
#[test]
fn steady_ticks_reuse_vision_terms_and_plan_rows() {
    let cfg = ModelConfig::lite(24, 25, vec![6, 12, 18, 24], 64);
    let (meta, emp) = model(&cfg, Ablation::EMP);
    let loaded = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
    let (n, c, s, l) = (cfg.n_ticks, cfg.n_joints, cfg.frame_size, cfg.plan_len());
    let total = n + 6;
    let joints = noise(total * c, 81);
    let plan = noise((total + l) * c, 82);
    let frames: Vec<Vec<f32>> = (0..total)
        .map(|t| noise(3 * s * s, 4000 + t as u64))
        .collect();
    let mut stream = StreamingForecaster::new(&loaded);
    let mut products_kept = false;
    for t in 0..total {
        let window = &plan[t * c..(t + l) * c];
        stream
            .push_parts(
                t as i64,
                &joints[t * c..(t + 1) * c],
                Some(&frames[t]),
                Some(window),
            )
            .unwrap();
        if t + 1 < n {
            stream.prepare().unwrap();
            continue;
        }
        let before = (
            stream.terms_computed(),
            stream.terms_reused(),
            stream.plan_rows(),
        );
        let got = stream.forecast().unwrap();
        let (wj, wf) = stream_window(&cfg, &joints, &frames, t);
        let want = loaded.forecast_arrays(&wj, window, &wf).unwrap();
        for (g, w) in got.iter().zip(&want) {
            assert!(
                (g - w).abs() < 1e-5,
                "tick {t}: streaming {got:?} vs window {want:?}"
            );
        }
        let rows = stream.plan_rows();
        let rows = (rows.0 - before.2 .0, rows.1 - before.2 .1);
        if t + 1 > n {
            let computed = stream.terms_computed() - before.0;
            let reused = stream.terms_reused() - before.1;
            assert!(
                computed > 0 && reused > 0,
                "tick {t}: {computed} terms computed, {reused} reused"
            );
            let want = if products_kept {
                (l as u64 - 1, 1)
            } else {
                (0, l as u64)
            };
            assert_eq!(rows, want, "tick {t}: plan rows reused and multiplied");
        }
        products_kept = rows.1 > 0;
    }
    assert!(
        products_kept,
        "the sliding window keeps the first block's products"
    );
}

#[test]
fn calibration_is_stored_applied_everywhere_and_checked() {
    let cfg = small_config();
    let dir = tempfile::tempdir().unwrap();
    let (mut meta, emp) = model(&cfg, Ablation::EMP);
    let plain = LoadedModel::from_parts(meta.clone(), &emp, cpu_device(), "mem".into());
    let cal = Calibration {
        scale: vec![0.5, 0.8, 1.2, 2.0],
        bias: vec![-1.0, -0.3, 0.2, 0.1],
        neg_scale: None,
        fitted_on: "test".into(),
    };
    meta.calibration = Some(cal.clone());
    let path = dir.path().join("cal.bpk");
    save_model(&path, &meta, &emp).unwrap();
    let loaded = LoadedModel::load(&path).unwrap();
    assert_eq!(loaded.meta.calibration.as_ref(), Some(&cal));

    // Whole window: the calibrated probabilities of the raw logits, ordered.
    let w = window(&cfg, 21);
    let z = plain.logits_arrays(&w.joints, &w.plan, &w.frames).unwrap();
    let raw = plain
        .forecast_arrays(&w.joints, &w.plan, &w.frames)
        .unwrap();
    let got = loaded
        .forecast_arrays(&w.joints, &w.plan, &w.frames)
        .unwrap();
    assert_eq!(got, cal.apply(&z));
    assert_ne!(got, raw, "calibration not applied");
    assert!(got.windows(2).all(|p| p[1] >= p[0]), "{got:?}");

    // Streaming (the daemon's path) applies it too.
    let mut stream = StreamingForecaster::new(&loaded);
    let (n, c, s) = (cfg.n_ticks, cfg.n_joints, cfg.frame_size);
    let frames: Vec<Vec<f32>> = (0..n)
        .map(|t| {
            let mut f = vec![0.0f32; 3 * s * s];
            for ch in 0..3 {
                let base = (ch * n + t) * s * s;
                f[ch * s * s..(ch + 1) * s * s].copy_from_slice(&w.frames[base..base + s * s]);
            }
            f
        })
        .collect();
    for (t, frame) in frames.iter().enumerate() {
        stream
            .push_parts(
                t as i64,
                &w.joints[t * c..(t + 1) * c],
                Some(frame),
                Some(&w.plan),
            )
            .unwrap();
    }
    let streamed = stream.forecast().unwrap();
    for (a, b) in streamed.iter().zip(&got) {
        assert!(
            (a - b).abs() < 1e-5,
            "streaming {streamed:?} vs window {got:?}"
        );
    }

    // Beta calibration: a negative side of its own, a version-2 file that a
    // reader of version 1 (Platt alone) refuses by its magic.
    let beta = Calibration {
        neg_scale: Some(vec![0.5, 2.0, 1.2, 0.7]),
        ..cal.clone()
    };
    meta.calibration = Some(beta.clone());
    let path = dir.path().join("beta.bpk");
    save_model(&path, &meta, &emp).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(&bytes[..8], b"FGEMP\0v2");
    let loaded = LoadedModel::load(&path).unwrap();
    assert_eq!(loaded.meta.calibration.as_ref(), Some(&beta));
    let got = loaded
        .forecast_arrays(&w.joints, &w.plan, &w.frames)
        .unwrap();
    assert_eq!(got, beta.apply(&z));
    let by_hand: Vec<f32> = (0..4)
        .map(|k| {
            let (a, c, b) = (
                beta.scale[k],
                beta.neg_scale.as_ref().unwrap()[k],
                beta.bias[k],
            );
            let q = 1.0 / (1.0 + (-f64::from(z[k])).exp());
            let s = f64::from(c) * q.ln() - f64::from(a) * (1.0 - q).ln() + f64::from(b);
            (1.0 / (1.0 + (-s).exp())) as f32
        })
        .scan(0.0f32, |m, p| {
            *m = m.max(p);
            Some(*m)
        })
        .collect();
    for (a, b) in got.iter().zip(&by_hand) {
        assert!((a - b).abs() < 1e-5, "{got:?} vs {by_hand:?}");
    }
    // The same bytes under version 1's magic: refused, not misread.
    let mut v1 = bytes.clone();
    v1[7] = b'1';
    let v1_path = dir.path().join("beta-v1.bpk");
    std::fs::write(&v1_path, &v1).unwrap();
    let e = LoadedModel::load(&v1_path).unwrap_err();
    assert!(
        matches!(e, ModelError::BadMeta { .. }) && e.to_string().contains("beta calibration"),
        "{e}"
    );
    // Platt scaling stays a version-1 file.
    assert_eq!(
        &std::fs::read(dir.path().join("cal.bpk")).unwrap()[..8],
        b"FGEMP\0v1"
    );

    // A calibration that does not fit the model is refused, naming the file.
    meta.calibration = Some(Calibration {
        scale: vec![1.0, -1.0, 1.0, 1.0],
        ..cal.clone()
    });
    let bad = dir.path().join("badcal.bpk");
    save_model(&bad, &meta, &emp).unwrap();
    let e = LoadedModel::load(&bad).unwrap_err();
    assert!(
        matches!(e, ModelError::BadMeta { .. })
            && e.to_string().contains("badcal.bpk")
            && e.to_string().contains("calibration"),
        "{e}"
    );
    meta.calibration = Some(Calibration {
        neg_scale: Some(vec![1.0, 1.0, 0.0, 1.0]),
        ..cal
    });
    save_model(&bad, &meta, &emp).unwrap();
    let e = LoadedModel::load(&bad).unwrap_err();
    assert!(e.to_string().contains("negative-side scale"), "{e}");
}

/// A small episode whose plan and joints say which tick they belong to:
/// the plan's joint `j` at tick `k` is `k + j/10`, the measured one
/// `1000 + k + j/10`.
fn labelled_episode(c: usize, ticks: i64) -> crate::window::EpisodeTicks {
    use crate::clock::TickGrid;
    use crate::streams::sample::Plan;
    use crate::window::TickInput;
    use std::sync::Arc;
    let grid = TickGrid::new(30.0).unwrap();
    let value = |k: i64, j: usize| k as f64 + j as f64 / 10.0;
    let horizon = ticks + 100;
    let plan = Arc::new(Plan {
        stamp_ns: 0,
        times_ns: (0..horizon).map(|k| grid.stamp_ns(k)).collect(),
        positions_rad: (0..horizon)
            .flat_map(|k| (0..c).map(move |j| value(k, j)))
            .collect(),
        n_joints: c,
    });
    crate::window::EpisodeTicks {
        path: "mem".into(),
        grid,
        ticks: (0..ticks)
            .map(|k| TickInput {
                tick: k,
                stamp_ns: grid.stamp_ns(k),
                joints_rad: Some((0..c).map(|j| (1000.0 + value(k, j)) as f32).collect()),
                frame: None,
                plan: Some(plan.clone()),
                age_ns: Default::default(),
                joint_stamps_ns: None,
            })
            .collect(),
        fall_onset_tick: None,
    }
}

#[test]
fn trajectory_inputs_hold_what_their_names_say_everywhere() {
    use crate::window::Streams;
    let mut cfg = small_config(); // N = 12, h_K = 12
    let (n, c, hk) = (cfg.n_ticks, cfg.n_joints, cfg.max_horizon_ticks());
    let end = 20i64;
    let episode = labelled_episode(c, end + 1);
    let needs = Streams {
        joints: true,
        plan: true,
        camera: false,
    };
    for trajectory in [
        TrajectoryInput::Planned,
        TrajectoryInput::HistoricalOnly,
        TrajectoryInput::RealPosition,
    ] {
        cfg.trajectory = trajectory;
        let (mut meta, emp) = model(&cfg, Ablation::MP);
        // Standardisation that is not the identity, so a mix-up of the
        // plan and joint statistics shows.
        meta.plan_mean = vec![5.0; c];
        meta.plan_std = vec![3.0; c];
        let loaded = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
        let spec = loaded.meta.window_spec();
        let window = episode.window_ending_at(end, &spec, needs).unwrap();
        let rows = cfg.trajectory_rows(&window.joints, &window.plan);
        assert_eq!(rows.len(), cfg.plan_len() * c, "{trajectory}");
        let tick_of_row = |i: usize| end - n as i64 + 1 + i as i64;
        match trajectory {
            TrajectoryInput::Planned => {
                assert_eq!(cfg.plan_len(), n + hk);
                for (i, row) in rows.chunks(c).enumerate() {
                    assert_eq!(row[0], tick_of_row(i) as f32, "planned row {i}");
                }
                // It reaches h_K ticks into the future.
                assert_eq!(rows[rows.len() - c], (end + hk as i64) as f32);
            }
            TrajectoryInput::HistoricalOnly => {
                assert_eq!(cfg.plan_len(), n);
                for (i, row) in rows.chunks(c).enumerate() {
                    assert_eq!(row[1], tick_of_row(i) as f32 + 0.1, "historical row {i}");
                }
                // Nothing from after the window's last tick.
                assert!(rows.iter().all(|&v| v < end as f32 + 1.0), "{rows:?}");
            }
            TrajectoryInput::RealPosition => {
                assert_eq!(cfg.plan_len(), n);
                assert_eq!(rows, window.joints.as_slice());
                assert_eq!(rows[0], 1000.0 + tick_of_row(0) as f32);
            }
        }
        // The daemon's path (tick by tick through the streaming forecaster,
        // with only the streams the model reads) builds the same input.
        let mut stream = StreamingForecaster::new(&loaded);
        for tick in &episode.ticks {
            let mut tick = tick.clone();
            if !trajectory.reads_plan() {
                tick.plan = None;
            }
            stream.push(&tick).unwrap();
        }
        let got = stream.forecast().unwrap();
        let want = loaded.forecast_window(&window).unwrap();
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 1e-5, "{trajectory}: {got:?} vs {want:?}");
        }
        // The setting is in the model file and read back.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.bpk");
        save_model(&path, &loaded.meta, &emp).unwrap();
        assert_eq!(
            LoadedModel::load(&path).unwrap().meta.config.trajectory,
            trajectory
        );
    }
}

#[test]
fn a_model_file_without_a_trajectory_setting_reads_as_planned() {
    let cfg = small_config();
    let mut json = serde_json::to_value(&cfg).unwrap();
    json.as_object_mut().unwrap().remove("trajectory");
    let back: ModelConfig = serde_json::from_value(json).unwrap();
    assert_eq!(back.trajectory, TrajectoryInput::Planned);
    assert_eq!(back, cfg);
}

/// The host GELU of the trajectory encoder equals burn's (erf from libm)
/// within 1e-6 · max(1, |x|) (a few f32 ulps of large x) over the range
/// activations take, and saturates beyond it.
#[test]
fn host_gelu_equals_burn_gelu() {
    let device = Default::default();
    let xs: Vec<f32> = (0..40_001).map(|i| -20.0 + i as f32 * 1e-3).collect();
    let want: Vec<f32> = burn::tensor::activation::gelu(Tensor::<1>::from_data(
        TensorData::new(xs.clone(), [xs.len()]),
        &device,
    ))
    .into_data()
    .try_to_vec::<f32>()
    .expect("f32");
    let mut got = xs.clone();
    plan::gelu_in_place(&mut got);
    let worst = got
        .iter()
        .zip(&want)
        .zip(&xs)
        .map(|((g, w), x)| ((g - w).abs() / x.abs().max(1.0), *x))
        .fold((0.0f32, 0.0f32), |a, b| if b.0 > a.0 { b } else { a });
    assert!(
        worst.0 < 1e-6,
        "largest difference {} at x = {}",
        worst.0,
        worst.1
    );
}

/// Every output slice of a short sequence summed from its terms
/// ([`host_conv::HostConv::slice_terms`], [`host_conv::HostConv::pooled_of_terms`])
/// equals `conv3d` ("same" padding), ReLU and the spatial pool, the
/// window's ends included.
#[test]
fn slice_conv_equals_conv3d_same_padding() {
    use burn::tensor::activation::relu;
    use burn::tensor::module::conv3d;
    use burn::tensor::ops::ConvOptions;
    let device = Default::default();
    let (c_in, c_out, k, hw, t) = (3, 5, 3, 8, 4);
    let signed = |n, seed| {
        noise(n, seed)
            .iter()
            .map(|v| 2.0 * v - 1.0)
            .collect::<Vec<f32>>()
    };
    let weight = Tensor::<5>::from_data(
        TensorData::new(signed(c_out * c_in * k * k * k, 1), [c_out, c_in, k, k, k]),
        &device,
    );
    let bias = Tensor::<1>::from_data(TensorData::new(signed(c_out, 2), [c_out]), &device);
    let conv = inception::FusedConv {
        weight: weight.clone(),
        bias: bias.clone(),
        kernel: k,
    };
    let x = signed(c_in * t * hw * hw, 3);
    let xt = Tensor::<5>::from_data(TensorData::new(x.clone(), [1, c_in, t, hw, hw]), &device);
    let want = vision::spatial_pool(relu(conv3d(
        xt,
        weight,
        Some(bias),
        ConvOptions::new([1, 1, 1], [1, 1, 1], [1, 1, 1], 1),
    )));
    let want: Vec<f32> = want.into_data().try_to_vec::<f32>().expect("f32");
    // Per-slice inputs [C_in, hw, hw].
    let plane = hw * hw;
    let slices: Vec<Vec<f32>> = (0..t)
        .map(|ti| {
            (0..c_in)
                .flat_map(|ci| x[(ci * t + ti) * plane..(ci * t + ti + 1) * plane].to_vec())
                .collect()
        })
        .collect();
    let sc = host_conv::HostConv::from_fused(&conv);
    let ho = hw / 2;
    for j in 0..t {
        let terms: Vec<Vec<f32>> = (0..k)
            .filter_map(|kt| {
                let input = (j + kt).checked_sub(1).and_then(|i| slices.get(i))?;
                Some(sc.slice_terms(input, &[kt], hw, &mut Vec::new()).remove(0))
            })
            .collect();
        let terms: Vec<&[f32]> = terms.iter().map(Vec::as_slice).collect();
        let got = sc.pooled_of_terms(&terms, hw);
        for co in 0..c_out {
            for m in 0..ho * ho {
                let w = want[(co * t + j) * ho * ho + m];
                let g = got[co * ho * ho + m];
                assert!(
                    (g - w).abs() < 1e-5,
                    "slice {j} ch {co} pos {m}: {g} vs {w}"
                );
            }
        }
    }
}

/// The trajectory encoder's training path (period grids as tap gathers and
/// matmuls, grouped by period) is the definition: per sample and period,
/// the plan folded into a zero-padded grid, `conv2d` -> GELU -> `conv2d`,
/// cut back to the plan, weighted and summed. Same outputs, and the same
/// gradients reach the input, the softmax weights and both kernels.
#[test]
fn grouped_period_grids_are_the_per_sample_convolutions() {
    use burn::tensor::activation::gelu;
    fn vec_of<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_to_vec::<f32>().unwrap()
    }
    let device = cpu_device().autodiff();
    let (b, l, d, k) = (3, 13, 4, 2);
    // Shared and distinct periods, one longer than half the plan, one that
    // divides it unevenly (the grid's last row is partly past the plan).
    let periods = vec![vec![5, 13], vec![5, 3], vec![7, 1]];
    let inc_in = inception::Inception2d::new(d, 6, 3, &device);
    let inc_out = inception::Inception2d::new(6, d, 3, &device);
    let x = Tensor::<3>::from_data(TensorData::new(noise(b * l * d, 31), [b, l, d]), &device);
    let weights = Tensor::<3>::from_data(TensorData::new(noise(b * k, 32), [b, 1, k]), &device);
    let target = Tensor::<3>::from_data(TensorData::new(noise(b * l * d, 33), [b, l, d]), &device);
    let run = |grouped: bool| -> Vec<Vec<f32>> {
        let (x, weights) = (x.clone().require_grad(), weights.clone().require_grad());
        let convs = [inc_in.fuse_differentiable(), inc_out.fuse_differentiable()];
        let y = if grouped {
            plan::grouped_periods(&x, &periods, weights.clone(), &convs)
        } else {
            let samples = (0..b)
                .map(|s| {
                    let xs = x.clone().slice([s..s + 1, 0..l, 0..d]);
                    periods[s]
                        .iter()
                        .enumerate()
                        .map(|(i, &p)| {
                            let rows = l.div_ceil(p);
                            let grid = Tensor::cat(
                                vec![xs.clone(), Tensor::zeros([1, rows * p - l, d], &device)],
                                1,
                            )
                            .reshape([1, rows, p, d])
                            .permute([0, 3, 1, 2]);
                            let y = convs[1].forward(gelu(convs[0].forward(grid)));
                            let y = y.permute([0, 2, 3, 1]).reshape([1, rows * p, d]).slice([
                                0..1,
                                0..l,
                                0..d,
                            ]);
                            y * weights.clone().slice([s..s + 1, 0..1, i..i + 1])
                        })
                        .reduce(|a, y| a + y)
                        .unwrap()
                })
                .collect();
            Tensor::cat(samples, 0)
        };
        let g = (y.clone() * target.clone()).sum().backward();
        let mut out = vec![
            vec_of(y),
            vec_of(x.grad(&g).expect("input gradient")),
            vec_of(weights.grad(&g).expect("weights gradient")),
        ];
        for c in inc_in.branches().iter().chain(inc_out.branches()) {
            out.push(vec_of(c.weight.val().grad(&g).expect("kernel gradient")));
        }
        out
    };
    let (got, want) = (run(true), run(false));
    assert_eq!(got.len(), 9);
    for (a, b) in got.iter().zip(&want) {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
        assert!(
            a.iter().zip(b).all(|(p, q)| (p - q).abs() <= 1e-5 * scale),
            "{a:?} vs {b:?}"
        );
    }
}

/// Trajectory features computed ahead of their tick give bit for bit the
/// forecast computed at the tick, are used only when the tick's plan window
/// is the one they were computed for (a new plan, or a guess for another
/// window, is computed at the tick), and equal the whole-window forward.
#[test]
fn plan_features_computed_ahead_change_nothing() {
    let cfg = small_config();
    for ablation in [Ablation::EMP, Ablation::MP] {
        let (meta, emp) = model(&cfg, ablation);
        let loaded = LoadedModel::from_parts(meta, &emp, cpu_device(), "mem".into());
        let (c, s, l) = (cfg.n_joints, cfg.frame_size, cfg.plan_len());
        let total = cfg.n_ticks + 9;
        let joints = noise(total * c, 79);
        let frames: Vec<Vec<f32>> = (0..total)
            .map(|t| noise(3 * s * s, 3000 + t as u64))
            .collect();
        // The plan window of tick t: a new message every fourth tick.
        let plan_of = |t: usize| noise(l * c, 6000 + (t / 4) as u64);
        let mut ahead = StreamingForecaster::new(&loaded);
        let mut plain = StreamingForecaster::new(&loaded);
        let mut reused = 0;
        for t in 0..total {
            let plan = plan_of(t);
            let frame = ablation.uses_vision().then_some(frames[t].as_slice());
            for f in [&mut ahead, &mut plain] {
                f.push_parts(
                    100 + t as i64,
                    &joints[t * c..(t + 1) * c],
                    frame,
                    Some(&plan),
                )
                .unwrap();
            }
            if t + 1 < cfg.n_ticks {
                continue;
            }
            let got = ahead.forecast().unwrap();
            let want = plain.forecast().unwrap();
            assert_eq!(got, want, "{ablation} tick {t}");
            let (wj, wf) = stream_window(&cfg, &joints, &frames, t);
            let window = loaded.forecast_arrays(&wj, &plan, &wf).unwrap();
            for (g, w) in got.iter().zip(&window) {
                assert!(
                    (g - w).abs() < 1e-5,
                    "{ablation} tick {t}: {got:?} vs {window:?}"
                );
            }
            // The guess for the next tick: this tick's plan message.
            ahead.precompute_plan(101 + t as i64, &plan).unwrap();
            if t + 1 < total && plan_of(t + 1) == plan {
                reused += 1;
            }
        }
        assert_eq!(ahead.plan_reused(), reused, "{ablation}");
        assert!(reused > 0 && reused < 9, "{ablation}: {reused}");
        assert_eq!(plain.plan_reused(), 0);
    }
}
