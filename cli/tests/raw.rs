//! Camera RAW end to end: a rendered sphere mosaicked into an RGGB Bayer pattern with a black
//! level, a 14-bit white level and a colour cast the as-shot white balance undoes, written as DNG
//! files (rawler's writer), then reconstructed from the command line. The development (black
//! subtracted, scaled to the white level, balanced, 2×2 quads binned) must give the rendered
//! radiance back, so the normals match the truth, and `report.json` records every choice.

#[path = "../../tests/common/mod.rs"]
mod common;

use common::{os, run};
use photostereo::capture::lights::Lights;
use photostereo::eval::demo::synthesize;
use photostereo::synth::render::RenderOptions;
use photostereo::synth::scene::{Albedo, Scene};
use rawler::cfa::{CFA, PlaneColor};
use rawler::decoders::Camera;
use rawler::dng::writer::DngWriter;
use rawler::dng::{CropMode, DNG_VERSION_V1_4, DngCompression, DngPhotometricConversion};
use rawler::formats::tiff::Rational;
use rawler::pixarray::PixU16;
use rawler::rawimage::{BlackLevel, CFAConfig, RawImage, RawPhotometricInterpretation, WhiteLevel};
use std::path::Path;

const BLACK: u16 = 512;
const WHITE: u16 = 16383;
/// What the camera's white balance multiplies R, G, B by: the sensor saw R at half and B at
/// two thirds of G for a grey surface.
const WB: [f32; 3] = [2.0, 1.0, 1.5];

/// Writes `radiance` (w×h, linear, ≤ 1) as an RGGB DNG at twice the size.
fn write_dng(path: &Path, radiance: &[f32], w: usize, h: usize) {
    let (sw, sh) = (2 * w, 2 * h);
    let mut counts = vec![0u16; sw * sh];
    let range = f32::from(WHITE - BLACK);
    for y in 0..sh {
        for x in 0..sw {
            // RGGB: R at (even, even), B at (odd, odd), G elsewhere.
            let colour = match (y % 2, x % 2) {
                (0, 0) => 0,
                (1, 1) => 2,
                _ => 1,
            };
            let v = radiance[(y / 2) * w + x / 2] / WB[colour];
            counts[y * sw + x] =
                (f32::from(BLACK) + v * range).round().min(f32::from(WHITE)) as u16;
        }
    }
    let cfa = CFA::new("RGGB");
    let camera = Camera {
        make: "photostereo".into(),
        model: "test sensor".into(),
        clean_make: "photostereo".into(),
        clean_model: "test sensor".into(),
        cfa: cfa.clone(),
        ..Camera::default()
    };
    let photometric =
        RawPhotometricInterpretation::Cfa(CFAConfig::new(&cfa, &PlaneColor::default()));
    let image = RawImage::new(
        camera,
        PixU16::new_with(counts, sw, sh),
        1,
        [WB[0], WB[1], WB[2], f32::NAN],
        photometric,
        Some(BlackLevel::new(&[BLACK], 1, 1, 1)),
        Some(WhiteLevel::new(vec![u32::from(WHITE)])),
        false,
    );
    let mut file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut dng = DngWriter::new(&mut file, DNG_VERSION_V1_4).unwrap();
    // AsShotNeutral is the reciprocal of the white-balance gains.
    let neutral: Vec<Rational> = WB
        .iter()
        .map(|g| Rational::new((1_000_000.0 / g).round() as u32, 1_000_000))
        .collect();
    dng.as_shot_neutral(&neutral);
    dng.load_base_tags(&image).unwrap();
    let mut frame = dng.subframe_on_root(0);
    frame
        .raw_image(
            &image,
            CropMode::None,
            DngCompression::Uncompressed,
            DngPhotometricConversion::Original,
            1,
        )
        .unwrap();
    frame.finalize().unwrap();
    dng.close().unwrap();
}

#[test]
fn dng_captures_reconstruct_linearly_with_the_development_reported() {
    let tmp = tempfile::tempdir().unwrap();
    let size = 64;
    let scene = Scene::sphere(
        size,
        26.0,
        Albedo::Smooth {
            mean: 0.6,
            amplitude: 0.2,
            period: 17.0,
        },
    );
    let lights = Lights::fibonacci(10, 30.0).unwrap();
    let synth = synthesize(scene, lights.clone(), &RenderOptions::default()).unwrap();
    let mut images = Vec::new();
    for (k, planes) in synth.rendering.images.iter().enumerate() {
        let path = tmp.path().join(format!("img_{k:03}.dng"));
        write_dng(&path, planes[0].data(), size, size);
        images.push(path);
    }
    // The developed image is the rendered radiance, within 14-bit and 16-bit steps.
    let decoded = photostereo::io::decode::read_image(&images[0]).unwrap();
    assert_eq!(
        (decoded.width, decoded.height, decoded.channels),
        (size, size, 3)
    );
    let truth = synth.rendering.images[0][0].data();
    let top = WB.iter().copied().fold(1.0f32, f32::max);
    let worst = decoded
        .data
        .chunks_exact(3)
        .zip(truth)
        .flat_map(|(px, &t)| px.iter().map(move |&v| (v * top - t).abs()))
        .fold(0.0f32, f32::max);
    assert!(worst < 2e-4, "developed samples are off by up to {worst}");

    let lights_txt = tmp.path().join("lights.txt");
    common::write_plain_lights(&lights_txt, &lights);
    let mask = tmp.path().join("mask.png");
    let m: Vec<u8> = synth
        .truth
        .mask
        .data()
        .iter()
        .map(|&b| if b { 255 } else { 0 })
        .collect();
    image::GrayImage::from_raw(size as u32, size as u32, m)
        .unwrap()
        .save(&mask)
        .unwrap();
    let out = tmp.path().join("out");
    let mut args: Vec<&std::ffi::OsStr> = images.iter().map(|p| p.as_os_str()).collect();
    args.extend([
        os("--lights"),
        lights_txt.as_os_str(),
        os("--mask"),
        mask.as_os_str(),
        os("--integrate"),
        os("none"),
        os("-q"),
        os("-o"),
        out.as_os_str(),
    ]);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let normals = photostereo::io::decode::read_normal_map(&out.join("normal.exr")).unwrap();
    let e = photostereo::eval::metrics::angular_errors(
        &normals,
        &synth.truth.normals,
        &synth.truth.mask,
    )
    .unwrap();
    assert!(e.mean_deg < 0.1, "{e:?}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let raw = &report["inputs"]["raw"];
    assert_eq!(raw["cfa"], "RGGB", "{raw}");
    assert_eq!(raw["binning"], "2x2 CFA quad");
    assert_eq!(raw["sensor"], serde_json::json!([2 * size, 2 * size]));
    for k in 0..4 {
        assert_eq!(
            raw["black_levels"][k].as_f64(),
            Some(f64::from(BLACK)),
            "{raw}"
        );
        assert_eq!(
            raw["white_levels"][k].as_f64(),
            Some(f64::from(WHITE)),
            "{raw}"
        );
    }
    for (c, g) in WB.iter().enumerate() {
        let got = raw["white_balance"][c].as_f64().unwrap();
        assert!((got - f64::from(*g)).abs() < 1e-4, "{raw}");
    }
    // 16-bit storage, not decoded as sRGB.
    assert_eq!(report["inputs"]["format"], "u16");
    assert_eq!(report["inputs"]["linearised_images"], 0);
}
