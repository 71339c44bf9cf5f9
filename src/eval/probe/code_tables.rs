//! `shoal eval probe code-tables`: regenerate the code tables under
//! `proto/data/codes/` from the installed libraries — OpenCV 4.6's ArUco
//! dictionaries and libapriltag 3's classic families. Each marker is
//! rendered by its own library at one pixel per module and its data modules
//! are read back, so the tables follow the libraries' printed markers
//! exactly (format: see `proto/src/marker.rs`). The tables are committed;
//! nothing builds them, this only re-derives them (e.g. for another library
//! version: compare with `git diff`).

use crate::eval::EvalError;
use opencv::{aruco, core, prelude::*};
use shoal_node::baseline::apriltag_ffi::{Family, FamilyHandle, DEFAULT_BITS_CORRECTED};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

#[derive(Debug, clap::Args)]
pub struct CodeTablesArgs {
    /// Folder the tables are written into.
    #[arg(long, default_value = "proto/data/codes")]
    pub out: PathBuf,
}

/// A table: data side, correctable bits, codes.
type Table = (usize, u32, Vec<u64>);

/// Pack an `n`x`n` grid (row-major, `true` = white) MSB-first.
fn pack(bits: impl Iterator<Item = bool>) -> u64 {
    bits.fold(0u64, |acc, b| (acc << 1) | u64::from(b))
}

fn aruco_table(dict_name: aruco::PREDEFINED_DICTIONARY_NAME) -> Result<Table, EvalError> {
    let dict = aruco::get_predefined_dictionary(dict_name)?;
    let n = dict.marker_size() as usize;
    let count = dict.bytes_list().rows() as usize;
    let mut codes = Vec::with_capacity(count);
    for id in 0..count {
        let mut img = core::Mat::default();
        // One pixel per module, one-module black border.
        aruco::draw_marker(&dict, id as i32, (n + 2) as i32, &mut img, 1)?;
        if img.rows() as usize != n + 2 || img.cols() as usize != n + 2 {
            return Err(EvalError::Setup(format!(
                "ArUco marker {id} drawn {}x{}, expected {}x{}",
                img.cols(),
                img.rows(),
                n + 2,
                n + 2
            )));
        }
        let mut bits = Vec::with_capacity(n * n);
        for r in 0..n {
            for c in 0..n {
                bits.push(*img.at_2d::<u8>((r + 1) as i32, (c + 1) as i32)? > 127);
            }
        }
        codes.push(pack(bits.into_iter()));
    }
    Ok((n, dict.max_correction_bits() as u32, codes))
}

fn apriltag_table(family: Family) -> Result<Table, EvalError> {
    let fam = FamilyHandle::new(family)
        .ok_or_else(|| EvalError::Setup(format!("libapriltag: creating {family:?} failed")))?;
    let border = fam.width_at_border();
    let n = border - 2;
    let mut codes = Vec::with_capacity(fam.ncodes());
    for id in 0..fam.ncodes() {
        let (w, px) = fam
            .render(id)
            .ok_or_else(|| EvalError::Setup(format!("libapriltag: rendering {id} failed")))?;
        // Classic families: black border of `width_at_border` modules centred in `total_width`.
        let off = (w - border) / 2 + 1;
        let bits = (0..n)
            .flat_map(|r| (0..n).map(move |c| (r, c)))
            .map(|(r, c)| px[(off + r) * w + off + c] > 127);
        codes.push(pack(bits));
    }
    // libapriltag's detector default (apriltag_detector_add_family -> 2 bits).
    Ok((n, DEFAULT_BITS_CORRECTED, codes))
}

fn write_table(path: &Path, source: &str, (n, k, codes): Table) -> Result<(), EvalError> {
    let mut s = String::new();
    // Writing into a String cannot fail.
    let _ = writeln!(s, "# {source}; extracted by `shoal eval probe code-tables`");
    let _ = writeln!(
        s,
        "# data bits row-major from the top-left, MSB first, 1 = white, upright"
    );
    let _ = writeln!(s, "# data_side = {n}");
    let _ = writeln!(s, "# max_correction_bits = {k}");
    let digits = (n * n).div_ceil(4);
    for c in &codes {
        let _ = writeln!(s, "0x{c:0digits$x}");
    }
    std::fs::write(path, s).map_err(|source| EvalError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    crate::outln!(
        "{}: {} codes, {n}x{n}, max_correction_bits = {k}",
        path.display(),
        codes.len()
    );
    Ok(())
}

pub fn run(a: &CodeTablesArgs) -> Result<(), EvalError> {
    use aruco::PREDEFINED_DICTIONARY_NAME as D;
    std::fs::create_dir_all(&a.out).map_err(|source| EvalError::Io {
        path: a.out.clone(),
        source,
    })?;
    write_table(
        &a.out.join("aruco_4x4_1000.txt"),
        "OpenCV 4.6 DICT_4X4_1000",
        aruco_table(D::DICT_4X4_1000)?,
    )?;
    write_table(
        &a.out.join("aruco_5x5_1000.txt"),
        "OpenCV 4.6 DICT_5X5_1000",
        aruco_table(D::DICT_5X5_1000)?,
    )?;
    write_table(
        &a.out.join("aruco_6x6_1000.txt"),
        "OpenCV 4.6 DICT_6X6_1000",
        aruco_table(D::DICT_6X6_1000)?,
    )?;
    write_table(
        &a.out.join("apriltag_16h5.txt"),
        "libapriltag 3 tag16h5 (max_correction_bits: detector default)",
        apriltag_table(Family::Tag16h5)?,
    )?;
    write_table(
        &a.out.join("apriltag_36h11.txt"),
        "libapriltag 3 tag36h11 (max_correction_bits: detector default)",
        apriltag_table(Family::Tag36h11)?,
    )?;
    Ok(())
}
