//! `shocktwin inspect`: what an MCAP file holds and what it lacks to be a
//! shocktwin log. Any valid MCAP inspects without error; only a broken or
//! non-MCAP file is an `Err`.

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

use super::decode::SampleDecoder;
use super::raw::{RawDecoder, RawEvent, ReadLimits};
use super::reader::Problems;
use super::{topic, LogError, RunMetadata, RUN_METADATA_NAME, TOPICS};

/// One channel of an inspected file.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ChannelReport {
    /// Channel id.
    pub id: u16,
    /// Topic.
    pub topic: String,
    /// Message encoding.
    pub message_encoding: String,
    /// Schema name, empty without a schema.
    pub schema_name: String,
    /// Schema encoding, empty without a schema.
    pub schema_encoding: String,
    /// Messages on the channel.
    pub message_count: u64,
    /// First and last `log_time`, ns.
    pub log_time_range_ns: Option<(u64, u64)>,
    /// The longest interval between consecutive messages (file order), ns.
    pub largest_interval_ns: u64,
    /// The previous message's `log_time`.
    #[serde(skip)]
    prev_ns: Option<u64>,
    /// Intervals longer than each of [`GAP_EDGES_S`].
    #[serde(skip)]
    longer_than: [u64; GAP_EDGES_S.len()],
}

/// Interval lengths (s) counted, to name a channel's gaps against its own
/// mean interval without keeping every interval.
const GAP_EDGES_S: [f64; 10] = [0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0];

/// An interval this many times the channel's mean interval (or more) is a
/// gap.
const GAP_TIMES_MEAN: f64 = 5.0;

impl ChannelReport {
    fn on_message(&mut self, log_time: u64) {
        if let Some(prev) = self.prev_ns {
            let dt = log_time.saturating_sub(prev);
            self.largest_interval_ns = self.largest_interval_ns.max(dt);
            let dt_s = dt as f64 * 1e-9;
            for (edge, n) in GAP_EDGES_S.iter().zip(&mut self.longer_than) {
                if dt_s > *edge {
                    *n += 1;
                }
            }
        }
        self.prev_ns = Some(log_time);
    }

    /// The channel's gaps: `(edge_s, count)`, the intervals longer than the
    /// first counted length at least [`GAP_TIMES_MEAN`] times the mean
    /// interval; `None` without any.
    #[must_use]
    pub fn gaps(&self) -> Option<(f64, u64)> {
        let mean_s = 1.0 / self.rate_hz()?;
        let k = GAP_EDGES_S
            .iter()
            .position(|e| *e >= GAP_TIMES_MEAN * mean_s)?;
        (self.longer_than[k] > 0).then(|| (GAP_EDGES_S[k], self.longer_than[k]))
    }

    fn new(channel: &super::raw::RawChannel) -> Self {
        ChannelReport {
            id: channel.id,
            topic: channel.topic.clone(),
            message_encoding: channel.message_encoding.clone(),
            schema_name: channel
                .schema
                .as_ref()
                .map(|s| s.name.clone())
                .unwrap_or_default(),
            schema_encoding: channel
                .schema
                .as_ref()
                .map(|s| s.encoding.clone())
                .unwrap_or_default(),
            message_count: 0,
            log_time_range_ns: None,
            largest_interval_ns: 0,
            prev_ns: None,
            longer_than: [0; GAP_EDGES_S.len()],
        }
    }

    /// Mean message rate in Hz: `(count - 1) / (last - first)` (intervals
    /// over the span), `None` with fewer than two messages or a zero span.
    #[must_use]
    pub fn rate_hz(&self) -> Option<f64> {
        let (first, last) = self.log_time_range_ns?;
        (self.message_count >= 2 && last > first)
            .then(|| (self.message_count - 1) as f64 / ((last - first) as f64 * 1e-9))
    }
}

/// What [`inspect`] found. Serialises to JSON (`shocktwin inspect --json`)
/// with the derived figures (`duration_s`, each channel's `rate_hz`) added
/// by [`InspectReport::to_json`].
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize)]
pub struct InspectReport {
    /// The file.
    pub file: String,
    /// File size, bytes.
    pub size_bytes: u64,
    /// Header profile.
    pub profile: String,
    /// Header library.
    pub library: String,
    /// Channels by id.
    pub channels: Vec<ChannelReport>,
    /// Messages over all channels.
    pub message_count: u64,
    /// First and last `log_time` over all messages, ns.
    pub log_time_range_ns: Option<(u64, u64)>,
    /// Metadata records in file order.
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    /// The parsed `shocktwin.run` record, if present and valid.
    pub run: Option<RunMetadata>,
    /// Chunks by compression (`none` for uncompressed).
    pub chunks: BTreeMap<String, u64>,
    /// Attachment records.
    pub attachments: u64,
    /// Whether the file has a summary section (a footer pointing to one).
    pub has_summary: bool,
    /// What the file lacks to be a shocktwin log, and other non-fatal findings.
    pub problems: Vec<String>,
}

impl InspectReport {
    /// Span of all messages in seconds (0 without messages).
    #[must_use]
    pub fn duration_s(&self) -> f64 {
        self.log_time_range_ns
            .map_or(0.0, |(a, b)| (b - a) as f64 * 1e-9)
    }

    /// The report as JSON, with `duration_s` and each channel's `rate_hz`.
    #[must_use]
    pub fn to_json(&self) -> serde_json::Value {
        let mut value = serde_json::to_value(self).unwrap_or_default();
        value["duration_s"] = self.duration_s().into();
        if let Some(channels) = value["channels"].as_array_mut() {
            for (c, report) in channels.iter_mut().zip(&self.channels) {
                c["rate_hz"] = report.rate_hz().into();
            }
        }
        value
    }

    /// Messages on `topic` over all its channels.
    #[must_use]
    pub fn count(&self, topic: &str) -> u64 {
        self.channels
            .iter()
            .filter(|c| c.topic == topic)
            .map(|c| c.message_count)
            .sum()
    }
}

/// Inspects a file (see the module docs).
pub fn inspect(path: impl AsRef<Path>) -> Result<InspectReport, LogError> {
    let path = path.as_ref();
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| LogError::Io {
        file: file.clone(),
        source,
    })?;
    inspect_bytes(&file, &bytes)
}

/// Inspects a file held in memory; `source_name` names it.
pub fn inspect_bytes(source_name: &str, bytes: &[u8]) -> Result<InspectReport, LogError> {
    let mut report = InspectReport {
        file: source_name.to_owned(),
        size_bytes: bytes.len() as u64,
        ..InspectReport::default()
    };
    let mut raw = RawDecoder::new(source_name, ReadLimits::default());
    raw.end_of_input();
    let mut decoder = SampleDecoder::default();
    let mut problems = Problems::default();
    let mut channels: BTreeMap<u16, ChannelReport> = BTreeMap::new();
    let mut run_records = 0;
    let mut input = bytes;
    while let Some(event) = raw.next_event(&mut input) {
        match event? {
            RawEvent::Header { profile, library } => {
                report.profile = profile;
                report.library = library;
            }
            RawEvent::Channel(channel) => {
                // A channel's record comes again in the summary: checked
                // (and its problem said) once.
                if channels.contains_key(&channel.id) {
                    continue;
                }
                if let Err(err) = decoder.on_channel(source_name, &channel) {
                    problems.note(err.to_string());
                }
                channels.insert(channel.id, ChannelReport::new(&channel));
            }
            RawEvent::Message {
                channel,
                log_time,
                data,
                ..
            } => {
                report.message_count += 1;
                report.log_time_range_ns = Some(widen(report.log_time_range_ns, log_time));
                if let Some(c) = channels.get_mut(&channel.id) {
                    c.message_count += 1;
                    c.log_time_range_ns = Some(widen(c.log_time_range_ns, log_time));
                    c.on_message(log_time);
                }
                if let Err(err) = decoder.decode(source_name, channel, log_time, data) {
                    problems.message(&err);
                }
            }
            RawEvent::Metadata { name, metadata } => {
                if name == RUN_METADATA_NAME {
                    run_records += 1;
                    if run_records == 1 && report.message_count > 0 {
                        // as `read_log` says it (a helper's audit: inspect
                        // called such a file complete)
                        problems.note(super::metadata_after_first_message());
                    }
                    if report.run.is_none() {
                        match RunMetadata::from_map(source_name, &metadata) {
                            Ok(run) => report.run = Some(run),
                            Err(err) => problems.note(err.to_string()),
                        }
                    }
                }
                report.metadata.push((name, metadata));
            }
            RawEvent::Other { opcode } => match opcode {
                mcap::records::op::ATTACHMENT => report.attachments += 1,
                mcap::records::op::STATISTICS
                | mcap::records::op::CHUNK_INDEX
                | mcap::records::op::SUMMARY_OFFSET
                | mcap::records::op::METADATA_INDEX
                | mcap::records::op::ATTACHMENT_INDEX => report.has_summary = true,
                _ => {}
            },
            RawEvent::Schema(_) => {}
        }
    }
    report.chunks = raw
        .chunks()
        .iter()
        .map(|(k, v)| {
            (
                if k.is_empty() {
                    "none".into()
                } else {
                    k.clone()
                },
                *v,
            )
        })
        .collect();
    report.channels = channels.into_values().collect();

    lacks(&report, run_records, &mut problems);
    report.problems = problems.into_strings();
    Ok(report)
}

/// Notes what the file lacks to be a shocktwin log.
fn lacks(report: &InspectReport, run_records: u32, problems: &mut Problems) {
    if run_records == 0 {
        problems.note(format!(
            "no `{RUN_METADATA_NAME}` metadata record: not a shocktwin log"
        ));
    } else if run_records > 1 {
        problems.note(format!(
            "{run_records} `{RUN_METADATA_NAME}` records; the first is used"
        ));
    }
    for spec in &TOPICS {
        let truth = spec.topic == topic::TRUTH_PRESSURE || spec.topic == topic::TRUTH_VELOCITY;
        if !truth && report.count(spec.topic) == 0 {
            problems.note(format!("no messages on {} (sensor missing)", spec.topic));
        }
    }
    let mut unknown: BTreeMap<&str, u64> = BTreeMap::new();
    for c in &report.channels {
        if super::topic_spec(&c.topic).is_none() && c.message_count > 0 {
            *unknown.entry(c.topic.as_str()).or_default() += c.message_count;
        }
    }
    for (topic, n) in unknown {
        problems.note(format!("ignored topic {topic} ({n} messages)"));
    }
    for c in &report.channels {
        if let Some((edge_s, n)) = c.gaps() {
            problems.note(format!(
                "{}: {n} gap(s) longer than {edge_s} s (the longest {:.3} s); its rate above is \
                 over the whole span, gaps included",
                c.topic,
                c.largest_interval_ns as f64 * 1e-9
            ));
        }
    }
}

fn widen(range: Option<(u64, u64)>, t: u64) -> (u64, u64) {
    match range {
        None => (t, t),
        Some((a, b)) => (a.min(t), b.max(t)),
    }
}

impl fmt::Display for InspectReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "file:      {} ({} bytes)", self.file, self.size_bytes)?;
        writeln!(
            f,
            "library:   {}{}",
            if self.library.is_empty() {
                "(none)"
            } else {
                &self.library
            },
            if self.profile.is_empty() {
                String::new()
            } else {
                format!("  profile: {}", self.profile)
            }
        )?;
        let chunks = if self.chunks.is_empty() {
            "none (unchunked)".to_owned()
        } else {
            self.chunks
                .iter()
                .map(|(k, v)| format!("{v} {k}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        writeln!(
            f,
            "chunks:    {chunks}; summary: {}; attachments: {}",
            if self.has_summary { "yes" } else { "no" },
            self.attachments
        )?;
        writeln!(f, "messages:  {}", self.message_count)?;
        match self.log_time_range_ns {
            Some((a, b)) => writeln!(
                f,
                "duration:  {:.3} s (log_time {a} .. {b} ns)",
                self.duration_s()
            )?,
            None => writeln!(f, "duration:  0 s (no messages)")?,
        }
        writeln!(f, "channels:  {}", self.channels.len())?;
        for c in &self.channels {
            let rate = c
                .rate_hz()
                .map_or_else(|| "-".to_owned(), |r| format!("{r:.3} Hz"));
            let schema = if c.schema_name.is_empty() && c.schema_encoding.is_empty() {
                "(no schema)".to_owned()
            } else {
                format!("{} [{}]", c.schema_name, c.schema_encoding)
            };
            writeln!(
                f,
                "  {:>3} {:<24} {:>10} msgs {:>14}  {} / {}",
                c.id, c.topic, c.message_count, rate, c.message_encoding, schema
            )?;
        }
        writeln!(f, "metadata:  {}", self.metadata.len())?;
        for (name, map) in &self.metadata {
            writeln!(f, "  {name}")?;
            for (k, v) in map {
                writeln!(f, "    {k} = {v}")?;
            }
        }
        if self.problems.is_empty() {
            writeln!(f, "problems:  none (a complete shocktwin log)")?;
        } else {
            writeln!(f, "problems:  {}", self.problems.len())?;
            for p in &self.problems {
                writeln!(f, "  - {p}")?;
            }
        }
        Ok(())
    }
}
