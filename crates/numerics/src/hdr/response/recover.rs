//! Recovery: every model fitted on the same sample pixels, the simplest whose shape fits the
//! bracket as well as any chosen (the others that fit nearly as well kept as alternatives),
//! then its noise, its misfit and its valid range.

use super::alternatives;
use super::borrow::{borrow_shapes, observed_top, SHAPE_FLOOR};
use super::curve::{
    channel_name, Alternative, Channel, ChoiceReport, Model, ModelChoice, RecoverOptions, Response,
    FORMAT, FORMAT_VERSION,
};
use super::debevec::{debevec_bin, debevec_binned, debevec_channel};
use super::linear::fit_linear;
use super::noise::estimate_noise;
use super::polynomial::fit_polynomial;
use super::samples::{default_samples, select_samples, Samples, MAX_DEBEVEC_SAMPLES};
use super::score::{bic_of, curve_rss, exact_readings, ln_curve, misfit, MisfitBins, NULL_COPIES};
use crate::hdr::bracket::{Bracket, DarkMedian};
use crate::hdr::error::{CurveError, MergeError};

/// Recover the camera response from a bracket (tile frames) and, where there are any,
/// dark frames. Warnings are collected into the result; failures are errors that say
/// what to change.
pub fn recover(
    b: &Bracket,
    darks: &Bracket,
    opts: &RecoverOptions,
) -> Result<Response, MergeError> {
    recover_with(b, &DarkMedian::of_bracket(darks), opts)
}

/// [`recover`] with the dark frames given by their exposures and channel medians (all
/// it needs of them), so that they can be read one at a time
/// ([`super::SessionFrames::dark_medians`]).
#[allow(clippy::needless_range_loop)] // channels index several parallel lists
pub fn recover_with(
    b: &Bracket,
    darks: &[DarkMedian],
    opts: &RecoverOptions,
) -> Result<Response, MergeError> {
    b.check_exposures()?;
    let nf = b.frames.len();
    let max = b.max_value();
    let ln_t: Vec<f64> = b.frames.iter().map(|f| f.exposure_us.ln()).collect();
    let step = b.step();
    let model = opts.model;
    // Debevec's solve grows with the cube of its unknowns (256 + samples); the other
    // models and the noise estimate cost little per sample and are fitted on eight times as
    // many, up to 4800 (their curve error is statistical: for gamma 2.2 with three
    // exposures 1.2% with 600 samples, 0.5% with 2400).
    let n = opts.samples.unwrap_or_else(|| default_samples(nf));
    let n_many = opts.samples.unwrap_or((8 * n).min(4800));
    // Debevec's dense solve has 256 + samples unknowns: more than MAX_DEBEVEC_SAMPLES
    // would take minutes and gigabytes (30 000 took 14 GB and 18 CPU minutes before it
    // was stopped), so it gets at most that many; the other models take them all.
    let n_deb = n.min(MAX_DEBEVEC_SAMPLES);
    if n < 2 {
        return Err(MergeError::Recovery(format!(
            "{n} sample pixels cannot determine a response; use at least 50"
        )));
    }
    // Every bit depth gets every model: a 16-bit camera may apply a tone curve as well as
    // an 8-bit one (measured: a 16-bit gamma camera merged with the linear model it was
    // once given untested was 8.5% off). Above 8 bits Debevec's free curve is solved on
    // 256 bins of values (see [`debevec_binned`]).
    let candidates = candidate_models(model);
    let auto = candidates.len() > 1;
    let mut warnings = Vec::new();
    if candidates.contains(&Model::Debevec) && n_deb < n {
        warnings.push(format!(
            "the Debevec curve is solved on {n_deb} sample pixels per channel, not {n} (its solve grows with the cube of them); the other models use all {n}"
        ));
    }
    let mut fitted: Vec<Fitted> = candidates.iter().map(|m| Fitted::new(*m)).collect();
    let mut samples = Vec::with_capacity(b.channels);
    // Where each channel clips (below the format's top on some cameras): one pass.
    let clips = b.clip_levels();
    for c in 0..b.channels {
        let s = select_samples(b, c, n_many, clips[c]);
        let s_deb = if candidates.contains(&Model::Debevec) && n_deb < n_many {
            select_samples(b, c, n_deb, clips[c])
        } else {
            s.clone()
        };
        let name = channel_name(b.channels, c);
        if s.values.len() < n {
            warnings.push(format!(
                "channel {name}: only {} usable sample pixels (asked for {n}); the scene has little texture or most pixels are saturated or black",
                s.values.len()
            ));
        }
        if s.values.len() < 10 {
            return Err(MergeError::Recovery(format!(
                "channel {name}: only {} pixels have two or more readings between black and saturation; check the exposures span the scene",
                s.values.len()
            )));
        }
        let input = ChannelInput {
            s: &s,
            s_deb: &s_deb,
            ln_t: &ln_t,
            step,
            max,
            name,
        };
        fit_models(&mut fitted, &input, b, darks, opts, c);
        // Score every model that fitted on the same readings: those all of them call valid.
        if auto {
            score_models(&mut fitted, &input, c);
        }
        samples.push(s);
    }
    let usable: Vec<&Fitted> = fitted.iter().filter(|f| f.failed.is_none()).collect();
    let best = choose(&fitted)?;
    let chosen = best.model;
    let choice = auto.then(|| ChoiceReport {
        bic: usable.iter().map(|f| (f.model, f.bic)).collect(),
        misfit: usable.iter().map(|f| (f.model, f.misfit)).collect(),
        chosen,
    });
    let alternatives = if auto {
        alternatives_of(&fitted, best)
    } else {
        Vec::new()
    };
    let mut channels = best.channels.clone();
    // A channel known only to mid-scale where another is known to the top: that one's
    // shape above (see [`borrow_shapes`]); the fit's own warnings about the range it
    // ended at no longer hold for it.
    let tops: Vec<Option<u32>> = samples.iter().map(|s| observed_top(s, max)).collect();
    let borrowed = borrow_shapes(&mut channels, &tops, max, &mut warnings);
    let mut best_warnings = best.warnings.clone();
    for bw in &borrowed {
        let name = channel_name(b.channels, bw.channel);
        best_warnings.retain(|w| {
            !(w.starts_with(&format!(
                "channel {name}: the curve is well determined only"
            )) || w.starts_with(&format!(
                "channel {name}: the polynomial curve is usable only"
            )))
        });
    }
    // A camera that clips below its format's top: its valid range ends below the clip.
    for (c, ch) in channels.iter_mut().enumerate() {
        let sat = clips[c];
        if sat < max && ch.valid_max >= sat {
            tracing::info!(
                "channel {}: the camera clips at value {sat}, below {max}: readings from there up count as saturated",
                channel_name(b.channels, c)
            );
            ch.valid_max = sat - 1;
            ch.valid_min = ch.valid_min.min(ch.valid_max.saturating_sub(1));
        }
    }
    warnings.extend(best_warnings);
    if auto {
        for f in &fitted {
            if let Some(e) = &f.failed {
                tracing::info!("{} model not used: {e}", f.model.as_str());
            }
        }
    }
    let mut r = Response {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        model: chosen,
        bit_depth: b.bit_depth,
        camera: None,
        recovered_from: String::new(),
        lambda: opts.lambda,
        choice,
        channels,
        alternatives,
        warnings: Vec::new(),
    };
    for c in estimate_noise(&mut r, b, &samples) {
        warnings.push(format!(
            "channel {}: its noise could not be measured (too few sample pixels read in two exposures within its curve's range, or none scattering beyond the quantisation), so it takes the other channels' (shot {:.3e}, read {:.3e} in exposure units); add exposures between the bracket's, one stop apart",
            r.channel_name(c),
            r.channels[c].noise.shot,
            r.channels[c].noise.read
        ));
    }
    settle_misfit(&mut r, &samples, &ln_t, chosen, &mut warnings);
    // A borrowed shape may miss by what the two channels disagree where both are known.
    for bw in &borrowed {
        let ch = &mut r.channels[bw.channel];
        ch.misfit_sd = ch.misfit_sd.max(bw.disagreement.max(SHAPE_FLOOR));
    }
    // Too dark: readings within three read-noise standard deviations of black.
    for c in 0..r.channels.len() {
        let floor = 3.0 * r.channels[c].noise.read.sqrt();
        let hi = r.channels[c].valid_max;
        while r.channels[c].valid_min < hi && r.exposure(c, r.channels[c].valid_min as f64) <= floor
        {
            r.channels[c].valid_min += 1;
        }
        // No value left between too dark and the curve's top: a response every reader
        // would refuse, so none is written.
        if r.channels[c].valid_min >= hi {
            return Err(MergeError::Recovery(format!(
                "channel {}: no value of the curve carries radiance (every one is within three read-noise standard deviations of black or beyond the curve's valid range, which ends at {hi}); add exposures between the bracket's (steps of a stop), several frames per exposure or more light",
                r.channel_name(c)
            )));
        }
    }
    // Very noisy readings bias any curve fitted to them (the noise is in the pixel values,
    // the regressor): say so when one reading at a quarter of the range is noisier than 5%.
    for c in 0..r.channels.len() {
        let z = (r.max_value() / 4) as f64;
        let e = r.exposure(c, z);
        let rel = r.exposure_variance(c, z).sqrt() / e;
        if e > 0.0 && rel > 0.05 {
            warnings.push(format!(
                "channel {}: single readings are {:.0}% noisy at value {z} (read noise), which biases the curve; take several frames per exposure (a rig's bracket.frames_per_exposure; imported photos: several photos at each time) or more light",
                r.channel_name(c),
                100.0 * rel
            ));
        }
    }
    r.warnings = warnings;
    Ok(r)
}

/// The models to fit for what the user asks for.
fn candidate_models(model: ModelChoice) -> Vec<Model> {
    match model {
        ModelChoice::Auto => vec![Model::Linear, Model::Polynomial, Model::Debevec],
        ModelChoice::Linear => vec![Model::Linear],
        ModelChoice::Polynomial => vec![Model::Polynomial],
        ModelChoice::Debevec => vec![Model::Debevec],
    }
}

/// One candidate model's fit: its channels, its warnings, its BIC (summed over channels)
/// or the reason it failed.
struct Fitted {
    model: Model,
    channels: Vec<Channel>,
    warnings: Vec<String>,
    bic: f64,
    failed: Option<CurveError>,
    /// Largest misfit beyond the noise over the channels (see [`misfit`]).
    misfit: f64,
    /// Each channel's misfit beyond the noise, on the readings every model calls valid.
    channel_misfit: Vec<f64>,
}

impl Fitted {
    fn new(model: Model) -> Self {
        Fitted {
            model,
            channels: Vec::new(),
            warnings: Vec::new(),
            bic: 0.0,
            failed: None,
            misfit: 0.0,
            channel_misfit: Vec::new(),
        }
    }
}

/// One channel's sample pixels (`s_deb`: those for the Debevec curve) and what every fit
/// of it needs.
struct ChannelInput<'a> {
    s: &'a Samples,
    s_deb: &'a Samples,
    ln_t: &'a [f64],
    step: Option<f64>,
    max: u32,
    name: &'static str,
}

/// Fit channel `c` with every candidate that has not failed yet; one that fails is out.
fn fit_models(
    fitted: &mut [Fitted],
    input: &ChannelInput,
    b: &Bracket,
    darks: &[DarkMedian],
    opts: &RecoverOptions,
    c: usize,
) {
    let ChannelInput {
        s,
        s_deb,
        ln_t,
        step,
        max,
        name,
    } = *input;
    for f in fitted.iter_mut().filter(|f| f.failed.is_none()) {
        let res = match f.model {
            Model::Linear => fit_linear(s, b, darks, c, max),
            Model::Debevec if max > 255 => {
                debevec_binned(s_deb, ln_t, max, opts, name, &mut f.warnings)
            }
            Model::Debevec => debevec_channel(s_deb, ln_t, max, opts, name, &mut f.warnings),
            Model::Polynomial => fit_polynomial(s, ln_t, step, max, name, &mut f.warnings),
        };
        match res {
            Ok(ch) => f.channels.push(ch),
            Err(e) => f.failed = Some(e),
        }
    }
}

/// Score every model that fitted channel `c` on the same readings, those all of them
/// call valid: its BIC, and its misfit beyond the noise.
fn score_models(fitted: &mut [Fitted], input: &ChannelInput, c: usize) {
    let ChannelInput { s, ln_t, max, .. } = *input;
    let ok: Vec<&Fitted> = fitted.iter().filter(|f| f.failed.is_none()).collect();
    let lo = ok
        .iter()
        .map(|f| f.channels[c].valid_min)
        .max()
        .unwrap_or(1);
    let hi = ok
        .iter()
        .map(|f| f.channels[c].valid_max)
        .min()
        .unwrap_or(max - 1);
    for f in fitted.iter_mut().filter(|f| f.failed.is_none()) {
        let ch = &f.channels[c];
        let curve = |z: u16| ln_curve(f.model, ch, z);
        let (rss, rows) = curve_rss(&curve, s, ln_t, lo, hi, max);
        let params = match f.model {
            Model::Linear => 1,
            Model::Polynomial => ch.coefficients.len(),
            // One free value a bin (256 bins above 8 bits).
            Model::Debevec => ((ch.valid_max - ch.valid_min) as usize).div_ceil(debevec_bin(max)),
        } + s.values.len();
        f.bic += bic_of(rss, rows, params);
        let bins = MisfitBins::new(lo, hi, max);
        let m = misfit(&curve, s, ln_t, &bins, None).0;
        f.misfit = f.misfit.max(m);
        f.channel_misfit.push(m);
    }
}

/// The model chosen among those that fitted every channel; refused, with the first
/// model's reason, where none did.
fn choose(fitted: &[Fitted]) -> Result<&Fitted, MergeError> {
    let usable: Vec<&Fitted> = fitted.iter().filter(|f| f.failed.is_none()).collect();
    // The simplest model whose curve fits the bracket's ratios as well as any: its misfit
    // (the binned mean residual, the curve's shape error the bracket can see) within
    // EQUIVALENT of the lowest. Not BIC over the readings: with the hundreds of thousands
    // of readings of a 16-bit bracket, BIC rewards a curve that bends to absorb the noise
    // model's own small errors (read noise clipped at 0, a demosaicked camera's
    // interpolated readings) even where its shape is worse: a linear 16-bit Bayer camera
    // got a polynomial by 1 900 in BIC whose misfit was 0.74% against the linear curve's
    // 0.28%, and whose merge was 1.8% off the true radiance against 0.6%.
    // Ties in misfit go to the simpler model: linear, then polynomial, then the free
    // Debevec curve.
    let rank = |m: Model| match m {
        Model::Linear => 0,
        Model::Polynomial => 1,
        Model::Debevec => 2,
    };
    let lowest = usable
        .iter()
        .map(|f| f.misfit)
        .filter(|m| m.is_finite())
        .fold(f64::INFINITY, f64::min);
    let Some(best) = usable
        .iter()
        .filter(|f| f.misfit <= lowest + EQUIVALENT || !lowest.is_finite())
        .min_by_key(|f| rank(f.model))
        .copied()
    else {
        // Every candidate failed: the (first) reason.
        return Err(match fitted[0].failed.clone() {
            Some(e) => MergeError::Curve(e),
            None => MergeError::Recovery(String::new()),
        });
    };
    Ok(best)
}

/// The other fitted models' curves, per channel where they fit the readings about as well
/// as the chosen one ([`alternatives::plausible`]), as changes from it.
fn alternatives_of(fitted: &[Fitted], best: &Fitted) -> Vec<Alternative> {
    fitted
        .iter()
        .filter(|f| f.failed.is_none() && f.model != best.model)
        .filter_map(|f| {
            let channels: Vec<Vec<(u32, f64)>> = (0..best.channels.len())
                .map(|c| {
                    let (Some(a), Some(m)) = (f.channel_misfit.get(c), best.channel_misfit.get(c))
                    else {
                        return Vec::new();
                    };
                    if !alternatives::plausible(*a, *m) {
                        return Vec::new();
                    }
                    match (best.channels.get(c), f.channels.get(c)) {
                        (Some(b), Some(a)) => alternatives::shape_change(best.model, b, f.model, a),
                        _ => Vec::new(),
                    }
                })
                .collect();
            channels
                .iter()
                .any(|c| !c.is_empty())
                .then_some(Alternative {
                    model: f.model,
                    channels,
                })
        })
        .collect()
}

/// Each channel's misfit beyond the noise, kept with its curve, and for the linear model a
/// warning where it is large.
fn settle_misfit(
    r: &mut Response,
    samples: &[Samples],
    ln_t: &[f64],
    chosen: Model,
    warnings: &mut Vec<String>,
) {
    let max = r.max_value();
    // The curve's misfit beyond the noise, whatever the model: kept with the curve (its
    // draws carry it into the fit's intervals) and, for the linear model, a warning that
    // names it (a camera with a tone curve taken for linear: the noise model absorbs the
    // misfit and hides it).
    for (c, s) in samples.iter().enumerate() {
        let ch = &r.channels[c];
        let curve = |z: u16| ln_curve(chosen, ch, z);
        let bins = MisfitBins::new(ch.valid_min, ch.valid_max, max);
        let null = exact_readings(&curve, ch.noise, s, ln_t, &bins, NULL_COPIES, c as u64);
        let (sd, worst) = misfit(&curve, s, ln_t, &bins, Some(&null));
        if chosen == Model::Linear && sd > LINEAR_MISFIT {
            let at = worst
                .map(|(z, m)| format!(", {:.1}% at value {z}", 100.0 * m.abs()))
                .unwrap_or_default();
            warnings.push(format!(
                "channel {}: the linear response misses its data by {:.1}% (rms over values{at}): the camera is not linear (a tone curve?); recover with --model auto or polynomial",
                r.channel_name(c),
                100.0 * sd
            ));
        }
        r.channels[c].misfit_sd = sd;
    }
}

/// Misfit beyond the noise (rms, ln E) below which a model explains the data as well as
/// any (see [`recover`]).
const EQUIVALENT: f64 = 0.0025;

/// Misfit (rms, ln E) above which a linear response is reported as not linear.
const LINEAR_MISFIT: f64 = 0.005;

#[cfg(test)]
mod tests {
    use super::*;

    fn scored(model: Model, bic: f64, misfit: f64) -> Fitted {
        Fitted {
            bic,
            misfit,
            ..Fitted::new(model)
        }
    }

    #[test]
    fn the_simplest_curve_whose_shape_fits_as_well_as_any_is_chosen_not_the_lowest_bic() {
        // A linear 16-bit Bayer camera of the second scene family: the polynomial wins BIC
        // by 1 900 with a worse shape (misfit 0.74% against 0.28%): linear.
        let f = [
            scored(Model::Linear, 289_575.1, 0.00283),
            scored(Model::Polynomial, 287_683.9, 0.00738),
            scored(Model::Debevec, 292_527.6, 0.00462),
        ];
        assert_eq!(choose(&f).unwrap().model, Model::Linear);
        // A tone curve: linear misses by 30%, the polynomial by 0.94%, Debevec's free curve
        // by 0.015%: Debevec.
        let f = [
            scored(Model::Linear, 34_653.6, 0.2993),
            scored(Model::Polynomial, 32_324.1, 0.0094),
            scored(Model::Debevec, 32_430.7, 0.00015),
        ];
        assert_eq!(choose(&f).unwrap().model, Model::Debevec);
        // Shapes within 0.25% of each other: the simpler, whatever BIC says.
        let f = [
            scored(Model::Linear, 1000.0, 0.2),
            scored(Model::Polynomial, 500.0, 0.0030),
            scored(Model::Debevec, 400.0, 0.0010),
        ];
        assert_eq!(choose(&f).unwrap().model, Model::Polynomial);
        // A failed model is never chosen.
        let mut f = [
            scored(Model::Linear, 0.0, 0.0),
            scored(Model::Polynomial, 500.0, 0.0030),
        ];
        f[0].failed = Some(CurveError::NothingAboveBlack {
            channel: "R".into(),
            black: 64.0,
        });
        assert_eq!(choose(&f).unwrap().model, Model::Polynomial);
    }
}
