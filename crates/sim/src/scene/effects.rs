//! Effects a frame may pay for, and the rule that decides which are live:
//! an effect is live only when the scene can show it for this frame, the
//! scene does not forbid it, and it is on by default or someone wants it.

use serde::{Serialize, Serializer};

/// One optional part of the image formation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Effect {
    /// Ray marching the heightfield: parallax and masking.
    Relief,
    /// Shadow rays through the heightfield towards the lamp.
    Shadows,
    /// The glossy lobe.
    Specular,
    /// Blur of the irradiance under the surface.
    Subsurface,
    /// One bounce of light inside the relief.
    Interreflection,
    /// The laser line.
    Laser,
    /// Macro self-shadowing from per-vertex binary visibility maps.
    VisibilityMaps,
    /// Lens fall-off towards the image corners.
    Vignetting,
    /// Shot and read noise from a seeded generator.
    Noise,
}

impl Effect {
    /// Every effect, in the order of declaration.
    pub const ALL: [Effect; 9] = [
        Effect::Relief,
        Effect::Shadows,
        Effect::Specular,
        Effect::Subsurface,
        Effect::Interreflection,
        Effect::Laser,
        Effect::VisibilityMaps,
        Effect::Vignetting,
        Effect::Noise,
    ];

    /// The effect's name in effect switches, JSON and the CLI (`relief`,
    /// `visibility-maps`, …).
    pub fn name(self) -> &'static str {
        match self {
            Effect::Relief => "relief",
            Effect::Shadows => "shadows",
            Effect::Specular => "specular",
            Effect::Subsurface => "subsurface",
            Effect::Interreflection => "interreflection",
            Effect::Laser => "laser",
            Effect::VisibilityMaps => "visibility-maps",
            Effect::Vignetting => "vignetting",
            Effect::Noise => "noise",
        }
    }

    /// Effects that cost so much that only a scene or a request that asks
    /// for them gets them.
    pub fn on_by_default(self) -> bool {
        self != Effect::Interreflection
    }

    fn bit(self) -> u16 {
        1 << (self as u16)
    }
}

impl std::str::FromStr for Effect {
    type Err = String;
    fn from_str(s: &str) -> Result<Effect, String> {
        Effect::ALL
            .into_iter()
            .find(|e| e.name() == s)
            .ok_or_else(|| {
                let names: Vec<_> = Effect::ALL.iter().map(|e| e.name()).collect();
                format!("unknown effect `{s}` (known: {})", names.join(", "))
            })
    }
}

/// A set of effects.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct EffectSet(u16);

impl EffectSet {
    /// The empty set.
    pub const NONE: EffectSet = EffectSet(0);

    /// The set of every effect.
    pub fn all() -> EffectSet {
        Effect::ALL.into_iter().collect()
    }

    /// True when `e` is in the set.
    pub fn contains(self, e: Effect) -> bool {
        self.0 & e.bit() != 0
    }

    /// Adds `e` to the set.
    pub fn insert(&mut self, e: Effect) {
        self.0 |= e.bit();
    }

    /// Takes `e` out of the set.
    pub fn remove(&mut self, e: Effect) {
        self.0 &= !e.bit();
    }

    /// The effects in the set, in the order of [`Effect::ALL`].
    pub fn iter(self) -> impl Iterator<Item = Effect> {
        Effect::ALL.into_iter().filter(move |e| self.contains(*e))
    }

    /// The names of the effects in the set, in the order of [`Effect::ALL`].
    pub fn names(self) -> Vec<&'static str> {
        self.iter().map(Effect::name).collect()
    }

    /// True when the set holds no effect.
    pub fn is_empty(self) -> bool {
        self.0 == 0
    }
}

impl FromIterator<Effect> for EffectSet {
    fn from_iter<I: IntoIterator<Item = Effect>>(iter: I) -> EffectSet {
        let mut s = EffectSet::NONE;
        for e in iter {
            s.insert(e);
        }
        s
    }
}

impl std::fmt::Display for EffectSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.is_empty() {
            return f.write_str("none");
        }
        f.write_str(&self.names().join(","))
    }
}

impl Serialize for EffectSet {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.names())
    }
}

/// What a frame request asks for beyond the defaults.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct EffectSwitches {
    /// Effects to render even if they are off by default.
    pub want: EffectSet,
    /// Effects never to render; this wins over `want`.
    pub forbid: EffectSet,
}

impl std::str::FromStr for EffectSwitches {
    type Err = String;
    /// `all`, `none`, or a comma list of `+effect` (want) and `-effect`
    /// (forbid); a bare name means want.
    fn from_str(s: &str) -> Result<EffectSwitches, String> {
        let mut sw = EffectSwitches::default();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            match part {
                "all" => sw.want = EffectSet::all(),
                "none" => sw.forbid = EffectSet::all(),
                _ => {
                    if let Some(name) = part.strip_prefix('-') {
                        sw.forbid.insert(name.parse()?);
                    } else {
                        let name = part.strip_prefix('+').unwrap_or(part);
                        sw.want.insert(name.parse()?);
                    }
                }
            }
        }
        Ok(sw)
    }
}

/// The effects live for one frame, and why the others are not.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct EffectPlan {
    /// The effects this frame renders.
    pub live: EffectSet,
    /// What the scene could show for this frame.
    pub possible: EffectSet,
}

impl EffectPlan {
    /// True when `e` is live for this frame.
    pub fn has(&self, e: Effect) -> bool {
        self.live.contains(e)
    }

    /// The rule: possible, not forbidden (by the scene or the request), and
    /// on by default or wanted (by the scene or the request).
    pub fn decide(
        possible: EffectSet,
        scene_want: EffectSet,
        scene_forbid: EffectSet,
        request: EffectSwitches,
    ) -> EffectPlan {
        let live = possible
            .iter()
            .filter(|e| !scene_forbid.contains(*e) && !request.forbid.contains(*e))
            .filter(|e| e.on_by_default() || scene_want.contains(*e) || request.want.contains(*e))
            .collect();
        EffectPlan { live, possible }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn switches_parse_and_reject_unknown_names() {
        let sw: EffectSwitches = "+interreflection,-noise".parse().unwrap();
        assert!(sw.want.contains(Effect::Interreflection));
        assert!(sw.forbid.contains(Effect::Noise));
        assert!("sparkle".parse::<EffectSwitches>().is_err());
        assert_eq!(
            "all".parse::<EffectSwitches>().unwrap().want,
            EffectSet::all()
        );
    }

    #[test]
    fn impossible_effects_are_never_live() {
        let possible: EffectSet = [Effect::Specular].into_iter().collect();
        let plan = EffectPlan::decide(
            possible,
            EffectSet::all(),
            EffectSet::NONE,
            EffectSwitches {
                want: EffectSet::all(),
                forbid: EffectSet::NONE,
            },
        );
        assert_eq!(plan.live, possible);
    }

    #[test]
    fn interreflection_needs_asking_for_and_forbid_wins() {
        let possible: EffectSet = [Effect::Interreflection, Effect::Noise]
            .into_iter()
            .collect();
        let none = EffectSwitches::default();
        let plan = EffectPlan::decide(possible, EffectSet::NONE, EffectSet::NONE, none);
        assert!(!plan.has(Effect::Interreflection) && plan.has(Effect::Noise));
        let want: EffectSwitches = "interreflection,-noise".parse().unwrap();
        let plan = EffectPlan::decide(possible, EffectSet::NONE, EffectSet::NONE, want);
        assert!(plan.has(Effect::Interreflection) && !plan.has(Effect::Noise));
        let forbid: EffectSet = [Effect::Interreflection].into_iter().collect();
        let plan = EffectPlan::decide(possible, EffectSet::NONE, forbid, want);
        assert!(!plan.has(Effect::Interreflection));
    }
}
