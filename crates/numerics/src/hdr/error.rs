//! What the numerical half of the HDR stage refuses: a bracket that cannot be merged
//! ([`MergeError`]), and why one model's curve could not be fitted to a channel
//! ([`CurveError`]). A leaf, so that the bracket, the merge and the response recovery all
//! name it without a circle.

/// What the numerical half of the HDR stage refuses.
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    /// The frames or times given cannot be merged (sizes, depths, times).
    #[error("{0}")]
    Input(String),
    /// The response cannot be recovered from these frames.
    #[error("response recovery failed: {0}")]
    Recovery(String),
    /// No model's curve could be fitted: the first model's reason.
    #[error("response recovery failed: {0}")]
    Curve(#[from] CurveError),
}

/// Why one model's curve could not be fitted to a channel's sample pixels. Recovery tries
/// each model it may choose; a model that fails is left out, and when every one fails
/// the first one's reason is the recovery's ([`MergeError::Curve`]).
#[derive(Debug, Clone, thiserror::Error)]
pub enum CurveError {
    /// A table curve's fit refused channel `channel`.
    #[error("channel {channel}: {problem}")]
    Channel {
        channel: String,
        #[source]
        problem: CurveProblem,
    },
    /// Debevec's curve above 8 bits, solved on 256 bins of `bin` values each, refused.
    #[error("{source} (values in 256 bins of {bin})")]
    Binned {
        bin: usize,
        #[source]
        source: Box<CurveError>,
    },
    /// The linear curve: no sample pixel reads above the black level twice. Its words
    /// begin as a recovery's do ("response recovery failed"), as they always have.
    #[error(
        "response recovery failed: channel {channel}: no sample pixel is above the black level ({black:.1}) in two frames"
    )]
    NothingAboveBlack { channel: String, black: f64 },
}

/// What a table curve's fit (Debevec's, the polynomial) finds wrong with one channel.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CurveProblem {
    /// Debevec's least-squares system has no unique solution.
    #[error("the least-squares system is singular")]
    Singular,
    /// Too few readings for Debevec's free curve.
    #[error(
        "{samples} samples x {exposures} exposures give {equations} independent equations for a {levels}-value curve; use more samples (--samples) or exposures"
    )]
    TooFewEquations {
        samples: usize,
        exposures: usize,
        equations: usize,
        levels: usize,
    },
    /// Debevec's curve is uncertain by `sd` (ln E) even at the gauge value.
    #[error(
        "the curve is not determined by the data even at mid-range (sd {sd:.3} in ln E); add exposures that overlap, more samples, or raise --lambda"
    )]
    UndeterminedAtMid { sd: f64 },
    /// Debevec's curve falls from `at` (ln E) at value `z` to `then` at `next`, beyond its
    /// uncertainty.
    #[error(
        "the recovered curve falls between values {z} and {next} (ln E {at:.4} then {then:.4}, more than 3 standard deviations); the data do not determine it there: raise --lambda, add samples or exposures"
    )]
    Falls {
        z: usize,
        next: usize,
        at: f64,
        then: f64,
    },
    /// The data determine Debevec's curve only on `lo..hi`, too short a range.
    #[error(
        "the data determine the curve only for values {lo}..{hi}; add exposures so that the scene's values overlap between frames"
    )]
    Narrow { lo: usize, hi: usize },
    /// The polynomial's normal equations have no unique solution at any degree.
    #[error("the polynomial fit is singular")]
    PolynomialSingular,
    /// The polynomial curve increases only on `lo..hi`, too short a range.
    #[error("the polynomial curve increases only for values {lo}..{hi}")]
    NotIncreasing { lo: usize, hi: usize },
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The words are those the string errors had: a channel's reason, the bins of a
    /// 16-bit Debevec curve after it, and the recovery's prefix before it.
    #[test]
    fn curve_errors_read_as_the_strings_they_replace() {
        let narrow = CurveError::Channel {
            channel: "G".into(),
            problem: CurveProblem::Narrow { lo: 3, hi: 40 },
        };
        let binned = CurveError::Binned {
            bin: 256,
            source: Box::new(narrow),
        };
        assert_eq!(
            MergeError::Curve(binned).to_string(),
            "response recovery failed: channel G: the data determine the curve only for values 3..40; add exposures so that the scene's values overlap between frames (values in 256 bins of 256)"
        );
        let black = CurveError::NothingAboveBlack {
            channel: "R".into(),
            black: 12.345,
        };
        assert_eq!(
            MergeError::Curve(black).to_string(),
            "response recovery failed: response recovery failed: channel R: no sample pixel is above the black level (12.3) in two frames"
        );
        let mid = CurveError::Channel {
            channel: "B".into(),
            problem: CurveProblem::UndeterminedAtMid { sd: 0.12345 },
        };
        assert!(mid.to_string().contains("(sd 0.123 in ln E)"), "{mid}");
    }
}
