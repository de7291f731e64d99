//! Diffuse interreflections: light that reaches a pixel after bouncing off other parts of the
//! surface, which makes concave shapes (grooves, bowls, dimples) brighter than the local image
//! model says — the effect that biases photometric stereo towards flatter shapes (Nayar, Ikeuchi
//! & Kanade, "Shape from interreflections", IJCV 6(3), 1991).
//!
//! **Radiosity view.** The scene is a height field seen by an orthographic camera, and each
//! pixel stands for a Lambertian patch. With the renderer's convention a distant light of
//! intensity E gives a Lambertian point of albedo ρ the value P = E ρ (n·l)⁺ V, V the
//! visibility: the pixel value is the patch's radiosity B (exitance, W/m² per unit E), and its
//! radiance is B/π. The irradiance that the surface sends to a point i is then
//!
//! H_i = ∫_Ω (B(hit(ω))/π) cos θ dω = E_ω[B(hit(ω))], ω ~ cos θ/π,
//!
//! the mean of B over cosine-weighted directions of i's hemisphere, taken where each ray first
//! meets the surface (0 where it escapes to the dark environment), and one bounce adds
//! ρ_i H_i to the pixel (Goral, Torrance, Greenberg & Battaile, "Modeling the interaction of
//! light between diffuse surfaces", SIGGRAPH 1984; the gather is Monte-Carlo radiosity).
//! Bounce k + 1 gathers bounce k: B⁽ᵏ⁺¹⁾_i = ρ_i H_i[B⁽ᵏ⁾], and the pixel is
//! B⁽⁰⁾ + Σ_{k=1..K} B⁽ᵏ⁾ — the Neumann series of the radiosity equation B = B⁽⁰⁾ + ρ F B, which
//! converges to (I − ρF)⁻¹ B⁽⁰⁾ as K grows (F the form factors, ‖ρF‖ < 1).
//!
//! **Trace once, gather per light.** Where a ray from pixel i meets the surface does not depend
//! on the light, so [`BounceHits::trace`] casts S cosine-weighted rays per surface pixel once
//! and stores the index of the pixel each one meets (the pixel nearest to the hit point, by the
//! ray march of [`crate::synth::raymarch`] refined by bisection), or [`ESCAPED`]. Every light
//! and every bounce is then a gather over that table, S reads per pixel
//! ([`BounceHits::indirect`]). The S directions of a pixel are a Fibonacci lattice
//! ((m + ½)/S, m·φ⁻¹) on the unit square, shifted by a per-pixel random offset (Cranley &
//! Patterson 1976; deterministic, a hash of the seed and the pixel) and mapped to the
//! cosine-weighted hemisphere by Malley's method (uniform on the unit disc, projected up): the
//! estimate is unbiased and stratified, its error falling faster than the 1/√S of independent
//! samples.
//!
//! **Approximations.** A receiver reflects the bounced light with its diffuse lobe only: the
//! pixel gains ρ·(diffuse colour)·H, whatever its specular lobe (none for a material without a
//! diffuse lobe). A sender's outgoing light is the view-independent part of its direct light,
//! the Lambertian exitance E ρ d (n·l)⁺ V of its diffuse lobe (d the diffuse colour; Oren–Nayar
//! counted as Lambertian of the same albedo); its specular lobe and mirror highlights send
//! nothing, and the ambient term takes no part. Hit points are represented by the nearest
//! pixel's radiosity: a ray that meets a wall the camera cannot see (the riser of a step) gets
//! the radiosity of the pixel at the wall's top. Rays that leave the image escape, so the
//! scene ends at the image's border.
//!
//! **Memory.** The hit table holds S `u32` per surface pixel: 4·S bytes, 256 bytes per pixel
//! at the default S = 64 (as much as 64 grey float images; 4 MiB at 128², 256 MiB at 1024²).
//! S is capped at [`MAX_BOUNCE_SAMPLES`] and the table is allocated fallibly, so a table too
//! large for the machine is an error, not an abort. A light's gather keeps three radiosity maps
//! of 12 bytes per pixel.

use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::synth::hash_unit;
use crate::synth::raymarch::{HeightBounds, first_hit};
use crate::synth::reflectance::Frame;
use crate::synth::scene::{HeightField, Scene};
use nalgebra::Vector3;
use rayon::prelude::*;
use std::f64::consts::PI;

/// Default cosine-weighted rays per pixel ([`crate::synth::render::RenderOptions::bounce_samples`]).
pub const DEFAULT_BOUNCE_SAMPLES: usize = 64;
/// Largest number of rays per pixel (4 KiB of hit table per pixel).
pub const MAX_BOUNCE_SAMPLES: usize = 1024;
/// Largest number of bounces.
pub const MAX_BOUNCES: usize = 64;
/// The hit-table entry of a ray that meets no surface.
pub const ESCAPED: u32 = u32::MAX;

/// March step of the bounce rays, in pixels: coarser than the shadow test's 0.5, the
/// refinement finding edges between samples (see [`crate::synth::raymarch`]).
const HIT_STEP: f64 = 1.0;
/// Halvings of a march step where a bounce ray may have passed below an edge (1/64 pixel).
const HIT_REFINE: u32 = 6;
/// A hit takes the radiosity of the nearest of the four pixels around it whose normal is
/// within this angle of the surface's normal at the hit (cos 10°).
const SAME_SURFACE_COS: f64 = 0.984_807_753_012_208;
/// 1/φ, the golden ratio's inverse: the second coordinate of the Fibonacci lattice.
const INV_GOLDEN: f64 = 0.618_033_988_749_894_9;
/// Mixed into the seed of the ray directions so that they do not share a stream with anything
/// else seeded by the same number.
const BOUNCE_SEED_MIX: u64 = 0x5EED_B0B0_CAFE_F00D;

/// Where S cosine-weighted rays from each surface pixel first meet the surface: the
/// light-independent half of the interreflection gather (see the module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct BounceHits {
    width: usize,
    height: usize,
    samples: usize,
    /// Image index (row-major) of each surface pixel.
    pixels: Vec<u32>,
    /// `samples` entries per surface pixel: the image index of the pixel each ray meets, or
    /// [`ESCAPED`].
    hits: Vec<u32>,
}

impl BounceHits {
    /// Traces `samples` rays from every pixel of `truth` (the height field of `scene`),
    /// their directions seeded by `seed`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when `samples` is outside 1..=[`MAX_BOUNCE_SAMPLES`], the
    /// image has 2³² pixels or more, `truth` is not the size of `scene`, or the hit table cannot
    /// be allocated.
    pub fn trace(scene: &Scene, truth: &HeightField, samples: usize, seed: u64) -> Result<Self> {
        if !(1..=MAX_BOUNCE_SAMPLES).contains(&samples) {
            return Err(Error::param(
                "bounce-samples",
                format!("{samples} is outside 1..={MAX_BOUNCE_SAMPLES}"),
            ));
        }
        let (w, h) = (truth.mask.width(), truth.mask.height());
        if (w, h) != (scene.width, scene.height) {
            return Err(Error::DimensionMismatch {
                what: "height field and scene".into(),
                width: scene.width,
                height: scene.height,
                found_width: w,
                found_height: h,
            });
        }
        if w.checked_mul(h).is_none_or(|n| n >= ESCAPED as usize) {
            return Err(Error::param(
                "size",
                format!("{w}x{h}: interreflections index pixels with 32 bits"),
            ));
        }
        let pixels: Vec<u32> = (0..w * h)
            .filter(|&i| truth.mask.data()[i])
            .map(|i| i as u32)
            .collect();
        let len = pixels.len() * samples;
        let mut hits = Vec::new();
        hits.try_reserve_exact(len).map_err(|_| {
            Error::param(
                "bounce-samples",
                format!(
                    "the hit table of {} pixels × {samples} rays ({} MiB) cannot be allocated",
                    pixels.len(),
                    (len * 4) >> 20
                ),
            )
        })?;
        hits.resize(len, ESCAPED);
        let bounds = HeightBounds::new(scene);
        let seed = seed ^ BOUNCE_SEED_MIX;
        hits.par_chunks_mut(samples)
            .zip(pixels.par_iter())
            .for_each(|(out, &p)| {
                let (c, r) = (p as usize % w, p as usize / w);
                let (x, y) = scene.pixel_xy(c, r);
                let start = (x, y, f64::from(*truth.depth.at(c, r)));
                let frame = Frame::from_normal(truth.normals.at(c, r).cast::<f64>());
                let shift1 = hash_unit(seed, u64::from(p), 1);
                let shift2 = hash_unit(seed, u64::from(p), 2);
                for (m, slot) in out.iter_mut().enumerate() {
                    let d = cosine_direction(&frame, m, samples, (shift1, shift2));
                    *slot = first_hit(scene, &bounds, start, &d, HIT_STEP, HIT_REFINE)
                        .and_then(|(hx, hy)| pixel_of(truth, scene, hx, hy))
                        .unwrap_or(ESCAPED);
                }
            });
        Ok(BounceHits {
            width: w,
            height: h,
            samples,
            pixels,
            hits,
        })
    }

    /// Rays per pixel.
    pub fn samples(&self) -> usize {
        self.samples
    }

    /// The fraction of all rays that meet the surface (0 for a convex object alone, or a
    /// plane).
    pub fn hit_fraction(&self) -> f64 {
        if self.hits.is_empty() {
            return 0.0;
        }
        self.hits.iter().filter(|&&h| h != ESCAPED).count() as f64 / self.hits.len() as f64
    }

    /// The irradiance H_i = mean over i's rays of `radiosity` at the pixel each meets (0 for
    /// rays that escape), at every surface pixel; 0 elsewhere.
    ///
    /// # Errors
    /// [`Error::DimensionMismatch`] when `radiosity` is not the image's size.
    pub fn gather(&self, radiosity: &Grid<[f32; 3]>) -> Result<Grid<[f32; 3]>> {
        self.check_size(radiosity, "radiosity")?;
        let mut out = Grid::new(self.width, self.height, [0f32; 3]);
        let values: Vec<[f32; 3]> = self
            .hits
            .par_chunks(self.samples)
            .map(|rays| {
                let mut sum = [0f64; 3];
                for &hit in rays {
                    if hit != ESCAPED {
                        let b = radiosity.data()[hit as usize];
                        for (s, v) in sum.iter_mut().zip(b) {
                            *s += f64::from(v);
                        }
                    }
                }
                sum.map(|s| (s / rays.len() as f64) as f32)
            })
            .collect();
        for (&p, v) in self.pixels.iter().zip(values) {
            out.data_mut()[p as usize] = v;
        }
        Ok(out)
    }

    /// The light added by `bounces` bounces, Σ_{k=1..K} B⁽ᵏ⁾ with B⁽ᵏ⁺¹⁾ = ρ ⊙ H[B⁽ᵏ⁾]: `direct`
    /// is B⁽⁰⁾, each pixel's diffuse exitance under the light (per channel), and `reflectance`
    /// each pixel's diffuse reflectance ρ·(diffuse colour) per channel.
    ///
    /// # Errors
    /// [`Error::DimensionMismatch`] when a map is not the image's size.
    pub fn indirect(
        &self,
        direct: &Grid<[f32; 3]>,
        reflectance: &Grid<[f32; 3]>,
        bounces: usize,
    ) -> Result<Grid<[f32; 3]>> {
        self.check_size(reflectance, "reflectance")?;
        let mut total = Grid::new(self.width, self.height, [0f32; 3]);
        let mut radiosity = direct.clone();
        for _ in 0..bounces {
            radiosity = self.gather(&radiosity)?;
            for ((b, rho), t) in radiosity
                .data_mut()
                .iter_mut()
                .zip(reflectance.data())
                .zip(total.data_mut())
            {
                for c in 0..3 {
                    b[c] *= rho[c];
                    t[c] += b[c];
                }
            }
        }
        Ok(total)
    }

    fn check_size<T>(&self, map: &Grid<T>, what: &str) -> Result<()> {
        if (map.width(), map.height()) == (self.width, self.height) {
            Ok(())
        } else {
            Err(Error::DimensionMismatch {
                what: what.into(),
                width: self.width,
                height: self.height,
                found_width: map.width(),
                found_height: map.height(),
            })
        }
    }
}

/// Direction `m` of `samples` cosine-weighted directions about `frame`'s normal: point m of
/// the Fibonacci lattice ((m + ½)/S, m·φ⁻¹) on the unit square, shifted by `shift` (modulo 1),
/// mapped to the hemisphere by Malley's method (uniform on the unit disc, projected up).
pub(crate) fn cosine_direction(
    frame: &Frame,
    m: usize,
    samples: usize,
    shift: (f64, f64),
) -> Vector3<f64> {
    let u1 = ((m as f64 + 0.5) / samples as f64 + shift.0).fract();
    let u2 = (m as f64 * INV_GOLDEN + shift.1).fract();
    let (s, co) = (2.0 * PI * u2).sin_cos();
    let radius = u1.sqrt();
    frame.t * (radius * co) + frame.b * (radius * s) + frame.n * (1.0 - u1).max(0.0).sqrt()
}

/// The surface pixel whose radiosity stands for the hit point (x, y): of the (up to) four
/// pixels around it, the nearest whose normal is within 10° of the surface's at the hit, or
/// failing that the one whose normal is closest — so that a ray meeting a steep wall just
/// below a rim, or a face just beside a crease, takes the radiosity of that wall or face
/// rather than of the plane or face across the edge, whose pixel centre may be nearer.
fn pixel_of(truth: &HeightField, scene: &Scene, x: f64, y: f64) -> Option<u32> {
    let (w, h) = (scene.width, scene.height);
    let normal = scene.surface_at(x, y)?.1;
    let (xi, yi) = (x + (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0 - y);
    let (c0, r0) = (xi.floor(), yi.floor());
    // (distance², cos to the hit's normal, index) of the pixels around, nearest first.
    let mut slots = [(0.0, 0.0, 0usize); 4];
    let mut n = 0;
    for (c, r) in [
        (c0, r0),
        (c0 + 1.0, r0),
        (c0, r0 + 1.0),
        (c0 + 1.0, r0 + 1.0),
    ] {
        if c < 0.0 || r < 0.0 || c >= w as f64 || r >= h as f64 {
            continue;
        }
        let i = r as usize * w + c as usize;
        if truth.mask.data()[i] {
            let dist2 = (xi - c).powi(2) + (yi - r).powi(2);
            let cos = normal.dot(&truth.normals.data()[i].cast::<f64>());
            slots[n] = (dist2, cos, i);
            n += 1;
        }
    }
    let around = &mut slots[..n];
    around.sort_by(|a, b| a.0.total_cmp(&b.0));
    around
        .iter()
        .find(|a| a.1 >= SAME_SURFACE_COS)
        .or_else(|| around.iter().max_by(|a, b| a.1.total_cmp(&b.1)))
        .map(|a| a.2 as u32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::Lights;
    use crate::synth::reflectance::Material;
    use crate::synth::render::{RenderOptions, render};
    use crate::synth::scene::{Albedo, Object, Primitive, SceneKind};
    use nalgebra::{DMatrix, DVector, Vector2, Vector3};

    /// Albedo of the closed-form scenes.
    const RHO: f64 = 0.8;

    /// A V-groove along y with 60° between its faces, long enough (400 rows for a groove 24
    /// pixels wide) that its middle rows see an infinite groove: from rows 150..250 the ends
    /// are ≥ 150 pixels away, and the form factor beyond them, ≈ 4d³/(3πY³) of a strip at
    /// distance d ≤ 34, is below 0.4% (0.1% at the typical d ≈ 20).
    fn long_groove() -> (Scene, f64, f64) {
        let half = 12.0;
        let depth = half * 60f64.to_radians().tan();
        let scene = Scene {
            width: 40,
            height: 400,
            objects: vec![Object::new(
                Primitive::Groove {
                    cx: 0.0,
                    half_width: half,
                    depth,
                    z0: 0.0,
                },
                Albedo::Constant(RHO as f32),
            )],
        };
        (scene, half, depth)
    }

    /// The groove's cross-section: a face as a segment in the (x, z) plane from the crease to
    /// the rim, its unit normal, and whether the point `p` of the face sees the light `l`
    /// (the ray towards it clears the other face).
    struct Face {
        crease: Vector2<f64>,
        rim: Vector2<f64>,
        normal: Vector2<f64>,
    }

    fn faces(half: f64, depth: f64) -> [Face; 2] {
        let crease = Vector2::new(0.0, -depth);
        let side = |s: f64| Face {
            crease,
            rim: Vector2::new(s * half, 0.0),
            normal: Vector2::new(-s * depth, half).normalize(),
        };
        [side(-1.0), side(1.0)]
    }

    /// Whether the ray from `p` along `d` (x, z) crosses the segment [a, b].
    fn crosses(p: Vector2<f64>, d: Vector2<f64>, a: Vector2<f64>, b: Vector2<f64>) -> bool {
        let e = b - a;
        let den = d.x * e.y - d.y * e.x;
        if den.abs() < 1e-12 {
            return false;
        }
        let w = a - p;
        let t = (w.x * e.y - w.y * e.x) / den;
        let u = (w.x * d.y - w.y * d.x) / den;
        t > 1e-9 && (0.0..=1.0).contains(&u)
    }

    /// The direct exitance E ρ (n·l)⁺ V at the point `p` of face `f` (E = 1), `other` the
    /// opposite face.
    fn direct(f: &Face, other: &Face, p: Vector2<f64>, l: &Vector3<f64>) -> f64 {
        let l2 = Vector2::new(l.x, l.z);
        let cos = f.normal.dot(&l2);
        if cos <= 0.0 || crosses(p, l2, other.crease, other.rim) {
            0.0
        } else {
            RHO * cos
        }
    }

    /// Hottel's crossed-string form factor of two strips of an infinitely long 2-D
    /// configuration that see each other unobstructed, from [p1, p2] to [q1, q2] (p1, q1 the
    /// ends nearer the crease): (crossed − uncrossed strings) / (2 |p1 p2|).
    fn crossed_strings(
        p1: Vector2<f64>,
        p2: Vector2<f64>,
        q1: Vector2<f64>,
        q2: Vector2<f64>,
    ) -> f64 {
        let d = |a: Vector2<f64>, b: Vector2<f64>| (a - b).norm();
        (d(p1, q2) + d(p2, q1) - d(p1, q1) - d(p2, q2)) / (2.0 * d(p1, p2))
    }

    /// The point at fraction `t` ∈ [0, 1] from the crease to the rim of `f`.
    fn along(f: &Face, t: f64) -> Vector2<f64> {
        f.crease + (f.rim - f.crease) * t
    }

    /// The one-bounce irradiance at the point at fraction `t` of face `f` from the opposite face
    /// `o` whose exitance is `b(q)`, the opposite face cut into `n` strips: Σ_j b(q_j) F(dP → j),
    /// with Hottel's crossed strings from a strip of 2·10⁻⁴ of the face around P.
    fn gather_2d(f: &Face, o: &Face, t: f64, n: usize, b: impl Fn(usize) -> f64) -> f64 {
        let (p1, p2) = (along(f, t - 1e-4), along(f, t + 1e-4));
        (0..n)
            .map(|j| {
                let (a, c) = (j as f64 / n as f64, (j + 1) as f64 / n as f64);
                b(j) * crossed_strings(p1, p2, along(o, a), along(o, c))
            })
            .sum()
    }

    /// The direct exitance of strip `j` of `n` of face `o` (facing `f`) under `l`, with its
    /// shadow edge moved by `shift` pixels along x: the lowest and highest over shifts of
    /// ±½ pixel bracket what a renderer that knows the exitance at pixel centres can see.
    fn strip_exitance(
        o: &Face,
        f: &Face,
        half: f64,
        j: usize,
        n: usize,
        l: &Vector3<f64>,
    ) -> [f64; 2] {
        let t = (j as f64 + 0.5) / n as f64;
        let values = [-0.5, 0.0, 0.5].map(|dx: f64| {
            let tt = (t + dx / half).clamp(0.0, 1.0);
            direct(o, f, along(o, tt), l)
        });
        [
            values.iter().copied().fold(f64::INFINITY, f64::min),
            values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        ]
    }

    /// The mean over rows 150..250 of column `c` of `img` − `base`.
    /// Rays per pixel of the groove tests.
    const GROOVE_SAMPLES: usize = 256;
    /// Per light, its channel planes ([`Rendering::images`]).
    type Images = Vec<Vec<Grid<f32>>>;

    /// The groove tests' two lights (overhead, and 40° above +x), and `scene` rendered under
    /// them with each of `bounces` ([`GROOVE_SAMPLES`] rays per pixel).
    fn groove_renders(scene: &Scene, bounces: [usize; 2]) -> ([Vector3<f64>; 2], [Images; 2]) {
        let e = 40f64.to_radians();
        let dirs = [Vector3::z(), Vector3::new(e.cos(), 0.0, e.sin())];
        let lights = Lights::from_directions(&dirs).unwrap();
        let images = bounces.map(|bounces| {
            let o = RenderOptions {
                bounces,
                bounce_samples: GROOVE_SAMPLES,
                ..RenderOptions::default()
            };
            render(scene, &lights, &o).unwrap().images
        });
        (dirs, images)
    }

    fn row_mean(img: &Grid<f32>, base: &Grid<f32>, c: usize) -> f64 {
        (150..250)
            .map(|r| f64::from(img.at(c, r) - base.at(c, r)))
            .sum::<f64>()
            / 100.0
    }

    /// One bounce in an infinite V-groove against the closed form (Nayar, Ikeuchi & Kanade
    /// 1991): the irradiance at a point of one face is Σ_j B_j F(dP → j) over the opposite
    /// face, with Hottel's crossed-string form factors, here over 2000 strips. Under an overhead
    /// light both faces are uniformly lit; under a low one (elevation 40° from +x) the right face
    /// is in attached shadow and the right rim shadows the lower 35% of the left face. The
    /// renderer knows the sending face's exitance at pixel centres, so its shadow edge may be
    /// anywhere within ½ pixel: the closed form is the interval over those edges (a point for
    /// the overhead light). Measured: the row means fall within 0.00033 of the overhead light's
    /// closed form (peak 0.235; 3σ = 0.0030) and inside the low light's interval.
    #[test]
    fn one_bounce_in_a_groove_matches_crossed_strings() {
        let (scene, half, depth) = long_groove();
        let fs = faces(half, depth);
        let (dirs, [base, one]) = groove_renders(&scene, [0, 1]);
        for (k, l) in dirs.iter().enumerate() {
            let (b0, b1) = (&base[k][0], &one[k][0]);
            // Standard deviation of a row mean of ρ·H for independent rays (the stratified
            // lattice only does better): ρ B_max / (2 √(S·rows)).
            let b_max = RHO
                * fs.iter()
                    .map(|f| f.normal.dot(&Vector2::new(l.x, l.z)))
                    .fold(0.0, f64::max);
            let sigma = RHO * b_max / (2.0 * ((GROOVE_SAMPLES * 100) as f64).sqrt());
            for c in 0..40 {
                let x = c as f64 - 19.5;
                if x.abs() >= half {
                    // The plane beside the groove sees nothing.
                    assert_eq!(row_mean(b1, b0, c), 0.0);
                    continue;
                }
                let (f, o) = if x < 0.0 {
                    (&fs[0], &fs[1])
                } else {
                    (&fs[1], &fs[0])
                };
                let n = 2000;
                let [lo, hi] = [0, 1].map(|m| {
                    RHO * gather_2d(f, o, x.abs() / half, n, |j| {
                        strip_exitance(o, f, half, j, n, l)[m]
                    })
                });
                let got = row_mean(b1, b0, c);
                let miss = (lo - got).max(got - hi).max(0.0);
                assert!(
                    miss < 3.0 * sigma,
                    "light {k}, x = {x}: {got:.5} outside [{lo:.5}, {hi:.5}] ± 3σ = {:.5}",
                    3.0 * sigma
                );
            }
        }
    }

    /// Many bounces in the groove converge to the radiosity solution B = (I − ρF)⁻¹ B⁽⁰⁾ of the
    /// two faces cut into 240 strips each (crossed-string F, solved directly), gathered at
    /// each pixel's point. Measured: overhead, 0.0024 at worst below the solution (0.5% of its
    /// 0.52 peak at the crease; 3σ = 0.005); low light, inside the ½-pixel edge interval.
    #[test]
    fn bounces_converge_to_the_radiosity_solution_in_a_groove() {
        let (scene, half, depth) = long_groove();
        let fs = faces(half, depth);
        // ρF between the faces is ≤ 0.8·0.5: 12 bounces leave 0.4¹³ ≈ 10⁻⁵.
        let (dirs, [base, many]) = groove_renders(&scene, [0, 12]);
        let n = 240;
        // Strips 0..n on the left face, n..2n on the right, from the crease out.
        let strip = |i: usize| {
            let f = &fs[i / n];
            let j = i % n;
            (
                along(f, j as f64 / n as f64),
                along(f, (j + 1) as f64 / n as f64),
            )
        };
        let mut m = DMatrix::<f64>::identity(2 * n, 2 * n);
        for i in 0..2 * n {
            for j in 0..2 * n {
                if i / n != j / n {
                    let ((p1, p2), (q1, q2)) = (strip(i), strip(j));
                    m[(i, j)] -= RHO * crossed_strings(p1, p2, q1, q2);
                }
            }
        }
        let lu = m.lu();
        for (k, l) in dirs.iter().enumerate() {
            let [lo, hi] = [0, 1].map(|bound| {
                let b0 = DVector::from_fn(2 * n, |i, _| {
                    let (f, o) = (&fs[i / n], &fs[1 - i / n]);
                    strip_exitance(f, o, half, i % n, n, l)[bound]
                });
                lu.solve(&b0).expect("I − ρF is invertible")
            });
            let b_max = RHO
                * fs.iter()
                    .map(|f| f.normal.dot(&Vector2::new(l.x, l.z)))
                    .fold(0.0, f64::max);
            // Σ_k (ρF)^k amplifies the one-bounce error by at most 1/(1 − 0.4).
            let sigma = RHO * b_max / (2.0 * ((GROOVE_SAMPLES * 100) as f64).sqrt()) / 0.6;
            for c in 0..40 {
                let x = c as f64 - 19.5;
                if x.abs() >= half {
                    continue;
                }
                let side = usize::from(x > 0.0);
                let (f, o) = (&fs[side], &fs[1 - side]);
                let offset = (1 - side) * n;
                let [elo, ehi] =
                    [&lo, &hi].map(|b| RHO * gather_2d(f, o, x.abs() / half, n, |j| b[offset + j]));
                let got = row_mean(&many[k][0], &base[k][0], c);
                let miss = (elo - got).max(got - ehi).max(0.0);
                assert!(
                    miss < 3.0 * sigma,
                    "light {k}, x = {x}: {got:.5} outside [{elo:.5}, {ehi:.5}] ± {:.5}",
                    3.0 * sigma
                );
            }
        }
    }

    /// A bowl (spherical cap of radius R, polar half-angle θ_max) against the closed form of a
    /// spherical cavity: every point of a sphere's inside sees an area dA with the form factor
    /// dA/4πR², so one bounce gives every point of the bowl the same irradiance
    /// H = ∫ B dA / 4πR² whatever the light and its shadows, and every further bounce
    /// multiplies the (uniform) radiosity by ρ f, f = (1 − cos θ_max)/2 the cap's share of the
    /// sphere: the total is ρH/(1 − ρf). ∫ B dA is integrated over the cap with the exact
    /// shadow test (the ray towards l leaves the sphere above the rim).
    ///
    /// Over the 4112 pixels more than 2 pixels inside the rim (96², R = 40, depth 0.7R,
    /// 256 rays), measured: the mean is within 0.25% of the closed form (+0.08% and +0.25% for
    /// one bounce under the overhead and the oblique light, +0.07% and +0.24% for 12 bounces;
    /// the Monte-Carlo standard error of the mean is below 0.2%), and the pixels scatter about
    /// it by 0.0014–0.0025 rms (1–2% of H; independent rays could scatter up to
    /// ρ·B_max/(2√S) = 0.02).
    #[test]
    fn bowl_interreflection_is_uniform_as_in_a_spherical_cavity() {
        let (size, radius, depth) = (96usize, 40.0, 28.0);
        let scene = Scene {
            width: size,
            height: size,
            objects: vec![Object::new(
                Primitive::Bowl {
                    cx: 0.0,
                    cy: 0.0,
                    radius,
                    depth,
                    z0: 0.0,
                },
                Albedo::Constant(RHO as f32),
            )],
        };
        let (e, az) = (50f64.to_radians(), 30f64.to_radians());
        let dirs = [
            Vector3::z(),
            Vector3::new(e.cos() * az.cos(), e.cos() * az.sin(), e.sin()),
        ];
        let lights = Lights::from_directions(&dirs).unwrap();
        let samples = 256;
        let with = |bounces| {
            let o = RenderOptions {
                bounces,
                bounce_samples: samples,
                ..RenderOptions::default()
            };
            render(&scene, &lights, &o).unwrap()
        };
        let (base, one, many) = (with(0), with(1), with(12));
        let cos_max = (radius - depth) / radius;
        let share = (1.0 - cos_max) / 2.0;
        // Pixels inside the rim (two pixels in, away from the rim's crease).
        let rim = (2.0 * radius * depth - depth * depth).sqrt();
        let inside: Vec<usize> = (0..size * size)
            .filter(|&i| {
                let (x, y) = scene.pixel_xy(i % size, i / size);
                (x * x + y * y).sqrt() < rim - 2.0
            })
            .collect();
        for (k, l) in dirs.iter().enumerate() {
            // ∫ B dA over the cap, midpoint rule in (θ, φ).
            let (nt, np) = (1000, 1000);
            let mut integral = 0.0;
            for i in 0..nt {
                let th = (i as f64 + 0.5) / nt as f64 * cos_max.acos();
                for j in 0..np {
                    let ph = (j as f64 + 0.5) / np as f64 * 2.0 * PI;
                    let n = Vector3::new(-th.sin() * ph.cos(), -th.sin() * ph.sin(), th.cos());
                    let cos = n.dot(l);
                    // P = C − R n; the ray leaves the sphere at P + 2R(n·l) l.
                    let exit_z = (radius - depth) - radius * n.z + 2.0 * radius * cos * l.z;
                    if cos > 0.0 && exit_z >= 0.0 {
                        integral += RHO * cos * th.sin();
                    }
                }
            }
            integral *= radius * radius * (cos_max.acos() / nt as f64) * (2.0 * PI / np as f64);
            let h = integral / (4.0 * PI * radius * radius);
            let expect_one = RHO * h;
            let expect_many = RHO * h / (1.0 - RHO * share);
            for (r, expect) in [(&one, expect_one), (&many, expect_many)] {
                let got: Vec<f64> = inside
                    .iter()
                    .map(|&i| f64::from(r.images[k][0].data()[i] - base.images[k][0].data()[i]))
                    .collect();
                let mean = got.iter().sum::<f64>() / got.len() as f64;
                let rms = (got.iter().map(|g| (g - expect).powi(2)).sum::<f64>()
                    / got.len() as f64)
                    .sqrt();
                assert!(
                    (mean / expect - 1.0).abs() < 0.01,
                    "light {k}: mean {mean} vs {expect}"
                );
                assert!(rms < 0.005, "light {k}: rms {rms} about {expect}");
            }
        }
    }

    /// Interreflections only add light; a plane and a convex object alone get none; the
    /// bounced light of a coloured surface is filtered by its colour once per reflection.
    #[test]
    fn bounces_add_light_only_where_the_surface_sees_itself() {
        let lights = Lights::fibonacci(5, 30.0).unwrap();
        let render_with = |scene: &Scene, bounces, color| {
            let o = RenderOptions {
                bounces,
                bounce_samples: 16,
                color,
                ..RenderOptions::default()
            };
            render(scene, &lights, &o).unwrap()
        };
        for kind in [
            SceneKind::Relief,
            SceneKind::Groove,
            SceneKind::Torus,
            SceneKind::Bowl,
        ] {
            let scene = kind.build(48, Albedo::Constant(0.7), Material::lambertian());
            let r: Vec<_> = (0..3).map(|b| render_with(&scene, b, false)).collect();
            let mut gained = 0.0;
            for k in 0..lights.len() {
                for i in 0..48 * 48 {
                    let v = [0, 1, 2].map(|b| r[b].images[k][0].data()[i]);
                    assert!(v[0] <= v[1] && v[1] <= v[2], "{}: {v:?}", kind.name());
                    gained += f64::from(v[2] - v[0]);
                }
            }
            assert!(gained > 1.0, "{}: {gained}", kind.name());
        }
        let plane = Scene {
            width: 32,
            height: 32,
            objects: vec![Object::ground(Albedo::Constant(0.9))],
        };
        let sphere = Scene::sphere(32, 12.0, Albedo::Constant(0.9));
        for scene in [plane, sphere] {
            let hf = scene.height_field();
            assert_eq!(
                BounceHits::trace(&scene, &hf, 32, 0)
                    .unwrap()
                    .hit_fraction(),
                0.0
            );
            assert_eq!(
                render_with(&scene, 3, false).images,
                render_with(&scene, 0, false).images
            );
        }
        // Colour: R, G, B diffuse colours 1, ½, ¼ — the first bounce's light is reflected twice.
        let material = Material {
            diffuse_color: [1.0, 0.5, 0.25],
            ..Material::lambertian()
        };
        let scene = SceneKind::Groove.build(32, Albedo::Constant(0.7), material);
        let (a, b) = (render_with(&scene, 0, true), render_with(&scene, 1, true));
        let mut checked = 0;
        for i in 0..32 * 32 {
            let add =
                [0, 1, 2].map(|c| f64::from(b.images[0][c].data()[i] - a.images[0][c].data()[i]));
            if add[0] > 0.01 {
                assert!((add[1] / add[0] - 0.25).abs() < 1e-3, "{add:?}");
                assert!((add[2] / add[0] - 0.0625).abs() < 1e-3, "{add:?}");
                checked += 1;
            }
        }
        assert!(checked > 100, "{checked}");
    }

    /// Bad inputs are errors, not panics.
    #[test]
    fn bad_tables_are_errors() {
        let scene = SceneKind::Groove.build(16, Albedo::Constant(0.5), Material::lambertian());
        let hf = scene.height_field();
        assert!(BounceHits::trace(&scene, &hf, 0, 0).is_err());
        assert!(BounceHits::trace(&scene, &hf, MAX_BOUNCE_SAMPLES + 1, 0).is_err());
        let other = SceneKind::Groove.build(17, Albedo::Constant(0.5), Material::lambertian());
        assert!(BounceHits::trace(&other, &hf, 4, 0).is_err());
        let hits = BounceHits::trace(&scene, &hf, 4, 0).unwrap();
        assert!(hits.gather(&Grid::new(15, 16, [0.0; 3])).is_err());
        let ok = Grid::new(16, 16, [1.0f32; 3]);
        assert!(hits.indirect(&ok, &Grid::new(16, 15, [0.0; 3]), 1).is_err());
        let options = RenderOptions {
            bounces: MAX_BOUNCES + 1,
            ..RenderOptions::default()
        };
        assert!(
            options
                .validate()
                .unwrap_err()
                .to_string()
                .contains("bounces")
        );
    }
}
