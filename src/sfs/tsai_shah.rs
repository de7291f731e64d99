//! The linear method of Tsai & Shah ("Shape from shading using linear approximation", Image and
//! Vision Computing 12(8), 1994).
//!
//! With backward differences p = z(x, y) − z(x−1, y) and q = z(x, y) − z(x, y−1), the brightness
//! equation f(z) = E/ρ − R(p, q) = 0 is linearised in z at each pixel, and every sweep takes one
//! Newton step per pixel from the previous sweep's depths, with the paper's Kalman-filter gain:
//!
//! z ← z + K (−f), K = S M / (W + M² S), S ← (1 − K M) S, M = ∂f/∂z = −(R_p + R_q),
//!
//! S starting at 0.01 and W = 10⁻⁴ (as in the original implementation). Neighbours outside the
//! mask count as depth 0 (the paper's image border). Fast and local, but the backward
//! differences make it biased along the (1, 1) direction and it has no notion of occluding
//! boundaries; under a frontal light M = 0 at the flat start and nothing moves
//! ([`super::SfsMethod::applicable`] refuses it).

use super::{Shading, Solved, clamp_gradient};
use crate::error::Result;
use crate::integrate::sparse::NONE;
use rayon::prelude::*;

/// Default number of sweeps.
const DEFAULT_MAX_ITERATIONS: usize = 300;
/// Initial gain state S.
const S0: f64 = 0.01;
/// Gain regulariser W.
const W: f64 = 1e-4;
/// Convergence: largest depth change per sweep (pixels).
const TOLERANCE: f64 = 1e-6;

pub(crate) fn solve(s: &Shading) -> Result<Solved> {
    let u = &s.u;
    let n = u.len();
    let max_iter = if s.options.max_iterations > 0 {
        s.options.max_iterations
    } else {
        DEFAULT_MAX_ITERATIONS
    };
    let mut z = vec![0.0f64; n];
    let mut next = z.clone();
    let mut gain = vec![S0; n];
    let at = |z: &[f64], j: u32| if j == NONE { 0.0 } else { z[j as usize] };
    let grad = |z: &[f64], k: usize| {
        // x: from the left neighbour; y up: from the row below.
        (z[k] - at(z, u.left[k]), z[k] - at(z, u.down[k]))
    };
    let mut iterations = 0;
    let mut converged = false;
    s.progress
        .begin("shape from shading (Tsai-Shah)", max_iter as u64);
    while iterations < max_iter {
        iterations += 1;
        s.progress.advance(1);
        let change = next
            .par_iter_mut()
            .zip(gain.par_iter_mut())
            .enumerate()
            .map(|(k, (zn, sk))| {
                let (p, q) = grad(&z, k);
                let sh = s.rmap.eval_with_derivatives(p, q);
                let f = s.e[k] - sh.r;
                let m = -(sh.r_p + sh.r_q);
                let k_gain = *sk * m / (W + m * m * *sk);
                *sk *= 1.0 - k_gain * m;
                let step = k_gain * -f;
                *zn = z[k] + if step.is_finite() { step } else { 0.0 };
                (*zn - z[k]).abs()
            })
            .reduce(|| 0.0, f64::max);
        std::mem::swap(&mut z, &mut next);
        if change < TOLERANCE {
            converged = true;
            break;
        }
    }
    let (mut p, mut q) = (vec![0.0; n], vec![0.0; n]);
    for k in 0..n {
        let (a, b) = grad(&z, k);
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
        coarse_iterations: 0,
        restarts: 0,
        warnings: Vec::new(),
        singular: 0,
        assumptions: vec![
            "depth 0 outside the mask and at the image border (the surface meets its \
             surroundings there); backward differences"
                .to_string(),
        ],
    })
}
