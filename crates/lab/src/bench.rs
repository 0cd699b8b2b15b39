//! `fall-guard-lab bench`: training throughput of the network (EMP, batch
//! 4, Adam) on the CPU or a GPU. Results as JSON. The per-tick inference
//! latencies are the robot binary's (`fall-guard bench`,
//! `fall_guard_runtime::model::bench`).

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use super::adam::FusedAdam;
use super::device::TrainDevice;
use super::fit::{bce_with_logits, keep_freed_memory, LabeledWindow};
use crate::error::{refused, CommandResult, Doing};
use fall_guard_runtime::model::bench::{backend_name, noise};
use fall_guard_runtime::model::file::build_input;
use fall_guard_runtime::model::{Ablation, Emp, ModelConfig, ModelMeta};

/// Arguments of `fall-guard-lab bench`.
#[derive(Debug, Clone)]
pub struct TrainBenchOptions {
    /// Training steps measured (batch 4, EMP), after one unmeasured step.
    pub train_steps: usize,
    /// Device of the training: cpu, cuda, cuda:N or wgpu (see `train --device`).
    pub device: TrainDevice,
    /// Network configuration at N=60, C=25, 64 px: lite or paper.
    pub config: String,
    /// Write the results here as JSON.
    pub json: Option<PathBuf>,
}

/// What `fall-guard-lab bench` measures.
#[derive(Debug, Clone, Serialize)]
pub struct TrainBenchReport {
    /// Backend compiled in for the CPU.
    pub backend: String,
    /// Configuration name.
    pub config: String,
    /// `N`.
    pub n_ticks: usize,
    /// Joints.
    pub n_joints: usize,
    /// Frame side.
    pub frame_size: usize,
    /// Training samples per second (EMP, batch 4).
    pub train_samples_per_s: f64,
    /// Device of the training measurement.
    pub train_device: String,
}

/// Runs the training benchmark.
pub fn run_train_bench(args: &TrainBenchOptions) -> CommandResult<TrainBenchReport> {
    if args.train_steps == 0 {
        return Err(refused("--train-steps: at least 1 step to measure"));
    }
    let cfg =
        ModelConfig::named(&args.config, 60, 25, vec![15, 30, 45, 60], 64).map_err(refused)?;
    let report = TrainBenchReport {
        backend: backend_name().into(),
        config: cfg.name.clone(),
        n_ticks: cfg.n_ticks,
        n_joints: cfg.n_joints,
        frame_size: cfg.frame_size,
        train_samples_per_s: train_throughput(&cfg, args.train_steps, args.device)?,
        train_device: args.device.to_string(),
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
    use fall_guard_runtime::model::cpu_device;

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
    /// software `llvmpipe` included: `cargo test -p fall-guard-lab
    /// --features wgpu --lib wgpu_trains`.
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
}
