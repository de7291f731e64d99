//! The scratch folder the fuzz targets write their inputs to (one per process).

/// This process's scratch folder, created if missing.
pub fn scratch() -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("photostereo-fuzz-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    dir
}
