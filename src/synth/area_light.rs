//! Area lights: a distant light of angular radius α is a disc of uniform radiance on the sky,
//! sampled over its directions for both the shading and the cast-shadow test, so that shadows
//! get penumbrae.
//!
//! **Model.** A source of uniform radiance L filling the cone of half angle α about the unit
//! direction l gives a surface facing it the irradiance E = ∫_cap L cos γ dω = π L sin²α (γ the
//! angle to l); E is the light's intensity, as for a point light. A surface of normal n with the
//! whole cap above its horizon receives ∫_cap L (n·ω) dω = L n·∫_cap ω dω = E (n·l), because the
//! cap's mean direction is l by symmetry: an unoccluded Lambertian surface is shaded exactly as
//! by a point light of the same E. The two differ where the cap is cut — by the horizon
//! (n·l < sin α, near the terminator) and by occluders, whose shadows get penumbrae 2α wide in
//! angle. A straight occluding edge (a wall's top seen from the ground, at angular distance δ
//! below the light's centre) cuts the disc along a chord: for small α the visible part of
//! the disc, projected on the plane ⊥ l, is a circular segment, and a Lambertian point
//! receives E·(A_seg/πR²)·(n·l + x̄ n·u) with R = sin α, A_seg = R² acos(c/R) − c√(R² − c²),
//! c = −sin δ the chord's offset, x̄ = ⅔(R² − c²)^{3/2}/A_seg the segment's centroid and u the
//! unit vector ⊥ l pointing away from the edge (the render tests check penumbrae against this).
//!
//! **Quadrature.** N directions l_m over the cap (uniform in solid angle): ⌊N/2⌋ pairs opposite
//! about l (same γ, azimuths φ_j and φ_j + π), the pairs at the midpoints of equal strata of
//! cos γ ∈ [cos α, 1], φ_j = j·(golden angle) + ψ; an odd N adds the centre l. ψ is a rotation
//! per pixel and light (a hash of the seed, the light and the pixel) that turns the banding of a
//! fixed pattern into noise. Every sample has the weight w = 1/Σ_m cos γ_m, so that
//! Σ_m w l_m = l exactly (the pairs' components ⊥ l cancel): the pixel
//! E Σ_m w π f(l_m, v) (n·l_m)⁺ V(l_m), V the visibility, equals E (n·l) to rounding for an
//! unoccluded Lambertian surface whatever N. (w ≈ 2/(N(1 + cos α)) = Ω/(N π sin²α), the
//! solid angle per sample over the cap's projected solid angle.)
//!
//! **Visibility** is the ray march of [`crate::synth::raymarch`] with the point light's
//! 0.5-pixel step, refined [`SOFT_SHADOW_REFINE`] halvings where the ray may have passed below
//! an edge between two samples (locating edges to 1/256 pixel). Unrefined, a ray that passes
//! below a wall's top between two samples and is above the wall at the next counts as clear,
//! which brightens a penumbra by a visible fraction of its range (up to 0.004 and 0.009 of 0.4 in the render test with
//! 0.125- and 0.25-pixel steps, against 0.0013 refined, which is the quadrature's noise).
//! Each sample costs one shadow ray: N samples cost about N times the point light's shadow
//! test.

use nalgebra::Vector3;
use std::f64::consts::PI;

/// Ray-march step of the soft-shadow test, in pixels (see the module documentation).
pub const SOFT_SHADOW_STEP: f64 = 0.5;
/// Halvings of a soft-shadow march step where the ray may have passed below an edge.
pub const SOFT_SHADOW_REFINE: u32 = 7;
/// Largest number of directions per light
/// ([`crate::synth::render::RenderOptions::area_light_samples`]).
pub const MAX_AREA_LIGHT_SAMPLES: usize = 1024;

/// The golden angle π(3 − √5), the azimuth increment of the pattern.
const GOLDEN_ANGLE: f64 = 2.399_963_229_728_653;

/// The sample directions of one disc light, before the per-pixel rotation.
#[derive(Debug, Clone, PartialEq)]
pub struct AreaLight {
    /// Centre direction l (unit).
    direction: Vector3<f64>,
    /// Two unit vectors completing l to an orthonormal frame.
    t: Vector3<f64>,
    b: Vector3<f64>,
    /// Per sample: cos γ, sin γ, φ.
    samples: Vec<(f64, f64, f64)>,
    /// The weight of every sample, 1/Σ cos γ.
    weight: f64,
}

impl AreaLight {
    /// The light of unit centre direction `direction` and angular radius `radius_deg` degrees,
    /// sampled by `samples` directions (at least 1; 1 is the centre alone, a point light).
    pub fn new(direction: Vector3<f64>, radius_deg: f64, samples: usize) -> Self {
        let samples = samples.max(1);
        let frame = crate::synth::reflectance::Frame::from_normal(direction);
        let cos_alpha = radius_deg.to_radians().cos();
        let pairs = samples / 2;
        let mut pattern = Vec::with_capacity(samples);
        if samples % 2 == 1 {
            pattern.push((1.0, 0.0, 0.0));
        }
        for j in 0..pairs {
            let cos_g = 1.0 - (1.0 - cos_alpha) * (j as f64 + 0.5) / pairs as f64;
            let sin_g = (1.0 - cos_g * cos_g).max(0.0).sqrt();
            let phi = j as f64 * GOLDEN_ANGLE;
            pattern.push((cos_g, sin_g, phi));
            pattern.push((cos_g, sin_g, phi + PI));
        }
        let weight = 1.0 / pattern.iter().map(|s| s.0).sum::<f64>();
        AreaLight {
            direction,
            t: frame.t,
            b: frame.b,
            samples: pattern,
            weight,
        }
    }

    /// Number of sample directions.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether there are no samples (never: at least the centre).
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The weight w of every sample: Σ_m w l_m = l.
    pub fn weight(&self) -> f64 {
        self.weight
    }

    /// The sample directions with the azimuths rotated by `rotation` radians about l.
    pub fn directions(&self, rotation: f64) -> impl Iterator<Item = Vector3<f64>> + '_ {
        let (sr, cr) = rotation.sin_cos();
        self.samples.iter().map(move |&(cos_g, sin_g, phi)| {
            let (sp, cp) = phi.sin_cos();
            // Rotate (cos φ, sin φ) by the rotation.
            let (c, s) = (cp * cr - sp * sr, sp * cr + cp * sr);
            cos_g * self.direction + sin_g * (c * self.t + s * self.b)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The weighted directions sum to l exactly, every direction is within α of l, and the
    /// weight approaches Ω/(N π sin²α).
    #[test]
    fn weighted_directions_sum_to_the_centre() {
        let l = Vector3::new(0.3, -0.4, 0.8).normalize();
        for (n, alpha) in [(2usize, 5.0f64), (7, 10.0), (64, 3.0), (255, 30.0)] {
            let light = AreaLight::new(l, alpha, n);
            assert_eq!(light.len(), n);
            for rot in [0.0, 1.3, 5.9] {
                let sum: Vector3<f64> = light.directions(rot).map(|d| d * light.weight()).sum();
                assert!((sum - l).norm() < 1e-13, "N {n} α {alpha}: {sum:?}");
                for d in light.directions(rot) {
                    assert!((d.norm() - 1.0).abs() < 1e-12);
                    assert!(d.dot(&l) >= alpha.to_radians().cos() - 1e-12);
                }
            }
            let a = alpha.to_radians();
            let expect = 2.0 * PI * (1.0 - a.cos()) / (n as f64 * PI * a.sin().powi(2));
            let tol = if n % 2 == 1 { 0.02 } else { 1e-9 };
            assert!(
                (light.weight() / expect - 1.0).abs() < tol,
                "N {n}: {} vs {expect}",
                light.weight()
            );
        }
        // One sample: the point light.
        let point = AreaLight::new(l, 5.0, 1);
        assert_eq!(point.directions(2.0).collect::<Vec<_>>(), vec![l]);
        assert_eq!(point.weight(), 1.0);
    }
}
