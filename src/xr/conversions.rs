//! OpenXR's poses, fields of view and views to and from the renderer's ([`crate::space`]), and
//! the choice of the views a frame renders and submits.

use crate::space::{Fov, Pose, View};
use glam::{Quat, Vec3};
use openxr as xr;

/// A runtime pose; an unnormalisable orientation (untracked, zero) becomes the identity.
pub fn pose_from_xr(p: &xr::Posef) -> Pose {
    let q = Quat::from_xyzw(
        p.orientation.x,
        p.orientation.y,
        p.orientation.z,
        p.orientation.w,
    );
    Pose {
        position: Vec3::new(p.position.x, p.position.y, p.position.z),
        orientation: if q.length_squared() > 0.5 {
            q.normalize()
        } else {
            Quat::IDENTITY
        },
    }
}

pub fn pose_to_xr(p: &Pose) -> xr::Posef {
    xr::Posef {
        orientation: xr::Quaternionf {
            x: p.orientation.x,
            y: p.orientation.y,
            z: p.orientation.z,
            w: p.orientation.w,
        },
        position: xr::Vector3f {
            x: p.position.x,
            y: p.position.y,
            z: p.position.z,
        },
    }
}

pub fn fov_from_xr(f: &xr::Fovf) -> Fov {
    Fov {
        angle_left: f.angle_left,
        angle_right: f.angle_right,
        angle_up: f.angle_up,
        angle_down: f.angle_down,
    }
}

pub fn fov_to_xr(f: &Fov) -> xr::Fovf {
    xr::Fovf {
        angle_left: f.angle_left,
        angle_right: f.angle_right,
        angle_up: f.angle_up,
        angle_down: f.angle_down,
    }
}

/// The views a frame renders: the located ones when the runtime flags both their position and
/// orientation valid (they become `last`), else the last valid ones; None before any.
pub fn frame_views(
    flags: xr::ViewStateFlags,
    located: &[xr::View],
    last: &mut Option<[View; 2]>,
) -> Option<[View; 2]> {
    let valid = flags.contains(xr::ViewStateFlags::ORIENTATION_VALID)
        && flags.contains(xr::ViewStateFlags::POSITION_VALID);
    if valid && located.len() == 2 {
        *last = Some([0, 1].map(|i| View {
            pose: pose_from_xr(&located[i].pose),
            fov: fov_from_xr(&located[i].fov),
        }));
    }
    *last
}

/// The views a projection layer submits: exactly those the image was rendered with, so the
/// compositor reprojects from the pose the pixels belong to.
pub fn projection_views(rendered: &[View; 2]) -> [xr::View; 2] {
    rendered.map(|v| xr::View {
        pose: pose_to_xr(&v.pose),
        fov: fov_to_xr(&v.fov),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn xr_view(x: f32, yaw: f32, left: f32) -> xr::View {
        let q = Quat::from_rotation_y(yaw);
        xr::View {
            pose: pose_to_xr(&Pose {
                position: Vec3::new(x, 1.6, 0.0),
                orientation: q,
            }),
            fov: xr::Fovf {
                angle_left: left,
                angle_right: 0.5,
                angle_up: 0.5,
                angle_down: -0.5,
            },
        }
    }

    fn same(a: &xr::View, b: &xr::View) -> bool {
        let (p, q) = (pose_from_xr(&a.pose), pose_from_xr(&b.pose));
        p.position.distance(q.position) < 1e-6
            && p.orientation.dot(q.orientation).abs() > 1.0 - 1e-6
            && fov_from_xr(&a.fov) == fov_from_xr(&b.fov)
    }

    #[test]
    fn invalid_views_render_and_submit_the_last_good_ones() {
        let all = xr::ViewStateFlags::ORIENTATION_VALID | xr::ViewStateFlags::POSITION_VALID;
        let good = [xr_view(-0.032, 0.1, -0.6), xr_view(0.032, 0.1, -0.5)];
        let mut last = None;
        assert!(frame_views(xr::ViewStateFlags::EMPTY, &good, &mut last).is_none());
        let first = frame_views(all, &good, &mut last).expect("valid views");
        // The head moved, but the runtime flags the new poses invalid (tracking lost).
        let stale = [xr_view(5.0, 2.0, -0.9), xr_view(5.1, 2.0, -0.9)];
        let flags = xr::ViewStateFlags::ORIENTATION_VALID;
        let rendered = frame_views(flags, &stale, &mut last).expect("the last good views");
        assert_eq!(rendered, first, "rendered from the last good views");
        let submitted = projection_views(&rendered);
        for eye in 0..2 {
            assert!(
                same(&submitted[eye], &good[eye]),
                "eye {eye}: submitted as rendered"
            );
            assert!(
                !same(&submitted[eye], &stale[eye]),
                "eye {eye}: not the invalid pose"
            );
        }
    }
}
