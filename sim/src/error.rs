//! The simulator's one error type.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A map file that cannot be read, parsed or is inconsistent. Always names the file.
    #[error("map file {path}: {problem}")]
    MapFile { path: PathBuf, problem: String },
    /// A built-in map name that does not exist.
    #[error("unknown map `{0}` (built-in maps: env1, env2, env3, outdoor20; a generated world gen:FAMILY:SEED; or a path to a .yaml map)")]
    UnknownMap(String),
    /// A configuration value outside its domain.
    #[error("invalid config: {0}")]
    InvalidConfig(String),
    /// An action that is not finite, or a batch of actions of the wrong length.
    #[error("invalid action for vehicle {vehicle}: {problem}")]
    InvalidAction { vehicle: usize, problem: String },
    /// Rejection sampling found no pose with the required clearance.
    #[error("map `{map}`: no collision-free start with {clearance_m} m clearance{}{} found in {attempts} attempts", if *escapable { " from which the car can drive a full-lock circle (episode.start_escapable)" } else { "" }, match facing_within_m { Some(d) => format!(" facing a surface within {d} m (a hard start, episode.hard_start_share)"), None => String::new() })]
    NoFreeStart { map: String, clearance_m: f64, escapable: bool, facing_within_m: Option<f64>, attempts: usize },
}

pub type Result<T, E = SimError> = std::result::Result<T, E>;
