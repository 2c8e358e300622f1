//! Raw marker observations of an installation: which camera, which marker, which pixels, and
//! the measured link `<camera>_from_<marker>` they give by PnP.
//!
//! [`Observer`] is built once from the installation: per measured link whose parent frame is a
//! configured camera and whose child frame a configured marker, the camera model, the marker's
//! points and ids, and the PnP options (the camera's `pixel_sigma`, the `[pnp]` settings).

use super::{LinkKind, Model};
use crate::chain::LinkId;
use crate::geometry::{Pose, Vec3};
use crate::vision::{CameraModel, PnpOptions, PnpSolution, solve_pnp, solve_pnp_weighted};
use nalgebra::Vector2;
use std::borrow::Cow;

/// A camera-marker pair that forms a measured link.
#[derive(Debug, Clone)]
pub struct ObservedLink {
    /// The camera's frame.
    pub camera_frame: String,
    /// The marker's frame.
    pub marker_frame: String,
    /// The link `<camera>_from_<marker>`.
    pub link: LinkId,
    /// Its name.
    pub name: String,
    /// The camera.
    pub camera: CameraModel,
    /// The camera's electrons per digital number, when known (for the detector's noise).
    pub gain_e_per_dn: Option<f64>,
    /// The marker's points (mm).
    pub points_mm: Vec<Vec3>,
    /// The marker's point ids, one per point.
    pub ids: Vec<u32>,
    /// What the points are in a frame (disc targets), when declared.
    pub target: Option<super::DiscTarget>,
    /// Each point's disc normal (marker frame, unit).
    pub normals: Vec<Vec3>,
    /// How to solve.
    pub options: PnpOptions,
    /// The link's designed `camera_from_marker`, where the installation gives one: the last
    /// prediction of its points in a frame.
    pub nominal: Option<Pose>,
}

/// Why an observation could not be turned into a link sample. `field` names the offending
/// field of the observation.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct ObservationError {
    /// `camera`, `marker`, `points_px`, `ids`, ...
    pub field: &'static str,
    /// What is wrong.
    pub message: String,
}

impl ObservationError {
    fn new(field: &'static str, message: impl Into<String>) -> Self {
        Self {
            field,
            message: message.into(),
        }
    }
}

/// Solves observations of an installation's markers.
#[derive(Debug, Clone, Default)]
pub struct Observer {
    /// A handful per installation: a scan finds one without building a key.
    links: Vec<ObservedLink>,
    cameras: Vec<String>,
    markers: Vec<String>,
}

impl Observer {
    /// Every camera-marker link of the model.
    pub fn new(model: &Model) -> Self {
        let mut links = Vec::new();
        for spec in &model.links {
            if !matches!(spec.kind, LinkKind::Measured(_)) {
                continue;
            }
            let link = model.topology.link(spec.id);
            let parent = model.topology.frame_name(link.parent).to_owned();
            let child = model.topology.frame_name(link.child).to_owned();
            let camera = model.camera(&parent);
            let marker = model.marker(&child);
            if let (Some(camera), Some(marker)) = (camera, marker) {
                let options = PnpOptions {
                    pixel_sigma_px: camera.pixel_sigma_px,
                    max_rms_px: model.pnp.max_reprojection_rms_px,
                    robust: model.pnp.robust,
                    inlier_threshold_px: model.pnp.inlier_threshold_px,
                    ..PnpOptions::default()
                };
                links.push(ObservedLink {
                    camera_frame: parent,
                    marker_frame: child,
                    link: spec.id,
                    name: spec.name.clone(),
                    camera: camera.intrinsics,
                    gain_e_per_dn: camera.gain_e_per_dn,
                    points_mm: marker.points_mm.iter().map(|p| Vec3::from(*p)).collect(),
                    ids: marker.ids.clone(),
                    target: marker.target,
                    normals: marker.normals.iter().map(|n| Vec3::from(*n)).collect(),
                    options,
                    nominal: match &spec.kind {
                        LinkKind::Measured(m) => m.nominal,
                        LinkKind::Calibrated { .. } => None,
                    },
                });
            }
        }
        Self {
            links,
            cameras: model.cameras.iter().map(|c| c.frame.clone()).collect(),
            markers: model.markers.iter().map(|m| m.frame.clone()).collect(),
        }
    }

    /// An observer of the given camera-marker links alone (a bench, a tool looking at one link).
    pub fn from_links(links: Vec<ObservedLink>) -> Self {
        let (mut cameras, mut markers): (Vec<String>, Vec<String>) = (Vec::new(), Vec::new());
        for l in &links {
            if !cameras.contains(&l.camera_frame) {
                cameras.push(l.camera_frame.clone());
            }
            if !markers.contains(&l.marker_frame) {
                markers.push(l.marker_frame.clone());
            }
        }
        Self {
            links,
            cameras,
            markers,
        }
    }

    /// The observable links.
    pub fn links(&self) -> impl Iterator<Item = &ObservedLink> {
        self.links.iter()
    }

    /// The link a camera and a marker form. The names are checked against the configuration
    /// only when no link matches, to say which one is wrong.
    pub fn link(&self, camera: &str, marker: &str) -> Result<&ObservedLink, ObservationError> {
        if let Some(link) = self
            .links
            .iter()
            .find(|l| l.camera_frame == camera && l.marker_frame == marker)
        {
            return Ok(link);
        }
        Err(if !self.cameras.iter().any(|c| c == camera) {
            self.camera_error(camera)
        } else if !self.markers.iter().any(|m| m == marker) {
            ObservationError::new(
                "marker",
                format!(
                    "unknown marker `{marker}` (configured: {})",
                    self.markers.join(", ")
                ),
            )
        } else {
            ObservationError::new(
                "marker",
                format!(
                    "no measured link `{camera}_from_{marker}`: camera {camera} is not configured to see marker {marker}"
                ),
            )
        })
    }

    /// The model of a camera that sees a marker through a measured link; otherwise why not.
    pub fn camera(&self, camera: &str) -> Result<&CameraModel, ObservationError> {
        self.links
            .iter()
            .find(|l| l.camera_frame == camera)
            .map(|l| &l.camera)
            .ok_or_else(|| self.camera_error(camera))
    }

    /// Why `camera` has no observable link: it is not configured, or it sees no marker through
    /// a measured link.
    pub fn camera_error(&self, camera: &str) -> ObservationError {
        if self.cameras.iter().any(|c| c == camera) {
            ObservationError::new(
                "camera",
                format!(
                    "camera {camera} sees no marker through a measured link `{camera}_from_<marker>`"
                ),
            )
        } else {
            ObservationError::new(
                "camera",
                format!(
                    "unknown camera `{camera}` (configured: {})",
                    self.cameras.join(", ")
                ),
            )
        }
    }

    /// Solves one observation: `points_px` in the marker's point order, or paired with `ids`;
    /// with `sigmas_px` (one per point, from a detector) each point weighted by its own
    /// standard deviation, the camera's `pixel_sigma` added in quadrature.
    pub fn solve(
        &self,
        camera: &str,
        marker: &str,
        points_px: &[[f64; 2]],
        ids: Option<&[u32]>,
        sigmas_px: Option<&[f64]>,
    ) -> Result<(&ObservedLink, PnpSolution), ObservationError> {
        let link = self.link(camera, marker)?;
        if let Some(sigmas) = sigmas_px {
            if sigmas.len() != points_px.len() {
                return Err(ObservationError::new(
                    "sigma_px",
                    format!("{} sigma(s) for {} point(s)", sigmas.len(), points_px.len()),
                ));
            }
            if let Some((i, s)) = sigmas
                .iter()
                .enumerate()
                .find(|(_, s)| !(s.is_finite() && **s >= 0.0))
            {
                return Err(ObservationError::new(
                    "sigma_px",
                    format!("sigma {i} must be a finite number >= 0, not {s}"),
                ));
            }
        }
        let marker_points: Cow<'_, [Vec3]> = match ids {
            None => {
                if points_px.len() != link.points_mm.len() {
                    return Err(ObservationError::new(
                        "points_px",
                        format!(
                            "{} point(s) given but marker {marker} has {}; send them all in its order, or give `ids`",
                            points_px.len(),
                            link.points_mm.len()
                        ),
                    ));
                }
                Cow::Borrowed(&link.points_mm)
            }
            Some(ids) => {
                if ids.len() != points_px.len() {
                    return Err(ObservationError::new(
                        "ids",
                        format!("{} id(s) for {} point(s)", ids.len(), points_px.len()),
                    ));
                }
                let mut seen = std::collections::HashSet::new();
                let mut out = Vec::with_capacity(ids.len());
                for id in ids {
                    if !seen.insert(*id) {
                        return Err(ObservationError::new(
                            "ids",
                            format!("id {id} appears twice"),
                        ));
                    }
                    let k = link.ids.iter().position(|m| m == id).ok_or_else(|| {
                        ObservationError::new(
                            "ids",
                            format!("marker {marker} has no point with id {id}"),
                        )
                    })?;
                    out.push(link.points_mm[k]);
                }
                Cow::Owned(out)
            }
        };
        let pixels: Vec<Vector2<f64>> =
            points_px.iter().map(|p| Vector2::new(p[0], p[1])).collect();
        let solution = match sigmas_px {
            None => solve_pnp(&link.camera, &marker_points, &pixels, &link.options),
            Some(sigmas) => {
                solve_pnp_weighted(&link.camera, &marker_points, &pixels, sigmas, &link.options)
            }
        }
        .map_err(|e| ObservationError::new("points_px", e.to_string()))?;
        Ok((link, solution))
    }
}
