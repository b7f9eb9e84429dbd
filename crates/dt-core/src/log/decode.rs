//! The one decoding path from MCAP channels and messages to [`Sample`]s,
//! shared by the whole-file reader, the incremental decoder and `inspect`.

use std::borrow::Cow;

use super::raw::RawChannel;
use super::{topic_spec, LogError, Sample, TopicSpec};

/// What a channel carries, once checked.
#[derive(Debug, Clone, Copy)]
pub(crate) enum ChannelKind {
    /// A SPEC §2 sensor topic with its rank.
    Sample(u8),
    /// Any other topic.
    Unknown,
}

/// Classifies channels and decodes their messages.
#[derive(Debug, Default)]
pub(crate) struct SampleDecoder {
    /// By channel id (a channel id re-used by a later record is re-checked);
    /// ids past the end, like `Unknown`, are not sensor topics. A vector,
    /// not a map: it is looked up once per message.
    kinds: Vec<ChannelKind>,
}

impl SampleDecoder {
    /// Checks a channel record. A known topic must use the `json` message
    /// encoding and, if its schema is `jsonschema`, declare every field.
    pub(crate) fn on_channel(&mut self, file: &str, channel: &RawChannel) -> Result<(), LogError> {
        let kind = match topic_spec(&channel.topic) {
            None => ChannelKind::Unknown,
            Some((rank, spec)) => {
                // Mark unknown until checked, so a bad channel's messages are not decoded.
                self.set_kind(channel.id, ChannelKind::Unknown);
                check_channel(file, channel, spec)?;
                ChannelKind::Sample(rank)
            }
        };
        self.set_kind(channel.id, kind);
        Ok(())
    }

    fn set_kind(&mut self, id: u16, kind: ChannelKind) {
        let i = usize::from(id);
        if self.kinds.len() <= i {
            self.kinds.resize(i + 1, ChannelKind::Unknown);
        }
        self.kinds[i] = kind;
    }

    /// The topic rank of a channel's messages, `None` for a topic this
    /// format does not know (or a channel that failed its check).
    pub(crate) fn rank(&self, channel: &RawChannel) -> Option<u8> {
        match self.kinds.get(usize::from(channel.id)) {
            Some(ChannelKind::Sample(rank)) => Some(*rank),
            _ => None,
        }
    }

    /// Decodes one message: `Ok(None)` for a topic this format does not know.
    pub(crate) fn decode(
        &self,
        file: &str,
        channel: &RawChannel,
        log_time: u64,
        data: &[u8],
    ) -> Result<Option<Sample>, LogError> {
        let Some(rank) = self.rank(channel) else {
            return Ok(None);
        };
        decode_sample(file, rank, log_time, data).map(Some)
    }
}

/// Decodes the JSON message `data` of the sensor topic of rank `rank`
/// (SPEC §2) logged at `log_time`; errors name `file`, the topic and the field.
///
/// `rank` comes from [`SampleDecoder::rank`], so it indexes `TOPICS`.
pub(crate) fn decode_sample(
    file: &str,
    rank: u8,
    log_time: u64,
    data: &[u8],
) -> Result<Sample, LogError> {
    let spec = &super::TOPICS[rank as usize];
    let message_error = |t_ns: i64, field: &str, reason: String| LogError::Message {
        file: file.to_owned(),
        topic: spec.topic.to_owned(),
        t_ns,
        field: field.to_owned(),
        reason,
    };
    let Ok(t_ns) = i64::try_from(log_time) else {
        return Err(message_error(
            i64::MAX,
            "log_time",
            format!("{log_time} does not fit in i64 nanoseconds"),
        ));
    };
    if let Some([v0, v1]) = members_as_written(data, spec.fields) {
        return Ok(Sample::from_rank(rank, t_ns, v0, v1));
    }
    let mut values = [f64::NAN; 2];
    let mut found = [false; 2];
    parse_flat_object(data, |key, value| {
        if let Some(i) = spec.fields.iter().position(|f| f.as_bytes() == key) {
            values[i] = value.map_err(|reason| (spec.fields[i].to_owned(), reason))?;
            found[i] = true;
        }
        Ok(())
    })
    .map_err(|(field, reason)| message_error(t_ns, &field, reason))?;
    for (i, field) in spec.fields.iter().enumerate() {
        if !found[i] {
            return Err(message_error(t_ns, field, "missing".into()));
        }
    }
    let [v0, v1] = values;
    Ok(Sample::from_rank(rank, t_ns, v0, v1))
}

fn check_channel(file: &str, channel: &RawChannel, spec: &TopicSpec) -> Result<(), LogError> {
    if channel.message_encoding != "json" {
        return Err(LogError::Encoding {
            file: file.to_owned(),
            topic: spec.topic.to_owned(),
            encoding: channel.message_encoding.clone(),
        });
    }
    // A channel without a schema is valid MCAP (schemaless JSON): read.
    let Some(schema) = &channel.schema else {
        return Ok(());
    };
    if schema.data.is_empty() {
        return Ok(()); // an empty schema says nothing either
    }
    let schema_error = |field: &str, detail: String| LogError::Schema {
        file: file.to_owned(),
        topic: spec.topic.to_owned(),
        field: field.to_owned(),
        detail,
    };
    if schema.encoding != "jsonschema" {
        return Err(schema_error(
            spec.fields[0],
            format!(
                "schema `{}` is encoded `{}`, not `jsonschema`",
                schema.name, schema.encoding
            ),
        ));
    }
    let parsed: serde_json::Value = serde_json::from_slice(&schema.data).map_err(|e| {
        schema_error(
            spec.fields[0],
            format!("schema `{}` is not valid JSON: {e}", schema.name),
        )
    })?;
    let properties = parsed
        .get("properties")
        .and_then(serde_json::Value::as_object);
    for field in spec.fields {
        let Some(declared) = properties.and_then(|p| p.get(*field)) else {
            return Err(schema_error(
                field,
                format!("schema `{}` has no property `{field}`", schema.name),
            ));
        };
        if let Some(other) = not_a_number(declared) {
            return Err(schema_error(
                field,
                format!(
                    "schema `{}` declares it `{other}`, not a number",
                    schema.name
                ),
            ));
        }
    }
    Ok(())
}

/// The declared `type` of a schema property when it admits no number
/// (neither `number` nor `integer`, alone or in a list: a writer may add
/// `null` for a missing sample); `None` when it admits one or declares none.
fn not_a_number(property: &serde_json::Value) -> Option<String> {
    let numeric = |t: &serde_json::Value| matches!(t.as_str(), Some("number" | "integer"));
    match property.get("type")? {
        serde_json::Value::Array(types) if types.iter().any(numeric) => None,
        t if numeric(t) => None,
        t => Some(t.to_string()),
    }
}

/// The message's numbers when it is written as the writers write it: the
/// topic's fields in SPEC order and nothing else, each a JSON number (a
/// digit first, or `-` and a digit), ASCII whitespace allowed between
/// tokens (Python's `json` puts spaces there). Read without the general
/// parser; anything else — `null`, escapes, other members, another order, a
/// number followed by anything but `,` or `}` — gives `None` and goes
/// through [`parse_flat_object`], which reads what this accepts to the same
/// values (the same number text through the same parser).
fn members_as_written(data: &[u8], fields: &[&str]) -> Option<[f64; 2]> {
    fn ws(b: &[u8]) -> &[u8] {
        let n = b
            .iter()
            .take_while(|c| matches!(c, b' ' | b'\t' | b'\n' | b'\r'))
            .count();
        &b[n..]
    }
    let mut rest = ws(data).strip_prefix(b"{")?;
    let mut out = [f64::NAN; 2];
    for (i, field) in fields.iter().enumerate() {
        if i > 0 {
            rest = ws(rest).strip_prefix(b",")?;
        }
        rest = ws(rest)
            .strip_prefix(b"\"")?
            .strip_prefix(field.as_bytes())?
            .strip_prefix(b"\"")?;
        rest = ws(ws(rest).strip_prefix(b":")?);
        let unsigned = rest.strip_prefix(b"-").unwrap_or(rest);
        if !unsigned.first()?.is_ascii_digit() {
            return None;
        }
        let (value, used) = fast_float2::parse_partial::<f64, _>(rest).ok()?;
        out[i] = value;
        rest = &rest[used..];
        // the general parser's number is the run of `[0-9+-.eE]`: it must end here
        if matches!(
            rest.first(),
            Some(b'0'..=b'9' | b'+' | b'-' | b'.' | b'e' | b'E')
        ) {
            return None;
        }
    }
    ws(ws(rest).strip_prefix(b"}")?).is_empty().then_some(out)
}

/// Parses a flat JSON object, calling `f(key, value)` (the key unescaped,
/// as UTF-8 bytes borrowed from `data` when it has no escapes: no copy, no
/// allocation) for each member whose
/// value is a number (or `null`, `NaN`, `Infinity`, `-Infinity`, all read as
/// NaN: a missing sample); for other values `f` gets `Err(reason)`.
/// Members of other types are passed too, so that a required field with a
/// wrong type is reported; unknown ones are ignored by `f`.
/// The error is `(field, reason)`.
fn parse_flat_object(
    data: &[u8],
    mut f: impl FnMut(&[u8], Result<f64, String>) -> Result<(), (String, String)>,
) -> Result<(), (String, String)> {
    let mut p = Parser { data, pos: 0 };
    let whole = |reason: String| {
        (
            "(whole message)".to_owned(),
            format!("malformed JSON: {reason}"),
        )
    };
    p.ws();
    if !p.eat(b'{') {
        return Err(whole("not a JSON object".into()));
    }
    p.ws();
    if p.eat(b'}') {
        return p.end().map_err(whole);
    }
    loop {
        p.ws();
        let key = p.string().map_err(whole)?;
        let name = || String::from_utf8_lossy(&key).into_owned();
        p.ws();
        if !p.eat(b':') {
            return Err(whole(format!("expected `:` after key {:?}", name())));
        }
        p.ws();
        let value = p
            .value()
            .map_err(|reason| (name(), format!("malformed JSON: {reason}")))?;
        f(&key, value)?;
        p.ws();
        if p.eat(b',') {
            continue;
        }
        if p.eat(b'}') {
            return p.end().map_err(whole);
        }
        return Err(whole("expected `,` or `}` after a member".into()));
    }
}

struct Parser<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Parser<'a> {
    fn ws(&mut self) {
        while let Some(b' ' | b'\t' | b'\n' | b'\r') = self.data.get(self.pos) {
            self.pos += 1;
        }
    }

    fn eat(&mut self, b: u8) -> bool {
        if self.data.get(self.pos) == Some(&b) {
            self.pos += 1;
            true
        } else {
            false
        }
    }

    fn end(&mut self) -> Result<(), String> {
        self.ws();
        if self.pos == self.data.len() {
            Ok(())
        } else {
            Err("trailing bytes after the object".into())
        }
    }

    fn eat_word(&mut self, word: &[u8]) -> bool {
        if self.data[self.pos..].starts_with(word) {
            self.pos += word.len();
            true
        } else {
            false
        }
    }

    /// A JSON string (the opening quote not yet eaten), unescaped, as UTF-8
    /// bytes (checked); borrowed from the message when it has no escapes
    /// (every key the writers write; ASCII checked without a call).
    fn string(&mut self) -> Result<Cow<'a, [u8]>, String> {
        let start = self.pos;
        if !self.eat(b'"') {
            return Err("expected a string".into());
        }
        let mut escaped = false;
        loop {
            match self.data.get(self.pos) {
                None => return Err("unterminated string".into()),
                Some(b'\\') => {
                    escaped = true;
                    self.pos += 2;
                }
                Some(b'"') => {
                    self.pos += 1;
                    break;
                }
                Some(_) => self.pos += 1,
            }
        }
        let raw = self
            .data
            .get(start..self.pos)
            .ok_or_else(|| "unterminated string".to_owned())?;
        if escaped {
            serde_json::from_slice::<String>(raw)
                .map(|s| Cow::Owned(s.into_bytes()))
                .map_err(|e| format!("bad string: {e}"))
        } else {
            let inner = &raw[1..raw.len() - 1];
            if !inner.is_ascii() {
                std::str::from_utf8(inner).map_err(|e| format!("bad string: {e}"))?;
            }
            Ok(Cow::Borrowed(inner))
        }
    }

    /// A member value: `Ok(Ok(number))` for numbers and the NaN spellings,
    /// `Ok(Err(reason))` for a well-formed value of another type,
    /// `Err(reason)` for malformed JSON.
    fn value(&mut self) -> Result<Result<f64, String>, String> {
        let Some(&c) = self.data.get(self.pos) else {
            return Err("missing value".into());
        };
        match c {
            b'n' if self.eat_word(b"null") => Ok(Ok(f64::NAN)),
            b'N' if self.eat_word(b"NaN") => Ok(Ok(f64::NAN)),
            b'I' if self.eat_word(b"Infinity") => Ok(Ok(f64::NAN)),
            b'-' if self.eat_word(b"-Infinity") => Ok(Ok(f64::NAN)),
            b'-' | b'0'..=b'9' => {
                let start = self.pos;
                while let Some(b'0'..=b'9' | b'-' | b'+' | b'.' | b'e' | b'E') =
                    self.data.get(self.pos)
                {
                    self.pos += 1;
                }
                let text = &self.data[start..self.pos];
                fast_float2::parse::<f64, _>(text)
                    .map(Ok)
                    .map_err(|_| format!("malformed number `{}`", String::from_utf8_lossy(text)))
            }
            b'"' => {
                self.string()?;
                Ok(Err("is a string, not a number".into()))
            }
            b't' if self.eat_word(b"true") => Ok(Err("is a boolean, not a number".into())),
            b'f' if self.eat_word(b"false") => Ok(Err("is a boolean, not a number".into())),
            b'{' | b'[' => {
                self.skip_nested()?;
                Ok(Err("is an object or array, not a number".into()))
            }
            _ => Err(format!("unexpected character `{}`", c.escape_ascii())),
        }
    }

    /// Skips a nested object or array, strings included.
    fn skip_nested(&mut self) -> Result<(), String> {
        let mut depth = 0_usize;
        while let Some(&c) = self.data.get(self.pos) {
            match c {
                b'"' => {
                    self.string()?;
                    continue;
                }
                b'{' | b'[' => depth += 1,
                b'}' | b']' => {
                    depth -= 1;
                    if depth == 0 {
                        self.pos += 1;
                        return Ok(());
                    }
                }
                _ => {}
            }
            self.pos += 1;
        }
        Err("unterminated object or array".into())
    }
}

#[cfg(test)]
mod tests {
    use super::{members_as_written, parse_flat_object};

    type Fields = Vec<(String, Result<f64, String>)>;

    fn fields(json: &str) -> Result<Fields, (String, String)> {
        let mut out = Vec::new();
        parse_flat_object(json.as_bytes(), |k, v| {
            out.push((String::from_utf8(k.to_vec()).unwrap(), v));
            Ok(())
        })?;
        Ok(out)
    }

    #[test]
    fn numbers_and_nan_spellings() {
        let got = fields(
            r#" {"a": 1.5e-3, "b":-2, "c": null, "d": NaN, "e": -Infinity, "f": Infinity} "#,
        )
        .unwrap();
        assert_eq!(got[0], ("a".into(), Ok(1.5e-3)));
        assert_eq!(got[1], ("b".into(), Ok(-2.0)));
        for (_, v) in &got[2..] {
            assert!(v.as_ref().unwrap().is_nan());
        }
    }

    #[test]
    fn other_types_and_nesting_are_reported_not_fatal() {
        let got = fields(r#"{"s":"x\"}","o":{"k":[1,{"z":"]"}]},"t":true,"n":3}"#).unwrap();
        assert!(got[0].1.is_err());
        assert!(got[1].1.is_err());
        assert!(got[2].1.is_err());
        assert_eq!(got[3], ("n".into(), Ok(3.0)));
        let esc = fields(r#"{"a\u0062":1}"#).unwrap();
        assert_eq!(esc[0].0, "ab");
    }

    #[test]
    fn malformed_json_is_an_error() {
        for bad in [
            r#"{"a":1"#,
            r#"{"a" 1}"#,
            "[1]",
            r#"{"a":1}x"#,
            r#"{"a":1.2.3}"#,
            r#"{"a":"#,
            "",
        ] {
            assert!(fields(bad).is_err(), "{bad}");
        }
    }

    /// Found by the fuzzer: a malformed value under an empty key gave
    /// an empty field name and "unterminated string"; the reason now says
    /// it is malformed JSON.
    #[test]
    fn a_malformed_value_is_named_malformed_json_with_its_key() {
        for (bad, key) in [(r#"{"": "abc"#, ""), (r#"{"a1_mps2": -x}"#, "a1_mps2")] {
            let (field, reason) = fields(bad).unwrap_err();
            assert_eq!(field, key);
            assert!(reason.starts_with("malformed JSON: "), "{reason}");
        }
    }

    /// What the fast path reads, the general parser reads to the same bits;
    /// what it refuses goes to the general parser.
    #[test]
    fn members_as_written_reads_what_the_general_parser_reads() {
        const F: [&str; 2] = ["a1_mps2", "a2_mps2"];
        let general = |json: &str| -> [u64; 2] {
            let got = fields(json).unwrap();
            [0, 1].map(|i| {
                let (_, v) = got.iter().find(|(k, _)| k == F[i]).unwrap();
                v.clone().unwrap().to_bits()
            })
        };
        let mut cases: Vec<String> = [
            r#"{"a1_mps2":1.5,"a2_mps2":-2e-3}"#,
            " { \"a1_mps2\" :\t0.1 ,\n\"a2_mps2\" : 7 } \r\n",
            r#"{"a1_mps2":1.,"a2_mps2":01}"#,
            r#"{"a1_mps2":-0,"a2_mps2":1E+300}"#,
            r#"{"a1_mps2":1e999,"a2_mps2":5e-400}"#,
            r#"{"a1_mps2":0.30000000000000004,"a2_mps2":-1.7976931348623157e308}"#,
        ]
        .map(String::from)
        .to_vec();
        // the writers' own text (shortest round trip) and Python's (`repr`, spaces)
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        for _ in 0..2000 {
            // a 64-bit LCG: a mantissa in [0, 1) and a decade in 1e-20 .. 1e19
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let x = (state >> 11) as f64 / (1u64 << 53) as f64
                * 10f64.powi(((state >> 3) % 40) as i32 - 20);
            let mut z = zmij::Buffer::new();
            cases.push(format!(
                r#"{{"a1_mps2":{},"a2_mps2":{:e}}}"#,
                z.format_finite(x),
                -x
            ));
            cases.push(format!(r#"{{"a1_mps2": {x:?}, "a2_mps2": {x}}}"#));
        }
        for c in &cases {
            let fast = members_as_written(c.as_bytes(), &F).unwrap_or_else(|| panic!("{c}"));
            assert_eq!(fast.map(f64::to_bits), general(c), "{c}");
        }
        for c in [
            r#"{"a1_mps2":null,"a2_mps2":1}"#,
            r#"{"a1_mps2":NaN,"a2_mps2":1}"#,
            r#"{"a1_mps2":nan,"a2_mps2":1}"#,
            r#"{"a1_mps2":-inf,"a2_mps2":1}"#,
            r#"{"a1_mps2":-Infinity,"a2_mps2":1}"#,
            r#"{"a2_mps2":1,"a1_mps2":2}"#,
            r#"{"a1_mps2":1,"a2_mps2":2,"x":3}"#,
            r#"{"a1_mps2":1,"a1_mps2":2}"#,
            r#"{"a1_mps2":1.5e,"a2_mps2":1}"#,
            r#"{"a1_mps2":1-2,"a2_mps2":1}"#,
            r#"{"a1_mps2":1 2,"a2_mps2":1}"#,
            r#"{"a1_mps2":+1,"a2_mps2":1}"#,
            r#"{"a1_mps2":.5,"a2_mps2":1}"#,
            r#"{"a1_mps2":"1","a2_mps2":1}"#,
            r#"{"a1\u005fmps2":1,"a2_mps2":1}"#,
            r#"{"a1_mps2x":1,"a2_mps2":1}"#,
            r#"{"a1_mps2":1,"a2_mps2":2}x"#,
            r#"{"a1_mps2":1,"a2_mps2":2"#,
            r#"{"a1_mps2":1}"#,
            "",
        ] {
            assert!(members_as_written(c.as_bytes(), &F).is_none(), "{c}");
        }
    }
}
