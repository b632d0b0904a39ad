//! Where a lightmap's texels gather their own light (irradiance caching, Ward 1988, on the
//! texels): a texel farther from the points it would interpolate than its validity reach (a
//! share of the harmonic mean distance to the surfaces around it,
//! [`crate::direct::points::closeness`]) reads instead the final gathers of **records**, texels
//! chosen so that each such texel has one within its reach and within the record's own.
//! Records are placed greedily, texel after texel in the atlas's order, where no record yet
//! covers a texel: in a narrow gap, where the reach is short, many; on an open floor, few. The
//! texels read the records around them, weighted by how far inside both reaches they are.
//!
//! A record covers a texel when their normals agree (a floor's record does not light the wall
//! beside it), the texel is near the record's plane (not a shelf above it) and their distance
//! is within both reaches. The records are looked up in a hash grid with a level per reach (a
//! record's cell at least its reach), so a query walks 27 cells a level.

use std::collections::HashMap;

use glam::DVec3;

/// A texel's reach as a share of the harmonic mean distance to the surfaces around it: irradiance
/// caching's accuracy `a` (0.1–0.3 in renderers that interpolate between records; 0.5 here,
/// where a record's gather is a texel's whole indirect light and its neighbours' texels read
/// others).
pub const VALIDITY: f64 = 0.5;

/// The longest reach (normalised units: the scene's radius is 1): a lattice's spacing apart,
/// the interpolation is the lattice's.
pub const MOST_REACH: f64 = 1.0 / 16.0;

/// Least cosine between a record's normal and a texel's it covers.
const NORMALS: f64 = 0.9;

/// Most distance of a texel off a record's plane, as a share of their distance.
const OFF_PLANE: f64 = 0.25;

/// Most levels of the hash grid (a reach of [`MOST_REACH`] / 2^20 is far below any texel).
const LEVELS: u32 = 20;

/// A texel that may read records: its point, its face's normal and its reach (normalised).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reader {
    pub x: DVec3,
    pub n: DVec3,
    pub reach: f64,
}

/// The records placed for some texels, and what each of those texels reads.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Records {
    /// Each record's reader (its index among the readers given to [`Records::place`]).
    pub at: Vec<u32>,
    /// Per reader, its records and their weights (summing to 1): `reads[first[i]..first[i+1]]`.
    pub first: Vec<u32>,
    pub reads: Vec<(u32, f32)>,
}

/// The hash grid's cell of `x` at `level`.
type Cell = (u32, [i64; 3]);

impl Records {
    /// Places records among `readers` (in their order) so that each is covered, and gives each
    /// reader the records covering it.
    #[must_use]
    pub fn place(readers: &[Reader]) -> Self {
        let mut grid: HashMap<Cell, Vec<u32>> = HashMap::new();
        let mut levels = 0;
        let mut at: Vec<u32> = Vec::new();
        let mut found = Vec::new();
        for (i, reader) in readers.iter().enumerate() {
            covering(readers, (&grid, levels), &at, reader, &mut found);
            if found.is_empty() {
                let level = level_of(reader.reach);
                levels = levels.max(level + 1);
                grid.entry(cell(reader.x, level))
                    .or_default()
                    .push(at.len() as u32);
                at.push(i as u32);
            }
        }
        let mut first = Vec::with_capacity(readers.len() + 1);
        let mut reads = Vec::new();
        for reader in readers {
            first.push(reads.len() as u32);
            covering(readers, (&grid, levels), &at, reader, &mut found);
            let total: f64 = found.iter().map(|f| f.1).sum();
            reads.extend(found.iter().map(|&(r, w)| (r, (w / total) as f32)));
        }
        first.push(reads.len() as u32);
        Self { at, first, reads }
    }

    /// The records reader `i` reads, with their weights.
    #[must_use]
    pub fn of(&self, i: usize) -> &[(u32, f32)] {
        &self.reads[self.first[i] as usize..self.first[i + 1] as usize]
    }
}

/// The grid level of a record of `reach`: the finest whose cell is at least the reach.
fn level_of(reach: f64) -> u32 {
    ((MOST_REACH / reach).log2().floor().max(0.0) as u32).min(LEVELS - 1)
}

/// `x`'s cell at `level`.
fn cell(x: DVec3, level: u32) -> Cell {
    let size = MOST_REACH / f64::from(1u32 << level);
    (level, (x / size).floor().as_i64vec3().to_array())
}

/// The records covering `reader` with their (unnormalised) weights, into `found`, in the order
/// they were placed.
fn covering(
    readers: &[Reader],
    (grid, levels): (&HashMap<Cell, Vec<u32>>, u32),
    at: &[u32],
    reader: &Reader,
    found: &mut Vec<(u32, f64)>,
) {
    found.clear();
    for level in 0..levels {
        let (_, [x, y, z]) = cell(reader.x, level);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let Some(records) = grid.get(&(level, [x + dx, y + dy, z + dz])) else {
                        continue;
                    };
                    for &r in records {
                        let record = &readers[at[r as usize] as usize];
                        if let Some(w) = weight(record, reader) {
                            found.push((r, w));
                        }
                    }
                }
            }
        }
    }
    found.sort_unstable_by_key(|f| f.0);
}

/// How much `reader` reads `record`, if the record covers it: `1 − d / reach` (a hair more, so
/// a record at the texel itself weighs 1), the reach the smaller of the two. A record covers
/// its own point whatever its normal (a sliver's may be none).
fn weight(record: &Reader, reader: &Reader) -> Option<f64> {
    let offset = reader.x - record.x;
    let d = offset.length();
    let reach = record.reach.min(reader.reach);
    (d <= reach && record.n.dot(reader.n) >= NORMALS && offset.dot(record.n).abs() <= OFF_PLANE * d)
        .then(|| 1.0 - d / reach + 1e-3)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn floor(n: usize, spacing: f64, reach: f64) -> Vec<Reader> {
        (0..n * n)
            .map(|k| Reader {
                x: DVec3::new((k % n) as f64 * spacing, 0.0, (k / n) as f64 * spacing),
                n: DVec3::Y,
                reach,
            })
            .collect()
    }

    #[test]
    fn every_reader_is_covered_and_records_are_fewer_where_the_reach_is_longer() {
        let near = Records::place(&floor(40, 0.001, 0.002));
        let far = Records::place(&floor(40, 0.001, 0.008));
        for records in [&near, &far] {
            for i in 0..40 * 40 {
                let reads = records.of(i);
                assert!(!reads.is_empty(), "reader {i} reads no record");
                let total: f32 = reads.iter().map(|r| r.1).sum();
                assert!((total - 1.0).abs() < 1e-5);
            }
        }
        // About one record per reach squared (greedy covering: between a half and twice that).
        assert!(
            near.at.len() > 8 * far.at.len(),
            "{} {}",
            near.at.len(),
            far.at.len()
        );
        let per_reach = 40.0 * 40.0 * 0.001f64.powi(2) / 0.008f64.powi(2);
        assert!((far.at.len() as f64) < 4.0 * per_reach, "{}", far.at.len());
    }

    #[test]
    fn a_record_lights_neither_the_wall_beside_it_nor_a_shelf_above_it() {
        let record = Reader {
            x: DVec3::ZERO,
            n: DVec3::Y,
            reach: 0.01,
        };
        let wall = Reader {
            x: DVec3::new(0.002, 0.002, 0.0),
            n: DVec3::NEG_X,
            ..record
        };
        let shelf = Reader {
            x: DVec3::new(0.002, 0.004, 0.0),
            ..record
        };
        let floor = Reader {
            x: DVec3::new(0.004, 0.0, 0.003),
            ..record
        };
        assert_eq!(weight(&record, &wall), None);
        assert_eq!(weight(&record, &shelf), None);
        assert!(weight(&record, &floor).is_some_and(|w| w > 0.4 && w < 0.6));
        // Beyond the shorter reach of the two.
        let tight = Reader {
            reach: 0.004,
            ..floor
        };
        assert_eq!(weight(&record, &tight), None);
    }
}
