//! A minimal MP4 (ISO/IEC 14496-12 and -15) for one H.264 video track: the writer of
//! `morph.mp4`, and, for the tests only (feature `check`), a reader of what they need to
//! check such a file (sizes, samples, timing, the decoder configuration): not part of the
//! library's API.
//!
//! The layout is "fast start": `ftyp`, `moov` (every table), then `mdat` with the samples in
//! order as one chunk, so a player can start before the whole file is read. Samples are in
//! AVCC form (each NAL unit behind its 4-byte big-endian length); the sequence and picture
//! parameter sets live in the `avcC` box, not in the samples.

#[cfg(any(test, feature = "check"))]
use std::ops::Range;

/// One coded picture.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Sample {
    /// Its NAL units, each behind its 4-byte big-endian length (AVCC).
    pub data: Vec<u8>,
    /// An IDR picture: playback can start here.
    pub sync: bool,
}

/// An H.264 track ready to be written.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Track {
    /// Coded width in pixels (even).
    pub width: u16,
    /// Coded height in pixels (even).
    pub height: u16,
    /// Time units per second.
    pub timescale: u32,
    /// Each sample's duration in time units.
    pub sample_duration: u32,
    /// The sequence parameter set NAL unit (without start code or length).
    pub sps: Vec<u8>,
    /// The picture parameter set NAL unit (without start code or length).
    pub pps: Vec<u8>,
    /// The pictures in presentation (= decoding: no B-frames) order.
    pub samples: Vec<Sample>,
}

/// Appends a box of type `kind` whose body `body` writes, with its size filled in.
fn atom(out: &mut Vec<u8>, kind: &[u8; 4], body: impl FnOnce(&mut Vec<u8>)) {
    let start = out.len();
    out.extend_from_slice(&[0; 4]);
    out.extend_from_slice(kind);
    body(out);
    let size = u32::try_from(out.len() - start).expect("boxes of this writer stay below 4 GiB");
    out[start..start + 4].copy_from_slice(&size.to_be_bytes());
}

/// A "full box": version 0 and `flags` before the body.
fn full_atom(out: &mut Vec<u8>, kind: &[u8; 4], flags: u32, body: impl FnOnce(&mut Vec<u8>)) {
    atom(out, kind, |out| {
        out.extend_from_slice(&flags.to_be_bytes());
        body(out);
    });
}

fn u16be(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_be_bytes());
}

fn u32be(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_be_bytes());
}

/// The identity transformation matrix of `mvhd` and `tkhd` (16.16 and 2.30 fixed point).
fn unity_matrix(out: &mut Vec<u8>) {
    for v in [0x0001_0000, 0, 0, 0, 0x0001_0000, 0, 0, 0, 0x4000_0000u32] {
        u32be(out, v);
    }
}

/// The movie's boxes, given where the samples' chunk starts in the file.
fn moov(track: &Track, chunk_offset: u32) -> Vec<u8> {
    let count = track.samples.len() as u32;
    let duration = count * track.sample_duration;
    let mut out = Vec::new();
    atom(&mut out, b"moov", |out| {
        full_atom(out, b"mvhd", 0, |out| {
            u32be(out, 0); // creation time
            u32be(out, 0); // modification time
            u32be(out, track.timescale);
            u32be(out, duration);
            u32be(out, 0x0001_0000); // rate 1.0
            u16be(out, 0x0100); // volume 1.0
            out.extend_from_slice(&[0; 10]);
            unity_matrix(out);
            out.extend_from_slice(&[0; 24]);
            u32be(out, 2); // next track id
        });
        atom(out, b"trak", |out| {
            // Flags: enabled, in movie, in preview.
            full_atom(out, b"tkhd", 0x7, |out| {
                u32be(out, 0);
                u32be(out, 0);
                u32be(out, 1); // track id
                u32be(out, 0);
                u32be(out, duration);
                out.extend_from_slice(&[0; 8]);
                u16be(out, 0); // layer
                u16be(out, 0); // alternate group
                u16be(out, 0); // volume: video
                u16be(out, 0);
                unity_matrix(out);
                u32be(out, u32::from(track.width) << 16);
                u32be(out, u32::from(track.height) << 16);
            });
            atom(out, b"mdia", |out| {
                full_atom(out, b"mdhd", 0, |out| {
                    u32be(out, 0);
                    u32be(out, 0);
                    u32be(out, track.timescale);
                    u32be(out, duration);
                    u16be(out, 0x55c4); // language "und"
                    u16be(out, 0);
                });
                full_atom(out, b"hdlr", 0, |out| {
                    u32be(out, 0);
                    out.extend_from_slice(b"vide");
                    out.extend_from_slice(&[0; 12]);
                    out.extend_from_slice(b"deepmorph\0");
                });
                atom(out, b"minf", |out| {
                    full_atom(out, b"vmhd", 1, |out| out.extend_from_slice(&[0; 8]));
                    atom(out, b"dinf", |out| {
                        full_atom(out, b"dref", 0, |out| {
                            u32be(out, 1);
                            // Flag 1: the media is in this file.
                            full_atom(out, b"url ", 1, |_| {});
                        });
                    });
                    stbl(out, track, chunk_offset);
                });
            });
        });
    });
    out
}

/// The sample table: description, timing, sync samples, sizes, one chunk.
fn stbl(out: &mut Vec<u8>, track: &Track, chunk_offset: u32) {
    let count = track.samples.len() as u32;
    atom(out, b"stbl", |out| {
        full_atom(out, b"stsd", 0, |out| {
            u32be(out, 1);
            atom(out, b"avc1", |out| {
                out.extend_from_slice(&[0; 6]);
                u16be(out, 1); // data reference index
                out.extend_from_slice(&[0; 16]);
                u16be(out, track.width);
                u16be(out, track.height);
                u32be(out, 0x0048_0000); // 72 dpi
                u32be(out, 0x0048_0000);
                u32be(out, 0);
                u16be(out, 1); // frames per sample
                let mut name = [0u8; 32];
                name[0] = 9;
                name[1..10].copy_from_slice(b"deepmorph");
                out.extend_from_slice(&name);
                u16be(out, 0x18); // depth: colour
                u16be(out, 0xffff);
                atom(out, b"avcC", |out| {
                    out.push(1); // configuration version
                    out.extend_from_slice(&track.sps[1..4]); // profile, compatibility, level
                    out.push(0xff); // 4-byte NAL lengths
                    out.push(0xe1); // one SPS
                    u16be(out, track.sps.len() as u16);
                    out.extend_from_slice(&track.sps);
                    out.push(1); // one PPS
                    u16be(out, track.pps.len() as u16);
                    out.extend_from_slice(&track.pps);
                });
            });
        });
        full_atom(out, b"stts", 0, |out| {
            u32be(out, 1);
            u32be(out, count);
            u32be(out, track.sample_duration);
        });
        let sync: Vec<u32> = (1..=count)
            .filter(|&i| track.samples[i as usize - 1].sync)
            .collect();
        full_atom(out, b"stss", 0, |out| {
            u32be(out, sync.len() as u32);
            sync.iter().for_each(|&i| u32be(out, i));
        });
        full_atom(out, b"stsc", 0, |out| {
            u32be(out, 1);
            u32be(out, 1); // first chunk
            u32be(out, count); // samples per chunk
            u32be(out, 1); // sample description
        });
        full_atom(out, b"stsz", 0, |out| {
            u32be(out, 0); // sizes differ
            u32be(out, count);
            for s in &track.samples {
                u32be(out, s.data.len() as u32);
            }
        });
        full_atom(out, b"stco", 0, |out| {
            u32be(out, 1);
            u32be(out, chunk_offset);
        });
    });
}

/// The MP4 file of `track`, or `None` if it would reach 4 GiB (32-bit offsets).
///
/// # Panics
///
/// If the track has no samples, or the SPS is shorter than its 4-byte header: the encoder
/// never makes such a track.
pub fn mux(track: &Track) -> Option<Vec<u8>> {
    assert!(!track.samples.is_empty() && track.sps.len() >= 4);
    let media: usize = track.samples.iter().map(|s| s.data.len()).sum();
    let mut out = Vec::new();
    atom(&mut out, b"ftyp", |out| {
        out.extend_from_slice(b"isom");
        u32be(out, 0x200);
        for brand in [b"isom", b"iso2", b"avc1", b"mp41"] {
            out.extend_from_slice(brand);
        }
    });
    // The tables' size does not depend on the offset's value: measure, then write.
    let moov_len = moov(track, 0).len();
    let chunk_offset = u32::try_from(out.len() + moov_len + 8).ok()?;
    u32::try_from(out.len() + moov_len + 8 + media).ok()?;
    out.extend_from_slice(&moov(track, chunk_offset));
    out.extend_from_slice(&((8 + media) as u32).to_be_bytes());
    out.extend_from_slice(b"mdat");
    for s in &track.samples {
        out.extend_from_slice(&s.data);
    }
    Some(out)
}

/// What [`inspect`] reads from an MP4 file's first video track.
#[cfg(any(test, feature = "check"))]
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Summary {
    /// The sample entry's width and height.
    pub width: u16,
    /// See `width`.
    pub height: u16,
    /// Time units per second of the media.
    pub timescale: u32,
    /// Each sample's duration, in time units.
    pub durations: Vec<u32>,
    /// Each sample's byte range in the file.
    pub samples: Vec<Range<usize>>,
    /// 1-based numbers of the sync samples (every sample when the file has no `stss`).
    pub sync: Vec<u32>,
    /// The `avcC` decoder configuration's SPS and PPS.
    pub sps: Vec<u8>,
    /// See `sps`.
    pub pps: Vec<u8>,
}

/// A box: type, body range (within the file).
#[cfg(any(test, feature = "check"))]
type Atom = ([u8; 4], Range<usize>);

/// The boxes laid end to end in `range` of `bytes`.
#[cfg(any(test, feature = "check"))]
fn atoms(bytes: &[u8], range: Range<usize>) -> Result<Vec<Atom>, String> {
    let mut found = Vec::new();
    let mut at = range.start;
    while at < range.end {
        let header = bytes
            .get(at..at + 8)
            .filter(|_| at + 8 <= range.end)
            .ok_or_else(|| format!("a box header at byte {at} runs past its parent"))?;
        let size = u32::from_be_bytes(header[..4].try_into().unwrap()) as usize;
        let kind: [u8; 4] = header[4..8].try_into().unwrap();
        let (body_start, end) = match size {
            0 => (at + 8, range.end),
            1 => {
                let large = bytes
                    .get(at + 8..at + 16)
                    .ok_or("a 64-bit box size runs past the file")?;
                let large = u64::from_be_bytes(large.try_into().unwrap());
                (at + 16, at.saturating_add(large as usize))
            }
            s => (at + 8, at.saturating_add(s)),
        };
        if end > range.end || end < body_start {
            return Err(format!(
                "box `{}` at byte {at} claims {size} bytes, more than its parent holds",
                String::from_utf8_lossy(&kind)
            ));
        }
        found.push((kind, body_start..end));
        at = end;
    }
    Ok(found)
}

/// The body of the first box `kind` among the boxes in `range`.
#[cfg(any(test, feature = "check"))]
fn child(bytes: &[u8], range: Range<usize>, kind: &[u8; 4]) -> Result<Range<usize>, String> {
    atoms(bytes, range)?
        .into_iter()
        .find(|(k, _)| k == kind)
        .map(|(_, r)| r)
        .ok_or_else(|| format!("no `{}` box", String::from_utf8_lossy(kind)))
}

/// Reads big-endian `u32`s (or `u16`s) at byte offsets of a box body.
#[cfg(any(test, feature = "check"))]
struct Reader<'a>(&'a [u8]);

#[cfg(any(test, feature = "check"))]
impl Reader<'_> {
    fn u32(&self, at: usize) -> Result<u32, String> {
        self.0
            .get(at..at + 4)
            .map(|b| u32::from_be_bytes(b.try_into().unwrap()))
            .ok_or_else(|| format!("a table ends before byte {}", at + 4))
    }

    fn u16(&self, at: usize) -> Result<u16, String> {
        self.0
            .get(at..at + 2)
            .map(|b| u16::from_be_bytes(b.try_into().unwrap()))
            .ok_or_else(|| format!("a table ends before byte {}", at + 2))
    }

    fn bytes(&self, at: usize, len: usize) -> Result<&[u8], String> {
        self.0
            .get(at..at + len)
            .ok_or_else(|| format!("a table ends before byte {}", at + len))
    }

    /// A full box's entry count at 4, then `count` entries of `width` bytes from 8.
    fn entries(&self, width: usize) -> Result<usize, String> {
        let count = self.u32(4)? as usize;
        if count.saturating_mul(width) > self.0.len().saturating_sub(8) {
            return Err(format!(
                "a table claims {count} entries, more than it holds"
            ));
        }
        Ok(count)
    }
}

/// Reads the first video track of an MP4 file: enough to check what [`mux`] wrote, and
/// to decode its samples.
///
/// # Errors
///
/// A message saying which box is missing or malformed.
#[cfg(any(test, feature = "check"))]
pub fn inspect(bytes: &[u8]) -> Result<Summary, String> {
    let moov = child(bytes, 0..bytes.len(), b"moov")?;
    let trak = atoms(bytes, moov)?
        .into_iter()
        .filter(|(k, _)| k == b"trak")
        .find(|(_, r)| {
            child(bytes, r.clone(), b"mdia")
                .and_then(|m| child(bytes, m, b"hdlr"))
                .is_ok_and(|h| bytes.get(h.start + 8..h.start + 12) == Some(b"vide"))
        })
        .ok_or("no video track")?
        .1;
    let mdia = child(bytes, trak, b"mdia")?;
    let mdhd = Reader(&bytes[child(bytes, mdia.clone(), b"mdhd")?]);
    if mdhd.0.first() != Some(&0) {
        return Err("a version-1 `mdhd` (64-bit times) is not read here".into());
    }
    let timescale = mdhd.u32(12)?;
    let stbl = child(bytes, child(bytes, mdia, b"minf")?, b"stbl")?;
    let table = |kind: &[u8; 4]| child(bytes, stbl.clone(), kind).map(|r| Reader(&bytes[r]));

    let stsd = child(bytes, stbl.clone(), b"stsd")?;
    let avc1 = child(bytes, stsd.start + 8..stsd.end, b"avc1")?;
    let entry = Reader(&bytes[avc1.clone()]);
    let (width, height) = (entry.u16(24)?, entry.u16(26)?);
    let avcc = Reader(&bytes[child(bytes, avc1.start + 78..avc1.end, b"avcC")?]);
    if avcc.bytes(5, 1)?[0] & 0x1f != 1 {
        return Err("the `avcC` box does not hold exactly one SPS".into());
    }
    let sps_len = avcc.u16(6)? as usize;
    let sps = avcc.bytes(8, sps_len)?.to_vec();
    let pps_len = avcc.u16(9 + sps_len)? as usize;
    let pps = avcc.bytes(11 + sps_len, pps_len)?.to_vec();

    let stsz = table(b"stsz")?;
    let count = stsz.u32(8)? as usize;
    let sizes: Vec<usize> = match stsz.u32(4)? {
        0 => {
            if count.saturating_mul(4) > stsz.0.len().saturating_sub(12) {
                return Err(format!("`stsz` claims {count} samples, more than it holds"));
            }
            (0..count)
                .map(|i| stsz.u32(12 + 4 * i).map(|s| s as usize))
                .collect::<Result<_, _>>()?
        }
        same => vec![same as usize; count],
    };

    let stts = table(b"stts")?;
    let mut durations = Vec::with_capacity(count);
    for e in 0..stts.entries(8)? {
        let (n, delta) = (stts.u32(8 + 8 * e)?, stts.u32(12 + 8 * e)?);
        if durations.len() + n as usize > count {
            return Err("`stts` times more samples than `stsz` sizes".into());
        }
        durations.extend(std::iter::repeat_n(delta, n as usize));
    }
    if durations.len() != count {
        return Err(format!(
            "`stts` times {} samples, `stsz` sizes {count}",
            durations.len()
        ));
    }

    let stco = table(b"stco")?;
    let chunks: Vec<usize> = (0..stco.entries(4)?)
        .map(|i| stco.u32(8 + 4 * i).map(|o| o as usize))
        .collect::<Result<_, _>>()?;
    let stsc = table(b"stsc")?;
    let runs: Vec<(usize, usize)> = (0..stsc.entries(12)?)
        .map(|i| {
            Ok((
                stsc.u32(8 + 12 * i)? as usize,
                stsc.u32(12 + 12 * i)? as usize,
            ))
        })
        .collect::<Result<_, String>>()?;
    let mut samples = Vec::with_capacity(count);
    for (c, &offset) in chunks.iter().enumerate() {
        let per_chunk = runs
            .iter()
            .rev()
            .find(|(first, _)| *first <= c + 1)
            .map_or(0, |r| r.1);
        let mut at = offset;
        for _ in 0..per_chunk {
            let Some(&size) = sizes.get(samples.len()) else {
                break;
            };
            if at + size > bytes.len() {
                return Err(format!(
                    "sample {} (bytes {at}..{}) runs past the file",
                    samples.len() + 1,
                    at + size
                ));
            }
            samples.push(at..at + size);
            at += size;
        }
    }
    if samples.len() != count {
        return Err(format!(
            "the chunks hold {} samples, `stsz` sizes {count}",
            samples.len()
        ));
    }
    let sync = match table(b"stss") {
        Ok(stss) => (0..stss.entries(4)?)
            .map(|i| stss.u32(8 + 4 * i))
            .collect::<Result<_, _>>()?,
        Err(_) => (1..=count as u32).collect(),
    };
    Ok(Summary {
        width,
        height,
        timescale,
        durations,
        samples,
        sync,
        sps,
        pps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(samples: usize) -> Track {
        Track {
            width: 34,
            height: 20,
            timescale: 90_000,
            sample_duration: 3000,
            sps: vec![0x67, 0x42, 0xc0, 0x1e, 1, 2, 3],
            pps: vec![0x68, 0xce, 0x3c, 0x80],
            samples: (0..samples)
                .map(|i| Sample {
                    data: vec![i as u8; 10 + i],
                    sync: i == 0,
                })
                .collect(),
        }
    }

    #[test]
    fn what_is_written_reads_back() {
        let track = track(5);
        let bytes = mux(&track).unwrap();
        let summary = inspect(&bytes).unwrap();
        assert_eq!((summary.width, summary.height), (34, 20));
        assert_eq!(summary.timescale, 90_000);
        assert_eq!(summary.durations, vec![3000; 5]);
        assert_eq!(summary.sync, vec![1]);
        assert_eq!((summary.sps, summary.pps), (track.sps, track.pps));
        for (range, sample) in summary.samples.iter().zip(&track.samples) {
            assert_eq!(&bytes[range.clone()], &sample.data[..]);
        }
        // Fast start: the tables come before the media.
        assert_eq!(&bytes[4..8], b"ftyp");
        let moov = bytes.windows(4).position(|w| w == b"moov").unwrap();
        let mdat = bytes.windows(4).position(|w| w == b"mdat").unwrap();
        assert!(moov < mdat);
    }

    #[test]
    fn truncated_or_corrupt_files_are_refused_not_misread() {
        let bytes = mux(&track(3)).unwrap();
        for cut in [10, 100, bytes.len() - 5] {
            assert!(inspect(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut wrong = bytes.clone();
        let stsz = wrong.windows(4).position(|w| w == b"stsz").unwrap();
        // The sample count of stsz, far above what the table holds.
        wrong[stsz + 12..stsz + 16].copy_from_slice(&u32::MAX.to_be_bytes());
        assert!(inspect(&wrong).unwrap_err().contains("stsz"));
    }
}
