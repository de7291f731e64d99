//! Synthetic data with ground truth: reflectance models ([`reflectance`]), scenes of height
//! fields and primitives ([`scene`]) and a renderer ([`render`]) with cast shadows, area lights
//! and soft shadows ([`area_light`]), diffuse interreflections ([`interreflection`]) and noise;
//! all three march rays over the scene's height field ([`raymarch`]). The tests run on scenes
//! rendered here; `data-synth` writes them as data sets.

pub mod area_light;
pub mod chrome;
pub mod interreflection;
pub mod light_sets;
pub mod near;
pub mod raymarch;
pub mod reflectance;
pub mod render;
pub mod scene;
#[cfg(test)]
pub(crate) mod test_support;
pub mod write;

pub use reflectance::Material;
pub use render::Rendering;
pub use scene::Scene;

/// A number uniform in [0, 1) hashed from three integers (the SplitMix64 finaliser, Steele, Lea
/// & Flood 2014): per-pixel sample rotations that are deterministic and independent of the
/// order in which threads render the pixels.
pub(crate) fn hash_unit(seed: u64, a: u64, b: u64) -> f64 {
    fn mix(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    (mix(mix(mix(seed) ^ a) ^ b) >> 11) as f64 / (1u64 << 53) as f64
}
