//! Form factors of a reconstructed surface: for each surface pixel, which pixels its
//! cosine-weighted hemisphere sees, and in what proportion (see the module documentation of
//! [`crate::ps::interreflection`] for the equations).
//!
//! The surface is the height map of an orthographic reconstruction (pixel units, x to the
//! right, y up, z towards the camera) with its normals. A ray leaves each surface pixel's
//! centre at its height; it is marched over the image plane one pixel at a time, the height
//! under it interpolated bilinearly between the four surrounding surface pixels (the nearest
//! one where some of the four are not surface), and it is blocked where that height exceeds
//! its own by more than [`HIT_EPS`] pixel. The interval where it crossed is halved
//! [`HIT_BISECTIONS`] times, and the ray's light comes from the surface pixel nearest the
//! crossing that faces back along the ray. Tiles of 8×8 pixels carry their highest height, so
//! a ray passing above a tile crosses it in one step, and a rising ray above the whole surface
//! escapes. Rays that leave the image, or pass over pixels that are not surface, escape to a
//! dark surround.

use crate::error::{Error, Result};
use crate::grid::{Mask, NormalMap, ScalarMap};
use crate::synth::hash_unit;
use crate::synth::interreflection::cosine_direction;
use crate::synth::reflectance::Frame;
use nalgebra::Vector3;
use rayon::prelude::*;

/// Largest number of rays per pixel.
pub const MAX_RAYS: usize = 1024;
/// A ray is blocked where the surface stands this far above it (pixel units): above the
/// rounding of heights integrated in single precision.
pub const HIT_EPS: f64 = 1e-2;
/// Halvings of the march step that locate a crossing (1/32 pixel).
pub const HIT_BISECTIONS: usize = 5;
/// Sides of the tiles whose highest height lets a ray skip them, in pixels, coarsest first:
/// a ray above a 64-pixel tile crosses it in one step, and one above an 8-pixel tile too.
const TILES: [usize; 2] = [64, 8];
/// Mixed into the seed so that the directions share no stream with other seeded draws.
const SEED_MIX: u64 = 0x1A7E_5EF1_EC75_0001;

/// The light-independent half of the interreflection gather on a reconstructed surface: for
/// each surface pixel i the pixels j that its rays meet first, with the fraction F_ij of its
/// rays that meet each (Σ_j F_ij ≤ 1: the rest escape). With cosine-weighted rays F_ij is the
/// form factor from i to pixel j's patch.
#[derive(Debug, Clone, PartialEq)]
pub struct FormFactors {
    width: usize,
    height: usize,
    rays: usize,
    /// Image index (row-major) of each surface pixel.
    pixels: Vec<u32>,
    /// Compressed rows: the senders of surface pixel k are `targets[offsets[k]..offsets[k+1]]`.
    offsets: Vec<u32>,
    /// Image index of each sender.
    targets: Vec<u32>,
    /// F_ij of each sender.
    weights: Vec<f32>,
}

/// The height map over the image, with the tile maxima used to skip empty space.
struct Surface<'a> {
    depth: &'a [f32],
    normals: &'a [Vector3<f32>],
    on: Vec<bool>,
    width: usize,
    height: usize,
    levels: Vec<Tiles>,
    top: f64,
}

/// The highest surface height over square tiles of one size.
struct Tiles {
    size: usize,
    across: usize,
    down: usize,
    top: Vec<f64>,
}

impl Tiles {
    fn new(size: usize, width: usize, height: usize, depth: &[f32], on: &[bool]) -> Self {
        let (across, down) = (width.div_ceil(size), height.div_ceil(size));
        let mut top = vec![f64::NEG_INFINITY; across * down];
        for ty in 0..down {
            for tx in 0..across {
                // A position inside the tile interpolates between pixels up to one beyond it.
                let mut t = f64::NEG_INFINITY;
                for r in ty * size..((ty + 1) * size + 1).min(height) {
                    for c in tx * size..((tx + 1) * size + 1).min(width) {
                        let i = r * width + c;
                        if on[i] {
                            t = t.max(f64::from(depth[i]));
                        }
                    }
                }
                top[ty * across + tx] = t;
            }
        }
        Tiles {
            size,
            across,
            down,
            top,
        }
    }

    /// The highest height of the tile holding (x, y), and how far along (ux, uy) the tile ends
    /// (the outer tiles end at the image's border, half a pixel beyond the last centre).
    fn at(&self, x: f64, y: f64, ux: f64, uy: f64, width: usize, height: usize) -> (f64, f64) {
        let size = self.size;
        let index = |p: f64, tiles: usize| ((p.max(0.0) as usize) / size).min(tiles - 1);
        let (tx, ty) = (index(x, self.across), index(y, self.down));
        let top = self.top[ty * self.across + tx];
        let exit = |p: f64, u: f64, t: usize, tiles: usize, dim: usize| {
            let lo = if t == 0 { -0.5 } else { (t * size) as f64 };
            let hi = if t + 1 == tiles {
                dim as f64 - 0.5
            } else {
                ((t + 1) * size) as f64
            };
            if u > 1e-12 {
                (hi - p) / u
            } else if u < -1e-12 {
                (p - lo) / -u
            } else {
                f64::INFINITY
            }
        };
        let along_x = exit(x, ux, tx, self.across, width);
        let along_y = exit(y, uy, ty, self.down, height);
        (top, along_x.min(along_y).max(0.0))
    }
}

impl<'a> Surface<'a> {
    fn new(depth: &'a ScalarMap, normals: &'a NormalMap, mask: &Mask) -> Self {
        let (width, height) = (depth.width(), depth.height());
        let on: Vec<bool> = mask
            .data()
            .iter()
            .zip(depth.data())
            .zip(normals.data())
            .map(|((&m, d), n)| m && d.is_finite() && n.iter().all(|v| v.is_finite()))
            .collect();
        let levels: Vec<Tiles> = TILES
            .iter()
            .map(|&size| Tiles::new(size, width, height, depth.data(), &on))
            .collect();
        let top = levels[0]
            .top
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        Surface {
            depth: depth.data(),
            normals: normals.data(),
            on,
            width,
            height,
            levels,
            top,
        }
    }

    /// Inside the image (column x, row y, pixel centres at integers)?
    fn inside(&self, x: f64, y: f64) -> bool {
        x >= -0.5 && y >= -0.5 && x < self.width as f64 - 0.5 && y < self.height as f64 - 0.5
    }

    /// The surface height at (x, y), or `None` where no surface pixel is near.
    fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        let (w, h) = (self.width, self.height);
        let (c0, r0) = (x.floor().max(0.0) as usize, y.floor().max(0.0) as usize);
        let (c1, r1) = ((c0 + 1).min(w - 1), (r0 + 1).min(h - 1));
        let corners = [r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1];
        if corners.iter().all(|&i| self.on[i]) {
            let (fx, fy) = (
                (x - c0 as f64).clamp(0.0, 1.0),
                (y - r0 as f64).clamp(0.0, 1.0),
            );
            let d = |i: usize| f64::from(self.depth[i]);
            let top = d(corners[0]) * (1.0 - fx) + d(corners[1]) * fx;
            let bottom = d(corners[2]) * (1.0 - fx) + d(corners[3]) * fx;
            return Some(top * (1.0 - fy) + bottom * fy);
        }
        let (c, r) = (
            x.round().clamp(0.0, (w - 1) as f64),
            y.round().clamp(0.0, (h - 1) as f64),
        );
        let i = r as usize * w + c as usize;
        self.on[i].then(|| f64::from(self.depth[i]))
    }

    /// The surface pixel a ray from pixel `from` in direction `d` meets first, if any.
    fn first_hit(&self, from: usize, d: &Vector3<f64>) -> Option<u32> {
        let dxy = d.x.hypot(d.y);
        if dxy < 1e-9 {
            return None;
        }
        let (x0, y0) = ((from % self.width) as f64, (from / self.width) as f64);
        let z0 = f64::from(self.depth[from]);
        // Image columns go with x, rows against y.
        let (ux, uy, slope) = (d.x / dxy, -d.y / dxy, d.z / dxy);
        let at = |s: f64| (x0 + s * ux, y0 + s * uy, z0 + s * slope);
        let blocked = |s: f64| {
            let (x, y, z) = at(s);
            self.height_at(x, y).is_some_and(|h| h > z + HIT_EPS)
        };
        let limit = (self.width + self.height) as f64 * 2.0;
        let (mut clear, mut s) = (0.0, 1.0);
        while s < limit {
            let (x, y, z) = at(s);
            if !self.inside(x, y) || (slope >= 0.0 && z > self.top + HIT_EPS) {
                return None;
            }
            // The largest tile the ray passes above, if any, is crossed in one step.
            let skip = self.levels.iter().find_map(|level| {
                let (top, exit) = level.at(x, y, ux, uy, self.width, self.height);
                (z.min(z + exit * slope) > top + HIT_EPS).then_some(exit)
            });
            if let Some(exit) = skip {
                clear = s;
                s += exit + 1e-6;
                continue;
            }
            if blocked(s) {
                let mut hit = s;
                for _ in 0..HIT_BISECTIONS {
                    let mid = 0.5 * (clear + hit);
                    if blocked(mid) {
                        hit = mid;
                    } else {
                        clear = mid;
                    }
                }
                let (x, y, _) = at(hit);
                return self.sender(x, y, d);
            }
            clear = s;
            s += 1.0;
        }
        None
    }

    /// The surface pixel that stands for the hit at (x, y): the nearest of the four around it
    /// that faces back along the ray, or failing that the nearest.
    fn sender(&self, x: f64, y: f64, d: &Vector3<f64>) -> Option<u32> {
        let (w, h) = (self.width as f64, self.height as f64);
        let (c0, r0) = (x.floor(), y.floor());
        let mut best: Option<(bool, f64, usize)> = None;
        for (c, r) in [
            (c0, r0),
            (c0 + 1.0, r0),
            (c0, r0 + 1.0),
            (c0 + 1.0, r0 + 1.0),
        ] {
            if c < 0.0 || r < 0.0 || c >= w || r >= h {
                continue;
            }
            let i = r as usize * self.width + c as usize;
            if !self.on[i] {
                continue;
            }
            let faces = self.normals[i].cast::<f64>().dot(d) < 0.0;
            let dist = (x - c).powi(2) + (y - r).powi(2);
            let better = match best {
                None => true,
                Some((f, bd, _)) => (faces && !f) || (faces == f && dist < bd),
            };
            if better {
                best = Some((faces, dist, i));
            }
        }
        best.map(|(_, _, i)| i as u32)
    }
}

impl FormFactors {
    /// Traces `rays` cosine-weighted rays from every pixel of `mask` where `depth` and
    /// `normals` are finite, their directions seeded by `seed`: a Fibonacci lattice on the unit
    /// square with a per-pixel random shift, mapped to the hemisphere by Malley's method.
    ///
    /// # Errors
    /// [`Error::DimensionMismatch`] when the maps differ in size; [`Error::InvalidParameter`]
    /// when `rays` is outside 1..=[`MAX_RAYS`] or the image has 2³² pixels or more.
    pub fn trace(
        depth: &ScalarMap,
        normals: &NormalMap,
        mask: &Mask,
        rays: usize,
        seed: u64,
    ) -> Result<Self> {
        depth.check_same_size(normals, "normals")?;
        depth.check_same_size(mask, "mask")?;
        if !(1..=MAX_RAYS).contains(&rays) {
            return Err(Error::param(
                "interreflection rays",
                format!("{rays} is outside 1..={MAX_RAYS}"),
            ));
        }
        let (width, height) = (depth.width(), depth.height());
        if width
            .checked_mul(height)
            .is_none_or(|n| n >= u32::MAX as usize)
        {
            return Err(Error::param(
                "size",
                format!("{width}x{height}: interreflections index pixels with 32 bits"),
            ));
        }
        let surface = Surface::new(depth, normals, mask);
        let pixels: Vec<u32> = (0..width * height)
            .filter(|&i| surface.on[i])
            .map(|i| i as u32)
            .collect();
        let seed = seed ^ SEED_MIX;
        let rows: Vec<Vec<(u32, f32)>> = pixels
            .par_iter()
            .map(|&p| {
                let n = normals.data()[p as usize].cast::<f64>().normalize();
                let frame = Frame::from_normal(n);
                let shift1 = hash_unit(seed, u64::from(p), 1);
                let shift2 = hash_unit(seed, u64::from(p), 2);
                let mut hits: Vec<u32> = (0..rays)
                    .filter_map(|m| {
                        let d = cosine_direction(&frame, m, rays, (shift1, shift2));
                        surface.first_hit(p as usize, &d)
                    })
                    .collect();
                hits.sort_unstable();
                let mut row: Vec<(u32, f32)> = Vec::new();
                for h in hits {
                    match row.last_mut() {
                        Some((t, count)) if *t == h => *count += 1.0,
                        _ => row.push((h, 1.0)),
                    }
                }
                for (_, w) in &mut row {
                    *w /= rays as f32;
                }
                row
            })
            .collect();
        let mut offsets = Vec::with_capacity(pixels.len() + 1);
        let mut targets = Vec::new();
        let mut weights = Vec::new();
        offsets.push(0u32);
        for row in rows {
            for (t, w) in row {
                targets.push(t);
                weights.push(w);
            }
            offsets.push(targets.len() as u32);
        }
        Ok(FormFactors {
            width,
            height,
            rays,
            pixels,
            offsets,
            targets,
            weights,
        })
    }

    /// Image width and height.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Rays per pixel.
    pub fn rays(&self) -> usize {
        self.rays
    }

    /// The surface pixels (row-major image indices), in the order of [`FormFactors::gather`].
    pub fn pixels(&self) -> &[u32] {
        &self.pixels
    }

    /// Σ_j F_ij of each surface pixel: the fraction of its hemisphere filled by the surface.
    pub fn occlusion(&self) -> Vec<f32> {
        self.offsets
            .windows(2)
            .map(|o| self.weights[o[0] as usize..o[1] as usize].iter().sum())
            .collect()
    }

    /// The mean fraction of a pixel's hemisphere that the surface fills (0 for a convex
    /// object or a plane).
    pub fn mean_occlusion(&self) -> f64 {
        if self.pixels.is_empty() {
            0.0
        } else {
            self.weights.iter().map(|&w| f64::from(w)).sum::<f64>() / self.pixels.len() as f64
        }
    }

    /// H_i = Σ_j F_ij·value(j) for every surface pixel, in the order of
    /// [`FormFactors::pixels`]: the irradiance that radiosity `value` (indexed by image pixel)
    /// sends to each pixel.
    pub fn gather(&self, value: impl Fn(usize) -> f32 + Sync) -> Vec<f32> {
        (0..self.pixels.len())
            .into_par_iter()
            .map(|k| self.gather_at(k, &value))
            .collect()
    }

    /// H_i of the `k`-th surface pixel alone (see [`FormFactors::gather`]).
    ///
    /// # Panics
    /// When `k` ≥ the number of surface pixels.
    pub fn gather_at(&self, k: usize, value: impl Fn(usize) -> f32) -> f32 {
        let (a, b) = (self.offsets[k] as usize, self.offsets[k + 1] as usize);
        self.targets[a..b]
            .iter()
            .zip(&self.weights[a..b])
            .map(|(&t, &w)| w * value(t as usize))
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;

    /// A 90° V-groove along the columns, `width` × `height`: height |x − cx| − half_width
    /// inside, 0 outside.
    fn long_groove(width: usize, height: usize, half_width: f64) -> (ScalarMap, NormalMap, Mask) {
        let cx = (width as f64 - 1.0) / 2.0;
        let depth = Grid::from_fn(width, height, |c, _| {
            let u = c as f64 - cx;
            (u.abs() - half_width).min(0.0) as f32
        });
        let normals = Grid::from_fn(width, height, |c, _| {
            let u = c as f64 - cx;
            if u.abs() >= half_width {
                Vector3::new(0.0, 0.0, 1.0)
            } else {
                let s = u.signum() as f32;
                Vector3::new(-s, 0.0, 1.0).normalize()
            }
        });
        (depth, normals, Grid::new(width, height, true))
    }

    fn groove(size: usize, half_width: f64) -> (ScalarMap, NormalMap, Mask) {
        long_groove(size, size, half_width)
    }

    #[test]
    fn a_plane_sees_nothing_of_itself() {
        let depth = Grid::from_fn(48, 40, |c, r| (0.3 * c as f64 - 0.2 * r as f64) as f32);
        let n = Vector3::new(-0.3f32, -0.2, 1.0).normalize();
        let normals = Grid::new(48, 40, n);
        let ff = FormFactors::trace(&depth, &normals, &Grid::new(48, 40, true), 64, 1).unwrap();
        assert_eq!(ff.pixels().len(), 48 * 40);
        assert!(ff.mean_occlusion() < 1e-3, "{}", ff.mean_occlusion());
    }

    /// The form factor from a point of a face of a long 90° V-groove to the opposite face,
    /// by the crossed-strings rule (Hottel): for a point at distance a from the crease on one
    /// face, facing a face of width L at 90°, F = ½(1 − a/√(a² + L²)).
    #[test]
    fn groove_form_factors_match_the_crossed_strings_rule() {
        // Long enough (320 rows) that the rays leaving through the cut ends are negligible
        // at the middle rows.
        let (width, height, half) = (96usize, 320usize, 30.0);
        let (depth, normals, mask) = long_groove(width, height, half);
        let ff = FormFactors::trace(&depth, &normals, &mask, 1024, 7).unwrap();
        let occ = ff.occlusion();
        let cx = (width as f64 - 1.0) / 2.0;
        let face = half * std::f64::consts::SQRT_2;
        let (mut worst, mut n): (f64, usize) = (0.0, 0);
        for (k, &p) in ff.pixels().iter().enumerate() {
            let (c, r) = (p as usize % width, p as usize / width);
            let u = (c as f64 - cx).abs();
            // Middle rows, both faces, away from the crease and the rims by 2 pixels.
            if !(150..170).contains(&r) || !(2.0..=half - 2.0).contains(&u) {
                continue;
            }
            let a = u * std::f64::consts::SQRT_2;
            let expected = 0.5 * (1.0 - a / (a * a + face * face).sqrt());
            worst = worst.max((f64::from(occ[k]) - expected).abs());
            n += 1;
        }
        assert!(n > 500);
        assert!(worst < 0.02, "worst |F − closed form| = {worst}");
    }

    #[test]
    fn gather_weights_the_senders() {
        let (depth, normals, mask) = groove(64, 20.0);
        let ff = FormFactors::trace(&depth, &normals, &mask, 256, 3).unwrap();
        let ones = ff.gather(|_| 1.0);
        for (h, o) in ones.iter().zip(ff.occlusion()) {
            assert!((h - o).abs() < 1e-5);
        }
        assert!(ff.mean_occlusion() > 0.05);
    }

    #[test]
    fn bad_ray_counts_are_refused() {
        let (depth, normals, mask) = groove(8, 2.0);
        assert!(FormFactors::trace(&depth, &normals, &mask, 0, 1).is_err());
        assert!(FormFactors::trace(&depth, &normals, &mask, MAX_RAYS + 1, 1).is_err());
    }
}
