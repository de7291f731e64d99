//! Capture folders: assembling a capture (images + lights + mask) from files — an image list
//! with a lights file, or a folder in the DiLiGenT layout — and writing synthetic data sets.
//!
//! DiLiGenT layout (Shi et al., CVPR 2016): `filenames.txt` (image names in order),
//! `light_directions.txt` (`x y z` per line), `light_intensities.txt` (`r g b` per line, optional)
//! and `mask.png` (optional; object pixels > 0).

use crate::capture::lights::Lights;
use crate::capture::order::ImageOrder;
use crate::capture::stack::{ImageStack, LoadOptions, load_stack_with_ambient};
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask};
use crate::io::decode::read_mask;
use crate::progress::Progress;
use std::path::{Path, PathBuf};

/// Images, the lights that lit them, and the object mask: the input of a reconstruction.
#[derive(Debug, Clone)]
pub struct Capture {
    /// The images, divided by light intensity.
    pub stack: ImageStack,
    /// One light per image, in stack order.
    pub lights: Lights,
    /// Object pixels (all pixels when no mask was given).
    pub mask: Mask,
    /// Where the images came from (empty for in-memory captures).
    pub images: Vec<PathBuf>,
    /// The lights file, if any.
    pub lights_source: Option<PathBuf>,
    /// The mask file, if any.
    pub mask_source: Option<PathBuf>,
    /// The ambient image subtracted from every image (see
    /// [`crate::capture::stack::load_stack_with_ambient`]), if any.
    pub ambient_source: Option<PathBuf>,
}

/// True when `dir` is a folder with DiLiGenT's `filenames.txt` and `light_directions.txt`.
pub fn is_diligent_dir(dir: &Path) -> bool {
    dir.is_dir()
        && dir.join("filenames.txt").is_file()
        && dir.join("light_directions.txt").is_file()
}

impl Capture {
    /// The capture of images `images` only (indices, in the order given), with their lights
    /// and the same mask: for measuring what fewer lights give ([`ImageStack::select`]).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`images`) when the list is empty or an index is out of
    /// range.
    pub fn select(&self, images: &[usize]) -> Result<Capture> {
        let stack = self.stack.select(images)?;
        let lights = Lights::new(
            images
                .iter()
                .map(|&k| self.lights.lights()[k].clone())
                .collect(),
        )?;
        Ok(Capture {
            stack,
            lights,
            mask: self.mask.clone(),
            images: images
                .iter()
                .filter_map(|&k| self.images.get(k).cloned())
                .collect(),
            lights_source: self.lights_source.clone(),
            mask_source: self.mask_source.clone(),
            ambient_source: self.ambient_source.clone(),
        })
    }

    /// A capture from an in-memory stack.
    ///
    /// # Errors
    /// [`Error::LightsMismatch`] when counts differ; [`Error::DimensionMismatch`] when the mask's
    /// size differs; [`Error::Mask`] when the mask is empty.
    pub fn from_stack(stack: ImageStack, lights: Lights, mask: Option<Mask>) -> Result<Self> {
        if lights.len() != stack.count() {
            return Err(Error::LightsMismatch {
                reason: format!("{} lights for {} images", lights.len(), stack.count()),
            });
        }
        let mask = match mask {
            Some(m) => {
                Grid::new(stack.width(), stack.height(), ())
                    .check_same_size(&m, "mask vs images")?;
                if m.count() == 0 {
                    return Err(Error::Mask {
                        path: "<memory>".into(),
                        reason: "no pixel is set".into(),
                    });
                }
                m
            }
            None => Grid::new(stack.width(), stack.height(), true),
        };
        Ok(Capture {
            stack,
            lights,
            mask,
            images: Vec::new(),
            lights_source: None,
            mask_source: None,
            ambient_source: None,
        })
    }

    /// Loads `images` lit by the lights of `lights_file` (JSON or text; matched to the images by
    /// file name when the file names them, else by order), with an optional mask file.
    ///
    /// # Errors
    /// The errors of [`Lights::from_file`], [`Lights::matched_to`], [`load_stack`] and
    /// [`read_mask`]; [`Error::Mask`] when the mask's size differs from the images'.
    pub fn from_files(
        images: &[PathBuf],
        lights_file: &Path,
        mask_file: Option<&Path>,
        options: &LoadOptions,
        progress: &dyn Progress,
    ) -> Result<Self> {
        CaptureFiles::from_files(images, lights_file, mask_file)?.load(options, progress)
    }

    /// Loads a DiLiGenT-layout folder.
    ///
    /// # Errors
    /// [`Error::Dataset`] when `filenames.txt` or `light_directions.txt` is missing or they
    /// disagree in length; otherwise as [`Capture::from_files`].
    pub fn from_diligent(
        dir: &Path,
        options: &LoadOptions,
        progress: &dyn Progress,
    ) -> Result<Self> {
        Capture::from_diligent_masked(dir, None, options, progress)
    }

    /// [`Capture::from_diligent`] with the mask in `mask` instead of the folder's `mask.png`
    /// (its window is the part of the images that is stored).
    ///
    /// # Errors
    /// As [`Capture::from_diligent`]; [`Error::Mask`] when `mask` cannot be read, is empty or
    /// differs in size from the images (checked before any image is decoded).
    pub fn from_diligent_masked(
        dir: &Path,
        mask: Option<&Path>,
        options: &LoadOptions,
        progress: &dyn Progress,
    ) -> Result<Self> {
        CaptureFiles::from_diligent(dir, mask)?.load(options, progress)
    }

    /// Replaces the mask by the one in `path`.
    ///
    /// # Errors
    /// The errors of [`read_mask`]; [`Error::Mask`] when its size differs from the images', or
    /// when it reaches pixels outside the window that was loaded (the capture was loaded for
    /// another mask; load it with [`LoadOptions::window`] covering this one).
    pub fn with_mask_file(mut self, path: &Path) -> Result<Self> {
        let mask = load_mask_for(path, &self.stack)?;
        let read = self.stack.window();
        if let Some(needed) = mask.bounding_box()
            && !read.covers(&needed)
        {
            return Err(Error::Mask {
                path: path.to_path_buf(),
                reason: format!(
                    "spans {needed} but only {read} of the images were loaded (for another mask); load with LoadOptions::window covering it"
                ),
            });
        }
        self.mask = mask;
        self.mask_source = Some(path.to_path_buf());
        Ok(self)
    }

    fn load(
        images: Vec<PathBuf>,
        lights: Lights,
        lights_source: Option<&Path>,
        mask_file: Option<&Path>,
        ambient: Option<&Path>,
        options: &LoadOptions,
        progress: &dyn Progress,
    ) -> Result<Self> {
        // Read the mask first: only its bounding box is stored, and rows below it are not
        // decoded.
        let mask = mask_file.map(read_mask).transpose()?;
        // A mask of another size is refused before anything is decoded (its window would
        // otherwise choose the part of the images to read).
        if let (Some(m), Some(path), Some(first)) = (&mask, mask_file, images.first()) {
            let (w, h) = crate::io::decode::image_size(first)?;
            check_mask_dims(m, path, w, h)?;
        }
        let window = mask.as_ref().and_then(Mask::bounding_box);
        let options = LoadOptions {
            window: options.window.or(window),
            ..*options
        };
        let stack = load_stack_with_ambient(&images, &lights, ambient, &options, progress)?;
        let mask = match (mask, mask_file) {
            (Some(m), Some(path)) => check_mask_size(m, path, &stack)?,
            _ => Grid::new(stack.width(), stack.height(), true),
        };
        Ok(Capture {
            stack,
            lights,
            mask,
            images,
            lights_source: lights_source.map(Path::to_path_buf),
            mask_source: mask_file.map(Path::to_path_buf),
            ambient_source: ambient.map(Path::to_path_buf),
        })
    }
}

/// A capture's files, resolved (image list, lights matched to the images, mask file) but not
/// decoded: what [`Capture`] loads into memory and [`crate::run::stream`] reads in row bands.
#[derive(Debug, Clone)]
pub struct CaptureFiles {
    /// One image per light.
    pub images: Vec<PathBuf>,
    /// The lights, in image order.
    pub lights: Lights,
    /// The lights file.
    pub lights_source: Option<PathBuf>,
    /// The mask file, if any.
    pub mask_source: Option<PathBuf>,
    /// The ambient image (the scene with every lamp off), subtracted from every image when
    /// loaded; set by [`CaptureFiles::with_ambient`].
    pub ambient_source: Option<PathBuf>,
}

impl CaptureFiles {
    /// The same files with `ambient`, the scene photographed with every lamp off, to be
    /// subtracted from every image ([`crate::capture::stack::load_stack_with_ambient`]).
    ///
    /// # Errors
    /// [`Error::Io`] when it cannot be read, the errors of decoding its header, and
    /// [`Error::Ambient`] when its size differs from the first image's, before anything is
    /// decoded.
    pub fn with_ambient(mut self, ambient: &Path) -> Result<Self> {
        let size = crate::io::decode::image_size(ambient)?;
        if let Some(first) = self.images.first() {
            let images = crate::io::decode::image_size(first)?;
            crate::capture::stack::check_ambient_size(ambient, size, images)?;
        }
        self.ambient_source = Some(ambient.to_path_buf());
        Ok(self)
    }

    /// `images` lit by the lights of `lights_file` (matched as [`Capture::from_files`] does),
    /// with an optional mask file; numbered images in text order are refused when the lights
    /// are a plain list ([`ImageOrder::Checked`]).
    ///
    /// # Errors
    /// The errors of [`Lights::from_file`], [`Lights::matched_to`] and
    /// [`crate::capture::order::apply`].
    pub fn from_files(
        images: &[PathBuf],
        lights_file: &Path,
        mask_file: Option<&Path>,
    ) -> Result<Self> {
        Self::from_files_ordered(images, lights_file, mask_file, ImageOrder::Checked)
    }

    /// As [`CaptureFiles::from_files`], with the images put in the order `order` asks for
    /// before lights given as a plain list are paired with them by position. Lights that name
    /// their image are matched by name whatever the order; under [`ImageOrder::Checked`] their
    /// images are not checked.
    ///
    /// # Errors
    /// As [`CaptureFiles::from_files`]; [`Error::ImageOrder`] (with the numeric order) for
    /// numbered images in text order under [`ImageOrder::Checked`].
    pub fn from_files_ordered(
        images: &[PathBuf],
        lights_file: &Path,
        mask_file: Option<&Path>,
        order: ImageOrder,
    ) -> Result<Self> {
        let lights = Lights::from_file(lights_file)?;
        let named = lights.lights().iter().any(|l| l.file.is_some());
        let images = if named && order == ImageOrder::Checked {
            images.to_vec()
        } else {
            crate::capture::order::apply(images, order)?
        };
        Ok(CaptureFiles {
            lights: lights.matched_to(&images)?,
            images,
            lights_source: Some(lights_file.to_path_buf()),
            mask_source: mask_file.map(Path::to_path_buf),
            ambient_source: None,
        })
    }

    /// The files of a DiLiGenT-layout folder; `mask` replaces the folder's `mask.png`.
    ///
    /// # Errors
    /// As [`Capture::from_diligent_masked`], before any image is decoded.
    pub fn from_diligent(dir: &Path, mask: Option<&Path>) -> Result<Self> {
        let list = dir.join("filenames.txt");
        let dirs_file = dir.join("light_directions.txt");
        for f in [&list, &dirs_file] {
            if !f.is_file() {
                return Err(Error::Dataset {
                    path: dir.to_path_buf(),
                    reason: format!(
                        "missing {}; a DiLiGenT folder has filenames.txt, light_directions.txt, optionally light_intensities.txt and mask.png",
                        f.file_name()
                            .map(|n| n.to_string_lossy())
                            .unwrap_or_default()
                    ),
                });
            }
        }
        let text = crate::io::input::read_text(&list)?;
        let images: Vec<PathBuf> = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(|l| dir.join(l))
            .collect();
        let mut lights = Lights::from_file(&dirs_file)?;
        let intens = dir.join("light_intensities.txt");
        if intens.is_file() {
            lights = lights.with_intensities_file(&intens)?;
        }
        if lights.len() != images.len() {
            return Err(Error::Dataset {
                path: dir.to_path_buf(),
                reason: format!(
                    "filenames.txt lists {} images but light_directions.txt has {} lights",
                    images.len(),
                    lights.len()
                ),
            });
        }
        let folder_mask = dir.join("mask.png");
        let mask = mask
            .map(Path::to_path_buf)
            .or_else(|| folder_mask.is_file().then_some(folder_mask));
        Ok(CaptureFiles {
            images,
            lights,
            lights_source: Some(dirs_file),
            mask_source: mask,
            ambient_source: None,
        })
    }

    /// Decodes the images into a [`Capture`] (only the window the mask spans is stored).
    ///
    /// # Errors
    /// The errors of [`load_stack`] and [`read_mask`]; [`Error::Mask`] when the mask's size
    /// differs from the images'.
    pub fn load(&self, options: &LoadOptions, progress: &dyn Progress) -> Result<Capture> {
        Capture::load(
            self.images.clone(),
            self.lights.clone(),
            self.lights_source.as_deref(),
            self.mask_source.as_deref(),
            self.ambient_source.as_deref(),
            options,
            progress,
        )
    }
}

/// Reads a mask and checks it against the stack's size.
fn load_mask_for(path: &Path, stack: &ImageStack) -> Result<Mask> {
    check_mask_size(read_mask(path)?, path, stack)
}

/// `m`, read from `path`, when its size is the stack's.
fn check_mask_size(m: Mask, path: &Path, stack: &ImageStack) -> Result<Mask> {
    check_mask_dims(&m, path, stack.width(), stack.height())?;
    Ok(m)
}

/// Whether mask `m`, read from `path`, is `width`×`height`.
fn check_mask_dims(m: &Mask, path: &Path, width: usize, height: usize) -> Result<()> {
    if m.width() != width || m.height() != height {
        return Err(Error::Mask {
            path: path.to_path_buf(),
            reason: format!(
                "size {}x{} differs from the images' {width}x{height}",
                m.width(),
                m.height(),
            ),
        });
    }
    Ok(())
}

/// An image list in the layout of the classic 12-light data sets (`psmImages/<name>.txt`): a
/// line with the number of images, one image path per line, then optionally the mask's path.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImageList {
    /// The images, in order.
    pub images: Vec<PathBuf>,
    /// The mask, when the list names one.
    pub mask: Option<PathBuf>,
}

/// True when `path` is a `.txt` file whose first non-empty line is a whole number (an image
/// list, as opposed to a lights file, whose lines hold three numbers).
pub fn is_image_list(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("txt"))
        && crate::io::input::read_text(path).is_ok_and(|t| {
            let mut lines = t.lines().map(str::trim).filter(|l| !l.is_empty());
            lines.next().is_some_and(|l| l.parse::<usize>().is_ok())
                && lines
                    .next()
                    .is_some_and(|l| l.split_whitespace().any(|w| w.parse::<f64>().is_err()))
        })
}

/// Reads an image list (see [`ImageList`]). Paths are relative to the list's folder; a path
/// that does not exist there is tried without its leading folders (the lists of the classic
/// data set start with `psmImages/`, the folder the list sits in).
///
/// # Errors
/// [`Error::Io`] when unreadable; [`Error::Dataset`] naming the line when the count is missing,
/// the lines do not match it, or an image cannot be found.
pub fn read_image_list(path: &Path) -> Result<ImageList> {
    let text = crate::io::input::read_text(path)?;
    let bad = |reason: String| Error::Dataset {
        path: path.to_path_buf(),
        reason,
    };
    let lines: Vec<(usize, &str)> = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty())
        .collect();
    let Some(((_, first), rest)) = lines.split_first() else {
        return Err(bad("empty image list".into()));
    };
    let count: usize = first.parse().map_err(|_| {
        bad(format!(
            "line 1 must hold the number of images, found `{first}`"
        ))
    })?;
    if rest.len() < count || rest.len() > count + 1 {
        return Err(bad(format!(
            "{count} images announced but {} path line(s) follow (expected the images, then optionally the mask)",
            rest.len()
        )));
    }
    let base = path.parent().unwrap_or(Path::new("."));
    let resolve = |(line, name): &(usize, &str)| -> Result<PathBuf> {
        let rel = Path::new(name);
        if rel.is_absolute() {
            return Ok(rel.to_path_buf());
        }
        let parts: Vec<_> = rel.components().collect();
        (0..parts.len())
            .map(|skip| base.join(parts[skip..].iter().collect::<PathBuf>()))
            .find(|p| p.is_file())
            .ok_or_else(|| {
                bad(format!(
                    "line {line}: `{name}` is not found relative to {}",
                    base.display()
                ))
            })
    };
    let images = rest[..count]
        .iter()
        .map(resolve)
        .collect::<Result<Vec<_>>>()?;
    let mask = rest.get(count).map(resolve).transpose()?;
    Ok(ImageList { images, mask })
}

/// Capture folders on disk, written by the tests into temporary folders (tiny 16-bit PNGs whose
/// every sample is distinct, so that order, intensity division and windowing can be read off the
/// loaded values): DiLiGenT layout detection and resolution without decoding, loading in list
/// order divided by the stated intensities and cut to the mask's window, mask size checks
/// (before any image is decoded, and against the loaded window), lights matched to files by
/// name, image lists, and errors that name the folder, file, line or image index at fault.
#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::stack::GREY_WEIGHTS;
    use crate::io::output::{write_png8, write_png16};
    use crate::progress::Silent;
    use nalgebra::Vector3;
    use std::fs;

    /// Image size of the test folders.
    const W: usize = 6;
    const H: usize = 5;

    /// The 16-bit code of pixel `p` of image `k`: distinct for every (k, p), never 0 or 65535.
    fn code(k: usize, p: usize) -> u16 {
        (1000 + 9000 * k + 97 * p) as u16
    }

    /// Writes image `k` of the test folders (`W`×`H`, grey, 16-bit, codes [`code`]).
    fn write_image(path: &Path, k: usize) {
        let codes: Vec<u16> = (0..W * H).map(|p| code(k, p)).collect();
        write_png16(path, W, H, 1, &codes).unwrap();
    }

    /// Writes a `width`×`height` mask PNG with the pixels of `inside` set.
    fn write_mask(
        path: &Path,
        width: usize,
        height: usize,
        inside: impl Fn(usize, usize) -> bool,
    ) -> Mask {
        let mask = Grid::from_fn(width, height, inside);
        let bytes: Vec<u8> = mask
            .data()
            .iter()
            .map(|&m| if m { 255 } else { 0 })
            .collect();
        write_png8(path, width, height, 1, &bytes).unwrap();
        mask
    }

    /// Names of the four images of [`diligent`], in the order `filenames.txt` lists them (not
    /// the alphabetical one, so that order is tested).
    const NAMES: [&str; 4] = ["b.png", "a.png", "d.png", "c.png"];
    /// Their light directions, one `x y z` line each (not unit: they are normalised on load).
    const DIRECTIONS: [[f64; 3]; 4] = [
        [0.0, 0.0, 1.0],
        [1.0, 0.0, 1.0],
        [0.0, 1.0, 1.0],
        [-1.0, -1.0, 2.0],
    ];
    /// Their RGB intensities.
    const INTENSITIES: [[f64; 3]; 4] = [
        [1.0, 1.0, 1.0],
        [0.5, 0.5, 0.5],
        [2.0, 1.0, 0.5],
        [1.0, 2.0, 1.0],
    ];

    /// A DiLiGenT-layout folder in `dir`: `filenames.txt` (with blank lines and stray
    /// whitespace), `light_directions.txt`, `light_intensities.txt` and image `k` of [`NAMES`]
    /// written as image `k` ([`write_image`]); no mask.
    fn diligent(dir: &Path) {
        fs::write(
            dir.join("filenames.txt"),
            format!(
                "  {}\n\n{} \r\n{}\n{}\n\n",
                NAMES[0], NAMES[1], NAMES[2], NAMES[3]
            ),
        )
        .unwrap();
        let lines = |rows: &[[f64; 3]]| {
            rows.iter()
                .map(|r| format!("{} {} {}\n", r[0], r[1], r[2]))
                .collect::<String>()
        };
        fs::write(dir.join("light_directions.txt"), lines(&DIRECTIONS)).unwrap();
        fs::write(dir.join("light_intensities.txt"), lines(&INTENSITIES)).unwrap();
        for (k, name) in NAMES.iter().enumerate() {
            write_image(&dir.join(name), k);
        }
    }

    /// The loaded value expected for pixel `p` of image `k` of a grey file whose light has RGB
    /// intensity `e`: the code scaled to [0, 1], divided by the BT.601 mix of `e`.
    fn expected(k: usize, p: usize, e: [f64; 3]) -> f64 {
        let grey: f64 = GREY_WEIGHTS
            .iter()
            .zip(e)
            .map(|(w, i)| f64::from(*w) * i)
            .sum();
        f64::from(code(k, p)) / 65535.0 / grey
    }

    /// Relative accuracy of a loaded value: a handful of f32 roundings (u = 6·10⁻⁸ each).
    const LOADED: f64 = 1e-6;

    fn unit(d: [f64; 3]) -> Vector3<f64> {
        Vector3::from(d).normalize()
    }

    #[test]
    fn diligent_dir_needs_both_list_files() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        assert!(!is_diligent_dir(dir));
        fs::write(dir.join("filenames.txt"), "a.png\n").unwrap();
        assert!(!is_diligent_dir(dir), "light_directions.txt is missing");
        fs::create_dir(dir.join("light_directions.txt")).unwrap();
        assert!(!is_diligent_dir(dir), "light_directions.txt is a folder");
        fs::remove_dir(dir.join("light_directions.txt")).unwrap();
        fs::write(dir.join("light_directions.txt"), "0 0 1\n").unwrap();
        assert!(is_diligent_dir(dir));
        assert!(
            !is_diligent_dir(&dir.join("filenames.txt")),
            "a file is no folder"
        );
        assert!(!is_diligent_dir(&dir.join("absent")));
    }

    /// Resolving a folder reads only its text files: the images need not exist yet. Names are
    /// trimmed, blank lines skipped, the order kept; directions are normalised and carry the
    /// intensities file's values; `mask.png` is used when present and a given mask replaces it.
    #[test]
    fn diligent_folder_resolves_without_decoding() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        diligent(dir);
        for name in NAMES {
            fs::remove_file(dir.join(name)).unwrap();
        }
        let files = CaptureFiles::from_diligent(dir, None).unwrap();
        let want: Vec<PathBuf> = NAMES.iter().map(|n| dir.join(n)).collect();
        assert_eq!(files.images, want);
        assert_eq!(files.lights_source, Some(dir.join("light_directions.txt")));
        assert_eq!(files.mask_source, None);
        assert_eq!(files.lights.len(), 4);
        for (k, light) in files.lights.lights().iter().enumerate() {
            assert!(
                (light.direction - unit(DIRECTIONS[k])).norm() < 1e-15,
                "light {k}"
            );
            assert_eq!(light.intensity, INTENSITIES[k], "light {k}");
        }
        fs::write(dir.join("mask.png"), b"").unwrap();
        let files = CaptureFiles::from_diligent(dir, None).unwrap();
        assert_eq!(files.mask_source, Some(dir.join("mask.png")));
        let other = dir.join("other_mask.png");
        let files = CaptureFiles::from_diligent(dir, Some(&other)).unwrap();
        assert_eq!(files.mask_source, Some(other));
    }

    /// Loading a folder with a mask: images in list order, each divided by its light's grey
    /// intensity, only the mask's bounding box stored (NaN outside it), the mask and the
    /// sources recorded.
    #[test]
    fn diligent_folder_loads_in_list_order_within_the_mask_window() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        diligent(dir);
        // A mask spanning columns 1..4, rows 1..3 (not a full rectangle: its corner is off).
        let mask = write_mask(&dir.join("mask.png"), W, H, |x, y| {
            (1..4).contains(&x) && (1..3).contains(&y) && (x, y) != (3, 2)
        });
        let cap = Capture::from_diligent(dir, &LoadOptions::default(), &Silent).unwrap();
        assert_eq!((cap.stack.width(), cap.stack.height()), (W, H));
        assert_eq!(cap.stack.count(), 4);
        assert_eq!(cap.mask, mask);
        assert_eq!(
            cap.stack.window(),
            crate::grid::Window {
                x0: 1,
                y0: 1,
                x1: 4,
                y1: 3
            }
        );
        assert_eq!(cap.mask_source, Some(dir.join("mask.png")));
        assert_eq!(cap.lights_source, Some(dir.join("light_directions.txt")));
        let names: Vec<PathBuf> = NAMES.iter().map(|n| dir.join(n)).collect();
        assert_eq!(cap.images, names);
        let mut checked = 0;
        for (k, &intensity) in INTENSITIES.iter().enumerate() {
            for p in 0..W * H {
                let v = f64::from(cap.stack.value(k, 0, p));
                if cap.stack.window().contains(p % W, p / W) {
                    let want = expected(k, p, intensity);
                    assert!(
                        (v - want).abs() < LOADED * want,
                        "image {k} pixel {p}: {v} vs {want}"
                    );
                    checked += 1;
                } else {
                    assert!(v.is_nan(), "image {k} pixel {p} outside the window: {v}");
                }
            }
        }
        assert_eq!(checked, 4 * 3 * 2);
    }

    /// The folder's errors name the folder and what is wrong: a missing list file, lists of
    /// different lengths, an intensities file of the wrong length (naming that file), and an
    /// image that is listed but absent (an I/O error naming the image, on load).
    #[test]
    fn diligent_errors_name_the_folder_and_the_fault() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        diligent(dir);
        let directions = dir.join("light_directions.txt");
        let saved = fs::read_to_string(&directions).unwrap();

        fs::remove_file(&directions).unwrap();
        let e = CaptureFiles::from_diligent(dir, None).unwrap_err();
        assert!(
            matches!(&e, Error::Dataset { path, reason } if path == dir && reason.contains("missing light_directions.txt")),
            "{e}"
        );

        fs::write(&directions, format!("{saved}0.5 0.5 1\n")).unwrap();
        fs::write(
            dir.join("light_intensities.txt"),
            "1 1 1\n1 1 1\n1 1 1\n1 1 1\n1 1 1\n",
        )
        .unwrap();
        let e = CaptureFiles::from_diligent(dir, None).unwrap_err();
        assert!(
            matches!(&e, Error::Dataset { path, reason } if path == dir
                && reason.contains("filenames.txt lists 4 images but light_directions.txt has 5 lights")),
            "{e}"
        );

        fs::write(&directions, &saved).unwrap();
        let intensities = dir.join("light_intensities.txt");
        let e = CaptureFiles::from_diligent(dir, None).unwrap_err();
        assert!(
            matches!(&e, Error::LightsFile { path, reason, .. } if *path == intensities
                && reason.contains("5 intensity lines for 4 lights")),
            "{e}"
        );

        fs::write(&intensities, "1\n1\n1\n1\n").unwrap();
        fs::remove_file(dir.join(NAMES[2])).unwrap();
        let files = CaptureFiles::from_diligent(dir, None).unwrap();
        let e = files.load(&LoadOptions::default(), &Silent).unwrap_err();
        assert!(
            matches!(&e, Error::Io { path, .. } if *path == dir.join(NAMES[2])),
            "{e}"
        );
    }

    /// A mask of another size is refused, naming the mask and both sizes, before any image is
    /// decoded: with the second image corrupt, the mask error comes first; with a mask of the
    /// right size the corrupt image is what is reported, by name. An image of another size is
    /// reported with its name and index.
    #[test]
    fn mask_size_is_checked_before_decoding() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        diligent(dir);
        let second = dir.join(NAMES[1]);
        fs::write(&second, b"not a PNG").unwrap();
        let wide = dir.join("wide.png");
        write_mask(&wide, W + 1, H, |_, _| true);
        let e = Capture::from_diligent_masked(dir, Some(&wide), &LoadOptions::default(), &Silent)
            .unwrap_err();
        assert!(
            matches!(&e, Error::Mask { path, reason } if *path == wide
                && reason.contains("7x5") && reason.contains("6x5")),
            "{e}"
        );
        let fitting = dir.join("fitting.png");
        write_mask(&fitting, W, H, |x, _| x > 2);
        let e =
            Capture::from_diligent_masked(dir, Some(&fitting), &LoadOptions::default(), &Silent)
                .unwrap_err();
        assert!(
            matches!(&e, Error::Decode { path, .. } if *path == second),
            "{e}"
        );

        write_image(&second, 1);
        let codes = vec![5000u16; (W + 2) * H];
        write_png16(&dir.join(NAMES[3]), W + 2, H, 1, &codes).unwrap();
        let e = Capture::from_diligent(dir, &LoadOptions::default(), &Silent).unwrap_err();
        assert!(
            matches!(&e, Error::SizeMismatch { path, index: 3, found_width: 8, width: 6, .. }
                if *path == dir.join(NAMES[3])),
            "{e}"
        );
    }

    /// Replacing the mask of a loaded capture: the new mask must have the images' size and lie
    /// within the window that was loaded for the old one; a mask that does replaces it.
    #[test]
    fn a_replacing_mask_must_fit_the_loaded_window() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        diligent(dir);
        write_mask(&dir.join("mask.png"), W, H, |x, y| x >= 2 && y >= 1);
        let cap = Capture::from_diligent(dir, &LoadOptions::default(), &Silent).unwrap();

        let beyond = dir.join("beyond.png");
        write_mask(&beyond, W, H, |x, y| x >= 1 && y >= 1);
        let e = cap.clone().with_mask_file(&beyond).unwrap_err();
        assert!(
            matches!(&e, Error::Mask { path, reason } if *path == beyond && reason.contains("spans")),
            "{e}"
        );
        let small = dir.join("small.png");
        write_mask(&small, W - 1, H, |_, _| true);
        let e = cap.clone().with_mask_file(&small).unwrap_err();
        assert!(
            matches!(&e, Error::Mask { path, reason } if *path == small && reason.contains("5x5")),
            "{e}"
        );
        let inner = dir.join("inner.png");
        let want = write_mask(&inner, W, H, |x, y| x == 3 && y == 2);
        let cap = cap.with_mask_file(&inner).unwrap();
        assert_eq!(cap.mask, want);
        assert_eq!(cap.mask_source, Some(inner));
    }

    /// An in-memory capture: the light count and the mask's size must match the stack, an
    /// empty mask is refused, and no mask means every pixel.
    #[test]
    fn in_memory_capture_checks_lights_and_mask() {
        let stack = ImageStack::from_images(W, H, 1, vec![vec![0.5; W * H]; 3]).unwrap();
        let lights = Lights::fibonacci(3, 30.0).unwrap();
        let e = Capture::from_stack(stack.clone(), Lights::fibonacci(4, 30.0).unwrap(), None)
            .unwrap_err();
        assert!(
            matches!(&e, Error::LightsMismatch { reason } if reason.contains("4 lights for 3 images")),
            "{e}"
        );
        let e = Capture::from_stack(
            stack.clone(),
            lights.clone(),
            Some(Grid::new(W, H + 1, true)),
        )
        .unwrap_err();
        assert!(
            matches!(
                e,
                Error::DimensionMismatch {
                    found_height: 6,
                    height: 5,
                    ..
                }
            ),
            "{e}"
        );
        let e = Capture::from_stack(stack.clone(), lights.clone(), Some(Grid::new(W, H, false)))
            .unwrap_err();
        assert!(matches!(e, Error::Mask { .. }), "{e}");
        let cap = Capture::from_stack(stack, lights, None).unwrap();
        assert_eq!(cap.mask.count(), W * H);
        assert!(cap.images.is_empty() && cap.lights_source.is_none() && cap.mask_source.is_none());
    }

    /// A JSON lights file naming the images is matched to them by file name, whatever order
    /// the images are given in: each loaded image gets the direction and intensity of the light
    /// that names it. Unnamed lights follow the images' order, and the counts must agree; an
    /// image no light names is reported with its index and path.
    #[test]
    fn lights_naming_files_are_matched_by_name() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        for k in 0..3 {
            write_image(&dir.join(format!("img_{k}.png")), k);
        }
        let lights = Lights::new(
            (0..3)
                .map(|k| crate::capture::lights::Light {
                    direction: unit(DIRECTIONS[k]),
                    intensity: INTENSITIES[k],
                    file: Some(format!("img_{k}.png")),
                    position: None,
                    anisotropy: None,
                })
                .collect(),
        )
        .unwrap();
        let json = dir.join("lights.json");
        fs::write(&json, lights.to_json()).unwrap();
        // The images in another order than the lights file's.
        let order = [2, 0, 1];
        let images: Vec<PathBuf> = order
            .iter()
            .map(|k| dir.join(format!("img_{k}.png")))
            .collect();
        let cap =
            Capture::from_files(&images, &json, None, &LoadOptions::default(), &Silent).unwrap();
        assert_eq!(cap.images, images);
        assert_eq!(cap.lights_source, Some(json.clone()));
        assert_eq!(cap.mask.count(), W * H);
        for (i, &k) in order.iter().enumerate() {
            let light = &cap.lights.lights()[i];
            assert!(
                (light.direction - unit(DIRECTIONS[k])).norm() < 1e-12,
                "image {i}"
            );
            for p in 0..W * H {
                let v = f64::from(cap.stack.value(i, 0, p));
                let want = expected(k, p, INTENSITIES[k]);
                assert!(
                    (v - want).abs() < LOADED * want,
                    "image {i} pixel {p}: {v} vs {want}"
                );
            }
        }

        let stray = dir.join("img_9.png");
        let mut more = images.clone();
        more.push(stray.clone());
        let e = CaptureFiles::from_files(&more, &json, None).unwrap_err();
        assert!(
            matches!(&e, Error::LightsMismatch { reason }
                if reason.contains("image 3") && reason.contains(&*stray.to_string_lossy())),
            "{e}"
        );

        let text = dir.join("lights.txt");
        fs::write(&text, "0 0 1\n1 0 1\n0 1 1\n").unwrap();
        let files = CaptureFiles::from_files(&images, &text, None).unwrap();
        assert!((files.lights.lights()[0].direction - Vector3::z()).norm() < 1e-15);
        let e = CaptureFiles::from_files(&images[..2], &text, None).unwrap_err();
        assert!(
            matches!(&e, Error::LightsMismatch { reason } if reason.contains("3 lights for 2 images")),
            "{e}"
        );
    }

    /// Selecting images keeps lights, files and samples in step; an index out of range is
    /// refused.
    #[test]
    fn selected_images_keep_their_lights_and_files() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        diligent(dir);
        let cap = Capture::from_diligent(dir, &LoadOptions::default(), &Silent).unwrap();
        let sub = cap.select(&[3, 0]).unwrap();
        assert_eq!(sub.images, vec![dir.join(NAMES[3]), dir.join(NAMES[0])]);
        assert_eq!(sub.lights.lights()[0], cap.lights.lights()[3]);
        assert_eq!(sub.lights.lights()[1], cap.lights.lights()[0]);
        assert_eq!(sub.stack.plane(0, 0), cap.stack.plane(3, 0));
        assert_eq!(sub.stack.plane(1, 0), cap.stack.plane(0, 0));
        assert_eq!(sub.mask, cap.mask);
        let e = cap.select(&[0, 4]).unwrap_err();
        assert!(
            matches!(e, Error::InvalidParameter { name: "images", .. }),
            "{e}"
        );
    }

    /// An image list in the classic layout: the list sits in `psmImages/` and names its images
    /// `psmImages/…`, which resolve beside it; names relative to the list's folder resolve
    /// directly; the optional last line is the mask.
    #[test]
    fn image_list_resolves_paths_beside_the_list() {
        let tmp = tempfile::tempdir().unwrap();
        let psm = tmp.path().join("psmImages");
        fs::create_dir_all(psm.join("cat")).unwrap();
        for name in [
            "cat/cat.0.png",
            "cat/cat.1.png",
            "cat/cat.mask.png",
            "plain.png",
        ] {
            fs::write(psm.join(name), b"").unwrap();
        }
        let list = psm.join("cat.txt");
        fs::write(
            &list,
            "3\npsmImages/cat/cat.0.png\n\n  cat/cat.1.png  \nplain.png\npsmImages/cat/cat.mask.png\n",
        )
        .unwrap();
        assert!(is_image_list(&list));
        let l = read_image_list(&list).unwrap();
        assert_eq!(
            l.images,
            vec![
                psm.join("cat/cat.0.png"),
                psm.join("cat/cat.1.png"),
                psm.join("plain.png")
            ]
        );
        assert_eq!(l.mask, Some(psm.join("cat/cat.mask.png")));
        fs::write(&list, "2\ncat/cat.0.png\ncat/cat.1.png\n").unwrap();
        assert_eq!(read_image_list(&list).unwrap().mask, None);
    }

    /// Malformed lists are refused with the list's path and the line at fault (counted in the
    /// file, blank lines included).
    #[test]
    fn image_list_errors_name_the_line() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        fs::write(dir.join("a.png"), b"").unwrap();
        let list = dir.join("list.txt");
        let error = |text: &str| {
            fs::write(&list, text).unwrap();
            match read_image_list(&list).unwrap_err() {
                Error::Dataset { path, reason } => {
                    assert_eq!(path, list);
                    reason
                }
                e => panic!("{e}"),
            }
        };
        assert!(error("").contains("empty"));
        let r = error("two\na.png\na.png\n");
        assert!(r.contains("line 1") && r.contains("`two`"), "{r}");
        let r = error("3\na.png\na.png\n");
        assert!(r.contains("3 images announced but 2"), "{r}");
        let r = error("1\na.png\na.png\na.png\n");
        assert!(r.contains("1 images announced but 3"), "{r}");
        let r = error("2\na.png\n\n\nmissing.png\n");
        assert!(r.contains("line 5") && r.contains("`missing.png`"), "{r}");
        let e = read_image_list(&dir.join("absent.txt")).unwrap_err();
        assert!(
            matches!(&e, Error::Io { path, .. } if *path == dir.join("absent.txt")),
            "{e}"
        );
    }

    /// Image lists are told from lights files (whose lines after the count are numbers) and
    /// from other files by their extension and first two lines.
    #[test]
    fn image_lists_are_told_from_lights_files() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let write = |name: &str, text: &str| {
            let p = dir.join(name);
            fs::write(&p, text).unwrap();
            p
        };
        assert!(is_image_list(&write("list.txt", "\n2\na.png\nb.png\n")));
        assert!(is_image_list(&write("LIST.TXT", "1\na.png\n")));
        assert!(!is_image_list(&write("lights.txt", "2\n0 0 1\n0.5 0 1\n")));
        assert!(!is_image_list(&write("list.lst", "1\na.png\n")));
        assert!(!is_image_list(&write("words.txt", "images\na.png\n")));
        assert!(!is_image_list(&write("count.txt", "1\n")));
        assert!(!is_image_list(&dir.join("absent.txt")));
    }
}
