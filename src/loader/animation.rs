//! Animation samplers: keyframes and their interpolation (glTF 2.0 §3.11 and Appendix C).
//!
//! Values are clamped before the first key and after the last. STEP holds a key's value until
//! the next key; LINEAR interpolates component-wise, and rotations by spherical linear
//! interpolation on the short path; CUBICSPLINE is the Hermite spline whose tangents are scaled
//! by the segment's duration, with rotations normalised afterwards.

use glam::DQuat;

/// How a sampler interpolates between keys.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    /// Hold each key's value until the next key.
    Step,
    /// Linear (slerp for rotations).
    Linear,
    /// Cubic Hermite spline with in- and out-tangents per key.
    CubicSpline,
}

/// A checked sampler: key times and values, ready to evaluate at any time.
#[derive(Clone, Debug)]
pub struct Sampler {
    /// Key times in seconds, non-decreasing, at least one.
    times: Vec<f64>,
    /// Values per key: `width` values, or `3 × width` for CUBICSPLINE laid out as
    /// (in-tangent, value, out-tangent).
    values: Vec<f64>,
    /// Components per value (3 for translation and scale, 4 for rotation, targets for weights).
    width: usize,
    interpolation: Interpolation,
}

impl Sampler {
    /// Checks and builds a sampler. Returns a message naming what is wrong on bad input.
    pub fn new(
        times: Vec<f64>,
        values: Vec<f64>,
        width: usize,
        interpolation: Interpolation,
    ) -> Result<Self, String> {
        if times.is_empty() {
            return Err("has no keyframes".into());
        }
        if width == 0 {
            return Err("animates a value with no components".into());
        }
        if let Some(k) = times.windows(2).position(|w| w[1] < w[0]) {
            return Err(format!(
                "input times must not decrease (key {}: {} after {})",
                k + 1,
                times[k + 1],
                times[k]
            ));
        }
        let per_key = if interpolation == Interpolation::CubicSpline {
            3 * width
        } else {
            width
        };
        if values.len() != times.len() * per_key {
            return Err(format!(
                "{} input keys need {} output values ({} per key), found {}",
                times.len(),
                times.len() * per_key,
                per_key,
                values.len()
            ));
        }
        Ok(Self {
            times,
            values,
            width,
            interpolation,
        })
    }

    /// Time of the first key.
    #[must_use]
    pub fn start(&self) -> f64 {
        self.times[0]
    }

    /// Time of the last key.
    #[must_use]
    pub fn end(&self) -> f64 {
        self.times[self.times.len() - 1]
    }

    /// Components per value.
    #[must_use]
    pub fn width(&self) -> usize {
        self.width
    }

    /// The value of key `k` (the middle third for CUBICSPLINE).
    fn key(&self, k: usize) -> &[f64] {
        match self.interpolation {
            Interpolation::CubicSpline => {
                &self.values[(3 * k + 1) * self.width..(3 * k + 2) * self.width]
            }
            _ => &self.values[k * self.width..(k + 1) * self.width],
        }
    }

    /// The segment containing `t`: `Some((k, s))` with `times[k] <= t < times[k + 1]` and `s` in
    /// [0, 1) the position within it, or `None` when `t` is clamped to a key (`Err(key)`).
    fn locate(&self, t: f64) -> Result<(usize, f64), usize> {
        let last = self.times.len() - 1;
        if t.is_nan() || t <= self.times[0] {
            return Err(0);
        }
        if t >= self.times[last] {
            return Err(last);
        }
        // First key strictly after t; the segment starts just before it. Keys with equal times
        // are never a segment's two ends, so the duration below is positive.
        let next = self.times.partition_point(|&x| x <= t);
        let k = next - 1;
        let s = (t - self.times[k]) / (self.times[next] - self.times[k]);
        Ok((k, s))
    }

    /// Evaluates a vector value (translation, scale, weights) at time `t` into `out`.
    pub fn sample(&self, t: f64, out: &mut [f64]) {
        debug_assert_eq!(out.len(), self.width);
        let (k, s) = match self.locate(t) {
            Ok(segment) => segment,
            Err(key) => {
                out.copy_from_slice(self.key(key));
                return;
            }
        };
        match self.interpolation {
            Interpolation::Step => out.copy_from_slice(self.key(k)),
            Interpolation::Linear => {
                let (a, b) = (self.key(k), self.key(k + 1));
                for i in 0..self.width {
                    out[i] = lerp(a[i], b[i], s);
                }
            }
            Interpolation::CubicSpline => self.hermite(k, s, out),
        }
    }

    /// Evaluates a rotation at time `t`: a unit quaternion.
    #[must_use]
    pub fn sample_rotation(&self, t: f64) -> DQuat {
        debug_assert_eq!(self.width, 4);
        let quat = |v: &[f64]| DQuat::from_xyzw(v[0], v[1], v[2], v[3]);
        let (k, s) = match self.locate(t) {
            Ok(segment) => segment,
            Err(key) => return normalize(quat(self.key(key))),
        };
        match self.interpolation {
            Interpolation::Step => normalize(quat(self.key(k))),
            Interpolation::Linear => slerp(quat(self.key(k)), quat(self.key(k + 1)), s),
            Interpolation::CubicSpline => {
                let mut v = [0.0; 4];
                self.hermite(k, s, &mut v);
                normalize(quat(&v))
            }
        }
    }

    /// The cubic Hermite spline of glTF 2.0 Appendix C between keys `k` and `k + 1`:
    /// `p(s) = (2s³ − 3s² + 1) v_k + (s³ − 2s² + s) Δt b_k + (−2s³ + 3s²) v_k+1 + (s³ − s²) Δt a_k+1`
    /// with `b_k` the out-tangent of key k, `a_k+1` the in-tangent of key k+1, `Δt` the duration.
    fn hermite(&self, k: usize, s: f64, out: &mut [f64]) {
        let w = self.width;
        let dt = self.times[k + 1] - self.times[k];
        let at = |key: usize, part: usize, i: usize| self.values[(3 * key + part) * w + i];
        let (s2, s3) = (s * s, s * s * s);
        let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
        let h10 = s3 - 2.0 * s2 + s;
        let h01 = -2.0 * s3 + 3.0 * s2;
        let h11 = s3 - s2;
        for (i, o) in out.iter_mut().enumerate() {
            *o = h00 * at(k, 1, i)
                + h10 * dt * at(k, 2, i)
                + h01 * at(k + 1, 1, i)
                + h11 * dt * at(k + 1, 0, i);
        }
    }
}

/// `a + s (b − a)`: exact at s = 0, and returns `a` exactly when `a == b`, so an animated
/// channel whose values never change leaves the object static.
#[must_use]
fn lerp(a: f64, b: f64, s: f64) -> f64 {
    a + s * (b - a)
}

/// Normalises a quaternion; a zero quaternion (already refused at load) becomes the identity.
#[must_use]
fn normalize(q: DQuat) -> DQuat {
    let len = q.length();
    if len > 0.0 && len.is_finite() {
        q / len
    } else {
        DQuat::IDENTITY
    }
}

/// Spherical linear interpolation on the short path (glTF 2.0 Appendix C). Close quaternions
/// fall back to normalised lerp of the keys as stored, which gives exactly the clamped key value
/// when `a == b`.
#[must_use]
fn slerp(a: DQuat, b: DQuat, s: f64) -> DQuat {
    let (na, mut nb, mut b) = (normalize(a), normalize(b), b);
    let mut d = na.dot(nb);
    if d < 0.0 {
        (b, nb, d) = (-b, -nb, -d);
    }
    if d > 0.9995 {
        let (a, b) = (a.to_array(), b.to_array());
        return normalize(DQuat::from_array([0, 1, 2, 3].map(|i| lerp(a[i], b[i], s))));
    }
    let angle = d.min(1.0).acos();
    let sin = angle.sin();
    let wa = ((1.0 - s) * angle).sin() / sin;
    let wb = (s * angle).sin() / sin;
    normalize(DQuat::from_vec4(
        glam::DVec4::from(na) * wa + glam::DVec4::from(nb) * wb,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    fn sampler(times: &[f64], values: &[f64], width: usize, i: Interpolation) -> Sampler {
        Sampler::new(times.to_vec(), values.to_vec(), width, i).unwrap()
    }

    fn at(s: &Sampler, t: f64) -> Vec<f64> {
        let mut out = vec![0.0; s.width()];
        s.sample(t, &mut out);
        out
    }

    #[test]
    fn step_holds_each_key_and_clamps() {
        let s = sampler(
            &[1.0, 2.0, 4.0],
            &[10.0, 20.0, 40.0],
            1,
            Interpolation::Step,
        );
        assert_eq!(at(&s, 0.0), [10.0]);
        assert_eq!(at(&s, 1.0), [10.0]);
        assert_eq!(at(&s, 1.999), [10.0]);
        assert_eq!(at(&s, 2.0), [20.0]);
        assert_eq!(at(&s, 3.9), [20.0]);
        assert_eq!(at(&s, 4.0), [40.0]);
        assert_eq!(at(&s, 100.0), [40.0]);
    }

    #[test]
    fn linear_interpolates_per_component() {
        let s = sampler(
            &[0.0, 2.0],
            &[0.0, 10.0, -4.0, 4.0, 20.0, 4.0],
            3,
            Interpolation::Linear,
        );
        assert_eq!(at(&s, 0.5), [1.0, 12.5, -2.0]);
        assert_eq!(at(&s, 1.0), [2.0, 15.0, 0.0]);
        assert_eq!(at(&s, -1.0), [0.0, 10.0, -4.0]);
        assert_eq!(at(&s, 3.0), [4.0, 20.0, 4.0]);
    }

    #[test]
    fn constant_channels_are_exactly_constant() {
        let v = [0.1, 0.7, -3.3];
        let s = sampler(
            &[0.0, 0.3, 1.7],
            &[v, v, v].concat(),
            3,
            Interpolation::Linear,
        );
        for k in 0..100 {
            assert_eq!(at(&s, k as f64 * 0.0173), v);
        }
        let q = DQuat::from_rotation_y(0.3);
        let qs = [q.to_array(), q.to_array()].concat();
        let r = sampler(&[0.0, 1.0], &qs, 4, Interpolation::Linear);
        let first = r.sample_rotation(0.0);
        for k in 0..100 {
            assert_eq!(r.sample_rotation(k as f64 * 0.01), first);
        }
    }

    #[test]
    fn linear_rotation_is_slerp_on_the_short_path() {
        // 0° to 90° about Y: halfway is 45°.
        let a = DQuat::IDENTITY;
        let b = DQuat::from_rotation_y(FRAC_PI_2);
        let s = sampler(
            &[0.0, 1.0],
            &[a.to_array(), b.to_array()].concat(),
            4,
            Interpolation::Linear,
        );
        let q = s.sample_rotation(0.5);
        assert!(
            q.abs_diff_eq(DQuat::from_rotation_y(FRAC_PI_2 / 2.0), 1e-12),
            "{q}"
        );
        // The same rotation given with the opposite sign must not take the long way round.
        let s = sampler(
            &[0.0, 1.0],
            &[a.to_array(), (-b).to_array()].concat(),
            4,
            Interpolation::Linear,
        );
        let q = s.sample_rotation(0.5);
        let expected = DQuat::from_rotation_y(FRAC_PI_2 / 2.0);
        assert!(
            q.abs_diff_eq(expected, 1e-12) || q.abs_diff_eq(-expected, 1e-12),
            "{q}"
        );
        // A quarter of the way: 22.5°, which nlerp would miss.
        let q = s.sample_rotation(0.25);
        let expected = DQuat::from_rotation_y(FRAC_PI_2 / 4.0);
        assert!(
            q.abs_diff_eq(expected, 1e-12) || q.abs_diff_eq(-expected, 1e-12),
            "{q}"
        );
    }

    #[test]
    fn cubic_spline_matches_hand_computed_values() {
        // Keys at t = 1 and t = 3 (Δt = 2), values 0 and 1, out-tangent of key 0 = 1,
        // in-tangent of key 1 = 2. Layout per key: in, value, out.
        let s = sampler(
            &[1.0, 3.0],
            &[9.0, 0.0, 1.0, 2.0, 1.0, 9.0],
            1,
            Interpolation::CubicSpline,
        );
        // s = 0.5: h00 = 0.5, h10 = 0.125, h01 = 0.5, h11 = −0.125.
        // p = 0.5·0 + 0.125·2·1 + 0.5·1 − 0.125·2·2 = 0.25 + 0.5 − 0.5 = 0.25.
        assert!((at(&s, 2.0)[0] - 0.25).abs() < 1e-15);
        // s = 0.25: h00 = 0.84375, h10 = 0.140625, h01 = 0.15625, h11 = −0.046875.
        // p = 0.140625·2 + 0.15625 − 0.046875·4 = 0.28125 + 0.15625 − 0.1875 = 0.25.
        assert!((at(&s, 1.5)[0] - 0.25).abs() < 1e-15);
        // Keys are hit exactly; outside the keys the value is clamped (tangents ignored).
        assert_eq!(at(&s, 1.0), [0.0]);
        assert_eq!(at(&s, 3.0), [1.0]);
        assert_eq!(at(&s, 0.0), [0.0]);
        assert_eq!(at(&s, 5.0), [1.0]);
    }

    #[test]
    fn cubic_spline_rotations_are_normalised() {
        let a = DQuat::IDENTITY.to_array();
        let b = DQuat::from_rotation_x(1.0).to_array();
        let z = [0.0; 4];
        let s = sampler(
            &[0.0, 1.0],
            &[z, a, z, z, b, z].concat(),
            4,
            Interpolation::CubicSpline,
        );
        for k in 0..=10 {
            let q = s.sample_rotation(k as f64 / 10.0);
            assert!((q.length() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn bad_samplers_are_refused() {
        assert!(Sampler::new(vec![], vec![], 1, Interpolation::Linear).is_err());
        assert!(Sampler::new(vec![1.0, 0.0], vec![0.0, 0.0], 1, Interpolation::Linear).is_err());
        assert!(Sampler::new(vec![0.0, 1.0], vec![0.0], 1, Interpolation::Linear).is_err());
        assert!(Sampler::new(vec![0.0, 1.0], vec![0.0; 2], 1, Interpolation::CubicSpline).is_err());
        // Repeated times are a jump, not a division by zero.
        let s = sampler(
            &[0.0, 1.0, 1.0, 2.0],
            &[0.0, 1.0, 5.0, 6.0],
            1,
            Interpolation::Linear,
        );
        assert_eq!(at(&s, 1.0), [5.0]);
        assert_eq!(at(&s, 0.5), [0.5]);
        assert_eq!(at(&s, 1.5), [5.5]);
    }
}
