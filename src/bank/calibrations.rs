//! The calibrations of calibrated links, each valid from a time, and the stamps that say which
//! calibrations a result was measured with.

use super::*;

/// A calibration of a calibrated link, in force from its time until a later one.
#[derive(Debug, Clone)]
pub(super) struct Calibration {
    /// From when (ns; `i64::MIN` for the installation file's).
    pub(super) valid_from_ns: i64,
    /// The link's pose with its covariance.
    pub(super) parent_from_child: PoseCov,
    /// The stamp of the pose and its covariance (see [`FilterBank::calibration_stamp`]).
    pub(super) stamp: i64,
    /// The covariance's factor, the link's error term (see [`crate::chain`]).
    pub(super) factor: Factor,
}

impl Calibration {
    /// A calibration valid from `valid_from_ns`, with its stamp and factor.
    pub(super) fn new(valid_from_ns: i64, parent_from_child: PoseCov) -> Self {
        Calibration {
            valid_from_ns,
            parent_from_child,
            stamp: pose_stamp(&parent_from_child),
            factor: factor_of_covariance(&parent_from_child.cov),
        }
    }
}

impl FilterBank {
    /// Adds a calibration of a calibrated link, valid from `valid_from_ns` (until a later one);
    /// the filters of the targets it serves start again. Returns false for a measured link.
    pub fn add_calibration(
        &mut self,
        link: LinkId,
        valid_from_ns: i64,
        parent_from_child: PoseCov,
    ) -> bool {
        match self.calibrations.get_mut(link.0) {
            Some(list) if !list.is_empty() => {
                let at = list.partition_point(|c| c.valid_from_ns <= valid_from_ns);
                list.insert(at, Calibration::new(valid_from_ns, parent_from_child));
                // The targets' raw results step with the new calibration: their filters start
                // again from the next one instead of taking the step for a deformation.
                self.restart_targets_of(link);
                true
            }
            _ => false,
        }
    }

    /// Removes a calibration added with [`Self::add_calibration`] (a write that did not commit).
    pub fn remove_calibration(&mut self, link: LinkId, valid_from_ns: i64) {
        if let Some(list) = self.calibrations.get_mut(link.0)
            && let Some(i) = list.iter().rposition(|c| c.valid_from_ns == valid_from_ns)
            && list.len() > 1
        {
            list.remove(i);
        }
    }

    /// The calibrations a target's result at `time_ns` is measured with: its measured links'
    /// cameras and the calibrations of its calibrated links in force then.
    pub fn calibration_stamp(&self, target: TargetId, time_ns: i64) -> CalibrationStamp {
        let stamps = self.model.targets[target.0]
            .resolution
            .paths
            .iter()
            .flat_map(|p| p.links())
            .map(|l| match self.calibration_entry_at(l, time_ns) {
                Some(c) => c.stamp,
                None => self.camera_stamps[l.0],
            });
        CalibrationStamp::of(stamps.map(|s| f64::from_bits(s as u64)))
    }

    /// The calibration of a calibrated link in force at `time_ns`.
    pub fn calibration_at(&self, link: LinkId, time_ns: i64) -> Option<PoseCov> {
        self.calibration_entry_at(link, time_ns)
            .map(|c| c.parent_from_child)
    }

    /// The calibration of a calibrated link in force at `time_ns`, with its stamp and factor.
    pub(super) fn calibration_entry_at(&self, link: LinkId, time_ns: i64) -> Option<&Calibration> {
        let list = self.calibrations.get(link.0)?;
        let at = list.partition_point(|c| c.valid_from_ns <= time_ns);
        list.get(at.checked_sub(1)?)
    }
}

/// The stamp of a calibrated link's calibration: its pose and covariance.
pub(super) fn pose_stamp(c: &PoseCov) -> i64 {
    let t = c.pose.translation.vector;
    let values = [t.x, t.y, t.z]
        .into_iter()
        .chain(c.pose.rotation.coords.iter().copied())
        .chain(c.cov.iter().copied());
    CalibrationStamp::of(values).0
}

/// The stamp of a camera's calibration: its intrinsics and their covariance, over the terms of
/// its lens model (a Brown-Conrady camera's stamp is that of its nine intrinsics, as it always
/// was).
pub(super) fn camera_stamp(camera: &crate::model::Camera) -> i64 {
    let m = &camera.intrinsics;
    let mut values = vec![m.fx_px, m.fy_px, m.cx_px, m.cy_px];
    values.extend_from_slice(m.distortion_coefficients());
    if let Some(c) = &camera.intrinsics_covariance {
        // Column-major, as the 9 x 9 matrix's iteration was.
        let n = 4 + m.distortion_coefficients().len();
        values.extend(c.view((0, 0), (n, n)).iter().copied());
    }
    CalibrationStamp::of(values).0
}
