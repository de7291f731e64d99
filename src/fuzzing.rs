//! Entry points for the fuzz targets in `fuzz/` (feature `fuzzing`, off by default): what
//! the targets reach that is not public.

use crate::error::Result;
use crate::io::bands::BandReader;
use std::path::Path;

/// Opens `path` for reading in row bands (its header checked) and reads it to the end in
/// bands of `rows` rows, then checks the rest of the file; returns the samples read.
///
/// # Errors
/// The errors of opening and reading the file.
pub fn read_in_bands(path: &Path, rows: usize) -> Result<usize> {
    let mut reader = BandReader::open(path)?;
    let (_, height) = reader.size();
    let mut samples = 0;
    let mut y = 0;
    while y < height {
        let end = (y + rows.max(1)).min(height);
        let band = reader.read(y..end)?;
        samples += band.width * band.height * band.channels;
        y = end;
    }
    reader.verify_rest()?;
    Ok(samples)
}
