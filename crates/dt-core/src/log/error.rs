//! The one error type of the `log` module.

/// Everything that can go wrong writing or reading a shocktwin run log.
///
/// `file` is the path of the file (or the source name given to
/// [`read_log_bytes`](super::read_log_bytes) / [`LogDecoder::new`](super::LogDecoder::new)).
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// Opening, reading or writing the file failed.
    #[error("{file}: {source}")]
    Io {
        /// File or source name.
        file: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The bytes are not valid MCAP (bad magic, bad record, bad CRC, ...).
    #[error("{file}: not a valid MCAP file: {reason}")]
    Mcap {
        /// File or source name.
        file: String,
        /// What the MCAP layer found.
        reason: String,
    },
    /// The file or stream ended in the middle of a record (or before the end magic).
    #[error("{file}: truncated MCAP: {reason}")]
    Truncated {
        /// File or source name.
        file: String,
        /// Where it ended.
        reason: String,
    },
    /// A record declares a length larger than the configured limit; nothing
    /// of that size was allocated.
    #[error("{file}: {what} declares {len} bytes, over the limit of {limit} bytes")]
    TooLarge {
        /// File or source name.
        file: String,
        /// Which record (e.g. `record with opcode 0x06`, `chunk (uncompressed)`).
        what: String,
        /// The declared length.
        len: u64,
        /// The limit in force.
        limit: u64,
    },
    /// The `shocktwin.run` metadata record is missing (or comes after the
    /// first message in a stream).
    #[error("{file}: metadata record `shocktwin.run` {reason}")]
    MissingMetadata {
        /// File or source name.
        file: String,
        /// `is missing`, `comes after the first message`, ...
        reason: String,
    },
    /// A `shocktwin.run` key is missing or its value is invalid.
    #[error("{file}: metadata `shocktwin.run` key `{key}`: {reason}")]
    InvalidMetadata {
        /// File or source name.
        file: String,
        /// The key at fault (`asset_id`, `run_id`, ...).
        key: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A known topic's channel does not use the `json` message encoding.
    #[error("{file}: topic `{topic}`: message encoding `{encoding}` is not `json`")]
    Encoding {
        /// File or source name.
        file: String,
        /// The topic.
        topic: String,
        /// The encoding found.
        encoding: String,
    },
    /// A known topic's schema does not match the format (SPEC §2): not
    /// `jsonschema`, not valid JSON, lacking a field the format requires, or
    /// declaring it other than a number.
    #[error("{file}: topic `{topic}`: schema field `{field}`: {detail}")]
    Schema {
        /// File or source name.
        file: String,
        /// The topic.
        topic: String,
        /// The field the schema gets wrong (the topic's first for a schema
        /// that is wrong as a whole).
        field: String,
        /// What is wrong.
        detail: String,
    },
    /// A message of a known topic could not be decoded (a field is missing or
    /// not a number). Non-fatal in the whole-file reader (see `RunLog::problems`).
    #[error("{file}: topic `{topic}` message at t_ns={t_ns}: field `{field}`: {reason}")]
    Message {
        /// File or source name.
        file: String,
        /// The topic.
        topic: String,
        /// The message's `log_time`.
        t_ns: i64,
        /// The field at fault.
        field: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A time stamp cannot be written (MCAP times are unsigned nanoseconds).
    #[error("{file}: topic `{topic}`: t_ns={t_ns} is negative; MCAP log_time is unsigned")]
    NegativeTime {
        /// File or source name.
        file: String,
        /// The topic.
        topic: String,
        /// The time stamp.
        t_ns: i64,
    },
    /// Serialising a message to JSON failed.
    #[error("{file}: topic `{topic}`: cannot serialise message: {reason}")]
    Serialize {
        /// File or source name.
        file: String,
        /// The topic.
        topic: String,
        /// `serde_json`'s reason.
        reason: String,
    },
}

impl LogError {
    pub(crate) fn mcap(file: &str, err: &mcap::McapError) -> Self {
        match err {
            mcap::McapError::UnexpectedEof | mcap::McapError::UnexpectedEoc => {
                LogError::Truncated {
                    file: file.to_owned(),
                    reason: err.to_string(),
                }
            }
            mcap::McapError::Io(io) => LogError::Io {
                file: file.to_owned(),
                source: std::io::Error::new(io.kind(), io.to_string()),
            },
            _ => LogError::Mcap {
                file: file.to_owned(),
                reason: err.to_string(),
            },
        }
    }
}
