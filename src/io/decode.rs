//! Decoding image files: EXR (half/float), PNG and TIFF (8/16 bit), grey or RGB, to samples
//! as stored (integers scaled to [0, 1], no transfer function), and the readers of masks,
//! normal maps and single EXR channels. The sRGB transfer function is here too: it is how
//! 8-bit files are encoded.

use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap};
use nalgebra::Vector3;
use serde::Serialize;
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
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    let img = reader.decode().map_err(|e| match e {
        image::ImageError::IoError(io) => Error::io(path, io),
        image::ImageError::Unsupported(u) => Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!("{u}; PNG and TIFF (8/16-bit, grey or RGB) and EXR are read"),
        },
        other => Error::Decode {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    })?;
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
    })
}

/// PNG through the `png` crate directly: 16-bit samples stay in the decoder's big-endian buffer.
/// With `rows`, a non-interlaced image is decoded only up to the end of the range (the rows
/// below stay zero, and the rest of the stream is not read).
fn decode_png(path: &Path, rows: Option<Range<usize>>) -> Result<RawDecoded> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
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
    let mut decoder = png::Decoder::new_with_limits(std::io::Cursor::new(bytes), limits);
    // Palette → RGB, grey below 8 bits → 8 bits, transparency chunk → alpha.
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(bad)?;
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
            reader.output_color_type()
        }
        _ => {
            let info = reader.next_frame(&mut buf).map_err(bad)?;
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
    })
}

/// Most samples (pixels × channels) of one image file this tool decodes: 2²⁸, 1 GiB as f32,
/// far above real captures (50 Mpx RGB is 1.5·10⁸), and a guard against headers that declare
/// sizes no file holds.
pub const MAX_IMAGE_SAMPLES: usize = 1 << 28;

/// The first valid layer of an EXR file with all its channels.
fn read_exr_layer(
    path: &Path,
) -> Result<exr::image::Image<exr::image::Layer<exr::image::AnyChannels<exr::image::FlatSamples>>>>
{
    use exr::prelude::*;
    // The header is checked before the decoder allocates what it declares.
    let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|e| match e {
        exr::error::Error::Io(io) => crate::Error::io(path, io),
        other => crate::Error::Decode {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    })?;
    for header in &meta.headers {
        let samples = header
            .layer_size
            .area()
            .saturating_mul(header.channels.list.len());
        if samples > MAX_IMAGE_SAMPLES {
            return Err(crate::Error::UnsupportedImage {
                path: path.to_path_buf(),
                reason: format!(
                    "the header declares {}x{} pixels × {} channels, more than the {MAX_IMAGE_SAMPLES} samples this tool reads",
                    header.layer_size.width(),
                    header.layer_size.height(),
                    header.channels.list.len()
                ),
            });
        }
    }
    read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|e| match e {
            exr::error::Error::Io(io) => crate::Error::io(path, io),
            other => crate::Error::Decode {
                path: path.to_path_buf(),
                reason: other.to_string(),
            },
        })
}

fn decode_exr(path: &Path) -> Result<RawDecoded> {
    use exr::prelude::*;
    let image = read_exr_layer(path)?;
    let layer = &image.layer_data;
    let (width, height) = (layer.size.width(), layer.size.height());
    let list = &layer.channel_data.list;
    let find = |name: &str| list.iter().find(|c| c.name.to_string() == name);
    let chosen: Vec<_> = match (find("R"), find("G"), find("B")) {
        (Some(r), Some(g), Some(b)) => vec![r, g, b],
        _ => {
            if let Some(y) = find("Y").or_else(|| find("Z")) {
                vec![y]
            } else if list.len() == 1 {
                vec![&list[0]]
            } else {
                let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
                return Err(crate::Error::UnsupportedImage {
                    path: path.to_path_buf(),
                    reason: format!(
                        "channels {names:?}: expected R, G, B, or a single channel (Y, Z or any one)"
                    ),
                });
            }
        }
    };
    let mut format = SampleFormat::F32;
    for c in &chosen {
        if c.sampling != Vec2(1, 1) {
            return Err(crate::Error::UnsupportedImage {
                path: path.to_path_buf(),
                reason: format!("channel {} is subsampled", c.name),
            });
        }
        if matches!(c.sample_data, FlatSamples::F16(_)) {
            format = SampleFormat::F16;
        }
    }
    let n = width * height;
    let channels = chosen.len();
    let mut data = vec![0f32; n * channels];
    for (ci, c) in chosen.iter().enumerate() {
        for (i, v) in c.sample_data.values_as_f32().enumerate().take(n) {
            data[i * channels + ci] = v;
        }
    }
    Ok(RawDecoded {
        width,
        height,
        channels,
        stride: channels,
        format,
        samples: Samples::F32(data),
    })
}

/// Reads the channel `name` of an EXR file (float or half) as a map — for multi-channel data
/// files such as depth plus gradients.
///
/// # Errors
/// [`Error::Io`] or [`Error::Decode`] naming the file; [`Error::UnsupportedImage`] listing the
/// channels when `name` is not one of them.
pub fn read_exr_channel(path: &Path, name: &str) -> Result<crate::grid::ScalarMap> {
    use exr::prelude::*;
    let image = read_exr_layer(path)?;
    let layer = &image.layer_data;
    let list = &layer.channel_data.list;
    let Some(ch) = list.iter().find(|c| c.name.to_string() == name) else {
        let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
        return Err(crate::Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!("no channel {name:?}; channels are {names:?}"),
        });
    };
    if ch.sampling != Vec2(1, 1) {
        return Err(crate::Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!("channel {name} is subsampled"),
        });
    }
    let (w, h) = (layer.size.width(), layer.size.height());
    Grid::from_vec(w, h, ch.sample_data.values_as_f32().take(w * h).collect())
}

/// Decodes an image file (EXR, PNG or TIFF) to interleaved floats: integers scaled to [0, 1],
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
        let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|e| match e {
            exr::error::Error::Io(io) => Error::io(path, io),
            other => Error::Decode {
                path: path.to_path_buf(),
                reason: other.to_string(),
            },
        })?;
        let header = meta.headers.first().ok_or_else(|| Error::Decode {
            path: path.to_path_buf(),
            reason: "no layer in file".into(),
        })?;
        return Ok((header.layer_size.width(), header.layer_size.height()));
    }
    let (w, h) = image::ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?
        .into_dimensions()
        .map_err(|e| Error::Decode {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
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
