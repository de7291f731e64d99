//! Image files of any content, as PNG, EXR or TIFF (first byte picks the extension): every
//! reader must return an image or an error, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "scratch.rs"]
mod scratch;
use photostereo::capture::lights::Lights;
use photostereo::capture::stack::{LoadOptions, load_stack};
use photostereo::io::decode::{read_image, read_mask, read_normal_map};
use photostereo::progress::Silent;
use scratch::scratch;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, bytes)) = data.split_first() else {
        return;
    };
    let ext = ["png", "exr", "tif"][usize::from(kind) % 3];
    let path = scratch().join(format!("input.{ext}"));
    if std::fs::write(&path, bytes).is_err() {
        return;
    }
    let _ = read_image(&path);
    let _ = read_mask(&path);
    let _ = read_normal_map(&path);
    // The stack loader: size probe, decode, conversion, saturation and darkness checks, with
    // and without a window.
    if let Ok(lights) = Lights::ring(3, 45.0, 0.0) {
        let paths = vec![path.clone(); 3];
        let _ = load_stack(&paths, &lights, &LoadOptions::default(), &Silent);
        let window = photostereo::grid::Window {
            x0: usize::from(kind) % 5,
            y0: 1,
            x1: 7,
            y1: 5,
        };
        let options = LoadOptions {
            window: Some(window),
            ..LoadOptions::default()
        };
        let _ = load_stack(&paths, &lights, &options, &Silent);
    }
});
