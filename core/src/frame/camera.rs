//! Cameras in the OpenEXR convention: `worldToCamera` and `worldToNDC` are
//! row-vector matrices (`p' = [x y z 1] M`); camera space is +x right, +y up,
//! +z forward; NDC (0,0) is the top-left and (1,1) the bottom-right corner of
//! the image after dividing by w. Internally the matrices are kept in glam's
//! column-vector form (`p' = M p`), i.e. transposed.

use glam::{DMat4, DVec2, DVec3, DVec4, Mat4};

/// A camera: world-to-camera and world-to-NDC transforms.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// World to camera space (+z forward), column-vector form.
    pub world_to_camera: Mat4,
    /// World to NDC (homogeneous; divide by w), column-vector form.
    pub world_to_ndc: Mat4,
}

impl Camera {
    /// From OpenEXR row-vector matrices given row by row (`m[row][col]`), as
    /// stored in the `worldToCamera` and `worldToNDC` header attributes.
    pub fn from_exr_rows(world_to_camera: [[f32; 4]; 4], world_to_ndc: [[f32; 4]; 4]) -> Camera {
        Camera {
            world_to_camera: Mat4::from_cols_array_2d(&world_to_camera),
            world_to_ndc: Mat4::from_cols_array_2d(&world_to_ndc),
        }
    }

    /// Back to OpenEXR row-vector matrices, row by row.
    pub fn to_exr_rows(&self) -> ([[f32; 4]; 4], [[f32; 4]; 4]) {
        (
            self.world_to_camera.to_cols_array_2d(),
            self.world_to_ndc.to_cols_array_2d(),
        )
    }

    /// A pinhole camera looking from `eye` toward `target` (+y up in world),
    /// with vertical field of view `fov_y` (radians) and `aspect` = width/height.
    pub fn look_at(eye: glam::Vec3, target: glam::Vec3, fov_y: f32, aspect: f32) -> Camera {
        let forward = (target - eye).normalize();
        let right = forward.cross(glam::Vec3::Y).normalize();
        let up = right.cross(forward);
        // Rows of the rotation are the camera axes: +x right, +y up, +z forward.
        let rot = Mat4::from_cols(
            glam::Vec4::new(right.x, up.x, forward.x, 0.0),
            glam::Vec4::new(right.y, up.y, forward.y, 0.0),
            glam::Vec4::new(right.z, up.z, forward.z, 0.0),
            glam::Vec4::W,
        );
        let world_to_camera = rot * Mat4::from_translation(-eye);
        let f = 1.0 / (fov_y * 0.5).tan();
        // Camera space to NDC in [0,1], y down: u = 0.5 + 0.5 f/aspect x/z, v = 0.5 - 0.5 f y/z.
        let cam_to_ndc = Mat4::from_cols(
            glam::Vec4::new(0.5 * f / aspect, 0.0, 0.0, 0.0),
            glam::Vec4::new(0.0, -0.5 * f, 0.0, 0.0),
            glam::Vec4::new(0.5, 0.5, 1.0, 1.0),
            glam::Vec4::new(0.0, 0.0, -0.1, 0.0),
        );
        Camera {
            world_to_camera,
            world_to_ndc: cam_to_ndc * world_to_camera,
        }
    }

    /// Camera-to-NDC transform (double precision).
    fn camera_to_ndc(&self) -> DMat4 {
        self.world_to_ndc.as_dmat4() * self.world_to_camera.as_dmat4().inverse()
    }

    /// Projects a world point to pixel coordinates (pixel centres at +0.5) and
    /// planar depth; `None` behind the camera.
    pub fn project(&self, p: DVec3, width: usize, height: usize) -> Option<(DVec2, f64)> {
        let cam = self.world_to_camera.as_dmat4() * p.extend(1.0);
        if cam.z <= 1e-9 {
            return None;
        }
        let ndc = self.world_to_ndc.as_dmat4() * p.extend(1.0);
        if ndc.w.abs() < 1e-12 {
            return None;
        }
        Some((
            DVec2::new(ndc.x / ndc.w * width as f64, ndc.y / ndc.w * height as f64),
            cam.z,
        ))
    }

    /// A precomputed unprojector for images of `width` x `height`.
    pub fn unprojector(&self, width: usize, height: usize) -> Unprojector {
        Unprojector {
            cam_to_ndc: self.camera_to_ndc(),
            camera_to_world: self.world_to_camera.as_dmat4().inverse(),
            width: width as f64,
            height: height as f64,
        }
    }
}

/// Turns pixel positions and planar depth back into world points.
#[derive(Debug, Clone, Copy)]
pub struct Unprojector {
    cam_to_ndc: DMat4,
    camera_to_world: DMat4,
    width: f64,
    height: f64,
}

impl Unprojector {
    /// Camera-space point at planar depth `depth` seen through pixel
    /// position `px` (pixel centres at +0.5).
    pub fn camera_point(&self, px: DVec2, depth: f64) -> DVec3 {
        let u = px.x / self.width;
        let v = px.y / self.height;
        let m = &self.cam_to_ndc;
        // Rows of the (column-vector) matrix.
        let r0 = m.row(0);
        let r1 = m.row(1);
        let r3 = m.row(3);
        // (r0 - u r3) . (x, y, d, 1) = 0 and (r1 - v r3) . (x, y, d, 1) = 0.
        let a: DVec4 = r0 - u * r3;
        let b: DVec4 = r1 - v * r3;
        let (a0, a1, ac) = (a.x, a.y, -(a.z * depth + a.w));
        let (b0, b1, bc) = (b.x, b.y, -(b.z * depth + b.w));
        let det = a0 * b1 - a1 * b0;
        if det.abs() < 1e-18 {
            return DVec3::new(0.0, 0.0, depth);
        }
        DVec3::new((ac * b1 - a1 * bc) / det, (a0 * bc - ac * b0) / det, depth)
    }

    /// World point at planar depth `depth` through pixel position `px`.
    pub fn world_point(&self, px: DVec2, depth: f64) -> DVec3 {
        (self.camera_to_world * self.camera_point(px, depth).extend(1.0)).truncate()
    }

    /// Factor that turns Euclidean distance along the ray through `px` into
    /// planar depth: `planar = euclidean * factor`.
    pub fn euclidean_to_planar(&self, px: DVec2) -> f64 {
        1.0 / self.camera_point(px, 1.0).length()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn project_unproject_round_trip() {
        let cam = Camera::look_at(Vec3::new(1.0, 2.0, -5.0), Vec3::ZERO, 0.8, 16.0 / 9.0);
        let p = DVec3::new(0.3, -0.2, 0.7);
        let (px, d) = cam.project(p, 320, 180).unwrap();
        let back = cam.unprojector(320, 180).world_point(px, d);
        assert!((back - p).length() < 1e-4, "{back:?} vs {p:?}");
    }

    #[test]
    fn exr_rows_round_trip_and_row_vector_convention() {
        let cam = Camera::look_at(Vec3::new(0.0, 0.0, -3.0), Vec3::ZERO, 0.9, 1.5);
        let (w2c, w2ndc) = cam.to_exr_rows();
        let back = Camera::from_exr_rows(w2c, w2ndc);
        assert_eq!(back, cam);
        // Row-vector: translation sits in the last row.
        let p = [0.0f32, 0.0, 0.0, 1.0];
        let z: f32 = (0..4).map(|k| p[k] * w2c[k][2]).sum();
        assert!((z - 3.0).abs() < 1e-5, "origin is 3 units in front: {z}");
    }

    #[test]
    fn centre_pixel_looks_forward_and_y_is_down() {
        let cam = Camera::look_at(Vec3::new(0.0, 0.0, -3.0), Vec3::ZERO, 0.9, 2.0);
        let (px, d) = cam.project(DVec3::ZERO, 200, 100).unwrap();
        assert!((px - DVec2::new(100.0, 50.0)).length() < 1e-4);
        assert!((d - 3.0).abs() < 1e-6);
        let (up, _) = cam.project(DVec3::new(0.0, 1.0, 0.0), 200, 100).unwrap();
        assert!(up.y < 50.0, "world up projects toward the top row");
    }
}
