//! Is the mask's outline an occluding contour? Tested against the image before solving.
//!
//! Horn's method with [`super::Boundary::Occluding`] (the default) assumes that wherever the
//! mask's outline lies inside the image the surface turns away from the camera there, and
//! starts from a surface that does. That is true of an object's silhouette, and false where the
//! mask was cut across the surface: the cut ends of a vase, an object's foot standing on a
//! table, a region drawn by hand. There the convex start is wrong, and nothing else tells the
//! solver so: on the rendered vase of `bench sfs` every Horn solve at 128² was more than 5° or
//! 5% off the truth, and 2 of the 11 warned (docs/shape-from-shading.md, "Is the outline an
//! occluding contour?").
//!
//! The image can say where the assumption fails. At an occluding contour the normal lies in the
//! image plane, along the outline's outward direction m: n = (m, 0). A pixel of the outline
//! lies within about a pixel of the contour, so its normal is n(t) = (√(1 − t²) m, t) for a
//! small t = n_z: at a distance δ inside a contour of curvature radius r (pixels),
//! t ≈ √(2δ/r), at most [`MAX_RIM_NZ`] = ½ for δ ≤ √2 (a pixel whose only outside neighbour
//! is diagonal) wherever r ≥ 8δ ≈ 11 px. A surface turning
//! away from the view therefore cannot make an outline pixel brighter than the largest
//! R(n(t)) over t ≤ ½. An outline pixel brighter than that, by more than the image's noise
//! allows, contradicts the occluding contour: the surface there faces the camera more than 60°
//! from edge-on. The test is one-sided on purpose: an outline darker than a contour could be
//! is also what an albedo set too high gives, while a brighter one needs an albedo more than
//! 20% too low before a silhouette fails it (measured below).
//!
//! Measured with a prototype of this test on rendered scenes (128², Lambertian, albedo 0.8,
//! seven lights: at the view, and 20°–30° off it at azimuths 26.6°–300°; the outward direction
//! from the outside pixels within two pixels): the
//! silhouettes of the sphere, ellipsoid and bust contradict in no pixel, with the albedo given
//! or set 10% off either way, with noise σ = 0 or 0.02; with the albedo 20% too low the bust
//! reaches 4.5% of its outline. The vase's cut ends, a quarter of its outline, contradict in
//! 6–24% of it (fewest under a light from below, where the cut ends are darker). So a result is
//! reported as resting on a wrong boundary above [`CONTRADICTED_WARN`] (5%) of the outline.
//!
//! Not tested: Horn's lower-resolution levels and the outline repair's upsampled image (their
//! outline pixels lie further inside the contour, or blend brighter pixels), which use the
//! full-resolution result; an outline pixel whose offsets to the outside cancel (a one-pixel
//! spur) has no outward direction and counts as a contour.
//!
//! The perspective method (`perspective`) takes the outline for an occluding contour too, and
//! is tested the same way after its solve (`test_outline`): its brightness depends on each
//! point's distance to the light, so the bound there is the brightest an edge-on normal (at
//! right angles to the pixel's ray, n·(towards the camera) ≤ [`MAX_RIM_NZ`]) can be at the
//! depth the result gives the pixel, in the image's units, with three times the image's noise
//! (at least the shadow level) as the margin. On the rendered sphere and bust (128², 31 lights:
//! at the camera and 10°–35° off it at six azimuths, no noise; 96², four lights, noise 0 and 1%,
//! the albedo given and 0.8, 0.9, 1.1 and 1.25 times it) no outline pixel contradicts at 128²
//! and at most one at 96²; the vase 6.8–10% of its outline under every light
//! (docs/shape-from-shading.md, "The perspective method's outline, tested"). Where the image's
//! noise cannot be measured the margin is the shadow level alone.
//!
//! Fails where: a contour of curvature radius under about 11 px (a rod thinner than 22 px) may
//! contradict it; a cut end that happens to be no brighter than a contour (lit from below, or
//! by a very oblique light) passes it; the albedo must be known within about 20% (Horn).

use crate::integrate::sparse::Unknowns;
use crate::sfs::reflectance_map::{ReflectanceMap, gradient_from_normal};
use nalgebra::Vector3;
use serde::Serialize;

/// Largest n_z of an outline pixel of an occluding contour (see the module documentation).
pub const MAX_RIM_NZ: f64 = 0.5;

/// Fraction of the outline's pixels contradicting an occluding contour above which a solve
/// that assumed one warns (see the module documentation for how it was chosen).
pub const CONTRADICTED_WARN: f64 = 0.05;

/// Radius (pixels) of the window whose outside pixels give an outline pixel's outward
/// direction (the offsets with dx² + dy² ≤ 6: the 5×5 square without its corners): one pixel's
/// eight neighbours resolve directions 45° apart, and a wrong direction
/// lowers the brightest edge-on normal the test allows (2 px: the silhouettes above contradict
/// in at most 3.6% of their outline with the albedo 12% too high and the eight neighbours, in
/// none with this window).
const WINDOW: i64 = 2;

/// Values of t = n_z sampled in (0, [`MAX_RIM_NZ`]].
const SAMPLES: usize = 50;

/// What the test of the outline found (see the module documentation).
#[non_exhaustive]
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OccludingTest {
    /// Outline pixels tested: mask pixels with a neighbour (of eight) outside the mask but inside
    /// the image, except where the offsets to the outside cancel (no outward direction).
    pub pixels: usize,
    /// Those brighter than a surface turning away from the view could make them.
    pub contradicted: usize,
    /// `contradicted / pixels`.
    pub fraction: f64,
    /// How much brighter a pixel must be to count: three times the image's noise, at least the
    /// shadow level; for the distant-light methods over the albedo (in E/ρ), for the
    /// perspective method in the image's own units.
    pub tolerance: f64,
}

/// The test's result: its summary (`None` when the outline has no pixel inside the image) and,
/// per unknown of `u`, whether it contradicts an occluding contour.
pub(crate) struct Outline {
    pub summary: Option<OccludingTest>,
    pub contradicted: Vec<bool>,
}

/// Tests the outline of the unknowns `u` against the relative brightness `e` (E/ρ per unknown)
/// under `rmap`, with the margin `tolerance` (see the module documentation).
pub(crate) fn test(u: &Unknowns, e: &[f64], rmap: &ReflectanceMap, tolerance: f64) -> Outline {
    test_outline(u, tolerance, |k, mx, my| {
        e[k] > brightest_edge_on(rmap, mx, my) + tolerance
    })
}

/// The outline test with the brightness bound left to the caller: `contradicts(k, mx, my)`
/// says whether outline unknown k, whose outward direction in the image is the unit (mx, my)
/// (x right, y up), is brighter than a surface turning away from the view could make it.
/// `tolerance` is the margin it allows, reported as is.
pub(crate) fn test_outline(
    u: &Unknowns,
    tolerance: f64,
    contradicts: impl Fn(usize, f64, f64) -> bool,
) -> Outline {
    let (w, h) = (u.w as i64, u.h as i64);
    let inside = u.inside();
    let outside = |x: i64, y: i64| {
        (0..w).contains(&x) && (0..h).contains(&y) && !inside[(y * w + x) as usize]
    };
    let mut contradicted = vec![false; u.len()];
    let (mut pixels, mut count) = (0usize, 0usize);
    for (k, &p) in u.pixel.iter().enumerate() {
        let (x, y) = (p as i64 % w, p as i64 / w);
        let on_outline = (-1..=1).any(|dy| (-1..=1).any(|dx| outside(x + dx, y + dy)));
        if !on_outline {
            continue;
        }
        // Outward, x right and y up (rows run down).
        let (mut ox, mut oy) = (0.0f64, 0.0f64);
        for dy in -WINDOW..=WINDOW {
            for dx in -WINDOW..=WINDOW {
                if dx * dx + dy * dy <= WINDOW * WINDOW + WINDOW && outside(x + dx, y + dy) {
                    ox += dx as f64;
                    oy -= dy as f64;
                }
            }
        }
        let length = ox.hypot(oy);
        if length == 0.0 {
            continue;
        }
        pixels += 1;
        if contradicts(k, ox / length, oy / length) {
            contradicted[k] = true;
            count += 1;
        }
    }
    Outline {
        summary: (pixels > 0).then(|| OccludingTest {
            pixels,
            contradicted: count,
            fraction: count as f64 / pixels as f64,
            tolerance,
        }),
        contradicted,
    }
}

/// The largest R(n(t)) over t ∈ (0, [`MAX_RIM_NZ`]] for the outward direction (mx, my).
fn brightest_edge_on(rmap: &ReflectanceMap, mx: f64, my: f64) -> f64 {
    (0..=SAMPLES)
        .map(|i| (MAX_RIM_NZ * i as f64 / SAMPLES as f64).max(1e-3))
        .filter_map(|t| {
            let c = (1.0 - t * t).sqrt();
            gradient_from_normal(&Vector3::new(c * mx, c * my, t))
        })
        .map(|(p, q)| rmap.eval(p, q))
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use crate::sfs::reflectance_map::normal_from_gradient;

    /// A disk's outline, shaded as an occluding contour, contradicts in no pixel; the same
    /// outline shaded as a surface facing the camera (a disk cut from a plane) contradicts in
    /// every pixel the light reaches brighter than edge-on, and the flags are on the outline
    /// only.
    #[test]
    fn a_cut_outline_is_told_from_a_silhouette() {
        let n = 41;
        let c = 20.0;
        let radius = 15.0;
        let mut mask = Grid::new(n, n, false);
        for y in 0..n {
            for x in 0..n {
                let (dx, dy) = (x as f64 - c, y as f64 - c);
                mask.data_mut()[y * n + x] = dx.hypot(dy) <= radius;
            }
        }
        let u = Unknowns::new(&mask);
        let light = Vector3::new(0.3, 0.2, 0.933).normalize();
        let rmap = ReflectanceMap::lambertian(light).unwrap();
        // A hemisphere: its outline is an occluding contour.
        let sphere: Vec<f64> = u
            .pixel
            .iter()
            .map(|&p| {
                let (x, y) = ((p as usize % n) as f64 - c, c - (p as usize / n) as f64);
                let r = (x.hypot(y) / (radius + 0.5)).min(0.999);
                let nz = (1.0 - r * r).sqrt();
                let nrm = Vector3::new(x / (radius + 0.5), y / (radius + 0.5), nz);
                rmap.eval(-nrm.x / nrm.z, -nrm.y / nrm.z)
            })
            .collect();
        let silhouette = test(&u, &sphere, &rmap, 0.01);
        let s = silhouette.summary.unwrap();
        assert!(s.pixels > 60, "{}", s.pixels);
        assert_eq!(s.contradicted, 0);
        // A plane facing the camera, cut to the same disk.
        let facing = normal_from_gradient(0.0, 0.0).dot(&light);
        let plane = vec![facing; u.len()];
        let cut = test(&u, &plane, &rmap, 0.01);
        let s = cut.summary.unwrap();
        assert!(s.fraction > 0.9, "{}", s.fraction);
        for (k, &flag) in cut.contradicted.iter().enumerate() {
            if flag {
                let p = u.pixel[k] as usize;
                let (x, y) = ((p % n) as f64 - c, (p / n) as f64 - c);
                assert!(
                    x.hypot(y) > radius - 2.0,
                    "({x}, {y}) is not on the outline"
                );
            }
        }
    }

    /// An image filling the frame has no outline to test.
    #[test]
    fn no_outline_inside_the_image_is_no_test() {
        let mask = Grid::new(8, 6, true);
        let u = Unknowns::new(&mask);
        let rmap = ReflectanceMap::lambertian(Vector3::z()).unwrap();
        let t = test(&u, &vec![1.0; u.len()], &rmap, 0.01);
        assert!(t.summary.is_none());
        assert!(t.contradicted.iter().all(|&b| !b));
    }
}
