//! Per-(view, instance) statistics, computed once per view in one pass over its instance map and
//! shared by the stages that need them (view selection, crops).

use std::collections::BTreeMap;

use deocc_io::scene::Frame;
use nalgebra::{Point3, Vector3};

/// What one view shows of one instance.
#[derive(Debug, Clone, PartialEq)]
pub struct InstanceStats {
    /// Pixels carrying the id.
    pub pixels: usize,
    /// Bounding box of those pixels, `[u0, v0, u1, v1)` (exclusive ends).
    pub bbox: [usize; 4],
    /// World-frame centroid of the pixels with depth; `None` if none has.
    pub centroid: Option<Point3<f32>>,
}

/// Statistics of every instance of a frame (empty without an instance map).
pub fn view_stats(frame: &Frame) -> BTreeMap<u16, InstanceStats> {
    let Some(inst) = frame.instances.as_ref() else {
        return BTreeMap::new();
    };
    let w = inst.width as usize;
    let d = frame.depth.data();
    // (pixels, bbox, sum of positions in f64, count with depth), accumulated in pixel order.
    let mut acc: BTreeMap<u16, (usize, [usize; 4], Vector3<f64>, usize)> = BTreeMap::new();
    for (i, &id) in inst.ids.iter().enumerate() {
        if id == 0 {
            continue;
        }
        let (u, v) = (i % w, i / w);
        let e = acc
            .entry(id)
            .or_insert((0, [usize::MAX, usize::MAX, 0, 0], Vector3::zeros(), 0));
        e.0 += 1;
        e.1 = [
            e.1[0].min(u),
            e.1[1].min(v),
            e.1[2].max(u + 1),
            e.1[3].max(v + 1),
        ];
        if d[i] > 0.0 {
            let p = frame.camera.unproject_pixel(u as u32, v as u32, d[i]);
            e.2 += p.coords.cast::<f64>();
            e.3 += 1;
        }
    }
    acc.into_iter()
        .map(|(id, (pixels, bbox, sum, n))| {
            let centroid = (n > 0).then(|| Point3::from((sum / n as f64).cast::<f32>()));
            (
                id,
                InstanceStats {
                    pixels,
                    bbox,
                    centroid,
                },
            )
        })
        .collect()
}
