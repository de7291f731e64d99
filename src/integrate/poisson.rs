//! Poisson integration by the discrete cosine transform (Simchony, Chellappa & Shao, "Direct
//! analytical methods for solving Poisson equations in computer vision problems", PAMI 1990).
//!
//! Minimises Σ over grid edges of (z_j − z_i − d_ij)², where d_ij is the trapezoid difference of
//! the gradients. Its normal equations are L z = b with L the grid-graph Laplacian (free, i.e.
//! Neumann, boundary) and b the divergence of the edge differences; the DCT-II diagonalises L
//! with eigenvalues (2 − 2cos(πu/W)) + (2 − 2cos(πv/H)), so z = IDCT(DCT(b) / λ). Edges leaving
//! the mask carry difference 0: the background is treated as flat, which distorts depth near a
//! mask boundary whose depth varies (a masked-domain solver avoids that).

use super::{edge_differences, finish_depth};
use crate::grid::{Mask, ScalarMap};
use rayon::prelude::*;
use rustdct::DctPlanner;

/// Integrates (p, q) on `domain` (pixels where p and q are finite) by DCT Poisson.
pub fn integrate_poisson(p: &ScalarMap, q: &ScalarMap, domain: &Mask) -> ScalarMap {
    let (w, h) = (p.width(), p.height());
    let (right, down) = edge_differences(p, q, domain);
    let edge = |v: f64| if v.is_nan() { 0.0 } else { v };
    // b_i = Σ incoming differences − Σ outgoing differences.
    let mut b = vec![0f64; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let mut v = -edge(right[i]) - edge(down[i]);
            if x > 0 {
                v += edge(right[i - 1]);
            }
            if y > 0 {
                v += edge(down[i - w]);
            }
            b[i] = v;
        }
    }
    let z = solve_neumann_laplacian(b, w, h);
    finish_depth(z, domain)
}

/// Solves L z = b for the w×h grid Laplacian with Neumann boundary (the mean of z is set to 0;
/// the mean of b is ignored, as L is singular along constants).
pub fn solve_neumann_laplacian(mut b: Vec<f64>, w: usize, h: usize) -> Vec<f64> {
    let mut planner = DctPlanner::new();
    let (row2, row3) = (planner.plan_dct2(w), planner.plan_dct3(w));
    let (col2, col3) = (planner.plan_dct2(h), planner.plan_dct3(h));
    let rows = |data: &mut [f64],
                len: usize,
                f: &(dyn Fn(&mut [f64], &mut [f64]) + Sync),
                scratch: usize| {
        data.par_chunks_mut(len)
            .for_each_init(|| vec![0f64; scratch], |s, row| f(row, s));
    };
    // Forward: DCT-II along rows, then along columns (via a transpose).
    rows(
        &mut b,
        w,
        &|r, s| row2.process_dct2_with_scratch(r, s),
        row2.get_scratch_len(),
    );
    let mut t = transpose(&b, w, h);
    rows(
        &mut t,
        h,
        &|r, s| col2.process_dct2_with_scratch(r, s),
        col2.get_scratch_len(),
    );
    // Divide by the eigenvalues; t is indexed [u (column freq)][v (row freq)].
    let lx: Vec<f64> = (0..w)
        .map(|u| 2.0 - 2.0 * (std::f64::consts::PI * u as f64 / w as f64).cos())
        .collect();
    let ly: Vec<f64> = (0..h)
        .map(|v| 2.0 - 2.0 * (std::f64::consts::PI * v as f64 / h as f64).cos())
        .collect();
    t.par_chunks_mut(h).enumerate().for_each(|(u, col)| {
        for (v, c) in col.iter_mut().enumerate() {
            let l = lx[u] + ly[v];
            *c = if l > 0.0 { *c / l } else { 0.0 };
        }
    });
    // Inverse: DCT-III along columns then rows, scaled by (2/W)(2/H).
    rows(
        &mut t,
        h,
        &|r, s| col3.process_dct3_with_scratch(r, s),
        col3.get_scratch_len(),
    );
    let mut z = transpose(&t, h, w);
    rows(
        &mut z,
        w,
        &|r, s| row3.process_dct3_with_scratch(r, s),
        row3.get_scratch_len(),
    );
    let scale = 4.0 / (w as f64 * h as f64);
    z.par_iter_mut().for_each(|v| *v *= scale);
    z
}

/// Transposes a row-major `w`×`h` array into a row-major `h`×`w` one.
fn transpose(a: &[f64], w: usize, h: usize) -> Vec<f64> {
    let mut t = vec![0f64; w * h];
    const TILE: usize = 32;
    for y0 in (0..h).step_by(TILE) {
        for x0 in (0..w).step_by(TILE) {
            for y in y0..(y0 + TILE).min(h) {
                for x in x0..(x0 + TILE).min(w) {
                    t[x * h + y] = a[y * w + x];
                }
            }
        }
    }
    t
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
