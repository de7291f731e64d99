//! Depth from surface gradients: normal integration.
//!
//! Input is the gradient field p = ∂z/∂x, q = ∂z/∂y of [`crate::normals::gradients`] (x right,
//! y up, pixel units, NaN where undefined) and the object mask; output is a depth map z in pixel
//! units (larger = nearer the camera), zero-mean over the mask (per connected part for path
//! integration), NaN outside the mask. Orthographic camera.
//!
//! Both integrators work on the same discretisation: the depth difference along an edge between
//! two neighbouring pixels is the trapezoid-rule value, the mean of the two pixels' gradients
//! along that edge.

pub mod path;
pub mod poisson;

use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap};
use crate::progress::Progress;
use serde::Serialize;

/// Normal-integration method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum Integrator {
    /// Least-squares (Poisson) integration over the whole image by DCT, Neumann boundary
    /// (Simchony, Chellappa & Shao 1990). Fast; pixels outside the mask are treated as flat.
    #[default]
    Poisson,
    /// Path integration with the trapezoid rule along breadth-first spanning trees of the mask
    /// from several seeds, averaged. Mask-aware, but noise accumulates along paths.
    Path,
}

impl Integrator {
    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Integrator::Poisson => "poisson",
            Integrator::Path => "path",
        }
    }
}

/// Number of spanning trees averaged by [`Integrator::Path`].
pub const DEFAULT_PATHS: usize = 4;

/// Integrates (p, q) over `mask` with `integrator`.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no masked pixel has a
/// finite gradient.
pub fn integrate(
    p: &ScalarMap,
    q: &ScalarMap,
    mask: &Mask,
    integrator: Integrator,
    progress: &dyn Progress,
) -> Result<ScalarMap> {
    p.check_same_size(q, "q vs p")?;
    p.check_same_size(mask, "mask vs gradients")?;
    let domain = Grid::from_vec(
        p.width(),
        p.height(),
        p.data()
            .iter()
            .zip(q.data())
            .zip(mask.data())
            .map(|((p, q), m)| *m && p.is_finite() && q.is_finite())
            .collect(),
    )?;
    if domain.count() == 0 {
        return Err(Error::Mask {
            path: "<integration domain>".into(),
            reason: "no masked pixel has a finite gradient".into(),
        });
    }
    progress.begin(integrator.name(), 1);
    let z = match integrator {
        Integrator::Poisson => poisson::integrate_poisson(p, q, &domain),
        Integrator::Path => path::integrate_path(p, q, &domain, DEFAULT_PATHS),
    };
    progress.advance(1);
    progress.end();
    Ok(z)
}

/// Trapezoid-rule depth differences on the edges of `domain`:
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
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !m[i] {
                continue;
            }
            if x + 1 < w && m[i + 1] {
                right[i] = 0.5 * (f64::from(pd[i]) + f64::from(pd[i + 1]));
            }
            // y is up, so going one row down changes z by −q.
            if y + 1 < h && m[i + w] {
                down[i] = -0.5 * (f64::from(qd[i]) + f64::from(qd[i + w]));
            }
        }
    }
    (right, down)
}

/// Sets pixels outside `domain` to NaN and subtracts the mean over `domain`.
pub(crate) fn finish_depth(z: Vec<f64>, domain: &Mask) -> ScalarMap {
    let m = domain.data();
    let (sum, n) = z
        .iter()
        .zip(m)
        .filter(|(_, m)| **m)
        .fold((0.0, 0usize), |(s, n), (z, _)| (s + z, n + 1));
    let mean = if n > 0 { sum / n as f64 } else { 0.0 };
    let data = z
        .iter()
        .zip(m)
        .map(|(z, m)| if *m { (z - mean) as f32 } else { f32::NAN })
        .collect();
    Grid::from_vec(domain.width(), domain.height(), data)
        .unwrap_or_else(|_| Grid::new(domain.width(), domain.height(), f32::NAN))
}
