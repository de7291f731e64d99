//! The streaming reader on arbitrary files: the header of a PNG, EXR or TIFF (chosen by the
//! first byte) is checked and the file read in bands of 1 to 16 rows to its end. It must return
//! an error or samples, never panic, hang or allocate what a forged header declares.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "scratch.rs"]
mod scratch;
use scratch::scratch;

fuzz_target!(|data: &[u8]| {
    let Some((&choice, bytes)) = data.split_first() else {
        return;
    };
    let ext = ["png", "exr", "tif"][usize::from(choice) % 3];
    let rows = 1 + usize::from(choice >> 4);
    let dir = scratch();
    let path = dir.join(format!("image.{ext}"));
    if std::fs::write(&path, bytes).is_err() {
        return;
    }
    let _ = photostereo::fuzzing::read_in_bands(&path, rows);
    // The whole-image decoder on the same file, for comparison of their checks.
    let _ = photostereo::io::decode::read_image(&path);
});
