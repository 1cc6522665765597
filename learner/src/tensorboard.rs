//! TensorBoard event files, written in pure Rust (no TensorFlow, no libtorch).
//!
//! A file `events.out.tfevents.<unix secs>.<host>` in the log directory is a sequence of
//! TFRecords, each
//!
//! ```text
//!  u64 LE  length of data
//!  u32 LE  masked CRC-32C of those 8 length bytes
//!  [u8]    data: one serialized tensorflow.Event
//!  u32 LE  masked CRC-32C of data
//! ```
//!
//! with masked(c) = ((c >> 15) | (c << 17)) + 0xa282ead8 and CRC-32C the Castagnoli CRC
//! (polynomial 0x1EDC6F41, reflected 0x82F63B78) — not the IEEE CRC-32 of zlib. The first
//! event carries `file_version = "brain.Event:2"`, every later one a scalar summary.
//! [`read_events`] reads such a file back, checking every CRC.
//!
//! Metric names follow fixed namespaces, e.g. `losses/critic`, `charts/updates_per_s`.

use std::fs::{File, OpenOptions};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use prost::Message as _;

use crate::error::LearnerError;

/// `Event.file_version` of the first record, as TensorFlow and TensorBoard write it.
pub const FILE_VERSION: &str = "brain.Event:2";
/// Default longest time an added scalar may sit in memory before it is written.
pub const DEFAULT_FLUSH_INTERVAL: Duration = Duration::from_secs(10);
/// Buffered bytes that trigger a write regardless of time.
const MAX_BUFFERED_BYTES: usize = 64 * 1024;

// ---------------------------------------------------------------------------------------------
// Messages (tensorflow/core/util/event.proto, tensorflow/core/framework/summary.proto), the
// fields a scalar needs, with TensorFlow's field numbers.
// ---------------------------------------------------------------------------------------------

/// `tensorflow.Event`: one record of an event file.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Event {
    /// Seconds since the Unix epoch.
    #[prost(double, tag = "1")]
    pub wall_time: f64,
    /// Global step of the event.
    #[prost(int64, tag = "2")]
    pub step: i64,
    /// Set on the first event of a file only (`oneof what`).
    #[prost(string, optional, tag = "3")]
    pub file_version: Option<String>,
    /// The values logged (`oneof what`).
    #[prost(message, optional, tag = "5")]
    pub summary: Option<Summary>,
}

/// `tensorflow.Summary`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Summary {
    /// The values.
    #[prost(message, repeated, tag = "1")]
    pub value: Vec<SummaryValue>,
}

/// `tensorflow.Summary.Value`, scalar case.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryValue {
    /// Metric name, e.g. `losses/critic`.
    #[prost(string, tag = "1")]
    pub tag: String,
    /// The scalar (`oneof value`: presence matters, so a 0.0 is still written).
    #[prost(float, optional, tag = "2")]
    pub simple_value: Option<f32>,
}

/// One scalar read back from an event file.
#[derive(Clone, Debug, PartialEq)]
pub struct Scalar {
    /// Metric name.
    pub tag: String,
    /// Global step.
    pub step: i64,
    /// The value.
    pub value: f32,
    /// Seconds since the Unix epoch.
    pub wall_time: f64,
}

// ---------------------------------------------------------------------------------------------
// CRC-32C and TFRecord framing
// ---------------------------------------------------------------------------------------------

/// CRC-32C (Castagnoli), as TFRecord uses (the `crc32c` crate; hardware-accelerated where
/// the CPU has it).
pub use crc32c::crc32c;

/// The masked CRC-32C TFRecord stores (masking keeps CRCs of CRC-bearing data well spread).
pub fn masked_crc32c(data: &[u8]) -> u32 {
    crc32c(data).rotate_right(15).wrapping_add(0xa282_ead8)
}

/// Appends one TFRecord holding `data` to `out`.
pub fn frame_record(data: &[u8], out: &mut Vec<u8>) {
    let len = (data.len() as u64).to_le_bytes();
    out.extend_from_slice(&len);
    out.extend_from_slice(&masked_crc32c(&len).to_le_bytes());
    out.extend_from_slice(data);
    out.extend_from_slice(&masked_crc32c(data).to_le_bytes());
}

// ---------------------------------------------------------------------------------------------
// Writer
// ---------------------------------------------------------------------------------------------

fn io_error(path: &Path, error: std::io::Error) -> LearnerError {
    LearnerError::FileIo { path: path.to_owned(), error }
}

fn now_secs() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// This machine's name for the file name: `/proc/sys/kernel/hostname`, else `$HOSTNAME`,
/// else `localhost`; characters other than `[A-Za-z0-9._-]` become `_`.
fn host_name() -> String {
    let raw = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_owned())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "localhost".to_owned());
    raw.chars().map(|c| if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') { c } else { '_' }).collect()
}

/// Writes scalars to a new TensorBoard event file.
///
/// Records are buffered in memory and written by the first `add_scalar` that finds
/// [`DEFAULT_FLUSH_INTERVAL`] (or the interval set) passed since the last write or 64 KiB
/// buffered, by [`SummaryWriter::flush`], and on drop. No background thread: a writer that
/// stops adding keeps its tail in memory until it is flushed or dropped. Not thread-safe by itself: one writer per thread, or
/// behind a mutex.
pub struct SummaryWriter {
    path: PathBuf,
    file: File,
    buffer: Vec<u8>,
    last_flush: Instant,
    flush_interval: Duration,
}

impl std::fmt::Debug for SummaryWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SummaryWriter").field("path", &self.path).field("buffered_bytes", &self.buffer.len()).finish()
    }
}

impl SummaryWriter {
    /// Creates `log_dir` (and parents) if needed and a new event file in it, named
    /// `events.out.tfevents.<unix secs>.<host>` (with `.1`, `.2`, ... appended when another
    /// writer took that name in the same second), and writes the `file_version` record.
    pub fn create(log_dir: &Path) -> Result<Self, LearnerError> {
        std::fs::create_dir_all(log_dir).map_err(|e| io_error(log_dir, e))?;
        let wall_time = now_secs();
        let base = format!("events.out.tfevents.{:010}.{}", wall_time as u64, host_name());
        let mut attempt = 0u32;
        let (path, file) = loop {
            let name = if attempt == 0 { base.clone() } else { format!("{base}.{attempt}") };
            let path = log_dir.join(name);
            match OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(file) => break (path, file),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && attempt < 1000 => {
                    attempt += 1;
                }
                Err(e) => return Err(io_error(&path, e)),
            }
        };
        let mut writer = Self { path, file, buffer: Vec::with_capacity(MAX_BUFFERED_BYTES), last_flush: Instant::now(), flush_interval: DEFAULT_FLUSH_INTERVAL };
        writer.push(&Event { wall_time, step: 0, file_version: Some(FILE_VERSION.to_owned()), summary: None });
        writer.flush()?;
        Ok(writer)
    }

    /// Sets the longest time a scalar may stay buffered [default 10 s].
    pub fn with_flush_interval(mut self, interval: Duration) -> Self {
        self.flush_interval = interval;
        self
    }

    /// The event file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Logs `value` under `tag` (e.g. `losses/critic`) at `step`, stamped now.
    pub fn add_scalar(&mut self, tag: &str, step: i64, value: f32) -> Result<(), LearnerError> {
        self.add_scalar_at(tag, step, value, now_secs())
    }

    /// [`SummaryWriter::add_scalar`] with an explicit wall time (seconds since the epoch).
    pub fn add_scalar_at(&mut self, tag: &str, step: i64, value: f32, wall_time: f64) -> Result<(), LearnerError> {
        if tag.is_empty() {
            return Err(LearnerError::EventFile { path: self.path.clone(), reason: "a scalar needs a non-empty tag".into() });
        }
        self.push(&Event { wall_time, step, file_version: None, summary: Some(Summary { value: vec![SummaryValue { tag: tag.to_owned(), simple_value: Some(value) }] }) });
        if self.buffer.len() >= MAX_BUFFERED_BYTES || self.last_flush.elapsed() >= self.flush_interval {
            self.flush()?;
        }
        Ok(())
    }

    fn push(&mut self, event: &Event) {
        frame_record(&event.encode_to_vec(), &mut self.buffer);
    }

    /// Writes everything buffered to the file (no fsync: TensorBoard reads it as it grows).
    pub fn flush(&mut self) -> Result<(), LearnerError> {
        self.last_flush = Instant::now();
        if self.buffer.is_empty() {
            return Ok(());
        }
        let result = self.file.write_all(&self.buffer).and_then(|()| self.file.flush());
        // Dropped even on error: a record written halfway must not be written again, and a
        // full disk must not grow memory without bound. TensorBoard skips a torn tail.
        self.buffer.clear();
        result.map_err(|e| io_error(&self.path, e))
    }
}

impl Drop for SummaryWriter {
    fn drop(&mut self) {
        if let Err(e) = self.flush() {
            tracing::warn!(error = %e, "could not flush the TensorBoard event file");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Reader
// ---------------------------------------------------------------------------------------------

/// The data of every record of a TFRecord file, checking both CRCs of each. Errors name the
/// byte offset of the bad record.
pub fn read_records(path: &Path) -> Result<Vec<Vec<u8>>, LearnerError> {
    let bytes = std::fs::read(path).map_err(|e| io_error(path, e))?;
    let bad = |offset: usize, reason: String| LearnerError::EventFile { path: path.to_owned(), reason: format!("record at byte {offset}: {reason}") };
    let mut records = Vec::new();
    let mut at = 0usize;
    while at < bytes.len() {
        let header = bytes.get(at..at + 12).ok_or_else(|| bad(at, format!("truncated header ({} bytes left)", bytes.len() - at)))?;
        let (len_bytes, len_crc) = header.split_at(8);
        let stored = u32::from_le_bytes([len_crc[0], len_crc[1], len_crc[2], len_crc[3]]);
        if stored != masked_crc32c(len_bytes) {
            return Err(bad(at, "length CRC mismatch".into()));
        }
        let len = u64::from_le_bytes(len_bytes.try_into().unwrap_or([0xff; 8]));
        let start = at + 12;
        let end = usize::try_from(len)
            .ok()
            .and_then(|l| start.checked_add(l))
            .filter(|&e| e.checked_add(4).is_some_and(|e4| e4 <= bytes.len()))
            .ok_or_else(|| bad(at, format!("length {len} runs past the end of the file")))?;
        let data = &bytes[start..end];
        let crc = &bytes[end..end + 4];
        let stored = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
        if stored != masked_crc32c(data) {
            return Err(bad(at, "data CRC mismatch".into()));
        }
        records.push(data.to_vec());
        at = end + 4;
    }
    Ok(records)
}

/// Every event of an event file, in order (CRCs checked, see [`read_records`]).
pub fn read_events(path: &Path) -> Result<Vec<Event>, LearnerError> {
    read_records(path)?
        .iter()
        .enumerate()
        .map(|(i, data)| Event::decode(data.as_slice()).map_err(|e| LearnerError::EventFile { path: path.to_owned(), reason: format!("record {i} is not a tensorflow.Event: {e}") }))
        .collect()
}

/// Every scalar of an event file, in order.
pub fn read_scalars(path: &Path) -> Result<Vec<Scalar>, LearnerError> {
    Ok(read_events(path)?
        .into_iter()
        .flat_map(|event| {
            let (step, wall_time) = (event.step, event.wall_time);
            event.summary.into_iter().flat_map(move |summary| summary.value.into_iter().filter_map(move |v| v.simple_value.map(|value| Scalar { tag: v.tag, step, value, wall_time })))
        })
        .collect())
}
