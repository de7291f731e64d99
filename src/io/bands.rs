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
use crate::io::decode::{MAX_IMAGE_SAMPLES, RawDecoded, SampleFormat, Samples};
use std::fs::File;
use std::io::BufReader;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// A file open for reading row bands, top to bottom.
pub(crate) struct BandReader {
    path: PathBuf,
    width: usize,
    height: usize,
    /// Colour channels kept (1 or 3).
    channels: usize,
    /// Interleaved samples per pixel in the decoded rows (may include alpha).
    stride: usize,
    format: SampleFormat,
    kind: Kind,
}

enum Kind {
    Png {
        reader: Box<png::Reader<BufReader<File>>>,
        /// Bytes per decoded row.
        line: usize,
        /// Next row the stream will give.
        next: usize,
        sixteen: bool,
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

fn decode_error(path: &Path, reason: impl std::fmt::Display) -> Error {
    Error::Decode {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

fn not_band_readable(path: &Path, reason: impl Into<String>) -> Error {
    Error::NotBandReadable {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

fn unsupported(path: &Path, reason: impl Into<String>) -> Error {
    Error::UnsupportedImage {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

fn extension_is(path: &Path, ext: &str) -> bool {
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
            Err(not_band_readable(path, "only PNG, TIFF and EXR files can"))
        }
    }

    /// Image width and height.
    pub(crate) fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Channels kept (1 grey, 3 RGB).
    pub(crate) fn channels(&self) -> usize {
        self.channels
    }

    fn open_png(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let bad = |e: png::DecodingError| match e {
            png::DecodingError::IoError(io) => Error::io(path, io),
            other => decode_error(path, other),
        };
        let limits = png::Limits {
            bytes: 4 * MAX_IMAGE_SAMPLES,
        };
        let mut decoder = png::Decoder::new_with_limits(BufReader::new(file), limits);
        decoder.set_transformations(png::Transformations::EXPAND);
        let reader = decoder.read_info().map_err(bad)?;
        let (width, height) = (reader.info().width, reader.info().height);
        if reader.info().interlaced {
            return Err(not_band_readable(
                path,
                "it is an interlaced PNG; re-save it without interlacing",
            ));
        }
        let line = reader
            .output_line_size(width)
            .ok_or_else(|| unsupported(path, "image too large"))?;
        let (color, depth) = reader.output_color_type();
        let (channels, stride) = match color {
            png::ColorType::Grayscale => (1, 1),
            png::ColorType::GrayscaleAlpha => (1, 2),
            png::ColorType::Rgb | png::ColorType::Indexed => (3, 3),
            png::ColorType::Rgba => (3, 4),
        };
        let sixteen = depth == png::BitDepth::Sixteen;
        Ok(BandReader {
            path: path.to_path_buf(),
            width: width as usize,
            height: height as usize,
            channels,
            stride,
            format: if sixteen {
                SampleFormat::U16
            } else {
                SampleFormat::U8
            },
            kind: Kind::Png {
                reader: Box::new(reader),
                line,
                next: 0,
                sixteen,
            },
        })
    }

    fn open_tiff(path: &Path) -> Result<Self> {
        use tiff::ColorType as C;
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let bad = |e: tiff::TiffError| match e {
            tiff::TiffError::IoError(io) => Error::io(path, io),
            other => decode_error(path, other),
        };
        let mut decoder = tiff::decoder::Decoder::new(BufReader::new(file)).map_err(bad)?;
        let (w, h) = decoder.dimensions().map_err(bad)?;
        let (width, height) = (w as usize, h as usize);
        let color = decoder.colortype().map_err(bad)?;
        let (channels, stride, bits) = match color {
            C::Gray(b) => (1, 1, b),
            C::GrayA(b) => (1, 2, b),
            C::RGB(b) => (3, 3, b),
            C::RGBA(b) => (3, 4, b),
            other => {
                return Err(unsupported(
                    path,
                    format!(
                        "TIFF colour type {other:?}: grey or RGB (with or without alpha) is read"
                    ),
                ));
            }
        };
        let format = match bits {
            8 => SampleFormat::U8,
            16 => SampleFormat::U16,
            32 => SampleFormat::F32,
            b => {
                return Err(unsupported(
                    path,
                    format!("{b}-bit TIFF samples: 8, 16 or 32 (float) bits are read"),
                ));
            }
        };
        let (cw, ch) = decoder.chunk_dimensions();
        let chunk = (cw as usize, ch as usize);
        if chunk.0 == 0 || chunk.1 == 0 {
            return Err(decode_error(path, "a strip or tile of zero size"));
        }
        let across = width.div_ceil(chunk.0);
        let expected = across * height.div_ceil(chunk.1);
        let count = match decoder.get_chunk_type() {
            tiff::decoder::ChunkType::Strip => decoder.strip_count().map_err(bad)?,
            tiff::decoder::ChunkType::Tile => decoder.tile_count().map_err(bad)?,
        } as usize;
        if count != expected {
            return Err(not_band_readable(
                path,
                format!(
                    "it is a TIFF with separate colour planes ({count} strips or tiles where one plane needs {expected})"
                ),
            ));
        }
        Ok(BandReader {
            path: path.to_path_buf(),
            width,
            height,
            channels,
            stride,
            format,
            kind: Kind::Tiff {
                decoder: Box::new(decoder),
                chunk,
                across,
                cache: None,
            },
        })
    }

    fn open_exr(path: &Path) -> Result<Self> {
        use exr::meta::attribute::SampleType;
        let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|e| match e {
            exr::error::Error::Io(io) => Error::io(path, io),
            other => decode_error(path, other),
        })?;
        let header = meta
            .headers
            .first()
            .ok_or_else(|| decode_error(path, "no layer in file"))?;
        let (width, height) = (header.layer_size.width(), header.layer_size.height());
        let list = &header.channels.list;
        let find = |name: &str| list.iter().position(|c| c.name.to_string() == name);
        let indices: Vec<usize> = match (find("R"), find("G"), find("B")) {
            (Some(r), Some(g), Some(b)) => vec![r, g, b],
            _ => match find("Y").or_else(|| find("Z")) {
                Some(y) => vec![y],
                None if list.len() == 1 => vec![0],
                None => {
                    let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
                    return Err(unsupported(
                        path,
                        format!(
                            "channels {names:?}: expected R, G, B, or a single channel (Y, Z or any one)"
                        ),
                    ));
                }
            },
        };
        let mut format = SampleFormat::F32;
        let mut chosen = Vec::new();
        for i in indices {
            let c = &list[i];
            if c.sampling != exr::math::Vec2(1, 1) {
                return Err(unsupported(
                    path,
                    format!("channel {} is subsampled", c.name),
                ));
            }
            if c.sample_type == SampleType::F16 {
                format = SampleFormat::F16;
            }
            chosen.push((i, c.sample_type));
        }
        Ok(BandReader {
            path: path.to_path_buf(),
            width,
            height,
            channels: chosen.len(),
            stride: chosen.len(),
            format,
            kind: Kind::Exr { chosen },
        })
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
        })
    }
}

/// Copies `src[src_range]` into `dst[dst_start..]` when both hold the same sample type.
fn copy_samples(dst: &mut Samples, dst_start: usize, src: &Samples, src_range: Range<usize>) {
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

/// Rows `rows` of a TIFF, `dims` = (width, height, samples per pixel), assembled from the
/// chunks that hold them; the last row of chunks stays in `cache`.
fn read_tiff_rows(
    path: &Path,
    decoder: &mut tiff::decoder::Decoder<BufReader<File>>,
    chunk: (usize, usize),
    across: usize,
    cache: &mut Option<(usize, Samples)>,
    dims: (usize, usize, usize),
    rows: Range<usize>,
) -> Result<Samples> {
    use tiff::decoder::DecodingResult as D;
    let (width, height, stride) = dims;
    let row_len = width * stride;
    let mut out: Option<Samples> = None;
    let mut y = rows.start;
    while y < rows.end {
        let band = y / chunk.1;
        let top = band * chunk.1;
        let band_rows = chunk.1.min(height - top);
        if cache.as_ref().is_none_or(|(t, _)| *t != top) {
            // Decode the row of chunks into one full-width buffer.
            let mut full: Option<Samples> = None;
            for tx in 0..across {
                let index = (band * across + tx) as u32;
                let data = decoder.read_chunk(index).map_err(|e| match e {
                    tiff::TiffError::IoError(io) => Error::io(path, io),
                    other => decode_error(path, other),
                })?;
                let (dw, _) = decoder.chunk_data_dimensions(index);
                let dw = dw as usize;
                let src = match data {
                    D::U8(v) => Samples::U8(v),
                    D::U16(v) => Samples::U16(v),
                    D::F32(v) => Samples::F32(v),
                    _ => {
                        return Err(unsupported(
                            path,
                            "TIFF sample type: 8- or 16-bit integers or 32-bit floats are read",
                        ));
                    }
                };
                let full = full.get_or_insert_with(|| empty_like(&src, band_rows * row_len));
                let x0 = tx * chunk.0;
                for r in 0..band_rows {
                    copy_samples(
                        full,
                        r * row_len + x0 * stride,
                        &src,
                        r * dw * stride..(r + 1) * dw * stride,
                    );
                }
            }
            let full = full.ok_or_else(|| decode_error(path, "a row of strips without data"))?;
            *cache = Some((top, full));
        }
        let Some((_, full)) = cache.as_ref() else {
            break;
        };
        let out = out.get_or_insert_with(|| empty_like(full, rows.len() * row_len));
        let last = rows.end.min(top + band_rows);
        copy_samples(
            out,
            (y - rows.start) * row_len,
            full,
            (y - top) * row_len..(last - top) * row_len,
        );
        y = last;
    }
    Ok(out.unwrap_or(Samples::U8(Vec::new())))
}

/// A zeroed buffer of `len` samples of `like`'s type.
fn empty_like(like: &Samples, len: usize) -> Samples {
    match like {
        Samples::U8(_) | Samples::U16Be(_) => Samples::U8(vec![0; len]),
        Samples::U16(_) => Samples::U16(vec![0; len]),
        Samples::F32(_) => Samples::F32(vec![0.0; len]),
    }
}

/// Rows `rows` of the first layer of an EXR, channels `chosen` interleaved, read from the
/// blocks that hold them.
fn read_exr_rows(
    path: &Path,
    chosen: &[(usize, exr::meta::attribute::SampleType)],
    width: usize,
    rows: Range<usize>,
) -> Result<Samples> {
    use exr::block::reader::ChunksReader;
    use exr::meta::attribute::SampleType;
    let bad = |e: exr::error::Error| match e {
        exr::error::Error::Io(io) => Error::io(path, io),
        other => decode_error(path, other),
    };
    let channels = chosen.len();
    let mut out = vec![0f32; rows.len() * width * channels];
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let reader = exr::block::read(BufReader::new(file), false).map_err(bad)?;
    let chunks = reader
        .filter_chunks(false, |_, _, block| {
            let y0 = block.pixel_position.y();
            block.layer == 0
                && block.level == exr::math::Vec2(0, 0)
                && y0 < rows.end
                && y0 + block.pixel_size.height() > rows.start
        })
        .map_err(bad)?;
    let mut row = Vec::new();
    chunks
        .decompress_sequential(false, |meta, block| {
            let header = &meta.headers[0];
            for line in block.lines(&header.channels) {
                let loc = &line.location;
                let y = loc.position.y();
                let Some(ci) = chosen.iter().position(|(i, _)| *i == loc.channel) else {
                    continue;
                };
                if !rows.contains(&y) {
                    continue;
                }
                let x0 = loc.position.x();
                let n = loc.sample_count.min(width.saturating_sub(x0));
                row.clear();
                match chosen[ci].1 {
                    SampleType::F16 => {
                        for v in line.read_samples::<exr::prelude::f16>().take(n) {
                            row.push(v?.to_f32());
                        }
                    }
                    SampleType::F32 => {
                        for v in line.read_samples::<f32>().take(n) {
                            row.push(v?);
                        }
                    }
                    SampleType::U32 => {
                        for v in line.read_samples::<u32>().take(n) {
                            row.push(v? as f32);
                        }
                    }
                }
                let base = ((y - rows.start) * width + x0) * channels + ci;
                for (i, v) in row.iter().enumerate() {
                    out[base + i * channels] = *v;
                }
            }
            Ok(())
        })
        .map_err(bad)?;
    Ok(Samples::F32(out))
}
