//! Reading one tabular export: find the header, parse every mapped cell,
//! convert to SPEC units. A bad row is an error naming the file, the line
//! and the column, unless rows may be skipped — then it is counted by
//! reason (with the first line) and left out.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::Path;

use anyhow::{bail, Context as _};

use super::map::{Mapping, TimeFormat};

/// The mapped columns of one file, in SPEC units, rows in time order.
#[derive(Debug, Default)]
pub struct Table {
    /// Sample times, ns (UTC epoch for absolute formats, else since 0).
    pub t_ns: Vec<i64>,
    /// One vector per mapped value column, in [`Mapping::columns`] order
    /// after the time.
    pub values: Vec<Vec<f64>>,
    /// Line number of each kept row.
    pub lines: Vec<u64>,
    /// Skipped rows by reason: (count, first line).
    pub skipped: BTreeMap<String, (u64, u64)>,
    /// Data rows read (kept + skipped).
    pub rows: u64,
    /// A units row under the header, passed over: its line and cells.
    pub units_row: Option<(u64, Vec<String>)>,
    /// Lines where a time of day without a date crossed midnight.
    pub midnights: Vec<u64>,
    /// Blank cells of a thermocouple column (a slow channel written only
    /// every so many rows) read as the value above them (the first value,
    /// before it): per such column, its name and how many.
    pub held: Vec<(String, u64)>,
    /// A thermocouple's error values (outside [`THERMOCOUPLE_RANGE_C`]),
    /// read as blank cells: per such column, its name and how many.
    pub error_values: Vec<(String, u64)>,
}

/// A thermocouple cell outside this range (°C) is its error value (an open
/// circuit's −999 °F, below absolute zero; or hotter than any damper runs),
/// read as a blank cell: a held value in a row kept, not a dropped row.
pub const THERMOCOUPLE_RANGE_C: (f64, f64) = (-273.15, 300.0);

/// A time of day going back by more than this is the next day's (a logger
/// stamping `hh:mm:ss` runs across midnight); less is a time going back.
const MIDNIGHT_JUMP_NS: i64 = 12 * 3600 * 1_000_000_000;
const DAY_NS: i64 = 24 * 3600 * 1_000_000_000;

impl Table {
    fn skip(&mut self, reason: String, line: u64) {
        self.skipped.entry(reason).or_insert((0, line)).0 += 1;
    }

    /// The rows `r` alone (their values, times and lines; no skip counts).
    #[must_use]
    pub fn slice(&self, r: std::ops::Range<usize>) -> Table {
        Table {
            t_ns: self.t_ns[r.clone()].to_vec(),
            values: self.values.iter().map(|v| v[r.clone()].to_vec()).collect(),
            lines: self.lines[r.clone()].to_vec(),
            skipped: BTreeMap::new(),
            rows: r.len() as u64,
            units_row: None,
            midnights: Vec::new(),
            held: Vec::new(),
            error_values: Vec::new(),
        }
    }

    /// Drops the rows where `bad` is true, counted as skipped for `reason`.
    pub fn drop_rows(&mut self, bad: &[bool], reason: &str) {
        for (i, _) in bad.iter().enumerate().filter(|(_, b)| **b) {
            self.skip(reason.to_owned(), self.lines[i]);
        }
        keep_rows(&mut self.t_ns, bad);
        keep_rows(&mut self.lines, bad);
        for v in &mut self.values {
            keep_rows(v, bad);
        }
    }

    /// Total skipped rows.
    #[must_use]
    pub fn skipped_rows(&self) -> u64 {
        self.skipped.values().map(|(n, _)| n).sum()
    }
}

/// `v` without the rows where `bad` is true.
fn keep_rows<T>(v: &mut Vec<T>, bad: &[bool]) {
    let mut k = bad.iter();
    v.retain(|_| !k.next().copied().unwrap_or(false));
}

/// Line numbers of byte offsets of a file, whatever its line ends: `\n`,
/// `\r\n`, or a lone `\r` ("CSV (Macintosh)" exports). The `csv` crate
/// counts `\n` alone, so a file of `\r` ends was all "line 1" in errors.
/// Reads the file a second time, alongside the CSV reader, never more than
/// once through.
struct LineCounter {
    input: BufReader<Text>,
    /// Bytes consumed.
    at: u64,
    /// Line ends passed (a `\r\n` counts once).
    ends: u64,
    /// The last byte consumed was a `\r`.
    after_cr: bool,
}

impl LineCounter {
    fn open(
        path: &Path,
        encoding: Option<&'static encoding_rs::Encoding>,
    ) -> std::io::Result<Self> {
        Ok(Self {
            input: BufReader::new(open_text(path, encoding)?),
            at: 0,
            ends: 0,
            after_cr: false,
        })
    }

    /// The 1-based line of the record that starts at byte offset `byte`:
    /// the line of its first byte after any blank lines, which the `csv`
    /// crate counts into the record that follows them (offsets must not
    /// decrease; the file's end stops the count).
    fn line_at(&mut self, byte: u64) -> std::io::Result<u64> {
        loop {
            let buf = self.input.fill_buf()?;
            let Some(&next) = buf.first() else { break };
            let n = if self.at < byte {
                buf.len()
                    .min(usize::try_from(byte - self.at).unwrap_or(usize::MAX))
            } else if matches!(next, b'\r' | b'\n') {
                1 // a blank line before the record's first byte
            } else {
                break;
            };
            for &b in &buf[..n] {
                match b {
                    b'\r' => self.ends += 1,
                    b'\n' if !self.after_cr => self.ends += 1,
                    _ => {}
                }
                self.after_cr = b == b'\r';
            }
            self.input.consume(n);
            self.at += n as u64;
        }
        Ok(self.ends + 1)
    }
}

/// A file's text as UTF-8: transcoded from `encoding`, or without one from
/// what a byte-order mark says (UTF-8, UTF-16), else passed through as UTF-8.
type Text = encoding_rs_io::DecodeReaderBytes<std::fs::File, Vec<u8>>;

fn open_text(
    path: &Path,
    encoding: Option<&'static encoding_rs::Encoding>,
) -> std::io::Result<Text> {
    Ok(encoding_rs_io::DecodeReaderBytesBuilder::new()
        .encoding(encoding)
        .build(std::fs::File::open(path)?))
}

/// A record the CSV reader could not read; text that is not UTF-8 when no
/// encoding was given says how to give it, naming the line (`line_at`: the
/// line of a byte offset, [`LineCounter::line_at`]).
fn unreadable(
    path: &Path,
    err: csv::Error,
    map: &Mapping,
    line_at: impl FnOnce(u64) -> anyhow::Result<u64>,
) -> anyhow::Error {
    let file = path.display();
    let hint = match err.kind() {
        csv::ErrorKind::Utf8 { .. } if map.encoding.is_none() && utf16_of(path).is_some() => {
            utf16_hint(utf16_of(path).unwrap_or_default())
        }
        csv::ErrorKind::Utf8 { pos, .. } if map.encoding.is_none() => {
            let line = line_at(pos.as_ref().map_or(0, csv::Position::byte));
            format!(
                ": line {} is not UTF-8; give the file's encoding, e.g. encoding = \"windows-1252\" \
                 in the mapping or --encoding windows-1252 for a CSV of Excel on Windows",
                line.map_or_else(|_| "?".to_owned(), |l| l.to_string())
            )
        }
        _ => String::new(),
    };
    anyhow::Error::new(err).context(format!("{file}: not readable as CSV{hint}"))
}

/// The first bytes of a file read for a hint (never more).
const HINT_BYTES: u64 = 64 * 1024;

/// `"utf-16le"` or `"utf-16be"` when the file's first bytes are text in it
/// without a byte-order mark: ASCII in UTF-16 has a NUL in every other
/// byte, which passes as UTF-8 (and names no column).
fn utf16_of(path: &Path) -> Option<&'static str> {
    use std::io::Read as _;
    let mut head = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(HINT_BYTES).read_to_end(&mut head))
        .ok()?;
    if head.len() < 4 || head.starts_with(&[0xFF, 0xFE]) || head.starts_with(&[0xFE, 0xFF]) {
        return None;
    }
    let pairs = head.len() / 2;
    let (mut even, mut odd) = (0, 0);
    for pair in head.chunks_exact(2) {
        even += usize::from(pair[0] == 0);
        odd += usize::from(pair[1] == 0);
    }
    if odd * 2 > pairs && even * 10 < pairs {
        Some("utf-16le")
    } else if even * 2 > pairs && odd * 10 < pairs {
        Some("utf-16be")
    } else {
        None
    }
}

fn utf16_hint(label: &str) -> String {
    format!(
        ": it reads as {} without a byte-order mark; give encoding = \"{label}\" in the mapping \
         or --encoding {label}",
        label.to_uppercase()
    )
}

/// Why no row named every mapped column, when the file's start says: text
/// in UTF-16 without a byte-order mark, or a row that another delimiter
/// splits into the mapped names (a `;` export read at `,`). Empty if
/// neither.
fn header_hint(path: &Path, map: &Mapping, wanted: &[&str]) -> String {
    use std::io::Read as _;
    if map.encoding.is_none() {
        if let Some(label) = utf16_of(path) {
            return utf16_hint(label);
        }
    }
    let mut head = Vec::new();
    if std::fs::File::open(path)
        .and_then(|f| f.take(HINT_BYTES).read_to_end(&mut head))
        .is_err()
    {
        return String::new();
    }
    let (text, _, _) = map.encoding.unwrap_or(encoding_rs::UTF_8).decode(&head);
    for delimiter in [b',', b';', b'\t', b'|'] {
        if delimiter == map.delimiter {
            continue;
        }
        let mut reader = csv::ReaderBuilder::new()
            .has_headers(false)
            .flexible(true)
            .delimiter(delimiter)
            .trim(csv::Trim::All)
            .from_reader(text.as_bytes());
        for record in reader.records() {
            let Ok(record) = record else { break };
            if wanted.iter().all(|w| record.iter().any(|c| c == *w)) {
                let byte = record.position().map_or(0, csv::Position::byte);
                let before = &text.as_bytes()[..usize::try_from(byte).unwrap_or(0).min(text.len())];
                // line ends before it: `\n`, `\r\n` or a lone `\r`
                let (mut line, mut prev) = (1, 0u8);
                for &b in before {
                    if b == b'\r' || (b == b'\n' && prev != b'\r') {
                        line += 1;
                    }
                    prev = b;
                }
                let (toml, flag) = match delimiter {
                    b'\t' => ("\\t".to_owned(), "tab".to_owned()),
                    d => (char::from(d).to_string(), format!("'{}'", char::from(d))),
                };
                return format!(
                    ": line {line} names them all when split at {flag}; give delimiter = \"{toml}\" \
                     in the mapping or --delimiter {flag}"
                );
            }
        }
    }
    String::new()
}

/// Reads `path` with `map`; `skip_bad` counts bad rows instead of failing.
#[allow(clippy::too_many_lines)] // header search, then the row loop with its two error paths
pub fn read(path: &Path, map: &Mapping, skip_bad: bool) -> anyhow::Result<Table> {
    let file = path.display().to_string();
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .delimiter(map.delimiter)
        .trim(csv::Trim::All)
        .from_reader(
            open_text(path, map.encoding).with_context(|| format!("{file}: cannot open"))?,
        );
    let mut lines =
        LineCounter::open(path, map.encoding).with_context(|| format!("{file}: cannot open"))?;
    let mut line_at = |byte: u64| -> anyhow::Result<u64> {
        lines
            .line_at(byte)
            .with_context(|| format!("{file}: cannot read"))
    };
    let byte_of = |record: &csv::StringRecord| record.position().map_or(0, csv::Position::byte);
    let wanted = map.columns();
    let mut records = reader.records();
    // The row naming the most mapped columns, should none name them all:
    // (how many, its line, its cells).
    let mut nearest: Option<(usize, u64, Vec<String>)> = None;
    // The header: the given line, or the first row naming every mapped column.
    let (header, header_line) = loop {
        let Some(record) = records.next() else {
            match (map.header_line, nearest) {
                (Some(n), _) => bail!("{file}: the file ends before header line {n}"),
                (None, Some((_, line, cells))) => {
                    let missing: Vec<&str> = wanted
                        .iter()
                        .copied()
                        .filter(|w| !cells.iter().any(|c| c == w))
                        .collect();
                    bail!(
                        "{file}: no header row names all the mapped columns {wanted:?}: line {line}, \
                         the nearest, has no {missing:?} (its columns: {cells:?}; give header_line \
                         if the names differ){}",
                        header_hint(path, map, &wanted)
                    )
                }
                (None, None) => bail!(
                    "{file}: no row names any of the mapped columns {wanted:?} (give header_line \
                     if the names differ){}",
                    header_hint(path, map, &wanted)
                ),
            }
        };
        let record = record.map_err(|e| unreadable(path, e, map, &mut line_at))?;
        let line = line_at(byte_of(&record))?;
        let found = if let Some(n) = map.header_line {
            line as usize == n
        } else {
            let named = wanted
                .iter()
                .filter(|w| record.iter().any(|c| c == **w))
                .count();
            if named > 0 && nearest.as_ref().is_none_or(|(n, ..)| named > *n) {
                nearest = Some((named, line, record.iter().map(str::to_owned).collect()));
            }
            named == wanted.len()
        };
        if found {
            break (record, line);
        }
    };
    let mut index = Vec::with_capacity(wanted.len());
    for w in &wanted {
        let i = header.iter().position(|c| c == *w).with_context(|| {
            format!(
                "{file}:{header_line}: no column {w:?} in the header (columns: {:?})",
                header.iter().collect::<Vec<_>>()
            )
        })?;
        // Two columns of one name (a spare channel copied): the first was
        // read without a word, whichever held the data.
        let fields: Vec<usize> = (0..header.len()).filter(|&k| &header[k] == *w).collect();
        if fields.len() > 1 {
            bail!(
                "{file}:{header_line}: column {w:?} is in the header {} times (fields {}): \
                 which one to read is not for the import to guess; rename them in the file",
                fields.len(),
                fields
                    .iter()
                    .map(|k| (k + 1).to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        index.push(i);
    }
    let scales: Vec<(f64, f64)> = map
        .value_columns()
        .into_iter()
        .map(|c| (c.scale, c.offset))
        .collect();
    let mut table = Table {
        values: vec![Vec::new(); wanted.len() - 1],
        ..Table::default()
    };
    let mut time_format = map.time_format.clone();
    let time_of_day = matches!(&map.time_format, TimeFormat::Layout(l) if l.is_time_of_day());
    let mut day_ns = 0_i64;
    // A thermocouple written once in so many rows, blank between (a common
    // export): each blank cell holds the value above it. Read as a bad row
    // instead, `--skip-bad-rows` kept 71 rows of 70,001 (a helper's trial).
    let is = |o: Option<&crate::cmd_import::map::Column>, c: &crate::cmd_import::map::Column| {
        o.is_some_and(|o| std::ptr::eq(o, c))
    };
    let holds: Vec<bool> = map
        .value_columns()
        .into_iter()
        .map(|c| is(map.temp_shock.as_ref(), c) || is(map.temp_ambient.as_ref(), c))
        .collect();
    let mut held = vec![0_u64; holds.len()];
    let mut errors = vec![0_u64; holds.len()];
    let mut row = vec![f64::NAN; wanted.len() - 1];
    // a row is parsed into `scratch`, and taken into `row` (the last kept
    // row, whose values blank cells hold) only when it is kept
    let mut scratch = row.clone();
    let mut blank = vec![false; holds.len()];
    let mut error = vec![false; holds.len()];
    for record in records {
        let record = record.map_err(|e| unreadable(path, e, map, &mut line_at))?;
        let line = line_at(byte_of(&record))?;
        if record.iter().all(str::is_empty) {
            continue; // blank line
        }
        if table.rows == 0 && table.units_row.is_none() {
            if let Some(cells) = units_row(&record, &index, map.decimal) {
                // `s, mm, N, °C` under the header: not data (it failed the file as
                // "not an ISO-8601 time", or was a skipped bad row)
                table.units_row = Some((line, cells));
                continue;
            }
        }
        table.rows += 1;
        scratch.copy_from_slice(&row);
        match parse_row(
            &record,
            &wanted,
            &index,
            &scales,
            map.decimal,
            &mut time_format,
            &mut RowOut {
                values: &mut scratch,
                holds: &holds,
                blank: &mut blank,
                error: &mut error,
            },
        ) {
            Ok(t_ns) => {
                let mut t_ns = t_ns + day_ns;
                if let Some(&prev) = table.t_ns.last() {
                    if time_of_day && prev - t_ns > MIDNIGHT_JUMP_NS {
                        day_ns += DAY_NS;
                        t_ns += DAY_NS;
                        table.midnights.push(line);
                    }
                }
                if let Some(&prev) = table.t_ns.last() {
                    if t_ns <= prev {
                        let prev_line = table.lines.last().copied().unwrap_or(0);
                        let reason = format!("column {:?}: time not increasing", wanted[0]);
                        if skip_bad {
                            table.skip(reason, line);
                            continue;
                        }
                        bail!(
                            "{file}:{line}: column {:?}: time {:?} is not after line {prev_line}'s ({:.6} s earlier or equal)",
                            wanted[0],
                            record.get(index[0]).unwrap_or(""),
                            // i128: saturated times (±9.2e9 s) must not overflow
                            (i128::from(prev) - i128::from(t_ns)) as f64 * 1e-9
                        );
                    }
                }
                table.t_ns.push(t_ns);
                table.lines.push(line);
                row.copy_from_slice(&scratch);
                for (col, v) in table.values.iter_mut().zip(&row) {
                    col.push(*v);
                }
                for k in 0..holds.len() {
                    held[k] += u64::from(blank[k]);
                    errors[k] += u64::from(error[k]);
                }
            }
            Err(bad) => {
                if skip_bad {
                    table.skip(bad.reason, line);
                } else {
                    bail!("{file}:{line}: {}", bad.message);
                }
            }
        }
    }
    if table.t_ns.len() < 2 {
        bail!(
            "{file}: {} usable data rows after the header at line {header_line}: nothing to import",
            table.t_ns.len()
        );
    }
    for (k, values) in table.values.iter_mut().enumerate() {
        if !holds[k] {
            continue;
        }
        // blank cells before the column's first value take that value
        let Some(first) = values.iter().copied().find(|v| v.is_finite()) else {
            bail!(
                "{file}: column {:?}: every cell is empty or a thermocouple's error value",
                wanted[k + 1]
            );
        };
        for v in values.iter_mut().take_while(|v| v.is_nan()) {
            *v = first;
        }
        if held[k] > 0 {
            table.held.push((wanted[k + 1].to_owned(), held[k]));
        }
        if errors[k] > 0 {
            table
                .error_values
                .push((wanted[k + 1].to_owned(), errors[k]));
        }
    }
    Ok(table)
}

/// The mapped cells of `record` if it reads as a units row: some cell
/// written, and not one of them a number (`s`, `[mm]`, `kN`, `°C`).
fn units_row(record: &csv::StringRecord, index: &[usize], decimal: u8) -> Option<Vec<String>> {
    let cells: Vec<&str> = index
        .iter()
        .map(|&i| record.get(i).unwrap_or("").trim())
        .collect();
    let number = |c: &str| with_point(c, decimal, true).is_ok_and(|t| t.parse::<f64>().is_ok());
    let any_text = cells.iter().any(|c| !c.is_empty());
    let letters = cells
        .iter()
        .all(|c| c.is_empty() || c.chars().any(char::is_alphabetic) || c.contains('°'));
    (any_text && letters && !cells.iter().any(|c| number(c)))
        .then(|| cells.iter().map(|c| (*c).to_owned()).collect())
}

/// `text` with its decimal separator `decimal` (`.` or `,`) read as a
/// point. With a decimal comma, a point is refused unless `point_ok`: in
/// `1.234,5` it separates thousands, and `1.234` read as a decimal would be
/// a thousand times off without a word.
fn with_point(text: &str, decimal: u8, point_ok: bool) -> Result<Cow<'_, str>, String> {
    if decimal == b'.' {
        return Ok(Cow::Borrowed(text));
    }
    if !point_ok && text.contains('.') {
        return Err(format!(
            "{text:?} has a \".\" while the decimal separator is \",\" (thousands separators are not read)"
        ));
    }
    Ok(if text.contains(',') {
        Cow::Owned(text.replace(',', "."))
    } else {
        Cow::Borrowed(text)
    })
}

/// A hint for a number that reads with a decimal comma when the mapping
/// expects a point (a European export, mapped without `decimal`).
fn comma_hint(text: &str, decimal: u8) -> &'static str {
    let reads = || text.replace(',', ".").trim().parse::<f64>().is_ok();
    if decimal == b'.' && text.contains(',') && reads() {
        " (written with a decimal comma? give decimal = \",\" in the mapping, or --decimal ',', \
         with the file's own delimiter, e.g. ';')"
    } else {
        ""
    }
}

/// Why a row was rejected: a full message and a short reason to count.
struct BadRow {
    message: String,
    reason: String,
}

/// Where [`parse_row`] puts a row: its values (SPEC units, a blank cell of
/// a column that `holds` left as it was), and for those columns whether the
/// cell was blank, or an error value read as blank.
struct RowOut<'a> {
    values: &'a mut [f64],
    holds: &'a [bool],
    blank: &'a mut [bool],
    error: &'a mut [bool],
}

fn parse_row(
    record: &csv::StringRecord,
    names: &[&str],
    index: &[usize],
    scales: &[(f64, f64)],
    decimal: u8,
    time_format: &mut TimeFormat,
    out: &mut RowOut<'_>,
) -> Result<i64, BadRow> {
    let RowOut {
        values: row,
        holds,
        blank,
        error,
    } = out;
    blank.fill(false);
    error.fill(false);
    let cell = |k: usize| -> Result<&str, BadRow> {
        record.get(index[k]).ok_or_else(|| BadRow {
            message: format!(
                "column {:?}: missing (the row has {} fields, the column is field {})",
                names[k],
                record.len(),
                index[k] + 1
            ),
            reason: format!("column {:?}: missing field", names[k]),
        })
    };
    let time_text = cell(0)?;
    let t_ns = if let TimeFormat::Layout(layout) = time_format {
        // a layout says itself how its fraction is written
        layout.parse(time_text)
    } else {
        // An ISO-8601 time keeps its point whatever the numbers' separator.
        let iso = time_text.contains(':');
        with_point(time_text, decimal, iso).and_then(|text| {
            parse_time(&text, time_format).map_err(|why| match text {
                // named as the file writes it
                Cow::Owned(read) => format!("{why} (the cell {time_text:?} read as {read:?})"),
                Cow::Borrowed(_) => format!("{why}{}", comma_hint(time_text, decimal)),
            })
        })
    }
    .map_err(|why| BadRow {
        message: format!("column {:?}: {why}", names[0]),
        reason: format!("column {:?}: unreadable time", names[0]),
    })?;
    for k in 1..names.len() {
        let raw = cell(k)?;
        if raw.is_empty() && holds[k - 1] {
            blank[k - 1] = true; // the row keeps the value above (NaN before any)
            continue;
        }
        let text = with_point(raw, decimal, false).map_err(|why| BadRow {
            message: format!("column {:?}: {why}", names[k]),
            reason: format!("column {:?}: a point in a decimal-comma number", names[k]),
        })?;
        let v: f64 = text.parse().unwrap_or(f64::NAN);
        if !v.is_finite() {
            let what = if raw.is_empty() {
                "empty".to_owned()
            } else {
                format!("{raw:?} is not a finite number{}", comma_hint(raw, decimal))
            };
            return Err(BadRow {
                message: format!("column {:?}: {what}", names[k]),
                reason: format!("column {:?}: empty or not a number", names[k]),
            });
        }
        let (scale, offset) = scales[k - 1];
        let si = scale * v + offset;
        if !si.is_finite() {
            // e.g. 1e308 kN, or a non-finite mid_stroke in the mapping (found by fuzzing)
            return Err(BadRow {
                message: format!(
                    "column {:?}: {raw:?} is out of range in SPEC units",
                    names[k]
                ),
                reason: format!("column {:?}: out of range", names[k]),
            });
        }
        if holds[k - 1] && !(THERMOCOUPLE_RANGE_C.0..=THERMOCOUPLE_RANGE_C.1).contains(&si) {
            error[k - 1] = true; // read as blank: the value above holds
            continue;
        }
        row[k - 1] = si;
    }
    Ok(t_ns)
}

/// Parses one time cell; `Auto` settles on the first row's format.
fn parse_time(text: &str, format: &mut TimeFormat) -> Result<i64, String> {
    if *format == TimeFormat::Auto {
        // Settled by the first cell that reads: a units row under the
        // header (`s`) must not settle it (it settled on ISO-8601, and every
        // numeric row after it failed).
        let mut guess = match text.parse::<f64>() {
            // beyond 1e11 s is the year 5138: milliseconds since the epoch
            Ok(x) if x.abs() > 1e11 => TimeFormat::EpochMs,
            Ok(x) if x > 1e8 => TimeFormat::EpochS,
            Ok(_) => TimeFormat::ElapsedS,
            Err(_) => TimeFormat::Iso8601,
        };
        let t = parse_time(text, &mut guess)?;
        *format = guess;
        return Ok(t);
    }
    let number = |scale: f64| -> Result<i64, String> {
        // An integer count (epoch milliseconds: 1.8e12 ms is 1.8e18 ns,
        // beyond f64's exact integers) is converted exactly.
        if let Ok(n) = text.trim().parse::<i64>() {
            if let Some(ns) = n.checked_mul(scale as i64) {
                return Ok(ns);
            }
        }
        let x: f64 = text
            .parse()
            .map_err(|_| format!("{text:?} is not a number ({} time)", format.key()))?;
        if !x.is_finite() {
            return Err(format!("{text:?} is not a finite time"));
        }
        Ok((x * scale).round() as i64)
    };
    match format {
        TimeFormat::EpochS | TimeFormat::ElapsedS => number(1e9),
        TimeFormat::EpochMs | TimeFormat::ElapsedMs => number(1e6),
        TimeFormat::Iso8601 | TimeFormat::Auto => parse_iso(text),
        TimeFormat::Layout(layout) => layout.parse(text),
    }
}

/// An ISO-8601 time: with `Z` or no zone (taken as UTC; `humantime`'s weak
/// RFC 3339, which takes a space for the `T`), or with a numeric UTC offset
/// (`+01:00`, `-0500`, `+01`), converted to UTC (the `time` crate's RFC
/// 3339). `humantime` never sees an offset: it read `12:00:00.000+01:00` as
/// 12:00 UTC without a word (sixty-first session, trying exports).
fn parse_iso(text: &str) -> Result<i64, String> {
    let ns = if let Some(rfc3339) = with_offset(text) {
        time::OffsetDateTime::parse(&rfc3339, &time::format_description::well_known::Rfc3339)
            .map_err(|e| format!("{text:?} is not an ISO-8601 time with a UTC offset ({e})"))?
            .unix_timestamp_nanos()
    } else {
        let t = humantime::parse_rfc3339_weak(text)
            .map_err(|e| format!("{text:?} is not an ISO-8601 time ({e})"))?;
        let d = t
            .duration_since(std::time::UNIX_EPOCH)
            .map_err(|_| format!("{text:?} is before 1970"))?;
        i128::try_from(d.as_nanos()).unwrap_or(i128::MAX)
    };
    if ns < 0 {
        return Err(format!("{text:?} is before 1970"));
    }
    i64::try_from(ns).map_err(|_| format!("{text:?} is out of range"))
}

/// `text` as RFC 3339 (`T` between date and time, `±HH:MM`) when it ends
/// in a numeric UTC offset after its time of day; `None` otherwise.
fn with_offset(text: &str) -> Option<String> {
    let t = text.trim();
    let (date, rest) = (t.get(..10)?, t.get(11..)?);
    if !matches!(t.as_bytes()[10], b'T' | b't' | b' ') {
        return None;
    }
    let at = rest.rfind(['+', '-'])?;
    let (clock, offset) = rest.split_at(at);
    let digits = &offset[1..];
    if !digits.bytes().all(|b| b.is_ascii_digit() || b == b':') {
        return None;
    }
    let hhmm = match digits.len() {
        2 => format!("{digits}:00"),
        4 if !digits.contains(':') => format!("{}:{}", &digits[..2], &digits[2..]),
        _ => digits.to_owned(),
    };
    Some(format!("{date}T{clock}{}{hhmm}", &offset[..1]))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `t` (elapsed seconds) and `x` (metres, as written), comma-separated,
    /// UTF-8 with decimal points; tests change what they need.
    fn base_map() -> Mapping {
        Mapping {
            header_line: None,
            delimiter: b',',
            decimal: b'.',
            encoding: None,
            time: "t".into(),
            time_format: TimeFormat::ElapsedS,
            position: Some(super::super::map::Column {
                name: "x".into(),
                scale: 1.0,
                offset: 0.0,
            }),
            force: None,
            temp_shock: None,
            temp_ambient: None,
            acceleration: None,
            asset_id: None,
            run_id: None,
            charge: super::super::map::Charge::None,
            frequency_hz: None,
            stroke_pp_m: None,
            metadata: BTreeMap::new(),
        }
    }

    /// Found by the fuzzer: an elapsed time of -7.7e18 s saturates to
    /// `i64::MIN` ns, and the "earlier by" figure overflowed (a panic in a
    /// debug build, a negative number in release).
    #[test]
    fn a_saturated_time_going_backwards_is_reported_without_overflow() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        std::fs::write(&path, "t,x\n0.1,1\n-7742193463672171491,2\n").unwrap();
        let map = base_map();
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(
            err.contains(":3: column \"t\"") && err.contains("(9223372036.954"),
            "{err}"
        );
        // a mapped column missing from the header: the nearest row and what
        // it lacks are named
        std::fs::write(&path, "Stroke,80\nt,y\n0.1,1\n").unwrap();
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(
            err.contains("line 2, the nearest, has no [\"x\"]") && err.contains("[\"t\", \"y\"]"),
            "{err}"
        );
        std::fs::write(&path, "a,b\n0.1,1\n").unwrap();
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(err.contains("no row names any of"), "{err}");
        // a time cell that is not a number names the format as the mapping does
        std::fs::write(&path, "t,x\n0.1,1\nsoon,2\n").unwrap();
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(err.contains("(elapsed_s time)"), "{err}");
        // a finite cell out of range once converted (found by fuzzing)
        std::fs::write(&path, "t,x\n0.1,1\n0.2,1e308\n").unwrap();
        let map = Mapping {
            position: Some(super::super::map::Column {
                name: "x".into(),
                scale: 1e3,
                offset: 0.0,
            }),
            ..map
        };
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(
            err.contains(":3: column \"x\": \"1e308\" is out of range"),
            "{err}"
        );
    }

    /// Found by the fuzzer (`make fuzz`, sixty-first session): a lone `\r`
    /// in a row left two rows on one "line", since the `csv` crate counts
    /// `\n` alone; an export with `\r` line ends (Excel's "CSV
    /// (Macintosh)") named line 1 in every error.
    #[test]
    fn lines_are_counted_whatever_the_line_ends() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        let map = base_map();
        let rows = ["# export", "t,x", "0.1,1", "0.2,2", "", "0.3,oops", "0.4,4"];
        for (ends, bom) in [("\n", ""), ("\r\n", ""), ("\r", ""), ("\r", "\u{feff}")] {
            let text = format!("{bom}{}{ends}", rows.join(ends));
            std::fs::write(&path, &text).unwrap();
            let err = format!("{:#}", read(&path, &map, false).unwrap_err());
            assert!(err.contains(":6: column \"x\""), "{ends:?}: {err}");
            let t = read(&path, &map, true).unwrap();
            assert_eq!(t.lines, [3, 4, 7], "{ends:?}");
            assert_eq!(t.skipped.values().next(), Some(&(1, 6)), "{ends:?}");
        }
        // A mapped column named twice is refused, naming its fields.
        std::fs::write(&path, "t,x,y,x\n0.1,0,1,2\n0.2,0,1,2\n").unwrap();
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(
            err.contains(":1: column \"x\" is in the header 2 times (fields 2, 4)"),
            "{err}"
        );
        // Ends mixed in one file, and a quoted cell across two lines before the header.
        std::fs::write(&path, "\"a\nb\"\r\nt,x\r0.1,1\n0.2,2\r\n0.3,3\r").unwrap();
        assert_eq!(read(&path, &map, false).unwrap().lines, [4, 5, 6]);
        // The header by its line, in a `\r` file.
        std::fs::write(&path, "t,x\rt,x\r0.1,1\r0.2,2\r").unwrap();
        let by_line = Mapping {
            header_line: Some(2),
            ..map
        };
        assert_eq!(read(&path, &by_line, false).unwrap().lines, [3, 4]);
    }

    /// Exports written with a decimal comma (`;` between the fields) read
    /// as with a point; a point there is refused, not read as a decimal.
    #[test]
    fn a_decimal_comma_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        let map = Mapping {
            delimiter: b';',
            decimal: b',',
            time_format: TimeFormat::Auto,
            position: Some(super::super::map::Column {
                name: "x".into(),
                scale: 1e-3,
                offset: 0.0,
            }),
            ..base_map()
        };
        std::fs::write(&path, "t;x\n0,25;1,5\n0,5;-2\n0,75;3,25e1\n").unwrap();
        let t = read(&path, &map, false).unwrap();
        assert_eq!(t.t_ns, [250_000_000, 500_000_000, 750_000_000]);
        assert_eq!(t.values[0], [1.5e-3, -2e-3, 32.5e-3]);
        // ISO times keep their point
        std::fs::write(
            &path,
            "t;x\n2024-05-01T10:00:00.25Z;1,5\n2024-05-01T10:00:00.5Z;2\n",
        )
        .unwrap();
        let t = read(&path, &map, false).unwrap();
        assert_eq!(t.t_ns[1] - t.t_ns[0], 250_000_000);
        // a thousands point is refused, named as the file writes it
        std::fs::write(&path, "t;x\n0,25;1,5\n0,5;1.234,5\n").unwrap();
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(
            err.contains(":3: column \"x\": \"1.234,5\" has a \".\""),
            "{err}"
        );
        std::fs::write(&path, "t;x\n0,25;1,5\n0,5x;2\n").unwrap();
        let err = format!("{:#}", read(&path, &map, false).unwrap_err());
        assert!(err.contains("the cell \"0,5x\" read as \"0.5x\""), "{err}");
        // the same file mapped without the decimal comma: a hint
        std::fs::write(&path, "t;x\n0,25;1,5\n0,5;2\n").unwrap();
        let point = Mapping {
            decimal: b'.',
            ..map
        };
        let err = format!("{:#}", read(&path, &point, false).unwrap_err());
        assert!(err.contains("--decimal ','"), "{err}");
        std::fs::write(&path, "t;x\n0.25;1,5\n0.5;2\n").unwrap();
        let err = format!("{:#}", read(&path, &point, false).unwrap_err());
        assert!(
            err.contains(
                ":2: column \"x\": \"1,5\" is not a finite number (written with a decimal comma?"
            ),
            "{err}"
        );
    }

    /// Exports in a Windows code page or in UTF-16 read as their UTF-8
    /// twin, lines and all; a code page read as UTF-8 says how to give it.
    #[test]
    fn other_encodings_read_as_utf8() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        let map = Mapping {
            delimiter: b';',
            decimal: b',',
            position: None,
            temp_shock: Some(super::super::map::Column {
                name: "T [°C]".into(),
                scale: 1.0,
                offset: 0.0,
            }),
            ..base_map()
        };
        let text = "Prüfstand µ-Test\r\nt;T [°C]\r\n0;25,5\r\n0,5;oops\r\n1;26\r\n";
        std::fs::write(&path, text).unwrap();
        let want = read(&path, &map, true).unwrap();
        assert_eq!(
            (want.lines.as_slice(), want.values[0].as_slice()),
            ([3, 5].as_slice(), [25.5, 26.0].as_slice())
        );
        let cp1252: Vec<u8> = text
            .chars()
            .map(|c| match c {
                'ü' => 0xFC,
                'µ' => 0xB5,
                '°' => 0xB0,
                c => u8::try_from(c).unwrap(),
            })
            .collect();
        std::fs::write(&path, &cp1252).unwrap();
        let err = format!("{:#}", read(&path, &map, true).unwrap_err());
        assert!(
            err.contains("line 1 is not UTF-8") && err.contains("--encoding windows-1252"),
            "{err}"
        );
        // the line is counted as everywhere else: `\r` ends, the `°` on line 2
        let cr = dir.path().join("cr.csv");
        std::fs::write(&cr, b"preamble\rt;T [\xB0C]\r0;25,5\r1;26\r").unwrap();
        let err = format!("{:#}", read(&cr, &map, true).unwrap_err());
        assert!(err.contains("line 2 is not UTF-8"), "{err}");
        let latin = Mapping {
            encoding: Some(encoding_rs::WINDOWS_1252),
            ..map.clone()
        };
        let got = read(&path, &latin, true).unwrap();
        assert_eq!(
            format!("{:?}", (&got.t_ns, &got.values, &got.lines, &got.skipped)),
            format!(
                "{:?}",
                (&want.t_ns, &want.values, &want.lines, &want.skipped)
            )
        );
        // UTF-16 with its byte-order mark: found without being told
        let mut utf16 = vec![0xFF, 0xFE];
        utf16.extend(text.encode_utf16().flat_map(u16::to_le_bytes));
        std::fs::write(&path, &utf16).unwrap();
        let got = read(&path, &map, true).unwrap();
        assert_eq!(
            format!("{:?}", (&got.t_ns, &got.values, &got.lines, &got.skipped)),
            format!(
                "{:?}",
                (&want.t_ns, &want.values, &want.lines, &want.skipped)
            )
        );
    }

    /// UTF-16 without a byte-order mark passes as UTF-8 (its NULs are valid)
    /// and named no column; `;` exports read at `,` named none either. Both
    /// now say what to give, and the file reads once it is given.
    #[test]
    fn a_header_not_found_says_what_the_file_looks_like() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        let text = "Prüfstand\r\nt;x\r\n0;1\r\n0.5;2\r\n1;3\r\n";
        let semi = Mapping {
            delimiter: b';',
            ..base_map()
        };
        // `ü` is not UTF-8 in UTF-16 (the reader's error); ASCII alone is
        // (no header found)
        let ascii = text.replace("Prüfstand", "Pruefstand");
        for (label, bytes) in [
            (
                "utf-16le",
                text.encode_utf16()
                    .flat_map(u16::to_le_bytes)
                    .collect::<Vec<u8>>(),
            ),
            (
                "utf-16be",
                text.encode_utf16().flat_map(u16::to_be_bytes).collect(),
            ),
            (
                "utf-16le",
                ascii.encode_utf16().flat_map(u16::to_le_bytes).collect(),
            ),
        ] {
            std::fs::write(&path, &bytes).unwrap();
            let err = format!("{:#}", read(&path, &semi, false).unwrap_err());
            assert!(
                err.contains(&format!(
                    "without a byte-order mark; give encoding = \"{label}\""
                )),
                "{label}: {err}"
            );
            let given = Mapping {
                encoding: encoding_rs::Encoding::for_label(label.as_bytes()),
                ..semi.clone()
            };
            assert_eq!(read(&path, &given, false).unwrap().lines, [3, 4, 5]);
        }
        // `;` read at `,`: the line that splits into the names
        std::fs::write(&path, text).unwrap();
        let err = format!("{:#}", read(&path, &base_map(), false).unwrap_err());
        assert!(
            err.contains("line 2 names them all when split at ';'; give delimiter = \";\""),
            "{err}"
        );
        std::fs::write(&path, text.replace(';', "\t")).unwrap();
        let err = format!("{:#}", read(&path, &base_map(), false).unwrap_err());
        assert!(
            err.contains("split at tab; give delimiter = \"\\t\""),
            "{err}"
        );
        // nothing to say: no hint
        std::fs::write(&path, "a,b\n0,1\n1,2\n").unwrap();
        let err = format!("{:#}", read(&path, &base_map(), false).unwrap_err());
        assert!(
            err.ends_with("(give header_line if the names differ)"),
            "{err}"
        );
    }

    #[test]
    fn times_in_every_format() {
        let mut f = TimeFormat::Auto;
        assert_eq!(
            parse_time("2023-11-14T22:13:20.003Z", &mut f),
            Ok(1_700_000_000_003_000_000)
        );
        assert_eq!(f, TimeFormat::Iso8601);
        let mut f = TimeFormat::Auto;
        assert_eq!(
            parse_time("1700000000.5", &mut f),
            Ok(1_700_000_000_500_000_000)
        );
        assert_eq!(f, TimeFormat::EpochS);
        let mut f = TimeFormat::Auto;
        assert_eq!(parse_time("0.25", &mut f), Ok(250_000_000));
        let mut f = TimeFormat::ElapsedMs;
        assert_eq!(parse_time("3", &mut f), Ok(3_000_000));
        // A UTC offset is converted, with or without a fraction, a `T` or a
        // colon (the fraction's form was read as UTC, the offset dropped).
        let noon_utc = 1_772_366_400_000_000_000_i64; // 2026-03-01T12:00:00Z
        for (text, hours) in [
            ("2026-03-01T12:00:00.000+01:00", -1),
            ("2026-03-01T12:00:00+01:00", -1),
            ("2026-03-01 12:00:00.5+09:00", -9),
            ("2026-03-01T12:00:00-05:00", 5),
            ("2026-03-01T12:00:00.000-0500", 5),
            ("2026-03-01T12:00:00+01", -1),
            ("2026-03-01T12:00:00Z", 0),
            ("2026-03-01 12:00:00", 0),
        ] {
            let mut f = TimeFormat::Auto;
            let half = if text.contains(".5") { 500_000_000 } else { 0 };
            assert_eq!(
                parse_time(text, &mut f),
                Ok(noon_utc + hours * 3_600_000_000_000 + half),
                "{text}"
            );
            assert_eq!(f, TimeFormat::Iso8601);
        }
        let mut f = TimeFormat::Iso8601;
        assert!(parse_time("2026-03-01T12:00:00+1:0", &mut f).is_err());
        // Milliseconds since the epoch, found by their size.
        let mut f = TimeFormat::Auto;
        assert_eq!(
            parse_time("1772366400002", &mut f),
            Ok(noon_utc + 2_000_000)
        );
        assert_eq!(f, TimeFormat::EpochMs);
        // A cell that reads as no time (a units row) leaves the format open.
        let mut f = TimeFormat::Auto;
        assert!(parse_time("s", &mut f).is_err());
        assert_eq!(f, TimeFormat::Auto);
        assert_eq!(parse_time("0.5", &mut f), Ok(500_000_000));
        assert_eq!(f, TimeFormat::ElapsedS);
    }

    /// A file's own layout: a European date with a decimal comma in the
    /// seconds, one with a UTC offset, and a time of day alone.
    #[test]
    fn times_in_a_layout_of_the_files_own() {
        let noon_utc = 1_772_366_400_000_000_000_i64; // 2026-03-01T12:00:00Z
        let layout =
            |text: &str| TimeFormat::Layout(super::super::map::TimeLayout::new(text).unwrap());
        let mut f = layout("[day].[month].[year] [hour]:[minute]:[second],[subsecond]");
        assert_eq!(
            parse_time("01.03.2026 12:00:00,125", &mut f),
            Ok(noon_utc + 125_000_000)
        );
        let err = parse_time("2026-03-01 12:00:00", &mut f).unwrap_err();
        assert!(
            err.contains("does not match the layout \"[day].[month]"),
            "{err}"
        );
        let mut f =
            layout("[month]/[day]/[year] [hour]:[minute]:[second] [offset_hour]:[offset_minute]");
        assert_eq!(
            parse_time("03/01/2026 13:00:00 +01:00", &mut f),
            Ok(noon_utc)
        );
        let mut f = layout("[hour]:[minute]:[second].[subsecond]");
        assert_eq!(parse_time("12:30:15.5", &mut f), Ok(45_015_500_000_000));
        // read through a whole file with a decimal comma and `;`: the
        // layout's comma is its own, not the numbers'
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        std::fs::write(
            &path,
            "Datum Zeit;x\r\n01.03.2026 12:00:00,000;1,5\r\n01.03.2026 12:00:00,010;2,5\r\n",
        )
        .unwrap();
        let map = Mapping {
            delimiter: b';',
            decimal: b',',
            time: "Datum Zeit".into(),
            time_format: layout("[day].[month].[year] [hour]:[minute]:[second],[subsecond]"),
            ..base_map()
        };
        let got = read(&path, &map, false).unwrap();
        assert_eq!(got.t_ns, [noon_utc, noon_utc + 10_000_000]);
        assert_eq!(got.values[0], [1.5, 2.5]);
    }
}
