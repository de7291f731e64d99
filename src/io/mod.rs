//! Files in and out: decoding and encoding EXR, PNG and TIFF (whole images and row bands), the
//! atomic output folder, previews, and the PLY mesh.
//!
//! - [`output`]: [`output::OutputDir`] stages every output as an unnamed temporary and moves
//!   them into place together, so a run leaves all its files or none; PNG previews.
//! - One file per format, each reading and writing it whole and by rows: `exr.rs`, `png.rs`,
//!   `tiff.rs` (private; one encoder for whole images and for rows written as a streamed run
//!   solves them, so both give identical files).
//! - [`decode`]: the sample types, the decoder of any supported file by its extension, masks,
//!   normal maps and the sRGB transfer function.
//! - `bands` (private): the row-band reader over the three formats; `encode` (private): the
//!   writer threads that feed the band encoders.
//! - [`raw`]: camera RAW (with the `raw` feature), developed linearly, every choice recorded.
//! - [`mesh`]: depth map → triangle mesh → PLY.

pub(crate) mod bands;
pub mod decode;
pub(crate) mod encode;
pub(crate) mod exr;
pub mod mesh;
pub mod output;
pub(crate) mod png;
pub mod raw;
pub(crate) mod tiff;

pub use output::OutputDir;
