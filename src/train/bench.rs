//! `fall-guard bench`: per-tick latency of the streaming forecast for each
//! ablation (one thread), the whole-window forward for comparison, and
//! training throughput. Results as JSON.

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use super::adam::FusedAdam;
use super::device::TrainDevice;
use super::fit::{bce_with_logits, keep_freed_memory, LabeledWindow};
use crate::model::file::build_input;
use crate::model::{
    cpu_device, Ablation, Emp, LoadedModel, ModelConfig, ModelMeta, ProjectionWeights,
    StreamingForecaster,
};
use crate::train::error::{refused, CommandResult, Doing};

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
    /// Training steps measured (batch 4, EMP); 0 skips.
    pub train_steps: usize,
    /// Measure only these ablations (repeatable); all four when absent.
    pub ablations: Vec<Ablation>,
    /// Measure training throughput only (skip the inference latencies).
    pub train_only: bool,
    /// Device of the training part: cpu, cuda, cuda:N or wgpu (see `train --device`).
    pub device: TrainDevice,
    /// How the classifier's input projection is held (inference part).
    pub projection: ProjectionWeights,
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
    fn from_ms(mut v: Vec<f64>) -> Latency {
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
}

/// Everything `bench` measures.
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
    /// Training samples per second (EMP, batch 4), if measured.
    pub train_samples_per_s: Option<f64>,
    /// Device of the training measurement.
    pub train_device: String,
    /// Threads used by inference.
    pub threads: usize,
    /// How the input projection was held (`as_file` or `int8`).
    pub projection: ProjectionWeights,
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
pub fn run_bench(args: &BenchOptions) -> CommandResult<BenchReport> {
    let file_model = match &args.model {
        Some(p) => Some(LoadedModel::load(p)?.with_projection(args.projection)),
        None => None,
    };
    let cfg = match &file_model {
        Some(m) => m.meta.config.clone(),
        None => {
            ModelConfig::named(&args.config, 60, 25, vec![15, 30, 45, 60], 64).map_err(refused)?
        }
    };
    let device = cpu_device();
    if !args.train_only {
        eprintln!("input projection held {}", args.projection.name());
    }
    let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
    let (n, c, s, l) = (cfg.n_ticks, cfg.n_joints, cfg.frame_size, cfg.plan_len());
    let mut ablations = Vec::new();
    for ablation in Ablation::ALL {
        if args.train_only || !args.ablations.is_empty() && !args.ablations.contains(&ablation) {
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
            }
        };
        let mut stream = StreamingForecaster::new(&model);
        let total = n + args.ticks;
        let mut per_tick = Vec::with_capacity(args.ticks);
        let mut cpu_per_tick = Vec::with_capacity(args.ticks);
        let mut fill = Vec::with_capacity(n);
        let mut first_forecast_ms = 0.0;
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
        };
        eprintln!(
            "{:>3}: per tick median {:.2} ms p99 {:.2} ms (thread CPU median {:.2} p99 {:.2}) | \
             fill tick median {:.2} ms | first forecast {:.2} ms | whole window median {:.2} ms",
            b.ablation,
            b.streaming_per_tick.median_ms,
            b.streaming_per_tick.p99_ms,
            b.streaming_cpu_per_tick.median_ms,
            b.streaming_cpu_per_tick.p99_ms,
            b.fill_tick.median_ms,
            b.first_forecast_ms,
            b.whole_window.median_ms
        );
        ablations.push(b);
    }
    let train_samples_per_s = if args.train_steps > 0 {
        Some(train_throughput(&cfg, args.train_steps, args.device)?)
    } else {
        None
    };
    if let Some(t) = train_samples_per_s {
        eprintln!("training (EMP, batch 4, {}): {t:.1} samples/s", args.device);
    }
    let report = BenchReport {
        backend: backend_name().into(),
        config: cfg.name.clone(),
        n_ticks: n,
        n_joints: c,
        frame_size: s,
        ablations,
        train_samples_per_s,
        train_device: args.device.to_string(),
        threads: 1,
        projection: args.projection,
    };
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_string_pretty(&report)?)
            .doing(|| format!("writing {}", path.display()))?;
    }
    Ok(report)
}

fn train_throughput(cfg: &ModelConfig, steps: usize, on: TrainDevice) -> CommandResult<f64> {
    keep_freed_memory();
    let device = on.device()?.autodiff();
    let mut run = TrainRun::new(cfg, Emp::new(cfg, Ablation::EMP, &device), device);
    let mut elapsed = 0.0;
    for step in 0..steps + 1 {
        let start = Instant::now();
        run.step().doing(|| format!("training step on {on}"))?;
        if step > 0 {
            elapsed += start.elapsed().as_secs_f64();
        }
    }
    Ok(4.0 * steps as f64 / elapsed)
}

/// EMP training steps (batch 4, Adam, learning rate 1e-4) on one fixed
/// batch of noise: what the training benchmark times, and what the GPU
/// backends are checked against the CPU with.
struct TrainRun {
    meta: ModelMeta,
    model: Emp,
    opt: burn::optim::ModuleOptimizer,
    batch: Vec<LabeledWindow>,
    device: burn::prelude::Device,
}

impl TrainRun {
    fn new(cfg: &ModelConfig, model: Emp, device: burn::prelude::Device) -> TrainRun {
        let names: Vec<String> = (0..cfg.n_joints).map(|i| format!("j{i}")).collect();
        let (n, c, s, l, k) = (
            cfg.n_ticks,
            cfg.n_joints,
            cfg.frame_size,
            cfg.plan_len(),
            cfg.k(),
        );
        let batch = (0..4)
            .map(|i| LabeledWindow {
                joints: noise(n * c, 40 + i),
                plan: noise(l * c, 50 + i),
                frames: noise(3 * n * s * s, 60 + i),
                labels: (0..k).map(|h| ((h as u64 + i) % 2) as f32).collect(),
                episode: i as usize,
                scored_horizon: None,
            })
            .collect();
        TrainRun {
            meta: ModelMeta::new(cfg.clone(), Ablation::EMP, 30.0, names),
            model,
            opt: FusedAdam::new(None).init(),
            batch,
            device,
        }
    }

    /// One step, once the device has done it; its loss (before the update),
    /// still on the device: reading it is a transfer the benchmark does not
    /// time.
    fn step(&mut self) -> CommandResult<burn::prelude::Tensor<1>> {
        use burn::optim::GradientsParams;
        let device = &self.device;
        let j: Vec<&[f32]> = self.batch.iter().map(|w| w.joints.as_slice()).collect();
        let p: Vec<&[f32]> = self.batch.iter().map(|w| w.plan.as_slice()).collect();
        let f: Vec<&[f32]> = self.batch.iter().map(|w| w.frames.as_slice()).collect();
        let input = build_input(&self.meta, &j, &p, &f, device)?;
        let k = self.meta.config.k();
        let labels: Vec<f32> = self
            .batch
            .iter()
            .flat_map(|w| w.labels.iter().copied())
            .collect();
        let labels = burn::prelude::Tensor::<2>::from_data(
            burn::prelude::TensorData::new(labels, [self.batch.len(), k]),
            device,
        );
        let loss = bce_with_logits(self.model.forward(input), labels);
        let value = loss.clone().detach();
        let grads = GradientsParams::from_grads(loss.backward(), &self.model);
        self.model = self.opt.step(1e-4, self.model.clone(), grads);
        // A GPU queues its work: wait for it before reading the clock.
        device
            .sync()
            .map_err(|e| refused(format!("waiting for the device: {e:?}")))?;
        Ok(value)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The benchmark's training steps run and move the network: finite
    /// losses, each step's after the previous update.
    #[test]
    fn train_run_steps_update_the_network() {
        let cfg = ModelConfig::lite(12, 5, vec![3, 6, 9, 12], 32);
        let cpu = cpu_device().autodiff();
        let mut run = TrainRun::new(&cfg, Emp::new(&cfg, Ablation::EMP, &cpu), cpu);
        let losses: Vec<f32> = (0..3)
            .map(|_| run.step().unwrap().into_scalar::<f32>())
            .collect();
        assert!(
            losses.iter().all(|l| l.is_finite() && *l > 0.0),
            "{losses:?}"
        );
        assert!(losses.windows(2).all(|w| w[0] != w[1]), "{losses:?}");
    }

    /// The wgpu backend trains as the CPU does: the same network (dropout
    /// off) and batch, three steps on each, the same losses (the first the
    /// forward alone, the next two after the gradients and Adam's update on
    /// that device).
    /// Built and run only with the feature, on any adapter, Mesa's
    /// software `llvmpipe` included: `cargo test --features wgpu --lib
    /// wgpu_trains`.
    #[cfg(feature = "wgpu")]
    #[test]
    fn wgpu_trains_as_the_cpu_does() {
        use burn::module::Module;
        // No dropout: its masks come from each device's own generator.
        let cfg = ModelConfig {
            dropout: 0.0,
            ..ModelConfig::lite(12, 5, vec![3, 6, 9, 12], 32)
        };
        let cpu = cpu_device().autodiff();
        let gpu = TrainDevice::Wgpu.device().unwrap().autodiff();
        let model = Emp::new(&cfg, Ablation::EMP, &cpu);
        let mut on_cpu = TrainRun::new(&cfg, model.clone(), cpu);
        let mut on_gpu = TrainRun::new(&cfg, model.fork(&gpu), gpu);
        for step in 0..3 {
            let loss = |run: &mut TrainRun| run.step().unwrap().into_scalar::<f32>();
            let (a, b) = (loss(&mut on_cpu), loss(&mut on_gpu));
            eprintln!("step {step}: loss on cpu {a}, on wgpu {b}");
            assert!(
                (a - b).abs() < 1e-4 * a.abs().max(1.0),
                "step {step}: cpu {a} vs wgpu {b}"
            );
        }
    }

    /// The reference benchmark, run by hand:
    /// `cargo test --lib reference_benchmark -- --ignored --nocapture`
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
            train_steps: 5,
            ablations: Vec::new(),
            train_only: false,
            device: TrainDevice::Cpu,
            projection: ProjectionWeights::AsFile,
        };
        let report = run_bench(&args).unwrap();
        println!("{}", serde_json::to_string_pretty(&report).unwrap());
    }
}
