//! Development script: the intrinsics covariance a calibration of each built-in camera leaves,
//! for the built-in installation's `intrinsics_covariance`.
//!
//! Run: `cargo run --release --example intrinsics_covariance -- [--views 12] [--seed 1]`.
//!
//! Each camera of the built-in installation is calibrated as `calibrate-camera` would do it
//! on a real rig: a 7 x 9 asymmetric plate of 7.5 mm dark discs 15 mm apart, rendered in
//! `--views` random poses (0.6 px blur, read and shot noise), detected, found and solved with
//! k3 fixed. Prints each camera's calibrated intrinsics, their sigmas, and the covariance as
//! the installation takes it.

use brokenray::config;
use brokenray::sim::plate::{plate_poses, render_plate};
use brokenray::sim::render::RenderSettings;
use brokenray::vision::{
    CalibrationOptions, CalibrationView, DetectSettings, Intrinsic, Plate, Polarity,
    calibrate_camera, detect,
};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .map(|v| v.parse::<u64>())
            .transpose()
    };
    let views = arg("--views")?.unwrap_or(12) as usize;
    let seed = arg("--seed")?.unwrap_or(1);
    let installation = config::load_or_default(None)?;
    let plate = Plate::new(7, 9, 15.0, 7.5, true, Polarity::Dark)?;
    for (k, camera) in installation.model.cameras.iter().enumerate() {
        let truth = camera.intrinsics;
        let detect_settings = DetectSettings {
            polarity: plate.polarity(),
            gain_e_per_dn: camera.gain_e_per_dn,
            ..DetectSettings::default()
        };
        let camera_seed = seed * 100 + k as u64;
        let found: Vec<CalibrationView> = plate_poses(&truth, &plate, views, camera_seed)
            .iter()
            .enumerate()
            .map(|(v, pose)| {
                let settings = RenderSettings {
                    samples_per_side: 16,
                    seed: camera_seed * 1000 + v as u64,
                    ..RenderSettings::default()
                };
                let frame = render_plate(&truth, &plate, pose, &settings);
                let view = plate.find(&detect(&frame, &detect_settings))?;
                Ok(CalibrationView {
                    ids: view.ids,
                    points_px: view.points_px,
                    sigmas_px: Some(view.sigmas_px),
                })
            })
            .collect::<anyhow::Result<_>>()?;
        let c = calibrate_camera(
            &plate,
            truth.width_px,
            truth.height_px,
            &found,
            &CalibrationOptions {
                fixed: vec![Intrinsic::K3],
                ..CalibrationOptions::default()
            },
        )?;
        println!(
            "# {}: {} views, RMS {:.4} px; sigmas {}",
            camera.frame,
            found.len(),
            c.rms_px,
            Intrinsic::ALL
                .iter()
                .map(|p| format!("{} {:.3e}", p.name(), c.sigma[p.index()]))
                .collect::<Vec<_>>()
                .join(", ")
        );
        println!("intrinsics_covariance = [");
        for row in &c.covariance {
            let cells: Vec<String> = row.iter().map(|v| format!("{v:.4e}")).collect();
            println!("  {},", cells.join(", "));
        }
        println!("]");
    }
    Ok(())
}
