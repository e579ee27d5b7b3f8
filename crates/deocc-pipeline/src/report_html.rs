//! `report.html`: a run's output as one self-contained page (no network, no external file): an
//! interactive 3-D view of the completed cloud drawn on a 2-D canvas with a z-buffer (turn,
//! zoom, pan; toggle observed points and each kind of generated point, show one instance,
//! colour by own colour, provenance, instance or confidence), the run's pictures embedded as
//! PNG data, and its figures.
//!
//! After drawing, the page writes what it drew into `<body>`'s data attributes
//! (`data-status="ok"`, `data-drawn-points`, `data-generated-pixels`), so a headless browser test
//! can check that the page loads without error and the canvas shows the generated points.

use std::path::Path;

use base64::Engine;
use deocc_geometry::{Camera, PointCloud, Provenance};

use crate::PipelineError;

/// Most points the page carries; generated points are all kept (up to this many), observed ones
/// subsampled evenly to fill the rest.
pub const MAX_PAGE_POINTS: usize = 300_000;

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// Which points of `cloud` the page carries, in order.
fn page_points(cloud: &PointCloud) -> Vec<usize> {
    let gen = cloud.generated.as_deref().unwrap_or(&[]);
    let is_gen = |i: usize| {
        gen.get(i)
            .is_some_and(|&g| g != Provenance::Observed.code())
    };
    let generated: Vec<usize> = (0..cloud.len())
        .filter(|&i| is_gen(i))
        .take(MAX_PAGE_POINTS)
        .collect();
    let room = MAX_PAGE_POINTS - generated.len();
    let observed: Vec<usize> = (0..cloud.len()).filter(|&i| !is_gen(i)).collect();
    // Evenly spread: the j-th kept observed point is at j * len / room.
    let mut keep: Vec<usize> = if observed.len() <= room {
        observed
    } else {
        (0..room)
            .map(|j| observed[j * observed.len() / room])
            .collect()
    };
    keep.extend(generated);
    keep
}

/// Escapes text for HTML.
fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Writes `dir/report.html` for the run whose clouds, pictures (the PNGs already in `dir`) and
/// `report.json` are in `dir`.
pub fn write_report_html(
    dir: &Path,
    completed: &PointCloud,
    first: Option<&Camera>,
    report: &serde_json::Value,
) -> Result<(), PipelineError> {
    let keep = page_points(completed);
    let mut pos = Vec::with_capacity(keep.len() * 12);
    let mut col = Vec::with_capacity(keep.len() * 3);
    let mut prov = Vec::with_capacity(keep.len());
    let mut inst = Vec::with_capacity(keep.len() * 4);
    let mut conf = Vec::with_capacity(keep.len());
    for &i in &keep {
        for v in completed.positions[i].coords.iter() {
            pos.extend(v.to_le_bytes());
        }
        col.extend(completed.colors.as_ref().map_or([200, 200, 200], |c| c[i]));
        prov.push(completed.generated.as_ref().map_or(0, |g| g[i]));
        inst.extend(
            completed
                .instance
                .as_ref()
                .map_or(0, |v| v[i])
                .to_le_bytes(),
        );
        let c = completed.confidence.as_ref().map_or(1.0, |c| c[i]);
        conf.push((c.clamp(0.0, 1.0) * 255.0).round() as u8);
    }
    let eye = first.map(|c| {
        let e = c.center();
        [e.x, e.y, e.z]
    });
    let data = serde_json::json!({
        "n": keep.len(),
        "total_points": completed.len(),
        "pos": b64(&pos), "col": b64(&col), "prov": b64(&prov),
        "inst": b64(&inst), "conf": b64(&conf),
        "eye": eye,
    });
    // The pictures the output stage wrote, in a fixed order.
    let mut pictures = String::new();
    let mut names: Vec<String> = [
        "render_input_view.png",
        "render_novel_view.png",
        "render_occluders_removed.png",
        "render_objects.png",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    if let Ok(rd) = std::fs::read_dir(dir.join("objects")) {
        let mut objs: Vec<String> = rd
            .filter_map(|e| e.ok())
            .map(|e| format!("objects/{}", e.file_name().to_string_lossy()))
            .collect();
        objs.sort();
        names.extend(objs.into_iter().skip(crate::pictures::MAX_STACKED));
    }
    for name in names {
        if let Ok(bytes) = std::fs::read(dir.join(&name)) {
            pictures += &format!(
                "<figure><img alt=\"{n}\" src=\"data:image/png;base64,{}\"><figcaption>{n}</figcaption></figure>\n",
                b64(&bytes),
                n = esc(&name)
            );
        }
    }
    let mut figures = String::new();
    for key in [
        "frames",
        "completers",
        "objects_completed",
        "points_observed",
        "points_generated",
        "objects_per_second",
    ] {
        if let Some(v) = report.get(key) {
            figures += &format!("<tr><th>{key}</th><td>{}</td></tr>", esc(&v.to_string()));
        }
    }
    if let Some(t) = report.get("timings").and_then(|t| t.get("total_s")) {
        figures += &format!("<tr><th>total time (s)</th><td>{t}</td></tr>");
    }
    if let Some(e) = report.get("evaluation").filter(|e| !e.is_null()) {
        for key in [
            "completeness_gain_whole_scene",
            "completeness_gain_hidden_region",
        ] {
            if let Some(v) = e.get(key) {
                figures += &format!("<tr><th>{key}</th><td>{v}</td></tr>");
            }
        }
    }
    let mut instances = String::new();
    if let Some(list) = report.get("instances").and_then(|v| v.as_array()) {
        for i in list {
            instances += &format!(
                "<tr><td>{}</td><td>{}</td><td>{}</td></tr>",
                i["instance_id"],
                esc(&i["occluded_in_views"].to_string()),
                i["generated_points"]
            );
        }
    }
    let html = TEMPLATE
        .replace("{{DATA}}", &data.to_string().replace("</", "<\\/"))
        .replace("{{PICTURES}}", &pictures)
        .replace("{{FIGURES}}", &figures)
        .replace("{{INSTANCES}}", &instances);
    deocc_io::atomic::write_bytes_atomic(&dir.join("report.html"), html.as_bytes())?;
    Ok(())
}

const TEMPLATE: &str = r##"<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>deocc run</title>
<style>
body { font: 14px system-ui, sans-serif; background: #16161c; color: #ddd; margin: 16px; }
h1, h2 { font-weight: 600; } a { color: #9cf; }
#controls { display: flex; flex-wrap: wrap; gap: 14px; align-items: center; margin: 8px 0; }
canvas { background: #14141a; border: 1px solid #333; cursor: grab; max-width: 100%; }
.sw { display: inline-block; width: 11px; height: 11px; margin-right: 4px; vertical-align: -1px; }
table { border-collapse: collapse; } td, th { padding: 2px 10px; text-align: left; border-bottom: 1px solid #333; }
figure { margin: 10px 0; } img { max-width: 100%; } figcaption { color: #999; }
</style></head>
<body data-status="loading">
<h1>deocc run</h1>
<div id="controls">
  <label><input type="checkbox" class="prov" value="0" checked><span class="sw" style="background:#aaa"></span>observed</label>
  <label><input type="checkbox" class="prov" value="1" checked><span class="sw" style="background:#ff00c8"></span>model</label>
  <label><input type="checkbox" class="prov" value="3" checked><span class="sw" style="background:#ff9a1e"></span>rules</label>
  <label><input type="checkbox" class="prov" value="2" checked><span class="sw" style="background:#50a0ff"></span>plane fill</label>
  <label>instance <select id="inst"><option value="all">all</option></select></label>
  <label>colour <select id="colour">
    <option value="prov">by provenance</option><option value="own">own colour</option>
    <option value="inst">by instance</option><option value="conf">by confidence</option></select></label>
  <label>point size <input id="size" type="range" min="1" max="5" value="2"></label>
</div>
<canvas id="view" width="960" height="620"></canvas>
<p id="info">drag to turn, shift-drag to pan, wheel to zoom</p>
<h2>Pictures</h2>
{{PICTURES}}
<h2>Figures</h2>
<table>{{FIGURES}}</table>
<h2>Instances</h2>
<table><tr><th>id</th><th>occluded in views</th><th>generated points</th></tr>{{INSTANCES}}</table>
<script id="data" type="application/json">{{DATA}}</script>
<script>
"use strict";
window.addEventListener("error", e => { document.body.dataset.status = "error: " + e.message; });
const D = JSON.parse(document.getElementById("data").textContent);
function bytes(s) { const b = atob(s); const a = new Uint8Array(b.length); for (let i = 0; i < b.length; i++) a[i] = b.charCodeAt(i); return a; }
const P = new Float32Array(bytes(D.pos).buffer), C = bytes(D.col), G = bytes(D.prov),
      I = new Uint32Array(bytes(D.inst).buffer), F = bytes(D.conf), N = D.n;
const PROV = [[170,170,170],[255,0,200],[80,160,255],[255,154,30]];
let cx = 0, cy = 0, cz = 0;
for (let i = 0; i < N; i++) { cx += P[3*i]; cy += P[3*i+1]; cz += P[3*i+2]; }
if (N) { cx /= N; cy /= N; cz /= N; }
let r = 0.5;
for (let i = 0; i < N; i += 97) r = Math.max(r, Math.hypot(P[3*i]-cx, P[3*i+1]-cy, P[3*i+2]-cz));
let yaw = 0, pitch = 0.5, dist = 2.2 * r, panX = 0, panY = 0;
if (D.eye) { yaw = Math.atan2(D.eye[1]-cy, D.eye[0]-cx); dist = Math.max(0.5, Math.hypot(D.eye[0]-cx, D.eye[1]-cy, D.eye[2]-cz)); pitch = Math.asin(Math.min(0.99, (D.eye[2]-cz)/dist)); }
const ids = Array.from(new Set(I)).filter(v => v).sort((a, b) => a - b);
const sel = document.getElementById("inst");
for (const v of ids) { const o = document.createElement("option"); o.value = v; o.textContent = v; sel.appendChild(o); }
function hue(id) { const h = (id * 0.618034) % 1, f = k => Math.round(255 * Math.max(0, Math.min(1, Math.abs(((h*6+k)%6)-3)-1))); return [f(0), f(4), f(2)]; }
const cv = document.getElementById("view"), ctx = cv.getContext("2d");
const W = cv.width, H = cv.height, zbuf = new Float32Array(W*H), pbuf = new Uint8Array(W*H);
function draw() {
  const on = new Set(Array.from(document.querySelectorAll(".prov:checked")).map(e => +e.value));
  const only = sel.value === "all" ? null : +sel.value, mode = document.getElementById("colour").value;
  const size = +document.getElementById("size").value;
  const img = ctx.createImageData(W, H), px = img.data;
  zbuf.fill(Infinity); pbuf.fill(255);
  for (let i = 0; i < W*H; i++) { px[4*i] = 20; px[4*i+1] = 20; px[4*i+2] = 26; px[4*i+3] = 255; }
  // Camera: orbit around the centroid, z up.
  const ex = cx + dist*Math.cos(pitch)*Math.cos(yaw), ey = cy + dist*Math.cos(pitch)*Math.sin(yaw), ez = cz + dist*Math.sin(pitch);
  let fx = cx-ex, fy = cy-ey, fz = cz-ez; const fl = Math.hypot(fx, fy, fz); fx /= fl; fy /= fl; fz /= fl;
  let rx = fy, ry = -fx, rz = 0; const rl = Math.hypot(rx, ry) || 1; rx /= rl; ry /= rl;
  const ux = ry*fz - rz*fy, uy = rz*fx - rx*fz, uz = rx*fy - ry*fx;
  const f = 0.9 * H;
  let drawn = 0;
  for (let i = 0; i < N; i++) {
    const g = G[i];
    if (!on.has(g) || (only !== null && I[i] !== only)) continue;
    const dx = P[3*i]-ex + panX*rx + panY*ux, dy = P[3*i+1]-ey + panX*ry + panY*uy, dz = P[3*i+2]-ez + panY*uz;
    const z = dx*fx + dy*fy + dz*fz; if (z <= 0.01) continue;
    const u = Math.floor(W/2 + f*(dx*rx + dy*ry + dz*rz)/z), v = Math.floor(H/2 - f*(dx*ux + dy*uy + dz*uz)/z);
    let c;
    if (mode === "own") c = [C[3*i], C[3*i+1], C[3*i+2]];
    else if (mode === "prov") c = g === 0 ? [C[3*i]*0.6+40, C[3*i+1]*0.6+40, C[3*i+2]*0.6+40] : PROV[g];
    else if (mode === "inst") c = I[i] ? hue(I[i]) : [90, 90, 90];
    else { const t = F[i]/255; c = [Math.round(255*(1-t)), Math.round(200*t), 60]; }
    const s = g === 0 ? size : size + 1; // generated points a little larger, so they are seen
    let any = false;
    for (let a = 0; a < s; a++) for (let b = 0; b < s; b++) {
      const x = u + b - (s >> 1), y = v + a - (s >> 1);
      if (x < 0 || y < 0 || x >= W || y >= H) continue;
      const k = y*W + x; if (z >= zbuf[k]) continue;
      zbuf[k] = z; pbuf[k] = g; px[4*k] = c[0]; px[4*k+1] = c[1]; px[4*k+2] = c[2]; any = true;
    }
    if (any) drawn++;
  }
  ctx.putImageData(img, 0, 0);
  let gen = 0; for (let k = 0; k < W*H; k++) if (pbuf[k] !== 255 && pbuf[k] !== 0) gen++;
  document.body.dataset.drawnPoints = drawn; document.body.dataset.generatedPixels = gen;
  document.getElementById("info").textContent = `${drawn} of ${N} points drawn (${D.total_points} in the cloud); drag to turn, shift-drag to pan, wheel to zoom`;
}
let drag = null;
cv.addEventListener("mousedown", e => { drag = [e.clientX, e.clientY, e.shiftKey]; });
window.addEventListener("mouseup", () => { drag = null; });
window.addEventListener("mousemove", e => {
  if (!drag) return; const ddx = e.clientX - drag[0], ddy = e.clientY - drag[1]; drag[0] = e.clientX; drag[1] = e.clientY;
  if (drag[2]) { panX += ddx*dist/800; panY -= ddy*dist/800; } else { yaw -= ddx*0.01; pitch = Math.max(-1.5, Math.min(1.5, pitch + ddy*0.01)); }
  draw();
});
cv.addEventListener("wheel", e => { e.preventDefault(); dist *= Math.exp(e.deltaY*0.001); draw(); }, { passive: false });
for (const el of document.querySelectorAll("#controls input, #controls select")) el.addEventListener("input", draw);
draw();
if (!document.body.dataset.status.startsWith("error")) document.body.dataset.status = "ok";
</script>
</body></html>
"##;

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn the_page_carries_every_generated_point_and_a_share_of_the_observed() {
        let n = 400_000;
        let mut cloud =
            PointCloud::from_positions((0..n).map(|i| Point3::new(i as f32, 0.0, 0.0)).collect());
        cloud.generated = Some((0..n).map(|i| u8::from(i % 50 == 0)).collect());
        let keep = page_points(&cloud);
        assert!(keep.len() <= MAX_PAGE_POINTS);
        let gen = keep.iter().filter(|&&i| i % 50 == 0).count();
        assert_eq!(gen, n / 50, "every generated point is on the page");
        assert!(keep.len() > MAX_PAGE_POINTS * 9 / 10, "{}", keep.len());
    }
}
