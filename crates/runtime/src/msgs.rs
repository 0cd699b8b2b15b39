//! ROS 2 message types, written once and used by both ROS 2 (ros2-client)
//! and the MCAP recordings.
//!
//! Each struct holds its fields in `.msg` order, so serde + CDR produce the
//! same bytes as rclcpp/rclpy. [`RosMessage`] adds what a recording needs to
//! describe the type: its name (`sensor_msgs/msg/JointState`) and its full
//! `ros2msg` definition (the `.msg` text followed by every nested definition
//! after a line of 80 `=` and a `MSG: pkg/Type` line, as `ros2 bag` writes
//! it), so `ros2 bag`, rosbags and Foxglove read our files unchanged.
//!
//! Bytes enter and leave through [`encode_cdr`] / [`decode_cdr`], which add
//! and check the 4-byte CDR encapsulation header (`00 01 00 00`: CDR, little
//! endian; big endian `00 00` is accepted on decode).

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// Errors from encoding or decoding one message.
#[derive(Debug, thiserror::Error)]
pub enum MsgError {
    #[error(
        "{type_name}: message is {len} bytes, shorter than the 4-byte CDR encapsulation header"
    )]
    TooShort { type_name: &'static str, len: usize },
    #[error("{type_name}: unsupported CDR encapsulation header {header:02x?} (expected 00 01 = CDR little endian, or 00 00 = CDR big endian)")]
    Encapsulation {
        type_name: &'static str,
        header: [u8; 2],
    },
    #[error("{type_name}: CDR decoding failed: {source}")]
    Decode {
        type_name: &'static str,
        source: cdr_encoding::Error,
    },
    #[error("{type_name}: CDR encoding failed: {source}")]
    Encode {
        type_name: &'static str,
        source: cdr_encoding::Error,
    },
}

/// A ROS 2 message type: its name and its complete `ros2msg` definition.
pub trait RosMessage: Serialize + DeserializeOwned {
    /// Package, e.g. `sensor_msgs`.
    const PACKAGE: &'static str;
    /// Type name inside the package, e.g. `JointState`.
    const NAME: &'static str;
    /// The full type name as ROS 2 and MCAP schemas spell it: `sensor_msgs/msg/JointState`.
    const TYPE_NAME: &'static str;
    /// This type's own `.msg` text (no nested definitions).
    const MSG_TEXT: &'static str;
    /// Nested types this one uses, depth first, each once: (`pkg/Type`, `.msg` text).
    const DEPENDENCIES: &'static [(&'static str, &'static str)];

    /// The complete `ros2msg` schema text: own definition, then each nested one
    /// after a separator line of 80 `=` and `MSG: pkg/Type`.
    fn schema_text() -> String {
        let mut text = String::from(Self::MSG_TEXT);
        for (name, msg) in Self::DEPENDENCIES {
            if !text.ends_with('\n') {
                text.push('\n');
            }
            text.push_str(SEPARATOR);
            text.push('\n');
            text.push_str("MSG: ");
            text.push_str(name);
            text.push('\n');
            text.push_str(msg);
        }
        text
    }
}

/// The separator line between definitions in a `ros2msg` schema (80 `=`).
pub const SEPARATOR: &str =
    "================================================================================";

/// CDR encapsulation header for little-endian plain CDR, as ROS 2 writes it.
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Serialise a message as ROS 2 does on the wire and in bags: encapsulation
/// header `00 01 00 00` followed by little-endian CDR.
pub fn encode_cdr<T: RosMessage>(msg: &T) -> Result<Vec<u8>, MsgError> {
    let body = cdr_encoding::to_vec::<T, byteorder::LittleEndian>(msg).map_err(|source| {
        MsgError::Encode {
            type_name: T::TYPE_NAME,
            source,
        }
    })?;
    let mut out = Vec::with_capacity(4 + body.len());
    out.extend_from_slice(&CDR_LE_HEADER);
    out.extend_from_slice(&body);
    Ok(out)
}

/// Decode a message written by [`encode_cdr`] (or by any ROS 2 node): checks
/// the encapsulation header, then decodes the CDR body that follows it.
pub fn decode_cdr<T: RosMessage>(bytes: &[u8]) -> Result<T, MsgError> {
    if bytes.len() < 4 {
        return Err(MsgError::TooShort {
            type_name: T::TYPE_NAME,
            len: bytes.len(),
        });
    }
    let body = &bytes[4..];
    let decoded = match [bytes[0], bytes[1]] {
        [0x00, 0x01] => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body),
        [0x00, 0x00] => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body),
        header => {
            return Err(MsgError::Encapsulation {
                type_name: T::TYPE_NAME,
                header,
            })
        }
    };
    decoded
        .map(|(msg, _consumed)| msg)
        .map_err(|source| MsgError::Decode {
            type_name: T::TYPE_NAME,
            source,
        })
}

macro_rules! ros_message {
    ($ty:ty, $pkg:literal, $name:literal, $text:expr, [$($dep:expr),* $(,)?]) => {
        impl RosMessage for $ty {
            const PACKAGE: &'static str = $pkg;
            const NAME: &'static str = $name;
            const TYPE_NAME: &'static str = concat!($pkg, "/msg/", $name);
            const MSG_TEXT: &'static str = $text;
            const DEPENDENCIES: &'static [(&'static str, &'static str)] = &[$($dep),*];
        }
        impl ros2_client::Message for $ty {}
    };
}

// `.msg` texts (comments left out; field names and types are what readers need).
const TIME_MSG: &str = "int32 sec\nuint32 nanosec\n";
const DURATION_MSG: &str = "int32 sec\nuint32 nanosec\n";
const HEADER_MSG: &str = "builtin_interfaces/Time stamp\nstring frame_id\n";
const BOOL_MSG: &str = "bool data\n";
const MULTI_ARRAY_DIMENSION_MSG: &str = "string label\nuint32 size\nuint32 stride\n";
const MULTI_ARRAY_LAYOUT_MSG: &str = "MultiArrayDimension[] dim\nuint32 data_offset\n";
const FLOAT32_MULTI_ARRAY_MSG: &str = "MultiArrayLayout layout\nfloat32[] data\n";
const JOINT_STATE_MSG: &str =
    "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n";
const COMPRESSED_IMAGE_MSG: &str = "std_msgs/Header header\nstring format\nuint8[] data\n";
const JOINT_TRAJECTORY_POINT_MSG: &str = "float64[] positions\nfloat64[] velocities\nfloat64[] accelerations\nfloat64[] effort\nbuiltin_interfaces/Duration time_from_start\n";
const JOINT_TRAJECTORY_MSG: &str =
    "std_msgs/Header header\nstring[] joint_names\nJointTrajectoryPoint[] points\n";
const KEY_VALUE_MSG: &str = "string key\nstring value\n";
const DIAGNOSTIC_STATUS_MSG: &str = "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n";
const DIAGNOSTIC_ARRAY_MSG: &str = "std_msgs/Header header\nDiagnosticStatus[] status\n";

const DEP_TIME: (&str, &str) = ("builtin_interfaces/Time", TIME_MSG);
const DEP_DURATION: (&str, &str) = ("builtin_interfaces/Duration", DURATION_MSG);
const DEP_HEADER: (&str, &str) = ("std_msgs/Header", HEADER_MSG);

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// From nanoseconds since the clock's epoch (negative allowed: floor division).
    pub fn from_ns(stamp_ns: i64) -> Time {
        Time {
            sec: stamp_ns.div_euclid(1_000_000_000) as i32,
            nanosec: stamp_ns.rem_euclid(1_000_000_000) as u32,
        }
    }

    /// Nanoseconds since the clock's epoch.
    pub fn to_ns(self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

impl Duration {
    /// From nanoseconds (negative allowed: floor division, as ROS 2 does).
    pub fn from_ns(duration_ns: i64) -> Duration {
        Duration {
            sec: duration_ns.div_euclid(1_000_000_000) as i32,
            nanosec: duration_ns.rem_euclid(1_000_000_000) as u32,
        }
    }

    /// Nanoseconds.
    pub fn to_ns(self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `std_msgs/msg/Bool`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Bool {
    pub data: bool,
}

/// `std_msgs/msg/MultiArrayDimension`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct MultiArrayDimension {
    pub label: String,
    pub size: u32,
    pub stride: u32,
}

/// `std_msgs/msg/MultiArrayLayout`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct MultiArrayLayout {
    pub dim: Vec<MultiArrayDimension>,
    pub data_offset: u32,
}

/// `std_msgs/msg/Float32MultiArray`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Float32MultiArray {
    pub layout: MultiArrayLayout,
    pub data: Vec<f32>,
}

/// `sensor_msgs/msg/JointState`: positions in radians.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

/// `sensor_msgs/msg/CompressedImage`: `format` is `jpeg` or `png` (or
/// image_transport's `"bgr8; jpeg compressed bgr8"` style).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    /// The compressed bytes (serde_bytes: one copy instead of one call per byte;
    /// the CDR bytes are the same as a `uint8[]` sequence).
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `trajectory_msgs/msg/JointTrajectoryPoint`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct JointTrajectoryPoint {
    pub positions: Vec<f64>,
    pub velocities: Vec<f64>,
    pub accelerations: Vec<f64>,
    pub effort: Vec<f64>,
    pub time_from_start: Duration,
}

/// `trajectory_msgs/msg/JointTrajectory`: `header.stamp` is when point 0's
/// `time_from_start` counts from.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct JointTrajectory {
    pub header: Header,
    pub joint_names: Vec<String>,
    pub points: Vec<JointTrajectoryPoint>,
}

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// `diagnostic_msgs/msg/DiagnosticStatus`; `level` is one of the constants.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    pub const OK: u8 = 0;
    pub const WARN: u8 = 1;
    pub const ERROR: u8 = 2;
    pub const STALE: u8 = 3;
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

ros_message!(Time, "builtin_interfaces", "Time", TIME_MSG, []);
ros_message!(Duration, "builtin_interfaces", "Duration", DURATION_MSG, []);
ros_message!(Header, "std_msgs", "Header", HEADER_MSG, [DEP_TIME]);
ros_message!(Bool, "std_msgs", "Bool", BOOL_MSG, []);
ros_message!(
    MultiArrayDimension,
    "std_msgs",
    "MultiArrayDimension",
    MULTI_ARRAY_DIMENSION_MSG,
    []
);
ros_message!(
    MultiArrayLayout,
    "std_msgs",
    "MultiArrayLayout",
    MULTI_ARRAY_LAYOUT_MSG,
    [("std_msgs/MultiArrayDimension", MULTI_ARRAY_DIMENSION_MSG)]
);
ros_message!(
    Float32MultiArray,
    "std_msgs",
    "Float32MultiArray",
    FLOAT32_MULTI_ARRAY_MSG,
    [
        ("std_msgs/MultiArrayLayout", MULTI_ARRAY_LAYOUT_MSG),
        ("std_msgs/MultiArrayDimension", MULTI_ARRAY_DIMENSION_MSG)
    ]
);
ros_message!(
    JointState,
    "sensor_msgs",
    "JointState",
    JOINT_STATE_MSG,
    [DEP_HEADER, DEP_TIME]
);
ros_message!(
    CompressedImage,
    "sensor_msgs",
    "CompressedImage",
    COMPRESSED_IMAGE_MSG,
    [DEP_HEADER, DEP_TIME]
);
ros_message!(
    JointTrajectoryPoint,
    "trajectory_msgs",
    "JointTrajectoryPoint",
    JOINT_TRAJECTORY_POINT_MSG,
    [DEP_DURATION]
);
ros_message!(
    JointTrajectory,
    "trajectory_msgs",
    "JointTrajectory",
    JOINT_TRAJECTORY_MSG,
    [
        DEP_HEADER,
        DEP_TIME,
        (
            "trajectory_msgs/JointTrajectoryPoint",
            JOINT_TRAJECTORY_POINT_MSG
        ),
        DEP_DURATION
    ]
);
ros_message!(KeyValue, "diagnostic_msgs", "KeyValue", KEY_VALUE_MSG, []);
ros_message!(
    DiagnosticStatus,
    "diagnostic_msgs",
    "DiagnosticStatus",
    DIAGNOSTIC_STATUS_MSG,
    [("diagnostic_msgs/KeyValue", KEY_VALUE_MSG)]
);
ros_message!(
    DiagnosticArray,
    "diagnostic_msgs",
    "DiagnosticArray",
    DIAGNOSTIC_ARRAY_MSG,
    [
        DEP_HEADER,
        DEP_TIME,
        ("diagnostic_msgs/DiagnosticStatus", DIAGNOSTIC_STATUS_MSG),
        ("diagnostic_msgs/KeyValue", KEY_VALUE_MSG)
    ]
);

#[cfg(test)]
mod tests {
    use super::*;

    /// Bool{true}: header, then one byte.
    #[test]
    fn bool_golden_bytes() {
        let bytes = encode_cdr(&Bool { data: true }).unwrap();
        assert_eq!(bytes, vec![0x00, 0x01, 0x00, 0x00, 0x01]);
        assert_eq!(decode_cdr::<Bool>(&bytes).unwrap(), Bool { data: true });
    }

    /// JointState worked out by hand from the CDR rules (offsets count from
    /// the end of the encapsulation header; primitives align to their size).
    #[test]
    fn joint_state_golden_bytes() {
        let msg = JointState {
            header: Header {
                stamp: Time { sec: 1, nanosec: 2 },
                frame_id: "ab".into(),
            },
            name: vec!["j".into()],
            position: vec![1.5],
            velocity: vec![],
            effort: vec![],
        };
        #[rustfmt::skip]
        let expected: Vec<u8> = vec![
            0x00, 0x01, 0x00, 0x00,             // encapsulation: CDR LE
            0x01, 0x00, 0x00, 0x00,             // @0  stamp.sec = 1
            0x02, 0x00, 0x00, 0x00,             // @4  stamp.nanosec = 2
            0x03, 0x00, 0x00, 0x00,             // @8  frame_id length 3 (with NUL)
            b'a', b'b', 0x00,                   // @12 "ab\0"
            0x00,                               // @15 pad to 4
            0x01, 0x00, 0x00, 0x00,             // @16 name: 1 string
            0x02, 0x00, 0x00, 0x00,             // @20 length 2
            b'j', 0x00,                         // @24 "j\0"
            0x00, 0x00,                         // @26 pad to 4
            0x01, 0x00, 0x00, 0x00,             // @28 position: 1 double
            0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xf8, 0x3f, // @32 (8-aligned) 1.5
            0x00, 0x00, 0x00, 0x00,             // @40 velocity: 0
            0x00, 0x00, 0x00, 0x00,             // @44 effort: 0
        ];
        let bytes = encode_cdr(&msg).unwrap();
        assert_eq!(bytes, expected);
        assert_eq!(decode_cdr::<JointState>(&bytes).unwrap(), msg);
    }

    /// DiagnosticStatus: a byte then strings (strings align the length to 4).
    #[test]
    fn diagnostic_status_golden_bytes() {
        let msg = DiagnosticStatus {
            level: DiagnosticStatus::WARN,
            name: "n".into(),
            message: String::new(),
            hardware_id: String::new(),
            values: vec![KeyValue {
                key: "k".into(),
                value: "v".into(),
            }],
        };
        #[rustfmt::skip]
        let expected: Vec<u8> = vec![
            0x00, 0x01, 0x00, 0x00,
            0x01,                         // @0 level = WARN
            0x00, 0x00, 0x00,             // @1 pad to 4
            0x02, 0x00, 0x00, 0x00, b'n', 0x00, // @4 name "n"
            0x00, 0x00,                   // @10 pad
            0x01, 0x00, 0x00, 0x00, 0x00, // @12 message "" (length 1: just NUL)
            0x00, 0x00, 0x00,             // @17 pad
            0x01, 0x00, 0x00, 0x00, 0x00, // @20 hardware_id ""
            0x00, 0x00, 0x00,             // @25 pad
            0x01, 0x00, 0x00, 0x00,       // @28 values: 1
            0x02, 0x00, 0x00, 0x00, b'k', 0x00, // @32 key "k"
            0x00, 0x00,                   // @38 pad
            0x02, 0x00, 0x00, 0x00, b'v', 0x00, // @40 value "v"
        ];
        let bytes = encode_cdr(&msg).unwrap();
        assert_eq!(bytes, expected);
        assert_eq!(decode_cdr::<DiagnosticStatus>(&bytes).unwrap(), msg);
    }

    #[test]
    fn compressed_image_round_trip_and_bytes() {
        let msg = CompressedImage {
            header: Header::default(),
            format: "jpeg".into(),
            data: vec![0xff, 0xd8, 0x00],
        };
        let bytes = encode_cdr(&msg).unwrap();
        #[rustfmt::skip]
        let expected: Vec<u8> = vec![
            0x00, 0x01, 0x00, 0x00,
            0, 0, 0, 0, 0, 0, 0, 0,             // stamp
            0x01, 0, 0, 0, 0x00,                // frame_id ""
            0, 0, 0,                            // pad
            0x05, 0, 0, 0, b'j', b'p', b'e', b'g', 0x00, // format
            0, 0, 0,                            // pad
            0x03, 0, 0, 0, 0xff, 0xd8, 0x00,    // data
        ];
        assert_eq!(bytes, expected);
        assert_eq!(decode_cdr::<CompressedImage>(&bytes).unwrap(), msg);
    }

    #[test]
    fn decode_rejects_bad_headers_and_short_input() {
        assert!(matches!(
            decode_cdr::<Bool>(&[0, 1]),
            Err(MsgError::TooShort { .. })
        ));
        assert!(matches!(
            decode_cdr::<Bool>(&[0, 7, 0, 0, 1]),
            Err(MsgError::Encapsulation { .. })
        ));
        // a JointState cut short inside a sequence
        let msg = JointState {
            name: vec!["a".into(), "b".into()],
            position: vec![1.0, 2.0],
            ..Default::default()
        };
        let bytes = encode_cdr(&msg).unwrap();
        let err = decode_cdr::<JointState>(&bytes[..bytes.len() - 5]).unwrap_err();
        assert!(
            err.to_string().contains("sensor_msgs/msg/JointState"),
            "{err}"
        );
    }

    #[test]
    fn schema_texts_have_nested_definitions() {
        let text = JointTrajectory::schema_text();
        assert!(text.starts_with("std_msgs/Header header\n"));
        assert!(text.contains(&format!(
            "\n{SEPARATOR}\nMSG: trajectory_msgs/JointTrajectoryPoint\nfloat64[] positions\n"
        )));
        assert!(text.contains("MSG: builtin_interfaces/Duration\n"));
        assert!(text.contains("MSG: builtin_interfaces/Time\n"));
        assert_eq!(
            JointTrajectory::TYPE_NAME,
            "trajectory_msgs/msg/JointTrajectory"
        );
        assert_eq!(Bool::schema_text(), "bool data\n");
        assert_eq!(SEPARATOR.len(), 80);
    }

    #[test]
    fn time_ns_round_trip() {
        for ns in [
            0i64,
            1,
            999_999_999,
            1_000_000_000,
            -1,
            1_700_000_000_123_456_789,
        ] {
            assert_eq!(Time::from_ns(ns).to_ns(), ns);
            assert_eq!(Duration::from_ns(ns).to_ns(), ns);
        }
        assert_eq!(
            Time::from_ns(-1),
            Time {
                sec: -1,
                nanosec: 999_999_999
            }
        );
    }
}
