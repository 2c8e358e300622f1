//! The one place that calls the Rerun SDK: turns [`Record`]s into entities on the measurement
//! timeline, owns the recording streams (a rotated file, a viewer to stream to, an in-process
//! server), and lays out the blueprint.
//!
//! Entities (frame and link names as in the installation):
//!
//! * `world/<base>/<frame>/...`: the frame tree, one `Transform3D` (parent from child) per tree
//!   link from the links' filtered poses; `.../camera` a pinhole of each camera, `.../points`
//!   each marker's points (mm);
//! * `world/<base>/<target>_filtered`, `_raw`, `_reference`: the target's fused, raw and
//!   reference poses in its base;
//! * `plots/<target>/rotation_arcsec/{raw,filtered,plus_3sigma,minus_3sigma}` and
//!   `plots/<target>/translation_mm/...`: the deformation `G0_from_G` (x, y, z);
//! * `plots/<target>/sigma_rotation_arcsec/{whole,random,systematic}` and
//!   `plots/<target>/sigma_translation_mm/...`: the filtered `G_from_B`'s sigma (x, y, z) and its
//!   two parts, the samples' noise and the calibrations';
//! * `plots/links/<link>/{nis,gate,outliers}`: each measured link's normalised innovation, its
//!   gate, and the rejected samples;
//! * `alarms/<target>`: the alarm level as a state lane; `alarms/log`: the transitions as text.

use super::{Record, TIMELINE, VizCounters, VizError};
use crate::chain::chi_square_quantile;
use crate::config::Installation;
use crate::geometry::Pose;
use crate::model::LinkKind;
use rerun::{RecordingStream, RecordingStreamBuilder};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

/// The application id of every recording; the viewer groups recordings by it.
pub(super) const APPLICATION_ID: &str = "brokenray";

/// Where each frame sits in the entity tree, and which link places it.
#[derive(Debug, Clone)]
struct FrameNode {
    path: String,
    /// The link between the frame and its tree parent, and whether the link maps the other way
    /// (its parent is this frame).
    link: Option<(usize, bool)>,
}

/// A file sink, renewed after a while or a size.
struct Rotation {
    dir: PathBuf,
    current: PathBuf,
    opened: Instant,
    after: Duration,
    max_bytes: u64,
    since_check: u32,
}

/// Writes records to Rerun.
pub(super) struct Logger {
    inst: Arc<Installation>,
    /// Every stream; each record goes to each.
    streams: Vec<RecordingStream>,
    /// Index in `streams` of the file stream, with its rotation.
    file: Option<(usize, Rotation)>,
    /// Index in `streams` of a stream to a remote viewer (whose flush may never return).
    remote: Option<usize>,
    frames: Vec<FrameNode>,
    /// Per target: the base frame's entity path.
    target_base: Vec<String>,
    /// Per link: the NIS gate (measured links).
    gates: Vec<Option<f64>>,
    counters: Arc<VizCounters>,
}

fn sdk_error(what: &'static str) -> impl Fn(rerun::RecordingStreamError) -> VizError {
    move |e| VizError::Sink {
        what,
        message: e.to_string(),
    }
}

/// A recording file name for a start time: `brokenray-20261121T120000Z.rrd`, made unique
/// within `dir`.
fn file_name(dir: &Path) -> PathBuf {
    let now = time::OffsetDateTime::now_utc();
    let stamp = format!(
        "{:04}{:02}{:02}T{:02}{:02}{:02}Z",
        now.year(),
        u8::from(now.month()),
        now.day(),
        now.hour(),
        now.minute(),
        now.second()
    );
    let mut path = dir.join(format!("brokenray-{stamp}.rrd"));
    let mut n = 1;
    while path.exists() {
        path = dir.join(format!("brokenray-{stamp}-{n}.rrd"));
        n += 1;
    }
    path
}

impl Logger {
    /// The streams of the live service, from `[rerun]`: `save`, `connect` and `serve` may be
    /// combined; all share one recording id, so a viewer merges them.
    pub(super) fn live(
        inst: &Arc<Installation>,
        counters: Arc<VizCounters>,
    ) -> Result<Self, VizError> {
        let s = &inst.rerun;
        let recording_id = format!("brokenray-{}", crate::clock::wall_now_ns());
        let builder = || {
            RecordingStreamBuilder::new(APPLICATION_ID)
                .recording_id(recording_id.clone())
                .recording_name("brokenray live")
        };
        let mut streams = Vec::new();
        let mut file = None;
        let mut remote = None;
        if s.save {
            std::fs::create_dir_all(&s.recordings_dir).map_err(|source| {
                VizError::RecordingsDir {
                    path: s.recordings_dir.clone(),
                    source,
                }
            })?;
            let path = file_name(&s.recordings_dir);
            let rec = builder().save(&path).map_err(sdk_error("save"))?;
            tracing::info!(file = %path.display(), "recording to file");
            counters.files.fetch_add(1, Relaxed);
            file = Some((
                streams.len(),
                Rotation {
                    dir: s.recordings_dir.clone(),
                    current: path,
                    opened: Instant::now(),
                    after: Duration::from_secs_f64(s.rotate_after_s),
                    max_bytes: s.rotate_max_bytes,
                    since_check: 0,
                },
            ));
            streams.push(rec);
        }
        if s.connect {
            let rec = builder()
                .connect_grpc_opts(s.url.clone())
                .map_err(sdk_error("connect"))?;
            tracing::info!(url = %s.url, "streaming to a Rerun viewer");
            remote = Some(streams.len());
            streams.push(rec);
        }
        if s.serve {
            let options = rerun::ServerOptions {
                memory_limit: rerun::MemoryLimit::from_bytes(s.serve_memory_limit_bytes),
                ..Default::default()
            };
            let rec = builder()
                .serve_grpc_opts(
                    s.serve_listen.ip().to_string(),
                    s.serve_listen.port(),
                    options,
                )
                .map_err(sdk_error("serve"))?;
            tracing::info!(
                url = %format!("rerun+http://{}/proxy", s.serve_listen),
                "serving Rerun to viewers"
            );
            streams.push(rec);
        }
        Ok(Self::with_streams(inst, streams, file, remote, counters))
    }

    /// One file, no rotation (for `replay`).
    pub(super) fn to_file(
        inst: &Arc<Installation>,
        path: &Path,
        name: &str,
        counters: Arc<VizCounters>,
    ) -> Result<Self, VizError> {
        let rec = RecordingStreamBuilder::new(APPLICATION_ID)
            .recording_name(name)
            .save(path)
            .map_err(sdk_error("save"))?;
        counters.files.fetch_add(1, Relaxed);
        Ok(Self::with_streams(inst, vec![rec], None, None, counters))
    }

    fn with_streams(
        inst: &Arc<Installation>,
        streams: Vec<RecordingStream>,
        file: Option<(usize, Rotation)>,
        remote: Option<usize>,
        counters: Arc<VizCounters>,
    ) -> Self {
        let frames = frame_tree(inst);
        let target_base = inst
            .model
            .targets
            .iter()
            .map(|t| frames[t.base.0].path.clone())
            .collect();
        let gates = inst
            .model
            .links
            .iter()
            .map(|l| match &l.kind {
                LinkKind::Measured(m) => Some(chi_square_quantile(6, m.tuning.gate_probability)),
                LinkKind::Calibrated { .. } => None,
            })
            .collect();
        let logger = Self {
            inst: Arc::clone(inst),
            streams,
            file,
            remote,
            frames,
            target_base,
            gates,
            counters,
        };
        for rec in &logger.streams {
            rec.set_log_time_enabled(false);
            logger.setup(rec);
        }
        logger
    }

    fn count(&self, r: rerun::RecordingStreamResult<()>) {
        if let Err(e) = r
            && self.counters.errors.fetch_add(1, Relaxed) < 10
        {
            tracing::warn!(error = %e, "Rerun refused a record");
        }
    }

    /// The static part: blueprint, styles, cameras, markers, the calibrated links.
    fn setup(&self, rec: &RecordingStream) {
        let inst = &self.inst;
        let bp = super::blueprint::blueprint(inst);
        self.count(rec.send_blueprint_opts(&rerun::blueprint::BlueprintOpts {
            blueprint: bp,
            activation: rerun::blueprint::BlueprintActivation::default(),
        }));
        for node in &self.frames {
            self.count(rec.log_static(
                node.path.as_str(),
                &rerun::TransformAxes3D::new(150.0).with_show_frame(true),
            ));
        }
        for c in &inst.model.cameras {
            let Some(f) = inst.model.topology.frame_id(&c.frame) else {
                continue;
            };
            let pinhole = rerun::Pinhole::from_focal_length_and_resolution(
                [c.intrinsics.fx_px as f32, c.intrinsics.fy_px as f32],
                [c.intrinsics.width_px as f32, c.intrinsics.height_px as f32],
            )
            .with_principal_point([c.intrinsics.cx_px as f32, c.intrinsics.cy_px as f32])
            .with_image_plane_distance(300.0);
            self.count(rec.log_static(format!("{}/camera", self.frames[f.0].path), &pinhole));
        }
        for m in &inst.model.markers {
            let Some(f) = inst.model.topology.frame_id(&m.frame) else {
                continue;
            };
            let points = rerun::Points3D::new(
                m.points_mm
                    .iter()
                    .map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]),
            )
            .with_radii([8.0])
            .with_colors([rerun::Color::from_rgb(255, 200, 40)]);
            self.count(rec.log_static(format!("{}/points", self.frames[f.0].path), &points));
        }
        // Calibrated links place their frames until a recalibration is seen.
        for (i, node) in self.frames.iter().enumerate() {
            let Some((link, inverted)) = node.link else {
                continue;
            };
            if let LinkKind::Calibrated { parent_from_child } = &inst.model.links[link].kind {
                let tf = tree_transform(&parent_from_child.pose, inverted);
                self.count(rec.log_static(self.frames[i].path.as_str(), &tf));
            }
        }
        let rgb = |r, g, b| rerun::Color::from_rgb(r, g, b);
        let axes = ["x", "y", "z"];
        let raw_colors = [rgb(255, 150, 150), rgb(150, 220, 150), rgb(150, 170, 255)];
        let colors = [rgb(220, 40, 40), rgb(30, 160, 30), rgb(40, 80, 230)];
        let band_colors = [rgb(240, 180, 180), rgb(180, 230, 180), rgb(180, 190, 250)];
        for t in &inst.model.targets {
            for (quantity, unit) in [("rotation_arcsec", "arcsec"), ("translation_mm", "mm")] {
                let base = format!("plots/{}/{quantity}", t.name);
                let names = |what: &str| axes.map(|a| format!("{a} {what} [{unit}]"));
                self.count(
                    rec.log_static(
                        format!("{base}/raw"),
                        &rerun::SeriesPoints::new()
                            .with_names(names("raw"))
                            .with_colors(raw_colors)
                            .with_marker_sizes([1.5, 1.5, 1.5]),
                    ),
                );
                self.count(
                    rec.log_static(
                        format!("{base}/filtered"),
                        &rerun::SeriesLines::new()
                            .with_names(names("filtered"))
                            .with_colors(colors)
                            .with_widths([2.0, 2.0, 2.0]),
                    ),
                );
                for band in ["plus_3sigma", "minus_3sigma"] {
                    self.count(
                        rec.log_static(
                            format!("{base}/{band}"),
                            &rerun::SeriesLines::new()
                                .with_names(names(&band.replace('_', " ")))
                                .with_colors(band_colors)
                                .with_widths([0.75, 0.75, 0.75]),
                        ),
                    );
                }
            }
            self.count(
                rec.log_static(
                    format!("alarms/{}", t.name),
                    &rerun::StateConfiguration::new()
                        .with_values(["none", "warn", "alarm"])
                        .with_labels(["ok", "warning", "ALARM"])
                        .with_colors([0x4CAF50FFu32, 0xFFA000FFu32, 0xD32F2FFFu32]),
                ),
            );
            self.count(rec.log_static(
                format!("alarms/{}", t.name),
                &rerun::StateChange::single("none"),
            ));
        }
        for (l, gate) in self.gates.iter().enumerate() {
            if gate.is_none() {
                continue;
            }
            let name = &inst.model.links[l].name;
            let base = format!("plots/links/{name}");
            self.count(
                rec.log_static(
                    format!("{base}/nis"),
                    &rerun::SeriesLines::new()
                        .with_names([format!("{name} NIS")])
                        .with_widths([1.0]),
                ),
            );
            self.count(
                rec.log_static(
                    format!("{base}/gate"),
                    &rerun::SeriesLines::new()
                        .with_names([format!("{name} gate")])
                        .with_colors([rgb(150, 150, 150)])
                        .with_widths([0.75]),
                ),
            );
            self.count(
                rec.log_static(
                    format!("{base}/outliers"),
                    &rerun::SeriesPoints::new()
                        .with_names([format!("{name} outlier")])
                        .with_colors([rgb(230, 30, 30)])
                        .with_markers([rerun::components::MarkerShape::Cross])
                        .with_marker_sizes([4.0]),
                ),
            );
        }
    }

    /// Writes one record to every stream (and rotates the file when due).
    pub(super) fn log(&mut self, record: &Record) {
        self.log_batch(std::slice::from_ref(record));
    }

    /// Writes records to every stream (and rotates the file when due). The frequent kinds
    /// (samples, results, scenes) go as columns, one chunk per entity and batch, which costs a
    /// fraction of a row-by-row `log` per value; the rare ones row by row.
    pub(super) fn log_batch(&mut self, records: &[Record]) {
        if records.is_empty() {
            return;
        }
        self.rotate_if_due(records.len());
        let columns = self.columns(records);
        for i in 0..self.streams.len() {
            let rec = self.streams[i].clone();
            for (entity, c) in &columns.scalars {
                let times = rerun::TimeColumn::new_timestamp_nanos_since_epoch(
                    TIMELINE,
                    c.times.iter().copied(),
                );
                let width = c.values.len() / c.times.len().max(1);
                match rerun::Scalars::new(c.values.iter().copied())
                    .columns(std::iter::repeat_n(width, c.times.len()))
                {
                    Ok(cols) => self.count(rec.send_columns(entity.as_str(), [times], cols)),
                    Err(e) => self.count(Err(e.into())),
                }
            }
            for (entity, c) in &columns.transforms {
                let times = rerun::TimeColumn::new_timestamp_nanos_since_epoch(
                    TIMELINE,
                    c.times.iter().copied(),
                );
                let n = c.times.len();
                match rerun::Transform3D::update_fields()
                    .with_many_translation(c.translations.iter().copied())
                    .with_many_quaternion(
                        c.quaternions_xyzw
                            .iter()
                            .map(|q| rerun::Quaternion::from_xyzw(*q)),
                    )
                    .with_many_relation(std::iter::repeat_n(
                        rerun::TransformRelation::ParentFromChild,
                        n,
                    ))
                    .columns_of_unit_batches()
                {
                    Ok(cols) => self.count(rec.send_columns(entity.as_str(), [times], cols)),
                    Err(e) => self.count(Err(e.into())),
                }
            }
            for record in records {
                if matches!(
                    record,
                    Record::Reference { .. } | Record::Alarm { .. } | Record::Frame { .. }
                ) {
                    rec.set_time(
                        TIMELINE,
                        rerun::TimeCell::from_timestamp_nanos_since_epoch(record.time_ns()),
                    );
                    self.log_to(&rec, record);
                }
            }
        }
        self.counters
            .logged
            .fetch_add(records.len() as u64, Relaxed);
    }

    /// The batch's samples, results and scenes as columns per entity.
    fn columns(&self, records: &[Record]) -> Columns {
        let inst = &self.inst;
        let mut out = Columns::default();
        for record in records {
            let t = record.time_ns();
            match record {
                Record::Sample {
                    link, nis, outlier, ..
                } => {
                    let name = &inst.model.links[*link].name;
                    if let Some(nis) = nis {
                        let entity = if *outlier { "outliers" } else { "nis" };
                        out.scalar(format!("plots/links/{name}/{entity}"), t, &[*nis]);
                    }
                    // The gate is a constant line: its first and last point of the batch
                    // draw it.
                    if let Some(gate) = self.gates[*link] {
                        out.gate_span(format!("plots/links/{name}/gate"), t, gate);
                    }
                }
                Record::Result {
                    target,
                    source,
                    target_from_base,
                    deformation,
                    ..
                } => {
                    let name = &inst.model.targets[target.0].name;
                    let which = source.name();
                    if *source == crate::bank::ResultSource::Filtered {
                        let s = target_from_base.sigmas();
                        for (label, s) in [
                            ("whole", s.whole),
                            ("random", s.random),
                            ("systematic", s.systematic),
                        ] {
                            out.scalar(
                                format!("plots/{name}/sigma_rotation_arcsec/{label}"),
                                t,
                                &s.rotation_arcsec,
                            );
                            out.scalar(
                                format!("plots/{name}/sigma_translation_mm/{label}"),
                                t,
                                &s.translation_mm,
                            );
                        }
                    }
                    out.transform(
                        format!("{}/{name}_{which}", self.target_base[target.0]),
                        t,
                        target_from_base.pose(),
                        true,
                    );
                    if let Some(d) = deformation {
                        let quantities = [
                            (
                                "rotation_arcsec",
                                d.rotation_arcsec,
                                d.sigmas.rotation_arcsec,
                            ),
                            ("translation_mm", d.translation_mm, d.sigmas.translation_mm),
                        ];
                        for (quantity, value, sigma) in quantities {
                            let base = format!("plots/{name}/{quantity}");
                            out.scalar(format!("{base}/{which}"), t, &value);
                            if *source == crate::bank::ResultSource::Filtered {
                                let plus: [f64; 3] =
                                    std::array::from_fn(|i| value[i] + 3.0 * sigma[i]);
                                let minus: [f64; 3] =
                                    std::array::from_fn(|i| value[i] - 3.0 * sigma[i]);
                                out.scalar(format!("{base}/plus_3sigma"), t, &plus);
                                out.scalar(format!("{base}/minus_3sigma"), t, &minus);
                            }
                        }
                    }
                }
                Record::Scene { link_poses, .. } => {
                    for node in &self.frames {
                        if let Some((link, inverted)) = node.link
                            && let Some(Some(pose)) = link_poses.get(link)
                        {
                            out.transform(node.path.clone(), t, pose, inverted);
                        }
                    }
                }
                Record::Reference { .. } | Record::Alarm { .. } | Record::Frame { .. } => {}
            }
        }
        out
    }

    /// The rare kinds, row by row (the time is set by the caller).
    fn log_to(&self, rec: &RecordingStream, record: &Record) {
        let inst = &self.inst;
        match record {
            Record::Sample { .. } | Record::Result { .. } | Record::Scene { .. } => {}
            Record::Reference {
                target, g0_from_b, ..
            } => {
                let name = &inst.model.targets[target.0].name;
                let frame = format!("{}/{name}_reference", self.target_base[target.0]);
                self.count(rec.log(frame.as_str(), &tree_transform(g0_from_b, true)));
            }
            Record::Frame {
                camera,
                image,
                marks,
                ..
            } => self.log_frame(rec, *camera, image, marks),
            Record::Alarm { target, transition } => {
                let name = &inst.model.targets[target.0].name;
                self.count(rec.log(
                    format!("alarms/{name}"),
                    &rerun::StateChange::single(transition.to.name()),
                ));
                let level = match transition.to {
                    crate::alarms::Level::Alarm => rerun::TextLogLevel::ERROR,
                    crate::alarms::Level::Warn => rerun::TextLogLevel::WARN,
                    crate::alarms::Level::None => rerun::TextLogLevel::INFO,
                };
                self.count(
                    rec.log(
                        "alarms/log",
                        &rerun::TextLog::new(format!(
                            "{name}: {} {} -> {}: {}",
                            transition.kind.name(),
                            transition.from.name(),
                            transition.to.name(),
                            transition.message
                        ))
                        .with_level(level),
                    ),
                );
            }
        }
    }

    /// A camera frame under the camera's pinhole (so that the 3-D view shows it in the
    /// frustum), the detected points labelled by id and the reprojected ones over it (at pixel
    /// centres: the image's pixel `(u, v)` covers `[u, u + 1) x [v, v + 1)` in Rerun's image
    /// coordinates), and a log line per marker not found.
    fn log_frame(
        &self,
        rec: &RecordingStream,
        camera: usize,
        image: &crate::vision::GreyImage,
        marks: &[super::FrameMarks],
    ) {
        let inst = &self.inst;
        let Some(c) = inst.model.cameras.get(camera) else {
            return;
        };
        let Some(f) = inst.model.topology.frame_id(&c.frame) else {
            return;
        };
        let base = format!("{}/camera", self.frames[f.0].path);
        // Lossless PNG (fast deflate): about half the raw size in the recording.
        let picture = match crate::imagefile::encode_png_fast(image) {
            Ok(png) => {
                rerun::EncodedImage::from_file_contents(png).with_media_type(rerun::MediaType::PNG)
            }
            Err(e) => {
                tracing::warn!(camera = %c.frame, error = %e, "a frame could not be encoded for Rerun");
                return;
            }
        };
        self.count(rec.log(format!("{base}/image"), &picture));
        let centre = |p: &[f64; 2]| [(p[0] + 0.5) as f32, (p[1] + 0.5) as f32];
        let found = marks.iter().filter(|m| m.not_found.is_none());
        let detected: Vec<[f32; 2]> = found
            .clone()
            .flat_map(|m| m.points_px.iter().map(centre))
            .collect();
        let labels: Vec<String> = found
            .clone()
            .flat_map(|m| m.ids.iter().map(|id| format!("{}{id}", m.marker)))
            .collect();
        let reprojected: Vec<[f32; 2]> = found
            .flat_map(|m| m.reprojected_px.iter().map(centre))
            .collect();
        self.count(
            rec.log(
                format!("{base}/image/detected"),
                &rerun::Points2D::new(detected)
                    .with_labels(labels)
                    .with_radii([rerun::Radius::new_ui_points(5.0)])
                    .with_colors([rerun::Color::from_rgb(255, 191, 71)]),
            ),
        );
        self.count(
            rec.log(
                format!("{base}/image/reprojected"),
                &rerun::Points2D::new(reprojected)
                    .with_radii([rerun::Radius::new_ui_points(2.0)])
                    .with_colors([rerun::Color::from_rgb(86, 180, 233)]),
            ),
        );
        for m in marks {
            if let Some(reason) = &m.not_found {
                self.count(
                    rec.log(
                        format!("cameras/{}", c.frame),
                        &rerun::TextLog::new(if m.marker.is_empty() {
                            reason.clone()
                        } else {
                            format!("{} not found: {reason}", m.marker)
                        })
                        .with_level(rerun::TextLogLevel::WARN),
                    ),
                );
            }
        }
    }

    /// Starts a new file when the current one is old or large enough; the static part is
    /// written again so that each file opens ready to read.
    fn rotate_if_due(&mut self, records: usize) {
        let Some((index, rotation)) = &mut self.file else {
            return;
        };
        rotation.since_check = rotation
            .since_check
            .saturating_add(u32::try_from(records).unwrap_or(u32::MAX));
        if rotation.since_check < 256 {
            return;
        }
        rotation.since_check = 0;
        let size = std::fs::metadata(&rotation.current).map_or(0, |m| m.len());
        if rotation.opened.elapsed() < rotation.after && size < rotation.max_bytes {
            return;
        }
        let next = file_name(&rotation.dir);
        let rec = self.streams[*index].clone();
        match rec.save(&next) {
            Ok(()) => {
                tracing::info!(closed = %rotation.current.display(), file = %next.display(), "recording rotated");
                rotation.current = next;
                rotation.opened = Instant::now();
                self.counters.files.fetch_add(1, Relaxed);
                rec.set_log_time_enabled(false);
                self.setup(&rec);
            }
            Err(e) => {
                tracing::warn!(error = %e, "cannot rotate the recording; continuing in the current file");
                rotation.opened = Instant::now();
            }
        }
    }

    /// Writes out what is buffered and closes the streams. A remote viewer gets a bounded
    /// time; files are always completed (their footer written).
    pub(super) fn close(self) {
        for (i, rec) in self.streams.into_iter().enumerate() {
            if Some(i) == self.remote {
                if rec.flush_with_timeout(Duration::from_secs(2)).is_err() {
                    tracing::warn!("the Rerun viewer did not take the last records");
                }
                // Dropping the stream would flush again without a bound.
                std::mem::forget(rec);
            } else if let Err(e) = rec.flush_with_timeout(Duration::from_secs(30)) {
                tracing::warn!(error = %e, "flushing a Rerun stream failed");
            }
        }
    }
}

/// Per entity, the rows of a batch.
#[derive(Default)]
struct Columns {
    scalars: std::collections::BTreeMap<String, ScalarColumn>,
    transforms: std::collections::BTreeMap<String, TransformColumn>,
}

#[derive(Default)]
struct ScalarColumn {
    times: Vec<i64>,
    /// Row after row, each as wide as the entity's series.
    values: Vec<f64>,
}

#[derive(Default)]
struct TransformColumn {
    times: Vec<i64>,
    translations: Vec<[f32; 3]>,
    quaternions_xyzw: Vec<[f32; 4]>,
}

impl Columns {
    fn scalar(&mut self, entity: String, time_ns: i64, values: &[f64]) {
        let c = self.scalars.entry(entity).or_default();
        c.times.push(time_ns);
        c.values.extend_from_slice(values);
    }

    /// Extends a constant series to `time_ns`: it keeps only the batch's first and last point.
    fn gate_span(&mut self, entity: String, time_ns: i64, value: f64) {
        let c = self.scalars.entry(entity).or_default();
        if c.times.len() == 2 {
            c.times[1] = c.times[1].max(time_ns);
            c.times[0] = c.times[0].min(time_ns);
        } else {
            c.times.push(time_ns);
            c.values.push(value);
            if c.times.len() == 2 && c.times[0] > c.times[1] {
                c.times.swap(0, 1);
            }
        }
    }

    fn transform(&mut self, entity: String, time_ns: i64, link_pose: &Pose, inverted: bool) {
        let (translation, quaternion_xyzw) = frame_parts(link_pose, inverted);
        let c = self.transforms.entry(entity).or_default();
        c.times.push(time_ns);
        c.translations.push(translation);
        c.quaternions_xyzw.push(quaternion_xyzw);
    }
}

/// The transform of a frame's entity, given the link between it and its tree parent: the
/// link's `parent_from_child` when the link maps the frame into its tree parent, its inverse
/// when it maps the other way.
fn tree_transform(link_pose: &Pose, inverted: bool) -> rerun::Transform3D {
    let (translation, quaternion_xyzw) = frame_parts(link_pose, inverted);
    rerun::Transform3D::from_translation(translation)
        .with_quaternion(rerun::Quaternion::from_xyzw(quaternion_xyzw))
        .with_relation(rerun::TransformRelation::ParentFromChild)
}

/// The translation and the `[x, y, z, w]` quaternion (f32, as Rerun stores them) of a frame
/// placed by a link, inverted when the link maps the other way.
fn frame_parts(link_pose: &Pose, inverted: bool) -> ([f32; 3], [f32; 4]) {
    let p = if inverted {
        link_pose.inverse()
    } else {
        *link_pose
    };
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    (
        [t.x as f32, t.y as f32, t.z as f32],
        [q.i as f32, q.j as f32, q.k as f32, q.w as f32],
    )
}

/// Each frame's entity path, by frame index.
pub(super) fn frame_paths(inst: &Installation) -> Vec<String> {
    frame_tree(inst).into_iter().map(|n| n.path).collect()
}

/// The entity tree of the frames: breadth first from each target's base (then from any frame
/// not reached), each frame under the first frame it is linked to.
fn frame_tree(inst: &Installation) -> Vec<FrameNode> {
    let topo = &inst.model.topology;
    let n = topo.frames().len();
    let mut nodes: Vec<Option<FrameNode>> = vec![None; n];
    let roots: Vec<usize> = inst
        .model
        .targets
        .iter()
        .map(|t| t.base.0)
        .chain(0..n)
        .collect();
    for root in roots {
        if nodes[root].is_some() {
            continue;
        }
        nodes[root] = Some(FrameNode {
            path: format!("world/{}", topo.frames()[root]),
            link: None,
        });
        let mut queue = std::collections::VecDeque::from([root]);
        while let Some(f) = queue.pop_front() {
            let parent_path = nodes[f]
                .as_ref()
                .map(|n| n.path.clone())
                .unwrap_or_default();
            for (l, ends) in topo.links().iter().enumerate() {
                // The link places its other end under `f`.
                let (other, inverted) = if ends.parent.0 == f {
                    (ends.child.0, false)
                } else if ends.child.0 == f {
                    (ends.parent.0, true)
                } else {
                    continue;
                };
                if nodes[other].is_some() {
                    continue;
                }
                nodes[other] = Some(FrameNode {
                    path: format!("{parent_path}/{}", topo.frames()[other]),
                    link: Some((l, inverted)),
                });
                queue.push_back(other);
            }
        }
    }
    nodes
        .into_iter()
        .enumerate()
        .map(|(i, n)| {
            // Every frame is a root or reached from one; this only keeps the types total.
            n.unwrap_or_else(|| FrameNode {
                path: format!("world/{}", topo.frames()[i]),
                link: None,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_chain_is_one_branch_from_the_base() {
        let inst = crate::config::default_installation();
        let tree = frame_tree(&inst);
        let path = |name: &str| {
            tree[inst.model.topology.frame_id(name).unwrap().0]
                .path
                .clone()
        };
        assert_eq!(path("B"), "world/B");
        assert_eq!(path("G"), "world/B/C1/C2/M/C3/G");
    }
}
