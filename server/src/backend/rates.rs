//! Work of graph runs, and the executor's measured seconds per unit of it, per model and graph:
//! what admission turns a request's work into time with. Each model's rates are its own, so a
//! slow model never changes what another model's requests are planned to take.

use std::collections::HashMap;

use crate::bundle::GraphKind;

/// Work of graph runs, in units per graph (`GraphKind::ALL` order): what a run's time grows
/// with, source pixels (V·H·W of the padded images) for the encoder and the volume graphs (for a
/// cost slab, times its share of the depth planes), rays for the renderer.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Work(pub [f64; GraphKind::ALL.len()]);

impl Work {
    pub fn of(graph: GraphKind, units: f64) -> Work {
        let mut work = Work::default();
        work.0[graph.index()] = units;
        work
    }

    pub fn plus(self, other: Work) -> Work {
        Work(std::array::from_fn(|i| self.0[i] + other.0[i]))
    }

    /// Planned seconds at `rates` (unmeasured graphs count 0).
    pub(super) fn secs(&self, rates: &Rates) -> f64 {
        self.secs_with(rates, true)
    }

    /// Seconds at `rates`, with or without the margin of their deviation.
    pub(super) fn secs_with(&self, rates: &Rates, margin: bool) -> f64 {
        GraphKind::ALL.iter().map(|&g| self.0[g.index()] * rates.per_unit(g, margin)).sum()
    }
}

/// Measured seconds per unit of work, per graph: sums of the runs' seconds, units and
/// deviations from the rate, each decayed by `1 - RATE_WEIGHT` a run. Summed rather than
/// averaged per run, so that a run weighs by its units: a request's last chunk of a few rays,
/// whose time is mostly the run's fixed cost, does not swing the rate.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Rates(pub(super) [Option<Rate>; GraphKind::ALL.len()]);

#[derive(Debug, Clone, Copy)]
pub(super) struct Rate {
    pub(super) secs: f64,
    pub(super) units: f64,
    pub(super) deviation: f64,
}

impl Rate {
    fn mean(&self) -> f64 {
        self.secs / self.units
    }

    /// What admission plans with when requests compete: the mean plus twice the deviation.
    fn planned(&self) -> f64 {
        self.mean() + 2.0 * self.deviation / self.units
    }
}

/// Weight of the latest run: a few runs follow a change of load.
const RATE_WEIGHT: f64 = 0.3;

impl Rates {
    pub(super) fn record(&mut self, graph: GraphKind, units: f64, took: f64) {
        if units <= 0.0 {
            return;
        }
        let keep = 1.0 - RATE_WEIGHT;
        let rate = &mut self.0[graph.index()];
        *rate = Some(match *rate {
            None => Rate { secs: took, units, deviation: 0.0 },
            Some(r) => Rate {
                secs: keep * r.secs + took,
                units: keep * r.units + units,
                deviation: keep * r.deviation + (took - r.mean() * units).abs(),
            },
        });
    }

    /// Seconds per unit of `graph` (0 while unmeasured): the mean, or with `margin` the planned
    /// rate.
    pub(super) fn per_unit(&self, graph: GraphKind, margin: bool) -> f64 {
        self.0[graph.index()].map_or(0.0, |r| if margin { r.planned() } else { r.mean() })
    }
}

/// Each model's [`Rates`], by its slot on the executor (`BackendHandle::add_runner`).
#[derive(Debug, Clone, Default)]
pub(super) struct ModelRates(HashMap<usize, Rates>);

impl ModelRates {
    /// The rates of `model`'s graphs (unmeasured ones count 0).
    pub(super) fn of(&self, model: usize) -> Rates {
        self.0.get(&model).copied().unwrap_or_default()
    }

    pub(super) fn record(&mut self, model: usize, graph: GraphKind, units: f64, took: f64) {
        self.0.entry(model).or_default().record(graph, units, took);
    }

    /// `model`'s graphs count as unmeasured again.
    pub(super) fn forget(&mut self, model: usize) {
        self.0.remove(&model);
    }

    #[cfg(test)]
    pub(super) fn set(&mut self, model: usize, rates: Rates) {
        self.0.insert(model, rates);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::testkit::scattered_rates;

    /// Runs whose times scatter plan with more than their mean.
    #[test]
    fn scattered_run_times_plan_above_their_mean() {
        let rate = scattered_rates().0[GraphKind::Renderer.index()].unwrap();
        assert!((0.8e-3..1.3e-3).contains(&rate.mean()), "{rate:?}");
        assert!(rate.planned() > rate.mean() + 1e-3, "{rate:?}");
        let steady = (0..6).fold(Rates::default(), |mut r, _| {
            r.record(GraphKind::Renderer, 20.0, 0.02);
            r
        });
        assert!((steady.per_unit(GraphKind::Renderer, true) - 1e-3).abs() < 1e-12);
        // A run of 2 units at 10 ms a unit (its fixed cost) moves a rate built on runs of 20 to
        // 1.4 ms, not to the 3.7 ms of an average per run.
        let mut tail = steady;
        tail.record(GraphKind::Renderer, 2.0, 0.02);
        assert!(tail.per_unit(GraphKind::Renderer, false) < 1.5e-3, "{tail:?}");
    }
}
