//! Stage: output. A run's output folder, written so that nothing is ever lost or half-written:
//!
//! ```text
//! OUT/
//!   completed.ply                 x y z, red green blue, instance (u32), generated (u8 provenance),
//!                                 confidence (f32)
//!   observed.ply                  the visible-only cloud
//!   instances/instance_NNNN.ply   each completed instance, observed and generated points
//!   report.json                   the run report (+ the evaluation against ground truth, if any)
//!   render_input_view.png         before / after from the first view, completed object points in
//!                                 magenta, plane fill tinted magenta
//!   render_novel_view.png         the same from higher up and to the side
//!   render_occluders_removed.png  before / after from the first view without the objects that
//!                                 hid the completed ones (when there are any)
//!   render_objects.png            each completed object (first eight): observed only beside
//!                                 observed + generated, from a view of its hidden side
//!   objects/object_NNNN.png       the same panel for every completed object
//!   report.html                   one self-contained page: an interactive 3-D view of the cloud
//!                                 (toggle provenance and instances, colour by confidence), the
//!                                 pictures and the run's figures
//! ```
//!
//! [`Staging`] assembles the folder beside `OUT` (`.OUT.partial-PID`) and swaps it in only when
//! everything succeeded: the previous output is renamed aside, the new one renamed into place,
//! the old one removed, so at every instant a complete version exists (a run killed between the
//! two renames leaves `.OUT.old-PID`, which the next run puts back). A lock file (`.OUT.lock`)
//! keeps two runs from writing the same `OUT`; staging folders, locks and set-aside outputs of
//! processes that no longer run are cleaned up by the next run. `OUT` may not be, contain or lie
//! inside the input folder.

use std::path::{Path, PathBuf};

use deocc_geometry::camera::look_at;
use deocc_geometry::Camera;
use deocc_io::ply::write_point_cloud;
use deocc_io::scene::SceneInput;
use deocc_io::PlyEncoding;
use nalgebra::{Point3, Vector3};
use serde::Serialize;

use crate::pictures::captioned;
use crate::render::{side_by_side, splat};
use crate::{PipelineError, PipelineOutput, RunReport};

/// The file that marks a folder as a deocc run's output (it may then be replaced).
pub const REPORT_FILE: &str = "report.json";

/// Whether `dir` holds a finished run's output: a `report.json` that is a run report (a JSON
/// object with the run's point counts) and a non-empty `completed.ply`. An empty or truncated
/// report is not one (a batch rerun redoes that scene instead of skipping it).
pub fn is_complete_output(dir: &Path) -> bool {
    let report = std::fs::read(dir.join(REPORT_FILE))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok());
    let is_report = report.as_ref().is_some_and(|r| {
        r.get("points_observed").is_some_and(|v| v.is_u64())
            && r.get("points_generated").is_some_and(|v| v.is_u64())
    });
    let has_cloud = std::fs::metadata(dir.join("completed.ply")).is_ok_and(|m| m.len() > 0);
    is_report && has_cloud
}

fn err(path: &Path, msg: impl Into<String>) -> PipelineError {
    PipelineError::input(path, msg)
}

/// `path` made absolute without requiring it to exist (its parent must, or be creatable).
fn absolute(path: &Path) -> Result<PathBuf, PipelineError> {
    if let Ok(p) = path.canonicalize() {
        return Ok(p);
    }
    let name = path
        .file_name()
        .ok_or_else(|| err(path, "not a folder name"))?;
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| {
        err(
            &parent,
            format!("cannot create the output's parent folder: {e}"),
        )
    })?;
    let parent = parent
        .canonicalize()
        .map_err(|e| err(&parent, e.to_string()))?;
    Ok(parent.join(name))
}

/// Whether process `pid` still runs (Linux: `/proc/PID` exists; elsewhere assumed running).
fn process_alive(pid: u32) -> bool {
    if cfg!(target_os = "linux") {
        Path::new("/proc").join(pid.to_string()).exists()
    } else {
        true
    }
}

/// An output folder being assembled. Dropped without [`Staging::commit`], it removes its work.
pub struct Staging {
    out: PathBuf,
    dir: PathBuf,
    lock: PathBuf,
    committed: bool,
}

impl Staging {
    /// Checks where the output goes, takes its lock, cleans up after dead runs, and makes the
    /// staging folder. `input` is the scene folder read (none for a generated example).
    pub fn begin(out: &Path, input: Option<&Path>) -> Result<Self, PipelineError> {
        let out_abs = absolute(out)?;
        let cwd = std::env::current_dir()
            .ok()
            .and_then(|c| c.canonicalize().ok());
        if cwd.as_deref() == Some(out_abs.as_path()) {
            return Err(err(
                out,
                "is the current folder; name a folder for the output (it is replaced as a whole)",
            ));
        }
        if let Some(input) = input {
            let input_abs = input
                .canonicalize()
                .map_err(|e| err(input, e.to_string()))?;
            if out_abs == input_abs || out_abs.starts_with(&input_abs) {
                return Err(err(
                    out,
                    format!(
                        "lies inside the input scene {}; choose a folder outside it",
                        input.display()
                    ),
                ));
            }
            if input_abs.starts_with(&out_abs) {
                return Err(err(
                    out,
                    format!(
                        "contains the input scene {}; replacing it would delete the input",
                        input.display()
                    ),
                ));
            }
        }
        if out_abs.exists() {
            let is_run = out_abs.join(REPORT_FILE).is_file();
            let empty = out_abs
                .read_dir()
                .map(|mut d| d.next().is_none())
                .unwrap_or(false);
            if !out_abs.is_dir() || !(is_run || empty) {
                return Err(err(
                    out,
                    "exists and is not a previous deocc run's output; choose an empty or new folder",
                ));
            }
        }
        let parent = out_abs
            .parent()
            .ok_or_else(|| err(out, "has no parent folder"))?
            .to_path_buf();
        let name = out_abs
            .file_name()
            .ok_or_else(|| err(out, "not a folder name"))?
            .to_string_lossy()
            .into_owned();
        let lock = parent.join(format!(".{name}.lock"));
        take_lock(&lock, out)?;
        let me = std::process::id();
        clean_dead(&parent, &name, &out_abs);
        let dir = parent.join(format!(".{name}.partial-{me}"));
        if dir.exists() {
            let _ = std::fs::remove_dir_all(&dir);
        }
        if let Err(e) = std::fs::create_dir_all(&dir) {
            let _ = std::fs::remove_file(&lock);
            return Err(err(&dir, format!("cannot write here: {e}")));
        }
        Ok(Self {
            out: out_abs,
            dir,
            lock,
            committed: false,
        })
    }

    /// The folder to write into.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Where the output will be.
    pub fn out(&self) -> &Path {
        &self.out
    }

    /// Swaps the staged folder in (see the module docs) and releases the lock.
    pub fn commit(mut self) -> Result<PathBuf, PipelineError> {
        let me = std::process::id();
        let parent = self.dir.parent().unwrap_or(Path::new(".")).to_path_buf();
        let name = self
            .out
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let aside = parent.join(format!(".{name}.old-{me}"));
        let had_old = self.out.exists();
        if had_old {
            std::fs::rename(&self.out, &aside).map_err(|e| {
                err(
                    &self.out,
                    format!("cannot move the previous output aside: {e}"),
                )
            })?;
        }
        if let Err(e) = std::fs::rename(&self.dir, &self.out) {
            if had_old {
                let _ = std::fs::rename(&aside, &self.out);
            }
            return Err(err(
                &self.out,
                format!("cannot move the output into place: {e}"),
            ));
        }
        self.committed = true;
        if had_old {
            let _ = std::fs::remove_dir_all(&aside);
        }
        let _ = std::fs::remove_file(&self.lock);
        Ok(self.out.clone())
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.dir);
            let _ = std::fs::remove_file(&self.lock);
        }
    }
}

/// This machine's host name and boot id (Linux), `-` where unknown.
fn host_and_boot() -> (String, String) {
    let read = |p: &str| {
        std::fs::read_to_string(p)
            .ok()
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty() && !s.contains(char::is_whitespace))
            .unwrap_or_else(|| "-".into())
    };
    (
        read("/proc/sys/kernel/hostname"),
        read("/proc/sys/kernel/random/boot_id"),
    )
}

/// When process `pid` started (clock ticks since boot, `/proc/PID/stat` field 22), if it runs.
fn process_start(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces: count after its end.
    let after = &stat[stat.rfind(')')? + 1..];
    after.split_whitespace().nth(19)?.parse().ok()
}

/// What a lock file says of its holder: PID, host, boot id and the process's start time. A PID
/// alone is not enough: in a container every run is PID 1, so a lock left by a killed run names
/// a live process (the next run itself) forever.
fn lock_line() -> String {
    let pid = std::process::id();
    let (host, boot) = host_and_boot();
    let start = process_start(pid).map_or("-".to_string(), |s| s.to_string());
    format!("{pid} {host} {boot} {start}\n")
}

/// The PID holding a lock written by [`lock_line`], if that very process still runs here. An
/// unreadable lock, or one from another host, another boot, or a process since replaced by
/// another with its PID, is stale.
fn live_holder(text: &str) -> Option<u32> {
    let words: Vec<&str> = text.split_whitespace().collect();
    let [pid, host, boot, start] = words[..] else {
        return None;
    };
    let pid: u32 = pid.parse().ok()?;
    if !cfg!(target_os = "linux") {
        return Some(pid);
    }
    let (my_host, my_boot) = host_and_boot();
    if host != my_host || boot != my_boot || !process_alive(pid) {
        return None;
    }
    match (start.parse::<u64>().ok(), process_start(pid)) {
        (Some(a), Some(b)) if a == b => Some(pid),
        _ => None,
    }
}

/// Creates the lock file naming this process; takes over a lock whose process is gone.
fn take_lock(lock: &Path, out: &Path) -> Result<(), PipelineError> {
    use std::io::Write;
    for _ in 0..2 {
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(lock)
        {
            Ok(mut f) => {
                let _ = f.write_all(lock_line().as_bytes());
                return Ok(());
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                let holder = std::fs::read_to_string(lock)
                    .ok()
                    .and_then(|s| live_holder(&s));
                match holder {
                    Some(pid) if pid != std::process::id() => {
                        return Err(err(
                            out,
                            format!(
                                "another deocc process (PID {pid}) is writing this output; \
                                 wait for it, or remove {} if it is gone",
                                lock.display()
                            ),
                        ));
                    }
                    _ => {
                        let _ = std::fs::remove_file(lock);
                    }
                }
            }
            Err(e) => return Err(err(lock, format!("cannot create the lock file: {e}"))),
        }
    }
    Err(err(lock, "cannot take the lock"))
}

/// Removes staging folders of dead runs, and puts back an output a dead run had set aside.
fn clean_dead(parent: &Path, name: &str, out: &Path) {
    let Ok(entries) = parent.read_dir() else {
        return;
    };
    let partial = format!(".{name}.partial-");
    let old = format!(".{name}.old-");
    for e in entries.flatten() {
        let file = e.file_name().to_string_lossy().into_owned();
        let pid_of = |prefix: &str| file.strip_prefix(prefix)?.parse::<u32>().ok();
        if let Some(pid) = pid_of(&partial) {
            if !process_alive(pid) {
                let _ = std::fs::remove_dir_all(e.path());
            }
        } else if let Some(pid) = pid_of(&old) {
            if !process_alive(pid) {
                if out.exists() {
                    let _ = std::fs::remove_dir_all(e.path());
                } else {
                    let _ = std::fs::rename(e.path(), out);
                }
            }
        }
    }
}

/// The report file: where the input was, the run report, and the evaluation when there is one.
#[derive(Serialize)]
struct ReportFile<'a, E: Serialize> {
    input: String,
    #[serde(flatten)]
    run: &'a RunReport,
    evaluation: Option<E>,
}

/// Writes a run's output folder into `dir` (a [`Staging`] folder): clouds, instances, pictures
/// and `report.json` naming `input` (where the scene is, after the run) and carrying
/// `evaluation`.
pub fn write_output<E: Serialize>(
    dir: &Path,
    input: &Path,
    scene: &SceneInput,
    result: &PipelineOutput,
    evaluation: Option<E>,
) -> Result<(), PipelineError> {
    write_point_cloud(
        &dir.join("completed.ply"),
        &result.completed,
        PlyEncoding::BinaryLittleEndian,
    )?;
    write_point_cloud(
        &dir.join("observed.ply"),
        &result.observed,
        PlyEncoding::BinaryLittleEndian,
    )?;
    let inst_dir = dir.join("instances");
    std::fs::create_dir_all(&inst_dir).map_err(|e| err(&inst_dir, e.to_string()))?;
    let ids = result.completed.instance.as_deref().unwrap_or(&[]);
    for inst in &result.report.instances {
        let one = result
            .completed
            .filter(|i| ids.get(i) == Some(&(inst.instance_id as u32)));
        write_point_cloud(
            &inst_dir.join(format!("instance_{:04}.ply", inst.instance_id)),
            &one,
            PlyEncoding::BinaryLittleEndian,
        )?;
    }
    write_pictures(dir, scene, result)?;
    let report = ReportFile {
        input: input.display().to_string(),
        run: &result.report,
        evaluation,
    };
    deocc_io::cameras::write_json(&dir.join(REPORT_FILE), &report)?;
    let as_json = serde_json::to_value(&report).map_err(|e| err(dir, e.to_string()))?;
    crate::report_html::write_report_html(
        dir,
        &result.completed,
        scene.frames.first().map(|f| &f.camera),
        &as_json,
    )?;
    Ok(())
}

/// The camera of the novel-view picture: from 1.2 m to the side of the first view and 0.6 m
/// higher, looking at the observed cloud's centroid.
pub fn novel_view_camera(first: &Camera, focus: &Point3<f32>) -> Option<Camera> {
    let eye = first.center()
        + (focus - first.center()).cross(&Vector3::z()).normalize() * 1.2
        + Vector3::new(0.0, 0.0, 0.6);
    let pose = look_at(&eye, focus, &Vector3::z()).ok()?;
    Some(Camera {
        intrinsics: first.intrinsics,
        world_from_camera: pose,
    })
}

fn write_pictures(
    dir: &Path,
    scene: &SceneInput,
    result: &PipelineOutput,
) -> Result<(), PipelineError> {
    let Some(first) = scene.frames.first() else {
        return Ok(());
    };
    let cam = first.camera;
    let legend: &[([u8; 3], &str)] = &[
        (crate::render::GENERATED_COLOR, "generated object points"),
        ([200, 120, 170], "plane fill (tinted)"),
    ];
    let before = splat(&result.observed, &cam, 1, true);
    let after = splat(&result.completed, &cam, 1, true);
    deocc_io::images::write_rgb_png(
        &dir.join("render_input_view.png"),
        &captioned(
            &side_by_side(&before, &after),
            "input view - left: observed, right: completed",
            legend,
        ),
    )?;
    let focus = result.observed.centroid().unwrap_or(Point3::origin());
    if let Some(novel) = novel_view_camera(&cam, &focus) {
        let b = splat(&result.observed, &novel, 1, true);
        let c = splat(&result.completed, &novel, 1, true);
        deocc_io::images::write_rgb_png(
            &dir.join("render_novel_view.png"),
            &captioned(
                &side_by_side(&b, &c),
                "novel view - left: observed, right: completed",
                legend,
            ),
        )?;
    }
    // One panel per completed object, from a viewpoint that sees its hidden side.
    let completed_ids: Vec<u32> = result
        .report
        .instances
        .iter()
        .filter(|i| i.generated_points > 0)
        .map(|i| i.instance_id as u32)
        .collect();
    let panels = crate::pictures::object_panels(&result.completed, &completed_ids, &cam);
    if !panels.is_empty() {
        let obj_dir = dir.join("objects");
        std::fs::create_dir_all(&obj_dir).map_err(|e| err(&obj_dir, e.to_string()))?;
        for (id, p) in &panels {
            deocc_io::images::write_rgb_png(&obj_dir.join(format!("object_{id:04}.png")), p)?;
        }
        let firsts: Vec<&image::RgbImage> = panels
            .iter()
            .take(crate::pictures::MAX_STACKED)
            .map(|(_, p)| p)
            .collect();
        if let Some(all) = crate::pictures::stacked(&firsts) {
            deocc_io::images::write_rgb_png(&dir.join("render_objects.png"), &all)?;
        }
    }
    let hid = occluders_of_completed(&result.report, &scene.structure_ids);
    if !hid.is_empty() {
        let without = |c: &deocc_geometry::PointCloud| {
            let ids = c.instance.as_deref().unwrap_or(&[]);
            c.filter(|i| !ids.get(i).is_some_and(|id| hid.contains(id)))
        };
        let before = splat(&without(&result.observed), &cam, 1, true);
        let after = splat(&without(&result.completed), &cam, 1, true);
        deocc_io::images::write_rgb_png(
            &dir.join("render_occluders_removed.png"),
            &captioned(
                &side_by_side(&before, &after),
                "occluders hidden - left: observed, right: completed",
                legend,
            ),
        )?;
    }
    Ok(())
}

/// The instances that hide a completed object in the first view (room structure and completed
/// objects themselves aside): what the occluders-removed picture leaves out.
pub fn occluders_of_completed(report: &RunReport, structure: &[u16]) -> Vec<u32> {
    let completed: Vec<u16> = report
        .instances
        .iter()
        .filter(|i| i.generated_points > 0)
        .map(|i| i.instance_id)
        .collect();
    let mut out: Vec<u32> = report
        .occlusion
        .first()
        .into_iter()
        .flatten()
        .filter(|m| completed.contains(&m.instance_id))
        .flat_map(|m| m.occluded_by.iter().copied())
        .filter(|o| !completed.contains(o) && !structure.contains(o))
        .map(u32::from)
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lock_names_its_process_and_only_that_process_holds_it() {
        let me = std::process::id();
        assert_eq!(live_holder(&lock_line()), Some(me));
        let (host, boot) = host_and_boot();
        let start = process_start(me).unwrap();
        // PID 1 is alive in every container: a lock naming it from another pod, another boot,
        // or with another start time is stale.
        for stale in [
            format!("1 another-pod {boot} {start}"),
            format!("{me} {host} 00000000-dead-beef {start}"),
            format!("{me} {host} {boot} {}", start + 1),
            "1".to_string(),
            format!("{me}"),
            String::new(),
            "garbage".to_string(),
        ] {
            assert_eq!(live_holder(&stale), None, "{stale:?}");
        }
    }

    #[test]
    fn a_leftover_lock_of_a_dead_or_foreign_run_does_not_block_the_output() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let (_, boot) = host_and_boot();
        std::fs::write(dir.path().join(".out.lock"), format!("1 pod-7 {boot} 42\n")).unwrap();
        let staging = Staging::begin(&out, None).unwrap();
        std::fs::write(staging.dir().join("x"), b"1").unwrap();
        staging.commit().unwrap();
        assert!(out.join("x").is_file());
        assert!(!dir.path().join(".out.lock").exists());
    }

    #[test]
    fn an_empty_or_foreign_report_is_not_a_finished_output() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        assert!(!is_complete_output(d));
        std::fs::write(d.join(REPORT_FILE), b"").unwrap();
        std::fs::write(d.join("completed.ply"), b"ply\n").unwrap();
        assert!(!is_complete_output(d));
        std::fs::write(d.join(REPORT_FILE), b"{}").unwrap();
        assert!(!is_complete_output(d));
        std::fs::write(
            d.join(REPORT_FILE),
            br#"{"points_observed": 10, "points_generated": 2}"#,
        )
        .unwrap();
        assert!(is_complete_output(d));
        std::fs::write(d.join("completed.ply"), b"").unwrap();
        assert!(!is_complete_output(d));
    }
}
