//! One measured link's filter: state, prediction, gated update, outlier runs, re-initialisation.

use super::NS_PER_S;
use super::kalman::{Update, gated_update, gated_update_direct, is_positive_definite, van_loan};
use super::tuning::{FilterTuning, MotionModel};
use crate::chain::chi_square_quantile;
use crate::geometry::{
    Mat6, Pose, PoseCov, Twist, adjoint, se3_exp, se3_left_jacobian, se3_log, symmetrize,
};
use nalgebra::SMatrix;

type Mat12 = SMatrix<f64, 12, 12>;

/// The `constant_velocity` rate prior: the twist-rate variance that this many seconds of the
/// model's acceleration noise produces (`q * t`).
pub const CV_RATE_PRIOR_S: f64 = 10.0;
type Mat18 = SMatrix<f64, 18, 18>;

/// What happened to a sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Disposition {
    /// The first sample: the filter starts from it.
    Initialized,
    /// Fused; `nis` is the normalised innovation squared (chi-square, 6 dof, if consistent).
    Fused {
        /// Normalised innovation squared.
        nis: f64,
    },
    /// Over the gate: kept by the caller, flagged, not fused.
    Outlier {
        /// Normalised innovation squared.
        nis: f64,
        /// How many outliers in a row, this one included.
        run_length: usize,
    },
    /// A run of consistent outliers was a real step: the filter restarted from the run.
    Reinitialized {
        /// Normalised innovation squared of this sample against the old state.
        nis: f64,
        /// How many outliers the run had.
        run_length: usize,
    },
    /// Older than the filter's time: not fused (see the module docs).
    OutOfOrder {
        /// How far behind the filter time (s).
        behind_s: f64,
    },
}

crate::words! {
    /// What the filter did with a sample, without the numbers: what is stored with it.
    pub enum DispositionKind("disposition") {
        /// The first sample.
        Initialized = "initialized",
        /// Fused.
        Fused = "fused",
        /// Over the gate, not fused.
        Outlier = "outlier",
        /// The filter restarted from a run of consistent outliers.
        Reinitialized = "reinitialized",
        /// Older than the filter's time, not fused.
        OutOfOrder = "out_of_order",
    }
}

impl Disposition {
    /// Its kind.
    pub fn kind(&self) -> DispositionKind {
        match self {
            Disposition::Initialized => DispositionKind::Initialized,
            Disposition::Fused { .. } => DispositionKind::Fused,
            Disposition::Outlier { .. } => DispositionKind::Outlier,
            Disposition::Reinitialized { .. } => DispositionKind::Reinitialized,
            Disposition::OutOfOrder { .. } => DispositionKind::OutOfOrder,
        }
    }

    /// True when the sample was flagged as an outlier (it may still have triggered a restart).
    pub fn is_outlier(&self) -> bool {
        matches!(
            self,
            Disposition::Outlier { .. } | Disposition::Reinitialized { .. }
        )
    }
}

#[derive(Debug, Clone)]
#[allow(
    clippy::large_enum_variant,
    reason = "one state per link, updated in place at the sample rate: no indirection"
)]
enum State {
    Static {
        pose: Pose,
        p: Mat6,
    },
    ConstantVelocity {
        pose: Pose,
        /// Twist rate `[v (mm/s); w (rad/s)]` in the left frame: `T <- Exp(nu dt) T`.
        nu: Twist,
        /// Boxed, as [`State::Oscillatory`]'s.
        p: Box<Mat12>,
    },
    Oscillatory {
        mean: Pose,
        /// Oscillation `x` per axis: `T = Exp(x) mean`.
        x: Twist,
        /// Its rate.
        v: Twist,
        /// Error state `[d_mean; d_x; d_v]`. Boxed: a filter is the size of its largest state,
        /// and every fused sample keeps a copy among the link's past states (`bank::slot`), so
        /// an unboxed 18 x 18 (2,592 bytes) would make each copy of a static link's filter
        /// about 2.9 KB instead of 512 bytes.
        p: Box<Mat18>,
    },
}

/// The filter of one measured link.
#[derive(Debug, Clone)]
pub struct LinkFilter {
    tuning: FilterTuning,
    gate: f64,
    state: Option<State>,
    time_ns: i64,
    /// The current run of consecutive outliers: time and measurement.
    outlier_run: Vec<(i64, PoseCov)>,
}

impl LinkFilter {
    /// An uninitialised filter; the first sample starts it.
    pub fn new(tuning: FilterTuning) -> Self {
        Self {
            gate: chi_square_quantile(6, tuning.gate_probability),
            tuning,
            state: None,
            time_ns: i64::MIN,
            outlier_run: Vec::new(),
        }
    }

    /// The tuning.
    pub fn tuning(&self) -> &FilterTuning {
        &self.tuning
    }

    /// Changes the tuning from now on, keeping the state: the process noise of the next
    /// prediction is the new tuning's. The motion model cannot change (its state differs).
    pub fn retune(&mut self, tuning: FilterTuning) {
        if tuning.model == self.tuning.model {
            self.gate = chi_square_quantile(6, tuning.gate_probability);
            self.tuning = tuning;
        }
    }

    /// The gate on the normalised innovation squared.
    pub fn gate(&self) -> f64 {
        self.gate
    }

    /// The time of the state (ns), once initialised.
    pub fn time_ns(&self) -> Option<i64> {
        self.state.as_ref().map(|_| self.time_ns)
    }

    /// True when the state covariance is symmetric positive definite.
    pub fn covariance_is_positive_definite(&self) -> bool {
        match &self.state {
            None => true,
            Some(State::Static { p, .. }) => is_positive_definite(p),
            Some(State::ConstantVelocity { p, .. }) => is_positive_definite(p),
            Some(State::Oscillatory { p, .. }) => is_positive_definite(p),
        }
    }

    /// Starts the state from a measurement.
    fn initialize(&mut self, time_ns: i64, z: &PoseCov) {
        let t = &self.tuning;
        self.state = Some(match t.model {
            MotionModel::Static => State::Static {
                pose: z.pose,
                p: z.cov,
            },
            MotionModel::ConstantVelocity => {
                // The rate is unknown: the spread that ten seconds of the model's white-noise
                // acceleration would give a link starting at rest.
                let acc = t.acceleration_density();
                let mut p = Mat12::zeros();
                p.fixed_view_mut::<6, 6>(0, 0).copy_from(&z.cov);
                p.fixed_view_mut::<6, 6>(6, 6)
                    .copy_from(&Mat6::from_diagonal(&(acc * CV_RATE_PRIOR_S)));
                State::ConstantVelocity {
                    pose: z.pose,
                    nu: Twist::zeros(),
                    p: Box::new(p),
                }
            }
            MotionModel::Oscillatory => {
                // Z = Exp(x) M with x at its stationary spread: M = Z - x to first order.
                let var_x = Mat6::from_diagonal(&t.oscillation_variance());
                let (mu, lambda) = t.oscillator_rates();
                let w0_sq = mu * mu + lambda * lambda;
                let var_v = var_x * w0_sq;
                let mut p = Mat18::zeros();
                p.fixed_view_mut::<6, 6>(0, 0).copy_from(&(z.cov + var_x));
                p.fixed_view_mut::<6, 6>(0, 6).copy_from(&(-var_x));
                p.fixed_view_mut::<6, 6>(6, 0).copy_from(&(-var_x));
                p.fixed_view_mut::<6, 6>(6, 6).copy_from(&var_x);
                p.fixed_view_mut::<6, 6>(12, 12).copy_from(&var_v);
                State::Oscillatory {
                    mean: z.pose,
                    x: Twist::zeros(),
                    v: Twist::zeros(),
                    p: Box::new(p),
                }
            }
        });
        self.time_ns = time_ns;
        self.outlier_run.clear();
    }

    /// The state propagated by `dt_s` seconds (`dt_s >= 0`).
    fn propagated(&self, state: &State, dt_s: f64) -> State {
        let t = &self.tuning;
        match state {
            State::Static { pose, p } => State::Static {
                pose: *pose,
                p: symmetrize(&(p + Mat6::from_diagonal(&(t.random_walk_density() * dt_s)))),
            },
            State::ConstantVelocity { pose, nu, p } => {
                let step = nu * dt_s;
                let motion = se3_exp(&step);
                // Exp(d') Exp(nu' dt) T = Exp((nu + dnu) dt) Exp(d) T:
                // d' = Ad(Exp(nu dt)) d + J(nu dt) dt dnu.
                let mut f = Mat12::identity();
                f.fixed_view_mut::<6, 6>(0, 0).copy_from(&adjoint(&motion));
                f.fixed_view_mut::<6, 6>(0, 6)
                    .copy_from(&(se3_left_jacobian(&step) * dt_s));
                let q = t.acceleration_density();
                let mut qd = Mat12::zeros();
                for i in 0..6 {
                    qd[(i, i)] = q[i] * dt_s.powi(3) / 3.0;
                    qd[(i, i + 6)] = q[i] * dt_s * dt_s / 2.0;
                    qd[(i + 6, i)] = q[i] * dt_s * dt_s / 2.0;
                    qd[(i + 6, i + 6)] = q[i] * dt_s;
                }
                let p_new = f * p.as_ref() * f.transpose() + qd;
                State::ConstantVelocity {
                    pose: motion * pose,
                    nu: *nu,
                    p: Box::new((p_new + p_new.transpose()) * 0.5),
                }
            }
            State::Oscillatory { mean, x, v, p } => {
                let (mu, lambda) = t.oscillator_rates();
                let w0_sq = mu * mu + lambda * lambda;
                let a = SMatrix::<f64, 2, 2>::new(0.0, 1.0, -w0_sq, -2.0 * mu);
                // Unit driving density; each axis scales it to its stationary variance.
                let qc = SMatrix::<f64, 2, 2>::new(0.0, 0.0, 0.0, 1.0);
                let (phi, q_unit) = van_loan(&a, &qc, dt_s);
                let q_axis = t.oscillation_variance() * (4.0 * mu * w0_sq);
                let rw = t.random_walk_density() * dt_s;
                let mut f = Mat18::identity();
                let mut qd = Mat18::zeros();
                for i in 0..6 {
                    let (ix, iv) = (6 + i, 12 + i);
                    f[(ix, ix)] = phi[(0, 0)];
                    f[(ix, iv)] = phi[(0, 1)];
                    f[(iv, ix)] = phi[(1, 0)];
                    f[(iv, iv)] = phi[(1, 1)];
                    qd[(i, i)] = rw[i];
                    qd[(ix, ix)] = q_unit[(0, 0)] * q_axis[i];
                    qd[(ix, iv)] = q_unit[(0, 1)] * q_axis[i];
                    qd[(iv, ix)] = q_unit[(1, 0)] * q_axis[i];
                    qd[(iv, iv)] = q_unit[(1, 1)] * q_axis[i];
                }
                let x_new = x * phi[(0, 0)] + v * phi[(0, 1)];
                let v_new = x * phi[(1, 0)] + v * phi[(1, 1)];
                let p_new = f * p.as_ref() * f.transpose() + qd;
                State::Oscillatory {
                    mean: *mean,
                    x: x_new,
                    v: v_new,
                    p: Box::new((p_new + p_new.transpose()) * 0.5),
                }
            }
        }
    }

    /// The pose of a state with its covariance.
    fn pose_of(state: &State) -> PoseCov {
        match state {
            State::Static { pose, p } => PoseCov {
                pose: *pose,
                cov: *p,
            },
            State::ConstantVelocity { pose, p, .. } => PoseCov {
                pose: *pose,
                cov: p.fixed_view::<6, 6>(0, 0).into_owned(),
            },
            State::Oscillatory { mean, x, p, .. } => {
                // T = Exp(x) M; to first order the pose error is d_mean + d_x.
                let h = Self::oscillatory_h();
                PoseCov {
                    pose: se3_exp(x) * mean,
                    cov: symmetrize(&(h * p.as_ref() * h.transpose())),
                }
            }
        }
    }

    fn oscillatory_h() -> SMatrix<f64, 6, 18> {
        let mut h = SMatrix::<f64, 6, 18>::zeros();
        h.fixed_view_mut::<6, 6>(0, 0).copy_from(&Mat6::identity());
        h.fixed_view_mut::<6, 6>(0, 6).copy_from(&Mat6::identity());
        h
    }

    /// The link pose predicted to `time_ns` (not changing the filter). `None` before the first
    /// sample; an error for a time before the filter's.
    pub fn predict(&self, time_ns: i64) -> Option<Result<PoseCov, i64>> {
        let state = self.state.as_ref()?;
        if time_ns < self.time_ns {
            return Some(Err(self.time_ns));
        }
        let dt_s = (time_ns - self.time_ns) as f64 / NS_PER_S;
        Some(Ok(if dt_s == 0.0 {
            Self::pose_of(state)
        } else {
            Self::pose_of(&self.propagated(state, dt_s))
        }))
    }

    /// Feeds one measurement `z` (the link pose `parent_from_child` with its covariance) taken
    /// at `time_ns`.
    pub fn update(&mut self, time_ns: i64, z: &PoseCov) -> Disposition {
        let Some(state) = self.state.as_ref() else {
            self.initialize(time_ns, z);
            return Disposition::Initialized;
        };
        if time_ns < self.time_ns {
            return Disposition::OutOfOrder {
                behind_s: (self.time_ns - time_ns) as f64 / NS_PER_S,
            };
        }
        let dt_s = (time_ns - self.time_ns) as f64 / NS_PER_S;
        let predicted = self.propagated(state, dt_s);
        let current = Self::pose_of(&predicted);
        let y = se3_log(&(z.pose * current.pose.inverse()));
        let Some(outcome) = Self::correct(predicted, &y, &z.cov, self.gate) else {
            // The innovation covariance was not positive definite: the measurement covariance
            // is unusable. Treat it as an outlier rather than corrupt the state.
            return self.outlier(time_ns, z, f64::INFINITY);
        };
        match outcome {
            Ok((state, nis)) => {
                self.state = Some(state);
                self.time_ns = time_ns;
                self.outlier_run.clear();
                Disposition::Fused { nis }
            }
            Err(nis) => self.outlier(time_ns, z, nis),
        }
    }

    /// The gated update of a predicted state: `Ok((corrected state, nis))`, `Err(nis)` over
    /// the gate, `None` when the innovation covariance is unusable.
    fn correct(
        predicted: State,
        y: &Twist,
        r: &Mat6,
        gate: f64,
    ) -> Option<Result<(State, f64), f64>> {
        let six = |d: &[f64], offset: usize| Twist::from_fn(|i, _| d[offset + i]);
        Some(match predicted {
            State::Static { pose, p } => match gated_update_direct(&p, y, r, gate)? {
                Update::Fused { delta, p, nis } => Ok((
                    State::Static {
                        pose: se3_exp(&delta) * pose,
                        p,
                    },
                    nis,
                )),
                Update::Rejected { nis } => Err(nis),
            },
            State::ConstantVelocity { pose, nu, p } => {
                let mut h = SMatrix::<f64, 6, 12>::zeros();
                h.fixed_view_mut::<6, 6>(0, 0).copy_from(&Mat6::identity());
                match gated_update(&p, &h, y, r, gate)? {
                    Update::Fused { delta, p, nis } => {
                        let d = delta.as_slice();
                        Ok((
                            State::ConstantVelocity {
                                pose: se3_exp(&six(d, 0)) * pose,
                                nu: nu + six(d, 6),
                                p: Box::new(p),
                            },
                            nis,
                        ))
                    }
                    Update::Rejected { nis } => Err(nis),
                }
            }
            State::Oscillatory { mean, x, v, p } => {
                match gated_update(&p, &Self::oscillatory_h(), y, r, gate)? {
                    Update::Fused { delta, p, nis } => {
                        let d = delta.as_slice();
                        Ok((
                            State::Oscillatory {
                                mean: se3_exp(&six(d, 0)) * mean,
                                x: x + six(d, 6),
                                v: v + six(d, 12),
                                p: Box::new(p),
                            },
                            nis,
                        ))
                    }
                    Update::Rejected { nis } => Err(nis),
                }
            }
        })
    }

    /// Records an outlier; restarts the filter when the run is long and self-consistent.
    fn outlier(&mut self, time_ns: i64, z: &PoseCov, nis: f64) -> Disposition {
        // A run continues only while its samples agree with each other: the newest must agree
        // with the previous one within the combined measurement covariance.
        if let Some((_, last)) = self.outlier_run.last() {
            let d = se3_log(&(z.pose * last.pose.inverse()));
            let s = symmetrize(&(z.cov + last.cov));
            let consistent = s
                .cholesky()
                .map(|c| d.dot(&c.solve(&d)) <= self.gate)
                .unwrap_or(false);
            if !consistent {
                self.outlier_run.clear();
            }
        }
        self.outlier_run.push((time_ns, *z));
        let run_length = self.outlier_run.len();
        if run_length >= self.tuning.reinit_after_outliers.max(1) {
            self.initialize(time_ns, z);
            return Disposition::Reinitialized { nis, run_length };
        }
        Disposition::Outlier { nis, run_length }
    }
}

/// A pose as `[tx, ty, tz, qw, qx, qy, qz]` (mm, unit quaternion).
fn pose_numbers(p: &Pose) -> [f64; 7] {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    [t.x, t.y, t.z, q.w, q.i, q.j, q.k]
}

fn pose_from_numbers(n: &[f64; 7]) -> Pose {
    Pose::from_parts(
        nalgebra::Translation3::new(n[0], n[1], n[2]),
        nalgebra::UnitQuaternion::new_normalize(nalgebra::Quaternion::new(n[3], n[4], n[5], n[6])),
    )
}

/// One outlier of a pending run, as plain numbers.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OutlierRecord {
    /// Its time (ns).
    pub time_ns: i64,
    /// Its pose `[tx, ty, tz, qw, qx, qy, qz]`.
    pub pose: [f64; 7],
    /// Its covariance, row-major.
    pub cov: Vec<f64>,
}

/// A link filter's state as plain numbers, so that a service can persist it and restart from
/// exactly where it stopped.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LinkFilterRecord {
    /// The model's name.
    pub model: String,
    /// The state's time (ns).
    pub time_ns: i64,
    /// The pose (static, constant-velocity) or the mean pose (oscillatory), `[t; q]`.
    pub pose: [f64; 7],
    /// The twist rate (constant-velocity), or `x` then `v` (oscillatory); empty for static.
    pub rates: Vec<f64>,
    /// The error-state covariance, row-major.
    pub p: Vec<f64>,
    /// The pending run of outliers.
    pub outlier_run: Vec<OutlierRecord>,
}

impl LinkFilter {
    /// The state as plain numbers; `None` before the first sample.
    pub fn record(&self) -> Option<LinkFilterRecord> {
        let state = self.state.as_ref()?;
        let (pose, rates, p) = match state {
            State::Static { pose, p } => (pose_numbers(pose), Vec::new(), p.as_slice().to_vec()),
            State::ConstantVelocity { pose, nu, p } => (
                pose_numbers(pose),
                nu.as_slice().to_vec(),
                p.as_slice().to_vec(),
            ),
            State::Oscillatory { mean, x, v, p } => (
                pose_numbers(mean),
                x.iter().chain(v.iter()).copied().collect(),
                p.as_slice().to_vec(),
            ),
        };
        Some(LinkFilterRecord {
            model: self.tuning.model.name().to_owned(),
            time_ns: self.time_ns,
            pose,
            rates,
            p,
            outlier_run: self
                .outlier_run
                .iter()
                .map(|(t, z)| OutlierRecord {
                    time_ns: *t,
                    pose: pose_numbers(&z.pose),
                    cov: z.cov.as_slice().to_vec(),
                })
                .collect(),
        })
    }

    /// A filter restored from a record; an error when the record does not fit the tuning's
    /// model (the installation changed) or its numbers are malformed.
    pub fn restore(tuning: FilterTuning, record: &LinkFilterRecord) -> Result<Self, String> {
        if record.model != tuning.model.name() {
            return Err(format!(
                "the stored state is of model `{}`, the link is now `{}`",
                record.model,
                tuning.model.name()
            ));
        }
        let n = match tuning.model {
            MotionModel::Static => 6,
            MotionModel::ConstantVelocity => 12,
            MotionModel::Oscillatory => 18,
        };
        let rates_len = n - 6;
        if record.p.len() != n * n
            || record.rates.len() != rates_len
            || record
                .p
                .iter()
                .chain(&record.rates)
                .chain(&record.pose)
                .any(|v| !v.is_finite())
        {
            return Err("the stored state has the wrong size or a non-finite number".into());
        }
        let pose = pose_from_numbers(&record.pose);
        let twist = |offset: usize| Twist::from_fn(|i, _| record.rates[offset + i]);
        let state = match tuning.model {
            MotionModel::Static => State::Static {
                pose,
                p: Mat6::from_column_slice(&record.p),
            },
            MotionModel::ConstantVelocity => State::ConstantVelocity {
                pose,
                nu: twist(0),
                p: Box::new(Mat12::from_column_slice(&record.p)),
            },
            MotionModel::Oscillatory => State::Oscillatory {
                mean: pose,
                x: twist(0),
                v: twist(6),
                p: Box::new(Mat18::from_column_slice(&record.p)),
            },
        };
        let mut outlier_run = Vec::with_capacity(record.outlier_run.len());
        for o in &record.outlier_run {
            if o.cov.len() != 36 {
                return Err("a stored outlier has a malformed covariance".into());
            }
            outlier_run.push((
                o.time_ns,
                PoseCov {
                    pose: pose_from_numbers(&o.pose),
                    cov: Mat6::from_column_slice(&o.cov),
                },
            ));
        }
        let mut filter = LinkFilter::new(tuning);
        filter.state = Some(state);
        filter.time_ns = record.time_ns;
        filter.outlier_run = outlier_run;
        Ok(filter)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A filter is the size of its largest state, and a measured link keeps a copy of its
    /// filter after every fused sample (`bank::slot`): the 12- and 18-state covariances are
    /// boxed, so a static link's copies are not the size of an oscillatory one's.
    #[test]
    fn a_filter_is_smaller_than_the_larger_models_covariances() {
        let size = std::mem::size_of::<LinkFilter>();
        assert!(
            size < std::mem::size_of::<Mat12>(),
            "a LinkFilter is {size} bytes"
        );
        assert!(size >= std::mem::size_of::<Mat6>());
    }
}
