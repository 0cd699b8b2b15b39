//! The i.i.d. window sampler and the data set on disk.

use std::sync::Arc;

use fall_guard_lab::dataset::{Dataset, DatasetError, Split};
use fall_guard_lab::sampler::{labels_at, EpisodeSpan, SamplerConfig, WindowSampler};
use fall_guard_runtime::clock::TickGrid;
use fall_guard_runtime::frame::Frame;
use fall_guard_runtime::streams::sample::Plan;
use fall_guard_runtime::window::{EpisodeTicks, Streams, TickInput, WindowSpec};
use fall_guard_testkit::recordings::{joint_names, learnable_episode, write_dataset};
use proptest::prelude::*;

/// An in-memory episode of `len` ticks (all streams present from `present_from`).
fn episode(len: usize, present_from: usize, onset: Option<i64>) -> EpisodeTicks {
    let grid = TickGrid::new(30.0).unwrap();
    let plan = Arc::new(Plan {
        stamp_ns: 0,
        times_ns: vec![0],
        positions_rad: vec![0.0; 2],
        n_joints: 2,
    });
    let frame = Arc::new(Frame::solid(2, 2, [1, 2, 3]));
    let ticks = (0..len)
        .map(|k| {
            let has = k >= present_from;
            TickInput {
                tick: k as i64,
                stamp_ns: grid.stamp_ns(k as i64),
                joints_rad: has.then(|| vec![k as f32; 2]),
                frame: has.then(|| frame.clone().into()),
                plan: has.then(|| plan.clone()),
                age_ns: Default::default(),
                joint_stamps_ns: None,
            }
        })
        .collect();
    EpisodeTicks {
        path: "mem".into(),
        grid,
        ticks,
        fall_onset_tick: onset,
    }
}

fn spec(n: usize, h_max: usize) -> WindowSpec {
    WindowSpec {
        n_ticks: n,
        max_horizon_ticks: h_max,
        rate_hz: 30.0,
        joint_names: joint_names(2),
        frame_size: 2,
    }
}

fn arb_episodes() -> impl Strategy<Value = Vec<(usize, usize, Option<usize>)>> {
    prop::collection::vec(
        (20usize..200, 0usize..10, prop::option::of(0usize..200)),
        1..30,
    )
}

proptest! {
    /// No window ever holds a fallen tick; labels are "fallen at end + h";
    /// every pick is a full window; one pick per usable episode.
    #[test]
    fn sampler_never_shows_a_fallen_tick(eps in arb_episodes(), seed in 0u64..1000) {
        let n = 8;
        let horizons = vec![3, 6, 9, 12];
        let episodes: Vec<EpisodeTicks> = eps.iter().map(|&(len, from, onset)| episode(len, from, onset.map(|o| o as i64))).collect();
        let cfg = SamplerConfig::new(n, horizons.clone());
        let usable = episodes.iter().filter(|e| EpisodeSpan::of(e, &cfg).is_some()).count();
        let sampler = WindowSampler::new(&episodes, cfg, seed);
        if usable == 0 {
            prop_assert!(sampler.is_err());
            return Ok(());
        }
        let mut sampler = sampler.unwrap();
        let sp = spec(n, 12);
        for _epoch in 0..3 {
            let picks = sampler.epoch();
            prop_assert_eq!(picks.len(), usable);
            let mut seen = std::collections::BTreeSet::new();
            for p in &picks {
                prop_assert!(seen.insert(p.episode));
                let e = &episodes[p.episode];
                let w = e.window_ending_at(p.end_tick, &sp, Streams::ALL);
                prop_assert!(w.is_ok(), "{:?}", w.err());
                for t in p.end_tick - n as i64 + 1..=p.end_tick {
                    prop_assert!(!e.is_fallen(t), "fallen tick {} in window ending {}", t, p.end_tick);
                }
                for (k, &h) in horizons.iter().enumerate() {
                    prop_assert_eq!(p.labels[k], e.is_fallen(p.end_tick + h as i64));
                }
                if e.fall_onset_tick.is_none() {
                    prop_assert!(p.end_tick + 12 <= e.last_tick().unwrap());
                }
            }
        }
    }
}

#[test]
fn labels_are_sticky_per_horizon() {
    assert_eq!(
        labels_at(Some(100), 90, &[5, 10, 15]),
        vec![false, true, true]
    );
    assert_eq!(labels_at(Some(100), 99, &[1]), vec![true]);
    assert_eq!(labels_at(None, 90, &[5, 10, 15]), vec![false; 3]);
}

#[test]
fn classes_balance_at_the_middle_horizon_and_runs_repeat() {
    // three quarters of the episodes fall: balance is reachable exactly, and
    // falling episodes must give negatives as well as positives
    let episodes: Vec<EpisodeTicks> = (0..200)
        .map(|i| episode(150, 0, (i % 4 != 0).then_some(100 + (i % 40) as i64)))
        .collect();
    let cfg = SamplerConfig::new(10, vec![15, 30, 45, 60]);
    assert_eq!(cfg.balance_horizon_index, 1);
    let mut a = WindowSampler::new(&episodes, cfg.clone(), 42).unwrap();
    let mut b = WindowSampler::new(&episodes, cfg.clone(), 42).unwrap();
    let mut c = WindowSampler::new(&episodes, cfg, 43).unwrap();
    for _ in 0..3 {
        let pa = a.epoch();
        assert_eq!(pa, b.epoch());
        assert_ne!(pa, c.epoch());
        let positives = pa.iter().filter(|p| p.labels[1]).count();
        assert!(
            (positives as i64 - 100).abs() <= 1,
            "{positives} positives of 200"
        );
        // windows of falling episodes are both positive and negative
        let fall_negatives = pa
            .iter()
            .filter(|p| p.episode % 2 == 0 && !p.labels[1])
            .count();
        assert!(fall_negatives > 0);
    }
}

#[test]
fn episodes_that_fall_too_early_are_skipped() {
    let episodes = vec![episode(100, 0, Some(5)), episode(100, 0, None)];
    let cfg = SamplerConfig::new(10, vec![5, 10]);
    assert_eq!(EpisodeSpan::of(&episodes[0], &cfg), None);
    let mut s = WindowSampler::new(&episodes, cfg.clone(), 1).unwrap();
    let picks = s.epoch();
    assert_eq!(picks.len(), 1);
    assert_eq!(picks[0].episode, 1);
    assert!(WindowSampler::new(&episodes[..1], cfg.clone(), 1).is_err());
    let mut bad = cfg;
    bad.horizons_ticks = vec![10, 5];
    assert!(WindowSampler::new(&episodes, bad, 1).is_err());
}

#[test]
fn dataset_on_disk_loads_and_checks_its_manifest() {
    let dir = tempfile::tempdir().unwrap();
    let names = joint_names(4);
    let make = |seed: u64| learnable_episode(seed, seed.is_multiple_of(2), 100, &names, 30.0, 16);
    let train: Vec<_> = (0..4).map(make).collect();
    write_dataset(dir.path(), &train, &[make(10)], &[make(11)]).unwrap();
    let ds = Dataset::open(dir.path()).unwrap();
    assert_eq!(ds.manifest.train.len(), 4);
    assert_eq!(
        ds.paths(Split::Test),
        vec![dir.path().join("episode_0005.mcap")]
    );
    let sp = WindowSpec {
        n_ticks: 20,
        max_horizon_ticks: 10,
        rate_hz: 30.0,
        joint_names: names.clone(),
        frame_size: 8,
    };
    let eps = ds.load_split(Split::Train, &sp, Streams::ALL).unwrap();
    assert_eq!(eps.len(), 4);
    assert_eq!(
        eps[0].fall_onset_tick,
        train[0].fall_onset_tick.map(|o| o as i64)
    );
    let mut sampler = WindowSampler::new(&eps, SamplerConfig::new(20, vec![5, 10]), 0).unwrap();
    for p in sampler.epoch() {
        eps[p.episode]
            .window_ending_at(p.end_tick, &sp, Streams::ALL)
            .unwrap();
    }

    // a model needing a joint the recordings lack: the error names the joint and file
    let mut other = sp.clone();
    other.joint_names[2] = "r_knee_y".into();
    let err = ds
        .load_split(Split::Train, &other, Streams::ALL)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("r_knee_y") && err.contains("episode_0000.mcap"),
        "{err}"
    );

    // no manifest
    let empty = tempfile::tempdir().unwrap();
    let err = Dataset::open(empty.path()).unwrap_err();
    assert!(matches!(err, DatasetError::NoManifest { .. }));
    assert!(err
        .to_string()
        .contains(&empty.path().display().to_string()));

    // a listed file that is missing
    std::fs::remove_file(dir.path().join("episode_0004.mcap")).unwrap();
    let err = Dataset::open(dir.path()).unwrap_err();
    assert!(
        err.to_string().contains("episode_0004.mcap") && err.to_string().contains("validation"),
        "{err}"
    );

    // an episode in two splits
    std::fs::write(
        dir.path().join("manifest.json"),
        r#"{"train": ["episode_0000.mcap"], "validation": [], "test": ["episode_0000.mcap"]}"#,
    )
    .unwrap();
    let err = Dataset::open(dir.path()).unwrap_err();
    assert!(matches!(err, DatasetError::SharedEpisode { .. }), "{err}");
}

/// Many episodes of varied length and onset: 60% fall, at a tick uniform
/// over most of the episode (some too early for the longest spans).
fn many_episodes(count: usize) -> Vec<EpisodeTicks> {
    let mut s = 0x2545_F491_4F6C_DD1Du64;
    let mut next = move |m: u64| {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s % m
    };
    (0..count)
        .map(|_| {
            let len = 120 + next(120) as usize;
            let onset = (next(10) < 6).then(|| 15 + next(len as u64 - 15) as i64);
            episode(len, next(4) as usize, onset)
        })
        .collect()
}

#[test]
fn paper_protocol_stop_lines_balance_and_one_window_per_episode() {
    use fall_guard_lab::sampler::Protocol;
    let episodes = many_episodes(1200);
    let n = 10;
    for h in [15usize, 30, 45, 60] {
        let cfg = SamplerConfig::paper(n, h);
        assert_eq!(cfg.protocol, Protocol::Paper);
        let mut sampler = WindowSampler::new(&episodes, cfg, 7).unwrap();
        let sp = spec(n, h);
        for _draw in 0..3 {
            let picks = sampler.epoch();
            assert!(picks.len() > 600, "span {h}: only {} windows", picks.len());
            let mut seen = std::collections::BTreeSet::new();
            let mut positives = 0usize;
            for p in &picks {
                assert!(seen.insert(p.episode), "episode {} twice", p.episode);
                let e = &episodes[p.episode];
                e.window_ending_at(p.end_tick, &sp, Streams::ALL).unwrap();
                match e.fall_onset_tick {
                    // the stop line of span h
                    Some(onset) => assert!(
                        p.end_tick <= onset - h as i64,
                        "span {h}: window ends at {}, onset {onset}",
                        p.end_tick
                    ),
                    None => assert!(p.end_tick + h as i64 <= e.last_tick().unwrap()),
                }
                assert_eq!(p.labels, vec![e.is_fallen(p.end_tick + h as i64)]);
                positives += usize::from(p.labels[0]);
            }
            let share = positives as f64 / picks.len() as f64;
            assert!(
                (share - 0.5).abs() <= 0.02,
                "span {h}: positive share {share}"
            );
        }
    }
}

#[test]
fn paper_protocol_window_sets_do_not_depend_on_the_other_horizons() {
    use fall_guard_lab::commands::SplitWindows;
    use fall_guard_lab::sampler::Protocol;
    let episodes = std::sync::Arc::new(many_episodes(300));
    let needs = Streams::ALL;
    let mut all = SplitWindows::new(
        episodes.clone(),
        &spec(10, 60),
        needs,
        &[15, 30, 45, 60],
        5,
        Protocol::Paper,
    )
    .unwrap();
    let mut one =
        SplitWindows::new(episodes, &spec(10, 30), needs, &[30], 5, Protocol::Paper).unwrap();
    let key =
        |w: &fall_guard_lab::LabeledWindow, k: usize| (w.episode, w.joints.clone(), w.labels[k]);
    let build = |set: fall_guard_lab::commands::SplitEpoch| {
        use fall_guard_lab::WindowSet;
        set.build(0..set.len(), true).unwrap()
    };
    let (a, b) = (build(all.epoch()), build(one.epoch()));
    let mut from_all: Vec<_> = a
        .iter()
        .filter(|w| w.scored_horizon == Some(1))
        .map(|w| key(w, 1))
        .collect();
    let mut from_one: Vec<_> = b.iter().map(|w| key(w, 0)).collect();
    assert!(b.iter().all(|w| w.scored_horizon == Some(0)));
    from_all.sort_by(|x, y| x.partial_cmp(y).unwrap());
    from_one.sort_by(|x, y| x.partial_cmp(y).unwrap());
    assert!(!from_one.is_empty());
    assert_eq!(from_all, from_one);
    // every horizon has its own set, and the deployment protocol one set
    for k in 0..4 {
        assert!(a.iter().any(|w| w.scored_horizon == Some(k)));
    }
}

#[test]
fn paper_protocol_rejects_the_surplus_when_few_episodes_fall() {
    // One episode in five falls: one window per episode cannot balance, so
    // the surplus negatives are rejected (the deployment protocol keeps them).
    let episodes: Vec<EpisodeTicks> = (0..500)
        .map(|i| episode(200, 0, (i % 5 == 0).then_some(150)))
        .collect();
    let mut paper = WindowSampler::new(&episodes, SamplerConfig::paper(10, 30), 3).unwrap();
    for _ in 0..3 {
        let picks = paper.epoch();
        let positives = picks.iter().filter(|p| p.labels[0]).count();
        assert_eq!(picks.len(), 200, "100 falling episodes, 100 positives kept");
        assert_eq!(positives, 100);
    }
    let mut deployment =
        WindowSampler::new(&episodes, SamplerConfig::new(10, vec![30]), 3).unwrap();
    assert_eq!(deployment.epoch().len(), 500);
}
