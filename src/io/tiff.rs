//! TIFF: reading row bands from the strips or tiles that hold them (chunk-planar files are
//! refused). Whole TIFF files are decoded through the `image` crate in [`crate::io::decode`].

use crate::error::{Error, Result};
use crate::io::bands::{
    BandReader, Kind, copy_samples, decode_error, empty_like, not_band_readable, unsupported,
};
use crate::io::decode::{SampleFormat, Samples};
use std::fs::File;
use std::io::BufReader;
use std::ops::Range;
use std::path::Path;

impl BandReader {
    pub(crate) fn open_tiff(path: &Path) -> Result<Self> {
        use tiff::ColorType as C;
        let (file, file_len) = crate::io::input::open_input(path)?;
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
        crate::io::input::check_declared_size(
            path,
            (width, height),
            stride,
            (width as u64 * height as u64).saturating_mul(stride as u64 * u64::from(bits) / 8),
            file_len,
            crate::io::input::MAX_STREAM_SAMPLES,
        )?;
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
}

/// Rows `rows` of a TIFF, `dims` = (width, height, samples per pixel), assembled from the
/// chunks that hold them; the last row of chunks stays in `cache`.
pub(crate) fn read_tiff_rows(
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
