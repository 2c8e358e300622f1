//! `[[markers]]`: cooperative markers, their points, identities and disc targets.

use super::*;

impl Validator {
    pub(super) fn markers(&mut self, raw: &RawFile) -> Vec<Marker> {
        let mut out = Vec::new();
        for spanned in &raw.markers {
            let at = spanned.span().start;
            let m = spanned.get_ref();
            let what = format!("marker `{}`", m.frame);
            let mut ok = self.frame_name(at, &m.frame);
            if m.points_mm.len() < 4 {
                self.problem(
                    at,
                    format!("{what} needs at least 4 points, has {}", m.points_mm.len()),
                );
                ok = false;
            }
            for (i, p) in m.points_mm.iter().enumerate() {
                ok &= self.finite(at, &format!("{what}: points_mm[{i}]"), p);
            }
            let ids = match &m.ids {
                Some(ids) if ids.len() != m.points_mm.len() => {
                    self.problem(
                        at,
                        format!(
                            "{what} has {} ids for {} points",
                            ids.len(),
                            m.points_mm.len()
                        ),
                    );
                    ok = false;
                    Vec::new()
                }
                Some(ids) => {
                    let unique: std::collections::HashSet<_> = ids.iter().collect();
                    if unique.len() != ids.len() {
                        self.problem(at, format!("{what} has duplicate point ids"));
                        ok = false;
                    }
                    ids.clone()
                }
                None => (0..m.points_mm.len() as u32).collect(),
            };
            let target = match &m.target {
                None => None,
                Some(t) => {
                    if t.kind != "disc" {
                        self.problem(
                            at,
                            format!("{what}: target kind `{}` is not known (`disc`)", t.kind),
                        );
                        ok = false;
                    }
                    ok &= self.positive(at, &format!("{what}: target.diameter_mm"), t.diameter_mm);
                    let polarity = match t.polarity.as_deref() {
                        None | Some("bright") => Polarity::Bright,
                        Some("dark") => Polarity::Dark,
                        Some(other) => {
                            self.problem(
                                at,
                                format!(
                                    "{what}: target polarity `{other}` is not `bright` or `dark`"
                                ),
                            );
                            ok = false;
                            Polarity::Bright
                        }
                    };
                    Some(DiscTarget {
                        diameter_mm: t.diameter_mm,
                        polarity,
                    })
                }
            };
            let normals = match &m.normals {
                None => vec![[0.0, 0.0, 1.0]; m.points_mm.len()],
                Some(normals) => {
                    if normals.len() != m.points_mm.len() {
                        self.problem(
                            at,
                            format!(
                                "{what} has {} normals for {} points",
                                normals.len(),
                                m.points_mm.len()
                            ),
                        );
                        ok = false;
                    }
                    normals
                        .iter()
                        .enumerate()
                        .map(|(i, n)| {
                            let norm = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                            if !(norm.is_finite() && norm > 1e-9) {
                                self.problem(
                                    at,
                                    format!(
                                        "{what}: normals[{i}] must be a finite, non-zero vector"
                                    ),
                                );
                                ok = false;
                                return [0.0, 0.0, 1.0];
                            }
                            [n[0] / norm, n[1] / norm, n[2] / norm]
                        })
                        .collect()
                }
            };
            if ok && let Some(target) = &target {
                let points: Vec<crate::geometry::Vec3> = m
                    .points_mm
                    .iter()
                    .map(|p| crate::geometry::Vec3::from(*p))
                    .collect();
                // Within a quarter of a disc's diameter a point is where another was: the
                // search with no prior cannot tell them apart.
                let tolerance_mm = 0.25 * target.diameter_mm;
                if let Some((k, onto)) = crate::model::layout_symmetries(&points, tolerance_mm)
                    .first()
                    .and_then(|map| map.iter().enumerate().find(|(k, m)| k != *m))
                {
                    self.warning(at, format!(
                            "{what}: its layout maps onto itself under a turn (point {k} onto point {onto}, within {tolerance_mm} mm): with no prediction it cannot be identified (it is tracked from its nominal pose); move a point off the symmetry"
                        ));
                }
            }
            if ok {
                self.marker_at.insert(m.frame.clone(), at);
                out.push(Marker {
                    frame: m.frame.clone(),
                    points_mm: m.points_mm.clone(),
                    ids,
                    target,
                    normals,
                });
            }
        }
        out
    }
}
