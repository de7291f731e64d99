//! Opening input files safely: only regular files are read (a device such as `/dev/zero`, a
//! pipe or a folder is refused before a byte is read), text files are read up to a size cap,
//! and an image's declared size is checked against the limits and against the file's length
//! before anything sized by it is allocated.
//!
//! The length check rests on a property of the codecs these formats use: none packs more
//! than [`MAX_PACKING`] decoded bytes into one byte of file. Deflate (PNG, EXR ZIP, TIFF
//! Deflate) is bounded by 258-byte matches coded in at least 2 bits, about 1032:1 (RFC 1951);
//! LZW with 12-bit codes by strings of at most 4096 bytes a code (TIFF LZW); run-length
//! schemes by 128:1 or less. A header that declares more pixels than its file could hold
//! under the best case is damaged or forged, and is refused naming both figures.

use crate::error::{Error, Result};
use std::fs::File;
use std::io::Read;
use std::path::Path;

/// Most decoded bytes one byte of an image file can hold under any codec read here (see the
/// module documentation).
pub const MAX_PACKING: u64 = 4096;

/// Most samples (pixels × channels) of one image read in row bands, or whose size is only
/// read: 2³², 16 GiB as f32. A streamed run holds a band of rows, not the image, and its
/// memory budget is checked on the declared size before anything is allocated; this bound
/// keeps the size arithmetic far from overflow.
pub const MAX_STREAM_SAMPLES: usize = if usize::BITS > 32 {
    (1u64 << 32) as usize
} else {
    usize::MAX
};

/// Most bytes read from a text input (a lights file, a camera file, an image list): far above
/// any real one (a lights file of 10,000 images is under 1 MiB).
pub const MAX_TEXT_BYTES: u64 = 64 << 20;

/// What kind of file system entry `meta` describes, for messages.
fn kind_of(meta: &std::fs::Metadata) -> &'static str {
    let t = meta.file_type();
    if t.is_dir() {
        return "a folder";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
        if t.is_fifo() {
            return "a pipe";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    "not a regular file"
}

/// Opens `path` for reading when it is (or a symbolic link leads to) a regular file; returns
/// the file and its length in bytes.
///
/// # Errors
/// [`Error::Io`] naming the file when it cannot be opened, or when it is a folder, a device,
/// a pipe or a socket (nothing is read from those).
pub fn open_input(path: &Path) -> Result<(File, u64)> {
    let file = open_nonblocking(path).map_err(|e| Error::io(path, e))?;
    let meta = file.metadata().map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        return Err(Error::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!(
                    "is {}, not a regular file; give a file saved on disk",
                    kind_of(&meta)
                ),
            ),
        ));
    }
    blocking(&file).map_err(|e| Error::io(path, e))?;
    Ok((file, meta.len()))
}

/// Opens `path` for reading without waiting for a writer (a named pipe would block the open).
#[cfg(target_os = "linux")]
fn open_nonblocking(path: &Path) -> std::io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
}

#[cfg(not(target_os = "linux"))]
fn open_nonblocking(path: &Path) -> std::io::Result<File> {
    File::open(path)
}

/// Clears `O_NONBLOCK` on a regular file (reads of which never block anyway).
#[cfg(target_os = "linux")]
fn blocking(file: &File) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let fd = file.as_raw_fd();
    // SAFETY: fcntl on a descriptor this function's caller owns; no memory is passed.
    #[allow(unsafe_code)]
    let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
    if flags < 0 {
        return Err(std::io::Error::last_os_error());
    }
    // SAFETY: as above.
    #[allow(unsafe_code)]
    let r = unsafe { libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK) };
    if r < 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(not(target_os = "linux"))]
fn blocking(_: &File) -> std::io::Result<()> {
    Ok(())
}

/// Reads the text file `path` whole (at most [`MAX_TEXT_BYTES`]), without a leading UTF-8
/// byte-order mark.
///
/// # Errors
/// As [`open_input`]; [`Error::Io`] when the file is longer than the cap or not UTF-8.
pub fn read_text(path: &Path) -> Result<String> {
    let (file, len) = open_input(path)?;
    let too_long = || {
        Error::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!(
                    "is longer than the {} MiB a text input of this tool can be",
                    MAX_TEXT_BYTES >> 20
                ),
            ),
        )
    };
    if len > MAX_TEXT_BYTES {
        return Err(too_long());
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(MAX_TEXT_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    if bytes.len() as u64 > MAX_TEXT_BYTES {
        return Err(too_long());
    }
    let text = String::from_utf8(bytes).map_err(|e| {
        Error::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!(
                    "is not UTF-8 text (byte {} is not valid UTF-8)",
                    e.utf8_error().valid_up_to()
                ),
            ),
        )
    })?;
    Ok(match text.strip_prefix('\u{feff}') {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

/// Checks the size an image header declares before anything sized by it is allocated:
/// `width * height` pixels of `samples` channels, `decoded` bytes as the file stores them
/// uncompressed.
///
/// - The pixel count and sample count are within `max_samples`
///   ([`crate::io::decode::MAX_IMAGE_SAMPLES`] for whole images; a streamed run passes the same
///   bound on pixels).
/// - The file of `file_len` bytes can hold them: decoded bytes ≤ `file_len` × [`MAX_PACKING`].
///
/// # Errors
/// [`Error::UnsupportedImage`] naming the file for a size beyond the limit, [`Error::Decode`]
/// for a size no file of that length can hold.
pub fn check_declared_size(
    path: &Path,
    (width, height): (usize, usize),
    samples: usize,
    decoded: u64,
    file_len: u64,
    max_samples: usize,
) -> Result<()> {
    let pixels = width.saturating_mul(height);
    let total = pixels.saturating_mul(samples);
    if pixels > max_samples || total > max_samples {
        return Err(Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!(
                "the header declares {width}x{height} pixels × {samples} channel(s), more than the {max_samples} samples this tool reads"
            ),
        });
    }
    if decoded > file_len.saturating_mul(MAX_PACKING) {
        return Err(Error::Decode {
            path: path.to_path_buf(),
            reason: format!(
                "the header declares {width}x{height} pixels × {samples} channel(s) ({decoded} bytes decoded), but the file holds only {file_len} bytes, and no codec packs more than {MAX_PACKING} bytes into one: the header is damaged or the file is truncated"
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_device_or_folder_is_refused_before_reading() {
        let tmp = tempfile::tempdir().unwrap();
        let e = open_input(tmp.path()).unwrap_err().to_string();
        assert!(e.contains("a folder"), "{e}");
        #[cfg(unix)]
        {
            let link = tmp.path().join("x.png");
            std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
            let e = open_input(&link).unwrap_err().to_string();
            assert!(e.contains("character device") && e.contains("x.png"), "{e}");
            let e = read_text(&link).unwrap_err().to_string();
            assert!(e.contains("character device"), "{e}");
        }
        #[cfg(target_os = "linux")]
        {
            // A named pipe with no writer: refused at once, not waited on.
            let fifo = tmp.path().join("pipe.png");
            let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
            // SAFETY: a valid NUL-terminated path.
            assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
            let e = open_input(&fifo).unwrap_err().to_string();
            assert!(e.contains("a pipe"), "{e}");
        }
    }

    #[test]
    fn text_loses_its_byte_order_mark_and_is_capped() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("l.txt");
        std::fs::write(&p, "\u{feff}0 0 1\n").unwrap();
        assert_eq!(read_text(&p).unwrap(), "0 0 1\n");
        std::fs::write(&p, [0xffu8, 0xfe, 0x30]).unwrap();
        assert!(read_text(&p).unwrap_err().to_string().contains("UTF-8"));
    }

    #[test]
    fn declared_sizes_beyond_the_limit_or_the_file_are_refused() {
        let p = Path::new("f.png");
        // 1000x1000 grey 8-bit in 300 bytes: possible (a flat image deflates that far).
        check_declared_size(p, (1000, 1000), 1, 1_000_000, 300, 1 << 28).unwrap();
        // ... but not in 200 bytes.
        let e = check_declared_size(p, (1000, 1000), 1, 1_000_000, 200, 1 << 28).unwrap_err();
        assert!(matches!(e, Error::Decode { .. }), "{e}");
        let e =
            check_declared_size(p, (100_000, 100_000), 3, u64::MAX, u64::MAX, 1 << 28).unwrap_err();
        assert!(matches!(e, Error::UnsupportedImage { .. }), "{e}");
        let e =
            check_declared_size(p, (usize::MAX, usize::MAX), 3, u64::MAX, 69, 1 << 28).unwrap_err();
        assert!(e.to_string().contains("more than"), "{e}");
    }
}
