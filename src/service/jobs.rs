//! Jobs: one timeline each, traced and solved off the async runtime, a bounded number at once.

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::time::{Instant, SystemTime};

use serde::Serialize;
use serde_json::json;
use serde_json::value::RawValue;
use tokio::sync::{Semaphore, watch};

use super::store::{Lighting, Record, Saved, Store, Traced, unix_seconds};
use crate::adaptive::{self, Adaptive};
use crate::bake::Bake;
use crate::control::{Control, Stop};
use crate::direct::area::Poses;
use crate::output::lightmap::Lightmap;
use crate::output::probes::ProbeGrid;
use crate::params::BakeSettings;
use crate::scene::{Material, Scene};
use crate::solve::{FrameSolution, NotConverged, SolveParams};
use crate::timeline::LineParams;

/// What a job's traced state was last rebuilt from when it was needed and not in memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rebuilt {
    /// Read back from the data directory (`traced.bin`), with any refinement it lacked traced.
    TracedState,
    /// Traced again from the stored scene.
    Scene,
}

impl Rebuilt {
    /// As the status document names it.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::TracedState => "traced_state",
            Self::Scene => "scene",
        }
    }
}

/// Where a job is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Waiting for a free slot.
    Queued,
    /// Tracing the lines.
    Tracing,
    /// Solving the frames.
    Solving,
    /// Every frame solved.
    Done,
    /// Stopped by an error (see the job's error).
    Failed,
    /// Stopped by a DELETE.
    Cancelled,
}

impl std::fmt::Display for Status {
    /// As the API writes it (`solving`), in messages as in documents.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Queued => "queued",
            Self::Tracing => "tracing",
            Self::Solving => "solving",
            Self::Done => "done",
            Self::Failed => "failed",
            Self::Cancelled => "cancelled",
        })
    }
}

impl Status {
    /// Whether the job will change no more.
    #[must_use]
    pub fn is_final(self) -> bool {
        matches!(self, Self::Done | Self::Failed | Self::Cancelled)
    }
}

/// Wall time of each stage, seconds.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct Timings {
    /// Loading and checking the scene.
    pub load: f64,
    /// Tracing and tallying the lines.
    pub trace: f64,
    /// Solving every frame.
    pub solve: f64,
}

/// The mutable part of a job.
#[derive(Debug)]
pub struct JobState {
    /// Where the job is.
    pub status: Status,
    /// Why it failed, if it did.
    pub error: Option<String>,
    /// Stage times.
    pub timings: Timings,
    /// Crossings stored and bytes of the list, once traced.
    pub memory: Option<(usize, usize)>,
    /// When the current stage started, for the ETA.
    pub stage_started: Instant,
    /// Seconds into the solving stage when its last frame was served, for the ETA.
    pub last_frame: Option<f64>,
    /// What the bake found that the user should know (coplanar overlaps, patches no line
    /// crossed), after the loader's warnings; renewed by every run.
    pub found: Vec<String>,
    /// When the job last ended (done, failed or cancelled), seconds since the Unix epoch.
    pub ended: Option<u64>,
}

/// A solved frame and the result version it belongs to.
pub type Versioned = (u64, Arc<FrameSolution>);

/// A solved frame as a job holds it.
#[derive(Clone, Debug)]
enum Held {
    /// In memory.
    Memory(Arc<FrameSolution>),
    /// Only in the data directory's `frames.bin` (dropped over the resident budget, or read
    /// back after a restart), read from there when served: its iteration count, if known, for
    /// the status document.
    Stored(Option<usize>),
}

/// A timeline job.
pub struct Job {
    /// Its id.
    pub id: String,
    /// The scene, until the bake takes it.
    scene: Mutex<Option<Scene>>,
    /// Frame times and patch count (kept when the scene moves into the bake).
    pub frame_times: Vec<f64>,
    /// Number of patches (those of the loaded scene until `auto` has cut them).
    pub patches: AtomicUsize,
    /// Loader warnings.
    pub warnings: Vec<String>,
    /// The patch table, as served (replaced when `auto` cuts the patches, before any frame is
    /// solved).
    /// Kept as its JSON text: a parsed document holds ten times the bytes, for every timeline.
    pub patch_table: RwLock<Arc<RawValue>>,
    /// Cut the patches after tracing where the light needs them (`patch_size=auto`).
    pub auto: Option<Adaptive>,
    /// Lines and seed asked for at creation.
    pub lines: LineParams,
    /// Lines asked for in all: at creation, and by every refinement since.
    pub lines_total: AtomicU64,
    /// How frames are solved: the sky's radiance, the tolerance and the iteration cap.
    pub solve: SolveParams,
    /// Largest reflectance the scene was loaded with; relighting may not go above it.
    pub max_reflectance: f64,
    /// Status, error, timings.
    state: Mutex<JobState>,
    /// Progress and cancellation of the tracing.
    pub control: Control,
    /// Frames of the current version solved so far (they are solved in order).
    pub frames_solved: AtomicUsize,
    /// Solved frames with the version they were solved for (a frame keeps its older version
    /// until the new one is solved).
    results: RwLock<Vec<Option<(u64, Held)>>>,
    /// The result version whose frames are in the data directory (0: none).
    saved_version: AtomicU64,
    /// When the job was posted, seconds since the Unix epoch.
    created: u64,
    /// Version of the result: 1, then one more for every refinement or relighting.
    version: AtomicU64,
    /// The traced scene, kept for refinement, relighting, statistics, previews and glTF; taken
    /// while it is traced (a bake's first trace, a refinement), read while frames are solved.
    bake: RwLock<Option<Bake>>,
    /// The materials the frames are solved with (the scene's, until relit).
    materials: Mutex<Vec<Material>>,
    /// The punctual lights' names and power (the scene's, until relit).
    lights: Mutex<Vec<LightSetting>>,
    /// Signals each newly solved frame (its count) and the end of the job.
    solved: watch::Sender<usize>,
    /// Where finished results are kept, if anywhere.
    store: Option<Store>,
    /// The request the job was posted with, when its scene is stored (in `store`): the traced
    /// state is then rebuilt from them whenever it is needed and not in memory.
    source: Option<BakeSettings>,
    /// Lines added by each refinement, in order.
    refinements: Mutex<Vec<u64>>,
    /// Times the job was started again after the server stopped while it ran.
    restarts: u32,
    /// Seconds the last rebuild of the traced state took, and what it was rebuilt from; its
    /// lock makes rebuilds one at a time.
    rebuilt: Mutex<Option<(f64, Rebuilt)>>,
    /// The lightmap last asked for ([`Job::lightmap`]), with its density's bits and the lines
    /// its traced state had; its lock makes lightmaps one at a time.
    lightmap: LastMade<(u64, u64), Lightmap>,
    /// The last light probe grid made (its spacing asked for, as bits; `None` the default),
    /// for the probes' route: the grid depends on the scene alone.
    probe_grid: LastMade<Option<u64>, ProbeGrid>,
    /// Whether the traced state in memory is the one in the data directory's `traced.bin`.
    traced_saved: AtomicBool,
    /// The timeline's exposure and the result version it is of, once every frame of that
    /// version is solved ([`Job::exposure`]).
    exposure: Mutex<Option<(u64, f64)>>,
    /// When the traced state was last used (the least recently used is dropped first).
    used: Mutex<Instant>,
}

/// `table` as JSON text.
fn raw_table(table: &serde_json::Value) -> Arc<RawValue> {
    let raw = serde_json::value::to_raw_value(table);
    Arc::from(raw.unwrap_or_else(|_| RawValue::NULL.to_owned()))
}

/// A punctual light as relighting sees it: its name and power.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct LightSetting {
    /// The light's name in the scene, if any.
    pub name: Option<String>,
    /// Linear RGB colour.
    pub colour: [f64; 3],
    /// Candela (point, spot) or lux (directional).
    pub intensity: f64,
}

impl LightSetting {
    /// Colour × intensity.
    #[must_use]
    pub fn power(&self) -> [f64; 3] {
        self.colour.map(|c| c * self.intensity)
    }
}

impl Job {
    /// A queued job for `scene`, loaded with `max_reflectance`.
    #[must_use]
    pub fn new(
        id: String,
        scene: Scene,
        lines: LineParams,
        solve: SolveParams,
        max_reflectance: f64,
        patch_table: serde_json::Value,
        store: Option<Store>,
    ) -> Self {
        let frame_times = (0..scene.frames.count)
            .map(|f| scene.frames.time(f))
            .collect::<Vec<_>>();
        let frames = frame_times.len();
        Self {
            id,
            version: AtomicU64::new(1),
            bake: RwLock::new(None),
            materials: Mutex::new(scene.materials.clone()),
            lights: Mutex::new(
                scene
                    .lights
                    .iter()
                    .map(|l| LightSetting {
                        name: l.name.clone(),
                        colour: l.colour,
                        intensity: l.intensity,
                    })
                    .collect(),
            ),
            patches: AtomicUsize::new(scene.patches.len()),
            warnings: scene.warnings.clone(),
            scene: Mutex::new(Some(scene)),
            frame_times,
            patch_table: RwLock::new(raw_table(&patch_table)),
            auto: None,
            lines_total: AtomicU64::new(lines.lines),
            lines,
            solve,
            max_reflectance,
            state: Mutex::new(JobState {
                status: Status::Queued,
                error: None,
                timings: Timings::default(),
                memory: None,
                stage_started: Instant::now(),
                last_frame: None,
                found: Vec::new(),
                ended: None,
            }),
            control: Control::default(),
            frames_solved: AtomicUsize::new(0),
            results: RwLock::new(vec![None; frames]),
            saved_version: AtomicU64::new(0),
            created: unix_seconds(SystemTime::now()),
            solved: watch::channel(0).0,
            store,
            source: None,
            refinements: Mutex::new(Vec::new()),
            restarts: 0,
            rebuilt: Mutex::new(None),
            lightmap: Mutex::new(None),
            probe_grid: Mutex::new(None),
            traced_saved: AtomicBool::new(false),
            exposure: Mutex::new(None),
            used: Mutex::new(Instant::now()),
        }
    }

    /// The same job, rebuilt when needed from its stored scene and `settings` (the scene is
    /// the store's to keep: [`Store::save_source`]).
    #[must_use]
    pub fn with_source(self, settings: BakeSettings) -> Self {
        Self {
            source: Some(settings),
            ..self
        }
    }

    /// The same job started again after the server stopped while it ran (its record
    /// `record`): the refinements asked for and the lighting are kept, a restart counted.
    #[must_use]
    pub fn resumed(self, record: &Record) -> Self {
        let lines = record.lines;
        let job = Self {
            version: AtomicU64::new(record.version),
            refinements: Mutex::new(record.refinements.clone()),
            restarts: record.restarts + 1,
            created: record.created.unwrap_or(self.created),
            lines_total: AtomicU64::new(lines),
            ..self
        };
        if let Some(lighting) = &record.lighting {
            job.set_lighting(lighting);
        }
        job
    }

    /// Replaces the materials and lights by `lighting`'s.
    fn set_lighting(&self, lighting: &Lighting) {
        if let (Ok(mut m), Ok(mut l)) = (self.materials.lock(), self.lights.lock()) {
            m.clone_from(&lighting.materials);
            l.clone_from(&lighting.lights);
        }
    }

    /// A job read back from the data directory ([`Store::load_all`]): `done` with its frames
    /// on disk, `failed` with its reason (`interrupted` if it had not finished; what is damaged
    /// if anything is), or `cancelled`.
    #[must_use]
    pub fn restored(saved: Saved, store: Option<Store>, source: Option<BakeSettings>) -> Self {
        let Saved { id, record, damage } = saved;
        let record = record.unwrap_or_else(|| Record {
            id: id.clone(),
            status: Status::Failed.to_string(),
            ..Record::default()
        });
        let interrupted = || "interrupted: the server stopped before the job finished".to_string();
        let (status, error) = match (damage, record.status.as_str()) {
            (Some(damage), _) => (Status::Failed, Some(damage)),
            (None, "done") => (Status::Done, None),
            (None, "cancelled") => (Status::Cancelled, None),
            (None, "failed") => (
                Status::Failed,
                record.error.clone().or_else(|| Some(interrupted())),
            ),
            (None, _) => (Status::Failed, Some(interrupted())),
        };
        let count = record.frame_times.len();
        let done = status == Status::Done;
        let results = match done {
            true => (0..count)
                .map(|f| {
                    let iterations = record.frame_iterations.get(f).copied().flatten();
                    Some((record.version, Held::Stored(iterations)))
                })
                .collect(),
            false => vec![None; count],
        };
        // A record from before jobs' ends were kept: its file's time.
        let ended = (record.ended)
            .or_else(|| Some(unix_seconds(store.as_ref()?.modified(&id)?)))
            .filter(|_| status.is_final());
        let job = Self {
            id,
            scene: Mutex::new(None),
            frame_times: record.frame_times,
            patches: AtomicUsize::new(record.patches),
            warnings: record.warnings,
            patch_table: RwLock::new(raw_table(&record.patch_table)),
            auto: None,
            lines: LineParams {
                lines: record.lines,
                seed: record.seed,
            },
            lines_total: AtomicU64::new(record.lines),
            solve: SolveParams {
                sky: record.sky,
                ..SolveParams::default()
            },
            max_reflectance: (source.as_ref())
                .map_or(crate::loader::MAX_REFLECTANCE, |s| s.load.max_reflectance),
            state: Mutex::new(JobState {
                status,
                error,
                timings: Timings {
                    load: record.timings[0],
                    trace: record.timings[1],
                    solve: record.timings[2],
                },
                memory: record.memory,
                stage_started: Instant::now(),
                last_frame: None,
                found: Vec::new(),
                ended,
            }),
            control: Control::default(),
            frames_solved: AtomicUsize::new(if done { count } else { 0 }),
            results: RwLock::new(results),
            saved_version: AtomicU64::new(if done { record.version } else { 0 }),
            created: record.created.unwrap_or_default(),
            version: AtomicU64::new(record.version),
            bake: RwLock::new(None),
            materials: Mutex::new(Vec::new()),
            lights: Mutex::new(Vec::new()),
            solved: watch::channel(if done { count } else { 0 }).0,
            store,
            refinements: Mutex::new(record.refinements),
            restarts: record.restarts,
            rebuilt: Mutex::new(None),
            lightmap: Mutex::new(None),
            probe_grid: Mutex::new(None),
            traced_saved: AtomicBool::new(false),
            exposure: Mutex::new(None),
            used: Mutex::new(Instant::now()),
            // Without its lighting, a job cannot be relit: it is not rebuilt either.
            source: source.filter(|_| record.lighting.is_some()),
        };
        if let Some(lighting) = &record.lighting {
            job.set_lighting(lighting);
        }
        job
    }

    /// The record of this job as it stands.
    #[must_use]
    pub fn record(&self) -> Record {
        let (status, error, timings, memory, ended) = match self.state.lock() {
            Ok(s) => (s.status, s.error.clone(), s.timings, s.memory, s.ended),
            Err(_) => (Status::Failed, None, Timings::default(), None, None),
        };
        Record {
            id: self.id.clone(),
            status: status.to_string(),
            error,
            version: self.version.load(Ordering::Acquire),
            frame_times: self.frame_times.clone(),
            frame_iterations: self.iterations(),
            patches: self.patches.load(Ordering::Acquire),
            warnings: self.warnings(),
            lines: self.lines_total.load(Ordering::Acquire),
            seed: self.lines.seed,
            sky: self.solve.sky,
            timings: [timings.load, timings.trace, timings.solve],
            memory,
            patch_table: serde_json::from_str(self.table().get()).unwrap_or_default(),
            refinements: self
                .refinements
                .lock()
                .map(|r| r.clone())
                .unwrap_or_default(),
            lighting: Some({
                let (materials, lights) = self.lighting();
                Lighting { materials, lights }
            }),
            restarts: self.restarts,
            created: Some(self.created),
            ended,
        }
    }

    /// Writes the record to the data directory, if there is one.
    ///
    /// # Errors
    /// It could not be written (the file before is left whole).
    pub fn persist(&self) -> std::io::Result<()> {
        match &self.store {
            Some(store) => store.save_record(&self.record()),
            None => Ok(()),
        }
    }

    /// [`Job::persist`], an error logged.
    pub fn persist_or_log(&self) {
        if let Err(e) = self.persist() {
            tracing::error!(id = %self.id, error = %e, "could not save the record");
        }
    }

    /// Writes the frames of the current version to the data directory, if there is one and
    /// they are all solved and not written yet.
    ///
    /// # Errors
    /// They could not be written (the file before is left whole).
    fn save_frames(&self) -> std::io::Result<()> {
        let Some(store) = &self.store else {
            return Ok(());
        };
        let version = self.version();
        if self.saved_version.load(Ordering::Acquire) == version {
            return Ok(());
        }
        let frames: Option<Vec<Arc<FrameSolution>>> = self.results.read().ok().and_then(|r| {
            (r.iter())
                .map(|f| match f {
                    Some((v, Held::Memory(s))) if *v == version => Some(s.clone()),
                    _ => None,
                })
                .collect()
        });
        let Some(frames) = frames else {
            return Ok(());
        };
        store.save_frames(
            &self.id,
            version,
            &frames.iter().map(AsRef::as_ref).collect::<Vec<_>>(),
        )?;
        self.saved_version.store(version, Ordering::Release);
        Ok(())
    }

    /// Solver iterations of each frame solved for the current version so far.
    fn iterations(&self) -> Vec<Option<usize>> {
        let version = self.version();
        let results = self.results.read().unwrap_or_else(PoisonError::into_inner);
        (results.iter())
            .map(|r| match r {
                Some((v, Held::Memory(s))) if *v == version => Some(s.iterations),
                Some((v, Held::Stored(iterations))) if *v == version => *iterations,
                _ => None,
            })
            .collect()
    }

    /// Current status.
    #[must_use]
    pub fn status(&self) -> Status {
        self.state.lock().map_or(Status::Failed, |s| s.status)
    }

    /// When the job last ended, seconds since the Unix epoch, if it has (when it was created,
    /// for one read back from a data directory that did not record it).
    #[must_use]
    pub fn ended(&self) -> Option<u64> {
        let state = self.state.lock().ok()?;
        state
            .status
            .is_final()
            .then(|| state.ended.unwrap_or(self.created))
    }

    /// Why the job failed, if it did.
    #[must_use]
    pub fn error(&self) -> Option<String> {
        let state = self.state.lock().ok()?;
        state
            .error
            .clone()
            .filter(|_| state.status == Status::Failed)
    }

    fn set_status(&self, status: Status) {
        if let Ok(mut s) = self.state.lock()
            && !s.status.is_final()
        {
            s.status = status;
            s.stage_started = Instant::now();
            s.last_frame = None;
        }
    }

    fn fail(&self, error: String) {
        if let Ok(mut s) = self.state.lock() {
            s.status = Status::Failed;
            s.error = Some(error);
            s.ended = Some(unix_seconds(SystemTime::now()));
        }
        self.persist_or_log();
        self.solved.send_modify(|_| {});
    }

    /// Marks the job `failed` because a file of its data directory is damaged (`error` says
    /// which and how): nothing is written, the files are kept as they are for inspection.
    fn damaged(&self, error: String) {
        tracing::error!(id = %self.id, %error, "a timeline's files are damaged");
        if let Ok(mut s) = self.state.lock() {
            s.status = Status::Failed;
            s.error = Some(error);
        }
        self.solved.send_modify(|_| {});
    }

    /// The same job cutting its patches after tracing as `auto` says (`patch_size=auto`).
    #[must_use]
    pub fn with_auto(self, auto: Option<Adaptive>) -> Self {
        Self { auto, ..self }
    }

    /// Records the seconds its scene took to load (its `timings`).
    pub fn loaded_in(&self, seconds: f64) {
        if let Ok(mut s) = self.state.lock() {
            s.timings.load = seconds;
        }
    }

    /// The patch table, as served.
    #[must_use]
    pub fn table(&self) -> Arc<RawValue> {
        let table = self.patch_table.read();
        table.map_or_else(|_| raw_table(&serde_json::Value::Null), |t| t.clone())
    }

    /// Asks a running job to stop; it ends `cancelled`.
    pub fn cancel(&self) {
        self.control.cancel();
        if let Ok(mut s) = self.state.lock()
            && !s.status.is_final()
        {
            s.status = Status::Cancelled;
            s.ended = Some(unix_seconds(SystemTime::now()));
        }
        self.solved.send_modify(|_| {});
    }

    /// The solution of `frame` and its version, if solved: from memory, or read from the data
    /// directory (a damaged file fails the job, and gives `None`).
    #[must_use]
    pub fn frame(&self, frame: usize) -> Option<Versioned> {
        // A rerun may replace the file between reading the slot and the file: then the slot
        // holds the new frame, in memory.
        for _ in 0..2 {
            let (version, held) = self.results.read().ok()?.get(frame)?.clone()?;
            if let Held::Memory(s) = held {
                return Some((version, s));
            }
            // A failed job's files are not read: one of them may be what failed it.
            let store = (self.store.as_ref()).filter(|_| self.status() != Status::Failed)?;
            match store.load_frame(&self.id, frame) {
                Ok((on_disk, s)) if on_disk == version => return Some((version, Arc::new(s))),
                Ok(_) => {}
                Err(e) => {
                    let kept = store.dir(&self.id);
                    self.damaged(format!("{e} (its files are kept in {})", kept.display()));
                    return None;
                }
            }
        }
        let kept = self.store.as_ref().map(|s| s.dir(&self.id));
        self.damaged(format!(
            "frames.bin is damaged: it holds another result version than its record's (its \
             files are kept in {})",
            kept.unwrap_or_default().display()
        ));
        None
    }

    /// The timeline's exposure: `of` every frame solved so far, kept once every frame of the
    /// current version is solved (frames dropped from memory are not read again for it).
    pub fn exposure(&self, of: impl FnOnce(&[Arc<FrameSolution>]) -> f64) -> f64 {
        let version = self.version();
        let kept = *self.exposure.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some((v, exposure)) = kept
            && v == version
        {
            return exposure;
        }
        let frames = self.frames();
        let every = (frames.iter()).all(|f| f.as_ref().is_some_and(|(v, _)| *v == version));
        let solved: Vec<Arc<FrameSolution>> =
            frames.into_iter().flatten().map(|(_, s)| s).collect();
        let exposure = of(&solved);
        if every {
            *self.exposure.lock().unwrap_or_else(PoisonError::into_inner) =
                Some((version, exposure));
        }
        exposure
    }

    /// Every frame's solution so far with its version (a frame keeps its older version until
    /// the new one is solved); those on disk are read.
    #[must_use]
    pub fn frames(&self) -> Vec<Option<Versioned>> {
        (0..self.frame_times.len()).map(|f| self.frame(f)).collect()
    }

    /// The version being solved or served: 1, then one more per refinement or relighting.
    #[must_use]
    pub fn version(&self) -> u64 {
        self.version.load(Ordering::Acquire)
    }

    /// A receiver woken at every newly solved frame and at the job's end.
    #[must_use]
    pub fn watch_solved(&self) -> watch::Receiver<usize> {
        self.solved.subscribe()
    }

    /// `read` applied to the traced scene, if it is kept and not being traced. A done job whose
    /// traced scene is not in memory (restored after a restart) has it rebuilt first from its
    /// stored scene, on the calling thread (one rebuild at a time; the others wait for it).
    pub fn with_bake<R>(&self, read: impl FnOnce(&Bake) -> R) -> Option<R> {
        if self.status() == Status::Done {
            self.ensure_traced().ok()?;
        }
        self.touch();
        self.bake.read().ok()?.as_ref().map(read)
    }

    /// The lightmap of `bake` (this job's traced state) at `texels_per_unit`, at most `most`
    /// texels: the one made last if it is of the same density and lines (a rebuilt traced state
    /// is the same; a refined one is not), else made now and kept in its place.
    ///
    /// # Errors
    /// [`Lightmap::within`]'s message.
    pub fn lightmap(
        &self,
        bake: &Bake,
        texels_per_unit: f64,
        most: f64,
    ) -> Result<Arc<Lightmap>, String> {
        let key = (
            texels_per_unit.to_bits(),
            self.lines_total.load(Ordering::Acquire),
        );
        last_made(&self.lightmap, key, || {
            Lightmap::within(bake, texels_per_unit, most)
        })
    }

    /// The light probe grid at `spacing` (`None`: the scene's default): the one made last if
    /// it is of the same spacing, else made now and kept in its place.
    ///
    /// # Errors
    /// [`ProbeGrid::new`]'s message.
    pub fn probe_grid(&self, bake: &Bake, spacing: Option<f64>) -> Result<Arc<ProbeGrid>, String> {
        let key = spacing.map(f64::to_bits);
        last_made(&self.probe_grid, key, || ProbeGrid::new(bake, spacing))
    }

    /// Marks the traced state used now.
    fn touch(&self) {
        if let Ok(mut used) = self.used.lock() {
            *used = Instant::now();
        }
    }

    /// Bytes of the traced state, if it is in memory.
    #[must_use]
    pub fn traced_bytes(&self) -> Option<usize> {
        self.bake.try_read().ok()?.as_ref().map(Bake::bytes)
    }

    /// Bytes of the solved frames in memory, if any is.
    #[must_use]
    pub fn solved_bytes(&self) -> Option<usize> {
        let results = self.results.try_read().ok()?;
        (results.iter().flatten())
            .filter_map(|(_, held)| match held {
                Held::Memory(s) => Some(s.bytes()),
                Held::Stored(_) => None,
            })
            .reduce(|a, b| a + b)
    }

    /// Drops the traced state of a done job that can trace it again, and its solved frames
    /// if they are in the data directory, where no one is using them; the bytes freed.
    fn evict(&self) -> Option<usize> {
        // Under the state lock, which reopening a job for more work takes: nothing is dropped
        // between a rerun's start and its use of it.
        let state = self.state.lock().ok()?;
        if state.status != Status::Done {
            return None;
        }
        let mut traced = 0;
        if self.source.is_some()
            && let Ok(mut slot) = self.bake.try_write()
            && let Some(bake) = slot.take()
        {
            traced = bake.bytes();
        }
        let mut solved = 0;
        if self.saved_version.load(Ordering::Acquire) == self.version()
            && let Ok(mut results) = self.results.try_write()
        {
            for (_, held) in results.iter_mut().flatten() {
                if let Held::Memory(s) = held {
                    solved += s.bytes();
                    *held = Held::Stored(Some(s.iterations));
                }
            }
        }
        drop(state);
        if traced + solved == 0 {
            return None;
        }
        tracing::info!(id = %self.id, traced, solved, "dropped from memory (over the resident budget)");
        Some(traced + solved)
    }

    /// Puts the traced state in its slot if it is not there, rebuilt from the stored scene
    /// (one rebuild at a time: another caller waits for it and finds it there).
    fn ensure_traced(&self) -> Result<(), Stop> {
        let in_slot = || self.bake.read().is_ok_and(|b| b.is_some());
        if self.source.is_none() || in_slot() {
            return Ok(());
        }
        let mut rebuilt = self.rebuilt.lock().unwrap_or_else(PoisonError::into_inner);
        if in_slot() {
            return Ok(());
        }
        let started = Instant::now();
        let (bake, from, refinements) = self.rebuild()?;
        let seconds = started.elapsed().as_secs_f64();
        tracing::info!(id = %self.id, seconds, from = from.as_str(), "rebuilt the traced scene");
        *rebuilt = Some((seconds, from));
        if from == Rebuilt::Scene {
            self.keep_traced(&bake, refinements);
        }
        // A refinement that started meanwhile found the slot empty and traced its own state,
        // with more lines: that one is kept.
        if let Ok(mut slot) = self.bake.write()
            && slot.is_none()
        {
            *slot = Some(bake);
        }
        Ok(())
    }

    /// Saves `bake`, which has the first `refinements` refinements, as the timeline's
    /// `traced.bin` unless it is there already (a failure is logged: the state can be traced
    /// again from the stored scene).
    fn keep_traced(&self, bake: &Bake, refinements: usize) {
        let Some(store) = self.store.as_ref().filter(|_| self.source.is_some()) else {
            return;
        };
        if self.traced_saved.load(Ordering::Acquire) {
            return;
        }
        let started = Instant::now();
        match store.save_traced(&self.id, refinements, bake) {
            Ok(bytes) => {
                let seconds = started.elapsed().as_secs_f64();
                tracing::info!(id = %self.id, bytes, seconds, "saved the traced state");
                self.traced_saved.store(bytes > 0, Ordering::Release);
            }
            Err(e) => tracing::warn!(
                id = %self.id, error = %e,
                "could not save the traced state: it will be traced again when it is needed"
            ),
        }
    }

    /// Whether a finished job can run again: its traced scene is kept, or can be rebuilt from
    /// its stored scene.
    #[must_use]
    pub fn can_rerun(&self) -> bool {
        self.status() != Status::Done
            || self.source.is_some()
            || self.bake.read().is_ok_and(|b| b.is_some())
    }

    /// Applies `change` to copies of the materials and lights the frames are solved with, and
    /// keeps them if it succeeds: a change that fails leaves both as they were. Meant as the
    /// change of [`Jobs::rerun`], which runs it under the job's state lock.
    pub fn change_lighting<E>(
        &self,
        change: impl FnOnce(&mut Vec<Material>, &mut Vec<LightSetting>) -> Result<(), E>,
    ) -> Result<(), E> {
        // A panic while they were held left them whole (they are only ever replaced).
        let mut materials = (self.materials.lock()).unwrap_or_else(PoisonError::into_inner);
        let mut lights = (self.lights.lock()).unwrap_or_else(PoisonError::into_inner);
        let (mut new_materials, mut new_lights) = (materials.clone(), lights.clone());
        change(&mut new_materials, &mut new_lights)?;
        *materials = new_materials;
        *lights = new_lights;
        Ok(())
    }

    /// The materials and lights the frames are solved with (empty for a job read back from a
    /// data directory written before they were recorded, which cannot be relit).
    #[must_use]
    pub fn lighting(&self) -> (Vec<Material>, Vec<LightSetting>) {
        let materials = (self.materials.lock()).unwrap_or_else(PoisonError::into_inner);
        let lights = (self.lights.lock()).unwrap_or_else(PoisonError::into_inner);
        (materials.clone(), lights.clone())
    }

    /// The loader's warnings, then what the last run found.
    #[must_use]
    pub fn warnings(&self) -> Vec<String> {
        let found = self
            .state
            .lock()
            .map(|s| s.found.clone())
            .unwrap_or_default();
        self.warnings.iter().cloned().chain(found).collect()
    }

    /// Does `work` to its end on the calling (blocking) thread.
    fn run(&self, work: Work) {
        let started = Instant::now();
        // The traced state for the solve: a new one (traced, refined or rebuilt), or `None`
        // for the one in its slot.
        let traced = match work {
            Work::Bake => {
                let scene = self.scene.lock().ok().and_then(|mut s| s.take());
                self.set_status(Status::Tracing);
                self.traced_saved.store(false, Ordering::Release);
                Some(match scene {
                    Some(scene) if self.restarts == 0 => self.trace(scene, &[]),
                    // Resumed after a restart: read back (if it had been traced, and refined
                    // since) or traced again.
                    _ => self.rebuild().map(|(bake, ..)| bake),
                })
            }
            Work::Refine(lines) => {
                self.set_status(Status::Tracing);
                self.traced_saved.store(false, Ordering::Release);
                // (Its lines are counted, and kept in the record, by [`Jobs::rerun`].)
                let taken = self.bake.write().ok().and_then(|mut b| b.take());
                Some(match taken {
                    Some(mut bake) => {
                        (bake.refine(lines, &self.control).map(|()| bake)).map_err(Stop::from)
                    }
                    // Not in memory: read back or traced again, this refinement included.
                    None => self.rebuild().map(|(bake, ..)| bake),
                })
            }
            Work::Relight => {
                if self.bake.read().is_ok_and(|b| b.is_none()) {
                    self.set_status(Status::Tracing);
                }
                match self.ensure_traced() {
                    Ok(()) => None,
                    Err(e) => Some(Err(e)),
                }
            }
        };
        let bake = match traced {
            None => None,
            Some(Ok(bake)) => {
                self.traced(&bake, started);
                Some(bake)
            }
            Some(Err(Stop::Cancelled)) => return,
            Some(Err(Stop::Failed(e))) => return self.fail(e),
        };
        // The traced scene is in its slot while the frames are solved (read, not taken), so
        // previews and glTF of the frames solved so far can be made meanwhile.
        if let Some(bake) = bake
            && let Ok(mut slot) = self.bake.write()
        {
            *slot = Some(bake);
        }
        let Ok(slot) = self.bake.read() else {
            return self.fail("the traced scene is unavailable".into());
        };
        let Some(bake) = slot.as_ref() else {
            return self.fail("the job has no traced scene".into());
        };
        if let Err(e) = self.solve_frames(bake) {
            drop(slot);
            // A failed job is not run again: its traced scene is not kept.
            self.bake.write().map(|mut b| b.take()).ok();
            return self.fail(e.to_string());
        }
        let frames: Vec<Arc<FrameSolution>> = self
            .frames()
            .into_iter()
            .flatten()
            .map(|(_, s)| s)
            .collect();
        let found = bake.findings(&frames);
        drop(slot);
        // The frames are on disk before the job is done: a failure to write them fails it.
        if let Err(e) = self.save_frames() {
            return self.fail(format!(
                "the solved frames could not be saved in the data directory: {e}"
            ));
        }
        // No one reruns the job before it is done: its state has every refinement listed.
        let refinements = self.refinements.lock().map_or(0, |r| r.len());
        if let Ok(slot) = self.bake.read()
            && let Some(bake) = slot.as_ref()
        {
            self.keep_traced(bake, refinements);
        }
        if let Ok(mut s) = self.state.lock() {
            s.found = found;
            if !s.status.is_final() {
                s.ended = Some(unix_seconds(SystemTime::now()));
            }
        }
        // On disk as done before anyone can see it done: a client that saw it done finds it
        // done after a crash, and no later write of this run can undo what it did with the
        // files since.
        if let Some(store) = self.store.as_ref().filter(|_| !self.status().is_final()) {
            let mut record = self.record();
            record.status = Status::Done.to_string();
            if let Err(e) = store.save_record(&record) {
                tracing::error!(id = %self.id, error = %e, "could not save the record");
            }
        }
        self.set_status(Status::Done);
        self.solved.send_modify(|_| {});
    }

    /// Traces `scene` as the job asks: its lines, `auto`'s cuts (the patch table replaced),
    /// the pieces, then each of `refinements` in order.
    fn trace(&self, scene: Scene, refinements: &[u64]) -> Result<Bake, Stop> {
        // A job read back from disk has its request's, for the scene as loaded.
        let auto = (self.auto)
            .or_else(|| (self.source.as_ref()).and_then(|s| s.adaptive(scene.patches.len())));
        let poses = Poses::for_bake(auto.is_some());
        let mut bake = Bake::trace_with(scene, (&self.lines, poses), &self.control)?;
        if let Some(auto) = &auto {
            adaptive::adapt(&mut bake, auto, &self.solve, &self.control)?;
            self.set_patches(&bake.scene);
        }
        bake.split(&self.solve, &self.control)?;
        for &lines in refinements {
            bake.refine(lines, &self.control)?;
        }
        Ok(bake)
    }

    /// The traced state rebuilt: read back from the data directory's `traced.bin` (the
    /// refinements it lacks traced), or traced again from the stored scene and request (the
    /// same lines, cuts, pieces and refinements, so the same tallies as when it was first
    /// traced: the lines are deterministic). With what it was rebuilt from and the number of
    /// refinements it has.
    fn rebuild(&self) -> Result<(Bake, Rebuilt, usize), Stop> {
        let Some(store) = &self.store else {
            return Err(Stop::Failed(
                "the job has no traced scene, and its scene is not stored".into(),
            ));
        };
        // What the record lists now: a refinement asked for later is traced by its own run.
        let refinements = self
            .refinements
            .lock()
            .map(|r| r.clone())
            .unwrap_or_default();
        let kept = || format!("(its files are kept in {})", store.dir(&self.id).display());
        let read = match store.load_traced(&self.id) {
            Ok(Traced::Read {
                bake,
                refinements: had,
            }) if had <= refinements.len() => {
                let mut bake = *bake;
                // A job resumed after a restart serves the patches its first run cut.
                if self.auto.is_some() {
                    self.set_patches(&bake.scene);
                }
                for &lines in &refinements[had..] {
                    bake.refine(lines, &self.control)?;
                }
                self.traced_saved
                    .store(had == refinements.len(), Ordering::Release);
                Some((bake, Rebuilt::TracedState))
            }
            // Of a refinement the record does not list (its record was not written).
            Ok(Traced::Read { .. }) => None,
            Ok(Traced::Missing) => None,
            Ok(Traced::OtherBuild) => {
                tracing::info!(id = %self.id, "traced.bin is another build's: traced again");
                None
            }
            Err(e) => {
                let reason = format!("{e} {}", kept());
                if e.kind() == std::io::ErrorKind::InvalidData {
                    self.damaged(reason.clone());
                }
                return Err(Stop::Failed(reason));
            }
        };
        let (bake, from) = match read {
            Some(read) => read,
            None => {
                self.traced_saved.store(false, Ordering::Release);
                let Some(settings) = &self.source else {
                    return Err(Stop::Failed(
                        "the job has no traced scene, and its scene is not stored".into(),
                    ));
                };
                let bytes = store.load_scene(&self.id).map_err(|e| {
                    let reason = format!("the stored scene cannot be read: {e} {}", kept());
                    if e.kind() == std::io::ErrorKind::InvalidData {
                        self.damaged(reason.clone());
                    }
                    Stop::Failed(reason)
                })?;
                let scene = crate::loader::load(&bytes, &settings.load)
                    .map_err(|e| Stop::Failed(format!("the stored scene does not load: {e}")))?;
                (self.trace(scene, &refinements)?, Rebuilt::Scene)
            }
        };
        // The frames solved are per patch: a rebuild that made other patches cannot serve them.
        let (made, expected) = (
            bake.scene.patches.len(),
            self.patches.load(Ordering::Acquire),
        );
        if made != expected {
            let what = match from {
                Rebuilt::TracedState => "the traced state read back",
                Rebuilt::Scene => "the stored scene, traced again,",
            };
            return Err(Stop::Failed(format!(
                "{what} has {made} patches, not the {expected} of its frames"
            )));
        }
        Ok((bake, from, refinements.len()))
    }

    /// Serves `scene`'s patches: `auto` cut them.
    fn set_patches(&self, scene: &Scene) {
        let table = crate::output::patch_table(scene);
        if let Ok(mut t) = self.patch_table.write() {
            *t = raw_table(&table);
        }
        (self.patches).store(scene.patches.len(), Ordering::Release);
    }

    /// Records what tracing took.
    fn traced(&self, bake: &Bake, started: Instant) {
        let memory = bake.list().memory();
        if let Ok(mut s) = self.state.lock() {
            s.timings.trace += started.elapsed().as_secs_f64();
            s.memory = Some((memory.hits(), bake.bytes()));
        }
    }

    /// Solves every frame for the current version as the bake command does
    /// ([`Bake::solve_frames`]: the same answers), a run per core at a time and in order, so
    /// that streams see the frames in order. A frame that does not converge stops the work:
    /// the frames before it are kept, it and those after are not.
    fn solve_frames(&self, bake: &Bake) -> Result<(), NotConverged> {
        self.set_status(Status::Solving);
        let started = Instant::now();
        let version = self.version.load(Ordering::Acquire);
        self.frames_solved.store(0, Ordering::Release);
        let params = self.solve;
        let materials = self.materials.lock().map(|m| m.clone()).unwrap_or_default();
        let power: Vec<[f64; 3]> = self
            .lights
            .lock()
            .map(|l| l.iter().map(LightSetting::power).collect())
            .unwrap_or_default();
        // The bake command's rule ([`Bake::solve_frames`]), a run per thread at a time, each
        // frame published as soon as it is served.
        let threads = rayon::current_num_threads();
        let mut failed = None;
        let solving = (&materials[..], &power[..], &params);
        bake.solve_frames(solving, (threads, &self.control), &|_| {}, |f, solution| {
            if let Err(e) = solution.ensure_converged(f, &params) {
                failed = Some(e);
                return ControlFlow::Break(());
            }
            if let Ok(mut results) = self.results.write() {
                results[f] = Some((version, Held::Memory(solution.clone())));
            }
            if let Ok(mut s) = self.state.lock() {
                s.last_frame = Some(s.stage_started.elapsed().as_secs_f64());
            }
            self.frames_solved.store(f + 1, Ordering::Release);
            self.solved.send_replace(f + 1);
            ControlFlow::Continue(())
        });
        if let Some(e) = failed {
            return Err(e);
        }
        if let Ok(mut s) = self.state.lock() {
            s.timings.solve += started.elapsed().as_secs_f64();
        }
        Ok(())
    }

    /// Makes the job run again (refinement or relighting) after `change`: a new version.
    fn reopen<E>(&self, change: impl FnOnce() -> Result<(), E>) -> Result<bool, E> {
        let Ok(mut s) = self.state.lock() else {
            return Ok(false);
        };
        if s.status != Status::Done {
            return Ok(false);
        }
        // Under the state lock: two requests cannot both change a done job, and a change that
        // fails leaves it done and as it was.
        change()?;
        s.status = Status::Queued;
        s.stage_started = Instant::now();
        s.last_frame = None;
        self.version.fetch_add(1, Ordering::AcqRel);
        self.frames_solved.store(0, Ordering::Release);
        Ok(true)
    }
}

/// What a job's next run does.
#[derive(Clone, Copy, Debug)]
pub enum Work {
    /// Trace and solve the timeline.
    Bake,
    /// Trace about this many more lines, then re-solve.
    Refine(u64),
    /// Re-solve with the job's (new) materials.
    Relight,
}

/// Which finished timelines are kept (by age, by count, or both); both `None`: all.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Retention {
    /// Days a timeline is kept after it ended.
    pub days: Option<f64>,
    /// Finished timelines kept, the most recently ended.
    pub count: Option<usize>,
}

/// The jobs of a server and the slots that bound how many run at once (cheap to clone: the
/// clones share them).
#[derive(Clone)]
pub struct Jobs {
    jobs: Arc<RwLock<HashMap<String, Arc<Job>>>>,
    /// Bytes of traced state and solved frames all jobs may hold
    /// ([`super::Config::resident_budget`]).
    budget: Option<u64>,
    /// Which finished timelines are kept.
    retention: Retention,
    /// Order of creation, for listing.
    order: Arc<Mutex<Vec<String>>>,
    slots: Arc<Semaphore>,
}

impl Jobs {
    /// An empty set running at most `running` jobs at once, their traced state and solved
    /// frames held within `budget` bytes, finished ones kept as `retention` says.
    #[must_use]
    pub fn new(running: usize, budget: Option<u64>, retention: Retention) -> Self {
        Self {
            jobs: Arc::new(RwLock::new(HashMap::new())),
            budget,
            retention,
            order: Arc::new(Mutex::new(Vec::new())),
            slots: Arc::new(Semaphore::new(running.max(1))),
        }
    }

    /// Registers `job` and starts it when a slot is free.
    pub fn start(&self, job: Arc<Job>) {
        self.insert(job.clone());
        job.persist_or_log();
        self.schedule(job, Work::Bake);
    }

    /// Registers a job without running it (one read back from the data directory).
    pub fn insert(&self, job: Arc<Job>) {
        if let (Ok(mut jobs), Ok(mut order)) = (self.jobs.write(), self.order.lock()) {
            order.push(job.id.clone());
            jobs.insert(job.id.clone(), job);
        }
    }

    /// Runs `work` on a finished job (a new version) after applying `change` to it; false if
    /// the job is not `done`, and the change's error (the job untouched) if it fails.
    pub fn rerun<E>(
        &self,
        job: Arc<Job>,
        work: Work,
        change: impl FnOnce() -> Result<(), E>,
    ) -> Result<bool, E> {
        if !job.reopen(change)? {
            return Ok(false);
        }
        if let Work::Refine(lines) = work {
            job.lines_total.fetch_add(lines, Ordering::AcqRel);
            if let Ok(mut r) = job.refinements.lock() {
                r.push(lines);
            }
        }
        // What was asked for is on disk before it runs: a restart resumes it.
        job.persist_or_log();
        self.schedule(job, work);
        Ok(true)
    }

    /// Starts a job read back from the data directory, which was queued or running when the
    /// server stopped ([`Job::resumed`]).
    pub fn resume(&self, job: Arc<Job>) {
        self.schedule(job, Work::Bake);
    }

    fn schedule(&self, job: Arc<Job>, work: Work) {
        let slots = self.slots.clone();
        let jobs = self.clone();
        tokio::spawn(async move {
            let Ok(_permit) = slots.acquire_owned().await else {
                return;
            };
            if job.status().is_final() {
                return;
            }
            let runner = job.clone();
            let run = move || super::panics::as_job(&runner.id, || runner.run(work));
            if let Err(e) = tokio::task::spawn_blocking(run).await {
                // Its panic is logged where it happened, with a backtrace
                // ([`super::panics::log_panics`]).
                let why = match e.try_into_panic() {
                    Ok(payload) => {
                        format!("it panicked: {}", crate::control::panic_message(&*payload))
                    }
                    Err(e) => e.to_string(),
                };
                tracing::error!(id = %job.id, %why, "the job failed");
                job.fail(format!("the job stopped unexpectedly: {why}"));
            }
            job.touch();
            jobs.enforce_budget();
            jobs.retain();
        });
    }

    /// Removes the finished timelines that `retention` does not keep: those ended more than
    /// its days ago, and those past its count (the most recently ended kept); each logged.
    pub fn retain(&self) {
        let Retention { days, count } = self.retention;
        if days.is_none() && count.is_none() {
            return;
        }
        let now = unix_seconds(SystemTime::now());
        let mut ended: Vec<(u64, String)> = (self.all().iter())
            .filter_map(|j| Some((j.ended()?, j.id.clone())))
            .collect();
        // Newest first; among equal times, the later created first.
        ended.reverse();
        ended.sort_by_key(|(at, _)| std::cmp::Reverse(*at));
        for (kept, (at, id)) in ended.into_iter().enumerate() {
            let age_days = now.saturating_sub(at) as f64 / 86_400.0;
            let reason = match (count, days) {
                (Some(count), _) if kept >= count => {
                    format!("past the {count} most recently ended timelines kept")
                }
                (_, Some(days)) if age_days > days => {
                    format!("ended {age_days:.2} days ago, past the {days} days kept")
                }
                _ => continue,
            };
            if self.remove(&id).is_some() {
                tracing::info!(%id, %reason, "removed a finished timeline (retention)");
            }
        }
    }

    /// Drops finished jobs' traced state and solved frames, least recently used first, until
    /// all jobs' fit the budget (running jobs' count, and are never dropped).
    pub fn enforce_budget(&self) {
        within_budget(&self.jobs, self.budget);
    }

    /// The retention the jobs are kept with.
    #[must_use]
    pub fn retention(&self) -> Retention {
        self.retention
    }

    /// The job with this id.
    #[must_use]
    pub fn get(&self, id: &str) -> Option<Arc<Job>> {
        self.jobs.read().ok()?.get(id).cloned()
    }

    /// Forgets a job (after cancelling it), on disk too: its directory is out of its place
    /// before anyone can see the job gone, and removed after.
    pub fn remove(&self, id: &str) -> Option<Arc<Job>> {
        let (job, aside) = {
            let mut jobs = self.jobs.write().ok()?;
            let job = jobs.remove(id)?;
            let aside = job.store.as_ref().and_then(|store| store.set_aside(id));
            (job, aside)
        };
        if let Some(dir) = aside
            && let Err(e) = Store::discard(&dir)
        {
            tracing::error!(id, error = %e, "could not remove the saved timeline");
        }
        if let Ok(mut order) = self.order.lock() {
            order.retain(|j| j != id);
        }
        Some(job)
    }

    /// Every job, oldest first.
    #[must_use]
    pub fn all(&self) -> Vec<Arc<Job>> {
        let order = self.order.lock().map(|o| o.clone()).unwrap_or_default();
        order.iter().filter_map(|id| self.get(id)).collect()
    }
}

/// [`Jobs::enforce_budget`] on `jobs`.
fn within_budget(jobs: &RwLock<HashMap<String, Arc<Job>>>, budget: Option<u64>) {
    let Some(budget) = budget else { return };
    let Ok(jobs) = jobs.read().map(|j| j.values().cloned().collect::<Vec<_>>()) else {
        return;
    };
    let mut held: Vec<(Instant, usize, &Arc<Job>)> = (jobs.iter())
        .filter_map(|j| {
            let bytes = j.traced_bytes().unwrap_or(0) + j.solved_bytes().unwrap_or(0);
            Some((*j.used.lock().ok()?, bytes, j)).filter(|_| bytes > 0)
        })
        .collect();
    let mut total: u64 = held.iter().map(|(_, b, _)| *b as u64).sum();
    held.sort_by_key(|(used, _, _)| *used);
    let mut evicted = false;
    for (_, _, job) in held {
        if total <= budget {
            break;
        }
        if let Some(freed) = job.evict() {
            total = total.saturating_sub(freed as u64);
            evicted = true;
        }
    }
    if evicted {
        give_back_memory();
    }
}

/// Returns the memory freed to the system: glibc's allocator keeps freed pages in its arenas
/// for reuse, so the resident memory would not go down (and grows with the arenas' scatter).
fn give_back_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` only releases free memory at the top of the heap and in the arenas;
    // it touches no live allocation.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// The seconds left of a stage that has done `done` of `total` like steps, the last ending
/// `at` seconds into it, now `now` seconds in: the steps left at the rate so far, counted down
/// while the next step takes longer than that, never below what the steps after it need. It
/// never climbs while a step stalls (the rate over the elapsed time did, at every poll).
pub(super) fn seconds_left((done, total): (usize, usize), at: f64, now: f64) -> f64 {
    let rate = at / done.max(1) as f64;
    let left = total.saturating_sub(done) as f64;
    (at + left * rate - now).max((left - 1.0).max(0.0) * rate)
}

impl Job {
    /// Its status document (`GET /v1/timelines/{id}`, the events stream).
    #[must_use]
    pub fn status_document(&self) -> serde_json::Value {
        let job = self;
        let (status, error, timings, memory, (stage_seconds, last_frame)) = match job.state.lock() {
            Ok(s) => (
                s.status,
                s.error.clone(),
                s.timings,
                s.memory,
                (s.stage_started.elapsed().as_secs_f64(), s.last_frame),
            ),
            Err(_) => (
                Status::Failed,
                Some("state unavailable".into()),
                Default::default(),
                None,
                (0.0, None),
            ),
        };
        let frames = job.frame_times.len();
        let solved = job.frames_solved.load(Ordering::Acquire);
        let fraction = job.control.fraction();
        // The control counts the work of the first trace and of every refinement since, in
        // proportion to their lines; a job read back from disk has traced all of its own.
        let lines_total = job.lines_total.load(Ordering::Acquire);
        let lines_traced = match status {
            Status::Done => lines_total,
            _ => (fraction * lines_total as f64).round() as u64,
        };
        let eta = match status {
            Status::Tracing if fraction > 0.0 => Some(stage_seconds * (1.0 - fraction) / fraction),
            Status::Solving if solved > 0 => {
                last_frame.map(|at| seconds_left((solved, frames), at, stage_seconds))
            }
            _ => None,
        };
        // The solves' iterations per frame, for the frames solved for the current version.
        let version = job.version();
        let iterations = job.iterations();
        let rebuilt = job.rebuilt.lock().ok().and_then(|r| *r);
        let mut doc = json!({
            "id": job.id,
            "status": status,
            "version": version,
            "progress": {
                "lines_traced": lines_traced,
                "lines_total": lines_total,
                "frames_solved": solved,
                "frames_total": frames,
                "eta_seconds": eta,
            },
            "frames": frames,
            "patches": job.patches.load(Ordering::Acquire),
            "iterations": iterations,
            "timings": timings,
            "memory": memory.map(|(hits, bytes)| {
                // The bake's, and the solved frames' kept for serving.
                json!({"hits": hits, "bytes": bytes + job.solved_bytes().unwrap_or(0)})
            }),
            "warnings": job.warnings(),
            "restarts": job.restarts,
            "rebuild_seconds": rebuilt.map(|(seconds, _)| seconds),
            "rebuilt_from": rebuilt.map(|(_, from)| from.as_str()),
            "traced_in_memory": job.bake.try_read().map_or(true, |b| b.is_some()),
            "solved_in_memory": job.solved_bytes().is_some(),
        });
        if let Some(error) = error {
            doc["error"] = json!(error);
        }
        doc
    }
}

/// The last value made, with the key it was made for.
type LastMade<K, V> = Mutex<Option<(K, Arc<V>)>>;

/// The value `kept` holds if it was made for `key`, else one `make` makes now, kept in its
/// place (a second caller waits for it rather than make it again).
fn last_made<K: PartialEq, V>(
    kept: &LastMade<K, V>,
    key: K,
    make: impl FnOnce() -> Result<V, String>,
) -> Result<Arc<V>, String> {
    let mut kept = kept.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some((k, value)) = kept.as_ref()
        && *k == key
    {
        return Ok(value.clone());
    }
    let value = Arc::new(make()?);
    *kept = Some((key, value.clone()));
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::{Status, seconds_left};

    #[test]
    fn a_status_reads_in_messages_as_in_documents() {
        for status in [
            Status::Queued,
            Status::Tracing,
            Status::Solving,
            Status::Done,
            Status::Failed,
            Status::Cancelled,
        ] {
            assert_eq!(
                serde_json::to_value(status).unwrap(),
                serde_json::Value::String(status.to_string())
            );
        }
    }

    #[test]
    fn the_eta_counts_down_and_holds_while_a_frame_stalls() {
        // 5 of 10 frames in 10 s, the last at 10 s: 2 s a frame, 10 s left.
        assert_eq!(seconds_left((5, 10), 10.0, 10.0), 10.0);
        assert_eq!(seconds_left((5, 10), 10.0, 11.0), 9.0);
        // Stalled on the sixth frame: it holds at what the four after it need, never climbs.
        let polls: Vec<f64> = (10..60)
            .map(|now| seconds_left((5, 10), 10.0, f64::from(now)))
            .collect();
        assert!(polls.windows(2).all(|w| w[1] <= w[0]), "{polls:?}");
        assert_eq!(polls.last(), Some(&8.0));
        // The last frame: down to 0, not below.
        assert_eq!(seconds_left((9, 10), 18.0, 100.0), 0.0);
        assert_eq!(seconds_left((10, 10), 20.0, 21.0), 0.0);
    }
}
