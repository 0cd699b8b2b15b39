//! The servo reader against the 25 Poppy motors emulated on real
//! pseudo-terminals (one USB2AX per bus): positions in radians, then each
//! fault injected, counted and recovered from.

use std::time::{Duration, Instant};

use fall_guard_runtime::robot::{JointTable, ServoModel};
use fall_guard_runtime::sources::dynamixel::{
    DynamixelConfig, JointReading, ServoErrorKind, ServoReader, ServoStatsSnapshot,
};
use fall_guard_testkit::emulator::{Fault, PoppyBuses, ReplyNoise};
use tempfile::TempDir;

struct Rig {
    _dir: TempDir,
    table: JointTable,
    buses: PoppyBuses,
}

fn rig() -> Rig {
    let dir = tempfile::tempdir().expect("temp dir");
    let table = JointTable::poppy_humanoid();
    let buses = PoppyBuses::start(&table, dir.path()).expect("emulated buses");
    Rig {
        _dir: dir,
        table,
        buses,
    }
}

impl Rig {
    fn config(&self, sync_read: bool) -> DynamixelConfig {
        let mut config = self.buses.config();
        for bus in config.buses.values_mut() {
            bus.sync_read = sync_read;
            // Generous, so that a busy test machine stalling the emulator
            // thread does not read as a fault.
            bus.timeout_ms = 100;
            bus.reopen_backoff_ms = 10;
            bus.reopen_backoff_max_ms = 40;
        }
        config
    }

    fn reader(&self, sync_read: bool) -> ServoReader {
        ServoReader::new(&self.config(sync_read), &self.table).expect("valid config")
    }

    /// A distinct raw position for every motor, inside its joint limits.
    fn set_distinct_positions(&self) -> Vec<u16> {
        self.table
            .joints()
            .iter()
            .enumerate()
            .map(|(i, joint)| {
                let t = (i as f64 + 0.5) / 25.0;
                let angle_deg =
                    joint.lower_limit_deg + t * (joint.upper_limit_deg - joint.lower_limit_deg);
                let raw = joint.deg_to_raw(angle_deg);
                self.buses.set_raw_position(joint.id, raw).expect("motor");
                raw
            })
            .collect()
    }
}

fn assert_positions(table: &JointTable, reading: &JointReading, raws: &[u16]) {
    assert_eq!(reading.positions_rad.len(), 25);
    for ((joint, raw), got) in table.joints().iter().zip(raws).zip(&reading.positions_rad) {
        let got = got.unwrap_or_else(|| panic!("{} missing", joint.name));
        let want = joint.raw_to_rad(*raw) as f32;
        assert!((got - want).abs() < 1e-6, "{}: {got} != {want}", joint.name);
    }
}

/// Run cycles until `done` holds for the stats (or fail after 3 s).
fn cycle_until(
    reader: &mut ServoReader,
    what: &str,
    done: impl Fn(&JointReading, &ServoStatsSnapshot) -> bool,
) -> JointReading {
    let deadline = Instant::now() + Duration::from_secs(3);
    let mut stamp = 0;
    loop {
        stamp += 1;
        let reading = reader.read_cycle(stamp);
        let stats = reader.stats().snapshot();
        if done(&reading, &stats) {
            return reading;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: not reached; stats {stats:#?}"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn sync_read_gives_all_25_positions_in_radians() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    let mut reader = rig.reader(true);
    let reading = reader.read_cycle(42);
    assert_eq!(reading.stamp_ns, 42);
    assert!(reading.is_complete());
    assert_positions(&rig.table, &reading, &raws);

    // Hand-computed, both conventions: head_y (AX-12, indirect, offset 20)
    // at raw 400 is -(300*400/1023 - 150) - 20 = 12.6979 deg; r_knee_y
    // (MX-28, indirect) at raw 1024 is -(360*1024/4095 - 180) = 89.9780 deg;
    // l_hip_y (MX-64, direct, offset 2) at raw 1024 is -91.9780 deg.
    rig.buses.set_raw_position(37, 400).unwrap();
    rig.buses.set_raw_position(24, 1024).unwrap();
    rig.buses.set_raw_position(13, 1024).unwrap();
    let reading = reader.read_cycle(43);
    let at = |name: &str| reading.positions_rad[rig.table.index_of(name).unwrap()].unwrap();
    assert!((at("head_y") - 12.697_947_f32.to_radians()).abs() < 1e-6);
    assert!((at("r_knee_y") - 89.978_02_f32.to_radians()).abs() < 1e-6);
    assert!((at("l_hip_y") - (-91.978_02_f32).to_radians()).abs() < 1e-6);

    let stats = reader.stats().snapshot();
    assert_eq!(stats.complete_cycles, 2);
    assert!(stats
        .buses
        .iter()
        .all(|b| b.connected && b.sync_read_active && b.ok_cycles == 2));
    // One 0x84 per bus and cycle, no per-motor reads.
    for bus in [&rig.buses.lower, &rig.buses.upper] {
        assert_eq!(bus.requests().sync_reads, 2);
        assert_eq!(bus.requests().reads, 0);
    }
}

#[test]
fn per_motor_reads_give_the_same_positions() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    let mut reader = rig.reader(false);
    let reading = reader.read_cycle(1);
    assert_positions(&rig.table, &reading, &raws);
    assert_eq!(rig.buses.lower.requests().reads, 10);
    assert_eq!(rig.buses.upper.requests().reads, 15);
    assert_eq!(rig.buses.lower.requests().sync_reads, 0);
    assert!(reader
        .stats()
        .snapshot()
        .buses
        .iter()
        .all(|b| !b.sync_read_active));
}

#[test]
fn adapter_without_usb2ax_sync_read_falls_back_to_per_motor_reads() {
    let rig = rig();
    rig.buses.upper.set_sync_read_supported(false);
    let raws = rig.set_distinct_positions();
    let mut reader = rig.reader(true);
    let reading = cycle_until(&mut reader, "fallback", |r, _| r.is_complete());
    assert_positions(&rig.table, &reading, &raws);
    let stats = reader.stats().snapshot();
    let upper = &stats.buses[1];
    assert_eq!(upper.name, "upper");
    assert!(!upper.sync_read_active);
    assert_eq!(
        upper.timeouts, 3,
        "three silent sync reads before falling back"
    );
    assert!(stats.buses[0].sync_read_active);
    assert!(rig.buses.upper.requests().reads >= 15);
}

#[test]
fn a_missing_motor_reads_as_none_and_comes_back() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    for sync_read in [true, false] {
        let mut reader = rig.reader(sync_read);
        rig.buses.lower.set_present(23, false).unwrap();
        let reading = reader.read_cycle(1);
        let index = rig.table.index_of("r_hip_y").unwrap();
        assert_eq!(reading.positions_rad[index], None);
        assert_eq!(
            reading.positions_rad.iter().filter(|p| p.is_some()).count(),
            24
        );
        let stats = reader.stats().snapshot();
        assert_eq!(stats.buses[0].missing_ids, vec![23]);
        assert_eq!(stats.buses[0].missing_motor_reads, 1);
        assert_eq!(stats.complete_cycles, 0);
        rig.buses.lower.set_present(23, true).unwrap();
        let reading = reader.read_cycle(2);
        assert_positions(&rig.table, &reading, &raws);
        assert!(reader.stats().snapshot().buses[0].missing_ids.is_empty());
    }
}

#[test]
fn no_reply_is_counted_as_timeouts_and_recovers() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    for sync_read in [true, false] {
        let mut reader = rig.reader(sync_read);
        reader.read_cycle(0);
        rig.buses.lower.set_fault(Some(Fault::NoReply));
        let reading = reader.read_cycle(1);
        // The lower bus is silent; the upper one is read as usual.
        for (joint, position) in rig.table.joints().iter().zip(&reading.positions_rad) {
            assert_eq!(position.is_some(), joint.bus == "upper", "{}", joint.name);
        }
        let stats = reader.stats().snapshot();
        let expected = if sync_read { 1 } else { 10 };
        assert_eq!(stats.buses[0].timeouts, expected);
        assert!(
            stats.buses[0].sync_read_active == sync_read,
            "no fallback after a good sync read"
        );
        rig.buses.lower.set_fault(None);
        let reading = cycle_until(&mut reader, "recovery", |r, _| r.is_complete());
        assert_positions(&rig.table, &reading, &raws);
    }
}

#[test]
fn bad_checksums_are_counted_and_skipped() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    for sync_read in [true, false] {
        let mut reader = rig.reader(sync_read);
        rig.buses.upper.set_fault(Some(Fault::BadChecksum));
        let reading = reader.read_cycle(1);
        for (joint, position) in rig.table.joints().iter().zip(&reading.positions_rad) {
            assert_eq!(position.is_some(), joint.bus == "lower", "{}", joint.name);
        }
        let stats = reader.stats().snapshot();
        assert_eq!(stats.buses[1].bad_checksums, if sync_read { 1 } else { 15 });
        assert_eq!(stats.buses[1].timeouts, 0, "a bad checksum fails fast");
        rig.buses.upper.set_fault(None);
        let reading = cycle_until(&mut reader, "recovery", |r, _| r.is_complete());
        assert_positions(&rig.table, &reading, &raws);
    }
}

#[test]
fn garbage_before_the_sync_read_reply_is_skipped_on_ff_ff() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    let mut reader = rig.reader(true);
    // Noise that holds FF bytes and a false FF FF header before the reply.
    let garbage = vec![0x00, 0xFF, 0x13, 0xFF, 0xFF, 0x01, 0x09, 0xFF, 0xFF, 0xFF];
    rig.buses
        .lower
        .set_fault(Some(Fault::Garbage(garbage.clone())));
    rig.buses
        .upper
        .set_fault(Some(Fault::Garbage(garbage.clone())));
    for stamp in 0..3 {
        let reading = reader.read_cycle(stamp);
        assert_positions(&rig.table, &reading, &raws);
    }
    let stats = reader.stats().snapshot();
    assert_eq!(
        stats.total(|b| b.garbage_bytes),
        2 * 3 * garbage.len() as u64
    );
    assert_eq!(stats.complete_cycles, 3);
}

#[test]
fn garbage_before_per_motor_replies_is_counted_and_recovers() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    let mut reader = rig.reader(false);
    rig.buses
        .lower
        .set_fault(Some(Fault::Garbage(vec![0x42, 0x00, 0x17])));
    let reading = reader.read_cycle(1);
    assert!(reading.positions_rad.iter().take(10).all(Option::is_none));
    assert!(reading.positions_rad.iter().skip(10).all(Option::is_some));
    let stats = reader.stats().snapshot();
    assert_eq!(stats.buses[0].bad_packets, 10, "rustypot cannot frame them");
    assert!(
        stats.buses[0].garbage_bytes > 0,
        "the rest of each reply is drained and counted"
    );
    rig.buses.lower.set_fault(None);
    let reading = cycle_until(&mut reader, "recovery", |r, _| r.is_complete());
    assert_positions(&rig.table, &reading, &raws);
}

#[test]
fn servo_error_bits_are_counted_by_kind_and_the_position_kept() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    let overheating_and_overload =
        ServoErrorKind::Overheating.bit() | ServoErrorKind::Overload.bit();
    rig.buses
        .lower
        .set_error_bits(13, overheating_and_overload)
        .unwrap();
    rig.buses
        .upper
        .set_error_bits(36, ServoErrorKind::InputVoltage.bit())
        .unwrap();

    let mut reader = rig.reader(false);
    for stamp in 0..2 {
        let reading = reader.read_cycle(stamp);
        assert_positions(&rig.table, &reading, &raws);
    }
    let stats = reader.stats().snapshot();
    assert_eq!(stats.servo_errors(ServoErrorKind::Overheating), 2);
    assert_eq!(stats.servo_errors(ServoErrorKind::Overload), 2);
    assert_eq!(stats.servo_errors(ServoErrorKind::InputVoltage), 2);
    assert_eq!(stats.servo_errors(ServoErrorKind::Range), 0);

    // Through the USB2AX sync read the servos' error bits do not come through.
    // (The first reader holds the ports exclusively: close them first.)
    drop(reader);
    let mut reader = rig.reader(true);
    let reading = reader.read_cycle(0);
    assert_positions(&rig.table, &reading, &raws);
    assert_eq!(
        reader
            .stats()
            .snapshot()
            .servo_errors(ServoErrorKind::Overheating),
        0
    );
}

#[test]
fn an_unplugged_adapter_is_reopened_with_backoff() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    for sync_read in [true, false] {
        let mut reader = rig.reader(sync_read);
        assert!(reader.read_cycle(0).is_complete());
        rig.buses.upper.unplug().unwrap();
        let reading = cycle_until(&mut reader, "loss noticed", |_, s| !s.buses[1].connected);
        assert!(reading.positions_rad.iter().skip(10).all(Option::is_none));
        // The lower bus keeps being read while the upper one is gone.
        let reading = cycle_until(&mut reader, "failed reopen", |_, s| {
            s.buses[1].open_failures >= 2
        });
        assert!(reading.positions_rad.iter().take(10).all(Option::is_some));
        let stats = reader.stats().snapshot();
        assert_eq!(stats.buses[1].io_errors, 1);
        assert_eq!(stats.buses[1].reopens, 0);

        rig.buses.upper.replug().unwrap();
        let reading = cycle_until(&mut reader, "reopen", |r, _| r.is_complete());
        assert_positions(&rig.table, &reading, &raws);
        let stats = reader.stats().snapshot();
        assert_eq!(stats.buses[1].reopens, 1);
        assert!(stats.buses[1].connected);
    }
}

#[test]
fn positions_out_of_the_register_range_are_rejected() {
    let rig = rig();
    rig.set_distinct_positions();
    // An AX-12 cannot report 2000 (10 bits).
    rig.buses.upper.set_raw_position(36, 2000).unwrap();
    let mut reader = rig.reader(true);
    let reading = reader.read_cycle(0);
    assert_eq!(
        reading.positions_rad[rig.table.index_of("head_z").unwrap()],
        None
    );
    assert_eq!(reader.stats().snapshot().buses[1].bad_packets, 1);
}

#[test]
fn emulator_answers_write_data_and_the_reader_sees_the_new_goal() {
    let rig = rig();
    let dph = rustypot::DynamixelProtocolHandler::v1();
    let mut port = serialport::new(rig.buses.upper.port_path().to_string_lossy(), 1_000_000)
        .timeout(Duration::from_millis(500))
        .open()
        .expect("open emulated bus");
    assert!(dph.ping(port.as_mut(), 41).unwrap());
    assert!(
        !dph.ping(port.as_mut(), 11).unwrap(),
        "11 is on the other bus"
    );
    // Goal Position of l_shoulder_y (MX-28) to raw 3000: the servo gets there.
    dph.write(port.as_mut(), 41, 30, &3000u16.to_le_bytes())
        .unwrap();
    let model = dph.read(port.as_mut(), 36, 0, 2).unwrap();
    assert_eq!(
        u16::from_le_bytes([model[0], model[1]]),
        ServoModel::Ax12.model_number()
    );
    drop(port);
    assert_eq!(rig.buses.upper.raw_position(41).unwrap(), 3000);
    let mut reader = rig.reader(true);
    let reading = reader.read_cycle(0);
    let joint = &rig.table.joints()[rig.table.index_of("l_shoulder_y").unwrap()];
    let got = reading.positions_rad[rig.table.index_of("l_shoulder_y").unwrap()].unwrap();
    assert!((got - joint.raw_to_rad(3000) as f32).abs() < 1e-6);
}

/// The noise of a bus that lost every forecast under a gap-per-cycle rule:
/// 5% of each motor's replies dropped, 2% with a bad checksum, 5% with
/// garbage bytes before them.
fn noise(seed: u64) -> ReplyNoise {
    ReplyNoise {
        seed,
        p_drop: 0.05,
        p_corrupt: 0.02,
        p_garbage: 0.05,
    }
}

#[test]
fn seeded_reply_noise_repeats_and_a_sync_read_asks_again_for_the_motors_lost() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    const CYCLES: i64 = 60;
    let run = || {
        rig.buses.lower.set_noise(Some(noise(3)));
        rig.buses.upper.set_noise(Some(noise(4)));
        let sync_before = rig.buses.upper.requests().sync_reads;
        let mut reader = rig.reader(true);
        let mut read = Vec::new();
        for stamp in 0..CYCLES {
            let reading = reader.read_cycle(stamp);
            // Every position read is the motor's own: a faulted reply is
            // never taken as a position.
            for ((joint, raw), got) in rig
                .table
                .joints()
                .iter()
                .zip(&raws)
                .zip(&reading.positions_rad)
            {
                if let Some(got) = got {
                    assert_eq!(*got, joint.raw_to_rad(*raw) as f32, "{}", joint.name);
                }
            }
            read.push(
                reading
                    .positions_rad
                    .iter()
                    .map(Option::is_some)
                    .collect::<Vec<_>>(),
            );
        }
        let sync_reads = rig.buses.upper.requests().sync_reads - sync_before;
        (
            read,
            rig.buses.upper.noise_counts(),
            sync_reads,
            reader.stats().snapshot(),
        )
    };
    let (first, counts, sync_reads, stats) = run();
    let (again, counts_again, _, _) = run();
    // The same seed, the same requests: the same faults and readings.
    assert_eq!(counts, counts_again);
    assert_eq!(first, again);
    assert!(
        counts.dropped > 0 && counts.corrupted > 0 && counts.garbage > 0,
        "{counts:?}"
    );
    let faulted = counts.dropped + counts.corrupted + counts.garbage;
    // A motor's faulted reply gives FF bytes in a well-formed adapter
    // reply (no host-side error), and the lost ones are asked for again.
    let upper = &stats.buses[1];
    assert_eq!(
        upper.bad_checksums + upper.timeouts + upper.bad_packets,
        0,
        "{upper:?}"
    );
    assert!(
        sync_reads > CYCLES as u64,
        "{sync_reads} sync reads in {CYCLES} cycles"
    );
    let missed: u64 = upper.motor_missed.iter().sum();
    assert!(
        missed * 4 < faulted,
        "{missed} motor reads missed after asking again, {faulted} faulted replies"
    );
    assert_eq!(missed, upper.missing_motor_reads);
}

#[test]
fn each_bus_and_each_retry_stamps_its_positions_with_its_own_request() {
    use std::sync::atomic::{AtomicI64, Ordering};

    let rig = rig();
    rig.set_distinct_positions();
    rig.buses.upper.set_noise(Some(noise(4)));
    let mut reader = rig.reader(true);
    // A clock that counts its reads: the cycle's start, then one read just
    // before each request (the lower bus's sync read, the upper's, and a
    // retry of the motors lost in one).
    let ticks = AtomicI64::new(0);
    let clock = || ticks.fetch_add(1, Ordering::SeqCst) + 1;
    let on_bus = |bus: &str| -> Vec<usize> {
        (0..25)
            .filter(|&i| rig.table.joints()[i].bus == bus)
            .collect()
    };
    let (lower, upper) = (on_bus("lower"), on_bus("upper"));
    let mut retried = 0;
    for _ in 0..40 {
        let start = ticks.load(Ordering::SeqCst) + 1;
        let reading = reader.read_cycle_with(&clock);
        for (p, t) in reading.positions_rad.iter().zip(&reading.read_ns) {
            assert_eq!(p.is_some(), t.is_some(), "{reading:?}");
        }
        // The lower bus (no noise): every position from its one sync read,
        // just after the cycle's start.
        assert!(
            lower.iter().all(|&i| reading.read_ns[i] == Some(start + 1)),
            "{:?}",
            reading.read_ns
        );
        // The upper bus, read after it: its sync read's stamp, or for a
        // motor lost in it and got by the retry, the retry's.
        let stamps: Vec<i64> = upper.iter().filter_map(|&i| reading.read_ns[i]).collect();
        assert!(
            stamps.iter().all(|&t| t == start + 2 || t == start + 3),
            "{stamps:?}"
        );
        retried += stamps.iter().filter(|&&t| t == start + 3).count();
        // The reading's stamp is its newest position's.
        assert_eq!(
            Some(reading.stamp_ns),
            reading.read_ns.iter().flatten().copied().max()
        );
    }
    assert!(retried > 0, "no position came from a retry");
    // The bus statistics keep each motor's own stamp too.
    let stats = reader.stats().snapshot();
    let last_lower = stats.buses[0].motor_last_read_ns[0].expect("read");
    let last_upper = stats.buses[1]
        .motor_last_read_ns
        .iter()
        .flatten()
        .max()
        .copied();
    assert!(last_upper > Some(last_lower), "{last_upper:?} {last_lower}");
}

#[test]
fn seeded_reply_noise_on_per_motor_reads_is_counted_by_kind() {
    let rig = rig();
    let raws = rig.set_distinct_positions();
    let mut reader = rig.reader(false);
    rig.buses.upper.set_noise(Some(noise(5)));
    for stamp in 0..12 {
        let reading = reader.read_cycle(stamp);
        for ((joint, raw), got) in rig
            .table
            .joints()
            .iter()
            .zip(&raws)
            .zip(&reading.positions_rad)
        {
            if let Some(got) = got {
                assert_eq!(*got, joint.raw_to_rad(*raw) as f32, "{}", joint.name);
            }
        }
    }
    let counts = rig.buses.upper.noise_counts();
    let upper = &reader.stats().snapshot().buses[1];
    // Seen by the host as they are: a dropped reply is a timeout, a
    // corrupted one a bad checksum, one after garbage a packet rustypot
    // cannot frame (the rest of it drained and counted as garbage).
    assert_eq!(counts.replies, 12 * 15);
    assert!(
        counts.dropped > 0 && counts.corrupted + counts.garbage > 0,
        "{counts:?}"
    );
    assert_eq!(upper.timeouts, counts.dropped, "{counts:?} {upper:?}");
    assert_eq!(
        upper.bad_checksums, counts.corrupted,
        "{counts:?} {upper:?}"
    );
    assert_eq!(upper.bad_packets, counts.garbage, "{counts:?} {upper:?}");
    assert_eq!(
        upper.missing_motor_reads,
        counts.dropped + counts.corrupted + counts.garbage,
        "{counts:?} {upper:?}"
    );
    assert_eq!(
        upper.garbage_bytes > 0,
        counts.garbage > 0,
        "{counts:?} {upper:?}"
    );
}
