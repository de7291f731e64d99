//! Camera RAW (DNG and the common vendor formats: CR2, CR3, NEF, ARW, RAF, ORF, RW2, PEF, …),
//! decoded by the `rawler` crate (dnglab's decoder library) when photostereo is built with the
//! `raw` feature, and developed here the way photometric stereo needs: linear, nothing guessed.
//!
//! A RAW file holds the sensor's own counts: linear in the light that reached each photosite,
//! which is exactly what photometric stereo models (I = ρ·L·n·l). The development is therefore
//! minimal and every choice is recorded ([`RawDevelopment`], written to `report.json`):
//! - **Active area**: the masked border of the sensor is cut off.
//! - **Black level** subtracted per CFA position, then division by (white − black), so a
//!   sample is the fraction of the sensor's range.
//! - **White balance**: the camera's as-shot coefficients, normalised to green = 1, scale R and B,
//!   so that the three channels of a grey surface agree (what the grey mix and the colour solves
//!   assume); then everything is divided by the largest gain so that no sample exceeds 1.
//! - **No demosaicing**: each 2×2 CFA quad (one R, two G, one B) becomes one RGB pixel (the two
//!   G averaged). Half the resolution, but no interpolated value: a demosaicing filter mixes
//!   neighbours with weights tuned for pictures, and at the object's edges and shadow boundaries
//!   it makes samples no light produced.
//! - **Saturation**: a quad with any photosite at or above the white level is stored at the
//!   maximum code of the 16-bit output and so is flagged saturated like any integer image.
//!
//! Files with three samples per pixel (linear DNG) keep their pixels and get the same black,
//! white and balance steps. Other CFA layouts (X-Trans, 4-colour) are refused by name.

use crate::error::{Error, Result};
use crate::io::decode::RawDecoded;
use serde::Serialize;
use std::path::Path;

/// File extensions read as camera RAW.
pub const RAW_EXTENSIONS: [&str; 18] = [
    "dng", "cr2", "cr3", "crw", "nef", "nrw", "arw", "srf", "sr2", "raf", "orf", "rw2", "pef",
    "srw", "3fr", "iiq", "erf", "kdc",
];

/// Whether `path` names a camera RAW file (by its extension).
pub fn is_raw(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| RAW_EXTENSIONS.iter().any(|r| e.eq_ignore_ascii_case(r)))
}

/// How a RAW file was turned into linear RGB samples (written to `report.json`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RawDevelopment {
    /// Camera make and model, as the file names them.
    pub camera: String,
    /// The colour filter pattern, e.g. `RGGB` (empty for three samples per pixel).
    pub cfa: String,
    /// Sensor size (width, height) in photosites.
    pub sensor: [usize; 2],
    /// The area used: left, top, width, height in photosites (the active area).
    pub area: [usize; 4],
    /// Black level per position of the 2×2 pattern (row-major), subtracted.
    pub black_levels: [f32; 4],
    /// White level per position of the 2×2 pattern: the count at which a photosite saturates.
    pub white_levels: [f32; 4],
    /// White-balance gains applied to R, G, B (the camera's as-shot coefficients, G = 1), before
    /// the division by their maximum.
    pub white_balance: [f32; 3],
    /// What became a pixel: `"2x2 CFA quad"` (half resolution, no interpolation) or
    /// `"pixel"` (three samples per pixel).
    pub binning: &'static str,
}

/// Decodes a camera RAW file into linear 16-bit RGB samples (see the module documentation).
///
/// # Errors
/// [`Error::Decode`] naming the file when `rawler` cannot read it (or fails on it);
/// [`Error::UnsupportedImage`] for colour filter layouts other than 2×2 RGB and when
/// photostereo was built without the `raw` feature.
pub(crate) fn decode(path: &Path) -> Result<(RawDecoded, RawDevelopment)> {
    imp::decode(path)
}

/// Longest camera RAW file read (the decoder reads a file whole): 2 GiB, several times the
/// largest RAW files of medium-format backs.
#[cfg_attr(not(feature = "raw"), allow(dead_code))]
const MAX_RAW_BYTES: u64 = 2 << 30;

#[cfg(not(feature = "raw"))]
mod imp {
    use super::*;

    pub(super) fn decode(path: &Path) -> Result<(RawDecoded, RawDevelopment)> {
        Err(Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: "camera RAW needs photostereo built with its `raw` feature (the command-line tool has it); or convert the file to 16-bit linear TIFF".into(),
        })
    }
}

#[cfg(feature = "raw")]
mod imp {
    use super::*;
    use crate::io::decode::{SampleFormat, Samples};
    use rawler::rawimage::{RawImageData, RawPhotometricInterpretation};

    pub(super) fn decode(path: &Path) -> Result<(RawDecoded, RawDevelopment)> {
        let decode_error = |reason: String| Error::Decode {
            path: path.to_path_buf(),
            reason,
        };
        // A regular file of a plausible size: the decoder reads it whole.
        let (_, len) = crate::io::input::open_input(path)?;
        if len > MAX_RAW_BYTES {
            return Err(decode_error(format!(
                "{len} bytes, more than the {} MiB of the largest camera RAW files; not read",
                MAX_RAW_BYTES >> 20
            )));
        }
        // A decoder that fails on a malformed file by panicking must not take the caller down.
        let raw = std::panic::catch_unwind(|| rawler::decode_file(path))
            .map_err(|_| decode_error("the RAW decoder failed on this file".into()))?
            .map_err(|e| decode_error(e.to_string()))?;
        let cfa = match &raw.photometric {
            RawPhotometricInterpretation::Cfa(c) if raw.cpp == 1 => Some(c.cfa.clone()),
            _ if raw.cpp == 3 => None,
            _ => {
                return Err(Error::UnsupportedImage {
                    path: path.to_path_buf(),
                    reason: format!(
                        "RAW with {} sample(s) per pixel and this photometric layout is not read (2x2 colour filter mosaics and 3-sample linear DNG are)",
                        raw.cpp
                    ),
                });
            }
        };
        if let Some(c) = &cfa
            && (c.width != 2 || c.height != 2)
        {
            return Err(Error::UnsupportedImage {
                path: path.to_path_buf(),
                reason: format!(
                    "colour filter pattern {} ({}x{}) is not a 2x2 Bayer pattern (X-Trans and other layouts are not read)",
                    c.name, c.width, c.height
                ),
            });
        }
        let (w, h, cpp) = (raw.width, raw.height, raw.cpp);
        let data: Vec<f32> = match &raw.data {
            RawImageData::Integer(v) => v.iter().map(|&x| f32::from(x)).collect(),
            RawImageData::Float(v) => v.clone(),
        };
        if data.len() < w * h * cpp || w == 0 || h == 0 {
            return Err(decode_error(format!(
                "{} samples for a {w}x{h} sensor with {cpp} per pixel",
                data.len()
            )));
        }
        // The active area (without the masked border); quads follow the pattern's own phase
        // there, as colours are looked up by absolute position.
        let area = raw
            .active_area
            .map(|r| [r.p.x, r.p.y, r.d.w, r.d.h])
            .filter(|a| a[0] + a[2] <= w && a[1] + a[3] <= h && a[2] > 0 && a[3] > 0)
            .unwrap_or([0, 0, w, h]);
        // Per 2×2 position (row-major): black from the file's pattern, white likewise.
        let bl = &raw.blacklevel;
        let black_at = |row: usize, col: usize, c: usize| -> f32 {
            if bl.levels.is_empty() {
                return 0.0;
            }
            let (bw, bh, bc) = (bl.width.max(1), bl.height.max(1), bl.cpp.max(1));
            let i = ((row % bh) * bw + col % bw) * bc + c.min(bc - 1);
            bl.levels.get(i).map_or(0.0, |r| r.as_f32())
        };
        let whites = raw.whitelevel.as_vec();
        let white_of = |c: usize| -> f32 {
            whites
                .get(c)
                .or_else(|| whites.first())
                .copied()
                .unwrap_or(f32::from(u16::MAX))
        };
        let (ax, ay) = (area[0], area[1]);
        let black_levels = [
            black_at(ay, ax, 0),
            black_at(ay, ax + 1, 0),
            black_at(ay + 1, ax, 0),
            black_at(ay + 1, ax + 1, 0),
        ];
        // White balance: as shot, normalised to green; 1 where the file has none.
        let wb = raw.wb_coeffs;
        let green = wb[1];
        let balance = if wb[..3].iter().all(|v| v.is_finite() && *v > 0.0) && green > 0.0 {
            [wb[0] / green, 1.0, wb[2] / green]
        } else {
            [1.0, 1.0, 1.0]
        };
        let top = balance.iter().copied().fold(1.0f32, f32::max);
        // The largest code of an unsaturated sample: the maximum is kept for saturated ones.
        const FULL: f32 = 65534.0;
        let code =
            |v: f32, gain: f32| -> u16 { (v * gain / top * FULL).round().clamp(0.0, FULL) as u16 };
        let (out_w, out_h, samples, white_levels, binning) = match &cfa {
            Some(c) => {
                let (qw, qh) = (area[2] / 2, area[3] / 2);
                if qw == 0 || qh == 0 {
                    return Err(decode_error(
                        "the sensor area is smaller than one 2x2 quad".into(),
                    ));
                }
                let mut out = vec![0u16; qw * qh * 3];
                let mut whites4 = [0.0f32; 4];
                for (k, wl) in whites4.iter_mut().enumerate() {
                    *wl = white_of(c.color_at(ay + k / 2, ax + k % 2).min(2));
                }
                for qy in 0..qh {
                    for qx in 0..qw {
                        let mut sum = [0.0f32; 3];
                        let mut count = [0u32; 3];
                        let mut saturated = false;
                        for (k, &white) in whites4.iter().enumerate() {
                            let (row, col) = (ay + 2 * qy + k / 2, ax + 2 * qx + k % 2);
                            let colour = c.color_at(row, col);
                            if colour > 2 {
                                continue;
                            }
                            let raw_v = data[row * w + col];
                            let black = black_at(row, col, 0);
                            saturated |= raw_v >= white;
                            let range = (white - black).max(1.0);
                            sum[colour] += ((raw_v - black) / range).max(0.0);
                            count[colour] += 1;
                        }
                        let px = &mut out[(qy * qw + qx) * 3..][..3];
                        for ch in 0..3 {
                            px[ch] = if saturated {
                                u16::MAX
                            } else if count[ch] == 0 {
                                0
                            } else {
                                code(sum[ch] / count[ch] as f32, balance[ch])
                            };
                        }
                    }
                }
                (qw, qh, out, whites4, "2x2 CFA quad")
            }
            None => {
                let (ow, oh) = (area[2], area[3]);
                let mut out = vec![0u16; ow * oh * 3];
                for y in 0..oh {
                    for x in 0..ow {
                        let (row, col) = (ay + y, ax + x);
                        let base = (row * w + col) * 3;
                        let saturated = (0..3).any(|ch| data[base + ch] >= white_of(ch));
                        for ch in 0..3 {
                            let (black, white) = (black_at(row, col, ch), white_of(ch));
                            let v = ((data[base + ch] - black) / (white - black).max(1.0)).max(0.0);
                            out[(y * ow + x) * 3 + ch] = if saturated {
                                u16::MAX
                            } else {
                                code(v, balance[ch])
                            };
                        }
                    }
                }
                (
                    ow,
                    oh,
                    out,
                    [white_of(0), white_of(1), white_of(2), white_of(1)],
                    "pixel",
                )
            }
        };
        let camera = format!("{} {}", raw.make.trim(), raw.model.trim())
            .trim()
            .to_string();
        Ok((
            RawDecoded {
                width: out_w,
                height: out_h,
                channels: 3,
                stride: 3,
                format: SampleFormat::U16,
                samples: Samples::U16(samples),
                raw: None,
            },
            RawDevelopment {
                camera,
                cfa: cfa.map(|c| c.name).unwrap_or_default(),
                sensor: [w, h],
                area,
                black_levels,
                white_levels,
                white_balance: balance,
                binning,
            },
        ))
    }
}
