//! In-process environments for testing the algorithms end to end without actors or a
//! replay service: today Pendulum-v1, the standard first check of a continuous-control
//! learner.

pub mod pendulum;

pub use pendulum::{Pendulum, PendulumStep};
