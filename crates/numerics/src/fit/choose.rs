//! Model choice: fit every candidate on the fitting samples, score each on held-out
//! samples of the same tile, and keep the simplest whose held-out error is within the
//! noise of the best ("model no more than the tile needs"); a model of as many parameters
//! that assumes more is taken only where the same held-out samples show it better beyond
//! their paired noise.

use serde::{Deserialize, Serialize};

use super::model::{Model, Reflectance};
use super::solve::{fit, measured_values, weights, ModelFit, Options, Sample};

/// One candidate's scores.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Scored<M = Model> {
    pub fit: ModelFit<M>,
    /// Parameters fitted (kd per channel, and ks per channel plus n for a lobe).
    pub parameters: usize,
    /// BIC on the fitting samples: chi2 + k ln m.
    pub bic: f64,
    /// Held-out error: weighted mean squared residual per channel value (about 1 for a
    /// model that explains the held-out samples to their noise).
    pub held_out: f64,
}

/// The choice.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Choice<M = Model> {
    pub candidates: Vec<Scored<M>>,
    pub chosen: M,
    /// The margin a held-out error may exceed the best's by and still count as equal.
    pub tolerance: f64,
}

/// Which samples the model choice fits on (`true`) and which it holds out: alternate
/// samples in order, counted apart for each set of channels a sample holds. A camera that
/// measures every channel at every pixel gives plain alternation; a demosaicked camera's
/// samples hold one channel each, and alternating along a line of red and green
/// photosites would put every red in one half and every green in the other (the second
/// scene family's Bayer scenes then chose the cosine lobe for Phong tiles, 7 of 95).
pub fn fitting_half(samples: &[Sample]) -> Vec<bool> {
    let mut seen = [0usize; 8];
    samples
        .iter()
        .map(|s| {
            let held = weights(s)
                .iter()
                .enumerate()
                .filter(|(_, w)| **w > 0.0)
                .fold(0usize, |k, (c, _)| k | 1 << c);
            seen[held] += 1;
            seen[held] % 2 == 1
        })
        .collect()
}

/// The samples of the fitting half and of the held-out half ([`fitting_half`]).
pub fn halves(samples: &[Sample]) -> (Vec<Sample>, Vec<Sample>) {
    let half = fitting_half(samples);
    let pick = |want: bool| {
        samples
            .iter()
            .zip(&half)
            .filter(|(_, h)| **h == want)
            .map(|(s, _)| *s)
            .collect()
    };
    (pick(true), pick(false))
}

/// Each held-out value's squared residual over its variance (the order is the same for
/// every model: sample by sample, channel by channel, values with a usable variance only).
fn held_out_terms<M: Reflectance>(f: &ModelFit<M>, test: &[Sample]) -> Vec<f64> {
    let mut out = Vec::with_capacity(test.len() * f.channels);
    for t in test {
        for c in 0..f.channels {
            let v = t.variance[c];
            if !(v.is_finite() && v > 0.0) {
                continue;
            }
            out.push((f.predict(&t.geometry, c) - t.radiance[c]).powi(2) / v);
        }
    }
    out
}

/// How many standard errors of the paired difference a more complex model's held-out
/// error must lie below a simpler one's of as many parameters to be taken instead.
const PAIRED_SE: f64 = 3.0;

/// The paired difference of two models' held-out terms, a - b: its mean and the mean's
/// standard error (both models scored on the same values, so the noise common to both
/// cancels).
fn paired(a: &[f64], b: &[f64]) -> (f64, f64) {
    let m = a.len().min(b.len());
    if m < 2 {
        return (0.0, f64::INFINITY);
    }
    let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    let mean = d.iter().sum::<f64>() / m as f64;
    let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (m - 1) as f64;
    (mean, (var / m as f64).sqrt())
}

/// Fit `models` on `train`, score on `test`, choose.
pub fn choose<M: Reflectance + Copy>(
    models: &[M],
    train: &[Sample],
    test: &[Sample],
    opts: &Options,
) -> Choice<M> {
    let m = measured_values(train);
    let (candidates, terms): (Vec<Scored<M>>, Vec<Vec<f64>>) = models
        .iter()
        .map(|&model| {
            let f = fit(model, train, opts);
            let terms = held_out_terms(&f, test);
            let scored = Scored {
                bic: f.bic(m),
                held_out: terms.iter().sum::<f64>() / terms.len().max(1) as f64,
                parameters: f.parameters,
                fit: f,
            };
            (scored, terms)
        })
        .unzip();
    // The mean of m chi-square(1) values has standard deviation sqrt(2 / m): two of those.
    let m_test = (opts.channels.clamp(1, 3) * test.len()).max(1) as f64;
    let best = candidates
        .iter()
        .map(|c| c.held_out)
        .fold(f64::INFINITY, f64::min);
    let tolerance = 2.0 * (2.0 / m_test).sqrt() * best.max(1.0);
    let total = |c: &Scored<M>| c.fit.chi2 + c.held_out * m_test;
    let first = candidates
        .iter()
        .enumerate()
        .filter(|(_, c)| c.held_out <= best + tolerance)
        .min_by(|(_, a), (_, b)| {
            // Fewest parameters; among equals, the smaller total misfit over fitting and
            // held-out samples together (the two halves' evidence combined).
            a.parameters
                .cmp(&b.parameters)
                .then(a.fit.model.complexity().cmp(&b.fit.model.complexity()))
                .then(total(a).total_cmp(&total(b)))
        })
        .map(|(k, _)| k);
    // A model of as many parameters that assumes more (the microfacet model beside the
    // paper's) is taken instead where the same held-out values show it better beyond
    // their noise: the tolerance above is the noise of one held-out mean, but two models
    // scored on the same samples differ by much less noise than that, so a difference
    // of PAIRED_SE of its own standard errors is evidence the tolerance would hide.
    let chosen = first
        .map(|k| {
            candidates
                .iter()
                .enumerate()
                .filter(|(j, c)| {
                    let a = &candidates[k];
                    // The paired test (a pass over the held-out values) last, only for
                    // a candidate that could be taken instead.
                    c.parameters == a.parameters
                        && c.fit.model.complexity() > a.fit.model.complexity()
                        && total(c) < total(a)
                        && {
                            let (d, se) = paired(&terms[k], &terms[*j]);
                            d > PAIRED_SE * se
                        }
                })
                .min_by(|(_, a), (_, b)| total(a).total_cmp(&total(b)))
                .map_or(k, |(j, _)| j)
        })
        .map(|k| candidates[k].fit.model)
        .unwrap_or(models[0]);
    Choice {
        candidates,
        chosen,
        tolerance,
    }
}

#[cfg(test)]
mod halves_tests {
    use super::fitting_half;
    use crate::fit::model::Geometry;
    use crate::fit::solve::Sample;

    fn with(channels: &[usize]) -> Sample {
        let g = Geometry::from_vectors([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], 1.0);
        let mut v = [f64::INFINITY; 3];
        for c in channels {
            v[*c] = 1.0;
        }
        Sample::new(g, [1.0; 3], v)
    }

    #[test]
    fn each_half_gets_every_colour_of_a_demosaicked_line() {
        // Every channel at every pixel: plain alternation.
        let full: Vec<Sample> = (0..6).map(|_| with(&[0, 1, 2])).collect();
        assert_eq!(fitting_half(&full), [true, false, true, false, true, false]);
        // A row of red and green photosites (R G R G R G R G): each colour alternates
        // on its own, so both halves hold reds and greens.
        let row: Vec<Sample> = (0..8).map(|k| with(&[k % 2])).collect();
        let half = fitting_half(&row);
        for c in 0..2 {
            let of_c: Vec<bool> = (0..8).filter(|k| k % 2 == c).map(|k| half[k]).collect();
            assert_eq!(of_c, [true, false, true, false], "channel {c}");
        }
    }
}
