//! Frame patterns: a path with one frame-number token.
//!
//! Accepted tokens: `####` (zero-padded to as many digits as `#`), `%04d`
//! (`%d` unpadded), `$F4` (`$F` unpadded), `${F4}` and `<F4>`. The token must
//! be in the file name, not in a directory. Negative frame numbers keep their
//! sign in front of the padded digits (`-005` for `###`).

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// A parsed frame pattern such as `render/beauty.####.exr`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FramePattern {
    raw: String,
    dir: PathBuf,
    prefix: String,
    suffix: String,
    padding: usize,
}

/// One frame-number token found in a file name: byte range and padding.
fn find_tokens(name: &str) -> Vec<(usize, usize, usize)> {
    let b = name.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let digits_at = |start: usize| -> (usize, usize) {
            let mut j = start;
            while j < b.len() && b[j].is_ascii_digit() {
                j += 1;
            }
            let pad = name[start..j].parse::<usize>().unwrap_or(0);
            (j, pad)
        };
        match b[i] {
            b'#' => {
                let mut j = i;
                while j < b.len() && b[j] == b'#' {
                    j += 1;
                }
                out.push((i, j, j - i));
                i = j;
                continue;
            }
            b'%' => {
                // %d, %4d, %04d
                let mut j = i + 1;
                if j < b.len() && b[j] == b'0' {
                    j += 1;
                }
                let (k, pad) = digits_at(j);
                if k < b.len() && b[k] == b'd' {
                    out.push((i, k + 1, pad.max(1)));
                    i = k + 1;
                    continue;
                }
            }
            b'$' => {
                if name[i..].starts_with("${F") {
                    let (k, pad) = digits_at(i + 3);
                    if k < b.len() && b[k] == b'}' {
                        out.push((i, k + 1, pad.max(1)));
                        i = k + 1;
                        continue;
                    }
                } else if name[i..].starts_with("$F") {
                    let (k, pad) = digits_at(i + 2);
                    out.push((i, k, pad.max(1)));
                    i = k;
                    continue;
                }
            }
            b'<' if name[i..].starts_with("<F") => {
                let (k, pad) = digits_at(i + 2);
                if k < b.len() && b[k] == b'>' {
                    out.push((i, k + 1, pad.max(1)));
                    i = k + 1;
                    continue;
                }
            }
            _ => {}
        }
        i += 1;
    }
    out
}

impl FramePattern {
    /// Parses a pattern; errors name the pattern and what is wrong.
    pub fn parse(pattern: &str) -> Result<FramePattern> {
        let path = Path::new(pattern);
        let name = path.file_name().and_then(|n| n.to_str()).ok_or_else(|| {
            Error::invalid(format!("frame pattern {pattern:?}: has no file name"))
        })?;
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        if !find_tokens(&dir.to_string_lossy()).is_empty() {
            return Err(Error::invalid(format!(
                "frame pattern {pattern:?}: the frame token must be in the file name, not in a directory"
            )));
        }
        let tokens = find_tokens(name);
        match tokens.len() {
            0 => Err(Error::invalid(format!(
                "frame pattern {pattern:?}: no frame token (use ####, %04d, $F4, ${{F4}} or <F4>)"
            ))),
            1 => {
                let (s, e, padding) = tokens[0];
                Ok(FramePattern {
                    raw: pattern.to_string(),
                    dir,
                    prefix: name[..s].to_string(),
                    suffix: name[e..].to_string(),
                    padding,
                })
            }
            n => Err(Error::invalid(format!(
                "frame pattern {pattern:?}: {n} frame tokens; use exactly one"
            ))),
        }
    }

    /// The pattern as given.
    pub fn as_str(&self) -> &str {
        &self.raw
    }

    /// Digits the frame number is padded to.
    pub fn padding(&self) -> usize {
        self.padding
    }

    /// The directory the frames live in (empty for the current directory).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn file_name(&self, frame: i64) -> String {
        let digits = format!("{:0width$}", frame.unsigned_abs(), width = self.padding);
        let sign = if frame < 0 { "-" } else { "" };
        format!("{}{sign}{digits}{}", self.prefix, self.suffix)
    }

    /// The path of frame `frame`.
    pub fn path(&self, frame: i64) -> PathBuf {
        self.dir.join(self.file_name(frame))
    }

    /// The frame number a file name stands for, if it matches the pattern.
    pub fn match_name(&self, name: &str) -> Option<i64> {
        let mid = name
            .strip_prefix(&self.prefix)?
            .strip_suffix(&self.suffix)?;
        let digits = mid.strip_prefix('-').unwrap_or(mid);
        if digits.is_empty() || !digits.bytes().all(|c| c.is_ascii_digit()) {
            return None;
        }
        let n: i64 = mid.parse().ok()?;
        // Only the canonical spelling matches (so `%04d` does not take `12.exr`).
        (self.file_name(n) == name).then_some(n)
    }

    /// Existing frames, in increasing order.
    pub fn list(&self) -> Result<Vec<(i64, PathBuf)>> {
        let dir = if self.dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            &self.dir
        };
        let entries = std::fs::read_dir(dir).map_err(|e| {
            Error::Io(format!(
                "frame pattern {:?}: cannot list directory {}: {e}",
                self.raw,
                dir.display()
            ))
        })?;
        let mut frames = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| Error::io(dir, e))?;
            if let Some(name) = entry.file_name().to_str() {
                if let Some(n) = self.match_name(name) {
                    frames.push((n, self.path(n)));
                }
            }
        }
        frames.sort_by_key(|(n, _)| *n);
        Ok(frames)
    }
}

impl std::fmt::Display for FramePattern {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.raw)
    }
}

/// An inclusive frame range `A-B` (or a single frame `A`), as `--frames` takes it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRange {
    /// First frame.
    pub start: i64,
    /// Last frame (inclusive).
    pub end: i64,
}

impl FrameRange {
    /// Parses `A-B`, `A:B` or `A`; negative numbers are allowed (`-5--1`).
    pub fn parse(s: &str) -> Result<FrameRange> {
        let bad =
            |why: &str| Error::invalid(format!("--frames {s:?}: {why} (expected A-B, e.g. 1-24)"));
        let t = s.trim();
        if t.is_empty() {
            return Err(bad("empty range"));
        }
        // Split at the first '-' or ':' that is not a leading sign.
        let split = t
            .char_indices()
            .skip(1)
            .find(|&(_, c)| c == '-' || c == ':')
            .map(|(i, _)| i);
        let (a, b) = match split {
            Some(i) => (&t[..i], &t[i + 1..]),
            None => (t, t),
        };
        let start: i64 = a
            .trim()
            .parse()
            .map_err(|_| bad(&format!("{a:?} is not a frame number")))?;
        let end: i64 = b
            .trim()
            .parse()
            .map_err(|_| bad(&format!("{b:?} is not a frame number")))?;
        if end < start {
            return Err(bad(&format!("end {end} is before start {start}")));
        }
        Ok(FrameRange { start, end })
    }

    /// True when `frame` is in the range.
    pub fn contains(&self, frame: i64) -> bool {
        (self.start..=self.end).contains(&frame)
    }
}

/// Writes frame numbers compactly: `3, 7-9, 12`.
pub fn format_frame_list(frames: &[i64]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < frames.len() {
        let mut j = i;
        while j + 1 < frames.len() && frames[j + 1] == frames[j] + 1 {
            j += 1;
        }
        parts.push(if j == i {
            frames[i].to_string()
        } else {
            format!("{}-{}", frames[i], frames[j])
        });
        i = j + 1;
    }
    parts.join(", ")
}

/// The frames of `pattern` to process: every existing frame, or exactly the
/// frames of `range` (an error lists the missing ones).
pub fn select_frames(
    pattern: &FramePattern,
    range: Option<FrameRange>,
) -> Result<Vec<(i64, PathBuf)>> {
    let found = pattern.list()?;
    match range {
        None => {
            if found.is_empty() {
                return Err(Error::invalid(format!(
                    "input {pattern}: no files match (looked for e.g. {})",
                    pattern.path(1).display()
                )));
            }
            Ok(found)
        }
        Some(r) => {
            let chosen: Vec<_> = found.into_iter().filter(|(n, _)| r.contains(*n)).collect();
            let have: std::collections::BTreeSet<i64> = chosen.iter().map(|(n, _)| *n).collect();
            let missing: Vec<i64> = (r.start..=r.end)
                .filter(|n| !have.contains(n))
                .take(100_000)
                .collect();
            if !missing.is_empty() {
                return Err(Error::invalid(format!(
                    "input {pattern}: missing frame(s) {} of --frames {}-{} (e.g. {})",
                    format_frame_list(&missing),
                    r.start,
                    r.end,
                    pattern.path(missing[0]).display()
                )));
            }
            Ok(chosen)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_expand() {
        for (p, want) in [
            ("a/b.####.exr", "a/b.0042.exr"),
            ("b.%04d.exr", "b.0042.exr"),
            ("b.%d.exr", "b.42.exr"),
            ("b.$F4.exr", "b.0042.exr"),
            ("b.${F4}.exr", "b.0042.exr"),
            ("b_<F4>.exr", "b_0042.exr"),
            ("b.$F.exr", "b.42.exr"),
        ] {
            assert_eq!(
                FramePattern::parse(p).unwrap().path(42),
                PathBuf::from(want),
                "{p}"
            );
        }
        assert_eq!(
            FramePattern::parse("x.###.exr").unwrap().path(-5),
            PathBuf::from("x.-005.exr")
        );
        assert_eq!(
            FramePattern::parse("x.##.exr").unwrap().path(12345),
            PathBuf::from("x.12345.exr")
        );
    }

    #[test]
    fn bad_patterns_are_named() {
        let e = FramePattern::parse("plain.exr").unwrap_err().to_string();
        assert!(
            e.contains("plain.exr") && e.contains("no frame token"),
            "{e}"
        );
        let e = FramePattern::parse("a.####.####.exr")
            .unwrap_err()
            .to_string();
        assert!(e.contains("2 frame tokens"), "{e}");
        let e = FramePattern::parse("d####/a.exr").unwrap_err().to_string();
        assert!(e.contains("directory"), "{e}");
    }

    #[test]
    fn only_canonical_names_match() {
        let p = FramePattern::parse("b.####.exr").unwrap();
        assert_eq!(p.match_name("b.0007.exr"), Some(7));
        assert_eq!(p.match_name("b.7.exr"), None);
        assert_eq!(p.match_name("b.00007.exr"), None);
        assert_eq!(p.match_name("b.12345.exr"), Some(12345));
        assert_eq!(p.match_name("b.-007.exr"), None);
        assert_eq!(p.match_name("b.-0007.exr"), Some(-7));
        assert_eq!(p.match_name("b.00x7.exr"), None);
    }

    #[test]
    fn ranges() {
        assert_eq!(
            FrameRange::parse("1-24").unwrap(),
            FrameRange { start: 1, end: 24 }
        );
        assert_eq!(
            FrameRange::parse("7").unwrap(),
            FrameRange { start: 7, end: 7 }
        );
        assert_eq!(
            FrameRange::parse("-5--1").unwrap(),
            FrameRange { start: -5, end: -1 }
        );
        assert_eq!(
            FrameRange::parse("3:4").unwrap(),
            FrameRange { start: 3, end: 4 }
        );
        let e = FrameRange::parse("10-5").unwrap_err().to_string();
        assert!(e.contains("10-5") && e.contains("before"), "{e}");
        assert!(FrameRange::parse("a-b").is_err());
        assert_eq!(format_frame_list(&[1, 3, 4, 5, 9]), "1, 3-5, 9");
    }
}
