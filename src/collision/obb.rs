//! Oriented bounding boxes and the paper's separating-axis test (§ "Collision detection
//! mechanism"): two boxes are apart if some axis L satisfies
//!
//! |L·(O_II − O_I)| > ½(W_I|L·x_I| + H_I|L·y_I| + D_I|L·z_I| + W_II|L·x_II| + H_II|L·y_II| + D_II|L·z_II|)
//!
//! The 15 candidate axes are tried in the paper's priority order: the segment axes z_I, z_II; the
//! radial axes x_I, y_I, x_II, y_II; then the nine cross products x_I×x_II, x_I×y_II, …, z_I×z_II.
//! Everything is evaluated in box I's frame (R = A_Iᵀ A_II), so the test costs a 3×3 product and
//! a few dozen multiply-adds, with no allocation.

use crate::geometry::Pose;
use nalgebra::{Matrix3, Vector3};

/// Cross-product axes shorter than this (nearly parallel edges) are skipped: the face axes
/// already decide those cases.
const DEGENERATE_CROSS: f64 = 1e-9;

/// An oriented bounding box: centre, unit axes (columns of a rotation), full edge lengths
/// (W, H, D along x, y, z) in mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Obb {
    /// Centre, mm.
    pub centre: Vector3<f64>,
    /// Unit axes x, y, z as the columns of a rotation matrix.
    pub axes: Matrix3<f64>,
    /// Full edge lengths W, H, D along x, y, z, mm.
    pub edges_mm: Vector3<f64>,
}

/// The axis that separated two boxes. `Cross(i, j)` is axis i of box I × axis j of box II, with
/// 0 = x, 1 = y, 2 = z.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SeparatingAxis {
    ZI,
    ZII,
    XI,
    YI,
    XII,
    YII,
    Cross(u8, u8),
}

impl SeparatingAxis {
    /// Position 0..15 in the paper's priority order.
    pub fn priority_index(&self) -> usize {
        match *self {
            SeparatingAxis::ZI => 0,
            SeparatingAxis::ZII => 1,
            SeparatingAxis::XI => 2,
            SeparatingAxis::YI => 3,
            SeparatingAxis::XII => 4,
            SeparatingAxis::YII => 5,
            SeparatingAxis::Cross(i, j) => 6 + 3 * usize::from(i) + usize::from(j),
        }
    }
}

impl Obb {
    /// A box centred at the pose's origin, its axes the pose's rotation; edges in mm.
    pub fn new(pose: &Pose, edges_mm: Vector3<f64>) -> Self {
        Obb {
            centre: pose.translation.vector,
            axes: *pose.rotation.to_rotation_matrix().matrix(),
            edges_mm,
        }
    }

    /// The paper's test over all 15 candidate axes in its priority order; the first separating
    /// axis found, or `None` when the boxes overlap (touching counts as overlap).
    pub fn separating_axis(&self, other: &Obb) -> Option<SeparatingAxis> {
        let a = &self.axes;
        let b = &other.axes;
        let ea = self.edges_mm * 0.5;
        let eb = other.edges_mm * 0.5;
        let d = other.centre - self.centre;
        // r[i][j] = a_i · b_j, ar = |r|; t = centre offset in box I's frame.
        let mut r = [[0.0f64; 3]; 3];
        let mut ar = [[0.0f64; 3]; 3];
        let mut t = [0.0f64; 3];
        for i in 0..3 {
            let ai = a.column(i);
            t[i] = ai.dot(&d);
            for j in 0..3 {
                let v = ai.dot(&b.column(j));
                r[i][j] = v;
                ar[i][j] = v.abs();
            }
        }
        // Face axis of box I: a_i.
        let face_i =
            |i: usize| t[i].abs() > ea[i] + eb[0] * ar[i][0] + eb[1] * ar[i][1] + eb[2] * ar[i][2];
        // Face axis of box II: b_j.
        let face_ii = |j: usize| {
            let tj = t[0] * r[0][j] + t[1] * r[1][j] + t[2] * r[2][j];
            tj.abs() > ea[0] * ar[0][j] + ea[1] * ar[1][j] + ea[2] * ar[2][j] + eb[j]
        };
        if face_i(2) {
            return Some(SeparatingAxis::ZI);
        }
        if face_ii(2) {
            return Some(SeparatingAxis::ZII);
        }
        if face_i(0) {
            return Some(SeparatingAxis::XI);
        }
        if face_i(1) {
            return Some(SeparatingAxis::YI);
        }
        if face_ii(0) {
            return Some(SeparatingAxis::XII);
        }
        if face_ii(1) {
            return Some(SeparatingAxis::YII);
        }
        // Cross axes L = a_i × b_j. In box I's frame L = e_i × (r[0][j], r[1][j], r[2][j]), so with
        // (i, k, l) cyclic: L·t = t_l r_kj − t_k r_lj, |L·a_k| = |r_lj|, |L·a_l| = |r_kj|,
        // |L·b_m| = |r_i n| for the two m ≠ j (n the third index), |L| = √(r_kj² + r_lj²).
        for i in 0..3 {
            let k = (i + 1) % 3;
            let l = (i + 2) % 3;
            for j in 0..3 {
                let m = (j + 1) % 3;
                let n = (j + 2) % 3;
                let len_sq = r[k][j] * r[k][j] + r[l][j] * r[l][j];
                if len_sq < DEGENERATE_CROSS * DEGENERATE_CROSS {
                    continue;
                }
                let dist = (t[l] * r[k][j] - t[k] * r[l][j]).abs();
                let radius =
                    ea[k] * ar[l][j] + ea[l] * ar[k][j] + eb[m] * ar[i][n] + eb[n] * ar[i][m];
                if dist > radius {
                    return Some(SeparatingAxis::Cross(i as u8, j as u8));
                }
            }
        }
        None
    }

    /// Whether the boxes overlap (or touch).
    pub fn intersects(&self, other: &Obb) -> bool {
        self.separating_axis(other).is_none()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Translation3, UnitQuaternion};
    use rand::{Rng, SeedableRng};
    use std::f64::consts::FRAC_1_SQRT_2;

    fn obb(rot: Matrix3<f64>, centre: Vector3<f64>, edges: Vector3<f64>) -> Obb {
        Obb {
            centre,
            axes: rot,
            edges_mm: edges,
        }
    }

    fn rot_z(deg: f64) -> Matrix3<f64> {
        *Rotation3::from_axis_angle(&Vector3::z_axis(), deg.to_radians()).matrix()
    }

    fn rot_x(deg: f64) -> Matrix3<f64> {
        *Rotation3::from_axis_angle(&Vector3::x_axis(), deg.to_radians()).matrix()
    }

    /// The paper's criterion written out literally with world vectors, for one axis L.
    fn separates_literally(a: &Obb, b: &Obb, l: Vector3<f64>) -> bool {
        let mut radius = 0.0;
        for k in 0..3 {
            radius += a.edges_mm[k] * l.dot(&a.axes.column(k)).abs();
            radius += b.edges_mm[k] * l.dot(&b.axes.column(k)).abs();
        }
        l.dot(&(b.centre - a.centre)).abs() > 0.5 * radius
    }

    /// The 15 axes in priority order, as world vectors (un-normalised).
    fn candidate_axes(a: &Obb, b: &Obb) -> [(SeparatingAxis, Vector3<f64>); 15] {
        let ax = |k: usize| a.axes.column(k).into_owned();
        let bx = |k: usize| b.axes.column(k).into_owned();
        let mut out = [(SeparatingAxis::ZI, Vector3::zeros()); 15];
        out[0] = (SeparatingAxis::ZI, ax(2));
        out[1] = (SeparatingAxis::ZII, bx(2));
        out[2] = (SeparatingAxis::XI, ax(0));
        out[3] = (SeparatingAxis::YI, ax(1));
        out[4] = (SeparatingAxis::XII, bx(0));
        out[5] = (SeparatingAxis::YII, bx(1));
        for i in 0..3 {
            for j in 0..3 {
                out[6 + 3 * i + j] = (SeparatingAxis::Cross(i as u8, j as u8), ax(i).cross(&bx(j)));
            }
        }
        out
    }

    fn literal_first_axis(a: &Obb, b: &Obb) -> Option<SeparatingAxis> {
        candidate_axes(a, b)
            .into_iter()
            .find(|(_, l)| l.norm() >= DEGENERATE_CROSS && separates_literally(a, b, *l))
            .map(|(axis, _)| axis)
    }

    #[test]
    fn priority_indices_follow_the_paper() {
        let a = obb(Matrix3::identity(), Vector3::zeros(), Vector3::repeat(1.0));
        for (k, (axis, _)) in candidate_axes(&a, &a).into_iter().enumerate() {
            assert_eq!(axis.priority_index(), k);
        }
    }

    #[test]
    fn face_axis_z_i() {
        let a = obb(
            Matrix3::identity(),
            Vector3::zeros(),
            Vector3::new(2.0, 3.0, 4.0),
        );
        let b = obb(
            rot_z(30.0),
            Vector3::new(0.0, 0.0, 4.1),
            Vector3::new(2.0, 3.0, 4.0),
        );
        assert_eq!(a.separating_axis(&b), Some(SeparatingAxis::ZI));
    }

    #[test]
    fn face_axis_z_ii() {
        // Box II lies on its side (z_II = −y): apart along y, overlapping along z.
        let a = obb(
            Matrix3::identity(),
            Vector3::zeros(),
            Vector3::new(2.0, 2.0, 2.0),
        );
        let b = obb(
            rot_x(90.0),
            Vector3::new(0.0, 3.1, 0.0),
            Vector3::new(2.0, 2.0, 4.0),
        );
        assert_eq!(a.separating_axis(&b), Some(SeparatingAxis::ZII));
    }

    #[test]
    fn face_axes_x_i_and_y_i() {
        let a = obb(
            Matrix3::identity(),
            Vector3::zeros(),
            Vector3::new(2.0, 2.0, 2.0),
        );
        let bx = obb(
            Matrix3::identity(),
            Vector3::new(2.5, 0.3, 0.0),
            Vector3::new(2.0, 2.0, 2.0),
        );
        assert_eq!(a.separating_axis(&bx), Some(SeparatingAxis::XI));
        let by = obb(
            Matrix3::identity(),
            Vector3::new(0.3, -2.5, 0.0),
            Vector3::new(2.0, 2.0, 2.0),
        );
        assert_eq!(a.separating_axis(&by), Some(SeparatingAxis::YI));
    }

    #[test]
    fn face_axes_x_ii_and_y_ii() {
        // Box II turned 45° about z: only its own face normals see the gap (2.6 > 1 + √2, while
        // along x and y the offset 2.6/√2 < 1 + √2).
        let a = obb(
            Matrix3::identity(),
            Vector3::zeros(),
            Vector3::new(2.0, 2.0, 2.0),
        );
        let r = rot_z(45.0);
        let bx = obb(r, r.column(0) * 2.6, Vector3::new(2.0, 2.0, 2.0));
        assert_eq!(a.separating_axis(&bx), Some(SeparatingAxis::XII));
        let by = obb(r, r.column(1) * -2.6, Vector3::new(2.0, 2.0, 2.0));
        assert_eq!(a.separating_axis(&by), Some(SeparatingAxis::YII));
    }

    /// A rotation whose column `k` is `dir` and whose other two columns lie at 45° to `up`.
    fn ridge_rotation(k: usize, dir: Vector3<f64>, up: Vector3<f64>) -> Matrix3<f64> {
        let side = up.cross(&dir);
        let p = (side + up) * FRAC_1_SQRT_2;
        let q = (up - side) * FRAC_1_SQRT_2;
        let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
        let mut m = Matrix3::zeros();
        m.set_column(k, &dir);
        m.set_column(k1, &p);
        // Right-handed: column k2 = column k × column k1.
        m.set_column(k2, &dir.cross(&p));
        assert!((m.column(k2) - q).norm() < 1e-12 || (m.column(k2) + q).norm() < 1e-12);
        m
    }

    #[test]
    fn every_cross_axis_can_be_the_first() {
        // Two crossed ridges: edge i of box I along world x at the top of box I, edge j of box II
        // along world y at the bottom of box II, 0.05 mm apart in z. Only directions near
        // x × y = z separate them, and of the 15 candidates only a_i × b_j is such a direction.
        for i in 0..3u8 {
            for j in 0..3u8 {
                let ra = ridge_rotation(i as usize, Vector3::x(), Vector3::z());
                let rb = ridge_rotation(j as usize, Vector3::y(), -Vector3::z());
                let ea = Vector3::new(3.0, 4.0, 5.0);
                let eb = Vector3::new(4.5, 3.5, 2.5);
                let reach = |e: &Vector3<f64>, k: usize| {
                    (e[(k + 1) % 3] + e[(k + 2) % 3]) * 0.5 * FRAC_1_SQRT_2
                };
                let a = obb(ra, Vector3::new(0.1, -0.2, -reach(&ea, i as usize)), ea);
                let b = obb(
                    rb,
                    Vector3::new(-0.1, 0.15, reach(&eb, j as usize) + 0.05),
                    eb,
                );
                let found = a.separating_axis(&b);
                assert_eq!(found, Some(SeparatingAxis::Cross(i, j)), "i={i} j={j}");
                assert_eq!(found, literal_first_axis(&a, &b));
                // Pushed together they overlap.
                let c = obb(rb, b.centre - Vector3::new(0.0, 0.0, 0.1), eb);
                assert_eq!(a.separating_axis(&c), None, "i={i} j={j}");
            }
        }
    }

    #[test]
    fn overlapping_boxes_have_no_separating_axis() {
        let a = obb(
            Matrix3::identity(),
            Vector3::zeros(),
            Vector3::new(2.0, 3.0, 4.0),
        );
        let b = obb(
            rot_x(20.0) * rot_z(35.0),
            Vector3::new(1.0, 1.0, 1.0),
            Vector3::new(2.0, 2.0, 2.0),
        );
        assert_eq!(a.separating_axis(&b), None);
        assert!(a.intersects(&b));
        assert!(a.intersects(&a));
        // Parallel boxes (all cross products degenerate) still work.
        let c = obb(
            Matrix3::identity(),
            Vector3::new(1.9, 0.0, 0.0),
            Vector3::new(2.0, 3.0, 4.0),
        );
        assert!(a.intersects(&c));
    }

    #[test]
    fn obb_new_uses_pose() {
        let pose = Pose::from_parts(
            Translation3::new(1.0, 2.0, 3.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.3),
        );
        let b = Obb::new(&pose, Vector3::new(1.0, 2.0, 3.0));
        assert_eq!(b.centre, Vector3::new(1.0, 2.0, 3.0));
        assert!((b.axes.column(2) - pose.rotation * Vector3::z()).norm() < 1e-15);
    }

    #[test]
    fn agrees_with_the_literal_criterion_on_random_boxes() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut separated = 0;
        for _ in 0..20_000 {
            let random_box = |rng: &mut rand_chacha::ChaCha8Rng| {
                let rot = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ));
                let centre = Vector3::new(
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-8.0..8.0),
                );
                let edges = Vector3::new(
                    rng.random_range(0.5..8.0),
                    rng.random_range(0.5..8.0),
                    rng.random_range(0.5..8.0),
                );
                obb(*rot.to_rotation_matrix().matrix(), centre, edges)
            };
            let a = random_box(&mut rng);
            let b = random_box(&mut rng);
            let found = a.separating_axis(&b);
            separated += usize::from(found.is_some());
            assert_eq!(found, literal_first_axis(&a, &b));
        }
        assert!(separated > 2_000 && separated < 18_000, "{separated}");
    }
}
