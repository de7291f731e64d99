//! Reliability against hostile and careless input (issue "Reliability: forged headers, output
//! sets that are all-or-nothing, and inputs that make no physical sense"): forged image headers
//! and devices are refused at once and in little memory; the output folder holds the old set
//! or the new one, never a mix, whatever runs beside it or kills it; nothing outside the output
//! folder changes; lights behind the surface, thread counts, checksums, escape sequences and
//! the other small cases. `cargo test --release --test reliability -- --nocapture` prints the
//! messages quoted in docs/inputs-and-outputs.md.

#![cfg(target_os = "linux")]

#[path = "../../tests/common/mod.rs"]
mod common;

use common::{
    Measured, bin, listing, main_args, measured, os, sphere_dataset, sphere_synth,
    write_plain_lights,
};
use photostereo::synth::write::ImageFormat;
use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn args_of(v: &[OsString]) -> Vec<&OsStr> {
    v.iter().map(|a| a.as_os_str()).collect()
}

/// CRC-32 (ISO 3309, as PNG uses), bit by bit.
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &b in bytes {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn png_chunk(out: &mut Vec<u8>, kind: &[u8], data: &[u8]) {
    out.extend((data.len() as u32).to_be_bytes());
    let mut body = kind.to_vec();
    body.extend(data);
    out.extend(&body);
    out.extend(crc32(&body).to_be_bytes());
}

/// A valid-looking 8-bit grey PNG whose header declares `w`×`h` and whose pixel data is a
/// stored zlib block of 10 zero bytes.
fn forged_png(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 0, 0, 0, 0]);
    png_chunk(&mut out, b"IHDR", &ihdr);
    // zlib: header, one final stored block of 10 zeros, Adler-32 of them (a = 1, b = 10).
    let mut z = vec![0x78, 0x01, 0x01, 10, 0, !10u8, 0xff];
    z.extend([0u8; 10]);
    z.extend(0x000a_0001u32.to_be_bytes());
    png_chunk(&mut out, b"IDAT", &z);
    png_chunk(&mut out, b"IEND", &[]);
    out
}

/// A baseline grey 8-bit TIFF whose header declares `w`×`h` and holds 4 bytes of pixels.
fn forged_tiff(w: u32, h: u32) -> Vec<u8> {
    let entries: [(u16, u16, u32); 9] = [
        (256, 4, w),
        (257, 4, h),
        (258, 3, 8),
        (259, 3, 1),
        (262, 3, 1),
        (273, 4, 8 + 2 + 12 * 9 + 4),
        (277, 3, 1),
        (278, 4, h),
        (279, 4, 4),
    ];
    let mut out = b"II*\x00".to_vec();
    out.extend(8u32.to_le_bytes());
    out.extend((entries.len() as u16).to_le_bytes());
    for (tag, kind, value) in entries {
        out.extend(tag.to_le_bytes());
        out.extend(kind.to_le_bytes());
        out.extend(1u32.to_le_bytes());
        out.extend(value.to_le_bytes());
    }
    out.extend(0u32.to_le_bytes());
    out.extend([0u8; 4]);
    out
}

/// A real 8×8 EXR whose `dataWindow` is rewritten to declare `w`×`h` (what one flipped byte of
/// its maximum does).
fn forged_exr(dir: &Path, w: i32, h: i32) -> Vec<u8> {
    let path = dir.join("real.exr");
    photostereo::io::output::write_exr(&path, 8, 8, &[("Y", &[0.5f32; 64])], &[]).unwrap();
    let mut bytes = std::fs::read(&path).unwrap();
    let key = b"dataWindow\0box2i\0";
    let at = bytes
        .windows(key.len())
        .position(|w| w == key)
        .expect("dataWindow attribute")
        + key.len()
        + 4;
    bytes[at + 8..at + 12].copy_from_slice(&(w - 1).to_le_bytes());
    bytes[at + 12..at + 16].copy_from_slice(&(h - 1).to_le_bytes());
    bytes
}

/// Three copies of a forged image and a plain lights file for them, in `dir`.
fn forged_stack(dir: &Path, ext: &str, bytes: &[u8]) -> (Vec<PathBuf>, PathBuf) {
    std::fs::create_dir_all(dir).unwrap();
    let images: Vec<PathBuf> = (0..3)
        .map(|k| {
            let p = dir.join(format!("img{k}.{ext}"));
            std::fs::write(&p, bytes).unwrap();
            p
        })
        .collect();
    let lights = dir.join("lights.txt");
    std::fs::write(&lights, "0 0 1\n0.5 0 0.866\n0 0.5 0.866\n").unwrap();
    (images, lights)
}

/// Item 1: headers that declare 100000² or 300000² pixels (or 3000² in a file of 70 bytes),
/// as PNG, TIFF and EXR, loaded whole or streamed within `--max-memory 1G`, as images, as a
/// mask and as calibration images: exit 1 within 1 s, under 100 MB, nothing written.
#[test]
fn forged_headers_are_refused_at_once_in_little_memory() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let good = tmp.path().join("good");
    let good_images = sphere_dataset(&good, ImageFormat::Exr);
    let mut worst = (0.0f64, 0.0f64);
    println!("| forged input | message |\n| --- | --- |");
    for (w, h) in [(100_000u32, 100_000u32), (300_000, 300_000), (3000, 3000)] {
        for ext in ["png", "tif", "exr"] {
            let bytes = match ext {
                "png" => forged_png(w, h),
                "tif" => forged_tiff(w, h),
                _ => forged_exr(tmp.path(), w as i32, h as i32),
            };
            let dir = tmp.path().join(format!("{ext}-{w}"));
            let (images, lights) = forged_stack(&dir, ext, &bytes);
            let mask_run = {
                let mut a = main_args(&good_images, &good.join("lights.json"), &[], &out);
                a.extend(["--mask".into(), images[0].clone().into_os_string()]);
                a
            };
            let calibrate = vec![
                OsString::from("calibrate"),
                images[0].clone().into_os_string(),
                images[1].clone().into_os_string(),
                images[2].clone().into_os_string(),
                "-o".into(),
                tmp.path().join("lights-out.json").into_os_string(),
            ];
            for (how, args) in [
                ("whole", main_args(&images, &lights, &[], &out)),
                (
                    "--max-memory 1G",
                    main_args(&images, &lights, &["--max-memory", "1G"], &out),
                ),
                (
                    "--band-rows 16",
                    main_args(&images, &lights, &["--band-rows", "16"], &out),
                ),
                ("as the mask", mask_run),
                ("calibrate", calibrate),
            ] {
                let m = measured(&args_of(&args));
                let what = format!("{w}x{h} {ext}, {how}");
                assert_eq!(m.code, Some(1), "{what}: {}", m.stderr);
                assert!(
                    m.stderr.contains(&format!("{ext}-{w}/img")),
                    "{what}: {}",
                    m.stderr
                );
                assert!(m.secs < 1.0, "{what}: {:.2} s", m.secs);
                assert!(m.peak_mb < 100.0, "{what}: {:.0} MB", m.peak_mb);
                assert!(!out.exists(), "{what}: wrote {:?}", listing(&out));
                worst = (worst.0.max(m.secs), worst.1.max(m.peak_mb));
                if how == "whole" {
                    let shown = m
                        .stderr
                        .trim()
                        .replace(&format!("{}/", tmp.path().display()), "");
                    println!("| {w}×{h} {ext} in {} bytes | `{shown}` |", bytes.len());
                }
            }
        }
    }
    println!(
        "slowest refusal {:.3} s, largest peak {:.1} MB",
        worst.0, worst.1
    );

    // A valid, flat 6000×6000 PNG (36 MB of pixels in a few ten kB) under `--max-memory 100M`:
    // refused on its declared size before the mask or any map is allocated.
    let big = tmp.path().join("big");
    std::fs::create_dir(&big).unwrap();
    let flat = vec![128u8; 6000 * 6000];
    let images: Vec<PathBuf> = (0..3)
        .map(|k| {
            let p = big.join(format!("img{k}.png"));
            photostereo::io::output::write_png8(&p, 6000, 6000, 1, &flat).unwrap();
            p
        })
        .collect();
    drop(flat);
    let (_, lights) = forged_stack(&tmp.path().join("big-lights"), "png", &[]);
    let m = measured(&args_of(&main_args(
        &images,
        &lights,
        &["--max-memory", "100M"],
        &out,
    )));
    assert_eq!(m.code, Some(1), "{}", m.stderr);
    assert!(m.stderr.contains("max-memory"), "{}", m.stderr);
    assert!(
        m.peak_mb < 100.0,
        "{:.0} MB under a 100 MB budget",
        m.peak_mb
    );
    assert!(!out.exists());
    println!(
        "6000×6000 under --max-memory 100M: {:.1} MB peak: `{}`",
        m.peak_mb,
        m.stderr.trim()
    );
}

/// Item 2: a symbolic link to `/dev/zero` named `x.png` (or given as the lights, mask or
/// camera file) is refused before a byte of it is read.
#[test]
fn devices_are_refused_before_they_are_read() {
    let tmp = tempfile::tempdir().unwrap();
    let good = tmp.path().join("good");
    let images = sphere_dataset(&good, ImageFormat::Exr);
    let zero = tmp.path().join("x.png");
    std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
    let out = tmp.path().join("out");
    let mut as_image = images.clone();
    as_image[4] = zero.clone();
    let plain = tmp.path().join("lights.txt");
    write_plain_lights(&plain, &sphere_synth().1);
    let runs = [
        main_args(&as_image, &plain, &[], &out),
        main_args(&images, &zero, &[], &out),
        main_args(
            &images,
            &good.join("lights.json"),
            &["--mask", zero.to_str().unwrap()],
            &out,
        ),
        main_args(
            &images,
            &good.join("lights.json"),
            &["--camera", zero.to_str().unwrap()],
            &out,
        ),
    ];
    for args in &runs {
        let m = measured(&args_of(args));
        assert_eq!(m.code, Some(1), "{}", m.stderr);
        assert!(
            m.stderr.contains("x.png") && m.stderr.contains("character device"),
            "{}",
            m.stderr
        );
        assert!(
            m.secs < 1.0 && m.peak_mb < 100.0,
            "{:.2} s, {:.0} MB",
            m.secs,
            m.peak_mb
        );
        assert!(!out.exists());
    }
}

/// Every file of `dir` named in its manifest, and nothing else (but the manifest).
fn manifest_matches(dir: &Path) -> bool {
    let listed: Vec<String> = std::fs::read_to_string(dir.join(photostereo::io::output::MANIFEST))
        .map(|t| t.lines().map(str::to_string).collect())
        .unwrap_or_default();
    let mut present: Vec<String> = listing(dir)
        .into_iter()
        .filter(|n| n != photostereo::io::output::MANIFEST)
        .collect();
    present.sort();
    let mut l = listed.clone();
    l.sort();
    !listed.is_empty() && present == l
}

/// The normal map of a set, decoded (the EXR header's attribute order varies between runs).
fn normals_of(dir: &Path) -> Option<Vec<f32>> {
    photostereo::io::decode::read_image(&dir.join("normal.exr"))
        .ok()
        .map(|i| i.data)
}

/// Which run the set in `dir` came from, by the estimator its report names and the values of
/// its normal map: `Some(method)` when both agree with that method's reference, else `None`.
fn set_origin(dir: &Path, references: &[(String, Vec<f32>)]) -> Option<String> {
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("report.json")).ok()?).ok()?;
    let method = report["config"]["solve"]["method"].as_str()?.to_string();
    let normals = normals_of(dir)?;
    let same = |a: &[f32], b: &[f32]| {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
    };
    references
        .iter()
        .find(|(m, n)| *m == method && same(n, &normals))
        .map(|(m, _)| m.clone())
}

/// Every entry of `dir` but `skip` and hidden ones, with its bytes, for "nothing else changed".
fn snapshot(dir: &Path, skip: &str) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = listing(dir)
        .into_iter()
        .filter(|n| n != skip && !n.starts_with('.'))
        .map(|n| {
            let bytes = std::fs::read(dir.join(&n)).unwrap_or_default();
            (n, bytes)
        })
        .collect();
    v.sort();
    v
}

/// Item 3: the output set is all or nothing. A folder that is taken in part (an output name
/// held by a folder) is refused before any work; runs into one folder at the same time are
/// refused while one holds its lock; and in 100 runs killed at random moments or run two at
/// a time, the folder holds afterwards one complete set from one run, every time. Nothing
/// outside the folder changes, and what a killed run leaves beside it is removed by the next.
#[test]
fn the_output_set_is_all_or_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let lights = data.join("lights.json");
    let work = tmp.path().join("work");
    std::fs::create_dir(&work).unwrap();
    std::fs::write(work.join("victim.txt"), b"not an output").unwrap();
    // The two runs whose sets can meet in the folder, and their normal maps.
    let methods = ["ls", "auto"];
    let references: Vec<(String, Vec<f32>)> = methods
        .iter()
        .map(|m| {
            let out = tmp.path().join(format!("ref-{m}"));
            let o = measured(&args_of(&main_args(
                &images,
                &lights,
                &["--method", m],
                &out,
            )));
            assert_eq!(o.code, Some(0), "{}", o.stderr);
            let report: serde_json::Value =
                serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
            (
                report["config"]["solve"]["method"]
                    .as_str()
                    .unwrap()
                    .to_string(),
                normals_of(&out).unwrap(),
            )
        })
        .collect();
    assert_ne!(references[0].0, references[1].0);
    assert_eq!(
        set_origin(&tmp.path().join("ref-ls"), &references).as_deref(),
        Some(references[0].0.as_str())
    );
    let out = work.join("out");

    // An output name taken by a folder: refused at the start, with or without --force.
    let o = measured(&args_of(&main_args(&images, &lights, &[], &out)));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    let saved = std::fs::read(out.join("normal.exr")).unwrap();
    std::fs::remove_file(out.join("normal.exr")).unwrap();
    std::fs::create_dir(out.join("normal.exr")).unwrap();
    for extra in [&[][..], &["--force"][..]] {
        let o = measured(&args_of(&main_args(&images, &lights, extra, &out)));
        assert_eq!(o.code, Some(1), "{extra:?}: {}", o.stderr);
        assert!(out.join("normal.exr").is_dir());
        assert!(
            o.secs < 1.0,
            "{extra:?}: refused only after {:.2} s",
            o.secs
        );
    }
    println!(
        "output name taken by a folder: `{}`",
        measured(&args_of(&main_args(&images, &lights, &["--force"], &out)))
            .stderr
            .trim()
            .replace(&format!("{}/", tmp.path().display()), "")
    );
    std::fs::remove_dir(out.join("normal.exr")).unwrap();
    std::fs::write(out.join("normal.exr"), saved).unwrap();

    // A run while another holds the folder: refused at once, naming the other process. (The
    // demo, in a folder of its own, runs long enough to be met.)
    let demo = work.join("demo");
    let demo_args = vec![
        OsString::from("demo"),
        "-q".into(),
        "--force".into(),
        "-o".into(),
        demo.clone().into_os_string(),
    ];
    let mut first = Command::new(bin())
        .args(args_of(&demo_args))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let lock = work.join(".demo.photostereo-lock");
    let waited = Instant::now();
    while !lock.exists() && waited.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(1));
    }
    let busy = measured(&args_of(&demo_args));
    assert!(first.wait().unwrap().success());
    assert_eq!(busy.code, Some(1), "{}", busy.stderr);
    assert!(
        busy.stderr.contains("another run (process"),
        "{}",
        busy.stderr
    );
    println!(
        "a second run into the same folder: `{}`",
        busy.stderr
            .trim()
            .replace(&format!("{}/", tmp.path().display()), "")
    );
    std::fs::remove_dir_all(&demo).unwrap();
    let before = snapshot(&work, "out");

    let mut outcomes = (0usize, 0usize, 0usize); // old set kept, new set, runs refused busy
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    // 50 runs killed at random moments while they replace the previous set.
    for i in 0..50 {
        let before_set = set_origin(&out, &references).expect("a complete set before");
        let method = methods[i % 2];
        let mut child = Command::new(bin())
            .args(args_of(&main_args(
                &images,
                &lights,
                &["--force", "--method", method],
                &out,
            )))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_micros(next() % 400_000));
        let _ = child.kill();
        child.wait().unwrap();
        let after = set_origin(&out, &references);
        assert!(
            after.is_some() && manifest_matches(&out),
            "kill {i}: the folder holds {:?}",
            listing(&out)
        );
        if after.as_deref() == Some(before_set.as_str()) {
            outcomes.0 += 1;
        } else {
            outcomes.1 += 1;
        }
        // Beside the folder: at most what a killed run leaves (hidden, removed by the next).
        for n in listing(&work) {
            assert!(
                n == "out" || n == "victim.txt" || n.starts_with(".out.photostereo-"),
                "kill {i}: {n} beside the output folder"
            );
        }
    }
    // 25 pairs of runs at the same time.
    for i in 0..25 {
        let spawn = |m: &str| {
            Command::new(bin())
                .args(args_of(&main_args(
                    &images,
                    &lights,
                    &["--force", "--method", m],
                    &out,
                )))
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        };
        let (a, b) = (spawn(methods[i % 2]), spawn(methods[(i + 1) % 2]));
        for child in [a, b] {
            let o = child.wait_with_output().unwrap();
            let err = String::from_utf8_lossy(&o.stderr);
            if !o.status.success() {
                assert!(err.contains("another run"), "pair {i}: {err}");
                outcomes.2 += 1;
            }
        }
        assert!(
            set_origin(&out, &references).is_some() && manifest_matches(&out),
            "pair {i}: the folder holds {:?}",
            listing(&out)
        );
    }
    // What killed runs left beside the folder is gone after the next run.
    let o = measured(&args_of(&main_args(&images, &lights, &["--force"], &out)));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert_eq!(listing(&work), vec!["out", "victim.txt"]);
    assert_eq!(
        snapshot(&work, "out"),
        before,
        "a file outside the output folder changed"
    );
    println!(
        "100 runs: {} killed runs left the old set, {} the new one; {} of 50 paired runs were refused as busy; never a mix",
        outcomes.0, outcomes.1, outcomes.2
    );
    assert!(
        outcomes.0 > 0 && outcomes.1 > 0,
        "{outcomes:?}: the kills did not span the run"
    );
}

/// Item 4: no temporary follows a symbolic link: a link planted in a previous set, in place of
/// one of its files, is replaced with the set and its target is untouched; so is a link at the
/// name of a single output file.
#[test]
fn planted_links_are_not_followed() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let lights = data.join("lights.json");
    let out = tmp.path().join("out");
    let victim = tmp.path().join("victim.txt");
    std::fs::write(&victim, b"keep me").unwrap();
    let o = measured(&args_of(&main_args(&images, &lights, &[], &out)));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    for name in ["normal.png", "report.json"] {
        std::fs::remove_file(out.join(name)).unwrap();
        std::os::unix::fs::symlink(&victim, out.join(name)).unwrap();
    }
    let o = measured(&args_of(&main_args(&images, &lights, &["--force"], &out)));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert_eq!(std::fs::read(&victim).unwrap(), b"keep me");
    assert!(!out.join("normal.png").is_symlink());
    // A single output file: `integrate -o` onto a link.
    let depth = tmp.path().join("depth.exr");
    std::os::unix::fs::symlink(&victim, &depth).unwrap();
    let normals = out.join("normal.exr");
    let o = measured(&[
        os("integrate"),
        os("--normals"),
        normals.as_os_str(),
        os("-o"),
        depth.as_os_str(),
        os("--force"),
    ]);
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert_eq!(std::fs::read(&victim).unwrap(), b"keep me");
    assert!(!depth.is_symlink());
    let hidden: Vec<String> = listing(tmp.path())
        .into_iter()
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(hidden.is_empty(), "{hidden:?}");
}

/// Item 5: lights behind the surface. All (or most) of them: refused, naming the first and
/// saying to flip z; a few: a warning naming each, and a result.
#[test]
fn lights_behind_the_surface_are_refused_or_named() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let (_, lights) = sphere_synth();
    let dirs = lights.directions();
    let write = |name: &str, flip: &dyn Fn(usize) -> bool| -> PathBuf {
        let text: String = dirs
            .iter()
            .enumerate()
            .map(|(k, d)| {
                let z = if flip(k) { -d.z } else { d.z };
                format!("{} {} {z}\n", d.x, d.y)
            })
            .collect();
        let p = tmp.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let all = write("all.txt", &|_| true);
    let two = write("two.txt", &|k| k == 2 || k == 7);
    let out = tmp.path().join("out");
    let o = measured(&args_of(&main_args(&images, &all, &[], &out)));
    assert_eq!(o.code, Some(1), "{}", o.stderr);
    for w in ["light 0", "behind", "10 of the 10", "flip the sign of z"] {
        assert!(o.stderr.contains(w), "{w:?} missing from {}", o.stderr);
    }
    println!("all lights behind: `{}`", o.stderr.trim());
    let o = measured(&args_of(&main_args(&images, &two, &[], &out)));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert!(o.stderr.contains("light(s) 2 and 7 of 10"), "{}", o.stderr);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    assert!(
        report["warnings"].to_string().contains("behind"),
        "{}",
        report["warnings"]
    );
    println!(
        "two lights behind: `{}`",
        o.stderr.lines().find(|l| l.contains("behind")).unwrap()
    );
}

/// Item 6: `--threads` is capped at a few threads a core, with a note; the run completes.
#[test]
fn thread_counts_are_capped() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let images = sphere_dataset(&data, ImageFormat::Exr);
    let out = tmp.path().join("out");
    let mut args = main_args(&images, &data.join("lights.json"), &[], &out);
    args.insert(0, "--threads".into());
    args.insert(1, "100000".into());
    let o = measured(&args_of(&args));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert!(o.stderr.contains("capped at"), "{}", o.stderr);
    let cores = std::thread::available_parallelism().unwrap().get();
    assert!(
        o.stderr.contains(&format!("capped at {} ", 4 * cores)),
        "{}",
        o.stderr
    );
    println!(
        "`{}`",
        o.stderr.lines().find(|l| l.contains("capped")).unwrap()
    );
}

/// Item 7, the smaller cases.
#[test]
fn the_smaller_cases_behave() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let data = t.join("data");
    let images = sphere_dataset(&data, ImageFormat::Png16);
    let (_, lights) = sphere_synth();
    let plain = t.join("lights.txt");
    write_plain_lights(&plain, &lights);
    let show = |o: &Measured| o.stderr.trim().replace(&format!("{}/", t.display()), "");

    // A bad checksum in the last pixel-data chunk of one image: refused whole and streamed.
    let mut bad = images.clone();
    let corrupt = t.join("corrupt.png");
    let mut bytes = std::fs::read(&images[3]).unwrap();
    let idat = bytes
        .windows(4)
        .rposition(|w| w == b"IDAT")
        .expect("an IDAT chunk");
    let len = u32::from_be_bytes(bytes[idat - 4..idat].try_into().unwrap()) as usize;
    bytes[idat + 4 + len] ^= 0xff;
    std::fs::write(&corrupt, bytes).unwrap();
    bad[3] = corrupt;
    for extra in [
        &[][..],
        &["--band-rows", "16"][..],
        &["--mask", data.join("mask.png").to_str().unwrap()][..],
    ] {
        let o = measured(&args_of(&main_args(&bad, &plain, extra, &t.join("o1"))));
        assert_eq!(o.code, Some(1), "{extra:?}: {}", o.stderr);
        assert!(
            o.stderr.contains("corrupt.png") && o.stderr.contains("CRC"),
            "{}",
            o.stderr
        );
        assert!(!t.join("o1").exists());
    }
    println!(
        "bad IDAT checksum: `{}`",
        show(&measured(&args_of(&main_args(
            &bad,
            &plain,
            &[],
            &t.join("o1")
        ))))
    );

    // A non-UTF-8 output path works.
    use std::os::unix::ffi::OsStrExt;
    let odd = t.join(OsStr::from_bytes(b"out-\xff"));
    let o = measured(&args_of(&main_args(&images, &plain, &[], &odd)));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert!(odd.join("normal.exr").is_file());

    // The input folder as the output, even with --force: refused, the input mask unchanged.
    let mask = std::fs::read(data.join("mask.png")).unwrap();
    let o = measured(&args_of(&main_args(&images, &plain, &["--force"], &data)));
    assert_eq!(o.code, Some(1), "{}", o.stderr);
    assert!(o.stderr.contains("holds (or is) the input"), "{}", o.stderr);
    assert_eq!(std::fs::read(data.join("mask.png")).unwrap(), mask);
    println!("-o onto the input folder with --force: `{}`", show(&o));

    // Escape sequences in a lights file are shown escaped, not sent to the terminal.
    let esc = t.join("esc.txt");
    std::fs::write(&esc, "0 0 \x1b[31mRED\x1b[0m\n").unwrap();
    let o = measured(&args_of(&main_args(&images, &esc, &[], &t.join("o2"))));
    assert_eq!(o.code, Some(1));
    assert!(!o.stderr.contains('\x1b'), "{:?}", o.stderr);
    assert!(o.stderr.contains("\\u{1b}[31mRED"), "{}", o.stderr);
    println!("escape sequence in a lights file: `{}`", show(&o));

    // An intensity whose reciprocal underflows 32-bit floats is refused as such.
    let huge = t.join("huge.json");
    let entries: Vec<String> = lights
        .directions()
        .iter()
        .enumerate()
        .map(|(k, d)| {
            format!(
                "{{\"direction\": [{}, {}, {}], \"intensity\": {}}}",
                d.x,
                d.y,
                d.z,
                if k == 2 { "1e308" } else { "1" }
            )
        })
        .collect();
    std::fs::write(&huge, format!("{{\"lights\": [{}]}}", entries.join(", "))).unwrap();
    let o = measured(&args_of(&main_args(&images, &huge, &[], &t.join("o3"))));
    assert_eq!(o.code, Some(1), "{}", o.stderr);
    assert!(
        o.stderr.contains("light 2") && o.stderr.contains("outside"),
        "{}",
        o.stderr
    );
    println!("intensity 1e308: `{}`", show(&o));

    // A byte-order mark is read past; an extra row is named as such.
    let bom = t.join("bom.txt");
    let mut text = b"\xef\xbb\xbf".to_vec();
    text.extend(std::fs::read(&plain).unwrap());
    std::fs::write(&bom, text).unwrap();
    let o = measured(&args_of(&main_args(&images, &bom, &[], &t.join("o4"))));
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    let extra = t.join("extra.txt");
    let mut text = std::fs::read_to_string(&plain).unwrap();
    text.push_str("0 0 1\n");
    std::fs::write(&extra, text).unwrap();
    let o = measured(&args_of(&main_args(&images, &extra, &[], &t.join("o5"))));
    assert_eq!(o.code, Some(1));
    assert!(o.stderr.contains("11 lights for 10 images"), "{}", o.stderr);

    // A read-only output folder is refused before the images are loaded (root writes anyway).
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    if !root {
        use std::os::unix::fs::PermissionsExt;
        let ro = t.join("ro");
        std::fs::create_dir(&ro).unwrap();
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
        let o = measured(&args_of(&main_args(&images, &plain, &[], &ro)));
        assert_eq!(o.code, Some(1), "{}", o.stderr);
        assert!(o.stderr.contains("cannot be written"), "{}", o.stderr);
    }
}
