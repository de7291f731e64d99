//! Ray marching over a [`Scene`]'s analytic height field: the cast-shadow test of
//! [`crate::synth::render`] and the first surface point a ray meets, for
//! [`crate::synth::interreflection`].
//!
//! A ray from a surface point (x, y, z) in direction d is parametrised by the distance s
//! travelled by its image-plane projection: (x, y) + s·(d_x, d_y)/|d_xy| at height
//! z + s·d_z/|d_xy|. It is sampled every `step` pixels of s; the surface blocks it where the
//! height exceeds the ray's by more than 10⁻³ pixel. Tiles of 8×8 pixels carry an upper
//! bound of the height ([`crate::synth::scene::Primitive::max_height_over`]), so a rising ray
//! skips every tile it passes above without evaluating the surface. A sampled march can step
//! over an occluder thinner than `step` or misplace an edge by up to one step along the ray:
//! the renderer's geometric resolution.
//!
//! With a refinement depth d > 0, a clear sample where the surface stands above the ray's
//! height one step back (the ray may have passed below a wall's top in between: a wall between
//! two samples is otherwise seen over) is searched by bisection: of the two halves of the step,
//! each is searched (to depth d) where the surface at its far end stands above the ray at its
//! near end. A wall is then found, or cleared, to step/2^d along a single path of d samples;
//! only where the ray grazes the surface does the search branch.
//!
//! The renderer's point lights march every 0.5 pixel unrefined (what every rendering without
//! the new options has always used); the soft shadows of area lights every 0.5 pixel refined to
//! 1/256 ([`crate::synth::area_light`]); the rays of the interreflection gather every pixel
//! refined to 1/64, their hit then located by bisection ([`crate::synth::interreflection`]).

use crate::synth::scene::Scene;
use nalgebra::Vector3;

/// Ray-march step of the point-light cast-shadow test along the light's image-plane direction,
/// in pixels.
pub(crate) const MARCH_STEP: f64 = 0.5;
/// Height tolerance for blocking tests, in pixel units.
pub(crate) const SHADOW_EPS: f64 = 1e-3;
/// Bisection steps that locate a ray's first hit within the interval that crossed
/// (1 px / 2¹⁴ ≈ 6·10⁻⁵ px).
const HIT_BISECTIONS: usize = 14;

/// Upper bounds of the scene's height on a grid of square tiles, so that shadow rays skip the
/// height evaluation wherever they pass above everything in a tile.
pub(crate) struct HeightBounds {
    tile: f64,
    cols: usize,
    rows: usize,
    /// Image-plane origin (x, y) of tile (0, 0).
    x0: f64,
    y0: f64,
    top: Vec<f64>,
    /// Bound over the whole image.
    zmax: f64,
}

impl HeightBounds {
    /// Tile side, in pixels.
    const TILE: f64 = 8.0;

    pub(crate) fn new(scene: &Scene) -> Self {
        let tile = Self::TILE;
        let (hw, hh) = (scene.width as f64 / 2.0, scene.height as f64 / 2.0);
        let cols = (2.0 * hw / tile).ceil() as usize;
        let rows = (2.0 * hh / tile).ceil() as usize;
        let (x0, y0) = (-hw, -hh);
        let mut top = Vec::with_capacity(cols * rows);
        for r in 0..rows {
            for c in 0..cols {
                let (ax, ay) = (x0 + c as f64 * tile, y0 + r as f64 * tile);
                let b = scene
                    .objects
                    .iter()
                    .filter_map(|o| o.shape.max_height_over(ax, ax + tile, ay, ay + tile))
                    .fold(f64::NEG_INFINITY, f64::max);
                top.push(b);
            }
        }
        let zmax = top.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        HeightBounds {
            tile,
            cols,
            rows,
            x0,
            y0,
            top,
            zmax,
        }
    }

    /// An upper bound of the scene's height over the whole image.
    pub(crate) fn zmax(&self) -> f64 {
        self.zmax
    }

    /// The tile containing (x, y) (clamped to the grid): its bound and its rectangle's origin.
    fn tile_at(&self, x: f64, y: f64) -> (f64, f64, f64) {
        // `as usize` saturates negatives (and NaN) to 0.
        let c = (((x - self.x0) / self.tile) as usize).min(self.cols - 1);
        let r = (((y - self.y0) / self.tile) as usize).min(self.rows - 1);
        (
            self.top[r * self.cols + c],
            self.x0 + c as f64 * self.tile,
            self.y0 + r as f64 * self.tile,
        )
    }

    /// Distance along the unit image-plane direction (ux, uy) from (x, y) to the boundary of the
    /// tile with origin (ax, ay).
    fn exit(&self, x: f64, y: f64, ax: f64, ay: f64, ux: f64, uy: f64) -> f64 {
        let along = |p: f64, a: f64, u: f64| {
            if u > 1e-12 {
                (a + self.tile - p) / u
            } else if u < -1e-12 {
                (a - p) / u
            } else {
                f64::INFINITY
            }
        };
        along(x, ax, ux).min(along(y, ay, uy))
    }
}

/// A ray from a surface point, parametrised by the distance s travelled by its image-plane
/// projection.
#[derive(Debug, Clone, Copy)]
struct Ray {
    x: f64,
    y: f64,
    z: f64,
    /// Unit image-plane direction.
    ux: f64,
    uy: f64,
    /// Height gained per pixel of s.
    rise: f64,
}

impl Ray {
    /// The ray from `start` along `d`, or `None` when it is vertical (|d_xy| < 10⁻⁹).
    fn new((x, y, z): (f64, f64, f64), d: &Vector3<f64>) -> Option<Self> {
        let dxy = (d.x * d.x + d.y * d.y).sqrt();
        (dxy >= 1e-9).then(|| Ray {
            x,
            y,
            z,
            ux: d.x / dxy,
            uy: d.y / dxy,
            rise: d.z / dxy,
        })
    }

    /// Whether the surface is above the ray at s.
    fn blocked(&self, scene: &Scene, s: f64) -> bool {
        scene
            .height_at(self.x + self.ux * s, self.y + self.uy * s)
            .is_some_and(|h| h > self.z + s * self.rise + SHADOW_EPS)
    }
}

/// A blocked point inside (lo, hi) of a ray clear at both ends, searched by bisection to
/// `depth` halvings where the surface at an interval's far end stands above the ray at its
/// near end: (the clear sample before it, the blocked one), the earliest found first.
fn crossed(scene: &Scene, ray: &Ray, lo: f64, hi: f64, depth: u32) -> Option<(f64, f64)> {
    if depth == 0 {
        return None;
    }
    let rises_above = scene
        .height_at(ray.x + ray.ux * hi, ray.y + ray.uy * hi)
        .is_some_and(|h| h > ray.z + lo * ray.rise + SHADOW_EPS);
    if !rises_above {
        return None;
    }
    let mid = 0.5 * (lo + hi);
    if ray.blocked(scene, mid) {
        return Some((lo, mid));
    }
    crossed(scene, ray, lo, mid, depth - 1).or_else(|| crossed(scene, ray, mid, hi, depth - 1))
}

/// Marches `ray` over the analytic height function every `step` pixels of s, evaluating it
/// only where the tile bound says the surface could reach the ray, with refinement `depth`
/// (see the module documentation): the first interval (lo, hi) found with the ray clear at lo
/// and blocked at hi, or `None` when the ray leaves the image or rises above every surface
/// first.
fn march(
    scene: &Scene,
    bounds: &HeightBounds,
    ray: &Ray,
    step: f64,
    depth: u32,
) -> Option<(f64, f64)> {
    let &Ray {
        x,
        y,
        z,
        ux,
        uy,
        rise,
    } = ray;
    // Refined, the whole last step must be above everything to stop.
    let margin = if depth > 0 { step * rise.max(0.0) } else { 0.0 };
    let (hw, hh) = (scene.width as f64 / 2.0, scene.height as f64 / 2.0);
    let mut s = step;
    loop {
        let (px, py) = (x + ux * s, y + uy * s);
        if px.abs() > hw || py.abs() > hh {
            return None;
        }
        let ray_z = z + s * rise;
        if ray_z - margin > bounds.zmax {
            return None;
        }
        let (top, ax, ay) = bounds.tile_at(px, py);
        if top <= ray_z + SHADOW_EPS {
            // Clear at s, but the tile may reach above the ray one step back.
            if depth > 0
                && top > z + (s - step) * rise + SHADOW_EPS
                && let Some(found) = crossed(scene, ray, s - step, s, depth)
            {
                return Some(found);
            }
            // The ray rises, so it stays above this tile's surface until it leaves the tile:
            // jump to the tile's edge (on the step grid, so results match plain marching).
            if rise >= 0.0 {
                let leave = s + bounds.exit(px, py, ax, ay, ux, uy);
                s = (leave / step).floor().max(s / step + 1.0) * step;
            } else {
                s += step;
            }
            continue;
        }
        // The sample one step back was clear (marched, skipped above its tile, or the start).
        if let Some(h) = scene.height_at(px, py) {
            if h > ray_z + SHADOW_EPS {
                return Some((s - step, s));
            }
            if depth > 0
                && h > z + (s - step) * rise + SHADOW_EPS
                && let Some(found) = crossed(scene, ray, s - step, s, depth)
            {
                return Some(found);
            }
        }
        s += step;
    }
}

/// Whether the point `start` = (x, y, z) is hidden from a light in direction `l` by the
/// scene's surface: the ray start + t·l marched every `step` pixels of its image-plane
/// projection, with refinement `depth` (0: none).
pub(crate) fn in_cast_shadow(
    scene: &Scene,
    bounds: &HeightBounds,
    start: (f64, f64, f64),
    l: &Vector3<f64>,
    step: f64,
    depth: u32,
) -> bool {
    Ray::new(start, l).is_some_and(|ray| march(scene, bounds, &ray, step, depth).is_some())
}

/// The image-plane point (x, y) where the ray from the surface point `start` in the unit
/// direction `d` first passes below the scene's surface (marched every `step` pixels with
/// refinement `depth`, then located by bisection within the interval that crossed), or `None`
/// when it leaves the image, or rises above every surface, first. A ray straight up
/// (|d_xy| < 10⁻⁹) meets nothing: in a height field nothing lies above a surface point.
pub(crate) fn first_hit(
    scene: &Scene,
    bounds: &HeightBounds,
    start: (f64, f64, f64),
    d: &Vector3<f64>,
    step: f64,
    depth: u32,
) -> Option<(f64, f64)> {
    let ray = Ray::new(start, d)?;
    let (mut lo, mut hi) = march(scene, bounds, &ray, step, depth)?;
    for _ in 0..HIT_BISECTIONS {
        let mid = 0.5 * (lo + hi);
        if ray.blocked(scene, mid) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Some((ray.x + ray.ux * hi, ray.y + ray.uy * hi))
}
