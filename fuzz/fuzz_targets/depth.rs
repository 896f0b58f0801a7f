//! The depth decoders (PNG16, RVL, zstd) on any payload: a decoded image always
//! has the declared size, and encoding it again round-trips exactly.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stillmap_proto::codec;
use stillmap_proto::pb::DepthEncoding;

fuzz_target!(|data: &[u8]| {
    let [w, h, e, payload @ ..] = data else { return };
    let (width, height) = (1 + u32::from(*w % 64), 1 + u32::from(*h % 64));
    let encoding = [DepthEncoding::Png16, DepthEncoding::Rvl, DepthEncoding::Zstd][usize::from(*e % 3)];
    if let Ok(image) = codec::decode_depth(encoding, payload, width, height) {
        assert_eq!((image.width, image.height), (width, height));
        assert_eq!(image.data.len(), (width * height) as usize);
        let again = codec::encode_depth(encoding, &image).expect("a decoded image encodes");
        assert_eq!(codec::decode_depth(encoding, &again, width, height).expect("round trip"), image);
    }
});
