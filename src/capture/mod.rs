//! Capture: what was photographed, as the solver sees it — the images converted to linear
//! radiance ([`stack`]), the lights ([`lights`]) and the mask, assembled from files or folders
//! ([`dataset`]).
//!
//! Files are resolved first ([`dataset::CaptureFiles`]: paths, lights, mask, nothing decoded),
//! then loaded whole ([`dataset::Capture`]) or read in row bands by [`crate::run::stream`].
//! Decoding of each file format lives in [`crate::io`]; this folder converts samples
//! (transfer curve, saturation, light intensity, colour mix) and keeps the stack; [`order`]
//! catches numbered images sorted as text before they are paired with a plain list of lights.
//! [`arrays`] builds the same stacks, lights and masks from [`ndarray`] arrays, and hands maps
//! back as arrays.

pub mod arrays;
pub mod dataset;
pub mod lights;
pub mod order;
pub mod stack;

pub use dataset::{Capture, CaptureFiles};
pub use lights::{Light, Lights};
pub use order::ImageOrder;
pub use stack::{ColorMode, ImageStack, LoadOptions};
