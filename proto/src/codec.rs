//! Colour and depth payload codecs of the wire contract.
//!
//! Depth is always lossless; the three encodings are measured against each other
//! on real TUM frames by `stillmap-client bench-codecs` (table in the README).
//! Decoders never trust the payload: sizes, bit depths and lengths are checked
//! against the session's `CameraInfo` and every failure names the problem.

use std::io::Cursor;

use crate::pb::{ColorEncoding, DepthEncoding};

/// Bytes per pixel of raw RGB8 colour.
const RGB8_BYTES_PER_PIXEL: usize = 3;
/// zstd level used for depth: level 1 is the fastest setting and, on depth
/// images, within a few percent of the ratio of level 3 (see the README table).
pub const DEPTH_ZSTD_LEVEL: i32 = 1;

/// A problem decoding or encoding a payload. The text names it.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum CodecError {
    #[error("{what} is {got_w}x{got_h}, but the session's camera is {want_w}x{want_h}")]
    SizeMismatch { what: &'static str, got_w: u32, got_h: u32, want_w: u32, want_h: u32 },
    #[error("depth PNG has {bits}-bit {color} samples, expected 16-bit greyscale")]
    DepthPngFormat { bits: u8, color: String },
    #[error("depth payload holds {got} bytes after decompression, expected {want} (16-bit, {width}x{height}){hint}")]
    DepthLength { got: usize, want: usize, width: u32, height: u32, hint: &'static str },
    #[error("RVL depth is malformed: {0}")]
    Rvl(&'static str),
    #[error("colour {encoding} payload is not decodable: {detail}")]
    Undecodable { encoding: &'static str, detail: String },
    #[error("colour PNG has {bits}-bit {color} samples, expected 8-bit RGB or RGBA")]
    ColorPngFormat { bits: u8, color: String },
    #[error("raw RGB8 colour holds {got} bytes, expected {want} ({width}x{height}x3)")]
    RgbLength { got: usize, want: usize, width: u32, height: u32 },
    #[error("{0} encoding is unspecified in the hello")]
    Unspecified(&'static str),
    #[error("encoding failed: {0}")]
    Encode(String),
}

/// A row-major 16-bit depth image in the sensor's units (0 = no measurement).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u16>,
}

/// A row-major RGB8 colour image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ColorImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl DepthImage {
    /// CRC-32 (IEEE) of the image as row-major little-endian u16: the value a
    /// `FrameResult.depth_crc32` carries.
    pub fn crc32(&self) -> u32 {
        /// Pixels converted per hashing step (a 4 KiB stack buffer).
        const CHUNK: usize = 2048;
        let mut hasher = crc32fast::Hasher::new();
        let mut buf = [0u8; CHUNK * 2];
        for pixels in self.data.chunks(CHUNK) {
            for (dst, v) in buf.chunks_exact_mut(2).zip(pixels) {
                dst.copy_from_slice(&v.to_le_bytes());
            }
            hasher.update(&buf[..pixels.len() * 2]);
        }
        hasher.finalize()
    }
}

fn pixel_count(width: u32, height: u32) -> usize {
    width as usize * height as usize
}

fn check_size(what: &'static str, got_w: u32, got_h: u32, want_w: u32, want_h: u32) -> Result<(), CodecError> {
    if (got_w, got_h) != (want_w, want_h) {
        return Err(CodecError::SizeMismatch { what, got_w, got_h, want_w, want_h });
    }
    Ok(())
}

// ------------------------------------------------------------------ depth

/// Encodes a depth image.
pub fn encode_depth(encoding: DepthEncoding, image: &DepthImage) -> Result<Vec<u8>, CodecError> {
    match encoding {
        DepthEncoding::Png16 => encode_png16(image),
        DepthEncoding::Rvl => Ok(rvl_encode(&image.data)),
        DepthEncoding::Zstd => {
            let bytes: Vec<u8> = image.data.iter().flat_map(|v| v.to_le_bytes()).collect();
            zstd::bulk::compress(&bytes, DEPTH_ZSTD_LEVEL).map_err(|e| CodecError::Encode(e.to_string()))
        }
        DepthEncoding::Unspecified => Err(CodecError::Unspecified("depth")),
    }
}

/// Decodes a depth payload that must be `width`×`height`.
pub fn decode_depth(encoding: DepthEncoding, payload: &[u8], width: u32, height: u32) -> Result<DepthImage, CodecError> {
    let want = pixel_count(width, height);
    let data = match encoding {
        DepthEncoding::Png16 => return decode_png16(payload, width, height),
        DepthEncoding::Rvl => rvl_decode(payload, want)?,
        DepthEncoding::Zstd => {
            // Cap the output one byte past the expected size so an oversized payload is
            // reported as such, never allocated without bound.
            let bytes = zstd::bulk::decompress(payload, want * 2 + 1)
                .map_err(|e| CodecError::Undecodable { encoding: "zstd depth", detail: e.to_string() })?;
            if bytes.len() != want * 2 {
                let hint = if bytes.len() == want { " — looks like 8-bit depth" } else { "" };
                return Err(CodecError::DepthLength { got: bytes.len(), want: want * 2, width, height, hint });
            }
            bytes.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect()
        }
        DepthEncoding::Unspecified => return Err(CodecError::Unspecified("depth")),
    };
    Ok(DepthImage { width, height, data })
}

fn encode_png16(image: &DepthImage) -> Result<Vec<u8>, CodecError> {
    let mut out = Vec::with_capacity(image.data.len());
    {
        let mut encoder = png::Encoder::new(&mut out, image.width, image.height);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Sixteen);
        encoder.set_compression(png::Compression::Fast);
        let mut writer = encoder.write_header().map_err(|e| CodecError::Encode(e.to_string()))?;
        let be: Vec<u8> = image.data.iter().flat_map(|v| v.to_be_bytes()).collect();
        writer.write_image_data(&be).map_err(|e| CodecError::Encode(e.to_string()))?;
    }
    Ok(out)
}

fn decode_png16(payload: &[u8], width: u32, height: u32) -> Result<DepthImage, CodecError> {
    let undecodable = |e: png::DecodingError| CodecError::Undecodable { encoding: "PNG16 depth", detail: e.to_string() };
    let decoder = png::Decoder::new(Cursor::new(payload));
    let mut reader = decoder.read_info().map_err(undecodable)?;
    let info = reader.info();
    let (w, h, bits, color) = (info.width, info.height, info.bit_depth, info.color_type);
    check_size("depth image", w, h, width, height)?;
    if bits != png::BitDepth::Sixteen || color != png::ColorType::Grayscale {
        return Err(CodecError::DepthPngFormat { bits: bits as u8, color: format!("{color:?}").to_lowercase() });
    }
    let mut buf = vec![0u8; pixel_count(w, h) * 2];
    reader.next_frame(&mut buf).map_err(undecodable)?;
    let data = buf.chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]])).collect();
    Ok(DepthImage { width, height, data })
}

/// RVL (Wilson, "Fast Lossless Depth Image Compression", ISS 2017): runs of zeros
/// and non-zeros, non-zero values as zig-zag deltas, all as variable-length
/// nibbles packed 8 to a little-endian u32 word, high nibble first. Byte-compatible
/// with the reference C code.
pub fn rvl_encode(pixels: &[u16]) -> Vec<u8> {
    let mut w = NibbleWriter::default();
    let mut i = 0;
    let mut previous: i32 = 0;
    while i < pixels.len() {
        let zeros = pixels[i..].iter().take_while(|&&p| p == 0).count();
        w.vle(zeros as u32);
        i += zeros;
        let nonzeros = pixels[i..].iter().take_while(|&&p| p != 0).count();
        w.vle(nonzeros as u32);
        for &p in &pixels[i..i + nonzeros] {
            let current = i32::from(p);
            let delta = current - previous;
            w.vle(((delta << 1) ^ (delta >> 31)) as u32);
            previous = current;
        }
        i += nonzeros;
    }
    w.finish()
}

/// Decodes RVL into exactly `pixel_count` pixels.
pub fn rvl_decode(payload: &[u8], pixel_count: usize) -> Result<Vec<u16>, CodecError> {
    if !payload.len().is_multiple_of(4) {
        return Err(CodecError::Rvl("length is not a whole number of 32-bit words"));
    }
    let mut r = NibbleReader { words: payload.chunks_exact(4), word: 0, left: 0 };
    let mut out = Vec::with_capacity(pixel_count);
    let mut previous: i32 = 0;
    while out.len() < pixel_count {
        let zeros = r.vle()? as usize;
        if zeros > pixel_count - out.len() {
            return Err(CodecError::Rvl("a run of zeros passes the end of the image"));
        }
        out.resize(out.len() + zeros, 0);
        if out.len() == pixel_count {
            break;
        }
        let nonzeros = r.vle()? as usize;
        if nonzeros > pixel_count - out.len() {
            return Err(CodecError::Rvl("a run of values passes the end of the image"));
        }
        for _ in 0..nonzeros {
            let positive = r.vle()?;
            let delta = ((positive >> 1) as i32) ^ -((positive & 1) as i32);
            let current = previous + delta;
            let value = u16::try_from(current).map_err(|_| CodecError::Rvl("a value leaves the 16-bit range"))?;
            out.push(value);
            previous = current;
        }
    }
    Ok(out)
}

#[derive(Default)]
struct NibbleWriter {
    out: Vec<u8>,
    word: u32,
    nibbles: u32,
}

impl NibbleWriter {
    fn vle(&mut self, mut value: u32) {
        loop {
            let mut nibble = value & 0x7;
            value >>= 3;
            if value != 0 {
                nibble |= 0x8;
            }
            self.word = (self.word << 4) | nibble;
            self.nibbles += 1;
            if self.nibbles == 8 {
                self.out.extend_from_slice(&self.word.to_le_bytes());
                self.nibbles = 0;
                self.word = 0;
            }
            if value == 0 {
                break;
            }
        }
    }

    fn finish(mut self) -> Vec<u8> {
        if self.nibbles > 0 {
            let word = self.word << (4 * (8 - self.nibbles));
            self.out.extend_from_slice(&word.to_le_bytes());
        }
        self.out
    }
}

struct NibbleReader<'a> {
    words: std::slice::ChunksExact<'a, u8>,
    word: u32,
    left: u32,
}

impl NibbleReader<'_> {
    /// Largest number of 3-bit groups a u32 needs.
    const MAX_GROUPS: u32 = 11;

    fn vle(&mut self) -> Result<u32, CodecError> {
        let mut value: u32 = 0;
        for group in 0..Self::MAX_GROUPS {
            if self.left == 0 {
                let w = self.words.next().ok_or(CodecError::Rvl("payload ends before the image is complete"))?;
                self.word = u32::from_le_bytes([w[0], w[1], w[2], w[3]]);
                self.left = 8;
            }
            let nibble = self.word >> 28;
            self.word <<= 4;
            self.left -= 1;
            value |= (nibble & 0x7).checked_shl(3 * group).unwrap_or(0);
            if nibble & 0x8 == 0 {
                return Ok(value);
            }
        }
        Err(CodecError::Rvl("a variable-length number is longer than 32 bits"))
    }
}

// ------------------------------------------------------------------ colour

/// Encodes RGB8 colour as baseline JPEG with 4:2:0 chroma subsampling.
pub fn encode_jpeg(image: &ColorImage, quality: u8) -> Result<Vec<u8>, CodecError> {
    let (w, h) = (
        u16::try_from(image.width).map_err(|_| CodecError::Encode("JPEG width above 65535".into()))?,
        u16::try_from(image.height).map_err(|_| CodecError::Encode("JPEG height above 65535".into()))?,
    );
    let mut out = Vec::with_capacity(image.data.len() / 8);
    let mut encoder = jpeg_encoder::Encoder::new(&mut out, quality);
    encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::R_4_2_0);
    encoder.encode(&image.data, w, h, jpeg_encoder::ColorType::Rgb).map_err(|e| CodecError::Encode(e.to_string()))?;
    Ok(out)
}

/// Encodes RGB8 colour as an 8-bit RGB PNG.
pub fn encode_png_rgb(image: &ColorImage) -> Result<Vec<u8>, CodecError> {
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, image.width, image.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::Fast);
        let mut writer = encoder.write_header().map_err(|e| CodecError::Encode(e.to_string()))?;
        writer.write_image_data(&image.data).map_err(|e| CodecError::Encode(e.to_string()))?;
    }
    Ok(out)
}

/// Encodes colour in the given encoding (`quality` applies to JPEG).
pub fn encode_color(encoding: ColorEncoding, image: &ColorImage, quality: u8) -> Result<Vec<u8>, CodecError> {
    match encoding {
        ColorEncoding::Jpeg => encode_jpeg(image, quality),
        ColorEncoding::Png => encode_png_rgb(image),
        ColorEncoding::Rgb8 => Ok(image.data.clone()),
        ColorEncoding::Unspecified => Err(CodecError::Unspecified("colour")),
    }
}

/// Decodes a colour payload that must be `width`×`height` into RGB8.
pub fn decode_color(encoding: ColorEncoding, payload: &[u8], width: u32, height: u32) -> Result<ColorImage, CodecError> {
    match encoding {
        ColorEncoding::Jpeg => decode_jpeg(payload, width, height),
        ColorEncoding::Png => decode_png_rgb(payload, width, height),
        ColorEncoding::Rgb8 => {
            let want = pixel_count(width, height) * RGB8_BYTES_PER_PIXEL;
            if payload.len() != want {
                return Err(CodecError::RgbLength { got: payload.len(), want, width, height });
            }
            Ok(ColorImage { width, height, data: payload.to_vec() })
        }
        ColorEncoding::Unspecified => Err(CodecError::Unspecified("colour")),
    }
}

fn decode_jpeg(payload: &[u8], width: u32, height: u32) -> Result<ColorImage, CodecError> {
    use zune_jpeg::zune_core::{colorspace::ColorSpace, options::DecoderOptions};
    let undecodable = |detail: String| CodecError::Undecodable { encoding: "JPEG", detail };
    let options =
        DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGB).set_max_width(width as usize).set_max_height(height as usize);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(Cursor::new(payload), options);
    match decoder.decode_headers() {
        Ok(()) => {}
        Err(e) => {
            // The size limits make an oversized image fail here; report it as a size problem.
            return Err(match peek_jpeg_size(payload) {
                Some((w, h)) if (w, h) != (width, height) => {
                    CodecError::SizeMismatch { what: "colour image", got_w: w, got_h: h, want_w: width, want_h: height }
                }
                _ => undecodable(e.to_string()),
            });
        }
    }
    let info = decoder.info().ok_or_else(|| undecodable("no image header".into()))?;
    check_size("colour image", u32::from(info.width), u32::from(info.height), width, height)?;
    let data = decoder.decode().map_err(|e| undecodable(e.to_string()))?;
    if data.len() != pixel_count(width, height) * RGB8_BYTES_PER_PIXEL {
        return Err(undecodable(format!("decoder produced {} bytes", data.len())));
    }
    Ok(ColorImage { width, height, data })
}

/// Reads the frame size from a JPEG's SOF marker without decoding.
fn peek_jpeg_size(payload: &[u8]) -> Option<(u32, u32)> {
    let mut i = 2;
    while i + 9 < payload.len() {
        if payload[i] != 0xFF {
            return None;
        }
        let marker = payload[i + 1];
        let len = usize::from(u16::from_be_bytes([payload[i + 2], payload[i + 3]]));
        // SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC).
        if (0xC0..=0xCF).contains(&marker) && ![0xC4, 0xC8, 0xCC].contains(&marker) {
            let h = u16::from_be_bytes([payload[i + 5], payload[i + 6]]);
            let w = u16::from_be_bytes([payload[i + 7], payload[i + 8]]);
            return Some((u32::from(w), u32::from(h)));
        }
        i += 2 + len;
    }
    None
}

fn decode_png_rgb(payload: &[u8], width: u32, height: u32) -> Result<ColorImage, CodecError> {
    let undecodable = |e: png::DecodingError| CodecError::Undecodable { encoding: "PNG", detail: e.to_string() };
    let decoder = png::Decoder::new(Cursor::new(payload));
    let mut reader = decoder.read_info().map_err(undecodable)?;
    let info = reader.info();
    let (w, h, bits, color) = (info.width, info.height, info.bit_depth, info.color_type);
    check_size("colour image", w, h, width, height)?;
    let channels = match (bits, color) {
        (png::BitDepth::Eight, png::ColorType::Rgb) => 3,
        (png::BitDepth::Eight, png::ColorType::Rgba) => 4,
        _ => return Err(CodecError::ColorPngFormat { bits: bits as u8, color: format!("{color:?}").to_lowercase() }),
    };
    let mut buf = vec![0u8; pixel_count(w, h) * channels];
    reader.next_frame(&mut buf).map_err(undecodable)?;
    let data = if channels == 3 { buf } else { buf.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect() };
    Ok(ColorImage { width, height, data })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp_depth(w: u32, h: u32) -> DepthImage {
        let data = (0..w * h).map(|i| if i % 7 == 0 || (i / w) < 2 { 0 } else { (1000 + (i * 37) % 9000) as u16 }).collect();
        DepthImage { width: w, height: h, data }
    }

    #[test]
    fn every_depth_codec_is_lossless() {
        let img = ramp_depth(64, 48);
        for enc in [DepthEncoding::Png16, DepthEncoding::Rvl, DepthEncoding::Zstd] {
            let bytes = encode_depth(enc, &img).unwrap();
            assert_eq!(decode_depth(enc, &bytes, 64, 48).unwrap(), img, "{enc:?}");
        }
    }

    #[test]
    fn rvl_matches_the_reference_bitstream() {
        // Worked by hand from Wilson's reference: pixels [0, 0, 5, 6] give
        // zeros=2 -> 0x2, nonzeros=2 -> 0x2, delta 5 -> zigzag 10 -> 0xA 0x1,
        // delta 1 -> zigzag 2 -> 0x2; five nibbles 2 2 A 1 2, padded: 0x22A12000.
        assert_eq!(rvl_encode(&[0, 0, 5, 6]), 0x22A1_2000u32.to_le_bytes().to_vec());
        assert_eq!(rvl_decode(&0x22A1_2000u32.to_le_bytes(), 4).unwrap(), vec![0, 0, 5, 6]);
        // Extremes of the range round-trip.
        let px = [u16::MAX, 1, u16::MAX, 0, 0, 1];
        assert_eq!(rvl_decode(&rvl_encode(&px), px.len()).unwrap(), px);
    }

    #[test]
    fn rvl_rejects_truncated_and_overlong_payloads() {
        let img = ramp_depth(32, 8);
        let bytes = rvl_encode(&img.data);
        assert_eq!(
            rvl_decode(&bytes[..bytes.len() - 4], img.data.len()).unwrap_err(),
            CodecError::Rvl("payload ends before the image is complete")
        );
        assert_eq!(rvl_decode(&bytes, 10).unwrap_err(), CodecError::Rvl("a run of zeros passes the end of the image"));
        assert_eq!(rvl_decode(&rvl_encode(&[0, 5, 6, 7]), 2).unwrap_err(), CodecError::Rvl("a run of values passes the end of the image"));
        assert!(rvl_decode(&[1, 2, 3], 4).is_err());
        assert!(rvl_decode(&[0xFF; 64], 4).is_err());
    }

    #[test]
    fn depth_size_and_bit_depth_are_checked() {
        let img = ramp_depth(64, 48);
        let png = encode_depth(DepthEncoding::Png16, &img).unwrap();
        assert_eq!(
            decode_depth(DepthEncoding::Png16, &png, 640, 480).unwrap_err().to_string(),
            "depth image is 64x48, but the session's camera is 640x480"
        );
        let eight_bit = encode_png_rgb(&ColorImage { width: 4, height: 4, data: vec![9; 48] }).unwrap();
        assert_eq!(
            decode_depth(DepthEncoding::Png16, &eight_bit, 4, 4).unwrap_err().to_string(),
            "depth PNG has 8-bit rgb samples, expected 16-bit greyscale"
        );
        let z8 = zstd::bulk::compress(&[7u8; 16], 1).unwrap();
        assert_eq!(
            decode_depth(DepthEncoding::Zstd, &z8, 4, 4).unwrap_err().to_string(),
            "depth payload holds 16 bytes after decompression, expected 32 (16-bit, 4x4) — looks like 8-bit depth"
        );
        assert!(matches!(decode_depth(DepthEncoding::Png16, b"garbage", 4, 4), Err(CodecError::Undecodable { .. })));
    }

    #[test]
    fn jpeg_round_trip_is_close_and_size_checked() {
        let (w, h) = (64u32, 48u32);
        let data = (0..w * h).flat_map(|i| [((i % w) * 4) as u8, ((i / w) * 5) as u8, 128]).collect();
        let img = ColorImage { width: w, height: h, data };
        let jpeg = encode_jpeg(&img, 95).unwrap();
        let back = decode_color(ColorEncoding::Jpeg, &jpeg, w, h).unwrap();
        let mean_err: f64 =
            img.data.iter().zip(&back.data).map(|(a, b)| (*a as f64 - *b as f64).abs()).sum::<f64>() / img.data.len() as f64;
        assert!(mean_err < 6.0, "mean abs error {mean_err}");
        assert_eq!(
            decode_color(ColorEncoding::Jpeg, &jpeg, 32, 24).unwrap_err().to_string(),
            "colour image is 64x48, but the session's camera is 32x24"
        );
        assert_eq!(
            decode_color(ColorEncoding::Jpeg, &jpeg, 640, 480).unwrap_err().to_string(),
            "colour image is 64x48, but the session's camera is 640x480"
        );
        let err = decode_color(ColorEncoding::Jpeg, b"\xFF\xD8not a jpeg", w, h).unwrap_err();
        assert!(err.to_string().starts_with("colour JPEG payload is not decodable"), "{err}");
        assert_eq!(
            decode_color(ColorEncoding::Rgb8, &[0; 10], 2, 2).unwrap_err().to_string(),
            "raw RGB8 colour holds 10 bytes, expected 12 (2x2x3)"
        );
    }

    #[test]
    fn crc_is_of_little_endian_bytes() {
        let img = DepthImage { width: 2, height: 1, data: vec![0x0102, 0x0304] };
        assert_eq!(img.crc32(), crc32fast::hash(&[0x02, 0x01, 0x04, 0x03]));
    }
}
