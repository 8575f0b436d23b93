//! A fine ray's samples, chosen from its neighbours' weights.

use std::cmp::Ordering;

use ndarray::ArrayView1;

/// The samples a fine ray runs, chosen from its neighbours' weights.
#[derive(Debug, Clone, PartialEq)]
pub struct Selection {
    /// K uniform-sample indices, increasing.
    pub index: Vec<u32>,
    /// How many uniform samples each stands for (>= 1).
    pub multiplicity: Vec<f32>,
    /// Per uniform sample, the position in `index` of the taken sample that stands for it, or -1.
    pub owner: Vec<i32>,
}

/// A fine ray's score: its neighbours' weights (S) dilated by one sample (half a neighbour's
/// weight), since a surface between two samples is seen by both. Computed once per ray, for its
/// sample count ([`Score::support`]) and its samples ([`select_samples`], [`spread_samples`]).
pub struct Score(Vec<f32>);

impl Score {
    pub fn of(weights: ArrayView1<f32>) -> Score {
        let s = weights.len();
        let at = |k: isize| if k < 0 || k as usize >= s { 0.0 } else { weights[k as usize] };
        Score((0..s as isize).map(|k| at(k).max(0.5 * at(k - 1).max(at(k + 1)))).collect())
    }

    /// How many samples the score counts as matter: reach `threshold`.
    pub fn support(&self, threshold: f32) -> usize {
        self.0.iter().filter(|&&d| d >= threshold).count()
    }
}

/// The `count` samples of a ray from its `score`: see the Python twin, `select_samples`. The
/// samples with the highest scores are taken (ties: the nearer to the best sample, then the lower
/// index); every sample whose score reaches `threshold` and is not taken is stood for by the
/// nearest taken one (ties: the lower).
pub fn select_samples(score: &Score, count: usize, threshold: f32) -> Selection {
    let dilated = &score.0;
    let s = dilated.len();
    let best = dilated.iter().enumerate().fold(0, |b, (k, &d)| if d > dilated[b] { k } else { b });
    let rank = |a: &usize, b: &usize| {
        dilated[*b]
            .partial_cmp(&dilated[*a])
            .unwrap_or(Ordering::Equal)
            .then(a.abs_diff(best).cmp(&b.abs_diff(best)))
            .then(a.cmp(b))
    };
    let mut order: Vec<usize> = (0..s).collect();
    let count = count.min(s);
    if count < s {
        order.select_nth_unstable_by(count, rank);
    }
    let mut index: Vec<usize> = order[..count].to_vec();
    index.sort_unstable();
    standing_for(index, s, |k| dilated[k] >= threshold)
}

/// The `count` samples of a pixel rendered again (`spread_samples` in the Python twin): its
/// neighbours' support (the samples whose score reaches `threshold`; where those are more than
/// half of `count`, the heaviest half, ties: the lower index), and the rest spread evenly
/// over the samples left (the i-th of the m left of r to take: left[i·m / r]). Every sample of
/// the ray is stood for by the nearest taken one (ties: the lower): the pixel disagreed with
/// its neighbours, so matter may lie where they saw none. `count` = S: every sample.
pub fn spread_samples(score: &Score, count: usize, threshold: f32) -> Selection {
    let dilated = &score.0;
    let s = dilated.len();
    let count = count.min(s);
    let mut kept: Vec<usize> = (0..s).filter(|&k| dilated[k] >= threshold).collect();
    if kept.len() > count / 2 {
        kept.sort_by(|&a, &b| dilated[b].total_cmp(&dilated[a]).then(a.cmp(&b)));
        kept.truncate(count / 2);
    }
    let mut taken = vec![false; s];
    kept.iter().for_each(|&k| taken[k] = true);
    let left: Vec<usize> = (0..s).filter(|&k| !taken[k]).collect();
    let rest = count - kept.len();
    let mut index: Vec<usize> = kept.into_iter().chain((0..rest).map(|i| left[i * left.len() / rest])).collect();
    index.sort_unstable();
    standing_for(index, s, |_| true)
}

/// A selection of the taken samples `index` (increasing) of a ray of `s`: every sample taken or
/// `stood_for` is stood for by the nearest taken one (ties: the lower).
fn standing_for(index: Vec<usize>, s: usize, stood_for: impl Fn(usize) -> bool) -> Selection {
    let count = index.len();
    let mut owner = vec![-1i32; s];
    let mut multiplicity = vec![0f32; count];
    let mut next = 0; // first taken index >= k
    for (k, owned) in owner.iter_mut().enumerate() {
        while next < count && index[next] < k {
            next += 1;
        }
        let taken = next < count && index[next] == k;
        if !taken && !stood_for(k) {
            continue;
        }
        let lower = next.checked_sub(1);
        let nearest = match (lower, (next < count).then_some(next)) {
            (Some(l), Some(h)) if k - index[l] <= index[h] - k => l,
            (_, Some(h)) => h,
            (Some(l), None) => l,
            (None, None) => continue,
        };
        *owned = nearest as i32;
        multiplicity[nearest] += 1.0;
    }
    Selection { index: index.into_iter().map(|k| k as u32).collect(), multiplicity, owner }
}

/// A fine ray's weights over all S samples, for the levels after it: each taken sample's weight
/// shared among the samples it stands for.
pub fn spread_weights(weights: ArrayView1<f32>, selection: &Selection, out: &mut [f32]) {
    for (k, &o) in selection.owner.iter().enumerate() {
        out[k] = if o < 0 { 0.0 } else { weights[o as usize] / selection.multiplicity[o as usize] };
    }
}
