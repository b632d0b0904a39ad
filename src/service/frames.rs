//! A timeline's frames: one as JSON or binary, all as NDJSON while they are solved, and a
//! frame's preview image.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::Json;
use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::jobs::{Job, LightSetting};
use super::query::{
    BakedQuery, LightmapQuery, NoParameters, PreviewQuery, ProbesQuery, StrictQuery,
};
use super::{ApiError, AppState, job};
use crate::bake::Bake;
use crate::direct::points::Lighting;
use crate::output::lightmap::{Lightmap, Quantity};
use crate::solve::FrameSolution;

/// Binary layout of a frame (`Accept: application/octet-stream`), little-endian: u32 frame,
/// u32 patch count P, f64 time, then P×3 f32 radiance, P×3 f32 standard error (−1 where the
/// patch was not sampled), P u32 sample counts.
fn frame_binary(frame: usize, time: f64, s: &FrameSolution) -> Vec<u8> {
    let p = s.radiance.len();
    let mut out = Vec::with_capacity(16 + p * 28);
    out.extend_from_slice(&(frame as u32).to_le_bytes());
    out.extend_from_slice(&(p as u32).to_le_bytes());
    out.extend_from_slice(&time.to_le_bytes());
    s.write_f32(&mut out);
    out
}

/// The frame named by the path segment `frame`: its number, result version and solution; 404
/// if there is no such frame, 409 if it is not solved yet.
fn solved_frame(job: &Job, frame: &str) -> Result<(usize, u64, Arc<FrameSolution>), ApiError> {
    let frames = job.frame_times.len();
    let f = frame
        .parse::<usize>()
        .ok()
        .filter(|&f| f < frames)
        .ok_or_else(|| {
            ApiError::NotFound(match frames {
                0 => format!("no frame {frame:?}: the timeline has no frames"),
                1 => format!("no frame {frame:?}: the timeline has frame 0 only"),
                _ => format!(
                    "no frame {frame:?}: the timeline has frames 0 to {}",
                    frames - 1
                ),
            })
        })?;
    let (version, solution) = job.frame(f).ok_or_else(|| match job.error() {
        Some(error) => ApiError::NotReady(format!(
            "frame {f} is not served: the timeline failed: {error}"
        )),
        None => ApiError::NotReady(format!(
            "frame {f} is not solved yet (status {})",
            job.status()
        )),
    })?;
    Ok((f, version, solution))
}

pub(super) async fn timeline_frame(
    State(state): State<AppState>,
    Path((id, frame)): Path<(String, String)>,
    _: StrictQuery<NoParameters>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let (f, version, solution) = solved_frame(&job, &frame)?;
    let time = job.frame_times[f];
    let accept = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    if accept.contains("application/octet-stream") {
        let bytes = frame_binary(f, time, &solution);
        return Ok((
            [
                (header::CONTENT_TYPE, "application/octet-stream".to_string()),
                (
                    header::HeaderName::from_static("x-result-version"),
                    version.to_string(),
                ),
            ],
            Body::from(bytes),
        )
            .into_response());
    }
    Ok(Json(frame_json(f, time, version, &solution)).into_response())
}

/// `GET /v1/timelines/{id}/frames/{f}/preview.png?width=&height=&exposure=`: the frame
/// rendered from the scene's camera (or an automatic one), each patch flat-shaded with its
/// tone-mapped radiance; the same image as `radiosity bake`'s previews.
pub(super) async fn frame_preview(
    State(state): State<AppState>,
    Path((id, frame)): Path<(String, String)>,
    StrictQuery(query): StrictQuery<PreviewQuery>,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let super::query::Preview {
        size: (width, height),
        exposure,
        shading,
    } = query.validate()?;
    frame_file(
        (&state, job),
        &frame,
        exposure,
        "image/png",
        "a preview",
        move |bake, f, (solution, lighting), tone| {
            let meshes = crate::output::lit_geometry(bake, f, solution, lighting);
            let look = (tone, shading);
            let shown = (&meshes[..], &solution.radiance[..]);
            let image = crate::output::preview_image(bake.shown(), f, shown, look, width, height);
            crate::output::preview::encode_png(&image)
                .map_err(|e| ApiError::Internal(format!("making a preview: {e}")))
        },
    )
    .await
}

/// `GET /v1/timelines/{id}/frames/{f}/baked.glb?exposure=`: the frame as a binary glTF, the
/// same bytes as `radiosity bake` writes for it (per-vertex radiance, tone-mapped into the
/// vertex colours and kept in `_RADIANCE`).
pub(super) async fn frame_baked(
    State(state): State<AppState>,
    Path((id, frame)): Path<(String, String)>,
    StrictQuery(query): StrictQuery<BakedQuery>,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let exposure = query.validate()?;
    frame_file(
        (&state, job),
        &frame,
        exposure,
        "model/gltf-binary",
        "a glTF",
        |bake, f, (solution, lighting), tone| {
            let meshes = crate::output::lit_geometry(bake, f, solution, lighting);
            crate::output::frame_glb(bake.shown(), f, &meshes, tone)
                .map_err(|e| ApiError::Internal(format!("making a glTF: {e}")))
        },
    )
    .await
}

/// `GET /v1/timelines/{id}/frames/{f}/probes.json?spacing=`: the light probes at the frame, by
/// the grid and evaluation of `radiosity bake --probes` (its `probes.json` with the frame's
/// state file's `sh`, `stderr`, `irradiance_stderr` and `inside` beside it).
pub(super) async fn frame_probes(
    State(state): State<AppState>,
    Path((id, frame)): Path<(String, String)>,
    StrictQuery(query): StrictQuery<ProbesQuery>,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let spacing = query.validate()?;
    let times = job.frame_times.clone();
    let owner = job.clone();
    frame_file(
        (&state, job),
        &frame,
        None,
        "application/json",
        "the light probes",
        move |bake, f, (solution, lighting), _| {
            let grid = (owner.probe_grid(bake, spacing)).map_err(ApiError::Parameter)?;
            let probes = grid.probes(bake, f, (solution, lighting));
            let frames = json!([{ "frame": f, "time": times.get(f) }]);
            let mut document = grid.document(bake, frames);
            let state = crate::output::probes::ProbeGrid::state_document(&probes);
            if let (Some(document), serde_json::Value::Object(state)) =
                (document.as_object_mut(), state)
            {
                document.extend(state);
            }
            serde_json::to_vec(&document)
                .map_err(|e| ApiError::Internal(format!("writing the probes: {e}")))
        },
    )
    .await
}

/// Texels at most in a lightmap the service makes (a quarter of `radiosity bake`'s
/// [`crate::output::lightmap::MAX_TEXELS`]: a timeline keeps the last one it made in memory).
pub const SERVICE_MOST_TEXELS: f64 = 4_194_304.0;

/// A lightmap's file format.
#[derive(Clone, Copy, Debug)]
pub(super) enum LightmapFile {
    /// Linear half-float RGB OpenEXR.
    Exr,
    /// KTX2, RGBA16F, Zstandard.
    Ktx2,
    /// RGBM PNG.
    Png,
}

/// `GET /v1/timelines/{id}/frames/{f}/lightmap.{exr,ktx2,png}?texels_per_unit=&quantity=`: the
/// frame's lightmap (its radiance, or its light), the texels `radiosity bake --lightmaps`
/// writes for its lighting state, on the atlas of `GET /v1/timelines/{id}/lightmap.glb` at the
/// same density.
pub(super) async fn frame_lightmap(
    State(state): State<AppState>,
    Path((id, frame)): Path<(String, String)>,
    StrictQuery(query): StrictQuery<LightmapQuery>,
    file: LightmapFile,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let (density, quantity) = query.validate()?;
    let (content_type, what) = match file {
        LightmapFile::Exr => ("image/x-exr", "the lightmap's EXR"),
        LightmapFile::Ktx2 => ("image/ktx2", "the lightmap's KTX2"),
        LightmapFile::Png => ("image/png", "the lightmap's PNG"),
    };
    let owner = job.clone();
    frame_file(
        (&state, job),
        &frame,
        None,
        content_type,
        what,
        move |bake, f, (solution, lighting), _| {
            let lightmap = (owner.lightmap(bake, density, SERVICE_MOST_TEXELS))
                .map_err(ApiError::Parameter)?;
            let texels = lightmap.texels(bake, f, None, (solution, lighting));
            let texels = texels.holding(quantity);
            match file {
                LightmapFile::Exr => texels.exr(1.0),
                LightmapFile::Ktx2 => texels.ktx2(1.0),
                LightmapFile::Png => texels.rgbm_png(1.0),
            }
            .map_err(ApiError::Internal)
        },
    )
    .await
}

/// `GET /v1/timelines/{id}/lightmap.glb?texels_per_unit=`: the scene as drawn at its rest pose
/// with its lightmap coordinates in `TEXCOORD_1`, as `radiosity bake --lightmaps` writes
/// `lightmaps/scene.glb`.
pub(super) async fn timeline_lightmap_geometry(
    State(state): State<AppState>,
    Path(id): Path<String>,
    StrictQuery(query): StrictQuery<LightmapQuery>,
) -> Result<Response, ApiError> {
    let (density, _) = query.validate()?;
    let job = job(&state, &id)?;
    // The materials as relit: the light lightmap leaves out the surface's own albedo.
    let (materials, _) = job.lighting();
    let what = ("the lightmap's glTF", "model/gltf-binary");
    with_lightmap(&state, job, density, what, move |bake, lightmap| {
        crate::output::lightmap_glb(bake.shown(), &materials, lightmap, None)
            .map_err(|e| e.to_string())
    })
    .await
}

/// `GET /v1/timelines/{id}/lightmap.json?texels_per_unit=&quantity=`: the lightmaps'
/// manifest, as `radiosity bake --lightmaps` writes `lightmaps/manifest.json`, its files the
/// service's routes: every frame's time and lighting state (`state`, its first frame), and
/// that state's lightmap in each format, holding `quantity`.
pub(super) async fn timeline_lightmap_manifest(
    State(state): State<AppState>,
    Path(id): Path<String>,
    StrictQuery(query): StrictQuery<LightmapQuery>,
) -> Result<Response, ApiError> {
    let (density, quantity) = query.validate()?;
    let base = format!("/v1/timelines/{id}");
    let what = ("the lightmaps' manifest", "application/json");
    with_lightmap(
        &state,
        job(&state, &id)?,
        density,
        what,
        move |bake, lightmap| {
            let geometry = format!("{base}/lightmap.glb?texels_per_unit={density}");
            let query = match quantity {
                Quantity::Radiance => format!("?texels_per_unit={density}"),
                Quantity::Light => format!("?texels_per_unit={density}&quantity=light"),
            };
            let states = bake.representatives();
            let described = (geometry.as_str(), quantity);
            let manifest = lightmap.manifest(bake.shown(), described, &states, |r, kind| {
                format!("{base}/frames/{r}/lightmap.{kind}{query}")
            });
            serde_json::to_vec(&manifest).map_err(|e| e.to_string())
        },
    )
    .await
}

/// `make`'s file from `job`'s lightmap at `density` (its atlas made if the timeline does not
/// keep it), off the async runtime, served as `content_type`; `what` names the file in errors.
async fn with_lightmap(
    state: &AppState,
    job: Arc<Job>,
    density: f64,
    (what, content_type): (&'static str, &'static str),
    make: impl FnOnce(&Bake, &Lightmap) -> Result<Vec<u8>, String> + Send + 'static,
) -> Result<Response, ApiError> {
    let _budget = Enforce(state);
    let made = tokio::task::spawn_blocking(move || {
        job.with_bake(|bake| {
            let lightmap =
                (job.lightmap(bake, density, SERVICE_MOST_TEXELS)).map_err(ApiError::Parameter)?;
            make(bake, &lightmap).map_err(|e| ApiError::Internal(format!("making {what}: {e}")))
        })
    })
    .await
    .map_err(|e| ApiError::Internal(format!("making {what}: {e}")))?;
    let bytes = made.ok_or_else(|| {
        ApiError::NotReady(
            "the timeline's geometry is not available: it is being traced (try again once \
             frames are being solved)"
                .into(),
        )
    })??;
    Ok(([(header::CONTENT_TYPE, content_type)], Body::from(bytes)).into_response())
}

/// Keeps the traced state within the resident budget when dropped (at the end of a route
/// that may have rebuilt a timeline's).
pub(super) struct Enforce<'a>(pub &'a AppState);

impl Drop for Enforce<'_> {
    fn drop(&mut self) {
        self.0.0.jobs.enforce_budget();
    }
}

/// Solved frame `frame` of `job` made into a file by `make` (from the scene as shown, the
/// frame, its radiance and the tone map of `exposure` or, if none, the timeline's), served as
/// `content_type` with the result's version and the exposure; `what` names the file in errors.
async fn frame_file(
    (state, job): (&AppState, Arc<Job>),
    frame: &str,
    exposure: Option<f64>,
    content_type: &str,
    what: &str,
    make: impl FnOnce(
        &Bake,
        usize,
        (&FrameSolution, Lighting<'_>),
        &crate::output::ToneMap,
    ) -> Result<Vec<u8>, ApiError>
    + Send
    + 'static,
) -> Result<Response, ApiError> {
    let (f, version, solution) = solved_frame(&job, frame)?;
    // The traced state may be rebuilt for this file: the budget is kept when it is made.
    let _budget = Enforce(state);
    let asked = job.clone();
    let made = tokio::task::spawn_blocking(move || {
        job.with_bake(|bake| {
            let tone = tone_map(&job, bake, exposure);
            // The light at the vertices, with the materials and lights the frame was solved
            // with (the scene's for a job that recorded none).
            let (mut materials, lights) = job.lighting();
            if materials.is_empty() {
                materials.clone_from(&bake.scene.materials);
            }
            let power: Vec<[f64; 3]> = if lights.is_empty() {
                bake.light_power()
            } else {
                lights.iter().map(LightSetting::power).collect()
            };
            let lighting = Lighting {
                materials: &materials,
                power: &power,
                sky: job.solve.sky,
            };
            (make(bake, f, (&solution, lighting), &tone), tone.exposure)
        })
    })
    .await
    .map_err(|e| ApiError::Internal(format!("making {what}: {e}")))?;
    let Some((bytes, exposure)) = made else {
        if let Some(error) = asked.error() {
            return Err(ApiError::NotReady(format!(
                "{what} of frame {f} is not made: the timeline failed: {error}"
            )));
        }
        return Err(ApiError::NotReady(
            "the timeline's geometry is not available: it is being traced (a bake's first \
             trace or a refinement: try again once frames are being solved), or it was restored \
             from a data directory written before scenes were stored with their timelines (post \
             the scene again)"
                .into(),
        ));
    };
    let bytes = bytes?;
    Ok((
        [
            (header::CONTENT_TYPE, content_type.to_string()),
            (
                header::HeaderName::from_static("x-result-version"),
                version.to_string(),
            ),
            (
                header::HeaderName::from_static("x-exposure"),
                exposure.to_string(),
            ),
        ],
        Body::from(bytes),
    )
        .into_response())
}

/// The tone map asked for, or the timeline's: its exposure from every frame solved so far.
fn tone_map(job: &Job, bake: &Bake, exposure: Option<f64>) -> crate::output::ToneMap {
    match exposure {
        Some(exposure) => crate::output::ToneMap { exposure },
        None => crate::output::ToneMap {
            exposure: job.exposure(|solved| {
                crate::output::ToneMap::for_timeline(bake.shown(), solved).exposure
            }),
        },
    }
}

/// A frame as JSON.
fn frame_json(frame: usize, time: f64, version: u64, s: &FrameSolution) -> serde_json::Value {
    json!({
        "frame": frame,
        "time": time,
        "version": version,
        "radiance": s.radiance,
        "stderr": s.stderr,
        "samples": s.samples,
        "converged": s.converged,
    })
}

/// `GET /v1/timelines/{id}/frames` as NDJSON: one line per frame, in order, each sent as soon
/// as it is solved; the stream ends with the last frame (or when the job stops).
pub(super) async fn timeline_frames(
    State(state): State<AppState>,
    Path(id): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let solved = job.watch_solved();
    let stream = futures_util::stream::unfold(
        (job, solved, 0usize),
        |(job, mut solved, next)| async move {
            loop {
                // The status before the frames: a job seen ended has stored all it will.
                let ended = job.status().is_final();
                let version = job.version();
                let available = job.frames_solved.load(Ordering::Acquire);
                if next < available
                    && let Some((v, s)) = job.frame(next).filter(|(v, _)| *v == version)
                {
                    let mut line =
                        serde_json::to_vec(&frame_json(next, job.frame_times[next], v, &s))
                            .unwrap_or_default();
                    line.push(b'\n');
                    return Some((
                        Ok::<_, std::convert::Infallible>(line),
                        (job, solved, next + 1),
                    ));
                }
                if next >= job.frame_times.len() || (ended && next >= available) {
                    return None;
                }
                if solved.changed().await.is_err() {
                    return None;
                }
            }
        },
    );
    Ok((
        [(header::CONTENT_TYPE, "application/x-ndjson")],
        Body::from_stream(stream),
    )
        .into_response())
}
