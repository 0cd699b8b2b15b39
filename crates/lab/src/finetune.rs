//! `fall-guard-lab finetune`: a shipped network fine-tuned on a robot
//! owner's own recordings mixed with the simulated set, calibrated, its
//! latch thresholds chosen again, and both networks measured on what was
//! held back of the owner's walks and on the simulated test falls; a small
//! card says what changed.
//!
//! The owner's walks (labelled `--no-fall`) are split by time: the first
//! `1 - holdout` of each goes to training, the rest is held back and never
//! used for a choice. Their falls (labelled `--fall-at`) all go to
//! training. The owner's parts are listed `owner_copies` times in the
//! training split so that they are not drowned by the simulated episodes.
//! The new network keeps the shipped one's standardisation and sizes
//! (`train --init`), and its input ranges are those of the mixed training
//! split, the owner's walks included.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::calibrate::{run_calibrate, CalibrateOptions, FormChoice};
use crate::commands::{run_train, TrainOptions};
use crate::dataset::{data_name, Dataset, Manifest, Split};
use crate::device::TrainDevice;
use crate::error::{refused, CommandResult, Doing};
use crate::sampler::Protocol;
use crate::warning::{run_warnings, WarningStats, WarningsOptions};
use fall_guard_runtime::config::Config;
use fall_guard_runtime::model::file::load_emp;
use fall_guard_runtime::model::{cpu_device, Ablation, ModelMeta};
use fall_guard_runtime::recording::{cut, Recording};

/// `fall-guard-lab finetune`.
#[derive(Debug, Clone)]
pub struct FinetuneOptions {
    /// The network to fine-tune (a shipped model file).
    pub model: PathBuf,
    /// The owner's labelled recordings.
    pub recordings: Vec<PathBuf>,
    /// The simulated data set (its train, validation and test splits).
    pub data: PathBuf,
    /// Output directory: the data set made, the network, the card.
    pub out: PathBuf,
    /// Share of each owner walk held back, its end.
    pub holdout: f64,
    /// How many times each owner part is listed in the training split.
    pub owner_copies: usize,
    /// Training epochs at most.
    pub epochs: usize,
    /// The shipped rates multiplied by this while fine-tuning.
    pub lr_scale: f64,
    pub seed: u64,
    /// The latch: horizon watched, release hold.
    pub horizon_ms: u32,
    pub release_hold_ms: u32,
    /// The shipped network's pair: `Some` as given, `None` read from
    /// `config` (its `[model.thresholds]` line for the network, else
    /// `[model].trigger` / `release`).
    pub pair: Option<(f32, f32)>,
    /// The daemon's config that holds the shipped pair; `None`: the
    /// embedded default (`config/replay.toml`, the shipped pairs).
    pub config: Option<PathBuf>,
    /// The data set whose validation split the new pair is chosen on (the
    /// retrain's choice set, as the shipped pair was); `None`: the
    /// simulated set's validation split.
    pub choice: Option<PathBuf>,
    /// Budgets of the threshold choice (validation: simulated).
    pub max_false_alarms_per_min: f64,
    pub max_held_share: f64,
    pub device: TrainDevice,
}

/// One network's figures on the two measures.
#[derive(Debug, Clone, Serialize)]
pub struct Measured {
    pub model: String,
    pub trigger: f32,
    pub release: f32,
    /// On the owner's held-back walks.
    pub owner: WarningStats,
    /// On the simulated test split.
    pub simulated: WarningStats,
}

/// What `finetune` wrote and found.
#[derive(Debug, Clone, Serialize)]
pub struct FinetuneCard {
    pub shipped: Measured,
    pub finetuned: Measured,
    /// Seconds of owner walking trained on / held back.
    pub owner_fit_s: f64,
    pub owner_held_s: f64,
    pub owner_falls: usize,
    pub owner_copies: usize,
    pub simulated_set: String,
}

fn seconds(rec: &Recording) -> f64 {
    match (rec.start_ns(), rec.end_ns()) {
        (Some(a), Some(b)) => (b - a) as f64 / 1e9,
        _ => 0.0,
    }
}

/// Links `target` as `dir/name` (a copy where links are refused).
fn link(target: &Path, dir: &Path, name: &str) -> CommandResult<String> {
    let at = dir.join(name);
    let _ = std::fs::remove_file(&at);
    let target = std::fs::canonicalize(target).doing(|| format!("reading {}", target.display()))?;
    #[cfg(unix)]
    let made = std::os::unix::fs::symlink(&target, &at);
    #[cfg(not(unix))]
    let made = std::fs::copy(&target, &at).map(|_| ());
    made.doing(|| format!("linking {}", at.display()))?;
    Ok(name.to_string())
}

fn write_manifest(dir: &Path, manifest: &Manifest) -> CommandResult<()> {
    std::fs::create_dir_all(dir).doing(|| format!("creating {}", dir.display()))?;
    let path = dir.join("manifest.json");
    std::fs::write(&path, serde_json::to_vec_pretty(manifest)?)
        .doing(|| format!("writing {}", path.display()))
}

/// The owner's recordings cut and the two data sets written: `OUT/set`
/// (the simulated splits, the owner's fitting parts added to train) and
/// `OUT/owner` (the held-back parts as its test split).
fn make_sets(args: &FinetuneOptions, sim: &Dataset) -> CommandResult<(f64, f64, usize)> {
    let parts = args.out.join("owner-parts");
    std::fs::create_dir_all(&parts).doing(|| format!("creating {}", parts.display()))?;
    let (mut fit, mut held) = (Vec::new(), Vec::new());
    let (mut fit_s, mut held_s, mut falls) = (0.0, 0.0, 0);
    for (i, path) in args.recordings.iter().enumerate() {
        let rec = Recording::open(path).doing(|| format!("reading {}", path.display()))?;
        let meta = rec.episode().map_err(|e| {
            refused(format!(
                "{}: not labelled ({e}); label it first: `fall-guard label --no-fall` or `--fall-at S`",
                path.display()
            ))
        })?;
        if meta.fall_onset_ns.is_some() {
            falls += 1;
            fit_s += seconds(&rec);
            fit.push(path.clone());
            continue;
        }
        let (Some(start), Some(end)) = (rec.start_ns(), rec.end_ns()) else {
            return Err(refused(format!("{}: no messages", path.display())));
        };
        let at = start + ((end - start) as f64 * (1.0 - args.holdout)) as i64;
        let (a, b) = (
            parts.join(format!("owner-{i:03}-fit.mcap")),
            parts.join(format!("owner-{i:03}-held.mcap")),
        );
        cut(path, &a, start, at).doing(|| format!("cutting {}", path.display()))?;
        cut(path, &b, at, end + 1).doing(|| format!("cutting {}", path.display()))?;
        fit_s += (at - start) as f64 / 1e9;
        held_s += (end - at) as f64 / 1e9;
        fit.push(a);
        held.push(b);
    }
    if held.is_empty() {
        return Err(refused(
            "no walk among the recordings (labelled --no-fall): nothing to measure time held on",
        ));
    }
    let set = args.out.join("set");
    std::fs::create_dir_all(&set).doing(|| format!("creating {}", set.display()))?;
    let mut manifest = Manifest {
        train: Vec::new(),
        validation: Vec::new(),
        test: Vec::new(),
        generator: sim.manifest.generator.clone(),
    };
    for split in Split::ALL {
        let names = sim
            .manifest
            .files(split)
            .iter()
            .map(|n| link(&sim.dir.join(n), &set, n))
            .collect::<CommandResult<Vec<_>>>()?;
        match split {
            Split::Train => manifest.train = names,
            Split::Validation => manifest.validation = names,
            Split::Test => manifest.test = names,
        }
    }
    for (i, part) in fit.iter().enumerate() {
        for copy in 0..args.owner_copies.max(1) {
            let name = format!("owner-{i:03}-c{copy:03}.mcap");
            manifest.train.push(link(part, &set, &name)?);
        }
    }
    write_manifest(&set, &manifest)?;
    let owner = args.out.join("owner");
    std::fs::create_dir_all(&owner).doing(|| format!("creating {}", owner.display()))?;
    let test = held
        .iter()
        .enumerate()
        .map(|(i, p)| link(p, &owner, &format!("held-{i:03}.mcap")))
        .collect::<CommandResult<Vec<_>>>()?;
    write_manifest(
        &owner,
        &Manifest {
            train: Vec::new(),
            validation: Vec::new(),
            test,
            generator: serde_json::json!({"name": "the owner's held-back walks"}),
        },
    )?;
    Ok((fit_s, held_s, falls))
}

/// The pair the daemon runs `network` with under `config` (the embedded
/// default when `None`).
fn shipped_pair(config: Option<&Path>, network: Ablation) -> CommandResult<(f32, f32)> {
    let (config, origin) = match config {
        Some(path) => (Config::load(path), path.display().to_string()),
        None => (
            Config::embedded_replay(),
            "the embedded default config".to_string(),
        ),
    };
    let pair = config
        .and_then(|c| c.latch_thresholds())
        .map_err(|e| refused(format!("the shipped pair from {origin}: {e}")))?
        .of(network);
    Ok((pair.trigger(), pair.release()))
}

fn warnings(
    args: &FinetuneOptions,
    model: &Path,
    data: &Path,
    split: Split,
    pair: (f32, f32),
    choose: bool,
) -> CommandResult<crate::warning::WarningsReport> {
    run_warnings(&WarningsOptions {
        model: model.to_path_buf(),
        data: data.to_path_buf(),
        split,
        horizon_ms: args.horizon_ms,
        trigger: pair.0,
        release: pair.1,
        release_hold_ms: args.release_hold_ms,
        choose,
        max_false_alarms_per_min: args.max_false_alarms_per_min,
        max_held_share: args.max_held_share,
        hold_out_of_range: true,
        out: None,
    })
}

fn measure(args: &FinetuneOptions, model: &Path, pair: (f32, f32)) -> CommandResult<Measured> {
    // The test split of OUT/`set` at `pair`: its one row.
    let on_test = |set: &str| -> CommandResult<WarningStats> {
        warnings(args, model, &args.out.join(set), Split::Test, pair, false)?
            .grid
            .into_iter()
            .next()
            .ok_or_else(|| refused(format!("no figures on {set}")))
    };
    Ok(Measured {
        model: data_name(model),
        trigger: pair.0,
        release: pair.1,
        owner: on_test("owner")?,
        simulated: on_test("set")?,
    })
}

/// Runs the fine-tune; writes `OUT/<name>.bpk`, `OUT/card.json` and
/// `OUT/card.md`, and returns the card.
pub fn run_finetune(args: &FinetuneOptions) -> CommandResult<FinetuneCard> {
    if !(0.0..1.0).contains(&args.holdout) || args.holdout == 0.0 {
        return Err(refused(format!(
            "--holdout {}: a share in (0, 1) of each walk to measure on",
            args.holdout
        )));
    }
    let (shipped, _): (ModelMeta, _) = load_emp(&args.model, &cpu_device())
        .doing(|| format!("reading {}", args.model.display()))?;
    let shipped_pair = match args.pair {
        Some(pair) => pair,
        None => shipped_pair(args.config.as_deref(), shipped.ablation)?,
    };
    let sim = Dataset::open(&args.data).doing(|| format!("opening {}", args.data.display()))?;
    let (fit_s, held_s, falls) = make_sets(args, &sim)?;
    let name = args
        .model
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "model".into());
    let trained = args.out.join(format!("{name}.finetuned.bpk"));
    let horizons = shipped.horizons_ticks.clone();
    // Trained and calibrated under the shipped network's protocol.
    let protocol = if shipped.protocol.as_deref() == Some(Protocol::Paper.name()) {
        Protocol::Paper
    } else {
        Protocol::Deployment
    };
    run_train(&TrainOptions {
        data: args.out.join("set"),
        ablation: shipped.ablation.to_string(),
        config: "lite".into(),
        seed: args.seed,
        out: trained.clone(),
        epochs: args.epochs,
        patience: args.epochs,
        batch: 4,
        rates: "sim".into(),
        vision_lr: shipped.vision_lr,
        lr_scale: args.lr_scale,
        n_ticks: shipped.n_ticks,
        horizons,
        rate_hz: shipped.rate_hz,
        frame_size: shipped.frame_size,
        joint_names: Some(shipped.joint_names.clone()),
        trained_on: format!(
            "{}, fine-tuned on {:.0} s of the owner's recordings ({} listed x{}) mixed with {} \
             (learning rates x{}, {} epochs at most)",
            shipped.trained_on,
            fit_s,
            args.recordings.len(),
            args.owner_copies,
            data_name(&sim.dir),
            args.lr_scale,
            args.epochs
        ),
        protocol,
        per_horizon: false,
        trajectory: shipped.config.trajectory,
        device: args.device,
        checkpoint_dir: None,
        quiet: true,
        init: Some(args.model.clone()),
    })?;
    if shipped.calibration.is_some() {
        run_calibrate(&CalibrateOptions {
            model: trained.clone(),
            data: args.out.join("set"),
            split: "validation".into(),
            draws: 10,
            sample_seed: 12345,
            protocol,
            out: trained.clone(),
            half: true,
            form: FormChoice::Auto,
        })?;
    }
    let choice = args.choice.clone().unwrap_or_else(|| args.out.join("set"));
    let chosen = warnings(
        args,
        &trained,
        &choice,
        Split::Validation,
        shipped_pair,
        true,
    )?
    .chosen
    .map(|c| (c.trigger, c.release));
    let pair = chosen.unwrap_or_else(|| {
        tracing::warn!(
            "no threshold pair keeps the validation walks within budget: the shipped pair is kept"
        );
        shipped_pair
    });
    let card = FinetuneCard {
        shipped: measure(args, &args.model, shipped_pair)?,
        finetuned: measure(args, &trained, pair)?,
        owner_fit_s: fit_s,
        owner_held_s: held_s,
        owner_falls: falls,
        owner_copies: args.owner_copies,
        simulated_set: data_name(&sim.dir),
    };
    let json = args.out.join("card.json");
    std::fs::write(&json, serde_json::to_vec_pretty(&card)?)
        .doing(|| format!("writing {}", json.display()))?;
    let md = args.out.join("card.md");
    std::fs::write(&md, card.markdown()).doing(|| format!("writing {}", md.display()))?;
    Ok(card)
}

impl FinetuneCard {
    /// The card as Markdown.
    pub fn markdown(&self) -> String {
        let row = |what: &str, m: &Measured| {
            format!(
                "| {what} | {:.2} / {:.2} | {:.1}% ({:.2} of {:.2} min) | {:.1}% | {}/{} ({:.0}%) | {:.1}% |\n",
                m.trigger,
                m.release,
                100.0 * m.owner.held_share,
                m.owner.held_minutes,
                m.owner.non_falling_minutes,
                100.0 * m.owner.out_of_range_share,
                m.simulated.warned_by_0_5s,
                m.simulated.falling_episodes,
                100.0 * m.simulated.warned_by_0_5s_share,
                100.0 * m.simulated.held_share,
            )
        };
        let mut t = format!(
            "# Fine-tuned on the owner's recordings\n\n\
             Trained on {:.0} s of the owner's walks ({} falls) listed x{} beside the \
             training split of {}; measured on the {:.0} s held back (the end of each walk, \
             never used for a choice) and on the simulated test split.\n\n\
             | network | trigger / release | owner: time held | owner: windows out of range | simulated test: falls warned >= 0.5 s | simulated test: time held |\n\
             | --- | --- | --- | --- | --- | --- |\n",
            self.owner_fit_s, self.owner_falls, self.owner_copies, self.simulated_set, self.owner_held_s
        );
        t += &row("shipped", &self.shipped);
        t += &row("fine-tuned", &self.finetuned);
        t += "\nWhat this can show: whether the network stops holding the owner's robot on \
              walks like the ones it was fine-tuned on, and whether it still warns of the \
              simulated falls. What it cannot: its worth on the owner's falls (a held-back \
              walk has none), or on walks unlike these; a few tens of seconds of one walk \
              are one gait on one floor.\n";
        t
    }
}
