//! Training episodes: `episodes.csv` (written as they arrive, read back on resume) and the
//! order-W moving averages the stop rule reads.

use std::fs;
use std::path::Path;

use anyhow::Result;
use mapless_proto::v1::EpisodeStats;
use serde::{Deserialize, Serialize};

// ---------------------------------------------------------------------------------------------
// Episodes: CSV and moving averages
// ---------------------------------------------------------------------------------------------

/// One training episode as the run records it: a row of `episodes.csv` (the `csv` crate
/// writes and reads it, quoting what must be quoted — an actor id is the peer's).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRow {
    pub episode: u64,
    pub wall_s: f64,
    pub actor_id: String,
    pub policy_version: u64,
    #[serde(rename = "return")]
    pub episode_return: f64,
    pub steps: u32,
    /// Written 1 (a collision ended it) or 0.
    #[serde(with = "zero_one")]
    pub terminal: bool,
    pub eqs: f64,
    pub ees: f64,
    pub distance_m: f64,
    pub shaded_time_s: f64,
}

/// A bool as 0 / 1 (what spreadsheets and pandas read as numbers).
pub(crate) mod zero_one {
    use serde::{Deserialize, Deserializer, Serializer};
    pub fn serialize<S: Serializer>(b: &bool, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u8(u8::from(*b))
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<bool, D::Error> {
        match u8::deserialize(d)? {
            0 => Ok(false),
            1 => Ok(true),
            n => Err(serde::de::Error::custom(format!("terminal is {n}, expected 0 or 1"))),
        }
    }
}

/// Appends rows to `episodes.csv` (the header first when the file is new).
pub(crate) fn episodes_writer(file: fs::File, header: bool) -> csv::Writer<fs::File> {
    csv::WriterBuilder::new().has_headers(header).from_writer(file)
}

/// Reads a run's `episodes.csv` (for a resume); rows that do not parse (a torn last line
/// after a crash) are skipped and counted.
pub fn read_episodes(path: &Path) -> (Vec<EpisodeRow>, usize) {
    let Ok(mut r) = csv::Reader::from_path(path) else { return (Vec::new(), 0) };
    let mut rows = Vec::new();
    let mut bad = 0;
    for row in r.deserialize::<EpisodeRow>() {
        match row {
            Ok(row) => rows.push(row),
            Err(_) => bad += 1,
        }
    }
    (rows, bad)
}

/// Cuts a last line that a crash left without its newline, so appended rows start clean.
pub(crate) fn truncate_torn_line(path: &Path) -> Result<()> {
    let Ok(bytes) = fs::read(path) else { return Ok(()) };
    if bytes.is_empty() || bytes.ends_with(b"\n") {
        return Ok(());
    }
    let keep = bytes.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
    let f = fs::OpenOptions::new().write(true).open(path)?;
    f.set_len(keep as u64)?;
    Ok(())
}

/// Trailing mean of the last `window` values (fewer at the start).
pub(crate) fn trailing_mean(values: impl DoubleEndedIterator<Item = f64>, window: usize) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for v in values.rev().take(window) {
        s += v;
        n += 1;
    }
    if n == 0 { f64::NAN } else { s / n as f64 }
}

/// Appends a training episode (numbered after the last one) to `rows` and `episodes.csv`;
/// evaluation records are not part of the training curve.
pub(crate) fn record_episode(e: EpisodeStats, wall_s: f64, rows: &mut Vec<EpisodeRow>, csv: &mut csv::Writer<fs::File>) -> Result<()> {
    if e.evaluation {
        return Ok(());
    }
    let row = EpisodeRow {
        episode: rows.last().map_or(1, |r| r.episode + 1),
        wall_s,
        // The peer's: one line per row, whatever it sent (a torn line is cut at a newline).
        actor_id: e.actor_id.replace(['\n', '\r'], " "),
        policy_version: e.policy_version,
        episode_return: e.episode_return,
        steps: e.steps,
        terminal: e.terminal,
        eqs: e.eqs,
        ees: e.ees,
        distance_m: e.distance_m,
        shaded_time_s: e.shaded_time_s,
    };
    csv.serialize(&row)?;
    // A line at a time: a crash tears at most the last one (skipped on resume).
    csv.flush()?;
    rows.push(row);
    Ok(())
}
