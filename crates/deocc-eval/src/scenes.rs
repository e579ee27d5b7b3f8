//! Benchmark scenes as pipeline input.

use deocc_io::scene::SceneInput;

/// The same scene without its instance maps (for the default segmenter).
pub fn unlabelled(mut scene: SceneInput) -> SceneInput {
    for f in &mut scene.frames {
        f.instances = None;
    }
    scene
}
