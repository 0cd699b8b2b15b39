//! Inputs from outside fed random bytes: the MCAP reader, the config loader
//! and the servo packet scanner (the latter in `sources/dynamixel/protocol.rs`)
//! return errors, never panic.

use std::path::{Path, PathBuf};

use fall_guard_runtime::config::Config;
use fall_guard_runtime::recording::Recording;
use proptest::prelude::*;

fn repo(path: &str) -> PathBuf {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join(path)
}

fn fixture() -> &'static [u8] {
    static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    BYTES.get_or_init(|| std::fs::read(repo("tests/fixtures/episode_00000.mcap")).expect("fixture"))
}

fn replay_config() -> &'static str {
    static TEXT: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    TEXT.get_or_init(|| std::fs::read_to_string(repo("config/replay.toml")).expect("config"))
}

fn open_bytes(bytes: &[u8]) {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("fuzz.mcap");
    std::fs::write(&path, bytes).expect("write");
    // Ok or Err; a panic fails the test.
    let _ = Recording::open(&path);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn mcap_reader_survives_random_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        open_bytes(&bytes);
    }

    #[test]
    fn mcap_reader_survives_a_corrupted_recording(
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..16),
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
    ) {
        let mut bytes = fixture().to_vec();
        for (at, value) in flips {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        if truncate {
            bytes.truncate(cut.index(bytes.len()));
        }
        open_bytes(&bytes);
    }

    #[test]
    fn config_loader_survives_random_text(bytes in proptest::collection::vec(any::<u8>(), 0..1024)) {
        let text = String::from_utf8_lossy(&bytes);
        let _ = Config::parse(&text, "fuzz.toml", Path::new(""));
    }

    #[test]
    fn config_loader_survives_a_mangled_config(
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<char>()), 1..8),
    ) {
        let mut chars: Vec<char> = replay_config().chars().collect();
        for (at, c) in flips {
            let i = at.index(chars.len());
            chars[i] = c;
        }
        let text: String = chars.into_iter().collect();
        let _ = Config::parse(&text, "fuzz.toml", Path::new(""));
    }
}
