//! The measurement model of an installation: what the core needs to know about it.
//!
//! Frames and links (the [`Topology`]), which links are calibrated and which measured (with
//! each filter's tuning), the targets and how each is reached, the cameras and markers that
//! form the measured links, and how marker observations are solved. Nothing here knows about
//! files, servers, tokens or Rerun: the `config` adapter reads the installation file into a
//! [`Model`] plus the deployment settings only the adapters see.
//!
//! [`Observer`] derives the camera-marker links from a model and solves raw observations of
//! them into link samples; [`identify`] finds a marker's points among a frame's detected discs
//! and solves its pose, corrected for the discs' perspective eccentricity; [`observe_frame`]
//! does both for every marker a camera sees in one frame.

mod frame;
mod identify;
mod observation;
mod pacing;
mod search;

pub use frame::{FrameObservation, MarkerInFrame, observe_frame, observe_frame_paced};
pub use identify::{
    Completed, Found, NotFound, Reach, complete, identify, identify_within, search_squares,
};
pub use observation::{ObservationError, ObservedLink, Observer};
pub use pacing::SearchPacer;
pub use search::{HINT_ACCEPT_DEG, HINT_REFUSE_DEG, find_without_prior, layout_symmetries};

use crate::alarms::AlarmThresholds;
use crate::chain::{
    Factor, FrameId, IntrinsicsCovariance, LinkId, Resolution, Topology, intrinsics_root,
};
use crate::filter::{BankSettings, FilterTuning};
use crate::geometry::{Pose, PoseCov, ReportedSigmas};
use crate::vision::{CameraModel, Polarity};

/// Index of a target in a [`Model`]'s `targets`: what the bank, the store and the service
/// call a target by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TargetId(pub usize);

/// The measurement model of one installation.
#[derive(Debug, Clone)]
pub struct Model {
    /// Cameras, by frame.
    pub cameras: Vec<Camera>,
    /// Cooperative markers, by frame.
    pub markers: Vec<Marker>,
    /// The frame/link graph.
    pub topology: Topology,
    /// Link settings, indexed by [`LinkId`].
    pub links: Vec<LinkSpec>,
    /// The targets and how each is reached.
    pub targets: Vec<TargetSpec>,
    /// Settings of the filter bank.
    pub filter: BankSettings,
    /// How marker observations are solved.
    pub pnp: PnpSettings,
}

/// A camera of the installation: its frame, its calibration and its pixel noise.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// The camera's frame.
    pub frame: String,
    /// Intrinsics, distortion and image size.
    pub intrinsics: CameraModel,
    /// Standard deviation of a measured image point (px); with points from frames, the part
    /// the detector's own uncertainty does not cover (calibration residuals, the air).
    pub pixel_sigma_px: f64,
    /// Electrons per digital number, when known: the detector then counts the signal's shot
    /// noise in each point's uncertainty (the background's noise is always counted).
    pub gain_e_per_dn: Option<f64>,
    /// The covariance of the intrinsics' estimate (`fx fy cx cy k1 k2 p1 p2 k3`), as its
    /// calibration reports it; `None`: the intrinsics are taken as exact.
    pub intrinsics_covariance: Option<IntrinsicsCovariance>,
}

impl Camera {
    /// The square root of the intrinsics' covariance (see [`crate::chain::intrinsics_root`]),
    /// `None` when the intrinsics are taken as exact.
    pub fn intrinsics_root(&self) -> Option<IntrinsicsCovariance> {
        self.intrinsics_covariance.as_ref().map(intrinsics_root)
    }
}

/// A cooperative marker: known points in its own frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Marker {
    /// The marker's frame.
    pub frame: String,
    /// The points (mm, in the marker frame).
    pub points_mm: Vec<[f64; 3]>,
    /// Point ids, one per point (defaults to 0, 1, 2, ...).
    pub ids: Vec<u32>,
    /// What the points are in an image, when the marker is seen in frames.
    pub target: Option<DiscTarget>,
    /// The unit normal of each point's disc (marker frame), one per point; the marker's +z
    /// unless the file gives them.
    pub normals: Vec<[f64; 3]>,
}

/// A marker point as a flat disc whose centre is the point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiscTarget {
    /// The disc's diameter (mm).
    pub diameter_mm: f64,
    /// Bright on dark or dark on bright.
    pub polarity: Polarity,
}

/// Pose estimation of marker observations.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PnpSettings {
    /// A solution with a larger reprojection RMS is refused (px).
    pub max_reprojection_rms_px: f64,
    /// Retry a refused observation by RANSAC, leaving out points off the consensus.
    pub robust: bool,
    /// RANSAC: a point within this reprojection error supports a pose (px).
    pub inlier_threshold_px: f64,
    /// A marker that stays lost is searched for in the whole frame at most once in this much
    /// frame time (s; 0: in every frame): see [`SearchPacer`].
    pub lost_search_interval_s: f64,
}

/// A link of the installation.
#[derive(Debug, Clone)]
pub struct LinkSpec {
    /// Its id in the topology.
    pub id: LinkId,
    /// `<parent>_from_<child>`.
    pub name: String,
    /// Calibrated or measured.
    pub kind: LinkKind,
}

/// What kind of link.
#[derive(Debug, Clone)]
#[allow(
    clippy::large_enum_variant,
    reason = "a handful of links per installation; boxing buys nothing"
)]
pub enum LinkKind {
    /// A rigid connection inside a station, calibrated once.
    Calibrated {
        /// The calibrated pose with its uncertainty.
        parent_from_child: PoseCov,
    },
    /// A camera seeing a marker, measured continuously.
    Measured(MeasuredLink),
}

/// Settings of a measured link.
#[derive(Debug, Clone)]
pub struct MeasuredLink {
    /// The filter model and its tuning.
    pub tuning: FilterTuning,
    /// Measurement noise used when a sample carries none.
    pub default_sigmas: ReportedSigmas,
    /// How often samples are expected (Hz).
    pub expected_rate_hz: f64,
    /// The designed pose, where known (simulation, visualisation before the first sample).
    pub nominal: Option<Pose>,
}

/// A target: a frame whose pose relative to its base is monitored.
#[derive(Debug, Clone)]
pub struct TargetSpec {
    /// The target's name (its frame).
    pub name: String,
    /// The target frame.
    pub frame: FrameId,
    /// The base frame.
    pub base: FrameId,
    /// How it is reached.
    pub resolution: Resolution,
    /// Deformation thresholds.
    pub alarms: AlarmThresholds,
    /// Its filter's model and tuning as the installation sets them; `None`: the most dynamic
    /// of its measured links', fitted from the data when oscillatory.
    pub filter: Option<TargetFilter>,
}

/// A target filter's model and tuning set by the installation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetFilter {
    /// The model and its tuning to start from.
    pub tuning: FilterTuning,
    /// Whether the oscillation's strengths are fitted from the data (oscillatory only), or
    /// kept as set.
    pub fit_from_data: bool,
}

impl Model {
    /// The name users know a contributor to a result's uncertainty by: its link's (noise,
    /// calibration) or its camera's (intrinsics).
    pub fn contributor_name(&self, contributor: crate::chain::Contributor) -> &str {
        use crate::chain::Contributor;
        match contributor {
            Contributor::Noise(l) | Contributor::Calibration(l) => &self.links[l.0].name,
            Contributor::Intrinsics(i) => &self.cameras[i].frame,
        }
    }

    /// The settings of a link.
    pub fn link(&self, id: LinkId) -> &LinkSpec {
        &self.links[id.0]
    }

    /// The link with this name.
    pub fn link_by_name(&self, name: &str) -> Option<&LinkSpec> {
        self.topology.link_id(name).map(|id| self.link(id))
    }

    /// The targets' names, in the installation's order.
    pub fn target_names(&self) -> Vec<String> {
        self.targets.iter().map(|t| t.name.clone()).collect()
    }

    /// The target with this name.
    pub fn target(&self, name: &str) -> Option<&TargetSpec> {
        self.targets.iter().find(|t| t.name == name)
    }

    /// The id of the target with this name.
    pub fn target_id(&self, name: &str) -> Option<TargetId> {
        self.targets
            .iter()
            .position(|t| t.name == name)
            .map(TargetId)
    }

    /// Every target's id, with its settings, in the installation's order.
    pub fn target_ids(&self) -> impl Iterator<Item = (TargetId, &TargetSpec)> {
        self.targets
            .iter()
            .enumerate()
            .map(|(i, t)| (TargetId(i), t))
    }

    /// The camera on this frame.
    pub fn camera(&self, frame: &str) -> Option<&Camera> {
        self.cameras.iter().find(|c| c.frame == frame)
    }

    /// The marker on this frame.
    pub fn marker(&self, frame: &str) -> Option<&Marker> {
        self.markers.iter().find(|m| m.frame == frame)
    }

    /// The camera (by its index in `cameras`) and the marker of a measured link
    /// `<camera>_from_<marker>`, when both are configured.
    pub fn camera_and_marker(&self, link: LinkId) -> Option<(usize, &Camera, &Marker)> {
        let ends = self.topology.link(link);
        let parent = self.topology.frame_name(ends.parent);
        let child = self.topology.frame_name(ends.child);
        let index = self.cameras.iter().position(|c| c.frame == parent)?;
        Some((index, &self.cameras[index], self.marker(child)?))
    }

    /// The systematic error a measured link's samples take from their camera's intrinsics, at
    /// a pose of the link: the camera's index and the factor `S L` (`S` PnP's sensitivity to
    /// the intrinsics at that pose over the marker's points, `L` the square root of the
    /// intrinsics' covariance; see [`crate::chain`]'s error terms). `None` for a camera taken
    /// as exact, a link that is not camera-to-marker, or a pose the marker's points do not
    /// determine.
    pub fn intrinsics_factor(
        &self,
        link: LinkId,
        camera_from_marker: &Pose,
    ) -> Option<(usize, Factor)> {
        let (index, camera, marker) = self.camera_and_marker(link)?;
        let root = camera.intrinsics_root()?;
        let points: Vec<crate::geometry::Vec3> = marker
            .points_mm
            .iter()
            .map(|p| crate::geometry::Vec3::from(*p))
            .collect();
        let s = crate::vision::intrinsics_sensitivity(
            &camera.intrinsics,
            &points,
            camera_from_marker,
            None,
        )?;
        Some((index, Factor::Intrinsics(s * root)))
    }
}
