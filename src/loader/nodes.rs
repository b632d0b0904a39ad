//! The node hierarchy and its animation over the frames: which nodes can move, and their world
//! transforms (in f64) at every frame.

use glam::{DMat4, DQuat, DVec3};
use gltf::Document;
use gltf::animation::Property;

use super::animation::{Interpolation, Sampler};
use super::{LoadError, LoadOptions, accessor};
use crate::scene::Frames;

/// The node tree of the chosen scene.
pub struct Hierarchy {
    /// Nodes of the scene, parents before children (depth-first, in file order).
    pub order: Vec<usize>,
    /// Parent of each node of the file.
    pub parent: Vec<Option<usize>>,
    /// Local transform of each node, as written in the file.
    pub local: Vec<DMat4>,
}

/// Builds the hierarchy of the scene with the given root nodes, refusing a node graph that is
/// not a forest (a node with two parents, a cycle) and non-finite transforms.
pub fn hierarchy(document: &Document, roots: &[usize]) -> Result<Hierarchy, LoadError> {
    let count = document.nodes().len();
    let mut parent = vec![None; count];
    let mut local = Vec::with_capacity(count);
    for node in document.nodes() {
        for child in node.children() {
            if let Some(other) = parent[child.index()].replace(node.index()) {
                return Err(LoadError::malformed(
                    format!("node {}", child.index()),
                    format!("is a child of both node {other} and node {}", node.index()),
                ));
            }
        }
        local.push(local_matrix(&node)?);
    }
    // A cycle is a chain of parents that comes back to where it started.
    let mut state = vec![0u8; count]; // 0 unseen, 1 on the current chain, 2 known acyclic
    for start in 0..count {
        let mut chain = Vec::new();
        let mut at = Some(start);
        while let Some(n) = at {
            match state[n] {
                2 => break,
                1 => {
                    return Err(LoadError::malformed(
                        format!("node {n}"),
                        "is its own ancestor: the node graph has a cycle",
                    ));
                }
                _ => {
                    state[n] = 1;
                    chain.push(n);
                    at = parent[n];
                }
            }
        }
        chain.into_iter().for_each(|n| state[n] = 2);
    }
    let mut order = Vec::new();
    let mut seen = vec![false; count];
    let mut stack: Vec<usize> = roots.iter().rev().copied().collect();
    while let Some(n) = stack.pop() {
        if std::mem::replace(&mut seen[n], true) {
            return Err(LoadError::malformed(
                format!("node {n}"),
                "is reached twice from the scene's roots",
            ));
        }
        order.push(n);
        if let Some(node) = document.nodes().nth(n) {
            let children: Vec<usize> = node.children().map(|c| c.index()).collect();
            stack.extend(children.into_iter().rev());
        }
    }
    Ok(Hierarchy {
        order,
        parent,
        local,
    })
}

fn local_matrix(node: &gltf::Node<'_>) -> Result<DMat4, LoadError> {
    let bad = |reason: &str| LoadError::malformed(format!("node {}", node.index()), reason);
    let m = match node.transform() {
        gltf::scene::Transform::Matrix { matrix } => {
            DMat4::from_cols_array_2d(&matrix.map(|c| c.map(f64::from)))
        }
        gltf::scene::Transform::Decomposed {
            translation,
            rotation,
            scale,
        } => {
            let r = DQuat::from_array(rotation.map(f64::from));
            if r.length_squared() == 0.0 {
                return Err(bad("rotation is a zero quaternion"));
            }
            DMat4::from_scale_rotation_translation(
                DVec3::from_array(scale.map(f64::from)),
                r.normalize(),
                DVec3::from_array(translation.map(f64::from)),
            )
        }
    };
    if m.is_finite() {
        Ok(m)
    } else {
        Err(bad("transform is not finite"))
    }
}

/// The animated properties of one node (the last channel targeting a property wins).
#[derive(Default)]
pub struct Tracks {
    translation: Option<Sampler>,
    rotation: Option<Sampler>,
    scale: Option<Sampler>,
    /// Morph weights.
    pub weights: Option<Sampler>,
}

impl Tracks {
    /// Whether the node's transform is animated.
    #[must_use]
    pub fn moves(&self) -> bool {
        self.translation.is_some() || self.rotation.is_some() || self.scale.is_some()
    }
}

/// The chosen animations' channels per node, and the frames they span.
pub struct Timeline {
    /// Tracks of each node of the file.
    pub tracks: Vec<Tracks>,
    /// The frames to evaluate.
    pub frames: Frames,
}

/// Reads the chosen animations and derives the frames: frame f is at `start + f / fps`,
/// f = 0..=floor(duration × fps), [start, end] spanning the chosen animations' keys unless
/// overridden. A scene without animation has exactly one frame.
pub fn timeline(
    document: &Document,
    buffers: &[Vec<u8>],
    options: &LoadOptions,
    morph_targets: &[usize],
    warnings: &mut Vec<String>,
) -> Result<Timeline, LoadError> {
    let chosen: Vec<gltf::Animation<'_>> = match &options.animation {
        None => document.animations().collect(),
        Some(wanted) => vec![find_animation(document, wanted)?],
    };
    let mut tracks: Vec<Tracks> = (0..document.nodes().len())
        .map(|_| Tracks::default())
        .collect();
    let mut span: Option<(f64, f64)> = None;
    for animation in &chosen {
        for channel in animation.channels() {
            let sampler = channel.sampler();
            let node = channel.target().node().index();
            let property = channel.target().property();
            let what = || {
                format!(
                    "animation {} sampler {}",
                    animation.index(),
                    sampler.index()
                )
            };
            let width = match property {
                Property::Translation | Property::Scale => 3,
                Property::Rotation => 4,
                Property::MorphTargetWeights => match morph_targets[node] {
                    0 => {
                        warnings.push(format!(
                            "animation {} animates the weights of node {node}, which has no \
                             morph targets: ignored",
                            animation.index()
                        ));
                        continue;
                    }
                    n => n,
                },
            };
            let times =
                accessor::read_exact(document, buffers, sampler.input().index(), 1, "input")?;
            let output = accessor::read(document, buffers, sampler.output().index())?;
            let interpolation = match sampler.interpolation() {
                gltf::animation::Interpolation::Step => Interpolation::Step,
                gltf::animation::Interpolation::Linear => Interpolation::Linear,
                gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
            };
            if output.width != 1 && output.width != width {
                return Err(LoadError::malformed(
                    what(),
                    format!(
                        "output has {} components, the target needs {width}",
                        output.width
                    ),
                ));
            }
            let sampler = Sampler::new(times.values, output.values, width, interpolation)
                .map_err(|reason| LoadError::malformed(what(), reason))?;
            span = Some(match span {
                None => (sampler.start(), sampler.end()),
                Some((a, b)) => (a.min(sampler.start()), b.max(sampler.end())),
            });
            let slot = &mut tracks[node];
            match property {
                Property::Translation => slot.translation = Some(sampler),
                Property::Rotation => slot.rotation = Some(sampler),
                Property::Scale => slot.scale = Some(sampler),
                Property::MorphTargetWeights => slot.weights = Some(sampler),
            }
        }
    }
    let frames = match span {
        None => Frames {
            start: options.start.unwrap_or(0.0),
            fps: options.fps,
            count: 1,
        },
        Some((first, last)) => {
            let start = options.start.unwrap_or(first);
            let end = options.end.unwrap_or(last);
            if end < start {
                return Err(LoadError::Option(format!(
                    "the timeline ends (t = {end}) before it starts (t = {start})"
                )));
            }
            // The small allowance keeps a duration × fps that is an integer up to rounding
            // (4.1666665 s × 24) from losing its last frame.
            let steps = ((end - start) * options.fps * (1.0 + 1e-12)).floor();
            if steps >= options.max_frames as f64 {
                return Err(LoadError::Limit(format!(
                    "{:.0} frames ({} s at {} fps) exceed the limit of {}",
                    steps + 1.0,
                    end - start,
                    options.fps,
                    options.max_frames
                )));
            }
            Frames {
                start,
                fps: options.fps,
                count: steps as usize + 1,
            }
        }
    };
    Ok(Timeline { tracks, frames })
}

pub(super) fn find_animation<'a>(
    document: &'a Document,
    wanted: &str,
) -> Result<gltf::Animation<'a>, LoadError> {
    let animations = document.animations().map(|a| (a.index(), a.name()));
    let index = super::find_named(animations, wanted, ("animation", "the file has"))?;
    document
        .animations()
        .nth(index)
        .ok_or_else(|| LoadError::Option(format!("no animation {index}")))
}

/// World transforms over the frames.
pub struct Poses {
    /// World transform of every node at frame 0.
    pub first: Vec<DMat4>,
    /// For the requested nodes whose transform can change: world transform per frame.
    pub over_time: Vec<Option<Vec<DMat4>>>,
    /// Morph weights per frame of the nodes whose weights are animated (frames × targets).
    pub weights: Vec<Option<Vec<f64>>>,
}

impl Poses {
    /// World transforms of `node`: one per frame if it can change, else only frame 0's.
    #[must_use]
    pub fn placements(&self, node: usize) -> Vec<glam::DAffine3> {
        match &self.over_time[node] {
            Some(worlds) => worlds
                .iter()
                .map(|m| glam::DAffine3::from_mat4(*m))
                .collect(),
            None => vec![glam::DAffine3::from_mat4(self.first[node])],
        }
    }

    /// World transform of `node` at `frame`.
    #[must_use]
    pub fn world(&self, node: usize, frame: usize) -> DMat4 {
        match &self.over_time[node] {
            Some(worlds) => worlds[frame],
            None => self.first[node],
        }
    }
}

/// Which nodes have an animated transform on their chain of ancestors (themselves included).
#[must_use]
pub fn animated(hierarchy: &Hierarchy, tracks: &[Tracks]) -> Vec<bool> {
    let mut animated = vec![false; hierarchy.local.len()];
    // Parents come first in `order`.
    for &n in &hierarchy.order {
        animated[n] = tracks[n].moves() || hierarchy.parent[n].is_some_and(|p| animated[p]);
    }
    animated
}

/// Evaluates the world transform of every node at frame 0, and of the `wanted` nodes at every
/// frame when they are `animated` (see [`animated`]).
pub fn evaluate(
    hierarchy: &Hierarchy,
    timeline: &Timeline,
    animated: &[bool],
    wanted: &[bool],
) -> Poses {
    let count = hierarchy.local.len();
    let tracks = &timeline.tracks;
    let base_trs: Vec<(DVec3, DQuat, DVec3)> = hierarchy
        .local
        .iter()
        .map(DMat4::to_scale_rotation_translation)
        .collect();
    let mut world = vec![DMat4::IDENTITY; count];
    let frames = timeline.frames.count;
    let mut over_time: Vec<Option<Vec<DMat4>>> = (0..count)
        .map(|n| (wanted[n] && animated[n]).then(|| Vec::with_capacity(frames)))
        .collect();
    let mut first = Vec::new();
    for f in 0..frames {
        let t = timeline.frames.time(f);
        for &n in &hierarchy.order {
            if f > 0 && !animated[n] {
                continue;
            }
            let local = if tracks[n].moves() {
                let (mut s, mut r, mut tr) = base_trs[n];
                let mut v = [0.0; 3];
                if let Some(sampler) = &tracks[n].translation {
                    sampler.sample(t, &mut v);
                    tr = DVec3::from_array(v);
                }
                if let Some(sampler) = &tracks[n].scale {
                    sampler.sample(t, &mut v);
                    s = DVec3::from_array(v);
                }
                if let Some(sampler) = &tracks[n].rotation {
                    r = sampler.sample_rotation(t);
                }
                DMat4::from_scale_rotation_translation(s, r, tr)
            } else {
                hierarchy.local[n]
            };
            world[n] = match hierarchy.parent[n] {
                Some(p) => world[p] * local,
                None => local,
            };
            if let Some(v) = &mut over_time[n] {
                v.push(world[n]);
            }
        }
        if f == 0 {
            first = world.clone();
        }
    }
    let weights = tracks
        .iter()
        .map(|tr| {
            tr.weights.as_ref().map(|sampler| {
                let width = sampler.width();
                let mut all = vec![0.0; frames * width];
                for (f, chunk) in all.chunks_mut(width).enumerate() {
                    sampler.sample(timeline.frames.time(f), chunk);
                }
                all
            })
        })
        .collect();
    Poses {
        first,
        over_time,
        weights,
    }
}
