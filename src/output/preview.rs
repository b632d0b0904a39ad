//! A small deterministic rasteriser for previews, and the PNG and GIF encoders.
//!
//! A colour per triangle corner interpolated across it (perspective-correct; equal corners
//! draw a flat triangle), a depth buffer, back faces culled (a closed room seen from outside
//! shows its inside: a dollhouse view), 2×2 supersampling averaged in linear light, then sRGB.
//! Shared edges are drawn exactly once (a tie rule on the edge functions), so a surface made of
//! many patches shows no cracks. The same input gives the same pixels on any machine and at any
//! thread count.

use glam::{DAffine3, DMat3, DVec2, DVec3};
use image::{ImageEncoder, RgbImage};

pub use crate::scene::Projection;

/// Samples per pixel side.
const SUPERSAMPLE: u32 = 2;

/// Largest side of a preview, pixels (the bake command's `--preview-size`, the service's
/// preview routes): a preview, not a render farm.
pub const MAX_PREVIEW_SIDE: u32 = 2048;

/// Colour behind everything, linear.
const BACKGROUND: [f32; 3] = [0.02, 0.02, 0.025];

/// A camera: where it is and how it projects.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Camera space to world space. Any scale in it is ignored (glTF's rule for cameras).
    pub pose: DAffine3,
    /// The projection, distances in world units.
    pub projection: Projection,
    /// The aspect ratio the camera asks for, if any. Previews keep the camera's vertical field
    /// of view and use the image's aspect ratio (glTF calls `aspectRatio` a hint).
    pub aspect: Option<f64>,
}

impl Camera {
    /// A perspective camera (vertical field of view 50°) that frames the sphere (`center`,
    /// `radius`) from above, in front and to the right (+Y up), for images of `aspect`.
    #[must_use]
    pub fn automatic(center: DVec3, radius: f64, aspect: f64) -> Self {
        let yfov = 50f64.to_radians();
        let half_y = yfov / 2.0;
        let half_x = (half_y.tan() * aspect.max(1e-3)).atan();
        let distance = 1.05 * radius / half_y.min(half_x).sin();
        let back = DVec3::new(0.6, 0.45, 0.9).normalize();
        let right = DVec3::Y.cross(back).normalize();
        let up = back.cross(right);
        Self {
            pose: DAffine3::from_mat3_translation(
                DMat3::from_cols(right, up, back),
                center + back * distance,
            ),
            projection: Projection::Perspective {
                yfov,
                znear: (distance - 1.1 * radius).max(distance * 1e-3),
                zfar: None,
            },
            aspect: None,
        }
    }

    /// World space to camera space, the pose's scale removed.
    fn view(&self) -> DAffine3 {
        rigid(self.pose).inverse()
    }
}

/// A camera's `pose` without scale or shear: a rotation (X along the pose's X, Y in the plane
/// of the pose's X and Y, Z = X × Y; the identity for a degenerate pose) and the translation.
#[must_use]
pub fn rigid(pose: DAffine3) -> DAffine3 {
    let m = pose.matrix3;
    let x = m.x_axis.normalize_or_zero();
    let y = (m.y_axis - x * x.dot(m.y_axis)).normalize_or_zero();
    let z = x.cross(y);
    let rotation = if z == DVec3::ZERO {
        DMat3::IDENTITY
    } else {
        DMat3::from_cols(x, y, z)
    };
    DAffine3::from_mat3_translation(rotation, pose.translation)
}

/// One triangle to draw.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Triangle {
    /// World-space corners, counter-clockwise seen from the front face.
    pub corners: [DVec3; 3],
    /// Display colour at each corner, linear, each channel in [0, 1].
    pub colours: [[f32; 3]; 3],
}

impl Triangle {
    /// A triangle of one colour.
    #[must_use]
    pub fn flat(corners: [DVec3; 3], colour: [f32; 3]) -> Self {
        Self {
            corners,
            colours: [colour; 3],
        }
    }
}

/// A vertex on screen: position in samples, the depth key (larger is nearer), the weight that
/// makes the interpolation of its colour perspective-correct (1 / distance, or 1 for an
/// orthographic camera) and its colour.
#[derive(Clone, Copy)]
struct Projected {
    p: DVec2,
    key: f64,
    weight: f64,
    colour: [f32; 3],
}

/// Memory a render of `width` × `height` holds while it runs, bytes: a depth, an owner and a
/// colour per sample.
#[must_use]
pub fn render_bytes(width: u32, height: u32) -> usize {
    let samples = (width.max(1) * SUPERSAMPLE) as usize * (height.max(1) * SUPERSAMPLE) as usize;
    samples
        * (std::mem::size_of::<f32>()
            + std::mem::size_of::<u32>()
            + std::mem::size_of::<[f32; 3]>())
}

/// Renders `triangles` seen by `camera` into a `width` × `height` sRGB image (sides of 0 are
/// taken as 1).
#[must_use]
pub fn render(triangles: &[Triangle], camera: &Camera, width: u32, height: u32) -> RgbImage {
    let (width, height) = (width.max(1), height.max(1));
    let (sw, sh) = (width * SUPERSAMPLE, height * SUPERSAMPLE);
    let aspect = f64::from(width) / f64::from(height);
    let view = camera.view();
    // Depth range kept: distances in front of the camera.
    let (near, far) = match camera.projection {
        Projection::Perspective { znear, zfar, .. } => (znear, zfar.unwrap_or(f64::INFINITY)),
        Projection::Orthographic { znear, zfar, .. } => (znear, zfar),
    };
    let project = |(c, colour): (DVec3, [f32; 3])| -> Projected {
        let distance = -c.z;
        let (ndc, key, weight) = match camera.projection {
            Projection::Perspective { yfov, .. } => {
                let t = (yfov / 2.0).tan();
                (
                    DVec2::new(c.x / (distance * t * aspect), c.y / (distance * t)),
                    1.0 / distance,
                    1.0 / distance,
                )
            }
            Projection::Orthographic { ymag, .. } => (
                DVec2::new(c.x / (ymag * aspect), c.y / ymag),
                -distance,
                1.0,
            ),
        };
        Projected {
            p: DVec2::new(
                (ndc.x + 1.0) * 0.5 * f64::from(sw),
                (1.0 - ndc.y) * 0.5 * f64::from(sh),
            ),
            key,
            weight,
            colour,
        }
    };
    let samples = (sw * sh) as usize;
    let mut buffers = Buffers {
        depth: vec![f32::NEG_INFINITY; samples],
        owner: vec![u32::MAX; samples],
        colour: vec![BACKGROUND; samples],
    };
    for (index, triangle) in triangles.iter().enumerate() {
        let corners = triangle.corners.map(|c| view.transform_point3(c));
        if corners.iter().any(|c| !c.is_finite()) {
            continue;
        }
        let polygon = clip(&corners, &triangle.colours, near, far);
        if polygon.len() < 3 {
            continue;
        }
        let screen: Vec<Projected> = polygon.into_iter().map(project).collect();
        for k in 1..screen.len() - 1 {
            fill(
                [screen[0], screen[k], screen[k + 1]],
                index as u32,
                (sw, sh),
                &mut buffers,
            );
        }
    }
    resolve(&buffers.colour, width, height)
}

/// What a render holds per sample: the nearest depth key so far, the triangle drawn there and
/// its colour.
struct Buffers {
    depth: Vec<f32>,
    owner: Vec<u32>,
    colour: Vec<[f32; 3]>,
}

/// The part of a camera-space triangle (with its corners' colours) between the distances
/// `near` and `far` (Sutherland–Hodgman against the two planes): a convex polygon of up to 5
/// corners, possibly empty, the colours interpolated along the cut edges.
fn clip(
    corners: &[DVec3; 3],
    colours: &[[f32; 3]; 3],
    near: f64,
    far: f64,
) -> Vec<(DVec3, [f32; 3])> {
    let mut polygon: Vec<(DVec3, [f32; 3])> = corners.iter().copied().zip(*colours).collect();
    // Signed distance inside each plane: distance − near ≥ 0 and far − distance ≥ 0.
    let planes: [&dyn Fn(DVec3) -> f64; 2] = [&|c| -c.z - near, &|c| far + c.z];
    for inside in planes {
        if polygon.iter().all(|&(c, _)| inside(c) >= 0.0) {
            continue;
        }
        let mut out = Vec::with_capacity(polygon.len() + 1);
        for (k, &a) in polygon.iter().enumerate() {
            let b = polygon[(k + 1) % polygon.len()];
            let (da, db) = (inside(a.0), inside(b.0));
            if da >= 0.0 {
                out.push(a);
            }
            if (da >= 0.0) != (db >= 0.0) {
                let t = da / (da - db);
                let colour = std::array::from_fn(|c| a.1[c] + (b.1[c] - a.1[c]) * t as f32);
                out.push((a.0 + (b.0 - a.0) * t, colour));
            }
        }
        polygon = out;
        if polygon.len() < 3 {
            return Vec::new();
        }
    }
    polygon
}

/// Whether a sample exactly on the edge `d` belongs to the triangle on its positive side. The
/// neighbour across a shared edge sees it as `−d` and gets the opposite answer, so the sample
/// is drawn once.
fn owns_edge(d: DVec2) -> bool {
    d.y > 0.0 || (d.y == 0.0 && d.x < 0.0)
}

/// Draws one screen triangle of `index` into the buffers, if it faces the camera.
fn fill(mut v: [Projected; 3], index: u32, (sw, sh): (u32, u32), buffers: &mut Buffers) {
    let area = (v[1].p - v[0].p).perp_dot(v[2].p - v[0].p);
    // With y pointing down, a front face (counter-clockwise in view) has a negative area here.
    // (NaN, from a degenerate projection, is not drawn either.)
    if area.is_nan() || area >= 0.0 {
        return;
    }
    v.swap(1, 2);
    let area = -area;
    let lo = v[0].p.min(v[1].p).min(v[2].p);
    let hi = v[0].p.max(v[1].p).max(v[2].p);
    let x0 = (lo.x - 0.5).ceil().max(0.0) as u32;
    let y0 = (lo.y - 0.5).ceil().max(0.0) as u32;
    let x1 = ((hi.x - 0.5).floor().min(f64::from(sw) - 1.0)).max(-1.0);
    let y1 = ((hi.y - 0.5).floor().min(f64::from(sh) - 1.0)).max(-1.0);
    if x1 < 0.0 || y1 < 0.0 {
        return;
    }
    let (x1, y1) = (x1 as u32, y1 as u32);
    let edges = [(0, 1), (1, 2), (2, 0)].map(|(a, b)| (v[a].p, v[b].p - v[a].p));
    for y in y0..=y1 {
        let py = f64::from(y) + 0.5;
        for x in x0..=x1 {
            let p = DVec2::new(f64::from(x) + 0.5, py);
            let mut weights = [0.0; 3];
            let mut inside = true;
            for (k, &(origin, d)) in edges.iter().enumerate() {
                let e = d.perp_dot(p - origin);
                if e < 0.0 || (e == 0.0 && !owns_edge(d)) {
                    inside = false;
                    break;
                }
                // The edge from corner k is opposite corner k + 2.
                weights[(k + 2) % 3] = e / area;
            }
            if !inside {
                continue;
            }
            let key =
                (weights[0] * v[0].key + weights[1] * v[1].key + weights[2] * v[2].key) as f32;
            let s = (y * sw + x) as usize;
            if key > buffers.depth[s] {
                buffers.depth[s] = key;
                buffers.owner[s] = index;
                let w = weights.map(|w| w as f32);
                let q: [f32; 3] = std::array::from_fn(|k| w[k] * v[k].weight as f32);
                let total = q[0] + q[1] + q[2];
                buffers.colour[s] = std::array::from_fn(|c| {
                    (q[0] * v[0].colour[c] + q[1] * v[1].colour[c] + q[2] * v[2].colour[c]) / total
                });
            }
        }
    }
}

/// Averages the samples of each pixel in linear light and encodes sRGB.
fn resolve(colours: &[[f32; 3]], width: u32, height: u32) -> RgbImage {
    let sw = width * SUPERSAMPLE;
    let n = (SUPERSAMPLE * SUPERSAMPLE) as f32;
    RgbImage::from_fn(width, height, |x, y| {
        let mut sum = [0f32; 3];
        for sy in 0..SUPERSAMPLE {
            for sx in 0..SUPERSAMPLE {
                let s = ((y * SUPERSAMPLE + sy) * sw + x * SUPERSAMPLE + sx) as usize;
                let colour = colours[s];
                for c in 0..3 {
                    sum[c] += colour[c];
                }
            }
        }
        image::Rgb(sum.map(|c| srgb(c / n)))
    })
}

/// The sRGB encoding of a linear value in [0, 1] (IEC 61966-2-1), as 8 bits.
#[must_use]
pub fn srgb(linear: f32) -> u8 {
    let c = linear.clamp(0.0, 1.0);
    let encoded = if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (encoded * 255.0).round() as u8
}

/// PNG bytes of an image.
///
/// # Errors
/// The encoder's error (none is expected for an in-memory image).
pub fn encode_png(image: &RgbImage) -> Result<Vec<u8>, image::ImageError> {
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out).write_image(
        image.as_raw(),
        image.width(),
        image.height(),
        image::ExtendedColorType::Rgb8,
    )?;
    Ok(out)
}

/// An animated GIF, looping forever, each image shown for `delay_ms`.
///
/// # Errors
/// The encoder's error (for instance images of different sizes).
pub fn encode_gif(images: &[RgbImage], delay_ms: u32) -> Result<Vec<u8>, image::ImageError> {
    let mut out = Vec::new();
    {
        let mut encoder = image::codecs::gif::GifEncoder::new_with_speed(&mut out, 10);
        encoder.set_repeat(image::codecs::gif::Repeat::Infinite)?;
        let delay = image::Delay::from_numer_denom_ms(delay_ms, 1);
        encoder.encode_frames(images.iter().map(|rgb| {
            let rgba = image::DynamicImage::ImageRgb8(rgb.clone()).into_rgba8();
            image::Frame::from_parts(rgba, 0, 0, delay)
        }))?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera at z = 3 looking down −Z at the origin.
    fn front_camera() -> Camera {
        Camera {
            pose: DAffine3::from_translation(DVec3::new(0.0, 0.0, 3.0)),
            projection: Projection::Perspective {
                yfov: 60f64.to_radians(),
                znear: 0.1,
                zfar: None,
            },
            aspect: None,
        }
    }

    /// A square of half-side `h` at depth `z` facing +Z (towards the camera), or away.
    fn square(h: f64, z: f64, colour: [f32; 3], facing: bool) -> Vec<Triangle> {
        let c = [
            DVec3::new(-h, -h, z),
            DVec3::new(h, -h, z),
            DVec3::new(h, h, z),
            DVec3::new(-h, h, z),
        ];
        let tris = [[c[0], c[1], c[2]], [c[0], c[2], c[3]]];
        tris.iter()
            .map(|&[a, b, d]| Triangle::flat(if facing { [a, b, d] } else { [a, d, b] }, colour))
            .collect()
    }

    const RED: [f32; 3] = [1.0, 0.0, 0.0];
    const BLUE: [f32; 3] = [0.0, 0.0, 1.0];

    #[test]
    fn a_front_face_is_drawn_and_a_back_face_culled() {
        let image = render(&square(0.5, 0.0, RED, true), &front_camera(), 64, 48);
        assert_eq!(image.get_pixel(32, 24).0, [255, 0, 0]);
        assert_eq!(image.get_pixel(0, 0).0, BACKGROUND.map(srgb));
        let image = render(&square(0.5, 0.0, RED, false), &front_camera(), 64, 48);
        assert!(image.pixels().all(|p| p.0 == BACKGROUND.map(srgb)));
    }

    #[test]
    fn the_nearer_surface_wins_in_any_order() {
        let near = square(0.5, 0.5, RED, true);
        let far = square(1.0, 0.0, BLUE, true);
        for tris in [[near.clone(), far.clone()].concat(), [far, near].concat()] {
            let image = render(&tris, &front_camera(), 64, 48);
            assert_eq!(image.get_pixel(32, 24).0, [255, 0, 0]);
        }
    }

    #[test]
    fn shared_edges_leave_no_cracks() {
        // Many thin triangles of one colour fanning a square: every pixel well inside is
        // fully covered, so exactly the triangles' colour.
        let mut tris = Vec::new();
        let n = 37;
        for k in 0..n {
            let t0 = k as f64 / n as f64;
            let t1 = (k + 1) as f64 / n as f64;
            let edge = |t: f64| DVec3::new(-0.5 + t, 0.5, 0.0);
            tris.push(Triangle::flat(
                [DVec3::new(0.0, -0.5, 0.0), edge(t1), edge(t0)],
                RED,
            ));
        }
        let image = render(&tris, &front_camera(), 101, 101);
        let (mut covered, mut total) = (0, 0);
        for x in 0..101 {
            for y in 0..101 {
                let p = image.get_pixel(x, y).0;
                if p != BACKGROUND.map(srgb) {
                    total += 1;
                    covered += usize::from(p == [255, 0, 0]);
                }
            }
        }
        // The fan is a triangle about 29 pixels wide and high: only its outline is partial.
        assert!(
            total > 300 && covered as f64 > 0.8 * total as f64,
            "{covered}/{total}"
        );
        // No sample inside is missed: a row through its wide part is solid.
        for x in 42..=58 {
            assert_eq!(image.get_pixel(x, 40).0, [255, 0, 0], "x = {x}");
        }
    }

    #[test]
    fn a_sample_on_a_shared_edge_is_drawn_exactly_once() {
        // Two screen triangles splitting a square along its diagonal, which passes through
        // the sample centres (k + 0.5, k + 0.5).
        let at = |x: f64, y: f64| Projected {
            p: DVec2::new(x, y),
            key: 1.0,
            weight: 1.0,
            colour: RED,
        };
        let halves = [
            [at(2.5, 2.5), at(18.5, 18.5), at(18.5, 2.5)],
            [at(2.5, 2.5), at(2.5, 18.5), at(18.5, 18.5)],
        ];
        let size = (24, 24);
        let drawn: Vec<Vec<u32>> = halves
            .iter()
            .map(|&tri| {
                let mut buffers = Buffers {
                    depth: vec![f32::NEG_INFINITY; 24 * 24],
                    owner: vec![u32::MAX; 24 * 24],
                    colour: vec![BACKGROUND; 24 * 24],
                };
                fill(tri, 0, size, &mut buffers);
                buffers.owner
            })
            .collect();
        for y in 3..18 {
            for x in 3..18 {
                let s = y * 24 + x;
                let times = drawn.iter().filter(|o| o[s] == 0).count();
                assert_eq!(times, 1, "sample ({x}, {y})");
            }
        }
    }

    #[test]
    fn colours_are_interpolated_in_perspective_across_a_triangle() {
        // A floor strip receding from the camera, black at the near edge and white at the far
        // one: on screen the far half is squeezed, so the middle of the strip in the world
        // (grey 0.5) appears above the middle of the image's span of it. Linear interpolation
        // on screen would put 0.5 at the screen middle.
        let (near, far) = (1.0, 9.0);
        let c = |x: f64, z: f64| DVec3::new(x, -0.5, 3.0 - z);
        let (black, white) = ([0.0; 3], [1.0; 3]);
        let strip = [
            Triangle {
                corners: [c(-0.2, near), c(0.2, near), c(0.2, far)],
                colours: [black, black, white],
            },
            Triangle {
                corners: [c(-0.2, near), c(0.2, far), c(-0.2, far)],
                colours: [black, white, white],
            },
        ];
        let image = render(&strip, &front_camera(), 64, 480);
        let column: Vec<f32> = (0..480)
            .map(|y| image.get_pixel(32, y).0[0])
            .filter(|&v| v != BACKGROUND.map(srgb)[0])
            .map(|v| {
                // Back to linear.
                let e = f32::from(v) / 255.0;
                if e <= 0.04045 {
                    e / 12.92
                } else {
                    ((e + 0.055) / 1.055).powf(2.4)
                }
            })
            .collect();
        assert!(column.len() > 20, "{}", column.len());
        // Brightest at the far (upper) end, darkest at the near end, monotone between.
        assert!(
            column.first().unwrap() > &0.9 && column.last().unwrap() < &0.1,
            "{column:?}"
        );
        assert!(column.windows(2).all(|w| w[1] <= w[0] + 1e-2), "{column:?}");
        // The screen middle of the strip is nearer than its world middle, so darker than 0.5:
        // at distance d from the camera the value is (d − 1) / 8; the middle row is where
        // 1 / d is halfway between 1 and 1/9, d = 1.8, value 0.1.
        let middle = column[column.len() / 2];
        assert!((middle - 0.1).abs() < 0.05, "{middle}");
    }

    #[test]
    fn a_triangle_through_the_near_plane_is_clipped() {
        let tri = Triangle::flat(
            [
                DVec3::new(-1.0, -0.3, 0.0),
                DVec3::new(1.0, -0.3, 0.0),
                DVec3::new(0.0, -0.3, 10.0),
            ],
            RED,
        );
        // The third corner is behind the camera (z = 3); the floor-like triangle faces +Y, and
        // the camera sits above it.
        let tri = Triangle {
            corners: [tri.corners[0], tri.corners[2], tri.corners[1]],
            ..tri
        };
        let image = render(&[tri], &front_camera(), 64, 48);
        let red = image.pixels().filter(|p| p.0 == [255, 0, 0]).count();
        assert!(red > 100, "{red}");
        // The part above the horizon line of y = −0.3 stays empty.
        assert_eq!(image.get_pixel(32, 2).0, BACKGROUND.map(srgb));
    }

    #[test]
    fn the_automatic_camera_frames_the_sphere() {
        let center = DVec3::new(10.0, -3.0, 2.0);
        let radius = 4.0;
        // A cube inscribed in the sphere, faces outward: 12 triangles.
        let h = radius / 3f64.sqrt();
        let mut tris = Vec::new();
        for axis in 0..3 {
            for sign in [-1.0, 1.0] {
                let n = DVec3::AXES[axis] * sign;
                let u = DVec3::AXES[(axis + 1) % 3];
                let v = n.cross(u);
                let c = |a: f64, b: f64| center + (n + u * a + v * b) * h;
                tris.push(Triangle::flat(
                    [c(-1.0, -1.0), c(1.0, -1.0), c(1.0, 1.0)],
                    RED,
                ));
                tris.push(Triangle::flat(
                    [c(-1.0, -1.0), c(1.0, 1.0), c(-1.0, 1.0)],
                    RED,
                ));
            }
        }
        let (w, h_px) = (80, 60);
        let camera = Camera::automatic(center, radius, f64::from(w) / f64::from(h_px));
        let image = render(&tris, &camera, w, h_px);
        let background = BACKGROUND.map(srgb);
        let drawn = image.pixels().filter(|p| p.0 != background).count();
        assert!(drawn > (w * h_px) as usize / 10, "{drawn}");
        for x in 0..w {
            assert_eq!(image.get_pixel(x, 0).0, background);
            assert_eq!(image.get_pixel(x, h_px - 1).0, background);
        }
        for y in 0..h_px {
            assert_eq!(image.get_pixel(0, y).0, background);
            assert_eq!(image.get_pixel(w - 1, y).0, background);
        }
    }

    #[test]
    fn srgb_encoding() {
        assert_eq!(srgb(0.5), 188);
        assert_eq!(srgb(0.0), 0);
        assert_eq!(srgb(1.0), 255);
        assert_eq!(srgb(0.002), 7);
    }

    #[test]
    fn png_and_gif_decode_back() {
        let a = render(&square(0.5, 0.0, RED, true), &front_camera(), 32, 24);
        let b = render(&square(0.3, 0.0, BLUE, true), &front_camera(), 32, 24);
        let png = encode_png(&a).unwrap();
        let decoded = image::load_from_memory(&png).unwrap().into_rgb8();
        assert_eq!(decoded, a);
        let gif = encode_gif(&[a, b], 100).unwrap();
        assert_eq!(&gif[..6], b"GIF89a");
        use image::AnimationDecoder;
        let frames = image::codecs::gif::GifDecoder::new(std::io::Cursor::new(gif))
            .unwrap()
            .into_frames()
            .collect_frames()
            .unwrap();
        assert_eq!(frames.len(), 2);
    }
}
