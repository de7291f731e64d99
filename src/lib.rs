//! # photostereo
//!
//! Photometric stereo, normal integration and synthetic scenes: from photographs of a still
//! object under known distant lights to albedo, normals and depth.
//!
//! The pipeline, one module per stage:
//! [`input`] (images → [`input::ImageStack`]) → [`lights`] ([`lights::Lights`]) →
//! [`solve`] (per-pixel g = ρN; [`color`] for one normal from RGB) → [`normals`] (albedo, normals, gradients, integrability) →
//! [`integrate`] (depth) → [`output`] (EXR/PNG, atomically). [`pipeline`] composes them;
//! [`dataset`] assembles inputs from files; [`calibrate`] measures the lights from a chrome
//! sphere (directions) and a matte reference (intensities). Beside it: [`reflectance`] holds the BRDF models,
//! [`scene`] and [`render`] make synthetic data with ground truth, [`reflectance_map`] gives
//! brightness as a function of the surface gradient and [`sfs`] inverts it for one image (shape
//! from shading), [`metrics`] measures errors, [`sweep`] measures error and time over noise,
//! lights and specularity, [`stream`] solves stacks larger than memory in row bands,
//! [`demo`] is the built-in default scene.
//!
//! Conventions: camera frame x right, y up, z towards the camera; image row 0 is the top; light
//! directions point from the surface to the light; normals point out of the surface.
//!
//! ```
//! use photostereo::{demo, pipeline, progress::Silent};
//! // Render the built-in scene without noise, reconstruct it, and check the normals.
//! let synth = demo::default_capture(0.0, 1)?;
//! let recon = pipeline::reconstruct(&synth.capture, &pipeline::Config::default(), &Silent)?;
//! let eval = demo::evaluate(&recon, &synth.truth)?;
//! assert!(eval.normals.mean_deg < 0.1);
//! # Ok::<(), photostereo::Error>(())
//! ```
#![deny(missing_docs)]

mod band_output;
mod bands;
mod buffer;
pub mod calibrate;
pub mod camera;
pub mod color;
pub mod dataset;
pub mod demo;
mod encode;
pub mod error;
pub mod grid;
pub mod input;
pub mod integrate;
pub mod intensities;
pub mod lights;
mod linalg;
pub mod mesh;
pub mod metrics;
pub mod noise;
pub mod normals;
pub mod output;
pub mod pipeline;
pub mod progress;
pub mod reflectance;
pub mod reflectance_map;
pub mod render;
pub mod robust;
pub mod scene;
pub mod sfs;
pub mod solve;
pub mod stream;
pub mod sweep;

pub use error::{Error, Result};
/// The linear-algebra crate of the public API (normals are `nalgebra::Vector3<f32>`).
pub use nalgebra;
