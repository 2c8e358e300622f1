//! Where a composed pose's error comes from: each contributor's error mapped linearly into the
//! pose's left perturbation, so the covariance splits into random and systematic parts and
//! into an error budget that adds up by construction.
//!
//! A pose's error `xi` (the left perturbation `[rho (mm); phi (rad)]`) is modelled as
//! `xi = sum_c F_c u_c`: one term per contributor `c`, `u_c` a standard normal vector of that
//! contributor alone (independent of every other contributor's) and `F_c` its factor, 6 x 6
//! for a six-dimensional contributor and 6 x [`FACTOR_COLUMNS`] for a camera's intrinsics.
//! Its covariance is `sum_c F_c F_c^T`, each term that contributor's share. The contributors:
//!
//! * a measured link's **noise** (pixel noise through PnP, a sample's own covariance): new in
//!   every sample, so it averages down;
//! * a camera's **intrinsics** (focal lengths, principal point, distortion, from its
//!   calibration's covariance through PnP's sensitivity): the same error in every frame of
//!   that camera, so it does not average down, and two links one camera sees share it;
//! * a calibrated link's **calibration**: the same in every result until it is recalibrated.
//!
//! A contributor that reaches a pose along two routes (one camera seeing two markers of a
//! path, or two fused paths) adds its factors, not its covariances: the correlation is kept.
//! Composition maps every factor by the adjoint of what follows it, exactly as the covariance
//! is mapped in [`super::compose_path`]; fusion maps each path's factors by its weight in the
//! fused estimate.

use super::{ChainError, Direction, Fused, LinkId, Path, fuse};
use crate::geometry::{Mat6, Pose, PoseCov, adjoint, symmetrize};
use nalgebra::{SMatrix, SymmetricEigen};

/// The columns of the widest factor: as many as a camera's intrinsics in the widest lens model
/// (`fx fy cx cy`, `k1 k2 p1 p2 k3`, `k4 k5 k6`, `s1 s2 s3 s4`).
pub const FACTOR_COLUMNS: usize = 16;

/// A contributor's factor: its error's effect on a pose's left perturbation per unit of its
/// standard normal vector. Each contributor keeps one width: six columns for what is
/// six-dimensional (a sample's noise, a link's calibration), [`FACTOR_COLUMNS`] for a camera's
/// intrinsics, so the common terms cost a 6 x 6 product.
// Both sizes are values copied through the hot loops of composition; boxing the wide one would
// allocate at every mapping of a camera's term.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Factor {
    /// Six columns: a contributor of six dimensions.
    Six(Mat6),
    /// A column per intrinsic of the widest lens model.
    Intrinsics(SMatrix<f64, 6, FACTOR_COLUMNS>),
}

impl Factor {
    /// `F F^T`, not yet symmetrized.
    fn outer(&self) -> Mat6 {
        match self {
            Factor::Six(f) => f * f.transpose(),
            Factor::Intrinsics(f) => f * f.transpose(),
        }
    }

    /// `m F`.
    pub fn mapped(&self, m: &Mat6) -> Factor {
        match self {
            Factor::Six(f) => Factor::Six(m * f),
            Factor::Intrinsics(f) => Factor::Intrinsics(m * f),
        }
    }

    /// The factor with every column, zero beyond its own.
    pub fn widened(&self) -> SMatrix<f64, 6, FACTOR_COLUMNS> {
        match self {
            Factor::Six(f) => {
                let mut wide = SMatrix::<f64, 6, FACTOR_COLUMNS>::zeros();
                wide.fixed_view_mut::<6, 6>(0, 0).copy_from(f);
                wide
            }
            Factor::Intrinsics(f) => *f,
        }
    }

    /// Adds `other`, of the same contributor (so the same width; a mixed sum is widened).
    fn add(&mut self, other: &Factor) {
        match (self as &mut Factor, other) {
            (Factor::Six(a), Factor::Six(b)) => *a += b,
            (Factor::Intrinsics(a), Factor::Intrinsics(b)) => *a += b,
            (this, other) => *this = Factor::Intrinsics(this.widened() + other.widened()),
        }
    }
}

/// The covariance of a camera's intrinsics, in the order `fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6
/// s1 s2 s3 s4` (rows and columns beyond the camera's lens model zero).
pub type IntrinsicsCovariance = SMatrix<f64, FACTOR_COLUMNS, FACTOR_COLUMNS>;

/// Something whose error reaches a composed pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Contributor {
    /// A measured link's noise: random, new in every sample.
    Noise(LinkId),
    /// A camera's intrinsics and distortion (the camera's index in the installation):
    /// systematic, the same in every frame of the camera.
    Intrinsics(usize),
    /// A calibrated link's calibration: systematic.
    Calibration(LinkId),
}

impl Contributor {
    /// True for what averages down over samples (a link's noise).
    pub fn is_random(self) -> bool {
        matches!(self, Contributor::Noise(_))
    }

    /// What kind of contributor it is.
    pub fn kind(self) -> ContributorKind {
        match self {
            Contributor::Noise(_) => ContributorKind::Noise,
            Contributor::Intrinsics(_) => ContributorKind::Intrinsics,
            Contributor::Calibration(_) => ContributorKind::Calibration,
        }
    }

    /// Which part of the uncertainty it is.
    pub fn part(self) -> UncertaintyPart {
        if self.is_random() {
            UncertaintyPart::Random
        } else {
            UncertaintyPart::Systematic
        }
    }
}

crate::words! {
    /// What kind of contributor to a result's uncertainty.
    pub enum ContributorKind("uncertainty contributor") {
        /// A measured link's noise (pixel noise through PnP): random, averaged by the filter.
        Noise = "noise",
        /// A camera's intrinsics and distortion, from its calibration's covariance:
        /// systematic, the same in every frame of the camera.
        Intrinsics = "intrinsics",
        /// A calibrated link's calibration: systematic.
        Calibration = "calibration",
    }
}

crate::words! {
    /// Which part of a result's uncertainty a contributor is.
    pub enum UncertaintyPart("uncertainty part") {
        /// Averages down over samples.
        Random = "random",
        /// The same in every result: no filtering reduces it.
        Systematic = "systematic",
    }
}

/// One contributor's term of a pose's error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Term {
    /// Whose error.
    pub contributor: Contributor,
    /// Its factor (see the module docs).
    pub factor: Factor,
}

impl Term {
    /// Its covariance, `F F^T`.
    pub fn covariance(&self) -> Mat6 {
        symmetrize(&self.factor.outer())
    }
}

/// A pose's error as a sum of independent contributors' terms (see the module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ErrorTerms {
    terms: Vec<Term>,
}

impl ErrorTerms {
    /// No error.
    pub fn none() -> Self {
        Self::default()
    }

    /// One contributor's term.
    pub fn of(contributor: Contributor, factor: Factor) -> Self {
        Self {
            terms: vec![Term {
                contributor,
                factor,
            }],
        }
    }

    /// Adds a contributor's factor, to its term if it has one already (a correlated route).
    pub fn add(&mut self, contributor: Contributor, factor: Factor) {
        match self.terms.iter_mut().find(|t| t.contributor == contributor) {
            Some(t) => t.factor.add(&factor),
            None => self.terms.push(Term {
                contributor,
                factor,
            }),
        }
    }

    /// Adds every term of `other` mapped by `m` (`m F` for each factor).
    pub fn add_mapped(&mut self, other: &ErrorTerms, m: &Mat6) {
        for t in &other.terms {
            self.add(t.contributor, t.factor.mapped(m));
        }
    }

    /// The terms, in the order their contributors were first added.
    pub fn terms(&self) -> &[Term] {
        &self.terms
    }

    /// The covariance of the terms whose contributors `keep` accepts.
    pub fn covariance_of(&self, keep: impl Fn(Contributor) -> bool) -> Mat6 {
        let mut out = Mat6::zeros();
        for t in self.terms.iter().filter(|t| keep(t.contributor)) {
            out += t.factor.outer();
        }
        symmetrize(&out)
    }

    /// The whole covariance.
    pub fn total(&self) -> Mat6 {
        if self.terms.is_empty() {
            return Mat6::zeros();
        }
        self.covariance_of(|_| true)
    }

    /// The random and the systematic parts, in one pass.
    pub fn parts(&self) -> (Mat6, Mat6) {
        let (mut random, mut systematic) = (Mat6::zeros(), Mat6::zeros());
        for t in &self.terms {
            let c = t.factor.outer();
            if t.contributor.is_random() {
                random += c;
            } else {
                systematic += c;
            }
        }
        (symmetrize(&random), symmetrize(&systematic))
    }

    /// The random part: the measured links' noise.
    pub fn random(&self) -> Mat6 {
        self.covariance_of(Contributor::is_random)
    }

    /// The systematic part: cameras' intrinsics and calibrations.
    pub fn systematic(&self) -> Mat6 {
        self.covariance_of(|c| !c.is_random())
    }
}

/// A pose with its error terms.
#[derive(Debug, Clone, PartialEq)]
pub struct SourcedPose {
    /// The mean pose.
    pub pose: Pose,
    /// Its error, by contributor.
    pub terms: ErrorTerms,
}

impl SourcedPose {
    /// The identity, exactly (a placeholder for a link that is missing).
    pub fn identity() -> Self {
        Self {
            pose: Pose::identity(),
            terms: ErrorTerms::none(),
        }
    }

    /// The pose with its whole covariance.
    pub fn total(&self) -> PoseCov {
        PoseCov {
            pose: self.pose,
            cov: self.terms.total(),
        }
    }

    /// The pose with its random covariance alone.
    pub fn random(&self) -> PoseCov {
        PoseCov {
            pose: self.pose,
            cov: self.terms.random(),
        }
    }
}

/// A factor `F` with `F F^T = cov` for a 6x6 covariance (symmetric, positive semi-definite):
/// its Cholesky factor, or the symmetric square root where it is singular.
pub fn factor_of_covariance(cov: &Mat6) -> Factor {
    match symmetrize(cov).cholesky() {
        Some(c) => Factor::Six(c.l()),
        None => {
            let e = SymmetricEigen::new(symmetrize(cov));
            Factor::Six(
                e.eigenvectors
                    * Mat6::from_diagonal(&e.eigenvalues.map(|v| v.max(0.0).sqrt()))
                    * e.eigenvectors.transpose(),
            )
        }
    }
}

/// The symmetric square root `L` (`L L^T = cov`) of an intrinsics covariance, which is singular
/// where a calibration kept parameters fixed; negative eigenvalues of rounding count as zero.
pub fn intrinsics_root(cov: &IntrinsicsCovariance) -> IntrinsicsCovariance {
    let s = (cov + cov.transpose()) * 0.5;
    let e = SymmetricEigen::new(s);
    e.eigenvectors
        * IntrinsicsCovariance::from_diagonal(&e.eigenvalues.map(|v| v.max(0.0).sqrt()))
        * e.eigenvectors.transpose()
}

/// Composes a path into `target_from_base` with its error terms: as [`super::compose_path`],
/// each factor instead of each covariance. With the steps applied first to last,
/// `T = A_n ... A_1` (`A_k` the link, or its inverse for an inverted step), link `k`'s error
/// reaches `T` through the adjoint of what is applied after it: `F <- Ad(A_n ... A_(k+1)) F`
/// forwards, `F <- -Ad(A_n ... A_(k+1) L_k^-1) F` inverted (the inverse's error is the
/// link's, negated and moved). Each factor is mapped once.
pub fn compose_path_terms<F>(path: &Path, mut parent_from_child: F) -> SourcedPose
where
    F: FnMut(LinkId) -> SourcedPose,
{
    let links: Vec<(SourcedPose, Direction)> = path
        .steps
        .iter()
        .map(|step| (parent_from_child(step.link), step.direction))
        .collect();
    let applied = |link: &SourcedPose, direction: Direction| match direction {
        Direction::Forward => link.pose,
        Direction::Inverse => link.pose.inverse(),
    };
    let pose = links
        .iter()
        .fold(Pose::identity(), |acc, (l, d)| applied(l, *d) * acc);
    let mut terms = ErrorTerms {
        terms: Vec::with_capacity(links.iter().map(|(l, _)| l.terms.terms.len()).sum()),
    };
    // What is applied after the step being mapped, walking from the last step back.
    let mut after = Pose::identity();
    for (link, direction) in links.iter().rev() {
        let step = applied(link, *direction);
        let map = match direction {
            Direction::Forward => adjoint(&after),
            Direction::Inverse => -adjoint(&(after * step)),
        };
        terms.add_mapped(&link.terms, &map);
        after *= step;
    }
    SourcedPose { pose, terms }
}

/// Fuses estimates of the same pose reached by link-disjoint paths: the pose and the
/// consistency as [`fuse`] gives them from each path's whole covariance, the fused error terms
/// as each path's terms weighted by its share `P I_p` (`P` the fused covariance, `I_p` the
/// path's information). A contributor on several paths (a camera that sees markers of two)
/// adds its weighted factors, so the fused covariance keeps the correlation [`fuse`] leaves
/// out.
pub fn fuse_terms(
    mut estimates: Vec<SourcedPose>,
    probability: f64,
) -> Result<(SourcedPose, Fused), ChainError> {
    if estimates.len() == 1
        && let Some(single) = estimates.pop()
    {
        let fused = Fused {
            estimate: single.total(),
            consistency: None,
        };
        return Ok((single, fused));
    }
    let totals: Vec<PoseCov> = estimates.iter().map(SourcedPose::total).collect();
    let fused = fuse(&totals, probability)?;
    let mut terms = ErrorTerms::none();
    for (index, (e, t)) in estimates.iter().zip(&totals).enumerate() {
        let info = symmetrize(&t.cov)
            .cholesky()
            .ok_or(ChainError::SingularCovariance { index })?
            .inverse();
        terms.add_mapped(&e.terms, &(fused.estimate.cov * info));
    }
    let sourced = SourcedPose {
        pose: fused.estimate.pose,
        terms,
    };
    Ok((sourced, fused))
}

/// One contributor's share of a pose's variance on each axis users read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BudgetLine {
    /// Whose error.
    pub contributor: Contributor,
    /// Its variance on each axis: rotation about x, y, z (rad^2, as
    /// [`PoseCov::reported_sigmas`] reads rotation), then the translation components x, y, z
    /// (mm^2).
    pub variance: [f64; 6],
}

/// A pose's variance on each axis split by contributor: the lines add up to the total by
/// construction (each axis' variance is linear in the covariance, and the covariance is the
/// sum of the contributors').
#[derive(Debug, Clone, PartialEq)]
pub struct Budget {
    /// One line per contributor, in the order of the terms.
    pub lines: Vec<BudgetLine>,
    /// The whole variance on each axis (as the lines' variance).
    pub total: [f64; 6],
}

/// The variance of each axis users read of a pose with covariance `cov` (see
/// [`BudgetLine::variance`]).
pub fn axis_variances(pose: &Pose, cov: &Mat6) -> [f64; 6] {
    let t = PoseCov {
        pose: *pose,
        cov: *cov,
    }
    .translation_covariance();
    [
        cov[(3, 3)],
        cov[(4, 4)],
        cov[(5, 5)],
        t[(0, 0)],
        t[(1, 1)],
        t[(2, 2)],
    ]
}

/// A budget's variances (rad^2 for rotation, mm^2) as sigmas in arc-seconds and mm.
pub fn budget_sigmas(variance: [f64; 6]) -> [f64; 6] {
    std::array::from_fn(|a| {
        let s = variance[a].max(0.0).sqrt();
        if a < 3 {
            s * crate::geometry::ARCSEC_PER_RAD
        } else {
            s
        }
    })
}

impl Budget {
    /// The variance on each axis of the lines of one part (random or systematic).
    pub fn part_variance(&self, part: UncertaintyPart) -> [f64; 6] {
        let mut v = [0.0; 6];
        for line in self.lines.iter().filter(|l| l.contributor.part() == part) {
            for (a, x) in v.iter_mut().zip(line.variance) {
                *a += x;
            }
        }
        v
    }

    /// A line's share of each axis' variance (0 to 1; the shares of an axis add up to 1, and
    /// an axis without variance gives every line a share of 0).
    pub fn share(&self, line: &BudgetLine) -> [f64; 6] {
        std::array::from_fn(|a| {
            if self.total[a] > 0.0 {
                line.variance[a] / self.total[a]
            } else {
                0.0
            }
        })
    }

    /// The lines with their shares, the largest share (over the six axes) first.
    pub fn lines_by_share(&self) -> Vec<(BudgetLine, [f64; 6])> {
        let mut lines: Vec<(BudgetLine, [f64; 6])> =
            self.lines.iter().map(|l| (*l, self.share(l))).collect();
        let largest = |s: &[f64; 6]| s.iter().copied().fold(0.0, f64::max);
        lines.sort_by(|a, b| largest(&b.1).total_cmp(&largest(&a.1)));
        lines
    }

    /// The budget of a pose as its terms give it (a raw result: every contributor as it is).
    pub fn of(sourced: &SourcedPose) -> Self {
        let lines: Vec<BudgetLine> = sourced
            .terms
            .terms()
            .iter()
            .map(|t| BudgetLine {
                contributor: t.contributor,
                variance: axis_variances(&sourced.pose, &t.covariance()),
            })
            .collect();
        let total = axis_variances(&sourced.pose, &sourced.terms.total());
        Self { lines, total }
    }

    /// The budget of a filtered pose: the systematic lines as the terms give them (filtering
    /// does not reduce them), and the random part the filter's own covariance
    /// `filtered_random`, shared on each axis among the measured links' noise in proportion to
    /// their share of the terms' random variance on that axis (the filter is one linear map of
    /// every link's noise, so their shares go through it together). The axes are those of the
    /// filtered pose `filtered` (its covariance the filter's random one).
    pub fn filtered(sourced: &SourcedPose, filtered: &PoseCov) -> Self {
        let sourced = &SourcedPose {
            pose: filtered.pose,
            terms: sourced.terms.clone(),
        };
        let filtered_random = &filtered.cov;
        let mut budget = Self::of(sourced);
        let raw_random = axis_variances(&sourced.pose, &sourced.terms.random());
        let filtered = axis_variances(&sourced.pose, filtered_random);
        let scale: [f64; 6] = std::array::from_fn(|a| {
            if raw_random[a] > 0.0 {
                filtered[a] / raw_random[a]
            } else {
                0.0
            }
        });
        for line in budget
            .lines
            .iter_mut()
            .filter(|l| l.contributor.is_random())
        {
            for (v, s) in line.variance.iter_mut().zip(scale) {
                *v *= s;
            }
        }
        let systematic = axis_variances(&sourced.pose, &sourced.terms.systematic());
        budget.total = std::array::from_fn(|a| {
            systematic[a]
                + if raw_random[a] > 0.0 {
                    filtered[a]
                } else {
                    0.0
                }
        });
        budget
    }
}
