//! The crate's one error type: every failure names the file, image index or parameter at fault.

use std::path::PathBuf;

/// Result alias used across the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything that can go wrong in the library, with the data needed to act on it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Reading or writing a file failed at the operating-system level.
    #[error("{path}: {cause}")]
    Io {
        /// The file or folder involved.
        path: PathBuf,
        /// The underlying error (part of the message, so not repeated as a source).
        cause: std::io::Error,
    },
    /// An image file could not be decoded.
    #[error("{path}: cannot decode image: {reason}")]
    Decode {
        /// The image file.
        path: PathBuf,
        /// What the decoder reported.
        reason: String,
    },
    /// An image cannot be read in row bands (a run streamed within a memory budget), though it
    /// can be loaded whole.
    #[error("{path}: cannot be read in row bands: {reason}")]
    NotBandReadable {
        /// The image file.
        path: PathBuf,
        /// What prevents it.
        reason: String,
    },
    /// No sphere was found in calibration images given without a mask of the sphere (with
    /// one, the sphere is not searched for).
    #[error("no sphere outline found in the images ({reason})")]
    SphereNotFound {
        /// What the search found instead.
        reason: String,
    },
    /// An image decoded but its layout is not one this tool reads.
    #[error("{path}: unsupported image: {reason}")]
    UnsupportedImage {
        /// The image file.
        path: PathBuf,
        /// What is unsupported and what is accepted instead.
        reason: String,
    },
    /// An image of a stack does not have the size of the first image.
    #[error(
        "{path} (image {index}): size {found_width}x{found_height} differs from the stack's {width}x{height}; all images must have the same size"
    )]
    SizeMismatch {
        /// The offending image.
        path: PathBuf,
        /// Its index in the stack (0-based).
        index: usize,
        /// Width of the stack.
        width: usize,
        /// Height of the stack.
        height: usize,
        /// Width found.
        found_width: usize,
        /// Height found.
        found_height: usize,
    },
    /// An image of a stack cannot take part in a solve: its channels differ from the first
    /// image's, or it holds no light (all dark) or no usable sample (all saturated).
    #[error("{path} (image {index}): {reason}")]
    BadImage {
        /// The offending image.
        path: PathBuf,
        /// Its index in the stack (0-based).
        index: usize,
        /// What is wrong and what to do.
        reason: String,
    },
    /// An output folder already holds files (or an output file exists) and overwriting was
    /// not asked for. Nothing was written.
    #[error("{path}: {what}")]
    OutputExists {
        /// The folder or file.
        path: PathBuf,
        /// What is there.
        what: String,
    },
    /// Another process holds the output folder's lock: a run is writing there. Nothing was
    /// written.
    #[error(
        "{path}: another run (process {holder}) is writing to this output folder; wait for it or choose another"
    )]
    OutputBusy {
        /// The output folder.
        path: PathBuf,
        /// The process that holds the lock, as it recorded itself (its id), or `unknown`.
        holder: String,
    },
    /// An output folder holds entries that are not a previous output set of this tool, so it
    /// is not replaced as a whole. Nothing was written.
    #[error(
        "{path}: holds {entry}, which is not an output of a previous run; the folder is not replaced: remove what is not an output, or choose another folder"
    )]
    OutputForeign {
        /// The output folder.
        path: PathBuf,
        /// The first entry found that no previous output set lists.
        entry: String,
    },
    /// An output would replace or sit over an input of the run. Nothing was written.
    #[error("{path}: it holds (or is) the input {input}; write the results apart from the inputs")]
    OutputHoldsInput {
        /// The output folder or file.
        path: PathBuf,
        /// The input it would replace.
        input: PathBuf,
    },
    /// A lights file is malformed.
    #[error("{path}{}: {reason}", line.map(|l| format!(" line {l}")).unwrap_or_default())]
    LightsFile {
        /// The lights file.
        path: PathBuf,
        /// 1-based line number, where one applies.
        line: Option<usize>,
        /// What is wrong.
        reason: String,
    },
    /// A light's direction or intensity is unusable.
    #[error("light {index}: {reason}")]
    InvalidLight {
        /// 0-based light index.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// The lights and the images cannot be paired.
    #[error("lights do not match the images: {reason}")]
    LightsMismatch {
        /// What does not match, and how to fix it.
        reason: String,
    },
    /// Numbered images given in text order (as a shell sorts `name.*.png`: `name.10.png`
    /// before `name.2.png`) while the lights are a plain list paired by position.
    #[error(
        "the images are numbered but given in text order ({} before {}, as a shell sorts them), so a plain list of lights would be paired with the wrong images; in numeric order they are: {}. Give the images in that order, or name each light's image in the lights file",
        crate::capture::order::short_list(std::slice::from_ref(.earlier), 1),
        crate::capture::order::short_list(std::slice::from_ref(.later), 1),
        crate::capture::order::short_list(.natural, 12)
    )]
    ImageOrder {
        /// An image given before `later` but numbered after it.
        earlier: PathBuf,
        /// The image that should come first.
        later: PathBuf,
        /// All images in numeric order.
        natural: Vec<PathBuf>,
    },
    /// Too few images or lights to determine a normal (three are needed).
    #[error(
        "{count} image(s) given; photometric stereo needs at least 3 lights in general position"
    )]
    TooFewImages {
        /// Number given.
        count: usize,
    },
    /// The light directions are (nearly) coplanar, so g = ρN is not determined.
    #[error(
        "light directions are degenerate (condition number {condition:.3e} > {limit:.1e}): they are (nearly) coplanar; add lights out of their plane"
    )]
    DegenerateLights {
        /// Condition number of the light matrix.
        condition: f64,
        /// The limit that was exceeded.
        limit: f64,
    },
    /// A mask is unusable.
    #[error("mask {path}: {reason}")]
    Mask {
        /// The mask file (or a description of where the mask came from).
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The ambient image (the scene with every lamp off) does not fit the capture.
    #[error("ambient image {path}: {reason}")]
    Ambient {
        /// The ambient image's file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A DiLiGenT-layout folder is incomplete or inconsistent.
    #[error("data set {path}: {reason}")]
    Dataset {
        /// The folder.
        path: PathBuf,
        /// What is missing or wrong.
        reason: String,
    },
    /// A parameter is out of its valid range.
    #[error("parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter's name as the user knows it.
        name: &'static str,
        /// What is wrong and what is accepted.
        reason: String,
    },
    /// Two maps that must have the same size do not.
    #[error("{what}: size {found_width}x{found_height}, expected {width}x{height}")]
    DimensionMismatch {
        /// Which maps.
        what: String,
        /// Expected width.
        width: usize,
        /// Expected height.
        height: usize,
        /// Width found.
        found_width: usize,
        /// Height found.
        found_height: usize,
    },
    /// Encoding an output file failed.
    #[error("{path}: cannot write: {reason}")]
    Encode {
        /// The output file.
        path: PathBuf,
        /// What the encoder reported.
        reason: String,
    },
}

impl Error {
    /// Wraps an I/O error with the path it concerns.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            cause: source,
        }
    }

    /// Shorthand for [`Error::InvalidParameter`].
    pub fn param(name: &'static str, reason: impl Into<String>) -> Self {
        Error::InvalidParameter {
            name,
            reason: reason.into(),
        }
    }
}
