//! The library's layers import only downwards (`scripts/check-layers.py`,
//! `docs/architecture.md`): the check passes on `src/`, and fails, naming
//! the import, on a copy of `src/` with one module importing a layer above
//! it or two modules importing each other.

use std::path::{Path, PathBuf};
use std::process::Command;

fn check(src: &Path) -> (bool, String) {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new("python3")
        .arg(root.join("scripts/check-layers.py"))
        .arg("--src")
        .arg(src)
        .output()
        .expect("python3 runs the layer check");
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("mkdir");
    for entry in std::fs::read_dir(from).expect("read_dir") {
        let entry = entry.expect("entry");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("type").is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).expect("copy");
        }
    }
}

fn append(path: &Path, text: &str) {
    let mut s = std::fs::read_to_string(path).expect("read");
    s.push_str(text);
    std::fs::write(path, s).expect("write");
}

#[test]
fn the_library_imports_only_downwards() {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("src");
    let (ok, text) = check(&src);
    assert!(ok, "layer check failed on src/:\n{text}");
    assert!(text.contains("layers ok"), "{text}");
}

#[test]
fn an_upward_import_or_a_cycle_is_named() {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("src");
    let scratch = tempfile::tempdir().expect("tempdir");
    let copy = scratch.path().join("src");
    copy_dir(&src, &copy);

    // A stream module reaching up into the daemon.
    append(
        &copy.join("streams.rs"),
        "\nfn _up() { let _ = crate::daemon::bench::BenchDaemonOptions::default; }\n",
    );
    let (ok, text) = check(&copy);
    assert!(!ok, "an upward import passed:\n{text}");
    assert!(
        text.contains("streams (streams) imports daemon::bench"),
        "{text}"
    );

    // Two units of one layer importing each other: a cycle.
    copy_dir(&src, &copy);
    append(&copy.join("clock.rs"), "\nuse crate::robot::JointTable;\n");
    append(&copy.join("robot.rs"), "\nuse crate::clock::TickGrid;\n");
    let (ok, text) = check(&copy);
    assert!(!ok, "a cycle passed:\n{text}");
    assert!(text.contains("import cycle: clock <-> robot"), "{text}");
}
