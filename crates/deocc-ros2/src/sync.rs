//! Matching colour, depth, calibration and pose messages into views by their header stamps
//! (message_filters' ApproximateTime, for one camera), and keeping the newest views as the
//! robot moves.
//!
//! A view is made when a colour and a depth image lie within `slop` of each other and, if poses
//! are used, a pose lies within `slop` of the depth image; the newest CameraInfo is used (it
//! changes rarely). Unmatched messages wait in short queues (`pending` each, oldest dropped), so
//! memory stays bounded however the topics arrive.

use std::collections::VecDeque;

use crate::convert::View;
use crate::msgs::{CameraInfo, Image, PoseStamped};

/// How views are formed and kept.
#[derive(Debug, Clone)]
pub struct SyncConfig {
    /// Largest stamp difference inside one view, nanoseconds.
    pub slop_ns: i64,
    /// Views kept (the newest); a completion uses all of them.
    pub max_views: usize,
    /// Whether every view needs a pose (a pose topic is subscribed).
    pub use_pose: bool,
    /// Unmatched messages kept per topic.
    pub pending: usize,
    /// A view closer in time than this to the newest kept one is not kept, nanoseconds (a
    /// camera at 30 Hz would otherwise fill the window with near-copies in a third of a
    /// second). 0 keeps every view.
    pub min_interval_ns: i64,
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self {
            slop_ns: 20_000_000,
            max_views: 10,
            use_pose: false,
            pending: 8,
            min_interval_ns: 0,
        }
    }
}

/// The synchroniser's state.
#[derive(Debug, Default)]
pub struct Synchronizer {
    cfg: SyncConfig,
    rgb: VecDeque<Image>,
    depth: VecDeque<Image>,
    poses: VecDeque<PoseStamped>,
    info: Option<CameraInfo>,
    views: VecDeque<View>,
    made: u64,
}

fn push_bounded<T>(q: &mut VecDeque<T>, v: T, cap: usize) {
    q.push_back(v);
    while q.len() > cap.max(1) {
        q.pop_front();
    }
}

impl Synchronizer {
    pub fn new(cfg: SyncConfig) -> Self {
        Self {
            cfg,
            ..Default::default()
        }
    }

    pub fn config(&self) -> &SyncConfig {
        &self.cfg
    }

    pub fn push_rgb(&mut self, m: Image) {
        push_bounded(&mut self.rgb, m, self.cfg.pending);
        self.try_match();
    }

    pub fn push_depth(&mut self, m: Image) {
        push_bounded(&mut self.depth, m, self.cfg.pending);
        self.try_match();
    }

    pub fn push_info(&mut self, m: CameraInfo) {
        self.info = Some(m);
        self.try_match();
    }

    pub fn push_pose(&mut self, m: PoseStamped) {
        push_bounded(&mut self.poses, m, self.cfg.pending.max(64));
        self.try_match();
    }

    /// The views kept, oldest first.
    pub fn views(&self) -> &VecDeque<View> {
        &self.views
    }

    /// Views made so far (including those since dropped from the window).
    pub fn made(&self) -> u64 {
        self.made
    }

    /// Forgets the kept views (pending messages stay).
    pub fn clear_views(&mut self) {
        self.views.clear();
    }

    /// What is missing before the first view, for a trigger answered with no view.
    pub fn waiting_for(&self) -> Vec<&'static str> {
        let mut w = Vec::new();
        if self.rgb.is_empty() {
            w.push("colour image");
        }
        if self.depth.is_empty() {
            w.push("depth image");
        }
        if self.info.is_none() {
            w.push("camera info");
        }
        if self.cfg.use_pose && self.poses.is_empty() {
            w.push("pose");
        }
        w
    }

    fn try_match(&mut self) {
        let Some(info) = self.info.clone() else {
            return;
        };
        // The newest depth image with a colour image (and a pose) within the slop.
        for di in (0..self.depth.len()).rev() {
            let t = self.depth[di].header.stamp.nanos();
            let Some(ri) = nearest(self.rgb.iter().map(|m| m.header.stamp.nanos()), t)
                .filter(|&(_, dt)| dt <= self.cfg.slop_ns)
                .map(|(i, _)| i)
            else {
                continue;
            };
            let pi = if self.cfg.use_pose {
                match nearest(self.poses.iter().map(|m| m.header.stamp.nanos()), t)
                    .filter(|&(_, dt)| dt <= self.cfg.slop_ns)
                {
                    Some((i, _)) => Some(i),
                    None => continue,
                }
            } else {
                None
            };
            let rgb_stamp = self.rgb[ri].header.stamp.nanos();
            let depth = self.depth.drain(..=di).next_back().expect("index in range");
            let rgb = self.rgb.drain(..=ri).next_back().expect("index in range");
            // Colour images older than the matched one can no longer match a newer depth.
            self.rgb.retain(|m| m.header.stamp.nanos() > rgb_stamp);
            let pose = pi.map(|i| self.poses[i].clone());
            self.add(View {
                rgb,
                depth,
                info,
                pose,
            });
            return;
        }
    }

    fn add(&mut self, v: View) {
        self.made += 1;
        if let Some(last) = self.views.back() {
            if v.stamp() <= last.stamp() {
                return; // out of order or a repeat: keep time moving forward
            }
            if v.stamp() - last.stamp() < self.cfg.min_interval_ns {
                return;
            }
        }
        push_bounded(&mut self.views, v, self.cfg.max_views);
    }
}

/// Index and distance of the stamp nearest `t`.
fn nearest(stamps: impl Iterator<Item = i64>, t: i64) -> Option<(usize, i64)> {
    stamps
        .enumerate()
        .map(|(i, s)| (i, (s - t).abs()))
        .min_by_key(|&(_, d)| d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Time};

    fn img(ns: i64) -> Image {
        Image {
            header: Header {
                stamp: Time::from_nanos(ns),
                frame_id: "cam".into(),
            },
            ..Default::default()
        }
    }

    fn pose(ns: i64) -> PoseStamped {
        PoseStamped {
            header: Header {
                stamp: Time::from_nanos(ns),
                frame_id: "world".into(),
            },
            ..Default::default()
        }
    }

    const MS: i64 = 1_000_000;

    #[test]
    fn views_form_within_the_slop_only() {
        let mut s = Synchronizer::new(SyncConfig::default());
        s.push_rgb(img(100 * MS));
        s.push_depth(img(105 * MS));
        assert!(s.views().is_empty(), "no camera info yet");
        assert_eq!(s.waiting_for(), vec!["camera info"]);
        s.push_info(CameraInfo::default());
        assert_eq!(s.views().len(), 1);
        assert_eq!(s.views()[0].stamp(), 105 * MS);
        // 30 ms apart: more than the 20 ms slop.
        s.push_rgb(img(200 * MS));
        s.push_depth(img(230 * MS));
        assert_eq!(s.views().len(), 1);
        s.push_rgb(img(235 * MS));
        assert_eq!(s.views().len(), 2);
        assert_eq!(s.views()[1].rgb.header.stamp.nanos(), 235 * MS);
    }

    #[test]
    fn poses_are_required_when_used_and_matched_by_stamp() {
        let mut s = Synchronizer::new(SyncConfig {
            use_pose: true,
            ..Default::default()
        });
        s.push_info(CameraInfo::default());
        s.push_rgb(img(100 * MS));
        s.push_depth(img(100 * MS));
        assert!(s.views().is_empty());
        assert_eq!(s.waiting_for(), vec!["pose"]);
        s.push_pose(pose(50 * MS));
        assert!(s.views().is_empty(), "50 ms away");
        s.push_pose(pose(110 * MS));
        s.push_pose(pose(95 * MS));
        // The pose arrived after the images: the view forms when it does, with the nearest.
        assert_eq!(s.views().len(), 1);
        assert_eq!(
            s.views()[0].pose.as_ref().unwrap().header.stamp.nanos(),
            110 * MS
        );
    }

    #[test]
    fn the_window_keeps_the_newest_views_and_memory_is_bounded() {
        let mut s = Synchronizer::new(SyncConfig {
            max_views: 3,
            ..Default::default()
        });
        s.push_info(CameraInfo::default());
        for k in 0..10 {
            s.push_rgb(img(k * 100 * MS));
            s.push_depth(img(k * 100 * MS + MS));
        }
        let stamps: Vec<i64> = s.views().iter().map(View::stamp).collect();
        assert_eq!(stamps, vec![701 * MS, 801 * MS, 901 * MS]);
        assert_eq!(s.made(), 10);
        // A flood of colour images with no depth never grows past `pending`.
        for k in 0..1000 {
            s.push_rgb(img(10_000 * MS + k));
        }
        assert!(s.rgb.len() <= s.config().pending);
        // Repeats and stamps going backwards do not enter the window.
        s.push_depth(img(801 * MS));
        assert_eq!(s.views().back().unwrap().stamp(), 901 * MS);
    }

    #[test]
    fn views_closer_than_the_interval_are_not_kept() {
        let mut s = Synchronizer::new(SyncConfig {
            min_interval_ns: 500 * MS,
            ..Default::default()
        });
        s.push_info(CameraInfo::default());
        for k in 0..10 {
            s.push_rgb(img(k * 100 * MS));
            s.push_depth(img(k * 100 * MS));
        }
        let stamps: Vec<i64> = s.views().iter().map(View::stamp).collect();
        assert_eq!(stamps, vec![0, 500 * MS]);
        assert_eq!(s.made(), 10);
    }
}
