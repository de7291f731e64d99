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
//! after it), and the coarsest level (at most [`COARSEST`] active cells) solved by dense
//! Cholesky. It preconditions a flexible conjugate-gradient solve ([`solve`]) whose iterate and
//! residual are kept in `f64` and its other vectors in `f32`.
//!
//! Speed: every pass works on whole rows (the neighbour sums of a row are four products of
//! shifted rows, with no test per cell, because edges leaving the grid have weight 0), so the
//! loops vectorise; both colours of a Gauss–Seidel sweep are relaxed in one pass, the second a
//! row behind the first, in parallel blocks of rows that exchange copies of their boundary rows;
//! the residual is restricted as it is computed, never stored; each product with A on a coarse
//! level gives the K-cycle's dot products in the same pass (summed over fixed blocks of rows,
//! so the same on any number of threads); and the cycle's vectors are allocated once per
//! solve. The sweeps, products and restricted residuals are those of the cell-by-cell formulas
//! bit for bit (unit test); only the K-cycle's dot products are summed in another order, which
//! moved the depth of a 1024² sphere by 1.7e-8 of its range, with the same 12 iterations.
//!
//! **Weighted systems** ([`GridPreconditioner`]): the same hierarchy built from any weighted
//! 5-point graph Laplacian on masked unknowns (the bilateral integrator's reweighting steps,
//! whose weights fall towards 0 across a depth jump) preconditions the parent module's
//! `f64` conjugate gradients on the exact system. Only the preconditioner is rounded to `f32`,
//! each diagonal upwards ([`round_up`]), so that every level stays diagonally dominant and
//! positive semidefinite however far its weights spread: rounded to nearest, conjugate
//! gradients on the rounded system broke down once they spanned many orders of magnitude.
//! Fixed blocks join the two sides of a jump, so a step needs more iterations than with the
//! aggregation hierarchy (whose aggregates follow the weights), but each costs less than half
//! as much and the hierarchy is rebuilt for every step at the cost of about one cycle
//! (docs/integration.md, "The reweighting steps on the pixel grid").
//!
//! Memory: [`BYTES_PER_CELL`] per pixel of the domain's bounding box at the peak, taken by
//! [`crate::integrate::Integrator::working_bytes`] for streamed runs.
//!
//! Fails where: the bounding box, not the mask, sets the cost — a thin diagonal mask costs as
//! much as the rectangle around it. The `f32` vectors do not limit the accuracy: A p is summed
//! in `f64`, so the residual the solve carries stays the true one (a 1024² test grid reaches a
//! relative residual of 1e-8 in 11 iterations, within 1e-7 of the solution's range).

use super::{
    COARSEST, Coarsest, Csr, KCYCLE_MIN_RATIO, KCYCLE_T, KVectors, STALLED_SWEEPS, Work,
    dense_factor, second_step,
};
use crate::grid::Window;
use crate::integrate::sparse::{Convergence, Misfit, NONE, Stencil, Stop, Unknowns, dot};
use faer::MatMut;
use faer::linalg::solvers::Solve;
use rayon::prelude::*;

/// Bytes of working memory a cell of the grid costs at the peak of masked least squares on it
/// (`masked.rs`), besides the maps over the whole image, as counted for the solve, when most is
/// held at once: the finest level's weights and diagonal (12), the coarse levels' (4), the
/// domain (1), the solve's iterate and residual (16), direction and preconditioned residual
/// (8), and the cycle's scratch, allocated once for all levels ([`GridMultigrid::work`]): the
/// first coarse level's restricted residual, correction and five K-cycle vectors (7) and the
/// deeper levels' (about 4, counted generously); the connected parts' labels (4) are dropped
/// before the solve's vectors are allocated. That is 52; the bound is kept at 56, which also
/// held the finest level's cycle scratch (the fused sweeps no longer need it) and is what the
/// streamed plans were measured with. The measured growth of the peak with the window is lower,
/// 26–46 B a cell (1732×1732 normal maps under discs of radius 400, 600 and 800 px), so this is
/// an upper bound.
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
pub(super) const CELLS_PER_TASK: usize = 1 << 15;

/// Rows of a `w`-wide grid a parallel task takes at least.
pub(super) fn rows_per_task(w: usize) -> usize {
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
    pub fn new(w: usize, h: usize, right: Vec<f32>, down: Vec<f32>) -> Self {
        Self::with_diagonal_storage(w, h, right, down, Vec::new())
    }

    /// [`Self::new`], its diagonal written into the storage of `diag` (any length).
    fn with_diagonal_storage(
        w: usize,
        h: usize,
        mut right: Vec<f32>,
        mut down: Vec<f32>,
        mut diag: Vec<f32>,
    ) -> Self {
        for y in 0..h {
            right[y * w + w - 1] = 0.0;
        }
        if h > 0 {
            down[(h - 1) * w..].iter_mut().for_each(|v| *v = 0.0);
        }
        diag.clear();
        diag.resize(w * h, 0.0);
        diag.par_chunks_mut(w.max(1))
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(y, row)| {
                for (x, d) in row.iter_mut().enumerate() {
                    let i = y * w + x;
                    let mut s = f64::from(right[i]) + f64::from(down[i]);
                    if x > 0 {
                        s += f64::from(right[i - 1]);
                    }
                    if y > 0 {
                        s += f64::from(down[i - w]);
                    }
                    *d = round_up(s);
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

    /// Width of the grid.
    pub(super) fn width(&self) -> usize {
        self.w
    }

    /// Cells.
    pub fn len(&self) -> usize {
        self.w * self.h
    }

    /// Cells with at least one edge.
    fn active(&self) -> usize {
        self.diag.iter().filter(|&&d| d > 0.0).count()
    }

    /// Σ over the neighbours of each cell of row `row` of weight × x, into `out` (`w` long),
    /// given that row of x and the rows above and below it (`None` outside the grid). Summed in
    /// the same order for every cell (right, left, below, above), with no test per cell: the
    /// weights of edges that leave the grid are zero, and the loops run over whole rows, so they
    /// vectorise.
    #[inline(always)]
    fn row_neighbours(
        &self,
        row: usize,
        xr: &[f32],
        above: Option<&[f32]>,
        below: Option<&[f32]>,
        out: &mut [f32],
    ) {
        let w = self.w;
        let rw = &self.right[row * w..(row + 1) * w];
        if w == 1 {
            out[0] = 0.0;
        } else {
            out[0] = rw[0] * xr[1];
            for (((o, &a), &xa), (&c, &xc)) in out[1..w - 1]
                .iter_mut()
                .zip(&rw[1..w - 1])
                .zip(&xr[2..])
                .zip(rw[..w - 2].iter().zip(&xr[..w - 2]))
            {
                *o = a * xa + c * xc;
            }
            out[w - 1] = rw[w - 2] * xr[w - 2];
        }
        self.vertical(row, above, below, out, |o, a, v| *o += a * v);
    }

    /// `f(out, weight, x)` for the edge to the row below and then the edge to the row above,
    /// over row `row` (given those rows of x).
    #[inline(always)]
    fn vertical<T>(
        &self,
        row: usize,
        above: Option<&[f32]>,
        below: Option<&[f32]>,
        out: &mut [T],
        f: impl Fn(&mut T, f32, f32),
    ) {
        let w = self.w;
        for (edges, xs) in [(row * w, below), (row.saturating_sub(1) * w, above)] {
            if let Some(xs) = xs {
                for ((o, &a), &v) in out.iter_mut().zip(&self.down[edges..edges + w]).zip(xs) {
                    f(o, a, v);
                }
            }
        }
    }

    /// Row `row` of `x` (a whole grid) with the rows above and below it.
    #[inline(always)]
    fn rows_around<'a>(
        &self,
        x: &'a [f32],
        row: usize,
    ) -> (&'a [f32], Option<&'a [f32]>, Option<&'a [f32]>) {
        let w = self.w;
        (
            &x[row * w..(row + 1) * w],
            (row > 0).then(|| &x[(row - 1) * w..row * w]),
            (row + 1 < self.h).then(|| &x[(row + 1) * w..(row + 2) * w]),
        )
    }

    /// y = A x.
    pub(super) fn multiply(&self, x: &[f32], y: &mut [f32]) {
        self.multiply_dots(x, y, []);
    }

    /// y = A x, with x·y and x·uₖ for each of `u`, summed in `f64` row by row over fixed
    /// blocks of rows, the blocks' sums added in order.
    fn multiply_dots<const K: usize>(
        &self,
        x: &[f32],
        y: &mut [f32],
        u: [&[f32]; K],
    ) -> (f64, [f64; K]) {
        let w = self.w;
        let rows = rows_per_task(w);
        let block = |(k, chunk): (usize, &mut [f32])| {
            let mut nb = vec![0f32; w];
            let (mut xy, mut xu) = (0.0, [0.0; K]);
            for (r, out) in chunk.chunks_mut(w).enumerate() {
                let row = k * rows + r;
                let (xr, above, below) = self.rows_around(x, row);
                self.row_neighbours(row, xr, above, below, &mut nb);
                let d = &self.diag[row * w..(row + 1) * w];
                for (((o, &d), &v), &s) in out.iter_mut().zip(d).zip(xr).zip(&nb) {
                    *o = d * v - s;
                    xy += f64::from(v) * f64::from(*o);
                }
                for (s, u) in xu.iter_mut().zip(u) {
                    for (&v, &u) in xr.iter().zip(&u[row * w..(row + 1) * w]) {
                        *s += f64::from(v) * f64::from(u);
                    }
                }
            }
            (xy, xu)
        };
        if rows >= self.h {
            return block((0, y));
        }
        let partial: Vec<(f64, [f64; K])> =
            y.par_chunks_mut(rows * w).enumerate().map(block).collect();
        partial
            .into_iter()
            .fold((0.0, [0.0; K]), |(a, mut b), (c, d)| {
                b.iter_mut().zip(d).for_each(|(b, d)| *b += d);
                (a + c, b)
            })
    }

    /// (A x)ᵢ in `f64`, for the outer solve's A p: its residual is updated by it, and a rounded
    /// A p would let that residual drift from the true one (the depth error then grows with the
    /// grid: 7e-6 of the range on a 1024² test grid, against 1e-7). It is recomputed where
    /// needed rather than stored, which saves 8 bytes a cell for two more stencil passes.
    #[inline(always)]
    fn row_wide(&self, x: &[f32], row: usize, out: &mut [f64]) {
        let w = self.w;
        let (xr, above, below) = self.rows_around(x, row);
        let d = &self.diag[row * w..(row + 1) * w];
        for ((o, &d), &v) in out.iter_mut().zip(d).zip(xr) {
            *o = f64::from(d) * f64::from(v);
        }
        let term = |weight: f32, v: f32| f64::from(weight) * f64::from(v);
        let rw = &self.right[row * w..(row + 1) * w];
        if w > 1 {
            for ((o, &a), &v) in out[..w - 1].iter_mut().zip(&rw[..w - 1]).zip(&xr[1..]) {
                *o -= term(a, v);
            }
            for ((o, &a), &v) in out[1..].iter_mut().zip(&rw[..w - 1]).zip(&xr[..w - 1]) {
                *o -= term(a, v);
            }
        }
        self.vertical(row, above, below, out, |o, a, v| *o -= term(a, v));
    }

    /// zᵀAz, pᵀAz and rᵀz in one pass (A z taken row by row in `f64`), each summed over fixed
    /// blocks of rows in order (the same on any number of threads).
    fn energy_dots(&self, z: &[f32], p: &[f32], r: &[f64]) -> [f64; 3] {
        let w = self.w;
        let rows = rows_per_task(w);
        let partial: Vec<[f64; 3]> = (0..self.h.div_ceil(rows))
            .into_par_iter()
            .map(|block| {
                let mut az = vec![0f64; w];
                let mut sums = [0.0; 3];
                for row in block * rows..((block + 1) * rows).min(self.h) {
                    self.row_wide(z, row, &mut az);
                    let span = row * w..(row + 1) * w;
                    for (((&a, &z), &p), &r) in az
                        .iter()
                        .zip(&z[span.clone()])
                        .zip(&p[span.clone()])
                        .zip(&r[span])
                    {
                        sums[0] += f64::from(z) * a;
                        sums[1] += f64::from(p) * a;
                        sums[2] += r * f64::from(z);
                    }
                }
                sums
            })
            .collect();
        partial.iter().fold([0.0; 3], |mut t, s| {
            t.iter_mut().zip(s).for_each(|(t, s)| *t += s);
            t
        })
    }

    /// One step of conjugate gradients along `p`: x += α p and r −= α A p, A p taken row by row
    /// in `f64`; returns |r|² after it, summed over fixed blocks of rows in order.
    fn step(&self, x: &mut [f64], r: &mut [f64], p: &[f32], alpha: f64) -> f64 {
        let w = self.w;
        let rows = rows_per_task(w);
        let partial: Vec<f64> = x
            .par_chunks_mut(rows * w)
            .zip(r.par_chunks_mut(rows * w))
            .enumerate()
            .map(|(block, (x, r))| {
                let mut ap = vec![0f64; w];
                let mut rr = 0.0;
                for ((k, x), r) in x.chunks_mut(w).enumerate().zip(r.chunks_mut(w)) {
                    let row = block * rows + k;
                    self.row_wide(p, row, &mut ap);
                    for (((x, r), &d), &ap) in x.iter_mut().zip(r).zip(&p[row * w..]).zip(&ap) {
                        *x += alpha * f64::from(d);
                        *r -= alpha * ap;
                        rr += *r * *r;
                    }
                }
                rr
            })
            .collect();
        partial.iter().sum()
    }

    /// The residual b − A x of row `row` (0 on inactive cells, which carry no equation), into
    /// `out`, with `nb` as scratch.
    #[inline(always)]
    fn row_residual<B: Rhs>(
        &self,
        b: &[B],
        x: &[f32],
        row: usize,
        nb: &mut [f32],
        out: &mut [f32],
    ) {
        let w = self.w;
        let (xr, above, below) = self.rows_around(x, row);
        self.row_neighbours(row, xr, above, below, nb);
        let (d, br) = (
            &self.diag[row * w..(row + 1) * w],
            &b[row * w..(row + 1) * w],
        );
        for ((((o, &d), &v), &s), &b) in out.iter_mut().zip(d).zip(xr).zip(nb.iter()).zip(br) {
            *o = if d > 0.0 {
                b.single() - (d * v - s)
            } else {
                0.0
            };
        }
    }

    /// rc = Pᵀ (b − A x): each 2×2 block's sum of the residual, without storing the residual.
    fn restricted_residual<B: Rhs>(&self, b: &[B], x: &[f32], rc: &mut [f32]) {
        let (w, h) = (self.w, self.h);
        let (wc, _) = self.coarse_size();
        let rows = rows_per_task(wc);
        let block = |(k, chunk): (usize, &mut [f32])| {
            let (mut nb, mut res) = (vec![0f32; w], vec![0f32; w]);
            for (r, out) in chunk.chunks_mut(wc).enumerate() {
                let row = k * rows + r;
                // Summed as the blocks are read, row by row: ((r00 + r01) + r10) + r11.
                for y in 2 * row..(2 * row + 2).min(h) {
                    let first = y == 2 * row;
                    self.row_residual(b, x, y, &mut nb, &mut res);
                    for (col, o) in out.iter_mut().enumerate() {
                        *o = if first {
                            res[2 * col]
                        } else {
                            *o + res[2 * col]
                        };
                        if 2 * col + 1 < w {
                            *o += res[2 * col + 1];
                        }
                    }
                }
            }
        };
        if rows * 2 >= h {
            block((0, rc));
        } else {
            rc.par_chunks_mut(rows * wc).enumerate().for_each(block);
        }
    }

    /// Copies of the row above and the row below each block of `rows` rows (`None` outside the
    /// grid).
    fn halos(&self, x: &[f32], rows: usize) -> Vec<Halo> {
        let (w, h) = (self.w, self.h);
        (0..h.div_ceil(rows))
            .map(|k| {
                let (r0, r1) = (k * rows, ((k + 1) * rows).min(h));
                (
                    (r0 > 0).then(|| x[(r0 - 1) * w..r0 * w].to_vec()),
                    (r1 < h).then(|| x[r1 * w..(r1 + 1) * w].to_vec()),
                )
            })
            .collect()
    }

    /// Gauss–Seidel on the cells of one colour ((column + row) mod 2) of row `r` of a block;
    /// rows outside the block come from its halo. A cell's new value depends only on the other
    /// colour's.
    #[inline(always)]
    fn relax_row<B: Rhs>(
        &self,
        b: &[B],
        block: &mut Block,
        r: usize,
        colour: usize,
        nb: &mut [f32],
    ) {
        let w = self.w;
        let Block {
            rows: chunk,
            first: row0,
            halo,
        } = block;
        let row0 = *row0;
        let n = chunk.len() / w;
        let row = row0 + r;
        {
            let xr = &chunk[r * w..(r + 1) * w];
            let up = if r > 0 {
                Some(&chunk[(r - 1) * w..r * w])
            } else {
                halo.0.as_deref()
            };
            let down = if r + 1 < n {
                Some(&chunk[(r + 1) * w..(r + 2) * w])
            } else {
                halo.1.as_deref()
            };
            self.row_neighbours(row, xr, up, down, nb);
        }
        let (d, br) = (
            &self.diag[row * w..(row + 1) * w],
            &b[row * w..(row + 1) * w],
        );
        let out = &mut chunk[r * w..(r + 1) * w];
        for col in ((row + colour) & 1..w).step_by(2) {
            out[col] = if d[col] > 0.0 {
                (br[col].single() + nb[col]) / d[col]
            } else {
                0.0
            };
        }
    }

    /// Calls `f(block, scratch row)` on blocks of `rows` rows of x, in parallel when there are
    /// several.
    fn for_blocks(
        &self,
        x: &mut [f32],
        rows: usize,
        halo: Vec<Halo>,
        f: impl Fn(&mut Block, &mut [f32]) + Sync,
    ) {
        let w = self.w;
        let block = |((k, chunk), halo): ((usize, &mut [f32]), Halo)| {
            let mut nb = vec![0f32; w];
            f(
                &mut Block {
                    rows: chunk,
                    first: k * rows,
                    halo: &halo,
                },
                &mut nb,
            );
        };
        if rows >= self.h {
            block(((0, x), halo.into_iter().next().unwrap_or((None, None))));
        } else {
            x.par_chunks_mut(rows * w)
                .enumerate()
                .zip(halo)
                .for_each(block);
        }
    }

    /// Half of a symmetric Gauss–Seidel step in red–black order, in place: forward, red then
    /// black; backward, black then red. Both colours are relaxed in one pass over the rows,
    /// the second colour a row behind the first (row y − 1's second colour needs the first
    /// colour's new values in rows y − 2 … y, and row y's first colour the second colour's old
    /// values in rows y − 1 … y + 1), which gives the same values as two half-sweeps for half
    /// the memory traffic. Blocks of rows run in parallel: each relaxes the first colour on all
    /// its rows and the second on its inner rows, reading copies of the rows around it (their
    /// second colour, unchanged until then), and then the second colour on its first and last
    /// rows, from fresh copies.
    pub(super) fn sweep<B: Rhs>(&self, b: &[B], x: &mut [f32], forward: bool) {
        let (first, second) = if forward { (0, 1) } else { (1, 0) };
        let w = self.w;
        let rows = rows_per_task(w);
        let halo = self.halos(x, rows);
        self.for_blocks(x, rows, halo, |block, nb| {
            for r in 0..block.rows.len() / w {
                self.relax_row(b, block, r, first, nb);
                if r >= 2 {
                    self.relax_row(b, block, r - 1, second, nb);
                }
            }
        });
        let halo = self.halos(x, rows);
        self.for_blocks(x, rows, halo, |block, nb| {
            let n = block.rows.len() / w;
            self.relax_row(b, block, 0, second, nb);
            if n > 1 {
                self.relax_row(b, block, n - 1, second, nb);
            }
        });
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
    #[cfg(test)]
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

/// `v` rounded to the nearest `f32` at or above it: a diagonal stored so is never below the sum
/// of its row's weights, so every level stays diagonally dominant, hence positive
/// semidefinite, whatever the spread of its weights (rounded to nearest, an edge of weight
/// 10⁻⁸ of its neighbours' is lost to the diagonal's rounding and the level can be indefinite
/// along the mode that edge alone holds). Sums of small integers (masked least squares' unit
/// weights) are exact and unchanged.
fn round_up(v: f64) -> f32 {
    let r = v as f32;
    if f64::from(r) < v { r.next_up() } else { r }
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

    /// The finest level, the hierarchy's other levels dropped.
    fn into_finest(self) -> GridLaplacian {
        let mut levels = self.levels;
        levels.truncate(1);
        levels.pop().expect("at least the finest level")
    }

    /// [`Self::work`] in the storage of `work` (from an earlier hierarchy, any sizes): the same
    /// zeros, without fresh allocations where the sizes are those already held.
    fn reset_work(&self, work: &mut Vec<Work<f32>>) {
        let coarse = &self.levels[1..];
        work.truncate(coarse.len());
        for (w, level) in work.iter_mut().zip(coarse) {
            w.reset(level.len());
        }
        for level in &coarse[work.len()..] {
            work.push(Work::zeros(level.len()));
        }
    }

    /// The scratch vectors of the cycle, kept between cycles (see [`Work`]).
    pub fn work(&self) -> Vec<Work<f32>> {
        self.levels[1..]
            .iter()
            .map(|level| Work::zeros(level.len()))
            .collect()
    }

    /// z = M⁻¹ r: one cycle from zero, with the scratch of [`Self::work`].
    pub fn apply<B: Rhs>(&self, r: &[B], z: &mut [f32], work: &mut [Work<f32>]) {
        self.cycle(0, r, z, work);
    }

    /// The K-cycle's coarse correction on `level` (Notay 2010): as the aggregation hierarchy's
    /// (`Multigrid::krylov`) but on grids, with the scratch of `own` and the deeper levels' in
    /// `deeper`, and each matrix product fused with the dot products that follow it.
    fn krylov(
        &self,
        level: usize,
        b: &[f32],
        x: &mut [f32],
        own: &mut KVectors<f32>,
        deeper: &mut [Work<f32>],
    ) {
        if level + 1 == self.levels.len() {
            self.cycle(level, b, x, deeper);
            return;
        }
        let a = &self.levels[level];
        let second =
            self.active[level] as f64 / self.active[level + 1].max(1) as f64 >= KCYCLE_MIN_RATIO;
        let KVectors { c1, v1, r2, c2, v2 } = own;
        self.cycle(level, b, c1, deeper);
        let (rho1, [alpha1]) = a.multiply_dots(c1, v1, [b]);
        if rho1.is_nan() || rho1 <= 0.0 {
            x.copy_from_slice(c1);
            return;
        }
        let s1 = alpha1 / rho1;
        let first_only = |x: &mut [f32], c1: &[f32]| {
            elementwise(x, |i, x| {
                for (x, &c) in x.iter_mut().zip(&c1[i..]) {
                    *x = (s1 * f64::from(c)) as f32;
                }
            });
        };
        // r2 = b − s1 v1, with |r2|² and |b|².
        let [r2r2, bb] = sums(r2, |i, r2| {
            let mut s = [0.0; 2];
            for ((r, &b), &v) in r2.iter_mut().zip(&b[i..]).zip(&v1[i..]) {
                *r = (f64::from(b) - s1 * f64::from(v)) as f32;
                s[0] += f64::from(*r) * f64::from(*r);
                s[1] += f64::from(b) * f64::from(b);
            }
            s
        });
        if !second || r2r2 <= KCYCLE_T * KCYCLE_T * bb {
            first_only(x, c1);
            return;
        }
        self.cycle(level, r2, c2, deeper);
        let (beta, [gamma, alpha2]) = a.multiply_dots(c2, v2, [v1, r2]);
        let Some((k1, k2)) = second_step(alpha1, rho1, gamma, beta, alpha2) else {
            first_only(x, c1);
            return;
        };
        elementwise(x, |i, x| {
            for ((x, &c1), &c2) in x.iter_mut().zip(&c1[i..]).zip(&c2[i..]) {
                *x = (k1 * f64::from(c1) + k2 * f64::from(c2)) as f32;
            }
        });
    }

    /// One cycle on `level` from x = 0; `work` holds the scratch of the levels below it.
    fn cycle<B: Rhs>(&self, level: usize, b: &[B], x: &mut [f32], work: &mut [Work<f32>]) {
        let a = &self.levels[level];
        x.fill(0.0);
        if level + 1 == self.levels.len() {
            self.coarsest_solve(a, b, x);
            return;
        }
        let Some((next, deeper)) = work.split_first_mut() else {
            return;
        };
        a.sweep(b, x, true);
        a.restricted_residual(b, x, &mut next.rc);
        let Work { rc, xc, k } = next;
        self.krylov(level + 1, rc, xc, k, deeper);
        a.prolong_add(xc, x);
        a.sweep(b, x, false);
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
                for _ in 0..STALLED_SWEEPS {
                    a.sweep(b, x, true);
                    a.sweep(b, x, false);
                }
            }
        }
    }
}

/// Copies of the rows just above and below a block of rows.
type Halo = (Option<Vec<f32>>, Option<Vec<f32>>);

/// A block of rows of x in a sweep: the rows, the index of the first, and copies of the rows
/// around it.
struct Block<'a> {
    rows: &'a mut [f32],
    first: usize,
    halo: &'a Halo,
}

/// Calls `f(offset, chunk)` on fixed chunks of `x`, in parallel when there are several.
fn elementwise(x: &mut [f32], f: impl Fn(usize, &mut [f32]) + Sync) {
    sums(x, |i, chunk| {
        f(i, chunk);
        []
    });
}

/// As [`elementwise`], with `N` sums that `f` returns for each chunk, added in chunk order (the
/// same on any number of threads).
fn sums<const N: usize>(
    x: &mut [f32],
    f: impl Fn(usize, &mut [f32]) -> [f64; N] + Sync,
) -> [f64; N] {
    let add = |mut a: [f64; N], b: [f64; N]| {
        a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
        a
    };
    if x.len() <= CELLS_PER_TASK {
        return f(0, x);
    }
    let partial: Vec<[f64; N]> = x
        .par_chunks_mut(CELLS_PER_TASK)
        .enumerate()
        .map(|(k, chunk)| f(k * CELLS_PER_TASK, chunk))
        .collect();
    partial.into_iter().fold([0.0; N], add)
}

/// Bytes a cell of the unknowns' bounding box that a [`GridPreconditioner`] holds, counted: the
/// finest level's weights and diagonal (12), the coarse levels' (4), the scattered residual
/// (`f64`, 8) and the gathered correction (`f32`, 4), and the cycle's scratch on the coarse
/// levels, about a third of the cells with seven `f32` vectors (10); 38, kept at 40. Besides,
/// 4 B an unknown for its window cell.
pub const PRECONDITIONER_BYTES_PER_CELL: u64 = 40;

/// The grid multigrid as the preconditioner of a weighted graph Laplacian on masked unknowns
/// (a [`Stencil`] on [`Unknowns`]): the hierarchy is built on the unknowns' bounding box, with
/// each edge's weight rounded to `f32`, and a residual is scattered into that window, cycled
/// and gathered back. The outer solve keeps the exact `f64` system; only the preconditioner
/// is rounded (its levels stay positive semidefinite: [`round_up`]).
pub(crate) struct GridPreconditioner {
    mg: GridMultigrid,
    /// The window cell of each unknown.
    cell: WindowCells,
}

/// The scratch of [`GridPreconditioner::apply`], kept between applications.
pub(crate) struct GridScratch {
    r: Vec<f64>,
    z: Vec<f32>,
    work: Vec<Work<f32>>,
}

/// Where a window's unknowns lie: the cell of each (unknowns are numbered in row-major order,
/// and so are their cells), and for each row of the window the first unknown at or below it,
/// so that the unknowns of a block of rows are one range and the cells of different blocks can
/// be written in parallel.
pub(crate) struct WindowCells {
    /// The window cell of each unknown.
    pub(super) cell: Vec<u32>,
    /// The window's width.
    w: usize,
    /// For each row y of the window (and y = its height), the number of unknowns in the rows
    /// above it.
    starts: Vec<usize>,
}

impl WindowCells {
    /// Calls `f(k, &mut grid[cell of k])` for every unknown k, in parallel blocks of rows of
    /// `grid` (the window's size); the other cells are left alone.
    pub(super) fn scatter<T: Send>(&self, grid: &mut [T], f: impl Fn(usize, &mut T) + Sync) {
        debug_assert_eq!(grid.len(), self.w * (self.starts.len() - 1));
        let w = self.w;
        let rows = rows_per_task(w);
        let h = self.starts.len() - 1;
        grid.par_chunks_mut(rows * w)
            .enumerate()
            .for_each(|(b, block)| {
                let (y0, y1) = (b * rows, ((b + 1) * rows).min(h));
                for k in self.starts[y0]..self.starts[y1] {
                    f(k, &mut block[self.cell[k] as usize - y0 * w]);
                }
            });
    }

    /// out[k] = `grid`[cell of k] for every unknown k, in parallel.
    pub(super) fn gather(&self, grid: &[f32], out: &mut [f64]) {
        out.par_iter_mut()
            .zip(self.cell.par_iter())
            .with_min_len(CELLS_PER_TASK)
            .for_each(|(z, &c)| *z = f64::from(grid[c as usize]));
    }
}

/// The cells of `u`'s unknowns in `window`, which holds them all.
pub(super) fn window_cells(u: &Unknowns, window: Window) -> WindowCells {
    let cell: Vec<u32> = u
        .pixel
        .iter()
        .map(|&p| {
            let c = window.local(u.w, p as usize);
            debug_assert!(c.is_some(), "unknown at pixel {p} outside {window}");
            c.unwrap_or(0) as u32
        })
        .collect();
    let w = window.width();
    let starts = (0..=window.height())
        .map(|y| cell.partition_point(|&c| (c as usize) < y * w))
        .collect();
    WindowCells { cell, w, starts }
}

/// Writes the edge weights of `a` (off-diagonals −weight) into the window's grids `right` and
/// `down` at each unknown's cell, rounded to `f32`; cells without an unknown or an edge are
/// left as they are (zero).
pub(super) fn scatter_weights(
    u: &Unknowns,
    a: &Stencil,
    cells: &WindowCells,
    right: &mut [f32],
    down: &mut [f32],
) {
    cells.scatter(right, |k, v| {
        if u.right[k] != NONE {
            *v = (-a.right[k]).max(0.0) as f32;
        }
    });
    cells.scatter(down, |k, v| {
        if u.down[k] != NONE {
            *v = (-a.down[k]).max(0.0) as f32;
        }
    });
}

impl GridPreconditioner {
    /// The hierarchy of `a` (off-diagonals −weight, as [`Stencil::add_edge`] writes them) on
    /// `window`, which holds every unknown of `u` (the domain's bounding box).
    pub fn new(u: &Unknowns, a: &Stencil, window: Window) -> Self {
        let cell = window_cells(u, window);
        let (w, h) = (window.width(), window.height());
        let cells = || vec![0f32; w * h];
        Self::build(u, a, (w, h), cell, (cells(), cells(), Vec::new()))
    }

    /// The hierarchy of `a`, new weights on the unknowns and window of `self`, built in the
    /// storage of `self`'s finest level and window cells: the bilateral integrator's
    /// reweighting steps rebuild it for every step, and on large windows fresh storage costs
    /// page faults (the kernel clearing each new page) as much as the build itself. The same
    /// hierarchy, value for value, as [`Self::new`] builds.
    pub fn rebuild(self, u: &Unknowns, a: &Stencil) -> Self {
        let GridPreconditioner { mg, cell } = self;
        let finest = mg.into_finest();
        let (w, h) = (finest.w, finest.h);
        let GridLaplacian {
            mut right,
            mut down,
            diag,
            ..
        } = finest;
        right.fill(0.0);
        down.fill(0.0);
        Self::build(u, a, (w, h), cell, (right, down, diag))
    }

    /// The hierarchy of `a` on a `w`×`h` window whose cell of each unknown is `cell`, its finest
    /// level's edge weights and diagonal written into `storage` (right and down zero, of the
    /// window's size; the diagonal of any size).
    fn build(
        u: &Unknowns,
        a: &Stencil,
        (w, h): (usize, usize),
        cell: WindowCells,
        (mut right, mut down, diag): (Vec<f32>, Vec<f32>, Vec<f32>),
    ) -> Self {
        scatter_weights(u, a, &cell, &mut right, &mut down);
        GridPreconditioner {
            mg: GridMultigrid::new(GridLaplacian::with_diagonal_storage(
                w, h, right, down, diag,
            )),
            cell,
        }
    }

    /// Scratch for [`Self::apply`].
    pub fn scratch(&self) -> GridScratch {
        let n = self.mg.finest().len();
        GridScratch {
            r: vec![0.0; n],
            z: vec![0.0; n],
            work: self.mg.work(),
        }
    }

    /// [`Self::scratch`] in the storage of `old` (another hierarchy's scratch, of any sizes):
    /// the same zeros, without fresh allocations where the sizes are those already held.
    pub fn scratch_in(&self, old: GridScratch) -> GridScratch {
        let n = self.mg.finest().len();
        let GridScratch {
            mut r,
            mut z,
            mut work,
        } = old;
        r.clear();
        r.resize(n, 0.0);
        z.clear();
        z.resize(n, 0.0);
        self.mg.reset_work(&mut work);
        GridScratch { r, z, work }
    }

    /// z = M⁻¹ r.
    pub fn apply(&self, r: &[f64], z: &mut [f64], s: &mut GridScratch) {
        self.cell.scatter(&mut s.r, |k, v| *v = r[k]);
        self.mg.apply(&s.r, &mut s.z, &mut s.work);
        self.cell.gather(&s.z, z);
    }
}

/// Connected parts of the active cells through edges of positive weight: a label per cell
/// ([`NONE`] for inactive cells) and the number of parts, numbered in the order of each part's
/// first cell in row-major order.
///
/// One scan joins each cell to its left and upper neighbours in a union–find forest whose
/// links always point to a lower index (with path halving), so that every root is its part's
/// first cell; a second scan makes every link point to its root, and a third replaces the links
/// by part numbers in place (a cell's root comes before it, so its number is already written).
/// Linear in the cells, sequential, and 4 bytes a cell.
pub(crate) fn parts(a: &GridLaplacian) -> (Vec<u32>, usize) {
    let (w, n) = (a.w, a.len());
    let mut link: Vec<u32> = (0..n as u32).collect();
    let root = |link: &mut [u32], mut i: usize| {
        while link[i] as usize != i {
            let up = link[link[i] as usize];
            link[i] = up;
            i = up as usize;
        }
        i
    };
    for i in 0..n {
        let join = |j: usize, link: &mut Vec<u32>| {
            let (ri, rj) = (root(link, i), root(link, j));
            if ri != rj {
                link[ri.max(rj)] = ri.min(rj) as u32;
            }
        };
        if i % w > 0 && a.right[i - 1] > 0.0 {
            join(i - 1, &mut link);
        }
        if i >= w && a.down[i - w] > 0.0 {
            join(i - w, &mut link);
        }
    }
    for i in 0..n {
        link[i] = link[link[i] as usize];
    }
    let mut count = 0u32;
    for i in 0..n {
        let r = link[i] as usize;
        link[i] = if a.diag[i] <= 0.0 {
            NONE
        } else if r == i {
            count += 1;
            count - 1
        } else {
            link[r]
        };
    }
    (link, count as usize)
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
/// first, and zero on inactive cells; `parts` are the labels and count of [`parts`] of A,
/// dropped before the solve's vectors are allocated) by
/// flexible conjugate gradients preconditioned with `mg`, from x = 0 until `stop`; returns x
/// (zero on inactive cells), the iterations used and why the solve stopped.
///
/// The iterate and the residual are `f64`, the direction and preconditioned residual `f32`, and
/// A p is recomputed in `f64` where it is needed ([`GridLaplacian::row_wide`]): the residual's
/// updates are then exact to `f64` for the (rounded) direction the iterate moves along, so it
/// stays the true residual. (An `f32` iterate gathers rounding noise at every step: on a 5000²
/// sphere of depth range 2000 px it raised the mean integration residual from 9.1e-4 to
/// 1.2e-3.) 24 bytes a cell, besides the hierarchy.
pub(crate) fn solve(
    mg: &GridMultigrid,
    mut b: Vec<f64>,
    (label, parts): (Vec<u32>, usize),
    stop: Stop,
) -> (Vec<f64>, usize, Convergence) {
    let Stop { tol, max_iter, .. } = stop;
    let a = mg.finest();
    let n = a.len();
    let means = part_means(&b, &label, parts);
    b.par_iter_mut().zip(&label).for_each(|(v, &l)| {
        *v = if l == NONE {
            0.0
        } else {
            *v - means[l as usize]
        };
    });
    // The labels go before the solve's own vectors are allocated.
    drop(label);
    // Zeros written, not a zeroed allocation: the first step reads x before writing it, and a
    // zeroed allocation's pages are first mapped to the shared zero page, so each would fault
    // twice (the second time with a TLB shootdown across the threads).
    let mut x: Vec<f64> = (0..n).into_par_iter().map(|_| 0.0).collect();
    let bn = dot(&b, &b).sqrt();
    if bn == 0.0 || bn <= tol * bn {
        return (x, 0, Convergence::Residual);
    }
    // The residual, from x = 0. Convergence is tested as soon as a residual is known, before
    // the cycle that would precondition it (most of an iteration's cost).
    // From x = 0 the misfit starts at |d|².
    let mut misfit = stop.data.map(|d| Misfit::new(d, 0.0, 0.0));
    let mut r = b;
    let mut z = vec![0f32; n];
    let mut work = mg.work();
    mg.apply(&r, &mut z, &mut work);
    let mut p = z.clone();
    // pᵀAp by its recurrence below (p = z + βp_prev), seeded with zᵀAz.
    let [mut pap, _, mut rz] = a.energy_dots(&z, &p, &r);
    for it in 1..=max_iter {
        if pap <= 0.0 || !pap.is_finite() {
            return (x, it - 1, Convergence::Breakdown);
        }
        let alpha = rz / pap;
        let rr = a.step(&mut x, &mut r, &p, alpha);
        if rr.sqrt() <= tol * bn {
            return (x, it, Convergence::Residual);
        }
        if misfit.as_mut().is_some_and(|m| m.step(alpha * rz)) {
            return (x, it, Convergence::DataNoise);
        }
        mg.apply(&r, &mut z, &mut work);
        let [zaz, paz, rz_new] = a.energy_dots(&z, &p, &r);
        // Flexible (Polak–Ribière) β for the K-cycle, which is not a fixed linear map:
        // zᵀ(r − r_prev)/ρ_prev, with r − r_prev = −α A p and pᵀAz = zᵀAp.
        let beta = -alpha * paz / rz;
        // The new direction's pᵀAp = zᵀAz + 2β pᵀAz + β² p_prevᵀAp_prev, from the products
        // just taken: no pass of its own.
        pap = zaz + 2.0 * beta * paz + beta * beta * pap;
        rz = rz_new;
        p.par_iter_mut()
            .zip(&z)
            .with_min_len(CELLS_PER_TASK)
            .for_each(|(p, &z)| *p = (f64::from(z) + beta * f64::from(*p)) as f32);
    }
    (x, max_iter, Convergence::IterationLimit)
}

#[cfg(test)]
pub(in crate::integrate::multigrid) mod tests {
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
        let stop = Stop {
            tol: 1e-8,
            max_iter: 200,
            data: None,
        };
        let (x, its, _) = solve(&mg, b, (label.clone(), parts), stop);
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

    /// A grid of `w`×`h` with irregular unit and fractional weights (some cells inactive), an
    /// iterate and a right-hand side.
    fn irregular(w: usize, h: usize) -> (GridLaplacian, Vec<f32>, Vec<f64>) {
        let weight = |k: usize| match (k * 2654435761) % 7 {
            0 | 1 => 0.0,
            2 => 0.5,
            _ => 1.0,
        };
        let right = (0..w * h).map(weight).collect();
        let down = (0..w * h).map(|k| weight(k + 3)).collect();
        let a = GridLaplacian::new(w, h, right, down);
        let x = (0..w * h)
            .map(|k| ((k * 7919) % 101) as f32 / 7.0)
            .collect();
        let b = (0..w * h).map(|k| ((k * 31) % 17) as f64 - 8.3).collect();
        (a, x, b)
    }

    /// (A x)ᵢ cell by cell, with the bounds tested per cell: the reference for the row kernels.
    fn reference_neighbours(a: &GridLaplacian, x: &[f32], i: usize) -> f32 {
        let (w, col, row) = (a.w, i % a.w, i / a.w);
        let mut s = 0.0;
        if col + 1 < w {
            s += a.right[i] * x[i + 1];
        }
        if col > 0 {
            s += a.right[i - 1] * x[i - 1];
        }
        if row + 1 < a.h {
            s += a.down[i] * x[i + w];
        }
        if row > 0 {
            s += a.down[i - w] * x[i - w];
        }
        s
    }

    /// The fused red–black sweep, in parallel blocks with copied rows between them, gives
    /// bit for bit what two half-sweeps cell by cell give, forward and backward, on one block
    /// and on several (a grid taller than a block), and the product and restricted residual
    /// what the cell-by-cell formulas give.
    #[test]
    fn row_kernels_match_the_cell_by_cell_formulas() {
        for (w, h) in [(1, 5), (7, 1), (37, 29), (64, 1500), (33, 2100)] {
            let (a, x0, b) = irregular(w, h);
            for forward in [true, false] {
                let mut fused = x0.clone();
                a.sweep(&b, &mut fused, forward);
                let mut reference = x0.clone();
                let order = if forward { [0, 1] } else { [1, 0] };
                for colour in order {
                    let old = reference.clone();
                    for i in 0..w * h {
                        if (i % w + i / w) % 2 == colour {
                            reference[i] = if a.diag[i] > 0.0 {
                                (b[i] as f32 + reference_neighbours(&a, &old, i)) / a.diag[i]
                            } else {
                                0.0
                            };
                        }
                    }
                }
                assert!(
                    fused
                        .iter()
                        .zip(&reference)
                        .all(|(p, q)| p.to_bits() == q.to_bits()),
                    "{w}×{h}, forward {forward}"
                );
            }
            let mut ax = vec![0f32; w * h];
            a.multiply(&x0, &mut ax);
            let xf: Vec<f32> = b.iter().map(|&v| v as f32).collect();
            let mut ax2 = vec![0f32; w * h];
            let (xy, [xu]) = a.multiply_dots(&x0, &mut ax2, [&xf]);
            assert_eq!(ax, ax2);
            let (mut ry, mut ru) = (0.0, 0.0);
            for i in 0..w * h {
                let v = a.diag[i] * x0[i] - reference_neighbours(&a, &x0, i);
                assert_eq!(ax[i].to_bits(), v.to_bits(), "{w}×{h}: A x at {i}");
                ry += f64::from(x0[i]) * f64::from(v);
                ru += f64::from(x0[i]) * f64::from(xf[i]);
            }
            assert!((xy - ry).abs() <= 1e-9 * ry.abs().max(1.0), "{xy} vs {ry}");
            assert!((xu - ru).abs() <= 1e-9 * ru.abs().max(1.0), "{xu} vs {ru}");
            let residual: Vec<f32> = (0..w * h)
                .map(|i| {
                    if a.diag[i] > 0.0 {
                        b[i] as f32 - ax[i]
                    } else {
                        0.0
                    }
                })
                .collect();
            let (wc, hc) = a.coarse_size();
            let (mut fused, mut reference) = (vec![0f32; wc * hc], vec![0f32; wc * hc]);
            a.restricted_residual(&b, &x0, &mut fused);
            a.restrict(&residual, &mut reference);
            assert_eq!(fused, reference, "{w}×{h}: restricted residual");
        }
    }

    /// The union–find labelling gives the parts a depth-first search gives, numbered alike.
    #[test]
    fn parts_match_a_depth_first_search() {
        for (w, h) in [(1, 1), (1, 9), (9, 1), (37, 29), (64, 300)] {
            // Edges present with probability 0.45, below the square lattice's bond percolation
            // threshold: many parts, of every shape.
            let edge = |k: usize| f32::from(u8::from((k * 2654435761) % 100 < 45));
            let a = GridLaplacian::new(
                w,
                h,
                (0..w * h).map(edge).collect(),
                (0..w * h).map(|k| edge(k * 7 + 11)).collect(),
            );
            let mut label = vec![NONE; a.len()];
            let mut count = 0u32;
            for s in 0..a.len() {
                if label[s] != NONE || a.diag[s] <= 0.0 {
                    continue;
                }
                label[s] = count;
                let mut stack = vec![s];
                while let Some(i) = stack.pop() {
                    let (x, y) = (i % w, i / w);
                    let mut edges = Vec::new();
                    if x + 1 < w {
                        edges.push((i + 1, a.right[i]));
                    }
                    if x > 0 {
                        edges.push((i - 1, a.right[i - 1]));
                    }
                    if y + 1 < h {
                        edges.push((i + w, a.down[i]));
                    }
                    if y > 0 {
                        edges.push((i - w, a.down[i - w]));
                    }
                    for (j, weight) in edges {
                        if weight > 0.0 && label[j] == NONE {
                            label[j] = count;
                            stack.push(j);
                        }
                    }
                }
                count += 1;
            }
            let (got, parts_found) = parts(&a);
            assert_eq!(parts_found, count as usize, "{w}×{h}");
            assert_eq!(got, label, "{w}×{h}");
            if w * h > 100 {
                assert!(count > 20, "{w}×{h}: {count} parts");
            }
        }
    }

    /// The misfit rule of [`Stop::data`] on the grid solver (as
    /// `conjugate_gradients_stop_within_the_noise_share` for the stencil solvers): on noisy
    /// edge differences of a smooth surface the solve returns a depth that could shed at most
    /// [`NOISE_SHARE`]² σ̂² more of its misfit than a solve to a relative residual of 10⁻¹³, in
    /// fewer iterations than 10⁻⁸ alone takes; on integrable differences the rule never
    /// applies.
    #[test]
    fn the_grid_solve_stops_within_the_noise_share() {
        use crate::integrate::sparse::{LeastSquares, NOISE_SHARE};
        let n = 256;
        let a = laplacian(n);
        let depth = |i: usize| {
            let (x, y) = ((i % n) as f64, (i / n) as f64);
            0.002 * (x - 90.0).powi(2) + 0.2 * y + 3.0 * (x / 17.0).sin() * (y / 23.0).cos()
        };
        let noise = |k: usize| {
            ((k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11) as f64 / (1u64 << 53) as f64
                - 0.5
        };
        let mut edges = Vec::new();
        for i in 0..a.len() {
            for (weight, j) in [(a.right[i], i + 1), (a.down[i], i + n)] {
                if weight > 0.0 {
                    edges.push((i, j, depth(j) - depth(i)));
                }
            }
        }
        let (label, parts) = parts(&a);
        let unknowns = label.iter().filter(|&&l| l != NONE).count();
        let mg = GridMultigrid::new(a);
        for sigma in [0.1, 0.0] {
            let d: Vec<(usize, usize, f64)> = edges
                .iter()
                .enumerate()
                .map(|(k, &(i, j, d))| (i, j, d + sigma * noise(k)))
                .collect();
            let mut b = vec![0.0; n * n];
            for &(i, j, d) in &d {
                b[i] -= d;
                b[j] += d;
            }
            let problem = LeastSquares {
                norm2: d.iter().map(|e| e.2 * e.2).sum(),
                redundancy: d.len() + parts - unknowns,
            };
            let run = |tol, data| {
                let stop = Stop {
                    tol,
                    max_iter: 200,
                    data,
                };
                solve(&mg, b.clone(), (label.clone(), parts), stop)
            };
            let f = |x: &[f64]| {
                d.iter()
                    .map(|&(i, j, d)| (x[j] - x[i] - d).powi(2))
                    .sum::<f64>()
            };
            let (early, its, how) = run(1e-8, Some(problem));
            let (_, plain, plain_how) = run(1e-8, None);
            assert_eq!(plain_how, Convergence::Residual);
            if sigma > 0.0 {
                assert_eq!(how, Convergence::DataNoise);
                let (tight, _, _) = run(1e-13, None);
                let variance = f(&tight) / problem.redundancy as f64;
                let excess = (f(&early) - f(&tight)) / variance;
                eprintln!("{its} iterations against {plain}, excess {excess:.2e} σ̂²");
                assert!(
                    excess <= NOISE_SHARE * NOISE_SHARE,
                    "excess {excess:.2e} σ̂²"
                );
                assert!(its < plain, "{its} iterations against {plain}");
            } else {
                assert_eq!((its, how), (plain, plain_how), "integrable differences");
            }
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

    /// Edge weights over twelve orders of magnitude, as a pseudo-random sequence (the same on
    /// every run).
    fn uneven(k: usize) -> f64 {
        let h = (k as u64)
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let unit = (h >> 11) as f64 / (1u64 << 53) as f64;
        10f64.powf(-12.0 * unit) * (1.0 + unit)
    }

    /// Every level's diagonal is at or above the sum of its row's stored weights, whatever
    /// their spread, so that every level is positive semidefinite (rounded to nearest, a
    /// diagonal falls below its row's sum in a fair share of the rows here).
    #[test]
    fn diagonals_never_fall_below_their_rows() {
        let n = 96;
        let right: Vec<f32> = (0..n * n).map(|k| uneven(2 * k) as f32).collect();
        let down: Vec<f32> = (0..n * n).map(|k| uneven(2 * k + 1) as f32).collect();
        let mg = GridMultigrid::new(GridLaplacian::new(n, n, right, down));
        let mut rows = 0;
        let mut nearest_below = 0;
        for level in &mg.levels {
            let w = level.w;
            for i in 0..level.len() {
                let (x, y) = (i % w, i / w);
                let mut terms = vec![level.right[i], level.down[i]];
                if x > 0 {
                    terms.push(level.right[i - 1]);
                }
                if y > 0 {
                    terms.push(level.down[i - w]);
                }
                let exact: f64 = terms.iter().map(|&v| f64::from(v)).sum();
                assert!(
                    f64::from(level.diag[i]) >= exact,
                    "level of width {w}, cell {i}: diagonal {} below its row's {exact}",
                    level.diag[i]
                );
                // What rounding the same sum to nearest would have given.
                if f64::from(exact as f32) < exact {
                    nearest_below += 1;
                }
                rows += 1;
            }
        }
        assert!(nearest_below * 10 > rows, "{nearest_below} of {rows}");
    }

    /// The masked unknowns and weights of the test below: a disc with a hole and a bar inside
    /// a wider image, weights spanning three orders of magnitude in a pattern moved by `shift`,
    /// and the edges to the right of the pixels on a line (column `pad + n/3`, but every ninth
    /// row) weighing `cut` — every edge of those pixels when `isolate`.
    pub(in crate::integrate::multigrid) fn uneven_weights(
        shift: usize,
        cut: f64,
        isolate: bool,
    ) -> (crate::grid::Mask, Unknowns, Stencil) {
        use crate::grid::Grid;
        let (n, pad) = (128, 24);
        let c = n as f64 * 0.35;
        let mask = Grid::from_fn(n + 2 * pad, n + pad, |x, y| {
            let (Some(x), Some(y)) = (x.checked_sub(pad), y.checked_sub(pad)) else {
                return false;
            };
            let (dx, dy) = (x as f64 - c, y as f64 - c);
            let r2 = dx * dx + dy * dy;
            x < n && ((r2 < (0.3 * n as f64).powi(2) && r2 > 4.0) || (x > 3 * n / 4 && y > n / 8))
        });
        let u = Unknowns::new(&mask);
        let mut a = Stencil::zeros(u.len());
        let mut unused = vec![0.0; u.len()];
        let on_line = |x: usize, y: usize| x == pad + n / 3 && !y.is_multiple_of(9);
        for i in 0..u.len() {
            let pix = u.pixel[i] as usize;
            let (x, y) = (pix % u.w, pix / u.w);
            for (nb, along) in [(u.right[i], true), (u.down[i], false)] {
                if nb != NONE {
                    let (x2, y2) = if along { (x + 1, y) } else { (x, y + 1) };
                    let cut_here = if isolate {
                        on_line(x, y) || on_line(x2, y2)
                    } else {
                        along && on_line(x, y)
                    };
                    let weight = if cut_here {
                        cut
                    } else {
                        10f64.powi((((x * 31 + y * 17 + shift) % 4) as i32) - 3)
                    };
                    a.add_edge(&mut unused, (i, nb as usize), along, weight, 0.0);
                }
            }
        }
        (mask, u, a)
    }

    /// The bilateral steps rebuild the hierarchy in the last step's storage and reuse the
    /// solve's vectors (`GridPreconditioner::rebuild`, `pcg_in`): that must solve as a hierarchy
    /// and vectors made afresh, value for value, also where the new weights change which cells
    /// are active (a line of pixels whose edges `f32` rounds to zero) and after the storage
    /// served another system.
    #[test]
    fn rebuilt_in_place_solves_as_built_afresh() {
        use crate::integrate::sparse::{PcgWork, Preconditioner, known_solution, pcg, pcg_in};
        let (mask, u, first) = uneven_weights(0, 1e-6, false);
        let (_, _, second) = uneven_weights(1, 1e-50, true);
        let window = mask.bounding_box().expect("a mask with pixels");
        let stop = Stop {
            tol: 1e-10,
            max_iter: 500,
            data: None,
        };
        let mut work = PcgWork::default();
        let old = GridPreconditioner::new(&u, &first, window);
        let (_, b) = known_solution(&u, &first);
        let mut x = vec![0.0; u.len()];
        pcg_in(
            &u,
            &first,
            &b,
            &mut x,
            &Preconditioner::Grid(&old),
            stop,
            &mut work,
        );
        let active = |g: &GridPreconditioner| g.mg.finest().active();
        let active_before = active(&old);
        let rebuilt = old.rebuild(&u, &second);
        let fresh = GridPreconditioner::new(&u, &second, window);
        assert!(
            active(&rebuilt) < active_before,
            "the active set did not change"
        );
        let (_, b) = known_solution(&u, &second);
        let (mut in_place, mut afresh) = (vec![0.0; u.len()], vec![0.0; u.len()]);
        let reused = pcg_in(
            &u,
            &second,
            &b,
            &mut in_place,
            &Preconditioner::Grid(&rebuilt),
            stop,
            &mut work,
        );
        let made = pcg(
            &u,
            &second,
            &b,
            &mut afresh,
            &Preconditioner::Grid(&fresh),
            stop,
        );
        assert_eq!(reused, made);
        assert_eq!(made.1, Convergence::Residual, "{made:?}");
        assert!(
            in_place
                .iter()
                .zip(&afresh)
                .all(|(p, q)| p.to_bits() == q.to_bits()),
            "the iterates differ"
        );
    }

    /// A scratch kept from another hierarchy (of another size and depth, and dirtied by a
    /// cycle) and reset for this one is the scratch made afresh: the same sizes, all zeros,
    /// and the same cycle bit for bit — both ways, from a deeper and from a shallower one.
    #[test]
    fn scratch_reset_from_another_hierarchy_is_made_afresh() {
        use crate::grid::Grid;
        let build = |n: usize| {
            let mask = Grid::from_fn(n, n, |x, y| !(x + y).is_multiple_of(7) || x == y);
            let u = Unknowns::new(&mask);
            let mut a = Stencil::zeros(u.len());
            let mut unused = vec![0.0; u.len()];
            for i in 0..u.len() {
                for (nb, along) in [(u.right[i], true), (u.down[i], false)] {
                    if nb != NONE {
                        let weight = 1.0 + (i % 5) as f64;
                        a.add_edge(&mut unused, (i, nb as usize), along, weight, 0.0);
                    }
                }
            }
            let window = mask.bounding_box().expect("a mask with pixels");
            let g = GridPreconditioner::new(&u, &a, window);
            let r: Vec<f64> = (0..u.len()).map(|k| ((k * 37) % 11) as f64 - 5.0).collect();
            (g, r)
        };
        let (small, r_small) = build(40);
        let (large, r_large) = build(300);
        assert!(large.mg.levels.len() > small.mg.levels.len());
        for ((from, r_from), (to, r_to)) in [
            ((&large, &r_large), (&small, &r_small)),
            ((&small, &r_small), (&large, &r_large)),
        ] {
            let mut dirty = from.scratch();
            let mut z = vec![0.0; r_from.len()];
            from.apply(r_from, &mut z, &mut dirty);
            let reset = to.scratch_in(dirty);
            let fresh = to.scratch();
            assert_eq!(reset.work.len(), fresh.work.len());
            assert!(reset.r.iter().chain(&fresh.r).all(|&v| v == 0.0));
            assert!(reset.z.iter().all(|&v| v == 0.0));
            assert_eq!(
                (reset.r.len(), reset.z.len()),
                (fresh.r.len(), fresh.z.len())
            );
            let (mut reused, mut afresh) = (reset, fresh);
            let (mut z1, mut z2) = (vec![0.0; r_to.len()], vec![0.0; r_to.len()]);
            to.apply(r_to, &mut z1, &mut reused);
            to.apply(r_to, &mut z2, &mut afresh);
            assert!(z1.iter().zip(&z2).all(|(p, q)| p.to_bits() == q.to_bits()));
        }
    }

    /// Masked unknowns (a disc with a hole and a bar, inside a wider image, so that their
    /// bounding box is a window of it) whose edge weights span three orders of magnitude, with
    /// a line of near-zero (cut) weights, as the bilateral integrator's reweighting steps make
    /// them (the aggregation hierarchy's test of the same weights, which it solves in 44
    /// iterations on its own mask): the
    /// grid preconditioner on the bounding box solves them in 71, where the diagonal (Jacobi)
    /// takes over a thousand.
    #[test]
    fn preconditions_uneven_weights_on_masked_unknowns() {
        use crate::integrate::sparse::{Preconditioner, solve_known};
        let (mask, u, a) = uneven_weights(0, 1e-6, false);
        assert_eq!(u.parts, 2);
        let window = mask.bounding_box().expect("a mask with pixels");
        let grid = GridPreconditioner::new(&u, &a, window);
        let solve = |pre: &Preconditioner| solve_known(&u, &a, pre, 5000);
        let (its, convergence, err) = solve(&Preconditioner::Grid(&grid));
        let (jacobi, _, _) = solve(&Preconditioner::Jacobi);
        eprintln!("grid: {its} iterations ({convergence:?}), error {err:.2e}; Jacobi {jacobi}");
        assert_eq!(convergence, Convergence::Residual);
        assert!(err < 1e-4, "error {err}");
        assert!(
            its <= 100 && 10 * its < jacobi,
            "{its} against Jacobi's {jacobi}"
        );
    }
}
