//! Shape from shading under a light at the viewer by fast marching (Kimmel & Sethian, "Optimal
//! algorithm for shape from shading and path planning", JMIV 14(3), 2001; Sethian, *Level Set
//! Methods and Fast Marching Methods*, 1999).
//!
//! With s = v = (0, 0, 1), a Lambertian image is E/ρ = n_z = 1/√(1 + |∇z|²), so the height
//! below the surface's tops, T = z_top − z, solves the eikonal equation |∇T| = F with
//! F = √(1/(E/ρ)² − 1). Its viscosity solution is computed by Dijkstra-like fast marching with
//! the first-order Godunov upwind update, from the singular points (E/ρ ≈ 1, local maxima of the
//! image), which are taken as local maxima of the surface — that is the convex/concave choice —
//! at a common height. The normals combine the image's slant (n_z = E/ρ) with the marched
//! surface's azimuth.
//!
//! Fails when the surface has no singular point (the brightest pixel is used instead, and the
//! report says so), when its tops are at different heights (unknowable from one image), and in
//! shadow (F is capped at the slope of [`super::MAX_GRADIENT`]).

use super::{MAX_GRADIENT, Shading, Solved, differences};
use crate::error::Result;
use crate::integrate::sparse::NONE;
use nalgebra::Vector3;
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// E/ρ above which a local maximum of the image is a singular point.
pub const SINGULAR_LEVEL: f64 = 0.995;

#[derive(PartialEq)]
struct Trial(f64, usize);

impl Eq for Trial {}

impl Ord for Trial {
    fn cmp(&self, other: &Self) -> Ordering {
        // Smallest arrival first.
        other.0.total_cmp(&self.0).then(other.1.cmp(&self.1))
    }
}

impl PartialOrd for Trial {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

pub(crate) fn solve(s: &Shading) -> Result<Solved> {
    let u = &s.u;
    let n = u.len();
    let min_e = 1.0 / (1.0 + MAX_GRADIENT * MAX_GRADIENT).sqrt();
    let speed: Vec<f64> =
        s.e.iter()
            .map(|&e| {
                let e = e.clamp(min_e, 1.0);
                (1.0 / (e * e) - 1.0).max(0.0).sqrt()
            })
            .collect();
    // Singular points: local maxima of the image at E/ρ ≥ SINGULAR_LEVEL.
    let mut sources: Vec<usize> = (0..n)
        .filter(|&k| {
            s.e[k] >= SINGULAR_LEVEL
                && [u.left[k], u.right[k], u.up[k], u.down[k]]
                    .iter()
                    .all(|&j| j == NONE || s.e[j as usize] <= s.e[k])
        })
        .collect();
    let mut assumptions = vec![format!(
        "every singular point (a local maximum of the image with E/ρ ≥ {SINGULAR_LEVEL}) is a \
         top of the surface, all at the same height (a dent would look the same)"
    )];
    // Every connected part needs a source: its brightest pixel when it has no singular point.
    let mut has_source = vec![false; u.parts];
    for &k in &sources {
        has_source[u.part[k] as usize] = true;
    }
    let mut brightest = vec![usize::MAX; u.parts];
    for k in 0..n {
        let part = u.part[k] as usize;
        if brightest[part] == usize::MAX || s.e[k] > s.e[brightest[part]] {
            brightest[part] = k;
        }
    }
    let missing: Vec<usize> = (0..u.parts).filter(|&p| !has_source[p]).collect();
    if !missing.is_empty() {
        assumptions.push(format!(
            "{} connected part(s) have no singular point: their brightest pixel was taken as \
             the top, so their depth is only approximate",
            missing.len()
        ));
        sources.extend(missing.iter().map(|&p| brightest[p]));
    }
    let singular = sources.len();

    let mut t = vec![f64::INFINITY; n];
    let mut done = vec![false; n];
    let mut heap = BinaryHeap::new();
    for &k in &sources {
        t[k] = 0.0;
        heap.push(Trial(0.0, k));
    }
    let value = |t: &[f64], done: &[bool], j: u32| {
        if j != NONE && done[j as usize] {
            t[j as usize]
        } else {
            f64::INFINITY
        }
    };
    s.progress
        .begin("shape from shading (fast marching)", n as u64);
    let mut fixed = 0u64;
    while let Some(Trial(tk, k)) = heap.pop() {
        if done[k] || tk > t[k] {
            continue;
        }
        done[k] = true;
        fixed += 1;
        if fixed.is_multiple_of(4096) {
            s.progress.advance(4096);
        }
        for j in [u.left[k], u.right[k], u.up[k], u.down[k]] {
            if j == NONE || done[j as usize] {
                continue;
            }
            let j = j as usize;
            let a = value(&t, &done, u.left[j]).min(value(&t, &done, u.right[j]));
            let b = value(&t, &done, u.up[j]).min(value(&t, &done, u.down[j]));
            let f = speed[j];
            let (lo, hi) = if a < b { (a, b) } else { (b, a) };
            let candidate = if hi.is_infinite() || hi - lo >= f {
                lo + f
            } else {
                0.5 * (a + b + (2.0 * f * f - (a - b) * (a - b)).sqrt())
            };
            if candidate < t[j] {
                t[j] = candidate;
                heap.push(Trial(candidate, j));
            }
        }
    }
    let z: Vec<f64> = t.iter().map(|&v| -v).collect();
    let mut p = vec![0.0; n];
    let mut q = vec![0.0; n];
    let mut normals = vec![Vector3::z(); n];
    for k in 0..n {
        let (tx, ty) = differences(u, &t, k);
        let m = tx.hypot(ty);
        let e = s.e[k].clamp(min_e, 1.0);
        let sin = (1.0 - e * e).max(0.0).sqrt();
        let nk = if m > 0.0 {
            // z = −T: the normal (−∇z, 1) leans along +∇T.
            Vector3::new(tx / m * sin, ty / m * sin, e)
        } else {
            Vector3::z()
        };
        normals[k] = nk;
        p[k] = -nk.x / nk.z;
        q[k] = -nk.y / nk.z;
    }
    s.progress.end();
    Ok(Solved {
        p,
        q,
        z,
        normals: Some(normals),
        iterations: 1,
        converged: true,
        coarse_iterations: 0,
        restarts: 0,
        warnings: Vec::new(),
        singular,
        assumptions,
    })
}
