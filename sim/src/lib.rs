//! `mapless-sim` — the pure, synchronous, deterministic simulator behind mapless.
//!
//! ```text
//!   Map (built-in / vector YAML / ROS map_server) ──► World (Scene index + EnvConfig)
//!                                                        │  shared by Arc
//!                                                        ▼
//!                                      Env (one vehicle) / VecEnv (many, one call)
//!                                         bicycle model · range sensor · reward · EQS/EES
//!   paper (the paper's numbers) · stats (order-W moving average)
//!   worlds (seeded procedural worlds in five families, `gen:FAMILY:SEED`) ──► Map
//! ```
//!
//! Pictures of maps, episodes and training curves live in `mapless-plots`, which reads these
//! types; the simulator itself draws nothing.
//!
//! No async, no global state: every random draw comes from a vehicle's own seeded stream, so a
//! seed fixes an episode exactly. Units are in names (`range_m`, `heading_rad`). Every number
//! is a config field documented with its source (`config`).

pub mod baseline;
pub mod bench;
pub mod bounds;
pub mod config;
pub mod env;
pub mod eqs_analysis;
pub mod error;
pub mod explore;
pub mod fuzzing;
mod image;
pub mod map;
pub mod paper;
pub mod scene;
pub mod sensor;
pub mod stats;
pub mod vehicle;
pub mod worlds;

pub use config::{EnvConfig, EpisodeConfig, ExplorationConfig, InnerSum, ObservationConfig, RaycastMethod, RewardConfig, SensorConfig, VehicleConfig};
pub use env::{Env, EpisodeSummary, StepOutcome, VecEnv, VecStep, World};
pub use error::{Result, SimError};
pub use explore::ExplorationTracker;
pub use map::Map;
pub use vehicle::Pose;
