//! Worlds without end: seeded, deterministic procedural worlds in five families, each with a
//! guaranteed connected space to drive in (`mapless worlds generate | show`, `gen:FAMILY:SEED`
//! wherever a map is named).
//!
//! ```text
//!   (family, seed) ──► Pcg64Mcg ──► size in the family's range ──► layout ──► Map
//!                                                  ▲                          │
//!                                                  └── next draw if not ──────┤ DrivableSpace:
//!                                                      one component           one 4-connected
//!                                                      of enough area          component?
//! ```
//!
//! | family   | sizes (m) | what it holds                                                         |
//! |----------|-----------|-----------------------------------------------------------------------|
//! | `rooms`  | 20–50     | rooms and corridors by binary space partition, 2.2–3.5 m doorways, furniture |
//! | `cave`   | 25–60     | cellular-automaton cave (1 m cells, the 4-5 rule), smoothed to 0.25 m |
//! | `hall`   | 15–40     | a walled hall of shelf rows with gaps, aisles 2.4–4 m, crates, pillars |
//! | `forest` | 20–60     | trunks and boulders, 1.4–3 m apart at the least                       |
//! | `field`  | 30–60     | an outdoor field: sparse trees whose canopies shade the ground, boulders |
//!
//! Every world is fenced (the car cannot leave it). A world is accepted only if the space where
//! the car's centre can be with [`DRIVE_CLEARANCE_M`] to spare, sampled every
//! [`DRIVABLE_CELL_M`], is one 4-connected piece covering at least the family's share of the
//! map; otherwise the same stream draws again, so a seed always names the same world. Every
//! random start of an episode (which needs more clearance) then lies in that one piece.
//!
//! Worlds are split three ways by seed ([`Split`]), as a learning result wants them: training
//! draws seeds below [`HELD_OUT_FIRST_SEED`]; the held-out worlds that evaluations report on
//! start there; the validation worlds that a run's own evaluations judge it on while it trains
//! (its stop gate, the choice of its policy) start at [`VALIDATION_FIRST_SEED`], so a policy
//! chosen on some worlds is never reported on those. A run's map may be a list of maps and
//! families (`env1+gen:rooms+gen:cave`, [`WorldPool`]): its vehicles draw a world per episode
//! from the families' training worlds.

mod cave;
mod clutter;
mod drivable;
mod pool;
mod rooms;

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;
use serde::{Deserialize, Serialize};

pub use drivable::DrivableSpace;
pub use pool::{DEFAULT_WORLDS_PER_FAMILY, MapItem, WorldPool, parse_map_list};

use crate::error::{Result, SimError};
use crate::map::{Bounds, Map, Obstacle, Region, VECTOR_FORMAT, VectorMapFile};

/// The smallest and largest side of a generated world (m).
pub const SIZE_RANGE_M: (f64, f64) = (15.0, 60.0);
/// Clearance the car's centre needs for a cell to count as drivable: the default car's
/// circumradius (0.55 m × 0.30 m → 0.313 m) plus 0.14 m, so any heading fits there.
pub const DRIVE_CLEARANCE_M: f64 = 0.45;
/// Spacing of the drivable-space lattice (m).
pub const DRIVABLE_CELL_M: f64 = 0.25;
/// First seed of the held-out evaluation worlds; training worlds use the seeds below it.
pub const HELD_OUT_FIRST_SEED: u64 = 1_000_000;
/// First seed of the validation worlds; the held-out ones end below it.
pub const VALIDATION_FIRST_SEED: u64 = 2_000_000;
/// Draws per seed before generation gives up (never reached by the shipped families; tested).
const MAX_DRAWS: usize = 64;
/// Prefix that names a generated world wherever a map is named: `gen:cave:7`.
pub const SPEC_PREFIX: &str = "gen:";

/// A family of worlds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Family {
    Rooms,
    Cave,
    Hall,
    Forest,
    Field,
}

impl Family {
    /// Every family, in the order of the module's table.
    pub const ALL: [Family; 5] = [Family::Rooms, Family::Cave, Family::Hall, Family::Forest, Family::Field];

    pub fn name(self) -> &'static str {
        match self {
            Family::Rooms => "rooms",
            Family::Cave => "cave",
            Family::Hall => "hall",
            Family::Forest => "forest",
            Family::Field => "field",
        }
    }

    /// A family by name.
    pub fn parse(name: &str) -> Result<Family> {
        Family::ALL.into_iter().find(|f| f.name() == name).ok_or_else(|| SimError::InvalidConfig(format!("unknown world family `{name}` (rooms, cave, hall, forest, field)")))
    }

    /// The range a world's side length is drawn from (m), within [`SIZE_RANGE_M`].
    pub fn size_range_m(self) -> (f64, f64) {
        match self {
            Family::Rooms => (20.0, 50.0),
            Family::Cave => (25.0, 60.0),
            Family::Hall => (15.0, 40.0),
            Family::Forest => (20.0, 60.0),
            Family::Field => (30.0, 60.0),
        }
    }

    /// The least share of the map's area that must be drivable (one piece).
    fn min_drivable_share(self) -> f64 {
        match self {
            Family::Cave => 0.25,
            Family::Rooms | Family::Hall => 0.45,
            Family::Forest | Family::Field => 0.6,
        }
    }

    /// One line on what the family holds.
    pub fn describe(self) -> &'static str {
        match self {
            Family::Rooms => "rooms and corridors with doorways, some furniture",
            Family::Cave => "a cave of winding passages and chambers",
            Family::Hall => "a cluttered hall: shelf rows, crates and pillars",
            Family::Forest => "a forest of trunks and boulders",
            Family::Field => "an outdoor field: trees whose canopies shade the ground, boulders",
        }
    }
}

impl std::fmt::Display for Family {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Which use a world seed is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    /// Seeds `0 .. HELD_OUT_FIRST_SEED`: what training draws from.
    Train,
    /// Seeds `HELD_OUT_FIRST_SEED .. VALIDATION_FIRST_SEED`: what evaluations report on, never
    /// trained on, never used to choose a policy.
    HeldOut,
    /// Seeds from `VALIDATION_FIRST_SEED` up: what a run's evaluations while it trains judge it
    /// on (its stop gate, the choice of its policy at the end), never trained on.
    Validation,
}

impl Split {
    /// The split a seed belongs to.
    pub fn of(seed: u64) -> Split {
        [Split::Train, Split::HeldOut, Split::Validation].into_iter().find(|s| s.bounds().1.is_none_or(|end| seed < end)).expect("the last split has no end")
    }

    /// The split's first seed and the seed it ends before (none: it runs to `u64::MAX`); the
    /// one place the ranges are written.
    fn bounds(self) -> (u64, Option<u64>) {
        match self {
            Split::Train => (0, Some(HELD_OUT_FIRST_SEED)),
            Split::HeldOut => (HELD_OUT_FIRST_SEED, Some(VALIDATION_FIRST_SEED)),
            Split::Validation => (VALIDATION_FIRST_SEED, None),
        }
    }

    /// The `index`-th seed of this split (an index must keep the seed inside the split).
    pub fn seed(self, index: u64) -> Result<u64> {
        let (first, end) = self.bounds();
        first.checked_add(index).filter(|s| end.is_none_or(|e| *s < e)).ok_or_else(|| {
            let seeds = match end {
                Some(e) => format!("{first}..{e}"),
                None => format!("from {first}"),
            };
            SimError::InvalidConfig(format!("{} world index {index} too large: the split holds seeds {seeds}", self.name()))
        })
    }

    /// What the split is called in messages.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "training",
            Split::HeldOut => "held-out",
            Split::Validation => "validation",
        }
    }
}

/// The generated world `family` / `seed`, named `FAMILY-SEED`. Deterministic: the same pair
/// gives the same world on every machine.
pub fn generate(family: Family, seed: u64) -> Result<Map> {
    // One stream per (family, seed): the family's index in the high bits keeps them apart.
    let mut rng = Pcg64Mcg::seed_from_u64(seed ^ ((family as u64 + 1) << 56).rotate_left(7));
    let (lo, hi) = family.size_range_m();
    let size = (rng.random_range(lo..=hi) * 2.0).round() / 2.0;
    let name = format!("{}-{seed}", family.name());
    for draw in 0..MAX_DRAWS {
        let map = match family {
            Family::Rooms => rooms::rooms(&mut rng, size, &name),
            Family::Cave => cave::cave(&mut rng, size, &name),
            Family::Hall => clutter::hall(&mut rng, size, &name),
            Family::Forest => clutter::forest(&mut rng, size, &name),
            Family::Field => clutter::field(&mut rng, size, &name),
        }?;
        let space = DrivableSpace::of(&map, DRIVE_CLEARANCE_M, DRIVABLE_CELL_M);
        if space.is_connected() && space.share() >= family.min_drivable_share() {
            let mut map = map;
            map.description = format!("generated {family} world, seed {seed}, {} m x {} m ({}); draw {}", map.bounds.width(), map.bounds.height(), family.describe(), draw + 1);
            return Ok(map);
        }
    }
    Err(SimError::InvalidConfig(format!("world {name}: no layout with one connected drivable space in {MAX_DRAWS} draws")))
}

/// A map wherever a user names one: a generated world `gen:FAMILY:SEED`, else a built-in
/// name or a map file ([`Map::resolve`]).
pub fn resolve(name_or_path: &str) -> Result<Map> {
    match parse_spec(name_or_path) {
        Some(spec) => {
            let (family, seed) = spec?;
            generate(family, seed)
        }
        None => Map::resolve(name_or_path),
    }
}

/// Parses `gen:FAMILY:SEED` (`None` if `spec` does not start with `gen:`).
pub fn parse_spec(spec: &str) -> Option<Result<(Family, u64)>> {
    let rest = spec.strip_prefix(SPEC_PREFIX)?;
    let bad = || SimError::InvalidConfig(format!("`{spec}`: a generated world is named gen:FAMILY:SEED, e.g. gen:cave:7"));
    let Some((fam, seed)) = rest.split_once(':') else { return Some(Err(bad())) };
    Some(Family::parse(fam).and_then(|f| seed.parse::<u64>().map(|s| (f, s)).map_err(|_| bad())))
}

/// A vector world of side `size` centred on the origin, fenced.
fn vector_map(name: &str, size: f64, obstacles: Vec<Obstacle>, shaded: Vec<Region>) -> Result<Map> {
    let h = size / 2.0;
    let file = VectorMapFile {
        format: VECTOR_FORMAT.into(),
        name: name.into(),
        description: String::new(),
        bounds: Bounds { min: [-h, -h], max: [h, h] },
        boundary_walls: true,
        wall_thickness_m: 0.0,
        obstacles,
        shaded,
    };
    let text = serde_yaml::to_string(&file).map_err(|e| SimError::InvalidConfig(format!("world {name}: {e}")))?;
    Map::from_vector_yaml(&text, std::path::Path::new(&format!("<generated {name}>")))
}

/// Rounds to centimetres, so a world's YAML reads cleanly and reloads exactly.
fn cm(v: f64) -> f64 {
    (v * 100.0).round() / 100.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_and_bad_ones_say_how() {
        assert_eq!(parse_spec("gen:cave:7").unwrap().unwrap(), (Family::Cave, 7));
        assert!(parse_spec("env1").is_none());
        let e = parse_spec("gen:lava:1").unwrap().unwrap_err().to_string();
        assert!(e.contains("unknown world family `lava`"), "{e}");
        let e = parse_spec("gen:cave").unwrap().unwrap_err().to_string();
        assert!(e.contains("gen:FAMILY:SEED"), "{e}");
    }

    #[test]
    fn the_split_is_by_seed_and_never_overlaps() {
        assert_eq!(Split::of(Split::Train.seed(HELD_OUT_FIRST_SEED - 1).unwrap()), Split::Train);
        assert_eq!(Split::of(Split::HeldOut.seed(0).unwrap()), Split::HeldOut);
        assert_eq!(Split::of(Split::HeldOut.seed(VALIDATION_FIRST_SEED - HELD_OUT_FIRST_SEED - 1).unwrap()), Split::HeldOut);
        assert_eq!(Split::of(Split::Validation.seed(0).unwrap()), Split::Validation);
        assert!(Split::Train.seed(HELD_OUT_FIRST_SEED).is_err());
        let e = Split::HeldOut.seed(VALIDATION_FIRST_SEED - HELD_OUT_FIRST_SEED).unwrap_err().to_string();
        assert!(e.contains("held-out world index 1000000 too large") && e.contains("1000000..2000000"), "{e}");
        assert!(Split::Validation.seed(u64::MAX).is_err());
        for i in [0, 1, 17, 999_999] {
            let (t, h, v) = (Split::Train.seed(i).unwrap(), Split::HeldOut.seed(i).unwrap(), Split::Validation.seed(i).unwrap());
            assert!(t < HELD_OUT_FIRST_SEED && (HELD_OUT_FIRST_SEED..VALIDATION_FIRST_SEED).contains(&h) && v >= VALIDATION_FIRST_SEED);
        }
    }
}
