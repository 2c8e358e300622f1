//! The frame/link graph and the resolution of a target's paths from its base.

use super::ChainError;
use std::collections::{HashMap, VecDeque};

/// Index of a frame in a [`Topology`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FrameId(pub usize);

/// Index of a link in a [`Topology`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct LinkId(pub usize);

/// A link's name and the two frames it joins: the link is `parent_from_child`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkEnds {
    /// The link's name, `<parent>_from_<child>`.
    pub name: String,
    /// The frame the link maps into.
    pub parent: FrameId,
    /// The frame the link maps from.
    pub child: FrameId,
}

/// How a path uses a link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Direction {
    /// The link as stored, `parent_from_child`: walks from the child frame to the parent.
    Forward,
    /// The inverted link, `child_from_parent`: walks from the parent frame to the child.
    Inverse,
}

/// One step of a path: `to_from_from`, which is a link or its inverse.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Step {
    /// The link walked.
    pub link: LinkId,
    /// Forwards or inverted.
    pub direction: Direction,
    /// The frame the step starts from.
    pub from: FrameId,
    /// The frame the step arrives at.
    pub to: FrameId,
}

/// A walk from a base frame to a target frame; composing its steps right to left gives
/// `target_from_base = step_n * ... * step_1`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Path {
    /// The steps, from the base outwards.
    pub steps: Vec<Step>,
}

impl Path {
    /// The links this path uses.
    pub fn links(&self) -> impl Iterator<Item = LinkId> + '_ {
        self.steps.iter().map(|s| s.link)
    }
}

/// How a target is reached from its base.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Resolution {
    /// The base frame.
    pub base: FrameId,
    /// The target frame.
    pub target: FrameId,
    /// Link-disjoint paths, shortest first: their estimates are independent and are fused.
    pub paths: Vec<Path>,
    /// Further simple paths that share a link with a path above. They are not fused (that would
    /// count the shared link's information twice) but are listed so users can see them.
    pub dependent_paths: Vec<Path>,
}

/// The graph of frames and links of one installation.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Topology {
    frames: Vec<String>,
    frame_index: HashMap<String, FrameId>,
    links: Vec<LinkEnds>,
    link_index: HashMap<String, LinkId>,
    /// Per frame: the links touching it.
    incident: Vec<Vec<LinkId>>,
}

/// Upper bound on the simple paths enumerated per target (relay installations are small; the
/// bound keeps a mis-written file with a dense graph from exploding).
const MAX_ENUMERATED_PATHS: usize = 64;

impl Topology {
    /// An empty topology.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a frame if it is not there yet; returns its id.
    pub fn add_frame(&mut self, name: &str) -> FrameId {
        if let Some(&id) = self.frame_index.get(name) {
            return id;
        }
        let id = FrameId(self.frames.len());
        self.frames.push(name.to_owned());
        self.frame_index.insert(name.to_owned(), id);
        self.incident.push(Vec::new());
        id
    }

    /// Adds the link `parent_from_child` named `name`, adding its frames as needed.
    pub fn add_link(
        &mut self,
        name: &str,
        parent: &str,
        child: &str,
    ) -> Result<LinkId, ChainError> {
        if self.link_index.contains_key(name) {
            return Err(ChainError::DuplicateLink(name.to_owned()));
        }
        if parent == child {
            return Err(ChainError::SelfLink(name.to_owned()));
        }
        let parent = self.add_frame(parent);
        let child = self.add_frame(child);
        let id = LinkId(self.links.len());
        self.links.push(LinkEnds {
            name: name.to_owned(),
            parent,
            child,
        });
        self.link_index.insert(name.to_owned(), id);
        self.incident[parent.0].push(id);
        self.incident[child.0].push(id);
        Ok(id)
    }

    /// Every frame name, in the order they were introduced.
    pub fn frames(&self) -> &[String] {
        &self.frames
    }

    /// Every link, indexed by [`LinkId`].
    pub fn links(&self) -> &[LinkEnds] {
        &self.links
    }

    /// The frame with this name.
    pub fn frame_id(&self, name: &str) -> Option<FrameId> {
        self.frame_index.get(name).copied()
    }

    /// The link with this name.
    pub fn link_id(&self, name: &str) -> Option<LinkId> {
        self.link_index.get(name).copied()
    }

    /// A frame's name.
    pub fn frame_name(&self, id: FrameId) -> &str {
        &self.frames[id.0]
    }

    /// A link's ends.
    pub fn link(&self, id: LinkId) -> &LinkEnds {
        &self.links[id.0]
    }

    /// The step that leaves `from` through `link`.
    fn step_from(&self, from: FrameId, link: LinkId) -> Step {
        let ends = &self.links[link.0];
        if ends.child == from {
            Step {
                link,
                direction: Direction::Forward,
                from,
                to: ends.parent,
            }
        } else {
            Step {
                link,
                direction: Direction::Inverse,
                from,
                to: ends.child,
            }
        }
    }

    /// A shortest path (fewest links) from `base` to `target` avoiding `excluded` links.
    fn shortest_path(&self, base: FrameId, target: FrameId, excluded: &[bool]) -> Option<Path> {
        let mut arrived_by: Vec<Option<Step>> = vec![None; self.frames.len()];
        let mut seen = vec![false; self.frames.len()];
        seen[base.0] = true;
        let mut queue = VecDeque::from([base]);
        while let Some(frame) = queue.pop_front() {
            if frame == target {
                let mut steps = Vec::new();
                let mut at = target;
                while let Some(step) = arrived_by[at.0] {
                    steps.push(step);
                    at = step.from;
                }
                steps.reverse();
                return Some(Path { steps });
            }
            for &link in &self.incident[frame.0] {
                if excluded[link.0] {
                    continue;
                }
                let step = self.step_from(frame, link);
                if !seen[step.to.0] {
                    seen[step.to.0] = true;
                    arrived_by[step.to.0] = Some(step);
                    queue.push_back(step.to);
                }
            }
        }
        None
    }

    /// Every simple path (no frame visited twice) from `base` to `target`, up to a bound.
    pub fn simple_paths(&self, base: FrameId, target: FrameId) -> Vec<Path> {
        let mut out = Vec::new();
        let mut on_path = vec![false; self.frames.len()];
        let mut steps = Vec::new();
        self.walk(base, target, &mut on_path, &mut steps, &mut out);
        out.sort_by_key(|p| p.steps.len());
        out
    }

    fn walk(
        &self,
        at: FrameId,
        target: FrameId,
        on_path: &mut [bool],
        steps: &mut Vec<Step>,
        out: &mut Vec<Path>,
    ) {
        if out.len() >= MAX_ENUMERATED_PATHS {
            return;
        }
        if at == target {
            out.push(Path {
                steps: steps.clone(),
            });
            return;
        }
        on_path[at.0] = true;
        for &link in &self.incident[at.0] {
            let step = self.step_from(at, link);
            if !on_path[step.to.0] {
                steps.push(step);
                self.walk(step.to, target, on_path, steps, out);
                steps.pop();
            }
        }
        on_path[at.0] = false;
    }

    /// Resolves `target` from `base`: link-disjoint paths (found shortest first, each one's
    /// links removed before the next search) and the other simple paths, listed as dependent.
    pub fn resolve(&self, base: &str, target: &str) -> Result<Resolution, ChainError> {
        let base_id = self
            .frame_id(base)
            .ok_or_else(|| ChainError::UnknownFrame(base.to_owned()))?;
        let target_id = self
            .frame_id(target)
            .ok_or_else(|| ChainError::UnknownFrame(target.to_owned()))?;
        if base_id == target_id {
            return Err(ChainError::TargetIsBase(target.to_owned()));
        }
        let mut excluded = vec![false; self.links.len()];
        let mut paths = Vec::new();
        while let Some(path) = self.shortest_path(base_id, target_id, &excluded) {
            for link in path.links() {
                excluded[link.0] = true;
            }
            paths.push(path);
        }
        if paths.is_empty() {
            return Err(ChainError::Unreachable {
                target: target.to_owned(),
                base: base.to_owned(),
            });
        }
        let dependent_paths = self
            .simple_paths(base_id, target_id)
            .into_iter()
            .filter(|p| !paths.contains(p))
            .collect();
        Ok(Resolution {
            base: base_id,
            target: target_id,
            paths,
            dependent_paths,
        })
    }

    /// The path written as a product of transforms, `G_from_C3 * C3_from_M * ...`.
    pub fn describe_product(&self, path: &Path) -> String {
        path.steps
            .iter()
            .rev()
            .map(|s| format!("{}_from_{}", self.frame_name(s.to), self.frame_name(s.from)))
            .collect::<Vec<_>>()
            .join(" * ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper_topology() -> Topology {
        let mut t = Topology::new();
        t.add_link("C1_from_B", "C1", "B").unwrap();
        t.add_link("C2_from_C1", "C2", "C1").unwrap();
        t.add_link("C2_from_M", "C2", "M").unwrap();
        t.add_link("C3_from_M", "C3", "M").unwrap();
        t.add_link("C3_from_G", "C3", "G").unwrap();
        t
    }

    #[test]
    fn paper_chain_walks_measured_links_inverted_where_needed() {
        let t = paper_topology();
        let r = t.resolve("B", "G").unwrap();
        assert_eq!(r.paths.len(), 1);
        assert!(r.dependent_paths.is_empty());
        let dirs: Vec<_> = r.paths[0].steps.iter().map(|s| s.direction).collect();
        use Direction::*;
        assert_eq!(dirs, vec![Forward, Forward, Inverse, Forward, Inverse]);
        assert_eq!(
            t.describe_product(&r.paths[0]),
            "G_from_C3 * C3_from_M * M_from_C2 * C2_from_C1 * C1_from_B"
        );
    }

    #[test]
    fn parallel_relays_give_two_disjoint_paths() {
        let mut t = paper_topology();
        t.add_link("C4_from_B", "C4", "B").unwrap();
        t.add_link("C4_from_G", "C4", "G").unwrap();
        let r = t.resolve("B", "G").unwrap();
        assert_eq!(r.paths.len(), 2);
        assert_eq!(r.paths[0].steps.len(), 2, "shortest path first");
    }

    #[test]
    fn a_branch_sharing_a_link_is_dependent_not_fused() {
        let mut t = paper_topology();
        // A second relay from C1 to G shares C1_from_B with the first.
        t.add_link("C5_from_C1", "C5", "C1").unwrap();
        t.add_link("C5_from_G", "C5", "G").unwrap();
        let r = t.resolve("B", "G").unwrap();
        assert_eq!(r.paths.len(), 1);
        assert_eq!(r.dependent_paths.len(), 1);
    }

    #[test]
    fn disconnected_target_is_unreachable() {
        let mut t = paper_topology();
        t.add_link("X_from_Y", "X", "Y").unwrap();
        assert_eq!(
            t.resolve("B", "X").unwrap_err(),
            ChainError::Unreachable {
                target: "X".into(),
                base: "B".into()
            }
        );
    }

    #[test]
    fn duplicate_and_self_links_are_refused() {
        let mut t = paper_topology();
        assert_eq!(
            t.add_link("C1_from_B", "C1", "B").unwrap_err(),
            ChainError::DuplicateLink("C1_from_B".into())
        );
        assert_eq!(
            t.add_link("A_from_A", "A", "A").unwrap_err(),
            ChainError::SelfLink("A_from_A".into())
        );
    }
}
