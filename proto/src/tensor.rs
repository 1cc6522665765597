//! Safetensors-compatible tensors and weight snapshots.

use std::collections::HashSet;

use crate::check_protocol_version;
use crate::error::ProtoError;
use crate::v1::{Algorithm, Dtype, NamedTensor, WeightsSnapshot};

impl Dtype {
    /// Bytes per element; `None` for [`Dtype::Unspecified`].
    pub fn size_bytes(self) -> Option<usize> {
        match self {
            Self::Unspecified => None,
            Self::F32 => Some(4),
            Self::F64 => Some(8),
            Self::F16 | Self::Bf16 => Some(2),
        }
    }

    /// The dtype string a `.safetensors` header uses ("F32", "BF16", ...); `None` for
    /// [`Dtype::Unspecified`].
    pub fn safetensors_name(self) -> Option<&'static str> {
        match self {
            Self::Unspecified => None,
            Self::F32 => Some("F32"),
            Self::F64 => Some("F64"),
            Self::F16 => Some("F16"),
            Self::Bf16 => Some("BF16"),
        }
    }

    /// Inverse of [`Dtype::safetensors_name`]; `None` for dtypes this contract does not carry.
    pub fn from_safetensors_name(name: &str) -> Option<Self> {
        match name {
            "F32" => Some(Self::F32),
            "F64" => Some(Self::F64),
            "F16" => Some(Self::F16),
            "BF16" => Some(Self::Bf16),
            _ => None,
        }
    }
}

impl NamedTensor {
    /// An F32 tensor from row-major values. Fails when `values.len()` is not the product of
    /// `shape` (an empty shape is a scalar: one value).
    pub fn from_f32(name: impl Into<String>, shape: Vec<u64>, values: &[f32]) -> Result<Self, ProtoError> {
        let name = name.into();
        let elements = element_count(&name, &shape)?;
        if elements != values.len() as u64 {
            return Err(ProtoError::InvalidTensor { name, reason: format!("shape {shape:?} holds {elements} values, got {}", values.len()) });
        }
        let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        Ok(Self { name, shape, dtype: Dtype::F32 as i32, data })
    }

    /// Number of elements, product(shape); an error if that overflows `u64`.
    pub fn element_count(&self) -> Result<u64, ProtoError> {
        element_count(&self.name, &self.shape)
    }

    /// Checks a received tensor: non-empty name, known dtype, and exactly
    /// `product(shape) * size_of(dtype)` bytes of data.
    pub fn validate(&self) -> Result<(), ProtoError> {
        if self.name.is_empty() {
            return Err(ProtoError::InvalidTensor { name: String::new(), reason: "name is empty".to_owned() });
        }
        let dtype = Dtype::try_from(self.dtype).ok();
        let Some(size) = dtype.and_then(Dtype::size_bytes) else {
            return Err(self.invalid(format!("unknown or unset dtype {}", self.dtype)));
        };
        let expected = self.element_count()?.checked_mul(size as u64).ok_or_else(|| self.invalid(format!("shape {:?} overflows u64 bytes", self.shape)))?;
        if expected != self.data.len() as u64 {
            return Err(self.invalid(format!("shape {:?} of {} needs {expected} bytes, data has {}", self.shape, dtype.and_then(Dtype::safetensors_name).unwrap_or("?"), self.data.len())));
        }
        Ok(())
    }

    /// The elements as `f32`, after [`NamedTensor::validate`]. Only F32 tensors are read:
    /// the learner publishes F32, and converting other dtypes belongs where they are produced.
    pub fn to_f32_vec(&self) -> Result<Vec<f32>, ProtoError> {
        self.validate()?;
        if self.dtype != Dtype::F32 as i32 {
            let got = Dtype::try_from(self.dtype).ok().and_then(Dtype::safetensors_name).unwrap_or("?");
            return Err(self.invalid(format!("dtype is {got}, only F32 can be read as f32")));
        }
        Ok(self.data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
    }

    fn invalid(&self, reason: String) -> ProtoError {
        ProtoError::InvalidTensor { name: self.name.clone(), reason }
    }
}

fn element_count(name: &str, shape: &[u64]) -> Result<u64, ProtoError> {
    shape.iter().try_fold(1u64, |acc, &d| acc.checked_mul(d)).ok_or_else(|| ProtoError::InvalidTensor { name: name.to_owned(), reason: format!("shape {shape:?} has more than u64::MAX elements") })
}

impl WeightsSnapshot {
    /// Checks a received snapshot before an actor loads it: protocol version, version >= 1,
    /// a known algorithm, dims > 0, unique tensor names, and every tensor valid.
    pub fn validate(&self) -> Result<(), ProtoError> {
        check_protocol_version(self.protocol_version)?;
        if self.version == 0 {
            return Err(ProtoError::InvalidField { field: "version", reason: "is 0; published versions start at 1".to_owned() });
        }
        match Algorithm::try_from(self.algorithm) {
            Ok(Algorithm::Ddpg | Algorithm::Td3 | Algorithm::Sac) => {}
            Ok(Algorithm::Unspecified) | Err(_) => {
                return Err(ProtoError::InvalidField { field: "algorithm", reason: format!("is {}, not a known algorithm", self.algorithm) });
            }
        }
        for (field, dim) in [("obs_dim", self.obs_dim), ("act_dim", self.act_dim)] {
            if dim == 0 {
                return Err(ProtoError::InvalidField { field, reason: "is 0".to_owned() });
            }
        }
        let mut names = HashSet::with_capacity(self.tensors.len());
        for tensor in &self.tensors {
            tensor.validate()?;
            if !names.insert(tensor.name.as_str()) {
                return Err(tensor.invalid("name occurs more than once".to_owned()));
            }
        }
        Ok(())
    }

    /// The tensor called `name`, if any. O(number of tensors).
    pub fn tensor(&self, name: &str) -> Option<&NamedTensor> {
        self.tensors.iter().find(|t| t.name == name)
    }
}
