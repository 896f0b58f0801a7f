//! The shipped vocabulary is what its build step makes: retrained from the public
//! clip with the fixed seed, it is the same, byte for byte (a golden test).

use stillmap_places::training;

use stillmap_places::Vocabulary;

#[test]
fn the_shipped_vocabulary_is_its_build_steps_output() {
    let trained = training::train_shipped().expect("train");
    let shipped = Vocabulary::shipped();
    assert_eq!(trained.words(), shipped.words());
    assert!(trained.to_bytes() == shipped.to_bytes(), "places/vocabulary/fr1_rpy.smvoc is stale: run `make vocabulary`");
}
