//! Symmetric systems with the 5-point sparsity of the pixel grid, restricted to a mask, and their
//! solvers: a direct sparse Cholesky factorisation (faer) under a nested-dissection ordering, and
//! preconditioned conjugate gradients (Jacobi, or the DCT Neumann solve of the enclosing
//! rectangle, which is nearly exact for uniform-weight masked Laplacians).
//!
//! Every integration system is singular along one constant per connected part of the mask
//! (depth is known up to an offset there). The direct solver fixes one anchor pixel per part;
//! conjugate gradients work on the consistent singular system. Results are made zero-mean per
//! part.

use super::poisson::NeumannSolver;
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap, Window};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{
    SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, MatMut, Par, Side};
use rayon::prelude::*;
use serde::Serialize;

/// No neighbour / not an unknown.
pub(crate) const NONE: u32 = u32::MAX;

/// How the linear systems of the masked integrators are solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum LinearSolver {
    /// Direct up to 100 000 unknowns, iterative beyond: masked least squares by
    /// conjugate gradients preconditioned with multigrid on the pixel grid (bounded memory); the
    /// bilateral integrator's reweighting steps always by conjugate gradients preconditioned with
    /// multigrid on the pixel grid (Jacobi, as published, for its soft-weighted variant without
    /// re-integration), its final re-integration beyond the direct limit with multigrid that
    /// smooths on the pixel grid and corrects on aggregates that never join the two sides of a
    /// cut (`integrate/multigrid/blocks.rs`).
    #[default]
    Auto,
    /// Sparse Cholesky factorisation (exact; memory grows like n log n).
    Direct,
    /// Conjugate gradients with the simplest preconditioner that fits: the rectangle's DCT solve
    /// for masked least squares, Jacobi (as published) for the bilateral integrator.
    ConjugateGradient,
    /// Conjugate gradients preconditioned with multigrid (`integrate/multigrid/`): time and
    /// memory linear in n; for masked least squares and the bilateral integrator's reweighting
    /// steps on the pixel grid, for its re-integration the grid's smoothing with a coarse
    /// correction on aggregates that never join the two sides of a cut.
    Multigrid,
}

/// Largest system [`LinearSolver::Auto`] solves directly.
pub const DIRECT_MAX_UNKNOWNS: usize = 100_000;

impl LinearSolver {
    /// Whether a system of `n` unknowns is solved directly.
    pub(crate) fn direct_for(self, n: usize) -> bool {
        match self {
            LinearSolver::Auto => n <= DIRECT_MAX_UNKNOWNS,
            LinearSolver::Direct => true,
            LinearSolver::ConjugateGradient | LinearSolver::Multigrid => false,
        }
    }
}

/// How one linear system was solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum SolveMethod {
    /// Sparse Cholesky.
    Direct,
    /// Conjugate gradients, Jacobi preconditioner.
    JacobiCg,
    /// Conjugate gradients, DCT preconditioner.
    DctCg,
    /// Conjugate gradients, multigrid preconditioner.
    MultigridCg,
    /// Conjugate gradients preconditioned with multigrid on the pixel grid (2×2 blocks,
    /// `integrate/multigrid/grid.rs`): masked least squares in bounded memory, and the
    /// bilateral integrator's reweighting steps.
    GridMultigridCg,
    /// Conjugate gradients preconditioned with smoothing on the pixel grid and a coarse
    /// correction on aggregates that never join the two sides of a weak edge
    /// (`integrate/multigrid/blocks.rs`): the bilateral integrator's re-integration.
    BlockMultigridCg,
}

impl SolveMethod {
    /// A short name for messages and reports.
    pub fn name(self) -> &'static str {
        match self {
            SolveMethod::Direct => "direct",
            SolveMethod::JacobiCg => "jacobi-cg",
            SolveMethod::DctCg => "dct-cg",
            SolveMethod::MultigridCg => "multigrid-cg",
            SolveMethod::GridMultigridCg => "grid-multigrid-cg",
            SolveMethod::BlockMultigridCg => "block-multigrid-cg",
        }
    }
}

/// The unknowns of a masked system: one per domain pixel, in row-major order.
pub(crate) struct Unknowns {
    pub w: usize,
    pub h: usize,
    /// Pixel of each unknown.
    pub pixel: Vec<u32>,
    /// Unknown of the right / lower neighbour, or [`NONE`].
    pub right: Vec<u32>,
    pub down: Vec<u32>,
    /// Unknown of the left / upper neighbour, or [`NONE`].
    pub left: Vec<u32>,
    pub up: Vec<u32>,
    /// Connected part (4-neighbourhood) of each unknown.
    pub part: Vec<u32>,
    /// Number of parts.
    pub parts: usize,
}

impl Unknowns {
    pub fn new(domain: &Mask) -> Self {
        let (w, h) = (domain.width(), domain.height());
        let mut index = vec![NONE; w * h];
        let mut pixel = Vec::new();
        for (i, m) in domain.data().iter().enumerate() {
            if *m {
                index[i] = pixel.len() as u32;
                pixel.push(i as u32);
            }
        }
        let n = pixel.len();
        let at = |x: isize, y: isize| -> u32 {
            if x < 0 || y < 0 || x >= w as isize || y >= h as isize {
                NONE
            } else {
                index[y as usize * w + x as usize]
            }
        };
        let (mut right, mut down, mut left, mut up) =
            (vec![NONE; n], vec![NONE; n], vec![NONE; n], vec![NONE; n]);
        for (k, &p) in pixel.iter().enumerate() {
            let (x, y) = ((p as usize % w) as isize, (p as usize / w) as isize);
            right[k] = at(x + 1, y);
            down[k] = at(x, y + 1);
            left[k] = at(x - 1, y);
            up[k] = at(x, y - 1);
        }
        let mut part = vec![NONE; n];
        let mut parts = 0;
        let mut stack = Vec::new();
        for s in 0..n {
            if part[s] != NONE {
                continue;
            }
            part[s] = parts;
            stack.push(s as u32);
            while let Some(k) = stack.pop() {
                let k = k as usize;
                for nb in [right[k], down[k], left[k], up[k]] {
                    if nb != NONE && part[nb as usize] == NONE {
                        part[nb as usize] = parts;
                        stack.push(nb);
                    }
                }
            }
            parts += 1;
        }
        Unknowns {
            w,
            h,
            pixel,
            right,
            down,
            left,
            up,
            part,
            parts: parts as usize,
        }
    }

    /// The unknowns' bounding box (a window of one cell when there are none).
    pub fn window(&self) -> Window {
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
        for &p in &self.pixel {
            let (x, y) = (p as usize % self.w, p as usize / self.w);
            x0 = x0.min(x);
            y0 = y0.min(y);
            x1 = x1.max(x + 1);
            y1 = y1.max(y + 1);
        }
        if self.pixel.is_empty() {
            Window::full(1, 1)
        } else {
            Window { x0, y0, x1, y1 }
        }
    }

    pub fn len(&self) -> usize {
        self.pixel.len()
    }

    /// Subtracts each part's mean.
    pub fn zero_mean_parts(&self, z: &mut [f64]) {
        let mut sum = vec![0f64; self.parts];
        let mut count = vec![0usize; self.parts];
        for (k, v) in z.iter().enumerate() {
            sum[self.part[k] as usize] += v;
            count[self.part[k] as usize] += 1;
        }
        for (k, v) in z.iter_mut().enumerate() {
            let p = self.part[k] as usize;
            *v -= sum[p] / count[p] as f64;
        }
    }

    /// Whether each pixel of the image (row-major) is an unknown.
    pub fn inside(&self) -> Vec<bool> {
        let mut inside = vec![false; self.w * self.h];
        for &p in &self.pixel {
            inside[p as usize] = true;
        }
        inside
    }

    /// Scatters per-unknown values into a map, NaN elsewhere.
    pub fn to_map(&self, z: &[f64]) -> ScalarMap {
        let mut out = Grid::new(self.w, self.h, f32::NAN);
        for (k, &p) in self.pixel.iter().enumerate() {
            out.data_mut()[p as usize] = z[k] as f32;
        }
        out
    }
}

/// A symmetric matrix with the grid's 5-point sparsity: `diag[i]`, and the entries coupling
/// unknown i to its right (`right[i]`) and lower (`down[i]`) neighbours.
pub(crate) struct Stencil {
    pub diag: Vec<f64>,
    pub right: Vec<f64>,
    pub down: Vec<f64>,
}

impl Stencil {
    pub fn zeros(n: usize) -> Self {
        Stencil {
            diag: vec![0.0; n],
            right: vec![0.0; n],
            down: vec![0.0; n],
        }
    }

    /// Adds the least-squares equation √weight·(x_j − x_i) = rhs_term/√weight for the edge from
    /// unknown i to its right (`along_rows`) or lower neighbour j: `weight` to the matrix, and
    /// ∓`rhs_term` (weight × the edge's difference) to `rhs` at i and j.
    pub fn add_edge(
        &mut self,
        rhs: &mut [f64],
        (i, j): (usize, usize),
        along_rows: bool,
        weight: f64,
        rhs_term: f64,
    ) {
        self.diag[i] += weight;
        self.diag[j] += weight;
        if along_rows {
            self.right[i] -= weight;
        } else {
            self.down[i] -= weight;
        }
        rhs[i] -= rhs_term;
        rhs[j] += rhs_term;
    }

    /// Row `i` of A x.
    #[inline(always)]
    fn row(&self, u: &Unknowns, x: &[f64], i: usize) -> f64 {
        let mut s = self.diag[i] * x[i];
        let r = u.right[i];
        if r != NONE {
            s += self.right[i] * x[r as usize];
        }
        let d = u.down[i];
        if d != NONE {
            s += self.down[i] * x[d as usize];
        }
        let l = u.left[i];
        if l != NONE {
            s += self.right[l as usize] * x[l as usize];
        }
        let t = u.up[i];
        if t != NONE {
            s += self.down[t as usize] * x[t as usize];
        }
        s
    }

    /// y = A x.
    pub fn apply(&self, u: &Unknowns, x: &[f64], y: &mut [f64]) {
        y.par_iter_mut()
            .enumerate()
            .for_each(|(i, yi)| *yi = self.row(u, x, i));
    }

    /// y = A x, and xᵀy as [`dot`] sums it (the same chunks, each added in order), in one pass
    /// over the vectors instead of two.
    pub fn apply_dot(&self, u: &Unknowns, x: &[f64], y: &mut [f64]) -> f64 {
        let chunk = |k: usize, y: &mut [f64]| -> f64 {
            let first = k * DOT_CHUNK;
            for (j, yi) in y.iter_mut().enumerate() {
                *yi = self.row(u, x, first + j);
            }
            x[first..].iter().zip(y.iter()).map(|(&x, &y)| x * y).sum()
        };
        if y.len() <= DOT_CHUNK {
            return chunk(0, y);
        }
        let partial: Vec<f64> = y
            .par_chunks_mut(DOT_CHUNK)
            .enumerate()
            .map(|(k, y)| chunk(k, y))
            .collect();
        partial.iter().sum()
    }
}

/// A nested-dissection ordering of the unknowns by recursive coordinate bisection: each region
/// is split along its longer side by `width` lines of pixels at the median, which separate it
/// when the matrix couples unknowns at most `width` pixels apart along an axis (one line for a
/// 4-connected grid); the separator is numbered after both halves (George 1973). See
/// [`nested_dissection_of`].
pub(crate) fn nested_dissection(u: &Unknowns, width: u32) -> Vec<usize> {
    let coords: Vec<(u32, u32)> = u
        .pixel
        .iter()
        .map(|&p| ((p as usize % u.w) as u32, (p as usize / u.w) as u32))
        .collect();
    nested_dissection_of(&coords, width)
}

/// The same ordering for unknowns at pixel positions `coords` (column, row) coupled up to
/// `width` pixels apart along each axis: the separators are `width` lines of pixels thick.
pub(crate) fn nested_dissection_of(coords: &[(u32, u32)], width: u32) -> Vec<usize> {
    let mut order = Vec::with_capacity(coords.len());
    let mut todo: Vec<Vec<u32>> = vec![(0..coords.len() as u32).collect()];
    // Iterative post-order: regions are emitted as (halves…, separator) by pushing markers.
    enum Task {
        Split(Vec<u32>),
        Emit(Vec<u32>),
    }
    let mut stack = vec![Task::Split(todo.pop().unwrap_or_default())];
    while let Some(task) = stack.pop() {
        match task {
            Task::Emit(v) => order.extend(v.into_iter().map(|k| k as usize)),
            Task::Split(set) => {
                if set.len() <= 64 {
                    order.extend(set.into_iter().map(|k| k as usize));
                    continue;
                }
                let (mut x0, mut x1, mut y0, mut y1) = (u32::MAX, 0, u32::MAX, 0);
                for &k in &set {
                    let (x, y) = coords[k as usize];
                    x0 = x0.min(x);
                    x1 = x1.max(x);
                    y0 = y0.min(y);
                    y1 = y1.max(y);
                }
                let vertical = x1 - x0 >= y1 - y0;
                let key = |k: u32| {
                    if vertical {
                        coords[k as usize].0
                    } else {
                        coords[k as usize].1
                    }
                };
                let mut keys: Vec<u32> = set.iter().map(|&k| key(k)).collect();
                let mid = keys.len() / 2;
                let (_, m, _) = keys.select_nth_unstable(mid);
                let m = *m;
                let (mut lo, mut hi, mut sep) = (Vec::new(), Vec::new(), Vec::new());
                for k in set {
                    let v = key(k);
                    if v < m {
                        lo.push(k);
                    } else if v >= m + width {
                        hi.push(k);
                    } else {
                        sep.push(k);
                    }
                }
                // Processed in stack order: lo, then hi, then the separator.
                stack.push(Task::Emit(sep));
                stack.push(Task::Split(hi));
                stack.push(Task::Split(lo));
            }
        }
    }
    order
}

/// A sparse Cholesky factorisation of stencils with the sparsity of `Unknowns`, analysed once
/// (ordering and symbolic factorisation) and refactorised numerically for each new matrix.
pub(crate) struct Direct {
    /// Which of (right, down) each column stores below its diagonal.
    neighbours: Vec<(bool, bool)>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    symbolic: SymbolicCholesky<usize>,
    /// One unknown per part, pinned by adding 1 to its diagonal.
    anchors: Vec<usize>,
}

/// The symbolic Cholesky factorisation of the symmetric matrices whose lower triangle has the
/// pattern (`col_ptr`, `row_idx`; rows sorted in each column), in the fill-reducing `order`.
///
/// # Errors
/// [`Error::InvalidParameter`] (`solver`) when faer refuses the pattern.
pub(crate) fn symbolic_cholesky(
    col_ptr: &[usize],
    row_idx: &[usize],
    order: Vec<usize>,
) -> Result<SymbolicCholesky<usize>> {
    let n = order.len();
    let mut inverse = vec![0usize; n];
    for (k, &p) in order.iter().enumerate() {
        inverse[p] = k;
    }
    let sym = SymbolicSparseColMat::new_checked(n, n, col_ptr.to_vec(), None, row_idx.to_vec());
    let perm = faer::perm::PermRef::new_checked(&order, &inverse, n);
    factorize_symbolic_cholesky(
        sym.as_ref(),
        Side::Lower,
        SymmetricOrdering::Custom(perm),
        Default::default(),
    )
    .map_err(faer_err)
}

/// The memory of a sequence of sparse Cholesky factorisations with one symbolic analysis (the
/// Gauss–Newton steps of the shape-from-shading solvers): the factor's values and the scratch
/// of the factorisation and of the solve, allocated once rather than for every matrix. At
/// 65 000 unknowns the factor holds about 10⁷ values (77 MB), which a fresh allocation maps and
/// faults in again at every step.
pub(crate) struct CholeskyWork {
    l_values: Vec<f64>,
    factor_mem: MemBuffer,
    solve_mem: MemBuffer,
    par: Par,
}

impl CholeskyWork {
    /// Memory for the factorisations analysed by `symbolic`, run with `par`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`solver`) when the scratch cannot be allocated.
    pub(crate) fn new(symbolic: &SymbolicCholesky<usize>, par: Par) -> Result<Self> {
        let (factor_mem, solve_mem) = llt_scratch::<f64>(symbolic, par)?;
        Ok(CholeskyWork {
            l_values: crate::buffer::zeroed_f64(symbolic.len_val()),
            factor_mem,
            solve_mem,
            par,
        })
    }

    /// Factorises the symmetric positive definite matrix whose lower triangle has the pattern
    /// (`col_ptr`, `row_idx`) analysed by `symbolic` (the one this memory was made for) and the
    /// `values`, and solves A x = b in place (`x` holds b on entry).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`solver`) when the factorisation fails (the matrix is not
    /// positive definite).
    pub(crate) fn solve(
        &mut self,
        symbolic: &SymbolicCholesky<usize>,
        col_ptr: &[usize],
        row_idx: &[usize],
        values: &[f64],
        x: &mut [f64],
    ) -> Result<()> {
        let llt = factorize(
            symbolic,
            &mut self.l_values,
            &mut self.factor_mem,
            self.par,
            (col_ptr, row_idx, values),
        )?;
        solve_with(&llt, x, &mut self.solve_mem, self.par);
        Ok(())
    }
}

/// The scratch of a numeric factorisation and of a solve in `T`, for the analysis `symbolic`.
fn llt_scratch<T: faer::traits::ComplexField>(
    symbolic: &SymbolicCholesky<usize>,
    par: Par,
) -> Result<(MemBuffer, MemBuffer)> {
    Ok((
        MemBuffer::try_new(symbolic.factorize_numeric_llt_scratch::<T>(par, Default::default()))
            .map_err(faer_err)?,
        MemBuffer::try_new(symbolic.solve_in_place_scratch::<T>(1, par)).map_err(faer_err)?,
    ))
}

/// The numeric factorisation, into `l_values`, of the matrix whose lower triangle is (`col_ptr`,
/// `row_idx`, `values`) with the analysis `symbolic`.
fn factorize<'a, T: faer::traits::ComplexField>(
    symbolic: &'a SymbolicCholesky<usize>,
    l_values: &'a mut [T],
    mem: &mut MemBuffer,
    par: Par,
    (col_ptr, row_idx, values): (&[usize], &[usize], &[T]),
) -> Result<faer::sparse::linalg::cholesky::LltRef<'a, usize, T>> {
    let n = col_ptr.len() - 1;
    let mat = SparseColMatRef::new(
        faer::sparse::SymbolicSparseColMatRef::new_checked(n, n, col_ptr, None, row_idx),
        values,
    );
    symbolic
        .factorize_numeric_llt(
            l_values,
            mat,
            Side::Lower,
            Default::default(),
            par,
            MemStack::new(mem),
            Default::default(),
        )
        .map_err(faer_err)
}

/// Solves L Lᴴ x = b in place with the factor `llt` (`x` holds b on entry).
fn solve_with<T: faer::traits::ComplexField>(
    llt: &faer::sparse::linalg::cholesky::LltRef<'_, usize, T>,
    x: &mut [T],
    mem: &mut MemBuffer,
    par: Par,
) {
    let n = x.len();
    llt.solve_in_place_with_conj(
        Conj::No,
        MatMut::from_column_major_slice_mut(x, n, 1),
        par,
        MemStack::new(mem),
    );
}

/// [`CholeskyWork`] in single precision, for the Gauss–Newton steps of the shape-from-shading
/// solvers, whose steps a line search then measures on the energy itself: the matrix is rounded
/// to `f32`, factorised and solved in `f32` (half the memory traffic and twice the SIMD width of
/// the factorisation, which is most of a step's time), and the solution is refined once in
/// `f64` (Wilkinson's iterative refinement: the residual b − A x in `f64`, its correction solved
/// with the same factor), which brings it to `f64` accuracy where cond(A) · 2⁻²⁴ ≪ 1.
pub(crate) struct CholeskyWorkF32 {
    l_values: Vec<f32>,
    values: Vec<f32>,
    x: Vec<f32>,
    factor_mem: MemBuffer,
    solve_mem: MemBuffer,
    par: Par,
}

impl CholeskyWorkF32 {
    /// Memory for the factorisations analysed by `symbolic`, run with `par`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`solver`) when the scratch cannot be allocated.
    pub(crate) fn new(symbolic: &SymbolicCholesky<usize>, par: Par) -> Result<Self> {
        let (factor_mem, solve_mem) = llt_scratch::<f32>(symbolic, par)?;
        Ok(CholeskyWorkF32 {
            l_values: vec![0.0; symbolic.len_val()],
            values: Vec::new(),
            x: Vec::new(),
            factor_mem,
            solve_mem,
            par,
        })
    }

    /// As [`CholeskyWork::solve`]: A x = b in place for the lower triangle (`col_ptr`,
    /// `row_idx`, `values`), factorised in `f32` and refined once in `f64`. Returns the
    /// refinement's correction relative to the solution (‖δx‖ / ‖x‖; 0 for b = 0).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`solver`) when the factorisation fails (the matrix rounded
    /// to `f32` is not positive definite).
    pub(crate) fn solve(
        &mut self,
        symbolic: &SymbolicCholesky<usize>,
        col_ptr: &[usize],
        row_idx: &[usize],
        values: &[f64],
        x: &mut [f64],
    ) -> Result<f64> {
        let n = x.len();
        self.values.clear();
        self.values.extend(values.iter().map(|&v| v as f32));
        let llt = factorize(
            symbolic,
            &mut self.l_values,
            &mut self.factor_mem,
            self.par,
            (col_ptr, row_idx, &self.values),
        )?;
        let b = x.to_vec();
        // Right-hand sides are rounded to f32 scaled to a largest entry of 1, so that tiny or
        // huge ones keep their digits; the solution is scaled back.
        let s = scaled_f32(&b, &mut self.x);
        solve_with(&llt, &mut self.x, &mut self.solve_mem, self.par);
        for (xi, &v) in x.iter_mut().zip(&self.x) {
            *xi = s * f64::from(v);
        }
        // One refinement (Wilkinson): r = b − A x with A's lower triangle read both ways, then
        // x += A⁻¹ r with the same factor. More refinements cost as much as they saved: at
        // 65 000 unknowns the shape-from-shading systems needed all of up to four to reach 10⁻¹²,
        // and the steps were then as slow as in `f64` (`bench sfs --size 256`).
        let mut r = b;
        for i in 0..n {
            for t in col_ptr[i]..col_ptr[i + 1] {
                let (j, a) = (row_idx[t], values[t]);
                r[j] -= a * x[i];
                if j != i {
                    r[i] -= a * x[j];
                }
            }
        }
        let s = scaled_f32(&r, &mut self.x);
        solve_with(&llt, &mut self.x, &mut self.solve_mem, self.par);
        let (mut change, mut size) = (0.0, 0.0);
        for (xi, &v) in x.iter_mut().zip(&self.x) {
            let d = s * f64::from(v);
            change += d * d;
            *xi += d;
            size += *xi * *xi;
        }
        Ok(if size == 0.0 {
            // x = 0 (b = 0): exact, unless the correction is not finite.
            if change == 0.0 { 0.0 } else { f64::INFINITY }
        } else {
            (change / size).sqrt()
        })
    }
}

/// `v` divided by its largest magnitude, rounded to `f32` into `out`; returns that magnitude
/// (1 when `v` is all zeros or not finite, which then rounds as it is).
fn scaled_f32(v: &[f64], out: &mut Vec<f32>) -> f64 {
    let top = v.iter().fold(0.0, |m: f64, a| m.max(a.abs()));
    let s = if top > 0.0 && top.is_finite() {
        top
    } else {
        1.0
    };
    out.clear();
    out.extend(v.iter().map(|&a| (a / s) as f32));
    s
}

/// The sparse Cholesky solves of a sequence of Gauss–Newton steps, in mixed precision: each
/// system is factorised in `f32` and refined once in `f64` ([`CholeskyWorkF32`]); when that
/// fails (the rounded matrix is not positive definite, or the solution is not finite) or the
/// refinement's correction exceeds [`MIXED_TOLERANCE`] of the solution (so ill-conditioned
/// that one refinement may not suffice), the system is solved again in `f64`
/// ([`CholeskyWork`], allocated the first time it is needed).
pub(crate) struct MixedCholesky {
    single: CholeskyWorkF32,
    double: Option<CholeskyWork>,
    par: Par,
    /// Systems solved again in `f64`.
    pub fallbacks: usize,
}

/// The largest relative correction of the `f32` solution's refinement that is accepted: a
/// refinement shrinks the error by about its correction's relative size, so 10⁻² leaves the
/// solution within about 10⁻⁴ of the exact one, under what the line search that follows a
/// Gauss–Newton step can tell; a larger one (cond(A) · 2⁻²⁴ not ≪ 1) sends the system to `f64`.
pub(crate) const MIXED_TOLERANCE: f64 = 1e-2;

impl MixedCholesky {
    /// Memory for the factorisations analysed by `symbolic`, run with `par`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`solver`) when the scratch cannot be allocated.
    pub(crate) fn new(symbolic: &SymbolicCholesky<usize>, par: Par) -> Result<Self> {
        Ok(MixedCholesky {
            single: CholeskyWorkF32::new(symbolic, par)?,
            double: None,
            par,
            fallbacks: 0,
        })
    }

    /// As [`CholeskyWork::solve`].
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`solver`) when the factorisation fails in `f64` too.
    pub(crate) fn solve(
        &mut self,
        symbolic: &SymbolicCholesky<usize>,
        col_ptr: &[usize],
        row_idx: &[usize],
        values: &[f64],
        x: &mut [f64],
    ) -> Result<()> {
        let b = x.to_vec();
        let single = self.single.solve(symbolic, col_ptr, row_idx, values, x);
        if matches!(single, Ok(c) if c <= MIXED_TOLERANCE) && x.iter().all(|v| v.is_finite()) {
            return Ok(());
        }
        self.fallbacks += 1;
        x.copy_from_slice(&b);
        let double = match &mut self.double {
            Some(d) => d,
            None => self.double.insert(CholeskyWork::new(symbolic, self.par)?),
        };
        double.solve(symbolic, col_ptr, row_idx, values, x)
    }
}

/// A faer factorisation error as the crate's error (parameter `solver`).
fn faer_err(e: impl std::fmt::Display) -> Error {
    Error::param("solver", format!("sparse factorisation failed: {e}"))
}

impl Direct {
    pub fn new(u: &Unknowns) -> Result<Self> {
        let n = u.len();
        // Lower triangle, column j: the diagonal, then the right and lower neighbours (both have
        // larger indices in row-major order, right before lower).
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(3 * n);
        let mut neighbours = Vec::with_capacity(n);
        col_ptr.push(0);
        for j in 0..n {
            row_idx.push(j);
            for nb in [u.right[j], u.down[j]] {
                if nb != NONE {
                    row_idx.push(nb as usize);
                }
            }
            neighbours.push((u.right[j] != NONE, u.down[j] != NONE));
            col_ptr.push(row_idx.len());
        }
        let symbolic = symbolic_cholesky(&col_ptr, &row_idx, nested_dissection(u, 1))?;
        let mut anchors = vec![usize::MAX; u.parts];
        for k in 0..n {
            let p = u.part[k] as usize;
            if anchors[p] == usize::MAX {
                anchors[p] = k;
            }
        }
        Ok(Direct {
            neighbours,
            col_ptr,
            row_idx,
            symbolic,
            anchors,
        })
    }

    /// Solves A x = b (A with this pattern; each part pinned at its anchor).
    pub fn solve(&self, a: &Stencil, b: &[f64]) -> Result<Vec<f64>> {
        let mut values = Vec::with_capacity(self.row_idx.len());
        let mut diag = a.diag.clone();
        for &k in &self.anchors {
            diag[k] += 1.0;
        }
        for (j, &(right, down)) in self.neighbours.iter().enumerate() {
            values.push(diag[j]);
            if right {
                values.push(a.right[j]);
            }
            if down {
                values.push(a.down[j]);
            }
        }
        let mut x = b.to_vec();
        CholeskyWork::new(&self.symbolic, Par::rayon(0))?.solve(
            &self.symbolic,
            &self.col_ptr,
            &self.row_idx,
            &values,
            &mut x,
        )?;
        Ok(x)
    }
}

/// Solves the consistent system A x = b by `method`: the sparse factorisation, or conjugate
/// gradients from the initial `x` until `stop` with the method's preconditioner. Returns the
/// conjugate-gradient iterations (0 for the direct solver) and why the solve stopped.
///
/// # Errors
/// [`Error::InvalidParameter`] when the sparse factorisation fails.
pub(crate) fn solve(
    u: &Unknowns,
    a: &Stencil,
    b: &[f64],
    x: &mut Vec<f64>,
    method: SolveMethod,
    stop: Stop,
) -> Result<(usize, Convergence)> {
    let (dct, multigrid, blocks);
    let pre = match method {
        SolveMethod::Direct => {
            *x = Direct::new(u)?.solve(a, b)?;
            return Ok((0, Convergence::Exact));
        }
        SolveMethod::JacobiCg => Preconditioner::Jacobi,
        SolveMethod::DctCg => {
            dct = NeumannSolver::new(u.w, u.h);
            Preconditioner::Dct(&dct)
        }
        SolveMethod::BlockMultigridCg => {
            blocks = super::multigrid::blocks::BlockPreconditioner::new(u, a, u.window());
            Preconditioner::Blocks(&blocks)
        }
        // The grid solve of masked least squares takes its own system (`masked.rs`), and the
        // bilateral steps build their grid preconditioner themselves; here, on a stencil, the
        // hierarchy is the algebraic one.
        SolveMethod::MultigridCg | SolveMethod::GridMultigridCg => {
            multigrid = super::multigrid::Multigrid::new(u, a);
            Preconditioner::Multigrid(&multigrid)
        }
    };
    Ok(pcg(u, a, b, x, &pre, stop))
}

/// Preconditioners for [`pcg`].
pub(crate) enum Preconditioner<'a> {
    /// Divide by the diagonal.
    Jacobi,
    /// The DCT Neumann solve on the enclosing w×h grid (for uniform-weight Laplacians).
    Dct(&'a NeumannSolver),
    /// One V-cycle of aggregation multigrid (`integrate/multigrid/mod.rs`).
    Multigrid(&'a super::multigrid::Multigrid),
    /// One cycle of the grid multigrid on the unknowns' bounding box
    /// (`integrate/multigrid/grid.rs`).
    Grid(&'a super::multigrid::grid::GridPreconditioner),
    /// One cycle of grid smoothing on the unknowns' bounding box with a coarse correction on
    /// aggregates that follow the weights (`integrate/multigrid/blocks.rs`).
    Blocks(&'a super::multigrid::blocks::BlockPreconditioner),
}

/// Elements summed per chunk of [`dot`] (and of other sums that must not depend on the thread
/// count): a fixed partition of the vectors.
pub(crate) const DOT_CHUNK: usize = 1 << 14;

/// p·q, summed in parallel over fixed chunks whose partial sums are then added in order, so
/// the result does not depend on the thread count or on how rayon's work stealing split the
/// work (a plain parallel sum does, and made the depth of every solve by conjugate gradients
/// change in its last bits from run to run).
pub(crate) fn dot<P, Q>(p: &[P], q: &[Q]) -> f64
where
    P: Copy + Into<f64> + Sync,
    Q: Copy + Into<f64> + Sync,
{
    // One chunk: the same sum, without the parallel machinery (the grid multigrid's coarse
    // levels call this often on short vectors).
    if p.len() <= DOT_CHUNK {
        return p.iter().zip(q).map(|(&x, &y)| x.into() * y.into()).sum();
    }
    let partial: Vec<f64> = p
        .par_chunks(DOT_CHUNK)
        .zip(q.par_chunks(DOT_CHUNK))
        .map(|(a, b)| {
            a.iter()
                .zip(b)
                .map(|(&x, &y)| x.into() * y.into())
                .sum::<f64>()
        })
        .collect();
    partial.iter().sum()
}

/// A step of conjugate gradients on the iterate and the residual: `x += α p` and `r −= α ap`
/// (ap = A p), the residual's previous values first copied into `r_prev` when it is given;
/// returns |r|² as [`dot`] sums it. One pass over the vectors instead of four.
fn cg_step(
    x: &mut [f64],
    r: &mut [f64],
    r_prev: Option<&mut [f64]>,
    (p, ap): (&[f64], &[f64]),
    alpha: f64,
) -> f64 {
    let chunk = |x: &mut [f64], r: &mut [f64], prev: Option<&mut [f64]>, p: &[f64], ap: &[f64]| {
        if let Some(prev) = prev {
            prev.copy_from_slice(r);
        }
        for (x, p) in x.iter_mut().zip(p) {
            *x += alpha * p;
        }
        for (r, ap) in r.iter_mut().zip(ap) {
            *r -= alpha * ap;
        }
        r.iter().map(|&v| v * v).sum::<f64>()
    };
    if x.len() <= DOT_CHUNK {
        return chunk(x, r, r_prev, p, ap);
    }
    let pieces = x
        .par_chunks_mut(DOT_CHUNK)
        .zip(r.par_chunks_mut(DOT_CHUNK))
        .zip(p.par_chunks(DOT_CHUNK).zip(ap.par_chunks(DOT_CHUNK)));
    let partial: Vec<f64> = match r_prev {
        Some(prev) => pieces
            .zip(prev.par_chunks_mut(DOT_CHUNK))
            .map(|(((x, r), (p, ap)), prev)| chunk(x, r, Some(prev), p, ap))
            .collect(),
        None => pieces
            .map(|((x, r), (p, ap))| chunk(x, r, None, p, ap))
            .collect(),
    };
    partial.iter().sum()
}

/// rᵀz and zᵀr_prev, each as [`dot`] sums it, in one pass.
fn dots_with(r: &[f64], z: &[f64], r_prev: &[f64]) -> [f64; 2] {
    let chunk = |r: &[f64], z: &[f64], prev: &[f64]| {
        [
            r.iter().zip(z).map(|(&r, &z)| r * z).sum::<f64>(),
            z.iter().zip(prev).map(|(&z, &q)| z * q).sum::<f64>(),
        ]
    };
    if r.len() <= DOT_CHUNK {
        return chunk(r, z, r_prev);
    }
    let partial: Vec<[f64; 2]> = r
        .par_chunks(DOT_CHUNK)
        .zip(z.par_chunks(DOT_CHUNK))
        .zip(r_prev.par_chunks(DOT_CHUNK))
        .map(|((r, z), prev)| chunk(r, z, prev))
        .collect();
    [
        partial.iter().map(|s| s[0]).sum(),
        partial.iter().map(|s| s[1]).sum(),
    ]
}

/// Why a linear solve stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum Convergence {
    /// Solved exactly (the sparse factorisation).
    Exact,
    /// Conjugate gradients reached their relative residual.
    Residual,
    /// Conjugate gradients stopped once the algebraic error was estimated below a tenth of the
    /// data's own uncertainty (the least-squares misfit rule of masked least squares; see
    /// docs/integration.md, "Stopping at the data's noise").
    DataNoise,
    /// Conjugate gradients reached their iteration limit without converging.
    IterationLimit,
    /// Conjugate gradients broke down (a search direction of no positive energy, by rounding)
    /// before converging.
    Breakdown,
}

impl Convergence {
    /// Whether the solve converged (exactly, to its residual, or to the data's noise).
    pub fn converged(self) -> bool {
        matches!(
            self,
            Convergence::Exact | Convergence::Residual | Convergence::DataNoise
        )
    }

    /// A short description, e.g. for a report line.
    pub fn describe(self) -> &'static str {
        match self {
            Convergence::Exact => "exact",
            Convergence::Residual => "to its relative residual",
            Convergence::DataNoise => "at the data's noise",
            Convergence::IterationLimit => "at its iteration limit, not converged",
            Convergence::Breakdown => "by breakdown, not converged",
        }
    }
}

/// Share of the data's own uncertainty, in every direction of the solution, that the
/// algebraic error may keep when conjugate gradients stop by [`Stop::data`].
pub(crate) const NOISE_SHARE: f64 = 0.1;

/// The least-squares problem behind a system, for [`Stop::data`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LeastSquares {
    /// |W^½ d|²: the weighted data's squared norm.
    pub norm2: f64,
    /// Equations less independent unknowns (edges − unknowns + connected parts): the misfit of
    /// the exact solution over it estimates the variance of one equation's error.
    pub redundancy: usize,
}

/// When conjugate gradients stop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Stop {
    /// At a relative residual |r| ≤ `tol`·|b|.
    pub tol: f64,
    /// After this many iterations at most.
    pub max_iter: usize,
    /// The least-squares problem, when the system is the normal equations DᵀWD x = DᵀWd of
    /// min F(x) = |W^½(Dx − d)|²: the solve then also stops as soon as the misfit the iterate
    /// could still shed, F(x) − F(x*) = |x − x*|²_A, is estimated at most
    /// [`NOISE_SHARE`]² σ̂², with σ̂² = F(x)/redundancy the variance of one equation's error.
    ///
    /// Why that is enough: with errors of variance σ² on the equations, the component of the
    /// exact solution x* along an eigenvector of A (eigenvalue λ) is uncertain by σ/√λ; an
    /// algebraic error e with |e|²_A ≤ s²σ² has each such component below s·σ/√λ, at most
    /// s = [`NOISE_SHARE`] of that component's own uncertainty, whatever the size of the
    /// problem. It is the criterion of Arioli, "A stopping criterion for the conjugate gradient
    /// algorithm in a finite element method framework" (Numer. Math. 2004) — stop once the
    /// algebraic error is below the discretisation error — with the data's error in that
    /// place; σ̂² holds the quadrature's discretisation error as well as the noise. Where the
    /// gradients are integrable (F(x*) ≈ 0) it never applies, and the relative residual
    /// decides alone.
    ///
    /// The estimate: the misfit a step of conjugate gradients removes, α rᵀz, is exactly
    /// F(x_k) − F(x_{k+1}) (for the flexible method too: pᵀr = rᵀz follows from α alone), and
    /// it bounds from below what x_k could still shed (Hestenes & Stiefel 1952, §6; that this
    /// bound is tight in finite precision, for the standard method: Strakoš & Tichý, "On error
    /// estimation in the conjugate gradient method and why it works in finite precision
    /// computations", ETNA 2002). What x_{k+1} could still shed is then extrapolated: while
    /// these steps shrink geometrically by a ratio q < ½ (multigrid gives q ≈ 0.03–0.15), it is
    /// about the tail of that series, α rᵀz · q/(1 − q), with q the larger of the last two
    /// ratios so that slowing convergence is not taken for fast. An extrapolation, not a
    /// bound: convergence that slows down after two fast steps would be underestimated
    /// (measured in the unit tests: the iterate returned could still shed 1.3–73% of the
    /// allowance).
    pub data: Option<LeastSquares>,
}

/// The misfit F(x) of [`Stop::data`] along the iterates, kept from F(x₀) by the misfit each
/// step removes.
pub(crate) struct Misfit {
    /// F of the present iterate.
    value: f64,
    /// Below this F is rounding: |d|² is summed once and each step subtracts with an error of
    /// about 10⁻¹⁶ of it (more where the steps' directions are rounded to `f32`, about 10⁻⁸ of
    /// each step's decrease), so F is trusted only above 10⁻¹² of |d|².
    floor: f64,
    /// [`LeastSquares::redundancy`].
    redundancy: f64,
    /// The misfit the last step removed, and the ratio of it to the one before.
    last: Option<(f64, f64)>,
}

impl Misfit {
    /// From F(x₀) = |d|² − x₀ᵀb − x₀ᵀr₀ (F = xᵀAx − 2xᵀb + |d|² and Ax = b − r).
    pub(crate) fn new(problem: LeastSquares, x0_b: f64, x0_r: f64) -> Self {
        Misfit {
            value: problem.norm2 - x0_b - x0_r,
            floor: 1e-12 * problem.norm2,
            redundancy: problem.redundancy as f64,
            last: None,
        }
    }

    /// Takes a step that removed `removed` (α rᵀz); whether the new iterate is done (see
    /// [`Stop::data`]).
    pub(crate) fn step(&mut self, removed: f64) -> bool {
        self.value -= removed;
        let (q, done) = match self.last {
            None => (f64::INFINITY, false),
            Some((last, q_last)) => {
                let q = removed / last;
                let worst = q.max(q_last);
                let done = self.redundancy > 0.0
                    && self.value > self.floor
                    && (0.0..0.5).contains(&worst)
                    && removed * worst / (1.0 - worst)
                        <= NOISE_SHARE * NOISE_SHARE * self.value / self.redundancy;
                (q, done)
            }
        };
        self.last = Some((removed, q));
        done
    }
}

/// Preconditioned conjugate gradients for the consistent, positive semidefinite system
/// A x = b (b is made zero-mean per part first), from the initial `x`, until `stop`. Returns
/// the iterations used.
pub(crate) fn pcg(
    u: &Unknowns,
    a: &Stencil,
    b: &[f64],
    x: &mut [f64],
    pre: &Preconditioner,
    stop: Stop,
) -> (usize, Convergence) {
    pcg_in(u, a, b, x, pre, stop, &mut PcgWork::default())
}

/// The vectors of [`pcg_in`], kept between solves of systems on the same unknowns (the
/// bilateral integrator's reweighting steps): on large images fresh vectors for every solve
/// cost page faults, the kernel clearing each new page, about 15% of a step at 1024².
#[derive(Default)]
pub(crate) struct PcgWork {
    b: Vec<f64>,
    ax: Vec<f64>,
    r: Vec<f64>,
    r_prev: Vec<f64>,
    z: Vec<f64>,
    p: Vec<f64>,
    ap: Vec<f64>,
    /// The grid preconditioner's scratch, from the last solve that used one.
    grid: Option<super::multigrid::grid::GridScratch>,
}

/// `v` as `n` zeros, in its own storage.
fn zeroed(v: &mut Vec<f64>, n: usize) {
    v.clear();
    v.resize(n, 0.0);
}

/// `v` of length `n`, its values left as they are when it already has that length: for a
/// vector that is written in full before it is read.
fn sized(v: &mut Vec<f64>, n: usize) {
    if v.len() != n {
        zeroed(v, n);
    }
}

/// [`pcg`] with its vectors in `work`: the same iterates, value for value.
pub(crate) fn pcg_in(
    u: &Unknowns,
    a: &Stencil,
    b_in: &[f64],
    x: &mut [f64],
    pre: &Preconditioner,
    stop: Stop,
    work: &mut PcgWork,
) -> (usize, Convergence) {
    let Stop { tol, max_iter, .. } = stop;
    let n = u.len();
    let PcgWork {
        b,
        ax,
        r,
        r_prev,
        z,
        p,
        ap,
        grid: grid_work,
    } = work;
    b.clear();
    b.extend_from_slice(b_in);
    u.zero_mean_parts(b);
    let norm = |v: &[f64]| dot(v, v).sqrt();
    let bn = norm(b);
    if bn == 0.0 {
        x.iter_mut().for_each(|v| *v = 0.0);
        return (0, Convergence::Residual);
    }
    // ax, z, ap and r_prev are written in full before they are read.
    sized(ax, n);
    a.apply(u, x, ax);
    r.clear();
    r.extend(b.iter().zip(ax.iter()).map(|(b, a)| b - a));
    let mut misfit = stop
        .data
        .map(|problem| Misfit::new(problem, dot(x, b), dot(x, r)));
    // Convergence is tested as soon as a residual is known, before it is preconditioned: the
    // preconditioner (a multigrid cycle) is most of an iteration's cost, and its output is
    // needed only when the solve goes on.
    if norm(r) <= tol * bn {
        return (0, Convergence::Residual);
    }
    let mut grid = match pre {
        Preconditioner::Dct(_) => vec![0f64; u.w * u.h],
        Preconditioner::Jacobi
        | Preconditioner::Multigrid(_)
        | Preconditioner::Grid(_)
        | Preconditioner::Blocks(_) => Vec::new(),
    };
    let mut cycle_work = match pre {
        Preconditioner::Multigrid(m) => m.work(),
        _ => Vec::new(),
    };
    if let Preconditioner::Grid(g) = pre {
        *grid_work = Some(match grid_work.take() {
            Some(old) => g.scratch_in(old),
            None => g.scratch(),
        });
    }
    let mut block_scratch = match pre {
        Preconditioner::Blocks(g) => Some(g.scratch()),
        _ => None,
    };
    let mut precondition = |r: &[f64], z: &mut [f64]| match pre {
        Preconditioner::Jacobi => {
            for ((z, r), d) in z.iter_mut().zip(r).zip(&a.diag) {
                *z = if *d > 1e-12 { r / d } else { *r };
            }
        }
        Preconditioner::Dct(s) => {
            grid.iter_mut().for_each(|v| *v = 0.0);
            for (k, &p) in u.pixel.iter().enumerate() {
                grid[p as usize] = r[k];
            }
            s.solve(&mut grid);
            for (k, &p) in u.pixel.iter().enumerate() {
                z[k] = grid[p as usize];
            }
        }
        Preconditioner::Multigrid(m) => m.apply(r, z, &mut cycle_work),
        Preconditioner::Grid(g) => {
            if let Some(s) = grid_work.as_mut() {
                g.apply(r, z, s);
            }
        }
        Preconditioner::Blocks(g) => {
            if let Some(s) = block_scratch.as_mut() {
                g.apply(r, z, s);
            }
        }
    };
    let flexible = matches!(
        pre,
        Preconditioner::Multigrid(_) | Preconditioner::Grid(_) | Preconditioner::Blocks(_)
    );
    if flexible {
        sized(r_prev, n);
    } else {
        r_prev.clear();
    }
    sized(z, n);
    precondition(r, z);
    p.clear();
    p.extend_from_slice(z);
    let mut rz = dot(r, z);
    sized(ap, n);
    // Each iteration's vector operations are fused into three passes (A p with pᵀAp; the step
    // with |r|²; rᵀz with zᵀr_prev) besides the new direction's, each sum taken as `dot` takes
    // it: the same iterates, value for value, as the operations one by one.
    for it in 1..=max_iter {
        let pap = a.apply_dot(u, p, ap);
        if pap <= 0.0 || !pap.is_finite() {
            return (it - 1, Convergence::Breakdown);
        }
        let alpha = rz / pap;
        let prev = flexible.then_some(r_prev.as_mut_slice());
        let rr = cg_step(x, r, prev, (p, ap), alpha);
        if rr.sqrt() <= tol * bn {
            return (it, Convergence::Residual);
        }
        if misfit.as_mut().is_some_and(|m| m.step(alpha * rz)) {
            return (it, Convergence::DataNoise);
        }
        precondition(r, z);
        // Flexible (Polak–Ribière) β, for preconditioners that are not a fixed linear map (the
        // K-cycle of multigrid): zᵀ(r − r_prev)/ρ_prev. With a fixed preconditioner it equals
        // the usual zᵀr/ρ_prev, since then zᵀr_prev = 0.
        let (rz_new, beta) = if flexible {
            let [rz_new, z_prev] = dots_with(r, z, r_prev);
            (rz_new, (rz_new - z_prev) / rz)
        } else {
            let rz_new = dot(r, z);
            (rz_new, rz_new / rz)
        };
        rz = rz_new;
        p.par_iter_mut()
            .zip(z.par_iter())
            .for_each(|(p, z)| *p = z + beta * *p);
    }
    (max_iter, Convergence::IterationLimit)
}

/// A system with a known solution, for tests: a solution that varies from unknown to unknown
/// (zero-mean in each connected part, as the singular systems' solutions are returned) and
/// the right-hand side A·solution.
#[cfg(test)]
pub(crate) fn known_solution(u: &Unknowns, a: &Stencil) -> (Vec<f64>, Vec<f64>) {
    let mut truth: Vec<f64> = (0..u.len())
        .map(|k| ((k * 7919) % 101) as f64 / 10.0)
        .collect();
    u.zero_mean_parts(&mut truth);
    let mut b = vec![0.0; u.len()];
    a.apply(u, &truth, &mut b);
    (truth, b)
}

/// Solves the system of [`known_solution`] by [`pcg`] with `pre` to a relative residual of
/// 10⁻¹⁰, for tests: the iterations, why the solve stopped, and the largest error.
#[cfg(test)]
pub(crate) fn solve_known(
    u: &Unknowns,
    a: &Stencil,
    pre: &Preconditioner,
    max_iter: usize,
) -> (usize, Convergence, f64) {
    let (truth, b) = known_solution(u, a);
    let mut x = vec![0.0; u.len()];
    let stop = Stop {
        tol: 1e-10,
        max_iter,
        data: None,
    };
    let (its, convergence) = pcg(u, a, &b, &mut x, pre, stop);
    u.zero_mean_parts(&mut x);
    let err = x
        .iter()
        .zip(&truth)
        .map(|(p, q)| (p - q).abs())
        .fold(0.0, f64::max);
    (its, convergence, err)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A masked grid Laplacian with a known solution: direct and both preconditioned CG agree.
    #[test]
    fn direct_and_cg_solve_a_masked_laplacian() {
        let (w, h) = (40, 30);
        // Two parts and a hole.
        let mask = Grid::from_fn(w, h, |x, y| {
            let (dx, dy) = (x as f64 - 12.0, y as f64 - 15.0);
            (dx * dx + dy * dy < 100.0 && !(x == 12 && y == 15)) || (x > 26 && y > 5 && y < 25)
        });
        let u = Unknowns::new(&mask);
        assert_eq!(u.parts, 2);
        let mut a = Stencil::zeros(u.len());
        for i in 0..u.len() {
            for (nb, off) in [(u.right[i], &mut a.right[i]), (u.down[i], &mut a.down[i])] {
                if nb != NONE {
                    let wgt = 1.0 + (i % 3) as f64;
                    *off -= wgt;
                    a.diag[i] += wgt;
                    a.diag[nb as usize] += wgt;
                }
            }
        }
        let (truth, b) = known_solution(&u, &a);
        let mut x = Direct::new(&u).unwrap().solve(&a, &b).unwrap();
        u.zero_mean_parts(&mut x);
        for (p, q) in x.iter().zip(&truth) {
            assert!((p - q).abs() < 1e-9, "direct {p} vs {q}");
        }
        let mut y = vec![0.0; u.len()];
        let its = pcg(
            &u,
            &a,
            &b,
            &mut y,
            &Preconditioner::Jacobi,
            Stop {
                tol: 1e-12,
                max_iter: 10_000,
                data: None,
            },
        );
        u.zero_mean_parts(&mut y);
        assert_eq!(its.1, Convergence::Residual);
        assert!(its.0 < 10_000);
        for (p, q) in y.iter().zip(&truth) {
            assert!((p - q).abs() < 1e-7, "cg {p} vs {q}");
        }
        let s = NeumannSolver::new(w, h);
        let mut y = vec![0.0; u.len()];
        pcg(
            &u,
            &a,
            &b,
            &mut y,
            &Preconditioner::Dct(&s),
            Stop {
                tol: 1e-12,
                max_iter: 10_000,
                data: None,
            },
        );
        u.zero_mean_parts(&mut y);
        for (p, q) in y.iter().zip(&truth) {
            assert!((p - q).abs() < 1e-7, "dct-pcg {p} vs {q}");
        }
    }

    /// Deterministic noise in [−1, 1] for edge `k`.
    fn noise(k: usize) -> f64 {
        ((k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11) as f64 / (1u64 << 53) as f64 * 2.0
            - 1.0
    }

    /// Masked least squares on a disc with a hole beside a bar (two parts): the edges' depth
    /// differences of a smooth surface plus noise of amplitude `sigma`. Returns the unknowns,
    /// the system, its right-hand side, |d|² and the edges (i, j, d).
    #[allow(clippy::type_complexity)]
    fn noisy_system(sigma: f64) -> (Unknowns, Stencil, Vec<f64>, f64, Vec<(usize, usize, f64)>) {
        let (w, h) = (120, 90);
        let mask = Grid::from_fn(w, h, |x, y| {
            let (dx, dy) = (x as f64 - 45.0, y as f64 - 45.0);
            let r2 = dx * dx + dy * dy;
            (r2 < 40.0 * 40.0 && r2 > 36.0) || (x > 95 && y > 10 && y < 80)
        });
        let u = Unknowns::new(&mask);
        let depth = |k: usize| {
            let p = u.pixel[k] as usize;
            let (x, y) = ((p % w) as f64, (p / w) as f64);
            0.01 * (x - 40.0).powi(2) + 0.3 * y + 4.0 * (x / 9.0).sin() * (y / 13.0).cos()
        };
        let mut a = Stencil::zeros(u.len());
        let mut b = vec![0.0; u.len()];
        let mut edges = Vec::new();
        for i in 0..u.len() {
            for (nb, along_rows) in [(u.right[i], true), (u.down[i], false)] {
                if nb != NONE {
                    let j = nb as usize;
                    let d = depth(j) - depth(i) + sigma * noise(edges.len());
                    a.add_edge(&mut b, (i, j), along_rows, 1.0, d);
                    edges.push((i, j, d));
                }
            }
        }
        let data = edges.iter().map(|e| e.2 * e.2).sum();
        (u, a, b, data, edges)
    }

    /// The misfit rule of [`Stop::data`]: measured against the exact least-squares solution
    /// (the direct solve), what conjugate gradients return could shed at most
    /// [`NOISE_SHARE`]² σ̂² more of the misfit (σ̂² the misfit per redundant equation), in
    /// fewer iterations than the relative residual of 10⁻⁸ alone takes, with the DCT and the
    /// multigrid preconditioners. On integrable data (no misfit beyond rounding) the rule never
    /// applies and the residual decides alone.
    #[test]
    fn conjugate_gradients_stop_within_the_noise_share() {
        let (u, a, b, norm2, edges) = noisy_system(0.05);
        let f = |x: &[f64]| {
            edges
                .iter()
                .map(|&(i, j, d)| (x[j] - x[i] - d).powi(2))
                .sum::<f64>()
        };
        let problem = LeastSquares {
            norm2,
            redundancy: edges.len() + u.parts - u.len(),
        };
        let fmin = f(&Direct::new(&u).unwrap().solve(&a, &b).unwrap());
        let variance = fmin / problem.redundancy as f64;
        let s = NeumannSolver::new(u.w, u.h);
        let m = super::super::multigrid::Multigrid::new(&u, &a);
        for (name, pre) in [
            ("dct", Preconditioner::Dct(&s)),
            ("multigrid", Preconditioner::Multigrid(&m)),
        ] {
            let run = |data| {
                let mut x = vec![0.0; u.len()];
                let stop = Stop {
                    tol: 1e-8,
                    max_iter: 1000,
                    data,
                };
                let (its, how) = pcg(&u, &a, &b, &mut x, &pre, stop);
                (x, its, how)
            };
            let (x, its, how) = run(Some(problem));
            let (_, plain, plain_how) = run(None);
            assert_eq!(
                (how, plain_how),
                (Convergence::DataNoise, Convergence::Residual)
            );
            let excess = (f(&x) - fmin) / variance;
            eprintln!("{name}: {its} iterations against {plain}, excess {excess:.2e} σ̂²");
            assert!(
                excess <= NOISE_SHARE * NOISE_SHARE,
                "{name}: excess {excess:.2e} σ̂²"
            );
            assert!(its < plain, "{name}: {its} iterations against {plain}");
        }
        // Integrable data: the same iterations with and without the rule.
        let (u, a, b, norm2, edges) = noisy_system(0.0);
        let problem = LeastSquares {
            norm2,
            redundancy: edges.len() + u.parts - u.len(),
        };
        let m = super::super::multigrid::Multigrid::new(&u, &a);
        let pre = Preconditioner::Multigrid(&m);
        let its = |data| {
            let stop = Stop {
                tol: 1e-8,
                max_iter: 1000,
                data,
            };
            pcg(&u, &a, &b, &mut vec![0.0; u.len()], &pre, stop)
        };
        let with_rule = its(Some(problem));
        assert_eq!(with_rule, its(None));
        assert_eq!(with_rule.1, Convergence::Residual);
    }

    #[test]
    fn nested_dissection_is_a_permutation() {
        let mask = Grid::from_fn(300, 200, |x, y| (x * y) % 7 != 3);
        let u = Unknowns::new(&mask);
        let mut order = nested_dissection(&u, 1);
        assert_eq!(order.len(), u.len());
        order.sort_unstable();
        assert!(order.iter().enumerate().all(|(i, k)| i == *k));
    }
}

#[cfg(test)]
mod mixed_tests {
    use super::*;

    /// The lower triangle of L + εI on an m × m grid (L the 5-point Laplacian with Neumann
    /// sides, so that ε sets the conditioning: cond ≈ 8/ε), in compressed columns.
    fn laplacian(m: usize, eps: f64) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
        let n = m * m;
        let (mut col_ptr, mut row_idx, mut values) = (vec![0], Vec::new(), Vec::new());
        for k in 0..n {
            let (r, c) = (k / m, k % m);
            let degree = [r > 0, r + 1 < m, c > 0, c + 1 < m]
                .iter()
                .filter(|&&b| b)
                .count();
            row_idx.push(k);
            values.push(degree as f64 + eps);
            if c + 1 < m {
                row_idx.push(k + 1);
                values.push(-1.0);
            }
            if r + 1 < m {
                row_idx.push(k + m);
                values.push(-1.0);
            }
            col_ptr.push(row_idx.len());
        }
        (col_ptr, row_idx, values)
    }

    /// Mixed precision agrees with the `f64` factorisation to 10⁻¹⁰ on a well-conditioned
    /// system without solving it again, and on one too ill-conditioned for one refinement
    /// (cond ≈ 10⁷) falls back to `f64` and agrees as well.
    #[test]
    fn mixed_precision_matches_double_and_falls_back_when_ill_conditioned() {
        let m = 40;
        let n = m * m;
        let b: Vec<f64> = (0..n)
            .map(|k| ((k * 7919) % 101) as f64 / 101.0 - 0.5)
            .collect();
        // ε = 10⁻⁶ survives the rounding to f32 (whose step at 4 is 4.8·10⁻⁷): the rounded
        // matrix is definite, of condition about 10⁷, too large for one refinement.
        for (eps, fallback) in [(1.0, false), (1e-6, true)] {
            let (col_ptr, row_idx, values) = laplacian(m, eps);
            let symbolic = symbolic_cholesky(&col_ptr, &row_idx, (0..n).collect()).unwrap();
            let mut exact = b.clone();
            CholeskyWork::new(&symbolic, Par::Seq)
                .unwrap()
                .solve(&symbolic, &col_ptr, &row_idx, &values, &mut exact)
                .unwrap();
            let mut mixed_work = MixedCholesky::new(&symbolic, Par::Seq).unwrap();
            let mut mixed = b.clone();
            mixed_work
                .solve(&symbolic, &col_ptr, &row_idx, &values, &mut mixed)
                .unwrap();
            let norm = exact.iter().map(|v| v * v).sum::<f64>().sqrt();
            let diff = exact
                .iter()
                .zip(&mixed)
                .map(|(a, b)| (a - b) * (a - b))
                .sum::<f64>()
                .sqrt();
            assert!(diff <= 1e-10 * norm, "ε = {eps}: {diff} against {norm}");
            assert_eq!(mixed_work.fallbacks, usize::from(fallback), "ε = {eps}");
            // The single-precision solve alone, without the refinement's check, is off there.
            // (Or it fails: the rounded pivots need not all stay positive.)
            let mut single = b.clone();
            let correction = CholeskyWorkF32::new(&symbolic, Par::Seq).unwrap().solve(
                &symbolic,
                &col_ptr,
                &row_idx,
                &values,
                &mut single,
            );
            let rejected = correction.as_ref().map_or(true, |&c| c > MIXED_TOLERANCE);
            assert_eq!(rejected, fallback, "ε = {eps}: {correction:?}");
        }
    }
}
