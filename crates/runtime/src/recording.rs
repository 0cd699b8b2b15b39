//! Recordings: one MCAP file per episode, as `ros2 bag record -s mcap`
//! writes them (profile `ros2`, schemas `ros2msg`, messages `cdr`).
//!
//! Files enter through [`Recording::open`] (typed per-topic streams of
//! `(log_time_ns, msg)` plus the `fall_guard.episode` metadata as
//! [`EpisodeMeta`]); they are written by [`RecordingWriter`] (the daemon's
//! `record` command, the test kit's synthetic recordings, tests) and
//! rewritten in place, safely, by [`label`]. Errors name the file and, for
//! a damaged file, the byte offset of the record that could not be read.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};

use mcap::records::{self, Record};

use crate::msgs::{self, Bool, CompressedImage, JointState, JointTrajectory, MsgError, RosMessage};

pub use crate::streams::topics;

/// Name of the metadata record that describes the episode.
pub const EPISODE_METADATA: &str = "fall_guard.episode";

/// Why a recording could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: truncated at byte {offset}: {reason}", path.display())]
    Truncated {
        path: PathBuf,
        offset: u64,
        reason: String,
    },
    #[error("{}: corrupt at byte {offset}: {reason}", path.display())]
    Corrupt {
        path: PathBuf,
        offset: u64,
        reason: String,
    },
    #[error("{}: {topic}: message at byte {offset} (log time {log_time_ns} ns): {source}", path.display())]
    Decode {
        path: PathBuf,
        topic: String,
        offset: u64,
        log_time_ns: i64,
        source: MsgError,
    },
    #[error("{}: topic {topic} has type {found:?} / encoding {encoding:?}, expected {expected} / cdr", path.display())]
    WrongType {
        path: PathBuf,
        topic: String,
        expected: &'static str,
        found: String,
        encoding: String,
    },
    #[error("{}: no messages on topic {topic}, which is needed", path.display())]
    MissingTopic { path: PathBuf, topic: String },
    #[error("{}: no `fall_guard.episode` metadata record", path.display())]
    MissingMetadata { path: PathBuf },
    #[error("{}: metadata `fall_guard.episode`: key {key:?}: {reason}", path.display())]
    BadMetadata {
        path: PathBuf,
        key: String,
        reason: String,
    },
    #[error("{}: writing: {reason}", path.display())]
    Write { path: PathBuf, reason: String },
    #[error("{}: {reason}", path.display())]
    Label { path: PathBuf, reason: String },
}

/// The episode facts of metadata record `fall_guard.episode` (all values are
/// strings in the file).
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeMeta {
    /// `sim` or `robot`.
    pub source: String,
    pub robot: String,
    pub rate_hz: f64,
    /// Fall onset on the log-time clock, ns (`None`: the episode does not fall).
    pub fall_onset_ns: Option<i64>,
    pub seed: Option<u64>,
    pub sigma: Option<f64>,
    /// Every other key, kept as written.
    pub other: BTreeMap<String, String>,
}

impl EpisodeMeta {
    /// Parses the metadata map; `source`, `robot` and `rate_hz` are required.
    pub fn from_map(
        path: &Path,
        map: &BTreeMap<String, String>,
    ) -> Result<EpisodeMeta, RecordingError> {
        let bad = |key: &str, reason: String| RecordingError::BadMetadata {
            path: path.to_path_buf(),
            key: key.to_string(),
            reason,
        };
        let required = |key: &str| {
            map.get(key)
                .cloned()
                .ok_or_else(|| bad(key, "missing".into()))
        };
        fn parse<T: std::str::FromStr>(
            map: &BTreeMap<String, String>,
            key: &str,
            bad: &dyn Fn(&str, String) -> RecordingError,
        ) -> Result<Option<T>, RecordingError> {
            match map.get(key) {
                None => Ok(None),
                Some(v) => v
                    .trim()
                    .parse::<T>()
                    .map(Some)
                    .map_err(|_| bad(key, format!("cannot parse {v:?}"))),
            }
        }
        let rate_hz: f64 =
            parse(map, "rate_hz", &bad)?.ok_or_else(|| bad("rate_hz", "missing".into()))?;
        if !(rate_hz.is_finite() && rate_hz > 0.0) {
            return Err(bad("rate_hz", format!("must be positive, got {rate_hz}")));
        }
        let mut other = map.clone();
        for key in [
            "source",
            "robot",
            "rate_hz",
            "fall_onset_ns",
            "seed",
            "sigma",
        ] {
            other.remove(key);
        }
        Ok(EpisodeMeta {
            source: required("source")?,
            robot: required("robot")?,
            rate_hz,
            fall_onset_ns: parse(map, "fall_onset_ns", &bad)?,
            seed: parse(map, "seed", &bad)?,
            sigma: parse(map, "sigma", &bad)?,
            other,
        })
    }

    /// The metadata map as written to the file.
    pub fn to_map(&self) -> BTreeMap<String, String> {
        let mut map = self.other.clone();
        map.insert("source".into(), self.source.clone());
        map.insert("robot".into(), self.robot.clone());
        map.insert("rate_hz".into(), format!("{}", self.rate_hz));
        if let Some(onset) = self.fall_onset_ns {
            map.insert("fall_onset_ns".into(), onset.to_string());
        }
        if let Some(seed) = self.seed {
            map.insert("seed".into(), seed.to_string());
        }
        if let Some(sigma) = self.sigma {
            map.insert("sigma".into(), format!("{sigma}"));
        }
        map
    }
}

/// One message with its log time.
#[derive(Debug, Clone, PartialEq)]
pub struct Logged<T> {
    pub log_time_ns: i64,
    /// Position among all messages of the file (ties in log time keep it).
    pub file_order: u64,
    pub msg: T,
}

/// A channel seen in a recording.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicInfo {
    pub type_name: String,
    pub message_encoding: String,
    pub count: u64,
}

/// A recording read into memory, typed per topic.
#[derive(Debug, Clone)]
pub struct Recording {
    pub path: PathBuf,
    /// Every metadata record, by name.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// `fall_guard.episode`, parsed (`None` when the record is absent).
    pub episode: Option<EpisodeMeta>,
    pub joint_states: Vec<Logged<JointState>>,
    pub plans: Vec<Logged<JointTrajectory>>,
    pub images: Vec<Logged<CompressedImage>>,
    pub fallen: Vec<Logged<Bool>>,
    /// Every topic in the file (ours and others), with its message count.
    pub topics: BTreeMap<String, TopicInfo>,
}

/// A message of a known topic whose bytes do not decode as its type (a
/// replay rejects it as a live sample, [`Recording::open_for_replay`]).
#[derive(Debug)]
pub struct UndecodableMessage {
    pub topic: String,
    pub log_time_ns: i64,
    /// Position among all messages of the file.
    pub file_order: u64,
    /// [`RecordingError::Decode`], naming the file, topic and byte offset.
    pub error: RecordingError,
}

impl Recording {
    /// Reads and decodes a whole recording; a message that does not decode
    /// is an error.
    pub fn open(path: impl AsRef<Path>) -> Result<Recording, RecordingError> {
        let (rec, undecodable) = Recording::read(path.as_ref(), false)?;
        debug_assert!(undecodable.is_empty());
        Ok(rec)
    }

    /// Reads a whole recording as [`open`](Self::open) does, but keeps
    /// going past a message whose bytes do not decode (bad CDR): each such
    /// message is returned beside the recording, for the replay to reject
    /// at its stream's input boundary. The file's structure (MCAP records,
    /// chunks, schemas, channels, a topic's type, the metadata) must still
    /// be sound.
    pub fn open_for_replay(
        path: impl AsRef<Path>,
    ) -> Result<(Recording, Vec<UndecodableMessage>), RecordingError> {
        Recording::read(path.as_ref(), true)
    }

    fn read(
        path: &Path,
        keep_going: bool,
    ) -> Result<(Recording, Vec<UndecodableMessage>), RecordingError> {
        let raw = RawMcap::read(path)?;
        let mut undecodable = Vec::new();
        let mut rec = Recording {
            path: path.to_path_buf(),
            metadata: raw.metadata.clone(),
            episode: None,
            joint_states: Vec::new(),
            plans: Vec::new(),
            images: Vec::new(),
            fallen: Vec::new(),
            topics: BTreeMap::new(),
        };
        if let Some(map) = raw.metadata.get(EPISODE_METADATA) {
            rec.episode = Some(EpisodeMeta::from_map(path, map)?);
        }
        for (order, m) in raw.messages.iter().enumerate() {
            let channel = raw.channel(path, m)?;
            let type_name = raw.schema_name(channel);
            let info = rec
                .topics
                .entry(channel.topic.clone())
                .or_insert_with(|| TopicInfo {
                    type_name: type_name.to_string(),
                    message_encoding: channel.message_encoding.clone(),
                    count: 0,
                });
            info.count += 1;
            let log_time_ns = i64::try_from(m.log_time).map_err(|_| RecordingError::Corrupt {
                path: path.to_path_buf(),
                offset: m.offset,
                reason: format!("log time {} ns does not fit i64", m.log_time),
            })?;
            let order = order as u64;
            let mut keep = |e: RecordingError| match e {
                RecordingError::Decode { .. } if keep_going => {
                    undecodable.push(UndecodableMessage {
                        topic: channel.topic.clone(),
                        log_time_ns,
                        file_order: order,
                        error: e,
                    });
                    Ok(())
                }
                e => Err(e),
            };
            match channel.topic.as_str() {
                topics::JOINT_STATES => match decode(path, &raw, channel, m, log_time_ns, order) {
                    Ok(s) => rec.joint_states.push(s),
                    Err(e) => keep(e)?,
                },
                topics::PLANNED_TRAJECTORY => {
                    match decode(path, &raw, channel, m, log_time_ns, order) {
                        Ok(s) => rec.plans.push(s),
                        Err(e) => keep(e)?,
                    }
                }
                topics::HEAD_CAMERA => match decode(path, &raw, channel, m, log_time_ns, order) {
                    Ok(s) => rec.images.push(s),
                    Err(e) => keep(e)?,
                },
                topics::GROUND_TRUTH_FALLEN => {
                    match decode(path, &raw, channel, m, log_time_ns, order) {
                        Ok(s) => rec.fallen.push(s),
                        Err(e) => keep(e)?,
                    }
                }
                _ => {}
            }
        }
        tracing::debug!(
            path = %path.display(),
            joint_states = rec.joint_states.len(),
            plans = rec.plans.len(),
            images = rec.images.len(),
            undecodable = undecodable.len(),
            "recording read"
        );
        Ok((rec, undecodable))
    }

    /// The episode metadata, or an error naming the file.
    pub fn episode(&self) -> Result<&EpisodeMeta, RecordingError> {
        self.episode
            .as_ref()
            .ok_or_else(|| RecordingError::MissingMetadata {
                path: self.path.clone(),
            })
    }

    /// Error naming `topic` when the recording has no message on it.
    pub fn require_topic(&self, topic: &str) -> Result<(), RecordingError> {
        if self.topics.get(topic).is_some_and(|t| t.count > 0) {
            Ok(())
        } else {
            Err(RecordingError::MissingTopic {
                path: self.path.clone(),
                topic: topic.to_string(),
            })
        }
    }

    /// First log time of any message, ns.
    pub fn start_ns(&self) -> Option<i64> {
        self.typed_times().min()
    }

    /// Last log time of any message on our four topics, ns.
    pub fn end_ns(&self) -> Option<i64> {
        self.typed_times().max()
    }

    fn typed_times(&self) -> impl Iterator<Item = i64> + '_ {
        self.joint_states
            .iter()
            .map(|m| m.log_time_ns)
            .chain(self.plans.iter().map(|m| m.log_time_ns))
            .chain(self.images.iter().map(|m| m.log_time_ns))
            .chain(self.fallen.iter().map(|m| m.log_time_ns))
    }
}

/// Every message on `topic` of the recording at `path`, decoded as `T`, in
/// file order with its log time (for topics [`Recording`] does not keep,
/// e.g. the daemon's outputs in a `replay --out` file).
pub fn read_topic<T: RosMessage>(
    path: impl AsRef<Path>,
    topic: &str,
) -> Result<Vec<(i64, T)>, RecordingError> {
    let path = path.as_ref();
    let raw = RawMcap::read(path)?;
    let mut out = Vec::new();
    for (order, m) in raw.messages.iter().enumerate() {
        let channel = raw.channel(path, m)?;
        if channel.topic != topic {
            continue;
        }
        let log_time_ns = i64::try_from(m.log_time).map_err(|_| RecordingError::Corrupt {
            path: path.to_path_buf(),
            offset: m.offset,
            reason: format!("log time {} ns does not fit i64", m.log_time),
        })?;
        let s: Logged<T> = decode(path, &raw, channel, m, log_time_ns, order as u64)?;
        out.push((s.log_time_ns, s.msg));
    }
    Ok(out)
}

fn decode<T: RosMessage>(
    path: &Path,
    raw: &RawMcap,
    channel: &records::Channel,
    m: &RawMessage,
    log_time_ns: i64,
    file_order: u64,
) -> Result<Logged<T>, RecordingError> {
    let type_name = raw.schema_name(channel);
    let short = format!("{}/{}", T::PACKAGE, T::NAME);
    if (type_name != T::TYPE_NAME && type_name != short) || channel.message_encoding != "cdr" {
        return Err(RecordingError::WrongType {
            path: path.to_path_buf(),
            topic: channel.topic.clone(),
            expected: T::TYPE_NAME,
            found: type_name.to_string(),
            encoding: channel.message_encoding.clone(),
        });
    }
    let msg = msgs::decode_cdr::<T>(&m.data).map_err(|source| RecordingError::Decode {
        path: path.to_path_buf(),
        topic: channel.topic.clone(),
        offset: m.offset,
        log_time_ns,
        source,
    })?;
    Ok(Logged {
        log_time_ns,
        file_order,
        msg,
    })
}

/// Decompresses one chunk's records (`zstd` or `lz4`, as MCAP writers
/// use), refusing more than the `declared` uncompressed size.
fn decompress_chunk(codec: &str, data: &[u8], declared: u64) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let limit = usize::try_from(declared).map_err(|e| e.to_string())?;
    let mut out = Vec::with_capacity(limit);
    let read = match codec {
        "zstd" => zstd::stream::read::Decoder::new(data)
            .and_then(|d| d.take(declared + 1).read_to_end(&mut out)),
        "lz4" => lz4::Decoder::new(data).and_then(|d| d.take(declared + 1).read_to_end(&mut out)),
        other => return Err(format!("unknown compression {other:?}")),
    };
    read.map_err(|e| e.to_string())?;
    if out.len() != limit {
        return Err(format!(
            "{} uncompressed bytes, {declared} declared",
            out.len()
        ));
    }
    Ok(out)
}

/// A message record, undecoded, with the byte offset of the record that
/// holds it (the chunk's offset for a message inside a chunk).
#[derive(Debug, Clone)]
struct RawMessage {
    channel_id: u16,
    sequence: u32,
    log_time: u64,
    publish_time: u64,
    data: Vec<u8>,
    offset: u64,
}

/// The records of an MCAP file we care about, in file order.
#[derive(Debug, Default)]
struct RawMcap {
    schemas: BTreeMap<u16, (records::SchemaHeader, Vec<u8>)>,
    channels: BTreeMap<u16, records::Channel>,
    messages: Vec<RawMessage>,
    metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// Metadata records in file order (name, map), for rewriting.
    metadata_order: Vec<String>,
    profile: String,
}

/// The largest uncompressed chunk accepted (the writer's chunks are well
/// under 1 MiB; 256 MiB leaves room for any sane writer).
const MAX_CHUNK_BYTES: u64 = 256 << 20;

impl RawMcap {
    fn read(path: &Path) -> Result<RawMcap, RecordingError> {
        let bytes = std::fs::read(path).map_err(|source| RecordingError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(path, &bytes)
    }

    /// Walks the top-level records (tracking offsets), expanding chunks.
    fn parse(path: &Path, bytes: &[u8]) -> Result<RawMcap, RecordingError> {
        let corrupt = |offset: u64, reason: String| RecordingError::Corrupt {
            path: path.to_path_buf(),
            offset,
            reason,
        };
        let truncated = |offset: u64, reason: String| RecordingError::Truncated {
            path: path.to_path_buf(),
            offset,
            reason,
        };
        let magic = mcap::MAGIC;
        if bytes.len() < magic.len() {
            return Err(truncated(
                0,
                format!("file is {} bytes, not an MCAP file", bytes.len()),
            ));
        }
        if &bytes[..magic.len()] != magic {
            return Err(corrupt(0, "not an MCAP file (bad magic bytes)".into()));
        }
        let mut raw = RawMcap::default();
        let mut pos = magic.len();
        loop {
            let offset = pos as u64;
            if bytes.len() - pos < 9 {
                return Err(truncated(
                    offset,
                    format!(
                        "file ends ({} bytes) before the footer; the recording was cut short",
                        bytes.len()
                    ),
                ));
            }
            let opcode = bytes[pos];
            let mut len_bytes = [0u8; 8];
            len_bytes.copy_from_slice(&bytes[pos + 1..pos + 9]);
            let len = u64::from_le_bytes(len_bytes);
            let body_start = pos + 9;
            let available = (bytes.len() - body_start) as u64;
            if len > available {
                return Err(truncated(
                    offset,
                    format!("record (opcode {opcode:#04x}) of {len} bytes runs past the end of the file ({available} bytes left)"),
                ));
            }
            let body = &bytes[body_start..body_start + len as usize];
            pos = body_start + len as usize;
            let record = mcap::read::parse_record(opcode, body)
                .map_err(|e| corrupt(offset, format!("record (opcode {opcode:#04x}): {e}")))?;
            match record {
                Record::Chunk { header, data } => {
                    // The chunk reader allocates the declared size up front:
                    // a corrupted size would abort the process, not fail.
                    let declared = header.uncompressed_size;
                    let plausible = if header.compression.is_empty() {
                        declared == data.len() as u64
                    } else {
                        declared <= MAX_CHUNK_BYTES
                    };
                    if !plausible {
                        return Err(corrupt(
                            offset,
                            format!(
                                "chunk declares {declared} uncompressed bytes ({} compression, {} stored)",
                                if header.compression.is_empty() { "no" } else { header.compression.as_str() },
                                data.len()
                            ),
                        ));
                    }
                    let decompressed;
                    let records: &[u8] = match header.compression.as_str() {
                        "" => &data,
                        codec => {
                            decompressed = decompress_chunk(codec, &data, declared)
                                .map_err(|e| corrupt(offset, format!("{codec} chunk: {e}")))?;
                            &decompressed
                        }
                    };
                    if header.uncompressed_crc != 0
                        && crc32fast::hash(records) != header.uncompressed_crc
                    {
                        return Err(corrupt(
                            offset,
                            "chunk CRC mismatch: its records are damaged".into(),
                        ));
                    }
                    // Walked here, every record length checked against the
                    // chunk (mcap's chunk reader reserves a corrupted
                    // length before checking it).
                    let mut p = 0usize;
                    while p < records.len() {
                        if records.len() - p < 9 {
                            return Err(corrupt(
                                offset,
                                "chunk ends inside a record header".into(),
                            ));
                        }
                        let op = records[p];
                        let mut lb = [0u8; 8];
                        lb.copy_from_slice(&records[p + 1..p + 9]);
                        let n = u64::from_le_bytes(lb);
                        let start = p + 9;
                        if n > (records.len() - start) as u64 {
                            return Err(corrupt(
                                offset,
                                format!("record (opcode {op:#04x}) of {n} bytes runs past the end of its chunk"),
                            ));
                        }
                        if op == 0x06 {
                            return Err(corrupt(offset, "chunk inside a chunk".into()));
                        }
                        let body = &records[start..start + n as usize];
                        p = start + n as usize;
                        let inner = mcap::read::parse_record(op, body).map_err(|e| {
                            corrupt(
                                offset,
                                format!("inside chunk: record (opcode {op:#04x}): {e}"),
                            )
                        })?;
                        raw.take(path, offset, inner)?;
                    }
                }
                Record::Footer(_) => {
                    if &bytes[pos..] != magic {
                        return Err(corrupt(
                            pos as u64,
                            "footer is not followed by the closing magic bytes".into(),
                        ));
                    }
                    return Ok(raw);
                }
                other => raw.take(path, offset, other)?,
            }
        }
    }

    fn take(&mut self, path: &Path, offset: u64, record: Record<'_>) -> Result<(), RecordingError> {
        match record {
            Record::Header(h) => self.profile = h.profile,
            Record::Schema { header, data } => {
                self.schemas
                    .entry(header.id)
                    .or_insert((header, data.into_owned()));
            }
            Record::Channel(c) => {
                self.channels.entry(c.id).or_insert(c);
            }
            Record::Message { header, data } => self.messages.push(RawMessage {
                channel_id: header.channel_id,
                sequence: header.sequence,
                log_time: header.log_time,
                publish_time: header.publish_time,
                data: data.into_owned(),
                offset,
            }),
            Record::Metadata(m) => {
                if !self.metadata.contains_key(&m.name) {
                    self.metadata_order.push(m.name.clone());
                }
                self.metadata.insert(m.name, m.metadata);
            }
            _ => {}
        }
        let _ = path;
        Ok(())
    }

    fn channel(&self, path: &Path, m: &RawMessage) -> Result<&records::Channel, RecordingError> {
        self.channels
            .get(&m.channel_id)
            .ok_or_else(|| RecordingError::Corrupt {
                path: path.to_path_buf(),
                offset: m.offset,
                reason: format!("message refers to unknown channel {}", m.channel_id),
            })
    }

    fn schema_name(&self, channel: &records::Channel) -> &str {
        self.schemas
            .get(&channel.schema_id)
            .map(|(h, _)| h.name.as_str())
            .unwrap_or("")
    }
}

/// Writes a recording: `ros2` profile, `ros2msg` schemas, `cdr` messages,
/// chunked without compression (what `ros2 bag record -s mcap` writes by default).
pub struct RecordingWriter<W: Write + Seek = BufWriter<File>> {
    path: PathBuf,
    writer: Option<mcap::Writer<W>>,
    /// topic -> (channel id, type name)
    channels: HashMap<String, (u16, &'static str)>,
    sequence: u32,
}

impl RecordingWriter<BufWriter<File>> {
    /// Creates (or truncates) the file at `path`.
    pub fn create(path: impl AsRef<Path>) -> Result<Self, RecordingError> {
        let path = path.as_ref();
        let file = File::create(path).map_err(|source| RecordingError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::new(path, BufWriter::new(file))
    }
}

impl<W: Write + Seek> RecordingWriter<W> {
    /// Writes to any seekable sink; `path` only names it in errors.
    pub fn new(path: impl AsRef<Path>, sink: W) -> Result<Self, RecordingError> {
        let path = path.as_ref().to_path_buf();
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("fall-guard ", env!("CARGO_PKG_VERSION")))
            .compression(None)
            .create(sink)
            .map_err(|e| RecordingError::Write {
                path: path.clone(),
                reason: e.to_string(),
            })?;
        Ok(RecordingWriter {
            path,
            writer: Some(writer),
            channels: HashMap::new(),
            sequence: 0,
        })
    }

    fn err(&self, reason: impl std::fmt::Display) -> RecordingError {
        RecordingError::Write {
            path: self.path.clone(),
            reason: reason.to_string(),
        }
    }

    fn inner(&mut self) -> Result<&mut mcap::Writer<W>, RecordingError> {
        self.writer.as_mut().ok_or_else(|| RecordingError::Write {
            path: self.path.clone(),
            reason: "writer already finished".into(),
        })
    }

    /// Declares `topic` with type `T` (done by the first [`write`](Self::write) too).
    pub fn add_topic<T: RosMessage>(&mut self, topic: &str) -> Result<u16, RecordingError> {
        if let Some(&(id, type_name)) = self.channels.get(topic) {
            if type_name != T::TYPE_NAME {
                return Err(self.err(format!(
                    "topic {topic} already has type {type_name}, cannot write {}",
                    T::TYPE_NAME
                )));
            }
            return Ok(id);
        }
        let text = T::schema_text();
        let w = self.inner()?;
        let result = w
            .add_schema(T::TYPE_NAME, "ros2msg", text.as_bytes())
            .and_then(|schema| w.add_channel(schema, topic, "cdr", &BTreeMap::new()));
        let id = result.map_err(|e| self.err(e))?;
        self.channels.insert(topic.to_string(), (id, T::TYPE_NAME));
        Ok(id)
    }

    /// Writes one message at `log_time_ns` (also its publish time).
    pub fn write<T: RosMessage>(
        &mut self,
        topic: &str,
        log_time_ns: i64,
        msg: &T,
    ) -> Result<(), RecordingError> {
        let data = msgs::encode_cdr(msg).map_err(|e| self.err(e))?;
        self.write_cdr::<T>(topic, log_time_ns, &data)
    }

    /// Writes an already CDR-encoded message (header included).
    pub fn write_cdr<T: RosMessage>(
        &mut self,
        topic: &str,
        log_time_ns: i64,
        data: &[u8],
    ) -> Result<(), RecordingError> {
        let channel_id = self.add_topic::<T>(topic)?;
        let time = u64::try_from(log_time_ns)
            .map_err(|_| self.err(format!("{topic}: negative log time {log_time_ns} ns")))?;
        self.sequence = self.sequence.wrapping_add(1);
        let header = records::MessageHeader {
            channel_id,
            sequence: self.sequence,
            log_time: time,
            publish_time: time,
        };
        let w = self.inner()?;
        let result = w.write_to_known_channel(&header, data);
        result.map_err(|e| self.err(e))
    }

    /// Writes a metadata record.
    pub fn write_metadata(
        &mut self,
        name: &str,
        map: BTreeMap<String, String>,
    ) -> Result<(), RecordingError> {
        let w = self.inner()?;
        let result = w.write_metadata(&records::Metadata {
            name: name.to_string(),
            metadata: map,
        });
        result.map_err(|e| self.err(e))
    }

    /// Writes the `fall_guard.episode` record.
    pub fn write_episode(&mut self, meta: &EpisodeMeta) -> Result<(), RecordingError> {
        self.write_metadata(EPISODE_METADATA, meta.to_map())
    }

    /// Ends the current chunk and flushes, so that what is written so far is
    /// readable by a streaming reader even if the process dies.
    pub fn flush(&mut self) -> Result<(), RecordingError> {
        let w = self.inner()?;
        let result = w.flush();
        result.map_err(|e| self.err(e))
    }

    /// Writes the summary and footer, flushes, and returns the sink.
    pub fn finish(mut self) -> Result<W, RecordingError> {
        let mut w = self
            .writer
            .take()
            .ok_or_else(|| self.err("writer already finished"))?;
        w.finish().map_err(|e| self.err(e))?;
        let mut sink = w.into_inner();
        sink.flush().map_err(|e| self.err(e))?;
        Ok(sink)
    }
}

/// Writes the part of the recording at `input` from `from_ns` (included)
/// to `to_ns` (excluded), log time, to `out`: metadata and the messages of
/// that span, unchanged (a walk split by time, `fall-guard-lab finetune`).
/// A falling episode is refused: its onset would name a time the part may
/// not hold. Written as `out.partial`, renamed when complete.
pub fn cut(
    input: impl AsRef<Path>,
    out: impl AsRef<Path>,
    from_ns: i64,
    to_ns: i64,
) -> Result<(), RecordingError> {
    let (input, out) = (input.as_ref(), out.as_ref());
    let rec = Recording::open(input)?;
    if rec.episode()?.fall_onset_ns.is_some() {
        return Err(RecordingError::Label {
            path: input.to_path_buf(),
            reason: "a falling episode is not cut (label the parts instead)".into(),
        });
    }
    copy_span(
        input,
        out,
        from_ns.max(0) as u64..to_ns.max(0) as u64,
        |_, _| Ok(()),
    )
}

/// Marks the fall onset of a recording, in place: `fall_at_s` seconds after
/// the recording's first message (`None`: the episode does not fall).
///
/// Rewrites metadata `fall_guard.episode` (`fall_onset_ns` set or removed;
/// the record must exist) and replaces `/ground_truth/fallen` with one
/// `Bool` per `/joint_states` message (`true` from the onset on). Every other
/// record is copied unchanged. The new file is written next to the old one
/// and renamed over it only when complete: on any error the original stays.
/// Returns the onset in ns on the log clock.
pub fn label(
    path: impl AsRef<Path>,
    fall_at_s: Option<f64>,
) -> Result<Option<i64>, RecordingError> {
    let path = path.as_ref();
    let label_err = |reason: String| RecordingError::Label {
        path: path.to_path_buf(),
        reason,
    };
    let rec = Recording::open(path)?;
    let meta = rec.episode()?.clone();
    let raw = RawMcap::read(path)?;
    let start_ns = rec
        .start_ns()
        .ok_or_else(|| label_err("recording has no messages".into()))?;
    let end_ns = rec.end_ns().unwrap_or(start_ns);
    rec.require_topic(topics::JOINT_STATES)?;
    let onset_ns = match fall_at_s {
        None => None,
        Some(s) => {
            let duration_s = (end_ns - start_ns) as f64 / 1e9;
            if !s.is_finite() || s < 0.0 || s > duration_s {
                return Err(label_err(format!(
                    "--fall-at {s} s is outside the recording (0 ..= {duration_s:.3} s)"
                )));
            }
            Some(start_ns + (s * 1e9).round() as i64)
        }
    };
    let mut meta = meta;
    meta.fall_onset_ns = onset_ns;

    let file_name = path
        .file_name()
        .ok_or_else(|| label_err("not a file path".into()))?
        .to_string_lossy()
        .into_owned();
    let tmp = path.with_file_name(format!(".{file_name}.label-tmp"));
    let result = (|| {
        let mut w = RecordingWriter::create(&tmp)?;
        // metadata first, in the original order, ours replaced
        let mut wrote_episode = false;
        for name in &raw.metadata_order {
            if name == EPISODE_METADATA {
                w.write_episode(&meta)?;
                wrote_episode = true;
            } else if let Some(map) = raw.metadata.get(name) {
                w.write_metadata(name, map.clone())?;
            }
        }
        if !wrote_episode {
            w.write_episode(&meta)?;
        }
        // one Bool per joint state, merged in log-time order with the rest
        let fallen: Vec<(i64, bool)> = rec
            .joint_states
            .iter()
            .map(|m| (m.log_time_ns, onset_ns.is_some_and(|o| m.log_time_ns >= o)))
            .collect();
        let mut next_fallen = 0;
        copy_messages(
            path,
            &raw,
            &mut w,
            &[topics::GROUND_TRUTH_FALLEN],
            0..u64::MAX,
            |w, until| {
                while next_fallen < fallen.len()
                    && until.is_none_or(|t| (fallen[next_fallen].0 as u64) <= t)
                {
                    let (t, data) = fallen[next_fallen];
                    w.write(topics::GROUND_TRUTH_FALLEN, t, &Bool { data })?;
                    next_fallen += 1;
                }
                Ok(())
            },
        )?;
        w.finish()?;
        // the new file must read back before it replaces the old one
        let check = Recording::open(&tmp)?;
        if check.joint_states.len() != rec.joint_states.len()
            || check.fallen.len() != rec.joint_states.len()
        {
            return Err(label_err(
                "rewritten file does not read back the same".into(),
            ));
        }
        std::fs::rename(&tmp, path).map_err(|source| RecordingError::Io {
            path: path.to_path_buf(),
            source,
        })
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result?;
    tracing::info!(path = %path.display(), fall_onset_ns = ?onset_ns, "recording labelled");
    Ok(onset_ns)
}

/// Copies every message of `raw` (read from `path`) into `w` unchanged, in
/// file order, except those on the `skip` topics. Before each copied message
/// at log time `t`, `merge(w, Some(t))` lets the caller write its own
/// messages up to `t`; `merge(w, None)` at the end writes the rest, so that
/// the output stays in log-time order.
fn copy_messages<W: Write + Seek>(
    path: &Path,
    raw: &RawMcap,
    w: &mut RecordingWriter<W>,
    skip: &[&str],
    log_times: std::ops::Range<u64>,
    mut merge: impl FnMut(&mut RecordingWriter<W>, Option<u64>) -> Result<(), RecordingError>,
) -> Result<(), RecordingError> {
    let mut ids: HashMap<u16, u16> = HashMap::new();
    for m in &raw.messages {
        let channel = raw.channel(path, m)?;
        if skip.contains(&channel.topic.as_str()) || !log_times.contains(&m.log_time) {
            continue;
        }
        merge(w, Some(m.log_time))?;
        let new_id = match ids.get(&channel.id) {
            Some(&id) => id,
            None => {
                let inner = w.inner()?;
                let schema_id = match raw.schemas.get(&channel.schema_id) {
                    Some((h, data)) => inner.add_schema(&h.name, &h.encoding, data),
                    None => Ok(0),
                };
                let id = schema_id
                    .and_then(|s| {
                        inner.add_channel(
                            s,
                            &channel.topic,
                            &channel.message_encoding,
                            &channel.metadata,
                        )
                    })
                    .map_err(|e| w.err(e))?;
                ids.insert(channel.id, id);
                id
            }
        };
        let header = records::MessageHeader {
            channel_id: new_id,
            sequence: m.sequence,
            log_time: m.log_time,
            publish_time: m.publish_time,
        };
        let inner = w.inner()?;
        let written = inner.write_to_known_channel(&header, &m.data);
        written.map_err(|e| w.err(e))?;
    }
    merge(w, None)
}

/// Writes a copy of the recording at `input` to `out` with messages of the
/// caller's merged in log-time order (`fall-guard replay --out`: the inputs
/// and the daemon's outputs in one file for Foxglove). Metadata and every
/// input message are copied unchanged. `merge(w, Some(t))` is called before
/// each copied message at log time `t` and must write the caller's messages
/// up to `t`; `merge(w, None)` writes the rest. The file is written as
/// `out.partial` and renamed to `out` only when complete.
pub fn copy_with(
    input: impl AsRef<Path>,
    out: impl AsRef<Path>,
    merge: impl FnMut(&mut RecordingWriter, Option<u64>) -> Result<(), RecordingError>,
) -> Result<(), RecordingError> {
    copy_span(input.as_ref(), out.as_ref(), 0..u64::MAX, merge)
}

/// [`copy_with`] of the messages whose log time lies in `log_times` (and
/// the metadata), written as `out.partial` and renamed when complete.
fn copy_span(
    input: &Path,
    out: &Path,
    log_times: std::ops::Range<u64>,
    merge: impl FnMut(&mut RecordingWriter, Option<u64>) -> Result<(), RecordingError>,
) -> Result<(), RecordingError> {
    let raw = RawMcap::read(input)?;
    let mut partial = out.as_os_str().to_owned();
    partial.push(".partial");
    let partial = PathBuf::from(partial);
    let result = (|| {
        let mut w = RecordingWriter::create(&partial)?;
        for name in &raw.metadata_order {
            if let Some(map) = raw.metadata.get(name) {
                w.write_metadata(name, map.clone())?;
            }
        }
        copy_messages(input, &raw, &mut w, &[], log_times, merge)?;
        w.finish()?;
        std::fs::rename(&partial, out).map_err(|source| RecordingError::Io {
            path: out.to_path_buf(),
            source,
        })
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&partial);
    }
    result
}
