//! Helpers shared by the integration tests: random poses and covariances, seeded.
#![allow(dead_code)]

pub mod hostile;
pub mod paper;
pub mod postgres;
pub mod process;

use brokenray::geometry::{Mat6, Pose, Rotation, Twist, Vec3, se3_exp};
use nalgebra::{Quaternion, Translation3};
use rand::Rng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};
use std::io::Write as _;
use std::path::{Path, PathBuf};

/// A pose with a uniformly random rotation and a translation within +-`reach_mm` per axis.
/// A random rigid motion of up to `mm` and `deg` per axis.
pub fn jolt(rng: &mut StdRng, mm: f64, deg: f64) -> Pose {
    let r = deg.to_radians();
    se3_exp(&Twist::new(
        rng.random_range(-mm..mm),
        rng.random_range(-mm..mm),
        rng.random_range(-mm..mm),
        rng.random_range(-r..r),
        rng.random_range(-r..r),
        rng.random_range(-r..r),
    ))
}

pub fn random_pose(rng: &mut StdRng, reach_mm: f64) -> Pose {
    let q = Quaternion::new(
        rng.sample::<f64, _>(StandardNormal),
        rng.sample::<f64, _>(StandardNormal),
        rng.sample::<f64, _>(StandardNormal),
        rng.sample::<f64, _>(StandardNormal),
    );
    let t = Vec3::new(
        rng.random_range(-reach_mm..reach_mm),
        rng.random_range(-reach_mm..reach_mm),
        rng.random_range(-reach_mm..reach_mm),
    );
    Pose::from_parts(Translation3::from(t), Rotation::new_normalize(q))
}

/// A random symmetric positive-definite covariance with rotation sigmas near `rot_arcsec` and
/// translation sigmas near `trans_mm`, correlated.
pub fn random_covariance(rng: &mut StdRng, rot_arcsec: f64, trans_mm: f64) -> Mat6 {
    let rot_rad = rot_arcsec / brokenray::geometry::ARCSEC_PER_RAD;
    let scale = [trans_mm, trans_mm, trans_mm, rot_rad, rot_rad, rot_rad];
    let a = Mat6::from_fn(|_, _| rng.sample::<f64, _>(StandardNormal));
    let correlated = (a * a.transpose()) / 6.0 + Mat6::identity() * 0.5;
    Mat6::from_fn(|r, c| correlated[(r, c)] * scale[r] * scale[c])
}

/// A draw of `xi ~ N(0, cov)`.
pub fn sample_twist(rng: &mut StdRng, cov: &Mat6) -> Twist {
    let l = cov.cholesky().expect("covariance is positive definite").l();
    let z = Twist::from_fn(|_, _| StandardNormal.sample(rng));
    l * z
}

/// `Exp(xi) * pose` with `xi ~ N(0, cov)`: a draw from a pose's left-perturbation distribution.
pub fn perturb(rng: &mut StdRng, pose: &Pose, cov: &Mat6) -> Pose {
    se3_exp(&sample_twist(rng, cov)) * pose
}

/// The normalized estimation error squared of an estimate against the truth:
/// `e^T cov^-1 e` with `e = Log(estimate * truth^-1)`, the left perturbation of the covariance.
pub fn nees(estimate: &Pose, truth: &Pose, cov: &Mat6) -> f64 {
    let e = brokenray::geometry::se3_log(&(estimate * truth.inverse()));
    let info = cov.try_inverse().expect("an invertible covariance");
    (e.transpose() * info * e)[(0, 0)]
}

/// Asserts that a NEES summed over `trials` 6-dof estimates lies between the chi-square
/// quantiles `tail` and `1 - tail` of `6 * trials` degrees of freedom.
pub fn assert_summed_nees_within(nees_sum: f64, trials: usize, tail: f64) {
    let dof = 6 * trials;
    let lower = brokenray::chain::chi_square_quantile(dof, tail);
    let upper = brokenray::chain::chi_square_quantile(dof, 1.0 - tail);
    assert!(
        (lower..=upper).contains(&nees_sum),
        "summed NEES {nees_sum:.1} outside [{lower:.1}, {upper:.1}] of chi2({dof}) (mean {:.3}, expected 6)",
        nees_sum / trials as f64
    );
}

/// What some tests need beyond Rust.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Needs {
    /// PostgreSQL 15 and pg_partman (a throwaway cluster is started from them).
    Postgres,
    /// Node.js, playwright-core under `tests/browser` and Chromium (the dashboard's tests).
    Browser,
    /// The Mosquitto MQTT broker (the MQTT output's tests start one on loopback).
    Mosquitto,
}

/// The PostgreSQL 15 binaries the tests start clusters from.
pub fn pg_bin() -> PathBuf {
    std::env::var_os("BROKENRAY_PG_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/lib/postgresql/15/bin"))
}

/// The Mosquitto broker's executable (Debian puts it in /usr/sbin).
pub fn mosquitto_bin() -> PathBuf {
    on_path("mosquitto").unwrap_or_else(|| PathBuf::from("/usr/sbin/mosquitto"))
}

/// An executable on the `PATH`.
pub fn on_path(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|p| p.join(name))
            .find(|p| p.is_file())
    })
}

impl Needs {
    /// What is missing, and how to get it; `None` when nothing is.
    pub fn missing(self) -> Option<String> {
        match self {
            Needs::Postgres => {
                let bin = pg_bin();
                if !bin.join("initdb").exists() {
                    return Some(format!(
                        "PostgreSQL 15 (no {}; Debian: apt-get install postgresql \
                         postgresql-15-partman, or set BROKENRAY_PG_BIN)",
                        bin.join("initdb").display()
                    ));
                }
                let partman = Path::new("/usr/share/postgresql/15/extension/pg_partman.control");
                if std::env::var_os("BROKENRAY_PG_BIN").is_none() && !partman.exists() {
                    return Some(
                        "pg_partman (Debian: apt-get install postgresql-15-partman)".to_owned(),
                    );
                }
                None
            }
            Needs::Mosquitto => (!mosquitto_bin().is_file())
                .then(|| "the Mosquitto broker (Debian: apt-get install mosquitto)".to_owned()),
            Needs::Browser => {
                let mut missing = Vec::new();
                if on_path("node").is_none() {
                    missing.push("Node.js (Debian: nodejs npm)");
                }
                let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/browser");
                if !dir
                    .join("node_modules/playwright-core/package.json")
                    .is_file()
                {
                    missing.push("playwright-core (npm ci --prefix tests/browser)");
                }
                if std::env::var_os("BROKENRAY_CHROMIUM").is_none()
                    && on_path("chromium").is_none()
                    && on_path("chromium-browser").is_none()
                {
                    missing.push("Chromium (Debian: chromium, or set BROKENRAY_CHROMIUM)");
                }
                (!missing.is_empty()).then(|| missing.join(", "))
            }
        }
    }
}

/// True when `test` must be skipped because this machine lacks what `needs` names; it then
/// says so on the terminal (past the test harness's capture), with how to get it. When the
/// environment sets `BROKENRAY_REQUIRE_ALL` (as `scripts/test` and CI do), a missing tool
/// fails the test instead: nothing is skipped there.
pub fn skip_without(needs: Needs, test: &str) -> bool {
    let Some(missing) = needs.missing() else {
        return false;
    };
    assert!(
        std::env::var_os("BROKENRAY_REQUIRE_ALL").is_none(),
        "{test} needs {missing}; `scripts/test` installs what is missing"
    );
    let _ = writeln!(
        std::io::stderr().lock(),
        "\n*** SKIPPED {test}: this machine lacks {missing}. `scripts/test` installs it and \
         runs everything. ***"
    );
    true
}
