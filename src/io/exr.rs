//! OpenEXR: decoding whole files (half or float, `R, G, B` or one channel such as `Y`) and
//! single channels, reading row bands through the offset table, and encoding float32 maps
//! (ZIP, scan-line blocks of [`EXR_BLOCK_ROWS`] rows) whole or a band of rows at a time.

use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::io::bands::{BandReader, Kind, decode_error, unsupported};
use crate::io::decode::{MAX_IMAGE_SAMPLES, RawDecoded, SampleFormat, Samples};
use crate::io::encode::Pipe;
use crate::io::input::{MAX_STREAM_SAMPLES, check_declared_size, open_input};
use crate::io::output::{ExrChannel, PendingFile};
use exr::block::UncompressedBlock;
use exr::block::writer::ChunksWriter;
use exr::prelude::{SmallVec, Text, Vec2};
use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::ops::Range;
use std::path::Path;
use std::sync::mpsc;

/// Opens the EXR file `path` (a regular file only) and reads its headers, each checked
/// ([`check_declared_size`]) against `max_samples` and the file's length; returns them and the
/// file, rewound, for the decoder.
///
/// # Errors
/// [`Error::Io`], [`Error::Decode`] or [`Error::UnsupportedImage`] naming the file.
pub(crate) fn read_exr_meta(
    path: &Path,
    max_samples: usize,
) -> Result<(exr::meta::MetaData, File)> {
    use std::io::Seek;
    let (mut file, file_len) = open_input(path)?;
    let meta =
        exr::meta::MetaData::read_from_buffered(BufReader::new(&mut file), false).map_err(|e| {
            match e {
                exr::error::Error::Io(io) => Error::io(path, io),
                other => decode_error(path, other),
            }
        })?;
    for header in &meta.headers {
        let size = (header.layer_size.width(), header.layer_size.height());
        let decoded = (header.layer_size.area() as u64)
            .saturating_mul(header.channels.bytes_per_pixel as u64);
        check_declared_size(
            path,
            size,
            header.channels.list.len(),
            decoded,
            file_len,
            max_samples,
        )?;
    }
    file.rewind().map_err(|e| Error::io(path, e))?;
    Ok((meta, file))
}

/// The first valid layer of an EXR file with all its channels.
pub(crate) fn read_exr_layer(
    path: &Path,
) -> Result<exr::image::Image<exr::image::Layer<exr::image::AnyChannels<exr::image::FlatSamples>>>>
{
    use exr::prelude::*;
    // The headers are checked before the decoder allocates what they declare.
    let (_, file) = read_exr_meta(path, MAX_IMAGE_SAMPLES)?;
    read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(BufReader::new(file))
        .map_err(|e| match e {
            exr::error::Error::Io(io) => crate::Error::io(path, io),
            other => crate::Error::Decode {
                path: path.to_path_buf(),
                reason: other.to_string(),
            },
        })
}

pub(crate) fn decode_exr(path: &Path) -> Result<RawDecoded> {
    use exr::prelude::*;
    let image = read_exr_layer(path)?;
    let layer = &image.layer_data;
    let (width, height) = (layer.size.width(), layer.size.height());
    let list = &layer.channel_data.list;
    let find = |name: &str| list.iter().find(|c| c.name.to_string() == name);
    let chosen: Vec<_> = match (find("R"), find("G"), find("B")) {
        (Some(r), Some(g), Some(b)) => vec![r, g, b],
        _ => {
            if let Some(y) = find("Y").or_else(|| find("Z")) {
                vec![y]
            } else if list.len() == 1 {
                vec![&list[0]]
            } else {
                let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
                return Err(crate::Error::UnsupportedImage {
                    path: path.to_path_buf(),
                    reason: format!(
                        "channels {names:?}: expected R, G, B, or a single channel (Y, Z or any one)"
                    ),
                });
            }
        }
    };
    let mut format = SampleFormat::F32;
    for c in &chosen {
        if c.sampling != Vec2(1, 1) {
            return Err(crate::Error::UnsupportedImage {
                path: path.to_path_buf(),
                reason: format!("channel {} is subsampled", c.name),
            });
        }
        if matches!(c.sample_data, FlatSamples::F16(_)) {
            format = SampleFormat::F16;
        }
    }
    let n = width * height;
    let channels = chosen.len();
    let mut data = vec![0f32; n * channels];
    for (ci, c) in chosen.iter().enumerate() {
        for (i, v) in c.sample_data.values_as_f32().enumerate().take(n) {
            data[i * channels + ci] = v;
        }
    }
    Ok(RawDecoded {
        width,
        height,
        channels,
        stride: channels,
        format,
        samples: Samples::F32(data),
        raw: None,
    })
}

/// Reads the channel `name` of an EXR file (float or half) as a map — for multi-channel data
/// files such as depth plus gradients.
///
/// # Errors
/// [`Error::Io`] or [`Error::Decode`] naming the file; [`Error::UnsupportedImage`] listing the
/// channels when `name` is not one of them.
pub fn read_exr_channel(path: &Path, name: &str) -> Result<crate::grid::ScalarMap> {
    use exr::prelude::*;
    let image = read_exr_layer(path)?;
    let layer = &image.layer_data;
    let list = &layer.channel_data.list;
    let Some(ch) = list.iter().find(|c| c.name.to_string() == name) else {
        let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
        return Err(crate::Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!("no channel {name:?}; channels are {names:?}"),
        });
    };
    if ch.sampling != Vec2(1, 1) {
        return Err(crate::Error::UnsupportedImage {
            path: path.to_path_buf(),
            reason: format!("channel {name} is subsampled"),
        });
    }
    let (w, h) = (layer.size.width(), layer.size.height());
    Grid::from_vec(w, h, ch.sample_data.values_as_f32().take(w * h).collect())
}

/// The channels of an EXR image, as [`read_exr_channels`] returns them.
#[derive(Debug, Clone, PartialEq)]
pub struct ExrChannels {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `(name, row-major values)` per channel, in the file's order.
    pub channels: Vec<(String, Vec<f32>)>,
}

/// Every channel of an EXR file's first layer (float or half, read as `f32`), in the file's
/// order: the image's width and height and `(name, row-major values)` per channel.
///
/// # Errors
/// [`Error::Io`] or [`Error::Decode`] naming the file; [`Error::UnsupportedImage`] for a
/// subsampled channel.
pub fn read_exr_channels(path: &Path) -> Result<ExrChannels> {
    use exr::prelude::*;
    let image = read_exr_layer(path)?;
    let layer = &image.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let mut out = Vec::with_capacity(layer.channel_data.list.len());
    for ch in &layer.channel_data.list {
        if ch.sampling != Vec2(1, 1) {
            return Err(crate::Error::UnsupportedImage {
                path: path.to_path_buf(),
                reason: format!("channel {} is subsampled", ch.name),
            });
        }
        out.push((
            ch.name.to_string(),
            ch.sample_data.values_as_f32().take(w * h).collect(),
        ));
    }
    Ok(ExrChannels {
        width: w,
        height: h,
        channels: out,
    })
}

/// The text attribute `name` of an EXR file's first layer (such as the `photostereo:units`
/// this tool writes), or `None` when the file has no such attribute or is not an EXR.
///
/// # Errors
/// [`Error::Io`] or [`Error::Decode`] naming the file when an EXR header cannot be read.
pub fn read_exr_text(path: &Path, name: &str) -> Result<Option<String>> {
    if !path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
    {
        return Ok(None);
    }
    let (meta, _) = read_exr_meta(path, MAX_STREAM_SAMPLES)?;
    let Some(header) = meta.headers.first() else {
        return Ok(None);
    };
    let key = Text::new_or_none(name);
    Ok(key.and_then(|k| {
        [
            &header.own_attributes.other,
            &header.shared_attributes.other,
        ]
        .into_iter()
        .find_map(|m| match m.get(&k) {
            Some(exr::meta::attribute::AttributeValue::Text(t)) => Some(t.to_string()),
            _ => None,
        })
    }))
}

impl BandReader {
    pub(crate) fn open_exr(path: &Path) -> Result<Self> {
        use exr::meta::attribute::SampleType;
        let (meta, _) = read_exr_meta(path, MAX_STREAM_SAMPLES)?;
        let header = meta
            .headers
            .first()
            .ok_or_else(|| decode_error(path, "no layer in file"))?;
        let (width, height) = (header.layer_size.width(), header.layer_size.height());
        let list = &header.channels.list;
        let find = |name: &str| list.iter().position(|c| c.name.to_string() == name);
        let indices: Vec<usize> = match (find("R"), find("G"), find("B")) {
            (Some(r), Some(g), Some(b)) => vec![r, g, b],
            _ => match find("Y").or_else(|| find("Z")) {
                Some(y) => vec![y],
                None if list.len() == 1 => vec![0],
                None => {
                    let names: Vec<String> = list.iter().map(|c| c.name.to_string()).collect();
                    return Err(unsupported(
                        path,
                        format!(
                            "channels {names:?}: expected R, G, B, or a single channel (Y, Z or any one)"
                        ),
                    ));
                }
            },
        };
        let mut format = SampleFormat::F32;
        let mut chosen = Vec::new();
        for i in indices {
            let c = &list[i];
            if c.sampling != exr::math::Vec2(1, 1) {
                return Err(unsupported(
                    path,
                    format!("channel {} is subsampled", c.name),
                ));
            }
            if c.sample_type == SampleType::F16 {
                format = SampleFormat::F16;
            }
            chosen.push((i, c.sample_type));
        }
        Ok(BandReader {
            path: path.to_path_buf(),
            width,
            height,
            channels: chosen.len(),
            stride: chosen.len(),
            format,
            kind: Kind::Exr { chosen },
        })
    }
}

/// Rows `rows` of the first layer of an EXR, channels `chosen` interleaved, read from the
/// blocks that hold them.
pub(crate) fn read_exr_rows(
    path: &Path,
    chosen: &[(usize, exr::meta::attribute::SampleType)],
    width: usize,
    rows: Range<usize>,
) -> Result<Samples> {
    use exr::block::reader::ChunksReader;
    use exr::meta::attribute::SampleType;
    let bad = |e: exr::error::Error| match e {
        exr::error::Error::Io(io) => Error::io(path, io),
        other => decode_error(path, other),
    };
    let channels = chosen.len();
    let mut out = vec![0f32; rows.len() * width * channels];
    // The headers were checked when the band reader opened the file.
    let (file, _) = open_input(path)?;
    let reader = exr::block::read(BufReader::new(file), false).map_err(bad)?;
    let chunks = reader
        .filter_chunks(false, |_, _, block| {
            let y0 = block.pixel_position.y();
            block.layer == 0
                && block.level == exr::math::Vec2(0, 0)
                && y0 < rows.end
                && y0 + block.pixel_size.height() > rows.start
        })
        .map_err(bad)?;
    let mut row = Vec::new();
    chunks
        .decompress_sequential(false, |meta, block| {
            let header = &meta.headers[0];
            for line in block.lines(&header.channels) {
                let loc = &line.location;
                let y = loc.position.y();
                let Some(ci) = chosen.iter().position(|(i, _)| *i == loc.channel) else {
                    continue;
                };
                if !rows.contains(&y) {
                    continue;
                }
                let x0 = loc.position.x();
                let n = loc.sample_count.min(width.saturating_sub(x0));
                row.clear();
                match chosen[ci].1 {
                    SampleType::F16 => {
                        for v in line.read_samples::<exr::prelude::f16>().take(n) {
                            row.push(v?.to_f32());
                        }
                    }
                    SampleType::F32 => {
                        for v in line.read_samples::<f32>().take(n) {
                            row.push(v?);
                        }
                    }
                    SampleType::U32 => {
                        for v in line.read_samples::<u32>().take(n) {
                            row.push(v? as f32);
                        }
                    }
                }
                let base = ((y - rows.start) * width + x0) * channels + ci;
                for (i, v) in row.iter().enumerate() {
                    out[base + i * channels] = *v;
                }
            }
            Ok(())
        })
        .map_err(bad)?;
    Ok(Samples::F32(out))
}

/// EXR compression of every map: lossless ZIP over blocks of 16 rows.
pub(crate) const EXR_COMPRESSION: exr::compression::Compression =
    exr::compression::Compression::ZIP16;

/// Rows per EXR block under [`EXR_COMPRESSION`].
pub(crate) const EXR_BLOCK_ROWS: usize = EXR_COMPRESSION.scan_lines_per_block();

/// The header of a single-layer float32 EXR and the order of its channels inside blocks
/// (sorted by name, as the format requires).
pub(crate) struct ExrLayout {
    headers: exr::meta::Headers,
    /// Indices into the caller's channel list, in file order.
    order: Vec<usize>,
    width: usize,
    height: usize,
}

impl ExrLayout {
    pub(crate) fn new(
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

    pub(crate) fn blocks(&self) -> usize {
        self.height.div_ceil(EXR_BLOCK_ROWS)
    }

    /// Rows of block `index`.
    pub(crate) fn rows(&self, index: usize) -> std::ops::Range<usize> {
        let y0 = index * EXR_BLOCK_ROWS;
        y0..(y0 + EXR_BLOCK_ROWS).min(self.height)
    }

    /// Block `index`, uncompressed, from `planes` (the caller's channel order) holding whole
    /// rows from image row `first` on: for each row, each channel's samples in file order.
    pub(crate) fn block(&self, index: usize, planes: &[&[f32]], first: usize) -> UncompressedBlock {
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
pub(crate) fn exr_error(path: &Path, e: exr::error::Error) -> Error {
    match e {
        exr::error::Error::Io(io) => Error::io(path, io),
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
