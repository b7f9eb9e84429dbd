//! Fuzzing the decoders a remote party reaches (issue 13): the daemon's TCP
//! and inbox ingest feed [`LogDecoder`]; `read_log_bytes`, `read_raw` and
//! `inspect_bytes` share its raw layer and JSON message decoding.
//!
//! - `mutated_files`: real files (the writer's logs in every layout, the 416
//!   MCAP conformance files) mutated at the byte level (bit flips, bytes set,
//!   removed or inserted, truncation, splices of two files) and at the record
//!   level (a record's length set to 0, the limit ± 1 or 2^64 − 1, records of
//!   random opcodes and lengths inserted, duplicated or removed, chunk sizes
//!   and compression names changed), with CRCs zeroed (= not checked) most of
//!   the time so that mutations reach the parsers behind them.
//! - `generated_json`: well-framed logs whose message payloads are generated
//!   JSON — numbers in every spelling, NaN/Infinity/null, out-of-range
//!   exponents, strings with escapes and lone surrogates, nesting thousands
//!   deep, non-UTF-8 bytes — checked against `serde_json` where it parses.
//! - every truncation and every two-piece split of a log, exhaustively.
//!
//! Asserted for every input: no panic, no hang (the driver's time limit), no
//! allocation beyond what the input and the [`ReadLimits`] allow (a counting
//! allocator), every error names the source (and a message error its topic
//! and field), the same events and result whatever the chunk split (and
//! with the sensor messages taken undecoded and parsed after), no
//! sample before the run's metadata, and the stream and whole-file readers
//! agreeing on the samples of a file both accept.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Cursor;
use std::sync::OnceLock;

use dt_core::log::raw::read_raw;
use dt_core::log::{
    inspect_bytes, json_schema, read_log_bytes, Compression, LogDecoder, LogError, LogEvent,
    ReadLimits, RunLog, Sample, Undecoded, WriteOptions, RUN_METADATA_NAME, TOPICS,
};
use proptest::prelude::*;
use proptest::sample::Index;

use crate::fuzz_driver::fuzz;
use crate::log_conformance::conformance_files;
use crate::log_writer::{meta, samples, write_bytes};

/// Counts the largest allocation request of the current thread.
mod alloc_meter {
    #![allow(unsafe_code)] // a `GlobalAlloc` is an unsafe trait; this one only forwards to `System`

    use std::alloc::{GlobalAlloc, Layout, System};
    use std::cell::Cell;

    pub struct Meter;

    thread_local! {
        static LARGEST: Cell<usize> = const { Cell::new(0) };
    }

    fn note(size: usize) {
        let _ = LARGEST.try_with(|l| {
            if size > l.get() {
                l.set(size);
            }
        });
    }

    /// Runs `f` and returns its result with the largest single allocation
    /// (or reallocation) it requested on this thread, in bytes.
    pub fn largest_allocation<R>(f: impl FnOnce() -> R) -> (R, usize) {
        LARGEST.with(|l| l.set(0));
        let out = f();
        (out, LARGEST.with(Cell::get))
    }

    // SAFETY: every call is forwarded unchanged to the system allocator.
    unsafe impl GlobalAlloc for Meter {
        unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
            note(layout.size());
            // SAFETY: the caller's contract is passed on.
            unsafe { System.alloc(layout) }
        }
        unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
            note(layout.size());
            // SAFETY: as above.
            unsafe { System.alloc_zeroed(layout) }
        }
        unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
            // SAFETY: as above.
            unsafe { System.dealloc(ptr, layout) }
        }
        unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
            note(new_size);
            // SAFETY: as above.
            unsafe { System.realloc(ptr, layout, new_size) }
        }
    }
}

#[global_allocator]
static METER: alloc_meter::Meter = alloc_meter::Meter;

const SOURCE: &str = "fuzz.mcap";
const OP_FOOTER: u8 = 0x02;
const OP_CHUNK: u8 = 0x06;
const OP_DATA_END: u8 = 0x0F;

/// The stream decoder's limits in the harness: small, so that the
/// allocation bound below means something.
const LIMITS: ReadLimits = ReadLimits {
    max_record_bytes: 1 << 20,
    max_chunk_uncompressed_bytes: 4 << 20,
};

// ---------------------------------------------------------------- seeds

/// Seed files, smallest first (proptest shrinks the index towards 0).
fn seeds() -> &'static [Vec<u8>] {
    static SEEDS: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    SEEDS.get_or_init(|| {
        let written = &samples()[..60];
        let mut out = Vec::new();
        for chunk_size in [None, Some(300), Some(1 << 20)] {
            for compression in [Compression::None, Compression::Zstd, Compression::Lz4] {
                if chunk_size.is_none() && compression != Compression::None {
                    continue;
                }
                out.push(write_bytes(
                    written,
                    WriteOptions {
                        compression,
                        chunk_size,
                    },
                ));
            }
        }
        for path in conformance_files() {
            out.push(std::fs::read(&path).unwrap());
        }
        out.sort_by_key(Vec::len);
        out
    })
}

// ---------------------------------------------------------------- record structure

/// `(start, end)` of each complete top-level record (up to the footer).
fn records(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut pos = 8;
    while pos + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap());
        let Some(end) = usize::try_from(len)
            .ok()
            .and_then(|l| (pos + 9).checked_add(l))
            .filter(|&end| end <= bytes.len())
        else {
            break;
        };
        out.push((pos, end));
        if bytes[pos] == OP_FOOTER {
            break;
        }
        pos = end;
    }
    out
}

/// Zeroes the CRCs (0 = not computed) of uncompressed chunks, data end and
/// footer. A compressed chunk keeps its CRC: without one, a corrupt
/// compressed stream is only found as it is decompressed, after records
/// before the damage were yielded, so when depends on the pieces the input
/// came in (see `check_bytes`).
fn zero_crcs(bytes: &mut [u8]) {
    for (start, end) in records(bytes) {
        let body = start + 9;
        let field = match bytes[start] {
            OP_CHUNK if chunk_compression_len(bytes, start, end) == Some(0) => body + 24..body + 28,
            OP_DATA_END => body..body + 4,
            OP_FOOTER => body + 16..body + 20,
            _ => continue,
        };
        if field.end <= end {
            bytes[field].fill(0);
        }
    }
}

/// The compression-name length of the chunk record at `start..end`.
fn chunk_compression_len(bytes: &[u8], start: usize, end: usize) -> Option<u32> {
    let field = bytes.get(start + 9 + 28..start + 9 + 32)?;
    (start + 9 + 32 <= end).then(|| u32::from_le_bytes(field.try_into().unwrap()))
}

/// The compression name of the chunk record at `start..end`, if whole.
fn chunk_compression(bytes: &[u8], start: usize, end: usize) -> Option<&[u8]> {
    let len = chunk_compression_len(bytes, start, end)? as usize;
    let name = start + 9 + 32;
    (name + len <= end).then(|| &bytes[name..name + len])
}

// ---------------------------------------------------------------- mutations

#[derive(Debug, Clone)]
enum Mutation {
    FlipBit {
        at: Index,
        bit: u8,
    },
    SetByte {
        at: Index,
        value: u8,
    },
    Truncate {
        at: Index,
    },
    Remove {
        at: Index,
        len: u8,
    },
    Insert {
        at: Index,
        bytes: Vec<u8>,
    },
    /// This file up to `at`, then seed `other` from `from`.
    Splice {
        other: Index,
        from: Index,
        at: Index,
    },
    SetLength {
        record: Index,
        len: u64,
    },
    InsertRecord {
        record: Index,
        opcode: u8,
        len: u64,
        body: Vec<u8>,
    },
    DuplicateRecord {
        record: Index,
    },
    RemoveRecord {
        record: Index,
    },
    /// A chunk's uncompressed size (0), CRC (1), compression-name length (2)
    /// or compression name (3).
    SetChunkField {
        record: Index,
        field: u8,
        value: u64,
    },
}

fn interesting_u64() -> impl Strategy<Value = u64> {
    prop_oneof![
        Just(0),
        Just(1),
        Just(8),
        Just(9),
        Just(31),
        Just(LIMITS.max_record_bytes - 1),
        Just(LIMITS.max_record_bytes),
        Just(LIMITS.max_record_bytes + 1),
        Just(LIMITS.max_chunk_uncompressed_bytes + 1),
        Just(u64::from(u32::MAX)),
        Just(1 << 62),
        Just(u64::MAX),
        0..4096_u64,
        any::<u64>(),
    ]
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let byte = prop_oneof![Just(0_u8), Just(0xff), Just(0x7f), Just(0x80), any::<u8>()];
    let opcode = prop_oneof![0_u8..=0x12, any::<u8>()];
    prop_oneof![
        4 => (any::<Index>(), 0_u8..8).prop_map(|(at, bit)| Mutation::FlipBit { at, bit }),
        2 => (any::<Index>(), byte).prop_map(|(at, value)| Mutation::SetByte { at, value }),
        2 => any::<Index>().prop_map(|at| Mutation::Truncate { at }),
        1 => (any::<Index>(), any::<u8>()).prop_map(|(at, len)| Mutation::Remove { at, len }),
        1 => (any::<Index>(), prop::collection::vec(any::<u8>(), 1..32))
            .prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
        1 => (any::<Index>(), any::<Index>(), any::<Index>())
            .prop_map(|(other, from, at)| Mutation::Splice { other, from, at }),
        3 => (any::<Index>(), interesting_u64())
            .prop_map(|(record, len)| Mutation::SetLength { record, len }),
        3 => (any::<Index>(), opcode, interesting_u64(), prop::collection::vec(any::<u8>(), 0..48))
            .prop_map(|(record, opcode, len, body)| Mutation::InsertRecord { record, opcode, len, body }),
        1 => any::<Index>().prop_map(|record| Mutation::DuplicateRecord { record }),
        1 => any::<Index>().prop_map(|record| Mutation::RemoveRecord { record }),
        2 => (any::<Index>(), 0_u8..4, interesting_u64())
            .prop_map(|(record, field, value)| Mutation::SetChunkField { record, field, value }),
    ]
}

#[allow(clippy::trivially_copy_pass_by_ref)] // called with fields of a borrowed `Mutation`
fn pick(index: &Index, len: usize) -> usize {
    if len == 0 {
        0
    } else {
        index.index(len)
    }
}

/// The record a record-level mutation targets (`None` if the file has none).
#[allow(clippy::trivially_copy_pass_by_ref)] // as `pick`
fn pick_record(bytes: &[u8], index: &Index) -> Option<(usize, usize)> {
    let recs = records(bytes);
    (!recs.is_empty()).then(|| recs[index.index(recs.len())])
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    match m {
        Mutation::FlipBit { at, bit } => {
            if !bytes.is_empty() {
                let i = pick(at, bytes.len());
                bytes[i] ^= 1 << bit;
            }
        }
        Mutation::SetByte { at, value } => {
            if !bytes.is_empty() {
                let i = pick(at, bytes.len());
                bytes[i] = *value;
            }
        }
        Mutation::Truncate { at } => bytes.truncate(pick(at, bytes.len() + 1)),
        Mutation::Remove { at, len } => {
            let i = pick(at, bytes.len() + 1);
            let end = (i + usize::from(*len)).min(bytes.len());
            bytes.drain(i..end);
        }
        Mutation::Insert { at, bytes: new } => {
            let i = pick(at, bytes.len() + 1);
            bytes.splice(i..i, new.iter().copied());
        }
        Mutation::Splice { other, from, at } => {
            let other = &seeds()[other.index(seeds().len())];
            let i = pick(at, bytes.len() + 1);
            let j = pick(from, other.len() + 1);
            bytes.truncate(i);
            bytes.extend_from_slice(&other[j..]);
        }
        Mutation::SetLength { record, len } => {
            if let Some((start, _)) = pick_record(bytes, record) {
                bytes[start + 1..start + 9].copy_from_slice(&len.to_le_bytes());
            }
        }
        Mutation::InsertRecord {
            record,
            opcode,
            len,
            body,
        } => {
            let at = pick_record(bytes, record).map_or(bytes.len().min(8), |r| r.0);
            let mut new = vec![*opcode];
            new.extend_from_slice(&len.to_le_bytes());
            new.extend_from_slice(body);
            bytes.splice(at..at, new);
        }
        Mutation::DuplicateRecord { record } => {
            if let Some((start, end)) = pick_record(bytes, record) {
                let copy = bytes[start..end].to_vec();
                bytes.splice(end..end, copy);
            }
        }
        Mutation::RemoveRecord { record } => {
            if let Some((start, end)) = pick_record(bytes, record) {
                bytes.drain(start..end);
            }
        }
        Mutation::SetChunkField {
            record,
            field,
            value,
        } => {
            let chunk = records(bytes)
                .into_iter()
                .filter(|r| bytes[r.0] == OP_CHUNK)
                .collect::<Vec<_>>();
            if chunk.is_empty() {
                return;
            }
            let (start, end) = chunk[record.index(chunk.len())];
            let body = start + 9;
            let (offset, width) = match field {
                0 => (16, 8),
                1 => (24, 4),
                2 => (28, 4),
                _ => (32, 4),
            };
            if body + offset + width <= end {
                bytes[body + offset..body + offset + width]
                    .copy_from_slice(&value.to_le_bytes()[..width]);
            }
        }
    }
}

#[derive(Debug, Clone)]
struct MutatedFile {
    seed: Index,
    mutations: Vec<Mutation>,
    zero_crcs: bool,
    /// Sizes of the pieces the stream is fed in (cycled).
    pieces: Vec<usize>,
}

impl MutatedFile {
    fn bytes(&self) -> Vec<u8> {
        let mut bytes = seeds()[self.seed.index(seeds().len())].clone();
        for m in &self.mutations {
            apply(&mut bytes, m);
        }
        if self.zero_crcs {
            zero_crcs(&mut bytes);
        }
        bytes
    }
}

fn pieces() -> impl Strategy<Value = Vec<usize>> {
    prop::collection::vec(
        prop_oneof![Just(1_usize), 1..64_usize, 1..70_000_usize],
        1..6,
    )
}

// ---------------------------------------------------------------- the checks

/// What the stream decoder made of an input: events (errors as text) and
/// `finish()`'s result.
#[derive(Debug)]
struct Decoded {
    events: Vec<Result<String, String>>,
    end: Result<(), String>,
    samples: Vec<Sample>,
    fatal: bool,
    saw_end: bool,
}

impl Decoded {
    /// What must not depend on the chunk split (samples are in `events`;
    /// compared as text, so that NaN equals NaN).
    fn outcome(&self) -> (&[Result<String, String>], &Result<(), String>) {
        (&self.events, &self.end)
    }
}

fn check_error(err: &LogError) {
    let text = err.to_string();
    assert!(
        text.starts_with(&format!("{SOURCE}: ")) && text.len() > SOURCE.len() + 4,
        "error does not name the source: {text}"
    );
    if let LogError::Message {
        topic,
        field,
        reason,
        ..
    } = err
    {
        assert!(
            topic.starts_with('/'),
            "message error without topic: {text}"
        );
        // the field is the JSON key at fault, which may be `""` in malformed JSON
        assert!(
            !field.is_empty() || reason.starts_with("malformed JSON"),
            "message error without field: {text}"
        );
        assert!(!reason.is_empty(), "message error without reason: {text}");
    }
}

/// Feeds `bytes` in pieces of the given sizes (cycled; empty: all at once).
fn stream(bytes: &[u8], pieces: &[usize]) -> Decoded {
    stream_with(bytes, pieces, false)
}

/// The next event of `decoder`; with `deferred`, a sensor message is taken
/// undecoded ([`LogDecoder::next_undecoded`]) and parsed afterwards, as
/// `shocktwin replay` does on its second thread.
fn next(decoder: &mut LogDecoder, deferred: bool) -> Option<Result<LogEvent, LogError>> {
    if !deferred {
        return decoder.next_event();
    }
    let mut text = Vec::new();
    Some(match decoder.next_undecoded(&mut text)? {
        Ok(Undecoded::Event(event)) => Ok(event),
        Ok(Undecoded::Sample(message)) => message.decode(SOURCE, &text).map(LogEvent::Sample),
        Err(err) => Err(err),
    })
}

fn stream_with(bytes: &[u8], pieces: &[usize], deferred: bool) -> Decoded {
    let mut decoder = LogDecoder::with_limits(SOURCE, LIMITS);
    let mut out = Decoded {
        events: Vec::new(),
        end: Ok(()),
        samples: Vec::new(),
        fatal: false,
        saw_end: false,
    };
    let mut metadata = false;
    let mut rest = bytes;
    let mut k = 0;
    loop {
        let n = match pieces {
            [] => rest.len(),
            _ => pieces[k % pieces.len()].max(1).min(rest.len()),
        };
        decoder.feed(&rest[..n]);
        rest = &rest[n..];
        k += 1;
        while let Some(event) = next(&mut decoder, deferred) {
            assert!(!out.fatal, "an event after a fatal error: {event:?}");
            match event {
                Ok(event) => {
                    match &event {
                        LogEvent::Metadata(_) => metadata = true,
                        LogEvent::Sample(s) => {
                            assert!(metadata, "a sample before the metadata: {s:?}");
                            out.samples.push(*s);
                        }
                        LogEvent::End => out.saw_end = true,
                        LogEvent::Unknown { .. } => {}
                    }
                    out.events.push(Ok(format!("{event:?}")));
                }
                Err(err) => {
                    check_error(&err);
                    out.fatal |= err.is_fatal();
                    out.events.push(Err(err.to_string()));
                }
            }
        }
        if rest.is_empty() {
            break;
        }
    }
    out.end = decoder.finish().map_err(|err| {
        check_error(&err);
        err.to_string()
    });
    out
}

fn columns(log: &RunLog) -> String {
    format!(
        "{:?}",
        (
            &log.position,
            &log.acceleration,
            &log.force,
            &log.temp_shock,
            &log.temp_ambient,
            &log.truth_pressure,
            &log.truth_velocity,
        )
    )
}

/// Every reader on `bytes`; the stream fed whole and in `pieces`.
fn check_bytes(bytes: &[u8], pieces: &[usize]) -> Decoded {
    let ((whole, split), largest) =
        alloc_meter::largest_allocation(|| (stream(bytes, &[]), stream(bytes, pieces)));
    let bound = 2 * LIMITS.max_chunk_uncompressed_bytes as usize + 8 * bytes.len() + (1 << 20);
    assert!(
        largest <= bound,
        "the stream decoder allocated {largest} bytes at once for a {}-byte input (bound {bound})",
        bytes.len()
    );
    let deferred = stream_with(bytes, pieces, true);
    assert_eq!(
        deferred.outcome(),
        split.outcome(),
        "messages parsed after the fact read otherwise (pieces {pieces:?})"
    );
    if whole.outcome() != split.outcome() {
        // Allowed only for a damaged compressed chunk, and only in where the
        // stream stops: without a CRC, records before the damage may come
        // first; with one (checked before any record), the LZ4/zstd frame
        // check or the CRC may fail first, and damage to the LZ4 frame trailer
        // alone (the records' CRC is right) is only seen when the chunk
        // arrives whole. Records yielded must agree: one list a prefix of the
        // other.
        let oks = |d: &Decoded| {
            d.events
                .iter()
                .filter(|e| e.is_ok())
                .cloned()
                .collect::<Vec<_>>()
        };
        let (a, b) = (oks(&whole), oks(&split));
        let prefix = a.iter().zip(&b).all(|(x, y)| x == y);
        let compressed = records(bytes).into_iter().any(|(start, end)| {
            bytes[start] == OP_CHUNK && chunk_compression_len(bytes, start, end) != Some(0)
        });
        // A limit of the `mcap` crate's streaming LZ4 decoding: a frame
        // damaged where its blocks still decode (no CRC to catch it) is
        // refused by LZ4 when the chunk comes in one piece and read when it
        // comes in small ones (found by `make fuzz`, sixty-second session).
        // Allowed only so: one side an LZ4 error, its records a prefix of
        // the other's.
        let lz4_error = |d: &Decoded| {
            d.fatal
                && d.events
                    .iter()
                    .any(|e| e.as_ref().is_err_and(|e| e.contains("LZ4 error")))
        };
        let lz4_only = (lz4_error(&whole) != lz4_error(&split))
            && (whole.fatal != split.fatal)
            && prefix
            && records(bytes).into_iter().any(|(start, end)| {
                bytes[start] == OP_CHUNK
                    && chunk_compression(bytes, start, end) == Some(b"lz4".as_slice())
            });
        assert!(
            (whole.fatal && split.fatal && compressed && prefix) || lz4_only,
            "the result depends on the chunk split (pieces {pieces:?}):\n{:?}\n{:?}",
            whole.outcome(),
            split.outcome()
        );
    }
    match read_log_bytes(SOURCE, bytes) {
        Err(err) => check_error(&err),
        Ok(log) => {
            if !whole.fatal && whole.end.is_ok() && whole.saw_end {
                let mut streamed = RunLog::default();
                for s in &whole.samples {
                    streamed.push(*s);
                }
                assert_eq!(
                    columns(&streamed),
                    columns(&log),
                    "stream and whole-file readers disagree"
                );
            }
        }
    }
    if let Err(err) = read_raw(SOURCE, bytes) {
        check_error(&err);
    }
    if let Err(err) = inspect_bytes(SOURCE, bytes) {
        check_error(&err);
    }
    whole
}

// ---------------------------------------------------------------- harness 1: mutated files

fn mutated_file() -> impl Strategy<Value = MutatedFile> {
    (
        any::<Index>(),
        prop::collection::vec(mutation(), 1..6),
        prop::bool::weighted(0.75),
        pieces(),
    )
        .prop_map(|(seed, mutations, zero_crcs, pieces)| MutatedFile {
            seed,
            mutations,
            zero_crcs,
            pieces,
        })
}

fn check_mutated(case: &MutatedFile) {
    let bytes = case.bytes();
    // SHOCKTWIN_FUZZ_DUMP=DIR keeps every crashing input there, named by its
    // length and hash (the shortest is the shrunk one), for fuzz-regressions/
    let dump = std::env::var("SHOCKTWIN_FUZZ_DUMP").ok().map(|dir| {
        use std::hash::{Hash as _, Hasher as _};
        let mut h = std::collections::hash_map::DefaultHasher::new();
        (&bytes, &case.pieces).hash(&mut h);
        let name = format!("crash-{:06}-{:016x}.mcap", bytes.len(), h.finish());
        let path = std::path::Path::new(&dir).join(name);
        std::fs::write(&path, &bytes).unwrap();
        path
    });
    check_bytes(&bytes, &case.pieces);
    if let Some(path) = dump {
        std::fs::remove_file(path).unwrap();
    }
}

#[test]
fn fuzz_mutated_files() {
    fuzz("decode/mutated_files", 400, &mutated_file(), check_mutated);
}

// ---------------------------------------------------------------- harness 2: generated JSON

/// One message of a generated log.
#[derive(Debug, Clone)]
struct JsonMessage {
    /// Index into `TOPICS`, or `TOPICS.len()` for an unknown topic.
    topic: usize,
    log_time: u64,
    payload: Vec<u8>,
    /// Generated as an object with distinct keys and not mutated since.
    pristine: bool,
}

#[derive(Debug, Clone)]
struct JsonLog {
    /// 0: unchunked, 1: uncompressed chunks, 2: zstd, 3: lz4.
    layout: u8,
    messages: Vec<JsonMessage>,
    pieces: Vec<usize>,
}

fn json_number() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => any::<f64>().prop_map(|x| format!("{x:?}")),
        2 => any::<f64>().prop_map(|x| format!("{x:e}")),
        2 => any::<i64>().prop_map(|x| x.to_string()),
        1 => (any::<i32>(), any::<i16>()).prop_map(|(m, e)| format!("{m}e{e}")),
    ]
}

fn json_value() -> impl Strategy<Value = String> {
    let special = prop::sample::select(vec![
        "null",
        "NaN",
        "Infinity",
        "-Infinity",
        "true",
        "false",
        "1e999",
        "-1e999",
        "1e-999",
        "-0",
        "0",
        "01",
        "1.",
        ".5",
        "+1",
        "-",
        "1e",
        "1e+",
        "0x10",
        "nul",
        "Inf",
        "NaNa",
        "--1",
        "1.2.3",
        "[]",
        "{}",
        "\"\"",
        "\"\\ud800\"",
        "\"\\\"}\"",
        "\"\\u00e9\"",
    ])
    .prop_map(str::to_owned);
    prop_oneof![
        6 => json_number(),
        3 => special,
        1 => "[ -~é\\x00-\\x1f]{0,12}".prop_map(|s| serde_json::to_string(&s).unwrap()),
        1 => (1..3000_usize, any::<bool>()).prop_map(|(depth, object)| {
            let (open, close) = if object { ("{\"a\":", "}") } else { ("[", "]") };
            format!("{}1{}", open.repeat(depth), close.repeat(depth))
        }),
        1 => prop::collection::vec(json_number(), 0..4)
            .prop_map(|v| format!("[{},{{\"k\":\"]\"}}]", v.join(","))),
    ]
}

/// An object for `topic`: each required field with probability 0.9, plus
/// up to three other members; distinct keys.
fn json_object(topic: usize) -> impl Strategy<Value = String> {
    let required: Vec<&'static str> = TOPICS.get(topic).map_or(&[][..], |s| s.fields).to_vec();
    let n = required.len();
    (
        prop::collection::vec((prop::bool::weighted(0.9), json_value()), n),
        prop::collection::vec(
            (
                prop_oneof!["[a-z_]{1,8}", Just("a1_mps2".to_owned()), "[\\\\\"é ]{0,3}"],
                json_value(),
            ),
            0..3,
        ),
        prop::sample::select(vec!["", " ", "\n\t ", "\r\n"]),
        any::<bool>(),
    )
        .prop_map(move |(fields, others, ws, others_first)| {
            let mut keys = BTreeSet::new();
            let mut members = Vec::new();
            let ours = required
                .iter()
                .zip(fields)
                .filter(|(_, (present, _))| *present)
                .map(|(k, (_, v))| ((*k).to_owned(), v));
            let theirs = others.into_iter();
            let all: Vec<(String, String)> = if others_first {
                theirs.chain(ours).collect()
            } else {
                ours.chain(theirs).collect()
            };
            for (k, v) in all {
                if keys.insert(k.clone()) {
                    let key = serde_json::to_string(&k).unwrap();
                    members.push(format!("{ws}{key}{ws}:{ws}{v}"));
                }
            }
            format!("{ws}{{{}{ws}}}{ws}", members.join(","))
        })
}

fn json_message() -> impl Strategy<Value = JsonMessage> {
    let log_time = prop_oneof![
        8 => 0..10_000_000_000_u64,
        1 => Just(i64::MAX as u64),
        1 => Just(i64::MAX as u64 + 1),
        1 => Just(u64::MAX),
    ];
    (0..=TOPICS.len(), log_time).prop_flat_map(|(topic, log_time)| {
        prop_oneof![
            6 => json_object(topic).prop_map(|s| (s.into_bytes(), true)),
            2 => (json_object(topic), prop::collection::vec(mutation_of_payload(), 1..3))
                .prop_map(|(s, muts)| {
                    let mut b = s.into_bytes();
                    for (at, byte, kind) in muts {
                        let i = pick(&at, b.len() + 1);
                        match kind {
                            0 if i < b.len() => b[i] = byte,
                            1 => b.insert(i, byte),
                            2 => b.truncate(i),
                            _ => {}
                        }
                    }
                    (b, false)
                }),
            1 => prop::collection::vec(any::<u8>(), 0..48).prop_map(|b| (b, false)),
        ]
        .prop_map(move |(payload, pristine)| JsonMessage {
            topic,
            log_time,
            payload,
            pristine,
        })
    })
}

fn mutation_of_payload() -> impl Strategy<Value = (Index, u8, u8)> {
    (
        any::<Index>(),
        prop_oneof![
            Just(0xff_u8),
            Just(0xc3),
            Just(b'"'),
            Just(b'\\'),
            Just(b'{'),
            any::<u8>()
        ],
        0_u8..3,
    )
}

fn json_log() -> impl Strategy<Value = JsonLog> {
    (
        0_u8..4,
        prop::collection::vec(json_message(), 1..12),
        pieces(),
    )
        .prop_map(|(layout, messages, pieces)| JsonLog {
            layout,
            messages,
            pieces,
        })
}

fn build_json_log(case: &JsonLog) -> Vec<u8> {
    let options = mcap::WriteOptions::new()
        .use_chunks(case.layout != 0)
        .chunk_size(Some(256))
        .compression(match case.layout {
            2 => Some(mcap::Compression::Zstd),
            3 => Some(mcap::Compression::Lz4),
            _ => None,
        });
    let mut w = options.create(Cursor::new(Vec::new())).unwrap();
    w.write_metadata(&mcap::records::Metadata {
        name: RUN_METADATA_NAME.into(),
        metadata: meta().to_map(),
    })
    .unwrap();
    let mut channels = BTreeMap::new();
    for (sequence, m) in case.messages.iter().enumerate() {
        let channel_id = *channels
            .entry(m.topic)
            .or_insert_with(|| match TOPICS.get(m.topic) {
                Some(spec) => {
                    let schema = w
                        .add_schema(spec.schema_name, "jsonschema", json_schema(spec).as_bytes())
                        .unwrap();
                    w.add_channel(schema, spec.topic, "json", &BTreeMap::new())
                        .unwrap()
                }
                None => w
                    .add_channel(0, "/unknown", "json", &BTreeMap::new())
                    .unwrap(),
            });
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: sequence as u32,
            log_time: m.log_time,
            publish_time: m.log_time,
        };
        w.write_to_known_channel(&header, &m.payload).unwrap();
    }
    w.finish().unwrap();
    w.into_inner().into_inner()
}

fn check_json(case: &JsonLog) {
    let bytes = build_json_log(case);
    let decoded = check_bytes(&bytes, &case.pieces);
    assert!(
        !decoded.fatal,
        "a well-framed log had a fatal error: {decoded:?}"
    );
    assert!(decoded.end.is_ok(), "{decoded:?}");
    // events: metadata, then one per message, then the end
    let per_message = &decoded.events[1..decoded.events.len() - 1];
    assert_eq!(per_message.len(), case.messages.len(), "{decoded:?}");
    for (m, event) in case.messages.iter().zip(per_message) {
        check_json_message(m, event);
    }
}

/// The decoded event of one message against `serde_json`'s reading of it.
fn check_json_message(m: &JsonMessage, event: &Result<String, String>) {
    let Some(spec) = TOPICS.get(m.topic) else {
        assert!(
            matches!(event, Ok(e) if e.starts_with("Unknown")),
            "unknown topic: {event:?}"
        );
        return;
    };
    let text = String::from_utf8_lossy(&m.payload);
    if i64::try_from(m.log_time).is_err() {
        let err = event.as_ref().expect_err("log_time beyond i64 accepted");
        assert!(err.contains("field `log_time`"), "{err}");
        return;
    }
    if let Err(err) = event {
        assert!(
            err.contains(&format!("topic `{}`", spec.topic)),
            "error does not name the topic: {err}"
        );
    }
    if !m.pristine {
        return;
    }
    let Ok(serde_json::Value::Object(object)) = serde_json::from_slice(&m.payload) else {
        return;
    };
    let mut expected = Vec::new();
    for field in spec.fields {
        match object.get(*field) {
            Some(serde_json::Value::Null) => expected.push(f64::NAN),
            Some(serde_json::Value::Number(n)) => expected.push(n.as_f64().unwrap()),
            _ => {
                // missing or not a number: an error naming a required field
                let err = event
                    .as_ref()
                    .expect_err(&format!("field `{field}` bad in {text}, accepted"));
                assert!(
                    spec.fields
                        .iter()
                        .any(|f| err.contains(&format!("field `{f}`"))),
                    "{err} (payload {text})"
                );
                return;
            }
        }
    }
    let got = event
        .as_ref()
        .unwrap_or_else(|e| panic!("serde_json reads {text}, we refused: {e}"));
    let want: Vec<String> = expected.iter().map(|v| format!("{v:?}")).collect();
    for (field, v) in spec.fields.iter().zip(&want) {
        assert!(
            got.contains(&format!("{field}: {v}")),
            "{field} should be {v} in {got} (payload {text})"
        );
    }
}

#[test]
fn fuzz_generated_json() {
    fuzz("decode/generated_json", 300, &json_log(), check_json);
}

// ---------------------------------------------------------------- exhaustive truncation and splits

/// Every prefix of a log and every two-piece split of it, in three layouts:
/// a prefix yields a prefix of the events and `finish` is `Ok` exactly when
/// it stops between records; a split changes nothing; the whole-file reader
/// refuses every proper prefix.
#[test]
fn every_truncation_and_every_two_piece_split() {
    let written = &samples()[..12];
    for (compression, chunk_size) in [
        (Compression::None, None),
        (Compression::None, Some(200)),
        (Compression::Zstd, Some(200)),
    ] {
        let bytes = write_bytes(
            written,
            WriteOptions {
                compression,
                chunk_size,
            },
        );
        let full = stream(&bytes, &[]);
        assert!(full.end.is_ok() && !full.fatal && full.saw_end, "{full:?}");
        assert_eq!(full.samples.len(), written.len());
        let mut boundaries: BTreeSet<usize> = [0, 8, bytes.len()].into();
        boundaries.extend(
            records(&bytes)
                .into_iter()
                .filter(|&(start, _)| bytes[start] != OP_FOOTER)
                .map(|(_, end)| end),
        );
        for cut in 0..=bytes.len() {
            let part = stream(&bytes[..cut], &[]);
            let ok: Vec<_> = part.events.iter().take_while(|e| e.is_ok()).collect();
            assert!(
                ok.iter().zip(&full.events).all(|(a, b)| *a == b),
                "cut {cut}: not a prefix"
            );
            assert_eq!(
                part.end.is_ok(),
                boundaries.contains(&cut),
                "cut {cut} of {}: {:?}",
                bytes.len(),
                part.end
            );
            let split = stream(&bytes, &[cut.max(1), bytes.len()]);
            assert_eq!(split.outcome(), full.outcome(), "split at {cut}");
            if cut < bytes.len() {
                let err = read_log_bytes(SOURCE, &bytes[..cut]).unwrap_err();
                check_error(&err);
            }
        }
    }
}

// ---------------------------------------------------------------- regressions

/// Every crash the fuzzer found, kept as a file in
/// `tests/fixtures/fuzz-regressions/` and checked in several splits.
#[test]
fn fuzz_regressions() {
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/fuzz-regressions");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert!(
        !files.is_empty(),
        "no regression inputs in {}",
        dir.display()
    );
    for path in files {
        let bytes = std::fs::read(&path).unwrap();
        for pieces in [&[1][..], &[4, 47], &[7], &[100_000]] {
            check_bytes(&bytes, pieces);
        }
    }
}
