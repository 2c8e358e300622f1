//! Markers found in a camera's detections: which blob is which marker point, and the pose.
//!
//! For each marker the camera sees through a measured link, its points are predicted in the
//! image from a pose of the link (the newest filtered one, or the nominal one), and each point
//! takes the nearest detected blob within a gate. A point with two blobs nearly as close, or a
//! blob claimed by two points, is left out (ambiguous) rather than guessed. With at least
//! [`MIN_POINTS`] points the pose is solved by PnP, each point weighted by the detector's
//! sigma (its RMS limit and, in robust mode, RANSAC
//! verify the assignment), then each point is corrected for its disc's perspective
//! eccentricity at that pose and the pose is solved again. A marker that is not found says
//! why ([`NotFound`]).

use super::observation::ObservedLink;
use crate::geometry::Pose;
use crate::vision::{Blob, MIN_POINTS, PnpSolution, solve_pnp_discs, solve_pnp_weighted};
use nalgebra::Vector2;

/// A point's gate: at most this far from its prediction (px) ...
pub(super) const GATE_MIN_PX: f64 = 15.0;
/// ... or this fraction of the distance to the nearest other predicted point, if larger
/// (then never so far that it reaches a neighbour's blob).
pub(super) const GATE_FRACTION_OF_SPACING: f64 = 0.4;
/// A second blob within this factor of the nearest one's distance makes a point ambiguous.
pub(super) const AMBIGUITY_FACTOR: f64 = 1.5;

/// How far around each predicted point identification looks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reach {
    /// Each point's full gate; the marker is found with at least [`MIN_POINTS`] points.
    Full,
    /// A gate of at most `GATE_MIN_PX` (15 px), and every point must match: the quick first look
    /// when the prediction is good. When it finds a marker, the full gate would have matched
    /// the same blobs (each point's nearest blob is within the short gate, and any blob that
    /// could make it ambiguous within 1.5 times that), so a caller can search the frame only
    /// that close to the points first and widen the search when it fails.
    Near,
}

/// Why a marker was not found in a frame.
#[derive(Debug, Clone, PartialEq)]
pub enum NotFound {
    /// The marker declares no disc target: nothing to look for in a frame.
    NoTarget,
    /// No pose of the link to predict the points from.
    NoPrediction,
    /// The marker is not in front of the camera at the predicted pose.
    NotInView,
    /// Too few points matched a blob.
    TooFewPoints {
        /// Points that matched.
        found: usize,
        /// Points that were ambiguous (two blobs, or a blob claimed twice).
        ambiguous: usize,
        /// Points needed.
        needed: usize,
    },
    /// PnP refused the matched points (the reason, e.g. the RMS over its limit).
    Pnp(String),
    /// With no prior, no identification of the layout used every visible point.
    NotIdentified {
        /// Points the best identification used.
        used: usize,
        /// Points it should have seen (imaged wholly inside the frame).
        visible: usize,
    },
    /// With no prior, two identifications that contradict each other fit nearly as well.
    Ambiguous {
        /// Points the best used.
        used: usize,
        /// Points the rival used.
        rival_used: usize,
    },
    /// A disc the marker was found on was taken by another marker of the camera too.
    SharedPoints {
        /// The other marker's frame.
        other: String,
    },
    /// Not found near its predictions, and lost: the whole frame was searched for it lately
    /// and is searched again only once its interval has passed ([`super::SearchPacer`]).
    SearchPaced {
        /// Why it was not found near its predictions.
        near: Box<NotFound>,
        /// Frame time until the next whole-frame search (s).
        next_in_s: f64,
    },
}

impl std::fmt::Display for NotFound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NotFound::NoTarget => write!(
                f,
                "the marker declares no disc target (`target = {{ kind = \"disc\", ... }}`)"
            ),
            NotFound::NoPrediction => {
                write!(f, "no filtered or nominal pose to predict the points from")
            }
            NotFound::NotInView => write!(
                f,
                "the marker is not in front of the camera at the predicted pose"
            ),
            NotFound::TooFewPoints {
                found,
                ambiguous,
                needed,
            } => write!(
                f,
                "{found} point(s) found near their predictions ({ambiguous} ambiguous), at least {needed} needed"
            ),
            NotFound::Pnp(reason) => write!(f, "the matched points give no pose: {reason}"),
            NotFound::NotIdentified { used: 0, .. } => write!(
                f,
                "searched with no prior: no arrangement of the detected discs fits the marker's layout"
            ),
            NotFound::NotIdentified { used, visible } => write!(
                f,
                "searched with no prior: no identification of the marker's layout used every visible point (the best used {used} of {visible})"
            ),
            NotFound::Ambiguous { used, rival_used } => write!(
                f,
                "searched with no prior: two contradicting identifications fit ({used} and {rival_used} points); the layout or the clutter is ambiguous here"
            ),
            NotFound::SharedPoints { other } => write!(
                f,
                "a disc it was found on was also found as a point of marker {other}"
            ),
            NotFound::SearchPaced { near, next_in_s } => write!(
                f,
                "{near}; lost: the whole frame is searched for it again in {next_in_s:.2} s \
                 (once every `[pnp] lost_search_interval_s` while it stays lost)"
            ),
        }
    }
}

/// A marker found in a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Found {
    /// The images of the disc centres (eccentricity corrected; px), in matched order.
    pub points_px: Vec<[f64; 2]>,
    /// The detected centroids they were corrected from (px), in the same order.
    pub centroids_px: Vec<[f64; 2]>,
    /// Their point ids.
    pub ids: Vec<u32>,
    /// Each point's standard deviation from the detector (px).
    pub sigma_px: Vec<f64>,
    /// The pose from the corrected points.
    pub solution: PnpSolution,
    /// The same points projected with that pose (px): `points_px` minus these are the
    /// residuals.
    pub reprojected_px: Vec<[f64; 2]>,
}

/// Where the points of `link`'s marker image at `prior` (`camera_from_marker`).
fn predict(link: &ObservedLink, prior: &Pose) -> Result<Vec<Vector2<f64>>, NotFound> {
    link.points_mm
        .iter()
        .map(|p| {
            link.camera
                .project(&(prior * nalgebra::Point3::from(*p)).coords)
        })
        .collect::<Option<_>>()
        .ok_or(NotFound::NotInView)
}

/// Each predicted point's gate (px) as `(take, look)`: the point takes its nearest blob within
/// `take`, and the blobs within `look` are weighed for ambiguity. With [`Reach::Full`] both are
/// [`GATE_MIN_PX`], or [`GATE_FRACTION_OF_SPACING`] of the distance to the nearest other point
/// if larger, but never over half that distance. With [`Reach::Near`] `take` is at most
/// [`GATE_MIN_PX`] and `look` at most [`AMBIGUITY_FACTOR`] times `take`: every blob that could
/// make a match within `take` ambiguous under the full gate.
fn gates(predicted: &[Vector2<f64>], reach: Reach) -> Vec<(f64, f64)> {
    predicted
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let spacing = predicted
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, q)| (q - p).norm())
                .fold(f64::INFINITY, f64::min);
            let gate = GATE_MIN_PX
                .max(GATE_FRACTION_OF_SPACING * spacing)
                .min(0.5 * spacing);
            match reach {
                Reach::Full => (gate, gate),
                Reach::Near => {
                    let take = gate.min(GATE_MIN_PX);
                    (take, gate.min(AMBIGUITY_FACTOR * take))
                }
            }
        })
        .collect()
}

/// The part of the frame [`identify_within`] looks at for `link`'s marker at `prior`: per
/// point, its prediction and the half side of a square that holds, whole, every blob its gates
/// weigh (the `look` of `gates`, plus the disc's predicted radius with half again for a tilt
/// the prior does not know, and the detector's window margin). Empty when the marker is not in
/// view.
pub fn search_squares(link: &ObservedLink, prior: &Pose, reach: Reach) -> Vec<([f64; 2], f64)> {
    let Ok(predicted) = predict(link, prior) else {
        return Vec::new();
    };
    let focal_px = link.camera.fx_px.max(link.camera.fy_px);
    let diameter_mm = link.target.map_or(0.0, |t| t.diameter_mm);
    predicted
        .iter()
        .zip(gates(&predicted, reach))
        .zip(&link.points_mm)
        .map(|((p, (_, look)), point)| {
            let depth_mm = (prior * nalgebra::Point3::from(*point)).z.max(1.0);
            let radius_px = 0.5 * diameter_mm * focal_px / depth_mm;
            ([p.x, p.y], look + 1.5 * radius_px + SEARCH_MARGIN_PX)
        })
        .collect()
}

/// Pixels around a disc the detector reads beyond its edge (its centroid window and ring).
const SEARCH_MARGIN_PX: f64 = 8.0;

/// Finds one marker among a frame's blobs, its points predicted from `prior`
/// (`camera_from_marker`).
pub fn identify(
    link: &ObservedLink,
    blobs: &[Blob],
    prior: Option<&Pose>,
) -> Result<Found, NotFound> {
    identify_within(link, blobs, prior, Reach::Full)
}

/// [`identify`] with the gates of `reach`.
pub fn identify_within(
    link: &ObservedLink,
    blobs: &[Blob],
    prior: Option<&Pose>,
    reach: Reach,
) -> Result<Found, NotFound> {
    let prior = prior.ok_or(NotFound::NoPrediction)?;
    let predicted = predict(link, prior)?;
    let gates = gates(&predicted, reach);
    let centres: Vec<Vector2<f64>> = blobs
        .iter()
        .map(|b| Vector2::new(b.centre_px[0], b.centre_px[1]))
        .collect();
    // Each point's nearest blob within its gate, unless a second one is nearly as close.
    let mut claims: Vec<Option<usize>> = vec![None; predicted.len()];
    let mut ambiguous = 0;
    for (i, (p, &(take, look))) in predicted.iter().zip(&gates).enumerate() {
        let mut near: Vec<(f64, usize)> = centres
            .iter()
            .enumerate()
            .map(|(k, c)| ((c - p).norm(), k))
            .filter(|(d, _)| *d <= look)
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0));
        match near.as_slice() {
            [] => {}
            [(d0, _), ..] if *d0 > take => {}
            [(_, k)] => claims[i] = Some(*k),
            [(d0, k), (d1, _), ..] => {
                if *d1 > AMBIGUITY_FACTOR * d0.max(0.5) {
                    claims[i] = Some(*k);
                } else {
                    ambiguous += 1;
                }
            }
        }
    }
    // A blob claimed by two points belongs to neither.
    for i in 0..claims.len() {
        if let Some(k) = claims[i]
            && claims.iter().filter(|c| **c == Some(k)).count() > 1
        {
            for c in claims.iter_mut().filter(|c| **c == Some(k)) {
                *c = None;
            }
            ambiguous += 2;
        }
    }
    let matched: Vec<(usize, usize)> = claims
        .iter()
        .enumerate()
        .filter_map(|(i, c)| c.map(|k| (i, k)))
        .collect();
    let needed = match reach {
        Reach::Full => MIN_POINTS,
        Reach::Near => predicted.len().max(MIN_POINTS),
    };
    if matched.len() < needed {
        return Err(NotFound::TooFewPoints {
            found: matched.len(),
            ambiguous,
            needed,
        });
    }
    solve_matched(link, blobs, &matched)
}

/// The pose of `link`'s marker from `matched` (point index, blob index) pairs: PnP on the
/// blobs' centroids, each weighted by the detector's sigma, corrected for the discs'
/// eccentricity at a first pose when the marker declares disc targets, and solved again.
pub(super) fn solve_matched(
    link: &ObservedLink,
    blobs: &[Blob],
    matched: &[(usize, usize)],
) -> Result<Found, NotFound> {
    let detected: Vec<Vector2<f64>> = matched
        .iter()
        .map(|&(_, k)| Vector2::new(blobs[k].centre_px[0], blobs[k].centre_px[1]))
        .collect();
    let object: Vec<_> = matched.iter().map(|&(i, _)| link.points_mm[i]).collect();
    let sigmas: Vec<f64> = matched.iter().map(|&(_, k)| blobs[k].sigma_px()).collect();
    // The centroids are not the images of the disc centres: with disc targets, corrected at a
    // first pose and solved again.
    let (solution, corrected) = match link.target {
        None => (
            solve_pnp_weighted(&link.camera, &object, &detected, &sigmas, &link.options),
            detected,
        ),
        Some(target) => {
            let normals: Vec<_> = matched.iter().map(|&(i, _)| link.normals[i]).collect();
            match solve_pnp_discs(
                &link.camera,
                &object,
                &normals,
                |_| target.diameter_mm,
                &detected,
                &sigmas,
                &link.options,
            ) {
                Ok((solution, corrected)) => (Ok(solution), corrected),
                Err(e) => (Err(e), detected),
            }
        }
    };
    let solution = solution.map_err(|e| NotFound::Pnp(e.to_string()))?;
    // A solved pose has every point in front of the camera; one that is not would show at NaN.
    let reprojected_px = object
        .iter()
        .map(|p| {
            link.camera
                .project(&(solution.camera_from_marker * nalgebra::Point3::from(*p)).coords)
                .map_or([f64::NAN, f64::NAN], |q| [q.x, q.y])
        })
        .collect();
    Ok(Found {
        points_px: corrected.iter().map(|c| [c.x, c.y]).collect(),
        centroids_px: matched.iter().map(|&(_, k)| blobs[k].centre_px).collect(),
        ids: matched.iter().map(|&(i, _)| link.ids[i]).collect(),
        sigma_px: sigmas,
        solution,
        reprojected_px,
    })
}

/// A marker found on some of its points, completed by [`complete`].
#[derive(Debug, Clone)]
pub struct Completed {
    /// The marker with every point that images near where its pose puts it.
    pub found: Found,
    /// Points that image wholly inside the frame, apart from the marker's other discs.
    pub visible: usize,
    /// Of those, the points no blob was found for.
    pub left_out: usize,
}

/// `found` with every point that images near where its pose puts it: each point's one blob
/// among `blobs` within a tight gate of its reprojection, solved again when that uses more
/// points than `found` did (`found` is kept when that solve fails). Also says how many
/// visible points no blob was found for.
pub fn complete(link: &ObservedLink, blobs: &[Blob], found: &Found) -> Completed {
    let (assignment, visible) =
        super::search::tight_match_at(link, blobs, &found.solution.camera_from_marker);
    let left_out = assignment
        .iter()
        .zip(&visible)
        .filter(|(b, v)| **v && b.is_none())
        .count();
    let visible = visible.iter().filter(|v| **v).count();
    let matched: Vec<(usize, usize)> = assignment
        .iter()
        .enumerate()
        .filter_map(|(i, b)| b.map(|b| (i, b)))
        .collect();
    let found = if matched.len() <= found.ids.len() {
        found.clone()
    } else {
        solve_matched(link, blobs, &matched).unwrap_or_else(|_| found.clone())
    };
    Completed {
        found,
        visible,
        left_out,
    }
}
