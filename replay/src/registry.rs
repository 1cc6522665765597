//! Actor slots: which small number each actor name holds (`RegisterActor` in replay.proto).
//!
//! ```text
//!   RegisterActor(name) ─► known name?  ── yes ─► its slot                       (known = true)
//!                                       └─ no ──► lowest slot no name holds ─► write the file
//!                                                  (atomically, fsynced) ─► slot (known = false)
//!   <data dir>/actor-slots.json: {"version": 1, "slots": {"<name>": <slot>, ...}}
//! ```
//!
//! Why: replicas of one container image (`docker-compose up --scale actor=N`) all start with
//! the same command line, so none can pick its own index; the slot the replay hands out gives
//! each replica its seeds and its actor-id prefix exactly as `mapless-actor --index N` does.
//! A container keeps its host name across restarts, so a restarted replica gets its slot back.
//!
//! Invariants: no two names hold one slot; a name's slot never changes; a slot is given out
//! only after the file that records it is on disk (a replay restarted from the same directory
//! answers every name as before). Slots are never released: a replica scaled away and back
//! under a new host name takes a new slot, so `max_slots` bounds the names ever seen.
//!
//! Threading: one mutex; `register` holds it while it writes the file (a few ms, once per
//! actor process start), so registrations are serialised and the file always matches memory.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use mapless_proto::atomic_file::write_file_atomically;
use mapless_proto::check_actor_name;
use serde::{Deserialize, Serialize};

use crate::error::ReplayError;

/// The slot file's name inside the replay's data directory (`persistence.dir`).
pub const SLOTS_FILE: &str = "actor-slots.json";

/// Version of the slot file's layout; a file of another version is refused.
const FORMAT_VERSION: u32 = 1;

/// Default of `max_actor_slots` ([`crate::server::ServerConfig`]): names that may hold a slot.
/// One actor process per core of a large cluster fits; a bound keeps a misbehaving client
/// (a new name per call) from growing the file and the replay's memory without limit.
pub const DEFAULT_MAX_ACTOR_SLOTS: u32 = 4096;

/// What the slot file holds.
#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SlotFile {
    version: u32,
    slots: BTreeMap<String, u32>,
}

/// The answer to one registration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Registration {
    pub slot: u32,
    /// The name held this slot already.
    pub known: bool,
    /// Names holding a slot now.
    pub registered: u32,
}

/// Counters for `/metrics`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RegistryCounts {
    /// Names holding a slot.
    pub registered: u64,
    /// Registrations that gave out a new slot.
    pub new: u64,
    /// Registrations of a name that already held a slot.
    pub known: u64,
    /// Registrations refused (bad name, no slot left, the file could not be written).
    pub refused: u64,
}

struct State {
    slots: BTreeMap<String, u32>,
    counts: RegistryCounts,
}

/// The name → slot table of one replay server.
pub struct ActorRegistry {
    /// The slot file; none keeps the table in memory only (a replay without a data directory).
    path: Option<PathBuf>,
    max_slots: u32,
    state: Mutex<State>,
}

impl std::fmt::Debug for ActorRegistry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ActorRegistry").field("path", &self.path).field("max_slots", &self.max_slots).finish_non_exhaustive()
    }
}

impl Default for ActorRegistry {
    fn default() -> Self {
        ActorRegistry::in_memory(DEFAULT_MAX_ACTOR_SLOTS)
    }
}

impl ActorRegistry {
    /// A table kept in memory only: slots hold while this process runs.
    pub fn in_memory(max_slots: u32) -> ActorRegistry {
        ActorRegistry { path: None, max_slots, state: Mutex::new(State { slots: BTreeMap::new(), counts: RegistryCounts::default() }) }
    }

    /// The table kept in `dir`/[`SLOTS_FILE`] (memory only when `dir` is none): loads the file
    /// when it exists. A file that is not a valid slot table (unreadable, not JSON of this
    /// layout, two names on one slot, a bad name) is an error naming the file, never a silent
    /// fresh start: handing out slots again would give two replicas the same seeds.
    pub fn open(dir: Option<&Path>, max_slots: u32) -> Result<ActorRegistry, ReplayError> {
        if max_slots == 0 {
            return Err(ReplayError::InvalidConfig("max_actor_slots must be ≥ 1".into()));
        }
        let Some(dir) = dir else { return Ok(ActorRegistry::in_memory(max_slots)) };
        let path = dir.join(SLOTS_FILE);
        let corrupt = |problem: String| ReplayError::Storage {
            path: path.clone(),
            problem: format!("not a valid actor-slot file ({problem}); fix or remove it (removing it gives every actor name a new slot)"),
        };
        let slots = match std::fs::read(&path) {
            Ok(bytes) => {
                let file: SlotFile = serde_json::from_slice(&bytes).map_err(|e| corrupt(e.to_string()))?;
                if file.version != FORMAT_VERSION {
                    return Err(corrupt(format!("layout version {}, this replay reads {FORMAT_VERSION}", file.version)));
                }
                let mut taken: BTreeMap<u32, &str> = BTreeMap::new();
                for (name, &slot) in &file.slots {
                    check_actor_name(name).map_err(|e| corrupt(format!("name {name:?}: {e}")))?;
                    if let Some(other) = taken.insert(slot, name) {
                        return Err(corrupt(format!("slot {slot} is held by both {other:?} and {name:?}")));
                    }
                }
                file.slots
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                std::fs::create_dir_all(dir).map_err(|e| ReplayError::Storage { path: dir.to_owned(), problem: format!("create: {e}") })?;
                BTreeMap::new()
            }
            Err(e) => return Err(ReplayError::Storage { path, problem: format!("read: {e}") }),
        };
        let counts = RegistryCounts { registered: slots.len() as u64, ..RegistryCounts::default() };
        Ok(ActorRegistry { path: Some(path), max_slots, state: Mutex::new(State { slots, counts }) })
    }

    /// The file the table lives in, if any.
    pub fn path(&self) -> Option<&Path> {
        self.path.as_deref()
    }

    /// Most names that may hold a slot.
    pub fn max_slots(&self) -> u32 {
        self.max_slots
    }

    /// `name`'s slot: the one it holds, or the lowest free one, recorded on disk before this
    /// returns. Errors: [`ReplayError::BadRequest`] for a bad name, [`ReplayError::SlotsExhausted`]
    /// when `max_slots` names hold one, [`ReplayError::Storage`] when the file cannot be
    /// written (the slot is then not given out). Every error is counted as refused.
    pub fn register(&self, name: &str) -> Result<Registration, ReplayError> {
        let mut state = self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let outcome = Self::register_locked(&mut state, self.path.as_deref(), self.max_slots, name);
        match &outcome {
            Ok(r) if r.known => state.counts.known += 1,
            Ok(_) => state.counts.new += 1,
            Err(_) => state.counts.refused += 1,
        }
        state.counts.registered = state.slots.len() as u64;
        outcome
    }

    fn register_locked(state: &mut State, path: Option<&Path>, max_slots: u32, name: &str) -> Result<Registration, ReplayError> {
        check_actor_name(name).map_err(|e| ReplayError::BadRequest(format!("actor name: {e}")))?;
        if let Some(&slot) = state.slots.get(name) {
            return Ok(Registration { slot, known: true, registered: state.slots.len() as u32 });
        }
        // Lowest free slot: slots are few (≤ max_slots), and this runs once per actor start.
        let mut held: Vec<u32> = state.slots.values().copied().collect();
        held.sort_unstable();
        let mut slot = 0u32;
        for h in held {
            if h == slot {
                slot += 1;
            } else if h > slot {
                break;
            }
        }
        if slot >= max_slots {
            return Err(ReplayError::SlotsExhausted { max: max_slots });
        }
        state.slots.insert(name.to_owned(), slot);
        if let Some(path) = path {
            let file = SlotFile { version: FORMAT_VERSION, slots: state.slots.clone() };
            let written = serde_json::to_vec_pretty(&file).map_err(|e| e.to_string()).and_then(|bytes| write_file_atomically(path, &bytes).map_err(|e| e.to_string()));
            if let Err(problem) = written {
                state.slots.remove(name);
                return Err(ReplayError::Storage { path: path.to_owned(), problem: format!("write: {problem}") });
            }
        }
        Ok(Registration { slot, known: false, registered: state.slots.len() as u32 })
    }

    /// Counts a registration refused before it reached [`ActorRegistry::register`] (a request
    /// of another protocol version).
    pub fn record_refused(&self) {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner).counts.refused += 1;
    }

    /// Counters for `/metrics`.
    pub fn counts(&self) -> RegistryCounts {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner).counts
    }

    /// The table, name → slot.
    pub fn slots(&self) -> BTreeMap<String, u32> {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner).slots.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(tag: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("mapless-registry-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn distinct_names_get_distinct_slots_and_a_name_keeps_its_slot() {
        let r = ActorRegistry::in_memory(8);
        let a = r.register("a1b2c3").unwrap();
        let b = r.register("d4e5f6").unwrap();
        assert_eq!((a.slot, a.known, b.slot, b.known), (0, false, 1, false));
        assert_eq!(r.register("a1b2c3").unwrap(), Registration { slot: 0, known: true, registered: 2 });
        assert_eq!(r.counts(), RegistryCounts { registered: 2, new: 2, known: 1, refused: 0 });
    }

    #[test]
    fn slots_survive_a_restart_from_the_data_dir() {
        let dir = scratch("restart");
        {
            let r = ActorRegistry::open(Some(&dir), 8).unwrap();
            for name in ["one", "two", "three"] {
                r.register(name).unwrap();
            }
        }
        let r = ActorRegistry::open(Some(&dir), 8).unwrap();
        assert_eq!(r.register("two").unwrap(), Registration { slot: 1, known: true, registered: 3 });
        assert_eq!(r.register("four").unwrap().slot, 3, "a new name takes the next free slot");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn bad_names_and_a_full_table_are_refused_and_counted() {
        let r = ActorRegistry::in_memory(2);
        assert!(matches!(r.register(""), Err(ReplayError::BadRequest(m)) if m.contains("empty")));
        assert!(matches!(r.register(&"x".repeat(129)), Err(ReplayError::BadRequest(m)) if m.contains("129 bytes")));
        assert!(matches!(r.register("tab\there"), Err(ReplayError::BadRequest(m)) if m.contains("control")));
        r.register("a").unwrap();
        r.register("b").unwrap();
        let full = r.register("c").unwrap_err();
        assert!(matches!(full, ReplayError::SlotsExhausted { max: 2 }), "{full}");
        assert_eq!(full.to_status().code(), tonic::Code::ResourceExhausted);
        assert_eq!(r.register("b").unwrap().slot, 1, "known names still get their slot when the table is full");
        assert_eq!(r.counts(), RegistryCounts { registered: 2, new: 2, known: 1, refused: 4 });
    }

    #[test]
    fn a_corrupt_slot_file_is_a_clear_error() {
        let dir = scratch("corrupt");
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(SLOTS_FILE);
        for (content, says) in [
            ("{\"version\": 1, \"slots\": {\"a\": 0", "EOF"),
            ("not json", "expected"),
            ("{\"version\": 7, \"slots\": {}}", "layout version 7"),
            ("{\"version\": 1, \"slots\": {\"a\": 0, \"b\": 0}}", "slot 0 is held by both"),
            ("{\"version\": 1, \"slots\": {\"\": 0}}", "is empty"),
            ("{\"version\": 1, \"slots\": {\"a\": -1}}", "invalid value"),
        ] {
            std::fs::write(&path, content).unwrap();
            let e = ActorRegistry::open(Some(&dir), 8).unwrap_err().to_string();
            assert!(e.contains(SLOTS_FILE) && e.contains("not a valid actor-slot file") && e.contains(says), "{content}: {e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_unwritable_file_gives_out_no_slot() {
        let dir = scratch("unwritable");
        let r = ActorRegistry::open(Some(&dir), 8).unwrap();
        r.register("kept").unwrap();
        // The directory is gone: the atomic write cannot create its temporary file.
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(matches!(r.register("lost"), Err(ReplayError::Storage { .. })));
        assert_eq!(r.slots(), BTreeMap::from([("kept".to_owned(), 0)]));
        assert_eq!(r.counts().refused, 1);
    }
}
