//! A whole run, from a capture to the files on disk: configuration, the stages in order,
//! the per-pixel maps, the outputs and the report.
//!
//! - [`pipeline`]: [`pipeline::Config`], [`pipeline::reconstruct`] (in memory) and
//!   [`pipeline::reconstruct_and_write`]; the finishing stage (integrability, integration,
//!   depth outputs, report) shared with streamed runs.
//! - [`stream`]: the same run on stacks larger than memory, read and solved in row bands
//!   within a memory budget; `band_output` (private) writes the per-pixel files band by band.
//! - `bands` (private): the band loop both kinds of run go through — a source of bands (the
//!   whole stack, or bands decoded from the files), the solve under one image model, a sink.
//! - [`warnings`]: what the user should know about a finished run, as data.
//! - [`checks`]: the capture-wide checks of a solve (shadow light, each light against the
//!   others) in a form that adds up over the parts of a capture solved elsewhere.
//! - [`html`]: `report.html`, the run's outputs and figures on one self-contained page.

pub(crate) mod band_output;
pub(crate) mod bands;
pub mod checks;
pub mod html;
pub mod pipeline;
pub mod stream;
pub mod warnings;

pub use checks::{CaptureChecks, PartCounts};
pub use pipeline::{Config, Reconstruction, Report, reconstruct, reconstruct_and_write};
pub use stream::{StreamOptions, StreamPlan};
pub use warnings::{SampleCounts, Warning};
