//! Views of a calibration plate from random poses, as a calibration session would take them:
//! the plate about 0.6 of the image wide, tilted by 15 to 45 degrees about a random axis
//! (the first view face-on), turned in its plane by up to 20 degrees, and placed so that the
//! views together reach every part of the image, each view wholly inside the frame.
//!
//! The plate is seen from its front: its +x to the image's right, +y down, +z away.

use super::render::{Disc, RenderSettings, SceneLight, on_plane, scene_light};
use crate::geometry::{Pose, Vec3};
use crate::vision::{CameraModel, GreyImage, Plate, Polarity};
use nalgebra::{Point3, Translation3, Unit, UnitQuaternion, Vector2};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Tries to place one view inside the frame before giving up on it.
const PLACEMENT_TRIES: usize = 200;

/// `camera_from_plate` of `views` random views of `plate` wholly inside `camera`'s frame
/// (fewer if the plate cannot be placed: too large for the view).
pub fn plate_poses(camera: &CameraModel, plate: &Plate, views: usize, seed: u64) -> Vec<Pose> {
    let mut rng = StdRng::seed_from_u64(seed);
    let (centre, size_mm) = extent(plate);
    let plate_width_mm = size_mm.x.max(size_mm.y);
    let (w, h) = (f64::from(camera.width_px), f64::from(camera.height_px));
    // The plate about 0.6 of the image's larger side at the nominal distance.
    let distance_mm = camera.fx_px * plate_width_mm / (0.6 * w.max(h));
    let margin_px = 0.02 * w.max(h);
    let mut poses = Vec::with_capacity(views);
    for view in 0..views {
        for _ in 0..PLACEMENT_TRIES {
            let tilt_deg: f64 = if view == 0 {
                0.0
            } else {
                rng.random_range(15.0..45.0)
            };
            let axis_angle: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            let turn_deg: f64 = rng.random_range(-20.0..20.0);
            let tilt = UnitQuaternion::from_axis_angle(
                &Unit::new_normalize(Vec3::new(axis_angle.cos(), axis_angle.sin(), 0.0)),
                tilt_deg.to_radians(),
            );
            let turn = UnitQuaternion::from_axis_angle(&Vec3::z_axis(), turn_deg.to_radians());
            let rotation = tilt * turn;
            let target = Vector2::new(
                rng.random_range(0.3 * w..0.7 * w),
                rng.random_range(0.3 * h..0.7 * h),
            );
            let Ok(ray) = camera.undistort(target) else {
                continue;
            };
            let depth = distance_mm * rng.random_range(0.85..1.15);
            let at = Vec3::new(ray.x, ray.y, 1.0) * depth;
            let pose = Pose::from_parts(Translation3::from(at - rotation * centre), rotation);
            if inside(camera, plate, &pose, margin_px) {
                poses.push(pose);
                break;
            }
        }
    }
    poses
}

/// The centre of the plate's points' bounding box and the plate's size over its discs' edges
/// (mm, plate frame).
fn extent(plate: &Plate) -> (Vec3, Vector2<f64>) {
    let (lo, hi) = plate.points_mm().iter().fold(
        (Vec3::repeat(f64::INFINITY), Vec3::repeat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.inf(p), hi.sup(p)),
    );
    let d = plate.origin_diameter_mm().unwrap_or(plate.diameter_mm());
    (
        (lo + hi) / 2.0,
        Vector2::new(hi.x - lo.x + d, hi.y - lo.y + d),
    )
}

/// Whether every disc of the plate at `camera_from_plate` images at least `margin_px` inside
/// the frame.
fn inside(camera: &CameraModel, plate: &Plate, camera_from_plate: &Pose, margin_px: f64) -> bool {
    let (w, h) = (f64::from(camera.width_px), f64::from(camera.height_px));
    plate.points_mm().iter().enumerate().all(|(i, p)| {
        let radius = plate.disc_diameter_mm(i) / 2.0;
        [
            (0.0, 0.0),
            (radius, 0.0),
            (-radius, 0.0),
            (0.0, radius),
            (0.0, -radius),
        ]
        .iter()
        .all(|(dx, dy)| {
            let q = camera_from_plate * Point3::new(p.x + dx, p.y + dy, 0.0);
            camera.project(&q.coords).is_some_and(|uv| {
                uv.x >= margin_px
                    && uv.y >= margin_px
                    && uv.x <= w - 1.0 - margin_px
                    && uv.y <= h - 1.0 - margin_px
            })
        })
    })
}

/// The plate's discs at `camera_from_plate`, in the camera frame.
pub fn plate_discs(plate: &Plate, camera_from_plate: &Pose) -> Vec<Disc> {
    let normal = camera_from_plate.rotation * Vec3::z();
    plate
        .points_mm()
        .iter()
        .enumerate()
        .map(|(i, p)| Disc {
            centre_mm: (camera_from_plate * Point3::from(*p)).coords,
            normal,
            diameter_mm: plate.disc_diameter_mm(i),
        })
        .collect()
}

/// A frame of the plate at `camera_from_plate`; `settings`' contrast is turned to the plate's
/// polarity (dark discs on a light plate, or bright ones).
pub fn render_plate(
    camera: &CameraModel,
    plate: &Plate,
    camera_from_plate: &Pose,
    settings: &RenderSettings,
) -> GreyImage {
    plate_light(camera, plate, camera_from_plate, settings).expose(settings.seed)
}

/// The light of a view of the plate before the sensor's noise (see [`SceneLight`]), as
/// [`render_plate`] renders it: expose it again for another frame of the same view.
pub fn plate_light(
    camera: &CameraModel,
    plate: &Plate,
    camera_from_plate: &Pose,
    settings: &RenderSettings,
) -> SceneLight {
    let mut settings = *settings;
    if plate.polarity() == Polarity::Dark && settings.contrast_dn > 0.0 {
        // A light plate: the background where the bright discs were, the discs dark.
        settings.background_dn += settings.contrast_dn;
        settings.contrast_dn = -settings.contrast_dn;
    }
    scene_light(
        camera,
        &plate_discs(plate, camera_from_plate),
        &[],
        &settings,
    )
}

/// The card a plate's discs are printed on, on a surface of another shade.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlateCard {
    /// The card's margin beyond the outermost discs' rims (mm).
    pub margin_mm: f64,
    /// The surround's reflectance relative to the card's (a dark table: a few tenths).
    pub surround: f64,
}

/// The light of a view of the plate printed on a card lying on a surround (see
/// [`PlateCard`]): [`plate_light`] with every pixel off the card shaded by the surround's
/// reflectance, each pixel by the share of it the card covers (4 x 4 samples where the card's
/// edge crosses it).
pub fn plate_light_on_card(
    camera: &CameraModel,
    plate: &Plate,
    camera_from_plate: &Pose,
    settings: &RenderSettings,
    card: PlateCard,
) -> SceneLight {
    let mut light = plate_light(camera, plate, camera_from_plate, settings);
    // The card: the plate's extent (its discs' rims) and the margin around it.
    let (centre, size_mm) = extent(plate);
    let half = size_mm / 2.0 + Vector2::repeat(card.margin_mm);
    let plate_from_camera = camera_from_plate.inverse();
    let normal = camera_from_plate.rotation * Vec3::z();
    let origin = camera_from_plate.translation.vector;
    // Whether the ray through a point of the image meets the card.
    let on_card = |u: f64, v: f64| -> bool {
        on_plane(camera, u, v, &normal, &origin).is_some_and(|p| {
            let p = plate_from_camera * Point3::from(p);
            (p.x - centre.x).abs() <= half.x && (p.y - centre.y).abs() <= half.y
        })
    };
    let (w, h) = (camera.width_px as usize, camera.height_px as usize);
    // The card at each pixel's corners; a pixel whose corners differ is sampled 4 x 4.
    let corners: Vec<bool> = (0..=h)
        .flat_map(|j| (0..=w).map(move |i| (i, j)))
        .map(|(i, j)| on_card(i as f64 - 0.5, j as f64 - 0.5))
        .collect();
    light.shade(|u, v| {
        let c = [
            corners[v * (w + 1) + u],
            corners[v * (w + 1) + u + 1],
            corners[(v + 1) * (w + 1) + u],
            corners[(v + 1) * (w + 1) + u + 1],
        ];
        let share = if c.iter().all(|&x| x) {
            1.0
        } else if c.iter().all(|&x| !x) {
            0.0
        } else {
            let mut hits = 0;
            for j in 0..4 {
                for i in 0..4 {
                    let su = u as f64 - 0.375 + 0.25 * i as f64;
                    let sv = v as f64 - 0.375 + 0.25 * j as f64;
                    hits += usize::from(on_card(su, sv));
                }
            }
            hits as f64 / 16.0
        };
        share + (1.0 - share) * card.surround
    });
    light
}

/// `camera_from_plate` of a plate in front of a camera, centred on its optical axis, about
/// `fill` of the image wide, tilted by `tilt_deg` about the plate's x axis.
pub fn plate_facing(camera: &CameraModel, plate: &Plate, fill: f64, tilt_deg: f64) -> Pose {
    let (centre, size_mm) = extent(plate);
    let width_mm = size_mm.x;
    let distance_mm = camera.fx_px * width_mm / (fill * f64::from(camera.width_px));
    let r = UnitQuaternion::from_axis_angle(&Vec3::x_axis(), tilt_deg.to_radians());
    Pose::from_parts(
        Translation3::from(Vec3::new(0.0, 0.0, distance_mm) - r * centre),
        r,
    )
}

/// Motions of a station being calibrated, `S(0)_from_S(i)` of the frame it turns about: the
/// first the identity, then turns of 2 to 3 degrees about axes that cycle through six
/// directions (so no two neighbours are parallel), and shifts of up to 4 mm. Small enough to
/// keep a plate wholly in view of a narrow lens.
pub fn station_motions(positions: usize, seed: u64) -> Vec<Pose> {
    let mut rng = StdRng::seed_from_u64(seed);
    let axes = [
        Vec3::x(),
        Vec3::y(),
        Vec3::z(),
        Vec3::new(1.0, 1.0, 0.0),
        Vec3::new(0.0, 1.0, -1.0),
        Vec3::new(1.0, 0.0, 1.0),
    ];
    (0..positions)
        .map(|i| {
            if i == 0 {
                return Pose::identity();
            }
            let sign = if i % 2 == 0 { -1.0 } else { 1.0 };
            let deg: f64 = sign * rng.random_range(2.0..3.0);
            let t = Vec3::from_fn(|_, _| rng.random_range(-4.0..4.0));
            Pose::from_parts(
                Translation3::from(t),
                UnitQuaternion::from_axis_angle(
                    &Unit::new_normalize(axes[(i - 1) % axes.len()]),
                    deg.to_radians(),
                ),
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_are_inside_the_frame_tilted_and_seen_from_the_front() {
        let camera = CameraModel::pinhole(4800.0, 4800.0, 652.0, 508.0, 1280, 1024)
            .with_distortion(&[-0.092, 0.151, 0.0004, -0.0003, 0.0]);
        let plate = Plate::new(7, 9, 15.0, 7.5, true, Polarity::Dark).expect("valid");
        let poses = plate_poses(&camera, &plate, 15, 3);
        assert_eq!(poses.len(), 15);
        let mut max_tilt = 0.0f64;
        for pose in &poses {
            assert!(inside(&camera, &plate, pose, 0.0));
            let normal = pose.rotation * Vec3::z();
            assert!(normal.z > 0.0, "the plate's +z points away from the camera");
            max_tilt = max_tilt.max(normal.z.acos().to_degrees());
        }
        assert!(max_tilt > 30.0, "{max_tilt}");
    }
}
