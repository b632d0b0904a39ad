//! Lightmaps (issue 49, its first part): the scene as drawn unwrapped once onto one texture
//! atlas, and each lighting state's radiance evaluated at every texel's own point.
//!
//! - **The atlas.** The drawn scene at frame 0 (the rest pose: [`frame_geometry`], each side
//!   of a double-sided face its own triangles) is unwrapped and packed by `uvunwrap` at a fixed
//!   density (`texels_per_unit` texels per scene unit), charts at least
//!   2 × [`PADDING`] texels apart, never overlapping. Every texel a triangle covers belongs to
//!   that triangle: its centre's, or (at a chart's rim, where bilinear filtering reads it) the
//!   nearest triangle's nearest point, so that a chart's edge texels hold its own light; the
//!   texels no triangle touches (the gutters) take their covered neighbours' mean when written.
//! - **Texels at their own points.** A texel's radiance is `Le + (ρ/π)(E_direct + E_gathered)`:
//!   the direct light of the lamps and the sampled emitters evaluated at the texel's point
//!   ([`crate::direct::points`], no gather rays: the emitters' closed form times the share of
//!   [`TEXEL_RAYS`] of a vertex's shadow rays that gets through; sharp shadows and penumbrae at
//!   texel scale, the static part kept across frames as the vertices' is), and the light
//!   gathered from the solution interpolated across its triangle: from the triangle's vertices'
//!   final gathers ([`crate::direct::points::PointRadiance::gathered`]) where the triangle is
//!   shorter than [`LATTICE_SPACING`], from a lattice of final gathers on the face itself where
//!   it is longer (a wall drawn as two triangles: its corners' light is not its middle's). A
//!   texel that a surface touches (under a resting box) takes no gathered light.
//! - **Where interpolating is wrong, gathers near the texel.** A texel farther from a point it
//!   would interpolate than [`VALIDITY`] times the harmonic mean distance to the surfaces
//!   around it (probed once, at the rest pose: [`crate::direct::points::closeness`]) reads the
//!   final gathers of records placed among such texels instead ([`super::records`]:
//!   irradiance caching, a record within the reach of each, many in a narrow gap, few in the
//!   open); a texel whose interpolation points' light differs by more than [`SPREAD`] of its
//!   radiance beyond their noise (the ceiling over an emitter against the ceiling beside it)
//!   gathers its own. Each texel's standard error is its direct light's in quadrature with
//!   its interpolation points' or records' error bars (which hold their own direct light's
//!   too: an upper estimate); what linear interpolation misses where it is kept is not in it.
//! - **States.** Frames that share a solution ([`Bake::representatives`]) share one lightmap,
//!   written once.

use glam::DVec3;

use super::NodeMesh;
use super::geometry::{frame_geometry, light_points, vertex_points};
use super::records::{MOST_REACH, Reader, Records, VALIDITY};
use crate::bake::Bake;
use crate::direct::points::closeness;
use crate::direct::points::{Gather, Lighting, PointRadiance, Points};
use crate::scene::Scene;
use crate::solve::FrameSolution;

/// Texels per scene unit of `bake --lightmaps` unless told (8 per metre: the level's 17,700
/// texels add about a tenth to its bake; 32 per metre, a quarter of a million, about as much
/// again as the bake: docs/outputs.md).
pub const TEXELS_PER_UNIT: f64 = 8.0;

/// Longest edge (normalised units: the scene's radius is 1) of a drawn triangle whose texels
/// interpolate the gathered light of its corner vertices; a longer one is cut into a lattice of
/// `n × n` smaller triangles no longer than this, whose nodes' light is gathered on the face
/// itself ([`Lattice`]). An eighth of the scene: on the moving Cornell box (large faces) the
/// texels' RMS error against the path tracer went from 12.8% to 2.5% (a sixteenth: 1.8%, at 2.2
/// times the texels' cost; both with a vertex's shadow rays per texel).
pub const LATTICE_SPACING: f64 = 1.0 / 8.0;

/// A texel's shadow rays to an emitter, as a share of a vertex's
/// ([`crate::direct::points::Gather::density`]).
pub const TEXEL_RAYS: f64 = 0.25;

/// Most lattice cuts along a triangle's edge.
const LATTICE_MOST: u32 = 64;

/// Gather rays of a record ([`crate::output::records`]), a quarter of a vertex's: records are
/// many (the level at 32 texels per unit: 17,800) and a texel reads several; more batches where
/// they leave a record uncertain, as at a vertex. At 256, the level's texels at 8 per unit were
/// 2.60% RMS from the path tracer against 3.09% at 64, for twice the texels' time.
pub const RECORD_RAYS: usize = 64;

/// The largest difference between the light gathered at a texel's interpolation points, as a
/// share of the texel's radiance, that interpolating it across them may span: more, and the
/// light is not smooth there (the ceiling over an emitter against the ceiling beside it), so
/// the texel gathers its own. A difference within 3 of its standard errors is noise.
pub const SPREAD: f64 = 0.25;

/// A source of a texel's interpolation whose weight is below this is left out of the tests
/// for its own gather ([`VALIDITY`], [`SPREAD`]).
const SOURCE_WEIGHT: f64 = 0.05;

/// The share of the spread of the light a texel interpolates (about its weighted mean) that its
/// error bar takes as what interpolating may miss: the light between sources that differ is
/// known to about their difference, not to their noise alone. With it, frame 0's texels are
/// within 2σ of the path tracer for 94.7–99.4% of them on the four measured scenes (92.9–97.9%
/// without; `radiosity bench-vertices --texels-per-unit 8`).
const INTERPOLATION_SPREAD: f64 = 1.0;

/// Empty texels around each chart (charts are at least twice this apart).
pub const PADDING: u32 = 2;

/// Most texels an atlas may have (a 4096 × 4096 map): past it, a bake asks for a lower density.
pub const MAX_TEXELS: f64 = 16_777_216.0;

/// What a lightmap's texels hold.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum Quantity {
    /// The outgoing radiance, albedo and emission included: what the surface shows (an unlit
    /// material, or a display of the bake).
    #[default]
    Radiance,
    /// The light: the irradiance arriving over π, what a white diffuse surface would reflect
    /// there; what engines' lightmaps hold (Unity, Godot; three.js's `lightMap` at an intensity
    /// of π), their material's albedo (its texture at full resolution) multiplying it and its
    /// emission added.
    Light,
}

impl Quantity {
    /// The manifest's words for it.
    #[must_use]
    pub fn describe(self) -> &'static str {
        match self {
            Self::Radiance => {
                "radiance: the outgoing radiance, albedo and emission included (what the surface shows)"
            }
            Self::Light => {
                "light: the irradiance arriving over pi, what a white diffuse surface would reflect; a material shows albedo * light + emission (Unity's and Godot's lightmaps; three.js lightMap with lightMapIntensity = pi)"
            }
        }
    }
}

/// The drawn scene unwrapped onto one atlas, and where each covered texel lies on it.
#[derive(Clone, Debug)]
pub struct Lightmap {
    /// Atlas width, texels.
    pub width: u32,
    /// Atlas height, texels.
    pub height: u32,
    /// Texels per scene unit.
    pub texels_per_unit: f64,
    /// Charts packed.
    pub charts: u32,
    /// The lightmap's copy of each node mesh of [`frame_geometry`] at frame 0, in its order.
    pub meshes: Vec<UvMesh>,
    /// The drawn geometry at frame 0 the atlas was made from (its vertices' corners say where
    /// their gathers are evaluated at any frame).
    rest: Vec<NodeMesh>,
    /// The covered texels, row after row.
    texels: Vec<Texel>,
    /// Where each texel is evaluated, one point per covered texel.
    points: Points,
    /// Per node mesh, per triangle: where its texels read the gathered light.
    lattices: Vec<Vec<Lattice>>,
    /// The lattices' nodes, each on its triangle's face.
    nodes: Points,
    /// Per covered texel, its index among the readers of `records` ([`u32::MAX`] for none): a
    /// texel farther from a point it would interpolate than [`VALIDITY`] times the harmonic
    /// mean distance to the surfaces around it (in a narrow gap, a corner) reads records
    /// gathered near it instead.
    reader: Vec<u32>,
    /// The records, and where they are gathered (each a reader's point).
    records: Records,
    record_points: Points,
}

/// Where a texel reads the gathered light from: a vertex of its node mesh (index), or a
/// lattice node (index in [`Lightmap::nodes`]).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Source {
    Vertex(usize),
    Node(usize),
}

/// Where a drawn triangle's texels read the gathered light: its corner vertices' (`cuts` 1),
/// or the nodes of a lattice of `cuts × cuts` triangles over it, row `i` (the second corner's
/// barycentric coordinate times `cuts`) holding `cuts + 1 − i` nodes, the first at
/// `Lightmap::nodes[first]`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Lattice {
    cuts: u32,
    first: u32,
}

impl Lattice {
    /// The node at (i, j) (second and third barycentric coordinates times the cuts).
    fn node(self, i: u32, j: u32) -> usize {
        let n = self.cuts;
        (self.first + i * (n + 1) - i * i.saturating_sub(1) / 2 + j) as usize
    }

    /// The three nodes around barycentric point `b` and their weights.
    fn around(self, b: [f64; 3]) -> [(usize, f64); 3] {
        let n = f64::from(self.cuts);
        let (u, v) = ((b[1] * n).clamp(0.0, n), (b[2] * n).clamp(0.0, n));
        let last = self.cuts - 1;
        let i = (u.floor() as u32).min(last);
        let j = (v.floor() as u32).min(last - i);
        let (fu, fv) = (u - f64::from(i), v - f64::from(j));
        if fu + fv <= 1.0 || i + j + 1 > last {
            // At the far edge a point a hair past it is read from the last row's triangle.
            let w = [(1.0 - fu - fv).max(0.0), fu, fv];
            let sum: f64 = w.iter().sum();
            [
                (self.node(i, j), w[0] / sum),
                (self.node(i + 1, j), w[1] / sum),
                (self.node(i, j + 1), w[2] / sum),
            ]
        } else {
            [
                (self.node(i + 1, j + 1), fu + fv - 1.0),
                (self.node(i + 1, j), 1.0 - fv),
                (self.node(i, j + 1), 1.0 - fu),
            ]
        }
    }
}

/// One node mesh's vertices in the atlas: seams split vertices, so a mesh vertex may have
/// several.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct UvMesh {
    /// The node mesh's vertex each lightmap vertex copies.
    pub xref: Vec<u32>,
    /// Each lightmap vertex's coordinates in the atlas, in [0, 1]: (0, 0) the top left corner of
    /// texel row 0, v growing down the rows (glTF's convention for texture coordinates).
    pub uv: Vec<[f32; 2]>,
    /// The node mesh's triangles, on the lightmap's vertices.
    pub triangles: Vec<[u32; 3]>,
}

/// A covered texel: where on which triangle it is evaluated.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Texel {
    /// `row × width + column`.
    at: u32,
    /// The node mesh and its triangle.
    mesh: u32,
    triangle: u32,
    /// The point, in barycentric coordinates of the triangle's corners (its own order).
    bary: [f64; 3],
}

/// Per vertex, RGB.
type Rgb = Vec<[f64; 3]>;

/// A node mesh's vertices' gathered irradiance and their radiance's error bars.
type VertexLight<'a> = (&'a [[f64; 3]], &'a [[f64; 3]]);

/// A point's gathered irradiance and its radiance's error bar, RGB.
type Gathered = ([f64; 3], [f64; 3]);

/// A texel's best triangle so far: its distance, the node mesh, the triangle, the point.
type Claim = (f64, u32, u32, [f64; 3]);

/// One lighting state's lightmap: linear radiance per texel (RGB, the scene's emission units)
/// and its standard error, gutters filled.
#[derive(Clone, Debug, PartialEq)]
pub struct Texels {
    /// Atlas width, texels.
    pub width: u32,
    /// Atlas height, texels.
    pub height: u32,
    /// Radiance per texel, row after row from the top.
    pub radiance: Vec<[f32; 3]>,
    /// Its standard error.
    pub stderr: Vec<[f32; 3]>,
    /// The light per texel: the irradiance arriving over π, what a white diffuse surface there
    /// would reflect, the albedo and the emission left out (an engine's lightmap, which its
    /// material's albedo multiplies: [`Texels::light`]).
    pub light: Vec<[f32; 3]>,
    /// Its standard error (the radiance's over the albedo: 0 where the albedo is).
    pub light_stderr: Vec<[f32; 3]>,
    /// Whether a triangle covers each texel (the others are gutters).
    pub covered: Vec<bool>,
}

impl Lightmap {
    /// Unwraps `bake`'s scene as drawn at frame 0 at `texels_per_unit` texels per scene unit.
    ///
    /// # Errors
    /// A message naming the problem: a density that is not a positive number, an atlas over
    /// [`MAX_TEXELS`] at that density, or the unwrapper's own failure.
    pub fn new(bake: &Bake, texels_per_unit: f64) -> Result<Self, String> {
        Self::within(bake, texels_per_unit, MAX_TEXELS)
    }

    /// [`Lightmap::new`] with at most `most` texels (the service's limit, below
    /// [`MAX_TEXELS`]).
    ///
    /// # Errors
    /// As [`Lightmap::new`], the atlas over `most`.
    pub fn within(bake: &Bake, texels_per_unit: f64, most: f64) -> Result<Self, String> {
        if !(texels_per_unit.is_finite() && texels_per_unit > 0.0) {
            return Err(format!(
                "texels_per_unit must be a positive number, not {texels_per_unit}"
            ));
        }
        let scene = bake.shown();
        let scale = scene.normalisation.radius;
        let rest = frame_geometry(scene, 0);
        // The texels the surface needs at this density, before packing.
        let area: f64 = (rest.iter())
            .flat_map(|m| {
                m.triangles
                    .iter()
                    .map(move |t| t.map(|v| m.positions[v as usize]))
            })
            .map(|[a, b, c]| 0.5 * (b - a).cross(c - a).length() * scale * scale)
            .sum();
        let needed = area * texels_per_unit * texels_per_unit;
        if needed > most {
            return Err(format!(
                "a lightmap at {texels_per_unit} texels per unit needs about {needed:.0} texels \
                 for {area:.1} square units of surface, over the {most} allowed: lower \
                 texels_per_unit"
            ));
        }
        let positions: Vec<Vec<[f32; 3]>> = (rest.iter())
            .map(|m| m.positions.iter().map(|p| p.as_vec3().to_array()).collect())
            .collect();
        let indices: Vec<Vec<u32>> = (rest.iter())
            .map(|m| m.triangles.iter().flatten().copied().collect())
            .collect();
        let inputs: Vec<uvunwrap::MeshInput<'_>> = (positions.iter().zip(&indices))
            .map(|(p, i)| uvunwrap::MeshInput {
                scale: scale as f32,
                ..uvunwrap::MeshInput::new(p, i)
            })
            .collect();
        let options = uvunwrap::Options {
            density: uvunwrap::Density::Fixed {
                texels_per_unit: texels_per_unit as f32,
                page_size: None,
            },
            padding: PADDING,
            ..uvunwrap::Options::default()
        };
        let atlas = uvunwrap::generate(&inputs, &options)
            .map_err(|e| format!("the lightmap's unwrap failed: {e}"))?;
        let meshes: Vec<UvMesh> = (atlas.meshes.iter())
            .map(|out| UvMesh {
                xref: out.vertices.iter().map(|v| v.xref).collect(),
                uv: out.vertices.iter().map(|v| v.uv).collect(),
                triangles: (out.indices.chunks_exact(3))
                    .map(|t| [t[0], t[1], t[2]])
                    .collect(),
            })
            .collect();
        let (width, height) = (atlas.width.max(1), atlas.height.max(1));
        let texels = raster(&meshes, width, height);
        let mut lightmap = Self {
            width,
            height,
            texels_per_unit,
            charts: atlas.chart_count,
            meshes,
            rest,
            texels,
            points: Points::default(),
            lattices: Vec::new(),
            nodes: Points::default(),
            reader: Vec::new(),
            records: Records::default(),
            record_points: Points::default(),
        };
        let faces: Vec<(u32, bool)> = (lightmap.texels.iter())
            .map(|t| lightmap.rest[t.mesh as usize].faces[t.triangle as usize])
            .collect();
        let at: Vec<DVec3> = lightmap.texel_points().map(|(_, x)| x).collect();
        lightmap.points = bake.points_on_faces(faces.into_iter().zip(at.iter().copied()));
        // The lattices of the long triangles.
        let mut nodes = Vec::new();
        for mesh in &lightmap.rest {
            let mut lattices = Vec::with_capacity(mesh.triangles.len());
            for (k, t) in mesh.triangles.iter().enumerate() {
                let p = t.map(|v| mesh.positions[v as usize]);
                let longest = (0..3)
                    .map(|e| p[e].distance(p[(e + 1) % 3]))
                    .fold(0.0, f64::max);
                let cuts = ((longest / LATTICE_SPACING).ceil() as u32).clamp(1, LATTICE_MOST);
                let lattice = Lattice {
                    cuts,
                    first: nodes.len() as u32,
                };
                if cuts > 1 {
                    let n = f64::from(cuts);
                    for i in 0..=cuts {
                        for j in 0..=cuts - i {
                            let (b1, b2) = (f64::from(i) / n, f64::from(j) / n);
                            let x = p[0] * (1.0 - b1 - b2) + p[1] * b1 + p[2] * b2;
                            nodes.push((mesh.faces[k], x));
                        }
                    }
                }
                lattices.push(lattice);
            }
            lightmap.lattices.push(lattices);
        }
        let node_at: Vec<DVec3> = nodes.iter().map(|n| n.1).collect();
        lightmap.nodes = bake.points_on_faces(nodes);
        lightmap.place_records(bake, &at, &node_at);
        Ok(lightmap)
    }

    /// The texels farther from a point they would interpolate (vertices, and lattice nodes at
    /// `node_at`) than [`VALIDITY`] times the harmonic mean distance to the surfaces around
    /// them (rest pose, every surface), and the records they read ([`Records::place`]).
    fn place_records(&mut self, bake: &Bake, at: &[DVec3], node_at: &[DVec3]) {
        let traced = (&bake.scene, bake.tracer());
        let closeness = closeness(traced, 0, &self.points, bake.seed());
        // The readers, and the texel each is.
        let (mut readers, mut texels) = (Vec::new(), Vec::new());
        self.reader = vec![u32::MAX; self.texels.len()];
        for (i, t) in self.texels.iter().enumerate() {
            let mesh = &self.rest[t.mesh as usize];
            let far = self.sources(t).iter().any(|&(source, w)| {
                let x = match source {
                    Source::Vertex(v) => mesh.positions[v],
                    Source::Node(n) => node_at[n],
                };
                w >= SOURCE_WEIGHT && x.distance(at[i]) * closeness[i] > VALIDITY
            });
            if far {
                let p = mesh.triangles[t.triangle as usize].map(|v| mesh.positions[v as usize]);
                self.reader[i] = readers.len() as u32;
                texels.push(i);
                readers.push(Reader {
                    x: at[i],
                    n: (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero(),
                    reach: (VALIDITY / closeness[i]).min(MOST_REACH),
                });
            }
        }
        self.records = Records::place(&readers);
        let mut points = Points::default();
        for &r in &self.records.at {
            points.push(self.points.point(texels[r as usize]).iter().cloned());
        }
        self.record_points = points;
    }

    /// The three points `texel` interpolates the gathered light of, with their weights: its
    /// triangle's corners, or the lattice's nodes around it.
    fn sources(&self, texel: &Texel) -> [(Source, f64); 3] {
        let lattice = self.lattices[texel.mesh as usize][texel.triangle as usize];
        if lattice.cuts > 1 {
            lattice
                .around(texel.bary)
                .map(|(n, w)| (Source::Node(n), w))
        } else {
            let corners = self.rest[texel.mesh as usize].triangles[texel.triangle as usize];
            std::array::from_fn(|k| (Source::Vertex(corners[k] as usize), texel.bary[k]))
        }
    }

    /// The drawn geometry at frame 0 the atlas was made from, node mesh by node mesh.
    #[must_use]
    pub fn rest(&self) -> &[NodeMesh] {
        &self.rest
    }

    /// Each covered texel (`row × width + column`) and its point at frame 0 (normalised
    /// space), row after row.
    pub fn texel_points(&self) -> impl Iterator<Item = (usize, DVec3)> + '_ {
        self.texels.iter().map(|t| {
            let mesh = &self.rest[t.mesh as usize];
            let corners = mesh.triangles[t.triangle as usize];
            let x = (0..3).fold(DVec3::ZERO, |x, k| {
                x + mesh.positions[corners[k] as usize] * t.bary[k]
            });
            (t.at as usize, x)
        })
    }

    /// Each covered texel's place in the atlas (`row × width + column`) and its patch, in the
    /// order of [`Lightmap::points`].
    pub fn texel_patches(&self) -> impl Iterator<Item = (usize, u32)> + '_ {
        (self.texels.iter()).map(|t| {
            (
                t.at as usize,
                self.rest[t.mesh as usize].patches[t.triangle as usize],
            )
        })
    }

    /// Where each covered texel is evaluated, row after row.
    #[must_use]
    pub fn points(&self) -> &Points {
        &self.points
    }

    /// The lightmaps' manifest: the atlas, the formats, and for every frame its time and its
    /// lighting state's files (`file(state, kind)`, `kind` `"exr"`, `"png"` or `"ktx2"`; a
    /// state is its first frame, `representatives[f]`); the geometry is `geometry`.
    #[must_use]
    pub fn manifest(
        &self,
        scene: &Scene,
        (geometry, quantity): (&str, Quantity),
        representatives: &[usize],
        file: impl Fn(usize, &str) -> String,
    ) -> serde_json::Value {
        serde_json::json!({
            "geometry": geometry,
            "quantity": quantity,
            "quantity_meaning": quantity.describe(),
            "uv_set": 1,
            "width": self.width,
            "height": self.height,
            "texels_per_unit": self.texels_per_unit,
            "charts": self.charts,
            "covered_texels": self.covered(),
            "format": "OpenEXR, half float, linear RGB (the quantity) in the scene's emission units; row 0 at the top (glTF's texture coordinates)",
            "rgbm": {
                "format": "PNG, 8-bit RGBA, linear RGBM: value = rgb * a * range, clamped at range",
                "range": RGBM_RANGE,
            },
            "ktx2": "KTX 2.0, VK_FORMAT_R16G16B16A16_SFLOAT, Zstandard-supercompressed, linear (alpha 1), rows from the top",
            "frames": (representatives.iter().enumerate()).map(|(f, &r)| serde_json::json!({
                "frame": f,
                "time": scene.frames.time(f),
                "state": r,
                "lightmap": file(r, "exr"),
                "rgbm": file(r, "png"),
                "ktx2": file(r, "ktx2"),
            })).collect::<Vec<_>>(),
        })
    }

    /// Covered texels.
    #[must_use]
    pub fn covered(&self) -> usize {
        self.texels.len()
    }

    /// The lightmap of `frame` (a lighting state: a distinct frame), from its `solution`
    /// solved with `lighting`: each texel's direct light at its point, and the light gathered
    /// at its triangle's vertices, its lattice's nodes or the records around it interpolated,
    /// or at the texel itself (module docs). `lit` is the frame's drawn geometry with its
    /// vertices lit ([`super::lit_geometry`]) if the caller has it; otherwise (or if the frame's
    /// creases split its vertices unlike the rest pose's) the vertices are lit here.
    #[must_use]
    pub fn texels(
        &self,
        bake: &Bake,
        frame: usize,
        lit: Option<&[NodeMesh]>,
        (solution, lighting): (&FrameSolution, Lighting<'_>),
    ) -> Texels {
        let seed = bake.seed();
        let same = |lit: &[NodeMesh]| {
            lit.len() == self.rest.len()
                && (lit.iter().zip(&self.rest)).all(|(a, b)| {
                    a.triangles == b.triangles && a.gathered.len() == a.positions.len()
                })
        };
        let owned: Vec<(Rgb, Rgb)>;
        // Per node mesh, per vertex: the irradiance gathered and its radiance's error bar.
        let vertices: Vec<VertexLight<'_>> = match lit.filter(|l| same(l)) {
            Some(lit) => (lit.iter())
                .map(|m| (&m.gathered[..], &m.stderr[..]))
                .collect(),
            None => {
                let points = vertex_points(bake, &self.rest);
                let gather = Gather::standard(seed);
                let values = light_points(bake, frame, &points, (solution, lighting), gather);
                let mut values = values.into_iter();
                owned = (self.rest.iter())
                    .map(|m| {
                        let v: Vec<PointRadiance> =
                            values.by_ref().take(m.positions.len()).collect();
                        (
                            v.iter().map(|p| p.gathered).collect(),
                            v.iter().map(|p| p.stderr).collect(),
                        )
                    })
                    .collect();
                owned.iter().map(|(g, e)| (&g[..], &e[..])).collect()
            }
        };
        self.assemble(bake, frame, (solution, lighting), &vertices)
    }

    /// [`Lightmap::texels`] from the vertices' gathered irradiance and error bars.
    fn assemble(
        &self,
        bake: &Bake,
        frame: usize,
        (solution, lighting): (&FrameSolution, Lighting<'_>),
        vertices: &[VertexLight<'_>],
    ) -> Texels {
        // The direct light alone, a quarter of the vertices' shadow rays: 4 × 4 to an emitter
        // up to twice its size away, 8 × 8 nearer (a texel's neighbours are as many samples
        // more of the same penumbra; 16 × 16 made the level's texels at 32 per unit 3 times
        // longer).
        let direct_only = Gather {
            rays: 0,
            density: TEXEL_RAYS,
            ..Gather::standard(bake.seed())
        };
        let direct = light_points(bake, frame, &self.points, (solution, lighting), direct_only);
        // The lattices' nodes, gathered on their faces.
        let nodes = if self.nodes.is_empty() {
            Vec::new()
        } else {
            let gather = Gather::standard(bake.seed());
            light_points(bake, frame, &self.nodes, (solution, lighting), gather)
        };
        let size = self.width as usize * self.height as usize;
        let mut out = Texels {
            width: self.width,
            height: self.height,
            radiance: vec![[0.0; 3]; size],
            stderr: vec![[0.0; 3]; size],
            light: vec![[0.0; 3]; size],
            light_stderr: vec![[0.0; 3]; size],
            covered: vec![false; size],
        };
        let patches = &bake.shown().patches;
        let reflectance = |texel: &Texel| {
            let patch = self.rest[texel.mesh as usize].patches[texel.triangle as usize];
            (patches.get(patch as usize))
                .and_then(|p| lighting.materials.get(p.material as usize))
                .map_or([0.0; 3], |m| m.reflectance)
        };
        // The records' gathers, for the texels that read them.
        let gather = Gather {
            rays: RECORD_RAYS,
            density: TEXEL_RAYS,
            ..Gather::standard(bake.seed())
        };
        let records = if self.record_points.is_empty() {
            Vec::new()
        } else {
            light_points(
                bake,
                frame,
                &self.record_points,
                (solution, lighting),
                gather,
            )
        };
        // The gathered light and its error bar interpolated from the corners, the lattice's
        // nodes or the records around each texel, or none: the texel gathers its own.
        let mut interpolated: Vec<Option<Gathered>> = Vec::new();
        let mut sources: Vec<(Gathered, f64)> = Vec::new();
        for ((texel, &reader), d) in self.texels.iter().zip(&self.reader).zip(&direct) {
            sources.clear();
            if reader == u32::MAX {
                let (gathered, errors) = vertices[texel.mesh as usize];
                let zero = [0.0; 3];
                sources.extend(self.sources(texel).map(|(source, w)| {
                    let light = match source {
                        Source::Vertex(v) => (
                            *gathered.get(v).unwrap_or(&zero),
                            *errors.get(v).unwrap_or(&zero),
                        ),
                        Source::Node(n) => (nodes[n].gathered, nodes[n].stderr),
                    };
                    (light, w)
                }));
            } else {
                sources.extend(self.records.of(reader as usize).iter().map(|&(r, w)| {
                    let record = &records[r as usize];
                    ((record.gathered, record.stderr), f64::from(w))
                }));
            }
            let (mut g, mut e) = ([0.0; 3], [0.0; 3]);
            for &((gk, ek), w) in &sources {
                (0..3).for_each(|c| {
                    g[c] += w * gk[c];
                    e[c] += w * ek[c];
                });
            }
            let rho = reflectance(texel);
            let to_radiance = |c: usize, x: f64| rho[c] * std::f64::consts::FRAC_1_PI * x;
            // Whether the sources' light differs by more than [`SPREAD`] of the texel's
            // radiance, beyond their noise.
            let uneven = (0..3).any(|c| {
                let weighed = sources.iter().filter(|s| s.1 >= SOURCE_WEIGHT);
                let (lo, hi, noise) = weighed.fold(
                    (f64::INFINITY, f64::NEG_INFINITY, 0.0f64),
                    |(lo, hi, noise), &((gk, ek), _)| {
                        let l = to_radiance(c, gk[c]);
                        (lo.min(l), hi.max(l), noise.max(ek[c]))
                    },
                );
                let total = d.radiance[c] + to_radiance(c, g[c]);
                hi - lo - 3.0 * std::f64::consts::SQRT_2 * noise > SPREAD * total
            });
            // What interpolating misses, in the error bar: the sources' spread about their
            // weighted mean ([`INTERPOLATION_SPREAD`] of it).
            let total: f64 = sources.iter().map(|s| s.1).sum();
            if total > 0.0 {
                for c in 0..3 {
                    let mean = g[c] / total;
                    let spread = (sources.iter())
                        .map(|&((gk, _), w)| w * (gk[c] - mean).powi(2))
                        .sum::<f64>()
                        / total;
                    let missed = INTERPOLATION_SPREAD * to_radiance(c, spread.sqrt());
                    e[c] = e[c].hypot(missed);
                }
            }
            interpolated.push((!uneven).then_some((g, e)));
        }
        // The texels that gather their own, with a record's gather rays and a texel's shadow
        // rays.
        let mut gathering = Points::default();
        for (k, i) in interpolated.iter().enumerate() {
            if i.is_none() {
                gathering.push(self.points.point(k).iter().cloned());
            }
        }
        let gathered = if gathering.is_empty() {
            Vec::new()
        } else {
            light_points(bake, frame, &gathering, (solution, lighting), gather)
        };
        let mut gathered = gathered.into_iter();
        for ((texel, d), i) in self.texels.iter().zip(&direct).zip(interpolated) {
            let at = texel.at as usize;
            let rho = reflectance(texel);
            let (radiance, stderr, irradiance) = match i {
                Some((g, e)) => (
                    std::array::from_fn(|c| {
                        d.radiance[c] + rho[c] * std::f64::consts::FRAC_1_PI * g[c] * d.reached
                    }),
                    std::array::from_fn(|c| d.stderr[c].hypot(e[c])),
                    std::array::from_fn(|c| d.irradiance[c] + g[c] * d.reached),
                ),
                None => {
                    let own = gathered.next().unwrap_or_default();
                    (own.radiance, own.stderr, own.irradiance)
                }
            };
            for c in 0..3 {
                out.radiance[at][c] = radiance[c].max(0.0) as f32;
                out.stderr[at][c] = stderr[c] as f32;
                out.light[at][c] = (irradiance[c] * std::f64::consts::FRAC_1_PI).max(0.0) as f32;
                out.light_stderr[at][c] = if rho[c] > 0.0 {
                    (stderr[c] / rho[c]) as f32
                } else {
                    0.0
                };
            }
            out.covered[at] = true;
        }
        dilate(&mut out, 2 * PADDING as usize);
        out
    }
}

/// Every covered texel of `meshes`' triangles in an atlas of `width × height`, row after row:
/// a texel whose centre a triangle holds is that triangle's, at its centre; a texel no centre
/// claims but a triangle touches (within half a texel's diagonal) is the nearest triangle's, at
/// its nearest point.
fn raster(meshes: &[UvMesh], width: u32, height: u32) -> Vec<Texel> {
    let (w, h) = (width as usize, height as usize);
    // Per texel: (distance, mesh, triangle, bary) of its best triangle so far.
    let mut best: Vec<Option<Claim>> = vec![None; w * h];
    let reach = std::f64::consts::FRAC_1_SQRT_2;
    for (m, mesh) in meshes.iter().enumerate() {
        for (k, t) in mesh.triangles.iter().enumerate() {
            let p = t.map(|v| {
                let [u, v] = mesh.uv[v as usize];
                [f64::from(u) * w as f64, f64::from(v) * h as f64]
            });
            let area = cross(p[0], p[1], p[2]);
            if area.abs() < 1e-12 || !area.is_finite() {
                continue;
            }
            let lo = |a: usize| p.iter().map(|q| q[a]).fold(f64::INFINITY, f64::min) - 1.0;
            let hi = |a: usize| p.iter().map(|q| q[a]).fold(f64::NEG_INFINITY, f64::max) + 1.0;
            let (x0, x1) = (lo(0).max(0.0) as usize, (hi(0).max(0.0) as usize).min(w));
            let (y0, y1) = (lo(1).max(0.0) as usize, (hi(1).max(0.0) as usize).min(h));
            for y in y0..y1 {
                for x in x0..x1 {
                    let c = [x as f64 + 0.5, y as f64 + 0.5];
                    let (distance, bary) = nearest(c, &p, area);
                    if distance > reach {
                        continue;
                    }
                    let slot = &mut best[y * w + x];
                    if slot.is_none_or(|(d, ..)| distance < d) {
                        *slot = Some((distance, m as u32, k as u32, bary));
                    }
                }
            }
        }
    }
    (best.iter().enumerate())
        .filter_map(|(at, b)| {
            b.map(|(_, mesh, triangle, bary)| Texel {
                at: at as u32,
                mesh,
                triangle,
                bary,
            })
        })
        .collect()
}

/// Twice the signed area of triangle `a b c`.
fn cross(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
}

/// The distance from `c` to triangle `p` (0 inside) and the barycentric coordinates of the
/// triangle's point nearest it, a hair inside.
fn nearest(c: [f64; 2], p: &[[f64; 2]; 3], area: f64) -> (f64, [f64; 3]) {
    let b = [
        cross(c, p[1], p[2]) / area,
        cross(p[0], c, p[2]) / area,
        cross(p[0], p[1], c) / area,
    ];
    if b.iter().all(|&x| x >= 0.0) {
        return (0.0, b);
    }
    // Outside: the nearest point on the nearest edge.
    let mut found = (f64::INFINITY, b);
    for k in 0..3 {
        let (a, e) = (p[k], p[(k + 1) % 3]);
        let d = [e[0] - a[0], e[1] - a[1]];
        let len2 = d[0] * d[0] + d[1] * d[1];
        let s = if len2 > 0.0 {
            (((c[0] - a[0]) * d[0] + (c[1] - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let q = [a[0] + s * d[0], a[1] + s * d[1]];
        let distance = (c[0] - q[0]).hypot(c[1] - q[1]);
        if distance < found.0 {
            let mut bary = [0.0; 3];
            bary[k] = 1.0 - s;
            bary[(k + 1) % 3] = s;
            found = (distance, bary);
        }
    }
    // A hair towards the centroid, so that the point is on the face, not its edge.
    let inset = 1e-4;
    (found.0, found.1.map(|x| x * (1.0 - inset) + inset / 3.0))
}

/// Fills the gutters within `steps` texels of a covered texel with the mean of their filled
/// neighbours, a ring at a time, so that filtering and mipmaps near a chart's rim read its light.
fn dilate(texels: &mut Texels, steps: usize) {
    let (w, h) = (texels.width as usize, texels.height as usize);
    let mut filled = texels.covered.clone();
    let mut next: Vec<(usize, Vec<usize>)> = Vec::new();
    for _ in 0..steps {
        next.clear();
        for y in 0..h {
            for x in 0..w {
                if filled[y * w + x] {
                    continue;
                }
                let around: Vec<usize> = [
                    (-1i64, 0i64),
                    (1, 0),
                    (0, -1),
                    (0, 1),
                    (-1, -1),
                    (1, 1),
                    (-1, 1),
                    (1, -1),
                ]
                .into_iter()
                .map(|(dx, dy)| (x as i64 + dx, y as i64 + dy))
                .filter(|&(nx, ny)| nx >= 0 && ny >= 0 && nx < w as i64 && ny < h as i64)
                .map(|(nx, ny)| ny as usize * w + nx as usize)
                .filter(|&at| filled[at])
                .collect();
                if !around.is_empty() {
                    next.push((y * w + x, around));
                }
            }
        }
        if next.is_empty() {
            break;
        }
        let fields = [
            &mut texels.radiance,
            &mut texels.stderr,
            &mut texels.light,
            &mut texels.light_stderr,
        ];
        for values in fields {
            let means: Vec<[f32; 3]> = (next.iter())
                .map(|(_, around)| {
                    let n = around.len() as f32;
                    std::array::from_fn(|c| around.iter().map(|&a| values[a][c]).sum::<f32>() / n)
                })
                .collect();
            for ((at, _), mean) in next.iter().zip(means) {
                values[*at] = mean;
            }
        }
        for (at, _) in &next {
            filled[*at] = true;
        }
    }
}

/// The range of [`Texels::rgbm_png`]: radiance up to this many times its scale is encoded
/// (three.js's `RGBM16`, Unity's and Babylon's RGBM: `linear = rgb × a × RGBM_RANGE`).
pub const RGBM_RANGE: f32 = 16.0;

impl Texels {
    /// These texels with `quantity` in place of the radiance (and its error bars), which the
    /// writers then write: the light ([`Quantity::Light`]) is the lightmap an engine's
    /// material multiplies by its albedo.
    #[must_use]
    pub fn holding(mut self, quantity: Quantity) -> Self {
        if quantity == Quantity::Light {
            std::mem::swap(&mut self.radiance, &mut self.light);
            std::mem::swap(&mut self.stderr, &mut self.light_stderr);
        }
        self
    }

    /// The largest value of a covered texel (0 if none).
    #[must_use]
    pub fn peak(&self) -> f32 {
        (self.radiance.iter().zip(&self.covered))
            .filter(|(_, c)| **c)
            .flat_map(|(v, _)| *v)
            .fold(0.0, f32::max)
    }

    /// The radiance over `scale` as an 8-bit sRGB-encoded RGB PNG (clamped to 1), as a glTF
    /// colour texture is read: the lightmap `MOZ_lightmap` embeds, with `scale` in its
    /// intensity.
    ///
    /// # Errors
    /// The encoder's, as text.
    pub fn srgb_png(&self, scale: f32) -> Result<Vec<u8>, String> {
        let mut image = image::RgbImage::new(self.width, self.height);
        for (pixel, value) in image.pixels_mut().zip(&self.radiance) {
            pixel.0 = value.map(|v| super::preview::srgb((v / scale).clamp(0.0, 1.0)));
        }
        super::preview::encode_png(&image).map_err(|e| e.to_string())
    }

    /// The radiance scaled by `scale` as an 8-bit RGBA PNG in linear RGBM: `a` the multiplier
    /// (rounded up, so that `rgb` stays within 1), `rgb` the colour over `a × RGBM_RANGE`;
    /// radiance past [`RGBM_RANGE`] (scaled) is clamped to it. For engines without float
    /// textures; the EXR is the exact file.
    ///
    /// # Errors
    /// The encoder's, as text.
    pub fn rgbm_png(&self, scale: f32) -> Result<Vec<u8>, String> {
        let mut bytes = Vec::with_capacity(self.radiance.len() * 4);
        for l in &self.radiance {
            bytes.extend(rgbm(l.map(|c| c * scale)));
        }
        let mut out = Vec::new();
        image::ImageEncoder::write_image(
            image::codecs::png::PngEncoder::new(&mut out),
            &bytes,
            self.width,
            self.height,
            image::ExtendedColorType::Rgba8,
        )
        .map_err(|e| format!("encoding the lightmap: {e}"))?;
        Ok(out)
    }

    /// The radiance scaled by `scale` as a KTX2 texture of linear RGBA half floats (alpha 1),
    /// Zstandard-supercompressed ([`super::ktx2`]): for the web (three.js's `KTX2Loader`) and
    /// Bevy.
    ///
    /// # Errors
    /// The encoder's, as text.
    pub fn ktx2(&self, scale: f32) -> Result<Vec<u8>, String> {
        let rgba: Vec<[f32; 4]> = (self.radiance.iter())
            .map(|l| [l[0] * scale, l[1] * scale, l[2] * scale, 1.0])
            .collect();
        super::ktx2::rgba16f(self.width, self.height, &rgba)
    }

    /// The radiance as a linear half-float RGB OpenEXR image, scaled by `scale` (1: the
    /// scene's emission units).
    ///
    /// # Errors
    /// The encoder's, as text.
    pub fn exr(&self, scale: f32) -> Result<Vec<u8>, String> {
        use exr::prelude::*;
        let w = self.width as usize;
        let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
            let l = self.radiance[y * w + x];
            (
                f16::from_f32(l[0] * scale),
                f16::from_f32(l[1] * scale),
                f16::from_f32(l[2] * scale),
            )
        });
        let image = Image::from_channels((w, self.height as usize), channels);
        let mut bytes = std::io::Cursor::new(Vec::new());
        image
            .write()
            .to_buffered(&mut bytes)
            .map_err(|e| format!("encoding the lightmap: {e}"))?;
        Ok(bytes.into_inner())
    }
}

/// Linear radiance `l` as RGBM bytes ([`Texels::rgbm_png`]).
fn rgbm(l: [f32; 3]) -> [u8; 4] {
    let l = l.map(|c| (c / RGBM_RANGE).clamp(0.0, 1.0));
    let peak = l.iter().fold(0.0f32, |m, &c| m.max(c));
    let a = ((peak * 255.0).ceil() / 255.0).max(1.0 / 255.0);
    let byte = |x: f32| (x * 255.0).round().clamp(0.0, 255.0) as u8;
    [byte(l[0] / a), byte(l[1] / a), byte(l[2] / a), byte(a)]
}

#[cfg(test)]
mod tests {
    use super::{Lattice, RGBM_RANGE, rgbm};

    /// RGBM bytes decode (`rgb × a × range`) to the radiance within 8 bits of its multiplier,
    /// from a dim texel to the range's top, black is black, and past the range is clamped.
    #[test]
    fn rgbm_decodes_to_the_radiance_within_its_bytes() {
        let decode = |b: [u8; 4]| {
            let a = f32::from(b[3]) / 255.0;
            [0, 1, 2].map(|c| f32::from(b[c]) / 255.0 * a * RGBM_RANGE)
        };
        for l in [
            [0.01, 0.02, 0.005],
            [0.5, 0.25, 1.0],
            [3.0, 7.5, 15.9],
            [16.0, 0.0, 1.0],
        ] {
            let back = decode(rgbm(l));
            let peak = l.iter().fold(0.0f32, |m, &c| m.max(c));
            for c in 0..3 {
                // Half a step of the colour byte at the multiplier, plus the multiplier's own.
                let step = peak / 255.0 + RGBM_RANGE / 255.0 / 255.0;
                assert!((back[c] - l[c]).abs() <= step, "{l:?} -> {back:?}");
            }
        }
        assert_eq!(decode(rgbm([0.0; 3])), [0.0; 3]);
        assert_eq!(decode(rgbm([100.0, 0.0, 0.0]))[0], RGBM_RANGE);
    }

    /// A point's nodes are the lattice's own (each row one shorter), their weights its
    /// barycentric coordinates in the small triangle holding it: they sum to 1 and give back
    /// the point; the corners read their own node alone.
    #[test]
    fn a_lattice_reads_a_point_from_the_three_nodes_around_it() {
        let cuts = 5;
        let lattice = Lattice { cuts, first: 7 };
        let n = f64::from(cuts);
        let count = ((cuts + 1) * (cuts + 2) / 2) as usize;
        // Every node's place, in the order `Lightmap::new` pushes them.
        let mut places = Vec::new();
        for i in 0..=cuts {
            for j in 0..=cuts - i {
                assert_eq!(lattice.node(i, j), 7 + places.len());
                places.push([f64::from(i) / n, f64::from(j) / n]);
            }
        }
        assert_eq!(places.len(), count);
        for k in 0..400 {
            let (a, b) = ((k % 20) as f64 / 19.0, (k / 20) as f64 / 19.0);
            let (b1, b2) = if a + b > 1.0 {
                (1.0 - a, 1.0 - b)
            } else {
                (a, b)
            };
            let around = lattice.around([1.0 - b1 - b2, b1, b2]);
            let sum: f64 = around.iter().map(|(_, w)| w).sum();
            assert!((sum - 1.0).abs() < 1e-12, "{sum}");
            let mut back = [0.0; 2];
            for (node, w) in around {
                assert!((7..7 + count).contains(&node), "{node}");
                assert!(w >= -1e-12, "{w}");
                back[0] += w * places[node - 7][0];
                back[1] += w * places[node - 7][1];
            }
            assert!(
                (back[0] - b1).abs() < 1e-9 && (back[1] - b2).abs() < 1e-9,
                "{back:?}"
            );
        }
        assert_eq!(lattice.around([1.0, 0.0, 0.0])[0], (7, 1.0));
        let far = lattice.around([0.0, 1.0, 0.0]);
        assert!(far.contains(&(lattice.node(cuts, 0), 1.0)), "{far:?}");
    }
}
