//! The daemon's side of the ROS 2 seam: one node ([`RosBridge`]) whose
//! publishers (`outputs::ros`) are fed from the [`OutputBus`], and on
//! which the ROS 2 source (`sources::ros`) subscribes, offering each
//! message, converted at its edge, into the live [`StreamFeed`]s.
//!
//! The node honours `ROS_DOMAIN_ID` and `ROS_AUTOMATIC_DISCOVERY_RANGE`
//! (`ROS_LOCALHOST_ONLY`), unless `[ros].domain_id` / `[ros].localhost_only`
//! set them in the config, and the DDS Security variables
//! (`ROS_SECURITY_*`, `ros::security`) with the enclave `[ros].enclave`.

use std::sync::Arc;

use tokio::sync::broadcast::error::RecvError;
use tokio::task::JoinHandle;

use crate::config::Config;
use crate::daemon::LiveStreams;
use crate::daemon::ServiceError;
use crate::msgs::{CompressedImage, Header, JointState};
use crate::outputs::ros::{ros_time, OutputTopics, RosOutputs};
use crate::outputs::{publish_imminent_change, published_probabilities, ForecastOutput, OutputBus};
use crate::pipeline::models::ModelSet;
use crate::ros::{RosError, RosNode, RosSettings, DISCOVERY_RANGE_ENV, DOMAIN_ID_ENV};
use crate::shutdown::Shutdown;
use crate::sources::ros::{CameraFeed, RosFeeds};
use crate::streams::sample::Sample;
use crate::streams::{PerStream, StreamFeed, StreamKind, StreamTap};
use crate::window::WindowSpec;

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

/// The daemon's ROS 2 node; shut it down after the tasks it started
/// (publisher, subscriptions) have ended.
pub struct RosBridge {
    node: RosNode,
}

impl RosBridge {
    /// Start the node (DDS participant, spinner).
    pub fn start(config: &Config) -> Result<RosBridge, ServiceError> {
        let settings = settings(config)?;
        Ok(RosBridge {
            node: RosNode::start(&settings)?,
        })
    }

    /// Leave the DDS domain (see [`RosNode::shutdown`]). Call after the
    /// tasks it started have ended: the subscriptions end with theirs.
    pub async fn shutdown(self) {
        self.node.shutdown().await;
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

    /// Subscribe to the topics of the streams `from_ros` selects, each
    /// offering into its feed of `streams` (`sources::ros`), until
    /// `shutdown`. `camera_raw` (`record`): the camera's images as
    /// received, not decoded, go to that feed (their stamps checked at the
    /// same boundary).
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
        let topic = |kind: StreamKind| t.input(kind).to_owned();
        let sample_feed =
            |kind: StreamKind| from_ros[kind].then(|| (topic(kind), streams.feeds[kind].clone()));
        let camera = match camera_raw {
            Some(raw) => Some((topic(StreamKind::Camera), CameraFeed::Images(raw))),
            None => sample_feed(StreamKind::Camera).map(|(t, f)| (t, CameraFeed::Frames(f))),
        };
        let feeds = RosFeeds {
            joints: sample_feed(StreamKind::Joints),
            camera,
            plan: sample_feed(StreamKind::Plan),
        };
        Ok(crate::sources::ros::subscribe(
            &mut self.node,
            feeds,
            spec,
            &shutdown,
        )?)
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
    // A skipped tick carries the latch's state as it was: the latch is
    // moved by forecasts only.
    if !f.skipped {
        let _ = publish_imminent_change(imminent, f.imminent, |v| outputs.publish_fall_imminent(v));
    }
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
            out_of_range: String::new(),
            skipped: false,
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
