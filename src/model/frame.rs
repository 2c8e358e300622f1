//! One camera frame turned into marker observations: the discs detected once per polarity the
//! camera's markers use, then each marker the camera sees through a measured link identified
//! among them ([`identify`]) from the poses the caller predicts for its link, tried in order.
//!
//! Decoding the file and choosing the predictions (the filtered pose of the link at the frame's
//! time, the pose in the previous frame) belong to the callers, the nominal pose comes last; the frame's size is checked against the
//! camera's here, so every caller refuses the same frames.

use super::identify::{Found, NotFound, identify};
use super::observation::{ObservationError, ObservedLink, Observer};
use crate::geometry::Pose;
use crate::vision::{DetectSettings, GreyImage, Polarity, detect};

/// What one frame showed of one marker.
#[derive(Debug, Clone)]
pub struct MarkerInFrame<'a> {
    /// The camera-marker link.
    pub link: &'a ObservedLink,
    /// Its points and pose, or why it was not found.
    pub result: Result<Found, NotFound>,
}

/// What one frame showed.
#[derive(Debug, Clone)]
pub struct FrameObservation<'a> {
    /// Discs detected (over every polarity searched).
    pub blobs: usize,
    /// Each marker of a measured link of the camera, in installation order.
    pub markers: Vec<MarkerInFrame<'a>>,
}

/// Detects and identifies the markers `camera` sees in `image`. `predictions(link)` gives the
/// poses `camera_from_marker` to predict a marker's points from, most trusted first, and the
/// link's nominal pose is tried after them; the next is tried only when one finds nothing.
pub fn observe_frame<'a>(
    observer: &'a Observer,
    camera: &str,
    image: &GreyImage,
    predictions: impl Fn(&ObservedLink) -> Vec<Pose>,
) -> Result<FrameObservation<'a>, ObservationError> {
    let links: Vec<&ObservedLink> = observer
        .links()
        .filter(|l| l.camera_frame == camera)
        .collect();
    let model = observer.camera(camera)?;
    let gain_e_per_dn = links.first().and_then(|l| l.gain_e_per_dn);
    if (image.width_px(), image.height_px()) != (model.width_px, model.height_px) {
        return Err(ObservationError {
            field: "body",
            message: format!(
                "the frame is {} x {} px but camera {camera} is {} x {} px",
                image.width_px(),
                image.height_px(),
                model.width_px,
                model.height_px
            ),
        });
    }
    let mut blobs_of: Vec<(Polarity, Vec<crate::vision::Blob>)> = Vec::new();
    for polarity in links.iter().filter_map(|l| l.target.map(|t| t.polarity)) {
        if !blobs_of.iter().any(|(p, _)| *p == polarity) {
            let settings = DetectSettings {
                polarity,
                gain_e_per_dn,
                ..DetectSettings::default()
            };
            blobs_of.push((polarity, detect(image, &settings)));
        }
    }
    let markers = links
        .into_iter()
        .map(|link| {
            let result = match link.target {
                None => Err(NotFound::NoTarget),
                Some(target) => {
                    let blobs = blobs_of
                        .iter()
                        .find(|(p, _)| *p == target.polarity)
                        .map(|(_, b)| b.as_slice())
                        .unwrap_or_default();
                    let mut result = Err(NotFound::NoPrediction);
                    for prior in predictions(link).into_iter().chain(link.nominal) {
                        let attempt = identify(link, blobs, Some(&prior));
                        let found = attempt.is_ok();
                        // The first reason is kept: it comes from the most trusted prediction.
                        if found || matches!(result, Err(NotFound::NoPrediction)) {
                            result = attempt;
                        }
                        if found {
                            break;
                        }
                    }
                    result
                }
            };
            MarkerInFrame { link, result }
        })
        .collect();
    Ok(FrameObservation {
        blobs: blobs_of.iter().map(|(_, b)| b.len()).sum(),
        markers,
    })
}
