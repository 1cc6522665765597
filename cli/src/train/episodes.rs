//! Training episodes: `episodes.csv` (written as they arrive, read back on resume), the
//! episodes of the run so far, and their order-W moving averages.

use std::fs;
use std::path::Path;

use anyhow::Result;
use mapless_proto::v1::EpisodeStats;
use mapless_sim::stats::trailing_mean;
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

/// The run's training episodes: those of earlier sessions (read back from `episodes.csv`) and
/// this session's, appended to the file as they arrive.
pub(crate) struct Episodes {
    pub(crate) rows: Vec<EpisodeRow>,
    csv: csv::Writer<fs::File>,
    /// Wall seconds of the run's earlier sessions (up to their last recorded episode): a
    /// resumed run continues its clock.
    pub(crate) offset_s: f64,
    /// Episodes recorded by earlier sessions.
    pub(crate) before: usize,
}

impl Episodes {
    /// Opens the run's `episodes.csv` (a resumed run continues its curve).
    pub(crate) fn open(run: &Path) -> Result<Episodes> {
        let path = run.join("episodes.csv");
        // A crash may have torn the last line: cut it before reading, so what is read is what stays.
        truncate_torn_line(&path)?;
        let (rows, bad) = read_episodes(&path);
        if bad > 0 {
            tracing::warn!(bad, "skipped unreadable lines of episodes.csv");
        }
        let offset_s = rows.last().map_or(0.0, |r| r.wall_s);
        let empty = fs::metadata(&path).map_or(true, |m| m.len() == 0);
        let csv = episodes_writer(fs::OpenOptions::new().create(true).append(true).open(&path)?, empty);
        let before = rows.len();
        Ok(Episodes { rows, csv, offset_s, before })
    }

    /// Records a training episode that ended at `wall_s` of the run.
    pub(crate) fn record(&mut self, e: EpisodeStats, wall_s: f64) -> Result<()> {
        record_episode(e, wall_s, &mut self.rows, &mut self.csv)
    }

    /// Training episodes of the run so far.
    pub(crate) fn count(&self) -> u64 {
        self.rows.len() as u64
    }

    /// The order-`window` moving averages of return and steps (NaN before the first episode).
    pub(crate) fn averages(&self, window: usize) -> (f64, f64) {
        averages(&self.rows, window)
    }
}

/// The order-`window` moving averages of return and steps now: the newest entries of
/// `mapless_sim::stats::moving_average` over `rows` (NaN before the first episode).
pub(crate) fn averages(rows: &[EpisodeRow], window: usize) -> (f64, f64) {
    (trailing_mean(rows.iter().map(|e| e.episode_return), window), trailing_mean(rows.iter().map(|e| f64::from(e.steps)), window))
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

/// A training episode for tests: episode `episode` at `episode` s, `ret` and `steps`.
#[cfg(test)]
pub(crate) fn row(episode: u64, ret: f64, steps: u32) -> EpisodeRow {
    EpisodeRow {
        episode,
        wall_s: episode as f64,
        actor_id: "actor-0-1-2".into(),
        policy_version: 3,
        episode_return: ret,
        steps,
        terminal: steps < 1000,
        eqs: 12.0,
        ees: 1.5,
        distance_m: 40.0,
        shaded_time_s: 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episodes_csv_round_trips_and_skips_a_torn_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("episodes.csv");
        // An actor id is the peer's: a comma or a quote in it stays inside its field.
        let mut odd = row(2, 321.25, 1000);
        odd.actor_id = "actor,\"0\"".into();
        let rows = vec![row(1, -12.5, 37), odd];
        let mut w = episodes_writer(std::fs::File::create(&p).unwrap(), true);
        for r in &rows {
            w.serialize(r).unwrap();
        }
        drop(w);
        let text = std::fs::read_to_string(&p).unwrap();
        assert!(text.starts_with("episode,wall_s,actor_id,policy_version,return,steps,terminal,eqs,ees,distance_m,shaded_time_s\n1,1.0,actor-0-1-2,3,-12.5,37,1,"), "{text}");
        std::fs::write(&p, format!("{text}3,12.0,actor-0")).unwrap();
        let (back, bad) = read_episodes(&p);
        assert_eq!(bad, 1);
        assert_eq!(back, rows);
        // A file written before the csv crate (fixed decimals) reads back the same way.
        std::fs::write(&p, "episode,wall_s,actor_id,policy_version,return,steps,terminal,eqs,ees,distance_m,shaded_time_s\n7,12.345,actor-1-9-0,40,321.2500,1000,0,55,1.1300,49.000,0.00\n").unwrap();
        let (back, bad) = read_episodes(&p);
        assert_eq!((back.len(), bad, back[0].episode, back[0].terminal, back[0].episode_return), (1, 0, 7, false, 321.25));
    }

    #[test]
    fn a_resumed_run_continues_its_episodes_and_clock() {
        let dir = tempfile::tempdir().unwrap();
        let stats = |ret: f64, evaluation: bool| EpisodeStats { actor_id: "a".into(), episode_return: ret, steps: 10, evaluation, ..EpisodeStats::default() };
        let mut e = Episodes::open(dir.path()).unwrap();
        assert_eq!((e.count(), e.before, e.offset_s), (0, 0, 0.0));
        assert!(e.averages(2).0.is_nan(), "no episodes: no average");
        e.record(stats(1.0, false), 5.0).unwrap();
        e.record(stats(99.0, true), 6.0).unwrap();
        e.record(stats(3.0, false), 7.5).unwrap();
        assert_eq!(e.count(), 2, "an evaluation episode is not a training episode");
        assert_eq!(e.averages(2), (2.0, 10.0));
        drop(e);
        let e = Episodes::open(dir.path()).unwrap();
        assert_eq!((e.count(), e.before, e.offset_s), (2, 2, 7.5));
        assert_eq!(e.rows.iter().map(|r| r.episode).collect::<Vec<_>>(), [1, 2]);
        let text = std::fs::read_to_string(dir.path().join("episodes.csv")).unwrap();
        assert_eq!(text.matches("episode,").count(), 1, "one header: {text}");
    }
}
