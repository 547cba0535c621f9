//! Pinhole cameras and poses. OpenCV axes (x right, y down, z forward); poses are
//! camera-to-world. Pixel (u, v) with integer u, v is a pixel centre. Ray directions are not
//! normalised: in camera space d = ((u - cx)/fx, (v - cy)/fy, 1), so the sample parameter t
//! along a ray is camera-z depth.
//!
//! Points and directions cross the API as `[f32; 3]` (the GPU ABI's words); inside, the
//! products are written with `glam`'s [`Vec3`] operators, which are component-wise `f32`
//! multiplies and adds in the written order (no fused multiply-add, no method that goes
//! through `sqrt`), so they give the same bits on the CPU and in the shaders.

use glam::Vec3;

/// Pinhole intrinsics of an image of `width` x `height` pixels.
///
/// # Examples
///
/// ```rust
/// use himap_core::camera::Intrinsics;
///
/// let k = Intrinsics { width: 640, height: 480, fx: 525.0, fy: 525.0, cx: 319.5, cy: 239.5 };
/// // A point on the optical axis lands on the principal point.
/// assert_eq!(k.project([0.0, 0.0, 2.0]), (319.5, 239.5, 2.0));
/// // The ray through a pixel, scaled by a depth, projects back onto that pixel.
/// let d = k.direction(100.0, 50.0);
/// let (u, v, z) = k.project([d[0] * 3.0, d[1] * 3.0, d[2] * 3.0]);
/// assert!((u - 100.0).abs() < 1e-3 && (v - 50.0).abs() < 1e-3 && z == 3.0);
/// // Halving the resolution halves the focal length and keeps pixel centres on integers.
/// let h = k.resized(320, 240);
/// assert_eq!((h.fx, h.cx, h.cy), (262.5, 159.5, 119.5));
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Intrinsics {
    /// Image width (pixels).
    pub width: u32,
    /// Image height (pixels).
    pub height: u32,
    /// Horizontal focal length (pixels).
    pub fx: f32,
    /// Vertical focal length (pixels).
    pub fy: f32,
    /// Principal point, horizontal coordinate (pixels; integer values are pixel centres).
    pub cx: f32,
    /// Principal point, vertical coordinate (pixels; integer values are pixel centres).
    pub cy: f32,
}

impl Intrinsics {
    /// Intrinsics after resizing the image to `width` x `height` (pixel centres kept at
    /// integers: c' = (c + 0.5) * s - 0.5).
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let sx = crate::math::div(width as f32, self.width as f32);
        let sy = crate::math::div(height as f32, self.height as f32);
        Self {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
        }
    }

    /// Intrinsics after cropping `edge` pixels from every border.
    pub fn cropped(&self, edge: u32) -> Self {
        Self {
            width: self.width.saturating_sub(2 * edge),
            height: self.height.saturating_sub(2 * edge),
            fx: self.fx,
            fy: self.fy,
            cx: self.cx - edge as f32,
            cy: self.cy - edge as f32,
        }
    }

    /// Camera-space direction (z = 1) through pixel coordinates (u, v).
    #[inline]
    pub fn direction(&self, u: f32, v: f32) -> [f32; 3] {
        [
            crate::math::div(u - self.cx, self.fx),
            crate::math::div(v - self.cy, self.fy),
            1.0,
        ]
    }

    /// Projects a camera-space point; returns (u, v, z). z <= 0 means behind the camera.
    #[inline]
    pub fn project(&self, p: [f32; 3]) -> (f32, f32, f32) {
        let z = p[2];
        (
            crate::math::div(self.fx * p[0], z) + self.cx,
            crate::math::div(self.fy * p[1], z) + self.cy,
            z,
        )
    }
}

/// Read access to a sequence of camera poses: a slice on the CPU, storage-buffer words on a
/// GPU (which cannot build slices of local arrays). Past the end reads [`Pose::IDENTITY`].
pub trait PoseRead {
    /// Number of poses in the sequence.
    fn count(&self) -> usize;
    /// Pose `i`, or [`Pose::IDENTITY`] when `i` is past the end.
    fn pose(&self, i: usize) -> Pose;
}

impl PoseRead for [Pose] {
    #[inline(always)]
    fn count(&self) -> usize {
        self.len()
    }

    #[inline(always)]
    fn pose(&self, i: usize) -> Pose {
        if i < self.len() {
            self[i]
        } else {
            Pose::IDENTITY
        }
    }
}

/// A rigid camera-to-world transform, stored as the top 3x4 of the row-major 4x4 matrix.
///
/// # Examples
///
/// ```rust
/// use himap_core::camera::{Intrinsics, Pose};
///
/// // Camera at (1, 2, 3) (metres), turned 90 degrees about the world y axis.
/// let pose = Pose {
///     m: [
///         [0.0, 0.0, 1.0, 1.0],
///         [0.0, 1.0, 0.0, 2.0],
///         [-1.0, 0.0, 0.0, 3.0],
///     ],
/// };
/// assert!(pose.is_rigid(1e-5));
/// assert_eq!(pose.origin(), [1.0, 2.0, 3.0]);
/// // The camera looks along its +z axis, which is world +x here.
/// assert_eq!(pose.transform([0.0, 0.0, 2.0]), [3.0, 2.0, 3.0]);
/// // World -> camera -> world is a round trip.
/// let p = [0.5, -1.0, 4.0];
/// assert_eq!(pose.transform(pose.inverse_transform(p)), p);
/// // A point at depth t on the ray through a pixel projects back onto that pixel.
/// let k = Intrinsics { width: 640, height: 480, fx: 525.0, fy: 525.0, cx: 319.5, cy: 239.5 };
/// let (o, d) = pose.ray(&k, 100.0, 50.0);
/// let t = 2.5;
/// let world = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
/// let (u, v, z) = k.project(pose.inverse_transform(world));
/// assert!((u - 100.0).abs() < 1e-3 && (v - 50.0).abs() < 1e-3 && (z - t).abs() < 1e-5);
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Pose {
    /// Rows of `[R | t]`: `R` rotates camera axes into the world, `t` is the camera centre
    /// (metres, world coordinates).
    pub m: [[f32; 4]; 3],
}

impl Pose {
    /// The identity transform (camera frame = world frame).
    pub const IDENTITY: Pose = Pose {
        m: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
    };

    /// Camera centre in world coordinates.
    #[inline]
    pub fn origin(&self) -> [f32; 3] {
        [self.m[0][3], self.m[1][3], self.m[2][3]]
    }

    /// Column `j` of the rotation (the camera's axis `j` in world coordinates).
    #[inline]
    fn axis(&self, j: usize) -> Vec3 {
        Vec3::new(self.m[0][j], self.m[1][j], self.m[2][j])
    }

    /// Row `i` of the rotation.
    #[inline]
    fn row(&self, i: usize) -> Vec3 {
        Vec3::new(self.m[i][0], self.m[i][1], self.m[i][2])
    }

    /// The translation (camera centre).
    #[inline]
    fn translation(&self) -> Vec3 {
        self.axis(3)
    }

    /// Rotates a camera-space vector into the world: `R d`, component `i` summed as
    /// `(m[i][0] d.x + m[i][1] d.y) + m[i][2] d.z`.
    #[inline]
    pub fn rotate(&self, d: [f32; 3]) -> [f32; 3] {
        let d = Vec3::from_array(d);
        (self.axis(0) * d.x + self.axis(1) * d.y + self.axis(2) * d.z).to_array()
    }

    /// Transforms a camera-space point into the world.
    #[inline]
    pub fn transform(&self, p: [f32; 3]) -> [f32; 3] {
        (Vec3::from_array(self.rotate(p)) + self.translation()).to_array()
    }

    /// Transforms a world point into camera space (inverse of a rigid transform: R^T (p - t)).
    #[inline]
    pub fn inverse_transform(&self, p: [f32; 3]) -> [f32; 3] {
        let q = Vec3::from_array(p) - self.translation();
        (self.row(0) * q.x + self.row(1) * q.y + self.row(2) * q.z).to_array()
    }

    /// World-space ray (origin, unnormalised direction whose camera-z component is 1) through
    /// pixel (u, v).
    #[inline]
    pub fn ray(&self, k: &Intrinsics, u: f32, v: f32) -> ([f32; 3], [f32; 3]) {
        (self.origin(), self.rotate(k.direction(u, v)))
    }

    /// Whether the rotation part is orthonormal with determinant +1 (within `tol`) and every
    /// entry is finite.
    pub fn is_rigid(&self, tol: f32) -> bool {
        let m = &self.m;
        let mut finite = true;
        for row in m {
            for x in row {
                finite &= x.is_finite();
            }
        }
        if !finite {
            return false;
        }
        let (c0, c1, c2) = (self.axis(0), self.axis(1), self.axis(2));
        let det = c0.cross(c1).dot(c2);
        (c0.length_squared() - 1.0).abs() < tol
            && (c1.length_squared() - 1.0).abs() < tol
            && (c2.length_squared() - 1.0).abs() < tol
            && c0.dot(c1).abs() < tol
            && c0.dot(c2).abs() < tol
            && c1.dot(c2).abs() < tol
            && (det - 1.0).abs() < tol
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_inverts_ray() {
        let k = Intrinsics {
            width: 640,
            height: 480,
            fx: 525.0,
            fy: 525.0,
            cx: 319.5,
            cy: 239.5,
        };
        // 90 degrees about y, translated.
        let pose = Pose {
            m: [
                [0.0, 0.0, 1.0, 1.0],
                [0.0, 1.0, 0.0, 2.0],
                [-1.0, 0.0, 0.0, 3.0],
            ],
        };
        assert!(pose.is_rigid(1e-5));
        let (o, d) = pose.ray(&k, 100.0, 50.0);
        let t = 2.5;
        let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
        let pc = pose.inverse_transform(p);
        let (u, v, z) = k.project(pc);
        assert!((u - 100.0).abs() < 1e-3 && (v - 50.0).abs() < 1e-3 && (z - t).abs() < 1e-5);
    }

    #[test]
    fn resize_keeps_pixel_centres() {
        let k = Intrinsics {
            width: 1200,
            height: 680,
            fx: 600.0,
            fy: 600.0,
            cx: 599.5,
            cy: 339.5,
        };
        let h = k.resized(600, 340);
        assert_eq!((h.fx, h.cx, h.cy), (300.0, 299.5, 169.5));
        let c = k.cropped(10);
        assert_eq!((c.width, c.height, c.cx, c.cy), (1180, 660, 589.5, 329.5));
        assert!(!Pose {
            m: [
                [2.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0]
            ]
        }
        .is_rigid(1e-3));
    }
}
