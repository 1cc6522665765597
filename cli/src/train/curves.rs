//! `curves.png`: the run's training curves (order-W moving averages of return and steps, the
//! paper's Figs. 8–9), drawn again as episodes come in and once at the end.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use mapless_plots::{CurvePoint, CurveStyle, training_curves_png};

use super::config::TrainConfig;
use super::episodes::EpisodeRow;

/// When `curves.png` is drawn again: after 50 new episodes, or 30 s after the last drawing
/// when any came.
pub(crate) struct Curves {
    run: PathBuf,
    drawn: usize,
    at: Instant,
}

impl Curves {
    /// `episodes` are drawn already (a resumed run's picture holds them).
    pub(crate) fn new(run: &Path, episodes: usize) -> Curves {
        Curves { run: run.to_owned(), drawn: episodes, at: Instant::now() }
    }

    /// Draws the curves when it is time.
    pub(crate) fn tick(&mut self, cfg: &TrainConfig, rows: &[EpisodeRow]) {
        if rows.len() > self.drawn && (rows.len() - self.drawn >= 50 || self.at.elapsed() >= Duration::from_secs(30)) {
            draw_curves(&self.run, cfg, rows);
            self.drawn = rows.len();
            self.at = Instant::now();
        }
    }
}

pub(crate) fn draw_curves(run: &Path, cfg: &TrainConfig, rows: &[EpisodeRow]) {
    let points: Vec<CurvePoint> = rows.iter().map(|r| CurvePoint { episode: r.episode, episode_return: r.episode_return, steps: r.steps }).collect();
    let style = CurveStyle {
        title: format!("{} – order-{} moving averages", cfg.name, cfg.stop.window),
        window: cfg.stop.window,
        return_goal: cfg.stop.average_return,
        steps_goal: cfg.stop.average_steps,
        footer: format!("{} episodes", rows.len()),
    };
    if let Err(e) = training_curves_png(&points, &style, &run.join("curves.png")) {
        tracing::warn!(error = %e, "cannot draw curves.png");
    }
}
