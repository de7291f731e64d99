//! Decoding image files: EXR (half/float), PNG and TIFF (8/16 bit), JPEG (8 bit), grey or RGB, to samples
//! as stored (integers scaled to [0, 1], no transfer function), and the readers of masks,
//! normal maps and single EXR channels. The sRGB transfer function is here too: it is how
//! 8-bit files are encoded.

use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap};
use crate::io::exr::decode_exr;
use crate::io::input::{check_declared_size, open_input};
use crate::io::png::decode_png;
use nalgebra::Vector3;
use serde::Serialize;

pub use crate::io::exr::{ExrChannels, read_exr_channel, read_exr_channels, read_exr_text};
use std::ops::Range;
use std::path::Path;

/// How samples are stored in a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SampleFormat {
    /// 8-bit unsigned integer.
    U8,
    /// 16-bit unsigned integer.
    U16,
    /// 16-bit float (EXR half).
    F16,
    /// 32-bit float.
    F32,
}

impl SampleFormat {
    /// True for integer formats (which have a maximum code that means "saturated").
    pub fn is_integer(self) -> bool {
        matches!(self, SampleFormat::U8 | SampleFormat::U16)
    }
}

/// Samples of one decoded file, interleaved, as stored.
#[derive(Debug, Clone)]
pub(crate) enum Samples {
    U8(Vec<u8>),
    U16(Vec<u16>),
    /// 16-bit samples as big-endian byte pairs (PNG's layout), converted without a copy.
    U16Be(Vec<u8>),
    F32(Vec<f32>),
}

/// An image as decoded from a file: interleaved samples scaled to [0, 1] for integer formats,
/// with no transfer function applied.
#[derive(Debug, Clone)]
pub struct DecodedImage {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// 1 (grey) or 3 (RGB); alpha is dropped.
    pub channels: usize,
    /// Storage format in the file.
    pub format: SampleFormat,
    /// `width * height * channels` values, row-major, channels interleaved.
    pub data: Vec<f32>,
}

/// sRGB EOTF (IEC 61966-2-1): encoded value in [0, 1] to linear.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Inverse sRGB EOTF: linear value in [0, 1] to encoded.
pub fn linear_to_srgb(v: f32) -> f32 {
    if v <= 0.003_130_8 {
        v * 12.92
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

pub(crate) struct RawDecoded {
    pub(crate) width: usize,
    pub(crate) height: usize,
    /// Channels kept (1 or 3).
    pub(crate) channels: usize,
    /// Interleaved stride in `samples` (may include alpha).
    pub(crate) stride: usize,
    pub(crate) format: SampleFormat,
    pub(crate) samples: Samples,
    /// How a camera RAW file was developed (`None` for other formats).
    pub(crate) raw: Option<crate::io::raw::RawDevelopment>,
}

/// The `image` crate's error for `path` as this crate's.
fn image_error(path: &Path, e: image::ImageError) -> Error {
    match e {
        image::ImageError::IoError(io) => Error::io(path, io),
        image::ImageError::Unsupported(u) => Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!("{u}; {READ_FORMATS} are read"),
        },
        other => Error::Decode {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    }
}

/// A decoder of the `image` crate (TIFF, JPEG and the other formats it reads) over the regular
/// file `path`, its header read and the size it declares checked ([`check_declared_size`])
/// (at most `max_samples`) before any pixel is decoded.
fn generic_decoder(path: &Path, max_samples: usize) -> Result<impl image::ImageDecoder> {
    use image::ImageDecoder as _;
    let (file, file_len) = open_input(path)?;
    let decoder = image::ImageReader::new(std::io::BufReader::new(file))
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?
        .into_decoder()
        .map_err(|e| image_error(path, e))?;
    let (w, h) = decoder.dimensions();
    check_declared_size(
        path,
        (w as usize, h as usize),
        usize::from(decoder.color_type().channel_count()),
        decoder.total_bytes(),
        file_len,
        max_samples,
    )?;
    Ok(decoder)
}

/// An image's stored samples as an `H×W×C` array of their own type (C = 1 grey, 3 RGB; alpha
/// dropped), as [`read_array`] returns them.
#[derive(Debug, Clone, PartialEq)]
pub enum ImageArray {
    /// 8-bit samples.
    U8(ndarray::Array3<u8>),
    /// 16-bit samples.
    U16(ndarray::Array3<u16>),
    /// Float samples (EXR half or float, float TIFF).
    F32(ndarray::Array3<f32>),
}

/// Reads an image's samples as stored (not scaled, not linearised): what
/// [`crate::capture::Capture::from_arrays_channels`] then converts exactly as a load of the
/// file does.
///
/// # Errors
/// As [`read_image`].
pub fn read_array(path: &Path) -> Result<ImageArray> {
    let raw = decode_raw(path, None)?;
    let (h, w, c, stride) = (raw.height, raw.width, raw.channels, raw.stride);
    fn keep<T: Copy>(v: &[T], c: usize, stride: usize) -> Vec<T> {
        if c == stride {
            v.to_vec()
        } else {
            v.chunks_exact(stride)
                .flat_map(|p| p[..c].to_vec())
                .collect()
        }
    }
    let shape = (h, w, c);
    let bad = |e: ndarray::ShapeError| Error::Decode {
        path: path.to_path_buf(),
        reason: format!("the samples do not fill a {w}x{h}x{c} image: {e}"),
    };
    Ok(match &raw.samples {
        Samples::U8(v) => {
            ImageArray::U8(ndarray::Array3::from_shape_vec(shape, keep(v, c, stride)).map_err(bad)?)
        }
        Samples::U16(v) => ImageArray::U16(
            ndarray::Array3::from_shape_vec(shape, keep(v, c, stride)).map_err(bad)?,
        ),
        Samples::U16Be(b) => {
            let v: Vec<u16> = b
                .chunks_exact(2)
                .map(|p| u16::from_be_bytes([p[0], p[1]]))
                .collect();
            ImageArray::U16(
                ndarray::Array3::from_shape_vec(shape, keep(&v, c, stride)).map_err(bad)?,
            )
        }
        Samples::F32(v) => ImageArray::F32(
            ndarray::Array3::from_shape_vec(shape, keep(v, c, stride)).map_err(bad)?,
        ),
    })
}

pub(crate) fn decode_raw(path: &Path, rows: Option<Range<usize>>) -> Result<RawDecoded> {
    let is_exr = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    if is_exr {
        return decode_exr(path);
    }
    let is_png = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if is_png {
        return decode_png(path, rows);
    }
    if crate::io::raw::is_raw(path) {
        let (mut decoded, development) = crate::io::raw::decode(path)?;
        decoded.raw = Some(development);
        return Ok(decoded);
    }
    let decoder = generic_decoder(path, MAX_IMAGE_SAMPLES)?;
    let img = image::DynamicImage::from_decoder(decoder).map_err(|e| image_error(path, e))?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    use image::DynamicImage as D;
    let (channels, stride, format, samples) = match img {
        D::ImageLuma8(b) => (1, 1, SampleFormat::U8, Samples::U8(b.into_raw())),
        D::ImageLumaA8(b) => (1, 2, SampleFormat::U8, Samples::U8(b.into_raw())),
        D::ImageRgb8(b) => (3, 3, SampleFormat::U8, Samples::U8(b.into_raw())),
        D::ImageRgba8(b) => (3, 4, SampleFormat::U8, Samples::U8(b.into_raw())),
        D::ImageLuma16(b) => (1, 1, SampleFormat::U16, Samples::U16(b.into_raw())),
        D::ImageLumaA16(b) => (1, 2, SampleFormat::U16, Samples::U16(b.into_raw())),
        D::ImageRgb16(b) => (3, 3, SampleFormat::U16, Samples::U16(b.into_raw())),
        D::ImageRgba16(b) => (3, 4, SampleFormat::U16, Samples::U16(b.into_raw())),
        D::ImageRgb32F(b) => (3, 3, SampleFormat::F32, Samples::F32(b.into_raw())),
        D::ImageRgba32F(b) => (3, 4, SampleFormat::F32, Samples::F32(b.into_raw())),
        other => (
            3,
            3,
            SampleFormat::F32,
            Samples::F32(other.to_rgb32f().into_raw()),
        ),
    };
    Ok(RawDecoded {
        width,
        height,
        channels,
        stride,
        format,
        samples,
        raw: None,
    })
}

/// The image formats this tool reads, for messages.
pub const READ_FORMATS: &str = "EXR (half/float), PNG and TIFF (8/16-bit, grey or RGB), JPEG (8-bit sRGB) and camera RAW (DNG, CR2, CR3, NEF, ARW, RAF, ORF, RW2, PEF, …)";

/// Whether `path` names a JPEG file (by its extension): lossy 8-bit sRGB, read whole only.
pub fn is_jpeg(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("jpg") || e.eq_ignore_ascii_case("jpeg"))
}

/// Most samples (pixels × channels) of one image file this tool decodes: 2²⁸, 1 GiB as f32,
/// far above real captures (50 Mpx RGB is 1.5·10⁸), and a guard against headers that declare
/// sizes no file holds.
pub const MAX_IMAGE_SAMPLES: usize = 1 << 28;

/// Decodes an image file (EXR, PNG, TIFF or JPEG) to interleaved floats: integers scaled to [0, 1],
/// no transfer function applied, alpha dropped.
///
/// # Errors
/// [`Error::Io`], [`Error::Decode`] or [`Error::UnsupportedImage`] naming the file.
pub fn read_image(path: &Path) -> Result<DecodedImage> {
    let raw = decode_raw(path, None)?;
    let n = raw.width * raw.height;
    let mut data = Vec::with_capacity(n * raw.channels);
    for i in 0..n {
        for c in 0..raw.channels {
            let j = i * raw.stride + c;
            data.push(match &raw.samples {
                Samples::U8(s) => f32::from(s[j]) * (1.0 / 255.0),
                Samples::U16(s) => f32::from(s[j]) * (1.0 / 65535.0),
                Samples::U16Be(s) => {
                    f32::from(u16::from_be_bytes([s[2 * j], s[2 * j + 1]])) * (1.0 / 65535.0)
                }
                Samples::F32(s) => s[j],
            });
        }
    }
    Ok(DecodedImage {
        width: raw.width,
        height: raw.height,
        channels: raw.channels,
        format: raw.format,
        data,
    })
}

/// Reads a normal map: an EXR (or float TIFF) with R, G, B = n_x, n_y, n_z as stored, or an 8/16-bit
/// PNG/TIFF encoded n = 2v − 1 with v the code scaled to [0, 1] (renormalised, as quantisation
/// shortens the vectors; all-zero codes — the usual background — become NaN).
///
/// # Errors
/// As [`read_image`]; [`Error::UnsupportedImage`] when the image does not have 3 channels.
pub fn read_normal_map(path: &Path) -> Result<NormalMap> {
    let img = read_image(path)?;
    if img.channels != 3 {
        return Err(Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!(
                "a normal map needs 3 channels (R, G, B = n_x, n_y, n_z), found {}",
                img.channels
            ),
        });
    }
    let encoded = img.format.is_integer();
    let normals = img
        .data
        .chunks_exact(3)
        .map(|c| {
            let v = Vector3::new(c[0], c[1], c[2]);
            if !encoded {
                v
            } else if v == Vector3::zeros() {
                Vector3::repeat(f32::NAN)
            } else {
                (v * 2.0 - Vector3::repeat(1.0)).normalize()
            }
        })
        .collect();
    Grid::from_vec(img.width, img.height, normals)
}

/// Reads a mask image: a pixel belongs to the object when any channel is > 0.
///
/// # Errors
/// As [`read_image`]; [`Error::Mask`] when the mask is empty.
pub fn read_mask(path: &Path) -> Result<Mask> {
    let img = read_image(path)?;
    let data: Vec<bool> = img
        .data
        .chunks_exact(img.channels)
        .map(|px| px.iter().any(|v| *v > 0.0))
        .collect();
    let mask = Grid::from_vec(img.width, img.height, data)?;
    if mask.count() == 0 {
        return Err(Error::Mask {
            path: path.to_path_buf(),
            reason: "no pixel is set (object pixels must be > 0)".into(),
        });
    }
    Ok(mask)
}

/// Width and height of an image file, from its header.
///
/// # Errors
/// [`Error::Io`] or [`Error::Decode`] naming the file.
pub fn image_size(path: &Path) -> Result<(usize, usize)> {
    let is_exr = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    if is_exr {
        let (meta, _) = crate::io::exr::read_exr_meta(path, crate::io::input::MAX_STREAM_SAMPLES)?;
        let header = meta.headers.first().ok_or_else(|| Error::Decode {
            path: path.to_path_buf(),
            reason: "no layer in file".into(),
        })?;
        return Ok((header.layer_size.width(), header.layer_size.height()));
    }
    if crate::io::raw::is_raw(path) {
        // The developed size (2x2 quads of the active area) is known only after decoding.
        let (d, _) = crate::io::raw::decode(path)?;
        return Ok((d.width, d.height));
    }
    use image::ImageDecoder as _;
    let (w, h) = generic_decoder(path, crate::io::input::MAX_STREAM_SAMPLES)?.dimensions();
    Ok((w as usize, h as usize))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trip_and_known_points() {
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
        for i in 0..=100 {
            let v = i as f32 / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-5);
        }
    }
}
