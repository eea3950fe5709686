//! The environment blend mode (`--blend`, `--passthrough`): chosen from what the runtime offers,
//! and what it means for the frame. OPAQUE shows the volume over its own background; ADDITIVE
//! (see-through displays that add light) needs a black background, so the colour is emitted
//! light; ALPHA_BLEND (passthrough cameras) needs premultiplied colour over a transparent
//! background, alpha = the volume's accumulated opacity, and a layer submitted with
//! BLEND_TEXTURE_SOURCE_ALPHA. Headsets whose cameras come through XR_FB_passthrough (Quest,
//! Pico) instead composite OPAQUE over a passthrough layer, with the same alpha rules.

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

/// How frames are composited over the world: the environment blend mode, and whether an
/// XR_FB_passthrough layer lies under the projection layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Composition {
    pub blend: BlendMode,
    pub fb_passthrough: bool,
}

impl Composition {
    fn native(blend: BlendMode) -> Composition {
        Composition {
            blend,
            fb_passthrough: false,
        }
    }

    /// Whether the world shows through where the volume is not: the frame's background is
    /// then black with alpha 0 (premultiplied colour).
    pub fn see_through(self) -> bool {
        self.fb_passthrough || self.blend.see_through()
    }

    /// Whether the projection layer is submitted with BLEND_TEXTURE_SOURCE_ALPHA (composited by
    /// its alpha over the world or over the passthrough layer).
    pub fn source_alpha(self) -> bool {
        self.fb_passthrough || self.blend == BlendMode::AlphaBlend
    }

    /// "alpha-blend", or "opaque over XR_FB_passthrough".
    pub fn name(self) -> String {
        match self.fb_passthrough {
            true => format!("{} over XR_FB_passthrough", self.blend.name()),
            false => self.blend.name().to_string(),
        }
    }
}

fn list(offered: &[BlendMode]) -> String {
    offered
        .iter()
        .map(|m| m.name())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The composition to submit with, from the runtime's `offered` list (its order of
/// preference) and whether it offers XR_FB_passthrough (`fb`), or why none fits; the message
/// lists what the runtime offers. With `--passthrough`, a see-through blend mode the runtime
/// offers comes first; else OPAQUE over an XR_FB_passthrough layer.
pub fn choose_blend(
    offered: &[BlendMode],
    request: BlendRequest,
    passthrough: bool,
    fb: bool,
) -> Result<Composition, String> {
    if offered.is_empty() {
        return Err("the runtime offers no environment blend mode this build knows".into());
    }
    let fb_layer = (fb && offered.contains(&BlendMode::Opaque)).then_some(Composition {
        blend: BlendMode::Opaque,
        fb_passthrough: true,
    });
    let fb_note = if fb {
        "XR_FB_passthrough is offered, but not the opaque mode it composites under"
    } else {
        "nor XR_FB_passthrough"
    };
    match request {
        BlendRequest::Auto if !passthrough => Ok(Composition::native(offered[0])),
        BlendRequest::Auto => [BlendMode::AlphaBlend, BlendMode::Additive]
            .into_iter()
            .find(|m| offered.contains(m))
            .map(Composition::native)
            .or(fb_layer)
            .ok_or_else(|| {
                format!(
                    "--passthrough needs the alpha-blend or additive blend mode or \
                     XR_FB_passthrough; the runtime offers only: {} ({fb_note})",
                    list(offered)
                )
            }),
        BlendRequest::Mode(m) if passthrough && !m.see_through() => fb_layer.ok_or_else(|| {
            format!(
                "--passthrough with --blend {}: the world cannot show through an opaque layer \
                 without XR_FB_passthrough; use --blend alpha-blend or additive (the runtime \
                 offers: {}; {fb_note})",
                m.name(),
                list(offered)
            )
        }),
        BlendRequest::Mode(m) if offered.contains(&m) => Ok(Composition::native(m)),
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
            for (passthrough, fb) in [(false, false), (false, true), (true, false), (true, true)] {
                let requests =
                    std::iter::once(BlendRequest::Auto).chain(ALL_MODES.map(BlendRequest::Mode));
                for req in requests {
                    let got = choose_blend(&offered, req, passthrough, fb);
                    let native = |m: BlendMode| Composition {
                        blend: m,
                        fb_passthrough: false,
                    };
                    let fb_layer = (fb && offered.contains(&Opaque)).then_some(Composition {
                        blend: Opaque,
                        fb_passthrough: true,
                    });
                    let want = if offered.is_empty() {
                        None
                    } else {
                        match (req, passthrough) {
                            (BlendRequest::Auto, false) => Some(native(offered[0])),
                            (BlendRequest::Auto, true) => [AlphaBlend, Additive]
                                .into_iter()
                                .find(|m| offered.contains(m))
                                .map(native)
                                .or(fb_layer),
                            (BlendRequest::Mode(Opaque), true) => fb_layer,
                            (BlendRequest::Mode(m), _) => offered.contains(&m).then_some(native(m)),
                        }
                    };
                    let case = format!("{offered:?} {req:?} passthrough {passthrough} fb {fb}");
                    match (want, &got) {
                        (Some(w), Ok(g)) => {
                            assert_eq!(*g, w, "{case}");
                            // Passthrough always sees the world, by alpha.
                            if passthrough {
                                assert!(g.see_through(), "{case}");
                            }
                            assert_eq!(g.source_alpha(), g.fb_passthrough || g.blend == AlphaBlend);
                        }
                        (None, Err(msg)) => {
                            for m in &offered {
                                assert!(msg.contains(m.name()), "{msg} lacks {}", m.name());
                            }
                        }
                        _ => panic!("{case}: got {got:?}, want {want:?}"),
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
