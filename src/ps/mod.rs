//! Photometric stereo proper: per-pixel fits of g = ρN to the samples of a
//! [`crate::capture::ImageStack`] under known [`crate::capture::Lights`].
//!
//! - [`solve`]: options, the per-pixel fit, the block kernel, the capture-wide image model
//!   ([`solve::ImageModel`]: noise and intensity gains, kept apart from the pixel fit) and the
//!   per-pixel solution maps.
//! - [`robust`]: the robust estimators (trimmed, Huber, Tukey, L1, specular cone).
//! - [`fill`]: a normal for the pixels too poorly determined to be solved alone, from their
//!   few samples and their solved neighbours.
//! - [`noise`]: per-image noise σ from the data; [`intensities`]: per-image intensity gains.
//! - [`color`]: one normal from three colour channels.
//! - [`normals`]: albedo and unit normals from g, gradients and the integrability check.
//! - [`interreflection`]: the light a concave surface throws onto itself, predicted from the
//!   reconstructed shape and subtracted (opt-in, a pipeline stage).
//! - [`lobes`]: a non-Lambertian refit (a diffuse term plus specular lobes) of the pixels
//!   Lambert's law does not explain, kept where it explains them ([`solve::SolveOptions::lobes`]).
//! - [`ambient`]: the light in attached shadows (ambient light, a black level,
//!   interreflections), measured after the solve, and how far it bends the normals.
//! - [`light_agreement`]: each light checked against the others — the direction the other
//!   images' normals give each image's brightness, and the lights that disagree beyond chance.
//! - [`shadows`]: spatially coherent shadow/inlier labels per image (graph cuts) and the refit
//!   from them (opt-in: [`solve::SolveOptions::shadow_labels`]).

pub mod ambient;
pub mod color;
pub mod fill;
pub mod intensities;
pub mod interreflection;
pub mod light_agreement;
pub mod lobes;
pub mod near;
pub mod noise;
pub mod normals;
pub mod robust;
pub mod shadows;
pub mod solve;

pub use color::ColorSolve;
pub use solve::{ImageModel, Method, PixelStatus, Solution, SolveOptions};

/// Scenes rendered and solved, for the tests of the passes that run after a solve.
#[cfg(test)]
pub(crate) mod test_support {
    use crate::capture::lights::Lights;
    use crate::capture::stack::{ColorMode, ImageStack};
    use crate::progress::Silent;
    use crate::ps::solve::{Solution, SolveOptions, solve};
    use crate::synth::render::{RenderOptions, Rendering, render};
    use crate::synth::scene::Scene;

    /// `scene` rendered under `rendered` with `options`, as a grey stack, solved with the
    /// default options under `given` (the rendered lights, or a set with a wrong row) over the
    /// rendered mask.
    pub(crate) fn rendered_and_solved(
        scene: &Scene,
        rendered: &Lights,
        given: &Lights,
        options: &RenderOptions,
    ) -> (Rendering, ImageStack, Solution) {
        let r = render(scene, rendered, options).unwrap();
        let stack = r.to_stack(given, ColorMode::Grey).unwrap();
        let sol = solve(
            &stack,
            0,
            given,
            &r.truth.mask,
            &SolveOptions::default(),
            &Silent,
        )
        .unwrap();
        (r, stack, sol)
    }

    /// The band tests' scene: a 64² Lambertian sphere (albedo 0.7) under `lights`, noise
    /// 0.005 and `ambient` room light, solved under those lights: its mask, stack and solution.
    pub(crate) fn sphere_for_bands(
        lights: &Lights,
        ambient: f32,
    ) -> (crate::grid::Mask, ImageStack, Solution) {
        use crate::synth::reflectance::Material;
        use crate::synth::scene::{Albedo, SceneKind};
        let scene = SceneKind::Sphere.build(64, Albedo::Constant(0.7), Material::lambertian());
        let options = RenderOptions {
            noise_sigma: 0.005,
            ambient,
            ..RenderOptions::default()
        };
        let (r, stack, sol) = rendered_and_solved(&scene, lights, lights, &options);
        (r.truth.mask, stack, sol)
    }

    /// The pixels of `mask` in rows `y0..y1`: a band of a streamed run, on the whole grid.
    pub(crate) fn band(mask: &crate::grid::Mask, y0: usize, y1: usize) -> crate::grid::Mask {
        crate::grid::Grid::from_fn(mask.width(), mask.height(), |x, y| {
            *mask.at(x, y) && (y0..y1).contains(&y)
        })
    }
}
