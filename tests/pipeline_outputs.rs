//! `reconstruct_and_write` (integration overlapped with writing) against `reconstruct` followed
//! by `write_outputs`: the same files with the same contents, and nothing left behind when a
//! stage fails.

use photostereo::eval::demo::default_capture;
use photostereo::io::decode::read_exr_channel;
use photostereo::progress::Silent;
use photostereo::run::pipeline::{
    Config, OUTPUT_FILES, reconstruct, reconstruct_and_write, write_outputs,
};
use std::path::Path;

/// The names in `dir`, sorted; none when it does not exist.
fn listing(dir: &Path) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut names: Vec<String> = entries
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// The report without its timings, which differ between runs.
fn report_without_timings(dir: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join("report.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v.as_object_mut().unwrap().remove("timings_s");
    v
}

/// Bit patterns, so that NaN outside the mask compares equal.
fn bits(dir: &Path, file: &str, channel: &str) -> Vec<u32> {
    read_exr_channel(&dir.join(file), channel)
        .unwrap()
        .data()
        .iter()
        .map(|v| v.to_bits())
        .collect()
}

#[test]
fn overlapped_run_writes_what_the_sequential_one_writes() {
    let synth = default_capture(0.01, 3).unwrap();
    let config = Config::default();
    let tmp = tempfile::tempdir().unwrap();
    let (seq, ovl) = (tmp.path().join("sequential"), tmp.path().join("overlapped"));

    let mut recon = reconstruct(&synth.capture, &config, &Silent).unwrap();
    write_outputs(&mut recon, &synth.capture, &config, &seq, None).unwrap();
    let mut saw_depth = false;
    let (overlapped, report) =
        reconstruct_and_write(&synth.capture, &config, &ovl, 0.0, &Silent, |r| {
            saw_depth = r.depth().is_some();
            Ok(Some(serde_json::json!({ "checked": true })))
        })
        .unwrap();
    assert!(saw_depth, "evaluate must see the integrated depth");
    assert_eq!(
        report.evaluation,
        Some(serde_json::json!({ "checked": true }))
    );

    // The outputs, the page made from them, and the set's list of its files.
    let mut expected: Vec<String> = OUTPUT_FILES.iter().map(|s| s.to_string()).collect();
    expected.extend([
        "report.html".to_string(),
        photostereo::io::output::MANIFEST.to_string(),
    ]);
    expected.sort();
    assert_eq!(listing(&seq), expected);
    assert_eq!(listing(&ovl), expected);
    for (file, channel) in [
        ("normal.exr", "R"),
        ("normal.exr", "B"),
        ("albedo.exr", "Y"),
        ("depth.exr", "Z"),
        ("depth.exr", "residual"),
        ("residual.exr", "residual"),
        ("residual.exr", "robust"),
        ("curl.exr", "curl"),
    ] {
        assert!(
            bits(&seq, file, channel) == bits(&ovl, file, channel),
            "{file} {channel} differs"
        );
    }
    for png in ["mask.png", "normal.png", "albedo.png", "depth.png"] {
        assert_eq!(
            std::fs::read(seq.join(png)).unwrap(),
            std::fs::read(ovl.join(png)).unwrap(),
            "{png} differs"
        );
    }
    let mut seq_report = report_without_timings(&seq);
    seq_report.as_object_mut().unwrap().remove("evaluation");
    let mut ovl_report = report_without_timings(&ovl);
    ovl_report.as_object_mut().unwrap().remove("evaluation");
    assert_eq!(seq_report, ovl_report);
    assert!(overlapped.timings.integrate > 0.0 && overlapped.timings.write > 0.0);
}

#[test]
fn a_failure_after_writing_started_leaves_no_file() {
    let synth = default_capture(0.0, 1).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let result = reconstruct_and_write(
        &synth.capture,
        &Config::default(),
        &out,
        0.0,
        &Silent,
        |_| {
            Err(photostereo::Error::param(
                "evaluation",
                "fails on purpose after the maps were staged",
            ))
        },
    );
    let err = result.expect_err("the evaluation error is returned");
    assert!(err.to_string().contains("evaluation"), "{err}");
    // Neither the folder nor anything beside it (a staging folder, the lock) is left.
    assert!(!out.exists(), "left behind: {:?}", listing(&out));
    assert!(
        listing(tmp.path()).is_empty(),
        "left beside: {:?}",
        listing(tmp.path())
    );
}
