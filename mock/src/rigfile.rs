//! The parts of a Glint rig file the simulated lab needs, read by the lab itself.
//!
//! The lab never calls Glint's code (its rig loader included): it reads `[camera]`,
//! `[lamp]`, `[geometry]` and `[mock]` on its own, ignoring every other key, and leaves the
//! validation of the rest to Glint.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::config::{LampPreset, MockConfig};
use crate::optics::SceneGeometry;
use crate::MockError;

#[derive(Debug, Clone, Deserialize)]
pub struct RigCamera {
    pub width: u32,
    pub height: u32,
    #[serde(default = "eight")]
    pub bit_depth: u8,
    #[serde(default)]
    pub pixel_format: Option<String>,
    #[serde(default)]
    pub device: Option<String>,
    #[serde(default = "thirty")]
    pub fps: f64,
}

fn eight() -> u8 {
    8
}
fn thirty() -> f64 {
    30.0
}

#[derive(Debug, Clone, Default, Deserialize)]
pub struct RigLamp {
    #[serde(default)]
    pub port: Option<String>,
    /// `[lamp.protocol]`: only its `preset` is the lab's business.
    #[serde(default)]
    pub protocol: Option<RigLampProtocol>,
}

/// `[lamp.protocol]` as the lab reads it: the preset Glint speaks to the lamp, which the
/// simulated lamp speaks too. Every other key is Glint's.
#[derive(Debug, Clone, Default, Deserialize)]
pub struct RigLampProtocol {
    #[serde(default)]
    pub preset: Option<String>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct RigGeometry {
    pub lamp_position_mm: [f64; 3],
    pub tile_thickness_mm: f64,
    pub tile_outline_mm: Vec<[f64; 2]>,
    pub grid_inner_corners: [u32; 2],
    pub grid_square_mm: f64,
}

/// `[reference]`: the reflectance standard's place and certificate value.
#[derive(Debug, Clone, Deserialize)]
pub struct RigReference {
    pub reflectance: OneOrThree,
    pub outline_mm: Vec<[f64; 2]>,
    pub thickness_mm: f64,
}

/// One number for every channel, or one per channel.
#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
pub enum OneOrThree {
    One(f64),
    Three([f64; 3]),
}

/// A rig file as the simulated lab reads it.
#[derive(Debug, Clone, Deserialize)]
pub struct RigFile {
    pub camera: RigCamera,
    #[serde(default)]
    pub lamp: RigLamp,
    pub geometry: RigGeometry,
    #[serde(default)]
    pub reference: Option<RigReference>,
    #[serde(default)]
    pub mock: Option<MockConfig>,
    /// The folder the file is in (relative paths in it are relative to it).
    #[serde(skip)]
    pub base: PathBuf,
}

impl RigFile {
    pub fn load(path: &Path) -> Result<RigFile, MockError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| MockError::Config(format!("cannot read {}: {e}", path.display())))?;
        let mut rig: RigFile = toml::from_str(&text).map_err(|e| {
            // One line: `path:line:column: message` (toml's own text draws the line).
            let at = e.span().map_or(String::new(), |r| {
                let before = &text[..r.start.min(text.len())];
                let line = before.matches('\n').count() + 1;
                let col = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
                format!("{line}:{col}:")
            });
            MockError::Config(format!(
                "{}:{at} {}",
                path.display(),
                e.message().trim().replace('\n', "; ")
            ))
        })?;
        rig.base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Ok(rig)
    }

    /// The protocol the rig's simulated lamp speaks: `[lamp.protocol] preset` if the rig
    /// names one (what Glint speaks to the lamp), else `[mock.lamp] preset` (default glint).
    pub fn lamp_preset(&self) -> Result<LampPreset, MockError> {
        let named = self
            .lamp
            .protocol
            .as_ref()
            .and_then(|p| p.preset.as_deref());
        match named {
            Some(name) => LampPreset::from_name(name).ok_or_else(|| {
                MockError::Config(format!(
                    "[lamp.protocol] preset = {name:?} is not simulated: the simulated lamp speaks {}",
                    LampPreset::ALL.map(LampPreset::name).join(", ")
                ))
            }),
            None => Ok(self.mock.as_ref().map(|m| m.lamp.preset).unwrap_or_default()),
        }
    }

    pub fn scene_geometry(&self) -> SceneGeometry {
        let g = &self.geometry;
        SceneGeometry {
            lamp_position_mm: g.lamp_position_mm,
            tile_thickness_mm: g.tile_thickness_mm,
            tile_outline_mm: g.tile_outline_mm.clone(),
            grid_inner_corners: g.grid_inner_corners,
            grid_square_mm: g.grid_square_mm,
            reference: self
                .reference
                .as_ref()
                .map(|r| crate::optics::ReferenceTarget {
                    outline_mm: r.outline_mm.clone(),
                    thickness_mm: r.thickness_mm,
                    albedo: self
                        .mock
                        .as_ref()
                        .and_then(|m| m.reference.as_ref())
                        .map(|t| t.albedo)
                        .unwrap_or(match r.reflectance {
                            OneOrThree::One(v) => [v; 3],
                            OneOrThree::Three(v) => v,
                        }),
                }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const RIG: &str = r#"
[camera]
width = 64
height = 48
[lamp]
port = "/tmp/x/ttyLAMP0"
[geometry]
lamp_position_mm = [100.0, 350.0, 300.0]
tile_thickness_mm = 5.0
tile_outline_mm = [[50.0, 30.0], [150.0, 30.0], [150.0, 130.0]]
grid_inner_corners = [9, 6]
grid_square_mm = 25.0
"#;

    fn load(extra: &str) -> Result<RigFile, MockError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rig.toml");
        std::fs::write(&path, format!("{RIG}{extra}")).unwrap();
        RigFile::load(&path)
    }

    #[test]
    fn the_lamp_preset_comes_from_lamp_protocol_then_mock_lamp() {
        assert_eq!(load("").unwrap().lamp_preset().unwrap(), LampPreset::Glint);
        let mock = "[mock.lamp]\npreset = \"coolled\"\n";
        assert_eq!(
            load(mock).unwrap().lamp_preset().unwrap(),
            LampPreset::Coolled
        );
        // Glint's own keys of [lamp.protocol] are ignored.
        let protocol = "[lamp.protocol]\npreset = \"lumencor\"\nreply_timeout_ms = 300\n";
        assert_eq!(
            load(&format!("{protocol}{mock}"))
                .unwrap()
                .lamp_preset()
                .unwrap(),
            LampPreset::Lumencor
        );
        let other = "[lamp.protocol]\nterminator = \"crlf\"\n";
        assert_eq!(
            load(other).unwrap().lamp_preset().unwrap(),
            LampPreset::Glint
        );
        let e = load("[lamp.protocol]\npreset = \"philips\"\n")
            .unwrap()
            .lamp_preset()
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "[lamp.protocol] preset = \"philips\" is not simulated: the simulated lamp speaks glint, lumencor, coolled"
        );
    }
}
