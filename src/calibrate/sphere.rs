//! The calibration sphere's outline in the image: a sub-pixel circle fitted to a mask's edge, or
//! detected in the images when there is no mask.
//!
//! Coordinates are pixel coordinates: `x` the column, `y` the row (downwards), the centre of
//! pixel `(c, r)` at `(c, r)`. Under the orthographic camera of the crate the sphere's normal at
//! `(x, y)` is `((x − cx)/R, −(y − cy)/R, √(1 − …))` in the camera frame (y up).

use crate::camera::Intrinsics;
use crate::error::{Error, Result};
use crate::grid::{Grid, ScalarMap};
use crate::stats::median_by;
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

/// Gauss–Newton iterations of the geometric circle fit (it converges in 3–5 from Kåsa's).
const GEOMETRIC_ITERATIONS: usize = 20;
/// Robust refits: points farther than [`OUTLIER_SIGMAS`] robust σ from the circle are dropped.
pub(crate) const ROBUST_ROUNDS: usize = 4;
/// Outlier cut in robust standard deviations (1.4826 × median absolute residual).
pub(crate) const OUTLIER_SIGMAS: f64 = 3.0;
/// Floor of the outlier cut in pixels (a mask edge is never better than this).
pub(crate) const OUTLIER_FLOOR_PX: f64 = 0.75;
/// A mask's edge points may lie this far (rms, pixels) from its circle, plus 1% of the radius.
pub(crate) const MAX_MASK_RMS_PX: f64 = 1.0;
/// Angular bins used to measure how much of the circumference the edge points cover.
const COVERAGE_BINS: usize = 72;
/// Least fraction of the circumference a detected circle's edge points must cover.
pub const MIN_COVERAGE: f64 = 0.5;
/// Distance (pixels) within which an edge point supports a circle.
const SUPPORT_TOLERANCE_PX: f64 = 1.5;
/// An edge point supports a circle only if its gradient is within this angle of radial
/// (cosine).
const RADIAL_COSINE: f64 = 0.9;
/// Length (pixels) of outline over which a detected circle's edge points share their errors:
/// the 3×3 Sobel stencil makes about three neighbours move together.
pub(crate) const EDGE_CORRELATION_PX: f64 = 3.0;
/// Side (pixels) of the tiles over which the gradient noise is measured.
const NOISE_TILE: usize = 16;
/// Noise-only pixels expected to pass the edge threshold in a whole image.
const FALSE_EDGES: f64 = 10.0;
/// Smallest radius [`detect_circle`] looks for, in pixels.
const MIN_RADIUS_PX: f64 = 8.0;

/// A circle in pixel coordinates (x the column, y the row).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Circle {
    /// Centre column.
    pub cx: f64,
    /// Centre row.
    pub cy: f64,
    /// Radius in pixels.
    pub radius: f64,
}

impl Circle {
    /// The outward sphere normal seen at pixel `(x, y)` under an orthographic camera:
    /// n = ((x − cx)/R, −(y − cy)/R, √(1 − n_x² − n_y²)); `None` outside the circle.
    pub fn normal_at(&self, x: f64, y: f64) -> Option<Vector3<f64>> {
        let nx = (x - self.cx) / self.radius;
        let ny = -(y - self.cy) / self.radius;
        let s = nx * nx + ny * ny;
        (s < 1.0).then(|| Vector3::new(nx, ny, (1.0 - s).sqrt()))
    }

    /// Signed distance of `(x, y)` from the circle (positive outside).
    pub fn distance(&self, x: f64, y: f64) -> f64 {
        (x - self.cx).hypot(y - self.cy) - self.radius
    }
}

/// A circle fitted to edge points, with what the fit says about its own accuracy.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CircleFit {
    /// The circle.
    pub circle: Circle,
    /// Standard errors of (cx, cy, R) in pixels, from the residuals and the fit's Jacobian.
    pub std_err: [f64; 3],
    /// Root-mean-square distance of the kept points from the circle, in pixels.
    pub rms_px: f64,
    /// Edge points kept by the robust fit.
    pub points: usize,
    /// Edge points rejected as outliers (e.g. a stand attached to the sphere's mask).
    pub outliers: usize,
    /// Fraction of the circumference covered by the kept points (1: the whole outline).
    pub coverage: f64,
}

/// Least-squares circle through `points` by the geometric distance Σ(|p − c| − R)², started
/// from Kåsa's algebraic fit (Kåsa 1976) and refined by Gauss–Newton; points farther than
/// 3 robust σ are dropped and the fit repeated.
///
/// # Errors
/// [`Error::InvalidParameter`] (`points`) with fewer than 3 points, or when they are collinear
/// or not finite.
pub fn fit_circle(points: &[[f64; 2]]) -> Result<CircleFit> {
    if points.len() < 3 {
        return Err(Error::param(
            "points",
            format!("{} edge points; a circle needs at least 3", points.len()),
        ));
    }
    if points.iter().flatten().any(|v| !v.is_finite()) {
        return Err(Error::param("points", "an edge point is not finite"));
    }
    let mut kept: Vec<[f64; 2]> = points.to_vec();
    let mut circle = kasa(&kept)?;
    let mut outliers = 0;
    for _ in 0..ROBUST_ROUNDS {
        circle = geometric(&kept, circle);
        let mut abs: Vec<f64> = kept
            .iter()
            .map(|p| circle.distance(p[0], p[1]).abs())
            .collect();
        let sigma = 1.4826 * median_by(&mut abs, f64::total_cmp).unwrap_or(0.0);
        let cut = (OUTLIER_SIGMAS * sigma).max(OUTLIER_FLOOR_PX);
        let before = kept.len();
        let next: Vec<[f64; 2]> = kept
            .iter()
            .copied()
            .filter(|p| circle.distance(p[0], p[1]).abs() <= cut)
            .collect();
        if next.len() == before || next.len() < 3 {
            break;
        }
        outliers += before - next.len();
        kept = next;
    }
    circle = geometric(&kept, circle);
    Ok(summarise(&kept, circle, outliers))
}

/// Standard errors, rms and coverage of `circle` over `points`.
fn summarise(points: &[[f64; 2]], circle: Circle, outliers: usize) -> CircleFit {
    let mut jtj = Matrix3::<f64>::zeros();
    let mut ss = 0.0;
    let mut bins = [false; COVERAGE_BINS];
    for p in points {
        let (dx, dy) = (p[0] - circle.cx, p[1] - circle.cy);
        let d = dx.hypot(dy).max(f64::MIN_POSITIVE);
        let j = Vector3::new(-dx / d, -dy / d, -1.0);
        jtj += j * j.transpose();
        ss += (d - circle.radius).powi(2);
        let a = dy.atan2(dx) + std::f64::consts::PI;
        let bin =
            ((a / std::f64::consts::TAU * COVERAGE_BINS as f64) as usize).min(COVERAGE_BINS - 1);
        bins[bin] = true;
    }
    let n = points.len();
    let dof = n.saturating_sub(3).max(1) as f64;
    let var = ss / dof;
    let cov = jtj
        .try_inverse()
        .unwrap_or_else(|| Matrix3::from_element(f64::INFINITY));
    CircleFit {
        circle,
        std_err: [
            (cov[(0, 0)] * var).sqrt(),
            (cov[(1, 1)] * var).sqrt(),
            (cov[(2, 2)] * var).sqrt(),
        ],
        rms_px: (ss / n as f64).sqrt(),
        points: n,
        outliers,
        coverage: bins.iter().filter(|b| **b).count() as f64 / COVERAGE_BINS as f64,
    }
}

/// Kåsa's fit: x² + y² + D x + E y + F = 0 by linear least squares (centred for conditioning).
fn kasa(points: &[[f64; 2]]) -> Result<Circle> {
    let n = points.len() as f64;
    let (mx, my) = points
        .iter()
        .fold((0.0, 0.0), |(a, b), p| (a + p[0] / n, b + p[1] / n));
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    for p in points {
        let (x, y) = (p[0] - mx, p[1] - my);
        let row = Vector3::new(x, y, 1.0);
        ata += row * row.transpose();
        atb += row * -(x * x + y * y);
    }
    let sol = ata
        .lu()
        .solve(&atb)
        .filter(|s| s.iter().all(|v| v.is_finite()))
        .ok_or_else(|| Error::param("points", "the edge points are collinear"))?;
    let (cx, cy) = (-sol.x / 2.0, -sol.y / 2.0);
    let r2 = cx * cx + cy * cy - sol.z;
    if r2 <= 0.0 || !r2.is_finite() {
        return Err(Error::param("points", "the edge points fit no circle"));
    }
    Ok(Circle {
        cx: cx + mx,
        cy: cy + my,
        radius: r2.sqrt(),
    })
}

/// Gauss–Newton on the geometric distances from `start`.
fn geometric(points: &[[f64; 2]], start: Circle) -> Circle {
    let mut c = start;
    for _ in 0..GEOMETRIC_ITERATIONS {
        let mut jtj = Matrix3::<f64>::zeros();
        let mut jtr = Vector3::<f64>::zeros();
        for p in points {
            let (dx, dy) = (p[0] - c.cx, p[1] - c.cy);
            let d = dx.hypot(dy).max(f64::MIN_POSITIVE);
            let j = Vector3::new(-dx / d, -dy / d, -1.0);
            jtj += j * j.transpose();
            jtr += j * (d - c.radius);
        }
        let Some(step) = jtj.lu().solve(&-jtr) else {
            break;
        };
        if !step.iter().all(|v| v.is_finite()) {
            break;
        }
        c = Circle {
            cx: c.cx + step.x,
            cy: c.cy + step.y,
            radius: (c.radius + step.z).abs(),
        };
        if step.norm() < 1e-9 {
            break;
        }
    }
    c
}

/// A mask's largest finite value (0 for an empty one).
fn mask_max(mask: &ScalarMap) -> f32 {
    mask.data()
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f32, f32::max)
}

/// Sub-pixel edge points of a mask: where the mask crosses half its maximum between two
/// neighbouring pixels (linear interpolation, so an anti-aliased mask gives its true edge and a
/// binary one the midpoints between inside and outside pixels).
pub fn mask_edge_points(mask: &ScalarMap) -> Vec<[f64; 2]> {
    let (w, h) = (mask.width(), mask.height());
    let max = mask_max(mask);
    let level = f64::from(max) / 2.0;
    let value = |x: usize, y: usize| {
        let v = f64::from(*mask.at(x, y));
        if v.is_finite() { v } else { 0.0 }
    };
    let mut points = Vec::new();
    let crossing = |a: f64, b: f64| -> Option<f64> {
        ((a >= level) != (b >= level)).then(|| ((level - a) / (b - a)).clamp(0.0, 1.0))
    };
    for y in 0..h {
        for x in 0..w {
            let v = value(x, y);
            if x + 1 < w
                && let Some(t) = crossing(v, value(x + 1, y))
            {
                points.push([x as f64 + t, y as f64]);
            }
            if y + 1 < h
                && let Some(t) = crossing(v, value(x, y + 1))
            {
                points.push([x as f64, y as f64 + t]);
            }
        }
    }
    points
}

/// The sphere's circle from its mask (pixel values > 0 inside; anti-aliased masks are used at
/// half their maximum): a robust sub-pixel fit to [`mask_edge_points`].
///
/// # Errors
/// [`Error::Mask`] (naming `source`) when the mask has no edge or its edge is not a circle
/// (covers less than [`MIN_COVERAGE`] of one, or its points lie more than 1 px + 1% of the
/// radius from it, rms, or most of them are outliers).
pub fn circle_from_mask(mask: &ScalarMap, source: &std::path::Path) -> Result<CircleFit> {
    let points = mask_edge_points(mask);
    let fit = fit_circle(&points).map_err(|e| Error::Mask {
        path: source.to_path_buf(),
        reason: format!("no circular outline: {e}"),
    })?;
    if fit.coverage < MIN_COVERAGE {
        return Err(Error::Mask {
            path: source.to_path_buf(),
            reason: format!(
                "the outline covers {:.0}% of a circle (at least {:.0}% is needed): is this a sphere's mask?",
                fit.coverage * 100.0,
                MIN_COVERAGE * 100.0
            ),
        });
    }
    // A disc's edge lies within a pixel of its circle (a binary mask's staircase is ±0.5 px);
    // a square's or an ellipse's does not.
    let limit = MAX_MASK_RMS_PX + 0.01 * fit.circle.radius;
    if fit.rms_px > limit || fit.outliers > fit.points {
        return Err(Error::Mask {
            path: source.to_path_buf(),
            reason: format!(
                "its outline is not a circle: the best circle leaves {} of {} edge points out and the rest {:.2} px from it on average (at most {limit:.2} px for a disc)",
                fit.outliers,
                fit.points + fit.outliers,
                fit.rms_px
            ),
        });
    }
    Ok(fit)
}

/// The separate parts of a mask (8-connected regions of pixels at or above half its maximum,
/// of at least 20 pixels), each as a mask of its own that keeps the anti-aliased values around
/// it, largest first: one per ball when a mask outlines two.
pub fn split_mask(mask: &ScalarMap) -> Vec<ScalarMap> {
    let (w, h) = (mask.width(), mask.height());
    let max = mask_max(mask);
    if max <= 0.0 {
        return Vec::new();
    }
    let on = |i: usize| mask.data()[i].is_finite() && mask.data()[i] >= max / 2.0;
    let mut label = vec![usize::MAX; w * h];
    let mut sizes = Vec::new();
    let mut stack = Vec::new();
    for start in 0..w * h {
        if label[start] != usize::MAX || !on(start) {
            continue;
        }
        let id = sizes.len();
        let mut size = 0usize;
        label[start] = id;
        stack.push(start);
        while let Some(i) = stack.pop() {
            size += 1;
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (qx, qy) = (x + dx, y + dy);
                    if qx < 0 || qy < 0 || qx >= w as isize || qy >= h as isize {
                        continue;
                    }
                    let q = qy as usize * w + qx as usize;
                    if label[q] == usize::MAX && on(q) {
                        label[q] = id;
                        stack.push(q);
                    }
                }
            }
        }
        sizes.push(size);
    }
    let mut order: Vec<usize> = (0..sizes.len()).filter(|&k| sizes[k] >= 20).collect();
    order.sort_by(|a, b| sizes[*b].cmp(&sizes[*a]));
    order
        .into_iter()
        .map(|id| {
            // A pixel belongs to the part when it or a neighbour within two pixels does (its
            // anti-aliased rim lies below half level).
            Grid::from_fn(w, h, |x, y| {
                let near = (y.saturating_sub(2)..(y + 3).min(h)).any(|qy| {
                    (x.saturating_sub(2)..(x + 3).min(w)).any(|qx| label[qy * w + qx] == id)
                });
                if near { *mask.at(x, y) } else { 0.0 }
            })
        })
        .collect()
}

/// An edge point of an image: sub-pixel position and unit gradient direction.
#[derive(Debug, Clone, Copy)]
struct Edge {
    x: f64,
    y: f64,
    gx: f64,
    gy: f64,
}

/// A circle found in an image, with how well the image supports it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Candidate {
    /// The circle fitted to its supporting edge points.
    pub fit: CircleFit,
    /// Fraction of the circumference inside the image (1: the whole circle is in the frame).
    pub in_frame: f64,
    /// Fraction of the in-frame circumference covered by supporting edge points.
    pub support: f64,
}

/// Circles in `evidence` (an image in which the sphere's outline shows, e.g. the median of the
/// calibration images), best supported first: up to `max` of them, each of radius ≥ 8 px with
/// supporting edge points over at least half its in-frame circumference.
///
/// Edge points are Sobel gradient maxima along the gradient direction, located to sub-pixel by
/// a parabola, whose magnitude is beyond what noise reaches: above √(2 ln(N/10)) robust
/// standard deviations of the gradient components (1.4826 × their median absolute value), the
/// level that N pixels of pure noise pass about ten times. Circles are sought by the gradient
/// Hough transform (Kimme, Ballard & Sklansky 1975): each edge point votes for centres along its
/// gradient line on both sides (a ball may be brighter or darker than its background); at each
/// strong centre the distances of the edge points whose gradient is radial give the radius.
/// Each candidate is then refined by [`fit_circle`] on its support (the edge points within
/// 1.5 px whose gradient is within 26° of radial), twice. The candidate's standard errors
/// allow for correlated edge points and a deformed outline: they are the larger of the fit's
/// (for points correlated over three pixels) and a block jackknife's over eight sectors of
/// the outline, combined with a 0.07 px floor for the shift of a whole mirror-ball outline
/// that neither shows.
///
/// With a pinhole `camera`, a ball θ off the optical axis images as an ellipse whose axes
/// differ by about R(1/cos θ − 1) ([`super::perspective`]); the support tolerances are widened
/// by that much, so that the circle is found, and the ellipse is then fitted as a cone of rays.
pub fn detect_circles(
    evidence: &ScalarMap,
    max: usize,
    camera: Option<&Intrinsics>,
) -> Vec<Candidate> {
    let edges = edge_points(evidence);
    let (w, h) = (evidence.width(), evidence.height());
    if edges.len() < 3 || max == 0 {
        return Vec::new();
    }
    let max_radius = 0.75 * w.max(h) as f64;
    // Centre votes, on the image grid.
    let mut acc = vec![0.0f32; w * h];
    for e in &edges {
        for side in [-1.0, 1.0] {
            let mut t = MIN_RADIUS_PX;
            while t <= max_radius {
                let (x, y) = (e.x + side * t * e.gx, e.y + side * t * e.gy);
                if x < -0.5 || y < -0.5 || x >= w as f64 - 0.5 || y >= h as f64 - 0.5 {
                    break;
                }
                acc[(y.round() as usize) * w + x.round() as usize] += 1.0;
                t += 1.0;
            }
        }
    }
    let smooth = box3(&acc, w, h);
    // Local maxima (5×5), strongest first.
    let mut peaks: Vec<(f32, usize, usize)> = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let v = smooth[y * w + x];
            if v < 3.0 {
                continue;
            }
            let mut top = true;
            'n: for dy in -2isize..=2 {
                for dx in -2isize..=2 {
                    let (qx, qy) = (x as isize + dx, y as isize + dy);
                    if (dx, dy) == (0, 0)
                        || qx < 0
                        || qy < 0
                        || qx >= w as isize
                        || qy >= h as isize
                    {
                        continue;
                    }
                    let q = smooth[qy as usize * w + qx as usize];
                    if q > v || (q == v && (dy, dx) < (0, 0)) {
                        top = false;
                        break 'n;
                    }
                }
            }
            if top {
                peaks.push((v, x, y));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0));
    peaks.truncate(4 * max.max(4));
    let mut found: Vec<Candidate> = Vec::new();
    for &(_, px, py) in &peaks {
        for radius in radius_peaks(&edges, px as f64, py as f64, max_radius, w, h) {
            let start = Circle {
                cx: px as f64,
                cy: py as f64,
                radius,
            };
            let Some(c) = refine(&edges, start, max_radius, w, h, camera) else {
                continue;
            };
            let same = |o: &Candidate| {
                (o.fit.circle.cx - c.fit.circle.cx).hypot(o.fit.circle.cy - c.fit.circle.cy) < 2.0
                    && (o.fit.circle.radius - c.fit.circle.radius).abs() < 2.0
            };
            if c.support >= MIN_COVERAGE && c.in_frame >= MIN_COVERAGE && !found.iter().any(same) {
                found.push(c);
            }
        }
    }
    found.sort_by(|a, b| {
        (b.support * b.in_frame)
            .total_cmp(&(a.support * a.in_frame))
            .then(b.fit.points.cmp(&a.fit.points))
    });
    found.truncate(max);
    found
}

/// The best circle of [`detect_circles`].
///
/// # Errors
/// [`Error::SphereNotFound`] when there is none.
pub fn detect_circle(evidence: &ScalarMap) -> Result<CircleFit> {
    detect_circles(evidence, 1, None)
        .first()
        .map(|c| c.fit)
        .ok_or_else(|| Error::SphereNotFound {
            reason: "no circle of radius ≥ 8 px has edges over half its outline".into(),
        })
}

/// 3×3 box filter (edges clamped).
fn box3(v: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for qy in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                for qx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                    s += v[qy * w + qx];
                }
            }
            out[y * w + x] = s;
        }
    }
    out
}

/// Radii at which the edge points with radial gradients about (cx, cy) cluster: peaks of their
/// distance histogram holding at least a third of the in-frame circumference (up to two).
fn radius_peaks(edges: &[Edge], cx: f64, cy: f64, max_radius: f64, w: usize, h: usize) -> Vec<f64> {
    let bins = max_radius.ceil() as usize + 2;
    let mut hist = vec![0.0f64; bins];
    let centre = Circle {
        cx,
        cy,
        radius: 1.0,
    };
    for e in edges {
        let d = (e.x - cx).hypot(e.y - cy);
        // A loose radial test: the centre is only known to a pixel or two.
        if d >= MIN_RADIUS_PX && d < max_radius && radial_cos(e, &centre) >= 0.8 {
            hist[d.round() as usize] += 1.0;
        }
    }
    let smooth: Vec<f64> = (0..bins)
        .map(|i| {
            let at = |j: isize| {
                if j < 0 || j as usize >= bins {
                    0.0
                } else {
                    hist[j as usize]
                }
            };
            at(i as isize - 1) + at(i as isize) + at(i as isize + 1)
        })
        .collect();
    let mut out: Vec<(f64, f64)> = Vec::new();
    for r in (MIN_RADIUS_PX as usize + 1)..bins.saturating_sub(1) {
        let v = smooth[r];
        if v <= smooth[r - 1] || v < smooth[r + 1] {
            continue;
        }
        let circle = Circle {
            cx,
            cy,
            radius: r as f64,
        };
        let visible = in_frame_fraction(&circle, w, h) * std::f64::consts::TAU * r as f64;
        if v >= visible / 3.0 && visible > 0.0 {
            out.push((v / visible, r as f64));
        }
    }
    out.sort_by(|a, b| b.0.total_cmp(&a.0));
    out.into_iter().take(2).map(|(_, r)| r).collect()
}

/// Standard error (pixels) of each parameter of a detected mirror ball's outline that no fit
/// statistic shows: the environment reflected at the rim moves the edge of one side in and of
/// the other out, a shift of the whole circle. On rendered balls whose environment is brighter
/// above by up to 0.3 of its level (`tests/chrome_captures.rs`' generator, seeds 1000–1099, not
/// those the test checks), the centre moved by 0.066 px rms along the gradient.
pub(crate) const OUTLINE_FLOOR_PX: f64 = 0.07;

/// Sectors of the block jackknife of a detected circle.
pub(crate) const JACKKNIFE_SECTORS: usize = 8;

/// Block-jackknife standard errors of (cx, cy, R) from `points` about `circle`: the geometric
/// fit without each of [`JACKKNIFE_SECTORS`] angular sectors in turn, var = (n − 1)/n Σ(θᵢ − θ̄)²
/// over the n sectors holding points (Efron & Stein 1981; Künsch 1989 for blocks).
fn sector_jackknife(points: &[[f64; 2]], circle: Circle) -> [f64; 3] {
    let sector = |p: &[f64; 2]| {
        let a = (p[1] - circle.cy)
            .atan2(p[0] - circle.cx)
            .rem_euclid(std::f64::consts::TAU);
        ((a / std::f64::consts::TAU * JACKKNIFE_SECTORS as f64) as usize).min(JACKKNIFE_SECTORS - 1)
    };
    let mut fits: Vec<[f64; 3]> = Vec::new();
    for s in 0..JACKKNIFE_SECTORS {
        let rest: Vec<[f64; 2]> = points.iter().copied().filter(|p| sector(p) != s).collect();
        if rest.len() == points.len() || rest.len() < 3 {
            continue;
        }
        let c = geometric(&rest, circle);
        fits.push([c.cx, c.cy, c.radius]);
    }
    jackknife_spread(&fits)
}

/// Jackknife standard errors of three parameters from their leave-one-block-out fits:
/// √((n − 1)/n Σ(θᵢ − θ̄)²) each, 0 with fewer than two fits.
pub(crate) fn jackknife_spread(fits: &[[f64; 3]]) -> [f64; 3] {
    let n = fits.len();
    if n < 2 {
        return [0.0; 3];
    }
    let mut out = [0.0; 3];
    for (k, o) in out.iter_mut().enumerate() {
        let mean = fits.iter().map(|f| f[k]).sum::<f64>() / n as f64;
        let ss: f64 = fits.iter().map(|f| (f[k] - mean).powi(2)).sum();
        *o = ((n - 1) as f64 / n as f64 * ss).sqrt();
    }
    out
}

/// Fraction of the circle's circumference inside the image (more than a pixel from its border).
pub fn in_frame_fraction(c: &Circle, w: usize, h: usize) -> f64 {
    let inside = (0..COVERAGE_BINS)
        .filter(|&b| {
            let a = (b as f64 + 0.5) / COVERAGE_BINS as f64 * std::f64::consts::TAU;
            let (x, y) = (c.cx + c.radius * a.cos(), c.cy + c.radius * a.sin());
            x >= 1.0 && y >= 1.0 && x <= w as f64 - 2.0 && y <= h as f64 - 2.0
        })
        .count();
    inside as f64 / COVERAGE_BINS as f64
}

/// Refits `start` to its supporting edge points, twice; `None` if it has too few.
fn refine(
    edges: &[Edge],
    start: Circle,
    max_radius: f64,
    w: usize,
    h: usize,
    camera: Option<&Intrinsics>,
) -> Option<Candidate> {
    let mut c = start;
    let mut fit = None;
    let mut points = Vec::new();
    for tolerance in [2.5, SUPPORT_TOLERANCE_PX, SUPPORT_TOLERANCE_PX] {
        let tolerance = tolerance + ellipse_excess(&c, camera);
        points = edges
            .iter()
            .filter(|e| {
                c.distance(e.x, e.y).abs() <= tolerance && radial_cos(e, &c) >= RADIAL_COSINE
            })
            .map(|e| [e.x, e.y])
            .collect();
        let f = fit_circle(&points).ok()?;
        if !(MIN_RADIUS_PX..=max_radius).contains(&f.circle.radius) {
            return None;
        }
        c = f.circle;
        fit = Some(f);
    }
    let mut fit = fit?;
    // The fit's standard errors assume independent edge points, but neighbouring ones share
    // the gradient stencil, and a ball's outline is never exactly a circle of
    // uniform contrast: a mirror ball's rim reflects the grazing environment, whose gradient
    // pulls the edge in on one side and out on another, which moves the centre. A block
    // jackknife over sectors of the outline measures both (each sector's points leave the fit
    // in turn; the spread of the fits is the error that errors shared within sectors make).
    // A shift of the whole outline deforms nothing, so neither sees it: that part is the floor
    // measured on rendered balls ([`OUTLINE_FLOOR_PX`]).
    let jack = sector_jackknife(&points, fit.circle);
    for (se, j) in fit.std_err.iter_mut().zip(jack) {
        *se = (EDGE_CORRELATION_PX.sqrt() * *se)
            .max(j)
            .hypot(OUTLINE_FLOOR_PX);
    }
    let c = fit.circle;
    // Support on one-pixel arcs of the circumference: the arcs inside the frame, and those
    // of them holding a supporting edge point.
    let arcs = (std::f64::consts::TAU * c.radius).ceil().max(8.0) as usize;
    let mut held = vec![false; arcs];
    let tolerance = SUPPORT_TOLERANCE_PX + ellipse_excess(&c, camera);
    for e in edges {
        if c.distance(e.x, e.y).abs() <= tolerance && radial_cos(e, &c) >= RADIAL_COSINE {
            let a = (e.y - c.cy)
                .atan2(e.x - c.cx)
                .rem_euclid(std::f64::consts::TAU);
            held[((a / std::f64::consts::TAU * arcs as f64) as usize).min(arcs - 1)] = true;
        }
    }
    let mut visible = 0usize;
    let mut supported = 0usize;
    for (b, held) in held.iter().enumerate() {
        let a = (b as f64 + 0.5) / arcs as f64 * std::f64::consts::TAU;
        let (x, y) = (c.cx + c.radius * a.cos(), c.cy + c.radius * a.sin());
        // Edge points are found two pixels or more from the border.
        if x >= 2.0 && y >= 2.0 && x <= w as f64 - 3.0 && y <= h as f64 - 3.0 {
            visible += 1;
            supported += usize::from(*held);
        }
    }
    Some(Candidate {
        fit,
        in_frame: visible as f64 / arcs as f64,
        support: supported as f64 / visible.max(1) as f64,
    })
}

/// The edge points of `evidence` (as [`detect_circles`] finds them) within `band` pixels of
/// `circle` whose gradient is within 26° of radial: the outline's points, for a fit of another
/// model of it (a sphere's cone of rays under a pinhole camera, whose image is an ellipse).
pub fn outline_points(evidence: &ScalarMap, circle: &Circle, band: f64) -> Vec<[f64; 2]> {
    edge_points(evidence)
        .iter()
        .filter(|e| {
            circle.distance(e.x, e.y).abs() <= band && radial_cos(e, circle) >= RADIAL_COSINE
        })
        .map(|e| [e.x, e.y])
        .collect()
}

/// How far (pixels) the image of a ball whose outline is about `c` departs from a circle
/// under `camera`: the difference of its ellipse's axes, R(1/cos θ − 1) at θ off the optical
/// axis (0 orthographic).
pub(crate) fn ellipse_excess(c: &Circle, camera: Option<&Intrinsics>) -> f64 {
    camera.map_or(0.0, |k| {
        let (x, y) = ((c.cx - k.cx) / k.fx, (c.cy - k.cy) / k.fy);
        c.radius * ((1.0 + x * x + y * y).sqrt() - 1.0)
    })
}

fn radial_cos(e: &Edge, c: &Circle) -> f64 {
    let (dx, dy) = (e.x - c.cx, e.y - c.cy);
    let d = dx.hypot(dy).max(f64::MIN_POSITIVE);
    ((dx * e.gx + dy * e.gy) / d).abs()
}

/// Edge points: Sobel gradient maxima along the gradient direction, above the noise level
/// (see [`detect_circles`]), located to sub-pixel by a parabola.
fn edge_points(img: &ScalarMap) -> Vec<Edge> {
    let (w, h) = (img.width(), img.height());
    if w < 3 || h < 3 {
        return Vec::new();
    }
    let smooth: Vec<f32> = img
        .data()
        .iter()
        .map(|v| if v.is_finite() { *v } else { 0.0 })
        .collect();
    let v = |x: usize, y: usize| smooth[y * w + x];
    let mut gx = vec![0.0f32; w * h];
    let mut gy = vec![0.0f32; w * h];
    let mut mag = vec![0.0f32; w * h];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let sx = (v(x + 1, y - 1) + 2.0 * v(x + 1, y) + v(x + 1, y + 1))
                - (v(x - 1, y - 1) + 2.0 * v(x - 1, y) + v(x - 1, y + 1));
            let sy = (v(x - 1, y + 1) + 2.0 * v(x, y + 1) + v(x + 1, y + 1))
                - (v(x - 1, y - 1) + 2.0 * v(x, y - 1) + v(x + 1, y - 1));
            let i = y * w + x;
            gx[i] = sx;
            gy[i] = sy;
            mag[i] = sx.hypot(sy);
        }
    }
    // Gradient components of pure noise are normal with one σ; most pixels of a tile are flat,
    // so the median absolute component measures it there (tile by tile: the noise of a bright
    // ball is not that of a dark or clipped background). The magnitude of noise exceeds kσ
    // with probability exp(−k²/2): k = √(2 ln(N / FALSE_EDGES)) lets about FALSE_EDGES
    // through in the whole image.
    let peak = mag.iter().copied().fold(0.0f32, f32::max);
    if peak <= 0.0 {
        return Vec::new();
    }
    let k = (2.0 * ((w * h) as f64 / FALSE_EDGES).max(1.0).ln()).sqrt() as f32;
    let (tw, th) = (w.div_ceil(NOISE_TILE), h.div_ceil(NOISE_TILE));
    let mut tile_threshold = vec![0.0f32; tw * th];
    let mut comps: Vec<f32> = Vec::with_capacity(2 * NOISE_TILE * NOISE_TILE);
    for ty in 0..th {
        for tx in 0..tw {
            comps.clear();
            for y in (ty * NOISE_TILE).max(1)..((ty + 1) * NOISE_TILE).min(h - 1) {
                for x in (tx * NOISE_TILE).max(1)..((tx + 1) * NOISE_TILE).min(w - 1) {
                    comps.push(gx[y * w + x].abs());
                    comps.push(gy[y * w + x].abs());
                }
            }
            let sigma = 1.4826 * median_by(&mut comps, f32::total_cmp).unwrap_or(0.0);
            // A noise-free image still has rounding: nothing below a millionth of the
            // strongest edge.
            tile_threshold[ty * tw + tx] = (k * sigma).max(1e-6 * peak);
        }
    }
    let threshold_at = |x: usize, y: usize| tile_threshold[(y / NOISE_TILE) * tw + x / NOISE_TILE];
    let mut edges = Vec::new();
    for y in 2..h - 2 {
        for x in 2..w - 2 {
            let i = y * w + x;
            let m = mag[i];
            if m <= threshold_at(x, y) {
                continue;
            }
            let (ux, uy) = (f64::from(gx[i] / m), f64::from(gy[i] / m));
            // Step to the neighbour nearest the gradient direction.
            let (sx, sy) = (ux.round() as isize, uy.round() as isize);
            let at = |dx: isize, dy: isize| {
                mag[(y as isize + dy) as usize * w + (x as isize + dx) as usize]
            };
            let (a, b) = (at(-sx, -sy), at(sx, sy));
            if m < a || m <= b {
                continue;
            }
            let denom = f64::from(a) - 2.0 * f64::from(m) + f64::from(b);
            let t = if denom < 0.0 {
                (0.5 * f64::from(a - b) / denom).clamp(-0.5, 0.5)
            } else {
                0.0
            };
            edges.push(Edge {
                x: x as f64 + t * sx as f64,
                y: y as f64 + t * sy as f64,
                gx: ux,
                gy: uy,
            });
        }
    }
    edges
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;

    fn disc(w: usize, h: usize, c: Circle, samples: usize) -> ScalarMap {
        // Area coverage by supersampling: an anti-aliased disc.
        Grid::from_fn(w, h, |x, y| {
            let mut inside = 0;
            for i in 0..samples {
                for j in 0..samples {
                    let px = x as f64 - 0.5 + (i as f64 + 0.5) / samples as f64;
                    let py = y as f64 - 0.5 + (j as f64 + 0.5) / samples as f64;
                    if c.distance(px, py) < 0.0 {
                        inside += 1;
                    }
                }
            }
            inside as f32 / (samples * samples) as f32
        })
    }

    #[test]
    fn fit_recovers_exact_circle_points() {
        let c = Circle {
            cx: 40.3,
            cy: -12.7,
            radius: 55.5,
        };
        let pts: Vec<[f64; 2]> = (0..40)
            .map(|k| {
                let a = k as f64 * 0.11;
                [c.cx + c.radius * a.cos(), c.cy + c.radius * a.sin()]
            })
            .collect();
        let f = fit_circle(&pts).unwrap();
        assert!((f.circle.cx - c.cx).abs() < 1e-8);
        assert!((f.circle.cy - c.cy).abs() < 1e-8);
        assert!((f.circle.radius - c.radius).abs() < 1e-8);
        assert!(f.rms_px < 1e-8);
    }

    #[test]
    fn robust_fit_ignores_a_stand_below_the_sphere() {
        let c = Circle {
            cx: 60.0,
            cy: 50.0,
            radius: 30.0,
        };
        // Binary mask of a sphere on a stand (a bar below it).
        let mask = Grid::from_fn(120, 110, |x, y| {
            let (xf, yf) = (x as f64, y as f64);
            let bar = (55.0..=65.0).contains(&xf) && yf > 70.0;
            f32::from(u8::from(c.distance(xf, yf) < 0.0 || bar))
        });
        let f = circle_from_mask(&mask, std::path::Path::new("m.png")).unwrap();
        assert!(f.outliers > 10, "{f:?}");
        assert!((f.circle.cx - c.cx).abs() < 0.1, "{f:?}");
        assert!((f.circle.cy - c.cy).abs() < 0.1, "{f:?}");
        assert!((f.circle.radius - c.radius).abs() < 0.1, "{f:?}");
    }

    #[test]
    fn anti_aliased_and_binary_masks_give_sub_pixel_circles() {
        let c = Circle {
            cx: 70.37,
            cy: 64.81,
            radius: 41.23,
        };
        for samples in [1, 8] {
            let f =
                circle_from_mask(&disc(150, 140, c, samples), std::path::Path::new("m")).unwrap();
            let err = (f.circle.cx - c.cx)
                .abs()
                .max((f.circle.cy - c.cy).abs())
                .max((f.circle.radius - c.radius).abs());
            assert!(err < 0.05, "samples {samples}: {f:?}");
            assert!(f.coverage > 0.99);
        }
    }

    #[test]
    fn detection_finds_a_faint_disc_among_clutter() {
        let c = Circle {
            cx: 81.6,
            cy: 70.2,
            radius: 47.9,
        };
        let d = disc(180, 150, c, 4);
        // A faint disc, a brighter square elsewhere, a gradient background.
        let img = Grid::from_fn(180, 150, |x, y| {
            let sq = (5..30).contains(&x) && (100..140).contains(&y);
            0.2 * *d.at(x, y) + if sq { 0.5 } else { 0.0 } + 0.0005 * x as f32
        });
        let f = detect_circle(&img).unwrap();
        let err = (f.circle.cx - c.cx)
            .abs()
            .max((f.circle.cy - c.cy).abs())
            .max((f.circle.radius - c.radius).abs());
        assert!(err < 0.2, "{f:?}");
        assert!(detect_circle(&Grid::new(50, 40, 0.3)).is_err());
    }

    #[test]
    fn too_few_or_collinear_points_are_errors() {
        assert!(fit_circle(&[[0.0, 0.0], [1.0, 1.0]]).is_err());
        assert!(fit_circle(&[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]).is_err());
        assert!(fit_circle(&[[0.0, 0.0], [1.0, f64::NAN], [2.0, 2.0]]).is_err());
    }
}
