//! Many worlds for one run: a run's `map` may name several maps and families joined by `+`
//! (`env1+gen:rooms+gen:cave`); every episode of every vehicle then draws its world from the
//! pool, built once per process and shared (`Arc<World>`), never rebuilt per episode.

use std::sync::Arc;

use super::{Family, Split, generate, resolve};
use crate::config::EnvConfig;
use crate::env::World;
use crate::error::{Result, SimError};

/// Worlds per family named in a run's map list, unless the run says otherwise [ours: enough
/// variety that a policy cannot learn the layouts, small enough to build in seconds].
pub const DEFAULT_WORLDS_PER_FAMILY: usize = 32;

/// One item of a map list.
#[derive(Clone, Debug, PartialEq)]
pub enum MapItem {
    /// One map: a built-in name, a path, or `gen:FAMILY:SEED`.
    Map(String),
    /// `gen:FAMILY`: the family's first worlds of the split in use.
    Family(Family),
}

/// The items of `spec`: the whole string if it names one map (so a path with a `+` still
/// works), else its `+`-separated parts.
pub fn parse_map_list(spec: &str) -> Result<Vec<MapItem>> {
    let item = |s: &str| -> Result<MapItem> {
        let s = s.trim();
        if s.is_empty() {
            return Err(SimError::InvalidConfig(format!("`{spec}`: an empty item in the map list")));
        }
        match s.strip_prefix(super::SPEC_PREFIX) {
            Some(rest) if !rest.contains(':') => Ok(MapItem::Family(Family::parse(rest)?)),
            _ => Ok(MapItem::Map(s.to_owned())),
        }
    };
    if !spec.contains('+') || std::path::Path::new(spec).exists() {
        return Ok(vec![item(spec)?]);
    }
    spec.split('+').map(item).collect()
}

/// The worlds of a run.
#[derive(Clone, Debug)]
pub struct WorldPool {
    worlds: Vec<Arc<World>>,
}

impl WorldPool {
    /// Builds every world `spec` names with `cfg`: each map once, each family `per_family`
    /// worlds, seeds `split.seed(0..per_family)`.
    pub fn build(spec: &str, per_family: usize, split: Split, cfg: &EnvConfig) -> Result<WorldPool> {
        let items = parse_map_list(spec)?;
        if per_family == 0 && items.iter().any(|i| matches!(i, MapItem::Family(_))) {
            return Err(SimError::InvalidConfig(format!("`{spec}` names a family but worlds_per_family is 0")));
        }
        let mut worlds = Vec::new();
        for item in items {
            match item {
                MapItem::Map(name) => worlds.push(World::new(resolve(&name)?, cfg.clone())?),
                MapItem::Family(f) => {
                    for i in 0..per_family as u64 {
                        worlds.push(World::new(generate(f, split.seed(i)?)?, cfg.clone())?);
                    }
                }
            }
        }
        Ok(WorldPool { worlds })
    }

    /// A pool of one world.
    pub fn single(world: Arc<World>) -> WorldPool {
        WorldPool { worlds: vec![world] }
    }

    /// Checks `spec` without building the families' worlds: every map loads, every family
    /// name exists.
    pub fn check(spec: &str) -> Result<()> {
        for item in parse_map_list(spec)? {
            if let MapItem::Map(name) = item {
                resolve(&name)?;
            }
        }
        Ok(())
    }

    pub fn worlds(&self) -> &[Arc<World>] {
        &self.worlds
    }

    /// The worlds, for [`crate::VecEnv::with_worlds`].
    pub fn into_worlds(self) -> Vec<Arc<World>> {
        self.worlds
    }

    pub fn len(&self) -> usize {
        self.worlds.len()
    }

    pub fn is_empty(&self) -> bool {
        self.worlds.is_empty()
    }

    /// World `i` (wrapping round).
    pub fn get(&self, i: usize) -> &Arc<World> {
        &self.worlds[i % self.worlds.len()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_lists_parse_into_maps_and_families() {
        assert_eq!(parse_map_list("env1").unwrap(), vec![MapItem::Map("env1".into())]);
        assert_eq!(parse_map_list("env1+gen:rooms+gen:cave:3").unwrap(), vec![MapItem::Map("env1".into()), MapItem::Family(Family::Rooms), MapItem::Map("gen:cave:3".into())]);
        assert!(parse_map_list("env1++env3").unwrap_err().to_string().contains("empty item"));
        assert!(parse_map_list("gen:lava").unwrap_err().to_string().contains("unknown world family"));
        assert!(WorldPool::check("env1+nowhere.yaml").is_err());
        assert!(WorldPool::check("env1+gen:forest").is_ok());
    }

    #[test]
    fn a_pool_holds_each_map_once_and_each_family_per_family_times_from_its_split() {
        let cfg = EnvConfig::default();
        let p = WorldPool::build("env1+gen:forest", 3, Split::HeldOut, &cfg).unwrap();
        let names: Vec<&str> = p.worlds().iter().map(|w| w.map.name.as_str()).collect();
        assert_eq!(names, ["env1", "forest-1000000", "forest-1000001", "forest-1000002"]);
        let t = WorldPool::build("gen:forest", 2, Split::Train, &cfg).unwrap();
        assert_eq!(t.get(0).map.name, "forest-0");
        assert_eq!(t.get(3).map.name, "forest-1");
        assert!(WorldPool::build("gen:forest", 0, Split::Train, &cfg).is_err());
    }
}
