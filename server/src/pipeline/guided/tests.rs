use ndarray::{arr1, Array1};

use super::*;
use crate::bundle::GuidedPolicy;

#[test]
fn levels_cover_every_pixel_once() {
    let (w, h, step) = (21, 13, 8);
    let mut seen = vec![0; w * h];
    for (v, u) in first_level_pixels(w, h, step) {
        seen[v * w + u] += 1;
    }
    let mut spacing = step / 2;
    while spacing >= 1 {
        for (v, u) in level_pixels(w, h, spacing) {
            seen[v * w + u] += 1;
            let near = neighbours((v, u), w, h, spacing);
            assert!(!near.is_empty() && near.len() <= 4);
            // Every neighbour lies on the coarser grid, rendered by an earlier level.
            assert!(near.iter().all(|&(nv, nu)| nv % (2 * spacing) == 0 && nu % (2 * spacing) == 0));
        }
        spacing /= 2;
    }
    assert!(seen.iter().all(|&n| n == 1), "{seen:?}");
}

#[test]
fn neighbours_are_one_spacing_away() {
    assert_eq!(neighbours((0, 4), 16, 16, 4), vec![(0, 0), (0, 8)]);
    assert_eq!(neighbours((4, 4), 16, 16, 4), vec![(0, 0), (0, 8), (8, 0), (8, 8)]);
    // The last column has no neighbour beyond the image.
    assert_eq!(neighbours((2, 15), 16, 16, 1), vec![(2, 14)]);
}

#[test]
fn a_narrow_surface_is_sampled_exactly() {
    let mut score = Array1::<f32>::zeros(16);
    score[7] = 0.6;
    score[8] = 0.3;
    let sel = select_samples(&Score::of(score.view()), 4, 1e-3);
    // The two samples with weight, their dilation (6 and 9), nothing else stands for more.
    assert_eq!(sel.index, vec![6, 7, 8, 9]);
    assert_eq!(sel.multiplicity, vec![1.0; 4]);
    assert_eq!(sel.owner.iter().filter(|&&o| o >= 0).count(), 4);
}

#[test]
fn a_wide_surface_is_stood_for_by_its_samples() {
    let score = arr1(&[0.0, 0.1, 0.1, 0.1, 0.1, 0.5, 0.1, 0.1, 0.1, 0.0, 0.0, 0.0]);
    let sel = select_samples(&Score::of(score.view()), 3, 1e-3);
    assert_eq!(sel.index, vec![4, 5, 6]);
    // Support: samples 0..=9 (0 and 9 by dilation); 0..=4 go to 4, 6..=9 to 6.
    assert_eq!(sel.multiplicity, vec![5.0, 1.0, 4.0]);
    assert_eq!(sel.multiplicity.iter().sum::<f32>(), 10.0);
    let mut spread = vec![0.0; 12];
    spread_weights(arr1(&[0.5, 0.2, 0.4]).view(), &sel, &mut spread);
    assert_eq!(spread[0], 0.1);
    assert_eq!(spread[5], 0.2);
    assert_eq!(spread[9], 0.1);
    assert_eq!(spread[10], 0.0);
}

#[test]
fn ties_go_to_the_samples_nearest_the_best() {
    let sel = select_samples(&Score::of(Array1::<f32>::zeros(10).view()), 3, 1e-3);
    assert_eq!(sel.index, vec![0, 1, 2]);
    let mut score = Array1::<f32>::zeros(10);
    score[5] = 1.0;
    let sel = select_samples(&Score::of(score.view()), 5, 0.6);
    assert_eq!(sel.index, vec![3, 4, 5, 6, 7]);
}

#[test]
fn the_support_counts_the_dilated_samples_that_reach_the_threshold() {
    let score = arr1(&[0.0, 0.0, 0.4, 0.0, 0.0, 0.0, 0.1, 0.1, 0.0, 0.0]);
    // 2 and its dilation 1, 3; 6, 7 and theirs 5, 8.
    assert_eq!(Score::of(score.view()).support(1e-3), 7);
    assert_eq!(Score::of(score.view()).support(0.1), 5, "the dilated 0.05s (5 and 8) fall short");
    assert_eq!(Score::of(Array1::<f32>::zeros(8).view()).support(1e-3), 0);
}

#[test]
fn a_pixel_rendered_again_keeps_its_support_and_spreads_the_rest() {
    let mut score = Array1::<f32>::zeros(16);
    score[9] = 0.5;
    let sel = spread_samples(&Score::of(score.view()), 8, 1e-3);
    // The support 8, 9, 10 and 5 more of the 13 samples left, evenly from the first.
    assert_eq!(sel.index, vec![0, 2, 5, 7, 8, 9, 10, 13]);
    // Every sample is stood for: the nearest taken one (ties: the lower).
    assert!(sel.owner.iter().all(|&o| o >= 0));
    assert_eq!(sel.multiplicity.iter().sum::<f32>(), 16.0);
    assert_eq!(sel.multiplicity, vec![2.0, 2.0, 3.0, 1.0, 1.0, 1.0, 2.0, 4.0]);
    // A support wider than half the count keeps its heaviest half: 3, then 2 and 4 tie at the
    // dilated 0.45 (the lower); the other two spread over 0, 1, 4, 5, 6, 7.
    let wide = arr1(&[0.2, 0.2, 0.2, 0.9, 0.2, 0.2, 0.2, 0.2]);
    assert_eq!(spread_samples(&Score::of(wide.view()), 4, 1e-3).index, vec![0, 2, 3, 5]);
    // At S samples: every sample, each for itself.
    let all = spread_samples(&Score::of(score.view()), 16, 1e-3);
    assert_eq!(all.index, (0..16).collect::<Vec<u32>>());
    assert_eq!(all.multiplicity, vec![1.0; 16]);
}

#[test]
fn a_thin_surface_runs_at_fewer_samples() {
    let fitted =
        GuidedPolicy { min_samples: Some(8), edge_span: Some(0.3), edge_samples: Some(32), ..verifying(0.1, 1.0) };
    // The support rounded up to a multiple of 4, at least 8, at most the level's (or the edge's)
    // count.
    assert_eq!(fitted.samples_at(16, 0.0, 3), 8);
    assert_eq!(fitted.samples_at(16, 0.0, 9), 12);
    assert_eq!(fitted.samples_at(16, 0.0, 40), 16);
    assert_eq!(fitted.samples_at(4, 0.0, 3), 4, "never more than the level's count");
    assert_eq!(fitted.samples_at(16, 0.5, 3), 8, "an edge's too");
    assert_eq!(fitted.samples_at(16, 0.5, 30), 32);
    assert_eq!(GuidedPolicy { min_samples: None, ..fitted.clone() }.samples_at(16, 0.0, 3), 16);
    assert!(GuidedPolicy { min_samples: Some(0), ..fitted.clone() }.validate(128).is_err());
    assert!(GuidedPolicy { verify_samples: Some(129), ..fitted }.validate(128).unwrap_err().contains("verify_samples"));
}

#[test]
fn the_nearest_guide_ray_rounds_half_way_up() {
    // A 3 x 3 level-0 grid at step 8 (pixels 0, 8, 16).
    assert_eq!(nearest_guide((4, 2), 3, 3, 8), 3);
    assert_eq!(nearest_guide((3, 12), 3, 3, 8), 2);
    // Beyond the last grid column: the last column.
    assert_eq!(nearest_guide((0, 23), 3, 3, 8), 2);
}

/// A 5 x 5 frame whose every pixel is grey and opaque.
fn grey_frame() -> Frame {
    let mut canvas = Canvas::new(5, 5);
    canvas.rgb.fill(0.5);
    canvas.opacity.fill(1.0);
    Frame { canvas, guidance: Guidance::new(5, 5, 4), height: 5, background: [0.0; 3] }
}

fn verifying(tolerance: f32, share: f64) -> GuidedPolicy {
    GuidedPolicy {
        step: 4,
        samples: vec![4, 4],
        support_threshold: 1e-3,
        smooth_tolerance: 0.0,
        smooth_max_step: 1,
        verify_tolerance: Some(tolerance),
        verify_share: Some(share),
        edge_span: None,
        edge_samples: None,
        min_samples: None,
        verify_samples: None,
    }
}

#[test]
fn pixels_that_disagree_with_their_neighbours_are_rendered_again_worst_first() {
    let mut frame = grey_frame();
    // On the grid of spacing 1: (1, 1) missed its neighbours' matter (dark: the background
    // shows), (1, 3) is brighter than any neighbour, (3, 1) a little off, (3, 3) agrees.
    let i = |p| frame.canvas.index(p);
    let (dark, bright, slight) = (i((1, 1)), i((1, 3)), i((3, 1)));
    frame.canvas.opacity[dark] = 0.3;
    frame.canvas.rgb.row_mut(dark).fill(0.15);
    frame.canvas.rgb.row_mut(bright).fill(0.9);
    frame.canvas.rgb.row_mut(slight).fill(0.55);
    let fine = [(1, 1), (1, 3), (3, 1), (3, 3)];
    let near = neighbours((1, 1), 5, 5, 1);
    assert!((frame.canvas.disagreement((1, 1), &near, [0.0; 3]) - 0.7).abs() < 1e-6);
    assert_eq!(disagreeing(&verifying(0.1, 1.0), &frame, &fine, 1), vec![(1, 1), (1, 3)]);
    // The share bounds how many: the worst (the dark pixel, 0.7 off) first.
    assert_eq!(disagreeing(&verifying(0.01, 0.25), &frame, &fine, 1), vec![(1, 1)]);
    assert_eq!(disagreeing(&verifying(0.01, 0.75), &frame, &fine, 1), vec![(1, 1), (1, 3), (3, 1)]);
    // A policy without verification renders no pixel again.
    let plain = GuidedPolicy { verify_tolerance: None, verify_share: None, ..verifying(0.0, 1.0) };
    assert!(disagreeing(&plain, &frame, &fine, 1).is_empty());
}

#[test]
fn reruns_count_in_the_most_work_at_all_samples() {
    let policy = verifying(0.1, 0.5);
    let plain = GuidedPolicy { verify_tolerance: None, verify_share: None, ..policy.clone() };
    let (w, h, samples) = (9, 9, 64);
    let fine: Vec<usize> = policy.levels().map(|(spacing, _)| level_pixels(w, h, spacing).len()).collect();
    let reruns: usize = fine.iter().map(|&n| n / 2).sum();
    assert_eq!(policy.most_work(w, h, samples).0, plain.most_work(w, h, samples).0);
    assert_eq!(policy.most_work(w, h, samples).1, plain.most_work(w, h, samples).1 + reruns * samples);
    let fewer = GuidedPolicy { verify_samples: Some(16), ..policy.clone() };
    assert_eq!(fewer.most_work(w, h, samples).1, plain.most_work(w, h, samples).1 + reruns * 16);
    assert!(GuidedPolicy { verify_share: None, ..policy.clone() }.validate(128).is_err());
    assert!(GuidedPolicy { verify_share: Some(1.5), ..policy }.validate(128).is_err());
}

#[test]
fn policy_checks() {
    let policy = GuidedPolicy {
        step: 8,
        samples: vec![32, 16, 8],
        support_threshold: 1e-3,
        smooth_tolerance: 0.03,
        smooth_max_step: 2,
        verify_tolerance: None,
        verify_share: None,
        edge_span: None,
        edge_samples: None,
        min_samples: None,
        verify_samples: None,
    };
    assert!(policy.validate(128).is_ok());
    assert!(policy.validate(16).unwrap_err().contains("32"));
    assert!(GuidedPolicy { step: 6, ..policy.clone() }.validate(128).is_err());
    assert!(GuidedPolicy { samples: vec![8], ..policy.clone() }.validate(128).is_err());
    assert_eq!(policy.levels().collect::<Vec<_>>(), vec![(4, 32), (2, 16), (1, 8)]);
}

#[test]
fn pixels_on_an_edge_run_at_more_samples() {
    let mut frame = grey_frame();
    // A bright pixel of the grid of 2: the finest level's pixels beside it see their
    // neighbours' colours span 0.4.
    let bright = frame.canvas.index((0, 2));
    frame.canvas.rgb.row_mut(bright).fill(0.9);
    let policy = |span| GuidedPolicy {
        samples: vec![2, 2],
        smooth_max_step: 0,
        edge_span: Some(span),
        edge_samples: Some(4),
        ..verifying(0.1, 1.0)
    };
    let runs = plan_level(&policy(0.3), &mut frame, 1, 2);
    let counts: Vec<(usize, usize)> = runs.iter().map(|r| (r.index.ncols(), r.pixels.len())).collect();
    assert_eq!(counts, vec![(2, 16 - 5), (4, 5)]);
    assert_eq!(runs[1].pixels, vec![(0, 1), (0, 3), (1, 1), (1, 2), (1, 3)]);
    assert!(runs[1].selections.iter().all(|s| s.index.len() == 4));
    // Below the span, every pixel runs at the level's count.
    let runs = plan_level(&policy(0.5), &mut frame, 1, 2);
    assert_eq!(runs.iter().map(|r| (r.index.ncols(), r.pixels.len())).collect::<Vec<_>>(), vec![(2, 16)]);
    assert_eq!(policy(0.3).samples_at(8, 1.0, 8), 8, "a level that runs more keeps its count");
}

#[test]
fn a_level_runs_pixels_between_thin_surfaces_at_fewer_samples() {
    let mut frame = grey_frame();
    frame.guidance = Guidance::new(5, 5, 16);
    let thin = Array1::from_iter((0..16).map(|k| if k == 5 { 0.9 } else { 0.0 }));
    for v in (0..5).step_by(2) {
        for u in (0..5).step_by(2) {
            frame.guidance.set((v, u), Array1::from_elem(16, 0.1).view());
        }
    }
    frame.guidance.set((0, 0), thin.view());
    frame.guidance.set((0, 2), thin.view());
    let policy = GuidedPolicy { samples: vec![8, 8], smooth_max_step: 0, min_samples: Some(4), ..verifying(0.1, 1.0) };
    // (0, 1) lies between two thin surfaces (support 3: sample 5 and its dilation): 4 samples.
    let runs = plan_level(&policy, &mut frame, 1, 8);
    let counts: Vec<(usize, usize)> = runs.iter().map(|r| (r.index.ncols(), r.pixels.len())).collect();
    assert_eq!(counts, vec![(4, 1), (8, 15)]);
    assert_eq!(runs[0].pixels, vec![(0, 1)]);
    assert_eq!(runs[0].selections[0].index, vec![3, 4, 5, 6]);
}

#[test]
fn edge_samples_count_in_the_most_work_and_come_with_their_span() {
    let plain = GuidedPolicy { verify_tolerance: None, verify_share: None, ..verifying(0.0, 1.0) };
    let edges = GuidedPolicy { edge_span: Some(0.3), edge_samples: Some(16), ..plain.clone() };
    let (w, h) = (9, 9);
    let fine: usize = plain.levels().map(|(spacing, _)| level_pixels(w, h, spacing).len()).sum();
    assert_eq!(edges.most_work(w, h, 16).1, fine * 16);
    assert_eq!(edges.most_work(w, h, 16).0, plain.most_work(w, h, 16).0);
    assert!(edges.validate(16).is_ok());
    assert!(edges.validate(8).unwrap_err().contains("edge_samples"));
    assert!(GuidedPolicy { edge_samples: None, ..edges.clone() }.validate(128).is_err());
    assert!(GuidedPolicy { edge_span: Some(f32::NAN), ..edges }.validate(128).is_err());
}
