//! Crossings that coincide along a line: contacts, coplanar overlaps and grazes (METHOD.md §10).
//!
//! Two crossings of one line closer than [`COINCIDENT`] are one place, and their order along the
//! line is decided by rounding, not by the geometry. What they mean depends on how the two
//! triangles face:
//!
//! - **A contact**: two surfaces touching face to face (a box standing on a floor, a pillar
//!   against a ceiling, a door closed in its frame). The line arrives at the back of one and at
//!   the front of the other. Physically no light passes between the touching faces, in either
//!   direction; each of the other two faces sees what lies on its own side. The run is ordered
//!   back before front (the line leaves one region before it enters the next), and the
//!   zero-length segment between them is dark ([`is_contact`]): it still counts in the touching
//!   patches' crossings `N_i`, so a face wholly in contact has radiance 0 and a patch partly in
//!   contact gets the area average of its lit and dark parts.
//! - **A coplanar overlap**: duplicated faces, decals, z-fighting geometry. The line arrives at
//!   every overlapping triangle from the same side; physically it crosses one surface once. The
//!   crossing is shared: one of the overlapping triangles gets it, chosen with equal
//!   probability (a hash of the crossing), so each is sampled at its share of the lines and none
//!   is left unsampled or made transparent. The choice is a function of the crossing alone, so
//!   the static and per-frame tallies of the multiframe method stay consistent.
//! - **A graze**: a line touching an edge or a fold of one surface in passing (in and out at one
//!   point). The two triangles meet at an angle; the line does not really pass, so both
//!   crossings are dropped (in the wrong order the touched faces would see the sky through a
//!   closed surface: a leak that ρ = 0.999 multiplies by 1000).
//!
//! Contacts and grazes both arrive at one back and one front; they differ in the geometry: a
//! contact is two triangles back to back in one plane, a graze two triangles at an angle. Their
//! normals are compared when both are in one space (static geometry, or one moving object);
//! otherwise the pair is a contact.

use glam::Vec3;

use super::Hit;
use crate::scene::Faces;

/// Crossings closer than this along a line are one place (normalised units: 4e-6 of the
/// scene's bounding radius, whatever the scene's size). It is a few times the rounding of a
/// crossing's distance in `f32` (about 2.4e-7 at the far end of a line, a few ulps after the
/// triangle test and an object's transform), and far below any gap worth lighting: a slit of
/// 1e-5 of the scene's radius still lets light through.
pub const COINCIDENT: f32 = 4e-6;

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
}

impl Surfaces<'_> {
    /// Whether the crossings `a` and `b`, one place on a line, are a contact: the line arrives
    /// at the back of one and the front of the other, and the triangles are not two faces of
    /// one surface meeting at an angle (a graze).
    #[must_use]
    pub fn contact(&self, a: Hit, b: Hit) -> bool {
        if a.front() == b.front() {
            return false;
        }
        let (i, j) = (a.surface() as usize, b.surface() as usize);
        self.spaces[i] != self.spaces[j] || self.normals[i].dot(self.normals[j]) <= BACK_TO_BACK
    }
}

/// Whether the segment between consecutive crossings `a` and `b` of a resolved line (see
/// [`resolve`]) is a contact, which no light crosses.
#[must_use]
pub fn is_contact(a: &Hit, b: &Hit) -> bool {
    b.t - a.t <= COINCIDENT
}

/// Resolves the runs of coincident crossings of a line (sorted along it) as the module
/// describes: each run becomes at most one back arrival followed by one front arrival (a
/// contact), one crossing, or nothing (a graze). `None` when nothing changes.
#[must_use]
pub fn resolve(hits: &[Hit], surfaces: &Surfaces<'_>) -> Option<Vec<Hit>> {
    if !hits.windows(2).any(|w| w[1].t - w[0].t <= COINCIDENT) {
        return None;
    }
    let mut out = Vec::with_capacity(hits.len());
    for run in runs(hits) {
        if run.len() == 1 {
            out.push(run[0]);
            continue;
        }
        let (backs, fronts) = settle(run, surfaces);
        match (share(&backs, run[0].t), share(&fronts, run[0].t)) {
            (Some(b), Some(f)) if surfaces.contact(b, f) => out.extend([b, f]),
            (Some(_), Some(_)) => {}
            (b, f) => out.extend(b.or(f)),
        }
    }
    Some(out)
}

/// Calls `shared(a, b)` for every two triangles that the line (crossings sorted along it)
/// crosses at one place from the same side: coplanar overlaps, whose crossing [`resolve`]
/// shares between them. Each run's triangles are paired with its first (by index).
pub fn overlaps(hits: &[Hit], surfaces: &Surfaces<'_>, mut shared: impl FnMut(u32, u32)) {
    for run in runs(hits).filter(|run| run.len() > 1) {
        let (backs, fronts) = settle(run, surfaces);
        for members in [backs, fronts] {
            if let Some((first, rest)) = members.split_first() {
                rest.iter()
                    .for_each(|other| shared(first.surface(), other.surface()));
            }
        }
    }
}

/// The runs of coincident crossings of a line sorted along it: its crossings grouped where
/// consecutive ones are closer than [`COINCIDENT`] (most runs are a single crossing).
fn runs(hits: &[Hit]) -> impl Iterator<Item = &[Hit]> {
    hits.chunk_by(|a, b| b.t - a.t <= COINCIDENT)
}

/// A run's arrivals at back faces and at front faces, each sorted by triangle, once its grazes
/// are taken out: an arrival at a back and one at a front of two triangles of one space meeting
/// at an angle (the line touching an edge in passing). Taking them out first matters where a
/// graze and a contact meet: a line along the bottom edge of a box standing on a floor crosses
/// the box's side, its bottom and the floor at one place, and only the floor is really crossed.
fn settle(run: &[Hit], surfaces: &Surfaces<'_>) -> (Vec<Hit>, Vec<Hit>) {
    let mut backs: Vec<Hit> = run.iter().filter(|h| !h.front()).copied().collect();
    let mut fronts: Vec<Hit> = run.iter().filter(|h| h.front()).copied().collect();
    backs.sort_unstable_by_key(|h| h.surface());
    fronts.sort_unstable_by_key(|h| h.surface());
    backs.retain(|&b| {
        let graze = fronts.iter().position(|&f| !surfaces.contact(b, f));
        graze.map(|k| fronts.remove(k)).is_none()
    });
    (backs, fronts)
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
fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Triangles 0 and 1: two faces of one static box meeting at a right angle (top, side);
    /// triangle 2: a floor back to back with 0's plane; triangle 3: a duplicate of the floor.
    fn surfaces() -> (Vec<Faces>, Vec<u32>, Vec<Vec3>) {
        let faces = (0..4)
            .map(|k| Faces {
                front: k,
                back: None,
            })
            .collect();
        let normals = vec![Vec3::NEG_Y, Vec3::X, Vec3::Y, Vec3::Y];
        (faces, vec![0; 4], normals)
    }

    /// Regression: 10 million lines through the furnace found two segments reaching the sky:
    /// lines grazing the cube's edge from outside, whose two crossings came out in the wrong
    /// order by rounding.
    #[test]
    fn grazes_are_dropped_contacts_ordered_overlaps_shared() {
        let (faces, spaces, normals) = surfaces();
        let s = Surfaces {
            faces: &faces,
            spaces: &spaces,
            normals: &normals,
        };
        let graze = [Hit::new(1.0, 1, true), Hit::new(1.0 + 1e-7, 0, false)];
        assert_eq!(resolve(&graze, &s), Some(vec![]));
        // A box's bottom (0) on the floor (2) at one place: leave, then enter.
        let contact = [Hit::new(2.0, 0, true), Hit::new(2.0, 2, false)];
        assert_eq!(resolve(&contact, &s), Some(vec![contact[1], contact[0]]));
        assert!(is_contact(&contact[1], &contact[0]));
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
        let (faces, spaces, normals) = surfaces();
        let s = Surfaces {
            faces: &faces,
            spaces: &spaces,
            normals: &normals,
        };
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
    /// let the room see the box's inside.
    #[test]
    fn a_graze_at_the_edge_of_a_contact_leaves_the_floor() {
        let faces = vec![
            Faces {
                front: 0,
                back: None
            };
            3
        ];
        // The box's side and bottom (object 1), the floor (static).
        let normals = [Vec3::X, Vec3::NEG_Y, Vec3::Y];
        let s = Surfaces {
            faces: &faces,
            spaces: &[1, 1, 0],
            normals: &normals,
        };
        for t in [0.5f32, 0.75, 1.0, 1.25] {
            let run = [
                Hit::new(t, 0, true),
                Hit::new(t, 1, false),
                Hit::new(t, 2, true),
            ];
            assert_eq!(resolve(&run, &s), Some(vec![run[2]]));
        }
    }

    #[test]
    fn surfaces_in_different_spaces_touching_are_a_contact() {
        let (faces, mut spaces, normals) = surfaces();
        spaces[1] = 1;
        let s = Surfaces {
            faces: &faces,
            spaces: &spaces,
            normals: &normals,
        };
        // Triangles 0 and 1 are at an angle, but 1 now belongs to a moving object.
        let run = [Hit::new(1.0, 1, true), Hit::new(1.0, 0, false)];
        assert_eq!(resolve(&run, &s), Some(vec![run[1], run[0]]));
    }
}
