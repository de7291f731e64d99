//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// `../shared/data` beside the repository, or `None` (the caller prints why it skips).
pub fn shared_data() -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    p.is_dir().then_some(p)
}

/// Skips a test with a clear message when the shared data are absent.
#[macro_export]
macro_rules! require_shared {
    ($sub:expr) => {
        match common::shared_data()
            .map(|d| d.join($sub))
            .filter(|p| p.exists())
        {
            Some(p) => p,
            None => {
                eprintln!(
                    "SKIPPED: ../shared/data/{} is absent; this test needs the shared real data",
                    $sub
                );
                return;
            }
        }
    };
}

/// The photostereo binary built for these tests.
pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_photostereo"))
}
