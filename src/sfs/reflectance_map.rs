//! The reflectance map R(p, q): image brightness as a function of the surface gradient, for one
//! distant light, an orthographic camera looking down −z, and a BRDF (Horn, "Understanding image
//! intensities", Artificial Intelligence 1977; Horn & Brooks, *Shape from Shading*, 1989, ch. 1).
//!
//! A surface z(x, y) with gradient p = ∂z/∂x, q = ∂z/∂y (x right, y up) has the unit normal
//! n = (−p, −q, 1)/√(1 + p² + q²). With the light direction s = (−p_s, −q_s, 1)/√(1 + p_s² + q_s²)
//! (pointing from the surface towards the light) and the rendering convention of
//! [`crate::synth::render`], a Lambertian surface of unit albedo gives
//!
//! R(p, q) = max(0, n·s) = max(0, (1 + p p_s + q q_s) / (√(1 + p² + q²) √(1 + p_s² + q_s²))),
//!
//! and any [`Material`] gives R = π f(s, v) max(0, n·s) with the view v = (0, 0, 1) (both in the
//! surface's frame; the colour channels mixed to grey with [`GREY_WEIGHTS`]). An image of albedo
//! ρ is E(x, y) = ρ R(p(x, y), q(x, y)): shape from shading inverts that one equation per pixel.
//!
//! The Lambertian map and its derivatives are closed forms; other materials are evaluated
//! through their BRDF and differentiated by central differences. Iso-brightness contours in the
//! (p, q) plane are drawn by [`ReflectanceMap::contour_svg`] (marching squares).

use crate::capture::stack::GREY_WEIGHTS;
use crate::error::{Error, Result};
use crate::grid::{Grid, ScalarMap};
use crate::synth::reflectance::{Diffuse, Frame, Material};
use nalgebra::Vector3;
use std::f64::consts::PI;
use std::fmt::Write as _;

/// Step of the central differences of non-Lambertian maps, in gradient units.
const DERIVATIVE_STEP: f64 = 1e-5;

/// The unit normal (−p, −q, 1)/√(1 + p² + q²) of gradient (p, q).
pub fn normal_from_gradient(p: f64, q: f64) -> Vector3<f64> {
    Vector3::new(-p, -q, 1.0) / (1.0 + p * p + q * q).sqrt()
}

/// The gradient (p, q) = (−n_x/n_z, −n_y/n_z) of a normal, or `None` when n_z ≤ 0 (a surface
/// seen edge-on or from behind has no finite gradient).
pub fn gradient_from_normal(n: &Vector3<f64>) -> Option<(f64, f64)> {
    (n.z > 0.0 && n.iter().all(|v| v.is_finite())).then(|| (-n.x / n.z, -n.y / n.z))
}

/// Brightness of a surface as a function of its gradient, for one distant light.
#[derive(Debug, Clone, PartialEq)]
pub struct ReflectanceMap {
    light: Vector3<f64>,
    /// (p_s, q_s), the gradient of a surface facing the light, when the light is in front.
    light_gradient: Option<(f64, f64)>,
    material: Material,
    lambertian: bool,
}

/// Where the derivative evaluation of a [`ReflectanceMap`] lands: R and its partials.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shading {
    /// R(p, q).
    pub r: f64,
    /// ∂R/∂p.
    pub r_p: f64,
    /// ∂R/∂q.
    pub r_q: f64,
}

impl ReflectanceMap {
    /// The map of a white Lambertian surface (unit albedo) under a light in direction `light`
    /// (any length; normalised here).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`light`) when the direction is zero or not finite.
    ///
    /// # Example
    /// ```
    /// use photostereo::sfs::reflectance_map::ReflectanceMap;
    /// use photostereo::nalgebra::Vector3;
    /// let r = ReflectanceMap::lambertian(Vector3::new(0.5, 0.0, 1.0))?;
    /// // A surface facing the light, gradient (p_s, q_s) = (−0.5, 0), is brightest.
    /// assert!((r.eval(-0.5, 0.0) - 1.0).abs() < 1e-12);
    /// # Ok::<(), photostereo::Error>(())
    /// ```
    pub fn lambertian(light: Vector3<f64>) -> Result<Self> {
        Self::new(light, Material::lambertian())
    }

    /// The map of `material` (unit albedo; the mirror's delta lobe is excluded) under a light in
    /// direction `light`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when the light direction is zero or not finite, or the
    /// material is not physical ([`Material::validate`]).
    pub fn new(light: Vector3<f64>, material: Material) -> Result<Self> {
        material.validate()?;
        let norm = light.norm();
        if !(light.iter().all(|v| v.is_finite()) && norm > 0.0 && norm.is_finite()) {
            return Err(Error::param(
                "light",
                format!(
                    "direction ({}, {}, {}) must be finite and non-zero",
                    light.x, light.y, light.z
                ),
            ));
        }
        let light = light / norm;
        let lambertian = material.diffuse == Diffuse::Lambertian
            && material.specular.is_none()
            && material.diffuse_color == [1.0; 3];
        Ok(ReflectanceMap {
            light,
            light_gradient: gradient_from_normal(&light),
            material,
            lambertian,
        })
    }

    /// The unit light direction s.
    pub fn light(&self) -> Vector3<f64> {
        self.light
    }

    /// (p_s, q_s): the gradient of the surface that faces the light, or `None` for a light at or
    /// behind the horizon.
    pub fn light_gradient(&self) -> Option<(f64, f64)> {
        self.light_gradient
    }

    /// The material.
    pub fn material(&self) -> &Material {
        &self.material
    }

    /// Whether this is the closed-form white Lambertian map.
    pub fn is_lambertian(&self) -> bool {
        self.lambertian
    }

    /// Angle between the light and the viewing direction (0, 0, 1), in degrees.
    pub fn slant_deg(&self) -> f64 {
        self.light.z.clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// R(p, q) (see the module documentation); 0 where the surface turns away from the light.
    pub fn eval(&self, p: f64, q: f64) -> f64 {
        let n = normal_from_gradient(p, q);
        let cos_i = n.dot(&self.light);
        if cos_i <= 0.0 {
            return 0.0;
        }
        if self.lambertian {
            return cos_i;
        }
        let frame = Frame::from_normal(n);
        let wi = frame.to_local(&self.light);
        let wo = frame.to_local(&Vector3::z());
        let f = self.material.eval(1.0, &wi, &wo);
        let grey: f64 = (0..3).map(|c| f64::from(GREY_WEIGHTS[c]) * f[c]).sum();
        PI * grey * cos_i
    }

    /// R(p, q) with ∂R/∂p and ∂R/∂q. Closed form for the Lambertian map: with k = √(1+p²+q²),
    /// ∂R/∂p = (−s_x − p R/k)/k and ∂R/∂q = (−s_y − q R/k)/k; central differences otherwise.
    /// In the shadow (R = 0) the partials are 0.
    pub fn eval_with_derivatives(&self, p: f64, q: f64) -> Shading {
        if self.lambertian {
            let k = (1.0 + p * p + q * q).sqrt();
            let dot = (-p * self.light.x - q * self.light.y + self.light.z) / k;
            if dot <= 0.0 {
                return Shading {
                    r: 0.0,
                    r_p: 0.0,
                    r_q: 0.0,
                };
            }
            // n·s = (−p s_x − q s_y + s_z)/k with k = √(1+p²+q²): ∂/∂p = (−s_x − p·(n·s)/k)/k.
            return Shading {
                r: dot,
                r_p: (-self.light.x - p * dot / k) / k,
                r_q: (-self.light.y - q * dot / k) / k,
            };
        }
        let h = DERIVATIVE_STEP * (1.0 + p.abs().max(q.abs()));
        Shading {
            r: self.eval(p, q),
            r_p: (self.eval(p + h, q) - self.eval(p - h, q)) / (2.0 * h),
            r_q: (self.eval(p, q + h) - self.eval(p, q - h)) / (2.0 * h),
        }
    }

    /// R sampled on an n×n grid of the square [−extent, extent]² of gradient space: column c is
    /// p = −extent + 2·extent·c/(n−1), row r is q = extent − 2·extent·r/(n−1) (q up, like y).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when `n` < 2 or `extent` is not finite and > 0.
    pub fn sample(&self, extent: f64, n: usize) -> Result<ScalarMap> {
        check_grid(extent, n)?;
        let step = 2.0 * extent / (n - 1) as f64;
        Ok(Grid::from_fn(n, n, |c, r| {
            self.eval(-extent + step * c as f64, extent - step * r as f64) as f32
        }))
    }

    /// An SVG drawing of the iso-brightness contours R(p, q) = level for each of `levels` over
    /// [−extent, extent]² (marching squares on a `resolution`² grid, linear interpolation along
    /// the cell edges), with the axes, the shadow line R = 0⁺ in red and the light's gradient
    /// (p_s, q_s) marked — the classic drawing of Horn (1977).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for a bad grid (see [`ReflectanceMap::sample`]) or a level
    /// that is not finite.
    pub fn contour_svg(&self, extent: f64, levels: &[f64], resolution: usize) -> Result<String> {
        check_grid(extent, resolution)?;
        if let Some(l) = levels.iter().find(|l| !l.is_finite()) {
            return Err(Error::param("levels", format!("{l} is not finite")));
        }
        const SIZE: f64 = 480.0;
        // Room for the two-line title above, the tick labels left and below.
        const MARGIN: f64 = 64.0;
        let n = resolution;
        let step = 2.0 * extent / (n - 1) as f64;
        let values: Vec<f64> = (0..n * n)
            .map(|i| {
                self.eval(
                    -extent + step * (i % n) as f64,
                    extent - step * (i / n) as f64,
                )
            })
            .collect();
        // Gradient (p, q) → drawing coordinates (q up).
        let to_svg = |p: f64, q: f64| {
            (
                MARGIN + (p + extent) / (2.0 * extent) * SIZE,
                MARGIN + (extent - q) / (2.0 * extent) * SIZE,
            )
        };
        let total = SIZE + 2.0 * MARGIN;
        let mut svg = String::new();
        let _ = writeln!(
            svg,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{total}" height="{total}" viewBox="0 0 {total} {total}" font-family="sans-serif" font-size="12">"#
        );
        let _ = writeln!(
            svg,
            r#"<rect x="{MARGIN}" y="{MARGIN}" width="{SIZE}" height="{SIZE}" fill="white" stroke="black"/>"#
        );
        let (x0, y0) = to_svg(0.0, 0.0);
        let _ = writeln!(
            svg,
            r##"<path d="M {MARGIN} {y0:.2} H {:.2} M {x0:.2} {MARGIN} V {:.2}" stroke="#999" stroke-dasharray="4 3"/>"##,
            MARGIN + SIZE,
            MARGIN + SIZE
        );
        let mut draw = |level: f64, colour: &str, width: f64| {
            let mut d = String::new();
            for (a, b) in marching_squares(&values, n, level) {
                let pa = to_svg(-extent + step * a.0, extent - step * a.1);
                let pb = to_svg(-extent + step * b.0, extent - step * b.1);
                let _ = write!(d, "M{:.2} {:.2}L{:.2} {:.2}", pa.0, pa.1, pb.0, pb.1);
            }
            if !d.is_empty() {
                let _ = writeln!(
                    svg,
                    r#"<path d="{d}" fill="none" stroke="{colour}" stroke-width="{width}"><title>R = {level}</title></path>"#
                );
            }
        };
        draw(1e-9, "#c00", 1.5);
        for &l in levels {
            draw(l, "#1f4e9c", 1.0);
        }
        if let Some((ps, qs)) = self.light_gradient
            && ps.abs() <= extent
            && qs.abs() <= extent
        {
            let (x, y) = to_svg(ps, qs);
            let _ = writeln!(
                svg,
                r#"<circle cx="{x:.2}" cy="{y:.2}" r="4" fill="orange" stroke="black"><title>light (p_s, q_s) = ({ps:.3}, {qs:.3})</title></circle>"#
            );
        }
        let s = self.light;
        let levels_text = levels
            .iter()
            .map(|l| format!("{l}"))
            .collect::<Vec<_>>()
            .join(", ");
        let _ = writeln!(
            svg,
            r#"<text x="{MARGIN}" y="22" font-size="14">R(p, q) under the light ({:.3}, {:.3}, {:.3})</text>"#,
            s.x, s.y, s.z
        );
        let _ = writeln!(
            svg,
            r#"<text x="{MARGIN}" y="42">contours at {levels_text}; red: the shadow edge R = 0</text>"#
        );
        // Ticks and their values on both axes.
        for k in 0..=4 {
            let v = -extent + extent * k as f64 / 2.0;
            let (x, _) = to_svg(v, 0.0);
            let (_, y) = to_svg(0.0, v);
            let label = format!("{}", (v * 100.0).round() / 100.0);
            let _ = writeln!(
                svg,
                r##"<path d="M {x:.2} {:.2} v 5 M {MARGIN} {y:.2} h -5" stroke="black"/><text x="{x:.2}" y="{:.2}" text-anchor="middle">{label}</text><text x="{:.2}" y="{:.2}" text-anchor="end">{label}</text>"##,
                MARGIN + SIZE,
                MARGIN + SIZE + 18.0,
                MARGIN - 8.0,
                y + 4.0
            );
        }
        let _ = writeln!(
            svg,
            r#"<text x="{:.0}" y="{:.0}" text-anchor="middle">p = ∂z/∂x</text>"#,
            MARGIN + SIZE / 2.0,
            MARGIN + SIZE + 40.0
        );
        let _ = writeln!(
            svg,
            r#"<text x="18" y="{:.0}" transform="rotate(-90 18 {:.0})" text-anchor="middle">q = ∂z/∂y</text>"#,
            MARGIN + SIZE / 2.0,
            MARGIN + SIZE / 2.0
        );
        svg.push_str("</svg>\n");
        Ok(svg)
    }
}

fn check_grid(extent: f64, n: usize) -> Result<()> {
    if n < 2 {
        return Err(Error::param(
            "resolution",
            format!("{n} samples per side: need at least 2"),
        ));
    }
    if !(extent.is_finite() && extent > 0.0) {
        return Err(Error::param(
            "extent",
            format!("{extent} must be finite and > 0"),
        ));
    }
    Ok(())
}

/// Segments of the iso-line `values = level` on an n×n row-major grid, in (column, row)
/// coordinates (marching squares, linear interpolation on the cell edges; the saddle cases are
/// split by the cell's mean).
fn marching_squares(values: &[f64], n: usize, level: f64) -> Vec<((f64, f64), (f64, f64))> {
    let mut out = Vec::new();
    let cross = |a: f64, b: f64| {
        let t = (level - a) / (b - a);
        if t.is_finite() {
            t.clamp(0.0, 1.0)
        } else {
            0.5
        }
    };
    for r in 0..n - 1 {
        for c in 0..n - 1 {
            // Corners: 0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left.
            let v = [
                values[r * n + c],
                values[r * n + c + 1],
                values[(r + 1) * n + c + 1],
                values[(r + 1) * n + c],
            ];
            let above = v.map(|x| x > level);
            let case = above
                .iter()
                .enumerate()
                .fold(0usize, |acc, (i, &a)| acc | (usize::from(a) << i));
            if case == 0 || case == 15 {
                continue;
            }
            let (cf, rf) = (c as f64, r as f64);
            // Edge points: top (0–1), right (1–2), bottom (3–2), left (0–3).
            let top = (cf + cross(v[0], v[1]), rf);
            let right = (cf + 1.0, rf + cross(v[1], v[2]));
            let bottom = (cf + cross(v[3], v[2]), rf + 1.0);
            let left = (cf, rf + cross(v[0], v[3]));
            let centre_above = v.iter().sum::<f64>() / 4.0 > level;
            match case {
                1 | 14 => out.push((left, top)),
                2 | 13 => out.push((top, right)),
                3 | 12 => out.push((left, right)),
                4 | 11 => out.push((right, bottom)),
                6 | 9 => out.push((top, bottom)),
                7 | 8 => out.push((left, bottom)),
                5 => {
                    // Corners 0 and 2 above.
                    if centre_above {
                        out.push((left, bottom));
                        out.push((top, right));
                    } else {
                        out.push((left, top));
                        out.push((right, bottom));
                    }
                }
                10 => {
                    // Corners 1 and 3 above.
                    if centre_above {
                        out.push((left, top));
                        out.push((right, bottom));
                    } else {
                        out.push((left, bottom));
                        out.push((top, right));
                    }
                }
                _ => {}
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::reflectance::{Phong, Specular};
    use approx::assert_relative_eq;

    /// The closed form of the issue, written independently of `eval`.
    fn horn(p: f64, q: f64, ps: f64, qs: f64) -> f64 {
        ((1.0 + p * ps + q * qs)
            / ((1.0 + p * p + q * q).sqrt() * (1.0 + ps * ps + qs * qs).sqrt()))
        .max(0.0)
    }

    #[test]
    fn lambertian_map_is_the_closed_form() {
        let (ps, qs) = (0.7, -0.3);
        let r = ReflectanceMap::lambertian(Vector3::new(-ps, -qs, 1.0)).unwrap();
        assert!(r.is_lambertian());
        let (gp, gq) = r.light_gradient().unwrap();
        assert_relative_eq!(gp, ps, epsilon = 1e-12);
        assert_relative_eq!(gq, qs, epsilon = 1e-12);
        for p in [-3.0, -1.0, -0.2, 0.0, 0.4, 2.5] {
            for q in [-2.0, -0.5, 0.0, 0.3, 1.7] {
                assert_relative_eq!(r.eval(p, q), horn(p, q, ps, qs), epsilon = 1e-12);
            }
        }
        assert_relative_eq!(r.eval(ps, qs), 1.0, epsilon = 1e-12);
    }

    #[test]
    fn derivatives_match_finite_differences() {
        let phong = Material::with_specular(Specular::Phong(Phong {
            ks: 0.3,
            exponent: 20.0,
        }));
        for material in [Material::lambertian(), phong] {
            let r = ReflectanceMap::new(Vector3::new(0.3, 0.4, 0.8), material).unwrap();
            for (p, q) in [(0.1, -0.2), (-0.5, 0.3), (0.9, 0.8), (-1.5, -0.4)] {
                let s = r.eval_with_derivatives(p, q);
                let h = 1e-6;
                let dp = (r.eval(p + h, q) - r.eval(p - h, q)) / (2.0 * h);
                let dq = (r.eval(p, q + h) - r.eval(p, q - h)) / (2.0 * h);
                assert_relative_eq!(s.r, r.eval(p, q), epsilon = 1e-12);
                assert_relative_eq!(s.r_p, dp, epsilon = 1e-5, max_relative = 1e-4);
                assert_relative_eq!(s.r_q, dq, epsilon = 1e-5, max_relative = 1e-4);
            }
        }
    }

    #[test]
    fn material_map_agrees_with_the_renderer_convention() {
        // A grey Lambertian material through the generic path equals the closed form scaled by
        // its colour (to the f32 precision of the grey weights, which sum to 1).
        let mut m = Material::lambertian();
        m.diffuse_color = [0.5; 3];
        let light = Vector3::new(-0.4, 0.2, 0.9);
        let generic = ReflectanceMap::new(light, m).unwrap();
        let closed = ReflectanceMap::lambertian(light).unwrap();
        assert!(!generic.is_lambertian());
        for (p, q) in [(0.0, 0.0), (0.5, -0.3), (-1.2, 0.8)] {
            assert_relative_eq!(generic.eval(p, q), closed.eval(p, q) * 0.5, epsilon = 1e-6);
        }
        // A Phong highlight peaks at the half-way gradient between view and light.
        let phong = ReflectanceMap::new(
            light,
            Material::with_specular(Specular::Phong(Phong {
                ks: 0.5,
                exponent: 50.0,
            })),
        )
        .unwrap();
        let h = (light.normalize() + Vector3::z()).normalize();
        let (hp, hq) = gradient_from_normal(&h).unwrap();
        assert!(phong.eval(hp, hq) > phong.eval(hp + 0.2, hq) + 0.05);
    }

    #[test]
    fn contours_lie_on_their_level() {
        let r = ReflectanceMap::lambertian(Vector3::new(0.5, 0.3, 1.0)).unwrap();
        let n = 101;
        let extent = 3.0;
        let values = r.sample(extent, n).unwrap();
        let step = 2.0 * extent / (n - 1) as f64;
        for level in [0.2, 0.5, 0.9] {
            let segs = marching_squares(
                &values
                    .data()
                    .iter()
                    .map(|&v| f64::from(v))
                    .collect::<Vec<_>>(),
                n,
                level,
            );
            assert!(segs.len() > 20, "level {level}: {} segments", segs.len());
            let worst = segs
                .iter()
                .flat_map(|(a, b)| [a, b])
                .map(|&(c, row)| (r.eval(-extent + step * c, extent - step * row) - level).abs())
                .fold(0.0, f64::max);
            assert!(worst < 0.01, "level {level}: off by {worst}");
        }
        let svg = r.contour_svg(extent, &[0.2, 0.5, 0.9], 81).unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<title>R = ").count(), 4);
        assert!(svg.contains("<circle"));
        // Both axes carry their range, and no text runs past the drawing (about 7 px a
        // character at 12 px, 8 at 14 px).
        assert_eq!(svg.matches(r#"text-anchor="end">"#).count(), 5);
        assert!(
            svg.contains(&format!(">{extent}</text>"))
                && svg.contains(&format!(">-{extent}</text>"))
        );
        let width: f64 = svg
            .split("width=\"")
            .nth(1)
            .and_then(|t| t.split('"').next())
            .and_then(|t| t.parse().ok())
            .unwrap();
        for line in svg.lines().filter(|l| l.starts_with("<text")) {
            let x: f64 = line
                .split("x=\"")
                .nth(1)
                .and_then(|t| t.split('"').next())
                .and_then(|t| t.parse().ok())
                .unwrap();
            let text = line.split('>').nth(1).unwrap().trim_end_matches("</text");
            let px = if line.contains("font-size=\"14\"") {
                8.0
            } else {
                7.0
            };
            if !line.contains("text-anchor") {
                assert!(
                    x + px * text.chars().count() as f64 <= width,
                    "clipped: {line}"
                );
            }
        }
    }

    #[test]
    fn bad_parameters_are_refused() {
        assert!(ReflectanceMap::lambertian(Vector3::zeros()).is_err());
        assert!(ReflectanceMap::lambertian(Vector3::new(f64::NAN, 0.0, 1.0)).is_err());
        let r = ReflectanceMap::lambertian(Vector3::z()).unwrap();
        assert!(r.sample(1.0, 1).is_err());
        assert!(r.sample(f64::INFINITY, 10).is_err());
        assert!(r.contour_svg(1.0, &[f64::NAN], 10).is_err());
    }
}
