//! The `deocc` Python module: the pipeline, grasping and placing on numpy arrays, and a client
//! of `deocc serve`. Frames go in as dicts of arrays and are checked exactly as a service request
//! is (deocc-service's request module), so an error names the frame and the field; the GIL is
//! released while the pipeline runs.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

use deocc_completion::CompleterChain;
use deocc_geometry::PointCloud;
use deocc_pipeline::segment::ConvexitySegmenter;
use deocc_robot::place::{PlaceOptions, UnseenSpace};
use deocc_robot::{AntipodalPlanner, GraspOptions, GraspPlanner, GridPlacer, PlacePlanner};
use deocc_service::proto;
use deocc_service::request::{scene_from_request, Limits};
use nalgebra::Point3;
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

fn value_error(msg: impl Into<String>) -> PyErr {
    PyValueError::new_err(msg.into())
}

/// Chains by (completer names, weights folder).
type Chains = HashMap<(String, Option<String>), Arc<CompleterChain>>;

/// Completer chains by (names, weights folder), built once and shared by every call.
fn chain(completer: &str, weights: Option<&str>) -> PyResult<Arc<CompleterChain>> {
    static CHAINS: OnceLock<Mutex<Chains>> = OnceLock::new();
    let key = (completer.to_string(), weights.map(str::to_string));
    let cache = CHAINS.get_or_init(Default::default);
    if let Some(c) = cache
        .lock()
        .map_err(|_| PyRuntimeError::new_err("poisoned"))?
        .get(&key)
    {
        return Ok(c.clone());
    }
    let names: Vec<&str> = completer.split(',').collect();
    let c = Arc::new(
        deocc_model::chain::build(&names, weights.map(std::path::Path::new))
            .map_err(|e| value_error(format!("completer: {e}")))?,
    );
    cache
        .lock()
        .map_err(|_| PyRuntimeError::new_err("poisoned"))?
        .insert(key, c.clone());
    Ok(c)
}

/// An image message from a numpy array of `dims` dimensions; non-contiguous arrays are copied in
/// logical order.
fn image<T: numpy::Element + Copy>(
    arr: &Bound<'_, PyAny>,
    at: &str,
    channels: usize,
    encoding: &str,
    to_bytes: fn(T) -> Vec<u8>,
) -> PyResult<proto::Image> {
    let a = arr.cast::<numpy::PyArrayDyn<T>>().map_err(|_| {
        value_error(format!(
            "{at}: expected a numpy array of {}",
            std::any::type_name::<T>()
        ))
    })?;
    let ro = a.readonly();
    let shape = ro.shape().to_vec();
    let ok = match channels {
        1 => shape.len() == 2,
        c => shape.len() == 3 && shape[2] == c,
    };
    if !ok || shape[0] == 0 || shape[1] == 0 {
        let want = if channels == 1 {
            "(H, W)".to_string()
        } else {
            format!("(H, W, {channels})")
        };
        return Err(value_error(format!(
            "{at}: expected shape {want}, got {shape:?}"
        )));
    }
    let view = ro.as_array();
    let data: Vec<u8> = view.iter().flat_map(|&v| to_bytes(v)).collect();
    let bpp = data.len() / (shape[0] * shape[1]);
    Ok(proto::Image {
        height: shape[0] as u32,
        width: shape[1] as u32,
        encoding: encoding.into(),
        is_bigendian: false,
        step: (shape[1] * bpp) as u32,
        data,
    })
}

fn matrix(obj: &Bound<'_, PyAny>, at: &str, n: usize) -> PyResult<Vec<f64>> {
    let rows: Vec<Vec<f64>> = obj
        .extract()
        .map_err(|_| value_error(format!("{at}: expected a {n}x{n} matrix of numbers")))?;
    if rows.len() != n || rows.iter().any(|r| r.len() != n) {
        return Err(value_error(format!("{at}: expected a {n}x{n} matrix")));
    }
    Ok(rows.into_iter().flatten().collect())
}

/// A frame dict into the service's frame message.
fn frame(d: &Bound<'_, PyAny>, k: usize) -> PyResult<proto::Frame> {
    let at = format!("frames[{k}]");
    let d = d.cast::<PyDict>().map_err(|_| {
        value_error(format!(
            "{at}: expected a dict with rgb, depth, K (and pose, instances, name)"
        ))
    })?;
    let get = |key: &str| -> PyResult<Option<Bound<'_, PyAny>>> {
        d.get_item(key).map(|v| v.filter(|v| !v.is_none()))
    };
    let need = |key: &str| -> PyResult<Bound<'_, PyAny>> {
        get(key)?.ok_or_else(|| value_error(format!("{at}: missing {key:?}")))
    };
    let rgb = image::<u8>(&need("rgb")?, &format!("{at}['rgb']"), 3, "rgb8", |v| {
        vec![v]
    })?;
    let depth_obj = need("depth")?;
    let depth = if depth_obj.cast::<numpy::PyArrayDyn<u16>>().is_ok() {
        image::<u16>(&depth_obj, &format!("{at}['depth']"), 1, "16UC1", |v| {
            v.to_le_bytes().to_vec()
        })?
    } else if depth_obj.cast::<numpy::PyArrayDyn<f32>>().is_ok() {
        image::<f32>(&depth_obj, &format!("{at}['depth']"), 1, "32FC1", |v| {
            v.to_le_bytes().to_vec()
        })?
    } else {
        return Err(value_error(format!(
            "{at}['depth']: expected uint16 millimetres or float32 metres"
        )));
    };
    let k_values = matrix(&need("K")?, &format!("{at}['K']"), 3)?;
    let distortion_model = match get("distortion_model")? {
        Some(m) => m
            .extract::<String>()
            .map_err(|_| value_error(format!("{at}['distortion_model']: expected a str")))?,
        None => String::new(),
    };
    let d_values = match get("D")? {
        Some(v) => v
            .extract::<Vec<f64>>()
            .map_err(|_| value_error(format!("{at}['D']: expected a sequence of numbers")))?,
        None => Vec::new(),
    };
    let pose = match get("pose")? {
        Some(p) => matrix(&p, &format!("{at}['pose']"), 4)?,
        None => Vec::new(),
    };
    let instances = match get("instances")? {
        Some(i) => Some(image::<u16>(
            &i,
            &format!("{at}['instances']"),
            1,
            "16UC1",
            |v| v.to_le_bytes().to_vec(),
        )?),
        None => None,
    };
    let name = match get("name")? {
        Some(n) => n
            .extract::<String>()
            .map_err(|_| value_error(format!("{at}['name']: expected a str")))?,
        None => String::new(),
    };
    Ok(proto::Frame {
        name,
        camera_info: Some(proto::CameraInfo {
            height: rgb.height,
            width: rgb.width,
            k: k_values,
            distortion_model,
            d: d_values,
        }),
        rgb: Some(rgb),
        depth: Some(depth),
        world_from_camera: pose,
        instances,
    })
}

fn options_json(py: Python<'_>, options: Option<&Bound<'_, PyAny>>) -> PyResult<String> {
    match options {
        None => Ok(String::new()),
        Some(o) if o.is_none() => Ok(String::new()),
        Some(o) => match o.extract::<String>() {
            Ok(s) => Ok(s),
            Err(_) => py.import("json")?.call_method1("dumps", (o,))?.extract(),
        },
    }
}

fn request(
    py: Python<'_>,
    frames: &Bound<'_, PyAny>,
    options: Option<&Bound<'_, PyAny>>,
    segment: bool,
    structure_ids: Option<Vec<u32>>,
) -> PyResult<proto::CompleteRequest> {
    let list = frames
        .cast::<PyList>()
        .map_err(|_| value_error("frames: expected a list of frame dicts"))?;
    let frames = list
        .iter()
        .enumerate()
        .map(|(k, f)| frame(&f, k))
        .collect::<PyResult<Vec<_>>>()?;
    Ok(proto::CompleteRequest {
        frames,
        options_json: options_json(py, options)?,
        segment,
        structure_ids: structure_ids.unwrap_or_default(),
    })
}

fn points_array<'py>(py: Python<'py>, pts: &[Point3<f32>]) -> PyResult<Bound<'py, PyAny>> {
    let flat: Vec<f32> = pts.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
    Ok(PyArray1::from_vec(py, flat)
        .reshape([pts.len(), 3])?
        .into_any())
}

/// A cloud as a dict of arrays: points (N, 3) float32, colors (N, 3) uint8, instance (N,)
/// uint32, provenance (N,) uint8, confidence (N,) float32 (1 where the cloud carries none),
/// expected_error (N,) float32, metres (0 where the cloud carries none).
fn cloud_dict<'py>(py: Python<'py>, c: &PointCloud) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let n = c.len();
    d.set_item("points", points_array(py, &c.positions)?)?;
    let colors: Vec<u8> = match &c.colors {
        Some(v) => v.iter().flatten().copied().collect(),
        None => vec![128; n * 3],
    };
    d.set_item("colors", PyArray1::from_vec(py, colors).reshape([n, 3])?)?;
    d.set_item(
        "instance",
        PyArray1::from_vec(py, c.instance.clone().unwrap_or_else(|| vec![0; n])),
    )?;
    d.set_item(
        "provenance",
        PyArray1::from_vec(py, c.generated.clone().unwrap_or_else(|| vec![0; n])),
    )?;
    d.set_item(
        "confidence",
        PyArray1::from_vec(py, c.confidence.clone().unwrap_or_else(|| vec![1.0; n])),
    )?;
    d.set_item(
        "expected_error",
        PyArray1::from_vec(py, c.expected_error.clone().unwrap_or_else(|| vec![0.0; n])),
    )?;
    Ok(d)
}

fn json_to_py<'py>(py: Python<'py>, json: &str) -> PyResult<Bound<'py, PyAny>> {
    py.import("json")?.call_method1("loads", (json,))
}

/// Runs the pipeline on `frames` (a list of dicts: `rgb` (H, W, 3) uint8, `depth` (H, W)
/// uint16 mm or float32 m, `K` 3x3, optional `pose` 4x4 world-from-camera, optional
/// `instances` (H, W) uint16, optional `name`). Returns a dict: the completed cloud's arrays,
/// `observed` (the observed cloud's arrays) and `report`.
#[pyfunction]
#[pyo3(signature = (frames, options=None, completer="gldot,rules", weights=None, segment=false, structure_ids=None))]
fn run<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    options: Option<&Bound<'py, PyAny>>,
    completer: &str,
    weights: Option<&str>,
    segment: bool,
    structure_ids: Option<Vec<u32>>,
) -> PyResult<Bound<'py, PyDict>> {
    let req = request(py, frames, options, segment, structure_ids)?;
    let chain = chain(completer, weights)?;
    let limits = Limits {
        max_frames: 10_000,
        ..Limits::default()
    };
    let interrupt = Interruptible::default();
    let out = py.detach(|| {
        let (scene, opts) = scene_from_request(&req, &limits).map_err(|e| e.to_string())?;
        drop(req);
        deocc_pipeline::run_in_memory(
            scene,
            &chain,
            &opts,
            &ConvexitySegmenter::default(),
            segment,
            &interrupt,
        )
        .map_err(|e| e.to_string())
    });
    // Ctrl-C stopped the run between stages (or between batches of the completion).
    if let Some(e) = interrupt.0.lock().ok().and_then(|mut e| e.take()) {
        return Err(e);
    }
    let out = out.map_err(value_error)?;
    let d = cloud_dict(py, &out.completed)?;
    d.set_item("observed", cloud_dict(py, &out.observed)?)?;
    let report =
        serde_json::to_string(&out.report).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    d.set_item("report", json_to_py(py, &report)?)?;
    Ok(d)
}

/// An observer that stops a run when Python has a signal pending (Ctrl-C): the run goes on
/// without the GIL, so Python cannot raise KeyboardInterrupt until it asks.
#[derive(Default)]
struct Interruptible(Mutex<Option<PyErr>>);

impl deocc_pipeline::Observer for Interruptible {
    fn stage(&self, _: &'static str, _: f32) -> bool {
        match Python::attach(|py| py.check_signals()) {
            Ok(()) => true,
            Err(e) => {
                if let Ok(mut slot) = self.0.lock() {
                    *slot = Some(e);
                }
                false
            }
        }
    }
}

/// Longest timeout a call takes (a day): a larger one overflowed the timeout's encoding.
const MAX_TIMEOUT_S: f64 = 86_400.0;

/// Runs `fut` on `rt` without the GIL, checking for Ctrl-C every 100 ms (a call blocked in
/// `block_on` never let Python see it).
fn block_interruptible<F: std::future::Future + Send>(
    py: Python<'_>,
    rt: &tokio::runtime::Runtime,
    fut: F,
) -> PyResult<F::Output>
where
    F::Output: Send,
{
    py.detach(|| {
        rt.block_on(async move {
            tokio::pin!(fut);
            let mut tick = tokio::time::interval(std::time::Duration::from_millis(100));
            loop {
                tokio::select! {
                    out = &mut fut => return Ok(out),
                    _ = tick.tick() => {
                        Python::attach(|py| py.check_signals())?;
                    }
                }
            }
        })
    })
}

/// Reads a scene folder (as `deocc run` does) into `(frames, structure_ids)`: frames as `run`
/// takes them, depth as float32 metres.
#[pyfunction]
fn read_scene<'py>(py: Python<'py>, path: &str) -> PyResult<(Bound<'py, PyList>, Vec<u32>)> {
    let scene = py
        .detach(|| deocc_io::scene::read_scene(path.as_ref()))
        .map_err(|e| value_error(e.to_string()))?;
    let raw_poses: Vec<Option<[[f64; 4]; 4]>> =
        std::fs::read_to_string(std::path::Path::new(path).join("cameras.json"))
            .ok()
            .and_then(|t| serde_json::from_str::<deocc_io::cameras::CamerasJson>(&t).ok())
            .map(|c| c.frames.into_iter().map(|f| f.world_from_camera).collect())
            .unwrap_or_default();
    let frames = PyList::empty(py);
    for (k, f) in scene.frames.iter().enumerate() {
        let d = PyDict::new(py);
        let (w, h) = (f.rgb.width() as usize, f.rgb.height() as usize);
        d.set_item("name", &f.name)?;
        d.set_item(
            "rgb",
            PyArray1::from_vec(py, f.rgb.as_raw().clone()).reshape([h, w, 3])?,
        )?;
        d.set_item(
            "depth",
            PyArray1::from_vec(py, f.depth.data().to_vec()).reshape([h, w])?,
        )?;
        let i = &f.camera.intrinsics;
        let intrinsics = vec![
            vec![i.fx() as f64, 0.0, i.cx() as f64],
            vec![0.0, i.fy() as f64, i.cy() as f64],
            vec![0.0, 0.0, 1.0],
        ];
        d.set_item("K", intrinsics)?;
        if scene.posed {
            // The rows as cameras.json has them, so `run` parses the very same pose.
            let rows =
                raw_poses.get(k).copied().flatten().unwrap_or_else(|| {
                    deocc_io::cameras::pose_to_rows(&f.camera.world_from_camera)
                });
            d.set_item("pose", rows.iter().map(|r| r.to_vec()).collect::<Vec<_>>())?;
        }
        if let Some(m) = &f.instances {
            d.set_item(
                "instances",
                PyArray1::from_vec(py, m.ids.clone()).reshape([h, w])?,
            )?;
        }
        frames.append(d)?;
    }
    Ok((
        frames,
        scene.structure_ids.iter().map(|&i| u32::from(i)).collect(),
    ))
}

/// Reads a PLY written by deocc (completed.ply, observed.ply) into the arrays `run` returns.
#[pyfunction]
fn read_ply<'py>(py: Python<'py>, path: &str) -> PyResult<Bound<'py, PyDict>> {
    let ply = py
        .detach(|| deocc_io::ply::read_ply(path.as_ref()))
        .map_err(|e| value_error(e.to_string()))?;
    cloud_dict(py, &ply.vertices)
}

fn points_from(arr: PyReadonlyArray2<'_, f32>, at: &str) -> PyResult<Vec<Point3<f32>>> {
    let shape = arr.shape();
    if shape.len() != 2 || shape[1] != 3 {
        return Err(value_error(format!(
            "{at}: expected shape (N, 3), got {shape:?}"
        )));
    }
    let a = arr.as_array();
    let pts: Vec<Point3<f32>> = a
        .rows()
        .into_iter()
        .map(|r| Point3::new(r[0], r[1], r[2]))
        .collect();
    if let Some(i) = pts
        .iter()
        .position(|p| !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()))
    {
        return Err(value_error(format!("{at}: row {i} is not finite")));
    }
    Ok(pts)
}

/// Grasps on instance `target` of a cloud (`points` (N, 3) float32, `instance` (N,) uint32),
/// best first: dicts of position (3), rotation (3x3, world from gripper), width, score.
#[pyfunction]
#[pyo3(signature = (points, instance, target, options=None))]
fn grasp<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    instance: PyReadonlyArray1<'py, u32>,
    target: u32,
    options: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyList>> {
    let pts = points_from(points, "points")?;
    let ids = instance.as_array();
    if ids.len() != pts.len() {
        return Err(value_error(format!(
            "instance: {} ids for {} points",
            ids.len(),
            pts.len()
        )));
    }
    let target_pts: Vec<Point3<f32>> = pts
        .iter()
        .zip(ids.iter())
        .filter(|(_, &i)| i == target)
        .map(|(p, _)| *p)
        .collect();
    if target_pts.is_empty() {
        return Err(value_error(format!(
            "target: no point has instance {target}"
        )));
    }
    let json = options_json(py, options)?;
    let opts: GraspOptions = if json.is_empty() {
        GraspOptions::default()
    } else {
        deocc_io::cameras::options_from_json(&json)
            .map_err(|e| value_error(format!("options: {e}")))?
    };
    opts.validate()
        .map_err(|e| value_error(format!("options: {e}")))?;
    let planner = AntipodalPlanner { options: opts };
    let grasps = py
        .detach(|| planner.plan(&pts, &target_pts))
        .map_err(|e| value_error(format!("target {target}: {e}")))?;
    let out = PyList::empty(py);
    for g in &grasps {
        let d = PyDict::new(py);
        d.set_item("position", g.position.to_vec())?;
        d.set_item(
            "rotation",
            g.rotation.iter().map(|r| r.to_vec()).collect::<Vec<_>>(),
        )?;
        d.set_item("width", g.width)?;
        d.set_item("score", g.score)?;
        out.append(d)?;
    }
    Ok(out)
}

/// Which instance of a cloud a pixel `(u, v)` or a box `(u0, v0, u1, v1)` of a view points at:
/// the surface in front there (a box: the instance with the largest share of its pixels inside).
/// `camera` is a dict with `K` (3x3), `width`, `height`, optional `pose` (4x4 world from
/// camera), `distortion_model` and `D` (pixels are then of the image as the camera gave it).
#[pyfunction]
fn target_at(
    points: PyReadonlyArray2<'_, f32>,
    instance: PyReadonlyArray1<'_, u32>,
    pixel: Vec<f32>,
    camera: &Bound<'_, PyAny>,
) -> PyResult<u32> {
    let pts = points_from(points, "points")?;
    let ids: Vec<u32> = instance.as_array().iter().copied().collect();
    if ids.len() != pts.len() {
        return Err(value_error(format!(
            "instance: {} ids for {} points",
            ids.len(),
            pts.len()
        )));
    }
    let cam = camera.cast::<PyDict>().map_err(|_| {
        value_error("camera: expected a dict with K, width, height (and pose, distortion_model, D)")
    })?;
    let get = |key: &str| -> PyResult<Option<Bound<'_, PyAny>>> {
        cam.get_item(key).map(|v| v.filter(|v| !v.is_none()))
    };
    let need = |key: &str| -> PyResult<Bound<'_, PyAny>> {
        get(key)?.ok_or_else(|| value_error(format!("camera: missing {key:?}")))
    };
    let size = |key: &str| -> PyResult<u32> {
        need(key)?
            .extract::<u32>()
            .map_err(|_| value_error(format!("camera[{key:?}]: expected a positive int")))
    };
    let pick = proto::TargetPick {
        pixel,
        camera_info: Some(proto::CameraInfo {
            width: size("width")?,
            height: size("height")?,
            k: matrix(&need("K")?, "camera['K']", 3)?,
            distortion_model: match get("distortion_model")? {
                Some(m) => m
                    .extract()
                    .map_err(|_| value_error("camera['distortion_model']: expected a str"))?,
                None => String::new(),
            },
            d: match get("D")? {
                Some(d) => d
                    .extract()
                    .map_err(|_| value_error("camera['D']: expected a sequence of numbers"))?,
                None => Vec::new(),
            },
        }),
        world_from_camera: match get("pose")? {
            Some(p) => matrix(&p, "camera['pose']", 4)?,
            None => Vec::new(),
        },
    };
    let (view, pick) = deocc_service::request::target_pick(&pick)
        .map_err(|e| value_error(e.to_string().replace("target_pick.", "")))?;
    let mut cloud = deocc_geometry::PointCloud::from_positions(pts);
    cloud.instance = Some(ids);
    deocc_robot::target::instance_at(&cloud, &view, pick).map_err(value_error)
}

/// The pipeline options with every completer's far side thin (`PipelineOptions::for_placing`),
/// as a dict for `run(frames, options=...)`: more free table on clean depth, more false free
/// space under a real sensor, where `deocc place` keeps the defaults (docs/decisions.md).
#[pyfunction]
fn placing_options<'py>(py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(&deocc_pipeline::PipelineOptions::default().for_placing())
        .map_err(|e| value_error(format!("options: {e}")))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// Where an object of `footprint` (w, d) and `height` (metres) can be put down on a cloud:
/// a dict with found, position, clearance_m, score and the placeable map of each support plane.
#[pyfunction]
#[pyo3(signature = (points, footprint=(0.08, 0.08), height=0.12, up=(0.0, 0.0, 1.0), robot=(0.0, 0.0, 0.0)))]
fn place<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    footprint: (f32, f32),
    height: f32,
    up: (f32, f32, f32),
    robot: (f32, f32, f32),
) -> PyResult<Bound<'py, PyDict>> {
    let pts = points_from(points, "points")?;
    let options = PlaceOptions {
        footprint: [footprint.0, footprint.1],
        height,
        up: [up.0, up.1, up.2],
        ..PlaceOptions::default()
    };
    options
        .validate()
        .map_err(|e| value_error(format!("footprint / height / up: {e}")))?;
    let placer = GridPlacer {
        options,
        unseen: UnseenSpace::AsPoints,
        eye: None,
    };
    let robot = Point3::new(robot.0, robot.1, robot.2);
    let (maps, best) = py
        .detach(|| placer.plan(&pts, &robot))
        .map_err(|e| value_error(format!("points: {e}")))?;
    let d = PyDict::new(py);
    d.set_item("found", best.is_some())?;
    if let Some(b) = &best {
        d.set_item("position", b.position.to_vec())?;
        d.set_item("clearance_m", b.clearance_m)?;
        d.set_item("score", b.score)?;
        d.set_item("plane", b.plane)?;
    }
    let list = PyList::empty(py);
    for m in &maps {
        let md = PyDict::new(py);
        md.set_item("plane_height", m.plane.height)?;
        md.set_item("bounds", m.plane.bounds.to_vec())?;
        md.set_item("cell_m", m.cell_m)?;
        let cells: Vec<bool> = m.placeable.clone();
        md.set_item(
            "placeable",
            PyArray1::from_vec(py, cells).reshape([m.ny, m.nx])?,
        )?;
        list.append(md)?;
    }
    d.set_item("maps", list)?;
    Ok(d)
}

/// A client of `deocc serve`.
#[pyclass(module = "deocc")]
struct Client {
    inner: deocc_service::client::Client,
    rt: tokio::runtime::Runtime,
}

#[pymethods]
impl Client {
    /// Connects to `address` (`http://127.0.0.1:50051`), with the server's shared token if it
    /// needs one.
    #[new]
    #[pyo3(signature = (address="http://127.0.0.1:50051", token=None))]
    fn new(py: Python<'_>, address: &str, token: Option<String>) -> PyResult<Self> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        let inner = py
            .detach(|| rt.block_on(deocc_service::client::Client::connect(address, token)))
            .map_err(|e| PyRuntimeError::new_err(format!("{address}: {e}")))?;
        Ok(Self { inner, rt })
    }

    /// The server's health: serving, version, model, queued, running, queue_capacity.
    fn health<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let (rt, inner) = (&self.rt, &mut self.inner);
        let h = py
            .detach(|| rt.block_on(inner.health()))
            .map_err(|s| PyRuntimeError::new_err(format!("{:?}: {}", s.code(), s.message())))?;
        let d = PyDict::new(py);
        d.set_item("serving", h.serving)?;
        d.set_item("version", h.version)?;
        d.set_item("model", h.model)?;
        d.set_item("queued", h.queued)?;
        d.set_item("running", h.running)?;
        d.set_item("queue_capacity", h.queue_capacity)?;
        Ok(d)
    }

    /// [`run`] on the server: the completed cloud's arrays and the report.
    #[pyo3(signature = (frames, options=None, segment=false, timeout_s=None))]
    fn complete<'py>(
        &mut self,
        py: Python<'py>,
        frames: &Bound<'py, PyAny>,
        options: Option<&Bound<'py, PyAny>>,
        segment: bool,
        timeout_s: Option<f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let req = request(py, frames, options, segment, None)?;
        let timeout = match timeout_s {
            Some(t) if t.is_finite() && t > 0.0 && t <= MAX_TIMEOUT_S => {
                Some(std::time::Duration::from_secs_f64(t))
            }
            Some(t) => {
                return Err(value_error(format!(
                    "timeout_s: {t} must be in (0, {MAX_TIMEOUT_S}] seconds"
                )))
            }
            None => None,
        };
        let (rt, inner) = (&self.rt, &mut self.inner);
        let got =
            block_interruptible(py, rt, inner.complete(req, timeout))?.map_err(|s| {
                match s.code() {
                    deocc_service::Code::InvalidArgument => value_error(s.message().to_string()),
                    _ => PyRuntimeError::new_err(format!("{:?}: {}", s.code(), s.message())),
                }
            })?;
        let cloud = got
            .cloud()
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        let d = cloud_dict(py, &cloud)?;
        d.set_item("report", json_to_py(py, &got.result.report_json)?)?;
        d.set_item("stages", got.stages)?;
        Ok(d)
    }
}

#[pymodule]
fn deocc(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(run, m)?)?;
    m.add_function(wrap_pyfunction!(read_scene, m)?)?;
    m.add_function(wrap_pyfunction!(read_ply, m)?)?;
    m.add_function(wrap_pyfunction!(grasp, m)?)?;
    m.add_function(wrap_pyfunction!(target_at, m)?)?;
    m.add_function(wrap_pyfunction!(place, m)?)?;
    m.add_function(wrap_pyfunction!(placing_options, m)?)?;
    m.add_class::<Client>()?;
    Ok(())
}
