//! The procedure's steps, one after another: the still window, then each known move.
//!
//! A step waits for the operator (who keeps everything still, or moves a target by the stated
//! displacement) to say it is in place; from the newest result at that moment its results
//! settle for `settle_ns`, then its window of `window_ns` is measured. A window is judged when
//! results past its end are in: when the halves of every target it measures agree, the step's
//! figures are taken; otherwise the window slides on by half its length, at most
//! [`MAX_SLIDES`] times, after which the step is recorded as not settled (and fails).
//!
//! Pure: the caller reads the results of a window and hands them in.

use crate::deformation::MeasuredPose;

use super::{
    AcceptanceError, Displacement, Limits, MoveFigures, Settling, StillFigures, WindowMean,
    move_figures, settling, still_figures, window_mean,
};

/// How many times a window that has not settled slides on before the step fails.
pub const MAX_SLIDES: u32 = 4;

/// A known move the operator makes.
#[derive(Debug, Clone, PartialEq)]
pub struct PlannedMove {
    /// Its name, as the record and the operator read it.
    pub name: String,
    /// The target it moves (its index in the installation).
    pub target: usize,
    /// The displacement from where the target stood still.
    pub displacement: Displacement,
}

/// The procedure an installation states.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// How many targets the installation has (all are measured still).
    pub targets: usize,
    /// The still window's length (ns).
    pub still_ns: i64,
    /// A move's window length (ns).
    pub step_ns: i64,
    /// How long results settle after the operator says a step is in place (ns).
    pub settle_ns: i64,
    /// The known moves, in order.
    pub moves: Vec<PlannedMove>,
    /// The limits.
    pub limits: Limits,
}

impl Plan {
    /// How many steps: the still window and each move.
    pub fn steps(&self) -> usize {
        1 + self.moves.len()
    }

    /// The name of step `k`.
    pub fn step_name(&self, k: usize) -> &str {
        match k {
            0 => "still",
            k => &self.moves[k - 1].name,
        }
    }

    /// What step `k` is.
    pub fn step_kind(&self, k: usize) -> super::StepKind {
        if k == 0 {
            super::StepKind::Still
        } else {
            super::StepKind::Move
        }
    }

    /// The targets step `k` measures: every target still, a move's own target.
    pub fn step_targets(&self, k: usize) -> Vec<usize> {
        match k {
            0 => (0..self.targets).collect(),
            k => vec![self.moves[k - 1].target],
        }
    }
}

/// What a step found.
#[derive(Debug, Clone, PartialEq)]
pub enum StepFigures {
    /// The still window: each target's mean and figures, in installation order.
    Still(Vec<(WindowMean, StillFigures)>),
    /// A known move.
    Move(Box<MoveFigures>),
    /// The window did not settle after [`MAX_SLIDES`] slides: the last halves' agreement.
    NotSettled(Settling),
    /// The figures could not be computed (too few results, a degenerate window).
    Unmeasured(AcceptanceError),
}

impl StepFigures {
    /// Whether the step passed.
    pub fn passed(&self) -> bool {
        match self {
            StepFigures::Still(t) => t.iter().all(|(_, f)| f.passed),
            StepFigures::Move(m) => m.passed,
            StepFigures::NotSettled(_) | StepFigures::Unmeasured(_) => false,
        }
    }
}

/// A step done: its window and what it found.
#[derive(Debug, Clone, PartialEq)]
pub struct StepDone {
    /// Its window `[from_ns, to_ns]` (measurement time).
    pub window_ns: (i64, i64),
    /// What it found.
    pub figures: StepFigures,
}

crate::words! {
    /// Where a run of the procedure is.
    pub enum Phase("acceptance phase") {
        /// The operator must place the current step and say so.
        AwaitingOperator = "awaiting_operator",
        /// The step's results settle, or its window fills.
        Measuring = "measuring",
        /// Every step is done.
        Finished = "finished",
    }
}

/// What handing in a window's results did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offered {
    /// The step is done; the next awaits the operator (or the procedure finished).
    StepDone,
    /// The window had not settled: it slid on.
    Slid,
}

/// A run of the procedure.
#[derive(Debug, Clone)]
pub struct Procedure {
    plan: Plan,
    done: Vec<StepDone>,
    window_ns: Option<(i64, i64)>,
    slides: u32,
    still_means: Vec<Option<WindowMean>>,
}

impl Procedure {
    /// A new run, awaiting the operator for the still window.
    pub fn new(plan: Plan) -> Self {
        let targets = plan.targets;
        Self {
            plan,
            done: Vec::new(),
            window_ns: None,
            slides: 0,
            still_means: vec![None; targets],
        }
    }

    /// Its plan.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The steps done so far.
    pub fn done(&self) -> &[StepDone] {
        &self.done
    }

    /// The current step (`None` once finished).
    pub fn current(&self) -> Option<usize> {
        (self.done.len() < self.plan.steps()).then_some(self.done.len())
    }

    /// Where the run is.
    pub fn phase(&self) -> Phase {
        match (self.current(), self.window_ns) {
            (None, _) => Phase::Finished,
            (Some(_), None) => Phase::AwaitingOperator,
            (Some(_), Some(_)) => Phase::Measuring,
        }
    }

    /// The current step's window `[from_ns, to_ns]` while measuring.
    pub fn window_ns(&self) -> Option<(i64, i64)> {
        self.window_ns
    }

    /// How many times the current window slid.
    pub fn slides(&self) -> u32 {
        self.slides
    }

    /// The operator placed the current step; `newest_ns` is the newest result's time then.
    /// False when no step awaits the operator.
    pub fn ready(&mut self, newest_ns: i64) -> bool {
        let Some(k) = self.current() else {
            return false;
        };
        if self.window_ns.is_some() {
            return false;
        }
        let length = if k == 0 {
            self.plan.still_ns
        } else {
            self.plan.step_ns
        };
        let from = newest_ns.saturating_add(self.plan.settle_ns);
        self.window_ns = Some((from, from.saturating_add(length)));
        self.slides = 0;
        true
    }

    /// Hands in the current window's results of each target the step measures (in
    /// [`Plan::step_targets`]'s order, each oldest first); called once results past the
    /// window's end are in.
    pub fn offer(&mut self, results: &[Vec<MeasuredPose>]) -> Offered {
        let (Some(k), Some(window)) = (self.current(), self.window_ns) else {
            return Offered::StepDone;
        };
        let halves: Result<Vec<Settling>, AcceptanceError> = results
            .iter()
            .map(|points| {
                let (a, b) = points.split_at(points.len() / 2);
                settling(&window_mean(a)?, &window_mean(b)?)
            })
            .collect();
        let figures = match halves {
            Err(e) => StepFigures::Unmeasured(e),
            Ok(halves) => match halves.iter().find(|s| !s.settled()) {
                Some(_) if self.slides < MAX_SLIDES => {
                    let half = (window.1 - window.0) / 2;
                    self.window_ns = Some((window.0 + half, window.1 + half));
                    self.slides += 1;
                    return Offered::Slid;
                }
                Some(unsettled) => StepFigures::NotSettled(*unsettled),
                None => self.figures(k, results),
            },
        };
        self.done.push(StepDone {
            window_ns: window,
            figures,
        });
        self.window_ns = None;
        self.slides = 0;
        Offered::StepDone
    }

    fn figures(&mut self, k: usize, results: &[Vec<MeasuredPose>]) -> StepFigures {
        let limits = self.plan.limits;
        if k == 0 {
            let mut still = Vec::new();
            for (t, points) in results.iter().enumerate() {
                let figures = window_mean(points)
                    .and_then(|m| still_figures(points, &m, &limits).map(|f| (m, f)));
                match figures {
                    Ok((m, f)) => {
                        self.still_means[t] = Some(m);
                        still.push((m, f));
                    }
                    Err(e) => return StepFigures::Unmeasured(e),
                }
            }
            return StepFigures::Still(still);
        }
        let planned = &self.plan.moves[k - 1];
        let Some(still) = self.still_means.get(planned.target).copied().flatten() else {
            return StepFigures::Unmeasured(AcceptanceError::Degenerate(
                "the target has no still window to move from".into(),
            ));
        };
        match window_mean(&results[0])
            .and_then(|m| move_figures(&still, &m, &planned.displacement, &limits))
        {
            Ok(m) => StepFigures::Move(Box::new(m)),
            Err(e) => StepFigures::Unmeasured(e),
        }
    }

    /// Whether every step passed (false while steps remain).
    pub fn passed(&self) -> bool {
        self.current().is_none() && self.done.iter().all(|d| d.figures.passed())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{ARCSEC_PER_RAD, Mat6, Pose, PoseCov, Twist, se3_exp};
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    fn plan() -> Plan {
        Plan {
            targets: 1,
            still_ns: 10_000_000_000,
            step_ns: 4_000_000_000,
            settle_ns: 1_000_000_000,
            moves: vec![PlannedMove {
                name: "z +20 mm".into(),
                target: 0,
                displacement: Displacement {
                    rotation_arcsec: [0.0; 3],
                    translation_mm: [0.0, 0.0, 20.0],
                },
            }],
            limits: Limits {
                still_rms_arcsec: 10.0,
                still_rms_mm: 0.1,
                move_arcsec: 10.0,
                move_mm: 0.1,
            },
        }
    }

    fn cov() -> Mat6 {
        let (r, t) = ((2.0 / ARCSEC_PER_RAD).powi(2), 0.01_f64.powi(2));
        Mat6::from_diagonal(&nalgebra::Vector6::new(t, t, t, r, r, r))
    }

    fn points(rng: &mut StdRng, truth: &Pose, n: usize, drift_mm: f64) -> Vec<MeasuredPose> {
        let l = cov().cholesky().unwrap().l();
        (0..n)
            .map(|i| {
                let mut xi = l * Twist::from_fn(|_, _| rng.sample::<f64, _>(StandardNormal));
                xi[0] += drift_mm * i as f64 / n as f64;
                MeasuredPose::whole(PoseCov {
                    pose: se3_exp(&xi) * truth,
                    cov: cov(),
                })
            })
            .collect()
    }

    #[test]
    fn a_run_goes_still_then_moves_and_passes_when_the_moves_are_made() {
        let mut rng = StdRng::seed_from_u64(1);
        let still = se3_exp(&Twist::new(100.0, -50.0, 3000.0, 0.1, 0.2, 0.3));
        let mut run = Procedure::new(plan());
        assert_eq!(run.phase(), Phase::AwaitingOperator);
        assert!(run.ready(5_000_000_000));
        assert_eq!(run.window_ns(), Some((6_000_000_000, 16_000_000_000)));
        assert!(
            !run.ready(7_000_000_000),
            "a step measuring is not placed again"
        );
        assert_eq!(
            run.offer(&[points(&mut rng, &still, 100, 0.0)]),
            Offered::StepDone
        );
        assert_eq!(run.phase(), Phase::AwaitingOperator);
        assert_eq!(run.current(), Some(1));
        let moved = plan().moves[0].displacement.g0_from_g().inverse() * still;
        assert!(run.ready(20_000_000_000));
        assert_eq!(
            run.offer(&[points(&mut rng, &moved, 40, 0.0)]),
            Offered::StepDone
        );
        assert_eq!(run.phase(), Phase::Finished);
        assert!(run.passed(), "{:?}", run.done());
    }

    #[test]
    fn a_window_still_moving_slides_on_and_fails_the_step_when_it_never_settles() {
        let mut rng = StdRng::seed_from_u64(2);
        let still = se3_exp(&Twist::new(100.0, -50.0, 3000.0, 0.1, 0.2, 0.3));
        let mut run = Procedure::new(plan());
        run.ready(0);
        for slide in 0..MAX_SLIDES {
            assert_eq!(
                run.offer(&[points(&mut rng, &still, 100, 0.5)]),
                Offered::Slid
            );
            assert_eq!(run.slides(), slide + 1);
        }
        assert_eq!(
            run.window_ns(),
            Some((
                1_000_000_000 + 4 * 5_000_000_000,
                11_000_000_000 + 4 * 5_000_000_000
            ))
        );
        assert_eq!(
            run.offer(&[points(&mut rng, &still, 100, 0.5)]),
            Offered::StepDone
        );
        assert!(matches!(run.done()[0].figures, StepFigures::NotSettled(_)));
        assert!(!run.done()[0].figures.passed());
    }

    #[test]
    fn too_few_results_leave_the_step_unmeasured() {
        let mut rng = StdRng::seed_from_u64(3);
        let still = se3_exp(&Twist::new(100.0, -50.0, 3000.0, 0.1, 0.2, 0.3));
        let mut run = Procedure::new(plan());
        run.ready(0);
        assert_eq!(
            run.offer(&[points(&mut rng, &still, 12, 0.0)]),
            Offered::StepDone
        );
        assert!(matches!(
            run.done()[0].figures,
            StepFigures::Unmeasured(AcceptanceError::TooFew { count: 6 })
        ));
    }
}
