//! Progress reporting for long stages, decoupled from any terminal library.

/// Receives progress of long-running stages (loading, solving, integrating).
///
/// The library calls [`Progress::begin`] once per stage, [`Progress::advance`] as work
/// completes (possibly from several threads), and [`Progress::end`] when the stage is done.
/// Any of them may come from a thread other than the caller's (integration runs on a thread of
/// rayon's pool). All methods default to doing nothing.
pub trait Progress: Sync {
    /// A stage named `stage` starts with `total` units of work.
    fn begin(&self, _stage: &str, _total: u64) {}
    /// `units` more units of the current stage are done.
    fn advance(&self, _units: u64) {}
    /// The current stage is finished.
    fn end(&self) {}
}

/// A [`Progress`] that reports nothing.
#[derive(Debug, Default, Clone, Copy)]
pub struct Silent;

impl Progress for Silent {}
