//! Training end to end on synthetic tasks where falls are learnable (the
//! test kit's windows and recordings): the training loop, the logistic
//! baseline, and the `train` and `eval` commands.

use fall_guard_lab::{fit, FitOptions};
use fall_guard_runtime::model::{save_model, Ablation, LoadedModel, ModelMeta};
#[path = "support/windows.rs"]
mod windows;
use windows::{small_config, RampEpisodes};

#[test]
fn learns_a_learnable_fall_task_and_the_file_reproduces_it() {
    let cfg = small_config();
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let meta = ModelMeta::new(cfg.clone(), Ablation::P, 30.0, names);
    let mut source = RampEpisodes {
        cfg: cfg.clone(),
        per_epoch: 400,
        seed: 1,
    };
    let opts = FitOptions {
        seed: 1,
        progress: false,
        ..FitOptions::default()
    };
    let (meta, model) = fit(meta, &mut source, &opts).unwrap();
    assert!(meta.best_epoch >= 1 && !meta.history.is_empty());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ramp.bpk");
    save_model(&path, &meta, &model).unwrap();
    let loaded = LoadedModel::load(&path).unwrap();
    let test = source.windows(200, 999);
    let (mut correct, mut total) = (0usize, 0usize);
    for w in &test {
        let p = loaded
            .forecast_arrays(&w.joints, &w.plan, &w.frames)
            .unwrap();
        for (pi, yi) in p.iter().zip(&w.labels) {
            correct += usize::from((*pi >= 0.5) == (*yi > 0.5));
            total += 1;
        }
    }
    let acc = correct as f64 / total as f64;
    assert!(
        acc > 0.9,
        "test accuracy {acc:.3}; history {:?}",
        meta.history
    );
}

#[test]
fn logistic_baseline_learns_the_ramp_task_and_round_trips() {
    use fall_guard_lab::logreg::LogRegModel;
    let cfg = small_config();
    let source = RampEpisodes {
        cfg: cfg.clone(),
        per_epoch: 0,
        seed: 5,
    };
    let train = source.windows(300, 1);
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let m = LogRegModel::fit(&train, cfg.horizons_ticks.clone(), 30.0, cfg.n_ticks, names).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("logreg.json");
    m.save(&path).unwrap();
    let m = LogRegModel::load(&path).unwrap().expect("a logreg file");
    let test = source.windows(200, 2);
    let (mut correct, mut total) = (0usize, 0usize);
    for w in &test {
        for (p, y) in m.predict(w).unwrap().iter().zip(&w.labels) {
            correct += usize::from((*p >= 0.5) == (*y > 0.5));
            total += 1;
        }
    }
    let acc = correct as f64 / total as f64;
    assert!(acc > 0.8, "baseline accuracy {acc:.3}");
}

/// Recordings written by the data plane's synthetic writer, trained on and
/// evaluated by the real commands; the offline per-tick forecast (streaming,
/// as the daemon runs it) equals the whole-window forecast of the windows
/// `window.rs` builds from the same recording.
#[test]
fn train_and_eval_commands_on_synthetic_recordings() {
    use fall_guard_lab::commands::{
        per_tick_forecast, run_eval, run_train, EvalOptions, TrainOptions,
    };
    use fall_guard_testkit::recordings::{joint_names, learnable_episode, write_dataset};
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let names = joint_names(4);
    let (rate, ticks, size) = (10.0, 70usize, 32u32);
    let eps = |from: u64, count: u64| -> Vec<_> {
        (from..from + count)
            .map(|s| learnable_episode(s, s % 2 == 0, ticks, &names, rate, size))
            .collect()
    };
    write_dataset(&data, &eps(0, 80), &eps(1000, 16), &eps(2000, 24)).unwrap();
    let model_path = dir.path().join("models/emp.bpk");
    let args = TrainOptions {
        data: data.clone(),
        ablation: "EMP".into(),
        config: "lite".into(),
        seed: 1,
        out: model_path.clone(),
        epochs: 10,
        patience: 3,
        batch: 4,
        rates: "sim".into(),
        vision_lr: None,
        lr_scale: 1.0,
        n_ticks: 12,
        horizons: vec![3, 6, 9, 12],
        rate_hz: rate,
        frame_size: size,
        joint_names: Some(names.clone()),
        trained_on: "synthetic".into(),
        quiet: true,
        init: None,
        device: fall_guard_lab::TrainDevice::Cpu,
        protocol: fall_guard_lab::sampler::Protocol::Deployment,
        per_horizon: false,
        trajectory: fall_guard_runtime::model::TrajectoryInput::Planned,
        checkpoint_dir: None,
    };
    run_train(&args).unwrap();
    let out = dir.path().join("eval");
    let eval = EvalOptions {
        model: model_path.clone(),
        seeds: vec![],
        data: Some(data.clone()),
        split: "test".into(),
        out: Some(out.clone()),
        sample_seed: 3,
        draws: 4,
        protocol: fall_guard_lab::sampler::Protocol::Deployment,
        recording: None,
        per_tick_out: None,
        projection: fall_guard_runtime::model::ProjectionWeights::AsFile,
        convolutions: fall_guard_runtime::model::Convolutions::F32,
    };
    run_eval(&eval).unwrap();
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).unwrap()).unwrap();
    for f in ["metrics.md", "roc.png", "reliability.png", "training.png"] {
        assert!(out.join(f).metadata().unwrap().len() > 100, "{f}");
    }
    let acc: Vec<f64> = metrics["horizons"]
        .as_array()
        .unwrap()
        .iter()
        .map(|h| h["accuracy"]["mean"].as_f64().unwrap())
        .collect();
    let mean_acc = acc.iter().sum::<f64>() / acc.len() as f64;
    assert!(mean_acc > 0.9, "test accuracy per horizon {acc:?}");
    // Both protocols are reported; under the paper's each horizon is scored
    // on its own set, balanced at it (each draw exactly).
    let protocols = metrics["protocols"].as_array().unwrap();
    assert_eq!(protocols.len(), 2);
    assert_eq!(protocols[0]["protocol"], "deployment");
    assert_eq!(protocols[0]["horizons"], metrics["horizons"]);
    assert_eq!(protocols[1]["protocol"], "paper");
    for h in protocols[1]["horizons"].as_array().unwrap() {
        assert!(h["windows"].as_u64().unwrap() > 0, "{h}");
        assert_eq!(h["positive_rate"].as_f64().unwrap(), 0.5, "{h}");
        let ci = &h["ece_ci95"][0];
        assert!(ci["lower"].as_f64().unwrap() <= ci["upper"].as_f64().unwrap());
        assert!(ci["floor"].as_f64().unwrap() <= ci["floor_upper"].as_f64().unwrap());
    }

    // `calibrate` on the validation split (never on train): a calibration
    // per horizon in the written file (f16), which `eval` reads.
    use fall_guard_lab::calibrate::{run_calibrate, CalibrateOptions};
    let calibrated = dir.path().join("models/emp.cal.bpk");
    let mut cal = CalibrateOptions {
        model: model_path.clone(),
        data: data.clone(),
        split: "train".into(),
        draws: 4,
        sample_seed: 5,
        protocol: fall_guard_lab::sampler::Protocol::Paper,
        out: calibrated.clone(),
        half: true,
        form: Default::default(),
    };
    let refused = run_calibrate(&cal).unwrap_err().to_string();
    assert!(refused.contains("--split train"), "{refused}");
    assert!(!calibrated.exists());
    cal.split = "validation".into();
    run_calibrate(&cal).unwrap();
    let model = LoadedModel::load(&calibrated).unwrap();
    let c = model.meta.calibration.clone().expect("a calibration");
    assert_eq!(c.scale.len(), 4);
    assert!(c.scale.iter().all(|&a| a >= 0.001), "{c:?}");
    assert!(
        c.fitted_on.starts_with("validation split"),
        "{}",
        c.fitted_on
    );
    let eval_cal = EvalOptions {
        model: calibrated.clone(),
        out: Some(dir.path().join("eval-cal")),
        ..eval.clone()
    };
    run_eval(&eval_cal).unwrap();

    // Streaming per tick == window.rs windows through the whole-window forward.
    let model = LoadedModel::load(&model_path).unwrap();
    let rec = data.join("episode_0096.mcap");
    let jsonl = dir.path().join("per_tick.jsonl");
    let lines = per_tick_forecast(&model, &rec, &jsonl).unwrap();
    assert!(lines > 20);
    let spec = model.meta.window_spec();
    let needs = fall_guard_lab::commands::needs_of_model(&model.meta);
    let episode = fall_guard_lab::dataset::load_episode(&rec, &spec, needs).unwrap();
    for line in std::fs::read_to_string(&jsonl).unwrap().lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        let tick = v["tick"].as_i64().unwrap();
        let window = episode.window_ending_at(tick, &spec, needs).unwrap();
        let want = model.forecast_window(&window).unwrap();
        for (g, w) in v["probabilities"].as_array().unwrap().iter().zip(&want) {
            assert!(
                (g.as_f64().unwrap() - *w as f64).abs() < 1e-5,
                "tick {tick}: {v} vs {want:?}"
            );
        }
    }
}
