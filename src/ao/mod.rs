//! Ambient occlusion: LAO directions and parameters, the GPU precompute, and a CPU reference.

pub mod cao;
pub mod cpu;
pub mod filter_gpu;
pub mod filtered;
pub mod lao;
pub mod progressive;
pub mod sh;

pub use lao::{directions, LaoGpu, LaoParams};

use filtered::{Estimator, FilterParams};

/// Which AO method fills the one ambient volume every view samples (docs/design.md, "AO
/// methods"). CAO's clip maps, dilation, mask and boxes make each one clip-aware per frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AoMethod {
    /// Local Ambient Occlusion (Hernell et al.) with the LAO parameters.
    Lao,
    /// Volumetric AO by separable filtering (Ruiz et al.).
    Filter(FilterParams),
}

impl AoMethod {
    /// The name `--ao` takes: lao, filter-cdf, filter-gauss, filter-penner, filter-exact.
    pub fn name(&self) -> String {
        match self {
            AoMethod::Lao => "lao".into(),
            AoMethod::Filter(f) => format!("filter-{}", f.estimator.name()),
        }
    }

    /// Parses `--ao NAME`; a filter takes the radius and input given beside it.
    pub fn parse(name: &str, filter: FilterParams) -> Result<AoMethod, String> {
        if name == "lao" {
            return Ok(AoMethod::Lao);
        }
        let estimator = name
            .strip_prefix("filter-")
            .and_then(|e| Estimator::ALL.into_iter().find(|x| x.name() == e))
            .ok_or_else(|| {
                format!(
                    "--ao '{name}': expected lao, filter-cdf, filter-gauss, filter-penner or filter-exact"
                )
            })?;
        filter.validate()?;
        Ok(AoMethod::Filter(FilterParams {
            estimator,
            ..filter
        }))
    }
}

/// The AO a session computes: the method, and LAO's parameters (used by `lao`, and by the
/// TF switch's budget).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AoConfig {
    pub method: AoMethod,
    pub lao: LaoParams,
}

impl From<LaoParams> for AoConfig {
    fn from(lao: LaoParams) -> Self {
        AoConfig {
            method: AoMethod::Lao,
            lao,
        }
    }
}
