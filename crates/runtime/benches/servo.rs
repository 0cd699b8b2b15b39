//! One 25-joint read cycle (both Poppy buses) over the bus emulator on real
//! pseudo-terminals: USB2AX sync read vs one READ_DATA per motor, with the
//! emulator answering at once (reader + pty cost) and with 1 Mbaud wire time
//! simulated (what a real bus adds, USB latency not included).
//!
//! `cargo bench -p fall-guard-runtime --bench servo`; medians in
//! `target/criterion/read_cycle_25_joints/<mode>_<wire>/new/estimates.json`.

use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use fall_guard_runtime::robot::JointTable;
use fall_guard_runtime::sources::dynamixel::ServoReader;
use fall_guard_testkit::emulator::PoppyBuses;

fn read_cycle(c: &mut Criterion) {
    let table = JointTable::poppy_humanoid();
    let dir = tempfile::tempdir().expect("temp dir");
    let buses = PoppyBuses::start(&table, dir.path()).expect("emulated buses");
    let mut group = c.benchmark_group("read_cycle_25_joints");
    group.sample_size(60);
    group.measurement_time(Duration::from_secs(3));
    for (wire, baud) in [("instant", None), ("wire_1mbaud", Some(1_000_000))] {
        buses.lower.set_wire_baud(baud);
        buses.upper.set_wire_baud(baud);
        for sync_read in [true, false] {
            let mut config = buses.config();
            for bus in config.buses.values_mut() {
                bus.sync_read = sync_read;
            }
            let mut reader = ServoReader::new(&config, &table).expect("config");
            assert!(
                (0..10).any(|stamp| reader.read_cycle(stamp).is_complete()),
                "the emulator does not answer"
            );
            let name = format!(
                "{}/{wire}",
                if sync_read { "sync_read" } else { "per_motor" }
            );
            let mut stamp = 0;
            group.bench_function(&name, |b| {
                b.iter(|| {
                    stamp += 1;
                    reader.read_cycle(stamp)
                })
            });
            let stats = reader.stats().snapshot();
            // A cycle misses motors when the emulator thread is not scheduled
            // within timeout_ms (a loaded machine): say how often.
            eprintln!(
                "{name}: {} of {} cycles complete, {} timeouts",
                stats.complete_cycles,
                stats.cycles,
                stats.total(|b| b.timeouts)
            );
        }
    }
    group.finish();
}

criterion_group!(benches, read_cycle);
criterion_main!(benches);
