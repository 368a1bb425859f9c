//! IMU samples from CSV: a header line (`t,gx,gy,gz,ax,ay,az`, or any first line that does not
//! read as numbers, such as `t_s,gx,...` or `timestamp,...`, with 7 columns), then one sample per
//! line with `t` in seconds (absolute, e.g. Unix time; parsed exactly to the nanosecond),
//! angular rate in rad/s and specific force in m/s^2. Blank lines and lines starting with `#`
//! are skipped; a file without a header starts with data.
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
    let s = s.trim();
    let (int, frac) = s.split_once('.').unwrap_or((s, ""));
    if int.is_empty() && frac.is_empty() {
        return None;
    }
    if !int.bytes().all(|c| c.is_ascii_digit()) || !frac.bytes().all(|c| c.is_ascii_digit()) || int.len() > 11
    {
        return None;
    }
    let secs: u64 = if int.is_empty() { 0 } else { int.parse().ok()? };
    let mut ns = 0u64;
    for (i, c) in frac.bytes().take(9).enumerate() {
        ns += (c - b'0') as u64 * 10u64.pow(8 - i as u32);
    }
    if frac.len() > 9 && frac.as_bytes()[9] >= b'5' {
        ns += 1;
    }
    secs.checked_mul(1_000_000_000)?.checked_add(ns)
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
fn parse_row(fields: &[&str]) -> Result<ImuSample, Bad> {
    if fields.len() != 7 {
        return Err(Bad::Malformed(format!("expected 7 fields, found {}", fields.len())));
    }
    let t_ns = parse_seconds_ns(fields[0]).ok_or_else(|| {
        let f = fields[0].to_ascii_lowercase();
        if f.contains("nan") || f.contains("inf") {
            Bad::NonFinite
        } else {
            Bad::Malformed(format!("time `{}` is not a non-negative number of seconds", fields[0]))
        }
    })?;
    let mut v = [0f32; 6];
    for (k, (d, s)) in v.iter_mut().zip(&fields[1..]).enumerate() {
        let x = s.parse::<f32>().map_err(|_| {
            Bad::Malformed(format!(
                "column `{}` value `{s}` is not a number",
                HEADER.split(',').nth(k + 1).unwrap_or("?")
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
    for (i, line) in r.lines().enumerate() {
        let n = i + 1;
        let line = line.map_err(|e| ImuCsvError { line: n, problem: format!("read error: {e}") })?;
        let t = line.trim().trim_start_matches('\u{feff}');
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = t.split(',').map(str::trim).collect();
        if !header_seen {
            header_seen = true;
            // A header is a first line whose fields are not all numbers.
            if fields.iter().any(|f| f.parse::<f64>().is_err()) {
                if fields.len() != 7 {
                    return Err(ImuCsvError {
                        line: n,
                        problem: format!(
                            "the header `{t}` has {} columns; expected 7 (`{HEADER}`)",
                            fields.len()
                        ),
                    });
                }
                continue;
            }
        }
        sorter.stats.rows += 1;
        match parse_row(&fields) {
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
            ("time,gx\n", 1, "has 2 columns; expected 7"),
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
}
