//! What `check-config` prints: a human-readable report of a validated installation.

use crate::chain::Direction;
use crate::config::Installation;
use crate::geometry::{euler_from_rotation, quaternion_wxyz};
use crate::model::LinkKind;
use std::fmt::Write as _;

fn fmt3(v: [f64; 3], decimals: usize) -> String {
    let parts: Vec<String> = v.iter().map(|x| format!("{x:.decimals$}")).collect();
    format!("[{}]", parts.join(", "))
}

/// A human-readable report of a validated installation.
pub fn describe_installation(inst: &Installation) -> String {
    let mut s = String::new();
    let topo = &inst.model.topology;
    let _ = writeln!(s, "installation: {} (valid)", inst.source);
    let _ = writeln!(
        s,
        "frames ({}): {}",
        topo.frames().len(),
        topo.frames().join(", ")
    );
    let _ = writeln!(s, "cameras ({}):", inst.model.cameras.len());
    for c in &inst.model.cameras {
        let _ = writeln!(
            s,
            "  {:<6} {}x{} px, fx {} fy {} px, pixel sigma {} px",
            c.frame,
            c.intrinsics.width_px,
            c.intrinsics.height_px,
            c.intrinsics.fx_px,
            c.intrinsics.fy_px,
            c.pixel_sigma_px
        );
    }
    let _ = writeln!(s, "markers ({}):", inst.model.markers.len());
    for m in &inst.model.markers {
        let _ = writeln!(s, "  {:<6} {} points", m.frame, m.points_mm.len());
    }
    let _ = writeln!(s, "links ({}):", inst.model.links.len());
    for l in &inst.model.links {
        match &l.kind {
            LinkKind::Calibrated { parent_from_child } => {
                let sig = parent_from_child.reported_sigmas();
                let _ = writeln!(
                    s,
                    "  {:<14} calibrated  t_mm {} euler_deg {} sigma {} arcsec {} mm",
                    l.name,
                    fmt3(parent_from_child.pose.translation.vector.into(), 1),
                    fmt3(
                        euler_from_rotation(&parent_from_child.pose.rotation).to_degrees(),
                        4
                    ),
                    fmt3(sig.rotation_arcsec, 1),
                    fmt3(sig.translation_mm, 3),
                );
            }
            LinkKind::Measured(m) => {
                let _ = writeln!(
                    s,
                    "  {:<14} measured    model {} at {} Hz, default sigma {} arcsec {} mm",
                    l.name,
                    m.tuning.model.name(),
                    m.expected_rate_hz,
                    fmt3(m.default_sigmas.rotation_arcsec, 1),
                    fmt3(m.default_sigmas.translation_mm, 3),
                );
            }
        }
    }
    let _ = writeln!(s, "targets ({}):", inst.model.targets.len());
    for t in &inst.model.targets {
        let r = &t.resolution;
        let _ = writeln!(
            s,
            "  {} from {}: {} independent path(s){}",
            t.name,
            topo.frame_name(t.base),
            r.paths.len(),
            if r.paths.len() > 1 { ", fused" } else { "" }
        );
        for (i, path) in r.paths.iter().enumerate() {
            let steps: Vec<String> = path
                .steps
                .iter()
                .map(|st| {
                    let name = &topo.link(st.link).name;
                    match st.direction {
                        Direction::Forward => format!("{name} (forward)"),
                        Direction::Inverse => format!("{name} (inverted)"),
                    }
                })
                .collect();
            let _ = writeln!(s, "    path {}: {}", i + 1, steps.join(" -> "));
            let _ = writeln!(
                s,
                "      {}_from_{} = {}",
                t.name,
                topo.frame_name(t.base),
                topo.describe_product(path)
            );
            if let Some(nominal) = nominal_of_path(inst, path) {
                let _ = writeln!(
                    s,
                    "      nominal: t_mm {} euler_deg {} q_wxyz {}",
                    fmt3(nominal.translation.vector.into(), 2),
                    fmt3(euler_from_rotation(&nominal.rotation).to_degrees(), 4),
                    {
                        let q = quaternion_wxyz(&nominal.rotation);
                        format!("[{:.6}, {:.6}, {:.6}, {:.6}]", q[0], q[1], q[2], q[3])
                    }
                );
            }
        }
        for path in &r.dependent_paths {
            let names: Vec<&str> = path.links().map(|l| topo.link(l).name.as_str()).collect();
            let _ = writeln!(
                s,
                "    not fused (shares a link with a path above): {}",
                names.join(" -> ")
            );
        }
    }
    s
}

/// The nominal pose of a path, when every link on it has a known (nominal or calibrated) pose.
fn nominal_of_path(
    inst: &Installation,
    path: &crate::chain::Path,
) -> Option<crate::geometry::Pose> {
    let mut known = true;
    let composed = crate::chain::compose_path(path, |id| match &inst.model.link(id).kind {
        LinkKind::Calibrated { parent_from_child } => *parent_from_child,
        LinkKind::Measured(m) => match m.nominal {
            Some(p) => crate::geometry::PoseCov::exact(p),
            None => {
                known = false;
                crate::geometry::PoseCov::identity()
            }
        },
    });
    known.then_some(composed.pose)
}
