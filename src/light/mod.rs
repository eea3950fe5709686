//! Lighting by a distant environment through spherical harmonics (Ritschel 2007, section 3):
//! the SH basis ([`sh`]), and the environment light and its projection to SH per colour channel
//! ([`environment`]). Pure CPU: the visibility volume (`crate::ao::sh`) takes its basis from
//! here, and the ray caster only dots stored coefficients with [`ShLight`]`::coeffs`.
//!
//! The emission of a voxel with albedo rho is E = rho * sum_k V_k L_k, with V_k the voxel's
//! visibility coefficients and L_k = [`ShLight`]`::coeffs` (see [`sh`] for the conventions: an
//! empty volume under a constant environment c gives E = rho * c). The light is projected into
//! the volume's data frame, so turning the light or the volume only re-runs
//! [`Environment::project`] (well under a millisecond), never the visibility volume.

pub mod environment;
pub mod sh;

pub use environment::{Environment, EquirectImage, ShLight, ENVIRONMENTS};

use std::path::PathBuf;

/// Errors of environment lights. Every message names the file (or the spec) and the problem.
#[derive(Debug, thiserror::Error)]
pub enum LightError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {msg}")]
    Format { path: PathBuf, msg: String },
    #[error("{path}: unsupported: {msg}")]
    Unsupported { path: PathBuf, msg: String },
    #[error("light '{spec}': {msg}")]
    Spec { spec: String, msg: String },
}

impl LightError {
    pub(crate) fn format(path: &std::path::Path, msg: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }
    pub(crate) fn unsupported(path: &std::path::Path, msg: impl Into<String>) -> Self {
        Self::Unsupported {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }
}

/// Random unit vectors for the tests, from the project's fixed SplitMix64.
#[cfg(test)]
pub(crate) mod test_rng {
    use crate::rng::SplitMix64;
    use glam::DVec3;
    use std::f64::consts::PI;

    pub(crate) struct Rng(SplitMix64);
    impl Rng {
        pub(crate) fn new(seed: u64) -> Self {
            Rng(SplitMix64(seed))
        }
        pub(crate) fn next_u64(&mut self) -> u64 {
            self.0.next_u64()
        }
        /// Uniform in [0, 1).
        pub(crate) fn f64(&mut self) -> f64 {
            self.0.unit()
        }
        pub(crate) fn unit(&mut self) -> DVec3 {
            let z = 2.0 * self.f64() - 1.0;
            let phi = 2.0 * PI * self.f64();
            let r = (1.0 - z * z).sqrt();
            DVec3::new(r * phi.cos(), r * phi.sin(), z)
        }
    }
}
