//! Radiosity baking for animated glTF scenes with global lines and the multiframe method.
//!
//! # Layout
//!
//! The modules follow the data's journey:
//!
//! - [`loader`]: glTF 2.0 in, [`scene::Scene`] out. Validates once, evaluates animations over
//!   the frames, decides what is static and what moves, normalises to the bounding sphere.
//! - [`scene`]: the engine's scene model: patches, static triangles, moving objects, frames. It
//!   knows nothing of glTF or HTTP.
//! - [`lines`]: global lines: bundles of parallel lines with uniformly distributed directions.
//! - [`trace`]: every crossing of a line with the scene (obvhs BVHs, a watertight
//!   line–triangle test), and what crossings at one place mean: contacts, coplanar overlaps,
//!   grazes and seams ([`trace::coincident`]).
//! - [`timeline`]: the timeline's one intersection list (multiframe), frame extraction and the
//!   scene statistics measured by the lines.
//! - [`solve`]: tallies of the list per frame (`N_i`, `S_ij`, with per-frame changes only for
//!   what moves), the radiosity solve with per-patch error bars, and the scene's visibility
//!   information measured by the lines ([`solve::information`]).
//! - [`direct`]: direct light from punctual lights (point, spot, directional) and, in
//!   [`direct::area`], from small emitting surfaces sampled as area lights, with shadows and
//!   their sampling error: the light the interreflection starts from. [`direct::reference`]
//!   is the path-traced reference the bake is judged against (the continuous scene's radiance
//!   averaged over each patch, or at given points, not a discretisation's).
//!   [`direct::points`] evaluates the light at the outputs' own points (the baked vertices):
//!   the direct light by shadow rays from the point, the rest gathered from the solved patches.
//! - [`bake`]: a traced scene ready to solve, refine and relight any frame; its frames are
//!   solved on finer pieces of the patches and each patch answered by their mean
//!   ([`bake::Bake::split`]).
//! - [`adaptive`]: `patch_size=auto`, patches cut after tracing where the light needs them
//!   and merged where it does not (the cuts and merges themselves are [`scene::refine`]).
//! - [`output`]: what people use and look at: the baked glTF (the radiance evaluated at each
//!   vertex, with its error bar), PNG and GIF previews, the tone map.
//! - [`params`]: the rules on parameters that the CLI and the HTTP API share (the sky's
//!   `r,g,b`, a timeline's start and end), so the two front ends cannot disagree.
//! - [`service`]: the HTTP service (axum): jobs, their status and their frames.
//! - [`control`]: progress and cancellation of long work, shared by the bake command and the
//!   service.
//! - [`checked`]: files that carry their length and checksum, read back only when whole.
//! - [`batch`]: batch baking of scenes into files (`radiosity bake`).
//! - [`bench`](mod@bench): the measurements behind the README's figures (`radiosity bench`).
//! - [`samples`]: the generator of the sample scenes in `scenes/`.
//!
//! The method is described in `METHOD.md` (shared with the team) and the README.

pub mod adaptive;
pub mod bake;
pub mod batch;
pub mod bench;
pub mod checked;
pub mod control;
pub mod direct;
pub mod lines;
pub mod loader;
pub mod output;
pub mod params;
pub mod progress;
pub mod samples;
pub mod scene;
pub mod service;
pub mod solve;
pub mod timeline;
pub mod trace;

/// Asks for the `bytes` from `at` to be brought into cache: a hint, no effect on results.
#[inline]
pub(crate) fn prefetch<T>(at: &T, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // Every cache line the bytes touch: an object may straddle two.
        let base = std::ptr::from_ref(at).cast::<i8>();
        let mut offset = 0;
        while offset < bytes {
            // SAFETY: SSE is part of x86_64; a prefetch never faults, whatever the address.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(offset)) };
            offset += 64;
        }
        // SAFETY: as above; the last line, when the bytes straddle one more than they fill.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(bytes.saturating_sub(1))) };
    }
}
