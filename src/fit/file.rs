//! `fit/fit.json` as every stage after the fit reads it (`glint validate`, `glint report`,
//! `glint export`): one typed file ([`FitFile`], glint-format's, which the writer
//! [`super::run::FitReport::file`] writes too) and one check of it against the session it
//! belongs to ([`Check::check`], with the session's [`Facts`]), so that a file one stage
//! refuses is refused by all of them, with the same one-line error naming the file, the
//! field and what to do.
//!
//! Every field that files written by earlier versions lack is optional, so today's files
//! (relative kd, ks) and older ones load.

use std::collections::HashSet;
use std::path::Path;

use super::model::{Model, Reflectance};
use super::types::{FitError, FORMAT, FORMAT_VERSION};

/// Most candidates a fit.json may list.
pub const MAX_CANDIDATES: usize = 16;
/// Largest |kd|, |ks| accepted (relative units; absolute ones are a few per sr).
pub const MAX_REFLECTANCE: f64 = 1e12;
/// Largest exponent n accepted.
pub const MAX_N: f64 = 1e6;

/// The file's types, one for its writer ([`super::run::FitReport::file`]) and every reader.
pub use glint_format::stage::fit::{
    Absolute, CameraRefined, Candidate, Covariance, FitFile, Intrinsics, Param,
    Reference as ReferenceFactor,
};

/// fit.json's bytes that are not a fit file (the message is one line).
#[derive(Debug, thiserror::Error)]
#[error("not a glint-fit file ({0})")]
pub struct ParseError(String);

/// A candidate's model, as this Glint knows it.
pub trait CandidateModel {
    /// The model (known once [`Check::check`] passed).
    fn model(&self) -> Option<Model>;
}

impl CandidateModel for Candidate {
    fn model(&self) -> Option<Model> {
        Model::ALL.into_iter().find(|m| m.name() == self.model)
    }
}

/// What a fit.json must agree with: the facts of the session it is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Facts {
    /// Samples a pixel of the session's frames: 3 (RGB) or 1 (monochrome).
    pub channels: usize,
}

impl Facts {
    /// The facts of a session, from its manifest.
    pub fn of(m: &crate::session::Manifest) -> Self {
        Facts {
            channels: m.channels() as usize,
        }
    }
}

/// Per channel, the names fit.json uses: "R, G, B" or "Y".
fn channel_words(channels: usize) -> String {
    crate::session::channels_name(channels as u8)
}

/// A list of parameters' problem (None when fine): `need` entries (or none where
/// `optional`), each value present unless `value_optional`, finite values in
/// `0..=max`, sd not negative, the interval's ends in order.
fn params_problem(
    p: &[Param],
    need: usize,
    optional: bool,
    value_optional: bool,
    max: f64,
) -> Option<String> {
    if p.is_empty() && optional {
        return None;
    }
    if p.len() != need {
        return Some(format!(
            "lists {} values but the session's frames have {} (one per channel)",
            p.len(),
            channel_words(need)
        ));
    }
    p.iter().enumerate().find_map(|(i, p)| {
        param_problem(p, value_optional, 0.0, max).map(|e| format!("[{i}]: {e}"))
    })
}

/// One parameter's problem (None when fine): its value present (unless `value_optional`)
/// and within `min..=max`, its sd not negative, its interval's ends in order.
fn param_problem(p: &Param, value_optional: bool, min: f64, max: f64) -> Option<String> {
    match p.value {
        None if !value_optional => return Some("value is missing (null)".into()),
        Some(v) if !(v.is_finite() && v >= min && v <= max) => {
            return Some(format!("value = {v:e} must be in {min}..{max:e}"))
        }
        _ => {}
    }
    if let Some(sd) = p.sd.filter(|s| s.is_nan() || *s < 0.0) {
        return Some(format!(
            "sd = {sd:e} is negative; a standard deviation is not"
        ));
    }
    if let [Some(lo), Some(hi)] = p.ci95 {
        if lo > hi {
            return Some(format!(
                "ci95 = [{lo:e}, {hi:e}] is inverted: its lower end is above its upper"
            ));
        }
    }
    None
}

/// Reading fit.json's bytes, and its check against a session.
pub trait Check: Sized {
    /// Parse fit.json's bytes (no check: [`Check::check`]); the error is one line.
    fn parse(bytes: &[u8]) -> Result<Self, ParseError>;

    /// The first problem of the file for a session with these `facts` (None when it is
    /// usable); see [`FitFile`]'s `impl`.
    fn check(&self, facts: &Facts) -> Option<String>;
}

impl Check for FitFile {
    fn parse(bytes: &[u8]) -> Result<FitFile, ParseError> {
        serde_json::from_slice(bytes).map_err(|e| ParseError(crate::fsx::json_error(&e)))
    }

    /// The first problem of the file for a session with these `facts` (None when it is
    /// usable), one line naming the field and what is wrong: the format (`glint-fit`,
    /// a version this Glint reads), `channels` (1 or 3, the session's), `units`
    /// (`absolute` or `relative`), 1 to 16 candidates of models this Glint knows, none
    /// listed twice, the chosen one among them; per candidate: kd and ks one per channel
    /// (ks may be left out for a model without a lobe), finite, not negative and at most
    /// 1e12, n positive and at most 1e6 for a model with a lobe, every sd not negative and
    /// every 95% interval in order (kd, ks, ks_over_kd, n, the absolute values), the
    /// covariance square over its named parameters with no negative variance; the
    /// reference factor one positive number per channel; the refined camera's pose finite
    /// and bounded.
    fn check(&self, facts: &Facts) -> Option<String> {
        if self.format != FORMAT {
            return Some(format!(
                "format: {} is not `{FORMAT}`",
                crate::fsx::quote(&self.format)
            ));
        }
        if let Some(v) = self.format_version.filter(|v| *v > FORMAT_VERSION) {
            return Some(format!(
                "format_version: {v} is newer than this Glint reads ({FORMAT_VERSION}); update Glint"
            ));
        }
        if !(self.channels == 1 || self.channels == 3) {
            return Some(format!(
                "channels: {} must be 1 (monochrome) or 3 (RGB)",
                self.channels
            ));
        }
        let nc = facts.channels;
        if self.channels != nc {
            return Some(format!(
                "channels: {} but the session's frames have {}",
                self.channels,
                channel_words(nc)
            ));
        }
        if let Some(u) = &self.units {
            if u != "absolute" && u != "relative" {
                return Some(format!(
                    "units: {} must be `absolute` or `relative`",
                    crate::fsx::quote(u)
                ));
            }
        }
        if self.candidates.is_empty() || self.candidates.len() > MAX_CANDIDATES {
            return Some(format!(
                "candidates: {} listed; a fit has 1 to {MAX_CANDIDATES}",
                self.candidates.len()
            ));
        }
        let mut seen = HashSet::new();
        for (i, c) in self.candidates.iter().enumerate() {
            let at = format!("candidates[{i}]");
            let Some(m) = c.model() else {
                return Some(format!(
                    "{at}.model: {} is not a model this Glint knows ({})",
                    crate::fsx::quote(&c.model),
                    Model::ALL.map(|m| m.name()).join(", ")
                ));
            };
            if !seen.insert(m) {
                return Some(format!(
                    "{at}.model: {} is listed twice; a fit lists each model once",
                    m.name()
                ));
            }
            let at = format!("{at} ({})", m.name());
            if let Some(p) = candidate_problem(c, m, nc) {
                return Some(format!("{at}.{p}"));
            }
        }
        if !self.candidates.iter().any(|c| c.model == self.chosen) {
            return Some(format!(
                "chosen: {} is not among the candidates",
                crate::fsx::quote(&self.chosen)
            ));
        }
        if let Some(r) = &self.reference {
            if r.factor.len() != nc
                || r.factor.iter().any(|p| {
                    !p.value
                        .is_some_and(|x| x.is_finite() && x > 0.0 && x < 1e300)
                })
            {
                return Some(format!(
                    "reference.factor: must hold one positive number per channel ({})",
                    channel_words(nc)
                ));
            }
            if let Some((i, p)) = r
                .factor
                .iter()
                .enumerate()
                .find_map(|(i, p)| param_problem(p, false, 0.0, f64::MAX).map(|e| (i, e)))
            {
                return Some(format!("reference.factor[{i}]: {p}"));
            }
        }
        if let Some(c) = &self.camera_refined {
            let pose = crate::calib::camera::Pose {
                rvec: c.rvec,
                t: c.t,
            };
            if !crate::calib::run::pose_is_bounded(&pose)
                || !c.centre_mm.iter().all(|x| x.is_finite() && x.abs() <= 1e9)
            {
                return Some(
                    "camera_refined: rvec, t and centre_mm must be finite and bounded".into(),
                );
            }
        }
        None
    }
}

/// One candidate's problem, starting with the field's name.
fn candidate_problem(c: &Candidate, m: Model, nc: usize) -> Option<String> {
    let lobe = m.has_lobe();
    if let Some(p) = params_problem(&c.kd, nc, false, false, MAX_REFLECTANCE) {
        return Some(format!("kd{p}"));
    }
    if let Some(p) = params_problem(&c.ks, nc, !lobe, !lobe, MAX_REFLECTANCE) {
        return Some(format!("ks{p}"));
    }
    if let Some(p) = params_problem(&c.ks_over_kd, nc, true, true, f64::MAX) {
        return Some(format!("ks_over_kd{p}"));
    }
    match &c.n {
        None if lobe => return Some("n: missing".into()),
        Some(n) => {
            if lobe && !n.value.is_some_and(|v| v > 0.0 && v <= MAX_N) {
                return Some(format!(
                    "n: value = {} must be positive and at most {MAX_N:e}",
                    n.value.map_or("null".into(), |v| format!("{v:e}"))
                ));
            }
            if let Some(p) = param_problem(n, true, f64::MIN, f64::MAX) {
                return Some(format!("n: {p}"));
            }
        }
        None => {}
    }
    if let Some(a) = &c.absolute {
        for (name, list, optional, value_optional) in [
            ("kd_per_sr", &a.kd_per_sr, false, false),
            ("ks_per_sr", &a.ks_per_sr, true, false),
            ("albedo", &a.albedo, true, false),
            ("f0", &a.f0, true, true),
        ] {
            if let Some(p) = params_problem(list, nc, optional, value_optional, MAX_REFLECTANCE) {
                return Some(format!("absolute.{name}{p}"));
            }
        }
    }
    if let Some(cov) = &c.covariance {
        let k = cov.parameters.len();
        if cov.matrix.len() != k || cov.matrix.iter().any(|r| r.len() != k) {
            return Some(format!(
                "covariance: its matrix must be {k}x{k}, one row and column per named parameter"
            ));
        }
        if let Some(i) = (0..k).find(|&i| cov.matrix[i][i].is_some_and(|x| x < 0.0)) {
            return Some(format!(
                "covariance: the variance of {} is negative",
                crate::fsx::quote(&cov.parameters[i])
            ));
        }
    }
    None
}

/// Read and check a session's `fit/fit.json` (`dir`: the session) for a session with
/// these `facts`: size-capped, a regular file, parsed and [`Check::check`]ed. Every
/// error is one line naming the file, the field and "re-run glint fit SESSION".
pub fn load(dir: &Path, facts: &Facts) -> Result<FitFile, FitError> {
    let file = crate::fsx::Within::new(dir, "fit/fit.json");
    let path = file.path();
    let bad = |reason: String| FitError::File {
        path: path.clone(),
        reason: format!("{reason}; re-run glint fit {}", dir.display()),
    };
    if !file.is_there() {
        return Err(FitError::File {
            path: path.clone(),
            reason: format!(
                "missing: fit the session first (glint fit {})",
                dir.display()
            ),
        });
    }
    let bytes = file
        .read(crate::fsx::MAX_TEXT_BYTES)
        .map_err(|e| FitError::File {
            path: path.clone(),
            reason: format!("cannot read ({e})"),
        })?;
    let f = FitFile::parse(&bytes).map_err(|e| bad(e.to_string()))?;
    if let Some(p) = f.check(facts) {
        return Err(bad(p));
    }
    Ok(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fit.json of two candidates (lambert, blinn-phong) for 3 channels.
    fn good() -> serde_json::Value {
        let p = |v: f64| serde_json::json!({"value": v, "sd": 0.01, "ci95": [v - 0.02, v + 0.02]});
        serde_json::json!({
            "format": "glint-fit", "format_version": 1, "channels": 3, "chosen": "blinn-phong",
            "candidates": [
                {"model": "lambert", "kd": [p(0.3), p(0.2), p(0.1)], "ks": [p(0.0), p(0.0), p(0.0)],
                 "n": {"value": null, "sd": null, "ci95": [null, null]}},
                {"model": "blinn-phong", "kd": [p(0.3), p(0.2), p(0.1)], "ks": [p(0.3), p(0.3), p(0.3)],
                 "ks_over_kd": [p(1.0), p(1.5), p(3.0)], "n": p(120.0),
                 "covariance": {"parameters": ["kd_r", "ln_n"], "matrix": [[1e-4, null], [null, 1e-3]]}},
            ],
        })
    }

    /// An edit of a fit.json.
    type Edit = Box<dyn Fn(&mut serde_json::Value)>;

    fn problem(v: &serde_json::Value, channels: usize) -> Option<String> {
        FitFile::parse(&serde_json::to_vec(v).unwrap())
            .unwrap()
            .check(&Facts { channels })
    }

    #[test]
    fn a_good_file_passes_and_each_absurd_field_is_named() {
        assert_eq!(problem(&good(), 3), None);
        let cases: Vec<(Edit, &str)> = vec![
            (
                Box::new(|v| v["candidates"][0]["kd"][0]["value"] = (-1e8).into()),
                "candidates[0] (lambert).kd[0]: value",
            ),
            (Box::new(|v| v["format"] = "x".into()), "format: `x`"),
            (Box::new(|v| v["channels"] = 1.into()), "channels: 1 but"),
            (
                Box::new(|v| v["candidates"][1]["n"]["ci95"] = serde_json::json!([200.0, 100.0])),
                "n: ci95",
            ),
            (
                Box::new(|v| v["candidates"][1]["ks"][2]["sd"] = (-1.0).into()),
                "ks[2]: sd",
            ),
            (
                Box::new(|v| {
                    let c = v["candidates"][1].clone();
                    v["candidates"].as_array_mut().unwrap().push(c)
                }),
                "listed twice",
            ),
            (
                Box::new(|v| v["candidates"][1]["n"]["value"] = 0.0.into()),
                "n: value",
            ),
            (
                Box::new(|v| v["candidates"][1]["covariance"]["matrix"][1][1] = (-1.0).into()),
                "variance of `ln_n`",
            ),
            (
                Box::new(|v| {
                    v["candidates"][1]["covariance"]["matrix"][1] = serde_json::json!([1.0])
                }),
                "covariance: its matrix",
            ),
            (Box::new(|v| v["chosen"] = "ward".into()), "chosen: `ward`"),
            (
                Box::new(|v| v["candidates"][0]["model"] = "ward".into()),
                "candidates[0].model: `ward`",
            ),
            (Box::new(|v| v["units"] = "furlongs".into()), "units"),
            (
                Box::new(|v| v["format_version"] = 2.into()),
                "format_version",
            ),
            (
                Box::new(|v| v["reference"] = serde_json::json!({"factor": [{"value": 1.0}]})),
                "reference.factor",
            ),
        ];
        for (edit, want) in cases {
            let mut v = good();
            edit(&mut v);
            let p = problem(&v, 3).unwrap_or_else(|| panic!("passed: {want}"));
            assert!(
                p.contains(want) && !p.contains('\n'),
                "{p}\nshould contain: {want}"
            );
        }
        // A monochrome session's file has one value each.
        let mut v = good();
        v["channels"] = 1.into();
        for c in v["candidates"].as_array_mut().unwrap() {
            for k in ["kd", "ks", "ks_over_kd"] {
                if let Some(a) = c.get_mut(k).and_then(|x| x.as_array_mut()) {
                    a.truncate(1);
                }
            }
        }
        assert_eq!(problem(&v, 1), None);
        assert!(problem(&v, 3).unwrap().contains("channels: 1 but"));
    }
}
