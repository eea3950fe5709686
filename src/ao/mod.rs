//! Ambient occlusion: LAO directions and parameters, the GPU precompute, and a CPU reference.

pub mod cao;
pub mod cpu;
pub mod filter_gpu;
pub mod filtered;
pub mod histogram;
pub mod histogram_gpu;
pub mod lao;
pub mod method;
pub mod pool;
pub mod progressive;
pub mod sh;
pub mod stored;
pub mod voxel_box;

/// `--bleeding`'s default: half way to the neighbourhood's colour where it is fully occluded.
pub const DEFAULT_BLEEDING: f32 = 0.5;
/// Gradients below this fraction of the value range per mm are noise, not surfaces: the ray
/// caster lights such samples by the ambient term alone (faded in up to twice this), and the
/// local histograms do not split their neighbourhood there.
pub const MIN_GRADIENT: f32 = 0.004;

pub use lao::{directions, LaoGpu, LaoParams};

use filtered::{Estimator, FilterParams};
use histogram::HistParams;

/// Which AO method fills the one ambient volume every view samples (docs/design.md, "AO
/// methods"). CAO's clip maps, dilation, mask and boxes make each one clip-aware per frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AoMethod {
    /// Local Ambient Occlusion (Hernell et al.) with the LAO parameters.
    Lao,
    /// Volumetric AO by separable filtering (Ruiz et al.).
    Filter(FilterParams),
    /// Local-histogram AO with colour bleeding (Ropinski et al.).
    Histogram(HistParams),
}

impl AoMethod {
    /// The name `--ao` takes: lao, filter-cdf, filter-gauss, filter-penner, filter-exact,
    /// histogram.
    pub fn name(&self) -> String {
        match self {
            AoMethod::Lao => "lao".into(),
            AoMethod::Filter(f) => format!("filter-{}", f.estimator.name()),
            AoMethod::Histogram(_) => "histogram".into(),
        }
    }

    /// Parses `--ao NAME`; a filter takes the radius and input given beside it, the local
    /// histograms their parameters.
    pub fn parse(name: &str, filter: FilterParams, hist: HistParams) -> Result<AoMethod, String> {
        match name {
            "lao" => return Ok(AoMethod::Lao),
            "histogram" => {
                hist.validate()?;
                return Ok(AoMethod::Histogram(hist));
            }
            _ => {}
        }
        let estimator = name
            .strip_prefix("filter-")
            .and_then(|e| Estimator::ALL.into_iter().find(|x| x.name() == e))
            .ok_or_else(|| {
                format!(
                    "--ao '{name}': expected lao, filter-cdf, filter-gauss, filter-penner, filter-exact or histogram"
                )
            })?;
        filter.validate()?;
        Ok(AoMethod::Filter(FilterParams {
            estimator,
            ..filter
        }))
    }
}

/// The AO a session computes: the method, LAO's parameters (used by `lao`, and by the TF
/// switch's budget) and the filters' (used by the filter methods of [`AoConfig::cycle`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AoConfig {
    pub method: AoMethod,
    pub lao: LaoParams,
    pub filter: FilterParams,
    /// The local-histogram method's bleeding weight W (`--bleeding`), for the ray caster.
    pub bleeding: f32,
}

impl AoConfig {
    /// A config whose method is `method`, its filter parameters the method's own (or the
    /// defaults for LAO).
    pub fn new(method: AoMethod, lao: LaoParams) -> Self {
        let filter = match method {
            AoMethod::Filter(f) => f,
            _ => FilterParams::default(),
        };
        AoConfig {
            method,
            lao,
            filter,
            bleeding: DEFAULT_BLEEDING,
        }
    }

    /// The reach in mm of the method on a volume of `spacing`, as its GPU state tells it
    /// ([`cao::Cao::reach_mm`]), without setting one up.
    pub fn reach_mm(&self, spacing: [f64; 3]) -> f64 {
        match &self.method {
            AoMethod::Lao => self.lao.steps.saturating_sub(1) as f64 * self.lao.step_mm as f64,
            AoMethod::Filter(f) => f.reach_mm(spacing),
            AoMethod::Histogram(h) => {
                histogram::Neighbourhood::new(h.radius_mm, spacing).reach_mm(spacing)
            }
        }
    }

    /// The methods the stick click cycles through: the configured one, then LAO and the three
    /// filter estimators (with the configured radius and input), each once. `exact` is for
    /// tests and the benchmark, not for viewing; the local histograms are in the cycle only
    /// when configured (their precompute takes minutes, so it is not started by a click).
    pub fn cycle(&self) -> Vec<AoMethod> {
        let mut all = vec![self.method, AoMethod::Lao];
        for estimator in [Estimator::Cdf, Estimator::Gauss, Estimator::Penner] {
            all.push(AoMethod::Filter(FilterParams {
                estimator,
                ..self.filter
            }));
        }
        let mut cycle: Vec<AoMethod> = Vec::new();
        for m in all {
            if !cycle.contains(&m) {
                cycle.push(m);
            }
        }
        cycle
    }
}

impl From<LaoParams> for AoConfig {
    fn from(lao: LaoParams) -> Self {
        AoConfig::new(AoMethod::Lao, lao)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cycle_starts_with_the_configured_method_and_lists_each_once() {
        let f = FilterParams {
            radius_mm: 9.0,
            ..Default::default()
        };
        let h = HistParams::default();
        let gauss = AoMethod::parse("filter-gauss", f, h).unwrap();
        let names = |c: &AoConfig| c.cycle().iter().map(|m| m.name()).collect::<Vec<_>>();
        let cfg = AoConfig::new(gauss, LaoParams::default());
        assert_eq!(
            names(&cfg),
            ["filter-gauss", "lao", "filter-cdf", "filter-penner"]
        );
        // Every filter in the cycle keeps the configured radius.
        assert!(cfg.cycle().iter().all(|m| match m {
            AoMethod::Filter(p) => p.radius_mm == 9.0,
            _ => true,
        }));
        let lao = AoConfig::from(LaoParams::default());
        assert_eq!(
            names(&lao),
            ["lao", "filter-cdf", "filter-gauss", "filter-penner"]
        );
        let exact = AoConfig::new(AoMethod::parse("filter-exact", f, h).unwrap(), lao.lao);
        assert_eq!(names(&exact)[0], "filter-exact");
        assert_eq!(exact.cycle().len(), 5);
        let hist = AoConfig::new(AoMethod::parse("histogram", f, h).unwrap(), lao.lao);
        assert_eq!(names(&hist)[..2], ["histogram", "lao"]);
        assert!(!names(&lao).contains(&"histogram".to_string()));
        assert!(AoMethod::parse("histogram", f, HistParams { bins: 1, ..h }).is_err());
    }
}
