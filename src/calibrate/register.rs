//! Registration: bringing each station's points into one frame.
//!
//! Station poses are unknown in a campaign. The coordinates criterion
//! (Eq. 17) compares the same reflector seen from different stations after
//! "a best-fit registration of all stations into one frame"; the bundle
//! adjustment needs a first guess of every pose and position. Both come
//! from here: the closed-form best rigid fit of two point sets (Kabsch) and a
//! generalised Procrustes alignment of all stations at once.

use nalgebra::{Matrix3, Rotation3, Vector3};
use rayon::prelude::*;
use std::collections::BTreeMap;

/// A rigid transformation `x ↦ R·x + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rigid {
    pub rotation: Rotation3<f64>,
    pub translation: Vector3<f64>,
}

impl Rigid {
    pub fn identity() -> Rigid {
        Rigid {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
        }
    }
    pub fn apply(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * x + self.translation
    }
}

/// The rigid transformation that best maps `from[i]` onto `to[i]` in the
/// least-squares sense (Kabsch). `None` with fewer than 3 points or points on
/// a line.
pub fn fit(from: &[Vector3<f64>], to: &[Vector3<f64>]) -> Option<Rigid> {
    let n = from.len();
    if n < 3 || to.len() != n {
        return None;
    }
    let ca = from.iter().sum::<Vector3<f64>>() / n as f64;
    let cb = to.iter().sum::<Vector3<f64>>() / n as f64;
    let mut h = Matrix3::zeros();
    for (a, b) in from.iter().zip(to) {
        h += (a - ca) * (b - cb).transpose();
    }
    // Bounded sweeps: NaN coordinates must give `None`, not a hang.
    let svd = h.try_svd(true, true, 5.0 * f64::EPSILON, 10_000)?;
    let (u, v_t) = (svd.u?, svd.v_t?);
    let sv = svd.singular_values;
    // Points on a line leave a rotation about it free.
    if sv[1] <= 1e-12 * sv[0].max(1e-300) {
        return None;
    }
    let v = v_t.transpose();
    let d = (v * u.transpose()).determinant().signum();
    let r = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
    let rotation = Rotation3::from_matrix_unchecked(r);
    Some(Rigid {
        rotation,
        translation: cb - rotation * ca,
    })
}

/// The result of aligning several stations.
#[derive(Clone, Debug)]
pub struct Alignment {
    /// Per station: station frame → common frame.
    pub poses: Vec<Rigid>,
    /// Per target seen by any station: its position in the common frame
    /// (the mean of the registered observations).
    pub points: BTreeMap<usize, Vector3<f64>>,
    /// Whether the refinement reached its tolerance within [`MAX_PASSES`]:
    /// a registration that did not is a result to flag, not to trust.
    pub converged: bool,
    /// Refinement passes made.
    pub passes: usize,
}

/// Refinement passes at most. The alternation of mean positions and
/// per-station fits converges linearly, slowly where the stations share
/// few reflectors: on the corner campaign it needs up to ~300 passes for
/// 1e-10 mm (it stopped at 100, 7e-7 mm short, before). Each pass is
/// linear in the observations, so the bound costs little and only an
/// ill-posed registration reaches it.
pub const MAX_PASSES: usize = 10_000;

/// Generalised Procrustes: `obs[s]` maps target → point in station `s`'s
/// frame. With `anchor`, the common frame is that of the given target
/// positions (e.g. reference coordinates, at least 3 not on a line);
/// without, it is station 0's frame. `None` when some station shares fewer
/// than 3 targets (not on a line) with the stations placed before it. The
/// refinement stops when no station moves by more than `tol_mm`: a
/// registration that is itself the result asks for round-off (1e-10 mm), a
/// first guess that an adjustment refines needs far less.
pub fn align(
    obs: &[BTreeMap<usize, Vector3<f64>>],
    anchor: Option<&BTreeMap<usize, Vector3<f64>>>,
    tol_mm: f64,
) -> Option<Alignment> {
    let s_n = obs.len();
    // The maps laid out as vectors indexed by target once: the chaining
    // below looks every observation up, and the refinement runs up to
    // MAX_PASSES times over every observation; each pass must stay linear.
    let n_t = obs
        .iter()
        .flat_map(|o| o.keys())
        .chain(anchor.into_iter().flat_map(|a| a.keys()))
        .max()
        .map_or(0, |k| k + 1);
    let lists: Vec<Vec<(usize, Vector3<f64>)>> = obs
        .iter()
        .map(|o| o.iter().map(|(k, x)| (*k, *x)).collect())
        .collect();
    let mut poses = vec![Rigid::identity(); s_n];
    let mut placed = vec![false; s_n];
    let mut points: Vec<Option<Vector3<f64>>> = vec![None; n_t];
    // First guess: chain stations onto what is already placed.
    match anchor {
        Some(a) => a.iter().for_each(|(k, v)| points[*k] = Some(*v)),
        None => {
            placed[0] = true;
            lists[0].iter().for_each(|(k, v)| points[*k] = Some(*v));
        }
    }
    loop {
        let mut progress = false;
        for s in 0..s_n {
            if placed[s] {
                continue;
            }
            let (from, to): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = lists[s]
                .iter()
                .filter_map(|(k, x)| points[*k].map(|p| (*x, p)))
                .unzip();
            if let Some(p) = fit(&from, &to) {
                poses[s] = p;
                placed[s] = true;
                progress = true;
                for (k, x) in &lists[s] {
                    points[*k].get_or_insert_with(|| p.apply(x));
                }
            }
        }
        if !progress {
            break;
        }
    }
    if placed.iter().any(|p| !p) {
        return None;
    }
    // Refine: alternate mean positions and per-station fits.
    // Per target, its (station, point) in station order: each mean sums
    // them in that order, and the targets' means are formed in parallel.
    let mut by_target: Vec<Vec<(usize, Vector3<f64>)>> = vec![Vec::new(); n_t];
    for (s, o) in lists.iter().enumerate() {
        for (k, x) in o {
            by_target[*k].push((s, *x));
        }
    }
    let means = |poses: &[Rigid]| -> Vec<(Vector3<f64>, usize)> {
        by_target
            .par_iter()
            .with_min_len(64)
            .map(|seen| {
                let sum = seen
                    .iter()
                    .fold(Vector3::zeros(), |sum, (s, x)| sum + poses[*s].apply(x));
                (sum, seen.len())
            })
            .collect()
    };
    let (mut converged, mut passes) = (false, 0);
    while passes < MAX_PASSES {
        passes += 1;
        let mut new_points: Vec<Vector3<f64>> = means(&poses)
            .into_iter()
            .map(|(v, n)| v / n.max(1) as f64)
            .collect();
        if let Some(a) = anchor {
            for (k, v) in a {
                new_points[*k] = *v;
            }
        }
        // Each station's fit on its own, in parallel; taken in order.
        let fits: Vec<Option<Rigid>> = lists
            .par_iter()
            .enumerate()
            .map(|(s, o)| {
                if anchor.is_none() && s == 0 {
                    return None;
                }
                let from: Vec<Vector3<f64>> = o.iter().map(|(_, x)| *x).collect();
                let to: Vec<Vector3<f64>> = o.iter().map(|(k, _)| new_points[*k]).collect();
                fit(&from, &to)
            })
            .collect();
        let mut moved = 0.0f64;
        for (s, p) in fits.into_iter().enumerate() {
            if let Some(p) = p {
                moved = moved.max((p.translation - poses[s].translation).norm());
                poses[s] = p;
            }
        }
        if moved < tol_mm {
            converged = true;
            break;
        }
    }
    // Final means with the final poses (anchored targets keep their mean too:
    // the criterion compares observations, not the anchor).
    let points = means(&poses)
        .into_iter()
        .enumerate()
        .filter(|(_, (_, n))| *n > 0)
        .map(|(k, (v, n))| (k, v / n as f64))
        .collect();
    Some(Alignment {
        poses,
        points,
        converged,
        passes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pts() -> Vec<Vector3<f64>> {
        vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1000.0, 0.0, 10.0),
            Vector3::new(0.0, 2000.0, -30.0),
            Vector3::new(500.0, 800.0, 1200.0),
            Vector3::new(-700.0, 300.0, 400.0),
        ]
    }

    #[test]
    fn kabsch_recovers_a_rigid_motion() {
        let r = Rotation3::from_euler_angles(0.1, -0.2, 2.5);
        let t = Vector3::new(100.0, -50.0, 3.0);
        let a = pts();
        let b: Vec<Vector3<f64>> = a.iter().map(|x| r * x + t).collect();
        let f = fit(&a, &b).unwrap();
        assert!((f.rotation.matrix() - r.matrix()).norm() < 1e-12);
        assert!((f.translation - t).norm() < 1e-9);
        assert!(fit(&a[..2], &b[..2]).is_none());
        let line: Vec<Vector3<f64>> = (0..4).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(fit(&line, &line).is_none());
    }

    #[test]
    fn procrustes_aligns_three_stations() {
        let truth = pts();
        let poses = [
            Rigid::identity(),
            Rigid {
                rotation: Rotation3::from_euler_angles(0.0, 0.01, 1.0),
                translation: Vector3::new(300.0, 0.0, 0.0),
            },
            Rigid {
                rotation: Rotation3::from_euler_angles(0.02, 0.0, -2.0),
                translation: Vector3::new(0.0, 500.0, 10.0),
            },
        ];
        let obs: Vec<BTreeMap<usize, Vector3<f64>>> = poses
            .iter()
            .map(|p| {
                truth
                    .iter()
                    .enumerate()
                    .map(|(k, x)| (k, p.rotation.inverse() * (x - p.translation)))
                    .collect()
            })
            .collect();
        let a = align(&obs, None, 1e-10).unwrap();
        for (k, x) in &a.points {
            assert!((x - truth[*k]).norm() < 1e-9);
        }
    }
}
