//! The two encodings of a batch's float columns (transition.proto, "Two encodings"): packed
//! `repeated float` fields and their `bytes *_f32le` twins (little-endian binary32).
//!
//! ```text
//!  obs        = 7  [packed float]   tag 7  | len | f32le f32le f32le ...   decoded value by value
//!  obs_f32le  = 16 [bytes]          tag 16 | len | f32le f32le f32le ...   one memcpy, or none
//! ```
//!
//! [`FloatColumn`] is a borrowed view of one column in whichever encoding carries it; the
//! batch messages hand them out (`TransitionBatch::obs_column`, ...), so readers never care
//! which encoding arrived. Copies into `f32` storage are one `memcpy` on little-endian
//! machines (a byte-by-byte conversion elsewhere); nothing here panics on malformed input.

use std::borrow::Cow;

use prost::bytes::Bytes;

/// Which encoding a batch message uses (or should use) for its float columns.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum FloatEncoding {
    /// The `repeated float` fields (packed). The default, readable by every client.
    #[default]
    Packed,
    /// The `bytes *_f32le` fields: IEEE-754 binary32, little-endian, 4 bytes a value.
    F32Le,
}

/// One float column of a batch message, borrowed, in the encoding it travelled in.
///
/// Lengths and indices count floats, not bytes. A `F32Le` column whose byte length is not a
/// multiple of 4 is malformed (`validate` rejects it); its trailing bytes are ignored here.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FloatColumn<'a> {
    /// From a `repeated float` field.
    Packed(&'a [f32]),
    /// From a `bytes *_f32le` field: 4 little-endian bytes per float.
    F32Le(&'a [u8]),
}

const F32_BYTES: usize = 4;

impl<'a> FloatColumn<'a> {
    /// The column a message carries in `packed` or `le`: the bytes when they are set, else
    /// the packed floats.
    pub(crate) fn of(packed: &'a [f32], le: &'a [u8]) -> FloatColumn<'a> {
        if le.is_empty() { FloatColumn::Packed(packed) } else { FloatColumn::F32Le(le) }
    }

    /// Number of floats.
    pub fn len(&self) -> usize {
        match self {
            FloatColumn::Packed(v) => v.len(),
            FloatColumn::F32Le(b) => b.len() / F32_BYTES,
        }
    }

    /// No floats.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The encoding it travelled in.
    pub fn encoding(&self) -> FloatEncoding {
        match self {
            FloatColumn::Packed(_) => FloatEncoding::Packed,
            FloatColumn::F32Le(_) => FloatEncoding::F32Le,
        }
    }

    /// Float `i`, or `None` past the end.
    pub fn get(&self, i: usize) -> Option<f32> {
        match self {
            FloatColumn::Packed(v) => v.get(i).copied(),
            FloatColumn::F32Le(b) => {
                let start = i.checked_mul(F32_BYTES)?;
                let c = b.get(start..start.checked_add(F32_BYTES)?)?;
                Some(f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            }
        }
    }

    /// Floats `start..end`, or `None` when that range is not inside the column.
    pub fn slice(&self, start: usize, end: usize) -> Option<FloatColumn<'a>> {
        if start > end || end > self.len() {
            return None;
        }
        Some(match *self {
            FloatColumn::Packed(v) => FloatColumn::Packed(&v[start..end]),
            FloatColumn::F32Le(b) => FloatColumn::F32Le(&b[start * F32_BYTES..end * F32_BYTES]),
        })
    }

    /// Copies the column into `dst` (one `memcpy` on little-endian machines) and returns
    /// true, when `dst` has exactly [`FloatColumn::len`] elements and the column is well
    /// formed; otherwise returns false and leaves `dst` untouched.
    pub fn copy_to_slice(&self, dst: &mut [f32]) -> bool {
        match self {
            FloatColumn::Packed(v) if v.len() == dst.len() => dst.copy_from_slice(v),
            FloatColumn::F32Le(b) if b.len() == dst.len() * F32_BYTES => le_bytes_to_f32s(b, dst),
            _ => return false,
        }
        true
    }

    /// Appends the column's floats to `out`.
    pub fn extend_vec(&self, out: &mut Vec<f32>) {
        match self {
            FloatColumn::Packed(v) => out.extend_from_slice(v),
            FloatColumn::F32Le(b) => {
                let n = b.len() / F32_BYTES;
                let start = out.len();
                out.resize(start + n, 0.0);
                le_bytes_to_f32s(&b[..n * F32_BYTES], &mut out[start..]);
            }
        }
    }

    /// The floats as a new vector.
    pub fn to_vec(&self) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.len());
        self.extend_vec(&mut out);
        out
    }

    /// The floats as a slice: borrowed for packed columns, and for little-endian bytes that
    /// happen to be 4-byte aligned on a little-endian machine; copied otherwise (received
    /// bytes usually sit at an arbitrary offset of the message buffer).
    pub fn to_cow(&self) -> Cow<'a, [f32]> {
        match *self {
            FloatColumn::Packed(v) => Cow::Borrowed(v),
            FloatColumn::F32Le(b) if cfg!(target_endian = "little") && b.len() % F32_BYTES == 0 => match bytemuck::try_cast_slice::<u8, f32>(b) {
                Ok(v) => Cow::Borrowed(v),
                Err(_) => Cow::Owned(self.to_vec()),
            },
            FloatColumn::F32Le(_) => Cow::Owned(self.to_vec()),
        }
    }

    /// Index and value of the first NaN or infinity, if any. Scans blocks branch-free (so the
    /// compiler vectorises it) and looks for the position only in a block that has one.
    pub(crate) fn first_non_finite(&self) -> Option<(usize, f32)> {
        const BLOCK: usize = 64;
        match self {
            FloatColumn::Packed(v) => {
                for (b, chunk) in v.chunks(BLOCK).enumerate() {
                    if chunk.iter().fold(false, |bad, x| bad | !x.is_finite()) {
                        let i = chunk.iter().position(|x| !x.is_finite())?;
                        return Some((b * BLOCK + i, chunk[i]));
                    }
                }
                None
            }
            FloatColumn::F32Le(bytes) => {
                // An unaligned little-endian load per float; tested as a float (not as exponent
                // bits, which the compiler narrows to 16-bit lanes and shuffles).
                let value = |c: &[u8]| f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
                for (b, chunk) in bytes.chunks(BLOCK * F32_BYTES).enumerate() {
                    if chunk.chunks_exact(F32_BYTES).fold(false, |bad, c| bad | !value(c).is_finite()) {
                        let i = chunk.chunks_exact(F32_BYTES).position(|c| !value(c).is_finite())?;
                        return Some((b * BLOCK + i, value(&chunk[i * F32_BYTES..])));
                    }
                }
                None
            }
        }
    }
}

/// Converts little-endian binary32 bytes into floats; `bytes.len()` must be `4 * dst.len()`
/// (callers check), else only the common prefix is converted.
fn le_bytes_to_f32s(bytes: &[u8], dst: &mut [f32]) {
    if cfg!(target_endian = "little") && bytes.len() == dst.len() * F32_BYTES {
        // Any bit pattern is a valid f32, and u8 has no alignment: a plain memcpy.
        bytemuck::cast_slice_mut::<f32, u8>(dst).copy_from_slice(bytes);
    } else {
        for (d, c) in dst.iter_mut().zip(bytes.chunks_exact(F32_BYTES)) {
            *d = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
    }
}

/// Appends `values` to `out` as little-endian binary32 bytes (one `memcpy` on little-endian
/// machines): the content of a `bytes *_f32le` field.
pub fn extend_f32le(out: &mut Vec<u8>, values: &[f32]) {
    if cfg!(target_endian = "little") {
        out.extend_from_slice(bytemuck::cast_slice::<f32, u8>(values));
    } else {
        out.reserve(values.len() * F32_BYTES);
        for v in values {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
}

/// `values` as the content of a `bytes *_f32le` field.
pub fn f32le_bytes(values: &[f32]) -> Bytes {
    let mut out = Vec::with_capacity(values.len() * F32_BYTES);
    extend_f32le(&mut out, values);
    Bytes::from(out)
}

/// Appends a length-delimited field (`tag`, length, `payload`) in protobuf wire format.
pub(crate) fn put_length_delimited(out: &mut Vec<u8>, tag: u32, payload_len: usize) {
    put_varint(out, (u64::from(tag) << 3) | 2);
    put_varint(out, payload_len as u64);
}

/// Bytes of a length-delimited field's key and length prefix.
pub(crate) fn length_delimited_overhead(tag: u32, payload_len: usize) -> usize {
    varint_len((u64::from(tag) << 3) | 2) + varint_len(payload_len as u64)
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn varint_len(v: u64) -> usize {
    // 1 byte per 7 significant bits, at least 1.
    (64 - (v | 1).leading_zeros() as usize).div_ceil(7)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_encodings_read_the_same_floats() {
        let values = [1.5f32, -0.0, 3.25e-7, f32::MAX, -2.0];
        let bytes = f32le_bytes(&values);
        let packed = FloatColumn::Packed(&values);
        let le = FloatColumn::F32Le(&bytes);
        assert_eq!(le.len(), 5);
        assert_eq!(le.to_vec(), values.to_vec());
        assert_eq!(le.to_cow().as_ref(), &values[..]);
        for i in 0..6 {
            assert_eq!(packed.get(i), le.get(i));
        }
        let mut dst = [0.0f32; 5];
        assert!(le.copy_to_slice(&mut dst));
        assert_eq!(dst, values);
        assert!(!le.copy_to_slice(&mut [0.0; 4]), "a wrong length copies nothing");
        assert_eq!(le.slice(1, 3).map(|c| c.to_vec()), Some(vec![-0.0, 3.25e-7]));
        assert_eq!(le.slice(4, 6), None);
        assert_eq!(FloatColumn::F32Le(&bytes[..7]).len(), 1, "trailing bytes are not a float");
    }

    #[test]
    fn first_non_finite_finds_nan_and_infinity_in_either_encoding() {
        for (at, bad) in [(0usize, f32::NAN), (63, f32::INFINITY), (64, f32::NEG_INFINITY), (199, f32::NAN)] {
            let mut v = vec![0.5f32; 200];
            v[at] = bad;
            let bytes = f32le_bytes(&v);
            for col in [FloatColumn::Packed(&v), FloatColumn::F32Le(&bytes)] {
                let (i, x) = col.first_non_finite().expect("found");
                assert_eq!(i, at);
                assert_eq!(x.to_bits(), bad.to_bits());
            }
        }
        let fine = vec![f32::MAX; 130];
        assert_eq!(FloatColumn::F32Le(&f32le_bytes(&fine)).first_non_finite(), None);
    }

    #[test]
    fn varints_have_the_protobuf_length() {
        for v in [0u64, 1, 127, 128, 16_383, 16_384, u64::from(u32::MAX), u64::MAX] {
            let mut out = Vec::new();
            put_varint(&mut out, v);
            assert_eq!(out.len(), varint_len(v), "{v}");
            assert_eq!(prost::decode_length_delimiter(&out[..]).ok().map(|x| x as u64).unwrap_or(v), v);
        }
    }
}
