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
//! box (`multigrid/grid.rs`): linear time, 6–12 iterations at any size (fewer the noisier the
//! data), and at most 56 bytes per pixel of that box, against 80–900 bytes per unknown for the
//! other two. Conjugate gradients stop once the algebraic error is estimated below a tenth of
//! the data's own uncertainty in every direction of the solution (`sparse::Stop::data`), or at
//! a relative residual of 10⁻⁸.
//!
//! Assumes a continuous surface inside each part: a depth jump inside the mask is smeared over
//! its neighbourhood (see the bilateral integrator for that case).

use super::multigrid::grid::{self, GridLaplacian, GridMultigrid};
use super::sparse::{
    Convergence, DOT_CHUNK, LeastSquares, LinearSolver, NONE, SolveMethod, Stencil, Stop, Unknowns,
    solve,
};
use super::{Censoring, edge_differences, window_edge_differences};
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap};
use rayon::prelude::*;
use std::borrow::Cow;

/// Relative residual at which conjugate gradients stop (unless the misfit rule of
/// [`Stop::data`] stops them first).
const CG_TOL: f64 = 1e-8;
/// Iteration limit of conjugate gradients.
const CG_MAX_ITER: usize = 2000;

/// When conjugate gradients stop on the normal equations of `edges` depth differences whose
/// squared norm is `norm2`, over `unknowns` pixels in `parts` connected parts.
fn stop(norm2: f64, edges: usize, unknowns: usize, parts: usize) -> Stop {
    Stop {
        tol: CG_TOL,
        max_iter: CG_MAX_ITER,
        data: Some(LeastSquares {
            norm2,
            redundancy: (edges + parts).saturating_sub(unknowns),
        }),
    }
}

/// How a linear system was solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct SolveInfo {
    /// Unknowns.
    pub unknowns: usize,
    /// The solver used.
    pub method: SolveMethod,
    /// Conjugate-gradient iterations (0 for the direct solver).
    pub iterations: usize,
    /// Why the solve stopped: whether it converged, and how.
    pub convergence: Convergence,
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
    masked_ls(
        Cow::Borrowed(p),
        Cow::Borrowed(q),
        censoring,
        domain,
        solver,
    )
}

/// [`integrate_masked_ls`] on gradients it may free: on the pixel grid (the default beyond the
/// direct limit) they are dropped once the window's depth differences are taken, so the solve
/// does not hold them (8 B a pixel of the image).
pub(crate) fn integrate_masked_ls_owned(
    p: ScalarMap,
    q: ScalarMap,
    censoring: &Censoring,
    domain: &Mask,
    solver: LinearSolver,
) -> Result<(ScalarMap, SolveInfo)> {
    masked_ls(Cow::Owned(p), Cow::Owned(q), censoring, domain, solver)
}

/// [`integrate_masked_ls`] on borrowed gradients, or on owned ones that the grid path frees.
fn masked_ls(
    p: Cow<'_, ScalarMap>,
    q: Cow<'_, ScalarMap>,
    censoring: &Censoring,
    domain: &Mask,
    solver: LinearSolver,
) -> Result<(ScalarMap, SolveInfo)> {
    p.check_same_size(&*q, "q vs p")?;
    p.check_same_size(domain, "domain vs gradients")?;
    if on_grid(solver, domain) {
        let edges = window_edges(&p, &q, censoring, domain)?;
        drop((p, q));
        return integrate_on_grid(edges, domain);
    }
    integrate_unknowns(&p, &q, censoring, domain, solver)
}

/// Whether `solver` integrates `domain` by the grid multigrid.
fn on_grid(solver: LinearSolver, domain: &Mask) -> bool {
    matches!(solver, LinearSolver::Auto | LinearSolver::Multigrid)
        && !solver.direct_for(domain.count())
}

/// The depth differences over the bounding box of `domain`: the window, the domain inside it and
/// the differences along rows and down columns.
type WindowEdges = (crate::grid::Window, Mask, Vec<f64>, Vec<f64>);

/// [`window_edge_differences`], or the error of a domain without a pixel.
fn window_edges(
    p: &ScalarMap,
    q: &ScalarMap,
    censoring: &Censoring,
    domain: &Mask,
) -> Result<WindowEdges> {
    window_edge_differences(p, q, domain, censoring).ok_or_else(|| Error::Mask {
        path: "<integration domain>".into(),
        reason: "no pixel to integrate".into(),
    })
}

/// [`integrate_masked_ls`] over the unknowns of `domain` (direct, or conjugate gradients with
/// the DCT or algebraic multigrid).
fn integrate_unknowns(
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
    let (mut data, mut edges) = (0.0, 0);
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
            data += d * d;
            edges += 1;
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
    let (iterations, convergence) =
        solve(&u, &a, &b, &mut z, method, stop(data, edges, n, u.parts))?;
    u.zero_mean_parts(&mut z);
    Ok((
        u.to_map(&z),
        SolveInfo {
            unknowns: n,
            method,
            iterations,
            convergence,
        },
    ))
}

/// [`integrate_masked_ls`] on the bounding box of `domain` with the grid multigrid
/// (`multigrid/grid.rs`), from its depth differences ([`window_edges`]): the same least-squares
/// problem, in bounded memory.
fn integrate_on_grid(
    (win, inside, right, down): WindowEdges,
    domain: &Mask,
) -> Result<(ScalarMap, SolveInfo)> {
    let (w, h) = (win.width(), win.height());
    let nan_free = |d: f64| if d.is_nan() { 0.0 } else { d };
    // Σ d² over the edges and their number, in fixed chunks added in order (the same on any
    // thread count).
    let (data, edges) = right
        .par_chunks(DOT_CHUNK)
        .chain(down.par_chunks(DOT_CHUNK))
        .map(|c| {
            let norm2 = c.iter().map(|&d| nan_free(d) * nan_free(d)).sum::<f64>();
            (norm2, c.iter().filter(|d| !d.is_nan()).count())
        })
        .collect::<Vec<(f64, usize)>>()
        .iter()
        .fold((0.0, 0), |(s, n), &(ds, dn)| (s + ds, n + dn));
    // b = Dᵀd: each cell's edges, added in the order edge by edge accumulation gives (left,
    // itself to the right, above, itself downwards).
    let b: Vec<f64> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let mut v = 0.0;
            if x > 0 {
                v += nan_free(right[i - 1]);
            }
            v -= nan_free(right[i]);
            if y > 0 {
                v += nan_free(down[i - w]);
            }
            v - nan_free(down[i])
        })
        .collect();
    let unit = |d: &[f64]| -> Vec<f32> {
        d.par_iter()
            .map(|d| if d.is_nan() { 0.0 } else { 1.0 })
            .collect()
    };
    let (wr, wd) = (unit(&right), unit(&down));
    drop((right, down));
    let mg = GridMultigrid::new(GridLaplacian::new(w, h, wr, wd));
    // The connected parts, for the solve; they are found again for the depth's zero mean per
    // part rather than held through the solve.
    let (label, parts) = grid::parts(mg.finest());
    let unknowns = label.par_iter().filter(|&&l| l != NONE).count();
    let stop = stop(data, edges, unknowns, parts);
    let (z, iterations, convergence) = grid::solve(&mg, b, (label, parts), stop);
    let (label, parts) = grid::parts(mg.finest());
    drop(mg);
    let means = grid::part_means(&z, &label, parts);
    let mut out = Grid::new(domain.width(), domain.height(), f32::NAN);
    out.par_window_rows_mut(win).for_each(|(y, row)| {
        for (x, cell) in row.iter_mut().enumerate() {
            let i = y * w + x;
            if inside.data()[i] {
                // A domain pixel without edges is a part of its own: depth 0.
                let v = match label[i] {
                    NONE => 0.0,
                    l => z[i] - means[l as usize],
                };
                *cell = v as f32;
            }
        }
    });
    Ok((
        out,
        SolveInfo {
            unknowns: domain.count(),
            method: SolveMethod::GridMultigridCg,
            iterations,
            convergence,
        },
    ))
}
