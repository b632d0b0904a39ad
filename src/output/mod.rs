//! What a bake gives people to use and to look at: the baked glTF (radiance at each vertex), PNG
//! previews of chosen frames and an animated GIF of the timeline.
//!
//! - [`geometry`]: the scene at a frame as drawable triangles with per-vertex radiance;
//! - [`tonemap`]: HDR radiance to display colours, one exposure per timeline;
//! - [`glb`]: the baked `.glb` of a frame;
//! - [`preview`]: a small deterministic rasteriser and the PNG and GIF encoders.

pub mod geometry;
pub mod glb;
pub mod ktx2;
pub mod lightmap;
pub mod preview;
pub mod probes;
pub mod records;
pub mod tonemap;

use std::str::FromStr;

pub use geometry::{NodeMesh, frame_geometry, light_vertices};
pub use glb::{Embedded, frame_glb, lightmap_glb};
pub use preview::Camera;
pub use tonemap::ToneMap;
use tonemap::luminance;

use serde_json::json;

use crate::bake::Bake;
use crate::direct::points::{Gather, Lighting};
use crate::scene::Scene;
use crate::solve::FrameSolution;

/// Why an output could not be made.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// GLB stores its length in 32 bits.
    #[error("the frame's glTF would be larger than GLB's 4 GiB limit; bake fewer patches")]
    TooLarge,
    /// The GLB container could not be written (it is written to memory: not expected).
    #[error("writing the GLB container: {0}")]
    Container(String),
    /// The image encoder failed.
    #[error("encoding an image: {0}")]
    Image(#[from] image::ImageError),
}

/// The camera of a preview of `frame`: the scene's own (posed at the frame) or, if it has none,
/// an automatic one framing the whole animation's bounding sphere (the unit sphere of
/// normalised space), seen from above and in front.
#[must_use]
pub fn camera(scene: &Scene, frame: usize, aspect: f64) -> Camera {
    match &scene.camera {
        Some(c) => Camera {
            pose: c.pose(frame),
            projection: c.projection,
            aspect: c.aspect,
        },
        None => Camera::automatic(glam::DVec3::ZERO, 1.0, aspect),
    }
}

/// How a preview shades the patches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Shading {
    /// The baked glTF's per-vertex radiance interpolated across each triangle: what an engine
    /// shows.
    #[default]
    Smooth,
    /// One colour per patch: to inspect the patches themselves.
    Flat,
}

impl FromStr for Shading {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "smooth" => Ok(Self::Smooth),
            "flat" => Ok(Self::Flat),
            _ => Err(format!("{s:?} is not a shading: smooth or flat")),
        }
    }
}

impl std::fmt::Display for Shading {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Smooth => "smooth",
            Self::Flat => "flat",
        })
    }
}

/// The scene as drawn at `frame` ([`Bake::shown`]) with the light evaluated at its vertices
/// from `solution`, solved with `lighting` ([`light_vertices`], the standard sampling of the
/// bake's seed): what the baked glTF and the previews show.
#[must_use]
pub fn lit_geometry(
    bake: &Bake,
    frame: usize,
    solution: &FrameSolution,
    lighting: Lighting<'_>,
) -> Vec<NodeMesh> {
    let mut meshes = frame_geometry(bake.shown(), frame);
    let gather = Gather::standard(bake.seed());
    light_vertices(bake, frame, &mut meshes, (solution, lighting), gather);
    meshes
}

/// A preview of one frame: the tone-mapped radiance, shaded per vertex as the baked glTF is
/// (`meshes`, lit: [`lit_geometry`]) or flat per patch (`radiance`, by `shading`), the unlit
/// sides of triangles lit on their other side cut away.
#[must_use]
pub fn preview_image(
    scene: &Scene,
    frame: usize,
    (meshes, radiance): (&[NodeMesh], &[[f64; 3]]),
    (tone, shading): (&ToneMap, Shading),
    width: u32,
    height: u32,
) -> image::RgbImage {
    // A cutaway: an unlit side of a triangle whose other side is lit is not drawn. A closed
    // room of double-sided walls (as Blender exports every material) seen from outside shows
    // its lit inside through the walls' dark outer sides, as a room of one-sided walls does
    // with its back faces culled.
    let brightest = radiance.iter().map(|&l| luminance(l)).fold(0.0, f64::max);
    let lit = |p: u32| luminance(radiance[p as usize]) > tonemap::UNLIT * brightest;
    let mut other_side = vec![None; scene.patches.len()];
    let traced = std::iter::once(&scene.statics).chain(scene.objects.iter().map(|o| &o.mesh));
    for f in traced.flat_map(|m| &m.faces) {
        if let Some(back) = f.back {
            other_side[f.front as usize] = Some(back);
            other_side[back as usize] = Some(f.front);
        }
    }
    let hidden = |p: u32| !lit(p) && other_side[p as usize].is_some_and(lit);
    let mut triangles = Vec::new();
    for mesh in meshes {
        for (t, &patch) in mesh.triangles.iter().zip(&mesh.patches) {
            if hidden(patch) {
                continue;
            }
            let corners = t.map(|i| mesh.positions[i as usize]);
            triangles.push(match shading {
                Shading::Smooth => preview::Triangle {
                    corners,
                    colours: t.map(|i| tone.apply(mesh.radiance[i as usize])),
                },
                Shading::Flat => {
                    preview::Triangle::flat(corners, tone.apply(radiance[patch as usize]))
                }
            });
        }
    }
    let aspect = f64::from(width.max(1)) / f64::from(height.max(1));
    preview::render(&triangles, &camera(scene, frame, aspect), width, height)
}

/// The patch table (the service's `GET /v1/timelines/{id}/patches`, the bake's
/// `patches.json`): each patch's source, side, area and material, and the materials' names
/// (what relighting takes). A patch that is not its source triangle whole (cut by a patch
/// size or by `auto`, or merged from several) has `parts`: each of its triangles' source
/// triangle, share of the patch's area and corners in barycentric coordinates on that source
/// triangle, so that an answer can be put back on the source mesh.
#[must_use]
pub fn patch_table(scene: &Scene) -> serde_json::Value {
    let parts = patch_parts(scene);
    let patches: Vec<serde_json::Value> = scene
        .patches
        .iter()
        .enumerate()
        .map(|(id, p)| {
            let mut entry = json!({"id": id, "node": p.source.node, "mesh": p.source.mesh, "primitive": p.source.primitive,
                   "triangle": p.source.triangle, "side": p.side, "area": p.area, "moving": p.object.is_some(),
                   "material": p.material});
            if !p.merged.is_empty() {
                entry["merged"] = json!(p.merged);
            }
            let own = &parts[id];
            let whole = matches!(own.as_slice(), [(o, _)] if o.is_whole() && o.triangle == p.source.triangle);
            let total: f64 = own.iter().map(|(_, a)| a).sum();
            if !own.is_empty() && !whole {
                let listed: Vec<serde_json::Value> = (own.iter())
                    .map(|(o, area)| {
                        let corners = o.corners.map(|[u, v]| [1.0 - u - v, u, v]);
                        let share = if total > 0.0 { area / total } else { 0.0 };
                        json!({"triangle": o.triangle, "share": share, "corners": corners})
                    })
                    .collect();
                entry["parts"] = json!(listed);
            }
            entry
        })
        .collect();
    let materials: Vec<serde_json::Value> = (scene.materials.iter().enumerate())
        .map(|(index, m)| json!({"index": index, "name": m.name}))
        .collect();
    json!({ "patches": patches, "materials": materials })
}

/// Each patch's triangles: where each lies on its source triangle, and its area (in its
/// mesh's own units). None for a mesh whose origins are unknown.
fn patch_parts(scene: &Scene) -> Vec<Vec<(crate::scene::Origin, f64)>> {
    let mut parts = vec![Vec::new(); scene.patches.len()];
    let meshes = std::iter::once(&scene.statics).chain(scene.objects.iter().map(|o| &o.mesh));
    for mesh in meshes.filter(|m| m.origins.len() == m.triangles.len()) {
        for ((t, faces), origin) in mesh.triangles.iter().zip(&mesh.faces).zip(&mesh.origins) {
            let [a, b, c] = t.map(|v| mesh.positions[v as usize].as_dvec3());
            let area = crate::scene::subdivide::triangle_area(a, b, c);
            for p in [Some(faces.front), faces.back].into_iter().flatten() {
                parts[p as usize].push((*origin, area));
            }
        }
    }
    parts
}

/// A choice of frames on the command line: `all`, `none`, or a comma-separated list of frame
/// numbers, ranges `a-b` (inclusive) and the words `first`, `middle`, `last`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FrameSpec {
    /// Every frame.
    All,
    /// The listed items.
    List(Vec<FrameItem>),
}

/// One item of a [`FrameSpec`] list.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameItem {
    /// Frames `a..=b`.
    Range(usize, usize),
    /// Frame 0.
    First,
    /// Frame `count / 2`.
    Middle,
    /// The last frame.
    Last,
}

impl FrameSpec {
    /// The frames chosen from a timeline of `count` frames, sorted, without repeats; frame
    /// numbers past the end are dropped.
    #[must_use]
    pub fn frames(&self, count: usize) -> Vec<usize> {
        let last = count.saturating_sub(1);
        let mut out: Vec<usize> = match self {
            Self::All => (0..count).collect(),
            Self::List(items) => items
                .iter()
                .flat_map(|item| match *item {
                    FrameItem::Range(a, b) => a..=b.min(last),
                    FrameItem::First => 0..=0,
                    FrameItem::Middle => count / 2..=count / 2,
                    FrameItem::Last => last..=last,
                })
                .filter(|&f| f < count)
                .collect(),
        };
        out.sort_unstable();
        out.dedup();
        out
    }
}

impl FrameSpec {
    /// The frame numbers asked for by number that a timeline of `count` frames does not have
    /// (a range's part past the end included), which [`FrameSpec::frames`] leaves out.
    #[must_use]
    pub fn past_end(&self, count: usize) -> Vec<usize> {
        let Self::List(items) = self else {
            return Vec::new();
        };
        let mut out: Vec<usize> = (items.iter())
            .filter_map(|item| match *item {
                FrameItem::Range(a, b) if b >= count => Some(a.max(count)),
                _ => None,
            })
            .collect();
        out.sort_unstable();
        out.dedup();
        out
    }
}

impl FromStr for FrameSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "all" => return Ok(Self::All),
            "none" | "" => return Ok(Self::List(Vec::new())),
            _ => {}
        }
        let number = |t: &str| {
            t.trim()
                .parse::<usize>()
                .map_err(|_| format!("{t:?} is not a frame number, range, first, middle or last"))
        };
        s.split(',')
            .map(|item| match item.trim() {
                "first" => Ok(FrameItem::First),
                "middle" => Ok(FrameItem::Middle),
                "last" => Ok(FrameItem::Last),
                t => match t.split_once('-') {
                    Some((a, b)) => {
                        let (a, b) = (number(a)?, number(b)?);
                        if a > b {
                            Err(format!("the range {t:?} is empty"))
                        } else {
                            Ok(FrameItem::Range(a, b))
                        }
                    }
                    None => number(t).map(|f| FrameItem::Range(f, f)),
                },
            })
            .collect::<Result<_, _>>()
            .map(Self::List)
    }
}

impl std::fmt::Display for FrameSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::All => write!(f, "all"),
            Self::List(items) if items.is_empty() => write!(f, "none"),
            Self::List(items) => {
                let parts: Vec<String> = items
                    .iter()
                    .map(|i| match *i {
                        FrameItem::Range(a, b) if a == b => a.to_string(),
                        FrameItem::Range(a, b) => format!("{a}-{b}"),
                        FrameItem::First => "first".into(),
                        FrameItem::Middle => "middle".into(),
                        FrameItem::Last => "last".into(),
                    })
                    .collect();
                write!(f, "{}", parts.join(","))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_specs_parse_and_choose() {
        let spec: FrameSpec = "first,middle,last".parse().unwrap();
        assert_eq!(spec.frames(25), vec![0, 12, 24]);
        assert_eq!(spec.frames(1), vec![0]);
        let spec: FrameSpec = "3, 1-2,99,2".parse().unwrap();
        assert_eq!(spec.frames(10), vec![1, 2, 3]);
        assert_eq!(spec.to_string(), "3,1-2,99,2");
        // What is left out is said.
        assert_eq!(spec.past_end(10), vec![99]);
        assert_eq!(spec.past_end(3), vec![3, 99]);
        assert!(spec.past_end(100).is_empty());
        let range: FrameSpec = "5-20".parse().unwrap();
        assert_eq!(range.past_end(10), vec![10]);
        assert!(
            "first,last"
                .parse::<FrameSpec>()
                .unwrap()
                .past_end(1)
                .is_empty()
        );
        assert_eq!("all".parse::<FrameSpec>().unwrap().frames(3), vec![0, 1, 2]);
        assert!("none".parse::<FrameSpec>().unwrap().frames(3).is_empty());
        assert!("5-2".parse::<FrameSpec>().is_err());
        assert!("x".parse::<FrameSpec>().is_err());
        assert!("-3".parse::<FrameSpec>().is_err());
    }
}
