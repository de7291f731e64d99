//! Depth from normals: normal integration, orthographic or perspective.
//!
//! [`integrate_normals`] takes a normal map and a mask and returns depth. Orthographic (no camera):
//! depth is the height z towards the camera in pixel units (larger = nearer), from the gradients
//! p = ∂z/∂x = −n_x/n_z, q = ∂z/∂y = −n_y/n_z (x right, y up). Perspective (pinhole intrinsics
//! K, Durou, Aujol & Courteille, "Integrating the normal field of a surface in the presence of
//! discontinuities", 2009; Quéau et al. 2018): the gradients of the log depth z̃ = ln d are
//! ∂z̃/∂u = n_x/(f_x m), ∂z̃/∂v = −n_y/(f_y m), m = n_z − n_x(u − c_x)/f_x + n_y(v − c_y)/f_y,
//! and depth is d = exp(z̃), the distance along the optical axis, known up to one global scale
//! per connected part (returned with geometric mean 1).
//!
//! Methods ([`Integrator`]), each with its assumptions and failure modes:
//! - `masked-ls` (default): least squares on the mask only (free boundary); smooths over depth
//!   jumps inside the mask.
//! - `poisson`: DCT least squares on the whole rectangle; fast, but treats the background as flat.
//! - `path`: quality-guided path integration on the mask; noise accumulates along paths.
//! - `fc`: Frankot–Chellappa by FFT; assumes periodicity, distorts near the image border.
//! - `bilateral`: discontinuity-preserving reweighted least squares; slower (one solve per
//!   iteration) and may break smooth surfaces where normals are noisy.
//!
//! The gradient-based methods share one discretisation: the depth difference between neighbours
//! is the trapezoid-rule mean of the two pixels' gradients. After integration, the per-pixel
//! residual |Δz − trapezoid gradient| (RMS over the pixel's edges) shows where the result is not
//! faithful to the normals: discontinuities, or non-integrable (wrong) normals.

pub mod bilateral;
pub mod fourier;
pub mod masked;
pub mod path;
pub mod poisson;
pub(crate) mod sparse;

pub use bilateral::BilateralParams;
pub use masked::SolveInfo;
pub use sparse::LinearSolver;

use crate::camera::Intrinsics;
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::normals::{MIN_NZ, gradients};
use crate::progress::Progress;
use rayon::prelude::*;
use serde::Serialize;

/// Normal-integration method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum Integrator {
    /// Least-squares (Poisson) integration over the whole image by DCT, Neumann boundary
    /// (Simchony, Chellappa & Shao 1990). Fast; pixels outside the mask are treated as flat.
    Poisson,
    /// Quality-guided path integration along spanning trees of the mask, several averaged.
    /// Mask-aware, but noise accumulates along paths.
    Path,
    /// Frankot–Chellappa (1988): least squares in the Fourier basis; periodic boundary.
    FrankotChellappa,
    /// Least squares on the mask only, free boundary, sparse solve. The default: exact on any
    /// mask shape, at a few times the cost of DCT Poisson.
    #[default]
    MaskedLs,
    /// Bilateral normal integration (Cao et al. 2022): discontinuity preserving.
    Bilateral,
}

impl Integrator {
    /// Every method, for listings and benchmarks.
    pub const ALL: [Integrator; 5] = [
        Integrator::Poisson,
        Integrator::Path,
        Integrator::FrankotChellappa,
        Integrator::MaskedLs,
        Integrator::Bilateral,
    ];

    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Integrator::Poisson => "poisson",
            Integrator::Path => "path",
            Integrator::FrankotChellappa => "fc",
            Integrator::MaskedLs => "masked-ls",
            Integrator::Bilateral => "bilateral",
        }
    }
}

/// Number of spanning trees averaged by [`Integrator::Path`].
pub const DEFAULT_PATHS: usize = 4;

/// What to integrate with.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct IntegrationOptions {
    /// The method.
    pub method: Integrator,
    /// Pinhole intrinsics for perspective integration; `None` for orthographic.
    pub camera: Option<Intrinsics>,
    /// Linear solver of the masked methods.
    pub solver: LinearSolver,
    /// Parameters of [`Integrator::Bilateral`].
    pub bilateral: BilateralParams,
}

/// Depth and diagnostics from [`integrate_normals`].
#[derive(Debug, Clone)]
pub struct Integration {
    /// Orthographic: height towards the camera (pixel units, zero-mean per part). Perspective:
    /// depth along the optical axis, up to scale (geometric mean 1 per part). NaN outside.
    pub depth: ScalarMap,
    /// Per-pixel RMS of (depth difference − trapezoid gradient) over the pixel's edges, in the
    /// integrated quantity's units (height, or log depth); NaN outside.
    pub residual: ScalarMap,
    /// Bilateral only: the forward weights along u and v (near 0 or 1 at discontinuities).
    pub weights: Option<(ScalarMap, ScalarMap)>,
    /// Masked methods: how the (last) linear system was solved.
    pub solve: Option<SolveInfo>,
    /// Bilateral only: reweighting iterations.
    pub iterations: usize,
}

/// Log-depth gradients (∂z̃/∂x, ∂z̃/∂y with x right, y up) under a pinhole camera; m is clamped
/// at [`MIN_NZ`] like n_z in the orthographic case.
pub fn perspective_gradients(
    normals: &NormalMap,
    mask: &Mask,
    k: &Intrinsics,
) -> (ScalarMap, ScalarMap) {
    let w = normals.width();
    let mut p = Grid::new(w, normals.height(), f32::NAN);
    let mut q = p.clone();
    for (i, n) in normals.data().iter().enumerate() {
        if !mask.data()[i] || !n.iter().all(|v| v.is_finite()) {
            continue;
        }
        let n = n.cast::<f64>();
        let (col, row) = ((i % w) as f64, (i / w) as f64);
        let m =
            (n.z - n.x * (col - k.cx) / k.fx + n.y * (row - k.cy) / k.fy).max(f64::from(MIN_NZ));
        p.data_mut()[i] = (n.x / (k.fx * m)) as f32;
        // ∂z̃/∂y = −∂z̃/∂v.
        q.data_mut()[i] = (n.y / (k.fy * m)) as f32;
    }
    (p, q)
}

/// Integrates a gradient field (p, q) (x right, y up) over `mask` with a gradient-based method.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no masked pixel has a
/// finite gradient; [`Error::InvalidParameter`] for [`Integrator::Bilateral`], which needs the
/// normals ([`integrate_normals`]), or when a sparse factorisation fails.
pub fn integrate_gradients(
    p: &ScalarMap,
    q: &ScalarMap,
    mask: &Mask,
    method: Integrator,
    solver: LinearSolver,
) -> Result<(ScalarMap, Option<SolveInfo>)> {
    p.check_same_size(q, "q vs p")?;
    p.check_same_size(mask, "mask vs gradients")?;
    let domain = gradient_domain(p, q, mask)?;
    Ok(match method {
        Integrator::Poisson => (poisson::integrate_poisson(p, q, &domain), None),
        Integrator::Path => (path::integrate_path(p, q, &domain, DEFAULT_PATHS), None),
        Integrator::FrankotChellappa => (fourier::integrate_fourier(p, q, &domain), None),
        Integrator::MaskedLs => {
            let (z, info) = masked::integrate_masked_ls(p, q, &domain, solver)?;
            (z, Some(info))
        }
        Integrator::Bilateral => {
            return Err(Error::param(
                "method",
                "bilateral integration works on normals, not gradients: use integrate_normals",
            ));
        }
    })
}

/// Integrates a normal map over `mask` (see the module documentation).
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no masked pixel has a
/// finite normal; [`Error::InvalidParameter`] when a sparse factorisation fails.
pub fn integrate_normals(
    normals: &NormalMap,
    mask: &Mask,
    options: &IntegrationOptions,
    progress: &dyn Progress,
) -> Result<Integration> {
    normals.check_same_size(mask, "mask vs normals")?;
    let (p, q) = match &options.camera {
        None => gradients(normals, mask),
        Some(k) => perspective_gradients(normals, mask, k),
    };
    let domain = gradient_domain(&p, &q, mask)?;
    progress.begin(options.method.name(), 1);
    let (z, solve, weights, iterations) = if options.method == Integrator::Bilateral {
        let r = bilateral::integrate_bilateral(
            normals,
            &domain,
            options.camera.as_ref(),
            &options.bilateral,
            options.solver,
        )?;
        (r.z, Some(r.solve), Some((r.wu, r.wv)), r.iterations)
    } else {
        let (z, solve) = integrate_gradients(&p, &q, &domain, options.method, options.solver)?;
        (z, solve, None, 0)
    };
    progress.advance(1);
    progress.end();
    let residual = integration_residual(&z, &p, &q, &domain);
    let depth = match &options.camera {
        None => z,
        Some(_) => z.map(|v| v.exp()),
    };
    Ok(Integration {
        depth,
        residual,
        weights,
        solve,
        iterations,
    })
}

/// Pixels of `mask` where both gradients are finite.
fn gradient_domain(p: &ScalarMap, q: &ScalarMap, mask: &Mask) -> Result<Mask> {
    let domain = Grid::from_vec(
        p.width(),
        p.height(),
        p.data()
            .par_iter()
            .zip(q.data())
            .zip(mask.data())
            .map(|((p, q), m)| *m && p.is_finite() && q.is_finite())
            .collect(),
    )?;
    if domain.count() == 0 {
        return Err(Error::Mask {
            path: "<integration domain>".into(),
            reason: "no masked pixel has a finite normal".into(),
        });
    }
    Ok(domain)
}

/// Per-pixel RMS over the pixel's edges within `domain` of (z_j − z_i − trapezoid difference).
pub fn integration_residual(
    z: &ScalarMap,
    p: &ScalarMap,
    q: &ScalarMap,
    domain: &Mask,
) -> ScalarMap {
    let (w, h) = (z.width(), z.height());
    let (right, down) = edge_differences(p, q, domain);
    let zd = z.data();
    let mut sum = vec![0f64; w * h];
    let mut count = vec![0u32; w * h];
    for i in 0..w * h {
        for (j, d) in [(i + 1, right[i]), (i + w, down[i])] {
            if d.is_nan() || j >= w * h {
                continue;
            }
            let e = (f64::from(zd[j]) - f64::from(zd[i]) - d).powi(2);
            sum[i] += e;
            sum[j] += e;
            count[i] += 1;
            count[j] += 1;
        }
    }
    let data = (0..w * h)
        .map(|i| {
            if domain.data()[i] && count[i] > 0 {
                (sum[i] / f64::from(count[i])).sqrt() as f32
            } else if domain.data()[i] {
                0.0
            } else {
                f32::NAN
            }
        })
        .collect();
    Grid::from_vec(w, h, data).unwrap_or_else(|_| Grid::new(w, h, f32::NAN))
}

/// ∫ between the centres of the middle two of four equally spaced derivative samples, exact for
/// polynomials up to degree 4: (−g₋₁ + 13g₀ + 13g₁ − g₂)/24.
fn quadrature(gm: f32, g0: f32, g1: f32, g2: f32) -> f64 {
    (13.0 * (f64::from(g0) + f64::from(g1)) - f64::from(gm) - f64::from(g2)) / 24.0
}

/// Depth differences on the edges of `domain` from the gradients: the fourth-order rule
/// [`quadrature`] where two more samples along the line lie in the domain, the trapezoid rule
/// (the mean of the two end samples) next to its edge. Indexed so that
/// `right[i]` = z(x+1, y) − z(x, y) and `down[i]` = z(x, y+1) − z(x, y) (row below), NaN where
/// the edge leaves the domain.
pub(crate) fn edge_differences(
    p: &ScalarMap,
    q: &ScalarMap,
    domain: &Mask,
) -> (Vec<f64>, Vec<f64>) {
    let (w, h) = (p.width(), p.height());
    let (pd, qd, m) = (p.data(), q.data(), domain.data());
    let mut right = vec![f64::NAN; w * h];
    let mut down = vec![f64::NAN; w * h];
    right
        .par_chunks_mut(w)
        .zip(down.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (right, down))| {
            for x in 0..w {
                let i = y * w + x;
                if !m[i] {
                    continue;
                }
                if x + 1 < w && m[i + 1] {
                    right[x] = if x >= 1 && x + 2 < w && m[i - 1] && m[i + 2] {
                        quadrature(pd[i - 1], pd[i], pd[i + 1], pd[i + 2])
                    } else {
                        0.5 * (f64::from(pd[i]) + f64::from(pd[i + 1]))
                    };
                }
                // y is up, so going one row down changes z by −q.
                if y + 1 < h && m[i + w] {
                    down[x] = -if y >= 1 && y + 2 < h && m[i - w] && m[i + 2 * w] {
                        quadrature(qd[i - w], qd[i], qd[i + w], qd[i + 2 * w])
                    } else {
                        0.5 * (f64::from(qd[i]) + f64::from(qd[i + w]))
                    };
                }
            }
        });
    (right, down)
}

/// Sets pixels outside `domain` to NaN and subtracts the mean over `domain`.
pub(crate) fn finish_depth(z: Vec<f64>, domain: &Mask) -> ScalarMap {
    let m = domain.data();
    let (sum, n) = z
        .par_iter()
        .zip(m)
        .filter(|(_, m)| **m)
        .map(|(z, _)| (*z, 1usize))
        .reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    let mean = if n > 0 { sum / n as f64 } else { 0.0 };
    let data = z
        .par_iter()
        .zip(m)
        .map(|(z, m)| if *m { (z - mean) as f32 } else { f32::NAN })
        .collect();
    Grid::from_vec(domain.width(), domain.height(), data)
        .unwrap_or_else(|_| Grid::new(domain.width(), domain.height(), f32::NAN))
}
