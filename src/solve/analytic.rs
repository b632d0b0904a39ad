//! Closed-form form factors (METHOD.md §7), the references the tests and the accuracy
//! benchmark measure against.

use glam::DVec3;

/// Form factor from a differential area at `p` (facing +y or −y) to the parallel rectangle
/// [x0, x1] × [z0, z1] lying at height `p.y ± h` (h > 0): superposition of four rectangles with
/// a corner above the point (Howell's catalogue, C-11).
#[must_use]
pub fn point_to_parallel_rectangle(p: (f64, f64), x: (f64, f64), z: (f64, f64), h: f64) -> f64 {
    let corner = |a: f64, b: f64| {
        let (u, v) = (a.abs() / h, b.abs() / h);
        let f = (u / (1.0 + u * u).sqrt() * (v / (1.0 + u * u).sqrt()).atan()
            + v / (1.0 + v * v).sqrt() * (u / (1.0 + v * v).sqrt()).atan())
            / (2.0 * std::f64::consts::PI);
        a.signum() * b.signum() * f
    };
    corner(x.1 - p.0, z.1 - p.1) - corner(x.0 - p.0, z.1 - p.1) - corner(x.1 - p.0, z.0 - p.1)
        + corner(x.0 - p.0, z.0 - p.1)
}

/// Mean over triangle (a, b, c), horizontal, of the form factor to the parallel rectangle
/// [x0, x1] × [z0, z1] in the plane y = `plane`: a 15 × 15 barycentric quadrature.
#[must_use]
pub fn triangle_to_parallel_rectangle(
    [a, b, c]: [DVec3; 3],
    x: (f64, f64),
    z: (f64, f64),
    plane: f64,
) -> f64 {
    let (mut sum, mut count) = (0.0, 0.0);
    for i in 0..15 {
        for j in 0..15 - i {
            let (u, v) = (
                (f64::from(i) + 1.0 / 3.0) / 15.0,
                (f64::from(j) + 1.0 / 3.0) / 15.0,
            );
            let q = a + (b - a) * u + (c - a) * v;
            sum += point_to_parallel_rectangle((q.x, q.z), x, z, (q.y - plane).abs());
            count += 1.0;
        }
    }
    sum / count
}

/// Form factor between two coaxial parallel discs of radii `r1` (from) and `r2` at distance
/// `h` (METHOD.md §7).
#[must_use]
pub fn coaxial_discs(r1: f64, r2: f64, h: f64) -> f64 {
    let (a, b) = (r1 / h, r2 / h);
    let x = 1.0 + (1.0 + b * b) / (a * a);
    (x - (x * x - 4.0 * (b / a).powi(2)).sqrt()) / 2.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_squares_one_apart_see_each_other_at_0_19982() {
        // Integrate the point form factor over the receiving square.
        let n = 200;
        let mut sum = 0.0;
        for i in 0..n {
            for j in 0..n {
                let p = (
                    (f64::from(i) + 0.5) / f64::from(n) - 0.5,
                    (f64::from(j) + 0.5) / f64::from(n) - 0.5,
                );
                sum += point_to_parallel_rectangle(p, (-0.5, 0.5), (-0.5, 0.5), 1.0);
            }
        }
        let f = sum / f64::from(n * n);
        assert!((f - 0.199_824).abs() < 1e-5, "{f}");
    }

    #[test]
    fn discs_match_the_catalogue() {
        // Equal discs of radius 1 at distance 1: (3 − √5) / 2.
        assert!((coaxial_discs(1.0, 1.0, 1.0) - (3.0 - 5f64.sqrt()) / 2.0).abs() < 1e-15);
        // A point-like disc under a large one tends to r2² / (h² + r2²).
        assert!((coaxial_discs(1e-4, 1.0, 1.0) - 0.5).abs() < 1e-6);
    }
}
