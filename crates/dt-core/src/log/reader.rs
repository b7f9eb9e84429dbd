//! The shocktwin readers: whole file ([`read_log`]) and incremental
//! ([`LogDecoder`]). Both go through the same raw layer and the same
//! message → [`Sample`] decoding, so they cannot disagree.
//!
//! # What is fatal
//!
//! | finding | [`read_log`] | [`LogDecoder`] |
//! | --- | --- | --- |
//! | not MCAP, bad CRC, truncated, record over a size limit | error | error, decoder stops |
//! | `shocktwin.run` missing | error | error if a message comes first |
//! | `asset_id` / `run_id` missing or not `[A-Za-z0-9._-]{1,64}` (nor `.`, `..`) | error | error |
//! | known topic not `json`, its schema not `jsonschema`, or lacking a field or declaring it other than a number | error | error |
//! | one message missing a field / not a number / bad JSON | problem: skipped, counted | `Err` item, decoding goes on |
//! | unknown topic | counted, problem | `LogEvent::Unknown` |
//! | second `shocktwin.run` record | problem, first one used | ignored |
//!
//! A field that is `null`, `NaN`, `Infinity` or `-Infinity` (Python's `json`
//! writes the last three) is read as NaN: a missing sample, kept in its place.

use std::borrow::Cow;
use std::io::Read;
use std::path::Path;

use super::decode::{decode_sample, SampleDecoder};
use super::raw::{RawDecoder, RawEvent, ReadLimits};
use super::{LogError, RunLog, RunMetadata, Sample, RUN_METADATA_NAME};

/// Reads a whole run log file. See the module docs for what is fatal.
pub fn read_log(path: impl AsRef<Path>) -> Result<RunLog, LogError> {
    let path = path.as_ref();
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| LogError::Io {
        file: file.clone(),
        source,
    })?;
    read_log_bytes(&file, &bytes)
}

/// Reads a whole run log held in memory; `source_name` names it in errors.
pub fn read_log_bytes(source_name: &str, bytes: &[u8]) -> Result<RunLog, LogError> {
    let mut raw = RawDecoder::new(source_name, ReadLimits::default());
    raw.end_of_input();
    let mut decoder = SampleDecoder::default();
    let mut log = RunLog::default();
    let mut metadata: Option<RunMetadata> = None;
    let mut problems = Problems::default();
    let mut seen_message = false;
    let mut input = bytes;
    let mut messages = 0usize;
    while let Some(event) = raw.next_event(&mut input) {
        match event? {
            RawEvent::Channel(channel) => decoder.on_channel(source_name, &channel)?,
            RawEvent::Metadata {
                name,
                metadata: map,
            } if name == RUN_METADATA_NAME => {
                if metadata.is_some() {
                    problems.note(format!(
                        "more than one `{RUN_METADATA_NAME}` metadata record; the first is used"
                    ));
                } else {
                    metadata = Some(RunMetadata::from_map(source_name, &map)?);
                    if seen_message {
                        problems.note(super::metadata_after_first_message());
                    }
                }
            }
            RawEvent::Message {
                channel,
                log_time,
                data,
                ..
            } => {
                // Ctrl-C in the bindings ([`crate::cancel`]): the rest is
                // not read, and the caller drops what was.
                if crate::cancel::requested_at(messages) {
                    break;
                }
                messages += 1;
                seen_message = true;
                match decoder.decode(source_name, channel, log_time, data) {
                    Ok(Some(sample)) => log.push(sample),
                    Ok(None) => *log.unknown_topics.entry(channel.topic.clone()).or_default() += 1,
                    Err(err) => problems.message(&err),
                }
            }
            _ => {}
        }
    }
    log.metadata = metadata.ok_or_else(|| LogError::MissingMetadata {
        file: source_name.to_owned(),
        reason: "is missing".into(),
    })?;
    for (topic, n) in &log.unknown_topics {
        problems.note(format!("ignored topic {topic} ({n} messages)"));
    }
    log.problems = problems.into_strings();
    Ok(log)
}

impl RunLog {
    /// Appends a sample to its topic's column.
    pub fn push(&mut self, sample: Sample) {
        match sample {
            Sample::Position { t_ns, position_m } => self.position.push((t_ns, position_m)),
            Sample::Acceleration {
                t_ns,
                a1_mps2,
                a2_mps2,
            } => self.acceleration.push((t_ns, a1_mps2, a2_mps2)),
            Sample::Force { t_ns, force_n } => self.force.push((t_ns, force_n)),
            Sample::TempShock {
                t_ns,
                temperature_c,
            } => self.temp_shock.push((t_ns, temperature_c)),
            Sample::TempAmbient {
                t_ns,
                temperature_c,
            } => self.temp_ambient.push((t_ns, temperature_c)),
            Sample::TruthPressure { t_ns, static_bar } => {
                self.truth_pressure.push((t_ns, static_bar));
            }
            Sample::TruthVelocity { t_ns, velocity_mps } => {
                self.truth_velocity.push((t_ns, velocity_mps));
            }
        }
    }

    /// Number of samples over all topics.
    #[must_use]
    pub fn sample_count(&self) -> usize {
        self.position.len()
            + self.acceleration.len()
            + self.force.len()
            + self.temp_shock.len()
            + self.temp_ambient.len()
            + self.truth_pressure.len()
            + self.truth_velocity.len()
    }

    /// All samples in time order; at equal `t_ns` by topic rank
    /// ([`Sample::topic_rank`]: acceleration first), then in file order.
    #[must_use]
    pub fn samples_sorted(&self) -> Vec<Sample> {
        self.samples_in_order().collect()
    }

    /// The samples of [`RunLog::samples_sorted`], in the same order, without
    /// building the vector: the topics' columns merged as they are read (a
    /// column out of time order is sorted first, stably, in a copy).
    #[must_use]
    pub fn samples_in_order(&self) -> SamplesInOrder<'_> {
        fn in_order<T: Copy>(col: &[T], t: impl Fn(&T) -> i64) -> Cow<'_, [T]> {
            if col.is_sorted_by_key(&t) {
                Cow::Borrowed(col)
            } else {
                let mut v = col.to_vec();
                v.sort_by_key(t); // stable: equal times keep file order
                Cow::Owned(v)
            }
        }
        let pair = |col| in_order(col, |s: &(i64, f64)| s.0);
        SamplesInOrder {
            acceleration: in_order(&self.acceleration, |s| s.0),
            pairs: [
                pair(&self.position),
                pair(&self.force),
                pair(&self.temp_shock),
                pair(&self.temp_ambient),
                pair(&self.truth_pressure),
                pair(&self.truth_velocity),
            ],
            next: [0; 7],
        }
    }

    /// Time of the first message over all sensor topics, ns.
    #[must_use]
    pub fn t0_ns(&self) -> Option<i64> {
        let firsts = [
            self.position.iter().map(|s| s.0).min(),
            self.acceleration.iter().map(|s| s.0).min(),
            self.force.iter().map(|s| s.0).min(),
            self.temp_shock.iter().map(|s| s.0).min(),
            self.temp_ambient.iter().map(|s| s.0).min(),
            self.truth_pressure.iter().map(|s| s.0).min(),
            self.truth_velocity.iter().map(|s| s.0).min(),
        ];
        firsts.into_iter().flatten().min()
    }
}

/// Non-fatal findings, grouped: one line per (topic, field) of skipped
/// messages with a count and the first error, plus free notes.
#[derive(Debug, Default)]
pub(crate) struct Problems {
    notes: Vec<String>,
    /// (topic, field, reason) → (count, first error), in order of first occurrence.
    skipped: Vec<((String, String, String), u64, String)>,
}

impl Problems {
    pub(crate) fn note(&mut self, text: String) {
        self.notes.push(text);
    }

    pub(crate) fn message(&mut self, err: &LogError) {
        let key = match err {
            LogError::Message {
                topic,
                field,
                reason,
                ..
            } => (topic.clone(), field.clone(), reason.clone()),
            other => (String::new(), String::new(), other.to_string()),
        };
        if let Some(entry) = self.skipped.iter_mut().find(|e| e.0 == key) {
            entry.1 += 1;
        } else {
            self.skipped.push((key, 1, err.to_string()));
        }
    }

    pub(crate) fn into_strings(self) -> Vec<String> {
        let mut out: Vec<String> = self
            .skipped
            .into_iter()
            .map(|((topic, field, reason), n, first)| {
                format!("topic {topic} field `{field}` {reason}: {n} message(s) skipped; first: {first}")
            })
            .collect();
        out.extend(self.notes);
        out
    }
}

/// What a [`LogDecoder`] yields.
#[derive(Debug, Clone, PartialEq)]
pub enum LogEvent {
    /// The `shocktwin.run` metadata (validated); comes before any sample.
    Metadata(RunMetadata),
    /// A sensor sample.
    Sample(Sample),
    /// A message on a topic this format does not know (e.g. `/estimate`).
    Unknown {
        /// Its topic.
        topic: String,
        /// Its `log_time`, ns (saturated to `i64::MAX`).
        t_ns: i64,
    },
    /// The MCAP footer: the sender finished the file.
    End,
}

/// What [`LogDecoder::next_undecoded`] yields.
#[derive(Debug, Clone, PartialEq)]
pub enum Undecoded {
    /// Anything but a sensor message, as [`LogDecoder::next_event`] gives it.
    Event(LogEvent),
    /// A sensor message, its text appended to the caller's buffer.
    Sample(SampleMessage),
}

/// A sensor message whose JSON text is not parsed yet
/// ([`LogDecoder::next_undecoded`]): its topic and its log time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SampleMessage {
    rank: u8,
    log_time: u64,
}

impl SampleMessage {
    /// Parses the message's text `data` into a sample, exactly as
    /// [`LogDecoder::next_event`] would have.
    ///
    /// # Errors
    /// [`LogError::Message`], naming `file`, the topic and the field, when
    /// the text lacks one of the topic's fields, one is not a number, or the
    /// log time does not fit in `i64` nanoseconds.
    pub fn decode(self, file: &str, data: &[u8]) -> Result<Sample, LogError> {
        decode_sample(file, self.rank, self.log_time, data)
    }
}

/// Incremental shocktwin log reader for bytes arriving in pieces (a socket).
///
/// ```
/// # use dt_core::log::{LogDecoder, LogEvent};
/// # fn demo(pieces: &[&[u8]]) -> Result<(), dt_core::log::LogError> {
/// let mut decoder = LogDecoder::new("tcp://10.0.0.7:4000");
/// for piece in pieces {
///     decoder.feed(piece);
///     while let Some(event) = decoder.next_event() {
///         match event {
///             Ok(LogEvent::Sample(sample)) => { /* process */ }
///             Ok(_) => {}
///             // one bad message: reported, decoding goes on
///             Err(err) if !err.is_fatal() => eprintln!("{err}"),
///             Err(err) => return Err(err),
///         }
///     }
/// }
/// decoder.finish()
/// # }
/// ```
///
/// See the module docs for what is fatal; after a fatal error
/// `next_event` returns `None`.
pub struct LogDecoder {
    /// The stream's name, for errors (the raw layer's, kept here so that a
    /// message's decoding borrows it instead of copying it).
    name: String,
    raw: RawDecoder,
    samples: SampleDecoder,
    pending: Vec<u8>,
    pos: usize,
    metadata_seen: bool,
    /// The fatal error that stopped decoding, as text.
    failed: Option<String>,
}

impl LogDecoder {
    /// A decoder for a stream called `source_name` (used in errors), with
    /// the default [`ReadLimits`].
    #[must_use]
    pub fn new(source_name: &str) -> Self {
        Self::with_limits(source_name, ReadLimits::default())
    }

    /// A decoder with explicit size limits.
    #[must_use]
    pub fn with_limits(source_name: &str, limits: ReadLimits) -> Self {
        LogDecoder {
            name: source_name.to_owned(),
            raw: RawDecoder::new(source_name, limits),
            samples: SampleDecoder::default(),
            pending: Vec::new(),
            pos: 0,
            metadata_seen: false,
            failed: None,
        }
    }

    /// Hands over the next bytes of the stream.
    pub fn feed(&mut self, bytes: &[u8]) {
        self.compact();
        self.pending.extend_from_slice(bytes);
    }

    /// Drops the bytes already decoded once they are half the buffer.
    fn compact(&mut self) {
        if self.pos > 0 && self.pos * 2 >= self.pending.len() {
            self.pending.drain(..self.pos);
            self.pos = 0;
        }
    }

    /// Reads from `source` straight into the decoder's buffer until `max`
    /// bytes or the end of `source` (what [`LogDecoder::feed`] does with
    /// bytes read elsewhere, without the copy); `Ok(0)` at the end. For
    /// files: on a socket or pipe it waits for all `max` bytes.
    ///
    /// # Errors
    /// The read's error (bytes read before it are kept).
    pub fn feed_from(&mut self, source: &mut impl Read, max: usize) -> std::io::Result<usize> {
        self.compact();
        // `read_to_end` reads into the vector's spare capacity without
        // zeroing it first; `take` bounds it to one read's worth.
        self.pending.reserve(max);
        let max = u64::try_from(max).unwrap_or(u64::MAX);
        source.take(max).read_to_end(&mut self.pending)
    }

    /// The next event, or `None` when more bytes are needed (or after the
    /// end of the file, or a fatal error).
    pub fn next_event(&mut self) -> Option<Result<LogEvent, LogError>> {
        self.next_checked(
            |event| event,
            |file, rank, log_time, data| {
                decode_sample(file, rank, log_time, data).map(LogEvent::Sample)
            },
        )
    }

    /// As [`LogDecoder::next_event`], but a sensor message is not parsed:
    /// its JSON text is appended to `data` and [`Undecoded::Sample`] says
    /// which topic it is and when it was logged; [`SampleMessage::decode`]
    /// parses it later, on another thread if need be (`shocktwin replay`
    /// does so to share the work between two cores). The channel and the
    /// metadata are checked here, as in `next_event`.
    pub fn next_undecoded(&mut self, data: &mut Vec<u8>) -> Option<Result<Undecoded, LogError>> {
        self.next_checked(Undecoded::Event, |_, rank, log_time, text| {
            data.extend_from_slice(text);
            Ok(Undecoded::Sample(SampleMessage { rank, log_time }))
        })
    }

    /// As [`LogDecoder::next_event`] for a run of sensor samples: appends
    /// the samples that come next to `samples` until it holds `max`, and
    /// returns the first event that is not a sample (an error included), or
    /// `None` once `samples` is full or more bytes are needed. The events
    /// and their order are those `next_event` yields; the samples are
    /// written where the caller keeps them instead of being returned one by
    /// one (`shocktwin replay`'s one-core path).
    pub fn next_samples(
        &mut self,
        samples: &mut Vec<Sample>,
        max: usize,
    ) -> Option<Result<LogEvent, LogError>> {
        while samples.len() < max {
            let next = self.next_checked(Some, |file, rank, log_time, data| {
                decode_sample(file, rank, log_time, data).map(|s| {
                    samples.push(s);
                    None
                })
            })?;
            match next {
                Ok(None) => {}
                Ok(Some(event)) => return Some(Ok(event)),
                Err(err) => return Some(Err(err)),
            }
        }
        None
    }

    /// The next item: `wrap` wraps what is not a sensor message, `sample`
    /// makes one of a sensor message (file name, topic rank, log time, text).
    fn next_checked<T>(
        &mut self,
        wrap: impl Fn(LogEvent) -> T,
        sample: impl FnOnce(&str, u8, u64, &[u8]) -> Result<T, LogError>,
    ) -> Option<Result<T, LogError>> {
        if self.failed.is_some() {
            return None;
        }
        let out = self.next_inner(wrap, sample);
        if let Some(Err(err)) = &out {
            if err.is_fatal() {
                self.failed = Some(err.to_string());
            }
        }
        out
    }

    fn next_inner<T>(
        &mut self,
        wrap: impl Fn(LogEvent) -> T,
        sample: impl FnOnce(&str, u8, u64, &[u8]) -> Result<T, LogError>,
    ) -> Option<Result<T, LogError>> {
        let file = self.name.as_str();
        loop {
            let mut input = &self.pending[self.pos..];
            let before = input.len();
            let event = self.raw.next_event(&mut input);
            self.pos += before - input.len();
            let event = match event? {
                Ok(event) => event,
                Err(err) => return Some(Err(err)),
            };
            match event {
                RawEvent::Channel(channel) => {
                    if let Err(err) = self.samples.on_channel(file, &channel) {
                        return Some(Err(err));
                    }
                }
                RawEvent::Metadata { name, metadata }
                    if name == RUN_METADATA_NAME && !self.metadata_seen =>
                {
                    self.metadata_seen = true;
                    return Some(
                        RunMetadata::from_map(file, &metadata).map(|m| wrap(LogEvent::Metadata(m))),
                    );
                }
                RawEvent::Message {
                    channel,
                    log_time,
                    data,
                    ..
                } => {
                    if !self.metadata_seen {
                        return Some(Err(LogError::MissingMetadata {
                            file: file.to_owned(),
                            reason: format!(
                                "does not come before the first message (topic `{}`)",
                                channel.topic
                            ),
                        }));
                    }
                    let Some(rank) = self.samples.rank(channel) else {
                        return Some(Ok(wrap(LogEvent::Unknown {
                            topic: channel.topic.clone(),
                            t_ns: i64::try_from(log_time).unwrap_or(i64::MAX),
                        })));
                    };
                    return Some(sample(file, rank, log_time, data));
                }
                RawEvent::Other {
                    opcode: mcap::records::op::FOOTER,
                } => return Some(Ok(wrap(LogEvent::End))),
                _ => {}
            }
        }
    }

    /// Whether every byte fed so far has been decoded and ends at a record
    /// boundary or after the end magic: a stream that stopped here would
    /// [`finish`](Self::finish) without being truncated.
    #[must_use]
    pub fn at_record_boundary(&self) -> bool {
        self.pos >= self.pending.len() && self.raw.at_record_boundary()
    }

    /// Ends the stream: drains what is left (discarding events the caller
    /// did not take) and fails if the stream stopped in the middle of a
    /// record, or on a fatal error found in what was left. A stream that
    /// stops between records (no footer yet) is not an error.
    pub fn finish(mut self) -> Result<(), LogError> {
        while let Some(event) = self.next_event() {
            if let Err(err) = event {
                if err.is_fatal() {
                    return Err(err);
                }
            }
        }
        if let Some(reason) = self.failed {
            return Err(LogError::Mcap {
                file: self.raw.source_name().to_owned(),
                reason: format!("decoding had stopped at an earlier error: {reason}"),
            });
        }
        if self.pos < self.pending.len() || !self.raw.at_record_boundary() {
            return Err(LogError::Truncated {
                file: self.raw.source_name().to_owned(),
                reason: format!(
                    "the stream ended in the middle of a record ({} bytes read)",
                    self.raw.bytes_consumed()
                ),
            });
        }
        Ok(())
    }
}

impl LogError {
    /// Whether reading cannot go on after this error. Only an undecodable
    /// message ([`LogError::Message`]) is not fatal.
    #[must_use]
    pub fn is_fatal(&self) -> bool {
        !matches!(self, LogError::Message { .. })
    }
}

/// Iterator of [`RunLog::samples_in_order`]: a merge of the topics' columns
/// by `(t_ns, topic rank)`, each column in time order.
#[derive(Debug)]
pub struct SamplesInOrder<'a> {
    acceleration: Cow<'a, [(i64, f64, f64)]>,
    /// Position, force, shock and ambient temperature, truth pressure and
    /// velocity: topic ranks 1 to 6.
    pairs: [Cow<'a, [(i64, f64)]>; 6],
    /// Next index in each column, by topic rank.
    next: [usize; 7],
}

impl SamplesInOrder<'_> {
    fn head_t(&self, rank: usize) -> Option<i64> {
        if rank == 0 {
            self.acceleration.get(self.next[0]).map(|s| s.0)
        } else {
            self.pairs[rank - 1].get(self.next[rank]).map(|s| s.0)
        }
    }
}

impl Iterator for SamplesInOrder<'_> {
    type Item = Sample;

    fn next(&mut self) -> Option<Sample> {
        // the earliest head; at equal times the lowest rank (strict `<`)
        let mut best: Option<(i64, u8)> = None;
        for rank in 0..7u8 {
            if let Some(t) = self.head_t(usize::from(rank)) {
                if best.is_none_or(|(bt, _)| t < bt) {
                    best = Some((t, rank));
                }
            }
        }
        let (t_ns, rank) = best?;
        let r = usize::from(rank);
        let i = self.next[r];
        self.next[r] += 1;
        let (v0, v1) = if r == 0 {
            let (_, a1, a2) = self.acceleration[i];
            (a1, a2)
        } else {
            (self.pairs[r - 1][i].1, f64::NAN)
        };
        Some(Sample::from_rank(rank, t_ns, v0, v1))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.acceleration.len() - self.next[0]
            + self
                .pairs
                .iter()
                .zip(&self.next[1..])
                .map(|(c, &i)| c.len() - i)
                .sum::<usize>();
        (left, Some(left))
    }
}

impl ExactSizeIterator for SamplesInOrder<'_> {}
