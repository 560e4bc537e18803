//! Presets shared by every stage: `tiny` for tests, `quick` for the CPU demo, `standard` for
//! quality, `paper` for the paper's schedule on a GPU. Each stage's configuration type says
//! what a preset means for it.

use serde::{Deserialize, Serialize};

use crate::SettingError;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// Seconds: unit and end-to-end tests.
    Tiny,
    /// Minutes on a 2-core CPU: the demo.
    #[default]
    Quick,
    /// Better quality, longer schedules.
    Standard,
    /// The paper's schedule (meant for a GPU).
    Paper,
}

impl Preset {
    pub const ALL: [Preset; 4] = [Preset::Tiny, Preset::Quick, Preset::Standard, Preset::Paper];

    pub const fn name(self) -> &'static str {
        match self {
            Preset::Tiny => "tiny",
            Preset::Quick => "quick",
            Preset::Standard => "standard",
            Preset::Paper => "paper",
        }
    }
}

impl std::str::FromStr for Preset {
    type Err = SettingError;

    fn from_str(s: &str) -> Result<Self, SettingError> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                SettingError::new(
                    "preset",
                    format!("unknown preset `{s}` (expected tiny, quick, standard or paper)"),
                )
            })
    }
}

impl std::fmt::Display for Preset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for p in Preset::ALL {
            assert_eq!(p.name().parse::<Preset>().unwrap(), p);
            assert_eq!(
                serde_json::to_value(p).unwrap(),
                serde_json::json!(p.name())
            );
        }
        let e = "huge".parse::<Preset>().unwrap_err();
        assert_eq!(e.field, "preset");
        assert!(e.reason.contains("huge"), "{e}");
    }
}
