//! Calibration captures of mirror balls: one or more chrome balls in front of a plain or
//! textured wall, photographed under one lamp per image, with the lamps' true directions (or
//! positions) as ground truth. They are what [`crate::calibrate`] is tested on, in the variety
//! a user's captures have: balls brighter or darker than the wall, partly outside the frame,
//! 30–400 px in radius, noisy, with secondary reflections and a second ball.
//!
//! Each pixel is the mean of `supersampling`² samples over its area (so the ball's outline
//! and the highlights are anti-aliased as a lens and sensor make them). A sample on a ball sees
//! the mirror reflection r = 2(n·v)n − v of the view direction v (orthographic, v = (0, 0, 1),
//! or the ray through the sample with a pinhole camera), weighted by the ball's reflectance: a
//! lamp's radiance where r points into the lamp's disc, else the environment's radiance, which
//! varies smoothly with r (brighter above). A sample off the balls sees the wall. Noise is
//! Gaussian, added before the values are clipped to [0, 1] (a sensor saturates) and quantised
//! to the requested depth.

use super::hash_unit;
use crate::calibrate::sphere::Circle;
use crate::camera::Intrinsics;
use nalgebra::Vector3;
use rayon::prelude::*;

/// A lamp: a disc of uniform radiance, seen from the balls at a direction (a distant lamp) or
/// placed at a position (a near one, in the camera frame with pixels as the unit of length
/// and the ball centres at depth 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lamp {
    /// Where the lamp is.
    pub place: LampPlace,
    /// Angular radius of the lamp's disc in degrees (for a near lamp: seen from the origin).
    pub radius_deg: f64,
    /// Radiance of the disc, in units of the full scale of the image (above 1 it saturates).
    pub radiance: f64,
}

/// A lamp's direction (distant) or position (near).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LampPlace {
    /// Unit direction towards the lamp, camera frame (x right, y up, z to the camera).
    Direction(Vector3<f64>),
    /// Position, camera frame, pixels.
    Position(Vector3<f64>),
}

/// The wall behind the balls.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Wall {
    /// Uniform brightness, with a gentle left-to-right gradient of `slope` per image width.
    Plain {
        /// Brightness.
        level: f64,
        /// Change across the image's width.
        slope: f64,
    },
    /// A brightness of `level` ± `contrast` in random rectangles and discs of about `cell` px
    /// (sharp-edged: a poster, tiles, a cluttered lab), drawn from `seed`.
    Textured {
        /// Mean brightness.
        level: f64,
        /// Half the range of the patches' brightness.
        contrast: f64,
        /// Typical patch size in pixels.
        cell: f64,
        /// Seed of the patches.
        seed: u64,
    },
}

/// How the images are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Depth {
    /// 8-bit codes, sRGB-encoded (as cameras write them).
    Srgb8,
    /// 16-bit linear codes.
    Linear16,
    /// 32-bit float, linear, not quantised.
    Float,
}

/// One calibration capture to render.
#[derive(Debug, Clone, PartialEq)]
pub struct ChromeCapture {
    /// Image columns.
    pub width: usize,
    /// Image rows.
    pub height: usize,
    /// The balls' outlines (pixel coordinates; they must not overlap).
    pub balls: Vec<Circle>,
    /// The balls' reflectance (a chrome ball reflects 0.5–0.8 of the light).
    pub reflectance: f64,
    /// The environment's radiance reflected by the balls: `environment` at the horizon, plus
    /// `environment_slope` × r_y (brighter above).
    pub environment: f64,
    /// See [`ChromeCapture::environment`].
    pub environment_slope: f64,
    /// The wall.
    pub wall: Wall,
    /// The wall's brightness in each image, as a factor of [`ChromeCapture::wall`]'s (the
    /// lamps light the wall too, each its own amount); missing entries are 1.
    pub wall_gain: Vec<f64>,
    /// One lamp per image: the light to calibrate.
    pub lamps: Vec<Lamp>,
    /// Further sources lit in every image with its lamp, as a fraction of that lamp's radiance
    /// and at a fixed rotation of its direction: the lamp's reflection in a glossy table below
    /// the balls (direction mirrored in the horizontal plane), giving each image a secondary
    /// highlight. 0: none.
    pub table_reflection: f64,
    /// Noise standard deviation (full scale = 1), added before clipping and quantising.
    pub noise: f64,
    /// Samples per pixel along each axis.
    pub supersampling: usize,
    /// The camera: `None` orthographic, else a pinhole with these intrinsics, the balls' centres
    /// at depth `distance` along the optical axis (pixels as units).
    pub camera: Option<(Intrinsics, f64)>,
    /// Stored depth.
    pub depth: Depth,
    /// Seed of the noise.
    pub seed: u64,
}

/// A rendered capture: the images as stored (values in [0, 1] on the stored code grid: k/255
/// sRGB-encoded for [`Depth::Srgb8`], k/65535 for [`Depth::Linear16`]), one per lamp.
#[derive(Debug, Clone)]
pub struct ChromeImages {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Row-major planes, one per lamp.
    pub images: Vec<Vec<f32>>,
}

impl ChromeImages {
    /// The images as 8-bit codes (for [`Depth::Srgb8`] captures).
    pub fn to_u8(&self) -> Vec<Vec<u8>> {
        self.images
            .iter()
            .map(|p| p.iter().map(|v| (v * 255.0).round() as u8).collect())
            .collect()
    }

    /// The images as 16-bit codes (for [`Depth::Linear16`] captures).
    pub fn to_u16(&self) -> Vec<Vec<u16>> {
        self.images
            .iter()
            .map(|p| p.iter().map(|v| (v * 65535.0).round() as u16).collect())
            .collect()
    }
}

impl ChromeCapture {
    /// The unit direction from ball `ball`'s centre towards lamp `k` (the lamp's direction for a
    /// distant lamp): the light a calibration from that ball should find. `None` for a lamp or
    /// ball that is not there.
    pub fn light_direction(&self, k: usize, ball: usize) -> Option<Vector3<f64>> {
        Some(match self.lamps.get(k)?.place {
            LampPlace::Direction(d) => d.normalize(),
            LampPlace::Position(p) => (p - self.ball_centre(ball)?).normalize(),
        })
    }

    /// Ball `ball`'s centre in the camera frame (pixels; x right, y up, depth 0 orthographic or
    /// −distance along the axis under a pinhole, the camera at the origin looking down −z).
    /// `None` for a ball that is not there.
    pub fn ball_centre(&self, ball: usize) -> Option<Vector3<f64>> {
        let c = self.balls.get(ball)?;
        Some(match &self.camera {
            None => Vector3::new(c.cx, -c.cy, 0.0),
            Some((k, distance)) => {
                let x = (c.cx - k.cx) / k.fx * distance;
                let y = -(c.cy - k.cy) / k.fy * distance;
                Vector3::new(x, y, -distance)
            }
        })
    }

    /// Renders the images.
    pub fn render(&self) -> ChromeImages {
        let (w, h) = (self.width, self.height);
        let s = self.supersampling.max(1);
        let images = (0..self.lamps.len())
            .into_par_iter()
            .map(|k| {
                let mut plane = vec![0.0f32; w * h];
                for (y, row) in plane.chunks_exact_mut(w.max(1)).enumerate() {
                    for (x, out) in row.iter_mut().enumerate() {
                        let mut sum = 0.0;
                        for j in 0..s {
                            for i in 0..s {
                                let px = x as f64 - 0.5 + (i as f64 + 0.5) / s as f64;
                                let py = y as f64 - 0.5 + (j as f64 + 0.5) / s as f64;
                                sum += self.radiance(k, px, py);
                            }
                        }
                        let mean = sum / (s * s) as f64;
                        let p = (y * w + x) as u64;
                        *out = self.store(mean + self.noise * gaussian(self.seed, k as u64, p));
                    }
                }
                plane
            })
            .collect();
        ChromeImages {
            width: w,
            height: h,
            images,
        }
    }

    /// The stored value of a linear value.
    fn store(&self, v: f64) -> f32 {
        let v = v.clamp(0.0, 1.0);
        match self.depth {
            Depth::Float => v as f32,
            Depth::Linear16 => ((v * 65535.0).round() / 65535.0) as f32,
            Depth::Srgb8 => {
                let e = if v <= 0.003_130_8 {
                    12.92 * v
                } else {
                    1.055 * v.powf(1.0 / 2.4) - 0.055
                };
                ((e * 255.0).round() / 255.0) as f32
            }
        }
    }

    /// Radiance seen at image point (x, y) in image `k`.
    fn radiance(&self, k: usize, x: f64, y: f64) -> f64 {
        let view = match &self.camera {
            None => Vector3::z(),
            Some((kk, _)) => {
                Vector3::new(-(x - kk.cx) / kk.fx, (y - kk.cy) / kk.fy, 1.0).normalize()
            }
        };
        for (b, c) in self.balls.iter().enumerate() {
            let Some(point) = self.hit(b, c, x, y, &view) else {
                continue;
            };
            let Some(centre) = self.ball_centre(b) else {
                continue;
            };
            let n = (point - centre).normalize();
            let r = 2.0 * n.dot(&view) * n - view;
            let lamp = &self.lamps[k];
            let mut value = self.environment + self.environment_slope * r.y;
            if lamp_covers(lamp, &point, &r) {
                value = lamp.radiance;
            }
            if self.table_reflection > 0.0 {
                let mirrored = Lamp {
                    place: match lamp.place {
                        LampPlace::Direction(d) => {
                            LampPlace::Direction(Vector3::new(d.x, -d.y, d.z))
                        }
                        LampPlace::Position(p) => LampPlace::Position(Vector3::new(p.x, -p.y, p.z)),
                    },
                    ..*lamp
                };
                if lamp_covers(&mirrored, &point, &r) {
                    value = value.max(self.table_reflection * lamp.radiance);
                }
            }
            return self.reflectance * value.max(0.0);
        }
        self.wall_at(x, y) * self.wall_gain.get(k).copied().unwrap_or(1.0)
    }

    /// Where the ray of image point (x, y) meets ball `b` (camera frame), if it does.
    fn hit(
        &self,
        b: usize,
        c: &Circle,
        x: f64,
        y: f64,
        view: &Vector3<f64>,
    ) -> Option<Vector3<f64>> {
        match &self.camera {
            None => {
                let (dx, dy) = (x - c.cx, -(y - c.cy));
                let s = c.radius * c.radius - dx * dx - dy * dy;
                (s > 0.0).then(|| Vector3::new(x, -y, s.sqrt()))
            }
            Some(_) => {
                // The ray from the camera at the origin along −view; the ball's radius in
                // the scene is its image radius at its centre's depth.
                let centre = self.ball_centre(b)?;
                let (kk, distance) = self.camera.as_ref()?;
                let radius = c.radius / kk.fx * distance;
                let d = -view;
                let tc = d.dot(&centre);
                let s = radius * radius - (centre - tc * d).norm_squared();
                (s > 0.0).then(|| (tc - s.sqrt()) * d)
            }
        }
    }

    /// The wall's brightness at (x, y).
    fn wall_at(&self, x: f64, y: f64) -> f64 {
        match self.wall {
            Wall::Plain { level, slope } => level + slope * (x / self.width.max(1) as f64 - 0.5),
            Wall::Textured {
                level,
                contrast,
                cell,
                seed,
            } => {
                // Patches on a jittered grid of `cell` px: each cell holds a rectangle or a
                // disc of its own brightness, a little larger or smaller than the cell.
                let (gx, gy) = ((x / cell).floor(), (y / cell).floor());
                let mut value = level;
                for oy in -1..=1 {
                    for ox in -1..=1 {
                        let (cx, cy) = (gx + f64::from(ox), gy + f64::from(oy));
                        let id = ((cx as i64 as u64) << 32) ^ (cy as i64 as u64 & 0xFFFF_FFFF);
                        let u = |j: u64| hash_unit(seed, id, j);
                        if u(0) < 0.4 {
                            continue;
                        }
                        let (px, py) = ((cx + u(1)) * cell, (cy + u(2)) * cell);
                        let size = cell * (0.3 + 0.6 * u(3));
                        let inside = if u(4) < 0.5 {
                            (x - px).abs() < size && (y - py).abs() < 0.7 * size
                        } else {
                            (x - px).hypot(y - py) < 0.6 * size
                        };
                        if inside {
                            value = level + contrast * (2.0 * u(5) - 1.0);
                        }
                    }
                }
                value
            }
        }
    }
}

/// Whether the ray leaving `point` along `r` enters the lamp's disc.
fn lamp_covers(lamp: &Lamp, point: &Vector3<f64>, r: &Vector3<f64>) -> bool {
    let cos = lamp.radius_deg.to_radians().cos();
    match lamp.place {
        LampPlace::Direction(d) => r.dot(&d.normalize()) >= cos,
        LampPlace::Position(p) => {
            // The disc's radius is its angular radius seen from the origin.
            let radius = p.norm() * lamp.radius_deg.to_radians().tan();
            let to = p - point;
            let t = to.dot(r);
            t > 0.0 && (to - t * r).norm() <= radius
        }
    }
}

/// A standard normal number hashed from (seed, image, pixel) (Box–Muller).
fn gaussian(seed: u64, image: u64, pixel: u64) -> f64 {
    let u1 = hash_unit(seed, image.wrapping_mul(2), pixel).max(1e-300);
    let u2 = hash_unit(seed, image.wrapping_mul(2) + 1, pixel);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
