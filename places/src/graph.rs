//! Pose-graph optimisation over keyframes: odometry edges between consecutive
//! keyframes of a session, loop edges from verified place matches within a
//! session, inter-session edges between sessions of a fleet, each a measured
//! relative pose with its uncertainty. Place edges sit behind a robust (Huber)
//! kernel, so that a wrong one pulls with a bounded force instead of bending the
//! map; odometry edges are least squares.
//!
//! The solver is factrs (`BetweenResidual` on SE(3), Levenberg–Marquardt, faer's
//! sparse Cholesky): chosen over tiny-solver and apex-solver for its typed Lie
//! groups, robust kernels and sparse back end with no C dependency, and over the
//! hand-written local BA of the tracker because a fleet's graph is large and
//! sparse (thousands of keyframes, a few edges each) where that one is tiny and dense.

use factrs::assign_symbols;
use factrs::containers::{Graph, Values};
use factrs::core::{BetweenResidual, GaussianNoise, Huber, LevenMarquardt, PriorResidual, SE3, SO3};
use factrs::linalg::Vector3 as FVector3;
use factrs::optimizers::{BaseOptParams, LevenParams, OptError};
use factrs::traits::Optimizer;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::PlacesError;

assign_symbols!(K: SE3);

/// What an edge measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EdgeKind {
    /// Consecutive keyframes of one session (tracking).
    Odometry,
    /// A verified place match within a session.
    Loop,
    /// A verified place match between two sessions of a fleet.
    InterSession,
}

/// A measured relative pose `from_from_to` (the `to` keyframe's camera in the
/// `from` keyframe's camera frame) with isotropic σ for rotation and translation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Edge {
    pub from: usize,
    pub to: usize,
    pub from_from_to: Isometry3<f64>,
    pub kind: EdgeKind,
    pub sigma_rotation_rad: f64,
    pub sigma_translation_m: f64,
}

/// Keyframe poses (`world_from_camera`) and the edges between them.
#[derive(Debug, Clone, Default)]
pub struct PoseGraph {
    pub poses: Vec<Isometry3<f64>>,
    pub edges: Vec<Edge>,
}

/// How the graph is solved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveConfig {
    /// Levenberg–Marquardt iterations at most.
    pub max_iterations: usize,
    /// The keyframe whose pose is held (the gauge: a session's first keyframe, or the fleet's anchor).
    pub fixed: usize,
    /// Rounds of re-weighting after the first solve: each group of edges
    /// (odometry; loop and inter-session) has its σ scaled by its RMS normalised
    /// residual in the last solution (within `1/MAX_REWEIGHT..=MAX_REWEIGHT` of
    /// the given σ), and the graph is solved again from the given poses. The
    /// configured σ are then a starting point: a group that disagrees with the
    /// rest more than its σ allow (odometry that drifted) loosens, one that
    /// agrees better tightens. 0: the σ as given.
    pub reweight_rounds: usize,
}

/// How far re-weighting may scale a group's σ, either way.
pub const MAX_REWEIGHT: f64 = 10.0;

impl Default for SolveConfig {
    fn default() -> Self {
        Self { max_iterations: 50, fixed: 0, reweight_rounds: 0 }
    }
}

impl PoseGraph {
    /// Adds a keyframe; returns its index.
    pub fn add_pose(&mut self, world_from_camera: Isometry3<f64>) -> usize {
        self.poses.push(world_from_camera);
        self.poses.len() - 1
    }

    /// Adds an edge (both ends must exist).
    pub fn add_edge(&mut self, edge: Edge) -> Result<(), PlacesError> {
        if edge.from >= self.poses.len() || edge.to >= self.poses.len() || edge.from == edge.to {
            return Err(PlacesError::Config(format!("pose graph: edge {} → {} of {} poses", edge.from, edge.to, self.poses.len())));
        }
        if !(edge.sigma_rotation_rad > 0.0 && edge.sigma_translation_m > 0.0) {
            return Err(PlacesError::Config("pose graph: edge sigmas must be positive".into()));
        }
        self.edges.push(edge);
        Ok(())
    }

    /// The optimised `world_from_camera` of every keyframe, `config.fixed` held,
    /// re-weighted `config.reweight_rounds` times.
    pub fn optimize(&self, config: &SolveConfig) -> Result<Vec<Isometry3<f64>>, PlacesError> {
        let mut solved = self.solve_once(config)?;
        for _ in 0..config.reweight_rounds {
            let residual = |odometry: bool| {
                let (mut sum, mut n) = (0.0, 0usize);
                for e in self.edges.iter().filter(|e| (e.kind == EdgeKind::Odometry) == odometry) {
                    let error = e.from_from_to.inverse() * (solved[e.from].inverse() * solved[e.to]);
                    let t = error.translation.vector.norm() / e.sigma_translation_m;
                    let r = error.rotation.angle() / e.sigma_rotation_rad;
                    sum += (t * t + r * r) / 2.0;
                    n += 1;
                }
                (n > 0).then(|| (sum / n as f64).sqrt())
            };
            let (Some(o), Some(p)) = (residual(true), residual(false)) else { break };
            let odometry_scale = o.clamp(1.0 / MAX_REWEIGHT, MAX_REWEIGHT);
            let place_scale = p.clamp(1.0 / MAX_REWEIGHT, MAX_REWEIGHT);
            let mut scaled = self.clone();
            for e in &mut scaled.edges {
                let k = if e.kind == EdgeKind::Odometry { odometry_scale } else { place_scale };
                e.sigma_translation_m *= k;
                e.sigma_rotation_rad *= k;
            }
            solved = scaled.solve_once(config)?;
        }
        Ok(solved)
    }

    fn solve_once(&self, config: &SolveConfig) -> Result<Vec<Isometry3<f64>>, PlacesError> {
        if config.fixed >= self.poses.len() {
            return Err(PlacesError::Config(format!("pose graph: fixed keyframe {} of {} poses", config.fixed, self.poses.len())));
        }
        let key = |i: usize| u32::try_from(i).map(K).map_err(|_| PlacesError::Config(format!("pose graph: keyframe index {i}")));
        let mut values = Values::new();
        for (i, p) in self.poses.iter().enumerate() {
            values.insert(key(i)?, se3(p));
        }
        let mut graph = Graph::new();
        // The gauge: a tight prior on the fixed keyframe.
        let gauge = key(config.fixed)?;
        graph.add_factor(factrs::fac![
            PriorResidual::new(se3(&self.poses[config.fixed])),
            gauge,
            GaussianNoise::<6>::from_split_sigma(1e-6, 1e-6)
        ]);
        for e in &self.edges {
            let noise = GaussianNoise::<6>::from_split_sigma(e.sigma_rotation_rad, e.sigma_translation_m);
            let (from, to) = (key(e.from)?, key(e.to)?);
            // Tracking's odometry is trusted as it is; a place match, however well
            // verified, can still be wrong: Huber caps its pull.
            match e.kind {
                EdgeKind::Odometry => graph.add_factor(factrs::fac![BetweenResidual::new(se3(&e.from_from_to)), (from, to), noise]),
                EdgeKind::Loop | EdgeKind::InterSession => {
                    graph.add_factor(factrs::fac![BetweenResidual::new(se3(&e.from_from_to)), (from, to), noise, Huber::default()])
                }
            }
        }
        let params = LevenParams {
            base: BaseOptParams { max_iterations: config.max_iterations, ..BaseOptParams::default() },
            ..LevenParams::default()
        };
        let mut optimizer = LevenMarquardt::new(params, graph);
        let result = match optimizer.optimize(values) {
            Ok(values) => values,
            // Levenberg–Marquardt only takes steps that lower the cost: the last values are the best found.
            Err(OptError::MaxIterations(values)) => values,
            Err(e) => return Err(PlacesError::Solver(format!("{e:?}"))),
        };
        let solved = (0..self.poses.len())
            .map(|i| {
                let p: &SE3 = result.get(key(i)?).ok_or_else(|| PlacesError::Solver(format!("keyframe {i} missing from the solution")))?;
                Ok(isometry(p))
            })
            .collect::<Result<Vec<_>, PlacesError>>()?;
        // The gauge exactly: the fixed keyframe where it was (the prior holds it to 1e-6).
        let correction = self.poses[config.fixed] * solved[config.fixed].inverse();
        let mut solved: Vec<Isometry3<f64>> = solved.iter().map(|p| correction * p).collect();
        solved[config.fixed] = self.poses[config.fixed];
        Ok(solved)
    }
}

fn se3(p: &Isometry3<f64>) -> SE3 {
    let (q, t) = (p.rotation.coords, p.translation.vector);
    SE3::from_rot_trans(SO3::from_xyzw(q.x, q.y, q.z, q.w), FVector3::new(t.x, t.y, t.z))
}

fn isometry(p: &SE3) -> Isometry3<f64> {
    let (r, t) = (p.rot(), p.xyz());
    Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), UnitQuaternion::from_quaternion(Quaternion::new(r.w(), r.x(), r.y(), r.z())))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn pose(x: f64, y: f64, yaw_deg: f64) -> Isometry3<f64> {
        Isometry3::new(Vector3::new(x, y, 0.0), Vector3::new(0.0, 0.0, yaw_deg.to_radians()))
    }

    fn edge(from: usize, to: usize, from_from_to: Isometry3<f64>, kind: EdgeKind) -> Edge {
        Edge { from, to, from_from_to, kind, sigma_rotation_rad: 0.01, sigma_translation_m: 0.01 }
    }

    /// Exact measurements, a start 10 cm and 5° off at every keyframe: the solution is the truth.
    #[test]
    fn consistent_edges_give_the_exact_poses_back() {
        let truth = [pose(0.0, 0.0, 0.0), pose(1.0, 0.0, 90.0), pose(1.0, 1.0, 180.0), pose(0.0, 1.0, 270.0)];
        let mut graph = PoseGraph::default();
        for (i, t) in truth.iter().enumerate() {
            let off = if i == 0 {
                Isometry3::identity()
            } else {
                Isometry3::new(Vector3::new(0.1, -0.05, 0.03), Vector3::new(0.02, -0.05, 0.08))
            };
            graph.add_pose(t * off);
        }
        for (a, b, kind) in [
            (0, 1, EdgeKind::Odometry),
            (1, 2, EdgeKind::Odometry),
            (2, 3, EdgeKind::Odometry),
            (3, 0, EdgeKind::Loop),
            (0, 2, EdgeKind::InterSession),
        ] {
            graph.add_edge(edge(a, b, truth[a].inverse() * truth[b], kind)).expect("edge");
        }
        let solved = graph.optimize(&SolveConfig::default()).expect("solved");
        assert_eq!(solved[0], truth[0], "the gauge is held");
        for (s, t) in solved.iter().zip(&truth) {
            let e = t.inverse() * s;
            assert!(e.translation.vector.norm() < 1e-6 && e.rotation.angle() < 1e-6, "{e:?}");
        }
        assert!(graph.add_edge(edge(0, 9, truth[0], EdgeKind::Loop)).is_err(), "an edge to a keyframe that does not exist");
        assert!(graph.optimize(&SolveConfig { fixed: 7, ..SolveConfig::default() }).is_err());
    }

    /// A circle of 24 keyframes whose odometry turns 0.5° too far at every step,
    /// closed by one exact loop edge: the loop takes most of the drift out.
    #[test]
    fn a_loop_takes_the_drift_out_of_a_circle() {
        let n = 24;
        let truth: Vec<Isometry3<f64>> = (0..n)
            .map(|i| {
                let a = (i as f64 / n as f64) * std::f64::consts::TAU;
                Isometry3::new(Vector3::new(2.0 * a.sin(), 2.0 - 2.0 * a.cos(), 0.0), Vector3::new(0.0, 0.0, a))
            })
            .collect();
        let drift = Isometry3::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 0.5f64.to_radians()));
        let mut graph = PoseGraph::default();
        let mut p = truth[0];
        graph.add_pose(p);
        for i in 1..n {
            let step = truth[i - 1].inverse() * truth[i] * drift;
            p *= step;
            graph.add_pose(p);
            graph.add_edge(edge(i - 1, i, step, EdgeKind::Odometry)).expect("odometry");
        }
        graph.add_edge(edge(n - 1, 0, truth[n - 1].inverse() * truth[0], EdgeKind::Loop)).expect("loop");
        let error = |poses: &[Isometry3<f64>]| {
            poses.iter().zip(&truth).map(|(p, t)| (p.translation.vector - t.translation.vector).norm()).fold(0.0, f64::max)
        };
        let (before, after) = (error(&graph.poses), error(&graph.optimize(&SolveConfig::default()).expect("solved")));
        assert!(before > 0.3 && after < before / 5.0, "worst keyframe {before:.3} m before, {after:.3} m after");
    }

    /// A wrong loop edge (2 m off) among good ones loses its weight (Huber).
    #[test]
    fn a_wrong_loop_does_not_bend_the_graph() {
        let mut graph = PoseGraph::default();
        let step = Isometry3::new(Vector3::new(0.5, 0.0, 0.0), Vector3::zeros());
        for i in 0..8 {
            graph.add_pose(Isometry3::new(Vector3::new(0.5 * i as f64, 0.0, 0.0), Vector3::zeros()));
        }
        for i in 0..7 {
            graph
                .add_edge(Edge {
                    from: i,
                    to: i + 1,
                    from_from_to: step,
                    kind: EdgeKind::Odometry,
                    sigma_rotation_rad: 0.01,
                    sigma_translation_m: 0.01,
                })
                .expect("edge");
        }
        let wrong = Isometry3::new(Vector3::new(1.5, 2.0, 0.0), Vector3::zeros());
        graph
            .add_edge(Edge {
                from: 0,
                to: 3,
                from_from_to: wrong,
                kind: EdgeKind::Loop,
                sigma_rotation_rad: 0.01,
                sigma_translation_m: 0.01,
            })
            .expect("edge");
        let solved = graph.optimize(&SolveConfig::default()).expect("solved");
        let worst = solved.iter().zip(&graph.poses).map(|(s, p)| (s.translation.vector - p.translation.vector).norm()).fold(0.0, f64::max);
        assert!(worst < 0.25, "the wrong loop moved a keyframe {worst:.3} m (it asks for 2 m)");
        // Re-weighting loosens the group that fits worst: here the loop, so it pulls less.
        let reweighted = graph.optimize(&SolveConfig { reweight_rounds: 2, ..SolveConfig::default() }).expect("solved");
        let worst_reweighted =
            reweighted.iter().zip(&graph.poses).map(|(s, p)| (s.translation.vector - p.translation.vector).norm()).fold(0.0, f64::max);
        assert!(worst_reweighted < worst, "re-weighted {worst_reweighted:.3} m, plain {worst:.3} m");
    }
}
