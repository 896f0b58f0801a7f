//! The depth decoders (PNG16, RVL, zstd) on any payload, and on valid payloads
//! with one byte changed (the target encodes the input's pixels itself, so the
//! fuzzer reaches past the containers' checksums): a decoded image always has
//! the declared size, and encoding it again round-trips exactly.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stillmap_proto::codec::{self, DepthImage};
use stillmap_proto::pb::DepthEncoding;

fuzz_target!(|data: &[u8]| {
    let [w, h, e, mode, rest @ ..] = data else { return };
    let (width, height) = (1 + u32::from(*w % 64), 1 + u32::from(*h % 64));
    let encoding = [DepthEncoding::Png16, DepthEncoding::Rvl, DepthEncoding::Zstd][usize::from(*e % 3)];
    let payload = if mode & 1 == 0 {
        rest.to_vec()
    } else {
        let pixel = |i: usize| u16::from_le_bytes([rest.get(2 * i).copied().unwrap_or(0), rest.get(2 * i + 1).copied().unwrap_or(0)]);
        let image = DepthImage { width, height, data: (0..(width * height) as usize).map(pixel).collect() };
        let mut encoded = codec::encode_depth(encoding, &image).expect("encode");
        // The mode's upper bits pick a byte to change, the last input byte its new value.
        if mode & 2 != 0 && !encoded.is_empty() {
            let at = usize::from(mode >> 2) * encoded.len() / 64;
            let at = at.min(encoded.len() - 1);
            encoded[at] ^= rest.last().copied().unwrap_or(1) | 1;
        }
        encoded
    };
    if let Ok(image) = codec::decode_depth(encoding, &payload, width, height) {
        assert_eq!((image.width, image.height), (width, height));
        assert_eq!(image.data.len(), (width * height) as usize);
        let again = codec::encode_depth(encoding, &image).expect("a decoded image encodes");
        assert_eq!(codec::decode_depth(encoding, &again, width, height).expect("round trip"), image);
    }
});
