//! Variational refinement of the perspective solution: the depth that best explains the whole
//! image, found by damped Gauss–Newton from the viscosity solution.
//!
//! # Why
//! The sweeps of [`super::solve`] solve the image equation pixel by pixel along its
//! characteristics, to first order. Where the light is off the camera's axis, two things limit
//! them: where the light grazes the surface the equation is not coercive and its solution
//! depends only on what flows in from the lit side, so a cast shadow or an occluding contour
//! upstream cuts it off; and shadows and pixels with no root get their depth only by
//! interpolation. Yet the image still constrains every lit pixel, whichever way its
//! characteristics run. This step minimises, over ln Z on every pixel of the mask,
//!
//! E(z) = Σ_cells (F(cos θ_c)/F(1) − I_c d_c²/(Φ F(1)))² + λ Σ_pixels f²(Δ²z)²,
//!
//! a least-squares fit of the image (the shape-from-shading energy of Horn & Brooks, *Shape
//! from Shading*, MIT Press 1989, chapter 5, written on the depth itself so that the surface is
//! integrable by construction, as in Szeliski, "Fast shape from shading", CVGIP 1991) plus a
//! small penalty on the second differences of ln Z (in units of the focal length f, so that it
//! is the change of slope from one pixel to the next).
//!
//! # Discretisation
//! Each 2×2 block of pixels (a cell) whose four corners are lit gives one residual: its normal
//! is the cross product of the mean differences of the four back-projected points across and
//! down the cell, its point their centroid, its brightness the mean of the four pixels. Both
//! are second-order accurate at the cell's centre, where the first-order upwind scheme is not,
//! and a cell's normal can be as steep as the points make it (the occluding contour is fitted,
//! not extrapolated). The residual is relative to the brightness of a surface facing the light
//! at the cell's distance, a cos θ for a Lambertian surface, so that λ does not depend on the
//! albedo, the light's intensity or the units. Cells with a corner in shadow carry no residual:
//! there the depth is the one of least curvature that joins the lit surface around it. The
//! second differences also remove the checkerboard that the cells' mean differences cannot see.
//!
//! # Solve
//! Gauss–Newton with a line search: each step solves (JᵀJ + λLᵀL)δ = −∇E/2 (its diagonal
//! raised by 10⁻⁶ of itself) by a sparse Cholesky factorisation (`faer`, nested dissection
//! ordering analysed once; factorised in single precision, refined in double:
//! `integrate::sparse::MixedCholesky`), with the cells' Jacobian by central differences (so any reflectance
//! the model holds can be fitted), and searches the length along δ by quadratic interpolation
//! of E (backtracking while E has not fallen, and one shorter length when the parabola puts the
//! minimum well short of a full step). It stops when a step lowers E by less than the tolerance
//! relative to E, when no step lowers it, or at the iteration limit, which the report says. The
//! factor's memory (about 10⁷ values at 65 000 unknowns) is allocated once for all the steps.
//!
//! # Coarse to fine
//! The steps crawl where the surface must move far and smoothly from its start: each lowers E
//! by a few thousandths, and each step differs from its own half-resolution interpolation by
//! about 1% of its norm (peaks at 256², light 30° off). A start swept at this resolution is
//! therefore first moved by its own refinement at half resolution (`refine_from_half`: block
//! means of the start and of the image, the focal lengths halved; the change interpolated back
//! and added, so the start keeps its detail), where such steps cost several times less, when
//! that level keeps at least 3 000 pixels (`MIN_HALF_PIXELS`). (A large mask is already swept
//! and refined at half resolution and upsampled: see [`super::solve`].) On the frame-filling
//! rendered shapes this takes a half to two thirds of the full-resolution steps away at the
//! same error.
//!
//! # Assumptions and failure modes
//! - A local method: it finds the minimum nearest its start, so it inherits the start's
//!   branch (the viscosity solution's), and refines rather than replaces it.
//! - λ trades fidelity against smoothness: larger smooths creases, smaller lets noise and the
//!   checkerboard through. The default was chosen on rendered shapes (see
//!   [`DEFAULT_SMOOTHNESS`]).
//! - A shadowed region's depth is a smooth continuation: a bump wholly inside a shadow is not
//!   recovered.
//! - The energy can have a lower valley far from the start: on the rendered relief under a light
//!   30° off the axis (azimuths 120° and 300°) a surface 30–40% nearer the camera as a whole
//!   explains the image with a fifth of the energy. Steps that move the whole surface by more
//!   than [`MAX_SHIFT`] in ln Z are therefore discarded ([`refine`]); a slower drift is not
//!   caught (the same relief at 96², azimuth 300°: 4.6° swept, 8.4° refined).

use crate::error::{Error, Result};
use crate::integrate::sparse::{MixedCholesky, nested_dissection_of, symbolic_cholesky};
use faer::Par;
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

use super::Model;
use crate::sfs::line_search;
use crate::sfs::pyramid::Transfer;

/// Default weight λ of the curvature penalty. Chosen on the rendered shapes of `photostereo
/// bench sfs` (sphere, vase, peaks, relief, bust; 128², the light at the camera and 30° off the
/// axis, clean and with 0.8% noise), over 0.001–0.03: smaller fits clean images better, larger
/// resists noise better; across 0.003–0.03 the normals move by 0.3–1.5°, and 0.01 is the middle
/// of that range in a log scale. Fixed rather than grown with the image's noise: swept against
/// 0–4% noise, 0.01 is the best fixed weight from 2% on, and larger weights, which the frontal
/// scenes prefer under noise, send oblique ones to another branch (docs/shape-from-shading.md,
/// "Smoothness against image noise").
pub const DEFAULT_SMOOTHNESS: f64 = 0.01;
/// Default limit of Gauss–Newton steps (one factorisation each).
pub const DEFAULT_MAX_ITERATIONS: usize = 100;
/// Default relative decrease of the energy below which a kept step ends the refinement.
pub const DEFAULT_TOLERANCE: f64 = 1e-3;
/// The largest mean change of ln Z that the steps at one resolution may make, about 5% of the
/// distance: a refinement that moves the surface further as a whole has left its start (see
/// [`refine`]). Chosen on the rendered shapes of `photostereo bench sfs` (five shapes, 128²,
/// the light at the camera and 20° and 30° off the axis at five azimuths): the refinements that
/// improve on their start move it by at most 0.014 (1.4%); the two that ran away (the relief,
/// 30° off at azimuths 120° and 300°, at its 64² level) by 0.44 and 0.47 at their limit of 100
/// steps.
pub const MAX_SHIFT: f64 = 0.05;
/// Step in ln Z of the central differences of a cell's residual.
const STEP: f64 = 1e-6;

/// Options of the refinement.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RefineOptions {
    /// Weight λ of the curvature penalty (0: none; [`DEFAULT_SMOOTHNESS`] by default).
    pub smoothness: f64,
    /// Limit of steps at each resolution ([`DEFAULT_MAX_ITERATIONS`]; the half-resolution
    /// refinements that make the start have their own).
    pub max_iterations: usize,
    /// Relative decrease of the energy below which a kept step ends it ([`DEFAULT_TOLERANCE`]).
    pub tolerance: f64,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            smoothness: DEFAULT_SMOOTHNESS,
            max_iterations: DEFAULT_MAX_ITERATIONS,
            tolerance: DEFAULT_TOLERANCE,
        }
    }
}

impl RefineOptions {
    /// Checks the options.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] naming `smoothness`, `refine iterations` or `refine
    /// tolerance`.
    pub fn validate(&self) -> Result<()> {
        if !(self.smoothness.is_finite() && self.smoothness >= 0.0) {
            return Err(Error::param(
                "smoothness",
                format!("{} must be finite and ≥ 0", self.smoothness),
            ));
        }
        if self.max_iterations == 0 {
            return Err(Error::param("refine iterations", "must be at least 1"));
        }
        if !(self.tolerance.is_finite() && self.tolerance > 0.0 && self.tolerance < 1.0) {
            return Err(Error::param(
                "refine tolerance",
                format!("{} must be in (0, 1)", self.tolerance),
            ));
        }
        Ok(())
    }
}

/// What the refinement did.
#[non_exhaustive]
#[derive(Debug, Clone, Serialize)]
pub struct RefineReport {
    /// Steps solved at full resolution (kept or not).
    pub iterations: usize,
    /// Steps solved at lower resolutions to make the start: the refinement of the
    /// half-resolution image (recursively) that produced an upsampled start, or that moved a
    /// start swept at this resolution; 0 when there was none.
    pub coarse_iterations: usize,
    /// Whether it stopped because the energy stopped falling (not at the limit, and not
    /// discarded).
    pub converged: bool,
    /// The mean change of ln Z that the full-resolution steps made (the surface moved as a
    /// whole by the factor e^shift), up to where they stopped.
    pub shift: f64,
    /// Whether the steps were discarded because they moved the surface as a whole by more than
    /// [`MAX_SHIFT`]: the depth is then their start.
    pub discarded: bool,
    /// Energy at the start of the full-resolution steps (the swept solution, moved by its
    /// half-resolution refinement when it had one, or the upsampled half-resolution result).
    pub energy_start: f64,
    /// Energy at the end.
    pub energy_end: f64,
    /// Root-mean-square relative residual of the lit cells at the end.
    pub rms_residual: f64,
    /// Cells (2×2 blocks of lit pixels) fitted.
    pub cells: usize,
    /// The curvature weight used.
    pub smoothness: f64,
    /// Seconds spent at full resolution (the steps at lower resolutions are in the solve's
    /// time, not here).
    pub seconds: f64,
}

/// One pixel of the refinement: normalised coordinates (internal frame, y down) and brightness.
#[derive(Clone, Copy)]
pub(super) struct Site {
    /// Normalised image coordinates.
    pub xi: f64,
    /// Normalised image coordinates (down).
    pub eta: f64,
    /// Brightness.
    pub i: f64,
    /// Whether the pixel is lit (above the shadow level).
    pub lit: bool,
}

/// A 2×2 block of lit pixels: its corners (top left, top right, bottom left, bottom right).
struct Cell {
    corners: [usize; 4],
    /// Mean brightness of the corners.
    i: f64,
    /// Position in the normal equations' values of each pair of corners (a, b) with
    /// corners[a] ≥ corners[b] (unused otherwise).
    slots: [[usize; 4]; 4],
}

/// A second difference along one axis: its three unknowns, their positions in the normal
/// equations' values (lower triangle), and the focal length that scales it.
struct Second {
    at: [usize; 3],
    slots: [[usize; 3]; 3],
    f: f64,
}

/// The refinement problem on a set of unknowns laid out on a `w`-wide grid.
pub(super) struct Problem<'a> {
    model: &'a Model,
    sites: &'a [Site],
    cells: Vec<Cell>,
    /// Second differences.
    seconds: Vec<Second>,
    /// Lower-triangle pattern of the normal equations (column pointers, row indices).
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Position in the values of each column's diagonal.
    diag_at: Vec<usize>,
    /// Fill-reducing ordering (nested dissection).
    order: Vec<usize>,
    /// Unknowns.
    n: usize,
}

/// Offsets (row, column) below the diagonal in row-major order: every pair a cell or a second
/// difference couples.
const LOWER: [(usize, isize); 6] = [(0, 1), (0, 2), (1, -1), (1, 0), (1, 1), (2, 0)];

impl<'a> Problem<'a> {
    /// The problem on the grid positions `grid` (row, column; row-major order) of a `w × h`
    /// image, with `sites` in the same order.
    pub fn new(
        model: &'a Model,
        sites: &'a [Site],
        grid: &[(usize, usize)],
        w: usize,
        h: usize,
    ) -> Self {
        let n = grid.len();
        let mut index = vec![usize::MAX; w * h];
        for (k, &(r, c)) in grid.iter().enumerate() {
            index[r * w + c] = k;
        }
        let at = |r: usize, c: isize| -> Option<usize> {
            (r < h && c >= 0 && (c as usize) < w)
                .then(|| index[r * w + c as usize])
                .filter(|&k| k != usize::MAX)
        };
        let mut cells = Vec::new();
        let mut seconds = Vec::new();
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(7 * n);
        let mut diag_at = Vec::with_capacity(n);
        col_ptr.push(0);
        for (k, &(r, c)) in grid.iter().enumerate() {
            let ci = c as isize;
            diag_at.push(row_idx.len());
            row_idx.push(k);
            for (dr, dc) in LOWER {
                if let Some(j) = at(r + dr, ci + dc) {
                    row_idx.push(j);
                }
            }
            col_ptr.push(row_idx.len());
            if let (Some(b), Some(cc), Some(d)) = (at(r, ci + 1), at(r + 1, ci), at(r + 1, ci + 1))
            {
                let corners = [k, b, cc, d];
                if corners.iter().all(|&j| sites[j].lit) {
                    let i = corners.iter().map(|&j| sites[j].i).sum::<f64>() / 4.0;
                    cells.push(Cell {
                        corners,
                        i,
                        slots: [[usize::MAX; 4]; 4],
                    });
                }
            }
            if let (Some(a), Some(b)) = ((c > 0).then(|| at(r, ci - 1)).flatten(), at(r, ci + 1)) {
                seconds.push(Second {
                    at: [a, k, b],
                    slots: [[usize::MAX; 3]; 3],
                    f: model.fx,
                });
            }
            if let (Some(a), Some(b)) = ((r > 0).then(|| at(r - 1, ci)).flatten(), at(r + 1, ci)) {
                seconds.push(Second {
                    at: [a, k, b],
                    slots: [[usize::MAX; 3]; 3],
                    f: model.fy,
                });
            }
        }
        let mut problem = Problem {
            model,
            sites,
            cells: Vec::new(),
            seconds: Vec::new(),
            col_ptr,
            row_idx,
            diag_at,
            order: Vec::new(),
            n,
        };
        for cell in &mut cells {
            for a in 0..4 {
                for b in 0..4 {
                    let (ja, jb) = (cell.corners[a], cell.corners[b]);
                    if ja >= jb {
                        cell.slots[a][b] = problem.slot(ja, jb);
                    }
                }
            }
        }
        for second in &mut seconds {
            for a in 0..3 {
                for b in 0..3 {
                    let (ja, jb) = (second.at[a], second.at[b]);
                    if ja >= jb {
                        second.slots[a][b] = problem.slot(ja, jb);
                    }
                }
            }
        }
        let coords: Vec<(u32, u32)> = grid.iter().map(|&(r, c)| (c as u32, r as u32)).collect();
        let order = nested_dissection_of(&coords, 2);
        problem.cells = cells;
        problem.seconds = seconds;
        problem.order = order;
        problem
    }

    /// Cells with a residual.
    pub fn cells(&self) -> usize {
        self.cells.len()
    }

    /// Whether unknown `k` is a corner of a cell with a residual.
    pub fn fitted(&self) -> Vec<bool> {
        let mut f = vec![false; self.n];
        for cell in &self.cells {
            for &j in &cell.corners {
                f[j] = true;
            }
        }
        f
    }

    /// The back-projected points at ln-depths `z`.
    fn points(&self, z: &[f64]) -> Vec<Vector3<f64>> {
        self.sites
            .par_iter()
            .zip(z)
            .map(|(s, &zk)| Vector3::new(s.xi, s.eta, 1.0) * zk.exp())
            .collect()
    }

    /// The relative residual of a cell whose corners are at the points `p`.
    fn cell_residual(&self, cell: &Cell, p: [Vector3<f64>; 4]) -> f64 {
        let across = (p[1] - p[0] + p[3] - p[2]) * 0.5;
        let down = (p[2] - p[0] + p[3] - p[1]) * 0.5;
        // Facing the camera (internal frame: z forward, y down).
        let n = down.cross(&across);
        let centre = (p[0] + p[1] + p[2] + p[3]) * 0.25;
        let to_light = self.model.s - centre;
        let d2 = to_light.norm_squared();
        let nn = n.norm();
        let cos = if nn > 0.0 {
            n.dot(&to_light) / (nn * d2.sqrt())
        } else {
            0.0
        };
        let f1 = self.model.brightness.max();
        (self.model.brightness.eval_extended(cos) - cell.i * d2 / self.model.phi) / f1
    }

    /// The energy: the cells' squared residuals plus λ times the squared second differences.
    fn energy(&self, z: &[f64], lambda: f64) -> f64 {
        self.data_energy(&self.points(z)) + lambda * self.smooth_energy(z)
    }

    /// Σ over cells of the squared residual, in fixed chunks and order (the line search compares
    /// energies, so a sum that moved in its last bits from run to run could change its path).
    fn data_energy(&self, points: &[Vector3<f64>]) -> f64 {
        crate::pool::ordered_fold(
            self.cells.len(),
            || 0.0,
            |sum, i| {
                let c = &self.cells[i];
                sum + self.cell_residual(c, c.corners.map(|j| points[j])).powi(2)
            },
            |a, b| a + b,
        )
    }

    /// Σ of the squared scaled second differences.
    fn smooth_energy(&self, z: &[f64]) -> f64 {
        self.seconds
            .iter()
            .map(|s| (s.f * (z[s.at[0]] - 2.0 * z[s.at[1]] + z[s.at[2]])).powi(2))
            .sum()
    }

    /// Position in the values of the entry (row `i`, column `j`), `i ≥ j`; `usize::MAX` for a
    /// pair outside the pattern (none: [`LOWER`] holds every pair a cell or a second difference
    /// couples), which the assembly skips.
    fn slot(&self, i: usize, j: usize) -> usize {
        if i == j {
            return self.diag_at[j];
        }
        let rows = &self.row_idx[self.col_ptr[j]..self.col_ptr[j + 1]];
        // Few entries: a linear scan.
        rows.iter()
            .position(|&r| r == i)
            .map_or(usize::MAX, |at| self.col_ptr[j] + at)
    }

    /// The normal equations at `z`: the lower triangle's values and the gradient half ∇E/2.
    fn normal_equations(&self, z: &[f64], lambda: f64) -> (Vec<f64>, Vec<f64>) {
        let n = self.n;
        let mut values = vec![0.0; self.row_idx.len()];
        let mut g = vec![0.0; n];
        let points = self.points(z);
        // d/dz_k of a corner's point is the point itself: a step h in ln Z scales it by e^h.
        let (up, down) = (STEP.exp(), (-STEP).exp());
        let rows: Vec<(f64, [f64; 4])> = self
            .cells
            .par_iter()
            .map(|c| {
                let p = c.corners.map(|j| points[j]);
                let r = self.cell_residual(c, p);
                let grad = std::array::from_fn(|k| {
                    let (mut hi, mut lo) = (p, p);
                    hi[k] *= up;
                    lo[k] *= down;
                    (self.cell_residual(c, hi) - self.cell_residual(c, lo)) / (2.0 * STEP)
                });
                (r, grad)
            })
            .collect();
        for (cell, (r, grad)) in self.cells.iter().zip(&rows) {
            for a in 0..4 {
                let ja = cell.corners[a];
                g[ja] += grad[a] * r;
                for b in 0..4 {
                    let at = cell.slots[a][b];
                    if ja >= cell.corners[b] && at != usize::MAX {
                        values[at] += grad[a] * grad[b];
                    }
                }
            }
        }
        for s in &self.seconds {
            let coef = [s.f, -2.0 * s.f, s.f];
            let r: f64 = (0..3).map(|t| coef[t] * z[s.at[t]]).sum();
            for a in 0..3 {
                g[s.at[a]] += lambda * coef[a] * r;
                for b in 0..3 {
                    let at = s.slots[a][b];
                    if s.at[a] >= s.at[b] && at != usize::MAX {
                        values[at] += lambda * coef[a] * coef[b];
                    }
                }
            }
        }
        (values, g)
    }
}

/// Refines the ln-depths `z` (one per unknown of `problem`) in place.
///
/// Steps that move the surface as a whole by more than [`MAX_SHIFT`] (the mean change of ln Z
/// from the start) stop the refinement and are discarded, `z` left at its start and the report
/// `discarded`: on the rendered relief under a light 30° off the axis the energy has a valley
/// of lower energy with the whole surface 30–40% nearer the camera, and steps that head there
/// have left the start's minimum rather than refined it (docs/shape-from-shading.md, "The
/// light's azimuth").
///
/// # Errors
/// [`Error::InvalidParameter`] for invalid options or a failed factorisation.
pub(super) fn refine(
    problem: &Problem<'_>,
    z: &mut [f64],
    options: &RefineOptions,
) -> Result<RefineReport> {
    options.validate()?;
    let started = std::time::Instant::now();
    let n = z.len();
    let lambda = options.smoothness;
    let energy_start = problem.energy(z, lambda);
    let mut report = RefineReport {
        iterations: 0,
        coarse_iterations: 0,
        converged: true,
        shift: 0.0,
        discarded: false,
        energy_start,
        energy_end: energy_start,
        rms_residual: 0.0,
        cells: problem.cells(),
        smoothness: lambda,
        seconds: 0.0,
    };
    if n == 0 || problem.cells() == 0 {
        report.seconds = started.elapsed().as_secs_f64();
        return Ok(report);
    }
    let symbolic = symbolic_cholesky(&problem.col_ptr, &problem.row_idx, problem.order.clone())?;
    // Sequential: on these sizes (10⁴–10⁵ unknowns) faer's parallel factorisation was slower
    // on 2 cores (34 000 unknowns: 0.10 s against 0.17 s).
    let mut work = MixedCholesky::new(&symbolic, Par::Seq)?;

    let mut energy = energy_start;
    let mut candidate = vec![0.0; n];
    let start = z.to_vec();
    report.converged = false;
    while report.iterations < options.max_iterations {
        let (mut values, g) = problem.normal_equations(z, lambda);
        // A little damping keeps the system definite where only the penalty reaches.
        let mean_diag = problem.diag_at.iter().map(|&p| values[p]).sum::<f64>() / n as f64;
        for &p in &problem.diag_at {
            values[p] += crate::sfs::gauss_newton_damping(values[p], mean_diag);
        }
        let mut step: Vec<f64> = g.iter().map(|v| -v).collect();
        work.solve(
            &symbolic,
            &problem.col_ptr,
            &problem.row_idx,
            &values,
            &mut step,
        )?;
        report.iterations += 1;
        // The length along the step (quadratic interpolation; see `sfs::line_search`).
        let slope = 2.0 * g.iter().zip(&step).map(|(a, b)| a * b).sum::<f64>();
        let kept = line_search::search(energy, slope, true, |alpha| {
            for k in 0..n {
                candidate[k] = z[k] + alpha * step[k];
            }
            problem.energy(&candidate, lambda)
        });
        let Some((alpha, e)) = kept else {
            // No step lowers the energy: z is a minimum to rounding (unless the energy is not a
            // number, which is no minimum).
            report.converged = energy.is_finite();
            break;
        };
        let fell = (energy - e) / energy;
        for k in 0..n {
            z[k] += alpha * step[k];
        }
        energy = e;
        report.shift = z.iter().zip(&start).map(|(a, b)| a - b).sum::<f64>() / n as f64;
        if report.shift.abs() > MAX_SHIFT {
            // Not a refinement of the start any more: the energy has a lower valley far from
            // it (a surface nearer or farther as a whole), which the start was not on.
            report.discarded = true;
            z.copy_from_slice(&start);
            energy = energy_start;
            break;
        }
        if fell < options.tolerance {
            report.converged = true;
            break;
        }
    }
    report.energy_end = energy;
    let data = problem.data_energy(&problem.points(z));
    report.rms_residual = (data / problem.cells() as f64).sqrt();
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

/// The fewest pixels of a half-resolution level that refines a start. Chosen on the rendered
/// test shapes (`photostereo bench sfs`, 128² and 256²), from two groups with nothing between
/// them: starts refined at levels of 1 000–2 100 pixels (32² frames; the sphere, vase and bust
/// at 64², whose occluding contours take a large share of so few pixels) took up to twice as
/// many steps at the next resolution, or landed in a worse minimum there (a glossy sphere 1.41°
/// against 0.84°), while the 64² levels of the frame-filling shapes (4 084–4 096 pixels) cut the
/// next resolution's steps by a half to two thirds at the same error. The limit lies between
/// the two; the pixel count stands in for what differs (the contour's share of the level).
const MIN_HALF_PIXELS: usize = 3000;

/// Moves the start `z` of the refinement of `problem` (the level of `model` and `sites` at the
/// grid positions `grid` of a `w × h` image) by what refining it at half resolution changes:
/// the start's 2×2 block means are refined on the half-resolution level (block-mean brightness,
/// a block lit when its four pixels are, the focal lengths halved; recursively while the levels
/// stay large enough), and the change, interpolated back, is added to `z`, which keeps the
/// start's own detail. The refinement's slow, smooth motions (a full-resolution step of a crawl
/// differs from its half-resolution interpolation by about 1% of its norm) then cost several
/// times less per step (a quarter of the unknowns; 4 ms against 27 ms a step at 64² and 128²).
///
/// The change is kept only when it lowers the energy of `problem`; a half-resolution level
/// too small ([`MIN_HALF_PIXELS`]), a mask with parts thinner than a block, or a refinement
/// that fails there (a factorisation that is not positive definite, say) or is discarded there
/// (it moved the whole surface, see [`refine`]) leaves `z` as it was:
/// this only makes a start, and the refinement at this resolution decides. Each level's steps
/// are limited by `options.max_iterations` on their own. Returns the steps taken at the lower
/// resolutions when the change was kept, else 0.
pub(super) fn refine_from_half(
    problem: &Problem<'_>,
    (model, sites, grid): (&Model, &[Site], &[(usize, usize)]),
    (w, h): (usize, usize),
    z: &mut [f64],
    options: &RefineOptions,
) -> usize {
    let Some(t) = Transfer::new(grid, w, h, MIN_HALF_PIXELS) else {
        return 0;
    };
    let csites: Vec<Site> = t
        .blocks
        .iter()
        .map(|b| {
            let mean = |f: fn(&Site) -> f64| b.iter().map(|&k| f(&sites[k])).sum::<f64>() / 4.0;
            Site {
                xi: mean(|s| s.xi),
                eta: mean(|s| s.eta),
                i: mean(|s| s.i),
                lit: b.iter().all(|&k| sites[k].lit),
            }
        })
        .collect();
    let cmodel = Model {
        fx: model.fx / 2.0,
        fy: model.fy / 2.0,
        ..model.clone()
    };
    let cproblem = Problem::new(&cmodel, &csites, &t.grid, t.w, t.h);
    let start = t.restrict(z);
    let mut cz = start.clone();
    let below = refine_from_half(
        &cproblem,
        (&cmodel, &csites, &t.grid),
        (t.w, t.h),
        &mut cz,
        options,
    );
    let report = match refine(&cproblem, &mut cz, options) {
        Ok(r) if !r.discarded => r,
        // Failed, or discarded there: no start (whatever the levels below it moved).
        _ => return 0,
    };
    let change: Vec<f64> = cz.iter().zip(&start).map(|(a, b)| a - b).collect();
    let moved: Vec<f64> = z
        .iter()
        .zip(t.prolong(&change))
        .map(|(a, d)| a + d)
        .collect();
    let lambda = options.smoothness;
    // Kept only if it helps (a NaN energy does not).
    if problem
        .energy(&moved, lambda)
        .partial_cmp(&problem.energy(z, lambda))
        != Some(std::cmp::Ordering::Less)
    {
        return 0;
    }
    z.copy_from_slice(&moved);
    below + report.iterations
}

#[cfg(test)]
mod tests {
    use super::super::Brightness;
    use super::*;

    fn model(s: Vector3<f64>) -> Model {
        Model {
            s,
            at_camera: s.norm() == 0.0,
            phi: 1e5,
            brightness: Brightness::Lambert(0.8),
            fx: 200.0,
            fy: 200.0,
        }
    }

    /// A `w × h` patch of the plane through (0, 0, `at`) with normal `nrm` (facing the camera,
    /// f = 200, centred), rendered exactly at each pixel under `m`: its grid, sites and ln Z.
    fn rendered_plane(
        m: &Model,
        nrm: Vector3<f64>,
        at: f64,
        w: usize,
        h: usize,
    ) -> (Vec<(usize, usize)>, Vec<Site>, Vec<f64>) {
        let (mut grid, mut sites, mut z) = (vec![], vec![], vec![]);
        for r in 0..h {
            for c in 0..w {
                let xi = (c as f64 - (w / 2) as f64) / 200.0;
                let eta = (r as f64 - (h / 2) as f64) / 200.0;
                let zz = at * nrm.z / nrm.dot(&Vector3::new(xi, eta, 1.0));
                let l = m.s - Vector3::new(xi, eta, 1.0) * zz;
                let i = m.phi * 0.8 * nrm.dot(&l).max(0.0) / l.norm().powi(3);
                grid.push((r, c));
                sites.push(Site {
                    xi,
                    eta,
                    i,
                    lit: true,
                });
                z.push(zz.ln());
            }
        }
        (grid, sites, z)
    }

    /// A plane's points, rendered exactly at each pixel: the cells' residual nearly vanishes on
    /// its depth (the cell's normal is exact on a plane, its centroid on the plane), so the
    /// refinement keeps it.
    #[test]
    fn a_rendered_plane_is_a_fixed_point() {
        let m = model(Vector3::new(60.0, -40.0, 0.0));
        let (w, h) = (12, 10);
        let nrm = Vector3::new(0.3, -0.2, -1.0).normalize();
        let (grid, sites, mut z) = rendered_plane(&m, nrm, 250.0, w, h);
        let problem = Problem::new(&m, &sites, &grid, w, h);
        assert_eq!(problem.cells(), (w - 1) * (h - 1));
        let start = z.clone();
        // The brightness is sampled at the corners and averaged, the cell's at its centre: on a
        // plane these differ only by the fall-off's curvature across a pixel, second order in
        // the pixel's size over the distance (here about 1/200): a residual under 10⁻⁴.
        let e0 = problem.energy(&z, 0.0);
        let rms = (e0 / problem.cells() as f64).sqrt();
        assert!(rms < 1e-4, "rms residual on the exact plane {rms}");
        // Moved 0.1% in depth, the plane is 100 times further from fitting.
        let moved_plane: Vec<f64> = z.iter().map(|v| v + 1e-3).collect();
        assert!(problem.energy(&moved_plane, 0.0) > 1e2 * e0);
        let report = refine(&problem, &mut z, &RefineOptions::default()).unwrap();
        assert!(report.converged);
        let moved = z
            .iter()
            .zip(&start)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        // It stays within 0.02% of its depth (where the residual's second-order floor and the
        // penalty balance).
        assert!(moved < 2e-4, "moved {moved}");
        assert!(report.energy_end <= report.energy_start);
    }

    /// From a plane pushed off its depth by a smooth bump (0.4% of the depth), the refinement
    /// returns to within a tenth of the bump.
    #[test]
    fn returns_to_the_rendered_plane() {
        let m = model(Vector3::new(-50.0, 30.0, 0.0));
        let (w, h) = (24, 20);
        let nrm = Vector3::new(-0.2, 0.25, -1.0).normalize();
        let (grid, sites, truth) = rendered_plane(&m, nrm, 300.0, w, h);
        let mut z: Vec<f64> = grid
            .iter()
            .zip(&truth)
            .map(|(&(r, c), &t)| {
                t + 0.004 * (-((c as f64 - 12.0).powi(2) + (r as f64 - 10.0).powi(2)) / 30.0).exp()
            })
            .collect();
        let problem = Problem::new(&m, &sites, &grid, w, h);
        let before = z
            .iter()
            .zip(&truth)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let tight = RefineOptions {
            tolerance: 1e-9,
            ..RefineOptions::default()
        };
        let report = refine(&problem, &mut z, &tight).unwrap();
        let after = z
            .iter()
            .zip(&truth)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(report.converged, "{report:?}");
        assert!(report.energy_end < 1e-3 * report.energy_start, "{report:?}");
        assert!(
            after < 0.1 * before,
            "before {before:.2e} after {after:.2e}"
        );
    }

    /// A plane pushed off its depth by a broad bump (0.4% of the depth, 25 pixels wide): the
    /// half-resolution refinement alone takes out most of the bump, then the refinement at full
    /// resolution returns to within a tenth of it.
    #[test]
    fn a_start_refined_at_half_resolution() {
        let m = model(Vector3::new(-50.0, 30.0, 0.0));
        let (w, h) = (128, 96);
        let nrm = Vector3::new(-0.2, 0.25, -1.0).normalize();
        let (grid, sites, truth) = rendered_plane(&m, nrm, 300.0, w, h);
        let bump = |r: usize, c: usize| {
            0.004 * (-((c as f64 - 60.0).powi(2) + (r as f64 - 50.0).powi(2)) / 625.0).exp()
        };
        let mut z: Vec<f64> = grid
            .iter()
            .zip(&truth)
            .map(|(&(r, c), &t)| t + bump(r, c))
            .collect();
        let off = |z: &[f64]| {
            z.iter()
                .zip(&truth)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max)
        };
        let before = off(&z);
        let tight = RefineOptions {
            tolerance: 1e-9,
            ..RefineOptions::default()
        };
        let problem = Problem::new(&m, &sites, &grid, w, h);
        let e0 = problem.energy(&z, tight.smoothness);
        let steps = refine_from_half(&problem, (&m, &sites, &grid), (w, h), &mut z, &tight);
        let halfway = off(&z);
        assert!(steps > 0);
        assert!(
            halfway < 0.05 * before,
            "before {before:.2e}, from half {halfway:.2e}"
        );
        assert!(problem.energy(&z, tight.smoothness) < 0.1 * e0);
        let report = refine(&problem, &mut z, &tight).unwrap();
        assert!(report.converged, "{report:?}");
        let after = off(&z);
        println!(
            "bump {before:.2e}: {halfway:.2e} after {steps} half-resolution steps, {after:.2e} \
             after {} more",
            report.iterations
        );
        assert!(
            after < 0.1 * before,
            "before {before:.2e} after {after:.2e}"
        );
    }

    /// The refinement does not depend on the number of threads: the same bumped plane (12 065
    /// cells, several chunks of the energy's sum) refined in a pool of one thread and in one of
    /// four gives the same depth and the same energies, bit for bit. (With rayon's own sum the
    /// energies moved in their last bits with the threads, and from run to run; the line search
    /// compares them.)
    #[test]
    fn the_refinement_does_not_depend_on_the_threads() {
        let m = model(Vector3::new(-50.0, 30.0, 0.0));
        let (w, h) = (128, 96);
        let nrm = Vector3::new(-0.2, 0.25, -1.0).normalize();
        let (grid, sites, truth) = rendered_plane(&m, nrm, 300.0, w, h);
        let start: Vec<f64> = grid
            .iter()
            .zip(&truth)
            .map(|(&(r, c), &t)| {
                t + 0.004 * (-((c as f64 - 60.0).powi(2) + (r as f64 - 50.0).powi(2)) / 625.0).exp()
            })
            .collect();
        let run = |threads: usize| {
            crate::synth::test_support::with_threads(threads, || {
                let problem = Problem::new(&m, &sites, &grid, w, h);
                let mut z = start.clone();
                let e0 = problem.energy(&z, 0.0);
                let report = refine(&problem, &mut z, &RefineOptions::default()).unwrap();
                (
                    e0,
                    report.energy_start,
                    report.energy_end,
                    report.iterations,
                    z,
                )
            })
        };
        let (one, four) = (run(1), run(4));
        assert!(one.3 > 0, "no step taken");
        assert_eq!(
            (one.0.to_bits(), one.1.to_bits(), one.2.to_bits(), one.3),
            (four.0.to_bits(), four.1.to_bits(), four.2.to_bits(), four.3)
        );
        assert!(
            one.4
                .iter()
                .zip(&four.4)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
    }

    #[test]
    fn options_are_checked() {
        for bad in [
            RefineOptions {
                smoothness: -1.0,
                ..RefineOptions::default()
            },
            RefineOptions {
                max_iterations: 0,
                ..RefineOptions::default()
            },
            RefineOptions {
                tolerance: 0.0,
                ..RefineOptions::default()
            },
        ] {
            assert!(bad.validate().is_err());
        }
    }
}
