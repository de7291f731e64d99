//! Synthetic data with ground truth: reflectance models ([`reflectance`]), scenes of height
//! fields and primitives ([`scene`]) and a renderer with cast shadows and noise ([`render`]).
//! Cast shadows march rays over the height field ([`raymarch`]). The tests run on scenes
//! rendered here; `data-synth` writes them as data sets.

pub mod light_sets;
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
