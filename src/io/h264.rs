//! `morph.mp4`: the animation's frames as H.264 (Cisco's OpenH264, built from source by the
//! `openh264` crate) in an MP4 file ([`crate::io::mp4`]).
//!
//! Frames go to 4:2:0 YUV (`yuv420p`, what every player decodes) by BT.601 in limited
//! range, the matrix the stream's colour description names; chroma is the mean of each
//! 2 × 2 block. Odd sides are padded by repeating the last row or column (H.264's 4:2:0
//! needs even sides).

use std::path::Path;

use image::RgbImage as Rgb8;
use openh264::OpenH264API;
use openh264::encoder::{
    BitRate, Encoder, EncoderConfig, FrameRate, FrameType, QpRange, RateControlMode, VuiConfig,
};
use openh264::formats::YUVSlices;

use crate::error::{Error, Result};
use crate::io::animation::QUALITY_RANGE;
use crate::io::images::write_atomically;
use crate::io::mp4::{Sample, Track, mux};

/// Time units per second of the video track: the usual 90 kHz of video timestamps.
const TIMESCALE: u32 = 90_000;

/// A planar 4:2:0 picture.
struct Yuv420 {
    width: usize,
    height: usize,
    y: Vec<u8>,
    u: Vec<u8>,
    v: Vec<u8>,
}

/// `frame` in BT.601 limited-range 4:2:0, its sides padded to even by edge repetition.
fn to_yuv420(frame: &Rgb8) -> Yuv420 {
    let (w0, h0) = (frame.width() as usize, frame.height() as usize);
    let (width, height) = (w0.next_multiple_of(2), h0.next_multiple_of(2));
    let raw = frame.as_raw();
    let pixel = |x: usize, y: usize| {
        let at = 3 * (y.min(h0 - 1) * w0 + x.min(w0 - 1));
        [raw[at], raw[at + 1], raw[at + 2]].map(f32::from)
    };
    let byte = |v: f32| v.round().clamp(0.0, 255.0) as u8;
    let mut y = vec![0; width * height];
    for row in 0..height {
        for col in 0..width {
            let [r, g, b] = pixel(col, row);
            y[row * width + col] = byte(16.0 + 0.256_788 * r + 0.504_129 * g + 0.097_906 * b);
        }
    }
    let (cw, ch) = (width / 2, height / 2);
    let (mut u, mut v) = (vec![0; cw * ch], vec![0; cw * ch]);
    for row in 0..ch {
        for col in 0..cw {
            let mut mean = [0.0f32; 3];
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let p = pixel(2 * col + dx, 2 * row + dy);
                (0..3).for_each(|c| mean[c] += 0.25 * p[c]);
            }
            let [r, g, b] = mean;
            u[row * cw + col] = byte(128.0 - 0.148_223 * r - 0.290_993 * g + 0.439_216 * b);
            v[row * cw + col] = byte(128.0 + 0.439_216 * r - 0.367_788 * g - 0.071_427 * b);
        }
    }
    Yuv420 {
        width,
        height,
        y,
        u,
        v,
    }
}

/// The NAL units of an Annex B stream, without their start codes: openh264's splitter
/// (each unit from its `00 00 01`), less that prefix and the zeros a following 4-byte start
/// code leaves at the end of the unit before it.
fn nal_units(stream: &[u8]) -> Vec<&[u8]> {
    openh264::nal_units(stream)
        .map(|unit| {
            let payload = unit.strip_prefix(&[0, 0, 1][..]).unwrap_or(unit);
            let trailing = payload.iter().rev().take_while(|&&b| b == 0).count();
            &payload[..payload.len() - trailing]
        })
        .filter(|unit| !unit.is_empty())
        .collect()
}

/// Encodes `frames` (each shown for `seconds_per_frame`) with the quantiser `quality` and
/// writes them as an MP4 file at `path`.
///
/// # Errors
///
/// The encoder refuses the settings or a frame, or the file cannot be written.
pub fn write_mp4(path: &Path, frames: &[&Rgb8], seconds_per_frame: f64, quality: u8) -> Result<()> {
    let failed = |detail: String| Error::Io {
        path: path.to_path_buf(),
        cause: std::io::Error::other(format!("H.264 encoding: {detail}")),
    };
    let track = encode(frames, seconds_per_frame, quality).map_err(failed)?;
    let bytes = mux(&track).ok_or_else(|| failed("the video would reach 4 GiB".into()))?;
    write_atomically(path, |w| w.write_all(&bytes))
}

/// The H.264 track of `frames`.
fn encode(
    frames: &[&Rgb8],
    seconds_per_frame: f64,
    quality: u8,
) -> std::result::Result<Track, String> {
    let first = frames.first().ok_or("no frames")?;
    if !QUALITY_RANGE.contains(&quality) {
        return Err(format!("quality {quality} is outside {QUALITY_RANGE:?}"));
    }
    // Quality mode with the quantiser pinned is a constant-quantiser encode: every frame
    // at `quality`. The bit-rate target is only there so that rate control never drops a
    // frame (with frame skipping off, OpenH264 warns that it cannot control the rate).
    let config = EncoderConfig::new()
        .rate_control_mode(RateControlMode::Quality)
        .qp(QpRange::new(quality, quality))
        .bitrate(BitRate::from_bps(200_000_000))
        .max_frame_rate(FrameRate::from_hz((1.0 / seconds_per_frame) as f32))
        .vui(VuiConfig::bt601())
        .num_threads(1);
    let mut encoder =
        Encoder::with_api_config(OpenH264API::from_source(), config).map_err(|e| format!("{e}"))?;
    let (mut sps, mut pps) = (None, None);
    let mut samples = Vec::with_capacity(frames.len());
    let size = (first.width(), first.height());
    for (i, frame) in frames.iter().enumerate() {
        if frame.dimensions() != size {
            return Err(format!(
                "frame {i} is {}x{}, the first {}x{}",
                frame.width(),
                frame.height(),
                size.0,
                size.1
            ));
        }
        let yuv = to_yuv420(frame);
        let (w, cw) = (yuv.width, yuv.width / 2);
        let slices = YUVSlices::new((&yuv.y, &yuv.u, &yuv.v), (w, yuv.height), (w, cw, cw));
        let coded = encoder.encode(&slices).map_err(|e| format!("{e}"))?;
        let kind = coded.frame_type();
        if !matches!(kind, FrameType::IDR | FrameType::I | FrameType::P) {
            return Err(format!("frame {i} came out as {kind:?}"));
        }
        let mut data = Vec::new();
        for unit in nal_units(&coded.to_vec()) {
            match unit[0] & 0x1f {
                7 => sps = Some(unit.to_vec()),
                8 => pps = Some(unit.to_vec()),
                _ => {
                    data.extend_from_slice(&(unit.len() as u32).to_be_bytes());
                    data.extend_from_slice(unit);
                }
            }
        }
        samples.push(Sample {
            data,
            sync: kind == FrameType::IDR,
        });
    }
    // Odd sides were padded to even.
    let (width, height) = (
        first.width().next_multiple_of(2),
        first.height().next_multiple_of(2),
    );
    Ok(Track {
        width: u16::try_from(width).map_err(|_| "wider than 65535 px")?,
        height: u16::try_from(height).map_err(|_| "taller than 65535 px")?,
        timescale: TIMESCALE,
        sample_duration: (seconds_per_frame * f64::from(TIMESCALE)).round().max(1.0) as u32,
        sps: sps
            .filter(|s| s.len() >= 4)
            .ok_or("no sequence parameter set")?,
        pps: pps.ok_or("no picture parameter set")?,
        samples,
    })
}

#[cfg(test)]
mod tests {
    use openh264::decoder::Decoder;
    use openh264::formats::YUVSource;

    use super::*;
    use crate::io::mp4::inspect;

    /// A soft blob moving over a colour gradient, `n` frames of `w × h` (smooth, as morph
    /// frames are: 4:2:0 halves the chroma resolution, which a hard colour edge would show).
    fn clip(n: usize, w: u32, h: u32) -> Vec<Rgb8> {
        (0..n)
            .map(|t| {
                Rgb8::from_fn(w, h, |x, y| {
                    let (dx, dy) = (x as f64 - 6.0 - 3.0 * t as f64, y as f64 - h as f64 / 2.0);
                    let blob = 50.0 + 170.0 * (-(dx * dx + dy * dy) / 32.0).exp();
                    image::Rgb([(x * 255 / w) as u8, (y * 255 / h) as u8, blob as u8])
                })
            })
            .collect()
    }

    /// Decodes every sample of an MP4 file written by [`write_mp4`] to RGB (by the
    /// decoder's own conversion) and its luma plane.
    fn decode(bytes: &[u8]) -> Vec<(Vec<u8>, Vec<u8>)> {
        let summary = inspect(bytes).unwrap();
        let mut decoder = Decoder::new().unwrap();
        let annex_b = |unit: &[u8]| [&[0, 0, 0, 1][..], unit].concat();
        let mut stream = [annex_b(&summary.sps), annex_b(&summary.pps)].concat();
        let mut frames = Vec::new();
        for range in &summary.samples {
            let mut sample = &bytes[range.clone()];
            while !sample.is_empty() {
                let len = u32::from_be_bytes(sample[..4].try_into().unwrap()) as usize;
                stream.extend(annex_b(&sample[4..4 + len]));
                sample = &sample[4 + len..];
            }
            let picture = decoder
                .decode(&stream)
                .unwrap()
                .expect("a picture per sample");
            let (w, h) = (summary.width as usize, summary.height as usize);
            let mut rgb = vec![0; w * h * 3];
            picture.write_rgb8(&mut rgb);
            let stride = picture.strides().0;
            let luma = (0..h)
                .flat_map(|r| picture.y()[r * stride..r * stride + w].to_vec())
                .collect();
            frames.push((rgb, luma));
            stream.clear();
        }
        frames
    }

    fn psnr(a: &[u8], b: &[u8]) -> f64 {
        let mse = a
            .iter()
            .zip(b)
            .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
            .sum::<f64>()
            / a.len() as f64;
        10.0 * (255.0f64.powi(2) / mse).log10()
    }

    #[test]
    fn every_frame_decodes_close_to_its_source() {
        let frames = clip(12, 48, 32);
        let refs: Vec<&Rgb8> = frames.iter().collect();
        let dir = std::env::temp_dir().join(format!("deepmorph-mp4-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("clip.mp4");
        write_mp4(&path, &refs, 0.125, 16).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let summary = inspect(&bytes).unwrap();
        assert_eq!((summary.width, summary.height), (48, 32));
        assert_eq!(summary.durations, vec![TIMESCALE / 8; 12]);
        assert_eq!(summary.sync.first(), Some(&1));
        let decoded = decode(&bytes);
        assert_eq!(decoded.len(), 12);
        for (t, ((rgb, luma), want)) in decoded.iter().zip(&frames).enumerate() {
            // The encoder's loss alone (luma against the luma it was given), and with both
            // colour conversions and 4:2:0 chroma.
            let coded = psnr(luma, &to_yuv420(want).y);
            let shown = psnr(rgb, want.as_raw());
            assert!(
                coded > 40.0 && shown > 32.0,
                "frame {t}: {coded:.1} / {shown:.1} dB"
            );
        }
        // A coarser quantiser: smaller and worse, but still the same frames.
        write_mp4(&path, &refs, 0.125, 40).unwrap();
        let coarse = std::fs::read(&path).unwrap();
        assert!(coarse.len() < bytes.len());
        assert_eq!(decode(&coarse).len(), 12);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn odd_sides_are_padded_to_even() {
        let frames = clip(3, 21, 15);
        let yuv = to_yuv420(&frames[0]);
        assert_eq!((yuv.width, yuv.height), (22, 16));
        // The padding repeats the last column and row.
        assert_eq!(yuv.y[21], yuv.y[20]);
        assert_eq!(yuv.y[15 * 22 + 3], yuv.y[14 * 22 + 3]);
        let refs: Vec<&Rgb8> = frames.iter().collect();
        let track = encode(&refs, 0.5, 20).unwrap();
        assert_eq!((track.width, track.height), (22, 16));
        assert_eq!(track.samples.len(), 3);
    }

    #[test]
    fn grey_is_grey_and_white_is_white() {
        // BT.601 limited range: black 16, white 235, no chroma for greys.
        let white = to_yuv420(&Rgb8::from_pixel(2, 2, image::Rgb([255; 3])));
        let black = to_yuv420(&Rgb8::from_pixel(2, 2, image::Rgb([0; 3])));
        assert_eq!((white.y[0], white.u[0], white.v[0]), (235, 128, 128));
        assert_eq!((black.y[0], black.u[0], black.v[0]), (16, 128, 128));
    }

    #[test]
    fn start_codes_of_both_lengths_split_units() {
        let stream = [
            0, 0, 0, 1, 0x67, 1, 2, 0, 0, 1, 0x68, 3, 0, 0, 0, 1, 0x65, 4, 5,
        ];
        assert_eq!(
            nal_units(&stream),
            vec![&[0x67, 1, 2][..], &[0x68, 3][..], &[0x65, 4, 5][..]]
        );
    }
}
