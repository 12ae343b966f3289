//! Checks shared by the table curves' fits: where a curve misses its data near the ends of
//! its range (cut off there), and a dip within its uncertainty made monotonic.

/// Where a curve misses its data: the mean residual (ln E) at each value (above 8 bits, in
/// each of 256 bins of values), significant when above 1% and four standard errors (from at
/// least 5 readings). Such values in the outer
/// eighth of `lo..=hi` (where a curve bends hardest) are cut off; returns the new range and
/// the worst remaining value with its mean residual.
pub(super) fn trim_by_bias(
    residuals: impl Iterator<Item = (usize, f64)>,
    levels: usize,
    mut lo: usize,
    mut hi: usize,
) -> (usize, usize, Option<(usize, f64)>) {
    let mid = levels / 2;
    // Above 8 bits, values are pooled in 256 bins (few readings share one 16-bit value, and
    // a standard error from five of them is itself too uncertain to judge by).
    let bin = (levels / 256).max(1);
    let mut sum = vec![(0.0f64, 0.0f64, 0usize); levels.div_ceil(bin)];
    for (z, r) in residuals {
        let e = &mut sum[z / bin];
        e.0 += r;
        e.1 += r * r;
        e.2 += 1;
    }
    let bias = |z: usize| -> Option<f64> {
        let (s1, s2, n) = sum[z / bin];
        if n < 5 {
            return None;
        }
        let m = s1 / n as f64;
        let se = ((s2 / n as f64 - m * m).max(0.0) / (n - 1) as f64).sqrt();
        (m.abs() > 0.01 && m.abs() > 4.0 * se).then_some(m)
    };
    let band = (hi - lo) / 8;
    if let Some(z) = (lo..(lo + band).min(mid))
        .rev()
        .find(|z| bias(*z).is_some())
    {
        lo = z + 1;
    }
    if let Some(z) = ((hi - band).max(mid + 1)..=hi).find(|z| bias(*z).is_some()) {
        hi = z - 1;
    }
    let worst = (lo..=hi)
        .filter_map(|z| bias(z).map(|m| (z, m)))
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()));
    (lo, hi, worst)
}

/// Least-squares non-decreasing fit, in place (pool adjacent violators, equal weights).
pub(super) fn isotonic(v: &mut [f64]) {
    let mut blocks: Vec<(f64, usize)> = Vec::with_capacity(v.len());
    for x in v.iter() {
        blocks.push((*x, 1));
        while blocks.len() > 1 {
            let (b, nb) = blocks[blocks.len() - 1];
            let (a, na) = blocks[blocks.len() - 2];
            if a <= b {
                break;
            }
            blocks.pop();
            let n = na + nb;
            *blocks.last_mut().unwrap() = ((a * na as f64 + b * nb as f64) / n as f64, n);
        }
    }
    let mut k = 0;
    for (m, n) in blocks {
        for x in &mut v[k..k + n] {
            *x = m;
        }
        k += n;
    }
}
