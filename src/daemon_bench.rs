//! `fall-guard bench-daemon`: the whole daemon pipeline replaying a
//! recording at maximum speed, over and over (each pass shifted in time so
//! the tick grid runs on), for a given wall time. Measures the
//! sensor-to-publish latency of every forecast (from the moment the tick's
//! newest sample entered the daemon to the moment a publisher had the
//! forecast: the ROS 2 publisher when `[ros].enabled`, else a bus subscriber
//! standing in for it), inference latency, and resident memory (RSS from
//! `/proc/self/statm`) once a second, to show it does not grow. It runs on
//! the daemon's one lifecycle (`service::lifecycle`), as `replay` does:
//! SIGINT / SIGTERM end the run early, with a report.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::forecast::percentiles_ms;
use crate::service::{load_config, Inputs, Running, ServiceError, What};
use crate::sources::replay::{replay_samples, shifted};

/// `fall-guard bench-daemon`.
#[derive(Debug, Clone)]
pub struct BenchDaemonOptions {
    /// Config file; without it, the embedded config/replay.toml.
    pub config: Option<PathBuf>,
    /// Recording to loop; without it, `[replay].recording`.
    pub recording: Option<PathBuf>,
    /// Wall time to run, seconds.
    pub duration_s: f64,
    /// Also write the report as JSON here.
    pub json: Option<PathBuf>,
    /// Replay at this many times real time instead of maximum speed: the
    /// sensor-to-publish latency as on the robot (at maximum speed a sample
    /// also waits for the previous tick's inference).
    pub speed: Option<f64>,
}

/// What the bench measured.
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub recording: String,
    pub wall_s: f64,
    pub passes: u64,
    pub ticks: u64,
    pub forecasts: u64,
    pub overruns: u64,
    pub ticks_per_s: f64,
    pub publish_latency_p50_ms: f64,
    pub publish_latency_p99_ms: f64,
    pub publish_latency_max_ms: f64,
    /// Worst per-second inference p50 / p99 over the run.
    pub inference_p50_ms: f64,
    pub inference_p99_ms: f64,
    pub rss_first_mb: f64,
    pub rss_after_10s_mb: f64,
    pub rss_max_mb: f64,
    pub rss_last_mb: f64,
    pub published_via: &'static str,
    /// `max` or the replay speed factor.
    pub pacing: String,
}

/// Resident set size of this process, MiB (Linux).
pub fn rss_mb() -> f64 {
    let page = 4096.0;
    std::fs::read_to_string("/proc/self/statm")
        .ok()
        .and_then(|s| {
            s.split_whitespace()
                .nth(1)
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map_or(0.0, |pages| pages * page / (1024.0 * 1024.0))
}

pub async fn run(args: BenchDaemonOptions) -> Result<BenchReport, ServiceError> {
    let mut config = load_config(args.config.as_deref())?;
    config.output.print_forecasts = false;
    let recording = config.replay_recording(args.recording.as_deref())?;
    // Maximum speed unless `--speed` says otherwise.
    let pacing = config.replay_pacing(args.speed, args.speed.is_none())?;
    let ros = config.ros.enabled;
    let mut daemon = Running::start(config, What::Replay(recording.clone()))?;
    let mut shutdown = daemon.shutdown();
    let bus = match &daemon.forecasting {
        Some(f) => f.bus.clone(),
        None => unreachable!("a replay forecasts"),
    };
    // Without ROS, a subscriber stands in for the publisher.
    let mut stand_in = (!ros).then(|| bus.subscribe());
    let mut stop = daemon.shutdown();
    let stand_in_task = tokio::spawn(async move {
        let Some(sub) = stand_in.as_mut() else { return };
        loop {
            tokio::select! {
                r = sub.forecasts.recv() => match r {
                    Ok(f) => sub.published(&f),
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                    Err(_) => return,
                },
                () = stop.recv() => return,
            }
        }
    });
    daemon.join_at_stop(stand_in_task);
    let mut diagnostics = bus.subscribe().diagnostics;
    let started = Instant::now();
    let rss_first = rss_mb();
    let rss = Arc::new(std::sync::Mutex::new(Vec::<(f64, f64)>::new()));
    let rss_log = Arc::clone(&rss);
    let mut rss_stop = daemon.shutdown();
    let rss_task = tokio::spawn(async move {
        let mut every = tokio::time::interval(Duration::from_secs(1));
        loop {
            tokio::select! {
                _ = every.tick() => {
                    if let Ok(mut v) = rss_log.lock() { v.push((started.elapsed().as_secs_f64(), rss_mb())); }
                }
                () = rss_stop.recv() => return,
            }
        }
    });
    daemon.join_at_stop(rss_task);
    let (
        Some(forecasting),
        Inputs::Replay {
            recording: replayed,
            gates,
        },
    ) = (daemon.forecasting.as_mut(), &daemon.inputs)
    else {
        unreachable!("a replay forecasts from a recording")
    };
    let span =
        replayed.end_ns - replayed.start_ns + (1e9 / forecasting.models.spec().rate_hz) as i64;
    let mut passes = 0u64;
    let mut latencies: Vec<u32> = Vec::new();
    let (mut inf_p50, mut inf_p99) = (0.0f64, 0.0f64);
    while started.elapsed().as_secs_f64() < args.duration_s && !shutdown.is_shutdown() {
        let offset = passes as i64 * span;
        let samples = replayed.samples.iter().map(|s| shifted(s, offset));
        replay_samples(
            &mut forecasting.tick_loop,
            samples,
            replayed.end_ns + offset,
            pacing,
            gates,
            &mut shutdown,
        )
        .await;
        passes += 1;
        latencies.extend(bus.latency().take_us());
        loop {
            use tokio::sync::broadcast::error::TryRecvError;
            match diagnostics.try_recv() {
                Ok(d) => {
                    inf_p50 = inf_p50.max(d.model.inference_p50_ms.unwrap_or(0.0));
                    inf_p99 = inf_p99.max(d.model.inference_p99_ms.unwrap_or(0.0));
                }
                // Snapshots older than the channel holds are gone: read on.
                Err(TryRecvError::Lagged(_)) => {}
                Err(_) => break,
            }
        }
    }
    let wall_s = started.elapsed().as_secs_f64();
    let counters = daemon.stop().await.counters;
    latencies.extend(bus.latency().take_us());
    let max = latencies.iter().copied().max().unwrap_or(0);
    let (p50, p99) = percentiles_ms(&mut latencies).unwrap_or((0.0, 0.0));
    let rss = rss.lock().map(|v| v.clone()).unwrap_or_default();
    let after_10 = rss
        .iter()
        .find(|(t, _)| *t >= 10.0)
        .map_or(rss_first, |x| x.1);
    let report = BenchReport {
        recording: recording.display().to_string(),
        wall_s,
        passes,
        ticks: counters.ticks,
        forecasts: counters.dispatched,
        overruns: counters.overruns,
        ticks_per_s: counters.ticks as f64 / wall_s,
        publish_latency_p50_ms: p50,
        publish_latency_p99_ms: p99,
        publish_latency_max_ms: f64::from(max) / 1000.0,
        inference_p50_ms: inf_p50,
        inference_p99_ms: inf_p99,
        rss_first_mb: rss_first,
        rss_after_10s_mb: after_10,
        rss_max_mb: rss.iter().map(|x| x.1).fold(rss_first, f64::max),
        rss_last_mb: rss.last().map_or(rss_first, |x| x.1),
        published_via: if ros { "ros2" } else { "bus subscriber" },
        pacing: args
            .speed
            .map_or_else(|| "max".to_string(), |x| format!("{x}x real time")),
    };
    let text = serde_json::to_string_pretty(&report).unwrap_or_default();
    println!("{text}");
    if let Some(path) = &args.json {
        std::fs::write(path, &text)
            .map_err(|e| ServiceError::Usage(format!("{}: {e}", path.display())))?;
    }
    Ok(report)
}
