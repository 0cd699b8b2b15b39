//! `fall-guard bench-daemon`: the whole daemon pipeline replaying a
//! recording at maximum speed, over and over (each pass shifted in time so
//! the tick grid runs on), for a given wall time. Measures the
//! sensor-to-publish latency of every forecast (from the moment the tick's
//! newest sample entered the daemon to the moment a publisher had the
//! forecast: the ROS 2 publisher when `[ros].enabled`, else a bus subscriber
//! standing in for it), inference latency, and resident memory (RSS from
//! `/proc/self/statm`) once a second, to show it does not grow. It runs on
//! the daemon's one lifecycle (`daemon::lifecycle`), as `replay` does:
//! SIGINT / SIGTERM end the run early, with a report.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::clock::ReplayClock;
use crate::daemon::replay::replay_samples;
use crate::daemon::{load_config, Replay, Running, ServiceError};
use crate::sources::replay::shifted;

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

/// `path` relative to the current directory when it lies there (a report
/// that names no machine), else as given.
fn relative_to_here(path: &std::path::Path) -> String {
    let canonical = |p: &std::path::Path| std::fs::canonicalize(p).ok();
    match (
        canonical(path),
        std::env::current_dir().ok().as_deref().and_then(canonical),
    ) {
        (Some(p), Some(here)) => match p.strip_prefix(&here) {
            Ok(rel) if !rel.as_os_str().is_empty() => rel.display().to_string(),
            _ => path.display().to_string(),
        },
        _ => path.display().to_string(),
    }
}

impl BenchReport {
    /// The report as pretty-printed JSON (what `--json` writes and the
    /// command prints).
    pub fn json(&self) -> String {
        serde_json::to_string_pretty(self).expect("the report serialises")
    }
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
    let mut daemon = Running::<Replay>::start(config, &recording)?;
    let mut shutdown = daemon.shutdown();
    let bus = daemon.command.forecasting.bus.clone();
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
    // Constant memory over any duration (a soak measures the daemon's
    // growth, not the bench's): four figures, not a log.
    let rss = Arc::new(std::sync::Mutex::new(RssFigures::new(rss_first)));
    let rss_log = Arc::clone(&rss);
    let mut rss_stop = daemon.shutdown();
    let rss_task = tokio::spawn(async move {
        let mut every = tokio::time::interval(Duration::from_secs(1));
        loop {
            tokio::select! {
                _ = every.tick() => {
                    if let Ok(mut r) = rss_log.lock() { r.sample(started.elapsed().as_secs_f64(), rss_mb()); }
                }
                () = rss_stop.recv() => return,
            }
        }
    });
    daemon.join_at_stop(rss_task);
    let Replay {
        forecasting,
        recording: replayed,
    } = &mut daemon.command;
    let span =
        replayed.end_ns - replayed.start_ns + (1e9 / forecasting.models.spec().rate_hz) as i64;
    let mut passes = 0u64;
    // One clock over every pass: each pass continues the previous one in
    // recorded time, so its first tick comes one tick period after the
    // previous pass's last, not at once (two ticks handed over together,
    // one skipped as an overrun at every pass boundary).
    let mut clock = ReplayClock::new();
    let mut latencies = LatencyHistogram::new();
    let (mut inf_p50, mut inf_p99) = (0.0f64, 0.0f64);
    while started.elapsed().as_secs_f64() < args.duration_s && !shutdown.is_shutdown() {
        let offset = passes as i64 * span;
        let samples = replayed.samples.iter().map(|s| shifted(s, offset));
        replay_samples(
            &mut forecasting.tick_loop,
            samples,
            replayed.end_ns + offset,
            pacing,
            &daemon.streams,
            &mut shutdown,
            &mut clock,
        )
        .await;
        passes += 1;
        bus.latency()
            .take_us()
            .into_iter()
            .for_each(|us| latencies.add(us));
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
    bus.latency()
        .take_us()
        .into_iter()
        .for_each(|us| latencies.add(us));
    let max = latencies.max_us;
    let p50 = latencies.quantile_ms(0.50).unwrap_or(0.0);
    let p99 = latencies.quantile_ms(0.99).unwrap_or(0.0);
    let rss = rss
        .lock()
        .map(|r| *r)
        .unwrap_or_else(|_| RssFigures::new(rss_first));
    let report = BenchReport {
        recording: relative_to_here(&recording),
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
        rss_first_mb: rss.first,
        rss_after_10s_mb: rss.after_10s,
        rss_max_mb: rss.max,
        rss_last_mb: rss.last,
        published_via: if ros { "ros2" } else { "bus subscriber" },
        pacing: args
            .speed
            .map_or_else(|| "max".to_string(), |x| format!("{x}x real time")),
    };
    if let Some(path) = &args.json {
        std::fs::write(path, report.json())
            .map_err(|e| ServiceError::Usage(format!("{}: {e}", path.display())))?;
    }
    Ok(report)
}

/// Resident memory over a run, in constant space: at start, the first
/// sample 10 s in or later, the largest, the last (MB).
#[derive(Debug, Clone, Copy, PartialEq)]
struct RssFigures {
    first: f64,
    after_10s: f64,
    max: f64,
    last: f64,
    after_10s_seen: bool,
}

impl RssFigures {
    fn new(first: f64) -> RssFigures {
        RssFigures {
            first,
            after_10s: first,
            max: first,
            last: first,
            after_10s_seen: false,
        }
    }

    fn sample(&mut self, elapsed_s: f64, mb: f64) {
        if !self.after_10s_seen && elapsed_s >= 10.0 {
            self.after_10s = mb;
            self.after_10s_seen = true;
        }
        self.max = self.max.max(mb);
        self.last = mb;
    }
}

/// Sensor-to-publish latencies of a whole run in constant memory (a Vec of
/// every latency grew by 4 bytes a tick: ~2.4 MB an hour at 170 ticks/s,
/// which a soak would have counted as the daemon's): counts per 10 µs up
/// to 100 ms, one bucket above, and the exact maximum.
struct LatencyHistogram {
    counts: Vec<u64>,
    n: u64,
    max_us: u32,
}

const BUCKET_US: u32 = 10;
const BUCKETS: usize = 10_000;

impl LatencyHistogram {
    fn new() -> LatencyHistogram {
        LatencyHistogram {
            counts: vec![0; BUCKETS + 1],
            n: 0,
            max_us: 0,
        }
    }

    fn add(&mut self, us: u32) {
        let i = ((us / BUCKET_US) as usize).min(BUCKETS);
        self.counts[i] += 1;
        self.n += 1;
        self.max_us = self.max_us.max(us);
    }

    /// Nearest-rank quantile in ms: the upper edge of the 10 µs bucket it
    /// falls in (never above the maximum); `None` without a sample.
    fn quantile_ms(&self, q: f64) -> Option<f64> {
        if self.n == 0 {
            return None;
        }
        let rank = ((q * self.n as f64).ceil() as u64).clamp(1, self.n);
        let mut seen = 0;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                let edge = if i == BUCKETS {
                    self.max_us
                } else {
                    ((i as u32 + 1) * BUCKET_US).min(self.max_us)
                };
                return Some(f64::from(edge) / 1000.0);
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::inference::percentiles_ms;

    #[test]
    fn histogram_quantiles_are_within_one_bucket_of_the_exact_ones() {
        let mut x: u64 = 0x2545_f491_4f6c_dd1d;
        let mut exact = Vec::new();
        let mut h = LatencyHistogram::new();
        for _ in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Mostly 2-30 ms, a few up to 300 ms (beyond the last bucket).
            let us = if x.is_multiple_of(100) {
                (x % 300_000) as u32
            } else {
                2_000 + (x % 28_000) as u32
            };
            exact.push(us);
            h.add(us);
        }
        let (p50, p99) = percentiles_ms(&mut exact).expect("samples");
        let bucket_ms = f64::from(BUCKET_US) / 1000.0;
        let hp50 = h.quantile_ms(0.50).expect("p50");
        let hp99 = h.quantile_ms(0.99).expect("p99");
        assert!(hp50 >= p50 && hp50 - p50 <= bucket_ms, "{hp50} vs {p50}");
        assert!(hp99 >= p99 || p99 * 1000.0 >= 100_000.0, "{hp99} vs {p99}");
        assert!(hp99 - p99 <= bucket_ms || p99 * 1000.0 >= 100_000.0);
        assert_eq!(h.max_us, *exact.iter().max().expect("max"));
        assert_eq!(LatencyHistogram::new().quantile_ms(0.5), None);
    }

    #[test]
    fn rss_figures_keep_start_ten_seconds_max_and_last() {
        let mut r = RssFigures::new(40.0);
        r.sample(1.0, 45.0);
        r.sample(10.5, 48.0);
        r.sample(20.0, 50.0);
        r.sample(30.0, 49.0);
        assert_eq!(
            (r.first, r.after_10s, r.max, r.last),
            (40.0, 48.0, 50.0, 49.0)
        );
    }
}
