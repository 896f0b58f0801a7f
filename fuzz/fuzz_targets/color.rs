//! The colour decoders (JPEG, PNG, raw RGB8) on any payload: a decoded image
//! always has the declared size and three bytes per pixel.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stillmap_proto::codec;
use stillmap_proto::pb::ColorEncoding;

fuzz_target!(|data: &[u8]| {
    let [w, h, e, payload @ ..] = data else { return };
    let (width, height) = (1 + u32::from(*w % 64), 1 + u32::from(*h % 64));
    let encoding = [ColorEncoding::Jpeg, ColorEncoding::Png, ColorEncoding::Rgb8][usize::from(*e % 3)];
    if let Ok(image) = codec::decode_color(encoding, payload, width, height) {
        assert_eq!((image.width, image.height), (width, height));
        assert_eq!(image.data.len(), (width * height * 3) as usize);
    }
});
