//! Synthetic inputs shared by the unit tests of several modules: a sphere's exact normals and
//! the noise-free Lambertian images of it under a light set, built in closed form (not with
//! the renderer, so that a test of a solver does not also test the renderer).

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::grid::{Grid, Mask};
use nalgebra::Vector3;

/// A sphere of radius 0.45·`size` centred in a `size`×`size` image, seen from above (x right,
/// y up): its unit normals, and the mask of the pixels whose normal is within `max_tilt_deg`
/// of the view (outside it the normal is NaN).
pub(crate) fn sphere(size: usize, max_tilt_deg: f64) -> (Grid<Vector3<f64>>, Mask) {
    let radius = 0.45 * size as f64;
    let centre = (size as f64 - 1.0) / 2.0;
    let min_z = max_tilt_deg.to_radians().cos();
    let normals = Grid::from_fn(size, size, |c, r| {
        let (x, y) = ((c as f64 - centre) / radius, (centre - r as f64) / radius);
        let z2 = 1.0 - x * x - y * y;
        if z2 >= min_z * min_z {
            Vector3::new(x, y, z2.sqrt())
        } else {
            Vector3::repeat(f64::NAN)
        }
    });
    let mask = normals.map(|n| n.z.is_finite());
    (normals, mask)
}

/// The noise-free Lambertian images I_{k,c}(p) = scale_k·ρ_c·max(0, N_p·l_k) of `normals`
/// under `lights`, one channel per entry of `albedo` (1 or 3), 0 outside `mask`: a stack whose
/// image k reads `scale[k]` times brighter than its stated intensity.
pub(crate) fn lambertian_stack(
    normals: &Grid<Vector3<f64>>,
    mask: &Mask,
    lights: &Lights,
    albedo: &[f64],
    scale: &[f64],
) -> ImageStack {
    assert_eq!(scale.len(), lights.len(), "one scale per light");
    let images = lights
        .directions()
        .iter()
        .zip(scale)
        .map(|(l, s)| {
            albedo
                .iter()
                .flat_map(|rho| {
                    normals
                        .data()
                        .iter()
                        .zip(mask.data())
                        .map(move |(n, &inside)| {
                            if inside {
                                (s * rho * n.dot(l).max(0.0)) as f32
                            } else {
                                0.0
                            }
                        })
                })
                .collect()
        })
        .collect();
    ImageStack::from_images(normals.width(), normals.height(), albedo.len(), images)
        .expect("one plane of width × height per albedo")
}

/// A `width`×`height` solution of `count` images with every pixel outside the mask but those
/// of `pixels` (x, y and the outcome recorded there, as the solver records it), unit gains and
/// no noise model: hand-made per-channel solutions for the tests of what is built from them.
pub(crate) fn hand_made_solution(
    width: usize,
    height: usize,
    count: usize,
    pixels: &[(usize, usize, crate::ps::solve::PixelSolution)],
) -> crate::ps::solve::Solution {
    use crate::ps::solve::{Solution, SolveOptions};
    let mut s = Solution::empty(
        width,
        height,
        crate::ps::intensities::GainEstimate::unit(count),
        Vec::new(),
        &SolveOptions::default(),
    );
    for (x, y, px) in pixels {
        s.record(y * width + x, px);
    }
    s
}

/// Asserts that two f32 sequences hold the same bit patterns (any NaN matches any NaN), naming
/// `what` and the first index that differs.
pub(crate) fn assert_same_bits(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len())
        .find(|&i| a[i].to_bits() != b[i].to_bits() && !(a[i].is_nan() && b[i].is_nan()))
    {
        panic!("{what}: value {i} differs: {} vs {}", a[i], b[i]);
    }
}

/// Asserts that two per-channel solutions hold the same maps bit for bit (g, residual,
/// condition; samples, status and robust flags exactly) and the same gains and noise.
pub(crate) fn assert_same_solutions(
    a: &[crate::ps::solve::Solution],
    b: &[crate::ps::solve::Solution],
    what: &str,
) {
    assert_eq!(a.len(), b.len(), "{what}: channels");
    for (c, (a, b)) in a.iter().zip(b).enumerate() {
        let g = |s: &crate::ps::solve::Solution| -> Vec<f32> {
            s.g.data().iter().flat_map(|v| [v.x, v.y, v.z]).collect()
        };
        assert_same_bits(&g(a), &g(b), &format!("{what}, channel {c}: g"));
        assert_same_bits(
            a.residual.data(),
            b.residual.data(),
            &format!("{what}, channel {c}: residual"),
        );
        assert_same_bits(
            a.condition.data(),
            b.condition.data(),
            &format!("{what}, channel {c}: condition"),
        );
        assert_eq!(a.samples, b.samples, "{what}, channel {c}: samples");
        assert_eq!(a.status, b.status, "{what}, channel {c}: status");
        assert_eq!(a.robust, b.robust, "{what}, channel {c}: robust");
        assert_same_bits(&a.gains.gains, &b.gains.gains, &format!("{what}: gains"));
        assert_same_bits(&a.noise, &b.noise, &format!("{what}: noise"));
    }
}

/// Runs `f` in a pool of `threads` threads of its own (results that must not depend on the
/// thread count are compared across pools).
pub(crate) fn with_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool")
        .install(f)
}
