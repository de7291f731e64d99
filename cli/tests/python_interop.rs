//! Notebook users read our EXR files with Python's `OpenEXR` and `numpy`: check that they can,
//! with the documented channel names, sizes and NaN masks (`.ci/run` installs the packages;
//! the test skips with a message where they are missing).

#[path = "../../tests/common/mod.rs"]
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
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../tests/python/read_outputs.py"
    );
    let r = Command::new("python3")
        .arg(script)
        .arg(&out)
        .output()
        .unwrap();
    println!("{}", String::from_utf8_lossy(&r.stdout));
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    // The `integrate` command's depth map (bilateral: Z, residual and the weights wu, wv).
    let depth = tmp.path().join("bilateral.exr");
    let o = Command::new(common::bin())
        .args(["integrate", "-q", "--method", "bilateral", "--normals"])
        .arg(out.join("normal.exr"))
        .arg("-o")
        .arg(&depth)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let check = r#"
import sys, numpy as np, OpenEXR
with OpenEXR.File(sys.argv[1]) as f:
    ch = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
with OpenEXR.File(sys.argv[2]) as f:
    n = np.asarray(f.channels()["RGB"].pixels)
assert sorted(ch) == ["Z", "residual", "wu", "wv"], sorted(ch)
assert all(v.shape == n.shape[:2] and v.dtype == np.float32 for v in ch.values())
valid = np.isfinite(n).all(axis=2)
assert (np.isfinite(ch["Z"]) == valid).all(), "depth NaN mask differs from the normals'"
w = ch["wu"][np.isfinite(ch["wu"])]
assert ((w >= 0) & (w <= 1)).all(), "bilateral weights outside [0, 1]"
print("integrate output:", sorted(ch), ch["Z"].shape)
"#;
    let r = Command::new("python3")
        .args(["-c", check])
        .arg(&depth)
        .arg(out.join("normal.exr"))
        .output()
        .unwrap();
    println!("{}", String::from_utf8_lossy(&r.stdout));
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
}
