//! `brokenray calibrate-camera`: a camera's intrinsics from frames of a plate; and
//! `brokenray calibrate-station`: a rigid station's calibrated link from frames taken at
//! several positions of the station, in one command.
//!
//! Both read frames with the same decoder as `POST /frames` and find targets with the same
//! detector. A frame in which the plate is not wholly found is left out with the reason (on
//! the log), never used in part.

use crate::config::Installation;
use crate::geometry::{ARCSEC_PER_RAD, Pose};
use crate::imagefile::{FrameFormat, decode};
use crate::model::{LinkKind, Observer, observe_frame};
use crate::vision::{
    CalibrationOptions, CalibrationView, CameraCalibration, CameraModel, DetectSettings, GreyImage,
    HandEyeOptions, Intrinsic, Plate, PlateView, PnpOptions, calibrate_camera_checked, detect,
    intrinsics_of, solve_hand_eye, solve_pnp_discs,
};
use crate::wire::{HandEyeOut, PlateIn, parse_fix};
use anyhow::{Context, bail};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Reads a plate file (TOML, the fields of `PlateIn`).
pub(super) fn read_plate(path: &Path) -> anyhow::Result<Plate> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the plate file {}", path.display()))?;
    let spec: PlateIn =
        toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    spec.to_plate()
        .map_err(|p| anyhow::anyhow!("{}: {}", path.display(), p.message))
}

/// Reads `--plate CAMERA=PLATE.toml` arguments.
pub(super) fn read_plates(args: &[String]) -> anyhow::Result<Vec<(String, Plate)>> {
    args.iter()
        .map(|p| {
            let (camera, file) = p
                .split_once('=')
                .ok_or_else(|| anyhow::anyhow!("--plate {p}: expected CAMERA=PLATE.toml"))?;
            Ok((camera.to_owned(), read_plate(Path::new(file))?))
        })
        .collect()
}

fn read_frame(path: &Path, expected: Option<(u32, u32)>) -> anyhow::Result<GreyImage> {
    let format = FrameFormat::from_path(path).ok_or_else(|| {
        anyhow::anyhow!(
            "{}: not a frame file (.png, .jpg, .jpeg, .tif, .tiff or .pgm)",
            path.display()
        )
    })?;
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    decode(&bytes, format, expected).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

fn find_plate(plate: &Plate, image: &GreyImage) -> Result<PlateView, String> {
    let settings = DetectSettings {
        polarity: plate.polarity(),
        ..DetectSettings::default()
    };
    plate
        .find(&detect(image, &settings))
        .map_err(|e| e.to_string())
}

/// A calibration from frame files, with the frames it used and those it left out.
pub(super) struct FramesCalibration {
    /// The result.
    pub calibration: CameraCalibration,
    /// The frames used, in view order.
    pub used: Vec<PathBuf>,
    /// The frames left out, with why.
    pub left_out: Vec<(PathBuf, String)>,
    /// Frames used that came lossy (JPEG).
    pub lossy: usize,
}

impl FramesCalibration {
    /// What the frames' files limit, in words (JPEG's blocks move disc centres).
    pub(super) fn file_warning(&self) -> Option<String> {
        (self.lossy > 0).then(|| {
            format!(
                "{} of the {} views came as JPEG: lossy compression moves disc centres by \
                 hundredths of a pixel and its blocks do not average out, so it limits the \
                 accuracy; take PNG or TIFF frames for a calibration to rely on",
                self.lossy,
                self.used.len()
            )
        })
    }
}

/// Detects the plate in each frame and calibrates; `progress` advances a frame at a time,
/// frames left out are reported on `log`.
pub(super) fn calibrate_from_frames(
    plate: &Plate,
    frames: &[PathBuf],
    fix: &[String],
    (plate_shape, model): (crate::vision::PlateShape, crate::vision::LensModel),
    progress: &indicatif::ProgressBar,
    log: &mut impl Write,
) -> anyhow::Result<FramesCalibration> {
    let fixed = parse_fix(fix).map_err(|p| anyhow::anyhow!("--fix: {}", p.message))?;
    progress.set_length(frames.len() as u64);
    let mut size = None;
    let mut views = Vec::new();
    let mut used = Vec::new();
    let mut left_out = Vec::new();
    let mut lossy = 0;
    for path in frames {
        let image = read_frame(path, size)?;
        size = Some((image.width_px(), image.height_px()));
        match find_plate(plate, &image) {
            Ok(found) => {
                if found.ids.len() < plate.len() {
                    progress.suspend(|| {
                        writeln!(
                            log,
                            "{}: the plate's origin disc is out of view (cut by the frame's edge or covered): the plate placed by its other corners, {} of its {} points used",
                            path.display(),
                            found.ids.len(),
                            plate.len()
                        )
                    })?;
                }
                views.push(CalibrationView {
                    ids: found.ids,
                    points_px: found.points_px,
                    sigmas_px: Some(found.sigmas_px),
                });
                used.push(path.clone());
                lossy +=
                    usize::from(FrameFormat::from_path(path).is_some_and(FrameFormat::is_lossy));
            }
            Err(reason) => {
                progress.suspend(|| writeln!(log, "{}: left out: {reason}", path.display()))?;
                left_out.push((path.clone(), reason));
            }
        }
        progress.inc(1);
    }
    let (w, h) = size.unwrap_or((0, 0));
    progress.set_message("solving");
    let options = CalibrationOptions {
        fixed,
        plate_shape,
        model,
        ..CalibrationOptions::default()
    };
    let calibration = calibrate_camera_checked(plate, w, h, &views, &options).map_err(|e| {
        anyhow::anyhow!(
            "{e} ({} of {} frames had the whole plate)",
            views.len(),
            frames.len()
        )
    })?;
    Ok(FramesCalibration {
        calibration,
        used,
        left_out,
        lossy,
    })
}

/// The report `calibrate-camera` prints.
pub(super) fn report(run: &FramesCalibration) -> String {
    use std::fmt::Write as _;
    let c = &run.calibration;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "camera calibration: {} views ({} frames left out), {} x {} px, RMS {:.4} px, variance factor {:.2}",
        run.used.len(),
        run.left_out.len(),
        c.camera.width_px,
        c.camera.height_px,
        c.rms_px,
        c.variance_factor
    );
    let values = intrinsics_of(&c.camera);
    let _ = writeln!(s, "  lens model {}", c.model);
    for &p in Intrinsic::of_model(c.model) {
        let i = p.index();
        if c.fixed.contains(&p) {
            let _ = writeln!(s, "  {:<3} {:>14.6}   (fixed)", p.name(), values[i]);
        } else {
            let _ = writeln!(
                s,
                "  {:<3} {:>14.6} +- {:.6}",
                p.name(),
                values[i],
                c.sigma[i]
            );
        }
    }
    if let Some(check) = &c.cross_validation {
        let _ = writeln!(s, "  {}", crate::vision::describe_cross_validation(check));
    }
    let _ = writeln!(
        s,
        "  {}",
        crate::vision::describe_plate_shape(c.plate_shape, c.plate_warp.as_ref())
    );
    if let Some(r) = &c.residual_structure {
        let _ = writeln!(
            s,
            "  {}",
            crate::vision::describe_residual_structure(r, c.model)
        );
    }
    for k in &c.correlations {
        let _ = writeln!(
            s,
            "  correlation {} - {}: {:+.3}",
            k.a.name(),
            k.b.name(),
            k.r
        );
    }
    let _ = writeln!(s, "views:");
    for (fit, path) in c.views.iter().zip(&run.used) {
        let _ = writeln!(
            s,
            "  {}: RMS {:.4} px, tilt {:.1} deg, distance {:.0} mm",
            path.display(),
            fit.rms_px,
            fit.tilt_deg,
            fit.camera_from_plate.translation.vector.norm()
        );
    }
    for w in &c.warnings {
        let _ = writeln!(s, "warning: {w}");
    }
    if let Some(w) = run.file_warning() {
        let _ = writeln!(s, "warning: {w}");
    }
    s
}

/// Writes the calibration's report into `dir` (made if missing) as `calibration.html`, which
/// must not exist; returns its path.
pub(super) fn write_report(
    dir: &Path,
    camera: Option<&str>,
    plate: &Plate,
    run: &FramesCalibration,
) -> anyhow::Result<PathBuf> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot make {}", dir.display()))?;
    let path = dir.join("calibration.html");
    let names: Vec<String> = run.used.iter().map(|p| p.display().to_string()).collect();
    let mut notes: Vec<String> = run
        .left_out
        .iter()
        .map(|(p, why)| format!("{} left out: {why}", p.display()))
        .collect();
    notes.extend(run.file_warning());
    let title = camera.map_or_else(
        || format!("{} frames", run.used.len() + run.left_out.len()),
        str::to_owned,
    );
    let page = crate::report::calibration::calibration_report(
        &crate::report::calibration::CalibrationReport {
            title: &title,
            calibration: &run.calibration,
            plate,
            view_names: &names,
            notes: &notes,
            made: &crate::clock::format_ns(crate::clock::wall_now_ns()),
        },
    );
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&path)
        .with_context(|| format!("cannot write {} (it must not exist)", path.display()))?;
    file.write_all(page.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(path)
}

/// A `[[cameras]]` block for the installation file; `report`, the calibration's HTML page,
/// is named in it for the dashboard to link.
pub(super) fn cameras_block(frame: &str, c: &CameraCalibration, report: Option<&Path>) -> String {
    let m = &c.camera;
    let n = c.model.intrinsics();
    let distortion: Vec<String> = m.distortion[..c.model.distortion_terms()]
        .iter()
        .map(|v| format!("{v:?}"))
        .collect();
    let names: Vec<&str> = Intrinsic::of_model(c.model)
        .iter()
        .map(|p| p.name())
        .collect();
    let mut fixed: Vec<&str> = c.fixed.iter().map(|p| p.name()).collect();
    if fixed.is_empty() {
        fixed.push("none");
    }
    let block = format!(
        "# Calibrated from {} views ({} lens model): RMS {:.4} px; sigmas fx {:.3}, fy {:.3}, cx {:.3}, cy {:.3} px; fixed: {}.\n\
         [[cameras]]\n\
         frame = \"{frame}\"\n\
         width = {}\n\
         height = {}\n\
         fx = {:?}\n\
         fy = {:?}\n\
         cx = {:?}\n\
         cy = {:?}\n\
         distortion = [{}]\n\
         pixel_sigma = {:?}\n\
         # The intrinsics' covariance (row-major: {}): the calibration's\n\
         # error enters every sigma through it.\n\
         intrinsics_covariance = [\n{}]\n",
        c.views.len(),
        c.model,
        c.rms_px,
        c.sigma[0],
        c.sigma[1],
        c.sigma[2],
        c.sigma[3],
        fixed.join(", "),
        m.width_px,
        m.height_px,
        m.fx_px,
        m.fy_px,
        m.cx_px,
        m.cy_px,
        distortion.join(", "),
        (c.pixel_sigma() * 1e4).round() / 1e4,
        names.join(" "),
        c.covariance[..n]
            .iter()
            .map(|row| {
                let cells: Vec<String> = row[..n].iter().map(|v| format!("{v:e}")).collect();
                format!("  {},\n", cells.join(", "))
            })
            .collect::<String>(),
    );
    match report {
        Some(page) => format!(
            "{block}# The calibration's report, linked from the dashboard.\ncalibration_report = {:?}\n",
            page.display().to_string()
        ),
        None => block,
    }
}

/// What one sensor of a station measures at each position.
enum Sensor {
    /// A camera of the station looking at a plate fixed in the world: `camera_from_plate`.
    CameraOnPlate {
        camera: String,
        model: CameraModel,
        plate: Plate,
    },
    /// A marker of the station seen by a camera fixed in the world: `camera_from_marker`.
    MarkerSeenBy { marker: String, camera: String },
}

impl Sensor {
    /// The frame file of this sensor at one position.
    fn frame_in(&self, dir: &Path) -> anyhow::Result<PathBuf> {
        let camera = match self {
            Sensor::CameraOnPlate { camera, .. } | Sensor::MarkerSeenBy { camera, .. } => camera,
        };
        for ext in ["png", "pgm", "tif", "tiff"] {
            let path = dir.join(format!("{camera}.{ext}"));
            if path.exists() {
                return Ok(path);
            }
        }
        bail!(
            "{}: no frame of camera {camera} ({camera}.png, .pgm, .tif or .tiff)",
            dir.display()
        )
    }
}

/// The two sensors of the station whose calibrated link is `link` (`parent_from_child`), and
/// the link's pose in the installation.
fn station(
    installation: &Installation,
    observer: &Observer,
    link: &str,
    plates: &[(String, Plate)],
) -> anyhow::Result<(Sensor, Sensor, Pose)> {
    let model = &installation.model;
    let spec = model
        .link_by_name(link)
        .ok_or_else(|| anyhow::anyhow!("no link `{link}` in the installation"))?;
    let LinkKind::Calibrated { parent_from_child } = &spec.kind else {
        bail!("`{link}` is a measured link: only a station's calibrated links are calibrated here");
    };
    let sensor = |frame: &str| -> anyhow::Result<Sensor> {
        if let Some(camera) = model.camera(frame) {
            let plate = plates
                .iter()
                .find(|(c, _)| c == frame)
                .map(|(_, p)| *p)
                .ok_or_else(|| {
                    anyhow::anyhow!(
                        "camera {frame} of the station needs its plate: --plate {frame}=PLATE.toml"
                    )
                })?;
            return Ok(Sensor::CameraOnPlate {
                camera: frame.to_owned(),
                model: camera.intrinsics,
                plate,
            });
        }
        if model.marker(frame).is_some() {
            let seen_by = observer
                .links()
                .find(|l| l.marker_frame == frame)
                .map(|l| l.camera_frame.clone())
                .ok_or_else(|| {
                    anyhow::anyhow!("no camera of the installation sees marker {frame}")
                })?;
            return Ok(Sensor::MarkerSeenBy {
                marker: frame.to_owned(),
                camera: seen_by,
            });
        }
        bail!("{frame} is neither a camera nor a marker of the installation")
    };
    let (parent, child) = link
        .split_once("_from_")
        .ok_or_else(|| anyhow::anyhow!("`{link}` is not named parent_from_child"))?;
    Ok((sensor(parent)?, sensor(child)?, parent_from_child.pose))
}

/// A station's calibrated link from frames at several positions.
pub(super) struct StationCalibration {
    /// The solution, as `POST /calibration/hand-eye` answers.
    pub result: HandEyeOut,
    /// The motions used (`A_i`, `B_i`), from the first position to each other.
    pub motions: usize,
    /// Positions left out, with why.
    pub left_out: Vec<(PathBuf, String)>,
}

/// Calibrates the calibrated link `link` (`parent_from_child`) of `installation` from
/// `positions` (one directory per position of the station, holding `<camera>.png` of each
/// camera involved). `plates` names the plate each camera of the station looks at.
pub(super) fn calibrate_station(
    installation: &Installation,
    link: &str,
    plates: &[(String, Plate)],
    positions: &[PathBuf],
    progress: &indicatif::ProgressBar,
    log: &mut impl Write,
) -> anyhow::Result<StationCalibration> {
    let observer = Observer::new(&installation.model);
    let (first, second, _) = station(installation, &observer, link, plates)?;
    for sensor in [&first, &second] {
        if let Sensor::CameraOnPlate { camera, plate, .. } = sensor
            && plate.is_symmetric()
        {
            writeln!(
                log,
                "warning: camera {camera}'s plate looks the same turned by half a turn: its labels follow the image's orientation, so keep the station's turns under 90 degrees (an asymmetric plate with an odd number of rows has no such limit)"
            )?;
        }
    }
    progress.set_length(positions.len() as u64);
    // Each position's two poses, `world_from_sensor` for each sensor (the world: what the
    // sensor is measured against, fixed), with their largest rotation and translation sigmas.
    let mut measured: Vec<(Pose, Pose, f64, f64)> = Vec::new();
    let mut left_out = Vec::new();
    let mut last_marker_pose: Option<Pose> = None;
    for dir in positions {
        let mut pose_of = |s: &Sensor| -> anyhow::Result<Result<(Pose, f64, f64), String>> {
            let path = s.frame_in(dir)?;
            match s {
                Sensor::CameraOnPlate { model, plate, .. } => {
                    let image = read_frame(&path, Some((model.width_px, model.height_px)))?;
                    Ok(plate_pose(model, plate, &image)
                        .map(|(pose, sr, st)| (pose.inverse(), sr, st))
                        .map_err(|r| format!("{}: {r}", path.display())))
                }
                Sensor::MarkerSeenBy { marker, camera } => {
                    let cam = observer
                        .camera(camera)
                        .map_err(|e| anyhow::anyhow!("{e}"))?;
                    let image = read_frame(&path, Some((cam.width_px, cam.height_px)))?;
                    let seen = observe_frame(&observer, camera, &image, |_| {
                        last_marker_pose.into_iter().collect()
                    })
                    .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
                    let Some(m) = seen.markers.iter().find(|m| m.link.marker_frame == *marker)
                    else {
                        return Ok(Err(format!(
                            "{}: marker {marker} not predicted in view",
                            path.display()
                        )));
                    };
                    Ok(match &m.result {
                        Ok(found) => {
                            let pose = found.solution.camera_from_marker;
                            last_marker_pose = Some(pose);
                            let (sr, st) = sigmas_of(&found.solution.covariance);
                            // The watching camera is fixed: `camera_from_marker` is the
                            // marker's `world_from_sensor` as it is.
                            Ok((pose, sr, st))
                        }
                        Err(e) => Err(format!(
                            "{}: marker {marker} not found: {e}",
                            path.display()
                        )),
                    })
                }
            }
        };
        let a = pose_of(&first)?;
        let b = pose_of(&second)?;
        match (a, b) {
            (Ok((a, ar, at)), Ok((b, br, bt))) => {
                measured.push((a, b, ar.max(br), at.max(bt)));
            }
            (a, b) => {
                let reason = [a.err(), b.err()]
                    .into_iter()
                    .flatten()
                    .collect::<Vec<_>>()
                    .join("; ");
                progress.suspend(|| writeln!(log, "{}: left out: {reason}", dir.display()))?;
                left_out.push((dir.clone(), reason));
            }
        }
        progress.inc(1);
    }
    // `measured` holds, per position, each sensor's `world_from_sensor` up to a fixed world
    // frame: for a camera `plate_from_camera`, for a marker `camera_from_marker`. A motion is
    // `sensor(0)_from_sensor(i) = (world_from_sensor(0))^-1 world_from_sensor(i)`.
    let Some((a0, b0, _, _)) = measured.first().copied() else {
        bail!("no position had both sensors' targets found");
    };
    let pairs: Vec<(Pose, Pose)> = measured
        .iter()
        .skip(1)
        .map(|(a, b, _, _)| (a0.inverse() * a, b0.inverse() * b))
        .collect();
    // A motion joins two measured poses: its noise is about sqrt(2) times theirs.
    let n = measured.len() as f64;
    let rms = |f: fn(&(Pose, Pose, f64, f64)) -> f64| {
        (measured.iter().map(|m| f(m).powi(2)).sum::<f64>() / n).sqrt() * std::f64::consts::SQRT_2
    };
    let options = HandEyeOptions {
        sigma_rotation_arcsec: rms(|m| m.2).max(0.01),
        sigma_translation_mm: rms(|m| m.3).max(1e-4),
        ..HandEyeOptions::default()
    };
    let solution = solve_hand_eye(&pairs, &options).map_err(|e| {
        anyhow::anyhow!(
            "{e} ({} motions from {} positions)",
            pairs.len(),
            measured.len()
        )
    })?;
    Ok(StationCalibration {
        result: HandEyeOut::from(&solution),
        motions: pairs.len(),
        left_out,
    })
}

/// The largest per-axis sigma of a pose covariance: rotation (arc-seconds), translation (mm).
fn sigmas_of(cov: &crate::geometry::Mat6) -> (f64, f64) {
    let t = (0..3).map(|i| cov[(i, i)]).fold(0.0f64, f64::max).sqrt();
    let r = (3..6).map(|i| cov[(i, i)]).fold(0.0f64, f64::max).sqrt() * ARCSEC_PER_RAD;
    (r, t)
}

/// `camera_from_plate` from a frame: the plate found, PnP on its discs weighted by the
/// detector, eccentricity corrected; with its sigmas.
fn plate_pose(
    camera: &CameraModel,
    plate: &Plate,
    image: &GreyImage,
) -> Result<(Pose, f64, f64), String> {
    let found = find_plate(plate, image)?;
    let points: Vec<_> = found.ids.iter().map(|&i| plate.point_mm(i)).collect();
    let normals = vec![crate::geometry::Vec3::z(); points.len()];
    let options = PnpOptions {
        pixel_sigma_px: 0.0,
        max_rms_px: 1.0,
        ..PnpOptions::default()
    };
    let (solution, _) = solve_pnp_discs(
        camera,
        &points,
        &normals,
        |k| plate.disc_diameter_mm(found.ids[k]),
        &found.points_px,
        &found.sigmas_px,
        &options,
    )
    .map_err(|e| e.to_string())?;
    let (r, t) = sigmas_of(&solution.covariance);
    Ok((solution.camera_from_marker, r, t))
}

/// Renders `views` random views of `plate` as `camera` of the installation sees them into the
/// new directory `dir` (`view_NN.png`, `truth.json`); returns how many were written.
pub(super) fn render_plate_views(
    installation: &Installation,
    camera: &str,
    plate: &Plate,
    views: usize,
    seed: u64,
    dir: &Path,
    progress: &indicatif::ProgressBar,
) -> anyhow::Result<usize> {
    let model = installation
        .model
        .camera(camera)
        .ok_or_else(|| anyhow::anyhow!("no camera `{camera}` in the installation"))?
        .intrinsics;
    std::fs::create_dir(dir)
        .with_context(|| format!("cannot create {} (it must not exist)", dir.display()))?;
    let poses = crate::sim::plate::plate_poses(&model, plate, views, seed);
    if poses.len() < views {
        bail!(
            "the plate could be placed wholly in the frame in {} of {views} tries: it is too large for this camera",
            poses.len()
        );
    }
    progress.set_length(poses.len() as u64);
    let mut truth = Vec::with_capacity(poses.len());
    for (k, pose) in poses.iter().enumerate() {
        let settings = crate::sim::render::RenderSettings {
            samples_per_side: 16,
            seed: seed.wrapping_mul(1000).wrapping_add(k as u64),
            ..crate::sim::render::RenderSettings::default()
        };
        let image = crate::sim::plate::render_plate(&model, plate, pose, &settings);
        let bytes = crate::imagefile::encode(&image, FrameFormat::Png)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let name = format!("view_{k:02}.png");
        std::fs::write(dir.join(&name), bytes)
            .with_context(|| format!("cannot write {}", dir.join(&name).display()))?;
        truth.push(serde_json::json!({
            "frame": name,
            "camera_from_plate": crate::wire::PoseOut::from(pose),
        }));
        progress.inc(1);
    }
    let d = model.distortion_coefficients();
    let body = serde_json::json!({
        "camera": {
            "frame": camera,
            "width": model.width_px, "height": model.height_px,
            "fx": model.fx_px, "fy": model.fy_px, "cx": model.cx_px, "cy": model.cy_px,
            "distortion": d,
        },
        "views": truth,
    });
    std::fs::write(dir.join("truth.json"), serde_json::to_string_pretty(&body)?)
        .with_context(|| format!("cannot write {}", dir.join("truth.json").display()))?;
    Ok(poses.len())
}

/// Renders a station's calibration session into the new directory `dir`: at each of
/// `positions` positions (`sim::plate::station_motions`), the frame of every camera involved
/// (`position_NN/<camera>.png`: a camera of the station looking at its plate, set up facing it
/// at the first position; a marker of the station seen by the installation's camera that
/// watches it, from the link's nominal pose), and `truth.json` with the link's true pose (the
/// installation's) and the motions. Returns how many positions were written.
#[allow(clippy::too_many_arguments)]
pub(super) fn render_station_views(
    installation: &Installation,
    link: &str,
    plates: &[(String, Plate)],
    positions: usize,
    seed: u64,
    dir: &Path,
    progress: &indicatif::ProgressBar,
) -> anyhow::Result<usize> {
    use crate::sim::plate::{plate_facing, render_plate, station_motions};
    use crate::sim::render::{RenderSettings, marker_discs, render_discs};
    let observer = Observer::new(&installation.model);
    let (first, second, x) = station(installation, &observer, link, plates)?;
    std::fs::create_dir(dir)
        .with_context(|| format!("cannot create {} (it must not exist)", dir.display()))?;
    let motions = station_motions(positions, seed);
    progress.set_length(motions.len() as u64);
    for (i, m) in motions.iter().enumerate() {
        let position = dir.join(format!("position_{i:02}"));
        std::fs::create_dir(&position)
            .with_context(|| format!("cannot create {}", position.display()))?;
        // The parent turns by m; the child by the same motion seen in its own frame.
        for (k, (sensor, motion)) in [(&first, *m), (&second, x.inverse() * m * x)]
            .into_iter()
            .enumerate()
        {
            let settings = RenderSettings {
                samples_per_side: 16,
                seed: seed
                    .wrapping_mul(1000)
                    .wrapping_add(10 * i as u64 + k as u64),
                ..RenderSettings::default()
            };
            let (camera, image) = match sensor {
                Sensor::CameraOnPlate {
                    camera,
                    model,
                    plate,
                } => {
                    let start = plate_facing(model, plate, 0.4, 20.0);
                    (
                        camera,
                        render_plate(model, plate, &(motion.inverse() * start), &settings),
                    )
                }
                Sensor::MarkerSeenBy { marker, camera } => {
                    let seen = observer
                        .link(camera, marker)
                        .map_err(|e| anyhow::anyhow!("{e}"))?;
                    let start = seen.nominal.ok_or_else(|| {
                        anyhow::anyhow!("link {} has no nominal pose to render from", seen.name)
                    })?;
                    (
                        camera,
                        render_discs(
                            &seen.camera,
                            &marker_discs(seen, &(start * motion)),
                            &settings,
                        ),
                    )
                }
            };
            let bytes = crate::imagefile::encode(&image, FrameFormat::Png)
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            let path = position.join(format!("{camera}.png"));
            std::fs::write(&path, bytes)
                .with_context(|| format!("cannot write {}", path.display()))?;
        }
        progress.inc(1);
    }
    let body = serde_json::json!({
        "link": link,
        "parent_from_child": crate::wire::PoseOut::from(&x),
        "motions": motions.iter().map(crate::wire::PoseOut::from).collect::<Vec<_>>(),
    });
    std::fs::write(dir.join("truth.json"), serde_json::to_string_pretty(&body)?)
        .with_context(|| format!("cannot write {}", dir.join("truth.json").display()))?;
    Ok(motions.len())
}
