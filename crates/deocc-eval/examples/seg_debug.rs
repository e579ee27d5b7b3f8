use deocc_pipeline::segment::{ConvexitySegmenter, Segmenter};
use deocc_synth::sheet::id_color;
fn main() {
    let preset = deocc_synth::dataset::bench_v1();
    let seed: usize = std::env::args()
        .nth(1)
        .map(|s| s.parse().unwrap())
        .unwrap_or(0);
    let view: usize = std::env::args()
        .nth(2)
        .map(|s| s.parse().unwrap())
        .unwrap_or(0);
    let mut cfg = preset.config.clone();
    cfg.gt_points_per_m2 = 10.0;
    let r = deocc_synth::dataset::render_full_scene(&cfg, preset.seeds[seed]).unwrap();
    let v = &r.views[view];
    let seg = ConvexitySegmenter::default().segment(&v.depth, &v.camera);
    let (w, h) = (v.frame.width, v.frame.height);
    let mut img = image::RgbImage::new(w * 3, h);
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            img.put_pixel(x, y, *v.rgb.get_pixel(x, y));
            img.put_pixel(x + w, y, image::Rgb(id_color(v.frame.instance[i])));
            img.put_pixel(x + 2 * w, y, image::Rgb(id_color(seg.ids[i])));
        }
    }
    img.save("/tmp/seg_debug.png").unwrap();
    let ious = deocc_pipeline::segment::matched_ious(
        &seg,
        &deocc_io::images::InstanceMap {
            width: w,
            height: h,
            ids: v.frame.instance.clone(),
        },
        50,
        &[],
    );
    for (t, iou) in ious {
        let c = r
            .scene
            .objects
            .iter()
            .find(|o| o.instance_id == t)
            .map(|o| o.category.name())
            .unwrap_or("?");
        println!("{t} {c} {iou:.2}");
    }
}
