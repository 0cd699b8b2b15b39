//! The crates are the architecture (`docs/architecture.md`): the robot's
//! binary never reaches the lab, nor plotters, linfa or indicatif
//! (`scripts/checks/check-crates.sh`, on `cargo tree`), and inside each library
//! crate the modules import one another without a cycle
//! (`scripts/checks/check-layers.py`). Each check passes on the repository and
//! fails, naming what is wrong, on a graph that breaks it.

use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn output(command: &mut Command) -> (bool, String) {
    let out = command.output().expect("the check runs");
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

fn layers(srcs: &[&Path]) -> (bool, String) {
    output(
        Command::new("python3")
            .arg(root().join("scripts/checks/check-layers.py"))
            .arg("--src")
            .args(srcs),
    )
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
fn the_crates_modules_import_without_a_cycle() {
    let (runtime, lab) = (
        root().join("crates/runtime/src"),
        root().join("crates/lab/src"),
    );
    let (ok, text) = layers(&[&runtime, &lab]);
    assert!(ok, "layer check failed:\n{text}");
    assert!(
        text.contains("crates/runtime/src: layers ok")
            && text.contains("crates/lab/src: layers ok"),
        "{text}"
    );
}

#[test]
fn an_import_back_up_or_a_cycle_is_named() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let copy = scratch.path().join("src");

    // A stream module reaching up into the daemon, which imports it.
    copy_dir(&root().join("crates/runtime/src"), &copy);
    append(
        &copy.join("streams.rs"),
        "\nfn _up() { let _ = crate::daemon::bench::BenchDaemonOptions::default; }\n",
    );
    let (ok, text) = layers(&[&copy]);
    assert!(!ok, "an import back up passed:\n{text}");
    assert!(text.contains("import cycle: "), "{text}");
    assert!(text.contains("streams -> daemon (streams)"), "{text}");

    // Two lab modules importing each other, through `super::`.
    std::fs::remove_dir_all(&copy).expect("rm");
    copy_dir(&root().join("crates/lab/src"), &copy);
    append(
        &copy.join("checkpoint.rs"),
        "\nuse super::fit::FitOptions;\n",
    );
    let (ok, text) = layers(&[&copy]);
    assert!(!ok, "a cycle passed:\n{text}");
    assert!(text.contains("checkpoint -> fit (checkpoint)"), "{text}");
}

fn crates(args: &[&str]) -> (bool, String) {
    output(
        Command::new("bash")
            .arg(root().join("scripts/checks/check-crates.sh"))
            .args(args)
            .env("CARGO", env!("CARGO")),
    )
}

#[test]
fn the_robot_binary_links_no_training() {
    let (ok, text) = crates(&[]);
    assert!(ok, "crate check failed:\n{text}");
    assert!(
        text.contains("check-crates: fall-guard (default features)"),
        "{text}"
    );
}

#[test]
fn a_robot_build_reaching_the_lab_is_named() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let tree = scratch.path().join("tree.txt");
    std::fs::write(
        &tree,
        "fall-guard v0.1.0\nfall-guard-runtime v0.1.0\nfall-guard-lab v0.1.0\nplotters v0.3.7\nclap v4.5.0\n",
    )
    .expect("write");
    let tree = tree.to_str().expect("utf8");
    let (ok, text) = crates(&["--tree", tree, "fall-guard"]);
    assert!(!ok, "a robot build with the lab passed:\n{text}");
    assert!(
        text.contains("fall-guard (") && text.contains("depends on fall-guard-lab"),
        "{text}"
    );
    assert!(text.contains("depends on plotters"), "{text}");
    // Nor may the runtime reach the lab.
    let (ok, text) = crates(&["--tree", tree, "fall-guard-runtime"]);
    assert!(!ok && text.contains("depends on fall-guard-lab"), "{text}");
    assert!(!text.contains("depends on clap"), "{text}");
}
