//! Marker code sets and their physical layouts.
//!
//! Every marker here is a square of black and white *modules*. Its
//! **footprint** is the side of its outer black square, `side_m`; all markers
//! are printed with a one-module white quiet zone around that square. So an
//! enhanced marker, an ArUco and an AprilTag "of the same footprint" have the
//! same outer black square and can be compared on identical images.
//!
//! | code set            | modules across the black square | layout from the outside in                                  | corners |
//! |---------------------|---------------------------------|-------------------------------------------------------------|---------|
//! | `shoal` (paper §3.2)| 10                              | black frame, white ring, black code border, 4x4 data (ArUco 4x4) | 12      |
//! | `arucoNxN_M`        | N + 2                           | black border, NxN data                                      | 4       |
//! | `apriltag16h5`      | 6                               | black border, 4x4 data                                      | 4       |
//! | `apriltag36h11`     | 8                               | black border, 6x6 data                                      | 4       |
//!
//! **Data bits** of a code are a `u64` holding the data grid row-major from
//! the top-left module, most significant bit first (bit `n·n−1−(r·n+c)` is row
//! `r`, column `c`), **1 = white**, in the marker's upright orientation. The
//! tables under `proto/data/codes/` are extracted from OpenCV 4.6 (ArUco) and
//! libapriltag 3 (AprilTag) by `shoal eval probe code-tables`, and a parity
//! test in `shoal-node` checks them against those libraries.
//!
//! **Marker frame**: origin at the centre of the face, x to the right of the
//! upright printed image, y up, z out of the face (towards a viewer). Corners
//! are listed per square clockwise as seen by that viewer: top-left,
//! top-right, bottom-right, bottom-left.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};
use std::sync::OnceLock;

/// A marker ID within its code set.
pub type MarkerId = u32;

/// The code sets shoal can print, render and read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[allow(non_camel_case_types)]
pub enum CodeSet {
    /// The paper's enhanced AR-coded marker: ArUco 4x4_50 data, 12 corners.
    Shoal,
    Aruco4x4_50,
    Aruco4x4_100,
    Aruco4x4_250,
    Aruco4x4_1000,
    Aruco5x5_50,
    Aruco5x5_100,
    Aruco5x5_250,
    Aruco5x5_1000,
    Aruco6x6_50,
    Aruco6x6_100,
    Aruco6x6_250,
    Aruco6x6_1000,
    AprilTag16h5,
    AprilTag36h11,
}

/// A code set's bit table, parsed once from `proto/data/codes/*.txt`.
#[derive(Debug)]
pub struct CodeTable {
    /// Side of the data grid in modules.
    pub data_side: usize,
    /// How many bit errors a decoder may correct (the dictionary's own figure).
    pub max_correction_bits: u32,
    /// Data bits of each ID, see the module docs.
    pub codes: Vec<u64>,
}

/// Errors of this module.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum MarkerError {
    #[error("unknown code set {name:?}; known: {known}")]
    UnknownCodeSet { name: String, known: String },
    #[error("marker ID {id} is not in code set {set} (IDs 0..{len})")]
    IdOutOfRange {
        set: &'static str,
        id: MarkerId,
        len: usize,
    },
    #[error("code table for {set} is empty; run `shoal eval probe code-tables`")]
    TableMissing { set: &'static str },
}

const ALL: [CodeSet; 15] = [
    CodeSet::Shoal,
    CodeSet::Aruco4x4_50,
    CodeSet::Aruco4x4_100,
    CodeSet::Aruco4x4_250,
    CodeSet::Aruco4x4_1000,
    CodeSet::Aruco5x5_50,
    CodeSet::Aruco5x5_100,
    CodeSet::Aruco5x5_250,
    CodeSet::Aruco5x5_1000,
    CodeSet::Aruco6x6_50,
    CodeSet::Aruco6x6_100,
    CodeSet::Aruco6x6_250,
    CodeSet::Aruco6x6_1000,
    CodeSet::AprilTag16h5,
    CodeSet::AprilTag36h11,
];

static ARUCO_4X4: &str = include_str!("../data/codes/aruco_4x4_1000.txt");
static ARUCO_5X5: &str = include_str!("../data/codes/aruco_5x5_1000.txt");
static ARUCO_6X6: &str = include_str!("../data/codes/aruco_6x6_1000.txt");
static APRILTAG_16H5: &str = include_str!("../data/codes/apriltag_16h5.txt");
static APRILTAG_36H11: &str = include_str!("../data/codes/apriltag_36h11.txt");

/// Parse a table file: `# data_side = N`, `# max_correction_bits = K`, then one hex code per line.
fn parse_table(text: &str) -> CodeTable {
    let mut data_side = 0;
    let mut max_correction_bits = 0;
    let mut codes = Vec::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        if let Some(rest) = line.strip_prefix('#') {
            if let Some((k, v)) = rest.split_once('=') {
                match k.trim() {
                    "data_side" => data_side = v.trim().parse().unwrap_or(0),
                    "max_correction_bits" => max_correction_bits = v.trim().parse().unwrap_or(0),
                    _ => {}
                }
            }
        } else if let Ok(c) = u64::from_str_radix(line.trim_start_matches("0x"), 16) {
            codes.push(c);
        }
    }
    CodeTable {
        data_side,
        max_correction_bits,
        codes,
    }
}

fn table(text: &'static str, cell: &'static OnceLock<CodeTable>) -> &'static CodeTable {
    cell.get_or_init(|| parse_table(text))
}

impl CodeSet {
    pub fn all() -> &'static [CodeSet] {
        &ALL
    }

    /// The name used on the command line and in config files.
    pub fn name(self) -> &'static str {
        use CodeSet::*;
        match self {
            Shoal => "shoal",
            Aruco4x4_50 => "aruco4x4_50",
            Aruco4x4_100 => "aruco4x4_100",
            Aruco4x4_250 => "aruco4x4_250",
            Aruco4x4_1000 => "aruco4x4_1000",
            Aruco5x5_50 => "aruco5x5_50",
            Aruco5x5_100 => "aruco5x5_100",
            Aruco5x5_250 => "aruco5x5_250",
            Aruco5x5_1000 => "aruco5x5_1000",
            Aruco6x6_50 => "aruco6x6_50",
            Aruco6x6_100 => "aruco6x6_100",
            Aruco6x6_250 => "aruco6x6_250",
            Aruco6x6_1000 => "aruco6x6_1000",
            AprilTag16h5 => "apriltag16h5",
            AprilTag36h11 => "apriltag36h11",
        }
    }

    pub fn from_name(name: &str) -> Result<CodeSet, MarkerError> {
        ALL.iter()
            .copied()
            .find(|c| c.name().eq_ignore_ascii_case(name.trim()))
            .ok_or_else(|| MarkerError::UnknownCodeSet {
                name: name.to_string(),
                known: ALL.iter().map(|c| c.name()).collect::<Vec<_>>().join(", "),
            })
    }

    /// How many IDs the set has (its dictionary size).
    pub fn len(self) -> usize {
        use CodeSet::*;
        let n = match self {
            Shoal | Aruco4x4_50 | Aruco5x5_50 | Aruco6x6_50 => 50,
            Aruco4x4_100 | Aruco5x5_100 | Aruco6x6_100 => 100,
            Aruco4x4_250 | Aruco5x5_250 | Aruco6x6_250 => 250,
            Aruco4x4_1000 | Aruco5x5_1000 | Aruco6x6_1000 => 1000,
            AprilTag16h5 => 30,
            AprilTag36h11 => 587,
        };
        n.min(self.table().codes.len())
    }

    pub fn is_empty(self) -> bool {
        self.len() == 0
    }

    /// The bit table behind this set (the larger ArUco dictionaries are prefixes of the 1000-code ones).
    pub fn table(self) -> &'static CodeTable {
        use CodeSet::*;
        static T4: OnceLock<CodeTable> = OnceLock::new();
        static T5: OnceLock<CodeTable> = OnceLock::new();
        static T6: OnceLock<CodeTable> = OnceLock::new();
        static T16: OnceLock<CodeTable> = OnceLock::new();
        static T36: OnceLock<CodeTable> = OnceLock::new();
        match self {
            Shoal | Aruco4x4_50 | Aruco4x4_100 | Aruco4x4_250 | Aruco4x4_1000 => {
                table(ARUCO_4X4, &T4)
            }
            Aruco5x5_50 | Aruco5x5_100 | Aruco5x5_250 | Aruco5x5_1000 => table(ARUCO_5X5, &T5),
            Aruco6x6_50 | Aruco6x6_100 | Aruco6x6_250 | Aruco6x6_1000 => table(ARUCO_6X6, &T6),
            AprilTag16h5 => table(APRILTAG_16H5, &T16),
            AprilTag36h11 => table(APRILTAG_36H11, &T36),
        }
    }

    /// Side of the data grid in modules.
    pub fn data_side(self) -> usize {
        use CodeSet::*;
        match self {
            Shoal | Aruco4x4_50 | Aruco4x4_100 | Aruco4x4_250 | Aruco4x4_1000 | AprilTag16h5 => 4,
            Aruco5x5_50 | Aruco5x5_100 | Aruco5x5_250 | Aruco5x5_1000 => 5,
            Aruco6x6_50 | Aruco6x6_100 | Aruco6x6_250 | Aruco6x6_1000 | AprilTag36h11 => 6,
        }
    }

    /// Modules across the outer black square.
    pub fn modules(self) -> usize {
        match self {
            CodeSet::Shoal => 10,
            other => other.data_side() + 2,
        }
    }

    /// The data bits of `id`, or an error naming the valid range.
    pub fn code(self, id: MarkerId) -> Result<u64, MarkerError> {
        let t = self.table();
        if t.codes.is_empty() {
            return Err(MarkerError::TableMissing { set: self.name() });
        }
        if (id as usize) >= self.len() {
            return Err(MarkerError::IdOutOfRange {
                set: self.name(),
                id,
                len: self.len(),
            });
        }
        Ok(t.codes[id as usize])
    }

    /// The module grid of marker `id` across its black square, row-major from
    /// the top-left, `true` = white. Its side is [`CodeSet::modules`].
    pub fn module_grid(self, id: MarkerId) -> Result<Vec<bool>, MarkerError> {
        let code = self.code(id)?;
        let m = self.modules();
        let n = self.data_side();
        let off = (m - n) / 2;
        let mut grid = vec![false; m * m];
        for r in 0..m {
            for c in 0..m {
                let ring = r.min(c).min(m - 1 - r).min(m - 1 - c);
                grid[r * m + c] = if r >= off && r < off + n && c >= off && c < off + n {
                    code_bit(code, n, r - off, c - off)
                } else {
                    // Only the enhanced marker has rings: black frame (0), white ring (1), black border (2).
                    self == CodeSet::Shoal && ring == 1
                };
            }
        }
        Ok(grid)
    }

    /// The 3-D corners in the marker frame for a marker of footprint `side_m`:
    /// for `shoal` the outer frame edge, the frame's inner edge and the code
    /// border's outer edge (12 points); for the others the black square (4).
    pub fn corners_3d(self, side_m: f64) -> Vec<Point3<f64>> {
        let halves: &[f64] = match self {
            CodeSet::Shoal => &[0.5, 0.4, 0.3],
            _ => &[0.5],
        };
        halves
            .iter()
            .flat_map(|&f| {
                let h = f * side_m;
                [
                    Point3::new(-h, h, 0.0),
                    Point3::new(h, h, 0.0),
                    Point3::new(h, -h, 0.0),
                    Point3::new(-h, -h, 0.0),
                ]
            })
            .collect()
    }

    /// How many corners a fully visible marker gives.
    pub fn corner_count(self) -> usize {
        if self == CodeSet::Shoal {
            12
        } else {
            4
        }
    }
}

impl std::fmt::Display for CodeSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for CodeSet {
    type Err = MarkerError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        CodeSet::from_name(s)
    }
}

/// Bit at row `r`, column `c` of an `n`x`n` code (`true` = white).
pub fn code_bit(code: u64, n: usize, r: usize, c: usize) -> bool {
    (code >> (n * n - 1 - (r * n + c))) & 1 == 1
}

/// The code as seen after rotating the marker 90° clockwise `k` times.
pub fn rotate_code(code: u64, n: usize, k: usize) -> u64 {
    let mut cur = code;
    for _ in 0..(k % 4) {
        let mut next = 0u64;
        for r in 0..n {
            for c in 0..n {
                // Clockwise: new (r, c) takes old (n-1-c, r).
                if code_bit(cur, n, n - 1 - c, r) {
                    next |= 1 << (n * n - 1 - (r * n + c));
                }
            }
        }
        cur = next;
    }
    cur
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for &c in CodeSet::all() {
            assert_eq!(CodeSet::from_name(c.name()).unwrap(), c);
        }
        assert!(matches!(
            CodeSet::from_name("qr"),
            Err(MarkerError::UnknownCodeSet { .. })
        ));
    }

    #[test]
    fn four_rotations_are_identity() {
        let code = 0b1011_0010_0111_0001u64;
        assert_eq!(rotate_code(code, 4, 4), code);
        assert_ne!(rotate_code(code, 4, 1), code);
        assert_eq!(rotate_code(rotate_code(code, 4, 1), 4, 3), code);
    }

    #[test]
    fn rotation_moves_top_left_to_top_right() {
        // Only the top-left bit set: after a clockwise quarter turn it is top-right.
        let tl = 1u64 << 15;
        let r = rotate_code(tl, 4, 1);
        assert!(code_bit(r, 4, 0, 3));
    }

    #[test]
    fn enhanced_marker_has_twelve_nested_corners() {
        let c = CodeSet::Shoal.corners_3d(0.1);
        assert_eq!(c.len(), 12);
        assert!((c[0].x + 0.05).abs() < 1e-12 && (c[0].y - 0.05).abs() < 1e-12);
        assert!((c[4].x + 0.04).abs() < 1e-12);
        assert!((c[8].x + 0.03).abs() < 1e-12);
        assert_eq!(CodeSet::AprilTag36h11.corners_3d(0.1).len(), 4);
    }

    #[test]
    fn paper_ids_exist_in_the_enhanced_set() {
        for id in [10, 15, 17] {
            let grid = CodeSet::Shoal.module_grid(id).unwrap();
            assert_eq!(grid.len(), 100);
            // Black frame, white ring, black code border.
            assert!(!grid[0] && grid[11] && !grid[22]);
        }
        assert!(matches!(
            CodeSet::Shoal.code(50),
            Err(MarkerError::IdOutOfRange { .. })
        ));
    }
}
