//! PNG: decoding whole files or rows in order (8 or 16 bits, grey or RGB, alpha dropped;
//! non-interlaced files for row bands), and encoding 8- and 16-bit files whole or a band of
//! rows at a time.

use crate::error::{Error, Result};
use crate::io::bands::{BandReader, Kind, decode_error, not_band_readable, unsupported};
use crate::io::decode::{MAX_IMAGE_SAMPLES, RawDecoded, SampleFormat, Samples};
use crate::io::encode::Pipe;
use crate::io::input::{check_declared_size, open_input};
use crate::io::output::PendingFile;
use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::ops::Range;
use std::path::Path;
use std::sync::mpsc;

/// PNG through the `png` crate directly: 16-bit samples stay in the decoder's big-endian buffer.
/// With `rows`, a non-interlaced image is decoded only up to the end of the range (the rows
/// below stay zero); the rest of the file is still read, so that every chunk's checksum is
/// verified.
pub(crate) fn decode_png(path: &Path, rows: Option<Range<usize>>) -> Result<RawDecoded> {
    let (file, file_len) = open_input(path)?;
    let bad = |e: png::DecodingError| match e {
        png::DecodingError::IoError(io) => Error::io(path, io),
        other => Error::Decode {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    };
    // The png crate's default limit (64 MiB decoded) refuses 16-bit RGB captures above
    // 11 Mpx; the image's own size is checked against MAX_IMAGE_SAMPLES below instead.
    let limits = png::Limits {
        bytes: 4 * MAX_IMAGE_SAMPLES,
    };
    let mut decoder = png::Decoder::new_with_limits(BufReader::new(file), limits);
    // Palette → RGB, grey below 8 bits → 8 bits, transparency chunk → alpha.
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(bad)?;
    check_png_header(path, reader.info(), file_len)?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: "image too large".into(),
        })?;
    let (width, height) = (reader.info().width, reader.info().height);
    // The header is checked before allocating what it declares (at most 2 bytes a sample).
    if size > 2 * MAX_IMAGE_SAMPLES {
        return Err(Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!(
                "the header declares {width}x{height} pixels ({size} bytes decoded), more than the {MAX_IMAGE_SAMPLES} samples this tool reads"
            ),
        });
    }
    let mut buf = vec![0u8; size];
    let (color_type, bit_depth) = match rows {
        Some(rows) if !reader.info().interlaced => {
            let line = reader
                .output_line_size(width)
                .ok_or_else(|| Error::UnsupportedImage {
                    path: path.to_path_buf(),
                    reason: "image too large".into(),
                })?;
            buf.truncate(line * height as usize);
            for row in buf.chunks_exact_mut(line.max(1)).take(rows.end) {
                reader.read_row(row).map_err(bad)?;
            }
            // Read to the end (the rows below are not decoded), so that the checksum of the
            // chunk that held the last row read is verified.
            reader.finish().map_err(bad)?;
            reader.output_color_type()
        }
        _ => {
            let info = reader.next_frame(&mut buf).map_err(bad)?;
            reader.finish().map_err(bad)?;
            buf.truncate(info.buffer_size());
            (info.color_type, info.bit_depth)
        }
    };
    let (channels, stride) = match color_type {
        png::ColorType::Grayscale => (1, 1),
        png::ColorType::GrayscaleAlpha => (1, 2),
        png::ColorType::Rgb | png::ColorType::Indexed => (3, 3),
        png::ColorType::Rgba => (3, 4),
    };
    let (format, samples) = match bit_depth {
        png::BitDepth::Sixteen => (SampleFormat::U16, Samples::U16Be(buf)),
        _ => (SampleFormat::U8, Samples::U8(buf)),
    };
    Ok(RawDecoded {
        width: width as usize,
        height: height as usize,
        channels,
        stride,
        format,
        samples,
        raw: None,
    })
}

/// The declared size of a PNG against the limits and the file's length
/// ([`check_declared_size`]), before anything sized by it is allocated.
fn check_png_header(path: &Path, info: &png::Info, file_len: u64) -> Result<()> {
    let (width, height) = (info.width as usize, info.height as usize);
    // The zlib stream holds each row's filter byte and its packed samples.
    let stream = (info.raw_row_length() as u64).saturating_mul(height as u64);
    check_declared_size(
        path,
        (width, height),
        info.color_type.samples(),
        stream,
        file_len,
        crate::io::input::MAX_STREAM_SAMPLES,
    )
}

impl BandReader {
    pub(crate) fn open_png(path: &Path) -> Result<Self> {
        let (file, file_len) = open_input(path)?;
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
        check_png_header(path, reader.info(), file_len)?;
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
                done: false,
            },
        })
    }
}

/// A PNG library error as ours, naming `path`.
pub(crate) fn png_error(path: &Path, e: png::EncodingError) -> Error {
    match e {
        png::EncodingError::IoError(io) => Error::io(path, io),
        other => Error::Encode {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    }
}

/// A PNG encoder with the settings of every PNG written: 1 (grey) or 3 (RGB) channels of
/// `depth`, balanced deflate, adaptive filtering.
pub(crate) fn png_encoder<W: Write>(
    w: W,
    width: usize,
    height: usize,
    channels: usize,
    depth: png::BitDepth,
) -> Result<png::Encoder<'static, W>> {
    let color = match channels {
        1 => png::ColorType::Grayscale,
        3 => png::ColorType::Rgb,
        _ => {
            return Err(Error::param(
                "channels",
                format!("{channels}: 1 or 3 expected"),
            ));
        }
    };
    let (Ok(w32), Ok(h32)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(Error::param(
            "size",
            format!("{width}x{height} is too large for a PNG"),
        ));
    };
    let mut e = png::Encoder::new(w, w32, h32);
    e.set_color(color);
    e.set_depth(depth);
    e.set_compression(png::Compression::Balanced);
    e.set_filter(png::Filter::Adaptive);
    Ok(e)
}

/// Encodes an 8-bit PNG (`channels` 1 or 3, interleaved) into `file`; `path` names it in
/// errors.
///
/// # Errors
/// [`Error::InvalidParameter`] for a channel count other than 1 or 3 or a data length that
/// does not match; [`Error::Encode`] or [`Error::Io`] when writing fails.
pub(crate) fn encode_png8(
    file: &mut File,
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    data: &[u8],
) -> Result<()> {
    encode_png(
        file,
        path,
        (width, height, channels),
        png::BitDepth::Eight,
        data,
    )
}

/// Encodes a 16-bit PNG (`channels` 1 or 3, interleaved) into `file`; `path` names it in
/// errors.
///
/// # Errors
/// As [`encode_png8`].
pub(crate) fn encode_png16(
    file: &mut File,
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    data: &[u16],
) -> Result<()> {
    // PNG stores 16-bit samples big-endian.
    let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_be_bytes()).collect();
    encode_png(
        file,
        path,
        (width, height, channels),
        png::BitDepth::Sixteen,
        &bytes,
    )
}

/// Encodes a PNG of `(width, height, channels)` samples of `depth` from their bytes.
pub(crate) fn encode_png(
    file: &mut File,
    path: &Path,
    (width, height, channels): (usize, usize, usize),
    depth: png::BitDepth,
    bytes: &[u8],
) -> Result<()> {
    let sample = if depth == png::BitDepth::Sixteen {
        2
    } else {
        1
    };
    if bytes.len() != width * height * channels * sample {
        return Err(Error::param(
            "data",
            format!(
                "{} samples for a {width}x{height} image of {channels} channel(s)",
                bytes.len() / sample
            ),
        ));
    }
    let mut out = BufWriter::new(file);
    let mut png = png_encoder(&mut out, width, height, channels, depth)?
        .write_header()
        .map_err(|e| png_error(path, e))?;
    let mut rows = png.stream_writer().map_err(|e| png_error(path, e))?;
    rows.write_all(bytes).map_err(|e| Error::io(path, e))?;
    rows.finish().map_err(|e| png_error(path, e))?;
    png.finish().map_err(|e| png_error(path, e))?;
    out.flush().map_err(|e| Error::io(path, e))
}

/// An 8-bit PNG written a band of rows at a time, on a thread of its own. The file's bytes are
/// those [`encode_png8`] writes for the whole image.
pub(crate) struct PngRows {
    pipe: Pipe<Vec<u8>>,
    row_bytes: usize,
}

impl PngRows {
    /// Starts writing `file` as a `width`×`height` PNG of `channels` (1 or 3) interleaved
    /// 8-bit channels.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for another channel count; [`Error::Io`] when the thread
    /// cannot start.
    pub(crate) fn start(
        file: PendingFile,
        width: usize,
        height: usize,
        channels: usize,
    ) -> Result<Self> {
        let path = file.path().to_path_buf();
        // Checked here so that a bad call fails before any thread starts.
        png_encoder(
            std::io::sink(),
            width,
            height,
            channels,
            png::BitDepth::Eight,
        )?;
        let thread_path = path.clone();
        let pipe = Pipe::spawn(path, height, move |rx: mpsc::Receiver<Vec<u8>>| {
            let mut file = file;
            let path = thread_path;
            let mut out = BufWriter::new(file.file_mut());
            let mut png = png_encoder(&mut out, width, height, channels, png::BitDepth::Eight)?
                .write_header()
                .map_err(|e| png_error(&path, e))?;
            let mut rows = png.stream_writer().map_err(|e| png_error(&path, e))?;
            for band in rx {
                rows.write_all(&band).map_err(|e| Error::io(&path, e))?;
            }
            rows.finish().map_err(|e| png_error(&path, e))?;
            png.finish().map_err(|e| png_error(&path, e))?;
            out.flush().map_err(|e| Error::io(&path, e))?;
            drop(out);
            Ok(file)
        })?;
        Ok(PngRows {
            pipe,
            row_bytes: width * channels,
        })
    }

    /// Appends the next rows (interleaved samples, a whole number of rows).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for a partial row or rows past the last; the writer's
    /// error when it has failed.
    pub(crate) fn write(&mut self, rows: Vec<u8>) -> Result<()> {
        if !rows.len().is_multiple_of(self.row_bytes) {
            return Err(self.pipe.misfit(format!(
                "{} bytes in rows of {}",
                rows.len(),
                self.row_bytes
            )));
        }
        self.pipe.send(rows.len() / self.row_bytes, rows)
    }

    /// Waits for the end of the file; returns it, ready to stage.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when rows are missing; the writer's error.
    pub(crate) fn finish(self) -> Result<PendingFile> {
        self.pipe.finish()
    }
}
