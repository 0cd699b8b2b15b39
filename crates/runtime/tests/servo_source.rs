//! The servo source as the daemon runs it: a thread offering into the
//! joints stream's feed, stopped by the shutdown signal; and its config as the daemon
//! parses it (TOML, unknown keys rejected, errors naming the key).

use std::time::Duration;

use fall_guard_runtime::robot::JointTable;
use fall_guard_runtime::sources::dynamixel::{
    DynamixelConfig, DynamixelError, DynamixelSource, ServoReader,
};
use fall_guard_runtime::streams::input::InputLimits;
use fall_guard_runtime::streams::sample::Sample;
use fall_guard_runtime::streams::{stream, StreamKind, StreamTap};
use fall_guard_testkit::emulator::{Fault, PoppyBuses};
use tokio::sync::watch;

/// The joints of the stream's next sample that `pick` accepts.
async fn next_joints(
    tap: &mut StreamTap<Sample>,
    pick: impl Fn(&[f32]) -> bool,
) -> Option<(i64, Vec<f32>)> {
    let wait = async {
        loop {
            let s = tap.changed().await.expect("reader alive");
            if let Sample::Joints { positions_rad, .. } = &s.value {
                if pick(positions_rad) {
                    return (s.stamp_ns, positions_rad.clone());
                }
            }
        }
    };
    tokio::time::timeout(Duration::from_secs(5), wait)
        .await
        .ok()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn source_offers_readings_survives_a_fault_and_stops_on_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let table = JointTable::poppy_humanoid();
    let buses = PoppyBuses::start(&table, dir.path()).unwrap();
    let head_y = table.index_of("head_y").unwrap();
    buses.set_raw_position(37, 400).unwrap();
    let mut config = buses.config();
    config.rate_hz = 100.0;

    let (shutdown_tx, shutdown_rx) = watch::channel(false);
    let clock = std::sync::Arc::new(fall_guard_runtime::sources::dynamixel::system_clock_ns);
    let (feed, mut tap) = stream::<Sample>(
        StreamKind::Joints,
        InputLimits::shapes(table.joints().len(), 0),
    );
    let source =
        DynamixelSource::spawn_with_clock(&config, &table, feed, shutdown_rx, clock).unwrap();

    let (complete_ns, complete) = next_joints(&mut tap, |p| p.iter().all(|v| v.is_finite()))
        .await
        .expect("a complete reading within 5 s");
    let expected = table.joints()[head_y].raw_to_rad(400) as f32;
    assert!((complete[head_y] - expected).abs() < 1e-6);
    assert!(complete_ns > 0);

    // The upper bus goes silent: readings keep coming with the lower bus
    // only (NaN for the upper bus's joints), each counted incomplete.
    buses.upper.set_fault(Some(Fault::NoReply));
    let (partial_ns, partial) = next_joints(&mut tap, |p| p[head_y].is_nan())
        .await
        .expect("a reading without the upper bus");
    assert!(partial[..10].iter().all(|v| v.is_finite()));
    assert!(partial_ns > complete_ns);
    assert!(source.stats.snapshot().buses[1].timeouts > 0);
    let errors = tap.stats().snapshot().error_kinds;
    assert!(
        errors
            .iter()
            .any(|(kind, n)| kind == "incomplete read" && *n > 0),
        "{errors:?}"
    );
    buses.upper.set_fault(None);

    // The bus counters and one status per bus reach the stream's diagnostics.
    tokio::time::sleep(Duration::from_millis(600)).await;
    let snapshot = tap.stats().snapshot();
    assert!(snapshot.errors > 0, "{snapshot:?}");
    assert_eq!(snapshot.devices.len(), 2, "{snapshot:?}");

    shutdown_tx.send(true).unwrap();
    let stats = source.stats.clone();
    tokio::task::spawn_blocking(move || source.join())
        .await
        .unwrap();
    let snapshot = stats.snapshot();
    assert!(!snapshot.running);
    assert!(snapshot.cycles >= 2);
}

#[test]
fn config_parses_from_toml_with_defaults() {
    let config: DynamixelConfig = toml::from_str(
        r#"
        [buses.lower]
        port = "/dev/ttyACM0"
        [buses.upper]
        port = "/dev/ttyACM1"
        sync_read = false
        timeout_ms = 10
        "#,
    )
    .unwrap();
    assert_eq!(config.rate_hz, 50.0);
    let lower = &config.buses["lower"];
    assert_eq!(lower.baud, 1_000_000);
    assert!(lower.sync_read);
    assert_eq!(lower.timeout_ms, 20);
    assert_eq!(lower.reopen_backoff_ms, 100);
    assert_eq!(lower.ids, None);
    assert!(!config.buses["upper"].sync_read);
    assert_eq!(config, {
        let mut poppy = DynamixelConfig::poppy("/dev/ttyACM0", "/dev/ttyACM1");
        let upper = poppy.buses.get_mut("upper").unwrap();
        upper.sync_read = false;
        upper.timeout_ms = 10;
        poppy
    });
    // Ports are opened on the first cycle, not here.
    assert!(ServoReader::new(&config, &JointTable::poppy_humanoid()).is_ok());
}

#[test]
fn unknown_keys_are_rejected() {
    let err = toml::from_str::<DynamixelConfig>(
        r#"
        [buses.lower]
        port = "/dev/ttyACM0"
        baudrate = 57600
        "#,
    )
    .unwrap_err();
    assert!(err.to_string().contains("baudrate"), "{err}");
}

fn config_error(toml_text: &str) -> String {
    let config: DynamixelConfig = toml::from_str(toml_text).unwrap();
    match ServoReader::new(&config, &JointTable::poppy_humanoid()) {
        Err(err @ DynamixelError::Config { .. }) => err.to_string(),
        Err(other) => panic!("unexpected error {other}"),
        Ok(_) => panic!("config accepted: {toml_text}"),
    }
}

#[test]
fn bad_values_are_errors_that_name_the_key() {
    let err = config_error("[buses.lower]\nport = \"/dev/x\"\nids = [11, 99]");
    assert!(
        err.starts_with("buses.lower.ids:") && err.contains("99"),
        "{err}"
    );
    let err = config_error(
        "[buses.lower]\nport = \"/dev/x\"\n[buses.upper]\nport = \"/dev/y\"\nids = [11, 31]",
    );
    assert!(
        err.starts_with("buses.upper.ids:") && err.contains("also on bus 'lower'"),
        "{err}"
    );
    let err = config_error("[buses.legs]\nport = \"/dev/x\"");
    assert!(
        err.starts_with("buses.legs.ids:") && err.contains("no bus named 'legs'"),
        "{err}"
    );
    let err = config_error("rate_hz = 0\n[buses.lower]\nport = \"/dev/x\"");
    assert!(err.starts_with("rate_hz:"), "{err}");
    let err = config_error("[buses.lower]\nport = \"/dev/x\"\ntimeout_ms = 0");
    assert!(err.starts_with("buses.lower.timeout_ms:"), "{err}");
    let err = config_error(
        "[buses.lower]\nport = \"/dev/x\"\nreopen_backoff_ms = 500\nreopen_backoff_max_ms = 100",
    );
    assert!(
        err.starts_with("buses.lower.reopen_backoff_max_ms:"),
        "{err}"
    );
    let ids: Vec<String> = (1..=32).map(|i| i.to_string()).collect();
    let err = config_error(&format!(
        "[buses.all]\nport = \"/dev/x\"\nids = [{}]",
        ids.join(", ")
    ));
    assert!(
        err.starts_with("buses.all.ids:") && err.contains("31"),
        "{err}"
    );
    let err = config_error("buses = {}");
    assert!(err.starts_with("buses:"), "{err}");
}

#[test]
fn a_port_that_does_not_exist_is_retried_without_failing() {
    let dir = tempfile::tempdir().unwrap();
    let table = JointTable::poppy_humanoid();
    let mut config = DynamixelConfig::poppy(
        dir.path().join("absent-lower").to_string_lossy(),
        dir.path().join("absent-upper").to_string_lossy(),
    );
    for bus in config.buses.values_mut() {
        bus.reopen_backoff_ms = 40;
        bus.reopen_backoff_max_ms = 40;
    }
    let mut reader = ServoReader::new(&config, &table).unwrap();
    let started = std::time::Instant::now();
    let mut cycles = 0;
    while started.elapsed() < Duration::from_millis(100) {
        let reading = reader.read_cycle(cycles);
        assert!(reading.positions_rad.iter().all(Option::is_none));
        cycles += 1;
        std::thread::sleep(Duration::from_millis(1));
    }
    // Tries at 0, 40 and 80 ms (later on a busy machine, never sooner),
    // not one per cycle.
    let stats = reader.stats().snapshot();
    let attempts = stats.buses[0].open_failures;
    assert!(
        (1..=3).contains(&attempts),
        "{attempts} open attempts in {cycles} cycles"
    );
    assert!(cycles > 10);
    assert_eq!(stats.cycles, cycles as u64);
    assert!(!stats.buses[0].connected);
}
