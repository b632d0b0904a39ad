//! A bake: a scene, its timeline's lines and tallies, and the radiosity of any frame.
//!
//! Tracing happens once (and again only for refinement); relighting — new emission or
//! reflectance per material — re-solves from the kept tallies without tracing a line.

use std::sync::Arc;

use rayon::prelude::*;

use crate::direct::DirectLight;
use crate::scene::{Light, Material, Scene};
use crate::solve::tally::{FrameTally, Tallies};
use crate::solve::{FrameSolution, SolveParams, solve_lit};
use crate::timeline::{Control, IntersectionList, LineParams, TraceError};
use crate::trace::SceneTracer;

/// A traced scene, ready to solve any frame with any materials.
pub struct Bake {
    /// The scene (its materials are the defaults for [`Bake::solve_frame`]).
    pub scene: Scene,
    tracer: SceneTracer,
    list: IntersectionList,
    tallies: Tallies,
    /// Direct light of the punctual lights per frame (per unit power, so lights can change
    /// without tracing).
    direct: DirectLight,
    /// Seed of the line set, reused (with the next batch index) by refinement.
    seed: u64,
}

impl Bake {
    /// Traces `params.lines` lines through the whole timeline and tallies them.
    pub fn trace(scene: Scene, params: &LineParams) -> Result<Self, TraceError> {
        Self::trace_with(scene, params, &Control::default())
    }

    /// [`Bake::trace`] watched by `control` (progress, cancellation).
    pub fn trace_with(
        scene: Scene,
        params: &LineParams,
        control: &Control,
    ) -> Result<Self, TraceError> {
        let tracer = SceneTracer::new(&scene);
        let list = IntersectionList::build(&scene, &tracer, params, control)?;
        let mut tallies = Tallies::default();
        tallies.update(&list, &tracer.surfaces());
        let direct = DirectLight::compute(&scene, &tracer, control)?;
        Ok(Self {
            scene,
            tracer,
            list,
            tallies,
            direct,
            seed: params.seed,
        })
    }

    /// Progressive refinement: traces about `lines` more lines (a new batch of directions) and
    /// adds their tallies; the lines already traced are kept.
    pub fn refine(&mut self, lines: u64, control: &Control) -> Result<(), TraceError> {
        let params = LineParams {
            lines,
            bundles: None,
            seed: self.seed,
        };
        self.list
            .add_lines(&self.scene, &self.tracer, &params, control)?;
        self.tallies.update(&self.list, &self.tracer.surfaces());
        Ok(())
    }

    /// The intersection list.
    #[must_use]
    pub fn list(&self) -> &IntersectionList {
        &self.list
    }

    /// The tallies.
    #[must_use]
    pub fn tallies(&self) -> &Tallies {
        &self.tallies
    }

    /// The tracer (BVHs and the faces of every traced triangle).
    #[must_use]
    pub fn tracer(&self) -> &SceneTracer {
        &self.tracer
    }

    /// The tallies of one frame.
    #[must_use]
    pub fn frame_tally(&self, frame: usize) -> FrameTally {
        self.tallies.frame(
            &self.list,
            &self.tracer.surfaces(),
            frame,
            self.scene.patches.len(),
        )
    }

    /// Frames that share their solution: `representatives()[f]` is the first frame with the
    /// same tallies and the same direct light as f.
    #[must_use]
    pub fn representatives(&self) -> Vec<usize> {
        let by_tally = self
            .tallies
            .representatives(&self.list, &self.tracer.surfaces());
        if self.direct.is_empty() {
            return by_tally;
        }
        let mut first: std::collections::HashMap<(usize, Option<usize>), usize> =
            Default::default();
        (0..by_tally.len())
            .map(|f| {
                *first
                    .entry((by_tally[f], self.direct.state(f)))
                    .or_insert(f)
            })
            .collect()
    }

    /// The direct light of the punctual lights.
    #[must_use]
    pub fn direct(&self) -> &DirectLight {
        &self.direct
    }

    /// Each light's power (colour × intensity) as the scene gives it.
    #[must_use]
    pub fn light_power(&self) -> Vec<[f64; 3]> {
        self.scene.lights.iter().map(Light::power).collect()
    }

    /// Material index of every patch.
    fn patch_materials(&self) -> Vec<u32> {
        self.scene.patches.iter().map(|p| p.material).collect()
    }

    /// Solves one frame with `materials` (the scene's own, or new ones for relighting) and the
    /// scene's lights.
    #[must_use]
    pub fn solve_frame(
        &self,
        frame: usize,
        materials: &[Material],
        params: &SolveParams,
    ) -> FrameSolution {
        self.solve_frame_lit(frame, materials, &self.light_power(), params)
    }

    /// Solves one frame with `materials` and the punctual lights at `power` (colour ×
    /// intensity per light, in the scene's order): relighting either needs no tracing.
    #[must_use]
    pub fn solve_frame_lit(
        &self,
        frame: usize,
        materials: &[Material],
        power: &[[f64; 3]],
        params: &SolveParams,
    ) -> FrameSolution {
        let direct = self.direct.irradiance(frame, power);
        solve_lit(
            &self.frame_tally(frame),
            &self.patch_materials(),
            materials,
            params,
            direct.as_deref(),
        )
    }

    /// Solves every frame; frames with identical tallies and direct light share one solution.
    #[must_use]
    pub fn solve_all(
        &self,
        materials: &[Material],
        params: &SolveParams,
    ) -> Vec<Arc<FrameSolution>> {
        self.solve_all_with(materials, params, &Control::default())
    }

    /// [`Bake::solve_all`], adding each distinct frame to solve as one unit of work to
    /// `control`'s current stage.
    #[must_use]
    pub fn solve_all_with(
        &self,
        materials: &[Material],
        params: &SolveParams,
        control: &Control,
    ) -> Vec<Arc<FrameSolution>> {
        let representatives = self.representatives();
        let distinct: Vec<usize> = (0..representatives.len())
            .filter(|&f| representatives[f] == f)
            .collect();
        control.add_work(distinct.len() as u64);
        let solved: Vec<(usize, Arc<FrameSolution>)> = distinct
            .par_iter()
            .map(|&f| {
                let solution = Arc::new(self.solve_frame(f, materials, params));
                control.advance(1);
                (f, solution)
            })
            .collect();
        let mut by_frame: Vec<Option<Arc<FrameSolution>>> = vec![None; representatives.len()];
        for (f, s) in solved {
            by_frame[f] = Some(s);
        }
        representatives
            .iter()
            .map(|&r| {
                by_frame[r]
                    .clone()
                    .unwrap_or_else(|| Arc::new(self.solve_frame(r, materials, params)))
            })
            .collect()
    }
}
