//! Colour photometric stereo with one normal per pixel, for RGB images under lights of known
//! RGB intensity.
//!
//! Once each channel is divided by its light's intensity e_{k,c}, the Lambertian model reads
//! I_{k,c} = ρ_c·max(0, N·l_k): three albedos and one normal. Per-channel solves
//! ([`ColorSolve::PerChannel`]) fit g_c = ρ_c·N in each channel on its own, so noise gives the
//! three estimates different directions and the normal is taken from their sum. The
//! shared-normal solve ([`ColorSolve::SharedNormal`]) fits the channels jointly:
//!
//! minimise Σ_c Σ_k w_k·(I_{k,c} − ρ_c·N·l_k)² over N and ρ,
//!
//! that is, G = [g_R g_G g_B] = N·ρᵀ of rank one. With A = Σ_k w_k·l_k·l_kᵀ and the
//! unconstrained per-channel solution Ĝ = A⁻¹·Σ_k w_k·l_k·I_kᵀ, the objective equals
//! Σ_c (g_c − ĝ_c)ᵀ·A·(g_c − ĝ_c) plus a constant, so the optimum is the best rank-one
//! approximation of Ĝ in the metric of A (Eckart & Young 1936, "The approximation of one matrix
//! by another of lower rank", Psychometrika 1(3)). Writing A = RᵀR (Cholesky), N ∝ R⁻¹·u for u
//! the leading eigenvector of (RĜ)(RĜ)ᵀ, and ρ_c = Nᵀ·A·ĝ_c / Nᵀ·A·N. This is the
//! maximum-likelihood normal when the three channels carry equal noise; it weights each channel
//! by its signal, where a fixed grey mix lets a dim channel count only by its BT.601 weight, and
//! it returns an RGB albedo that belongs to the one normal.
//!
//! Which samples count, and how much (shadows, highlights, saturation), is decided once per pixel
//! by the estimator of the [`SolveOptions`] run on the grey mix of the channels — for the default
//! [`crate::ps::solve::Method::Auto`], the Lambertian fit test and, where it fails, specular
//! rejection — so the channels share the sample weights w_k as well as the normal. The grey mix
//! also supplies the noise estimate and the per-image intensity gains.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::Mask;
use crate::progress::Progress;
use crate::ps::solve::{
    ImageModel, PixelSolution, PixelStatus, Solution, SolveOptions, check_inputs, check_model,
    fit_with, fitter, noise_and_gains,
};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::Serialize;

/// How the channels of an RGB capture are solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColorSolve {
    /// One normal and three albedos fitted jointly (this module).
    #[default]
    SharedNormal,
    /// An independent g_c per channel; the normal is the direction of g_R + g_G + g_B
    /// ([`crate::ps::normals::combine_channels`]).
    PerChannel,
}

/// Masked pixels per parallel work item.
const CHUNK: usize = 2048;

/// One pixel of the shared-normal solve.
#[derive(Debug, Clone, Copy)]
struct ColorPixel {
    normal: Vector3<f64>,
    albedo: [f64; 3],
    /// RMS residual over the used samples of all three channels.
    residual: f64,
    grey: PixelSolution,
}

/// Solves a 3-channel `stack` for one normal and an RGB albedo per masked pixel (see the module
/// documentation). The result has one [`Solution`] per channel with g_c = ρ_c·N, so
/// [`crate::ps::normals::combine_channels`] returns the shared normal and the per-channel albedo;
/// residual, samples, condition, status and robust flags are the same in all three.
///
/// # Errors
/// [`Error::InvalidParameter`] when the stack does not have 3 channels or the options are
/// invalid; [`Error::LightsMismatch`] when the light count differs from the image count;
/// [`Error::DimensionMismatch`] for a mask of another size.
///
/// # Example
/// ```
/// use photostereo::{ps::color::solve_shared_normal, grid::Grid, capture::stack::ImageStack};
/// use photostereo::{capture::lights::Lights, progress::Silent, ps::solve::SolveOptions};
/// let lights = Lights::ring(8, 45.0, 0.0)?;
/// // A flat patch facing the camera with RGB albedo (0.6, 0.4, 0.2): I_kc = ρ_c · l_k.z.
/// let images = lights
///     .directions()
///     .iter()
///     .map(|l| [0.6, 0.4, 0.2].iter().flat_map(|r| vec![(r * l.z) as f32; 4]).collect())
///     .collect();
/// let stack = ImageStack::from_images(2, 2, 3, images)?;
/// let sol = solve_shared_normal(&stack, &lights, &Grid::new(2, 2, true), &SolveOptions::default(), &Silent)?;
/// assert!((sol[2].g.at(0, 0).z - 0.2).abs() < 1e-5);
/// # Ok::<(), photostereo::Error>(())
/// ```
pub fn solve_shared_normal(
    stack: &ImageStack,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    progress: &dyn Progress,
) -> Result<Vec<Solution>> {
    check_rgb_inputs(stack, lights, mask, options)?;
    let grey = stack.grey_mix();
    let (sigma, gains) = noise_and_gains(&grey, 0, lights, mask, options);
    fit_shared(
        stack,
        &grey,
        lights,
        mask,
        options,
        ImageModel {
            sigma,
            gains,
            lobe_limit: None,
        },
        progress,
    )
}

/// [`solve_shared_normal`] with the per-image noise and gains given (estimated on the grey mix
/// of the whole capture, see [`ImageModel`]): the solve of one part of a capture.
///
/// # Errors
/// As [`solve_shared_normal`]; [`Error::InvalidParameter`] when the model's length differs
/// from the image count.
pub fn solve_shared_normal_with_model(
    stack: &ImageStack,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    model: ImageModel,
    progress: &dyn Progress,
) -> Result<Vec<Solution>> {
    solve_shared_normal_with_grey(
        stack,
        &stack.grey_mix(),
        lights,
        mask,
        options,
        model,
        progress,
    )
}

/// [`solve_shared_normal_with_model`] with the grey mix of `stack` ([`ImageStack::grey_mix`])
/// already made (an in-memory run makes it once, for the model and the fit).
pub(crate) fn solve_shared_normal_with_grey(
    stack: &ImageStack,
    grey: &ImageStack,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    model: ImageModel,
    progress: &dyn Progress,
) -> Result<Vec<Solution>> {
    check_rgb_inputs(stack, lights, mask, options)?;
    check_model(&model, stack.count())?;
    fit_shared(stack, grey, lights, mask, options, model, progress)
}

/// The checks of [`check_inputs`], and that the stack is RGB.
pub(crate) fn check_rgb_inputs(
    stack: &ImageStack,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
) -> Result<()> {
    if stack.channels() != 3 {
        return Err(Error::param(
            "stack",
            format!(
                "the shared-normal colour solve needs RGB images; the stack has {} channel(s)",
                stack.channels()
            ),
        ));
    }
    check_inputs(stack, 0, lights, mask, options)
}

/// The per-pixel fits of the shared-normal solve, under `model`.
fn fit_shared(
    stack: &ImageStack,
    grey: &ImageStack,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    model: ImageModel,
    progress: &dyn Progress,
) -> Result<Vec<Solution>> {
    let ImageModel { sigma, gains, .. } = model;
    let dirs = lights.directions();
    let k = stack.count();
    let pixels: Vec<usize> = (0..mask.len()).filter(|&i| mask.data()[i]).collect();
    progress.begin("solve", pixels.len().div_ceil(CHUNK) as u64);
    let fitted: Vec<Vec<ColorPixel>> = pixels
        .par_chunks(CHUNK)
        .map_init(
            || fitter(&dirs, &gains.gains, options),
            |f, chunk| {
                let m = chunk.len();
                // Gather the chunk as [pixel][image] (grey, flags) and [pixel][channel][image].
                let mut values = vec![0f32; m * k];
                let mut saturated = vec![false; m * k];
                let mut colour = vec![0f32; 3 * m * k];
                for img in 0..k {
                    let g = grey.plane(img, 0);
                    let planes = [0, 1, 2].map(|c| stack.plane(img, c));
                    for (i, &p) in chunk.iter().enumerate() {
                        // The mask lies in the window (checked above).
                        let Some(local) = stack.local(p) else {
                            continue;
                        };
                        values[i * k + img] = g[local];
                        saturated[i * k + img] = grey.is_saturated(img, p);
                        for (c, plane) in planes.iter().enumerate() {
                            colour[(i * 3 + c) * k + img] = plane[local];
                        }
                    }
                }
                let out = (0..m)
                    .map(|i| {
                        let samples = i * k..(i + 1) * k;
                        let p = fit_with(
                            f,
                            &values[samples.clone()],
                            &saturated[samples],
                            &sigma,
                            options,
                        );
                        shared_fit(
                            &dirs,
                            &gains.gains,
                            f.weights(),
                            &colour[i * 3 * k..(i + 1) * 3 * k],
                            p,
                        )
                    })
                    .collect();
                progress.advance(1);
                out
            },
        )
        .collect();
    progress.end();
    let (w, h) = (stack.width(), stack.height());
    let mut out: Vec<Solution> = (0..3)
        .map(|_| Solution::empty(w, h, gains.clone(), sigma.clone(), options))
        .collect();
    for (&p, px) in pixels.iter().zip(fitted.iter().flatten()) {
        for (c, sol) in out.iter_mut().enumerate() {
            let channel = PixelSolution {
                g: px.normal * px.albedo[c],
                residual: px.residual,
                ..px.grey
            };
            sol.record(p, &channel);
        }
    }
    // The light in each channel's attached shadows, on the shared normals and that channel's
    // albedo (before the fill, as the grey solve measures it).
    for (c, sol) in out.iter_mut().enumerate() {
        sol.shadow_light = Some(crate::ps::ambient::measure(stack, c, lights, mask, sol));
        sol.light_agreement = Some(crate::ps::light_agreement::measure(
            stack, c, lights, mask, sol,
        ));
    }
    if options.fill {
        // Each channel from its solved neighbours only: the grey fit's weights that would
        // give the data term are not kept for the pixels it could not solve.
        for sol in &mut out {
            crate::ps::fill::fill(sol, &[]);
        }
    }
    Ok(out)
}

/// The rank-one fit of one pixel: `colour` holds the three channels' samples ([channel][image]),
/// `weights` the per-image weights of the grey fit `grey`, `gains` the intensity corrections.
fn shared_fit(
    dirs: &[Vector3<f64>],
    gains: &[f32],
    weights: &[f64],
    colour: &[f32],
    grey: PixelSolution,
) -> ColorPixel {
    let k = dirs.len();
    let failed = |status| ColorPixel {
        normal: Vector3::repeat(f64::NAN),
        albedo: [f64::NAN; 3],
        residual: f64::NAN,
        grey: PixelSolution { status, ..grey },
    };
    if grey.status != PixelStatus::Solved {
        return failed(grey.status);
    }
    let sample = |c: usize, j: usize| f64::from(colour[c * k + j]) * f64::from(gains[j]);
    let mut a = Matrix3::zeros();
    let mut b = Matrix3::zeros();
    let mut used = 0;
    for (j, l) in dirs.iter().enumerate() {
        let w = weights[j];
        if w <= 0.0 {
            continue;
        }
        used += 1;
        a += l * l.transpose() * w;
        for c in 0..3 {
            let mut col = b.column_mut(c);
            col += l * (w * sample(c, j));
        }
    }
    let Some(chol) = a.cholesky() else {
        return failed(PixelStatus::IllConditioned);
    };
    let g_hat = chol.solve(&b);
    let r = chol.l().transpose();
    let m = r * g_hat;
    let eigen = (m * m.transpose()).symmetric_eigen();
    let top = eigen.eigenvalues.imax();
    let u = eigen.eigenvectors.column(top).into_owned();
    let Some(n) = r.solve_upper_triangular(&u) else {
        return failed(PixelStatus::IllConditioned);
    };
    let mut n = n.normalize();
    let an = a * n;
    let nan = n.dot(&an);
    let mut albedo = [0, 1, 2].map(|c| an.dot(&g_hat.column(c)) / nan);
    if albedo.iter().sum::<f64>() < 0.0 {
        n = -n;
        albedo = albedo.map(|v| -v);
    }
    // A negative albedo is noise in a channel without signal.
    let albedo = albedo.map(|v| v.max(0.0));
    if !n.iter().all(|v| v.is_finite()) || albedo.iter().all(|&v| v <= 0.0) {
        return failed(PixelStatus::Dark);
    }
    let mut ss = 0.0;
    for (j, l) in dirs.iter().enumerate() {
        if weights[j] > 0.0 {
            let shading = n.dot(l);
            for (c, rho) in albedo.iter().enumerate() {
                ss += (sample(c, j) - rho * shading).powi(2);
            }
        }
    }
    ColorPixel {
        normal: n,
        albedo,
        residual: (ss / (3 * used.max(1)) as f64).sqrt(),
        grey,
    }
}

/// The shared-normal solve on noise-free synthetic RGB stacks whose channels share one normal
/// but differ in albedo: it returns that normal and the three albedos to the accuracy of the
/// f32 inputs (the closed form of the module documentation is exact for such data), with the
/// per-image gains of a given model applied to every channel; and the channel, light, mask,
/// option and model checks refuse what they should.
#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::stack::ImageStack;
    use crate::grid::Grid;
    use crate::progress::Silent;
    use crate::ps::intensities::GainEstimate;
    use crate::synth::test_support::{lambertian_stack, sphere};

    /// Unit roundoff of f32 (2⁻²⁴).
    const U: f64 = f32::EPSILON as f64 / 2.0;

    /// Angle in radians between two vectors (atan2 form: accurate at small angles).
    fn angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
        a.cross(b).norm().atan2(a.dot(b))
    }

    /// Errors of a solve of exact data, over the masked pixels and the channels.
    #[derive(Debug)]
    struct Worst {
        /// Largest angle (radians) between a channel's g and the true normal.
        angle: f64,
        /// Largest relative error of a channel's |g| against its albedo (absolute where the
        /// albedo is 0).
        albedo: f64,
        /// Largest of both errors divided by the pixel's bound (below 1 when within bounds).
        ratio: f64,
    }

    /// The errors of `sol` against `truth` and `albedo`, each measured against its pixel's bound:
    /// the samples carry `roundings` f32 roundings (relative error ≤ `roundings`·u each, u =
    /// 2⁻²⁴), so |δI| ≤ `roundings`·u·|I| ≤ `roundings`·u·σ_max·|g|, and least squares turns
    /// that into |δg|/|g| ≤ `roundings`·κ·u with κ = σ_max/σ_min of the used light directions
    /// (the solution's condition); storing g in f32 adds u to the direction and the length, and
    /// the length's norm one more u. Asserts every masked pixel is solved in every channel and
    /// every other pixel is outside.
    fn worst_errors(
        sol: &[Solution],
        truth: &Grid<Vector3<f64>>,
        mask: &Mask,
        albedo: [f64; 3],
        roundings: f64,
    ) -> Worst {
        assert_eq!(sol.len(), 3);
        let mut w = Worst {
            angle: 0.0,
            albedo: 0.0,
            ratio: 0.0,
        };
        for p in 0..mask.len() {
            for (c, s) in sol.iter().enumerate() {
                if !mask.data()[p] {
                    assert_eq!(s.status.data()[p], PixelStatus::Outside);
                    continue;
                }
                assert_eq!(s.status.data()[p], PixelStatus::Solved, "pixel {p}");
                let bound = (roundings * f64::from(s.condition.data()[p]) + 2.0) * U;
                let g = s.g.data()[p].cast::<f64>();
                let rho = g.norm();
                let (a, r) = if albedo[c] > 0.0 {
                    (
                        angle(&g, &truth.data()[p]),
                        (rho - albedo[c]).abs() / albedo[c],
                    )
                } else {
                    // No signal: g must be zero, not noise.
                    (0.0, rho)
                };
                w.angle = w.angle.max(a);
                w.albedo = w.albedo.max(r);
                w.ratio = w.ratio.max(a.max(r) / bound);
            }
        }
        w
    }

    /// A 16×16 sphere (normals up to 60° from the view) under 12 lights at 30°–90° elevation,
    /// with three different albedos per pixel — including a channel without signal, whose
    /// albedo must come out 0 rather than negative — is solved exactly: every channel's g
    /// points along the true normal and has the channel's albedo as its length, within the
    /// f32 bound of [`worst_errors`].
    #[test]
    fn recovers_the_shared_normal_and_three_albedos() {
        let (normals, mask) = sphere(16, 60.0);
        assert!(mask.count() > 100, "{} pixels", mask.count());
        let lights = Lights::fibonacci(12, 30.0).unwrap();
        for albedo in [[0.8, 0.45, 0.1], [0.6, 0.3, 0.0]] {
            let stack = lambertian_stack(&normals, &mask, &lights, &albedo, &[1.0; 12]);
            let sol =
                solve_shared_normal(&stack, &lights, &mask, &SolveOptions::default(), &Silent)
                    .unwrap();
            // Each sample is one rounding of the exact value to f32.
            let w = worst_errors(&sol, &normals, &mask, albedo, 1.0);
            println!("albedo {albedo:?}: {w:?}");
            assert!(w.ratio < 1.0, "albedo {albedo:?}: {w:?}");
        }
    }

    /// Images that read brighter or dimmer than their stated intensity by known factors are
    /// solved exactly when the model carries the inverse factors as gains: the gains multiply
    /// every channel's samples, not only the grey mix that chooses the samples. (Without them
    /// the data are not Lambertian and no normal fits them exactly.)
    #[test]
    fn model_gains_scale_every_channel() {
        let (normals, mask) = sphere(16, 60.0);
        let lights = Lights::fibonacci(12, 30.0).unwrap();
        let mut scale = [1.0; 12];
        for (k, s) in [(1, 0.8), (4, 1.25), (7, 0.9), (10, 1.15)] {
            scale[k] = s;
        }
        let albedo = [0.7, 0.5, 0.25];
        let stack = lambertian_stack(&normals, &mask, &lights, &albedo, &scale);
        let model = ImageModel {
            sigma: vec![1e-3; 12],
            gains: GainEstimate {
                gains: scale.iter().map(|s| (1.0 / s) as f32).collect(),
                ..GainEstimate::unit(12)
            },
            lobe_limit: None,
        };
        let options = SolveOptions::default();
        let sol = solve_shared_normal_with_model(&stack, &lights, &mask, &options, model, &Silent)
            .unwrap();
        // Two roundings per sample: the sample's and the f32 gain's (their product is exact
        // in f64).
        let w = worst_errors(&sol, &normals, &mask, albedo, 2.0);
        println!("with gains: {w:?}");
        assert!(w.ratio < 1.0, "{w:?}");
    }

    /// A grey stack, a light count or mask size that differs from the stack's, invalid options
    /// and a model of the wrong length are refused with the error that names them.
    #[test]
    fn refuses_inputs_that_do_not_fit() {
        let (normals, mask) = sphere(16, 60.0);
        let lights = Lights::fibonacci(12, 30.0).unwrap();
        let rgb = lambertian_stack(&normals, &mask, &lights, &[0.5, 0.5, 0.5], &[1.0; 12]);
        let grey = lambertian_stack(&normals, &mask, &lights, &[0.5], &[1.0; 12]);
        let options = SolveOptions::default();
        let solve = |stack: &ImageStack, lights: &Lights, mask: &Mask, options: &SolveOptions| {
            solve_shared_normal(stack, lights, mask, options, &Silent)
        };

        let e = solve(&grey, &lights, &mask, &options).unwrap_err();
        assert!(
            matches!(&e, Error::InvalidParameter { name: "stack", reason } if reason.contains("1 channel(s)")),
            "{e}"
        );
        let eleven = Lights::fibonacci(11, 30.0).unwrap();
        let e = solve(&rgb, &eleven, &mask, &options).unwrap_err();
        assert!(
            matches!(&e, Error::LightsMismatch { reason } if reason.contains("11 lights for 12 images")),
            "{e}"
        );
        let narrow = Grid::new(15, 16, true);
        let e = solve(&rgb, &lights, &narrow, &options).unwrap_err();
        assert!(
            matches!(
                e,
                Error::DimensionMismatch {
                    width: 16,
                    height: 16,
                    found_width: 15,
                    found_height: 16,
                    ..
                }
            ),
            "{e}"
        );
        let bad = SolveOptions {
            shadow_threshold: 1.0,
            ..SolveOptions::default()
        };
        let e = solve(&rgb, &lights, &mask, &bad).unwrap_err();
        assert!(
            matches!(
                e,
                Error::InvalidParameter {
                    name: "shadow-threshold",
                    ..
                }
            ),
            "{e}"
        );

        let model = |n: usize| ImageModel {
            sigma: vec![1e-3; n],
            gains: GainEstimate::unit(n),
            lobe_limit: None,
        };
        let with_model = |stack: &ImageStack, m: ImageModel| {
            solve_shared_normal_with_model(stack, &lights, &mask, &options, m, &Silent)
        };
        let e = with_model(&rgb, model(11)).unwrap_err();
        assert!(
            matches!(&e, Error::InvalidParameter { name: "model", reason } if reason.contains("for 12 images")),
            "{e}"
        );
        let e = with_model(&grey, model(12)).unwrap_err();
        assert!(
            matches!(e, Error::InvalidParameter { name: "stack", .. }),
            "{e}"
        );
        // The right inputs pass the same checks.
        assert!(with_model(&rgb, model(12)).is_ok());
    }
}
