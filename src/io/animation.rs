//! The morph as animations: `morph.mp4` (H.264, feature `mp4`), `morph.apng` (lossless) and
//! `morph.gif` (256 colours, plays everywhere), which of them a run writes (`--video`), how
//! fast they play (`--fps`) and the MP4's quality (`--crf`).

use std::path::Path;

use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbImage as Rgb8};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::io::images::write_atomically;

/// An animation format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum VideoFormat {
    /// `morph.mp4`: H.264 in MP4, `yuv420p`, for players, editors and the web.
    Mp4,
    /// `morph.apng`: animated PNG, lossless 24-bit colour; browsers play it.
    Apng,
    /// `morph.gif`: 256 colours per frame (gradients band), plays everywhere.
    Gif,
}

impl VideoFormat {
    /// Every format, in the order they are written.
    pub const ALL: [VideoFormat; 3] = [VideoFormat::Mp4, VideoFormat::Apng, VideoFormat::Gif];

    /// The smallest frame side this format encodes: the H.264 encoder takes no frame side
    /// below 16 pixels (a smaller one failed after the whole solve, issue 43 #7).
    pub fn min_side(self) -> usize {
        match self {
            VideoFormat::Mp4 => 16,
            VideoFormat::Apng | VideoFormat::Gif => 1,
        }
    }

    /// The file this format is written to.
    pub fn file_name(self) -> &'static str {
        match self {
            VideoFormat::Mp4 => "morph.mp4",
            VideoFormat::Apng => "morph.apng",
            VideoFormat::Gif => "morph.gif",
        }
    }

    /// Whether this build can write the format (MP4 needs the cargo feature `mp4`).
    pub fn compiled(self) -> bool {
        self != VideoFormat::Mp4 || cfg!(feature = "mp4")
    }

    /// The formats a run writes unless told otherwise: every one this build can write.
    pub fn defaults() -> Vec<VideoFormat> {
        Self::ALL.into_iter().filter(|f| f.compiled()).collect()
    }
}

impl std::fmt::Display for VideoFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            VideoFormat::Mp4 => "mp4",
            VideoFormat::Apng => "apng",
            VideoFormat::Gif => "gif",
        })
    }
}

/// The playing time of a whole animation when no frame rate is given, in seconds.
pub const DEFAULT_SECONDS: f64 = 3.0;

/// The frame rates `--fps` takes: GIF delays are whole hundredths of a second, so above
/// 50 frames per second GIF players would slow the clip down.
pub const FPS_RANGE: std::ops::RangeInclusive<f64> = 0.1..=50.0;

/// The quantisers `--crf` takes: H.264's 0 (near lossless) to 51 (smallest).
pub const QUALITY_RANGE: std::ops::RangeInclusive<u8> = 0..=51;

/// The MP4's quantiser when none is given, the number x264 users know as "visually
/// lossless". Measured on the `faces` draft morph (128², 16 frames): 2.1 kB per frame, RGB
/// PSNR 36.8 dB against the PNG frames, most of the loss being 4:2:0's halved chroma
/// resolution (the APNG is the lossless one).
pub const DEFAULT_QUALITY: u8 = 18;

/// How the animations are written.
#[derive(Clone, Debug, PartialEq)]
pub struct Playback {
    /// Which files.
    pub formats: Vec<VideoFormat>,
    /// Forward, then back to the second frame.
    pub pingpong: bool,
    /// Frames per second; `None`: the whole animation lasts [`DEFAULT_SECONDS`].
    pub fps: Option<f64>,
    /// The MP4's H.264 quantiser (0 best … 51 smallest).
    pub quality: u8,
}

impl Playback {
    /// How long each frame of an animation of `played` frames shows, in seconds.
    pub fn seconds_per_frame(&self, played: usize) -> f64 {
        match self.fps {
            Some(fps) => 1.0 / fps,
            None => DEFAULT_SECONDS / played as f64,
        }
    }

    /// Checks the settings.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the bad value and its range.
    pub fn validate(&self) -> Result<()> {
        if self.formats.is_empty() {
            return Err(Error::invalid(
                "video",
                "(none)",
                "one or more of mp4, apng, gif",
            ));
        }
        if let Some(missing) = self.formats.iter().find(|f| !f.compiled()) {
            return Err(Error::invalid(
                "video",
                missing,
                "apng or gif: this build has no H.264 encoder (rebuild with the cargo feature \
                 `mp4`, on by default)",
            ));
        }
        if let Some(fps) = self.fps
            && !FPS_RANGE.contains(&fps)
        {
            return Err(Error::invalid(
                "fps",
                fps,
                format!(
                    "{} to {} frames per second",
                    FPS_RANGE.start(),
                    FPS_RANGE.end()
                ),
            ));
        }
        if !QUALITY_RANGE.contains(&self.quality) {
            return Err(Error::invalid(
                "crf",
                self.quality,
                "0 (best) to 51 (smallest): H.264's quantiser",
            ));
        }
        Ok(())
    }

    /// Writes the chosen animations of `frames` into `dir`.
    ///
    /// # Errors
    ///
    /// A file cannot be encoded or written.
    pub fn write(&self, dir: &Path, frames: &[Rgb8]) -> Result<()> {
        let order = animation_order(frames, self.pingpong);
        let seconds = self.seconds_per_frame(order.len());
        for &format in &self.formats {
            let path = dir.join(format.file_name());
            match format {
                VideoFormat::Gif => write_gif(&path, &order, seconds)?,
                VideoFormat::Apng => write_apng(&path, &order, seconds)?,
                #[cfg(feature = "mp4")]
                VideoFormat::Mp4 => {
                    crate::io::h264::write_mp4(&path, &order, seconds, self.quality)?
                }
                #[cfg(not(feature = "mp4"))]
                VideoFormat::Mp4 => unreachable!("validate refuses mp4 in builds without it"),
            }
        }
        Ok(())
    }
}

/// Writes an endlessly looping GIF of `order`, each frame shown `seconds` (at least 20 ms,
/// the shortest delay browsers honour).
///
/// # Errors
///
/// If the file cannot be encoded or written.
pub fn write_gif(path: &Path, order: &[&Rgb8], seconds: f64) -> Result<()> {
    let delay_ms = (seconds * 1000.0).round().max(20.0) as u32;
    let mut bytes = Vec::new();
    {
        let mut encoder = GifEncoder::new_with_speed(&mut bytes, 10);
        let gif_error = |e| Error::Image {
            path: path.to_path_buf(),
            cause: e,
        };
        encoder.set_repeat(Repeat::Infinite).map_err(gif_error)?;
        for frame in order {
            let rgba = image::DynamicImage::ImageRgb8((*frame).clone()).to_rgba8();
            let delay = Delay::from_numer_denom_ms(delay_ms, 1);
            encoder
                .encode_frame(Frame::from_parts(rgba, 0, 0, delay))
                .map_err(gif_error)?;
        }
    }
    write_atomically(path, |w| w.write_all(&bytes))
}

/// Writes an endlessly looping animated PNG of `order`, each frame shown `seconds`:
/// lossless 24-bit colour, so unlike the GIF's 256-colour palette it shows smooth gradients
/// without banding.
///
/// # Errors
///
/// If the file cannot be encoded or written.
pub fn write_apng(path: &Path, order: &[&Rgb8], seconds: f64) -> Result<()> {
    let (width, height) = order[0].dimensions();
    // The delay as a fraction of a second with a millisecond denominator (u16 each).
    let delay_ms = (seconds * 1000.0).round().clamp(20.0, 65535.0) as u16;
    let png_error = |e: png::EncodingError| Error::Io {
        path: path.to_path_buf(),
        cause: std::io::Error::other(e),
    };
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder
            .set_animated(order.len() as u32, 0)
            .map_err(png_error)?;
        encoder.set_frame_delay(delay_ms, 1000).map_err(png_error)?;
        let mut writer = encoder.write_header().map_err(png_error)?;
        for frame in order {
            writer.write_image_data(frame.as_raw()).map_err(png_error)?;
        }
        writer.finish().map_err(png_error)?;
    }
    write_atomically(path, |w| w.write_all(&bytes))
}

/// The frames in the order an animation plays them: forward, then back to the second when
/// `pingpong` (the first is not repeated: the loop returns to it).
pub fn animation_order(frames: &[Rgb8], pingpong: bool) -> Vec<&Rgb8> {
    let mut order: Vec<&Rgb8> = frames.iter().collect();
    if pingpong && frames.len() > 2 {
        order.extend(frames[1..frames.len() - 1].iter().rev());
    }
    order
}

#[cfg(test)]
mod tests {
    use super::*;

    fn playback(pingpong: bool, fps: Option<f64>) -> Playback {
        Playback {
            formats: vec![VideoFormat::Apng],
            pingpong,
            fps,
            quality: DEFAULT_QUALITY,
        }
    }

    /// The APNG decodes to the frames in play order, losslessly (every 8-bit value), loops
    /// forever and shares the duration out (or shows each frame 1/fps).
    #[test]
    fn apng_holds_every_frame_losslessly() {
        let (h, w) = (5, 7);
        let frames: Vec<Rgb8> = (0..4)
            .map(|k| {
                let data = (0..3 * h * w)
                    .map(|i| ((i * 37 + k * 101) % 256) as u8)
                    .collect();
                Rgb8::from_raw(w as u32, h as u32, data).unwrap()
            })
            .collect();
        let dir = std::env::temp_dir().join(format!("deepmorph-apng-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("morph.apng");
        for (pingpong, fps, order) in [
            (false, None, vec![0, 1, 2, 3]),
            (true, None, vec![0, 1, 2, 3, 2, 1]),
            (false, Some(8.0), vec![0, 1, 2, 3]),
        ] {
            playback(pingpong, fps).write(&dir, &frames).unwrap();
            let decoder = png::Decoder::new(std::io::Cursor::new(std::fs::read(&path).unwrap()));
            let mut reader = decoder.read_info().unwrap();
            let control = reader.info().animation_control.unwrap();
            assert_eq!(
                (control.num_frames, control.num_plays),
                (order.len() as u32, 0)
            );
            let mut buf = vec![0; reader.output_buffer_size().unwrap()];
            for &k in &order {
                let info = reader.next_frame(&mut buf).unwrap();
                assert_eq!((info.width, info.height), (w as u32, h as u32));
                assert_eq!(&buf[..info.buffer_size()], frames[k].as_raw().as_slice());
                let fc = reader.info().frame_control.unwrap();
                let seconds = f64::from(fc.delay_num) / f64::from(fc.delay_den);
                let want = fps.map_or(3.0 / order.len() as f64, |f| 1.0 / f);
                assert!((seconds - want).abs() < 0.001, "{seconds} vs {want}");
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn bad_settings_name_the_flag_and_range() {
        let mut p = playback(false, Some(0.0));
        assert!(p.validate().unwrap_err().to_string().contains("fps"));
        p.fps = Some(f64::NAN);
        assert!(p.validate().is_err());
        p.fps = None;
        p.quality = 52;
        assert!(p.validate().unwrap_err().to_string().contains("crf"));
        p.quality = 0;
        p.formats.clear();
        assert!(p.validate().unwrap_err().to_string().contains("video"));
        p.formats = VideoFormat::defaults();
        p.validate().unwrap();
        assert_eq!(
            VideoFormat::defaults().contains(&VideoFormat::Mp4),
            cfg!(feature = "mp4")
        );
    }
}
