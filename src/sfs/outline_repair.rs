//! A second solve of Horn's method, at twice the resolution, for a result that contradicts the
//! occluding boundary it assumed ([`super::OutlineAgreement`]), kept only when it honours it.
//!
//! Why: on a small image Horn's continuation in λ has no coarse-to-fine start (no level of half
//! resolution keeps [`super::horn`]'s 3 000 pixels), and the rim, where the occluding contour
//! sets the shape, is a pixel or two wide. There the iteration can settle on another surface
//! that explains the image as well: a Lambertian ellipsoid at 48² under a light 40° off the view
//! ends 26.5° wrong with half the outline's normals turned away from it. Solved on the image
//! upsampled 2×, the same shape comes out 2.1° off and its outline agrees. The upsampled solve
//! is not better in general (at 48² it turns the Lambertian sphere's 1.6° into 16°), so it is
//! only run when the first result fails the outline check, and only returned when its own result, on
//! this image's pixels, passes that check (and converged): otherwise the first result is returned with its
//! warning, and the report says the repair was tried (docs/shape-from-shading.md, "Does the
//! result honour the occluding boundary?").
//!
//! The upsampled level: each pixel of the mask becomes a 2×2 block; a fine pixel's E/ρ is the
//! bilinear interpolation (weights 9/16, 3/16, 3/16, 1/16 inside) of the mask's pixels around it,
//! renormalised over those in the mask, so that nothing from outside the object enters. Back on
//! this image, each pixel's gradient (p, q) is the mean of its four fine pixels' (a slope is the
//! same in fine pixels) and its height the mean of theirs, halved (heights are in each level's
//! pixels).
//!
//! Cost: the second solve has four times the unknowns and often crawls (rough surfaces), so it
//! is attempted only for images with no coarse-to-fine start of their own and at most
//! [`MAX_UNKNOWNS`] fine unknowns. Measured on rendered shapes (sphere, ellipsoid, vase, bust;
//! Lambertian and Oren–Nayar σ 0.4; lights 30° and 40° off the view): at 32²–64² it takes
//! 0.03–4.5 s and repairs 13 of 32 failures, 8 of them to within 6° (every kept result is
//! closer to the truth than the first); at 96² and 128², where the first solves are 6–21° off,
//! the kept ones gained 2–6° for 8–27 s, so images that large are not retried. [`super::SfsOptions::outline_repair`] turns it off.

use super::pyramid::bilinear_from_half;
use super::{OutlineAgreement, Shading, Solved, clamp_gradient, horn, outline_agreement};
use crate::error::Result;
use crate::grid::{Grid, Mask, NormalMap};
use crate::integrate::sparse::Unknowns;
use crate::sfs::reflectance_map::normal_from_gradient;
use nalgebra::Vector3;
use serde::Serialize;

/// The most unknowns the upsampled solve may have: those of a 128² frame (a mask of at most
/// 4 096 pixels is retried; see the module documentation for the costs that set it).
pub const MAX_UNKNOWNS: usize = 16_384;

/// What the repair did (in [`super::SfsReport::outline_repair`]).
#[non_exhaustive]
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OutlineRepair {
    /// The first solve's agreement with the outline, which failed the check.
    pub first: OutlineAgreement,
    /// The agreement of the solve at twice the resolution, measured on this image's pixels
    /// (`None` when it has no outline or the solve failed).
    pub upsampled: Option<OutlineAgreement>,
    /// Whether the upsampled solve's result is the one returned (it passed the check).
    pub kept: bool,
    /// Iterations of the upsampled solve (at full and at lower resolutions).
    pub iterations: usize,
    /// Whether the upsampled solve converged.
    pub converged: bool,
}

/// The outline agreement of a solver's result over the unknowns `u`.
pub(crate) fn agreement(
    u: &Unknowns,
    solved: &Solved,
    exclude: &[bool],
) -> Option<OutlineAgreement> {
    match &solved.normals {
        Some(v) => agreement_of(u, |k| v[k], exclude),
        None => agreement_of_gradients(u, &solved.p, &solved.q, exclude),
    }
}

/// The outline agreement of the gradients (`p`, `q`) of the unknowns `u`.
pub(crate) fn agreement_of_gradients(
    u: &Unknowns,
    p: &[f64],
    q: &[f64],
    exclude: &[bool],
) -> Option<OutlineAgreement> {
    agreement_of(u, |k| normal_from_gradient(p[k], q[k]), exclude)
}

/// The outline agreement of the normals `normal(k)` of the unknowns `u`.
fn agreement_of(
    u: &Unknowns,
    normal: impl Fn(usize) -> Vector3<f64>,
    exclude: &[bool],
) -> Option<OutlineAgreement> {
    let mut normals: NormalMap = Grid::new(u.w, u.h, Vector3::repeat(f32::NAN));
    for (k, &pix) in u.pixel.iter().enumerate() {
        normals.data_mut()[pix as usize] = normal(k).cast::<f32>();
    }
    outline_agreement(u, &normals, exclude)
}

/// Horn's result for `s`, repaired when it contradicts the occluding boundary (see the module
/// documentation): the result returned, and what the repair did when it was tried.
///
/// # Errors
/// As [`horn::solve`], for the first solve only: a failed second solve leaves the first result.
pub(crate) fn solve(s: &Shading) -> Result<(Solved, Option<OutlineRepair>)> {
    let first = horn::solve(s)?;
    let occluding = s.options.boundary == super::Boundary::Occluding;
    let cut = s.outline().contradicted;
    let Some(before) = agreement(&s.u, &first, &cut).filter(|_| occluding) else {
        return Ok((first, None));
    };
    if before.misaligned_fraction <= super::OUTLINE_MISALIGNED_WARN
        || !s.options.outline_repair
        || first.coarse_iterations > 0
        || s.start.is_some()
        || 4 * s.u.len() > MAX_UNKNOWNS
        || s.u.w < 2
        || s.u.h < 2
    {
        return Ok((first, None));
    }
    let (mask, e) = upsampled(s);
    let shading = Shading {
        u: Unknowns::new(&mask),
        shadow: e.iter().map(|&v| v <= s.options.shadow_level).collect(),
        e,
        rmap: s.rmap,
        options: s.options,
        progress: s.progress,
        start: None,
        // Not tested on the upsampled image: its outline pixels blend the original's with
        // brighter ones further in; the original's flags judge both results below.
        occluding_tolerance: None,
    };
    let Ok(second) = horn::solve(&shading) else {
        return Ok((
            first,
            Some(OutlineRepair {
                first: before,
                upsampled: None,
                kept: false,
                iterations: 0,
                converged: false,
            }),
        ));
    };
    let back = downsampled(s, &shading.u, &second);
    let after = agreement(&s.u, &back, &cut);
    let kept = second.converged
        && after.is_some_and(|a| a.misaligned_fraction <= super::OUTLINE_MISALIGNED_WARN);
    let repair = OutlineRepair {
        first: before,
        upsampled: after,
        kept,
        iterations: second.iterations + second.coarse_iterations,
        converged: second.converged,
    };
    Ok((if kept { back } else { first }, Some(repair)))
}

/// The mask upsampled 2× (each pixel a 2×2 block) and E/ρ on its unknowns, interpolated
/// bilinearly from the mask's pixels around each fine pixel.
fn upsampled(s: &Shading) -> (Mask, Vec<f64>) {
    let (w, h) = (s.u.w, s.u.h);
    let mut index = vec![usize::MAX; w * h];
    for (k, &p) in s.u.pixel.iter().enumerate() {
        index[p as usize] = k;
    }
    let mask = Grid::from_fn(2 * w, 2 * h, |c, r| {
        index[(r / 2) * w + c / 2] != usize::MAX
    });
    let mut e = Vec::with_capacity(4 * s.u.len());
    // Row-major over the fine mask: the order of the fine unknowns.
    for r in 0..2 * h {
        for c in 0..2 * w {
            let own = index[(r / 2) * w + c / 2];
            if own == usize::MAX {
                continue;
            }
            let (mut sum, mut weight) = (0.0, 0.0);
            for (x, y, wt) in bilinear_from_half(c, r, w, h) {
                let k = index[y * w + x];
                if k != usize::MAX && wt > 0.0 {
                    sum += wt * s.e[k];
                    weight += wt;
                }
            }
            // The pixel's own block always carries weight (at least 9/16).
            e.push(if weight > 0.0 { sum / weight } else { s.e[own] });
        }
    }
    (mask, e)
}

/// The fine solve `fine` (over the unknowns `fu` of the upsampled mask) on the unknowns of `s`:
/// each pixel's gradient the mean of its four fine pixels', its height their mean halved.
fn downsampled(s: &Shading, fu: &Unknowns, fine: &Solved) -> Solved {
    let fw = fu.w;
    let mut findex = vec![usize::MAX; fu.w * fu.h];
    for (k, &p) in fu.pixel.iter().enumerate() {
        findex[p as usize] = k;
    }
    let n = s.u.len();
    let (mut p, mut q, mut z) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    for (k, &pix) in s.u.pixel.iter().enumerate() {
        let (x, y) = (pix as usize % s.u.w, pix as usize / s.u.w);
        let (mut sp, mut sq, mut sz, mut m) = (0.0, 0.0, 0.0, 0.0);
        for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            let j = findex[(2 * y + dy) * fw + 2 * x + dx];
            if j != usize::MAX {
                sp += fine.p[j];
                sq += fine.q[j];
                sz += fine.z[j];
                m += 1.0;
            }
        }
        (p[k], q[k]) = clamp_gradient(sp / m, sq / m);
        z[k] = sz / m / 2.0;
    }
    let mut assumptions = fine.assumptions.clone();
    assumptions.push(
        "outline repair: the first solve contradicted the occluding boundary, so the image \
         was solved again upsampled 2× (bilinear), and that result, which honours the \
         boundary, is returned on this image's pixels"
            .to_string(),
    );
    Solved {
        p,
        q,
        z,
        normals: None,
        iterations: fine.iterations,
        coarse_iterations: fine.coarse_iterations,
        restarts: fine.restarts,
        converged: fine.converged,
        singular: 0,
        assumptions,
        warnings: fine.warnings.clone(),
    }
}
