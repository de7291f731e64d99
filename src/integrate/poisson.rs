//! Poisson integration by the discrete cosine transform (Simchony, Chellappa & Shao, "Direct
//! analytical methods for solving Poisson equations in computer vision problems", PAMI 1990).
//!
//! Minimises Σ over grid edges of (z_j − z_i − d_ij)², where d_ij is the depth difference of
//! the gradients. Its normal equations are L z = b with L the grid-graph Laplacian (free, i.e.
//! Neumann, boundary) and b the divergence of the edge differences; the DCT-II diagonalises L
//! with eigenvalues (2 − 2cos(πu/W)) + (2 − 2cos(πv/H)), so z = IDCT(DCT(b) / λ). Edges leaving
//! the mask carry difference 0: the background is treated as flat, which distorts depth near a
//! mask boundary whose depth varies (a masked-domain solver avoids that).

use super::{Censoring, edge_differences, finish_depth};
use crate::grid::{Mask, ScalarMap};
use rayon::prelude::*;
use rustdct::DctPlanner;

/// Integrates (p, q) on `domain` (pixels where p and q are finite) by DCT Poisson.
/// `censoring` marks samples that are only bounds ([`Censoring`]).
pub fn integrate_poisson(
    p: &ScalarMap,
    q: &ScalarMap,
    censoring: &Censoring,
    domain: &Mask,
) -> ScalarMap {
    let (w, h) = (p.width(), p.height());
    let (right, down) = edge_differences(p, q, domain, censoring);
    let edge = |v: f64| if v.is_nan() { 0.0 } else { v };
    // b_i = Σ incoming differences − Σ outgoing differences.
    let mut b = vec![0f64; w * h];
    b.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, v) in row.iter_mut().enumerate() {
            let i = y * w + x;
            let mut s = -edge(right[i]) - edge(down[i]);
            if x > 0 {
                s += edge(right[i - 1]);
            }
            if y > 0 {
                s += edge(down[i - w]);
            }
            *v = s;
        }
    });
    let z = solve_neumann_laplacian(b, w, h);
    finish_depth(z, domain)
}

/// Solves L z = b for the w×h grid Laplacian with Neumann boundary (the mean of z is set to 0;
/// the mean of b is ignored, as L is singular along constants).
pub fn solve_neumann_laplacian(mut b: Vec<f64>, w: usize, h: usize) -> Vec<f64> {
    NeumannSolver::new(w, h).solve(&mut b);
    b
}

type Dct = std::sync::Arc<dyn rustdct::TransformType2And3<f64>>;

/// The planned DCT solver of the w×h Neumann grid Laplacian, reusable across solves (it is the
/// preconditioner of the masked conjugate-gradient solver).
pub struct NeumannSolver {
    w: usize,
    h: usize,
    row: Dct,
    col: Dct,
    /// Eigenvalues λ_u + λ_v, indexed [u (column frequency)][v (row frequency)].
    lambda: Vec<f64>,
}

impl NeumannSolver {
    /// Plans the transforms for a `w`×`h` grid.
    pub fn new(w: usize, h: usize) -> Self {
        let mut planner = DctPlanner::new();
        let (row, col) = (planner.plan_dct2(w), planner.plan_dct2(h));
        let ev = |n: usize| -> Vec<f64> {
            (0..n)
                .map(|k| 2.0 - 2.0 * (std::f64::consts::PI * k as f64 / n as f64).cos())
                .collect()
        };
        let (lu, lv) = (ev(w), ev(h));
        let mut lambda = Vec::with_capacity(w * h);
        for a in &lu {
            lambda.extend(lv.iter().map(|b| a + b));
        }
        NeumannSolver {
            w,
            h,
            row,
            col,
            lambda,
        }
    }

    /// Replaces `b` (row-major, w×h) by the zero-mean solution z of L z = b.
    pub fn solve(&self, b: &mut [f64]) {
        let (w, h) = (self.w, self.h);
        let each = |data: &mut [f64], len: usize, t: &Dct, forward: bool| {
            data.par_chunks_mut(len).for_each_init(
                || vec![0f64; t.get_scratch_len()],
                |s, row| {
                    if forward {
                        t.process_dct2_with_scratch(row, s)
                    } else {
                        t.process_dct3_with_scratch(row, s)
                    }
                },
            );
        };
        // Forward: DCT-II along rows, then along columns (via a transpose).
        each(b, w, &self.row, true);
        let mut t = vec![0f64; w * h];
        transpose_into(b, &mut t, w, h);
        each(&mut t, h, &self.col, true);
        // Divide by the eigenvalues, with the inverse transforms' scale (2/W)(2/H) folded in.
        let scale = 4.0 / (w as f64 * h as f64);
        t.par_iter_mut()
            .zip(self.lambda.par_iter())
            .for_each(|(c, l)| {
                *c = if *l > 0.0 { *c * scale / l } else { 0.0 };
            });
        // Inverse: DCT-III along columns then rows.
        each(&mut t, h, &self.col, false);
        transpose_into(&t, b, h, w);
        each(b, w, &self.row, false);
    }
}

/// Writes the transpose of the row-major `w`×`h` array `a` into `t` (row-major `h`×`w`), in
/// parallel over tiles of output rows.
fn transpose_into(a: &[f64], t: &mut [f64], w: usize, h: usize) {
    const TILE: usize = 32;
    t.par_chunks_mut(TILE * h)
        .enumerate()
        .for_each(|(bx, out)| {
            let x0 = bx * TILE;
            let x1 = (x0 + TILE).min(w);
            for y0 in (0..h).step_by(TILE) {
                for y in y0..(y0 + TILE).min(h) {
                    let row = &a[y * w..y * w + w];
                    for x in x0..x1 {
                        out[(x - x0) * h + y] = row[x];
                    }
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// L z = b recovers z exactly for any zero-mean z, where b = L z computed directly.
    #[test]
    fn inverts_the_neumann_laplacian() {
        let (w, h) = (13, 9);
        let z: Vec<f64> = (0..w * h)
            .map(|i| ((i * 37 % 17) as f64).sin() + (i % w) as f64 * 0.1)
            .collect();
        let mean = z.iter().sum::<f64>() / z.len() as f64;
        let z: Vec<f64> = z.iter().map(|v| v - mean).collect();
        let mut b = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let mut s = 0.0;
                for (ok, j) in [
                    (x > 0, i.wrapping_sub(1)),
                    (x + 1 < w, i + 1),
                    (y > 0, i.wrapping_sub(w)),
                    (y + 1 < h, i + w),
                ] {
                    if ok {
                        s += z[i] - z[j];
                    }
                }
                b[i] = s;
            }
        }
        let got = solve_neumann_laplacian(b, w, h);
        for (a, b) in got.iter().zip(&z) {
            assert!((a - b).abs() < 1e-10, "{a} vs {b}");
        }
    }
}
