//! The layout a recording opens with: the frame tree on the left, below it a tab per camera
//! (its frames with the detected and reprojected points, and its markers not found); per target
//! a tab with the
//! deformation rotation and translation (raw, filtered, 3-sigma band); the links' innovations;
//! the alarm lanes and log. The time panel follows the measurement timeline.

use super::TIMELINE;
use crate::config::Installation;
use crate::model::LinkKind;
use rerun::blueprint::{
    Blueprint, ContainerLike, Horizontal, Spatial2DView, Spatial3DView, StateTimelineView, Tabs,
    TextLogView, TimePanel, TimeSeriesView, Vertical,
};

/// The blueprint of an installation's recordings.
pub(super) fn blueprint(inst: &Installation) -> Blueprint {
    let per_target: Vec<ContainerLike> = inst
        .model
        .targets
        .iter()
        .map(|t| {
            Vertical::new([
                TimeSeriesView::new(format!("{} deformation rotation [arcsec]", t.name))
                    .with_origin(format!("/plots/{}/rotation_arcsec", t.name))
                    .into(),
                TimeSeriesView::new(format!("{} deformation translation [mm]", t.name))
                    .with_origin(format!("/plots/{}/translation_mm", t.name))
                    .into(),
            ])
            .with_name(t.name.clone())
            .into()
        })
        .collect();
    let mut right: Vec<ContainerLike> = vec![Tabs::new(per_target).into()];
    if inst
        .model
        .links
        .iter()
        .any(|l| matches!(l.kind, LinkKind::Measured(_)))
    {
        right.push(
            TimeSeriesView::new("Link innovations (NIS) and outliers")
                .with_origin("/plots/links")
                .into(),
        );
    }
    right.push(
        StateTimelineView::new("Alarm state")
            .with_origin("/alarms")
            .with_contents(["+ /alarms/**", "- /alarms/log"])
            .into(),
    );
    right.push(
        TextLogView::new("Alarm log")
            .with_origin("/alarms/log")
            .into(),
    );
    // The target tabs get the most room, the alarm lanes and log the least.
    let mut shares = vec![4.0, 2.0, 1.0, 1.0];
    shares.drain(1..1 + (4 - right.len()));
    // Per camera a tab: what it sees (its frame with the detected and reprojected points) and
    // its log of markers not found.
    let cameras: Vec<ContainerLike> = inst
        .model
        .cameras
        .iter()
        .filter_map(|c| {
            let path = camera_path(inst, &c.frame)?;
            Some(
                Vertical::new([
                    Spatial2DView::new(format!("Camera {}", c.frame))
                        .with_origin(path)
                        .into(),
                    TextLogView::new(format!("Camera {}: markers not found", c.frame))
                        .with_origin(format!("/cameras/{}", c.frame))
                        .into(),
                ])
                .with_row_shares([4.0, 1.0])
                .with_name(c.frame.clone())
                .into(),
            )
        })
        .collect();
    let frames = Spatial3DView::new("Frames").with_origin("/world").into();
    let left: ContainerLike = if cameras.is_empty() {
        frames
    } else {
        Vertical::new([frames, Tabs::new(cameras).into()])
            .with_row_shares([1.0, 1.0])
            .into()
    };
    Blueprint::new(
        Horizontal::new([left, Vertical::new(right).with_row_shares(shares).into()])
            .with_column_shares([1.0, 1.0]),
    )
    .with_time_panel(TimePanel::new().with_timeline(TIMELINE))
}

/// The entity path of a camera's pinhole (its frame's path in the frame tree, then `camera`).
pub(super) fn camera_path(inst: &Installation, camera: &str) -> Option<String> {
    let f = inst.model.topology.frame_id(camera)?;
    super::logger::frame_paths(inst)
        .into_iter()
        .nth(f.0)
        .map(|p| format!("/{p}/camera"))
}
