//! The pictures' one error type.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// An input the picture cannot be drawn from (a window of 0, a picture of no pixels).
    #[error("cannot draw {what}: {problem}")]
    Invalid { what: &'static str, problem: String },
    /// plotters failed (the embedded font unreadable, a drawing error).
    #[error("drawing {what} failed: {problem}")]
    Draw { what: &'static str, problem: String },
    #[error("cannot write {path}: {problem}")]
    Output { path: PathBuf, problem: String },
}

pub type Result<T, E = PlotError> = std::result::Result<T, E>;
