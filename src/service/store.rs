//! Finished results on disk, so that a restart loses nothing.
//!
//! Each timeline has a directory `DATA/{id}/` with
//! - `scene.bin` and `request.json`: the scene as posted and the request's query string,
//!   written when the job is accepted, from which the job is traced again when its traced
//!   state is needed and not in memory (lines are deterministic, so the same state);
//! - `job.json`: what the status and patch endpoints serve, the frame times, the refinements
//!   asked for and the materials and lights as relit;
//! - once done, `frames.bin`: every frame's radiance, standard error (−1 where unsampled) and
//!   samples, little-endian f64/u64, so that the numbers served after a restart are
//!   bit-identical.
//!
//! Files are written to a temporary name and renamed. At start-up, finished timelines come back
//! `done`; the others start again from their stored scene (or, from a data directory written
//! before scenes were stored, come back `failed` with the reason `interrupted`).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::solve::FrameSolution;

/// What `job.json` holds.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Record {
    /// Timeline id.
    pub id: String,
    /// Last status written.
    pub status: String,
    /// Result version of the frames on disk.
    pub version: u64,
    /// Time of each frame.
    pub frame_times: Vec<f64>,
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

/// The data directory.
#[derive(Clone, Debug)]
pub struct Store {
    root: PathBuf,
}

impl Store {
    /// Uses (and creates) `root`.
    pub fn open(root: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(root)?;
        Ok(Self {
            root: root.to_path_buf(),
        })
    }

    fn dir(&self, id: &str) -> PathBuf {
        self.root.join(id)
    }

    /// Writes `bytes` to `path` atomically (temporary file, then rename).
    fn write(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, bytes)?;
        std::fs::rename(tmp, path)
    }

    /// Saves a timeline's record.
    pub fn save_record(&self, record: &Record) -> std::io::Result<()> {
        let dir = self.dir(&record.id);
        std::fs::create_dir_all(&dir)?;
        let json = serde_json::to_vec(record).map_err(std::io::Error::other)?;
        Self::write(&dir.join("job.json"), &json)
    }

    /// Saves the scene as posted and the query string it was posted with.
    pub fn save_source(&self, id: &str, scene: &[u8], query: &str) -> std::io::Result<()> {
        let dir = self.dir(id);
        std::fs::create_dir_all(&dir)?;
        Self::write(&dir.join("scene.bin"), scene)?;
        let request = serde_json::to_vec(&Request {
            query: query.to_string(),
        })
        .map_err(std::io::Error::other)?;
        Self::write(&dir.join("request.json"), &request)
    }

    /// The query string a timeline was posted with, if its source is stored.
    #[must_use]
    pub fn load_query(&self, id: &str) -> Option<String> {
        let bytes = std::fs::read(self.dir(id).join("request.json")).ok()?;
        Some(serde_json::from_slice::<Request>(&bytes).ok()?.query)
    }

    /// The scene a timeline was posted with.
    ///
    /// # Errors
    /// The file cannot be read.
    pub fn load_scene(&self, id: &str) -> std::io::Result<Vec<u8>> {
        std::fs::read(self.dir(id).join("scene.bin"))
    }

    /// Saves every frame of a finished timeline.
    pub fn save_frames(&self, id: &str, frames: &[Arc<FrameSolution>]) -> std::io::Result<()> {
        let mut out = Vec::new();
        for s in frames {
            out.extend_from_slice(&(s.radiance.len() as u64).to_le_bytes());
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
        }
        Self::write(&self.dir(id).join("frames.bin"), &out)
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

    /// Removes a timeline.
    pub fn remove(&self, id: &str) -> std::io::Result<()> {
        match std::fs::remove_dir_all(self.dir(id)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    /// Every saved timeline: its record and, if finished, its frames.
    pub fn load_all(&self) -> Vec<(Record, Option<Vec<Arc<FrameSolution>>>)> {
        let Ok(entries) = std::fs::read_dir(&self.root) else {
            return Vec::new();
        };
        let mut out: Vec<(Record, Option<Vec<Arc<FrameSolution>>>)> = entries
            .filter_map(Result::ok)
            .filter_map(|e| {
                let dir = e.path();
                let record: Record =
                    serde_json::from_slice(&std::fs::read(dir.join("job.json")).ok()?).ok()?;
                let frames = (record.status == "done")
                    .then(|| {
                        read_frames(
                            &std::fs::read(dir.join("frames.bin")).ok()?,
                            record.frame_times.len(),
                        )
                    })
                    .flatten();
                Some((record, frames))
            })
            .collect();
        out.sort_by(|a, b| a.0.id.cmp(&b.0.id));
        out
    }
}

/// Parses `frames.bin`; `None` if it is damaged.
fn read_frames(bytes: &[u8], frames: usize) -> Option<Vec<Arc<FrameSolution>>> {
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
        let mut radiance = Vec::with_capacity(patches);
        for _ in 0..patches {
            radiance.push([f64_at(take(8)?), f64_at(take(8)?), f64_at(take(8)?)]);
        }
        let mut stderr = Vec::with_capacity(patches);
        for _ in 0..patches {
            let e = [f64_at(take(8)?), f64_at(take(8)?), f64_at(take(8)?)];
            stderr.push((e[0] >= 0.0).then_some(e));
        }
        let mut samples = Vec::with_capacity(patches);
        for _ in 0..patches {
            samples.push(u64_at(take(8)?));
        }
        out.push(Arc::new(FrameSolution {
            radiance,
            stderr,
            samples,
            iterations,
            residual,
            converged,
        }));
    }
    Some(out)
}
