//! DiLiGenT-layout folders of any content: the input is split at 0xFF bytes into
//! `filenames.txt`, `light_directions.txt`, `light_intensities.txt` and `mask.png`, beside
//! three small valid 16-bit PNG images `1.png`–`3.png`. Loading (and, when it succeeds,
//! reconstructing) must return a result or an error, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use photostereo::capture::dataset::Capture;
use photostereo::capture::stack::LoadOptions;
use photostereo::progress::Silent;
use photostereo::run::pipeline::{Config, reconstruct};
use std::path::PathBuf;

/// This process's folder, with the three images written once.
fn folder() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("photostereo-fuzz-dil-{}", std::process::id()));
    if !dir.join("3.png").is_file() {
        let _ = std::fs::create_dir_all(&dir);
        for k in 1..=3u16 {
            let values: Vec<u16> = (0..64u16).map(|i| 1000 + 700 * k + 97 * i).collect();
            let _ = photostereo::io::output::write_png16(
                &dir.join(format!("{k}.png")),
                8,
                8,
                1,
                &values,
            );
        }
    }
    dir
}

fuzz_target!(|data: &[u8]| {
    let dir = folder();
    let mut parts = data.split(|&b| b == 0xFF);
    let names = [
        "filenames.txt",
        "light_directions.txt",
        "light_intensities.txt",
        "mask.png",
    ];
    for name in names {
        let path = dir.join(name);
        match parts.next() {
            Some(bytes) => {
                let _ = std::fs::write(&path, bytes);
            }
            None => {
                let _ = std::fs::remove_file(&path);
            }
        }
    }
    if let Ok(capture) = Capture::from_diligent(&dir, &LoadOptions::default(), &Silent) {
        let _ = reconstruct(&capture, &Config::default(), &Silent);
    }
});
