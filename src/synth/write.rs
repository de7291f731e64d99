//! Writing a rendering as a data set on disk: images, `lights.json`, mask and ground truth,
//! in the layout the command line reads.

use crate::capture::lights::Lights;
use crate::error::Result;
use std::path::{Path, PathBuf};

/// File format of written images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ImageFormat {
    /// Float32 EXR, linear: channel `Y`, or `R, G, B` for colour renderings.
    #[default]
    Exr,
    /// 16-bit PNG, linear, values clipped to [0, 1] and quantised (clipped samples read back as
    /// saturated).
    Png16,
    /// 8-bit PNG, values clipped to [0, 1], sRGB-encoded when `srgb` (as cameras write JPEG/PNG),
    /// then quantised.
    Png8 {
        /// Encode with the sRGB transfer function (the reader decodes it by default).
        srgb: bool,
    },
}

impl ImageFormat {
    /// File extension.
    pub fn extension(self) -> &'static str {
        match self {
            ImageFormat::Exr => "exr",
            ImageFormat::Png16 | ImageFormat::Png8 { .. } => "png",
        }
    }
}

/// Value in `gt/shadow_NNN.png` of a pixel in attached shadow (facing away from the light).
pub const SHADOW_ATTACHED: u8 = 128;

/// Value in `gt/shadow_NNN.png` of a pixel in cast shadow (facing the light, but blocked).
pub const SHADOW_CAST: u8 = 255;

/// File stem of a synthetic data set's ambient frame (the scene with every lamp off, written
/// when the rendering has an ambient term), in the images' format: `ambient.exr` or
/// `ambient.png`, for the main command's `--ambient`.
pub const AMBIENT_STEM: &str = "ambient";

/// Sub-folder of a synthetic data set that holds its ground truth.
pub const GROUND_TRUTH_DIR: &str = "gt";

/// Writes a synthetic capture as a data set that the command line reads directly
/// (`photostereo DIR/*.exr --lights DIR/lights.json --mask DIR/mask.png`; for PNG images
/// `DIR/img_*.png`): images `img_NNN`, `lights.json` naming them and `mask.png` at the top, and
/// the ground truth in [`GROUND_TRUTH_DIR`]: `normal_gt.exr` (R, G, B), `depth_gt.exr`
/// (Z, pixel units), `albedo_gt.exr` (Y) and per-light shadow masks `shadow_NNN.png`
/// ([`SHADOW_ATTACHED`] where n·l ≤ 0, [`SHADOW_CAST`] where the light is blocked, 0 where lit),
/// and `saturated_NNN.png` (255 where clipped) for images that clip; with an ambient term, the
/// frame with every lamp off as [`AMBIENT_STEM`]. Returns the files written.
///
/// # Errors
/// [`crate::Error::Io`] or [`crate::Error::Encode`] when writing fails (nothing is left half-written).
pub fn write_synthetic(
    rendering: &crate::synth::render::Rendering,
    lights: &Lights,
    dir: &Path,
    format: ImageFormat,
) -> Result<Vec<PathBuf>> {
    write_synthetic_with_camera(rendering, lights, None, dir, format)
}

/// [`write_synthetic`] for a rendering through a pinhole `camera` (a near-light rendering,
/// [`crate::synth::near`]): its intrinsics go to `K.txt` (three rows of three numbers, as
/// `--camera` reads them), and `gt/depth_gt.exr` holds the depth along the optical axis.
///
/// # Errors
/// As [`write_synthetic`].
pub fn write_synthetic_with_camera(
    rendering: &crate::synth::render::Rendering,
    lights: &Lights,
    camera: Option<&crate::camera::Intrinsics>,
    dir: &Path,
    format: ImageFormat,
) -> Result<Vec<PathBuf>> {
    use crate::io::output::{OutputDir, mask_bytes, normal_planes};
    let t = &rendering.truth;
    let (w, h) = (t.mask.width(), t.mask.height());
    let mut out = OutputDir::create(dir)?;
    let names: Vec<String> = (0..rendering.images.len())
        .map(|k| format!("img_{k:03}.{}", format.extension()))
        .collect();
    let ch = rendering.channels;
    // The ambient frame, when the rendering has one, is written as the images are.
    let ambient_name = format!("{AMBIENT_STEM}.{}", format.extension());
    let frames = names
        .iter()
        .zip(&rendering.images)
        .chain(rendering.ambient.iter().map(|a| (&ambient_name, a)));
    for (name, planes) in frames {
        // Interleaved samples, clipped to [0, 1] for integer formats.
        let interleaved = |f: &dyn Fn(f32) -> f32| -> Vec<f32> {
            (0..w * h)
                .flat_map(|i| planes.iter().map(move |p| p.data()[i]))
                .map(f)
                .collect()
        };
        match format {
            ImageFormat::Exr => {
                let named: Vec<(&str, &[f32])> = if ch == 1 {
                    vec![("Y", planes[0].data())]
                } else {
                    vec![
                        ("R", planes[0].data()),
                        ("G", planes[1].data()),
                        ("B", planes[2].data()),
                    ]
                };
                out.stage_exr(name, w, h, &named, &[])?;
            }
            ImageFormat::Png16 => {
                let codes: Vec<u16> = interleaved(&|v| v.clamp(0.0, 1.0) * 65535.0)
                    .iter()
                    .map(|v| v.round() as u16)
                    .collect();
                out.stage_png16(name, w, h, ch, &codes)?;
            }
            ImageFormat::Png8 { srgb } => {
                let encode = |v: f32| {
                    let v = v.clamp(0.0, 1.0);
                    255.0
                        * if srgb {
                            crate::io::decode::linear_to_srgb(v)
                        } else {
                            v
                        }
                };
                let codes: Vec<u8> = interleaved(&encode)
                    .iter()
                    .map(|v| v.round() as u8)
                    .collect();
                out.stage_png8(name, w, h, ch, &codes)?;
            }
        }
    }
    for (k, (a, c)) in rendering.attached.iter().zip(&rendering.cast).enumerate() {
        let code: Vec<u8> = a
            .data()
            .iter()
            .zip(c.data())
            .map(|(a, c)| {
                if *c {
                    SHADOW_CAST
                } else if *a {
                    SHADOW_ATTACHED
                } else {
                    0
                }
            })
            .collect();
        out.stage_png8(
            &format!("{GROUND_TRUTH_DIR}/shadow_{k:03}.png"),
            w,
            h,
            1,
            &code,
        )?;
    }
    for (k, sat) in rendering.saturated.iter().enumerate() {
        if sat.count() > 0 {
            out.stage_png8(
                &format!("{GROUND_TRUTH_DIR}/saturated_{k:03}.png"),
                w,
                h,
                1,
                &mask_bytes(sat),
            )?;
        }
    }
    let lights = lights.clone().with_files(&names)?;
    out.stage_bytes("lights.json", lights.to_json().as_bytes())?;
    out.stage_png8("mask.png", w, h, 1, &mask_bytes(&t.mask))?;
    let [nx, ny, nz] = normal_planes(&t.normals);
    let gt = |name: &str| format!("{GROUND_TRUTH_DIR}/{name}");
    out.stage_exr(
        &gt("normal_gt.exr"),
        w,
        h,
        &[("R", &nx), ("G", &ny), ("B", &nz)],
        &[],
    )?;
    out.stage_exr(&gt("depth_gt.exr"), w, h, &[("Z", t.depth.data())], &[])?;
    out.stage_exr(&gt("albedo_gt.exr"), w, h, &[("Y", t.albedo.data())], &[])?;
    if let Some(k) = camera {
        let text = format!("{} 0 {}\n0 {} {}\n0 0 1\n", k.fx, k.cx, k.fy, k.cy);
        out.stage_bytes("K.txt", text.as_bytes())?;
    }
    out.commit()
}
