//! Synthetic scenes as height fields z(x, y) with analytic normals, a mask, an albedo map and a
//! material per object.
//!
//! Coordinates: pixel (column c, row r) of a W×H image is at x = c − (W−1)/2, y = (H−1)/2 − r
//! (x right, y up, pixel units); z is height towards the camera. A scene is the upper envelope
//! (pointwise maximum) of its objects; pixels that no object covers are outside the mask. A
//! ground is simply a [`Primitive::Plane`] object.

use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::synth::reflectance::Material;
use nalgebra::Vector3;
use std::f64::consts::PI;

/// A surface patch z = f(x, y) over part (or all) of the image plane.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Primitive {
    /// The plane z = z0 + slope_x·x + slope_y·y over the whole image (a ground, or a ramp).
    Plane {
        /// Height at the image centre.
        z0: f64,
        /// ∂z/∂x.
        slope_x: f64,
        /// ∂z/∂y.
        slope_y: f64,
    },
    /// The plane z = z0 with a step of `height` for x ≥ x0: a depth discontinuity (the step's
    /// vertical wall is invisible to the orthographic camera but casts shadows).
    Step {
        /// Height of the low side.
        z0: f64,
        /// Position of the step edge.
        x0: f64,
        /// Height of the step (positive: the right side is higher).
        height: f64,
    },
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
    /// Upper half of the ellipsoid ((x−cx)/a)² + ((y−cy)/b)² + ((z−base)/c)² = 1.
    Ellipsoid {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Semi-axis along x.
        a: f64,
        /// Semi-axis along y.
        b: f64,
        /// Semi-axis along z.
        c: f64,
        /// Height of the centre.
        base: f64,
    },
    /// A vase: the surface of revolution about the vertical line x = cx of the radius profile
    /// r(u) = width·(0.62 + 0.22 sin(1.3πu + 0.5) − 0.12u²), u = (y − cy)/half_height ∈ [−1, 1];
    /// its front half z = base + √(r² − (x−cx)²).
    Vase {
        /// Axis x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Half the vase's height.
        half_height: f64,
        /// Radius scale.
        width: f64,
        /// Height of the axis.
        base: f64,
    },
    /// MATLAB's `peaks` surface, z = base + height·peaks((x−cx)/scale, (y−cy)/scale) over
    /// |x−cx|, |y−cy| ≤ 3·scale, with peaks(u, v) = 3(1−u)²e^(−u²−(v+1)²)
    /// − 10(u/5 − u³ − v⁵)e^(−u²−v²) − e^(−(u+1)²−v²)/3.
    Peaks {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Pixels per unit of the peaks domain [−3, 3].
        scale: f64,
        /// Pixels of height per unit of peaks.
        height: f64,
        /// Base height.
        base: f64,
    },
    /// A torus of radii (`major`, `minor`) lying on z = base, its tube height modulated by
    /// 1 + bumps·cos(lobes·θ) around the ring: a bumpy, non-convex relief with self-shadowing.
    Torus {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Ring radius.
        major: f64,
        /// Tube radius.
        minor: f64,
        /// Relative modulation amplitude (0: a plain torus), < 1.
        bumps: f64,
        /// Number of lobes around the ring.
        lobes: u32,
        /// Base height.
        base: f64,
    },
    /// Gaussian bump z = base + height·exp(−d²/2σ²), out to 4σ.
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
    /// A plane z = z0 cut by a V-groove running along y: z = z0 − depth·max(0, 1 − |x − cx|/w)
    /// with w = `half_width`, over the whole image. Its two planar faces meet at the crease
    /// x = cx at an opening angle of 2·atan(w/depth) (90° when depth = w) and see each other:
    /// the classic interreflection scene (Nayar, Ikeuchi & Kanade, "Shape from
    /// interreflections", IJCV 1991).
    Groove {
        /// Position of the crease.
        cx: f64,
        /// Half the groove's width at the rim (pixels).
        half_width: f64,
        /// Depth of the crease below `z0`.
        depth: f64,
        /// Height of the plane.
        z0: f64,
    },
    /// A plane z = z0 with a hollow spherical cap (a bowl): inside the rim, the lower part of
    /// the sphere of radius `radius` whose bottom is `depth` below z0,
    /// z = z0 + (R − depth) − √(R² − d²), d the distance to (cx, cy), out to the rim radius
    /// √(2R·depth − depth²); normals point inwards, towards the sphere's centre. `depth` ≤ R
    /// (at most a hemisphere: a deeper cap would overhang its rim). Every point of a spherical
    /// cavity sees every other with the same form factor, dA/4πR², which makes its
    /// interreflections a closed form.
    Bowl {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Radius of the sphere (pixels).
        radius: f64,
        /// Depth of the bottom below `z0`, in (0, `radius`].
        depth: f64,
        /// Height of the plane (and of the rim).
        z0: f64,
    },
    /// A relief over the whole image: the plane z = base plus Gaussian dimples, bumps and a
    /// straight groove of Gaussian cross-section, z = base + scale·height·r(u, v) with
    /// (u, v) = ((x − cx)/scale, (y − cy)/scale) and
    /// r = Σ_k a_k exp(−|(u, v) − c_k|²/2s_k²) + a_g exp(−w²/2s_g²), w the signed distance to the
    /// groove's line; the features' centres, widths and amplitudes are
    /// [`RELIEF_FEATURES`] and [`RELIEF_GROOVE`] (steepest slopes ≈ 1–1.2 at height 1). Concave
    /// and convex detail side by side, with interreflections in the dimples and the groove.
    Relief {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Pixels per unit of (u, v) (the image size for the named scene).
        scale: f64,
        /// Amplitude factor (1: the nominal relief; negative turns it inside out).
        height: f64,
        /// Height of the plane.
        base: f64,
    },
    /// A bust-like head, the classic shape-from-shading test surface in a form with a closed
    /// expression: the upper half of an ellipsoid (semi-axes [`BUST_HEAD`] times `scale`)
    /// carrying a face of Gaussian features ([`BUST_FEATURES`]: nose, eye sockets, brows,
    /// cheeks, lips, mouth and chin), z = base + scale·b(u, v), (u, v) = ((x − cx)/scale,
    /// (y − cy)/scale), over the head's ellipse. Convex and concave detail on a surface whose
    /// outline is an occluding contour.
    Bust {
        /// Centre x.
        cx: f64,
        /// Centre y.
        cy: f64,
        /// Pixels per unit of (u, v) (the image size for the named scene).
        scale: f64,
        /// Height of the head's base plane.
        base: f64,
    },
}

/// The head of [`Primitive::Bust`]: semi-axes (a, b, c) of its ellipsoid along u, v and the
/// height, in units of `scale`.
pub const BUST_HEAD: (f64, f64, f64) = (0.34, 0.44, 0.3);

/// The face of [`Primitive::Bust`]: (u, v, s_u, s_v, a) — centre, widths along u and v and
/// amplitude of each Gaussian feature, in units of `scale` (v up; negative a: a hollow).
pub const BUST_FEATURES: [(f64, f64, f64, f64, f64); 13] = [
    (0.0, 0.0, 0.035, 0.1, 0.06),       // bridge of the nose
    (0.0, -0.08, 0.04, 0.035, 0.04),    // tip of the nose
    (-0.12, 0.08, 0.05, 0.035, -0.045), // eye sockets
    (0.12, 0.08, 0.05, 0.035, -0.045),
    (-0.12, 0.15, 0.07, 0.03, 0.025), // brows
    (0.12, 0.15, 0.07, 0.03, 0.025),
    (-0.17, -0.06, 0.07, 0.07, 0.025), // cheeks
    (0.17, -0.06, 0.07, 0.07, 0.025),
    (0.0, -0.16, 0.06, 0.02, 0.015),   // upper lip
    (0.0, -0.19, 0.07, 0.012, -0.015), // mouth
    (0.0, -0.22, 0.05, 0.02, 0.012),   // lower lip
    (0.0, -0.3, 0.07, 0.05, 0.03),     // chin
    (0.0, 0.3, 0.2, 0.08, -0.01),      // temples' hollow across the forehead
];

/// The bust function b(u, v) of [`Primitive::Bust`] and its gradient, or `None` outside the
/// head's ellipse.
fn bust(u: f64, v: f64) -> Option<(f64, f64, f64)> {
    let (a, b, c) = BUST_HEAD;
    let s2 = 1.0 - (u / a).powi(2) - (v / b).powi(2);
    if s2 < 0.0 {
        return None;
    }
    let root = s2.sqrt().max(1e-12);
    let (mut r, mut ru, mut rv) = (c * root, -c * u / (a * a * root), -c * v / (b * b * root));
    for (fu, fv, su, sv, amp) in BUST_FEATURES {
        let (du, dv) = (u - fu, v - fv);
        let e = amp * (-(du * du) / (2.0 * su * su) - (dv * dv) / (2.0 * sv * sv)).exp();
        r += e;
        ru -= e * du / (su * su);
        rv -= e * dv / (sv * sv);
    }
    Some((r, ru, rv))
}

/// The round features of [`Primitive::Relief`]: (u, v, s, a) — centre, width and amplitude in
/// units of `scale` (negative a: a dimple, positive: a bump).
pub const RELIEF_FEATURES: [(f64, f64, f64, f64); 4] = [
    (-0.22, 0.18, 0.09, -0.18),
    (0.24, -0.24, 0.06, -0.10),
    (0.22, 0.2, 0.08, 0.14),
    (-0.25, -0.22, 0.05, 0.08),
];

/// The straight groove of [`Primitive::Relief`]: (u, v, angle in degrees from the u axis, s,
/// a) — a point of its line, its direction, its width and (negative) amplitude.
pub const RELIEF_GROOVE: (f64, f64, f64, f64, f64) = (0.0, 0.0, 30.0, 0.035, -0.07);

/// The relief function r(u, v) of [`Primitive::Relief`] and its gradient.
fn relief(u: f64, v: f64) -> (f64, f64, f64) {
    let (mut r, mut ru, mut rv) = (0.0, 0.0, 0.0);
    for (cu, cv, s, a) in RELIEF_FEATURES {
        let (du, dv) = (u - cu, v - cv);
        let e = a * (-(du * du + dv * dv) / (2.0 * s * s)).exp();
        r += e;
        ru -= e * du / (s * s);
        rv -= e * dv / (s * s);
    }
    let (gu, gv, angle, s, a) = RELIEF_GROOVE;
    let (sin_t, cos_t) = angle.to_radians().sin_cos();
    let w = -(u - gu) * sin_t + (v - gv) * cos_t;
    let e = a * (-w * w / (2.0 * s * s)).exp();
    r += e;
    ru += e * w / (s * s) * sin_t;
    rv -= e * w / (s * s) * cos_t;
    (r, ru, rv)
}

/// Unit normal of a surface with gradient (zx, zy).
fn normal_of_gradient(zx: f64, zy: f64) -> Vector3<f64> {
    Vector3::new(-zx, -zy, 1.0).normalize()
}

/// MATLAB's peaks function and its gradient.
fn peaks(u: f64, v: f64) -> (f64, f64, f64) {
    let e1 = (-u * u - (v + 1.0).powi(2)).exp();
    let e2 = (-u * u - v * v).exp();
    let e3 = (-(u + 1.0).powi(2) - v * v).exp();
    let p = u / 5.0 - u.powi(3) - v.powi(5);
    let z = 3.0 * (1.0 - u).powi(2) * e1 - 10.0 * p * e2 - e3 / 3.0;
    let zu = -6.0 * (1.0 - u) * e1
        - 6.0 * u * (1.0 - u).powi(2) * e1
        - 10.0 * ((0.2 - 3.0 * u * u) - 2.0 * u * p) * e2
        + 2.0 / 3.0 * (u + 1.0) * e3;
    let zv = -6.0 * (1.0 - u).powi(2) * (v + 1.0) * e1
        - 10.0 * (-5.0 * v.powi(4) - 2.0 * v * p) * e2
        + 2.0 / 3.0 * v * e3;
    (z, zu, zv)
}

impl Primitive {
    /// An upper bound of the height over the rectangle [x0, x1] × [y0, y1], or `None` when the
    /// primitive's footprint misses it (used to skip empty space when marching shadow rays).
    pub fn max_height_over(&self, x0: f64, x1: f64, y0: f64, y1: f64) -> Option<f64> {
        // Distance from (cx, cy) to the rectangle along each axis (0 inside), scaled.
        let gap = |c: f64, lo: f64, hi: f64| (lo - c).max(c - hi).max(0.0);
        let near2 = |cx: f64, cy: f64, sx: f64, sy: f64| {
            (gap(cx, x0, x1) / sx).powi(2) + (gap(cy, y0, y1) / sy).powi(2)
        };
        let far2 = |cx: f64, cy: f64| {
            let fx = (x0 - cx).abs().max((x1 - cx).abs());
            let fy = (y0 - cy).abs().max((y1 - cy).abs());
            fx * fx + fy * fy
        };
        match *self {
            Primitive::Plane {
                z0,
                slope_x,
                slope_y,
            } => Some(z0 + (slope_x * x0).max(slope_x * x1) + (slope_y * y0).max(slope_y * y1)),
            Primitive::Step {
                z0,
                x0: edge,
                height,
            } => Some(
                z0 + if x1 >= edge {
                    height.max(0.0)
                } else {
                    height.min(0.0)
                },
            ),
            Primitive::Sphere {
                cx,
                cy,
                radius,
                base,
            } => {
                let d2 = near2(cx, cy, 1.0, 1.0);
                (d2 <= radius * radius).then(|| base + (radius * radius - d2).sqrt())
            }
            Primitive::Ellipsoid {
                cx,
                cy,
                a,
                b,
                c,
                base,
            } => {
                let d2 = near2(cx, cy, a, b);
                (d2 <= 1.0).then(|| base + c * (1.0 - d2).sqrt())
            }
            // The profile r(u) ≤ width·(0.62 + 0.22) and the front half rises at most r.
            Primitive::Vase {
                cx,
                cy,
                half_height,
                width,
                base,
            } => {
                let r = 0.84 * width;
                (gap(cx, x0, x1) <= r && gap(cy, y0, y1) <= half_height).then_some(base + r)
            }
            // max peaks ≈ 8.106.
            Primitive::Peaks {
                cx,
                cy,
                scale,
                height,
                base,
            } => (gap(cx, x0, x1) <= 3.0 * scale && gap(cy, y0, y1) <= 3.0 * scale)
                .then_some(base + 8.2 * height.abs()),
            Primitive::Torus {
                cx,
                cy,
                major,
                minor,
                bumps,
                base,
                ..
            } => {
                let (inner, outer) = ((major - minor).max(0.0), major + minor);
                let reaches =
                    near2(cx, cy, 1.0, 1.0) <= outer * outer && far2(cx, cy) >= inner * inner;
                reaches.then_some(base + minor * (1.0 + bumps.abs()))
            }
            Primitive::Gaussian {
                cx,
                cy,
                sigma,
                height,
                base,
            } => {
                let d2 = near2(cx, cy, 1.0, 1.0);
                (d2 <= 16.0 * sigma * sigma)
                    .then(|| base + height.max(0.0) * (-d2 / (2.0 * sigma * sigma)).exp())
            }
            Primitive::Pyramid {
                cx,
                cy,
                half,
                height,
                base,
            } => {
                let m = gap(cx, x0, x1).max(gap(cy, y0, y1));
                (m <= half).then(|| base + height.max(0.0) * (1.0 - m / half))
            }
            // The highest point is the one farthest from the crease.
            Primitive::Groove {
                cx,
                half_width,
                depth,
                z0,
            } => {
                let far = (x0 - cx).abs().max((x1 - cx).abs());
                Some(z0 - depth * (1.0 - far / half_width).max(0.0))
            }
            // The highest point is the one farthest from the axis.
            Primitive::Bowl {
                cx,
                cy,
                radius,
                depth,
                z0,
            } => {
                let rim2 = 2.0 * radius * depth - depth * depth;
                let f2 = far2(cx, cy);
                Some(if f2 >= rim2 {
                    z0
                } else {
                    z0 + (radius - depth) - (radius * radius - f2).sqrt()
                })
            }
            // Dimples and the groove only lower the plane; each bump is bounded by its value at
            // the rectangle's nearest point.
            Primitive::Relief {
                cx,
                cy,
                scale,
                height,
                base,
            } => {
                let (u0, u1) = ((x0 - cx) / scale, (x1 - cx) / scale);
                let (v0, v1) = ((y0 - cy) / scale, (y1 - cy) / scale);
                let (u0, u1, v0, v1) = (u0.min(u1), u0.max(u1), v0.min(v1), v0.max(v1));
                let mut top = 0.0;
                for (cu, cv, s, a) in RELIEF_FEATURES {
                    let d2 = gap(cu, u0, u1).powi(2) + gap(cv, v0, v1).powi(2);
                    top += (height * a).max(0.0) * (-d2 / (2.0 * s * s)).exp();
                }
                top += (height * RELIEF_GROOVE.4).max(0.0);
                Some(base + scale.abs() * top)
            }
            // The dome's top plus every raised feature at full height.
            Primitive::Bust {
                cx,
                cy,
                scale,
                base,
            } => {
                let (a, b, c) = BUST_HEAD;
                let d2 = near2(cx, cy, a * scale, b * scale);
                let raised: f64 = BUST_FEATURES.iter().map(|f| f.4.max(0.0)).sum();
                (d2 <= 1.0).then_some(base + scale.abs() * (c + raised))
            }
        }
    }

    /// Height and unit normal at (x, y), or `None` outside the primitive's footprint.
    pub fn eval(&self, x: f64, y: f64) -> Option<(f64, Vector3<f64>)> {
        match *self {
            Primitive::Plane {
                z0,
                slope_x,
                slope_y,
            } => Some((
                z0 + slope_x * x + slope_y * y,
                normal_of_gradient(slope_x, slope_y),
            )),
            Primitive::Step { z0, x0, height } => {
                Some((if x >= x0 { z0 + height } else { z0 }, Vector3::z()))
            }
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
            Primitive::Ellipsoid {
                cx,
                cy,
                a,
                b,
                c,
                base,
            } => {
                let (u, v) = ((x - cx) / a, (y - cy) / b);
                let s2 = 1.0 - u * u - v * v;
                (s2 >= 0.0).then(|| {
                    let s = s2.sqrt();
                    // ∇F of F = u² + v² + w² − 1 with w = (z − base)/c.
                    let n = Vector3::new(u / a, v / b, s / c).normalize();
                    (base + c * s, n)
                })
            }
            Primitive::Vase {
                cx,
                cy,
                half_height,
                width,
                base,
            } => {
                let u = (y - cy) / half_height;
                if u.abs() > 1.0 {
                    return None;
                }
                let w = 1.3 * PI;
                let r = width * (0.62 + 0.22 * (w * u + 0.5).sin() - 0.12 * u * u);
                let dr_dy = width * (0.22 * w * (w * u + 0.5).cos() - 0.24 * u) / half_height;
                let dx = x - cx;
                let s2 = r * r - dx * dx;
                (s2 >= 0.0).then(|| {
                    let s = s2.sqrt();
                    // ∇F of F = (x − cx)² + (z − base)² − r(y)².
                    (base + s, Vector3::new(dx, -r * dr_dy, s).normalize())
                })
            }
            Primitive::Peaks {
                cx,
                cy,
                scale,
                height,
                base,
            } => {
                let (u, v) = ((x - cx) / scale, (y - cy) / scale);
                (u.abs() <= 3.0 && v.abs() <= 3.0).then(|| {
                    let (z, zu, zv) = peaks(u, v);
                    (
                        base + height * z,
                        normal_of_gradient(height * zu / scale, height * zv / scale),
                    )
                })
            }
            Primitive::Torus {
                cx,
                cy,
                major,
                minor,
                bumps,
                lobes,
                base,
            } => {
                let (dx, dy) = (x - cx, y - cy);
                let rho = (dx * dx + dy * dy).sqrt();
                let s2 = minor * minor - (rho - major).powi(2);
                if s2 < 0.0 || rho < 1e-9 {
                    return None;
                }
                let s = s2.sqrt();
                let theta = dy.atan2(dx);
                let k = f64::from(lobes);
                let m = 1.0 + bumps * (k * theta).cos();
                let (ct, st) = (dx / rho, dy / rho);
                // (−z_x, −z_y, 1)·s, finite at the tube's rim, with z = m(θ)·s(ρ):
                // −z_x·s = m(ρ−R)cos θ + m′s² sin θ/ρ, −z_y·s = m(ρ−R)sin θ − m′s² cos θ/ρ.
                let dm = -bumps * k * (k * theta).sin();
                let nx = m * (rho - major) * ct + dm * s * s * st / rho;
                let ny = m * (rho - major) * st - dm * s * s * ct / rho;
                Some((base + m * s, Vector3::new(nx, ny, s).normalize()))
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
                (dx * dx + dy * dy <= 16.0 * sigma * sigma).then(|| {
                    let (zx, zy) = (-e * dx / (sigma * sigma), -e * dy / (sigma * sigma));
                    (base + e, normal_of_gradient(zx, zy))
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
                    (base + height * (1.0 - m / half), normal_of_gradient(zx, zy))
                })
            }
            Primitive::Groove {
                cx,
                half_width,
                depth,
                z0,
            } => {
                let d = x - cx;
                Some(if d.abs() < half_width {
                    (
                        z0 - depth * (1.0 - d.abs() / half_width),
                        normal_of_gradient(depth / half_width * d.signum(), 0.0),
                    )
                } else {
                    (z0, Vector3::z())
                })
            }
            Primitive::Bowl {
                cx,
                cy,
                radius,
                depth,
                z0,
            } => {
                let (dx, dy) = (x - cx, y - cy);
                let d2 = dx * dx + dy * dy;
                Some(if d2 < 2.0 * radius * depth - depth * depth {
                    let h = (radius * radius - d2).sqrt();
                    (
                        z0 + (radius - depth) - h,
                        Vector3::new(-dx, -dy, h) / radius,
                    )
                } else {
                    (z0, Vector3::z())
                })
            }
            Primitive::Relief {
                cx,
                cy,
                scale,
                height,
                base,
            } => {
                let (r, ru, rv) = relief((x - cx) / scale, (y - cy) / scale);
                Some((
                    base + scale * height * r,
                    normal_of_gradient(height * ru, height * rv),
                ))
            }
            Primitive::Bust {
                cx,
                cy,
                scale,
                base,
            } => bust((x - cx) / scale, (y - cy) / scale)
                .map(|(r, ru, rv)| (base + scale * r, normal_of_gradient(ru, rv))),
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
                let w = 2.0 * PI / period;
                mean + amplitude * ((w * x).sin() * (w * y).sin()) as f32
            }
        }
    }
}

/// One surface of a scene: its shape, albedo map and material.
#[derive(Debug, Clone, PartialEq)]
pub struct Object {
    /// Geometry.
    pub shape: Primitive,
    /// Albedo map (scales the material's diffuse lobe).
    pub albedo: Albedo,
    /// Reflectance.
    pub material: Material,
}

impl Object {
    /// A Lambertian object.
    pub fn new(shape: Primitive, albedo: Albedo) -> Self {
        Object {
            shape,
            albedo,
            material: Material::lambertian(),
        }
    }

    /// The same object with another material.
    pub fn with_material(mut self, material: Material) -> Self {
        self.material = material;
        self
    }

    /// A flat ground z = 0 covering the image.
    pub fn ground(albedo: Albedo) -> Self {
        Object::new(
            Primitive::Plane {
                z0: 0.0,
                slope_x: 0.0,
                slope_y: 0.0,
            },
            albedo,
        )
    }
}

/// A scene: objects seen from above by an orthographic camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Surfaces; the highest one at a pixel is the one seen.
    pub objects: Vec<Object>,
}

/// What a scene looks like from the camera: depth, normals, albedo, mask and which object is
/// seen at each pixel.
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
    /// Index into [`Scene::objects`] of the surface seen (`u32::MAX` outside the mask).
    pub object: Grid<u32>,
}

/// The named test scenes, each built by [`SceneKind::build`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneKind {
    /// A sphere of radius 0.4·size, no background.
    Sphere,
    /// An ellipsoid (semi-axes 0.42, 0.3, 0.3 of the size), no background.
    Ellipsoid,
    /// A vase (surface of revolution), no background.
    Vase,
    /// MATLAB's peaks over the whole image.
    Peaks,
    /// A plane with a step of 0.1·size at the centre (a depth discontinuity).
    Step,
    /// A plane tilted at slope 0.5 along x.
    Ramp,
    /// A bumpy torus on a ground plane (non-convex: self- and cast shadows).
    Torus,
    /// A pyramid and a Gaussian bump on a ground plane.
    Bumps,
    /// A 90° V-groove along y, 0.6·size wide and 0.3·size deep, in a plane (concave: its
    /// faces light each other).
    Groove,
    /// A bowl, a hollow spherical cap of radius 0.4·size and depth 0.28·size, in a plane
    /// (concave).
    Bowl,
    /// Dimples, bumps and a groove on a plane ([`Primitive::Relief`]): concave and convex
    /// detail.
    Relief,
    /// The built-in default scene ([`Scene::default_scene`], 320×240 whatever the size).
    Demo,
    /// A bust-like head ([`Primitive::Bust`]), no background: a face on an ellipsoid.
    Bust,
}

impl SceneKind {
    /// Every kind, for listings.
    pub const ALL: [SceneKind; 13] = [
        SceneKind::Sphere,
        SceneKind::Ellipsoid,
        SceneKind::Vase,
        SceneKind::Peaks,
        SceneKind::Step,
        SceneKind::Ramp,
        SceneKind::Torus,
        SceneKind::Bumps,
        SceneKind::Groove,
        SceneKind::Bowl,
        SceneKind::Relief,
        SceneKind::Demo,
        SceneKind::Bust,
    ];

    /// The name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            SceneKind::Sphere => "sphere",
            SceneKind::Ellipsoid => "ellipsoid",
            SceneKind::Vase => "vase",
            SceneKind::Peaks => "peaks",
            SceneKind::Step => "step",
            SceneKind::Ramp => "ramp",
            SceneKind::Torus => "torus",
            SceneKind::Bumps => "bumps",
            SceneKind::Groove => "groove",
            SceneKind::Bowl => "bowl",
            SceneKind::Relief => "relief",
            SceneKind::Demo => "demo",
            SceneKind::Bust => "bust",
        }
    }

    /// The scene at `size`×`size` pixels (the demo keeps its own size), every object with
    /// `albedo` and `material`.
    pub fn build(self, size: usize, albedo: Albedo, material: Material) -> Scene {
        let s = size as f64;
        let obj = |shape| Object::new(shape, albedo).with_material(material);
        let ground = || {
            obj(Primitive::Plane {
                z0: 0.0,
                slope_x: 0.0,
                slope_y: 0.0,
            })
        };
        let objects = match self {
            SceneKind::Sphere => vec![obj(Primitive::Sphere {
                cx: 0.0,
                cy: 0.0,
                radius: 0.4 * s,
                base: 0.0,
            })],
            SceneKind::Ellipsoid => vec![obj(Primitive::Ellipsoid {
                cx: 0.0,
                cy: 0.0,
                a: 0.42 * s,
                b: 0.3 * s,
                c: 0.3 * s,
                base: 0.0,
            })],
            SceneKind::Vase => vec![obj(Primitive::Vase {
                cx: 0.0,
                cy: 0.0,
                half_height: 0.45 * s,
                width: 0.45 * s,
                base: 0.0,
            })],
            SceneKind::Peaks => vec![obj(Primitive::Peaks {
                cx: 0.0,
                cy: 0.0,
                scale: s / 6.0,
                height: s / 30.0,
                base: 0.0,
            })],
            SceneKind::Step => vec![obj(Primitive::Step {
                z0: 0.0,
                x0: 0.0,
                height: 0.1 * s,
            })],
            SceneKind::Ramp => vec![obj(Primitive::Plane {
                z0: 0.0,
                slope_x: 0.5,
                slope_y: 0.0,
            })],
            SceneKind::Torus => vec![
                ground(),
                obj(Primitive::Torus {
                    cx: 0.0,
                    cy: 0.0,
                    major: 0.28 * s,
                    minor: 0.12 * s,
                    bumps: 0.3,
                    lobes: 7,
                    base: 0.0,
                }),
            ],
            SceneKind::Bumps => vec![
                ground(),
                obj(Primitive::Pyramid {
                    cx: -0.2 * s,
                    cy: 0.0,
                    half: 0.17 * s,
                    height: 0.12 * s,
                    base: 0.0,
                }),
                obj(Primitive::Gaussian {
                    cx: 0.23 * s,
                    cy: 0.05 * s,
                    sigma: 0.07 * s,
                    height: 0.14 * s,
                    base: 0.0,
                }),
            ],
            SceneKind::Groove => vec![obj(Primitive::Groove {
                cx: 0.0,
                half_width: 0.3 * s,
                depth: 0.3 * s,
                z0: 0.0,
            })],
            SceneKind::Bowl => vec![obj(Primitive::Bowl {
                cx: 0.0,
                cy: 0.0,
                radius: 0.4 * s,
                depth: 0.28 * s,
                z0: 0.0,
            })],
            SceneKind::Relief => vec![obj(Primitive::Relief {
                cx: 0.0,
                cy: 0.0,
                scale: s,
                height: 1.0,
                base: 0.0,
            })],
            SceneKind::Bust => vec![obj(Primitive::Bust {
                cx: 0.0,
                cy: 0.0,
                scale: s,
                base: 0.0,
            })],
            SceneKind::Demo => {
                let mut d = Scene::default_scene();
                for o in &mut d.objects {
                    o.material = material;
                }
                return d;
            }
        };
        Scene {
            width: size,
            height: size,
            objects,
        }
    }
}

impl Scene {
    /// A single sphere of radius `radius` (pixels) centred in a `size`×`size` image, with no
    /// background: the classic photometric-stereo test object.
    pub fn sphere(size: usize, radius: f64, albedo: Albedo) -> Self {
        Scene {
            width: size,
            height: size,
            objects: vec![Object::new(
                Primitive::Sphere {
                    cx: 0.0,
                    cy: 0.0,
                    radius,
                    base: 0.0,
                },
                albedo,
            )],
        }
    }

    /// A sphere of radius 0.28·`size` rising from a ground plane beside a pyramid, all of
    /// `material` and albedo 0.7: attached shadows, cast shadows (the sphere's on the ground, the
    /// pyramid's on the sphere) and highlights in one view — the scene of the estimator
    /// comparison against specularity.
    pub fn sphere_on_ground(size: usize, material: Material) -> Self {
        let s = size as f64;
        let albedo = Albedo::Constant(0.7);
        let obj = |shape| Object::new(shape, albedo).with_material(material);
        Scene {
            width: size,
            height: size,
            objects: vec![
                obj(Primitive::Plane {
                    z0: 0.0,
                    slope_x: 0.0,
                    slope_y: 0.0,
                }),
                obj(Primitive::Sphere {
                    cx: -0.08 * s,
                    cy: -0.08 * s,
                    radius: 0.28 * s,
                    base: 0.0,
                }),
                obj(Primitive::Pyramid {
                    cx: 0.3 * s,
                    cy: 0.3 * s,
                    half: 0.12 * s,
                    height: 0.3 * s,
                    base: 0.0,
                }),
            ],
        }
    }

    /// The built-in default scene: a textured hemisphere, a Gaussian bump, a pyramid and a
    /// shallow dome on a checkered ground plane (320×240), all Lambertian. Objects cast shadows
    /// on the ground.
    pub fn default_scene() -> Self {
        Scene {
            width: 320,
            height: 240,
            objects: vec![
                Object::ground(Albedo::Checker {
                    size: 20.0,
                    a: 0.35,
                    b: 0.5,
                }),
                Object::new(
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
                Object::new(
                    Primitive::Gaussian {
                        cx: 80.0,
                        cy: 45.0,
                        sigma: 20.0,
                        height: 30.0,
                        base: 0.0,
                    },
                    Albedo::Constant(0.8),
                ),
                Object::new(
                    Primitive::Pyramid {
                        cx: 75.0,
                        cy: -60.0,
                        half: 35.0,
                        height: 28.0,
                        base: 0.0,
                    },
                    Albedo::Constant(0.7),
                ),
                Object::new(
                    Primitive::Sphere {
                        cx: -40.0,
                        cy: -80.0,
                        radius: 60.0,
                        base: -42.0,
                    },
                    Albedo::Constant(0.5),
                ),
            ],
        }
    }

    /// Pixel centre (x, y) of column `c`, row `r`.
    pub fn pixel_xy(&self, c: usize, r: usize) -> (f64, f64) {
        (
            c as f64 - (self.width as f64 - 1.0) / 2.0,
            (self.height as f64 - 1.0) / 2.0 - r as f64,
        )
    }

    /// The visible surface at any point (x, y): (height, normal, object index), or `None`.
    pub fn surface_at(&self, x: f64, y: f64) -> Option<(f64, Vector3<f64>, usize)> {
        let mut best: Option<(f64, Vector3<f64>, usize)> = None;
        for (i, o) in self.objects.iter().enumerate() {
            if let Some((z, n)) = o.shape.eval(x, y)
                && best.is_none_or(|(bz, _, _)| z > bz)
            {
                best = Some((z, n, i));
            }
        }
        best
    }

    /// Height of the visible surface at any point (x, y) of the image plane (not only pixel
    /// centres), or `None` where nothing is.
    pub fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        self.objects
            .iter()
            .filter_map(|o| o.shape.eval(x, y).map(|(z, _)| z))
            .reduce(f64::max)
    }

    /// Evaluates the scene at every pixel centre.
    pub fn height_field(&self) -> HeightField {
        let (w, h) = (self.width, self.height);
        let mut depth = Grid::new(w, h, f32::NAN);
        let mut normals = Grid::new(w, h, Vector3::repeat(f32::NAN));
        let mut albedo = Grid::new(w, h, f32::NAN);
        let mut mask = Grid::new(w, h, false);
        let mut object = Grid::new(w, h, u32::MAX);
        for r in 0..h {
            for c in 0..w {
                let (x, y) = self.pixel_xy(c, r);
                if let Some((z, n, i)) = self.surface_at(x, y) {
                    *depth.at_mut(c, r) = z as f32;
                    *normals.at_mut(c, r) = n.cast::<f32>();
                    *albedo.at_mut(c, r) = self.objects[i].albedo.at(x, y);
                    *mask.at_mut(c, r) = true;
                    *object.at_mut(c, r) = i as u32;
                }
            }
        }
        HeightField {
            depth,
            normals,
            albedo,
            mask,
            object,
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

    /// For every primitive, the normal agrees with the finite-difference gradient of the height:
    /// n ∝ (−∂z/∂x, −∂z/∂y, 1), at points away from creases and rims.
    #[test]
    fn normals_match_finite_differences() {
        let prims = [
            Primitive::Plane {
                z0: 1.0,
                slope_x: 0.3,
                slope_y: -0.2,
            },
            Primitive::Step {
                z0: 0.0,
                x0: 5.0,
                height: 3.0,
            },
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
            Primitive::Ellipsoid {
                cx: 0.5,
                cy: 0.0,
                a: 12.0,
                b: 8.0,
                c: 5.0,
                base: 1.0,
            },
            Primitive::Vase {
                cx: 0.0,
                cy: 0.0,
                half_height: 20.0,
                width: 15.0,
                base: 0.0,
            },
            Primitive::Peaks {
                cx: 0.0,
                cy: 0.0,
                scale: 4.0,
                height: 0.7,
                base: 0.0,
            },
            Primitive::Torus {
                cx: 0.0,
                cy: 0.0,
                major: 3.0,
                minor: 3.0,
                bumps: 0.3,
                lobes: 5,
                base: 0.0,
            },
            Primitive::Pyramid {
                cx: 0.0,
                cy: 0.0,
                half: 10.0,
                height: 5.0,
                base: 0.0,
            },
            Primitive::Groove {
                cx: 0.3,
                half_width: 6.0,
                depth: 4.0,
                z0: 1.0,
            },
            Primitive::Bowl {
                cx: 0.5,
                cy: -0.5,
                radius: 8.0,
                depth: 5.0,
                z0: 0.0,
            },
            Primitive::Relief {
                cx: 0.0,
                cy: 0.0,
                scale: 20.0,
                height: 1.0,
                base: 0.0,
            },
            Primitive::Bust {
                cx: 0.0,
                cy: 0.0,
                scale: 20.0,
                base: 0.0,
            },
        ];
        for prim in prims {
            for (x, y) in [(2.3, -1.1), (-1.7, 3.2), (0.4, 0.9)] {
                let d = 1e-6;
                let (_, n) = prim
                    .eval(x, y)
                    .unwrap_or_else(|| panic!("{prim:?} at {x},{y}"));
                let zx =
                    (prim.eval(x + d, y).unwrap().0 - prim.eval(x - d, y).unwrap().0) / (2.0 * d);
                let zy =
                    (prim.eval(x, y + d).unwrap().0 - prim.eval(x, y - d).unwrap().0) / (2.0 * d);
                assert!((n.norm() - 1.0).abs() < 1e-9, "{prim:?}");
                assert!(
                    (zx + n.x / n.z).abs() < 1e-4,
                    "{prim:?} at {x},{y}: {zx} vs {}",
                    -n.x / n.z
                );
                assert!(
                    (zy + n.y / n.z).abs() < 1e-4,
                    "{prim:?} at {x},{y}: {zy} vs {}",
                    -n.y / n.z
                );
            }
        }
    }

    /// The concave primitives have the stated geometry: the groove's crease at its depth and
    /// its faces at slope depth/half-width; the bowl's normals point at its sphere's centre and
    /// its rim is flush with the plane; the relief's dimples dip and its bumps rise.
    #[test]
    fn concave_primitives_have_their_geometry() {
        let groove = Primitive::Groove {
            cx: 2.0,
            half_width: 10.0,
            depth: 5.0,
            z0: 1.0,
        };
        assert_eq!(groove.eval(2.0, 7.0).unwrap().0, -4.0);
        let (z, n) = groove.eval(7.0, 0.0).unwrap();
        assert!((z + 1.5).abs() < 1e-12);
        assert!((n - Vector3::new(-0.5, 0.0, 1.0).normalize()).norm() < 1e-12);
        assert_eq!(groove.eval(12.5, 3.0).unwrap(), (1.0, Vector3::z()));
        let bowl = Primitive::Bowl {
            cx: 1.0,
            cy: -1.0,
            radius: 10.0,
            depth: 4.0,
            z0: 0.0,
        };
        // Bottom 4 below the plane; rim radius √(2·10·4 − 4²) = 8; centre at height 10 − 4.
        assert!((bowl.eval(1.0, -1.0).unwrap().0 + 4.0).abs() < 1e-12);
        for (x, y) in [(4.0, -3.0), (-4.0, 4.5), (8.9, -1.0)] {
            let (z, n) = bowl.eval(x, y).unwrap();
            let centre = Vector3::new(x, y, z) + 10.0 * n;
            assert!((centre - Vector3::new(1.0, -1.0, 6.0)).norm() < 1e-9);
        }
        assert_eq!(bowl.eval(9.1, -1.0).unwrap(), (0.0, Vector3::z()));
        assert!(bowl.eval(8.99, -1.0).unwrap().0.abs() < 0.05);
        let relief = Primitive::Relief {
            cx: 0.0,
            cy: 0.0,
            scale: 100.0,
            height: 1.0,
            base: 0.0,
        };
        // At each feature's centre the height is its amplitude, give or take the groove's and
        // the other features' tails (under 25%).
        for (u, v, _, a) in RELIEF_FEATURES {
            let z = relief.eval(100.0 * u, 100.0 * v).unwrap().0;
            assert!((z / (100.0 * a) - 1.0).abs() < 0.25, "{z} at ({u}, {v})");
        }
        assert!(relief.eval(0.0, 0.0).unwrap().0 < -6.0);
    }

    /// The rectangle bounds used to skip empty space never fall below the surface.
    #[test]
    fn height_bounds_are_upper_bounds() {
        for kind in SceneKind::ALL {
            let scene = kind.build(80, Albedo::Constant(0.5), Material::lambertian());
            for o in &scene.objects {
                for (x0, y0) in [(-40.0, -40.0), (-12.0, 3.0), (5.5, -20.25), (20.0, 20.0)] {
                    let (x1, y1) = (x0 + 8.0, y0 + 8.0);
                    let bound = o.shape.max_height_over(x0, x1, y0, y1);
                    for i in 0..=16 {
                        for j in 0..=16 {
                            let (x, y) = (x0 + i as f64 * 0.5, y0 + j as f64 * 0.5);
                            if let Some((z, _)) = o.shape.eval(x, y) {
                                let b = bound.unwrap_or_else(|| {
                                    panic!("{:?}: no bound but surface at {x},{y}", o.shape)
                                });
                                assert!(
                                    z <= b + 1e-9,
                                    "{:?}: z = {z} above bound {b} at {x},{y}",
                                    o.shape
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn every_named_scene_builds_with_a_mask() {
        for kind in SceneKind::ALL {
            let scene = kind.build(64, Albedo::Constant(0.5), Material::lambertian());
            let hf = scene.height_field();
            let covered = hf.mask.count();
            assert!(covered > 500, "{}: {covered} pixels", kind.name());
            assert!(
                hf.depth
                    .data()
                    .iter()
                    .zip(hf.mask.data())
                    .all(|(d, m)| d.is_finite() == *m)
            );
        }
    }
}
