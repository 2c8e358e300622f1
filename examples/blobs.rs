//! Prints the discs the detector finds in frame files, one JSON line per file, for development
//! scripts that compare them with another detector's (`scripts/real_plates.py --blobs`).
//!
//! Run: `cargo run --release --example blobs -- [--bright] FILE...`.

use brokenray::imagefile::{FrameFormat, decode};
use brokenray::vision::{DetectSettings, Polarity, detect};
use serde_json::json;

fn main() -> anyhow::Result<()> {
    let mut settings = DetectSettings {
        polarity: Polarity::Dark,
        ..DetectSettings::default()
    };
    for arg in std::env::args().skip(1) {
        if arg == "--bright" {
            settings.polarity = Polarity::Bright;
            continue;
        }
        let path = std::path::Path::new(&arg);
        let format = FrameFormat::from_path(path)
            .ok_or_else(|| anyhow::anyhow!("{arg}: not a frame file"))?;
        let image = decode(&std::fs::read(path)?, format, None)?;
        let start = std::time::Instant::now();
        let blobs = detect(&image, &settings);
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let out: Vec<_> = blobs
            .iter()
            .map(|b| {
                json!({"c": b.centre_px, "area": b.area_px, "ellipse": b.ellipse,
                       "sigma": b.sigma_px(), "contrast": b.contrast_dn})
            })
            .collect();
        println!("{}", json!({"file": arg, "ms": ms, "blobs": out}));
    }
    Ok(())
}
