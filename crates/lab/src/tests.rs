//! Training on the simulator's fixtures and the shipped networks, and the
//! masked loss. (Training on synthetic tasks where falls are learnable, with
//! the test kit's windows and recordings: `tests/train_synthetic.rs`.)

use super::fit::*;
use fall_guard_runtime::model::LoadedModel;

#[test]
fn masked_loss_counts_only_the_scored_labels() {
    use burn::prelude::*;
    let device = fall_guard_runtime::model::cpu_device();
    let t = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, [2, 2]), &device);
    // Window 0 scores horizon 0, window 1 horizon 1; the unscored labels
    // are badly wrong and must not count.
    let logits = t(vec![2.0, 9.0, -9.0, -1.0]);
    let labels = t(vec![1.0, 0.0, 1.0, 0.0]);
    let mask = t(vec![1.0, 0.0, 0.0, 1.0]);
    let got: f32 = masked_bce_with_logits(logits, labels, mask).into_scalar();
    let bce = |z: f32, y: f32| z.max(0.0) - z * y + (-z.abs()).exp().ln_1p();
    let want = (bce(2.0, 1.0) + bce(-1.0, 0.0)) / 2.0;
    assert!((got - want).abs() < 1e-6, "{got} vs {want}");
}

/// A tiny run of `train --per-horizon --protocol paper` on the simulator's
/// fixtures (their content changes; nothing here depends on it): one
/// network per horizon, each forecasting that horizon only with a plan
/// reaching that far, and `eval` reports both protocols for it.
#[test]
fn per_horizon_paper_training_on_the_fixtures() {
    use super::commands::{per_horizon_path, run_eval, run_train, EvalOptions, TrainOptions};
    use super::sampler::Protocol;
    let _turn = fixture_training_turn();
    let data =
        std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("tests/fixtures");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("mp.bpk");
    let horizons = vec![10, 20];
    let args = TrainOptions {
        protocol: Protocol::Paper,
        per_horizon: true,
        ..fixture_training("MP", out.clone())
    };
    run_train(&args).unwrap();
    assert!(!out.exists(), "no all-horizon file with --per-horizon");
    let ckpt = super::commands::default_checkpoint_dir(&out);
    assert_eq!(ckpt, dir.path().join("mp.bpk.ckpt"));
    assert!(
        !ckpt.exists(),
        "the checkpoint is removed once every file is written"
    );
    resume_skips_the_written_horizons(&args, &horizons);
    for &h in &horizons {
        let path = per_horizon_path(&out, h);
        assert_eq!(path, dir.path().join(format!("mp.h{h}.bpk")));
        let m = LoadedModel::load(&path).unwrap();
        assert_eq!(m.meta.horizons_ticks, vec![h]);
        assert_eq!(m.meta.config.plan_len(), 20 + h);
        assert_eq!(m.meta.protocol.as_deref(), Some("paper"));
        let eval_dir = dir.path().join(format!("eval{h}"));
        run_eval(&EvalOptions {
            model: path,
            seeds: vec![],
            data: Some(data.clone()),
            split: "test".into(),
            out: Some(eval_dir.clone()),
            sample_seed: 3,
            draws: 1,
            protocol: Protocol::Paper,
            recording: None,
            per_tick_out: None,
            projection: fall_guard_runtime::model::ProjectionWeights::AsFile,
            convolutions: fall_guard_runtime::model::Convolutions::F32,
        })
        .unwrap();
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(eval_dir.join("metrics.json")).unwrap()).unwrap();
        assert_eq!(v["protocol"], "paper");
        let names: Vec<&str> = v["protocols"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["protocol"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["paper", "deployment"]);
        for p in v["protocols"].as_array().unwrap() {
            let hs = p["horizons"].as_array().unwrap();
            assert_eq!(hs.len(), 1);
            assert_eq!(hs[0]["horizon_ticks"], h);
            assert_eq!(hs[0]["ece_ci95"].as_array().unwrap().len(), 1);
        }
        let md = std::fs::read_to_string(eval_dir.join("metrics.md")).unwrap();
        assert!(
            md.contains("## Protocol: paper") && md.contains("## Protocol: deployment"),
            "{md}"
        );
    }
}

/// A per-horizon run stopped after its first network resumes at the
/// second: the first, marked done in the checkpoint, is not trained again
/// (its file is left as it is), the second is trained as before (the same
/// bytes: training is deterministic); the checkpoint goes at the end. A
/// checkpoint of other arguments is refused, naming them.
fn resume_skips_the_written_horizons(args: &super::commands::TrainOptions, horizons: &[usize]) {
    use super::commands::{default_checkpoint_dir, per_horizon_path, run_arguments, run_train};
    let ckpt = default_checkpoint_dir(&args.out);
    let (first, second) = (
        per_horizon_path(&args.out, horizons[0]),
        per_horizon_path(&args.out, horizons[1]),
    );
    let (first_bytes, second_bytes) = (
        std::fs::read(&first).unwrap(),
        std::fs::read(&second).unwrap(),
    );
    // The state a run stopped while training the second network leaves
    // (its epochs aside): the first written and marked done. The first's
    // file is replaced by another model to show it is not rewritten.
    std::fs::create_dir_all(&ckpt).unwrap();
    let dataset = super::dataset::Dataset::open(&args.data).unwrap();
    std::fs::write(
        ckpt.join("args.json"),
        serde_json::to_vec(&run_arguments(args, &dataset)).unwrap(),
    )
    .unwrap();
    std::fs::write(ckpt.join(format!("h{}.done", horizons[0])), b"").unwrap();
    std::fs::copy(&second, &first).unwrap();
    run_train(args).unwrap();
    assert_eq!(
        std::fs::read(&first).unwrap(),
        second_bytes,
        "first retrained"
    );
    assert_eq!(std::fs::read(&second).unwrap(), second_bytes);
    assert!(!ckpt.exists());
    // Another run's checkpoint in the way: refused.
    std::fs::create_dir_all(&ckpt).unwrap();
    let mut other = run_arguments(args, &dataset);
    other["seed"] = serde_json::json!(args.seed + 1);
    std::fs::write(ckpt.join("args.json"), serde_json::to_vec(&other).unwrap()).unwrap();
    let e = format!("{:#}", run_train(args).unwrap_err());
    assert!(e.contains("other arguments") && e.contains("seed"), "{e}");
    std::fs::remove_dir_all(&ckpt).unwrap();
    // The first network back for the checks that follow.
    std::fs::write(&first, first_bytes).unwrap();
}

/// Held by each test here that trains on the fixtures: a run's bytes are
/// compared with a rerun's (resume), and another test's training or
/// evaluation beside it changes them, so they take turns.
fn fixture_training_turn() -> std::sync::MutexGuard<'static, ()> {
    static TURN: std::sync::Mutex<()> = std::sync::Mutex::new(());
    TURN.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// One epoch on the fixtures (20-tick windows, horizons 10 and 20 ticks,
/// deployment protocol), written to OUT.
fn fixture_training(ablation: &str, out: std::path::PathBuf) -> super::commands::TrainOptions {
    super::commands::TrainOptions {
        data: std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
            .join("tests/fixtures"),
        ablation: ablation.into(),
        config: "lite".into(),
        seed: 1,
        out,
        epochs: 1,
        patience: 1,
        batch: 4,
        rates: "sim".into(),
        vision_lr: None,
        lr_scale: 1.0,
        n_ticks: 20,
        horizons: vec![10, 20],
        rate_hz: 30.0,
        frame_size: 64,
        joint_names: None,
        trained_on: "fixtures".into(),
        quiet: true,
        init: None,
        device: super::device::TrainDevice::Cpu,
        protocol: super::sampler::Protocol::Deployment,
        per_horizon: false,
        trajectory: fall_guard_runtime::model::TrajectoryInput::Planned,
        checkpoint_dir: None,
    }
}

/// `--vision-lr`: refused unless a positive number, or for a network
/// without a vision encoder,
/// kept in the model file, and part of the arguments a run resumes on only
/// when given (runs started without it still resume).
#[test]
fn vision_learning_rate_is_checked_kept_and_resumed_on() {
    use super::commands::{run_arguments, run_train, TrainOptions};
    let _turn = fixture_training_turn();
    let dir = tempfile::tempdir().unwrap();
    let mut args = fixture_training("EP", dir.path().join("ep.bpk"));
    let data = args.data.clone();
    for bad in [0.0, -1e-4, f64::NAN] {
        args.vision_lr = Some(bad);
        let e = format!("{:#}", run_train(&args).unwrap_err());
        assert!(e.contains("--vision-lr"), "{e}");
    }
    for blind in ["logreg", "MP", "P"] {
        let without = TrainOptions {
            ablation: blind.into(),
            vision_lr: Some(1e-4),
            ..args.clone()
        };
        let e = format!("{:#}", run_train(&without).unwrap_err());
        assert!(e.contains(&format!("{blind} has no vision encoder")), "{e}");
    }
    assert!(!args.out.exists(), "nothing written by a refused run");

    let dataset = super::dataset::Dataset::open(&data).unwrap();
    args.vision_lr = None;
    assert!(run_arguments(&args, &dataset).get("vision_lr").is_none());
    args.vision_lr = Some(1e-4);
    assert_eq!(run_arguments(&args, &dataset)["vision_lr"], 1e-4);
    run_train(&args).unwrap();
    assert_eq!(
        LoadedModel::load(&args.out).unwrap().meta.vision_lr,
        Some(1e-4)
    );
}

/// The shipped networks with their input projection in int8 forecast what
/// they forecast with it as stored (f16), within 0.02 on every tick and
/// horizon of a recorded episode (`[model].projection`; the model card
/// gives the figures over the simulated validation and test episodes).
#[test]
fn int8_projection_moves_the_shipped_forecasts_by_little() {
    use super::commands::{forecast_ticks, needs_of_model};
    use fall_guard_runtime::model::ProjectionWeights;
    let root = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."));
    let recording = root.join("tests/fixtures/episode_00005.mcap");
    for net in ["emp", "p"] {
        let stored = LoadedModel::load(root.join("models").join(format!("{net}.bpk"))).unwrap();
        let int8 = stored.clone().with_projection(ProjectionWeights::Int8);
        // Half of f16, plus one f32 scale per input row.
        let (b16, b8) = (
            stored.network.projection_bytes(),
            int8.network.projection_bytes(),
        );
        assert!(
            b8 * 100 < b16 * 52,
            "{net}: {b8} bytes in int8, {b16} as stored"
        );
        let spec = stored.meta.window_spec();
        let episode =
            crate::dataset::load_episode(&recording, &spec, needs_of_model(&stored.meta)).unwrap();
        let a = forecast_ticks(&stored, &episode).unwrap();
        let b = forecast_ticks(&int8, &episode).unwrap();
        assert_eq!(a.len(), b.len());
        assert!(a.len() > 100, "{net}: {} forecasts", a.len());
        let worst = a
            .iter()
            .zip(&b)
            .flat_map(|(x, y)| x.2.iter().zip(&y.2).map(|(p, q)| (p - q).abs()))
            .fold(0.0f32, f32::max);
        assert!(worst > 0.0, "{net}: int8 changed nothing: not int8");
        assert!(worst < 0.02, "{net}: int8 moved a forecast by {worst}");
    }
}
