//! The service's own pages: `GET /` (the timelines, a glTF file dropped or a sample picked to
//! bake) and `GET /v1/timelines/{id}/viewer` (a timeline in 3D, frame by frame, as its frames
//! are solved). One page does both; it and its script are in the binary, so the viewer needs no
//! network beyond this service. It draws with WebGL2 from the baked glTF of each frame
//! (`baked.glb`): radiance per vertex, tone-mapped as the files are, and a patch per triangle
//! for the error and sample overlays and for picking.
//!
//! Also here, for the page and for other clients: the sample scenes (`GET /v1/samples`) and the
//! materials and lights a timeline is solved with (`GET /v1/timelines/{id}/materials`).

use std::sync::OnceLock;

use axum::Json;
use axum::extract::{Path, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::query::{NoParameters, StrictQuery, ViewerQuery};
use super::{ApiError, AppState, job};
use crate::samples::Sample;

/// The page, the same for `/` and for a timeline's viewer (its script reads the path).
const PAGE: &str = include_str!("viewer/index.html");

/// The page's assets, by name: content and media type.
const ASSETS: [(&str, &str, &str); 2] = [
    (
        "viewer.js",
        include_str!("viewer/viewer.js"),
        "text/javascript; charset=utf-8",
    ),
    (
        "viewer.css",
        include_str!("viewer/viewer.css"),
        "text/css; charset=utf-8",
    ),
];

/// The page, which loads nothing from elsewhere (its content security policy says so too).
fn page() -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (
                header::CONTENT_SECURITY_POLICY,
                "default-src 'self'; img-src 'self' data: blob:; connect-src 'self'",
            ),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        PAGE,
    )
        .into_response()
}

/// `GET /`: the home page.
pub(super) async fn home(_: StrictQuery<NoParameters>) -> Response {
    page()
}

/// `GET /v1/timelines/{id}/viewer`: the timeline's viewer (the page; `?frame=&exposure=` are
/// the script's to read).
pub(super) async fn timeline_viewer(
    State(state): State<AppState>,
    Path(id): Path<String>,
    StrictQuery(query): StrictQuery<ViewerQuery>,
) -> Result<Response, ApiError> {
    query.validate()?;
    job(&state, &id)?;
    Ok(page())
}

/// `GET /viewer/{file}`: the page's script and style sheet.
pub(super) async fn asset(
    Path(file): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Response, ApiError> {
    let (_, content, media) = ASSETS
        .iter()
        .find(|(name, _, _)| *name == file)
        .ok_or_else(|| ApiError::NotFound(format!("no asset {file:?}")))?;
    Ok((
        [
            (header::CONTENT_TYPE, *media),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        *content,
    )
        .into_response())
}

/// The sample scenes, generated once.
fn samples() -> &'static [Sample] {
    static SAMPLES: OnceLock<Vec<Sample>> = OnceLock::new();
    SAMPLES.get_or_init(crate::samples::all)
}

/// `GET /v1/samples`: the sample scenes' names and descriptions.
pub(super) async fn list_samples(_: StrictQuery<NoParameters>) -> Json<serde_json::Value> {
    let samples: Vec<_> = samples()
        .iter()
        .map(|s| json!({"name": s.file_name, "description": s.description}))
        .collect();
    Json(json!({ "samples": samples }))
}

/// `GET /v1/samples/{name}`: one sample scene's glTF.
pub(super) async fn sample(
    Path(name): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Response, ApiError> {
    let sample = samples()
        .iter()
        .find(|s| s.file_name == name)
        .ok_or_else(|| {
            let names: Vec<&str> = samples().iter().map(|s| s.file_name).collect();
            ApiError::NotFound(format!(
                "no sample {name:?}; the samples are {}",
                names.join(", ")
            ))
        })?;
    Ok((
        [(header::CONTENT_TYPE, "model/gltf+json")],
        sample.gltf.clone(),
    )
        .into_response())
}

/// `GET /v1/timelines/{id}/materials`: the materials and punctual lights the frames are solved
/// with (the scene's, as relit since), by index as `POST` takes them.
pub(super) async fn timeline_materials(
    State(state): State<AppState>,
    Path(id): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let job = job(&state, &id)?;
    let (materials, lights) = job.lighting();
    let materials: Vec<_> = (materials.iter().enumerate())
        .map(|(i, m)| {
            json!({
                "index": i,
                "name": m.name,
                "emission": m.emission,
                "reflectance": m.reflectance,
            })
        })
        .collect();
    let lights: Vec<_> = (lights.iter().enumerate())
        .map(|(i, l)| {
            json!({"index": i, "name": l.name, "intensity": l.intensity, "color": l.colour})
        })
        .collect();
    Ok(Json(json!({ "materials": materials, "lights": lights })))
}
