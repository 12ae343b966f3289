//! One type per stage file, used by the stage that writes the file and by every stage that
//! reads it, so that a field exists once and a renamed field fails to compile in every
//! reader (a reader of `serde_json::Value` would read `null` and go on).
//!
//! The types are plain data: numbers, strings, lists. Every number that may be absent or
//! not finite is an `Option<f64>`: `serde_json` writes a NaN or an infinity as `null`, so a
//! writer that gives `None` there writes the same bytes, and a reader gets `None` back
//! where the file has `null` (a round trip, `serialize(deserialize(file)) == file`, keeps
//! every byte). Fields that files written by earlier versions lack are `#[serde(default)]`,
//! so those files still load.
//!
//! - [`hdr`], `hdr/summary.json` (the radiance summary);
//! - [`camera`], `calib/camera.json`;
//! - [`fit`], `fit/fit.json`;
//! - [`validation`], `validation/validation.json`.

pub mod camera;
pub mod fit;
pub mod hdr;
pub mod validation;

/// A finite number as a file holds it: `None` for NaN and the infinities (written `null`).
pub fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// Deserializers that read a field as a reader of `serde_json::Value` would: a field of
/// another kind than expected is `None` (a list: the entries of the expected kind), not an
/// error.
pub mod lenient {
    use serde::{Deserialize, Deserializer};
    use serde_json::Value;

    /// A number (`as_f64`).
    pub fn num<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        Ok(Value::deserialize(d)?.as_f64())
    }

    /// A count (`as_u64`).
    pub fn count<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
        Ok(Value::deserialize(d)?.as_u64())
    }

    /// A string (`as_str`).
    pub fn text<'de, D: Deserializer<'de>>(d: D) -> Result<Option<String>, D::Error> {
        Ok(Value::deserialize(d)?.as_str().map(String::from))
    }

    /// A list of numbers (None when not a list; an entry that is not a number, None).
    pub fn nums<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Vec<Option<f64>>>, D::Error> {
        Ok(Value::deserialize(d)?
            .as_array()
            .map(|a| a.iter().map(Value::as_f64).collect()))
    }

    /// The strings of a list (entries of other kinds left out; not a list: none).
    pub fn texts<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
        Ok(Value::deserialize(d)?
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|x| x.as_str().map(String::from))
                    .collect()
            })
            .unwrap_or_default())
    }

    /// The HDR summary's response source (not an object: unknown).
    pub fn response<'de, D: Deserializer<'de>>(
        d: D,
    ) -> Result<super::hdr::ResponseSource, D::Error> {
        let v = Value::deserialize(d)?;
        Ok(super::hdr::ResponseSource {
            kind: v.get("kind").and_then(Value::as_str).map(String::from),
            path: v.get("path").and_then(Value::as_str).map(String::from),
        })
    }
}
