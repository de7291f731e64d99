//! Files in and out: decoding and encoding EXR, PNG and TIFF (whole images and row bands), the
//! atomic output folder, previews, and the PLY mesh.
//!
//! - [`output`]: [`output::OutputDir`] stages every output as an unnamed temporary and moves
//!   them into place together, so a run leaves all its files or none; PNG previews.
//! - `encode` (private): the EXR and PNG encoders, for whole images and for rows written as a
//!   streamed run solves them (one encoder, so both give identical files).
//! - `bands` (private): readers that decode a PNG, TIFF or EXR a band of rows at a time.
//! - [`mesh`]: depth map → triangle mesh → PLY.

pub(crate) mod bands;
pub mod decode;
pub(crate) mod encode;
pub mod mesh;
pub mod output;

pub use output::OutputDir;
