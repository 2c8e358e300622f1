//! Raw marker observations of an installation: which camera, which marker, which pixels, and
//! the measured link `<camera>_from_<marker>` they give by PnP.
//!
//! [`Observer`] is built once from the installation: per measured link whose parent frame is a
//! configured camera and whose child frame a configured marker, the camera model, the marker's
//! points and ids, and the PnP options (the camera's `pixel_sigma`, the `[pnp]` settings).

use super::{CameraModel, PnpOptions, PnpSolution, solve_pnp};
use crate::chain::LinkId;
use crate::config::{Installation, LinkKind};
use crate::geometry::Vec3;
use nalgebra::Vector2;
use std::collections::HashMap;

/// A camera-marker pair that forms a measured link.
#[derive(Debug, Clone)]
pub struct ObservedLink {
    /// The link `<camera>_from_<marker>`.
    pub link: LinkId,
    /// Its name.
    pub name: String,
    /// The camera.
    pub camera: CameraModel,
    /// The marker's points (mm).
    pub points_mm: Vec<Vec3>,
    /// The marker's point ids, one per point.
    pub ids: Vec<u32>,
    /// How to solve.
    pub options: PnpOptions,
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
    by_pair: HashMap<(String, String), ObservedLink>,
    cameras: Vec<String>,
    markers: Vec<String>,
}

impl Observer {
    /// Every camera-marker link of the installation.
    pub fn new(installation: &Installation) -> Self {
        let mut by_pair = HashMap::new();
        for spec in &installation.links {
            if !matches!(spec.kind, LinkKind::Measured(_)) {
                continue;
            }
            let link = installation.topology.link(spec.id);
            let parent = installation.topology.frame_name(link.parent).to_owned();
            let child = installation.topology.frame_name(link.child).to_owned();
            let camera = installation.camera(&parent);
            let marker = installation.marker(&child);
            if let (Some(camera), Some(marker)) = (camera, marker) {
                let options = PnpOptions {
                    pixel_sigma_px: camera.pixel_sigma_px,
                    max_rms_px: installation.pnp.max_reprojection_rms_px,
                    robust: installation.pnp.robust,
                    inlier_threshold_px: installation.pnp.inlier_threshold_px,
                    ..PnpOptions::default()
                };
                by_pair.insert(
                    (parent, child),
                    ObservedLink {
                        link: spec.id,
                        name: spec.name.clone(),
                        camera: CameraModel::from(camera),
                        points_mm: marker.points_mm.iter().map(|p| Vec3::from(*p)).collect(),
                        ids: marker.ids.clone(),
                        options,
                    },
                );
            }
        }
        Self {
            by_pair,
            cameras: installation
                .cameras
                .iter()
                .map(|c| c.frame.clone())
                .collect(),
            markers: installation
                .markers
                .iter()
                .map(|m| m.frame.clone())
                .collect(),
        }
    }

    /// The observable links.
    pub fn links(&self) -> impl Iterator<Item = &ObservedLink> {
        self.by_pair.values()
    }

    /// The link a camera and a marker form.
    pub fn link(&self, camera: &str, marker: &str) -> Result<&ObservedLink, ObservationError> {
        if !self.cameras.iter().any(|c| c == camera) {
            return Err(ObservationError::new(
                "camera",
                format!(
                    "unknown camera `{camera}` (configured: {})",
                    self.cameras.join(", ")
                ),
            ));
        }
        if !self.markers.iter().any(|m| m == marker) {
            return Err(ObservationError::new(
                "marker",
                format!(
                    "unknown marker `{marker}` (configured: {})",
                    self.markers.join(", ")
                ),
            ));
        }
        self.by_pair
            .get(&(camera.to_owned(), marker.to_owned()))
            .ok_or_else(|| {
                ObservationError::new(
                    "marker",
                    format!("no measured link `{camera}_from_{marker}`: camera {camera} is not configured to see marker {marker}"),
                )
            })
    }

    /// Solves one observation: `points_px` in the marker's point order, or paired with `ids`.
    pub fn solve(
        &self,
        camera: &str,
        marker: &str,
        points_px: &[[f64; 2]],
        ids: Option<&[u32]>,
    ) -> Result<(&ObservedLink, PnpSolution), ObservationError> {
        let link = self.link(camera, marker)?;
        let marker_points: Vec<Vec3> = match ids {
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
                link.points_mm.clone()
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
                out
            }
        };
        let pixels: Vec<Vector2<f64>> =
            points_px.iter().map(|p| Vector2::new(p[0], p[1])).collect();
        let solution = solve_pnp(&link.camera, &marker_points, &pixels, &link.options)
            .map_err(|e| ObservationError::new("points_px", e.to_string()))?;
        Ok((link, solution))
    }
}
