//! Least-squares integration on the mask only (the "masked-domain" Poisson problem with a free
//! boundary; Quéau, Durou & Aujol, "Normal integration: a survey", JMIV 2018, §3).
//!
//! Minimises Σ over the edges between neighbouring mask pixels of (z_j − z_i − d_ij)², d_ij the
//! depth difference the gradients give (the shared rule of the parent module, with its rim
//! profile). Unlike DCT Poisson, nothing outside the mask enters: the mask boundary is a free
//! (natural) boundary, so masks of any shape and depth discontinuities along the silhouette are
//! handled. Each connected part is integrated independently (anchored at
//! one pixel, then made zero-mean). Its normal equations are the mask's graph Laplacian L z = b,
//! solved by sparse Cholesky, by conjugate gradients preconditioned with the DCT solve of the
//! enclosing rectangle (a few tens of iterations for compact masks), or by conjugate gradients
//! preconditioned with aggregation multigrid (linear time and memory on any mask).
//!
//! Assumes a continuous surface inside each part: a depth jump inside the mask is smeared over
//! its neighbourhood (see the bilateral integrator for that case).

use super::sparse::{LinearSolver, SolveMethod, Stencil, Unknowns, solve};
use super::{Censoring, edge_differences};
use crate::error::Result;
use crate::grid::{Mask, ScalarMap};

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
