//! The run-log writer (SPEC §2).

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::Path;

use super::{json_schema, LogError, RunMetadata, Sample, RUN_METADATA_NAME, TOPICS};

/// Chunk compression of a written log (in configuration files: `"zstd"`,
/// `"lz4"`, `"none"`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Compression {
    /// zstd level 1 (the default): the smallest files, fast enough.
    #[default]
    Zstd,
    /// lz4: less CPU per message, larger files.
    Lz4,
    /// Uncompressed chunks.
    None,
}

/// Options of [`LogWriter`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WriteOptions {
    /// Chunk compression (ignored when `chunk_size` is `None`).
    pub compression: Compression,
    /// Target uncompressed chunk size in bytes; `None` writes no chunks at
    /// all (messages directly in the data section, uncompressed).
    pub chunk_size: Option<u64>,
}

impl Default for WriteOptions {
    /// zstd chunks of about 1 MiB.
    fn default() -> Self {
        WriteOptions {
            compression: Compression::Zstd,
            chunk_size: Some(1 << 20),
        }
    }
}

/// Number of sensor topics (`TOPICS.len()`).
const N_TOPICS: usize = TOPICS.len();

/// Writes one run as a shocktwin log v1 MCAP file.
///
/// The `shocktwin.run` metadata record is written by the constructor, before
/// any message. Each topic gets one channel (message encoding `json`, schema
/// encoding `jsonschema`), created when its first message is written.
/// `log_time` = `publish_time` = `t_ns`. zstd runs single-threaded: callers
/// parallelise across runs.
///
/// ```
/// use dt_core::log::{LogWriter, RunMetadata, Sample, WriteOptions};
/// # fn main() -> Result<(), dt_core::log::LogError> {
/// # let dir = std::env::temp_dir().join(format!("dt-core-doc-{}", std::process::id()));
/// # std::fs::create_dir_all(&dir).unwrap();
/// let meta = RunMetadata {
///     asset_id: "shock-001".into(),
///     run_id: "p12-f2".into(),
///     charge_pressure_bar: Some(12.0),
///     ..RunMetadata::default()
/// };
/// let mut w = LogWriter::create(dir.join("run.mcap"), &meta, WriteOptions::default())?;
/// w.write_sample(&Sample::Position { t_ns: 0, position_m: 0.01 })?;
/// w.write_sample(&Sample::Acceleration { t_ns: 1_000_000, a1_mps2: 0.5, a2_mps2: -0.1 })?;
/// // any serde type, e.g. estimator output:
/// w.write_json("/estimate", r#"{"type":"object"}"#, 20_000_000, &serde_json::json!({"pressure_bar": 11.9}))?;
/// w.finish()?;
/// # std::fs::remove_dir_all(&dir).unwrap();
/// # Ok(()) }
/// ```
pub struct LogWriter<W: Write + Seek> {
    mcap: mcap::Writer<W>,
    file: String,
    /// Channel id and next sequence number per sensor topic (by rank).
    sample_channels: [Option<(u16, u32)>; N_TOPICS],
    /// Channel id and next sequence number per `write_json` topic.
    json_channels: HashMap<String, (u16, u32)>,
    buf: Vec<u8>,
    float: zmij::Buffer,
}

impl LogWriter<BufWriter<File>> {
    /// Creates (truncates) the file at `path` and writes the header and the
    /// `shocktwin.run` metadata.
    pub fn create(
        path: impl AsRef<Path>,
        metadata: &RunMetadata,
        options: WriteOptions,
    ) -> Result<Self, LogError> {
        let path = path.as_ref();
        let file = path.display().to_string();
        let f = File::create(path).map_err(|source| LogError::Io {
            file: file.clone(),
            source,
        })?;
        Self::with_name(
            BufWriter::with_capacity(1 << 16, f),
            file,
            metadata,
            options,
        )
    }
}

impl<W: Write + Seek> LogWriter<W> {
    /// Writes a log into any seekable writer (e.g. `Cursor<Vec<u8>>`).
    pub fn new(w: W, metadata: &RunMetadata, options: WriteOptions) -> Result<Self, LogError> {
        Self::with_name(w, "<memory>".into(), metadata, options)
    }

    fn with_name(
        w: W,
        file: String,
        metadata: &RunMetadata,
        options: WriteOptions,
    ) -> Result<Self, LogError> {
        for (key, value) in [
            ("asset_id", &metadata.asset_id),
            ("run_id", &metadata.run_id),
        ] {
            if !super::is_valid_id(value) {
                return Err(LogError::InvalidMetadata {
                    file,
                    key: key.into(),
                    reason: format!("value {value:?} is not {}", super::ID_FORMAT),
                });
            }
        }
        let compression = match options.compression {
            Compression::Zstd => Some(mcap::Compression::Zstd),
            Compression::Lz4 => Some(mcap::Compression::Lz4),
            Compression::None => None,
        };
        let mcap_options = mcap::WriteOptions::new()
            .compression(compression)
            .compression_threads(0)
            .compression_level(1)
            .use_chunks(options.chunk_size.is_some())
            .chunk_size(options.chunk_size)
            .library(concat!("shocktwin dt-core ", env!("CARGO_PKG_VERSION")));
        let mut mcap = mcap_options
            .create(w)
            .map_err(|e| LogError::mcap(&file, &e))?;
        mcap.write_metadata(&mcap::records::Metadata {
            name: RUN_METADATA_NAME.into(),
            metadata: metadata.to_map(),
        })
        .map_err(|e| LogError::mcap(&file, &e))?;
        Ok(LogWriter {
            mcap,
            file,
            sample_channels: [None; N_TOPICS],
            json_channels: HashMap::new(),
            buf: Vec::with_capacity(128),
            float: zmij::Buffer::new(),
        })
    }

    /// Writes one sensor sample on its topic. A NaN or infinite value is
    /// written as JSON `null` (a missing sample).
    pub fn write_sample(&mut self, sample: &Sample) -> Result<(), LogError> {
        let rank = sample.topic_rank() as usize;
        let spec = &TOPICS[rank];
        let t_ns = sample.t_ns();
        let log_time = u64::try_from(t_ns).map_err(|_| LogError::NegativeTime {
            file: self.file.clone(),
            topic: spec.topic.into(),
            t_ns,
        })?;
        let (channel_id, sequence) = if let Some(c) = self.sample_channels[rank] {
            c
        } else {
            let schema = json_schema(spec);
            let id = self.add_channel(spec.topic, spec.schema_name, &schema)?;
            (id, 0)
        };
        self.sample_channels[rank] = Some((channel_id, sequence.wrapping_add(1)));

        self.buf.clear();
        match *sample {
            Sample::Acceleration {
                a1_mps2, a2_mps2, ..
            } => {
                self.buf.extend_from_slice(b"{\"a1_mps2\":");
                push_f64(&mut self.buf, &mut self.float, a1_mps2);
                self.buf.extend_from_slice(b",\"a2_mps2\":");
                push_f64(&mut self.buf, &mut self.float, a2_mps2);
            }
            Sample::Position { position_m: v, .. } => {
                self.buf.extend_from_slice(b"{\"position_m\":");
                push_f64(&mut self.buf, &mut self.float, v);
            }
            Sample::Force { force_n: v, .. } => {
                self.buf.extend_from_slice(b"{\"force_n\":");
                push_f64(&mut self.buf, &mut self.float, v);
            }
            Sample::TempShock {
                temperature_c: v, ..
            }
            | Sample::TempAmbient {
                temperature_c: v, ..
            } => {
                self.buf.extend_from_slice(b"{\"temperature_c\":");
                push_f64(&mut self.buf, &mut self.float, v);
            }
            Sample::TruthPressure { static_bar: v, .. } => {
                self.buf.extend_from_slice(b"{\"static_bar\":");
                push_f64(&mut self.buf, &mut self.float, v);
            }
            Sample::TruthVelocity {
                velocity_mps: v, ..
            } => {
                self.buf.extend_from_slice(b"{\"velocity_mps\":");
                push_f64(&mut self.buf, &mut self.float, v);
            }
        }
        self.buf.push(b'}');
        self.write_raw(spec.topic, channel_id, sequence, log_time)
    }

    /// Writes any serde value as a JSON message on `topic` (e.g. `/estimate`).
    /// The first message on a topic creates its channel with `schema_json`
    /// (a JSON schema, encoding `jsonschema`); later calls ignore it.
    /// Non-finite floats are written as `null` (`serde_json`'s behaviour).
    pub fn write_json<T: serde::Serialize + ?Sized>(
        &mut self,
        topic: &str,
        schema_json: &str,
        t_ns: i64,
        value: &T,
    ) -> Result<(), LogError> {
        let log_time = u64::try_from(t_ns).map_err(|_| LogError::NegativeTime {
            file: self.file.clone(),
            topic: topic.into(),
            t_ns,
        })?;
        let (channel_id, sequence) = if let Some(c) = self.json_channels.get_mut(topic) {
            let out = *c;
            c.1 = c.1.wrapping_add(1);
            out
        } else {
            let id = self.add_channel(topic, topic.trim_start_matches('/'), schema_json)?;
            self.json_channels.insert(topic.to_owned(), (id, 1));
            (id, 0)
        };
        self.buf.clear();
        serde_json::to_writer(&mut self.buf, value).map_err(|e| LogError::Serialize {
            file: self.file.clone(),
            topic: topic.into(),
            reason: e.to_string(),
        })?;
        self.write_raw(topic, channel_id, sequence, log_time)
    }

    /// Finishes the file (last chunk, summary, footer), flushes and returns
    /// the underlying writer.
    pub fn finish(mut self) -> Result<W, LogError> {
        self.mcap
            .finish()
            .map_err(|e| LogError::mcap(&self.file, &e))?;
        let file = std::mem::take(&mut self.file);
        let mut w = self.mcap.into_inner();
        w.flush().map_err(|source| LogError::Io { file, source })?;
        Ok(w)
    }

    fn add_channel(
        &mut self,
        topic: &str,
        schema_name: &str,
        schema: &str,
    ) -> Result<u16, LogError> {
        let schema_id = self
            .mcap
            .add_schema(schema_name, "jsonschema", schema.as_bytes())
            .map_err(|e| LogError::mcap(&self.file, &e))?;
        self.mcap
            .add_channel(schema_id, topic, "json", &BTreeMap::new())
            .map_err(|e| LogError::mcap(&self.file, &e))
    }

    fn write_raw(
        &mut self,
        _topic: &str,
        channel_id: u16,
        sequence: u32,
        log_time: u64,
    ) -> Result<(), LogError> {
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence,
            log_time,
            publish_time: log_time,
        };
        self.mcap
            .write_to_known_channel(&header, &self.buf)
            .map_err(|e| LogError::mcap(&self.file, &e))
    }
}

/// Appends `v` as a JSON number (shortest round-trip form), or `null` when
/// it is not finite.
fn push_f64(buf: &mut Vec<u8>, float: &mut zmij::Buffer, v: f64) {
    if v.is_finite() {
        buf.extend_from_slice(float.format_finite(v).as_bytes());
    } else {
        buf.extend_from_slice(b"null");
    }
}
