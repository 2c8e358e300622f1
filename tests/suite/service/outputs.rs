//! The plant's outputs end to end on loopback: a real Mosquitto broker and an MQTT subscriber,
//! a Modbus/TCP client, a UDP listener parsing NMEA sentences strictly. What each receives
//! equals the API's answer for the same result; alarm transitions arrive in order; a broker
//! that goes away and returns gets the newest state.

use super::helpers::{T0_NS, TestApp, alarmed_installation, turned_sample};
use crate::common::{Needs, mosquitto_bin, skip_without};
use axum::http::StatusCode;
use serde_json::{Value, json};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Waits (at most `limit`) until `done` holds; false when it never did.
async fn within(limit: Duration, mut done: impl FnMut() -> bool) -> bool {
    let start = std::time::Instant::now();
    while start.elapsed() < limit {
        if done() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    done()
}

/// 25 samples a second turned by `arcsec` in four runs: warn, back, alarm, back (four
/// transitions).
fn four_transitions(from_k: i64) -> Vec<Value> {
    (0..100)
        .map(|k| {
            turned_sample(
                T0_NS + (from_k + k) * 40_000_000,
                [80.0, 0.0, 200.0, 0.0][k as usize / 25],
            )
        })
        .collect()
}

/// Sets G's reference and posts [`four_transitions`]: the four stored transitions, as the API
/// lists them.
async fn four_alarms(app: &TestApp) -> Vec<Value> {
    app.set_straight_reference().await;
    let (status, body) = app
        .post_live(
            "/api/v1/samples",
            &json!({ "samples": four_transitions(0) }),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (_, list) = app.get("/api/v1/alarms?target=G").await;
    let alarms = list["alarms"].as_array().unwrap().clone();
    assert_eq!(alarms.len(), 4, "{list}");
    alarms
}

/// A throwaway Mosquitto broker on a loopback port, stopped when dropped.
struct Broker {
    port: u16,
    dir: tempfile::TempDir,
    child: Option<std::process::Child>,
}

impl Broker {
    fn start() -> Broker {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let mut broker = Broker {
            port,
            dir: tempfile::tempdir().unwrap(),
            child: None,
        };
        broker.run();
        broker
    }

    /// Starts (or starts again) the broker on its port, and waits until it accepts.
    fn run(&mut self) {
        let conf = self.dir.path().join("mosquitto.conf");
        std::fs::write(
            &conf,
            format!(
                "listener {} 127.0.0.1\nallow_anonymous true\npersistence false\n",
                self.port
            ),
        )
        .unwrap();
        let child = std::process::Command::new(mosquitto_bin())
            .arg("-c")
            .arg(&conf)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("mosquitto starts");
        self.child = Some(child);
        for _ in 0..500 {
            if std::net::TcpStream::connect(("127.0.0.1", self.port)).is_ok() {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!("mosquitto does not accept on {}", self.port);
    }

    fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A message received: topic, payload.
type Message = (String, Vec<u8>);

/// What a subscriber received, in order.
#[derive(Clone, Default)]
struct Heard(Arc<Mutex<Vec<Message>>>);

impl Heard {
    /// Waits (at most `limit`) until the newest message on `topic` is the result of `time`.
    async fn newest_is(&self, topic: &str, time: &Value, limit: Duration) -> bool {
        within(limit, || {
            self.on(topic).last().is_some_and(|c| &c["time"] == time)
        })
        .await
    }

    fn on(&self, topic: &str) -> Vec<Value> {
        (self.0.lock().unwrap().iter())
            .filter(|(t, _)| t == topic)
            .map(|(_, p)| serde_json::from_slice(p).expect("JSON payload"))
            .collect()
    }
}

/// Subscribes to everything below `brokenray/` on the broker at `port`.
async fn subscriber(port: u16, id: &str) -> (Heard, tokio::task::JoinHandle<()>) {
    let mut options = rumqttc::MqttOptions::new(id, "127.0.0.1", port);
    options.set_keep_alive(Duration::from_secs(5));
    let (client, mut events) = rumqttc::AsyncClient::new(options, 100);
    client
        .subscribe("brokenray/#", rumqttc::QoS::AtLeastOnce)
        .await
        .unwrap();
    let heard = Heard::default();
    let record = heard.clone();
    let task = tokio::spawn(async move {
        let _client = client;
        loop {
            match events.poll().await {
                Ok(rumqttc::Event::Incoming(rumqttc::Packet::Publish(p))) => {
                    record.0.lock().unwrap().push((p.topic, p.payload.to_vec()));
                }
                Ok(_) => {}
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        }
    });
    (heard, task)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mqtt_carries_the_apis_compensation_and_every_alarm_in_order_and_survives_the_broker() {
    if skip_without(Needs::Mosquitto, "mqtt_carries_the_apis_compensation") {
        return;
    }
    let mut broker = Broker::start();
    let (heard, listener) = subscriber(broker.port, "listener").await;
    let app = TestApp::start(Some(&alarmed_installation(&format!(
        "[[outputs.mqtt]]\nurl = \"mqtt://127.0.0.1:{}\"\nclient_id = \"ship\"\nrate_hz = 50\n",
        broker.port
    ))))
    .await;
    // Online, said on the status topic.
    assert!(
        within(Duration::from_secs(20), || heard
            .on("brokenray/status")
            .iter()
            .any(|s| s["state"] == "online"))
        .await,
        "no online status"
    );
    let alarms = four_alarms(&app).await;

    // Every transition, in order, each as the API shows it.
    let topic = "brokenray/targets/G/alarm";
    assert!(
        within(Duration::from_secs(20), || heard.on(topic).len() == 4).await,
        "{:?}",
        heard.on(topic)
    );
    assert_eq!(heard.on(topic), alarms);
    // The newest compensation equals the API's answer for the same result.
    let (_, api) = app.get("/api/v1/targets/G/compensation").await;
    let compensation = "brokenray/targets/G/compensation";
    assert!(
        heard
            .newest_is(compensation, &api["time"], Duration::from_secs(20))
            .await,
        "the newest compensation never arrived"
    );
    let mut newest = heard.on(compensation).last().cloned().unwrap();
    let mut expected = api.clone();
    // The API's live answer carries the alarm level in force; a published result carries the
    // level of its own figures (as the event stream does). Both are `none` here.
    assert_eq!(newest["alarm"], "none");
    for v in [&mut newest, &mut expected] {
        v.as_object_mut().unwrap().remove("alarm");
    }
    assert_eq!(newest, expected);
    // The link's state.
    assert!(
        within(Duration::from_secs(20), || heard
            .on("brokenray/links/G_from_B/state")
            .last()
            .is_some_and(|s| s["state"] == "ok"))
        .await
    );

    // An acknowledgement is published on the alarm topic.
    let id = alarms[2]["id"].as_i64().unwrap();
    let (status, body) = app
        .post_json(
            &format!("/api/v1/alarms/{id}/ack"),
            &json!({"by": "officer of the watch"}),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert!(
        within(Duration::from_secs(20), || heard
            .on(topic)
            .last()
            .is_some_and(
                |a| a["id"] == id && a["acknowledged_by"] == "officer of the watch"
            ))
        .await,
        "{:?}",
        heard.on(topic)
    );

    // A subscriber that connects later gets the newest compensation at once (retained).
    let (late, late_task) = subscriber(broker.port, "late").await;
    assert!(
        within(Duration::from_secs(20), || late
            .on(compensation)
            .first()
            .is_some_and(|c| c["time"] == api["time"]))
        .await
    );
    late_task.abort();

    // The broker goes away; four more transitions happen; the output says it is not
    // connected and keeps them.
    broker.stop();
    listener.abort();
    let mut noticed = false;
    for _ in 0..2000 {
        let (_, outputs) = app.get("/api/v1/outputs").await;
        if outputs[0]["connected"] == false {
            noticed = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(noticed, "the output never said that the broker went away");
    let (status, _) = app
        .post_live(
            "/api/v1/samples",
            &json!({ "samples": four_transitions(100) }),
        )
        .await;
    assert_eq!(status, StatusCode::OK);
    let (_, health) = app.get("/healthz").await;
    assert!(
        health["output_problem"]
            .as_str()
            .is_some_and(|p| p.contains("mqtt output") && p.contains("not connected")),
        "{health}"
    );
    let (_, list) = app.get("/api/v1/alarms?target=G").await;
    let alarms = list["alarms"].as_array().unwrap().clone();
    assert_eq!(alarms.len(), 8);
    let (_, api) = app.get("/api/v1/targets/G/compensation").await;

    // It returns (with nothing retained: no persistence): the transitions made while it was
    // away arrive in order, and the newest compensation.
    broker.run();
    let returned = std::time::Instant::now();
    let (heard, _listener) = subscriber(broker.port, "listener-again").await;
    assert!(
        heard
            .newest_is(compensation, &api["time"], Duration::from_secs(30))
            .await,
        "the newest compensation never arrived after the broker returned"
    );
    println!(
        "the newest compensation arrived {:.1} s after the broker returned",
        returned.elapsed().as_secs_f64()
    );
    assert!(
        within(Duration::from_secs(20), || heard.on(topic).len() >= 4).await,
        "{:?}",
        heard.on(topic)
    );
    let ids: Vec<Value> = heard.on(topic).iter().map(|a| a["id"].clone()).collect();
    let expected: Vec<Value> = alarms[4..].iter().map(|a| a["id"].clone()).collect();
    assert_eq!(ids, expected, "the transitions made while away, in order");
    let (_, outputs) = app.get("/api/v1/outputs").await;
    assert_eq!(outputs[0]["kind"], "mqtt");
    assert_eq!(outputs[0]["dropped"], 0, "{outputs}");
    let (_, metrics) = app.get("/metrics").await;
    assert!(
        metrics.as_str().unwrap().contains(&format!(
            "brokenray_output_connected{{output=\"mqtt\",address=\"127.0.0.1:{}\"}}",
            broker.port
        )),
        "{metrics}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mqtt_holds_its_rate_per_target_and_publishes_the_newest() {
    if skip_without(Needs::Mosquitto, "mqtt_holds_its_rate_per_target") {
        return;
    }
    let broker = Broker::start();
    let (heard, _listener) = subscriber(broker.port, "listener").await;
    let app = TestApp::start(Some(&alarmed_installation(&format!(
        "[[outputs.mqtt]]\nurl = \"mqtt://127.0.0.1:{}\"\nrate_hz = 4\n",
        broker.port
    ))))
    .await;
    let topic = "brokenray/targets/G/compensation";
    // 40 batches a few milliseconds apart, each of 0.2 s of measurement time (two results of
    // the event stream's 10 a second): about 80 results in a second or so of wall time.
    let start = std::time::Instant::now();
    for b in 0..40 {
        let samples: Vec<Value> = (0..5)
            .map(|k| turned_sample(T0_NS + (b * 5 + k) * 40_000_000, 10.0))
            .collect();
        let (status, body) = app
            .post_live("/api/v1/samples", &json!({ "samples": samples }))
            .await;
        assert_eq!(status, StatusCode::OK, "{body}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let posting_s = start.elapsed().as_secs_f64();
    let (_, api) = app.get("/api/v1/targets/G/compensation").await;
    assert!(
        heard
            .newest_is(topic, &api["time"], Duration::from_secs(20))
            .await,
        "the newest compensation is published once the rate allows"
    );
    let published = heard.on(topic).len();
    // At most one at once, then 4 a second over the posting, and the newest after it.
    let allowed = 2 + (4.0 * posting_s).ceil() as usize;
    assert!(
        published <= allowed,
        "{published} compensations published in {posting_s:.2} s at 4 a second (at most {allowed})"
    );
    assert!(published >= 2, "{published}");
}

/// A float of the map: two registers, high word first.
fn f32_at(registers: &[u16], at: usize) -> f32 {
    f32::from_bits((u32::from(registers[at]) << 16) | u32::from(registers[at + 1]))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn modbus_registers_equal_the_apis_compensation_and_refuse_writes() {
    use tokio_modbus::prelude::*;
    let app = TestApp::start(Some(&alarmed_installation(
        "[[outputs.modbus]]\nlisten = \"127.0.0.1:0\"\n",
    )))
    .await;
    let (_, outputs) = app.get("/api/v1/outputs").await;
    assert_eq!(outputs[0]["kind"], "modbus", "{outputs}");
    assert_eq!(outputs[0]["connected"], true);
    let addr: std::net::SocketAddr = outputs[0]["address"].as_str().unwrap().parse().unwrap();
    let mut ctx = tcp::connect(addr).await.expect("connects");

    // Before any result: the service block, and a target block that says so.
    let head = ctx.read_holding_registers(0, 4).await.unwrap().unwrap();
    assert_eq!(&head[..2], &[1, 1], "map version 1, one target");
    let block = ctx.read_input_registers(100, 60).await.unwrap().unwrap();
    assert_eq!(block[0], 0, "initializing");
    assert_eq!(block[6], 0, "no flags");
    assert!(f32_at(&block, 12).is_nan());

    app.set_straight_reference().await;
    let samples: Vec<Value> = (0..50)
        .map(|k| turned_sample(T0_NS + k * 40_000_000, 30.0))
        .collect();
    let (status, body) = app
        .post_live("/api/v1/samples", &json!({ "samples": samples }))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    // The result counter moves as the outputs' dispatcher hears of the results, just after
    // the answer: wait for it. Everything else is read from the live state at the read.
    let counter = |block: &[u16]| (u32::from(block[2]) << 16) | u32::from(block[3]);
    let mut block = ctx.read_holding_registers(100, 60).await.unwrap().unwrap();
    for _ in 0..2000 {
        if counter(&block) >= 1 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
        block = ctx.read_holding_registers(100, 60).await.unwrap().unwrap();
    }
    assert!(counter(&block) >= 1, "the result counter never moved");
    let (_, api) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(block[0], 1, "ok: {api}");
    assert_eq!(api["status"], "ok");
    assert_eq!(block[1], 0, "no alarm at 30 arcsec");
    assert_eq!(block[6], 3, "a result and a deformation");
    assert_eq!(f32_at(&block, 4), api["age_s"].as_f64().unwrap() as f32);
    let d = &api["deformation"];
    let c = &api["correction"];
    for i in 0..3 {
        let pairs = [
            (12, &d["rotation_arcsec"][i]),
            (18, &d["translation_mm"][i]),
            (24, &d["sigma"]["rotation_arcsec"][i]),
            (30, &d["sigma"]["translation_mm"][i]),
            (36, &c["rotation_arcsec"][i]),
            (42, &c["t_mm"][i]),
            (48, &c["sigma"]["rotation_arcsec"][i]),
            (54, &c["sigma"]["translation_mm"][i]),
        ];
        for (at, v) in pairs {
            let want = v.as_f64().unwrap() as f32;
            let got = f32_at(&block, at + 2 * i);
            // The correction's translation is the pose's (the API), the register the small
            // motion's: the same vector.
            assert!(
                (got - want).abs() <= want.abs() * 1e-6 + 1e-9,
                "register {} = {got}, the API says {want}",
                100 + at + 2 * i
            );
        }
    }
    let turned = (0..3)
        .map(|i| f64::from(f32_at(&block, 12 + 2 * i)).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        (turned - 30.0).abs() < 5.0,
        "turned by {turned} arcsec, not about 30"
    );
    let time_s = (u32::from(block[8]) << 16) | u32::from(block[9]);
    assert_eq!(
        i64::from(time_s) * 1000 + i64::from(block[10]),
        (T0_NS + 49 * 40_000_000) / 1_000_000
    );

    // A read across the service block, the gap and a target's block.
    let across = ctx.read_holding_registers(0, 110).await.unwrap().unwrap();
    assert_eq!(&across[100..110], &block[..10]);
    // Writes are refused; a read past the map is refused.
    assert_eq!(
        ctx.write_single_register(100, 7).await.unwrap(),
        Err(ExceptionCode::IllegalFunction)
    );
    assert_eq!(
        ctx.read_holding_registers(150, 20).await.unwrap(),
        Err(ExceptionCode::IllegalDataAddress)
    );
    let (_, outputs) = app.get("/api/v1/outputs").await;
    assert_eq!(outputs[0]["clients"], 1, "{outputs}");
    assert!(outputs[0]["sent"].as_u64().unwrap() >= 4, "{outputs}");
}

/// A strictly parsed sentence: `$`, body, `*`, checksum, CR LF, at most 82 characters.
fn parse_sentence(datagram: &[u8]) -> Vec<String> {
    let text = std::str::from_utf8(datagram).expect("ASCII");
    assert!(text.len() <= 82, "{text:?} is longer than 82");
    assert!(text.starts_with('$') && text.ends_with("\r\n"), "{text:?}");
    let (body, sum) = text[1..text.len() - 2].split_once('*').expect("a checksum");
    let want = body.bytes().fold(0u8, |a, b| a ^ b);
    assert_eq!(u8::from_str_radix(sum, 16).unwrap(), want, "{text:?}");
    assert_eq!(sum.len(), 2);
    body.split(',').map(str::to_owned).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nmea_sentences_carry_the_apis_deformation_and_the_alarms_in_order() {
    let receiver = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let started = std::time::Instant::now();
    let mut rotation_sentences = 0usize;
    let to = receiver.local_addr().unwrap();
    let app = TestApp::start(Some(&alarmed_installation(&format!(
        "[[outputs.nmea]]\nto = \"{to}\"\ntalker = \"YX\"\nrate_hz = 10\n"
    ))))
    .await;
    let alarms = four_alarms(&app).await;
    let (_, api) = app.get("/api/v1/targets/G/compensation").await;

    let mut alr = Vec::new();
    let mut rotation = None;
    let mut translation = None;
    let mut buf = [0u8; 1500];
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while (alr.len() < 4 || rotation.is_none() || translation.is_none())
        && tokio::time::Instant::now() < deadline
    {
        let Ok(Ok(n)) = tokio::time::timeout(Duration::from_secs(1), receiver.recv(&mut buf)).await
        else {
            continue;
        };
        let fields = parse_sentence(&buf[..n]);
        match fields[0].as_str() {
            "YXXDR" => {
                assert_eq!(fields.len(), 13, "{fields:?}");
                if fields[1] == "A" {
                    rotation_sentences += 1;
                }
                // Empty values (not available) until the result and its reference are there.
                if fields[2].is_empty() {
                    continue;
                }
                if fields[1] == "A" {
                    assert_eq!(&fields[3..5], ["D", "G_RX"]);
                    rotation = Some(fields);
                } else {
                    assert_eq!(&fields[1..5], ["D", &fields[2], "M", "G_TX"]);
                    translation = Some(fields);
                }
            }
            "YXALR" => alr.push(fields),
            other => panic!("unexpected sentence {other}"),
        }
    }
    // The rate held: 10 rotation sentences a second at most (and one at the start).
    let elapsed_s = started.elapsed().as_secs_f64();
    assert!(
        rotation_sentences as f64 <= 2.0 + 10.0 * elapsed_s,
        "{rotation_sentences} rotation sentences in {elapsed_s:.2} s at 10 a second"
    );
    let rotation = rotation.expect("an XDR of the rotation");
    let translation = translation.expect("an XDR of the translation");
    for i in 0..3 {
        let deg: f64 = rotation[2 + 4 * i].parse().unwrap();
        let want = api["deformation"]["rotation_arcsec"][i].as_f64().unwrap() / 3600.0;
        assert!((deg - want).abs() <= 0.6e-7, "{deg} deg against {want}");
        let m: f64 = translation[2 + 4 * i].parse().unwrap();
        let want = api["deformation"]["translation_mm"][i].as_f64().unwrap() / 1000.0;
        assert!((m - want).abs() <= 0.6e-7, "{m} m against {want}");
    }
    // The four transitions, in order: active, normal, active, normal; none acknowledged.
    assert_eq!(alr.len(), 4, "{alr:?}");
    let states: Vec<(&str, &str, &str)> = alr
        .iter()
        .map(|f| (f[2].as_str(), f[3].as_str(), f[4].as_str()))
        .collect();
    assert_eq!(
        states,
        [
            ("001", "A", "V"),
            ("001", "V", "V"),
            ("001", "A", "V"),
            ("001", "V", "V")
        ]
    );
    assert_eq!(alr[2][5], "G DEFORMATION ALARM");
    // `hhmmss.ss` of the transition's time (UTC).
    let t = brokenray::clock::parse_json_time(&alarms[0]["time"]).unwrap();
    let cs = t.rem_euclid(86_400_000_000_000) / 10_000_000;
    assert_eq!(
        alr[0][1],
        format!(
            "{:02}{:02}{:02}.{:02}",
            cs / 360_000,
            cs / 6_000 % 60,
            cs / 100 % 60,
            cs % 100
        )
    );
}

#[tokio::test]
async fn a_modbus_port_in_use_is_refused_naming_its_key() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let dir = tempfile::tempdir().unwrap();
    let inst = super::helpers::installation(
        &dir,
        Some(&alarmed_installation(&format!(
            "[[outputs.modbus]]\nlisten = \"127.0.0.1:{port}\"\n"
        ))),
    );
    let (service, pipeline) = brokenray::service::Service::start(inst).await.unwrap();
    let e = brokenray::outputs::Outputs::start(
        &service,
        Arc::new([]),
        brokenray::api::output_encoders(&service),
    )
    .await
    .expect_err("the port is taken");
    let message = e.to_string();
    assert!(
        message.contains("outputs.modbus[0].listen") && message.contains(&port.to_string()),
        "{message}"
    );
    drop(service);
    pipeline.finished().await.unwrap();
}

/// Runs `openssl` with `args` in `dir`.
fn openssl(dir: &std::path::Path, args: &[&str]) {
    let out = std::process::Command::new("openssl")
        .args(args)
        .current_dir(dir)
        .output()
        .expect("openssl runs");
    assert!(
        out.status.success(),
        "openssl {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mqtts_with_credentials_reaches_a_broker_that_asks_for_them_and_a_wrong_password_is_said() {
    if skip_without(Needs::Mosquitto, "mqtts_with_credentials") {
        return;
    }
    // A certificate authority of this test, and the broker's certificate for 127.0.0.1.
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ec = [
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:prime256v1",
        "-nodes",
    ];
    openssl(
        d,
        &[
            &["req", "-x509"],
            &ec[..],
            &[
                "-keyout",
                "ca.key",
                "-out",
                "ca.crt",
                "-days",
                "2",
                "-subj",
                "/CN=test authority",
            ],
        ]
        .concat(),
    );
    openssl(
        d,
        &[
            &["req"],
            &ec[..],
            &[
                "-keyout",
                "server.key",
                "-out",
                "server.csr",
                "-subj",
                "/CN=127.0.0.1",
            ],
        ]
        .concat(),
    );
    std::fs::write(
        d.join("ext.cnf"),
        "subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n",
    )
    .unwrap();
    openssl(
        d,
        &[
            "x509",
            "-req",
            "-in",
            "server.csr",
            "-CA",
            "ca.crt",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-out",
            "server.crt",
            "-days",
            "2",
            "-extfile",
            "ext.cnf",
        ],
    );
    let made = std::process::Command::new("mosquitto_passwd")
        .args(["-b", "-c"])
        .arg(d.join("passwords"))
        .args(["ship", "s3cret"])
        .output()
        .expect("mosquitto_passwd runs");
    assert!(made.status.success());
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let conf = d.join("mosquitto.conf");
    std::fs::write(
        &conf,
        format!(
            "user root\nper_listener_settings false\nallow_anonymous false\npassword_file {pw}\n\
             listener {port} 127.0.0.1\ncafile {ca}\ncertfile {crt}\nkeyfile {key}\n",
            pw = d.join("passwords").display(),
            ca = d.join("ca.crt").display(),
            crt = d.join("server.crt").display(),
            key = d.join("server.key").display(),
        ),
    )
    .unwrap();
    let mut broker = std::process::Command::new(mosquitto_bin())
        .arg("-c")
        .arg(&conf)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("mosquitto starts");
    let ca = d.join("ca.crt").display().to_string();
    let app = TestApp::start(Some(&alarmed_installation(&format!(
        "[[outputs.mqtt]]\nurl = \"mqtts://127.0.0.1:{port}\"\nca_file = \"{ca}\"\nusername = \"ship\"\npassword = \"s3cret\"\n\n\
         [[outputs.mqtt]]\nurl = \"mqtts://127.0.0.1:{port}\"\nclient_id = \"wrong\"\nca_file = \"{ca}\"\nusername = \"ship\"\npassword = \"wrong\"\n"
    ))))
    .await;
    let mut outputs = Value::Null;
    for _ in 0..2000 {
        outputs = app.get("/api/v1/outputs").await.1;
        // Connected, the status published (it is queued a moment before it is sent), and the
        // wrong password refused.
        if outputs[0]["connected"] == true
            && outputs[0]["sent"].as_u64().unwrap_or(0) >= 1
            && !outputs[1]["last_error"].is_null()
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let _ = broker.kill();
    let _ = broker.wait();
    assert_eq!(outputs[0]["connected"], true, "{outputs}");
    assert!(
        outputs[0]["sent"].as_u64().unwrap() >= 1,
        "the online status: {outputs}"
    );
    assert_eq!(outputs[1]["connected"], false, "{outputs}");
    let error = outputs[1]["last_error"].as_str().unwrap();
    assert!(
        !error.contains("wrong"),
        "the password is never said: {error}"
    );
    assert!(
        error.to_lowercase().contains("refused") || error.to_lowercase().contains("not authorized"),
        "{error}"
    );
}
