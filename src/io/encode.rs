//! The writer threads of the encoders that take a file a band of rows at a time
//! ([`crate::io::exr`]: float32 EXR maps, ZIP, scan-line blocks of
//! [`crate::io::exr::EXR_BLOCK_ROWS`] rows; [`crate::io::png`]: 8-bit PNG previews).
//!
//! A whole image and the same image fed in bands of any height give the same bytes: blocks
//! are cut at the same rows and compressed the same way. So a run streamed in row bands
//! ([`crate::run::stream`]) writes what an in-memory run writes from the same solution, while
//! holding at most one block of rows per file.
//!
//! The band writers ([`crate::io::exr::ExrRows`], [`crate::io::png::PngRows`]) each run on a thread of their own, fed through a
//! bounded channel: the EXR crate writes blocks from inside a closure, and a thread turns its
//! pull into the push of a band loop. The files are [`PendingFile`]s of an
//! [`crate::io::output::OutputDir`], so they appear only when the whole run commits.

use crate::error::{Error, Result};
use crate::io::output::PendingFile;
use std::path::PathBuf;
use std::sync::mpsc;

/// Bands a writer thread may have queued (besides the one it is encoding) before the band
/// loop waits for it.
pub(crate) const QUEUE_DEPTH: usize = 1;

/// A writer thread fed through a bounded channel with the rows of a file, top to bottom; it
/// returns the file it wrote.
pub(crate) struct Pipe<T: Send + 'static> {
    tx: Option<mpsc::SyncSender<T>>,
    handle: Option<std::thread::JoinHandle<Result<PendingFile>>>,
    path: PathBuf,
    /// Rows of the file, and rows sent so far.
    height: usize,
    rows: usize,
}

impl<T: Send + 'static> Pipe<T> {
    pub(crate) fn spawn(
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
    pub(crate) fn misfit(&self, what: String) -> Error {
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
    pub(crate) fn send(&mut self, rows: usize, item: T) -> Result<()> {
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
    pub(crate) fn join(&mut self) -> Result<PendingFile> {
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
    pub(crate) fn finish(mut self) -> Result<PendingFile> {
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

#[cfg(test)]
mod tests {
    use crate::io::exr::ExrRows;
    use crate::io::output::OutputDir;
    use crate::io::png::PngRows;
    use std::path::Path;

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
        let left: Vec<String> = std::fs::read_dir(tmp.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n == "bad" || (n.starts_with('.') && n != crate::io::output::MANIFEST))
            .collect();
        assert!(left.is_empty(), "abandoned writers left {left:?}");
    }
}
