//! The tick grid, the resampler, the ring and the windows: properties, and
//! the promise that a window built offline from a recording (training)
//! equals the one a replaying daemon builds at the same tick, bit for bit.

use std::sync::Arc;

use fall_guard_runtime::clock::TickGrid;
use fall_guard_runtime::frame::Frame;
use fall_guard_runtime::msgs::{Duration, Header, JointTrajectory, JointTrajectoryPoint, Time};
use fall_guard_runtime::recording::Recording;
use fall_guard_runtime::streams::sample::{Plan, Sample};
use fall_guard_runtime::window::{
    samples_from_recording, EpisodeTicks, Resampler, Ring, Streams, TickInput, Window, WindowError,
    WindowSpec,
};
use fall_guard_testkit::recordings::{joint_names, learnable_episode};
use proptest::prelude::*;

fn spec(n_ticks: usize, c: usize) -> WindowSpec {
    WindowSpec {
        n_ticks,
        max_horizon_ticks: 6,
        rate_hz: 30.0,
        joint_names: joint_names(c),
        frame_size: 4,
    }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn grid_at_30_hz() {
    let g = TickGrid::new(30.0).unwrap();
    assert_eq!(g.stamp_ns(0), 0);
    assert_eq!(g.stamp_ns(1), 33_333_334);
    assert_eq!(g.stamp_ns(2), 66_666_667);
    assert_eq!(g.stamp_ns(3), 100_000_000);
    assert_eq!(g.stamp_ns(-1), -33_333_333);
    assert_eq!(g.first_tick_at_or_after(33_333_333), 1);
    assert_eq!(g.first_tick_at_or_after(33_333_335), 2);
    assert_eq!(g.last_tick_at_or_before(33_333_333), 0);
    assert!(TickGrid::new(0.0).is_err());
    assert!(TickGrid::new(f64::NAN).is_err());
    assert!(TickGrid::new(30.0001).is_err());
}

proptest! {
    #[test]
    fn grid_tick_lookup_is_exact(t in -4_000_000_000_000i64..4_000_000_000_000_000_000i64, mhz in 1_000i64..1_000_000) {
        let g = TickGrid::new(mhz as f64 / 1000.0).unwrap();
        let k = g.first_tick_at_or_after(t);
        prop_assert!(g.stamp_ns(k) >= t);
        prop_assert!(g.stamp_ns(k - 1) < t);
        let j = g.last_tick_at_or_before(t);
        prop_assert!(g.stamp_ns(j) <= t && g.stamp_ns(j + 1) > t);
    }
}

/// Random time-ordered samples over a few streams.
fn arb_samples() -> impl Strategy<Value = Vec<(i64, u8, f32)>> {
    prop::collection::vec((0i64..400_000_000, 0u8..3, -1.0f32..1.0), 1..60).prop_map(|mut v| {
        v.sort_by_key(|x| x.0);
        v
    })
}

fn to_sample(c: usize, (stamp_ns, stream, value): (i64, u8, f32)) -> Sample {
    match stream {
        0 => Sample::Joints {
            stamp_ns,
            positions_rad: vec![value; c],
            read_ns: None,
        },
        1 => Sample::Frame {
            stamp_ns,
            frame: Arc::new(Frame::solid(4, 4, [(value.abs() * 255.0) as u8, 0, 0])),
        },
        _ => Sample::Plan {
            stamp_ns,
            plan: Arc::new(Plan {
                stamp_ns,
                times_ns: vec![stamp_ns, stamp_ns + 100_000_000],
                positions_rad: [vec![f64::from(value); c], vec![f64::from(-value); c]].concat(),
                n_joints: c,
            }),
        },
    }
}

proptest! {
    /// Each tick holds the last sample of each stream stamped at or before it.
    #[test]
    fn resampler_is_zero_order_hold(samples in arb_samples()) {
        let c = 2;
        let sp = spec(5, c);
        let mut r = Resampler::new(&sp).unwrap();
        let mut ticks = Vec::new();
        for s in &samples {
            r.push(to_sample(c, *s), &mut ticks);
        }
        let end = samples.last().unwrap().0 + 50_000_000;
        r.advance_to(end, &mut ticks);
        let g = TickGrid::new(30.0).unwrap();
        prop_assert_eq!(ticks[0].tick, g.first_tick_at_or_after(samples[0].0));
        prop_assert_eq!(ticks.last().unwrap().tick, g.last_tick_at_or_before(end));
        for (i, t) in ticks.iter().enumerate() {
            prop_assert_eq!(t.tick, ticks[0].tick + i as i64);
            prop_assert_eq!(t.stamp_ns, g.stamp_ns(t.tick));
            let last_joint = samples.iter().rfind(|s| s.1 == 0 && s.0 <= t.stamp_ns);
            prop_assert_eq!(t.joints_rad.clone(), last_joint.map(|s| vec![s.2; c]));
            prop_assert_eq!(t.age_ns.joints, last_joint.map(|s| t.stamp_ns - s.0));
            let last_plan = samples.iter().rfind(|s| s.1 == 2 && s.0 <= t.stamp_ns);
            prop_assert_eq!(t.plan.as_ref().map(|p| p.stamp_ns), last_plan.map(|s| s.0));
            prop_assert_eq!(t.age_ns.camera.is_some(), samples.iter().any(|s| s.1 == 1 && s.0 <= t.stamp_ns));
        }
    }

    /// How pushes and advances interleave does not change the ticks.
    #[test]
    fn resampler_ignores_call_interleaving(samples in arb_samples(), advances in prop::collection::vec(0i64..400_000_000, 0..20)) {
        let c = 2;
        let sp = spec(5, c);
        let end = samples.last().unwrap().0 + 10_000_000;
        let mut batch = Resampler::new(&sp).unwrap();
        let mut a = Vec::new();
        for s in &samples {
            batch.push(to_sample(c, *s), &mut a);
        }
        batch.advance_to(end, &mut a);

        // the same samples, with advance_to calls wherever they are allowed
        // (strictly before the next sample's stamp, as a tick timer would)
        let mut live = Resampler::new(&sp).unwrap();
        let mut b = Vec::new();
        let mut adv = advances.clone();
        adv.sort();
        let mut ai = 0;
        for s in &samples {
            while ai < adv.len() && adv[ai] < s.0 {
                if live.next_tick().is_some() {
                    live.advance_to(adv[ai], &mut b);
                }
                ai += 1;
            }
            live.push(to_sample(c, *s), &mut b);
        }
        live.advance_to(end, &mut b);
        prop_assert_eq!(a, b);
    }

    /// The ring holds the last N consecutive ticks, and its window is
    /// `Window::from_ticks` of them.
    #[test]
    fn ring_keeps_last_n_consecutive(n in 1usize..8, steps in prop::collection::vec(1i64..3, 1..40)) {
        let c = 3;
        let sp = spec(n, c);
        let mut ring = Ring::new(n);
        let mut all: Vec<TickInput> = Vec::new();
        let mut tick = 0i64;
        for step in steps {
            tick += step; // step 2 = a gap
            let t = TickInput {
                tick,
                stamp_ns: TickGrid::new(30.0).unwrap().stamp_ns(tick),
                joints_rad: Some(vec![tick as f32; c]),
                frame: Some(Frame::solid(4, 4, [tick as u8, 1, 2]).into()),
                plan: Some(Arc::new(Plan { stamp_ns: 0, times_ns: vec![0], positions_rad: vec![0.5; c], n_joints: c })),
                age_ns: Default::default(),
                joint_stamps_ns: None,
            };
            ring.push(t.clone());
            all.push(t);
            // expected: the longest run of consecutive ticks at the end, at most n
            let mut run = 1;
            while run < all.len() && run < n && all[all.len() - run].tick == all[all.len() - run - 1].tick + 1 {
                run += 1;
            }
            prop_assert_eq!(ring.len(), run);
            prop_assert_eq!(ring.is_full(), run == n);
            prop_assert_eq!(ring.latest().map(|t| t.tick), Some(tick));
            let expected: Vec<&TickInput> = all[all.len() - run..].iter().collect();
            prop_assert_eq!(ring.iter().collect::<Vec<_>>(), expected.clone());
            match ring.window(&sp) {
                Some(w) => {
                    prop_assert!(run == n);
                    let direct = Window::from_ticks(expected, &sp, Streams::ALL).unwrap();
                    prop_assert_eq!(&w, &direct);
                    prop_assert_eq!(w.joints.len(), n * c);
                    prop_assert_eq!(w.plan.len(), (n + 6) * c);
                    prop_assert_eq!(w.frames.len(), 3 * n * 16);
                    prop_assert_eq!(w.end_tick, tick);
                }
                None => prop_assert!(run < n),
            }
        }
    }
}

#[test]
fn window_layout_is_time_major_and_channel_planes() {
    let c = 2;
    let n = 3;
    let sp = spec(n, c);
    let ticks: Vec<TickInput> = (10..13)
        .map(|k| TickInput {
            tick: k,
            stamp_ns: TickGrid::new(30.0).unwrap().stamp_ns(k),
            joints_rad: Some(vec![k as f32, -(k as f32)]),
            frame: Some(Frame::solid(4, 4, [k as u8, 100, 255]).into()),
            plan: Some(Arc::new(Plan {
                stamp_ns: 0,
                times_ns: vec![0],
                positions_rad: vec![0.25, 0.5],
                n_joints: c,
            })),
            age_ns: Default::default(),
            joint_stamps_ns: None,
        })
        .collect();
    let w = Window::from_ticks(&ticks, &sp, Streams::ALL).unwrap();
    assert_eq!(w.joints, vec![10.0, -10.0, 11.0, -11.0, 12.0, -12.0]);
    assert_eq!(w.plan.len(), (3 + 6) * 2);
    assert!(w.plan.chunks(2).all(|r| r == [0.25, 0.5]));
    // frames [3, N, S, S]: channel 0 of tick 1 (k = 11) is 11/255
    assert_eq!(w.frames[16], 11.0 / 255.0);
    assert_eq!(w.frames[(n + 2) * 16 + 5], 100.0 / 255.0);
    assert_eq!(w.frames[(2 * n) * 16], 1.0);
    // a missing stream is named, an unneeded one is empty
    let mut no_frame = ticks.clone();
    no_frame[1].frame = None;
    let err = Window::from_ticks(&no_frame, &sp, Streams::ALL).unwrap_err();
    assert!(
        matches!(
            err,
            WindowError::MissingStream {
                stream: "frames",
                tick: 11,
                ..
            }
        ),
        "{err}"
    );
    let w = Window::from_ticks(
        &no_frame,
        &sp,
        Streams {
            camera: false,
            ..Streams::ALL
        },
    )
    .unwrap();
    assert!(w.frames.is_empty());
}

#[test]
fn plan_interpolates_linearly_and_holds_ends() {
    let names = joint_names(2);
    let msg = JointTrajectory {
        header: Header {
            stamp: Time::from_ns(1_000),
            frame_id: String::new(),
        },
        // the message lists joints in another order than the model
        joint_names: vec![names[1].clone(), names[0].clone(), "extra".into()],
        points: vec![
            JointTrajectoryPoint {
                positions: vec![10.0, 0.0, 9.0],
                time_from_start: Duration::from_ns(0),
                ..Default::default()
            },
            JointTrajectoryPoint {
                positions: vec![20.0, 1.0, 9.0],
                time_from_start: Duration::from_ns(100),
                ..Default::default()
            },
        ],
    };
    let plan = Plan::from_msg(&msg, &names).unwrap();
    let mut out = [0f32; 2];
    plan.sample_into(500, &mut out);
    assert_eq!(out, [0.0, 10.0]);
    plan.sample_into(1_025, &mut out);
    assert_eq!(out, [0.25, 12.5]);
    plan.sample_into(5_000, &mut out);
    assert_eq!(out, [1.0, 20.0]);
    let mut missing = msg.clone();
    missing.joint_names[0] = "other".into();
    let err = Plan::from_msg(&missing, &names).unwrap_err();
    assert!(err.to_string().contains("j01"), "{err}");
}

/// The promise of the architecture: replaying a recording the way the daemon
/// does (a tick timer on recorded time, samples handed over as their time
/// comes, a ring) gives, at every tick, the window training cuts from the
/// same recording, bit for bit.
#[test]
fn replay_windows_equal_training_windows_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ep.mcap");
    let names = joint_names(5);
    let ep = learnable_episode(7, true, 150, &names, 30.0, 16);
    ep.write(&path).unwrap();
    let sp = WindowSpec {
        n_ticks: 20,
        max_horizon_ticks: 15,
        rate_hz: 30.0,
        joint_names: names,
        frame_size: 8,
    };

    // training
    let rec = Recording::open(&path).unwrap();
    let episode = EpisodeTicks::from_recording(&rec, &sp).unwrap();
    let first_end = episode
        .first_complete_end_tick(sp.n_ticks, Streams::ALL)
        .unwrap();

    // daemon-style replay: the tick timer fires at each grid stamp; samples
    // whose recorded time has come are pushed first
    let samples = samples_from_recording(&Recording::open(&path).unwrap(), &sp).unwrap();
    let grid = TickGrid::new(sp.rate_hz).unwrap();
    let mut resampler = Resampler::new(&sp).unwrap();
    let mut ring = Ring::new(sp.n_ticks);
    let mut next = samples.into_iter().peekable();
    let mut tick = grid.first_tick_at_or_after(rec.start_ns().unwrap());
    let mut compared = 0;
    while tick <= episode.last_tick().unwrap() {
        let now = grid.stamp_ns(tick);
        let mut out = Vec::new();
        while next.peek().is_some_and(|s| s.stamp_ns() <= now) {
            resampler.push(next.next().unwrap(), &mut out);
        }
        resampler.advance_to(now, &mut out);
        for t in out {
            ring.push(t);
        }
        if let Some(live) = ring.window(&sp) {
            let offline = episode.window_ending_at(tick, &sp, Streams::ALL).unwrap();
            assert_eq!(live.end_tick, offline.end_tick);
            assert_eq!(
                bits(&live.joints),
                bits(&offline.joints),
                "joints at tick {tick}"
            );
            assert_eq!(bits(&live.plan), bits(&offline.plan), "plan at tick {tick}");
            assert_eq!(
                bits(&live.frames),
                bits(&offline.frames),
                "frames at tick {tick}"
            );
            compared += 1;
        } else {
            assert!(tick < first_end);
        }
        tick += 1;
    }
    assert_eq!(
        compared as i64,
        episode.last_tick().unwrap() - first_end + 1
    );
    assert!(compared > 100);
}

#[test]
fn episode_ticks_from_synthetic_recording() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ep.mcap");
    let names = joint_names(3);
    let ep = learnable_episode(3, true, 120, &names, 30.0, 8);
    let onset = ep.fall_onset_tick.unwrap() as i64;
    ep.write(&path).unwrap();
    let sp = WindowSpec {
        n_ticks: 10,
        max_horizon_ticks: 5,
        rate_hz: 30.0,
        joint_names: names,
        frame_size: 8,
    };
    let ticks = EpisodeTicks::from_recording(&Recording::open(&path).unwrap(), &sp).unwrap();
    assert_eq!(ticks.first_tick(), Some(0));
    assert_eq!(ticks.last_tick(), Some(119));
    assert_eq!(ticks.fall_onset_tick, Some(onset));
    assert!(ticks.is_fallen(onset) && !ticks.is_fallen(onset - 1));
    // every tick has exactly the sample written for it
    for (k, t) in ticks.ticks.iter().enumerate() {
        assert_eq!(t.age_ns.joints, Some(0));
        assert_eq!(t.age_ns.camera, Some(0));
        let expected: Vec<f32> = ep.joints_rad[k]
            .iter()
            .map(|&v| f64::from(v) as f32)
            .collect();
        assert_eq!(t.joints_rad.as_ref().unwrap(), &expected);
    }
    let w = ticks.window_ending_at(50, &sp, Streams::ALL).unwrap();
    // the plan at the window's ticks equals the per-tick planned pose
    for (i, row) in w.plan.chunks(3).enumerate() {
        let k = (41 + i).min(119);
        assert_eq!(row, &ep.plan_rad[k][..], "plan row {i}");
    }
    assert!(matches!(
        ticks.window_ending_at(5, &sp, Streams::ALL),
        Err(WindowError::TickOutOfRange { .. })
    ));
}

/// An episode read with its frames kept compressed (how a data set's splits
/// are held) has the ticks of the decoded one, and every window built from
/// it is the same bytes, at the recorded size and resized.
#[test]
fn compressed_frames_give_the_windows_of_decoded_ones() {
    use fall_guard_runtime::window::{FrameStorage, TickFrame};
    let path = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
        .join("tests/fixtures/episode_00005.mcap");
    let rec = Recording::open(&path).unwrap();
    for size in [64u32, 40] {
        let sp = WindowSpec {
            n_ticks: 60,
            max_horizon_ticks: 60,
            rate_hz: 30.0,
            joint_names: fall_guard_runtime::robot::JointTable::poppy_humanoid().names(),
            frame_size: size,
        };
        let decoded = EpisodeTicks::from_recording_as(&rec, &sp, FrameStorage::Decoded).unwrap();
        let compressed =
            EpisodeTicks::from_recording_as(&rec, &sp, FrameStorage::Compressed).unwrap();
        assert_eq!(decoded.ticks.len(), compressed.ticks.len());
        assert_eq!(decoded.fall_onset_tick, compressed.fall_onset_tick);
        let (mut held, mut frames) = (0usize, 0usize);
        for (d, c) in decoded.ticks.iter().zip(&compressed.ticks) {
            assert_eq!(
                (d.tick, d.stamp_ns, &d.joints_rad, &d.plan, d.age_ns),
                (c.tick, c.stamp_ns, &c.joints_rad, &c.plan, c.age_ns)
            );
            match (&d.frame, &c.frame) {
                (Some(TickFrame::Decoded(f)), Some(TickFrame::Compressed(z))) => {
                    assert_eq!(**f, z.decode().unwrap(), "tick {}", d.tick);
                    held += z.compressed_len();
                    frames += f.rgb.len();
                }
                (None, None) => {}
                other => panic!("tick {}: {other:?}", d.tick),
            }
        }
        // At the recorded 64 x 64 this episode's JPEGs are ~2 KB, the
        // decoded frame 12 KB: compressed storage holds under a quarter.
        assert!(
            size != 64 || held * 4 < frames,
            "{held} bytes compressed, {frames} decoded"
        );
        let first = decoded.first_complete_end_tick(60, Streams::ALL).unwrap();
        let last = decoded.last_tick().unwrap();
        for end in (first..=last).step_by(7).chain([last]) {
            assert_eq!(
                decoded.window_ending_at(end, &sp, Streams::ALL).unwrap(),
                compressed.window_ending_at(end, &sp, Streams::ALL).unwrap(),
                "window ending at {end}, frames {size} px"
            );
        }
    }
}

#[test]
fn a_joint_not_read_in_a_sample_keeps_its_value_and_its_age() {
    let mut r = Resampler::new(&spec(4, 3)).unwrap();
    let mut out = Vec::new();
    let joints = |stamp_ns: i64, v: [f32; 3]| Sample::Joints {
        stamp_ns,
        positions_rad: v.to_vec(),
        read_ns: None,
    };
    let nan = f32::NAN;
    // Tick k at k/30 s; a servo reading every 20 ms, joint 1 missed twice,
    // joint 2 never read until the third reading.
    r.push(joints(0, [0.1, 0.2, nan]), &mut out);
    r.push(joints(20_000_000, [0.11, nan, nan]), &mut out);
    r.push(joints(40_000_000, [0.12, nan, 0.32]), &mut out);
    r.advance_to(66_666_667, &mut out);
    let ticks: Vec<&TickInput> = out.iter().collect();
    assert_eq!(ticks.iter().map(|t| t.tick).collect::<Vec<_>>(), [0, 1, 2]);
    // Tick 0: only the first reading; joint 2 not read yet.
    let t0 = ticks[0];
    assert_eq!(t0.joints_rad.as_ref().unwrap()[..2], [0.1, 0.2]);
    assert!(t0.joints_rad.as_ref().unwrap()[2].is_nan());
    assert_eq!((t0.joint_age_ns(0), t0.joint_age_ns(2)), (Some(0), None));
    assert_eq!(t0.age_ns.joints, Some(0));
    // Tick 1 (33.3 ms): joint 1 held from the first reading.
    let t1 = ticks[1];
    assert_eq!(t1.joints_rad.as_ref().unwrap()[..2], [0.11, 0.2]);
    assert_eq!(t1.joint_age_ns(0), Some(33_333_334 - 20_000_000));
    assert_eq!(t1.joint_age_ns(1), Some(33_333_334));
    // The tick's joints age is its oldest joint's.
    assert_eq!(t1.age_ns.joints, Some(33_333_334));
    // Tick 2 (66.7 ms): every joint has a value, joint 1 the oldest.
    let t2 = ticks[2];
    assert_eq!(t2.joints_rad.as_ref().unwrap(), &vec![0.12, 0.2, 0.32]);
    assert_eq!(t2.joint_age_ns(1), Some(66_666_667));
    assert_eq!(t2.joint_age_ns(2), Some(66_666_667 - 40_000_000));
    assert_eq!(t2.age_ns.joints, Some(66_666_667));
    // A complete reading: every value from it, no per-joint stamps kept.
    out.clear();
    r.push(joints(80_000_000, [0.13, 0.23, 0.33]), &mut out);
    r.advance_to(100_000_000, &mut out);
    let t3 = out.last().unwrap();
    assert_eq!(t3.tick, 3);
    assert!(t3.joint_stamps_ns.is_none());
    assert_eq!(t3.age_ns.joints, Some(20_000_000));
    assert_eq!(t3.joint_age_ns(1), Some(20_000_000));
    assert_eq!(t3.joints_rad.as_ref().unwrap(), &vec![0.13, 0.23, 0.33]);
}

#[test]
fn each_joint_takes_its_own_read_stamp_when_the_sample_has_them() {
    let mut r = Resampler::new(&spec(4, 3)).unwrap();
    let mut out = Vec::new();
    let joints = |stamp_ns: i64, v: [f32; 3], read_ns: [i64; 3]| Sample::Joints {
        stamp_ns,
        positions_rad: v.to_vec(),
        read_ns: Some(read_ns.to_vec()),
    };
    let nan = f32::NAN;
    // Two buses read one after the other: joints 0 and 1 at 0 ms, joint 2
    // at 12 ms; the sample is stamped with its newest read.
    r.push(
        joints(12_000_000, [0.1, 0.2, 0.3], [0, 0, 12_000_000]),
        &mut out,
    );
    // The next cycle: joint 1 got by a retry at 30 ms, joint 2 not read.
    r.push(
        joints(
            30_000_000,
            [0.11, 0.21, nan],
            [23_000_000, 30_000_000, 30_000_000],
        ),
        &mut out,
    );
    r.advance_to(33_333_334, &mut out);
    let t1 = out.iter().find(|t| t.tick == 1).unwrap();
    assert_eq!(t1.joints_rad.as_ref().unwrap(), &vec![0.11, 0.21, 0.3]);
    assert_eq!(t1.joint_age_ns(0), Some(33_333_334 - 23_000_000));
    assert_eq!(t1.joint_age_ns(1), Some(33_333_334 - 30_000_000));
    assert_eq!(t1.joint_age_ns(2), Some(33_333_334 - 12_000_000));
    assert_eq!(t1.age_ns.joints, Some(33_333_334 - 12_000_000));
    // A sample takes effect at its stamp (12 ms): the first tick is tick 1.
    assert_eq!(out[0].tick, 1);
    // A position read before the one held is not taken: the joint keeps
    // its newer value and stamp.
    r.push(
        joints(
            40_000_000,
            [0.12, 0.19, 0.31],
            [40_000_000, 25_000_000, 40_000_000],
        ),
        &mut out,
    );
    r.advance_to(66_666_667, &mut out);
    let t2 = out.iter().find(|t| t.tick == 2).unwrap();
    assert_eq!(t2.joints_rad.as_ref().unwrap(), &vec![0.12, 0.21, 0.31]);
    assert_eq!(t2.joint_age_ns(1), Some(66_666_667 - 30_000_000));
}
