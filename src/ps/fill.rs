//! A normal for every pixel of the mask: pixels too poorly determined to be solved alone
//! (fewer than three usable samples, ill-conditioned lights, or a zero estimate) are filled
//! in from the samples they do have and from their solved neighbours.
//!
//! **Model.** For the unsolved pixels U, g is the maximum a posteriori estimate under
//! Gaussian sample noise σ and a Gaussian smoothness prior on g across 4-neighbours with
//! variance τ² per component:
//!
//! E(g) = Σ_{i∈U} Σ_k (I_ik − l_k·g_i)²/σ² + Σ_{i∈U, j∈N(i)} |g_i − g_j|²/τ²,
//!
//! the sum over k running over pixel i's usable samples (the threshold set of the estimator,
//! [`crate::ps::robust`]), N(i) its neighbours inside the mask (solved ones fixed). Each pixel
//! then satisfies (A_i/σ² + n_i/τ²·𝟙) g_i = b_i/σ² + Σ_{j∈N(i)} g_j/τ², with A_i = Σ l lᵀ and
//! b_i = Σ l I over its samples, n_i = |N(i)|: with no samples it is the mean of its
//! neighbours (harmonic inpainting); with one or two, or with coplanar lights, the samples fix
//! g along the directions they span and the neighbours the rest. This is the smoothness
//! prior of variational photometric stereo (e.g. Quéau, Durou & Aujol, "Variational methods
//! for normal integration", 2018; Ikehata et al., "Robust photometric stereo using sparse
//! regression", CVPR 2012, for the sparse-outlier view of the samples) restricted to the pixels
//! that need it: solved pixels keep their own estimate.
//!
//! **Parameters, from the data.** σ² is the median squared RMS residual of the solved pixels
//! (how well a sample predicts g, noise and model error together); τ² is the median over pairs
//! of solved 4-neighbours of |g_i − g_j|²/3 (how much g varies from pixel to pixel on this
//! object). Both are floored at (10⁻⁶·median |g|)² so that exact synthetic data stays defined.
//!
//! **Solver.** The unknowns are initialised layer by layer from the solved border inwards
//! (each the mean of its already-set neighbours), then refined by Gauss–Seidel sweeps of the
//! 3×3 equations above until no g moves by more than 10⁻⁶ of the median |g| or
//! [`MAX_SWEEPS`] sweeps. A group of unsolved pixels with no solved pixel next to any of them is
//! left unsolved: nothing determines its normal.
//!
//! **Where it breaks.** A filled normal is an interpolation: right for a smooth surface under a
//! small highlight or shadow, wrong across a crease or a depth edge inside the hole, and
//! unreliable in a large hole. Filled pixels are flagged (status [`PixelStatus::Filled`], the
//! `filled` channel of `residual.exr`), counted in the report and warned about;
//! [`crate::ps::solve::SolveOptions::fill`] = false leaves them unsolved (NaN).

use crate::grid::four_neighbours;
use crate::ps::solve::{PixelStatus, Solution};
use crate::stats::median_by;
use nalgebra::{Matrix3, Vector3};
use std::collections::VecDeque;

/// Most Gauss–Seidel sweeps over the unsolved pixels.
pub const MAX_SWEEPS: usize = 500;
/// Sweeps stop once no g moves by more than this fraction of the median |g|.
const TOLERANCE: f64 = 1e-6;

/// The samples an unsolved pixel has: its normal equations (Σ l lᵀ as xx, xy, xz, yy, yz, zz,
/// and Σ l·I) over its usable samples, and their count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct PixelData {
    /// Row-major index of the pixel in the solution.
    pub pixel: usize,
    /// Σ l·lᵀ.
    pub a: [f64; 6],
    /// Σ l·I.
    pub b: [f64; 3],
    /// Number of samples.
    pub samples: usize,
}

/// What a fill did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FillSummary {
    /// Pixels filled.
    pub filled: usize,
    /// Unsolved pixels left so (no solved pixel next to their group).
    pub left: usize,
    /// Gauss–Seidel sweeps run.
    pub sweeps: usize,
    /// The noise σ of the data term.
    pub sigma: f64,
    /// The prior's per-component standard deviation τ of g between neighbours.
    pub tau: f64,
}

/// Fills the unsolved mask pixels of `sol` (statuses too-few-samples, ill-conditioned and
/// dark) from their samples `data` (pixels absent from it have none) and their solved
/// neighbours, and marks them [`PixelStatus::Filled`].
pub(crate) fn fill(sol: &mut Solution, data: &[PixelData]) -> FillSummary {
    let (w, h) = (sol.g.width(), sol.g.height());
    let status = sol.status.data();
    let unknown: Vec<usize> = (0..w * h)
        .filter(|&p| status[p] != PixelStatus::Outside && !status[p].has_normal())
        .collect();
    let mut summary = FillSummary {
        left: unknown.len(),
        ..FillSummary::default()
    };
    if unknown.is_empty() {
        return summary;
    }
    let g64 = |p: usize| sol.g.data()[p].map(f64::from);
    let solved = |p: usize| status[p] == PixelStatus::Solved;
    // Parameters from the solved pixels.
    let mut norms: Vec<f64> = (0..w * h)
        .filter(|&p| solved(p))
        .map(|p| g64(p).norm())
        .collect();
    let Some(scale) = median_by(&mut norms, f64::total_cmp) else {
        return summary;
    };
    let floor = (1e-6 * scale).powi(2).max(f64::MIN_POSITIVE);
    let mut res2: Vec<f64> = (0..w * h)
        .filter(|&p| solved(p))
        .map(|p| f64::from(sol.residual.data()[p]).powi(2))
        .filter(|r| r.is_finite())
        .collect();
    let var_data = median_by(&mut res2, f64::total_cmp)
        .unwrap_or(0.0)
        .max(floor);
    let mut diffs = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if !solved(p) {
                continue;
            }
            for q in [(x + 1 < w).then_some(p + 1), (y + 1 < h).then_some(p + w)]
                .into_iter()
                .flatten()
            {
                if solved(q) {
                    diffs.push((g64(p) - g64(q)).norm_squared() / 3.0);
                }
            }
        }
    }
    let var_prior = median_by(&mut diffs, f64::total_cmp)
        .unwrap_or(0.0)
        .max(floor);
    summary.sigma = var_data.sqrt();
    summary.tau = var_prior.sqrt();

    // The unknowns, their data and their neighbours in the mask.
    let mut index = vec![usize::MAX; w * h];
    for (i, &p) in unknown.iter().enumerate() {
        index[p] = i;
    }
    let n = unknown.len();
    let mut a = vec![Matrix3::zeros(); n];
    let mut b = vec![Vector3::zeros(); n];
    let mut samples = vec![0usize; n];
    for d in data {
        let i = index.get(d.pixel).copied().unwrap_or(usize::MAX);
        if i == usize::MAX {
            continue;
        }
        let [xx, xy, xz, yy, yz, zz] = d.a;
        a[i] = Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz) / var_data;
        b[i] = Vector3::from(d.b) / var_data;
        samples[i] = d.samples;
    }
    let neighbours = |p: usize| {
        four_neighbours(p, w, h)
            .into_iter()
            .flatten()
            .filter(|&q| status[q] != PixelStatus::Outside)
    };

    // Σ g_j over the neighbours of p that have a value (solved, or set unknowns), and their count.
    let neighbour_sum = |p: usize, value: &[Option<Vector3<f64>>]| {
        let (mut sum, mut count) = (Vector3::zeros(), 0.0);
        for q in neighbours(p) {
            let v = if solved(q) {
                Some(g64(q))
            } else {
                value[index[q]]
            };
            if let Some(v) = v {
                sum += v;
                count += 1.0;
            }
        }
        (sum, count)
    };

    // Layer-by-layer initialisation from the solved border inwards; the visiting order is
    // also the sweep order.
    let mut value: Vec<Option<Vector3<f64>>> = vec![None; n];
    let mut order = Vec::with_capacity(n);
    let mut queued = vec![false; n];
    let mut queue = VecDeque::new();
    for (i, &p) in unknown.iter().enumerate() {
        if neighbours(p).any(solved) {
            queued[i] = true;
            queue.push_back(i);
        }
    }
    while let Some(i) = queue.pop_front() {
        let p = unknown[i];
        let (sum, count) = neighbour_sum(p, &value);
        value[i] = Some(sum / count);
        order.push(i);
        for q in neighbours(p) {
            let j = index[q];
            if j != usize::MAX && !queued[j] {
                queued[j] = true;
                queue.push_back(j);
            }
        }
    }

    // Gauss–Seidel sweeps.
    let inv_prior = 1.0 / var_prior;
    let tolerance = TOLERANCE * scale;
    for sweep in 1..=MAX_SWEEPS {
        let mut largest: f64 = 0.0;
        for &i in &order {
            let p = unknown[i];
            let (sum, count) = neighbour_sum(p, &value);
            let rhs = b[i] + sum * inv_prior;
            let m = a[i] + Matrix3::identity() * (count * inv_prior);
            if let Some(g) = m.cholesky().map(|c| c.solve(&rhs))
                && let Some(old) = value[i]
            {
                largest = largest.max((g - old).norm());
                value[i] = Some(g);
            }
        }
        summary.sweeps = sweep;
        if largest <= tolerance {
            break;
        }
    }

    // Record.
    for (i, &p) in unknown.iter().enumerate() {
        let Some(g) = value[i] else { continue };
        if !g.iter().all(|v| v.is_finite()) {
            continue;
        }
        sol.g.data_mut()[p] = g.map(|v| v as f32);
        sol.status.data_mut()[p] = PixelStatus::Filled;
        sol.samples.data_mut()[p] = samples[i].min(u16::MAX as usize) as u16;
        sol.residual.data_mut()[p] = f32::NAN;
        summary.filled += 1;
    }
    summary.left = n - summary.filled;
    summary
}

#[cfg(test)]
mod tests {
    use crate::capture::lights::Lights;
    use crate::capture::stack::ImageStack;
    use crate::grid::Grid;
    use crate::progress::Silent;
    use crate::ps::solve::{PixelStatus, SolveOptions, solve};
    use crate::synth::test_support::sphere;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// A noisy Lambertian sphere under 12 lights with two holes: a 6×6 patch seen in only
    /// two images (too few samples) and a 6×6 patch seen in none. Strict mode leaves the 72
    /// pixels unsolved; the default fills them about as well as the noise lets the solved
    /// pixels be solved (a smooth surface), and leaves every other pixel as it was.
    #[test]
    fn holes_in_a_smooth_surface_are_filled_close_to_the_truth() {
        let size = 64;
        let (normals, mask) = sphere(size, 70.0);
        let lights = Lights::ring(12, 40.0, 0.0).unwrap();
        let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, 0.005).unwrap();
        let few = |x: usize, y: usize| (24..30).contains(&x) && (20..26).contains(&y);
        let none = |x: usize, y: usize| (36..42).contains(&x) && (36..42).contains(&y);
        let images = lights
            .directions()
            .iter()
            .enumerate()
            .map(|(k, l)| {
                Grid::from_fn(size, size, |x, y| {
                    let n = normals.at(x, y);
                    if !*mask.at(x, y) || none(x, y) || (few(x, y) && k > 1) {
                        f32::NAN
                    } else {
                        (0.6 * n.dot(l).max(0.0)) as f32 + noise.sample(&mut rng)
                    }
                })
                .into_data()
            })
            .collect();
        let stack = ImageStack::from_images(size, size, 1, images).unwrap();
        let strict = SolveOptions {
            fill: false,
            ..SolveOptions::default()
        };
        let held = solve(&stack, 0, &lights, &mask, &strict, &Silent).unwrap();
        let filled = solve(&stack, 0, &lights, &mask, &SolveOptions::default(), &Silent).unwrap();
        let hole = |x: usize, y: usize| few(x, y) || none(x, y);
        let (mut worst, mut sum, mut count) = (0.0f64, 0.0, 0);
        let (mut solved_sum, mut solved_count) = (0.0, 0);
        let error = |sol: &crate::ps::solve::Solution, x: usize, y: usize| {
            let g = sol.g.at(x, y).map(f64::from);
            let e = g.normalize().dot(normals.at(x, y)).clamp(-1.0, 1.0).acos();
            e.to_degrees()
        };
        for y in 0..size {
            for x in 0..size {
                if !*mask.at(x, y) {
                    continue;
                }
                let (s, f) = (*held.status.at(x, y), *filled.status.at(x, y));
                if hole(x, y) {
                    assert!(!s.has_normal(), "({x}, {y}) solved in strict mode: {s:?}");
                    assert_eq!(f, PixelStatus::Filled, "({x}, {y})");
                    let e = error(&filled, x, y);
                    worst = worst.max(e);
                    sum += e;
                    count += 1;
                } else {
                    assert_eq!(s, f, "({x}, {y})");
                    solved_sum += error(&filled, x, y);
                    solved_count += 1;
                    assert_eq!(held.g.at(x, y), filled.g.at(x, y), "({x}, {y})");
                }
            }
        }
        let (mean, solved_mean) = (sum / count as f64, solved_sum / solved_count as f64);
        println!(
            "filled {count} pixels: mean {mean:.3}°, worst {worst:.3}°; solved pixels mean {solved_mean:.3}°"
        );
        assert_eq!(count, 72);
        // Measured: filled 0.34° mean, 1.12° worst; solved pixels 0.43° mean.
        assert!(mean < 1.5 * solved_mean, "{mean}° vs {solved_mean}°");
        assert!(worst < 2.0, "worst filled error {worst}°");
    }

    /// A group of unsolved pixels with no solved neighbour stays unsolved: nothing determines
    /// its normal.
    #[test]
    fn an_isolated_hole_stays_unsolved() {
        let lights = Lights::ring(8, 45.0, 0.0).unwrap();
        let images = lights
            .directions()
            .iter()
            .map(|_| vec![f32::NAN; 9])
            .collect();
        let stack = ImageStack::from_images(3, 3, 1, images).unwrap();
        let mask = Grid::new(3, 3, true);
        let sol = solve(&stack, 0, &lights, &mask, &SolveOptions::default(), &Silent).unwrap();
        assert!(sol.status.data().iter().all(|s| !s.has_normal()));
        assert!(sol.g.data().iter().all(|g| g.x.is_nan()));
    }
}
