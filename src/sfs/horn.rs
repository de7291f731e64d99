//! Horn's height-and-gradient shape from shading (B. K. P. Horn, "Height and gradient from
//! shading", IJCV 5(1), 1990), in its integrable limit.
//!
//! Horn minimises Σ (E/ρ − R(p, q))² + λ (smoothness of p, q) + μ Σ [(z_x − p)² + (z_y − q)²]
//! and lets μ enforce integrability. Here (p, q) are the height's own differences, which is the
//! limit μ → ∞: on Horn's staggered grid the gradient of each 2×2 cell of pixels is
//! p = ((z_TR + z_BR) − (z_TL + z_BL))/2, q = ((z_TL + z_TR) − (z_BL + z_BR))/2, the data term
//! compares R(p, q) with the mean brightness of the cell's four pixels, and the smoothness term
//! is λ Σ over adjacent cells of |∇z_c − ∇z_c'|². The energy in z is minimised by damped
//! Gauss–Newton (Levenberg–Marquardt) steps, each one sparse Cholesky solve (faer), instead of
//! Horn's Jacobi sweeps: tens of iterations instead of thousands, and no discretisation mismatch
//! between the gradients and the height. λ decreases geometrically to `smoothness`, as Horn
//! recommends: it only guides the early iterations.
//!
//! Boundary: the mask's edge is a free (natural) boundary. With [`Boundary::Occluding`] the
//! height starts from the convex surface z = √(d(2D − d)) of the distance d to the edge (D its
//! maximum; exact for a disk), which is what selects the convex solution and the steep rim of an
//! occluding contour; with [`Boundary::Free`] it starts from a plane. In shadow only R ≤ E/ρ is
//! enforced. (A hard occluding-contour prior on the edge pixels' gradients was tried and
//! dropped: the cells next to the rim are far less steep than the rim itself, and forcing them
//! raised the sphere's error from 1.6° to 21°.)

use super::{Boundary, Shading, Solved, clamp_gradient, differences, distance_to_edge};
use crate::error::{Error, Result};
use crate::integrate::sparse::NONE;
use faer::linalg::solvers::SolveCore;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{Pair, SparseColMat, SymbolicSparseColMat};
use faer::{Conj, MatMut, Side};

/// Default Gauss–Newton iteration limit.
const DEFAULT_MAX_ITERATIONS: usize = 80;
/// Initial smoothness weight.
const LAMBDA_START: f64 = 0.1;
/// Factor applied to λ after each accepted step.
const LAMBDA_DECAY: f64 = 0.5;
/// Initial Levenberg–Marquardt damping.
const DAMPING_START: f64 = 1e-3;
/// Convergence: largest height change of a step (pixels).
const TOLERANCE: f64 = 1e-3;

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
    let diag_start = pattern.len();
    pattern.extend((0..n).map(|k| Pair::new(k, k)));
    let assembly_err =
        |e: &dyn std::fmt::Debug| Error::param("solver", format!("sparse assembly failed: {e:?}"));
    let (structure, argsort) =
        SymbolicSparseColMat::try_new_from_indices(n, n, &pattern).map_err(|e| assembly_err(&e))?;
    let symbolic =
        SymbolicLlt::try_new(structure.as_ref(), Side::Lower).map_err(|e| assembly_err(&e))?;
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
        values.resize(pattern.len(), 0.0);
        let mut step = None;
        for _ in 0..12 {
            values[diag_start..].iter_mut().for_each(|v| *v = damping);
            let mat = SparseColMat::new_from_argsort(structure.clone(), &argsort, &values)
                .map_err(|e| assembly_err(&e))?;
            let Ok(llt) = Llt::try_new_with_symbolic(symbolic.clone(), mat.as_ref(), Side::Lower)
            else {
                damping *= 10.0;
                continue;
            };
            let mut delta = rhs.clone();
            llt.solve_in_place_with_conj(
                Conj::No,
                MatMut::from_column_major_slice_mut(&mut delta, n, 1),
            );
            let trial: Vec<f64> = z.iter().zip(&delta).map(|(a, b)| a + b).collect();
            if delta.iter().all(|v| v.is_finite()) && energy(&trial, lambda) <= e0 {
                damping = (damping / 3.0).max(1e-9);
                step = Some((trial, delta.iter().fold(0.0f64, |m, v| m.max(v.abs()))));
                break;
            }
            damping *= 4.0;
        }
        let at_floor = lambda <= floor;
        lambda = (lambda * LAMBDA_DECAY).max(floor);
        match step {
            Some((trial, largest)) => {
                z = trial;
                if at_floor && largest < TOLERANCE {
                    converged = true;
                    break;
                }
            }
            // No step lowers the energy: a (local) minimum.
            None if at_floor => {
                converged = true;
                break;
            }
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
