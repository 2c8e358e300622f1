//! The disc detector against rendered truth: the pixel convention, bias over radius and
//! sub-pixel phase, scatter under noise against the stated accuracy, and an honest reported
//! uncertainty. Frames come from the renderer (`sim::render`), whose sub-pixel integration
//! makes the truth exact to well under a thousandth of a pixel.

use brokenray::geometry::Vec3;
use brokenray::sim::render::{Disc, RenderSettings, render_discs};
use brokenray::vision::{
    BitDepth, CameraModel, DetectSettings, Polarity, SearchArea, detect, detect_in,
    disc_image_offset,
};

const FOCAL_PX: f64 = 4800.0;
const DISTANCE_MM: f64 = 3000.0;

/// A frontal disc of `radius_px` whose centre images at `(cx, cy)` of a `size` x `size` camera.
fn frontal(size: u32, cx: f64, cy: f64, radius_px: f64) -> (CameraModel, Disc) {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, cx, cy, size, size);
    let disc = Disc {
        centre_mm: Vec3::new(0.0, 0.0, DISTANCE_MM),
        normal: Vec3::new(0.0, 0.0, -1.0),
        diameter_mm: 2.0 * radius_px * DISTANCE_MM / FOCAL_PX,
    };
    (camera, disc)
}

fn noise_free() -> RenderSettings {
    RenderSettings {
        read_noise_dn: 0.0,
        gain_e_per_dn: None,
        depth: BitDepth::Sixteen,
        background_dn: 1000.0,
        contrast_dn: 20000.0,
        ..RenderSettings::default()
    }
}

/// The one detection of a frame with a single disc.
fn only_centre(camera: &CameraModel, disc: &Disc, render: &RenderSettings) -> ([f64; 2], f64) {
    let frame = render_discs(camera, std::slice::from_ref(disc), render);
    let settings = DetectSettings {
        gain_e_per_dn: render.gain_e_per_dn,
        ..DetectSettings::default()
    };
    let blobs = detect(&frame, &settings);
    assert_eq!(blobs.len(), 1, "one disc, one detection: {blobs:?}");
    (blobs[0].centre_px, blobs[0].sigma_px())
}

#[test]
fn a_disc_centred_on_a_pixel_is_reported_at_that_pixel() {
    let (camera, disc) = frontal(0, 0.0, 0.0, 0.0);
    let camera = CameraModel {
        width_px: 300,
        height_px: 400,
        cx_px: 100.0,
        cy_px: 200.0,
        ..camera
    };
    let disc = Disc {
        diameter_mm: 2.0 * 16.0 * DISTANCE_MM / FOCAL_PX,
        ..disc
    };
    let (centre, _) = only_centre(&camera, &disc, &noise_free());
    assert!(
        (centre[0] - 100.0).abs() < 1e-6 && (centre[1] - 200.0).abs() < 1e-6,
        "integer coordinates are pixel centres: {centre:?}"
    );
}

/// Noise-free frames, radius 4 to 20 px in quarter pixels, four sub-pixel phases each: the
/// largest error is the grey-weighted centroid's own sampling bias on small discs (the centroid
/// of pixel values is not the centroid of the light for partly covered pixels), about 0.003 px
/// at a 4 px radius and falling with the radius.
#[test]
fn without_noise_the_centre_is_unbiased_over_radius_and_phase() {
    let phases = [(0.0, 0.0), (0.25, 0.5), (0.5, 0.125), (0.875, 0.75)];
    let mut worst = (0.0f64, 0.0, (0.0, 0.0));
    for step in 0..=64 {
        let radius = 4.0 + 0.25 * f64::from(step);
        for &(pu, pv) in &phases {
            let (cx, cy) = (48.0 + pu, 48.0 + pv);
            let (camera, disc) = frontal(96, cx, cy, radius);
            let (centre, _) = only_centre(&camera, &disc, &noise_free());
            let error = (centre[0] - cx).hypot(centre[1] - cy);
            if error > worst.0 {
                worst = (error, radius, (pu, pv));
            }
        }
    }
    eprintln!(
        "noise-free sweep: largest error {:.5} px at radius {} px, phase {:?}",
        worst.0, worst.1, worst.2
    );
    assert!(
        worst.0 < 0.005,
        "largest error {:.5} px at radius {} px, phase {:?}",
        worst.0,
        worst.1,
        worst.2
    );
}

/// Scatter and bias of the centre under 0.6 px blur, 2 DN read noise plus shot noise (40 e-/DN)
/// and 200 DN contrast over sub-pixel phases, and the reported sigma against the scatter.
fn noisy_statistics(radius_px: f64, frames: u64) -> (f64, [f64; 2], f64) {
    let mut errors = Vec::new();
    let mut sigmas = Vec::new();
    for k in 0..frames {
        // A low-discrepancy sweep of the sub-pixel phase.
        let (pu, pv) = ((k as f64 * 0.618_034) % 1.0, (k as f64 * 0.754_878) % 1.0);
        let (cx, cy) = (48.0 + pu, 48.0 + pv);
        let (camera, disc) = frontal(96, cx, cy, radius_px);
        let render = RenderSettings {
            seed: 1000 + k,
            ..RenderSettings::default()
        };
        let (centre, sigma) = only_centre(&camera, &disc, &render);
        errors.push([centre[0] - cx, centre[1] - cy]);
        sigmas.push(sigma);
    }
    let n = errors.len() as f64;
    let bias = [
        errors.iter().map(|e| e[0]).sum::<f64>() / n,
        errors.iter().map(|e| e[1]).sum::<f64>() / n,
    ];
    let rms = (errors
        .iter()
        .map(|e| e[0] * e[0] + e[1] * e[1])
        .sum::<f64>()
        / (2.0 * n))
        .sqrt();
    let mean_sigma = sigmas.iter().sum::<f64>() / n;
    eprintln!(
        "radius {radius_px} px, {frames} frames: rms {rms:.4} px per axis, bias [{:.4}, {:.4}] px, reported sigma {mean_sigma:.4} px",
        bias[0], bias[1]
    );
    (rms, bias, mean_sigma)
}

#[test]
fn a_16_px_disc_is_found_to_a_hundredth_of_a_pixel_without_bias() {
    let (rms, bias, sigma) = noisy_statistics(16.0, 400);
    assert!(rms <= 0.01, "rms per axis {rms:.4} px");
    // 400 frames: the mean's standard error is rms / 20, about 0.0005 px.
    assert!(
        bias[0].abs() < 0.003 && bias[1].abs() < 0.003,
        "bias {bias:?} px"
    );
    assert!(
        (0.7..1.4).contains(&(sigma / rms)),
        "reported sigma {sigma:.4} px against the scatter {rms:.4} px"
    );
}

#[test]
fn an_8_px_disc_is_found_to_two_hundredths_of_a_pixel() {
    let (rms, bias, sigma) = noisy_statistics(8.0, 400);
    assert!(rms <= 0.02, "rms per axis {rms:.4} px");
    assert!(
        bias[0].abs() < 0.003 && bias[1].abs() < 0.003,
        "bias {bias:?} px"
    );
    assert!(
        (0.7..1.4).contains(&(sigma / rms)),
        "reported sigma {sigma:.4} px against the scatter {rms:.4} px"
    );
}

#[test]
fn dark_discs_on_a_bright_field_are_found_with_dark_polarity_only() {
    let (camera, disc) = frontal(96, 47.3, 48.6, 10.0);
    let render = RenderSettings {
        background_dn: 220.0,
        contrast_dn: -180.0,
        ..RenderSettings::default()
    };
    let frame = render_discs(&camera, &[disc], &render);
    let dark = DetectSettings {
        polarity: Polarity::Dark,
        ..DetectSettings::default()
    };
    let found = detect(&frame, &dark);
    assert_eq!(found.len(), 1);
    assert!(
        (found[0].centre_px[0] - 47.3).abs() < 0.05 && (found[0].centre_px[1] - 48.6).abs() < 0.05
    );
    assert!(
        detect(&frame, &DetectSettings::default()).is_empty(),
        "a bright-disc detector sees no disc in a dark one"
    );
}

#[test]
fn cut_discs_streaks_and_specks_are_refused() {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, 100.0, 100.0, 200, 200);
    let at = |u: f64, v: f64, radius_px: f64| Disc {
        centre_mm: Vec3::new(
            (u - 100.0) * DISTANCE_MM / FOCAL_PX,
            (v - 100.0) * DISTANCE_MM / FOCAL_PX,
            DISTANCE_MM,
        ),
        normal: Vec3::new(0.0, 0.0, -1.0),
        diameter_mm: 2.0 * radius_px * DISTANCE_MM / FOCAL_PX,
    };
    let discs = [
        at(100.0, 100.0, 10.0), // a disc
        at(2.0, 60.0, 8.0),     // cut by the left edge
        at(150.0, 40.0, 1.5),   // a speck, under min_area_px
        // A streak: three discs in a row, one long blob.
        at(40.0, 150.0, 5.0),
        at(48.0, 150.0, 5.0),
        at(56.0, 150.0, 5.0),
        // Two discs touching.
        at(140.0, 150.0, 8.0),
        at(156.0, 150.0, 8.0),
    ];
    let frame = render_discs(&camera, &discs, &noise_free());
    let settings = DetectSettings {
        min_area_px: 80.0,
        ..DetectSettings::default()
    };
    let found = detect(&frame, &settings);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!((found[0].centre_px[0] - 100.0).abs() < 0.01);
}

/// Searching part of a frame: the discs inside the searched tiles come out exactly as from the
/// whole frame (same tiles, same thresholds), none outside is reported, and a disc the searched
/// area's edge cuts is refused like one the frame's edge cuts.
#[test]
fn a_search_area_finds_its_discs_as_the_whole_frame_does_and_refuses_cut_ones() {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, 320.0, 256.0, 640, 512);
    let at = |u: f64, v: f64| Disc {
        centre_mm: Vec3::new(
            (u - 320.0) * DISTANCE_MM / FOCAL_PX,
            (v - 256.0) * DISTANCE_MM / FOCAL_PX,
            DISTANCE_MM,
        ),
        normal: Vec3::new(0.0, 0.0, -1.0),
        diameter_mm: 2.0 * 12.0 * DISTANCE_MM / FOCAL_PX,
    };
    // Tiles are 64 px: the first disc lies well inside tile (1, 1), the second far away, the
    // third straddles the border between tiles (3, 1) and (4, 1).
    let discs = [at(96.3, 95.7), at(500.2, 400.9), at(256.4, 100.1)];
    let render = RenderSettings {
        read_noise_dn: 2.0,
        gain_e_per_dn: Some(40.0),
        depth: BitDepth::Eight,
        background_dn: 20.0,
        contrast_dn: 180.0,
        ..RenderSettings::default()
    };
    let frame = render_discs(&camera, &discs, &render);
    let settings = DetectSettings {
        gain_e_per_dn: render.gain_e_per_dn,
        ..DetectSettings::default()
    };
    let whole = detect(&frame, &settings);
    assert_eq!(whole.len(), 3, "{whole:?}");
    assert_eq!(
        detect_in(&frame, &settings, &SearchArea::whole(640, 512)),
        whole,
        "the whole frame as a search area is plain detection"
    );

    let mut area = SearchArea::empty(640, 512);
    area.add_square([96.0, 96.0], 40.0); // tiles 0..=2 in both directions
    area.add_square([230.0, 100.0], 10.0); // tile (3, 1) only: the third disc is cut
    assert!(
        (area.fraction() - 10.0 / 80.0).abs() < 1e-12,
        "{}",
        area.fraction()
    );
    let part = detect_in(&frame, &settings, &area);
    assert_eq!(
        part.len(),
        1,
        "only the first disc is whole in the area: {part:?}"
    );
    assert_eq!(part[0], whole[0], "bit for bit the whole frame's detection");

    area.add_square([280.0, 100.0], 10.0); // and tile (4, 1): the third is whole now
    let part = detect_in(&frame, &settings, &area);
    assert_eq!(part.len(), 2, "{part:?}");
    assert_eq!(
        part[1],
        *whole
            .iter()
            .find(|b| b.centre_px[0] > 200.0 && b.centre_px[0] < 300.0)
            .unwrap()
    );

    // A square outside the frame adds nothing; one over its edge adds the tiles it overlaps.
    let mut outside = SearchArea::empty(640, 512);
    outside.add_square([-100.0, 50.0], 20.0);
    outside.add_square([50.0, 900.0], 20.0);
    assert_eq!(outside.fraction(), 0.0);
    outside.add_square([630.0, 505.0], 20.0);
    assert!((outside.fraction() - 1.0 / 80.0).abs() < 1e-12);
}

/// A 20 mm disc at 3 m tilted by 30 degrees, off the optical axis, under the laboratory lens'
/// distortion: the detected centroid misses the image of the centre by the eccentricity; after
/// subtracting the computed offset the error is within the detector's own bias.
#[test]
fn the_eccentricity_correction_removes_the_bias_of_a_tilted_disc() {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, 200.0, 200.0, 400, 400)
        .with_distortion(&[-0.092, 0.151, 0.0004, -0.0003, 0.0]);
    let tilt = 30f64.to_radians();
    let mut worst_corrected = 0.0f64;
    let mut smallest_offset = f64::INFINITY;
    for (k, centre) in [
        Vec3::new(60.0, -40.0, DISTANCE_MM),
        Vec3::new(-70.0, 50.0, DISTANCE_MM),
        Vec3::new(0.0, 0.0, DISTANCE_MM),
    ]
    .into_iter()
    .enumerate()
    {
        let axis_angle = k as f64 * 1.3;
        let normal = Vec3::new(
            tilt.sin() * axis_angle.cos(),
            tilt.sin() * axis_angle.sin(),
            -tilt.cos(),
        );
        let disc = Disc {
            centre_mm: centre,
            normal,
            diameter_mm: 20.0,
        };
        let truth = camera.project(&centre).expect("in front");
        let (found, _) = only_centre(&camera, &disc, &noise_free());
        let offset = disc_image_offset(&camera, &centre, &normal, 20.0).expect("in front");
        let raw = (found[0] - truth.x).hypot(found[1] - truth.y);
        let corrected = (found[0] - offset.x - truth.x).hypot(found[1] - offset.y - truth.y);
        eprintln!(
            "tilted disc {k}: offset [{:.4}, {:.4}] px, error {raw:.4} px before, {corrected:.5} px after",
            offset.x, offset.y
        );
        worst_corrected = worst_corrected.max(corrected);
        smallest_offset = smallest_offset.min(offset.norm());
    }
    assert!(
        smallest_offset > 0.01,
        "the eccentricity is measurable here: {smallest_offset:.4} px"
    );
    assert!(
        worst_corrected < 0.005,
        "after correction {worst_corrected:.5} px"
    );
}

/// Large discs under a wide lens: a disc about 200 px across near the corner of a 1280 x 1024
/// frame with strong barrel distortion (k1 -0.3), tilted by 40 degrees. The offset computed by
/// integrating over the disc through the whole camera model matches the area centroid of the
/// disc's image rendered by brute force (64 x 64 samples per edge pixel, each traced back
/// through the distortion onto the disc's plane) to a thousandth of a pixel, where the same
/// offset computed without the distortion (a first-order view of the image) misses it by a
/// large fraction of a pixel.
#[test]
fn the_eccentricity_of_a_large_disc_holds_through_a_wide_lens_distortion() {
    let camera = CameraModel::pinhole(900.0, 900.0, 641.0, 509.0, 1280, 1024)
        .with_distortion(&[-0.3, 0.12, 0.0005, -0.0004, -0.02]);
    let pinhole = CameraModel {
        distortion: [0.0; brokenray::vision::DISTORTION_TERMS],
        ..camera
    };
    let render = RenderSettings {
        blur_sigma_px: 0.0,
        samples_per_side: 64,
        background_dn: 0.0,
        contrast_dn: 60000.0,
        ..noise_free()
    };
    let tilt = 40f64.to_radians();
    let mut worst = 0.0f64;
    let mut first_order_miss = f64::INFINITY;
    for (k, (centre, axis)) in [
        (Vec3::new(-190.0, -150.0, 420.0), 0.4f64),
        (Vec3::new(200.0, 140.0, 420.0), 2.3),
        (Vec3::new(-205.0, 155.0, 400.0), 4.0),
    ]
    .into_iter()
    .enumerate()
    {
        let normal = Vec3::new(
            tilt.sin() * axis.cos(),
            tilt.sin() * axis.sin(),
            -tilt.cos(),
        );
        let disc = Disc {
            centre_mm: centre,
            normal,
            diameter_mm: 100.0,
        };
        let frame = render_discs(&camera, std::slice::from_ref(&disc), &render);
        let w = frame.width_px() as usize;
        let (mut s, mut su, mut sv, mut lo, mut hi) = (0.0, 0.0, 0.0, [f64::MAX; 2], [0.0f64; 2]);
        for (i, &p) in frame.pixels().iter().enumerate() {
            if p > 0 {
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                let p = f64::from(p);
                s += p;
                su += p * u;
                sv += p * v;
                lo = [lo[0].min(u), lo[1].min(v)];
                hi = [hi[0].max(u), hi[1].max(v)];
            }
        }
        assert!(
            lo[0] > 0.0 && lo[1] > 0.0 && hi[0] < 1279.0 && hi[1] < 1023.0,
            "disc {k} wholly in the frame"
        );
        let across = (hi[0] - lo[0]).max(hi[1] - lo[1]);
        assert!(across > 180.0, "disc {k} is {across:.0} px across");
        let image = camera.project(&centre).expect("in front");
        let brute = nalgebra::Vector2::new(su / s, sv / s) - image;
        let offset = disc_image_offset(&camera, &centre, &normal, 100.0).expect("in front");
        let first_order = disc_image_offset(&pinhole, &centre, &normal, 100.0).expect("in front");
        let error = (offset - brute).norm();
        eprintln!(
            "disc {k}, {across:.0} px across: offset [{:.4}, {:.4}] px, brute force [{:.4}, {:.4}], \
             difference {error:.5} px; without the distortion [{:.4}, {:.4}]",
            offset.x, offset.y, brute.x, brute.y, first_order.x, first_order.y
        );
        worst = worst.max(error);
        first_order_miss = first_order_miss.min((first_order - brute).norm());
    }
    assert!(
        worst < 0.001,
        "the integral misses the rendered centroid by {worst:.5} px"
    );
    assert!(
        first_order_miss > 0.1,
        "without the distortion the offset is missed by only {first_order_miss:.4} px: the test \
         would not tell the integral from a first-order correction"
    );
}

/// The offset of a frontal disc on the optical axis of a distortion-free camera is zero, and it
/// changes sign with the tilt.
#[test]
fn the_eccentricity_of_a_frontal_disc_is_zero_and_odd_in_the_tilt() {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, 200.0, 200.0, 400, 400);
    let centre = Vec3::new(0.0, 0.0, DISTANCE_MM);
    let frontal =
        disc_image_offset(&camera, &centre, &Vec3::new(0.0, 0.0, -1.0), 20.0).expect("in front");
    assert!(frontal.norm() < 1e-9, "{frontal:?}");
    let t = 0.5f64;
    let plus = disc_image_offset(&camera, &centre, &Vec3::new(t.sin(), 0.0, -t.cos()), 20.0)
        .expect("in front");
    let minus = disc_image_offset(&camera, &centre, &Vec3::new(-t.sin(), 0.0, -t.cos()), 20.0)
        .expect("in front");
    assert!(plus.x.abs() > 0.01 && (plus.x + minus.x).abs() < 1e-9 && plus.y.abs() < 1e-9);
}

/// The built-in installation's marker B seen by camera C1, moved off its nominal pose by about a
/// millimetre and a minute of arc: rendered, detected, identified from the nominal pose, solved
/// with the eccentricity correction; and the ways a marker is not found.
mod identification {
    use super::*;
    use brokenray::config::default_installation;
    use brokenray::geometry::{Pose, Twist, se3_exp, se3_log};
    use brokenray::model::{NotFound, ObservedLink, Observer, identify, observe_frame};
    use nalgebra::Point3;
    use rand::SeedableRng;

    fn link_c1_b() -> ObservedLink {
        let inst = default_installation();
        Observer::new(&inst.model)
            .link("C1", "B")
            .expect("C1 sees B")
            .clone()
    }

    fn nominal(link: &ObservedLink) -> Pose {
        let inst = default_installation();
        match &inst.model.link(link.link).kind {
            brokenray::model::LinkKind::Measured(m) => m.nominal.expect("a nominal pose"),
            brokenray::model::LinkKind::Calibrated { .. } => unreachable!("measured"),
        }
    }

    /// The frame of `link`'s marker at `pose`, without the points listed in `hidden`, plus
    /// extra discs at the given pixels (reflections).
    fn frame(
        link: &ObservedLink,
        pose: &Pose,
        hidden: &[usize],
        extra_px: &[[f64; 2]],
    ) -> brokenray::vision::GreyImage {
        let target = link.target.expect("disc targets");
        let mut discs: Vec<Disc> = link
            .points_mm
            .iter()
            .zip(&link.normals)
            .enumerate()
            .filter(|(i, _)| !hidden.contains(i))
            .map(|(_, (p, n))| Disc {
                centre_mm: (pose * Point3::from(*p)).coords,
                normal: pose.rotation * n,
                diameter_mm: target.diameter_mm,
            })
            .collect();
        for px in extra_px {
            let xy = link
                .camera
                .undistort(nalgebra::Vector2::new(px[0], px[1]))
                .expect("undistorts");
            discs.push(Disc {
                centre_mm: Vec3::new(xy.x, xy.y, 1.0) * DISTANCE_MM,
                normal: Vec3::new(0.0, 0.0, -1.0),
                diameter_mm: target.diameter_mm,
            });
        }
        render_discs(&link.camera, &discs, &RenderSettings::default())
    }

    fn moved(nominal: &Pose) -> Pose {
        let arcmin = (1.0f64 / 60.0).to_radians();
        se3_exp(&Twist::new(0.8, -0.6, 1.2, arcmin, -arcmin, 0.5 * arcmin)) * nominal
    }

    #[test]
    fn a_marker_moved_off_its_nominal_pose_is_found_and_solved() {
        let link = link_c1_b();
        let prior = nominal(&link);
        let truth = moved(&prior);
        let blobs = detect(&frame(&link, &truth, &[], &[]), &DetectSettings::default());
        assert_eq!(blobs.len(), link.points_mm.len(), "every disc detected");
        let found = identify(&link, &blobs, Some(&prior)).expect("found");
        let mut ids = found.ids.clone();
        ids.sort_unstable();
        assert_eq!(ids, link.ids, "every point identified, each once");
        // Each corrected point is the image of its disc's centre.
        for (id, e) in point_errors_px(&link, &truth, &found) {
            assert!(
                e < 0.05,
                "point {id}: {e:.4} px from the image of its centre"
            );
        }
        let error = se3_log(&(found.solution.camera_from_marker * truth.inverse()));
        let cov = found.solution.covariance;
        for k in 0..6 {
            let sigma = cov[(k, k)].sqrt();
            assert!(
                error[k].abs() < 3.0 * sigma,
                "component {k}: error {:.3e} over 3 sigma {:.3e}",
                error[k],
                3.0 * sigma
            );
        }
        assert!(found.sigma_px.iter().all(|s| *s > 0.0 && *s < 0.05));
        // The reprojections are the points' projections at the solved pose, a residual away.
        assert_eq!(found.reprojected_px.len(), found.points_px.len());
        for ((r, p), id) in found
            .reprojected_px
            .iter()
            .zip(&found.points_px)
            .zip(&found.ids)
        {
            let i = link.ids.iter().position(|x| x == id).expect("known id");
            let at_pose = link
                .camera
                .project(
                    &(found.solution.camera_from_marker * Point3::from(link.points_mm[i])).coords,
                )
                .expect("in front");
            assert!((r[0] - at_pose.x).abs() < 1e-9 && (r[1] - at_pose.y).abs() < 1e-9);
            assert!((r[0] - p[0]).hypot(r[1] - p[1]) < 0.05, "point {id}");
        }
    }

    /// A good prediction is searched only near its points and the marker comes out exactly as
    /// from the whole frame; a prediction 32 px off widens the search, which still finds it.
    #[test]
    fn a_good_prediction_is_searched_near_its_points_and_a_poor_one_widely() {
        let inst = default_installation();
        let observer = Observer::new(&inst.model);
        let link = link_c1_b();
        let truth = moved(&nominal(&link));
        let image = frame(&link, &truth, &[], &[]);
        let settings = DetectSettings {
            polarity: link.target.expect("discs").polarity,
            gain_e_per_dn: link.gain_e_per_dn,
            ..DetectSettings::default()
        };
        let whole = identify(&link, &detect(&image, &settings), Some(&truth)).expect("found");

        let good = observe_frame(&observer, "C1", &image, |_| vec![truth]).expect("observed");
        assert_eq!(good.markers.len(), 1);
        assert_eq!(good.markers[0].result.as_ref(), Ok(&whole));
        assert_eq!(good.blobs, link.points_mm.len(), "only the marker's discs");
        assert!(
            good.searched_fraction < 0.25,
            "searched {:.3} of the frame",
            good.searched_fraction
        );

        // 20 mm sideways at 3 m: 32 px, beyond the near gate of 15 px.
        let off = Pose::from_parts(
            nalgebra::Translation3::new(20.0, 0.0, 0.0),
            nalgebra::UnitQuaternion::identity(),
        ) * truth;
        let poor = observe_frame(&observer, "C1", &image, |_| vec![off]).expect("observed");
        assert_eq!(poor.markers[0].result.as_ref(), Ok(&whole));
        assert!(
            poor.searched_fraction > good.searched_fraction + 0.5,
            "the near search ({:.3}) and the wide one",
            poor.searched_fraction
        );
    }

    #[test]
    fn a_covered_point_leaves_the_rest_and_too_few_is_not_found() {
        let link = link_c1_b();
        let prior = nominal(&link);
        let truth = moved(&prior);
        let one_hidden = detect(&frame(&link, &truth, &[2], &[]), &DetectSettings::default());
        let found = identify(&link, &one_hidden, Some(&prior)).expect("found without point 2");
        assert_eq!(found.ids.len(), link.points_mm.len() - 1);
        assert!(!found.ids.contains(&link.ids[2]));

        let five_hidden = detect(
            &frame(&link, &truth, &[0, 1, 2, 3, 4], &[]),
            &DetectSettings::default(),
        );
        assert!(matches!(
            identify(&link, &five_hidden, Some(&prior)),
            Err(NotFound::TooFewPoints {
                found: 3,
                needed: 4,
                ..
            })
        ));
        assert_eq!(
            identify(&link, &one_hidden, None),
            Err(NotFound::NoPrediction)
        );
    }

    /// With no prior at all the marker is found wherever it is and at a tilt, every point with
    /// its own disc; a layout that maps onto itself is refused as ambiguous unless a hint is
    /// near one of its turns.
    #[test]
    fn a_marker_is_found_with_no_prior_and_a_symmetric_one_is_refused() {
        use brokenray::model::{find_without_prior, layout_symmetries};
        let link = link_c1_b();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for trial in 0..12 {
            let truth = wander(&link, &nominal(&link), &mut rng, 150.0, 25.0);
            let blobs = detect(&frame(&link, &truth, &[], &[]), &DetectSettings::default());
            let found = find_without_prior(&link, &blobs, None)
                .unwrap_or_else(|e| panic!("trial {trial}: not found: {e}"));
            assert_labelled_right(&link, &truth, &found, trial);
        }
        // Four discs at the corners of a square and one in the middle: a quarter turn maps the
        // layout onto itself.
        let mut square = link.clone();
        square.points_mm = vec![
            Vec3::new(-200.0, -200.0, 0.0),
            Vec3::new(200.0, -200.0, 0.0),
            Vec3::new(200.0, 200.0, 0.0),
            Vec3::new(-200.0, 200.0, 0.0),
            Vec3::new(0.0, 0.0, 0.0),
        ];
        square.normals = vec![Vec3::z(); 5];
        square.ids = (0..5).collect();
        assert!(!layout_symmetries(&square.points_mm, 1.0).is_empty());
        assert!(layout_symmetries(&link.points_mm, 5.0).is_empty());
        let blobs = detect(
            &frame(&square, &nominal(&link), &[], &[]),
            &DetectSettings::default(),
        );
        assert!(matches!(
            find_without_prior(&square, &blobs, None),
            Err(NotFound::Ambiguous { .. })
        ));
        // A hint (the pose last seen) settles the turn, and only when it is near one of them.
        let truth = nominal(&link);
        let found = find_without_prior(&square, &blobs, Some(&truth)).expect("settled");
        assert_labelled_right(&square, &truth, &found, 0);
        let halfway = truth
            * se3_exp(&Twist::new(
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
                std::f64::consts::FRAC_PI_4,
            ));
        assert!(matches!(
            find_without_prior(&square, &blobs, Some(&halfway)),
            Err(NotFound::Ambiguous { .. })
        ));
    }

    /// `nominal` moved by up to `mm` and `deg` about the marker's centre, kept in view.
    fn wander(
        link: &ObservedLink,
        nominal: &Pose,
        rng: &mut rand::rngs::StdRng,
        mm: f64,
        deg: f64,
    ) -> Pose {
        loop {
            let pose = nominal * crate::common::jolt(rng, mm, deg);
            let inside = link.points_mm.iter().all(|p| {
                link.camera
                    .project(&(pose * Point3::from(*p)).coords)
                    .is_some_and(|q| {
                        q.x > 30.0
                            && q.y > 30.0
                            && q.x < f64::from(link.camera.width_px) - 30.0
                            && q.y < f64::from(link.camera.height_px) - 30.0
                    })
            });
            if inside {
                return pose;
            }
        }
    }

    /// Each found point's id and its distance (px) from the image of its disc's centre at
    /// `truth`.
    fn point_errors_px(
        link: &ObservedLink,
        truth: &Pose,
        found: &brokenray::model::Found,
    ) -> Vec<(u32, f64)> {
        found
            .points_px
            .iter()
            .zip(&found.ids)
            .map(|(px, id)| {
                let i = link.ids.iter().position(|x| x == id).expect("known id");
                let truth_px = link
                    .camera
                    .project(&(truth * Point3::from(link.points_mm[i])).coords)
                    .expect("in front");
                (*id, (px[0] - truth_px.x).hypot(px[1] - truth_px.y))
            })
            .collect()
    }

    /// Every point of `found` is the disc of its own id, and the pose is the truth.
    fn assert_labelled_right(
        link: &ObservedLink,
        truth: &Pose,
        found: &brokenray::model::Found,
        trial: usize,
    ) {
        assert_eq!(
            found.ids.len(),
            link.points_mm.len(),
            "trial {trial}: every point"
        );
        for (id, e) in point_errors_px(link, truth, found) {
            assert!(e < 0.2, "trial {trial}: point {id} {e:.3} px from its disc");
        }
    }

    #[test]
    fn a_reflection_beside_a_point_is_not_taken_for_it() {
        let link = link_c1_b();
        let prior = nominal(&link);
        let truth = moved(&prior);
        let p0 = link
            .camera
            .project(&(truth * Point3::from(link.points_mm[0])).coords)
            .expect("in front");
        // A second disc 40 px beside point 0: both within its gate, nearly as close.
        let blobs = detect(
            &frame(&link, &truth, &[], &[[p0.x + 40.0, p0.y + 3.0]]),
            &DetectSettings::default(),
        );
        assert_eq!(blobs.len(), link.points_mm.len() + 1);
        let found = identify(&link, &blobs, Some(&prior)).expect("found from the others");
        for (id, e) in point_errors_px(&link, &truth, &found) {
            assert!(e < 0.05, "point {id} is labelled with another disc");
        }
    }
}

/// A frontal disc of `radius_px` whose centre images at `(u, v)` of `camera` (focal length
/// [`FOCAL_PX`], no distortion).
fn frontal_at(camera: &CameraModel, u: f64, v: f64, radius_px: f64) -> Disc {
    Disc {
        centre_mm: Vec3::new(
            (u - camera.cx_px) * DISTANCE_MM / FOCAL_PX,
            (v - camera.cy_px) * DISTANCE_MM / FOCAL_PX,
            DISTANCE_MM,
        ),
        normal: Vec3::new(0.0, 0.0, -1.0),
        diameter_mm: 2.0 * radius_px * DISTANCE_MM / FOCAL_PX,
    }
}

/// Each truth's detection (the nearest blob within a pixel), and its squared z-score against
/// the blob's own covariance.
fn matched(blobs: &[brokenray::vision::Blob], truths: &[[f64; 2]]) -> Vec<([f64; 2], f64)> {
    truths
        .iter()
        .map(|t| {
            let b = blobs
                .iter()
                .find(|b| (b.centre_px[0] - t[0]).hypot(b.centre_px[1] - t[1]) < 1.0)
                .unwrap_or_else(|| panic!("no disc found at {t:?} among {blobs:?}"));
            let e = [b.centre_px[0] - t[0], b.centre_px[1] - t[1]];
            let [[a, c], [_, d]] = b.covariance_px2;
            let det = a * d - c * c;
            let z2 = (d * e[0] * e[0] - 2.0 * c * e[0] * e[1] + a * e[1] * e[1]) / det;
            (e, z2)
        })
        .collect()
}

/// Discs from 5 to 300 px across in one frame, dark on a light field whose light changes
/// three to one across the frame (a lamp to one side): every one is found, nothing else is,
/// and each centre is within its own reported uncertainty of the truth (z-scores against
/// chi-square bounds), with a bias under a hundredth of a pixel on average.
#[test]
fn discs_of_every_size_are_found_and_measured_under_light_that_changes_three_to_one() {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, 800.0, 500.0, 1600, 1000);
    let discs_px: [(f64, f64, f64); 9] = [
        (250.3, 480.6, 150.0),
        (610.7, 260.2, 80.0),
        (640.2, 720.9, 40.0),
        (880.6, 250.4, 16.0),
        (905.1, 700.7, 8.0),
        (1050.4, 480.3, 4.0),
        (1200.8, 300.1, 2.5),
        (1300.3, 720.5, 24.0),
        (1450.6, 420.8, 60.0),
    ];
    let discs: Vec<Disc> = discs_px
        .iter()
        .map(|&(u, v, r)| frontal_at(&camera, u, v, r))
        .collect();
    let truths: Vec<[f64; 2]> = discs_px.iter().map(|&(u, v, _)| [u, v]).collect();
    let (mut z2_sum, mut n, mut bias) = (0.0, 0usize, [0.0f64; 2]);
    for seed in 1..=4u64 {
        let render = RenderSettings {
            background_dn: 150.0,
            contrast_dn: -110.0,
            // 0.5 at the left edge, 1.5 at the right: three to one.
            light_gradient_per_px: [1.0 / 1600.0, 0.0],
            samples_per_side: 16,
            seed,
            ..RenderSettings::default()
        };
        let frame = render_discs(&camera, &discs, &render);
        let settings = DetectSettings {
            polarity: Polarity::Dark,
            max_area_px: 80_000.0,
            min_area_px: 12.0,
            gain_e_per_dn: render.gain_e_per_dn,
            ..DetectSettings::default()
        };
        let blobs = detect(&frame, &settings);
        assert_eq!(blobs.len(), discs.len(), "{blobs:?}");
        for (e, z2) in matched(&blobs, &truths) {
            z2_sum += z2;
            n += 1;
            bias[0] += e[0];
            bias[1] += e[1];
            assert!(z2 < 25.0, "an error of {e:?} px, z^2 = {z2:.1}");
        }
    }
    // Mean z^2 over n two-dimensional errors: chi-square with 2n degrees of freedom over n,
    // within its 99.9 % bounds for n = 36 (0.52 to 1.7 of the expected 2).
    let mean_z2 = z2_sum / n as f64;
    assert!(
        (1.0..3.4).contains(&mean_z2),
        "mean z^2 {mean_z2:.2} (2 when the sigmas are honest)"
    );
    let bias = [bias[0] / n as f64, bias[1] / n as f64];
    assert!(
        bias[0].abs() < 0.01 && bias[1].abs() < 0.01,
        "mean error {bias:?} px"
    );
}

/// A disc wholly inside the frame is measured however close to the edge (its window clipped,
/// its uncertainty widened to cover what the frame cut off); one the edge cuts is refused.
#[test]
fn a_disc_close_to_the_edge_is_measured_and_says_so_and_a_cut_one_is_refused() {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, 200.0, 100.0, 400, 200);
    let render = RenderSettings {
        read_noise_dn: 2.0,
        gain_e_per_dn: Some(40.0),
        samples_per_side: 64,
        ..RenderSettings::default()
    };
    let settings = DetectSettings {
        gain_e_per_dn: render.gain_e_per_dn,
        ..DetectSettings::default()
    };
    let (mut z2_sum, mut n) = (0.0, 0);
    for seed in 1..=12u64 {
        // Edges 1.1 to 2.1 px inside the frame's left edge (at -0.5) and its top one; a like
        // disc in the middle for comparison; one cut by the right edge. The sub-pixel phase
        // swept from frame to frame.
        let phase = (
            (seed as f64 * 0.618_034) % 1.0,
            (seed as f64 * 0.754_878) % 1.0,
        );
        let near = [
            (8.6 + phase.0, 120.0 + phase.1),
            (200.0 + phase.1, 8.6 + phase.0),
        ];
        let middle = (150.0 + phase.0, 120.0 + phase.1);
        let discs = [
            frontal_at(&camera, near[0].0, near[0].1, 8.0),
            frontal_at(&camera, near[1].0, near[1].1, 8.0),
            frontal_at(&camera, middle.0, middle.1, 8.0),
            frontal_at(&camera, 396.0, 60.0, 8.0),
        ];
        let frame = render_discs(&camera, &discs, &RenderSettings { seed, ..render });
        let blobs = detect(&frame, &settings);
        assert_eq!(blobs.len(), 3, "the cut disc is refused: {blobs:?}");
        let truths = [
            [near[0].0, near[0].1],
            [near[1].0, near[1].1],
            [middle.0, middle.1],
        ];
        let found = matched(&blobs, &truths);
        for &(e, z2) in &found {
            assert!(z2 < 20.0, "error {e:?} px, z^2 {z2:.1}");
            z2_sum += z2;
            n += 1;
        }
    }
    // Mean z^2 of 36 two-dimensional errors: 2 when honest; chi-square(72) / 36 stays under
    // 2.9 with 99.9 % probability.
    let mean_z2 = z2_sum / n as f64;
    assert!(mean_z2 < 2.9, "mean z^2 {mean_z2:.2}, 2 when honest");
}

/// A reflection inside a disc (a bright speck off its centre), soft focus, and 16-bit frames:
/// the centre stays where it is.
#[test]
fn a_speck_inside_a_disc_soft_focus_and_sixteen_bits_leave_the_centre() {
    let camera = CameraModel::pinhole(FOCAL_PX, FOCAL_PX, 100.0, 100.0, 200, 200);
    let truth = [100.3, 99.6];
    let disc = frontal_at(&camera, truth[0], truth[1], 14.0);
    let settings = DetectSettings::default();
    // A speck: 5 pixels back to the background, 5 px from the centre.
    let clean = render_discs(&camera, &[disc], &noise_free_8bit());
    let mut pixels = clean.pixels().to_vec();
    for (du, dv) in [(5, 0), (6, 0), (5, 1), (6, 1), (5, -1)] {
        let (u, v) = ((100 + du) as usize, (100 + dv) as usize);
        pixels[v * 200 + u] = 40;
    }
    let specked =
        brokenray::vision::GreyImage::new(200, 200, BitDepth::Eight, pixels).expect("valid");
    // The one disc's distance from the truth (px) and its sigma.
    let error = |frame: &brokenray::vision::GreyImage| {
        let blobs = detect(frame, &settings);
        assert_eq!(blobs.len(), 1, "{blobs:?}");
        let e = (blobs[0].centre_px[0] - truth[0]).hypot(blobs[0].centre_px[1] - truth[1]);
        (e, blobs[0].sigma_px())
    };
    let (e, _) = error(&specked);
    assert!(e < 0.01, "a speck moved the centre by {e:.4} px");

    // Soft focus: a blur of 3 px on a 14 px disc.
    let soft = render_discs(
        &camera,
        &[disc],
        &RenderSettings {
            blur_sigma_px: 3.0,
            ..noise_free_8bit()
        },
    );
    let (e, _) = error(&soft);
    assert!(e < 0.01, "soft focus moved the centre by {e:.4} px");

    // Sixteen bits, a full-scale contrast like the 8-bit one.
    let deep = render_discs(
        &camera,
        &[disc],
        &RenderSettings {
            depth: BitDepth::Sixteen,
            background_dn: 40.0 * 257.0,
            contrast_dn: 200.0 * 257.0,
            read_noise_dn: 2.0 * 257.0,
            gain_e_per_dn: None,
            ..RenderSettings::default()
        },
    );
    let (e, sigma) = error(&deep);
    assert!(e < 4.0 * sigma + 0.002, "16 bit: {e:.4} px, sigma {sigma}");
}

fn noise_free_8bit() -> RenderSettings {
    RenderSettings {
        read_noise_dn: 0.0,
        gain_e_per_dn: None,
        samples_per_side: 32,
        ..RenderSettings::default()
    }
}

/// A plate of large discs close to a wide lens, as a bench calibration of a short-range camera
/// takes it: discs 130 to 330 px across, the light falling off three to one across the plate
/// in a random direction, vignetting, the card on a darker surround, the plate anywhere in the
/// frame up to a few pixels from its edge and tilted up to 40 degrees. Every disc is found and
/// the plate labelled in every view, and each centre lies within its reported uncertainty of
/// the truth. `BROKENRAY_LARGE_DISC_VIEWS` sets the number of views (12; the figure in
/// BENCHMARKS.md is of 100).
#[test]
fn large_discs_under_falling_light_on_a_card_are_all_found() {
    use brokenray::sim::plate::{PlateCard, plate_discs, plate_light_on_card};
    use brokenray::vision::Plate;
    use rand::{Rng, SeedableRng};
    let camera = CameraModel::pinhole(1500.0, 1500.0, 1031.0, 760.0, 2048, 1536)
        .with_distortion(&[-0.21, 0.09, 0.0, 0.0, -0.015]);
    let plate = Plate::new(4, 3, 30.0, 28.0, true, Polarity::Dark).expect("a valid plate");
    let views: u64 = std::env::var("BROKENRAY_LARGE_DISC_VIEWS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(12);
    let detect_settings = DetectSettings {
        polarity: Polarity::Dark,
        gain_e_per_dn: Some(40.0),
        ..DetectSettings::default()
    };
    let points = plate.points_mm();
    let centre = points
        .iter()
        .fold(brokenray::geometry::Vec3::zeros(), |a, p| a + p)
        / points.len() as f64;
    let mut rng = rand::rngs::StdRng::seed_from_u64(47);
    let (mut failures, mut largest_px, mut z2_sum, mut n) = (Vec::new(), 0.0f64, 0.0, 0usize);
    let mut worst_px = 0.0f64;
    let (w, h) = (f64::from(camera.width_px), f64::from(camera.height_px));
    for view in 0..views {
        // A pose with every disc's rim inside the frame by 3 px or more.
        let pose = loop {
            let tilt = rng.random_range(0.0f64..40.0).to_radians();
            let axis_angle = rng.random_range(0.0..std::f64::consts::TAU);
            let rotation = nalgebra::UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(brokenray::geometry::Vec3::new(
                    axis_angle.cos(),
                    axis_angle.sin(),
                    0.0,
                )),
                tilt,
            ) * nalgebra::UnitQuaternion::from_axis_angle(
                &brokenray::geometry::Vec3::z_axis(),
                rng.random_range(-0.3..0.3),
            );
            // The first view close, for discs over 300 px across.
            let distance = if view == 0 {
                rng.random_range(135.0..145.0)
            } else {
                rng.random_range(135.0..330.0)
            };
            let at = brokenray::geometry::Vec3::new(
                rng.random_range(-0.4..0.4) * distance,
                rng.random_range(-0.3..0.3) * distance,
                distance,
            );
            let pose = brokenray::geometry::Pose::from_parts(
                nalgebra::Translation3::from(at - rotation * centre),
                rotation,
            );
            let inside = plate_discs(&plate, &pose).iter().all(|d| {
                let n = d.normal.normalize();
                let a = n.cross(&brokenray::geometry::Vec3::x()).normalize();
                let b = n.cross(&a);
                (0..32).all(|k| {
                    let t = k as f64 / 32.0 * std::f64::consts::TAU;
                    let rim = d.centre_mm + (a * t.cos() + b * t.sin()) * (d.diameter_mm / 2.0);
                    camera
                        .project(&rim)
                        .is_some_and(|p| p.x > 3.0 && p.y > 3.0 && p.x < w - 4.0 && p.y < h - 4.0)
                })
            });
            if inside {
                break pose;
            }
        };
        let discs = plate_discs(&plate, &pose);
        let images: Vec<nalgebra::Vector2<f64>> = discs
            .iter()
            .map(|d| {
                camera.project(&d.centre_mm).expect("in front")
                    + disc_image_offset(&camera, &d.centre_mm, &d.normal, d.diameter_mm)
                        .expect("in front")
            })
            .collect();
        let across: f64 = discs
            .iter()
            .map(|d| d.diameter_mm * camera.fx_px / d.centre_mm.z)
            .fold(0.0, f64::max);
        largest_px = largest_px.max(across);
        let (lo, hi) = images.iter().fold(
            (
                nalgebra::Vector2::repeat(f64::INFINITY),
                nalgebra::Vector2::repeat(f64::NEG_INFINITY),
            ),
            |(lo, hi), p| (lo.inf(p), hi.sup(p)),
        );
        let span = (hi - lo).norm() + across;
        // The light is `1 + g . (u - c)` about the principal point `c`: along a random
        // direction `d`, `g = d / (span - offset)` makes it three to one across the plate's
        // image, `offset` its centre's distance from `c` along `d` (the direction turned when
        // that leaves the plate's dim end in the dark).
        let mut direction = rng.random_range(0.0..std::f64::consts::TAU);
        let middle = (lo + hi) / 2.0 - nalgebra::Vector2::new(camera.cx_px, camera.cy_px);
        let along = |a: f64| middle.x * a.cos() + middle.y * a.sin();
        if along(direction) > span / 2.0 {
            direction += std::f64::consts::PI;
        }
        let gradient = 1.0 / (span - along(direction));
        // Exposed so that the card's brightest end stays clear of saturation (220 of 255),
        // the discs at 15 % of the card.
        let brightest = 1.0 + gradient * (along(direction) + span / 2.0);
        let card_dn = 220.0 / brightest;
        let settings = RenderSettings {
            background_dn: 0.15 * card_dn,
            contrast_dn: 0.85 * card_dn,
            vignetting: 0.3,
            // Three to one across the plate's image.
            light_gradient_per_px: [direction.cos() * gradient, direction.sin() * gradient],
            samples_per_side: 8,
            seed: 5000 + view,
            ..RenderSettings::default()
        };
        let card = PlateCard {
            margin_mm: 8.0,
            surround: 0.3,
        };
        let frame = plate_light_on_card(&camera, &plate, &pose, &settings, card).expose(view);
        let blobs = detect(&frame, &detect_settings);
        match plate.find(&blobs) {
            Ok(found) => {
                for ((p, &id), s) in found.points_px.iter().zip(&found.ids).zip(&found.sigmas_px) {
                    let e = p - images[id];
                    z2_sum += e.norm_squared() / (s * s);
                    worst_px = worst_px.max(e.norm());
                    n += 1;
                }
            }
            Err(e) => failures.push(format!("view {view} (largest disc {across:.0} px): {e}")),
        }
    }
    eprintln!(
        "{} of {views} views found, largest disc {largest_px:.0} px, largest error {worst_px:.4} px, mean z² {:.2}",
        views as usize - failures.len(),
        z2_sum / n.max(1) as f64
    );
    assert!(failures.is_empty(), "{failures:#?}");
    assert!(
        largest_px > 300.0,
        "the largest disc was {largest_px:.0} px across"
    );
    // Each centre within its own sigmas: the mean z² of n two-dimensional errors is 2 when
    // they are honest (chi-square of 2n degrees of freedom over n: within 1.5 to 2.6 for
    // n = 144 at 99.9 %, widened for the renderer's own error on the edges).
    let mean_z2 = z2_sum / n as f64;
    assert!((1.2..=2.9).contains(&mean_z2), "mean z² {mean_z2:.2}");
    assert!(worst_px < 0.05, "an error of {worst_px:.4} px");
}
