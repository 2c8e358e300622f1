//! Markers that move far between frames, among clutter, beside a second marker: 1000 rendered
//! frames of one camera that sees two markers, each moved by up to 50 mm and 25 degrees
//! between consecutive frames, with stray discs, bars, rings and triangles around them, light
//! that changes across the frame, vignetting, defocus, and frames that come as JPEG or from a
//! colour (Bayer) camera. Tracked as the service tracks them (the previous frame's pose, then
//! the nominal one, then the search with no prior). Checked: every marker found in every
//! frame, every visible point used, no point labelled with another's disc, and no marker found
//! where it is not.

use brokenray::config::parse;
use brokenray::geometry::{Pose, Twist, se3_exp, se3_log};
use brokenray::imagefile::{FrameFormat, decode, encode_jpeg, encode_rgb};
use brokenray::model::{ObservedLink, Observer, observe_frame};
use brokenray::sim::render::{
    Clutter, Disc, RenderSettings, bayer_rgb, marker_discs, render_scene,
};
use nalgebra::{Point3, Vector2};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::collections::HashMap;

const INSTALLATION: &str = r#"
[[cameras]]
frame = "C"
width = 960
height = 720
fx = 1800.0
fy = 1800.0
cx = 482.0
cy = 356.0
distortion = [-0.09, 0.15, 0.0004, -0.0003, 0.0]
pixel_sigma = 0.1
gain_e_per_dn = 40.0

[[markers]]
frame = "B"
target = { kind = "disc", diameter_mm = 20.0, polarity = "bright" }
points_mm = [[-280, -200, 0], [0, -200, 0], [280, -200, 0], [-280, 200, 0],
             [0, 200, 0], [280, 200, 0], [-120, 0, 150], [120, 80, 150]]

[[markers]]
frame = "X"
target = { kind = "disc", diameter_mm = 20.0, polarity = "bright" }
points_mm = [[-240, -160, 0], [240, -160, 0], [-240, 160, 0], [240, 160, 0],
             [0, -160, 0], [0, 160, 0], [-100, 0, 140], [100, 70, 140]]

[[links]]
name = "C_from_B"
kind = "measured"
model = "static"
sigma = { rotation_arcsec = [20.0, 20.0, 8.0], translation_mm = [0.05, 0.05, 0.5] }
expected_rate_hz = 25.0
nominal = { t_mm = [-420.0, 0.0, 3000.0], euler_deg = [180.0, 0.0, 0.0] }

[[links]]
name = "C_from_X"
kind = "measured"
model = "static"
sigma = { rotation_arcsec = [20.0, 20.0, 8.0], translation_mm = [0.05, 0.05, 0.5] }
expected_rate_hz = 25.0
nominal = { t_mm = [480.0, 0.0, 3500.0], euler_deg = [180.0, 0.0, 0.0] }

[[targets]]
name = "X"
base = "B"
"#;

const FRAMES: usize = 1000;
/// Largest motion of a marker between consecutive frames.
const STEP_MM: f64 = 50.0;
const STEP_DEG: f64 = 25.0;

/// A pose near `nominal` (within 80 mm sideways, 200 mm in depth, 35 degrees about each
/// axis), at most a step from `previous`.
fn next_pose(rng: &mut StdRng, nominal: &Pose, previous: &Pose) -> Pose {
    loop {
        let r = 35f64.to_radians();
        let candidate = nominal
            * se3_exp(&Twist::new(
                rng.random_range(-80.0..80.0),
                rng.random_range(-80.0..80.0),
                rng.random_range(-200.0..200.0),
                rng.random_range(-r..r),
                rng.random_range(-r..r),
                rng.random_range(-r..r),
            ));
        let step = previous.inverse() * candidate;
        if step.translation.vector.norm() <= STEP_MM
            && step.rotation.angle().to_degrees() <= STEP_DEG
        {
            return candidate;
        }
    }
}

/// Where each point of `link`'s marker images at `pose`.
fn images(link: &ObservedLink, pose: &Pose) -> Vec<Option<Vector2<f64>>> {
    link.points_mm
        .iter()
        .map(|p| link.camera.project(&(pose * Point3::from(*p)).coords))
        .collect()
}

/// A point is visible when its disc images wholly inside the frame (its radius and 2 px) and
/// apart from the marker's other discs (a raised disc may image over another).
fn visible(link: &ObservedLink, pose: &Pose) -> Vec<bool> {
    let at = images(link, pose);
    let (w, h) = (
        f64::from(link.camera.width_px),
        f64::from(link.camera.height_px),
    );
    images(link, pose)
        .iter()
        .zip(&link.points_mm)
        .map(|(q, p)| {
            let depth = (pose * Point3::from(*p)).z;
            let margin = 0.5 * 20.0 * link.camera.fx_px / depth + 2.0;
            let apart = |q: &Vector2<f64>| {
                at.iter()
                    .flatten()
                    .filter(|o| *o != q)
                    .all(|o| (o - q).norm() > 2.0 * margin)
            };
            q.is_some_and(|q| {
                apart(&q) && q.x > margin && q.y > margin && q.x < w - margin && q.y < h - margin
            })
        })
        .collect()
}

/// How a frame reaches the service.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Delivery {
    Grey,
    Jpeg,
    Colour,
}

struct Scene {
    truths: HashMap<String, Pose>,
    image: brokenray::vision::GreyImage,
}

fn render(links: &[ObservedLink], poses: &[Pose], k: usize) -> Scene {
    let camera = &links[0].camera;
    let mut discs: Vec<Disc> = Vec::new();
    for (link, pose) in links.iter().zip(poses) {
        discs.extend(marker_discs(link, pose));
    }
    // Clutter kept off the markers' discs (a piece over a disc would hide it: a covered point
    // is another test's business).
    let marker_px: Vec<Vector2<f64>> = links
        .iter()
        .zip(poses)
        .flat_map(|(l, p)| images(l, p))
        .flatten()
        .collect();
    let clutter =
        Clutter::scattered(camera, 40, 3000.0, 1000 + k as u64).clear_of(camera, &marker_px, 12.0);
    discs.extend(clutter.discs.iter().copied());
    let shapes = clutter.shapes;
    let mut rng = StdRng::seed_from_u64(k as u64);
    let settings = RenderSettings {
        blur_sigma_px: rng.random_range(0.5..1.5),
        vignetting: 0.3,
        light_gradient_per_px: [rng.random_range(-6e-4..6e-4), rng.random_range(-6e-4..6e-4)],
        samples_per_side: 8,
        seed: k as u64,
        ..RenderSettings::default()
    };
    let grey = render_scene(camera, &discs, &shapes, &settings);
    let delivery = match k % 5 {
        1 => Delivery::Jpeg,
        3 => Delivery::Colour,
        _ => Delivery::Grey,
    };
    let image = match delivery {
        Delivery::Grey => grey,
        Delivery::Jpeg => {
            let bytes = encode_jpeg(&grey, 92).expect("encodes");
            decode(&bytes, FrameFormat::Jpeg, Some((960, 720))).expect("decodes")
        }
        Delivery::Colour => {
            let rgb = bayer_rgb(&grey, [0.55, 1.0, 0.75]);
            let bytes = encode_rgb(960, 720, rgb, FrameFormat::Png, 0).expect("encodes");
            decode(&bytes, FrameFormat::Png, Some((960, 720))).expect("decodes")
        }
    };
    Scene {
        truths: links
            .iter()
            .zip(poses)
            .map(|(l, p)| (l.name.clone(), *p))
            .collect(),
        image,
    }
}

/// The visible points of `link`'s marker at `pose` that no disc detected in the whole frame
/// lies within a pixel of: what the detector missed, to tell its failures from the search's.
fn undetected(
    link: &ObservedLink,
    pose: &Pose,
    image: &brokenray::vision::GreyImage,
) -> Vec<usize> {
    let blobs = brokenray::vision::detect(image, &brokenray::vision::DetectSettings::default());
    images(link, pose)
        .iter()
        .zip(visible(link, pose))
        .enumerate()
        .filter(|(_, (q, v))| {
            *v && q.is_some_and(|q| {
                blobs
                    .iter()
                    .all(|b| (b.centre_px[0] - q.x).hypot(b.centre_px[1] - q.y) > 1.0)
            })
        })
        .map(|(i, _)| i)
        .collect()
}

#[test]
fn a_thousand_frames_of_moving_markers_among_clutter_are_all_found_and_none_mislabelled() {
    let installation = parse("two-markers.toml", INSTALLATION).expect("a valid installation");
    let observer = Observer::new(&installation.model);
    let links: Vec<ObservedLink> = observer.links().cloned().collect();
    assert_eq!(links.len(), 2);
    let nominals: Vec<Pose> = links
        .iter()
        .map(|l| l.nominal.expect("a nominal pose"))
        .collect();
    let mut rng = StdRng::seed_from_u64(34);
    let mut poses = nominals.clone();
    let mut sequence = Vec::with_capacity(FRAMES);
    while sequence.len() < FRAMES {
        let next: Vec<Pose> = nominals
            .iter()
            .zip(&poses)
            .map(|(n, p)| next_pose(&mut rng, n, p))
            .collect();
        // The two markers' discs kept apart (discs run together are one blob).
        let apart = images(&links[0], &next[0]).iter().flatten().all(|a| {
            images(&links[1], &next[1])
                .iter()
                .flatten()
                .all(|b| (a - b).norm() > 40.0)
        });
        if apart {
            poses = next.clone();
            sequence.push(next);
        }
    }

    // Two halves on two threads, each tracked from its own start (the first frame of each
    // with no previous pose).
    let half = FRAMES / 2;
    let outcomes: Vec<Vec<String>> = std::thread::scope(|scope| {
        let handles: Vec<_> = [0, half]
            .into_iter()
            .map(|start| {
                let (links, sequence, observer) = (&links, &sequence, &observer);
                scope.spawn(move || {
                    let mut failures = Vec::new();
                    let mut previous: HashMap<String, Pose> = HashMap::new();
                    for (k, poses) in sequence.iter().enumerate().skip(start).take(half) {
                        let scene = render(links, poses, k);
                        let observation = observe_frame(observer, "C", &scene.image, |l| {
                            previous.get(&l.name).copied().into_iter().collect()
                        })
                        .expect("observed");
                        for marker in &observation.markers {
                            let link = marker.link;
                            let truth = scene.truths[&link.name];
                            let found = match &marker.result {
                                Ok(found) => found,
                                Err(e) => {
                                    let undetected = undetected(link, &truth, &scene.image);
                                    failures.push(format!(
                                        "frame {k} {}: not found: {e} (visible points no disc was detected at: {undetected:?})",
                                        link.name
                                    ));
                                    previous.remove(&link.name);
                                    continue;
                                }
                            };
                            previous.insert(link.name.clone(), found.solution.camera_from_marker);
                            let truth_px = images(link, &truth);
                            let seen = visible(link, &truth);
                            for (px, id) in found.points_px.iter().zip(&found.ids) {
                                let i = link.ids.iter().position(|x| x == id).expect("known id");
                                let t = truth_px[i].expect("in front");
                                let e = (px[0] - t.x).hypot(px[1] - t.y);
                                if e > 1.0 {
                                    failures.push(format!(
                                        "frame {k} {}: point {id} on a disc {e:.1} px from its own",
                                        link.name
                                    ));
                                }
                            }
                            let used = found.ids.len();
                            let should = seen.iter().filter(|v| **v).count();
                            if used < should {
                                failures.push(format!(
                                    "frame {k} {}: {used} of {should} visible points used",
                                    link.name
                                ));
                            }
                            let error =
                                se3_log(&(found.solution.camera_from_marker * truth.inverse()));
                            if error.fixed_rows::<3>(3).norm().to_degrees() > 0.1 {
                                failures.push(format!(
                                    "frame {k} {}: pose off by {error:?}",
                                    link.name
                                ));
                            }
                        }
                    }
                    failures
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("no panic"))
            .collect()
    });
    let failures: Vec<&String> = outcomes.iter().flatten().collect();
    assert!(
        failures.is_empty(),
        "{} failures in {FRAMES} frames, the first: {:#?}",
        failures.len(),
        &failures[..failures.len().min(12)]
    );
}
