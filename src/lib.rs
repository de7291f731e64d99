//! # photostereo
//!
//! Photometric stereo, normal integration and synthetic scenes: from photographs of a still
//! object under known distant lights to albedo, normals and depth.
//!
//! The pipeline, one folder per stage (see `docs/ARCHITECTURE.md` for the data flow):
//! [`capture`] (files → images, lights and mask: [`capture::ImageStack`], [`capture::Lights`])
//! → [`ps`] (per-pixel g = ρN, robust estimators, the image model, colour; albedo, normals and
//! the integrability check) → [`integrate`] (normals → depth, one file per method) → [`io`]
//! (EXR/PNG/TIFF in and out, written atomically). [`run`] composes the stages, in memory or
//! streamed in row bands. Beside the pipeline: [`calibrate`] measures the lights from a chrome
//! sphere and a matte reference; [`sfs`] is shape from shading through reflectance maps;
//! [`synth`] renders scenes with ground truth (reflectance models, renderer); [`eval`] measures
//! errors, runs the demo and the speed–accuracy sweeps. The foundations every stage uses sit at
//! the root: [`grid`] (images, masks, maps), [`camera`], [`error`], [`progress`].
//!
//! Conventions: camera frame x right, y up, z towards the camera; image row 0 is the top; light
//! directions point from the surface to the light; normals point out of the surface.
//!
//! ```
//! use photostereo::{eval::demo, run::pipeline, progress::Silent};
//! // Render the built-in scene without noise, reconstruct it, and check the normals.
//! let synth = demo::default_capture(0.0, 1)?;
//! let recon = pipeline::reconstruct(&synth.capture, &pipeline::Config::default(), &Silent)?;
//! let eval = demo::evaluate(&recon, &synth.truth)?;
//! assert!(eval.normals.mean_deg < 0.1);
//! # Ok::<(), photostereo::Error>(())
//! ```
#![deny(missing_docs)]

mod buffer;
pub mod calibrate;
pub mod camera;
pub mod capture;
pub mod error;
pub mod eval;
#[cfg(feature = "fuzzing")]
#[doc(hidden)]
pub mod fuzzing;
pub mod grid;
pub mod integrate;
pub mod io;
mod linalg;
mod pool;
pub mod progress;
pub mod ps;
pub mod run;
pub mod sfs;
pub mod stats;
pub mod synth;

pub use error::{Error, Result};

// The domain types, re-exported: what most callers need without knowing the folders.
pub use camera::Intrinsics;
pub use capture::{Capture, CaptureFiles, ImageStack, Lights, LoadOptions};
pub use grid::{Grid, Mask, NormalMap, ScalarMap};
pub use integrate::{Integration, IntegrationOptions, Integrator, integrate_normals};
/// The linear-algebra crate of the public API (normals are `nalgebra::Vector3<f32>`).
pub use nalgebra;
/// The array crate of the array interop ([`capture::arrays`]): images in, maps out.
pub use ndarray;
pub use ps::{Method, SolveOptions};
pub use run::{Config, Reconstruction, Report, reconstruct, reconstruct_and_write};
