//! Errors that point at the file, line and field that is wrong, and say what to do.

use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// One problem found in a netlist.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Diagnostic {
    /// Dotted path of the offending field, e.g. `task.teleop.links[1]`.
    pub field: String,
    pub message: String,
    /// What to do about it.
    pub help: Option<String>,
    /// 1-based line and column in the file, when known.
    pub location: Option<(usize, usize)>,
}

/// A netlist could not be read or is not valid. Lists every problem found, not just the first.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub struct NetlistError {
    pub file: PathBuf,
    pub diagnostics: Vec<Diagnostic>,
    /// What the file is: `"netlist"`, or `"sequence"` for an onboard sequence.
    pub document: &'static str,
}

impl NetlistError {
    /// `file` (a `document`: "netlist" or "sequence") could not be read.
    pub(crate) fn unreadable(file: &Path, e: &std::io::Error, document: &'static str) -> Self {
        NetlistError {
            file: file.to_path_buf(),
            diagnostics: vec![Diagnostic {
                field: "file".into(),
                message: format!("cannot read: {e}"),
                help: Some("check the path".into()),
                location: None,
            }],
            document,
        }
    }
}

impl fmt::Display for NetlistError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = self.diagnostics.len();
        writeln!(
            f,
            "{}: {n} error{} in {}",
            self.file.display(),
            if n == 1 { "" } else { "s" },
            self.document
        )?;
        for d in &self.diagnostics {
            match d.location {
                Some((line, col)) => write!(f, "  {}:{line}:{col}: ", self.file.display())?,
                None => write!(f, "  {}: ", self.file.display())?,
            }
            writeln!(f, "{}: {}", d.field, d.message)?;
            if let Some(help) = &d.help {
                writeln!(f, "      help: {help}")?;
            }
        }
        Ok(())
    }
}

/// Why a module executable named by a netlist (`exec`) did not say what kind it is. The
/// netlist's diagnostic for the kind quotes it.
#[derive(Debug, thiserror::Error)]
pub enum DescribeError {
    /// It is not run here: why, and what to do.
    #[error("{0}")]
    NotRun(String),
    #[error("{0}")]
    Io(#[from] std::io::Error),
    #[error("`describe` did not finish within {0} s")]
    Timeout(u64),
    #[error("`describe` printed more than {0} bytes")]
    TooMuchOutput(u64),
    /// It failed: its status and the end of what it printed on standard error (a Python
    /// module's traceback, say).
    #[error("`describe` exited with {status}{}", if stderr.is_empty() { String::new() } else { format!(", saying:\n{stderr}") })]
    Failed {
        status: std::process::ExitStatus,
        stderr: String,
    },
    #[error("`describe` printed no kind: {0}")]
    NoKind(#[source] serde_json::Error),
}

impl From<String> for DescribeError {
    fn from(why: String) -> Self {
        Self::NotRun(why)
    }
}

impl From<&str> for DescribeError {
    fn from(why: &str) -> Self {
        Self::NotRun(why.to_string())
    }
}

/// Asks a module executable for its kind (see [`crate::Netlist::parse`]).
pub type Describe<'a> = dyn FnMut(&Path) -> Result<crate::KindSpec, DescribeError> + 'a;

/// Collects diagnostics while validating one source text.
#[derive(Debug)]
pub(crate) struct Reporter<'a> {
    file: &'a Path,
    text: &'a str,
    diagnostics: Vec<Diagnostic>,
}

impl<'a> Reporter<'a> {
    pub(crate) fn new(file: &'a Path, text: &'a str) -> Self {
        Self {
            file,
            text,
            diagnostics: Vec::new(),
        }
    }

    pub(crate) fn error(
        &mut self,
        span: Option<Range<usize>>,
        field: impl Into<String>,
        message: impl Into<String>,
        help: Option<String>,
    ) {
        let location = span.map(|s| line_col(self.text, s.start));
        self.diagnostics.push(Diagnostic {
            field: field.into(),
            message: message.into(),
            help,
            location,
        });
    }

    /// The source text being checked.
    pub(crate) fn text(&self) -> &'a str {
        self.text
    }

    pub(crate) fn has_errors(&self) -> bool {
        !self.diagnostics.is_empty()
    }

    pub(crate) fn finish(self) -> Result<(), NetlistError> {
        if self.diagnostics.is_empty() {
            Ok(())
        } else {
            Err(NetlistError {
                file: self.file.to_path_buf(),
                diagnostics: self.diagnostics,
                document: "netlist",
            })
        }
    }
}

/// 1-based line and column of a byte offset.
pub(crate) fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let mut offset = offset.min(text.len());
    // A span computed into the middle of a character points at the character.
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let col = before.rfind('\n').map_or(before.chars().count(), |nl| {
        before[nl + 1..].chars().count()
    }) + 1;
    (line, col)
}

/// The closest candidate by edit distance, for "did you mean" hints.
pub(crate) fn closest<'c>(
    word: &str,
    candidates: impl IntoIterator<Item = &'c str>,
) -> Option<&'c str> {
    candidates
        .into_iter()
        .map(|c| (edit_distance(word, c), c))
        .filter(|(d, c)| *d <= 2.max(c.len() / 3))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, cb) in b.iter().enumerate() {
            let cost = usize::from(ca != *cb);
            cur[j + 1] = (prev[j] + cost).min(prev[j + 1] + 1).min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

/// "did you mean `x`? known: a, b, c"
pub(crate) fn suggest<'c>(
    word: &str,
    candidates: impl IntoIterator<Item = &'c str> + Clone,
) -> String {
    let known: Vec<&str> = candidates.clone().into_iter().collect();
    let list = if known.is_empty() {
        "none are declared".to_string()
    } else {
        format!("known: {}", known.join(", "))
    };
    match closest(word, candidates) {
        Some(c) => format!("did you mean `{c}`? ({list})"),
        None => list,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_col_counts_from_one() {
        let text = "a\nbc\ndef";
        assert_eq!(line_col(text, 0), (1, 1));
        assert_eq!(line_col(text, 3), (2, 2));
        assert_eq!(line_col(text, 5), (3, 1));
    }

    #[test]
    fn closest_finds_typos_only() {
        assert_eq!(closest("joystik", ["joystick", "drive"]), Some("joystick"));
        assert_eq!(closest("zzz", ["joystick", "drive"]), None);
    }
}
