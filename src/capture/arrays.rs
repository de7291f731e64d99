//! Captures from arrays ([`ndarray`]): image stacks, lights and masks built from the arrays a
//! Rust vision program or a Python caller already holds, and the maps handed back as arrays.
//!
//! Images come as `N×H×W` (grey) or `N×H×W×C` (C = 1 grey, 2 grey and alpha, 3 RGB, 4 RGBA;
//! alpha ignored) views of `u8`, `u16`, `f32` or `f64` samples, any strides. They are converted
//! exactly as files of the same samples are ([`crate::capture::stack`]): integers scaled to
//! [0, 1] by their largest code (which marks a sample saturated, judged on the codes as the
//! file reader judges it), 8-bit values sRGB-decoded unless [`Transfer::Linear`],
//! each image divided by its light's intensity, then mixed to grey or kept per channel. That
//! conversion is the one pass over the samples: a view is read where it lies, not copied
//! first. With [`LoadOptions::window`] only that part of each image is stored (a mask's
//! bounding box, as [`Capture::from_arrays`] does).
//!
//! Maps come back without a copy where the layout allows: a [`Grid`] moves its buffer into an
//! [`Array2`] ([`Grid::into_array`]); a normal map becomes `H×W×3` ([`normals_to_array`]).
//!
//! ```
//! use ndarray::{Array2, Array3};
//! use photostereo::{capture::{Capture, LoadOptions, Lights}, progress::Silent, run};
//! // Four lights and a flat patch facing the camera with albedo 0.5: I_k = 0.5 · l_k.z.
//! let directions = Array2::from_shape_vec((4, 3), vec![
//!     0.5, 0.0, 0.866, -0.5, 0.0, 0.866, 0.0, 0.5, 0.866, 0.0, -0.5, 0.866,
//! ]).unwrap();
//! let lights = Lights::from_array(directions.view(), None)?;
//! let images = Array3::from_shape_fn((4, 8, 8), |(k, _, _)| {
//!     0.5 * lights.lights()[k].direction.z as f32
//! });
//! let capture = Capture::from_arrays(images.view(), lights, None, &LoadOptions::default())?;
//! let recon = run::reconstruct(&capture, &run::Config::default(), &Silent)?;
//! let normals = photostereo::capture::arrays::normals_to_array(&recon.maps.normals);
//! assert_eq!(normals.dim(), (8, 8, 3));
//! assert!((normals[[4, 4, 2]] - 1.0).abs() < 1e-5);
//! # Ok::<(), photostereo::Error>(())
//! ```

use crate::capture::dataset::Capture;
use crate::capture::lights::{Light, Lights};
use crate::capture::stack::{
    ColorMode, Converted, ImageInfo, ImageStack, LoadOptions, RowPlace, Transfer, check_usable,
    coefficients, combine_any, mark_frame_saturation, srgb_lut, stored_window, take_off_frame,
};
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap, Window};
use crate::io::decode::{MAX_IMAGE_SAMPLES, SampleFormat, srgb_to_linear};
use nalgebra::Vector3;
use ndarray::{Array2, Array3, ArrayView2, ArrayView3, ArrayView4, Axis};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// A sample type images can be given in: how it is stored and scaled to [0, 1].
pub trait Sample: Copy + PartialOrd + Send + Sync + 'static {
    /// The storage format it stands for (integers have a saturating maximum code).
    const FORMAT: SampleFormat;
    /// The value scaled to [0, 1] for integers, as is (in `f32`) for floats.
    fn stored(self) -> f32;
    /// An integer code as the saturation level it is compared with (`code / max`, as the
    /// file reader computes it); floats as [`Sample::stored`].
    fn level(self) -> f32 {
        self.stored()
    }
}

impl Sample for u8 {
    const FORMAT: SampleFormat = SampleFormat::U8;
    fn stored(self) -> f32 {
        f32::from(self) * (1.0 / 255.0)
    }
    fn level(self) -> f32 {
        f32::from(self) / 255.0
    }
}

impl Sample for u16 {
    const FORMAT: SampleFormat = SampleFormat::U16;
    fn stored(self) -> f32 {
        f32::from(self) * (1.0 / 65535.0)
    }
    fn level(self) -> f32 {
        f32::from(self) / 65535.0
    }
}

impl Sample for f32 {
    const FORMAT: SampleFormat = SampleFormat::F32;
    fn stored(self) -> f32 {
        self
    }
}

impl Sample for f64 {
    const FORMAT: SampleFormat = SampleFormat::F32;
    fn stored(self) -> f32 {
        // Beyond f32's range a value becomes infinite, and is then treated as non-finite.
        self as f32
    }
}

/// Whether arrays hold a whole capture or a part of one (whose images may be dark or
/// saturated in that part alone).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Extent {
    Whole,
    Part,
}

/// The name an in-memory ambient frame goes by in messages.
const AMBIENT_NAME: &str = "<array ambient frame>";

/// What converting the images of an array keeps from one image to the next.
struct ArrayConversion<'a> {
    window: Window,
    width: usize,
    height: usize,
    /// Values per pixel on the last axis.
    stride: usize,
    /// Output planes.
    channels: usize,
    linearise: bool,
    /// Saturation level.
    level: f32,
    lut: &'a [f32; 256],
}

impl ArrayConversion<'_> {
    /// Converts `image` (`H×W×C`) into `out` (the stack's planes of one image), dividing by
    /// `coef`: its saturation flags and tallies.
    fn run<S: Sample>(
        &self,
        image: ArrayView3<'_, S>,
        coef: [f32; 3],
        out: &mut [f32],
    ) -> Converted {
        let (window, width, stride, level, lut) =
            (self.window, self.width, self.stride, self.level, self.lut);
        let (linearise, channels, n) = (self.linearise, self.channels, self.window.len());
        let height = self.height;
        let mut c = Converted {
            bits: vec![0u64; (width * height).div_ceil(64)],
            saturated: 0,
            non_finite: 0,
        };
        let ww = window.width();
        let mut stored = vec![0f32; ww * stride];
        let mut linear = vec![0f32; if linearise { stored.len() } else { 0 }];
        for y in window.y0..window.y1 {
            let row = image.index_axis(Axis(0), y);
            let row = row.slice(ndarray::s![window.x0..window.x1, ..]);
            match row.as_slice() {
                Some(s) => {
                    for (d, v) in stored.iter_mut().zip(s) {
                        *d = v.stored();
                    }
                }
                None => {
                    for (d, v) in stored.iter_mut().zip(row.iter()) {
                        *d = v.stored();
                    }
                }
            }
            if linearise {
                if S::FORMAT == SampleFormat::U8 {
                    for (d, v) in linear.iter_mut().zip(&stored) {
                        *d = lut[(v * 255.0).round() as usize];
                    }
                } else {
                    for (d, v) in linear.iter_mut().zip(&stored) {
                        *d = srgb_to_linear(v.clamp(0.0, 1.0));
                    }
                }
            }
            // Integer rows are finite, and saturated only if their largest value reaches
            // the level; float rows are checked per pixel.
            let (row_max, check_finite) = if S::FORMAT.is_integer() {
                // The largest code, as a level the way the file reader makes it.
                let top = row.iter().copied().reduce(|a, b| if b > a { b } else { a });
                (top.map_or(0.0, Sample::level), false)
            } else {
                (level, true)
            };
            let lin: &[f32] = if linearise { &linear } else { &stored };
            let place = RowPlace {
                out_channels: channels,
                n,
                offset: (y - window.y0) * ww,
                pixel: y * width + window.x0,
            };
            combine_any(
                stride,
                &stored,
                lin,
                (coef, level),
                out,
                &place,
                row_max,
                check_finite,
                &mut c,
            );
        }
        c
    }
}

/// The name an in-memory image goes by in messages and [`ImageInfo::path`].
fn array_name(index: usize) -> PathBuf {
    PathBuf::from(format!("<array image {index}>"))
}

impl ImageStack {
    /// A stack from `N×H×W` grey images, image `k` lit by light `k` of `lights` (whose
    /// intensities divide it), converted as `options` says (see the [module](self) notes).
    ///
    /// # Errors
    /// As [`ImageStack::from_array_channels`].
    pub fn from_array<S: Sample>(
        images: ArrayView3<'_, S>,
        lights: &Lights,
        options: &LoadOptions,
    ) -> Result<ImageStack> {
        ImageStack::from_array_channels(images.insert_axis(Axis(3)), lights, options)
    }

    /// A stack from `N×H×W×C` images (C = 1 grey, 2 grey and alpha, 3 RGB, or 4 RGBA; alpha
    /// ignored), image `k` lit by light `k` of `lights`, converted as `options` says: mixed to grey with
    /// [`crate::capture::stack::GREY_WEIGHTS`] or kept per channel ([`ColorMode`]).
    ///
    /// # Errors
    /// [`Error::LightsMismatch`] when N differs from the light count;
    /// [`Error::TooFewImages`] for no image; [`Error::InvalidParameter`] (`images`) for an
    /// empty image, C not 1 to 4, more than [`MAX_IMAGE_SAMPLES`] samples an image or a stack
    /// too large to allocate, or a per-channel load of grey images; (`window`) for a window
    /// outside the images; [`Error::BadImage`] for an image that is entirely dark or
    /// saturated everywhere.
    pub fn from_array_channels<S: Sample>(
        images: ArrayView4<'_, S>,
        lights: &Lights,
        options: &LoadOptions,
    ) -> Result<ImageStack> {
        ImageStack::convert_array(images, None, lights, options, Extent::Whole)
    }

    /// [`ImageStack::from_array_channels`] with an ambient frame subtracted: `ambient`
    /// (`H×W×C`, as each image), the scene taken with every lamp off, converted as each image
    /// is and subtracted from it, as [`crate::capture::stack::load_stack_with_ambient`] does
    /// for files.
    ///
    /// # Errors
    /// As [`ImageStack::from_array_channels`]; [`Error::Ambient`] when the frame's shape
    /// differs from an image's or it holds a non-finite value.
    pub fn from_array_channels_with_ambient<S: Sample>(
        images: ArrayView4<'_, S>,
        ambient: ArrayView3<'_, S>,
        lights: &Lights,
        options: &LoadOptions,
    ) -> Result<ImageStack> {
        ImageStack::convert_array(images, Some(ambient), lights, options, Extent::Whole)
    }

    /// [`ImageStack::from_array_channels`] for a part of a larger capture (a tile of it): an
    /// image that is entirely dark or saturated in this part is kept, not refused (a tile in a
    /// cast shadow under one light is, while the whole image is not).
    ///
    /// # Errors
    /// As [`ImageStack::from_array_channels`], but for [`Error::BadImage`].
    pub fn from_array_part<S: Sample>(
        images: ArrayView4<'_, S>,
        lights: &Lights,
        options: &LoadOptions,
    ) -> Result<ImageStack> {
        ImageStack::convert_array(images, None, lights, options, Extent::Part)
    }

    fn convert_array<S: Sample>(
        images: ArrayView4<'_, S>,
        ambient: Option<ArrayView3<'_, S>>,
        lights: &Lights,
        options: &LoadOptions,
        extent: Extent,
    ) -> Result<ImageStack> {
        let (count, height, width, stride) = images.dim();
        if let Some(a) = &ambient
            && a.dim() != (height, width, stride)
        {
            let (h, w, c) = a.dim();
            return Err(Error::Ambient {
                path: AMBIENT_NAME.into(),
                reason: format!(
                    "shape {h}×{w}×{c} differs from each image's {height}×{width}×{stride}"
                ),
            });
        }
        if count != lights.len() {
            return Err(Error::LightsMismatch {
                reason: format!("{count} images for {} lights", lights.len()),
            });
        }
        if count == 0 {
            return Err(Error::TooFewImages { count: 0 });
        }
        if width == 0 || height == 0 {
            return Err(Error::param(
                "images",
                format!("each image is {height}×{width} pixels; an image needs at least one"),
            ));
        }
        let channels_in = match stride {
            1 | 2 => 1,
            3 | 4 => 3,
            _ => {
                return Err(Error::param(
                    "images",
                    format!(
                        "{stride} channels per pixel (last axis); 1 (grey), 2 (grey and alpha), 3 (RGB) or 4 (RGBA) expected"
                    ),
                ));
            }
        };
        let channels = match options.color {
            ColorMode::Grey => 1,
            ColorMode::PerChannel if channels_in == 3 => 3,
            ColorMode::PerChannel => {
                return Err(Error::param(
                    "images",
                    "a per-channel solve needs RGB images (3 or 4 channels on the last axis)",
                ));
            }
        };
        let window = stored_window(options.window, width, height)?;
        let linearise = match options.transfer {
            Transfer::Auto => S::FORMAT == SampleFormat::U8,
            Transfer::Linear => false,
            Transfer::Srgb => true,
        };
        let level = options
            .saturation
            .or(S::FORMAT.is_integer().then_some(1.0))
            .unwrap_or(f32::INFINITY);
        let n = window.len();
        // The limits of a decoded file hold for an array too: each stored image at most
        // MAX_IMAGE_SAMPLES samples, and the whole stack an allocation that can be had.
        let per_image = n.checked_mul(channels).filter(|&v| v <= MAX_IMAGE_SAMPLES);
        let total = per_image.and_then(|v| v.checked_mul(count));
        let Some(total) = total else {
            return Err(Error::param(
                "images",
                format!(
                    "{count} images of {} stored pixels × {channels} channel(s): more than {MAX_IMAGE_SAMPLES} samples an image; pass a mask or solve the capture in parts",
                    n
                ),
            ));
        };
        let mut probe: Vec<f32> = Vec::new();
        if probe.try_reserve_exact(total).is_err() {
            return Err(Error::param(
                "images",
                format!(
                    "{count} images of {n} stored pixels × {channels} channel(s) need {} GiB of memory, which could not be had; pass a mask or solve the capture in parts",
                    (total * 4) >> 30
                ),
            ));
        }
        drop(probe);
        let lut = srgb_lut();
        let conversion = ArrayConversion {
            window,
            width,
            height,
            stride,
            channels,
            linearise,
            level,
            lut: &lut,
        };
        let mut data = crate::buffer::zeroed_f32(total);
        let results: Vec<Result<(Option<Vec<u64>>, ImageInfo)>> = data
            .par_chunks_mut(channels * n)
            .enumerate()
            .map(|(index, out)| {
                let image = images.index_axis(Axis(0), index);
                let intensity = lights.lights()[index].intensity.map(|v| v as f32);
                let coef = coefficients(channels_in, channels, intensity);
                let mut c = conversion.run(image, coef, out);
                if let Some(frame) = &ambient {
                    let mut light = vec![0f32; out.len()];
                    let a = conversion.run(frame.view(), coef, &mut light);
                    take_off_frame(out, &light, Path::new(AMBIENT_NAME), a.non_finite)?;
                    if a.saturated > 0 {
                        c.saturated = mark_frame_saturation(&mut c.bits, &a.bits);
                    }
                }
                let path = array_name(index);
                let where_ = || {
                    if window == Window::full(width, height) {
                        String::new()
                    } else {
                        format!(" in the part the mask spans ({window})")
                    }
                };
                if extent == Extent::Whole {
                    check_usable(out, c.saturated, n, &path, index, where_)?;
                }
                let info = ImageInfo {
                    path,
                    format: S::FORMAT,
                    channels: channels_in,
                    linearised: linearise,
                    saturated: c.saturated,
                    non_finite: c.non_finite,
                    raw: None,
                };
                Ok(((c.saturated > 0).then_some(c.bits), info))
            })
            .collect();
        let mut saturated = Vec::with_capacity(count);
        let mut info = Vec::with_capacity(count);
        for r in results {
            let (s, i) = r?;
            saturated.push(s);
            info.push(i);
        }
        Ok(ImageStack::from_parts(
            width, height, channels, data, saturated, info, window,
        ))
    }
}

impl Lights {
    /// Lights from an `N×3` array of directions (camera frame, towards the light; normalised
    /// here) and optional intensities, `N×1` (one per light) or `N×3` (R, G, B).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`lights`, `intensities`) for a wrong shape; the errors of
    /// [`Lights::new`] (zero or non-finite directions, bad intensities) naming the light.
    pub fn from_array(
        directions: ArrayView2<'_, f64>,
        intensities: Option<ArrayView2<'_, f64>>,
    ) -> Result<Lights> {
        let (count, three) = directions.dim();
        if three != 3 {
            return Err(Error::param(
                "lights",
                format!("shape {count}×{three}; one row x, y, z per light (N×3) expected"),
            ));
        }
        if let Some(i) = &intensities
            && (i.nrows() != count || !(i.ncols() == 1 || i.ncols() == 3))
        {
            return Err(Error::param(
                "intensities",
                format!(
                    "shape {}×{}; N×1 or N×3 (one row a light, N = {count}) expected",
                    i.nrows(),
                    i.ncols()
                ),
            ));
        }
        let lights = (0..count)
            .map(|k| {
                let d = directions.row(k);
                let mut light = Light::new(Vector3::new(d[0], d[1], d[2]));
                if let Some(i) = &intensities {
                    let row = i.row(k);
                    light.intensity = if row.len() == 1 {
                        [row[0]; 3]
                    } else {
                        [row[0], row[1], row[2]]
                    };
                }
                light
            })
            .collect();
        Lights::new(lights)
    }

    /// The directions as an `N×3` array.
    pub fn directions_array(&self) -> Array2<f64> {
        Array2::from_shape_fn((self.len(), 3), |(k, c)| self.lights[k].direction[c])
    }

    /// The intensities as an `N×3` array (R, G, B).
    pub fn intensities_array(&self) -> Array2<f64> {
        Array2::from_shape_fn((self.len(), 3), |(k, c)| self.lights[k].intensity[c])
    }
}

impl<T: Clone> Grid<T> {
    /// A grid holding the `H×W` array's values, row by row.
    pub fn from_array(values: ArrayView2<'_, T>) -> Grid<T> {
        let (h, w) = values.dim();
        Grid::from_fn(w, h, |x, y| values[[y, x]].clone())
    }
}

impl<T> Grid<T> {
    /// The grid as an `H×W` array, its buffer moved, not copied.
    pub fn into_array(self) -> Array2<T> {
        let (w, h) = (self.width(), self.height());
        // The grid holds exactly w·h values in row-major order, so the shape always fits.
        Array2::from_shape_vec((h, w), self.into_vec())
            .unwrap_or_else(|_| unreachable!("a grid holds width × height values"))
    }
}

/// A normal map as an `H×W×3` array of (n_x, n_y, n_z), NaN where undefined.
pub fn normals_to_array(normals: &NormalMap) -> Array3<f32> {
    let (w, h) = (normals.width(), normals.height());
    let flat: Vec<f32> = normals
        .data()
        .iter()
        .flat_map(|n| [n.x, n.y, n.z])
        .collect();
    Array3::from_shape_vec((h, w, 3), flat).unwrap_or_else(|_| unreachable!("three values a pixel"))
}

/// A normal map from an `H×W×3` array.
///
/// # Errors
/// [`Error::InvalidParameter`] (`normals`) when the last axis is not 3 long.
pub fn normals_from_array(normals: ArrayView3<'_, f32>) -> Result<NormalMap> {
    let (h, w, c) = normals.dim();
    if c != 3 {
        return Err(Error::param(
            "normals",
            format!("shape {h}×{w}×{c}; H×W×3 (n_x, n_y, n_z) expected"),
        ));
    }
    Ok(Grid::from_fn(w, h, |x, y| {
        Vector3::new(normals[[y, x, 0]], normals[[y, x, 1]], normals[[y, x, 2]])
    }))
}

impl Capture {
    /// A capture from `N×H×W` grey images, their lights and an optional `H×W` mask (every
    /// pixel when `None`): only the part of the images the mask spans is stored, as a capture
    /// loaded from files does. Images are converted as [`ImageStack::from_array`] says.
    ///
    /// # Errors
    /// The errors of [`ImageStack::from_array_channels`]; [`Error::Mask`] for an empty mask or
    /// one whose size differs from the images'.
    pub fn from_arrays<S: Sample>(
        images: ArrayView3<'_, S>,
        lights: Lights,
        mask: Option<ArrayView2<'_, bool>>,
        options: &LoadOptions,
    ) -> Result<Capture> {
        Capture::from_arrays_channels(images.insert_axis(Axis(3)), lights, mask, options)
    }

    /// [`Capture::from_arrays`] for `N×H×W×C` images.
    ///
    /// # Errors
    /// As [`Capture::from_arrays`].
    pub fn from_arrays_channels<S: Sample>(
        images: ArrayView4<'_, S>,
        lights: Lights,
        mask: Option<ArrayView2<'_, bool>>,
        options: &LoadOptions,
    ) -> Result<Capture> {
        Capture::from_array_views(images, None, lights, mask, options, Extent::Whole)
    }

    /// [`Capture::from_arrays_channels`] with an ambient frame (`H×W×C`: the scene taken
    /// with every lamp off) subtracted from every image
    /// ([`ImageStack::from_array_channels_with_ambient`]).
    ///
    /// # Errors
    /// As [`Capture::from_arrays_channels`] and
    /// [`ImageStack::from_array_channels_with_ambient`].
    pub fn from_arrays_channels_with_ambient<S: Sample>(
        images: ArrayView4<'_, S>,
        ambient: ArrayView3<'_, S>,
        lights: Lights,
        mask: Option<ArrayView2<'_, bool>>,
        options: &LoadOptions,
    ) -> Result<Capture> {
        Capture::from_array_views(images, Some(ambient), lights, mask, options, Extent::Whole)
    }

    /// [`Capture::from_arrays_channels`] for a part of a larger capture (a tile), to be solved
    /// under the whole capture's models
    /// ([`crate::run::pipeline::reconstruct_normals_with_models`]): images dark or saturated
    /// in this part alone are kept ([`ImageStack::from_array_part`]).
    ///
    /// # Errors
    /// As [`Capture::from_arrays_channels`], but for [`Error::BadImage`].
    pub fn from_arrays_part<S: Sample>(
        images: ArrayView4<'_, S>,
        lights: Lights,
        mask: Option<ArrayView2<'_, bool>>,
        options: &LoadOptions,
    ) -> Result<Capture> {
        Capture::from_array_views(images, None, lights, mask, options, Extent::Part)
    }

    /// [`Capture::from_arrays_part`] with the part of an ambient frame (`H×W×C`) subtracted
    /// ([`Capture::from_arrays_channels_with_ambient`]).
    ///
    /// # Errors
    /// As [`Capture::from_arrays_part`] and
    /// [`ImageStack::from_array_channels_with_ambient`].
    pub fn from_arrays_part_with_ambient<S: Sample>(
        images: ArrayView4<'_, S>,
        ambient: ArrayView3<'_, S>,
        lights: Lights,
        mask: Option<ArrayView2<'_, bool>>,
        options: &LoadOptions,
    ) -> Result<Capture> {
        Capture::from_array_views(images, Some(ambient), lights, mask, options, Extent::Part)
    }

    fn from_array_views<S: Sample>(
        images: ArrayView4<'_, S>,
        ambient: Option<ArrayView3<'_, S>>,
        lights: Lights,
        mask: Option<ArrayView2<'_, bool>>,
        options: &LoadOptions,
        extent: Extent,
    ) -> Result<Capture> {
        let (_, height, width, _) = images.dim();
        let mask: Option<Mask> = match mask {
            Some(m) => {
                if m.dim() != (height, width) {
                    return Err(Error::Mask {
                        path: "<array mask>".into(),
                        reason: format!(
                            "shape {}×{} differs from the images' {height}×{width}",
                            m.nrows(),
                            m.ncols()
                        ),
                    });
                }
                let mask = Grid::from_array(m);
                if mask.count() == 0 {
                    return Err(Error::Mask {
                        path: "<array mask>".into(),
                        reason: "no pixel is set".into(),
                    });
                }
                Some(mask)
            }
            None => None,
        };
        let window = mask.as_ref().and_then(|m| m.bounding_box());
        let options = LoadOptions {
            window: options.window.or(window),
            ..*options
        };
        let stack = ImageStack::convert_array(images, ambient, &lights, &options, extent)?;
        Capture::from_stack(stack, lights, mask)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::stack::GREY_WEIGHTS;
    use ndarray::{Array3, Array4, s};

    fn lights4() -> Lights {
        Lights::from_array(
            ndarray::arr2(&[
                [0.5, 0.1, 0.86],
                [-0.5, 0.0, 0.86],
                [0.0, 0.5, 0.86],
                [0.1, -0.5, 0.86],
            ])
            .view(),
            Some(
                ndarray::arr2(&[
                    [1.0, 2.0, 4.0],
                    [1.0, 1.0, 1.0],
                    [2.0, 2.0, 2.0],
                    [0.5, 1.0, 1.0],
                ])
                .view(),
            ),
        )
        .unwrap()
    }

    /// The array path converts as the file path does: u16 RGB scaled, divided by the
    /// intensities, grey-mixed; the largest code marks saturation.
    #[test]
    fn u16_rgb_matches_the_closed_form() {
        let lights = lights4();
        let imgs = Array4::from_shape_fn((4, 3, 5, 3), |(k, y, x, c)| {
            if (k, y, x) == (2, 1, 1) {
                65535
            } else {
                (1000 * (k + 1) + 100 * y + 10 * x + c) as u16
            }
        });
        let stack =
            ImageStack::from_array_channels(imgs.view(), &lights, &LoadOptions::default()).unwrap();
        assert_eq!((stack.width(), stack.height(), stack.channels()), (5, 3, 1));
        for k in 0..4 {
            let i = lights.lights()[k].intensity;
            for y in 0..3 {
                for x in 0..5 {
                    let want: f64 = (0..3)
                        .map(|c| {
                            f64::from(GREY_WEIGHTS[c]) * f64::from(imgs[[k, y, x, c]])
                                / 65535.0
                                / i[c]
                        })
                        .sum();
                    let got = f64::from(stack.value(k, 0, y * 5 + x));
                    assert!((got - want).abs() < 1e-6 * want.max(1.0), "{got} vs {want}");
                }
            }
        }
        assert!(stack.is_saturated(2, 6));
        assert_eq!(stack.info()[2].saturated, 1);
        assert_eq!(stack.info()[0].saturated, 0);
    }

    /// An ambient frame is converted as each image is (8-bit sRGB decoded, divided by that
    /// image's per-channel intensities, grey-mixed) and subtracted; its saturated pixel counts
    /// in every image; a frame of another shape is refused.
    #[test]
    fn an_ambient_frame_is_subtracted_as_each_image_is_converted() {
        let lights = lights4();
        let imgs = Array4::from_shape_fn((4, 2, 3, 3), |(k, y, x, c)| {
            (40 * k + 30 * y + 9 * x + 5 * c + 60) as u8
        });
        let frame = Array3::from_shape_fn((2, 3, 3), |(y, x, c)| {
            if (y, x, c) == (1, 2, 0) {
                255
            } else {
                (3 * y + 2 * x + c + 10) as u8
            }
        });
        let stack = ImageStack::from_array_channels_with_ambient(
            imgs.view(),
            frame.view(),
            &lights,
            &LoadOptions::default(),
        )
        .unwrap();
        let lin = |v: u8| f64::from(crate::io::decode::srgb_to_linear(f32::from(v) / 255.0));
        for k in 0..4 {
            let i = lights.lights()[k].intensity;
            for y in 0..2 {
                for x in 0..3 {
                    let want: f64 = (0..3)
                        .map(|c| {
                            f64::from(GREY_WEIGHTS[c])
                                * (lin(imgs[[k, y, x, c]]) - lin(frame[[y, x, c]]))
                                / i[c]
                        })
                        .sum();
                    let got = f64::from(stack.value(k, 0, y * 3 + x));
                    assert!(
                        (got - want).abs() < 1e-6,
                        "image {k} ({x}, {y}): {got} vs {want}"
                    );
                }
            }
            assert!(stack.is_saturated(k, 5), "image {k}");
            assert_eq!(stack.info()[k].saturated, 1);
        }
        let wrong = Array3::<u8>::zeros((2, 2, 3));
        let e = ImageStack::from_array_channels_with_ambient(
            imgs.view(),
            wrong.view(),
            &lights,
            &LoadOptions::default(),
        )
        .unwrap_err();
        assert!(
            matches!(e, Error::Ambient { .. }) && e.to_string().contains("2×2×3"),
            "{e}"
        );
    }

    /// A strided (non-contiguous) view gives the same stack as a contiguous copy of it.
    #[test]
    fn strided_views_read_as_copies() {
        let lights = lights4();
        let big = Array4::from_shape_fn((4, 8, 10, 3), |(k, y, x, c)| {
            ((k + 1) * (y + 2) * (x + 3) + c) as f32 / 100.0
        });
        let strided = big.slice(s![.., ..;2, ..;3, ..]);
        assert!(strided.as_slice().is_none());
        let copy = strided.to_owned();
        let options = LoadOptions {
            color: ColorMode::PerChannel,
            ..LoadOptions::default()
        };
        let a = ImageStack::from_array_channels(strided, &lights, &options).unwrap();
        let b = ImageStack::from_array_channels(copy.view(), &lights, &options).unwrap();
        assert_eq!(a.data(), b.data());
        assert_eq!(a.channels(), 3);
    }

    /// 8-bit data are sRGB-decoded by default and kept linear on request.
    #[test]
    fn u8_is_srgb_decoded_unless_linear() {
        let lights = Lights::from_directions(&[Vector3::z(); 3]).unwrap();
        let imgs = Array3::from_elem((3, 2, 2), 128u8);
        let srgb = ImageStack::from_array(imgs.view(), &lights, &LoadOptions::default()).unwrap();
        let want = srgb_to_linear(128.0 / 255.0);
        assert!((srgb.value(0, 0, 0) - want).abs() < 1e-6);
        let linear = LoadOptions {
            transfer: Transfer::Linear,
            ..LoadOptions::default()
        };
        let lin = ImageStack::from_array(imgs.view(), &lights, &linear).unwrap();
        assert!((lin.value(1, 0, 3) - 128.0 / 255.0).abs() < 1e-6);
    }

    /// Shapes and counts that do not fit are refused with the parameter named.
    #[test]
    fn bad_shapes_are_refused() {
        let lights = lights4();
        let three = Array3::<f32>::ones((3, 4, 4));
        let e = ImageStack::from_array(three.view(), &lights, &LoadOptions::default());
        assert!(matches!(e, Err(Error::LightsMismatch { .. })), "{e:?}");
        let five = Array4::<f32>::ones((4, 4, 4, 5));
        let e = ImageStack::from_array_channels(five.view(), &lights, &LoadOptions::default());
        assert!(e.unwrap_err().to_string().contains("5 channels"));
        let e = Lights::from_array(Array2::<f64>::ones((4, 2)).view(), None);
        assert!(e.unwrap_err().to_string().contains("4×2"));
        let mut d = Array2::<f64>::ones((4, 3));
        d[[2, 1]] = f64::NAN;
        let e = Lights::from_array(d.view(), None).unwrap_err();
        assert!(matches!(e, Error::InvalidLight { index: 2, .. }), "{e:?}");
        let dark = Array3::<f32>::zeros((4, 4, 4));
        let e = ImageStack::from_array(dark.view(), &lights, &LoadOptions::default()).unwrap_err();
        assert!(matches!(e, Error::BadImage { index: 0, .. }), "{e:?}");
        let ones = Array3::<f32>::ones((4, 4, 4));
        let mask = Array2::from_elem((3, 4), true);
        let e = Capture::from_arrays(
            ones.view(),
            lights,
            Some(mask.view()),
            &LoadOptions::default(),
        );
        assert!(matches!(e, Err(Error::Mask { .. })));
    }

    /// A part of a capture may be dark under one light (a tile in a cast shadow): kept as a
    /// part, refused as a whole; and integer saturation is judged on codes, as files are.
    #[test]
    fn parts_keep_images_dark_in_the_part_alone() {
        let lights = lights4();
        let mut imgs = Array4::<u16>::from_elem((4, 3, 3, 1), 1000);
        imgs.index_axis_mut(Axis(0), 1).fill(0);
        let whole = ImageStack::from_array_channels(imgs.view(), &lights, &LoadOptions::default());
        assert!(matches!(whole, Err(Error::BadImage { index: 1, .. })));
        let part =
            ImageStack::from_array_part(imgs.view(), &lights, &LoadOptions::default()).unwrap();
        assert_eq!(part.value(1, 0, 4), 0.0);
        // A user level just below code 1000's flags every sample of images 0, 2 and 3.
        let level = LoadOptions {
            saturation: Some(999.5 / 65535.0),
            ..LoadOptions::default()
        };
        let sat = ImageStack::from_array_part(imgs.view(), &lights, &level).unwrap();
        assert!(sat.is_saturated(0, 4) && !sat.is_saturated(1, 4));
    }

    /// A mask stores only its bounding box, and maps round-trip through arrays.
    #[test]
    fn masks_window_the_stack_and_maps_round_trip() {
        let lights = lights4();
        let imgs = Array3::<f32>::from_elem((4, 6, 7), 0.25);
        let mut mask = Array2::from_elem((6, 7), false);
        mask[[2, 3]] = true;
        mask[[4, 5]] = true;
        let cap = Capture::from_arrays(
            imgs.view(),
            lights,
            Some(mask.view()),
            &LoadOptions::default(),
        )
        .unwrap();
        assert_eq!(cap.stack.window().len(), 3 * 3);
        assert_eq!(cap.mask.clone().into_array(), mask);
        let normals = Array3::from_shape_fn((2, 3, 3), |(y, x, c)| (y * 9 + x * 3 + c) as f32);
        let map = normals_from_array(normals.view()).unwrap();
        assert_eq!(normals_to_array(&map), normals);
    }
}
