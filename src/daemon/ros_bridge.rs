//! The daemon's side of the ROS 2 seam: one node ([`RosBridge`]) whose
//! publishers (`outputs::ros`) are fed from the [`OutputBus`], and whose
//! subscriptions (`sources::ros`) are turned into model-form samples and
//! offered to the live [`StreamFeed`]s (the input boundary,
//! `sources/input.rs`), converted once per message with the same functions
//! a replay uses (`window::joints_from_msg`, `frame_from_msg`,
//! `Plan::from_msg`); a conversion error is a typed rejection there.
//!
//! The node honours `ROS_DOMAIN_ID` and `ROS_AUTOMATIC_DISCOVERY_RANGE`
//! (`ROS_LOCALHOST_ONLY`), unless `[ros].domain_id` / `[ros].localhost_only`
//! set them in the config, and the DDS Security variables
//! (`ROS_SECURITY_*`, `ros::security`) with the enclave `[ros].enclave`.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use tokio::sync::broadcast::error::RecvError;
use tokio::task::JoinHandle;

use crate::config::Config;
use crate::daemon::LiveStreams;
use crate::daemon::ServiceError;
use crate::msgs::{CompressedImage, Header, JointState};
use crate::outputs::ros::{ros_time, OutputTopics, RosOutputs};
use crate::outputs::{publish_imminent_change, published_probabilities, ForecastOutput, OutputBus};
use crate::pipeline::forecast::ModelSet;
use crate::pipeline::window::WindowSpec;
use crate::ros::{RosError, RosNode, RosSettings, DISCOVERY_RANGE_ENV, DOMAIN_ID_ENV};
use crate::shutdown::Shutdown;
use crate::sources::ros::{InputErrors, InputMessage, InputTopics, Latest, RosInputs};
use crate::streams::input::{InputLimits, Rejection, StreamValue};
use crate::streams::sample::{frame_from_msg, joints_from_msg, Plan, Sample};
use crate::streams::{PerStream, Stamped, StreamFeed, StreamKind, StreamTap};

impl From<RosError> for ServiceError {
    fn from(e: RosError) -> Self {
        ServiceError::Source(format!("ROS 2: {e}"))
    }
}

/// The node settings: the environment, overridden by `[ros]`.
pub fn settings(config: &Config) -> Result<RosSettings, RosError> {
    let ros = &config.ros;
    RosSettings::from_vars_in_enclave(&ros.namespace, &ros.node_name, &ros.enclave, |var| {
        if var == DOMAIN_ID_ENV {
            if let Some(id) = ros.domain_id {
                return Some(id.to_string());
            }
        }
        if var == DISCOVERY_RANGE_ENV {
            match ros.localhost_only {
                Some(true) => return Some("LOCALHOST".into()),
                Some(false) => return Some("SUBNET".into()),
                None => {}
            }
        }
        std::env::var(var).ok()
    })
}

/// The daemon's ROS 2 node; drop it after the tasks it started have ended.
pub struct RosBridge {
    node: RosNode,
    inputs: Option<RosInputs>,
}

impl RosBridge {
    /// Start the node (DDS participant, spinner).
    pub fn start(config: &Config) -> Result<RosBridge, ServiceError> {
        let settings = settings(config)?;
        Ok(RosBridge {
            node: RosNode::start(&settings)?,
            inputs: None,
        })
    }

    /// Leave the DDS domain: subscriptions first, then the node (see
    /// [`RosNode::shutdown`]). Call after the tasks it started have ended.
    pub async fn shutdown(self) {
        let RosBridge { node, inputs } = self;
        drop(inputs);
        node.shutdown().await;
    }

    /// Publish what the bus carries until `shutdown`; with `joints_out`
    /// (the daemon owns the servo bus), also every servo read on
    /// `/joint_states`, names in model order.
    pub fn start_outputs(
        &mut self,
        config: &Config,
        models: &ModelSet,
        bus: &OutputBus,
        mut shutdown: Shutdown,
        mut joints_out: Option<StreamTap<Sample>>,
    ) -> Result<JoinHandle<()>, ServiceError> {
        let t = &config.ros.topics;
        let topics = OutputTopics {
            forecast: t.forecast.clone(),
            horizons_ms: t.horizons_ms.clone(),
            fall_imminent: t.fall_imminent.clone(),
            diagnostics: t.diagnostics.clone(),
            joint_states: joints_out.as_ref().map(|_| t.joint_states.clone()),
        };
        let names = models.spec().joint_names.clone();
        let horizons: Vec<f32> = models.horizons_ms().iter().map(|&h| h as f32).collect();
        let outputs = RosOutputs::new(&mut self.node, &topics, &horizons)?;
        let mut sub = bus.subscribe();
        Ok(tokio::spawn(async move {
            let mut imminent: Option<bool> = None;
            loop {
                tokio::select! {
                    f = sub.forecasts.recv() => match f {
                        Ok(f) => {
                            publish_tick(&outputs, &mut imminent, &f);
                            sub.published(&f);
                        }
                        Err(RecvError::Lagged(n)) => tracing::warn!(lost = n, "ROS 2 publisher fell behind: forecasts dropped"),
                        Err(RecvError::Closed) => break,
                    },
                    d = sub.diagnostics.recv() => match d {
                        Ok(d) => { let _ = outputs.publish_diagnostics(&d); }
                        Err(RecvError::Lagged(_)) => {}
                        Err(RecvError::Closed) => break,
                    },
                    j = async {
                        match joints_out.as_mut() {
                            Some(tap) => tap.changed().await,
                            None => std::future::pending().await,
                        }
                    } => match j {
                        Some(s) => {
                            if let Sample::Joints { stamp_ns, positions_rad, .. } = &s.value {
                                if let Some(msg) = joint_state(&names, *stamp_ns, positions_rad) {
                                    let _ = outputs.publish_joint_states(msg);
                                }
                            }
                        }
                        None => joints_out = None,
                    },
                    () = shutdown.recv() => break,
                }
            }
            // Drain what is already produced, so the last ticks go out too.
            while let Ok(f) = sub.forecasts.try_recv() {
                publish_tick(&outputs, &mut imminent, &f);
                sub.published(&f);
            }
        }))
    }

    /// Subscribe to the topics of the streams `from_ros` selects and feed
    /// those of `streams` until `shutdown`. `camera_raw` (`record`): the
    /// camera's messages as received, not decoded, offered to that feed
    /// (their stamps checked at the same boundary).
    pub fn start_inputs(
        &mut self,
        config: &Config,
        spec: &WindowSpec,
        streams: &LiveStreams,
        from_ros: PerStream<bool>,
        camera_raw: Option<StreamFeed<Arc<CompressedImage>>>,
        shutdown: Shutdown,
    ) -> Result<Vec<JoinHandle<()>>, ServiceError> {
        let t = &config.ros.topics;
        // `record` reads the camera topic for its raw feed.
        let topics: InputTopics = PerStream::from_fn(|kind| {
            let raw = kind == StreamKind::Camera && camera_raw.is_some();
            (from_ros[kind] || raw).then(|| t.input(kind).to_owned())
        });
        let inputs = RosInputs::start(&mut self.node, &topics)?;
        let mut tasks = Vec::new();
        for (kind, latest) in inputs.latest.iter() {
            let Some(rx) = latest.clone().filter(|_| from_ros[kind]) else {
                continue;
            };
            let spec = spec.clone();
            let feed = streams.feeds[kind].clone();
            let limits = feed.limits().clone();
            let errors = Arc::clone(&inputs.errors);
            tasks.push(forward(rx, feed, errors, shutdown.clone(), move |m| {
                model_sample(m, &spec, &limits)
            }));
        }
        if let (Some(rx), Some(feed)) = (inputs.latest.camera.clone(), camera_raw) {
            let errors = Arc::clone(&inputs.errors);
            tasks.push(forward(rx, feed, errors, shutdown, |m| match &m.value {
                InputMessage::Camera(image) => (
                    header_stamp(&image.header, m.stamp_ns),
                    Ok(Arc::new(image.clone())),
                ),
                other => (m.stamp_ns, Err(wrong_stream(other, StreamKind::Camera))),
            }));
        }
        self.inputs = Some(inputs);
        Ok(tasks)
    }
}

/// A servo read as `sensor_msgs/JointState` (positions only, radians),
/// with only the joints that were read: a motor that did not answer (NaN)
/// is left out of `name` and `position`, as `sensor_msgs/JointState`
/// allows, so one absent servo does not hide the others. `None` when no
/// joint was read.
pub fn joint_state(names: &[String], stamp_ns: i64, positions: &[f32]) -> Option<JointState> {
    let (name, position): (Vec<String>, Vec<f64>) = names
        .iter()
        .zip(positions)
        .filter(|(_, p)| p.is_finite())
        .map(|(n, &p)| (n.clone(), f64::from(p)))
        .unzip();
    (!name.is_empty()).then(|| JointState {
        header: Header {
            stamp: ros_time(stamp_ns),
            frame_id: String::new(),
        },
        name,
        position,
        velocity: Vec::new(),
        effort: Vec::new(),
    })
}

/// One tick's outputs: the forecast, and the safety signal when it changed
/// (`imminent`: the last value published). Publish failures are counted by
/// `RosOutputs` and reported on `/diagnostics`.
fn publish_tick(outputs: &RosOutputs, imminent: &mut Option<bool>, f: &ForecastOutput) {
    let _ = outputs.publish_forecast(&published_probabilities(f));
    let _ = publish_imminent_change(imminent, f.imminent, |v| outputs.publish_fall_imminent(v));
}

/// A ROS 2 message in model form (the conversions a replay uses), with
/// its stamp on the tick clock: a sensor reading's header stamp (its
/// reception when the header has none); a plan's reception, since a plan
/// is known from the moment it arrives. An image too large for `limits`
/// is rejected before it is decoded.
fn model_sample(
    m: &Stamped<InputMessage>,
    spec: &WindowSpec,
    limits: &InputLimits,
) -> (i64, Result<Sample, Rejection>) {
    let (stamp_ns, sample) = match &m.value {
        InputMessage::Joints(msg) => {
            let stamp_ns = header_stamp(&msg.header, m.stamp_ns);
            let sample =
                joints_from_msg(msg, &spec.joint_names).map(|positions_rad| Sample::Joints {
                    stamp_ns,
                    positions_rad,
                    read_ns: None,
                });
            (stamp_ns, sample)
        }
        InputMessage::Camera(msg) => {
            let stamp_ns = header_stamp(&msg.header, m.stamp_ns);
            if let Err(too_large) = limits.image_size(msg.data.len()) {
                return (stamp_ns, Err(too_large));
            }
            let sample = frame_from_msg(msg, spec.frame_size).map(|frame| Sample::Frame {
                stamp_ns,
                frame: Arc::new(frame),
            });
            (stamp_ns, sample)
        }
        InputMessage::Plan(msg) => {
            let stamp_ns = m.stamp_ns;
            let sample = Plan::from_msg(msg, &spec.joint_names).map(|plan| Sample::Plan {
                stamp_ns,
                plan: Arc::new(plan),
            });
            (stamp_ns, sample)
        }
    };
    (stamp_ns, sample.map_err(|e| Rejection::from_sample(&e)))
}

/// A header's stamp, or `received_ns` when the sender left it zero.
fn header_stamp(header: &Header, received_ns: i64) -> i64 {
    let stamp = header.stamp.to_ns();
    if stamp > 0 {
        stamp
    } else {
        received_ns
    }
}

/// A message that arrived on another stream's subscription (never, by
/// construction of [`RosInputs`]).
fn wrong_stream(m: &InputMessage, expected: StreamKind) -> Rejection {
    Rejection::BadMessage {
        what: format!("a {} message on the {expected} stream", m.kind()),
    }
}

/// Convert each new message of `rx` once and offer it to `feed`; the
/// samples DDS could not deserialize (counted per stream by the
/// subscription, `errors`) go to the stream's errors (`dds_undecodable`),
/// polled twice a second.
fn forward<T, F>(
    mut rx: Latest,
    feed: StreamFeed<T>,
    errors: Arc<InputErrors>,
    mut shutdown: Shutdown,
    convert: F,
) -> JoinHandle<()>
where
    T: StreamValue,
    F: Fn(&Stamped<InputMessage>) -> (i64, Result<T, Rejection>) + Send + 'static,
{
    tokio::spawn(async move {
        let mut poll = tokio::time::interval(std::time::Duration::from_millis(500));
        let mut undecodable = 0;
        loop {
            tokio::select! {
                changed = rx.changed() => {
                    if changed.is_err() {
                        feed.stats().set_state("subscription ended");
                        return;
                    }
                }
                _ = poll.tick() => {
                    let n = errors[feed.kind()].load(Ordering::Relaxed);
                    if n != undecodable {
                        undecodable = n;
                        feed.stats().set_external(n, vec![("dds_undecodable".into(), n.to_string())]);
                    }
                    continue;
                }
                () = shutdown.recv() => return,
            }
            let latest = rx.borrow_and_update().clone();
            let Some(received) = latest else { continue };
            let (stamp_ns, value) = convert(&received);
            let _ = feed.offer(stamp_ns, value);
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn output(valid: bool, probabilities: Vec<f32>) -> ForecastOutput {
        ForecastOutput {
            tick: 7,
            stamp_ns: 0,
            probabilities,
            horizons_ms: vec![500, 1000],
            valid,
            imminent: true,
            ablation: "MP",
            invalid_reason: String::new(),
            sensed_at: std::time::Instant::now(),
        }
    }

    #[test]
    fn a_failed_imminent_change_is_sent_again() {
        let mut last = None;
        let mut sent = Vec::new();
        let mut publish = |v: bool, ok: bool| {
            publish_imminent_change(&mut last, v, |v| {
                sent.push(v);
                if ok {
                    Ok(())
                } else {
                    Err("window full")
                }
            })
        };
        assert!(publish(false, true).is_ok());
        assert!(publish(false, true).is_ok()); // unchanged: not sent
        assert!(publish(true, false).is_err()); // the change fails...
        assert!(publish(true, true).is_ok()); // ...and is sent on the next tick
        assert!(publish(true, true).is_ok());
        assert_eq!(sent, [false, true, true]);
    }

    #[test]
    fn joint_states_leave_out_the_joints_not_read() {
        let names: Vec<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
        let msg = joint_state(&names, 1_500_000_000, &[0.5, f32::NAN, -1.0]).expect("msg");
        assert_eq!(msg.name, ["a", "c"]);
        assert_eq!(msg.position, [0.5, -1.0]);
        assert_eq!(msg.header.stamp.sec, 1);
        assert!(joint_state(&names, 0, &[f32::NAN; 3]).is_none());
    }

    #[test]
    fn only_a_valid_forecast_is_published_as_numbers() {
        assert_eq!(
            published_probabilities(&output(true, vec![0.1, 0.2])),
            [0.1, 0.2]
        );
        for invalid in [output(false, vec![0.1, 0.2]), output(true, Vec::new())] {
            let p = published_probabilities(&invalid);
            assert_eq!(p.len(), 2);
            assert!(p.iter().all(|x| x.is_nan()), "{p:?}");
        }
    }
}
