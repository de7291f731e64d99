//! The preconditioner of the bilateral integrator's re-integration beyond the direct limit:
//! Gauss–Seidel smoothing on the pixel grid, and a coarse correction on aggregates that never
//! join the two sides of a weak edge.
//!
//! The re-integration's system is a weighted 5-point graph Laplacian on the domain's pixels whose
//! cut edges weigh 10⁻⁶ of the others and whose weights fall towards 0 at grazing normals
//! (`bilateral.rs`). The two multigrid hierarchies of the parent module each get half of that
//! right:
//! - the grid hierarchy (`grid.rs`) smooths fast — whole rows in `f32`, red–black, in parallel —
//!   but its fixed 2×2 blocks join the two sides of a cut, so its coarse corrections cannot move
//!   one side without the other: the 1024² sphere's re-integration (1 192 cut edges at its rim)
//!   took 66 iterations with it against 12 with the aggregation hierarchy;
//! - the aggregation hierarchy (`mod.rs`) follows the weights (Notay's pairwise matching joins
//!   only strongly coupled nodes), but it smooths sequentially on compressed rows in `f64`, and
//!   its finest level, the one that costs most, is its slowest (about 65 ms an iteration on that
//!   sphere).
//!
//! So this one takes the finest level from the first and everything below from the second.
//! The finest level is the grid's (on the unknowns' bounding box, weights rounded to `f32`, each
//! diagonal upwards so that it stays positive semidefinite: `grid::round_up`), smoothed by a
//! red–black Gauss–Seidel sweep before the coarse correction (red, then black) and one after
//! it (black, then red): together one symmetric sweep. Its
//! aggregates are the **strongly coupled components of each 2×2 block**: two cells of a block
//! are joined when the edge between them weighs at least [`STRONG`] of the strongest coupling of
//! *each* of them (Notay's test, "An aggregation-based algebraic multigrid method", ETNA 37,
//! 2010, asked of both ends), so a block that a cut crosses becomes two aggregates (up to four)
//! and a smooth block one. The coarse level is the Galerkin product PᵀAP of the
//! piecewise-constant prolongation, computed in `f64` from the exact system — a graph Laplacian
//! again, each diagonal the sum of the aggregate's edges to the others (not the difference of
//! its members' diagonals and inner edges, which cancels the weak edges away when the weights
//! span many orders of magnitude) — and the aggregation hierarchy is built on it; its K-cycle
//! (Notay 2010) is the coarse correction. Aggregates are numbered in the order of their first
//! cell, so the aggregates of each pair of grid rows are a contiguous range and the residual is
//! restricted in parallel blocks of rows.
//!
//! Why not for the reweighting steps too: its build (union–find, Galerkin product, pairwise
//! aggregation) is sequential, about 45–58 ms at 1024² against the grid hierarchy's 15, and a
//! step is rebuilt every time and needs only a few iterations; measured there, it was slower on
//! every rendered scene (docs/integration.md, "A coarse level that follows the weights"). The
//! re-integration builds it once and runs 6–10 iterations to the data's noise.
//!
//! Memory: the finest level's weights and diagonal (12 B a cell of the window), its aggregate
//! (4), the scattered residual (`f64`, 8), the smoothed correction and its product with the
//! level (`f32`, 4 each); the coarse hierarchy holds about a quarter as many nodes as unknowns
//! where the blocks are smooth and inside the mask, up to one a node where cuts split every block
//! or the mask is one pixel thin (each such pixel its own aggregate).
//! Measured, the re-integration's peak is below the aggregation hierarchy's, which the
//! streamed plans count (`run/stream.rs`: 2048² sphere 745 → 654 MB, a 1024² torus on a ground
//! 350 → 314 MB for the whole `integrate` process).
//!
//! Fails where: the finest level's cost is set by the bounding box, not by the mask (as the grid
//! hierarchy's); the aggregation levels below are sequential.

use super::grid::{
    CELLS_PER_TASK, GridLaplacian, WindowCells, rows_per_task, scatter_weights, window_cells,
};
use super::{CoarseRows, Csr, Multigrid, STRONG, Work, aggregate_members};
use crate::grid::Window;
use crate::integrate::sparse::{NONE, Stencil, Unknowns};
use rayon::prelude::*;

/// The preconditioner (see the module documentation) of a weighted graph Laplacian on masked
/// unknowns (a [`Stencil`] on [`Unknowns`], off-diagonals −weight as [`Stencil::add_edge`]
/// writes them), on the unknowns' bounding box.
pub(crate) struct BlockPreconditioner {
    /// The finest level, on the window.
    finest: GridLaplacian,
    /// The aggregate of each window cell ([`NONE`] where there is no unknown).
    aggregate: Vec<u32>,
    /// Blocks of window rows (an even number each) restricted in parallel: the first row of
    /// each and its first aggregate, then (rows, aggregates).
    spans: Vec<(usize, usize)>,
    /// The window cell of each unknown.
    cell: WindowCells,
    /// The aggregation hierarchy on the aggregates.
    coarse: Multigrid,
}

/// The scratch of [`BlockPreconditioner::apply`], kept between applications.
pub(crate) struct BlockScratch {
    r: Vec<f64>,
    z: Vec<f32>,
    az: Vec<f32>,
    top: Work<f64>,
    deeper: Vec<Work<f64>>,
}

impl BlockPreconditioner {
    /// The preconditioner of `a` on `window`, which holds every unknown of `u` (the domain's
    /// bounding box).
    pub fn new(u: &Unknowns, a: &Stencil, window: Window) -> Self {
        let (w, h) = (window.width(), window.height());
        let cell = window_cells(u, window);
        let mut right = vec![0f32; w * h];
        let mut down = vec![0f32; w * h];
        scatter_weights(u, a, &cell, &mut right, &mut down);
        let finest = GridLaplacian::new(w, h, right, down);
        let (of_unknown, m) = block_aggregates(u, a, &cell.cell, w);
        let mut aggregate = vec![NONE; w * h];
        cell.scatter(&mut aggregate, |k, g| *g = of_unknown[k]);
        // Blocks of rows for the restriction: an even number of rows each, so that no 2×2 block
        // (and no aggregate) straddles two; each block's first aggregate is the number of
        // aggregates that start in the rows before it.
        let mut starts_before_row = vec![0usize; h + 1];
        {
            let mut seen = 0usize;
            for y in 0..h {
                starts_before_row[y] = seen;
                for &g in &aggregate[y * w..(y + 1) * w] {
                    if g != NONE && g as usize == seen {
                        seen += 1;
                    }
                }
            }
            starts_before_row[h] = seen;
            debug_assert_eq!(seen, m);
        }
        let rows = rows_per_task(w).next_multiple_of(2);
        let mut spans: Vec<(usize, usize)> = (0..h)
            .step_by(rows)
            .map(|y| (y, starts_before_row[y]))
            .collect();
        spans.push((h, m));
        let coarse = Multigrid::from_finest(galerkin(u, a, &of_unknown, m));
        BlockPreconditioner {
            finest,
            aggregate,
            spans,
            cell,
            coarse,
        }
    }

    /// Scratch for [`Self::apply`].
    pub fn scratch(&self) -> BlockScratch {
        let cells = self.finest.len();
        let m = self.spans.last().map_or(0, |s| s.1);
        BlockScratch {
            r: vec![0.0; cells],
            z: vec![0.0; cells],
            az: vec![0.0; cells],
            top: Work::zeros(m),
            deeper: self.coarse.work(),
        }
    }

    /// z = M⁻¹ r: one cycle from zero.
    pub fn apply(&self, r: &[f64], z: &mut [f64], s: &mut BlockScratch) {
        self.cell.scatter(&mut s.r, |k, v| *v = r[k]);
        s.z.par_iter_mut()
            .with_min_len(CELLS_PER_TASK)
            .for_each(|v| *v = 0.0);
        self.finest.sweep(&s.r, &mut s.z, true);
        self.finest.multiply(&s.z, &mut s.az);
        self.restrict(&s.r, &s.az, &mut s.top.rc);
        // The coarse correction: the K-cycle's up to two Krylov steps on the coarse level.
        let Work { rc, xc, k } = &mut s.top;
        self.coarse.krylov(0, rc, xc, k, &mut s.deeper);
        let w = self.finest.width();
        let rows = rows_per_task(w);
        let xc = &*xc;
        s.z.par_chunks_mut(rows * w)
            .zip(self.aggregate.par_chunks(rows * w))
            .for_each(|(z, g)| {
                for (z, &g) in z.iter_mut().zip(g) {
                    if g != NONE {
                        *z += xc[g as usize] as f32;
                    }
                }
            });
        self.finest.sweep(&s.r, &mut s.z, false);
        self.cell.gather(&s.z, z);
    }

    /// rc = Pᵀ(b − A x) on the aggregates, with A x given, in parallel blocks of rows.
    fn restrict(&self, b: &[f64], ax: &[f32], rc: &mut [f64]) {
        let w = self.finest.width();
        let mut parts: Vec<(&mut [f64], usize, usize, usize)> = Vec::new();
        let mut rest = rc;
        for pair in self.spans.windows(2) {
            let ((y0, g0), (y1, g1)) = (pair[0], pair[1]);
            let (mine, others) = rest.split_at_mut(g1 - g0);
            parts.push((mine, g0, y0 * w, y1 * w));
            rest = others;
        }
        parts.into_par_iter().for_each(|(rc, g0, c0, c1)| {
            rc.iter_mut().for_each(|v| *v = 0.0);
            for c in c0..c1 {
                let g = self.aggregate[c];
                if g != NONE {
                    rc[g as usize - g0] += b[c] - f64::from(ax[c]);
                }
            }
        });
    }
}

/// The aggregates of `u`'s unknowns: the components of each 2×2 block of the window (`cell`:
/// each unknown's cell in a window `w` wide) through the edges that are strong for both their
/// ends, numbered in the order of their first unknown; and their number.
fn block_aggregates(u: &Unknowns, a: &Stencil, cell: &[u32], w: usize) -> (Vec<u32>, usize) {
    let n = u.len();
    let mut strongest = vec![0f64; n];
    for i in 0..n {
        for (j, v) in [(u.right[i], a.right[i]), (u.down[i], a.down[i])] {
            if j != NONE {
                let s = -v;
                strongest[i] = strongest[i].max(s);
                strongest[j as usize] = strongest[j as usize].max(s);
            }
        }
    }
    // Union–find whose links point to lower indices, so that a root is its component's first
    // unknown.
    let mut link: Vec<u32> = (0..n as u32).collect();
    fn root(link: &mut [u32], mut i: u32) -> u32 {
        while link[i as usize] != i {
            let up = link[link[i as usize] as usize];
            link[i as usize] = up;
            i = up;
        }
        i
    }
    for i in 0..n {
        let (x, y) = (cell[i] as usize % w, cell[i] as usize / w);
        for (j, v, inside) in [
            (u.right[i], a.right[i], x % 2 == 0),
            (u.down[i], a.down[i], y % 2 == 0),
        ] {
            if j == NONE || !inside {
                continue;
            }
            let s = -v;
            if s > 0.0 && s >= STRONG * strongest[i].max(strongest[j as usize]) {
                let (ri, rj) = (root(&mut link, i as u32), root(&mut link, j));
                if ri != rj {
                    link[ri.max(rj) as usize] = ri.min(rj);
                }
            }
        }
    }
    let mut of_unknown = vec![NONE; n];
    let mut m = 0u32;
    for i in 0..n {
        let r = root(&mut link, i as u32) as usize;
        if r == i {
            of_unknown[i] = m;
            m += 1;
        } else {
            of_unknown[i] = of_unknown[r];
        }
    }
    (of_unknown, m as usize)
}

/// The Galerkin product PᵀAP of the stencil `a` for the aggregates `agg` (`m` of them): the
/// weight between two aggregates is the sum of the weights between their members, and each
/// diagonal the sum of its aggregate's edges to the others.
fn galerkin(u: &Unknowns, a: &Stencil, agg: &[u32], m: usize) -> Csr {
    let (first, members) = aggregate_members(agg, m);
    let mut rows = CoarseRows::new(m, 4 * m);
    for g in 0..m {
        for &i in &members[first[g]..first[g + 1]] {
            let i = i as usize;
            let left = u.left[i];
            let up = u.up[i];
            let edges = [
                (u.right[i], a.right[i]),
                (u.down[i], a.down[i]),
                (
                    left,
                    if left != NONE {
                        a.right[left as usize]
                    } else {
                        0.0
                    },
                ),
                (up, if up != NONE { a.down[up as usize] } else { 0.0 }),
            ];
            for (j, v) in edges {
                if j == NONE || v == 0.0 {
                    continue;
                }
                let c = agg[j as usize] as usize;
                if c == g {
                    continue;
                }
                rows.add(c, v);
            }
        }
        rows.end_row();
    }
    rows.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrate::sparse::Convergence;

    /// Masked unknowns (a disc with a hole and a bar, inside a wider image, so that their
    /// bounding box is a window of it) whose edge weights span three orders of magnitude, with
    /// a line of near-zero (cut) weights, as the bilateral integrator makes them (the grid
    /// preconditioner's test of the same weights): these aggregates follow the cut, so the
    /// solve takes fewer iterations than with the grid hierarchy's fixed blocks (47 against
    /// 71 when written), and far fewer than with the diagonal (Jacobi: over a thousand).
    #[test]
    fn preconditions_uneven_weights_on_masked_unknowns() {
        use crate::integrate::sparse::{Preconditioner, solve_known};
        let (mask, u, a) = super::super::grid::tests::uneven_weights(0, 1e-6, false);
        let window = mask.bounding_box().expect("a mask with pixels");
        let blocks = BlockPreconditioner::new(&u, &a, window);
        let grid = crate::integrate::multigrid::grid::GridPreconditioner::new(&u, &a, window);
        assert_eq!(u.window(), window);
        let solve = |pre: &Preconditioner| solve_known(&u, &a, pre, 5000);
        let (its, convergence, err) = solve(&Preconditioner::Blocks(&blocks));
        let (on_grid, grid_convergence, _) = solve(&Preconditioner::Grid(&grid));
        let (jacobi, _, _) = solve(&Preconditioner::Jacobi);
        eprintln!(
            "blocks: {its} iterations ({convergence:?}), error {err:.2e}; grid {on_grid}, \
             Jacobi {jacobi}"
        );
        assert_eq!(convergence, Convergence::Residual);
        assert_eq!(grid_convergence, Convergence::Residual);
        assert!(err < 1e-4, "error {err}");
        assert!(
            5 * its < 4 * on_grid && 10 * its < jacobi,
            "{its} against the grid's {on_grid} and Jacobi's {jacobi}"
        );
    }

    /// A comb of 48 one-pixel-wide columns (every other column of 96 × 160, as many parts),
    /// weights over three orders of magnitude: a few levels down each column is one node with
    /// no coupling left, whose diagonal must be 0, not the rounding residue of its members'
    /// diagonals less their inner edges (`Csr::galerkin`); with the residue the conjugate
    /// gradients did not converge in 500 iterations.
    #[test]
    fn preconditions_many_thin_parts() {
        use crate::grid::Grid;
        use crate::integrate::sparse::{Preconditioner, solve_known};
        let (w, h) = (96, 160);
        let mask = Grid::from_fn(w, h, |x, _| x % 2 == 0);
        let u = Unknowns::new(&mask);
        assert_eq!(u.parts, w / 2);
        let mut a = Stencil::zeros(u.len());
        let mut rhs = vec![0.0; u.len()];
        for i in 0..u.len() {
            let pix = u.pixel[i] as usize;
            let weight = 10f64.powi((((pix * 7919) % 4) as i32) - 3);
            if u.down[i] != NONE {
                a.add_edge(&mut rhs, (i, u.down[i] as usize), false, weight, 0.0);
            }
        }
        let window = mask.bounding_box().expect("a mask with pixels");
        let blocks = BlockPreconditioner::new(&u, &a, window);
        let (its, convergence, err) = solve_known(&u, &a, &Preconditioner::Blocks(&blocks), 500);
        assert_eq!(convergence, Convergence::Residual, "after {its} iterations");
        assert!(its <= 40, "{its} iterations");
        assert!(err < 1e-6, "error {err}");
    }
}
