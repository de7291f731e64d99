//! Notebook users read our EXR files with Python's `OpenEXR` and `numpy`: check that they can,
//! with the documented channel names, sizes and NaN masks (`.ci/run` installs the packages;
//! the test skips with a message where they are missing).

mod common;

use std::process::Command;

#[test]
fn python_openexr_reads_every_output() {
    let probe = Command::new("python3")
        .args(["-c", "import OpenEXR, numpy"])
        .output();
    if !probe.is_ok_and(|o| o.status.success()) {
        eprintln!(
            "SKIPPED: python3 with OpenEXR and numpy is not available (pip install openexr numpy)"
        );
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let o = Command::new(common::bin())
        .args(["demo", "-q", "-o"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/read_outputs.py");
    let r = Command::new("python3")
        .arg(script)
        .arg(&out)
        .output()
        .unwrap();
    println!("{}", String::from_utf8_lossy(&r.stdout));
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
}
