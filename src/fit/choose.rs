//! Model choice: fit every candidate on the fitting samples, score each on held-out
//! samples of the same tile, and keep the simplest whose held-out error is within the
//! noise of the best ("model no more than the tile needs").

use serde::{Deserialize, Serialize};

use super::model::{Model, Reflectance};
use super::solve::{fit, measured_values, ModelFit, Options, Sample};

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

fn held_out<M: Reflectance>(f: &ModelFit<M>, test: &[Sample]) -> f64 {
    let mut s = 0.0;
    let mut m = 0usize;
    for t in test {
        for c in 0..f.channels {
            let v = t.variance[c];
            if !(v.is_finite() && v > 0.0) {
                continue;
            }
            s += (f.predict(&t.geometry, c) - t.radiance[c]).powi(2) / v;
            m += 1;
        }
    }
    s / m.max(1) as f64
}

/// Fit `models` on `train`, score on `test`, choose.
pub fn choose<M: Reflectance + Copy>(
    models: &[M],
    train: &[Sample],
    test: &[Sample],
    opts: &Options,
) -> Choice<M> {
    let m = measured_values(train);
    let candidates: Vec<Scored<M>> = models
        .iter()
        .map(|&model| {
            let f = fit(model, train, opts);
            Scored {
                bic: f.bic(m),
                held_out: held_out(&f, test),
                parameters: f.parameters,
                fit: f,
            }
        })
        .collect();
    // The mean of m chi-square(1) values has standard deviation sqrt(2 / m): two of those.
    let m_test = (opts.channels.clamp(1, 3) * test.len()).max(1) as f64;
    let best = candidates
        .iter()
        .map(|c| c.held_out)
        .fold(f64::INFINITY, f64::min);
    let tolerance = 2.0 * (2.0 / m_test).sqrt() * best.max(1.0);
    let chosen = candidates
        .iter()
        .filter(|c| c.held_out <= best + tolerance)
        .min_by(|a, b| {
            // Fewest parameters; among equals, the smaller total misfit over fitting and
            // held-out samples together (the two halves' evidence combined).
            let total = |c: &Scored<M>| c.fit.chi2 + c.held_out * m_test;
            a.parameters
                .cmp(&b.parameters)
                .then(a.fit.model.complexity().cmp(&b.fit.model.complexity()))
                .then(total(a).total_cmp(&total(b)))
        })
        .map(|c| c.fit.model)
        .unwrap_or(models[0]);
    Choice {
        candidates,
        chosen,
        tolerance,
    }
}
