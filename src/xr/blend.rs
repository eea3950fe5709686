//! The environment blend mode (`--blend`, `--passthrough`): chosen from what the runtime offers,
//! and what it means for the frame. OPAQUE shows the volume over its own background; ADDITIVE
//! (see-through displays that add light) needs a black background, so the colour is emitted
//! light; ALPHA_BLEND (passthrough cameras) needs premultiplied colour over a transparent
//! background, alpha = the volume's accumulated opacity, and a layer submitted with
//! BLEND_TEXTURE_SOURCE_ALPHA.

use openxr as xr;

/// A blend mode by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlendMode {
    Opaque,
    Additive,
    AlphaBlend,
}

impl BlendMode {
    pub const ALL: [BlendMode; 3] = [
        BlendMode::Opaque,
        BlendMode::Additive,
        BlendMode::AlphaBlend,
    ];

    /// The name `--blend` takes.
    pub fn name(self) -> &'static str {
        match self {
            BlendMode::Opaque => "opaque",
            BlendMode::Additive => "additive",
            BlendMode::AlphaBlend => "alpha-blend",
        }
    }

    pub fn to_xr(self) -> xr::EnvironmentBlendMode {
        match self {
            BlendMode::Opaque => xr::EnvironmentBlendMode::OPAQUE,
            BlendMode::Additive => xr::EnvironmentBlendMode::ADDITIVE,
            BlendMode::AlphaBlend => xr::EnvironmentBlendMode::ALPHA_BLEND,
        }
    }

    /// None for a mode this build does not know (a vendor extension's).
    pub fn from_xr(m: xr::EnvironmentBlendMode) -> Option<BlendMode> {
        BlendMode::ALL.into_iter().find(|b| b.to_xr() == m)
    }

    /// Whether the world shows through where the volume is not: the frame's background is
    /// then black with alpha 0 (premultiplied colour).
    pub fn see_through(self) -> bool {
        self != BlendMode::Opaque
    }
}

/// What `--blend` asks for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BlendRequest {
    /// The runtime's preferred mode (its first), or with `--passthrough` the first of
    /// ALPHA_BLEND and ADDITIVE it offers.
    #[default]
    Auto,
    Mode(BlendMode),
}

impl std::str::FromStr for BlendRequest {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(BlendRequest::Auto);
        }
        BlendMode::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .map(BlendRequest::Mode)
            .ok_or_else(|| format!("--blend '{s}': expected auto, opaque, additive or alpha-blend"))
    }
}

fn list(offered: &[BlendMode]) -> String {
    offered
        .iter()
        .map(|m| m.name())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The mode to submit with, from the runtime's `offered` list (its order of preference), or why
/// none fits; the message lists what the runtime offers.
pub fn choose_blend(
    offered: &[BlendMode],
    request: BlendRequest,
    passthrough: bool,
) -> Result<BlendMode, String> {
    if offered.is_empty() {
        return Err("the runtime offers no environment blend mode this build knows".into());
    }
    match request {
        BlendRequest::Auto if !passthrough => Ok(offered[0]),
        BlendRequest::Auto => [BlendMode::AlphaBlend, BlendMode::Additive]
            .into_iter()
            .find(|m| offered.contains(m))
            .ok_or_else(|| {
                format!(
                    "--passthrough needs the alpha-blend or additive blend mode; the runtime offers \
                     only: {}",
                    list(offered)
                )
            }),
        BlendRequest::Mode(m) if passthrough && !m.see_through() => Err(format!(
            "--passthrough with --blend {}: the world cannot show through an opaque layer; use \
             --blend alpha-blend or additive (the runtime offers: {})",
            m.name(),
            list(offered)
        )),
        BlendRequest::Mode(m) if offered.contains(&m) => Ok(m),
        BlendRequest::Mode(m) => Err(format!(
            "--blend {}: the runtime does not offer it; it offers: {}",
            m.name(),
            list(offered)
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use BlendMode::*;

    /// Every subset of the modes, in every order the runtime could prefer them.
    fn offers() -> Vec<Vec<BlendMode>> {
        let mut out = vec![vec![]];
        for a in ALL_MODES {
            out.push(vec![a]);
            for b in ALL_MODES.iter().filter(|b| **b != a) {
                out.push(vec![a, *b]);
                for c in ALL_MODES.iter().filter(|c| **c != a && *c != b) {
                    out.push(vec![a, *b, *c]);
                }
            }
        }
        out
    }
    const ALL_MODES: [BlendMode; 3] = BlendMode::ALL;

    #[test]
    fn every_offer_and_request_gets_the_documented_mode_or_a_message_listing_the_offer() {
        for offered in offers() {
            for passthrough in [false, true] {
                let requests =
                    std::iter::once(BlendRequest::Auto).chain(ALL_MODES.map(BlendRequest::Mode));
                for req in requests {
                    let got = choose_blend(&offered, req, passthrough);
                    let want = if offered.is_empty() {
                        None
                    } else {
                        match (req, passthrough) {
                            (BlendRequest::Auto, false) => Some(offered[0]),
                            (BlendRequest::Auto, true) => [AlphaBlend, Additive]
                                .into_iter()
                                .find(|m| offered.contains(m)),
                            (BlendRequest::Mode(Opaque), true) => None,
                            (BlendRequest::Mode(m), _) => offered.contains(&m).then_some(m),
                        }
                    };
                    match (want, &got) {
                        (Some(w), Ok(g)) => assert_eq!(*g, w, "{offered:?} {req:?} {passthrough}"),
                        (None, Err(msg)) => {
                            for m in &offered {
                                assert!(msg.contains(m.name()), "{msg} lacks {}", m.name());
                            }
                        }
                        _ => panic!("{offered:?} {req:?} passthrough {passthrough}: got {got:?}, want {want:?}"),
                    }
                }
            }
        }
    }

    #[test]
    fn names_parse_and_map_to_openxr() {
        for m in BlendMode::ALL {
            assert_eq!(
                m.name().parse::<BlendRequest>().unwrap(),
                BlendRequest::Mode(m)
            );
            assert_eq!(BlendMode::from_xr(m.to_xr()), Some(m));
        }
        assert_eq!("auto".parse::<BlendRequest>().unwrap(), BlendRequest::Auto);
        assert!("alpha"
            .parse::<BlendRequest>()
            .unwrap_err()
            .contains("alpha-blend"));
        assert!(!Opaque.see_through() && Additive.see_through() && AlphaBlend.see_through());
    }
}
