//! Least-squares integration on the mask only (the "masked-domain" Poisson problem with a free
//! boundary; Quéau, Durou & Aujol, "Normal integration: a survey", JMIV 2018, §3).
//!
//! Minimises Σ over the edges between neighbouring mask pixels of (z_j − z_i − d_ij)², d_ij the
//! depth difference the gradients give (the shared rule of the parent module, with its rim
//! profile). Unlike DCT Poisson, nothing outside the mask enters: the mask boundary is a free
//! (natural) boundary, so masks of any shape and depth discontinuities along the silhouette are
//! handled. Each connected part is integrated independently (anchored at
//! one pixel, then made zero-mean). Its normal equations are the mask's graph Laplacian L z = b,
//! solved by sparse Cholesky (up to [`super::sparse::DIRECT_MAX_UNKNOWNS`] unknowns by default),
//! by conjugate gradients preconditioned with the DCT solve of the enclosing rectangle (a few
//! tens of iterations for compact masks), or — the default beyond the direct limit — by
//! conjugate gradients preconditioned with multigrid on the pixel grid of the mask's bounding
//! box (`multigrid/grid.rs`): linear time, about a dozen iterations at any size, and at most
//! 56 bytes per pixel of that box, against 80–900 bytes per unknown for the other two.
//!
//! Assumes a continuous surface inside each part: a depth jump inside the mask is smeared over
//! its neighbourhood (see the bilateral integrator for that case).

use super::multigrid::grid::{self, GridLaplacian, GridMultigrid};
use super::sparse::{LinearSolver, NONE, SolveMethod, Stencil, Unknowns, solve};
use super::{Censoring, edge_differences, window_edge_differences};
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap};

/// Relative residual at which conjugate gradients stop.
const CG_TOL: f64 = 1e-8;
/// Iteration limit of conjugate gradients.
const CG_MAX_ITER: usize = 2000;

/// How a linear system was solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct SolveInfo {
    /// Unknowns.
    pub unknowns: usize,
    /// The solver used.
    pub method: SolveMethod,
    /// Conjugate-gradient iterations (0 for the direct solver).
    pub iterations: usize,
}

/// Integrates (p, q) over `domain` (pixels where both are finite) by masked least squares.
/// Returns depth (zero-mean per connected part, NaN outside) and how the system was solved.
///
/// # Errors
/// [`crate::Error::InvalidParameter`] when the sparse factorisation fails (e.g. out of memory).
pub fn integrate_masked_ls(
    p: &ScalarMap,
    q: &ScalarMap,
    censoring: &Censoring,
    domain: &Mask,
    solver: LinearSolver,
) -> Result<(ScalarMap, SolveInfo)> {
    if matches!(solver, LinearSolver::Auto | LinearSolver::Multigrid)
        && !solver.direct_for(domain.count())
    {
        return integrate_on_grid(p, q, censoring, domain);
    }
    let u = Unknowns::new(domain);
    let n = u.len();
    let (right, down) = edge_differences(p, q, domain, censoring);
    let mut a = Stencil::zeros(n);
    let mut b = vec![0f64; n];
    for i in 0..n {
        let pix = u.pixel[i] as usize;
        for (nb, d, along_rows) in [
            (u.right[i], right[pix], true),
            (u.down[i], down[pix], false),
        ] {
            if nb == super::sparse::NONE || d.is_nan() {
                continue;
            }
            a.add_edge(&mut b, (i, nb as usize), along_rows, 1.0, d);
        }
    }
    // The DCT preconditioner assumes uniform weights; censored edges make it approximate only,
    // which costs iterations, not accuracy.
    let method = if solver.direct_for(n) {
        SolveMethod::Direct
    } else if solver == LinearSolver::Multigrid {
        SolveMethod::MultigridCg
    } else {
        SolveMethod::DctCg
    };
    let mut z = vec![0f64; n];
    let iterations = solve(&u, &a, &b, &mut z, method, CG_TOL, CG_MAX_ITER)?;
    u.zero_mean_parts(&mut z);
    Ok((
        u.to_map(&z),
        SolveInfo {
            unknowns: n,
            method,
            iterations,
        },
    ))
}

/// [`integrate_masked_ls`] on the bounding box of `domain` with the grid multigrid
/// (`multigrid/grid.rs`): the same least-squares problem, in bounded memory.
fn integrate_on_grid(
    p: &ScalarMap,
    q: &ScalarMap,
    censoring: &Censoring,
    domain: &Mask,
) -> Result<(ScalarMap, SolveInfo)> {
    let (win, inside, right, down) =
        window_edge_differences(p, q, domain, censoring).ok_or_else(|| Error::Mask {
            path: "<integration domain>".into(),
            reason: "no pixel to integrate".into(),
        })?;
    let (w, h) = (win.width(), win.height());
    let mut b = vec![0f64; w * h];
    let unit = |d: &[f64], step: usize, b: &mut [f64]| -> Vec<f32> {
        d.iter()
            .enumerate()
            .map(|(i, &d)| {
                if d.is_nan() {
                    return 0.0;
                }
                b[i] -= d;
                b[i + step] += d;
                1.0
            })
            .collect()
    };
    let wr = unit(&right, 1, &mut b);
    let wd = unit(&down, w, &mut b);
    drop((right, down));
    let mg = GridMultigrid::new(GridLaplacian::new(w, h, wr, wd));
    let (z, iterations) = grid::solve(&mg, b, CG_TOL, CG_MAX_ITER);
    // Zero-mean per part; the labels are found again rather than held through the solve.
    let (label, parts) = grid::parts(mg.finest());
    drop(mg);
    let means = grid::part_means(&z, &label, parts);
    let mut out = Grid::new(domain.width(), domain.height(), f32::NAN);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if inside.data()[i] {
                // A domain pixel without edges is a part of its own: depth 0.
                let v = match label[i] {
                    NONE => 0.0,
                    l => z[i] - means[l as usize],
                };
                *out.at_mut(win.x0 + x, win.y0 + y) = v as f32;
            }
        }
    }
    Ok((
        out,
        SolveInfo {
            unknowns: domain.count(),
            method: SolveMethod::GridMultigridCg,
            iterations,
        },
    ))
}
