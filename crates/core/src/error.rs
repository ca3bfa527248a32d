//! User-facing errors for scene input. Every variant names the file and a
//! line or element, because "invalid input" with no location is useless on a
//! 300,000-triangle model.

use std::fmt;
use std::path::PathBuf;

/// Where in a file a problem is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Location {
    /// 1-based line (and column when known).
    Line { line: usize, column: Option<usize> },
    /// A named element where the format has no lines (binary PLY, glTF).
    Element(String),
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::Line {
                line,
                column: Some(c),
            } => write!(f, "line {line}, column {c}"),
            Location::Line { line, column: None } => write!(f, "line {line}"),
            Location::Element(e) => write!(f, "{e}"),
        }
    }
}

impl Location {
    pub fn line(line: usize) -> Self {
        Location::Line { line, column: None }
    }
    /// Line of byte offset `offset` in `text`.
    pub fn of_offset(text: &str, offset: usize) -> Self {
        let before = &text[..offset.min(text.len())];
        let line = before.bytes().filter(|&b| b == b'\n').count() + 1;
        let column = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
        Location::Line {
            line,
            column: Some(column),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{file}: cannot read: {source}")]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: {location}: syntax error: {message}")]
    Syntax {
        file: PathBuf,
        location: Location,
        message: String,
    },
    #[error("{file}: {location}: referenced file {missing} does not exist")]
    MissingFile {
        file: PathBuf,
        location: Location,
        missing: PathBuf,
    },
    #[error("{file}: {location}: non-finite value ({what})")]
    NonFinite {
        file: PathBuf,
        location: Location,
        what: String,
    },
    #[error("{file}: {location}: index {index} out of range ({count} available)")]
    IndexOutOfRange {
        file: PathBuf,
        location: Location,
        index: i64,
        count: usize,
    },
    #[error("{file}: {location}: {message}")]
    Invalid {
        file: PathBuf,
        location: Location,
        message: String,
    },
}

impl SceneError {
    pub fn file(&self) -> &std::path::Path {
        match self {
            SceneError::Io { file, .. }
            | SceneError::Syntax { file, .. }
            | SceneError::MissingFile { file, .. }
            | SceneError::NonFinite { file, .. }
            | SceneError::IndexOutOfRange { file, .. }
            | SceneError::Invalid { file, .. } => file,
        }
    }

    /// Where in the file, for every error but a file that cannot be read.
    pub fn location(&self) -> Option<&Location> {
        match self {
            SceneError::Io { .. } => None,
            SceneError::Syntax { location, .. }
            | SceneError::MissingFile { location, .. }
            | SceneError::NonFinite { location, .. }
            | SceneError::IndexOutOfRange { location, .. }
            | SceneError::Invalid { location, .. } => Some(location),
        }
    }
}
