//! Reading accessors, with every offset, stride and count checked against the buffers.
//!
//! The `gltf` crate validates references between objects; it does not check that an accessor's
//! bytes lie inside its buffer view, nor the view inside its buffer. This module does, and
//! converts every component type (normalised or not) to `f64`, applying sparse substitution.

use gltf::accessor::{DataType, Dimensions};
use gltf::{Accessor, Document};

use super::LoadError;

/// Values (components) an accessor without a buffer view may expand to: such an accessor is all
/// zeros (or sparse), so a tiny hostile file could otherwise ask for any amount of memory.
/// Accessors backed by a view are bounded by the bytes actually present.
const MAX_VIEWLESS_VALUES: usize = 1 << 24;

/// An accessor's elements, flattened: element `i` is `values[i * width..(i + 1) * width]`.
pub struct Elements {
    /// The components, converted to `f64` (normalised integers mapped to [0, 1] or [-1, 1]).
    pub values: Vec<f64>,
    /// Components per element (3 for VEC3, 16 for MAT4).
    pub width: usize,
}

impl Elements {
    /// Number of elements.
    #[must_use]
    pub fn len(&self) -> usize {
        self.values.len() / self.width.max(1)
    }

    /// Element `i`.
    #[must_use]
    pub fn get(&self, i: usize) -> &[f64] {
        &self.values[i * self.width..(i + 1) * self.width]
    }
}

fn what(accessor: &Accessor<'_>) -> String {
    format!("accessor {}", accessor.index())
}

fn component_size(t: DataType) -> usize {
    match t {
        DataType::I8 | DataType::U8 => 1,
        DataType::I16 | DataType::U16 => 2,
        DataType::U32 | DataType::F32 => 4,
    }
}

fn read_component(bytes: &[u8], t: DataType, normalized: bool) -> f64 {
    match t {
        DataType::I8 => {
            let v = f64::from(bytes[0] as i8);
            if normalized { (v / 127.0).max(-1.0) } else { v }
        }
        DataType::U8 => {
            let v = f64::from(bytes[0]);
            if normalized { v / 255.0 } else { v }
        }
        DataType::I16 => {
            let v = f64::from(i16::from_le_bytes([bytes[0], bytes[1]]));
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U16 => {
            let v = f64::from(u16::from_le_bytes([bytes[0], bytes[1]]));
            if normalized { v / 65535.0 } else { v }
        }
        DataType::U32 => {
            let v = f64::from(u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]));
            if normalized { v / 4_294_967_295.0 } else { v }
        }
        DataType::F32 => f64::from(f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])),
    }
}

/// How the bytes of one element are laid out and read.
struct Layout {
    /// Offset of each component within the element (matrix columns are aligned to 4 bytes,
    /// glTF 2.0 §3.6.2.4).
    offsets: Vec<usize>,
    /// The element's packed size in bytes.
    size: usize,
    /// Component type.
    kind: DataType,
    /// Whether integers map to [0, 1] or [-1, 1].
    normalized: bool,
}

fn element_layout(dims: Dimensions, kind: DataType, normalized: bool) -> Layout {
    let t = kind;
    let size = component_size(t);
    let (columns, rows) = match dims {
        Dimensions::Scalar => (1, 1),
        Dimensions::Vec2 => (1, 2),
        Dimensions::Vec3 => (1, 3),
        Dimensions::Vec4 => (1, 4),
        Dimensions::Mat2 => (2, 2),
        Dimensions::Mat3 => (3, 3),
        Dimensions::Mat4 => (4, 4),
    };
    let column_bytes = if columns > 1 {
        (rows * size).next_multiple_of(4)
    } else {
        rows * size
    };
    let offsets = (0..columns)
        .flat_map(|c| (0..rows).map(move |r| c * column_bytes + r * size))
        .collect();
    Layout {
        offsets,
        size: columns * column_bytes,
        kind,
        normalized,
    }
}

/// The bytes of buffer view `view`, checked to lie inside its buffer.
fn view_bytes<'b>(
    view: &gltf::buffer::View<'_>,
    buffers: &'b [Vec<u8>],
) -> Result<&'b [u8], LoadError> {
    let buffer = &buffers[view.buffer().index()];
    view.offset()
        .checked_add(view.length())
        .and_then(|end| buffer.get(view.offset()..end))
        .ok_or_else(|| {
            LoadError::malformed(
                format!("bufferView {}", view.index()),
                format!(
                    "bytes {}..{} lie outside buffer {} ({} bytes)",
                    view.offset(),
                    view.offset().saturating_add(view.length()),
                    view.buffer().index(),
                    buffer.len()
                ),
            )
        })
}

/// Reads `count` elements starting at `offset` in a view, with the view's stride.
fn read_strided(
    bytes: &[u8],
    offset: usize,
    stride: usize,
    count: usize,
    layout: &Layout,
    out: &mut Vec<f64>,
) -> Result<(), String> {
    if count == 0 {
        return Ok(());
    }
    let size = component_size(layout.kind);
    let end = (count - 1)
        .checked_mul(stride)
        .and_then(|x| x.checked_add(offset))
        .and_then(|x| x.checked_add(layout.size));
    match end {
        Some(end) if end <= bytes.len() => {}
        _ => {
            return Err(format!(
                "{count} elements of {} bytes with stride {stride} from offset {offset} overrun \
                 its bufferView ({} bytes)",
                layout.size,
                bytes.len()
            ));
        }
    }
    out.reserve(count * layout.offsets.len());
    for i in 0..count {
        let base = offset + i * stride;
        for &c in &layout.offsets {
            let component = &bytes[base + c..base + c + size];
            out.push(read_component(component, layout.kind, layout.normalized));
        }
    }
    Ok(())
}

/// Reads an accessor entirely, checking that its bytes lie inside its buffer view and buffer,
/// and that every value is finite.
pub fn read(document: &Document, buffers: &[Vec<u8>], index: usize) -> Result<Elements, LoadError> {
    let accessor = document
        .accessors()
        .nth(index)
        .ok_or_else(|| LoadError::malformed(format!("accessor {index}"), "does not exist"))?;
    let bad = |reason: String| LoadError::malformed(what(&accessor), reason);
    let layout = element_layout(
        accessor.dimensions(),
        accessor.data_type(),
        accessor.normalized(),
    );
    let width = layout.offsets.len();
    let count = accessor.count();
    let mut values = Vec::new();
    match accessor.view() {
        Some(view) => {
            let bytes = view_bytes(&view, buffers)?;
            let stride = view.stride().unwrap_or(layout.size);
            if stride < layout.size {
                return Err(bad(format!(
                    "byteStride {stride} is smaller than an element ({} bytes)",
                    layout.size
                )));
            }
            read_strided(
                bytes,
                accessor.offset(),
                stride,
                count,
                &layout,
                &mut values,
            )
            .map_err(bad)?;
        }
        None => match count
            .checked_mul(width)
            .filter(|&n| n <= MAX_VIEWLESS_VALUES)
        {
            Some(n) => values.resize(n, 0.0),
            None => {
                return Err(bad(format!(
                    "{count} elements without a bufferView exceed the limit of \
                     {MAX_VIEWLESS_VALUES} values"
                )));
            }
        },
    }
    if let Some(sparse) = accessor.sparse() {
        let n = sparse.count();
        if n > count {
            return Err(bad(format!("sparse count {n} exceeds count {count}")));
        }
        let ind = sparse.indices();
        let ind_type = match ind.index_type() {
            gltf::accessor::sparse::IndexType::U8 => DataType::U8,
            gltf::accessor::sparse::IndexType::U16 => DataType::U16,
            gltf::accessor::sparse::IndexType::U32 => DataType::U32,
        };
        let ind_layout = element_layout(Dimensions::Scalar, ind_type, false);
        let mut indices = Vec::with_capacity(n);
        let ind_bytes = view_bytes(&ind.view(), buffers)?;
        read_strided(
            ind_bytes,
            ind.offset(),
            ind_layout.size,
            n,
            &ind_layout,
            &mut indices,
        )
        .map_err(|e| bad(format!("sparse indices: {e}")))?;
        let mut replacement = Vec::with_capacity(n * width);
        let val = sparse.values();
        let val_bytes = view_bytes(&val.view(), buffers)?;
        read_strided(
            val_bytes,
            val.offset(),
            layout.size,
            n,
            &layout,
            &mut replacement,
        )
        .map_err(|e| bad(format!("sparse values: {e}")))?;
        for (k, &i) in indices.iter().enumerate() {
            let i = i as usize;
            if i >= count {
                return Err(bad(format!(
                    "sparse index {i} is out of range (count {count})"
                )));
            }
            values[i * width..(i + 1) * width]
                .copy_from_slice(&replacement[k * width..(k + 1) * width]);
        }
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(bad(format!("element {} is not finite", i / width.max(1))));
    }
    Ok(Elements { values, width })
}

/// Reads an accessor that must have exactly `width` components per element.
pub fn read_exact(
    document: &Document,
    buffers: &[Vec<u8>],
    index: usize,
    width: usize,
    role: &str,
) -> Result<Elements, LoadError> {
    let elements = read(document, buffers, index)?;
    if elements.width != width {
        return Err(LoadError::malformed(
            format!("accessor {index}"),
            format!(
                "{role} needs {width} components per element, found {}",
                elements.width
            ),
        ));
    }
    Ok(elements)
}

/// Reads an index accessor: unsigned integer scalars.
pub fn read_indices(
    document: &Document,
    buffers: &[Vec<u8>],
    index: usize,
) -> Result<Vec<u32>, LoadError> {
    let accessor = document
        .accessors()
        .nth(index)
        .ok_or_else(|| LoadError::malformed(format!("accessor {index}"), "does not exist"))?;
    if !matches!(
        accessor.data_type(),
        DataType::U8 | DataType::U16 | DataType::U32
    ) || accessor.normalized()
    {
        return Err(LoadError::malformed(
            what(&accessor),
            "indices must be unsigned integers (u8, u16 or u32), not normalised",
        ));
    }
    let elements = read_exact(document, buffers, index, 1, "indices")?;
    // Exact: every u32 is representable in f64.
    Ok(elements.values.iter().map(|&v| v as u32).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalised_components_follow_the_spec() {
        assert_eq!(read_component(&[255], DataType::U8, true), 1.0);
        assert_eq!(read_component(&[0x81], DataType::I8, true), -1.0);
        assert_eq!(read_component(&[0x80], DataType::I8, true), -1.0);
        assert_eq!(read_component(&[0xff, 0x7f], DataType::I16, true), 1.0);
        assert_eq!(read_component(&[0xff, 0xff], DataType::U16, false), 65535.0);
    }

    #[test]
    fn matrix_columns_are_padded_to_four_bytes() {
        let l = element_layout(Dimensions::Mat3, DataType::U8, false);
        assert_eq!(l.offsets, vec![0, 1, 2, 4, 5, 6, 8, 9, 10]);
        assert_eq!(l.size, 12);
        let l = element_layout(Dimensions::Mat4, DataType::F32, false);
        assert_eq!(l.offsets.len(), 16);
        assert_eq!(l.size, 64);
    }

    #[test]
    fn overruns_are_detected_without_overflow() {
        let layout = element_layout(Dimensions::Vec3, DataType::F32, false);
        let mut out = Vec::new();
        let bytes = [0u8; 24];
        assert!(read_strided(&bytes, 0, 12, 2, &layout, &mut out).is_ok());
        assert!(read_strided(&bytes, 4, 12, 2, &layout, &mut out).is_err());
        assert!(read_strided(&bytes, usize::MAX, 12, 2, &layout, &mut out).is_err());
        assert!(read_strided(&bytes, 0, usize::MAX, 3, &layout, &mut out).is_err());
    }
}
