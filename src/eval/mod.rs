//! Measuring results: error metrics against ground truth ([`metrics`]), the built-in demo scene
//! and its evaluation ([`demo`]), and the experiments behind `docs/bench` — error and time over
//! noise, lights, specularity and integrators ([`sweep`]).

pub mod demo;
pub mod metrics;
pub mod sweep;
