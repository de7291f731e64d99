//! Image noise level from one image, for the model-fit test of the automatic method.
//!
//! Immerkær (1996), "Fast noise variance estimation", CVIU 64(2): the 3×3 operator
//! M = [1 −2 1; −2 4 −2; 1 −2 1] is the difference of two Laplacians, so it cancels the
//! smooth part of the image (it is zero on any quadratic patch) and leaves noise of standard
//! deviation 6σ. Here the median of |I * M| over pixels whose whole 3×3 neighbourhood is in the
//! mask replaces the mean, so albedo edges and occluding contours do not inflate the estimate:
//! σ = 1.4826 · median|I * M| / 6.

use crate::capture::stack::ImageStack;
use crate::grid::Mask;
use crate::ps::robust::MAD_TO_SIGMA;
use crate::stats::median_by;
use rayon::prelude::*;

/// Norm of the Immerkær operator: the standard deviation of its response to unit white noise.
const OPERATOR_NORM: f64 = 6.0;
/// At most this many responses are ranked per image (a regular subsample of the interior
/// beyond): the median of 5000 half-normal values has a relative standard error of 1.7%
/// (1.167/√n), which moves the fit test's χ² by 3.4%, well inside its margin; more would make the
/// estimate cost as much as a least-squares solve on matte data.
const MAX_RESPONSES: usize = 5_000;
/// Fewest responses for an estimate.
const MIN_RESPONSES: usize = 50;

/// Noise estimate of one image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseLevel {
    /// Standard deviation of the noise (NaN when the mask has too few interior pixels).
    pub sigma: f32,
    /// Median of the positive samples inside the mask: the image's typical signal level.
    pub level: f32,
}

/// Estimates the noise of the row-major `width`-wide image `plane` inside `mask`.
pub fn image_noise(plane: &[f32], width: usize, mask: &Mask) -> NoiseLevel {
    noise_at(plane, width, &interior_sample(mask))
}

/// A regular subsample of at most [`MAX_RESPONSES`] pixels of `mask` whose whole 3×3
/// neighbourhood is in the mask.
fn interior_sample(mask: &Mask) -> Vec<usize> {
    let (width, height) = (mask.width(), mask.height());
    let m = mask.data();
    let interior: Vec<usize> = (1..height.saturating_sub(1))
        .flat_map(|y| (1..width.saturating_sub(1)).map(move |x| y * width + x))
        .filter(|&i| {
            [i - width - 1, i - width, i - width + 1, i - 1, i, i + 1]
                .iter()
                .chain(&[i + width - 1, i + width, i + width + 1])
                .all(|&j| m[j])
        })
        .collect();
    let stride = interior.len().div_ceil(MAX_RESPONSES).max(1);
    interior.into_iter().step_by(stride).collect()
}

/// The estimate of [`image_noise`] from the responses at the `interior` pixels.
fn noise_at(plane: &[f32], width: usize, interior: &[usize]) -> NoiseLevel {
    let mut responses: Vec<f64> = Vec::with_capacity(interior.len());
    let mut levels: Vec<f32> = Vec::with_capacity(interior.len());
    for &i in interior {
        let at = |j: usize| f64::from(plane[j]);
        let r = at(i - width - 1) - 2.0 * at(i - width) + at(i - width + 1) - 2.0 * at(i - 1)
            + 4.0 * at(i)
            - 2.0 * at(i + 1)
            + at(i + width - 1)
            - 2.0 * at(i + width)
            + at(i + width + 1);
        if r.is_finite() {
            responses.push(r.abs());
        }
        if plane[i] > 0.0 && plane[i].is_finite() {
            levels.push(plane[i]);
        }
    }
    let level = median_by(&mut levels, f32::total_cmp).unwrap_or(f32::NAN);
    if responses.len() < MIN_RESPONSES {
        return NoiseLevel {
            sigma: f32::NAN,
            level,
        };
    }
    let median = median_by(&mut responses, f64::total_cmp).unwrap_or(f64::NAN);
    NoiseLevel {
        sigma: (MAD_TO_SIGMA * median / OPERATOR_NORM) as f32,
        level,
    }
}

/// [`image_noise`] for every image of channel `channel` of `stack`, in parallel. Pixels of
/// the mask outside the stack's window are left out.
pub fn stack_noise(stack: &ImageStack, channel: usize, mask: &Mask) -> Vec<NoiseLevel> {
    // A pixel's whole neighbourhood is in the mask, so inside the window when the pixel's
    // neighbours are; the sample is mapped into the window's planes.
    let window = stack.window();
    let interior: Vec<usize> = interior_sample(mask)
        .into_iter()
        .filter(|&i| {
            let (x, y) = (i % stack.width(), i / stack.width());
            x > window.x0 && x + 1 < window.x1 && y > window.y0 && y + 1 < window.y1
        })
        .filter_map(|i| stack.local(i))
        .collect();
    (0..stack.count())
        .into_par_iter()
        .map(|k| noise_at(stack.plane(k, channel), window.width(), &interior))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// Smooth shading plus white noise of known σ: the estimate is within 5%, and a noise-free
    /// quadratic image gives (nearly) zero.
    #[test]
    fn recovers_known_sigma() {
        let (w, h) = (200, 150);
        let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(11);
        let mask = Grid::from_fn(w, h, |x, y| {
            let (dx, dy) = (x as f64 - 100.0, y as f64 - 75.0);
            dx * dx + dy * dy < 70.0 * 70.0
        });
        let smooth: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 / w as f32, (i / w) as f32 / h as f32);
                0.3 + 0.4 * x - 0.2 * y * y + 0.1 * x * y
            })
            .collect();
        assert!(image_noise(&smooth, w, &mask).sigma < 1e-6);
        for sigma in [0.001, 0.01, 0.05] {
            let normal = Normal::new(0.0, sigma).unwrap();
            let noisy: Vec<f32> = smooth
                .iter()
                .map(|v| v + normal.sample(&mut rng) as f32)
                .collect();
            let est = image_noise(&noisy, w, &mask);
            let rel = (f64::from(est.sigma) - sigma).abs() / sigma;
            assert!(rel < 0.05, "σ {sigma}: estimated {}", est.sigma);
            assert!((est.level - 0.45).abs() < 0.1);
        }
        // A mask without interior pixels gives no estimate.
        let thin = Grid::from_fn(w, h, |x, _| x == 10);
        assert!(image_noise(&smooth, w, &thin).sigma.is_nan());
    }
}
