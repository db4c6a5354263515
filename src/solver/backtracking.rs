//! The backtracking search on a Lipschitz estimate, shared by the deformation and feature
//! steps (SPEC §6): start from `shrink^(m+1) · L_stored`, double `L` until a trial is
//! accepted, and give up after `max_trials`, keeping the `L` the step started from.
//!
//! `m` is the search's *streak* (SPEC §6, "Where a search starts"): the sweeps in a row whose
//! search for the same block accepted its first trial. Deformation searches carry it
//! ([`LevelState::phi_streak`](super::ipalm::LevelState::phi_streak)); feature searches
//! always start with `m = 0`, the plain `shrink · L_stored`.

use crate::error::{Error, Result};

/// Backtracking on a Lipschitz estimate `L`: each step starts from `shrink · L_stored` and
/// doubles `L` until the trial is accepted.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Backtracking {
    /// Factor applied to the stored `L` before the first trial of a step. Default 0.9
    /// (SPEC §6). Must lie in `(0, 1]`.
    pub shrink: f64,
    /// Trials per step before giving up and keeping the current iterate. Default 60 (SPEC §6,
    /// *Giving up*; in practice a handful of trials suffice).
    pub max_trials: usize,
    /// Relative slack of the decrease tests where the energies cannot be accumulated in
    /// float64 (wgpu): a float32 sum over `67·256²` values has a relative error of about
    /// `6e-6`, so a step that barely changes the energy could fail by rounding alone, and a
    /// violation below `slack · |F(x̃)|` counts as satisfied (SPEC §6, "Floating point").
    /// Backends that accumulate in float64 use no slack. Default 1e-6. Must lie in
    /// `[0, 1e-3]`.
    pub float32_slack: f64,
}

impl Default for Backtracking {
    fn default() -> Self {
        Self {
            shrink: 0.9,
            max_trials: 60,
            float32_slack: 1e-6,
        }
    }
}

/// What one trial of a search found.
#[derive(Clone, Debug, PartialEq)]
pub enum Trial<T> {
    /// The trial passed the test; the search ends with it.
    Accepted(T),
    /// The decrease test failed.
    Rejected,
    /// The candidate is not admissible (a deformation that folds or moves the boundary).
    Inadmissible,
}

/// The outcome of a search.
#[derive(Clone, Debug, PartialEq)]
pub struct Search<T> {
    /// The accepted candidate, `None` when the search gave up.
    pub accepted: Option<T>,
    /// The `L` to store for the next sweep: the accepted one, or, when the search gave up,
    /// the stored `L` the step started from (SPEC §6, *Giving up*: a doubled `L·2⁶⁰` would
    /// freeze the block for hundreds of sweeps).
    pub lipschitz: f64,
    /// Trials run (1 = the first was accepted).
    pub trials: usize,
    /// Trials whose candidate was inadmissible.
    pub inadmissible: usize,
}

impl Backtracking {
    /// Checks the ranges.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        if !(self.shrink > 0.0 && self.shrink <= 1.0) {
            return Err(Error::invalid("shrink", self.shrink, "in (0, 1]"));
        }
        if self.max_trials == 0 || self.max_trials > 1000 {
            return Err(Error::invalid(
                "max_trials",
                self.max_trials,
                "in 1..=1000 (L doubles per trial)",
            ));
        }
        if !(0.0..=1e-3).contains(&self.float32_slack) {
            return Err(Error::invalid(
                "float32_slack",
                self.float32_slack,
                "in [0, 1e-3]",
            ));
        }
        Ok(())
    }

    /// The sufficient-decrease test of SPEC §6,
    /// `F(x_new) ≤ F(x̃) + ⟨∇F(x̃), x_new − x̃⟩ + L/2 ‖x_new − x̃‖² + slack·|F(x̃)|`.
    /// A non-finite `F(x_new)` never passes.
    pub fn accepts(&self, new: f64, old: f64, inner: f64, norm2: f64, l: f64, slack: f64) -> bool {
        new.is_finite() && new <= old + inner + 0.5 * l * norm2 + slack * old.abs()
    }

    /// The same test for an objective that is quadratic along the step, from its exact
    /// remainder `F(x_new) − F(x̃) − ⟨∇F(x̃), x_new − x̃⟩` (the step's curvature term):
    /// `remainder ≤ L/2 ‖x_new − x̃‖² + slack·|F(x̃)|`. Equal to [`accepts`](Self::accepts) in
    /// exact arithmetic; in floating point it never subtracts `F(x̃)` from `F(x_new)`, whose
    /// rounding (float32 summands) can exceed the decrease a small step predicts and then
    /// decides the test. A non-finite remainder or `F(x_new)` never passes.
    pub fn accepts_remainder(
        &self,
        new: f64,
        old: f64,
        remainder: f64,
        norm2: f64,
        l: f64,
        slack: f64,
    ) -> bool {
        new.is_finite() && remainder.is_finite() && remainder <= 0.5 * l * norm2 + slack * old.abs()
    }

    /// The factor `shrink^(m+1)` on the stored estimate where a search with streak `m`
    /// starts (SPEC §6, "Where a search starts"). `m = 0` gives the plain `shrink`.
    pub fn start_factor(&self, streak: u32) -> f64 {
        // Repeated products, not `powi`: the factor of a streak is then exactly the product
        // the shrinking sweeps would have applied one by one.
        (0..=streak).fold(1.0, |factor, _| factor * self.shrink)
    }

    /// Runs one search from the stored estimate `stored`: calls `trial(L)` for
    /// `L = shrink·stored, 2·shrink·stored, …` until it accepts or `max_trials` have run.
    ///
    /// # Errors
    ///
    /// Whatever `trial` returns.
    pub fn search<T>(
        &self,
        stored: f64,
        trial: impl FnMut(f64) -> Result<Trial<T>>,
    ) -> Result<Search<T>> {
        self.search_from(stored, 0, trial)
    }

    /// [`search`](Self::search) with streak `m`: the first trial is
    /// `shrink^(m+1)·stored` ([`start_factor`](Self::start_factor)); giving up still keeps
    /// `stored`.
    ///
    /// # Errors
    ///
    /// Whatever `trial` returns.
    pub fn search_from<T>(
        &self,
        stored: f64,
        streak: u32,
        mut trial: impl FnMut(f64) -> Result<Trial<T>>,
    ) -> Result<Search<T>> {
        let mut run = SearchRun::from_streak(self, stored, streak);
        while let Some(l) = run.next() {
            let outcome = trial(l)?;
            if let Some(found) = run.record(outcome) {
                return Ok(found);
            }
        }
        Ok(run.give_up())
    }
}

/// One search in progress, driven from outside: [`next`](Self::next) gives the `L` to try,
/// [`record`](Self::record) takes what the trial found. [`Backtracking::search`] runs one;
/// a batched step runs several in lockstep, one per block, evaluating all trials of a round
/// as one tensor operation.
#[derive(Clone, Debug)]
pub struct SearchRun {
    stored: f64,
    l: f64,
    trials: usize,
    inadmissible: usize,
    max_trials: usize,
}

impl SearchRun {
    /// A search starting from the stored estimate `stored` (first trial `shrink · stored`).
    pub fn new(rule: &Backtracking, stored: f64) -> Self {
        Self::from_streak(rule, stored, 0)
    }

    /// A search with streak `m` (first trial `shrink^(m+1) · stored`, SPEC §6).
    pub fn from_streak(rule: &Backtracking, stored: f64, streak: u32) -> Self {
        Self {
            stored,
            l: rule.start_factor(streak) * stored,
            trials: 0,
            inadmissible: 0,
            max_trials: rule.max_trials,
        }
    }

    /// The next `L` to try, or `None` when the trials are used up.
    pub fn next(&self) -> Option<f64> {
        (self.trials < self.max_trials).then_some(self.l)
    }

    /// Records the outcome of a trial at [`next`](Self::next)'s `L`; returns the finished
    /// search if it was accepted.
    pub fn record<T>(&mut self, outcome: Trial<T>) -> Option<Search<T>> {
        self.trials += 1;
        match outcome {
            Trial::Accepted(candidate) => {
                return Some(Search {
                    accepted: Some(candidate),
                    lipschitz: self.l,
                    trials: self.trials,
                    inadmissible: self.inadmissible,
                });
            }
            Trial::Inadmissible => self.inadmissible += 1,
            Trial::Rejected => {}
        }
        self.l *= 2.0;
        None
    }

    /// The outcome of a search that ran out of trials: nothing accepted, and the stored
    /// estimate kept.
    pub fn give_up<T>(self) -> Search<T> {
        Search {
            accepted: None,
            lipschitz: self.stored,
            trials: self.trials,
            inadmissible: self.inadmissible,
        }
    }
}

/// Several independent searches side by side (the batched schedule, one per `k`): each
/// round tries every undecided search's next `L`, and the caller evaluates all of them in
/// one stacked tensor operation. Searches that were never started (`None`) stay `None`.
#[derive(Debug)]
pub struct Lockstep<T> {
    runs: Vec<Option<SearchRun>>,
    found: Vec<Option<Search<T>>>,
}

impl<T> Lockstep<T> {
    /// The searches, `None` for a slot with nothing to search.
    pub fn new(runs: Vec<Option<SearchRun>>) -> Self {
        let found = runs.iter().map(|_| None).collect();
        Self { runs, found }
    }

    /// The `L` each search tries this round (`None` where it is decided or idle), or `None`
    /// when no search has a trial left.
    pub fn round(&self) -> Option<Vec<Option<f64>>> {
        let trials: Vec<Option<f64>> = self
            .runs
            .iter()
            .map(|r| r.as_ref().and_then(SearchRun::next))
            .collect();
        trials.iter().any(Option::is_some).then_some(trials)
    }

    /// Records search `i`'s outcome for the `L` [`round`](Self::round) gave it.
    pub fn record(&mut self, i: usize, outcome: Trial<T>) {
        let run = self.runs[i].as_mut().expect("a running search");
        if let Some(found) = run.record(outcome) {
            self.found[i] = Some(found);
            self.runs[i] = None;
        }
    }

    /// Every search's result; those that ran out of trials give up.
    pub fn finish(self) -> Vec<Option<Search<T>>> {
        self.runs
            .into_iter()
            .zip(self.found)
            .map(|(run, found)| found.or_else(|| run.map(SearchRun::give_up)))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lockstep_searches_decide_independently() {
        let rule = Backtracking {
            max_trials: 3,
            ..Backtracking::default()
        };
        let runs = vec![
            Some(SearchRun::new(&rule, 10.0)),
            None,
            Some(SearchRun::new(&rule, 1.0)),
        ];
        let mut lockstep = Lockstep::new(runs);
        let mut rounds = Vec::new();
        while let Some(trials) = lockstep.round() {
            rounds.push(trials.clone());
            // Search 0 accepts its second trial; search 2 never accepts.
            if let Some(l) = trials[0] {
                lockstep.record(
                    0,
                    if l > 10.0 {
                        Trial::Accepted(l)
                    } else {
                        Trial::Rejected
                    },
                );
            }
            if trials[2].is_some() {
                lockstep.record(2, Trial::Rejected);
            }
        }
        assert_eq!(rounds.len(), 3);
        assert_eq!(rounds[1], vec![Some(18.0), None, Some(1.8)]);
        assert_eq!(rounds[2], vec![None, None, Some(3.6)]);
        let [a, b, c]: [Option<Search<f64>>; 3] = lockstep.finish().try_into().unwrap();
        let (a, c) = (a.unwrap(), c.unwrap());
        assert_eq!((a.accepted, a.lipschitz, a.trials), (Some(18.0), 18.0, 2));
        assert!(b.is_none());
        assert_eq!((c.accepted, c.lipschitz, c.trials), (None, 1.0, 3));
    }

    #[test]
    fn decrease_test_and_slack() {
        let b = Backtracking::default();
        assert!(b.accepts(1.0, 1.0, 0.0, 0.0, 1.0, 0.0));
        assert!(b.accepts(1.0 + 5e-7, 1.0, 0.0, 0.0, 1.0, 1e-6));
        assert!(!b.accepts(1.0 + 5e-7, 1.0, 0.0, 0.0, 1.0, 0.0));
        assert!(!b.accepts(1.0 + 2e-6, 1.0, 0.0, 0.0, 1.0, 1e-6));
        assert!(b.accepts(1.5, 1.0, -0.5, 2.0, 1.0, 0.0)); // 1.5 <= 1 − 0.5 + 1
        assert!(!b.accepts(f64::INFINITY, 1.0, 0.0, 0.0, 1.0, 0.0));
        assert!(!b.accepts(f64::NAN, 1.0, 0.0, 0.0, 1.0, 0.0));
        let bad = Backtracking { shrink: 1.5, ..b };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("shrink = 1.5")
        );
    }

    #[test]
    fn a_search_doubles_from_the_shrunk_estimate_and_stores_the_accepted_l() {
        let rule = Backtracking::default();
        let mut tried = Vec::new();
        let found = rule
            .search(10.0, |l| {
                tried.push(l);
                Ok(match tried.len() {
                    1 => Trial::Inadmissible,
                    2 => Trial::Rejected,
                    _ => Trial::Accepted(l),
                })
            })
            .unwrap();
        assert_eq!(tried, vec![9.0, 18.0, 36.0]);
        assert_eq!(found.accepted, Some(36.0));
        assert_eq!(
            (found.lipschitz, found.trials, found.inadmissible),
            (36.0, 3, 1)
        );
    }

    #[test]
    fn a_streak_accelerates_the_first_trial_but_not_the_estimate_kept_on_giving_up() {
        let rule = Backtracking {
            max_trials: 2,
            ..Backtracking::default()
        };
        assert_eq!(rule.start_factor(0), 0.9);
        assert!((rule.start_factor(2) - 0.729).abs() < 1e-15);
        let mut tried = Vec::new();
        let found = rule
            .search_from(100.0, 1, |l| {
                tried.push(l);
                Ok(Trial::<()>::Rejected)
            })
            .unwrap();
        assert!((tried[0] - 81.0).abs() < 1e-12 && (tried[1] - 162.0).abs() < 1e-12);
        // SPEC §6, *Giving up*: the value the step started from, before the factor.
        assert_eq!(found.lipschitz, 100.0);
    }

    #[test]
    fn a_search_that_gives_up_keeps_the_estimate_it_started_from() {
        let rule = Backtracking {
            max_trials: 5,
            ..Backtracking::default()
        };
        let found = rule.search(10.0, |_| Ok(Trial::<()>::Rejected)).unwrap();
        assert_eq!(found.accepted, None);
        assert_eq!(found.trials, 5);
        // Not 0.9 · 10 · 2⁵: the next sweep starts again from 0.9 · 10.
        assert_eq!(found.lipschitz, 10.0);
    }
}
