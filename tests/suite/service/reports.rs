//! A period's report (`GET /api/v1/report`): every statistic it prints is the API's for the
//! same period, and it tells the gap, the alarm with its acknowledgement and the budget that
//! the store and the filters hold.

use super::helpers::{Backend, T0_NS, TestApp, alarmed_installation, turned_sample};
use axum::http::StatusCode;
use brokenray::clock::format_ns;
use brokenray::report::period::{Quantity, cell_id, figure};
use serde_json::{Value, json};

on_both_backends!(a_period_s_report_prints_the_api_s_figures_and_tells_its_gap_and_alarm,);

/// The text of the table cell with `id`.
fn cell<'a>(page: &'a str, id: &str) -> &'a str {
    let start = page
        .find(&format!("id=\"{id}\">"))
        .unwrap_or_else(|| panic!("no cell `{id}`"))
        + id.len()
        + 6;
    &page[start..start + page[start..].find('<').expect("the cell ends")]
}

/// Posts 25 Hz samples of `G_from_B` from `start_ns`, a few arc-seconds of noise about x, the
/// last `turned` of them turned by 90 arc-seconds.
async fn post_run(app: &TestApp, start_ns: i64, count: i64, turned: i64) {
    let samples: Vec<Value> = (0..count)
        .map(|k| {
            let noise = 3.0 * ((k * 7919 % 101) as f64 / 50.0 - 1.0);
            let turn = if k >= count - turned { 90.0 } else { 0.0 };
            turned_sample(start_ns + k * 40_000_000, turn + noise)
        })
        .collect();
    let (status, body) = app
        .post_live("/api/v1/samples", &json!({ "samples": samples }))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
}

async fn a_period_s_report_prints_the_api_s_figures_and_tells_its_gap_and_alarm(backend: Backend) {
    let app = TestApp::start_on(backend, Some(&alarmed_installation(""))).await;
    app.set_straight_reference().await;
    // 4 s of samples, 120 s of silence, 4 s more whose last second turns past the warning.
    post_run(&app, T0_NS, 100, 0).await;
    let resumed_ns = T0_NS + 124_000_000_000;
    post_run(&app, resumed_ns, 100, 25).await;
    let (_, list) = app.get("/api/v1/alarms?target=G").await;
    let raised = list["alarms"]
        .as_array()
        .and_then(|a| a.iter().find(|a| a["to"] == "warn").cloned())
        .expect("the turn raises a warning");
    let id = raised["id"].as_i64().unwrap();
    let ack = json!({"by": "watch officer", "note": "crane load, checked"});
    let (status, body) = app
        .post_json(&format!("/api/v1/alarms/{id}/ack"), &ack)
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");

    let (from, to) = (format_ns(T0_NS), format_ns(T0_NS + 130_000_000_000));
    let window = format!("from={from}&to={to}");
    let (status, headers, bytes) = app
        .request_raw(
            "GET",
            &format!("/api/v1/report?{window}&min_gap_s=30"),
            &[],
            axum::body::Body::empty(),
        )
        .await;
    let page = String::from_utf8(bytes.to_vec()).expect("UTF-8");
    assert_eq!(status, StatusCode::OK, "{page}");
    assert_eq!(headers["content-type"], "text/html; charset=utf-8");
    assert_eq!(
        headers["content-security-policy"],
        brokenray::report::CONTENT_SECURITY_POLICY
    );
    assert!(!page.contains("<script"), "a report runs no script");

    // Every statistic is the API's for the same period, printed as the report prints it.
    for source in ["raw", "filtered"] {
        let (status, stats) = app
            .get(&format!("/api/v1/targets/G/stats?{window}&source={source}"))
            .await;
        assert_eq!(status, StatusCode::OK, "{stats}");
        let count = stats["count"].as_u64().expect("a count");
        assert!(count > 150, "most of the 200 groups give a result: {count}");
        assert!(
            page.contains(&format!(" {count} {source} results")),
            "the {source} count"
        );
        for (quantity, unit) in [
            ("euler_deg", Quantity::EulerDeg),
            ("t_mm", Quantity::TranslationMm),
        ] {
            for statistic in ["min", "max", "mean", "rms", "expected_rms"] {
                let values = &stats[quantity][statistic];
                if values.is_null() {
                    continue;
                }
                for axis in 0..3 {
                    let api = values[axis].as_f64().expect("a number");
                    let id = cell_id("G", source, quantity, statistic, axis);
                    assert_eq!(cell(&page, &id), figure(api, unit), "{id}");
                }
            }
        }
    }
    assert!(
        page.contains("G-raw-euler_deg-expected_rms-x"),
        "raw results carry their random part: the expected rms is printed"
    );

    // The silence: from the last sample before it to the first after, nothing measured.
    let last_before = format_ns(T0_NS + 99 * 40_000_000);
    let gap_row = format!(
        "<tr><td class=\"l\">{last_before}</td><td class=\"l\">{}</td><td>120.0</td>",
        format_ns(resumed_ns)
    );
    assert!(page.contains(&gap_row), "the gap's row: {gap_row}");
    assert!(page.contains("1 gap, 120 s in all"), "the count");
    assert!(page.contains("no link of its chain stored a sample"));

    // The alarm and who acknowledged it.
    assert!(page.contains("none &rarr; warn"), "the warning");
    assert!(page.contains("by watch officer at"));
    assert!(page.contains("crane load, checked"));

    // The budget's whole sigma is the API's.
    let (_, budget) = app.get("/api/v1/targets/G/budget").await;
    let sigma_rx = budget["sigma"]["rotation"][0].as_f64().unwrap();
    assert!(
        page.contains(&format!(
            "<td class=\"l\">whole sigma</td><td class=\"l\"></td><td>{}</td>",
            figure(sigma_rx, Quantity::RotationArcsec)
        )),
        "the whole sigma"
    );
    assert!(page.contains("noise G_from_B"), "the contributor");

    // Six pictures of the target's deformation (against the reference), each with a band.
    assert_eq!(page.matches("<svg").count(), 6);
    assert!(page.contains("aria-label=\"G: rotation x (arcsec)\""));
    // The pictures are the history's: the filtered line of each panel, read back from its
    // picture's pixels, is `GET .../history`'s bucket means for the same period (600 buckets),
    // to the half tenth of a pixel the path is written with.
    for (label, component) in [
        ("rotation x (arcsec)", "def_rx_arcsec"),
        ("translation z (mm)", "def_tz_mm"),
    ] {
        let (_, history) = app
            .get(&format!(
                "/api/v1/targets/G/history?{window}&source=filtered&max_points=600&components={component}"
            ))
            .await;
        let means: Vec<f64> = history["series"][component]["mean"]
            .as_array()
            .expect("means")
            .iter()
            .filter_map(Value::as_f64)
            .collect();
        let drawn = picture_line(&page, &format!("G: {label}"));
        assert_eq!(drawn.len(), means.len(), "{label}: a point a bucket");
        let (lo, hi, px_value) = drawn_range(&page, &format!("G: {label}"));
        for (k, (v, m)) in drawn.iter().zip(&means).enumerate() {
            assert!(
                (v - m).abs() <= 0.06 * px_value + 1e-4 * (hi - lo).abs().max(1.0),
                "{label}, bucket {k}: drawn {v}, history {m}"
            );
        }
    }

    // A period that is not one is refused, naming the field.
    for (query, field) in [
        (format!("{window}&min_gap_s=0"), "min_gap_s"),
        (format!("from={to}&to={from}"), "to"),
        (format!("from={to}&to={to}"), "to"),
        (
            "from=2020-01-01T00:00:00Z&to=2022-01-01T00:00:00Z".to_owned(),
            "from",
        ),
    ] {
        let (status, body) = app.get(&format!("/api/v1/report?{query}")).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{query}: {body}");
        assert_eq!(
            body["error"]["details"][0]["field"], field,
            "{query}: {body}"
        );
    }
}

/// `[reports]`: the last day that has ended is filed once, under its ends' name, with the
/// day's results; a folder that cannot be written is told in `/healthz` (which stays 200) until
/// a report is filed.
#[tokio::test]
async fn the_scheduled_report_files_each_period_once_and_tells_a_failure() {
    let folder = tempfile::tempdir().unwrap();
    let reports = folder.path().join("filed");
    let config = alarmed_installation(&format!(
        "[reports]\nevery_days = 1\nfolder = \"{}\"\nmin_gap_s = 30\n",
        reports.display()
    ));
    let app = TestApp::start(Some(&config)).await;
    // The service looks at once: the day before its start (the 20th) is filed, empty. Waited
    // for, so that this look's own file and problem cannot land among the checks below.
    let at_start = reports.join("brokenray-report-2026-11-20T00-00-00Z--2026-11-21T00-00-00Z.html");
    let waited = std::time::Instant::now();
    while !at_start.exists() {
        assert!(
            waited.elapsed() < std::time::Duration::from_secs(60),
            "the scheduled look at start filed nothing"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    post_run(&app, T0_NS, 100, 0).await;
    // The next morning: the 21st has ended.
    app.clock.set_ns(T0_NS + 86_400_000_000_000);
    let settings = app
        .service
        .installation()
        .reports
        .clone()
        .expect("[reports]");
    assert_eq!(settings.every_ns, 86_400_000_000_000);
    let filed = app
        .service
        .file_due_report(&settings)
        .await
        .expect("filed")
        .expect("a new report");
    assert_eq!(
        filed,
        reports.join("brokenray-report-2026-11-21T00-00-00Z--2026-11-22T00-00-00Z.html")
    );
    let page = std::fs::read_to_string(&filed).unwrap();
    assert!(page.contains("The period holds 100 raw results"), "{page}");
    assert!(
        page.contains("2 gaps"),
        "the silences before the first result and after the last"
    );
    // Once: the next look finds it there and leaves it.
    assert_eq!(app.service.file_due_report(&settings).await, Ok(None));
    assert_eq!(std::fs::read_to_string(&filed).unwrap(), page);
    assert!(
        std::fs::read_dir(&reports).unwrap().all(|e| !e
            .unwrap()
            .file_name()
            .to_string_lossy()
            .ends_with(".part")),
        "no part file left"
    );

    // A folder that cannot be made: the failure is told, the service stays healthy.
    let blocker = folder.path().join("blocker");
    std::fs::write(&blocker, b"a file").unwrap();
    let broken = brokenray::config::ReportSettings {
        folder: blocker.join("reports"),
        ..settings.clone()
    };
    let error = app.service.file_due_report(&broken).await.unwrap_err();
    assert!(error.contains("could not be written"), "{error}");
    let (status, health) = app.get("/healthz").await;
    assert_eq!(status, StatusCode::OK, "{health}");
    assert_eq!(health["reports_problem"], error.as_str(), "{health}");
    // The next report filed clears it.
    app.clock.set_ns(T0_NS + 2 * 86_400_000_000_000);
    assert!(
        app.service
            .file_due_report(&settings)
            .await
            .unwrap()
            .is_some()
    );
    let (_, health) = app.get("/healthz").await;
    assert!(health["reports_problem"].is_null(), "{health}");
}

/// The picture labelled `label` in a report page.
fn picture<'a>(page: &'a str, label: &str) -> &'a str {
    let start = page
        .find(&format!("aria-label=\"{label}\""))
        .unwrap_or_else(|| panic!("a picture {label}"));
    let end = start + page[start..].find("</svg>").expect("the picture's end");
    &page[start..end]
}

/// A picture's value axis: its lowest and highest values as printed, and the value of a
/// pixel (the plot area is 110 pixels high: 150 less 18 above and 22 below).
fn drawn_range(page: &str, label: &str) -> (f64, f64, f64) {
    let svg = picture(page, label);
    let texts: Vec<&str> = svg
        .split("<text ")
        .skip(1)
        .map(|t| &t[t.find('>').unwrap() + 1..t.find("</text>").unwrap()])
        .collect();
    // The label, the highest value, the lowest, then the period's ends.
    let (hi, lo): (f64, f64) = (texts[1].parse().unwrap(), texts[2].parse().unwrap());
    (lo, hi, (hi - lo) / 110.0)
}

/// The values of the filtered line of the picture labelled `label`, read back from its paths.
fn picture_line(page: &str, label: &str) -> Vec<f64> {
    let svg = picture(page, label);
    let (lo, hi, _) = drawn_range(page, label);
    // One path a run of consecutive buckets, in time order.
    svg.split("<path ")
        .filter(|p| p.contains("stroke=\"#1f4e8c\""))
        .flat_map(|path| {
            let d = &path[path.find("d=\"").unwrap() + 3..];
            let d = &d[..d.find('"').unwrap()];
            d.split(['M', 'L'])
                .filter(|p| !p.is_empty())
                .map(|point| {
                    let y: f64 = point.split(',').nth(1).unwrap().parse().unwrap();
                    hi - (y - 18.0) * (hi - lo) / 110.0
                })
                .collect::<Vec<f64>>()
        })
        .collect()
}
