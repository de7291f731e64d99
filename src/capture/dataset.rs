//! Capture folders: assembling a capture (images + lights + mask) from files — an image list
//! with a lights file, or a folder in the DiLiGenT layout — and writing synthetic data sets.
//!
//! DiLiGenT layout (Shi et al., CVPR 2016): `filenames.txt` (image names in order),
//! `light_directions.txt` (`x y z` per line), `light_intensities.txt` (`r g b` per line, optional)
//! and `mask.png` (optional; object pixels > 0).

use crate::capture::lights::Lights;
use crate::capture::stack::{ImageStack, LoadOptions, load_stack};
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
        let stack = load_stack(&images, &lights, &options, progress)?;
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
}

impl CaptureFiles {
    /// `images` lit by the lights of `lights_file` (matched as [`Capture::from_files`] does),
    /// with an optional mask file.
    ///
    /// # Errors
    /// The errors of [`Lights::from_file`] and [`Lights::matched_to`].
    pub fn from_files(
        images: &[PathBuf],
        lights_file: &Path,
        mask_file: Option<&Path>,
    ) -> Result<Self> {
        Ok(CaptureFiles {
            lights: Lights::from_file(lights_file)?.matched_to(images)?,
            images: images.to_vec(),
            lights_source: Some(lights_file.to_path_buf()),
            mask_source: mask_file.map(Path::to_path_buf),
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
        let text = std::fs::read_to_string(&list).map_err(|e| Error::io(&list, e))?;
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
        && std::fs::read_to_string(path).is_ok_and(|t| {
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
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
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
