//! The HTTP service: POST a glTF animation, fetch per-frame radiosity.
//!
//! `app` builds the router (tests drive it over a real socket); `serve` runs it until a
//! shutdown signal. Heavy work runs on blocking threads, at most `max_running` jobs at once; the
//! rest wait `queued`. Every error is `application/problem+json` with a 4xx for bad input. Each
//! route reads its query string into a struct of `query` that refuses parameters it does not
//! take.

mod error;
mod frames;
mod jobs;
mod panics;
mod query;
mod relight;
mod store;
mod viewer;

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde_json::json;

pub use error::ApiError;
pub use jobs::Retention;
use jobs::{Job, Jobs, Status, Work};
use query::{NoParameters, RefineQuery, StatsQuery, StrictQuery};

use crate::loader;
use crate::params::{BakeRequest, Limits};
use crate::scene::Scene;
use crate::solve::SolveParams;

/// Server settings.
#[derive(Clone, Debug)]
pub struct Config {
    /// Largest accepted body, bytes: larger ones get 413 without being read.
    pub max_body_bytes: usize,
    /// Jobs traced or solved at once; the others wait `queued`.
    pub max_running: usize,
    /// Memory one job may use (estimated before tracing), bytes.
    pub memory_budget: u64,
    /// What one job may ask for (lines, frames, patches): the command line's too.
    pub limits: Limits,
    /// Where finished results are kept across restarts; `None` keeps them in memory only.
    pub data_dir: Option<std::path::PathBuf>,
    /// Iteration cap of each frame's solve (`SolveParams::max_iterations`): a frame that
    /// reaches it fails its job.
    pub max_iterations: usize,
    /// Bytes of traced state (lines, tallies, direct light) all timelines may hold: over it,
    /// finished timelines' traced state is dropped, least recently used first, and traced again
    /// from the stored scene when needed (only timelines whose scene is stored: with a data
    /// directory). `None`: no limit. Solved frames count too: over it, those of finished
    /// timelines are dropped from memory and served from the data directory.
    pub resident_budget: Option<u64>,
    /// Which finished timelines are kept (in memory and on disk): by age, by count, or both.
    pub retention: Retention,
    /// Whether traced state is written to the data directory, to be read back instead of
    /// traced again when it is needed and not in memory.
    pub traced_files: bool,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            max_body_bytes: 64 << 20,
            max_running: 1,
            memory_budget: 8 << 30,
            limits: Limits::default(),
            data_dir: None,
            max_iterations: SolveParams::default().max_iterations,
            resident_budget: None,
            retention: Retention::default(),
            traced_files: true,
        }
    }
}

/// What the handlers share.
struct Shared {
    config: Config,
    jobs: Jobs,
    store: Option<store::Store>,
    /// Jobs to start again when the server starts serving.
    pending: std::sync::Mutex<Vec<Arc<Job>>>,
}

/// The server's state: cheap to clone.
#[derive(Clone)]
pub struct AppState(Arc<Shared>);

impl AppState {
    /// A server, with the timelines saved in the data directory: finished ones `done`; those
    /// that were queued or running start again from their stored scene when [`serve`] starts
    /// (or, without one, come back `failed`: interrupted).
    pub fn new(config: Config) -> std::io::Result<Self> {
        let jobs = Jobs::new(config.max_running, config.resident_budget, config.retention);
        let store = config
            .data_dir
            .as_deref()
            .map(store::Store::open)
            .transpose()?
            .map(|s| s.with_traced_files(config.traced_files));
        let mut pending = Vec::new();
        if let Some(store) = &store {
            for mut saved in store.load_all() {
                // (A damaged request is in `saved.damage` already.)
                let source = (store.load_query(&saved.id).ok().flatten())
                    .and_then(|query| settings_of(&query, &config.limits));
                let unfinished = (saved.record.as_ref()).filter(|r| {
                    saved.damage.is_none()
                        && ["queued", "tracing", "solving"].contains(&r.status.as_str())
                });
                if let (Some(record), Some(settings)) = (unfinished, &source) {
                    match resumed(store, record, settings, &config) {
                        Ok(job) => {
                            let job = Arc::new(job);
                            jobs.insert(job.clone());
                            pending.push(job);
                            continue;
                        }
                        Err(damage) => saved.damage = Some(damage),
                    }
                }
                if let Some(damage) = &saved.damage {
                    tracing::error!(id = %saved.id, %damage, "a timeline's files are damaged");
                }
                let damaged = saved.damage.is_some();
                let job = Arc::new(Job::restored(saved, Some(store.clone()), source));
                if !damaged && job.status() == Status::Failed {
                    // Interrupted, with no scene to start again from: said so on disk too.
                    job.persist_or_log();
                }
                jobs.insert(job);
            }
        }
        Ok(Self(Arc::new(Shared {
            config,
            jobs,
            store,
            pending: std::sync::Mutex::new(pending),
        })))
    }

    /// Starts the jobs to resume (once).
    fn resume_pending(&self) {
        let pending =
            std::mem::take(&mut *self.0.pending.lock().unwrap_or_else(|e| e.into_inner()));
        for job in pending {
            tracing::info!(id = %job.id, "resuming a job the server stopped while it ran");
            job.persist_or_log();
            self.0.jobs.resume(job);
        }
    }
}

/// The settings of a stored request's query string, as they were checked when it was posted
/// (with today's limits).
fn settings_of(query: &str, limits: &Limits) -> Option<crate::params::BakeSettings> {
    let uri: axum::http::Uri = format!("/?{query}").parse().ok()?;
    let axum::extract::Query(request) =
        axum::extract::Query::<BakeRequest>::try_from_uri(&uri).ok()?;
    request.validate(limits).ok()
}

/// The job of `record`, which was queued or running when the server stopped, made again from
/// its stored scene and request, with the refinements and lighting it had been asked for; what
/// stops it if its scene cannot be read or loaded.
fn resumed(
    store: &store::Store,
    record: &store::Record,
    settings: &crate::params::BakeSettings,
    config: &Config,
) -> Result<Job, String> {
    let kept = format!(
        " (its files are kept in {})",
        store.dir(&record.id).display()
    );
    let bytes = store
        .load_scene(&record.id)
        .map_err(|e| format!("{e}{kept}"))?;
    let scene = loader::load(&bytes, &settings.load)
        .map_err(|e| format!("the stored scene does not load: {e}{kept}"))?;
    let auto = settings.adaptive(scene.patches.len());
    let table = crate::output::patch_table(&scene);
    let solve = SolveParams {
        sky: settings.sky,
        max_iterations: config.max_iterations,
        ..SolveParams::default()
    };
    let job = Job::new(
        record.id.clone(),
        scene,
        settings.lines,
        solve,
        settings.load.max_reflectance,
        table,
        Some(store.clone()),
    );
    Ok(job
        .with_auto(auto)
        .with_source(settings.clone())
        .resumed(record))
}

/// The router.
pub fn app(state: AppState) -> Router {
    let limit = state.0.config.max_body_bytes;
    Router::new()
        .route("/", get(viewer::home))
        .route("/viewer/{*file}", get(viewer::asset))
        .route("/healthz", get(healthz))
        .route("/v1/samples", get(viewer::list_samples))
        .route("/v1/samples/{name}", get(viewer::sample))
        .route("/v1/timelines/{id}/viewer", get(viewer::timeline_viewer))
        .route(
            "/v1/timelines/{id}/lightmapped",
            get(viewer::timeline_lightmapped),
        )
        .route("/v1/timelines", get(list_timelines).post(create_timeline))
        .route(
            "/v1/timelines/{id}",
            get(timeline_status).delete(delete_timeline),
        )
        .route("/v1/timelines/{id}/patches", get(timeline_patches))
        .route("/v1/timelines/{id}/frames", get(frames::timeline_frames))
        .route(
            "/v1/timelines/{id}/lines",
            axum::routing::post(refine_timeline),
        )
        .route(
            "/v1/timelines/{id}/materials",
            get(viewer::timeline_materials).post(relight::relight_timeline),
        )
        .route("/v1/timelines/{id}/stats", get(timeline_stats))
        .route("/v1/timelines/{id}/events", get(timeline_events))
        .route("/openapi.json", get(openapi))
        .route(
            "/v1/timelines/{id}/frames/{frame}",
            get(frames::timeline_frame),
        )
        .route(
            "/v1/timelines/{id}/frames/{frame}/preview.png",
            get(frames::frame_preview),
        )
        .route(
            "/v1/timelines/{id}/frames/{frame}/baked.glb",
            get(frames::frame_baked),
        )
        .route(
            "/v1/timelines/{id}/frames/{frame}/probes.json",
            get(frames::frame_probes),
        )
        .route(
            "/v1/timelines/{id}/lightmap.glb",
            get(frames::timeline_lightmap_geometry),
        )
        .route(
            "/v1/timelines/{id}/lightmap.json",
            get(frames::timeline_lightmap_manifest),
        )
        .route(
            "/v1/timelines/{id}/frames/{frame}/lightmap.exr",
            get(|s, p, q| frames::frame_lightmap(s, p, q, frames::LightmapFile::Exr)),
        )
        .route(
            "/v1/timelines/{id}/frames/{frame}/lightmap.ktx2",
            get(|s, p, q| frames::frame_lightmap(s, p, q, frames::LightmapFile::Ktx2)),
        )
        .route(
            "/v1/timelines/{id}/frames/{frame}/lightmap.png",
            get(|s, p, q| frames::frame_lightmap(s, p, q, frames::LightmapFile::Png)),
        )
        .fallback(|| async { ApiError::NotFound("no such path".into()) })
        .layer(DefaultBodyLimit::max(limit))
        .layer(axum::middleware::from_fn(
            move |request: axum::extract::Request, next: axum::middleware::Next| {
                declared_length_within(limit, request, next)
            },
        ))
        .layer(
            tower_http::trace::TraceLayer::new_for_http()
                .make_span_with(
                    tower_http::trace::DefaultMakeSpan::new().level(tracing::Level::INFO),
                )
                .on_response(
                    tower_http::trace::DefaultOnResponse::new().level(tracing::Level::INFO),
                ),
        )
        .with_state(state)
}

/// Serves `app` on `listener` until `shutdown` completes, then lets requests in flight finish.
pub async fn serve(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    panics::log_panics();
    state.resume_pending();
    // Retention by age is applied every minute, and by count (and age) whenever a job ends.
    let jobs = state.0.jobs.clone();
    let sweep = tokio::spawn(async move {
        let mut every = tokio::time::interval(std::time::Duration::from_secs(60));
        loop {
            every.tick().await;
            let jobs = jobs.clone();
            let _ = tokio::task::spawn_blocking(move || jobs.retain()).await;
        }
    });
    let served = axum::serve(listener, app(state))
        .with_graceful_shutdown(shutdown)
        .await;
    sweep.abort();
    served
}

fn new_id() -> String {
    use rand::RngExt;
    let mut rng = rand::rng();
    format!("{:016x}", rng.random::<u64>())
}

/// `GET /healthz`: liveness, and what the service holds: its resident memory, the traced
/// state and solved frames in memory against the budget, the timelines (how many have their
/// traced state or frames in memory, how many are in the data directory), the data
/// directory's size and the retention it is kept with.
async fn healthz(
    State(state): State<AppState>,
    _: StrictQuery<NoParameters>,
) -> Json<serde_json::Value> {
    let jobs = state.0.jobs.all();
    let traced: Vec<usize> = jobs.iter().filter_map(|j| j.traced_bytes()).collect();
    let solved: Vec<usize> = jobs.iter().filter_map(|j| j.solved_bytes()).collect();
    let store = state.0.store.clone();
    let on_disk = if store.is_some() { jobs.len() } else { 0 };
    let data_bytes = tokio::task::spawn_blocking(move || store.map(|s| s.bytes()))
        .await
        .ok()
        .flatten();
    let retention = state.0.jobs.retention();
    Json(json!({
        "status": "ok",
        "memory": {
            "resident_bytes": resident_bytes(),
            "traced_bytes": traced.iter().sum::<usize>(),
            "solved_bytes": solved.iter().sum::<usize>(),
            "budget_bytes": state.0.config.resident_budget,
        },
        "timelines": {
            "total": jobs.len(),
            "traced_in_memory": traced.len(),
            "solved_in_memory": solved.len(),
            "on_disk": on_disk,
        },
        "data_dir_bytes": data_bytes,
        "retention": {"days": retention.days, "count": retention.count},
    }))
}

/// Refuses a request whose declared length is over `limit` before any of its body is read: a
/// client streaming a large upload gets the 413 at once instead of after the first `limit`
/// bytes (bodies without a declared length are cut by the body limit as they are read).
async fn declared_length_within(
    limit: usize,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Result<Response, ApiError> {
    let declared = request
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit as u64) {
        return Err(ApiError::TooLarge(limit));
    }
    Ok(next.run(request).await)
}

/// The process's resident memory (Linux's `/proc/self/statm`, 4 KiB pages), if known.
fn resident_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096)
}

async fn create_timeline(
    State(state): State<AppState>,
    StrictQuery(request): StrictQuery<BakeRequest>,
    uri: axum::http::Uri,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<Response, ApiError> {
    let config = &state.0.config;
    let settings = request.validate(&config.limits)?;
    let (options, lines, sky) = (settings.load.clone(), settings.lines, settings.sky);
    gltf_media(&headers)?;
    let body = body.map_err(|e| match e.status() {
        StatusCode::PAYLOAD_TOO_LARGE => ApiError::TooLarge(config.max_body_bytes),
        _ => ApiError::Parameter(format!("the body could not be read: {e}")),
    })?;
    let started = Instant::now();
    let max_reflectance = options.max_reflectance;
    let posted = body.clone();
    let scene = tokio::task::spawn_blocking(move || loader::load(&body, &options))
        .await
        .map_err(|e| ApiError::Internal(format!("loader task: {e}")))??;
    let auto = settings.adaptive(scene.patches.len());
    within_budget(config, &scene, lines.lines, auto.map(|a| a.budget))?;
    let id = new_id();
    let table = crate::output::patch_table(&scene);
    let solve = SolveParams {
        sky,
        max_iterations: config.max_iterations,
        ..SolveParams::default()
    };
    let mut job = Job::new(
        id.clone(),
        scene,
        lines,
        solve,
        max_reflectance,
        table,
        state.0.store.clone(),
    )
    .with_auto(auto);
    // The scene and request are stored first, so the job can be traced again after a restart
    // (or once its traced state is dropped).
    if let Some(store) = state.0.store.clone() {
        let (key, query) = (id.clone(), uri.query().unwrap_or("").to_string());
        let saved =
            tokio::task::spawn_blocking(move || store.save_source(&key, &posted, &query)).await;
        match saved {
            Ok(Ok(())) => job = job.with_source(settings),
            Ok(Err(e)) => {
                tracing::error!(%id, error = %e, "could not store the scene");
                let removed = state.0.store.as_ref().map(|s| s.remove(&id));
                if let Some(Err(e)) = removed {
                    tracing::error!(%id, error = %e, "could not remove what was stored");
                }
                return Err(ApiError::Storage(format!(
                    "the scene could not be stored in the service's data directory ({e}): \
                     nothing was accepted"
                )));
            }
            Err(e) => return Err(ApiError::Internal(format!("storing the scene: {e}"))),
        }
    }
    let job = Arc::new(job);
    job.loaded_in(started.elapsed().as_secs_f64());
    let body = json!({
        "id": id,
        "status": job.status(),
        "frames": job.frame_times.len(),
        "patches": job.patches.load(Ordering::Acquire),
        "warnings": job.warnings(),
    });
    state.0.jobs.start(job);
    let location = format!("/v1/timelines/{id}");
    Ok((
        StatusCode::ACCEPTED,
        [(header::LOCATION, location)],
        Json(body),
    )
        .into_response())
}

/// Refuses a body that is not glTF by its content type.
fn gltf_media(headers: &HeaderMap) -> Result<(), ApiError> {
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let media = content_type.split(';').next().unwrap_or("").trim();
    if media == "model/gltf-binary" || media == "model/gltf+json" {
        Ok(())
    } else {
        Err(ApiError::ContentType(format!(
            "content type {content_type:?}: send model/gltf-binary (.glb) or model/gltf+json (.gltf)"
        )))
    }
}

/// Refuses a job whose memory, estimated before tracing ([`crate::bake::estimate_bytes`]),
/// is over `config`'s budget.
fn within_budget(
    config: &Config,
    scene: &Scene,
    lines: u64,
    budget: Option<usize>,
) -> Result<(), ApiError> {
    let needed = crate::bake::estimate_bytes(scene, lines, budget);
    if needed <= config.memory_budget {
        return Ok(());
    }
    let gib = |bytes: u64| bytes as f64 / f64::from(1 << 30);
    Err(ApiError::Budget(format!(
        "the job would need about {:.1} GiB with {lines} lines, over the budget of {:.1} GiB: use \
         fewer lines, fewer frames or a larger patch_size",
        gib(needed),
        gib(config.memory_budget)
    )))
}

fn job(state: &AppState, id: &str) -> Result<Arc<Job>, ApiError> {
    state
        .0
        .jobs
        .get(id)
        .ok_or_else(|| ApiError::NotFound(format!("no timeline {id:?}")))
}

async fn timeline_status(
    State(state): State<AppState>,
    Path(id): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let job = job(&state, &id)?;
    Ok(Json(job.status_document()))
}

async fn list_timelines(
    State(state): State<AppState>,
    _: StrictQuery<NoParameters>,
) -> Json<serde_json::Value> {
    let timelines: Vec<_> = state
        .0
        .jobs
        .all()
        .iter()
        .map(|j| json!({"id": j.id, "status": j.status()}))
        .collect();
    Json(json!({ "timelines": timelines }))
}

/// `DELETE /v1/timelines/{id}`: a queued or running timeline is cancelled (it stays, with
/// status `cancelled` and the frames solved before, until deleted again); a finished one
/// (done, failed or cancelled) is deleted with its saved results.
async fn delete_timeline(
    State(state): State<AppState>,
    Path(id): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<StatusCode, ApiError> {
    let job = job(&state, &id)?;
    if job.status().is_final() {
        state.0.jobs.remove(&id);
    } else {
        job.cancel();
    }
    Ok(StatusCode::NO_CONTENT)
}

async fn timeline_patches(
    State(state): State<AppState>,
    Path(id): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Response, ApiError> {
    let table = job(&state, &id)?.table();
    Ok((
        [(header::CONTENT_TYPE, "application/json")],
        table.get().to_owned(),
    )
        .into_response())
}

/// The answer to a refinement or relighting: the job runs again for a new version.
fn rerun(
    state: &AppState,
    job: Arc<Job>,
    work: Work,
    change: impl FnOnce() -> Result<(), ApiError>,
) -> Result<Response, ApiError> {
    if !job.can_rerun() {
        return Err(ApiError::NotReady(format!(
            "timeline {} was restored from a data directory written before scenes were stored \
             with their timelines: it cannot be traced again, so it cannot be refined or relit; \
             post the scene again",
            job.id
        )));
    }
    if !state.0.jobs.rerun(job.clone(), work, change)? {
        return Err(ApiError::NotReady(format!(
            "timeline {} is {}: refine or relight it once it is done",
            job.id,
            job.status()
        )));
    }
    let body = json!({"id": job.id, "status": job.status(), "version": job.version()});
    Ok((StatusCode::ACCEPTED, Json(body)).into_response())
}

/// `POST /v1/timelines/{id}/lines?add=N`: trace about N more lines and re-solve.
async fn refine_timeline(
    State(state): State<AppState>,
    Path(id): Path<String>,
    StrictQuery(query): StrictQuery<RefineQuery>,
) -> Result<Response, ApiError> {
    let job = job(&state, &id)?;
    let add = query.validate(&state.0.config)?;
    rerun(&state, job, Work::Refine(add), || Ok(()))
}

/// `GET /v1/timelines/{id}/stats?frame=f`: the scene statistics measured by the lines.
async fn timeline_stats(
    State(state): State<AppState>,
    Path(id): Path<String>,
    StrictQuery(query): StrictQuery<StatsQuery>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let job = job(&state, &id)?;
    let (frame, patches) = query.validate(job.frame_times.len())?;
    let _budget = frames::Enforce(&state);
    if !job.can_rerun() {
        return Err(ApiError::NotReady(format!(
            "timeline {id} was restored from a data directory written before scenes were \
             stored with their timelines: its lines cannot be traced again, so their statistics \
             cannot be measured; post the scene again"
        )));
    }
    let stats = tokio::task::spawn_blocking(move || {
        job.with_bake(|bake| {
            let stats =
                crate::timeline::stats::SceneStats::measure(&bake.scene, bake.list(), frame);
            let mut stats = serde_json::to_value(stats).ok()?;
            stats["information"] =
                serde_json::to_value(bake.information(frame).report(patches)).ok()?;
            Some(stats)
        })
        .flatten()
    })
    .await
    .map_err(|e| ApiError::Internal(format!("stats task: {e}")))?
    .ok_or_else(|| {
        ApiError::NotReady(
            "the timeline is not traced yet, or busy: try again when it is done".into(),
        )
    })?;
    Ok(Json(stats))
}

/// `GET /v1/timelines/{id}/events`: Server-Sent Events, a `status` event with the status
/// document whenever a frame is solved or the job changes stage, and at least every second;
/// the stream ends when the job does.
async fn timeline_events(
    State(state): State<AppState>,
    Path(id): Path<String>,
    _: StrictQuery<NoParameters>,
) -> Result<Response, ApiError> {
    use axum::response::sse::{Event, KeepAlive, Sse};
    let job = job(&state, &id)?;
    let solved = job.watch_solved();
    let stream = futures_util::stream::unfold(
        (job, solved, false),
        |(job, mut solved, ended)| async move {
            if ended {
                return None;
            }
            // The status before the document: a job ending in between sends one more event
            // (the final document), never a final event with an older document.
            let last = job.status().is_final();
            let doc = job.status_document();
            let event = Event::default()
                .event("status")
                .json_data(&doc)
                .unwrap_or_else(|_| Event::default().event("status"));
            if !last {
                // Wake on the next solved frame or stage change, or after a second for progress.
                let _ =
                    tokio::time::timeout(std::time::Duration::from_secs(1), solved.changed()).await;
            }
            Some((
                Ok::<_, std::convert::Infallible>(event),
                (job, solved, last),
            ))
        },
    );
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::default())
        .into_response())
}

/// The OpenAPI description of this service (the file checked in as `api/openapi.json`).
pub const OPENAPI: &str = include_str!("../../api/openapi.json");

async fn openapi(_: StrictQuery<NoParameters>) -> Response {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI).into_response()
}
