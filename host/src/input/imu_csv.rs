//! IMU samples from CSV: a header line, then one sample per line with the time (absolute, e.g.
//! Unix time; parsed exactly to the nanosecond), angular rate in rad/s and specific force in
//! m/s^2. Blank lines and lines starting with `#` are skipped; a file without a header starts
//! with data in the order `t,gx,gy,gz,ax,ay,az`, `t` in seconds.
//!
//! The header names the columns, in any order ([`Layout`]): the time as `t`, `time`,
//! `timestamp` or `stamp`, its unit named by a suffix (`t_ns`, `timestamp_us`, `t_ms`, `t_s`)
//! or in brackets (`time [ns]`, `t(ms)`), seconds when none is named; the angular rate as
//! `gx,gy,gz` (also `gyro_x`, `wx`, `w_RS_S_x`, `angular_velocity_x`, ...) and the specific
//! force as `ax,ay,az` (also `acc_x`, `a_RS_S_x`, `linear_acceleration_x`, ...), with units in
//! brackets only if they are rad/s and m/s^2. Other columns are ignored when all seven are
//! named. A first `#` line that reads as such a header (EuRoC's `#timestamp [ns],w_RS_S_x
//! [rad s^-1],...`) is the header. A header that cannot be understood is refused in one line
//! that names it and what was expected: a column taken by position could be the wrong one.
//!
//! Real recordings have bad rows; one must not cost the whole file. Rows with a non-finite
//! value, a wrong number of fields or an unparsable field are dropped and counted; rows are
//! sorted within a window of [`REORDER_ROWS`] rows (loggers with several threads swap
//! neighbours); a row with the time of one already taken (a duplicate), or still out of order
//! after the window, is dropped and counted. The file is refused (one line) only when more than
//! half of its rows are bad. The counts are in [`ImuCsvStats`]; [`load`] and [`parse`] say each
//! kind of drop in one `warning:` line.

use std::collections::BinaryHeap;
use std::io::BufRead;
use std::path::Path;

use loglio_core::imu::ImuSample;

use crate::diag::warn;

/// The canonical header.
pub const HEADER: &str = "t,gx,gy,gz,ax,ay,az";

/// How many rows are held to sort small disorder.
pub const REORDER_ROWS: usize = 50;

/// A CSV problem at a line (1-based).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImuCsvError {
    /// Line number, from 1 (0: the file itself).
    pub line: usize,
    /// What is wrong.
    pub problem: String,
}

impl std::fmt::Display for ImuCsvError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.line == 0 {
            write!(f, "IMU CSV: {}", self.problem)
        } else {
            write!(f, "IMU CSV line {}: {}", self.line, self.problem)
        }
    }
}

impl std::error::Error for ImuCsvError {}

/// What a CSV held and what was dropped, for the run summary.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ImuCsvStats {
    /// Data rows read (after the header; blank and `#` lines not counted).
    pub rows: u64,
    /// Samples delivered.
    pub samples: u64,
    /// Rows dropped for a NaN or infinite value.
    pub non_finite: u64,
    /// Rows dropped for a wrong number of fields or a field that is not a number.
    pub malformed: u64,
    /// Rows dropped because a row with the same time was taken.
    pub duplicates: u64,
    /// Rows dropped because they were still out of order after the reorder window.
    pub out_of_order: u64,
    /// Rows put back in order by the window (delivered, not dropped).
    pub reordered: u64,
    /// Rows stamped more than [`FAR_AHEAD_NS`] after the rows around them (dropped).
    pub wrong_stamps: u64,
}

/// A row this far after the newest row is held until the next row confirms it (a real gap)
/// or comes before it (a wrong stamp): one bad stamp must not make every later row "late".
pub const FAR_AHEAD_NS: u64 = 1_000_000_000;

impl ImuCsvStats {
    /// Rows dropped, all kinds.
    pub fn dropped(&self) -> u64 {
        self.non_finite + self.malformed + self.duplicates + self.out_of_order + self.wrong_stamps
    }

    /// One line per kind of drop (and for reordered rows), without the `warning: ` prefix.
    pub fn warnings(&self) -> Vec<String> {
        let mut out = Vec::new();
        let n = self.rows;
        if self.non_finite > 0 {
            out.push(format!(
                "IMU CSV: dropped {} of {n} rows with a NaN or infinite value",
                self.non_finite
            ));
        }
        if self.malformed > 0 {
            out.push(format!(
                "IMU CSV: dropped {} of {n} rows with a wrong number of fields or a field that is not a number",
                self.malformed
            ));
        }
        if self.duplicates > 0 {
            out.push(format!(
                "IMU CSV: dropped {} of {n} rows repeating the time of an earlier row (duplicates)",
                self.duplicates
            ));
        }
        if self.out_of_order > 0 {
            out.push(format!(
                "IMU CSV: dropped {} of {n} rows out of time order by more than {REORDER_ROWS} rows",
                self.out_of_order
            ));
        }
        if self.wrong_stamps > 0 {
            out.push(format!(
                "IMU CSV: dropped {} of {n} rows stamped more than {} s after the rows around them (wrong stamps)",
                self.wrong_stamps,
                FAR_AHEAD_NS / 1_000_000_000
            ));
        }
        if self.reordered > 0 {
            out.push(format!(
                "IMU CSV: {} of {n} rows were out of time order and sorted back",
                self.reordered
            ));
        }
        out
    }
}

impl std::fmt::Display for ImuCsvStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} IMU CSV rows: {} samples; dropped {} non-finite, {} malformed, {} duplicates, {} out of order; {} reordered",
            self.rows,
            self.samples,
            self.non_finite,
            self.malformed,
            self.duplicates,
            self.out_of_order,
            self.reordered
        )
    }
}

/// Reads a CSV file; each kind of drop is said in one warning.
pub fn load(path: impl AsRef<Path>) -> Result<Vec<ImuSample>, ImuCsvError> {
    let (samples, stats) = load_counted(path)?;
    stats.warnings().into_iter().for_each(warn);
    Ok(samples)
}

/// Reads a CSV file and returns the counts, without warnings (the caller says them).
pub fn load_counted(path: impl AsRef<Path>) -> Result<(Vec<ImuSample>, ImuCsvStats), ImuCsvError> {
    let path = path.as_ref();
    let f = std::fs::File::open(path)
        .map_err(|e| ImuCsvError { line: 0, problem: format!("{}: {e}", path.display()) })?;
    parse_counted(std::io::BufReader::new(f))
}
/// Parses seconds (`123.456789012`, at most 9 decimals used, more are rounded off) into ns.
pub fn parse_seconds_ns(s: &str) -> Option<u64> {
    parse_time_ns(s, TimeUnit::S)
}

/// Parses a non-negative decimal time in `unit` into ns, exactly (decimals below 1 ns are
/// rounded off).
pub fn parse_time_ns(s: &str, unit: TimeUnit) -> Option<u64> {
    let s = s.trim();
    let (int, frac) = s.split_once('.').unwrap_or((s, ""));
    if int.is_empty() && frac.is_empty() {
        return None;
    }
    let digits = unit.decimals();
    if !int.bytes().all(|c| c.is_ascii_digit())
        || !frac.bytes().all(|c| c.is_ascii_digit())
        || int.len() > 11 + (9 - digits) as usize
    {
        return None;
    }
    let whole: u64 = if int.is_empty() { 0 } else { int.parse().ok()? };
    let mut ns = 0u64;
    for (i, c) in frac.bytes().take(digits as usize).enumerate() {
        ns += (c - b'0') as u64 * 10u64.pow(digits - 1 - i as u32);
    }
    if frac.len() > digits as usize && frac.as_bytes()[digits as usize] >= b'5' {
        ns += 1;
    }
    whole.checked_mul(10u64.pow(digits))?.checked_add(ns)
}

/// The unit of the time column.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimeUnit {
    /// Seconds (the default).
    S,
    /// Milliseconds.
    Ms,
    /// Microseconds.
    Us,
    /// Nanoseconds.
    Ns,
}

impl TimeUnit {
    /// Decimal digits from this unit down to ns.
    fn decimals(self) -> u32 {
        match self {
            TimeUnit::S => 9,
            TimeUnit::Ms => 6,
            TimeUnit::Us => 3,
            TimeUnit::Ns => 0,
        }
    }

    /// The unit's symbol.
    pub fn symbol(self) -> &'static str {
        match self {
            TimeUnit::S => "s",
            TimeUnit::Ms => "ms",
            TimeUnit::Us => "us",
            TimeUnit::Ns => "ns",
        }
    }

    fn from_symbol(s: &str) -> Option<TimeUnit> {
        Some(match s {
            "s" | "sec" | "secs" | "seconds" => TimeUnit::S,
            "ms" | "msec" => TimeUnit::Ms,
            "us" | "\u{b5}s" | "usec" => TimeUnit::Us,
            "ns" | "nsec" => TimeUnit::Ns,
            _ => return None,
        })
    }
}

/// Where each value is in a row, from the header (or the canonical order without one).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Layout {
    /// Fields in a row.
    pub columns: usize,
    /// The time column.
    pub t: usize,
    /// The time column's unit.
    pub t_unit: TimeUnit,
    /// The angular rate's columns, x, y, z.
    pub gyro: [usize; 3],
    /// The specific force's columns, x, y, z.
    pub acc: [usize; 3],
    /// The columns' names, for messages.
    names: Vec<String>,
}

impl Default for Layout {
    fn default() -> Self {
        Layout {
            columns: 7,
            t: 0,
            t_unit: TimeUnit::S,
            gyro: [1, 2, 3],
            acc: [4, 5, 6],
            names: HEADER.split(',').map(String::from).collect(),
        }
    }
}

/// What a header must hold, for the refusal.
const EXPECTED_HEADER: &str = "expected a time column (`t`, `time`, `timestamp` or `stamp`, the unit named as in `t_ns` or `time [us]`, seconds if none) and the columns `gx,gy,gz` (rad/s) and `ax,ay,az` (m/s^2), in any order";

/// What one header field names.
enum Column {
    Time(TimeUnit),
    Gyro(usize),
    Acc(usize),
}

/// Splits `name [unit]` / `name (unit)` into the name and the unit.
fn split_unit(f: &str) -> (String, Option<String>) {
    let f = f.trim().trim_matches('"').trim();
    for (open, close) in [('[', ']'), ('(', ')')] {
        if let Some(body) = f.strip_suffix(close)
            && let Some(at) = body.rfind(open)
        {
            let unit: String = body[at + 1..].chars().filter(|c| !c.is_whitespace()).collect();
            return (
                body[..at].trim().trim_end_matches('_').to_ascii_lowercase(),
                Some(unit.to_ascii_lowercase()),
            );
        }
    }
    (f.to_ascii_lowercase(), None)
}

/// What a header field names: `Ok(None)` for a column that names nothing known.
fn classify(field: &str) -> Result<Option<Column>, String> {
    const TIME: [&str; 6] = ["t", "time", "timestamp", "stamp", "ts", "times"];
    let (name, unit) = split_unit(field);
    let tokens: Vec<&str> = name.split(['_', '.', ' ', '-']).filter(|t| !t.is_empty()).collect();
    let Some((&first, _)) = tokens.split_first() else { return Ok(None) };
    // Time: `t`, `t_ns`, `timestamp [ns]`.
    let (base, suffix_unit) = match tokens.as_slice() {
        [b] => (*b, None),
        [b, u] => match TimeUnit::from_symbol(u) {
            Some(tu) => (*b, Some(tu)),
            None => ("", None),
        },
        _ => ("", None),
    };
    if TIME.contains(&base) {
        let bracket = match &unit {
            Some(u) => Some(TimeUnit::from_symbol(u).ok_or_else(|| {
                format!("the time column `{}` names the unit `{u}`, not s, ms, us or ns", field.trim())
            })?),
            None => None,
        };
        return match (suffix_unit, bracket) {
            (Some(a), Some(b)) if a != b => Err(format!(
                "the time column `{}` names two units, {} and {}",
                field.trim(),
                a.symbol(),
                b.symbol()
            )),
            (a, b) => Ok(Some(Column::Time(a.or(b).unwrap_or(TimeUnit::S)))),
        };
    }
    // Axes: `gx`, `gyro_x`, `w_RS_S_x`, `angular_velocity_x`; `ax`, `acc_x`, `a_RS_S_x`.
    let last = *tokens.last().unwrap_or(&"");
    let (kind, axis) = if tokens.len() == 1 && first.len() >= 2 {
        let (k, a) = first.split_at(first.len() - 1);
        (k, a)
    } else {
        (first, last)
    };
    let Some(axis) = ["x", "y", "z"].iter().position(|a| *a == axis) else { return Ok(None) };
    // Words between the kind and the axis: only those of the known spellings (`a_bias_x` is not
    // the specific force).
    if tokens.len() > 2
        && !tokens[1..tokens.len() - 1].iter().all(|t| {
            matches!(*t, "velocity" | "vel" | "acceleration" | "accel" | "rs" | "s" | "raw" | "meas")
        })
    {
        return Ok(None);
    }
    let gyro = matches!(kind, "g" | "gyro" | "gyr" | "w" | "omega" | "angular" | "ang" | "rot");
    let acc = matches!(kind, "a" | "acc" | "accel" | "linear" | "lin");
    if !gyro && !acc {
        return Ok(None);
    }
    if let Some(u) = unit {
        let ok = if gyro {
            matches!(u.as_str(), "rad/s" | "rads^-1" | "rad*s^-1" | "rad/sec")
        } else {
            matches!(u.as_str(), "m/s^2" | "m/s2" | "ms^-2" | "m*s^-2" | "m/s\u{b2}")
        };
        if !ok {
            return Err(format!(
                "the column `{}` is in `{u}`; expected {}",
                field.trim(),
                if gyro { "rad/s" } else { "m/s^2" }
            ));
        }
    }
    Ok(Some(if gyro { Column::Gyro(axis) } else { Column::Acc(axis) }))
}

impl Layout {
    /// Reads a header's fields; `Err` says why they are not a header this parser understands.
    pub fn from_header(fields: &[&str]) -> Result<Layout, String> {
        let mut t: Option<(usize, TimeUnit)> = None;
        let mut gyro = [None; 3];
        let mut acc = [None; 3];
        let mut unknown = Vec::new();
        for (i, f) in fields.iter().enumerate() {
            let slot = match classify(f)? {
                Some(Column::Time(u)) => {
                    if t.is_some() {
                        return Err("two time columns".into());
                    }
                    t = Some((i, u));
                    continue;
                }
                Some(Column::Gyro(a)) => &mut gyro[a],
                Some(Column::Acc(a)) => &mut acc[a],
                None => {
                    unknown.push(format!("`{}`", f.trim()));
                    continue;
                }
            };
            if slot.is_some() {
                return Err(format!("the column `{}` is named twice", f.trim()));
            }
            *slot = Some(i);
        }
        let mut missing = Vec::new();
        if t.is_none() {
            missing.push("the time");
        }
        for (c, name) in gyro.iter().chain(&acc).zip(["gx", "gy", "gz", "ax", "ay", "az"]) {
            if c.is_none() {
                missing.push(name);
            }
        }
        if !missing.is_empty() {
            let unknown = if unknown.is_empty() {
                String::new()
            } else {
                format!(" (not understood: {})", unknown.join(", "))
            };
            return Err(format!("no column for {}{unknown}", missing.join(", ")));
        }
        let (t, t_unit) = t.unwrap_or((0, TimeUnit::S));
        Ok(Layout {
            columns: fields.len(),
            t,
            t_unit,
            gyro: gyro.map(|c| c.unwrap_or(0)),
            acc: acc.map(|c| c.unwrap_or(0)),
            names: fields.iter().map(|f| f.trim().to_string()).collect(),
        })
    }
}

/// Parses CSV from a reader; each kind of drop is said in one warning.
pub fn parse(r: impl BufRead) -> Result<Vec<ImuSample>, ImuCsvError> {
    let (samples, stats) = parse_counted(r)?;
    stats.warnings().into_iter().for_each(warn);
    Ok(samples)
}

/// Why a row was dropped.
enum Bad {
    NonFinite,
    Malformed(String),
}

/// Parses one data row.
fn parse_row(fields: &[&str], layout: &Layout) -> Result<ImuSample, Bad> {
    if fields.len() != layout.columns {
        return Err(Bad::Malformed(format!("expected {} fields, found {}", layout.columns, fields.len())));
    }
    let tf = fields[layout.t];
    let t_ns = parse_time_ns(tf, layout.t_unit).ok_or_else(|| {
        let f = tf.to_ascii_lowercase();
        if f.contains("nan") || f.contains("inf") {
            Bad::NonFinite
        } else {
            let unit = match layout.t_unit {
                TimeUnit::S => "seconds",
                TimeUnit::Ms => "milliseconds",
                TimeUnit::Us => "microseconds",
                TimeUnit::Ns => "nanoseconds",
            };
            let hint =
                if layout.t_unit == TimeUnit::S && tf.len() > 11 && tf.bytes().all(|c| c.is_ascii_digit()) {
                    " (if the times are in ns, us or ms, name the unit in the header: `t_ns`, `t_us`, `t_ms`)"
                } else {
                    ""
                };
            Bad::Malformed(format!("time `{tf}` is not a non-negative number of {unit}{hint}"))
        }
    })?;
    let mut v = [0f32; 6];
    for (d, &c) in v.iter_mut().zip(layout.gyro.iter().chain(&layout.acc)) {
        let s = fields[c];
        let x = s.parse::<f32>().map_err(|_| {
            Bad::Malformed(format!(
                "column `{}` value `{s}` is not a number",
                layout.names.get(c).map_or("?", String::as_str)
            ))
        })?;
        if !x.is_finite() {
            return Err(Bad::NonFinite);
        }
        *d = x;
    }
    Ok(ImuSample { t_ns, gyro: [v[0], v[1], v[2]], acc: [v[3], v[4], v[5]] })
}

/// A row waiting in the reorder window: (time, arrival, read after a newer row, sample);
/// a min-heap on (time, arrival).
struct Held(u64, u64, bool, ImuSample);

impl PartialEq for Held {
    fn eq(&self, o: &Self) -> bool {
        (self.0, self.1) == (o.0, o.1)
    }
}
impl Eq for Held {}
impl PartialOrd for Held {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Held {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        (o.0, o.1).cmp(&(self.0, self.1))
    }
}

/// Sorts rows within the window and drops duplicates and rows still out of order.
struct Sorter {
    heap: BinaryHeap<Held>,
    out: Vec<ImuSample>,
    /// Rows taken so far, for the arrival order.
    seq: u64,
    /// The newest row time read so far.
    newest: Option<u64>,
    /// A row far after the newest, waiting for the next row's verdict.
    far: Option<ImuSample>,
    stats: ImuCsvStats,
}

impl Sorter {
    fn push(&mut self, s: ImuSample) {
        if let Some(h) = self.far.take() {
            if s.t_ns < h.t_ns {
                self.stats.wrong_stamps += 1;
            } else {
                self.take(h);
            }
        }
        if self.newest.is_some_and(|n| s.t_ns > n.saturating_add(FAR_AHEAD_NS)) {
            self.far = Some(s);
            return;
        }
        self.take(s);
    }

    /// The last row, if it waits for a verdict no row will give: taken (a gap at the end).
    fn flush_far(&mut self) {
        if let Some(h) = self.far.take() {
            self.take(h);
        }
    }

    fn take(&mut self, s: ImuSample) {
        let late = self.newest.is_some_and(|n| s.t_ns < n);
        self.newest = Some(self.newest.map_or(s.t_ns, |n| n.max(s.t_ns)));
        self.seq += 1;
        self.heap.push(Held(s.t_ns, self.seq, late, s));
        if self.heap.len() > REORDER_ROWS {
            self.pop();
        }
    }

    fn pop(&mut self) {
        let Some(Held(t, _, late, s)) = self.heap.pop() else { return };
        match self.out.last().map(|p| p.t_ns) {
            Some(prev) if t == prev => self.stats.duplicates += 1,
            Some(prev) if t < prev => self.stats.out_of_order += 1,
            _ => {
                self.stats.reordered += u64::from(late);
                self.out.push(s);
            }
        }
    }
}

/// Parses CSV from a reader and returns the counts, without warnings.
pub fn parse_counted(r: impl BufRead) -> Result<(Vec<ImuSample>, ImuCsvStats), ImuCsvError> {
    let mut header_seen = false;
    let mut first_bad: Option<(usize, String)> = None;
    let mut sorter = Sorter {
        heap: BinaryHeap::new(),
        out: Vec::new(),
        seq: 0,
        newest: None,
        far: None,
        stats: ImuCsvStats::default(),
    };
    let mut layout = Layout::default();
    // The header came from a `#` line: a real header line may still follow.
    let mut header_from_comment = false;
    for (i, line) in r.lines().enumerate() {
        let n = i + 1;
        let line = line.map_err(|e| ImuCsvError { line: n, problem: format!("read error: {e}") })?;
        let t = line.trim().trim_start_matches('\u{feff}');
        if t.is_empty() {
            continue;
        }
        if let Some(c) = t.strip_prefix('#') {
            // EuRoC's header is a comment: `#timestamp [ns],w_RS_S_x [rad s^-1],...`.
            if !header_seen {
                let fields: Vec<&str> = c.split(',').map(str::trim).collect();
                if fields.len() >= 7
                    && let Ok(l) = Layout::from_header(&fields)
                {
                    layout = l;
                    header_seen = true;
                    header_from_comment = true;
                }
            }
            continue;
        }
        let fields: Vec<&str> = t.split(',').map(str::trim).collect();
        let is_header = fields.iter().any(|f| f.parse::<f64>().is_err());
        if !header_seen || (header_from_comment && is_header) {
            header_seen = true;
            header_from_comment = false;
            // A header is a first line whose fields are not all numbers.
            if is_header {
                layout = Layout::from_header(&fields).map_err(|why| ImuCsvError {
                    line: n,
                    problem: format!("the header `{t}` is not understood: {why}; {EXPECTED_HEADER}"),
                })?;
                continue;
            }
        }
        header_from_comment = false;
        sorter.stats.rows += 1;
        match parse_row(&fields, &layout) {
            Ok(s) => sorter.push(s),
            Err(Bad::NonFinite) => {
                sorter.stats.non_finite += 1;
                first_bad.get_or_insert((n, "a NaN or infinite value".into()));
            }
            Err(Bad::Malformed(why)) => {
                sorter.stats.malformed += 1;
                first_bad.get_or_insert((n, why));
            }
        }
    }
    if !header_seen {
        return Err(ImuCsvError { line: 0, problem: format!("empty file (expected the header `{HEADER}`)") });
    }
    sorter.flush_far();
    while !sorter.heap.is_empty() {
        sorter.pop();
    }
    let mut stats = sorter.stats;
    stats.samples = sorter.out.len() as u64;
    let bad = stats.dropped();
    if bad * 2 > stats.rows {
        let first =
            first_bad.map_or(String::new(), |(l, why)| format!("; the first bad row, line {l}: {why}"));
        return Err(ImuCsvError {
            line: 0,
            problem: format!(
                "{bad} of {} rows are bad ({} non-finite, {} malformed, {} duplicates, {} out of order, {} wrong stamps); refusing the file{first}",
                stats.rows,
                stats.non_finite,
                stats.malformed,
                stats.duplicates,
                stats.out_of_order,
                stats.wrong_stamps
            ),
        });
    }
    Ok((sorter.out, stats))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_samples_exactly() {
        let text = "t, gx,gy,gz,ax,ay,az\n# comment\n1700000000.123456789,0.1,-0.2,0.3,0,0,9.81\n\n1700000000.128,0,0,0,1e-3,0,9.8\n";
        let s = parse(text.as_bytes()).unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(s[0].t_ns, 1_700_000_000_123_456_789);
        assert_eq!(s[1].t_ns, 1_700_000_000_128_000_000);
        assert_eq!(s[0].gyro, [0.1, -0.2, 0.3]);
        assert_eq!(s[1].acc, [1e-3, 0.0, 9.8]);
        assert_eq!(parse_seconds_ns("0.0000000015"), Some(2));
        assert_eq!(parse_seconds_ns(".5"), Some(500_000_000));
        assert_eq!(parse_seconds_ns("-1"), None);
        assert_eq!(parse_seconds_ns("1e9"), None);
    }

    #[test]
    fn refusals_are_one_line() {
        let cases = [
            ("", 0, "empty"),
            (
                "time,gx\n",
                1,
                "the header `time,gx` is not understood: no column for gy, gz, ax, ay, az; expected a time column",
            ),
            ("t,gx,gy,gz,ax,ay,az\n1,2,3\n", 0, "1 of 1 rows are bad (0 non-finite, 1 malformed"),
            (
                "t,gx,gy,gz,ax,ay,az\n1,0,0,0,0,0,0\nx,0,0,0,0,0,0\ny,0,0,0,0,0,0\n",
                0,
                "2 of 3 rows are bad (0 non-finite, 2 malformed, 0 duplicates, 0 out of order, 0 wrong stamps); refusing the file; the first bad row, line 3: time `x`",
            ),
            ("t,gx,gy,gz,ax,ay,az\n1,0,0,nan,0,0,0\n", 0, "the first bad row, line 2: a NaN"),
            (
                "t,gx,gy,gz,ax,ay,az\n2,0,0,0,0,0,0\n\n2,0,0,0,0,0,0\n2,1,0,0,0,0,0\n",
                0,
                "2 of 3 rows are bad (0 non-finite, 0 malformed, 2 duplicates",
            ),
        ];
        for (text, line, needle) in cases {
            let e = parse_counted(text.as_bytes()).unwrap_err();
            assert_eq!(e.line, line, "{text:?}: {e}");
            assert!(e.to_string().contains(needle), "{e}");
            assert!(!e.to_string().contains('\n'));
        }
    }

    fn row(t_ns: u64, k: usize) -> String {
        format!(
            "{}.{:09},{},-0.02,0.3,0.5,{},9.81\n",
            t_ns / 1_000_000_000,
            t_ns % 1_000_000_000,
            k as f32 * 1e-4,
            k % 7
        )
    }

    fn sample(t_ns: u64, k: usize) -> ImuSample {
        ImuSample { t_ns, gyro: [k as f32 * 1e-4, -0.02, 0.3], acc: [0.5, (k % 7) as f32, 9.81] }
    }

    /// 12,000 samples at 200 Hz written as 12,002 rows: one with a NaN, one repeated, one pair
    /// swapped, one extra stamped 60 s ahead. Exactly the NaN row, the repeat and the wrong
    /// stamp are dropped; the pair is sorted back (before the stamp guard the +60 s row made
    /// every later row "late": 3,000 of them counted as sorted back).
    #[test]
    fn bad_rows_are_dropped_and_counted_exactly() {
        let t0 = 1_700_000_000_000_000_000u64;
        let good: Vec<ImuSample> = (0..12_000).map(|k| sample(t0 + k as u64 * 5_000_000, k)).collect();
        let mut rows: Vec<String> = (0..12_000).map(|k| row(t0 + k as u64 * 5_000_000, k)).collect();
        rows[5000] = rows[5000].replacen(",-0.02,", ",NaN,", 1);
        rows.swap(9000, 9001);
        let dup = rows[7000].clone();
        rows.insert(7001, dup);
        rows.insert(9500, row(t0 + 9_499 * 5_000_000 + 60_000_000_000, 1));
        assert_eq!(rows.len(), 12_002);
        let text = format!("timestamp,gx,gy,gz,ax,ay,az\n{}", rows.concat());
        let (got, stats) = parse_counted(text.as_bytes()).unwrap();
        let mut want = good.clone();
        want.remove(5000);
        assert_eq!(got.len(), 11_999);
        assert_eq!(got, want);
        assert_eq!(
            stats,
            ImuCsvStats {
                rows: 12_002,
                samples: 11_999,
                non_finite: 1,
                malformed: 0,
                duplicates: 1,
                out_of_order: 0,
                reordered: 1,
                wrong_stamps: 1,
            }
        );
        assert_eq!(
            stats.warnings(),
            vec![
                "IMU CSV: dropped 1 of 12002 rows with a NaN or infinite value".to_string(),
                "IMU CSV: dropped 1 of 12002 rows repeating the time of an earlier row (duplicates)"
                    .to_string(),
                "IMU CSV: dropped 1 of 12002 rows stamped more than 1 s after the rows around them (wrong stamps)"
                    .to_string(),
                "IMU CSV: 1 of 12002 rows were out of time order and sorted back".to_string(),
            ]
        );
        // `parse` says the same, one warning per kind.
        let (r, warnings) = crate::diag::capture(|| parse(text.as_bytes()));
        assert_eq!(r.unwrap(), want);
        assert_eq!(warnings.len(), 4, "{warnings:?}");
        assert!(warnings.iter().all(|w| w.starts_with("warning: IMU CSV: ")));
    }

    #[test]
    fn short_rows_far_disorder_and_headerless_files() {
        let t0 = 1_000_000_000u64;
        let mut rows: Vec<String> = (0..200).map(|k| row(t0 + k as u64 * 10_000_000, k)).collect();
        // A row 60 rows late: past the window, dropped.
        let late = rows.remove(20);
        rows.insert(80, late);
        rows[100] = "1.5,0,0\n".into();
        rows[101] = "1.51,0,0,0,0,0,inf\n".into();
        let text = rows.concat();
        let (got, stats) = parse_counted(text.as_bytes()).unwrap();
        assert_eq!(stats.rows, 200);
        assert_eq!((stats.malformed, stats.non_finite, stats.out_of_order, stats.duplicates), (1, 1, 1, 0));
        assert_eq!(got.len(), 197);
        assert!(got.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
        assert_eq!(got[0], sample(t0, 0), "no header: the first line is data");
        assert_eq!(stats.warnings().len(), 3);
        assert!(stats.warnings()[2].contains("dropped 1 of 200 rows out of time order by more than 50 rows"));
    }

    #[test]
    fn a_file_mostly_garbage_is_refused_in_one_line() {
        let mut text = String::from("t_s,gx,gy,gz,ax,ay,az\n");
        for k in 0..1000usize {
            if k % 5 < 3 {
                text.push_str("garbage;;\n");
            } else {
                text.push_str(&row(1_000_000_000 + k as u64 * 1_000_000, k));
            }
        }
        let e = parse_counted(text.as_bytes()).unwrap_err().to_string();
        assert_eq!(
            e,
            "IMU CSV: 600 of 1000 rows are bad (0 non-finite, 600 malformed, 0 duplicates, 0 out of order, 0 wrong stamps); refusing the file; the first bad row, line 2: expected 7 fields, found 1"
        );
    }

    /// The values every header variant below must give: 1.5 s, then 1.502 s.
    fn two_samples() -> Vec<ImuSample> {
        vec![
            ImuSample { t_ns: 1_500_000_000, gyro: [0.1, 0.2, 0.3], acc: [1.0, 2.0, 9.8] },
            ImuSample { t_ns: 1_502_000_000, gyro: [-0.1, 0.0, 0.5], acc: [0.5, -2.0, 9.7] },
        ]
    }

    #[test]
    fn header_variants_name_the_time_column_and_its_unit() {
        let rows = |t0: &str, t1: &str| format!("{t0},0.1,0.2,0.3,1,2,9.8\n{t1},-0.1,0,0.5,0.5,-2,9.7\n");
        let cases = [
            ("t", "1.5", "1.502"),
            ("t_s", "1.5", "1.502"),
            ("time", "1.5", "1.502"),
            ("timestamp", "1.500", "1.502000000"),
            ("stamp", "1.5", "1.502"),
            ("time [s]", "1.5", "1.502"),
            ("t_ms", "1500", "1502"),
            ("t(ms)", "1500.0", "1502"),
            ("t_us", "1500000", "1502000"),
            ("timestamp (us)", "1500000", "1502000.0004"),
            ("t_ns", "1500000000", "1502000000"),
            ("timestamp_ns", "1500000000", "1502000000"),
            ("stamp[ns]", "1500000000", "1502000000"),
            ("\"Time (ns)\"", "1500000000", "1502000000"),
        ];
        for (time, t0, t1) in cases {
            let text = format!("{time},gx,gy,gz,ax,ay,az\n{}", rows(t0, t1));
            let (got, stats) = parse_counted(text.as_bytes()).unwrap_or_else(|e| panic!("{time}: {e}"));
            assert_eq!(got, two_samples(), "{time}");
            assert_eq!(stats.dropped(), 0, "{time}");
        }
        // Unix time in ns: 19 digits, exact.
        let text = "t_ns,gx,gy,gz,ax,ay,az\n1700000000123456789,0,0,0,0,0,9.81\n";
        assert_eq!(parse(text.as_bytes()).unwrap()[0].t_ns, 1_700_000_000_123_456_789);
        assert_eq!(parse_time_ns("1700000000123456.7895", TimeUnit::Us), Some(1_700_000_000_123_456_790));
        assert_eq!(parse_time_ns("12.5", TimeUnit::Ms), Some(12_500_000));
        assert_eq!(parse_time_ns("12.5", TimeUnit::Ns), Some(13));
    }

    #[test]
    fn named_columns_are_read_in_any_order() {
        let text = "ax,ay,az,gx,gy,gz,t\n1,2,9.8,0.1,0.2,0.3,1.5\n0.5,-2,9.7,-0.1,0,0.5,1.502\n";
        assert_eq!(parse(text.as_bytes()).unwrap(), two_samples());
        // Long names, units in brackets and an extra column that is ignored.
        let text = "timestamp_ms,temp,acc_x [m/s^2],acc_y [m/s^2],acc_z [m/s^2],gyro_x [rad/s],gyro_y [rad/s],gyro_z [rad/s]\n\
                    1500,25.0,1,2,9.8,0.1,0.2,0.3\n1502,25.1,0.5,-2,9.7,-0.1,0,0.5\n";
        assert_eq!(parse(text.as_bytes()).unwrap(), two_samples());
        // EuRoC: the header is a `#` line, the time in ns.
        let text = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n\
                    1500000000,0.1,0.2,0.3,1,2,9.8\n1502000000,-0.1,0,0.5,0.5,-2,9.7\n";
        assert_eq!(parse(text.as_bytes()).unwrap(), two_samples());
        // A `#` comment that reads as a header, then the header itself (in another order).
        let text = "# t,gx,gy,gz,ax,ay,az\nt,ax,ay,az,gx,gy,gz\n1.5,1,2,9.8,0.1,0.2,0.3\n1.502,0.5,-2,9.7,-0.1,0,0.5\n";
        assert_eq!(parse(text.as_bytes()).unwrap(), two_samples());
        // A bad value names its column by the header's name.
        let text =
            "t,ax,ay,az,gx,gy,gz\n1.5,1,2,9.8,0.1,0.2,0.3\n1.502,x,x,x,x,x,x\n1.504,1,2,9.8,0.1,0.2,0.3\n";
        let (got, stats) = parse_counted(text.as_bytes()).unwrap();
        assert_eq!((got.len(), stats.malformed), (2, 1));
        let e = parse_counted("t,ax,ay,az,gx,gy,gz\n1.5,1,2,9.8,0.1,0.2,oops\n".as_bytes()).unwrap_err();
        assert!(e.to_string().ends_with("line 2: column `gz` value `oops` is not a number"), "{e}");
    }

    #[test]
    fn headers_not_understood_are_refused_naming_them() {
        let cases = [
            (
                "a,b,c,d,e,f,g",
                "no column for the time, gx, gy, gz, ax, ay, az (not understood: `a`, `b`, `c`, `d`, `e`, `f`, `g`)",
            ),
            ("t,gx,gy,gz,ax,ay,q", "no column for az (not understood: `q`)"),
            (
                "t,gx,gy,gz,a_bias_x,a_bias_y,a_bias_z",
                "no column for ax, ay, az (not understood: `a_bias_x`, `a_bias_y`, `a_bias_z`)",
            ),
            ("t,gx,gy,gx,ax,ay,az", "the column `gx` is named twice"),
            ("t,time,gx,gy,gz,ax,ay,az", "two time columns"),
            ("t [h],gx,gy,gz,ax,ay,az", "the time column `t [h]` names the unit `h`, not s, ms, us or ns"),
            ("t_ns [ms],gx,gy,gz,ax,ay,az", "the time column `t_ns [ms]` names two units, ns and ms"),
            ("t,gx [deg/s],gy,gz,ax,ay,az", "the column `gx [deg/s]` is in `deg/s`; expected rad/s"),
            ("t,gx,gy,gz,ax [g],ay,az", "the column `ax [g]` is in `g`; expected m/s^2"),
        ];
        for (header, why) in cases {
            let text = format!("{header}\n1,0,0,0,0,0,0\n");
            let e = parse_counted(text.as_bytes()).unwrap_err();
            assert_eq!(e.line, 1);
            assert_eq!(
                e.to_string(),
                format!("IMU CSV line 1: the header `{header}` is not understood: {why}; {EXPECTED_HEADER}")
            );
        }
        // The Ouster SDK's IMU CSV (g and deg/s, three clocks): refused, not guessed at.
        let path =
            concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/data/ouster-sdk/OS-1-64_1024x10_fw20.imu.csv");
        let e = load_counted(path).unwrap_err();
        assert_eq!(e.line, 1);
        assert_eq!(
            e.problem,
            format!(
                "the header `capture_ts_s,sys_ts_ns,accel_ts_ns,gyro_ts_ns,la_x_g,la_y_g,la_z_g,av_x_dps,av_y_dps,av_z_dps` is not understood: no column for the time, gx, gy, gz, ax, ay, az (not understood: `capture_ts_s`, `sys_ts_ns`, `accel_ts_ns`, `gyro_ts_ns`, `la_x_g`, `la_y_g`, `la_z_g`, `av_x_dps`, `av_y_dps`, `av_z_dps`); {EXPECTED_HEADER}"
            )
        );
        // Unix ns under a header without a unit: the refusal says how to name it.
        let text = "t,gx,gy,gz,ax,ay,az\n1700000000123456789,0,0,0,0,0,9.81\n";
        let e = parse_counted(text.as_bytes()).unwrap_err().to_string();
        assert!(e.ends_with("time `1700000000123456789` is not a non-negative number of seconds (if the times are in ns, us or ms, name the unit in the header: `t_ns`, `t_us`, `t_ms`)"), "{e}");
    }
}
