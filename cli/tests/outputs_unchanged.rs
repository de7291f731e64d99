//! The files a run writes, byte for byte: the SHA-256 of every output of the default command on
//! the built-in demo scene and on DiLiGenT cat and bear (in memory and streamed in row bands)
//! against `tests/golden/outputs.json`.
//!
//! A restructuring of the code must leave these digests as they are. A change meant to alter
//! the results (a better estimator, a new default) regenerates them with
//! `REGENERATE=1 cargo test --release --test outputs_unchanged`; the commit then says which
//! files changed and why, with the measured accuracy before and after.
//!
//! `report.json` is compared without its timings and with the input paths reduced to file
//! names (both depend on the machine, not on the results). An EXR file's header attributes are
//! compared in name order: the `exr` crate keeps them in a hash map, so their order in the file
//! changes from run to run while every byte of the pixel data stays the same.

use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

type Digests = BTreeMap<String, BTreeMap<String, String>>;

fn golden_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/golden/outputs.json")
}

fn shared(sub: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(sub);
    p.exists().then_some(p)
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// `report.json` without what depends on the machine: timings, and folders of input paths.
fn canonical_report(bytes: &[u8]) -> Vec<u8> {
    let mut v: serde_json::Value = serde_json::from_slice(bytes).expect("report.json parses");
    let obj = v.as_object_mut().expect("report.json is an object");
    obj.remove("timings_s");
    let name = |p: &serde_json::Value| -> serde_json::Value {
        match p.as_str() {
            Some(s) => Path::new(s)
                .file_name()
                .map(|f| f.to_string_lossy().into_owned())
                .into(),
            None => p.clone(),
        }
    };
    if let Some(inputs) = obj.get_mut("inputs").and_then(|i| i.as_object_mut()) {
        for key in ["lights", "mask"] {
            if let Some(p) = inputs.get(key).map(name) {
                inputs.insert(key.into(), p);
            }
        }
        if let Some(images) = inputs.get_mut("images").and_then(|i| i.as_array_mut()) {
            for p in images.iter_mut() {
                *p = name(p);
            }
        }
    }
    serde_json::to_vec_pretty(&v).expect("report serialises")
}

/// A single-part EXR file with its header attributes sorted by name, every other byte as it was
/// (magic number, version, attribute values, offset table and pixel data).
fn canonical_exr(bytes: &[u8]) -> Vec<u8> {
    fn until_nul(b: &[u8], at: usize) -> usize {
        at + b[at..]
            .iter()
            .position(|c| *c == 0)
            .expect("EXR header string ends")
    }
    let mut attributes: Vec<&[u8]> = Vec::new();
    let mut at = 8;
    loop {
        let name_end = until_nul(bytes, at);
        if name_end == at {
            break;
        }
        let type_end = until_nul(bytes, name_end + 1);
        let size_at = type_end + 1;
        let size = u32::from_le_bytes(bytes[size_at..size_at + 4].try_into().unwrap()) as usize;
        let end = size_at + 4 + size;
        attributes.push(&bytes[at..end]);
        at = end;
    }
    attributes.sort();
    let mut out = bytes[..8].to_vec();
    for a in attributes {
        out.extend_from_slice(a);
    }
    out.extend_from_slice(&bytes[at..]);
    out
}

/// Runs the binary with `args` into a fresh folder; returns the digest of every file written
/// (the demo's rendered scene and its ground truth included), by path inside the folder.
fn digests_of(args: &[&str]) -> BTreeMap<String, String> {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let status = Command::new(env!("CARGO_BIN_EXE_photostereo"))
        .args(args)
        .arg("-o")
        .arg(&out)
        .arg("-q")
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "photostereo {args:?} failed: {}",
        String::from_utf8_lossy(&status.stderr)
    );
    let mut digests = BTreeMap::new();
    let mut folders = vec![out.clone()];
    while let Some(folder) = folders.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                folders.push(path);
                continue;
            }
            let name = path
                .strip_prefix(&out)
                .unwrap()
                .to_string_lossy()
                .into_owned();
            // report.html holds the run's timings; it is made from the files compared here
            // and checked by its own test (report_html.rs).
            if name == "report.html" {
                continue;
            }
            let mut bytes = std::fs::read(&path).unwrap();
            if name == "report.json" {
                bytes = canonical_report(&bytes);
            } else if name.ends_with(".exr") {
                bytes = canonical_exr(&bytes);
            }
            digests.insert(name, hex(&Sha256::digest(&bytes)));
        }
    }
    digests
}

/// The runs compared: name, and the arguments before `-o`.
fn runs() -> Vec<(String, Vec<String>)> {
    let mut runs = vec![
        ("demo".to_string(), vec!["demo".to_string()]),
        (
            "demo mesh".to_string(),
            ["demo", "--mesh"].map(String::from).to_vec(),
        ),
        // Conjugate gradients inside: reproducible since their dot products are summed over a
        // fixed partition (integrate::sparse).
        (
            "demo bilateral".to_string(),
            ["demo", "--integrate", "bilateral"]
                .map(String::from)
                .to_vec(),
        ),
    ];
    for object in ["cat", "bear"] {
        match shared(&format!("diligent/{object}PNG")) {
            Some(dir) => {
                let dir = dir.to_string_lossy().into_owned();
                runs.push((object.to_string(), vec![dir.clone()]));
                if object == "cat" {
                    runs.push((
                        "cat streamed".to_string(),
                        vec![
                            dir,
                            "--max-memory".into(),
                            "300M".into(),
                            "--band-rows".into(),
                            "100".into(),
                        ],
                    ));
                }
            }
            None => eprintln!(
                "SKIPPED: ../shared/data/diligent/{object}PNG is absent; its outputs are not compared"
            ),
        }
    }
    runs
}

#[test]
fn outputs_are_byte_identical_to_the_golden_digests() {
    let regenerate = std::env::var_os("REGENERATE").is_some();
    let golden: Digests = std::fs::read(golden_path())
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default();
    let mut measured = Digests::new();
    let mut differences = Vec::new();
    for (name, args) in runs() {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let digests = digests_of(&args);
        match golden.get(&name) {
            Some(expected) if !regenerate => {
                for (file, digest) in expected {
                    match digests.get(file) {
                        Some(d) if d == digest => {}
                        Some(_) => differences.push(format!("{name}: {file} differs")),
                        None => differences.push(format!("{name}: {file} was not written")),
                    }
                }
                for file in digests.keys().filter(|f| !expected.contains_key(*f)) {
                    differences.push(format!("{name}: {file} is new"));
                }
            }
            None if !regenerate => {
                differences.push(format!("{name}: no golden digests (run with REGENERATE=1)"))
            }
            _ => {}
        }
        measured.insert(name, digests);
    }
    if regenerate {
        let mut all = golden;
        all.extend(measured);
        let text = serde_json::to_string_pretty(&all).unwrap();
        std::fs::write(golden_path(), text + "\n").unwrap();
        eprintln!("regenerated {}", golden_path().display());
        return;
    }
    assert!(
        differences.is_empty(),
        "outputs differ from tests/golden/outputs.json:\n{}",
        differences.join("\n")
    );
}
