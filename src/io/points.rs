//! Landmark files (`--points`, SPEC §11): pairs of a point of A and the same point of B,
//! each in its own input file's pixel coordinates, and their mapping to the working grid.
//!
//! Two formats, told apart by the file's first non-blank character:
//! - CSV with a header naming the columns `x_a,y_a,x_b,y_b` (in any order), and for a chain
//!   optionally `segment` (1 for the first pair of images, 2 for the next, …): one pair a
//!   line;
//! - JSON: an array of `{"a": [x, y], "b": [x, y]}`, with `"segment": n` for a chain.
//!
//! `x` is the column and `y` the row, with the origin at the centre of the top-left pixel;
//! fractional values are allowed.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::model::energy::landmarks::Landmarks;
use crate::read::read_bytes;

/// One landmark pair: `a` a point of A, `b` the same point of B, `[x, y]` each (column, row;
/// pixels of the image they belong to, origin at the centre of the top-left pixel).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointPair {
    /// The point of A, `[x, y]`.
    pub a: [f64; 2],
    /// The point of B, `[x, y]`.
    pub b: [f64; 2],
    /// In a chain, the segment the pair belongs to (1 = the first two images); `None` in a
    /// morph of two images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segment: Option<usize>,
}

impl PointPair {
    /// The pair `a` → `b`, of no particular segment.
    pub fn new(a: [f64; 2], b: [f64; 2]) -> Self {
        Self {
            a,
            b,
            segment: None,
        }
    }
}

/// The columns a CSV points file must have.
const COLUMNS: [&str; 4] = ["x_a", "y_a", "x_b", "y_b"];

/// The optional column of a chain's CSV points file.
const SEGMENT: &str = "segment";

/// The pairs of each of `segments` segments (`None`: a segment without pairs). Pairs that
/// name no segment belong to the only one of a morph of two images.
///
/// # Errors
///
/// [`Error::InvalidParameter`] for a segment number out of `1..=segments`, or, in a chain,
/// a pair that names no segment.
pub fn split_by_segment(
    pairs: &[PointPair],
    segments: usize,
) -> Result<Vec<Option<Vec<PointPair>>>> {
    let mut out: Vec<Vec<PointPair>> = vec![Vec::new(); segments];
    for (i, pair) in pairs.iter().enumerate() {
        let segment = match pair.segment {
            Some(s) if (1..=segments).contains(&s) => s,
            Some(s) => {
                return Err(Error::invalid(
                    "points",
                    format!("pair {}: segment {s}", i + 1),
                    format!(
                        "a segment in 1..={segments} (the images give {segments} consecutive \
                         pair(s))"
                    ),
                ));
            }
            None if segments == 1 => 1,
            None => {
                return Err(Error::invalid(
                    "points",
                    format!("pair {} of a chain names no segment", i + 1),
                    "a `segment` column (1 = the first two images), or one --points file per \
                     segment, in order",
                ));
            }
        };
        out[segment - 1].push(PointPair {
            segment: None,
            ..*pair
        });
    }
    Ok(out
        .into_iter()
        .map(|p| (!p.is_empty()).then_some(p))
        .collect())
}

/// Reads a points file (at most 16 MiB).
///
/// # Errors
///
/// [`Error::Io`] if it cannot be read; [`Error::Format`] naming the file and the line for
/// wrong columns, a value that is not a number or a file with no pair.
pub fn read_points(path: &Path) -> Result<Vec<PointPair>> {
    let bytes = read_bytes(path, 16 << 20, "points file")?;
    let text = String::from_utf8_lossy(&bytes);
    parse_points(&text).map_err(|detail| Error::Format {
        path: path.to_path_buf(),
        detail,
    })
}

/// Parses the text of a points file (see the module docs).
///
/// # Errors
///
/// A message naming what is wrong (and the line of a CSV).
pub fn parse_points(text: &str) -> std::result::Result<Vec<PointPair>, String> {
    let pairs = if text.trim_start().starts_with('[') {
        serde_json::from_str::<Vec<PointPair>>(text).map_err(|e| {
            format!("not a JSON points file ([{{\"a\": [x, y], \"b\": [x, y]}}, …]): {e}")
        })?
    } else {
        parse_csv(text)?
    };
    if pairs.is_empty() {
        return Err("no landmark pair: at least 1 is needed".into());
    }
    Ok(pairs)
}

fn parse_csv(text: &str) -> std::result::Result<Vec<PointPair>, String> {
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, line)| !line.trim().is_empty());
    let header: Vec<&str> = lines
        .next()
        .map(|(_, line)| line.split(',').map(str::trim).collect())
        .unwrap_or_default();
    let wanted = || {
        format!(
            "a CSV header naming the columns {} (any order), or a JSON array",
            COLUMNS.join(",")
        )
    };
    let segment_at = header.iter().position(|h| *h == SEGMENT);
    let columns = COLUMNS.len() + usize::from(segment_at.is_some());
    if header.len() != columns {
        return Err(format!(
            "header `{}`: expected {}",
            header.join(","),
            wanted()
        ));
    }
    let at: Vec<usize> = COLUMNS
        .iter()
        .map(|name| header.iter().position(|h| h == name))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("header `{}`: expected {}", header.join(","), wanted()))?;
    lines
        .map(|(i, line)| {
            let cells: Vec<&str> = line.split(',').map(str::trim).collect();
            if cells.len() != columns {
                return Err(format!(
                    "line {}: {} values, expected {columns}",
                    i + 1,
                    cells.len(),
                ));
            }
            let segment = segment_at
                .map(|at| {
                    let cell = cells[at];
                    cell.parse::<usize>()
                        .ok()
                        .filter(|&s| s >= 1)
                        .ok_or_else(|| {
                            format!("line {}: segment = `{cell}` is not a number ≥ 1", i + 1)
                        })
                })
                .transpose()?;
            let value = |column: usize| -> std::result::Result<f64, String> {
                let cell = cells[at[column]];
                cell.parse::<f64>().map_err(|_| {
                    format!(
                        "line {}: {} = `{cell}` is not a number",
                        i + 1,
                        COLUMNS[column]
                    )
                })
            };
            Ok(PointPair {
                a: [value(0)?, value(1)?],
                b: [value(2)?, value(3)?],
                segment,
            })
        })
        .collect()
}

/// A coordinate of an input of `from` pixels on a side, on the working grid's `to`: pixel
/// centres map as the resampling to the working size maps them (`image`'s resize, which
/// samples output pixel `i` at input position `(i + ½)·from/to − ½`), so
/// `x_w = (x + ½)·to/from − ½`. The identity when the sizes agree.
pub fn to_working(x: f64, from: usize, to: usize) -> f64 {
    if from == to {
        return x;
    }
    (x + 0.5) * to as f64 / from as f64 - 0.5
}

/// The pairs on the working grid of `working` `(H, W)`, from inputs of `size_a` and
/// `size_b` `(H, W)`, as [`Landmarks`] (`[row, col]`).
///
/// # Errors
///
/// [`Error::InvalidParameter`] for a point outside its image, or anything
/// [`Landmarks::new`] refuses on the working grid (not finite, within one pixel of the
/// border, one point of A with two partners).
pub fn landmarks_on_working_grid(
    pairs: &[PointPair],
    size_a: (usize, usize),
    size_b: (usize, usize),
    working: (usize, usize),
) -> Result<Landmarks> {
    let map = |side: &str, i: usize, [x, y]: [f64; 2], (h, w): (usize, usize)| {
        let inside = (0.0..=(w - 1) as f64).contains(&x) && (0.0..=(h - 1) as f64).contains(&y);
        if !inside && x.is_finite() && y.is_finite() {
            return Err(Error::invalid(
                "points",
                format!("pair {}: the point of {side} = ({x}, {y}) (x, y)", i + 1),
                format!(
                    "inside the {w}x{h} image: x in [0, {}], y in [0, {}]",
                    w - 1,
                    h - 1
                ),
            ));
        }
        Ok([to_working(y, h, working.0), to_working(x, w, working.1)])
    };
    let mut a = Vec::with_capacity(pairs.len());
    let mut b = Vec::with_capacity(pairs.len());
    for (i, pair) in pairs.iter().enumerate() {
        a.push(map("A", i, pair.a, size_a)?);
        b.push(map("B", i, pair.b, size_b)?);
    }
    Landmarks::new(a, b, working)
}

/// The pairs of `landmarks` as [`PointPair`]s in its grid's pixels (`[x, y]`).
pub fn pairs_of(landmarks: &Landmarks) -> Vec<PointPair> {
    let (a, b) = landmarks.pairs();
    a.iter()
        .zip(b)
        .map(|(p, q)| PointPair::new([p[1], p[0]], [q[1], q[0]]))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_and_json_files_give_the_same_pairs() {
        let csv = "y_a, x_a,x_b,y_b\n2,3,4.5,6\n\n7,8,9,10\n";
        let json = r#"[{"a": [3, 2], "b": [4.5, 6]}, {"a": [8, 7], "b": [9, 10]}]"#;
        let expected = vec![
            PointPair::new([3.0, 2.0], [4.5, 6.0]),
            PointPair::new([8.0, 7.0], [9.0, 10.0]),
        ];
        assert_eq!(parse_points(csv).unwrap(), expected);
        assert_eq!(parse_points(json).unwrap(), expected);
    }

    #[test]
    fn a_chain_names_the_segment_of_each_pair() {
        let csv = "segment,x_a,y_a,x_b,y_b\n2,3,2,4.5,6\n1,8,7,9,10\n";
        let json = r#"[{"a": [3, 2], "b": [4.5, 6], "segment": 2},
                       {"a": [8, 7], "b": [9, 10], "segment": 1}]"#;
        for text in [csv, json] {
            let pairs = parse_points(text).unwrap();
            assert_eq!(pairs[0].segment, Some(2));
            let split = split_by_segment(&pairs, 3).unwrap();
            assert_eq!(
                split,
                vec![
                    Some(vec![PointPair::new([8.0, 7.0], [9.0, 10.0])]),
                    Some(vec![PointPair::new([3.0, 2.0], [4.5, 6.0])]),
                    None
                ]
            );
            let err = split_by_segment(&pairs, 1).unwrap_err().to_string();
            assert!(err.contains("segment 2") && err.contains("1..=1"), "{err}");
        }
        let plain = parse_points("x_a,y_a,x_b,y_b\n1,2,3,4\n").unwrap();
        assert_eq!(
            split_by_segment(&plain, 1).unwrap(),
            vec![Some(plain.clone())]
        );
        let err = split_by_segment(&plain, 2).unwrap_err().to_string();
        assert!(err.contains("names no segment"), "{err}");
        let bad = parse_points("segment,x_a,y_a,x_b,y_b\n0,1,2,3,4\n").unwrap_err();
        assert!(bad.contains("segment = `0`"), "{bad}");
    }

    #[test]
    fn bad_files_are_refused_with_what_is_wrong() {
        let wrong = parse_points("x,y,u,v\n1,2,3,4\n").unwrap_err();
        assert!(wrong.contains("x_a,y_a,x_b,y_b"), "{wrong}");
        let short = parse_points("x_a,y_a,x_b,y_b\n1,2,3\n").unwrap_err();
        assert!(short.contains("line 2: 3 values"), "{short}");
        let word = parse_points("x_a,y_a,x_b,y_b\n1,2,three,4\n").unwrap_err();
        assert!(word.contains("line 2: x_b = `three`"), "{word}");
        assert!(
            parse_points("x_a,y_a,x_b,y_b\n")
                .unwrap_err()
                .contains("at least 1")
        );
        assert!(parse_points("[]").unwrap_err().contains("at least 1"));
        assert!(
            parse_points(r#"[{"a": [1, 2]}]"#)
                .unwrap_err()
                .contains("JSON")
        );
    }

    #[test]
    fn points_map_to_the_working_grid_by_pixel_centres() {
        // Halving: pixel centres 0.5 and 2.5 of a 4-pixel side are the centres of pixels 0
        // and 1 of a 2-pixel side.
        assert_eq!(to_working(0.5, 4, 2), 0.0);
        assert_eq!(to_working(2.5, 4, 2), 1.0);
        assert_eq!(to_working(1.25, 7, 7), 1.25);
        let pairs = [PointPair::new([10.0, 5.0], [20.0, 30.0])];
        let l = landmarks_on_working_grid(&pairs, (40, 40), (80, 40), (40, 40)).unwrap();
        // B is 80 rows high: its row 30 is row (30.5)/2 − 0.5 = 14.75 at 40 rows.
        assert_eq!(l.pairs(), (&[[5.0, 10.0]][..], &[[14.75, 20.0]][..]));
        assert_eq!(pairs_of(&l)[0].b, [20.0, 14.75]);
        // One pair on 40² images and a 40² working grid.
        let refused = |a: [f64; 2]| {
            let pair = PointPair::new(a, [20.0, 30.0]);
            landmarks_on_working_grid(&[pair], (40, 40), (40, 40), (40, 40))
                .unwrap_err()
                .to_string()
        };
        let outside = refused([40.0, 5.0]);
        assert!(
            outside.contains("pair 1: the point of A") && outside.contains("x in [0, 39]"),
            "{outside}"
        );
        assert!(refused([0.5, 5.0]).contains("at least one"));
        assert!(refused([f64::NAN, 5.0]).contains("finite"));
    }
}
