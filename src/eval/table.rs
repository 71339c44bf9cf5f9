//! Small statistics and a CSV writer for the evaluation's outputs.

use super::EvalError;
use std::fmt::Write as _;
use std::path::Path;

/// The `q`-quantile (0..=1) of `values` by linear interpolation between
/// order statistics (R's type 7, numpy's default); `None` when empty.
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let pos = q.clamp(0.0, 1.0) * (v.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    Some(v[lo] + (v[hi] - v[lo]) * (pos - lo as f64))
}

/// The median of the finite values; `None` when there are none.
pub fn median(values: &[f64]) -> Option<f64> {
    quantile(values, 0.5)
}

/// Root mean square of the finite values; `None` when there are none.
pub fn rmse(values: &[f64]) -> Option<f64> {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    (!v.is_empty()).then(|| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt())
}

/// A CSV table built in memory and written at once.
#[derive(Debug, Clone)]
pub struct Csv {
    columns: usize,
    text: String,
}

impl Csv {
    pub fn new(header: &[&str]) -> Csv {
        let mut c = Csv {
            columns: header.len(),
            text: String::new(),
        };
        c.push_fields(header.iter().map(|s| s.to_string()));
        c
    }

    fn push_fields(&mut self, fields: impl Iterator<Item = String>) {
        let mut first = true;
        for f in fields {
            if !first {
                self.text.push(',');
            }
            first = false;
            if f.contains([',', '"', '\n']) {
                let _ = write!(self.text, "\"{}\"", f.replace('"', "\"\""));
            } else {
                self.text.push_str(&f);
            }
        }
        self.text.push('\n');
    }

    /// Append a row; its length must match the header's.
    pub fn row(&mut self, fields: Vec<String>) {
        debug_assert_eq!(fields.len(), self.columns, "CSV row width");
        self.push_fields(fields.into_iter());
    }

    pub fn write(&self, path: &Path) -> Result<(), EvalError> {
        std::fs::write(path, &self.text).map_err(|source| EvalError::Io {
            path: path.to_path_buf(),
            source,
        })
    }
}

/// A number for a CSV cell: empty when missing or not finite.
pub fn cell(v: Option<f64>) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.6}"),
        _ => String::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_like_numpy() {
        let v = [4.0, 1.0, 3.0, 2.0];
        assert_eq!(median(&v), Some(2.5));
        assert_eq!(quantile(&v, 0.25), Some(1.75));
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[f64::NAN, 7.0]), Some(7.0));
    }

    #[test]
    fn rmse_of_three_four_is_its_quadratic_mean() {
        let r = rmse(&[3.0, 4.0]).unwrap();
        assert!((r - 12.5f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn csv_quotes_fields_with_commas() {
        let mut c = Csv::new(&["a", "b"]);
        c.row(vec!["x,y".into(), "1".into()]);
        assert_eq!(c.text, "a,b\n\"x,y\",1\n");
    }
}
