//! The scenario simulator: ground-truth motion of an installation's bodies, and what its
//! cameras would see.
//!
//! The installation's nominal link poses (`nominal` of measured links, `pose` of calibrated
//! ones) place every frame in the world of the first target's base. Frames joined by calibrated
//! links form one rigid body (a station); markers and cameras on their own are bodies too. The
//! base body stays still (it is the reference); every other body moves by a scenario, as a
//! perturbation about its own origin, `world_from_body(t) = world_from_body0 * Exp(xi(t))`:
//!
//! * `static`: nothing moves;
//! * `drift`: slow linear drift (target 0.5 arc-second/s and 2 um/s, stations half of it);
//! * `ship`: hull flexure, per axis two second-order Gauss-Markov processes
//!   `x'' + 2 mu x' + (mu^2 + lambda^2) x = w` with periods 8 s and 15 s (target 1 and 1.5
//!   arc-minutes, 0.2 and 0.3 mm; stations half), on a slow static flexure of 0.2 arc-second/s;
//! * `tunnel`: a creep ramp of the target (1 arc-second/s and 20 um/s), stations 0.3 of it;
//! * `bump`: static, until half-way through a relay station is knocked by 0.05 degrees and 1 mm
//!   (the true `G_from_B` does not change: the chain must see through it).
//!
//! Each group, every camera-marker link is observed: the marker points projected by the
//! camera model with Gaussian pixel noise, and optionally an outlier (every point of the
//! observation shifted by 2 to 5 px, as a glint or a vibration blur would). Links no camera
//! model covers are emitted as pose samples with their configured sigmas.
//!
//! Pure and deterministic for a seed: no clock, no IO.

mod motion;
pub mod plate;
pub mod render;

pub use motion::GaussMarkov2;

use crate::chain::FrameId;
use crate::geometry::{ARCSEC_PER_RAD, Pose, ReportedSigmas, Twist, se3_exp};
use crate::model::{LinkKind, Model, ObservedLink, Observer};
use nalgebra::Point3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use std::str::FromStr;

/// What moves, and how.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scenario {
    /// Nothing moves.
    Static,
    /// Slow linear drift.
    Drift,
    /// Ship hull flexure: wave-driven oscillation on a slow static flexure.
    Ship,
    /// Tunnel creep: a ramp.
    Tunnel,
    /// A relay station knocked half-way through.
    Bump,
}

impl FromStr for Scenario {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "static" => Ok(Self::Static),
            "drift" => Ok(Self::Drift),
            "ship" => Ok(Self::Ship),
            "tunnel" => Ok(Self::Tunnel),
            "bump" => Ok(Self::Bump),
            other => Err(format!(
                "unknown scenario `{other}`: static, drift, ship, tunnel or bump"
            )),
        }
    }
}

/// How a run is generated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimSettings {
    /// The scenario.
    pub scenario: Scenario,
    /// Groups per second.
    pub rate_hz: f64,
    /// Time of the first group (ns since the Unix epoch).
    pub start_ns: i64,
    /// Length of the run (s), which `bump` needs to place its knock; `None` runs forever.
    pub duration_s: Option<f64>,
    /// Pixel noise (px); each camera's `pixel_sigma` without it.
    pub pixel_sigma_px: Option<f64>,
    /// Probability that an observation is an outlier.
    pub outlier_rate: f64,
    /// Seed of the noise and the motion.
    pub seed: u64,
}

/// Why a simulation cannot run on an model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    /// A link without a pose to place its frames.
    #[error(
        "link `{0}` has no nominal pose: the simulator places frames by `nominal` (measured links) and `pose` (calibrated links)"
    )]
    NoNominal(String),
    /// Nothing to measure.
    #[error("the installation has no target")]
    NoTarget,
    /// Bad settings.
    #[error("{0}")]
    Settings(String),
}

/// One camera image of one marker.
#[derive(Debug, Clone, PartialEq)]
pub struct SimObservation {
    /// The camera's frame.
    pub camera: String,
    /// The marker's frame.
    pub marker: String,
    /// The pixel of every marker point, in the marker's order.
    pub points_px: Vec<[f64; 2]>,
    /// Whether it was made an outlier.
    pub outlier: bool,
}

/// A link pose sample (for links no camera model covers).
#[derive(Debug, Clone, PartialEq)]
pub struct SimSample {
    /// The link's name.
    pub link: String,
    /// The noisy `parent_from_child`.
    pub pose: Pose,
    /// The noise it was drawn with.
    pub sigma: ReportedSigmas,
}

/// Everything of one trigger time.
#[derive(Debug, Clone, PartialEq)]
pub struct SimGroup {
    /// Time (ns since the Unix epoch).
    pub time_ns: i64,
    /// The observations.
    pub observations: Vec<SimObservation>,
    /// Pose samples of links without a camera model.
    pub samples: Vec<SimSample>,
    /// True `target_from_base` per target, in the installation's target order.
    pub truth: Vec<(String, Pose)>,
    /// True `parent_from_child` of every measured link.
    pub link_truth: Vec<(String, Pose)>,
}

/// A moving body: frames rigidly joined, their nominal world poses, and its motion.
#[derive(Debug, Clone)]
struct Body {
    frames: Vec<FrameId>,
    /// Nominal pose of the body's own frame (its first frame).
    world_from_body0: Pose,
    role: Role,
    oscillators: Vec<GaussMarkov2>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    Base,
    Target,
    Station,
}

/// A measured link as the simulator sees it: its frames, its default noise, and how a camera
/// observes it (resolved once, at construction).
#[derive(Debug, Clone)]
struct SimLink {
    name: String,
    parent: FrameId,
    child: FrameId,
    sigma: ReportedSigmas,
    /// The camera-marker pair, when the installation has both models; a pose sample otherwise.
    observed: Option<ObservedLink>,
}

/// Generates groups of an installation, one after another.
pub struct Simulator {
    settings: SimSettings,
    observer: Observer,
    world_from_frame0: Vec<Pose>,
    frame_body: Vec<usize>,
    bodies: Vec<Body>,
    measured: Vec<SimLink>,
    targets: Vec<(String, FrameId, FrameId)>,
    bumped: Option<usize>,
    rng: StdRng,
    index: u64,
    last_t_s: f64,
    /// Keep the targets' bodies still (only the relay stations move).
    still_target: bool,
    /// How far apart (ns) the cameras' exposures are spread within a group.
    exposure_spread_ns: i64,
    /// Each body's motion at the previous group, to extrapolate to an exposure's own time.
    last_xi: Vec<Twist>,
    /// Per body, the move an operator made (a world-frame motion applied after the
    /// scenario's), as [`Self::displace_target`] sets it.
    displaced: Vec<Option<Pose>>,
}

impl Simulator {
    /// Places the installation's frames and prepares the scenario.
    pub fn new(model: &Model, settings: SimSettings) -> Result<Self, SimError> {
        if !(settings.rate_hz.is_finite() && settings.rate_hz > 0.0) {
            return Err(SimError::Settings(format!(
                "the rate must be a positive number of groups per second, not {}",
                settings.rate_hz
            )));
        }
        if !(settings.outlier_rate >= 0.0 && settings.outlier_rate <= 1.0) {
            return Err(SimError::Settings(format!(
                "the outlier rate is a probability in [0, 1], not {}",
                settings.outlier_rate
            )));
        }
        let topo = &model.topology;
        let first = model.targets.first().ok_or(SimError::NoTarget)?;
        let n_frames = topo.frames().len();
        // Place frames by walking the links from the base.
        let mut world: Vec<Option<Pose>> = vec![None; n_frames];
        world[first.base.0] = Some(Pose::identity());
        let link_pose = |spec: &crate::model::LinkSpec| -> Option<Pose> {
            match &spec.kind {
                LinkKind::Calibrated { parent_from_child } => Some(parent_from_child.pose),
                LinkKind::Measured(m) => m.nominal,
            }
        };
        loop {
            let mut progressed = false;
            for spec in &model.links {
                let ends = topo.link(spec.id);
                let (p, c) = (ends.parent.0, ends.child.0);
                if world[p].is_some() == world[c].is_some() {
                    continue;
                }
                let pose = link_pose(spec).ok_or_else(|| SimError::NoNominal(spec.name.clone()))?;
                if let Some(wp) = world[p] {
                    world[c] = Some(wp * pose);
                } else if let Some(wc) = world[c] {
                    world[p] = Some(wc * pose.inverse());
                }
                progressed = true;
            }
            if !progressed {
                break;
            }
        }
        let world_from_frame0: Vec<Pose> = world
            .into_iter()
            .map(|w| w.unwrap_or_else(Pose::identity))
            .collect();
        // Bodies: union of frames joined by calibrated links.
        let mut parent: Vec<usize> = (0..n_frames).collect();
        fn find(parent: &mut [usize], mut i: usize) -> usize {
            while parent[i] != i {
                parent[i] = parent[parent[i]];
                i = parent[i];
            }
            i
        }
        for spec in &model.links {
            if matches!(spec.kind, LinkKind::Calibrated { .. }) {
                let ends = topo.link(spec.id);
                let (a, b) = (
                    find(&mut parent, ends.parent.0),
                    find(&mut parent, ends.child.0),
                );
                parent[a] = b;
            }
        }
        let mut rng = StdRng::seed_from_u64(settings.seed);
        let mut bodies: Vec<Body> = Vec::new();
        let mut frame_body = vec![0; n_frames];
        let mut root_body: Vec<Option<usize>> = vec![None; n_frames];
        for f in 0..n_frames {
            let root = find(&mut parent, f);
            let b = match root_body[root] {
                Some(b) => b,
                None => {
                    bodies.push(Body {
                        frames: Vec::new(),
                        world_from_body0: world_from_frame0[f],
                        role: Role::Station,
                        oscillators: Vec::new(),
                    });
                    root_body[root] = Some(bodies.len() - 1);
                    bodies.len() - 1
                }
            };
            bodies[b].frames.push(FrameId(f));
            frame_body[f] = b;
        }
        let bases: Vec<usize> = model.targets.iter().map(|t| frame_body[t.base.0]).collect();
        for t in &model.targets {
            bodies[frame_body[t.frame.0]].role = Role::Target;
        }
        for b in bases {
            bodies[b].role = Role::Base;
        }
        for body in &mut bodies {
            let scale = match body.role {
                Role::Base => 0.0,
                Role::Target => 1.0,
                Role::Station => 0.5,
            };
            if settings.scenario == Scenario::Ship && scale > 0.0 {
                // Per component [tx ty tz rx ry rz]: an 8 s and a 15 s process.
                for k in 0..6 {
                    let (a8, a15) = if k < 3 {
                        (0.2 * scale, 0.3 * scale)
                    } else {
                        (60.0 * scale / ARCSEC_PER_RAD, 90.0 * scale / ARCSEC_PER_RAD)
                    };
                    body.oscillators
                        .push(GaussMarkov2::new(8.0, 0.1, a8, &mut rng));
                    body.oscillators
                        .push(GaussMarkov2::new(15.0, 0.1, a15, &mut rng));
                }
            }
        }
        let bumped = (settings.scenario == Scenario::Bump)
            .then(|| bodies.iter().position(|b| b.role == Role::Station))
            .flatten();
        let n_bodies = bodies.len();
        let observer = Observer::new(model);
        let measured = model
            .links
            .iter()
            .filter_map(|spec| match &spec.kind {
                LinkKind::Measured(m) => {
                    let ends = topo.link(spec.id);
                    Some(SimLink {
                        name: spec.name.clone(),
                        parent: ends.parent,
                        child: ends.child,
                        sigma: m.default_sigmas,
                        observed: observer.links().find(|l| l.link == spec.id).cloned(),
                    })
                }
                LinkKind::Calibrated { .. } => None,
            })
            .collect();
        let targets = model
            .targets
            .iter()
            .map(|t| (t.name.clone(), t.frame, t.base))
            .collect();
        Ok(Self {
            settings,
            observer,
            world_from_frame0,
            frame_body,
            bodies,
            measured,
            targets,
            bumped,
            rng,
            index: 0,
            last_t_s: 0.0,
            still_target: false,
            exposure_spread_ns: 0,
            last_xi: Vec::new(),
            displaced: vec![None; n_bodies],
        })
    }

    /// The cameras of the camera-marker links, each once, in installation order, with their
    /// models.
    fn cameras(&self) -> Vec<(&str, &crate::vision::CameraModel)> {
        let mut cameras: Vec<(&str, &crate::vision::CameraModel)> = Vec::new();
        for link in self.observer.links() {
            if !cameras.iter().any(|(c, _)| *c == link.camera_frame) {
                cameras.push((&link.camera_frame, &link.camera));
            }
        }
        cameras
    }

    /// Keeps every target's body still relative to its base while the relay stations move as
    /// the scenario says: the true `target_from_base` is then constant, and any motion of the
    /// stations must cancel in it.
    pub fn set_still_target(&mut self, still: bool) {
        self.still_target = still;
    }

    /// The installation's targets, in order.
    pub fn target_names(&self) -> Vec<String> {
        self.targets.iter().map(|(name, ..)| name.clone()).collect()
    }

    /// Plays an operator who moves target `target` (with the body it is rigid with) to stand
    /// displaced by `displacement` from its nominal pose, as the acceptance procedure asks:
    /// the true deformation `G0_from_G` becomes that displacement (the scenario's motion, if
    /// any, comes on top). [`crate::acceptance::Displacement::ZERO`] puts it back.
    pub fn displace_target(
        &mut self,
        target: &str,
        displacement: &crate::acceptance::Displacement,
    ) -> Result<(), SimError> {
        let Some(&(_, g, _)) = self.targets.iter().find(|(name, ..)| name == target) else {
            return Err(SimError::Settings(format!("no target `{target}`")));
        };
        let b = self.frame_body[g.0];
        if self.bodies[b].role != Role::Target {
            return Err(SimError::Settings(format!(
                "target `{target}` is rigid with a base: it cannot be moved"
            )));
        }
        let world_from_g0 = self.world_from_frame0[g.0];
        self.displaced[b] = (*displacement != crate::acceptance::Displacement::ZERO)
            .then(|| world_from_g0 * displacement.g0_from_g() * world_from_g0.inverse());
        Ok(())
    }

    /// Spreads the cameras' exposures over `spread_ns` within each group: the cameras, in the
    /// installation's order, expose at equal steps from the group's time (the first) to
    /// `spread_ns` after it (the last), and each observation shows the bodies at its camera's
    /// exposure (their motion extrapolated from the last two groups over that offset).
    pub fn set_exposure_spread_ns(&mut self, spread_ns: i64) {
        self.exposure_spread_ns = spread_ns.max(0);
    }

    /// When `camera` exposes after the group's time (ns), by
    /// [`Self::set_exposure_spread_ns`]; 0 for a camera the simulator does not know.
    pub fn exposure_offset_ns(&self, camera: &str) -> i64 {
        let cameras = self.cameras();
        let Some(k) = cameras.iter().position(|(c, _)| *c == camera) else {
            return 0;
        };
        if cameras.len() < 2 {
            return 0;
        }
        (self.exposure_spread_ns as f64 * k as f64 / (cameras.len() - 1) as f64).round() as i64
    }

    /// The body's motion `xi(t)` (left of nothing: applied about its own origin).
    fn body_motion(&mut self, b: usize, t_s: f64) -> Twist {
        let scale = match self.bodies[b].role {
            Role::Base => return Twist::zeros(),
            Role::Target if self.still_target => return Twist::zeros(),
            Role::Target => 1.0,
            Role::Station => 0.5,
        };
        let rate = |arcsec_per_s: f64, mm_per_s: f64, ax: [f64; 3]| {
            Twist::new(
                mm_per_s * ax[0] * t_s,
                mm_per_s * ax[1] * t_s,
                mm_per_s * ax[2] * t_s,
                arcsec_per_s / ARCSEC_PER_RAD * ax[0] * t_s,
                arcsec_per_s / ARCSEC_PER_RAD * ax[1] * t_s,
                arcsec_per_s / ARCSEC_PER_RAD * ax[2] * t_s,
            )
        };
        let axes = [0.6, 0.8, 0.0];
        match self.settings.scenario {
            Scenario::Static => Twist::zeros(),
            Scenario::Drift => rate(0.5 * scale, 0.002 * scale, axes),
            Scenario::Tunnel => {
                let s = if self.bodies[b].role == Role::Target {
                    1.0
                } else {
                    0.3
                };
                rate(s, 0.02 * s, axes)
            }
            Scenario::Bump => {
                let half = self.settings.duration_s.unwrap_or(60.0) / 2.0;
                if Some(b) == self.bumped && t_s >= half {
                    Twist::new(1.0, 0.0, 0.0, 0.0, 0.05f64.to_radians(), 0.0)
                } else {
                    Twist::zeros()
                }
            }
            Scenario::Ship => {
                let dt = t_s - self.last_t_s;
                let mut xi = rate(0.2 * scale, 0.0, axes);
                let oscillators = &mut self.bodies[b].oscillators;
                for k in 0..6 {
                    for o in &mut oscillators[2 * k..2 * k + 2] {
                        xi[k] += o.advance(dt, &mut self.rng);
                    }
                }
                xi
            }
        }
    }

    /// The next group.
    pub fn next_group(&mut self) -> SimGroup {
        let t_s = self.index as f64 / self.settings.rate_hz;
        let time_ns = self.settings.start_ns + (t_s * 1e9).round() as i64;
        self.index += 1;
        let dt_s = t_s - self.last_t_s;
        let xis: Vec<Twist> = (0..self.bodies.len())
            .map(|b| self.body_motion(b, t_s))
            .collect();
        // Each body's motion `offset_s` after the group's time, extrapolated linearly from the
        // last two groups (the first group has no rate: it is taken as it is).
        let moves_at = |offset_s: f64| -> Vec<Pose> {
            xis.iter()
                .enumerate()
                .map(|(b, xi)| {
                    let xi = match self.last_xi.get(b) {
                        Some(last) if dt_s > 0.0 && offset_s != 0.0 => {
                            xi + (xi - last) * (offset_s / dt_s)
                        }
                        _ => *xi,
                    };
                    let w0 = self.bodies[b].world_from_body0;
                    let moved = w0 * se3_exp(&xi) * w0.inverse();
                    match self.displaced[b] {
                        Some(operator) => operator * moved,
                        None => moved,
                    }
                })
                .collect()
        };
        let moves = moves_at(0.0);
        let world = |f: FrameId| moves[self.frame_body[f.0]] * self.world_from_frame0[f.0];
        let link_truth: Vec<(String, Pose)> = self
            .measured
            .iter()
            .map(|l| (l.name.clone(), world(l.parent).inverse() * world(l.child)))
            .collect();
        let truth = self
            .targets
            .iter()
            .map(|(name, g, b)| (name.clone(), world(*g).inverse() * world(*b)))
            .collect();
        let mut observations = Vec::new();
        let mut samples = Vec::new();
        let spread = self.exposure_spread_ns != 0;
        for (simulated, (_, camera_from_marker)) in self.measured.iter().zip(&link_truth) {
            if let Some(link) = &simulated.observed {
                let exposed;
                let camera_from_marker = if spread {
                    let offset_s = self.exposure_offset_ns(&link.camera_frame) as f64 / 1e9;
                    let moves = moves_at(offset_s);
                    let world =
                        |f: FrameId| moves[self.frame_body[f.0]] * self.world_from_frame0[f.0];
                    exposed = world(simulated.parent).inverse() * world(simulated.child);
                    &exposed
                } else {
                    camera_from_marker
                };
                let sigma_px = self
                    .settings
                    .pixel_sigma_px
                    .unwrap_or(link.options.pixel_sigma_px);
                let outlier = self.rng.random_bool(self.settings.outlier_rate);
                let shift = if outlier {
                    let angle = self.rng.random_range(0.0..std::f64::consts::TAU);
                    let size = self.rng.random_range(2.0..5.0);
                    [size * angle.cos(), size * angle.sin()]
                } else {
                    [0.0, 0.0]
                };
                let points_px = link
                    .points_mm
                    .iter()
                    .filter_map(|x| {
                        link.camera
                            .project(&(camera_from_marker * Point3::from(*x)).coords)
                    })
                    .map(|uv| {
                        [
                            uv.x + sigma_px * self.rng.sample::<f64, _>(StandardNormal) + shift[0],
                            uv.y + sigma_px * self.rng.sample::<f64, _>(StandardNormal) + shift[1],
                        ]
                    })
                    .collect();
                observations.push(SimObservation {
                    camera: link.camera_frame.clone(),
                    marker: link.marker_frame.clone(),
                    points_px,
                    outlier,
                });
            } else {
                let sigma = &simulated.sigma;
                let r = sigma.rotation_arcsec.map(|s| s / ARCSEC_PER_RAD);
                let t = sigma.translation_mm;
                let mut draw = || self.rng.sample::<f64, _>(StandardNormal);
                let xi = Twist::new(
                    t[0] * draw(),
                    t[1] * draw(),
                    t[2] * draw(),
                    r[0] * draw(),
                    r[1] * draw(),
                    r[2] * draw(),
                );
                samples.push(SimSample {
                    link: simulated.name.clone(),
                    pose: se3_exp(&xi) * camera_from_marker,
                    sigma: *sigma,
                });
            }
        }
        self.last_t_s = t_s;
        self.last_xi = xis;
        SimGroup {
            time_ns,
            observations,
            samples,
            truth,
            link_truth,
        }
    }

    /// What each camera sees in a group, ready to render (owned, so that rendering can run on
    /// another thread): per camera of a camera-marker link, in installation order, the discs
    /// of every marker it sees at the group's true poses, and a noise seed of its own.
    pub fn frame_scenes(&self, group: &SimGroup) -> Vec<render::FrameScene> {
        self.cameras()
            .into_iter()
            .enumerate()
            .map(|(k, (camera, model))| render::FrameScene {
                camera: camera.to_owned(),
                model: *model,
                discs: self
                    .observer
                    .links()
                    .filter(|l| l.camera_frame == camera)
                    .filter_map(|l| {
                        let pose = group.link_truth.iter().find(|(n, _)| *n == l.name)?.1;
                        Some(render::marker_discs(l, &pose))
                    })
                    .flatten()
                    .collect(),
                seed: self
                    .settings
                    .seed
                    .wrapping_mul(0x9E37_79B9_7F4A_7C15)
                    .wrapping_add(group.time_ns as u64)
                    .wrapping_add(k as u64),
            })
            .collect()
    }

    /// The frames of a group ([`Self::frame_scenes`] rendered with `settings`, each with its
    /// own noise seed).
    pub fn render_frames(
        &self,
        group: &SimGroup,
        settings: &render::RenderSettings,
    ) -> Vec<(String, crate::vision::GreyImage)> {
        self.frame_scenes(group)
            .into_iter()
            .map(|scene| {
                let frame = scene.render(settings);
                (scene.camera, frame)
            })
            .collect()
    }

    /// The installation's camera-marker links (to solve the observations it generates).
    pub fn observer(&self) -> &Observer {
        &self.observer
    }
}
