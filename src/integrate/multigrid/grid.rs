//! Geometric aggregation multigrid on the pixel grid, and the conjugate-gradient solve it
//! preconditions: masked least squares in time and memory linear in the pixels, with no index
//! arrays or compressed rows.
//!
//! Masked least squares is a graph Laplacian on the pixel grid: unit weight on every edge
//! between two domain pixels, zero elsewhere. Aggregating the pixels in fixed 2×2 blocks
//! (instead of the strength-based matching of the parent module) keeps every level a weighted
//! 5-point graph Laplacian on a grid of half the width and height: for the piecewise-constant
//! prolongation of the blocks, the Galerkin product PᵀAP weighs the edge between two
//! neighbouring blocks by the sum of the two fine edges that cross between them, and its
//! diagonal is the sum of the block's coarse edge weights (the fine edges inside a block
//! cancel). A level is therefore nothing but its edge weights and diagonal (12 B a cell in
//! `f32`), and its vectors are grids; the coarse levels together hold a third of the finest.
//!
//! The cycle is the parent module's: Notay's K-cycle (Notay, "An aggregation-based algebraic
//! multigrid method", ETNA 37, 2010) — on each coarse level up to two steps of flexible
//! conjugate gradients preconditioned by that level's cycle — with symmetric Gauss–Seidel
//! smoothing in red–black order (red then black before the coarse correction, black then red
//! after it), so that each half-sweep updates one colour from the other in parallel, and the
//! coarsest level (at most [`COARSEST`] active cells) solved by dense Cholesky. It preconditions
//! a flexible conjugate-gradient solve ([`solve`]) whose iterate and residual are kept in `f64`
//! and its other vectors in `f32`.
//!
//! Memory: [`BYTES_PER_CELL`] per pixel of the domain's bounding box at the peak, taken by
//! [`crate::integrate::Integrator::working_bytes`] for streamed runs.
//!
//! Fails where: the bounding box, not the mask, sets the cost — a thin diagonal mask costs as
//! much as the rectangle around it. The `f32` vectors do not limit the accuracy: A p is summed
//! in `f64`, so the residual the solve carries stays the true one (a 1024² test grid reaches a
//! relative residual of 1e-8 in 11 iterations, within 1e-7 of the solution's range).

use super::{COARSEST, Coarsest, Csr, KCYCLE_MIN_RATIO, STALLED_SWEEPS, dense_factor, kcycle};
use crate::integrate::sparse::{NONE, dot};
use faer::MatMut;
use faer::linalg::solvers::Solve;
use rayon::prelude::*;

/// Bytes of working memory a cell of the grid costs at the peak of masked least squares on it
/// (`masked.rs`), besides the maps over the whole image, as counted for the solve's first
/// cycle, when most is held at once: the finest level's weights and diagonal (12), the coarse
/// levels' (4), the domain (1), the solve's iterate and residual (16), direction and
/// preconditioned residual (8), the finest level's cycle scratch (4), the restricted residual
/// and correction (2), the first coarse level's K-cycle vectors (5) and the deeper levels'
/// (about 4). The measured growth of the peak with the window is lower, 26–46 B a cell
/// (1732×1732 normal maps under discs of radius 400, 600 and 800 px), so this is an upper
/// bound.
pub const BYTES_PER_CELL: u64 = 56;

/// A right-hand side's element: the outer solve's residual is `f64`, the coarse levels' `f32`.
pub(crate) trait Rhs: Copy + Send + Sync + Into<f64> {
    /// The value in the cycle's precision.
    fn single(self) -> f32;
}

impl Rhs for f32 {
    #[inline(always)]
    fn single(self) -> f32 {
        self
    }
}

impl Rhs for f64 {
    #[inline(always)]
    fn single(self) -> f32 {
        self as f32
    }
}

/// Cells a parallel task takes at least: smaller levels (most of the coarse ones, which the
/// K-cycle visits most often) run on one thread, where scheduling would cost more than the work.
const CELLS_PER_TASK: usize = 1 << 15;

/// Rows of a `w`-wide grid a parallel task takes at least.
fn rows_per_task(w: usize) -> usize {
    (CELLS_PER_TASK / w.max(1)).max(1)
}

/// A weighted 5-point graph Laplacian on a `w`×`h` grid: `right[i]` weighs the edge from cell i
/// to its right neighbour, `down[i]` the edge to the cell below (0 where there is none), and
/// `diag[i]` is the sum of the cell's edge weights. A cell without edges (diagonal 0) is
/// inactive: it is not an unknown and keeps the value 0.
pub(crate) struct GridLaplacian {
    w: usize,
    h: usize,
    right: Vec<f32>,
    down: Vec<f32>,
    diag: Vec<f32>,
}

impl GridLaplacian {
    /// The Laplacian with the given edge weights (row-major, `w`×`h` each); the weights of
    /// edges that leave the grid are ignored.
    pub fn new(w: usize, h: usize, mut right: Vec<f32>, mut down: Vec<f32>) -> Self {
        for y in 0..h {
            right[y * w + w - 1] = 0.0;
        }
        if h > 0 {
            down[(h - 1) * w..].iter_mut().for_each(|v| *v = 0.0);
        }
        let mut diag = vec![0f32; w * h];
        diag.par_chunks_mut(w.max(1))
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(y, row)| {
                for (x, d) in row.iter_mut().enumerate() {
                    let i = y * w + x;
                    let mut s = right[i] + down[i];
                    if x > 0 {
                        s += right[i - 1];
                    }
                    if y > 0 {
                        s += down[i - w];
                    }
                    *d = s;
                }
            });
        GridLaplacian {
            w,
            h,
            right,
            down,
            diag,
        }
    }

    /// Cells.
    pub fn len(&self) -> usize {
        self.w * self.h
    }

    /// Cells with at least one edge.
    fn active(&self) -> usize {
        self.diag.iter().filter(|&&d| d > 0.0).count()
    }

    /// Σ over the cell's neighbours of weight × x.
    #[inline(always)]
    fn neighbours(&self, x: &[f32], i: usize, col: usize, row: usize) -> f32 {
        let w = self.w;
        let mut s = 0.0;
        if col + 1 < w {
            s += self.right[i] * x[i + 1];
        }
        if col > 0 {
            s += self.right[i - 1] * x[i - 1];
        }
        if row + 1 < self.h {
            s += self.down[i] * x[i + w];
        }
        if row > 0 {
            s += self.down[i - w] * x[i - w];
        }
        s
    }

    /// y = A x.
    pub fn multiply(&self, x: &[f32], y: &mut [f32]) {
        let w = self.w;
        y.par_chunks_mut(w)
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(row, out)| {
                for (col, o) in out.iter_mut().enumerate() {
                    let i = row * w + col;
                    *o = self.diag[i] * x[i] - self.neighbours(x, i, col, row);
                }
            });
    }

    /// (A x)ᵢ in `f64`, for the outer solve's A p: its residual is updated by it, and a rounded
    /// A p would let that residual drift from the true one (the depth error then grows with the
    /// grid: 7e-6 of the range on a 1024² test grid, against 1e-7). It is recomputed where
    /// needed rather than stored, which saves 8 bytes a cell for two more stencil passes.
    #[inline(always)]
    fn wide(&self, x: &[f32], i: usize, col: usize, row: usize) -> f64 {
        let w = self.w;
        let term = |weight: f32, v: f32| f64::from(weight) * f64::from(v);
        let mut s = f64::from(self.diag[i]) * f64::from(x[i]);
        if col + 1 < w {
            s -= term(self.right[i], x[i + 1]);
        }
        if col > 0 {
            s -= term(self.right[i - 1], x[i - 1]);
        }
        if row + 1 < self.h {
            s -= term(self.down[i], x[i + w]);
        }
        if row > 0 {
            s -= term(self.down[i - w], x[i - w]);
        }
        s
    }

    /// Σᵢ vᵢ (A x)ᵢ, summed over fixed blocks of rows in order (the same on any number of
    /// threads).
    fn dot_product_with(&self, v: &[f32], x: &[f32]) -> f64 {
        let w = self.w;
        let rows = rows_per_task(w);
        let partial: Vec<f64> = (0..self.h.div_ceil(rows))
            .into_par_iter()
            .map(|block| {
                let mut sum = 0.0;
                for row in block * rows..((block + 1) * rows).min(self.h) {
                    for col in 0..w {
                        let i = row * w + col;
                        sum += f64::from(v[i]) * self.wide(x, i, col, row);
                    }
                }
                sum
            })
            .collect();
        partial.iter().sum()
    }

    /// r = b − A x.
    fn residual<B: Rhs>(&self, b: &[B], x: &[f32], r: &mut [f32]) {
        let w = self.w;
        r.par_chunks_mut(w)
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(row, out)| {
                for (col, o) in out.iter_mut().enumerate() {
                    let i = row * w + col;
                    // Inactive cells carry no equation: their right-hand side is not restricted.
                    *o = if self.diag[i] > 0.0 {
                        b[i].single() - (self.diag[i] * x[i] - self.neighbours(x, i, col, row))
                    } else {
                        0.0
                    };
                }
            });
    }

    /// One Gauss–Seidel half-sweep over the cells of one colour ((column + row) mod 2): their
    /// new values depend only on the other colour's, which it leaves alone, so they are computed
    /// in parallel into `scratch` and then copied.
    fn half_sweep<B: Rhs>(&self, b: &[B], x: &mut [f32], colour: usize, scratch: &mut [f32]) {
        let w = self.w;
        let xs: &[f32] = x;
        scratch
            .par_chunks_mut(w)
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(row, out)| {
                for col in ((row + colour) & 1..w).step_by(2) {
                    let i = row * w + col;
                    let d = self.diag[i];
                    out[col] = if d > 0.0 {
                        (b[i].single() + self.neighbours(xs, i, col, row)) / d
                    } else {
                        0.0
                    };
                }
            });
        x.par_chunks_mut(w)
            .zip(scratch.par_chunks(w))
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(row, (out, new))| {
                for col in ((row + colour) & 1..w).step_by(2) {
                    out[col] = new[col];
                }
            });
    }

    /// A symmetric Gauss–Seidel step in red–black order: forward red then black, backward
    /// black then red.
    fn sweep<B: Rhs>(&self, b: &[B], x: &mut [f32], forward: bool, scratch: &mut [f32]) {
        let order = if forward { [0, 1] } else { [1, 0] };
        for colour in order {
            self.half_sweep(b, x, colour, scratch);
        }
    }

    /// Size of the coarse grid: 2×2 blocks.
    fn coarse_size(&self) -> (usize, usize) {
        (self.w.div_ceil(2), self.h.div_ceil(2))
    }

    /// The Galerkin coarse level of the 2×2 blocks (see the module documentation).
    fn coarsen(&self) -> GridLaplacian {
        let (w, h) = (self.w, self.h);
        let (wc, hc) = self.coarse_size();
        let mut right = vec![0f32; wc * hc];
        let mut down = vec![0f32; wc * hc];
        right
            .par_chunks_mut(wc)
            .zip(down.par_chunks_mut(wc))
            .enumerate()
            .with_min_len(rows_per_task(wc))
            .for_each(|(row, (r_out, d_out))| {
                let rows = (2 * row..(2 * row + 2).min(h)).collect::<Vec<_>>();
                for col in 0..wc {
                    // The fine edges between columns 2·col + 1 and 2·col + 2.
                    if 2 * col + 2 < w {
                        r_out[col] = rows.iter().map(|&y| self.right[y * w + 2 * col + 1]).sum();
                    }
                    // The fine edges between rows 2·row + 1 and 2·row + 2.
                    if 2 * row + 2 < h {
                        d_out[col] = (2 * col..(2 * col + 2).min(w))
                            .map(|x| self.down[(2 * row + 1) * w + x])
                            .sum();
                    }
                }
            });
        GridLaplacian::new(wc, hc, right, down)
    }

    /// rc = Pᵀ r: each block's sum.
    fn restrict(&self, r: &[f32], rc: &mut [f32]) {
        let (w, h) = (self.w, self.h);
        let (wc, _) = self.coarse_size();
        rc.par_chunks_mut(wc)
            .enumerate()
            .with_min_len(rows_per_task(wc))
            .for_each(|(row, out)| {
                for (col, o) in out.iter_mut().enumerate() {
                    let mut s = 0.0;
                    for y in 2 * row..(2 * row + 2).min(h) {
                        for x in 2 * col..(2 * col + 2).min(w) {
                            s += r[y * w + x];
                        }
                    }
                    *o = s;
                }
            });
    }

    /// x += P xc on the active cells.
    fn prolong_add(&self, xc: &[f32], x: &mut [f32]) {
        let w = self.w;
        let (wc, _) = self.coarse_size();
        x.par_chunks_mut(w)
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(row, out)| {
                let coarse = &xc[(row / 2) * wc..];
                for (col, o) in out.iter_mut().enumerate() {
                    if self.diag[row * w + col] > 0.0 {
                        *o += coarse[col / 2];
                    }
                }
            });
    }

    /// The active cells as a compressed-row matrix, with each active cell's index in it.
    fn to_csr(&self) -> (Csr, Vec<u32>) {
        let w = self.w;
        let mut index = vec![NONE; self.len()];
        let mut cells = Vec::new();
        for (i, &d) in self.diag.iter().enumerate() {
            if d > 0.0 {
                index[i] = cells.len() as u32;
                cells.push(i);
            }
        }
        let mut start = vec![0];
        let (mut col, mut val) = (Vec::new(), Vec::new());
        let mut diag = Vec::with_capacity(cells.len());
        for &i in &cells {
            let (x, y) = (i % w, i / w);
            let mut entries = Vec::with_capacity(4);
            if y > 0 {
                entries.push((i - w, self.down[i - w]));
            }
            if x > 0 {
                entries.push((i - 1, self.right[i - 1]));
            }
            if x + 1 < w {
                entries.push((i + 1, self.right[i]));
            }
            if y + 1 < self.h {
                entries.push((i + w, self.down[i]));
            }
            for (j, weight) in entries {
                if weight > 0.0 {
                    col.push(index[j]);
                    val.push(-f64::from(weight));
                }
            }
            start.push(col.len());
            diag.push(f64::from(self.diag[i]));
        }
        (Csr::new(diag, start, col, val), index)
    }
}

/// The multigrid hierarchy of a [`GridLaplacian`] (see the module documentation).
pub(crate) struct GridMultigrid {
    /// Levels, finest first.
    levels: Vec<GridLaplacian>,
    /// Active cells of each level: the K-cycle's second step is judged on how fast they
    /// coarsen (a grid one cell wide halves, not quarters, its cells).
    active: Vec<usize>,
    coarsest: Coarsest,
    /// Index of each cell of the coarsest level in the dense solve (or [`NONE`]).
    coarsest_index: Vec<u32>,
}

impl GridMultigrid {
    /// The hierarchy of `finest`, coarsened in 2×2 blocks until at most [`COARSEST`] cells are
    /// active.
    pub fn new(finest: GridLaplacian) -> Self {
        let mut active = vec![finest.active()];
        let mut levels = vec![finest];
        loop {
            let last = levels.last().expect("at least the finest level");
            if active[active.len() - 1] <= COARSEST || last.len() <= 1 {
                break;
            }
            let next = last.coarsen();
            active.push(next.active());
            levels.push(next);
        }
        let (csr, coarsest_index) = levels.last().expect("at least one level").to_csr();
        GridMultigrid {
            coarsest: dense_factor(&csr),
            levels,
            active,
            coarsest_index,
        }
    }

    /// The finest level.
    pub fn finest(&self) -> &GridLaplacian {
        &self.levels[0]
    }

    /// z = M⁻¹ r: one cycle from zero.
    pub fn apply<B: Rhs>(&self, r: &[B], z: &mut [f32]) {
        self.cycle(0, r, z);
    }

    /// The K-cycle's coarse correction on `level` (as the parent module's, on grids).
    fn krylov(&self, level: usize, b: &[f32], x: &mut [f32]) {
        if level + 1 == self.levels.len() {
            self.cycle(level, b, x);
            return;
        }
        let a = &self.levels[level];
        let ratio = self.active[level] as f64 / self.active[level + 1].max(1) as f64;
        kcycle(
            b,
            x,
            |b, x| self.cycle(level, b, x),
            |x, y| a.multiply(x, y),
            dot,
            ratio >= KCYCLE_MIN_RATIO,
        );
    }

    fn cycle<B: Rhs>(&self, level: usize, b: &[B], x: &mut [f32]) {
        let a = &self.levels[level];
        x.iter_mut().for_each(|v| *v = 0.0);
        if level + 1 == self.levels.len() {
            self.coarsest_solve(a, b, x);
            return;
        }
        let mut scratch = vec![0f32; a.len()];
        a.sweep(b, x, true, &mut scratch);
        a.residual(b, x, &mut scratch);
        let (wc, hc) = a.coarse_size();
        let mut rc = vec![0f32; wc * hc];
        a.restrict(&scratch, &mut rc);
        let mut xc = vec![0f32; wc * hc];
        self.krylov(level + 1, &rc, &mut xc);
        drop(rc);
        a.prolong_add(&xc, x);
        drop(xc);
        a.sweep(b, x, false, &mut scratch);
    }

    fn coarsest_solve<B: Rhs>(&self, a: &GridLaplacian, b: &[B], x: &mut [f32]) {
        match &self.coarsest {
            Coarsest::Dense(llt) => {
                let mut dense: Vec<f64> = Vec::new();
                for (i, &k) in self.coarsest_index.iter().enumerate() {
                    if k != NONE {
                        dense.push(b[i].into());
                    }
                }
                let n = dense.len();
                llt.solve_in_place(MatMut::from_column_major_slice_mut(&mut dense, n, 1));
                for (i, &k) in self.coarsest_index.iter().enumerate() {
                    if k != NONE {
                        x[i] = dense[k as usize] as f32;
                    }
                }
            }
            Coarsest::Sweeps => {
                let mut scratch = vec![0f32; a.len()];
                for _ in 0..STALLED_SWEEPS {
                    a.sweep(b, x, true, &mut scratch);
                    a.sweep(b, x, false, &mut scratch);
                }
            }
        }
    }
}

/// Connected parts of the active cells through edges of positive weight: a label per cell
/// ([`NONE`] for inactive cells) and the number of parts.
pub(crate) fn parts(a: &GridLaplacian) -> (Vec<u32>, usize) {
    let (w, h) = (a.w, a.h);
    let mut label = vec![NONE; a.len()];
    let mut count = 0u32;
    let mut stack = Vec::new();
    for s in 0..a.len() {
        if label[s] != NONE || a.diag[s] <= 0.0 {
            continue;
        }
        label[s] = count;
        stack.push(s);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            let mut visit = |j: usize, weight: f32| {
                if weight > 0.0 && label[j] == NONE {
                    label[j] = count;
                    stack.push(j);
                }
            };
            if x + 1 < w {
                visit(i + 1, a.right[i]);
            }
            if x > 0 {
                visit(i - 1, a.right[i - 1]);
            }
            if y + 1 < h {
                visit(i + w, a.down[i]);
            }
            if y > 0 {
                visit(i - w, a.down[i - w]);
            }
        }
        count += 1;
    }
    (label, count as usize)
}

/// The mean of `v` over each part (`label`, `parts` from [`parts`]), summed in `f64`.
pub(crate) fn part_means<T: Copy + Into<f64>>(v: &[T], label: &[u32], parts: usize) -> Vec<f64> {
    let mut sum = vec![0f64; parts];
    let mut count = vec![0usize; parts];
    for (&x, &l) in v.iter().zip(label) {
        if l != NONE {
            sum[l as usize] += x.into();
            count[l as usize] += 1;
        }
    }
    sum.iter()
        .zip(&count)
        .map(|(s, &c)| s / c.max(1) as f64)
        .collect()
}

/// Solves the consistent singular system A x = b (`b` is made zero-mean per connected part
/// first, and zero on inactive cells) by flexible conjugate gradients preconditioned with `mg`,
/// from x = 0 until |r| ≤ tol·|b| or `max_iter` iterations; returns x (zero on inactive cells)
/// and the iterations used.
///
/// The iterate and the residual are `f64`, the direction and preconditioned residual `f32`, and
/// A p is recomputed in `f64` where it is needed ([`GridLaplacian::wide`]): the residual's
/// updates are then exact to `f64` for the (rounded) direction the iterate moves along, so it
/// stays the true residual. (An `f32` iterate gathers rounding noise at every step: on a 5000²
/// sphere of depth range 2000 px it raised the mean integration residual from 9.1e-4 to
/// 1.2e-3.) 24 bytes a cell, besides the hierarchy.
pub(crate) fn solve(
    mg: &GridMultigrid,
    mut b: Vec<f64>,
    tol: f64,
    max_iter: usize,
) -> (Vec<f64>, usize) {
    let a = mg.finest();
    let n = a.len();
    {
        let (label, parts) = parts(a);
        let means = part_means(&b, &label, parts);
        b.par_iter_mut().zip(&label).for_each(|(v, &l)| {
            *v = if l == NONE {
                0.0
            } else {
                *v - means[l as usize]
            };
        });
    }
    let mut x = vec![0f64; n];
    let bn = dot(&b, &b).sqrt();
    if bn == 0.0 {
        return (x, 0);
    }
    // The residual, from x = 0.
    let mut r = b;
    let mut z = vec![0f32; n];
    mg.apply(&r, &mut z);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let w = a.w;
    for it in 0..max_iter {
        if dot(&r, &r).sqrt() <= tol * bn {
            return (x, it);
        }
        let pap = a.dot_product_with(&p, &p);
        if pap <= 0.0 || !pap.is_finite() {
            return (x, it);
        }
        let alpha = rz / pap;
        let dir: &[f32] = &p;
        x.par_chunks_mut(w)
            .zip(r.par_chunks_mut(w))
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(row, (x, r))| {
                for col in 0..w {
                    let i = row * w + col;
                    x[col] += alpha * f64::from(dir[i]);
                    r[col] -= alpha * a.wide(dir, i, col, row);
                }
            });
        mg.apply(&r, &mut z);
        let rz_new = dot(&r, &z);
        // Flexible (Polak–Ribière) β for the K-cycle, which is not a fixed linear map:
        // zᵀ(r − r_prev)/ρ_prev, with r − r_prev = −α A p.
        let beta = -alpha * a.dot_product_with(&z, &p) / rz;
        rz = rz_new;
        p.par_iter_mut()
            .zip(&z)
            .with_min_len(CELLS_PER_TASK)
            .for_each(|(p, &z)| *p = (f64::from(z) + beta * f64::from(*p)) as f32);
    }
    (x, max_iter)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A disk with a hole and a separate bar (two parts) on an n×n grid, as unit-weight edges.
    fn laplacian(n: usize) -> GridLaplacian {
        let c = n as f64 * 0.35;
        let inside = |x: usize, y: usize| {
            let (dx, dy) = (x as f64 - c, y as f64 - c);
            let r2 = dx * dx + dy * dy;
            (r2 < (0.3 * n as f64).powi(2) && r2 > 4.0) || (x > 3 * n / 4 && y > n / 8 && y < n - 4)
        };
        let mut right = vec![0f32; n * n];
        let mut down = vec![0f32; n * n];
        for y in 0..n {
            for x in 0..n {
                if inside(x, y) && x + 1 < n && inside(x + 1, y) {
                    right[y * n + x] = 1.0;
                }
                if inside(x, y) && y + 1 < n && inside(x, y + 1) {
                    down[y * n + x] = 1.0;
                }
            }
        }
        GridLaplacian::new(n, n, right, down)
    }

    /// Solves A x = A·truth; returns the iterations and the largest error (zero-mean per part)
    /// relative to the truth's range.
    fn solve_known(a: GridLaplacian) -> (usize, f64) {
        let n = a.len();
        let (label, parts) = parts(&a);
        assert_eq!(parts, 2);
        let mut truth: Vec<f64> = (0..n)
            .map(|k| {
                if label[k] == NONE {
                    0.0
                } else {
                    ((k * 7919) % 101) as f64 / 10.0
                }
            })
            .collect();
        let means = part_means(&truth, &label, parts);
        for (t, &l) in truth.iter_mut().zip(&label) {
            if l != NONE {
                *t -= means[l as usize];
            }
        }
        // b = A·truth in f64 (an f32 product would perturb b by more than the solve's error).
        let mut b = vec![0f64; n];
        for i in 0..n {
            let mut edge = |j: usize, weight: f32| {
                let d = f64::from(weight) * (truth[i] - truth[j]);
                b[i] += d;
                b[j] -= d;
            };
            if (i + 1) % a.w != 0 {
                edge(i + 1, a.right[i]);
            }
            if i + a.w < n {
                edge(i + a.w, a.down[i]);
            }
        }
        let mg = GridMultigrid::new(a);
        let (x, its) = solve(&mg, b, 1e-8, 200);
        let means = part_means(&x, &label, parts);
        let err = x
            .iter()
            .zip(&truth)
            .zip(&label)
            .filter(|(_, l)| **l != NONE)
            .map(|((&p, q), &l)| (p - means[l as usize] - q).abs())
            .fold(0.0, f64::max);
        (its, err / 10.0)
    }

    #[test]
    fn coarse_levels_are_quarter_size_laplacians() {
        let a = laplacian(64);
        let coarse = a.coarsen();
        assert_eq!(coarse.len(), 32 * 32);
        // Galerkin: the coarse matrix applied to a block-constant vector equals Pᵀ A P.
        let xc: Vec<f32> = (0..coarse.len()).map(|k| ((k * 31) % 17) as f32).collect();
        let mut fine = vec![0f32; a.len()];
        a.prolong_add(&xc, &mut fine);
        let mut afine = vec![0f32; a.len()];
        a.multiply(&fine, &mut afine);
        let mut galerkin = vec![0f32; coarse.len()];
        a.restrict(&afine, &mut galerkin);
        let mut direct = vec![0f32; coarse.len()];
        coarse.multiply(&xc, &mut direct);
        for (g, d) in galerkin.iter().zip(&direct) {
            assert!((g - d).abs() < 1e-3, "{g} vs {d}");
        }
    }

    /// Exact to the f32 precision, and the iteration count does not grow with the grid.
    #[test]
    fn iterations_do_not_grow_with_the_grid() {
        let mut counts = Vec::new();
        for n in [64, 256, 1024] {
            let (its, err) = solve_known(laplacian(n));
            eprintln!("n {n}: {its} iterations, error {err}");
            assert!(err < 1e-6, "n {n}: relative error {err}");
            counts.push(its);
        }
        eprintln!("iterations {counts:?}");
        assert!(counts[2] <= counts[0] + 4 && counts[2] <= 20, "{counts:?}");
    }
}
