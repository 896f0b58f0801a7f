//! The map import (`POST /api/v1/maps/import`): any file, and any body behind
//! the magic compressed as an export is (so the fuzzer reaches the sections).
//! An accepted file's blocks are within the map's range and it exports and
//! imports again to the same session.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stillmap_server::store::{EXPORT_MAGIC, export, import_file};

/// Uncompressed bytes an import may hold here (the server's default is larger;
/// the cap is what is under test, not its value).
const MAX_BYTES: usize = 1 << 22;

fuzz_target!(|data: &[u8]| {
    let [mode, rest @ ..] = data else { return };
    let file = if mode & 1 == 0 {
        rest.to_vec()
    } else {
        let mut file = EXPORT_MAGIC.to_vec();
        file.extend(zstd::bulk::compress(rest, 1).expect("compress"));
        file
    };
    if let Ok(session) = import_file(&file, MAX_BYTES) {
        assert!(session.blocks.iter().all(|(key, _)| stillmap_mapping::voxel::block_in_range(*key)));
        let again = export(&session).expect("an imported session exports");
        let back = import_file(&again, usize::MAX).expect("an export imports");
        assert_eq!(back.id, session.id);
        assert_eq!(back.poses, session.poses);
        assert_eq!(back.blocks.len(), session.blocks.len());
    }
});
