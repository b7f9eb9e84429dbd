//! Generic MCAP layer: records of any MCAP file, shocktwin or not.
//!
//! [`RawDecoder`] is an incremental (sans-io) reader built on the `mcap`
//! crate's [`mcap::sans_io::LinearReader`]: it accepts chunked
//! or unchunked files, zstd, lz4 or uncompressed chunks, with or without
//! indexes and summary. It decodes the records a reader needs (header,
//! schemas, channels, messages, metadata) with bounds-checked parsers of its
//! own and reports the others by opcode.
//!
//! **Untrusted lengths.** Before the bytes of a top-level record reach the
//! MCAP reader, a scanner checks its declared length against
//! [`ReadLimits::max_record_bytes`] and, for a chunk, its declared
//! uncompressed size against [`ReadLimits::max_chunk_uncompressed_bytes`];
//! records inside chunks are checked by the MCAP reader against
//! `max_record_bytes`. A record over a limit is an error
//! ([`LogError::TooLarge`]) and nothing of its declared size is allocated.
//! Record data is only ever buffered as it arrives.

use std::collections::BTreeMap;
use std::sync::Arc;

use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::LogError;

/// Limits on declared sizes in an untrusted file or stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// Largest accepted record (top level, including a whole chunk, or inside a chunk).
    pub max_record_bytes: u64,
    /// Largest accepted uncompressed size a chunk may declare.
    pub max_chunk_uncompressed_bytes: u64,
}

impl Default for ReadLimits {
    /// 256 MiB records, 1 GiB uncompressed chunks.
    fn default() -> Self {
        ReadLimits {
            max_record_bytes: 256 << 20,
            max_chunk_uncompressed_bytes: 1 << 30,
        }
    }
}

/// A schema record.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawSchema {
    /// Schema id (non-zero).
    pub id: u16,
    /// Schema name.
    pub name: String,
    /// Schema encoding, e.g. `jsonschema`.
    pub encoding: String,
    /// Schema data.
    pub data: Vec<u8>,
}

/// A channel record, with its schema resolved.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawChannel {
    /// Channel id.
    pub id: u16,
    /// Topic name.
    pub topic: String,
    /// Message encoding, e.g. `json`.
    pub message_encoding: String,
    /// Channel metadata.
    pub metadata: BTreeMap<String, String>,
    /// The channel's schema, `None` for schema id 0.
    pub schema: Option<Arc<RawSchema>>,
}

/// One record of an MCAP file, as [`RawDecoder::next_event`] yields it.
#[derive(Debug)]
pub enum RawEvent<'a> {
    /// The header record.
    Header {
        /// Profile, e.g. `ros2` or empty.
        profile: String,
        /// Writing library.
        library: String,
    },
    /// A schema record (also each repeat of one in the summary section).
    Schema(Arc<RawSchema>),
    /// A channel record (also each repeat of one in the summary section).
    Channel(Arc<RawChannel>),
    /// A message, on a channel seen before it.
    Message {
        /// The message's channel.
        channel: &'a RawChannel,
        /// Sequence number.
        sequence: u32,
        /// Log time, ns.
        log_time: u64,
        /// Publish time, ns.
        publish_time: u64,
        /// Payload.
        data: &'a [u8],
    },
    /// A metadata record.
    Metadata {
        /// Record name.
        name: String,
        /// Its string map.
        metadata: BTreeMap<String, String>,
    },
    /// Any other record (indexes, statistics, attachments, data end, footer,
    /// unknown opcodes), by opcode. Chunks are read into, not reported: see
    /// [`RawDecoder::chunks`].
    Other {
        /// The record's opcode.
        opcode: u8,
    },
}

/// A message of [`RawMcap`], owning its data.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawMessage {
    /// Channel id.
    pub channel_id: u16,
    /// The channel's topic.
    pub topic: String,
    /// Sequence number.
    pub sequence: u32,
    /// Log time, ns.
    pub log_time: u64,
    /// Publish time, ns.
    pub publish_time: u64,
    /// Payload.
    pub data: Vec<u8>,
}

/// Everything [`read_raw`] keeps of an MCAP file.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RawMcap {
    /// Header profile.
    pub profile: String,
    /// Header library.
    pub library: String,
    /// Channels by id (the last record for an id wins).
    pub channels: BTreeMap<u16, Arc<RawChannel>>,
    /// Messages in file order.
    pub messages: Vec<RawMessage>,
    /// Metadata records in file order: (name, map).
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    /// Chunks by compression (`""` = uncompressed): count.
    pub chunks: BTreeMap<String, u64>,
    /// Records of other kinds by opcode: count.
    pub other_records: BTreeMap<u8, u64>,
}

/// Reads a whole MCAP file from memory into a [`RawMcap`].
pub fn read_raw(source_name: &str, bytes: &[u8]) -> Result<RawMcap, LogError> {
    let mut out = RawMcap::default();
    let mut decoder = RawDecoder::new(source_name, ReadLimits::default());
    decoder.end_of_input();
    let mut input = bytes;
    while let Some(event) = decoder.next_event(&mut input) {
        match event? {
            RawEvent::Header { profile, library } => {
                out.profile = profile;
                out.library = library;
            }
            RawEvent::Schema(_) => {}
            RawEvent::Channel(c) => {
                out.channels.insert(c.id, c);
            }
            RawEvent::Message {
                channel,
                sequence,
                log_time,
                publish_time,
                data,
            } => out.messages.push(RawMessage {
                channel_id: channel.id,
                topic: channel.topic.clone(),
                sequence,
                log_time,
                publish_time,
                data: data.to_vec(),
            }),
            RawEvent::Metadata { name, metadata } => out.metadata.push((name, metadata)),
            RawEvent::Other { opcode } => *out.other_records.entry(opcode).or_default() += 1,
        }
    }
    out.chunks = decoder.chunks().clone();
    Ok(out)
}

/// Calls `f` for every record of a whole MCAP file in memory, in file order.
/// Stops at the first error (of the file or of `f`).
pub fn for_each_record(
    source_name: &str,
    bytes: &[u8],
    limits: ReadLimits,
    mut f: impl FnMut(RawEvent<'_>) -> Result<(), LogError>,
) -> Result<(), LogError> {
    let mut decoder = RawDecoder::new(source_name, limits);
    let mut input = bytes;
    decoder.end_of_input();
    while let Some(event) = decoder.next_event(&mut input) {
        f(event?)?;
    }
    Ok(())
}

/// Incremental, sans-io MCAP record decoder (see the module docs).
///
/// Call [`next_event`](Self::next_event) with the bytes available so far;
/// it takes what it needs from the front of `input` and returns `None` when
/// it needs more (or, after [`end_of_input`](Self::end_of_input), at the end
/// of a complete file). After an error, the decoder is finished.
pub struct RawDecoder {
    file: String,
    reader: LinearReader,
    scanner: Scanner,
    limits: ReadLimits,
    schemas: BTreeMap<u16, Arc<RawSchema>>,
    channels: Vec<Option<Arc<RawChannel>>>,
    scratch: Vec<u8>,
    /// A size-limit or magic error the scanner found ahead of the reader.
    deferred: Option<LogError>,
    /// A record head the scanner has begun and not finished (a chunk's is
    /// 37 bytes and more), kept from the reader until it is checked: fed
    /// byte by byte, the reader read into a chunk whose declared sizes the
    /// scanner then refused, and reported another error than the file fed
    /// whole (found by the fuzzer, sixty-second session).
    held: Vec<u8>,
    eof: bool,
    eof_notified: bool,
    failed: bool,
}

/// How many bytes to hand the MCAP reader at least, per request.
const FEED_STEP: usize = 64 * 1024;

/// A record parsed out of the reader's buffer, owning what it needs.
enum Parsed {
    Header {
        profile: String,
        library: String,
    },
    Schema(Arc<RawSchema>),
    Channel(Arc<RawChannel>),
    Message {
        channel_id: u16,
        sequence: u32,
        log_time: u64,
        publish_time: u64,
    },
    Metadata {
        name: String,
        metadata: BTreeMap<String, String>,
    },
    Other(u8),
}

impl RawDecoder {
    /// A decoder for a file or stream called `source_name` (used in errors).
    #[must_use]
    pub fn new(source_name: &str, limits: ReadLimits) -> Self {
        let record_limit = usize::try_from(limits.max_record_bytes).unwrap_or(usize::MAX);
        let options = LinearReaderOptions::default()
            .with_validate_chunk_crcs(true)
            // a chunk with a CRC is checked whole before any of its records
            // is yielded: a corrupt chunk yields nothing, whatever pieces
            // the stream comes in (found by the fuzzer)
            .with_prevalidate_chunk_crcs(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true)
            .with_record_length_limit(record_limit);
        RawDecoder {
            file: source_name.to_owned(),
            reader: LinearReader::new_with_options(options),
            scanner: Scanner::default(),
            limits,
            schemas: BTreeMap::new(),
            channels: Vec::new(),
            scratch: Vec::new(),
            deferred: None,
            held: Vec::new(),
            eof: false,
            eof_notified: false,
            failed: false,
        }
    }

    /// The source name given to [`new`](Self::new).
    #[must_use]
    pub fn source_name(&self) -> &str {
        &self.file
    }

    /// Declares that no input will follow what is passed to the next
    /// [`next_event`](Self::next_event) calls: a file that ends before its
    /// end magic is then an error ([`LogError::Truncated`]).
    pub fn end_of_input(&mut self) {
        self.eof = true;
    }

    /// Whether everything handed over so far ends at a record boundary
    /// (or after the end magic): a stream that stops here lost no record.
    #[must_use]
    pub fn at_record_boundary(&self) -> bool {
        self.scanner.at_boundary()
    }

    /// Chunks seen so far, by compression (`""` = uncompressed): count.
    #[must_use]
    pub fn chunks(&self) -> &BTreeMap<String, u64> {
        &self.scanner.chunks
    }

    /// Offset in the input of the next byte the decoder will take.
    #[must_use]
    pub fn bytes_consumed(&self) -> u64 {
        self.scanner.offset
    }

    /// The next record, taking bytes from the front of `input` as needed.
    #[allow(clippy::too_many_lines)] // one loop feeding the reader, then one match on the record
    pub fn next_event(&mut self, input: &mut &[u8]) -> Option<Result<RawEvent<'_>, LogError>> {
        if self.failed {
            return None;
        }
        let parsed = loop {
            match self.reader.next_event() {
                None => {
                    // The reader has read the end magic. Whatever follows is
                    // not read, only counted (as the scanner does past the
                    // end): taken here, so that it does not depend on how
                    // much of it came with the bytes the reader last asked
                    // for (up to `FEED_STEP` more than it needed).
                    if !input.is_empty()
                        && self.scanner.scan(&self.file, input, &self.limits).is_ok()
                    {
                        *input = &[];
                    }
                    return None;
                }
                Some(Err(err)) => {
                    self.failed = true;
                    return Some(Err(map_mcap_error(&self.file, &err, &self.limits)));
                }
                Some(Ok(LinearReadEvent::ReadRequest(need))) => {
                    if input.is_empty() {
                        if self.eof && !self.held.is_empty() {
                            // a head cut by the end: the reader says how
                            let held = std::mem::take(&mut self.held);
                            self.reader.insert(held.len()).copy_from_slice(&held);
                            self.reader.notify_read(held.len());
                            continue;
                        }
                        if self.eof && !self.eof_notified {
                            self.eof_notified = true;
                            self.reader.notify_read(0);
                            continue;
                        }
                        return None;
                    }
                    if let Some(err) = self.deferred.take() {
                        self.failed = true;
                        return Some(Err(err));
                    }
                    let mut n = need.max(FEED_STEP).min(input.len());
                    // The held head, then these bytes, up to the first of a
                    // record head still unfinished (held in its turn) or of
                    // the record at fault.
                    let held = self.held.len();
                    let (from_held, from_input) =
                        match self.scanner.scan(&self.file, &input[..n], &self.limits) {
                            Ok(()) => {
                                let keep = self.scanner.unfinished_head();
                                let total = held + n;
                                (
                                    (total - keep).min(held),
                                    (total - keep).saturating_sub(held),
                                )
                            }
                            Err((before, err)) => {
                                // Reported when the reader asks for the record
                                // at fault, after every record before it: the
                                // same events whatever the pieces the input
                                // came in.
                                self.deferred = Some(err);
                                n = before;
                                // At 0 the fault is the held head's own record
                                // (no record starts inside an unfinished head):
                                // none of it is fed.
                                (if before > 0 { held } else { 0 }, before)
                            }
                        };
                    let fed = from_held + from_input;
                    if fed > 0 {
                        let buf = self.reader.insert(fed);
                        buf[..from_held].copy_from_slice(&self.held[..from_held]);
                        buf[from_held..].copy_from_slice(&input[..from_input]);
                        self.reader.notify_read(fed);
                    }
                    // what is left of the held bytes and the new ones not fed
                    self.held.drain(..from_held);
                    if self.deferred.is_none() {
                        self.held.extend_from_slice(&input[from_input..n]);
                    } else {
                        self.held.clear();
                    }
                    *input = &input[n..];
                }
                Some(Ok(LinearReadEvent::Record { opcode, data })) => {
                    match parse(&self.file, opcode, data, &mut self.scratch) {
                        Ok(p) => break p,
                        Err(err) => {
                            self.failed = true;
                            return Some(Err(err));
                        }
                    }
                }
            }
        };
        let event = match parsed {
            Parsed::Header { profile, library } => RawEvent::Header { profile, library },
            Parsed::Schema(schema) => {
                self.schemas.insert(schema.id, Arc::clone(&schema));
                RawEvent::Schema(schema)
            }
            Parsed::Channel(mut channel) => {
                let schema_id = channel.schema.as_ref().map_or(0, |s| s.id);
                if schema_id != 0 {
                    let Some(schema) = self.schemas.get(&schema_id) else {
                        self.failed = true;
                        return Some(Err(LogError::Mcap {
                            file: self.file.clone(),
                            reason: format!(
                                "channel {} (topic `{}`) refers to unknown schema {schema_id}",
                                channel.id, channel.topic
                            ),
                        }));
                    };
                    Arc::make_mut(&mut channel).schema = Some(Arc::clone(schema));
                }
                let id = usize::from(channel.id);
                if self.channels.len() <= id {
                    self.channels.resize(id + 1, None);
                }
                self.channels[id] = Some(Arc::clone(&channel));
                RawEvent::Channel(channel)
            }
            Parsed::Message {
                channel_id,
                sequence,
                log_time,
                publish_time,
            } => {
                let Some(Some(channel)) = self.channels.get(usize::from(channel_id)) else {
                    self.failed = true;
                    return Some(Err(LogError::Mcap {
                        file: self.file.clone(),
                        reason: format!(
                            "message (sequence {sequence}, log_time {log_time}) refers to unknown channel {channel_id}"
                        ),
                    }));
                };
                RawEvent::Message {
                    channel,
                    sequence,
                    log_time,
                    publish_time,
                    data: &self.scratch,
                }
            }
            Parsed::Metadata { name, metadata } => RawEvent::Metadata { name, metadata },
            Parsed::Other(opcode) => RawEvent::Other { opcode },
        };
        Some(Ok(event))
    }
}

/// The length a writer puts in a record's head while it is still writing
/// the record (the `mcap` crate's chunk, patched when the chunk is
/// finished): a file cut there (`kill -9` of the writer) ends with it.
const UNFINISHED_LEN: u64 = u64::MAX;

/// A record whose writer never finished it: said as such, not as a record
/// of 2⁶⁴ − 1 bytes over the limit (a helper's trial of `inspect` on a
/// recording cut by `kill -9`).
fn unfinished(file: &str, offset: u64) -> LogError {
    LogError::Truncated {
        file: file.to_owned(),
        reason: format!(
            "an unfinished record at offset {offset} (its writer stopped while writing it, \
             e.g. killed): what comes before it is complete"
        ),
    }
}

fn map_mcap_error(file: &str, err: &mcap::McapError, limits: &ReadLimits) -> LogError {
    match err {
        mcap::McapError::RecordTooLarge { len, .. } | mcap::McapError::ChunkTooLarge(len)
            if *len == UNFINISHED_LEN =>
        {
            LogError::Truncated {
                file: file.to_owned(),
                reason: "an unfinished record (its writer stopped while writing it, e.g. \
                         killed): what comes before it is complete"
                    .into(),
            }
        }
        mcap::McapError::RecordTooLarge { opcode, len } => LogError::TooLarge {
            file: file.to_owned(),
            what: format!("record with opcode {opcode:#04x}"),
            len: *len,
            limit: limits.max_record_bytes,
        },
        mcap::McapError::ChunkTooLarge(len) => LogError::TooLarge {
            file: file.to_owned(),
            what: "chunk".into(),
            len: *len,
            limit: limits.max_record_bytes,
        },
        _ => LogError::mcap(file, err),
    }
}

/// Bounds-checked little-endian reader over one record's body.
struct Body<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Body<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let out = self.data.get(self.pos..end)?;
        self.pos = end;
        Some(out)
    }
    fn u16(&mut self) -> Option<u16> {
        Some(u16::from_le_bytes(self.take(2)?.try_into().ok()?))
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn bytes32(&mut self) -> Option<&'a [u8]> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    fn string(&mut self) -> Option<Result<String, std::str::Utf8Error>> {
        let b = self.bytes32()?;
        Some(std::str::from_utf8(b).map(str::to_owned))
    }
    fn map(&mut self) -> Option<Result<BTreeMap<String, String>, String>> {
        let mut inner = Body {
            data: self.bytes32()?,
            pos: 0,
        };
        let mut map = BTreeMap::new();
        while inner.pos < inner.data.len() {
            let k = match inner.string()? {
                Ok(k) => k,
                Err(e) => return Some(Err(e.to_string())),
            };
            let v = match inner.string()? {
                Ok(v) => v,
                Err(e) => return Some(Err(e.to_string())),
            };
            if map.insert(k.clone(), v).is_some() {
                return Some(Err(format!("duplicate key `{k}`")));
            }
        }
        Some(Ok(map))
    }
}

/// Parses one record body; message payloads go to `scratch`.
fn parse(file: &str, opcode: u8, data: &[u8], scratch: &mut Vec<u8>) -> Result<Parsed, LogError> {
    use mcap::records::op;
    let bad = |what: &str, reason: &str| LogError::Mcap {
        file: file.to_owned(),
        reason: format!("{what} record: {reason}"),
    };
    let short = |what: &str| bad(what, "shorter than its fields");
    let utf8 = |what: &str, e: &dyn std::fmt::Display| bad(what, &format!("invalid UTF-8: {e}"));
    let mut b = Body { data, pos: 0 };
    Ok(match opcode {
        op::MESSAGE => {
            let channel_id = b.u16().ok_or_else(|| short("message"))?;
            let sequence = b.u32().ok_or_else(|| short("message"))?;
            let log_time = b.u64().ok_or_else(|| short("message"))?;
            let publish_time = b.u64().ok_or_else(|| short("message"))?;
            scratch.clear();
            scratch.extend_from_slice(&data[b.pos..]);
            Parsed::Message {
                channel_id,
                sequence,
                log_time,
                publish_time,
            }
        }
        op::HEADER => {
            let profile = b.string().ok_or_else(|| short("header"))?;
            let library = b.string().ok_or_else(|| short("header"))?;
            Parsed::Header {
                profile: profile.map_err(|e| utf8("header", &e))?,
                library: library.map_err(|e| utf8("header", &e))?,
            }
        }
        op::SCHEMA => {
            let id = b.u16().ok_or_else(|| short("schema"))?;
            let name = b
                .string()
                .ok_or_else(|| short("schema"))?
                .map_err(|e| utf8("schema", &e))?;
            let encoding = b
                .string()
                .ok_or_else(|| short("schema"))?
                .map_err(|e| utf8("schema", &e))?;
            let schema_data = b.bytes32().ok_or_else(|| short("schema"))?;
            if id == 0 {
                return Err(bad("schema", "id 0 is reserved"));
            }
            Parsed::Schema(Arc::new(RawSchema {
                id,
                name,
                encoding,
                data: schema_data.to_vec(),
            }))
        }
        op::CHANNEL => {
            let id = b.u16().ok_or_else(|| short("channel"))?;
            let schema_id = b.u16().ok_or_else(|| short("channel"))?;
            let topic = b
                .string()
                .ok_or_else(|| short("channel"))?
                .map_err(|e| utf8("channel", &e))?;
            let message_encoding = b
                .string()
                .ok_or_else(|| short("channel"))?
                .map_err(|e| utf8("channel", &e))?;
            let metadata = b
                .map()
                .ok_or_else(|| short("channel"))?
                .map_err(|e| bad("channel", &e))?;
            // the schema is resolved by the caller; a placeholder carries its id
            let schema = (schema_id != 0).then(|| {
                Arc::new(RawSchema {
                    id: schema_id,
                    name: String::new(),
                    encoding: String::new(),
                    data: Vec::new(),
                })
            });
            Parsed::Channel(Arc::new(RawChannel {
                id,
                topic,
                message_encoding,
                metadata,
                schema,
            }))
        }
        op::METADATA => {
            let name = b
                .string()
                .ok_or_else(|| short("metadata"))?
                .map_err(|e| utf8("metadata", &e))?;
            let metadata = b
                .map()
                .ok_or_else(|| short("metadata"))?
                .map_err(|e| bad("metadata", &e))?;
            Parsed::Metadata { name, metadata }
        }
        other => Parsed::Other(other),
    })
}

/// Follows the top-level record structure of the bytes handed to the MCAP
/// reader, to check declared sizes before the reader buffers a record and
/// to know whether a stream stopped at a record boundary.
#[derive(Debug, Default)]
struct Scanner {
    state: ScanState,
    /// Bytes of the current record's header collected so far.
    head: Vec<u8>,
    /// Bytes seen.
    offset: u64,
    /// Chunks seen, by compression: count.
    chunks: BTreeMap<String, u64>,
}

#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
enum ScanState {
    /// Within the leading magic (bytes of it seen).
    #[default]
    StartMagic,
    /// Collecting a record's opcode, length (and chunk header).
    Head,
    /// Skipping the rest of a record's body; `footer` if it is the footer.
    Body { remaining: u64, footer: bool },
    /// Within the trailing magic.
    EndMagic,
    /// After the trailing magic: nothing more is checked.
    Done,
}

const MAGIC_LEN: usize = 8;
/// opcode + length.
const RECORD_HEAD: usize = 9;
/// Chunk fields before the compression string: start, end, uncompressed size,
/// uncompressed CRC, compression length.
const CHUNK_FIXED: usize = 8 + 8 + 8 + 4 + 4;
/// Longest compression name the scanner keeps.
const MAX_COMPRESSION_NAME: usize = 64;

impl Scanner {
    /// Bytes of a record head begun and not finished.
    fn unfinished_head(&self) -> usize {
        if self.state == ScanState::Head {
            self.head.len()
        } else {
            0
        }
    }

    fn at_boundary(&self) -> bool {
        match self.state {
            ScanState::Head | ScanState::StartMagic => self.head.is_empty(),
            ScanState::Done => true,
            ScanState::Body { .. } | ScanState::EndMagic => false,
        }
    }

    /// Scans `bytes`; an error comes with the number of them before the
    /// record (or magic) at fault.
    fn scan(
        &mut self,
        file: &str,
        bytes: &[u8],
        limits: &ReadLimits,
    ) -> Result<(), (usize, LogError)> {
        let start = self.offset;
        self.scan_inner(file, bytes, limits).map_err(|err| {
            let at_fault = self.offset - self.head.len() as u64;
            (at_fault.saturating_sub(start) as usize, err)
        })
    }

    fn scan_inner(
        &mut self,
        file: &str,
        mut bytes: &[u8],
        limits: &ReadLimits,
    ) -> Result<(), LogError> {
        while !bytes.is_empty() {
            match self.state {
                ScanState::Done => {
                    self.offset += bytes.len() as u64;
                    return Ok(());
                }
                ScanState::StartMagic | ScanState::EndMagic => {
                    let n = (MAGIC_LEN - self.head.len()).min(bytes.len());
                    self.head.extend_from_slice(&bytes[..n]);
                    bytes = &bytes[n..];
                    self.offset += n as u64;
                    if !mcap::MAGIC.starts_with(&self.head) {
                        return Err(LogError::Mcap {
                            file: file.to_owned(),
                            reason: format!(
                                "bad magic at offset {} (expected \\x89MCAP0\\r\\n)",
                                self.offset - self.head.len() as u64
                            ),
                        });
                    }
                    if self.head.len() == MAGIC_LEN {
                        self.head.clear();
                        self.state = if self.state == ScanState::StartMagic {
                            ScanState::Head
                        } else {
                            ScanState::Done
                        };
                    }
                }
                ScanState::Body { remaining, footer } => {
                    let n = remaining.min(bytes.len() as u64);
                    bytes = &bytes[n as usize..];
                    self.offset += n;
                    if n == remaining {
                        self.state = if footer {
                            ScanState::EndMagic
                        } else {
                            ScanState::Head
                        };
                    } else {
                        self.state = ScanState::Body {
                            remaining: remaining - n,
                            footer,
                        };
                    }
                }
                ScanState::Head => {
                    let want = self.head_len();
                    let n = (want - self.head.len()).min(bytes.len());
                    self.head.extend_from_slice(&bytes[..n]);
                    bytes = &bytes[n..];
                    self.offset += n as u64;
                    if self.head.len() < want {
                        continue;
                    }
                    if self.head.len() == RECORD_HEAD {
                        let opcode = self.head[0];
                        let len = u64::from_le_bytes(self.head[1..9].try_into().unwrap_or([0; 8]));
                        if len == UNFINISHED_LEN {
                            return Err(unfinished(file, self.offset - RECORD_HEAD as u64));
                        }
                        if len > limits.max_record_bytes {
                            return Err(LogError::TooLarge {
                                file: file.to_owned(),
                                what: format!(
                                    "record with opcode {opcode:#04x} at offset {}",
                                    self.offset - RECORD_HEAD as u64
                                ),
                                len,
                                limit: limits.max_record_bytes,
                            });
                        }
                    }
                    if self.head.len() == RECORD_HEAD + CHUNK_FIXED
                        && self.head[0] == mcap::records::op::CHUNK
                    {
                        // before the compression name: the MCAP reader
                        // cannot have found anything wrong with the chunk yet
                        self.check_chunk_size(file, limits)?;
                    }
                    if self.head_len() > self.head.len() {
                        continue; // a chunk: collect its header and compression name
                    }
                    self.finish_head();
                }
            }
        }
        Ok(())
    }

    /// How many header bytes the current record needs before its body is skipped.
    fn head_len(&self) -> usize {
        if self.head.len() < RECORD_HEAD || self.head[0] != mcap::records::op::CHUNK {
            return RECORD_HEAD;
        }
        let len = u64::from_le_bytes(self.head[1..9].try_into().unwrap_or([0; 8]));
        let fixed = RECORD_HEAD + CHUNK_FIXED;
        if len < CHUNK_FIXED as u64 {
            // malformed chunk: let the MCAP reader report it
            return RECORD_HEAD;
        }
        if self.head.len() < fixed {
            return fixed;
        }
        let name_len = u32::from_le_bytes(self.head[fixed - 4..fixed].try_into().unwrap_or([0; 4]));
        let name_len = (name_len as usize).min(MAX_COMPRESSION_NAME);
        (fixed + name_len).min(RECORD_HEAD + usize::try_from(len).unwrap_or(usize::MAX))
    }

    /// Checks the uncompressed size a chunk declares (its fixed fields are in `head`).
    fn check_chunk_size(&self, file: &str, limits: &ReadLimits) -> Result<(), LogError> {
        let uncompressed = u64::from_le_bytes(
            self.head[RECORD_HEAD + 16..RECORD_HEAD + 24]
                .try_into()
                .unwrap_or([0; 8]),
        );
        if uncompressed > limits.max_chunk_uncompressed_bytes {
            return Err(LogError::TooLarge {
                file: file.to_owned(),
                what: format!(
                    "chunk at offset {} (uncompressed size)",
                    self.offset - self.head.len() as u64
                ),
                len: uncompressed,
                limit: limits.max_chunk_uncompressed_bytes,
            });
        }
        Ok(())
    }

    fn finish_head(&mut self) {
        let opcode = self.head[0];
        let len = u64::from_le_bytes(self.head[1..9].try_into().unwrap_or([0; 8]));
        if opcode == mcap::records::op::CHUNK && self.head.len() >= RECORD_HEAD + CHUNK_FIXED {
            let name = &self.head[RECORD_HEAD + CHUNK_FIXED..];
            *self
                .chunks
                .entry(String::from_utf8_lossy(name).into_owned())
                .or_default() += 1;
        }
        let body_seen = (self.head.len() - RECORD_HEAD) as u64;
        let remaining = len.saturating_sub(body_seen);
        let footer = opcode == mcap::records::op::FOOTER;
        self.head.clear();
        self.state = if remaining == 0 {
            if footer {
                ScanState::EndMagic
            } else {
                ScanState::Head
            }
        } else {
            ScanState::Body { remaining, footer }
        };
    }
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::{RawDecoder, RawEvent, ReadLimits};
    use crate::log::{Compression, LogError, LogWriter, RunMetadata, Sample, WriteOptions};

    /// Opcodes of the events and the error, feeding `bytes` in `piece`-byte pieces.
    fn decode(bytes: &[u8], piece: usize, limits: ReadLimits) -> (Vec<u8>, Option<LogError>) {
        let mut decoder = RawDecoder::new("ahead.mcap", limits);
        let mut opcodes = Vec::new();
        for chunk in bytes.chunks(piece) {
            let mut input = chunk;
            while let Some(event) = decoder.next_event(&mut input) {
                match event {
                    Ok(RawEvent::Message { .. }) => opcodes.push(0x05),
                    Ok(RawEvent::Channel(_)) => opcodes.push(0x04),
                    Ok(_) => opcodes.push(0),
                    Err(err) => return (opcodes, Some(err)),
                }
            }
            assert!(input.is_empty());
        }
        (opcodes, None)
    }

    /// A size error the scanner sees ahead of the reader (found by the
    /// fuzzer): every record before the one at fault is still yielded,
    /// whatever the pieces the input comes in.
    /// Five force samples written with `options`, and the offset of the
    /// first top-level record with `opcode`.
    fn five_forces(options: WriteOptions, opcode: u8) -> (Vec<u8>, usize) {
        let meta = RunMetadata {
            asset_id: "a".into(),
            run_id: "r".into(),
            ..RunMetadata::default()
        };
        let mut w = LogWriter::new(Cursor::new(Vec::new()), &meta, options).unwrap();
        for i in 0..5 {
            w.write_sample(&Sample::Force {
                t_ns: i,
                force_n: 1.0,
            })
            .unwrap();
        }
        let bytes = w.finish().unwrap().into_inner();
        let mut pos = 8;
        while bytes[pos] != opcode {
            pos += 9 + u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        }
        (bytes, pos)
    }

    #[test]
    fn a_size_error_ahead_comes_after_the_records_before_it() {
        let options = WriteOptions {
            compression: Compression::None,
            chunk_size: None,
        };
        // cut at the data end record, then a channel declaring 1 KiB + 1
        let (mut bytes, pos) = five_forces(options, 0x0F);
        bytes.truncate(pos);
        bytes.push(0x04);
        bytes.extend_from_slice(&1025_u64.to_le_bytes());
        let limits = ReadLimits {
            max_record_bytes: 1024,
            max_chunk_uncompressed_bytes: 4096,
        };
        let (whole, err) = decode(&bytes, bytes.len(), limits);
        assert_eq!(whole.iter().rev().take_while(|&&op| op == 0x05).count(), 5);
        assert!(
            matches!(err, Some(LogError::TooLarge { len: 1025, .. })),
            "{err:?}"
        );
        for piece in [1, 9, 100] {
            let (events, err) = decode(&bytes, piece, limits);
            assert_eq!(events, whole, "pieces of {piece}");
            assert!(matches!(err, Some(LogError::TooLarge { .. })), "{err:?}");
        }
    }

    /// A recording cut by `kill -9` ends in a chunk whose head still holds
    /// the writer's placeholder length (2⁶⁴ − 1): it is a truncation after
    /// complete records, not a record over the size limit.
    #[test]
    fn a_chunk_its_writer_never_finished_is_a_truncation() {
        let (mut bytes, pos) = five_forces(WriteOptions::default(), mcap::records::op::CHUNK);
        bytes[pos + 1..pos + 9].copy_from_slice(&u64::MAX.to_le_bytes());
        bytes.truncate(pos + 40);
        let (_, err) = decode(&bytes, bytes.len(), ReadLimits::default());
        let Some(LogError::Truncated { reason, .. }) = err else {
            panic!("{err:?}")
        };
        assert!(
            reason.contains(&format!("unfinished record at offset {pos}")),
            "{reason}"
        );
    }
}
