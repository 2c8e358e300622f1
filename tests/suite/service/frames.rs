//! `POST /frames` through the router: rendered frames of the built-in installation in every
//! accepted file format, the markers found, solved and stored, the chain completed; and every
//! refusal named with nothing stored.

use super::helpers::{T0_NS, TestApp};
use axum::http::StatusCode;
use brokenray::clock::{Clock as _, format_ns};
use brokenray::imagefile::{FrameFormat, encode};
use brokenray::sim::render::RenderSettings;
use brokenray::sim::{Scenario, SimGroup, SimSettings, Simulator};
use brokenray::vision::{BitDepth, GreyImage};
use serde_json::Value;

/// A static run of the built-in installation from `T0_NS` at 25 Hz.
pub(super) fn static_simulator(seed: u64) -> Simulator {
    let inst = brokenray::config::default_installation();
    Simulator::new(
        &inst.model,
        SimSettings {
            scenario: Scenario::Static,
            rate_hz: 25.0,
            start_ns: T0_NS,
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed,
        },
    )
    .expect("simulator")
}

/// The group at `T0_NS` of a static run and its three frames (C1, C2, C3).
pub(super) fn rendered(depth: BitDepth) -> (SimGroup, Vec<(String, GreyImage)>) {
    let mut sim = static_simulator(5);
    let group = sim.next_group();
    let settings = RenderSettings {
        samples_per_side: 16,
        depth,
        contrast_dn: if depth == BitDepth::Eight {
            200.0
        } else {
            200.0 * 256.0
        },
        background_dn: if depth == BitDepth::Eight {
            40.0
        } else {
            40.0 * 256.0
        },
        read_noise_dn: if depth == BitDepth::Eight {
            2.0
        } else {
            2.0 * 256.0
        },
        gain_e_per_dn: if depth == BitDepth::Eight {
            Some(40.0)
        } else {
            Some(40.0 / 256.0)
        },
        ..RenderSettings::default()
    };
    let frames = sim.render_frames(&group, &settings);
    (group, frames)
}

pub(crate) async fn post_frame(
    app: &TestApp,
    camera: &str,
    time: &str,
    content_type: &str,
    body: Vec<u8>,
) -> (StatusCode, Value) {
    app.request_with_headers(
        "POST",
        &format!("/api/v1/frames?camera={camera}&time={time}"),
        &[("content-type", content_type)],
        body,
    )
    .await
}

async fn stored_samples(app: &TestApp, link: &str) -> usize {
    let (status, body) = app.get(&format!("/api/v1/links/{link}/samples")).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    body["samples"].as_array().expect("samples").len()
}

#[tokio::test]
async fn frames_in_png_pgm_and_tiff_are_detected_solved_stored_and_complete_the_chain() {
    let app = TestApp::start(None).await;
    let (group, frames) = rendered(BitDepth::Eight);
    let (_, frames16) = rendered(BitDepth::Sixteen);
    let time = format_ns(group.time_ns);
    // C1 as 8-bit PNG, C2 as 16-bit PGM, C3 as 16-bit TIFF.
    let bodies = [
        (
            FrameFormat::Png,
            encode(&frames[0].1, FrameFormat::Png).expect("png"),
        ),
        (
            FrameFormat::Pgm,
            encode(&frames16[1].1, FrameFormat::Pgm).expect("pgm"),
        ),
        (
            FrameFormat::Tiff,
            encode(&frames16[2].1, FrameFormat::Tiff).expect("tiff"),
        ),
    ];
    let mut filtered = 0;
    for ((camera, _), (format, bytes)) in frames.iter().zip(bodies) {
        let (status, body) = post_frame(&app, camera, &time, format.content_type(), bytes).await;
        assert_eq!(status, StatusCode::OK, "{camera}: {body}");
        assert_eq!(body["camera"], camera.as_str());
        assert_eq!(body["time"], time.as_str());
        // Only around the marker's predicted points is searched, and its discs are all there.
        let searched = body["searched_fraction"].as_f64().expect("fraction");
        assert!(searched > 0.0 && searched < 0.3, "{camera}: {searched}");
        let markers = body["markers"].as_array().expect("markers");
        assert_eq!(markers.len(), 1, "{body}");
        assert_eq!(
            body["blobs"].as_u64(),
            Some(markers[0]["ids"].as_array().map_or(0, |i| i.len() as u64)),
            "{camera}: every disc searched is a marker point: {body}"
        );
        let m = &markers[0];
        assert_eq!(m["found"], true, "{camera}: {m}");
        let link = m["link"].as_str().expect("link");
        let points = m["points_px"].as_array().expect("points").len();
        assert_eq!(m["ids"].as_array().expect("ids").len(), points);
        assert_eq!(m["sigma_px"].as_array().expect("sigmas").len(), points);
        assert!(points >= 7, "{m}");
        assert!(
            m["reprojection_rms_px"].as_f64().expect("rms") < 0.05,
            "{m}"
        );
        // The pose is the true one within a tenth of a millimetre.
        let truth = group
            .link_truth
            .iter()
            .find(|(n, _)| n == link)
            .expect("a true pose")
            .1;
        let t = &m["pose"]["t_mm"];
        let error = (0..3)
            .map(|i| (t[i].as_f64().expect("t") - truth.translation.vector[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(error < 0.1, "{link}: {error} mm off");
        assert_eq!(body["ingest"]["accepted"], 1, "{body}");
        assert_eq!(body["ingest"]["stored"], 1, "{body}");
        filtered += body["ingest"]["raw_results"].as_u64().expect("count");
        assert_eq!(stored_samples(&app, link).await, 1);
    }
    // The third frame completes the group: one raw result of G.
    assert_eq!(filtered, 1);
    let (_, stats) = app
        .get(&format!(
            "/api/v1/targets/G/stats?source=raw&from={time}&to={time}"
        ))
        .await;
    assert_eq!(stats["count"], 1, "{stats}");
    let truth = group.truth[0].1;
    let t = &stats["t_mm"]["mean"];
    for i in 0..3 {
        let e = t[i].as_f64().expect("t") - truth.translation.vector[i];
        assert!(e.abs() < 0.5, "G_from_B translation {i} off by {e} mm");
    }
    // The same frame again is a retry: accepted, not stored twice.
    let again = encode(&frames[0].1, FrameFormat::Png).expect("png");
    let (status, body) = post_frame(&app, "C1", &time, "image/png", again).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["ingest"]["duplicates"], 1, "{body}");
    assert_eq!(stored_samples(&app, "C1_from_B").await, 1);
}

#[tokio::test]
async fn a_colour_frame_is_taken_as_its_luma() {
    let app = TestApp::start(None).await;
    let (group, frames) = rendered(BitDepth::Eight);
    let grey = &frames[0].1;
    let rgb = image::RgbImage::from_fn(grey.width_px(), grey.height_px(), |u, v| {
        let g = grey.at(u, v) as u8;
        image::Rgb([g, g, g])
    });
    let mut png = std::io::Cursor::new(Vec::new());
    rgb.write_to(&mut png, image::ImageFormat::Png)
        .expect("png");
    let (status, body) = post_frame(
        &app,
        "C1",
        &format_ns(group.time_ns),
        "image/png",
        png.into_inner(),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["markers"][0]["found"], true, "{body}");
}

#[tokio::test]
async fn an_empty_frame_finds_nothing_and_says_why() {
    let app = TestApp::start(None).await;
    let (group, frames) = rendered(BitDepth::Eight);
    let empty = GreyImage::from_u8(
        frames[0].1.width_px(),
        frames[0].1.height_px(),
        &vec![40; (frames[0].1.width_px() * frames[0].1.height_px()) as usize],
    )
    .expect("frame");
    let (status, body) = post_frame(
        &app,
        "C1",
        &format_ns(group.time_ns),
        "image/png",
        encode(&empty, FrameFormat::Png).expect("png"),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["blobs"], 0);
    let m = &body["markers"][0];
    assert_eq!(m["found"], false);
    assert_eq!(m["reason_code"], "too_few_points", "{m}");
    assert!(
        m["reason"].as_str().expect("reason").contains("at least 4"),
        "{m}"
    );
    assert_eq!(body["ingest"]["accepted"], 0);
    assert_eq!(stored_samples(&app, "C1_from_B").await, 0);
}

#[tokio::test]
async fn bad_frames_are_refused_by_name_and_nothing_is_stored() {
    let app = TestApp::start(None).await;
    let (group, frames) = rendered(BitDepth::Eight);
    let time = format_ns(group.time_ns);
    let png = encode(&frames[0].1, FrameFormat::Png).expect("png");
    let refused = |status: StatusCode, body: &Value, field: Option<&str>, words: &str| {
        assert_eq!(status.as_u16() / 100, 4, "{body}");
        let error = &body["error"];
        let message = error["message"].as_str().expect("message");
        assert!(message.contains(words), "`{words}` not in {message}");
        if let Some(field) = field {
            assert_eq!(error["details"][0]["field"], field, "{body}");
        }
    };
    let (s, b) = post_frame(&app, "C1", &time, "image/gif", png.clone()).await;
    assert_eq!(s, StatusCode::UNSUPPORTED_MEDIA_TYPE);
    refused(s, &b, None, "image/png");
    // A PNG called a JPEG: read as a JPEG, refused as undecodable.
    let (s, b) = post_frame(&app, "C1", &time, "image/jpeg", png.clone()).await;
    refused(s, &b, Some("body"), "not a readable Jpeg image");
    let (s, b) = app
        .request_with_headers(
            "POST",
            &format!("/api/v1/frames?time={time}"),
            &[("content-type", "image/png")],
            png.clone(),
        )
        .await;
    refused(s, &b, Some("camera"), "names no camera");
    let (s, b) = post_frame(&app, "C9", &time, "image/png", png.clone()).await;
    refused(s, &b, Some("camera"), "unknown camera `C9`");
    let (s, b) = app
        .request_with_headers(
            "POST",
            "/api/v1/frames?camera=C1",
            &[("content-type", "image/png")],
            png.clone(),
        )
        .await;
    refused(s, &b, Some("time"), "no measurement time");
    let future = format_ns(app.clock.now_ns() + 3_600_000_000_000);
    let (s, b) = post_frame(&app, "C1", &future, "image/png", png.clone()).await;
    refused(s, &b, Some("time"), "in the future");
    let (s, b) = post_frame(&app, "C1", "yesterday", "image/png", png.clone()).await;
    refused(s, &b, Some("time"), "");
    let (s, b) = post_frame(&app, "C1", &time, "image/png", b"not a png".to_vec()).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY);
    refused(s, &b, Some("body"), "not a readable Png image");
    // A PNG cut short: the header reads, the pixels do not.
    let (s, b) = post_frame(
        &app,
        "C1",
        &time,
        "image/png",
        png[..png.len() / 2].to_vec(),
    )
    .await;
    refused(s, &b, Some("body"), "not a readable");
    // A JPEG cut short: its decoder would fill the rest with grey; refused as the PNG is.
    let jpeg = brokenray::imagefile::encode_jpeg(&frames[0].1, 95).expect("jpeg");
    let (s, b) = post_frame(
        &app,
        "C1",
        &time,
        "image/jpeg",
        jpeg[..jpeg.len() * 2 / 3].to_vec(),
    )
    .await;
    refused(s, &b, Some("body"), "the file was cut");
    // C3's frame is 1392 x 1040, not C1's 1280 x 1024.
    let c3 = encode(&frames[2].1, FrameFormat::Png).expect("png");
    let (s, b) = post_frame(&app, "C1", &time, "image/png", c3).await;
    refused(
        s,
        &b,
        Some("body"),
        "1392 x 1040 px but camera C1 is 1280 x 1024 px",
    );
    assert_eq!(stored_samples(&app, "C1_from_B").await, 0);
    // Then the good frame is taken.
    let (s, b) = post_frame(&app, "C1", &time, "image/png", png).await;
    assert_eq!(s, StatusCode::OK, "{b}");
    assert_eq!(stored_samples(&app, "C1_from_B").await, 1);
}

/// A marker that stays lost is searched for in the whole frame once a second of frame time
/// (`[pnp] lost_search_interval_s`, 1 by default), near its prediction in every frame, and the
/// camera's answer says when the next whole search comes; once found it is searched for at once
/// when lost again.
#[tokio::test]
async fn a_lost_marker_is_searched_for_in_the_whole_frame_once_a_second() {
    let app = TestApp::start(None).await;
    let (_, frames) = rendered(BitDepth::Eight);
    let seen = encode(&frames[0].1, FrameFormat::Png).expect("png");
    let empty = GreyImage::from_u8(
        frames[0].1.width_px(),
        frames[0].1.height_px(),
        &vec![40; (frames[0].1.width_px() * frames[0].1.height_px()) as usize],
    )
    .expect("frame");
    let empty = encode(&empty, FrameFormat::Png).expect("png");
    // Frame k at k * 40 ms: (whether it shows the marker, whether the whole frame is searched).
    // The predictions' full gates reach over half of this camera's frame: a frame that may
    // search the whole frame detects the whole frame in their stead (once, not the gates and
    // then the whole frame again), and a paced one keeps to the gates.
    let mut fractions: Vec<(bool, f64)> = Vec::new();
    let mut last_whole = 0;
    for (k, shows, whole) in [
        (0, false, true),
        (1, false, false),
        (2, false, false),
        (24, false, false),
        (25, false, true),
        (26, false, false),
        (27, true, false),
        (28, false, true),
        (29, false, false),
    ] {
        let body = if shows { seen.clone() } else { empty.clone() };
        let time = format_ns(T0_NS + k * 40_000_000);
        let (status, out) = post_frame(&app, "C1", &time, "image/png", body).await;
        assert_eq!(status, StatusCode::OK, "{k}: {out}");
        let searched = out["searched_fraction"].as_f64().expect("fraction");
        let m = &out["markers"][0];
        assert_eq!(m["found"], shows, "{k}: {m}");
        if whole {
            fractions.push((true, searched));
            last_whole = k;
            assert_eq!(m["reason_code"], "too_few_points", "{k}: {m}");
        } else if !shows {
            fractions.push((false, searched));
            assert_eq!(m["reason_code"], "search_paced", "{k}: {m}");
            let since = k - last_whole;
            let next = format!("again in {:.2} s", 1.0 - since as f64 * 0.04);
            let reason = m["reason"].as_str().expect("reason");
            assert!(reason.contains(&next), "{k}: {reason}");
            assert!(
                reason.contains("at least 4"),
                "the reason near the prediction: {reason}"
            );
        }
    }
    // Searched: near + gates (over half the frame) when paced, near + the whole frame when not;
    // so the whole frame's searches exceed the paced ones by less than half a frame.
    let paced: Vec<f64> = fractions.iter().filter(|f| !f.0).map(|f| f.1).collect();
    let wholes: Vec<f64> = fractions.iter().filter(|f| f.0).map(|f| f.1).collect();
    assert!(
        paced.iter().all(|p| (p - paced[0]).abs() < 1e-9),
        "{fractions:?}"
    );
    assert!(
        wholes.iter().all(|w| (w - wholes[0]).abs() < 1e-9),
        "{fractions:?}"
    );
    assert!(paced[0] > 0.5 && paced[0] < 1.5, "{fractions:?}");
    assert!(
        wholes[0] > 1.0 && wholes[0] > paced[0] && wholes[0] < paced[0] + 0.5,
        "{fractions:?}"
    );
    // The camera's state shows the last frame's reason.
    let (_, cameras) = app.get("/api/v1/cameras").await;
    let c1 = &cameras["cameras"][0];
    assert_eq!(
        c1["frame"]["markers"][0]["reason_code"], "search_paced",
        "{c1}"
    );
}
