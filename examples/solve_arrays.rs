//! Photometric stereo on arrays a caller already holds: a DiLiGenT-layout folder read into one
//! `N×H×W×C` array of its stored samples, then solved from that array with the library, as
//! Rust vision code (or the Python module) hands images over. Prints one JSON line a repetition
//! with the seconds of the array → normals call (conversion, capture-wide model, per-pixel
//! solve, albedo and normals), and the mean angular error when the folder has `normal_gt.exr`.
//! `python/benches/solve_speed.py` runs it beside the Python module and the numpy peer.
//!
//! `cargo run --release --example solve_arrays -- path/to/catPNG [REPEATS]`

use photostereo::eval::metrics::angular_errors;
use photostereo::io::decode::{ImageArray, read_array, read_mask, read_normal_map};
use photostereo::ndarray::{Array4, Axis, stack};
use photostereo::progress::Silent;
use photostereo::run::pipeline::reconstruct_normals;
use photostereo::{Capture, CaptureFiles, Config, LoadOptions};
use std::path::PathBuf;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(
        args.next()
            .ok_or("usage: solve_arrays DILIGENT_DIR [REPEATS]")?,
    );
    let repeats: usize = args.next().map_or(Ok(1), |r| r.parse())?;
    let files = CaptureFiles::from_diligent(&dir, None)?;
    let mask_path = files
        .mask_source
        .clone()
        .ok_or("the folder has no mask.png")?;
    let mask = read_mask(&mask_path)?.into_array();
    let planes = files
        .images
        .iter()
        .map(|p| match read_array(p)? {
            ImageArray::U16(a) => Ok(a),
            _ => Err(format!("{}: 16-bit images expected", p.display()).into()),
        })
        .collect::<Result<Vec<_>, Box<dyn std::error::Error>>>()?;
    let views: Vec<_> = planes.iter().map(|a| a.view()).collect();
    let images: Array4<u16> = stack(Axis(0), &views)?;
    let config = Config {
        integration: None,
        ..Config::default()
    };
    for _ in 0..repeats {
        let t = Instant::now();
        let capture = Capture::from_arrays_channels(
            images.view(),
            files.lights.clone(),
            Some(mask.view()),
            &LoadOptions::default(),
        )?;
        let recon = reconstruct_normals(&capture, &config, &Silent)?;
        let seconds = t.elapsed().as_secs_f64();
        let gt = dir.join("normal_gt.exr");
        let err = if gt.is_file() {
            let e = angular_errors(&recon.maps.normals, &read_normal_map(&gt)?, &capture.mask)?;
            format!("{:.4}", e.mean_deg)
        } else {
            "null".into()
        };
        println!("{{\"seconds\": {seconds:.6}, \"mean_deg\": {err}}}");
    }
    Ok(())
}
