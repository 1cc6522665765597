//! Policy weights as `.safetensors` files: the codec between a [`WeightsSnapshot`] and the
//! bytes of a file, written with the workspace's one atomic write
//! ([`crate::atomic_file`]). Pure Rust, so that actors,
//! `mapless eval` and deployments read policies without libtorch.
//!
//! # The `.safetensors` layout of a snapshot
//!
//! Tensor name → dtype, shape, little-endian row-major data, exactly as in the snapshot. The
//! header's `__metadata__` holds the snapshot's free-form `metadata` map plus these reserved
//! keys (every key starting with `mapless.` is reserved; a snapshot whose own metadata uses
//! the prefix is refused):
//!
//! | key | value |
//! |---|---|
//! | `mapless.version` | the weights version, decimal |
//! | `mapless.algorithm` | `ddpg`, `td3` or `sac` |
//! | `mapless.obs_dim`, `mapless.act_dim` | decimal |
//! | `mapless.created_unix_ms` | decimal |
//! | `mapless.tensor_order` | JSON array of the tensor names in snapshot order (safetensors sorts them) |
//! | `mapless.data_crc32` | CRC-32 (IEEE) of the tensors' data concatenated in that order, 8 hex digits |
//!
//! safetensors itself checks the header and the offsets; the CRC catches flipped bits in the
//! data, which the format alone would load silently.

use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};

use crate::atomic_file::{AtomicWriteError, write_file_atomically};
use crate::v1::{Algorithm, Dtype, NamedTensor, ProtocolVersion, WeightsSnapshot};

/// Prefix of the `__metadata__` keys this module writes itself.
pub const RESERVED_METADATA_PREFIX: &str = "mapless.";
/// `__metadata__` key: the weights version.
pub const META_VERSION: &str = "mapless.version";
/// `__metadata__` key: `ddpg`, `td3` or `sac`.
pub const META_ALGORITHM: &str = "mapless.algorithm";
/// `__metadata__` key: observation length.
pub const META_OBS_DIM: &str = "mapless.obs_dim";
/// `__metadata__` key: action length.
pub const META_ACT_DIM: &str = "mapless.act_dim";
/// `__metadata__` key: publication time.
pub const META_CREATED_UNIX_MS: &str = "mapless.created_unix_ms";
/// `__metadata__` key: tensor names in snapshot order, a JSON array.
pub const META_TENSOR_ORDER: &str = "mapless.tensor_order";
/// `__metadata__` key: CRC-32 of the tensor data, 8 lowercase hex digits.
pub const META_DATA_CRC32: &str = "mapless.data_crc32";

/// What reading or writing a weights file can fail with.
#[derive(Debug, thiserror::Error)]
pub enum WeightsFileError {
    /// Bytes that are not a valid mapless weights file, or a snapshot that cannot be written
    /// as one; `origin` names the file or snapshot.
    #[error("invalid weights ({origin}): {reason}")]
    Invalid { origin: String, reason: String },
    /// The file system refused.
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
}

/// A failed atomic write as the file system's refusal: the path the failed step acted on and
/// what the OS said.
impl From<AtomicWriteError> for WeightsFileError {
    fn from(e: AtomicWriteError) -> Self {
        WeightsFileError::Io { path: e.path, error: e.error }
    }
}

fn invalid(origin: impl Into<String>, reason: impl Into<String>) -> WeightsFileError {
    WeightsFileError::Invalid { origin: origin.into(), reason: reason.into() }
}

fn algorithm_name(algorithm: i32) -> Option<&'static str> {
    match Algorithm::try_from(algorithm).ok()? {
        Algorithm::Ddpg => Some("ddpg"),
        Algorithm::Td3 => Some("td3"),
        Algorithm::Sac => Some("sac"),
        Algorithm::Unspecified => None,
    }
}

fn algorithm_from_name(name: &str) -> Option<Algorithm> {
    match name.to_ascii_lowercase().as_str() {
        "ddpg" | "algorithm_ddpg" => Some(Algorithm::Ddpg),
        "td3" | "algorithm_td3" => Some(Algorithm::Td3),
        "sac" | "algorithm_sac" => Some(Algorithm::Sac),
        _ => None,
    }
}

fn to_st_dtype(dtype: Dtype) -> Option<safetensors::Dtype> {
    match dtype {
        Dtype::F32 => Some(safetensors::Dtype::F32),
        Dtype::F64 => Some(safetensors::Dtype::F64),
        Dtype::F16 => Some(safetensors::Dtype::F16),
        Dtype::Bf16 => Some(safetensors::Dtype::BF16),
        Dtype::Unspecified => None,
    }
}

fn from_st_dtype(dtype: safetensors::Dtype) -> Option<Dtype> {
    match dtype {
        safetensors::Dtype::F32 => Some(Dtype::F32),
        safetensors::Dtype::F64 => Some(Dtype::F64),
        safetensors::Dtype::F16 => Some(Dtype::F16),
        safetensors::Dtype::BF16 => Some(Dtype::Bf16),
        _ => None,
    }
}

fn data_crc32<'a>(data: impl IntoIterator<Item = &'a [u8]>) -> String {
    let mut hasher = crc32fast::Hasher::new();
    for chunk in data {
        hasher.update(chunk);
    }
    format!("{:08x}", hasher.finalize())
}

/// Encodes a snapshot as the bytes of a `.safetensors` file (layout in the module doc).
///
/// Validates the snapshot first ([`WeightsSnapshot::validate`]) and refuses metadata keys
/// with the reserved `mapless.` prefix.
pub fn snapshot_to_safetensors(snapshot: &WeightsSnapshot) -> Result<Vec<u8>, WeightsFileError> {
    let origin = || format!("snapshot version {}", snapshot.version);
    snapshot.validate().map_err(|e| invalid(origin(), e.to_string()))?;
    if let Some(key) = snapshot.metadata.keys().find(|k| k.starts_with(RESERVED_METADATA_PREFIX)) {
        return Err(invalid(origin(), format!("metadata key `{key}` uses the reserved prefix `{RESERVED_METADATA_PREFIX}`")));
    }
    let algorithm = algorithm_name(snapshot.algorithm).ok_or_else(|| invalid(origin(), format!("unknown algorithm {}", snapshot.algorithm)))?;

    let mut views = Vec::with_capacity(snapshot.tensors.len());
    for tensor in &snapshot.tensors {
        // validate() above guarantees a known dtype and a consistent byte length.
        let dtype = Dtype::try_from(tensor.dtype).ok().and_then(to_st_dtype).ok_or_else(|| invalid(origin(), format!("tensor `{}`: unknown dtype", tensor.name)))?;
        let shape = tensor.shape.iter().map(|&d| usize::try_from(d)).collect::<Result<Vec<usize>, _>>().map_err(|_| invalid(origin(), format!("tensor `{}`: dimension exceeds usize", tensor.name)))?;
        let view = safetensors::tensor::TensorView::new(dtype, shape, &tensor.data).map_err(|e| invalid(origin(), format!("tensor `{}`: {e}", tensor.name)))?;
        views.push((tensor.name.as_str(), view));
    }

    let order: Vec<&str> = snapshot.tensors.iter().map(|t| t.name.as_str()).collect();
    let mut metadata: HashMap<String, String> = snapshot.metadata.clone().into_iter().collect();
    metadata.insert(META_VERSION.into(), snapshot.version.to_string());
    metadata.insert(META_ALGORITHM.into(), algorithm.into());
    metadata.insert(META_OBS_DIM.into(), snapshot.obs_dim.to_string());
    metadata.insert(META_ACT_DIM.into(), snapshot.act_dim.to_string());
    metadata.insert(META_CREATED_UNIX_MS.into(), snapshot.created_unix_ms.to_string());
    metadata.insert(META_TENSOR_ORDER.into(), serde_json::to_string(&order).map_err(|e| invalid(origin(), e.to_string()))?);
    metadata.insert(META_DATA_CRC32.into(), data_crc32(snapshot.tensors.iter().map(|t| t.data.as_slice())));
    safetensors::serialize(views, Some(metadata)).map_err(|e| invalid(origin(), format!("safetensors: {e}")))
}

fn required<'a>(metadata: &'a HashMap<String, String>, key: &str, origin: &dyn Fn() -> String) -> Result<&'a str, WeightsFileError> {
    metadata.get(key).map(String::as_str).ok_or_else(|| invalid(origin(), format!("`__metadata__` has no `{key}`; not a mapless weights file")))
}

fn parse_number<T: std::str::FromStr>(metadata: &HashMap<String, String>, key: &str, origin: &dyn Fn() -> String) -> Result<T, WeightsFileError> {
    let text = required(metadata, key, origin)?;
    text.parse().map_err(|_| invalid(origin(), format!("`__metadata__.{key}` is `{text}`, not a number")))
}

/// Decodes the bytes of a `.safetensors` file written by [`snapshot_to_safetensors`]. `origin`
/// names the bytes in errors (a path, a URL).
///
/// Every problem is an [`WeightsFileError::Invalid`] naming it: a malformed or truncated
/// header, offsets that do not cover the data, a missing reserved key, a dtype the contract
/// does not carry, a data checksum mismatch, or a snapshot that then fails
/// [`WeightsSnapshot::validate`].
pub fn snapshot_from_safetensors(bytes: &[u8], origin: &str) -> Result<WeightsSnapshot, WeightsFileError> {
    let origin_fn = || origin.to_owned();
    let origin_ref: &dyn Fn() -> String = &origin_fn;
    let not_safetensors = |e: safetensors::SafeTensorError| invalid(origin, format!("not a valid .safetensors file: {e}"));
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes).map_err(not_safetensors)?;
    let file = safetensors::SafeTensors::deserialize(bytes).map_err(not_safetensors)?;
    let mut metadata = header.metadata().clone().unwrap_or_default();

    let version: u64 = parse_number(&metadata, META_VERSION, origin_ref)?;
    let algorithm_text = required(&metadata, META_ALGORITHM, origin_ref)?;
    let algorithm = algorithm_from_name(algorithm_text).ok_or_else(|| invalid(origin, format!("`__metadata__.{META_ALGORITHM}` is `{algorithm_text}`; expected ddpg, td3 or sac")))?;
    let obs_dim: u32 = parse_number(&metadata, META_OBS_DIM, origin_ref)?;
    let act_dim: u32 = parse_number(&metadata, META_ACT_DIM, origin_ref)?;
    let created_unix_ms: u64 = parse_number(&metadata, META_CREATED_UNIX_MS, origin_ref)?;
    let order: Vec<String> = match metadata.get(META_TENSOR_ORDER) {
        Some(text) => serde_json::from_str(text).map_err(|e| invalid(origin, format!("`__metadata__.{META_TENSOR_ORDER}` is not a JSON list of names: {e}")))?,
        // Written by another tool: file (offset) order.
        None => header.offset_keys(),
    };
    if order.len() != file.len() {
        return Err(invalid(origin, format!("`__metadata__.{META_TENSOR_ORDER}` names {} tensors, the file holds {}", order.len(), file.len())));
    }

    let mut tensors = Vec::with_capacity(order.len());
    for name in order {
        let view = file.tensor(&name).map_err(|e| invalid(origin, e.to_string()))?;
        let dtype = from_st_dtype(view.dtype()).ok_or_else(|| invalid(origin, format!("tensor `{name}` has dtype {}; weights carry F32, F64, F16 or BF16", view.dtype())))?;
        tensors.push(NamedTensor { name, shape: view.shape().iter().map(|&d| d as u64).collect(), dtype: dtype as i32, data: view.data().to_vec() });
    }
    if let Some(expected) = metadata.get(META_DATA_CRC32) {
        let actual = data_crc32(tensors.iter().map(|t| t.data.as_slice()));
        if !expected.eq_ignore_ascii_case(&actual) {
            return Err(invalid(origin, format!("tensor data checksum is {actual}, the header says {expected}: the file is corrupt")));
        }
    }
    metadata.retain(|k, _| !k.starts_with(RESERVED_METADATA_PREFIX));
    let snapshot =
        WeightsSnapshot { protocol_version: ProtocolVersion::V1 as i32, version, algorithm: algorithm as i32, created_unix_ms, obs_dim, act_dim, tensors, metadata: metadata.into_iter().collect() };
    snapshot.validate().map_err(|e| invalid(origin, e.to_string()))?;
    Ok(snapshot)
}

fn io_error(path: &Path, error: std::io::Error) -> WeightsFileError {
    WeightsFileError::Io { path: path.to_owned(), error }
}

/// [`snapshot_to_safetensors`], written atomically and durably to `path`
/// ([`write_file_atomically`]).
pub fn write_safetensors_file(path: &Path, snapshot: &WeightsSnapshot) -> Result<(), WeightsFileError> {
    let bytes = snapshot_to_safetensors(snapshot)?;
    Ok(write_file_atomically(path, &bytes)?)
}

/// Reads a `.safetensors` file written by [`write_safetensors_file`].
pub fn read_safetensors_file(path: &Path) -> Result<WeightsSnapshot, WeightsFileError> {
    let bytes = fs::read(path).map_err(|e| io_error(path, e))?;
    snapshot_from_safetensors(&bytes, &path.display().to_string())
}
