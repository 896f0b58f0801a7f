//! Local bundle adjustment: keyframe poses and map points refined together by
//! Levenberg–Marquardt with the Schur complement.
//!
//! The structure is the classic one: every observation links one pose (6
//! parameters) and one point (3). Point blocks are 3×3 and independent, so they are
//! eliminated first; the reduced camera system is dense but tiny (6 × window size,
//! 36–60 unknowns), solved by Cholesky. Keyframes outside the window that see the
//! window's points take part as fixed poses and anchor the gauge.

use std::collections::HashMap;

use nalgebra::{DMatrix, DVector, Isometry3, Matrix3, Matrix6x3, Point3, Vector3, Vector6};

use crate::camera::Camera;
use crate::geometry::{Measurement, huber_weight, linearise, perturb, residual, robust_cost};

/// Initial LM damping, relative to the mean diagonal of the system.
const INITIAL_LAMBDA: f64 = 1e-4;
/// Damping growth on a rejected step and shrink on an accepted one.
const LAMBDA_UP: f64 = 10.0;
const LAMBDA_DOWN: f64 = 3.0;
/// Relative cost decrease below which the solver stops.
const MIN_RELATIVE_DECREASE: f64 = 1e-6;

/// A bundle-adjustment problem.
pub struct Problem {
    /// `camera_from_world` per keyframe.
    pub poses: Vec<Isometry3<f64>>,
    pub fixed: Vec<bool>,
    pub points: Vec<Point3<f64>>,
    /// (pose index, point index, measurement).
    pub observations: Vec<(usize, usize, Measurement)>,
}

/// What the solver did.
#[derive(Debug, Clone, Copy, Default)]
pub struct Report {
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: u32,
}

fn total_cost(camera: &Camera, bf: f64, p: &Problem) -> f64 {
    p.observations
        .iter()
        .map(|(ci, pi, m)| match residual(camera, bf, &p.poses[*ci], &p.points[*pi], m) {
            Some(r) => robust_cost(r.chi2(m.information), m.chi2_threshold()),
            None => 2.0 * m.chi2_threshold(),
        })
        .sum()
}

/// The normal equations of one state: pose blocks, point blocks and their coupling.
struct Linearisation {
    hpp: DMatrix<f64>,
    bp: DVector<f64>,
    hll: Vec<Matrix3<f64>>,
    bl: Vec<Vector3<f64>>,
    hpl: Vec<Option<Matrix6x3<f64>>>,
}

/// Runs at most `iterations` LM iterations, updating the problem in place.
pub fn solve(camera: &Camera, bf: f64, problem: &mut Problem, iterations: u32) -> Report {
    let mut fixed = problem.fixed.clone();
    if !fixed.iter().any(|&f| f) && !fixed.is_empty() {
        fixed[0] = true;
    }
    let mut block_of = vec![usize::MAX; problem.poses.len()];
    let mut free = 0;
    for (i, f) in fixed.iter().enumerate() {
        if !f {
            block_of[i] = free;
            free += 1;
        }
    }
    let mut cost = total_cost(camera, bf, problem);
    let mut report = Report { initial_cost: cost, final_cost: cost, iterations: 0 };
    if free == 0 && problem.points.is_empty() {
        return report;
    }
    let n = 6 * free;
    let mut lambda = None::<f64>;

    // Observations grouped by point.
    let mut by_point: Vec<Vec<usize>> = vec![Vec::new(); problem.points.len()];
    for (k, (_, pi, _)) in problem.observations.iter().enumerate() {
        by_point[*pi].push(k);
    }

    // The linearisation at the current state; a rejected step leaves the state, and
    // so it, unchanged.
    let mut linearised: Option<Linearisation> = None;
    for _ in 0..iterations {
        report.iterations += 1;
        let Linearisation { hpp, bp, hll, bl, hpl } = linearised.get_or_insert_with(|| {
            let mut hpp = DMatrix::<f64>::zeros(n, n);
            let mut bp = DVector::<f64>::zeros(n);
            let mut hll = vec![Matrix3::<f64>::zeros(); problem.points.len()];
            let mut bl = vec![Vector3::<f64>::zeros(); problem.points.len()];
            let mut hpl: Vec<Option<Matrix6x3<f64>>> = vec![None; problem.observations.len()];
            for (k, (ci, pi, m)) in problem.observations.iter().enumerate() {
                let Some(lin) = linearise(camera, bf, &problem.poses[*ci], &problem.points[*pi], m) else { continue };
                let w = huber_weight(lin.chi2(m.information), m.chi2_threshold()) * m.information;
                let jl = lin.d_point.rows(0, lin.rows);
                let e = lin.error.rows(0, lin.rows);
                hll[*pi] += jl.transpose() * jl * w;
                bl[*pi] += jl.transpose() * e * w;
                let a = block_of[*ci];
                if a != usize::MAX {
                    let jp = lin.d_pose.rows(0, lin.rows);
                    let mut block = hpp.view_mut((6 * a, 6 * a), (6, 6));
                    block += jp.transpose() * jp * w;
                    let mut rhs = bp.rows_mut(6 * a, 6);
                    rhs += jp.transpose() * e * w;
                    hpl[k] = Some(jp.transpose() * jl * w);
                }
            }
            Linearisation { hpp, bp, hll, bl, hpl }
        });
        let (hpp, bp, hll, bl, hpl) = (&*hpp, &*bp, &*hll, &*bl, &*hpl);
        let lam = *lambda.get_or_insert_with(|| {
            let diag: f64 = (0..n).map(|i| hpp[(i, i)]).sum::<f64>() + hll.iter().map(|h| h.trace()).sum::<f64>();
            let count = (n + 3 * problem.points.len()).max(1) as f64;
            INITIAL_LAMBDA * diag / count
        });

        // Schur complement: S = Hpp − Σ Hpl Hll⁻¹ Hlp,  r = bp − Σ Hpl Hll⁻¹ bl.
        let mut s = hpp.clone();
        for i in 0..n {
            s[(i, i)] += lam;
        }
        let mut r = bp.clone();
        let mut hll_inv = vec![Matrix3::<f64>::zeros(); problem.points.len()];
        for (pi, obs) in by_point.iter().enumerate() {
            let damped = hll[pi] + Matrix3::identity() * lam;
            let Some(inv) = damped.try_inverse() else { continue };
            hll_inv[pi] = inv;
            for &ka in obs {
                let Some(hpl_a) = hpl[ka] else { continue };
                let a = block_of[problem.observations[ka].0];
                let t = hpl_a * inv;
                let mut ra = r.rows_mut(6 * a, 6);
                ra -= t * bl[pi];
                for &kb in obs {
                    let Some(hpl_b) = hpl[kb] else { continue };
                    let b = block_of[problem.observations[kb].0];
                    let mut block = s.view_mut((6 * a, 6 * b), (6, 6));
                    block -= t * hpl_b.transpose();
                }
            }
        }
        let dp = if n > 0 {
            match s.cholesky() {
                Some(c) => c.solve(&r),
                None => {
                    lambda = Some(lam * LAMBDA_UP);
                    continue;
                }
            }
        } else {
            DVector::zeros(0)
        };
        // Back-substitution for the points.
        let mut dl = vec![Vector3::<f64>::zeros(); problem.points.len()];
        for (pi, obs) in by_point.iter().enumerate() {
            let mut rhs = bl[pi];
            for &k in obs {
                if let Some(h) = hpl[k] {
                    let a = block_of[problem.observations[k].0];
                    rhs -= h.transpose() * dp.rows(6 * a, 6);
                }
            }
            dl[pi] = hll_inv[pi] * rhs;
        }

        let old_poses = problem.poses.clone();
        let old_points = problem.points.clone();
        for (i, pose) in problem.poses.iter_mut().enumerate() {
            let a = block_of[i];
            if a != usize::MAX {
                let d = Vector6::from_iterator(dp.rows(6 * a, 6).iter().copied());
                *pose = perturb(&d, pose);
            }
        }
        for (p, d) in problem.points.iter_mut().zip(&dl) {
            *p += d;
        }
        let new_cost = total_cost(camera, bf, problem);
        if new_cost < cost {
            let decrease = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
            cost = new_cost;
            linearised = None;
            lambda = Some(lam / LAMBDA_DOWN);
            if decrease < MIN_RELATIVE_DECREASE {
                break;
            }
        } else {
            problem.poses = old_poses;
            problem.points = old_points;
            lambda = Some(lam * LAMBDA_UP);
        }
    }
    report.final_cost = cost;
    report
}

/// Observations whose error exceeds the χ² threshold after solving.
pub fn outliers(camera: &Camera, bf: f64, problem: &Problem) -> Vec<usize> {
    problem
        .observations
        .iter()
        .enumerate()
        .filter(|(_, (ci, pi, m))| {
            residual(camera, bf, &problem.poses[*ci], &problem.points[*pi], m).is_none_or(|r| r.chi2(m.information) > m.chi2_threshold())
        })
        .map(|(k, _)| k)
        .collect()
}

/// Maps arbitrary keys to dense indices (helper for building problems).
#[derive(Default)]
pub struct Indexer<K: std::hash::Hash + Eq + Copy> {
    pub index: HashMap<K, usize>,
    pub keys: Vec<K>,
}

impl<K: std::hash::Hash + Eq + Copy> Indexer<K> {
    pub fn get_or_insert(&mut self, key: K) -> (usize, bool) {
        if let Some(&i) = self.index.get(&key) {
            return (i, false);
        }
        let i = self.keys.len();
        self.index.insert(key, i);
        self.keys.push(key);
        (i, true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point2;

    #[test]
    fn converges_to_the_true_structure_from_a_perturbed_start() {
        let camera = Camera::pinhole(640, 480, 520.0, 520.0, 320.0, 240.0, 5000.0);
        let bf = 41.6;
        let truth: Vec<Isometry3<f64>> = (0..5)
            .map(|i| Isometry3::new(Vector3::new(0.05 * i as f64, 0.01 * i as f64, 0.0), Vector3::new(0.0, 0.03 * i as f64, 0.0)))
            .collect();
        let points: Vec<Point3<f64>> = (0..300)
            .map(|i| Point3::new(((i * 37) % 300) as f64 / 150.0 - 1.0, ((i * 91) % 200) as f64 / 200.0 - 0.5, 2.0 + (i % 11) as f64 * 0.2))
            .collect();
        let mut observations = Vec::new();
        for (ci, pose) in truth.iter().enumerate() {
            for (pi, pw) in points.iter().enumerate() {
                let pc = pose * pw;
                if let Some(px) = camera.project(&pc).filter(|p| camera.contains(p)) {
                    let disparity = (pi % 2 == 0).then(|| bf / pc.z);
                    observations.push((ci, pi, Measurement { ideal: Point2::from(px.coords), disparity, information: 1.0 }));
                }
            }
        }
        let mut problem = Problem {
            poses: truth
                .iter()
                .enumerate()
                .map(|(i, p)| if i < 2 { *p } else { Isometry3::new(Vector3::new(0.01, -0.01, 0.02), Vector3::new(0.01, 0.0, -0.01)) * p })
                .collect(),
            fixed: vec![true, true, false, false, false],
            points: points.iter().enumerate().map(|(i, p)| p + Vector3::new(0.01, -0.02, 0.03) * ((i % 3) as f64 - 1.0)).collect(),
            observations,
        };
        let report = solve(&camera, bf, &mut problem, 30);
        assert!(report.final_cost < 1e-8, "{report:?}");
        for (est, t) in problem.poses.iter().zip(&truth) {
            let e = est.inverse() * t;
            assert!(e.translation.vector.norm() < 1e-6 && e.rotation.angle() < 1e-6);
        }
        assert!(outliers(&camera, bf, &problem).is_empty());
    }
}
