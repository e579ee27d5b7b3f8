//! From what a real RGB-D camera gives to the pinhole frame deocc's stages use, once, at read
//! time: the colour image's lens distortion removed (same `K`), depth from a separate depth
//! camera undistorted in its own camera and registered to colour with a z-buffer, instance maps
//! resampled by nearest neighbour. Every input path (scene folders, gRPC, Python, ROS 2,
//! recordings) calls [`to_pinhole`].

use deocc_geometry::camera::Intrinsics;
use deocc_geometry::depth::register_depth;
use deocc_geometry::distortion::{undistort_depth, undistort_labels, undistort_rgb};
use deocc_geometry::DepthMap;
use image::RgbImage;

use crate::cameras::Lens;
use crate::images::InstanceMap;

/// The frame's images as a pinhole camera with `color` intrinsics, registered to colour, would
/// have given them. `depth` is in the depth camera's size when the lens has one.
pub fn to_pinhole(
    rgb: RgbImage,
    depth: DepthMap,
    instances: Option<InstanceMap>,
    color: &Intrinsics,
    lens: &Lens,
) -> (RgbImage, DepthMap, Option<InstanceMap>) {
    if lens.is_pinhole() {
        return (rgb, depth, instances);
    }
    let dist = &lens.distortion;
    let (w, h) = (color.width(), color.height());
    let rgb = if dist.is_none() {
        rgb
    } else {
        RgbImage::from_raw(w, h, undistort_rgb(rgb.as_raw(), 3, color, dist))
            .expect("same size as the colour image")
    };
    let depth = match &lens.depth_camera {
        Some(dc) => {
            let own = undistort_depth(&depth, &dc.intrinsics, &dc.distortion);
            register_depth(&own, &dc.intrinsics, color, &dc.color_from_depth)
        }
        None => undistort_depth(&depth, color, dist),
    };
    let instances = instances.map(|m| InstanceMap {
        width: m.width,
        height: m.height,
        ids: undistort_labels(&m.ids, color, dist),
    });
    (rgb, depth, instances)
}
