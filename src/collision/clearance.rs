//! Exact clearance of the shaft (Segment I) in the bore (Segment II), in frame {F}.
//!
//! # Geometry model
//!
//! All lengths in mm. {F}: centre of the bore entrance, z out of the bore. {M}: on the shaft axis
//! at the shoulder, z from the tip back to the shoulder; `f_m` is {M} in {F}.
//!
//! - **Shaft**: solid cylinder of radius r_s about z_M, z_M ∈ [−L, 0] (tip at −L).
//! - **Segment I's body** behind the shoulder (z_M ≥ 0, radius `body_radius`): only its shoulder
//!   face (the annulus z_M = 0, r ∈ [r_s, body_radius]) can reach Segment II.
//! - **Segment II's wall**: the points with z_F ∈ [−h, 0], h = depth + relief, at radial distance
//!   r ≥ r_b from the z_F axis. The outer radius is treated as unbounded (conservative: it can only
//!   report contact where a finite part has none, and only at lateral offsets beyond r_s + outer
//!   radius). The entrance face is the plane z_F = 0 for r ≥ r_b; the bore bottom is at z_F = −h.
//!
//! **Wall clearance** = r_b − (largest r over the part of the shaft inside the slab
//! z_F ∈ [−h, 0]); +∞ when no part of the shaft is in the slab. This covers the shaft against the
//! bore wall and against the entrance face. Shaft ∩ slab is convex and r is convex, so the maximum
//! lies on an extreme point: on the tip or shoulder rim circle (where inside the slab), or on the
//! curve where the side surface crosses z_F = 0 or z_F = −h (where within the shaft's length);
//! the flat end faces only contribute chord end points, which lie on the rims. On each curve, with
//! t = sin φ of a suitable angle parameter, r² = K + α√(1−t²) + βt + γt² (α ≥ 0) and the
//! feasible part is an interval of t, so the maximum is found exactly: the function is concave in
//! t except on one middle interval where it is convex (closed-form limits), and each concave piece
//! is maximised by safeguarded Newton on the angle, to ~1e-12 mm. Valid for any tilt < 90°.
//!
//! **Seat clearance**: the seating faces touch at insertion depth + relief, i.e. contact when any
//! point of the shoulder face reaches z_F < −relief: seat = (min z_F over the shoulder's outer
//! rim) + relief, with min z over a circle = c_z − ρ·√(1 − n_z²). The shaft's lowest point reaching
//! the bore bottom (z_F < −h) also counts as a seat contact; with L = depth the shoulder always
//! seats first, so it only matters for shafts longer than the bore.

use super::obb::Obb;
use crate::config::cell::CellConfig;
use crate::geometry::pose::{Pose, interpolate};
use nalgebra::{Isometry3, Point3, Translation3, Vector2, Vector3};

/// Thickness of the slab above the shoulder face included in Segment I's OBB, mm.
const SHOULDER_SLAB_MM: f64 = 1.0;
/// Extra growth of the swept-shaft certificate in [`clearance_along`], mm: covers rounding in
/// the interpolated rotation.
const SWEEP_SLACK_MM: f64 = 1e-9;
/// At most this many sub-intervals are examined by [`clearance_along`].
const MAX_SWEEP_NODES: usize = 2048;
/// Sub-intervals are not split below this half-width (fraction of the move).
const MIN_SWEEP_HALF: f64 = 1e-12;

/// Dimensions of the two parts, from the cell file (mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartGeometry {
    pub shaft_radius_mm: f64,
    /// Tip to shoulder.
    pub shaft_length_mm: f64,
    /// Segment I's body behind the shoulder.
    pub body_radius_mm: f64,
    pub bore_radius_mm: f64,
    pub bore_depth_mm: f64,
    pub axial_relief_mm: f64,
    pub bore_outer_radius_mm: f64,
}

impl PartGeometry {
    pub fn from_config(cell: &CellConfig) -> Self {
        PartGeometry {
            shaft_radius_mm: cell.shaft.diameter_mm / 2.0,
            shaft_length_mm: cell.shaft.engaged_length_mm,
            body_radius_mm: cell.shaft.body_diameter_mm / 2.0,
            bore_radius_mm: cell.bore.diameter_mm / 2.0,
            bore_depth_mm: cell.bore.depth_mm,
            axial_relief_mm: cell.bore.axial_relief_mm,
            bore_outer_radius_mm: cell.bore.outer_diameter_mm / 2.0,
        }
    }

    /// The centre of the tip in {F} with the shaft at `f_m` ({M} in {F}): the tip is the
    /// engaged length below {M}'s origin at the shoulder.
    fn tip_centre(&self, f_m: &Pose) -> Point3<f64> {
        f_m * Point3::new(0.0, 0.0, -self.shaft_length_mm)
    }

    /// How far the tip is below the bore's entrance (mm; negative above it) with the shaft at
    /// `f_m`.
    pub fn tip_depth_mm(&self, f_m: &Pose) -> f64 {
        -self.tip_centre(f_m).z
    }

    /// How far the tip's centre is off the bore's axis (mm) with the shaft at `f_m`.
    pub fn tip_off_axis_mm(&self, f_m: &Pose) -> f64 {
        self.tip_centre(f_m).coords.xy().norm()
    }

    /// Depth of the bore bottom below the entrance, h = depth + relief (mm).
    fn bottom_depth_mm(&self) -> f64 {
        self.bore_depth_mm + self.axial_relief_mm
    }

    /// OBB of Segment I at `f_m`, in {F}: the shaft plus a 1 mm slab above the shoulder face,
    /// as wide as the body. Contains the shaft and the shoulder face.
    pub fn shaft_obb(&self, f_m: &Pose) -> Obb {
        let width = 2.0 * self.body_radius_mm.max(self.shaft_radius_mm);
        let centre = Translation3::new(0.0, 0.0, (SHOULDER_SLAB_MM - self.shaft_length_mm) / 2.0);
        Obb::new(
            &(f_m * centre),
            Vector3::new(width, width, self.shaft_length_mm + SHOULDER_SLAB_MM),
        )
    }

    /// OBB of Segment II in {F}: the body around the bore out to the outer radius, from the
    /// entrance face (z_F = 0) down past the bottom by a wall thickness (outer − bore radius).
    pub fn bore_obb(&self) -> Obb {
        let width = 2.0 * self.bore_outer_radius_mm;
        let bottom = (self.bore_outer_radius_mm - self.bore_radius_mm).max(SHOULDER_SLAB_MM);
        let height = self.bottom_depth_mm() + bottom;
        Obb::new(
            &Isometry3::translation(0.0, 0.0, -height / 2.0),
            Vector3::new(width, width, height),
        )
    }
}

/// Signed gaps (mm): > 0 clear, ≤ 0 contact; `f64::INFINITY` when that pair cannot touch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Clearance {
    /// Shaft against the bore wall or the entrance face.
    pub wall_mm: f64,
    /// Shoulder face against the seating face (or the shaft against the bore bottom).
    pub seat_mm: f64,
}

/// Which pair of faces is in contact.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ContactKind {
    /// The shaft's solid against the bore wall or the entrance face.
    Wall,
    /// The shoulder face of Segment I on the seating face of Segment II (or the tip on the bottom).
    Seat,
}

impl Clearance {
    /// Both gaps positive (NaN counts as contact).
    pub fn is_clear(&self) -> bool {
        self.wall_mm > 0.0 && self.seat_mm > 0.0
    }

    /// The smaller gap, mm.
    pub fn min_mm(&self) -> f64 {
        if self.wall_mm.is_nan() || self.seat_mm.is_nan() {
            return f64::NAN;
        }
        self.wall_mm.min(self.seat_mm)
    }

    /// The contact, if any; the deeper one when both are in contact.
    pub fn contact_kind(&self) -> Option<ContactKind> {
        let touching = |gap: f64| gap.is_nan() || gap <= 0.0;
        let (wall, seat) = (touching(self.wall_mm), touching(self.seat_mm));
        match (wall, seat) {
            (false, false) => None,
            (true, false) => Some(ContactKind::Wall),
            (false, true) => Some(ContactKind::Seat),
            (true, true) if self.seat_mm < self.wall_mm => Some(ContactKind::Seat),
            (true, true) => Some(ContactKind::Wall),
        }
    }

    /// Element-wise minimum (NaN propagates).
    fn min_with(self, other: Clearance) -> Clearance {
        let min = |a: f64, b: f64| {
            if a.is_nan() || b.is_nan() {
                f64::NAN
            } else {
                a.min(b)
            }
        };
        Clearance {
            wall_mm: min(self.wall_mm, other.wall_mm),
            seat_mm: min(self.seat_mm, other.seat_mm),
        }
    }
}

/// Exact clearance of the shaft at pose `f_m` ({M} in {F}).
pub fn clearance(geom: &PartGeometry, f_m: &Pose) -> Clearance {
    grown_clearance(geom, f_m, 0.0, 0.0, 0.0)
}

/// The smallest clearance along a straight move from `from` to `to` (poses of {M} in {F};
/// translation lerp, rotation slerp as in [`interpolate`]), over the samples taken: the end pose,
/// the fraction where the tip's lowest point crosses the entrance plane (if it does), and the
/// midpoints of an adaptive bisection of the move. The start pose itself is not a sample. The
/// search stops at the first contact found, so a contact's value need not be the deepest.
///
/// Bound: over a sub-interval of half-width w (fraction) around its midpoint, every point p of
/// Segment I (|p| ≤ ρ in {M}) moves at most w·|Δt_xy| + w·Θ·ρ sideways and w·|Δt_z| + w·Θ·ρ
/// along z_F (Δt the move's translation, Θ its rotation angle, since the chord of a rotation by
/// φ is ≤ φ·ρ). The clearance at the midpoint recomputed with the bore radius shrunk by the
/// sideways bound, the slab grown by the axial bound and the seat faces raised by it (+1e-9 mm)
/// contains every pose of the sub-interval; if it is clear, the whole sub-interval is clear, else
/// it is split. So no contact deeper than ~1e-9 mm is missed, for any move size (5 mm / 1°
/// moves far from contact are settled by 1–3 sub-intervals). A sub-interval that cannot be
/// settled within 2048 sub-intervals or at half-width 1e-12 ends the search with its grown
/// (pessimistic, ≤ 0) clearance, so running out of budget can only report contact, never hide one.
pub fn clearance_along(geom: &PartGeometry, from: &Pose, to: &Pose) -> Clearance {
    clearance_along_grown(geom, from, to, &Growth::default())
}

/// How far every point of Segment I may be from where its pose puts it (mm, in {F}): the
/// envelope of the poses an uncertain estimate allows.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Growth {
    /// Sideways (across the bore axis).
    pub sideways_mm: f64,
    /// Along the bore axis, for the shaft against the wall and the entrance face.
    pub axial_mm: f64,
    /// Along the bore axis, for the shoulder against the seating face.
    pub seat_mm: f64,
}

/// The clearance of every pose within `growth` of `f_m`: a lower bound on the clearance of
/// Segment I wherever its points lie within `growth` of where `f_m` puts them.
pub fn clearance_grown(geom: &PartGeometry, f_m: &Pose, growth: &Growth) -> Clearance {
    grown_clearance(
        geom,
        f_m,
        growth.sideways_mm,
        growth.axial_mm,
        growth.seat_mm,
    )
}

/// [`clearance_along`] for the shaft grown by `growth` at every pose of the move: a lower
/// bound on the clearance along the move of any Segment I within `growth` of it.
pub fn clearance_along_grown(
    geom: &PartGeometry,
    from: &Pose,
    to: &Pose,
    growth: &Growth,
) -> Clearance {
    let mut acc = clearance_grown(geom, to, growth);
    if !acc.is_clear() {
        return acc;
    }
    if let Some(s) = tip_crossing_fraction(geom, from, to) {
        acc = acc.min_with(clearance_grown(geom, &interpolate(from, to, s), growth));
        if !acc.is_clear() {
            return acc;
        }
    }
    let dt = to.translation.vector - from.translation.vector;
    let dt_xy = (dt.x * dt.x + dt.y * dt.y).sqrt();
    let dt_z = dt.z.abs();
    let relative = from.rotation.inverse() * to.rotation;
    let theta = 2.0 * relative.imag().norm().atan2(relative.w.abs());
    let reach_shaft = geom.shaft_length_mm.hypot(geom.shaft_radius_mm);
    let reach_seat = reach_shaft.max(geom.body_radius_mm);

    // Depth-first bisection; each level adds at most one pending interval.
    let mut stack = [(0.0f64, 1.0f64); 64];
    let mut len = 1;
    let mut nodes = 0;
    while len > 0 {
        len -= 1;
        let (a, b) = stack[len];
        let mid = 0.5 * (a + b);
        let half = 0.5 * (b - a);
        let pose = interpolate(from, to, mid);
        acc = acc.min_with(clearance_grown(geom, &pose, growth));
        if !acc.is_clear() {
            return acc;
        }
        nodes += 1;
        let turn = theta * half;
        let grown = grown_clearance(
            geom,
            &pose,
            growth.sideways_mm + dt_xy * half + turn * reach_shaft + SWEEP_SLACK_MM,
            growth.axial_mm + dt_z * half + turn * reach_shaft + SWEEP_SLACK_MM,
            growth.seat_mm + dt_z * half + turn * reach_seat + SWEEP_SLACK_MM,
        );
        if grown.is_clear() {
            continue;
        }
        if nodes >= MAX_SWEEP_NODES || half < MIN_SWEEP_HALF || len + 2 > stack.len() {
            // Cannot settle it: report the pessimistic bound (a contact).
            return acc.min_with(grown);
        }
        stack[len] = (mid, b);
        stack[len + 1] = (a, mid);
        len += 2;
    }
    acc
}

/// z_F of the lowest point of the shaft's tip rim at `f_m`.
fn tip_low_z(geom: &PartGeometry, f_m: &Pose) -> f64 {
    let a = f_m.rotation * Vector3::z();
    f_m.translation.vector.z - geom.shaft_length_mm * a.z - geom.shaft_radius_mm * a.x.hypot(a.y)
}

/// The fraction of the move at which the tip's lowest point crosses z_F = 0, if the two ends
/// lie on different sides (Illinois regula falsi).
fn tip_crossing_fraction(geom: &PartGeometry, from: &Pose, to: &Pose) -> Option<f64> {
    let f = |s: f64| tip_low_z(geom, &interpolate(from, to, s));
    let (mut a, mut b) = (0.0, 1.0);
    let (mut fa, mut fb) = (f(a), f(b));
    if (fa > 0.0) == (fb > 0.0) || !fa.is_finite() || !fb.is_finite() {
        return None;
    }
    let mut side = 0;
    for _ in 0..60 {
        let s = (a * fb - b * fa) / (fb - fa);
        let fs = f(s);
        if fs.abs() < 1e-10 || b - a < 1e-14 {
            return Some(s);
        }
        if (fs > 0.0) == (fa > 0.0) {
            a = s;
            fa = fs;
            if side == -1 {
                fb *= 0.5;
            }
            side = -1;
        } else {
            b = s;
            fb = fs;
            if side == 1 {
                fa *= 0.5;
            }
            side = 1;
        }
    }
    Some(0.5 * (a + b))
}

/// The shaft's axis in {F}, with a horizontal frame: `d` along the axis' horizontal part,
/// `e1` = ẑ × d.
struct AxisFrame {
    centre: Vector3<f64>,
    a: Vector3<f64>,
    sigma: f64,
    d: Vector2<f64>,
    e1: Vector2<f64>,
}

impl AxisFrame {
    fn new(f_m: &Pose) -> Self {
        let a = f_m.rotation * Vector3::z();
        let sigma = a.x.hypot(a.y);
        let d = if sigma > 0.0 {
            Vector2::new(a.x / sigma, a.y / sigma)
        } else {
            Vector2::new(1.0, 0.0)
        };
        AxisFrame {
            centre: f_m.translation.vector,
            a,
            sigma,
            d,
            e1: Vector2::new(-d.y, d.x),
        }
    }
}

/// Clearance with the bore radius shrunk by `dxy`, the slab grown by `dz` at both faces and
/// the seating faces raised by `dz_seat` (all 0 for the exact clearance).
fn grown_clearance(geom: &PartGeometry, f_m: &Pose, dxy: f64, dz: f64, dz_seat: f64) -> Clearance {
    let frame = AxisFrame::new(f_m);
    let h = geom.bottom_depth_mm();
    let wall_mm = match max_radius_sq(geom, &frame, -h - dz, dz) {
        Some(r_sq) => geom.bore_radius_mm - dxy - r_sq.max(0.0).sqrt(),
        None => f64::INFINITY,
    };
    let cz = frame.centre.z;
    let shoulder = cz - geom.body_radius_mm.max(geom.shaft_radius_mm) * frame.sigma;
    let shaft_low =
        cz.min(cz - geom.shaft_length_mm * frame.a.z) - geom.shaft_radius_mm * frame.sigma;
    let seat_mm = (shoulder + geom.axial_relief_mm).min(shaft_low + h) - dz_seat;
    Clearance { wall_mm, seat_mm }
}

/// Largest r² (squared distance from the z_F axis) over the shaft's points with
/// z_F ∈ [z_lo, z_hi]; `None` if there are none.
fn max_radius_sq(geom: &PartGeometry, f: &AxisFrame, z_lo: f64, z_hi: f64) -> Option<f64> {
    let r = geom.shaft_radius_mm;
    let len = geom.shaft_length_mm;
    let mut best: Option<f64> = None;
    let mut take = |v: Option<f64>| {
        if let Some(v) = v {
            best = Some(best.map_or(v, |b: f64| b.max(v)));
        }
    };
    // Rim circles at s = −L (tip) and s = 0 (shoulder end): X = C + r(cos φ e1 + sin φ e2) with
    // e2 = (−a_z d, σ): X_xy = C_xy + r cos φ e1 − r a_z sin φ d, X_z = C_z + rσ sin φ.
    for s in [-len, 0.0] {
        let c = f.centre + f.a * s;
        let cxy = Vector2::new(c.x, c.y);
        let (q1, q2) = (cxy.dot(&f.e1), cxy.dot(&f.d));
        let (lo, hi) = if r * f.sigma > 0.0 {
            ((z_lo - c.z) / (r * f.sigma), (z_hi - c.z) / (r * f.sigma))
        } else if c.z >= z_lo && c.z <= z_hi {
            (-1.0, 1.0)
        } else {
            continue;
        };
        let k = cxy.norm_squared() + r * r;
        let g = max_trig(
            2.0 * r * q1.abs(),
            -2.0 * r * f.a.z * q2,
            -r * r * f.sigma * f.sigma,
            lo,
            hi,
        );
        take(g.map(|g| k + g));
    }
    // Side surface ∩ plane z_F = z0: the axial position is s = s0 − (rσ/a_z) t, and
    // X_xy = Q0 + r cos φ e1 − (r/a_z) t d with Q0 = c_xy + s0 a_xy. At a_z ≈ 0 the cross-section
    // is a rectangle whose corners lie on the rims, already covered.
    if f.a.z.abs() > 1e-12 {
        for z0 in [z_lo, z_hi] {
            let s0 = (z0 - f.centre.z) / f.a.z;
            let q = Vector2::new(f.centre.x + s0 * f.a.x, f.centre.y + s0 * f.a.y);
            let (q1, q2) = (q.dot(&f.e1), q.dot(&f.d));
            let slope = r * f.sigma / f.a.z;
            let (lo, hi) = if slope != 0.0 {
                let (t1, t2) = (s0 / slope, (s0 + len) / slope);
                (t1.min(t2), t1.max(t2))
            } else if (-len..=0.0).contains(&s0) {
                (-1.0, 1.0)
            } else {
                continue;
            };
            let k = q.norm_squared() + r * r;
            let g = max_trig(
                2.0 * r * q1.abs(),
                -2.0 * r * q2 / f.a.z,
                r * r * f.sigma * f.sigma / (f.a.z * f.a.z),
                lo,
                hi,
            );
            take(g.map(|g| k + g));
        }
    }
    best
}

/// Maximum of g(t) = α√(1−t²) + βt + γt² over t ∈ [lo, hi] ∩ [−1, 1] (α ≥ 0), or `None` if
/// that interval is empty. g'' = 2γ − α(1−t²)^(−3/2) is largest at t = 0, so g is concave on
/// [−1, 1] or on [−1, −t_s] and [t_s, 1] with t_s = √(1 − (α/2γ)^(2/3)), convex between.
fn max_trig(alpha: f64, beta: f64, gamma: f64, lo: f64, hi: f64) -> Option<f64> {
    let lo = lo.max(-1.0);
    let hi = hi.min(1.0);
    if lo.is_nan() || hi.is_nan() || lo > hi {
        return None;
    }
    let g = |t: f64| alpha * ((1.0 - t) * (1.0 + t)).max(0.0).sqrt() + beta * t + gamma * t * t;
    let mut best = g(lo).max(g(hi));
    if gamma > 0.0 && alpha < 2.0 * gamma {
        let ts = (1.0 - (alpha / (2.0 * gamma)).powi(2).cbrt())
            .max(0.0)
            .sqrt();
        for t in [-ts, ts] {
            if t > lo && t < hi {
                best = best.max(g(t));
            }
        }
        best = best.max(concave_piece_max(alpha, beta, gamma, lo, hi.min(-ts)));
        best = best.max(concave_piece_max(alpha, beta, gamma, lo.max(ts), hi));
    } else {
        best = best.max(concave_piece_max(alpha, beta, gamma, lo, hi));
    }
    Some(best)
}

/// Interior maximum of g on [lo, hi] where g is concave, −∞ if g' does not change sign there
/// (the maximum is then at an end, which the caller evaluates). Safeguarded Newton on
/// G(φ) = α cos φ + β sin φ + γ sin²φ = g(sin φ), φ ∈ [−π/2, π/2], bracketed in t = sin φ.
fn concave_piece_max(alpha: f64, beta: f64, gamma: f64, lo: f64, hi: f64) -> f64 {
    if lo.is_nan() || hi.is_nan() || lo >= hi {
        return f64::NEG_INFINITY;
    }
    // G'(φ) = cos φ · g'(sin φ), same sign as g' inside the interval.
    let d1 = |s: f64, c: f64| -alpha * s + beta * c + 2.0 * gamma * s * c;
    let cos_of = |t: f64| ((1.0 - t) * (1.0 + t)).max(0.0).sqrt();
    if !(d1(lo, cos_of(lo)) > 0.0 && d1(hi, cos_of(hi)) < 0.0) {
        return f64::NEG_INFINITY;
    }
    let (mut lo, mut hi) = (lo, hi);
    // The root without the γ term, φ = atan2(β, α), is a good start for small tilts.
    let norm = alpha.hypot(beta);
    let guess = if norm > 0.0 { beta / norm } else { 0.0 };
    let mut x = if guess > lo && guess < hi {
        beta.atan2(alpha)
    } else {
        (0.5 * (lo + hi)).asin()
    };
    for _ in 0..100 {
        let (s, c) = x.sin_cos();
        if !(s > lo && s < hi) {
            // Only after a Newton step that left the bracket: bisect instead.
            if hi - lo < 1e-15 {
                break;
            }
            x = (0.5 * (lo + hi)).asin();
            continue;
        }
        let g1 = d1(s, c);
        if g1 > 0.0 {
            lo = s;
        } else if g1 < 0.0 {
            hi = s;
        } else {
            break;
        }
        let g2 = -alpha * c - beta * s + 2.0 * gamma * (c * c - s * s);
        if g2 < 0.0 {
            let step = g1 / g2;
            x -= step;
            if step.abs() < 1e-12 {
                break;
            }
        } else {
            x = (0.5 * (lo + hi)).asin();
        }
        if hi - lo < 1e-15 {
            break;
        }
    }
    let (s, c) = x.sin_cos();
    alpha * c + beta * s + gamma * s * s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose::{pose_from_mm_deg, rotation_x_deg};
    use nalgebra::{Translation3, UnitQuaternion};

    fn geom() -> PartGeometry {
        PartGeometry::from_config(&CellConfig::reference())
    }

    fn at(x: f64, y: f64, z: f64) -> Pose {
        Isometry3::translation(x, y, z)
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    #[test]
    fn reference_geometry() {
        let g = geom();
        assert!(close(g.shaft_radius_mm, 84.95));
        assert!(close(g.bore_radius_mm, 85.0));
        assert!(close(g.body_radius_mm, 115.0));
        assert!(close(g.bore_outer_radius_mm, 115.0));
        assert!(close(g.shaft_length_mm, 60.0) && close(g.bore_depth_mm, 60.0));
    }

    #[test]
    fn docked() {
        let c = clearance(&geom(), &Pose::identity());
        assert!(close(c.wall_mm, 0.05), "{c:?}");
        assert!(close(c.seat_mm, 0.5), "{c:?}");
        assert!(c.is_clear());
        assert_eq!(c.contact_kind(), None);
        assert!(close(c.min_mm(), 0.05));
    }

    #[test]
    fn centred_and_offset_inserted() {
        let g = geom();
        let c = clearance(&g, &at(0.0, 0.0, 30.0));
        assert!(close(c.wall_mm, 0.05), "{c:?}");
        assert!(close(c.seat_mm, 30.5), "{c:?}");
        let c = clearance(&g, &at(0.03, 0.0, 30.0));
        assert!(close(c.wall_mm, 0.02), "{c:?}");
        let c = clearance(&g, &at(0.0, -0.03, 10.0));
        assert!(close(c.wall_mm, 0.02), "{c:?}");
        let c = clearance(&g, &at(0.06, 0.0, 30.0));
        assert!(close(c.wall_mm, -0.01), "{c:?}");
        assert!(!c.is_clear());
        assert_eq!(c.contact_kind(), Some(ContactKind::Wall));
    }

    #[test]
    fn over_inserted_seats() {
        let g = geom();
        let c = clearance(&g, &at(0.0, 0.0, -0.6));
        assert!(close(c.seat_mm, -0.1), "{c:?}");
        assert_eq!(c.contact_kind(), Some(ContactKind::Seat));
        // Inside the success band: clear.
        assert!(clearance(&g, &at(0.0, 0.0, -0.05)).is_clear());
        assert!(clearance(&g, &at(0.0, 0.0, 0.05)).is_clear());
    }

    #[test]
    fn tip_above_entrance_cannot_touch_the_wall() {
        let g = geom();
        // Tip 1 mm above the entrance, 50 mm off the axis.
        let c = clearance(&g, &at(50.0, 0.0, 61.0));
        assert_eq!(c.wall_mm, f64::INFINITY);
        assert!(close(c.seat_mm, 61.5));
        assert!(c.is_clear());
        // Lowered 2 mm: the tip lands on the entrance face.
        let c = clearance(&g, &at(50.0, 0.0, 59.0));
        assert!(close(c.wall_mm, 85.0 - (50.0 + 84.95)), "{c:?}");
        assert_eq!(c.contact_kind(), Some(ContactKind::Wall));
    }

    #[test]
    fn tilted_tip_rim_dips_onto_the_face() {
        let g = geom();
        // Tip centre 2 mm above the entrance, 100 mm off the axis: clear when upright.
        let upright = at(100.0, 0.0, 62.0);
        assert_eq!(clearance(&g, &upright).wall_mm, f64::INFINITY);
        // Tilted 5° about y the tip centre stays ~2 mm up but its rim dips ~7.4 mm down.
        let rot = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 5f64.to_radians());
        let tip_centre = Vector3::new(100.0, 0.0, 2.0);
        let origin = tip_centre + rot * Vector3::new(0.0, 0.0, 60.0);
        let tilted = Pose::from_parts(Translation3::from(origin), rot);
        let c = clearance(&g, &tilted);
        assert!(c.wall_mm < -90.0, "{c:?}");
        assert_eq!(c.contact_kind(), Some(ContactKind::Wall));
    }

    #[test]
    fn tilted_at_full_insertion_matches_hand_formula() {
        // Tilt θ about x at the docked position: the farthest point of the shaft is on the tip
        // rim, r = L sin θ + r_s cos θ (it lies at z = −L cos θ + r_s sin θ, inside the slab).
        let g = geom();
        for deg in [0.005, 0.02, 0.03, 0.1, 1.0, 3.0] {
            let c = clearance(&g, &rotation_x_deg(deg));
            let th = f64::to_radians(deg);
            let expected = 85.0 - (60.0 * th.sin() + 84.95 * th.cos());
            assert!(
                (c.wall_mm - expected).abs() < 1e-9,
                "{deg}: {c:?} vs {expected}"
            );
            // The shoulder's outer rim dips by 115 sin θ.
            assert!(
                (c.seat_mm - (0.5 - 115.0 * th.sin())).abs() < 1e-9,
                "{deg}: {c:?}"
            );
        }
        assert!(clearance(&g, &rotation_x_deg(0.03)).is_clear());
        assert!(!clearance(&g, &rotation_x_deg(0.1)).is_clear());
    }

    #[test]
    fn tilted_with_centred_tip_peaks_at_the_entrance_plane() {
        // Tip centred at z = −30, tilt θ about x, so the shaft leans out towards −y above it.
        // The cross-section at z = 0 is an ellipse centred at y = −30 tan θ with semi-axis
        // r_s / cos θ along y; its far end, r = 30 tan θ + r_s / cos θ, is the farthest point
        // in the slab (the side-surface/entrance-plane curve, not a rim) while it lies on the
        // shaft: (30 + r_s sin θ) / cos θ ≤ 60, i.e. θ below ~16°.
        let g = geom();
        for deg in [0.005, 0.02, 0.5, 2.0, 10.0] {
            let th = f64::to_radians(deg);
            let rot = rotation_x_deg(deg);
            let shoulder = Vector3::new(0.0, 0.0, -30.0) + rot * Vector3::new(0.0, 0.0, 60.0);
            let pose = Isometry3::from_parts(Translation3::from(shoulder), rot.rotation);
            let expected = 85.0 - (30.0 * th.tan() + 84.95 / th.cos());
            let c = clearance(&g, &pose);
            assert!(
                (c.wall_mm - expected).abs() < 1e-9,
                "{deg}: {c:?} vs {expected}"
            );
        }
    }

    #[test]
    fn clearance_along_straight_moves() {
        let g = geom();
        // Sliding sideways inside the bore within the clearance: clear.
        let along = clearance_along(&g, &at(-0.04, 0.0, 30.0), &at(0.04, 0.0, 30.0));
        assert!(along.is_clear() && close(along.wall_mm, 0.01), "{along:?}");
        // Aligned insertion of 5 mm: clear, smallest gap the radial clearance less the offset.
        let along = clearance_along(&g, &at(0.01, 0.0, 40.0), &at(0.01, 0.0, 35.0));
        assert!(along.is_clear() && close(along.wall_mm, 0.04), "{along:?}");
        // Diagonal entry: starts above the entrance 5 mm off axis, ends centred 5 mm inside.
        // Both ends are clear; the tip lands on the entrance face on the way.
        let (from, to) = (at(5.0, 0.0, 61.0), at(0.0, 0.0, 55.0));
        assert!(clearance(&g, &from).is_clear() && clearance(&g, &to).is_clear());
        let along = clearance_along(&g, &from, &to);
        assert_eq!(along.contact_kind(), Some(ContactKind::Wall), "{along:?}");
        // Moving away from the parts: clear, and the wall cannot be touched.
        let along = clearance_along(&g, &at(10.0, 0.0, 70.0), &at(12.0, 3.0, 74.0));
        assert_eq!(along.wall_mm, f64::INFINITY);
        assert!(along.is_clear());
    }

    #[test]
    fn clearance_along_catches_a_contact_the_crossing_sample_misses() {
        // Entering tilted 1° about y with 0.3 mm offset: when the rim's lowest point (on the −x
        // side, pulled towards the axis) crosses the entrance the shaft is still clear; a moment
        // later the high side, outside r_b, reaches the face. The move ends centred and upright.
        let g = geom();
        let rot = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), (-1f64).to_radians());
        let tip = Vector3::new(0.3, 0.0, 1.6);
        let from = Pose::from_parts(
            Translation3::from(tip + rot * Vector3::new(0.0, 0.0, 60.0)),
            rot,
        );
        let to = at(0.0, 0.0, 58.0);
        assert!(clearance(&g, &from).is_clear() && clearance(&g, &to).is_clear());
        let s = tip_crossing_fraction(&g, &from, &to).unwrap();
        assert!(clearance(&g, &interpolate(&from, &to, s)).is_clear());
        let touching = (1..1000)
            .filter(|k| !clearance(&g, &interpolate(&from, &to, f64::from(*k) / 1000.0)).is_clear())
            .count();
        assert!(touching > 0);
        assert!(!clearance_along(&g, &from, &to).is_clear());
    }

    #[test]
    fn obbs_contain_the_solids() {
        let g = geom();
        let bore = g.bore_obb();
        assert!(close(bore.centre.z, -(60.5 + 30.0) / 2.0));
        assert!(close(bore.edges_mm.x, 230.0));
        let pose = pose_from_mm_deg(Vector3::new(3.0, -2.0, 40.0), Vector3::new(2.0, -1.0, 0.5));
        let shaft = g.shaft_obb(&pose);
        // Tip rim and shoulder rim points lie inside the shaft OBB.
        for k in 0..36 {
            let phi = f64::from(k) * 10f64.to_radians();
            for (z, rho) in [(-60.0, 84.95), (0.0, 84.95), (0.0, 115.0)] {
                let p = pose * nalgebra::Point3::new(rho * phi.cos(), rho * phi.sin(), z);
                let local = shaft.axes.transpose() * (p.coords - shaft.centre);
                for i in 0..3 {
                    assert!(local[i].abs() <= shaft.edges_mm[i] / 2.0 + 1e-9);
                }
            }
        }
        // Far above: the boxes are apart and the parts clear.
        assert!(!g.shaft_obb(&at(0.0, 0.0, 70.0)).intersects(&bore));
        assert!(g.shaft_obb(&Pose::identity()).intersects(&bore));
    }

    #[test]
    fn max_trig_matches_dense_search() {
        let cases = [
            (1.0, 0.3, -0.2, -1.0, 1.0),
            (0.1, 0.0, 1.0, -1.0, 1.0),
            (0.0, 0.5, 2.0, -0.3, 0.9),
            (0.3, -0.2, 1.0, -0.8, 0.2),
            (2.0, 5.0, 0.01, -1.0, 1.0),
            (0.5, 0.0, 0.0, 0.1, 0.1),
        ];
        for (a, b, c, lo, hi) in cases {
            let got = max_trig(a, b, c, lo, hi).unwrap();
            let mut want = f64::NEG_INFINITY;
            for k in 0..=200_000 {
                let t = lo + (hi - lo) * f64::from(k) / 200_000.0;
                want = want.max(a * (1.0 - t * t).max(0.0).sqrt() + b * t + c * t * t);
            }
            assert!(got >= want - 1e-12 && got - want < 1e-6, "{got} {want}");
        }
        assert_eq!(max_trig(1.0, 0.0, 0.0, 1.5, 2.0), None);
    }
}
