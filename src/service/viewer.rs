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

use super::query::{LightmappedQuery, NoParameters, StrictQuery, ViewerQuery};
use super::{ApiError, AppState, job};
use crate::samples::Sample;

/// The page, the same for `/` and for a timeline's viewer (its script reads the path).
const PAGE: &str = include_str!("viewer/index.html");

/// The three.js example's page (`GET /v1/timelines/{id}/lightmapped`).
const LIGHTMAPPED: &str = include_str!("viewer/lightmapped.html");

/// JavaScript's media type.
const JS: &str = "text/javascript; charset=utf-8";

/// The pages' assets, by path under `/viewer/`: content and media type. Under `three/`,
/// three.js (the npm package `three`, at the version `.ci/run` checks these against: its build
/// and the example loaders the three.js page imports).
const ASSETS: [(&str, &str, &str); 12] = [
    ("viewer.js", include_str!("viewer/viewer.js"), JS),
    (
        "viewer.css",
        include_str!("viewer/viewer.css"),
        "text/css; charset=utf-8",
    ),
    ("lightmapped.js", include_str!("viewer/lightmapped.js"), JS),
    (
        "lightmapped.css",
        include_str!("viewer/lightmapped.css"),
        "text/css; charset=utf-8",
    ),
    (
        "three/three.module.min.js",
        include_str!("viewer/three/three.module.min.js"),
        JS,
    ),
    (
        "three/three.core.min.js",
        include_str!("viewer/three/three.core.min.js"),
        JS,
    ),
    (
        "three/addons/loaders/GLTFLoader.js",
        include_str!("viewer/three/addons/loaders/GLTFLoader.js"),
        JS,
    ),
    (
        "three/addons/loaders/EXRLoader.js",
        include_str!("viewer/three/addons/loaders/EXRLoader.js"),
        JS,
    ),
    (
        "three/addons/libs/fflate.module.js",
        include_str!("viewer/three/addons/libs/fflate.module.js"),
        JS,
    ),
    (
        "three/addons/utils/BufferGeometryUtils.js",
        include_str!("viewer/three/addons/utils/BufferGeometryUtils.js"),
        JS,
    ),
    (
        "three/addons/controls/OrbitControls.js",
        include_str!("viewer/three/addons/controls/OrbitControls.js"),
        JS,
    ),
    (
        "three/LICENSE",
        include_str!("viewer/three/LICENSE"),
        "text/plain; charset=utf-8",
    ),
];

/// A page of ours under the content security policy `policy`.
fn html(content: &'static str, policy: &str) -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CONTENT_SECURITY_POLICY, policy),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        content,
    )
        .into_response()
}

/// The page, which loads nothing from elsewhere (its content security policy says so too).
fn page() -> Response {
    html(
        PAGE,
        "default-src 'self'; img-src 'self' data: blob:; connect-src 'self'",
    )
}

/// The three.js example's page. Its content security policy admits its import map (by its
/// hash) and nothing from elsewhere.
fn lightmapped_page() -> Response {
    static POLICY: OnceLock<String> = OnceLock::new();
    let policy = POLICY.get_or_init(|| {
        use base64::Engine as _;
        use sha2::Digest as _;
        let map = (LIGHTMAPPED.split_once("<script type=\"importmap\">"))
            .and_then(|(_, rest)| rest.split_once("</script>"))
            .map_or("", |(map, _)| map);
        let hash = base64::engine::general_purpose::STANDARD.encode(sha2::Sha256::digest(map));
        format!(
            "default-src 'self'; script-src 'self' 'sha256-{hash}'; img-src 'self' data: blob:; \
             connect-src 'self'"
        )
    });
    html(LIGHTMAPPED, policy)
}

/// `GET /v1/timelines/{id}/lightmapped`: the three.js example (`?frame=&orbit=&exposure=` for
/// its first view, `?texels_per_unit=&probe_spacing=` passed on to the lightmap's and probes'
/// routes): the timeline's lightmaps by frame time on its lightmapped geometry, its moving
/// nodes lit from the light probes.
pub(super) async fn timeline_lightmapped(
    State(state): State<AppState>,
    Path(id): Path<String>,
    StrictQuery(query): StrictQuery<LightmappedQuery>,
) -> Result<Response, ApiError> {
    query.validate()?;
    job(&state, &id)?;
    Ok(lightmapped_page())
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

/// `GET /viewer/{file}`: the pages' scripts and style sheets, and three.js (`three/...`,
/// which changes only with the binary: cached for a day).
pub(super) async fn asset(
    Path(file): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Response, ApiError> {
    let (_, content, media) = ASSETS
        .iter()
        .find(|(name, _, _)| *name == file)
        .ok_or_else(|| ApiError::NotFound(format!("no asset {file:?}")))?;
    let cache = if file.starts_with("three/") {
        "max-age=86400"
    } else {
        "no-cache"
    };
    Ok((
        [
            (header::CONTENT_TYPE, *media),
            (header::CACHE_CONTROL, cache),
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
