//! Training is deterministic for a seed on one machine. In a process of its
//! own: burn's random generator is global to a process, and other tests
//! creating networks at the same time would draw from it.

use fall_guard::model::{Ablation, ModelConfig, ModelMeta};
use fall_guard::train::synthetic::RampEpisodes;
use fall_guard::train::{fit, FitOptions};

#[test]
fn training_is_deterministic_for_a_seed() {
    let mut cfg = ModelConfig::lite(24, 4, vec![3, 6, 9, 12], 32);
    cfg.d_model = 128;
    cfg.inc_dim = 8;
    cfg.plan_d = 8;
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let run = |seed: u64| {
        let meta = ModelMeta::new(cfg.clone(), Ablation::MP, 30.0, names.clone());
        let mut source = RampEpisodes {
            cfg: cfg.clone(),
            per_epoch: 16,
            seed: 3,
        };
        let opts = FitOptions {
            seed,
            max_epochs: 2,
            progress: false,
            ..FitOptions::default()
        };
        fit(meta, &mut source, &opts).expect("fit").0.history
    };
    let first = run(7);
    assert_eq!(first, run(7), "same seed, same history");
    assert_ne!(first, run(8), "another seed, another history");
}
