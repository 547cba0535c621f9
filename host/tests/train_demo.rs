//! `himap train-demo`'s loop (the parallel CPU backend on the synthetic room) learns. The
//! backends' bit-for-bit agreement with the core's reference is the conformance suite's
//! (`tests/tests/conformance.rs`).

use himap::dump::small_config;
use himap_core::field::model::ModelLayout;
use himap_core::field::render::RenderMode;

#[test]
fn demo_training_reduces_the_loss() {
    let layout = ModelLayout::new(&small_config(RenderMode::SdfDensity)).unwrap();
    let (first, last) = himap::train_demo::run(layout, 60, 256, 2, 1, |_, _, _| {}, 10).unwrap();
    assert!(last < 0.8 * first, "loss {first} -> {last}");
}
