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
//! Boundary: the mask's edge is a free (natural) boundary. With [`Boundary::Occluding`] the
//! height starts from the convex surface z = √(d(2D − d)) of the distance d to the edge (D its
//! maximum; exact for a disk), which is what selects the convex solution and the steep rim of an
//! occluding contour; with [`Boundary::Free`] it starts from a plane. In shadow only R ≤ E/ρ is
//! enforced. (A hard occluding-contour prior on the edge pixels' gradients was tried and
//! dropped: the cells next to the rim are far less steep than the rim itself, and forcing them
//! raised the sphere's error from 1.6° to 21°.)

use super::line_search;
use super::{Boundary, Shading, Solved, clamp_gradient, differences, distance_to_edge};
use crate::error::{Error, Result};
use crate::integrate::sparse::{CholeskyWork, NONE, nested_dissection, symbolic_cholesky};
use faer::Par;
use faer::sparse::{Pair, SparseColMat, SymbolicSparseColMat};

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

pub(crate) fn solve(s: &Shading) -> Result<Solved> {
    let u = &s.u;
    let n = u.len();
    let max_iter = if s.options.max_iterations > 0 {
        s.options.max_iterations
    } else {
        DEFAULT_MAX_ITERATIONS
    };
    let cells = Cells::new(s);
    let mut assumptions = Vec::new();
    let occluding_boundary = s.options.boundary != Boundary::Free;
    let mut z = vec![0.0; n];
    if occluding_boundary && let Some(d) = distance_to_edge(u) {
        let top = d.iter().cloned().fold(0.0, f64::max);
        for (zk, dk) in z.iter_mut().zip(&d) {
            *zk = (dk * (2.0 * top - dk)).max(0.0).sqrt();
        }
        assumptions.push(
            "convex: the iteration starts from a convex surface over the mask (a concave \
             surface with the same shading is not considered)"
                .to_string(),
        );
    } else {
        assumptions.push(
            "the iteration starts from a plane facing the camera; with a light near the viewer \
             a bump and a dent explain the image equally well"
                .to_string(),
        );
    }
    // Normal equations J_dᵀJ_d + λ SᵀS + νI, where J_d are the data rows linearised at z (one per
    // cell, coefficients R_p ∂p/∂z + R_q ∂q/∂z over its corners) and S the smoothness rows (the
    // difference of two adjacent cells' p or q). The pattern is the same at every iteration:
    // it is sorted and analysed once, and only the values change.
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
    let lower = |idx: &[usize], out: &mut Vec<Pair<usize, usize>>| {
        for &i in idx {
            for &j in idx {
                if j >= i {
                    out.push(Pair::new(j, i));
                }
            }
        }
    };
    let mut pattern = Vec::new();
    for c in &cells.corners {
        lower(c, &mut pattern);
    }
    for (idx, _) in &smooth {
        lower(idx, &mut pattern);
    }
    // The assembled entries on the diagonal (the damping's own n entries follow them).
    let diagonal: Vec<(usize, usize)> = pattern
        .iter()
        .enumerate()
        .filter(|(_, at)| at.row == at.col)
        .map(|(p, at)| (p, at.row))
        .collect();
    pattern.extend((0..n).map(|k| Pair::new(k, k)));
    let assembly_err =
        |e: &dyn std::fmt::Debug| Error::param("solver", format!("sparse assembly failed: {e:?}"));
    let (structure, argsort) =
        SymbolicSparseColMat::try_new_from_indices(n, n, &pattern).map_err(|e| assembly_err(&e))?;
    let (col_ptr, row_idx) = (structure.col_ptr().to_vec(), structure.row_idx().to_vec());
    // A cell and its neighbours couple pixels up to two apart: separators two pixels thick.
    let symbolic = symbolic_cholesky(&col_ptr, &row_idx, nested_dissection(u, 2))?;
    // Sequential: faer's parallel factorisation spends more time synchronising than it saves on
    // these sizes (as in the perspective refinement).
    let mut work = CholeskyWork::new(&symbolic, Par::Seq)?;
    let lower_values = |idx: &[usize], coef: &[f64], w: f64, out: &mut Vec<f64>| {
        for (a, &i) in idx.iter().enumerate() {
            for (b, &j) in idx.iter().enumerate() {
                if j >= i {
                    out.push(w * coef[a] * coef[b]);
                }
            }
        }
    };
    let smooth_value = |z: &[f64], (idx, coef): &([usize; 8], [f64; 8])| -> f64 {
        idx.iter().zip(coef).map(|(&k, c)| c * z[k]).sum()
    };
    // Data residuals and linearised rows at z: (r₀ per cell, 0 for inactive shadow cells).
    let data = |z: &[f64]| -> Vec<(f64, [f64; 4])> {
        (0..cells.corners.len())
            .map(|c| {
                let (p, q) = cells.gradient(z, c);
                let sh = s.rmap.eval_with_derivatives(p, q);
                let r0 = cells.e[c] - sh.r;
                if cells.shadow[c] && r0 >= 0.0 {
                    (0.0, [0.0; 4])
                } else {
                    (r0, [0, 1, 2, 3].map(|i| sh.r_p * DP[i] + sh.r_q * DQ[i]))
                }
            })
            .collect()
    };
    let energy = |z: &[f64], lambda: f64| -> f64 {
        let d: f64 = data(z).iter().map(|(r, _)| r * r).sum();
        let sm: f64 = smooth.iter().map(|row| smooth_value(z, row).powi(2)).sum();
        d + lambda * sm
    };

    let floor = s.options.smoothness;
    let mut lambda = LAMBDA_START.max(floor);
    let mut damping = DAMPING_START;
    let mut iterations = 0;
    let mut converged = false;
    let mut values = Vec::with_capacity(pattern.len());
    let mut diag = vec![0.0; n];
    let mut trial = vec![0.0; n];
    s.progress
        .begin("shape from shading (Horn)", max_iter as u64);
    while iterations < max_iter {
        iterations += 1;
        s.progress.advance(1);
        let rows = data(&z);
        let e0 = energy(&z, lambda);
        values.clear();
        let mut rhs = vec![0.0; n];
        for (c, (r0, coef)) in rows.iter().enumerate() {
            let idx = &cells.corners[c];
            lower_values(idx, coef, 1.0, &mut values);
            for (a, &i) in idx.iter().enumerate() {
                rhs[i] += coef[a] * r0;
            }
        }
        for row in &smooth {
            lower_values(&row.0, &row.1, lambda, &mut values);
            let v = smooth_value(&z, row);
            for (a, &i) in row.0.iter().enumerate() {
                rhs[i] -= lambda * row.1[a] * v;
            }
        }
        let at_floor = lambda <= floor;
        let base = values.len();
        // Solves the normal equations with `damping(k)` added to the k-th diagonal entry.
        let mut solve_damped = |values: &mut Vec<f64>, damping: &dyn Fn(usize) -> f64| {
            values.truncate(base);
            values.extend((0..n).map(damping));
            let mat = SparseColMat::new_from_argsort(structure.clone(), &argsort, values)
                .map_err(|e| assembly_err(&e))?;
            let mut delta = rhs.clone();
            work.solve(&symbolic, &col_ptr, &row_idx, mat.val(), &mut delta)?;
            Ok::<_, Error>(delta)
        };
        let mut lowered = None;
        // Whether the Gauss–Newton step could be computed (a factorisation that fails, or a
        // step that is not finite, falls back to Levenberg–Marquardt's damping).
        let mut newton = false;
        if at_floor {
            // Gauss–Newton with a line search at the final λ.
            diag.iter_mut().for_each(|d| *d = 0.0);
            for &(p, row) in &diagonal {
                diag[row] += values[p];
            }
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
                // trying its minimum after a length that lowered E left the bust and the relief
                // at 128² at the iteration limit).
                lowered = line_search::search(e0, slope, false, |alpha| {
                    for k in 0..n {
                        trial[k] = z[k] + alpha * delta[k];
                    }
                    energy(&trial, lambda)
                })
                .map(|(alpha, e)| (delta, alpha, e));
            }
        }
        if !newton {
            // Levenberg–Marquardt while λ is lowered: the damping holds accepted steps near the
            // last, so that the continuation in λ follows one solution.
            for _ in 0..12 {
                let Ok(delta) = solve_damped(&mut values, &|_| damping) else {
                    damping *= 10.0;
                    continue;
                };
                for k in 0..n {
                    trial[k] = z[k] + delta[k];
                }
                let e = energy(&trial, lambda);
                if delta.iter().all(|v| v.is_finite()) && e <= e0 {
                    damping = (damping / 3.0).max(1e-9);
                    lowered = Some((delta, 1.0, e));
                    break;
                }
                damping *= 4.0;
            }
        }
        // A floor of 0 (or one below what 0.1 halved every iteration reaches) would never be
        // reached: below LAMBDA_NEGLIGIBLE, λ jumps to the floor.
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
    // Pixel gradients: the mean of the adjacent cells' (central differences where none).
    let mut p = vec![0.0; n];
    let mut q = vec![0.0; n];
    for k in 0..n {
        let cs = &cells.of_unknown[k];
        let (a, b) = if cs.is_empty() {
            differences(u, &z, k)
        } else {
            let (mut a, mut b) = (0.0, 0.0);
            for &c in cs {
                let (x, y) = cells.gradient(&z, c);
                a += x;
                b += y;
            }
            (a / cs.len() as f64, b / cs.len() as f64)
        };
        (p[k], q[k]) = clamp_gradient(a, b);
    }
    s.progress.end();
    Ok(Solved {
        p,
        q,
        z,
        normals: None,
        iterations,
        converged,
        singular: 0,
        assumptions,
    })
}
