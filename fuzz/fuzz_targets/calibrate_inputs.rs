//! Light calibration's inputs from arbitrary bytes: 1 to 4 small grey images (size and pixels
//! from the bytes) written as 8-bit PNG, and a sphere mask that is either such an image or the
//! raw bytes as a file, through the calibration the command line runs: load, find the sphere,
//! find each highlight, make the lights. An error or a result, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "scratch.rs"]
mod scratch;
use photostereo::calibrate::{
    ChromeOptions, calibrate_chrome, load_reference_images, read_grey_mask,
};
use photostereo::capture::stack::Transfer;
use photostereo::progress::Silent;
use scratch::scratch;

fuzz_target!(|data: &[u8]| {
    if data.len() < 4 {
        return;
    }
    let (w, h) = (4 + usize::from(data[0] % 61), 4 + usize::from(data[1] % 61));
    let count = 1 + usize::from(data[2] % 4);
    let mask_kind = data[3] % 3;
    let body = &data[4..];
    let dir = scratch();
    let pixel = |k: usize| body.get(k % body.len().max(1)).copied().unwrap_or(0);
    let mut paths = Vec::new();
    for i in 0..count {
        let path = dir.join(format!("{i}.png"));
        let px: Vec<u8> = (0..w * h).map(|k| pixel(k + i * w * h)).collect();
        photostereo::io::output::write_png8(&path, w, h, 1, &px).expect("write a PNG");
        paths.push(path);
    }
    let Ok(stack) = load_reference_images(&paths, Transfer::Linear, None, &Silent) else {
        return;
    };
    let mask_path = dir.join("mask.png");
    let mask = match mask_kind {
        0 => None,
        1 => {
            let px: Vec<u8> = (0..w * h).map(|k| pixel(k * 7 + 3)).collect();
            photostereo::io::output::write_png8(&mask_path, w, h, 1, &px).expect("write a PNG");
            read_grey_mask(&mask_path).ok()
        }
        _ => {
            std::fs::write(&mask_path, body).expect("write the mask");
            read_grey_mask(&mask_path).ok()
        }
    };
    let Ok(calibration) = calibrate_chrome(
        &stack,
        mask.as_ref().map(|m| (m, mask_path.as_path())),
        &ChromeOptions::default(),
    ) else {
        return;
    };
    if let Ok(lights) = calibration.lights() {
        for l in lights.lights() {
            assert!((l.direction.norm() - 1.0).abs() < 1e-6, "{:?}", l.direction);
        }
    }
});
