//! Reading images into linear-radiance stacks: EXR (half/float), PNG and TIFF (8/16 bit).
//!
//! Integer images are scaled to [0, 1] by their maximum code (16-bit data keeps all 16 bits).
//! 8-bit images are normally gamma-encoded, so by default they are linearised with the sRGB
//! transfer function (IEC 61966-2-1); [`Transfer::Linear`] keeps them as they are. Each image is
//! divided by its light's intensity per channel, then either mixed to grey with the BT.601
//! weights [`GREY_WEIGHTS`] or kept as three channels for a per-channel solve.

use crate::capture::lights::Lights;
use crate::error::{Error, Result};
use crate::grid::Window;
use crate::io::decode::{
    MAX_IMAGE_SAMPLES, RawDecoded, SampleFormat, Samples, decode_raw, image_size, srgb_to_linear,
};
use crate::progress::Progress;
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// BT.601 luma weights (R, G, B) used to mix colour images to grey.
pub const GREY_WEIGHTS: [f32; 3] = [0.299, 0.587, 0.114];

/// The transfer function that maps stored values to linear radiance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Transfer {
    /// sRGB for 8-bit files, linear for everything else.
    #[default]
    Auto,
    /// Values are linear radiance already.
    Linear,
    /// Values are sRGB-encoded (decoded with the sRGB EOTF).
    Srgb,
}

/// Whether colour stacks are mixed to grey or solved per channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColorMode {
    /// Divide each channel by its light intensity, then mix with [`GREY_WEIGHTS`].
    #[default]
    Grey,
    /// Keep R, G and B (each divided by its intensity) for a colour solve
    /// ([`crate::ps::color::ColorSolve`]: one shared normal, or three separate solves).
    /// Reported as `"rgb"`.
    #[serde(rename = "rgb")]
    PerChannel,
}

/// Options for [`load_stack`].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct LoadOptions {
    /// Grey mix or per-channel planes.
    pub color: ColorMode,
    /// Transfer function of the stored values.
    pub transfer: Transfer,
    /// Stored value (after scaling integers to [0, 1], before linearisation) at or above which a
    /// sample counts as saturated. `None`: the maximum code for integer files, no limit for floats.
    pub saturation: Option<f32>,
    /// Keep only this window of every image (clamped to its size): the stack stores just the
    /// window, and a PNG is not decoded past its last row. [`crate::capture::dataset::Capture`] sets it
    /// to its mask's bounding box. `None`: the whole image.
    pub window: Option<Window>,
}

/// What a loaded image was and what loading found in it.
#[derive(Debug, Clone, Serialize)]
pub struct ImageInfo {
    /// The file.
    pub path: PathBuf,
    /// Its storage format.
    pub format: SampleFormat,
    /// Channels in the file (alpha excluded).
    pub channels: usize,
    /// Whether the sRGB transfer function was undone.
    pub linearised: bool,
    /// Pixels of the stored window with at least one saturated channel.
    pub saturated: usize,
    /// Pixels of the stored window with a NaN or infinite value (excluded from solves).
    pub non_finite: usize,
    /// How a camera RAW file was developed (`None` for other formats).
    pub raw: Option<crate::io::raw::RawDevelopment>,
}

/// A stack of equally sized single- or three-channel images in linear radiance, each divided by
/// its light's intensity. Layout: image-major, then channel, then the row-major pixels of
/// [`ImageStack::window`] (the whole image, or the part a mask spans).
#[derive(Debug, Clone)]
pub struct ImageStack {
    width: usize,
    height: usize,
    count: usize,
    channels: usize,
    data: Vec<f32>,
    saturated: Vec<Option<Vec<u64>>>,
    info: Vec<ImageInfo>,
    /// The part of each image that is stored (see [`ImageStack::plane`]).
    window: Window,
}

/// Per-image conversion parameters.
pub(crate) struct Convert<'a> {
    transfer: Transfer,
    saturation: Option<f32>,
    intensity: [f32; 3],
    srgb_lut: &'a [f32; 256],
}

impl<'a> Convert<'a> {
    /// The conversion of image `index`: `options`' transfer function and saturation level,
    /// divided by its light's intensity.
    pub(crate) fn new(
        options: &LoadOptions,
        lights: &Lights,
        index: usize,
        srgb_lut: &'a [f32; 256],
    ) -> Self {
        Convert {
            transfer: options.transfer,
            saturation: options.saturation,
            intensity: lights.lights()[index].intensity.map(|v| v as f32),
            srgb_lut,
        }
    }
}

/// Tallies of one conversion.
pub(crate) struct Converted {
    /// Saturation flags, one bit per whole-image pixel.
    pub(crate) bits: Vec<u64>,
    /// Pixels with a saturated colour sample.
    pub(crate) saturated: usize,
    /// Pixels with a non-finite colour sample.
    pub(crate) non_finite: usize,
}

/// Coefficients of a conversion: 1/intensity per channel, times the grey weight for a grey
/// output (`out_channels` 1); a grey source (`channels` 1) is divided by the grey-mixed
/// intensity.
pub(crate) fn coefficients(channels: usize, out_channels: usize, intensity: [f32; 3]) -> [f32; 3] {
    if channels == 1 {
        let grey: f32 = GREY_WEIGHTS
            .iter()
            .zip(&intensity)
            .map(|(w, i)| w * i)
            .sum();
        [1.0 / grey; 3]
    } else if out_channels == 1 {
        [0, 1, 2].map(|c| GREY_WEIGHTS[c] / intensity[c])
    } else {
        intensity.map(|i| 1.0 / i)
    }
}

/// Where one converted row goes: planes of `n` values, `out_channels` of them, the row
/// starting at `offset` in each plane and at whole-image pixel `pixel`.
pub(crate) struct RowPlace {
    pub(crate) out_channels: usize,
    pub(crate) n: usize,
    pub(crate) offset: usize,
    pub(crate) pixel: usize,
}

/// [`combine_row`] for a row of `stride` interleaved values per pixel (1 grey, 2 grey and
/// alpha, 3 RGB, 4 RGBA); `scale` is the coefficients and the saturation level.
#[allow(clippy::too_many_arguments)]
pub(crate) fn combine_any(
    stride: usize,
    stored: &[f32],
    linear: &[f32],
    scale: ([f32; 3], f32),
    out: &mut [f32],
    row: &RowPlace,
    row_max: f32,
    check_finite: bool,
    c: &mut Converted,
) {
    let (coef, level) = scale;
    let (n, offset, pixel) = (row.n, row.offset, row.pixel);
    macro_rules! go {
        ($s:literal, $ci:literal, $co:literal) => {
            combine_row::<$s, $ci, $co>(
                stored,
                linear,
                coef,
                level,
                out,
                n,
                offset,
                pixel,
                row_max,
                check_finite,
                c,
            )
        };
    }
    match (stride, row.out_channels) {
        (1, _) => go!(1, 1, 1),
        (2, _) => go!(2, 1, 1),
        (3, 1) => go!(3, 3, 1),
        (3, _) => go!(3, 3, 3),
        (_, 1) => go!(4, 3, 1),
        _ => go!(4, 3, 3),
    }
}

/// Combines one row: `stored` and `linear` hold `STRIDE` values per pixel of which the first
/// `CIN` are colour; writes `COUT` planes at `out[k * n + offset + x]`. Saturated when a stored
/// colour value ≥ `level` (bit `pixel + x` of the image's flags); pixels with a non-finite value
/// become NaN. The arithmetic runs as a straight loop; saturation and finiteness are checked per
/// pixel only in rows that need it.
#[allow(clippy::too_many_arguments)]
fn combine_row<const STRIDE: usize, const CIN: usize, const COUT: usize>(
    stored: &[f32],
    linear: &[f32],
    coef: [f32; 3],
    level: f32,
    out: &mut [f32],
    n: usize,
    offset: usize,
    pixel: usize,
    row_max: f32,
    check_finite: bool,
    c: &mut Converted,
) {
    let w = linear.len() / STRIDE;
    if COUT == 1 {
        let dst = &mut out[offset..offset + w];
        for (d, l) in dst.iter_mut().zip(linear.chunks_exact(STRIDE)) {
            *d = if CIN == 1 {
                l[0] * coef[0]
            } else {
                l[0] * coef[0] + l[1] * coef[1] + l[2] * coef[2]
            };
        }
    } else {
        for (k, ck) in coef.iter().enumerate() {
            let dst = &mut out[k * n + offset..k * n + offset + w];
            for (d, l) in dst.iter_mut().zip(linear.chunks_exact(STRIDE)) {
                *d = l[k] * ck;
            }
        }
    }
    // An infinite level means no saturation limit (float data without `--saturation`).
    if level.is_finite() && row_max >= level {
        for (x, s) in stored.chunks_exact(STRIDE).enumerate() {
            if s[..CIN].iter().any(|v| *v >= level) {
                let i = pixel + x;
                c.bits[i >> 6] |= 1 << (i & 63);
                c.saturated += 1;
            }
        }
    }
    // Finiteness of the stored values (the sRGB curve clamps, so the linear ones would hide
    // infinities). Non-short-circuiting so that it vectorises.
    if check_finite && !stored.iter().fold(true, |a, v| a & v.is_finite()) {
        for (x, s) in stored.chunks_exact(STRIDE).enumerate() {
            if !s[..CIN].iter().all(|v| v.is_finite()) {
                c.non_finite += 1;
                for k in 0..COUT {
                    out[k * n + offset + x] = f32::NAN;
                }
            }
        }
    }
}

/// Converts window `window` of `raw` into `out` (planes of the stack's layout, each
/// `window.len()` long); saturation flags are indexed by whole-image pixel.
pub(crate) fn convert_into(
    raw: &RawDecoded,
    cv: &Convert,
    out: &mut [f32],
    path: &Path,
    window: Window,
) -> (Option<Vec<u64>>, ImageInfo) {
    let (w, h) = (raw.width, raw.height);
    let (n, ww) = (window.len(), window.width());
    let linearise = match cv.transfer {
        Transfer::Auto => raw.format == SampleFormat::U8,
        Transfer::Linear => false,
        Transfer::Srgb => true,
    };
    let level = cv
        .saturation
        .or(raw.format.is_integer().then_some(1.0))
        .unwrap_or(f32::INFINITY);
    let out_channels = out.len() / n.max(1);
    let coef = coefficients(raw.channels, out_channels, cv.intensity);
    let row_len = w * raw.stride;
    let mut stored = vec![0f32; ww * raw.stride];
    let mut linear = vec![0f32; if linearise { stored.len() } else { 0 }];
    let mut c = Converted {
        bits: vec![0u64; (w * h).div_ceil(64)],
        saturated: 0,
        non_finite: 0,
    };
    for y in window.y0..window.y1 {
        let r = y * row_len + window.x0 * raw.stride..y * row_len + window.x1 * raw.stride;
        // Stored values scaled to [0, 1], and the row's largest (in integer codes where possible,
        // which vectorises; NaN for float rows, whose finiteness is then checked).
        let row_max = match &raw.samples {
            Samples::U8(s) => {
                for (d, v) in stored.iter_mut().zip(&s[r.clone()]) {
                    *d = f32::from(*v) * (1.0 / 255.0);
                }
                if linearise {
                    for (d, v) in linear.iter_mut().zip(&s[r.clone()]) {
                        *d = cv.srgb_lut[*v as usize];
                    }
                }
                f32::from(s[r].iter().fold(0u8, |m, v| m.max(*v))) / 255.0
            }
            Samples::U16(s) => {
                for (d, v) in stored.iter_mut().zip(&s[r.clone()]) {
                    *d = f32::from(*v) * (1.0 / 65535.0);
                }
                f32::from(s[r].iter().fold(0u16, |m, v| m.max(*v))) / 65535.0
            }
            Samples::U16Be(s) => {
                let bytes = &s[2 * r.start..2 * r.end];
                let mut mx = 0u16;
                for (d, b) in stored.iter_mut().zip(bytes.chunks_exact(2)) {
                    let code = u16::from_be_bytes([b[0], b[1]]);
                    mx = mx.max(code);
                    *d = f32::from(code) * (1.0 / 65535.0);
                }
                f32::from(mx) / 65535.0
            }
            Samples::F32(s) => {
                stored.copy_from_slice(&s[r]);
                f32::NAN
            }
        };
        if linearise && !matches!(raw.samples, Samples::U8(_)) {
            for (d, v) in linear.iter_mut().zip(&stored) {
                *d = srgb_to_linear(v.clamp(0.0, 1.0));
            }
        }
        let lin: &[f32] = if linearise { &linear } else { &stored };
        // Float rows (NaN row_max): saturation is decided per pixel against `level`, and
        // finiteness checked; integers are always finite.
        let check_finite = row_max.is_nan();
        let row_max = if check_finite { level } else { row_max };
        let row = RowPlace {
            out_channels,
            n,
            offset: (y - window.y0) * ww,
            pixel: y * w + window.x0,
        };
        combine_any(
            raw.stride,
            &stored,
            lin,
            (coef, level),
            out,
            &row,
            row_max,
            check_finite,
            &mut c,
        );
    }
    let info = ImageInfo {
        path: path.to_path_buf(),
        format: raw.format,
        channels: raw.channels,
        linearised: linearise,
        saturated: c.saturated,
        non_finite: c.non_finite,
        raw: raw.raw.clone(),
    };
    ((c.saturated > 0).then_some(c.bits), info)
}

/// Loads `paths` (one per light, in the order of `lights`) into a stack, dividing each image by
/// its light's intensity. Images are decoded in parallel.
///
/// # Errors
/// The errors of [`crate::io::decode::read_image`]; [`Error::SizeMismatch`] when an image's size differs from the
/// first; [`Error::LightsMismatch`] when counts differ; [`Error::UnsupportedImage`] when a
/// per-channel load meets a grey image.
pub fn load_stack(
    paths: &[PathBuf],
    lights: &Lights,
    options: &LoadOptions,
    progress: &dyn Progress,
) -> Result<ImageStack> {
    load_stack_with_ambient(paths, lights, None, options, progress)
}

/// [`load_stack`] with an ambient image subtracted: `ambient`, the scene photographed with
/// every lamp off (room light, the camera's black level, a screen's glow), is decoded once,
/// converted as each image is (its transfer function, then divided by that image's light
/// intensity) and subtracted from it, so that each image holds only its own lamp's light, as
/// Lambert's law I = ρ n·l assumes. Photometric stereo has no term for light that every image
/// shares: left in, it lifts every shadow and flattens the normals towards the mean light
/// direction. A pixel saturated in the ambient image is counted saturated in every image
/// (its lamp's share there is unknown). Values may fall slightly below 0 after the
/// subtraction (noise); they are kept, so that the noise stays unbiased.
///
/// # Errors
/// As [`load_stack`]; [`Error::Ambient`] when the ambient image's size, colour channels or
/// sample format differ from the images'.
pub fn load_stack_with_ambient(
    paths: &[PathBuf],
    lights: &Lights,
    ambient: Option<&Path>,
    options: &LoadOptions,
    progress: &dyn Progress,
) -> Result<ImageStack> {
    if paths.len() != lights.len() {
        return Err(Error::LightsMismatch {
            reason: format!("{} images for {} lights", paths.len(), lights.len()),
        });
    }
    let Some(first_path) = paths.first() else {
        return Err(Error::TooFewImages { count: 0 });
    };
    let (width, height) = image_size(first_path)?;
    if width.saturating_mul(height) > MAX_IMAGE_SAMPLES {
        return Err(Error::UnsupportedImage {
            path: first_path.clone(),
            reason: format!(
                "{width}x{height} pixels, more than the {MAX_IMAGE_SAMPLES} this tool reads"
            ),
        });
    }
    let window = stored_window(options.window, width, height)?;
    let n = window.len();
    let channels = match options.color {
        ColorMode::Grey => 1,
        ColorMode::PerChannel => 3,
    };
    let lut = srgb_lut();
    let ambient = ambient
        .map(|path| {
            let raw = decode_raw(path, Some(0..window.y1))?;
            check_ambient_size(path, (raw.width, raw.height), (width, height))?;
            Ok::<_, Error>((path, raw))
        })
        .transpose()?;
    progress.begin("load", paths.len() as u64);
    let mut data = crate::buffer::zeroed_f32(paths.len() * channels * n);
    let results: Vec<Result<(Option<Vec<u64>>, ImageInfo)>> = data
        .par_chunks_mut(channels * n)
        .zip(paths.par_iter())
        .enumerate()
        .map(|(index, (out, path))| {
            let raw = decode_raw(path, Some(0..window.y1))?;
            if (raw.width, raw.height) != (width, height) {
                return Err(Error::SizeMismatch {
                    path: path.clone(),
                    index,
                    width,
                    height,
                    found_width: raw.width,
                    found_height: raw.height,
                });
            }
            if channels == 3 && raw.channels != 3 {
                return Err(Error::UnsupportedImage {
                    path: path.clone(),
                    reason: format!(
                        "image {index} has {} channel(s); a per-channel solve needs RGB images",
                        raw.channels
                    ),
                });
            }
            let cv = Convert::new(options, lights, index, &lut);
            let mut r = convert_into(&raw, &cv, out, path, window);
            if let Some((apath, araw)) = &ambient {
                subtract_ambient(araw, apath, &raw, &cv, out, window, &mut r)?;
            }
            progress.advance(1);
            // Where the verdicts below apply, for their messages.
            let where_ = || {
                if window == Window::full(width, height) {
                    String::new()
                } else {
                    format!(" in the part the mask spans ({window})")
                }
            };
            check_usable(out, r.1.saturated, window.len(), path, index, where_)?;
            Ok(r)
        })
        .collect();
    progress.end();
    let mut saturated = Vec::with_capacity(paths.len());
    let mut info: Vec<ImageInfo> = Vec::with_capacity(paths.len());
    for r in results {
        let (s, i) = r?;
        saturated.push(s);
        info.push(i);
    }
    // Grey and colour files do not mix: the grey mix of an RGB file and a grey file are not
    // the same measurement.
    if let Some(first) = info.first()
        && let Some((index, odd)) = info
            .iter()
            .enumerate()
            .find(|(_, i)| i.channels != first.channels)
    {
        return Err(Error::BadImage {
            path: odd.path.clone(),
            index,
            reason: format!(
                "it has {} colour channel(s) but image 0 ({}) has {}; all images must be grey or all RGB",
                odd.channels,
                first.path.display(),
                first.channels
            ),
        });
    }
    Ok(ImageStack {
        width,
        height,
        count: paths.len(),
        channels,
        data,
        saturated,
        info,
        window,
    })
}

/// Refuses an ambient image (`path`, of `size` pixels) whose size is not the images'
/// (`images`, width and height).
pub(crate) fn check_ambient_size(
    path: &Path,
    size: (usize, usize),
    images: (usize, usize),
) -> Result<()> {
    if size != images {
        return Err(Error::Ambient {
            path: path.to_path_buf(),
            reason: format!(
                "size {}x{} differs from the images' {}x{}",
                size.0, size.1, images.0, images.1
            ),
        });
    }
    Ok(())
}

/// Subtracts the ambient image `ambient` (decoded from `path`; the same rows as `image`),
/// converted by image `image`'s conversion `cv`, from that image's converted planes `out`
/// (window `window`), and counts the pixels saturated in the ambient image as saturated in the
/// image (`converted`: its saturation flags and what loading found).
pub(crate) fn subtract_ambient(
    ambient: &RawDecoded,
    path: &Path,
    image: &RawDecoded,
    cv: &Convert,
    out: &mut [f32],
    window: Window,
    converted: &mut (Option<Vec<u64>>, ImageInfo),
) -> Result<()> {
    let (bits, info) = converted;
    let refuse = |reason: String| Error::Ambient {
        path: path.to_path_buf(),
        reason,
    };
    if ambient.channels != image.channels {
        return Err(refuse(format!(
            "it has {} colour channel(s) but {} has {}; it must be taken as the images are",
            ambient.channels,
            info.path.display(),
            image.channels
        )));
    }
    // A camera RAW file is developed with its own levels and white balance; beside other
    // files it is another measurement.
    if ambient.raw.is_some() != image.raw.is_some() {
        return Err(refuse(format!(
            "it is {}a camera RAW file but {} is {}; it must be taken and stored as the images are",
            if ambient.raw.is_some() { "" } else { "not " },
            info.path.display(),
            if image.raw.is_some() { "one" } else { "not" }
        )));
    }
    // Integer codes are scaled by their format's largest code: an 8-bit frame beside 16-bit
    // images (or float ones) is another measurement. Half and single floats are one scale.
    if ambient.format != image.format && (ambient.format.is_integer() || image.format.is_integer())
    {
        let name = |f: SampleFormat| match f {
            SampleFormat::U8 => "8-bit",
            SampleFormat::U16 => "16-bit",
            SampleFormat::F16 | SampleFormat::F32 => "floating-point",
        };
        return Err(refuse(format!(
            "it is stored {} but {} is {}; it must be taken and stored as the images are",
            name(ambient.format),
            info.path.display(),
            name(image.format)
        )));
    }
    let mut light = vec![0f32; out.len()];
    let (abits, ainfo) = convert_into(ambient, cv, &mut light, path, window);
    take_off_frame(out, &light, path, ainfo.non_finite)?;
    if let Some(abits) = abits {
        let merged = bits.get_or_insert_with(|| vec![0u64; abits.len()]);
        info.saturated = mark_frame_saturation(merged, &abits);
    }
    Ok(())
}

/// Takes an ambient frame, converted as the image was (`light`), off that image's converted
/// planes `out`; a frame with `non_finite` pixels holding NaN or infinite values is refused
/// (`path` names it). The files' and the arrays' loads both subtract through it.
pub(crate) fn take_off_frame(
    out: &mut [f32],
    light: &[f32],
    path: &Path,
    non_finite: usize,
) -> Result<()> {
    if non_finite > 0 {
        return Err(Error::Ambient {
            path: path.to_path_buf(),
            reason: format!(
                "{non_finite} pixel(s) hold NaN or infinite values; an ambient image must be finite where the images are solved"
            ),
        });
    }
    for (o, l) in out.iter_mut().zip(light) {
        *o -= l;
    }
    Ok(())
}

/// Marks the pixels saturated in an ambient frame (`frame`, its flags) as saturated in an
/// image (`bits`, its flags, over the same pixels); returns the image's saturated pixels.
pub(crate) fn mark_frame_saturation(bits: &mut [u64], frame: &[u64]) -> usize {
    for (m, f) in bits.iter_mut().zip(frame) {
        *m |= f;
    }
    bits.iter().map(|w| w.count_ones() as usize).sum()
}

/// The part of `width`×`height` images a load stores: `window` clamped to them (refused when
/// it holds no pixel of them), or the whole images.
pub(crate) fn stored_window(window: Option<Window>, width: usize, height: usize) -> Result<Window> {
    match window {
        Some(win) => {
            let clamped = win.clamp(width, height);
            if clamped.is_empty() {
                return Err(Error::param(
                    "window",
                    format!("{win} holds no pixel of the {width}×{height} images"),
                ));
            }
            Ok(clamped)
        }
        None => Ok(Window::full(width, height)),
    }
}

/// Refuses a converted image (`out`, its planes) that is entirely dark or whose every pixel of
/// the `stored` stored ones is saturated; `where_` says which part of the image was stored.
pub(crate) fn check_usable(
    out: &[f32],
    saturated: usize,
    stored: usize,
    path: &Path,
    index: usize,
    where_: impl Fn() -> String,
) -> Result<()> {
    // NaN compares false: an image of NaN counts as dark.
    if !out.iter().any(|v| *v > 0.0) {
        return Err(Error::BadImage {
            path: path.to_path_buf(),
            index,
            reason: format!(
                "the image is entirely dark{}: no sample above 0, so it says nothing about the shape; check the exposure, or remove it and its light",
                where_()
            ),
        });
    }
    if saturated >= stored {
        return Err(Error::BadImage {
            path: path.to_path_buf(),
            index,
            reason: format!(
                "every pixel is saturated{}; lower the exposure, or remove the image and its light",
                where_()
            ),
        });
    }
    Ok(())
}

/// Linear value of each 8-bit sRGB code.
pub(crate) fn srgb_lut() -> [f32; 256] {
    let mut lut = [0f32; 256];
    for (code, v) in lut.iter_mut().enumerate() {
        *v = srgb_to_linear(code as f32 / 255.0);
    }
    lut
}

impl ImageStack {
    /// A stack from converted planes (the layout of [`ImageStack`]) and what loading found: the
    /// band stacks of [`crate::run::stream`].
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn from_parts(
        width: usize,
        height: usize,
        channels: usize,
        data: Vec<f32>,
        saturated: Vec<Option<Vec<u64>>>,
        info: Vec<ImageInfo>,
        window: Window,
    ) -> Self {
        ImageStack {
            width,
            height,
            count: info.len(),
            channels,
            data,
            saturated,
            info,
            window,
        }
    }

    /// A stack from in-memory images (e.g. rendered ones): `images[k]` holds `channels` planes of
    /// `width * height` linear values, already divided by the light intensities.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when an image has the wrong length or `channels` is not 1 or 3.
    pub fn from_images(
        width: usize,
        height: usize,
        channels: usize,
        images: Vec<Vec<f32>>,
    ) -> Result<Self> {
        if channels != 1 && channels != 3 {
            return Err(Error::param(
                "channels",
                format!("{channels} channels; 1 or 3 expected"),
            ));
        }
        let n = width * height;
        let mut data = Vec::with_capacity(images.len() * channels * n);
        let mut info = Vec::with_capacity(images.len());
        for (k, img) in images.iter().enumerate() {
            if img.len() != channels * n {
                return Err(Error::param(
                    "images",
                    format!(
                        "image {k} has {} values, {} expected for {width}x{height}x{channels}",
                        img.len(),
                        channels * n
                    ),
                ));
            }
            // Infinite samples become NaN, which every solver skips.
            data.extend(
                img.iter()
                    .map(|v| if v.is_finite() { *v } else { f32::NAN }),
            );
            info.push(ImageInfo {
                path: PathBuf::from(format!("<memory {k}>")),
                format: SampleFormat::F32,
                channels,
                linearised: false,
                saturated: 0,
                non_finite: img.iter().filter(|v| !v.is_finite()).count(),
                raw: None,
            });
        }
        Ok(ImageStack {
            width,
            height,
            count: images.len(),
            channels,
            data,
            saturated: vec![None; images.len()],
            info,
            window: Window::full(width, height),
        })
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Number of images.
    pub fn count(&self) -> usize {
        self.count
    }

    /// Channels per image (1 or 3).
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Pixels per image.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }

    /// The part of each image that is stored: the whole image, or the window it was loaded
    /// with ([`LoadOptions::window`]).
    pub fn window(&self) -> Window {
        self.window
    }

    /// Channel `channel` of image `image` inside [`ImageStack::window`], row-major and
    /// `window().width()` wide: pixel `p` of the image (`y * width + x`) is at
    /// `window().local(width, p)`.
    ///
    /// # Panics
    /// When `image >= count()` or `channel >= channels()`.
    pub fn plane(&self, image: usize, channel: usize) -> &[f32] {
        let n = self.window.len();
        let start = (image * self.channels + channel) * n;
        &self.data[start..start + n]
    }

    /// The stack of images `images` (indices into this one, in the order given; repeats
    /// allowed), with their saturation flags and load records: for asking what fewer lights
    /// would have given.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`images`) when the list is empty or an index is out of
    /// range.
    pub fn select(&self, images: &[usize]) -> Result<ImageStack> {
        if images.is_empty() {
            return Err(Error::param("images", "no image selected"));
        }
        if let Some(k) = images.iter().find(|k| **k >= self.count) {
            return Err(Error::param(
                "images",
                format!("index {k} is out of range for a stack of {}", self.count),
            ));
        }
        let n = self.window.len() * self.channels;
        let mut data = Vec::with_capacity(n * images.len());
        for &k in images {
            data.extend_from_slice(&self.data[k * n..(k + 1) * n]);
        }
        Ok(ImageStack::from_parts(
            self.width,
            self.height,
            self.channels,
            data,
            images.iter().map(|&k| self.saturated[k].clone()).collect(),
            images.iter().map(|&k| self.info[k].clone()).collect(),
            self.window,
        ))
    }

    /// Index in [`ImageStack::plane`] of pixel `pixel` of the image; `None` outside the window.
    pub fn local(&self, pixel: usize) -> Option<usize> {
        self.window.local(self.width, pixel)
    }

    /// The value of pixel `pixel` of channel `channel` of image `image`: NaN outside the
    /// window, the image or the channels.
    pub fn value(&self, image: usize, channel: usize, pixel: usize) -> f32 {
        match self.local(pixel) {
            Some(i) if image < self.count && channel < self.channels => {
                self.plane(image, channel)[i]
            }
            _ => f32::NAN,
        }
    }

    /// Saturation bits of image `image` (bit `p % 64` of word `p / 64` set when pixel `p` has a
    /// saturated channel), or `None` when the image has no saturated pixel.
    pub fn saturation_bits(&self, image: usize) -> Option<&[u64]> {
        self.saturated.get(image).and_then(|s| s.as_deref())
    }

    /// Whether pixel `pixel` of image `image` is saturated in any channel.
    pub fn is_saturated(&self, image: usize, pixel: usize) -> bool {
        self.saturation_bits(image)
            .is_some_and(|b| b[pixel / 64] >> (pixel % 64) & 1 == 1)
    }

    /// Marks pixel `pixel` of image `image` as saturated (for synthetic stacks that clip).
    pub fn mark_saturated(&mut self, image: usize, pixel: usize) {
        let words = self.pixels().div_ceil(64);
        if let Some(slot) = self.saturated.get_mut(image) {
            let bits = slot.get_or_insert_with(|| vec![0; words]);
            bits[pixel / 64] |= 1 << (pixel % 64);
        }
    }

    /// The grey mix Σ_c w_c·I_c of a 3-channel stack with [`GREY_WEIGHTS`], keeping the
    /// saturation flags (a pixel saturated in any channel stays saturated); a 1-channel stack
    /// is returned as is.
    pub fn grey_mix(&self) -> ImageStack {
        if self.channels == 1 {
            return self.clone();
        }
        let n = self.window.len();
        let mut data = crate::buffer::zeroed_f32(self.count * n);
        for (k, out) in data.chunks_mut(n.max(1)).enumerate().take(self.count) {
            for (c, w) in GREY_WEIGHTS.iter().enumerate() {
                for (o, v) in out.iter_mut().zip(self.plane(k, c)) {
                    *o += w * v;
                }
            }
        }
        ImageStack {
            width: self.width,
            height: self.height,
            count: self.count,
            channels: 1,
            data,
            saturated: self.saturated.clone(),
            info: self.info.clone(),
            window: self.window,
        }
    }

    /// This stack with its samples replaced by `data` (same layout, length and flags): for
    /// corrected copies of the images ([`crate::ps::interreflection`]).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when `data` is not as long as [`ImageStack::data`].
    pub fn with_data(&self, data: Vec<f32>) -> Result<ImageStack> {
        if data.len() != self.data.len() {
            return Err(Error::param(
                "images",
                format!("{} samples, {} expected", data.len(), self.data.len()),
            ));
        }
        Ok(ImageStack {
            data,
            saturated: self.saturated.clone(),
            info: self.info.clone(),
            ..*self
        })
    }

    /// What was loaded, per image.
    pub fn info(&self) -> &[ImageInfo] {
        &self.info
    }

    /// All stored samples, image-major then channel then pixel of the window.
    pub fn data(&self) -> &[f32] {
        &self.data
    }
}
