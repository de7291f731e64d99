//! Row bands of image files, decoded without holding the whole image: the input stage of
//! [`crate::run::stream`].
//!
//! - PNG: rows come out of the zlib stream in order (non-interlaced files only; an interlaced
//!   file spreads every row over seven passes).
//! - TIFF: the strips or tiles that hold the band's rows are decoded, the last one is kept for
//!   the next band (chunk-planar files are refused).
//! - EXR: the scan-line or tile blocks that hold the band's rows are found through the file's
//!   offset table and only they are read and decompressed.
//!
//! Each band is returned as the same raw samples [`crate::capture::stack`] converts for a whole image,
//! so the conversion (transfer function, saturation, intensity, grey mix) is the same code.

use crate::error::{Error, Result};

use crate::io::decode::{RawDecoded, SampleFormat, Samples};
use crate::io::exr::read_exr_rows;
use crate::io::tiff::read_tiff_rows;
use std::fs::File;
use std::io::BufReader;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// A file open for reading row bands, top to bottom.
pub(crate) struct BandReader {
    pub(crate) path: PathBuf,
    pub(crate) width: usize,
    pub(crate) height: usize,
    /// Colour channels kept (1 or 3).
    pub(crate) channels: usize,
    /// Interleaved samples per pixel in the decoded rows (may include alpha).
    pub(crate) stride: usize,
    pub(crate) format: SampleFormat,
    pub(crate) kind: Kind,
}

pub(crate) enum Kind {
    Png {
        reader: Box<png::Reader<BufReader<File>>>,
        /// Bytes per decoded row.
        line: usize,
        /// Next row the stream will give.
        next: usize,
        sixteen: bool,
        /// The stream was read to its end (every chunk's checksum verified).
        done: bool,
    },
    Tiff {
        decoder: Box<tiff::decoder::Decoder<BufReader<File>>>,
        /// Chunk (strip or tile) size.
        chunk: (usize, usize),
        /// Chunks per row of chunks.
        across: usize,
        /// The last decoded row of chunks: its first row and its samples, full width.
        cache: Option<(usize, Samples)>,
    },
    Exr {
        /// Index in the file's channel list and sample type of each kept channel.
        chosen: Vec<(usize, exr::meta::attribute::SampleType)>,
    },
}

pub(crate) fn decode_error(path: &Path, reason: impl std::fmt::Display) -> Error {
    Error::Decode {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

pub(crate) fn not_band_readable(path: &Path, reason: impl Into<String>) -> Error {
    Error::NotBandReadable {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

pub(crate) fn unsupported(path: &Path, reason: impl Into<String>) -> Error {
    Error::UnsupportedImage {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

pub(crate) fn extension_is(path: &Path, ext: &str) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case(ext))
}

impl BandReader {
    /// Opens `path` (PNG, TIFF or EXR, by its extension) and reads its header.
    ///
    /// # Errors
    /// [`Error::Io`] or [`Error::Decode`] naming the file; [`Error::NotBandReadable`] for a
    /// file that can only be loaded whole (not PNG, TIFF or EXR; interlaced PNG; chunk-planar
    /// TIFF); [`Error::UnsupportedImage`] for subsampled EXR channels or an unsupported sample
    /// type.
    pub(crate) fn open(path: &Path) -> Result<Self> {
        if extension_is(path, "exr") {
            Self::open_exr(path)
        } else if extension_is(path, "tif") || extension_is(path, "tiff") {
            Self::open_tiff(path)
        } else if extension_is(path, "png") {
            Self::open_png(path)
        } else {
            Err(not_band_readable(
                path,
                "only PNG, TIFF and EXR files can (JPEG and other formats are read whole)",
            ))
        }
    }

    /// Reads the rest of the file after the last band (a band run can stop above the last
    /// row), so that the checksum of the chunk that held the last row read is verified (PNG;
    /// the other formats check each block as they read it).
    ///
    /// # Errors
    /// [`Error::Decode`] naming the file for a checksum that does not match.
    pub(crate) fn verify_rest(&mut self) -> Result<()> {
        if let Kind::Png { reader, done, .. } = &mut self.kind
            && !*done
        {
            let path = &self.path;
            reader.finish().map_err(|e| match e {
                png::DecodingError::IoError(io) => Error::io(path, io),
                other => decode_error(path, other),
            })?;
            *done = true;
        }
        Ok(())
    }

    /// Image width and height.
    pub(crate) fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Channels kept (1 grey, 3 RGB).
    pub(crate) fn channels(&self) -> usize {
        self.channels
    }

    /// Decodes rows `rows` (which must not start above the end of the previous band for PNG;
    /// an earlier start reopens the file).
    ///
    /// # Errors
    /// [`Error::Io`] or [`Error::Decode`] naming the file; [`Error::InvalidParameter`] for rows
    /// beyond the image.
    pub(crate) fn read(&mut self, rows: Range<usize>) -> Result<RawDecoded> {
        if rows.start > rows.end || rows.end > self.height {
            return Err(Error::param(
                "rows",
                format!(
                    "rows {}..{} of {} (a {}-row image)",
                    rows.start,
                    rows.end,
                    self.path.display(),
                    self.height
                ),
            ));
        }
        let samples = match &mut self.kind {
            Kind::Png { next, .. } if rows.start < *next => {
                *self = Self::open_png(&self.path)?;
                return self.read(rows);
            }
            Kind::Png {
                reader,
                line,
                next,
                sixteen,
                done,
            } => {
                let path = &self.path;
                let bad = |e: png::DecodingError| match e {
                    png::DecodingError::IoError(io) => Error::io(path, io),
                    other => decode_error(path, other),
                };
                let mut skip = vec![0u8; *line];
                while *next < rows.start {
                    reader.read_row(&mut skip).map_err(bad)?;
                    *next += 1;
                }
                let mut buf = vec![0u8; *line * rows.len()];
                for row in buf.chunks_exact_mut((*line).max(1)) {
                    reader.read_row(row).map_err(bad)?;
                    *next += 1;
                }
                if *next == self.height && !*done {
                    // Read to the end, so that the checksums of the last chunks are verified.
                    reader.finish().map_err(bad)?;
                    *done = true;
                }
                if *sixteen {
                    Samples::U16Be(buf)
                } else {
                    Samples::U8(buf)
                }
            }
            Kind::Tiff {
                decoder,
                chunk,
                across,
                cache,
            } => read_tiff_rows(
                &self.path,
                decoder,
                *chunk,
                *across,
                cache,
                (self.width, self.height, self.stride),
                rows.clone(),
            )?,
            Kind::Exr { chosen } => read_exr_rows(&self.path, chosen, self.width, rows.clone())?,
        };
        Ok(RawDecoded {
            width: self.width,
            height: rows.len(),
            channels: self.channels,
            stride: self.stride,
            format: self.format,
            samples,
            raw: None,
        })
    }
}

/// Copies `src[src_range]` into `dst[dst_start..]` when both hold the same sample type.
pub(crate) fn copy_samples(
    dst: &mut Samples,
    dst_start: usize,
    src: &Samples,
    src_range: Range<usize>,
) {
    let n = src_range.len();
    match (dst, src) {
        (Samples::U8(d), Samples::U8(s)) => {
            d[dst_start..dst_start + n].copy_from_slice(&s[src_range]);
        }
        (Samples::U16(d), Samples::U16(s)) => {
            d[dst_start..dst_start + n].copy_from_slice(&s[src_range]);
        }
        (Samples::F32(d), Samples::F32(s)) => {
            d[dst_start..dst_start + n].copy_from_slice(&s[src_range]);
        }
        _ => {}
    }
}

/// A zeroed buffer of `len` samples of `like`'s type.
pub(crate) fn empty_like(like: &Samples, len: usize) -> Samples {
    match like {
        Samples::U8(_) | Samples::U16Be(_) => Samples::U8(vec![0; len]),
        Samples::U16(_) => Samples::U16(vec![0; len]),
        Samples::F32(_) => Samples::F32(vec![0.0; len]),
    }
}
