//! Camera intrinsics files (a 3×3 matrix as text) on arbitrary bytes: an error or a
//! valid camera, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "scratch.rs"]
mod scratch;
use scratch::scratch;

fuzz_target!(|data: &[u8]| {
    let dir = scratch();
    let path = dir.join("camera.txt");
    if std::fs::write(&path, data).is_err() {
        return;
    }
    if let Ok(k) = photostereo::camera::Intrinsics::from_file(&path) {
        assert!(k.fx.is_finite() && k.fy.is_finite() && k.fx != 0.0 && k.fy != 0.0);
        let p = k.unproject(1.0, 2.0, 3.0);
        assert!(p.iter().all(|v| v.is_finite()), "{k:?} unprojects to {p:?}");
    }
});
