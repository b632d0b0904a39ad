//! A tiny glTF writer for tests: build a document piece by piece, get `.gltf` or `.glb` bytes.

use base64::Engine as _;
use serde_json::{Value, json};

/// One animation channel: (node, path, key times, values, interpolation).
pub type Channel<'a> = (usize, &'a str, &'a [f32], &'a [f32], &'a str);

/// A glTF document under construction with one binary buffer.
pub struct Doc {
    /// The JSON, without `buffers` (added when written).
    pub json: Value,
    /// The binary buffer's bytes.
    pub bin: Vec<u8>,
}

impl Default for Doc {
    fn default() -> Self {
        Self::new()
    }
}

impl Doc {
    pub fn new() -> Self {
        Self {
            json: json!({"asset": {"version": "2.0"}}),
            bin: Vec::new(),
        }
    }

    /// Appends `value` to the top-level array `key`, returning its index.
    pub fn push(&mut self, key: &str, value: Value) -> usize {
        let arr = self.json[key].as_array_mut();
        match arr {
            Some(a) => {
                a.push(value);
                a.len() - 1
            }
            None => {
                self.json[key] = json!([value]);
                0
            }
        }
    }

    fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.push(
            "bufferViews",
            json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}),
        )
    }

    /// A float accessor of `ty` ("SCALAR", "VEC3", "VEC4", "MAT4") with min/max.
    pub fn floats(&mut self, data: &[f32], ty: &str) -> usize {
        let width = match ty {
            "SCALAR" => 1,
            "VEC2" => 2,
            "VEC3" => 3,
            "VEC4" => 4,
            "MAT4" => 16,
            _ => panic!("type {ty}"),
        };
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        let mut min = vec![f32::INFINITY; width];
        let mut max = vec![f32::NEG_INFINITY; width];
        for chunk in data.chunks(width) {
            for (i, &v) in chunk.iter().enumerate() {
                min[i] = min[i].min(v);
                max[i] = max[i].max(v);
            }
        }
        let mut accessor = json!({"bufferView": view, "componentType": 5126,
            "count": data.len() / width, "type": ty});
        if !data.is_empty() {
            accessor["min"] = json!(min);
            accessor["max"] = json!(max);
        }
        self.push("accessors", accessor)
    }

    /// An index accessor with component type 5121 (u8), 5123 (u16) or 5125 (u32).
    pub fn indices(&mut self, data: &[u32], component: u32) -> usize {
        let bytes: Vec<u8> = match component {
            5121 => data.iter().map(|&v| v as u8).collect(),
            5123 => data
                .iter()
                .flat_map(|&v| (v as u16).to_le_bytes())
                .collect(),
            _ => data.iter().flat_map(|v| v.to_le_bytes()).collect(),
        };
        let view = self.view(&bytes);
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": component, "count": data.len(), "type": "SCALAR"}),
        )
    }

    /// A mesh with one triangle primitive; returns the mesh index.
    pub fn mesh(
        &mut self,
        positions: &[[f32; 3]],
        indices: Option<&[u32]>,
        material: Option<usize>,
    ) -> usize {
        let flat: Vec<f32> = positions.iter().flatten().copied().collect();
        let pos = self.floats(&flat, "VEC3");
        let mut prim = json!({"attributes": {"POSITION": pos}});
        if let Some(idx) = indices {
            prim["indices"] = json!(self.indices(idx, 5123));
        }
        if let Some(m) = material {
            prim["material"] = json!(m);
        }
        self.push("meshes", json!({"primitives": [prim]}))
    }

    /// A node; returns its index.
    pub fn node(&mut self, node: Value) -> usize {
        self.push("nodes", node)
    }

    /// A scene with the given root nodes, made the default.
    pub fn scene(&mut self, roots: &[usize]) -> usize {
        let s = self.push("scenes", json!({"nodes": roots}));
        self.json["scene"] = json!(s);
        s
    }

    /// An animation with one channel per (node, path, times, values, interpolation).
    pub fn animation(&mut self, name: &str, channels: &[Channel<'_>]) -> usize {
        let mut samplers = Vec::new();
        let mut chans = Vec::new();
        for (i, &(node, path, times, values, interp)) in channels.iter().enumerate() {
            let input = self.floats(times, "SCALAR");
            let ty = match path {
                "rotation" => "VEC4",
                "weights" => "SCALAR",
                _ => "VEC3",
            };
            let output = self.floats(values, ty);
            samplers.push(json!({"input": input, "output": output, "interpolation": interp}));
            chans.push(json!({"sampler": i, "target": {"node": node, "path": path}}));
        }
        self.push(
            "animations",
            json!({"name": name, "samplers": samplers, "channels": chans}),
        )
    }

    fn with_buffer(&self, uri: Option<String>) -> Value {
        let mut j = self.json.clone();
        if !self.bin.is_empty() {
            let mut b = json!({"byteLength": self.bin.len()});
            if let Some(uri) = uri {
                b["uri"] = json!(uri);
            }
            j["buffers"] = json!([b]);
        }
        j
    }

    /// The document as `.gltf` with the buffer embedded as a data: URI.
    pub fn gltf(&self) -> Vec<u8> {
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&self.bin)
        );
        serde_json::to_vec(&self.with_buffer(Some(uri))).unwrap()
    }

    /// The document as `.glb`.
    pub fn glb(&self) -> Vec<u8> {
        let mut json = serde_json::to_vec(&self.with_buffer(None)).unwrap();
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        let mut bin = self.bin.clone();
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let mut out = Vec::new();
        out.extend_from_slice(b"glTF");
        out.extend_from_slice(&2u32.to_le_bytes());
        let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
        out.extend_from_slice(&(total as u32).to_le_bytes());
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&json);
        if !bin.is_empty() {
            out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
            out.extend_from_slice(b"BIN\0");
            out.extend_from_slice(&bin);
        }
        out
    }
}

/// Corners of an axis-aligned quad in the XY plane facing +Z: two triangles.
pub const QUAD: [[f32; 3]; 4] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [1.0, 1.0, 0.0],
    [0.0, 1.0, 0.0],
];
pub const QUAD_INDICES: [u32; 6] = [0, 1, 2, 0, 2, 3];

/// An icosphere of radius `r`: `level` subdivisions of the icosahedron (20 × 4^level faces),
/// vertices on the sphere, faces outward or, if `inward`, inward (the sample generator's).
pub fn icosphere(level: usize, r: f32, inward: bool) -> (Vec<[f32; 3]>, Vec<u32>) {
    let (positions, triangles) = radiosity::samples::icosphere_mesh(level, r);
    let indices = triangles
        .iter()
        .flat_map(|t| if inward { [t[0], t[2], t[1]] } else { *t })
        .collect();
    (positions.iter().map(|p| p.to_array()).collect(), indices)
}

/// A closed box of `size` centred at `center`: 8 vertices, 12 triangles, faces outward or, if
/// `inward`, inward (a room).
pub fn cuboid(size: [f32; 3], center: [f32; 3], inward: bool) -> (Vec<[f32; 3]>, Vec<u32>) {
    let positions = (0..8)
        .map(|k| {
            let s = |bit: usize, axis: usize| {
                center[axis] + if k & bit == 0 { -0.5 } else { 0.5 } * size[axis]
            };
            [s(1, 0), s(2, 1), s(4, 2)]
        })
        .collect();
    let quads = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let indices = quads
        .iter()
        .flat_map(|q| {
            if inward {
                [q[0], q[2], q[1], q[0], q[3], q[2]]
            } else {
                [q[0], q[1], q[2], q[0], q[2], q[3]]
            }
        })
        .collect();
    (positions, indices)
}

/// The mean over triangle `t` of `f`, by the midpoint rule on its 4^`level` equal
/// sub-triangles (a reference quadrature for the bake's stratified sampling).
pub fn mean_over_triangle(t: [glam::DVec3; 3], level: u32, f: &dyn Fn(glam::DVec3) -> f64) -> f64 {
    if level == 0 {
        return f((t[0] + t[1] + t[2]) / 3.0);
    }
    let [a, b, c] = t;
    let (ab, bc, ca) = ((a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5);
    [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
        .into_iter()
        .map(|s| mean_over_triangle(s, level - 1, f))
        .sum::<f64>()
        / 4.0
}

/// A scene of closed meshes (one node each), static.
pub fn static_scene(
    meshes: &[(Vec<[f32; 3]>, Vec<u32>)],
    patch_size: Option<f64>,
) -> radiosity::scene::Scene {
    let mut d = Doc::new();
    let nodes: Vec<usize> = meshes
        .iter()
        .map(|(v, i)| {
            let m = d.mesh(v, Some(i), None);
            d.node(json!({"mesh": m}))
        })
        .collect();
    d.scene(&nodes);
    radiosity::loader::load(
        &d.glb(),
        &radiosity::loader::LoadOptions {
            patch_size,
            ..radiosity::loader::LoadOptions::default()
        },
    )
    .unwrap()
}

/// A horizontal square of half-side `h` at height `y`, one-sided, facing up or down: two
/// triangles.
pub fn quad(h: f32, y: f32, up: bool) -> (Vec<[f32; 3]>, Vec<u32>) {
    let v = vec![[-h, y, -h], [h, y, -h], [h, y, h], [-h, y, h]];
    let i = if up {
        vec![0, 2, 1, 0, 3, 2]
    } else {
        vec![0, 1, 2, 0, 2, 3]
    };
    (v, i)
}

/// The bundled sample `file_name` (`radiosity::samples`) loaded at `fps` frames a second.
pub fn sample_at(file_name: &str, fps: f64) -> radiosity::scene::Scene {
    let sample = (radiosity::samples::all().into_iter())
        .find(|s| s.file_name == file_name)
        .unwrap();
    let options = radiosity::loader::LoadOptions {
        fps,
        ..radiosity::loader::LoadOptions::default()
    };
    radiosity::loader::load(sample.gltf.as_bytes(), &options).unwrap()
}

/// An IEEE half float's value.
pub fn half_float(bits: u16) -> f32 {
    let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = i32::from((bits >> 10) & 0x1f);
    let mantissa = f32::from(bits & 0x3ff);
    sign * match exponent {
        0 => mantissa * 2f32.powi(-24),
        31 => f32::INFINITY,
        e => (1.0 + mantissa / 1024.0) * 2f32.powi(e - 15),
    }
}
