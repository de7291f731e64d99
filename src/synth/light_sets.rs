//! Synthetic light sets for rendered scenes and experiments: rings, Fibonacci spirals, random
//! cones, the DiLiGenT-like grid, coplanar and clustered sets (the degenerate cases the tests
//! render on purpose).

use crate::capture::lights::{Light, Lights};
use crate::error::{Error, Result};
use nalgebra::Vector3;

/// The unit direction at `slant_deg` from the viewing axis (z) and azimuth `azimuth_deg` from
/// the x axis (x right, y up).
pub fn slanted(slant_deg: f64, azimuth_deg: f64) -> Vector3<f64> {
    let (s, t) = (slant_deg.to_radians(), azimuth_deg.to_radians());
    Vector3::new(s.sin() * t.cos(), s.sin() * t.sin(), s.cos())
}

impl Lights {
    /// `count` lights evenly spaced in azimuth on a ring at `elevation_deg` above the image
    /// plane (90° is the viewing direction), starting at azimuth `azimuth0_deg`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for `count == 0` or an elevation outside (0, 90].
    pub fn ring(count: usize, elevation_deg: f64, azimuth0_deg: f64) -> Result<Self> {
        if count == 0 {
            return Err(Error::param("count", "a ring needs at least one light"));
        }
        if !(elevation_deg > 0.0 && elevation_deg <= 90.0) {
            return Err(Error::param(
                "elevation",
                format!("{elevation_deg}° is outside (0°, 90°]"),
            ));
        }
        let e = elevation_deg.to_radians();
        let dirs: Vec<_> = (0..count)
            .map(|k| {
                let a = (azimuth0_deg + 360.0 * k as f64 / count as f64).to_radians();
                Vector3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin())
            })
            .collect();
        Lights::from_directions(&dirs)
    }

    /// `count` lights on a Fibonacci spiral over the cap of the upper hemisphere above
    /// `min_elevation_deg`: a near-uniform spread of directions.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for `count == 0` or an elevation outside [0, 90).
    pub fn fibonacci(count: usize, min_elevation_deg: f64) -> Result<Self> {
        if count == 0 {
            return Err(Error::param("count", "needs at least one light"));
        }
        if !(0.0..90.0).contains(&min_elevation_deg) {
            return Err(Error::param(
                "min_elevation",
                format!("{min_elevation_deg}° is outside [0°, 90°)"),
            ));
        }
        let z_min = min_elevation_deg.to_radians().sin();
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let dirs: Vec<_> = (0..count)
            .map(|k| {
                // Equal-area sampling of z over [z_min, 1].
                let z = 1.0 - (1.0 - z_min) * (k as f64 + 0.5) / count as f64;
                let r = (1.0 - z * z).max(0.0).sqrt();
                let a = golden * k as f64;
                Vector3::new(r * a.cos(), r * a.sin(), z)
            })
            .collect();
        Lights::from_directions(&dirs)
    }

    /// `count` directions drawn uniformly (by solid angle) within `half_angle_deg` of `axis`,
    /// seeded: the same seed gives the same set.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for `count == 0`, a zero axis or an angle outside (0, 90].
    pub fn random_cone(
        count: usize,
        axis: Vector3<f64>,
        half_angle_deg: f64,
        seed: u64,
    ) -> Result<Self> {
        use rand::{RngExt, SeedableRng};
        if count == 0 {
            return Err(Error::param("count", "needs at least one light"));
        }
        if !(half_angle_deg > 0.0 && half_angle_deg <= 90.0) {
            return Err(Error::param(
                "cone",
                format!("half angle {half_angle_deg}° is outside (0°, 90°]"),
            ));
        }
        let a = axis
            .try_normalize(1e-12)
            .ok_or_else(|| Error::param("axis", "zero vector"))?;
        let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
        let cos_max = half_angle_deg.to_radians().cos();
        let frame = crate::synth::reflectance::Frame::from_normal(a);
        let dirs: Vec<_> = (0..count)
            .map(|_| {
                let z: f64 = 1.0 - rng.random::<f64>() * (1.0 - cos_max);
                let phi: f64 = rng.random::<f64>() * 2.0 * std::f64::consts::PI;
                let r = (1.0 - z * z).max(0.0).sqrt();
                frame.t * (r * phi.cos()) + frame.b * (r * phi.sin()) + frame.n * z
            })
            .collect();
        Lights::from_directions(&dirs)
    }

    /// A DiLiGenT-like set: 96 lights on a planar 12 × 8 grid in front of the object, at
    /// (x/z, y/z) ∈ [−0.8, 0.8] × [−0.5, 0.5] (elevations 47°–90°), row by row from the bottom.
    pub fn diligent_grid() -> Self {
        let dirs: Vec<_> = (0..8)
            .flat_map(|r| {
                (0..12).map(move |c| {
                    let x = -0.8 + 1.6 * c as f64 / 11.0;
                    let y = -0.5 + r as f64 / 7.0;
                    Vector3::new(x, y, 1.0).normalize()
                })
            })
            .collect();
        // Unit, finite, non-zero by construction.
        Lights {
            lights: dirs.into_iter().map(Light::new).collect(),
        }
    }

    /// A near-degenerate set for stability tests: `count` directions spread over ±60° within the
    /// plane that contains the viewing axis and the image x axis, then tilted alternately by
    /// ±`tilt_deg` out of it. `tilt_deg` = 0 is exactly coplanar (rank 2).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] for fewer than 2 lights.
    pub fn coplanar(count: usize, tilt_deg: f64) -> Result<Self> {
        if count < 2 {
            return Err(Error::param(
                "count",
                "a coplanar set needs at least 2 lights",
            ));
        }
        let t = tilt_deg.to_radians();
        let dirs: Vec<_> = (0..count)
            .map(|k| {
                let a = (-60.0 + 120.0 * k as f64 / (count - 1) as f64).to_radians();
                let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                Vector3::new(a.sin() * t.cos(), sign * t.sin(), a.cos() * t.cos())
            })
            .collect();
        Lights::from_directions(&dirs)
    }

    /// A near-degenerate set for stability tests: `count` directions within `radius_deg` of the
    /// direction at `elevation_deg` towards +x (a cluster), seeded.
    ///
    /// # Errors
    /// As [`Lights::random_cone`].
    pub fn clustered(count: usize, elevation_deg: f64, radius_deg: f64, seed: u64) -> Result<Self> {
        let e = elevation_deg.to_radians();
        Lights::random_cone(count, Vector3::new(e.cos(), 0.0, e.sin()), radius_deg, seed)
    }
}
