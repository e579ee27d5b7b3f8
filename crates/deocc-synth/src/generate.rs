//! One entry point for every kind of scene.

use crate::scene::{indoor_scene, Scene, SceneConfig, SceneKind};
use crate::SynthError;

/// The scene of `config.kind` for `seed`: a config and a seed fix it.
pub fn generate_scene(config: &SceneConfig, seed: u64) -> Result<Scene, SynthError> {
    match config.kind {
        SceneKind::Indoor => indoor_scene(config, seed),
        SceneKind::Pickup => crate::tasks::pickup_scene(config, seed),
        SceneKind::PickupV2 => crate::tasks::pickup_v2_scene(config, seed),
        SceneKind::Place => crate::tasks::place_scene(config, seed),
    }
}
