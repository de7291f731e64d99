//! What `bench all` runs to regenerate `docs/bench` ([`SuitePlan`]), in order: the
//! speed–accuracy sweeps ([`crate::eval::sweep`]), solver scaling ([`super::scaling`]),
//! integrator timing ([`super::integration`]), interreflection compensation on rendered
//! concave scenes ([`super::interreflections`]), near lights ([`crate::eval::near`]), every
//! shape-from-shading method on rendered shapes ([`crate::eval::sfs`]), then on each DiLiGenT
//! object present the
//! stages beside the numpy peer ([`super::stages`]) and every estimator with all lights and
//! light subsets ([`super::diligent`]), and last every integrator on the shared depth data
//! ([`super::real_depth`]). The quick plan is a smoke run of the whole chain, not for
//! publishing.

use super::integration::IntegrationBenchOptions;
use super::interreflections::InterreflectionBenchOptions;
use super::scaling::ScalingOptions;
use crate::eval::sweep::SweepOptions;
use crate::ps::solve::SolveOptions;
use crate::run::pipeline::Config;

/// The settings of every part of `bench all`.
#[derive(Debug, Clone, PartialEq)]
pub struct SuitePlan {
    /// The speed–accuracy sweeps.
    pub sweep: SweepOptions,
    /// Solver scaling.
    pub scaling: ScalingOptions,
    /// Integrator timing.
    pub integration: IntegrationBenchOptions,
    /// Interreflection compensation on rendered concave scenes.
    pub interreflections: InterreflectionBenchOptions,
    /// Near lights against distant ones as the LEDs move away ([`crate::eval::near::sweep`]).
    pub near: crate::eval::near::NearSweepOptions,
    /// Every shape-from-shading method on rendered shapes, error against time
    /// ([`crate::eval::sfs::sweep`]).
    pub sfs: crate::eval::sfs::SfsSweepOptions,
    /// The DiLiGenT stage timing beside the peer: plain least squares ([`super::stages::PEER_METHOD`]),
    /// normals only.
    pub stages: Config,
    /// Runs of the DiLiGenT stage timing and of each estimator on DiLiGenT; medians are
    /// reported.
    pub diligent_repeat: usize,
}

impl SuitePlan {
    /// The plan that regenerates `docs/bench`: every part at its defaults, three timed runs per
    /// point.
    pub fn full() -> Self {
        SuitePlan {
            sweep: SweepOptions {
                repeat: super::DEFAULT_REPEAT,
                ..SweepOptions::default()
            },
            scaling: ScalingOptions::default(),
            integration: IntegrationBenchOptions::default(),
            interreflections: InterreflectionBenchOptions::default(),
            near: crate::eval::near::NearSweepOptions::default(),
            sfs: crate::eval::sfs::SfsSweepOptions::default(),
            stages: Config {
                solve: SolveOptions::with_method(super::stages::PEER_METHOD),
                integration: None,
                ..Config::default()
            },
            diligent_repeat: super::DEFAULT_REPEAT,
        }
    }

    /// A smoke run of the whole chain: small images ([`SweepOptions::quick`]; scaling at 64²
    /// and 128², integrators at 64² and 128², interreflections at 48² with 12 lights, near
    /// lights at 48² with 8 LEDs at 2 and 10 sizes, shape from shading at 48²) and single runs,
    /// except the sweeps' three.
    pub fn quick() -> Self {
        let full = Self::full();
        SuitePlan {
            sweep: full.sweep.quick(),
            scaling: ScalingOptions {
                sizes: vec![64, 128],
                repeat: 1,
                ..full.scaling
            },
            integration: IntegrationBenchOptions {
                sizes: vec![64, 128],
                repeat: 1,
                ..full.integration
            },
            interreflections: InterreflectionBenchOptions {
                size: 48,
                lights: 12,
                ..full.interreflections
            },
            near: crate::eval::near::NearSweepOptions {
                size: 48,
                lights: 8,
                distances: vec![2.0, 10.0],
                ..full.near
            },
            sfs: crate::eval::sfs::SfsSweepOptions {
                size: 48,
                ..full.sfs
            },
            diligent_repeat: 1,
            ..full
        }
    }

    /// [`Self::quick`] when `quick`, else [`Self::full`].
    pub fn new(quick: bool) -> Self {
        if quick { Self::quick() } else { Self::full() }
    }
}
