//! `fall-guard-lab finetune` end to end on the bundled data: the shipped MP
//! network fine-tuned on the real Poppy walk (its first 60%) mixed with the
//! fixture set, for one epoch; the card measures both networks on the last
//! 40% of the walk and on the fixture set's test falls.

use std::path::{Path, PathBuf};

use fall_guard_lab::device::TrainDevice;
use fall_guard_lab::finetune::{run_finetune, FinetuneOptions};
use fall_guard_runtime::model::file::load_emp;
use fall_guard_runtime::model::{cpu_device, LoadedModel};

fn repo(path: &str) -> PathBuf {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join(path)
}

#[test]
fn a_shipped_network_is_fine_tuned_on_the_first_part_of_a_walk_and_measured_on_the_rest() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("ft");
    let args = FinetuneOptions {
        model: repo("models/mp.bpk"),
        recordings: vec![repo("tests/fixtures/real/poppy_muffin_walk.mcap")],
        data: repo("tests/fixtures"),
        out: out.clone(),
        holdout: 0.4,
        owner_copies: 2,
        epochs: 1,
        lr_scale: 0.1,
        seed: 1,
        horizon_ms: 2000,
        release_hold_ms: 1000,
        // The shipped MP's pair, read from the daemon's config.
        pair: None,
        config: Some(repo("config/poppy_humanoid.toml")),
        // The pair chosen on the fixture set's own validation split.
        choice: Some(repo("tests/fixtures")),
        max_false_alarms_per_min: 0.1,
        max_held_share: 0.01,
        device: TrainDevice::Cpu,
    };
    let card = run_finetune(&args).expect("fine-tune");

    // The walk is 35.6 s: 60% trained on, 40% held back.
    assert!(
        (card.owner_fit_s - 21.4).abs() < 0.5,
        "{}",
        card.owner_fit_s
    );
    assert!(
        (card.owner_held_s - 14.3).abs() < 0.5,
        "{}",
        card.owner_held_s
    );
    assert_eq!(card.owner_falls, 0);
    // Both networks measured on the same held-back ticks and test falls.
    for m in [&card.shipped, &card.finetuned] {
        assert!(m.owner.non_falling_minutes > 0.15, "{m:?}");
        assert_eq!(m.owner.falling_episodes, 0);
        assert_eq!(
            m.simulated.falling_episodes, 1,
            "the fixture test split's fall"
        );
        assert!((0.0..=1.0).contains(&m.owner.held_share));
    }
    assert_eq!(
        card.shipped.owner.non_falling_minutes,
        card.finetuned.owner.non_falling_minutes
    );
    // The shipped pair is the config's line for MP.
    let mp = fall_guard_runtime::config::Config::load(&repo("config/poppy_humanoid.toml"))
        .and_then(|c| c.latch_thresholds())
        .expect("config")
        .of(fall_guard_runtime::model::Ablation::MP);
    assert_eq!(
        (card.shipped.trigger, card.shipped.release),
        (mp.trigger(), mp.release())
    );

    // The new network: the shipped one's sizes and standardisation, new
    // weights, input ranges of the mixed training split, and says so.
    let (shipped, shipped_net) = load_emp(&repo("models/mp.bpk"), &cpu_device()).expect("shipped");
    let path = out.join("mp.finetuned.bpk");
    let (tuned, tuned_net) = load_emp(&path, &cpu_device()).expect("fine-tuned");
    assert_eq!(tuned.config, shipped.config);
    assert_eq!(tuned.joint_std, shipped.joint_std);
    assert_eq!(tuned.plan_mean, shipped.plan_mean);
    assert!(
        tuned
            .trained_on
            .contains("fine-tuned on 21 s of the owner's recordings"),
        "{}",
        tuned.trained_on
    );
    assert!(
        tuned.trained_on.contains("learning rates x0.1"),
        "{}",
        tuned.trained_on
    );
    assert!(tuned.calibration.is_some(), "calibrated again");
    let ranges = tuned.input_ranges.as_ref().expect("ranges");
    assert!(ranges.measured_on.contains("train split"), "{ranges:?}");
    // abs_x swings +-36 deg on the real walk: the ranges hold it now.
    let abs_x = shipped
        .joint_names
        .iter()
        .position(|n| n == "abs_x")
        .expect("abs_x");
    assert!(
        ranges.joints[abs_x][1].to_degrees() > 20.0,
        "{:?}",
        ranges.joints[abs_x]
    );
    let weights = |m: &fall_guard_runtime::model::Emp| {
        use burn::module::Module;
        m.clone().into_record().into_bytes().expect("bytes").len()
    };
    assert_eq!(weights(&tuned_net), weights(&shipped_net));
    let a = LoadedModel::load(repo("models/mp.bpk")).expect("load");
    let b = LoadedModel::load(&path).expect("load");
    let (j, p) = (
        vec![0.0f32; a.meta.n_ticks * a.meta.config.n_joints],
        vec![0.0f32; a.meta.config.plan_len() * a.meta.config.n_joints],
    );
    assert_ne!(
        a.forecast_arrays(&j, &p, &[]).expect("a"),
        b.forecast_arrays(&j, &p, &[]).expect("b"),
        "the weights moved"
    );

    // The card, in both forms.
    let md = std::fs::read_to_string(out.join("card.md")).expect("card.md");
    assert!(
        md.contains("| shipped |") && md.contains("| fine-tuned |"),
        "{md}"
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("card.json")).expect("card.json"))
            .expect("json");
    assert!(json["finetuned"]["owner"]["held_share"].is_number());
}
