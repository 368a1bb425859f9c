//! IMU samples from CSV: a header line `t,gx,gy,gz,ax,ay,az`, then one sample per line with
//! `t` in seconds (absolute, e.g. Unix time; parsed exactly to the nanosecond), angular rate in
//! rad/s and specific force in m/s^2. Blank lines and lines starting with `#` are skipped.
//! Every problem is an error naming the line: a wrong header, a wrong number of fields, a
//! field that is not a finite number, a timestamp that does not increase.

use loglio_core::imu::ImuSample;
use std::io::BufRead;
use std::path::Path;

/// The required header.
pub const HEADER: &str = "t,gx,gy,gz,ax,ay,az";

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

/// Reads a CSV file.
pub fn load(path: impl AsRef<Path>) -> Result<Vec<ImuSample>, ImuCsvError> {
    let path = path.as_ref();
    let f = std::fs::File::open(path)
        .map_err(|e| ImuCsvError { line: 0, problem: format!("{}: {e}", path.display()) })?;
    parse(std::io::BufReader::new(f))
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

/// Parses CSV from a reader.
pub fn parse(r: impl BufRead) -> Result<Vec<ImuSample>, ImuCsvError> {
    let mut out = Vec::new();
    let mut header_seen = false;
    for (i, line) in r.lines().enumerate() {
        let n = i + 1;
        let line = line.map_err(|e| ImuCsvError { line: n, problem: format!("read error: {e}") })?;
        let t = line.trim().trim_start_matches('\u{feff}');
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        if !header_seen {
            let cols: Vec<&str> = t.split(',').map(str::trim).collect();
            if cols.join(",") != HEADER {
                return Err(ImuCsvError {
                    line: n,
                    problem: format!("expected the header `{HEADER}`, found `{t}`"),
                });
            }
            header_seen = true;
            continue;
        }
        let fields: Vec<&str> = t.split(',').map(str::trim).collect();
        if fields.len() != 7 {
            return Err(ImuCsvError {
                line: n,
                problem: format!("expected 7 fields, found {}", fields.len()),
            });
        }
        let t_ns = parse_seconds_ns(fields[0]).ok_or_else(|| ImuCsvError {
            line: n,
            problem: format!("time `{}` is not a non-negative number of seconds", fields[0]),
        })?;
        let mut v = [0f32; 6];
        for (k, (d, s)) in v.iter_mut().zip(&fields[1..]).enumerate() {
            *d = s.parse::<f32>().ok().filter(|x| x.is_finite()).ok_or_else(|| ImuCsvError {
                line: n,
                problem: format!(
                    "column `{}` value `{s}` is not a finite number",
                    HEADER.split(',').nth(k + 1).unwrap_or("?")
                ),
            })?;
        }
        if let Some(prev) = out.last().map(|p: &ImuSample| p.t_ns)
            && t_ns <= prev
        {
            return Err(ImuCsvError {
                line: n,
                problem: format!(
                    "time {} s does not increase (previous {} s)",
                    fields[0],
                    prev as f64 * 1e-9
                ),
            });
        }
        out.push(ImuSample { t_ns, gyro: [v[0], v[1], v[2]], acc: [v[3], v[4], v[5]] });
    }
    if !header_seen {
        return Err(ImuCsvError { line: 0, problem: format!("empty file (expected the header `{HEADER}`)") });
    }
    Ok(out)
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
    fn errors_name_the_line() {
        let cases = [
            ("", 0, "empty"),
            ("time,gx\n", 1, "header"),
            ("t,gx,gy,gz,ax,ay,az\n1,2,3\n", 2, "7 fields"),
            ("t,gx,gy,gz,ax,ay,az\n1,0,0,0,0,0,0\nx,0,0,0,0,0,0\n", 3, "time `x`"),
            ("t,gx,gy,gz,ax,ay,az\n1,0,0,nan,0,0,0\n", 2, "column `gz`"),
            ("t,gx,gy,gz,ax,ay,az\n2,0,0,0,0,0,0\n\n2,0,0,0,0,0,0\n", 4, "does not increase"),
        ];
        for (text, line, needle) in cases {
            let e = parse(text.as_bytes()).unwrap_err();
            assert_eq!(e.line, line, "{text:?}: {e}");
            assert!(e.to_string().contains(needle), "{e}");
        }
    }
}
