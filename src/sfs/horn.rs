//! Horn's height-and-gradient shape from shading (B. K. P. Horn, "Height and gradient from
//! shading", IJCV 5(1), 1990), in its integrable limit.
//!
//! Horn minimises Σ (E/ρ − R(p, q))² + λ (smoothness of p, q) + μ Σ [(z_x − p)² + (z_y − q)²]
//! and lets μ enforce integrability. Here (p, q) are the height's own differences, which is the
//! limit μ → ∞: on Horn's staggered grid the gradient of each 2×2 cell of pixels is
//! p = ((z_TR + z_BR) − (z_TL + z_BL))/2, q = ((z_TL + z_TR) − (z_BL + z_BR))/2, the data term
//! compares R(p, q) with the mean brightness of the cell's four pixels, and the smoothness term
//! is λ Σ over adjacent cells of |∇z_c − ∇z_c'|². The energy in z is minimised by Gauss–Newton
//! steps, each by sparse Cholesky solves (faer), instead of Horn's Jacobi sweeps: tens of
//! iterations instead of thousands, and no discretisation mismatch between the gradients and the
//! height. λ decreases geometrically to `smoothness`, as Horn recommends: it only guides the
//! early iterations.
//!
//! While λ is lowered (halved every iteration) the steps are Levenberg–Marquardt's (a damping
//! adapted to accepted and rejected steps holds accepted steps near the last, so that the
//! continuation follows one solution; up to 12 factorisations an iteration).
//! At the final λ they are Gauss–Newton's with a damping of 10⁻⁶ of the diagonal (which keeps the
//! equations definite where only the smoothness reaches) and a line search
//! ([`super::line_search`]); should that step fail (a factorisation that fails, a step that is
//! not finite) the iteration takes Levenberg–Marquardt's. The iteration stops when a step at the final λ lowers the energy by
//! less than 10⁻³ of it, or when no step lowers it; the iteration limit (200) is reported when it
//! is hit. Measured on the rendered shapes of `bench sfs` (128², frontal and 30° lights):
//! - Levenberg–Marquardt throughout, as before, let its damping grow to 10⁻² where grazing cells
//!   made full steps fail, after which the shadows and the smoothness-only pixels barely moved:
//!   with the light 30° off, every shape was at the limit of 80 iterations, the relief's and the
//!   bust's energy still falling by 0.5% a step. Now all converge (the relief in 82 iterations,
//!   the bust in 106).
//! - Gauss–Newton with the line search throughout converged too and was better on the vase
//!   and peaks under the oblique light (4.1° and 6.6° against 8.1° and 11.1°), but its long
//!   early steps left the continuation's path on a rough (Oren–Nayar) sphere: 17.7° against
//!   1.2°.
//!
//! Coarse to fine ([`SfsOptions::coarse_to_fine`](super::SfsOptions), on by default): when
//! the mask keeps [`MIN_COARSE_PIXELS`] pixels at half resolution (2×2 blocks all in the mask),
//! the image's block means are solved first, recursively, the coarsest level with the whole
//! continuation in λ; the change that level makes to the start, interpolated bilinearly and
//! doubled (heights are in each level's pixels), is added to the full-resolution start, which is
//! then refined by Gauss–Newton steps at the final λ alone. The change is kept only if it lowers
//! the full-resolution energy (under a frontal light a frame-filling plane start is a stationary
//! point at every level, and nothing changes). Measured with `bench sfs` (light 30° off the
//! view): at 128², peaks 11.14° → 6.28° (1.37 → 0.81 s) and relief 13.56° → 12.36° (3.49 →
//! 2.30 s), the other shapes too small to have a coarse level; at 256², sphere, peaks, relief
//! and bust at both lights, 1.4–1.9× faster and as accurate or better (bust frontal 7.77° →
//! 2.44°, peaks oblique 14.47° → 6.02°) except the oblique sphere, 0.92° → 1.08°. The levels
//! stop at 3 000 pixels, the perspective refinement's limit: Horn settles on a wrong surface
//! for a rough sphere at 48²–64² (about 1 300–2 000 pixels), and a coarse level that small
//! would hand it to every finer one.
//!
//! Repeated continuation ([`SfsOptions::restarts`](super::SfsOptions), on by default): at every
//! level below the full resolution, and at the full resolution when it has no coarse start, the
//! continuation in λ is run again from the level's result (λ raised to its start and lowered
//! again), while a
//! repeat converges, lowers the energy at the final λ by more than [`TOLERANCE`] of it and,
//! with an occluding boundary, does not contradict it (its outline's misaligned fraction at most
//! [`super::OUTLINE_MISALIGNED_WARN`] or no more than before); at most [`MAX_RESTARTS`] times.
//! Why: started from the true surface, the iteration stays within 0.5–1.6° of it (vase, peaks,
//! relief, bust at 128², light 30° off the view) at a lower energy than the one continuation
//! reaches from the convex or plane start, so the error is the basin the continuation ends in,
//! not the energy's minimum; each repeat smooths the last result at a large λ and lets the data
//! pull it back, a graduated non-convexity (Blake and Zisserman, *Visual Reconstruction*, 1987)
//! restarted from where the last one ended. The outline test is what keeps a repeat from
//! walking into a surface of lower energy that the occluding boundary rules out (from a plane
//! start the vase reaches an energy below the truth's, 29° off). Measured in
//! docs/shape-from-shading.md ("Repeating the continuation").
//!
//! The normal equations are assembled into their compressed columns directly: the pattern
//! (at most 11 rows per column of the lower triangle) is gathered without sorting, the
//! smoothness part SᵀS is computed once and scaled by λ, and each cell's data row adds its ten
//! products at entries found once. Sorting the 10.5 million products of a frame-filling 256² image
//! at every iteration took as long as the factorisation.
//!
//! Boundary: the mask's edge is a free (natural) boundary. With [`Boundary::Occluding`] the
//! height starts from the convex surface z = √(d(2D − d)) of the distance d to the edge (D its
//! maximum; exact for a disk), which is what selects the convex solution and the steep rim of an
//! occluding contour; with [`Boundary::Free`] it starts from a plane. In shadow only R ≤ E/ρ is
//! enforced. (A hard occluding-contour prior on the edge pixels' gradients was tried and
//! dropped: the cells next to the rim are far less steep than the rim itself, and forcing them
//! raised the sphere's error from 1.6° to 21°.)

use super::line_search;
use super::pyramid::Transfer;
use super::{Boundary, Shading, Solved, clamp_gradient, differences, distance_to_edge};
use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::integrate::sparse::{
    CholeskyWork, NONE, Unknowns, nested_dissection, symbolic_cholesky,
};
use faer::Par;

/// Default Gauss–Newton iteration limit.
const DEFAULT_MAX_ITERATIONS: usize = 200;
/// Initial smoothness weight.
const LAMBDA_START: f64 = 0.1;
/// Factor applied to λ after each iteration (until it reaches `smoothness`).
const LAMBDA_DECAY: f64 = 0.5;
/// Below this λ the smoothness weighs nothing against the data terms (each at most 1 per cell):
/// λ is then set to `smoothness`, so that a floor of 0 is reached too.
const LAMBDA_NEGLIGIBLE: f64 = 1e-8;
/// Levenberg–Marquardt's initial damping, while λ is lowered.
const DAMPING_START: f64 = 1e-3;
/// Convergence at the final λ: a step lowers the energy by less than this fraction of it (the
/// shape-from-shading refinement's default test).
const TOLERANCE: f64 = super::perspective::refine::DEFAULT_TOLERANCE;
/// Room for the rows of one column of the normal equations' lower triangle (11 at most).
const MAX_COLUMN: usize = 16;
/// The fewest pixels of a half-resolution level that makes the start of the level above: the
/// perspective refinement's limit (chosen there on the rendered shapes), which also keeps Horn
/// off the levels of 1 300–2 000 pixels where it finds a wrong surface for a rough sphere.
const MIN_COARSE_PIXELS: usize = 3000;

/// The largest change of the height, relative to the start's largest height (or 1), under
/// which the result is reported as its start unchanged (when it also explains the image
/// poorly): only a start where the energy's gradient vanishes (no step leaves it) stays that
/// close.
const STATIONARY: f64 = 1e-9;

/// ∂p/∂z and ∂q/∂z of a cell for its corners (top-left, top-right, bottom-left, bottom-right).
const DP: [f64; 4] = [-0.5, 0.5, -0.5, 0.5];
const DQ: [f64; 4] = [0.5, 0.5, -0.5, -0.5];

/// The 2×2 cells of the staggered grid whose four pixels are in the mask.
struct Cells {
    /// Corner unknowns (TL, TR, BL, BR).
    corners: Vec<[usize; 4]>,
    /// Mean E/ρ of the corners.
    e: Vec<f64>,
    /// In shadow (mean E/ρ at or below the shadow level).
    shadow: Vec<bool>,
    /// Pairs of adjacent cells (sharing an edge).
    pairs: Vec<(usize, usize)>,
    /// Cells having each unknown as a corner.
    of_unknown: Vec<Vec<usize>>,
}

impl Cells {
    fn new(s: &Shading) -> Self {
        let u = &s.u;
        let n = u.len();
        let mut corners = Vec::new();
        let mut index = vec![usize::MAX; n];
        for (k, slot) in index.iter_mut().enumerate() {
            let (r, d) = (u.right[k], u.down[k]);
            if r == NONE || d == NONE || u.right[d as usize] == NONE {
                continue;
            }
            *slot = corners.len();
            corners.push([k, r as usize, d as usize, u.right[d as usize] as usize]);
        }
        let e: Vec<f64> = corners
            .iter()
            .map(|c| c.iter().map(|&k| s.e[k]).sum::<f64>() / 4.0)
            .collect();
        let shadow = e.iter().map(|&v| v <= s.options.shadow_level).collect();
        let mut pairs = Vec::new();
        let mut of_unknown = vec![Vec::new(); n];
        for (c, cs) in corners.iter().enumerate() {
            // The cell to the right has this cell's top-right corner as its top-left; the one
            // below has the bottom-left corner as its top-left.
            for next in [cs[1], cs[2]] {
                if index[next] != usize::MAX {
                    pairs.push((c, index[next]));
                }
            }
            for &k in cs {
                of_unknown[k].push(c);
            }
        }
        Cells {
            corners,
            e,
            shadow,
            pairs,
            of_unknown,
        }
    }

    fn gradient(&self, z: &[f64], c: usize) -> (f64, f64) {
        let k = self.corners[c];
        let (mut p, mut q) = (0.0, 0.0);
        for i in 0..4 {
            p += DP[i] * z[k[i]];
            q += DQ[i] * z[k[i]];
        }
        (p, q)
    }
}

/// The energy of Horn's method on one level, with its normal equations' sparsity pattern and
/// their Cholesky analysis: the pattern is the same at every iteration, so it is gathered and
/// analysed once, and only the values change.
struct Problem<'a> {
    s: &'a Shading<'a>,
    cells: Cells,
    /// The smoothness rows: the difference of two adjacent cells' p or q, over their corners.
    smooth: Vec<([usize; 8], [f64; 8])>,
    /// The lower triangle of the normal equations, column by column (compressed columns).
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    symbolic: faer::sparse::linalg::cholesky::SymbolicCholesky<usize>,
    /// SᵀS (the smoothness rows' normal equations at λ = 1) at each entry of the pattern: the
    /// same at every iteration, scaled by λ.
    smooth_values: Vec<f64>,
    /// The entries of each cell's data row's outer product, in the order the assembly adds
    /// them (corners a, b with unknown(b) ≥ unknown(a), a outer).
    cell_slots: Vec<[usize; 10]>,
    /// The diagonal entry of each unknown.
    diagonal: Vec<usize>,
    /// Per unknown, whether the image says it lies on the outline where that is no occluding
    /// contour ([`super::occluding`]): left out of the outline's agreement and of the convex
    /// start's distances.
    cut: Vec<bool>,
}

fn assembly_err(e: &dyn std::fmt::Debug) -> Error {
    Error::param("solver", format!("sparse assembly failed: {e:?}"))
}

impl<'a> Problem<'a> {
    fn new(s: &'a Shading<'a>) -> Result<Self> {
        let n = s.u.len();
        let cells = Cells::new(s);
        // Normal equations J_dᵀJ_d + λ SᵀS + νI, where J_d are the data rows linearised at z
        // (one per cell, coefficients R_p ∂p/∂z + R_q ∂q/∂z over its corners) and S the
        // smoothness rows.
        let smooth: Vec<([usize; 8], [f64; 8])> = cells
            .pairs
            .iter()
            .flat_map(|&(a, b)| {
                [DP, DQ].map(|d| {
                    let (ka, kb) = (cells.corners[a], cells.corners[b]);
                    (
                        [ka[0], ka[1], ka[2], ka[3], kb[0], kb[1], kb[2], kb[3]],
                        [d[0], d[1], d[2], d[3], -d[0], -d[1], -d[2], -d[3]],
                    )
                })
            })
            .collect();
        // The pattern's lower triangle, column by column: the unknowns at or after each that
        // share a cell or a smoothness row with it. Those lie in a window of 3 × 2 or 2 × 3
        // pixels, so a column has at most 11 rows (3 in its own image row, 5 in the next, 3 in
        // the one after): collected without duplicates in place of sorting every product's
        // entries.
        let mut columns = vec![([0u32; MAX_COLUMN], 0u8); n];
        let mut add = |idx: &[usize]| -> Result<()> {
            for &i in idx {
                for &j in idx {
                    let (rows, len) = &mut columns[i];
                    if j < i || rows[..*len as usize].contains(&(j as u32)) {
                        continue;
                    }
                    if *len as usize == MAX_COLUMN {
                        return Err(assembly_err(
                            &"a column of more rows than a 2×2 cell's smoothness reaches",
                        ));
                    }
                    rows[*len as usize] = j as u32;
                    *len += 1;
                }
            }
            Ok(())
        };
        for k in 0..n {
            add(&[k])?;
        }
        for c in &cells.corners {
            add(c)?;
        }
        for (idx, _) in &smooth {
            add(idx)?;
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0);
        for (rows, len) in &mut columns {
            let rows = &mut rows[..*len as usize];
            rows.sort_unstable();
            row_idx.extend(rows.iter().map(|&r| r as usize));
            col_ptr.push(row_idx.len());
        }
        drop(columns);
        // The entry of row `j` in column `i` (j ≥ i, in the pattern by construction).
        let slot = |j: usize, i: usize| -> usize {
            let column = &row_idx[col_ptr[i]..col_ptr[i + 1]];
            let at = column.iter().position(|&r| r == j);
            debug_assert!(at.is_some(), "entry ({j}, {i}) is not in the pattern");
            col_ptr[i] + at.unwrap_or(0)
        };
        let mut smooth_values = vec![0.0; row_idx.len()];
        for (idx, coef) in &smooth {
            for (a, &i) in idx.iter().enumerate() {
                for (b, &j) in idx.iter().enumerate() {
                    if j >= i {
                        smooth_values[slot(j, i)] += coef[a] * coef[b];
                    }
                }
            }
        }
        let cell_slots = cells
            .corners
            .iter()
            .map(|idx| {
                let mut out = [0; 10];
                let mut t = 0;
                for &i in idx {
                    for &j in idx {
                        if j >= i {
                            out[t] = slot(j, i);
                            t += 1;
                        }
                    }
                }
                out
            })
            .collect();
        let diagonal = (0..n).map(|k| slot(k, k)).collect();
        let nd = nested_dissection(&s.u, 2);
        // A cell and its neighbours couple pixels up to two apart: separators two pixels thick.
        let symbolic = symbolic_cholesky(&col_ptr, &row_idx, nd)?;
        Ok(Problem {
            s,
            cells,
            smooth,
            col_ptr,
            row_idx,
            symbolic,
            smooth_values,
            cell_slots,
            diagonal,
            cut: s.outline().contradicted,
        })
    }

    fn smooth_value(z: &[f64], (idx, coef): &([usize; 8], [f64; 8])) -> f64 {
        idx.iter().zip(coef).map(|(&k, c)| c * z[k]).sum()
    }

    /// Data residuals and linearised rows at z: (r₀ per cell, 0 for inactive shadow cells).
    fn data(&self, z: &[f64]) -> Vec<(f64, [f64; 4])> {
        let cells = &self.cells;
        (0..cells.corners.len())
            .map(|c| {
                let (p, q) = cells.gradient(z, c);
                let sh = self.s.rmap.eval_with_derivatives(p, q);
                let r0 = cells.e[c] - sh.r;
                if cells.shadow[c] && r0 >= 0.0 {
                    (0.0, [0.0; 4])
                } else {
                    (r0, [0, 1, 2, 3].map(|i| sh.r_p * DP[i] + sh.r_q * DQ[i]))
                }
            })
            .collect()
    }

    fn energy(&self, z: &[f64], lambda: f64) -> f64 {
        let d: f64 = self.data(z).iter().map(|(r, _)| r * r).sum();
        let sm: f64 = self
            .smooth
            .iter()
            .map(|row| Self::smooth_value(z, row).powi(2))
            .sum();
        d + lambda * sm
    }

    /// The normal equations of the Gauss–Newton step at `z` and smoothness `lambda`: their lower
    /// triangle J_dᵀJ_d + λ SᵀS into `values` (at the pattern's entries, without damping) and
    /// their right-hand side J_dᵀ r − λ SᵀS z, returned (−∇E/2).
    fn assemble(&self, z: &[f64], lambda: f64, values: &mut [f64]) -> Vec<f64> {
        for (v, sv) in values.iter_mut().zip(&self.smooth_values) {
            *v = lambda * sv;
        }
        let mut rhs = vec![0.0; self.s.u.len()];
        for (c, (r0, coef)) in self.data(z).iter().enumerate() {
            let idx = &self.cells.corners[c];
            let slots = &self.cell_slots[c];
            let mut t = 0;
            for (a, &i) in idx.iter().enumerate() {
                rhs[i] += coef[a] * r0;
                for (b, &j) in idx.iter().enumerate() {
                    if j >= i {
                        values[slots[t]] += coef[a] * coef[b];
                        t += 1;
                    }
                }
            }
        }
        for row in &self.smooth {
            let v = Self::smooth_value(z, row);
            for (a, &i) in row.0.iter().enumerate() {
                rhs[i] -= lambda * row.1[a] * v;
            }
        }
        rhs
    }

    /// Each pixel's gradient (p, q) for the heights `z`: the mean of its cells' (central
    /// differences where it has none), clamped as every method's are.
    fn pixel_gradients(&self, z: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let u = &self.s.u;
        let cells = &self.cells;
        let n = u.len();
        let mut p = vec![0.0; n];
        let mut q = vec![0.0; n];
        for k in 0..n {
            let cs = &cells.of_unknown[k];
            let (a, b) = if cs.is_empty() {
                differences(u, z, k)
            } else {
                let (mut a, mut b) = (0.0, 0.0);
                for &c in cs {
                    let (x, y) = cells.gradient(z, c);
                    a += x;
                    b += y;
                }
                (a / cs.len() as f64, b / cs.len() as f64)
            };
            (p[k], q[k]) = clamp_gradient(a, b);
        }
        (p, q)
    }

    /// The fraction of the outline's pixels whose normals contradict the occluding boundary
    /// ([`super::OutlineAgreement`]) for the heights `z`; `None` with a free boundary or
    /// where the mask has no outline inside the image.
    fn misaligned(&self, z: &[f64]) -> Option<f64> {
        if self.s.options.boundary != Boundary::Occluding {
            return None;
        }
        let (p, q) = self.pixel_gradients(z);
        super::outline_repair::agreement_of_gradients(&self.s.u, &p, &q, &self.cut)
            .map(|a| a.misaligned_fraction)
    }

    /// Minimises from `z` ([`Self::minimise`], with the continuation in λ when
    /// `first_continuation`, else at the final λ only), then repeats the whole continuation
    /// from the result while a repeat converges and lowers the energy at the final λ by more than
    /// [`TOLERANCE`] of it without contradicting the occluding boundary (with
    /// [`Boundary::Occluding`], its outline's misaligned fraction at most
    /// [`super::OUTLINE_MISALIGNED_WARN`], or no more than before), at most [`MAX_RESTARTS`]
    /// times; the first repeat that does not is dropped and ends them. Returns the iterations
    /// run (the dropped repeat's included), whether the first minimisation converged, and the
    /// repeats kept.
    fn continued(
        &self,
        z: &mut [f64],
        first_continuation: bool,
        progress: &dyn crate::progress::Progress,
    ) -> Result<(usize, bool, usize)> {
        if !self.s.options.restarts {
            let (iterations, converged) = self.minimise(z, first_continuation, progress)?;
            return Ok((iterations, converged, 0));
        }
        let before = z.to_vec();
        let (mut iterations, converged) = self.minimise(z, first_continuation, progress)?;
        // A continuation that returned its start (a stationary point: a plane facing a light
        // at the viewer) would return it again.
        if !converged || z == before.as_slice() {
            return Ok((iterations, converged, 0));
        }
        let floor = self.s.options.smoothness;
        let mut energy = self.energy(z, floor);
        let mut misaligned = self.misaligned(z);
        let mut kept = 0;
        let mut trial = z.to_vec();
        for _ in 0..MAX_RESTARTS {
            trial.copy_from_slice(z);
            let Ok((its, repeat_converged)) = self.minimise(&mut trial, true, progress) else {
                break;
            };
            iterations += its;
            let e = self.energy(&trial, floor);
            if !(repeat_converged && e < (1.0 - TOLERANCE) * energy) {
                break;
            }
            let m = self.misaligned(&trial);
            if let (Some(m), Some(before)) = (m, misaligned)
                && m > before.max(super::OUTLINE_MISALIGNED_WARN)
            {
                break;
            }
            z.copy_from_slice(&trial);
            energy = e;
            misaligned = m;
            kept += 1;
        }
        Ok((iterations, true, kept))
    }

    /// Minimises the energy from `z`, in place: with `continuation`, λ starts at
    /// [`LAMBDA_START`] and is halved every iteration down to the final `smoothness`
    /// (Levenberg–Marquardt steps until it is reached); without, every iteration is at the final
    /// λ (a start that already follows one solution, made at a lower resolution). Returns the
    /// iterations run and whether the energy stopped falling.
    fn minimise(
        &self,
        z: &mut [f64],
        continuation: bool,
        progress: &dyn crate::progress::Progress,
    ) -> Result<(usize, bool)> {
        let s = self.s;
        let n = s.u.len();
        let max_iter = max_iterations(s);
        // Sequential: faer's parallel factorisation spends more time synchronising than it
        // saves on these sizes (as in the perspective refinement).
        let mut work = CholeskyWork::new(&self.symbolic, Par::Seq)?;
        let floor = s.options.smoothness;
        let mut lambda = if continuation {
            LAMBDA_START.max(floor)
        } else {
            floor
        };
        let mut damping = DAMPING_START;
        let mut iterations = 0;
        let mut converged = false;
        let mut values = vec![0.0; self.row_idx.len()];
        let mut diag = vec![0.0; n];
        let mut trial = vec![0.0; n];
        while iterations < max_iter {
            iterations += 1;
            progress.advance(1);
            let e0 = self.energy(z, lambda);
            let rhs = self.assemble(z, lambda, &mut values);
            let at_floor = lambda <= floor;
            for (d, &at) in diag.iter_mut().zip(&self.diagonal) {
                *d = values[at];
            }
            // Solves the normal equations with `damping(k)` added to the k-th diagonal entry.
            let mut solve_damped = |values: &mut Vec<f64>, damping: &dyn Fn(usize) -> f64| {
                for (k, &at) in self.diagonal.iter().enumerate() {
                    values[at] = diag[k] + damping(k);
                }
                let mut delta = rhs.clone();
                work.solve(
                    &self.symbolic,
                    &self.col_ptr,
                    &self.row_idx,
                    values,
                    &mut delta,
                )?;
                Ok::<_, Error>(delta)
            };
            let mut lowered = None;
            // Whether the Gauss–Newton step could be computed (a factorisation that fails, or
            // a step that is not finite, falls back to Levenberg–Marquardt's damping).
            let mut newton = false;
            if at_floor {
                // Gauss–Newton with a line search at the final λ.
                let mean_diag = diag.iter().sum::<f64>() / n as f64;
                let delta = solve_damped(&mut values, &|k| {
                    super::gauss_newton_damping(diag[k], mean_diag)
                })
                .ok()
                .filter(|d| d.iter().all(|v| v.is_finite()));
                if let Some(delta) = delta {
                    newton = true;
                    // rhs is −∇E/2: the energy's slope along the step is −2 rhs·δ.
                    let slope = -2.0 * rhs.iter().zip(&delta).map(|(a, b)| a * b).sum::<f64>();
                    // Without shortening: a shadow cell's data term switches on and off, which
                    // makes the parabola a poor guide (with Gauss–Newton steps from the start,
                    // trying its minimum after a length that lowered E left the bust and the
                    // relief at 128² at the iteration limit).
                    lowered = line_search::search(e0, slope, false, |alpha| {
                        for k in 0..n {
                            trial[k] = z[k] + alpha * delta[k];
                        }
                        self.energy(&trial, lambda)
                    })
                    .map(|(alpha, e)| (delta, alpha, e));
                }
            }
            if !newton {
                // Levenberg–Marquardt while λ is lowered: the damping holds accepted steps near
                // the last, so that the continuation in λ follows one solution.
                for _ in 0..12 {
                    let Ok(delta) = solve_damped(&mut values, &|_| damping) else {
                        damping *= 10.0;
                        continue;
                    };
                    for k in 0..n {
                        trial[k] = z[k] + delta[k];
                    }
                    let e = self.energy(&trial, lambda);
                    if delta.iter().all(|v| v.is_finite()) && e <= e0 {
                        damping = (damping / 3.0).max(1e-9);
                        lowered = Some((delta, 1.0, e));
                        break;
                    }
                    damping *= 4.0;
                }
            }
            // A floor of 0 (or one below what 0.1 halved every iteration reaches) would never
            // be reached: below LAMBDA_NEGLIGIBLE, λ jumps to the floor.
            lambda *= LAMBDA_DECAY;
            if lambda < floor.max(LAMBDA_NEGLIGIBLE) {
                lambda = floor;
            }
            match lowered {
                Some((delta, alpha, e)) => {
                    for k in 0..n {
                        z[k] += alpha * delta[k];
                    }
                    if at_floor && e0 - e < TOLERANCE * e0 {
                        converged = true;
                        break;
                    }
                }
                // No Gauss–Newton step lowers the energy: a (local) minimum, unless the energy
                // is not a number, which is no minimum.
                None if newton => {
                    converged = e0.is_finite();
                    break;
                }
                // No Levenberg–Marquardt step either at the final λ: stuck, not converged.
                None if at_floor => break,
                None => {}
            }
        }
        Ok((iterations, converged))
    }
}

/// Repeats of the continuation in λ from its own result at most ([`Problem::continued`]).
pub const MAX_RESTARTS: usize = 8;

/// The progress stage's total for a level of `s`: its iteration limit, times the runs at most
/// where the continuation is repeated (`repeated`, [`Problem::continued`]).
fn stage_total(s: &Shading, repeated: bool) -> u64 {
    let runs = if repeated && s.options.restarts {
        1 + MAX_RESTARTS
    } else {
        1
    };
    (max_iterations(s) * runs) as u64
}

/// The iteration limit of each level: the options', or [`DEFAULT_MAX_ITERATIONS`].
fn max_iterations(s: &Shading) -> usize {
    if s.options.max_iterations > 0 {
        s.options.max_iterations
    } else {
        DEFAULT_MAX_ITERATIONS
    }
}

/// Moves the start `z` of `problem` by what solving the level of half its resolution changes:
/// the image's 2×2 block means are solved from the start's block means (halved: heights are in
/// each level's pixels), recursively while the levels keep [`MIN_COARSE_PIXELS`], the coarsest
/// with the whole continuation in λ; the change, interpolated back and doubled, is added to `z`,
/// which keeps the start's own detail (the steep rim of the convex start). Returns the
/// iterations run at the lower resolutions and the repeats of the continuation kept there
/// ([`Problem::continued`]) when the change was kept; `None` (and `z` as it
/// was) when there is no such level (too small, or a part of the mask thinner than a block),
/// when the solve there fails, or when the change does not lower the energy at this level.
fn from_half(problem: &Problem<'_>, z: &mut [f64]) -> Option<(usize, usize)> {
    let s = problem.s;
    let u = &s.u;
    let grid: Vec<(usize, usize)> = u
        .pixel
        .iter()
        .map(|&p| (p as usize / u.w, p as usize % u.w))
        .collect();
    let t = Transfer::new(&grid, u.w, u.h, MIN_COARSE_PIXELS)?;
    let mut mask = Grid::new(t.w, t.h, false);
    for &(r, c) in &t.grid {
        mask.data_mut()[r * t.w + c] = true;
    }
    // The coarse unknowns are the mask's pixels in row-major order: the order of `t.grid`.
    let e = t.restrict(&s.e);
    let shadow = e.iter().map(|&v| v <= s.options.shadow_level).collect();
    let coarse = Shading {
        u: Unknowns::new(&mask),
        e,
        shadow,
        rmap: s.rmap,
        options: s.options,
        progress: s.progress,
        start: None,
        // Not tested at the coarse levels: a coarse outline pixel is a block mean up to two
        // fine pixels inside the contour, whose curvature radius is halved in its pixels, so a
        // silhouette could fail the test there. The start came from the full resolution's.
        occluding_tolerance: None,
    };
    let cproblem = Problem::new(&coarse).ok()?;
    let start: Vec<f64> = t.restrict(z).iter().map(|v| v / 2.0).collect();
    let mut cz = start.clone();
    let below = from_half(&cproblem, &mut cz);
    // Each level is a stage of its own, so that the progress shows from the coarsest level on.
    s.progress.begin(
        &format!("shape from shading (Horn), {}×{} level", t.w, t.h),
        stage_total(s, true),
    );
    let minimised = cproblem.continued(&mut cz, below.is_none(), s.progress);
    s.progress.end();
    let (iterations, _, repeats) = minimised.ok()?;
    let change: Vec<f64> = cz.iter().zip(&start).map(|(a, b)| 2.0 * (a - b)).collect();
    let moved: Vec<f64> = z
        .iter()
        .zip(t.prolong(&change))
        .map(|(a, d)| a + d)
        .collect();
    let lambda = s.options.smoothness;
    // Kept only if it helps (a NaN energy does not).
    if problem
        .energy(&moved, lambda)
        .partial_cmp(&problem.energy(z, lambda))
        != Some(std::cmp::Ordering::Less)
    {
        return None;
    }
    z.copy_from_slice(&moved);
    let (below_iterations, below_repeats) = below.unwrap_or((0, 0));
    Some((below_iterations + iterations, below_repeats + repeats))
}

pub(crate) fn solve(s: &Shading) -> Result<Solved> {
    let u = &s.u;
    let n = u.len();
    let problem = Problem::new(s)?;
    let mut assumptions = Vec::new();
    let mut warnings = Vec::new();
    let mut no_contour = false;
    let occluding_boundary = s.options.boundary != Boundary::Free;
    let mut z = vec![0.0; n];
    if let Some(given) = &s.start {
        z.copy_from_slice(given);
        assumptions.push(
            "the given start surface: the iteration refines it at the final smoothness (no \
             continuation in λ, no coarse-to-fine start, no repeats), so the result is the \
             solution nearest that surface"
                .to_string(),
        );
    } else if occluding_boundary && let Some(d) = distance_to_edge(u, &problem.cut) {
        let top = d.iter().cloned().fold(0.0, f64::max);
        for (zk, dk) in z.iter_mut().zip(&d) {
            *zk = (dk * (2.0 * top - dk)).max(0.0).sqrt();
        }
        assumptions.push(
            "convex: the iteration starts from a convex surface over the mask (a concave \
             surface with the same shading is not considered)"
                .to_string(),
        );
        if problem.cut.iter().any(|&b| b) {
            assumptions.push(
                "the start is convex from the outline's occluding part only: where the image \
                 is brighter than a surface turning away from the view can be, the outline is \
                 taken to cut across the surface"
                    .to_string(),
            );
        }
    } else {
        if occluding_boundary && s.rmap.slant_deg() > super::FRONTAL_SLANT_DEG {
            // Under a light at the viewer the stationary start is warned of below.
            no_contour = true;
        }
        assumptions.push(
            "the iteration starts from a plane facing the camera; with a light near the viewer \
             a bump and a dent explain the image equally well"
                .to_string(),
        );
    }
    if no_contour {
        warnings.push(
            "no part of the mask's outline inside the image is an occluding contour (the \
             surface fills the frame, or the image says the outline cuts across it), so \
             nothing fixes the shape's overall form but the smoothness and the flat start: the \
             result is one of many surfaces that explain the image (on rendered frame-filling \
             surfaces lit 20–30° off the view, 16 of 20 such solves were more than 5° or 5% \
             off); for depth to rely on, use the perspective method with a light near the \
             camera, or photometric stereo"
                .to_string(),
        );
    }
    let start = z.clone();
    let coarse = if s.options.coarse_to_fine && s.start.is_none() {
        from_half(&problem, &mut z)
    } else {
        None
    };
    if coarse.is_some() {
        assumptions.push(
            "coarse to fine: the start was solved at lower resolutions first (2×2 block means \
             of the image), then refined at full resolution at the final smoothness"
                .to_string(),
        );
    }
    // A given start is refined at the final λ, as a coarse level's result is.
    let refine_only = coarse.is_some() || s.start.is_some();
    s.progress
        .begin("shape from shading (Horn)", stage_total(s, !refine_only));
    let minimised = if !refine_only {
        problem.continued(&mut z, true, s.progress)
    } else {
        problem
            .minimise(&mut z, false, s.progress)
            .map(|(its, converged)| (its, converged, 0))
    };
    if minimised.is_err() {
        s.progress.end();
    }
    let (iterations, converged, repeats) = minimised?;
    let restarts = repeats + coarse.map_or(0, |(_, r)| r);
    let scale = start.iter().fold(1.0, |m: f64, v| m.max(v.abs()));
    let moved = z
        .iter()
        .zip(&start)
        .fold(0.0, |m: f64, (a, b)| m.max((a - b).abs()));
    // A start that already explains the image (a plane under a light it faces obliquely) is a
    // minimum, not a point the iteration could not leave: only a poor fit is flagged (the
    // residuals are evaluated only for a result that did not move).
    let poor = || {
        let lit: Vec<f64> = problem
            .data(&z)
            .iter()
            .zip(&problem.cells.shadow)
            .filter(|(_, sh)| !**sh)
            .map(|((r, _), _)| r.abs())
            .collect();
        !lit.is_empty() && lit.iter().sum::<f64>() / lit.len() as f64 > super::POOR_FIT
    };
    if z.iter().all(|v| v.is_finite()) && moved <= STATIONARY * scale && poor() {
        // Under a light at the viewer a plane facing the camera has R_p = R_q = 0 in every
        // cell: the energy's gradient is 0 there, and no step (nor a coarse level) leaves it.
        warnings.push(
            "the result is the start surface, unchanged: the energy does not change to first \
             order there (a plane facing a light at the viewer is such a point, where a bump \
             and a dent lower the energy alike), so the depth is not a reconstruction: light \
             the scene off the view axis, or use the perspective method (a point light with \
             its fall-off, well posed here)"
                .to_string(),
        );
    }
    let (p, q) = problem.pixel_gradients(&z);
    s.progress.end();
    Ok(Solved {
        p,
        q,
        z,
        normals: None,
        iterations,
        coarse_iterations: coarse.map_or(0, |(its, _)| its),
        restarts,
        converged,
        singular: 0,
        assumptions,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sfs::SfsOptions;
    use crate::sfs::reflectance_map::ReflectanceMap;
    use nalgebra::Vector3;

    /// The normal equations assembled into their compressed columns equal J_dᵀJ_d + λ SᵀS and
    /// J_dᵀ r − λ SᵀS z formed densely from the same rows, on a mask with a hole, a notch, a
    /// one-pixel spur and a lone pixel, with cells in shadow: every entry of the dense lower
    /// triangle is in the pattern, at its value.
    #[test]
    fn assembly_matches_dense_normal_equations() {
        let (w, h) = (11, 9);
        let mut mask = Grid::new(w, h, false);
        for r in 0..h {
            for c in 0..w {
                let hole = (3..5).contains(&r) && (4..6).contains(&c);
                let notch = r == 0 && c >= 7;
                let cut = c == 9 && r < 7;
                mask.data_mut()[r * w + c] = !(hole || notch || cut);
            }
        }
        // A spur one pixel wide, and a lone pixel.
        mask.data_mut()[8 * w + 10] = false;
        mask.data_mut()[2 * w + 10] = false;
        let u = Unknowns::new(&mask);
        let n = u.len();
        // A smooth surface's brightness, some of it at the shadow level.
        let z: Vec<f64> = (0..n)
            .map(|k| {
                let (r, c) = (
                    (u.pixel[k] as usize / w) as f64,
                    (u.pixel[k] as usize % w) as f64,
                );
                0.3 * (0.7 * c).sin() + 0.2 * (0.5 * r).cos() * c
            })
            .collect();
        let e: Vec<f64> = (0..n)
            .map(|k| {
                let (r, c) = (u.pixel[k] as usize / w, u.pixel[k] as usize % w);
                if r >= 5 && c <= 2 {
                    0.0
                } else {
                    0.2 + 0.6 * ((k * 37) % 11) as f64 / 11.0
                }
            })
            .collect();
        let options = SfsOptions::default();
        let shadow = e.iter().map(|&v| v <= options.shadow_level).collect();
        let rmap = ReflectanceMap::lambertian(Vector3::new(0.4, -0.3, 0.87)).unwrap();
        let s = Shading {
            u,
            e,
            shadow,
            rmap: &rmap,
            options: &options,
            progress: &crate::progress::Silent,
            start: None,
            occluding_tolerance: None,
        };
        let problem = Problem::new(&s).unwrap();
        assert!(problem.cells.shadow.iter().any(|&b| b));
        let lambda = 0.037;
        let mut values = vec![0.0; problem.row_idx.len()];
        let rhs = problem.assemble(&z, lambda, &mut values);
        let mut dense = vec![vec![0.0; n]; n];
        let mut dense_rhs = vec![0.0; n];
        for (c, (r0, coef)) in problem.data(&z).iter().enumerate() {
            let idx = problem.cells.corners[c];
            for a in 0..4 {
                dense_rhs[idx[a]] += coef[a] * r0;
                for b in 0..4 {
                    dense[idx[a]][idx[b]] += coef[a] * coef[b];
                }
            }
        }
        for row in &problem.smooth {
            let v = Problem::smooth_value(&z, row);
            for a in 0..8 {
                dense_rhs[row.0[a]] -= lambda * row.1[a] * v;
                for b in 0..8 {
                    dense[row.0[a]][row.0[b]] += lambda * row.1[a] * row.1[b];
                }
            }
        }
        let mut seen = vec![vec![false; n]; n];
        for i in 0..n {
            let column = problem.col_ptr[i]..problem.col_ptr[i + 1];
            for (&j, &v) in problem.row_idx[column.clone()].iter().zip(&values[column]) {
                assert!(j >= i, "entry ({j}, {i}) above the diagonal");
                assert!(!seen[j][i], "entry ({j}, {i}) twice");
                seen[j][i] = true;
                let d = (v - dense[j][i]).abs();
                assert!(d < 1e-12, "entry ({j}, {i}): {v} against {}", dense[j][i]);
            }
            assert!(seen[i][i], "diagonal {i} missing");
            assert!(
                (problem.diagonal[i] < problem.col_ptr[i + 1])
                    && problem.row_idx[problem.diagonal[i]] == i
            );
            for j in i..n {
                assert!(
                    seen[j][i] || dense[j][i] == 0.0,
                    "({j}, {i}) = {} is outside the pattern",
                    dense[j][i]
                );
            }
            assert!(
                (rhs[i] - dense_rhs[i]).abs() < 1e-12,
                "rhs {i}: {} against {}",
                rhs[i],
                dense_rhs[i]
            );
        }
    }
}
