//! Crossings that coincide along a line: contacts, coplanar overlaps, grazes and seams
//! (METHOD.md §10).
//!
//! Two crossings of one line closer than [`COINCIDENT`] are one place, and their order along the
//! line may be decided by rounding, not by the geometry. What they mean depends on how the
//! triangles face:
//!
//! - **A coplanar overlap**: duplicated faces, decals, z-fighting geometry. The line arrives at
//!   every overlapping triangle from the same side; physically it crosses one surface once. The
//!   crossing is shared: one of the overlapping triangles gets it, chosen with equal
//!   probability (a hash of the crossing), so each is sampled at its share of the lines and none
//!   is left unsampled or made transparent. The choice is a function of the crossing alone, so
//!   the static and per-frame tallies of the multiframe method stay consistent.
//! - **A contact**: two surfaces touching face to face (a box standing on a floor, a pillar
//!   against a ceiling, a door against a wall). The line arrives at the back of one and at the
//!   front of the other, back to back. Physically no light passes between the touching faces,
//!   in either direction; each of the other two faces sees what lies on its own side. The pair
//!   is ordered back before front (the line leaves one region before it enters the next), and
//!   the zero-length segment between them is dark ([`is_contact`]): the crossing lies on a part
//!   of each touching patch that no one sees, counted apart from its `N_i`
//!   ([`crate::solve::tally::HIDDEN`]), so a face wholly in contact is black and a patch partly
//!   in contact answers for its uncovered part.
//! - **A graze**: a line touching the fold between two faces of one surface in passing (in and
//!   out at one point): they share an edge, at an angle. The line does not really pass, so both
//!   crossings are dropped (in the wrong order the touched faces would see the sky through a
//!   closed surface: a leak that ρ = 0.999 multiplies by 1000).
//! - **A seam**: a surface standing on another (a box's side on a floor) shares no edge with
//!   it; a line through the seam crosses both, in the order of their distances.
//!
//! They are found in that order ([`resolve`]). Normals are compared when both triangles are in
//! one space (static geometry, or one moving object); otherwise a back-and-front pair is a
//! contact.

use glam::Vec3;

use super::Hit;
use crate::scene::Faces;

/// Crossings closer than this along a line are one place (normalised units: 4e-6 of the
/// scene's bounding radius, whatever the scene's size). It is a few times the rounding of a
/// crossing's distance in `f32` (about 2.4e-7 at the far end of a line, a few ulps after the
/// triangle test and an object's transform), and far below any gap worth lighting: a slit of
/// 1e-5 of the scene's radius still lets light through.
pub const COINCIDENT: f32 = 4e-6;

/// Crossings of a static surface are one place across it ([`Surfaces::coincide`]) up to this
/// far apart along the line (normalised units): for lines meeting the surface at 0.9° (a
/// cosine of 1/64) or more; a line closer to parallel keeps the tolerance along it.
pub const ALONG_MAX: f32 = 64.0 * COINCIDENT;

/// Normals of two triangles at least this close to opposite are back to back (about 2.6°).
const BACK_TO_BACK: f32 = -0.999;

/// What the tallies and shadow rays need to know of the traced triangles.
#[derive(Clone, Copy, Debug)]
pub struct Surfaces<'a> {
    /// The patches on the faces of each traced triangle.
    pub faces: &'a [Faces],
    /// The space each triangle's normal is given in: 0 for static geometry (normalised space),
    /// `1 + k` for moving object `k` (its own space). Normals compare only within one space.
    pub spaces: &'a [u32],
    /// Unit normal of each triangle's front face in its space (zero if degenerate there).
    pub normals: &'a [Vec3],
    /// Each triangle's corners in its space, as hashes of their positions' bits: two triangles
    /// share an edge when they share two (their vertices' indices may differ, as a flat-shaded
    /// export repeats a vertex per face).
    pub corners: &'a [[u32; 3]],
    /// The direction of the line being resolved, if known ([`Surfaces::along`]).
    pub direction: Option<Vec3>,
}

impl Surfaces<'_> {
    /// The same surfaces for resolving a line of direction `d`: crossings of a static surface
    /// are then one place when they are closer than [`COINCIDENT`] across it, not only along
    /// the line ([`ALONG_MAX`]).
    #[must_use]
    pub fn along(self, d: Vec3) -> Self {
        Self {
            direction: Some(d),
            ..self
        }
    }

    /// Whether crossings `a` and `b` (in this order along the line) are one place: closer than
    /// [`COINCIDENT`] along the line, or, for a line of known direction, across a static
    /// surface among them (their distance along the line times the cosine between the line and
    /// that surface's normal). A position's rounding along a surface's normal becomes a
    /// distance along a line that meets it at a grazing angle divided by the cosine: two faces
    /// in contact are crossed further apart than the tolerance by lines within a few degrees of
    /// grazing them.
    #[must_use]
    pub fn coincide(&self, a: Hit, b: Hit) -> bool {
        let gap = b.t - a.t;
        if gap <= COINCIDENT {
            return true;
        }
        let Some(d) = self.direction else {
            return false;
        };
        gap <= ALONG_MAX
            && [a, b]
                .iter()
                .filter(|h| self.spaces[h.surface() as usize] == 0)
                .any(|h| gap * self.normals[h.surface() as usize].dot(d).abs() <= COINCIDENT)
    }

    /// Whether the crossings `a` and `b`, one place on a line, are a contact: the line arrives
    /// at the back of one and the front of the other, and the triangles are not two faces of
    /// one surface folded along an edge (a graze: in one space, they share an edge and are not
    /// back to back; a line crossing such a fold passes one of them only, by the watertight
    /// test's tie rule, so both are reported only where it touches the fold in passing). A
    /// triangle ending on another's face (a box's side standing on a floor) shares no edge with
    /// it: a line through that seam really crosses both.
    #[must_use]
    pub fn contact(&self, a: Hit, b: Hit) -> bool {
        if a.front() == b.front() {
            return false;
        }
        let (i, j) = (a.surface() as usize, b.surface() as usize);
        let shared = self.corners[i]
            .iter()
            .filter(|c| self.corners[j].contains(c))
            .count();
        self.spaces[i] != self.spaces[j] || shared < 2 || self.back_to_back(a, b)
    }

    /// Whether two triangles crossed at one place lie back to back in one plane (normals
    /// opposite), or may (they are in two spaces): their order along the line is rounding's.
    #[must_use]
    pub fn back_to_back(&self, a: Hit, b: Hit) -> bool {
        let (i, j) = (a.surface() as usize, b.surface() as usize);
        self.spaces[i] != self.spaces[j] || self.normals[i].dot(self.normals[j]) <= BACK_TO_BACK
    }

    /// Whether two triangles crossed at one place lie in one plane facing one way: in one
    /// space, normals parallel (overlapping faces, which share the crossing). Triangles in two
    /// spaces are never taken for an overlap.
    #[must_use]
    pub fn coplanar(&self, a: Hit, b: Hit) -> bool {
        let (i, j) = (a.surface() as usize, b.surface() as usize);
        self.spaces[i] == self.spaces[j] && self.normals[i].dot(self.normals[j]) >= -BACK_TO_BACK
    }

    /// Whether crossing `h`, at the start of a shadow ray leaving face `back` (or the front) of
    /// triangle `own`, is a surface touching that face: the ray arrives at its front, which
    /// lies against the lit face (back to back with it, or in another space).
    #[must_use]
    pub fn touching(&self, own: u32, back: bool, h: Hit) -> bool {
        let (i, j) = (own as usize, h.surface() as usize);
        if !h.front() || i == j {
            return false;
        }
        let lit = if back {
            -self.normals[i]
        } else {
            self.normals[i]
        };
        self.spaces[i] != self.spaces[j] || self.normals[j].dot(lit) <= BACK_TO_BACK
    }
}

/// Whether the segment between consecutive crossings `a` and `b` of a resolved line (see
/// [`resolve`]) is dark: it joins two crossings of one place (a contact, or the zero-length
/// gap between surfaces a line crosses at a seam), which no light crosses.
#[must_use]
pub fn is_contact(a: &Hit, b: &Hit) -> bool {
    b.t - a.t <= COINCIDENT
}

/// Resolves the runs of coincident crossings of a line (sorted along it) as the module
/// describes: each run becomes what it really crosses (contacts as a back arrival followed by
/// a front arrival, one crossing per overlap, seams' crossings in order, nothing for a graze),
/// all at the run's first distance. `None` when nothing changes.
#[must_use]
pub fn resolve(hits: &[Hit], surfaces: &Surfaces<'_>) -> Option<Vec<Hit>> {
    if !hits.windows(2).any(|w| surfaces.coincide(w[0], w[1])) {
        return None;
    }
    let mut out = Vec::with_capacity(hits.len());
    for run in runs(hits, surfaces) {
        if run.len() == 1 {
            out.push(run[0]);
            continue;
        }
        // What the run crosses, in the order of the distances (a line through the seam where a
        // wall stands on a floor crosses the one it reaches first first: their distances
        // differ by more than rounding). Next to a contact, whose faces lie in one plane with
        // the others', rounding decides the distances: the line then enters what it enters
        // (front arrivals), passes the contacts, and leaves what it leaves (back arrivals).
        // All end at one distance, so that every segment between them is a contact
        // ([`is_contact`]) however long the run they stand for.
        let mut units = settle(run, surfaces);
        let contacts = units.iter().any(|u| matches!(u, Unit::Contact(..)));
        let rank = |u: &Unit| match u {
            _ if !contacts => 0,
            Unit::Single(h) if h.front() => 0,
            Unit::Contact(..) => 1,
            Unit::Single(_) => 2,
        };
        units.sort_unstable_by(|a, b| {
            let (fa, fb) = (a.first(), b.first());
            (rank(a).cmp(&rank(b)))
                .then(a.t().total_cmp(&b.t()))
                .then((fa.front(), fa.surface()).cmp(&(fb.front(), fb.surface())))
        });
        let at = |h: Hit| Hit::new(run[0].t, h.surface(), h.front());
        for unit in &units {
            match *unit {
                Unit::Contact(b, f) => out.extend([at(b), at(f)]),
                Unit::Single(h) => out.push(at(h)),
            }
        }
    }
    Some(out)
}

/// Calls `shared(a, b)` for every two triangles that the line (crossings sorted along it)
/// crosses at one place from the same side, in one plane: coplanar overlaps, whose crossing
/// [`resolve`] shares between them. Each overlap's triangles are paired with its first.
pub fn overlaps(hits: &[Hit], surfaces: &Surfaces<'_>, mut shared: impl FnMut(u32, u32)) {
    for run in runs(hits, surfaces).filter(|run| run.len() > 1) {
        for members in overlap_groups(run, surfaces) {
            if let Some((first, rest)) = members.split_first() {
                rest.iter()
                    .for_each(|other| shared(first.surface(), other.surface()));
            }
        }
    }
}

/// The runs of coincident crossings of a line sorted along it: its crossings grouped where
/// consecutive ones are one place ([`Surfaces::coincide`]; most runs are a single crossing).
fn runs<'h>(hits: &'h [Hit], surfaces: &Surfaces<'_>) -> impl Iterator<Item = &'h [Hit]> {
    hits.chunk_by(|&a, &b| surfaces.coincide(a, b))
}

/// One thing a run of coincident crossings really crosses.
enum Unit {
    /// A back arrival and a front arrival back to back: two faces touching.
    Contact(Hit, Hit),
    /// One crossing (standing for an overlap's copies, see [`share`]).
    Single(Hit),
}

impl Unit {
    /// The first of its crossings the line meets.
    fn first(&self) -> Hit {
        match *self {
            Unit::Contact(b, _) => b,
            Unit::Single(h) => h,
        }
    }

    /// Where along the line it is, as computed (the nearest of its crossings).
    fn t(&self) -> f32 {
        match *self {
            Unit::Contact(b, f) => b.t.min(f.t),
            Unit::Single(h) => h.t,
        }
    }
}

/// The arrivals of a run at each side, in groups of coplanar overlapping triangles (each
/// sorted by triangle; most groups are one crossing): back arrivals first.
fn overlap_groups(run: &[Hit], surfaces: &Surfaces<'_>) -> Vec<Vec<Hit>> {
    let mut groups: Vec<Vec<Hit>> = Vec::new();
    for front in [false, true] {
        let mut side: Vec<Hit> = run.iter().filter(|h| h.front() == front).copied().collect();
        side.sort_unstable_by_key(|h| h.surface());
        let first = groups.len();
        for h in side {
            match groups[first..]
                .iter_mut()
                .find(|g| surfaces.coplanar(g[0], h))
            {
                Some(group) => group.push(h),
                None => groups.push(vec![h]),
            }
        }
    }
    groups
}

/// What a run really crosses, in no particular order:
/// 1. each overlap's copies stand for one crossing, shared between them ([`share`]);
/// 2. back-to-back pairs of a back arrival and a front arrival are contacts;
/// 3. of the rest, a back and a front arrival of two triangles folded along an edge are a graze
///    (the line touching the fold in passing): both are dropped;
/// 4. what is left is crossed, each (a line through the seam where a wall stands on a floor
///    crosses both).
///
/// Contacts come before grazes: where a door stands open against a wall at the doorway's edge,
/// a line through that corner touches the doorway's fold and meets the door's edge against the
/// wall; the door's edge is in contact, whatever the fold does. Grazes come before seams: a
/// line along the bottom edge of a box standing on a floor crosses the box's side, its bottom
/// and the floor at one place; the bottom is in contact with the floor, and the side's crossing
/// stays a crossing of the box.
fn settle(run: &[Hit], surfaces: &Surfaces<'_>) -> Vec<Unit> {
    let crossings: Vec<Hit> = overlap_groups(run, surfaces)
        .iter()
        .filter_map(|members| share(members, run[0].t))
        .collect();
    let (mut backs, mut fronts): (Vec<Hit>, Vec<Hit>) =
        crossings.into_iter().partition(|h| !h.front());
    let mut units = Vec::new();
    backs.retain(|&b| {
        let touching = fronts.iter().position(|&f| surfaces.back_to_back(b, f));
        touching
            .map(|k| units.push(Unit::Contact(b, fronts.remove(k))))
            .is_none()
    });
    backs.retain(|&b| {
        let graze = fronts.iter().position(|&f| !surfaces.contact(b, f));
        graze.map(|k| fronts.remove(k)).is_none()
    });
    units.extend(backs.into_iter().chain(fronts).map(Unit::Single));
    units
}

/// The crossing that stands for `members`, arrivals at one side of coplanar overlapping
/// triangles (sorted by triangle) at `t`: one of them with equal probability, from a hash of
/// the place and the triangles, so the choice does not depend on the order rounding gave them.
fn share(members: &[Hit], t: f32) -> Option<Hit> {
    match members.len() {
        0 => None,
        1 => Some(members[0]),
        n => {
            let mut key = u64::from(t.to_bits());
            for h in members {
                key = mix(key ^ u64::from(h.surface()));
            }
            Some(members[(key % n as u64) as usize])
        }
    }
}

/// SplitMix64's finaliser: a well-mixed 64-bit hash of `x`.
pub(crate) fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` one-sided triangles, triangle `k` carrying patch `k`.
    fn one_sided(n: u32) -> Vec<Faces> {
        (0..n)
            .map(|k| Faces {
                front: k,
                back: None,
            })
            .collect()
    }

    /// Triangles 0 and 1: two faces of one static box meeting at a right angle along an edge
    /// (bottom, side); triangle 2: a floor back to back with 0's plane; triangle 3: a duplicate
    /// of the floor; triangle 4: a wall standing on the floor, with a corner on one of the
    /// floor's (a shared vertex, not an edge).
    struct Scene {
        faces: Vec<Faces>,
        spaces: Vec<u32>,
        normals: Vec<Vec3>,
        corners: Vec<[u32; 3]>,
    }

    impl Scene {
        fn new() -> Self {
            Self {
                faces: one_sided(5),
                spaces: vec![0; 5],
                normals: vec![Vec3::NEG_Y, Vec3::X, Vec3::Y, Vec3::Y, Vec3::NEG_X],
                corners: vec![
                    [1, 2, 3],
                    [2, 3, 4],
                    [10, 11, 12],
                    [10, 11, 12],
                    [12, 21, 22],
                ],
            }
        }

        fn surfaces(&self) -> Surfaces<'_> {
            Surfaces {
                faces: &self.faces,
                spaces: &self.spaces,
                normals: &self.normals,
                corners: &self.corners,
                direction: None,
            }
        }
    }

    /// Regression: 10 million lines through the furnace found two segments reaching the sky:
    /// lines grazing the cube's edge from outside, whose two crossings came out in the wrong
    /// order by rounding.
    #[test]
    fn grazes_are_dropped_contacts_ordered_overlaps_shared() {
        let scene = Scene::new();
        let s = scene.surfaces();
        let graze = [Hit::new(1.0, 1, true), Hit::new(1.0 + 1e-7, 0, false)];
        assert_eq!(resolve(&graze, &s), Some(vec![]));
        // A box's bottom (0) on the floor (2) at one place: leave, then enter.
        let contact = [Hit::new(2.0, 0, true), Hit::new(2.0, 2, false)];
        assert_eq!(resolve(&contact, &s), Some(vec![contact[1], contact[0]]));
        assert!(is_contact(&contact[1], &contact[0]));
        // Regression: a line through the seam where a floor (2) meets a wall standing on it (4)
        // crosses both; at an angle in one space, but not a graze (they share no corner).
        let seam = [Hit::new(2.5, 2, false), Hit::new(2.5, 4, true)];
        assert_eq!(resolve(&seam, &s), Some(seam.to_vec()));
        // Entering the wall and the floor at their seam from one side: both are crossed (not an
        // overlap), in the order of their distances, then at one distance.
        let seam = [Hit::new(2.5, 4, true), Hit::new(2.5 + 1e-6, 2, true)];
        let both = vec![Hit::new(2.5, 4, true), Hit::new(2.5, 2, true)];
        assert_eq!(resolve(&seam, &s), Some(both));
        // The floor and its duplicate: one of them, the same whatever their order.
        let overlap = [Hit::new(3.0, 2, true), Hit::new(3.0, 3, true)];
        let shared = resolve(&overlap, &s).unwrap();
        assert_eq!(shared.len(), 1);
        assert_eq!(resolve(&[overlap[1], overlap[0]], &s), Some(shared.clone()));
        // Crossings that are far apart are left alone.
        let apart = [Hit::new(1.0, 0, true), Hit::new(1.5, 1, false)];
        assert_eq!(resolve(&apart, &s), None);
        assert!(!is_contact(&apart[0], &apart[1]));
    }

    #[test]
    fn an_overlap_is_shared_evenly() {
        let scene = Scene::new();
        let s = scene.surfaces();
        let n = 20_000;
        let firsts = (0..n)
            .filter(|&k| {
                let t = 0.5 + k as f32 * 1e-4;
                let run = [Hit::new(t, 2, true), Hit::new(t, 3, true)];
                resolve(&run, &s).unwrap()[0].surface() == 2
            })
            .count();
        // Binomial(n, 1/2): standard deviation √n / 2 ≈ 71; 5σ.
        let sigma = (n as f64).sqrt() / 2.0;
        assert!(
            (firsts as f64 - n as f64 / 2.0).abs() < 5.0 * sigma,
            "{firsts}"
        );
    }

    /// Regression: a line along the bottom edge of a moving box on a floor crossed the box's
    /// side, its bottom and the floor at one place; sharing the side's crossing with the floor's
    /// let the room see the box's inside. The line enters the box, passes the contact, and
    /// enters the floor.
    #[test]
    fn a_line_along_a_box_edge_on_a_floor_enters_the_box_then_passes_the_contact() {
        let faces = one_sided(3);
        // The box's side and bottom (object 1), the floor (static).
        let normals = [Vec3::X, Vec3::NEG_Y, Vec3::Y];
        let s = Surfaces {
            faces: &faces,
            spaces: &[1, 1, 0],
            normals: &normals,
            corners: &[[1, 2, 3], [2, 3, 4], [10, 11, 12]],
            direction: None,
        };
        for t in [0.5f32, 0.75, 1.0, 1.25] {
            let side = Hit::new(t, 0, true);
            let bottom = Hit::new(t + 1e-6, 1, false);
            let floor = Hit::new(t - 1e-6, 2, true);
            let resolved = resolve(&[floor, side, bottom], &s).unwrap();
            let at = |h: Hit| Hit::new(t - 1e-6, h.surface(), h.front());
            assert_eq!(resolved, vec![at(side), at(bottom), at(floor)]);
            assert!(is_contact(&resolved[1], &resolved[2]));
        }
    }

    /// Regression: a door open against a wall at the doorway's edge; a line through that corner
    /// touched the fold between the wall and the doorway's jamb (a graze, which took the wall)
    /// and met the door's edge alone, which saw the room's lamp through the wall.
    #[test]
    fn a_contact_is_found_before_a_graze() {
        let faces = one_sided(3);
        // The jamb and the wall share the doorway's edge (static); the door is object 1.
        let normals = [Vec3::Z, Vec3::X, Vec3::NEG_Z];
        let s = Surfaces {
            faces: &faces,
            spaces: &[0, 0, 1],
            normals: &normals,
            corners: &[[1, 2, 3], [2, 3, 4], [10, 11, 12]],
            direction: None,
        };
        let (jamb, wall, door) = (
            Hit::new(1.0, 0, true),
            Hit::new(1.0 + 2e-6, 1, false),
            Hit::new(1.0 + 1e-6, 2, true),
        );
        let at = |h: Hit| Hit::new(1.0, h.surface(), h.front());
        assert_eq!(
            resolve(&[jamb, door, wall], &s),
            Some(vec![at(jamb), at(wall), at(door)])
        );
    }

    /// Regression: a line within 6° of grazing the floor crossed it and the bottom of a block
    /// sliding on it 4.5e-6 apart (their positions' rounding divided by the cosine): taken for
    /// two places, the block's inside saw the floor.
    #[test]
    fn a_grazing_line_finds_a_contact_across_the_surfaces() {
        let faces = one_sided(2);
        // The floor (static) and the block's bottom (object 1).
        let s = Surfaces {
            faces: &faces,
            spaces: &[0, 1],
            normals: &[Vec3::Y, Vec3::NEG_Y],
            corners: &[[1, 2, 3], [10, 11, 12]],
            direction: None,
        };
        let (floor, bottom) = (Hit::new(1.0, 0, true), Hit::new(1.0 + 4.5e-6, 1, false));
        assert_eq!(resolve(&[floor, bottom], &s), None);
        // cos θ = 0.1 with the floor: 4.5e-7 apart across it.
        let d = Vec3::new((1.0f32 - 0.01).sqrt(), -0.1, 0.0);
        let contact = vec![Hit::new(1.0, 1, false), Hit::new(1.0, 0, true)];
        assert_eq!(resolve(&[floor, bottom], &s.along(d)), Some(contact));
        // A line along the floor does not merge crossings further apart than ALONG_MAX.
        let far = Hit::new(1.0 + 2.0 * ALONG_MAX, 1, false);
        let flat = Vec3::new(1.0, -1e-6, 0.0).normalize();
        assert_eq!(resolve(&[floor, far], &s.along(flat)), None);
    }

    #[test]
    fn surfaces_in_different_spaces_touching_are_a_contact() {
        let mut scene = Scene::new();
        scene.spaces[1] = 1;
        let s = scene.surfaces();
        // Triangles 0 and 1 are at an angle, but 1 now belongs to a moving object.
        let run = [Hit::new(1.0, 1, true), Hit::new(1.0, 0, false)];
        assert_eq!(resolve(&run, &s), Some(vec![run[1], run[0]]));
    }
}
