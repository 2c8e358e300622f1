//! One camera frame turned into marker observations: the discs detected once per polarity the
//! camera's markers use, only in the part of the frame the predicted marker points' gates reach
//! (a fifth of the frame or less for a marker or two), then each marker the camera sees through
//! a measured link identified among them ([`identify`]) from the poses the caller predicts for
//! its link, tried in order. A marker found so on some of its points is completed with every
//! point that images where its pose puts it; one that leaves visible points out is kept only
//! when its pose is near the prediction (the rest are covered), else searched for afresh.
//! A marker no prediction finds is searched for in the whole frame from its layout alone
//! ([`find_without_prior`]), at the pace the caller allows ([`super::SearchPacer`]); when the
//! gates of the predictions that missed reach over half the frame, the whole frame is detected
//! at once and serves both, so a lost marker's frame is not detected nearly twice. A disc
//! found as a point of two markers refuses both.
//!
//! Decoding the file and choosing the predictions (the filtered pose of the link at the frame's
//! time, the pose in the previous frame) belong to the callers; the nominal pose comes last.
//! The frame's size is checked against the camera's here, so every caller refuses the same
//! frames.

use super::identify::{
    Found, GATE_MIN_PX, NotFound, Reach, complete, identify, identify_within, search_squares,
};
use super::observation::{ObservationError, ObservedLink, Observer};
use super::search::find_without_prior;
use crate::geometry::Pose;
use crate::vision::{Blob, DetectSettings, GreyImage, Polarity, SearchArea, detect_in};
use std::borrow::Cow;

/// The share of the frame beyond which the gates of the predictions that missed are not
/// detected alone: the whole frame is, once (see [`observe_frame_paced`]).
const WHOLE_FRAME_SHARE: f64 = 0.5;

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
    /// Discs detected (over every polarity searched) in the searched part of the frame.
    pub blobs: usize,
    /// The share of the frame searched, summed over the polarities searched: only the tiles
    /// the predictions' gates reach are (0 when nothing predicts a marker).
    pub searched_fraction: f64,
    /// Each marker of a measured link of the camera, in installation order.
    pub markers: Vec<MarkerInFrame<'a>>,
}

/// Detects and identifies the markers `camera` sees in `image`. `predictions(link)` gives the
/// poses `camera_from_marker` to predict a marker's points from, most trusted first, and the
/// link's nominal pose is tried after them; the next is tried only when one finds nothing. A
/// marker no prediction finds is searched for in the whole frame.
pub fn observe_frame<'a>(
    observer: &'a Observer,
    camera: &str,
    image: &GreyImage,
    predictions: impl Fn(&ObservedLink) -> Vec<Pose>,
) -> Result<FrameObservation<'a>, ObservationError> {
    observe_frame_paced(observer, camera, image, predictions, |_| Ok(()))
}

/// [`observe_frame`], where `whole_frame(link)` says whether a marker no prediction finds may
/// be searched for in the whole frame, or how long (s) until it may ([`super::SearchPacer`];
/// it is asked as often as needed, so it must not change what it answers within a frame);
/// one that may not is [`NotFound::SearchPaced`]. When no marker may, the whole frame is not
/// searched at all.
pub fn observe_frame_paced<'a>(
    observer: &'a Observer,
    camera: &str,
    image: &GreyImage,
    predictions: impl Fn(&ObservedLink) -> Vec<Pose>,
    whole_frame: impl Fn(&ObservedLink) -> Result<(), f64>,
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
    // Every pose each link's points are predicted from, most trusted first.
    let priors: Vec<Vec<Pose>> = links
        .iter()
        .map(|l| predictions(l).into_iter().chain(l.nominal).collect())
        .collect();
    let mut polarities: Vec<Polarity> = Vec::new();
    for polarity in links.iter().filter_map(|l| l.target.map(|t| t.polarity)) {
        if !polarities.contains(&polarity) {
            polarities.push(polarity);
        }
    }
    let area_of = |squares: &mut dyn Iterator<Item = ([f64; 2], f64)>| {
        let mut area = SearchArea::empty(model.width_px, model.height_px);
        for (centre_px, half_side_px) in squares {
            area.add_square(centre_px, half_side_px);
        }
        area
    };
    let detect_area = |polarity: Polarity, area: &SearchArea| {
        let settings = DetectSettings {
            polarity,
            gain_e_per_dn,
            ..DetectSettings::default()
        };
        (detect_in(image, &settings, area), area.fraction())
    };
    let detect_around = |polarity: Polarity, squares: &mut dyn Iterator<Item = ([f64; 2], f64)>| {
        detect_area(polarity, &area_of(squares))
    };
    let of_polarity =
        |link: &ObservedLink, polarity: Polarity| link.target.map(|t| t.polarity) == Some(polarity);
    let mut results: Vec<Result<Found, NotFound>> = links
        .iter()
        .map(|l| {
            Err(match l.target {
                None => NotFound::NoTarget,
                Some(_) => NotFound::NoPrediction,
            })
        })
        .collect();
    let (mut blobs, mut searched) = (0, 0.0);
    for polarity in polarities {
        // First only close to the points of each link's most trusted prediction: when the
        // prediction is good every point is there and the marker is found as a search of the
        // whole frame would find it (`Reach::Near`).
        let (near, fraction) = detect_around(
            polarity,
            &mut links
                .iter()
                .zip(&priors)
                .filter(|(l, _)| of_polarity(l, polarity))
                .filter_map(|(l, p)| p.first().map(|prior| search_squares(l, prior, Reach::Near)))
                .flatten(),
        );
        searched += fraction;
        let mut last_blobs = near.len();
        let mut missing = Vec::new();
        for (i, (link, priors)) in links.iter().zip(&priors).enumerate() {
            if !of_polarity(link, polarity) {
                continue;
            }
            if let Some(prior) = priors.first() {
                match identify_within(link, &near, Some(prior), Reach::Near) {
                    Ok(found) => results[i] = Ok(found),
                    Err(_) => missing.push(i),
                }
            }
        }
        // Then, for the markers not found so, as far as every prediction's full gates reach,
        // each prediction in turn; a marker found so is completed with every point that
        // images near where its pose puts it.
        if !missing.is_empty() {
            let wide_area = area_of(
                &mut missing
                    .iter()
                    .flat_map(|&i| priors[i].iter().map(move |p| (i, p)))
                    .flat_map(|(i, p)| search_squares(links[i], p, Reach::Full)),
            );
            // Gates reaching over half the frame cost most of the whole frame's detection,
            // which a marker they miss then needs: when one of them may be searched for in the
            // whole frame now, the whole frame is detected at once and serves both, so a lost
            // marker's frame is detected once, not nearly twice (and a found one costs at most
            // twice its gates' share). A paced marker's frame keeps to its gates.
            let whole = wide_area.fraction() > WHOLE_FRAME_SHARE
                && missing.iter().any(|&i| whole_frame(links[i]).is_ok());
            let (wide, fraction) = if whole {
                detect_area(
                    polarity,
                    &SearchArea::whole(model.width_px, model.height_px),
                )
            } else {
                detect_area(polarity, &wide_area)
            };
            searched += fraction;
            last_blobs = wide.len();
            // The discs of an area made when needed, or the whole frame's already detected.
            let detect_unless_whole =
                |searched: &mut f64, area: &dyn Fn() -> SearchArea| -> Cow<'_, [Blob]> {
                    if whole {
                        return Cow::Borrowed(&wide);
                    }
                    let (blobs, fraction) = detect_area(polarity, &area());
                    *searched += fraction;
                    Cow::Owned(blobs)
                };
            let mut lost = Vec::new();
            for &i in &missing {
                let mut result = Err(NotFound::NoPrediction);
                let mut from = None;
                for prior in &priors[i] {
                    let attempt = identify(links[i], &wide, Some(prior));
                    let found = attempt.is_ok();
                    // The first reason is kept: it comes from the most trusted prediction.
                    if found || matches!(result, Err(NotFound::NoPrediction)) {
                        result = attempt;
                    }
                    if found {
                        from = Some(*prior);
                        break;
                    }
                }
                if let (Ok(found), Some(prior)) = (&result, from) {
                    let pose = found.solution.camera_from_marker;
                    let around = detect_unless_whole(&mut searched, &|| {
                        area_of(&mut search_squares(links[i], &pose, Reach::Near).into_iter())
                    });
                    let completed = complete(links[i], &around, found);
                    // Points left out are believed covered only when the prediction was good;
                    // a marker that moved far, found on a few points, may have been found on
                    // the wrong ones, and is searched for afresh.
                    let at = completed.found.solution.camera_from_marker;
                    result = if completed.left_out == 0 || predicted_alike(links[i], &prior, &at) {
                        Ok(completed.found)
                    } else {
                        Err(NotFound::TooFewPoints {
                            found: completed.found.ids.len(),
                            ambiguous: 0,
                            needed: completed.visible,
                        })
                    };
                }
                match (result, whole_frame(links[i])) {
                    (Err(near), Err(next_in_s)) => {
                        results[i] = Err(NotFound::SearchPaced {
                            near: Box::new(near),
                            next_in_s,
                        });
                    }
                    (result, _) => {
                        if result.is_err() {
                            lost.push(i);
                        }
                        results[i] = result;
                    }
                }
            }
            // Last, the markers no prediction found, searched for in the whole frame from their
            // layouts alone.
            if !lost.is_empty() {
                let all = detect_unless_whole(&mut searched, &|| {
                    SearchArea::whole(model.width_px, model.height_px)
                });
                last_blobs = all.len();
                for i in lost {
                    let searched = find_without_prior(links[i], &all, priors[i].first());
                    // A search that formed no identification at all adds nothing to the
                    // prediction's reason (nothing of the marker near it, nor anywhere).
                    let nothing = matches!(searched, Err(NotFound::NotIdentified { used: 0, .. }));
                    if !nothing || matches!(results[i], Err(NotFound::NoPrediction)) {
                        results[i] = searched;
                    }
                }
            }
        }
        blobs += last_blobs;
    }
    refuse_shared(&links, &mut results);
    let markers = links
        .into_iter()
        .zip(results)
        .map(|(link, result)| MarkerInFrame { link, result })
        .collect();
    Ok(FrameObservation {
        blobs,
        searched_fraction: searched,
        markers,
    })
}

/// Whether every point of `link`'s marker images within the near gate ([`GATE_MIN_PX`]) at
/// `a` of where it images at `b`.
fn predicted_alike(link: &ObservedLink, a: &Pose, b: &Pose) -> bool {
    link.points_mm.iter().all(|p| {
        let at = |pose: &Pose| {
            link.camera
                .project(&(pose * nalgebra::Point3::from(*p)).coords)
        };
        match (at(a), at(b)) {
            (Some(x), Some(y)) => (x - y).norm() <= GATE_MIN_PX,
            _ => false,
        }
    })
}

/// Markers found on a common disc are refused, both: a disc is one point of one marker.
fn refuse_shared(links: &[&ObservedLink], results: &mut [Result<Found, NotFound>]) {
    let mut shared: Vec<(usize, usize)> = Vec::new();
    for (a, ra) in results.iter().enumerate() {
        for (b, rb) in results.iter().enumerate().skip(a + 1) {
            if let (Ok(fa), Ok(fb)) = (ra, rb)
                && fa.centroids_px.iter().any(|p| fb.centroids_px.contains(p))
            {
                shared.push((a, b));
            }
        }
    }
    for (a, b) in shared {
        results[a] = Err(NotFound::SharedPoints {
            other: links[b].marker_frame.clone(),
        });
        results[b] = Err(NotFound::SharedPoints {
            other: links[a].marker_frame.clone(),
        });
    }
}
