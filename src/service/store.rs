//! Finished results on disk, so that a restart loses nothing and damage is never served.
//!
//! Each timeline has a directory `DATA/{id}/` with
//! - `scene.bin` and `request.json`: the scene as posted and the request's query string,
//!   written when the job is accepted, from which the job is traced again when its traced
//!   state is needed and not in memory (lines are deterministic, so the same state);
//! - `job.json`: what the status and patch endpoints serve, the frame times, the refinements
//!   asked for, the materials and lights as relit, and when the job was created and ended;
//! - once done, `frames.bin`: every frame's radiance, standard error (−1 where unsampled) and
//!   samples, little-endian f64/u64, so that the numbers served after a restart are
//!   bit-identical; a frame is read alone (at a fixed offset) when it is served from disk;
//! - once traced, `traced.bin`: the traced state (the intersection list, tallies, scenes as cut,
//!   direct light; [`Bake::write_bytes`]) with the refinements it has, read back instead of
//!   tracing again when the state is needed and not in memory. Only the build that wrote it
//!   reads it (the encoding does not describe itself); another build traces again from
//!   `scene.bin` and writes its own.
//!
//! Every file is checked: `scene.bin`, `request.json`, `job.json` and `traced.bin` start with a
//! 24-byte header (`RADSTOR1`, the payload's length as u64, its CRC-32 as u32, 4 zero bytes; the
//! JSON follows it as it is); `frames.bin` starts with a 40-byte header (`RADFRMS2`, frames,
//! patches and result version as u64, the CRC-32 of those 32 bytes, 4 zero bytes) and ends each
//! frame with its CRC-32. A file that does not match is reported with what is wrong, never read as
//! numbers. Files of data directories written before (plain JSON, a raw scene, the first frames
//! layout) are read as they are; frames in the first layout are rewritten in this one.
//!
//! Files are written to a temporary name, flushed to the disk, and renamed: a crash or a full
//! disk leaves the previous file whole. At start-up, finished timelines come back `done`; the
//! others start again from their stored scene (or, from a data directory written before scenes
//! were stored, come back `failed` with the reason `interrupted`).

use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::PoisonError;
use std::time::SystemTime;

use serde::{Deserialize, Serialize};

use crate::bake::Bake;
use crate::checked::{Stamp, checked, damaged, payload, sealed, stamped, unstamped, write_whole};
use crate::solve::FrameSolution;

/// The kind of `traced.bin` ([`stamped`]); the refinements its state has (u64) follow the
/// stamp.
const TRACED: &[u8; 8] = b"RADTRCD1";
/// First bytes of `frames.bin`.
const FRAMES: &[u8; 8] = b"RADFRMS2";
/// Bytes of `frames.bin`'s header.
const FRAMES_HEADER: usize = 40;
/// Bytes of a patch in a frame of `frames.bin`: radiance, standard error (f64 RGB each) and
/// samples (u64).
const STORED_PER_PATCH: usize = 56;
/// What a timeline's directory is renamed to begin with while it is removed
/// ([`Store::set_aside`]); no timeline's id begins so.
const SET_ASIDE: &str = ".removing-";

/// What `job.json` holds.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Record {
    /// Timeline id.
    pub id: String,
    /// Last status written.
    pub status: String,
    /// Why the job failed, if it did.
    #[serde(default)]
    pub error: Option<String>,
    /// Result version of the frames on disk.
    pub version: u64,
    /// Time of each frame.
    pub frame_times: Vec<f64>,
    /// Solver iterations of each frame solved (for the status document, without reading the
    /// frames).
    #[serde(default)]
    pub frame_iterations: Vec<Option<usize>>,
    /// Patch count.
    pub patches: usize,
    /// Loader warnings.
    pub warnings: Vec<String>,
    /// Lines asked for.
    pub lines: u64,
    /// Seed of the lines.
    pub seed: u64,
    /// Radiance of the sky.
    pub sky: [f64; 3],
    /// Stage times.
    pub timings: [f64; 3],
    /// Crossings and bytes of the list.
    pub memory: Option<(usize, usize)>,
    /// The patch table.
    pub patch_table: serde_json::Value,
    /// Lines added by each refinement, in order (in `lines` too).
    #[serde(default)]
    pub refinements: Vec<u64>,
    /// The materials and lights the frames are solved with (the scene's, as relit since).
    #[serde(default)]
    pub lighting: Option<Lighting>,
    /// How many times the job was started again after the server stopped while it ran.
    #[serde(default)]
    pub restarts: u32,
    /// When the job was posted, seconds since the Unix epoch.
    #[serde(default)]
    pub created: Option<u64>,
    /// When the job last ended (done, failed or cancelled), seconds since the Unix epoch.
    #[serde(default)]
    pub ended: Option<u64>,
}

/// Seconds since the Unix epoch of `time`.
#[must_use]
pub fn unix_seconds(time: SystemTime) -> u64 {
    time.duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// Materials and lights as a job solves with them.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Lighting {
    /// Per material, in the scene's order.
    pub materials: Vec<crate::scene::Material>,
    /// Per punctual light, in the scene's order.
    pub lights: Vec<super::jobs::LightSetting>,
}

/// What `request.json` holds.
#[derive(Serialize, Deserialize)]
struct Request {
    /// The query string of the `POST`, as sent.
    query: String,
}

/// A timeline found in the data directory.
#[derive(Debug)]
pub struct Saved {
    /// Its id (its directory's name).
    pub id: String,
    /// Its record, unless `job.json` is damaged.
    pub record: Option<Record>,
    /// What is damaged, if anything: the timeline is then served as `failed` with this reason.
    pub damage: Option<String>,
}

/// What [`Store::load_traced`] found.
pub enum Traced {
    /// No traced state on disk.
    Missing,
    /// A traced state written by another build, which this one cannot read.
    OtherBuild,
    /// The traced state, and how many of the timeline's refinements it has.
    Read {
        /// The state, its tracers built again.
        bake: Box<Bake>,
        /// Refinements it has (the first ones of the record's).
        refinements: usize,
    },
}

/// Bytes of one frame of `patches` patches in `frames.bin`.
fn frame_bytes(patches: usize) -> usize {
    8 + 8 + 1 + patches * STORED_PER_PATCH + 4
}

/// The header of `frames.bin`: frames, patches, version.
fn frames_header(frames: usize, patches: usize, version: u64) -> [u8; FRAMES_HEADER] {
    let mut out = [0; FRAMES_HEADER];
    out[..8].copy_from_slice(FRAMES);
    out[8..16].copy_from_slice(&(frames as u64).to_le_bytes());
    out[16..24].copy_from_slice(&(patches as u64).to_le_bytes());
    out[24..32].copy_from_slice(&version.to_le_bytes());
    let crc = crc32fast::hash(&out[..32]);
    out[32..36].copy_from_slice(&crc.to_le_bytes());
    out
}

/// Frames, patches and version read from the header of `frames.bin`.
fn read_frames_header(header: &[u8]) -> std::io::Result<(usize, usize, u64)> {
    let name = "frames.bin";
    if header.len() < FRAMES_HEADER || !header.starts_with(FRAMES) {
        return Err(damaged(name, "its header is not that of a frames file"));
    }
    let word = |at: usize| u64::from_le_bytes(header[at..at + 8].try_into().unwrap_or_default());
    let crc = u32::from_le_bytes(header[32..36].try_into().unwrap_or_default());
    if crc32fast::hash(&header[..32]) != crc || header[36..FRAMES_HEADER] != [0; 4] {
        return Err(damaged(name, "its header's checksum does not match"));
    }
    let count = |n: u64| usize::try_from(n).map_err(|_| damaged(name, "a count is out of range"));
    Ok((count(word(8))?, count(word(16))?, word(24)))
}

/// Frame `s` as `frames.bin` holds it, its checksum last.
fn encode_frame(s: &FrameSolution, out: &mut Vec<u8>) {
    let start = out.len();
    out.extend_from_slice(&(s.iterations as u64).to_le_bytes());
    out.extend_from_slice(&s.residual.to_le_bytes());
    out.push(u8::from(s.converged));
    for l in &s.radiance {
        l.iter()
            .for_each(|c| out.extend_from_slice(&c.to_le_bytes()));
    }
    for e in &s.stderr {
        e.unwrap_or([-1.0; 3])
            .iter()
            .for_each(|c| out.extend_from_slice(&c.to_le_bytes()));
    }
    for n in &s.samples {
        out.extend_from_slice(&n.to_le_bytes());
    }
    let crc = crc32fast::hash(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// Frame `frame` of `patches` patches from its bytes in `frames.bin` (checksum last).
fn decode_frame(frame: usize, patches: usize, bytes: &[u8]) -> std::io::Result<FrameSolution> {
    let (body, crc) = bytes.split_at(bytes.len().saturating_sub(4));
    let crc = u32::from_le_bytes(crc.try_into().unwrap_or_default());
    if bytes.len() != frame_bytes(patches) || crc32fast::hash(body) != crc {
        return Err(damaged(
            "frames.bin",
            format!("frame {frame}'s checksum does not match its contents"),
        ));
    }
    let word = |at: usize| <[u8; 8]>::try_from(&body[at..at + 8]).unwrap_or_default();
    let f64_at = |at: usize| f64::from_le_bytes(word(at));
    let triple = |at: usize| [f64_at(at), f64_at(at + 8), f64_at(at + 16)];
    let (radiance_at, stderr_at, samples_at) = (17, 17 + 24 * patches, 17 + 48 * patches);
    Ok(FrameSolution {
        pieces: Vec::new(),
        pieces_stderr: Vec::new(),
        shape: Vec::new(),
        spread: Vec::new(),
        first: Vec::new(),
        iterations: usize::try_from(u64::from_le_bytes(word(0))).unwrap_or(usize::MAX),
        residual: f64_at(8),
        converged: body[16] == 1,
        radiance: (0..patches).map(|p| triple(radiance_at + 24 * p)).collect(),
        stderr: (0..patches)
            .map(|p| Some(triple(stderr_at + 24 * p)).filter(|e| e[0] >= 0.0))
            .collect(),
        samples: (0..patches)
            .map(|p| u64::from_le_bytes(word(samples_at + 8 * p)))
            .collect(),
    })
}

/// The data directory (cheap to clone: the clones share it).
#[derive(Clone, Debug)]
pub struct Store {
    root: PathBuf,
    /// Held while a file is written: two writers of one file would share its temporary file.
    writing: std::sync::Arc<std::sync::Mutex<()>>,
    /// Whether traced state is written ([`Store::save_traced`]).
    traced_files: bool,
}

impl Store {
    /// Uses (and creates) `root`.
    pub fn open(root: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(root)?;
        Ok(Self {
            root: root.to_path_buf(),
            writing: std::sync::Arc::default(),
            traced_files: true,
        })
    }

    /// The same store, writing traced state if `traced_files` (it is read back either way).
    #[must_use]
    pub fn with_traced_files(self, traced_files: bool) -> Self {
        Self {
            traced_files,
            ..self
        }
    }

    /// The directory of timeline `id`.
    #[must_use]
    pub fn dir(&self, id: &str) -> PathBuf {
        self.root.join(id)
    }

    /// Writes `bytes` to `path` so that a crash or a full disk leaves either the file before
    /// or the new one: a temporary file, flushed to the disk, renamed over it (the temporary
    /// file removed if anything fails).
    fn write(&self, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
        let _one_at_a_time = self.writing.lock().unwrap_or_else(PoisonError::into_inner);
        write_whole(path, bytes)
    }

    /// Reads checked file `name` of timeline `id` ([`payload`]).
    fn read(&self, id: &str, name: &str) -> std::io::Result<Vec<u8>> {
        let bytes = std::fs::read(self.dir(id).join(name))?;
        let payload = payload(name, &bytes)?;
        Ok(if payload.len() == bytes.len() {
            bytes
        } else {
            payload.to_vec()
        })
    }

    /// Saves a timeline's record.
    pub fn save_record(&self, record: &Record) -> std::io::Result<()> {
        let dir = self.dir(&record.id);
        std::fs::create_dir_all(&dir)?;
        let json = serde_json::to_vec(record).map_err(std::io::Error::other)?;
        self.write(&dir.join("job.json"), &checked(&json))
    }

    /// Saves the scene as posted and the query string it was posted with.
    pub fn save_source(&self, id: &str, scene: &[u8], query: &str) -> std::io::Result<()> {
        let dir = self.dir(id);
        std::fs::create_dir_all(&dir)?;
        self.write(&dir.join("scene.bin"), &checked(scene))?;
        let request = serde_json::to_vec(&Request {
            query: query.to_string(),
        })
        .map_err(std::io::Error::other)?;
        self.write(&dir.join("request.json"), &checked(&request))
    }

    /// The query string a timeline was posted with: `None` if its source is not stored.
    ///
    /// # Errors
    /// `request.json` is damaged.
    pub fn load_query(&self, id: &str) -> std::io::Result<Option<String>> {
        match self.read(id, "request.json") {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e),
            Ok(bytes) => serde_json::from_slice::<Request>(&bytes)
                .map(|r| Some(r.query))
                .map_err(|e| damaged("request.json", e)),
        }
    }

    /// The scene a timeline was posted with.
    ///
    /// # Errors
    /// The file cannot be read, or is damaged.
    pub fn load_scene(&self, id: &str) -> std::io::Result<Vec<u8>> {
        self.read(id, "scene.bin")
    }

    /// Saves every frame of a finished timeline, solved for result `version`.
    pub fn save_frames(
        &self,
        id: &str,
        version: u64,
        frames: &[&FrameSolution],
    ) -> std::io::Result<()> {
        let patches = frames.first().map_or(0, |s| s.radiance.len());
        let mut out = Vec::with_capacity(FRAMES_HEADER + frames.len() * frame_bytes(patches));
        out.extend_from_slice(&frames_header(frames.len(), patches, version));
        for s in frames {
            encode_frame(s, &mut out);
        }
        let dir = self.dir(id);
        std::fs::create_dir_all(&dir)?;
        self.write(&dir.join("frames.bin"), &out)
    }

    /// Frame `frame` of timeline `id` as `frames.bin` holds it, read alone, and the version it
    /// was solved for.
    ///
    /// # Errors
    /// The file cannot be read, has no such frame, or is damaged.
    pub fn load_frame(&self, id: &str, frame: usize) -> std::io::Result<(u64, FrameSolution)> {
        let mut file = std::fs::File::open(self.dir(id).join("frames.bin"))?;
        let mut header = [0; FRAMES_HEADER];
        file.read_exact(&mut header)
            .map_err(|_| damaged("frames.bin", "its header is cut short"))?;
        let (frames, patches, version) = read_frames_header(&header)?;
        if frame >= frames {
            return Err(damaged(
                "frames.bin",
                format!("it holds {frames} frames, not frame {frame}"),
            ));
        }
        let size = frame_bytes(patches);
        let mut bytes = vec![0; size];
        file.seek(SeekFrom::Start((FRAMES_HEADER + frame * size) as u64))?;
        file.read_exact(&mut bytes)
            .map_err(|_| damaged("frames.bin", format!("frame {frame} is cut short")))?;
        Ok((version, decode_frame(frame, patches, &bytes)?))
    }

    /// Checks that `frames.bin` holds `record`'s frames, whole: its header, and its length
    /// (each frame's checksum is checked when it is read).
    ///
    /// # Errors
    /// What is wrong with it.
    pub fn check_frames(&self, record: &Record) -> std::io::Result<()> {
        let path = self.dir(&record.id).join("frames.bin");
        let mut file = std::fs::File::open(&path)
            .map_err(|e| damaged("frames.bin", format!("it cannot be opened: {e}")))?;
        let mut header = [0; FRAMES_HEADER];
        file.read_exact(&mut header)
            .map_err(|_| damaged("frames.bin", "its header is cut short"))?;
        let (frames, patches, version) = read_frames_header(&header)?;
        let expected = (record.frame_times.len(), record.patches, record.version);
        if (frames, patches, version) != expected {
            return Err(damaged(
                "frames.bin",
                format!(
                    "it holds {frames} frames of {patches} patches of version {version}, not \
                     {} of {} of version {}",
                    expected.0, expected.1, expected.2
                ),
            ));
        }
        let length = file.metadata()?.len();
        let whole = (FRAMES_HEADER + frames * frame_bytes(patches)) as u64;
        if length != whole {
            return Err(damaged(
                "frames.bin",
                format!("it holds {length} bytes of {whole}"),
            ));
        }
        Ok(())
    }

    /// Rewrites `frames.bin` of a data directory written before frames were checked in this
    /// layout; nothing if it is in it.
    fn upgrade_frames(&self, record: &Record) -> std::io::Result<()> {
        let path = self.dir(&record.id).join("frames.bin");
        let bytes = std::fs::read(&path)
            .map_err(|e| damaged("frames.bin", format!("it cannot be read: {e}")))?;
        if bytes.starts_with(FRAMES) {
            return Ok(());
        }
        let frames = read_first_layout(&bytes, record.frame_times.len())
            .ok_or_else(|| damaged("frames.bin", "it cannot be read as frames"))?;
        tracing::info!(id = %record.id, "frames.bin rewritten in the checked layout");
        self.save_frames(
            &record.id,
            record.version,
            &frames.iter().collect::<Vec<_>>(),
        )
    }

    /// Saves the traced state of timeline `id`, which has its first `refinements` refinements
    /// (nothing, if the store writes none or this build cannot tell itself from others); its
    /// bytes.
    ///
    /// # Errors
    /// It cannot be written (the file before, if any, is left whole).
    pub fn save_traced(&self, id: &str, refinements: usize, bake: &Bake) -> std::io::Result<u64> {
        let Some(mut out) = stamped(TRACED).filter(|_| self.traced_files) else {
            return Ok(0);
        };
        out.extend_from_slice(&(refinements as u64).to_le_bytes());
        let out = sealed(bake.write_bytes(out).map_err(std::io::Error::other)?);
        let dir = self.dir(id);
        std::fs::create_dir_all(&dir)?;
        self.write(&dir.join("traced.bin"), &out)?;
        Ok(out.len() as u64)
    }

    /// The traced state of timeline `id` ([`Store::save_traced`]), if this build wrote it.
    ///
    /// # Errors
    /// The file cannot be read, or is damaged.
    pub fn load_traced(&self, id: &str) -> std::io::Result<Traced> {
        let bytes = match std::fs::read(self.dir(id).join("traced.bin")) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Traced::Missing),
            bytes => bytes?,
        };
        let rest = match unstamped("traced.bin", &bytes, (TRACED, "a traced state"))? {
            Stamp::Ours(rest) => rest,
            Stamp::OtherBuild => return Ok(Traced::OtherBuild),
        };
        let (Some(count), Some(state)) = (rest.get(..8), rest.get(8..)) else {
            return Err(damaged("traced.bin", "it is cut short"));
        };
        let refinements = u64::from_le_bytes(count.try_into().unwrap_or_default());
        let bake = Bake::from_bytes(state).map_err(|e| damaged("traced.bin", e))?;
        Ok(Traced::Read {
            bake: Box::new(bake),
            refinements: usize::try_from(refinements).unwrap_or(usize::MAX),
        })
    }

    /// Bytes of every file in the data directory.
    #[must_use]
    pub fn bytes(&self) -> u64 {
        let Ok(dirs) = std::fs::read_dir(&self.root) else {
            return 0;
        };
        (dirs.filter_map(Result::ok))
            .filter_map(|d| std::fs::read_dir(d.path()).ok())
            .flat_map(|files| files.filter_map(Result::ok))
            .filter_map(|f| f.metadata().ok())
            .map(|m| m.len())
            .sum()
    }

    /// When timeline `id`'s record was last written.
    #[must_use]
    pub fn modified(&self, id: &str) -> Option<SystemTime> {
        std::fs::metadata(self.dir(id).join("job.json"))
            .ok()?
            .modified()
            .ok()
    }

    /// Removes a timeline ([`Store::set_aside`], then [`Store::discard`]).
    pub fn remove(&self, id: &str) -> std::io::Result<()> {
        self.set_aside(id).map_or(Ok(()), |dir| Self::discard(&dir))
    }

    /// Moves timeline `id`'s directory out of its place in one rename, so that nothing finds
    /// it under its id from then on, and gives where it went for [`Store::discard`] (None if
    /// there was none). A directory set aside and never discarded (a crash between the two)
    /// is removed by the next [`Store::load_all`]. If it cannot be renamed, it is given as it
    /// is, to be removed in place.
    #[must_use]
    pub fn set_aside(&self, id: &str) -> Option<PathBuf> {
        let dir = self.dir(id);
        let aside = self.root.join(format!("{SET_ASIDE}{id}"));
        match std::fs::rename(&dir, &aside) {
            Ok(()) => Some(aside),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(_) => Some(dir),
        }
    }

    /// Removes a directory [`Store::set_aside`] gave.
    pub fn discard(dir: &Path) -> std::io::Result<()> {
        match std::fs::remove_dir_all(dir) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    /// Every saved timeline, by id: its record, checked, and for a done one its frames' file
    /// (header and length). Temporary files a crash left are removed; a directory without a
    /// record (a job stopped before it was accepted) is left alone.
    #[must_use]
    pub fn load_all(&self) -> Vec<Saved> {
        let Ok(entries) = std::fs::read_dir(&self.root) else {
            return Vec::new();
        };
        let mut out: Vec<Saved> = (entries.filter_map(Result::ok))
            .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
            .filter(|e| {
                let set_aside = e.file_name().to_string_lossy().starts_with(SET_ASIDE);
                if set_aside {
                    tracing::warn!(dir = %e.path().display(), "removing a timeline's directory a removal left");
                    if let Err(e) = Self::discard(&e.path()) {
                        tracing::error!(error = %e, "could not remove it");
                    }
                }
                !set_aside
            })
            .filter_map(|e| self.load_one(&e.file_name().to_string_lossy()))
            .collect();
        out.sort_by(|a, b| a.id.cmp(&b.id));
        out
    }

    /// [`Store::load_all`] for timeline `id`.
    fn load_one(&self, id: &str) -> Option<Saved> {
        let dir = self.dir(id);
        for file in std::fs::read_dir(&dir).ok()?.filter_map(Result::ok) {
            if file.path().extension().is_some_and(|e| e == "tmp") {
                tracing::warn!(id, file = %file.path().display(), "removing a file left half-written");
                let _ = std::fs::remove_file(file.path());
            }
        }
        if !dir.join("job.json").exists() {
            tracing::warn!(id, "a timeline's directory without a record: left alone");
            return None;
        }
        let kept = format!(" (its files are kept in {})", dir.display());
        let record = self.read(id, "job.json").and_then(|bytes| {
            serde_json::from_slice::<Record>(&bytes).map_err(|e| damaged("job.json", e))
        });
        let record = match record {
            Ok(record) if record.id == id => record,
            Ok(record) => {
                let damage = format!("job.json is of timeline {:?}{kept}", record.id);
                return Some(Saved {
                    id: id.to_string(),
                    record: None,
                    damage: Some(damage),
                });
            }
            Err(e) => {
                return Some(Saved {
                    id: id.to_string(),
                    record: None,
                    damage: Some(format!("{e}{kept}")),
                });
            }
        };
        let damage = (record.status == "done")
            .then(|| {
                self.upgrade_frames(&record)
                    .and_then(|()| self.check_frames(&record))
                    .err()
            })
            .flatten()
            .or_else(|| self.load_query(id).err())
            .map(|e| format!("{e}{kept}"));
        Some(Saved {
            id: id.to_string(),
            record: Some(record),
            damage,
        })
    }
}

/// Parses `frames.bin` in its first layout (no header, no checksums); `None` if it is damaged.
fn read_first_layout(bytes: &[u8], frames: usize) -> Option<Vec<FrameSolution>> {
    let mut at = 0;
    let mut take = |n: usize| -> Option<&[u8]> {
        let s = bytes.get(at..at + n)?;
        at += n;
        Some(s)
    };
    let mut out = Vec::with_capacity(frames);
    for _ in 0..frames {
        let f64_at = |b: &[u8]| f64::from_le_bytes(b.try_into().unwrap_or([0; 8]));
        let u64_at = |b: &[u8]| u64::from_le_bytes(b.try_into().unwrap_or([0; 8]));
        let patches = usize::try_from(u64_at(take(8)?)).ok()?;
        let iterations = usize::try_from(u64_at(take(8)?)).ok()?;
        let residual = f64_at(take(8)?);
        let converged = take(1)?[0] == 1;
        let mut radiance = Vec::with_capacity(patches.min(bytes.len()));
        for _ in 0..patches {
            radiance.push([f64_at(take(8)?), f64_at(take(8)?), f64_at(take(8)?)]);
        }
        let mut stderr = Vec::with_capacity(patches.min(bytes.len()));
        for _ in 0..patches {
            let e = [f64_at(take(8)?), f64_at(take(8)?), f64_at(take(8)?)];
            stderr.push((e[0] >= 0.0).then_some(e));
        }
        let mut samples = Vec::with_capacity(patches.min(bytes.len()));
        for _ in 0..patches {
            samples.push(u64_at(take(8)?));
        }
        out.push(FrameSolution {
            pieces: Vec::new(),
            pieces_stderr: Vec::new(),
            shape: Vec::new(),
            spread: Vec::new(),
            first: Vec::new(),
            radiance,
            stderr,
            samples,
            iterations,
            residual,
            converged,
        });
    }
    (at == bytes.len()).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn solution(patches: usize, k: f64) -> FrameSolution {
        FrameSolution {
            pieces: Vec::new(),
            pieces_stderr: Vec::new(),
            shape: Vec::new(),
            spread: Vec::new(),
            first: Vec::new(),
            radiance: (0..patches).map(|p| [k, p as f64, 0.5]).collect(),
            stderr: (0..patches)
                .map(|p| (p % 3 != 0).then_some([0.1 * k, 0.0, 1e-300]))
                .collect(),
            samples: (0..patches as u64).collect(),
            iterations: 7,
            residual: 1e-9,
            converged: true,
        }
    }

    fn temp_store(name: &str) -> Store {
        let root =
            std::env::temp_dir().join(format!("radiosity-store-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        Store::open(&root).unwrap()
    }

    #[test]
    fn frames_are_read_back_alone_and_bit_identical() {
        let store = temp_store("frames");
        let frames = [solution(5, 1.0), solution(5, 2.0), solution(5, -0.0)];
        store
            .save_frames("t", 3, &frames.iter().collect::<Vec<_>>())
            .unwrap();
        for (f, s) in frames.iter().enumerate() {
            let (version, read) = store.load_frame("t", f).unwrap();
            assert_eq!(version, 3);
            assert_eq!(format!("{read:?}"), format!("{s:?}"));
        }
        assert!(store.load_frame("t", 3).is_err());
        let _ = std::fs::remove_dir_all(&store.root);
    }

    #[test]
    fn a_removed_timeline_leaves_its_place_at_once_and_a_removal_cut_short_is_finished() {
        let store = temp_store("remove");
        let record = |id: &str| Record {
            id: id.into(),
            status: "failed".into(),
            ..Record::default()
        };
        for id in ["a", "b", "c"] {
            store.save_record(&record(id)).unwrap();
        }
        store.remove("a").unwrap();
        assert!(!store.dir("a").exists());
        // Set aside, and the server stopped before it was discarded.
        let aside = store.set_aside("b").unwrap();
        assert!(!store.dir("b").exists() && aside.join("job.json").exists());
        let ids: Vec<String> = store.load_all().into_iter().map(|s| s.id).collect();
        assert_eq!(ids, ["c"]);
        assert!(!aside.exists());
        assert_eq!(store.set_aside("a"), None);
        let _ = std::fs::remove_dir_all(&store.root);
    }

    #[test]
    fn a_traced_state_is_read_back_by_its_build_only_and_damage_is_detected() {
        let store = temp_store("traced");
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell_box.gltf");
        let options = crate::loader::LoadOptions::default();
        let scene = crate::loader::load(&std::fs::read(path).unwrap(), &options).unwrap();
        let lines = crate::timeline::LineParams {
            lines: 2_000,
            seed: 3,
        };
        let bake = Bake::trace(scene, &lines).unwrap();
        assert!(matches!(store.load_traced("t"), Ok(Traced::Missing)));
        let bytes = store.save_traced("t", 2, &bake).unwrap();
        let path = store.dir("t").join("traced.bin");
        assert_eq!(std::fs::metadata(&path).unwrap().len(), bytes);
        let Ok(Traced::Read {
            bake: read,
            refinements: 2,
        }) = store.load_traced("t")
        else {
            panic!("not read back");
        };
        let written = |b: &Bake| b.write_bytes(Vec::new()).unwrap();
        assert!(written(&read) == written(&bake));
        let good = std::fs::read(&path).unwrap();
        // Another build's (resealed, so only the build differs): not read, not damaged.
        let mut other = good.clone();
        other[crate::checked::HEADER + 8] ^= 1;
        std::fs::write(&path, sealed(other)).unwrap();
        assert!(matches!(store.load_traced("t"), Ok(Traced::OtherBuild)));
        // A flipped bit anywhere, a cut anywhere: damaged.
        for at in (0..good.len()).step_by(good.len() / 97 + 1) {
            let mut bad = good.clone();
            bad[at] ^= 0x10;
            std::fs::write(&path, &bad).unwrap();
            let e = store.load_traced("t").err().expect("a flipped bit read");
            assert_eq!(e.kind(), std::io::ErrorKind::InvalidData, "{e}");
            std::fs::write(&path, &good[..at]).unwrap();
            let e = store.load_traced("t").err().expect("a cut file read");
            assert!(e.to_string().contains("traced.bin is damaged"), "{e}");
        }
        let _ = std::fs::remove_dir_all(&store.root);
    }

    #[test]
    fn every_flipped_byte_and_every_cut_is_detected() {
        let store = temp_store("damage");
        let frames = [solution(2, 1.0), solution(2, 2.0)];
        store
            .save_frames("t", 1, &frames.iter().collect::<Vec<_>>())
            .unwrap();
        let record = Record {
            id: "t".into(),
            status: "done".into(),
            version: 1,
            frame_times: vec![0.0, 1.0],
            patches: 2,
            ..Record::default()
        };
        let path = store.dir("t").join("frames.bin");
        let good = std::fs::read(&path).unwrap();
        store.check_frames(&record).unwrap();
        for at in 0..good.len() {
            let mut bad = good.clone();
            bad[at] ^= 0x10;
            std::fs::write(&path, &bad).unwrap();
            let read = store
                .check_frames(&record)
                .and_then(|()| (0..2).try_for_each(|f| store.load_frame("t", f).map(|_| ())));
            assert!(read.is_err(), "a flipped byte at {at} was not found");
        }
        for length in 0..good.len() {
            std::fs::write(&path, &good[..length]).unwrap();
            assert!(store.check_frames(&record).is_err(), "cut at {length}");
        }
        let json = br#"{"query": "lines=1000"}"#;
        let file = checked(json);
        assert_eq!(payload("x", &file).unwrap(), json);
        for at in 0..file.len() {
            let mut bad = file.clone();
            bad[at] ^= 0x01;
            // A header damaged into none reads as an unchecked file: not as this JSON.
            assert!(payload("x", &bad).map_or(true, |p| p != json), "byte {at}");
        }
        for length in 0..file.len() {
            assert!(payload("x", &file[..length]).map_or(true, |p| p != json));
        }
        let _ = std::fs::remove_dir_all(&store.root);
    }
}
