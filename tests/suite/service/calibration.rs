//! `POST /calibration/camera` through the router: a calibration from detected plate points,
//! and every kind of refusal with the field or the reason.

use super::helpers::TestApp;
use crate::camera_calibration::{plate, projected_views, wide_camera};
use axum::http::StatusCode;
use brokenray::sim::plate::plate_poses;
use serde_json::{Value, json};

pub(crate) fn request(views: usize, fix: &[&str]) -> Value {
    let camera = wide_camera();
    let plate = plate();
    let poses = plate_poses(&camera, &plate, views, 11);
    let views: Vec<Value> = projected_views(&camera, &plate, &poses, 0.01, 12)
        .iter()
        .map(|v| {
            json!({
                "points_px": v.points_px.iter().map(|p| [p.x, p.y]).collect::<Vec<_>>(),
                "ids": v.ids,
            })
        })
        .collect();
    json!({
        "plate": {"rows": 7, "cols": 9, "spacing_mm": 15.0, "diameter_mm": 7.5, "asymmetric": true},
        "image_size": [1280, 1024],
        "views": views,
        "fix": fix,
    })
}

#[tokio::test]
async fn a_camera_is_calibrated_from_plate_points_and_nothing_is_stored() {
    let app = TestApp::start(None).await;
    let truth = wide_camera();
    let (status, body) = app
        .post_json("/api/v1/calibration/camera", &request(12, &["k3"]))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let get = |v: &Value| v.as_f64().expect("a number");
    for (name, value) in [
        ("fx", truth.fx_px),
        ("fy", truth.fy_px),
        ("cx", truth.cx_px),
        ("cy", truth.cy_px),
    ] {
        let error = get(&body["camera"][name]) - value;
        let sigma = get(&body["sigma"][name]);
        assert!(
            sigma > 0.0 && error.abs() < 4.0 * sigma,
            "{name}: {error} vs {sigma}"
        );
    }
    // k3 stays fixed at zero (truth -0.02, so the others absorb it: only fixed is checked).
    assert_eq!(get(&body["camera"]["distortion"][4]), 0.0);
    assert_eq!(get(&body["sigma"]["distortion"][4]), 0.0);
    assert_eq!(body["fixed"], json!(["k3"]));
    assert_eq!(body["covariance"].as_array().expect("covariance").len(), 81);
    assert_eq!(body["parameters"][2], "cx");
    let cov_cx = get(&body["covariance"][2 * 9 + 2]);
    assert!((cov_cx.sqrt() - get(&body["sigma"]["cx"])).abs() < 1e-12);
    let views = body["views"].as_array().expect("views");
    assert_eq!(views.len(), 12);
    assert!(
        views
            .iter()
            .all(|v| v["rms_px"].as_f64().is_some() && v["pose"]["t_mm"].is_array())
    );
    assert!(get(&body["rms_px"]) < 0.05, "{body}");
    assert!(body["warnings"].is_array());
    // The rendered plate is flat: `auto` tests its sag and keeps it flat.
    assert_eq!(body["plate_shape"], "flat", "{body}");
    assert_eq!(body["plate_warp"]["significant"], false, "{body}");
    assert!(get(&body["plate_warp"]["sigma_x_mm"]) > 0.0, "{body}");
    // The lens model: Brown-Conrady's by default.
    assert_eq!(body["model"], "brown", "{body}");
    assert_eq!(
        body["camera"]["distortion"]
            .as_array()
            .expect("terms")
            .len(),
        5
    );
    assert_eq!(body["parameters"].as_array().expect("names").len(), 9);
    // The residuals binned and judged: the bins' z² add up to chi2, the sigma of a bin's mean
    // is positive, and the message says the judgement.
    let structure = &body["residual_structure"];
    assert_eq!(
        (structure["bins_x"].as_u64(), structure["bins_y"].as_u64()),
        (Some(8), Some(6))
    );
    let bins = structure["bins"].as_array().expect("bins");
    assert!(!bins.is_empty() && structure["dof"].as_u64() == Some(2 * bins.len() as u64));
    let sum: f64 = bins.iter().map(|b| get(&b["z2"])).sum();
    assert!(
        (sum - get(&structure["chi2"])).abs() < 1e-9 * sum.max(1.0),
        "{structure}"
    );
    for b in bins {
        let (m, s) = (&b["mean_px"], get(&b["sigma_px"]));
        let z2 = (get(&m[0]).powi(2) + get(&m[1]).powi(2)) / (s * s);
        assert!(
            s > 0.0 && (z2 - get(&b["z2"])).abs() < 1e-9 * z2.max(1.0),
            "{b}"
        );
        assert!(b["points"].as_u64().expect("points") >= 5);
    }
    let significant = structure["significant"].as_bool().expect("a judgement");
    assert_eq!(
        significant,
        get(&structure["chi2"]) > get(&structure["threshold"])
    );
    let message = body["residual_message"].as_str().expect("text");
    assert!(message.contains("brown lens model"), "{message}");
    // The rational model answers its eight terms and a 12 x 12 covariance.
    let mut rational = request(12, &["k3"]);
    rational["model"] = json!("rational");
    rational["fix"] = json!(["k3", "k6"]);
    let (status, body) = app.post_json("/api/v1/calibration/camera", &rational).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["model"], "rational", "{body}");
    assert_eq!(
        body["camera"]["distortion"]
            .as_array()
            .expect("terms")
            .len(),
        8
    );
    assert_eq!(
        body["covariance"].as_array().expect("covariance").len(),
        144
    );
    assert_eq!(body["parameters"][11], "k6");
    assert!(
        body["plate_message"]
            .as_str()
            .expect("text")
            .starts_with("plate fitted flat"),
        "{body}"
    );
    let mut warped = request(12, &["k3"]);
    warped["plate_shape"] = json!("warped");
    let (status, body) = app.post_json("/api/v1/calibration/camera", &warped).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["plate_shape"], "warped", "{body}");
    // The sag of a flat plate is zero within its sigma.
    let (sag, sigma) = (
        get(&body["plate_warp"]["sag_x_mm"]),
        get(&body["plate_warp"]["sigma_x_mm"]),
    );
    assert!(sag.abs() < 4.0 * sigma, "{body}");
    // Nothing stored: no link has samples.
    app.assert_nothing_stored().await;
}

#[tokio::test]
async fn invalid_requests_name_the_field_and_impossible_ones_say_why() {
    let app = TestApp::start(None).await;
    // Focal lengths are fixed at a known value only.
    let mut known = request(6, &["fx", "fy"]);
    known["initial"] = json!({"fx": 1650.0, "fy": 1648.0, "cx": 640.0, "cy": 512.0});
    let (status, body) = app.post_json("/api/v1/calibration/camera", &known).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["camera"]["fx"], 1650.0);
    assert_eq!(body["sigma"]["fx"], 0.0);
    assert_ne!(
        body["camera"]["cx"], 640.0,
        "cx is free: initial gives only fixed values"
    );
    let (status, body) = app
        .post_json("/api/v1/calibration/camera", &request(6, &["fx"]))
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert!(
        body["error"]["message"]
            .as_str()
            .expect("text")
            .contains("fx can be fixed only at a known value"),
        "{body}"
    );

    // The asymmetric plate's discs are sqrt(2) x 15 mm = 21.2 mm from their neighbours.
    let mut bad_plate = request(4, &[]);
    bad_plate["plate"]["diameter_mm"] = json!(22.0);
    let (status, body) = app
        .post_json("/api/v1/calibration/camera", &bad_plate)
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["error"]["code"], "invalid_request");
    assert_eq!(body["error"]["details"][0]["field"], "plate");
    assert!(
        body["error"]["details"][0]["message"]
            .as_str()
            .expect("text")
            .contains("would touch")
    );

    let (status, body) = app
        .post_json("/api/v1/calibration/camera", &request(4, &["k7"]))
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["error"]["details"][0]["field"], "fix");

    let mut fisheye = request(4, &[]);
    fisheye["model"] = json!("fisheye");
    let (status, body) = app.post_json("/api/v1/calibration/camera", &fisheye).await;
    assert!(status.is_client_error(), "{body}");
    let message = body["error"]["message"].as_str().expect("text");
    assert!(
        message.contains("fisheye") && message.contains("rational_prism"),
        "{body}"
    );
    let mut long = request(4, &[]);
    long["initial"] = json!({"fx": 1650.0, "fy": 1650.0, "cx": 640.0, "cy": 512.0,
        "distortion": [0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0]});
    let (status, body) = app.post_json("/api/v1/calibration/camera", &long).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["error"]["details"][0]["field"], "initial", "{body}");
    assert!(
        body["error"]["details"][0]["message"]
            .as_str()
            .is_some_and(|m| m.contains("the brown model has 5")),
        "{body}"
    );

    let mut bent = request(4, &[]);
    bent["plate_shape"] = json!("bent");
    let (status, body) = app.post_json("/api/v1/calibration/camera", &bent).await;
    assert!(status.is_client_error(), "{body}");
    let message = body["error"]["message"].as_str().expect("text");
    assert!(
        message.contains("bent") && message.contains("warped"),
        "{body}"
    );

    let mut unknown = request(4, &[]);
    unknown["views"][0]["colour"] = json!("red");
    let (status, body) = app.post_json("/api/v1/calibration/camera", &unknown).await;
    assert!(status.is_client_error(), "{body}");
    assert!(
        body["error"]["message"]
            .as_str()
            .expect("text")
            .contains("colour"),
        "{body}"
    );

    let (status, body) = app
        .post_json("/api/v1/calibration/camera", &request(2, &[]))
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["error"]["code"], "calibration_refused");
    assert!(
        body["error"]["message"]
            .as_str()
            .expect("text")
            .contains("at least 3"),
        "{body}"
    );
}
