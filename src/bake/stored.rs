//! A bake's traced state as bytes, to be kept on disk and read back instead of traced again:
//! everything but the tracers (bounding volume hierarchies), which are built again from the
//! scenes they trace in a small fraction of the tracing's time.
//!
//! The encoding (postcard) does not describe itself: bytes are only read back by the build
//! that wrote them (the caller keeps a build identity beside them), and a round trip gives
//! the same bake to the bit (tested).

use serde::{Deserialize, Serialize};

use super::{Bake, Coarse, Pieces};
use crate::direct::DirectLight;
use crate::direct::area::AreaLights;
use crate::scene::Scene;
use crate::solve::Groups;
use crate::solve::tally::Tallies;
use crate::timeline::IntersectionList;
use crate::trace::SceneTracer;

/// [`Bake`] without its tracers, borrowed to be written.
#[derive(Serialize)]
struct Written<'a> {
    scene: &'a Scene,
    list: &'a IntersectionList,
    tallies: &'a Tallies,
    direct: &'a DirectLight,
    area: &'a AreaLights,
    seed: u64,
    warnings: &'a [String],
    inherited: bool,
    pieces: Option<WrittenPieces<'a>>,
    shown: Option<&'a Scene>,
}

/// [`Pieces`] without its tracer, borrowed to be written.
#[derive(Serialize)]
struct WrittenPieces<'a> {
    scene: &'a Scene,
    tallies: &'a Tallies,
    direct: &'a DirectLight,
    area: &'a AreaLights,
    groups: &'a Groups,
    /// Each piece's coarse piece: the rest of [`Coarse`] follows from it and the pieces.
    coarse: &'a [u32],
}

/// [`Written`] read back: the same fields in the same order.
#[derive(Deserialize)]
struct Read {
    scene: Scene,
    list: IntersectionList,
    tallies: Tallies,
    direct: DirectLight,
    area: AreaLights,
    seed: u64,
    warnings: Vec<String>,
    inherited: bool,
    pieces: Option<ReadPieces>,
    shown: Option<Scene>,
}

/// [`WrittenPieces`] read back.
#[derive(Deserialize)]
struct ReadPieces {
    scene: Scene,
    tallies: Tallies,
    direct: DirectLight,
    area: AreaLights,
    groups: Groups,
    coarse: Vec<u32>,
}

impl Bake {
    /// Appends the traced state to `out` ([`Bake::from_bytes`] reads it back).
    ///
    /// # Errors
    /// The encoder's (none is expected: every field has a plain encoding).
    pub fn write_bytes(&self, out: Vec<u8>) -> Result<Vec<u8>, postcard::Error> {
        let pieces = self.pieces.as_ref().map(|p| WrittenPieces {
            scene: &p.scene,
            tallies: &p.tallies,
            direct: &p.direct,
            area: &p.area,
            groups: &p.groups,
            coarse: p.coarse.of_pieces.of(),
        });
        let written = Written {
            scene: &self.scene,
            list: &self.list,
            tallies: &self.tallies,
            direct: &self.direct,
            area: &self.area,
            seed: self.seed,
            warnings: &self.warnings,
            inherited: self.inherited,
            pieces,
            shown: self.shown.as_ref(),
        };
        postcard::to_extend(&written, out)
    }

    /// The bake whose traced state [`Bake::write_bytes`] wrote, by the same build, its tracers
    /// built again.
    ///
    /// # Errors
    /// The bytes are not such a state (cut short, or written by another build).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, postcard::Error> {
        let read: Read = postcard::from_bytes(bytes)?;
        let pieces = read.pieces.map(|p| Pieces {
            map: crate::direct::points::PieceMap::new(&p.scene, p.groups.of()),
            coarse: Coarse::with_map(&p.scene, (p.groups.of(), p.groups.len()), p.coarse),
            tracer: SceneTracer::new(&p.scene),
            scene: p.scene,
            tallies: p.tallies,
            direct: p.direct,
            area: p.area,
            groups: p.groups,
            shares: Default::default(),
        });
        Ok(Self {
            tracer: SceneTracer::new(&read.scene),
            scene: read.scene,
            list: read.list,
            tallies: read.tallies,
            direct: read.direct,
            area: read.area,
            seed: read.seed,
            warnings: read.warnings,
            inherited: read.inherited,
            pieces,
            shown: read.shown,
            gathered: Default::default(),
            shares: Default::default(),
        })
    }
}
