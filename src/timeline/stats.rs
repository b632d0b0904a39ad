//! Scene statistics measured by the lines (METHOD.md §1): how many crossings a line makes, and
//! how long the free paths between crossings are, against what integral geometry predicts.

use serde::Serialize;

use super::IntersectionList;
use crate::scene::Scene;
use crate::scene::subdivide::triangle_area;
use crate::trace::Hit;

/// Statistics of the lines at one frame.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SceneStats {
    /// The frame measured.
    pub frame: usize,
    /// Lines in the list (all meet the scene's box W).
    pub lines: usize,
    /// Mean crossings per line.
    pub mean_hits_per_line: f64,
    /// The prediction `2 A(K) / A(W)`: A(K) the area of all traced triangles at this frame,
    /// A(W) the area of the box the lines are drawn against.
    pub predicted_hits_per_line: f64,
    /// `histogram[i]`: fraction of lines with exactly i crossings (the last bin holds
    /// everything beyond).
    pub histogram: Vec<f64>,
    /// Mean distance between consecutive crossings along a line, in scene units (for a single
    /// convex body, the mean chord `4V/A`).
    pub mean_segment: f64,
    /// Segments measured.
    pub segments: u64,
}

/// Bins of [`SceneStats::histogram`].
const BINS: usize = 32;

impl SceneStats {
    /// Measures the statistics of `list` at `frame`.
    #[must_use]
    pub fn measure(scene: &Scene, list: &IntersectionList, frame: usize) -> Self {
        let mut counts = vec![0u64; BINS];
        let (mut hits, mut segments, mut length) = (0u64, 0u64, 0f64);
        let mut scratch: Vec<Hit> = Vec::new();
        for line in 0..list.lines() {
            list.frame_hits(line, frame, &mut scratch);
            hits += scratch.len() as u64;
            counts[scratch.len().min(BINS - 1)] += 1;
            for pair in scratch.windows(2) {
                length += f64::from(pair[1].t - pair[0].t);
                segments += 1;
            }
        }
        let area: f64 = scene
            .triangles_at(frame)
            .iter()
            .map(|(c, _)| triangle_area(c[0].as_dvec3(), c[1].as_dvec3(), c[2].as_dvec3()))
            .sum();
        let lines = list.lines().max(1) as f64;
        Self {
            frame,
            lines: list.lines(),
            mean_hits_per_line: hits as f64 / lines,
            predicted_hits_per_line: 2.0 * area / scene.bounds.surface_area(),
            histogram: counts.iter().map(|&c| c as f64 / lines).collect(),
            mean_segment: if segments == 0 {
                0.0
            } else {
                length / segments as f64 * scene.normalisation.radius
            },
            segments,
        }
    }
}
