//! The response curve as stored and used: its models, channels and noise, the options a
//! recovery takes, and what a curve gives a reading (exposure, slope, variance, the inverse).

use serde::{Deserialize, Serialize};

/// Name of the response file format.
pub const FORMAT: &str = "glint-response";
pub const FORMAT_VERSION: u32 = 1;
/// Channel names in storage order.
pub const CHANNELS: [&str; 3] = ["R", "G", "B"];

/// The name of channel `c` of an image with `channels` samples a pixel: R, G, B, or Y
/// (luminance) for a monochrome camera's one channel.
pub fn channel_name(channels: usize, c: usize) -> &'static str {
    if channels == 1 {
        "Y"
    } else {
        CHANNELS[c]
    }
}

/// Which response model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Model {
    Debevec,
    /// ln E a polynomial (Chebyshev basis) in ln z of a degree chosen by BIC.
    Polynomial,
    Linear,
}

impl Model {
    pub fn as_str(self) -> &'static str {
        match self {
            Model::Debevec => "debevec",
            Model::Polynomial => "polynomial",
            Model::Linear => "linear",
        }
    }
}

/// What the user asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelChoice {
    /// Fit every model (any bit depth) and keep the simplest whose shape fits as well as any.
    Auto,
    Debevec,
    Polynomial,
    Linear,
}

/// Shot + read noise in exposure units: var(E) = shot x E + read.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Noise {
    pub shot: f64,
    pub read: f64,
}

/// One channel's curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Channel {
    /// Debevec: ln E for every pixel value (empty for the linear model).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ln_exposure: Vec<f64>,
    /// Debevec: standard deviation of ln E at each value, relative to the gauge value
    /// (how well the data determine the curve there).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ln_exposure_sd: Vec<f64>,
    /// Polynomial: the degree chosen and the coefficients (Chebyshev, in u linear in ln z
    /// from -1 at z = ceil(max / 64) to 1 at z = max - 1, gauge removed).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub coefficients: Vec<f64>,
    /// Polynomial: the coefficients' covariance, so that later stages can carry the
    /// curve's uncertainty into theirs (see [`Response::draw`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub coefficient_covariance: Vec<Vec<f64>>,
    /// Linear: E = (z - black) x gain.
    #[serde(default)]
    pub black: f64,
    #[serde(default)]
    pub gain: f64,
    /// Values in `valid_min..=valid_max` carry radiance; below is too dark, above saturated.
    pub valid_min: u32,
    pub valid_max: u32,
    pub noise: Noise,
    /// Residual of the fit, rms, in ln E (Debevec) or values (linear).
    pub rms_residual: f64,
    /// How far the curve misses its data beyond their noise, rms over the valid values, in
    /// ln E: the mean residual in bins of values, less what the readings' scatter explains
    /// (see [`misfit`]). The curve's systematic error that no covariance of its own
    /// parameters holds; [`Response::draws_at`] draws it too.
    #[serde(default)]
    pub misfit_sd: f64,
    /// Sample pixels used.
    pub samples: usize,
}

/// The largest |ln E| a response table holds (e^700 is near the largest f64); response
/// files with more are refused.
pub const LN_EXPOSURE_LIMIT: f64 = 700.0;

/// Make `g` rise strictly, each value that does not exceed the one before it lifted to
/// that one plus the least step (1e-9): what every reader of a response requires over its
/// valid range, after a fix-up (isotonic regression, a blend) left flat or slightly
/// falling steps.
pub(super) fn rise_strictly(g: &mut [f64]) {
    for z in 1..g.len() {
        if g[z] <= g[z - 1] {
            g[z] = g[z - 1] + 1e-9;
        }
    }
}

impl Channel {
    /// A table channel (Debevec or polynomial); the noise model is filled in later.
    pub(super) fn table(
        ln_exposure: Vec<f64>,
        ln_exposure_sd: Vec<f64>,
        coefficients: Vec<f64>,
        (lo, hi): (usize, usize),
        rms_residual: f64,
        samples: usize,
    ) -> Self {
        // Outside the valid range a curve is only continued (nothing is read from it
        // there), and a steep dark end continued in a straight line can run past what a
        // response file may hold (|ln E| <= LN_EXPOSURE_LIMIT; a polynomial reached -2367
        // at value 0 on a second scene family's bracket, seed 10085, and the session's own
        // response.json was then refused by every later stage).
        let ln_exposure = ln_exposure
            .into_iter()
            .map(|x| x.clamp(-LN_EXPOSURE_LIMIT, LN_EXPOSURE_LIMIT))
            .collect();
        Channel {
            ln_exposure,
            ln_exposure_sd,
            coefficients,
            coefficient_covariance: Vec::new(),
            black: 0.0,
            gain: 0.0,
            valid_min: lo as u32,
            valid_max: hi as u32,
            noise: Noise {
                shot: 0.0,
                read: 0.0,
            },
            rms_residual,
            misfit_sd: 0.0,
            samples,
        }
    }
}

/// A camera response, one entry in `channels` per channel of the camera's frames: three
/// (R, G, B), or one (Y) for a monochrome camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Response {
    pub format: String,
    pub format_version: u32,
    pub model: Model,
    pub bit_depth: u8,
    /// The camera this belongs to (its model string), where known.
    #[serde(default)]
    pub camera: Option<String>,
    /// Where it was recovered (a session path), for the record.
    #[serde(default)]
    pub recovered_from: String,
    /// Smoothness weight used (Debevec).
    #[serde(default)]
    pub lambda: f64,
    /// Why the other model was not chosen, and the criterion values.
    #[serde(default)]
    pub choice: Option<ChoiceReport>,
    pub channels: Vec<Channel>,
    /// The other models' curves that fit the bracket nearly as well (per channel; see
    /// [`super::alternatives`]): what they disagree on the fit counts as the response's
    /// uncertainty. Empty where only one model was fitted or none came near.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub alternatives: Vec<Alternative>,
    /// Warnings raised while recovering.
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// Another model's curve that fits the bracket nearly as well as the chosen one, kept as its
/// change in ln E ([`super::alternatives`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Alternative {
    pub model: Model,
    /// Per channel: (value, change of ln E from the chosen curve to this one) at values
    /// even in ln z over the range where both curves are valid, the mean change removed (a
    /// constant is a scale every relative result leaves out). Empty for a channel where
    /// this model misses the bracket clearly more than the chosen one.
    pub channels: Vec<Vec<(u32, f64)>>,
}

/// How every model fitted scored on the same readings: BIC (lower is better, summed over
/// the channels, for the record) and the misfit the choice goes by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChoiceReport {
    pub bic: Vec<(Model, f64)>,
    /// Each model's misfit beyond the noise (rms ln E, the largest over the channels, on the
    /// readings every model calls valid): what the choice goes by (the simplest within
    /// 0.25% of the lowest). Empty in files written before 2026-12-08.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub misfit: Vec<(Model, f64)>,
    pub chosen: Model,
}

impl Response {
    /// Standard deviation of ln E at each of `values[c]` for channel `c`: what the fit's
    /// curve draws carry ([`Response::draws_for_bracket`], with the bracket's step where
    /// known), a Debevec curve's own `ln_exposure_sd`, and the top's shape allowance
    /// ([`Response::top_sd`]), added as independent variances. Zeros where there is none
    /// of these (a linear curve that fits its data: its gain is a scale, which every
    /// relative result leaves out).
    pub fn ln_sd_at(&self, values: &[Vec<u32>], step: Option<f64>) -> Vec<Vec<f64>> {
        let drawn = self.draws_for_bracket(values, step).map(|d| d.sd());
        values
            .iter()
            .enumerate()
            .map(|(c, vals)| {
                vals.iter()
                    .enumerate()
                    .map(|(i, &z)| {
                        let mut var = drawn
                            .as_ref()
                            .and_then(|d| d.get(c))
                            .and_then(|d| d.get(i))
                            .map_or(0.0, |s| s * s);
                        if let Some(sd) = self
                            .channels
                            .get(c)
                            .and_then(|ch| ch.ln_exposure_sd.get(z as usize))
                        {
                            var += sd * sd;
                        }
                        let top = self.top_sd(z as f64);
                        (var + top * top).sqrt()
                    })
                    .collect()
            })
            .collect()
    }

    /// Channels of the frames this response is for: 3 (RGB) or 1 (monochrome).
    pub fn channel_count(&self) -> usize {
        self.channels.len()
    }

    /// The name of channel `c` (R, G, B, or Y for a monochrome camera).
    pub fn channel_name(&self, c: usize) -> &'static str {
        channel_name(self.channels.len(), c)
    }

    /// Largest pixel value.
    pub fn max_value(&self) -> u32 {
        (1u32 << self.bit_depth) - 1
    }

    /// Relative exposure for value `z` (any z: outside the valid range the value is the
    /// curve's extrapolation and must not be used as a measurement).
    pub fn exposure(&self, c: usize, z: f64) -> f64 {
        let ch = &self.channels[c];
        match self.model {
            Model::Linear => (z - ch.black) * ch.gain,
            Model::Debevec | Model::Polynomial => interp(&ch.ln_exposure, z).exp(),
        }
    }

    /// Derivative dE/dz.
    pub fn slope(&self, c: usize, z: f64) -> f64 {
        let ch = &self.channels[c];
        match self.model {
            Model::Linear => ch.gain,
            Model::Debevec | Model::Polynomial => {
                let zi = z.round().clamp(0.0, (ch.ln_exposure.len() - 1) as f64) as usize;
                let lo = zi.saturating_sub(1);
                let hi = (zi + 1).min(ch.ln_exposure.len() - 1);
                let d = (ch.ln_exposure[hi] - ch.ln_exposure[lo]) / (hi - lo) as f64;
                d * self.exposure(c, z)
            }
        }
    }

    /// Variance of the exposure a reading `z` stands for: shot + read noise, the
    /// quantisation of one step of the curve, and the curve's shape near the top
    /// ([`Response::top_sd`]).
    pub fn exposure_variance(&self, c: usize, z: f64) -> f64 {
        self.reading_variance(c, z, self.exposure(c, z), self.slope(c, z))
    }

    /// [`Response::exposure_variance`] with the exposure `e` and the curve's slope `s` at
    /// `z` given (the merge's response draws move both).
    pub fn reading_variance(&self, c: usize, z: f64, e: f64, s: f64) -> f64 {
        let ch = &self.channels[c];
        let e = e.max(0.0);
        let top = self.top_sd(z) * e;
        ch.noise.shot * e + ch.noise.read + s * s / 12.0 + top * top
    }

    /// Relative sd of a fitted curve's shape at value `z` near the top of the range: 0 for a
    /// linear curve and below TOP_FROM of full scale, rising as the square to TOP_SD at full
    /// scale. In the merge it makes a reading near the top count less where the same pixel
    /// is read lower on the curve at another exposure (and count, with its wider variance,
    /// where it is not). Why: a fitted curve's top is its weakest part (few readings, and
    /// those dropped by their own value as they cross the saturation limit bias the rest
    /// low), and a bracket cannot see an error there that moves every reading of a pixel
    /// alike. On the simulated family 8-bit EMoR curves were recovered 0.2-0.4% low at 0.95
    /// of full scale and 0.7-1.1% at 0.98, within 0.1% below 0.9; an n = 63 tile read its
    /// highlight there and n came out +4.2% (3.1 sd), +0.5% with readings above 0.8 left out;
    /// with TOP_SD 1% +3.3% (2.8 sd), with 3% +2.1% (1.8 sd), and no scene of 200 worse.
    pub fn top_sd(&self, z: f64) -> f64 {
        if self.model == Model::Linear {
            return 0.0;
        }
        let t = ((z / self.max_value() as f64 - TOP_FROM) / (1.0 - TOP_FROM)).clamp(0.0, 1.0);
        TOP_SD * t * t
    }

    /// Inverse response: the pixel value (fractional, before rounding) a camera with this
    /// response shows for relative exposure `e` = radiance x time. Clamped to 0..max.
    pub fn value(&self, c: usize, e: f64) -> f64 {
        let ch = &self.channels[c];
        let max = self.max_value() as f64;
        match self.model {
            Model::Linear => (e / ch.gain + ch.black).clamp(0.0, max),
            Model::Debevec | Model::Polynomial => {
                if e <= 0.0 {
                    return 0.0;
                }
                let l = e.ln();
                let g = &ch.ln_exposure;
                // g is increasing over the valid range; search the whole table for the
                // bracketing pair with a monotone envelope.
                let lo = ch.valid_min as usize;
                let hi = ch.valid_max as usize;
                if l <= g[lo] {
                    // Below the valid range: follow the table down to 0.
                    for z in (0..lo).rev() {
                        if l >= g[z] && g[z + 1] > g[z] {
                            return z as f64 + (l - g[z]) / (g[z + 1] - g[z]);
                        }
                    }
                    return 0.0;
                }
                if l >= g[hi] {
                    for z in hi..g.len() - 1 {
                        if l <= g[z + 1] && g[z + 1] > g[z] {
                            return z as f64 + (l - g[z]) / (g[z + 1] - g[z]);
                        }
                    }
                    return max;
                }
                let (mut a, mut b) = (lo, hi);
                while b - a > 1 {
                    let m = (a + b) / 2;
                    if g[m] <= l {
                        a = m;
                    } else {
                        b = m;
                    }
                }
                a as f64 + (l - g[a]) / (g[b] - g[a])
            }
        }
    }

    /// The response's values as a 256-row (or 2^bits-row for linear 16-bit: 256 evenly
    /// spaced rows) table of relative exposure per channel, for CSV and plots.
    pub fn table(&self) -> Vec<(u32, Vec<f64>)> {
        let max = self.max_value();
        let step = if max > 255 { (max + 1) / 256 } else { 1 };
        (0..=max)
            .step_by(step as usize)
            .map(|z| {
                (
                    z,
                    (0..self.channels.len())
                        .map(|c| self.exposure(c, z as f64))
                        .collect(),
                )
            })
            .collect()
    }
}

/// Where a fitted curve's top begins (a fraction of full scale) and its shape's relative sd
/// at full scale ([`Response::top_sd`]).
const TOP_FROM: f64 = 0.8;
const TOP_SD: f64 = 0.03;

/// Linear interpolation in a table indexed by value.
pub(super) fn interp(t: &[f64], z: f64) -> f64 {
    let z = z.clamp(0.0, (t.len() - 1) as f64);
    let i = (z.floor() as usize).min(t.len() - 2);
    let f = z - i as f64;
    t[i] * (1.0 - f) + t[i + 1] * f
}

/// Options for recovery.
#[derive(Debug, Clone)]
pub struct RecoverOptions {
    pub model: ModelChoice,
    /// Smoothness weight (Debevec), in the units of Debevec & Malik / OpenCV.
    pub lambda: f64,
    /// Sample pixels per channel; `None` chooses from the number of exposures.
    pub samples: Option<usize>,
    /// Largest standard deviation of ln E (relative to the gauge) a value may have and
    /// still count as determined by the data.
    pub max_sd: f64,
}

impl Default for RecoverOptions {
    fn default() -> Self {
        RecoverOptions {
            model: ModelChoice::Auto,
            lambda: 10.0,
            samples: None,
            max_sd: 0.03,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Channel, LN_EXPOSURE_LIMIT};

    #[test]
    fn a_table_continued_past_what_a_response_file_holds_is_clamped_outside_its_range() {
        // A steep dark end continued in a straight line (seed 10085 of the second scene
        // family reached -2367 at value 0); the valid range 9..254 is kept as it was.
        let mut g: Vec<f64> = (0..256).map(|z| -4.0 + 0.02 * z as f64).collect();
        g[0] = -2367.2;
        g[1] = -1672.6;
        g[255] = 1e6;
        let ch = Channel::table(g.clone(), vec![0.01; 256], Vec::new(), (9, 254), 0.01, 100);
        assert!(ch
            .ln_exposure
            .iter()
            .all(|x| x.is_finite() && x.abs() <= LN_EXPOSURE_LIMIT));
        assert_eq!(ch.ln_exposure[0], -LN_EXPOSURE_LIMIT);
        assert_eq!(ch.ln_exposure[9..=254], g[9..=254]);
        assert_eq!((ch.valid_min, ch.valid_max), (9, 254));
    }
}
