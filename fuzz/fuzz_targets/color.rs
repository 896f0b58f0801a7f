//! The colour decoders (JPEG, PNG, raw RGB8) on any payload, and on valid
//! payloads with one byte changed (the target encodes the input's pixels itself):
//! a decoded image always has the declared size and three bytes per pixel.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stillmap_proto::codec::{self, ColorImage};
use stillmap_proto::pb::ColorEncoding;

fuzz_target!(|data: &[u8]| {
    let [w, h, e, mode, rest @ ..] = data else { return };
    let (width, height) = (1 + u32::from(*w % 64), 1 + u32::from(*h % 64));
    let encoding = [ColorEncoding::Jpeg, ColorEncoding::Png, ColorEncoding::Rgb8][usize::from(*e % 3)];
    let payload = if mode & 1 == 0 {
        rest.to_vec()
    } else {
        let n = (width * height * 3) as usize;
        let image = ColorImage { width, height, data: (0..n).map(|i| rest.get(i).copied().unwrap_or(0)).collect() };
        let mut encoded = codec::encode_color(encoding, &image, 90).expect("encode");
        if mode & 2 != 0 && !encoded.is_empty() {
            let at = usize::from(mode >> 2) * encoded.len() / 64;
            let at = at.min(encoded.len() - 1);
            encoded[at] ^= rest.last().copied().unwrap_or(1) | 1;
        }
        encoded
    };
    if let Ok(image) = codec::decode_color(encoding, &payload, width, height) {
        assert_eq!((image.width, image.height), (width, height));
        assert_eq!(image.data.len(), (width * height * 3) as usize);
    }
});
