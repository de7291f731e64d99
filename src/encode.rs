//! Encoders of the output files, whole or a band of rows at a time: float32 EXR maps (ZIP,
//! scan-line blocks of [`EXR_BLOCK_ROWS`] rows) and 8-bit PNG previews.
//!
//! A whole image and the same image fed in bands of any height give the same bytes: blocks
//! are cut at the same rows and compressed the same way. So a run streamed in row bands
//! ([`crate::stream`]) writes what an in-memory run writes from the same solution, while
//! holding at most one block of rows per file.
//!
//! The band writers ([`ExrRows`], [`PngRows`]) each run on a thread of their own, fed through a
//! bounded channel: the EXR crate writes blocks from inside a closure, and a thread turns its
//! pull into the push of a band loop. The files are [`PendingFile`]s of an
//! [`crate::output::OutputDir`], so they appear only when the whole run commits.

use crate::error::{Error, Result};
use crate::output::{ExrChannel, PendingFile};
use exr::block::UncompressedBlock;
use exr::block::writer::ChunksWriter;
use exr::prelude::{SmallVec, Text, Vec2};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc;

/// EXR compression of every map: lossless ZIP over blocks of 16 rows.
const EXR_COMPRESSION: exr::compression::Compression = exr::compression::Compression::ZIP16;
/// Rows per EXR block under [`EXR_COMPRESSION`].
pub(crate) const EXR_BLOCK_ROWS: usize = EXR_COMPRESSION.scan_lines_per_block();
/// Bands a writer thread may have queued (besides the one it is encoding) before the band
/// loop waits for it.
const QUEUE_DEPTH: usize = 1;

/// The header of a single-layer float32 EXR and the order of its channels inside blocks
/// (sorted by name, as the format requires).
struct ExrLayout {
    headers: exr::meta::Headers,
    /// Indices into the caller's channel list, in file order.
    order: Vec<usize>,
    width: usize,
    height: usize,
}

impl ExrLayout {
    fn new(
        path: &Path,
        width: usize,
        height: usize,
        names: &[&str],
        attributes: &[(&str, String)],
    ) -> Result<Self> {
        use exr::meta::attribute::{ChannelDescription, LineOrder, SampleType};
        use exr::meta::header::{Header, LayerAttributes};
        if width == 0 || height == 0 || names.is_empty() {
            return Err(Error::Encode {
                path: path.to_path_buf(),
                reason: format!(
                    "an EXR map needs at least one pixel and one channel ({width}x{height}, {} channels)",
                    names.len()
                ),
            });
        }
        let mut order: Vec<usize> = (0..names.len()).collect();
        order.sort_by(|&a, &b| names[a].as_bytes().cmp(names[b].as_bytes()));
        if order.windows(2).any(|w| names[w[0]] == names[w[1]]) {
            return Err(Error::param(
                "channel",
                format!("{}: channel names repeat in {names:?}", path.display()),
            ));
        }
        let mut channels: SmallVec<[ChannelDescription; 5]> = SmallVec::new();
        for &i in &order {
            let text = Text::new_or_none(names[i]).ok_or_else(|| {
                Error::param(
                    "channel",
                    format!("channel name {:?} is not Latin-1", names[i]),
                )
            })?;
            channels.push(ChannelDescription::named(text, SampleType::F32));
        }
        let mut attrs = LayerAttributes::default();
        for (key, value) in attributes {
            if let (Some(k), Some(v)) = (Text::new_or_none(key), Text::new_or_none(value)) {
                attrs
                    .other
                    .insert(k, exr::meta::attribute::AttributeValue::Text(v));
            }
        }
        let header = Header::new(Text::default(), (width, height), channels)
            .with_encoding(
                EXR_COMPRESSION,
                exr::meta::BlockDescription::ScanLines,
                LineOrder::Increasing,
            )
            .with_attributes(attrs);
        let mut headers = exr::meta::Headers::new();
        headers.push(header);
        Ok(ExrLayout {
            headers,
            order,
            width,
            height,
        })
    }

    fn blocks(&self) -> usize {
        self.height.div_ceil(EXR_BLOCK_ROWS)
    }

    /// Rows of block `index`.
    fn rows(&self, index: usize) -> std::ops::Range<usize> {
        let y0 = index * EXR_BLOCK_ROWS;
        y0..(y0 + EXR_BLOCK_ROWS).min(self.height)
    }

    /// Block `index`, uncompressed, from `planes` (the caller's channel order) holding whole
    /// rows from image row `first` on: for each row, each channel's samples in file order.
    fn block(&self, index: usize, planes: &[&[f32]], first: usize) -> UncompressedBlock {
        let rows = self.rows(index);
        let w = self.width;
        let mut data = Vec::with_capacity(rows.len() * w * 4 * planes.len());
        for y in rows.clone() {
            let at = (y - first) * w;
            for &c in &self.order {
                for v in &planes[c][at..at + w] {
                    data.extend_from_slice(&v.to_ne_bytes());
                }
            }
        }
        UncompressedBlock {
            index: exr::block::BlockIndex {
                layer: 0,
                pixel_position: Vec2(0, rows.start),
                pixel_size: Vec2(w, rows.len()),
                level: Vec2(0, 0),
            },
            data,
        }
    }
}

/// An EXR library error as ours, naming `path`.
fn exr_error(path: &Path, e: exr::error::Error) -> Error {
    match e {
        exr::error::Error::Io(io) => Error::io(path, io),
        other => Error::Encode {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    }
}

/// A PNG library error as ours, naming `path`.
fn png_error(path: &Path, e: png::EncodingError) -> Error {
    match e {
        png::EncodingError::IoError(io) => Error::io(path, io),
        other => Error::Encode {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    }
}

/// Encodes a float32 EXR (ZIP) with the given channels and string attributes into `file`,
/// compressing blocks in parallel; `path` names it in errors.
///
/// # Errors
/// [`Error::InvalidParameter`] when a channel's length is not `width * height` or a name is
/// not Latin-1; [`Error::Encode`] or [`Error::Io`] when writing fails.
pub(crate) fn encode_exr(
    file: &mut File,
    path: &Path,
    width: usize,
    height: usize,
    channels: &[ExrChannel],
    attributes: &[(&str, String)],
) -> Result<()> {
    for (name, data) in channels {
        if data.len() != width * height {
            return Err(Error::param(
                "channel",
                format!(
                    "channel {name} has {} values for {width}x{height}",
                    data.len()
                ),
            ));
        }
    }
    let names: Vec<&str> = channels.iter().map(|c| c.0).collect();
    let layout = ExrLayout::new(path, width, height, &names, attributes)?;
    let planes: Vec<&[f32]> = channels.iter().map(|c| c.1).collect();
    let mut out = BufWriter::new(file);
    exr::block::write(&mut out, layout.headers.clone(), true, |meta, chunks| {
        let blocks = (0..layout.blocks()).map(|i| (i, layout.block(i, &planes, 0)));
        chunks
            .on_progress(|_| ())
            .compress_all_blocks_parallel(&meta, blocks)
    })
    .map_err(|e| exr_error(path, e))?;
    out.flush().map_err(|e| Error::io(path, e))
}

/// A PNG encoder with the settings of every preview: 8 bits, 1 (grey) or 3 (RGB) channels,
/// balanced deflate, adaptive filtering.
fn png_encoder<W: Write>(
    w: W,
    width: usize,
    height: usize,
    channels: usize,
) -> Result<png::Encoder<'static, W>> {
    let color = match channels {
        1 => png::ColorType::Grayscale,
        3 => png::ColorType::Rgb,
        _ => {
            return Err(Error::param(
                "channels",
                format!("{channels}: 1 or 3 expected"),
            ));
        }
    };
    let (Ok(w32), Ok(h32)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(Error::param(
            "size",
            format!("{width}x{height} is too large for a PNG"),
        ));
    };
    let mut e = png::Encoder::new(w, w32, h32);
    e.set_color(color);
    e.set_depth(png::BitDepth::Eight);
    e.set_compression(png::Compression::Balanced);
    e.set_filter(png::Filter::Adaptive);
    Ok(e)
}

/// Encodes an 8-bit PNG (`channels` 1 or 3, interleaved) into `file`; `path` names it in
/// errors.
///
/// # Errors
/// [`Error::InvalidParameter`] for a channel count other than 1 or 3 or a data length that
/// does not match; [`Error::Encode`] or [`Error::Io`] when writing fails.
pub(crate) fn encode_png8(
    file: &mut File,
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    data: &[u8],
) -> Result<()> {
    if data.len() != width * height * channels {
        return Err(Error::param(
            "data",
            format!(
                "{} bytes for a {width}x{height} image of {channels} channel(s)",
                data.len()
            ),
        ));
    }
    let mut out = BufWriter::new(file);
    let mut png = png_encoder(&mut out, width, height, channels)?
        .write_header()
        .map_err(|e| png_error(path, e))?;
    let mut rows = png.stream_writer().map_err(|e| png_error(path, e))?;
    rows.write_all(data).map_err(|e| Error::io(path, e))?;
    rows.finish().map_err(|e| png_error(path, e))?;
    png.finish().map_err(|e| png_error(path, e))?;
    out.flush().map_err(|e| Error::io(path, e))
}

/// A writer thread fed through a bounded channel; it returns the file it wrote.
struct Pipe<T: Send + 'static> {
    tx: Option<mpsc::SyncSender<T>>,
    handle: Option<std::thread::JoinHandle<Result<PendingFile>>>,
    path: PathBuf,
}

impl<T: Send + 'static> Pipe<T> {
    fn spawn(
        path: PathBuf,
        work: impl FnOnce(mpsc::Receiver<T>) -> Result<PendingFile> + Send + 'static,
    ) -> Result<Self> {
        let (tx, rx) = mpsc::sync_channel(QUEUE_DEPTH);
        let handle = std::thread::Builder::new()
            .name("photostereo-writer".into())
            .spawn(move || work(rx))
            .map_err(|e| Error::io(&path, e))?;
        Ok(Pipe {
            tx: Some(tx),
            handle: Some(handle),
            path,
        })
    }

    /// Queues `item`; when the writer has stopped, returns the error that stopped it.
    fn send(&mut self, item: T) -> Result<()> {
        if let Some(tx) = &self.tx
            && tx.send(item).is_ok()
        {
            return Ok(());
        }
        match self.join() {
            Err(e) => Err(e),
            Ok(_) => Err(Error::io(
                &self.path,
                std::io::Error::other("the writer finished before all rows were sent"),
            )),
        }
    }

    /// Closes the channel and waits for the writer.
    fn join(&mut self) -> Result<PendingFile> {
        self.tx = None;
        let handle = self.handle.take().ok_or_else(|| {
            Error::io(
                &self.path,
                std::io::Error::other("the writer was already joined"),
            )
        })?;
        handle.join().map_err(|_| {
            Error::io(
                &self.path,
                std::io::Error::other("the writer thread panicked"),
            )
        })?
    }
}

impl<T: Send + 'static> Drop for Pipe<T> {
    fn drop(&mut self) {
        // Closing the channel makes an unfinished writer give up; its temporary goes with it.
        self.tx = None;
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

/// An EXR map written a band of rows at a time, on a thread of its own. The file's bytes are
/// those [`encode_exr`] writes for the whole map.
pub(crate) struct ExrRows {
    pipe: Pipe<Vec<Vec<f32>>>,
    width: usize,
    height: usize,
    channels: usize,
    rows: usize,
}

impl ExrRows {
    /// Starts writing `file` as a `width`×`height` map with channels `names` (in the order
    /// [`ExrRows::write`] takes them) and string `attributes`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for a bad channel name; [`Error::Io`] when the thread cannot
    /// start.
    pub(crate) fn start(
        file: PendingFile,
        width: usize,
        height: usize,
        names: &[&str],
        attributes: &[(&str, String)],
    ) -> Result<Self> {
        let path = file.path().to_path_buf();
        let layout = ExrLayout::new(&path, width, height, names, attributes)?;
        let channels = names.len();
        let thread_path = path.clone();
        let pipe = Pipe::spawn(path, move |rx: mpsc::Receiver<Vec<Vec<f32>>>| {
            let mut file = file;
            let path = thread_path;
            let mut out = BufWriter::new(file.file_mut());
            exr::block::write(&mut out, layout.headers.clone(), true, |meta, chunks| {
                let mut blocks = chunks.sequential_blocks_compressor(&meta);
                let mut pending: Vec<Vec<f32>> = vec![Vec::new(); channels];
                let (mut first, mut next) = (0, 0);
                for band in rx {
                    for (p, b) in pending.iter_mut().zip(band) {
                        p.extend_from_slice(&b);
                    }
                    let have = first + pending[0].len() / width;
                    while next < layout.blocks() && layout.rows(next).end <= have {
                        let planes: Vec<&[f32]> = pending.iter().map(Vec::as_slice).collect();
                        blocks.compress_block(next, layout.block(next, &planes, first))?;
                        next += 1;
                    }
                    let done = (next * EXR_BLOCK_ROWS).min(layout.height);
                    if done > first {
                        for p in &mut pending {
                            p.drain(..(done - first) * width);
                        }
                        first = done;
                    }
                }
                if next < layout.blocks() {
                    // The band loop stopped early: no file.
                    return Err(exr::error::Error::Aborted);
                }
                Ok(())
            })
            .map_err(|e| exr_error(&path, e))?;
            out.flush().map_err(|e| Error::io(&path, e))?;
            drop(out);
            Ok(file)
        })?;
        Ok(ExrRows {
            pipe,
            width,
            height,
            channels,
            rows: 0,
        })
    }

    /// Appends the next rows: one plane per channel, each a whole number of rows (the same
    /// number for every channel).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for planes of the wrong count or length, or rows past the
    /// last; the writer's error when it has failed.
    pub(crate) fn write(&mut self, planes: Vec<Vec<f32>>) -> Result<()> {
        let len = planes.first().map_or(0, Vec::len);
        if planes.len() != self.channels
            || planes.iter().any(|p| p.len() != len)
            || !len.is_multiple_of(self.width)
            || self.rows + len / self.width > self.height
        {
            return Err(Error::param(
                "rows",
                format!(
                    "{}: {} planes of {len} values do not continue a {}x{} map of {} channel(s) at row {}",
                    self.pipe.path.display(),
                    planes.len(),
                    self.width,
                    self.height,
                    self.channels,
                    self.rows
                ),
            ));
        }
        self.rows += len / self.width;
        self.pipe.send(planes)
    }

    /// Waits for the last block; returns the written file, ready to stage.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when rows are missing; the writer's error.
    pub(crate) fn finish(mut self) -> Result<PendingFile> {
        if self.rows != self.height {
            return Err(Error::param(
                "rows",
                format!(
                    "{}: {} of {} rows were written",
                    self.pipe.path.display(),
                    self.rows,
                    self.height
                ),
            ));
        }
        self.pipe.join()
    }
}

/// An 8-bit PNG written a band of rows at a time, on a thread of its own. The file's bytes are
/// those [`encode_png8`] writes for the whole image.
pub(crate) struct PngRows {
    pipe: Pipe<Vec<u8>>,
    row_bytes: usize,
    height: usize,
    rows: usize,
}

impl PngRows {
    /// Starts writing `file` as a `width`×`height` PNG of `channels` (1 or 3) interleaved
    /// 8-bit channels.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for another channel count; [`Error::Io`] when the thread
    /// cannot start.
    pub(crate) fn start(
        file: PendingFile,
        width: usize,
        height: usize,
        channels: usize,
    ) -> Result<Self> {
        let path = file.path().to_path_buf();
        // Checked here so that a bad call fails before any thread starts.
        png_encoder(std::io::sink(), width, height, channels)?;
        let thread_path = path.clone();
        let pipe = Pipe::spawn(path, move |rx: mpsc::Receiver<Vec<u8>>| {
            let mut file = file;
            let path = thread_path;
            let mut out = BufWriter::new(file.file_mut());
            let mut png = png_encoder(&mut out, width, height, channels)?
                .write_header()
                .map_err(|e| png_error(&path, e))?;
            let mut rows = png.stream_writer().map_err(|e| png_error(&path, e))?;
            for band in rx {
                rows.write_all(&band).map_err(|e| Error::io(&path, e))?;
            }
            rows.finish().map_err(|e| png_error(&path, e))?;
            png.finish().map_err(|e| png_error(&path, e))?;
            out.flush().map_err(|e| Error::io(&path, e))?;
            drop(out);
            Ok(file)
        })?;
        Ok(PngRows {
            pipe,
            row_bytes: width * channels,
            height,
            rows: 0,
        })
    }

    /// Appends the next rows (interleaved samples, a whole number of rows).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for a partial row or rows past the last; the writer's
    /// error when it has failed.
    pub(crate) fn write(&mut self, rows: Vec<u8>) -> Result<()> {
        if !rows.len().is_multiple_of(self.row_bytes)
            || self.rows + rows.len() / self.row_bytes > self.height
        {
            return Err(Error::param(
                "rows",
                format!(
                    "{}: {} bytes do not continue rows of {} bytes at row {} of {}",
                    self.pipe.path.display(),
                    rows.len(),
                    self.row_bytes,
                    self.rows,
                    self.height
                ),
            ));
        }
        self.rows += rows.len() / self.row_bytes;
        self.pipe.send(rows)
    }

    /// Waits for the end of the file; returns it, ready to stage.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when rows are missing; the writer's error.
    pub(crate) fn finish(mut self) -> Result<PendingFile> {
        if self.rows != self.height {
            return Err(Error::param(
                "rows",
                format!(
                    "{}: {} of {} rows were written",
                    self.pipe.path.display(),
                    self.rows,
                    self.height
                ),
            ));
        }
        self.pipe.join()
    }
}
