//! Image loading through the public API: PNG (8/16-bit), TIFF (8/16-bit) and EXR (half/float)
//! files written to a temporary folder, loaded with `read_image`, `load_stack`, `read_mask` and
//! `image_size`, and checked against the exact values the documentation promises.

mod common;

use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer, LayerAttributes, SmallVec,
    WritableImage, f16,
};
use image::{DynamicImage, ImageBuffer};
use nalgebra::Vector3;
use photostereo::Error;
use photostereo::capture::lights::{Light, Lights};
use photostereo::capture::stack::{
    ColorMode, GREY_WEIGHTS, ImageStack, LoadOptions, Transfer, load_stack, load_stack_with_ambient,
};
use photostereo::grid::Window;
use photostereo::io::decode::{SampleFormat, image_size, read_image, read_mask, srgb_to_linear};
use photostereo::io::output::{write_exr, write_png8, write_png16};
use photostereo::progress::Silent;
use std::path::{Path, PathBuf};

// ---------------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------------

/// Four light directions in general position (any three are independent).
fn directions() -> [Vector3<f64>; 4] {
    [
        Vector3::new(0.0, 0.0, 1.0),
        Vector3::new(1.0, 0.0, 1.0),
        Vector3::new(0.0, 1.0, 1.0),
        Vector3::new(-1.0, 0.0, 1.0),
    ]
}

/// `n` unit-intensity lights.
fn unit_lights(n: usize) -> Lights {
    Lights::from_directions(&directions()[..n]).unwrap()
}

/// One light per entry of `intensities`, with the given per-channel intensity.
fn lights_with(intensities: &[[f64; 3]]) -> Lights {
    let dirs = directions();
    Lights::new(
        intensities
            .iter()
            .zip(dirs.iter().cycle())
            .map(|(i, d)| Light {
                direction: *d,
                intensity: *i,
                file: None,
                position: None,
                anisotropy: None,
            })
            .collect(),
    )
    .unwrap()
}

/// Loads `paths` under unit lights with `options`.
fn load(paths: &[PathBuf], options: LoadOptions) -> ImageStack {
    load_stack(paths, &unit_lights(paths.len()), &options, &Silent).unwrap()
}

fn opts(color: ColorMode, transfer: Transfer) -> LoadOptions {
    LoadOptions {
        color,
        transfer,
        ..LoadOptions::default()
    }
}

/// Asserts `|actual[i] - expected[i]| <= tol` for every i, naming the first offender.
fn assert_close(actual: &[f32], expected: &[f32], tol: f32, what: &str) {
    assert_eq!(actual.len(), expected.len(), "{what}: length");
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        assert!(
            (a - e).abs() <= tol,
            "{what}: sample {i} is {a:e}, expected {e:e} (tolerance {tol:e})"
        );
    }
}

/// Like [`assert_close`] with a relative tolerance, and NaN expected where `expected` is NaN.
fn assert_rel(actual: &[f32], expected: &[f32], rel: f32, what: &str) {
    assert_eq!(actual.len(), expected.len(), "{what}: length");
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        if e.is_nan() {
            assert!(a.is_nan(), "{what}: sample {i} is {a:e}, expected NaN");
        } else {
            assert!(
                (a - e).abs() <= rel * e.abs(),
                "{what}: sample {i} is {a:e}, expected {e:e} (relative tolerance {rel:e})"
            );
        }
    }
}

/// Bitwise equality, NaN equal to NaN.
fn assert_same(actual: &[f32], expected: &[f32], what: &str) {
    assert_eq!(actual.len(), expected.len(), "{what}: length");
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        assert!(
            a == e || (a.is_nan() && e.is_nan()),
            "{what}: sample {i} is {a:e}, expected exactly {e:e}"
        );
    }
}

fn u16_to_unit(codes: &[u16]) -> Vec<f32> {
    codes.iter().map(|c| f32::from(*c) / 65535.0).collect()
}

fn u8_to_unit(codes: &[u8]) -> Vec<f32> {
    codes.iter().map(|c| f32::from(*c) / 255.0).collect()
}

/// Channel `c` of interleaved data with `stride` values per pixel.
fn channel<T: Copy>(data: &[T], stride: usize, c: usize) -> Vec<T> {
    data.chunks_exact(stride).map(|px| px[c]).collect()
}

fn save(img: DynamicImage, path: &Path) {
    img.save(path)
        .unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
}

fn luma8(w: u32, h: u32, data: &[u8]) -> DynamicImage {
    DynamicImage::ImageLuma8(ImageBuffer::from_raw(w, h, data.to_vec()).unwrap())
}

fn rgb8(w: u32, h: u32, data: &[u8]) -> DynamicImage {
    DynamicImage::ImageRgb8(ImageBuffer::from_raw(w, h, data.to_vec()).unwrap())
}

fn rgba8(w: u32, h: u32, data: &[u8]) -> DynamicImage {
    DynamicImage::ImageRgba8(ImageBuffer::from_raw(w, h, data.to_vec()).unwrap())
}

fn luma16(w: u32, h: u32, data: &[u16]) -> DynamicImage {
    DynamicImage::ImageLuma16(ImageBuffer::from_raw(w, h, data.to_vec()).unwrap())
}

fn luma_alpha16(w: u32, h: u32, data: &[u16]) -> DynamicImage {
    DynamicImage::ImageLumaA16(ImageBuffer::from_raw(w, h, data.to_vec()).unwrap())
}

fn rgb16(w: u32, h: u32, data: &[u16]) -> DynamicImage {
    DynamicImage::ImageRgb16(ImageBuffer::from_raw(w, h, data.to_vec()).unwrap())
}

fn rgba16(w: u32, h: u32, data: &[u16]) -> DynamicImage {
    DynamicImage::ImageRgba16(ImageBuffer::from_raw(w, h, data.to_vec()).unwrap())
}

/// Writes an EXR with the given named channels through the `exr` crate (lossless ZIP).
fn write_exr_channels(path: &Path, w: usize, h: usize, channels: Vec<(&str, FlatSamples)>) {
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> = channels
        .into_iter()
        .map(|(name, samples)| AnyChannel::new(name, samples))
        .collect();
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(list),
    );
    Image::from_layer(layer)
        .write()
        .to_file(path)
        .unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
}

fn halves(values: &[f32]) -> Vec<f16> {
    values.iter().map(|v| f16::from_f32(*v)).collect()
}

fn from_halves(values: &[f16]) -> Vec<f32> {
    values.iter().map(|v| v.to_f32()).collect()
}

/// Pixels flagged saturated in image `k`.
fn saturated_pixels(stack: &ImageStack, k: usize) -> Vec<usize> {
    (0..stack.pixels())
        .filter(|p| stack.is_saturated(k, *p))
        .collect()
}

/// 16-bit codes that 8-bit truncation (or 8-bit scaling) would change: none is a multiple of 257
/// except the ends, which are there to check the scale.
const CODES16: [u16; 10] = [0, 1, 2, 255, 256, 12345, 32767, 40001, 65534, 65535];

// ---------------------------------------------------------------------------------------------
// 1. 16-bit PNG
// ---------------------------------------------------------------------------------------------

/// A 16-bit grey PNG loads to code/65535 for every code (no truncation to 8 bits), in file order.
#[test]
fn png16_grey_keeps_all_16_bits() {
    let dir = tempfile::tempdir().unwrap();
    let mut paths = Vec::new();
    let mut expected = Vec::new();
    for k in 0..3 {
        let mut codes = CODES16;
        codes.rotate_left(k * 3);
        let p = dir.path().join(format!("grey16_{k}.png"));
        write_png16(&p, 5, 2, 1, &codes).unwrap();
        paths.push(p);
        expected.push(codes);
    }
    let stack = load(&paths, LoadOptions::default());
    assert_eq!((stack.width(), stack.height()), (5, 2));
    assert_eq!((stack.count(), stack.channels()), (3, 1));
    for (k, codes) in expected.iter().enumerate() {
        assert_close(
            stack.plane(k, 0),
            &u16_to_unit(codes),
            1e-7,
            &format!("image {k}"),
        );
        let info = &stack.info()[k];
        assert_eq!(info.format, SampleFormat::U16);
        assert_eq!(info.channels, 1);
        assert!(!info.linearised, "16-bit data must stay linear under Auto");
        assert_eq!(info.non_finite, 0);
        assert_eq!(info.path, paths[k]);
    }
    // read_image agrees.
    let img = read_image(&paths[0]).unwrap();
    assert_eq!((img.width, img.height, img.channels), (5, 2, 1));
    assert_eq!(img.format, SampleFormat::U16);
    assert_close(&img.data, &u16_to_unit(&expected[0]), 1e-7, "read_image");
}

/// A 16-bit RGB PNG keeps all 16 bits per channel, both as per-channel planes and in the grey mix.
#[test]
fn png16_rgb_keeps_all_16_bits() {
    let dir = tempfile::tempdir().unwrap();
    // 4x2 pixels, 3 channels: 24 codes, none a multiple of 257 except 0 and 65535.
    let codes: Vec<u16> = (0..24u32)
        .map(|i| ((i * 2731 + 40001) % 65536) as u16)
        .collect();
    let paths: Vec<PathBuf> = (0..3)
        .map(|k| {
            let p = dir.path().join(format!("rgb16_{k}.png"));
            let mut c = codes.clone();
            c.rotate_left(k);
            save(rgb16(4, 2, &c), &p);
            p
        })
        .collect();
    let per = load(&paths, opts(ColorMode::PerChannel, Transfer::Auto));
    let grey = load(&paths, LoadOptions::default());
    assert_eq!(per.channels(), 3);
    assert_eq!(grey.channels(), 1);
    for k in 0..3 {
        let mut c = codes.clone();
        c.rotate_left(k);
        let unit = u16_to_unit(&c);
        for ch in 0..3 {
            assert_close(
                per.plane(k, ch),
                &channel(&unit, 3, ch),
                1e-7,
                &format!("image {k} channel {ch}"),
            );
        }
        let mix: Vec<f32> = unit
            .chunks_exact(3)
            .map(|px| (0..3).map(|c| GREY_WEIGHTS[c] * px[c]).sum())
            .collect();
        assert_close(grey.plane(k, 0), &mix, 2e-7, &format!("grey image {k}"));
        assert_eq!(per.info()[k].format, SampleFormat::U16);
        assert_eq!(per.info()[k].channels, 3);
        assert!(!per.info()[k].linearised);
    }
    let img = read_image(&paths[0]).unwrap();
    assert_eq!(img.channels, 3);
    assert_close(&img.data, &u16_to_unit(&codes), 1e-7, "read_image");
}

/// The alpha channel of a 16-bit RGBA PNG is dropped: values, grey mix and saturation ignore it.
#[test]
fn png16_rgba_alpha_is_dropped() {
    let dir = tempfile::tempdir().unwrap();
    // 3x1 pixels: alpha is 65535 (would be "saturated"), 0 and 1.
    let rgba: [u16; 12] = [
        40001, 1, 65534, 65535, //
        2, 30000, 12345, 0, //
        65534, 65534, 65534, 1,
    ];
    let rgb: Vec<u16> = rgba
        .chunks_exact(4)
        .flat_map(|px| px[..3].to_vec())
        .collect();
    let p = dir.path().join("rgba16.png");
    save(rgba16(3, 1, &rgba), &p);
    let paths = vec![p.clone(), p.clone(), p.clone()];

    let img = read_image(&p).unwrap();
    assert_eq!((img.width, img.height, img.channels), (3, 1, 3));
    assert_close(&img.data, &u16_to_unit(&rgb), 1e-7, "read_image");

    let per = load(&paths, opts(ColorMode::PerChannel, Transfer::Auto));
    let unit = u16_to_unit(&rgb);
    for ch in 0..3 {
        assert_close(per.plane(0, ch), &channel(&unit, 3, ch), 1e-7, "plane");
    }
    assert_eq!(per.info()[0].channels, 3);
    assert_eq!(per.info()[0].saturated, 0, "alpha 65535 is not saturation");
    assert!(per.saturation_bits(0).is_none());

    let grey = load(&paths, LoadOptions::default());
    let mix: Vec<f32> = unit
        .chunks_exact(3)
        .map(|px| (0..3).map(|c| GREY_WEIGHTS[c] * px[c]).sum())
        .collect();
    assert_close(grey.plane(2, 0), &mix, 2e-7, "grey mix without alpha");
    assert_eq!(grey.info()[2].saturated, 0);
}

/// A 16-bit grey+alpha PNG loads as one channel (alpha dropped) with all 16 bits.
#[test]
fn png16_grey_alpha_is_one_channel() {
    let dir = tempfile::tempdir().unwrap();
    let la: [u16; 6] = [40001, 65535, 1, 0, 65534, 7];
    let p = dir.path().join("la16.png");
    save(luma_alpha16(3, 1, &la), &p);
    let img = read_image(&p).unwrap();
    assert_eq!(img.channels, 1);
    assert_close(
        &img.data,
        &u16_to_unit(&[40001, 1, 65534]),
        1e-7,
        "read_image",
    );
    let stack = load(&[p.clone(), p.clone(), p], LoadOptions::default());
    assert_close(
        stack.plane(1, 0),
        &u16_to_unit(&[40001, 1, 65534]),
        1e-7,
        "stack",
    );
    assert_eq!(stack.info()[1].channels, 1);
    assert_eq!(stack.info()[1].saturated, 0);
}

/// Only code 65535 saturates a 16-bit image by default (65534 does not), in any channel, and the
/// bitmask addresses pixels beyond the first 64-bit word correctly.
#[test]
fn png16_saturation_only_at_maximum_code() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (67usize, 3usize);
    let n = w * h;
    let mut grey = vec![40001u16; n];
    let full = [3usize, 64, 70, 133, n - 1];
    for p in full {
        grey[p] = 65535;
    }
    for p in [0usize, 65, 134, 150] {
        grey[p] = 65534;
    }
    let gp = dir.path().join("sat_grey.png");
    write_png16(&gp, w, h, 1, &grey).unwrap();

    // RGB: one channel at 65535 is enough; 65534 in all three is not.
    let mut rgb = vec![20000u16; n * 3];
    rgb[5 * 3 + 1] = 65535; // pixel 5, G
    rgb[100 * 3 + 2] = 65535; // pixel 100, B
    rgb[101 * 3] = 65535; // pixel 101, R
    for c in 0..3 {
        rgb[102 * 3 + c] = 65534;
    }
    let cp = dir.path().join("sat_rgb.png");
    save(rgb16(w as u32, h as u32, &rgb), &cp);

    // An image with nothing saturated.
    let clean = dir.path().join("clean.png");
    write_png16(&clean, w, h, 1, &vec![65534u16; n]).unwrap();

    let clean_rgb = dir.path().join("clean_rgb.png");
    save(
        rgb16(w as u32, h as u32, &vec![65534u16; n * 3]),
        &clean_rgb,
    );

    for color in [ColorMode::Grey, ColorMode::PerChannel] {
        let paths = vec![cp.clone(), clean_rgb.clone(), cp.clone()];
        let stack = load(&paths, opts(color, Transfer::Auto));
        assert_eq!(saturated_pixels(&stack, 0), vec![5, 100, 101], "{color:?}");
        assert_eq!(stack.info()[0].saturated, 3);
        assert!(stack.saturation_bits(1).is_none(), "65534 is not saturated");
        assert_eq!(stack.info()[1].saturated, 0);
    }
    let paths = vec![gp.clone(), clean.clone(), gp];
    let stack = load(&paths, LoadOptions::default());
    assert_eq!(saturated_pixels(&stack, 0), full.to_vec());
    assert_eq!(stack.info()[0].saturated, full.len());
    assert_eq!(saturated_pixels(&stack, 2), full.to_vec());
    assert!(stack.saturation_bits(1).is_none());
    // Saturated samples keep their value.
    assert_eq!(stack.plane(0, 0)[64], 1.0);
}

/// `saturation: Some(0.5)` flags 16-bit codes ≥ 32768 and nothing below.
#[test]
fn png16_saturation_option_lowers_the_level() {
    let dir = tempfile::tempdir().unwrap();
    let codes: [u16; 8] = [0, 1, 32766, 32767, 32768, 32769, 40001, 65535];
    let p = dir.path().join("levels.png");
    write_png16(&p, 4, 2, 1, &codes).unwrap();
    let options = LoadOptions {
        saturation: Some(0.5),
        ..LoadOptions::default()
    };
    let stack = load(&[p.clone(), p.clone(), p], options);
    for k in 0..3 {
        assert_eq!(saturated_pixels(&stack, k), vec![4, 5, 6, 7]);
        assert_eq!(stack.info()[k].saturated, 4);
    }
    // The level does not change the values.
    assert_close(stack.plane(0, 0), &u16_to_unit(&codes), 1e-7, "values");
}

// ---------------------------------------------------------------------------------------------
// 2. 8-bit PNG and transfer functions
// ---------------------------------------------------------------------------------------------

/// All 256 codes of an 8-bit grey PNG: `Auto` decodes sRGB, `Linear` gives code/255.
#[test]
fn png8_auto_is_srgb_linear_is_code_over_255() {
    let dir = tempfile::tempdir().unwrap();
    let codes: Vec<u8> = (0..=255u8).collect();
    let p = dir.path().join("ramp8.png");
    write_png8(&p, 16, 16, 1, &codes).unwrap();
    let paths = vec![p.clone(), p.clone(), p];

    let auto = load(&paths, LoadOptions::default());
    let srgb: Vec<f32> = codes
        .iter()
        .map(|c| srgb_to_linear(f32::from(*c) / 255.0))
        .collect();
    for k in 0..3 {
        assert_close(auto.plane(k, 0), &srgb, 1e-7, "auto");
        assert!(auto.info()[k].linearised);
        assert_eq!(auto.info()[k].format, SampleFormat::U8);
    }
    // A mid code really is decoded (not left linear): sRGB 128 ≈ 0.2158.
    assert!((auto.plane(0, 0)[128] - 0.215_861).abs() < 1e-5);

    let linear = load(
        &[
            auto.info()[0].path.clone(),
            auto.info()[1].path.clone(),
            auto.info()[2].path.clone(),
        ],
        opts(ColorMode::Grey, Transfer::Linear),
    );
    assert_close(linear.plane(1, 0), &u8_to_unit(&codes), 1e-7, "linear");
    assert!(!linear.info()[1].linearised);

    // Explicit Srgb matches Auto on 8-bit data.
    let forced = load(&paths_of(&auto), opts(ColorMode::Grey, Transfer::Srgb));
    assert_same(forced.plane(2, 0), auto.plane(2, 0), "srgb vs auto");
    assert!(forced.info()[2].linearised);
}

fn paths_of(stack: &ImageStack) -> Vec<PathBuf> {
    stack.info().iter().map(|i| i.path.clone()).collect()
}

/// 8-bit RGB and RGBA PNGs are linearised per channel; alpha is neither decoded nor mixed in.
#[test]
fn png8_rgb_and_rgba_linearise_each_channel() {
    let dir = tempfile::tempdir().unwrap();
    let rgb: [u8; 12] = [0, 1, 10, 11, 64, 128, 200, 254, 255, 3, 77, 190];
    let rgba: Vec<u8> = rgb
        .chunks_exact(3)
        .zip([255u8, 0, 17, 128])
        .flat_map(|(px, a)| [px[0], px[1], px[2], a])
        .collect();
    let p3 = dir.path().join("rgb8.png");
    let p4 = dir.path().join("rgba8.png");
    write_png8(&p3, 2, 2, 3, &rgb).unwrap();
    save(rgba8(2, 2, &rgba), &p4);
    let lin: Vec<f32> = rgb
        .iter()
        .map(|c| srgb_to_linear(f32::from(*c) / 255.0))
        .collect();
    let paths = vec![p3, p4.clone(), p4];
    let per = load(&paths, opts(ColorMode::PerChannel, Transfer::Auto));
    let grey = load(&paths, LoadOptions::default());
    let mix: Vec<f32> = lin
        .chunks_exact(3)
        .map(|px| (0..3).map(|c| GREY_WEIGHTS[c] * px[c]).sum())
        .collect();
    for k in 0..3 {
        for ch in 0..3 {
            assert_close(
                per.plane(k, ch),
                &channel(&lin, 3, ch),
                1e-7,
                &format!("image {k} channel {ch}"),
            );
        }
        assert_close(grey.plane(k, 0), &mix, 2e-7, &format!("grey {k}"));
        assert!(per.info()[k].linearised);
        assert_eq!(per.info()[k].channels, 3);
    }
    // Pixel 2 has R = 255 (saturated); alpha 255 on pixel 0 of the RGBA file is not.
    for k in 0..3 {
        assert_eq!(saturated_pixels(&per, k), vec![2], "image {k}");
    }
}

/// 8-bit saturation: 255 flags, 254 does not; `Some(0.5)` compares stored code/255 (not the
/// linearised value), so code 128 flags and 127 does not.
#[test]
fn png8_saturation_uses_stored_values() {
    let dir = tempfile::tempdir().unwrap();
    let codes: [u8; 6] = [0, 127, 128, 200, 254, 255];
    let p = dir.path().join("sat8.png");
    write_png8(&p, 6, 1, 1, &codes).unwrap();
    let paths = vec![p.clone(), p.clone(), p];
    let stack = load(&paths, LoadOptions::default());
    assert_eq!(saturated_pixels(&stack, 0), vec![5]);
    let half = load(
        &paths,
        LoadOptions {
            saturation: Some(0.5),
            ..LoadOptions::default()
        },
    );
    assert_eq!(saturated_pixels(&half, 1), vec![2, 3, 4, 5]);
    assert_eq!(half.info()[1].saturated, 4);
}

/// 16-bit data stays linear under `Auto` and `Linear`; `Srgb` forces decoding of 16-bit data.
#[test]
fn png16_transfer_auto_linear_and_forced_srgb() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("t16.png");
    write_png16(&p, 5, 2, 1, &CODES16).unwrap();
    let paths = vec![p.clone(), p.clone(), p];
    let unit = u16_to_unit(&CODES16);
    for transfer in [Transfer::Auto, Transfer::Linear] {
        let stack = load(&paths, opts(ColorMode::Grey, transfer));
        assert_close(stack.plane(0, 0), &unit, 1e-7, &format!("{transfer:?}"));
        assert!(!stack.info()[0].linearised);
    }
    let srgb = load(&paths, opts(ColorMode::Grey, Transfer::Srgb));
    let expected: Vec<f32> = unit.iter().map(|v| srgb_to_linear(*v)).collect();
    assert_close(srgb.plane(0, 0), &expected, 2e-7, "forced sRGB");
    assert!(srgb.info()[0].linearised);
    // Decoding actually happened: 32767/65535 ≈ 0.5 decodes to ≈ 0.214.
    assert!((srgb.plane(0, 0)[6] - 0.214_04).abs() < 1e-4);
    // Saturation is still judged on stored codes.
    assert_eq!(saturated_pixels(&srgb, 0), vec![9]);
}

// ---------------------------------------------------------------------------------------------
// 3. TIFF
// ---------------------------------------------------------------------------------------------

/// 8-bit TIFFs (grey and RGB) load to exactly the values of the same data as PNG (sRGB decoded).
#[test]
fn tiff8_matches_png8() {
    let dir = tempfile::tempdir().unwrap();
    let grey: Vec<u8> = (0..12u8).map(|i| i * 23).collect();
    let rgb: Vec<u8> = (0..36u32).map(|i| ((i * 37 + 5) % 256) as u8).collect();
    let (tg, pg) = (dir.path().join("g8.tif"), dir.path().join("g8.png"));
    let (tc, pc) = (dir.path().join("c8.tiff"), dir.path().join("c8.png"));
    save(luma8(4, 3, &grey), &tg);
    save(luma8(4, 3, &grey), &pg);
    save(rgb8(4, 3, &rgb), &tc);
    save(rgb8(4, 3, &rgb), &pc);

    let ti = read_image(&tg).unwrap();
    assert_eq!((ti.width, ti.height, ti.channels), (4, 3, 1));
    assert_eq!(ti.format, SampleFormat::U8);
    assert_same(&ti.data, &read_image(&pg).unwrap().data, "read_image grey");
    assert_same(
        &read_image(&tc).unwrap().data,
        &read_image(&pc).unwrap().data,
        "read_image rgb",
    );

    let tiffs = load(&[tg.clone(), tg.clone(), tg], LoadOptions::default());
    let pngs = load(&[pg.clone(), pg.clone(), pg], LoadOptions::default());
    assert_same(tiffs.data(), pngs.data(), "grey stack");
    let lin: Vec<f32> = grey
        .iter()
        .map(|c| srgb_to_linear(f32::from(*c) / 255.0))
        .collect();
    assert_close(tiffs.plane(0, 0), &lin, 1e-7, "tiff grey values");
    assert!(tiffs.info()[0].linearised);
    assert_eq!(tiffs.info()[0].format, SampleFormat::U8);

    let o = opts(ColorMode::PerChannel, Transfer::Auto);
    let tiffs = load(&[tc.clone(), tc.clone(), tc], o);
    let pngs = load(&[pc.clone(), pc.clone(), pc], o);
    assert_same(tiffs.data(), pngs.data(), "rgb stack");
    assert_eq!(tiffs.info()[2].channels, 3);
}

/// 16-bit TIFFs (grey and RGB) keep all 16 bits and match the PNG equivalents.
#[test]
fn tiff16_matches_png16() {
    let dir = tempfile::tempdir().unwrap();
    let rgb: Vec<u16> = (0..30u32)
        .map(|i| ((i * 2731 + 40001) % 65536) as u16)
        .collect();
    let (tg, pg) = (dir.path().join("g16.tif"), dir.path().join("g16.png"));
    let (tc, pc) = (dir.path().join("c16.tif"), dir.path().join("c16.png"));
    save(luma16(5, 2, &CODES16), &tg);
    write_png16(&pg, 5, 2, 1, &CODES16).unwrap();
    save(rgb16(5, 2, &rgb), &tc);
    save(rgb16(5, 2, &rgb), &pc);

    let ti = read_image(&tg).unwrap();
    assert_eq!(ti.format, SampleFormat::U16);
    assert_eq!(ti.channels, 1);
    assert_close(&ti.data, &u16_to_unit(&CODES16), 1e-7, "read_image tiff");
    assert_same(&ti.data, &read_image(&pg).unwrap().data, "read_image grey");
    let tci = read_image(&tc).unwrap();
    assert_eq!(tci.channels, 3);
    assert_same(&tci.data, &read_image(&pc).unwrap().data, "read_image rgb");

    let tiffs = load(&[tg.clone(), tg.clone(), tg], LoadOptions::default());
    let pngs = load(&[pg.clone(), pg.clone(), pg], LoadOptions::default());
    assert_close(tiffs.plane(1, 0), &u16_to_unit(&CODES16), 1e-7, "tiff");
    assert_same(tiffs.data(), pngs.data(), "grey stack");
    assert!(!tiffs.info()[1].linearised);
    assert_eq!(saturated_pixels(&tiffs, 1), vec![9]);

    let o = opts(ColorMode::PerChannel, Transfer::Auto);
    let tiffs = load(&[tc.clone(), tc.clone(), tc], o);
    let pngs = load(&[pc.clone(), pc.clone(), pc], o);
    assert_same(tiffs.data(), pngs.data(), "rgb stack");
    let unit = u16_to_unit(&rgb);
    for ch in 0..3 {
        assert_close(tiffs.plane(0, ch), &channel(&unit, 3, ch), 1e-7, "rgb");
    }
}

// ---------------------------------------------------------------------------------------------
// 4. EXR
// ---------------------------------------------------------------------------------------------

const FLOATS: [f32; 6] = [0.1, 123.456, 1e-30, -2.5, 65504.0, 0.0];

/// A float32 RGB EXR (written with `output::write_exr`) comes back bit-exactly per channel,
/// including negatives, tiny and large values, with no saturation and no sRGB decoding.
#[test]
fn exr_f32_rgb_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let r = FLOATS.to_vec();
    let g: Vec<f32> = FLOATS.iter().map(|v| v * 3.0 + 0.7).collect();
    let b: Vec<f32> = FLOATS.iter().rev().copied().collect();
    let p = dir.path().join("rgb32.exr");
    write_exr(&p, 3, 2, &[("R", &r), ("G", &g), ("B", &b)], &[]).unwrap();

    let img = read_image(&p).unwrap();
    assert_eq!((img.width, img.height, img.channels), (3, 2, 3));
    assert_eq!(img.format, SampleFormat::F32);
    assert_same(&channel(&img.data, 3, 0), &r, "read_image R");
    assert_same(&channel(&img.data, 3, 1), &g, "read_image G");
    assert_same(&channel(&img.data, 3, 2), &b, "read_image B");

    let paths = vec![p.clone(), p.clone(), p];
    let stack = load(&paths, opts(ColorMode::PerChannel, Transfer::Auto));
    for k in 0..3 {
        assert_same(stack.plane(k, 0), &r, "R");
        assert_same(stack.plane(k, 1), &g, "G");
        assert_same(stack.plane(k, 2), &b, "B");
        let info = &stack.info()[k];
        assert_eq!(info.format, SampleFormat::F32);
        assert!(!info.linearised);
        assert_eq!((info.saturated, info.non_finite), (0, 0));
        assert!(stack.saturation_bits(k).is_none());
    }
}

/// A single-channel float32 EXR named `Y` loads as grey, bit-exactly under unit light.
#[test]
fn exr_f32_y_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("y32.exr");
    write_exr_channels(&p, 2, 3, vec![("Y", FlatSamples::F32(FLOATS.to_vec()))]);
    assert_eq!(image_size(&p).unwrap(), (2, 3));
    let img = read_image(&p).unwrap();
    assert_eq!((img.width, img.height, img.channels), (2, 3, 1));
    assert_same(&img.data, &FLOATS, "read_image");
    let stack = load(&[p.clone(), p.clone(), p], LoadOptions::default());
    assert_eq!(stack.channels(), 1);
    for k in 0..3 {
        assert_same(stack.plane(k, 0), &FLOATS, "stack");
        assert_eq!(stack.info()[k].channels, 1);
        assert_eq!(stack.info()[k].format, SampleFormat::F32);
    }
}

/// Half-float EXRs (RGB and `Y`) come back as the exact f16 values, reported as `F16`.
#[test]
fn exr_half_rgb_and_y_are_exact_to_f16() {
    let dir = tempfile::tempdir().unwrap();
    let base = [0.1f32, 3.5, 1000.0, 1e-6, -0.25, 65504.0];
    let r = halves(&base);
    let g = halves(&base.map(|v| v * 0.3));
    let b = halves(&base.map(|v| v + 0.01));
    let prgb = dir.path().join("rgb16f.exr");
    write_exr_channels(
        &prgb,
        3,
        2,
        vec![
            ("R", FlatSamples::F16(r.clone())),
            ("G", FlatSamples::F16(g.clone())),
            ("B", FlatSamples::F16(b.clone())),
        ],
    );
    let py = dir.path().join("y16f.exr");
    write_exr_channels(&py, 3, 2, vec![("Y", FlatSamples::F16(g.clone()))]);

    // The f16 values differ from the f32 ones, so exactness to f16 is a real check.
    assert_ne!(from_halves(&r)[0], 0.1);

    let per = load(
        &[prgb.clone(), prgb.clone(), prgb],
        opts(ColorMode::PerChannel, Transfer::Auto),
    );
    for k in 0..3 {
        assert_same(per.plane(k, 0), &from_halves(&r), "R");
        assert_same(per.plane(k, 1), &from_halves(&g), "G");
        assert_same(per.plane(k, 2), &from_halves(&b), "B");
        assert_eq!(per.info()[k].format, SampleFormat::F16);
        assert_eq!(per.info()[k].saturated, 0);
    }
    let grey = load(
        &[py.clone(), py.clone(), py.clone()],
        LoadOptions::default(),
    );
    for k in 0..3 {
        assert_same(grey.plane(k, 0), &from_halves(&g), "Y");
        assert_eq!(grey.info()[k].format, SampleFormat::F16);
        assert_eq!(grey.info()[k].channels, 1);
    }
    let img = read_image(&py).unwrap();
    assert_eq!(img.format, SampleFormat::F16);
    assert_same(&img.data, &from_halves(&g), "read_image");
}

/// An RGBA EXR: alpha is ignored, R, G, B are used.
#[test]
fn exr_rgba_ignores_alpha() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("rgba.exr");
    let r = vec![0.5f32, 2.0];
    let g = vec![0.25f32, 4.0];
    let b = vec![0.125f32, 8.0];
    let a = vec![f32::NAN, 1.0];
    write_exr(&p, 2, 1, &[("R", &r), ("G", &g), ("B", &b), ("A", &a)], &[]).unwrap();
    let stack = load(
        &[p.clone(), p.clone(), p],
        opts(ColorMode::PerChannel, Transfer::Auto),
    );
    assert_same(stack.plane(0, 0), &r, "R");
    assert_same(stack.plane(0, 1), &g, "G");
    assert_same(stack.plane(0, 2), &b, "B");
    assert_eq!(
        stack.info()[0].non_finite,
        0,
        "NaN alpha is not a colour sample"
    );
}

/// NaN and ±Inf samples in float32 RGB EXRs become NaN in every plane of that pixel (grey and
/// per-channel) and are counted per image in `non_finite`; other pixels are untouched.
#[test]
fn exr_f32_non_finite_become_nan_and_are_counted() {
    let dir = tempfile::tempdir().unwrap();
    let n = 8;
    let r: Vec<f32> = (0..n).map(|i| i as f32 * 0.5 + 0.25).collect();
    let mut g: Vec<f32> = r.iter().map(|v| v * 2.0).collect();
    let mut b: Vec<f32> = r.iter().map(|v| v * 4.0).collect();
    let mut r_bad = r.clone();
    r_bad[1] = f32::NAN;
    g[3] = f32::INFINITY;
    b[5] = f32::NEG_INFINITY;
    let bad = dir.path().join("bad.exr");
    let good = dir.path().join("good.exr");
    let g_ok: Vec<f32> = r.iter().map(|v| v * 2.0).collect();
    let b_ok: Vec<f32> = r.iter().map(|v| v * 4.0).collect();
    write_exr(&bad, 4, 2, &[("R", &r_bad), ("G", &g), ("B", &b)], &[]).unwrap();
    write_exr(&good, 4, 2, &[("R", &r), ("G", &g_ok), ("B", &b_ok)], &[]).unwrap();
    let paths = vec![good.clone(), bad.clone(), good];
    let nan_at = [1usize, 3, 5];

    let per = load(&paths, opts(ColorMode::PerChannel, Transfer::Auto));
    for (ch, clean) in [&r, &g_ok, &b_ok].into_iter().enumerate() {
        let mut expected = clean.clone();
        for p in nan_at {
            expected[p] = f32::NAN;
        }
        assert_same(per.plane(1, ch), &expected, &format!("channel {ch}"));
        assert_same(per.plane(0, ch), clean, "clean image 0");
        assert_same(per.plane(2, ch), clean, "clean image 2");
    }
    assert_eq!(per.info()[1].non_finite, 3);
    assert_eq!(per.info()[0].non_finite, 0);
    assert_eq!(per.info()[2].non_finite, 0);

    let grey = load(&paths, LoadOptions::default());
    let plane = grey.plane(1, 0);
    for (p, v) in plane.iter().enumerate() {
        if nan_at.contains(&p) {
            assert!(v.is_nan(), "pixel {p} should be NaN, is {v}");
        } else {
            let e = GREY_WEIGHTS[0] * r[p] + GREY_WEIGHTS[1] * g_ok[p] + GREY_WEIGHTS[2] * b_ok[p];
            assert!((v - e).abs() <= 1e-6 * e, "pixel {p}: {v} vs {e}");
        }
    }
    assert_eq!(grey.info()[1].non_finite, 3);
    assert!(grey.plane(0, 0).iter().all(|v| v.is_finite()));
}

/// NaN and Inf in a half-float `Y` EXR become NaN and are counted.
#[test]
fn exr_half_non_finite_become_nan_and_are_counted() {
    let dir = tempfile::tempdir().unwrap();
    let mut y = halves(&[0.5, 1.5, 2.5, 3.5, 4.5, 5.5]);
    y[0] = f16::NAN;
    y[4] = f16::INFINITY;
    let p = dir.path().join("bad_half.exr");
    write_exr_channels(&p, 3, 2, vec![("Y", FlatSamples::F16(y))]);
    let stack = load(&[p.clone(), p.clone(), p], LoadOptions::default());
    let expected = [f32::NAN, 1.5, 2.5, 3.5, f32::NAN, 5.5];
    for k in 0..3 {
        assert_same(stack.plane(k, 0), &expected, &format!("image {k}"));
        assert_eq!(stack.info()[k].non_finite, 2);
        assert_eq!(stack.info()[k].format, SampleFormat::F16);
    }
}

/// With no saturation level, a float image has no saturated pixels: an infinite sample is
/// non-finite (NaN, excluded), not "saturated".
#[test]
fn exr_inf_is_not_reported_saturated_without_a_level() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("inf.exr");
    write_exr_channels(
        &p,
        2,
        1,
        vec![("Y", FlatSamples::F32(vec![f32::INFINITY, 0.5]))],
    );
    let stack = load(&[p.clone(), p.clone(), p], LoadOptions::default());
    assert!(stack.plane(0, 0)[0].is_nan());
    assert_eq!(stack.info()[0].non_finite, 1);
    assert_eq!(
        stack.info()[0].saturated,
        0,
        "float data has no saturation limit"
    );
    assert!(!stack.is_saturated(0, 0));
}

/// With a forced sRGB transfer, an infinite EXR sample still becomes NaN and counts as non-finite.
#[test]
fn exr_inf_with_srgb_transfer_becomes_nan() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("inf_srgb.exr");
    write_exr_channels(
        &p,
        3,
        1,
        vec![(
            "Y",
            FlatSamples::F32(vec![f32::INFINITY, 0.5, f32::NEG_INFINITY]),
        )],
    );
    let stack = load(
        &[p.clone(), p.clone(), p],
        opts(ColorMode::Grey, Transfer::Srgb),
    );
    let v = stack.plane(0, 0);
    assert!((v[1] - srgb_to_linear(0.5)).abs() < 1e-7);
    assert!(v[0].is_nan(), "+Inf became {}", v[0]);
    assert!(v[2].is_nan(), "-Inf became {}", v[2]);
    assert_eq!(stack.info()[0].non_finite, 2);
}

// ---------------------------------------------------------------------------------------------
// 5. Light intensities
// ---------------------------------------------------------------------------------------------

const INTENSITIES: [[f64; 3]; 3] = [[2.0, 4.0, 8.0], [1.0, 1.0, 1.0], [0.5, 3.0, 10.0]];

/// RGB images in grey mode equal Σ_c w_c·v_c/I_c; in per-channel mode each plane is v_c/I_c.
#[test]
fn rgb_images_are_divided_by_per_channel_intensity() {
    let dir = tempfile::tempdir().unwrap();
    let r = vec![0.8f32, 0.1, 2.0, 0.333];
    let g = vec![0.4f32, 0.9, 0.05, 1.0];
    let b = vec![0.2f32, 0.6, 0.7, 0.0];
    let p = dir.path().join("rgb.exr");
    write_exr(&p, 2, 2, &[("R", &r), ("G", &g), ("B", &b)], &[]).unwrap();
    let paths = vec![p.clone(), p.clone(), p];
    let lights = lights_with(&INTENSITIES);
    let planes = [&r, &g, &b];

    let grey = load_stack(&paths, &lights, &LoadOptions::default(), &Silent).unwrap();
    let per = load_stack(
        &paths,
        &lights,
        &opts(ColorMode::PerChannel, Transfer::Auto),
        &Silent,
    )
    .unwrap();
    for (k, int) in INTENSITIES.iter().enumerate() {
        let i = int.map(|v| v as f32);
        let expected: Vec<f32> = (0..4)
            .map(|p| (0..3).map(|c| GREY_WEIGHTS[c] * planes[c][p] / i[c]).sum())
            .collect();
        assert_rel(grey.plane(k, 0), &expected, 1e-6, &format!("grey {k}"));
        for c in 0..3 {
            let e: Vec<f32> = planes[c].iter().map(|v| v / i[c]).collect();
            assert_rel(per.plane(k, c), &e, 1e-6, &format!("image {k} channel {c}"));
        }
    }
    // Concretely, image 0 pixel 0: 0.299·0.8/2 + 0.587·0.4/4 + 0.114·0.2/8.
    let e0 = 0.299 * 0.8 / 2.0 + 0.587 * 0.4 / 4.0 + 0.114 * 0.2 / 8.0;
    assert!((grey.plane(0, 0)[0] - e0).abs() < 1e-7);
}

/// A grey image under an RGB light is divided by the grey-mixed intensity Σ w_c·I_c, for float,
/// 16-bit and (after sRGB decoding) 8-bit files.
#[test]
fn grey_images_are_divided_by_grey_mixed_intensity() {
    let dir = tempfile::tempdir().unwrap();
    let y = vec![0.5f32, 1.0, 0.02, 7.0];
    let py = dir.path().join("y.exr");
    write_exr_channels(&py, 2, 2, vec![("Y", FlatSamples::F32(y.clone()))]);
    let p16 = dir.path().join("g16.png");
    let codes16 = [40001u16, 1, 65534, 12345];
    write_png16(&p16, 2, 2, 1, &codes16).unwrap();
    let p8 = dir.path().join("g8.png");
    let codes8 = [10u8, 128, 200, 255];
    write_png8(&p8, 2, 2, 1, &codes8).unwrap();
    let lights = lights_with(&INTENSITIES);

    let mixed: Vec<f32> = INTENSITIES
        .iter()
        .map(|i| (0..3).map(|c| GREY_WEIGHTS[c] * i[c] as f32).sum())
        .collect();
    // The library's own grey intensity agrees.
    for (k, l) in lights.lights().iter().enumerate() {
        assert!((l.grey_intensity() as f32 - mixed[k]).abs() < 1e-6);
    }
    // 0.299·2 + 0.587·4 + 0.114·8 = 3.858.
    assert!((mixed[0] - 3.858).abs() < 1e-6);

    let cases: [(&PathBuf, Vec<f32>); 3] = [
        (&py, y.clone()),
        (&p16, u16_to_unit(&codes16)),
        (
            &p8,
            codes8
                .iter()
                .map(|c| srgb_to_linear(f32::from(*c) / 255.0))
                .collect(),
        ),
    ];
    for (path, values) in cases {
        let paths = vec![path.clone(), path.clone(), path.clone()];
        let stack = load_stack(&paths, &lights, &LoadOptions::default(), &Silent).unwrap();
        for (k, m) in mixed.iter().enumerate() {
            let e: Vec<f32> = values.iter().map(|v| v / m).collect();
            assert_rel(
                stack.plane(k, 0),
                &e,
                1e-6,
                &format!("{} image {k}", path.display()),
            );
        }
    }
}

/// An ambient image is converted as each image is — the same transfer function, then divided
/// by that image's light intensity — and subtracted: 8-bit sRGB RGB files, per-channel
/// intensities, grey and per-channel loads. A pixel saturated in the ambient image counts as
/// saturated in every image; values below 0 after the subtraction are kept.
#[test]
fn an_ambient_image_is_subtracted_as_each_image_is_converted() {
    let dir = tempfile::tempdir().unwrap();
    // Two pixels: RGB codes of two images and of the ambient frame (its second pixel
    // saturated in G).
    let images: [[u8; 6]; 3] = [
        [200, 120, 60, 90, 10, 250],
        [150, 220, 30, 40, 5, 17],
        [100, 100, 100, 2, 3, 4],
    ];
    let ambient_codes: [u8; 6] = [20, 30, 40, 60, 255, 5];
    let mut paths = Vec::new();
    for (k, codes) in images.iter().enumerate() {
        let p = dir.path().join(format!("img{k}.png"));
        save(rgb8(2, 1, codes), &p);
        paths.push(p);
    }
    let ambient = dir.path().join("ambient.png");
    save(rgb8(2, 1, &ambient_codes), &ambient);
    let lights = lights_with(&INTENSITIES);
    let lin = |c: u8| srgb_to_linear(f32::from(c) / 255.0);
    let grey = load_stack_with_ambient(
        &paths,
        &lights,
        Some(&ambient),
        &LoadOptions::default(),
        &Silent,
    )
    .unwrap();
    let per = load_stack_with_ambient(
        &paths,
        &lights,
        Some(&ambient),
        &opts(ColorMode::PerChannel, Transfer::Auto),
        &Silent,
    )
    .unwrap();
    let plain = load_stack(&paths, &lights, &LoadOptions::default(), &Silent).unwrap();
    for (k, int) in INTENSITIES.iter().enumerate() {
        let i = int.map(|v| v as f32);
        let own =
            |p: usize, c: usize| (lin(images[k][3 * p + c]) - lin(ambient_codes[3 * p + c])) / i[c];
        let expected: Vec<f32> = (0..2)
            .map(|p| (0..3).map(|c| GREY_WEIGHTS[c] * own(p, c)).sum())
            .collect();
        assert_close(grey.plane(k, 0), &expected, 1e-6, &format!("grey {k}"));
        for c in 0..3 {
            let e: Vec<f32> = (0..2).map(|p| own(p, c)).collect();
            assert_close(per.plane(k, c), &e, 1e-6, &format!("image {k} channel {c}"));
        }
        // The ambient frame's saturated pixel is saturated in every image; without the frame
        // no pixel is (no code of the images is 255).
        assert_eq!(saturated_pixels(&grey, k), vec![1], "image {k}");
        assert_eq!(
            saturated_pixels(&plain, k),
            Vec::<usize>::new(),
            "image {k}"
        );
        assert_eq!(grey.info()[k].saturated, 1);
    }
    // Image 2's second pixel is darker than the frame in R: below 0, kept.
    assert!(per.plane(2, 0)[1] < 0.0);
}

/// An ambient image of another size, colour channel count or integer format than the images
/// is refused, naming it; a half-float frame beside float images is one scale and is used.
#[test]
fn an_ambient_image_that_does_not_fit_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("img.png");
    save(rgb8(2, 2, &[50; 12]), &img);
    let paths = vec![img.clone(), img.clone(), img];
    let lights = unit_lights(3);
    let refused = |ambient: &Path, needle: &str| {
        let e = load_stack_with_ambient(
            &paths,
            &lights,
            Some(ambient),
            &LoadOptions::default(),
            &Silent,
        )
        .unwrap_err();
        assert!(matches!(e, Error::Ambient { .. }), "{e}");
        let text = e.to_string();
        assert!(
            text.contains(&*ambient.to_string_lossy()) && text.contains(needle),
            "{text}"
        );
    };
    let small = dir.path().join("small.png");
    save(rgb8(1, 2, &[5; 6]), &small);
    refused(&small, "size 1x2");
    let grey = dir.path().join("grey.png");
    save(luma8(2, 2, &[5; 4]), &grey);
    refused(&grey, "1 colour channel(s)");
    let deep = dir.path().join("deep.png");
    save(rgb16(2, 2, &[500; 12]), &deep);
    refused(&deep, "16-bit");

    let y = vec![0.5f32, 0.25, 0.125, 1.0];
    let float = dir.path().join("float.exr");
    write_exr(&float, 2, 2, &[("Y", &y)], &[]).unwrap();
    let half = dir.path().join("half.exr");
    write_exr_channels(
        &half,
        2,
        2,
        vec![("Y", FlatSamples::F16(halves(&[0.125; 4])))],
    );
    let stack = load_stack_with_ambient(
        &[float.clone(), float],
        &unit_lights(2),
        Some(&half),
        &LoadOptions::default(),
        &Silent,
    )
    .unwrap();
    let e: Vec<f32> = y.iter().map(|v| v - 0.125).collect();
    assert_close(stack.plane(1, 0), &e, 1e-7, "float less half");
}

/// Saturation is judged on stored values, before the division by intensity.
#[test]
fn saturation_is_judged_before_intensity_division() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("sat.png");
    write_png16(&p, 3, 1, 1, &[65535, 65534, 1]).unwrap();
    let lights = lights_with(&[[4.0; 3], [0.25; 3], [1.0; 3]]);
    let paths = vec![p.clone(), p.clone(), p];
    let stack = load_stack(&paths, &lights, &LoadOptions::default(), &Silent).unwrap();
    for k in 0..3 {
        assert_eq!(saturated_pixels(&stack, k), vec![0], "image {k}");
    }
    assert!((stack.plane(0, 0)[0] - 0.25).abs() < 1e-7);
    assert!((stack.plane(1, 0)[0] - 4.0).abs() < 1e-6);
}

// ---------------------------------------------------------------------------------------------
// 6. Errors
// ---------------------------------------------------------------------------------------------

/// An image whose size differs from the first gives `SizeMismatch` naming its file and index.
#[test]
fn size_mismatch_names_file_and_index() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("first.png");
    let b = dir.path().join("wider_one.png");
    let c = dir.path().join("third.png");
    let d = dir.path().join("taller.exr");
    write_png16(&a, 4, 3, 1, &[100; 12]).unwrap();
    write_png16(&b, 5, 3, 1, &[100; 15]).unwrap();
    write_png16(&c, 4, 3, 1, &[100; 12]).unwrap();
    write_exr_channels(&d, 4, 4, vec![("Y", FlatSamples::F32(vec![0.5; 16]))]);

    let err = load_stack(
        &[a.clone(), b.clone(), c.clone()],
        &unit_lights(3),
        &LoadOptions::default(),
        &Silent,
    )
    .unwrap_err();
    let msg = err.to_string();
    match err {
        Error::SizeMismatch {
            path,
            index,
            width,
            height,
            found_width,
            found_height,
        } => {
            assert_eq!(path, b);
            assert_eq!(index, 1);
            assert_eq!((width, height, found_width, found_height), (4, 3, 5, 3));
        }
        other => panic!("expected SizeMismatch, got {other:?}"),
    }
    assert!(msg.contains("wider_one.png"), "{msg}");
    assert!(msg.contains("image 1"), "{msg}");

    let err = load_stack(
        &[a, c, d.clone()],
        &unit_lights(3),
        &LoadOptions::default(),
        &Silent,
    )
    .unwrap_err();
    let msg = err.to_string();
    assert!(
        matches!(
            err,
            Error::SizeMismatch {
                index: 2,
                found_height: 4,
                ..
            }
        ),
        "{err:?}"
    );
    assert!(
        msg.contains("taller.exr") && msg.contains("image 2"),
        "{msg}"
    );
}

/// A corrupt PNG (random bytes) fails to load with an error that names the file, whether read
/// alone, first in a stack (header read) or later in a stack (decode).
#[test]
fn corrupt_png_error_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("garbage_file.png");
    // Deterministic pseudo-random bytes.
    let mut x = 0x2545_f491_4f6c_dd1du64;
    let bytes: Vec<u8> = (0..512)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 32) as u8
        })
        .collect();
    std::fs::write(&bad, bytes).unwrap();
    let good = dir.path().join("good.png");
    write_png16(&good, 2, 2, 1, &[1, 2, 3, 4]).unwrap();
    let name = bad.display().to_string();

    let err = read_image(&bad).unwrap_err();
    assert!(err.to_string().contains(&name), "{err}");
    assert!(
        matches!(err, Error::Decode { ref path, .. } if *path == bad),
        "{err:?}"
    );

    for paths in [
        vec![bad.clone(), good.clone(), good.clone()],
        vec![good.clone(), bad.clone(), good.clone()],
    ] {
        let err =
            load_stack(&paths, &unit_lights(3), &LoadOptions::default(), &Silent).unwrap_err();
        assert!(err.to_string().contains(&name), "{err}");
    }
    assert!(read_mask(&bad).unwrap_err().to_string().contains(&name));
}

/// Found by the fuzz targets: an EXR whose header declares 8×822 083 578 pixels made the decoder
/// allocate 26 GB, a PNG header declaring 2 097 160 columns likewise. Headers are checked first.
#[test]
fn exr_header_declaring_a_huge_image_is_refused() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/huge_header.exr");
    match read_image(&path) {
        Err(Error::UnsupportedImage { path: p, reason }) => {
            assert_eq!(p, path);
            assert!(reason.contains("8x822083578"), "{reason}");
        }
        other => panic!("expected a size refusal, got {:?}", other.map(|i| i.width)),
    }
    // The stack loader meets the same check.
    let paths = vec![path.clone(); 3];
    assert!(load_stack(&paths, &unit_lights(3), &LoadOptions::default(), &Silent).is_err());
    // Likewise a PNG header (from the `diligent_folder` target, read as a mask).
    let png = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/huge_header.png");
    for result in [read_image(&png).map(|_| ()), read_mask(&png).map(|_| ())] {
        match result {
            Err(Error::UnsupportedImage { path: p, reason }) => {
                assert_eq!(p, png);
                assert!(reason.contains("the header declares"), "{reason}");
            }
            other => panic!("expected a size refusal, got {other:?}"),
        }
    }
}

/// A 16-bit RGB PNG of 4000×3000 (72 MB decoded, above the png crate's default 64 MiB limit)
/// loads: camera captures are that large.
#[test]
fn png16_above_64_mib_decoded_loads() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (4000u32, 3000u32);
    let path = dir.path().join("big.png");
    let codes: Vec<u16> = (0..(w * h * 3) as usize)
        .map(|i| (i % 7) as u16 * 9000)
        .collect();
    save(rgb16(w, h, &codes), &path);
    let img = read_image(&path).unwrap();
    assert_eq!((img.width, img.height, img.channels), (4000, 3000, 3));
    // Pixel 7, green: sample 22, code (22 mod 7)·9000 = 9000.
    assert_eq!(img.data[7 * 3 + 1], u16_to_unit(&[9000])[0]);
}

/// A PNG cut short after its header fails with an error naming the file.
#[test]
fn truncated_png_error_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let full = dir.path().join("full.png");
    let codes: Vec<u16> = (0..64 * 64).map(|i| (i * 7919 % 65536) as u16).collect();
    write_png16(&full, 64, 64, 1, &codes).unwrap();
    let bytes = std::fs::read(&full).unwrap();
    let cut = dir.path().join("cut_short.png");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let err = load_stack(
        &[full.clone(), cut.clone(), full],
        &unit_lights(3),
        &LoadOptions::default(),
        &Silent,
    )
    .unwrap_err();
    assert!(err.to_string().contains("cut_short.png"), "{err}");
    assert!(
        read_image(&cut)
            .unwrap_err()
            .to_string()
            .contains("cut_short.png")
    );
}

/// A missing file gives `Error::Io` carrying its path, from every entry point.
#[test]
fn missing_file_is_io_error_with_path() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.png");
    write_png16(&good, 2, 2, 1, &[1, 2, 3, 4]).unwrap();
    for missing in [
        dir.path().join("nope.png"),
        dir.path().join("nope.tif"),
        dir.path().join("nope.exr"),
    ] {
        let is_io_for = |e: &Error| matches!(e, Error::Io { path, .. } if *path == missing);
        let e = read_image(&missing).unwrap_err();
        assert!(is_io_for(&e), "read_image: {e:?}");
        assert!(e.to_string().contains(&missing.display().to_string()));
        let e = image_size(&missing).unwrap_err();
        assert!(is_io_for(&e), "image_size: {e:?}");
        let e = read_mask(&missing).unwrap_err();
        assert!(is_io_for(&e), "read_mask: {e:?}");
        for paths in [
            vec![missing.clone(), good.clone(), good.clone()],
            vec![good.clone(), good.clone(), missing.clone()],
        ] {
            let e =
                load_stack(&paths, &unit_lights(3), &LoadOptions::default(), &Silent).unwrap_err();
            assert!(is_io_for(&e), "load_stack {paths:?}: {e:?}");
        }
    }
}

/// A per-channel load meeting a grey image fails with `UnsupportedImage` naming file and index;
/// a grey load of grey and RGB files mixed fails with `BadImage`.
#[test]
fn per_channel_load_of_grey_image_fails() {
    let dir = tempfile::tempdir().unwrap();
    let rgb = dir.path().join("colour.png");
    save(rgb16(2, 2, &[1000; 12]), &rgb);
    let grey = dir.path().join("grey_only.png");
    write_png16(&grey, 2, 2, 1, &[1000; 4]).unwrap();
    let y = dir.path().join("grey_only.exr");
    write_exr_channels(&y, 2, 2, vec![("Y", FlatSamples::F32(vec![0.5; 4]))]);
    let o = opts(ColorMode::PerChannel, Transfer::Auto);
    for bad in [&grey, &y] {
        let paths = vec![rgb.clone(), bad.clone(), rgb.clone()];
        let err = load_stack(&paths, &unit_lights(3), &o, &Silent).unwrap_err();
        let msg = err.to_string();
        assert!(
            matches!(err, Error::UnsupportedImage { ref path, .. } if path == bad),
            "{err:?}"
        );
        assert!(msg.contains("image 1"), "{msg}");
    }
    // Grey mode refuses them too: a grey file and the grey mix of an RGB file are different
    // measurements. The first image whose channels differ from image 0's is named.
    for bad in [&grey, &y] {
        let paths = vec![rgb.clone(), rgb.clone(), bad.clone()];
        match load_stack(&paths, &unit_lights(3), &LoadOptions::default(), &Silent) {
            Err(Error::BadImage {
                path,
                index,
                reason,
            }) => {
                assert_eq!((&path, index), (bad, 2));
                assert!(reason.contains("1 colour channel(s)"), "{reason}");
                assert!(reason.contains("has 3"), "{reason}");
            }
            other => panic!(
                "expected a channel mismatch, got {:?}",
                other.map(|s| s.count())
            ),
        }
    }
}

/// An all-zero mask is rejected with `Error::Mask` naming the file.
#[test]
fn empty_mask_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("empty_mask.png");
    write_png8(&p, 3, 2, 1, &[0; 6]).unwrap();
    let err = read_mask(&p).unwrap_err();
    assert!(
        matches!(err, Error::Mask { ref path, .. } if *path == p),
        "{err:?}"
    );
    assert!(err.to_string().contains("empty_mask.png"));
    // All-zero RGB with full alpha is still empty: alpha is not a mask channel.
    let q = dir.path().join("empty_rgba.png");
    save(rgba8(2, 1, &[0, 0, 0, 255, 0, 0, 0, 255]), &q);
    assert!(matches!(read_mask(&q), Err(Error::Mask { .. })));
}

/// Image and light counts must agree (`LightsMismatch`); no images at all is `TooFewImages`.
#[test]
fn image_and_light_counts_must_match() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.png");
    write_png16(&p, 2, 2, 1, &[1, 2, 3, 4]).unwrap();
    let paths = vec![p.clone(), p.clone(), p];
    let err = load_stack(&paths, &unit_lights(4), &LoadOptions::default(), &Silent).unwrap_err();
    assert!(matches!(err, Error::LightsMismatch { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains('3') && msg.contains('4'), "{msg}");
    let err = load_stack(
        &paths[..2],
        &unit_lights(3),
        &LoadOptions::default(),
        &Silent,
    )
    .unwrap_err();
    assert!(matches!(err, Error::LightsMismatch { .. }), "{err:?}");
    let none = Lights::from_directions(&[]).unwrap();
    let err = load_stack(&[], &none, &LoadOptions::default(), &Silent).unwrap_err();
    assert!(matches!(err, Error::TooFewImages { count: 0 }), "{err:?}");
}

// ---------------------------------------------------------------------------------------------
// 7. Masks and sizes
// ---------------------------------------------------------------------------------------------

/// `read_mask`: a pixel is set when any colour channel is > 0 (even code 1 in one channel).
#[test]
fn mask_any_channel_counts() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("mask_rgb.png");
    #[rustfmt::skip]
    let rgb: [u8; 18] = [
        0, 0, 0,    1, 0, 0,    0, 1, 0,
        0, 0, 1,    255, 255, 255,    0, 0, 0,
    ];
    write_png8(&p, 3, 2, 3, &rgb).unwrap();
    let mask = read_mask(&p).unwrap();
    assert_eq!((mask.width(), mask.height()), (3, 2));
    assert_eq!(mask.data(), &[false, true, true, true, true, false]);
    assert_eq!(mask.count(), 4);
    assert!(*mask.at(1, 0) && !*mask.at(2, 1));
}

/// `read_mask` of a 16-bit PNG sees code 1 (which 8-bit truncation would turn into 0).
#[test]
fn mask_from_16_bit_png_keeps_low_codes() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("mask16.png");
    write_png16(&p, 4, 1, 1, &[0, 1, 255, 65535]).unwrap();
    let mask = read_mask(&p).unwrap();
    assert_eq!(mask.data(), &[false, true, true, true]);
    // A TIFF works the same way.
    let t = dir.path().join("mask16.tif");
    save(luma16(4, 1, &[0, 1, 255, 65535]), &t);
    assert_eq!(read_mask(&t).unwrap().data(), &[false, true, true, true]);
}

/// An EXR mask: only values > 0 count (negatives, zero and NaN do not).
#[test]
fn mask_from_exr() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("mask.exr");
    write_exr_channels(
        &p,
        5,
        1,
        vec![("Y", FlatSamples::F32(vec![0.0, 1e-20, -1.0, f32::NAN, 1.0]))],
    );
    assert_eq!(
        read_mask(&p).unwrap().data(),
        &[false, true, false, false, true]
    );
}

/// `image_size` reads width and height of PNG, TIFF and EXR files (non-square, so not swapped).
#[test]
fn image_size_of_each_format() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("s.png");
    let tif = dir.path().join("s.tif");
    let exr = dir.path().join("s.exr");
    write_png16(&png, 7, 3, 1, &[5; 21]).unwrap();
    save(rgb8(7, 3, &[5; 63]), &tif);
    write_exr(&exr, 7, 3, &[("Y", &[0.5; 21])], &[]).unwrap();
    for p in [&png, &tif, &exr] {
        assert_eq!(image_size(p).unwrap(), (7, 3), "{}", p.display());
        let img = read_image(p).unwrap();
        assert_eq!((img.width, img.height), (7, 3));
        assert_eq!(img.data.len(), 21 * img.channels);
    }
    // A stack mixing the three formats (all grey) loads, with each image's format recorded.
    let grey_tif = dir.path().join("g.tif");
    save(luma8(7, 3, &[5; 21]), &grey_tif);
    let stack = load(&[png, grey_tif, exr], LoadOptions::default());
    let formats: Vec<SampleFormat> = stack.info().iter().map(|i| i.format).collect();
    assert_eq!(
        formats,
        vec![SampleFormat::U16, SampleFormat::U8, SampleFormat::F32]
    );
    assert_eq!((stack.width(), stack.height()), (7, 3));
}

/// Loading only a window (as a capture does for its mask's bounding box) stores just that
/// window, bit-identical to the same pixels of a full load, for 16-bit RGB PNG (decoded only up
/// to the window's last row) and float EXR; saturation flags keep whole-image pixel indices and
/// counts come from the window only. Through [`photostereo::capture::dataset::Capture`] the window is the
/// mask's bounding box, and a mask reaching outside it is refused.
#[test]
fn window_stores_only_those_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (7u32, 9u32);
    let n = (w * h) as usize;
    let codes = |k: u32| -> Vec<u16> {
        (0..3 * n as u32)
            .map(|i| ((i * 2731 + 997 * k + 40001) % 65536) as u16)
            .collect()
    };
    let mut pngs = Vec::new();
    let mut exrs = Vec::new();
    for k in 0..3u32 {
        let mut c = codes(k);
        // One saturated pixel inside the window below, one outside it.
        c[3 * (3 * w as usize + 2)] = 65535;
        c[3 * (7 * w as usize + 6) + 1] = 65535;
        let png = dir.path().join(format!("img_{k}.png"));
        save(rgb16(w, h, &c), &png);
        pngs.push(png);
        let unit = u16_to_unit(&c);
        let exr = dir.path().join(format!("img_{k}.exr"));
        let planes: Vec<Vec<f32>> = (0..3).map(|ch| channel(&unit, 3, ch)).collect();
        write_exr(
            &exr,
            w as usize,
            h as usize,
            &[("R", &planes[0]), ("G", &planes[1]), ("B", &planes[2])],
            &[],
        )
        .unwrap();
        exrs.push(exr);
    }
    let window = Window {
        x0: 1,
        y0: 2,
        x1: 5,
        y1: 6,
    };
    for (paths, saturation) in [(&pngs, None), (&exrs, Some(1.0))] {
        for color in [ColorMode::Grey, ColorMode::PerChannel] {
            let base = LoadOptions {
                saturation,
                ..opts(color, Transfer::Auto)
            };
            let full = load(paths, base);
            let part = load(
                paths,
                LoadOptions {
                    window: Some(window),
                    ..base
                },
            );
            assert_eq!(part.window(), window);
            for k in 0..3 {
                for ch in 0..full.channels() {
                    let b = part.plane(k, ch);
                    assert_eq!(b.len(), window.len());
                    for p in 0..n {
                        let (x, y) = (p % w as usize, p / w as usize);
                        let a = full.plane(k, ch)[p];
                        match part.local(p) {
                            Some(i) => {
                                assert!(window.contains(x, y));
                                assert_eq!(a.to_bits(), b[i].to_bits(), "{paths:?} pixel {p}");
                                assert_eq!(part.value(k, ch, p).to_bits(), a.to_bits());
                            }
                            None => {
                                assert!(!window.contains(x, y), "pixel {p} in the window");
                                assert!(part.value(k, ch, p).is_nan());
                            }
                        }
                    }
                }
                let inside = 3 * w as usize + 2;
                let outside = 7 * w as usize + 6;
                assert!(full.is_saturated(k, inside) && full.is_saturated(k, outside));
                assert!(part.is_saturated(k, inside), "{paths:?} image {k}");
                assert!(!part.is_saturated(k, outside), "{paths:?} image {k}");
                assert_eq!(part.info()[k].saturated, 1);
                assert_eq!(part.info()[k].non_finite, 0);
            }
        }
    }
    // A window outside the images is refused, naming the parameter.
    let outside = LoadOptions {
        window: Some(Window {
            x0: 8,
            y0: 0,
            x1: 12,
            y1: 4,
        }),
        ..LoadOptions::default()
    };
    match load_stack(&pngs, &unit_lights(3), &outside, &Silent) {
        Err(Error::InvalidParameter { name, reason }) => {
            assert_eq!(name, "window");
            assert!(reason.contains("no pixel"), "{reason}");
        }
        other => panic!(
            "expected a window error, got {:?}",
            other.map(|s| s.window())
        ),
    }
    // A capture stores its mask's bounding box (columns 2..=4 of rows 3..=5 here).
    let mask: Vec<u8> = (0..n)
        .map(|i| {
            let (x, y) = (i % w as usize, i / w as usize);
            if (3..6).contains(&y) && (2..5).contains(&x) && (x + y) % 2 == 0 {
                255
            } else {
                0
            }
        })
        .collect();
    let mask_path = dir.path().join("mask.png");
    save(luma8(w, h, &mask), &mask_path);
    let lights_path = dir.path().join("lights.txt");
    std::fs::write(&lights_path, "0 0 1\n1 0 1\n0 1 1\n").unwrap();
    let capture = photostereo::capture::dataset::Capture::from_files(
        &pngs,
        &lights_path,
        Some(&mask_path),
        &LoadOptions::default(),
        &Silent,
    )
    .unwrap();
    let boxed = Window {
        x0: 2,
        y0: 3,
        x1: 5,
        y1: 6,
    };
    assert_eq!(capture.stack.window(), boxed);
    assert_eq!(capture.mask.bounding_box(), Some(boxed));
    let full = load(&pngs, LoadOptions::default());
    for p in 0..n {
        let v = capture.stack.value(1, 0, p);
        if capture.stack.local(p).is_some() {
            assert_eq!(v.to_bits(), full.plane(1, 0)[p].to_bits(), "pixel {p}");
        } else {
            assert!(v.is_nan(), "pixel {p}");
        }
    }
    // A mask reaching pixels that were not stored is refused, naming the file; the solver
    // refuses such a mask too rather than reading outside the window.
    let wide = vec![255u8; n];
    let wide_path = dir.path().join("wide.png");
    save(luma8(w, h, &wide), &wide_path);
    match capture.clone().with_mask_file(&wide_path) {
        Err(Error::Mask { path, reason }) => {
            assert_eq!(path, wide_path);
            assert!(reason.contains("columns 0..7, rows 0..9"), "{reason}");
            assert!(reason.contains("columns 2..5, rows 3..6"), "{reason}");
        }
        other => panic!(
            "expected a mask error, got {:?}",
            other.map(|c| c.mask.count())
        ),
    }
    let everything = photostereo::grid::Grid::new(w as usize, h as usize, true);
    let solved = photostereo::ps::solve::solve(
        &capture.stack,
        0,
        &capture.lights,
        &everything,
        &photostereo::ps::solve::SolveOptions::default(),
        &Silent,
    );
    match solved {
        Err(Error::InvalidParameter { name, reason }) => {
            assert_eq!(name, "mask");
            assert!(reason.contains("LoadOptions::window"), "{reason}");
        }
        other => panic!("expected a mask error, got {:?}", other.is_ok()),
    }
}

/// JPEG, as phones and cameras write it: 8-bit sRGB, lossy. A rendered sphere written as 8-bit
/// sRGB PNG and as JPEG (quality 95) reads back within JPEG's error of the PNG, is linearised,
/// gives normals within 3° of the truth (the PNG's error plus what the compression adds), and
/// the run says the inputs are lossy.
#[test]
fn jpeg_is_read_linearised_and_reported_lossy() {
    use photostereo::capture::dataset::CaptureFiles;
    use photostereo::eval::metrics::angular_errors;
    use photostereo::run::{Config, Warning, reconstruct};
    use photostereo::synth::write::{ImageFormat, write_synthetic};
    let dir = tempfile::tempdir().unwrap();
    let (synth, lights) = common::sphere_synth();
    write_synthetic(
        &synth.rendering,
        &lights,
        dir.path(),
        ImageFormat::Png8 { srgb: true },
    )
    .unwrap();
    // A plain list of directions, so the JPEG files pair by position.
    let list = dir.path().join("lights.txt");
    common::write_plain_lights(&list, &lights);
    let png: Vec<PathBuf> = (0..10)
        .map(|k| dir.path().join(format!("img_{k:03}.png")))
        .collect();
    let jpg: Vec<PathBuf> = png.iter().map(|p| p.with_extension("jpg")).collect();
    for (p, j) in png.iter().zip(&jpg) {
        let img = image::open(p).unwrap().to_luma8();
        let mut bytes = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 95)
            .encode_image(&img)
            .unwrap();
        std::fs::write(j, bytes).unwrap();
    }
    let a = read_image(&png[0]).unwrap();
    let b = read_image(&jpg[0]).unwrap();
    assert_eq!(
        (b.width, b.height, b.channels, b.format),
        (96, 96, 1, SampleFormat::U8)
    );
    let diff = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| (x - y).abs())
        .sum::<f32>()
        / a.data.len() as f32;
    assert!(
        diff < 0.01,
        "JPEG differs from the PNG by {diff} on average"
    );

    let mask = dir.path().join("mask.png");
    let mut errors = Vec::new();
    for files in [&png, &jpg] {
        let capture = CaptureFiles::from_files(files, &list, Some(&mask))
            .unwrap()
            .load(&LoadOptions::default(), &Silent)
            .unwrap();
        assert!(capture.stack.info().iter().all(|i| i.linearised));
        let config = Config {
            integration: None,
            ..Config::default()
        };
        let recon = reconstruct(&capture, &config, &Silent).unwrap();
        let e = angular_errors(&recon.maps.normals, &synth.truth.normals, &capture.mask).unwrap();
        let lossy = recon
            .warnings
            .iter()
            .any(|w| matches!(w, Warning::Lossy { images: 10 }));
        errors.push((e.mean_deg, lossy));
    }
    let (png_err, png_lossy) = errors[0];
    let (jpg_err, jpg_lossy) = errors[1];
    assert!(!png_lossy && jpg_lossy, "{errors:?}");
    assert!(jpg_err < 3.0 && png_err < 3.0, "{errors:?}");
}

/// Formats that are not read are refused with the list of those that are.
#[test]
fn unread_formats_list_the_read_ones() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("frame.bmp");
    image::GrayImage::from_pixel(8, 8, image::Luma([90]))
        .save(dir.path().join("frame.png"))
        .unwrap();
    std::fs::write(&path, b"BM not really a bitmap").unwrap();
    let e = read_image(&path).unwrap_err().to_string();
    assert!(
        e.contains("frame.bmp") && e.contains("JPEG") && e.contains("TIFF"),
        "{e}"
    );
}
