//! Writing results: float EXR maps, PNG previews and JSON, all atomically.
//!
//! Every file is first written to a temporary and put in place only when all files of the run
//! were written ([`OutputDir::commit`]). On Linux the temporary is an unnamed file
//! (`O_TMPFILE`) in the destination folder: it gets its name only at the commit, so a failed,
//! interrupted (Ctrl-C) or killed (`SIGKILL`) run leaves nothing behind. Where the file system
//! cannot create unnamed files, it is a hidden `.NAME.tmp-PID` beside the destination, removed
//! when the [`OutputDir`] is dropped uncommitted (a killed process can leave those).

use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::io::decode::linear_to_srgb;
use crate::io::exr::encode_exr;
use crate::io::png::{encode_png8, encode_png16};
use std::fs::File;
use std::io::{Seek, Write};
use std::path::{Path, PathBuf};

/// A folder that receives a set of output files atomically.
#[derive(Debug)]
pub struct OutputDir {
    dir: PathBuf,
    staged: Vec<Staged>,
    /// Whether to try unnamed temporaries first (off only in tests of the fallback).
    anonymous: bool,
}

/// A written file waiting for the commit.
#[derive(Debug)]
struct Staged {
    temp: Temp,
    dest: PathBuf,
}

/// Where a staged file's bytes are.
#[derive(Debug)]
enum Temp {
    /// An unnamed file in the destination's folder (Linux `O_TMPFILE`): it vanishes with the
    /// process unless linked into place.
    Anonymous(File),
    /// A hidden file beside the destination.
    Named(PathBuf),
}

/// A file of an [`OutputDir`] being written ([`OutputDir::begin`]): a temporary that becomes
/// the file only when staged ([`OutputDir::add`]) and committed. Dropped before that, it leaves
/// nothing behind.
#[derive(Debug)]
pub struct PendingFile {
    file: File,
    /// The hidden name of the temporary, where it has one.
    named: Option<NamedTemp>,
    dest: PathBuf,
}

impl PendingFile {
    /// The temporary to write to.
    pub fn file_mut(&mut self) -> &mut File {
        &mut self.file
    }

    /// The path the file will have, to name in errors.
    pub fn path(&self) -> &Path {
        &self.dest
    }
}

/// A named temporary, removed when dropped unless kept.
#[derive(Debug)]
struct NamedTemp(PathBuf);

impl NamedTemp {
    /// The path, no longer removed on drop.
    fn keep(mut self) -> PathBuf {
        std::mem::take(&mut self.0)
    }
}

impl Drop for NamedTemp {
    fn drop(&mut self) {
        if !self.0.as_os_str().is_empty() {
            let _ = std::fs::remove_file(&self.0);
        }
    }
}

/// An unnamed file in folder `dir`, or `None` where the platform or file system cannot make
/// one.
#[cfg(target_os = "linux")]
fn anonymous_file(dir: &Path) -> Option<File> {
    use std::os::unix::fs::OpenOptionsExt;
    std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .mode(0o644)
        .custom_flags(libc::O_TMPFILE)
        .open(dir)
        .ok()
}

#[cfg(not(target_os = "linux"))]
fn anonymous_file(_: &Path) -> Option<File> {
    None
}

/// Gives the unnamed file `file` the name `dest`: a hard link through `/proc/self/fd`, straight
/// to `dest` when it does not exist, else to a hidden temporary renamed over it (so an existing
/// file is replaced atomically). Without `/proc`, the bytes are copied to the temporary.
#[cfg(target_os = "linux")]
fn link_into_place(file: &mut File, dest: &Path) -> std::io::Result<()> {
    use std::ffi::CString;
    use std::os::fd::AsRawFd;
    use std::os::unix::ffi::OsStrExt;
    let link = |to: &Path| -> std::io::Result<()> {
        let from = CString::new(format!("/proc/self/fd/{}", file.as_raw_fd()))?;
        let to = CString::new(to.as_os_str().as_bytes())?;
        // SAFETY: both arguments are valid NUL-terminated paths that outlive the call;
        // linkat only reads them.
        #[allow(unsafe_code)]
        let r = unsafe {
            libc::linkat(
                libc::AT_FDCWD,
                from.as_ptr(),
                libc::AT_FDCWD,
                to.as_ptr(),
                libc::AT_SYMLINK_FOLLOW,
            )
        };
        if r == 0 {
            Ok(())
        } else {
            Err(std::io::Error::last_os_error())
        }
    };
    match link(dest) {
        Ok(()) => return Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(_) => return copy_into_place(file, dest),
    }
    let tmp = temp_path(dest);
    let _ = std::fs::remove_file(&tmp);
    link(&tmp)?;
    std::fs::rename(&tmp, dest).inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}

#[cfg(not(target_os = "linux"))]
fn link_into_place(file: &mut File, dest: &Path) -> std::io::Result<()> {
    copy_into_place(file, dest)
}

/// Copies the bytes of `file` to a hidden temporary beside `dest` and renames it over `dest`.
fn copy_into_place(file: &mut File, dest: &Path) -> std::io::Result<()> {
    let tmp = temp_path(dest);
    let result = (|| {
        file.rewind()?;
        let mut out = File::create(&tmp)?;
        std::io::copy(file, &mut out)?;
        std::fs::rename(&tmp, dest)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// One named channel of an EXR file.
pub type ExrChannel<'a> = (&'a str, &'a [f32]);

/// The hidden temporary beside `dest`.
fn temp_path(dest: &Path) -> PathBuf {
    let name = dest
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    dest.with_file_name(format!(".{name}.tmp-{}", std::process::id()))
}

/// Checks that `dir` can take a new set of outputs without overwriting anything: it does not
/// exist yet, or it is an empty folder. (The command line calls this unless `--force` is given.)
///
/// # Errors
/// [`Error::OutputExists`] when `dir` is a folder holding entries; [`Error::Io`] when it exists
/// but is not a folder, or cannot be listed.
pub fn ensure_fresh_dir(dir: &Path) -> Result<()> {
    match std::fs::metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(Error::io(
            dir,
            std::io::Error::new(
                e.kind(),
                format!("cannot be used as the output folder: {e}"),
            ),
        )),
        Ok(m) if !m.is_dir() => Err(Error::io(
            dir,
            std::io::Error::other("exists and is not a folder; pass a folder for the outputs"),
        )),
        Ok(_) => {
            let entries = std::fs::read_dir(dir)
                .map_err(|e| Error::io(dir, e))?
                .count();
            if entries == 0 {
                Ok(())
            } else {
                Err(Error::OutputExists {
                    path: dir.to_path_buf(),
                    what: format!("the output folder already exists and holds {entries} entries"),
                })
            }
        }
    }
}

/// Checks, before any work is done, that files can be created in the output folder `dir`:
/// in `dir` itself when it exists, else in its nearest existing parent (where it would be
/// created). A probe file is created there and removed at once.
///
/// # Errors
/// [`Error::Io`] naming `dir` (and the folder tried) when nothing can be created there.
pub fn ensure_writable_dir(dir: &Path) -> Result<()> {
    let mut base = dir;
    while std::fs::symlink_metadata(base).is_err() {
        match base.parent() {
            Some(p) if !p.as_os_str().is_empty() => base = p,
            _ => {
                base = Path::new(".");
                break;
            }
        }
    }
    let probe = base.join(format!(".photostereo-write-check-{}", std::process::id()));
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            // Best effort: the probe is empty and hidden.
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) => Err(Error::io(
            dir,
            std::io::Error::new(
                e.kind(),
                if base == dir {
                    format!("the output folder cannot be written: {e}")
                } else {
                    format!(
                        "the output folder cannot be created in {}: {e}",
                        base.display()
                    )
                },
            ),
        )),
    }
}

/// Checks that the output file `path` does not exist yet.
///
/// # Errors
/// [`Error::OutputExists`] when it does.
pub fn ensure_fresh_file(path: &Path) -> Result<()> {
    if std::fs::symlink_metadata(path).is_ok() {
        return Err(Error::OutputExists {
            path: path.to_path_buf(),
            what: "the output file already exists".into(),
        });
    }
    Ok(())
}

impl OutputDir {
    /// Creates `dir` (and parents) if needed.
    ///
    /// # Errors
    /// [`Error::Io`] when the folder cannot be created or is not a folder.
    pub fn create(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        Ok(OutputDir {
            dir: dir.to_path_buf(),
            staged: Vec::new(),
            anonymous: true,
        })
    }

    /// The destination folder.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Opens a temporary for the file `name` (a file name, or a relative path whose folders
    /// are created), to be written and then staged with [`OutputDir::add`]; dropped instead, it
    /// leaves nothing behind.
    ///
    /// # Errors
    /// [`Error::Io`] when the folder or the temporary cannot be created.
    pub fn begin(&self, name: &str) -> Result<PendingFile> {
        let dest = self.dir.join(name);
        let parent = dest.parent().unwrap_or(&self.dir);
        std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        if let Some(file) = self.anonymous.then(|| anonymous_file(parent)).flatten() {
            return Ok(PendingFile {
                file,
                named: None,
                dest,
            });
        }
        let tmp = temp_path(&dest);
        let file = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
        Ok(PendingFile {
            file,
            named: Some(NamedTemp(tmp)),
            dest,
        })
    }

    /// Stages a file opened with [`OutputDir::begin`] and written: it is put in place by
    /// [`OutputDir::commit`].
    pub fn add(&mut self, file: PendingFile) {
        let PendingFile { file, named, dest } = file;
        let temp = match named {
            Some(n) => {
                drop(file);
                Temp::Named(n.keep())
            }
            None => Temp::Anonymous(file),
        };
        self.staged.push(Staged { temp, dest });
    }

    /// Writes `name` to a temporary with `write` (given the file and the path to name in
    /// errors), to be put in place by [`OutputDir::commit`].
    fn stage(
        &mut self,
        name: &str,
        write: impl FnOnce(&mut File, &Path) -> Result<()>,
    ) -> Result<()> {
        let mut file = self.begin(name)?;
        let dest = file.dest.clone();
        write(file.file_mut(), &dest)?;
        self.add(file);
        Ok(())
    }

    /// Stages a float32 EXR file `name` with the given channels (ZIP compression) and string
    /// attributes in its header.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when a channel's length is not `width * height`;
    /// [`Error::Encode`] or [`Error::Io`] when writing fails.
    pub fn stage_exr(
        &mut self,
        name: &str,
        width: usize,
        height: usize,
        channels: &[ExrChannel],
        attributes: &[(&str, String)],
    ) -> Result<()> {
        self.stage(name, |file, path| {
            encode_exr(file, path, width, height, channels, attributes)
        })
    }

    /// Stages an 8-bit PNG (`channels` 1 or 3, interleaved).
    ///
    /// # Errors
    /// [`Error::Encode`] or [`Error::Io`] when writing fails.
    pub fn stage_png8(
        &mut self,
        name: &str,
        width: usize,
        height: usize,
        channels: usize,
        data: &[u8],
    ) -> Result<()> {
        self.stage(name, |file, path| {
            encode_png8(file, path, width, height, channels, data)
        })
    }

    /// Stages a 16-bit PNG (`channels` 1 or 3, interleaved).
    ///
    /// # Errors
    /// [`Error::Encode`] or [`Error::Io`] when writing fails.
    pub fn stage_png16(
        &mut self,
        name: &str,
        width: usize,
        height: usize,
        channels: usize,
        data: &[u16],
    ) -> Result<()> {
        self.stage(name, |file, path| {
            encode_png16(file, path, width, height, channels, data)
        })
    }

    /// Stages a file with the given bytes (JSON, text).
    ///
    /// # Errors
    /// [`Error::Io`] when writing fails.
    pub fn stage_bytes(&mut self, name: &str, bytes: &[u8]) -> Result<()> {
        self.stage(name, |file, path| {
            file.write_all(bytes).map_err(|e| Error::io(path, e))?;
            file.sync_all().map_err(|e| Error::io(path, e))
        })
    }

    /// Puts every staged file in place; returns the final paths. While it runs,
    /// [`hold_commits`] waits.
    ///
    /// # Errors
    /// [`Error::Io`] when a file cannot be put in place (the remaining temporaries are
    /// removed).
    pub fn commit(mut self) -> Result<Vec<PathBuf>> {
        let _commit = hold_commits();
        let staged = std::mem::take(&mut self.staged);
        let mut done = Vec::with_capacity(staged.len());
        let mut iter = staged.into_iter();
        while let Some(Staged { temp, dest }) = iter.next() {
            let result = match temp {
                Temp::Anonymous(mut file) => link_into_place(&mut file, &dest),
                Temp::Named(tmp) => std::fs::rename(&tmp, &dest).inspect_err(|_| {
                    let _ = std::fs::remove_file(&tmp);
                }),
            };
            if let Err(e) = result {
                for rest in iter {
                    if let Temp::Named(t) = rest.temp {
                        let _ = std::fs::remove_file(t);
                    }
                }
                return Err(Error::io(dest, e));
            }
            done.push(dest);
        }
        Ok(done)
    }
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        // Unnamed files vanish when closed; named ones are removed.
        for staged in &self.staged {
            if let Temp::Named(tmp) = &staged.temp {
                let _ = std::fs::remove_file(tmp);
            }
        }
    }
}

/// Held by [`OutputDir::commit`] while it puts files in place.
static COMMITS: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Waits for a commit in progress to finish and keeps new ones from starting while the guard
/// lives: an interrupt handler takes it before exiting, so that a run stops either before its
/// outputs appear or after all of them are in place.
pub fn hold_commits() -> std::sync::MutexGuard<'static, ()> {
    COMMITS
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Writes a float32 EXR (ZIP) at `path` directly (not atomically; see [`OutputDir`]).
///
/// # Errors
/// As [`OutputDir::stage_exr`].
pub fn write_exr(
    path: &Path,
    width: usize,
    height: usize,
    channels: &[ExrChannel],
    attributes: &[(&str, String)],
) -> Result<()> {
    let mut file = File::create(path).map_err(|e| Error::io(path, e))?;
    encode_exr(&mut file, path, width, height, channels, attributes)
}

/// Writes an 8-bit PNG with 1 or 3 interleaved channels.
///
/// # Errors
/// [`Error::Encode`] or [`Error::Io`].
pub fn write_png8(
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    data: &[u8],
) -> Result<()> {
    let mut file = File::create(path).map_err(|e| Error::io(path, e))?;
    encode_png8(&mut file, path, width, height, channels, data)
}

/// Writes a 16-bit PNG with 1 or 3 interleaved channels.
///
/// # Errors
/// [`Error::Encode`] or [`Error::Io`].
pub fn write_png16(
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    data: &[u16],
) -> Result<()> {
    let mut file = File::create(path).map_err(|e| Error::io(path, e))?;
    encode_png16(&mut file, path, width, height, channels, data)
}

/// Splits a normal map into its n_x, n_y, n_z planes (for the R, G, B channels of an EXR).
pub fn normal_planes(normals: &NormalMap) -> [Vec<f32>; 3] {
    [0, 1, 2].map(|c| normals.data().iter().map(|n| n[c]).collect())
}

/// A normal map coloured the usual way: RGB = (n + 1)/2 with y up, black where undefined.
pub fn normal_preview(normals: &NormalMap) -> Vec<u8> {
    let mut out = Vec::with_capacity(normals.len() * 3);
    for n in normals.data() {
        for c in 0..3 {
            let v = n[c];
            out.push(if v.is_finite() {
                ((v + 1.0) * 0.5 * 255.0).round().clamp(0.0, 255.0) as u8
            } else {
                0
            });
        }
    }
    out
}

/// The factor that turns `depth` into a height towards the camera in pixel units: 1 for an
/// orthographic map (already one); under a pinhole `camera`, where depth is along the optical
/// axis up to scale (larger is farther), −f/Z̄ with f the mean focal length in pixels and Z̄ the
/// median finite depth, since a pixel spans Z̄/f at the object's distance.
pub fn height_scale(depth: &ScalarMap, camera: Option<&crate::camera::Intrinsics>) -> f32 {
    let Some(k) = camera else {
        return 1.0;
    };
    let mut finite: Vec<f32> = depth
        .data()
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    let median = if finite.is_empty() {
        1.0
    } else {
        let mid = finite.len() / 2;
        *finite.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    let f = 0.5 * (k.fx + k.fy) as f32;
    if median.abs() > f32::MIN_POSITIVE && f.is_finite() {
        -f / median
    } else {
        -1.0
    }
}

/// A depth map shown as a shaded relief (normals of the depth map lit from the upper left),
/// black where undefined.
///
/// Without `camera` the map is an orthographic height in pixel units (larger is nearer). With
/// one, it is depth along the optical axis up to scale (larger is farther), whose changes from
/// pixel to pixel are a tiny fraction of its value; it is first turned into a height in pixel
/// units at the object's median distance ([`height_scale`]), so that the relief shows the
/// object's slopes.
pub fn depth_preview(depth: &ScalarMap, camera: Option<&crate::camera::Intrinsics>) -> Vec<u8> {
    let (w, h) = (depth.width(), depth.height());
    let l = nalgebra::Vector3::new(-1.0f32, 1.0, 1.0).normalize();
    let scaled: Vec<f32>;
    let d = match camera {
        None => depth.data(),
        Some(_) => {
            let s = height_scale(depth, camera);
            scaled = depth.data().iter().map(|v| v * s).collect();
            &scaled
        }
    };
    let at = |x: isize, y: isize| -> Option<f32> {
        (x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h)
            .then(|| d[y as usize * w + x as usize])
            .filter(|v| v.is_finite())
    };
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let (xi, yi) = (x as isize, y as isize);
            let Some(z) = at(xi, yi) else { continue };
            let dx = match (at(xi - 1, yi), at(xi + 1, yi)) {
                (Some(a), Some(b)) => (b - a) / 2.0,
                (None, Some(b)) => b - z,
                (Some(a), None) => z - a,
                (None, None) => 0.0,
            };
            // y up: ∂z/∂y = −∂z/∂row.
            let dy = match (at(xi, yi - 1), at(xi, yi + 1)) {
                (Some(a), Some(b)) => (a - b) / 2.0,
                (None, Some(b)) => z - b,
                (Some(a), None) => a - z,
                (None, None) => 0.0,
            };
            let n = nalgebra::Vector3::new(-dx, -dy, 1.0).normalize();
            // Displayed without gamma so that the relief keeps its contrast.
            let shade = 0.1 + 0.9 * n.dot(&l).max(0.0);
            out[y * w + x] = (shade * 255.0).round() as u8;
        }
    }
    out
}

/// A scalar map scaled by its 99th percentile and sRGB-encoded; black where undefined.
pub fn scalar_preview(map: &ScalarMap) -> Vec<u8> {
    let mut vals: Vec<f32> = map
        .data()
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    let scale = if vals.is_empty() {
        1.0
    } else {
        let k = ((vals.len() - 1) as f64 * 0.99) as usize;
        let (_, v, _) = vals.select_nth_unstable_by(k, f32::total_cmp);
        if *v > 0.0 { *v } else { 1.0 }
    };
    map.data()
        .iter()
        .map(|v| {
            if v.is_finite() {
                (linear_to_srgb((v / scale).clamp(0.0, 1.0)) * 255.0).round() as u8
            } else {
                0
            }
        })
        .collect()
}

/// A mask as 8-bit grey: 255 inside, 0 outside.
pub fn mask_bytes(mask: &Mask) -> Vec<u8> {
    mask.data()
        .iter()
        .map(|&m| if m { 255 } else { 0 })
        .collect()
}

/// Sets every pixel outside `mask` to NaN.
pub fn nan_outside(map: &ScalarMap, mask: &Mask) -> ScalarMap {
    let data = map
        .data()
        .iter()
        .zip(mask.data())
        .map(|(v, m)| if *m { *v } else { f32::NAN })
        .collect();
    Grid::from_vec(map.width(), map.height(), data).unwrap_or_else(|_| map.clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    /// Both staging paths (unnamed files where the platform has them, hidden named files
    /// otherwise): nothing is visible before the commit, the files are complete after it, an
    /// existing file is replaced, and an uncommitted set leaves nothing behind.
    #[test]
    fn staging_commits_all_or_nothing_with_either_kind_of_temporary() {
        for anonymous in [true, false] {
            let tmp = tempfile::tempdir().unwrap();
            let dir = tmp.path().join("out");
            let mut out = OutputDir::create(&dir).unwrap();
            out.anonymous = anonymous;
            std::fs::write(dir.join("b.txt"), b"old").unwrap();
            out.stage_bytes("a.txt", b"first").unwrap();
            out.stage_bytes("b.txt", b"second").unwrap();
            out.stage_bytes("sub/c.txt", b"third").unwrap();
            let staged: Vec<bool> = out
                .staged
                .iter()
                .map(|s| matches!(s.temp, Temp::Named(_)))
                .collect();
            assert!(
                staged
                    .iter()
                    .all(|&named| named != anonymous || cfg!(not(target_os = "linux"))),
                "{anonymous}: {staged:?}"
            );
            // Before the commit only the old file is visible (and, with named temporaries,
            // their hidden names).
            let before: Vec<String> = names(&dir)
                .into_iter()
                .filter(|n| !n.starts_with('.'))
                .collect();
            assert_eq!(before, vec!["b.txt", "sub"], "{anonymous}");
            let done = out.commit().unwrap();
            assert_eq!(done.len(), 3);
            assert_eq!(names(&dir), vec!["a.txt", "b.txt", "sub"], "{anonymous}");
            assert_eq!(std::fs::read(dir.join("a.txt")).unwrap(), b"first");
            assert_eq!(std::fs::read(dir.join("b.txt")).unwrap(), b"second");
            assert_eq!(std::fs::read(dir.join("sub/c.txt")).unwrap(), b"third");
            // Dropped without a commit: nothing new, no temporary.
            let mut out = OutputDir::create(&dir).unwrap();
            out.anonymous = anonymous;
            out.stage_bytes("d.txt", b"never").unwrap();
            drop(out);
            assert_eq!(names(&dir), vec!["a.txt", "b.txt", "sub"], "{anonymous}");
        }
    }

    /// The copy fallback (used where an unnamed file cannot be linked) writes the bytes and
    /// replaces the destination, leaving no temporary.
    #[test]
    fn copy_fallback_replaces_the_destination() {
        let tmp = tempfile::tempdir().unwrap();
        let dest = tmp.path().join("x.bin");
        std::fs::write(&dest, b"old contents").unwrap();
        let mut file = tempfile::tempfile().unwrap();
        file.write_all(b"new").unwrap();
        copy_into_place(&mut file, &dest).unwrap();
        assert_eq!(std::fs::read(&dest).unwrap(), b"new");
        assert_eq!(names(tmp.path()), vec!["x.bin"]);
    }
}
