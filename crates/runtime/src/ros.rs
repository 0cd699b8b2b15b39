//! The daemon's ROS 2 node: one DDS participant, one node, the QoS profiles
//! of `docs/ros.md` and the topic-name rules, shared by the publishers in
//! `outputs::ros` and the subscriptions in `sources::ros`.
//!
//! Settings enter from the environment the way every ROS 2 node reads them
//! (`ROS_DOMAIN_ID`, `ROS_AUTOMATIC_DISCOVERY_RANGE`, the older
//! `ROS_LOCALHOST_ONLY`: ros2-client reads none of them itself) plus a
//! namespace and node name from the config. [`RosNode::start`] builds the
//! participant (bound to 127.0.0.1 only when discovery is limited to the
//! localhost), creates the node and runs its spinner (discovery, parameter
//! services) as a tokio task. Topics leave this module as `Topic` handles
//! created with the QoS that belongs to them.

pub mod security;

use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;

use serde::Deserialize;

use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::{Context, MessageTypeName, Name, Node, NodeName, NodeOptions, QosProfile};
use rustdds::{
    DomainParticipant, DomainParticipantBuilder, QosPolicies, QosPolicyBuilder, Topic,
    TopicDescription, TopicKind,
};

/// Environment variable with the DDS domain (0 when unset or empty).
pub const DOMAIN_ID_ENV: &str = "ROS_DOMAIN_ID";
/// Environment variable limiting discovery (`LOCALHOST`, `SUBNET`, ...).
pub const DISCOVERY_RANGE_ENV: &str = "ROS_AUTOMATIC_DISCOVERY_RANGE";
/// Humble-era switch (`1` = localhost only), honoured when the range is unset.
pub const LOCALHOST_ONLY_ENV: &str = "ROS_LOCALHOST_ONLY";

/// Largest domain id whose RTPS ports still fit in 16 bits (ROS 2 allows
/// 0..=232 on Linux).
pub const MAX_DOMAIN_ID: u16 = 232;

/// Errors of the ROS 2 layer; each names the variable, topic or node involved.
#[derive(Debug, thiserror::Error)]
pub enum RosError {
    #[error("{var}={value:?} is not a ROS domain id (expected an integer 0..={MAX_DOMAIN_ID})")]
    BadDomainId { var: &'static str, value: String },
    #[error(
        "{var}={value:?} is not a discovery range (expected LOCALHOST, SUBNET or SYSTEM_DEFAULT)"
    )]
    BadDiscoveryRange { var: &'static str, value: String },
    #[error(
        "{var}=OFF disables discovery: fall-guard would publish to nobody; use LOCALHOST instead"
    )]
    DiscoveryOff { var: &'static str },
    #[error("bad ROS name {name:?} ({what}): {reason}")]
    BadName {
        name: String,
        what: &'static str,
        reason: String,
    },
    #[error("cannot create the DDS participant on domain {domain_id}: {reason}")]
    Participant { domain_id: u16, reason: String },
    #[error("cannot create ROS 2 node {node}: {reason}")]
    Node { node: String, reason: String },
    #[error("cannot create topic {topic} ({type_name}): {reason}")]
    Topic {
        topic: String,
        type_name: String,
        reason: String,
    },
    #[error("cannot create {kind} on {topic}: {reason}")]
    Endpoint {
        kind: &'static str,
        topic: String,
        reason: String,
    },
    #[error("publishing on {topic} failed: {reason}")]
    Publish { topic: String, reason: String },
    #[error("RosNode::start must run inside a tokio runtime (it spawns the node's spinner)")]
    NoRuntime,
    #[error("{var}={value:?} is not valid (expected {expected})")]
    BadSecurityVar {
        var: &'static str,
        value: String,
        expected: &'static str,
    },
    #[error("enclave {enclave:?} (from {from}) is not valid: {reason}")]
    BadEnclave {
        enclave: String,
        from: &'static str,
        reason: String,
    },
    #[error(
        "ROS_SECURITY_ENABLE=true with ROS_SECURITY_STRATEGY=Enforce, but this fall-guard was built without DDS Security: refusing to start on an open DDS domain; install a build with `--features security`, or set ROS_SECURITY_STRATEGY=Permissive to run unsecured"
    )]
    SecurityNotBuiltIn,
    #[error(
        "ROS_SECURITY_ENABLE=true with ROS_SECURITY_STRATEGY=Enforce, but ROS_SECURITY_KEYSTORE is not set: point it at the SROS2 keystore (the directory holding enclaves/)"
    )]
    NoKeystore,
    #[error("DDS Security (Enforce refuses to start without it): {}: {reason}", path.display())]
    SecurityFile { path: PathBuf, reason: String },
    #[error("cannot create the secured DDS participant on domain {domain_id} with the enclave {}: {reason}", enclave_dir.display())]
    SecureParticipant {
        domain_id: u16,
        enclave_dir: PathBuf,
        reason: String,
    },
}

/// How far automatic discovery reaches, as ROS 2 (Iron and later) defines
/// `ROS_AUTOMATIC_DISCOVERY_RANGE`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DiscoveryRange {
    /// Only processes on this machine: the participant uses 127.0.0.1 only.
    Localhost,
    /// Every interface (the ROS 2 default).
    Subnet,
}

/// Everything needed to create the node. Build it with [`RosSettings::from_env`]
/// (what the daemon does) or fill it directly (tests).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RosSettings {
    pub domain_id: u16,
    pub discovery: DiscoveryRange,
    /// Node namespace, e.g. `/` or `/poppy`; relative topic names resolve under it.
    pub namespace: String,
    pub node_name: String,
    /// DDS Security, present when `ROS_SECURITY_ENABLE=true`
    /// (`security::SecuritySettings`).
    pub security: Option<security::SecuritySettings>,
}

impl RosSettings {
    /// Reads `ROS_DOMAIN_ID`, `ROS_AUTOMATIC_DISCOVERY_RANGE` and
    /// `ROS_LOCALHOST_ONLY` from the process environment.
    pub fn from_env(namespace: &str, node_name: &str) -> Result<RosSettings, RosError> {
        RosSettings::from_vars(namespace, node_name, |var| std::env::var(var).ok())
    }

    /// As [`RosSettings::from_env`], with the environment given as a lookup
    /// function (so that tests need not mutate the process environment).
    /// The security variables, when enabled, use [`security::DEFAULT_ENCLAVE`].
    pub fn from_vars(
        namespace: &str,
        node_name: &str,
        var: impl Fn(&str) -> Option<String>,
    ) -> Result<RosSettings, RosError> {
        RosSettings::from_vars_in_enclave(namespace, node_name, security::DEFAULT_ENCLAVE, var)
    }

    /// As [`RosSettings::from_vars`], also reading `ROS_SECURITY_ENABLE`,
    /// `ROS_SECURITY_STRATEGY`, `ROS_SECURITY_KEYSTORE` and
    /// `ROS_SECURITY_ENCLAVE_OVERRIDE`, with `enclave` the configured one.
    pub fn from_vars_in_enclave(
        namespace: &str,
        node_name: &str,
        enclave: &str,
        var: impl Fn(&str) -> Option<String>,
    ) -> Result<RosSettings, RosError> {
        let domain_id = match var(DOMAIN_ID_ENV).map(|v| v.trim().to_owned()) {
            None => 0,
            Some(v) if v.is_empty() => 0,
            Some(v) => match v.parse::<u16>() {
                Ok(id) if id <= MAX_DOMAIN_ID => id,
                _ => {
                    return Err(RosError::BadDomainId {
                        var: DOMAIN_ID_ENV,
                        value: v,
                    })
                }
            },
        };
        let range = var(DISCOVERY_RANGE_ENV).map(|v| v.trim().to_ascii_uppercase());
        let discovery = match range.as_deref() {
            Some("LOCALHOST") => DiscoveryRange::Localhost,
            Some("SUBNET") | Some("SYSTEM_DEFAULT") => DiscoveryRange::Subnet,
            Some("OFF") => {
                return Err(RosError::DiscoveryOff {
                    var: DISCOVERY_RANGE_ENV,
                })
            }
            Some("") | None => {
                // Humble's switch, still read by Jazzy when the range is unset.
                if var(LOCALHOST_ONLY_ENV).is_some_and(|v| v.trim() == "1") {
                    DiscoveryRange::Localhost
                } else {
                    DiscoveryRange::Subnet
                }
            }
            Some(_) => {
                return Err(RosError::BadDiscoveryRange {
                    var: DISCOVERY_RANGE_ENV,
                    value: var(DISCOVERY_RANGE_ENV).unwrap_or_default(),
                })
            }
        };
        let security = security::SecuritySettings::from_vars(enclave, &var)?;
        let settings = RosSettings {
            domain_id,
            discovery,
            namespace: namespace.to_owned(),
            node_name: node_name.to_owned(),
            security,
        };
        settings.node_name()?;
        Ok(settings)
    }

    fn node_name(&self) -> Result<NodeName, RosError> {
        NodeName::new(&self.namespace, &self.node_name).map_err(|e| RosError::BadName {
            name: format!("{}/{}", self.namespace, self.node_name),
            what: "node namespace/name",
            reason: format!("{e:?}"),
        })
    }
}

/// The most samples a latched (transient-local) publisher keeps for late
/// subscribers and for repair ([`RosNode::publisher_topic`]). Also its
/// reliable send window: a reliable write fails (and is counted) only when
/// this many samples are unacknowledged, far more than `fall_imminent`
/// changes between two acknowledgements.
pub const LATCHED_MAX_SAMPLES: i32 = 16;

fn latched_limits() -> rustdds::policy::ResourceLimits {
    rustdds::policy::ResourceLimits {
        max_samples: LATCHED_MAX_SAMPLES,
        max_instances: 1,
        max_samples_per_instance: LATCHED_MAX_SAMPLES,
    }
}

/// The QoS profiles of `docs/ros.md` ("Topics"), one function per kind of topic.
pub mod qos {
    use super::*;

    /// rclpy's `qos_profile_sensor_data`: best effort, keep last 5, volatile.
    /// For `/joint_states` and `/head_camera/image_raw/compressed`.
    pub fn sensor_data() -> QosProfile {
        QosProfile::subscription_default().history(History::KeepLast { depth: 5 })
    }

    /// `/fall_guard/forecast`: reliable, keep last 1, volatile (a fresh value
    /// every tick; an old one is worthless).
    pub fn forecast() -> QosProfile {
        reliable().history(History::KeepLast { depth: 1 })
    }

    /// `/fall_guard/fall_imminent`: reliable, transient local, keep last 1, so
    /// that a safety node starting late still gets the current state.
    pub fn fall_imminent() -> QosProfile {
        latched()
    }

    /// `/fall_guard/horizons_ms`: latched like `fall_imminent`.
    pub fn horizons() -> QosProfile {
        latched()
    }

    /// `/planned_trajectory`: reliable, transient local, depth 1 (the
    /// planner's current plan survives a late subscriber). A subscription
    /// with this profile does not match a volatile or best-effort publisher.
    pub fn planned_trajectory() -> QosProfile {
        latched()
    }

    /// `/diagnostics`: the ROS 2 default, reliable, keep last 10, volatile.
    pub fn diagnostics() -> QosProfile {
        reliable().history(History::KeepLast { depth: 10 })
    }

    fn reliable() -> QosProfile {
        // Never block the tick: if the send window is full, fail at once and
        // count it; the next tick publishes a newer value anyway.
        QosProfile::publisher_default().reliability_reliable(WhenFull::Fail)
    }

    fn latched() -> QosProfile {
        reliable()
            .durability(Durability::TransientLocal)
            .history(History::KeepLast { depth: 1 })
    }
}

/// A running ROS 2 node: the DDS participant, the node and its spinner task.
/// [`RosNode::shutdown`] leaves the DDS domain in order; dropping it does the
/// same without waiting for the spinner.
///
/// Order matters: ros2-client's `Node` drops its context handle before its
/// own readers and writers, so when the node holds the last handle the
/// participant's event loop is gone before they are removed, and every one
/// of them logs an ERROR (`Cannot remove Writer GUID`). `context` is held
/// here, declared after `node` and `spinner`, so that the participant
/// outlives all of them.
pub struct RosNode {
    /// Dropping it tells the spinner to stop (`Node::drop` sends the signal;
    /// sending it ourselves as well fills the one-slot channel, which
    /// ros2-client logs as an ERROR).
    node: Node,
    settings: RosSettings,
    spinner: tokio::task::JoinHandle<()>,
    context: Context,
}

impl RosNode {
    /// Creates the participant and the node and spawns the spinner on the
    /// current tokio runtime.
    pub fn start(settings: &RosSettings) -> Result<RosNode, RosError> {
        let runtime = tokio::runtime::Handle::try_current().map_err(|_| RosError::NoRuntime)?;
        let node_name = settings.node_name()?;
        let participant = participant(settings)?;
        let context =
            Context::from_domain_participant(participant).map_err(|e| RosError::Node {
                node: node_name.fully_qualified_name(),
                reason: e.to_string(),
            })?;
        let node_error = |e: String| RosError::Node {
            node: node_name.fully_qualified_name(),
            reason: e,
        };
        let mut node = context
            .new_node(node_name.clone(), NodeOptions::new().enable_rosout(true))
            .map_err(|e| node_error(format!("{e:?}")))?;
        let spinner = node.spinner().map_err(|e| node_error(e.to_string()))?;
        let fqn = node_name.fully_qualified_name();
        let spinner = runtime.spawn(async move {
            if let Err(e) = spinner.spin().await {
                tracing::error!(node = %fqn, error = %e, "ROS 2 spinner stopped");
            }
        });
        tracing::info!(
            node = %node_name.fully_qualified_name(),
            domain_id = settings.domain_id,
            discovery = ?settings.discovery,
            "ROS 2 node started"
        );
        Ok(RosNode {
            node,
            settings: settings.clone(),
            spinner,
            context,
        })
    }

    pub fn settings(&self) -> &RosSettings {
        &self.settings
    }

    /// Leave the DDS domain cleanly: drop the node (which stops the
    /// spinner), wait for the spinner to end (it owns some of the node's
    /// built-in readers and writers), then the participant. Publishers and
    /// subscriptions made on this node must be dropped before.
    pub async fn shutdown(self) {
        let RosNode {
            node,
            spinner,
            context,
            ..
        } = self;
        drop(node);
        let mut spinner = spinner;
        if tokio::time::timeout(std::time::Duration::from_secs(2), &mut spinner)
            .await
            .is_err()
        {
            // Ended here, not left running: its readers must go before the
            // participant, or RustDDS logs an ERROR for each when they do.
            tracing::warn!("ROS 2 spinner did not stop within 2 s: ended");
            spinner.abort();
            let _ = spinner.await;
        }
        drop(context);
    }

    /// The underlying ros2-client node, to create publishers and subscriptions.
    pub fn node_mut(&mut self) -> &mut Node {
        &mut self.node
    }

    pub fn node(&self) -> &Node {
        &self.node
    }

    /// Creates a topic. `topic` is a ROS name: absolute (`/diagnostics`) or
    /// relative (`fall_guard/forecast`, resolved under the node namespace).
    /// `type_name` is `pkg/msg/Type` or `pkg/Type`.
    pub fn topic(
        &mut self,
        topic: &str,
        type_name: &str,
        qos: &QosProfile,
    ) -> Result<Topic, RosError> {
        // Resolved here rather than by ros2-client: with the root namespace it
        // would map a relative `fall_guard/forecast` to the DDS topic
        // `rt//fall_guard/forecast`, which no ROS 2 node ever matches.
        let name = parse_topic_name(&self.resolve(topic))?;
        let message_type = parse_type_name(type_name)?;
        self.node
            .create_topic(&name, message_type, qos)
            .map_err(|e| RosError::Topic {
                topic: self.resolve(topic),
                type_name: type_name.to_owned(),
                reason: e.to_string(),
            })
    }

    /// Creates a topic for a publisher: [`RosNode::topic`], plus, for a
    /// transient-local profile, a bound of [`LATCHED_MAX_SAMPLES`] on the
    /// samples its writer keeps. RustDDS 0.15 keeps every sample of a
    /// durable writer that no reader has acknowledged, up to 8,192, whatever
    /// the history depth: with no subscriber, `fall_imminent` grew the
    /// daemon's heap by its ~300 bytes per change for hours. The resource
    /// limit is where RustDDS takes its bound from (`ResourceLimits`, which
    /// ros2-client's `QosProfile` cannot express). A late subscriber gets at
    /// most that many past values, the newest last; a matched one's
    /// acknowledged samples are trimmed to the depth as before.
    pub fn publisher_topic(
        &mut self,
        topic: &str,
        type_name: &str,
        qos: &QosProfile,
    ) -> Result<Topic, RosError> {
        let t = self.topic(topic, type_name, qos)?;
        if qos.durability != Durability::TransientLocal {
            return Ok(t);
        }
        let bounded = QosPolicies::from(qos).modify_by(
            &QosPolicyBuilder::new()
                .resource_limits(latched_limits())
                .build(),
        );
        self.context
            .domain_participant()
            .create_topic(
                t.name(),
                t.get_type().name().to_owned(),
                &bounded,
                TopicKind::NoKey,
            )
            .map_err(|e| RosError::Topic {
                topic: self.resolve(topic),
                type_name: type_name.to_owned(),
                reason: e.to_string(),
            })
    }

    /// The fully qualified name a topic name resolves to on this node.
    pub fn resolve(&self, topic: &str) -> String {
        resolve_topic(&self.settings.namespace, topic)
    }
}

/// Resolves a topic name against a node namespace the way ROS 2 does
/// (absolute names stay, relative names get the namespace prefix).
pub fn resolve_topic(namespace: &str, topic: &str) -> String {
    if topic.starts_with('/') {
        topic.to_owned()
    } else if namespace == "/" || namespace.is_empty() {
        format!("/{topic}")
    } else {
        format!("{}/{topic}", namespace.trim_end_matches('/'))
    }
}

fn parse_topic_name(topic: &str) -> Result<Name, RosError> {
    Name::parse(topic).map_err(|e| RosError::BadName {
        name: topic.to_owned(),
        what: "topic",
        reason: format!("{e:?}"),
    })
}

/// Accepts `pkg/msg/Type` (the form in `.msg` files and MCAP schemas) and `pkg/Type`.
fn parse_type_name(type_name: &str) -> Result<MessageTypeName, RosError> {
    let parts: Vec<&str> = type_name.split('/').collect();
    match parts.as_slice() {
        [pkg, "msg", ty] | [pkg, ty] if !pkg.is_empty() && !ty.is_empty() => {
            Ok(MessageTypeName::new(pkg, ty))
        }
        _ => Err(RosError::BadName {
            name: type_name.to_owned(),
            what: "message type",
            reason: "expected pkg/msg/Type".to_owned(),
        }),
    }
}

/// The participant, secured when `settings.security` asks for it and
/// [`security::plan`] allows it.
fn participant(settings: &RosSettings) -> Result<DomainParticipant, RosError> {
    let builder = DomainParticipantBuilder::new(settings.domain_id);
    let builder = match settings.discovery {
        DiscoveryRange::Localhost => builder.with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)]),
        DiscoveryRange::Subnet => builder,
    };
    let plan = security::plan(settings.security.as_ref())?;
    let builder = security::configure(builder, &plan)?;
    let participant = builder.build().map_err(|e| match &plan {
        security::Plan::Secure { dir, .. } => RosError::SecureParticipant {
            domain_id: settings.domain_id,
            enclave_dir: dir.clone(),
            reason: e.to_string(),
        },
        security::Plan::Open { .. } => RosError::Participant {
            domain_id: settings.domain_id,
            reason: e.to_string(),
        },
    })?;
    if let security::Plan::Secure { dir, strategy } = &plan {
        tracing::info!(
            enclave_dir = %dir.display(),
            strategy = ?strategy,
            "DDS Security on: authenticated, access-controlled, encrypted as the governance says"
        );
    }
    Ok(participant)
}

/// `[ros.topics]`: topic names (relative names get the namespace).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct TopicsConfig {
    pub joint_states: String,
    pub planned_trajectory: String,
    pub camera: String,
    pub forecast: String,
    pub fall_imminent: String,
    pub horizons_ms: String,
    pub diagnostics: String,
}

impl Default for TopicsConfig {
    fn default() -> Self {
        TopicsConfig {
            joint_states: "joint_states".into(),
            planned_trajectory: "planned_trajectory".into(),
            camera: "head_camera/image_raw/compressed".into(),
            forecast: "fall_guard/forecast".into(),
            fall_imminent: "fall_guard/fall_imminent".into(),
            horizons_ms: "fall_guard/horizons_ms".into(),
            diagnostics: "/diagnostics".into(),
        }
    }
}

impl TopicsConfig {
    /// The topic of an input stream.
    pub fn input(&self, kind: crate::streams::StreamKind) -> &str {
        use crate::streams::StreamKind;
        match kind {
            StreamKind::Joints => &self.joint_states,
            StreamKind::Camera => &self.camera,
            StreamKind::Plan => &self.planned_trajectory,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The environment `pairs` as a variable lookup (also for `security`'s tests).
    pub(super) fn env<'a>(pairs: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |k| {
            pairs
                .iter()
                .find(|(n, _)| *n == k)
                .map(|(_, v)| (*v).to_owned())
        }
    }

    #[test]
    fn defaults_are_domain_0_on_every_interface() {
        let s = RosSettings::from_vars("/", "fall_guard", env(&[])).expect("defaults");
        assert_eq!(s.domain_id, 0);
        assert_eq!(s.discovery, DiscoveryRange::Subnet);
    }

    #[test]
    fn reads_domain_and_localhost_range() {
        let s = RosSettings::from_vars(
            "/poppy",
            "fall_guard",
            env(&[(DOMAIN_ID_ENV, "42"), (DISCOVERY_RANGE_ENV, "localhost")]),
        )
        .expect("valid");
        assert_eq!(s.domain_id, 42);
        assert_eq!(s.discovery, DiscoveryRange::Localhost);
        let s = RosSettings::from_vars("/", "n", env(&[(LOCALHOST_ONLY_ENV, "1")])).expect("valid");
        assert_eq!(s.discovery, DiscoveryRange::Localhost);
        // An explicit range wins over the older switch, as in rmw.
        let s = RosSettings::from_vars(
            "/",
            "n",
            env(&[(LOCALHOST_ONLY_ENV, "1"), (DISCOVERY_RANGE_ENV, "SUBNET")]),
        )
        .expect("valid");
        assert_eq!(s.discovery, DiscoveryRange::Subnet);
    }

    #[test]
    fn bad_values_name_the_variable() {
        for bad in ["abc", "-1", "233", "70000"] {
            let e = RosSettings::from_vars("/", "n", env(&[(DOMAIN_ID_ENV, bad)]))
                .expect_err("must reject");
            assert!(e.to_string().contains("ROS_DOMAIN_ID"), "{e}");
        }
        let e = RosSettings::from_vars("/", "n", env(&[(DISCOVERY_RANGE_ENV, "MOON")]))
            .expect_err("must reject");
        assert!(
            e.to_string().contains("ROS_AUTOMATIC_DISCOVERY_RANGE"),
            "{e}"
        );
        let e = RosSettings::from_vars("/", "n", env(&[(DISCOVERY_RANGE_ENV, "OFF")]))
            .expect_err("must reject");
        assert!(matches!(e, RosError::DiscoveryOff { .. }));
        let e = RosSettings::from_vars("poppy", "n", env(&[])).expect_err("namespace needs /");
        assert!(e.to_string().contains("poppy"), "{e}");
    }

    #[test]
    fn topic_names_resolve_like_ros() {
        assert_eq!(
            resolve_topic("/", "fall_guard/forecast"),
            "/fall_guard/forecast"
        );
        assert_eq!(
            resolve_topic("/poppy", "fall_guard/forecast"),
            "/poppy/fall_guard/forecast"
        );
        assert_eq!(resolve_topic("/poppy", "/diagnostics"), "/diagnostics");
        assert!(parse_type_name("std_msgs/msg/Bool").is_ok());
        assert!(parse_type_name("std_msgs/Bool").is_ok());
        assert!(parse_type_name("Bool").is_err());
    }

    /// The DDS topic names ROS 2 peers match on, for the root namespace and
    /// another one (ros2-client alone gets the root case wrong).
    #[tokio::test]
    async fn topics_get_the_dds_names_rclcpp_uses() {
        use rustdds::TopicDescription;
        for (namespace, topic, dds) in [
            ("/", "fall_guard/forecast", "rt/fall_guard/forecast"),
            ("/", "/diagnostics", "rt/diagnostics"),
            (
                "/poppy",
                "fall_guard/forecast",
                "rt/poppy/fall_guard/forecast",
            ),
            ("/poppy", "/diagnostics", "rt/diagnostics"),
        ] {
            let settings = RosSettings {
                domain_id: MAX_DOMAIN_ID,
                discovery: DiscoveryRange::Localhost,
                namespace: namespace.to_owned(),
                node_name: "fall_guard_names".to_owned(),
                security: None,
            };
            let mut node = RosNode::start(&settings).expect("node");
            let t = node
                .topic(topic, "std_msgs/msg/Bool", &qos::forecast())
                .expect("topic");
            assert_eq!(t.name(), dds, "{namespace} + {topic}");
        }
    }

    #[test]
    fn qos_profiles_follow_docs_ros_md() {
        use ros2_client::qos::Reliability;
        assert_eq!(qos::sensor_data().reliability, Reliability::BestEffort);
        assert_eq!(qos::sensor_data().history, History::KeepLast { depth: 5 });
        assert_eq!(qos::sensor_data().durability, Durability::Volatile);
        assert!(matches!(
            qos::forecast().reliability,
            Reliability::Reliable { .. }
        ));
        assert_eq!(qos::forecast().durability, Durability::Volatile);
        assert_eq!(qos::forecast().history, History::KeepLast { depth: 1 });
        for latched in [
            qos::fall_imminent(),
            qos::planned_trajectory(),
            qos::horizons(),
        ] {
            assert!(matches!(latched.reliability, Reliability::Reliable { .. }));
            assert_eq!(latched.durability, Durability::TransientLocal);
            assert_eq!(latched.history, History::KeepLast { depth: 1 });
        }
        assert_eq!(qos::diagnostics().history, History::KeepLast { depth: 10 });
        assert_eq!(qos::diagnostics().durability, Durability::Volatile);
    }
}
