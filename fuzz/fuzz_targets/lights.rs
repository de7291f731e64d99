//! Lights files of any content, as JSON and as `x y z` text: parsing, matching to images,
//! validation and the JSON round trip must return values or errors, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use photostereo::capture::lights::Lights;
use std::path::{Path, PathBuf};

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let source = Path::new("fuzz-lights");
    for parsed in [
        Lights::from_json_str(&text, source),
        Lights::from_text_str(&text, source),
    ] {
        let Ok(lights) = parsed else { continue };
        let _ = lights.condition_number();
        let _ = lights.check_usable(1e4);
        let images: Vec<PathBuf> = (0..lights.len())
            .map(|k| PathBuf::from(format!("img_{k:03}.exr")))
            .collect();
        let _ = lights.matched_to(&images);
        let json = lights.to_json();
        // What we write, we read back.
        assert!(
            Lights::from_json_str(&json, source).is_ok(),
            "round trip failed for {json}"
        );
    }
});
