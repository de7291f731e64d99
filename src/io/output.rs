//! Writing results: float EXR maps, PNG previews and JSON, as one set, all or nothing.
//!
//! # The output set
//! A run's files are written into a private staging folder beside the output folder
//! (`.NAME.photostereo-XXXXXXXXXXXXXXXX`, created exclusively, its suffix unpredictable; every
//! file in it is created exclusively, so a symbolic link planted there is never followed).
//! [`OutputDir::commit`] then puts the whole folder in place with one rename: into a folder
//! that does not exist or is empty, or, where replacing is allowed, exchanged atomically with
//! the previous set (Linux `renameat2(RENAME_EXCHANGE)`), which is then deleted. A reader of
//! the output folder therefore sees the old set or the new one, never a mix. Each set holds a
//! list of its files ([`MANIFEST`]); a folder is replaced only when everything in it is listed
//! there, so files that are not outputs (the input images, say) are never deleted.
//!
//! # The lock
//! While an [`OutputLock`] is held (the command line takes it at the start of a run; an
//! [`OutputDir`] takes it if no one has), `.NAME.photostereo-lock` beside the folder is locked
//! (`flock`) and names the process: a second run into the same folder is refused at once
//! ([`Error::OutputBusy`]). The lock carries the policy ([`Overwrite`]), so the check that the
//! folder is fresh is made again at the commit, atomically: a folder filled meanwhile is not
//! overwritten.
//!
//! # What an interruption leaves
//! A failed run, or one stopped by Ctrl-C or SIGTERM, removes its staging folder and lock file:
//! nothing of it is left (the interrupt handler removes what [`discard_uncommitted`] lists, and
//! nothing more is made after it; only an empty probe folder of [`ensure_writable_dir`], made and
//! removed at once, can be left by a Ctrl-C between the two, and the next run removes it). A killed run (`SIGKILL`, power loss) can leave the hidden staging
//! folder and lock file beside the output folder, never a partial set in it; the next run into
//! that folder removes both.
//!
//! Single files (a calibration, a depth map written by `integrate`) are written with
//! [`write_file`]: an exclusively created temporary beside the file, renamed over it.

use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::io::decode::linear_to_srgb;
use crate::io::exr::encode_exr;
use crate::io::png::{encode_png8, encode_png16};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The list of a set's files, one relative path a line, written into every committed set.
pub const MANIFEST: &str = ".photostereo-outputs";

/// What a commit may do to an output folder that already holds files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Overwrite {
    /// Nothing: the folder must not exist or be empty at the commit ([`Error::OutputExists`]
    /// otherwise).
    Never,
    /// Replace a previous output set as a whole (a folder holding anything its list does not
    /// name is refused with [`Error::OutputForeign`]).
    PreviousSet,
}

/// A held lock of an output folder (see the module documentation); released when the last
/// guard of this process for that folder is dropped.
#[derive(Debug)]
pub struct OutputLock {
    key: PathBuf,
    /// The folder that holds the output folder, and its name there, resolved once when the
    /// lock was taken: the set is committed there, whatever the path comes to name later.
    parent: PathBuf,
    name: std::ffi::OsString,
}

/// A lock held by this process.
#[derive(Debug)]
struct Held {
    key: PathBuf,
    /// The path the lock was asked for, as given.
    given: PathBuf,
    parent: PathBuf,
    name: std::ffi::OsString,
    lock_path: PathBuf,
    /// The locked file (the lock goes with it).
    _file: Option<File>,
    guards: usize,
    overwrite: Overwrite,
}

/// The locks this process holds, and the staging folders it has not committed.
static LOCKS: Mutex<Vec<Held>> = Mutex::new(Vec::new());
static STAGING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Set by [`discard_uncommitted`] (under [`STAGING`]'s lock): no staging folder, temporary or
/// lock file is created, and no file begun in a staging folder, after it.
static DISCARDED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// The error of a set begun or written after [`discard_uncommitted`].
fn discarded(path: &Path) -> Error {
    Error::io(
        path,
        std::io::Error::new(
            std::io::ErrorKind::Interrupted,
            "the run was interrupted and its outputs discarded",
        ),
    )
}

fn guard<T>(m: &'static Mutex<T>) -> std::sync::MutexGuard<'static, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The folder that holds `dir` (created if missing) and `dir`'s name in it, with symbolic
/// links resolved.
///
/// # Errors
/// [`Error::Io`] naming `dir` when it has no usable name (the current folder, one of its
/// ancestors, a root), is a mount point, or its parent cannot be created.
fn locate(dir: &Path) -> Result<(PathBuf, std::ffi::OsString)> {
    let refuse = |why: &str| Error::io(dir, std::io::Error::other(why.to_string()));
    let absolute = if dir.exists() {
        dir.canonicalize().map_err(|e| Error::io(dir, e))?
    } else {
        let name = dir
            .file_name()
            .filter(|n| *n != "." && *n != "..")
            .ok_or_else(|| refuse("is not a folder name"))?;
        let parent = match dir.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        std::fs::create_dir_all(parent).map_err(|e| {
            Error::io(
                dir,
                std::io::Error::new(
                    e.kind(),
                    format!(
                        "the output folder cannot be created in {}: {e}",
                        parent.display()
                    ),
                ),
            )
        })?;
        parent
            .canonicalize()
            .map_err(|e| Error::io(parent, e))?
            .join(name)
    };
    let (Some(parent), Some(name)) = (absolute.parent(), absolute.file_name()) else {
        return Err(refuse(
            "is a root folder; results go into a folder of their own inside it",
        ));
    };
    if let Ok(cwd) = std::env::current_dir().and_then(|c| c.canonicalize())
        && cwd.starts_with(&absolute)
    {
        return Err(refuse(
            "is the current folder or holds it; results go into a folder of their own, which is put in place as a whole",
        ));
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let (Ok(d), Ok(p)) = (std::fs::metadata(&absolute), std::fs::metadata(parent))
            && d.dev() != p.dev()
        {
            return Err(refuse(
                "is a mount point, which cannot be replaced as a whole; choose a folder inside it",
            ));
        }
    }
    Ok((parent.to_path_buf(), name.to_os_string()))
}

/// `.NAME.photostereo-SUFFIX` in `parent`.
fn sibling(parent: &Path, name: &std::ffi::OsStr, suffix: &str) -> PathBuf {
    let mut n = std::ffi::OsString::from(".");
    n.push(name);
    n.push(".photostereo-");
    n.push(suffix);
    parent.join(n)
}

/// 16 hexadecimal digits no other process can predict (from the standard library's randomly
/// keyed hasher, the process id and the time).
fn unpredictable() -> String {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    if let Ok(t) = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH) {
        h.write_u128(t.as_nanos());
    }
    format!("{:016x}", h.finish())
}

impl OutputLock {
    /// Locks the output folder `dir` for this process, with the commit policy `overwrite`
    /// (the first holder's policy stays while the lock is held), and removes what a killed
    /// run into the same folder left beside it. Takes no lock across processes where the
    /// platform has none (other than Linux).
    ///
    /// # Errors
    /// [`Error::OutputBusy`] when another process holds it; [`Error::Io`] as `locate` or
    /// when the lock file cannot be created.
    pub fn acquire(dir: &Path, overwrite: Overwrite) -> Result<Self> {
        let mut locks = guard(&LOCKS);
        // The interrupt handler sets the flag before it removes the lock files listed here:
        // after that, no lock file is made (one made before is listed, and removed).
        if DISCARDED.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(discarded(dir));
        }
        // The same path as given is the same folder, even if it came to resolve elsewhere.
        if let Some(h) = locks.iter_mut().find(|h| h.given == dir) {
            h.guards += 1;
            return Ok(OutputLock {
                key: h.key.clone(),
                parent: h.parent.clone(),
                name: h.name.clone(),
            });
        }
        let (parent, name) = locate(dir)?;
        let key = parent.join(&name);
        if let Some(h) = locks.iter_mut().find(|h| h.key == key) {
            h.guards += 1;
            return Ok(OutputLock {
                key,
                parent: h.parent.clone(),
                name: h.name.clone(),
            });
        }
        let lock_path = sibling(&parent, &name, "lock");
        let file = lock_file(&lock_path, dir)?;
        // Under the lock, what a killed run left (its staging folder, the old set of an
        // exchange) is no one's. Without a lock across processes (other platforms than
        // Linux), it could be another run's, and is left.
        if file.is_some() {
            remove_leftovers(&parent, &name);
        }
        locks.push(Held {
            key: key.clone(),
            given: dir.to_path_buf(),
            parent: parent.clone(),
            name: name.clone(),
            lock_path,
            _file: file,
            guards: 1,
            overwrite,
        });
        Ok(OutputLock { key, parent, name })
    }

    /// The output folder's path, as resolved when the lock was taken.
    fn dest(&self) -> PathBuf {
        self.parent.join(&self.name)
    }

    /// The folder's commit policy.
    fn overwrite(&self) -> Overwrite {
        guard(&LOCKS)
            .iter()
            .find(|h| h.key == self.key)
            .map_or(Overwrite::Never, |h| h.overwrite)
    }
}

impl Drop for OutputLock {
    fn drop(&mut self) {
        let mut locks = guard(&LOCKS);
        if let Some(i) = locks.iter().position(|h| h.key == self.key) {
            locks[i].guards -= 1;
            if locks[i].guards == 0 {
                let held = locks.swap_remove(i);
                // Removed while still locked; a process that opened it meanwhile sees it
                // unlinked and retries.
                let _ = std::fs::remove_file(&held.lock_path);
            }
        }
    }
}

/// Opens and locks `path` (never through a symbolic link), writes this process's id into it,
/// and makes sure the locked file is still the one at `path` (a lock file removed by its
/// holder between the open and the lock is retried).
#[cfg(target_os = "linux")]
fn lock_file(path: &Path, dir: &Path) -> Result<Option<File>> {
    use std::io::{Read, Seek};
    use std::os::fd::AsRawFd;
    use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
    for _ in 0..16 {
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(0o644)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(path)
            .map_err(|e| {
                Error::io(
                    dir,
                    std::io::Error::new(
                        e.kind(),
                        format!(
                            "the output folder cannot be locked (its lock file {}): {e}",
                            path.display()
                        ),
                    ),
                )
            })?;
        // SAFETY: flock on a file descriptor this function owns; no memory is shared.
        #[allow(unsafe_code)]
        let r = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if r != 0 {
            let e = std::io::Error::last_os_error();
            if e.raw_os_error() == Some(libc::EWOULDBLOCK) {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                return Err(Error::OutputBusy {
                    path: dir.to_path_buf(),
                    holder: if holder.is_empty() || !holder.bytes().all(|b| b.is_ascii_digit()) {
                        "unknown".into()
                    } else {
                        holder.to_string()
                    },
                });
            }
            return Err(Error::io(path, e));
        }
        let same = match (file.metadata(), std::fs::symlink_metadata(path)) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        };
        if !same {
            continue;
        }
        // Never truncate a file that is not this tool's lock (a hard link planted there).
        if file
            .metadata()
            .is_ok_and(|m| !m.is_file() || m.nlink() != 1)
        {
            return Err(Error::io(
                dir,
                std::io::Error::other(format!(
                    "the output folder's lock file {} is not a plain file of its own; remove it",
                    path.display()
                )),
            ));
        }
        let _ = file.set_len(0);
        let _ = file.rewind();
        let _ = write!(file, "{}", std::process::id());
        return Ok(Some(file));
    }
    Err(Error::io(
        path,
        std::io::Error::other("the lock file keeps being replaced; is another run starting?"),
    ))
}

#[cfg(not(target_os = "linux"))]
fn lock_file(_: &Path, _: &Path) -> Result<Option<File>> {
    Ok(None)
}

/// Whether `name` is one of the hidden names this tool gives its staging folders, lock files
/// and temporaries (`.NAME.photostereo-` then `lock`, 16 hexadecimal digits, or those and
/// `.tmp`): what a killed run can leave beside an output (see the module documentation), and
/// the next run into that output removes.
///
/// ```
/// use photostereo::io::output::is_leftover;
/// assert!(is_leftover(".scene.photostereo-lock"));
/// assert!(is_leftover(".out.photostereo-0123456789abcdef"));
/// assert!(!is_leftover("depth.exr"));
/// ```
pub fn is_leftover(name: &str) -> bool {
    let Some(at) = name.find(".photostereo-") else {
        return false;
    };
    let suffix = &name[at + ".photostereo-".len()..];
    let hex = |t: &str| t.len() == 16 && t.bytes().all(|c| c.is_ascii_hexdigit());
    name.starts_with('.')
        && (suffix == "lock" || hex(suffix) || suffix.strip_suffix(".tmp").is_some_and(hex))
}

/// Removes the staging folders a killed run into `parent/name` left (called under the lock).
fn remove_leftovers(parent: &Path, name: &std::ffi::OsStr) {
    let prefix = sibling(Path::new(""), name, "");
    let prefix = prefix.as_os_str().as_encoded_bytes();
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    for e in entries.flatten() {
        let n = e.file_name();
        let b = n.as_encoded_bytes();
        let suffix = b.strip_prefix(prefix).unwrap_or_default();
        let staging =
            suffix.len() == 16 && suffix.iter().all(|c| c.is_ascii_hexdigit()) && b != prefix;
        if staging && e.file_type().is_ok_and(|t| t.is_dir()) {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Removes every staging folder and temporary file of this process not yet committed, for an
/// exit that skips destructors (the interrupt handler, after [`hold_commits`]), and the lock
/// files of this process. From then on no staging folder, temporary or lock file is created and
/// no file begun in a staging folder (an error says the run was interrupted), so that what was
/// removed stays removed while the run's other threads go on until the exit.
pub fn discard_uncommitted() {
    let mut uncommitted = guard(&STAGING);
    DISCARDED.store(true, std::sync::atomic::Ordering::SeqCst);
    for s in uncommitted.drain(..) {
        if std::fs::remove_dir_all(&s).is_err() {
            let _ = std::fs::remove_file(&s);
        }
    }
    drop(uncommitted);
    for h in guard(&LOCKS).drain(..) {
        let _ = std::fs::remove_file(&h.lock_path);
    }
}

/// A folder that receives a set of output files, all or nothing (see the module
/// documentation).
#[derive(Debug)]
pub struct OutputDir {
    dir: PathBuf,
    staging: PathBuf,
    /// Relative paths of the files staged.
    staged: Vec<String>,
    lock: OutputLock,
}

/// A file of an [`OutputDir`] being written ([`OutputDir::begin`]): it becomes part of the set
/// when staged ([`OutputDir::add`]) and committed. Dropped before that, it leaves nothing.
#[derive(Debug)]
pub struct PendingFile {
    file: File,
    name: String,
    dest: PathBuf,
}

impl PendingFile {
    /// The file to write to.
    pub fn file_mut(&mut self) -> &mut File {
        &mut self.file
    }

    /// The path the file will have, to name in errors.
    pub fn path(&self) -> &Path {
        &self.dest
    }
}

/// One named channel of an EXR file.
pub type ExrChannel<'a> = (&'a str, &'a [f32]);

/// Checks that `dir` can take a new set of outputs without overwriting anything: it does not
/// exist yet, or it is an empty folder. (The command line calls this unless `--force` is given;
/// the commit checks it again.)
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

/// Checks, before any work is done, that the output folder `dir` can be put in place: that
/// it is writable when it exists, and that folders can be created beside it (where its
/// staging folder goes).
///
/// # Errors
/// [`Error::Io`] naming `dir` (and the folder tried) when nothing can be created there.
pub fn ensure_writable_dir(dir: &Path) -> Result<()> {
    let (parent, name) = locate(dir)?;
    // A folder that exists must be writable too: a read-only one is the user's choice not to
    // have it replaced. (Asked of the system, not probed: a probe inside the folder is an entry
    // a killed run could leave in a set.)
    if std::fs::metadata(dir).is_ok_and(|m| m.is_dir())
        && let Err(e) = writable(dir)
    {
        return Err(Error::io(
            dir,
            std::io::Error::new(
                e.kind(),
                format!("the output folder cannot be written: {e}"),
            ),
        ));
    }
    let probe = sibling(&parent, &name, &unpredictable());
    match std::fs::create_dir(&probe) {
        Ok(()) => {
            let _ = std::fs::remove_dir(&probe);
            Ok(())
        }
        Err(e) => Err(Error::io(
            dir,
            std::io::Error::new(
                e.kind(),
                format!(
                    "the output folder cannot be created or replaced in {}: {e}",
                    parent.display()
                ),
            ),
        )),
    }
}

/// Whether this process may create entries in the folder `dir` (`access(W_OK)`).
#[cfg(target_os = "linux")]
fn writable(dir: &Path) -> std::io::Result<()> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes())?;
    // SAFETY: a valid NUL-terminated path that outlives the call, which only reads it.
    #[allow(unsafe_code)]
    let r = unsafe { libc::access(c.as_ptr(), libc::W_OK) };
    if r == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

#[cfg(not(target_os = "linux"))]
fn writable(dir: &Path) -> std::io::Result<()> {
    match std::fs::metadata(dir) {
        Ok(m) if m.permissions().readonly() => Err(std::io::Error::new(
            std::io::ErrorKind::PermissionDenied,
            "read-only",
        )),
        Ok(_) => Ok(()),
        Err(e) => Err(e),
    }
}

/// Checks that `dir`, if it holds anything, holds a previous output set and nothing else: each
/// entry is listed in its [`MANIFEST`], or is a folder of listed files, or a folder that is a
/// set of its own (such as `scene/` of `photostereo demo`).
///
/// # Errors
/// [`Error::OutputForeign`] naming the first entry that is not; [`Error::Io`] when the folder
/// cannot be listed.
pub fn ensure_replaceable(dir: &Path) -> Result<()> {
    match std::fs::metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::io(dir, e)),
        Ok(m) if !m.is_dir() => {
            return Err(Error::io(
                dir,
                std::io::Error::other("exists and is not a folder; pass a folder for the outputs"),
            ));
        }
        Ok(_) => {}
    }
    if std::fs::read_dir(dir)
        .map_err(|e| Error::io(dir, e))?
        .next()
        .is_none()
    {
        return Ok(());
    }
    match foreign_entry(dir).map_err(|e| Error::io(dir, e))? {
        None => Ok(()),
        Some(entry) => Err(Error::OutputForeign {
            path: dir.to_path_buf(),
            entry,
        }),
    }
}

/// The first entry of the set folder `dir` its manifest does not account for.
fn foreign_entry(dir: &Path) -> std::io::Result<Option<String>> {
    let manifest = dir.join(MANIFEST);
    let listed: Vec<String> = match std::fs::symlink_metadata(&manifest) {
        // A plain file of a sane size only: a link or a device planted there lists nothing.
        Ok(m) if m.is_file() && m.len() <= crate::io::input::MAX_TEXT_BYTES => {
            std::fs::read_to_string(&manifest)?
                .lines()
                .map(str::to_string)
                .collect()
        }
        Ok(_) => Vec::new(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(e),
    };
    fn walk(
        root: &Path,
        rel: &str,
        listed: &[String],
        top: bool,
    ) -> std::io::Result<Option<String>> {
        let here = if rel.is_empty() {
            root.to_path_buf()
        } else {
            root.join(rel)
        };
        let mut names: Vec<_> = std::fs::read_dir(&here)?.collect::<std::io::Result<_>>()?;
        names.sort_by_key(|e| e.file_name());
        for e in names {
            let name = e.file_name().to_string_lossy().into_owned();
            let path = if rel.is_empty() {
                name.clone()
            } else {
                format!("{rel}/{name}")
            };
            if top && name == MANIFEST && !listed.is_empty() {
                continue;
            }
            // What a killed run left (a nested set's staging folder, lock or temporary): this
            // tool's own, deleted with the set.
            if is_leftover(&name) {
                continue;
            }
            let t = e.file_type()?;
            if t.is_dir() {
                let prefix = format!("{path}/");
                if listed.iter().any(|l| l.starts_with(&prefix)) {
                    if let Some(f) = walk(root, &path, listed, false)? {
                        return Ok(Some(f));
                    }
                    continue;
                }
                if e.path().join(MANIFEST).is_file() {
                    if let Some(f) = foreign_entry(&e.path())? {
                        return Ok(Some(format!("{path}/{f}")));
                    }
                    continue;
                }
                return Ok(Some(format!("{path}/")));
            }
            if !listed.contains(&path) {
                return Ok(Some(path));
            }
        }
        Ok(None)
    }
    walk(dir, "", &listed, true)
}

/// Checks that the output `path` (a folder, whose set replaces it as a whole, or a file) is
/// none of `inputs` and holds none of them, symbolic links resolved: a run must not replace
/// what it reads.
///
/// # Errors
/// [`Error::OutputHoldsInput`] naming the first input it holds.
pub fn ensure_apart(path: &Path, inputs: &[&Path]) -> Result<()> {
    let Ok(out) = path.canonicalize() else {
        // It does not exist yet, so it holds nothing.
        return Ok(());
    };
    for input in inputs {
        if let Ok(i) = input.canonicalize()
            && i.starts_with(&out)
        {
            return Err(Error::OutputHoldsInput {
                path: path.to_path_buf(),
                input: input.to_path_buf(),
            });
        }
    }
    Ok(())
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

/// A relative output name, checked: no absolute path, no `..`, no empty part.
fn relative_name(dir: &Path, name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && !name.starts_with('/')
        && name
            .split('/')
            .all(|p| !p.is_empty() && p != "." && p != ".." && !p.contains('\\'))
        && name != MANIFEST;
    if ok {
        Ok(())
    } else {
        Err(Error::param(
            "output name",
            format!(
                "{name:?} in {}: a relative path inside the output folder",
                dir.display()
            ),
        ))
    }
}

impl OutputDir {
    /// Starts a set for the folder `dir` (its parents are created; the folder itself appears
    /// only at the commit): takes the folder's lock (policy [`Overwrite::PreviousSet`] unless
    /// a lock is already held with another) and creates the staging folder.
    ///
    /// # Errors
    /// [`Error::OutputBusy`], and [`Error::Io`] when the staging folder cannot be created.
    pub fn create(dir: &Path) -> Result<Self> {
        let lock = OutputLock::acquire(dir, Overwrite::PreviousSet)?;
        let (parent, name) = (lock.parent.clone(), lock.name.clone());
        let staging = sibling(&parent, &name, &unpredictable());
        // Created and listed under the list's lock, which the interrupt handler takes before it
        // removes what the list holds: a Ctrl-C between the two would otherwise leave a staging
        // folder that nothing removes (the demo's scene set, interrupted as it began, did).
        let mut uncommitted = guard(&STAGING);
        if DISCARDED.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(discarded(dir));
        }
        // Created exclusively: it cannot be a folder or link planted beforehand.
        std::fs::create_dir(&staging).map_err(|e| {
            Error::io(
                dir,
                std::io::Error::new(
                    e.kind(),
                    format!(
                        "the output folder cannot be made in {}: {e}",
                        parent.display()
                    ),
                ),
            )
        })?;
        uncommitted.push(staging.clone());
        drop(uncommitted);
        Ok(OutputDir {
            dir: dir.to_path_buf(),
            staging,
            staged: Vec::new(),
            lock,
        })
    }

    /// The destination folder.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// The staging folder, where the files staged so far can be read back before the commit.
    pub fn staging_path(&self) -> &Path {
        &self.staging
    }

    /// Opens the file `name` (a file name, or a relative path whose folders are created) in the
    /// set, to be written and then staged with [`OutputDir::add`]; dropped instead, it is not
    /// part of the set.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for a name that leaves the folder; [`Error::Io`] when the
    /// file cannot be created.
    pub fn begin(&self, name: &str) -> Result<PendingFile> {
        relative_name(&self.dir, name)?;
        let dest = self.dir.join(name);
        let path = self.staging.join(name);
        // Under the staging list's lock, so that the interrupt handler's removal of the staging
        // folder cannot interleave with a file (or its folder) being created in it: a file
        // created while the folder's entries were removed would keep the folder itself.
        let uncommitted = guard(&STAGING);
        if DISCARDED.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(discarded(&dest));
        }
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(&dest, e))?;
        }
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| Error::io(&dest, e))?;
        drop(uncommitted);
        Ok(PendingFile {
            file,
            name: name.to_string(),
            dest,
        })
    }

    /// Stages a file opened with [`OutputDir::begin`] and written: it is part of the set put in
    /// place by [`OutputDir::commit`].
    pub fn add(&mut self, file: PendingFile) {
        if !self.staged.contains(&file.name) {
            self.staged.push(file.name);
        }
    }

    /// Writes `name` with `write` (given the file and the path to name in errors).
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

    /// Puts the set in place (see the module documentation); returns the final paths. While it
    /// runs, [`hold_commits`] waits.
    ///
    /// # Errors
    /// [`Error::OutputExists`] when the folder holds entries and the lock's policy is
    /// [`Overwrite::Never`] (filled by someone else while the run worked);
    /// [`Error::OutputForeign`] when it holds what is not a previous set; [`Error::Io`] when the
    /// folder cannot be put in place. The folder is unchanged then.
    pub fn commit(self) -> Result<Vec<PathBuf>> {
        let _commit = hold_commits();
        let mut staged = self.staged.clone();
        staged.sort();
        prune(&self.staging, &staged);
        let manifest = self.staging.join(MANIFEST);
        let mut list = staged.join("\n");
        list.push('\n');
        std::fs::write(&manifest, list).map_err(|e| Error::io(&self.dir, e))?;
        sync_dir(&self.staging);
        let parent = self.lock.parent.clone();
        let dest = self.lock.dest();
        if std::fs::symlink_metadata(&dest).is_ok_and(|m| m.file_type().is_symlink()) {
            return Err(Error::io(
                &self.dir,
                std::io::Error::other(
                    "the output folder was replaced by a symbolic link while this run worked; nothing of this run was written",
                ),
            ));
        }
        let filled = || {
            Error::OutputExists {
            path: self.dir.clone(),
            what: "the output folder was filled by another process while this run worked; nothing of this run was written".into(),
        }
        };
        let fill = |e: std::io::Error| -> Error {
            if matches!(e.raw_os_error(), Some(code) if code == ENOTEMPTY || code == EEXIST) {
                filled()
            } else {
                Error::io(&self.dir, e)
            }
        };
        let occupied = std::fs::read_dir(&dest).is_ok_and(|mut d| d.next().is_some());
        if !occupied {
            // Into a folder that does not exist or is empty: one rename, which fails if the
            // folder was filled meanwhile.
            std::fs::rename(&self.staging, &dest).map_err(fill)?;
        } else {
            if self.lock.overwrite() == Overwrite::Never {
                return Err(filled());
            }
            ensure_replaceable(&dest)?;
            if let Ok(m) = std::fs::metadata(&dest) {
                let _ = std::fs::set_permissions(&self.staging, m.permissions());
            }
            exchange(&self.staging, &parent, &self.lock.name)
                .map_err(|e| Error::io(&self.dir, e))?;
            // The staging path now holds the previous set. It is deleted only if it still
            // holds nothing but that set: whatever was written into the folder between the
            // check and the exchange is kept, in a visible folder beside it.
            if matches!(foreign_entry(&self.staging), Ok(None)) {
                let _ = std::fs::remove_dir_all(&self.staging);
            } else {
                let kept = sibling_visible(&parent, &self.lock.name, "previous");
                let _ = std::fs::rename(&self.staging, kept);
            }
        }
        sync_dir(&parent);
        guard(&STAGING).retain(|s| s != &self.staging);
        Ok(staged.iter().map(|n| self.dir.join(n)).collect())
    }
}

#[cfg(target_os = "linux")]
const ENOTEMPTY: i32 = libc::ENOTEMPTY;
#[cfg(target_os = "linux")]
const EEXIST: i32 = libc::EEXIST;
#[cfg(not(target_os = "linux"))]
const ENOTEMPTY: i32 = 39;
#[cfg(not(target_os = "linux"))]
const EEXIST: i32 = 17;

/// Removes from the staging folder what was begun but not staged.
fn prune(staging: &Path, staged: &[String]) {
    fn walk(root: &Path, rel: &str, staged: &[String]) {
        let here = if rel.is_empty() {
            root.to_path_buf()
        } else {
            root.join(rel)
        };
        let Ok(entries) = std::fs::read_dir(&here) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let path = if rel.is_empty() {
                name
            } else {
                format!("{rel}/{name}")
            };
            if e.file_type().is_ok_and(|t| t.is_dir()) {
                walk(root, &path, staged);
            } else if !staged.contains(&path) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    walk(staging, "", staged);
}

/// Flushes a folder's entries to disk (best effort).
fn sync_dir(dir: &Path) {
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}

/// `NAME.SUFFIX-XXXXXXXXXXXXXXXX` in `parent`: a folder left for the user to see.
fn sibling_visible(parent: &Path, name: &std::ffi::OsStr, suffix: &str) -> PathBuf {
    let mut n = name.to_os_string();
    n.push(format!(".{suffix}-{}", unpredictable()));
    parent.join(n)
}

/// Swaps the folder `a` and the folder `name` in `parent` (`b`) atomically (Linux `renameat2`
/// with `RENAME_EXCHANGE`); where the file system or platform cannot, `b` is moved aside and
/// `a` renamed in its place (a moment without `b`, never a mix).
fn exchange(a: &Path, parent: &Path, name: &std::ffi::OsStr) -> std::io::Result<()> {
    let b = &parent.join(name);
    #[cfg(target_os = "linux")]
    {
        use std::ffi::CString;
        use std::os::unix::ffi::OsStrExt;
        let ca = CString::new(a.as_os_str().as_bytes())?;
        let cb = CString::new(b.as_os_str().as_bytes())?;
        // SAFETY: two valid NUL-terminated paths that outlive the call; the system call only
        // reads them.
        #[allow(unsafe_code)]
        let r = unsafe {
            libc::syscall(
                libc::SYS_renameat2,
                libc::AT_FDCWD,
                ca.as_ptr(),
                libc::AT_FDCWD,
                cb.as_ptr(),
                libc::RENAME_EXCHANGE,
            )
        };
        if r == 0 {
            return Ok(());
        }
        let e = std::io::Error::last_os_error();
        if !matches!(e.raw_os_error(), Some(libc::EINVAL) | Some(libc::ENOSYS)) {
            return Err(e);
        }
    }
    let aside = sibling(parent, name, &unpredictable());
    std::fs::rename(b, &aside)?;
    if let Err(e) = std::fs::rename(a, b) {
        let _ = std::fs::rename(&aside, b);
        return Err(e);
    }
    // The new set is in place; the previous one is left aside, where the next run into the
    // folder removes it, if it cannot take `a`'s name.
    let _ = std::fs::rename(&aside, a);
    Ok(())
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        // Uncommitted (or the previous set after an exchange that failed to be removed).
        if self.staging.exists() {
            let _ = std::fs::remove_dir_all(&self.staging);
        }
        guard(&STAGING).retain(|s| s != &self.staging);
    }
}

/// Held by [`OutputDir::commit`] while it puts a set in place.
static COMMITS: Mutex<()> = Mutex::new(());

/// Waits for a commit in progress to finish and keeps new ones from starting while the guard
/// lives: an interrupt handler takes it before exiting, so that a run stops either before its
/// outputs appear or after all of them are in place.
pub fn hold_commits() -> std::sync::MutexGuard<'static, ()> {
    guard(&COMMITS)
}

/// Writes the single file `path` atomically: `write` fills a temporary created exclusively
/// beside it (hidden, unpredictable name), which then takes the name: with
/// [`Overwrite::Never`] by a hard link that fails if `path` appeared meanwhile, else by a
/// rename over it. Nothing is left on failure.
///
/// # Errors
/// [`Error::OutputExists`] when `path` exists under [`Overwrite::Never`]; [`Error::Io`] and the
/// errors of `write`.
pub fn write_file(
    path: &Path,
    overwrite: Overwrite,
    write: impl FnOnce(&mut File, &Path) -> Result<()>,
) -> Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| Error::io(path, std::io::Error::other("is not a file name")))?;
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
    let tmp = sibling(parent, name, &format!("{}.tmp", unpredictable()));
    // Created and listed under the list's lock, as a staging folder is ([`OutputDir::create`]).
    let mut uncommitted = guard(&STAGING);
    if DISCARDED.load(std::sync::atomic::Ordering::SeqCst) {
        return Err(discarded(path));
    }
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .map_err(|e| Error::io(path, e))?;
    uncommitted.push(tmp.clone());
    drop(uncommitted);
    struct Remove<'a>(&'a Path);
    impl Drop for Remove<'_> {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(self.0);
            guard(&STAGING).retain(|s| s != self.0);
        }
    }
    let _remove = Remove(&tmp);
    write(&mut file, path)?;
    file.sync_all().map_err(|e| Error::io(path, e))?;
    drop(file);
    let _commit = hold_commits();
    match overwrite {
        Overwrite::Never => match std::fs::hard_link(&tmp, path) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(Error::OutputExists {
                    path: path.to_path_buf(),
                    what: "the output file already exists".into(),
                });
            }
            // A file system without hard links: checked, then renamed (not atomic).
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::Unsupported | std::io::ErrorKind::PermissionDenied
                ) =>
            {
                ensure_fresh_file(path)?;
                std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
            }
            Err(e) => return Err(Error::io(path, e)),
        },
        Overwrite::PreviousSet => std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?,
    }
    sync_dir(parent);
    Ok(())
}

/// Writes `bytes` to the file `path` atomically ([`write_file`]).
///
/// # Errors
/// As [`write_file`].
pub fn write_bytes(path: &Path, overwrite: Overwrite, bytes: &[u8]) -> Result<()> {
    write_file(path, overwrite, |file, p| {
        file.write_all(bytes).map_err(|e| Error::io(p, e))
    })
}

/// Writes a float32 EXR (ZIP) at `path` atomically ([`write_file`]), with the given channels
/// and string attributes.
///
/// # Errors
/// As [`write_file`] and [`OutputDir::stage_exr`].
pub fn write_exr_file(
    path: &Path,
    overwrite: Overwrite,
    (width, height): (usize, usize),
    channels: &[ExrChannel],
    attributes: &[(&str, String)],
) -> Result<()> {
    write_file(path, overwrite, |file, p| {
        encode_exr(file, p, width, height, channels, attributes)
    })
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

    /// Nothing is visible before the commit (the folder does not exist), the whole set with its
    /// list after it, and nothing is left beside it (no staging folder, no lock file).
    #[test]
    fn a_set_appears_whole_at_the_commit() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("out");
        let mut out = OutputDir::create(&dir).unwrap();
        out.stage_bytes("a.txt", b"first").unwrap();
        out.stage_bytes("sub/c.txt", b"third").unwrap();
        // A file begun but not staged is not part of the set.
        drop(out.begin("never.txt").unwrap());
        assert!(!dir.exists());
        let hidden: Vec<String> = names(tmp.path());
        assert_eq!(hidden.len(), 2, "{hidden:?}"); // the staging folder and the lock file
        let done = out.commit().unwrap();
        assert_eq!(done, vec![dir.join("a.txt"), dir.join("sub/c.txt")]);
        assert_eq!(names(tmp.path()), vec!["out"]);
        assert_eq!(names(&dir), vec![MANIFEST, "a.txt", "sub"]);
        assert_eq!(std::fs::read(dir.join("sub/c.txt")).unwrap(), b"third");
        assert_eq!(
            std::fs::read_to_string(dir.join(MANIFEST)).unwrap(),
            "a.txt\nsub/c.txt\n"
        );
        // Dropped without a commit: nothing changes, nothing is left.
        let mut out = OutputDir::create(&dir).unwrap();
        out.stage_bytes("d.txt", b"never").unwrap();
        drop(out);
        assert_eq!(names(tmp.path()), vec!["out"]);
        assert_eq!(names(&dir), vec![MANIFEST, "a.txt", "sub"]);
    }

    /// A previous set is replaced as a whole (files it had and the new one has not are gone);
    /// a folder holding anything else is not touched.
    #[test]
    fn only_a_previous_set_is_replaced() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("out");
        let mut out = OutputDir::create(&dir).unwrap();
        out.stage_bytes("a.txt", b"old").unwrap();
        out.stage_bytes("b.txt", b"old").unwrap();
        out.commit().unwrap();
        let mut out = OutputDir::create(&dir).unwrap();
        out.stage_bytes("a.txt", b"new").unwrap();
        out.commit().unwrap();
        assert_eq!(names(&dir), vec![MANIFEST, "a.txt"]);
        assert_eq!(std::fs::read(dir.join("a.txt")).unwrap(), b"new");
        // A foreign file: refused, the folder unchanged, nothing left beside it.
        std::fs::write(dir.join("mine.png"), b"user's").unwrap();
        let mut out = OutputDir::create(&dir).unwrap();
        out.stage_bytes("a.txt", b"newer").unwrap();
        let e = out.commit().unwrap_err();
        assert!(
            matches!(&e, Error::OutputForeign { entry, .. } if entry == "mine.png"),
            "{e}"
        );
        assert_eq!(names(&dir), vec![MANIFEST, "a.txt", "mine.png"]);
        assert_eq!(std::fs::read(dir.join("a.txt")).unwrap(), b"new");
        assert_eq!(names(tmp.path()), vec!["out"]);
        // A folder never written by this tool is not replaced either.
        let plain = tmp.path().join("plain");
        std::fs::create_dir(&plain).unwrap();
        std::fs::write(plain.join("img.png"), b"x").unwrap();
        assert!(matches!(
            ensure_replaceable(&plain),
            Err(Error::OutputForeign { .. })
        ));
    }

    /// Under [`Overwrite::Never`], a folder filled while the run worked is not overwritten:
    /// the check is made again, atomically, at the commit.
    #[test]
    fn a_fresh_only_commit_refuses_a_folder_filled_meanwhile() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("out");
        let _lock = OutputLock::acquire(&dir, Overwrite::Never).unwrap();
        let mut out = OutputDir::create(&dir).unwrap();
        out.stage_bytes("a.txt", b"mine").unwrap();
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(dir.join("theirs.txt"), b"theirs").unwrap();
        let e = out.commit().unwrap_err();
        assert!(matches!(e, Error::OutputExists { .. }), "{e}");
        assert_eq!(names(&dir), vec!["theirs.txt"]);
    }

    /// A single file is written whole or not at all, refused when it exists under
    /// [`Overwrite::Never`], and a symbolic link at its name is replaced, not followed.
    #[test]
    fn single_files_are_put_in_place_atomically() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("lights.json");
        write_file(&path, Overwrite::Never, |f, p| {
            f.write_all(b"one").map_err(|e| Error::io(p, e))
        })
        .unwrap();
        let e = write_file(&path, Overwrite::Never, |_, _| Ok(())).unwrap_err();
        assert!(matches!(e, Error::OutputExists { .. }), "{e}");
        let e = write_file(&path, Overwrite::PreviousSet, |_, p| {
            Err(Error::io(p, std::io::Error::other("failed")))
        })
        .unwrap_err();
        assert!(e.to_string().contains("failed"));
        assert_eq!(std::fs::read(&path).unwrap(), b"one");
        #[cfg(unix)]
        {
            let victim = tmp.path().join("victim");
            std::fs::write(&victim, b"keep").unwrap();
            let link = tmp.path().join("link.json");
            std::os::unix::fs::symlink(&victim, &link).unwrap();
            write_file(&link, Overwrite::PreviousSet, |f, p| {
                f.write_all(b"two").map_err(|e| Error::io(p, e))
            })
            .unwrap();
            assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
            assert_eq!(std::fs::read(&link).unwrap(), b"two");
        }
        assert_eq!(names(tmp.path()).len(), if cfg!(unix) { 3 } else { 1 });
    }

    /// What killed runs leave is recognised by name, and a set holding such leftovers (of a
    /// nested set) is still replaceable; an output folder given as a symbolic link is replaced
    /// where it points, the link kept.
    #[test]
    fn leftovers_and_linked_folders() {
        assert!(is_leftover(".out.photostereo-lock"));
        assert!(is_leftover(".out.photostereo-0123456789abcdef"));
        assert!(is_leftover(".x.json.photostereo-0123456789abcdef.tmp"));
        assert!(!is_leftover(".out.photostereo-notes"));
        assert!(!is_leftover("out.photostereo-lock"));
        let tmp = tempfile::tempdir().unwrap();
        let real = tmp.path().join("real");
        let mut out = OutputDir::create(&real).unwrap();
        out.stage_bytes("a.txt", b"one").unwrap();
        out.commit().unwrap();
        std::fs::create_dir(real.join(".scene.photostereo-0123456789abcdef")).unwrap();
        std::fs::write(real.join(".scene.photostereo-lock"), b"").unwrap();
        ensure_replaceable(&real).unwrap();
        #[cfg(unix)]
        {
            let link = tmp.path().join("link");
            std::os::unix::fs::symlink(&real, &link).unwrap();
            ensure_replaceable(&link).unwrap();
            let mut out = OutputDir::create(&link).unwrap();
            out.stage_bytes("b.txt", b"two").unwrap();
            out.commit().unwrap();
            assert!(link.is_symlink());
            assert_eq!(names(&real), vec![MANIFEST, "b.txt"]);
        }
    }

    /// Output names cannot leave the folder.
    #[test]
    fn names_stay_inside_the_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let out = OutputDir::create(&tmp.path().join("out")).unwrap();
        for bad in ["../x", "/etc/x", "a/../../x", "", MANIFEST] {
            assert!(out.begin(bad).is_err(), "{bad}");
        }
    }
}
