//! `fall-guard bench`: per-tick latency of the streaming forecast for each
//! ablation (one thread) and the whole-window forward for comparison, as
//! the daemon runs them. Results as a [`BenchReport`] (JSON with `--json`).
//! Training throughput is the lab's (`fall-guard-lab bench`).

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use crate::model::{
    cpu_device, Ablation, Convolutions, Emp, LoadedModel, ModelConfig, ModelError, ModelMeta,
    ProjectionWeights, StreamingForecaster,
};

/// Arguments of `fall-guard bench`.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// Model file whose configuration is benchmarked (every ablation of it;
    /// the file's own ablation with its weights, held at the file's
    /// precision); without one, the reference `lite` configuration (N=60,
    /// C=25, 64 px) with freshly initialised f32 weights.
    pub model: Option<PathBuf>,
    /// Configuration when no model is given: lite or paper.
    pub config: String,
    /// Write the results here as JSON.
    pub json: Option<PathBuf>,
    /// Ticks measured per ablation (after the window is full).
    pub ticks: usize,
    /// Measure only these ablations; all four when empty.
    pub ablations: Vec<Ablation>,
    /// How the classifier's input projection is held.
    pub projection: ProjectionWeights,
    /// How the streaming convolutions multiply.
    pub convolutions: Convolutions,
}

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// `--config` names no configuration.
    #[error("--config: {0}")]
    Config(String),
    /// Loading the model file or a forecast failed.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// The JSON report could not be written.
    #[error("writing {path}: {source}")]
    Write {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

/// Latency summary, milliseconds.
#[derive(Debug, Clone, Serialize)]
pub struct Latency {
    /// Median.
    pub median_ms: f64,
    /// 99th percentile.
    pub p99_ms: f64,
    /// Mean.
    pub mean_ms: f64,
    /// Maximum.
    pub max_ms: f64,
    /// Number of samples.
    pub samples: usize,
}

impl Latency {
    pub fn from_ms(mut v: Vec<f64>) -> Latency {
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() as f64 - 1.0) * p).round() as usize];
        Latency {
            median_ms: q(0.5),
            p99_ms: q(0.99),
            mean_ms: v.iter().sum::<f64>() / v.len() as f64,
            max_ms: *v.last().unwrap_or(&0.0),
            samples: v.len(),
        }
    }
}

/// Results of one ablation.
#[derive(Debug, Clone, Serialize)]
pub struct AblationBench {
    /// Which ablation.
    pub ablation: String,
    /// Streaming forecast per tick (push + forecast), wall time.
    pub streaming_per_tick: Latency,
    /// The same in CPU time of the inference thread: what the tick costs
    /// without the time other processes take the core away.
    pub streaming_cpu_per_tick: Latency,
    /// A tick while the window fills (push + vision slices prepared).
    pub fill_tick: Latency,
    /// The first forecast once the window is full (after a prepared fill).
    pub first_forecast_ms: f64,
    /// Whole-window forward (fused, no cache).
    pub whole_window: Latency,
    /// Vision slices computed per streaming tick, all layers (mean over
    /// the measured ticks; 0 without vision).
    pub vision_slices_per_tick: f64,
    /// Vision slice terms (one input slice through one time tap) computed
    /// per streaming tick: the vision's convolution work.
    pub vision_terms_per_tick: f64,
    /// Terms kept from an earlier tick and summed again, per tick.
    pub vision_terms_reused_per_tick: f64,
}

/// Everything `fall-guard bench` measures.
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    /// Backend the numbers were taken on.
    pub backend: String,
    /// Configuration name.
    pub config: String,
    /// `N`, `C`, `S`.
    pub n_ticks: usize,
    /// Joints.
    pub n_joints: usize,
    /// Frame side.
    pub frame_size: usize,
    /// Per ablation.
    pub ablations: Vec<AblationBench>,
    /// Threads used by inference.
    pub threads: usize,
    /// How the input projection was held (`as_file` or `int8`).
    pub projection: ProjectionWeights,
    /// How the streaming convolutions multiplied (`f32` or `int8`).
    pub convolutions: Convolutions,
}

/// The backend compiled in.
pub fn backend_name() -> &'static str {
    if cfg!(feature = "flex") {
        "flex"
    } else if cfg!(feature = "ndarray") {
        "ndarray"
    } else {
        "default"
    }
}

/// CPU time of the calling thread, ms.
fn thread_cpu_ms() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec, which `ts` is.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return 0.0;
    }
    ts.tv_sec as f64 * 1e3 + ts.tv_nsec as f64 * 1e-6
}

/// Deterministic pseudo-random values in [0, 1) (xorshift), the bench's
/// inputs (and the model tests').
pub fn noise(len: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E3779B97F4A7C15).wrapping_add(7);
    (0..len)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect()
}

/// Runs the benchmark.
pub fn run_bench(args: &BenchOptions) -> Result<BenchReport, BenchError> {
    let file_model = match &args.model {
        Some(p) => Some(
            LoadedModel::load(p)?
                .with_projection(args.projection)
                .with_convolutions(args.convolutions),
        ),
        None => None,
    };
    let cfg = match &file_model {
        Some(m) => m.meta.config.clone(),
        None => ModelConfig::named(&args.config, 60, 25, vec![15, 30, 45, 60], 64)
            .map_err(BenchError::Config)?,
    };
    let device = cpu_device();
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let (n, c, s, l) = (cfg.n_ticks, cfg.n_joints, cfg.frame_size, cfg.plan_len());
    let mut ablations = Vec::new();
    for ablation in Ablation::ALL {
        if !args.ablations.is_empty() && !args.ablations.contains(&ablation) {
            continue;
        }
        // The file's own network (its weights, at its precision) for its
        // ablation; freshly initialised f32 networks for the others.
        let model = match &file_model {
            Some(m) if m.meta.ablation == ablation => m.clone(),
            _ => {
                let meta = ModelMeta::new(cfg.clone(), ablation, 30.0, names.clone());
                let emp = Emp::new(&cfg, ablation, &device);
                LoadedModel::from_parts(meta, &emp, device.clone(), "bench".into())
                    .with_projection(args.projection)
                    .with_convolutions(args.convolutions)
            }
        };
        let mut stream = StreamingForecaster::new(&model);
        let total = n + args.ticks;
        let mut per_tick = Vec::with_capacity(args.ticks);
        let mut cpu_per_tick = Vec::with_capacity(args.ticks);
        let mut fill = Vec::with_capacity(n);
        let mut first_forecast_ms = 0.0;
        let mut steady_from = (0, 0, 0);
        for t in 0..total {
            let joints = noise(c, t as u64);
            let frame = noise(3 * s * s, 10_000 + t as u64);
            let plan = noise(l * c, 20_000 + t as u64);
            let start = Instant::now();
            let cpu_start = thread_cpu_ms();
            stream.push_parts(t as i64, &joints, Some(&frame), Some(&plan))?;
            if t + 1 < n {
                // As the daemon does while its ring fills.
                stream.prepare()?;
                fill.push(start.elapsed().as_secs_f64() * 1e3);
                continue;
            }
            let p = stream.forecast()?;
            std::hint::black_box(p);
            let ms = start.elapsed().as_secs_f64() * 1e3;
            if t + 1 == n {
                first_forecast_ms = ms;
                steady_from = (
                    stream.slices_computed(),
                    stream.terms_computed(),
                    stream.terms_reused(),
                );
            } else {
                per_tick.push(ms);
                cpu_per_tick.push(thread_cpu_ms() - cpu_start);
            }
        }
        let joints = noise(n * c, 1);
        let plan = noise(l * c, 2);
        let frames = noise(3 * n * s * s, 3);
        let reps = (args.ticks / 10).max(5);
        let mut whole = Vec::with_capacity(reps);
        for _ in 0..reps {
            let start = Instant::now();
            std::hint::black_box(model.forecast_arrays(&joints, &plan, &frames)?);
            whole.push(start.elapsed().as_secs_f64() * 1e3);
        }
        let b = AblationBench {
            ablation: ablation.to_string(),
            streaming_per_tick: Latency::from_ms(per_tick),
            streaming_cpu_per_tick: Latency::from_ms(cpu_per_tick),
            fill_tick: Latency::from_ms(fill),
            first_forecast_ms,
            whole_window: Latency::from_ms(whole),
            vision_slices_per_tick: (stream.slices_computed() - steady_from.0) as f64
                / args.ticks.max(1) as f64,
            vision_terms_per_tick: (stream.terms_computed() - steady_from.1) as f64
                / args.ticks.max(1) as f64,
            vision_terms_reused_per_tick: (stream.terms_reused() - steady_from.2) as f64
                / args.ticks.max(1) as f64,
        };
        ablations.push(b);
    }
    let report = BenchReport {
        backend: backend_name().into(),
        config: cfg.name.clone(),
        n_ticks: n,
        n_joints: c,
        frame_size: s,
        ablations,
        threads: 1,
        projection: args.projection,
        convolutions: args.convolutions,
    };
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report).expect("the report serialises");
        std::fs::write(path, text).map_err(|source| BenchError::Write {
            path: path.display().to_string(),
            source,
        })?;
    }
    Ok(report)
}

impl AblationBench {
    /// One line of the figures, for the command's output.
    pub fn summary(&self) -> String {
        format!(
            "{:>3}: per tick median {:.2} ms p99 {:.2} ms (thread CPU median {:.2} p99 {:.2}) | \
             fill tick median {:.2} ms | first forecast {:.2} ms | whole window median {:.2} ms | \
             vision slices {:.1} terms {:.1} (and {:.1} kept) a tick",
            self.ablation,
            self.streaming_per_tick.median_ms,
            self.streaming_per_tick.p99_ms,
            self.streaming_cpu_per_tick.median_ms,
            self.streaming_cpu_per_tick.p99_ms,
            self.fill_tick.median_ms,
            self.first_forecast_ms,
            self.whole_window.median_ms,
            self.vision_slices_per_tick,
            self.vision_terms_per_tick,
            self.vision_terms_reused_per_tick
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The reference benchmark, run by hand:
    /// `cargo test -p fall-guard-runtime --lib reference_benchmark -- --ignored --nocapture`
    /// (`FALL_GUARD_BENCH_JSON=path` writes the JSON report).
    #[test]
    #[ignore = "benchmark, not a test: run by hand"]
    fn reference_benchmark() {
        let args = BenchOptions {
            model: None,
            config: std::env::var("FALL_GUARD_BENCH_CONFIG").unwrap_or_else(|_| "lite".into()),
            json: std::env::var("FALL_GUARD_BENCH_JSON")
                .ok()
                .map(PathBuf::from),
            ticks: 300,
            ablations: Vec::new(),
            projection: ProjectionWeights::AsFile,
            convolutions: Convolutions::F32,
        };
        let report = run_bench(&args).unwrap();
        println!("{}", serde_json::to_string_pretty(&report).unwrap());
    }

    /// An unknown configuration is refused, naming the flag.
    #[test]
    fn an_unknown_configuration_is_refused() {
        let args = BenchOptions {
            model: None,
            config: "nonesuch".into(),
            json: None,
            ticks: 3,
            ablations: vec![Ablation::P],
            projection: ProjectionWeights::AsFile,
            convolutions: Convolutions::F32,
        };
        let e = run_bench(&args).expect_err("unknown configuration refused");
        assert!(e.to_string().starts_with("--config"), "{e}");
    }
}
