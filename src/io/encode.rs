//! Encoders of the output files, whole or a band of rows at a time: float32 EXR maps (ZIP,
//! scan-line blocks of [`EXR_BLOCK_ROWS`] rows) and 8-bit PNG previews.
//!
//! A whole image and the same image fed in bands of any height give the same bytes: blocks
//! are cut at the same rows and compressed the same way. So a run streamed in row bands
//! ([`crate::run::stream`]) writes what an in-memory run writes from the same solution, while
//! holding at most one block of rows per file.
//!
//! The band writers ([`ExrRows`], [`PngRows`]) each run on a thread of their own, fed through a
//! bounded channel: the EXR crate writes blocks from inside a closure, and a thread turns its
//! pull into the push of a band loop. The files are [`PendingFile`]s of an
//! [`crate::io::output::OutputDir`], so they appear only when the whole run commits.

use crate::error::{Error, Result};
use crate::io::output::{ExrChannel, PendingFile};
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

/// A PNG encoder with the settings of every PNG written: 1 (grey) or 3 (RGB) channels of
/// `depth`, balanced deflate, adaptive filtering.
fn png_encoder<W: Write>(
    w: W,
    width: usize,
    height: usize,
    channels: usize,
    depth: png::BitDepth,
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
    e.set_depth(depth);
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
    encode_png(
        file,
        path,
        (width, height, channels),
        png::BitDepth::Eight,
        data,
    )
}

/// Encodes a 16-bit PNG (`channels` 1 or 3, interleaved) into `file`; `path` names it in
/// errors.
///
/// # Errors
/// As [`encode_png8`].
pub(crate) fn encode_png16(
    file: &mut File,
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    data: &[u16],
) -> Result<()> {
    // PNG stores 16-bit samples big-endian.
    let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_be_bytes()).collect();
    encode_png(
        file,
        path,
        (width, height, channels),
        png::BitDepth::Sixteen,
        &bytes,
    )
}

/// Encodes a PNG of `(width, height, channels)` samples of `depth` from their bytes.
fn encode_png(
    file: &mut File,
    path: &Path,
    (width, height, channels): (usize, usize, usize),
    depth: png::BitDepth,
    bytes: &[u8],
) -> Result<()> {
    let sample = if depth == png::BitDepth::Sixteen {
        2
    } else {
        1
    };
    if bytes.len() != width * height * channels * sample {
        return Err(Error::param(
            "data",
            format!(
                "{} samples for a {width}x{height} image of {channels} channel(s)",
                bytes.len() / sample
            ),
        ));
    }
    let mut out = BufWriter::new(file);
    let mut png = png_encoder(&mut out, width, height, channels, depth)?
        .write_header()
        .map_err(|e| png_error(path, e))?;
    let mut rows = png.stream_writer().map_err(|e| png_error(path, e))?;
    rows.write_all(bytes).map_err(|e| Error::io(path, e))?;
    rows.finish().map_err(|e| png_error(path, e))?;
    png.finish().map_err(|e| png_error(path, e))?;
    out.flush().map_err(|e| Error::io(path, e))
}

/// A writer thread fed through a bounded channel with the rows of a file, top to bottom; it
/// returns the file it wrote.
struct Pipe<T: Send + 'static> {
    tx: Option<mpsc::SyncSender<T>>,
    handle: Option<std::thread::JoinHandle<Result<PendingFile>>>,
    path: PathBuf,
    /// Rows of the file, and rows sent so far.
    height: usize,
    rows: usize,
}

impl<T: Send + 'static> Pipe<T> {
    fn spawn(
        path: PathBuf,
        height: usize,
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
            height,
            rows: 0,
        })
    }

    /// An error naming the file: `what` does not continue it at the current row.
    fn misfit(&self, what: String) -> Error {
        Error::param(
            "rows",
            format!(
                "{}: {what} do not continue a file of {} rows at row {}",
                self.path.display(),
                self.height,
                self.rows
            ),
        )
    }

    /// Queues `item`, which holds the next `rows` rows; when the writer has stopped, returns
    /// the error that stopped it.
    fn send(&mut self, rows: usize, item: T) -> Result<()> {
        if self.rows + rows > self.height {
            return Err(self.misfit(format!("{rows} more rows")));
        }
        self.rows += rows;
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

    /// Waits for the end of the file; returns it, ready to stage.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when rows are missing; the writer's error.
    fn finish(mut self) -> Result<PendingFile> {
        if self.rows != self.height {
            return Err(Error::param(
                "rows",
                format!(
                    "{}: {} of {} rows were written",
                    self.path.display(),
                    self.rows,
                    self.height
                ),
            ));
        }
        self.join()
    }
}

/// An EXR map written a band of rows at a time, on a thread of its own. The file's bytes are
/// those [`encode_exr`] writes for the whole map.
pub(crate) struct ExrRows {
    pipe: Pipe<Vec<Vec<f32>>>,
    width: usize,
    channels: usize,
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
        let pipe = Pipe::spawn(path, height, move |rx: mpsc::Receiver<Vec<Vec<f32>>>| {
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
            channels,
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
        {
            return Err(self.pipe.misfit(format!(
                "{} planes of {len} values for {} channel(s) of width {}",
                planes.len(),
                self.channels,
                self.width
            )));
        }
        self.pipe.send(len / self.width, planes)
    }

    /// Waits for the last block; returns the written file, ready to stage.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when rows are missing; the writer's error.
    pub(crate) fn finish(self) -> Result<PendingFile> {
        self.pipe.finish()
    }
}

/// An 8-bit PNG written a band of rows at a time, on a thread of its own. The file's bytes are
/// those [`encode_png8`] writes for the whole image.
pub(crate) struct PngRows {
    pipe: Pipe<Vec<u8>>,
    row_bytes: usize,
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
        png_encoder(
            std::io::sink(),
            width,
            height,
            channels,
            png::BitDepth::Eight,
        )?;
        let thread_path = path.clone();
        let pipe = Pipe::spawn(path, height, move |rx: mpsc::Receiver<Vec<u8>>| {
            let mut file = file;
            let path = thread_path;
            let mut out = BufWriter::new(file.file_mut());
            let mut png = png_encoder(&mut out, width, height, channels, png::BitDepth::Eight)?
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
        })
    }

    /// Appends the next rows (interleaved samples, a whole number of rows).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for a partial row or rows past the last; the writer's
    /// error when it has failed.
    pub(crate) fn write(&mut self, rows: Vec<u8>) -> Result<()> {
        if !rows.len().is_multiple_of(self.row_bytes) {
            return Err(self.pipe.misfit(format!(
                "{} bytes in rows of {}",
                rows.len(),
                self.row_bytes
            )));
        }
        self.pipe.send(rows.len() / self.row_bytes, rows)
    }

    /// Waits for the end of the file; returns it, ready to stage.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when rows are missing; the writer's error.
    pub(crate) fn finish(self) -> Result<PendingFile> {
        self.pipe.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::output::OutputDir;

    fn read_exr(path: &Path) -> Vec<(String, Vec<f32>)> {
        let image = exr::prelude::read_all_flat_layers_from_file(path).unwrap();
        image.layer_data[0]
            .channel_data
            .list
            .iter()
            .map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect()))
            .collect()
    }

    /// Bands of any height give the values the whole-image encoder gives, for a size that
    /// is not a multiple of the block height; rows in the wrong shape, too many rows and
    /// missing rows are refused naming the file.
    #[test]
    fn bands_encode_like_the_whole_image() {
        let (w, h) = (37, 53);
        let a: Vec<f32> = (0..w * h).map(|i| (i as f32 * 0.37).sin()).collect();
        let mut b: Vec<f32> = (0..w * h).map(|i| i as f32).collect();
        b[5] = f32::NAN;
        let grey: Vec<u8> = (0..w * h).map(|i| (i * 7 % 251) as u8).collect();
        let tmp = tempfile::tempdir().unwrap();
        let mut out = OutputDir::create(tmp.path()).unwrap();
        out.stage_exr("whole.exr", w, h, &[("b", &b), ("a", &a)], &[])
            .unwrap();
        out.stage_png8("whole.png", w, h, 1, &grey).unwrap();
        for band in [1, 5, 16, 17, 53] {
            let mut exr = ExrRows::start(
                out.begin(&format!("{band}.exr")).unwrap(),
                w,
                h,
                &["b", "a"],
                &[],
            )
            .unwrap();
            let mut png =
                PngRows::start(out.begin(&format!("{band}.png")).unwrap(), w, h, 1).unwrap();
            for y in (0..h).step_by(band) {
                let r = y * w..(y + band).min(h) * w;
                exr.write(vec![b[r.clone()].to_vec(), a[r.clone()].to_vec()])
                    .unwrap();
                png.write(grey[r].to_vec()).unwrap();
            }
            out.add(exr.finish().unwrap());
            out.add(png.finish().unwrap());
        }
        out.commit().unwrap();
        let whole = read_exr(&tmp.path().join("whole.exr"));
        assert_eq!(whole.len(), 2);
        let whole_png = image::open(tmp.path().join("whole.png")).unwrap();
        assert_eq!(whole_png.as_bytes(), grey.as_slice());
        for band in [1, 5, 16, 17, 53] {
            let got = read_exr(&tmp.path().join(format!("{band}.exr")));
            for ((nw, vw), (ng, vg)) in whole.iter().zip(&got) {
                assert_eq!(nw, ng);
                assert!(
                    vw.iter()
                        .zip(vg)
                        .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan())),
                    "bands of {band}: channel {nw} differs"
                );
            }
            let png = image::open(tmp.path().join(format!("{band}.png"))).unwrap();
            assert_eq!(png.as_bytes(), grey.as_slice(), "bands of {band}");
        }
        // Refusals.
        let out = OutputDir::create(&tmp.path().join("bad")).unwrap();
        let mut exr = ExrRows::start(out.begin("x.exr").unwrap(), w, h, &["a"], &[]).unwrap();
        let e = exr.write(vec![vec![0.0; w + 1]]).unwrap_err().to_string();
        assert!(e.contains("x.exr"), "{e}");
        let e = exr
            .write(vec![vec![0.0; w * (h + 1)]])
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.exr") && e.contains("rows"), "{e}");
        exr.write(vec![vec![0.0; w * 3]]).unwrap();
        let e = exr.finish().unwrap_err().to_string();
        assert!(e.contains("3 of 53 rows"), "{e}");
        let mut png = PngRows::start(out.begin("y.png").unwrap(), w, h, 3).unwrap();
        let e = png.write(vec![0; w * 3 - 1]).unwrap_err().to_string();
        assert!(e.contains("y.png"), "{e}");
        assert!(PngRows::start(out.begin("z.png").unwrap(), w, h, 2).is_err());
        drop(png);
        drop(out);
        assert!(
            std::fs::read_dir(tmp.path().join("bad"))
                .unwrap()
                .next()
                .is_none(),
            "abandoned writers left files"
        );
    }
}
