//! Synthetic scenes as height fields z(x, y) with analytic normals, a mask and an albedo map.
//!
//! Coordinates: pixel (column c, row r) of a W×H image is at x = c − (W−1)/2, y = (H−1)/2 − r
//! (x right, y up, pixel units); z is height towards the camera. A scene is the upper envelope
//! (pointwise maximum) of its primitives, optionally standing on a ground plane z = 0.

use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use nalgebra::Vector3;

/// A surface patch z = f(x, y) over part of the image plane.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Primitive {
    /// Upper half of a sphere of radius `radius` centred at (cx, cy, `base`).
    Sphere {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Radius (pixels).
        radius: f64,
        /// Height of the centre.
        base: f64,
    },
    /// Gaussian bump z = base + height·exp(−d²/2σ²), cut where it falls below `base`.
    Gaussian {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Standard deviation (pixels).
        sigma: f64,
        /// Peak height above `base`.
        height: f64,
        /// Base height.
        base: f64,
    },
    /// Square pyramid of half-width `half` and apex height `height` above `base`: planar facets
    /// meeting at creases (gradient discontinuities).
    Pyramid {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Half the base width.
        half: f64,
        /// Apex height above `base`.
        height: f64,
        /// Base height.
        base: f64,
    },
}

impl Primitive {
    /// Height and unit normal at (x, y), or `None` outside the primitive's footprint.
    pub fn eval(&self, x: f64, y: f64) -> Option<(f64, Vector3<f64>)> {
        match *self {
            Primitive::Sphere {
                cx,
                cy,
                radius,
                base,
            } => {
                let (dx, dy) = (x - cx, y - cy);
                let h2 = radius * radius - dx * dx - dy * dy;
                (h2 >= 0.0).then(|| {
                    let h = h2.sqrt();
                    (base + h, Vector3::new(dx, dy, h) / radius)
                })
            }
            Primitive::Gaussian {
                cx,
                cy,
                sigma,
                height,
                base,
            } => {
                let (dx, dy) = (x - cx, y - cy);
                let e = height * (-(dx * dx + dy * dy) / (2.0 * sigma * sigma)).exp();
                // Footprint: out to 4σ.
                (dx * dx + dy * dy <= 16.0 * sigma * sigma).then(|| {
                    let (zx, zy) = (-e * dx / (sigma * sigma), -e * dy / (sigma * sigma));
                    (base + e, Vector3::new(-zx, -zy, 1.0).normalize())
                })
            }
            Primitive::Pyramid {
                cx,
                cy,
                half,
                height,
                base,
            } => {
                let (dx, dy) = (x - cx, y - cy);
                let m = dx.abs().max(dy.abs());
                (m <= half).then(|| {
                    let s = height / half;
                    let (zx, zy) = if dx.abs() >= dy.abs() {
                        (-s * dx.signum(), 0.0)
                    } else {
                        (0.0, -s * dy.signum())
                    };
                    (
                        base + height * (1.0 - m / half),
                        Vector3::new(-zx, -zy, 1.0).normalize(),
                    )
                })
            }
        }
    }
}

/// How albedo varies over a surface.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum Albedo {
    /// The same everywhere.
    Constant(f32),
    /// Squares of side `size` pixels alternating between `a` and `b`.
    Checker {
        /// Square side (pixels).
        size: f64,
        /// First value.
        a: f32,
        /// Second value.
        b: f32,
    },
    /// Smooth texture mean + amplitude·sin(2πx/period)·sin(2πy/period).
    Smooth {
        /// Mean albedo.
        mean: f32,
        /// Amplitude (mean ± amplitude must stay in (0, 1]).
        amplitude: f32,
        /// Period (pixels).
        period: f64,
    },
}

impl Albedo {
    /// The albedo at (x, y).
    pub fn at(&self, x: f64, y: f64) -> f32 {
        match *self {
            Albedo::Constant(a) => a,
            Albedo::Checker { size, a, b } => {
                let k = (x / size).floor() as i64 + (y / size).floor() as i64;
                if k.rem_euclid(2) == 0 { a } else { b }
            }
            Albedo::Smooth {
                mean,
                amplitude,
                period,
            } => {
                let w = 2.0 * std::f64::consts::PI / period;
                mean + amplitude * ((w * x).sin() * (w * y).sin()) as f32
            }
        }
    }
}

/// A scene: primitives, each with an albedo, over an optional ground plane.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Surfaces and their albedo; the highest one at a pixel is the one seen.
    pub objects: Vec<(Primitive, Albedo)>,
    /// Albedo of a ground plane z = 0 filling the image, or `None` for no ground (pixels that no
    /// primitive covers are then outside the mask).
    pub ground: Option<Albedo>,
}

/// What a scene looks like from the camera: depth, normals, albedo and mask per pixel.
#[derive(Debug, Clone)]
pub struct HeightField {
    /// Height towards the camera (pixel units); NaN outside the mask.
    pub depth: ScalarMap,
    /// Unit normals; NaN outside the mask.
    pub normals: NormalMap,
    /// Albedo; NaN outside the mask.
    pub albedo: ScalarMap,
    /// Pixels covered by a surface.
    pub mask: Mask,
}

impl Scene {
    /// A single sphere of radius `radius` (pixels) centred in a `size`×`size` image, with no
    /// ground and constant albedo: the classic photometric-stereo test object.
    pub fn sphere(size: usize, radius: f64, albedo: Albedo) -> Self {
        Scene {
            width: size,
            height: size,
            objects: vec![(
                Primitive::Sphere {
                    cx: 0.0,
                    cy: 0.0,
                    radius,
                    base: 0.0,
                },
                albedo,
            )],
            ground: None,
        }
    }

    /// The built-in default scene: a textured hemisphere, a Gaussian bump, a pyramid and a
    /// shallow dome on a checkered ground plane (320×240). Objects cast shadows on the ground.
    pub fn default_scene() -> Self {
        Scene {
            width: 320,
            height: 240,
            objects: vec![
                (
                    Primitive::Sphere {
                        cx: -70.0,
                        cy: 15.0,
                        radius: 62.0,
                        base: 0.0,
                    },
                    Albedo::Smooth {
                        mean: 0.6,
                        amplitude: 0.25,
                        period: 40.0,
                    },
                ),
                (
                    Primitive::Gaussian {
                        cx: 80.0,
                        cy: 45.0,
                        sigma: 20.0,
                        height: 30.0,
                        base: 0.0,
                    },
                    Albedo::Constant(0.8),
                ),
                (
                    Primitive::Pyramid {
                        cx: 75.0,
                        cy: -60.0,
                        half: 35.0,
                        height: 28.0,
                        base: 0.0,
                    },
                    Albedo::Constant(0.7),
                ),
                (
                    Primitive::Sphere {
                        cx: -40.0,
                        cy: -80.0,
                        radius: 60.0,
                        base: -42.0,
                    },
                    Albedo::Constant(0.5),
                ),
            ],
            ground: Some(Albedo::Checker {
                size: 20.0,
                a: 0.35,
                b: 0.5,
            }),
        }
    }

    /// Pixel centre (x, y) of column `c`, row `r`.
    pub fn pixel_xy(&self, c: usize, r: usize) -> (f64, f64) {
        (
            c as f64 - (self.width as f64 - 1.0) / 2.0,
            (self.height as f64 - 1.0) / 2.0 - r as f64,
        )
    }

    /// Height of the visible surface at any point (x, y) of the image plane (not only pixel
    /// centres), or `None` where nothing is.
    pub fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        let ground = self.ground.map(|_| 0.0);
        self.objects
            .iter()
            .filter_map(|(p, _)| p.eval(x, y).map(|(z, _)| z))
            .chain(ground)
            .reduce(f64::max)
    }

    /// Evaluates the scene at every pixel centre.
    pub fn height_field(&self) -> HeightField {
        let (w, h) = (self.width, self.height);
        let mut depth = Grid::new(w, h, f32::NAN);
        let mut normals = Grid::new(w, h, Vector3::repeat(f32::NAN));
        let mut albedo = Grid::new(w, h, f32::NAN);
        let mut mask = Grid::new(w, h, false);
        for r in 0..h {
            for c in 0..w {
                let (x, y) = self.pixel_xy(c, r);
                let mut best: Option<(f64, Vector3<f64>, f32)> =
                    self.ground.map(|g| (0.0, Vector3::z(), g.at(x, y)));
                for (prim, alb) in &self.objects {
                    if let Some((z, n)) = prim.eval(x, y)
                        && best.is_none_or(|(bz, _, _)| z > bz)
                    {
                        best = Some((z, n, alb.at(x, y)));
                    }
                }
                if let Some((z, n, a)) = best {
                    *depth.at_mut(c, r) = z as f32;
                    *normals.at_mut(c, r) = n.cast::<f32>();
                    *albedo.at_mut(c, r) = a;
                    *mask.at_mut(c, r) = true;
                }
            }
        }
        HeightField {
            depth,
            normals,
            albedo,
            mask,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_normals_are_radial_and_unit() {
        let hf = Scene::sphere(41, 15.0, Albedo::Constant(0.5)).height_field();
        // Centre pixel looks straight at the camera.
        let n = hf.normals.at(20, 20);
        assert!((n.z - 1.0).abs() < 1e-6);
        // One pixel right of centre: x = 1 → n_x = 1/15; row above: y = +1 → n_y > 0.
        assert!((hf.normals.at(21, 20).x - 1.0 / 15.0).abs() < 1e-6);
        assert!(hf.normals.at(20, 19).y > 0.0);
        assert!(!*hf.mask.at(0, 0));
        assert!((hf.depth.at(20, 20) - 15.0).abs() < 1e-6);
    }

    #[test]
    fn gradients_match_finite_differences() {
        // For every primitive, −n_x/n_z ≈ ∂z/∂x away from creases.
        let prims = [
            Primitive::Gaussian {
                cx: 0.0,
                cy: 0.0,
                sigma: 5.0,
                height: 4.0,
                base: 0.0,
            },
            Primitive::Sphere {
                cx: 0.0,
                cy: 0.0,
                radius: 10.0,
                base: 0.0,
            },
            Primitive::Pyramid {
                cx: 0.0,
                cy: 0.0,
                half: 10.0,
                height: 5.0,
                base: 0.0,
            },
        ];
        for prim in prims {
            let (x, y, d) = (2.3, -1.1, 1e-5);
            let (z, n) = prim.eval(x, y).unwrap();
            let zx = (prim.eval(x + d, y).unwrap().0 - z) / d;
            let zy = (prim.eval(x, y + d).unwrap().0 - z) / d;
            assert!((zx + n.x / n.z).abs() < 1e-3, "{prim:?}");
            assert!((zy + n.y / n.z).abs() < 1e-3, "{prim:?}");
        }
    }
}
