//! Files in and out: decoding and encoding EXR, PNG and TIFF (whole images and row bands), the
//! atomic output folder, previews, and the PLY mesh.
//!
//! - [`output`]: [`output::OutputDir`] writes a run's files into a private staging folder and
//!   puts it in place as a whole, so the output folder holds the old set or the new one, never
//!   a mix; [`output::OutputLock`] keeps a second run out; PNG previews.
//! - One file per format, each reading and writing it whole and by rows: `exr.rs`, `png.rs`,
//!   `tiff.rs` (private; one encoder for whole images and for rows written as a streamed run
//!   solves them, so both give identical files).
//! - [`decode`]: the sample types, the decoder of any supported file by its extension, masks,
//!   normal maps and the sRGB transfer function.
//! - `bands` (private): the row-band reader over the three formats; `encode` (private): the
//!   writer threads that feed the band encoders.
//! - [`raw`]: camera RAW (with the `raw` feature), developed linearly, every choice recorded.
//! - [`input`]: opening inputs: regular files only, text capped, declared image sizes checked
//!   against the limits and the file's length before anything is allocated.
//! - [`mesh`]: depth map → triangle mesh → PLY.

pub(crate) mod bands;
pub mod decode;
pub(crate) mod encode;
pub(crate) mod exr;
pub mod input;
pub mod mesh;
pub mod output;
pub(crate) mod png;
pub mod raw;
pub(crate) mod tiff;

pub use output::OutputDir;
