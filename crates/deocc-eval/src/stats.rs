//! Statistics of the reports: means, paired bootstrap intervals over clusters, ROC AUC.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

/// Mean of the finite values; NaN when there is none.
pub fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (s, n) = v
        .into_iter()
        .filter(|x| x.is_finite())
        .fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// A method against a baseline on the same items: both means, their difference, and its
/// 95% interval from a paired bootstrap that resamples whole clusters (the pairs of one object,
/// whose views are not independent).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Comparison {
    pub items: usize,
    pub clusters: usize,
    pub method: f64,
    pub baseline: f64,
    /// `method - baseline`.
    pub difference: f64,
    pub ci95: [f64; 2],
}

/// Paired comparison of `method[i]` against `baseline[i]` (items whose values are both finite),
/// `clusters[i]` naming each item's cluster; `resamples` bootstrap draws from `seed`.
pub fn compare(
    method: &[f64],
    baseline: &[f64],
    clusters: &[u32],
    resamples: usize,
    seed: u64,
) -> Comparison {
    let keep: Vec<usize> = (0..method.len())
        .filter(|&i| method[i].is_finite() && baseline[i].is_finite())
        .collect();
    // Sum of differences and count per cluster.
    let mut by_cluster: std::collections::BTreeMap<u32, (f64, usize)> = Default::default();
    for &i in &keep {
        let e = by_cluster.entry(clusters[i]).or_default();
        e.0 += method[i] - baseline[i];
        e.1 += 1;
    }
    let groups: Vec<(f64, usize)> = by_cluster.into_values().collect();
    let m = mean(keep.iter().map(|&i| method[i]));
    let b = mean(keep.iter().map(|&i| baseline[i]));
    let mut draws = Vec::with_capacity(resamples);
    if !groups.is_empty() {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..resamples {
            let (mut s, mut n) = (0.0, 0usize);
            for _ in 0..groups.len() {
                let g = groups[rng.random_range(0..groups.len())];
                s += g.0;
                n += g.1;
            }
            draws.push(s / n.max(1) as f64);
        }
    }
    let q = interval_quantiles(draws);
    Comparison {
        items: keep.len(),
        clusters: groups.len(),
        method: m,
        baseline: b,
        difference: m - b,
        ci95: [q(0.025), q(0.975)],
    }
}

/// Area under the ROC curve of `scores` for the `labels` (ties count half), by the rank-sum
/// formula; NaN without both classes.
pub fn roc_auc(scores: &[f32], labels: &[bool]) -> f64 {
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
    let positives = labels.iter().filter(|&&l| l).count() as f64;
    let negatives = labels.len() as f64 - positives;
    if positives == 0.0 || negatives == 0.0 {
        return f64::NAN;
    }
    // Average ranks over ties.
    let mut rank_sum = 0.0;
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && scores[order[j + 1]] == scores[order[i]] {
            j += 1;
        }
        let avg_rank = (i + j) as f64 / 2.0 + 1.0;
        for &k in &order[i..=j] {
            if labels[k] {
                rank_sum += avg_rank;
            }
        }
        i = j + 1;
    }
    (rank_sum - positives * (positives + 1.0) / 2.0) / (positives * negatives)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auc_of_known_rankings() {
        assert_eq!(
            roc_auc(&[0.1, 0.2, 0.8, 0.9], &[false, false, true, true]),
            1.0
        );
        assert_eq!(
            roc_auc(&[0.9, 0.8, 0.2, 0.1], &[false, false, true, true]),
            0.0
        );
        assert_eq!(
            roc_auc(&[0.5, 0.5, 0.5, 0.5], &[false, true, false, true]),
            0.5
        );
        assert!(roc_auc(&[0.1, 0.2], &[true, true]).is_nan());
    }

    #[test]
    fn bootstrap_interval_covers_a_shift_and_excludes_zero() {
        // Method = baseline + 0.1 + noise, in 200 clusters of 3 items.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let n = 600;
        let baseline: Vec<f64> = (0..n).map(|_| rng.random_range(0.0..1.0)).collect();
        let method: Vec<f64> = baseline
            .iter()
            .map(|b| b + 0.1 + rng.random_range(-0.05..0.05))
            .collect();
        let clusters: Vec<u32> = (0..n as u32).map(|i| i / 3).collect();
        let c = compare(&method, &baseline, &clusters, 500, 7);
        assert_eq!((c.items, c.clusters), (600, 200));
        assert!((c.difference - 0.1).abs() < 0.01);
        assert!(
            c.ci95[0] > 0.09 && c.ci95[1] < 0.11 && c.ci95[0] < c.ci95[1],
            "{c:?}"
        );
        // No difference: the interval holds zero.
        let same = compare(&baseline, &baseline, &clusters, 200, 7);
        assert_eq!(same.ci95, [0.0, 0.0]);
    }
}

/// The bootstrap draws' quantile function (nearest rank; NaN without draws).
fn interval_quantiles(mut draws: Vec<f64>) -> impl Fn(f64) -> f64 {
    draws.sort_by(f64::total_cmp);
    move |p: f64| {
        if draws.is_empty() {
            f64::NAN
        } else {
            draws[((p * (draws.len() - 1) as f64).round() as usize).min(draws.len() - 1)]
        }
    }
}

/// A mean with its 95% bootstrap interval (items resampled with replacement).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Estimate {
    pub items: usize,
    pub mean: f64,
    pub ci95: [f64; 2],
}

/// [`Estimate`] of the finite values of `v`, `resamples` draws from `seed`.
pub fn estimate(v: &[f64], resamples: usize, seed: u64) -> Estimate {
    let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    let clusters: Vec<u32> = (0..v.len() as u32).collect();
    let zero = vec![0.0; v.len()];
    let c = compare(&v, &zero, &clusters, resamples, seed);
    Estimate {
        items: v.len(),
        mean: c.method,
        ci95: c.ci95,
    }
}

/// How much of an upper bound's gain over a baseline a method recovers, on the same items:
/// `mean(method - baseline) / mean(bound - baseline)`, with its 95% interval from a bootstrap
/// over items (numerator and denominator from the same draw).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ShareOfBound {
    pub items: usize,
    /// `mean(method - baseline)`.
    pub gain: f64,
    /// `mean(bound - baseline)`.
    pub bound_gain: f64,
    pub share: f64,
    pub ci95: [f64; 2],
}

/// [`ShareOfBound`] over the items where all three values are finite; NaN share when the bound
/// gains nothing.
pub fn share_of_bound(
    method: &[f64],
    baseline: &[f64],
    bound: &[f64],
    resamples: usize,
    seed: u64,
) -> ShareOfBound {
    let keep: Vec<(f64, f64)> = (0..method.len().min(baseline.len()).min(bound.len()))
        .filter(|&i| method[i].is_finite() && baseline[i].is_finite() && bound[i].is_finite())
        .map(|i| (method[i] - baseline[i], bound[i] - baseline[i]))
        .collect();
    let ratio = |pairs: &mut dyn Iterator<Item = (f64, f64)>| {
        let (g, b, n) = pairs.fold((0.0, 0.0, 0usize), |(g, b, n), (x, y)| {
            (g + x, b + y, n + 1)
        });
        (g / n.max(1) as f64, b / n.max(1) as f64)
    };
    let (gain, bound_gain) = ratio(&mut keep.iter().copied());
    let share = if bound_gain.abs() > 1e-12 {
        gain / bound_gain
    } else {
        f64::NAN
    };
    let mut draws = Vec::with_capacity(resamples);
    if !keep.is_empty() {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..resamples {
            let (g, b) = ratio(&mut (0..keep.len()).map(|_| keep[rng.random_range(0..keep.len())]));
            if b.abs() > 1e-12 {
                draws.push(g / b);
            }
        }
    }
    let q = interval_quantiles(draws);
    ShareOfBound {
        items: keep.len(),
        gain,
        bound_gain,
        share,
        ci95: [q(0.025), q(0.975)],
    }
}

#[cfg(test)]
mod share_tests {
    use super::*;

    /// A method that recovers half of the bound's gain on every item scores 0.5 with a tight
    /// interval; the bound itself scores 1; the baseline 0; items with a NaN are left out.
    #[test]
    fn share_of_bound_is_the_ratio_of_mean_gains() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let base: Vec<f64> = (0..300).map(|_| rng.random_range(0.3..0.7)).collect();
        let bound: Vec<f64> = base
            .iter()
            .map(|b| b + rng.random_range(0.1..0.3))
            .collect();
        let half: Vec<f64> = base
            .iter()
            .zip(&bound)
            .map(|(b, u)| b + 0.5 * (u - b))
            .collect();
        let s = share_of_bound(&half, &base, &bound, 500, 1);
        assert!((s.share - 0.5).abs() < 1e-9, "{s:?}");
        assert!(s.ci95[0] > 0.49 && s.ci95[1] < 0.51, "{s:?}");
        assert!((share_of_bound(&bound, &base, &bound, 100, 1).share - 1.0).abs() < 1e-9);
        assert_eq!(share_of_bound(&base, &base, &bound, 100, 1).share, 0.0);
        let mut with_nan = half.clone();
        with_nan[0] = f64::NAN;
        assert_eq!(share_of_bound(&with_nan, &base, &bound, 100, 1).items, 299);
        // A bound that gains nothing has no share.
        assert!(share_of_bound(&half, &base, &base, 100, 1).share.is_nan());
    }
}
