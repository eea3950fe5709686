//! GPU-free geometry every stage shares: poses, views (pose + asymmetric field of view, as
//! OpenXR reports them), the volume's placement and the maps between world, patient (LPS) and
//! volume texture space (docs/design.md, "Conventions").

use crate::volume::Volume;
use glam::{DMat4, DVec3, Mat3, Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};

pub const NEAR: f32 = 0.05;
pub const FAR: f32 = 100.0;

/// A typical adult interpupillary distance (m), used where no headset reports one.
pub const DEFAULT_IPD: f32 = 0.064;

/// A rigid pose in the world (OpenXR STAGE space: metres, +Y up, right-handed).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Vec3,
    pub orientation: Quat,
}

impl Pose {
    pub const IDENTITY: Pose = Pose {
        position: Vec3::ZERO,
        orientation: Quat::IDENTITY,
    };

    pub fn matrix(&self) -> Mat4 {
        Mat4::from_rotation_translation(self.orientation, self.position)
    }
}

/// Field-of-view half-angles in radians, OpenXR style (left and down are negative).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fov {
    pub angle_left: f32,
    pub angle_right: f32,
    pub angle_up: f32,
    pub angle_down: f32,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct View {
    pub pose: Pose,
    pub fov: Fov,
}

impl View {
    /// Vulkan projection (depth 0..1, y down) of this view's frustum.
    pub fn projection(&self) -> Mat4 {
        let f = &self.fov;
        glam::camera::rh::proj::vulkan::frustum(
            NEAR * f.angle_left.tan(),
            NEAR * f.angle_right.tan(),
            NEAR * f.angle_down.tan(),
            NEAR * f.angle_up.tan(),
            NEAR,
            FAR,
        )
    }

    pub fn view_proj(&self) -> Mat4 {
        self.projection() * self.pose.matrix().inverse()
    }
}

/// A symmetric field of view: `half_angle` radians to each side, up and down.
/// `X,Y,Z`: exactly three comma-separated values, each a `T` (a float must be finite), for every
/// triple the command line takes (points, offsets, dims, spacings); anything else is refused
/// with the text it was given.
pub fn parse_triple<T: std::str::FromStr + ToString>(s: &str) -> Result<[T; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts[..] else {
        return Err(format!(
            "'{s}': expected X,Y,Z, three comma-separated numbers"
        ));
    };
    let one = |v: &str| {
        v.parse::<T>()
            .ok()
            // NaN and infinities parse as floats; a triple is never one.
            .filter(|x| x.to_string().parse::<f64>().is_ok_and(f64::is_finite))
            .ok_or_else(|| format!("'{s}': {v:?} is not a finite number"))
    };
    Ok([one(x)?, one(y)?, one(z)?])
}

pub fn symmetric_fov(half_angle: f32) -> Fov {
    Fov {
        angle_left: -half_angle,
        angle_right: half_angle,
        angle_up: half_angle,
        angle_down: -half_angle,
    }
}

/// The head between two eyes: their midpoint, turned halfway between them (the eyes of a
/// headset look the same way, or nearly).
pub fn head_of(views: &[View; 2]) -> Pose {
    let [a, b] = views.map(|v| v.pose);
    Pose {
        position: a.position.lerp(b.position, 0.5),
        orientation: a.orientation.slerp(b.orientation, 0.5),
    }
}

/// Patient LPS axes in the world: patient left -> +X, posterior -> -Z, superior -> +Y, so a
/// head stands upright facing a viewer who looks down -Z.
pub fn world_from_lps() -> Mat3 {
    Mat3::from_cols(Vec3::X, Vec3::NEG_Z, Vec3::Y)
}

/// Where the volume sits in the world: its centre, a rotation and a uniform scale (1 = true size).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Placement {
    pub center: Vec3,
    pub rotation: Quat,
    pub scale: f32,
}

impl Placement {
    /// World point `world` in the volume's own millimetres: relative to its centre, along the
    /// world's axes as they were before the volume was turned ([`world_from_lps`] of the
    /// patient axes), unscaled.
    pub fn local_mm(&self, world: Vec3) -> Vec3 {
        self.rotation.inverse() * (world - self.center) / (self.scale * 1e-3)
    }

    /// The world point of volume-local millimetres `local` (the inverse of [`Self::local_mm`]).
    pub fn world_of_local_mm(&self, local: Vec3) -> Vec3 {
        self.center + self.rotation * (local * (self.scale * 1e-3))
    }
}

impl Default for Placement {
    /// At chest height, 0.6 m in front of a standing user at the stage origin.
    fn default() -> Self {
        Placement {
            center: Vec3::new(0.0, 1.4, -0.6),
            rotation: Quat::IDENTITY,
            scale: 1.0,
        }
    }
}

/// The model matrix taking volume texture coordinates \[0,1]^3 (tex = index / dims) to the world.
pub fn world_from_tex(vol: &Volume, placement: &Placement) -> Mat4 {
    let ext = vol.extent_mm();
    let axes_from_tex = DMat4::from_scale(ext) * DMat4::from_translation(DVec3::splat(-0.5));
    let lps_from_axes = DMat4::from_mat3(vol.directions);
    let world_from_lps = DMat4::from_mat3(world_from_lps().as_dmat3());
    let place = DMat4::from_scale_rotation_translation(
        DVec3::splat(placement.scale as f64 * 1e-3),
        placement.rotation.as_dquat(),
        placement.center.as_dvec3(),
    );
    (place * world_from_lps * lps_from_axes * axes_from_tex).as_mat4()
}

/// The world position of patient (LPS, mm) point `lps` of `vol` placed at `placement`: through
/// the voxel index (`origin + directions · (index ⊙ spacing)` is a voxel centre's LPS) and
/// [`world_from_tex`] (a centre's texture coordinate is (index + 0.5) / dims).
pub fn world_from_lps_point(vol: &Volume, placement: &Placement, lps: DVec3) -> Vec3 {
    let index = (vol.directions.inverse() * (lps - vol.origin)) / DVec3::from_array(vol.spacing);
    let dims = DVec3::new(vol.dims[0] as f64, vol.dims[1] as f64, vol.dims[2] as f64);
    let tex = (index + 0.5) / dims;
    world_from_tex(vol, placement).transform_point3(tex.as_vec3())
}

/// Patient (LPS, mm) point of volume-local millimetres `local` ([`Placement::local_mm`]): the
/// volume's box centre (the point [`world_from_tex`] places at the placement's centre) plus the
/// offset turned from world axes back to patient axes (a rotation: lengths are kept).
pub fn lps_from_local_mm(vol: &Volume, local: Vec3) -> DVec3 {
    let half = DVec3::from_array(vol.dims.map(|d| d as f64 * 0.5 - 0.5));
    let centre = vol.origin + vol.directions * (half * DVec3::from_array(vol.spacing));
    centre + world_from_lps().transpose().as_dmat3() * local.as_dvec3()
}

/// Radius (m) of the sphere around the placed volume.
pub fn bounding_radius(vol: &Volume, placement: &Placement) -> f32 {
    (vol.extent_mm().length() * 0.5e-3) as f32 * placement.scale
}

/// Two parallel eyes `ipd` metres apart, looking down -Z at the volume, each with the
/// asymmetric frustum that frames the volume's bounding sphere (as a headset's views would).
pub fn default_stereo_views(vol: &Volume, placement: &Placement, ipd: f32) -> [View; 2] {
    let r = bounding_radius(vol, placement) * 1.02;
    let dist = (2.6 * r).max(0.3);
    let head = placement.center + Vec3::new(0.0, 0.0, dist);
    [-0.5f32, 0.5].map(|side| {
        let x = side * ipd;
        View {
            pose: Pose {
                position: head + Vec3::new(x, 0.0, 0.0),
                orientation: Quat::IDENTITY,
            },
            fov: Fov {
                angle_left: ((-r - x) / dist).atan(),
                angle_right: ((r - x) / dist).atan(),
                angle_up: (r / dist).atan(),
                angle_down: (-r / dist).atan(),
            },
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triples_are_three_finite_numbers_or_refused_by_name() {
        assert_eq!(parse_triple::<f32>("0.2, 1.3,-0.58"), Ok([0.2, 1.3, -0.58]));
        assert_eq!(parse_triple::<usize>("512,512,133"), Ok([512, 512, 133]));
        for bad in [
            "1,x,2,3", "1,2", "1,2,3,4", "nan,0,0", "0,inf,0", "1,2,", "",
        ] {
            let e = parse_triple::<f32>(bad).unwrap_err();
            assert!(e.contains(&format!("'{bad}'")), "{bad}: {e}");
        }
        assert!(parse_triple::<usize>("1,-2,3").is_err());
    }

    #[test]
    fn lps_maps_upright_and_facing_the_viewer() {
        let m = world_from_lps();
        assert_eq!(m * Vec3::Z, Vec3::Y, "superior is up");
        assert_eq!(
            m * -Vec3::Y,
            Vec3::Z,
            "anterior faces +Z, towards the viewer"
        );
        assert!(
            (m.determinant() - 1.0).abs() < 1e-6,
            "a rotation, not a mirror"
        );
    }

    #[test]
    fn volume_local_mm_is_patient_space_turned_and_placed() {
        // An oblique, anisotropic volume, turned, moved and scaled in the world.
        let mut vol = crate::volume::phantom::head(8);
        vol.dims = [8, 6, 5];
        vol.spacing = [0.7, 0.9, 2.5];
        vol.origin = DVec3::new(-12.0, 30.0, 7.0);
        vol.directions = glam::DMat3::from_rotation_z(0.4) * glam::DMat3::from_rotation_x(-0.3);
        let placement = Placement {
            center: Vec3::new(0.1, 1.2, -0.5),
            rotation: Quat::from_rotation_y(0.7),
            scale: 2.0,
        };
        for lps in [
            DVec3::new(-10.0, 31.0, 9.0),
            DVec3::new(3.0, 27.5, 12.25),
            vol.origin,
        ] {
            let world = world_from_lps_point(&vol, &placement, lps);
            let local = placement.local_mm(world);
            assert!((placement.world_of_local_mm(local) - world).length() < 1e-6);
            let back = lps_from_local_mm(&vol, local);
            assert!((back - lps).length() < 1e-3, "{lps} -> {local} -> {back}");
        }
        // Lengths in local mm are patient mm, whatever the placement's scale.
        let (a, b) = (DVec3::new(-10.0, 31.0, 9.0), DVec3::new(3.0, 27.5, 12.25));
        let [la, lb] =
            [a, b].map(|p| placement.local_mm(world_from_lps_point(&vol, &placement, p)));
        assert!((la.distance(lb) as f64 - a.distance(b)).abs() < 1e-3);
    }

    #[test]
    fn projection_maps_fov_edges_to_ndc_edges() {
        let v = View {
            pose: Pose::IDENTITY,
            fov: Fov {
                angle_left: -0.5,
                angle_right: 0.3,
                angle_up: 0.4,
                angle_down: -0.2,
            },
        };
        let p = v.view_proj();
        let right_edge = Vec3::new(0.3f32.tan(), 0.0, -1.0);
        let c = p * right_edge.extend(1.0);
        assert!((c.x / c.w - 1.0).abs() < 1e-5);
        let top = Vec3::new(0.0, 0.4f32.tan(), -1.0);
        let c = p * top.extend(1.0);
        assert!((c.y / c.w + 1.0).abs() < 1e-5, "Vulkan NDC y is down");
    }
}
