//! `EXT_meshopt_compression`: buffer views stored compressed by meshoptimizer (what `gltfpack
//! -c` writes), decoded into the buffers they view before anything else reads them.
//!
//! A compressed view names its compressed bytes in the extension (a range of another buffer)
//! and keeps its own place in its buffer, which is often a fallback buffer with no data at all
//! (`{"byteLength": N, "extensions": {"EXT_meshopt_compression": {"fallback": true}}}`): that
//! buffer starts as zeros and each view's decoded bytes are written at its place. The decoders
//! are meshoptimizer's own (the `meshopt` crate), safe on untrusted input; the ranges are checked
//! here first.

use gltf::json::Root;
use serde_json::Value;

use super::LoadError;

/// The extension's name.
pub const EXTENSION: &str = "EXT_meshopt_compression";

/// Most bytes a view may decode to per compressed byte (plus [`SLACK`]): far above what real
/// geometry reaches (gltfpack's output decodes to 2–8 times its size), and a bound on what a
/// hostile file's few bytes can make the loader allocate.
const MAX_RATIO: usize = 128;
/// Bytes a view may decode to beyond [`MAX_RATIO`] times its compressed bytes.
const SLACK: usize = 1 << 16;

/// How a view's bytes were encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Mode {
    /// Vertex attributes, `stride` bytes each.
    Attributes,
    /// Triangle indices.
    Triangles,
    /// Other indices.
    Indices,
}

/// What undoes the attribute filter applied before encoding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Filter {
    None,
    Octahedral,
    Quaternion,
    Exponential,
}

/// One compressed buffer view.
#[derive(Clone, Debug, PartialEq)]
struct View {
    /// The view's index, for messages.
    index: usize,
    /// Where the decoded bytes go: the view's buffer and offset in it.
    target: (usize, usize),
    /// Where the compressed bytes are: buffer, offset and length.
    source: (usize, usize, usize),
    /// Elements and their size in bytes.
    count: usize,
    stride: usize,
    mode: Mode,
    filter: Filter,
}

/// The compressed views of a file and the buffers that only hold their decoded bytes.
#[derive(Debug, Default)]
pub struct Plan {
    views: Vec<View>,
    fallback: Vec<usize>,
}

impl Plan {
    /// Reads the extension's objects from `root`, and takes it off the required extensions (it
    /// is supported here); an object that is not as the extension defines it is an error naming
    /// it.
    pub fn read(root: &mut Root) -> Result<Self, LoadError> {
        root.extensions_required.retain(|e| e != EXTENSION);
        let mut plan = Self::default();
        for (b, buffer) in root.buffers.iter().enumerate() {
            let ext = buffer
                .extensions
                .as_ref()
                .and_then(|e| e.others.get(EXTENSION));
            if ext.is_some_and(|e| e.get("fallback") == Some(&Value::Bool(true))) {
                plan.fallback.push(b);
            }
        }
        for (v, view) in root.buffer_views.iter().enumerate() {
            let Some(ext) = view
                .extensions
                .as_ref()
                .and_then(|e| e.others.get(EXTENSION))
            else {
                continue;
            };
            let what = || format!("bufferViews[{v}].extensions.{EXTENSION}");
            let field = |name: &str| -> Result<usize, LoadError> {
                ext.get(name)
                    .and_then(Value::as_u64)
                    .and_then(|n| usize::try_from(n).ok())
                    .ok_or_else(|| {
                        LoadError::malformed(what(), format!("{name} must be a whole number"))
                    })
            };
            let offset = match ext.get("byteOffset") {
                None => 0,
                Some(_) => field("byteOffset")?,
            };
            let word = |name: &str, default: &str| {
                ext.get(name)
                    .map_or(Some(default), Value::as_str)
                    .map(str::to_owned)
                    .ok_or_else(|| LoadError::malformed(what(), format!("{name} must be a string")))
            };
            let mode = match word("mode", "")?.as_str() {
                "ATTRIBUTES" => Mode::Attributes,
                "TRIANGLES" => Mode::Triangles,
                "INDICES" => Mode::Indices,
                other => {
                    return Err(LoadError::malformed(
                        what(),
                        format!("mode {other:?} is not ATTRIBUTES, TRIANGLES or INDICES"),
                    ));
                }
            };
            let filter = match word("filter", "NONE")?.as_str() {
                "NONE" => Filter::None,
                "OCTAHEDRAL" => Filter::Octahedral,
                "QUATERNION" => Filter::Quaternion,
                "EXPONENTIAL" => Filter::Exponential,
                other => {
                    return Err(LoadError::malformed(
                        what(),
                        format!(
                            "filter {other:?} is not NONE, OCTAHEDRAL, QUATERNION or EXPONENTIAL"
                        ),
                    ));
                }
            };
            let (count, stride) = (field("count")?, field("byteStride")?);
            let stride_ok = match (mode, filter) {
                (Mode::Attributes, Filter::None | Filter::Exponential) => {
                    stride % 4 == 0 && (4..=256).contains(&stride)
                }
                (Mode::Attributes, Filter::Octahedral) => stride == 4 || stride == 8,
                (Mode::Attributes, Filter::Quaternion) => stride == 8,
                (_, Filter::None) => stride == 2 || stride == 4,
                _ => false,
            };
            if !stride_ok {
                return Err(LoadError::malformed(
                    what(),
                    format!(
                        "byteStride {stride} does not fit mode {mode:?} with filter {filter:?}"
                    ),
                ));
            }
            let decoded = count
                .checked_mul(stride)
                .filter(|&n| n <= view.byte_length.0 as usize);
            if decoded.is_none() {
                return Err(LoadError::malformed(
                    what(),
                    format!(
                        "{count} elements of {stride} bytes do not fit the view's byteLength {}",
                        view.byte_length.0
                    ),
                ));
            }
            plan.views.push(View {
                index: v,
                target: (
                    view.buffer.value(),
                    view.byte_offset.map_or(0, |o| o.0 as usize),
                ),
                source: (field("buffer")?, offset, field("byteLength")?),
                count,
                stride,
                mode,
                filter,
            });
        }
        Ok(plan)
    }

    /// Whether buffer `b` only holds decoded views (it has no bytes of its own).
    #[must_use]
    pub fn is_fallback(&self, b: usize) -> bool {
        self.fallback.contains(&b)
    }

    /// Decodes every compressed view into its place in `buffers` (the fallback ones empty,
    /// made `lengths[b]` zeros here once every view's compressed bytes are known to be present
    /// and its decoded bytes within [`MAX_RATIO`] of them, so that a file cannot make the
    /// loader allocate far more than it holds).
    pub fn decode(&self, buffers: &mut [Vec<u8>], lengths: &[usize]) -> Result<(), LoadError> {
        let mut reach = vec![0usize; buffers.len()];
        for view in &self.views {
            let what = || format!("bufferViews[{}] ({EXTENSION})", view.index);
            let (b, offset, length) = view.source;
            let present = (buffers.get(b)).is_some_and(|data| {
                !self.is_fallback(b)
                    && offset
                        .checked_add(length)
                        .is_some_and(|end| end <= data.len())
            });
            let decoded = view.count * view.stride;
            if !present || decoded > length.saturating_mul(MAX_RATIO).saturating_add(SLACK) {
                return Err(LoadError::malformed(
                    what(),
                    format!(
                        "its {decoded} bytes do not come from {length} compressed bytes present \
                         in buffer {b} (at most {MAX_RATIO} times as many)"
                    ),
                ));
            }
            let (t, at) = view.target;
            if let Some(r) = reach.get_mut(t) {
                *r = (*r).max(at.saturating_add(decoded));
            }
        }
        for &b in &self.fallback {
            let length = lengths.get(b).copied().unwrap_or(0);
            if length > reach.get(b).copied().unwrap_or(0) {
                return Err(LoadError::malformed(
                    format!("buffer {b} ({EXTENSION} fallback)"),
                    format!("byteLength {length} is beyond the views decoded into it"),
                ));
            }
            if let Some(data) = buffers.get_mut(b) {
                *data = vec![0; length];
            }
        }
        for view in &self.views {
            let what = || format!("bufferViews[{}] ({EXTENSION})", view.index);
            let (b, offset, length) = view.source;
            let source = (buffers.get(b))
                .and_then(|data| data.get(offset..offset.checked_add(length)?))
                .ok_or_else(|| {
                    LoadError::malformed(
                        what(),
                        format!("its compressed bytes {offset}+{length} are not in buffer {b}"),
                    )
                })?;
            let bytes = decode_view(view, source)
                .map_err(|e| LoadError::malformed(what(), format!("cannot be decoded: {e}")))?;
            let (t, at) = view.target;
            let target = (buffers.get_mut(t))
                .and_then(|data| data.get_mut(at..at.checked_add(bytes.len())?))
                .ok_or_else(|| {
                    LoadError::malformed(what(), format!("its place is not in buffer {t}"))
                })?;
            target.copy_from_slice(&bytes);
        }
        Ok(())
    }
}

/// The decoded bytes of `view` from its compressed `source`.
fn decode_view(view: &View, source: &[u8]) -> Result<Vec<u8>, String> {
    let count = view.count;
    let fail = |e: meshopt::Error| e.to_string();
    let mut bytes = match (view.mode, view.stride) {
        (Mode::Attributes, stride) => vertices(source, count, stride)?,
        (Mode::Triangles, 2) => to_bytes(
            meshopt::decode_index_buffer::<u16>(source, count).map_err(fail)?,
            u16::to_le_bytes,
        ),
        (Mode::Triangles, _) => to_bytes(
            meshopt::decode_index_buffer::<u32>(source, count).map_err(fail)?,
            u32::to_le_bytes,
        ),
        (Mode::Indices, 2) => to_bytes(
            meshopt::decode_index_sequence::<u16>(source, count).map_err(fail)?,
            u16::to_le_bytes,
        ),
        (Mode::Indices, _) => to_bytes(
            meshopt::decode_index_sequence::<u32>(source, count).map_err(fail)?,
            u32::to_le_bytes,
        ),
    };
    match (view.filter, view.stride) {
        (Filter::None, _) => {}
        (Filter::Octahedral, 4) => {
            let mut v: Vec<[i8; 4]> = (bytes.chunks_exact(4))
                .map(|c| {
                    c.try_into()
                        .map(|a: [u8; 4]| a.map(|b| b as i8))
                        .unwrap_or_default()
                })
                .collect();
            meshopt::decode_filter_oct(&mut v);
            bytes = v.iter().flatten().map(|&c| c as u8).collect();
        }
        (Filter::Octahedral, _) => {
            let mut v = shorts(&bytes);
            meshopt::decode_filter_oct(&mut v);
            bytes = v.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        }
        (Filter::Quaternion, _) => {
            let mut v = shorts(&bytes);
            meshopt::decode_filter_quat(&mut v);
            bytes = v.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        }
        (Filter::Exponential, _) => {
            // Each 32-bit component decoded in isolation: the stride does not matter.
            let mut v: Vec<[u32; 1]> = (bytes.chunks_exact(4))
                .map(|c| [u32::from_le_bytes([c[0], c[1], c[2], c[3]])])
                .collect();
            meshopt::decode_filter_exp(&mut v);
            bytes = v.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        }
    }
    Ok(bytes)
}

/// `count` vertices of `stride` bytes (a multiple of 4, at most 256) decoded from `source`.
fn vertices(source: &[u8], count: usize, stride: usize) -> Result<Vec<u8>, String> {
    /// One vertex of `S` bytes (the decoder takes the vertex size from the type).
    #[derive(Clone, Copy)]
    #[repr(transparent)]
    struct Vertex<const S: usize>([u8; S]);
    impl<const S: usize> Default for Vertex<S> {
        fn default() -> Self {
            Self([0; S])
        }
    }
    fn decode<const S: usize>(source: &[u8], count: usize) -> Result<Vec<u8>, String> {
        let v: Vec<Vertex<S>> =
            meshopt::decode_vertex_buffer(source, count).map_err(|e| e.to_string())?;
        Ok(v.iter().flat_map(|v| v.0).collect())
    }
    macro_rules! by_stride {
        ($($s:literal)*) => {
            match stride {
                $($s => decode::<$s>(source, count),)*
                _ => Err(format!("byteStride {stride} is not a multiple of 4 up to 256")),
            }
        };
    }
    by_stride!(4 8 12 16 20 24 28 32 36 40 44 48 52 56 60 64 68 72 76 80 84 88 92 96 100 104
        108 112 116 120 124 128 132 136 140 144 148 152 156 160 164 168 172 176 180 184 188 192
        196 200 204 208 212 216 220 224 228 232 236 240 244 248 252 256)
}

/// The little-endian bytes of `values`.
fn to_bytes<T: Copy, const N: usize>(values: Vec<T>, bytes: fn(T) -> [u8; N]) -> Vec<u8> {
    values.into_iter().flat_map(bytes).collect()
}

/// `bytes` as groups of four 16-bit integers (little-endian).
fn shorts(bytes: &[u8]) -> Vec<[i16; 4]> {
    (bytes.chunks_exact(8))
        .map(|c| std::array::from_fn(|k| i16::from_le_bytes([c[2 * k], c[2 * k + 1]])))
        .collect()
}
